//! The world's decisions, with no clock, channel or thread (as `quinn-proto` is to `quinn`):
//! who joins and where they start, which vehicle id they get, each driver's queue of key
//! states, whose vehicle is held for a dropped driver, who leaves, and the snapshot after
//! each tick. [`WorldCore::handle`] takes the one closed set of [`Event`]s the network
//! produces; [`WorldCore::tick`] advances the world one 10 ms step. The server's world
//! thread (`net::world_loop`) only paces it; the simulated network in the tests drives it
//! by virtual time.
//!
//! **A tick, in order:**
//!
//! 1. Events that arrived since the last tick have been handled in arrival order (joins
//!    take the lowest free start slot and the next free id, at the limit first freeing
//!    the oldest held vehicle ([`WorldCore::with_limit`]); leaves free both; key states
//!    are queued per driver by sequence number, repeats and stale ones dropped; a hold
//!    clears its driver's queue and keys, a resume makes a held vehicle driven again).
//! 2. Each driver takes its steps for the tick, one physics step per key state, in order
//!    (a held vehicle has no queue, so it waits):
//!    - until [`PRIME`] states have queued (a tick of slack for jitter), or when its queue
//!      has run dry (a state lost and not yet repeated, or late), its vehicle **waits**: no
//!      step this tick, so its drive is delayed, never changed;
//!    - with more than [`PRIME`] + [`CATCH_UP`] queued (a backlog after a wait or a
//!      stall), it steps **twice**, one step per state, until the backlog is gone;
//!    - with more than [`PRIME`] queued at every tick for [`TRIM_AFTER`] ticks (slack a
//!      past wait left that the path has not needed for a second), it steps **twice**
//!      once, so the queue, and the driver's latency, goes back to [`PRIME`];
//!    - otherwise one step, with the oldest queued state folded into the driver's latch;
//!    - a queue longer than [`MAX_QUEUED`] (a viewer whose clock runs fast) is folded into
//!      the latch at once: the only case where a drive is not step for step the script's.
//! 3. The world steps (and the recording takes the tick's inputs, joins and leaves).
//! 4. Held vehicles whose hold has lasted its ticks ([`WorldCore::with_hold`]) leave, as a
//!    [`Event::Leave`] would make them (and recorded as one).
//! 5. The snapshot: tick, every vehicle, each driver's newest applied key state (the
//!    viewer measures input→frame latency from it), and which vehicles are held.
//!
//! **A recording never stops the world:** it is a [`SessionRecording`], which changes the
//! world and records the change, and reports its failures as [`Notice`]s that the shell
//! drains ([`WorldCore::notices`]) and logs; the world goes on unrecorded.
//!
//! **Held vehicles:** a driver whose connection dropped (not a goodbye) comes back with a
//! ticket; meanwhile [`Event::Hold`] keeps its vehicle in the world, waiting, and
//! [`Event::Resume`] gives it back. Key states after a resume may number on from the old
//! connection's or start again: the first states after a resume that are all at or below
//! the newest seen before say the count started again.
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
use std::io;
use std::sync::Arc;

use roam_protocol::keys::{KeyLatch, KeyStep, Keys};
use roam_protocol::messages::KeyState;

use crate::Terrain;
use crate::sim::session::{Notice, RecordOptions, SessionRecording};
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
    /// A driver's key states, from one datagram: any order, repeats allowed. A held
    /// vehicle takes none.
    Keys {
        vehicle: VehicleId,
        states: Vec<KeyState>,
    },
    /// A driver's connection dropped (not a goodbye): its vehicle stays, waiting, until
    /// resumed or until the hold runs out (then it leaves). Its queued keys are dropped.
    /// The hold counts from `silent` ticks ago: a path that fell silent is seen dead only
    /// at its idle timeout, and the driver's time to come back runs from the silence.
    Hold { vehicle: VehicleId, silent: u64 },
    /// A held vehicle's driver is back: [`WorldCore::handle`] gives the vehicle back
    /// (driven again, its queue empty and unprimed), or `None` when it is not held (freed,
    /// or never held).
    Resume(VehicleId),
}

/// The world after a tick.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Snapshot {
    pub tick: u64,
    pub vehicles: Vec<Vehicle>,
    /// Per driver, the newest key state applied by this tick.
    pub applied: Vec<(VehicleId, u32)>,
    /// The vehicles held for a driver whose connection dropped, the oldest hold first.
    pub held: Vec<VehicleId>,
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

/// Ticks (1 s) a driver's queue must hold more than [`PRIME`] states at every tick before
/// one double step trims the excess. A wait adds a tick that catch-up alone takes back
/// only past [`PRIME`] + [`CATCH_UP`], so jitter ratcheted queues up and left them there:
/// through an edge (more jitter) some 6 ms higher on the input→frame p99 than through
/// `serve` (`scripts/cluster.sh latency`). Trimming to no slack at all (an adaptive jitter
/// buffer) was tried: `serve`'s p99 fell 3 ms, an edge's rose 2 (its jitter kept drying
/// the queues), so the bus added 7.4 ms instead of 2.0 (6 rounds each, this machine).
pub const TRIM_AFTER: u32 = 100;

/// Key states a driver may have waiting (a third of a second): a longer backlog is folded
/// into the latch at once, so a fast clock cannot delay a driver's keys without bound.
pub const MAX_QUEUED: usize = 32;

/// Ticks a dropped driver's vehicle is held unless told otherwise (30 s).
pub const HOLD_TICKS: u64 = 3000;

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
    /// Consecutive ticks its queue held more than [`PRIME`] states (see [`TRIM_AFTER`]).
    spare: u32,
    /// The tick its hold began, while its vehicle is held.
    held_since: Option<u64>,
    /// Resumed, and no key state taken since: the next may number from 0 again.
    resumed: bool,
}

impl Driver {
    fn new(id: VehicleId, slot: u32) -> Driver {
        Driver {
            id,
            slot,
            latch: KeyLatch::default(),
            received: None,
            queue: VecDeque::new(),
            applied: None,
            primed: false,
            spare: 0,
            held_since: None,
            resumed: false,
        }
    }

    /// Its connection dropped at `tick`: no keys until resumed, so it waits.
    fn hold(&mut self, tick: u64) {
        self.held_since = Some(tick);
        self.queue.clear();
        self.primed = false;
        self.spare = 0;
        self.latch = KeyLatch::default();
    }

    /// Driven again: an empty queue, unprimed; the key states' count may start again.
    fn resume(&mut self) {
        self.held_since = None;
        self.queue.clear();
        self.primed = false;
        self.spare = 0;
        self.resumed = true;
    }

    fn apply(&mut self, (seq, step): (u32, KeyStep)) {
        self.latch.apply(step);
        self.applied = Some(seq);
    }

    /// The vehicle's steps for the next tick (step 2 of the tick), into `inputs`.
    fn take(&mut self, inputs: &mut Inputs) {
        self.primed |= self.queue.len() >= PRIME;
        if !self.primed || self.queue.is_empty() {
            self.spare = 0;
            inputs.set_extra(self.id, Extra::Wait);
            return;
        }
        while self.queue.len() > MAX_QUEUED {
            let s = self.queue.pop_front().expect("longer than MAX_QUEUED");
            self.apply(s);
        }
        self.spare = if self.queue.len() > PRIME {
            self.spare + 1
        } else {
            0
        };
        let first = self.step();
        inputs.set(self.id, first);
        let trim = self.spare >= TRIM_AFTER;
        if self.queue.len() >= PRIME + CATCH_UP || trim {
            self.spare = 0;
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
        if self.resumed && !states.is_empty() {
            self.resumed = false;
            if states
                .iter()
                .all(|s| self.received.is_some_and(|seq| s.seq <= seq))
            {
                self.received = None; // the count started again
            }
        }
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

/// The world and the decisions around it (see the module docs for a tick's order).
pub struct WorldCore {
    terrain: Arc<Terrain>,
    world: World,
    /// `None`: not recorded.
    recording: Option<SessionRecording>,
    /// Sorted by id (a binary search finds a key event's driver).
    drivers: Vec<Driver>,
    next_id: VehicleId,
    inputs: Inputs,
    hold_ticks: u64,
    /// Vehicles at most before a join frees the oldest held one ([`WorldCore::with_limit`]).
    limit: usize,
    /// Whether a join past `limit` with nothing held to free is refused
    /// ([`WorldCore::refusing_past_limit`]).
    hard_limit: bool,
    /// Held vehicles a join freed, since [`WorldCore::take_evicted`].
    evicted: Vec<VehicleId>,
}

impl WorldCore {
    /// An empty world on `terrain`, recorded as `record` says if given. An error is the
    /// recording's first file failing (the only error there is: later ones are
    /// [`Notice`]s).
    pub fn new(terrain: Arc<Terrain>, record: Option<RecordOptions>) -> io::Result<WorldCore> {
        let world = World::new(terrain.clone());
        let recording = match record {
            Some(options) => {
                let hash = options
                    .terrain_hash
                    .unwrap_or_else(|| terrain.content_hash());
                Some(SessionRecording::start(options, hash, &world)?)
            }
            None => None,
        };
        Ok(WorldCore {
            terrain,
            world,
            recording,
            drivers: Vec::new(),
            next_id: 0,
            inputs: Inputs::new(),
            hold_ticks: HOLD_TICKS,
            limit: usize::MAX,
            hard_limit: false,
            evicted: Vec::new(),
        })
    }

    /// Holds a dropped driver's vehicle `ticks` ticks (default [`HOLD_TICKS`]).
    pub fn with_hold(mut self, ticks: u64) -> WorldCore {
        self.hold_ticks = ticks;
        self
    }

    /// Held vehicles have no seat: without a bound, a driver that joins and drops over and
    /// over would fill the world with them. With `limit` vehicles (or more) in the world, a
    /// [`Event::Join`] first frees the oldest held one, as a [`Event::Leave`] would (no
    /// bound unless told). Decided here, where joins come one at a time in order: two joins
    /// at once free two distinct vehicles, and held ones never take the world past it.
    pub fn with_limit(mut self, limit: usize) -> WorldCore {
        self.limit = limit;
        self
    }

    /// A join at the limit with no held vehicle to free is refused (`None`), as the world of
    /// `roam-server world` needs: its joins come from any number of edges, each admitting
    /// its own viewers. (`serve` admits viewers up to the limit itself, and lets a driver
    /// replacing its own connection take a seat past it for a moment.)
    pub fn refusing_past_limit(mut self) -> WorldCore {
        self.hard_limit = true;
        self
    }

    /// The held vehicles joins freed since the last call, oldest first (the shell forgets
    /// their drivers' tickets).
    pub fn take_evicted(&mut self) -> Vec<VehicleId> {
        std::mem::take(&mut self.evicted)
    }

    pub fn world(&self) -> &World {
        &self.world
    }

    /// The vehicles that have a driver (held ones included), by id: every vehicle in the
    /// world, always.
    pub fn drivers(&self) -> Vec<VehicleId> {
        self.drivers.iter().map(|d| d.id).collect()
    }

    /// The recording's file being written; `None` when not recorded or after a failure.
    pub fn recording_file(&self) -> Option<&str> {
        self.recording.as_ref().and_then(|r| r.file())
    }

    /// What happened to the recording since the last call, for the shell to log.
    pub fn notices(&mut self) -> Vec<Notice> {
        self.recording
            .as_mut()
            .map_or_else(Vec::new, SessionRecording::notices)
    }

    /// Handles one event. A [`Event::Join`] returns the new driver's vehicle (`None`:
    /// every id is taken), a [`Event::Resume`] the vehicle given back (`None`: it is not
    /// held); other events return `None`.
    pub fn handle(&mut self, event: Event) -> Option<VehicleId> {
        match event {
            Event::Join => self.join(),
            Event::Leave(vehicle) => {
                self.leave(vehicle);
                None
            }
            Event::Keys { vehicle, states } => {
                if let Some(d) = self.driver(vehicle)
                    && d.held_since.is_none()
                {
                    d.receive(states);
                }
                None
            }
            Event::Hold { vehicle, silent } => {
                let since = self.world.tick().saturating_sub(silent);
                if let Some(d) = self.driver(vehicle)
                    && d.held_since.is_none()
                {
                    d.hold(since);
                }
                None
            }
            Event::Resume(vehicle) => {
                let d = self.driver(vehicle)?;
                d.held_since?;
                d.resume();
                Some(vehicle)
            }
        }
    }

    /// By binary search, the drivers sorted by id (a walk per key event was 32 % of the
    /// world's `perf` samples at 1,000 drivers, `scripts/cluster.sh fanout 1000`; now 10 %).
    fn driver(&mut self, vehicle: VehicleId) -> Option<&mut Driver> {
        let at = self.drivers.binary_search_by_key(&vehicle, |d| d.id).ok()?;
        self.drivers.get_mut(at)
    }

    /// The driver and its vehicle go (a vehicle that is not there changes nothing).
    fn leave(&mut self, vehicle: VehicleId) {
        self.drivers.retain(|d| d.id != vehicle);
        let _gone = match &mut self.recording {
            Some(r) => r.leave(&mut self.world, vehicle).is_ok(),
            None => self.world.remove(vehicle).is_ok(),
        };
    }

    fn join(&mut self) -> Option<VehicleId> {
        if self.drivers.len() >= self.limit
            && let Some((_, oldest)) = self
                .drivers
                .iter()
                .filter_map(|d| d.held_since.map(|since| (since, d.id)))
                .min()
        {
            self.leave(oldest);
            self.evicted.push(oldest);
        }
        if self.hard_limit && self.drivers.len() >= self.limit {
            return None;
        }
        // The next id not in use (ids wrap after 65,536 joins).
        let drivers = &self.drivers;
        let id = free_id(&mut self.next_id, |id| {
            drivers.binary_search_by_key(&id, |d| d.id).is_ok()
        })?;
        let slot = (0u32..)
            .find(|s| drivers.iter().all(|d| d.slot != *s))
            .expect("fewer than 2^32 vehicles");
        let state = world::start_state(&self.terrain, slot);
        // Made in the world first, then recorded: a failing record ends the recording, not
        // the join, so every vehicle has its driver.
        let joined = match &mut self.recording {
            Some(r) => r.join(&mut self.world, id, state).is_ok(),
            None => self.world.add(id, state).is_ok(),
        };
        joined.then(|| {
            // Sorted by id (ids wrap, so not always at the end): see `driver`.
            let at = self.drivers.partition_point(|d| d.id < id);
            self.drivers.insert(at, Driver::new(id, slot));
            id
        })
    }

    /// One tick (steps 2 to 5 of the module docs): every driver's keys, one step of the
    /// world, the holds that ran out, and the snapshot after it. Recording errors are
    /// [`Notice`]s: a tick always happens.
    pub fn tick(&mut self) -> Snapshot {
        self.inputs.clear();
        for d in &mut self.drivers {
            d.take(&mut self.inputs);
        }
        match &mut self.recording {
            Some(r) => r.step(&mut self.world, &self.inputs),
            None => world::step(&mut self.world, &self.inputs),
        }
        let now = self.world.tick();
        let hold = self.hold_ticks;
        let expired: Vec<VehicleId> = self
            .drivers
            .iter()
            .filter(|d| d.held_since.is_some_and(|since| now - since >= hold))
            .map(|d| d.id)
            .collect();
        for id in expired {
            self.leave(id);
        }
        // Oldest hold first (then by id), the order a join at the limit frees them in.
        let mut held: Vec<(u64, VehicleId)> = self
            .drivers
            .iter()
            .filter_map(|d| d.held_since.map(|since| (since, d.id)))
            .collect();
        held.sort_unstable();
        let held = held.into_iter().map(|(_, id)| id).collect();
        Snapshot {
            tick: now,
            vehicles: self.world.vehicles().to_vec(),
            applied: self
                .drivers
                .iter()
                .filter_map(|d| d.applied.map(|s| (d.id, s)))
                .collect(),
            held,
        }
    }

    /// Ends the world: the recording is finished. Returns the final world and the
    /// recording's last notices (its closing among them).
    pub fn finish(self) -> (World, Vec<Notice>) {
        let notices = match self.recording {
            Some(r) => r.finish(&self.world),
            None => Vec::new(),
        };
        (self.world, notices)
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
    use std::sync::Arc;

    use roam_protocol::keys::Keys;
    use roam_protocol::messages::KeyState;

    use super::{Event, TRIM_AFTER, WorldCore, free_id};
    use crate::sim::physics::VehicleState;
    use crate::sim::world::VehicleId;

    fn core(hold: u64) -> WorldCore {
        let terrain = Arc::new(crate::terrain::generate::synthetic(65, 7));
        WorldCore::new(terrain, None)
            .expect("nothing recorded")
            .with_hold(hold)
    }

    /// `vehicle`'s connection dropped just now.
    fn hold(vehicle: VehicleId) -> Event {
        Event::Hold { vehicle, silent: 0 }
    }

    /// `vehicle`'s key states `seqs`, Up held, in one datagram.
    fn up(vehicle: VehicleId, seqs: std::ops::RangeInclusive<u32>) -> Event {
        Event::Keys {
            vehicle,
            states: seqs
                .map(|seq| KeyState {
                    seq,
                    held: Keys::UP.bits(),
                    pressed: 0,
                })
                .collect(),
        }
    }

    fn state(c: &WorldCore, id: VehicleId) -> Option<VehicleState> {
        c.world().vehicle(id).map(|v| v.state)
    }

    /// Key states `seqs`, one a tick, then ticks until the queue is dry.
    fn drive(c: &mut WorldCore, id: VehicleId, seqs: std::ops::RangeInclusive<u32>) {
        for seq in seqs {
            c.handle(up(id, seq..=seq));
            c.tick();
        }
        for _ in 0..10 {
            c.tick();
        }
    }

    /// One vehicle that took `n` steps with Up, from its start.
    fn driven(n: u32) -> VehicleState {
        let mut c = core(100);
        let id = c.handle(Event::Join).expect("a vehicle");
        drive(&mut c, id, 0..=n - 1);
        state(&c, id).expect("still there")
    }

    #[test]
    fn a_held_vehicle_waits_and_is_given_back_as_it_was() {
        let mut c = core(50);
        let a = c.handle(Event::Join).expect("a vehicle");
        let b = c.handle(Event::Join).expect("another");
        c.handle(up(a, 0..=5));
        for _ in 0..3 {
            c.tick();
        }
        c.handle(hold(a));
        let held = state(&c, a).expect("still there");
        assert!(held.speed > 0.0, "it was moving");
        // Keys for a held vehicle are not taken; it waits, its state unchanged.
        c.handle(up(a, 6..=20));
        for _ in 0..49 {
            let s = c.tick();
            assert_eq!(s.held, [a]);
            assert_eq!(state(&c, a), Some(held));
        }
        assert_eq!(c.handle(Event::Resume(a)), Some(a), "given back");
        assert_eq!(state(&c, a), Some(held));
        assert_eq!(c.drivers(), [a, b]);
        let s = c.tick();
        assert!(s.held.is_empty());
        assert_eq!(state(&c, a), Some(held), "unprimed: it waits for its keys");
        // Not held any more, or never held: nothing to resume.
        assert_eq!(c.handle(Event::Resume(a)), None);
        assert_eq!(c.handle(Event::Resume(b)), None);
        assert_eq!(c.handle(Event::Resume(77)), None);
    }

    #[test]
    fn slack_past_prime_the_path_did_not_need_for_a_second_is_trimmed() {
        let mut c = core(100);
        let id = c.handle(Event::Join).expect("a vehicle");
        // Three states before the first tick (as after a wait): one more than PRIME.
        c.handle(up(id, 0..=2));
        let n = 3 + 2 * TRIM_AFTER;
        // States received and not yet applied after each tick, one arriving a tick.
        let mut waiting = Vec::new();
        for seq in 3..n {
            let applied = c.tick().applied_by(id).expect("driving");
            waiting.push(seq - 1 - applied);
            c.handle(up(id, seq..=seq));
        }
        // A calm second trims the state past PRIME; the state of slack PRIME leaves stays.
        let once = (TRIM_AFTER - 1) as usize;
        assert!(waiting[..once].iter().all(|&w| w == 2), "{waiting:?}");
        assert!(waiting[once..].iter().all(|&w| w == 1), "{waiting:?}");
        // Every state applied once, in order: the drive is the one-step-a-tick drive.
        for _ in 0..10 {
            c.tick();
        }
        assert_eq!(state(&c, id), Some(driven(n)));
    }

    #[test]
    fn key_numbering_may_start_again_or_go_on_after_a_resume() {
        // 16 states with Up, however they are split around a hold, make 16 steps.
        let want = driven(16);
        for restart in [false, true] {
            let mut c = core(500);
            let id = c.handle(Event::Join).expect("a vehicle");
            drive(&mut c, id, 0..=10);
            c.handle(hold(id));
            for _ in 0..20 {
                c.tick();
            }
            assert_eq!(c.handle(Event::Resume(id)), Some(id));
            if restart {
                drive(&mut c, id, 0..=4);
            } else {
                // The first datagram repeats states the old connection sent.
                c.handle(up(id, 6..=11));
                drive(&mut c, id, 12..=15);
            }
            assert_eq!(state(&c, id), Some(want), "restart {restart}");
            let applied = c.tick().applied_by(id);
            assert_eq!(applied, Some(if restart { 4 } else { 15 }));
        }
    }

    #[test]
    fn a_hold_runs_out_after_its_ticks_as_a_leave() {
        let mut c = core(30);
        let a = c.handle(Event::Join).expect("a vehicle");
        c.tick();
        c.handle(hold(a));
        c.handle(hold(a)); // a second hold does not restart it
        for _ in 0..29 {
            assert_eq!(c.tick().held, [a]);
        }
        let s = c.tick();
        assert!(s.vehicles.is_empty() && s.held.is_empty(), "{s:?}");
        assert!(c.drivers().is_empty());
        assert_eq!(c.handle(Event::Resume(a)), None, "freed");
        // Its start slot is free again: the next driver starts where it did.
        let b = c.handle(Event::Join).expect("a vehicle");
        let mut fresh = core(30);
        let first = fresh.handle(Event::Join).expect("a vehicle");
        assert_eq!(state(&c, b), state(&fresh, first));
    }

    #[test]
    fn a_hold_counts_from_when_the_path_fell_silent() {
        let mut c = core(30);
        let a = c.handle(Event::Join).expect("a vehicle");
        let b = c.handle(Event::Join).expect("a vehicle");
        for _ in 0..50 {
            c.tick();
        }
        // Silent for 20 of its 30 ticks already: 10 left. Silent past the hold: freed at
        // the next tick.
        c.handle(Event::Hold {
            vehicle: a,
            silent: 20,
        });
        c.handle(Event::Hold {
            vehicle: b,
            silent: 40,
        });
        assert_eq!(c.tick().held, [a]);
        for _ in 0..8 {
            assert_eq!(c.tick().held, [a]);
        }
        let s = c.tick();
        assert!(s.vehicles.is_empty() && s.held.is_empty(), "{s:?}");
        // Silent for longer than the world has run: held from its first tick.
        let mut young = core(30);
        let d = young.handle(Event::Join).expect("a vehicle");
        young.tick();
        young.handle(Event::Hold {
            vehicle: d,
            silent: 1_000,
        });
        assert_eq!(young.tick().held, [d], "held from tick 0, 30 ticks");
    }

    #[test]
    fn a_leave_frees_a_held_vehicle_at_once() {
        let mut c = core(3000);
        let a = c.handle(Event::Join).expect("a vehicle");
        c.tick();
        c.handle(hold(a));
        c.handle(Event::Leave(a));
        let s = c.tick();
        assert!(s.vehicles.is_empty() && s.held.is_empty());
        assert_eq!(c.handle(Event::Resume(a)), None);
    }

    #[test]
    fn joins_at_the_limit_free_distinct_held_vehicles_oldest_first() {
        let mut c = core(3000).with_limit(3);
        let a = c.handle(Event::Join).expect("a vehicle");
        let b = c.handle(Event::Join).expect("a vehicle");
        let d = c.handle(Event::Join).expect("a vehicle");
        c.tick();
        c.handle(hold(b));
        c.tick();
        c.handle(hold(a));
        assert_eq!(c.tick().held, [b, a]);
        assert!(c.take_evicted().is_empty());
        // Two joins in the same tick (as two viewers joining at once arrive): each frees
        // a held vehicle of its own, the oldest hold first.
        let e = c.handle(Event::Join).expect("a vehicle");
        let f = c.handle(Event::Join).expect("a vehicle");
        assert_eq!(c.take_evicted(), [b, a]);
        let s = c.tick();
        assert!(s.held.is_empty(), "{:?}", s.held);
        assert_eq!(c.drivers(), [d, e, f]);
        assert_eq!(s.vehicles.len(), 3);
        assert_eq!(c.handle(Event::Resume(a)), None, "freed");
        // At the limit with nothing held, a join (a driver replacing its own connection
        // takes a seat past the limit for a moment) frees no driven vehicle.
        let g = c.handle(Event::Join).expect("a vehicle");
        assert!(c.take_evicted().is_empty());
        assert_eq!(c.drivers(), [d, e, f, g]);
        // Refusing past the limit: at it with nothing held, a join gets no vehicle.
        let mut hard = core(3000).with_limit(2).refusing_past_limit();
        assert!(hard.handle(Event::Join).is_some());
        assert!(hard.handle(Event::Join).is_some());
        assert_eq!(hard.handle(Event::Join), None);
        // Without a limit, held vehicles stay until their hold runs out.
        let mut open = core(3000);
        let h = open.handle(Event::Join).expect("a vehicle");
        open.handle(hold(h));
        open.handle(Event::Join).expect("a vehicle");
        assert_eq!(open.tick().held, [h]);
    }

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

    #[test]
    fn key_states_reach_their_drivers_after_the_ids_wrap() {
        let mut c = core(100);
        let a = c.handle(Event::Join).expect("a vehicle");
        let b = c.handle(Event::Join).expect("another");
        c.next_id = u16::MAX;
        let last = c.handle(Event::Join).expect("the last id");
        let wrapped = c.handle(Event::Join).expect("the ids wrap");
        assert_eq!((a, b, last, wrapped), (0, 1, u16::MAX, 2));
        // Each driver its own number of states: each applies exactly its own.
        for (id, n) in [(a, 3), (b, 5), (last, 7), (wrapped, 9)] {
            c.handle(up(id, 0..=n - 1));
        }
        let snap = (0..20).fold(c.tick(), |_, _| c.tick());
        for (id, n) in [(a, 3), (b, 5), (last, 7), (wrapped, 9)] {
            assert_eq!(snap.applied_by(id), Some(n - 1), "vehicle {id}");
        }
    }
}
