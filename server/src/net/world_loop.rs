//! The world thread: the one place the world lives, stepped at 100 Hz by its own clock. The
//! network hands it a closed set of [`Event`]s; it publishes a [`Snapshot`] after every
//! tick (latest value wins: nobody queues behind a slow reader).

use std::fs::File;
use std::io::BufWriter;
use std::path::Path;
use std::sync::Arc;
use std::sync::mpsc::{Receiver, RecvTimeoutError};
use std::time::{Duration, Instant};

use roam_protocol::messages::KeyState;
use tokio::sync::{oneshot, watch};

use crate::Terrain;
use crate::sim::physics::Keys;
use crate::sim::recording::{self, RecordedWorld};
use crate::sim::world::{self, InputLatch, Inputs, Vehicle, VehicleId, World};

/// What the network tells the world.
pub enum Event {
    /// A driver joins: it gets a vehicle of its own (the reply), at the next start slot.
    Join { reply: oneshot::Sender<VehicleId> },
    /// A driver left: its vehicle goes.
    Leave { vehicle: VehicleId },
}

/// The world after a tick.
#[derive(Clone, Debug, Default)]
pub struct Snapshot {
    pub tick: u64,
    pub vehicles: Vec<Vehicle>,
    /// Per vehicle, the newest key state applied by this tick.
    pub applied: Vec<(VehicleId, u32)>,
}

/// A driver's keys: new states queue up and the world takes one per tick, in order, so a
/// viewer sampling its keys every 10 ms drives exactly as `simulate` would, whatever the
/// network's jitter. A queue longer than [`MAX_QUEUED`] (a viewer's clock running fast)
/// is folded into the latch at once.
struct Driver {
    latch: InputLatch,
    /// The newest state received.
    seq: Option<u32>,
    queue: std::collections::VecDeque<(u32, Keys, Keys)>,
    /// The newest state applied.
    applied: Option<u32>,
    /// States are taken once [`PRIME`] have queued: a tick's worth of slack, so a state
    /// arriving a little late (jitter) is still there when its tick comes.
    primed: bool,
}

/// Key states queued before the world starts taking them.
const PRIME: usize = 2;

/// Key states a driver may have waiting (a third of a second): more than a stalled moment's
/// backlog, which the world catches up by stepping faster, keeps every state exact.
const MAX_QUEUED: usize = 32;

impl Driver {
    fn new() -> Driver {
        Driver {
            latch: InputLatch::default(),
            seq: None,
            queue: std::collections::VecDeque::new(),
            applied: None,
            primed: false,
        }
    }

    fn apply(&mut self, (seq, held, pressed): (u32, Keys, Keys)) {
        self.latch.press(pressed);
        self.latch.set_held(held);
        self.applied = Some(seq);
    }

    /// The keys for the next tick.
    fn take(&mut self) -> Keys {
        self.primed |= self.queue.len() >= PRIME;
        if !self.primed {
            return self.latch.take();
        }
        while self.queue.len() > MAX_QUEUED {
            let s = self.queue.pop_front().expect("longer than MAX_QUEUED");
            self.apply(s);
        }
        if let Some(s) = self.queue.pop_front() {
            self.apply(s);
        }
        self.latch.take()
    }
}

enum Stepper {
    Plain(World),
    Recorded(RecordedWorld<Arc<Terrain>, BufWriter<File>>),
}

/// Runs the world until `events` closes, then closes the recording. Returns the final
/// world.
/// Key states from a driver's datagram (any order, repeats allowed), on a bounded channel
/// of their own: when it is full the network drops datagrams (their states come again in
/// later ones), so a flood cannot grow memory or starve the ticks.
pub type KeyStates = (VehicleId, Vec<KeyState>);

/// How many key datagrams may wait for the world.
pub const KEY_BACKLOG: usize = 1024;

pub fn run(
    terrain: Arc<Terrain>,
    record: Option<&Path>,
    events: Receiver<Event>,
    keys: Receiver<KeyStates>,
    snapshots: watch::Sender<Arc<Snapshot>>,
) -> std::io::Result<World> {
    let world = World::new(terrain.clone());
    let mut stepper = match record {
        Some(path) => Stepper::Recorded(RecordedWorld::start(
            world,
            BufWriter::new(File::create(path)?),
            terrain.content_hash(),
            recording::MAX_CHECKPOINT_INTERVAL,
        )?),
        None => Stepper::Plain(world),
    };
    let mut drivers: Vec<(VehicleId, Driver)> = Vec::new();
    let mut next_id = 0u16;
    // The start slot of each driven vehicle: a leaver's slot is given to the next joiner.
    let mut slots: Vec<(VehicleId, u32)> = Vec::new();
    let mut inputs = Inputs::new();
    let tick = Duration::from_millis(10);
    let mut due = Instant::now() + tick;
    loop {
        // Events until the tick is due.
        loop {
            let wait = due.saturating_duration_since(Instant::now());
            if wait.is_zero() {
                break; // the tick is due: events wait for the next one
            }
            let event = match events.recv_timeout(wait) {
                Ok(e) => e,
                Err(RecvTimeoutError::Timeout) => break,
                Err(RecvTimeoutError::Disconnected) => return finish(stepper),
            };
            match event {
                Event::Join { reply } => {
                    // The next id not in use (ids wrap after 65,536 joins; with every id
                    // taken the join is refused by dropping the reply).
                    let Some(id) =
                        free_id(&mut next_id, |id| drivers.iter().any(|(v, _)| *v == id))
                    else {
                        continue;
                    };
                    let slot = (0u32..)
                        .find(|s| slots.iter().all(|(_, t)| t != s))
                        .expect("fewer than 2^32 vehicles");
                    let state = world::start_state(&terrain, slot);
                    let joined = match &mut stepper {
                        Stepper::Plain(w) => w.add(id, state).is_ok(),
                        Stepper::Recorded(r) => r.join(id, state).is_ok(),
                    };
                    if !joined {
                        continue;
                    }
                    if reply.send(id).is_ok() {
                        drivers.push((id, Driver::new()));
                        slots.push((id, slot));
                    } else {
                        // The viewer went away while joining: no vehicle left behind.
                        let _gone = match &mut stepper {
                            Stepper::Plain(w) => w.remove(id).is_ok(),
                            Stepper::Recorded(r) => r.leave(id).is_ok(),
                        };
                    }
                }
                Event::Leave { vehicle } => {
                    drivers.retain(|(v, _)| *v != vehicle);
                    slots.retain(|(v, _)| *v != vehicle);
                    // A vehicle that is not there (a repeated leave) changes nothing.
                    let _gone = match &mut stepper {
                        Stepper::Plain(w) => w.remove(vehicle).is_ok(),
                        Stepper::Recorded(r) => r.leave(vehicle).is_ok(),
                    };
                }
            }
        }
        // The key states that arrived, oldest first (bounded by the channel).
        while let Ok((vehicle, mut states)) = keys.try_recv() {
            let Some((_, d)) = drivers.iter_mut().find(|(v, _)| *v == vehicle) else {
                continue;
            };
            states.sort_by_key(|s| s.seq);
            for s in states {
                if d.seq.is_some_and(|seq| s.seq <= seq) {
                    continue; // seen already
                }
                let (Some(held), Some(pressed)) =
                    (Keys::from_bits(s.held), Keys::from_bits(s.pressed))
                else {
                    continue; // not keys: ignore the state
                };
                d.queue.push_back((s.seq, held, pressed));
                d.seq = Some(s.seq);
            }
        }
        // The tick: every driver's keys since the last one, then one step.
        inputs.clear();
        for (id, d) in &mut drivers {
            inputs.set(*id, d.take());
        }
        let w = match &mut stepper {
            Stepper::Plain(w) => {
                world::step(w, &inputs);
                &*w
            }
            Stepper::Recorded(r) => {
                r.step(&inputs)?;
                r.world()
            }
        };
        let snapshot = Snapshot {
            tick: w.tick(),
            vehicles: w.vehicles().to_vec(),
            applied: drivers
                .iter()
                .filter_map(|(id, d)| d.applied.map(|s| (*id, s)))
                .collect(),
        };
        snapshots.send_replace(Arc::new(snapshot));
        due += tick;
        let now = Instant::now();
        if now > due + Duration::from_millis(250) {
            // Far behind (the machine stalled): skip the backlog rather than race.
            due = now + tick;
        }
    }
}

fn finish(stepper: Stepper) -> std::io::Result<World> {
    match stepper {
        Stepper::Plain(w) => Ok(w),
        Stepper::Recorded(r) => Ok(r.finish()?.0),
    }
}

/// The first id from `next` on (wrapping) that is not `taken`, and `next` moved past it;
/// `None` when all 65,536 are taken.
fn free_id(next: &mut u16, taken: impl Fn(u16) -> bool) -> Option<u16> {
    for _ in 0..=u16::MAX {
        let id = *next;
        *next = next.wrapping_add(1);
        if !taken(id) {
            return Some(id);
        }
    }
    None
}

#[cfg(test)]
mod tests {
    use super::free_id;

    #[test]
    fn ids_wrap_and_skip_those_in_use() {
        let mut next = u16::MAX;
        assert_eq!(free_id(&mut next, |id| id == u16::MAX), Some(0));
        assert_eq!(next, 1);
        let mut next = 65_534;
        let in_use = [65_534, 65_535, 0, 1];
        assert_eq!(free_id(&mut next, |id| in_use.contains(&id)), Some(2));
        assert_eq!(free_id(&mut next, |_| true), None);
    }
}
