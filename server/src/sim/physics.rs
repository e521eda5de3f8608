//! Vehicle physics, exactly as SPEC states it: one fixed step of 10 ms.
//!
//! A vehicle is `(x, z, speed, heading)`: position in world units on the X–Z plane, speed in
//! m/s (never negative), heading in degrees (0 faces south/+Z, 90 east/+X, 180 north). Its
//! altitude is always the ground height plus [`ALTITUDE`]. One step, in SPEC's order:
//!
//! 1. friction `f0 + f1·v + f2·v²` and gravity along the slope `9.8·s_y` slow it;
//! 2. then it accelerates (`max(0, 8 − v²/16)`) or brakes (`b`), never below 0;
//! 3. then it turns by `t / (v² + l)` degrees, with the new speed;
//! 4. then it moves `0.01·v` along the new heading.
//!
//! Choices SPEC leaves open, and what this module does:
//!
//! - **Ground height**: bilinear interpolation of the four samples around the point (the
//!   seeds' vehicle collision uses bilinear height). A point off the map is clamped onto it,
//!   so the slope's one-unit look-ahead is defined at the edge.
//! - **Slope vector**: SPEC's first method, `s = normalize(sin h, H(p + d) − H(p), cos h)`
//!   with `d` one world unit along the heading.
//! - **Keys together**: Down brakes even with Up held (braking wins); Left with Right does
//!   not turn.
//! - **The map's edge**: the vehicle bounces. A step that ends past an edge is reflected
//!   back across it, and the heading mirrored (`360 − h` off an east or west edge, `180 − h`
//!   off a north or south edge); speed is kept.
//! - **Heading** is kept in `[0, 360)`.
//!
//! Everything is `f64`, and the only transcendental functions (sine and cosine) come from
//! `libm`, not the platform, so a step gives the same bits on every machine.

use crate::Terrain;

/// One step, seconds.
pub const STEP_S: f64 = 0.01;
/// Steps per second.
pub const STEPS_PER_SECOND: u32 = 100;
/// Braking (`b`), m/s².
pub const BRAKE: f64 = 0.6;
/// Friction coefficients (`f0`, `f1`, `f2`).
pub const F0: f64 = 6e-4;
pub const F1: f64 = 2e-4;
pub const F2: f64 = 4e-4;
/// Gravity, m/s².
pub const GRAVITY: f64 = 9.8;
/// Turn limit (`l`) and turning factor (`t`): the heading changes by `t / (v² + l)` degrees
/// per step.
pub const TURN_LIMIT: f64 = 32.0;
pub const TURN: f64 = 24.0;
/// Height of the vehicle above the ground, world units.
pub const ALTITUDE: f64 = 2.0;

/// The arrow keys (the protocol's: the wire, the scripts and the physics share them).
pub use roam_protocol::keys::Keys;

/// One vehicle's state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VehicleState {
    /// World X (east) and Z (south).
    pub x: f64,
    pub z: f64,
    /// m/s, ≥ 0.
    pub speed: f64,
    /// Degrees in `[0, 360)`.
    pub heading: f64,
}

impl VehicleState {
    /// At rest at `(x, z)`, facing `heading` (any number of degrees).
    pub fn at_rest(x: f64, z: f64, heading: f64) -> VehicleState {
        VehicleState {
            x,
            z,
            speed: 0.0,
            heading: wrap_degrees(heading),
        }
    }

    /// The state's exact bits, for digests and recordings.
    pub fn to_bits(&self) -> [u64; 4] {
        [self.x, self.z, self.speed, self.heading].map(f64::to_bits)
    }

    pub fn from_bits(bits: [u64; 4]) -> VehicleState {
        let [x, z, speed, heading] = bits.map(f64::from_bits);
        VehicleState {
            x,
            z,
            speed,
            heading,
        }
    }
}

/// Sine and cosine of an angle in degrees.
fn sin_cos_deg(deg: f64) -> (f64, f64) {
    let rad = deg * (std::f64::consts::PI / 180.0);
    (libm::sin(rad), libm::cos(rad))
}

/// The terrain as the physics sees it: heights in world units.
pub trait Ground {
    /// Height at world `(x, z)`; points off the map are clamped onto it.
    fn height(&self, x: f64, z: f64) -> f64;
    /// World extent along X and along Z.
    fn size(&self) -> f64;
}

impl Ground for Terrain {
    fn height(&self, x: f64, z: f64) -> f64 {
        let size = self.heights.size();
        let max = f64::from(size);
        let (gx, gz) = (
            (x / self.map.h_scale).clamp(0.0, max),
            (z / self.map.h_scale).clamp(0.0, max),
        );
        // The cell's corner, kept inside the map so that the far corner exists.
        let (i, j) = (
            (gx as u32).min(size - 1), // `as` saturates; gx ≥ 0
            (gz as u32).min(size - 1),
        );
        let (fx, fz) = (gx - f64::from(i), gz - f64::from(j));
        let h = |x: u32, z: u32| f64::from(self.heights.get(x, z));
        let north = h(i, j) + (h(i + 1, j) - h(i, j)) * fx;
        let south = h(i, j + 1) + (h(i + 1, j + 1) - h(i, j + 1)) * fx;
        (north + (south - north) * fz) * self.map.v_scale
    }

    fn size(&self) -> f64 {
        self.world_size()
    }
}

/// Altitude of a vehicle at `(x, z)`: the ground plus [`ALTITUDE`].
pub fn altitude(ground: &impl Ground, x: f64, z: f64) -> f64 {
    ground.height(x, z) + ALTITUDE
}

/// The vertical component of the unit slope vector at `(x, z)` along a heading whose sine
/// and cosine are given: SPEC's `s_y`.
fn slope_y(ground: &impl Ground, x: f64, z: f64, sin_h: f64, cos_h: f64) -> f64 {
    let dy = ground.height(x + sin_h, z + cos_h) - ground.height(x, z);
    let len = (sin_h * sin_h + dy * dy + cos_h * cos_h).sqrt();
    dy / len
}

/// One 10 ms step of one vehicle with `keys` held.
pub fn step(ground: &impl Ground, s: &VehicleState, keys: Keys) -> VehicleState {
    let v = s.speed;
    let a = (8.0 - v * v / 16.0).max(0.0);
    let f = F0 + F1 * v + F2 * v * v;
    let (sin_h, cos_h) = sin_cos_deg(s.heading);
    let g = GRAVITY * slope_y(ground, s.x, s.z, sin_h, cos_h);
    let v1 = v - STEP_S * (f + g);
    let speed = if keys.contains(Keys::DOWN) {
        (v1 - STEP_S * BRAKE).max(0.0)
    } else if keys.contains(Keys::UP) {
        (v1 + STEP_S * a).max(0.0)
    } else {
        v1.max(0.0)
    };
    let turn = TURN / (speed * speed + TURN_LIMIT);
    let heading = match (keys.contains(Keys::LEFT), keys.contains(Keys::RIGHT)) {
        (true, false) => s.heading + turn,
        (false, true) => s.heading - turn,
        _ => s.heading,
    };
    let (sin_n, cos_n) = sin_cos_deg(heading);
    let (x, z) = (s.x + STEP_S * speed * sin_n, s.z + STEP_S * speed * cos_n);
    bounce(ground.size(), x, z, speed, heading)
}

/// Keeps a step on the map: reflects a position past an edge back across it, mirroring the
/// heading, and brings the heading into `[0, 360)`.
fn bounce(size: f64, x: f64, z: f64, speed: f64, heading: f64) -> VehicleState {
    // A coordinate past an edge, reflected back across it, and whether it was.
    let reflect = |v: f64| {
        if v < 0.0 {
            (-v, true)
        } else if v > size {
            (2.0 * size - v, true)
        } else {
            (v, false)
        }
    };
    let (x, off_x) = reflect(x);
    let (z, off_z) = reflect(z);
    let heading = if off_x { 360.0 - heading } else { heading };
    let heading = if off_z { 180.0 - heading } else { heading };
    VehicleState {
        // A step longer than the map (not reachable at these speeds) still ends on it.
        x: x.clamp(0.0, size),
        z: z.clamp(0.0, size),
        speed,
        heading: wrap_degrees(heading),
    }
}

/// An angle in degrees brought into `[0, 360)`.
pub fn wrap_degrees(deg: f64) -> f64 {
    let r = deg.rem_euclid(360.0);
    // A tiny negative angle rounds up to 360 itself.
    if r >= 360.0 { 0.0 } else { r }
}
