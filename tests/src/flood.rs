//! A flood of junk connections, as an unauthenticated attacker would open them: some
//! finish the QUIC handshake and then send nothing, some open the control stream and stall
//! inside their hello (a length that promises more bytes than ever come). Each waits for
//! the server to close it and says how it ended. Shared by the admission test
//! (`tests/tests/it/admission.rs`) and the `roam-flood` binary, which prints the figures as
//! JSON against a server in another process.
//!
//! The connections come from one client endpoint (one UDP port, as one attacker's
//! machine), as fast as `in_flight` allows: no pacing, so the rate is whatever the two
//! ends can take.

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use roam_link::tls;

/// How many junk connections of each kind.
#[derive(Clone, Copy, Debug)]
pub struct Flood {
    /// Connections that finish the handshake and send nothing.
    pub idle: usize,
    /// Connections that open the control stream and stall inside their hello.
    pub stalled: usize,
    /// Connections being opened at once (handshakes in flight).
    pub in_flight: usize,
    /// How long a junk connection waits for the server to close it before it counts as
    /// never closed (a bound for the test, well past the server's deadline).
    pub patience: Duration,
}

/// How the junk connections ended.
#[derive(Clone, Debug, Default, PartialEq, Eq, serde::Serialize)]
pub struct Outcome {
    /// Per connection whose handshake finished, how it ended and the milliseconds from
    /// the handshake to that end.
    #[serde(skip)]
    pub closed_after_ms: Vec<(Ending, u64)>,
    /// Opened (handshake attempted).
    pub opened: usize,
    /// The handshake completed.
    pub handshaken: usize,
    /// Closed by the server with an application code (a deadline, an eviction, a
    /// protocol error), after or during the handshake.
    pub closed_by_server: usize,
    /// Refused or reset during the handshake (the server dropped it unfinished).
    pub refused: usize,
    /// Timed out: the server never closed it within `patience`.
    pub never_closed: usize,
    /// Anything else (a local error).
    pub other: usize,
}

/// How one junk connection ended, as its side of QUIC saw it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Ending {
    /// The server's application close: [`Outcome::closed_by_server`].
    ClosedByServer,
    /// A transport close (the server dropped it unfinished): [`Outcome::refused`].
    Refused,
    /// A stateless reset (the server had already forgotten it: a close this side never
    /// heard): also [`Outcome::refused`].
    Reset,
    /// Its idle timeout or our patience ran out: [`Outcome::never_closed`].
    NeverClosed,
    /// [`Outcome::other`].
    Other,
}

impl Ending {
    /// The name of its count in [`Outcome`].
    pub fn name(self) -> &'static str {
        match self {
            Ending::ClosedByServer => "closed_by_server",
            Ending::Refused => "refused",
            Ending::Reset => "reset",
            Ending::NeverClosed => "never_closed",
            Ending::Other => "other",
        }
    }
}

impl Outcome {
    fn ended(&mut self, e: Ending) {
        let n = match e {
            Ending::ClosedByServer => &mut self.closed_by_server,
            Ending::Refused | Ending::Reset => &mut self.refused,
            Ending::NeverClosed => &mut self.never_closed,
            Ending::Other => &mut self.other,
        };
        *n += 1;
    }

    fn add(&mut self, o: &Outcome) {
        self.opened += o.opened;
        self.handshaken += o.handshaken;
        self.closed_by_server += o.closed_by_server;
        self.refused += o.refused;
        self.never_closed += o.never_closed;
        self.other += o.other;
        self.closed_after_ms.extend_from_slice(&o.closed_after_ms);
    }
}

/// Runs the flood against the server at `addr` (pinned to `fingerprint`) to its end: every
/// connection opened, and closed by the server or given up on.
///
/// `opened`, if given, counts the connections started so far (to start something else in
/// the middle of the flood).
pub async fn run(
    addr: SocketAddr,
    fingerprint: [u8; 32],
    flood: Flood,
    opened: Option<&tokio::sync::watch::Sender<usize>>,
) -> Result<Outcome> {
    let mut endpoint = quinn::Endpoint::client("127.0.0.1:0".parse().expect("an address"))
        .context("opening the flood's UDP socket")?;
    endpoint.set_default_client_config(tls::client_config(fingerprint)?);
    let gate = Arc::new(tokio::sync::Semaphore::new(flood.in_flight.max(1)));
    let mut tasks = tokio::task::JoinSet::new();
    // The two kinds alternate while both last.
    let both = 2 * flood.idle.min(flood.stalled);
    for k in 0..flood.idle + flood.stalled {
        let stall = if k < both {
            k % 2 == 1
        } else {
            flood.stalled > flood.idle
        };
        if let Some(opened) = opened {
            opened.send_replace(k);
        }
        let permit = gate.clone().acquire_owned().await.expect("never closed");
        let connecting = endpoint.connect(addr, "roam");
        let patience = flood.patience;
        tasks.spawn(async move {
            let mut o = Outcome {
                opened: 1,
                ..Outcome::default()
            };
            let conn = match connecting {
                Ok(c) => tokio::time::timeout(patience, c).await,
                Err(_) => {
                    o.ended(Ending::Other);
                    return o;
                }
            };
            drop(permit); // the next may start its handshake
            let conn = match conn {
                Ok(Ok(conn)) => conn,
                Ok(Err(e)) => {
                    o.ended(ending(&e));
                    return o;
                }
                Err(_) => {
                    o.ended(Ending::NeverClosed);
                    return o;
                }
            };
            o.handshaken = 1;
            let handshaken = std::time::Instant::now();
            // Keep the stream alive until the connection ends.
            let mut _stream = None;
            if stall && let Ok((mut send, _recv)) = conn.open_bi().await {
                // A hello's length saying 100 bytes, and 10 of them.
                let mut partial = 100u32.to_le_bytes().to_vec();
                partial.extend_from_slice(&[0u8; 10]);
                let _ = send.write_all(&partial).await;
                _stream = Some(send);
            }
            let end = match tokio::time::timeout(patience, conn.closed()).await {
                Ok(e) => ending(&e),
                Err(_) => Ending::NeverClosed,
            };
            o.ended(end);
            o.closed_after_ms = vec![(end, handshaken.elapsed().as_millis() as u64)];
            o
        });
    }
    let mut total = Outcome::default();
    while let Some(o) = tasks.join_next().await {
        total.add(&o.context("a junk connection's task")?);
    }
    endpoint.close(0u32.into(), b"done");
    Ok(total)
}

fn ending(e: &quinn::ConnectionError) -> Ending {
    use quinn::ConnectionError as E;
    match e {
        E::ApplicationClosed(_) => Ending::ClosedByServer,
        E::ConnectionClosed(_) => Ending::Refused,
        E::Reset => Ending::Reset,
        E::TimedOut => Ending::NeverClosed,
        _ => Ending::Other,
    }
}

/// The resident memory of process `pid` (`"self"` for this one) now (`"VmRSS"`) or at its
/// peak (`"VmHWM"`), bytes, from `/proc/PID/status`.
pub fn memory(pid: &str, field: &str) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status
        .lines()
        .find(|l| l.strip_prefix(field).is_some_and(|r| r.starts_with(':')))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}
