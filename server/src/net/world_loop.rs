//! The world thread: it owns the [`WorldCore`] and only paces it. Events from the network
//! are handed to the core as they arrive; every 10 ms by this thread's clock the core
//! ticks, and the snapshot is published in a `watch` (latest value wins: nobody queues
//! behind a slow reader).

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use tokio::sync::{oneshot, watch};

use crate::Terrain;
use crate::sim::world::{VehicleId, World};
use crate::sim::world_core::{Event, Snapshot, WorldCore};

/// An event for the world, and where a join's answer goes (a dropped sender refuses it).
pub type Inbound = (Event, Option<oneshot::Sender<VehicleId>>);

/// Events handled at most between two ticks: a flood waits for the next tick rather than
/// starving this one (each viewer's key datagrams are rate-limited before they get here).
const MAX_EVENTS_PER_TICK: usize = 4096;

/// Runs the world until `inbox` closes, then closes the recording. Returns the final
/// world.
pub fn run(
    terrain: Arc<Terrain>,
    record: Option<&Path>,
    inbox: Receiver<Inbound>,
    snapshots: watch::Sender<Arc<Snapshot>>,
) -> std::io::Result<World> {
    let out = match record {
        Some(path) => Some(BufWriter::new(File::create(path)?)),
        None => None,
    };
    let mut core = WorldCore::new(terrain, out)?;
    let handle = |core: &mut WorldCore<BufWriter<File>>, (event, reply): Inbound| {
        let joined = core.handle(event);
        if let (Some(id), Some(reply)) = (joined, reply)
            && reply.send(id).is_err()
        {
            // The viewer went away while joining: no vehicle left behind.
            core.handle(Event::Leave(id));
        }
    };
    let tick = Duration::from_millis(10);
    let mut due = Instant::now() + tick;
    loop {
        // Events as they come until the tick is due.
        loop {
            let wait = due.saturating_duration_since(Instant::now());
            if wait.is_zero() {
                break;
            }
            match inbox.recv_timeout(wait) {
                Ok(inbound) => handle(&mut core, inbound),
                Err(RecvTimeoutError::Timeout) => break,
                Err(RecvTimeoutError::Disconnected) => return Ok(core.finish()?.0),
            }
        }
        // What arrived while the tick came due belongs to this tick.
        for inbound in inbox.try_iter().take(MAX_EVENTS_PER_TICK) {
            handle(&mut core, inbound);
        }
        let snapshot = core.tick()?;
        snapshots.send_replace(Arc::new(snapshot));
        due += tick;
        let now = Instant::now();
        if now > due + Duration::from_millis(250) {
            // Far behind (the machine stalled): skip the backlog rather than race.
            due = now + tick;
        }
    }
}
