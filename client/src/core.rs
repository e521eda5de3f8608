//! The viewer's connection logic, with no socket, task or clock (as `quinn-proto` is to
//! `quinn`): the newest frame waiting, the bases frames are coded against, decoding,
//! acknowledgements and key-frame requests, the triangle budget, and the keys (the latch,
//! the numbered states and the history each datagram repeats). Time comes in as a
//! parameter. `session.rs`, `connection.rs` and `quic.rs` are the I/O around it (QUIC,
//! tasks, the clock); the window, the
//! headless viewer and `--bench` all take frames through it, and the simulated network
//! in the tests drives this core directly.
//!
//! What leaves the core: control messages ([`ClientCore::poll_control`], for the control
//! stream, in order) and key datagrams ([`KeyCore::key_datagram`], one per physics step).
//!
//! **Frames and bases.** The newest frame offered waits to be taken (an older one is
//! superseded), and so, apart, does the newest key frame offered: the server sends a key
//! frame reliably (on a stream it does not abandon while the key frame is pending) and codes
//! the frames after it against it before this viewer has it, so the key frame may arrive
//! after them, and a change frame offered meanwhile must not push it out. [`ClientCore::take`]
//! takes the key frame first when the waiting frame's base is not decoded yet. A frame coded
//! against a base newer than the newest frame taken (a key frame still on its way) is not an
//! error: it is passed over ([`Taken::Nothing`]) while the base may still come, up to
//! [`AWAIT_BASE`] frames in a row, after which a key frame is asked for. A frame coded
//! against a base this viewer had and no longer has (or never decoded) is dropped and a key
//! frame asked for at once.
//!
//! **Decoding follows the cut** (issue 22): the bases are a [`Follower`] (the current cut
//! in a map sized by the cut, and the diamonds each recent frame toggled), and the mesh a
//! [`LiveMesh`] (a slot of triangles per split diamond), so a frame costs what it changed.
//! Before, each base was a bitset over the grid (128 MiB at 32769²), copied, counted and
//! walked every frame: 8.6 frames/s taken of 60 at 32769², 52 at 16385².
//!
//! The core has two halves, [`ClientCore`] (frames) and [`KeyCore`] (keys), so the I/O can
//! lock them apart: a key state must leave every 10 ms even while a frame is being
//! decoded. With one lock, a decode preempted on a loaded machine held the key sender past
//! the server's one tick of slack, and the exact drive over the network diverged (seen in
//! `tests/tests/it/e2e.rs` with the CPU saturated).
//!
//! **Frame numbers are checked** ([`Broken`]): a server numbers the frames of a connection
//! from 0, one more per frame sent, so a frame more than [`MAX_FRAME_JUMP`] past the newest
//! one offered (or past [`MAX_FRAME_NUMBER`]) is not a frame this server could have sent in
//! order: it would make every later frame look old (latest wins) and wedge the viewer. It
//! is dropped, never taken into account, and [`ClientCore::take`] reports it as an error,
//! as it does a frame coded against a base that is not before it, and a frame showing an
//! older tick than the frame taken before it (unless the server said it serves a recording
//! being watched, whose clock is sought back: [`ClientCore::set_replay`]). The session ends on such an error (the
//! server is broken or hostile); the core itself goes on with the frames after it.
//!
//! **Across connections**: a [`ClientCore`] lives for one connection (frame numbers start
//! again at 0 on the next); the [`KeyCore`] lives for the session (key states keep their
//! numbering across a reconnection, so a resumed vehicle's queue takes them as new), and so
//! do the [`Gaps`], which count reconnections and measure the time without frames.

use std::collections::VecDeque;

/// More ticks than this between two frames of a watched recording is a seek (8× at 60
/// frames a second moves 14 a frame).
const SOUGHT_TICKS: u64 = 100;
use std::time::Duration;

use web_time::Instant;

use roam_protocol::keys::{KeyLatch, KeyStep, Keys};
use roam_protocol::messages::{
    self, ClientMessage, Frame, KeyDatagram, KeyState, VehicleView, ViewChange, Welcome,
};
use roam_protocol::{DiamondMap, Follower, Grid, LiveMesh, mesh};

use crate::render::{Morph, MorphView, Scene, TerrainVertices};

/// Decoded frames kept as bases: the server codes against the newest one acknowledged, or
/// its newest key frame while that is on its way, and never against a frame more than its
/// logs' length (`roam_server::viewer::LOGS`, at most this many) before the frame it makes;
/// frames are decoded in order, so such a base is never one dropped here. A base is not a
/// copy of its cut but the diamonds each frame since toggled ([`Follower`]): on every grid,
/// the bases together hold what the frames since the oldest changed.
pub const BASES: usize = 32;

/// Frames in a row coded against a base newer than the newest frame taken (a key frame on
/// its way) that the viewer passes over before it asks for a key frame: a second at 60 Hz.
pub const AWAIT_BASE: u32 = 60;

/// Key changes awaiting the frame that shows them applied (a spectator's never are).
const MAX_PENDING: usize = 1024;

/// How far past the newest frame offered (or past 0, before any) a frame's number may be:
/// the frames between were lost or superseded, and a connection that loses 65,536 frames
/// in a row (18 minutes at 60 Hz) has long timed out.
pub const MAX_FRAME_JUMP: u64 = 1 << 16;
/// Frame numbers from here on are refused whatever came before (the largest integer a
/// double holds exactly: no server gets there at any frame rate).
pub const MAX_FRAME_NUMBER: u64 = 1 << 53;

/// The largest frame message read: a key frame at the largest budget is under 2 MiB, and
/// 16 streams of this much bound what a server can make the viewer hold.
pub const MAX_FRAME: usize = 8 << 20;

/// A frame taken.
#[derive(Clone, Debug)]
pub struct Received {
    pub frame: u64,
    pub tick: u64,
    pub vehicles: Vec<VehicleView>,
    /// The newest key state the world had applied.
    pub input_seq: Option<u32>,
    /// Bytes on the wire (the frame message).
    pub wire_bytes: usize,
    /// Triangles decoded into [`ClientCore::mesh`] (0 when not decoded).
    pub triangles: usize,
    /// When its bytes arrived.
    pub arrived: Instant,
    /// Decoding it (with emitting the mesh), seconds, as the I/O measured it (0 here).
    pub decode_s: f64,
    /// Key change → this frame showing it applied, milliseconds, for each change it is the
    /// first to show ([`KeyCore::applied`] fills it in).
    pub latencies_ms: Vec<f64>,
}

/// What [`ClientCore::take`] found.
#[derive(Clone, Debug)]
pub enum Taken {
    /// Nothing newer than the last frame taken; or a frame coded against a base that has
    /// not arrived yet (a key frame on its way), passed over.
    Nothing,
    /// A frame, decoded (unless asked not to) and acknowledged.
    Frame(Received),
    /// A frame that could not be decoded (bytes that are not a frame, a base this viewer
    /// never had, a payload that fails its checks): a key frame has been asked for.
    Dropped(String),
}

/// A frame the server could not have sent: the server is broken (or hostile). Reported by
/// [`ClientCore::take`]; the frame is not taken.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum Broken {
    /// The mesh of a frame disagrees with its own header.
    #[error("frame {frame}: {emitted} triangles emitted, the header says {header}")]
    Inconsistent {
        frame: u64,
        emitted: usize,
        header: u32,
    },
    /// A frame number too far ahead of the newest frame offered (`None`: before any).
    #[error(
        "frame {frame} is {} frames past {}: frame numbers rise by one per frame \
         sent, and at most {MAX_FRAME_JUMP} may be skipped (below {MAX_FRAME_NUMBER} in all)",
        .frame.saturating_sub(.newest.unwrap_or(0)),
        .newest.map_or("the start (0)".to_string(), |n| format!("the newest frame, {n}"))
    )]
    FrameAhead { frame: u64, newest: Option<u64> },
    /// A frame coded against a frame that is not before it.
    #[error("frame {frame} is coded against frame {base}, which is not before it")]
    BaseAhead { frame: u64, base: u64 },
    /// A frame showing an older tick than the frame taken before it.
    #[error("frame {frame} shows tick {tick}, before tick {newest_tick} of frame {newest}")]
    TickBackwards {
        frame: u64,
        tick: u64,
        newest: u64,
        newest_tick: u64,
    },
}

/// The frame-number checks of a frame offered when the newest offered is `newest`.
fn check_numbers(frame: &Frame, newest: Option<u64>) -> Result<(), Broken> {
    let reference = newest.unwrap_or(0);
    if frame.frame >= MAX_FRAME_NUMBER || frame.frame > reference.saturating_add(MAX_FRAME_JUMP) {
        return Err(Broken::FrameAhead {
            frame: frame.frame,
            newest,
        });
    }
    match frame.base {
        Some(base) if base >= frame.frame => Err(Broken::BaseAhead {
            frame: frame.frame,
            base,
        }),
        _ => Ok(()),
    }
}

/// What a session's reconnections cost, kept across its connections: how many there were,
/// how many got their vehicle back, and the time without frames. Instants come in (the
/// arrival of each frame taken, the moment a loss is noticed); nothing here reads a clock.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Gaps {
    /// Connections made again after one was lost.
    pub reconnects: u32,
    /// Of those, the drivers' that got their vehicle back.
    pub resumed: u32,
    /// When the newest frame taken arrived.
    pub last_frame: Option<Instant>,
    /// While reconnecting: when the loss was noticed.
    pub lost_at: Option<Instant>,
    /// The longest time between two frames taken so far.
    longest: Duration,
}

impl Gaps {
    /// A frame taken, which arrived at `arrived`.
    pub fn frame(&mut self, arrived: Instant) {
        if let Some(last) = self.last_frame {
            self.longest = self.longest.max(arrived.saturating_duration_since(last));
        }
        self.last_frame = Some(self.last_frame.map_or(arrived, |l| l.max(arrived)));
    }

    /// The connection was found lost at `now`.
    pub fn lost(&mut self, now: Instant) {
        self.lost_at.get_or_insert(now);
    }

    /// A new connection is up; `resumed`: the server gave the vehicle back.
    pub fn reconnected(&mut self, resumed: bool) {
        self.reconnects += 1;
        self.resumed += u32::from(resumed);
        self.lost_at = None;
    }

    /// While reconnecting, the time without frames at `now`: since the last frame (or since
    /// the loss, when none came).
    pub fn current(&self, now: Instant) -> Option<Duration> {
        let lost = self.lost_at?;
        Some(now.saturating_duration_since(self.last_frame.unwrap_or(lost).min(lost)))
    }

    /// The longest time between two frames, the one going on included.
    pub fn longest(&self, now: Instant) -> Duration {
        self.longest.max(self.current(now).unwrap_or_default())
    }
}

/// A frame offered: the frame, its size on the wire and when it arrived.
type Offered = (Frame, usize, Instant);

/// One joined viewer's state.
pub struct ClientCore {
    grid: Grid,
    /// The current cut and the bases the server may code against.
    cut: Follower,
    /// The current cut's triangles, slot by diamond.
    live: LiveMesh,
    /// The newest frame taken.
    newest: Option<u64>,
    /// The newest frame offered and not yet taken, its size on the wire and arrival.
    waiting: Option<Offered>,
    /// The newest key frame offered and not yet taken, kept apart from `waiting`: the
    /// frames after it are coded against it and may arrive (and be offered) before it.
    key: Option<Offered>,
    /// Frames in a row passed over because their base had not arrived yet.
    awaiting_base: u32,
    /// Bytes offered that were not a frame, not yet reported.
    junk: Option<String>,
    /// The newest frame number offered (frames older than it are superseded).
    offered: Option<u64>,
    /// A frame offered that the server could not have sent, not yet reported.
    broken: Option<Broken>,
    /// The tick of the newest frame taken.
    newest_tick: Option<u64>,
    /// Watching a recording: its clock may be sought back, so a frame may show an older
    /// tick than the one before it ([`ClientCore::set_replay`]).
    replay: bool,
    /// The most triangles the server serves ([`Welcome::max_budget`]).
    max_budget: u32,
    budget: u32,
    /// The largest budget asked for: frames tessellated before a cut may still come.
    limit: u32,
    outbox: VecDeque<ClientMessage>,
    /// Frames are acknowledged in the key datagrams ([`ClientCore::set_acks_in_datagrams`]),
    /// not on the control stream.
    acks_in_datagrams: bool,
    bytes_in: u64,
    /// The cut as drawn, with geomorphs ([`ClientCore::set_morph`]): the diamonds the
    /// frames toggled since it last followed them (each once, with its height), and the
    /// tick it last followed.
    morph: Option<Morph>,
    pending: DiamondMap<u16>,
    morph_tick: Option<u64>,
    /// Scratch: `pending` as a list, for the morph's step.
    changes: Vec<(u32, u16)>,
}

/// The keys: the latch the window's key events go into, the numbered states, the history
/// each datagram repeats, and the key changes awaiting the frame that shows them.
#[derive(Debug, Default)]
pub struct KeyCore {
    latch: KeyLatch,
    seq: u32,
    history: VecDeque<KeyState>,
    last_held: Keys,
    /// Key changes sent and not yet seen applied, with when they were sent.
    pending: VecDeque<(u32, Instant)>,
}

impl ClientCore {
    /// The core of a viewer welcomed by `welcome`, having asked for `budget` triangles.
    /// `None` when the welcome's grid is not one this protocol has.
    pub fn new(welcome: &Welcome, budget: u32) -> Option<ClientCore> {
        let grid = Grid::new(u32::from(welcome.levels))?;
        let budget = messages::clamp_budget(budget);
        Some(ClientCore {
            grid,
            cut: Follower::new(grid, BASES),
            live: LiveMesh::new(&grid),
            newest: None,
            waiting: None,
            key: None,
            awaiting_base: 0,
            junk: None,
            offered: None,
            broken: None,
            newest_tick: None,
            replay: false,
            max_budget: welcome.max_budget,
            budget,
            limit: budget,
            outbox: VecDeque::new(),
            acks_in_datagrams: false,
            bytes_in: 0,
            morph: None,
            pending: DiamondMap::new(),
            morph_tick: None,
            changes: Vec::new(),
        })
    }

    /// Draws the cut through a [`Morph`] whose geomorphs take `ticks` world ticks (0: the
    /// decoded cut as it is, through the same drawing); without a call, the decoded cut
    /// is drawn directly (a viewer that draws nothing pays nothing). Starts from the
    /// decoded cut as it is now, shown at once.
    pub fn set_morph(&mut self, ticks: u16) {
        if self.morph_ticks() == Some(ticks) {
            return;
        }
        self.pending.clear();
        let mut m = Morph::new(self.grid, ticks);
        let now: Vec<(u32, u16)> = self.cut.split().collect();
        let cut = &self.cut;
        m.step(&now, |d| cut.contains(d), |i| cut.height(i), None);
        self.morph = Some(m);
        self.morph_tick = self.newest_tick;
    }

    /// The camera the next geomorph steps measure their speed on screen from (the frame's:
    /// [`MorphView::of_vehicle`]); `None` keeps the last one.
    pub fn set_morph_view(&mut self, view: Option<MorphView>) {
        if let (Some(m), Some(v)) = (self.morph.as_mut(), view) {
            m.set_view(Some(v));
        }
    }

    /// This connection serves a recording being watched (the server said so): its clock
    /// may go back when sought, and a jump of it shows the cut there at once.
    pub fn set_replay(&mut self) {
        self.replay = true;
    }

    /// Frames taken from now on are acknowledged by the key datagrams ([`Self::acked`] in
    /// each, [`KeyDatagram::acked`]) rather than by [`ClientMessage::Ack`]s: a driver sends
    /// a datagram every 10 ms, so its frames need no control message.
    pub fn set_acks_in_datagrams(&mut self) {
        self.acks_in_datagrams = true;
        self.outbox
            .retain(|m| !matches!(m, ClientMessage::Ack { .. }));
    }

    /// Whether frames are acknowledged by the key datagrams.
    pub fn acks_in_datagrams(&self) -> bool {
        self.acks_in_datagrams
    }

    /// The newest frame taken: what a key datagram acknowledges.
    pub fn acked(&self) -> Option<u64> {
        self.newest
    }

    /// Whether the server said it serves a recording being watched.
    pub fn is_replay(&self) -> bool {
        self.replay
    }

    /// The geomorphs' length in ticks, when the cut is drawn through a [`Morph`].
    pub fn morph_ticks(&self) -> Option<u16> {
        self.morph.as_ref().map(Morph::ticks)
    }

    /// The cut as drawn (with geomorphs), when drawn so.
    pub fn morph(&self) -> Option<&Morph> {
        self.morph.as_ref()
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The newest decoded mesh, as the protocol lays one out (vertices row-major,
    /// triangles in slot order): made on each call, O(cut), for checks and screenshots.
    pub fn mesh(&self) -> mesh::Mesh {
        let cut = &self.cut;
        self.live.to_mesh(&self.grid, |i| cut.height(i))
    }

    /// The newest decoded cut, with its bases.
    pub fn cut(&self) -> &Follower {
        &self.cut
    }

    /// The newest decoded mesh's triangles, slot by diamond.
    pub fn live_mesh(&self) -> &LiveMesh {
        &self.live
    }

    /// Brings `terrain` up to date with the newest decoded mesh on `scene`'s scales:
    /// rewrites the slots the frames decoded since its last update changed (all of them
    /// the first time). One `terrain` follows a core: the slots rewritten are forgotten.
    /// With geomorphs, the vertices are the drawn cut's, advanced to the newest frame's
    /// tick (by the ticks since the last update: never by a clock).
    pub fn update_vertices(&mut self, scene: &Scene, terrain: &mut TerrainVertices) {
        let cut = &self.cut;
        let Some(morph) = self.morph.as_mut() else {
            terrain.update(scene, &mut self.live, |i| cut.height(i), |_| 0.0);
            return;
        };
        self.changes.clear();
        self.changes.extend(self.pending.iter());
        self.pending.clear();
        // A watched recording's clock sought (back, or more than a second on): the cut
        // there is shown at once, as a first frame is.
        let ticks = match (self.morph_tick, self.newest_tick) {
            (Some(a), Some(b)) if b < a || (self.replay && b - a > SOUGHT_TICKS) => None,
            (Some(a), Some(b)) => Some(b - a),
            _ => None,
        };
        morph.step(&self.changes, |d| cut.contains(d), |i| cut.height(i), ticks);
        self.morph_tick = self.newest_tick;
        morph.draw(scene, terrain, |i| cut.height(i));
    }

    /// Bytes the decoder and the mesh hold (the cut, the bases' logs, the slots).
    pub fn decoder_bytes(&self) -> usize {
        self.cut.bytes() + self.live.bytes()
    }

    /// The budget asked for.
    pub fn budget(&self) -> u32 {
        self.budget
    }

    /// The budget served: the one asked for, or the server's most if that is less.
    pub fn effective_budget(&self) -> u32 {
        self.budget.min(self.max_budget)
    }

    /// Frame bytes received so far (frames superseded or dropped included).
    pub fn bytes_in(&self) -> u64 {
        self.bytes_in
    }

    /// A frame's bytes arrived at `now` (a datagram, or a stream read to its end): it
    /// waits to be taken if it is the newest yet; an older one is superseded. A key frame
    /// waits apart, if it is newer than the newest taken and the newest key frame offered,
    /// even when older than a frame offered already (that frame may be coded against it).
    /// A frame failing the frame-number checks ([`Broken`]) is dropped, to be reported.
    pub fn offer(&mut self, bytes: &[u8], now: Instant) {
        self.bytes_in += bytes.len() as u64;
        match messages::decode::<Frame>(bytes) {
            Ok(frame) => {
                if let Err(broken) = check_numbers(&frame, self.offered) {
                    self.broken.get_or_insert(broken);
                    return;
                }
                let newer = |than: Option<u64>| than.is_none_or(|n| frame.frame > n);
                let newest_offered = newer(self.offered);
                if newest_offered {
                    self.offered = Some(frame.frame);
                }
                if frame.base.is_none() {
                    if newer(self.newest) && newer(self.key.as_ref().map(|(k, ..)| k.frame)) {
                        if newest_offered {
                            self.waiting = None; // superseded by the key frame
                        }
                        self.key = Some((frame, bytes.len(), now));
                    }
                } else if newest_offered {
                    self.waiting = Some((frame, bytes.len(), now));
                }
                // Anything else is older than a frame offered already: superseded.
            }
            Err(e) => {
                self.junk.get_or_insert_with(|| format!("not a frame: {e}"));
            }
        }
    }

    /// Whether [`Self::take`] has something to say.
    pub fn has_frame(&self) -> bool {
        self.waiting.is_some() || self.key.is_some() || self.junk.is_some() || self.broken.is_some()
    }

    /// The frame to take: the waiting frame, or the key frame kept apart when the waiting
    /// frame's base is not decoded yet (or nothing newer waits). A waiting frame newer than
    /// the key frame taken stays waiting, for the next take.
    fn next_offered(&mut self, decode: bool) -> Option<Offered> {
        let newest = self.newest;
        let key = self
            .key
            .take()
            .filter(|(k, ..)| newest.is_none_or(|n| k.frame > n));
        let waiting = self.waiting.take();
        let Some(key) = key else {
            return waiting;
        };
        match waiting {
            Some(w) if w.0.frame > key.0.frame => {
                // Without decoding no base is needed: the newest frame goes.
                let needs_key = decode && w.0.base.is_some_and(|b| !self.cut.has_base(b));
                if !needs_key {
                    return Some(w); // the key frame is superseded
                }
                self.waiting = Some(w);
                Some(key)
            }
            // The key frame itself, or older than it.
            _ => Some(key),
        }
    }

    /// Takes the waiting frame; decodes it into [`Self::mesh`] (unless `decode` is false)
    /// against its base, and acknowledges it. A key frame kept apart goes first when the
    /// waiting frame's base is not decoded yet. A frame coded against a base newer than the
    /// newest taken is passed over ([`Taken::Nothing`]: the base is on its way), up to
    /// [`AWAIT_BASE`] in a row; any other frame that cannot be decoded asks for a key frame.
    /// An error for a frame the server could not have sent ([`Broken`]): one that failed
    /// the frame-number checks when offered, one showing an older tick than the frame
    /// before it, or one inconsistent with itself.
    pub fn take(&mut self, decode: bool) -> Result<Taken, Broken> {
        if let Some(broken) = self.broken.take() {
            return Err(broken);
        }
        if let Some(why) = self.junk.take() {
            self.request_key_frame();
            return Ok(Taken::Dropped(why));
        }
        let Some((frame, wire_bytes, arrived)) = self.next_offered(decode) else {
            return Ok(Taken::Nothing);
        };
        if self.newest.is_some_and(|n| frame.frame <= n) {
            return Ok(Taken::Nothing);
        }
        if let (Some(newest), Some(newest_tick)) = (self.newest, self.newest_tick)
            && frame.tick < newest_tick
            && !self.replay
        {
            return Err(Broken::TickBackwards {
                frame: frame.frame,
                tick: frame.tick,
                newest,
                newest_tick,
            });
        }
        let mut triangles = 0;
        if decode {
            if let Some(b) = frame.base
                && !self.cut.has_base(b)
            {
                // Coded against a frame not taken yet (a key frame still on its way): not
                // an error, unless it is too long coming.
                if self.newest.is_none_or(|n| b > n) && self.awaiting_base < AWAIT_BASE {
                    self.awaiting_base += 1;
                    return Ok(Taken::Nothing);
                }
                self.awaiting_base = 0;
                self.request_key_frame();
                return Ok(Taken::Dropped(format!(
                    "frame {}: coded against frame {b}, which this viewer does not have",
                    frame.frame
                )));
            }
            let info = match self
                .cut
                .decode(frame.frame, &frame.mesh, frame.base, self.limit)
            {
                Ok(info) => info,
                Err(e) => {
                    self.awaiting_base = 0;
                    self.request_key_frame();
                    return Ok(Taken::Dropped(format!("frame {}: {e}", frame.frame)));
                }
            };
            let cut = &self.cut;
            self.live
                .update(&self.grid, cut.toggled(), |i| cut.contains(i));
            if self.morph.is_some() {
                for &(d, h) in cut.toggled_heights() {
                    self.pending.toggle(d, h);
                }
            }
            triangles = self.live.triangle_count();
            if triangles != info.triangles as usize {
                return Err(Broken::Inconsistent {
                    frame: frame.frame,
                    emitted: triangles,
                    header: info.triangles,
                });
            }
        }
        self.awaiting_base = 0;
        if !self.acks_in_datagrams {
            self.outbox
                .push_back(ClientMessage::Ack { frame: frame.frame });
        }
        self.newest = Some(frame.frame);
        self.newest_tick = Some(frame.tick);
        Ok(Taken::Frame(Received {
            frame: frame.frame,
            tick: frame.tick,
            vehicles: frame.vehicles,
            input_seq: frame.input_seq,
            wire_bytes,
            triangles,
            arrived,
            decode_s: 0.0,
            latencies_ms: Vec::new(),
        }))
    }

    fn request_key_frame(&mut self) {
        // One request waiting to leave is enough. Each request that reaches the server
        // gets a key frame (superseding the one before, if still pending), sent reliably.
        if !self.outbox.contains(&ClientMessage::KeyFrame) {
            self.outbox.push_back(ClientMessage::KeyFrame);
        }
    }

    /// Asks for `budget` triangles from now on (clamped to what a server takes).
    pub fn set_budget(&mut self, budget: u32) {
        let budget = messages::clamp_budget(budget);
        self.budget = budget;
        self.limit = self.limit.max(budget);
        self.outbox.push_back(ClientMessage::Budget(budget));
    }

    /// Tells the server how the camera differs from the default at the vehicle.
    pub fn set_view(&mut self, view: ViewChange) {
        // Only the newest view matters: one waiting is replaced.
        self.outbox.retain(|m| !matches!(m, ClientMessage::View(_)));
        self.outbox.push_back(ClientMessage::View(view));
    }

    /// The next control message to send, in order.
    pub fn poll_control(&mut self) -> Option<ClientMessage> {
        self.outbox.pop_front()
    }
}

impl KeyCore {
    /// Keys go down (the window's key events; read at the next step).
    pub fn key_down(&mut self, keys: Keys) {
        self.latch.press(keys);
    }

    /// Keys come up.
    pub fn key_up(&mut self, keys: Keys) {
        self.latch.release(keys);
    }

    /// Every key comes up (the window lost focus: nothing stays held).
    pub fn keys_released(&mut self) {
        self.latch.set_held(Keys::NONE);
    }

    /// The latch's state for this step (a press since the last step, however short, is in
    /// it exactly once).
    pub fn take_keys(&mut self) -> KeyStep {
        self.latch.take()
    }

    /// The datagram for one physics step of keys taken at `now`: the new state, numbered,
    /// and the [`messages::KEY_HISTORY`] before it (a lost datagram loses nothing), with
    /// the frame acknowledgement `acked` ([`ClientCore::acked`] when the frames are
    /// acknowledged by datagram, else `None`).
    pub fn key_datagram(&mut self, step: KeyStep, now: Instant, acked: Option<u64>) -> KeyDatagram {
        self.seq = self.seq.wrapping_add(1);
        if step.held != self.last_held || !step.pressed.is_empty() {
            self.pending.push_back((self.seq, now));
            if self.pending.len() > MAX_PENDING {
                self.pending.pop_front();
            }
        }
        self.last_held = step.held;
        self.history.push_front(KeyState {
            seq: self.seq,
            held: step.held.bits(),
            pressed: step.pressed.bits(),
        });
        self.history.truncate(messages::KEY_HISTORY);
        KeyDatagram {
            states: self.history.iter().copied().collect(),
            acked,
        }
    }

    /// A frame showing key states up to `seq` arrived at `arrived`: the latencies of the
    /// changes it is the first to show, milliseconds.
    pub fn applied(&mut self, seq: u32, arrived: Instant) -> Vec<f64> {
        let mut out = Vec::new();
        while let Some(&(s, at)) = self.pending.front() {
            if s > seq {
                break;
            }
            out.push(arrived.saturating_duration_since(at).as_secs_f64() * 1e3);
            self.pending.pop_front();
        }
        out
    }
}
