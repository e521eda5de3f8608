//! The native viewer's QUIC: the client endpoint pinning the server's certificate (one per
//! session, whatever addresses it tries: [`endpoint_for`]), one join over a connection
//! ([`hello`]: the hello, the welcome, its colour layout checked against the grid and the
//! window asked, [`ColorCache::new`], and the coarsest colour tile, so that the first
//! frame has a colour everywhere; the rest of the colour pyramid streams during the
//! session), and what a connection's end means ([`ending`], [`end_of`]): **lost** (timed
//! out, reset, a transport error: worth reconnecting) or **final** (the server closed it,
//! refused the viewer, or broke the protocol). No clock here: the session's tasks bound
//! each step in time. What the messages mean is [`crate::conversation`]'s, shared with the
//! page.
//!
//! Grid limit: the viewer takes any grid the protocol has (`2^15 + 1`,
//! `roam_protocol::Grid::new`); it was `2^13 + 1` while the colour map came whole. Grid
//! coordinates are `u16` (32768 fits) and world positions `f32` (32768 cells at 100 m are
//! 3,277 km: `f32` steps of 0.25 m at the far edge). The frame decoder's state is sized by
//! the cut, not the grid ([`crate::core::ClientCore`]).

use std::net::SocketAddr;

use anyhow::{Context, Result};
use roam_link::{tls, wire};
use roam_protocol::messages::{
    self, ClientMessage, Hello, ServerMessage, Welcome, WorldNews, close,
};

use crate::color_cache::{ColorCache, Keep};
use crate::conversation::{Joining, welcome_of};
use crate::supervisor::End;

/// A client endpoint for `addr`'s address family that accepts only the certificate with
/// SHA-256 `fingerprint`: one per session, reused by its reconnections (one UDP socket
/// however often it connects again).
pub fn endpoint(addr: SocketAddr, fingerprint: [u8; 32]) -> Result<quinn::Endpoint> {
    endpoint_for(&[addr], fingerprint)
}

/// As [`endpoint`], for every address of `addrs`: IPv4 when they all are, else IPv6
/// (which reaches IPv4 addresses too, mapped).
pub fn endpoint_for(addrs: &[SocketAddr], fingerprint: [u8; 32]) -> Result<quinn::Endpoint> {
    let bind: SocketAddr = if addrs.iter().all(SocketAddr::is_ipv4) {
        "0.0.0.0:0".parse().expect("a valid address")
    } else {
        "[::]:0".parse().expect("a valid address")
    };
    let mut endpoint = quinn::Endpoint::client(bind).context("opening a UDP socket")?;
    endpoint.set_default_client_config(tls::client_config(fingerprint)?);
    Ok(endpoint)
}

/// Connects to `addr`, accepting only the certificate with SHA-256 `fingerprint`.
pub async fn connect(
    addr: SocketAddr,
    fingerprint: [u8; 32],
) -> Result<(quinn::Endpoint, quinn::Connection)> {
    let endpoint = endpoint(addr, fingerprint)?;
    let conn = endpoint
        .connect(addr, "roam")
        .with_context(|| format!("connecting to {addr}"))?
        .await
        .with_context(|| format!("connecting to {addr}"))?;
    Ok((endpoint, conn))
}

/// How a connection ended: `lost` when it is worth connecting again (the path or the
/// server's process went away: an idle timeout, a reset, a transport error); not when the
/// server closed it on purpose (a goodbye, a refusal, shutting down), the viewer closed it,
/// or the server's certificate is not the one pinned.
pub fn ending(e: &quinn::ConnectionError) -> (bool, String) {
    use quinn::ConnectionError as E;
    match e {
        E::ApplicationClosed(c) => (
            false,
            format!(
                "the server closed the connection: {}",
                String::from_utf8_lossy(&c.reason)
            ),
        ),
        // A TLS alert: the certificate is not the pinned one (or the handshake failed).
        E::TransportError(t) if (0x100..0x200).contains(&u64::from(t.code)) => {
            (false, format!("the connection ended: {e}"))
        }
        E::TimedOut | E::Reset | E::TransportError(_) | E::ConnectionClosed(_) => {
            (true, format!("the connection was lost: {e}"))
        }
        E::LocallyClosed | E::VersionMismatch | E::CidsExhausted => {
            (false, format!("the connection ended: {e}"))
        }
    }
}

/// How a connection ended, for the supervisor: the server shutting down (its close code
/// says so), lost, or final ([`ending`]).
pub fn end_of(e: &quinn::ConnectionError) -> End {
    if let quinn::ConnectionError::ApplicationClosed(c) = e
        && c.error_code == close::SHUTDOWN.into()
    {
        return End::Shutdown(ending(e).1);
    }
    match ending(e) {
        (true, why) => End::Lost { why, silent: false },
        (false, why) => End::Final(why),
    }
}

/// Why a join failed, and whether trying again may help.
#[derive(Debug)]
pub struct JoinError {
    /// The connection was lost (or a step timed out): another attempt may succeed.
    pub lost: bool,
    pub message: String,
}

impl JoinError {
    /// A failure that another attempt cannot mend (a refusal, a malformed welcome).
    pub fn fatal(message: String) -> JoinError {
        JoinError {
            lost: false,
            message,
        }
    }

    /// A failure another attempt may not meet (the path or the server went away).
    pub fn lost(message: String) -> JoinError {
        JoinError {
            lost: true,
            message,
        }
    }

    /// A failure on `conn`: lost when the connection itself was lost meanwhile.
    fn on(conn: &quinn::Connection, message: String) -> JoinError {
        match conn.close_reason() {
            Some(e) if ending(&e).0 => JoinError::lost(message),
            _ => JoinError::fatal(message),
        }
    }
}

impl std::fmt::Display for JoinError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

/// A connection that has joined: its control stream, the welcome, the colour cache
/// holding (at least) the coarsest tile, and an edge's news of its world that came
/// meanwhile.
pub struct Joined {
    pub conn: quinn::Connection,
    pub send: quinn::SendStream,
    pub recv: quinn::RecvStream,
    pub welcome: Welcome,
    pub colors: ColorCache,
    pub news: Vec<WorldNews>,
}

/// Says `hello` on `conn`, reads the welcome and the colour messages up to the coarsest
/// tile, kept as `keep` says.
pub async fn hello(conn: quinn::Connection, hello: Hello, keep: Keep) -> Result<Joined, JoinError> {
    let asked = hello.color_window;
    let (mut send, mut recv) = conn
        .open_bi()
        .await
        .map_err(|e| JoinError::on(&conn, format!("opening the control stream: {e}")))?;
    wire::write(&mut send, &ClientMessage::Hello(hello))
        .await
        .map_err(|e| JoinError::on(&conn, format!("sending the hello: {e}")))?;
    let welcome = match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await {
        Ok(msg) => welcome_of(msg).map_err(|e| JoinError::fatal(e.to_string()))?,
        Err(e) => {
            return Err(match conn.close_reason() {
                Some(why) => JoinError::on(
                    &conn,
                    format!("the server closed the connection: {why} ({e})"),
                ),
                None => JoinError::fatal(format!("reading the welcome: {e}")),
            });
        }
    };
    let (colors, news) = coarsest(&mut recv, &welcome, asked, keep)
        .await
        .map_err(|e| JoinError::on(&conn, format!("{e:#}")))?;
    Ok(Joined {
        conn,
        send,
        recv,
        welcome,
        colors,
        news,
    })
}

/// Reads the colour messages that follow the welcome until the coarsest level's tile is
/// resident ([`Joining`]), and the news of the world among them.
async fn coarsest(
    recv: &mut quinn::RecvStream,
    welcome: &Welcome,
    asked: u8,
    keep: Keep,
) -> Result<(ColorCache, Vec<WorldNews>)> {
    let mut joining = Joining::new(welcome, asked, keep)?;
    loop {
        let msg = wire::read::<ServerMessage>(recv, messages::MAX_MESSAGE).await?;
        if let Some(cache) = joining.apply(&msg)? {
            return Ok((cache, joining.take_news()));
        }
    }
}
