//! The window's network task: it keeps a [`Session`] going on the async runtime (the
//! session's key sender, in `connection.rs`, sends the latch every 10 ms), feeds the
//! window's keys into the session's latch, decodes the newest frame and builds its vertices, and
//! leaves the result for the render thread, which never waits on the network. The session
//! reconnects by itself; the HUD reads its state ([`Shared::status`]).

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use roam_protocol::keys::Keys;
use roam_protocol::messages::VehicleView;
use roam_protocol::sync::lock;
use tokio::sync::mpsc;

use crate::camera::LocalGround;
use crate::color_cache::ColorUpdate;
use crate::render::{MorphView, TerrainUpdate, TerrainVertices};
use crate::session::{Session, Taken};

/// What the render thread asks of the network task.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Command {
    /// A new triangle budget.
    Budget(u32),
    /// The camera the server should tessellate for.
    View(roam_protocol::messages::ViewChange),
    /// Follow this vehicle (a spectator).
    Follow(u16),
    /// Steer a watched recording's clock.
    Replay(roam_protocol::messages::ReplayControl),
    /// Say goodbye and stop.
    Quit,
}

/// A frame decoded and ready to draw.
#[derive(Debug)]
pub struct Arrived {
    pub frame: u64,
    pub tick: u64,
    pub vehicles: Vec<VehicleView>,
    /// What changed in the terrain's vertices since the frame before was left: the render
    /// thread applies it to its copy ([`crate::render::Renderer::apply`]).
    pub terrain: TerrainUpdate,
    /// The drawn ground around the followed vehicle, for the camera.
    pub ground: LocalGround,
    /// Decoding, following the mesh and rewriting the vertices it changed, milliseconds.
    pub decode_ms: f64,
    pub at: Instant,
}

/// How a session that quit ends: [`Connection::Ended`] with this, and more when the goodbye
/// was not heard.
pub const QUIT: &str = "quit";

/// Whether the task still has its session, in words for the HUD (reconnections are the
/// session's own [`crate::session::State`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Connection {
    Connected,
    Ended(String),
}

/// What the network task and the render thread share.
pub struct Shared {
    pub arrived: Mutex<Option<Arrived>>,
    /// The session: its core latches the window's keys for the key sender.
    session: Arc<Session>,
    pub connection: Mutex<Connection>,
    /// Frames taken from the stream and decoded.
    pub frames: AtomicU64,
    /// Frames that could not be decoded (a key frame was asked for).
    pub dropped: AtomicU64,
    /// Recent input→frame latencies, milliseconds.
    pub latencies: Mutex<VecDeque<f64>>,
    /// Ctrl-C was pressed in the terminal.
    pub interrupted: std::sync::atomic::AtomicBool,
}

impl Shared {
    pub fn take_arrived(&self) -> Option<Arrived> {
        lock(&self.arrived).take()
    }

    pub fn connection(&self) -> Connection {
        lock(&self.connection).clone()
    }

    pub fn key_down(&self, k: Keys) {
        self.session.key_down(k);
    }

    pub fn key_up(&self, k: Keys) {
        self.session.key_up(k);
    }

    /// Every key released (the window lost focus: nothing stays held).
    pub fn keys_released(&self) {
        self.session.keys_released();
    }

    /// Bytes of frames received.
    pub fn bytes_in(&self) -> u64 {
        self.session.bytes_in()
    }

    /// At most `most` colour tiles to upload and every level's state
    /// ([`crate::color_cache::ColorCache::drain`]), with the colour bytes received so far
    /// and the tiles resident out of the most held.
    pub fn colors(&self, most: usize) -> (ColorUpdate, u64, u32, u32) {
        let bytes = self.session.color_bytes();
        let mut c = self.session.colors();
        (c.drain(most), bytes, c.resident(), c.capacity())
    }

    /// The vehicle the camera rides (another after a reconnection that did not get it back).
    pub fn vehicle(&self) -> u16 {
        self.session.vehicle()
    }

    /// The session's state (reconnecting, and since when), its gaps and welcome.
    pub fn status(&self) -> crate::session::Status {
        self.session.status()
    }

    /// The median of the recent latencies, milliseconds.
    pub fn latency_ms(&self) -> Option<f64> {
        let l = lock(&self.latencies);
        let mut v: Vec<f64> = l.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied()
    }
}

/// Radius of the ground kept for the camera's look-ahead, world units.
const GROUND_RADIUS: f32 = 600.0;

/// Starts the task on `runtime`; it ends on [`Command::Quit`] or when the connection does.
pub fn spawn(
    runtime: &tokio::runtime::Handle,
    session: Session,
) -> (
    Arc<Shared>,
    mpsc::UnboundedSender<Command>,
    tokio::task::JoinHandle<()>,
) {
    let session = Arc::new(session);
    let shared = Arc::new(Shared {
        arrived: Mutex::new(None),
        session: session.clone(),
        connection: Mutex::new(Connection::Connected),
        frames: AtomicU64::new(0),
        dropped: AtomicU64::new(0),
        latencies: Mutex::new(VecDeque::new()),
        interrupted: std::sync::atomic::AtomicBool::new(false),
    });
    let (tx, rx) = mpsc::unbounded_channel();
    // Ctrl-C in the terminal quits as `q` does: the server is told.
    let quit = tx.clone();
    let interrupted = shared.clone();
    runtime.spawn(async move {
        let mut stop = crate::session::ctrl_c();
        if stop.wait_for(|s| *s).await.is_ok() {
            interrupted.interrupted.store(true, Ordering::Relaxed);
            let _ = quit.send(Command::Quit);
            // A second Ctrl-C exits at once.
            std::future::pending::<()>().await;
        }
    });
    let task = runtime.spawn(run(session, shared.clone(), rx));
    (shared, tx, task)
}

enum Event {
    Command(Option<Command>),
    Frame(anyhow::Result<Taken>),
}

async fn run(
    session: Arc<Session>,
    shared: Arc<Shared>,
    mut commands: mpsc::UnboundedReceiver<Command>,
) {
    // The vertices, kept up to date frame by frame (the slots each frame changed).
    let mut terrain = TerrainVertices::default();
    let ended = loop {
        let event = tokio::select! {
            c = commands.recv() => Event::Command(c),
            t = session.next_frame(true) => Event::Frame(t),
        };
        let r = match event {
            Event::Command(Some(Command::Budget(b))) => {
                session.set_budget(b);
                continue;
            }
            Event::Command(Some(Command::View(v))) => {
                session.set_view(v);
                continue;
            }
            Event::Command(Some(Command::Follow(v))) => {
                session.follow(v);
                continue;
            }
            Event::Command(Some(Command::Replay(c))) => {
                session.replay_control(c);
                continue;
            }
            Event::Command(Some(Command::Quit) | None) => break "quit".to_string(),
            Event::Frame(Err(e)) => break format!("{e:#}"),
            Event::Frame(Ok(Taken::Nothing)) => continue,
            Event::Frame(Ok(Taken::Dropped(_))) => {
                shared.dropped.fetch_add(1, Ordering::Relaxed);
                continue;
            }
            Event::Frame(Ok(Taken::Frame(r))) => r,
        };
        let started = Instant::now();
        let seen = MorphView::of_vehicle(
            &session.scene,
            &r.vehicles,
            session.vehicle(),
            session.fov_y_deg(),
            session.viewport()[1],
        );
        {
            let mut core = session.core();
            core.set_morph_view(seen);
            core.update_vertices(&session.scene, &mut terrain);
        }
        let update = terrain.take_update();
        let me = session.vehicle();
        let ground = match r.vehicles.iter().find(|v| v.id == me) {
            Some(v) => LocalGround::near(&terrain.corners, v.x as f32, v.z as f32, GROUND_RADIUS),
            None => LocalGround::default(),
        };
        let now = Instant::now();
        if !r.latencies_ms.is_empty() {
            let mut l = lock(&shared.latencies);
            l.extend(r.latencies_ms.iter().copied());
            while l.len() > 64 {
                l.pop_front();
            }
        }
        shared.frames.fetch_add(1, Ordering::Relaxed);
        let mut arrived = lock(&shared.arrived);
        // A frame the render thread has not taken yet: its changes go with this one's.
        let update = match arrived.take() {
            Some(older) => older
                .terrain
                .then(update)
                .unwrap_or_else(|| terrain.full_update()),
            None => update,
        };
        *arrived = Some(Arrived {
            frame: r.frame,
            tick: r.tick,
            vehicles: r.vehicles,
            terrain: update,
            ground,
            decode_ms: (r.decode_s + (now - started).as_secs_f64()) * 1e3,
            at: r.arrived,
        });
    };
    if ended == "quit" {
        let told = session.quit().await;
        *lock(&shared.connection) = Connection::Ended(if told {
            QUIT.into()
        } else {
            format!("{QUIT}, but the server did not acknowledge the goodbye")
        });
    } else {
        *lock(&shared.connection) = Connection::Ended(ended);
    }
}
