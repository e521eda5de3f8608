//! The world thread: it owns the [`WorldCore`] and only paces it. Every 10 ms by this
//! thread's clock it wakes, hands the core the events from the network that came since
//! (the thread sleeps between: a key datagram wakes nobody), and the core
//! ticks, and the snapshot is published in a `watch` (latest value wins: nobody queues
//! behind a slow reader).
//!
//! The loop never ends on its own account: the core's recording reports its failures as
//! notices, which are logged here (`tracing`: errors as errors, rotation as info, joins
//! after a failed recording as warnings), and the world goes on. [`WorldStats`] counts the
//! ticks made, those dropped when the thread fell more than 250 ms behind, and those that
//! started more than a tick late, for the shell and the load tests to read.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, TryRecvError};
use std::time::{Duration, Instant};

use roam_protocol::sync::lock;
use tokio::sync::{oneshot, watch};

use crate::sim::physics::STEPS_PER_SECOND;
use crate::sim::session::Notice;
use crate::sim::world::{VehicleId, World};
use crate::sim::world_core::{Event, Snapshot, WorldCore};

/// An event for the world, and where a join's or a resume's answer goes (a dropped sender
/// refuses it).
pub type Inbound = (Event, Option<oneshot::Sender<VehicleId>>);

/// Events handled at most between two ticks: a flood waits for the next tick rather than
/// starving this one (each viewer's key datagrams are rate-limited before they get here).
const MAX_EVENTS_PER_TICK: usize = 4096;

/// Behind by more than this, the loop skips the backlog rather than race through it.
const MAX_BEHIND: Duration = Duration::from_millis(250);

/// How the world thread keeps time, counted as it goes (read from any thread).
#[derive(Debug, Default)]
pub struct WorldStats {
    ticks: AtomicU64,
    dropped: AtomicU64,
    late: AtomicU64,
    /// Held vehicles joins freed at the limit ([`WorldCore::take_evicted`]), put here
    /// before the join that freed them is answered, for the shell to forget their tickets.
    evicted: std::sync::Mutex<Vec<VehicleId>>,
}

impl WorldStats {
    /// Ticks made.
    pub fn ticks(&self) -> u64 {
        self.ticks.load(Ordering::Relaxed)
    }

    /// Ticks skipped because the thread was more than 250 ms behind (never made).
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }

    /// Ticks made that started more than one tick after they were due.
    pub fn late(&self) -> u64 {
        self.late.load(Ordering::Relaxed)
    }

    /// The held vehicles joins freed since the last call.
    pub fn take_evicted(&self) -> Vec<VehicleId> {
        std::mem::take(&mut *lock(&self.evicted))
    }
}

/// The world's ticks in `hold` (for [`WorldCore::with_hold`]).
pub fn hold_ticks(hold: Duration) -> u64 {
    let ms = u64::try_from(hold.as_millis()).unwrap_or(u64::MAX);
    ms / (1000 / u64::from(STEPS_PER_SECOND))
}

/// The wall clock in Unix seconds (recording file names: see
/// [`crate::sim::record_files::RecordDir`]); 0 on a clock set before 1970.
pub fn unix_seconds() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs())
}

/// Logs what happened to the recording.
pub fn log(notice: &Notice) {
    match notice {
        Notice::Failed { .. } | Notice::CreateFailed { .. } => tracing::error!("{notice}"),
        Notice::JoinedUnrecorded { .. } => tracing::warn!("{notice}"),
        Notice::Started { .. } | Notice::Rotated { .. } | Notice::Closed { .. } => {
            tracing::info!("{notice}")
        }
    }
}

fn log_all(core: &mut WorldCore) {
    for n in core.notices() {
        log(&n);
    }
}

/// The world thread, started: a [`WorldCore`] of `terrain` recording to `record`, holding
/// a dropped driver's vehicle `hold`, with at most `limit` vehicles (held ones included;
/// `hard`: a join past it refused, [`WorldCore::refusing_past_limit`]), [`run`] on a
/// thread of its own. Both `serve` and `roam-server world` start it so.
pub fn start(
    terrain: Arc<crate::Terrain>,
    record: Option<crate::sim::session::RecordOptions>,
    (hold, limit, hard): (Duration, usize, bool),
    inbox: Receiver<Inbound>,
    snapshots: watch::Sender<Arc<Snapshot>>,
    stats: Arc<WorldStats>,
) -> std::io::Result<std::thread::JoinHandle<World>> {
    let core = WorldCore::new(terrain, record)?
        .with_hold(hold_ticks(hold))
        .with_limit(limit);
    let core = if hard {
        core.refusing_past_limit()
    } else {
        core
    };
    std::thread::Builder::new()
        .name("roam-world".into())
        .spawn(move || run(core, inbox, snapshots, &stats))
}

/// Runs the world until `inbox` closes, then finishes the recording. Returns the final
/// world.
pub fn run(
    mut core: WorldCore,
    inbox: Receiver<Inbound>,
    snapshots: watch::Sender<Arc<Snapshot>>,
    stats: &WorldStats,
) -> World {
    let handle = |core: &mut WorldCore, (event, reply): Inbound| {
        let resume = matches!(event, Event::Resume(_));
        let answer = core.handle(event);
        let evicted = core.take_evicted();
        if !evicted.is_empty() {
            let mut list = lock(&stats.evicted);
            list.extend(evicted);
        }
        if let (Some(id), Some(reply)) = (answer, reply)
            && reply.send(id).is_err()
        {
            // The viewer went away while joining (no vehicle left behind) or resuming
            // (held again, for a later try).
            core.handle(if resume {
                Event::Hold {
                    vehicle: id,
                    silent: 0,
                }
            } else {
                Event::Leave(id)
            });
        }
        log_all(core);
    };
    log_all(&mut core);
    let mut pacer = Pacer::new();
    loop {
        // Asleep until the tick is due, then the events that came meanwhile, in order: a
        // key datagram does not wake this thread (every driver sends 100 a second; woken
        // for each, 50 drivers cost 5,000 wake-ups and thread switches a second on the
        // server's core), and an event belongs to the tick it arrived before either way.
        // A join's answer waits for the tick (at most 10 ms; its vehicle appears with the
        // tick's snapshot anyway).
        pacer.wait();
        for _ in 0..MAX_EVENTS_PER_TICK {
            match inbox.try_recv() {
                Ok(inbound) => handle(&mut core, inbound),
                Err(TryRecvError::Empty) => break,
                Err(TryRecvError::Disconnected) => {
                    let (world, notices) = core.finish();
                    notices.iter().for_each(log);
                    return world;
                }
            }
        }
        pacer.begin(stats);
        let snapshot = core.tick();
        log_all(&mut core);
        snapshots.send_replace(Arc::new(snapshot));
        pacer.made(stats);
    }
}

/// The world thread's clock: a tick every 10 ms by this thread's clock, the late ones
/// and the skipped ones counted in [`WorldStats`] (a replay's thread keeps time with it
/// too, [`super::replay`]).
pub(super) struct Pacer {
    tick: Duration,
    due: Instant,
}

impl Pacer {
    pub(super) fn new() -> Pacer {
        let tick = Duration::from_millis(1000 / u64::from(STEPS_PER_SECOND));
        Pacer {
            tick,
            due: Instant::now() + tick,
        }
    }

    /// Sleeps until the next tick is due (not at all when it is).
    pub(super) fn wait(&self) {
        let wait = self.due.saturating_duration_since(Instant::now());
        if !wait.is_zero() {
            std::thread::sleep(wait);
        }
    }

    /// The tick begins: counted late if more than a tick after it was due.
    pub(super) fn begin(&self, stats: &WorldStats) {
        if Instant::now() > self.due + self.tick {
            stats.late.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// The tick was made: the next is due a tick on, or, far behind (the machine
    /// stalled), a tick from now, the backlog skipped rather than raced through.
    pub(super) fn made(&mut self, stats: &WorldStats) {
        stats.ticks.fetch_add(1, Ordering::Relaxed);
        self.due += self.tick;
        let now = Instant::now();
        let skipped = skipped(self.due, now, self.tick);
        if skipped > 0 {
            stats.dropped.fetch_add(skipped, Ordering::Relaxed);
            self.due = now + self.tick;
        }
    }
}

/// Ticks to skip with the next one `due` at `now`: none unless more than [`MAX_BEHIND`]
/// late, else every tick due by now (the next is made a tick from now).
fn skipped(due: Instant, now: Instant, tick: Duration) -> u64 {
    if now <= due + MAX_BEHIND {
        return 0;
    }
    let behind = (now - due).as_nanos() / tick.as_nanos().max(1);
    u64::try_from(behind).unwrap_or(u64::MAX).saturating_add(1)
}

#[cfg(test)]
mod tests {
    use std::time::{Duration, Instant};

    use super::{hold_ticks, skipped};

    #[test]
    fn the_backlog_skipped_is_every_tick_due() {
        let tick = Duration::from_millis(10);
        let due = Instant::now();
        let at = |ms| due + Duration::from_millis(ms);
        assert_eq!(skipped(due, at(0), tick), 0);
        assert_eq!(skipped(due, at(250), tick), 0, "250 ms behind is caught up");
        // 251 ms late: the ticks due at 0, 10, … 250 ms are never made.
        assert_eq!(skipped(due, at(251), tick), 26);
        assert_eq!(skipped(due, at(1000), tick), 101);
        assert_eq!(skipped(at(5), due, tick), 0, "early");
    }

    #[test]
    fn holds_in_ticks() {
        assert_eq!(hold_ticks(Duration::from_secs(30)), 3000);
        assert_eq!(hold_ticks(Duration::from_millis(15)), 1);
        assert_eq!(hold_ticks(Duration::ZERO), 0);
    }
}
