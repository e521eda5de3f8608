//! The world: every vehicle, stepping together at 100 Hz.
//!
//! `step(&mut World, &Inputs)` advances exactly one 10 ms tick. It reads no clock, does no
//! I/O and draws no random numbers: the same world and inputs give the same bits, which is
//! what recordings and replays rest on. Who feeds it (a script, a replay, the network) is
//! not its business.

use std::sync::Arc;

use crate::Terrain;
use crate::sim::physics::{self, Ground, Keys, VehicleState};

/// A vehicle's name in the world, recordings and (later) the wire.
pub type VehicleId = u16;

/// One vehicle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Vehicle {
    pub id: VehicleId,
    pub state: VehicleState,
}

/// Why the world refused a change.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum WorldError {
    #[error("vehicle {0} is already in the world")]
    Duplicate(VehicleId),
    #[error("vehicle {0} is not in the world")]
    Missing(VehicleId),
    #[error(
        "vehicle {id}: state {state:?} is not on the map (0 ..= {size} on X and Z, speed ≥ 0, heading in [0, 360))"
    )]
    OffMap {
        id: VehicleId,
        state: VehicleState,
        size: f64,
    },
}

/// How a vehicle's tick differs from one physics step with its keys.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Extra {
    /// The vehicle waits: no physics step this tick (a driver whose next key state has not
    /// arrived: its drive is delayed, never changed).
    Wait,
    /// Two physics steps this tick, with these keys (a driver catching up a backlog of key
    /// states, one step each).
    Twice(Keys, Keys),
}

/// The keys each vehicle holds during one step. A vehicle not listed holds none. A vehicle
/// may also wait or step twice, for this tick only ([`Extra`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Inputs {
    /// Sorted by id.
    keys: Vec<(VehicleId, Keys)>,
    /// Sorted by id; for the next step only.
    extra: Vec<(VehicleId, Extra)>,
}

impl Inputs {
    pub fn new() -> Inputs {
        Inputs::default()
    }

    /// Sets `id`'s keys for the step.
    pub fn set(&mut self, id: VehicleId, keys: Keys) {
        match self.keys.binary_search_by_key(&id, |&(v, _)| v) {
            Ok(at) => self.keys[at].1 = keys,
            Err(at) => self.keys.insert(at, (id, keys)),
        }
    }

    pub fn get(&self, id: VehicleId) -> Keys {
        self.keys
            .binary_search_by_key(&id, |&(v, _)| v)
            .map_or(Keys::NONE, |at| self.keys[at].1)
    }

    /// `(id, keys)` by id.
    pub fn iter(&self) -> impl Iterator<Item = (VehicleId, Keys)> + '_ {
        self.keys.iter().copied()
    }

    /// `id` waits or steps twice in the next step (not after it).
    pub fn set_extra(&mut self, id: VehicleId, extra: Extra) {
        match self.extra.binary_search_by_key(&id, |&(v, _)| v) {
            Ok(at) => self.extra[at].1 = extra,
            Err(at) => self.extra.insert(at, (id, extra)),
        }
    }

    pub fn extra(&self, id: VehicleId) -> Option<Extra> {
        self.extra
            .binary_search_by_key(&id, |&(v, _)| v)
            .ok()
            .map(|at| self.extra[at].1)
    }

    /// Forgets every [`Extra`] (after the step they were for).
    pub fn clear_extra(&mut self) {
        self.extra.clear();
    }

    pub fn clear(&mut self) {
        self.keys.clear();
        self.extra.clear();
    }
}

/// A digest of the world: its tick and every vehicle's exact state.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct Digest(pub [u8; 32]);

impl std::fmt::Display for Digest {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        for b in self.0 {
            write!(f, "{b:02x}")?;
        }
        Ok(())
    }
}

/// Where the `slot`-th vehicle to join starts: slot 0 at the map's start, the others in a
/// row across the start heading, 8 world units apart, alternately to the right and the
/// left (slot 1 right, 2 left, 3 two places right, …), clamped onto the map, all at rest
/// facing the start heading.
pub fn start_state(terrain: &Terrain, slot: u32) -> VehicleState {
    const SPACING: f64 = 8.0;
    let start = terrain.map.start;
    let places = f64::from(slot.div_ceil(2));
    let side = if slot % 2 == 1 { 1.0 } else { -1.0 };
    // Right of a heading (sin h, cos h), seen from above with Y up, is (−cos h, sin h).
    let rad = start.heading_deg * (std::f64::consts::PI / 180.0);
    let (right_x, right_z) = (-libm::cos(rad), libm::sin(rad));
    let offset = SPACING * places * side;
    let size = terrain.world_size();
    VehicleState::at_rest(
        (start.x + offset * right_x).clamp(0.0, size),
        (start.z + offset * right_z).clamp(0.0, size),
        start.heading_deg,
    )
}

/// The vehicles and the tick they have reached.
#[derive(Clone, Debug)]
pub struct World<G = Arc<Terrain>> {
    ground: G,
    tick: u64,
    /// Sorted by id.
    vehicles: Vec<Vehicle>,
}

impl<G: Ground> World<G> {
    /// An empty world at tick 0.
    pub fn new(ground: G) -> Self {
        World {
            ground,
            tick: 0,
            vehicles: Vec::new(),
        }
    }

    /// An empty world that has taken `tick` steps already (where a recording that starts
    /// mid-session begins).
    pub fn at_tick(ground: G, tick: u64) -> Self {
        World {
            ground,
            tick,
            vehicles: Vec::new(),
        }
    }

    pub fn ground(&self) -> &G {
        &self.ground
    }

    /// Steps taken so far.
    pub fn tick(&self) -> u64 {
        self.tick
    }

    /// The vehicles, by id.
    pub fn vehicles(&self) -> &[Vehicle] {
        &self.vehicles
    }

    pub fn vehicle(&self, id: VehicleId) -> Option<&Vehicle> {
        self.find(id).ok().map(|i| &self.vehicles[i])
    }

    fn find(&self, id: VehicleId) -> Result<usize, usize> {
        self.vehicles.binary_search_by_key(&id, |v| v.id)
    }

    /// Adds a vehicle in `state`, which must be on the map.
    pub fn add(&mut self, id: VehicleId, state: VehicleState) -> Result<(), WorldError> {
        let size = self.ground.size();
        let on_map = (0.0..=size).contains(&state.x)
            && (0.0..=size).contains(&state.z)
            && state.speed >= 0.0
            && state.speed.is_finite()
            && (0.0..360.0).contains(&state.heading);
        if !on_map {
            return Err(WorldError::OffMap { id, state, size });
        }
        match self.find(id) {
            Ok(_) => Err(WorldError::Duplicate(id)),
            Err(at) => {
                self.vehicles.insert(at, Vehicle { id, state });
                Ok(())
            }
        }
    }

    /// Removes a vehicle.
    pub fn remove(&mut self, id: VehicleId) -> Result<Vehicle, WorldError> {
        let at = self.find(id).map_err(|_| WorldError::Missing(id))?;
        Ok(self.vehicles.remove(at))
    }

    /// The vehicle's altitude: ground plus [`physics::ALTITUDE`].
    pub fn altitude(&self, state: &VehicleState) -> f64 {
        physics::altitude(&self.ground, state.x, state.z)
    }

    /// A digest of the tick and every vehicle's exact state.
    pub fn digest(&self) -> Digest {
        let mut h = blake3::Hasher::new();
        h.update(b"roam world v1");
        h.update(&self.tick.to_le_bytes());
        h.update(&(self.vehicles.len() as u64).to_le_bytes());
        for v in &self.vehicles {
            h.update(&v.id.to_le_bytes());
            for bits in v.state.to_bits() {
                h.update(&bits.to_le_bytes());
            }
        }
        Digest(*h.finalize().as_bytes())
    }
}

/// Advances the world one 10 ms tick, every vehicle with its keys from `inputs` (one
/// physics step; none or two for a vehicle with an [`Extra`]).
pub fn step<G: Ground>(world: &mut World<G>, inputs: &Inputs) {
    // The lists are sorted by id: walk them together.
    let mut keys = inputs.keys.iter().peekable();
    let mut extra = inputs.extra.iter().peekable();
    for v in &mut world.vehicles {
        while keys.next_if(|&&(id, _)| id < v.id).is_some() {}
        while extra.next_if(|&&(id, _)| id < v.id).is_some() {}
        let held = keys
            .next_if(|&&(id, _)| id == v.id)
            .map_or(Keys::NONE, |&(_, k)| k);
        match extra.next_if(|&&(id, _)| id == v.id).map(|&(_, e)| e) {
            None => v.state = physics::step(&world.ground, &v.state, held),
            Some(Extra::Wait) => {}
            Some(Extra::Twice(a, b)) => {
                let once = physics::step(&world.ground, &v.state, a);
                v.state = physics::step(&world.ground, &once, b);
            }
        }
    }
    world.tick += 1;
}

impl<T: Ground + ?Sized> Ground for Arc<T> {
    fn height(&self, x: f64, z: f64) -> f64 {
        (**self).height(x, z)
    }

    fn size(&self) -> f64 {
        (**self).size()
    }
}

impl<T: Ground + ?Sized> Ground for &T {
    fn height(&self, x: f64, z: f64) -> f64 {
        (**self).height(x, z)
    }

    fn size(&self) -> f64 {
        (**self).size()
    }
}
