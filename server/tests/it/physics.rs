//! The vehicle physics against hand-computed steps and analytic terms, and its properties
//! on random terrains and drives.

use std::sync::Arc;

use proptest::prelude::*;
use roam_protocol::keys::KeyLatch;
use roam_server::sim::physics::{self, Ground, Keys, VehicleState};
use roam_server::sim::world::{self, Inputs, World};
use roam_server::{ColorMap, Heightfield, MapParams, Terrain};

/// A terrain of `side` whose sample at `(x, z)` is `f(x, z)`, one world unit per cell,
/// `v_scale` per sample step.
fn terrain(side: u32, v_scale: f64, f: impl Fn(u32, u32) -> u16) -> Terrain {
    let samples = (0..side * side).map(|i| f(i % side, i / side)).collect();
    let mut map = MapParams::default_for_side(side);
    map.v_scale = v_scale;
    let cells = side - 1;
    Terrain {
        map,
        heights: Heightfield::new(side, samples).expect("a valid side"),
        color: Some(ColorMap::new(cells, vec![[0; 3]; (cells * cells) as usize]).expect("cells²")),
    }
}

fn flat() -> Terrain {
    terrain(65, 0.1, |_, _| 1000)
}

fn at(speed: f64, heading: f64) -> VehicleState {
    VehicleState {
        x: 32.0,
        z: 32.0,
        speed,
        heading,
    }
}

/// `got` equals `want` to within a few units in the last place.
fn close(got: f64, want: f64) {
    assert!(
        (got - want).abs() <= 1e-12 * want.abs().max(1.0),
        "got {got}, want {want}"
    );
}

#[test]
fn one_step_from_rest_with_up_held() {
    let s = physics::step(&flat(), &at(0.0, 0.0), Keys::UP);
    // 0.01·8 − 0.01·6e-4
    close(s.speed, 0.079994);
    assert_eq!(s.heading, 0.0);
    // Heading 0 faces +Z: the vehicle moved south by 0.01·v.
    assert_eq!(s.x, 32.0);
    close(s.z, 32.0 + 0.01 * s.speed);
}

#[test]
fn acceleration_is_speed_limited() {
    // a = max(0, 8 − v²/16) is 0 from v = √128 on: at that speed Up only fights friction.
    let v = 128f64.sqrt();
    let s = physics::step(&flat(), &at(v, 90.0), Keys::UP);
    let f = physics::F0 + physics::F1 * v + physics::F2 * v * v;
    close(s.speed, v - 0.01 * f);
}

#[test]
fn braking_reaches_zero_and_stays_there() {
    let ground = flat();
    let mut s = at(3.0, 45.0);
    let mut steps = 0;
    while s.speed > 0.0 {
        let v = s.speed;
        let f = physics::F0 + physics::F1 * v + physics::F2 * v * v;
        let next = physics::step(&ground, &s, Keys::DOWN);
        close(next.speed, (v - 0.01 * f - 0.01 * physics::BRAKE).max(0.0));
        s = next;
        steps += 1;
        assert!(steps < 1000, "3 m/s stops within 5 s of braking");
    }
    // About 3 / (0.6 + friction) seconds.
    assert!((480..=500).contains(&steps), "{steps} steps");
    for _ in 0..10 {
        let (x, z) = (s.x, s.z);
        s = physics::step(&ground, &s, Keys::DOWN);
        assert_eq!(
            (s.speed, s.x, s.z),
            (0.0, x, z),
            "never below zero, never moves"
        );
    }
}

#[test]
fn up_and_down_together_brake() {
    let both = physics::step(&flat(), &at(2.0, 0.0), Keys::UP.union(Keys::DOWN));
    let down = physics::step(&flat(), &at(2.0, 0.0), Keys::DOWN);
    assert_eq!(both, down);
}

#[test]
fn turning_rate_is_t_over_v_squared_plus_l() {
    let ground = flat();
    for v in [0.0, 1.0, 4.0, 11.0] {
        // No Up: the new speed is the old one less friction.
        let next_v = (v - 0.01 * (physics::F0 + physics::F1 * v + physics::F2 * v * v)).max(0.0);
        let rate = 24.0 / (next_v * next_v + 32.0);
        let left = physics::step(&ground, &at(v, 100.0), Keys::LEFT);
        let right = physics::step(&ground, &at(v, 100.0), Keys::RIGHT);
        close(left.heading, 100.0 + rate);
        close(right.heading, 100.0 - rate);
        let both = physics::step(&ground, &at(v, 100.0), Keys::LEFT.union(Keys::RIGHT));
        assert_eq!(both.heading, 100.0, "left and right cancel");
    }
    // At rest a turn is 24/32 = 0.75° per step, and headings wrap into [0, 360).
    let s = physics::step(&ground, &at(0.0, 0.5), Keys::RIGHT);
    close(s.heading, 360.0 - 0.25);
}

#[test]
fn gravity_on_a_constant_slope() {
    // Heights rise eastwards by 3 samples per cell: 0.3 world units per unit.
    let ground = terrain(65, 0.1, |x, _| 5000 + 3 * x as u16);
    let k: f64 = 0.3;
    let s_y = k / (1.0 + k * k).sqrt();
    // Facing west (downhill) from rest, no keys: gravity alone pulls.
    let s = physics::step(&ground, &at(0.0, 270.0), Keys::NONE);
    close(s.speed, -0.01 * (physics::F0 - physics::GRAVITY * s_y));
    // Facing east (uphill) from rest, Up held: gravity takes its share of the acceleration.
    let s = physics::step(&ground, &at(0.0, 90.0), Keys::UP);
    close(
        s.speed,
        0.01 * 8.0 - 0.01 * (physics::F0 + physics::GRAVITY * s_y),
    );
    // Facing south, across the slope: no gravity term.
    let s = physics::step(&ground, &at(0.0, 0.0), Keys::UP);
    close(s.speed, 0.079994);
}

#[test]
fn bilinear_ground_between_samples() {
    let ground = terrain(5, 0.5, |x, z| (10 * x + 100 * z) as u16);
    // A plane: bilinear is exact on it.
    close(ground.height(1.25, 2.5), 0.5 * (12.5 + 250.0));
    // Off the map the point is clamped onto it.
    close(ground.height(-3.0, 9.0), 0.5 * 400.0);
    close(physics::altitude(&ground, 4.0, 4.0), 0.5 * 440.0 + 2.0);
}

#[test]
fn bounces_off_every_edge() {
    let ground = flat();
    let size = ground.size();
    for (x, z, heading, mirrored) in [
        (size - 0.01, 32.0, 90.0, 270.0), // east edge, heading east
        (0.01, 32.0, 270.0, 90.0),        // west
        (32.0, size - 0.01, 0.0, 180.0),  // south
        (32.0, 0.01, 180.0, 0.0),         // north
        (size - 0.01, size - 0.01, 45.0, 225.0),
    ] {
        let s = VehicleState {
            x,
            z,
            speed: 10.0,
            heading,
        };
        let next = physics::step(&ground, &s, Keys::NONE);
        assert!((0.0..=size).contains(&next.x) && (0.0..=size).contains(&next.z));
        close(next.heading, mirrored);
        assert!(next.speed > 9.9, "speed kept");
    }
}

#[test]
fn a_transient_press_acts_in_exactly_one_step() {
    let terrain = Arc::new(flat());
    let mut world = World::new(terrain);
    world.add(7, at(0.0, 0.0)).expect("on the map");
    let mut latch = KeyLatch::default();
    let mut inputs = Inputs::new();
    // Pressed and released between two steps.
    latch.press(Keys::UP);
    latch.release(Keys::UP);
    inputs.set(7, latch.take().active());
    assert_eq!(inputs.get(7), Keys::UP);
    world::step(&mut world, &inputs);
    close(world.vehicles()[0].state.speed, 0.079994);
    inputs.set(7, latch.take().active());
    assert_eq!(
        inputs.get(7),
        Keys::NONE,
        "consumed by the step that saw it"
    );
    world::step(&mut world, &inputs);
    assert!(world.vehicles()[0].state.speed < 0.079994, "coasting");
    // A key held across steps acts in each; a new key in a key-state update counts as a
    // press even if a later update drops it before the step.
    latch.set_held(Keys::LEFT);
    assert_eq!(latch.take().active(), Keys::LEFT);
    assert_eq!(latch.take().active(), Keys::LEFT);
    latch.set_held(Keys::LEFT.union(Keys::UP));
    latch.set_held(Keys::LEFT);
    assert_eq!(latch.take().active(), Keys::LEFT.union(Keys::UP));
    assert_eq!(latch.take().active(), Keys::LEFT);
}

#[test]
fn world_steps_every_vehicle_with_its_own_keys() {
    let terrain = Arc::new(flat());
    let mut world = World::new(terrain.clone());
    for id in [3, 1, 2] {
        world
            .add(id, world::start_state(&terrain, u32::from(id)))
            .expect("on the map");
    }
    assert!(world.add(2, at(0.0, 0.0)).is_err(), "ids are unique");
    assert!(
        world.add(9, at(0.0, 400.0)).is_err(),
        "headings are in [0, 360)"
    );
    assert_eq!(
        world.vehicles().iter().map(|v| v.id).collect::<Vec<_>>(),
        [1, 2, 3]
    );
    let mut inputs = Inputs::new();
    inputs.set(2, Keys::UP);
    let before = world.vehicles().to_vec();
    world::step(&mut world, &inputs);
    assert_eq!(world.tick(), 1);
    for (b, a) in before.iter().zip(world.vehicles()) {
        let want = physics::step(&*terrain, &b.state, inputs.get(b.id));
        assert_eq!(a.state, want, "vehicle {}", b.id);
    }
    // Start slots sit 8 units apart across the start heading.
    let d = |a: &VehicleState, b: &VehicleState| ((a.x - b.x).powi(2) + (a.z - b.z).powi(2)).sqrt();
    close(d(&before[0].state, &before[1].state), 16.0);
    world.remove(2).expect("present");
    assert!(world.remove(2).is_err());
}

fn keys() -> impl Strategy<Value = Keys> {
    (0u8..16).prop_map(|b| Keys::from_bits(b).expect("4 bits"))
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Speed ≥ 0, always on the map, heading in [0, 360), and the altitude never below the
    /// ground around the vehicle, whatever the terrain and the keys.
    #[test]
    fn drives_stay_on_the_map(
        seed in 0u64..1000,
        start in (0.0f64..1.0, 0.0f64..1.0, 0.0f64..360.0, 0.0f64..30.0),
        drive in prop::collection::vec((1u32..200, keys()), 1..12),
    ) {
        let t = roam_server::terrain::generate::synthetic(17, seed);
        let size = t.world_size();
        let mut s = VehicleState { x: start.0 * size, z: start.1 * size, speed: start.3, heading: start.2 };
        for (ticks, k) in drive {
            for _ in 0..ticks {
                s = physics::step(&t, &s, k);
                prop_assert!(s.speed >= 0.0 && s.speed.is_finite());
                prop_assert!((0.0..=size).contains(&s.x) && (0.0..=size).contains(&s.z), "{s:?}");
                prop_assert!((0.0..360.0).contains(&s.heading));
                let (i, j) = ((s.x / t.map.h_scale) as u32, (s.z / t.map.h_scale) as u32);
                let lowest = [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .iter()
                    .map(|&(dx, dz)| {
                        let (x, z) = ((i + dx).min(16), (j + dz).min(16));
                        t.world_height(x, z)
                    })
                    .fold(f64::INFINITY, f64::min);
                let alt = physics::altitude(&t, s.x, s.z);
                prop_assert!(alt >= lowest + physics::ALTITUDE - 1e-9, "{alt} below {lowest} + 2");
                prop_assert_eq!(alt, t.height(s.x, s.z) + physics::ALTITUDE);
            }
        }
    }

    /// The same state and keys give the same bits.
    #[test]
    fn steps_are_pure(x in 0.0f64..64.0, z in 0.0f64..64.0, v in 0.0f64..20.0, h in 0.0f64..360.0, k in keys()) {
        let t = roam_server::terrain::generate::synthetic(65, 3);
        let s = VehicleState { x, z, speed: v, heading: h };
        let a = physics::step(&t, &s, k);
        let b = physics::step(&t, &s, k);
        prop_assert_eq!(a.to_bits(), b.to_bits());
    }
}
