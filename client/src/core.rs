//! The viewer's connection logic, with no socket, task or clock (as `quinn-proto` is to
//! `quinn`): the newest frame waiting, the bases frames are coded against, decoding,
//! acknowledgements and key-frame requests, the triangle budget, and the keys (the latch,
//! the numbered states and the history each datagram repeats). Time comes in as a
//! parameter. `session.rs` is the I/O around it (QUIC, tasks, the clock); the window, the
//! headless viewer and `--bench` all take frames through it, and the simulated network
//! in the tests drives this core directly.
//!
//! What leaves the core: control messages ([`ClientCore::poll_control`], for the control
//! stream, in order) and key datagrams ([`KeyCore::key_datagram`], one per physics step).
//!
//! The core has two halves, [`ClientCore`] (frames) and [`KeyCore`] (keys), so the I/O can
//! lock them apart: a key state must leave every 10 ms even while a frame is being
//! decoded. With one lock, a decode preempted on a loaded machine held the key sender past
//! the server's one tick of slack, and the exact drive over the network diverged (seen in
//! `tests/tests/e2e.rs` with the CPU saturated).

use std::collections::VecDeque;
use std::time::Instant;

use roam_protocol::keys::{KeyLatch, KeyStep, Keys};
use roam_protocol::messages::{
    self, ClientMessage, Frame, KeyDatagram, KeyState, VehicleView, ViewChange, Welcome,
};
use roam_protocol::{Cut, Grid, MeshDecoder, mesh};

/// Decoded frames kept as bases: the server codes against the newest one acknowledged,
/// which is at most a round trip old.
pub const BASES: usize = 32;

/// Key changes awaiting the frame that shows them applied (a spectator's never are).
const MAX_PENDING: usize = 1024;

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
    /// Nothing newer than the last frame taken.
    Nothing,
    /// A frame, decoded (unless asked not to) and acknowledged.
    Frame(Received),
    /// A frame that could not be decoded (bytes that are not a frame, a base this viewer
    /// never had, a payload that fails its checks): a key frame has been asked for.
    Dropped(String),
}

/// The mesh of a frame disagrees with its own header: the server is broken.
#[derive(Debug, thiserror::Error)]
#[error("frame {frame}: {emitted} triangles emitted, the header says {header}")]
pub struct Inconsistent {
    pub frame: u64,
    pub emitted: usize,
    pub header: u32,
}

/// One joined viewer's state.
pub struct ClientCore {
    grid: Grid,
    decoder: MeshDecoder,
    /// Cuts of recent frames: the bases the server may code against, oldest first.
    bases: VecDeque<(u64, Cut)>,
    /// The newest frame taken.
    newest: Option<u64>,
    /// The newest frame offered and not yet taken, its size on the wire and arrival.
    waiting: Option<(Frame, usize, Instant)>,
    /// Bytes offered that were not a frame, not yet reported.
    junk: Option<String>,
    /// The newest frame number offered (frames older than it are superseded).
    offered: Option<u64>,
    mesh: mesh::Mesh,
    budget: u32,
    /// The largest budget asked for: frames tessellated before a cut may still come.
    limit: u32,
    outbox: VecDeque<ClientMessage>,
    bytes_in: u64,
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
            decoder: MeshDecoder::new(grid),
            bases: VecDeque::new(),
            newest: None,
            waiting: None,
            junk: None,
            offered: None,
            mesh: mesh::Mesh::default(),
            budget,
            limit: budget,
            outbox: VecDeque::new(),
            bytes_in: 0,
        })
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The newest decoded mesh.
    pub fn mesh(&self) -> &mesh::Mesh {
        &self.mesh
    }

    /// Takes the newest decoded mesh, leaving an empty one.
    pub fn take_mesh(&mut self) -> mesh::Mesh {
        std::mem::take(&mut self.mesh)
    }

    pub fn budget(&self) -> u32 {
        self.budget
    }

    /// Frame bytes received so far (frames superseded or dropped included).
    pub fn bytes_in(&self) -> u64 {
        self.bytes_in
    }

    /// A frame's bytes arrived at `now` (a datagram, or a stream read to its end): it
    /// waits to be taken if it is the newest yet; an older one is superseded.
    pub fn offer(&mut self, bytes: &[u8], now: Instant) {
        self.bytes_in += bytes.len() as u64;
        match messages::decode::<Frame>(bytes) {
            Ok(frame) => {
                if self.offered.is_some_and(|n| frame.frame <= n) {
                    return; // older than one already offered: superseded
                }
                self.offered = Some(frame.frame);
                self.waiting = Some((frame, bytes.len(), now));
            }
            Err(e) => {
                self.junk.get_or_insert_with(|| format!("not a frame: {e}"));
            }
        }
    }

    /// Whether [`Self::take`] has something to say.
    pub fn has_frame(&self) -> bool {
        self.waiting.is_some() || self.junk.is_some()
    }

    /// Takes the waiting frame; decodes it into [`Self::mesh`] (unless `decode` is false)
    /// against its base, and acknowledges it. A frame that cannot be decoded asks for a key
    /// frame. An error only for a frame inconsistent with itself (the server is broken).
    pub fn take(&mut self, decode: bool) -> Result<Taken, Inconsistent> {
        if let Some(why) = self.junk.take() {
            self.request_key_frame();
            return Ok(Taken::Dropped(why));
        }
        let Some((frame, wire_bytes, arrived)) = self.waiting.take() else {
            return Ok(Taken::Nothing);
        };
        if self.newest.is_some_and(|n| frame.frame <= n) {
            return Ok(Taken::Nothing);
        }
        let mut triangles = 0;
        if decode {
            let base = match frame.base {
                Some(b) => match self.bases.iter().find(|(f, _)| *f == b) {
                    Some((_, cut)) => Some(cut),
                    None => {
                        self.request_key_frame();
                        return Ok(Taken::Dropped(format!(
                            "frame {}: coded against frame {b}, which this viewer does not have",
                            frame.frame
                        )));
                    }
                },
                None => None,
            };
            let mut cut = Cut::default();
            let info = match self
                .decoder
                .decode_cut(&frame.mesh, base, self.limit, &mut cut)
            {
                Ok(info) => info,
                Err(e) => {
                    self.request_key_frame();
                    return Ok(Taken::Dropped(format!("frame {}: {e}", frame.frame)));
                }
            };
            mesh::emit(
                &self.grid,
                &cut.split,
                self.decoder.heights(),
                &mut self.mesh,
            );
            triangles = self.mesh.triangle_count();
            if triangles != info.triangles as usize {
                return Err(Inconsistent {
                    frame: frame.frame,
                    emitted: triangles,
                    header: info.triangles,
                });
            }
            self.bases.push_back((frame.frame, cut));
            if self.bases.len() > BASES {
                self.bases.pop_front();
            }
        }
        self.outbox
            .push_back(ClientMessage::Ack { frame: frame.frame });
        self.newest = Some(frame.frame);
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
        // One request is enough until the key frame comes: the server sends key frames
        // until one is acknowledged.
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
    /// and the [`messages::KEY_HISTORY`] before it (a lost datagram loses nothing).
    pub fn key_datagram(&mut self, step: KeyStep, now: Instant) -> KeyDatagram {
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
