//! Joining a server, once: the QUIC handshake (pinning the server's certificate), the
//! hello, the welcome and the colour map (its announced sizes checked against the grid
//! before anything is allocated); whether a reconnection found the same terrain; and what a
//! connection's end means: **lost** (timed out, reset, a transport error: worth
//! reconnecting) or **final** (the server closed it, refused the viewer, or broke the
//! protocol). No clock here: the session ([`crate::session`]) bounds each step in time.

use std::net::SocketAddr;

use anyhow::{Context, Result};
use roam_link::{tls, wire};
use roam_protocol::messages::{self, ClientMessage, Hello, Reason, ServerMessage, Welcome};

/// A client endpoint for `addr`'s address family that accepts only the certificate with
/// SHA-256 `fingerprint`: one per session, reused by its reconnections (one UDP socket
/// however often it connects again).
pub fn endpoint(addr: SocketAddr, fingerprint: [u8; 32]) -> Result<quinn::Endpoint> {
    let bind: SocketAddr = if addr.is_ipv4() {
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

/// Why a connection ended or was refused, in words.
pub fn describe(reason: &Reason) -> String {
    match reason {
        Reason::WrongToken => "wrong token".into(),
        Reason::Version { server } => format!("the server speaks protocol version {server}"),
        Reason::Shutdown => "the server is shutting down".into(),
        Reason::Quit => "quit".into(),
        Reason::Protocol(s) | Reason::Unavailable(s) => s.clone(),
        Reason::Full { viewers } => format!("the server is full ({viewers} viewers)"),
    }
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

/// A connection that has joined: its control stream, the welcome and the colour map.
pub struct Joined {
    pub conn: quinn::Connection,
    pub send: quinn::SendStream,
    pub recv: quinn::RecvStream,
    pub welcome: Welcome,
    /// The decoded colour map (RGB texels).
    pub colors: Vec<u8>,
}

/// Says `hello` on `conn` and reads the welcome and the colour map.
pub async fn hello(conn: quinn::Connection, hello: Hello) -> Result<Joined, JoinError> {
    let (mut send, mut recv) = conn
        .open_bi()
        .await
        .map_err(|e| JoinError::on(&conn, format!("opening the control stream: {e}")))?;
    wire::write(&mut send, &ClientMessage::Hello(hello))
        .await
        .map_err(|e| JoinError::on(&conn, format!("sending the hello: {e}")))?;
    let welcome = match wire::read::<ServerMessage>(&mut recv, messages::MAX_MESSAGE).await {
        Ok(ServerMessage::Welcome(w)) => w,
        Ok(ServerMessage::Refused(reason)) => {
            return Err(JoinError::fatal(format!("refused: {}", describe(&reason))));
        }
        Ok(other) => {
            return Err(JoinError::fatal(format!(
                "expected a welcome, got {}",
                name(&other)
            )));
        }
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
    let colors = color_map(&mut recv, &welcome)
        .await
        .map_err(|e| JoinError::on(&conn, format!("{e:#}")))?;
    Ok(Joined {
        conn,
        send,
        recv,
        welcome,
        colors,
    })
}

/// A server message, named (a colour-map chunk's bytes are not spelled out).
pub fn name(m: &ServerMessage) -> String {
    match m {
        ServerMessage::Welcome(_) => "a welcome".into(),
        ServerMessage::ColorMap { offset, data } => {
            format!("a colour-map chunk ({} bytes at {offset})", data.len())
        }
        ServerMessage::Refused(r) => format!("Refused({r:?})"),
        ServerMessage::Bye(r) => format!("Bye({r:?})"),
    }
}

/// The terrain a viewer draws, from its first welcome and colour map: what every
/// reconnection must find again.
#[derive(Clone, Debug, PartialEq)]
pub struct TerrainId {
    levels: u8,
    h_scale: f64,
    v_scale: f64,
    color_cells: u32,
    /// SHA-256 of the decoded colour map.
    colors: Vec<u8>,
}

impl TerrainId {
    pub fn of(welcome: &Welcome, colors: &[u8]) -> TerrainId {
        TerrainId {
            levels: welcome.levels,
            h_scale: welcome.h_scale,
            v_scale: welcome.v_scale,
            color_cells: welcome.color_cells,
            colors: ring::digest::digest(&ring::digest::SHA256, colors)
                .as_ref()
                .to_vec(),
        }
    }

    /// What differs from `self` in `other`, in words; `None` when nothing does.
    pub fn differences(&self, other: &TerrainId) -> Option<String> {
        let mut out = Vec::new();
        if self.levels != other.levels {
            out.push(format!(
                "a grid of 2^{} + 1, was 2^{} + 1",
                other.levels, self.levels
            ));
        }
        if (self.h_scale, self.v_scale) != (other.h_scale, other.v_scale) {
            out.push(format!(
                "scales {} × {}, were {} × {}",
                other.h_scale, other.v_scale, self.h_scale, self.v_scale
            ));
        }
        if self.color_cells != other.color_cells || self.colors != other.colors {
            out.push("another colour map".into());
        }
        (!out.is_empty()).then(|| out.join("; "))
    }
}

/// Receives the colour map that follows the welcome, after checking its announced sizes
/// against the grid (nothing is allocated before).
async fn color_map(recv: &mut quinn::RecvStream, welcome: &Welcome) -> Result<Vec<u8>> {
    if welcome.levels > 13 {
        anyhow::bail!(
            "the server's grid is 2^{} + 1: more than this viewer holds (2^13 + 1)",
            welcome.levels
        );
    }
    let cells = 1u64 << welcome.levels;
    let most = roam_protocol::colormap::max_len(cells as u32) as u64;
    if u64::from(welcome.color_cells) != cells || u64::from(welcome.color_bytes) > most {
        anyhow::bail!(
            "the server's colour map is {} bytes of {} cells a side, expected {cells} cells \
             in at most {most} bytes",
            welcome.color_bytes,
            welcome.color_cells,
        );
    }
    // Grown as chunks come, in order, not allocated at the size claimed.
    let size = welcome.color_bytes as usize;
    let mut packed = Vec::new();
    while packed.len() < size {
        match wire::read::<ServerMessage>(recv, messages::MAX_MESSAGE).await? {
            ServerMessage::ColorMap { offset, data } => {
                if offset as usize != packed.len() {
                    anyhow::bail!(
                        "a colour-map chunk at byte {offset}, expected the next at {}",
                        packed.len()
                    );
                }
                if data.is_empty() || packed.len() + data.len() > size {
                    anyhow::bail!("a colour-map chunk past the end (or empty)");
                }
                packed.extend_from_slice(&data);
            }
            other => anyhow::bail!("expected the colour map, got {}", name(&other)),
        }
    }
    let mut color = Vec::new();
    roam_protocol::colormap::decode(welcome.color_cells, &packed, &mut color)
        .map_err(|e| anyhow::anyhow!("the server's colour map: {e}"))?;
    Ok(color)
}
