//! A headless viewer: connects, plays an input script as key datagrams, decodes and checks
//! every frame, acknowledges it, and measures what it got: reconnections and the longest
//! time without frames included. A session lost for good midway still reports what it
//! measured ([`measure`]), with the error beside. Colour tiles are decoded and checked,
//! and kept only for a screenshot ([`Keep::Masks`] otherwise: a load generator of many
//! viewers holds no texels; with `--skip-decode`, [`Keep::Counted`]: none is decoded); the window asked is the default one
//! ([`roam_protocol::tiles::DEFAULT_WINDOW`]), as a viewer with a GPU asks. Given several
//! addresses (the edges of one world, [`measure_any`]) it goes from one to the next as
//! the session does; an edge's word that its world is gone, and back, is one line each on
//! stderr.

use std::net::SocketAddr;
use std::time::Instant;

use anyhow::{Result, anyhow, bail};
use roam_protocol::mesh;
use roam_protocol::messages::{self, Role};
use roam_protocol::script::Script;

use crate::color_cache::{ColorCache, Keep};
use crate::session::{KeySource, Patience, Session, Status, Taken};

pub use crate::session::connect;

/// What one viewer asks for.
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    pub token: String,
    pub role: Role,
    pub budget: u32,
    /// Stop after this many frames.
    pub frames: u64,
    /// Keys to play, one step of the script per 10 ms (drivers).
    pub inputs: Option<Script>,
    /// Where on the process's 10 ms grid the key clock ticks ([`KeySource::ScriptAt`]);
    /// `None`: from the join.
    pub key_phase: Option<std::time::Duration>,
    /// Play the script in step with the process's other viewers ([`KeySource::InStep`]),
    /// whatever `key_phase` says.
    pub in_step: bool,
    pub viewport: [u32; 2],
    pub fov_y_deg: f32,
    pub frame_rate: u16,
    /// Acknowledge frames without decoding them, and count colour and normal tiles without
    /// decoding them after the join's (a load generator measuring the server, not itself).
    pub skip_decode: bool,
    /// Keep the scene and the last mesh (for a screenshot).
    pub keep_last: bool,
    /// Set to true to stop early (Ctrl-C): the viewer says goodbye and reports.
    pub stop: Option<tokio::sync::watch::Receiver<bool>>,
    /// How long to wait on a silent server, and to reconnect after a loss.
    pub patience: Patience,
}

impl Default for ViewerOptions {
    fn default() -> Self {
        ViewerOptions {
            token: String::new(),
            role: Role::Driver,
            budget: 65_536,
            frames: 300,
            inputs: None,
            key_phase: None,
            in_step: false,
            viewport: [1280, 720],
            fov_y_deg: 60.0,
            frame_rate: 60,
            skip_decode: false,
            keep_last: false,
            stop: None,
            patience: Patience::default(),
        }
    }
}

/// What one viewer measured.
#[derive(Clone, Debug, Default)]
pub struct ViewerStats {
    pub frames: u64,
    /// Numbers of the first and the last frame taken: the server made every frame between
    /// them, so their span over [`Self::seconds`] is the rate it sent at, and the frames not
    /// taken were lost or superseded before the viewer got to them. Of the newest
    /// connection: frame numbers start again on each.
    pub first_frame: Option<u64>,
    pub last_frame: u64,
    /// The frames the server made on the connections before the newest (their spans).
    pub made_before: u64,
    pub seconds: f64,
    /// From the join (welcome and colour map received) to the first frame, and from the
    /// first frame to the last: the frame rate is taken over the latter, so it measures
    /// frames arriving, not joining.
    pub first_frame_s: f64,
    pub streaming_s: f64,
    /// Wire bytes per triangle of the first frame, and of each later one.
    pub first: Option<f64>,
    pub steady: Vec<f64>,
    /// Key change sent → first frame showing it applied, ms.
    pub latencies_ms: Vec<f64>,
    pub decode_errors: u64,
    /// The vehicle driven or followed, and its state in the last frame.
    pub vehicle: u16,
    pub last: Option<messages::VehicleView>,
    pub last_tick: u64,
    /// The largest mesh received, triangles.
    pub max_triangles: usize,
    /// The most vehicles one frame taken carried.
    pub vehicles_max: usize,
    /// With `keep_last`: the scene, the last mesh decoded and the colour tiles resident.
    pub scene: Option<crate::render::Scene>,
    pub last_mesh: Option<mesh::Mesh>,
    pub colors: Option<ColorCache>,
    /// Colour tile bytes received (every connection's), and the tiles resident at the end
    /// out of the most the viewer holds.
    pub color_bytes: u64,
    pub color_tiles: u32,
    pub color_capacity: u32,
    /// Connections made again after one was lost, and of those the driver's that got its
    /// vehicle back.
    pub reconnects: u32,
    pub resumed: u32,
    /// The longest time between two frames (a reconnection's gap included), seconds.
    pub gap_max_s: f64,
    /// The budget served: the one asked for, or the server's most if that is less.
    pub budget_served: u32,
    /// Addresses learned from the edges' lists, and the time the world behind the edge
    /// was said gone, in all, seconds.
    pub edges_learned: usize,
    pub world_gone_s: f64,
    /// Why the session ended before its frame count, if it did.
    pub error: Option<String>,
}

impl ViewerStats {
    /// The frames the server made from the first frame taken to the last, every connection
    /// together.
    pub fn made(&self) -> u64 {
        self.made_before
            + self
                .first_frame
                .map_or(0, |f| self.last_frame.saturating_sub(f) + 1)
    }
}

/// Runs one viewer to its frame count; an error if the session ended before.
pub async fn run(
    addr: SocketAddr,
    fingerprint: [u8; 32],
    opts: ViewerOptions,
) -> Result<ViewerStats> {
    let stats = measure(addr, fingerprint, opts).await?;
    match &stats.error {
        Some(e) => Err(anyhow!("{e}")),
        None => Ok(stats),
    }
}

/// Runs one viewer to its frame count, or until its session ends: what it measured, with
/// [`ViewerStats::error`] saying why it ended early. An error only when it cannot join.
pub async fn measure(
    addr: SocketAddr,
    fingerprint: [u8; 32],
    opts: ViewerOptions,
) -> Result<ViewerStats> {
    measure_any(&[addr], fingerprint, opts).await
}

/// As [`measure`], joining the first of `addrs` that answers and going from one to the
/// next when one is lost ([`Session::join_any`]).
pub async fn measure_any(
    addrs: &[SocketAddr],
    fingerprint: [u8; 32],
    opts: ViewerOptions,
) -> Result<ViewerStats> {
    // The window of a native viewer's device, as the window asks (the default one).
    let hello = crate::conversation::hello(
        opts.role.clone(),
        opts.token.clone(),
        opts.viewport,
        opts.fov_y_deg,
        opts.budget,
        opts.frame_rate,
        crate::render::native_max_texture(),
    );
    let keys = match (&opts.role, &opts.inputs) {
        (Role::Driver, Some(script)) if opts.in_step => KeySource::InStep(script.clone()),
        (Role::Driver, Some(script)) => match opts.key_phase {
            Some(phase) => KeySource::ScriptAt(script.clone(), phase),
            None => KeySource::Script(script.clone()),
        },
        _ => KeySource::None,
    };
    let keep = if opts.keep_last {
        Keep::Texels
    } else if opts.skip_decode {
        Keep::Counted
    } else {
        Keep::Masks
    };
    let session = Session::join_any(addrs, fingerprint, hello, keys, opts.patience, keep).await?;
    if opts.skip_decode {
        session.skip_color();
    }
    let said = tokio::spawn(say_world(session.status_changes()));
    let mut stats = ViewerStats {
        scene: opts.keep_last.then(|| session.scene.clone()),
        ..ViewerStats::default()
    };
    let started = Instant::now();
    let mut first_at: Option<Instant> = None;
    let ended = frames(&session, &opts, &mut stats, started, &mut first_at).await;
    stats.seconds = started.elapsed().as_secs_f64();
    stats.streaming_s = first_at.map_or(0.0, |t| t.elapsed().as_secs_f64());
    let status = session.status();
    stats.vehicle = status.welcome.vehicle;
    stats.reconnects = status.gaps.reconnects;
    stats.resumed = status.gaps.resumed;
    stats.gap_max_s = status.gaps.longest(Instant::now()).as_secs_f64();
    stats.edges_learned = status.edges_learned;
    stats.world_gone_s = status.world.gone_total(Instant::now()).as_secs_f64();
    stats.budget_served = session.core().effective_budget();
    stats.color_bytes = session.color_bytes();
    {
        let colors = session.colors();
        stats.color_tiles = colors.resident();
        stats.color_capacity = colors.capacity();
    }
    if opts.keep_last && stats.max_triangles > 0 {
        // The mesh of the last frame decoded, and the colour it is drawn with.
        stats.last_mesh = Some(session.core().mesh());
        stats.colors = Some(session.take_colors());
    }
    match ended {
        Ok(()) => {
            session.quit().await;
        }
        Err(e) => stats.error = Some(format!("{e:#}")),
    }
    said.abort();
    Ok(stats)
}

/// One line on stderr when the edge says its world is gone, one when it is back (or
/// another edge, which does not say it is gone, takes the viewer), until the session ends.
async fn say_world(mut status: tokio::sync::watch::Receiver<Status>) {
    let mut gone: Option<String> = None;
    loop {
        let (now, addr) = {
            let s = status.borrow_and_update();
            (s.world.gone.clone(), s.addr)
        };
        if now != gone {
            match &now {
                Some(why) => eprintln!("roam-client: the world behind {addr} is gone: {why}"),
                None => eprintln!("roam-client: the world behind {addr} is back"),
            }
            gone = now;
        }
        if status.changed().await.is_err() {
            return;
        }
    }
}

/// Takes frames into `stats` until the frame count, a stop, or the session's end (an
/// error).
async fn frames(
    session: &Session,
    opts: &ViewerOptions,
    stats: &mut ViewerStats,
    started: Instant,
    first_at: &mut Option<Instant>,
) -> Result<()> {
    let mut stop = opts.stop.clone();
    let mut connection = 0;
    let mut terrain = crate::render::TerrainVertices::default();
    let mut checking: Option<tokio::task::JoinHandle<Result<()>>> = None;
    while stats.frames < opts.frames {
        let taken = tokio::select! {
            t = session.next_frame(!opts.skip_decode) => t?,
            () = stopped(&mut stop) => break,
        };
        let r = match taken {
            Taken::Nothing => continue,
            Taken::Dropped(_) => {
                stats.decode_errors += 1;
                continue;
            }
            Taken::Frame(r) => r,
        };
        if stats.frames == 0 {
            *first_at = Some(Instant::now());
            stats.first_frame_s = started.elapsed().as_secs_f64();
        }
        stats.frames += 1;
        stats.vehicles_max = stats.vehicles_max.max(r.vehicles.len());
        let reconnects = session.reconnects();
        if reconnects != connection {
            // A new connection: its frames are numbered from 0 again.
            connection = reconnects;
            stats.made_before = stats.made();
            stats.first_frame = None;
        }
        stats.first_frame.get_or_insert(r.frame);
        stats.last_frame = r.frame;
        stats.last_tick = r.tick;
        if opts.skip_decode {
            continue;
        }
        // The vertices, as a viewer with a window builds them (the slots the frame
        // changed); nothing uploads them here.
        session.core().update_vertices(&session.scene, &mut terrain);
        terrain.forget_changes();
        let tris = r.triangles;
        if tris > opts.budget.max(2) as usize {
            bail!(
                "frame {}: {tris} triangles, budget {}",
                r.frame,
                opts.budget
            );
        }
        if stats.frames % 60 == 1 {
            // Checked on a copy: the core's lock is not held while checking.
            let (m, size) = {
                let core = session.core();
                (core.mesh(), core.grid().size())
            };
            // Off the frame loop (O(cut), tens of milliseconds at 65,536 triangles: frames
            // would be superseded meanwhile); one at a time, its verdict taken at the next.
            if let Some(previous) = checking.take() {
                previous.await??;
            }
            let frame = r.frame;
            checking = Some(tokio::task::spawn_blocking(move || {
                roam_protocol::validate::check_mesh(&m.vertices, &m.indices, size)
                    .map_err(|e| anyhow!("frame {frame}: not a conforming mesh: {e}"))
            }));
        }
        let per_tri = r.wire_bytes as f64 / tris.max(1) as f64;
        if stats.first.is_none() {
            stats.first = Some(per_tri);
        } else {
            stats.steady.push(per_tri);
        }
        stats.max_triangles = stats.max_triangles.max(tris);
        stats.latencies_ms.extend(&r.latencies_ms);
        let me = session.vehicle();
        stats.last = r.vehicles.iter().find(|v| v.id == me).copied();
    }
    if let Some(last) = checking {
        last.await??;
    }
    Ok(())
}

/// Returns once `stop` is set; never without one.
async fn stopped(stop: &mut Option<tokio::sync::watch::Receiver<bool>>) {
    match stop {
        Some(r) => {
            if r.wait_for(|s| *s).await.is_err() {
                std::future::pending::<()>().await;
            }
        }
        None => std::future::pending().await,
    }
}
