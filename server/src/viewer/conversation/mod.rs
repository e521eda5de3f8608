//! Everything one viewer's connection decides, with no socket, task or clock, in the
//! manner of `quinn-proto`: [`Conversation`] takes what arrived ([`Conversation::handle`]:
//! a datagram, a control message, the path's figures), makes the frame when its clock says
//! ([`Conversation::frame`], the heavy part handed back as a [`Job`] to run on any thread
//! and [`Conversation::finish`]), and says what to send ([`Conversation::poll_transmit`]),
//! what to tell the shell ([`Conversation::poll_event`]: the world's key events stay with
//! [`Conversation::handle`]'s answer) and when to call again
//! ([`Conversation::poll_timeout`]). The `net` shell owns only the sockets, the tasks and
//! the clock; the simulated network in the tests drives the same type, so no decision
//! exists twice.
//!
//! What it decides, in order of a frame:
//!
//! - **when**: one frame each period of the viewer's rate, missed periods skipped (a
//!   frame made late is never followed by a burst). The period's phase is the shell's
//!   ([`Conversation::new`]'s `origin`): every viewer of a rate on one grid lets one
//!   frame clock serve them all;
//! - **whom it follows**: a spectator the vehicle it asks for (if there); watching a
//!   recording, the first vehicle there once its own left, the camera parked where the last
//!   one was while none is ([`Out::Following`] tells the shell);
//! - **the frame**: the mailbox's events handed to the [`ViewerCore`] (a budget clamped
//!   here, once: by the server's limits, then by what the shell grants, its seat's memory),
//!   the frame begun in line, and anything heavy (the first frame, a rebuild, a key frame's
//!   coding) handed out as a [`Job`];
//! - **how it goes** ([`Transmit`]): a change frame that fits in one datagram as one (on a
//!   lossy path, [`LossMeter`], a small one twice, the copy [`REPEAT_AFTER`] later); any
//!   other frame on a stream of its own, a key frame at the highest priority. Latest frame
//!   wins: the change frame on a stream before it is reset unless acknowledged, and a key
//!   frame is reset only once it is no longer pending and not acknowledged
//!   ([`ViewerCore::pending_key`]);
//! - **its end** ([`End`]): a goodbye, the vehicle followed gone, a frame that cannot be
//!   made; and how long the path has been silent ([`Conversation::silent`]), from which a
//!   dropped driver's hold counts.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

use roam_protocol::messages::{self, ClientMessage, Hello, ReplayControl};

use super::{KeyCause, Made, Scene, ViewerCore, ViewerLimits};
use crate::Terrain;
use crate::sim::physics::VehicleState;
use crate::sim::world::VehicleId;
use crate::sim::world_core::{self, Snapshot};

mod parts;

pub use parts::{
    Control, KEY_BURST, KEY_RATE, KeyGate, LossMeter, MAX_REPLAY_CONTROLS, MAX_SHOWN, Mailbox,
    REPEAT_ABOVE_LOSS, REPEAT_MAX_BYTES, frame_message, welcome,
};

/// How long after a small frame its second copy goes, on a lossy path ([`LossMeter`]).
pub const REPEAT_AFTER: Duration = Duration::from_millis(4);

/// What reached the conversation.
#[derive(Debug)]
pub enum Event<'a> {
    /// A datagram from the viewer (a driver's keys).
    Datagram(&'a [u8]),
    /// A control message, in order.
    Control(ClientMessage),
    /// The path now: the largest datagram it takes (`None`: none), and the transport's
    /// running counts of packets lost and sent.
    Path {
        max_datagram: Option<usize>,
        lost: u64,
        sent: u64,
    },
    /// The shell could not send `frame`'s datagram after all (refused, or larger than the
    /// path now takes): it goes on a stream.
    Refused { frame: u64, bytes: Vec<u8> },
}

/// What [`Conversation::handle`] asks of the shell at once.
#[derive(Clone, Debug, PartialEq)]
pub enum Handled {
    /// A driver's key states for the world.
    World(world_core::Event),
    /// The viewer said goodbye (or sent what only starts a connection): it ends.
    Goodbye,
}

/// Why a conversation's frames ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum End {
    /// The vehicle it followed (or drove) is gone.
    VehicleLeft,
    /// The server could not make a frame (said to the viewer, never a panic).
    Failed(&'static str),
}

/// What the shell is told besides the bytes to send.
#[derive(Clone, Debug, PartialEq)]
pub enum Out {
    /// The frames follow another vehicle now (the viewer is told; colour streams around it).
    Following(VehicleId),
    /// A control of the watched recording, for the replay's shared clock.
    Replay(ReplayControl),
}

/// Bytes to send.
#[derive(Clone, Debug, PartialEq)]
pub enum Transmit {
    /// A frame (or its second copy) in one datagram.
    Datagram { frame: u64, bytes: Vec<u8> },
    /// A frame on a uni stream of its own, at `priority` (higher first); `frame` names it
    /// for a later [`Transmit::Reset`].
    Stream {
        frame: u64,
        priority: i32,
        bytes: Vec<u8>,
    },
    /// Abandon the stream of `frame`: stop sending and retransmitting it.
    Reset { frame: u64 },
}

/// A frame made: what the shell counts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sent {
    pub frame: u64,
    /// Why it is a key frame (`None`: a change frame).
    pub key: Option<KeyCause>,
    pub triangles: u32,
    /// The frame message's bytes.
    pub bytes: usize,
    /// Its cut stopped at the allowance ([`Conversation::set_allowance`]).
    pub short: bool,
}

/// What [`Conversation::frame`] did.
#[derive(Debug)]
pub enum Step {
    /// No frame now: not due, or a new driver's vehicle not yet in the world.
    Idle,
    /// A frame made; its transmits are queued.
    Sent(Sent),
    /// A frame whose heavy part is left: run the job (on any thread), then hand what it
    /// returns to [`Conversation::finish`]. No other frame is made meanwhile. (Boxed: it
    /// carries the viewer's core, and comes a few times a second at most.)
    Heavy(Box<Job>),
    /// The frames end.
    End(End),
}

/// The heavy part of a frame, away from its conversation: the viewer's core with it.
pub struct Job {
    core: ViewerCore,
    /// A first frame is made whole, for where the vehicle is when the job runs.
    first: bool,
    vehicle: VehicleId,
    /// Where the camera is if the vehicle is not in the newest snapshot (a replay's).
    state: VehicleState,
    replay: bool,
    snapshot: Arc<Snapshot>,
}

/// What a [`Job`] made.
pub struct Finished {
    core: ViewerCore,
    made: Option<(Made, Arc<Snapshot>)>,
}

impl std::fmt::Debug for Job {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Job")
            .field("first", &self.first)
            .field("vehicle", &self.vehicle)
            .finish_non_exhaustive()
    }
}

impl Job {
    /// Whether this is the viewer's first frame (its makers wait behind the others').
    pub fn first(&self) -> bool {
        self.first
    }

    /// The budget the frame is made to.
    pub fn budget(&self) -> u32 {
        self.core.budget()
    }

    /// Makes the frame. `newest` is the world's newest snapshot when the job runs: a first
    /// frame that waited behind many joins is made for where its vehicle is then, not
    /// where it was when begun (else the next frame rebuilt, and was a key frame again).
    pub fn run(mut self, scene: &Scene, newest: impl FnOnce() -> Arc<Snapshot>) -> Finished {
        if !self.first {
            let made = self.core.finish_frame(scene);
            return Finished {
                core: self.core,
                made: Some((made, self.snapshot)),
            };
        }
        let snap = newest();
        let state = match snap.vehicles.iter().find(|v| v.id == self.vehicle) {
            Some(v) => v.state,
            None if self.replay => self.state,
            None => {
                return Finished {
                    core: self.core,
                    made: None,
                };
            }
        };
        let made = self.core.make_frame(scene, &state);
        Finished {
            core: self.core,
            made: Some((made, snap)),
        }
    }
}

/// One viewer's connection, past its hello.
pub struct Conversation {
    /// Lent to a [`Job`] while one runs.
    core: Option<ViewerCore>,
    limits: ViewerLimits,
    mailbox: Mailbox,
    gate: KeyGate,
    vehicle: VehicleId,
    driver: bool,
    /// Watching a recording: controls go to the replay, and the camera parks.
    replay: bool,
    parked: VehicleState,
    seen: bool,
    period: Duration,
    /// The frame clock's phase: frames after the first are due at `origin + k·period`.
    origin: Instant,
    next_frame: Instant,
    /// The newest frame made (they are numbered from 0).
    newest: Option<u64>,
    /// The change frame on a stream, and the key frame on one (kept apart: it is never
    /// abandoned while it is pending).
    in_flight: Option<u64>,
    key_in_flight: Option<u64>,
    loss: LossMeter,
    max_datagram: Option<usize>,
    heard: Option<Instant>,
    transmits: VecDeque<Transmit>,
    /// Second copies of small frames, each when due.
    repeats: VecDeque<(Instant, u64, Vec<u8>)>,
    events: VecDeque<Out>,
    /// The most changes a frame's cut makes ([`ViewerCore::set_allowance`]).
    allowance: u32,
    /// When the core last came back from a [`Job`].
    back: Option<Instant>,
    /// Whether the last frame due was passed over ([`Conversation::pass_over`]); cleared
    /// when [`Conversation::frame`] runs with a frame due.
    passed_over: bool,
}

/// Who a conversation serves.
#[derive(Clone, Copy, Debug)]
pub struct Role {
    /// The vehicle it drives or first follows.
    pub vehicle: VehicleId,
    pub driver: bool,
    /// Watching a recording.
    pub replay: bool,
}

impl Conversation {
    /// The conversation with a viewer that said `hello`, as `role`, on `terrain` (heights
    /// multiples of `height_step`), served within `limits`. Its first frame is due at
    /// `now`, the others at `origin + k·period` (one origin for every viewer of a server
    /// lets one frame clock serve them all).
    pub fn new(
        terrain: &Terrain,
        height_step: u16,
        hello: &Hello,
        limits: ViewerLimits,
        role: Role,
        (now, origin): (Instant, Instant),
    ) -> Conversation {
        let period = Conversation::period(hello, limits);
        let core = ViewerCore::for_hello(terrain, height_step, hello, limits);
        Conversation {
            core: Some(core),
            limits,
            mailbox: Mailbox::default(),
            gate: KeyGate::new(role.vehicle),
            vehicle: role.vehicle,
            driver: role.driver,
            replay: role.replay,
            parked: crate::sim::world::start_state(terrain, 0),
            seen: false,
            period,
            next_frame: now,
            origin,
            newest: None,
            in_flight: None,
            key_in_flight: None,
            loss: LossMeter::default(),
            max_datagram: None,
            heard: None,
            transmits: VecDeque::new(),
            repeats: VecDeque::new(),
            events: VecDeque::new(),
            allowance: u32::MAX,
            passed_over: false,
            back: None,
        }
    }

    /// The most changes the frames' cuts make from now on, once within their budget
    /// (`u32::MAX`: none): what a loaded server allows ([`crate::viewer::Allowance`]).
    pub fn set_allowance(&mut self, changes: u32) {
        self.allowance = changes;
    }

    /// The time between two frames of a viewer that said `hello`, served within `limits`.
    pub fn period(hello: &Hello, limits: ViewerLimits) -> Duration {
        let rate = ViewerCore::frame_rate(hello, limits);
        Duration::from_secs_f64(1.0 / f64::from(rate))
    }

    /// Takes what arrived at `now`.
    pub fn handle(&mut self, now: Instant, event: Event) -> Option<Handled> {
        match event {
            Event::Datagram(bytes) => {
                self.heard = Some(now);
                let (keys, acked) = self.gate.admit(bytes, now)?;
                if let Some(frame) = acked {
                    self.mailbox.ack(frame);
                }
                self.driver.then_some(Handled::World(keys))
            }
            Event::Control(msg) => {
                (self.mailbox.push(msg) == Control::End).then_some(Handled::Goodbye)
            }
            Event::Path {
                max_datagram,
                lost,
                sent,
            } => {
                self.max_datagram = max_datagram;
                self.loss.update(lost, sent);
                None
            }
            // Only the newest frame, once: a copy refused, or an older frame, is let go
            // (latest frame wins).
            Event::Refused { frame, bytes } => {
                if self.newest == Some(frame) && self.in_flight != Some(frame) {
                    self.on_stream(frame, false, bytes);
                }
                None
            }
        }
    }

    /// The vehicle the frames follow now.
    pub fn vehicle(&self) -> VehicleId {
        self.vehicle
    }

    pub fn driver(&self) -> bool {
        self.driver
    }

    /// Frames made.
    pub fn frames(&self) -> u64 {
        self.newest.map_or(0, |f| f + 1)
    }

    /// The viewer's core, unless a [`Job`] has it.
    pub fn core(&self) -> Option<&ViewerCore> {
        self.core.as_ref()
    }

    /// How long the path had been silent at `now` (since the last datagram; since `since`,
    /// the connection's start, if none came): a dropped driver's hold counts from then.
    pub fn silent(&self, now: Instant, since: Instant) -> Duration {
        now.saturating_duration_since(self.heard.unwrap_or(since))
    }

    /// When to call [`Self::frame`] or [`Self::poll_transmit`] next; `None` while nothing
    /// will be due before a [`Job`] comes back.
    pub fn poll_timeout(&self) -> Option<Instant> {
        let frame = self.core.is_some().then_some(self.next_frame);
        let repeat = self.repeats.front().map(|r| r.0);
        match (frame, repeat) {
            (Some(f), Some(r)) => Some(f.min(r)),
            (f, r) => f.or(r),
        }
    }

    /// When the next frame is due.
    pub fn due_at(&self) -> Instant {
        self.next_frame
    }

    /// How late a frame started at `started` is for want of the core, for the clock's
    /// [`crate::viewer::Allowance`]: from when it was due, or from when the core came back
    /// from a [`Job`] if later (a frame cannot start while its core is away); `None` for a
    /// first frame (its wait for its turn is the clock's own doing).
    pub fn late(&self, started: Instant) -> Option<Duration> {
        let from = self
            .back
            .map_or(self.next_frame, |b| b.max(self.next_frame));
        (self.newest.is_some()).then(|| started.saturating_duration_since(from))
    }

    /// Whether a frame is due at `now` (and the core is here to make it).
    pub fn frame_due(&self, now: Instant) -> bool {
        self.core.is_some() && now >= self.next_frame
    }

    /// Passes over the frame due at `now`, if any and if the last one due was made: the
    /// next is due on the grid after `now`. For a clock short of core while viewers join
    /// (their first frames wait): a served viewer then gets every other frame, never two
    /// missed in a row, and never its first; a viewer whose period is over
    /// [`PASS_OVER_PERIOD`] is never passed over. True when it passed one over.
    pub fn pass_over(&mut self, now: Instant) -> bool {
        if self.period > PASS_OVER_PERIOD
            || !self.frame_due(now)
            || self.newest.is_none()
            || self.passed_over
        {
            return false;
        }
        self.next_frame = next_on_grid(now, self.origin, self.period);
        self.passed_over = true;
        true
    }

    /// The next thing to send, by `now`.
    pub fn poll_transmit(&mut self, now: Instant) -> Option<Transmit> {
        if let Some(t) = self.transmits.pop_front() {
            return Some(t);
        }
        if self.repeats.front().is_some_and(|r| r.0 <= now) {
            let (_, frame, bytes) = self.repeats.pop_front()?;
            return Some(Transmit::Datagram { frame, bytes });
        }
        None
    }

    /// The next thing to tell the shell.
    pub fn poll_event(&mut self) -> Option<Out> {
        self.events.pop_front()
    }

    /// The frame due at `now`, if one is, of `snapshot`'s world. `grant` says how large a
    /// budget the viewer may have (its seat's memory), given one within the limits.
    pub fn frame(
        &mut self,
        now: Instant,
        scene: &Scene,
        snapshot: &Arc<Snapshot>,
        grant: &mut dyn FnMut(u32) -> u32,
    ) -> Step {
        if !self.frame_due(now) {
            return Step::Idle;
        }
        self.next_frame = next_on_grid(now, self.origin, self.period);
        self.passed_over = false;
        let asked = self.mailbox.take_follow();
        for c in self.mailbox.take_replay() {
            if self.replay {
                self.events.push_back(Out::Replay(c));
            }
        }
        let there = |id: VehicleId| snapshot.vehicles.iter().any(|v| v.id == id);
        // A spectator follows the vehicle it asks for, if there; a replay's spectator whose
        // vehicle left follows the first there.
        let switch = match asked {
            Some(a) if !self.driver && a != self.vehicle && there(a) => Some(a),
            _ if self.replay && !there(self.vehicle) => snapshot.vehicles.first().map(|v| v.id),
            _ => None,
        };
        if let Some(to) = switch {
            self.vehicle = to;
            self.events.push_back(Out::Following(to));
        }
        let state = match snapshot.vehicles.iter().find(|v| v.id == self.vehicle) {
            Some(v) => v.state,
            None if self.replay => self.parked,
            // A new driver's vehicle appears with the next tick; a spectator's was there
            // when it joined.
            None if self.seen || !self.driver => return Step::End(End::VehicleLeft),
            None => return Step::Idle,
        };
        self.parked = state;
        self.seen = true;
        let mut core = self.core.take().expect("frame_due checked it is here");
        for event in self.mailbox.drain() {
            core.handle(match event {
                // The one place a budget is clamped: the server's limits, then the seat.
                super::Event::Budget(asked) => {
                    super::Event::Budget(grant(self.limits.budget(asked)))
                }
                other => other,
            });
        }
        let first = self.newest.is_none();
        core.set_allowance(self.allowance);
        let inline = if first {
            None
        } else {
            core.begin_frame(scene, &state)
        };
        match inline {
            Some(made) => {
                self.core = Some(core);
                self.sent(now, scene.terrain, made, snapshot)
            }
            None => Step::Heavy(Box::new(Job {
                core,
                first,
                vehicle: self.vehicle,
                state,
                replay: self.replay,
                snapshot: snapshot.clone(),
            })),
        }
    }

    /// Takes back what a [`Job`] made, at `now`, and queues the frame.
    pub fn finish(&mut self, now: Instant, terrain: &Terrain, done: Finished) -> Step {
        self.core = Some(done.core);
        self.back = Some(now);
        match done.made {
            Some((made, snap)) => self.sent(now, terrain, made, &snap),
            None => Step::End(End::VehicleLeft),
        }
    }

    /// Queues `made`, showing `snapshot`'s world.
    fn sent(&mut self, now: Instant, terrain: &Terrain, made: Made, snapshot: &Snapshot) -> Step {
        let core = self
            .core
            .as_ref()
            .expect("the core is back before a frame is sent");
        let (acked, pending_key) = (core.acked(), core.pending_key());
        let short = made.mode == crate::tessellate::Mode::Update && core.cut().stats().short;
        let (frame, key) = (made.frame, made.base.is_none());
        let (cause, triangles) = (made.key, made.triangles);
        let msg = frame_message(terrain, snapshot, made, self.vehicle, self.driver);
        let mut bytes = Vec::new();
        if messages::encode(&msg, &mut bytes).is_err() {
            return Step::End(End::Failed("a frame over the message limit"));
        }
        let sent = Sent {
            frame,
            key: cause,
            triangles,
            bytes: bytes.len(),
            short,
        };
        self.newest = Some(frame);
        // Latest frame wins: the change frame on a stream is reset unless the viewer has
        // acknowledged it; the key frame goes on until it is no longer pending.
        let unacked = |f: u64| acked.is_none_or(|a| a < f);
        let key_done = self.key_in_flight.take_if(|k| pending_key != Some(*k));
        for f in key_done.into_iter().chain(self.in_flight.take()) {
            if unacked(f) {
                self.transmits.push_back(Transmit::Reset { frame: f });
            }
        }
        // A change frame that fits in one datagram goes as one: a lost one is never a base.
        if !key && self.max_datagram.is_some_and(|max| bytes.len() <= max) {
            if self.loss.repeat(bytes.len()) {
                self.repeats
                    .push_back((now + REPEAT_AFTER, frame, bytes.clone()));
            }
            self.transmits
                .push_back(Transmit::Datagram { frame, bytes });
        } else {
            self.on_stream(frame, key, bytes);
        }
        Step::Sent(sent)
    }

    /// `frame` goes on a stream of its own: newer frames first, a key frame before all.
    fn on_stream(&mut self, frame: u64, key: bool, bytes: Vec<u8>) {
        let priority = if key { i32::MAX } else { frame as i32 };
        self.transmits.push_back(Transmit::Stream {
            frame,
            priority,
            bytes,
        });
        if key {
            self.key_in_flight = Some(frame);
        } else {
            self.in_flight = Some(frame);
        }
    }
}

/// The longest period whose frames [`Conversation::pass_over`] may pass over: a viewer
/// at 30 frames a second or fewer would see a gap of 67 ms and more.
const PASS_OVER_PERIOD: Duration = Duration::from_millis(34);

/// The first instant of `origin + k·period` after `now` (`origin` itself if later).
fn next_on_grid(now: Instant, origin: Instant, period: Duration) -> Instant {
    if now < origin {
        return origin;
    }
    let p = period.as_nanos().max(1);
    let k = now.saturating_duration_since(origin).as_nanos() / p + 1;
    origin + Duration::from_nanos(u64::try_from(k * p).unwrap_or(u64::MAX))
}

#[cfg(test)]
mod tests;
