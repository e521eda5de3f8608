//! `fogged_error_px_*`: the screen error of the served cut that the fog lets through
//! ([`roam_server::tessellate::fogged_error_px`]: the largest error in pixels of the cut's
//! unsplit diamonds, each weighed by the fog's transmission at its distance), frame by
//! frame, with the camera the server tessellated that frame for. Needs the data set (the
//! viewer's in-process server's, `--local`): a viewer alone does not know the errors.

use std::sync::Arc;

use roam_protocol::DiamondMap;
use roam_protocol::messages::{Hello, VehicleView};
use roam_server::Terrain;
use roam_server::sim::physics::VehicleState;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::{Scales, Scratch, fogged_error_px};
use roam_server::viewer::{Scene, ViewerCore, ViewerLimits};

/// The data set served, to measure against.
#[derive(Clone)]
pub struct Truth {
    pub terrain: Arc<Terrain>,
    pub variance: Arc<VarianceTree>,
    /// The guard band the server's cut is made with (`--guard-deg`), degrees.
    pub guard_deg: f32,
}

impl std::fmt::Debug for Truth {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Truth({}² samples)", self.terrain.heights.side())
    }
}

/// Follows the decoded cut frame by frame and measures each frame's fogged error.
pub(super) struct FoggedError {
    truth: Truth,
    core: ViewerCore,
    scratch: Scratch,
    split: DiamondMap<u16>,
}

impl FoggedError {
    /// For a viewer that said `hello` (its camera's shape), from the empty cut.
    pub(super) fn new(truth: Truth, hello: &Hello) -> FoggedError {
        let core = ViewerCore::for_hello(&truth.terrain, 1, hello, ViewerLimits::default());
        let scratch = Scratch::new(truth.terrain.heights.side(), 1);
        FoggedError {
            truth,
            core,
            scratch,
            split: DiamondMap::new(),
        }
    }

    /// The next frame: the diamonds it toggled (with their heights) and the viewer's
    /// vehicle in it; its fogged error in pixels.
    pub(super) fn frame(&mut self, toggled: &[(u32, u16)], vehicle: &VehicleView) -> f32 {
        for &(d, h) in toggled {
            self.split.toggle(d, h);
        }
        let t = &self.truth;
        let scene = Scene {
            terrain: &t.terrain,
            variance: &t.variance,
            scratch: &self.scratch,
        };
        let state = VehicleState {
            x: vehicle.x,
            z: vehicle.z,
            speed: vehicle.speed,
            heading: vehicle.heading,
        };
        let camera = self.core.camera_at(&scene, &state);
        let map = &t.terrain.map;
        let split = &self.split;
        fogged_error_px(
            &t.terrain.heights,
            &t.variance,
            Scales {
                h: map.h_scale,
                v: map.v_scale,
            },
            &camera,
            map.fog_density as f32,
            t.guard_deg,
            |i| split.contains(i),
        )
    }
}
