//! `world` and `edge`: one world served by many machines over NATS
//! (`roam_server::net::bus`). `world` runs the 100 Hz world and records it; `edge` is
//! `serve` whose world is the one on the bus (`super::net::serve_on`).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, Result};
use clap::Args;
use roam_server::net::bus::world::{WorldOptions, WorldServer};
use roam_server::net::bus::{BusOptions, BusSecret};
use roam_server::net::{self};
use roam_server::sim::session::{self, RecordOptions};

use super::net::{Edge, ServeArgs};

/// Which world, on which NATS.
#[derive(Args, Clone)]
pub(crate) struct BusArgs {
    /// The NATS server: `nats://HOST:PORT`, or `tls://HOST:PORT` to require TLS; several
    /// comma-separated.
    #[arg(long, value_name = "URL")]
    pub nats: String,
    /// The world's name (its NATS subjects are `roam.NAME.…`; worlds may share one NATS).
    #[arg(long, value_name = "NAME", default_value = roam_protocol::bus::DEFAULT_WORLD)]
    pub world: String,
    /// NATS credentials: a `.creds` file (JWT and nkey seed), or a file holding a token.
    #[arg(long, value_name = "FILE")]
    pub nats_creds: Option<PathBuf>,
    /// CA certificates (PEM) to trust for NATS's TLS certificate, for a NATS whose
    /// certificate is self-signed or from a private CA; given, the system's CAs are not
    /// used for NATS.
    #[arg(long, value_name = "FILE")]
    pub nats_ca: Option<PathBuf>,
    /// The cluster's secret, shared by the world and its edges (make one with
    /// `roam-server bus-secret FILE`): every bus message is sealed with it, so nobody else
    /// on the NATS can steer, free, hold, kick or fill anything, or read a ticket.
    #[arg(long, value_name = "FILE")]
    pub bus_secret: Option<PathBuf>,
    /// Run without the cluster's secret: plain bus messages, which anyone who can publish
    /// on the NATS can forge (steer or free any vehicle) and anyone who can subscribe can
    /// read (tickets). Only on a NATS nobody else can reach.
    #[arg(long, conflicts_with = "bus_secret")]
    pub insecure_bus: bool,
}

impl BusArgs {
    pub(crate) fn options(&self, name: &str) -> Result<BusOptions> {
        roam_protocol::bus::Subjects::of(&self.world).context("--world")?;
        let secret = match &self.bus_secret {
            Some(file) => {
                warn_if_others_read(file);
                Some(BusSecret::read(file)?)
            }
            None if self.insecure_bus => {
                tracing::warn!(
                    "--insecure-bus: bus messages are not sealed; anyone who can publish on \
                     the NATS can steer or free any vehicle"
                );
                None
            }
            None => anyhow::bail!(
                "the cluster's secret is needed: --bus-secret FILE (make one with \
                 `roam-server bus-secret FILE` and copy it to the world and every edge), or \
                 --insecure-bus to run without it"
            ),
        };
        Ok(BusOptions {
            url: self.nats.clone(),
            world: self.world.clone(),
            creds: self.nats_creds.clone(),
            ca: self.nats_ca.clone(),
            name: name.into(),
            secret,
        })
    }
}

/// Says so when the secret's file can be read by others than its owner.
fn warn_if_others_read(file: &std::path::Path) {
    use std::os::unix::fs::PermissionsExt;
    if let Ok(meta) = std::fs::metadata(file)
        && meta.permissions().mode() & 0o077 != 0
    {
        tracing::warn!(
            "the bus secret {} can be read by others than its owner (mode {:o}): chmod 600 it",
            file.display(),
            meta.permissions().mode() & 0o777
        );
    }
}

#[derive(Args)]
pub(crate) struct BusSecretArgs {
    /// Where to write it (refused if the file exists).
    pub file: PathBuf,
}

/// `bus-secret FILE`: a new random cluster secret (64 hex digits), readable by its owner
/// only, for `world`, `edge` and `bus-load`'s `--bus-secret`.
pub(crate) fn bus_secret(args: BusSecretArgs) -> Result<()> {
    use std::io::Write;
    use std::os::unix::fs::OpenOptionsExt;
    let secret = BusSecret::random();
    let mut file = std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .mode(0o600)
        .open(&args.file)
        .with_context(|| {
            format!(
                "creating {} (an existing file is never replaced)",
                args.file.display()
            )
        })?;
    file.write_all(secret.as_bytes())
        .and_then(|()| file.write_all(b"\n"))
        .and_then(|()| file.sync_all())
        .with_context(|| format!("writing {}", args.file.display()))?;
    say!(
        "wrote a new bus secret to {}: copy it to the world's and every edge's machine and give it as --bus-secret {}",
        args.file.display(),
        args.file.display()
    );
    Ok(())
}

#[derive(Args)]
pub(crate) struct WorldArgs {
    /// Data set directory (each edge serves the same data set).
    pub dir: PathBuf,
    #[command(flatten)]
    pub bus: BusArgs,
    /// Where the state is kept (the recordings, unless --record-dir).
    #[arg(long, default_value = "roam-state")]
    pub state_dir: PathBuf,
    /// Where sessions are recorded (default: `recordings` in the state directory).
    #[arg(long)]
    pub record_dir: Option<PathBuf>,
    /// A recording file is closed and the next begun before it grows past this many bytes.
    #[arg(long, default_value_t = session::DEFAULT_MAX_BYTES,
          value_parser = clap::value_parser!(u64).range(session::MIN_MAX_BYTES..=session::MAX_MAX_BYTES))]
    pub record_max_bytes: u64,
    /// Seconds a driver's vehicle is held after its connection drops, for it to come back
    /// (through any edge).
    #[arg(long, default_value_t = net::HOLD.as_secs_f64())]
    pub hold: f64,
    /// Vehicles at most, held ones included; a join past it frees the oldest held one, or
    /// is refused.
    #[arg(long, default_value_t = 1024)]
    pub max_vehicles: usize,
    /// Serve this recording to the edges instead of a live world, from its start at 1×:
    /// every edge's viewers watch it as spectators, the viewer holding an edge's controls
    /// (its first) pauses, speeds and seeks it for all; nothing is recorded. A recording of
    /// another data set is refused.
    #[arg(long, value_name = "FILE")]
    pub replay: Option<PathBuf>,
    /// With --replay: the recording is still being written: follow it as it grows.
    #[arg(long, requires = "replay")]
    pub follow: bool,
}

#[derive(Args)]
pub(crate) struct EdgeArgs {
    #[command(flatten)]
    pub serve: ServeArgs,
    #[command(flatten)]
    pub bus: BusArgs,
    /// Seconds to wait for the world to answer when starting.
    #[arg(long, default_value_t = 30.0)]
    pub world_wait: f64,
    /// The host name or address viewers reach this edge at, as the world's other edges tell
    /// their viewers (default: the --listen address, or this machine's LAN address when
    /// that is unspecified).
    #[arg(long, value_name = "HOST")]
    pub advertise: Option<String>,
}

pub(crate) fn edge(args: EdgeArgs) -> Result<()> {
    anyhow::ensure!(
        args.serve.record_dir.is_none(),
        "--record-dir: an edge records nothing (the world does: give it to `roam-server world`)"
    );
    anyhow::ensure!(
        args.world_wait.is_finite() && (0.0..=86_400.0).contains(&args.world_wait),
        "--world-wait {}: expected 0 to 86400 seconds",
        args.world_wait
    );
    if let Some(host) = &args.advertise {
        // With a port and a URL around it, within the bus's limit on an address.
        anyhow::ensure!(
            !host.is_empty() && host.len() <= roam_protocol::bus::MAX_ADDRESS - 128,
            "--advertise: expected a host name or address of 1 to {} bytes",
            roam_protocol::bus::MAX_ADDRESS - 128
        );
    }
    let edge = Edge {
        bus: args.bus.options("roam-server edge")?,
        wait: Duration::from_secs_f64(args.world_wait),
        advertise: args.advertise,
    };
    super::net::serve_on(args.serve, Some(edge))
}

pub(crate) fn world(args: WorldArgs) -> Result<()> {
    let bus = args.bus.options("roam-server world")?;
    anyhow::ensure!(
        args.hold.is_finite() && (0.0..=86_400.0).contains(&args.hold),
        "--hold {}: expected 0 to 86400 seconds",
        args.hold
    );
    anyhow::ensure!(
        args.max_vehicles >= 1,
        "--max-vehicles: expected at least 1"
    );
    let served = super::served::open_served(&args.dir)?;
    let hash = super::served::data_hash(&args.dir, &served.terrain, &served.report)?;
    let terrain = Arc::new(served.terrain);
    // A replay records nothing.
    let replay = match &args.replay {
        Some(file) => Some(super::served::open_replay(
            file,
            (&None, args.follow),
            &terrain,
            &hash,
        )?),
        None => None,
    };
    let recording = match replay {
        None => Some(super::served::record_files(
            &args.state_dir,
            args.record_dir.as_deref(),
        )?),
        Some(_) => None,
    };
    let made = recording.as_ref().map(|(_, files)| files.made());
    let (record_dir, record) = match recording {
        Some((dir, files)) => (
            Some(dir),
            Some(RecordOptions::new(files, args.record_max_bytes).with_terrain_hash(hash)),
        ),
        None => (None, None),
    };
    let runtime = tokio::runtime::Runtime::new().context("starting the async runtime")?;
    runtime.block_on(async {
        let world = WorldServer::start(
            terrain,
            hash,
            WorldOptions {
                record,
                hold: Duration::from_secs_f64(args.hold),
                max_vehicles: args.max_vehicles,
                replay,
            },
            &bus,
        )
        .await?;
        say!("world {:?} on NATS at {}", bus.world, bus.url);
        say!("data set {}", roam_link::tls::hex(&hash));
        match &made {
            Some(made) => {
                let first = made.list().first().map(|p| p.display().to_string());
                say!("recording to {}", first.as_deref().unwrap_or("nothing"));
            }
            None => say!("serving a recording: its viewers watch it"),
        }
        let secret = match &args.bus.bus_secret {
            Some(file) => format!("--bus-secret {}", file.display()),
            None => "--insecure-bus".into(),
        };
        say!(
            "serve it with: roam-server edge {} --nats {} --world {} {secret}",
            args.dir.display(),
            bus.url,
            bus.world
        );
        tokio::signal::ctrl_c()
            .await
            .context("waiting for Ctrl-C")?;
        say!("shutting down");
        let world = world.shutdown().await?;
        match &record_dir {
            Some(record_dir) => say!(
                "stopped at tick {}; each recording file in {} replays with: roam-server replay FILE --data {}",
                world.tick(),
                record_dir.display(),
                args.dir.display()
            ),
            None => say!("stopped (the recording at tick {})", world.tick()),
        }
        Ok(())
    })
}
