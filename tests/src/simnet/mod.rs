//! A deterministic simulated network, in the spirit of `quinn-proto`'s `Pair` test harness:
//! the server's sans-IO cores ([`WorldCore`], and per viewer a [`ViewerCore`] with its
//! [`Mailbox`] and [`KeyGate`]) and the viewer's sans-IO cores ([`ClientCore`] for frames,
//! [`KeyCore`] for keys) driven together by virtual time, with no socket, task, thread or
//! clock. Tests add viewers over [`Path`]s, run virtual time, steer the viewers and break
//! their paths, and read what each viewer took ([`Stats`], [`TakenFrame`]s, a driver's
//! [`TrackPoint`]s) and what the world holds.
//!
//! **Time.** One `Instant` is read when a [`Sim`] is made (its epoch); from then on "now" is
//! the epoch plus a virtual [`Duration`] that [`Sim::step`] advances by 1 ms. Nothing reads
//! the clock again, so a run is a pure function of its seed and what the test does.
//! Packets arrive at nanosecond times, and are handled in the step that reaches them (a
//! step: arrivals at the server, the world's tick if due, frames due, arrivals at the
//! viewers, their keys, takes and control messages, then the paths send).
//!
//! **Composition** (as `net::viewer` and `net::world_loop` do it):
//!
//! - The world ticks every 10 ms of virtual time; what arrived up to the tick belongs to
//!   it. Its newest snapshot is what frames show (the shell's `watch`, latest wins).
//! - A viewer sends its hello on the control stream; the server answers a driver's with a
//!   [`world_core::Event::Join`] (a spectator follows a vehicle of the snapshot) and a
//!   welcome, and from then on makes a frame every `1 / frame_rate` s (60 here): the
//!   mailbox drained into the core, [`ViewerCore::make_frame`] for the followed vehicle's
//!   state in the newest snapshot, [`frame_message`], [`messages::encode`]. A change frame
//!   of at most [`MAX_DATAGRAM`] bytes goes as a datagram, a larger one on a reliable
//!   stream of its own, reset when the next frame is made unless the viewer has
//!   acknowledged its frame (the shell's `in_flight`). A key frame, whatever its size, goes
//!   on a reliable stream of its own that is not reset while it is pending
//!   ([`ViewerCore::pending_key`]); once it is not (superseded by a newer key frame, or
//!   another asked for) it is reset unless acknowledged (the shell's `key_in_flight`).
//! - Control messages arriving at the server go into the [`Mailbox`] (a goodbye, or a
//!   second hello, ends the connection); key datagrams go through the driver's [`KeyGate`]
//!   into the world.
//! - The viewer, once welcomed, sends a key datagram every 10 ms with its script's next
//!   step ([`roam_protocol::script::Script::steps`], then no keys) from its [`KeyCore`],
//!   offers every frame that arrives (datagrams, and each stream once complete, whatever
//!   streams after it have completed; those before the welcome wait for the welcome) to its
//!   [`ClientCore`], takes one frame a step when it has one (decoding it, and measuring key
//!   latencies with [`KeyCore::applied`]) and sends its control messages, in order. The
//!   harness checks each decoded mesh against the server's cut for that frame.
//! - Either side closes a connection it has heard nothing on for [`IDLE_TIMEOUT`] (quinn's
//!   `max_idle_timeout` in `link/src/tls.rs`); the server then tells the world the driver
//!   left and drops the viewer's core. A server that ends a connection itself (the
//!   viewer's goodbye, the followed vehicle gone, a refusal) gives its last word, if it
//!   has one, [`LAST_WORD`] to arrive, then closes: a close packet (which may be lost),
//!   and the driver's leave.
//!
//! **The path model**, per direction ([`Direction`]): a packet (at most [`MAX_DATAGRAM`] payload
//! bytes plus [`OVERHEAD`] bytes of headers) waits in a FIFO serialisation queue until the
//! direction is free (`rate_bytes_per_s`; none: it leaves at once), is dropped at the tail when
//! the queue holds more than `queue_bytes`, is lost with probability `loss`, and arrives
//! `delay` plus a uniform `[0, jitter]` after it left (so jitter reorders). Each direction
//! has its own seeded [`SplitMix64`]. A path can be cut for a while or for good
//! ([`Sim::cut_path`], [`Sim::kill_path`]): every packet that leaves or arrives meanwhile
//! is lost.
//!
//! - **Datagrams** (key datagrams, small frames, the close packet) are lost for good.
//! - **The control stream**, one per direction: each message is one packet with a
//!   sequence number; a lost one is sent again [`rto`] (2 × delay + 10 ms) after it left,
//!   as often as it takes; the receiver hands messages to the application in order (a lost
//!   one holds up those behind it).
//! - **Frame streams** (server to viewer): a frame's bytes in packets of [`MAX_DATAGRAM`],
//!   each retransmitted like a control message; the viewer offers the frame once every
//!   packet has arrived. A reset stream loses its packets still queued and is never sent
//!   again; packets already on the wire still arrive (the viewer reads streams as data
//!   comes, so a reset that follows them is too late to discard them), and the viewer
//!   forgets a reset stream once none of its packets is on the way (the reset arrives
//!   behind them).
//!
//! **What it does not model:** the QUIC handshake (a hello leaves when the viewer is
//! added), congestion control and pacing (only a fixed rate), transport acknowledgements
//! (free and never lost: a sender knows of a loss exactly `rto` after the packet left),
//! stream priorities (one FIFO for everything: the shell sends a key frame first, here it
//! waits its turn), flow control, keep-alives (a live
//! connection always has traffic here), the colour map (the welcome says 0 bytes of it),
//! the join token, the time the cores take (they run in zero virtual time), a window's
//! or a viewer's pacing of takes (a viewer takes a frame in the millisecond it arrives),
//! and key datagrams still reaching the world during a last word (dropped here).
//!
//! **Files:** this one (the harness: time, viewers, what a test does and reads), `path.rs`
//! (the path and packet model), `server.rs` (the server's cores composed as its shell
//! composes them) and `client.rs` (the viewer's, as `session.rs` does).
//!
//! [`ViewerCore`]: roam_server::viewer::ViewerCore
//! [`ViewerCore::make_frame`]: roam_server::viewer::ViewerCore::make_frame
//! [`ViewerCore::pending_key`]: roam_server::viewer::ViewerCore::pending_key
//! [`Mailbox`]: roam_server::viewer::conversation::Mailbox
//! [`KeyGate`]: roam_server::viewer::conversation::KeyGate
//! [`frame_message`]: roam_server::viewer::conversation::frame_message
//! [`world_core::Event::Join`]: roam_server::sim::world_core::Event::Join
use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use roam_client::core::{ClientCore, KeyCore, Received};
use roam_protocol::keys::KeyStep;
use roam_protocol::messages::{
    self, ClientMessage, Hello, Reason, Role, VERSION, ViewChange, Welcome,
};
use roam_protocol::script::Script;
use roam_server::Terrain;
use roam_server::sim::physics::VehicleState;
use roam_server::sim::world::{VehicleId, World};
use roam_server::sim::world_core::{Snapshot, WorldCore};
use roam_server::terrain::variance::VarianceTree;

/// The largest packet payload: a frame of at most this many bytes goes as a datagram, a
/// larger one in packets of this size on a stream (quinn's datagrams are about this big
/// on a 1,280-byte path MTU).
pub const MAX_DATAGRAM: usize = 1200;

/// Header bytes per packet, counted against a direction's rate and queue.
pub const OVERHEAD: usize = 40;

/// Silence after which either side closes a connection (quinn's `max_idle_timeout`).
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(10);

/// The world's step.
pub const TICK: Duration = Duration::from_millis(10);

/// How long the server gives a goodbye to arrive before it closes the connection.
pub const LAST_WORD: Duration = Duration::from_millis(250);

/// The simulation's step.
pub const STEP: Duration = Duration::from_millis(1);

/// The frame rate viewers ask for.
pub const FRAME_RATE: u16 = 60;

/// A viewer's window, as its hello tells it.
pub const VIEWPORT: [u32; 2] = [640, 480];
pub const FOV_Y_DEG: f32 = 60.0;

// The server codes against frames at most its logs old; the viewer keeps that many bases.
const _: () = assert!(roam_server::viewer::LOGS <= roam_client::core::BASES);

/// Frames whose meshes the server side remembers for checking what the viewer decodes.
const MADE_KEPT: usize = 512;

/// Frame bytes a viewer keeps from before its welcome (quinn buffers them for the reader).
const EARLY_BYTES: usize = 1 << 20;

/// A message's bytes (`messages::encode`; the messages here are all within its limits).
macro_rules! encoded {
    ($msg:expr) => {{
        let mut out = Vec::new();
        messages::encode($msg, &mut out).expect("a message within the limits");
        out
    }};
}

mod client;
mod path;
mod server;

use client::{ClientSide, client_control};
pub use path::{Direction, Path, SplitMix64, WireStats, rto};
use path::{InOrder, Wire};
use server::{ServerSide, ServerState};

/// A frame the viewer took.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TakenFrame {
    /// Virtual time it was taken.
    pub at: Duration,
    pub frame: u64,
    pub tick: u64,
    pub triangles: usize,
    /// Whether the server made it as a key frame.
    pub key: bool,
    pub decoded: bool,
}

/// A driver's vehicle after a world tick.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackPoint {
    pub tick: u64,
    /// The newest of its key states the world had applied.
    pub applied: Option<u32>,
    pub state: VehicleState,
}

/// What happened to one viewer (no wall-clock value: two runs with one seed compare
/// equal).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Stats {
    /// Frames taken (`Taken::Frame`).
    pub frames: u64,
    /// Frames that failed to decode (`Taken::Dropped`).
    pub decode_errors: u64,
    /// Frames inconsistent with their own header (the server is broken).
    pub inconsistent: u64,
    /// Frames taken that the server made as key frames.
    pub key_frames: u64,
    /// Decoded meshes compared with the server's cut for that frame, and those that
    /// differed (index for index, vertex for vertex).
    pub meshes_checked: u64,
    pub mesh_mismatches: u64,
    pub first_frame_at: Option<Duration>,
    pub last_frame_at: Option<Duration>,
    /// The largest time between two frames taken.
    pub largest_gap: Duration,
    pub max_triangles: usize,
    /// The server's side: frames made, as key frames, sent as datagrams and on streams,
    /// streams reset.
    pub frames_made: u64,
    pub key_frames_made: u64,
    pub datagram_frames: u64,
    pub stream_frames: u64,
    pub streams_reset: u64,
    /// Key-frame requests that reached the server.
    pub key_frame_requests: u64,
    /// The largest frame message made, bytes.
    pub largest_frame: usize,
    /// Streams the viewer read to their end.
    pub streams_completed: u64,
    pub key_datagrams: u64,
    /// Key change sent → the first frame taken showing it applied, virtual ms (as
    /// `KeyCore::applied` measures it).
    pub key_latencies_ms: Vec<f64>,
    /// Viewer to server, and back.
    pub up: WireStats,
    pub down: WireStats,
}

/// A viewer's id in a [`Sim`].
pub type ViewerId = usize;

struct Viewer {
    up: Wire,
    down: Wire,
    server: ServerSide,
    client: ClientSide,
    stats: Stats,
    taken: Vec<TakenFrame>,
    track: Vec<TrackPoint>,
    latest: Option<Received>,
    dropped: Vec<String>,
}

/// The server's cores, the viewers' cores, and the paths between them, in virtual time.
pub struct Sim {
    epoch: Instant,
    now: Duration,
    seed: u64,
    terrain: Arc<Terrain>,
    variance: VarianceTree,
    scratch: roam_server::tessellate::Scratch,
    height_step: u16,
    world: WorldCore,
    snapshot: Snapshot,
    next_tick: Duration,
    viewers: Vec<Viewer>,
}

/// A 64-bit FNV-1a of a mesh: its vertices in order, its triangles as a set.
fn mesh_hash(vertices: &[[u16; 2]], indices: &[u32]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h ^= u64::from(b);
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        }
    };
    eat(&(vertices.len() as u64).to_le_bytes());
    for v in vertices {
        eat(&v[0].to_le_bytes());
        eat(&v[1].to_le_bytes());
    }
    // The triangles as a set: each rotated to start at its least index, then sorted (the
    // viewer keeps them in slot order, the server's tessellator row-major).
    let mut triangles: Vec<[u32; 3]> = indices
        .chunks_exact(3)
        .map(|t| {
            let k = (0..3).min_by_key(|&k| t[k]).unwrap_or(0);
            [t[k], t[(k + 1) % 3], t[(k + 2) % 3]]
        })
        .collect();
    triangles.sort_unstable();
    eat(&(indices.len() as u64).to_le_bytes());
    for i in triangles.iter().flatten() {
        eat(&i.to_le_bytes());
    }
    h
}
impl Sim {
    /// An empty world on `terrain`, no viewer yet, at virtual time 0.
    pub fn new(seed: u64, terrain: Arc<Terrain>) -> Sim {
        let variance = VarianceTree::build(&terrain.heights, 1, &mut |_, _| {});
        let height_step = roam_protocol::height_step(terrain.heights.samples());
        let world = WorldCore::new(terrain.clone(), None).expect("no recording to fail");
        Sim {
            epoch: Instant::now(),
            now: Duration::ZERO,
            seed,
            scratch: roam_server::tessellate::Scratch::new(terrain.heights.side()),
            terrain,
            variance,
            height_step,
            world,
            snapshot: Snapshot::default(),
            next_tick: TICK,
            viewers: Vec::new(),
        }
    }

    /// The virtual time.
    pub fn now(&self) -> Duration {
        self.now
    }

    fn at(&self, t: Duration) -> Instant {
        self.epoch + t
    }

    /// A driver joins over `path`, asking for `budget` triangles, and drives `script`.
    pub fn add_driver(&mut self, script: &Script, budget: u32, path: Path) -> ViewerId {
        self.add(Role::Driver, Some(script.steps().collect()), budget, path)
    }

    /// A spectator joins over `path`, following `follow` (or the first vehicle).
    pub fn add_spectator(
        &mut self,
        follow: Option<VehicleId>,
        budget: u32,
        path: Path,
    ) -> ViewerId {
        self.add(Role::Spectator { follow }, None, budget, path)
    }

    fn add(
        &mut self,
        role: Role,
        steps: Option<Vec<KeyStep>>,
        budget: u32,
        path: Path,
    ) -> ViewerId {
        let id = self.viewers.len();
        let seed = |k: u64| {
            SplitMix64::new(self.seed ^ ((id as u64) << 32) ^ k.wrapping_mul(0x5851_f42d_4c95_7f2d))
                .next_u64()
        };
        let hello = Hello {
            version: VERSION,
            role,
            token: "simnet".into(),
            viewport: VIEWPORT,
            fov_y_deg: FOV_Y_DEG,
            budget: messages::clamp_budget(budget),
            frame_rate: FRAME_RATE,
            resume: None,
            color_window: roam_protocol::tiles::DEFAULT_WINDOW,
        };
        let mut v = Viewer {
            up: Wire::new(path.up, seed(1)),
            down: Wire::new(path.down, seed(2)),
            server: ServerSide {
                state: ServerState::Waiting,
                control_in: InOrder::default(),
                control_seq: 0,
                last_heard: self.now,
                joined: None,
            },
            client: ClientSide {
                hello: hello.clone(),
                core: None,
                welcome: None,
                steps,
                next_step: 0,
                next_key: Duration::ZERO,
                control_in: InOrder::default(),
                control_seq: 0,
                streams: BTreeMap::new(),
                early: VecDeque::new(),
                keys: KeyCore::default(),
                skip_decoding: 0,
                closed: None,
                last_heard: self.now,
            },
            stats: Stats::default(),
            taken: Vec::new(),
            track: Vec::new(),
            latest: None,
            dropped: Vec::new(),
        };
        let now = self.now;
        client_control(&mut v, now, &ClientMessage::Hello(hello));
        v.up.pump(now);
        self.viewers.push(v);
        id
    }

    /// Runs until the virtual time is `t`.
    pub fn run_until(&mut self, t: Duration) {
        while self.now < t {
            self.step();
        }
    }

    /// Runs for `d` of virtual time.
    pub fn run_for(&mut self, d: Duration) {
        self.run_until(self.now + d);
    }

    /// One millisecond: arrivals at the server, the world's tick if due, frames due, arrivals
    /// at the viewers, the viewers' keys, takes and control messages, and the paths send.
    pub fn step(&mut self) {
        self.now += STEP;
        let now = self.now;
        self.server_receive(now);
        if now >= self.next_tick {
            self.tick();
            self.next_tick += TICK;
        }
        for i in 0..self.viewers.len() {
            self.server_frames(i, now);
        }
        for i in 0..self.viewers.len() {
            self.client_step(i, now);
        }
        for v in &mut self.viewers {
            v.up.pump(now);
            v.down.pump(now);
            v.stats.up = v.up.stats;
            v.stats.down = v.down.stats;
        }
    }

    // ---- What a test does ----

    /// Viewer `i`'s core, once welcomed (to change its budget or view: what it has to
    /// send leaves at the next step).
    pub fn client(&mut self, i: ViewerId) -> Option<&mut ClientCore> {
        self.viewers[i].client.core.as_mut()
    }

    /// The viewer asks for `budget` triangles.
    pub fn set_budget(&mut self, i: ViewerId, budget: u32) {
        if let Some(c) = self.client(i) {
            c.set_budget(budget);
        }
    }

    /// The viewer's camera changes.
    pub fn set_view(&mut self, i: ViewerId, view: ViewChange) {
        if let Some(c) = self.client(i) {
            c.set_view(view);
        }
    }

    /// The viewer takes its next `n` frames without decoding them (it acknowledges them
    /// all the same, and keeps no base of them).
    pub fn skip_decoding(&mut self, i: ViewerId, n: u32) {
        self.viewers[i].client.skip_decoding = n;
    }

    /// The viewer says goodbye on its control stream and stops.
    pub fn quit(&mut self, i: ViewerId) {
        let now = self.now;
        let v = &mut self.viewers[i];
        client_control(v, now, &ClientMessage::Bye(Reason::Quit));
        v.client.core = None;
        v.client.steps = None;
    }

    /// Viewer `i`'s path carries nothing (either way, packets on the way included) for `d`.
    pub fn cut_path(&mut self, i: ViewerId, d: Duration) {
        let until = self.now.saturating_add(d);
        let v = &mut self.viewers[i];
        v.up.down_until = v.up.down_until.max(until);
        v.down.down_until = v.down.down_until.max(until);
    }

    /// Viewer `i`'s path to the server carries nothing (packets on the way included) for
    /// `d`; the way back works.
    pub fn cut_up(&mut self, i: ViewerId, d: Duration) {
        let until = self.now.saturating_add(d);
        let v = &mut self.viewers[i];
        v.up.down_until = v.up.down_until.max(until);
    }

    /// Viewer `i`'s path carries nothing, ever again.
    pub fn kill_path(&mut self, i: ViewerId) {
        self.cut_path(i, Duration::MAX);
    }

    /// Viewer `i`'s path is now `path` (packets on the way keep their arrival times).
    pub fn set_path(&mut self, i: ViewerId, path: Path) {
        let v = &mut self.viewers[i];
        v.up.direction = path.up;
        v.down.direction = path.down;
    }

    // ---- What a test reads ----

    pub fn stats(&self, i: ViewerId) -> &Stats {
        &self.viewers[i].stats
    }

    /// Every frame the viewer took, in order.
    pub fn taken(&self, i: ViewerId) -> &[TakenFrame] {
        &self.viewers[i].taken
    }

    /// The newest frame the viewer took.
    pub fn latest(&self, i: ViewerId) -> Option<&Received> {
        self.viewers[i].latest.as_ref()
    }

    /// Why frames failed to decode, with when.
    pub fn decode_failures(&self, i: ViewerId) -> &[String] {
        &self.viewers[i].dropped
    }

    /// A driver's vehicle after each tick since it joined.
    pub fn track(&self, i: ViewerId) -> &[TrackPoint] {
        &self.viewers[i].track
    }

    /// The viewer's welcome, once it has one.
    pub fn welcome(&self, i: ViewerId) -> Option<&Welcome> {
        self.viewers[i].client.welcome.as_ref()
    }

    /// The vehicle the server gave (or let follow) viewer `i`, while it serves it.
    pub fn vehicle(&self, i: ViewerId) -> Option<VehicleId> {
        match &self.viewers[i].server.state {
            ServerState::Serving(s) => Some(s.vehicle),
            _ => None,
        }
    }

    /// Whether the server still serves viewer `i` (its core is alive).
    pub fn server_open(&self, i: ViewerId) -> bool {
        !matches!(self.viewers[i].server.state, ServerState::Closed)
    }

    /// Why the viewer's connection ended, if it has.
    pub fn client_closed(&self, i: ViewerId) -> Option<&str> {
        self.viewers[i].client.closed.as_deref()
    }

    /// The triangle budget the server's core for viewer `i` works to.
    pub fn server_budget(&self, i: ViewerId) -> Option<u32> {
        match &self.viewers[i].server.state {
            ServerState::Serving(s) => Some(s.core.budget()),
            _ => None,
        }
    }

    /// The world now.
    pub fn world(&self) -> &World {
        self.world.world()
    }

    /// Whether the world has vehicle `id`.
    pub fn world_has(&self, id: VehicleId) -> bool {
        self.world().vehicle(id).is_some()
    }

    /// The newest snapshot.
    pub fn snapshot(&self) -> &Snapshot {
        &self.snapshot
    }
}
