//! The benchmark's camera path and its statistics: pure functions, no clock. The binary
//! times each frame and hands the durations back here.

use crate::terrain::dataset::Terrain;
use crate::tessellate::camera::Camera;

/// Viewport of the benchmark (the 1920×1080 at 60° vertical field of view).
pub const WIDTH: u32 = 1920;
pub const HEIGHT: u32 = 1080;
pub const FOV_Y_DEG: f64 = 60.0;
/// Height of the eye above the ground along the path, world units.
pub const EYE_ABOVE_GROUND: f64 = 10.0;
/// Pitch along the path, degrees (slightly down, as a driver looks).
pub const PITCH_DEG: f64 = roam_protocol::messages::DEFAULT_PITCH_DEG;

/// `frames` cameras along a closed loop around the map centre (radius a third of the map),
/// each `EYE_ABOVE_GROUND` over the terrain below it and looking along the loop.
pub fn flyover(terrain: &Terrain, frames: usize) -> Vec<Camera> {
    let size = f64::from(terrain.heights.size());
    let h = terrain.map.h_scale;
    (0..frames)
        .map(|i| {
            let t = std::f64::consts::TAU * i as f64 / frames.max(1) as f64;
            let (gx, gz) = (size * (0.5 + t.cos() / 3.0), size * (0.5 + t.sin() / 3.0));
            // Tangent of the loop: d/dt (cos t, sin t) = (-sin t, cos t); heading 0 faces +Z.
            let heading = (-t.sin()).atan2(t.cos()).to_degrees();
            let ground = terrain.world_height(gx.round() as u32, gz.round() as u32);
            Camera {
                eye: [gx * h, ground + EYE_ABOVE_GROUND, gz * h],
                yaw_deg: heading,
                pitch_deg: PITCH_DEG,
                fov_y_deg: FOV_Y_DEG,
                width: WIDTH,
                height: HEIGHT,
            }
        })
        .collect()
}

/// Cameras at the vehicle of `script` (one driving from the map's start), `fps` frames a
/// second: the eye at the vehicle's altitude, looking along its heading at
/// [`PITCH_DEG`]. A frame shows the world at the latest tick it has reached.
pub fn drive(
    terrain: &std::sync::Arc<Terrain>,
    script: &roam_protocol::script::Script,
    fps: u32,
) -> Vec<Camera> {
    use crate::sim::physics::STEPS_PER_SECOND;
    use crate::sim::world::{self, Inputs, World};
    let mut w = World::new(terrain.clone());
    w.add(0, world::start_state(terrain, 0))
        .expect("the map's start is on the map");
    let mut inputs = Inputs::new();
    let mut cameras = Vec::new();
    let camera = |w: &World| {
        let s = w.vehicles()[0].state;
        Camera {
            eye: [s.x, w.altitude(&s), s.z],
            yaw_deg: s.heading,
            pitch_deg: PITCH_DEG,
            fov_y_deg: FOV_Y_DEG,
            width: WIDTH,
            height: HEIGHT,
        }
    };
    cameras.push(camera(&w));
    for keys in script.keys() {
        inputs.set(0, keys);
        world::step(&mut w, &inputs);
        // Frame k is due at tick k · STEPS_PER_SECOND / fps.
        let frames_due = w.tick() * u64::from(fps) / u64::from(STEPS_PER_SECOND);
        if frames_due >= cameras.len() as u64 {
            cameras.push(camera(&w));
        }
    }
    cameras
}
