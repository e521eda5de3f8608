//! One connection's tasks and words, with no clock (the session, [`crate::session`], bounds
//! them in time): the frames read into the session's core (datagrams, and streams read to
//! their end, each chunk news of the server), the server's control messages after the
//! colour map (a goodbye ends the session), the goodbye said when the viewer quits, and
//! how a connection ended ([`End`]: quit, lost, or for good).

use std::sync::Arc;

use roam_link::wire;
use roam_protocol::messages::{self, ClientMessage, Reason, ServerMessage, close};
use tokio::sync::{mpsc, oneshot};
use tokio::task::JoinSet;

use crate::join::{self, describe};
use crate::session::Link;

/// The largest frame message read: a key frame at the largest budget is under 2 MiB, and
/// 16 streams of this much bound what a server can make the viewer hold.
pub const MAX_FRAME: usize = 8 << 20;

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

/// The server's control messages after the colour map: each is news of the server; a
/// goodbye ends the session, anything else is not the protocol. Ends with the stream.
pub async fn read_control(mut recv: quinn::RecvStream, link: Arc<Link>, ends: mpsc::Sender<End>) {
    let end = match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await {
        Ok(ServerMessage::Bye(reason)) => {
            End::Final(format!("the server said goodbye: {}", describe(&reason)))
        }
        Ok(other) => End::Final(format!(
            "the server sent {} after the colour map",
            join::name(&other)
        )),
        // The stream or the connection ended: the connection tells why.
        Err(wire::WireError::Closed | wire::WireError::Read(_)) => return,
        Err(e) => End::Final(format!("the server's control stream: {e}")),
    };
    link.heard();
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
