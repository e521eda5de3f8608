//! A headless viewer: connects, plays an input script as key datagrams, decodes and checks
//! every frame, acknowledges it, and measures what it got.

use std::collections::VecDeque;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use roam_protocol::messages::{
    self, ClientMessage, Frame, Hello, KeyDatagram, KeyState, Reason, Role, ServerMessage, VERSION,
};
use roam_protocol::{BitSet, Grid, MeshDecoder, mesh};
use roam_server::net::{tls, wire};
use roam_server::physics::Keys;
use roam_server::script::Script;

/// What one viewer asks for.
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    pub token: String,
    pub role: Role,
    pub budget: u32,
    /// Stop after this many frames.
    pub frames: u64,
    /// Keys to play, one step of the script per 10 ms (drivers).
    pub inputs: Option<Script>,
    pub viewport: [u32; 2],
    pub fov_y_deg: f32,
    pub frame_rate: u16,
    /// Acknowledge frames without decoding them (a load generator measuring the server,
    /// not itself).
    pub skip_decode: bool,
    /// Keep the scene and the last mesh (for a screenshot).
    pub keep_last: bool,
}

impl Default for ViewerOptions {
    fn default() -> Self {
        ViewerOptions {
            token: String::new(),
            role: Role::Driver,
            budget: 65_536,
            frames: 300,
            inputs: None,
            viewport: [1280, 720],
            fov_y_deg: 60.0,
            frame_rate: 60,
            skip_decode: false,
            keep_last: false,
        }
    }
}

/// What one viewer measured.
#[derive(Clone, Debug, Default)]
pub struct ViewerStats {
    pub frames: u64,
    pub seconds: f64,
    /// Wire bytes per triangle of the first frame, and of each later one.
    pub first: Option<f64>,
    pub steady: Vec<f64>,
    /// Key change sent → first frame showing it applied, ms.
    pub latencies_ms: Vec<f64>,
    pub decode_errors: u64,
    /// The vehicle driven or followed, and its state in the last frame.
    pub vehicle: u16,
    pub last: Option<messages::VehicleView>,
    pub last_tick: u64,
    /// The largest mesh received, triangles.
    pub max_triangles: usize,
    /// With `keep_last`: the scene, and the last mesh decoded.
    pub scene: Option<crate::render::Scene>,
    pub last_mesh: Option<mesh::Mesh>,
}

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

/// Runs one viewer to its frame count.
pub async fn run(
    addr: SocketAddr,
    fingerprint: [u8; 32],
    opts: ViewerOptions,
) -> Result<ViewerStats> {
    let (_endpoint, conn) = connect(addr, fingerprint).await?;
    let (mut send, mut recv) = conn.open_bi().await.context("opening the control stream")?;
    let hello = Hello {
        version: VERSION,
        role: opts.role.clone(),
        token: opts.token.clone(),
        viewport: opts.viewport,
        fov_y_deg: opts.fov_y_deg,
        budget: opts.budget,
        frame_rate: opts.frame_rate,
    };
    wire::write(&mut send, &ClientMessage::Hello(hello)).await?;
    let welcome = match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await {
        Ok(ServerMessage::Welcome(w)) => w,
        Ok(ServerMessage::Refused(reason)) => bail!("refused: {}", describe(&reason)),
        Ok(other) => bail!("expected a welcome, got {other:?}"),
        Err(e) => bail!(
            "the server closed the connection: {e} ({:?})",
            conn.close_reason()
        ),
    };
    // The colour map follows the welcome; its size must be what the grid says, within
    // reason, before anything is allocated.
    if welcome.levels > 13 {
        bail!(
            "the server's grid is 2^{} + 1: more than this viewer holds (2^13 + 1)",
            welcome.levels
        );
    }
    let cells = 1u64 << welcome.levels;
    if u64::from(welcome.color_cells) != cells
        || u64::from(welcome.color_bytes) != cells * cells * 3
    {
        bail!(
            "the server's colour map is {} bytes of {} cells a side, expected {} of {cells}",
            welcome.color_bytes,
            welcome.color_cells,
            cells * cells * 3
        );
    }
    let mut color = vec![0u8; welcome.color_bytes as usize];
    let mut got = 0usize;
    while got < color.len() {
        match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await? {
            ServerMessage::ColorMap { offset, data } => {
                let at = offset as usize;
                let end = at
                    .checked_add(data.len())
                    .filter(|&e| e <= color.len())
                    .ok_or_else(|| anyhow!("a colour-map chunk past the end"))?;
                color[at..end].copy_from_slice(&data);
                got += data.len();
            }
            other => bail!("expected the colour map, got {other:?}"),
        }
    }
    let grid = Grid::new(u32::from(welcome.levels))
        .ok_or_else(|| anyhow!("a grid of 2^{} + 1", welcome.levels))?;
    let pending = std::sync::Arc::new(std::sync::Mutex::new(VecDeque::<(u32, Instant)>::new()));
    let keys = match (&opts.role, &opts.inputs) {
        (Role::Driver, Some(script)) => Some(tokio::spawn(play(
            conn.clone(),
            script.clone(),
            pending.clone(),
        ))),
        _ => None,
    };
    let mut stats = ViewerStats {
        vehicle: welcome.vehicle,
        ..ViewerStats::default()
    };
    if opts.keep_last {
        stats.scene = Some(crate::render::Scene {
            levels: u32::from(welcome.levels),
            h_scale: welcome.h_scale,
            v_scale: welcome.v_scale,
            sun_dir: welcome.sun_dir,
            sun_color: welcome.sun_color,
            fog_density: welcome.fog_density,
            fog_color: welcome.fog_color,
            cells: welcome.color_cells,
            colors: color.clone(),
        });
    }
    let mut decoder = MeshDecoder::new(grid);
    let mut decoded: VecDeque<(u64, BitSet)> = VecDeque::new();
    let mut newest: Option<u64> = None;
    let mut viewer_mesh = mesh::Mesh::default();
    let started = Instant::now();
    // Frames arrive on streams of their own, read side by side; only the newest waits to
    // be shown (latest frame wins here too: a slow viewer skips frames, never lags).
    let slot: Slot = Default::default();
    let reader = tokio::spawn(read_frames(conn.clone(), slot.clone()));
    while stats.frames < opts.frames {
        let taken = slot.0.lock().unwrap_or_else(|e| e.into_inner()).take();
        let Some((frame, wire_len)) = taken else {
            if reader.is_finished() {
                bail!("the connection ended: {:?}", conn.close_reason());
            }
            slot.1.notified().await;
            continue;
        };
        if wire_len == 0 {
            stats.decode_errors += 1; // a stream that was not a frame
            continue;
        }
        if newest.is_some_and(|n| frame.frame <= n) {
            continue; // older than what is shown: latest frame wins here too
        }
        if opts.skip_decode {
            wire::write(&mut send, &ClientMessage::Ack { frame: frame.frame }).await?;
            newest = Some(frame.frame);
            stats.frames += 1;
            stats.last_tick = frame.tick;
            continue;
        }
        let base = match frame.base {
            Some(b) => match decoded.iter().find(|(f, _)| *f == b) {
                Some((_, set)) => Some(set),
                None => {
                    stats.decode_errors += 1;
                    wire::write(&mut send, &ClientMessage::KeyFrame).await?;
                    continue;
                }
            },
            None => None,
        };
        let mut split = BitSet::default();
        let info = match decoder.decode(&frame.mesh, base, opts.budget, &mut split) {
            Ok(i) => i,
            Err(_) => {
                stats.decode_errors += 1;
                wire::write(&mut send, &ClientMessage::KeyFrame).await?;
                continue;
            }
        };
        mesh::emit(&grid, &split, decoder.heights(), &mut viewer_mesh);
        let tris = viewer_mesh.triangle_count();
        if tris != info.triangles as usize || tris > opts.budget.max(2) as usize {
            bail!(
                "frame {}: {tris} triangles, budget {}",
                frame.frame,
                opts.budget
            );
        }
        if stats.frames.is_multiple_of(60) {
            let v: Vec<[u16; 2]> = viewer_mesh.vertices.clone();
            roam_server::validate::check_mesh(&v, &viewer_mesh.indices, grid.size())
                .map_err(|e| anyhow!("frame {}: not a conforming mesh: {e}", frame.frame))?;
        }
        wire::write(&mut send, &ClientMessage::Ack { frame: frame.frame }).await?;
        decoded.push_back((frame.frame, split));
        if decoded.len() > 32 {
            decoded.pop_front();
        }
        newest = Some(frame.frame);
        let per_tri = wire_len as f64 / tris.max(1) as f64;
        if stats.first.is_none() {
            stats.first = Some(per_tri);
        } else {
            stats.steady.push(per_tri);
        }
        stats.max_triangles = stats.max_triangles.max(tris);
        if let Some(seq) = frame.input_seq {
            let now = Instant::now();
            let mut p = pending.lock().unwrap_or_else(|e| e.into_inner());
            while let Some(&(s, at)) = p.front() {
                if s > seq {
                    break;
                }
                stats.latencies_ms.push((now - at).as_secs_f64() * 1e3);
                p.pop_front();
            }
        }
        stats.last = frame
            .vehicles
            .iter()
            .find(|v| v.id == welcome.vehicle)
            .copied();
        stats.last_tick = frame.tick;
        stats.frames += 1;
    }
    stats.seconds = started.elapsed().as_secs_f64();
    if opts.keep_last && stats.max_triangles > 0 {
        // The mesh of the last frame decoded.
        stats.last_mesh = Some(viewer_mesh);
    }
    reader.abort();
    if let Some(k) = keys {
        k.abort();
    }
    let _ = wire::write(&mut send, &ClientMessage::Bye(Reason::Quit)).await;
    let _ = send.finish();
    conn.close(0u32.into(), b"done");
    Ok(stats)
}

type Slot = std::sync::Arc<(
    std::sync::Mutex<Option<(Frame, usize)>>,
    tokio::sync::Notify,
)>;

/// Accepts frame streams and reads each in a task of its own; a frame newer than the one
/// waiting replaces it. A stream that is not a frame leaves `(_, 0)` to be counted.
async fn read_frames(conn: quinn::Connection, slot: Slot) {
    let newest = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    while let Ok(mut stream) = conn.accept_uni().await {
        let (slot, newest) = (slot.clone(), newest.clone());
        tokio::spawn(async move {
            // A frame abandoned by the server (reset) is simply skipped.
            let Ok(bytes) = stream.read_to_end(messages::MAX_MESSAGE).await else {
                return;
            };
            let mut s = slot.0.lock().unwrap_or_else(|e| e.into_inner());
            match messages::decode::<Frame>(&bytes) {
                Ok(frame) => {
                    let n = frame.frame + 1;
                    if newest.fetch_max(n, std::sync::atomic::Ordering::Relaxed) < n {
                        *s = Some((frame, bytes.len()));
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
                        *s = Some((bad, 0));
                    }
                }
            }
            drop(s);
            slot.1.notify_one();
        });
    }
    slot.1.notify_one();
}

fn describe(reason: &Reason) -> String {
    match reason {
        Reason::WrongToken => "wrong token".into(),
        Reason::Version { server } => format!("the server speaks protocol version {server}"),
        Reason::Shutdown => "the server is shutting down".into(),
        Reason::Quit => "quit".into(),
        Reason::Protocol(s) | Reason::Unavailable(s) => s.clone(),
    }
}

/// Plays `script` as key datagrams, one state per 10 ms, each datagram repeating the last
/// eight states; remembers when each change was sent.
async fn play(
    conn: quinn::Connection,
    script: Script,
    pending: std::sync::Arc<std::sync::Mutex<VecDeque<(u32, Instant)>>>,
) {
    let mut states: VecDeque<KeyState> = VecDeque::new();
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    let mut last = Keys::NONE;
    let keys = script.keys().chain(std::iter::repeat(Keys::NONE));
    for (seq, k) in (1u32..).zip(keys) {
        tick.tick().await;
        let state = KeyState {
            seq,
            held: k.bits(),
            pressed: k.without(last).bits(),
        };
        if k != last {
            pending
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push_back((seq, Instant::now()));
        }
        last = k;
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
