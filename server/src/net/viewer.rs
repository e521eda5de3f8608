//! One viewer's connection: the handshake, its key datagrams and control messages, and its
//! frames, paced by the clock and made by the viewer's sans-IO core
//! ([`crate::viewer::ViewerCore`]).
//!
//! How a frame goes:
//!
//! - a **change frame** that fits in one datagram goes as one (almost every frame); a
//!   larger one on a stream of its own, abandoned (reset) when the next frame is ready
//!   unless the viewer has acknowledged it (latest frame wins): a lost or abandoned change
//!   frame is never a base;
//! - a **key frame** always goes on a stream of its own, reliably, at the highest
//!   priority, and is not abandoned while it is pending
//!   ([`crate::viewer::ViewerCore::pending_key`]): the frames after it are coded against
//!   it before the viewer has it, so on a link that cannot carry a key frame a frame
//!   interval it still arrives, and the viewer decodes it and the frames after. It is reset
//!   only once superseded by a newer key frame (or when the viewer asked for another),
//!   unless acknowledged.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use roam_link::wire;
use roam_protocol::messages::{ClientMessage, Reason, Role, ServerMessage, VERSION, close};
use tokio::sync::oneshot;

use super::Shared;
use crate::sim::world::VehicleId;
use crate::sim::world_core::{Event, Snapshot};
use crate::viewer::link::{self, Control, KeyGate, LossMeter, Mailbox, frame_message};
use crate::viewer::{Scene, ViewerCore};

/// Colour-map bytes per chunk.
const CHUNK: usize = 64 << 10;
/// How long after a small frame its second copy goes, on a lossy link ([`LossMeter`]).
const REPEAT_AFTER: Duration = Duration::from_millis(4);

fn refuse(conn: &quinn::Connection, code: u32, why: &str) {
    conn.close(code.into(), why.as_bytes());
}

/// Sends a last message (a refusal, a goodbye) and gives it a moment to arrive before the
/// connection closes (closing drops what is unsent).
async fn last_word(send: &mut quinn::SendStream, msg: &ServerMessage) {
    if wire::write(send, msg).await.is_ok() && send.finish().is_ok() {
        let _ = tokio::time::timeout(Duration::from_millis(250), send.stopped()).await;
    }
}

/// Serves one connection to its end.
pub async fn serve(conn: quinn::Connection, shared: Arc<Shared>) {
    let accepted = tokio::time::timeout(Duration::from_secs(5), conn.accept_bi()).await;
    let Ok(Ok((mut send, mut recv))) = accepted else {
        refuse(&conn, close::PROTOCOL, "no control stream within 5 s");
        return;
    };
    let hello = match tokio::time::timeout(
        Duration::from_secs(5),
        wire::read::<ClientMessage>(&mut recv, 4096),
    )
    .await
    {
        Ok(Ok(ClientMessage::Hello(h))) => h,
        _ => {
            refuse(&conn, close::PROTOCOL, "expected a hello");
            return;
        }
    };
    let reply = |reason: Reason| ServerMessage::Refused(reason);
    if hello.version != VERSION {
        last_word(&mut send, &reply(Reason::Version { server: VERSION })).await;
        refuse(&conn, close::REFUSED, "protocol version");
        return;
    }
    if !constant_time_eq(hello.token.as_bytes(), shared.token.as_bytes()) {
        last_word(&mut send, &reply(Reason::WrongToken)).await;
        refuse(&conn, close::REFUSED, "wrong token");
        return;
    }
    // A driver gets a vehicle; a spectator follows one.
    let (vehicle, driver) = match hello.role {
        Role::Driver => {
            let (tx, rx) = oneshot::channel();
            if shared.world.send((Event::Join, Some(tx))).is_err() {
                refuse(&conn, close::SHUTDOWN, "shutting down");
                return;
            }
            match rx.await {
                Ok(id) => (id, true),
                Err(_) => {
                    refuse(&conn, close::SHUTDOWN, "shutting down");
                    return;
                }
            }
        }
        Role::Spectator { follow } => {
            let snap = shared.snapshots.borrow().clone();
            let target = match follow {
                Some(id) => snap.vehicles.iter().find(|v| v.id == id),
                None => snap.vehicles.first(),
            };
            match target {
                Some(v) => (v.id, false),
                None => {
                    let why = Reason::Unavailable("no vehicle to follow".into());
                    last_word(&mut send, &reply(why)).await;
                    refuse(&conn, close::REFUSED, "no vehicle to follow");
                    return;
                }
            }
        }
    };
    let leave = Leave {
        world: shared.world.clone(),
        vehicle: driver.then_some(vehicle),
    };
    if welcome(&mut send, &shared, vehicle).await.is_err() {
        return;
    }
    let control = Arc::new(Mutex::new(Mailbox::default()));
    let keys = tokio::spawn(read_keys(conn.clone(), shared.clone(), vehicle, driver));
    let ctl = tokio::spawn(read_control(recv, control.clone()));
    let core = ViewerCore::for_hello(&shared.terrain, shared.height_step, &hello, shared.limits);
    let rate = ViewerCore::frame_rate(&hello, shared.limits);
    tokio::select! {
        end = frames(&conn, &shared, control, core, rate, vehicle, driver) => {
            let why = match end {
                FramesEnd::ConnectionLost => None,
                FramesEnd::VehicleLeft => Some("the vehicle followed has left"),
                FramesEnd::Failed(why) => Some(why),
            };
            if let Some(why) = why {
                let bye = ServerMessage::Bye(Reason::Unavailable(why.into()));
                last_word(&mut send, &bye).await;
                conn.close(close::BYE.into(), why.as_bytes());
            }
        }
        _ = ctl => conn.close(close::BYE.into(), b"bye"),
        _ = conn.closed() => {}
        _ = shared.shutting_down() => {
            last_word(&mut send, &ServerMessage::Bye(Reason::Shutdown)).await;
            conn.close(close::SHUTDOWN.into(), b"the server is shutting down");
        }
    }
    keys.abort();
    drop(leave);
}

/// Tells the world a driver left, however the connection ended.
struct Leave {
    world: std::sync::mpsc::Sender<super::world_loop::Inbound>,
    vehicle: Option<VehicleId>,
}

impl Drop for Leave {
    fn drop(&mut self) {
        if let Some(vehicle) = self.vehicle {
            let _ = self.world.send((Event::Leave(vehicle), None));
        }
    }
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn welcome(
    send: &mut quinn::SendStream,
    shared: &Shared,
    vehicle: VehicleId,
) -> Result<(), wire::WireError> {
    let tick = shared.snapshots.borrow().tick;
    let w = link::welcome(
        &shared.terrain,
        vehicle,
        tick,
        shared.color_map.len() as u32,
        shared.limits,
    );
    wire::write(send, &ServerMessage::Welcome(w)).await?;
    for (k, chunk) in shared.color_map.chunks(CHUNK).enumerate() {
        let msg = ServerMessage::ColorMap {
            offset: (k * CHUNK) as u32,
            data: chunk.to_vec(),
        };
        wire::write(send, &msg).await?;
    }
    Ok(())
}

/// Key datagrams to the world, through the driver's [`KeyGate`] (rate-limited; anything
/// that is not a key datagram is ignored). A spectator's are read and dropped.
async fn read_keys(conn: quinn::Connection, shared: Arc<Shared>, vehicle: VehicleId, driver: bool) {
    let mut gate = KeyGate::new(vehicle);
    while let Ok(bytes) = conn.read_datagram().await {
        if let Some(event) = gate.admit(&bytes, std::time::Instant::now())
            && driver
            && shared.world.send((event, None)).is_err()
        {
            return; // the world has stopped
        }
    }
}

/// Control messages into the mailbox until the viewer says goodbye or sends something
/// that is not one.
async fn read_control(mut recv: quinn::RecvStream, control: Arc<Mutex<Mailbox>>) {
    while let Ok(msg) = wire::read::<ClientMessage>(&mut recv, 4096).await {
        let mut c = control.lock().unwrap_or_else(|e| e.into_inner());
        if c.push(msg) == Control::End {
            return;
        }
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

async fn frames(
    conn: &quinn::Connection,
    shared: &Arc<Shared>,
    control: Arc<Mutex<Mailbox>>,
    core: ViewerCore,
    rate: u16,
    vehicle: VehicleId,
    driver: bool,
) -> FramesEnd {
    let mut core = Some(core);
    let mut interval = tokio::time::interval(Duration::from_secs_f64(1.0 / f64::from(rate)));
    interval.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // The newest change frame sent on a stream, and the newest key frame (kept apart: it
    // is never abandoned while it is pending).
    let mut in_flight: Option<Sending> = None;
    let mut key_in_flight: Option<Sending> = None;
    let mut seen = false;
    let mut loss = LossMeter::default();
    loop {
        interval.tick().await;
        let snap: Arc<Snapshot> = shared.snapshots.borrow().clone();
        let Some(v) = snap.vehicles.iter().find(|v| v.id == vehicle) else {
            if seen {
                return FramesEnd::VehicleLeft;
            }
            continue; // a new driver's vehicle appears with the next tick
        };
        seen = true;
        let mut c = core.take().expect("put back below");
        for event in control.lock().unwrap_or_else(|e| e.into_inner()).drain() {
            c.handle(event);
        }
        let (shared2, state) = (shared.clone(), v.state);
        let make = move |mut c: ViewerCore| {
            let scene = Scene {
                terrain: &shared2.terrain,
                variance: &shared2.variance,
            };
            let made = c.make_frame(&scene, &state);
            (c, made)
        };
        let scene = Scene {
            terrain: &shared.terrain,
            variance: &shared.variance,
        };
        // An update is a fraction of a millisecond: made in line. A rebuild or a key frame
        // (milliseconds at large budgets) goes to a blocking thread, so it never holds up
        // the other viewers' tasks.
        let (c, made) = if c.next_is_cheap(&scene, &state) {
            make(c)
        } else {
            match tokio::task::spawn_blocking(move || make(c)).await {
                Ok(r) => r,
                Err(_) => return FramesEnd::Failed("the frame maker failed"),
            }
        };
        let acked = c.acked();
        let pending_key = c.pending_key();
        core = Some(c);
        let frame = made.frame;
        let key = made.base.is_none();
        let msg = frame_message(&shared.terrain, &snap, made, vehicle, driver);
        let mut bytes = Vec::new();
        if roam_protocol::messages::encode(&msg, &mut bytes).is_err() {
            return FramesEnd::Failed("a frame over the message limit");
        }
        // Latest frame wins: the previous change frame's stream is reset unless the viewer
        // has acknowledged it, whether it is still being written or already handed to quinn
        // (a finished stream still waits in the send buffer on a slow link). The key frame
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
            let stats = conn.stats();
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
                Err(quinn::SendDatagramError::ConnectionLost(_)) => {
                    return FramesEnd::ConnectionLost;
                }
                // Not allowed or too large after all: the stream takes it.
                Err(_) => {}
            }
        }
        let Ok(mut stream) = conn.open_uni().await else {
            return FramesEnd::ConnectionLost;
        };
        // Newer frames first, and a key frame before all: the frames after it need it.
        let _ = stream.set_priority(if key { i32::MAX } else { frame as i32 });
        let (cancel, cancelled) = oneshot::channel::<()>();
        let task = tokio::spawn(async move {
            tokio::select! {
                r = stream.write_all(&bytes) => {
                    if r.is_ok() && stream.finish().is_ok() {
                        return Some(stream);
                    }
                    None
                }
                _ = cancelled => {
                    let _ = stream.reset(0u32.into());
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
    task: tokio::task::JoinHandle<Option<quinn::SendStream>>,
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
            let _ = stream.reset(0u32.into());
        }
    }
}
