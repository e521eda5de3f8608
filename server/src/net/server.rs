//! A running server: its [`Options`] and their defaults, [`Server::start`] (the checks on
//! the data set, the QUIC endpoint, the world thread, a replay or the remote world in its
//! place, the browser viewer's endpoints) and [`Server::shutdown`], the accept loop, the
//! summary logged every [`Options::summary_every`], and the allocator's free memory given
//! back every [`TRIM_EVERY`].

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use roam_link::tls;
use tokio::sync::watch;

use super::serve_error::ServeError;
use super::shared::{Gate, Shared};
use super::stats::{self, ServeStats};
use super::world_loop::{self, Inbound};
use super::{bus, clock, color_budget, conn, frames, handshake, makers, replay, viewer, web};
use crate::Terrain;
use crate::sim::world_core::Snapshot;
use crate::terrain::color_pyramid::ColorPyramid;
use crate::terrain::normal_pyramid::NormalPyramid;
use crate::terrain::variance::VarianceTree;
use crate::viewer::admission::Admission;

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
    /// Bytes the viewers' state may hold together ([`crate::viewer::admission`]: each
    /// viewer's seat reserves an estimate from its budget); the next viewer that would not
    /// fit is refused with [`roam_protocol::messages::Reason::Unavailable`] naming the
    /// limit. `None`: [`crate::viewer::admission::default_max_memory`] of this machine's
    /// `/proc/meminfo` when the server starts (half the memory available), or no limit
    /// where that cannot be read.
    pub max_memory: Option<u64>,
    /// Connections still in their handshake or hello at once; past it, new ones must
    /// prove their address (QUIC Retry), and are refused if still over.
    pub max_pending: usize,
    /// One deadline for a connection's TLS handshake and its hello together.
    pub hello_timeout: std::time::Duration,
    /// How long a driver's vehicle is held after its connection drops, for the driver to
    /// come back to ([`roam_protocol::messages::Hello::resume`]).
    pub hold: std::time::Duration,
    /// How often the summary line is logged.
    pub summary_every: std::time::Duration,
    /// Colour tile bytes a second at most, per viewer, each tile's normals included (the
    /// coarsest tile, sent before the first frame, is outside it).
    pub color_rate: u64,
    /// Colour tile bytes a second at most (normals included), every viewer together:
    /// shared equally by the viewers still wanting tiles, and sent only while no frame is
    /// behind ([`color_budget`]).
    pub color_total: u64,
    /// The colour window (tiles a side per level) offered; a viewer asking less gets its
    /// own ([`roam_protocol::messages::Hello::color_window`]).
    pub color_window: u8,
    /// The browser viewer (`serve --web`): its page over HTTPS and WebTransport.
    pub web: Option<web::WebOptions>,
    /// The world, when it is elsewhere (`roam-server edge`): reached over NATS, its
    /// snapshots served and its tickets handed out. `None`: the world runs in this process
    /// (`serve`), and [`Options::record`] records it.
    pub remote: Option<Arc<bus::edge::Remote>>,
    /// The terrain's normal tiles ([`crate::terrain::normal_pyramid`]), with the colour
    /// pyramid's layout; `None`: built in memory from the terrain when the server starts
    /// (`serve` maps them from the data set's cache).
    pub normals: Option<Arc<NormalPyramid>>,
    /// A recording to serve instead of a live world (`serve --replay`): every viewer
    /// watches it as a spectator, and [`Options::record`] is not used ([`replay`]).
    pub replay: Option<replay::Replaying>,
}

/// [`Options::max_viewers`] unless told otherwise.
pub const MAX_VIEWERS: usize = 64;
/// [`Options::max_pending`] unless told otherwise.
pub const MAX_PENDING: usize = 256;
/// [`Options::hello_timeout`] unless told otherwise.
pub const HELLO_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);
/// [`Options::hold`] unless told otherwise.
pub const HOLD: std::time::Duration = std::time::Duration::from_secs(30);
/// [`Options::color_rate`] unless told otherwise: 2 MB/s.
pub const COLOR_RATE: u64 = 2_000_000;
/// [`Options::color_total`] unless told otherwise: 4 MB/s.
pub const COLOR_TOTAL: u64 = 4_000_000;

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
            max_memory: None,
            max_pending: MAX_PENDING,
            hello_timeout: HELLO_TIMEOUT,
            hold: HOLD,
            summary_every: std::time::Duration::from_secs(60),
            color_rate: COLOR_RATE,
            color_total: COLOR_TOTAL,
            color_window: roam_protocol::tiles::DEFAULT_WINDOW,
            web: None,
            remote: None,
            normals: None,
            replay: None,
        }
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
    shared: Arc<Shared>,
    summary: tokio::task::JoinHandle<()>,
    trim: tokio::task::JoinHandle<()>,
    web: Option<web::Running>,
}

/// [`Options::max_memory`] when not given: half the memory this machine has available now
/// ([`crate::viewer::admission::default_max_memory`]), or no limit (logged) where
/// `/proc/meminfo` does not say. Read once, as the server starts.
fn machine_max_memory() -> u64 {
    let meminfo = std::fs::read_to_string("/proc/meminfo").unwrap_or_default();
    match crate::viewer::admission::default_max_memory(&meminfo) {
        Some(bytes) => {
            tracing::info!(
                mib = bytes >> 20,
                "viewers' memory at most half of what is available (--max-memory to change)"
            );
            bytes
        }
        None => {
            tracing::warn!(
                "no MemAvailable in /proc/meminfo: viewers' memory is not limited \
                 (--max-memory to limit it)"
            );
            u64::MAX
        }
    }
}

/// The most levels a served data set may have: a grid of `2^15 + 1` samples a side, the
/// protocol's largest colour map ([`roam_protocol::tiles::MAX_COLOR_CELLS`]; it streams as
/// tiles, so no viewer ever holds it whole).
pub const MAX_LEVELS: u32 = 15;

/// Whether `terrain` can be served: an error (before anything starts) if not.
pub fn check_servable(terrain: &Terrain) -> Result<(), ServeError> {
    servable(terrain.heights.levels())
}

/// Whether a grid of `2^levels + 1` samples a side can be served.
fn servable(levels: u32) -> Result<(), ServeError> {
    if levels > MAX_LEVELS {
        return Err(ServeError::TooLarge {
            side: (1u32 << levels.min(31)) + 1,
            max: (1 << MAX_LEVELS) + 1,
            levels: MAX_LEVELS,
        });
    }
    Ok(())
}

impl Server {
    /// Starts serving (on the current tokio runtime) and returns once it listens.
    pub fn start(
        terrain: Arc<Terrain>,
        variance: Arc<VarianceTree>,
        pyramid: Arc<ColorPyramid>,
        identity: &tls::Identity,
        options: Options,
    ) -> Result<Server, ServeError> {
        check_servable(&terrain)?;
        // Everything that can refuse the data set comes before the recording's first file.
        let layout = pyramid.layout(options.color_window)?;
        if layout.cells != terrain.heights.size() {
            return Err(ServeError::ColorPyramid {
                got: layout.cells,
                expected: terrain.heights.size(),
            });
        }
        let normals = match options.normals {
            Some(n) => n,
            None => {
                let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
                Arc::new(NormalPyramid::build(
                    &terrain.heights,
                    (terrain.map.h_scale, terrain.map.v_scale),
                    layout.tile,
                    threads,
                    &mut |_, _| {},
                )?)
            }
        };
        let normal_layout = normals.layout(options.color_window)?;
        if normal_layout != layout {
            return Err(ServeError::NormalLayout {
                got: normal_layout,
                expected: layout,
            });
        }
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
        let web = options.web.map(web::bind).transpose()?;
        let max_memory = options.max_memory.unwrap_or_else(machine_max_memory);
        let (inbox, inbox_rx) = std::sync::mpsc::channel();
        let (snap_tx, snapshots) = watch::channel(Arc::new(Snapshot::default()));
        let world_stats = Arc::new(world_loop::WorldStats::default());
        let (world, replaying) = match (options.replay, options.remote.clone()) {
            (Some(r), _) => {
                let (thread, shared) = replay::start(r, inbox_rx, snap_tx, world_stats.clone())
                    .map_err(ServeError::World)?;
                (thread, Some(shared))
            }
            // Vehicles at most, held ones included: a seat each.
            (None, None) => (
                world_loop::start(
                    terrain.clone(),
                    options.record,
                    (options.hold, options.max_viewers, false),
                    inbox_rx,
                    snap_tx,
                    world_stats.clone(),
                )
                .map_err(ServeError::World)?,
                None,
            ),
            (None, Some(remote)) => {
                let terrain = terrain.clone();
                let runtime = tokio::runtime::Handle::current();
                // The world may serve a recording (`world --replay`): watched here while
                // its snapshots say so.
                let replay = replay::ReplayShared::for_edge(remote.clone(), remote.replay_clock());
                let thread = std::thread::Builder::new()
                    .name("roam-edge".into())
                    .spawn(move || bus::edge::run(remote, terrain, runtime, inbox_rx, snap_tx))
                    .map_err(ServeError::World)?;
                (thread, Some(replay))
            }
        };
        let (stop, shutdown) = watch::channel(false);
        // One from-scratch tessellator per frame maker at most: only the makers borrow them.
        let makers = makers();
        let shared = Arc::new(Shared {
            scratch: crate::tessellate::Scratch::new(terrain.heights.side(), makers),
            height_step: roam_protocol::height_step(terrain.heights.samples()),
            pyramid,
            normals,
            color: color_budget::ColorBudget::new(
                options.color_rate,
                options.color_total,
                std::time::Instant::now(),
            ),
            color_window: options.color_window,
            terrain,
            variance,
            token: options.token,
            limits: options.limits,
            world: inbox.clone(),
            snapshots: snapshots.clone(),
            shutdown,
            hello_timeout: options.hello_timeout,
            world_stats: world_stats.clone(),
            gate: Mutex::new(Gate {
                admission: Admission::new(options.max_pending, options.max_viewers)
                    .with_max_memory(max_memory),
                evict: HashMap::new(),
            }),
            tickets: Mutex::new(HashMap::new()),
            remote: options.remote,
            replay: replaying,
            makers: Arc::new(makers::Makers::new(makers)),
            unfinished: Arc::new(tokio::sync::Semaphore::new(options.max_pending)),
            stats: Arc::new(ServeStats::default()),
            clock: clock::FrameClock::default(),
        });
        // Every viewer's frames, until the shutdown.
        tokio::spawn(frames::run(shared.clone()));
        let web = web.map(|w| w.start(shared.clone()));
        let accept = tokio::spawn(accept_loop(endpoint.clone(), shared.clone()));
        let summary = tokio::spawn(summary_loop(
            shared.clone(),
            world_stats.clone(),
            options.summary_every,
        ));
        let trim = tokio::spawn(trim_loop());
        Ok(Server {
            addr,
            snapshots,
            endpoint,
            stop,
            accept,
            world,
            world_stats,
            world_inbox: Some(inbox),
            shared,
            summary,
            trim,
            web,
        })
    }

    /// The browser viewer's address (HTTPS over TCP; WebTransport over UDP, same port),
    /// when served.
    pub fn web_addr(&self) -> Option<SocketAddr> {
        self.web.as_ref().map(|w| w.addr)
    }

    /// The SHA-256 of the browser viewer's certificate now (it changes when renewed).
    pub fn web_certificate(&self) -> Option<[u8; 32]> {
        self.web.as_ref().map(|w| w.certs.current().sha256)
    }

    /// What a page pins the browser viewer's certificate by (none for a given one).
    pub fn web_hashes(&self) -> Vec<[u8; 32]> {
        self.web
            .as_ref()
            .map(|w| w.certs.served_hashes())
            .unwrap_or_default()
    }

    /// What the server has counted so far.
    pub fn counts(&self) -> stats::Counts {
        self.shared.stats.counts()
    }

    /// Connections pending (handshake or hello) and viewers served, now.
    pub fn load(&self) -> (usize, usize) {
        let gate = self.shared.gate();
        (gate.admission.pending(), gate.admission.viewers())
    }

    /// Bytes the viewers' seats reserve now, and the most they may
    /// ([`Options::max_memory`], resolved).
    pub fn memory(&self) -> (u64, u64) {
        let gate = self.shared.gate();
        (gate.admission.memory(), gate.admission.max_memory())
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
        if let Some(web) = &mut self.web {
            web.stop();
            // A web session's close goes as a capsule the browser answers by closing the
            // connection (web_transport_quinn::Session::close): wait for that (bounded),
            // else the browser sees only "connection lost" and reconnects to nothing.
            let _ =
                tokio::time::timeout(viewer::WEB_CLOSE_WAIT * 2, web.endpoint.wait_idle()).await;
            web.endpoint.close(
                roam_protocol::messages::close::SHUTDOWN.into(),
                b"the server is shutting down",
            );
        }
        self.accept.abort();
        let _ = self.accept.await;
        self.summary.abort();
        let _ = self.summary.await;
        self.trim.abort();
        let _ = self.trim.await;
        self.endpoint.wait_idle().await;
        if let Some(web) = &self.web {
            web.endpoint.wait_idle().await;
        }
        // Connections are closed; viewer tasks (and a tessellation in flight) end shortly
        // and drop their senders (the last of them in `shared`), and then the world
        // thread sees the channel close.
        drop(self.shared);
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
        handshake::arrive(incoming, &shared, conn::Via::Quic);
    }
}

/// Blocking frame makers at once: one fewer than the cores, at least one.
fn makers() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get().saturating_sub(1).max(1))
}

/// How often the allocator gives back what is free ([`trim_loop`]).
const TRIM_EVERY: std::time::Duration = std::time::Duration::from_secs(2);

/// Gives the free memory of the allocator's heaps back to the system every [`TRIM_EVERY`]
/// (glibc's `malloc_trim`, on a blocking thread). A driving viewer's cut grows and shrinks
/// its tables as it changes, and what a table leaves free in the heaps below the
/// mmap threshold (`cli/net.rs`) stays resident until something of its size is asked for
/// again: read over a drive (`scripts/viewer_memory.sh /tmp/synth-16385`, 65,536
/// triangles, the medians of 17 samples a run, 2026-12-08), a viewer held 3.95–4.13 MB
/// of anonymous memory where its cut's tables were 2.8 MB (the bench's
/// `serve_viewer_heap_bytes` along the same drive); trimmed, 3.38–3.41 (3.71–3.72 at the
/// most, just before a trim). A trim took 0.1–4.2 ms with 100 viewers driving in step,
/// and their frames were the same (`scripts/capacity.sh --in-step 100`: 59.0–59.1
/// frames/s, 116–124 µs a frame, against 59.0–59.2 and 121–124 untrimmed).
async fn trim_loop() {
    let mut ticker = tokio::time::interval(TRIM_EVERY);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    ticker.tick().await;
    loop {
        ticker.tick().await;
        if tokio::task::spawn_blocking(give_back_free_memory)
            .await
            .is_err()
        {
            return; // the runtime is shutting down
        }
    }
}

#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn give_back_free_memory() {
    // SAFETY: `malloc_trim` only returns free memory of the allocator's own heaps to the
    // system; it may be called at any time from any thread.
    unsafe { libc::malloc_trim(0) };
}

#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn give_back_free_memory() {}

/// Logs a summary every `every`: viewers, frames a second, CPU per frame, bytes out a
/// second, the world's health and what admission turned away.
async fn summary_loop(
    shared: Arc<Shared>,
    world: Arc<world_loop::WorldStats>,
    every: std::time::Duration,
) {
    let mut last_ticks = (world.ticks(), world.dropped());
    let mut ticker = tokio::time::interval(every);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    ticker.tick().await;
    let mut last = (
        std::time::Instant::now(),
        shared.stats.counts(),
        stats::process_cpu(),
    );
    loop {
        ticker.tick().await;
        let now = (
            std::time::Instant::now(),
            shared.stats.counts(),
            stats::process_cpu(),
        );
        let seconds = now.0.duration_since(last.0).as_secs_f64().max(1e-3);
        let cpu = now.2.zip(last.2).map(|(b, a)| b.saturating_sub(a));
        let s = stats::Summary::between(&last.1, &now.1, seconds, cpu);
        let (pending, viewers, reserved) = {
            let gate = shared.gate();
            let a = &gate.admission;
            (a.pending(), a.viewers(), a.memory())
        };
        let snap = shared.snapshots.borrow().clone();
        let ticks = world.ticks();
        let dropped = world.dropped();
        let pending_longest_ms = shared.stats.summarized();
        let late_ms_max = shared.stats.late_longest_us() as f64 / 1e3;
        // The least allowance a frame's cut had (`-`: none all along).
        let allowance = shared.stats.allowance_least();
        let allowance_min = allowance.map_or("-".to_string(), |a| a.to_string());
        tracing::info!(
            viewers,
            memory_mb = format_args!("{:.1}", reserved as f64 / f64::from(1u32 << 20)),
            ticks_per_s = format_args!("{:.1}", (ticks - last_ticks.0) as f64 / seconds),
            dropped_ticks = dropped - last_ticks.1,
            vehicles = snap.vehicles.len(),
            tick = snap.tick,
            fps = format_args!("{:.1}", s.frames_per_s),
            cpu_per_frame_us = format_args!("{:.0}", s.cpu_per_frame_us.unwrap_or(0.0)),
            make_us = format_args!("{:.0}", s.make_us.unwrap_or(0.0)),
            key_frames = now.1.key_frames - last.1.key_frames,
            key_asked = now.1.key_asked - last.1.key_asked,
            key_behind = now.1.key_behind - last.1.key_behind,
            key_larger = now.1.key_larger - last.1.key_larger,
            late_ms_max = format_args!("{late_ms_max:.1}"),
            short_frames = now.1.short - last.1.short,
            allowance_min,
            passed_over = now.1.passed_over - last.1.passed_over,
            heavy_frames = now.1.heavy - last.1.heavy,
            kbytes_out_per_s = format_args!("{:.1}", s.bytes_out_per_s / 1e3),
            color_kbytes_per_s = format_args!("{:.1}", s.color_bytes_per_s / 1e3),
            normal_kbytes_per_s = format_args!("{:.1}", s.normal_bytes_per_s / 1e3),
            pending,
            pending_longest_ms,
            junk_closed = s.junk,
            retried = s.retried,
            refused = s.refused,
            "summary"
        );
        last = now;
        last_ticks = (ticks, dropped);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grids_past_32769_are_refused_with_the_reason() {
        for levels in 1..=MAX_LEVELS {
            assert!(servable(levels).is_ok(), "{levels} levels");
        }
        for (levels, side) in [(16, 65_537), (17, 131_073)] {
            let e = servable(levels).expect_err("too large").to_string();
            assert!(
                e.contains(&format!("{side}²")) && e.contains("32769²"),
                "{e}"
            );
        }
    }
}
