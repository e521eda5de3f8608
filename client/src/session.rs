//! One viewer's connection: the handshake, the colour map, and the frame stream decoded
//! newest-first; and key states sent as datagrams. The headless viewer and the window both
//! drive a [`Session`].

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use roam_protocol::messages::{
    self, ClientMessage, Frame, Hello, KeyDatagram, KeyState, Reason, ServerMessage, VehicleView,
    Welcome,
};
use roam_protocol::{Cut, Grid, MeshDecoder, mesh};
use roam_server::net::{tls, wire};
use roam_server::sim::physics::Keys;
use roam_server::sim::script::Script;

use crate::render::Scene;

/// Connects to `addr`, accepting only the certificate with SHA-256 `fingerprint`.
pub async fn connect(
    addr: SocketAddr,
    fingerprint: [u8; 32],
) -> Result<(quinn::Endpoint, quinn::Connection)> {
    let bind: SocketAddr = if addr.is_ipv4() {
        "0.0.0.0:0".parse().expect("a valid address")
    } else {
        "[::]:0".parse().expect("a valid address")
    };
    let mut endpoint = quinn::Endpoint::client(bind).context("opening a UDP socket")?;
    endpoint.set_default_client_config(tls::client_config(fingerprint)?);
    let conn = endpoint
        .connect(addr, "roam")
        .with_context(|| format!("connecting to {addr}"))?
        .await
        .with_context(|| format!("connecting to {addr}"))?;
    Ok((endpoint, conn))
}

/// How long a control message may take to leave (a server that stops reading does not
/// hold the viewer).
const CONTROL_TIMEOUT: Duration = Duration::from_secs(2);
/// How long the welcome and the colour map may take.
const JOIN_TIMEOUT: Duration = Duration::from_secs(30);
/// The largest frame message read: a key frame at the largest budget is under 2 MiB, and
/// 16 streams of this much bound what a server can make the viewer hold.
pub const MAX_FRAME: usize = 8 << 20;

/// Writes a control message, within [`CONTROL_TIMEOUT`].
async fn send_control(send: &mut quinn::SendStream, msg: &ClientMessage) -> Result<()> {
    tokio::time::timeout(CONTROL_TIMEOUT, wire::write(send, msg))
        .await
        .map_err(|_| anyhow!("the server stopped reading the control stream"))??;
    Ok(())
}

/// Why a connection ended or was refused, in words.
pub fn describe(reason: &Reason) -> String {
    match reason {
        Reason::WrongToken => "wrong token".into(),
        Reason::Version { server } => format!("the server speaks protocol version {server}"),
        Reason::Shutdown => "the server is shutting down".into(),
        Reason::Quit => "quit".into(),
        Reason::Protocol(s) | Reason::Unavailable(s) => s.clone(),
    }
}

/// A frame taken from the stream.
#[derive(Clone, Debug)]
pub struct Received {
    pub frame: u64,
    pub tick: u64,
    pub vehicles: Vec<VehicleView>,
    /// The newest key state the world had applied.
    pub input_seq: Option<u32>,
    /// Bytes on the wire (the frame message).
    pub wire_bytes: usize,
    /// Triangles decoded into [`Session::mesh`] (0 when not decoded).
    pub triangles: usize,
    /// Decoding and building the mesh, seconds.
    pub decode_s: f64,
    /// When its stream was read to the end.
    pub arrived: Instant,
}

/// What [`Session::take`] found.
#[derive(Clone, Debug)]
pub enum Taken {
    /// Nothing newer than what was shown.
    Nothing,
    /// A frame, decoded (unless asked not to) and acknowledged.
    Frame(Received),
    /// A frame that could not be decoded (its base unknown, or the bytes wrong): a key
    /// frame has been asked for.
    Dropped,
}

/// The newest frame read and not yet taken, and the reader's state.
#[derive(Default)]
struct SlotInner {
    /// The frame, its size on the wire (0: a stream that was not a frame), and when it
    /// arrived.
    frame: Mutex<Option<(Frame, usize, Instant)>>,
    notify: tokio::sync::Notify,
    /// The reader has stopped: no frame will come.
    ended: std::sync::atomic::AtomicBool,
}

type Slot = Arc<SlotInner>;

/// The largest budget a server takes; a viewer asks for no more.
pub const MAX_BUDGET: u32 = roam_server::net::viewer::MAX_BUDGET;

/// A joined viewer.
pub struct Session {
    _endpoint: quinn::Endpoint,
    pub conn: quinn::Connection,
    send: quinn::SendStream,
    pub welcome: Welcome,
    pub scene: Scene,
    grid: Grid,
    decoder: MeshDecoder,
    /// Cuts of recent frames: the bases the server may code against.
    decoded: VecDeque<(u64, Cut)>,
    newest: Option<u64>,
    slot: Slot,
    reader: tokio::task::JoinHandle<()>,
    /// The newest decoded mesh.
    pub mesh: mesh::Mesh,
    pub budget: u32,
    /// The largest budget asked for: frames tessellated before a cut may still come.
    limit: u32,
    /// Bytes received on frame streams so far (frames skipped included).
    pub bytes_in: Arc<AtomicU64>,
}

impl Session {
    /// Connects, says hello, and receives the welcome and the colour map.
    pub async fn join(addr: SocketAddr, fingerprint: [u8; 32], hello: Hello) -> Result<Session> {
        let (endpoint, conn) = connect(addr, fingerprint).await?;
        let (mut send, mut recv) = conn.open_bi().await.context("opening the control stream")?;
        let mut hello = hello;
        hello.budget = hello.budget.clamp(2, MAX_BUDGET);
        let budget = hello.budget;
        send_control(&mut send, &ClientMessage::Hello(hello)).await?;
        let joined = tokio::time::timeout(JOIN_TIMEOUT, async {
            let welcome = match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await
            {
                Ok(ServerMessage::Welcome(w)) => w,
                Ok(ServerMessage::Refused(reason)) => {
                    bail!("refused: {}", describe(&reason))
                }
                Ok(other) => bail!("expected a welcome, got {other:?}"),
                Err(e) => bail!(
                    "the server closed the connection: {e} ({:?})",
                    conn.close_reason()
                ),
            };
            let colors = color_map(&mut recv, &welcome).await?;
            anyhow::Ok((welcome, colors))
        })
        .await;
        let (welcome, colors) = match joined {
            Ok(j) => j?,
            Err(_) => bail!(
                "the server sent no welcome and colour map within {} s",
                JOIN_TIMEOUT.as_secs()
            ),
        };
        let grid = Grid::new(u32::from(welcome.levels))
            .ok_or_else(|| anyhow!("a grid of 2^{} + 1", welcome.levels))?;
        let scene = Scene {
            levels: u32::from(welcome.levels),
            h_scale: welcome.h_scale,
            v_scale: welcome.v_scale,
            sun_dir: welcome.sun_dir,
            sun_color: welcome.sun_color,
            fog_density: welcome.fog_density,
            fog_color: welcome.fog_color,
            water_level: welcome.water_level,
            cells: welcome.color_cells,
            colors,
        };
        let slot: Slot = Default::default();
        let bytes_in = Arc::new(AtomicU64::new(0));
        let reader = tokio::spawn(read_frames(conn.clone(), slot.clone(), bytes_in.clone()));
        Ok(Session {
            _endpoint: endpoint,
            conn,
            send,
            welcome,
            scene,
            decoder: MeshDecoder::new(grid),
            grid,
            decoded: VecDeque::new(),
            newest: None,
            slot,
            reader,
            mesh: mesh::Mesh::default(),
            budget,
            limit: budget,
            bytes_in,
        })
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// Waits until a frame is waiting. Cancel-safe (for `select!`). An error when the
    /// connection has ended.
    pub async fn wait(&self) -> Result<()> {
        loop {
            if lock(&self.slot.frame).is_some() {
                return Ok(());
            }
            if self.slot.ended.load(Ordering::Acquire) {
                bail!("{}", self.ended());
            }
            self.slot.notify.notified().await;
        }
    }

    /// Why the connection ended, in words.
    pub fn ended(&self) -> String {
        match self.conn.close_reason() {
            Some(quinn::ConnectionError::ApplicationClosed(c)) => format!(
                "the server closed the connection: {}",
                String::from_utf8_lossy(&c.reason)
            ),
            Some(e) => format!("the connection ended: {e}"),
            None => "the connection ended".into(),
        }
    }

    /// Takes the waiting frame, if it is newer than the last shown; decodes it into
    /// [`Session::mesh`] (unless `decode` is false) and acknowledges it.
    pub async fn take(&mut self, decode: bool) -> Result<Taken> {
        let taken = lock(&self.slot.frame).take();
        let Some((frame, wire_len, arrived)) = taken else {
            return Ok(Taken::Nothing);
        };
        if wire_len == 0 {
            return Ok(Taken::Dropped); // a stream that was not a frame
        }
        if self.newest.is_some_and(|n| frame.frame <= n) {
            return Ok(Taken::Nothing); // latest frame wins here too
        }
        let mut received = Received {
            frame: frame.frame,
            tick: frame.tick,
            vehicles: frame.vehicles,
            input_seq: frame.input_seq,
            wire_bytes: wire_len,
            triangles: 0,
            decode_s: 0.0,
            arrived,
        };
        if decode {
            let started = Instant::now();
            let base = match frame.base {
                Some(b) => match self.decoded.iter().find(|(f, _)| *f == b) {
                    Some((_, cut)) => Some(cut),
                    None => {
                        send_control(&mut self.send, &ClientMessage::KeyFrame).await?;
                        return Ok(Taken::Dropped);
                    }
                },
                None => None,
            };
            let mut cut = Cut::default();
            let Ok(info) = self
                .decoder
                .decode_cut(&frame.mesh, base, self.limit, &mut cut)
            else {
                send_control(&mut self.send, &ClientMessage::KeyFrame).await?;
                return Ok(Taken::Dropped);
            };
            mesh::emit(
                &self.grid,
                &cut.split,
                self.decoder.heights(),
                &mut self.mesh,
            );
            let tris = self.mesh.triangle_count();
            if tris != info.triangles as usize {
                bail!(
                    "frame {}: {tris} triangles emitted, the header says {}",
                    frame.frame,
                    info.triangles
                );
            }
            self.decoded.push_back((frame.frame, cut));
            if self.decoded.len() > 32 {
                self.decoded.pop_front();
            }
            received.triangles = tris;
            received.decode_s = started.elapsed().as_secs_f64();
        }
        send_control(&mut self.send, &ClientMessage::Ack { frame: frame.frame }).await?;
        self.newest = Some(frame.frame);
        Ok(Taken::Frame(received))
    }

    /// Asks for `budget` triangles from now on.
    pub async fn set_budget(&mut self, budget: u32) -> Result<()> {
        let budget = budget.clamp(2, MAX_BUDGET);
        send_control(&mut self.send, &ClientMessage::Budget(budget)).await?;
        self.budget = budget;
        self.limit = self.limit.max(budget);
        Ok(())
    }

    /// Tells the server how the camera differs from the default at the vehicle.
    pub async fn set_view(&mut self, view: messages::ViewChange) -> Result<()> {
        send_control(&mut self.send, &ClientMessage::View(view)).await?;
        Ok(())
    }

    /// Says goodbye and closes the connection. True when the server heard: it took the
    /// whole control stream, goodbye included, or closed the connection with the code it
    /// closes with on a goodbye (bounded: a dead or slow server does not hold the viewer
    /// more than a second).
    pub async fn quit(mut self) -> bool {
        self.reader.abort();
        let said = tokio::time::timeout(Duration::from_secs(1), async {
            wire::write(&mut self.send, &ClientMessage::Bye(Reason::Quit)).await?;
            self.send.finish()?;
            match self.send.stopped().await {
                Ok(_) => anyhow::Ok(true),
                Err(quinn::StoppedError::ConnectionLost(
                    quinn::ConnectionError::ApplicationClosed(c),
                )) => Ok(c.error_code == roam_server::net::viewer::close::BYE.into()),
                Err(e) => Err(e.into()),
            }
        })
        .await;
        self.conn.close(0u32.into(), b"quit");
        matches!(said, Ok(Ok(true)))
    }
}

impl Drop for Session {
    /// However the session ends, the connection closes and the reader stops.
    fn drop(&mut self) {
        self.reader.abort();
        self.conn.close(0u32.into(), b"bye");
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Receives the colour map that follows the welcome, after checking its announced sizes
/// against the grid (nothing is allocated before).
async fn color_map(recv: &mut quinn::RecvStream, welcome: &Welcome) -> Result<Vec<u8>> {
    if welcome.levels > 13 {
        bail!(
            "the server's grid is 2^{} + 1: more than this viewer holds (2^13 + 1)",
            welcome.levels
        );
    }
    let cells = 1u64 << welcome.levels;
    let most = roam_protocol::colormap::max_len(cells as u32) as u64;
    if u64::from(welcome.color_cells) != cells || u64::from(welcome.color_bytes) > most {
        bail!(
            "the server's colour map is {} bytes of {} cells a side, expected {cells} cells \
             in at most {most} bytes",
            welcome.color_bytes,
            welcome.color_cells,
        );
    }
    // Grown as chunks come, not allocated at the size claimed.
    let size = welcome.color_bytes as usize;
    let mut packed = Vec::new();
    let mut got = 0usize;
    while got < size {
        match wire::read::<ServerMessage>(recv, messages::MAX_MESSAGE).await? {
            ServerMessage::ColorMap { offset, data } => {
                let at = offset as usize;
                let end = at
                    .checked_add(data.len())
                    .filter(|&e| e <= size)
                    .ok_or_else(|| anyhow!("a colour-map chunk past the end"))?;
                if data.is_empty() {
                    bail!("an empty colour-map chunk");
                }
                if packed.len() < end {
                    packed.resize(end, 0);
                }
                packed[at..end].copy_from_slice(&data);
                got += data.len();
            }
            other => bail!("expected the colour map, got {other:?}"),
        }
    }
    let mut color = Vec::new();
    roam_protocol::colormap::decode(welcome.color_cells, &packed, &mut color)
        .map_err(|e| anyhow!("the server's colour map: {e}"))?;
    Ok(color)
}

/// Accepts frame streams and reads each in a task of its own, and reads frames that come
/// as datagrams (small ones do); a frame newer than the one waiting replaces it. Anything
/// that is not a frame leaves `(_, 0)` to be counted.
async fn read_frames(conn: quinn::Connection, slot: Slot, bytes_in: Arc<AtomicU64>) {
    let newest = Arc::new(AtomicU64::new(0));
    let datagrams = {
        let (conn, slot, newest, bytes_in) =
            (conn.clone(), slot.clone(), newest.clone(), bytes_in.clone());
        tokio::spawn(async move {
            while let Ok(bytes) = conn.read_datagram().await {
                offer(&slot, &newest, &bytes_in, &bytes, Instant::now());
            }
        })
    };
    while let Ok(mut stream) = conn.accept_uni().await {
        let (slot, newest, bytes_in) = (slot.clone(), newest.clone(), bytes_in.clone());
        tokio::spawn(async move {
            // A frame abandoned by the server (reset) is simply skipped.
            let Ok(bytes) = stream.read_to_end(MAX_FRAME).await else {
                return;
            };
            offer(&slot, &newest, &bytes_in, &bytes, Instant::now());
        });
    }
    datagrams.abort();
    // Set before the last wake-up, so a waiter that wakes sees it.
    slot.ended.store(true, Ordering::Release);
    slot.notify.notify_one();
}

/// A frame's bytes, arrived at `arrived`: it waits in the slot if it is the newest yet.
fn offer(slot: &Slot, newest: &AtomicU64, bytes_in: &AtomicU64, bytes: &[u8], arrived: Instant) {
    bytes_in.fetch_add(bytes.len() as u64, Ordering::Relaxed);
    let mut s = lock(&slot.frame);
    match messages::decode::<Frame>(bytes) {
        Ok(frame) => {
            let n = frame.frame.saturating_add(1);
            if newest.fetch_max(n, Ordering::Relaxed) < n {
                *s = Some((frame, bytes.len(), arrived));
            }
        }
        Err(_) => {
            let bad = Frame {
                frame: 0,
                base: None,
                tick: 0,
                vehicles: Vec::new(),
                input_seq: None,
                mesh: Vec::new(),
            };
            if s.is_none() {
                *s = Some((bad, 0, arrived));
            }
        }
    }
    drop(s);
    slot.notify.notify_one();
}

/// Key changes sent and not yet seen applied: the input→frame latency.
#[derive(Debug, Default)]
pub struct Latency {
    pending: Mutex<VecDeque<(u32, Instant)>>,
}

impl Latency {
    /// Key state `seq`, a change, was sent at `at`.
    pub fn sent(&self, seq: u32, at: Instant) {
        let mut p = self.pending.lock().unwrap_or_else(|e| e.into_inner());
        p.push_back((seq, at));
        // A server that never applies keys (a spectator's) must not grow this.
        if p.len() > 1024 {
            p.pop_front();
        }
    }

    /// A frame showing key states up to `seq` arrived at `now`: the latencies of the
    /// changes it shows, in milliseconds.
    pub fn applied(&self, seq: u32, now: Instant, out: &mut Vec<f64>) {
        let mut p = self.pending.lock().unwrap_or_else(|e| e.into_inner());
        while let Some(&(s, at)) = p.front() {
            if s > seq {
                break;
            }
            out.push((now - at).as_secs_f64() * 1e3);
            p.pop_front();
        }
    }
}

/// A script's keys as [`play`] takes them, one step per call: held keys, and those newly
/// down; then no keys, for ever.
pub fn script_keys(script: &Script) -> impl FnMut() -> Option<(Keys, Keys)> + Send + 'static {
    let keys: Vec<Keys> = script.keys().collect();
    let mut steps = keys.into_iter().chain(std::iter::repeat(Keys::NONE));
    let mut last = Keys::NONE;
    move || {
        let k = steps.next()?;
        let pressed = k.without(last);
        last = k;
        Some((k, pressed))
    }
}

/// Sends key states as datagrams, one per 10 ms (the physics' step), each datagram
/// repeating the last eight states so a lost one costs nothing. `next` gives each step's
/// held keys and the keys pressed since the last step (latched: a press released before
/// the step is still sent). Returns when `next` says stop or the connection is gone.
pub async fn play(
    conn: quinn::Connection,
    mut next: impl FnMut() -> Option<(Keys, Keys)> + Send + 'static,
    latency: Arc<Latency>,
) {
    let mut states: VecDeque<KeyState> = VecDeque::new();
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut last = Keys::NONE;
    for seq in 1u32.. {
        tick.tick().await;
        let Some((held, pressed)) = next() else {
            return;
        };
        let state = KeyState {
            seq,
            held: held.bits(),
            pressed: pressed.bits(),
        };
        if held != last || pressed != Keys::NONE {
            latency.sent(seq, Instant::now());
        }
        last = held;
        states.push_front(state);
        states.truncate(messages::KEY_HISTORY);
        let d = KeyDatagram {
            states: states.iter().copied().collect(),
        };
        let mut bytes = Vec::new();
        if messages::encode(&d, &mut bytes).is_ok() && conn.send_datagram(bytes.into()).is_err() {
            return;
        }
    }
}
