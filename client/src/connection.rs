//! One connection's tasks and words, with no clock (the session, [`crate::session`], bounds
//! them in time): the frames read into the session's core (datagrams, and streams read to
//! their end, each chunk news of the server), the server's control messages after the
//! join (colour windows and tiles into the colour cache, each tile decoded outside its
//! lock; a goodbye ends the session; a colour message the cache refuses ends it as the
//! server's protocol error), the goodbye said when the viewer quits, and how a connection
//! ended ([`End`]: quit, lost, or for good); one attempt to join (bounded by the session's
//! timeouts), and the key sender.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{Result, anyhow};
use roam_link::wire;
use roam_protocol::messages::{self, ClientMessage, Hello, Reason, ServerMessage, close};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;

use crate::color_cache::Keep;
use crate::join::{self, JoinError, Joined};
use crate::joining::take_control;
use crate::session::{CONTROL_TIMEOUT, JOIN_TIMEOUT, Link, Steps, lock, secs};

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
    /// For good.
    Final(String),
}

impl End {
    pub fn of(e: &quinn::ConnectionError) -> End {
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
/// windows and tiles go to the colour cache; a goodbye ends the session, and so does
/// anything else (not the protocol). Ends with the stream.
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
        if let Err(why) = take_control(&msg, &mut rgb, || lock(&link.colors)) {
            break End::Final(why);
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
/// are numbered) unsent. Ends with the session.
pub async fn send_keys(link: Arc<Link>, mut steps: Steps) {
    let mut tick = tokio::time::interval(Duration::from_millis(10));
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
