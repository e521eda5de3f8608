//! The frame clock's viewers ([`FrameClock`]): each a [`Served`], its [`Conversation`]
//! with the connection it is sent on and what the shell hears of it, and the phase each
//! new viewer's frames fall on. What the clock does with them is in [`super::frames`];
//! this file comes before [`super::shared`], which holds the clock, so that neither
//! refers to the other in a circle.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use roam_protocol::messages::Hello;
use roam_protocol::sync::lock;
use tokio::sync::{Notify, oneshot, watch};

use super::conn::Conn;
use crate::sim::world::VehicleId;
use crate::viewer::ViewerLimits;
use crate::viewer::conversation::Conversation;

/// Why a viewer's frames stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum FramesEnd {
    /// The vehicle it followed (or drove) is gone.
    VehicleLeft,
    /// The connection can take no more streams, or is gone.
    ConnectionLost,
    /// The server could not make a frame: said to the viewer, never a panic.
    Failed(&'static str),
}

/// One viewer on the clock.
pub(super) struct Served {
    pub conv: Mutex<Conversation>,
    pub conn: Conn,
    /// The budget it may have for one it asks (within the limits): as far as its seat
    /// can grow within the server's memory. Holds the seat, released when this goes.
    pub grant: Mutex<Box<dyn FnMut(u32) -> u32 + Send>>,
    /// Frames made (the colour task starts once the first is).
    pub sent: watch::Sender<u64>,
    /// The vehicle followed (the colour task streams around it; a spectator is told).
    pub follow: watch::Sender<VehicleId>,
    /// Watching a recording: this viewer's place among those sharing its clock.
    pub(super) replay: Option<u64>,
    /// Frames on streams of their own, by frame.
    pub(super) streams: Mutex<Vec<(u64, oneshot::Sender<()>)>>,
    /// Told once, when the frames end.
    pub(super) end: Mutex<Option<oneshot::Sender<FramesEnd>>>,
    /// The connection's bytes sent when last counted.
    pub(super) bytes_out: AtomicU64,
}

impl Served {
    /// A viewer to serve; `end` hears why its frames stopped.
    pub(super) fn new(
        conv: Conversation,
        conn: Conn,
        grant: Box<dyn FnMut(u32) -> u32 + Send>,
        replay: Option<u64>,
        end: oneshot::Sender<FramesEnd>,
    ) -> Served {
        let vehicle = conv.vehicle();
        let bytes_out = conn.quic().stats().udp_tx.bytes;
        Served {
            conv: Mutex::new(conv),
            conn,
            grant: Mutex::new(grant),
            sent: watch::channel(0).0,
            follow: watch::channel(vehicle).0,
            replay,
            streams: Mutex::new(Vec::new()),
            end: Mutex::new(Some(end)),
            bytes_out: AtomicU64::new(bytes_out),
        }
    }

    pub(super) fn ended(&self) -> bool {
        lock(&self.end).is_none()
    }

    pub(super) fn stop(&self, why: FramesEnd) {
        if let Some(tx) = lock(&self.end).take() {
            let _ = tx.send(why);
        }
    }
}

/// Phases of the frame period the viewers are spread over.
const PHASES: u32 = 16;

/// The clock's viewers, and its alarm for a new one.
pub(super) struct FrameClock {
    pub(super) viewers: Mutex<Vec<Arc<Served>>>,
    /// Wakes the clock: a viewer joined (its first frame is due: the clock makes it after
    /// the served viewers' frames and the earlier joiners' first frames, one a pass), or a
    /// heavy frame came back (the viewer's next one is due on its grid).
    pub(super) wake: Notify,
    /// The grid every phase is counted from.
    origin: Instant,
    /// Viewers put on a phase so far.
    phased: AtomicU64,
}

impl Default for FrameClock {
    fn default() -> FrameClock {
        FrameClock {
            viewers: Mutex::default(),
            wake: Notify::new(),
            origin: Instant::now(),
            phased: AtomicU64::new(0),
        }
    }
}

impl FrameClock {
    /// Where the next viewer's frames fall (`origin + k·period`, [`Conversation::new`]):
    /// on one of [`PHASES`] phases of its period, in turn.
    pub(super) fn origin(&self, hello: &Hello, limits: ViewerLimits) -> Instant {
        let period = Conversation::period(hello, limits);
        let n = self.phased.fetch_add(1, Ordering::Relaxed) % u64::from(PHASES);
        self.origin + period * n as u32 / PHASES
    }

    /// Puts a viewer on the clock: its first frame is due at once (made in its turn, one
    /// a pass: `net/frames.rs`).
    pub(super) fn add(&self, served: Arc<Served>) {
        lock(&self.viewers).push(served);
        self.wake.notify_one();
    }

    /// Takes a viewer off (its frames, and any job of its, are let go).
    pub(super) fn remove(&self, served: &Arc<Served>) {
        served.stop(FramesEnd::ConnectionLost);
        // The seat goes now, not when the last job holding the viewer ends.
        *lock(&served.grant) = Box::new(|budget| budget);
        lock(&self.viewers).retain(|s| !Arc::ptr_eq(s, served));
    }
}
