//! One viewer's connection after its hello ([`super::handshake`] admits it and hands over
//! its [`Seat`] and its place in the world, [`Joined`]): the welcome, its key datagrams
//! (through its [`KeyGate`] into the world), its control messages, its frames (paced by the
//! clock, made by its sans-IO core, [`crate::viewer::ViewerCore`]), and its end: a goodbye
//! frees a driver's vehicle, a lost connection has it held ([`Event::Hold`]), and a
//! reconnection with the driver's ticket replaces it.
//!
//! How a frame goes:
//!
//! - a **change frame** that fits in one datagram goes as one (on a lossy path,
//!   [`LossMeter`], a small one goes twice, the copy [`REPEAT_AFTER`] later); a larger one
//!   on a stream of its own, abandoned (reset) when the next frame is ready unless the
//!   viewer has acknowledged it (latest frame wins): a lost or abandoned change frame is
//!   never a base;
//! - a **key frame** always goes on a stream of its own, reliably, at the highest
//!   priority, and is not abandoned while it is pending
//!   ([`crate::viewer::ViewerCore::pending_key`]): the frames after it are coded against
//!   it before the viewer has it, so on a path that cannot carry a key frame a frame
//!   interval it still arrives, and the viewer decodes it and the frames after. It is reset
//!   only once superseded by a newer key frame (or when the viewer asked for another),
//!   unless acknowledged.
//!
//! A frame is begun in line; the first one, and any heavier one (a rebuild, a key frame's
//! coding, many changes), is finished on a blocking frame maker ([`super::makers`]), so it
//! never holds up the other viewers' tasks.
//!
//! The colour map goes on the control stream, at a priority below every frame's, so that
//! colour never delays a frame: the welcome, then the coarsest tile (before the first
//! frame), then, once the first frame is made, what [`stream_color`] sends
//! ([`super::control`]: the tiles the viewer's [`ColorScheduler`] picks for the followed
//! vehicle's position, each with its normals, paced by the viewer's share of the
//! server-wide colour budget, [`super::color_budget`]). A goodbye waits for the tile being
//! written (at most [`GOODBYE_WITHIN`]), so no message is ever cut.
//!
//! The control stream is read into a [`Mailbox`] until a goodbye. A message that is not
//! one (undecodable, longer than [`MAX_CONTROL`], or cut short by the stream's end) closes
//! the connection with [`close::PROTOCOL`], the reason in the "left" log line with the
//! peer's address, and frees a driver's vehicle. A control stream that merely ends
//! (finished between messages, reset, or with the connection) leaves the end to the
//! connection, so one rule ([`Conn::hold_after`]) decides hold or leave.
//!
//! A spectator is told whom its frames follow when that changes; watching a recording, a
//! viewer is told the replay's state ([`super::replay`]). On an edge (`roam-server edge`),
//! the news of the world ([`tell_news`], in [`super::control`]) goes on the control stream
//! as it changes: the world's edges (where the viewer may go if this one fails), the world
//! gone and back; a driver whose world restarted (its vehicle unknown there) is told so
//! and let go.
//!
//! A browser's WebTransport session is served by the same code, through [`super::conn`]'s
//! [`Conn`]: the logs' `via` tells them apart, and at shutdown a browser is given
//! [`WEB_CLOSE_WAIT`] to close its session on the goodbye (closed from here first, a busy
//! page may see only a lost connection, and try to reconnect).

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use roam_link::wire;
use roam_protocol::ColorLayout;
use roam_protocol::messages::{ClientMessage, Hello, Reason, ServerMessage, Welcome, close};
use roam_protocol::sync::lock;
use tokio::sync::oneshot;

use super::conn::{Conn, DatagramError, RecvStream, SendStream};
use super::control::{WORLD_RESTARTED, stream_color, tell_news, write_color};
use super::seat::{Joined, MAX_CONTROL, Seat, role_name};
use super::shared::Shared;
use crate::sim::world::VehicleId;
use crate::sim::world_core::{Event, Snapshot};
use crate::viewer::color::ColorScheduler;
use crate::viewer::conversation::{self, Control, KeyGate, LossMeter, Mailbox, frame_message};
use crate::viewer::{KeyCause, ViewerCore};

/// How long after a small frame its second copy goes, on a lossy path ([`LossMeter`]).
const REPEAT_AFTER: Duration = Duration::from_millis(4);

/// How long a last message may take to be received before the connection closes anyway.
/// The wait ends as soon as the peer has it; 250 ms was too short for a browser on a
/// loaded 2-core machine (the page saw the connection lost, not the refusal, in one run
/// of the whole test suite).
const LAST_WORD_WAIT: Duration = Duration::from_secs(2);

/// How long a shutdown waits for browsers to close their sessions after the goodbye (the
/// endpoint waits a little longer, for the viewer tasks' own closes).
pub(super) const WEB_CLOSE_WAIT: Duration = Duration::from_secs(1);

/// Sends a last message (a refusal, a goodbye) and gives it up to [`LAST_WORD_WAIT`] to
/// arrive before the connection closes (closing drops what is unsent).
pub(super) async fn last_word(send: &mut SendStream, msg: &ServerMessage) {
    if send.write_msg(msg).await.is_ok() && send.finish() {
        let _ = tokio::time::timeout(LAST_WORD_WAIT, send.stopped()).await;
    }
}

/// A viewer past its hello ([`super::handshake`]).
pub(super) struct Viewer {
    pub conn: Conn,
    pub send: SendStream,
    pub recv: RecvStream,
    pub hello: Hello,
    pub peer: SocketAddr,
    pub joined: Joined,
}

/// Serves a welcomed viewer to its end. A driver whose connection is lost (not a
/// goodbye) has its vehicle held for a while, to take back with its ticket.
pub(super) async fn serve(viewer: Viewer, mut seat: Seat, shared: Arc<Shared>) {
    let Viewer {
        conn,
        send,
        recv,
        hello,
        peer,
        mut joined,
    } = viewer;
    let (vehicle, driver) = (joined.vehicle, joined.driver);
    // Kept until the vehicle's hold is sent (below): a reconnection that replaces this
    // one waits on it, so its resume reaches the world after the hold.
    let mut replaced = joined.replaced.take();
    let mut answer = None;
    let mut leave = Leave {
        world: shared.world.clone(),
        remote: shared.remote.clone().map(|r| (r, joined.claim)),
        vehicle: driver.then_some(vehicle),
        hold: None,
    };
    let started = std::time::Instant::now();
    // When a key datagram last came: a driver sends one every 10 ms, so the time since is
    // how long its path has been silent when the connection is found dead.
    let heard = Arc::new(Mutex::new(started));
    let silent = || lock(&heard).elapsed();
    // Colour never delays a frame (frames' priorities are their numbers, from 0).
    send.set_priority(-1);
    let layout = shared
        .pyramid
        .layout(shared.color_window.min(hello.color_window.max(1)))
        .expect("the pyramid's layout was checked at start with a larger window");
    let mut colors = ColorScheduler::with_normals(layout);
    let send = Arc::new(tokio::sync::Mutex::new(send));
    let welcomed = welcome(
        &mut *send.lock().await,
        &shared,
        &joined,
        layout,
        &mut colors,
    )
    .await;
    if welcomed.is_err() {
        // Lost on the way (held), or the viewer stopped its control stream (a leave).
        leave.hold = conn.hold_after().then(silent);
        conn.close(close::PROTOCOL, b"the welcome could not be sent");
        return;
    }
    // Frames made: the colour task starts once the first is (what it sends is of no use
    // before, and would only share the path with it).
    let (sent, made) = tokio::sync::watch::channel(0u64);
    // The vehicle followed: a spectator may change it, and so may a replay (its vehicle
    // left); the colour task streams around it.
    let (follow, followed) = tokio::sync::watch::channel(vehicle);
    // Watching a recording: this viewer's place among those sharing its clock, and the
    // task telling it the replay's state.
    let replay_seat = shared
        .watching()
        .map(|r| r.enter(peer.to_string(), joined.controller));
    // A spectator is told whom its frames follow when that changes (the newest, in order).
    let _following = (!driver).then(|| {
        AbortOnDrop(tokio::spawn(tell_following(
            send.clone(),
            follow.subscribe(),
        )))
    });
    let _tell = match (&shared.replay, &replay_seat) {
        (Some(r), Some(seat)) => Some(AbortOnDrop(tokio::spawn(super::replay::tell(
            send.clone(),
            r.clone(),
            seat.id,
        )))),
        _ => None,
    };
    // Aborted when this task ends by any path, unwinding included: the colour task holds
    // the shared state (the world's inbox) and never ends on its own.
    let color = AbortOnDrop(tokio::spawn(stream_color(
        send.clone(),
        shared.clone(),
        colors,
        (followed, made),
    )));
    let control = Arc::new(Mutex::new(Mailbox::default()));
    let keys = tokio::spawn(read_keys(
        conn.clone(),
        shared.clone(),
        (vehicle, driver),
        heard.clone(),
    ));
    let mut ctl = tokio::spawn(read_control(recv, control.clone()));
    let core = ViewerCore::for_hello(&shared.terrain, shared.height_step, &hello, shared.limits);
    let rate = ViewerCore::frame_rate(&hello, shared.limits);
    // A driver whose vehicle vanishes on an edge after a world restart is told why.
    let restarts = shared.remote.as_ref().map(|r| r.restarts());
    let why: String = tokio::select! {
        end = frames(
            &conn,
            &shared,
            (control, &mut seat),
            core,
            rate,
            (&follow, driver, replay_seat.as_ref().map(|s| s.id)),
            &sent,
        ) => {
            match end {
                FramesEnd::ConnectionLost => {
                    leave.hold = conn.hold_after().then(silent);
                    lost(&conn)
                }
                FramesEnd::VehicleLeft | FramesEnd::Failed(_) => {
                    let why = match end {
                        FramesEnd::Failed(why) => why,
                        _ if driver && restarts != shared.remote.as_ref().map(|r| r.restarts()) => {
                            WORLD_RESTARTED
                        }
                        _ => "the vehicle followed has left",
                    };
                    let bye = ServerMessage::Bye(Reason::Unavailable(why.into()));
                    goodbye(&send, &color.0, &bye).await;
                    conn.close(close::BYE, why.as_bytes());
                    why.into()
                }
            }
        }
        end = &mut ctl => match end {
            Ok(ControlEnd::Broken(why)) => {
                // Its vehicle goes (no hold: the viewer is not coming back with this); the
                // "left" line below names the peer and the reason.
                conn.close(close::PROTOCOL, why.as_bytes());
                why
            }
            // A goodbye (a read task that panicked ends the same way).
            Ok(ControlEnd::Goodbye) | Err(_) => {
                conn.close(close::BYE, b"bye");
                "goodbye".into()
            }
        },
        _ = conn.closed() => {
            leave.hold = conn.hold_after().then(silent);
            lost(&conn)
        }
        Ok(done) = async {
            match replaced.as_mut() {
                Some(rx) => rx.await,
                None => std::future::pending().await,
            }
        } => {
            // The driver is back on a new connection: held only for the handover.
            leave.hold = Some(std::time::Duration::ZERO);
            answer = Some(done);
            conn.close(close::BYE, b"replaced by a reconnection");
            "replaced by a reconnection".into()
        }
        why = tell_news(&send, shared.remote.clone(), driver) => {
            let bye = ServerMessage::Bye(Reason::Unavailable(why.clone()));
            goodbye(&send, &color.0, &bye).await;
            conn.close(close::BYE, why.as_bytes());
            why
        }
        _ = shared.shutting_down() => {
            let bye = ServerMessage::Bye(Reason::Shutdown);
            goodbye(&send, &color.0, &bye).await;
            if conn.via() == super::conn::Via::Web {
                // A browser closes its session on the goodbye; closed from here first, a
                // busy page may see only "connection lost" (and try to reconnect).
                let _ = tokio::time::timeout(WEB_CLOSE_WAIT, conn.closed()).await;
            }
            conn.close(close::SHUTDOWN, b"the server is shutting down");
            "the server is shutting down".into()
        }
    };
    keys.abort();
    ctl.abort();
    drop(color);
    let held = leave.hold.is_some() && leave.vehicle.is_some();
    if driver && !held {
        // Gone for good: its ticket names nothing any more.
        shared.tickets().retain(|_, c| c.vehicle != vehicle);
    }
    tracing::info!(
        %peer,
        via = conn.via().name(),
        role = role_name(&hello.role),
        vehicle,
        reason = %why,
        held,
        frames = *sent.borrow(),
        seconds = started.elapsed().as_secs(),
        "left"
    );
    drop(leave);
    drop(seat);
    drop(replaced);
    if let Some(done) = answer {
        let _ = done.send(()); // the vehicle's hold is on its way to the world
    }
}

/// Tells a spectator the vehicle its frames follow each time that changes (a switch
/// asked for, or a replay's vehicle gone): one writer, so the newest is said last.
async fn tell_following(
    send: Arc<tokio::sync::Mutex<SendStream>>,
    mut followed: tokio::sync::watch::Receiver<VehicleId>,
) {
    while followed.changed().await.is_ok() {
        let to = *followed.borrow_and_update();
        let msg = ServerMessage::Following(to);
        if send.lock().await.write_msg(&msg).await.is_err() {
            return;
        }
    }
}

/// Why a connection ended, as the logs say it.
fn lost(conn: &Conn) -> String {
    match conn.close_reason() {
        Some(e) => format!("connection lost: {e}"),
        None => "connection lost".into(),
    }
}

/// Tells the world a driver left, however the connection ended: a goodbye frees its
/// vehicle, a lost connection has it held ([`Event::Hold`]), the hold counted from when
/// its path fell silent (`hold`: how long before the end that was). On an edge, told to the
/// world over the bus with the connection's claim, in order with the resumes.
struct Leave {
    world: std::sync::mpsc::Sender<super::world_loop::Inbound>,
    remote: Option<(Arc<super::bus::edge::Remote>, u64)>,
    vehicle: Option<VehicleId>,
    hold: Option<std::time::Duration>,
}

impl Drop for Leave {
    fn drop(&mut self) {
        if let Some(vehicle) = self.vehicle {
            if let Some((remote, claim)) = &self.remote {
                let hold = self.hold.map(super::world_loop::hold_ticks);
                remote.ended(vehicle, *claim, hold);
                return;
            }
            let event = match self.hold {
                Some(silent) => Event::Hold {
                    vehicle,
                    silent: super::world_loop::hold_ticks(silent),
                },
                None => Event::Leave(vehicle),
            };
            let _ = self.world.send((event, None));
        }
    }
}

/// A task aborted when dropped.
struct AbortOnDrop(tokio::task::JoinHandle<()>);

impl Drop for AbortOnDrop {
    fn drop(&mut self) {
        self.0.abort();
    }
}

/// How long a goodbye may wait for the control stream: a viewer that stopped reading it
/// (flow control full, a colour tile half written) must not hold its seat and vehicle.
const GOODBYE_WITHIN: Duration = Duration::from_secs(1);

/// `bye` on the control stream once the colour task is stopped, within [`GOODBYE_WITHIN`]
/// (the connection closes next, so a goodbye cut short loses nothing more).
async fn goodbye(
    send: &tokio::sync::Mutex<SendStream>,
    color: &tokio::task::JoinHandle<()>,
    bye: &ServerMessage,
) {
    let said = async { last_word(&mut *quiet(send, color).await, bye).await };
    let _ = tokio::time::timeout(GOODBYE_WITHIN, said).await;
    color.abort();
}

/// The control stream, once the colour task is stopped between two messages.
async fn quiet<'a>(
    send: &'a tokio::sync::Mutex<SendStream>,
    color: &tokio::task::JoinHandle<()>,
) -> tokio::sync::MutexGuard<'a, SendStream> {
    let guard = send.lock().await;
    // It waits for the lock or its next turn: never inside a write.
    color.abort();
    guard
}

/// The welcome, then the coarsest colour tile.
async fn welcome(
    send: &mut SendStream,
    shared: &Shared,
    joined: &Joined,
    layout: ColorLayout,
    colors: &mut ColorScheduler,
) -> Result<(), wire::WireError> {
    let tick = shared.snapshots.borrow().tick;
    let w = Welcome {
        ticket: joined.ticket,
        resumed: joined.resumed,
        ..conversation::welcome(&shared.terrain, joined.vehicle, tick, layout, shared.limits)
    };
    send.write_msg(&ServerMessage::Welcome(w)).await?;
    let first = colors.first();
    write_color(send, shared, first).await
}

/// Key datagrams to the world, through the driver's [`KeyGate`] (rate-limited; anything
/// that is not a key datagram is ignored). A spectator's are read and dropped.
async fn read_keys(
    conn: Conn,
    shared: Arc<Shared>,
    (vehicle, driver): (VehicleId, bool),
    heard: Arc<Mutex<std::time::Instant>>,
) {
    let mut gate = KeyGate::new(vehicle);
    while let Some(bytes) = conn.read_datagram().await {
        let now = std::time::Instant::now();
        *lock(&heard) = now;
        if let Some(event) = gate.admit(&bytes, now)
            && driver
            && shared.world.send((event, None)).is_err()
        {
            return; // the world has stopped
        }
    }
}

/// How a viewer's control stream ended, as far as [`read_control`] decides.
#[derive(Debug, PartialEq, Eq)]
enum ControlEnd {
    /// A goodbye (or what only starts a connection: a second hello).
    Goodbye,
    /// A message that is not one: too long, undecodable, or cut short by the stream's end.
    Broken(String),
}

/// Control messages into the mailbox until the viewer says goodbye or breaks the protocol,
/// and only then: a control stream that ends otherwise (finished between two messages,
/// reset, or ended with the connection) leaves the end to the connection, so that one rule
/// ([`Conn::hold_after`]) decides hold or leave.
async fn read_control(mut recv: RecvStream, control: Arc<Mutex<Mailbox>>) -> ControlEnd {
    loop {
        match wire::read::<ClientMessage>(&mut recv, MAX_CONTROL).await {
            Ok(msg) => {
                let mut c = lock(&control);
                if c.push(msg) == Control::End {
                    return ControlEnd::Goodbye;
                }
            }
            Err(e) => match broken(&e) {
                Some(why) => return ControlEnd::Broken(why),
                None => break,
            },
        }
    }
    std::future::pending().await
}

/// Why a control-stream read error breaks the protocol; `None` when the stream merely
/// ended (finished between messages, reset by the viewer, or the connection gone).
fn broken(e: &wire::WireError) -> Option<String> {
    use quinn::ReadExactError;
    match e {
        wire::WireError::TooLong { .. } | wire::WireError::Decode(_) => {
            Some(format!("a control message that is not one: {e}"))
        }
        wire::WireError::Read(ReadExactError::FinishedEarly(n)) => Some(format!(
            "a control message cut short: the stream finished {n} bytes into it"
        )),
        wire::WireError::Closed
        | wire::WireError::Read(ReadExactError::ReadError(_))
        | wire::WireError::Write(_)
        | wire::WireError::Encode(_) => None,
    }
}

/// Why a viewer's frames stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum FramesEnd {
    /// The vehicle it followed (or drove) is gone.
    VehicleLeft,
    /// The connection can take no more streams.
    ConnectionLost,
    /// The server could not make a frame: said to the viewer, never a panic.
    Failed(&'static str),
}

/// `seat`: the viewer's budget changes are served as far as its seat can grow
/// ([`Seat::granted`]).
async fn frames(
    conn: &Conn,
    shared: &Arc<Shared>,
    (control, seat): (Arc<Mutex<Mailbox>>, &mut Seat),
    core: ViewerCore,
    rate: u16,
    (follow, driver, replay): (&tokio::sync::watch::Sender<VehicleId>, bool, Option<u64>),
    sent: &tokio::sync::watch::Sender<u64>,
) -> FramesEnd {
    let mut vehicle = *follow.borrow();
    // Where the followed vehicle was last: a replay's camera stays there while it has none
    // to follow (sought to before any joined).
    let mut parked = crate::sim::world::start_state(&shared.terrain, 0);
    let mut core = Some(core);
    let mut bytes_out = conn.quic().stats().udp_tx.bytes;
    let mut interval = tokio::time::interval(Duration::from_secs_f64(1.0 / f64::from(rate)));
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // The newest change frame sent on a stream, and the newest key frame (kept apart: it
    // is never abandoned while it is pending).
    let mut in_flight: Option<Sending> = None;
    let mut key_in_flight: Option<Sending> = None;
    let mut seen = false;
    let mut loss = LossMeter::default();
    loop {
        let due = interval.tick().await.into_std();
        // Frames first: one that starts behind holds every viewer's colour back.
        let now = std::time::Instant::now();
        shared.color.frame_started(due, now);
        shared.stats.frame_late(now.saturating_duration_since(due));
        let snap: Arc<Snapshot> = shared.snapshots.borrow().clone();
        let (asked, controls) = {
            let mut m = lock(&control);
            (m.take_follow(), m.take_replay())
        };
        if let (Some(r), Some(id)) = (&shared.replay, replay) {
            for c in controls {
                r.control(id, c);
            }
        }
        let there = |id: VehicleId| snap.vehicles.iter().any(|v| v.id == id);
        // A spectator follows the vehicle it asks for, if there; a replay's spectator whose
        // vehicle left follows the first there.
        let switch = match asked {
            Some(a) if !driver && a != vehicle && there(a) => Some(a),
            _ if replay.is_some() && !there(vehicle) => snap.vehicles.first().map(|v| v.id),
            _ => None,
        };
        if let Some(to) = switch {
            // The viewer is told by `tell_following`, the newest switch once.
            vehicle = to;
            follow.send_replace(to);
        }
        let state = match snap.vehicles.iter().find(|v| v.id == vehicle) {
            Some(v) => v.state,
            None if replay.is_some() => parked,
            // A new driver's vehicle appears with the next tick; a spectator's was there
            // when it joined.
            None if seen || !driver => return FramesEnd::VehicleLeft,
            None => continue,
        };
        parked = state;
        seen = true;
        let mut c = core.take().expect("put back below");
        for event in lock(&control).drain() {
            c.handle(seat.granted(event));
        }
        let scene = shared.scene();
        // A frame is begun in line: an update of a few changes coded as a change frame is
        // made there (microseconds). Anything heavier (more changes, a rebuild, a key
        // frame's coding: milliseconds at large budgets) is left unfinished and finished on
        // a blocking thread, so it never holds up the other viewers' tasks.
        // At most one fewer blocking frame maker than cores ([`Shared::makers`]): the
        // world thread always finds a core, whatever the viewers ask for.
        let started = std::time::Instant::now();
        // The first frame (a rebuild and a key frame) is made whole on the maker, for the
        // vehicle where it is when the maker starts: made for where it was when the frame
        // was begun, a first frame that waited behind many joins (1.6 s for 40 at once)
        // showed a place the vehicle had long left, so the second frame rebuilt and was a
        // key frame again (41 of 81 key frames for 40 joins, `key_larger`).
        let first = *sent.borrow() == 0;
        let inline = if first {
            None
        } else {
            c.begin_frame(&scene, &state)
        };
        let (c, made, snap) = match inline {
            Some(made) => (c, made, snap),
            None => {
                // The permit goes with the job: it is held until the job ends, even if
                // this viewer's task is dropped while waiting for it.
                let Ok(permit) = shared.makers.acquire(first).await else {
                    return FramesEnd::Failed("the server is shutting down");
                };
                let shared2 = shared.clone();
                match tokio::task::spawn_blocking(move || {
                    let _permit = permit;
                    // Below the async workers: frames first ([`super::makers`]).
                    super::makers::lower_this_thread();
                    let scene = shared2.scene();
                    if !first {
                        let made = c.finish_frame(&scene);
                        return Some((c, made, snap));
                    }
                    let snap: Arc<Snapshot> = shared2.snapshots.borrow().clone();
                    let state = match snap.vehicles.iter().find(|v| v.id == vehicle) {
                        Some(v) => v.state,
                        None if replay.is_some() => state,
                        None => return None,
                    };
                    let made = c.make_frame(&scene, &state);
                    Some((c, made, snap))
                })
                .await
                {
                    Ok(Some(r)) => r,
                    Ok(None) => return FramesEnd::VehicleLeft,
                    Err(_) => return FramesEnd::Failed("the frame maker failed"),
                }
            }
        };
        let stats = &shared.stats;
        stats.add(&stats.make_ns, started.elapsed().as_nanos() as u64);
        stats.add(&stats.frames, 1);
        sent.send_modify(|n| *n += 1);
        let tx = conn.quic().stats().udp_tx.bytes;
        stats.add(&stats.bytes_out, tx.saturating_sub(bytes_out));
        bytes_out = tx;
        let acked = c.acked();
        let pending_key = c.pending_key();
        core = Some(c);
        let frame = made.frame;
        let key = made.base.is_none();
        stats.add(&stats.key_frames, u64::from(key));
        match made.key {
            Some(KeyCause::Asked) => stats.add(&stats.key_asked, 1),
            Some(KeyCause::Behind) => stats.add(&stats.key_behind, 1),
            Some(KeyCause::Larger) => stats.add(&stats.key_larger, 1),
            Some(KeyCause::First) | None => {}
        }
        let msg = frame_message(&shared.terrain, &snap, made, vehicle, driver);
        let mut bytes = Vec::new();
        if roam_protocol::messages::encode(&msg, &mut bytes).is_err() {
            return FramesEnd::Failed("a frame over the message limit");
        }
        // Latest frame wins: the previous change frame's stream is reset unless the viewer
        // has acknowledged it, whether it is still being written or already handed to quinn
        // (a finished stream still waits in the send buffer on a slow path). The key frame
        // is the exception: it goes on until it is no longer pending (acknowledged,
        // superseded by a newer key frame, or another asked for).
        if let Some(k) = key_in_flight.take_if(|k| pending_key != Some(k.frame)) {
            k.abandon_unless(acked).await;
        }
        if let Some(previous) = in_flight.take() {
            previous.abandon_unless(acked).await;
        }
        // A change frame that fits in one datagram goes as one: no stream to open, finish
        // or reset, one packet. A lost one is simply never a base; the viewer keeps the
        // newest. A key frame goes on a stream, reliably: the frames after it are coded
        // against it.
        if !key
            && conn
                .max_datagram_size()
                .is_some_and(|max| bytes.len() <= max)
        {
            let stats = conn.quic().stats();
            loss.update(stats.path.lost_packets, stats.path.sent_packets);
            if loss.repeat(bytes.len()) {
                // A second copy in a packet of its own, a few milliseconds later (a lost
                // copy is repaired before the next frame; the viewer takes one of them).
                let (conn, copy) = (conn.clone(), bytes.clone());
                tokio::spawn(async move {
                    tokio::time::sleep(REPEAT_AFTER).await;
                    let _ = conn.send_datagram(copy.into());
                });
            }
            match conn.send_datagram(bytes.clone().into()) {
                Ok(()) => continue,
                Err(DatagramError::Lost) => return FramesEnd::ConnectionLost,
                // Not allowed or too large after all: the stream takes it.
                Err(DatagramError::Refused) => {}
            }
        }
        let Some(mut stream) = conn.open_uni().await else {
            return FramesEnd::ConnectionLost;
        };
        // Newer frames first, and a key frame before all: the frames after it need it.
        stream.set_priority(if key { i32::MAX } else { frame as i32 });
        let (cancel, cancelled) = oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            tokio::select! {
                r = stream.write_all(&bytes) => {
                    if r.is_ok() && stream.finish() {
                        return Some(stream);
                    }
                    None
                }
                _ = cancelled => {
                    stream.reset(0);
                    None
                }
            }
        });
        let sending = Sending {
            cancel,
            task,
            frame,
        };
        if key {
            key_in_flight = Some(sending);
        } else {
            in_flight = Some(sending);
        }
    }
}

/// A frame being sent on a stream of its own.
struct Sending {
    /// Resets the stream while it is still being written.
    cancel: oneshot::Sender<()>,
    /// Writes the frame; the stream once it is all handed to quinn.
    task: tokio::task::JoinHandle<Option<SendStream>>,
    frame: u64,
}

impl Sending {
    /// Abandons the frame (resets its stream: quinn stops sending and retransmitting it)
    /// unless the viewer has acknowledged it.
    async fn abandon_unless(self, acked: Option<u64>) {
        if acked.is_some_and(|a| a >= self.frame) {
            return; // delivered: the stream is finished, nothing to stop
        }
        if !self.task.is_finished() {
            let _ = self.cancel.send(());
        } else if let Ok(Some(mut stream)) = self.task.await {
            stream.reset(0);
        }
    }
}
