//! The messages between a roam server and its viewers, and their byte encoding (bincode 2
//! over serde, standard configuration: little-endian varints).
//!
//! Where they travel (see ARCHITECTURE.md, "Bird's-eye view"):
//!
//! - the **control stream** (reliable, ordered, one per connection): [`ClientMessage`]s one
//!   way, [`ServerMessage`]s the other, each preceded by its length as a `u32`;
//! - **key-state datagrams** ([`KeyDatagram`]): the latest key states, repeated, so a lost
//!   datagram costs nothing and a transient press survives, and a driver's acknowledgement
//!   of the newest frame it decoded;
//! - **frames** ([`Frame`]): one QUIC datagram each when the frame fits one (nearly all
//!   change frames do), otherwise a unidirectional stream of its own, abandoned (reset)
//!   when a newer frame is ready first.
//!
//! Every decode has a byte limit ([`Checked::MAX_BYTES`]), and every variable-length field
//! one of its own: the join token [`MAX_TOKEN`] bytes, a reason [`MAX_REASON`], a key
//! datagram [`KEY_HISTORY`] states, a frame [`MAX_VEHICLES`] vehicles, a colour or normal
//! tile [`MAX_TILE_BYTES`] bytes, a frame's mesh what the message holds. A length or count that
//! claims more than its limit is [`DecodeError::TooLong`], naming the field, before
//! anything is allocated for it; a list reserves little until its items arrive (see
//! `bounded`). Decoding borrows from the input, so no string or byte string is allocated
//! before its length has been checked. Bytes left over after a message are an error.

use serde::de::DeserializeOwned;
use serde::{Deserialize, Deserializer, Serialize};

use crate::bounded;
pub use crate::bounded::PREALLOC;
pub use crate::tiles::{ColorLayout, MAX_TILE_BYTES, MAX_WINDOW};

/// The protocol version this code speaks. 2: the colour map is sent compressed
/// ([`crate::colormap`]). 3: a frame's mesh may be a change frame (mesh format 2,
/// [`crate::changes`]). 4: a driver's welcome carries a resume ticket, and a hello may
/// present one to take its vehicle back after a dropped connection ([`Hello::resume`]);
/// a full server says so ([`Reason::Full`]). 5: the colour map is streamed by view as
/// tiles of a pyramid ([`ColorLayout`], [`ServerMessage::ColorWindow`],
/// [`ServerMessage::ColorTile`]) instead of whole; a hello says the window it can hold
/// ([`Hello::color_window`]). 6: an edge server (`roam-server edge`) tells its viewers
/// how the world behind it stands and where the world's other edges are
/// ([`ServerMessage::World`]). 7: a view change says whether the viewer draws its fog
/// ([`ViewChange::fog`]): the server weighs far errors by the fog only while it does; and
/// each colour tile's normals follow it ([`ServerMessage::NormalTile`],
/// [`crate::normals`]), for lighting per pixel. 8: a spectator may follow another vehicle
/// ([`ClientMessage::Follow`], [`ServerMessage::Following`]), and a server serving a
/// recording (`serve --replay`) says how it stands and takes its controls
/// ([`ServerMessage::Replay`], [`ClientMessage::Replay`]). 9: a key datagram may carry the
/// frame acknowledgement ([`KeyDatagram::acked`]), so a driver sends no [`ClientMessage::Ack`].
pub const VERSION: u16 = 9;
/// The largest message (a frame with its mesh).
pub const MAX_MESSAGE: usize = 16 << 20;
/// The largest key datagram.
pub const MAX_DATAGRAM: usize = 256;
/// Longest join token, bytes.
pub const MAX_TOKEN: usize = 128;
/// Key states a datagram repeats.
pub const KEY_HISTORY: usize = 8;
/// Longest reason ([`Reason::Protocol`], [`Reason::Unavailable`]), bytes.
pub const MAX_REASON: usize = 1024;
/// The most vehicles a frame lists: one per vehicle id (`u16`).
pub const MAX_VEHICLES: usize = 1 << 16;
/// The fewest and the most triangles a viewer may ask for: one limit, kept by both ends
/// ([`clamp_budget`]).
pub const MIN_BUDGET: u32 = 2;
pub const MAX_BUDGET: u32 = 1 << 20;
/// The pitch of a viewer's camera before its first [`ViewChange`], degrees (slightly
/// down, as a driver looks); also the benchmarks' camera pitch.
pub const DEFAULT_PITCH_DEG: f64 = -5.0;

/// A triangle budget within [`MIN_BUDGET`]`..=`[`MAX_BUDGET`].
pub fn clamp_budget(budget: u32) -> u32 {
    budget.clamp(MIN_BUDGET, MAX_BUDGET)
}

/// The codes a connection is closed with (QUIC application close codes).
pub mod close {
    /// The server is shutting down.
    pub const SHUTDOWN: u32 = 1;
    /// The hello was refused (version, token, nothing to follow, the server is full).
    pub const REFUSED: u32 = 2;
    /// The peer broke the protocol (no hello, a malformed message).
    pub const PROTOCOL: u32 = 3;
    /// A goodbye: the server heard the viewer's, or said its own.
    pub const BYE: u32 = 4;
}

/// What a viewer does.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Role {
    /// Drives a vehicle of its own.
    Driver,
    /// Watches: follows vehicle `follow`, or the first one when `None`.
    Spectator { follow: Option<u16> },
}

/// The viewer's first message.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hello {
    pub version: u16,
    pub role: Role,
    /// The join token the server printed.
    #[serde(deserialize_with = "token")]
    pub token: String,
    /// Viewport in pixels, width and height.
    pub viewport: [u32; 2],
    /// Vertical field of view, degrees.
    pub fov_y_deg: f32,
    /// Most triangles per frame.
    pub budget: u32,
    /// Frames per second wanted.
    pub frame_rate: u16,
    /// The ticket of an earlier connection's welcome ([`Welcome::ticket`]): a driver whose
    /// connection dropped gets its vehicle back if the server still holds it.
    pub resume: Option<Ticket>,
    /// The colour window (tiles a side per level) this viewer can hold, 1 ..=
    /// [`MAX_WINDOW`]: the server uses the smaller of its own and this
    /// ([`ColorLayout::window`]).
    pub color_window: u8,
}

/// A driver's claim on its vehicle across a dropped connection: random, known only to the
/// server and that viewer.
pub type Ticket = [u8; 16];

/// The server's answer to a welcome viewer: the terrain's shape and look, and its vehicle.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Welcome {
    pub version: u16,
    /// The grid is `2^levels + 1` samples on a side.
    pub levels: u8,
    /// World units between samples, and per sample step.
    pub h_scale: f64,
    pub v_scale: f64,
    /// Towards the sun (unit), and its colour.
    pub sun_dir: [f32; 3],
    pub sun_color: [u8; 3],
    pub fog_density: f32,
    pub fog_color: [u8; 3],
    pub water_level: Option<f32>,
    /// The vehicle this viewer drives or follows.
    pub vehicle: u16,
    /// The colour map's tile pyramid: its coarsest level's single tile follows the
    /// welcome, before the first frame; the other tiles stream as
    /// [`ServerMessage::ColorWindow`] and [`ServerMessage::ColorTile`].
    pub color: ColorLayout,
    /// The world's tick when the viewer joined.
    pub tick: u64,
    /// A driver's ticket, to present in the hello of a reconnection ([`Hello::resume`]).
    pub ticket: Option<Ticket>,
    /// The hello's ticket was honoured: this is the vehicle the viewer drove before.
    pub resumed: bool,
    /// The most triangles per frame and frames per second this server serves a viewer
    /// (a hello or budget asking more gets these).
    pub max_budget: u32,
    pub max_fps: u16,
}

/// Why a connection ends or is refused.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Reason {
    WrongToken,
    /// The other side speaks another protocol version.
    Version {
        server: u16,
    },
    /// The server is shutting down.
    Shutdown,
    /// The viewer quit.
    Quit,
    /// The viewer sent something that is not the protocol.
    Protocol(#[serde(deserialize_with = "reason")] String),
    /// No vehicle to follow, or no room.
    Unavailable(#[serde(deserialize_with = "reason")] String),
    /// The server serves `viewers` viewers, its limit.
    Full {
        viewers: u32,
    },
}

/// Viewer to server, on the control stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ClientMessage {
    Hello(Hello),
    /// A new triangle budget (`+` / `−`).
    Budget(u32),
    /// Frame `frame` decoded: the server may code later frames against it.
    Ack {
        frame: u64,
    },
    /// A frame failed to decode: send a key frame.
    KeyFrame,
    Bye(Reason),
    /// The viewer's camera changed (it damps its pitch over rough ground, its window was
    /// resized, its fog was turned on or off): tessellate for this view from now on.
    View(ViewChange),
    /// A spectator follows another vehicle (Tab, number keys): the server answers with
    /// [`ServerMessage::Following`] once its frames are made for it.
    Follow(u16),
    /// The one watching a recording steers its clock (`serve --replay`); from a viewer
    /// that does not hold the controls, ignored ([`ReplayStatus::control`]).
    Replay(ReplayControl),
}

/// What the one watching a recording asks of its clock.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ReplayControl {
    Pause,
    Resume,
    /// Speed in quarters: 1 (¼×) ..= 32 (8×); others are clamped.
    Speed(u8),
    /// To this world tick (clamped to the recording's valid part).
    Seek(u64),
    /// To the next join or leave after the clock (`true`), or the last before it.
    SeekMark {
        forward: bool,
    },
}

/// Where a watched recording stands, sent when it changes other than by its clock running
/// (the clock is each frame's tick).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ReplayStatus {
    /// The clock when this was sent.
    pub tick: u64,
    /// The recording's valid part, first and last tick.
    pub start: u64,
    pub end: u64,
    /// Quarters (4: 1×).
    pub speed: u8,
    pub paused: bool,
    /// This viewer holds the controls.
    pub control: bool,
    /// Who holds them, in words (a peer's address, or none yet).
    #[serde(deserialize_with = "reason")]
    pub controller: String,
}

/// How the viewer's camera differs from the default one at the followed vehicle.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ViewChange {
    /// Degrees, positive looking up.
    pub pitch_deg: f32,
    /// The eye's height above the vehicle's hover altitude, world units.
    pub eye_above: f32,
    /// Window size, pixels.
    pub viewport: [u32; 2],
    /// The viewer draws its fog (key `f` toggles it). While it does, the server spends
    /// less of the budget where the fog hides the error; while it does not, the fog must
    /// not lower any priority. Before the first view change the server assumes it does.
    pub fog: bool,
}

/// Server to viewer, on the control stream.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ServerMessage {
    Welcome(Welcome),
    /// From now on the viewer keeps, of colour level `level`, the tiles `x0 .. x0 + W` ×
    /// `z0 .. z0 + W` (`W` = [`ColorLayout::window`]) and drops the others. Only for
    /// levels larger than a window ([`ColorLayout::windowed`]); a level's window starts
    /// at `(0, 0)`.
    ColorWindow {
        level: u8,
        x0: u32,
        z0: u32,
    },
    /// Tile `(x, z)` of colour level `level`, coded by [`crate::colormap`] (its side is
    /// [`ColorLayout::tile_side`]); always inside the level's current window.
    ColorTile {
        level: u8,
        x: u32,
        z: u32,
        #[serde(deserialize_with = "tile")]
        data: Vec<u8>,
    },
    Refused(Reason),
    Bye(Reason),
    /// News of the world behind an edge server (never sent by `serve`).
    World(WorldNews),
    /// The normals of tile `(x, z)` of level `level` ([`crate::normals::encode_tile`]: a
    /// code per texel, the colour tile's side), right after that tile's
    /// [`ServerMessage::ColorTile`] (the coarsest tile's after the first frame); held and
    /// dropped with it, by the same windows.
    NormalTile {
        level: u8,
        x: u32,
        z: u32,
        #[serde(deserialize_with = "normal_tile")]
        data: Vec<u8>,
    },
    /// The vehicle this spectator's frames follow from now on (after a
    /// [`ClientMessage::Follow`], or when the one followed left a watched recording).
    Following(u16),
    /// A watched recording's state (`serve --replay`): at the welcome, then when it
    /// changes.
    Replay(ReplayStatus),
}

/// What an edge server says of its world ([`ServerMessage::World`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum WorldNews {
    /// The world does not answer (why, in words): frames go on showing it as last seen,
    /// and the edge keeps trying.
    Gone(#[serde(deserialize_with = "reason")] String),
    /// The world answers again, after [`WorldNews::Gone`].
    Back,
    /// The world's edges, this one included, where a viewer may connect again: `host:port`
    /// for a native viewer's QUIC, `https://host:port` for the page's WebTransport.
    Edges(#[serde(deserialize_with = "edge_list")] Vec<String>),
}

/// The most edge addresses in [`WorldNews::Edges`].
pub const MAX_EDGES: usize = 64;

/// The longest edge address.
pub const MAX_ADDRESS: usize = 256;

/// A vehicle as the viewer sees it.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct VehicleView {
    pub id: u16,
    pub x: f64,
    pub z: f64,
    /// Altitude (ground plus 2).
    pub y: f64,
    pub speed: f64,
    pub heading: f64,
}

/// One frame, on a stream of its own.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Frame {
    /// Rises by one per frame sent to this viewer.
    pub frame: u64,
    /// The frame the mesh is coded against (one the viewer acknowledged, or the newest key
    /// frame, sent reliably); `None` for a key frame.
    pub base: Option<u64>,
    /// The world tick the frame shows.
    pub tick: u64,
    #[serde(deserialize_with = "vehicles")]
    pub vehicles: Vec<VehicleView>,
    /// The newest key state of this viewer the world had applied by `tick` (drivers).
    pub input_seq: Option<u32>,
    /// The mesh, in the codec's format ([`crate::codec`]).
    #[serde(deserialize_with = "crate::bounded::bytes")]
    pub mesh: Vec<u8>,
}

/// One key state: the keys held, and those pressed since the previous state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeyState {
    /// Rises by one per state the viewer samples.
    pub seq: u32,
    /// Bits: Up, Down, Left, Right.
    pub held: u8,
    pub pressed: u8,
}

/// The viewer's latest key states, newest first, at most [`KEY_HISTORY`], and the newest
/// frame it decoded.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct KeyDatagram {
    #[serde(deserialize_with = "key_states")]
    pub states: Vec<KeyState>,
    /// The newest frame decoded, as [`ClientMessage::Ack`] says it; `None` from a viewer
    /// that acknowledges on the control stream. A driver's datagrams go 100 a second and
    /// each repeats it, so a lost one costs nothing: its frames need no control message (60
    /// a second of a server's received packets, each decrypted and acknowledged, and a
    /// wake of the viewer's reader). Unordered with the control stream: an
    /// acknowledgement older than a key-frame request reaches the server after it at
    /// times, and the server takes none of a frame made before the request.
    pub acked: Option<u64>,
}

/// Why bytes are not a message.
#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    #[error("{0}")]
    Bincode(#[from] bincode::error::DecodeError),
    #[error("{extra} bytes after the message")]
    Trailing { extra: usize },
    #[error("{what}: {got}, at most {limit}")]
    TooLong {
        what: &'static str,
        got: usize,
        limit: usize,
    },
}

/// Why a message could not be encoded.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct EncodeError(#[from] bincode::error::EncodeError);

fn config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<MAX_MESSAGE>()
}

/// Appends `msg` to `out`.
pub fn encode<T: Serialize>(msg: &T, out: &mut Vec<u8>) -> Result<(), EncodeError> {
    bincode::serde::encode_into_std_write(msg, out, config())?;
    Ok(())
}

/// One message as it goes on a stream: its length (`u32`, little-endian), then its bytes.
pub fn frame<T: Serialize>(msg: &T) -> Result<Vec<u8>, EncodeError> {
    let mut buf = vec![0u8; 4];
    encode(msg, &mut buf)?;
    let len = (buf.len() - 4) as u32;
    buf[..4].copy_from_slice(&len.to_le_bytes());
    Ok(buf)
}

/// Decodes a whole message from `bytes` (nothing may follow it). Strings and byte
/// strings are read from the slice itself, and every length is checked against its
/// field's limit before anything is allocated for it.
pub fn decode<T: DeserializeOwned + Checked>(bytes: &[u8]) -> Result<T, DecodeError> {
    at_most("message bytes", bytes.len(), T::MAX_BYTES)?;
    // Nothing left over from an earlier decode on this thread (one that panicked).
    bounded::take_refusal();
    let decoded = bincode::serde::borrow_decode_from_slice::<T, _>(bytes, config());
    let refusal = bounded::take_refusal();
    let (msg, used) = match (decoded, refusal) {
        (Ok(decoded), _) => decoded,
        (Err(_), Some(r)) => {
            return Err(DecodeError::TooLong {
                what: r.what,
                got: r.got,
                limit: r.limit,
            });
        }
        (Err(e), None) => return Err(e.into()),
    };
    if used != bytes.len() {
        return Err(DecodeError::Trailing {
            extra: bytes.len() - used,
        });
    }
    Ok(msg)
}

/// The longest encoding of a message that [`decode`] accepts.
pub trait Checked {
    const MAX_BYTES: usize = MAX_MESSAGE;
}

fn at_most(what: &'static str, got: usize, limit: usize) -> Result<(), DecodeError> {
    if got > limit {
        return Err(DecodeError::TooLong { what, got, limit });
    }
    Ok(())
}

impl Checked for ClientMessage {}
impl Checked for ServerMessage {}
impl Checked for Frame {}

impl Checked for KeyDatagram {
    const MAX_BYTES: usize = MAX_DATAGRAM;
}

// The bounded fields' readers (`#[serde(deserialize_with)]` above): each field's name, as
// errors give it, and its limit.

fn token<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    bounded::string(d, "join token bytes", MAX_TOKEN)
}

fn reason<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    bounded::string(d, "reason bytes", MAX_REASON)
}

/// At most [`MAX_EDGES`] addresses of at most [`MAX_ADDRESS`] bytes each.
pub(crate) fn edge_list<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<String>, D::Error> {
    #[derive(Deserialize)]
    struct Address(#[serde(deserialize_with = "address")] String);
    fn address<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
        bounded::string(d, "address bytes", MAX_ADDRESS)
    }
    let list: Vec<Address> = bounded::list(d, "addresses", MAX_EDGES)?;
    Ok(list.into_iter().map(|a| a.0).collect())
}

fn tile<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
    bounded::list(d, "colour tile bytes", MAX_TILE_BYTES)
}

fn normal_tile<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u8>, D::Error> {
    bounded::list(d, "normal tile bytes", MAX_TILE_BYTES)
}

fn vehicles<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<VehicleView>, D::Error> {
    bounded::list(d, "vehicles", MAX_VEHICLES)
}

fn key_states<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<KeyState>, D::Error> {
    bounded::list(d, "key states", KEY_HISTORY)
}
