//! The world's decisions, with no clock, channel or thread (as `quinn-proto` is to `quinn`):
//! who joins and where they start, which vehicle id they get, each driver's queue of key
//! states, who leaves, and the snapshot after each tick. [`WorldCore::handle`] takes the one
//! closed set of [`Event`]s the network produces; [`WorldCore::tick`] advances the world
//! one 10 ms step. The server's world thread (`net::world_loop`) only paces it; the
//! simulated network in the tests drives it by virtual time.
//!
//! **A tick, in order:**
//!
//! 1. Events that arrived since the last tick have been handled in arrival order (joins
//!    take the lowest free start slot and the next free id; leaves free both; key states
//!    are queued per driver by sequence number, repeats and stale ones dropped).
//! 2. Each driver takes its steps for the tick, one physics step per key state, in order:
//!    - until [`PRIME`] states have queued (a tick of slack for jitter), or when its queue
//!      has run dry (a state lost and not yet repeated, or late), its vehicle **waits**: no
//!      step this tick, so its drive is delayed, never changed;
//!    - with more than [`PRIME`] + [`CATCH_UP`] queued (a backlog after a wait or a
//!      stall), it steps **twice**, one step per state, until the backlog is gone;
//!    - otherwise one step, with the oldest queued state folded into the driver's latch;
//!    - a queue longer than [`MAX_QUEUED`] (a viewer whose clock runs fast) is folded into
//!      the latch at once: the only case where a drive is not step for step the script's.
//! 3. The world steps (and the recording takes the tick's inputs, joins and leaves).
//! 4. The snapshot: tick, every vehicle, and each driver's newest applied key state (the
//!    viewer measures input→frame latency from it).
//!
//! **Why the world keeps a queue rather than the latest state:** a viewer samples its keys
//! every 10 ms, the physics' step, and numbers them. Applying them one step each, in
//! order, waiting when the next has not come and catching up two a tick after, makes a
//! remote drive step for step the drive `simulate` makes from the same script, whatever
//! the network's jitter or loss (a datagram repeats the last 8 states, so a state is lost
//! only if 8 datagrams in a row are). Before waits, a late state made the vehicle repeat
//! the last keys for a tick and the drive differed (the simulated network showed it at 10 %
//! loss with 20 ms of delay on every seed).

use std::collections::VecDeque;
use std::io::{self, Write};
use std::sync::Arc;

use roam_protocol::keys::{KeyLatch, KeyStep, Keys};
use roam_protocol::messages::KeyState;

use crate::Terrain;
use crate::sim::recording::{self, RecordedWorld};
use crate::sim::world::{self, Extra, Inputs, Vehicle, VehicleId, World};

/// What the network tells the world.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Event {
    /// A driver joins: it gets a vehicle of its own at the next free start slot, or
    /// nothing when every id is taken ([`WorldCore::handle`] says which).
    Join,
    /// A driver left (or its join was abandoned): its vehicle goes. A vehicle that is not
    /// there changes nothing.
    Leave(VehicleId),
    /// TEMPORARY (replaced by the records branch): a lost connection's vehicle.
    Hold(VehicleId),
    /// TEMPORARY (replaced by the records branch): take a held vehicle back.
    Resume(VehicleId),
    /// A driver's key states, from one datagram: any order, repeats allowed.
    Keys {
        vehicle: VehicleId,
        states: Vec<KeyState>,
    },
}

/// The world after a tick.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Snapshot {
    pub tick: u64,
    pub vehicles: Vec<Vehicle>,
    /// Per driver, the newest key state applied by this tick.
    pub applied: Vec<(VehicleId, u32)>,
}

impl Snapshot {
    /// The newest key state of `vehicle` applied by this tick.
    pub fn applied_by(&self, vehicle: VehicleId) -> Option<u32> {
        self.applied
            .iter()
            .find(|(id, _)| *id == vehicle)
            .map(|&(_, s)| s)
    }
}

/// Key states queued before the world starts taking them: a tick's worth of slack, so a
/// state arriving a little late is still there when its tick comes.
pub const PRIME: usize = 2;

/// Key states queued beyond [`PRIME`] before a driver catches up, two steps a tick: a
/// little more slack, so ordinary jitter does not make a vehicle alternate waits and
/// double steps.
pub const CATCH_UP: usize = 2;

/// Key states a driver may have waiting (a third of a second): a longer backlog is folded
/// into the latch at once, so a fast clock cannot delay a driver's keys without bound.
pub const MAX_QUEUED: usize = 32;

/// One driver's keys: the states received and not yet applied, oldest first.
struct Driver {
    id: VehicleId,
    /// The start slot its vehicle took (given to the next joiner when it leaves).
    slot: u32,
    latch: KeyLatch,
    /// The newest state received.
    received: Option<u32>,
    queue: VecDeque<(u32, KeyStep)>,
    /// The newest state applied.
    applied: Option<u32>,
    primed: bool,
}

impl Driver {
    fn apply(&mut self, (seq, step): (u32, KeyStep)) {
        self.latch.apply(step);
        self.applied = Some(seq);
    }

    /// The vehicle's steps for the next tick (step 2 of the tick), into `inputs`.
    fn take(&mut self, inputs: &mut Inputs) {
        self.primed |= self.queue.len() >= PRIME;
        if !self.primed || self.queue.is_empty() {
            inputs.set_extra(self.id, Extra::Wait);
            return;
        }
        while self.queue.len() > MAX_QUEUED {
            let s = self.queue.pop_front().expect("longer than MAX_QUEUED");
            self.apply(s);
        }
        let first = self.step();
        inputs.set(self.id, first);
        if self.queue.len() >= PRIME + CATCH_UP {
            let second = self.step();
            inputs.set_extra(self.id, Extra::Twice(first, second));
        }
    }

    /// One physics step's keys: the oldest queued state, folded into the latch.
    fn step(&mut self) -> Keys {
        if let Some(s) = self.queue.pop_front() {
            self.apply(s);
        }
        self.latch.take().active()
    }

    fn receive(&mut self, mut states: Vec<KeyState>) {
        states.sort_by_key(|s| s.seq);
        for s in states {
            if self.received.is_some_and(|seq| s.seq <= seq) {
                continue; // seen already
            }
            let (Some(held), Some(pressed)) = (Keys::from_bits(s.held), Keys::from_bits(s.pressed))
            else {
                continue; // not keys: the state is ignored
            };
            self.queue.push_back((s.seq, KeyStep { held, pressed }));
            self.received = Some(s.seq);
        }
        // A flood (more than a backlog's worth at once) folds as a long queue would.
        while self.queue.len() > 2 * MAX_QUEUED {
            let s = self.queue.pop_front().expect("longer than 2 * MAX_QUEUED");
            self.apply(s);
        }
    }
}

/// The world, recorded or not.
enum Stepper<W: Write> {
    Plain(World),
    Recorded(RecordedWorld<Arc<Terrain>, W>),
}

/// The world and the decisions around it (see the module docs for a tick's order).
pub struct WorldCore<W: Write> {
    terrain: Arc<Terrain>,
    stepper: Stepper<W>,
    drivers: Vec<Driver>,
    next_id: VehicleId,
    inputs: Inputs,
}

impl<W: Write> WorldCore<W> {
    /// An empty world on `terrain`, recorded to `record` if given.
    pub fn new(terrain: Arc<Terrain>, record: Option<W>) -> io::Result<WorldCore<W>> {
        let world = World::new(terrain.clone());
        let stepper = match record {
            Some(out) => Stepper::Recorded(RecordedWorld::start(
                world,
                out,
                terrain.content_hash(),
                recording::MAX_CHECKPOINT_INTERVAL,
            )?),
            None => Stepper::Plain(world),
        };
        Ok(WorldCore {
            terrain,
            stepper,
            drivers: Vec::new(),
            next_id: 0,
            inputs: Inputs::new(),
        })
    }

    pub fn world(&self) -> &World {
        match &self.stepper {
            Stepper::Plain(w) => w,
            Stepper::Recorded(r) => r.world(),
        }
    }

    /// Handles one event. A [`Event::Join`] returns the new driver's vehicle (`None`:
    /// every id is taken, or the recording refused it); other events return `None`.
    pub fn handle(&mut self, event: Event) -> Option<VehicleId> {
        match event {
            Event::Join => self.join(),
            Event::Leave(vehicle) => {
                self.drivers.retain(|d| d.id != vehicle);
                // A vehicle that is not there (a repeated leave) changes nothing.
                let _gone = match &mut self.stepper {
                    Stepper::Plain(w) => w.remove(vehicle).is_ok(),
                    Stepper::Recorded(r) => r.leave(vehicle).is_ok(),
                };
                None
            }
            Event::Hold(vehicle) => self.handle(Event::Leave(vehicle)),
            Event::Resume(_) => None,
            Event::Keys { vehicle, states } => {
                if let Some(d) = self.drivers.iter_mut().find(|d| d.id == vehicle) {
                    d.receive(states);
                }
                None
            }
        }
    }

    fn join(&mut self) -> Option<VehicleId> {
        // The next id not in use (ids wrap after 65,536 joins).
        let drivers = &self.drivers;
        let id = free_id(&mut self.next_id, |id| drivers.iter().any(|d| d.id == id))?;
        let slot = (0u32..)
            .find(|s| drivers.iter().all(|d| d.slot != *s))
            .expect("fewer than 2^32 vehicles");
        let state = world::start_state(&self.terrain, slot);
        let joined = match &mut self.stepper {
            Stepper::Plain(w) => w.add(id, state).is_ok(),
            Stepper::Recorded(r) => r.join(id, state).is_ok(),
        };
        joined.then(|| {
            self.drivers.push(Driver {
                id,
                slot,
                latch: KeyLatch::default(),
                received: None,
                queue: VecDeque::new(),
                applied: None,
                primed: false,
            });
            id
        })
    }

    /// One tick (steps 2 to 4 of the module docs): every driver's keys, one step of the
    /// world, and the snapshot after it. An error is the recording's.
    pub fn tick(&mut self) -> io::Result<Snapshot> {
        self.inputs.clear();
        for d in &mut self.drivers {
            d.take(&mut self.inputs);
        }
        let w = match &mut self.stepper {
            Stepper::Plain(w) => {
                world::step(w, &self.inputs);
                &*w
            }
            Stepper::Recorded(r) => {
                r.step(&self.inputs)?;
                r.world()
            }
        };
        Ok(Snapshot {
            tick: w.tick(),
            vehicles: w.vehicles().to_vec(),
            applied: self
                .drivers
                .iter()
                .filter_map(|d| d.applied.map(|s| (d.id, s)))
                .collect(),
        })
    }

    /// Ends the world: the recording is closed. Returns the final world and the
    /// recording's writer.
    pub fn finish(self) -> io::Result<(World, Option<W>)> {
        match self.stepper {
            Stepper::Plain(w) => Ok((w, None)),
            Stepper::Recorded(r) => {
                let (w, out) = r.finish()?;
                Ok((w, Some(out)))
            }
        }
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
