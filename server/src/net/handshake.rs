//! A connection from its first packet to its hello and join (the welcome is
//! `viewer.rs`'s): admission (the pending cap, QUIC
//! Retry, eviction of the oldest pending connection: [`crate::viewer::admission`]), one
//! deadline for the TLS handshake and the hello together, the hello's checks (version,
//! token, then a seat: the viewer limit and the memory limit), and the join: a new
//! vehicle, a held one taken back with the driver's ticket, or a vehicle to follow. A seat
//! reserves the viewer's state against `max_memory` (the estimate from its budget,
//! [`crate::viewer::admission::viewer_bytes`]) until it leaves; a refusal for memory names
//! the limit, as [`Reason::Unavailable`] (the protocol's reasons are unchanged). Every
//! refusal is said to the viewer with its reason and logged with the peer's address; junk
//! that never says hello is closed at the deadline (or evicted) and only counted (one log
//! line per junk connection would let a flood fill the disk). An evicted connection still in its TLS handshake is finished in
//! the background (at most the pending cap of them at once), by the same deadline, and
//! closed with its reason: dropped unfinished, it would end with a bare transport close,
//! which a peer whose side of the handshake is done and that sends nothing hears only if
//! that one packet arrives. Every close is made by the deadline (the summary's
//! `pending_longest_ms`); when the peer hears it is up to the network (`roam-flood`'s
//! `junk_close_ms_max_by_end`).
//!
//! A browser's connection ([`Via::Web`], on the `--web` endpoint) is admitted the same
//! way, by the same gate; after its QUIC handshake and within the same deadline come
//! HTTP/3's settings and the WebTransport `CONNECT` (to [`crate::web::SESSION_PATH`], any
//! other path answered 404), and from there on the protocol is the native one
//! ([`super::conn`]).

use std::net::SocketAddr;
use std::sync::Arc;

use roam_link::wire;
use roam_protocol::messages::{ClientMessage, Hello, Reason, Role, ServerMessage, Ticket};
use roam_protocol::messages::{VERSION, close};
use tokio::sync::oneshot;
use tokio::time::Instant;
use web_transport_quinn as wt;

use super::bus::edge::Remote;
use super::conn::{AcceptError, Conn, RecvStream, SendStream, Via, Web};
use super::seat::{Joined, MAX_CONTROL, Seat, role_name};
use super::shared::Shared;
use super::tickets::{Claim, random_ticket, secret_eq};
use super::viewer::{self, Viewer};
use crate::sim::world::VehicleId;
use crate::sim::world_core::Event;
use crate::viewer::admission::{NoSeat, PendingId, Verdict};

/// A new connection: admitted (its handshake runs on a task of its own), asked to retry
/// from a proven address, or refused, as [`crate::viewer::admission`] decides.
pub(super) fn arrive(incoming: quinn::Incoming, shared: &Arc<Shared>, via: Via) {
    let mut gate = shared.gate();
    let verdict = gate
        .admission
        .arrive(incoming.remote_address_validated(), incoming.may_retry());
    let id = match verdict {
        Verdict::Retry => {
            shared.stats.add(&shared.stats.retried, 1);
            if let Err(e) = incoming.retry() {
                e.into_incoming().refuse();
            }
            return;
        }
        Verdict::Refuse => {
            shared.stats.add(&shared.stats.refused_early, 1);
            incoming.refuse();
            return;
        }
        Verdict::Admit(id) => id,
        Verdict::AdmitEvicting { id, evict } => {
            if let Some(tx) = gate.evict.remove(&evict) {
                let _ = tx.send(());
            }
            shared.stats.add(&shared.stats.evicted, 1);
            id
        }
    };
    let (tx, evicted) = oneshot::channel();
    gate.evict.insert(id, tx);
    drop(gate);
    let pending = Pending {
        id,
        since: Instant::now(),
        shared: shared.clone(),
    };
    tokio::spawn(handshake(incoming, via, pending, evicted, shared.clone()));
}

/// A connection counted as pending until dropped.
struct Pending {
    id: PendingId,
    since: Instant,
    shared: Arc<Shared>,
}

impl Drop for Pending {
    fn drop(&mut self) {
        let ms = self.since.elapsed().as_millis();
        self.shared
            .stats
            .pending_ended(u64::try_from(ms).unwrap_or(u64::MAX));
        let mut gate = self.shared.gate();
        gate.admission.gone(self.id);
        gate.evict.remove(&self.id);
    }
}

/// Why a pending connection never said hello.
enum Early {
    /// The deadline passed.
    Deadline,
    /// A newer connection took its place.
    Evicted,
    /// The handshake failed, or the peer closed, or sent something else.
    Failed(HelloError),
}

/// Why a connection failed before its hello: the words its close gives the peer.
#[derive(Debug, thiserror::Error)]
enum HelloError {
    /// The QUIC handshake failed, or the connection ended.
    #[error(transparent)]
    Connection(#[from] quinn::ConnectionError),
    #[error("no WebTransport request: {0}")]
    NoRequest(wt::ServerError),
    /// A WebTransport request for another path than [`crate::web::SESSION_PATH`] (the
    /// path's first 64 characters), answered 404.
    #[error(
        "a WebTransport session for {path:?}, not {:?}",
        crate::web::SESSION_PATH
    )]
    WrongPath { path: String },
    #[error("answering the WebTransport request: {0}")]
    Answering(wt::ServerError),
    #[error("no control stream: {0}")]
    NoControlStream(AcceptError),
    #[error("expected a hello, got another message")]
    NotHello,
    #[error("expected a hello: {0}")]
    BadHello(wire::WireError),
}

async fn handshake(
    incoming: quinn::Incoming,
    via: Via,
    pending: Pending,
    mut evicted: oneshot::Receiver<()>,
    shared: Arc<Shared>,
) {
    let peer = incoming.remote_address();
    let deadline = Instant::now() + shared.hello_timeout;
    let mut connecting = match incoming.accept() {
        Ok(c) => c,
        Err(e) => return early(&shared, peer, via, None, Early::Failed(e.into())),
    };
    let quic = tokio::select! {
        r = tokio::time::timeout_at(deadline, &mut connecting) => match r {
            Ok(Ok(conn)) => {
                shared.gate().admission.handshaken(pending.id);
                conn
            }
            Ok(Err(why)) => return early(&shared, peer, via, None, Early::Failed(why.into())),
            Err(_) => return early(&shared, peer, via, None, Early::Deadline),
        },
        _ = &mut evicted => {
            // Its place is given up now; the handshake itself is finished (within the
            // same deadline) only to say why, as an application close the peer reads.
            if let Ok(room) = shared.unfinished.clone().try_acquire_owned() {
                tokio::spawn(async move {
                    close_unfinished(connecting, deadline).await;
                    drop(room);
                });
            }
            return early(&shared, peer, via, None, Early::Evicted);
        }
    };
    let conn = match via {
        Via::Quic => Conn::Quic(quic),
        Via::Web => {
            let raw = Some(Conn::Quic(quic.clone()));
            tokio::select! {
                r = tokio::time::timeout_at(deadline, web_session(quic)) => match r {
                    Ok(Ok(session)) => Conn::Web(Box::new(Web::new(session))),
                    Ok(Err(why)) => {
                        return early(&shared, peer, via, raw.as_ref(), Early::Failed(why));
                    }
                    Err(_) => return early(&shared, peer, via, raw.as_ref(), Early::Deadline),
                },
                _ = &mut evicted => return early(&shared, peer, via, raw.as_ref(), Early::Evicted),
            }
        }
    };
    let greeted = tokio::select! {
        r = tokio::time::timeout_at(deadline, greet(&conn)) => match r {
            Ok(Ok(g)) => g,
            Ok(Err(why)) => return early(&shared, peer, via, Some(&conn), Early::Failed(why)),
            Err(_) => return early(&shared, peer, via, Some(&conn), Early::Deadline),
        },
        _ = &mut evicted => return early(&shared, peer, via, Some(&conn), Early::Evicted),
    };
    let (mut send, recv, hello) = greeted;
    // The hello is in: the connection is no longer pending. Version and token first (a
    // peer without the token never takes a seat), then a seat, or a refusal when full.
    drop(pending);
    // Watching a recording, everyone is a spectator.
    let role = match shared.watching() {
        Some(_) => "spectator",
        None => role_name(&hello.role),
    };
    let refuse = async |send: &mut SendStream, reason: Reason, why: &str| {
        let web = via == Via::Web;
        // One line per refusal, up to a bound per summary interval: a peer without the
        // token can send hellos as fast as handshakes, and must not fill the disk.
        let via = via.name();
        if shared.stats.refusal_logged() {
            tracing::info!(%peer, via, role, reason = why, "refused");
        } else {
            tracing::debug!(%peer, via, role, reason = why, "refused");
        }
        shared.stats.add(&shared.stats.refused, 1);
        // A browser has the refusal once its QUIC stack acknowledges it, not once the page
        // has read it, and a session closed meanwhile may take both the message and the
        // close's reason with it (the page saw only "Connection lost" in a run of the whole
        // suite on a loaded machine): the page closes its session once it has read the
        // refusal, so that close is waited for. The whole refusal has one deadline, a last
        // word's: a peer that never takes the message, or never closes, holds nothing
        // longer (refusals are past the pending cap's count).
        let answer = async {
            viewer::last_word(send, &ServerMessage::Refused(reason)).await;
            if web {
                conn.closed().await;
            }
        };
        let _ = tokio::time::timeout(viewer::LAST_WORD_WAIT, answer).await;
        conn.close(close::REFUSED, why.as_bytes());
    };
    if hello.version != VERSION {
        let why = format!(
            "protocol version {} (this server: {VERSION})",
            hello.version
        );
        return refuse(&mut send, Reason::Version { server: VERSION }, &why).await;
    }
    let control_token = shared
        .replay
        .as_ref()
        .and_then(|r| r.control_token.as_deref());
    // Both compared in constant time whatever the lengths (`tickets::secret_eq`).
    let controller = control_token.is_some_and(|t| secret_eq(hello.token.as_bytes(), t.as_bytes()));
    if !controller && !secret_eq(hello.token.as_bytes(), shared.token.as_bytes()) {
        return refuse(&mut send, Reason::WrongToken, "wrong token").await;
    }
    // A driver coming back while its old connection still holds a seat (this server has
    // not seen it die yet) may take one past the limit: the old one is about to go.
    let replacing = hello.resume.is_some_and(|t| {
        shared
            .tickets()
            .get(&t)
            .is_some_and(|c| c.replace.as_ref().is_some_and(|r| !r.is_closed()))
    });
    // Its state is reserved for the budget it is served (clamped), before it costs anything.
    let budget = shared.limits.budget(hello.budget);
    let seated = shared.gate().admission.seat(budget, replacing);
    let seat = match seated {
        Ok(seat) => Seat::new(shared.clone(), seat),
        Err(NoSeat::Full(full)) => {
            let reason = Reason::Full {
                viewers: full.max as u32,
            };
            return refuse(&mut send, reason, &full.to_string()).await;
        }
        Err(NoSeat::Memory(out)) => {
            let why = out.to_string();
            return refuse(&mut send, Reason::Unavailable(why.clone()), &why).await;
        }
    };
    let joined = match join(&shared, &hello).await {
        Ok(j) => Joined { controller, ..j },
        Err(Refusal::Shutdown) => {
            conn.close(close::SHUTDOWN, b"the server is shutting down");
            return;
        }
        Err(Refusal::Unavailable(why)) => {
            return refuse(&mut send, Reason::Unavailable(why.clone()), &why).await;
        }
    };
    tracing::info!(
        %peer,
        via = via.name(),
        role,
        vehicle = joined.vehicle,
        resumed = joined.resumed,
        "joined"
    );
    shared.stats.add(&shared.stats.joins, 1);
    viewer::serve(
        Viewer {
            conn,
            send,
            recv,
            hello,
            peer,
            joined,
        },
        seat,
        shared,
    )
    .await;
}

/// Counts a connection that never said hello, and closes it with the reason.
fn early(shared: &Shared, peer: SocketAddr, via: Via, conn: Option<&Conn>, why: Early) {
    let (counter, text) = match &why {
        Early::Deadline => (
            &shared.stats.timed_out,
            "no hello by the deadline".to_owned(),
        ),
        Early::Evicted => (
            &shared.stats.evicted_closed,
            "evicted: too many connections without a hello".to_owned(),
        ),
        Early::Failed(e) => (&shared.stats.failed, e.to_string()),
    };
    shared.stats.add(counter, 1);
    tracing::debug!(%peer, via = via.name(), reason = %text, "closed before its hello");
    if let Some(conn) = conn {
        let code = match why {
            Early::Failed(_) => close::PROTOCOL,
            _ => close::REFUSED,
        };
        conn.close(code, text.as_bytes());
    }
}

/// An evicted connection caught mid-handshake: dropped there, it would end with a bare
/// transport close that a peer whose side of the handshake is done may never see (it
/// waits out its idle timeout, 10 s, twice the deadline). Finished (by the deadline at the
/// latest) and closed with [`close::REFUSED`] instead, it is told at once. It holds no
/// place in the admission gate while it finishes; at most `max_pending` are finished at
/// once (`Shared::unfinished`), the rest are dropped as before.
async fn close_unfinished(connecting: quinn::Connecting, deadline: Instant) {
    if let Ok(Ok(conn)) = tokio::time::timeout_at(deadline, connecting).await {
        conn.close(
            close::REFUSED.into(),
            b"evicted: too many connections without a hello",
        );
    }
}

/// How long a refused WebTransport request's answer (404) is given to arrive before the
/// connection closes.
const REJECT_GRACE: std::time::Duration = std::time::Duration::from_millis(250);

/// HTTP/3's settings and the WebTransport `CONNECT` on a new web connection: a session
/// on [`crate::web::SESSION_PATH`], or why not (another path is answered 404).
async fn web_session(conn: quinn::Connection) -> Result<wt::Session, HelloError> {
    let request = wt::Request::accept(conn.clone())
        .await
        .map_err(HelloError::NoRequest)?;
    let path = request.url.path().to_owned();
    if path != crate::web::SESSION_PATH {
        let _ = request.reject(http::StatusCode::NOT_FOUND).await;
        let _ = tokio::time::timeout(REJECT_GRACE, conn.closed()).await;
        let path = path.chars().take(64).collect();
        return Err(HelloError::WrongPath { path });
    }
    request.ok().await.map_err(HelloError::Answering)
}

/// The viewer's control stream and its hello.
async fn greet(conn: &Conn) -> Result<(SendStream, RecvStream, Hello), HelloError> {
    let (send, mut recv) = conn
        .accept_bi()
        .await
        .map_err(HelloError::NoControlStream)?;
    match wire::read::<ClientMessage>(&mut recv, MAX_CONTROL).await {
        Ok(ClientMessage::Hello(h)) => Ok((send, recv, h)),
        Ok(_) => Err(HelloError::NotHello),
        Err(e) => Err(HelloError::BadHello(e)),
    }
}

enum Refusal {
    Shutdown,
    Unavailable(String),
}

/// How long a reconnection waits for the connection it replaces to end.
const REPLACE_WAIT: std::time::Duration = std::time::Duration::from_secs(1);

/// A driver takes its held vehicle back with its ticket, or gets a new one; a spectator
/// follows the vehicle it asked for (or the first).
async fn join(shared: &Shared, hello: &Hello) -> Result<Joined, Refusal> {
    if let Some(replay) = shared.watching() {
        // Watching a recording: everyone is a spectator, of the vehicle asked for if it is
        // there, else the first there, else the first the recording has (or, a session
        // still empty, vehicle 0: the frames follow the first to come).
        let follow = match hello.role {
            Role::Spectator { follow } => follow,
            Role::Driver => None,
        };
        let snap = shared.snapshots.borrow().clone();
        let there = |id: u16| snap.vehicles.iter().any(|v| v.id == id);
        let vehicle = follow
            .filter(|&id| there(id))
            .or_else(|| snap.vehicles.first().map(|v| v.id))
            .or(replay.first_vehicle)
            .unwrap_or(0);
        return Ok(Joined::spectator(vehicle));
    }
    if let Role::Spectator { follow } = hello.role {
        let snap = shared.snapshots.borrow().clone();
        let target = match follow {
            Some(id) => snap.vehicles.iter().find(|v| v.id == id),
            None => snap.vehicles.first(),
        };
        return match target {
            Some(v) => Ok(Joined::spectator(v.id)),
            None => Err(Refusal::Unavailable("no vehicle to follow".into())),
        };
    }
    let (replace, replaced) = oneshot::channel();
    let (vehicle, ticket, resumed, claim) = match &shared.remote {
        Some(remote) => from_world(shared, remote, hello).await?,
        None => from_here(shared, hello).await?,
    };
    let mut tickets = shared.tickets();
    // The freed vehicles' tickets name nothing now. Taken before this join's own ticket
    // goes in: a vehicle freed before this join was answered is never this one.
    for freed in shared.world_stats.take_evicted() {
        tickets.retain(|_, c| c.vehicle != freed);
    }
    // A ticket names one vehicle, and a vehicle has one ticket (ids are reused).
    tickets.retain(|_, c| c.vehicle != vehicle);
    tickets.insert(
        ticket,
        Claim {
            vehicle,
            replace: Some(replace),
        },
    );
    Ok(Joined {
        vehicle,
        driver: true,
        ticket: Some(ticket),
        resumed,
        claim,
        replaced: Some(replaced),
        controller: false,
    })
}

/// A driver's vehicle from the world in this process: its held one taken back with the
/// ticket this server gave it, or a new one with a new ticket. Whether it was resumed (and
/// no claim: 0).
async fn from_here(
    shared: &Shared,
    hello: &Hello,
) -> Result<(VehicleId, Ticket, bool, u64), Refusal> {
    let claim = hello.resume.and_then(|t| shared.tickets().remove(&t));
    if let (Some(ticket), Some(claim)) = (hello.resume, claim) {
        end_replaced(claim.replace).await;
        if let Ok(vehicle) = ask(shared, Event::Resume(claim.vehicle)).await {
            return Ok((vehicle, ticket, true, 0));
        }
    }
    // At the limit, the world frees the oldest held vehicle before it seats this one
    // ([`crate::sim::world_core::WorldCore::with_limit`]): decided there, in the order the
    // joins arrive, so two at once free two distinct vehicles.
    let vehicle = ask(shared, Event::Join)
        .await
        .map_err(|()| refused(shared, "no vehicle free".into()))?;
    Ok((vehicle, random_ticket(), false, 0))
}

/// A driver's vehicle from the world over the bus (an edge): its held one taken back with
/// its ticket (the world's: any edge's), or a new one with the world's new ticket; and the
/// world's claim for this connection.
async fn from_world(
    shared: &Shared,
    remote: &Remote,
    hello: &Hello,
) -> Result<(VehicleId, Ticket, bool, u64), Refusal> {
    if let Some(ticket) = hello.resume {
        let claim = shared.tickets().remove(&ticket);
        end_replaced(claim.and_then(|c| c.replace)).await;
        match remote.resume(ticket).await {
            Ok((vehicle, claim)) => return Ok((vehicle, ticket, true, claim)),
            Err(why) => tracing::info!("a resume refused by the world ({why}): a new vehicle"),
        }
    }
    let (vehicle, ticket, claim) = remote
        .join()
        .await
        .map_err(|why| refused(shared, why.to_string()))?;
    Ok((vehicle, ticket, false, claim))
}

/// The old connection of a driver coming back may still be up (its loss not yet seen
/// here): it is ended first, so that the world holds the vehicle before it is asked for
/// it back.
async fn end_replaced(old: Option<oneshot::Sender<oneshot::Sender<()>>>) {
    if let Some(old) = old {
        let (done, ended) = oneshot::channel();
        if old.send(done).is_ok() {
            let _ = tokio::time::timeout(REPLACE_WAIT, ended).await;
        }
    }
}

/// A join the world did not grant: the server is stopping, or `why`.
fn refused(shared: &Shared, why: String) -> Refusal {
    if *shared.shutdown.borrow() {
        Refusal::Shutdown
    } else {
        Refusal::Unavailable(why)
    }
}

/// Hands the world an event that answers with a vehicle: `Err` when it answers none (a
/// resume too late, no free id) or has stopped.
async fn ask(shared: &Shared, event: Event) -> Result<VehicleId, ()> {
    let (tx, rx) = oneshot::channel();
    shared.world.send((event, Some(tx))).map_err(|_| ())?;
    rx.await.map_err(|_| ())
}
