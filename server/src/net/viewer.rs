//! One viewer's connection after its hello ([`super::handshake`] admits it and hands over
//! its [`Seat`] and its place in the world, [`Joined`]): the welcome, its datagrams and
//! control messages handed to its [`Conversation`] (the sans-IO core that decides
//! everything about the connection: a driver's key events for the world, the frames and
//! how each goes), the frames put on the frame clock ([`super::frames`], which makes and
//! sends them), and its end: a goodbye frees a driver's vehicle, a lost connection has it
//! held ([`Event::Hold`], counted from the last datagram, [`Conversation::silent`]), and
//! a reconnection with the driver's ticket replaces it.
//!
//! The colour map goes on the control stream, at a priority below every frame's, so that
//! colour never delays a frame: the welcome, then the coarsest tile (before the first
//! frame), then, once the first frame is made, what [`stream_color`] sends
//! ([`super::control`]: the tiles the viewer's [`ColorScheduler`] picks for the followed
//! vehicle's position, each with its normals, paced by the viewer's share of the
//! server-wide colour budget, [`super::color_budget`]). A goodbye waits for the tile being
//! written (at most [`GOODBYE_WITHIN`]), so no message is ever cut.
//!
//! The control stream is read into the conversation until a goodbye. A message that is not
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
use std::sync::Arc;
use std::time::Duration;

use roam_link::wire;
use roam_protocol::ColorLayout;
use roam_protocol::messages::{ClientMessage, Hello, Reason, ServerMessage, Welcome, close};
use roam_protocol::sync::lock;
use tokio::sync::oneshot;

use super::clock::{FramesEnd, Served};
use super::conn::{Conn, RecvStream, SendStream};
use super::control::{WORLD_RESTARTED, stream_color, tell_news, write_color};
use super::seat::{Joined, MAX_CONTROL, Seat, role_name};
use super::shared::Shared;
use crate::sim::world::VehicleId;
use crate::sim::world_core::Event;
use crate::viewer::color::ColorScheduler;
use crate::viewer::conversation::{self, Conversation, Handled, Role};

/// How long a last message may take to be received before the connection closes anyway.
/// The wait ends as soon as the peer has it; 250 ms was too short for a browser on a
/// loaded 2-core machine (the page saw the connection lost, not the refusal, in one run
/// of the whole test suite).
pub(super) const LAST_WORD_WAIT: Duration = Duration::from_secs(2);

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
pub(super) async fn serve(viewer: Viewer, seat: Seat, shared: Arc<Shared>) {
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
        leave.hold = conn.hold_after().then(|| started.elapsed());
        conn.close(close::PROTOCOL, b"the welcome could not be sent");
        return;
    }
    // Watching a recording: this viewer's place among those sharing its clock, and the
    // task telling it the replay's state.
    let replay_seat = shared
        .watching()
        .map(|r| r.enter(peer.to_string(), joined.controller));
    let role = Role {
        vehicle,
        driver,
        replay: replay_seat.is_some(),
    };
    let conv = Conversation::new(
        &shared.terrain,
        shared.height_step,
        &hello,
        shared.limits,
        role,
        (started, shared.clock.origin(&hello, shared.limits)),
    );
    let (end_tx, mut frames_end) = oneshot::channel();
    let mut seat = seat;
    let served = Arc::new(Served::new(
        conv,
        conn.clone(),
        Box::new(move |budget| seat.grow(budget)),
        replay_seat.as_ref().map(|s| s.id),
        end_tx,
    ));
    // Off the clock when this task ends by any path.
    let _on_clock = OnClock(shared.clone(), served.clone());
    let silent = || lock(&served.conv).silent(std::time::Instant::now(), started);
    // A spectator is told whom its frames follow when that changes (the newest, in order).
    let _following = (!driver).then(|| {
        AbortOnDrop(tokio::spawn(tell_following(
            send.clone(),
            served.follow.subscribe(),
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
    // the shared state (the world's inbox) and never ends on its own. It starts once the
    // first frame is made (what it sends is of no use before, and would only share the
    // path with it), and streams around the vehicle followed.
    let color = AbortOnDrop(tokio::spawn(stream_color(
        send.clone(),
        shared.clone(),
        colors,
        (served.follow.subscribe(), served.sent.subscribe()),
    )));
    let keys = tokio::spawn(read_keys(served.clone(), shared.clone()));
    let mut ctl = tokio::spawn(read_control(recv, served.clone()));
    shared.clock.add(served.clone());
    // A driver whose vehicle vanishes on an edge after a world restart is told why.
    let restarts = shared.remote.as_ref().map(|r| r.restarts());
    let why: String = tokio::select! {
        Ok(end) = &mut frames_end => {
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
                    shared.clock.remove(&served); // frames stop before the goodbye
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
            shared.clock.remove(&served); // frames stop before the goodbye
            goodbye(&send, &color.0, &bye).await;
            conn.close(close::BYE, why.as_bytes());
            why
        }
        _ = shared.shutting_down() => {
            let bye = ServerMessage::Bye(Reason::Shutdown);
            shared.clock.remove(&served); // frames stop before the goodbye
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
    // No more frames (a goodbye may have gone; nothing should follow it).
    shared.clock.remove(&served);
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
        frames = *served.sent.borrow(),
        seconds = started.elapsed().as_secs(),
        "left"
    );
    drop(leave);
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

/// Key datagrams into the conversation, and what it takes of them to the world (a
/// driver's, rate-limited; anything that is not a key datagram is ignored).
async fn read_keys(served: Arc<Served>, shared: Arc<Shared>) {
    while let Some(bytes) = served.conn.read_datagram().await {
        let now = std::time::Instant::now();
        let handled = lock(&served.conv).handle(now, conversation::Event::Datagram(&bytes));
        if let Some(Handled::World(event)) = handled
            && shared.world.send((event, None)).is_err()
        {
            return; // the world has stopped
        }
    }
}

/// Takes a viewer off the frame clock when dropped.
struct OnClock(Arc<Shared>, Arc<Served>);

impl Drop for OnClock {
    fn drop(&mut self) {
        self.0.clock.remove(&self.1);
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
async fn read_control(mut recv: RecvStream, served: Arc<Served>) -> ControlEnd {
    loop {
        match wire::read::<ClientMessage>(&mut recv, MAX_CONTROL).await {
            Ok(msg) => {
                let now = std::time::Instant::now();
                let handled = lock(&served.conv).handle(now, conversation::Event::Control(msg));
                if handled == Some(Handled::Goodbye) {
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
