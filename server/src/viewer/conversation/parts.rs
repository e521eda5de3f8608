//! The pieces a [`Conversation`](super::Conversation) is made of, each its own decision:
//! the control messages coalesced between frames ([`Mailbox`]), the key datagrams admitted
//! and turned into world events ([`KeyGate`]), the welcome ([`welcome`]), the frame message
//! for a snapshot ([`frame_message`]), and whether small frames go twice ([`LossMeter`]).

use std::time::Instant;

use roam_protocol::messages::{
    self, ClientMessage, ColorLayout, Frame, KeyDatagram, ReplayControl, VERSION, VehicleView,
    ViewChange, Welcome,
};

use crate::Terrain;
use crate::sim::physics::altitude;
use crate::sim::world::VehicleId;
use crate::sim::world_core::{self, Snapshot};
use crate::viewer::{Event, Made, ViewerLimits};

/// The viewer's control messages since the last frame, coalesced (the newest budget and
/// view, the highest acknowledgement, whether a key frame was asked for), so a viewer
/// sending faster than its frames grows nothing.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mailbox {
    budget: Option<u32>,
    acked: Option<u64>,
    key_frame: bool,
    view: Option<ViewChange>,
    /// The newest vehicle a spectator asked to follow.
    follow: Option<u16>,
    /// A watched recording's controls, in order, at most [`MAX_REPLAY_CONTROLS`] (the
    /// newest).
    replay: Vec<ReplayControl>,
}

/// Replay controls kept between two frames: a viewer pressing keys faster than its frames
/// come loses its oldest.
pub const MAX_REPLAY_CONTROLS: usize = 8;

/// What a control message means for the connection.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Control {
    /// Taken; more may come.
    Continue,
    /// The viewer said goodbye, or sent what only starts a connection: it ends.
    End,
}

impl Mailbox {
    /// Takes one control message.
    pub fn push(&mut self, msg: ClientMessage) -> Control {
        match msg {
            ClientMessage::Budget(b) => self.budget = Some(b),
            ClientMessage::Ack { frame } => self.ack(frame),
            ClientMessage::KeyFrame => {
                self.key_frame = true;
                self.acked = None;
            }
            ClientMessage::View(v) => self.view = Some(v),
            ClientMessage::Follow(v) => self.follow = Some(v),
            ClientMessage::Replay(c) => {
                if self.replay.len() == MAX_REPLAY_CONTROLS {
                    self.replay.remove(0);
                }
                self.replay.push(c);
            }
            ClientMessage::Bye(_) | ClientMessage::Hello(_) => return Control::End,
        }
        Control::Continue
    }

    /// The vehicle a spectator asked to follow since the last call (the newest).
    pub fn take_follow(&mut self) -> Option<u16> {
        self.follow.take()
    }

    /// The replay controls since the last call, oldest first.
    pub fn take_replay(&mut self) -> Vec<ReplayControl> {
        std::mem::take(&mut self.replay)
    }

    /// The viewer decoded `frame` (the highest acknowledgement wins).
    pub fn ack(&mut self, frame: u64) {
        self.acked = Some(self.acked.map_or(frame, |a| a.max(frame)));
    }

    /// The events for the core, emptying the mailbox: the budget and view first (they may
    /// rebuild the cut), then a key-frame request, then the acknowledgement.
    pub fn drain(&mut self) -> impl Iterator<Item = Event> + use<> {
        let (follow, replay) = (self.follow.take(), std::mem::take(&mut self.replay));
        let m = std::mem::take(self);
        (self.follow, self.replay) = (follow, replay);
        [
            m.budget.map(Event::Budget),
            m.view.map(Event::View),
            m.key_frame.then_some(Event::KeyFrame),
            m.acked.map(Event::Acked),
        ]
        .into_iter()
        .flatten()
    }
}

/// Key datagrams a driver may send per second, and in a burst (a viewer sends 100 a
/// second).
pub const KEY_RATE: f64 = 250.0;
pub const KEY_BURST: f64 = 50.0;

/// One driver's key datagrams: at most [`KEY_RATE`] a second (a burst of [`KEY_BURST`]) are
/// taken, so one flooding viewer cannot crowd the others out of the world's ticks;
/// anything that is not a key datagram is ignored.
#[derive(Clone, Debug)]
pub struct KeyGate {
    vehicle: VehicleId,
    tokens: f64,
    refilled: Option<Instant>,
}

impl KeyGate {
    pub fn new(vehicle: VehicleId) -> KeyGate {
        KeyGate {
            vehicle,
            tokens: KEY_BURST,
            refilled: None,
        }
    }

    /// A datagram arrived at `now`: if it is taken, the world's event for it and the frame
    /// it acknowledges ([`KeyDatagram::acked`]).
    pub fn admit(
        &mut self,
        bytes: &[u8],
        now: Instant,
    ) -> Option<(world_core::Event, Option<u64>)> {
        let since = self
            .refilled
            .map_or(0.0, |t| now.saturating_duration_since(t).as_secs_f64());
        self.tokens = (self.tokens + since * KEY_RATE).min(KEY_BURST);
        self.refilled = Some(now);
        if self.tokens < 1.0 {
            return None;
        }
        self.tokens -= 1.0;
        let d = messages::decode::<KeyDatagram>(bytes).ok()?;
        let keys = world_core::Event::Keys {
            vehicle: self.vehicle,
            states: d.states,
        };
        Some((keys, d.acked))
    }
}

/// The welcome for a viewer of `vehicle` on `terrain` at world tick `tick`, whose colour
/// map streams as tiles of `color`, served within `limits`. A driver's `ticket` and
/// whether it was resumed are the caller's to add.
pub fn welcome(
    terrain: &Terrain,
    vehicle: VehicleId,
    tick: u64,
    color: ColorLayout,
    limits: ViewerLimits,
) -> Welcome {
    let m = &terrain.map;
    let limits = limits.clamped();
    Welcome {
        version: VERSION,
        levels: terrain.heights.levels() as u8,
        h_scale: m.h_scale,
        v_scale: m.v_scale,
        sun_dir: m.sun_dir.map(|v| v as f32),
        sun_color: m.sun_color,
        fog_density: m.fog_density as f32,
        fog_color: m.fog_color,
        water_level: m.water_level.map(|v| v as f32),
        vehicle,
        color,
        tick,
        ticket: None,
        resumed: false,
        max_budget: limits.max_budget,
        max_fps: limits.max_fps,
    }
}

/// The most vehicles a frame shows: the followed one and those nearest it. Each takes 42
/// bytes, so a frame showing every vehicle grew with the drivers: at 50 a change frame
/// was some 2.4 kB, past a datagram, and every frame went on a stream of its own (opened,
/// written, reset when superseded); a server's bytes grew as the square of its drivers.
/// Sixteen (672 bytes) leave a change frame room for its payload in one datagram. With no
/// more vehicles than this, a frame shows them all, as before.
pub const MAX_SHOWN: usize = 16;

/// The frame message for `made`, showing `snapshot`'s world: the vehicle followed and the
/// others nearest it, at most [`MAX_SHOWN`] (in the snapshot's order), as the viewer sees
/// them, and (for a driver) the newest key state of its own the world had applied.
pub fn frame_message(
    terrain: &Terrain,
    snapshot: &Snapshot,
    made: Made,
    vehicle: VehicleId,
    driver: bool,
) -> Frame {
    let all = &snapshot.vehicles;
    let view = |v: &crate::sim::world::Vehicle| VehicleView {
        id: v.id,
        x: v.state.x,
        z: v.state.z,
        y: altitude(terrain, v.state.x, v.state.z),
        speed: v.state.speed,
        heading: v.state.heading,
    };
    let vehicles = match all.iter().find(|v| v.id == vehicle) {
        Some(me) if all.len() > MAX_SHOWN => {
            // The nearest, the followed one first (at distance 0, then by id: a tie is
            // decided the same way on every run).
            // Each key computed once, not at each comparison: with 100 viewers in step the
            // selection was 2 % of the server's time (`perf`, 2026-12-08), a frame per
            // viewer over every vehicle.
            let mut keyed: Vec<_> = all
                .iter()
                .enumerate()
                .map(|(i, v)| {
                    let (dx, dz) = (v.state.x - me.state.x, v.state.z - me.state.z);
                    (v.id != vehicle, dx * dx + dz * dz, v.id, i)
                })
                .collect();
            // A total order (`total_cmp`): a position that is not a number cannot panic the
            // selection.
            keyed.select_nth_unstable_by(MAX_SHOWN - 1, |a, b| {
                (a.0.cmp(&b.0))
                    .then(a.1.total_cmp(&b.1))
                    .then(a.2.cmp(&b.2))
            });
            let mut order: Vec<usize> = keyed[..MAX_SHOWN].iter().map(|k| k.3).collect();
            order.sort_unstable();
            order.into_iter().map(|i| view(&all[i])).collect()
        }
        // All of them, or (the followed one not there: a replay's parked camera) the first.
        _ => all.iter().take(MAX_SHOWN).map(view).collect(),
    };
    Frame {
        frame: made.frame,
        base: made.base,
        tick: snapshot.tick,
        vehicles,
        input_seq: if driver {
            snapshot.applied_by(vehicle)
        } else {
            None
        },
        mesh: made.payload,
    }
}

/// The share of packets lost over which small frames are sent twice.
pub const REPEAT_ABOVE_LOSS: f64 = 0.01;
/// The largest frame sent twice: change frames, tens to hundreds of bytes; never a key frame.
pub const REPEAT_MAX_BYTES: usize = 600;
/// Packets a loss measurement spans before it counts.
const LOSS_WINDOW: u64 = 200;

/// Whether to send each small frame twice, a few milliseconds apart: on a path that loses
/// packets at random (Wi-Fi, a long one), a frame lost is a frame the viewer never shows,
/// and at 5 % loss that caps it at 57 frames of 60. A second copy in a packet of its own
/// makes a loss cost a frame only when both go (0.25 % at 5 %). It doubles a few hundred
/// bytes a frame, and only while the connection measures loss above
/// [`REPEAT_ABOVE_LOSS`]; a clean path sends each frame once.
#[derive(Clone, Debug, Default)]
pub struct LossMeter {
    /// The transport's counters at the start of the window.
    start: Option<(u64, u64)>,
    /// The loss measured over the last whole window.
    rate: f64,
}

impl LossMeter {
    /// The transport's running counts of packets `lost` and `sent`.
    pub fn update(&mut self, lost: u64, sent: u64) {
        let (lost0, sent0) = *self.start.get_or_insert((lost, sent));
        let sent_now = sent.saturating_sub(sent0);
        if sent_now >= LOSS_WINDOW {
            self.rate = lost.saturating_sub(lost0) as f64 / sent_now as f64;
            self.start = Some((lost, sent));
        }
    }

    /// The loss measured over the last whole window.
    pub fn rate(&self) -> f64 {
        self.rate
    }

    /// Whether a frame of `len` bytes should be sent twice.
    pub fn repeat(&self, len: usize) -> bool {
        self.rate > REPEAT_ABOVE_LOSS && len <= REPEAT_MAX_BYTES
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_frames_are_repeated_only_while_the_path_loses() {
        let mut m = LossMeter::default();
        m.update(0, 0);
        assert!(!m.repeat(100), "nothing measured yet");
        m.update(10, 199);
        assert!(!m.repeat(100), "a window is 200 packets");
        m.update(10, 200);
        assert!((m.rate() - 0.05).abs() < 1e-12);
        assert!(m.repeat(100) && m.repeat(REPEAT_MAX_BYTES));
        assert!(!m.repeat(REPEAT_MAX_BYTES + 1), "never a large frame");
        m.update(11, 400);
        assert!(!m.repeat(100), "0.5 % over the next window: once again");
        // Counters that go backwards (never from quinn) do not panic.
        m.update(0, 0);
        assert!(!m.repeat(100));
    }
}
