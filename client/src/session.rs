//! The viewer's I/O: QUIC, tasks and the clock around the clock-free cores
//! ([`ClientCore`] and [`ColorCache`] per connection, [`KeyCore`] and [`Gaps`] per
//! session). It joins ([`crate::join`]: hello, welcome, the colour layout checked against
//! the grid, the coarsest colour tile), then runs beside the caller: a **supervisor** that
//! drives the connection (reading frames into the core, the server's control messages —
//! colour windows and tiles into the colour cache —, writing the core's control messages in
//! order) and reconnects when it is lost, and a **key sender** that sends a key
//! datagram every 10 ms (the physics' step) from the core's latch or a script. The window,
//! the headless viewer and `--bench` take frames with [`Session::next_frame`].
//!
//! **Reconnecting.** A connection is *lost* when QUIC says so (idle timeout, reset,
//! transport error) or when the server is *silent*: no frame, no control message and no
//! frame bytes for [`Patience::silence`] (10 s) after the welcome (the server sends frames
//! at the viewer's rate whatever the world does, so silence means a stuck path or server).
//! Then the session connects again to the same address, from the same endpoint, with the
//! same certificate pin and token, presenting the driver's ticket
//! ([`Hello::resume`]; a spectator asks to follow the same vehicle), after 100 ms, then
//! doubling to 2 s between attempts, each handshake bounded to 5 s, for
//! [`Patience::reconnect_for`] (35 s: the server's 30 s hold and a margin), and then gives
//! up with an error naming the server. The new connection starts a fresh [`ClientCore`]
//! (frame numbers start again at 0) with the budget and view asked so far; the keys go on
//! (their numbers keep rising, so a resumed vehicle's queue takes them as new). Its
//! welcome must show the same terrain (grid, scales, colour layout and coarsest tile), else
//! the session ends. A new connection also starts a fresh colour cache: the server sends
//! the colour pyramid again from its coarsest tile.
//!
//! Never reconnected after: a refusal (wrong token, version, a full server), the server
//! closing the connection (a goodbye, shutting down), a frame the server could not have
//! sent ([`crate::core::Broken`]: the session ends with the server and the numbers named),
//! the viewer quitting. **Silence reconnects once**: it may be a stuck path, but a server
//! that welcomes again and then stays silent (two silences with no frame between) is
//! stuck itself, and the session ends.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use roam_protocol::keys::{KeyStep, Keys};
use roam_protocol::messages::{self, Hello, Role, ViewChange, Welcome, close};
use roam_protocol::script::Script;
use tokio::sync::{Notify, mpsc, oneshot, watch};
use tokio::task::JoinSet;

use crate::color_cache::{ColorCache, Keep};
pub use crate::connection::MAX_FRAME;
use crate::connection::{
    End, Outgoing, attempt, failed_write, goodbye, quit_asked, read_control, read_frames,
    send_keys, write_control,
};
pub use crate::core::{Broken, ClientCore, Gaps, KeyCore, Received, Taken};
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
/// The first pause between reconnection attempts, doubled after each up to the second.
const BACKOFF_FIRST: Duration = Duration::from_millis(100);
const BACKOFF_MOST: Duration = Duration::from_secs(2);
/// A reconnection's QUIC handshake, at most (the next attempt starts afresh; the last
/// may end this much after [`Patience::reconnect_for`]).
const HANDSHAKE: Duration = Duration::from_secs(5);

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

/// What a session shows of itself: its state, its gaps and its newest welcome.
#[derive(Clone, Debug)]
pub struct Status {
    pub state: State,
    pub gaps: Gaps,
    /// The newest connection's welcome (the vehicle may change on a reconnection that
    /// did not get it back).
    pub welcome: Welcome,
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
}

/// Each physics step's keys, taken from the core's latch or a script.
pub(crate) type Steps = Box<dyn FnMut(&mut KeyCore) -> KeyStep + Send>;

/// What the tasks and the caller share.
pub(crate) struct Link {
    /// The connection's frames; replaced with each connection.
    core: Mutex<ClientCore>,
    /// The connection's colour tiles; replaced with each connection. Locked apart from
    /// the frames (and never while a tile decodes): the render thread drains it.
    pub(crate) colors: Mutex<ColorCache>,
    /// Colour bytes of the connections before this one.
    color_bytes_before: AtomicU64,
    /// Locked apart from the frames: a key state never waits on a decode. For the session.
    pub(crate) keys: Mutex<KeyCore>,
    /// Woken when a frame is offered or the session ends.
    notify: Notify,
    /// Bumped (under the core's lock) with each connection: bytes of an older one are not
    /// offered to the new core.
    epoch: AtomicU64,
    /// The connection the keys go on; none while reconnecting.
    pub(crate) conn: Mutex<Option<quinn::Connection>>,
    /// When the server was last heard (a frame's bytes, a control message, the welcome).
    heard: Mutex<Instant>,
    /// Frames offered, all connections together.
    frames: AtomicU64,
    /// Frame bytes of the connections before this one.
    bytes_before: AtomicU64,
    /// The newest view asked for, sent again on a new connection.
    view: Mutex<Option<ViewChange>>,
    status: watch::Sender<Status>,
}

impl Link {
    /// The session ends with `why` (the first reason given stands).
    fn end(&self, why: String) {
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

    /// Closes the current connection, if any.
    fn close(&self, code: u32, why: &[u8]) {
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
    addr: SocketAddr,
    pub scene: Scene,
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
        let endpoint = join::endpoint(addr, fingerprint)?;
        let conn = endpoint
            .connect(addr, "roam")
            .with_context(|| format!("connecting to {addr}"))?
            .await
            .with_context(|| format!("connecting to {addr}"))?;
        let mut hello = hello;
        hello.budget = messages::clamp_budget(hello.budget);
        let joined = match tokio::time::timeout(
            JOIN_TIMEOUT,
            join::hello(conn, hello.clone(), keep),
        )
        .await
        {
            Ok(j) => j.map_err(|e| anyhow!("{e}"))?,
            Err(_) => bail!(
                "the server sent no welcome and coarsest colour tile within {} s",
                JOIN_TIMEOUT.as_secs()
            ),
        };
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
        });
        let (control, outgoing) = mpsc::unbounded_channel();
        let supervisor = Supervisor {
            addr,
            endpoint,
            hello: next_hello(hello, &welcome),
            patience,
            keep,
            terrain,
            link: link.clone(),
            outgoing,
        };
        let mut tasks = vec![tokio::spawn(supervisor.run(joined))];
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
            tasks.push(tokio::spawn(send_keys(link.clone(), steps)));
        }
        Ok(Session {
            addr,
            scene,
            link,
            control,
            tasks,
        })
    }

    /// The server's address.
    pub fn addr(&self) -> SocketAddr {
        self.addr
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
                            let why = format!("the server at {}: {broken}", self.addr);
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

/// The connection's life and the reconnections: owns the control stream's writing end.
struct Supervisor {
    addr: SocketAddr,
    endpoint: quinn::Endpoint,
    /// The hello of the next connection (the newest ticket, the vehicle followed).
    hello: Hello,
    patience: Patience,
    /// What the colour caches keep.
    keep: Keep,
    /// The first connection's terrain: every later one must show it.
    terrain: TerrainId,
    link: Arc<Link>,
    outgoing: mpsc::UnboundedReceiver<Outgoing>,
}

impl Supervisor {
    async fn run(mut self, mut joined: Joined) {
        // Frames offered at the last silence: a second silence with none since ends it.
        let mut silent_at: Option<u64> = None;
        loop {
            let Joined {
                conn,
                mut send,
                recv,
                ..
            } = joined;
            let end = self.drive(&conn, &mut send, recv).await;
            let (why, silent) = match end {
                End::Quit => return self.link.end("quit".into()),
                End::Final(why) => {
                    conn.close(close::BYE.into(), b"bye");
                    return self.link.end(why);
                }
                End::Lost { why, silent } => (why, silent),
            };
            conn.close(0u32.into(), b"lost");
            *lock(&self.link.conn) = None;
            if silent {
                let frames = self.link.frames.load(Ordering::Relaxed);
                if silent_at == Some(frames) {
                    return self.link.end(format!(
                        "lost the server at {}: {why}, again right after reconnecting, with \
                         no frame between: the server welcomes but sends nothing",
                        self.addr
                    ));
                }
                silent_at = Some(frames);
            }
            self.link.status.send_modify(|s| {
                s.gaps.lost(Instant::now());
                s.state = State::Reconnecting {
                    why: why.clone(),
                    attempts: 0,
                };
            });
            joined = match self.reconnect(&why).await {
                Ok(Some(j)) => j,
                Ok(None) => return self.link.end("quit".into()),
                Err(why) => return self.link.end(why),
            };
            if self.link.ended().is_some() {
                joined.conn.close(close::BYE.into(), b"bye");
                return;
            }
            if let Err(why) = self.adopt(&mut joined) {
                joined.conn.close(close::BYE.into(), b"bye");
                return self.link.end(why);
            }
        }
    }

    /// Serves one connection until it ends: frames into the core, the server's control
    /// messages, the core's control messages out, the silence watched.
    async fn drive(
        &mut self,
        conn: &quinn::Connection,
        send: &mut quinn::SendStream,
        recv: quinn::RecvStream,
    ) -> End {
        let epoch = self.link.epoch.load(Ordering::Acquire);
        let (ends_tx, mut ends) = mpsc::channel(1);
        // Dropped on return: the readers stop with the connection's end.
        let mut tasks = JoinSet::new();
        tasks.spawn(read_frames(conn.clone(), self.link.clone(), epoch));
        tasks.spawn(read_control(recv, self.link.clone(), ends_tx));
        // A view to tell the new connection.
        let mut outbox = Vec::new();
        while let Some(m) = lock(&self.link.core).poll_control() {
            outbox.push(m);
        }
        for m in outbox {
            if let Err(e) = write_control(send, &m).await {
                return failed_write(conn, e);
            }
        }
        let silence = self.patience.silence;
        loop {
            let quiet_until = *lock(&self.link.heard) + silence;
            tokio::select! {
                o = self.outgoing.recv() => match o {
                    Some(Outgoing::Message(m)) => {
                        if let Err(e) = write_control(send, &m).await {
                            return failed_write(conn, e);
                        }
                    }
                    Some(Outgoing::Quit(heard)) => {
                        let _ = heard.send(goodbye(send).await);
                        return End::Quit;
                    }
                    None => return End::Quit,
                },
                Some(end) = ends.recv() => return end,
                e = conn.closed() => return End::of(&e),
                () = tokio::time::sleep_until(quiet_until.into()) => {
                    if lock(&self.link.heard).elapsed() >= silence {
                        return End::Lost {
                            why: format!(
                                "no frame or message from the server for {}",
                                secs(silence)
                            ),
                            silent: true,
                        };
                    }
                }
            }
        }
    }

    /// Connects again until a connection joins, the session quits (`None`), or the time
    /// runs out or the server refuses (an error, in words).
    async fn reconnect(&mut self, why: &str) -> Result<Option<Joined>, String> {
        let deadline = Instant::now() + self.patience.reconnect_for;
        let mut backoff = BACKOFF_FIRST;
        let mut attempts = 0u32;
        let lost =
            |more: String| format!("lost the server at {}: {why}; {more}", self.addr, why = why);
        loop {
            attempts += 1;
            self.link.status.send_modify(|s| {
                if let State::Reconnecting { attempts: a, .. } = &mut s.state {
                    *a = attempts;
                }
            });
            // An attempt begun before the deadline has its whole handshake.
            let hello = self.hello_now();
            let attempt = attempt(&self.endpoint, self.addr, HANDSHAKE, hello, self.keep);
            let result = tokio::select! {
                r = attempt => r,
                () = quit_asked(&mut self.outgoing) => {
                    // The attempt in flight may already have been welcomed (and the vehicle
                    // resumed): close it with the goodbye code, so the server frees the
                    // vehicle rather than holding it.
                    self.endpoint.close(close::BYE.into(), b"quit");
                    return Ok(None);
                }
            };
            let last = match result {
                Ok(j) => {
                    let found = TerrainId::of(&j.welcome, j.colors.coarsest());
                    return match self.terrain.differences(&found) {
                        None => Ok(Some(j)),
                        Some(d) => {
                            j.conn.close(close::BYE.into(), b"another terrain");
                            Err(lost(format!("the server changed its terrain: {d}")))
                        }
                    };
                }
                Err(e) if !e.lost => return Err(lost(format!("reconnecting: {e}"))),
                Err(e) => e.message,
            };
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() || self.link.ended().is_some() {
                return Err(lost(format!(
                    "tried to reconnect for {} s ({attempts} attempts; the last: {last})",
                    self.patience.reconnect_for.as_secs()
                )));
            }
            tokio::select! {
                () = tokio::time::sleep(backoff.min(left)) => {}
                () = quit_asked(&mut self.outgoing) => return Ok(None),
            }
            backoff = (backoff * 2).min(BACKOFF_MOST);
        }
    }

    /// The next hello, asking for the budget asked so far.
    fn hello_now(&self) -> Hello {
        Hello {
            budget: lock(&self.link.core).budget(),
            ..self.hello.clone()
        }
    }

    /// Makes `joined` the session's connection: a fresh core (with the budget and the view
    /// asked so far) and its colour cache, the keys sent on it, the reconnection counted.
    fn adopt(&mut self, joined: &mut Joined) -> Result<(), String> {
        let welcome = joined.welcome.clone();
        {
            let mut core = lock(&self.link.core);
            let mut fresh = ClientCore::new(&welcome, core.budget())
                .ok_or_else(|| format!("a grid of 2^{} + 1", welcome.levels))?;
            if let Some(view) = *lock(&self.link.view) {
                fresh.set_view(view);
            }
            self.link
                .bytes_before
                .fetch_add(core.bytes_in(), Ordering::Relaxed);
            self.link.epoch.fetch_add(1, Ordering::AcqRel);
            *core = fresh;
        }
        {
            let mut colors = lock(&self.link.colors);
            let joined_colors = std::mem::replace(&mut joined.colors, colors.fresh());
            self.link
                .color_bytes_before
                .fetch_add(colors.bytes(), Ordering::Relaxed);
            *colors = joined_colors;
        }
        self.link.heard();
        *lock(&self.link.conn) = Some(joined.conn.clone());
        let driver = self.hello.role == Role::Driver;
        self.link.status.send_modify(|s| {
            s.gaps.reconnected(driver && welcome.resumed);
            s.state = State::Connected;
            s.welcome = welcome.clone();
        });
        self.hello = next_hello(self.hello.clone(), &welcome);
        Ok(())
    }
}
