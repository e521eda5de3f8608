//! A native viewer's session with a server, the API the window, the headless viewer and
//! `--bench` use: [`Session::join`] (and its variants) joins over QUIC (`quic.rs`: the
//! hello, the welcome, the colour layout checked against the grid, the coarsest colour
//! tile), then starts the tasks that run beside the caller (`connection.rs`): one that
//! drives each connection in turn (frames into the core, the server's control messages,
//! the core's control messages out, the silence watched) and reconnects as the
//! reconnection [`Supervisor`] says when one is lost, and a **key sender** that sends a
//! key datagram every 10 ms (the physics' step) from the core's latch or a script. The
//! caller takes frames with [`Session::next_frame`] and reads the [`Status`].
//!
//! **Addresses.** A session has one address or several ([`Session::join_any`]: the edges
//! of one world, `roam-client --connect A,B,…`), all behind the one certificate pin and
//! token; an edge's [`WorldNews::Edges`] adds the others it names
//! ([`crate::edges::Addresses`]). The first connection tries them in turn (each handshake
//! within [`HANDSHAKE_MANY`] when there are several); [`Session::addr`] is the one in use.
//!
//! **Reconnecting** follows the [`Supervisor`] (`supervisor.rs`, the page's too): a lost
//! or silent connection ([`Patience::silence`], 10 s; [`SILENCE_MANY`](crate::supervisor::SILENCE_MANY) with other
//! addresses) is made again at the next address in turn, from the same endpoint, with the
//! same certificate pin and token, presenting the driver's ticket ([`Hello::resume`]; a
//! spectator asks to follow the same vehicle), backing off from 100 ms to 2 s, for
//! [`Patience::reconnect_for`] (35 s: the server's 30 s hold and a margin). The new
//! connection starts a fresh [`ClientCore`] (frame numbers start again at 0) with the
//! budget and view asked so far; the keys go on (their numbers keep rising, so a resumed
//! vehicle's queue takes them as new). Its welcome must show the same terrain (grid,
//! scales, colour layout and coarsest tile), else the session ends. A new connection also
//! starts a fresh colour cache: the server sends the colour pyramid again from its
//! coarsest tile. Never reconnected after: a refusal, the server closing the connection
//! (a goodbye; shutting down, unless there are other addresses), a frame the server could
//! not have sent ([`Broken`]: the session ends with the server and the numbers named), the
//! viewer quitting, or the same address silent twice with no frame between.
//!
//! [`WorldNews::Edges`]: roam_protocol::messages::WorldNews::Edges

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::{Context, Result, anyhow, bail};
use roam_protocol::keys::{KeyStep, Keys};
use roam_protocol::messages::{
    self, ClientMessage, Hello, ReplayControl, ReplayStatus, ViewChange, Welcome, close,
};
use roam_protocol::script::Script;
use roam_protocol::sync::lock;
use tokio::sync::{Notify, mpsc, oneshot, watch};

use crate::color_cache::{ColorCache, Keep};
pub use crate::connection::Status;
use crate::connection::{Connections, Outgoing, Phase, Shared, Steps, attempt, send_keys};
pub use crate::conversation::describe;
use crate::conversation::{TerrainId, next_hello};
pub use crate::core::{Broken, ClientCore, Gaps, KeyCore, MAX_FRAME, Received, Taken};
use crate::edges::Addresses;
pub use crate::edges::World;
pub use crate::quic::connect;
use crate::quic::{self, Joined};
use crate::render::Scene;
use crate::supervisor::{HANDSHAKE_MANY, JOIN_TIMEOUT, Supervisor};
pub use crate::supervisor::{Patience, State};

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
    /// A script played in step with every other viewer of the process that plays one so:
    /// on the process's 10 ms grid, each step at the same instant for all, so a viewer
    /// that joins later starts where the others are (`--in-step`: a group driving one
    /// script from the same moment).
    InStep(Script),
}

/// A joined viewer.
pub struct Session {
    pub scene: Scene,
    /// The hello's viewport and field of view (the geomorphs' camera).
    viewport: [u32; 2],
    fov_y_deg: f32,
    shared: Arc<Shared>,
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
        let endpoint = quic::endpoint_for(addresses.all(), fingerprint)?;
        let ipv6 = endpoint.local_addr().is_ok_and(|a| a.is_ipv6());
        let mut hello = hello;
        hello.budget = messages::clamp_budget(hello.budget);
        let (viewport, fov_y_deg) = (hello.viewport, hello.fov_y_deg);
        let (i, joined) = first_join(&endpoint, &addresses, hello.clone(), keep).await?;
        addresses.set_current(i);
        let addr = *addresses.current();
        let mut joined = joined;
        let welcome = joined.welcome.clone();
        let levels = welcome.levels;
        let core = ClientCore::new(&welcome, hello.budget)
            .ok_or(crate::conversation::ConversationError::Levels { levels })?;
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
        let shared = Arc::new(Shared {
            core: Mutex::new(core),
            colors: Mutex::new(colors),
            color_bytes_before: AtomicU64::new(0),
            // Set from the start for a session that decodes no tile (the tiles read
            // before `skip_color` is called are not decoded either).
            skip_color: AtomicBool::new(keep == Keep::Counted),
            color_bytes_skipped: AtomicU64::new(0),
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
            shared.news(&news);
        }
        let (control, outgoing) = mpsc::unbounded_channel();
        let connections = Connections {
            endpoint,
            hello: next_hello(hello, &welcome),
            keep,
            supervisor: Supervisor::new(patience, terrain),
            shared: shared.clone(),
            outgoing,
        };
        let mut tasks = vec![tokio::spawn(connections.run(joined))];
        let phase = match &keys {
            KeySource::ScriptAt(_, phase) => Some(Phase::At(*phase)),
            KeySource::InStep(_) => Some(Phase::InStep),
            _ => None,
        };
        let steps: Option<Steps> = match keys {
            KeySource::None => None,
            KeySource::Latch => Some(Box::new(KeyCore::take_keys)),
            KeySource::Script(script)
            | KeySource::ScriptAt(script, _)
            | KeySource::InStep(script) => {
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
            tasks.push(tokio::spawn(send_keys(shared.clone(), steps, phase)));
        }
        Ok(Session {
            scene,
            viewport,
            fov_y_deg,
            shared,
            control,
            tasks,
        })
    }

    /// The address of the server connected now (the newest connection's, while
    /// reconnecting).
    pub fn addr(&self) -> SocketAddr {
        self.shared.status.borrow().addr
    }

    /// Every address the session may go to, in turn: those given, then those learned.
    pub fn addresses(&self) -> Vec<SocketAddr> {
        lock(&self.shared.addresses).all().to_vec()
    }

    /// The core (the newest mesh, the grid, the budget) of the current connection: held
    /// briefly, never across an await.
    pub fn core(&self) -> MutexGuard<'_, ClientCore> {
        lock(&self.shared.core)
    }

    /// The current connection's colour cache: held briefly (the renderer drains it), never
    /// across an await.
    pub fn colors(&self) -> MutexGuard<'_, ColorCache> {
        lock(&self.shared.colors)
    }

    /// The current connection's colour cache, taken (an empty one of the same layout left
    /// in its place): for a renderer made after the session (a screenshot).
    pub fn take_colors(&self) -> ColorCache {
        let mut c = lock(&self.shared.colors);
        let empty = c.fresh();
        std::mem::replace(&mut *c, empty)
    }

    /// Colour tile bytes received so far, every connection's.
    pub fn color_bytes(&self) -> u64 {
        self.shared.color_bytes_before.load(Ordering::Relaxed)
            + self.shared.color_bytes_skipped.load(Ordering::Relaxed)
            + self.colors().bytes()
    }

    /// From now on, colour and normal tiles are counted ([`Self::color_bytes`]) and let go
    /// undecoded: a load generator measures the server, not its own decoding (`roam-client
    /// --skip-decode`). Decoding them was three quarters of a generator's CPU with 50
    /// driving viewers (`perf`, 2026-12-07: `colormap::run`), the frames being undecoded
    /// already. The cache keeps what came before (the join's window); a session joined
    /// with [`crate::color_cache::Keep::Counted`] decoded none of it either.
    pub fn skip_color(&self) {
        self.shared.skip_color.store(true, Ordering::Relaxed);
    }

    /// Where the session stands, its gaps and its newest welcome.
    pub fn status(&self) -> Status {
        self.shared.status.borrow().clone()
    }

    /// The status as it changes (the state, reconnections; not each frame): to wait for a
    /// loss or a reconnection without polling.
    pub fn status_changes(&self) -> watch::Receiver<Status> {
        self.shared.status.subscribe()
    }

    /// The newest connection's welcome.
    pub fn welcome(&self) -> Welcome {
        self.shared.status.borrow().welcome.clone()
    }

    /// Connections made again after one was lost, so far.
    pub fn reconnects(&self) -> u32 {
        self.shared.status.borrow().gaps.reconnects
    }

    /// The vehicle driven or followed now.
    pub fn vehicle(&self) -> u16 {
        self.shared.status.borrow().welcome.vehicle
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
            let notified = self.shared.notify.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if let Some(why) = self.shared.ended() {
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
                                r.latencies_ms = lock(&self.shared.keys).applied(seq, r.arrived);
                            }
                            // Not a change to wake watchers for: read with `status`.
                            self.shared.status.send_if_modified(|s| {
                                s.gaps.frame(r.arrived);
                                false
                            });
                            Ok(Taken::Frame(r))
                        }
                        Ok(other) => Ok(other),
                        Err(broken) => {
                            let why = format!("the server at {}: {broken}", self.addr());
                            self.shared.end(why.clone());
                            self.shared.close(close::PROTOCOL, b"a frame out of order");
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
        self.shared.status.borrow().replay.clone()
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
        *lock(&self.shared.view) = Some(view);
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
        lock(&self.shared.keys).key_down(keys);
    }

    pub fn key_up(&self, keys: Keys) {
        lock(&self.shared.keys).key_up(keys);
    }

    /// Every key released (the window lost focus: nothing stays held).
    pub fn keys_released(&self) {
        lock(&self.shared.keys).keys_released();
    }

    /// Frame bytes received so far, every connection's.
    pub fn bytes_in(&self) -> u64 {
        let core = self.core();
        self.shared.bytes_before.load(Ordering::Relaxed) + core.bytes_in()
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
        self.shared.end(crate::supervisor::SessionEnd::Quit);
        self.shared.close(close::BYE, b"quit");
        heard
    }
}

impl Drop for Session {
    /// However the session ends, the connection closes and the tasks stop.
    fn drop(&mut self) {
        for t in &self.tasks {
            t.abort();
        }
        self.shared.close(close::BYE, b"bye");
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
        return match tokio::time::timeout(JOIN_TIMEOUT, quic::hello(conn, hello, keep)).await {
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
