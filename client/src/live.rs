//! The window's network task: it keeps a [`Session`] going on the async runtime, sends the
//! key latch every physics step, decodes the newest frame and builds its vertices, and
//! leaves the result for the render thread, which never waits on the network.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use roam_protocol::messages::VehicleView;
use roam_server::sim::physics::Keys;
use tokio::sync::mpsc;

use crate::camera::LocalGround;
use crate::render::TerrainVertices;
use crate::session::{self, Latency, Session, Taken};

/// What the render thread asks of the network task.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Command {
    /// A new triangle budget.
    Budget(u32),
    /// The camera the server should tessellate for.
    View(roam_protocol::messages::ViewChange),
    /// Say goodbye and stop.
    Quit,
}

/// A frame decoded and ready to draw.
#[derive(Debug)]
pub struct Arrived {
    pub frame: u64,
    pub tick: u64,
    pub vehicles: Vec<VehicleView>,
    pub terrain: TerrainVertices,
    /// The drawn ground around the followed vehicle, for the camera.
    pub ground: LocalGround,
    /// Decoding, emitting and building the vertices, milliseconds.
    pub decode_ms: f64,
    pub at: Instant,
}

/// Keys as the window saw them: held now, and pressed since the last physics step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct KeyLatch {
    pub held: Keys,
    pub pressed: Keys,
}

impl KeyLatch {
    pub fn down(&mut self, k: Keys) {
        self.held = self.held.union(k);
        self.pressed = self.pressed.union(k);
    }

    pub fn up(&mut self, k: Keys) {
        self.held = self.held.without(k);
    }

    /// This step's state; a press, however short, is in exactly one step.
    pub fn take(&mut self) -> (Keys, Keys) {
        let out = (self.held, self.pressed);
        self.pressed = Keys::NONE;
        out
    }
}

/// How a session that quit ends: [`Link::Ended`] with this, and more when the goodbye
/// was not heard.
pub const QUIT: &str = "quit";

/// The connection's state, in words for the HUD.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Link {
    Connected,
    Ended(String),
}

/// What the network task and the render thread share.
#[derive(Debug)]
pub struct Shared {
    pub arrived: Mutex<Option<Arrived>>,
    pub keys: Mutex<KeyLatch>,
    pub link: Mutex<Link>,
    /// Bytes of frames received.
    pub bytes_in: Arc<AtomicU64>,
    /// Frames taken from the stream and decoded.
    pub frames: AtomicU64,
    /// Frames that could not be decoded (a key frame was asked for).
    pub dropped: AtomicU64,
    /// Recent input→frame latencies, milliseconds.
    pub latencies: Mutex<VecDeque<f64>>,
    /// The vehicle the camera rides.
    pub vehicle: u16,
    /// Ctrl-C was pressed in the terminal.
    pub interrupted: std::sync::atomic::AtomicBool,
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl Shared {
    pub fn take_arrived(&self) -> Option<Arrived> {
        lock(&self.arrived).take()
    }

    pub fn link(&self) -> Link {
        lock(&self.link).clone()
    }

    pub fn key_down(&self, k: Keys) {
        lock(&self.keys).down(k);
    }

    pub fn key_up(&self, k: Keys) {
        lock(&self.keys).up(k);
    }

    /// Every key released (the window lost focus: nothing stays held).
    pub fn keys_released(&self) {
        let mut k = lock(&self.keys);
        k.held = Keys::NONE;
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
    driver: bool,
) -> (
    Arc<Shared>,
    mpsc::UnboundedSender<Command>,
    tokio::task::JoinHandle<()>,
) {
    let shared = Arc::new(Shared {
        arrived: Mutex::new(None),
        keys: Mutex::new(KeyLatch::default()),
        link: Mutex::new(Link::Connected),
        bytes_in: session.bytes_in.clone(),
        frames: AtomicU64::new(0),
        dropped: AtomicU64::new(0),
        latencies: Mutex::new(VecDeque::new()),
        vehicle: session.welcome.vehicle,
        interrupted: std::sync::atomic::AtomicBool::new(false),
    });
    let (tx, rx) = mpsc::unbounded_channel();
    // Ctrl-C in the terminal quits as `q` does: the server is told.
    let quit = tx.clone();
    let interrupted = shared.clone();
    runtime.spawn(async move {
        if tokio::signal::ctrl_c().await.is_ok() {
            interrupted.interrupted.store(true, Ordering::Relaxed);
            let _ = quit.send(Command::Quit);
            // A second Ctrl-C does not wait for anything.
            if tokio::signal::ctrl_c().await.is_ok() {
                std::process::exit(130);
            }
        }
    });
    let task = runtime.spawn(run(session, shared.clone(), rx, driver));
    (shared, tx, task)
}

enum Event {
    Command(Option<Command>),
    Waiting(anyhow::Result<()>),
}

async fn run(
    mut session: Session,
    shared: Arc<Shared>,
    mut commands: mpsc::UnboundedReceiver<Command>,
    driver: bool,
) {
    let latency = Arc::new(Latency::default());
    let keys = driver.then(|| {
        let shared = shared.clone();
        tokio::spawn(session::play(
            session.conn.clone(),
            move || Some(lock(&shared.keys).take()),
            latency.clone(),
        ))
    });
    let mut lat = Vec::new();
    let ended = loop {
        let event = tokio::select! {
            c = commands.recv() => Event::Command(c),
            w = session.wait() => Event::Waiting(w),
        };
        match event {
            Event::Command(Some(Command::Budget(b))) => {
                if let Err(e) = session.set_budget(b).await {
                    break format!("{e:#}");
                }
                continue;
            }
            Event::Command(Some(Command::View(v))) => {
                if let Err(e) = session.set_view(v).await {
                    break format!("{e:#}");
                }
                continue;
            }
            Event::Command(Some(Command::Quit) | None) => break "quit".to_string(),
            Event::Waiting(Err(e)) => break format!("{e:#}"),
            Event::Waiting(Ok(())) => {}
        }
        let r = match session.take(true).await {
            Ok(Taken::Frame(r)) => r,
            Ok(Taken::Nothing) => continue,
            Ok(Taken::Dropped) => {
                shared.dropped.fetch_add(1, Ordering::Relaxed);
                continue;
            }
            Err(e) => break format!("{e:#}"),
        };
        let started = Instant::now();
        let mut terrain = TerrainVertices::default();
        terrain.build(&session.scene, &session.mesh);
        let ground = match r.vehicles.iter().find(|v| v.id == shared.vehicle) {
            Some(v) => LocalGround::near(&terrain.corners, v.x as f32, v.z as f32, GROUND_RADIUS),
            None => LocalGround::default(),
        };
        let now = Instant::now();
        if let Some(seq) = r.input_seq {
            lat.clear();
            latency.applied(seq, now, &mut lat);
            let mut l = lock(&shared.latencies);
            l.extend(lat.iter().copied());
            while l.len() > 64 {
                l.pop_front();
            }
        }
        shared.frames.fetch_add(1, Ordering::Relaxed);
        *lock(&shared.arrived) = Some(Arrived {
            frame: r.frame,
            tick: r.tick,
            vehicles: r.vehicles,
            terrain,
            ground,
            decode_ms: (r.decode_s + (now - started).as_secs_f64()) * 1e3,
            at: r.arrived,
        });
    };
    if let Some(k) = keys {
        k.abort();
    }
    if ended == "quit" {
        let told = session.quit().await;
        *lock(&shared.link) = Link::Ended(if told {
            QUIT.into()
        } else {
            format!("{QUIT}, but the server did not acknowledge the goodbye")
        });
    } else {
        *lock(&shared.link) = Link::Ended(ended);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_press_released_before_the_step_is_still_sent_once() {
        let mut k = KeyLatch::default();
        k.down(Keys::UP);
        k.up(Keys::UP);
        assert_eq!(k.take(), (Keys::NONE, Keys::UP));
        assert_eq!(k.take(), (Keys::NONE, Keys::NONE));
        k.down(Keys::LEFT);
        assert_eq!(k.take(), (Keys::LEFT, Keys::LEFT));
        assert_eq!(k.take(), (Keys::LEFT, Keys::NONE));
    }
}
