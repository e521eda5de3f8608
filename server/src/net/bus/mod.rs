//! One world, many machines: the world ([`world::WorldServer`], `roam-server world`) and
//! its edges ([`edge::Remote`], `roam-server edge`) over NATS. The messages and subjects
//! are [`roam_protocol::bus`]'s; this module owns the NATS client (`async-nats`).
//!
//! ```text
//! viewer ─► edge: viewer tasks ─► edge thread ─keys─► NATS ─► world: keys task ─┐
//!           handshake ──────────── ask (join, resume) ─►       ask task ───────┤
//!           viewer tasks ◄── watch ◄── snapshot task ◄─ NATS ◄── publisher ◄── world thread (100 Hz)
//! ```
//!
//! The seam is the one `serve` already has: the world thread takes a closed set of events
//! ([`crate::sim::world_core::Event`]) and gives a snapshot each tick; a viewer task needs
//! only snapshots and the terrain. `serve` keeps its in-process channel and `watch`; an
//! edge puts NATS between the two, and the drivers' tickets live with the world, so a
//! driver may come back through any edge.

pub mod asker;
mod drivers;
pub mod edge;
pub mod seal;
pub mod voice;
pub mod window;
pub mod world;

pub use seal::{BusSecret, Refused};

use std::path::PathBuf;
use std::sync::Arc;

use roam_protocol::bus::{self as wire, Subjects};

use crate::sim::physics::VehicleState;
use crate::sim::world::Vehicle;
use crate::sim::world_core::Snapshot;

/// The refusal of a request for another world process (the edge then asks who the world
/// is now: [`edge::Remote::join`]).
pub const OTHER_WORLD: &str = "the request is for another world process: the world restarted";

/// Where the world's NATS is, and which world.
#[derive(Clone, Debug)]
pub struct BusOptions {
    /// `nats://host:port` (or `tls://…`: TLS required), or several, comma-separated.
    pub url: String,
    /// The world's name: its subjects are `roam.<world>.…`.
    pub world: String,
    /// A NATS credentials file (`.creds`: a JWT and its nkey seed), or a file holding a
    /// token (one line).
    pub creds: Option<PathBuf>,
    /// A PEM file of CA certificates that NATS's TLS certificate must chain to (a private
    /// or self-signed CA). Given, these are the only ones trusted for NATS (async-nats
    /// then leaves out the system's); else the system's are.
    pub ca: Option<PathBuf>,
    /// What this process calls itself to the NATS server (its connection name).
    pub name: String,
    /// The cluster's secret (`--bus-secret FILE`): every message is sealed with it
    /// ([`seal`]). `None` only when told `--insecure-bus`: plain messages, which anyone
    /// on the NATS can forge, read and replay.
    pub secret: Option<BusSecret>,
}

/// Why the bus could not be used.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    #[error("world name: {0}")]
    Name(#[from] wire::NameError),
    #[error("reading the NATS credentials {file}: {error}")]
    Creds {
        file: PathBuf,
        error: std::io::Error,
    },
    #[error("the CA certificates for NATS's TLS, {file}: {error}")]
    Ca {
        file: PathBuf,
        error: std::io::Error,
    },
    #[error("connecting to NATS at {url}: {error}")]
    Connect { url: String, error: String },
    #[error("TLS to NATS at {url} failed: {error} ({})", tls_hint(.ca.as_deref()))]
    Tls {
        url: String,
        error: String,
        /// The CA file trusted ([`BusOptions::ca`]), if one was.
        ca: Option<PathBuf>,
    },
    #[error("NATS ({what}): {error}")]
    Nats { what: &'static str, error: String },
    #[error(
        "the world {world:?} serves the data set {world_data}, this edge has {edge_data} \
         ({dir}): serve the same data set on both"
    )]
    DataSet {
        world: String,
        world_data: String,
        edge_data: String,
        dir: String,
    },
    #[error(
        "the world {world:?} did not answer on NATS at {url} (is `roam-server world` running?)"
    )]
    NoWorld { world: String, url: String },
    #[error("the world's answer: {0}")]
    Answer(String),
    #[error("the world thread: {0}")]
    World(std::io::Error),
    #[error("the world thread panicked")]
    WorldPanicked,
}

/// What to do about a TLS failure, with the CA file trusted or without one.
fn tls_hint(ca: Option<&std::path::Path>) -> String {
    match ca {
        None => "if NATS's certificate is from a private or self-signed CA, give that CA's \
                 certificate with --nats-ca FILE"
            .into(),
        Some(file) => format!(
            "NATS's certificate must be signed by one in --nats-ca {}, or be one of them and \
             not itself a CA (basicConstraints CA:FALSE)",
            file.display()
        ),
    }
}

/// A random name for this process (an edge's, a world's), as the bus knows it (from the
/// system's random source: it names the key the process seals with).
pub fn random_id() -> u64 {
    let t = crate::net::tickets::random_ticket();
    u64::from_le_bytes([t[0], t[1], t[2], t[3], t[4], t[5], t[6], t[7]])
}

/// Messages from the bus that did not decode, counted; logged at the first, second,
/// fourth… so a flood cannot fill the log.
pub(crate) struct Malformed {
    what: &'static str,
    count: u64,
}

impl Malformed {
    pub(crate) fn new(what: &'static str) -> Malformed {
        Malformed { what, count: 0 }
    }

    /// A sealed message heard by a process without the secret (`--insecure-bus`).
    pub(crate) fn note_sealed(&mut self) {
        self.count += 1;
        if self.count.is_power_of_two() {
            tracing::warn!(
                malformed = self.count,
                "a sealed {} on the bus, but this process runs --insecure-bus: give it the \
                 cluster's --bus-secret FILE",
                self.what
            );
        }
    }

    pub(crate) fn note(&mut self, error: &roam_protocol::messages::DecodeError) {
        self.count += 1;
        if self.count.is_power_of_two() {
            tracing::warn!(
                malformed = self.count,
                "a malformed {} on the bus: {error}",
                self.what
            );
        }
    }
}

impl BusOptions {
    pub fn subjects(&self) -> Result<Subjects, BusError> {
        Ok(Subjects::of(&self.world)?)
    }

    /// The world's key (from the secret and the world's name), or `None` when insecure.
    pub fn key(&self) -> Option<seal::BusKey> {
        self.secret.as_ref().map(|s| s.key(&self.world))
    }

    /// Connects to NATS: TLS when the URL (or the server) asks for it, trusting
    /// [`Self::ca`]'s certificates if given, the credentials or token from
    /// [`Self::creds`], reconnecting for ever when the server goes away (the client keeps
    /// a bounded buffer meanwhile: a publish waits, nothing grows).
    pub async fn connect(&self) -> Result<async_nats::Client, BusError> {
        let refused = |e: async_nats::ConnectError| {
            let url = self.url.clone();
            match tls_failure(&e) {
                Some(error) => BusError::Tls {
                    url,
                    error,
                    ca: self.ca.clone(),
                },
                None => BusError::Connect {
                    url,
                    error: e.to_string(),
                },
            }
        };
        // Tried once first: credentials or TLS the server refuses are said now, rather
        // than retried for ever in the background.
        match self.options().await?.connect(self.url.as_str()).await {
            Ok(client) => return Ok(client),
            Err(e) if refusal(&e) || tls_failure(&e).is_some() => return Err(refused(e)),
            Err(e) => tracing::warn!("NATS at {} not reached yet ({e}); waiting for it", self.url),
        }
        // `retry_on_initial_connect` makes this return at once; the first connection is
        // made in the background (a world started before its NATS waits for it).
        self.options()
            .await?
            .retry_on_initial_connect()
            .connect(self.url.as_str())
            .await
            .map_err(refused)
    }

    async fn options(&self) -> Result<async_nats::ConnectOptions, BusError> {
        let mut options = async_nats::ConnectOptions::new()
            .name(&self.name)
            .max_reconnects(None)
            // The world's snapshots come 100 a second; a subscriber buffers a few seconds.
            .subscription_capacity(1024)
            .require_tls(self.url.split(',').any(|u| u.trim().starts_with("tls://")));
        if let Some(file) = &self.creds {
            options = creds(options, file).await?;
        }
        if let Some(file) = &self.ca {
            check_ca(file)?;
            options = options.add_root_certificates(file.clone());
        }
        Ok(options)
    }
}

/// Whether a first connection failed for a reason trying again will not cure: the server
/// refused the credentials, or TLS, or the URL is not one.
fn refusal(e: &async_nats::ConnectError) -> bool {
    use async_nats::ConnectErrorKind as K;
    matches!(
        e.kind(),
        K::Authentication | K::AuthorizationViolation | K::Tls | K::ServerParse
    )
}

/// What went wrong if a first connection failed in TLS: its setup (`ConnectErrorKind::Tls`),
/// or the handshake (async-nats reports those as I/O errors wrapping rustls' error: a
/// certificate not trusted, a name that does not match). Neither is cured by trying again.
fn tls_failure(e: &async_nats::ConnectError) -> Option<String> {
    use async_nats::ConnectErrorKind as K;
    use std::error::Error as _;
    match e.kind() {
        K::Tls => Some(e.to_string()),
        K::Io => e
            .source()
            .and_then(|s| s.downcast_ref::<std::io::Error>())
            .and_then(|io| io.get_ref())
            .and_then(|inner| inner.downcast_ref::<async_nats::rustls::Error>())
            .map(|tls| tls.to_string()),
        _ => None,
    }
}

/// The `--nats-ca` file is readable and holds at least one PEM certificate (else
/// async-nats would trust none, and every server would be refused as untrusted).
fn check_ca(file: &std::path::Path) -> Result<(), BusError> {
    use async_nats::rustls::pki_types::{CertificateDer, pem::PemObject};
    let err = |error| BusError::Ca {
        file: file.to_owned(),
        error,
    };
    let pem = std::fs::read(file).map_err(err)?;
    let mut certs = 0;
    for cert in CertificateDer::pem_slice_iter(&pem) {
        cert.map_err(|e| err(std::io::Error::new(std::io::ErrorKind::InvalidData, e)))?;
        certs += 1;
    }
    if certs == 0 {
        return Err(err(std::io::Error::new(
            std::io::ErrorKind::InvalidData,
            "no PEM certificate (-----BEGIN CERTIFICATE-----) in it",
        )));
    }
    Ok(())
}

/// A credentials file (it holds `-----BEGIN NATS USER JWT-----`), else a token file.
async fn creds(
    options: async_nats::ConnectOptions,
    file: &std::path::Path,
) -> Result<async_nats::ConnectOptions, BusError> {
    let err = |error| BusError::Creds {
        file: file.to_owned(),
        error,
    };
    let text = std::fs::read_to_string(file).map_err(err)?;
    if text.contains("NATS USER JWT") {
        options.credentials_file(file).await.map_err(err)
    } else {
        let token = text.trim();
        if token.is_empty() || token.contains(char::is_whitespace) {
            return Err(err(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                "expected a NATS credentials file or one line holding a token",
            )));
        }
        Ok(options.token(token.to_owned()))
    }
}

/// A snapshot of world process `world` as it goes on the bus.
pub fn to_wire(s: &Snapshot, world: u64) -> wire::Snapshot {
    to_wire_watched(s, world, None)
}

/// [`to_wire`], with a watched recording's clock (`world --replay`).
pub fn to_wire_watched(s: &Snapshot, world: u64, replay: Option<wire::Replay>) -> wire::Snapshot {
    wire::Snapshot {
        replay,
        world,
        tick: s.tick,
        vehicles: s
            .vehicles
            .iter()
            .map(|v| wire::Vehicle {
                id: v.id,
                x: v.state.x,
                z: v.state.z,
                speed: v.state.speed,
                heading: v.state.heading,
            })
            .collect(),
        applied: s.applied.clone(),
        held: s.held.clone(),
    }
}

/// A snapshot from the bus, as the viewer tasks take it.
pub fn from_wire(s: wire::Snapshot) -> Arc<Snapshot> {
    Arc::new(Snapshot {
        tick: s.tick,
        vehicles: s
            .vehicles
            .into_iter()
            .map(|v| Vehicle {
                id: v.id,
                state: VehicleState {
                    x: v.x,
                    z: v.z,
                    speed: v.speed,
                    heading: v.heading,
                },
            })
            .collect(),
        applied: s.applied,
        held: s.held,
    })
}

/// Encodes a bus message (they are small and bounded: encoding cannot fail).
pub(crate) fn encode<T: serde::Serialize>(msg: &T) -> bytes::Bytes {
    let mut out = Vec::new();
    roam_protocol::messages::encode(msg, &mut out)
        .expect("bus messages have no field bincode refuses");
    out.into()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A snapshot goes over the bus and comes back bit for bit.
    #[test]
    fn snapshots_cross_the_bus_exactly() {
        let snap = Snapshot {
            tick: 77,
            vehicles: vec![Vehicle {
                id: 4,
                state: VehicleState {
                    x: 0.1 + 0.2,
                    z: 1e-300,
                    speed: f64::from_bits(33f64.to_bits() + 1),
                    heading: f64::from_bits(360f64.to_bits() - 1),
                },
            }],
            applied: vec![(4, 12)],
            held: vec![9],
        };
        let bytes = encode(&to_wire(&snap, 5));
        let back: wire::Snapshot =
            roam_protocol::messages::decode(&bytes).expect("a snapshot decodes");
        assert_eq!(*from_wire(back), snap);
    }
}
