//! A deterministic simulated network, in the spirit of `quinn-proto`'s `Pair` test harness:
//! the server's sans-IO cores ([`WorldCore`], and per viewer a [`ViewerCore`] with its
//! [`Mailbox`] and [`KeyGate`]) and the viewer's sans-IO cores ([`ClientCore`] for frames,
//! [`KeyCore`] for keys) driven together by virtual time, with no socket, task, thread or
//! clock. Tests add viewers over [`Path`]s, run virtual time, steer the viewers and break
//! their links, and read what each viewer took ([`Stats`], [`TakenFrame`]s, a driver's
//! [`TrackPoint`]s) and what the world holds.
//!
//! **Time.** One `Instant` is read when a [`Sim`] is made (its epoch); from then on "now" is
//! the epoch plus a virtual [`Duration`] that [`Sim::step`] advances by 1 ms. Nothing reads
//! the clock again, so a run is a pure function of its seed and what the test does.
//! Packets arrive at nanosecond times, and are handled in the step that reaches them (a
//! step: arrivals at the server, the world's tick if due, frames due, arrivals at the
//! viewers, their keys, takes and control messages, then the links send).
//!
//! **Composition** (as `net::viewer` and `net::world_loop` do it):
//!
//! - The world ticks every 10 ms of virtual time; what arrived up to the tick belongs to
//!   it. Its newest snapshot is what frames show (the shell's `watch`, latest wins).
//! - A viewer sends its hello on the control stream; the server answers a driver's with a
//!   [`world_core::Event::Join`] (a spectator follows a vehicle of the snapshot) and a
//!   welcome, and from then on makes a frame every `1 / frame_rate` s (60 here): the
//!   mailbox drained into the core, [`ViewerCore::make_frame`] for the followed vehicle's
//!   state in the newest snapshot, [`frame_message`], [`messages::encode`]. A frame of at
//!   most [`MAX_DATAGRAM`] bytes goes as a datagram, a larger one (key frames) on a reliable
//!   stream of its own; when the next frame is made the stream in flight is reset unless
//!   the viewer has acknowledged its frame (the shell's `in_flight`).
//! - Control messages arriving at the server go into the [`Mailbox`] (a goodbye, or a
//!   second hello, ends the connection); key datagrams go through the driver's [`KeyGate`]
//!   into the world.
//! - The viewer, once welcomed, sends a key datagram every 10 ms with its script's next
//!   step ([`roam_protocol::script::Script::steps`], then no keys) from its [`KeyCore`],
//!   offers every frame that arrives (datagrams, and streams once complete; those before
//!   the welcome wait for it) to its [`ClientCore`], takes the waiting frame (decoding it,
//!   and measuring key latencies with [`KeyCore::applied`]) and sends its control
//!   messages, in order. The harness checks each decoded mesh against the server's cut
//!   for that frame.
//! - Either side closes a connection it has heard nothing on for [`IDLE_TIMEOUT`] (quinn's
//!   `max_idle_timeout` in `link/src/tls.rs`); the server then tells the world the driver
//!   left and drops the viewer's core. A server that ends a connection itself (the
//!   viewer's goodbye, the followed vehicle gone, a refusal) gives its last word, if it
//!   has one, [`LAST_WORD`] to arrive, then closes: a close packet (which may be lost),
//!   and the driver's leave.
//!
//! **The link model**, per direction ([`Link`]): a packet (at most [`MAX_DATAGRAM`] payload
//! bytes plus [`OVERHEAD`] bytes of headers) waits in a FIFO serialisation queue until the
//! link is free (`rate_bytes_per_s`; none: it leaves at once), is dropped at the tail when
//! the queue holds more than `queue_bytes`, is lost with probability `loss`, and arrives
//! `delay` plus a uniform `[0, jitter]` after it left (so jitter reorders). Each direction
//! has its own seeded [`SplitMix64`]. A link can be cut for a while or for good
//! ([`Sim::cut_link`], [`Sim::kill_link`]): every packet that leaves or arrives meanwhile
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
//!   comes, so a reset that follows them is too late to discard them).
//!
//! **What it does not model:** the QUIC handshake (a hello leaves when the viewer is
//! added), congestion control and pacing (only a fixed rate), transport acknowledgements
//! (free and never lost: a sender knows of a loss exactly `rto` after the packet left),
//! stream priorities (one FIFO for everything), flow control, keep-alives (a live
//! connection always has traffic here), the colour map (the welcome says 0 bytes of it),
//! the join token, the time the cores take (they run in zero virtual time), a window's
//! or a viewer's pacing of takes (a viewer takes a frame in the millisecond it arrives),
//! and key datagrams still reaching the world during a last word (dropped here).

use std::collections::{BTreeMap, BTreeSet, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use roam_client::core::{ClientCore, KeyCore, Received, Taken};
use roam_protocol::keys::{KeyStep, Keys};
use roam_protocol::messages::{
    self, ClientMessage, Hello, Reason, Role, ServerMessage, VERSION, ViewChange, Welcome,
};
use roam_protocol::script::Script;
use roam_server::Terrain;
use roam_server::sim::physics::VehicleState;
use roam_server::sim::world::{VehicleId, World};
use roam_server::sim::world_core::{self, Snapshot, WorldCore};
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::Mesh;
use roam_server::viewer::link::{Control, KeyGate, Mailbox, frame_message};
use roam_server::viewer::{Scene, ViewerCore};

/// The largest packet payload: a frame of at most this many bytes goes as a datagram, a
/// larger one in packets of this size on a stream (quinn's datagrams are about this big
/// on a 1,280-byte path MTU).
pub const MAX_DATAGRAM: usize = 1200;

/// Header bytes per packet, counted against a link's rate and queue.
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

/// A small deterministic generator (Vigna's SplitMix64).
#[derive(Clone, Debug)]
pub struct SplitMix64(u64);

impl SplitMix64 {
    pub fn new(seed: u64) -> SplitMix64 {
        SplitMix64(seed)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    /// True with probability `p`.
    pub fn chance(&mut self, p: f64) -> bool {
        p > 0.0 && self.unit() < p
    }
}

/// One direction of a viewer's path.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Link {
    /// One-way delay.
    pub delay: Duration,
    /// Extra delay, uniform in `[0, jitter]`, per packet (packets overtake each other).
    pub jitter: Duration,
    /// Probability that a packet is lost.
    pub loss: f64,
    /// The bandwidth: a packet leaves when the link is free. `None`: no limit.
    pub rate_bytes_per_s: Option<u64>,
    /// The serialisation queue's limit, bytes: a packet that finds it fuller is dropped.
    pub queue_bytes: usize,
}

impl Default for Link {
    /// 10 ms, no jitter, no loss, no bandwidth limit.
    fn default() -> Link {
        Link {
            delay: Duration::from_millis(10),
            jitter: Duration::ZERO,
            loss: 0.0,
            rate_bytes_per_s: None,
            queue_bytes: 256 << 10,
        }
    }
}

impl Link {
    /// A link with this delay, jitter and loss, and no bandwidth limit.
    pub fn lossy(delay_ms: u64, jitter_ms: u64, loss: f64) -> Link {
        Link {
            delay: Duration::from_millis(delay_ms),
            jitter: Duration::from_millis(jitter_ms),
            loss,
            ..Link::default()
        }
    }

    /// The same link at `bytes_per_s`.
    pub fn with_rate(self, bytes_per_s: u64) -> Link {
        Link {
            rate_bytes_per_s: Some(bytes_per_s),
            ..self
        }
    }
}

/// A viewer's path: the link to the server and the link back.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Path {
    pub up: Link,
    pub down: Link,
}

impl Path {
    /// The same link both ways.
    pub fn symmetric(link: Link) -> Path {
        Path {
            up: link,
            down: link,
        }
    }
}

/// When a sender learns that a packet on `link` was lost and sends it again: 2 × the
/// one-way delay + 10 ms after it left.
pub fn rto(link: &Link) -> Duration {
    2 * link.delay + Duration::from_millis(10)
}

/// What a packet carries.
#[derive(Clone, Debug)]
enum Payload {
    Datagram(Vec<u8>),
    Control {
        seq: u64,
        bytes: Vec<u8>,
    },
    Chunk {
        stream: u64,
        index: u32,
        count: u32,
        bytes: Vec<u8>,
    },
    /// The sender closed the connection.
    Close,
}

impl Payload {
    fn size(&self) -> usize {
        OVERHEAD
            + match self {
                Payload::Datagram(b)
                | Payload::Control { bytes: b, .. }
                | Payload::Chunk { bytes: b, .. } => b.len(),
                Payload::Close => 0,
            }
    }

    fn stream(&self) -> Option<u64> {
        match self {
            Payload::Chunk { stream, .. } => Some(*stream),
            _ => None,
        }
    }

    /// Whether a loss is repaired (control and stream packets).
    fn reliable(&self) -> bool {
        matches!(self, Payload::Control { .. } | Payload::Chunk { .. })
    }
}

/// Packets through one direction of a link.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WireStats {
    /// Packets that left (retransmissions included).
    pub packets: u64,
    /// Bytes that left, headers included.
    pub bytes: u64,
    /// Packets lost on the way (or to a cut link).
    pub lost: u64,
    /// Packets dropped at a full queue.
    pub dropped: u64,
    /// Packets sent again after a loss.
    pub retransmitted: u64,
}

struct Flying {
    left: Duration,
    arrive: Duration,
    order: u64,
    payload: Payload,
}

/// One direction of a viewer's path, with its packets queued, on the way and awaiting
/// retransmission.
struct Wire {
    link: Link,
    rng: SplitMix64,
    /// `(enqueued at, packet)`, first out first.
    queue: VecDeque<(Duration, Payload)>,
    queued_bytes: usize,
    /// When the link has finished sending what left so far.
    free_at: Duration,
    flying: Vec<Flying>,
    /// `(due, packet)`: lost packets to send again.
    retransmit: Vec<(Duration, Payload)>,
    /// The link carries nothing before this time (`Duration::MAX`: never again).
    down_until: Duration,
    order: u64,
    /// Streams the sender reset: nothing of theirs is sent again.
    reset: BTreeSet<u64>,
    /// The sender closed: nothing lost is sent again.
    closed: bool,
    stats: WireStats,
}

impl Wire {
    fn new(link: Link, seed: u64) -> Wire {
        Wire {
            link,
            rng: SplitMix64::new(seed),
            queue: VecDeque::new(),
            queued_bytes: 0,
            free_at: Duration::ZERO,
            flying: Vec::new(),
            retransmit: Vec::new(),
            down_until: Duration::ZERO,
            order: 0,
            reset: BTreeSet::new(),
            closed: false,
            stats: WireStats::default(),
        }
    }

    fn is_down(&self, at: Duration) -> bool {
        at < self.down_until
    }

    fn lose(&mut self, at: Duration, payload: Payload) {
        self.stats.lost += 1;
        self.repair(at, payload);
    }

    /// A lost packet is sent again, `rto` after `at`, if it is to be.
    fn repair(&mut self, at: Duration, payload: Payload) {
        let reset = payload.stream().is_some_and(|s| self.reset.contains(&s));
        if payload.reliable() && !self.closed && !reset {
            self.retransmit.push((at + rto(&self.link), payload));
        }
    }

    /// Queues a packet at `now` (it leaves at the next [`Self::pump`]).
    fn send(&mut self, now: Duration, payload: Payload) {
        let size = payload.size();
        if self.link.rate_bytes_per_s.is_some() && self.queued_bytes + size > self.link.queue_bytes
        {
            self.stats.dropped += 1;
            self.repair(now, payload);
            return;
        }
        self.queued_bytes += size;
        self.queue.push_back((now, payload));
    }

    /// Retransmissions due by `now` are queued, and what the link can send by `now` leaves.
    fn pump(&mut self, now: Duration) {
        let mut due = Vec::new();
        self.retransmit.retain(|(at, p)| {
            if *at <= now {
                due.push((*at, p.clone()));
                false
            } else {
                true
            }
        });
        due.sort_by_key(|(at, _)| *at);
        for (_, p) in due {
            self.stats.retransmitted += 1;
            self.send(now, p);
        }
        while let Some((enqueued, _)) = self.queue.front() {
            let start = self.free_at.max(*enqueued);
            if start > now {
                break;
            }
            let (_, payload) = self.queue.pop_front().expect("front checked");
            let size = payload.size();
            self.queued_bytes -= size;
            let busy = match self.link.rate_bytes_per_s {
                Some(rate) => {
                    Duration::from_nanos((size as u64 * 1_000_000_000).div_ceil(rate.max(1)))
                }
                None => Duration::ZERO,
            };
            let left = start + busy;
            self.free_at = left;
            self.stats.packets += 1;
            self.stats.bytes += size as u64;
            if self.is_down(left) || self.rng.chance(self.link.loss) {
                self.lose(left, payload);
                continue;
            }
            let jitter =
                Duration::from_nanos((self.rng.unit() * self.link.jitter.as_nanos() as f64) as u64);
            self.order += 1;
            self.flying.push(Flying {
                left,
                arrive: left + self.link.delay + jitter,
                order: self.order,
                payload,
            });
        }
    }

    /// The packets that have arrived by `now`, in the order they arrived.
    fn arrived(&mut self, now: Duration) -> Vec<(Duration, Payload)> {
        let mut due: Vec<Flying> = Vec::new();
        let mut i = 0;
        while i < self.flying.len() {
            if self.flying[i].arrive <= now {
                due.push(self.flying.swap_remove(i));
            } else {
                i += 1;
            }
        }
        due.sort_by_key(|f| (f.arrive, f.order));
        let mut out = Vec::new();
        for f in due {
            if self.is_down(f.arrive) {
                self.lose(f.left, f.payload);
            } else {
                out.push((f.arrive, f.payload));
            }
        }
        out
    }

    /// The sender resets `stream`: its queued packets go, and none is sent again.
    fn reset(&mut self, stream: u64) {
        let mut freed = 0;
        self.queue.retain(|(_, p)| {
            let keep = p.stream() != Some(stream);
            if !keep {
                freed += p.size();
            }
            keep
        });
        self.queued_bytes -= freed;
        self.retransmit.retain(|(_, p)| p.stream() != Some(stream));
        self.reset.insert(stream);
    }

    /// The sender closed: what waits to leave goes, and nothing lost is sent again (what
    /// is on the way still arrives, and a last word may still be sent).
    fn close(&mut self) {
        self.closed = true;
        self.queue.clear();
        self.queued_bytes = 0;
        self.retransmit.clear();
    }
}

/// A control stream's receiving end: messages handed on in order.
#[derive(Default)]
struct InOrder {
    next: u64,
    held: BTreeMap<u64, Vec<u8>>,
}

impl InOrder {
    fn accept(&mut self, seq: u64, bytes: Vec<u8>) -> Vec<Vec<u8>> {
        if seq >= self.next {
            self.held.insert(seq, bytes);
        }
        let mut out = Vec::new();
        while let Some(b) = self.held.remove(&self.next) {
            out.push(b);
            self.next += 1;
        }
        out
    }
}

/// A frame stream being received.
struct Assembly {
    parts: Vec<Option<Vec<u8>>>,
    have: usize,
}

/// What the server remembers of a frame it made, to check what the viewer decodes.
#[derive(Clone, Copy, Debug)]
struct MadeFrame {
    frame: u64,
    key: bool,
    triangles: usize,
    mesh: u64,
}

/// A viewer's connection as the server's shell holds it.
struct Serving {
    core: ViewerCore,
    mailbox: Mailbox,
    gate: KeyGate,
    vehicle: VehicleId,
    driver: bool,
    seen: bool,
    period: Duration,
    next_frame: Duration,
    /// The frame stream not yet known to be acknowledged: `(stream, frame)`.
    in_flight: Option<(u64, u64)>,
    next_stream: u64,
    made: VecDeque<MadeFrame>,
}

enum ServerState {
    /// Connected; no hello yet.
    Waiting,
    Serving(Box<Serving>),
    /// Frames have stopped and a goodbye is on its way: the connection closes at this
    /// time (the shell's `last_word` waits up to 250 ms).
    Closing(Duration),
    Closed,
}

struct ServerSide {
    state: ServerState,
    control_in: InOrder,
    control_seq: u64,
    last_heard: Duration,
    /// The driver's vehicle, while the world has been told of it.
    joined: Option<VehicleId>,
}

struct ClientSide {
    hello: Hello,
    core: Option<ClientCore>,
    welcome: Option<Welcome>,
    /// The script's steps, for a driver.
    steps: Option<Vec<KeyStep>>,
    next_step: usize,
    next_key: Duration,
    control_in: InOrder,
    control_seq: u64,
    streams: BTreeMap<u64, Assembly>,
    /// Streams up to this one are complete or superseded.
    streams_done: Option<u64>,
    early: VecDeque<Vec<u8>>,
    /// The keys' half of the viewer's core (numbered states, history, latencies).
    keys: KeyCore,
    skip_decoding: u32,
    closed: Option<String>,
    last_heard: Duration,
}

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

/// The server's cores, the viewers' cores, and the links between them, in virtual time.
pub struct Sim {
    epoch: Instant,
    now: Duration,
    seed: u64,
    terrain: Arc<Terrain>,
    variance: VarianceTree,
    height_step: u16,
    world: WorldCore<Vec<u8>>,
    snapshot: Snapshot,
    next_tick: Duration,
    viewers: Vec<Viewer>,
}

/// A 64-bit FNV-1a of a mesh's vertices and indices.
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
    eat(&(indices.len() as u64).to_le_bytes());
    for i in indices {
        eat(&i.to_le_bytes());
    }
    h
}

fn welcome(terrain: &Terrain, vehicle: VehicleId, tick: u64) -> Welcome {
    let m = &terrain.map;
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
        color_cells: terrain.color.cells(),
        color_bytes: 0,
        tick,
    }
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
                streams_done: None,
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
    /// at the viewers, the viewers' keys, takes and control messages, and the links send.
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

    /// Everything that reached the server by `now`, in the order it arrived (over all
    /// viewers).
    fn server_receive(&mut self, now: Duration) {
        let mut arrivals = Vec::new();
        for (i, v) in self.viewers.iter_mut().enumerate() {
            for (k, (at, p)) in v.up.arrived(now).into_iter().enumerate() {
                arrivals.push((at, i, k, p));
            }
        }
        arrivals.sort_by_key(|(at, i, k, _)| (*at, *i, *k));
        for (at, i, _, payload) in arrivals {
            let instant = self.at(at);
            let v = &mut self.viewers[i];
            if matches!(v.server.state, ServerState::Closed) {
                continue;
            }
            v.server.last_heard = at;
            if matches!(v.server.state, ServerState::Closing(_)) {
                continue;
            }
            match payload {
                Payload::Datagram(bytes) => {
                    let ServerState::Serving(s) = &mut v.server.state else {
                        continue;
                    };
                    if let Some(event) = s.gate.admit(&bytes, instant)
                        && s.driver
                    {
                        self.world.handle(event);
                    }
                }
                Payload::Control { seq, bytes } => {
                    for msg in v.server.control_in.accept(seq, bytes) {
                        self.server_control(i, now, &msg);
                    }
                }
                Payload::Chunk { .. } => {}
                Payload::Close => self.server_close(i, now, None),
            }
        }
    }

    /// A control message in order at the server.
    fn server_control(&mut self, i: ViewerId, now: Duration, bytes: &[u8]) {
        let Ok(msg) = messages::decode::<ClientMessage>(bytes) else {
            self.server_close(i, now, None); // not the protocol: the stream ends
            return;
        };
        let v = &mut self.viewers[i];
        match &mut v.server.state {
            ServerState::Closed | ServerState::Closing(_) => {}
            ServerState::Serving(s) => {
                if matches!(msg, ClientMessage::KeyFrame) {
                    v.stats.key_frame_requests += 1;
                }
                if s.mailbox.push(msg) == Control::End {
                    self.server_close(i, now, None);
                }
            }
            ServerState::Waiting => {
                let ClientMessage::Hello(hello) = msg else {
                    self.server_close(i, now, None);
                    return;
                };
                if hello.version != VERSION {
                    let refused = ServerMessage::Refused(Reason::Version { server: VERSION });
                    self.server_close(i, now, Some(refused));
                    return;
                }
                let (vehicle, driver) = match hello.role {
                    Role::Driver => match self.world.handle(world_core::Event::Join) {
                        Some(id) => {
                            v.server.joined = Some(id);
                            (id, true)
                        }
                        None => {
                            let why = Reason::Unavailable("no room".into());
                            self.server_close(i, now, Some(ServerMessage::Refused(why)));
                            return;
                        }
                    },
                    Role::Spectator { follow } => {
                        let target = match follow {
                            Some(id) => self.snapshot.vehicles.iter().find(|v| v.id == id),
                            None => self.snapshot.vehicles.first(),
                        };
                        match target {
                            Some(t) => (t.id, false),
                            None => {
                                let why = Reason::Unavailable("no vehicle to follow".into());
                                self.server_close(i, now, Some(ServerMessage::Refused(why)));
                                return;
                            }
                        }
                    }
                };
                let w = welcome(&self.terrain, vehicle, self.snapshot.tick);
                server_control_send(v, now, &ServerMessage::Welcome(w));
                let core = ViewerCore::new(
                    self.terrain.heights.levels(),
                    self.height_step,
                    hello.fov_y_deg,
                    hello.viewport,
                    hello.budget,
                );
                let rate = hello.frame_rate.clamp(1, 240);
                v.server.state = ServerState::Serving(Box::new(Serving {
                    core,
                    mailbox: Mailbox::default(),
                    gate: KeyGate::new(vehicle),
                    vehicle,
                    driver,
                    seen: false,
                    period: Duration::from_secs_f64(1.0 / f64::from(rate)),
                    next_frame: now,
                    in_flight: None,
                    next_stream: 0,
                    made: VecDeque::new(),
                }));
            }
        }
    }

    /// The server ends viewer `i`'s connection: its core goes, and (once a last word, a
    /// refusal or a goodbye, if any, has had [`LAST_WORD`] to arrive) the connection closes and the world is told
    /// its driver left.
    fn server_close(&mut self, i: ViewerId, now: Duration, last: Option<ServerMessage>) {
        let v = &mut self.viewers[i];
        match (&v.server.state, last) {
            (ServerState::Closed, _) => {}
            (ServerState::Closing(until), _) if now < *until => {}
            (ServerState::Waiting | ServerState::Serving(_), Some(msg)) => {
                v.server.state = ServerState::Closing(now + LAST_WORD);
                server_control_send(v, now, &msg);
            }
            _ => {
                v.server.state = ServerState::Closed;
                v.down.close();
                v.down.send(now, Payload::Close);
                if let Some(id) = v.server.joined.take() {
                    self.world.handle(world_core::Event::Leave(id));
                }
            }
        }
    }

    fn tick(&mut self) {
        self.snapshot = self.world.tick().expect("no recording to fail");
        for v in &mut self.viewers {
            let ServerState::Serving(s) = &v.server.state else {
                continue;
            };
            if !s.driver {
                continue;
            }
            if let Some(veh) = self.snapshot.vehicles.iter().find(|x| x.id == s.vehicle) {
                v.track.push(TrackPoint {
                    tick: self.snapshot.tick,
                    applied: self.snapshot.applied_by(s.vehicle),
                    state: veh.state,
                });
            }
        }
    }

    /// Viewer `i`'s server side at `now`: the idle timeout, and a frame if one is due.
    fn server_frames(&mut self, i: ViewerId, now: Duration) {
        let v = &mut self.viewers[i];
        let idle = now.saturating_sub(v.server.last_heard) >= IDLE_TIMEOUT;
        match v.server.state {
            ServerState::Closed => return,
            ServerState::Closing(until) if now >= until => {
                self.server_close(i, now, None);
                return;
            }
            _ if idle => {
                self.server_close(i, now, None);
                return;
            }
            _ => {}
        }
        let ServerState::Serving(s) = &mut v.server.state else {
            return;
        };
        if now < s.next_frame {
            return;
        }
        // The shell's interval, missed ticks skipped.
        s.next_frame += s.period;
        while s.next_frame <= now {
            s.next_frame += s.period;
        }
        let Some(veh) = self.snapshot.vehicles.iter().find(|x| x.id == s.vehicle) else {
            if s.seen {
                let why = Reason::Unavailable("the vehicle followed has left".into());
                self.server_close(i, now, Some(ServerMessage::Bye(why)));
            }
            return; // a new driver's vehicle appears with the next tick
        };
        s.seen = true;
        for event in s.mailbox.drain() {
            s.core.handle(event);
        }
        let scene = Scene {
            terrain: &self.terrain,
            variance: &self.variance,
        };
        let made = s.core.make_frame(&scene, &veh.state);
        let acked = s.core.acked();
        let frame = made.frame;
        let key = made.base.is_none();
        let triangles = made.triangles as usize;
        let mut mesh = Mesh::default();
        s.core.mesh(&mut mesh);
        s.made.push_back(MadeFrame {
            frame,
            key,
            triangles,
            mesh: mesh_hash(&mesh.vertices, &mesh.indices),
        });
        while s.made.len() > MADE_KEPT {
            s.made.pop_front();
        }
        v.stats.frames_made += 1;
        v.stats.key_frames_made += u64::from(key);
        let msg = frame_message(&self.terrain, &self.snapshot, made, s.vehicle, s.driver);
        let mut bytes = Vec::new();
        if messages::encode(&msg, &mut bytes).is_err() {
            let why = Reason::Unavailable("a frame over the message limit".into());
            self.server_close(i, now, Some(ServerMessage::Bye(why)));
            return;
        }
        // Latest frame wins: the stream in flight is reset unless its frame was
        // acknowledged.
        if let Some((stream, sent)) = s.in_flight.take()
            && acked.is_none_or(|a| a < sent)
        {
            v.down.reset(stream);
            v.stats.streams_reset += 1;
        }
        v.stats.largest_frame = v.stats.largest_frame.max(bytes.len());
        if bytes.len() <= MAX_DATAGRAM {
            v.stats.datagram_frames += 1;
            v.down.send(now, Payload::Datagram(bytes));
            return;
        }
        v.stats.stream_frames += 1;
        let stream = s.next_stream;
        s.next_stream += 1;
        let count = bytes.len().div_ceil(MAX_DATAGRAM) as u32;
        for (index, chunk) in bytes.chunks(MAX_DATAGRAM).enumerate() {
            v.down.send(
                now,
                Payload::Chunk {
                    stream,
                    index: index as u32,
                    count,
                    bytes: chunk.to_vec(),
                },
            );
        }
        s.in_flight = Some((stream, frame));
    }

    /// Viewer `i`'s client side at `now`: arrivals, the idle timeout, keys, a take, and
    /// control messages.
    fn client_step(&mut self, i: ViewerId, now: Duration) {
        let epoch = self.epoch;
        let v = &mut self.viewers[i];
        let arrivals = v.down.arrived(now);
        if v.client.closed.is_some() {
            return;
        }
        for (at, payload) in arrivals {
            v.client.last_heard = at;
            match payload {
                Payload::Datagram(bytes) => client_offer(v, epoch + at, bytes),
                Payload::Chunk {
                    stream,
                    index,
                    count,
                    bytes,
                } => {
                    if v.client.streams_done.is_some_and(|d| stream <= d) {
                        continue;
                    }
                    let a = v.client.streams.entry(stream).or_insert_with(|| Assembly {
                        parts: vec![None; count as usize],
                        have: 0,
                    });
                    let Some(slot) = a.parts.get_mut(index as usize) else {
                        continue;
                    };
                    if slot.is_none() {
                        *slot = Some(bytes);
                        a.have += 1;
                    }
                    if a.have == a.parts.len() {
                        let a = v.client.streams.remove(&stream).expect("just found");
                        let whole: Vec<u8> = a.parts.into_iter().flatten().flatten().collect();
                        // Older streams are superseded: the core would drop their frames.
                        v.client.streams.retain(|&s, _| s > stream);
                        v.client.streams_done = Some(stream);
                        v.stats.streams_completed += 1;
                        client_offer(v, epoch + at, whole);
                    }
                }
                Payload::Control { seq, bytes } => {
                    for msg in v.client.control_in.accept(seq, bytes) {
                        match messages::decode::<ServerMessage>(&msg) {
                            Ok(ServerMessage::Welcome(w)) => {
                                let core = ClientCore::new(&w, v.client.hello.budget)
                                    .expect("the welcome's grid is one the protocol has");
                                v.client.core = Some(core);
                                v.client.welcome = Some(w);
                                v.client.next_key = now;
                                for bytes in std::mem::take(&mut v.client.early) {
                                    client_offer(v, epoch + at, bytes);
                                }
                            }
                            Ok(ServerMessage::ColorMap { .. }) => {}
                            Ok(ServerMessage::Refused(r) | ServerMessage::Bye(r)) => {
                                v.client.closed = Some(format!("{r:?}"));
                            }
                            Err(e) => v.client.closed = Some(format!("control stream: {e}")),
                        }
                    }
                }
                Payload::Close => {
                    v.client
                        .closed
                        .get_or_insert_with(|| "the server closed the connection".into());
                }
            }
        }
        if v.client.closed.is_none() && now.saturating_sub(v.client.last_heard) >= IDLE_TIMEOUT {
            v.client.closed = Some("idle timeout".into());
        }
        if v.client.closed.is_some() {
            v.up.close();
            return;
        }
        let Some(core) = v.client.core.as_mut() else {
            return;
        };
        // A key datagram every 10 ms.
        if let Some(steps) = &v.client.steps {
            while v.client.next_key <= now {
                let step = steps.get(v.client.next_step).copied().unwrap_or(KeyStep {
                    held: Keys::NONE,
                    pressed: Keys::NONE,
                });
                v.client.next_step += 1;
                let datagram = v.client.keys.key_datagram(step, epoch + now);
                v.up.send(now, Payload::Datagram(encoded!(&datagram)));
                v.stats.key_datagrams += 1;
                v.client.next_key += TICK;
            }
        }
        if core.has_frame() {
            let decode = v.client.skip_decoding == 0;
            v.client.skip_decoding = v.client.skip_decoding.saturating_sub(1);
            match core.take(decode) {
                Ok(Taken::Frame(mut r)) => {
                    if let Some(seq) = r.input_seq {
                        r.latencies_ms = v.client.keys.applied(seq, r.arrived);
                        v.stats.key_latencies_ms.extend(&r.latencies_ms);
                    }
                    let made = match &v.server.state {
                        ServerState::Serving(s) => {
                            s.made.iter().find(|m| m.frame == r.frame).copied()
                        }
                        _ => None,
                    };
                    let key = made.is_some_and(|m| m.key);
                    if decode && let Some(m) = made {
                        let mesh = core.mesh();
                        v.stats.meshes_checked += 1;
                        let same = mesh.triangle_count() == m.triangles
                            && mesh_hash(&mesh.vertices, &mesh.indices) == m.mesh;
                        v.stats.mesh_mismatches += u64::from(!same);
                    }
                    let st = &mut v.stats;
                    st.frames += 1;
                    st.key_frames += u64::from(key);
                    st.max_triangles = st.max_triangles.max(r.triangles);
                    if let Some(last) = st.last_frame_at {
                        st.largest_gap = st.largest_gap.max(now - last);
                    }
                    st.first_frame_at.get_or_insert(now);
                    st.last_frame_at = Some(now);
                    v.taken.push(TakenFrame {
                        at: now,
                        frame: r.frame,
                        tick: r.tick,
                        triangles: r.triangles,
                        key,
                        decoded: decode,
                    });
                    v.latest = Some(r);
                }
                Ok(Taken::Nothing) => {}
                Ok(Taken::Dropped(why)) => {
                    v.stats.decode_errors += 1;
                    v.dropped.push(format!("{now:?}: {why}"));
                }
                Err(e) => {
                    v.stats.inconsistent += 1;
                    v.dropped.push(format!("{now:?}: {e}"));
                }
            }
        }
        client_flush(v, now);
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

    /// Viewer `i`'s links carry nothing (either way, packets on the way included) for `d`.
    pub fn cut_link(&mut self, i: ViewerId, d: Duration) {
        let until = self.now.saturating_add(d);
        let v = &mut self.viewers[i];
        v.up.down_until = v.up.down_until.max(until);
        v.down.down_until = v.down.down_until.max(until);
    }

    /// Viewer `i`'s link to the server carries nothing (packets on the way included) for
    /// `d`; the link back works.
    pub fn cut_up(&mut self, i: ViewerId, d: Duration) {
        let until = self.now.saturating_add(d);
        let v = &mut self.viewers[i];
        v.up.down_until = v.up.down_until.max(until);
    }

    /// Viewer `i`'s links carry nothing, ever again.
    pub fn kill_link(&mut self, i: ViewerId) {
        self.cut_link(i, Duration::MAX);
    }

    /// Viewer `i`'s links are now `path` (packets on the way keep their arrival times).
    pub fn set_path(&mut self, i: ViewerId, path: Path) {
        let v = &mut self.viewers[i];
        v.up.link = path.up;
        v.down.link = path.down;
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

/// Viewer `v`'s frame bytes arrived at `at`: to the core, or kept until the welcome.
fn client_offer(v: &mut Viewer, at: Instant, bytes: Vec<u8>) {
    match v.client.core.as_mut() {
        Some(core) => core.offer(&bytes, at),
        None => {
            v.client.early.push_back(bytes);
            while v.client.early.iter().map(Vec::len).sum::<usize>() > EARLY_BYTES {
                v.client.early.pop_front();
            }
        }
    }
}

/// The viewer sends what its core has for the control stream.
fn client_flush(v: &mut Viewer, now: Duration) {
    while let Some(m) = v.client.core.as_mut().and_then(ClientCore::poll_control) {
        client_control(v, now, &m);
    }
}

fn client_control(v: &mut Viewer, now: Duration, msg: &ClientMessage) {
    let seq = v.client.control_seq;
    v.client.control_seq += 1;
    v.up.send(
        now,
        Payload::Control {
            seq,
            bytes: encoded!(msg),
        },
    );
}

fn server_control_send(v: &mut Viewer, now: Duration, msg: &ServerMessage) {
    let seq = v.server.control_seq;
    v.server.control_seq += 1;
    v.down.send(
        now,
        Payload::Control {
            seq,
            bytes: encoded!(msg),
        },
    );
}
