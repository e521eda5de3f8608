//! The network shell: the only module that touches QUIC (quinn), an async runtime (tokio) or
//! a clock for pacing. It turns traffic into the world thread's closed set of events
//! ([`crate::sim::world_core::Event`]), and snapshots of the world into frames for each viewer.
//!
//! ```text
//! viewer ──hello/acks/budget (control stream)──► viewer task ──frames (a uni stream each)──► viewer
//!        ──key datagrams──────────────────────► world thread (100 Hz) ──snapshot (latest)──┘
//! ```

pub mod viewer;
pub mod world_loop;

use std::net::SocketAddr;
use std::sync::Arc;

use roam_link::tls;
use tokio::sync::watch;

use crate::Terrain;
use crate::sim::world_core::Snapshot;
use crate::terrain::variance::VarianceTree;
use world_loop::Inbound;

/// How to run a server.
pub struct Options {
    pub listen: SocketAddr,
    /// The join token viewers must present.
    pub token: String,
    /// Where to record the session, if anywhere: the files (a
    /// [`crate::sim::record_files::RecordDir`]) and the size cap of each.
    pub record: Option<crate::sim::session::RecordOptions>,
    /// What one viewer is served at most.
    pub limits: crate::viewer::ViewerLimits,
    /// Viewers served at once (drivers and spectators); the next is refused with
    /// [`roam_protocol::messages::Reason::Full`].
    pub max_viewers: usize,
    /// Connections still in their handshake or hello at once; past it, new ones must
    /// prove their address (QUIC Retry), and are refused if still over.
    pub max_pending: usize,
    /// One deadline for a connection's TLS handshake and its hello together.
    pub hello_timeout: std::time::Duration,
    /// How long a driver's vehicle is held after its connection drops, for the driver to
    /// come back to ([`roam_protocol::messages::Hello::resume`]).
    pub hold: std::time::Duration,
}

/// [`Options::max_viewers`] unless told otherwise.
pub const MAX_VIEWERS: usize = 64;
/// [`Options::max_pending`] unless told otherwise.
pub const MAX_PENDING: usize = 256;
/// [`Options::hello_timeout`] unless told otherwise.
pub const HELLO_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);
/// [`Options::hold`] unless told otherwise.
pub const HOLD: std::time::Duration = std::time::Duration::from_secs(30);

impl Options {
    /// Listening on `listen` for viewers with `token`, not recorded, with the default
    /// limits.
    pub fn new(listen: SocketAddr, token: String) -> Options {
        Options {
            listen,
            token,
            record: None,
            limits: crate::viewer::ViewerLimits::default(),
            max_viewers: MAX_VIEWERS,
            max_pending: MAX_PENDING,
            hello_timeout: HELLO_TIMEOUT,
            hold: HOLD,
        }
    }
}

/// What every connection task shares.
pub struct Shared {
    pub terrain: Arc<Terrain>,
    pub variance: Arc<VarianceTree>,
    pub token: String,
    pub limits: crate::viewer::ViewerLimits,
    /// The heights' common step, for the mesh coder (computed once).
    pub height_step: u16,
    /// The colour map, compressed once (`roam_protocol::colormap`) for every welcome.
    pub color_map: Vec<u8>,
    /// The world thread's one inbox: joins, leaves and key states.
    world: std::sync::mpsc::Sender<Inbound>,
    snapshots: watch::Receiver<Arc<Snapshot>>,
    shutdown: watch::Receiver<bool>,
}

impl Shared {
    async fn shutting_down(&self) {
        let mut rx = self.shutdown.clone();
        let _ = rx.wait_for(|&s| s).await;
    }
}

/// A running server.
pub struct Server {
    pub addr: SocketAddr,
    snapshots: watch::Receiver<Arc<Snapshot>>,
    endpoint: quinn::Endpoint,
    stop: watch::Sender<bool>,
    accept: tokio::task::JoinHandle<()>,
    world: std::thread::JoinHandle<crate::sim::world::World>,
    world_stats: Arc<world_loop::WorldStats>,
    world_inbox: Option<std::sync::mpsc::Sender<Inbound>>,
}

/// Why the server could not start or stop cleanly.
#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("listening on {addr}: {error}")]
    Listen {
        addr: SocketAddr,
        error: std::io::Error,
    },
    #[error(transparent)]
    Tls(#[from] tls::TlsError),
    #[error("the world thread: {0}")]
    World(std::io::Error),
    #[error("the world thread panicked")]
    WorldPanicked,
    #[error("the colour map: {0}")]
    ColorMapShape(String),
    #[error("the colour map codes to {0} bytes, more than a viewer takes")]
    ColorMap(usize),
}

impl Server {
    /// Starts serving (on the current tokio runtime) and returns once it listens.
    pub fn start(
        terrain: Arc<Terrain>,
        variance: Arc<VarianceTree>,
        identity: &tls::Identity,
        options: Options,
    ) -> Result<Server, ServeError> {
        let config = tls::server_config(identity)?;
        let endpoint = quinn::Endpoint::server(config, options.listen).map_err(|error| {
            ServeError::Listen {
                addr: options.listen,
                error,
            }
        })?;
        let addr = endpoint.local_addr().map_err(|error| ServeError::Listen {
            addr: options.listen,
            error,
        })?;
        let (inbox, inbox_rx) = std::sync::mpsc::channel();
        let (snap_tx, snapshots) = watch::channel(Arc::new(Snapshot::default()));
        let world_stats = Arc::new(world_loop::WorldStats::default());
        let world = {
            let core = crate::sim::world_core::WorldCore::new(terrain.clone(), options.record)
                .map_err(ServeError::World)?
                .with_hold(world_loop::hold_ticks(options.hold));
            let stats = world_stats.clone();
            std::thread::Builder::new()
                .name("roam-world".into())
                .spawn(move || world_loop::run(core, inbox_rx, snap_tx, &stats))
                .map_err(ServeError::World)?
        };
        let (stop, shutdown) = watch::channel(false);
        let mut color_map = Vec::new();
        let rgb: Vec<u8> = terrain.color.rgb().iter().flatten().copied().collect();
        roam_protocol::colormap::encode(terrain.color.cells(), &rgb, &mut color_map)
            .map_err(|e| ServeError::ColorMapShape(e.to_string()))?;
        if color_map.len() > roam_protocol::colormap::max_len(terrain.color.cells()) {
            return Err(ServeError::ColorMap(color_map.len()));
        }
        let shared = Arc::new(Shared {
            height_step: roam_protocol::height_step(terrain.heights.samples()),
            color_map,
            terrain,
            variance,
            token: options.token,
            limits: options.limits,
            world: inbox.clone(),
            snapshots: snapshots.clone(),
            shutdown,
        });
        let accept = tokio::spawn(accept_loop(endpoint.clone(), shared));
        Ok(Server {
            addr,
            snapshots,
            endpoint,
            stop,
            accept,
            world,
            world_stats,
            world_inbox: Some(inbox),
        })
    }

    /// How the world thread keeps time (ticks made, dropped, late).
    pub fn world_stats(&self) -> Arc<world_loop::WorldStats> {
        self.world_stats.clone()
    }

    /// The world after its latest tick.
    pub fn snapshot(&self) -> Arc<Snapshot> {
        self.snapshots.borrow().clone()
    }

    /// The world's snapshots as they come (latest wins): to wait for a change in the
    /// world without polling.
    pub fn watch(&self) -> watch::Receiver<Arc<Snapshot>> {
        self.snapshots.clone()
    }

    /// Stops: viewers are told why, the world stops and its recording is closed. Returns
    /// the final world.
    pub async fn shutdown(mut self) -> Result<crate::sim::world::World, ServeError> {
        let _ = self.stop.send(true);
        // Give viewer tasks a moment to say goodbye, then close what is left.
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
        self.endpoint.close(
            roam_protocol::messages::close::SHUTDOWN.into(),
            b"the server is shutting down",
        );
        self.accept.abort();
        let _ = self.accept.await;
        self.endpoint.wait_idle().await;
        // Connections are closed; viewer tasks (and a tessellation in flight) end shortly
        // and drop their senders, and then the world thread sees the channel close.
        drop(self.world_inbox.take());
        let world = tokio::task::spawn_blocking(move || self.world.join())
            .await
            .map_err(|_| ServeError::WorldPanicked)?
            .map_err(|_| ServeError::WorldPanicked)?;
        Ok(world)
    }
}

async fn accept_loop(endpoint: quinn::Endpoint, shared: Arc<Shared>) {
    while let Some(incoming) = endpoint.accept().await {
        let shared = shared.clone();
        tokio::spawn(async move {
            if let Ok(conn) = incoming.await {
                viewer::serve(conn, shared).await;
            }
        });
    }
}

/// A fresh random join token (16 hex digits).
pub fn random_token() -> String {
    use ring::rand::SecureRandom;
    let mut bytes = [0u8; 8];
    ring::rand::SystemRandom::new()
        .fill(&mut bytes)
        .expect("the system's random source works");
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}
