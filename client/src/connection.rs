//! Each connection's tasks and words, and the [`Supervisor`] that runs them one
//! connection after another. A connection's tasks have no clock (the supervisor bounds
//! them in time): the frames read into the session's core (datagrams, and streams read to
//! their end, each chunk news of the server), the server's control messages after the
//! join (colour windows and tiles into the colour cache, each tile decoded outside its
//! lock; an edge's news of its world to the session; a goodbye ends the session; a colour
//! message the cache refuses ends it as the server's protocol error), the goodbye said
//! when the viewer quits, and how a connection ended ([`End`]: quit, lost, the server
//! shutting down, or for good); one attempt to join (bounded by the session's timeouts),
//! and the key sender.
//!
//! **The supervisor** ([`crate::session`] starts it) drives each connection (the readers
//! above, the core's control messages written in order, the silence watched:
//! [`Patience::silence`], or [`SILENCE_MANY`] when there are other addresses), and when
//! one is lost, reconnects: to the next address in turn ([`Addresses::after_loss`]), each
//! handshake within 5 s ([`HANDSHAKE_MANY`] with other addresses), backing off from
//! 100 ms to 2 s, for [`Patience::reconnect_for`]; the silence rule counted per address
//! ([`Silences`]). With other addresses, a server shutting down is a loss too (the next
//! edge takes the viewer); alone, it ends the session.
//!
//! [`Addresses::after_loss`]: crate::edges::Addresses::after_loss

use std::net::SocketAddr;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use anyhow::{Result, anyhow};
use roam_link::wire;
use roam_protocol::messages::{self, ClientMessage, Hello, Reason, Role, ServerMessage, close};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;

use crate::color_cache::Keep;
use crate::core::ClientCore;
use crate::edges::{HANDSHAKE_MANY, SILENCE_MANY, Silences};
use crate::join::{self, JoinError, Joined, TerrainId};
use crate::joining::{Told, next_hello, take_control};
use crate::session::{CONTROL_TIMEOUT, JOIN_TIMEOUT, Link, Patience, State, Steps, lock, secs};

pub use crate::core::MAX_FRAME;

/// What the control writer is asked to do.
pub enum Outgoing {
    Message(ClientMessage),
    /// Say goodbye, finish the stream, and tell whether the server heard.
    Quit(oneshot::Sender<bool>),
}

/// How a connection ended.
pub enum End {
    /// The viewer quit (or the session was dropped).
    Quit,
    /// Lost: worth connecting again. `silent`: the server went silent.
    Lost { why: String, silent: bool },
    /// The server is shutting down (it said goodbye so, or closed with that code): for
    /// good when there is no other address to go to.
    Shutdown(String),
    /// For good.
    Final(String),
}

impl End {
    pub fn of(e: &quinn::ConnectionError) -> End {
        if let quinn::ConnectionError::ApplicationClosed(c) = e
            && c.error_code == close::SHUTDOWN.into()
        {
            return End::Shutdown(join::ending(e).1);
        }
        match join::ending(e) {
            (true, why) => End::Lost { why, silent: false },
            (false, why) => End::Final(why),
        }
    }
}

/// Returns once the viewer quits (answering that the server did not hear: there is no
/// connection to say goodbye on) or the session is dropped; control messages meanwhile are
/// dropped (the next hello asks for the budget, and the view is sent again).
pub async fn quit_asked(outgoing: &mut mpsc::UnboundedReceiver<Outgoing>) {
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
pub fn failed_write(conn: &quinn::Connection, e: anyhow::Error) -> End {
    match conn.close_reason() {
        Some(e) => End::of(&e),
        None => End::Final(format!("{e:#}")),
    }
}

/// Says goodbye, finishes the stream, and tells whether the server heard.
pub async fn goodbye(send: &mut quinn::SendStream) -> bool {
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
/// ([`Link::news`]); a goodbye ends the session, and so does anything else (not the
/// protocol). Ends with the stream.
pub async fn read_control(mut recv: quinn::RecvStream, link: Arc<Link>, ends: mpsc::Sender<End>) {
    let mut rgb = Vec::new();
    let end = loop {
        let msg = match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await {
            Ok(m) => m,
            // The stream or the connection ended: the connection tells why.
            Err(wire::WireError::Closed | wire::WireError::Read(_)) => return,
            Err(e) => break End::Final(format!("the server's control stream: {e}")),
        };
        link.heard();
        match take_control(&msg, &mut rgb, || lock(&link.colors)) {
            Ok(None) => {}
            Ok(Some(Told::News(news))) => link.news(news),
            Ok(Some(Told::Following(v))) => link.following(v),
            Ok(Some(Told::Replay(s))) => link.replay(s),
            Err(why) if msg == ServerMessage::Bye(Reason::Shutdown) => break End::Shutdown(why),
            Err(why) => break End::Final(why),
        }
    };
    let _ = ends.send(end).await;
}

/// Reads frames into the core as they arrive: datagrams (small frames), and streams, each
/// read to its end in a task of its own (a stream the server abandons is skipped). Every
/// chunk counts as news of the server (a large frame on a slow link is not silence).
pub async fn read_frames(conn: quinn::Connection, link: Arc<Link>, epoch: u64) {
    let datagrams = async {
        while let Ok(bytes) = conn.read_datagram().await {
            link.offer(epoch, &bytes);
        }
    };
    let streams = async {
        let mut readers = JoinSet::new();
        while let Ok(stream) = conn.accept_uni().await {
            readers.spawn(read_stream(stream, link.clone(), epoch));
            while readers.try_join_next().is_some() {}
        }
    };
    tokio::select! {
        () = datagrams => {}
        () = streams => {}
    }
}

/// One frame's stream, read to its end (at most [`MAX_FRAME`] bytes) and offered.
async fn read_stream(mut stream: quinn::RecvStream, link: Arc<Link>, epoch: u64) {
    let mut bytes = Vec::new();
    loop {
        match stream.read_chunk(MAX_FRAME, true).await {
            Ok(Some(chunk)) => {
                link.heard();
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
    link.offer(epoch, &bytes);
}

/// One attempt to join: the handshake within `handshake`, the welcome and the coarsest
/// colour tile within [`JOIN_TIMEOUT`].
pub async fn attempt(
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
            let (lost, why) = join::ending(&e);
            return Err(JoinError { lost, message: why });
        }
        Err(_) => {
            return Err(JoinError::lost(format!(
                "no handshake within {}",
                secs(handshake)
            )));
        }
    };
    match tokio::time::timeout(JOIN_TIMEOUT, join::hello(conn.clone(), hello, keep)).await {
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
pub async fn write_control(send: &mut quinn::SendStream, msg: &ClientMessage) -> Result<()> {
    tokio::time::timeout(CONTROL_TIMEOUT, wire::write(send, msg))
        .await
        .map_err(|_| anyhow!("the server stopped reading the control stream"))??;
    Ok(())
}

/// Sends a key datagram every 10 ms (the physics' step) with the step's keys from
/// `steps`, on whichever connection is up: the core numbers the state and repeats the
/// last eight, so a lost datagram costs nothing. While reconnecting the steps go on (and
/// are numbered) unsent. Ends with the session. With a `phase`, the clock ticks at that
/// offset on the process's 10 ms grid ([`KeySource::ScriptAt`]); without, from now.
pub async fn send_keys(link: Arc<Link>, mut steps: Steps, phase: Option<Duration>) {
    const STEP: Duration = Duration::from_millis(10);
    let start = match phase {
        Some(phase) => on_grid(tokio::time::Instant::now(), STEP, phase),
        None => tokio::time::Instant::now(),
    };
    let mut tick = tokio::time::interval_at(start, STEP);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        if link.ended().is_some() {
            return;
        }
        let datagram = {
            let mut keys = lock(&link.keys);
            let step = steps(&mut keys);
            keys.key_datagram(step, Instant::now())
        };
        let conn = lock(&link.conn).clone();
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
    static EPOCH: std::sync::OnceLock<tokio::time::Instant> = std::sync::OnceLock::new();
    let epoch = *EPOCH.get_or_init(|| now);
    let at = grid_after(
        now.duration_since(epoch).as_nanos(),
        step.as_nanos(),
        phase.as_nanos(),
    );
    epoch + Duration::from_nanos(u64::try_from(at).unwrap_or(u64::MAX))
}

/// The first `k × step + phase mod step` at or after `since` (nanoseconds).
fn grid_after(since: u128, step: u128, phase: u128) -> u128 {
    let step = step.max(1);
    let offset = phase % step;
    since.saturating_sub(offset).div_ceil(step) * step + offset
}

/// The first pause between reconnection attempts, doubled after each up to the second.
const BACKOFF_FIRST: Duration = Duration::from_millis(100);
const BACKOFF_MOST: Duration = Duration::from_secs(2);
/// A reconnection's QUIC handshake, at most, with one address (the next attempt starts
/// afresh; the last may end this much after [`Patience::reconnect_for`]).
const HANDSHAKE: Duration = Duration::from_secs(5);

/// The connection's life and the reconnections: owns the control stream's writing end.
pub(crate) struct Supervisor {
    pub(crate) endpoint: quinn::Endpoint,
    /// The hello of the next connection (the newest ticket, the vehicle followed).
    pub(crate) hello: Hello,
    pub(crate) patience: Patience,
    /// What the colour caches keep.
    pub(crate) keep: Keep,
    /// The first connection's terrain: every later one must show it.
    pub(crate) terrain: TerrainId,
    pub(crate) link: Arc<Link>,
    pub(crate) outgoing: mpsc::UnboundedReceiver<Outgoing>,
}

impl Supervisor {
    pub(crate) async fn run(mut self, mut joined: Joined) {
        // The addresses silent since the last frame: the same one silent again ends it.
        let mut silences = Silences::default();
        loop {
            let Joined {
                conn,
                mut send,
                recv,
                ..
            } = joined;
            let end = self.drive(&conn, &mut send, recv).await;
            let (here, many) = {
                let a = lock(&self.link.addresses);
                (a.index(), a.many())
            };
            let addr = self.addr();
            let (why, silent) = match end {
                End::Quit => return self.link.end("quit".into()),
                // Another edge takes the viewer.
                End::Shutdown(why) if many => (why, false),
                End::Final(why) | End::Shutdown(why) => {
                    conn.close(close::BYE.into(), b"bye");
                    return self.link.end(why);
                }
                End::Lost { why, silent } => (why, silent),
            };
            conn.close(0u32.into(), b"lost");
            *lock(&self.link.conn) = None;
            if silent && silences.silent(here, self.link.frames.load(Ordering::Relaxed)) {
                return self.link.end(format!(
                    "lost the server at {addr}: {why}, again right after reconnecting, with \
                     no frame between: the server welcomes but sends nothing"
                ));
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

    /// The address in use.
    fn addr(&self) -> SocketAddr {
        *lock(&self.link.addresses).current()
    }

    /// How long a silence may last: shorter when there are other addresses to go to.
    fn silence(&self) -> Duration {
        if lock(&self.link.addresses).many() {
            self.patience.silence.min(SILENCE_MANY)
        } else {
            self.patience.silence
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
        loop {
            // Edges learned meanwhile shorten it.
            let silence = self.silence();
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

    /// Connects again, each attempt to the next address in turn, until a connection
    /// joins, the session quits (`None`), or the time runs out or a server refuses (an
    /// error, in words).
    async fn reconnect(&mut self, why: &str) -> Result<Option<Joined>, String> {
        let deadline = Instant::now() + self.patience.reconnect_for;
        let mut backoff = BACKOFF_FIRST;
        let mut attempts = 0u32;
        let from = self.addr();
        let lost = |more: String| format!("lost the server at {from}: {why}; {more}");
        loop {
            attempts += 1;
            self.link.status.send_modify(|s| {
                if let State::Reconnecting { attempts: a, .. } = &mut s.state {
                    *a = attempts;
                }
            });
            // An attempt begun before the deadline has its whole handshake.
            let hello = self.hello_now();
            let (addr, handshake) = {
                let mut a = lock(&self.link.addresses);
                let addr = *a.after_loss();
                (addr, if a.many() { HANDSHAKE_MANY } else { HANDSHAKE })
            };
            let attempt = attempt(&self.endpoint, addr, handshake, hello, self.keep);
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
                Err(e) if !e.lost => return Err(lost(format!("reconnecting to {addr}: {e}"))),
                Err(e) => format!("{addr}: {}", e.message),
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
            if let Some(ticks) = core.morph_ticks() {
                fresh.set_morph(ticks);
            }
            // A watched recording stays one across a reconnection (its status may come
            // after the new connection's first frames).
            if core.is_replay() {
                fresh.set_replay();
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
        let addr = self.addr();
        let now = Instant::now();
        self.link.status.send_modify(|s| {
            s.gaps.reconnected(driver && welcome.resumed);
            s.state = State::Connected;
            s.welcome = welcome.clone();
            s.addr = addr;
            // This edge says so if its world is gone too.
            s.world.back(now);
        });
        for news in std::mem::take(&mut joined.news) {
            self.link.news(&news);
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
