//! The native session's I/O: what its tasks share ([`Shared`]: the connection's clock-free
//! cores, the keys, the status, the addresses), each connection's tasks, and
//! [`Connections`], which drives one connection after another as the reconnection
//! supervisor ([`crate::supervisor::Supervisor`], shared with the page) decides.
//!
//! A connection's tasks: the frames read into the core (datagrams, and streams read to
//! their end, each chunk news of the server), the server's control messages after the
//! join (colour windows and tiles into the colour cache, each tile decoded outside its
//! lock; an edge's news of its world to the status; a goodbye ends the connection, and a
//! colour message the cache refuses ends it as the server's protocol error), the core's
//! control messages written in order (each within [`CONTROL_TIMEOUT`]), the goodbye said
//! when the viewer quits, and the silence watched
//! ([`crate::supervisor::Patience::allowed_silence`]); one attempt to join ([`attempt`]:
//! the handshake and then the welcome bounded); and the key sender, every 10 ms (on the
//! process's 10 ms grid for a script given a phase). This is a shell: it reads the clock (when the server was last heard,
//! when a frame arrived, the key clock, the timeouts) and hands the instants to the cores
//! and the supervisor; the supervisor decides whether a connection's end ends the session.

use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Result, anyhow};
use roam_link::wire;
use roam_protocol::keys::KeyStep;
use roam_protocol::messages::{
    self, ClientMessage, Hello, Reason, ReplayStatus, Role, ServerMessage, ViewChange, Welcome,
    WorldNews, close,
};
use roam_protocol::sync::lock;
use tokio::sync::{Notify, mpsc, oneshot, watch};
use tokio::task::JoinSet;

use crate::color_cache::{ColorCache, Keep};
use crate::conversation::{ConversationError, TerrainId, Told, next_hello, take_control};
use crate::core::{ClientCore, Gaps, KeyCore, MAX_FRAME};
use crate::edges::{Addresses, World, native_edges};
use crate::quic::{self, JoinError, Joined};
use crate::supervisor::{End, JOIN_TIMEOUT, SessionEnd, State, Supervisor, secs};

/// How long a control message may take to leave (a server that stops reading does not
/// hold the viewer).
pub(crate) const CONTROL_TIMEOUT: Duration = Duration::from_secs(2);

/// What the control writer is asked to do.
pub(crate) enum Outgoing {
    Message(ClientMessage),
    /// Say goodbye, finish the stream, and tell whether the server heard.
    Quit(oneshot::Sender<bool>),
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

/// Each physics step's keys, taken from the core's latch or a script.
pub(crate) type Steps = Box<dyn FnMut(&mut KeyCore) -> KeyStep + Send>;

/// What a session's tasks and its handle share.
pub(crate) struct Shared {
    /// The connection's frames; replaced with each connection.
    pub(crate) core: Mutex<ClientCore>,
    /// The connection's colour tiles; replaced with each connection. Locked apart from
    /// the frames (and never while a tile decodes): the render thread drains it.
    pub(crate) colors: Mutex<ColorCache>,
    /// Colour bytes of the connections before this one.
    pub(crate) color_bytes_before: AtomicU64,
    /// Colour and normal tiles are counted, not decoded ([`crate::Session::skip_color`]).
    pub(crate) skip_color: AtomicBool,
    /// The bytes of the tiles not decoded, every connection's.
    pub(crate) color_bytes_skipped: AtomicU64,
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
    pub(crate) ipv6: bool,
}

impl Shared {
    /// The session ends with `why` (the first reason given stands).
    pub(crate) fn end(&self, why: impl std::fmt::Display) {
        self.status.send_if_modified(|s| {
            if matches!(s.state, State::Ended(_)) {
                return false;
            }
            s.state = State::Ended(why.to_string());
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

/// Returns once the viewer quits (answering that the server did not hear: there is no
/// connection to say goodbye on) or the session is dropped; control messages meanwhile are
/// dropped (the next hello asks for the budget, and the view is sent again).
pub(crate) async fn quit_asked(outgoing: &mut mpsc::UnboundedReceiver<Outgoing>) {
    loop {
        match outgoing.recv().await {
            Some(Outgoing::Message(_)) => {}
            Some(Outgoing::Quit(heard)) => {
                let _ = heard.send(false);
                return;
            }
            None => return,
        }
    }
}

/// How a connection whose control message could not be written ends: as the connection
/// did, if it did; else for good (the server stopped reading).
pub(crate) fn failed_write(conn: &quinn::Connection, e: anyhow::Error) -> End {
    match conn.close_reason() {
        Some(e) => quic::end_of(&e),
        None => End::Final(format!("{e:#}")),
    }
}

/// Says goodbye, finishes the stream, and tells whether the server heard.
pub(crate) async fn goodbye(send: &mut quinn::SendStream) -> bool {
    let said = async {
        wire::write(send, &ClientMessage::Bye(Reason::Quit)).await?;
        send.finish()?;
        match send.stopped().await {
            Ok(_) => anyhow::Ok(true),
            Err(quinn::StoppedError::ConnectionLost(
                quinn::ConnectionError::ApplicationClosed(c),
            )) => Ok(c.error_code == close::BYE.into()),
            Err(e) => Err(e.into()),
        }
    };
    matches!(said.await, Ok(true))
}

/// The server's control messages after the join: each is news of the server; colour
/// windows and tiles go to the colour cache, an edge's news of its world to the session
/// ([`Shared::news`]); a goodbye ends the session, and so does anything else (not the
/// protocol). Ends with the stream.
pub(crate) async fn read_control(
    mut recv: quinn::RecvStream,
    shared: Arc<Shared>,
    ends: mpsc::Sender<End>,
) {
    let mut rgb = Vec::new();
    let end = loop {
        let msg = match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await {
            Ok(m) => m,
            // The stream or the connection ended: the connection tells why.
            Err(wire::WireError::Closed | wire::WireError::Read(_)) => return,
            Err(e) => break End::Final(format!("the server's control stream: {e}")),
        };
        shared.heard();
        if shared.skip_color.load(Ordering::Relaxed)
            && let ServerMessage::ColorTile { data, .. } | ServerMessage::NormalTile { data, .. } =
                &msg
        {
            let bytes = data.len() as u64;
            shared
                .color_bytes_skipped
                .fetch_add(bytes, Ordering::Relaxed);
            continue;
        }
        match take_control(&msg, &mut rgb, || lock(&shared.colors)) {
            Ok(None) => {}
            Ok(Some(Told::News(news))) => shared.news(news),
            Ok(Some(Told::Following(v))) => shared.following(v),
            Ok(Some(Told::Replay(s))) => shared.replay(s),
            Err(why @ ConversationError::Goodbye(Reason::Shutdown)) => {
                break End::Shutdown(why.to_string());
            }
            Err(why) => break End::Final(why.to_string()),
        }
    };
    let _ = ends.send(end).await;
}

/// Reads frames into the core as they arrive: datagrams (small frames), and streams, each
/// read to its end in a task of its own (a stream the server abandons is skipped). Every
/// chunk counts as news of the server (a large frame on a slow path is not silence).
pub(crate) async fn read_frames(conn: quinn::Connection, shared: Arc<Shared>, epoch: u64) {
    let datagrams = async {
        while let Ok(bytes) = conn.read_datagram().await {
            shared.offer(epoch, &bytes);
        }
    };
    let streams = async {
        let mut readers = JoinSet::new();
        while let Ok(stream) = conn.accept_uni().await {
            readers.spawn(read_stream(stream, shared.clone(), epoch));
            while readers.try_join_next().is_some() {}
        }
    };
    tokio::select! {
        () = datagrams => {}
        () = streams => {}
    }
}

/// One frame's stream, read to its end (at most [`MAX_FRAME`] bytes) and offered.
async fn read_stream(mut stream: quinn::RecvStream, shared: Arc<Shared>, epoch: u64) {
    let mut bytes = Vec::new();
    loop {
        match stream.read_chunk(MAX_FRAME, true).await {
            Ok(Some(chunk)) => {
                shared.heard();
                if bytes.len() + chunk.bytes.len() > MAX_FRAME {
                    let _ = stream.stop(0u32.into());
                    return;
                }
                bytes.extend_from_slice(&chunk.bytes);
            }
            Ok(None) => break,
            Err(_) => return,
        }
    }
    shared.offer(epoch, &bytes);
}

/// One attempt to join: the handshake within `handshake`, the welcome and the coarsest
/// colour tile within [`JOIN_TIMEOUT`].
pub(crate) async fn attempt(
    endpoint: &quinn::Endpoint,
    addr: SocketAddr,
    handshake: Duration,
    hello: Hello,
    keep: Keep,
) -> Result<Joined, JoinError> {
    let connecting = endpoint
        .connect(addr, "roam")
        .map_err(|e| JoinError::fatal(format!("connecting: {e}")))?;
    let conn = match tokio::time::timeout(handshake, connecting).await {
        Ok(Ok(conn)) => conn,
        Ok(Err(e)) => {
            let (lost, why) = quic::ending(&e);
            return Err(JoinError { lost, message: why });
        }
        Err(_) => {
            return Err(JoinError::lost(format!(
                "no handshake within {}",
                secs(handshake)
            )));
        }
    };
    match tokio::time::timeout(JOIN_TIMEOUT, quic::hello(conn.clone(), hello, keep)).await {
        Ok(r) => r.inspect_err(|_| conn.close(close::BYE.into(), b"bye")),
        Err(_) => {
            conn.close(0u32.into(), b"too slow");
            Err(JoinError::lost(format!(
                "no welcome and coarsest colour tile within {} s",
                JOIN_TIMEOUT.as_secs()
            )))
        }
    }
}

/// Writes a control message, within [`CONTROL_TIMEOUT`].
pub(crate) async fn write_control(send: &mut quinn::SendStream, msg: &ClientMessage) -> Result<()> {
    tokio::time::timeout(CONTROL_TIMEOUT, wire::write(send, msg))
        .await
        .map_err(|_| anyhow!("the server stopped reading the control stream"))??;
    Ok(())
}

/// Sends a key datagram every 10 ms (the physics' step) with the step's keys from
/// `steps`, on whichever connection is up: the core numbers the state and repeats the
/// last eight, so a lost datagram costs nothing. While reconnecting the steps go on (and
/// are numbered) unsent. Ends with the session. With a `phase`, the clock ticks at that
/// offset on the process's 10 ms grid (`KeySource::ScriptAt`); in step, on the grid with
/// the steps since the grid began skipped (`KeySource::InStep`); without, from now.
pub(crate) async fn send_keys(shared: Arc<Shared>, mut steps: Steps, phase: Option<Phase>) {
    const STEP: Duration = Duration::from_millis(10);
    // The key datagrams acknowledge the frames from now on (a core made again on a
    // reconnection keeps the setting: `Connections::adopt`).
    lock(&shared.core).set_acks_in_datagrams();
    let now = tokio::time::Instant::now();
    let start = match phase {
        Some(Phase::At(phase)) => on_grid(now, STEP, phase),
        Some(Phase::InStep) => on_grid(now, STEP, Duration::ZERO),
        None => now,
    };
    let in_step = matches!(phase, Some(Phase::InStep));
    // In step, step k of the script is played at the grid's start + k steps by every
    // viewer: the steps of ticks missed (a loaded process) are skipped, never played late.
    let mut played: u128 = 0;
    let mut tick = tokio::time::interval_at(start, STEP);
    tick.set_missed_tick_behavior(if in_step {
        tokio::time::MissedTickBehavior::Skip
    } else {
        tokio::time::MissedTickBehavior::Delay
    });
    loop {
        let at = tick.tick().await;
        if shared.ended().is_some() {
            return;
        }
        let datagram = {
            let mut keys = lock(&shared.keys);
            if in_step {
                let due = at.saturating_duration_since(grid_epoch(at)).as_nanos() / STEP.as_nanos();
                while played < due {
                    steps(&mut keys);
                    played += 1;
                }
                played += 1;
            }
            let step = steps(&mut keys);
            let acked = lock(&shared.core).acked();
            keys.key_datagram(step, Instant::now(), acked)
        };
        let conn = lock(&shared.conn).clone();
        let mut bytes = Vec::new();
        if let Some(conn) = conn
            && messages::encode(&datagram, &mut bytes).is_ok()
        {
            let _ = conn.send_datagram(bytes.into());
        }
    }
}

/// The first instant at or after `now` that is `phase` past a multiple of `step` counted
/// from the process's first call (one grid for every clock in the process).
fn on_grid(now: tokio::time::Instant, step: Duration, phase: Duration) -> tokio::time::Instant {
    let epoch = grid_epoch(now);
    let at = grid_after(
        now.duration_since(epoch).as_nanos(),
        step.as_nanos(),
        phase.as_nanos(),
    );
    epoch + Duration::from_nanos(u64::try_from(at).unwrap_or(u64::MAX))
}

/// Where the process's grid begins: the first call's `now`.
fn grid_epoch(now: tokio::time::Instant) -> tokio::time::Instant {
    static EPOCH: std::sync::OnceLock<tokio::time::Instant> = std::sync::OnceLock::new();
    *EPOCH.get_or_init(|| now)
}

/// Where a script's key clock ticks.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Phase {
    /// At this offset on the process's 10 ms grid.
    At(Duration),
    /// On the grid, at the step every viewer in step is at.
    InStep,
}

/// The first `k × step + phase mod step` at or after `since` (nanoseconds).
fn grid_after(since: u128, step: u128, phase: u128) -> u128 {
    let step = step.max(1);
    let offset = phase % step;
    since.saturating_sub(offset).div_ceil(step) * step + offset
}

/// A session's connections, one after another: each driven until it ends, then the
/// supervisor asked whether and how to connect again. Owns the control stream's writing
/// end.
pub(crate) struct Connections {
    pub(crate) endpoint: quinn::Endpoint,
    /// The hello of the next connection (the newest ticket, the vehicle followed).
    pub(crate) hello: Hello,
    /// What the colour caches keep.
    pub(crate) keep: Keep,
    pub(crate) supervisor: Supervisor,
    pub(crate) shared: Arc<Shared>,
    pub(crate) outgoing: mpsc::UnboundedReceiver<Outgoing>,
}

impl Connections {
    pub(crate) async fn run(mut self, mut joined: Joined) {
        loop {
            let Joined {
                conn,
                mut send,
                recv,
                ..
            } = joined;
            let end = self.drive(&conn, &mut send, recv).await;
            let (here, many) = {
                let a = lock(&self.shared.addresses);
                (a.index(), a.many())
            };
            let again = end.worth_reconnecting(many);
            let quit = end == End::Quit;
            let frames = self.shared.frames.load(Ordering::Relaxed);
            let verdict =
                self.supervisor
                    .ended(end, &self.addr(), here, many, frames, Instant::now());
            if again {
                // Not a goodbye: the server holds a driver's vehicle for the reconnection.
                conn.close(0u32.into(), b"lost");
                *lock(&self.shared.conn) = None;
            } else if !quit {
                conn.close(close::BYE.into(), b"bye");
            }
            if let Err(why) = verdict {
                return self.shared.end(why);
            }
            joined = match self.reconnect(Instant::now()).await {
                Ok(Some(j)) => j,
                Ok(None) => return self.shared.end(SessionEnd::Quit),
                Err(why) => return self.shared.end(why),
            };
            if self.shared.ended().is_some() {
                joined.conn.close(close::BYE.into(), b"bye");
                return;
            }
            if let Err(why) = self.adopt(&mut joined) {
                joined.conn.close(close::BYE.into(), b"bye");
                return self.shared.end(why);
            }
        }
    }

    /// The address in use.
    fn addr(&self) -> SocketAddr {
        *lock(&self.shared.addresses).current()
    }

    /// Serves one connection until it ends: frames into the core, the server's control
    /// messages, the core's control messages out, the silence watched.
    async fn drive(
        &mut self,
        conn: &quinn::Connection,
        send: &mut quinn::SendStream,
        recv: quinn::RecvStream,
    ) -> End {
        let epoch = self.shared.epoch.load(Ordering::Acquire);
        let (ends_tx, mut ends) = mpsc::channel(1);
        // Dropped on return: the readers stop with the connection's end.
        let mut tasks = JoinSet::new();
        tasks.spawn(read_frames(conn.clone(), self.shared.clone(), epoch));
        tasks.spawn(read_control(recv, self.shared.clone(), ends_tx));
        // A view to tell the new connection.
        let mut outbox = Vec::new();
        while let Some(m) = lock(&self.shared.core).poll_control() {
            outbox.push(m);
        }
        for m in outbox {
            if let Err(e) = write_control(send, &m).await {
                return failed_write(conn, e);
            }
        }
        loop {
            // Edges learned meanwhile shorten it.
            let many = lock(&self.shared.addresses).many();
            let silence = self.supervisor.patience().allowed_silence(many);
            let quiet_until = *lock(&self.shared.heard) + silence;
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
                e = conn.closed() => return quic::end_of(&e),
                () = tokio::time::sleep_until(quiet_until.into()) => {
                    if lock(&self.shared.heard).elapsed() >= silence {
                        return End::silence(silence);
                    }
                }
            }
        }
    }

    /// Connects again, each attempt to the next address in turn, as the supervisor says,
    /// until a connection joins, the session quits (`None`), or the supervisor gives up
    /// (an error, in words). `lost_at`: when the connection was lost.
    async fn reconnect(&mut self, lost_at: Instant) -> Result<Option<Joined>, SessionEnd> {
        let mut lost_at = Some(lost_at);
        loop {
            let (addr, many) = {
                let mut a = lock(&self.shared.addresses);
                (*a.after_loss(), a.many())
            };
            let next = self.supervisor.attempt(many);
            let state = self.supervisor.state();
            self.shared.status.send_modify(|s| {
                if let Some(at) = lost_at.take() {
                    s.gaps.lost(at);
                }
                s.state = state;
            });
            let hello = self.hello_now();
            let attempt = attempt(&self.endpoint, addr, next.handshake, hello, self.keep);
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
            let e = match result {
                Ok(j) => {
                    let found = TerrainId::of(&j.welcome, j.colors.coarsest());
                    return match self.supervisor.joined(&found) {
                        Ok(()) => Ok(Some(j)),
                        Err(why) => {
                            j.conn.close(close::BYE.into(), b"another terrain");
                            Err(why)
                        }
                    };
                }
                Err(e) => e,
            };
            let pause = self
                .supervisor
                .failed(&addr, e.lost, &e.message, Instant::now())?;
            if self.shared.ended().is_some() {
                return Ok(None);
            }
            tokio::select! {
                () = tokio::time::sleep(pause) => {}
                () = quit_asked(&mut self.outgoing) => return Ok(None),
            }
        }
    }

    /// The next hello, asking for the budget asked so far.
    fn hello_now(&self) -> Hello {
        Hello {
            budget: lock(&self.shared.core).budget(),
            ..self.hello.clone()
        }
    }

    /// Makes `joined` the session's connection: a fresh core (with the budget and the view
    /// asked so far) and its colour cache, the keys sent on it, the reconnection counted.
    fn adopt(&mut self, joined: &mut Joined) -> Result<(), ConversationError> {
        let welcome = joined.welcome.clone();
        {
            let mut core = lock(&self.shared.core);
            let levels = welcome.levels;
            let mut fresh = ClientCore::new(&welcome, core.budget())
                .ok_or(ConversationError::Levels { levels })?;
            if let Some(view) = *lock(&self.shared.view) {
                fresh.set_view(view);
            }
            if let Some(ticks) = core.morph_ticks() {
                fresh.set_morph(ticks);
            }
            // A watched recording stays one across a reconnection (its status may come
            // after the new connection's first frames).
            if core.is_replay() {
                fresh.set_replay();
            }
            if core.acks_in_datagrams() {
                fresh.set_acks_in_datagrams();
            }
            self.shared
                .bytes_before
                .fetch_add(core.bytes_in(), Ordering::Relaxed);
            self.shared.epoch.fetch_add(1, Ordering::AcqRel);
            *core = fresh;
        }
        {
            let mut colors = lock(&self.shared.colors);
            let joined_colors = std::mem::replace(&mut joined.colors, colors.fresh());
            self.shared
                .color_bytes_before
                .fetch_add(colors.bytes(), Ordering::Relaxed);
            *colors = joined_colors;
        }
        self.shared.heard();
        *lock(&self.shared.conn) = Some(joined.conn.clone());
        let driver = self.hello.role == Role::Driver;
        let addr = self.addr();
        let now = Instant::now();
        self.shared.status.send_modify(|s| {
            s.gaps.reconnected(driver && welcome.resumed);
            s.state = State::Connected;
            s.welcome = welcome.clone();
            s.addr = addr;
            // This edge says so if its world is gone too.
            s.world.back(now);
        });
        for news in std::mem::take(&mut joined.news) {
            self.shared.news(&news);
        }
        self.hello = next_hello(self.hello.clone(), &welcome);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::grid_after;

    #[test]
    fn key_clocks_start_on_their_phase_of_the_grid() {
        let check = |since, phase, expected| assert_eq!(grid_after(since, 10, phase), expected);
        check(0, 0, 0);
        check(0, 5, 5);
        check(5, 5, 5);
        check(6, 5, 15);
        check(10, 0, 10);
        check(11, 0, 20);
        check(3, 25, 5); // a phase past the step wraps
    }
}
