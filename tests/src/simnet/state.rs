//! The simulated network's state: the [`Sim`] and each [`Viewer`] in it (its two directions,
//! its server side and its client side, what it took), the harness's constants, and the
//! helpers both sides share. What the sides do is in `server.rs` and `client.rs`, what a
//! test does and reads in `sim.rs`.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::time::{Duration, Instant};

use roam_client::core::{ClientCore, KeyCore, Received};
use roam_protocol::keys::KeyStep;
use roam_protocol::messages::{self, Hello, Welcome};
use roam_server::Terrain;
use roam_server::sim::physics::VehicleState;
use roam_server::sim::world::VehicleId;
use roam_server::sim::world_core::{Snapshot, WorldCore};
use roam_server::terrain::variance::VarianceTree;
use roam_server::viewer::conversation::Conversation;

use super::path::{InOrder, Wire, WireStats};

/// The largest packet payload: a frame of at most this many bytes goes as a datagram, a
/// larger one in packets of this size on a stream (quinn's datagrams are about this big
/// on a 1,280-byte path MTU).
pub const MAX_DATAGRAM: usize = 1200;

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
pub(super) const MADE_KEPT: usize = 512;

/// Frame bytes a viewer keeps from before its welcome (quinn buffers them for the reader).
pub(super) const EARLY_BYTES: usize = 1 << 20;

/// A message's bytes (`messages::encode`; the messages here are all within its limits).
pub(super) fn encoded<T: serde::Serialize>(msg: &T) -> Vec<u8> {
    let mut out = Vec::new();
    messages::encode(msg, &mut out).expect("a message within the limits");
    out
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

pub(super) struct Viewer {
    pub(super) up: Wire,
    pub(super) down: Wire,
    pub(super) server: ServerSide,
    pub(super) client: ClientSide,
    pub(super) stats: Stats,
    pub(super) taken: Vec<TakenFrame>,
    pub(super) track: Vec<TrackPoint>,
    pub(super) latest: Option<Received>,
    pub(super) dropped: Vec<String>,
}

/// The server's cores, the viewers' cores, and the paths between them, in virtual time.
pub struct Sim {
    pub(super) epoch: Instant,
    pub(super) now: Duration,
    pub(super) seed: u64,
    pub(super) terrain: Arc<Terrain>,
    pub(super) variance: VarianceTree,
    pub(super) scratch: roam_server::tessellate::Scratch,
    pub(super) height_step: u16,
    pub(super) world: WorldCore,
    pub(super) snapshot: Arc<Snapshot>,
    pub(super) next_tick: Duration,
    pub(super) viewers: Vec<Viewer>,
}

/// A 64-bit FNV-1a of a mesh: its vertices in order, its triangles as a set.
pub(super) fn mesh_hash(vertices: &[[u16; 2]], indices: &[u32]) -> u64 {
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

/// What the server remembers of a frame it made, to check what the viewer decodes.
#[derive(Clone, Copy, Debug)]
pub(super) struct MadeFrame {
    pub(super) frame: u64,
    pub(super) key: bool,
    pub(super) triangles: usize,
    pub(super) mesh: u64,
}

/// A viewer's connection as the server's shell holds it: its conversation, and the
/// stream each frame on one went on.
pub(super) struct Serving {
    pub(super) conv: Conversation,
    /// `(frame, stream)`, for the conversation's resets.
    pub(super) streams: Vec<(u64, u64)>,
    pub(super) next_stream: u64,
    pub(super) made: VecDeque<MadeFrame>,
}

pub(super) enum ServerState {
    /// Connected; no hello yet.
    Waiting,
    Serving(Box<Serving>),
    /// Frames have stopped and a goodbye is on its way: the connection closes at this
    /// time (the shell's `last_word` waits up to 250 ms).
    Closing(Duration),
    Closed,
}

pub(super) struct ServerSide {
    pub(super) state: ServerState,
    pub(super) control_in: InOrder,
    pub(super) control_seq: u64,
    pub(super) last_heard: Duration,
    /// The driver's vehicle, while the world has been told of it.
    pub(super) joined: Option<VehicleId>,
}

/// A frame stream being received.
pub(super) struct Assembly {
    pub(super) parts: Vec<Option<Vec<u8>>>,
    pub(super) have: usize,
}

pub(super) struct ClientSide {
    pub(super) hello: Hello,
    pub(super) core: Option<ClientCore>,
    pub(super) welcome: Option<Welcome>,
    /// The script's steps, for a driver.
    pub(super) steps: Option<Vec<KeyStep>>,
    pub(super) next_step: usize,
    pub(super) next_key: Duration,
    pub(super) control_in: InOrder,
    pub(super) control_seq: u64,
    /// Frame streams being read, each to its end (as `session.rs` reads each in a task of
    /// its own): one completes whatever streams after it have completed.
    pub(super) streams: BTreeMap<u64, Assembly>,
    pub(super) early: VecDeque<Vec<u8>>,
    /// The keys' half of the viewer's core (numbered states, history, latencies).
    pub(super) keys: KeyCore,
    pub(super) skip_decoding: u32,
    pub(super) closed: Option<String>,
    pub(super) last_heard: Duration,
}
