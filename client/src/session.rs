//! The viewer's I/O: QUIC, tasks and the clock around the clock-free cores
//! ([`ClientCore`] and [`ColorCache`] per connection, [`KeyCore`] and [`Gaps`] per
//! session). It joins ([`crate::join`]: hello, welcome, the colour layout checked against
//! the grid, the coarsest colour tile), then runs beside the caller: a **supervisor**
//! (in `connection.rs`) that drives the connection (reading frames into the core, the
//! server's control messages — colour windows and tiles into the colour cache, an edge's
//! news of its world into the [`Status`] —, writing the core's control messages in order)
//! and reconnects when it is lost, and a **key sender** that sends a key datagram every
//! 10 ms (the physics' step) from the core's latch or a script. The window, the headless
//! viewer and `--bench` take frames with [`Session::next_frame`].
//!
//! **Addresses.** A session has one address or several ([`Session::join_any`]: the edges
//! of one world, `roam-client --connect A,B,…`), all behind the one certificate pin and
//! token; an edge's [`WorldNews::Edges`] adds the others it names
//! ([`crate::edges::Addresses`]). The first connection tries them in turn (each handshake
//! within [`HANDSHAKE_MANY`] when there are several); [`Session::addr`] is the one in use.
//!
//! **Reconnecting.** A connection is *lost* when QUIC says so (idle timeout, reset,
//! transport error) or when the server is *silent*: no frame, no control message and no
//! frame bytes for [`Patience::silence`] (10 s; [`SILENCE_MANY`], 0.8 s, when there are other
//! addresses, unless the patience is shorter) after the welcome (the server sends frames
//! at the viewer's rate whatever the world does, so silence means a stuck path or server).
//! Then the session connects again to the next address in turn (the same one when it has
//! one), from the same endpoint, with the same certificate pin and token, presenting the
//! driver's ticket ([`Hello::resume`]; a spectator asks to follow the same vehicle), at
//! once, then after 100 ms, doubling to 2 s between attempts, each handshake bounded to
//! 5 s (1 s with other addresses), for [`Patience::reconnect_for`] (35 s: the server's 30 s
//! hold and a margin), and then gives up with an error naming the server. The new
//! connection starts a fresh [`ClientCore`] (frame numbers start again at 0) with the
//! budget and view asked so far; the keys go on (their numbers keep rising, so a resumed
//! vehicle's queue takes them as new). Its welcome must show the same terrain (grid,
//! scales, colour layout and coarsest tile), else the session ends. A new connection also
//! starts a fresh colour cache: the server sends the colour pyramid again from its
//! coarsest tile.
//!
//! Never reconnected after: a refusal (wrong token, version, a full server), the server
//! closing the connection (a goodbye; shutting down, unless there are other addresses), a
//! frame the server could not have sent ([`crate::core::Broken`]: the session ends with the
//! server and the numbers named), the viewer quitting. **Silence reconnects once** per
//! address: it may be a stuck path, but a server that welcomes again and then stays
//! silent (the same address silent twice with no frame between) is stuck itself, and the
//! session ends ([`crate::edges::Silences`]).

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use roam_protocol::keys::{KeyStep, Keys};
use roam_protocol::messages::{
    self, ClientMessage, Hello, ReplayControl, ReplayStatus, ViewChange, Welcome, WorldNews, close,
};
use roam_protocol::script::Script;
use tokio::sync::{Notify, mpsc, oneshot, watch};

use crate::color_cache::{ColorCache, Keep};
pub use crate::connection::MAX_FRAME;
use crate::connection::{Outgoing, Supervisor, attempt, send_keys};
pub use crate::core::{Broken, ClientCore, Gaps, KeyCore, Received, Taken};
use crate::edges::{Addresses, native_edges};
pub use crate::edges::{HANDSHAKE_MANY, SILENCE_MANY, World};
use crate::join::{self, Joined, TerrainId};
pub use crate::join::{connect, describe};
use crate::joining::next_hello;
use crate::render::Scene;

/// How long a control message may take to leave (a server that stops reading does not
/// hold the viewer).
pub(crate) const CONTROL_TIMEOUT: Duration = Duration::from_secs(2);
/// How long the welcome and the coarsest colour tile may take.
pub(crate) const JOIN_TIMEOUT: Duration = Duration::from_secs(30);
/// [`Patience::silence`] unless told otherwise.
pub const SILENCE: Duration = Duration::from_secs(10);
/// [`Patience::reconnect_for`] unless told otherwise: the server's hold (30 s) and a margin.
pub const RECONNECT_FOR: Duration = Duration::from_secs(35);

/// How long a session waits on its server.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Patience {
    /// After the welcome, this long without a frame or a control message: the connection
    /// is lost.
    pub silence: Duration,
    /// How long after a loss to keep trying to connect again.
    pub reconnect_for: Duration,
}

impl Default for Patience {
    fn default() -> Self {
        Patience {
            silence: SILENCE,
            reconnect_for: RECONNECT_FOR,
        }
    }
}

/// Where a session stands.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum State {
    Connected,
    /// The connection was lost (`why`); `attempts` to connect again so far.
    Reconnecting {
        why: String,
        attempts: u32,
    },
    /// No more frames will come: why.
    Ended(String),
}

/// What a session shows of itself: its state, its gaps, its newest welcome, where it is
/// connected and what the edge said of its world.
#[derive(Clone, Debug)]
pub struct Status {
    pub state: State,
    pub gaps: Gaps,
    /// The newest connection's welcome (the vehicle may change on a reconnection that
    /// did not get it back).
    pub welcome: Welcome,
    /// The newest connection's address.
    pub addr: SocketAddr,
    /// The world behind the server: `world.gone` says why when the edge said it does not
    /// answer (frames go on, showing it as last seen); the time gone in all.
    pub world: World,
    /// Addresses learned from the edges ([`WorldNews::Edges`]), in the rotation.
    pub edges_learned: usize,
    /// A watched recording's state, as the server last said it (`serve --replay`).
    pub replay: Option<ReplayStatus>,
}

/// Set once Ctrl-C is pressed in the terminal; a second Ctrl-C exits at once (130), not
/// waiting for goodbyes. For the headless viewer and the window alike.
pub fn ctrl_c() -> watch::Receiver<bool> {
    let (stop, stopped) = watch::channel(false);
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
    /// A script whose 10 ms key clock ticks at this offset on the process's own 10 ms
    /// grid (`--viewers N` spreads its drivers' clocks over the step, so their latencies
    /// sample every phase of the server's tick rather than the one the joins fell on).
    ScriptAt(Script, std::time::Duration),
}

/// Each physics step's keys, taken from the core's latch or a script.
pub(crate) type Steps = Box<dyn FnMut(&mut KeyCore) -> KeyStep + Send>;

/// What the tasks and the caller share.
pub(crate) struct Link {
    /// The connection's frames; replaced with each connection.
    pub(crate) core: Mutex<ClientCore>,
    /// The connection's colour tiles; replaced with each connection. Locked apart from
    /// the frames (and never while a tile decodes): the render thread drains it.
    pub(crate) colors: Mutex<ColorCache>,
    /// Colour bytes of the connections before this one.
    pub(crate) color_bytes_before: AtomicU64,
    /// Locked apart from the frames: a key state never waits on a decode. For the session.
    pub(crate) keys: Mutex<KeyCore>,
    /// Woken when a frame is offered or the session ends.
    pub(crate) notify: Notify,
    /// Bumped (under the core's lock) with each connection: bytes of an older one are not
    /// offered to the new core.
    pub(crate) epoch: AtomicU64,
    /// The connection the keys go on; none while reconnecting.
    pub(crate) conn: Mutex<Option<quinn::Connection>>,
    /// When the server was last heard (a frame's bytes, a control message, the welcome).
    pub(crate) heard: Mutex<Instant>,
    /// Frames offered, all connections together.
    pub(crate) frames: AtomicU64,
    /// Frame bytes of the connections before this one.
    pub(crate) bytes_before: AtomicU64,
    /// The newest view asked for, sent again on a new connection.
    pub(crate) view: Mutex<Option<ViewChange>>,
    pub(crate) status: watch::Sender<Status>,
    /// The addresses tried in turn, the one in use among them.
    pub(crate) addresses: Mutex<Addresses<SocketAddr>>,
    /// Whether the endpoint reaches IPv6 addresses (learned ones it cannot are skipped).
    ipv6: bool,
}

impl Link {
    /// The session ends with `why` (the first reason given stands).
    pub(crate) fn end(&self, why: String) {
        self.status.send_if_modified(|s| {
            if matches!(s.state, State::Ended(_)) {
                return false;
            }
            s.state = State::Ended(why);
            true
        });
        self.notify.notify_one();
    }

    pub(crate) fn ended(&self) -> Option<String> {
        match &self.status.borrow().state {
            State::Ended(why) => Some(why.clone()),
            _ => None,
        }
    }

    /// The server was heard from, now.
    pub(crate) fn heard(&self) {
        *lock(&self.heard) = Instant::now();
    }

    /// Bytes of a frame of connection `epoch` arrived.
    pub(crate) fn offer(&self, epoch: u64, bytes: &[u8]) {
        {
            let mut core = lock(&self.core);
            if self.epoch.load(Ordering::Acquire) != epoch {
                return;
            }
            core.offer(bytes, Instant::now());
        }
        self.frames.fetch_add(1, Ordering::Relaxed);
        self.heard();
        self.notify.notify_one();
    }

    /// An edge's news of its world: its other edges join the rotation; the world gone or
    /// back goes into the status (waking its watchers).
    pub(crate) fn news(&self, news: &WorldNews) {
        let now = Instant::now();
        match news {
            WorldNews::Edges(edges) => {
                let reachable = native_edges(edges)
                    .into_iter()
                    .filter(|a| self.ipv6 || a.is_ipv4());
                let learned = {
                    let mut a = lock(&self.addresses);
                    a.learn(reachable);
                    a.learned()
                };
                self.status.send_if_modified(|s| {
                    let changed = s.edges_learned != learned;
                    s.edges_learned = learned;
                    changed
                });
            }
            other => {
                self.status
                    .send_if_modified(|s| s.world.apply(other, now).is_some());
            }
        }
    }

    /// The server's frames follow vehicle `v` from now on (a reconnection asks for it).
    pub(crate) fn following(&self, v: u16) {
        self.status.send_if_modified(|s| {
            let changed = s.welcome.vehicle != v;
            s.welcome.vehicle = v;
            changed
        });
    }

    /// A watched recording's state changed.
    pub(crate) fn replay(&self, status: &ReplayStatus) {
        lock(&self.core).set_replay();
        self.status.send_if_modified(|s| {
            let changed = s.replay.as_ref() != Some(status);
            s.replay = Some(status.clone());
            changed
        });
    }

    /// Closes the current connection, if any.
    pub(crate) fn close(&self, code: u32, why: &[u8]) {
        if let Some(conn) = lock(&self.conn).take() {
            conn.close(code.into(), why);
        }
    }
}

pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// Seconds, as people read them.
pub(crate) fn secs(d: Duration) -> String {
    format!("{:.1} s", d.as_secs_f64())
}

/// A joined viewer.
pub struct Session {
    pub scene: Scene,
    /// The hello's viewport and field of view (the geomorphs' camera).
    viewport: [u32; 2],
    fov_y_deg: f32,
    link: Arc<Link>,
    control: mpsc::UnboundedSender<Outgoing>,
    tasks: Vec<tokio::task::JoinHandle<()>>,
}

impl Session {
    /// Connects, says hello, receives the welcome and the coarsest colour tile, and starts
    /// the I/O tasks; keys are sent from `keys`. Waits on the server as
    /// [`Patience::default`] says. Colour texels are kept for a renderer ([`Keep::Texels`]).
    pub async fn join(
        addr: SocketAddr,
        fingerprint: [u8; 32],
        hello: Hello,
        keys: KeySource,
    ) -> Result<Session> {
        Session::join_with(addr, fingerprint, hello, keys, Patience::default()).await
    }

    /// As [`Session::join`], with this patience.
    pub async fn join_with(
        addr: SocketAddr,
        fingerprint: [u8; 32],
        hello: Hello,
        keys: KeySource,
        patience: Patience,
    ) -> Result<Session> {
        Session::join_keeping(addr, fingerprint, hello, keys, patience, Keep::Texels).await
    }

    /// As [`Session::join_with`], keeping colour texels as `keep` says ([`Keep::Masks`]: a
    /// viewer that never draws).
    pub async fn join_keeping(
        addr: SocketAddr,
        fingerprint: [u8; 32],
        hello: Hello,
        keys: KeySource,
        patience: Patience,
        keep: Keep,
    ) -> Result<Session> {
        Session::join_any(&[addr], fingerprint, hello, keys, patience, keep).await
    }

    /// As [`Session::join_keeping`], at the first of `addrs` that joins, tried in turn; the
    /// others (and those the edges tell of) are where the session goes when it loses one
    /// (the module's docs). An error when none joins, naming each.
    pub async fn join_any(
        addrs: &[SocketAddr],
        fingerprint: [u8; 32],
        hello: Hello,
        keys: KeySource,
        patience: Patience,
        keep: Keep,
    ) -> Result<Session> {
        let Some(mut addresses) = Addresses::new(addrs.iter().copied()) else {
            bail!("no address to connect to");
        };
        let endpoint = join::endpoint_for(addresses.all(), fingerprint)?;
        let ipv6 = endpoint.local_addr().is_ok_and(|a| a.is_ipv6());
        let mut hello = hello;
        hello.budget = messages::clamp_budget(hello.budget);
        let (viewport, fov_y_deg) = (hello.viewport, hello.fov_y_deg);
        let (i, joined) = first_join(&endpoint, &addresses, hello.clone(), keep).await?;
        addresses.set_current(i);
        let addr = *addresses.current();
        let mut joined = joined;
        let welcome = joined.welcome.clone();
        let core = ClientCore::new(&welcome, hello.budget)
            .ok_or_else(|| anyhow!("a grid of 2^{} + 1", welcome.levels))?;
        let terrain = TerrainId::of(&welcome, joined.colors.coarsest());
        let empty = joined.colors.fresh();
        let colors = std::mem::replace(&mut joined.colors, empty);
        let scene = Scene::of(&welcome);
        let (status, _) = watch::channel(Status {
            state: State::Connected,
            gaps: Gaps::default(),
            welcome: welcome.clone(),
            addr,
            world: World::default(),
            edges_learned: 0,
            replay: None,
        });
        let link = Arc::new(Link {
            core: Mutex::new(core),
            colors: Mutex::new(colors),
            color_bytes_before: AtomicU64::new(0),
            keys: Mutex::new(KeyCore::default()),
            notify: Notify::new(),
            epoch: AtomicU64::new(0),
            conn: Mutex::new(Some(joined.conn.clone())),
            heard: Mutex::new(Instant::now()),
            frames: AtomicU64::new(0),
            bytes_before: AtomicU64::new(0),
            view: Mutex::new(None),
            status,
            addresses: Mutex::new(addresses),
            ipv6,
        });
        for news in std::mem::take(&mut joined.news) {
            link.news(&news);
        }
        let (control, outgoing) = mpsc::unbounded_channel();
        let supervisor = Supervisor {
            endpoint,
            hello: next_hello(hello, &welcome),
            patience,
            keep,
            terrain,
            link: link.clone(),
            outgoing,
        };
        let mut tasks = vec![tokio::spawn(supervisor.run(joined))];
        let phase = match &keys {
            KeySource::ScriptAt(_, phase) => Some(*phase),
            _ => None,
        };
        let steps: Option<Steps> = match keys {
            KeySource::None => None,
            KeySource::Latch => Some(Box::new(KeyCore::take_keys)),
            KeySource::Script(script) | KeySource::ScriptAt(script, _) => {
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
            tasks.push(tokio::spawn(send_keys(link.clone(), steps, phase)));
        }
        Ok(Session {
            scene,
            viewport,
            fov_y_deg,
            link,
            control,
            tasks,
        })
    }

    /// The address of the server connected now (the newest connection's, while
    /// reconnecting).
    pub fn addr(&self) -> SocketAddr {
        self.link.status.borrow().addr
    }

    /// Every address the session may go to, in turn: those given, then those learned.
    pub fn addresses(&self) -> Vec<SocketAddr> {
        lock(&self.link.addresses).all().to_vec()
    }

    /// The core (the newest mesh, the grid, the budget) of the current connection: held
    /// briefly, never across an await.
    pub fn core(&self) -> MutexGuard<'_, ClientCore> {
        lock(&self.link.core)
    }

    /// The current connection's colour cache: held briefly (the renderer drains it), never
    /// across an await.
    pub fn colors(&self) -> MutexGuard<'_, ColorCache> {
        lock(&self.link.colors)
    }

    /// The current connection's colour cache, taken (an empty one of the same layout left
    /// in its place): for a renderer made after the session (a screenshot).
    pub fn take_colors(&self) -> ColorCache {
        let mut c = lock(&self.link.colors);
        let empty = c.fresh();
        std::mem::replace(&mut *c, empty)
    }

    /// Colour tile bytes received so far, every connection's.
    pub fn color_bytes(&self) -> u64 {
        self.link.color_bytes_before.load(Ordering::Relaxed) + self.colors().bytes()
    }

    /// Where the session stands, its gaps and its newest welcome.
    pub fn status(&self) -> Status {
        self.link.status.borrow().clone()
    }

    /// The status as it changes (the state, reconnections; not each frame): to wait for a
    /// loss or a reconnection without polling.
    pub fn status_changes(&self) -> watch::Receiver<Status> {
        self.link.status.subscribe()
    }

    /// The newest connection's welcome.
    pub fn welcome(&self) -> Welcome {
        self.link.status.borrow().welcome.clone()
    }

    /// Connections made again after one was lost, so far.
    pub fn reconnects(&self) -> u32 {
        self.link.status.borrow().gaps.reconnects
    }

    /// The vehicle driven or followed now.
    pub fn vehicle(&self) -> u16 {
        self.link.status.borrow().welcome.vehicle
    }

    /// Sends what the core has for the control stream.
    fn flush(&self, core: &mut ClientCore) {
        while let Some(m) = core.poll_control() {
            let _ = self.control.send(Outgoing::Message(m));
        }
    }

    /// Waits for the next frame and takes it: decoded into the core's mesh (unless
    /// `decode` is false) and acknowledged. Waits through a reconnection. An error once
    /// the session has ended (frames still waiting are not taken) (lost for good, closed by the server, refused on
    /// reconnecting), or the server sent a frame it could not have sent (then the session
    /// ends, naming the server and the frame).
    pub async fn next_frame(&self, decode: bool) -> Result<Taken> {
        loop {
            let notified = self.link.notify.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if let Some(why) = self.link.ended() {
                bail!("{why}");
            }
            {
                let mut core = self.core();
                if core.has_frame() {
                    let started = Instant::now();
                    let taken = core.take(decode);
                    self.flush(&mut core);
                    drop(core);
                    return match taken {
                        Ok(Taken::Frame(mut r)) => {
                            r.decode_s = started.elapsed().as_secs_f64();
                            if let Some(seq) = r.input_seq {
                                r.latencies_ms = lock(&self.link.keys).applied(seq, r.arrived);
                            }
                            // Not a change to wake watchers for: read with `status`.
                            self.link.status.send_if_modified(|s| {
                                s.gaps.frame(r.arrived);
                                false
                            });
                            Ok(Taken::Frame(r))
                        }
                        Ok(other) => Ok(other),
                        Err(broken) => {
                            let why = format!("the server at {}: {broken}", self.addr());
                            self.link.end(why.clone());
                            self.link.close(close::PROTOCOL, b"a frame out of order");
                            Err(anyhow!(why))
                        }
                    };
                }
            }
            notified.await;
        }
    }

    /// Asks the server to make this spectator's frames follow vehicle `v` (the session's
    /// [`Session::vehicle`] changes when the server says it does).
    pub fn follow(&self, v: u16) {
        let _ = self
            .control
            .send(Outgoing::Message(ClientMessage::Follow(v)));
    }

    /// Steers a watched recording's clock (heeded from the viewer holding the controls:
    /// [`ReplayStatus::control`]).
    pub fn replay_control(&self, c: ReplayControl) {
        let _ = self
            .control
            .send(Outgoing::Message(ClientMessage::Replay(c)));
    }

    /// A watched recording's state as the server last said it; `None` for a live world.
    pub fn replay(&self) -> Option<ReplayStatus> {
        self.link.status.borrow().replay.clone()
    }

    /// Asks for `budget` triangles from now on (on this connection and the next).
    pub fn set_budget(&self, budget: u32) {
        let mut core = self.core();
        core.set_budget(budget);
        self.flush(&mut core);
    }

    /// Tells the server how the camera differs from the default at the vehicle (this
    /// connection, and the next).
    pub fn set_view(&self, view: ViewChange) {
        *lock(&self.link.view) = Some(view);
        let mut core = self.core();
        core.set_view(view);
        self.flush(&mut core);
    }

    /// The viewport the hello asked for, pixels.
    pub fn viewport(&self) -> [u32; 2] {
        self.viewport
    }

    /// The vertical field of view the hello asked for, degrees.
    pub fn fov_y_deg(&self) -> f32 {
        self.fov_y_deg
    }

    /// Draws the cut with geomorphs taking `ticks` world ticks (0: none), on this
    /// connection and the next ([`ClientCore::set_morph`]).
    pub fn set_morph(&self, ticks: u16) {
        self.core().set_morph(ticks);
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

    /// Frame bytes received so far, every connection's.
    pub fn bytes_in(&self) -> u64 {
        let core = self.core();
        self.link.bytes_before.load(Ordering::Relaxed) + core.bytes_in()
    }

    /// Says goodbye and closes the connection. True when the server heard: it took the
    /// whole control stream, goodbye included, or closed the connection with the code it
    /// closes with on a goodbye (bounded: a dead or slow server does not hold the viewer
    /// more than a second). False while reconnecting.
    pub async fn quit(&self) -> bool {
        let (tx, rx) = oneshot::channel();
        let heard = if self.control.send(Outgoing::Quit(tx)).is_ok() {
            tokio::time::timeout(Duration::from_secs(1), rx)
                .await
                .is_ok_and(|r| r.unwrap_or(false))
        } else {
            false
        };
        self.link.end("quit".into());
        self.link.close(close::BYE, b"quit");
        heard
    }
}

impl Drop for Session {
    /// However the session ends, the connection closes and the tasks stop.
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
        self.link.close(close::BYE, b"bye");
    }
}

/// The first connection: to the one address as it always was (the handshake within
/// QUIC's own idle timeout); with several, each in turn, its handshake within
/// [`HANDSHAKE_MANY`], until one joins. The address's place, and the joined connection.
async fn first_join(
    endpoint: &quinn::Endpoint,
    addresses: &Addresses<SocketAddr>,
    hello: Hello,
    keep: Keep,
) -> Result<(usize, Joined)> {
    if !addresses.many() {
        let addr = *addresses.current();
        let conn = endpoint
            .connect(addr, "roam")
            .with_context(|| format!("connecting to {addr}"))?
            .await
            .with_context(|| format!("connecting to {addr}"))?;
        return match tokio::time::timeout(JOIN_TIMEOUT, join::hello(conn, hello, keep)).await {
            Ok(j) => Ok((0, j.map_err(|e| anyhow!("{e}"))?)),
            Err(_) => bail!(
                "the server sent no welcome and coarsest colour tile within {} s",
                JOIN_TIMEOUT.as_secs()
            ),
        };
    }
    let mut failed = Vec::new();
    for (i, &addr) in addresses.all().iter().enumerate() {
        match attempt(endpoint, addr, HANDSHAKE_MANY, hello.clone(), keep).await {
            Ok(joined) => return Ok((i, joined)),
            Err(e) => failed.push(format!("{addr}: {e}")),
        }
    }
    bail!(
        "none of the {} addresses joined: {}",
        failed.len(),
        failed.join("; ")
    )
}
