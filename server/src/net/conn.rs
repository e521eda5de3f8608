//! A viewer's connection, whichever way it came: native QUIC (`roam/1`) or a browser's
//! WebTransport session (HTTP/3). After the handshake the protocol is the same: one
//! bidirectional control stream opened by the viewer, frames as datagrams or uni streams,
//! key datagrams, the same close codes. [`Conn`], [`SendStream`] and [`RecvStream`] are
//! closed enums over the two, with exactly what the handshake and the viewer task use.
//!
//! Decisions:
//!
//! - **A web session's I/O goes through `web_transport_quinn`.** Its streams and datagrams
//!   carry an HTTP/3 prefix (stream type, session id), its stream codes are mapped into
//!   HTTP/3's space and its close code travels in a capsule on the `CONNECT` stream; the
//!   raw `quinn::Connection` under it is read only for statistics and the address.
//! - **Errors look like quinn's.** A web stream's errors are turned into the
//!   `quinn::ReadExactError`/`WriteError` that [`roam_link::wire`] reports, so the
//!   framing, its limits and the logs are the native ones.
//! - **One hold rule for both** ([`Conn::hold_after`]): a goodbye or this server's own
//!   close frees a driver's vehicle; anything else (lost, timed out, closed by the viewer
//!   with another code) holds it. A web session's peer close comes as the capsule's code;
//!   its library closes the QUIC connection itself when the `CONNECT` stream ends, so
//!   whether this server closed it is remembered here, not read from quinn.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use bytes::Bytes;
use roam_link::wire::{self, Source, WireError};
use roam_protocol::messages::close;
use web_transport_quinn as wt;

/// How a viewer came: the logs' `via`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Via {
    /// Native QUIC (`roam-client`).
    Quic,
    /// WebTransport over HTTP/3 (the browser page).
    Web,
}

impl Via {
    pub fn name(self) -> &'static str {
        match self {
            Via::Quic => "quic",
            Via::Web => "web",
        }
    }
}

/// Why a connection gave no stream (it ended), in quinn's or WebTransport's words.
#[derive(Debug, thiserror::Error)]
pub enum AcceptError {
    #[error(transparent)]
    Quic(#[from] quinn::ConnectionError),
    #[error(transparent)]
    Web(#[from] wt::SessionError),
}

/// A viewer's connection.
#[derive(Clone)]
pub enum Conn {
    Quic(quinn::Connection),
    /// Boxed: a session is some 800 bytes, a connection a pointer.
    Web(Box<Web>),
}

/// A WebTransport session, and whether this server closed it.
#[derive(Clone)]
pub struct Web {
    pub session: wt::Session,
    closed_here: Arc<AtomicBool>,
}

impl Web {
    pub fn new(session: wt::Session) -> Web {
        Web {
            session,
            closed_here: Arc::new(AtomicBool::new(false)),
        }
    }
}

/// Why a datagram was not sent.
#[derive(Debug, PartialEq, Eq)]
pub enum DatagramError {
    /// The connection is gone.
    Lost,
    /// Too large, or datagrams not allowed: a stream takes it instead.
    Refused,
}

impl Conn {
    /// The QUIC connection under it: statistics and the address only.
    pub fn quic(&self) -> &quinn::Connection {
        match self {
            Conn::Quic(c) => c,
            Conn::Web(w) => &w.session,
        }
    }

    pub fn via(&self) -> Via {
        match self {
            Conn::Quic(_) => Via::Quic,
            Conn::Web(_) => Via::Web,
        }
    }

    /// The viewer's control stream.
    pub async fn accept_bi(&self) -> Result<(SendStream, RecvStream), AcceptError> {
        Ok(match self {
            Conn::Quic(c) => c
                .accept_bi()
                .await
                .map(|(s, r)| (SendStream::Quic(s), RecvStream::Quic(r)))?,
            Conn::Web(w) => w
                .session
                .accept_bi()
                .await
                .map(|(s, r)| (SendStream::Web(s), RecvStream::Web(r)))?,
        })
    }

    /// A new stream for a frame; `None` when the connection can take no more.
    pub async fn open_uni(&self) -> Option<SendStream> {
        match self {
            Conn::Quic(c) => c.open_uni().await.ok().map(SendStream::Quic),
            Conn::Web(w) => w.session.open_uni().await.ok().map(SendStream::Web),
        }
    }

    /// The next datagram from the viewer; `None` once the connection is gone. A web
    /// datagram for another session is skipped.
    pub async fn read_datagram(&self) -> Option<Bytes> {
        match self {
            Conn::Quic(c) => c.read_datagram().await.ok(),
            Conn::Web(w) => loop {
                match w.session.read_datagram().await {
                    Ok(b) => return Some(b),
                    Err(wt::SessionError::WebTransportError(
                        wt::WebTransportError::UnknownSession,
                    )) => continue,
                    Err(_) => return None,
                }
            },
        }
    }

    pub fn send_datagram(&self, data: Bytes) -> Result<(), DatagramError> {
        use quinn::SendDatagramError as Q;
        let e = match self {
            Conn::Quic(c) => match c.send_datagram(data) {
                Ok(()) => return Ok(()),
                Err(e) => e,
            },
            Conn::Web(w) => match w.session.send_datagram(data) {
                Ok(()) => return Ok(()),
                Err(wt::SessionError::SendDatagramError(e)) => e,
                Err(_) => return Err(DatagramError::Lost),
            },
        };
        match e {
            Q::ConnectionLost(_) => Err(DatagramError::Lost),
            _ => Err(DatagramError::Refused),
        }
    }

    /// The largest datagram payload the viewer takes now, `None` if it takes none.
    pub fn max_datagram_size(&self) -> Option<usize> {
        match self {
            Conn::Quic(c) => c.max_datagram_size(),
            Conn::Web(w) => Some(w.session.max_datagram_size()).filter(|&n| n > 0),
        }
    }

    /// Closes with one of [`roam_protocol::messages::close`]'s codes (a web session's
    /// close code, said in its capsule).
    pub fn close(&self, code: u32, reason: &[u8]) {
        match self {
            Conn::Quic(c) => c.close(code.into(), reason),
            Conn::Web(w) => {
                w.closed_here.store(true, Ordering::Relaxed);
                w.session.close(code, reason);
            }
        }
    }

    /// Waits until the connection has ended.
    pub async fn closed(&self) {
        match self {
            Conn::Quic(c) => {
                c.closed().await;
            }
            Conn::Web(w) => {
                w.session.closed().await;
            }
        }
    }

    /// Why the connection ended, as the logs say it; `None` while it is up.
    pub fn close_reason(&self) -> Option<String> {
        match self {
            Conn::Quic(c) => c.close_reason().map(|e| e.to_string()),
            Conn::Web(w) => {
                // The session's reason (a capsule's code) once the QUIC connection is down.
                self.quic().close_reason()?;
                w.session.close_reason().map(|e| e.to_string())
            }
        }
    }

    /// Whether a driver whose connection ended gets its vehicle held: yes when the
    /// connection was lost (timed out, reset, a transport error, or closed by the viewer
    /// with any code but the goodbye's, as a viewer does that gave up on a path it thinks
    /// dead); no after a goodbye, or when this server closed it. One rule, whichever of
    /// the viewer's tasks noticed the end first (quinn records the reason before it wakes
    /// them, and a web session its capsule's before it closes the connection).
    pub fn hold_after(&self) -> bool {
        use quinn::ConnectionError as E;
        match self {
            Conn::Quic(c) => match c.close_reason() {
                None | Some(E::LocallyClosed) => false,
                Some(E::ApplicationClosed(c)) => {
                    c.error_code != quinn::VarInt::from_u32(close::BYE)
                }
                Some(_) => true,
            },
            Conn::Web(w) => {
                if self.quic().close_reason().is_none() || w.closed_here.load(Ordering::Relaxed) {
                    return false;
                }
                match w.session.close_reason() {
                    Some(wt::SessionError::WebTransportError(wt::WebTransportError::Closed(
                        code,
                        _,
                    ))) => code != close::BYE,
                    _ => true,
                }
            }
        }
    }
}

/// A stream the server writes: the control stream's sending half, or a frame's.
pub enum SendStream {
    Quic(quinn::SendStream),
    Web(wt::SendStream),
}

impl SendStream {
    pub async fn write_all(&mut self, buf: &[u8]) -> Result<(), quinn::WriteError> {
        match self {
            SendStream::Quic(s) => s.write_all(buf).await,
            SendStream::Web(s) => s.write_all(buf).await.map_err(write_error),
        }
    }

    /// One message, length-prefixed ([`roam_link::wire`]).
    pub async fn write_msg<T: serde::Serialize>(&mut self, msg: &T) -> Result<(), WireError> {
        let bytes = wire::frame(msg)?;
        self.write_all(&bytes).await.map_err(WireError::Write)
    }

    /// Higher first ([`quinn::SendStream::set_priority`]); an error only if the stream is
    /// gone, which the next write reports.
    pub fn set_priority(&self, priority: i32) {
        let _ = match self {
            SendStream::Quic(s) => s.set_priority(priority).map_err(|_| ()),
            SendStream::Web(s) => s.set_priority(priority).map_err(|_| ()),
        };
    }

    /// Abandons what is unsent (quinn stops sending and retransmitting it).
    pub fn reset(&mut self, code: u32) {
        let _ = match self {
            SendStream::Quic(s) => s.reset(code.into()).map_err(|_| ()),
            SendStream::Web(s) => s.reset(code).map_err(|_| ()),
        };
    }

    /// No more data; `false` if the stream was already gone.
    pub fn finish(&mut self) -> bool {
        match self {
            SendStream::Quic(s) => s.finish().is_ok(),
            SendStream::Web(s) => s.finish().is_ok(),
        }
    }

    /// Waits until the peer has everything, stopped the stream, or the connection ended.
    pub async fn stopped(&self) {
        match self {
            SendStream::Quic(s) => {
                let _ = s.stopped().await;
            }
            SendStream::Web(s) => {
                let _ = s.stopped().await;
            }
        }
    }
}

/// The control stream's receiving half.
pub enum RecvStream {
    Quic(quinn::RecvStream),
    Web(wt::RecvStream),
}

impl Source for RecvStream {
    async fn read_exact(&mut self, buf: &mut [u8]) -> Result<(), quinn::ReadExactError> {
        match self {
            RecvStream::Quic(r) => r.read_exact(buf).await,
            RecvStream::Web(r) => r.read_exact(buf).await.map_err(|e| match e {
                wt::ReadExactError::FinishedEarly(n) => quinn::ReadExactError::FinishedEarly(n),
                wt::ReadExactError::ReadError(e) => quinn::ReadExactError::ReadError(read_error(e)),
            }),
        }
    }
}

/// A web session's error as the QUIC connection's.
fn connection_error(e: wt::SessionError) -> quinn::ConnectionError {
    match e {
        wt::SessionError::ConnectionError(e) => e,
        wt::SessionError::SendDatagramError(quinn::SendDatagramError::ConnectionLost(e)) => e,
        wt::SessionError::WebTransportError(wt::WebTransportError::Closed(code, reason)) => {
            quinn::ConnectionError::ApplicationClosed(quinn::ApplicationClose {
                error_code: code.into(),
                reason: reason.into_bytes().into(),
            })
        }
        // A stream header or datagram for another session, or a datagram refused: not the
        // connection's end, but nothing more can be read where it happened.
        _ => quinn::ConnectionError::LocallyClosed,
    }
}

fn read_error(e: wt::ReadError) -> quinn::ReadError {
    match e {
        wt::ReadError::SessionError(e) => quinn::ReadError::ConnectionLost(connection_error(e)),
        wt::ReadError::Reset(code) => quinn::ReadError::Reset(code.into()),
        wt::ReadError::InvalidReset(code) => quinn::ReadError::Reset(code),
        wt::ReadError::ClosedStream => quinn::ReadError::ClosedStream,
        wt::ReadError::IllegalOrderedRead => quinn::ReadError::IllegalOrderedRead,
    }
}

fn write_error(e: wt::WriteError) -> quinn::WriteError {
    match e {
        wt::WriteError::Stopped(code) => quinn::WriteError::Stopped(code.into()),
        wt::WriteError::InvalidStopped(code) => quinn::WriteError::Stopped(code),
        wt::WriteError::SessionError(e) => quinn::WriteError::ConnectionLost(connection_error(e)),
        wt::WriteError::ClosedStream => quinn::WriteError::ClosedStream,
    }
}
