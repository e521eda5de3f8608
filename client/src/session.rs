//! The viewer's I/O: QUIC, tasks and the clock around the clock-free [`ClientCore`]. It
//! connects (pinning the server's certificate), joins (hello, welcome, the colour map checked
//! against the grid before anything is allocated), then runs three tasks beside the
//! caller: one reads frames (datagrams, and streams read to their end) into the core, one
//! writes the core's control messages in order, and one sends a key datagram every 10 ms
//! (the physics' step) from the core's latch or a script. The window, the headless viewer
//! and `--bench` take frames with [`Session::next_frame`].

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use roam_link::{tls, wire};
use roam_protocol::keys::{KeyStep, Keys};
use roam_protocol::messages::{self, ClientMessage, Hello, Reason, ServerMessage, Welcome, close};
use roam_protocol::script::Script;
use tokio::sync::{Notify, mpsc, oneshot};

pub use crate::core::{ClientCore, KeyCore, Received, Taken};
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

/// Why a connection ended or was refused, in words.
pub fn describe(reason: &Reason) -> String {
    match reason {
        Reason::WrongToken => "wrong token".into(),
        Reason::Version { server } => format!("the server speaks protocol version {server}"),
        Reason::Shutdown => "the server is shutting down".into(),
        Reason::Quit => "quit".into(),
        Reason::Protocol(s) | Reason::Unavailable(s) => s.clone(),
        Reason::Full { viewers } => format!("the server is full ({viewers} viewers)"),
    }
}

/// Set once Ctrl-C is pressed in the terminal; a second Ctrl-C exits at once (130), not
/// waiting for goodbyes. For the headless viewer and the window alike.
pub fn ctrl_c() -> tokio::sync::watch::Receiver<bool> {
    let (stop, stopped) = tokio::sync::watch::channel(false);
    tokio::spawn(async move {
        if tokio::signal::ctrl_c().await.is_ok() {
            let _ = stop.send(true);
            if tokio::signal::ctrl_c().await.is_ok() {
                std::process::exit(130);
            }
        }
    });
    stopped
}

/// Where a driver's keys come from.
#[derive(Clone, Debug)]
pub enum KeySource {
    /// No keys are sent (a spectator).
    None,
    /// The core's latch, fed by [`Session::key_down`] and [`Session::key_up`] (the window).
    Latch,
    /// A script, one step per 10 ms, then no keys.
    Script(Script),
}

/// Each physics step's keys, taken from the core's latch or a script.
type Steps = Box<dyn FnMut(&mut KeyCore) -> KeyStep + Send>;

/// What the control writer is asked to do.
enum Outgoing {
    Message(ClientMessage),
    /// Say goodbye, finish the stream, and tell whether the server heard.
    Quit(oneshot::Sender<bool>),
}

/// What the I/O tasks and the caller share.
struct Link {
    core: Mutex<ClientCore>,
    /// Locked apart from the frames: a key state never waits on a decode.
    keys: Mutex<KeyCore>,
    /// Woken when a frame is offered or the connection ends.
    notify: Notify,
    /// Set once no more frames can come: the reason.
    ended: Mutex<Option<String>>,
    closed: AtomicBool,
}

impl Link {
    fn end(&self, why: String) {
        lock(&self.ended).get_or_insert(why);
        self.closed.store(true, Ordering::Release);
        self.notify.notify_one();
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// A joined viewer.
pub struct Session {
    _endpoint: quinn::Endpoint,
    pub conn: quinn::Connection,
    pub welcome: Welcome,
    pub scene: Scene,
    link: Arc<Link>,
    control: mpsc::UnboundedSender<Outgoing>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Session {
    /// Connects, says hello, receives the welcome and the colour map, and starts the I/O
    /// tasks; keys are sent from `keys`.
    pub async fn join(
        addr: SocketAddr,
        fingerprint: [u8; 32],
        hello: Hello,
        keys: KeySource,
    ) -> Result<Session> {
        let (endpoint, conn) = connect(addr, fingerprint).await?;
        let (mut send, mut recv) = conn.open_bi().await.context("opening the control stream")?;
        let mut hello = hello;
        hello.budget = messages::clamp_budget(hello.budget);
        let budget = hello.budget;
        write_control(&mut send, &ClientMessage::Hello(hello)).await?;
        let joined = tokio::time::timeout(JOIN_TIMEOUT, async {
            let welcome = match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await
            {
                Ok(ServerMessage::Welcome(w)) => w,
                Ok(ServerMessage::Refused(reason)) => {
                    bail!("refused: {}", describe(&reason))
                }
                Ok(other) => bail!("expected a welcome, got {other:?}"),
                Err(e) => match conn.close_reason() {
                    Some(why) => bail!("the server closed the connection: {why} ({e})"),
                    None => bail!("reading the welcome: {e}"),
                },
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
        let core = ClientCore::new(&welcome, budget)
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
        let link = Arc::new(Link {
            core: Mutex::new(core),
            keys: Mutex::new(KeyCore::default()),
            notify: Notify::new(),
            ended: Mutex::new(None),
            closed: AtomicBool::new(false),
        });
        let (control, outgoing) = mpsc::unbounded_channel();
        let mut tasks = vec![
            tokio::spawn(read_frames(conn.clone(), link.clone())),
            tokio::spawn(control_writer(send, outgoing, link.clone())),
        ];
        let steps: Option<Steps> = match keys {
            KeySource::None => None,
            KeySource::Latch => Some(Box::new(KeyCore::take_keys)),
            KeySource::Script(script) => {
                let mut steps: Vec<KeyStep> = script.steps().collect();
                steps.reverse();
                Some(Box::new(move |_: &mut KeyCore| {
                    steps.pop().unwrap_or(KeyStep {
                        held: Keys::NONE,
                        pressed: Keys::NONE,
                    })
                }))
            }
        };
        if let Some(steps) = steps {
            tasks.push(tokio::spawn(send_keys(conn.clone(), link.clone(), steps)));
        }
        Ok(Session {
            _endpoint: endpoint,
            conn,
            welcome,
            scene,
            link,
            control,
            tasks,
        })
    }

    /// The core (the newest mesh, the grid, the budget): held briefly, never across an
    /// await.
    pub fn core(&self) -> MutexGuard<'_, ClientCore> {
        lock(&self.link.core)
    }

    /// Sends what the core has for the control stream.
    fn flush(&self, core: &mut ClientCore) {
        while let Some(m) = core.poll_control() {
            let _ = self.control.send(Outgoing::Message(m));
        }
    }

    /// Waits for the next frame and takes it: decoded into the core's mesh (unless
    /// `decode` is false) and acknowledged. An error when the connection has ended or the
    /// server sent a frame inconsistent with itself.
    pub async fn next_frame(&self, decode: bool) -> Result<Taken> {
        loop {
            let notified = self.link.notify.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            {
                let mut core = self.core();
                if core.has_frame() {
                    let started = Instant::now();
                    let mut taken = core.take(decode);
                    self.flush(&mut core);
                    drop(core);
                    if let Ok(Taken::Frame(r)) = &mut taken {
                        r.decode_s = started.elapsed().as_secs_f64();
                        if let Some(seq) = r.input_seq {
                            r.latencies_ms = lock(&self.link.keys).applied(seq, r.arrived);
                        }
                    }
                    return Ok(taken?);
                }
            }
            if self.link.closed.load(Ordering::Acquire) {
                bail!("{}", self.ended());
            }
            notified.await;
        }
    }

    /// Why the connection ended, in words.
    pub fn ended(&self) -> String {
        if let Some(why) = lock(&self.link.ended).clone()
            && self.conn.close_reason().is_none()
        {
            return why;
        }
        match self.conn.close_reason() {
            Some(quinn::ConnectionError::ApplicationClosed(c)) => format!(
                "the server closed the connection: {}",
                String::from_utf8_lossy(&c.reason)
            ),
            Some(e) => format!("the connection ended: {e}"),
            None => "the connection ended".into(),
        }
    }

    /// Asks for `budget` triangles from now on.
    pub fn set_budget(&self, budget: u32) {
        let mut core = self.core();
        core.set_budget(budget);
        self.flush(&mut core);
    }

    /// Tells the server how the camera differs from the default at the vehicle.
    pub fn set_view(&self, view: messages::ViewChange) {
        let mut core = self.core();
        core.set_view(view);
        self.flush(&mut core);
    }

    pub fn key_down(&self, keys: Keys) {
        lock(&self.link.keys).key_down(keys);
    }

    pub fn key_up(&self, keys: Keys) {
        lock(&self.link.keys).key_up(keys);
    }

    /// Every key released (the window lost focus: nothing stays held).
    pub fn keys_released(&self) {
        lock(&self.link.keys).keys_released();
    }

    /// Frame bytes received so far.
    pub fn bytes_in(&self) -> u64 {
        self.core().bytes_in()
    }

    /// Says goodbye and closes the connection. True when the server heard: it took the
    /// whole control stream, goodbye included, or closed the connection with the code it
    /// closes with on a goodbye (bounded: a dead or slow server does not hold the viewer
    /// more than a second).
    pub async fn quit(&self) -> bool {
        let (tx, rx) = oneshot::channel();
        let heard = if self.control.send(Outgoing::Quit(tx)).is_ok() {
            tokio::time::timeout(Duration::from_secs(1), rx)
                .await
                .is_ok_and(|r| r.unwrap_or(false))
        } else {
            false
        };
        self.conn.close(0u32.into(), b"quit");
        heard
    }
}

impl Drop for Session {
    /// However the session ends, the connection closes and the tasks stop.
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
        self.conn.close(0u32.into(), b"bye");
    }
}

/// Writes a control message, within [`CONTROL_TIMEOUT`].
async fn write_control(send: &mut quinn::SendStream, msg: &ClientMessage) -> Result<()> {
    tokio::time::timeout(CONTROL_TIMEOUT, wire::write(send, msg))
        .await
        .map_err(|_| anyhow!("the server stopped reading the control stream"))??;
    Ok(())
}

/// Writes the control messages in order until the session ends or a write fails (then
/// the session ends with why).
async fn control_writer(
    mut send: quinn::SendStream,
    mut outgoing: mpsc::UnboundedReceiver<Outgoing>,
    link: Arc<Link>,
) {
    while let Some(o) = outgoing.recv().await {
        match o {
            Outgoing::Message(m) => {
                if let Err(e) = write_control(&mut send, &m).await {
                    link.end(format!("{e:#}"));
                    return;
                }
            }
            Outgoing::Quit(heard) => {
                let said = async {
                    wire::write(&mut send, &ClientMessage::Bye(Reason::Quit)).await?;
                    send.finish()?;
                    match send.stopped().await {
                        Ok(_) => anyhow::Ok(true),
                        Err(quinn::StoppedError::ConnectionLost(
                            quinn::ConnectionError::ApplicationClosed(c),
                        )) => Ok(c.error_code == close::BYE.into()),
                        Err(e) => Err(e.into()),
                    }
                };
                let _ = heard.send(matches!(said.await, Ok(true)));
                return;
            }
        }
    }
}

/// Sends a key datagram every 10 ms (the physics' step) with the step's keys from
/// `steps`: the core numbers the state and repeats the last eight, so a lost datagram
/// costs nothing. Ends when the connection does.
async fn send_keys(conn: quinn::Connection, link: Arc<Link>, mut steps: Steps) {
    let mut tick = tokio::time::interval(Duration::from_millis(10));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let datagram = {
            let mut keys = lock(&link.keys);
            let step = steps(&mut keys);
            keys.key_datagram(step, Instant::now())
        };
        let mut bytes = Vec::new();
        if messages::encode(&datagram, &mut bytes).is_ok()
            && conn.send_datagram(bytes.into()).is_err()
        {
            return;
        }
    }
}

/// Reads frames into the core as they arrive: datagrams (small frames), and streams, each
/// read to its end in a task of its own (a stream the server abandons is skipped).
async fn read_frames(conn: quinn::Connection, link: Arc<Link>) {
    let offer = |link: &Link, bytes: &[u8]| {
        lock(&link.core).offer(bytes, Instant::now());
        link.notify.notify_one();
    };
    let datagrams = {
        let (conn, link) = (conn.clone(), link.clone());
        tokio::spawn(async move {
            while let Ok(bytes) = conn.read_datagram().await {
                offer(&link, &bytes);
            }
        })
    };
    while let Ok(mut stream) = conn.accept_uni().await {
        let link = link.clone();
        tokio::spawn(async move {
            if let Ok(bytes) = stream.read_to_end(MAX_FRAME).await {
                offer(&link, &bytes);
            }
        });
    }
    datagrams.abort();
    link.end("the connection ended".into());
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
