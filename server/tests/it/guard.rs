//! The guard band (issue 24): the frustum's side planes turned out, so the ground a
//! turning driver is about to see is refined before it comes into view. A guarded cut,
//! carried along a turning drive, stays conforming, within budget and culled by its own
//! wider frustum, passes its audit every frame, refines the band beside the view, and is
//! charged by the error measures only for what is in the view.

use crate::tess;

use roam_protocol::validate::check_mesh;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::camera::WorldPlane;
use roam_server::tessellate::{Coherent, Limits, Mesh, Scratch};
use tess::{camera, check_frustum_guarded, measured_both, scales, terrain};

const GUARD_DEG: f32 = 10.0;

/// Whether the world point `p` lies in the guard band: in the guarded frustum `wide`, not
/// in the view's `view`.
fn in_band(view: &[WorldPlane; 5], wide: &[WorldPlane; 5], p: [f64; 3]) -> bool {
    let inside = |planes: &[WorldPlane; 5]| planes.iter().all(|pl| pl.distance(p) >= 0.0);
    inside(wide) && !inside(view)
}

/// One drive: a low eye over rough ground turning left then right, a guarded and an
/// unguarded cut carried along it at the same budget and fog.
fn drive(levels: u32, seed: u64, start: (f64, f64), above: f64, budget: u32, density: f32) {
    let name = format!("levels {levels} seed {seed} from {start:?} budget {budget}");
    let hf = terrain(levels, seed, 1.0);
    let vt = VarianceTree::build(&hf, 1, &mut |_, _| {});
    let pool = Scratch::new(hf.side(), 1);
    let guarded = Limits {
        budget,
        threshold_px: 0.0,
        fog_density: density,
        guard_deg: GUARD_DEG,
    };
    let plain = Limits {
        guard_deg: 0.0,
        ..guarded
    };
    let (mut g, mut p) = (Coherent::new(hf.side()), Coherent::new(hf.side()));
    let mut served = Mesh::default();
    let (mut band_g, mut band_p) = (0u32, 0u32);
    for k in 0..40 {
        let f = f64::from(k);
        // Forward along +x while the yaw swings 30° left and back.
        let yaw = 90.0 - 30.0 * (f * std::f64::consts::PI / 20.0).sin();
        let cam = camera(&hf, start.0 + 0.4 * f, start.1, above, yaw, -8.0, 60.0);
        let at = format!("{name}, frame {k}");
        g.frame(&hf, &vt, scales(), &cam, guarded, false, &pool);
        p.frame(&hf, &vt, scales(), &cam, plain, false, &pool);
        g.audit(&hf, &vt, scales(), &cam, guarded)
            .unwrap_or_else(|e| panic!("{at}: {e}"));
        g.mesh(&pool, &mut served);
        check_mesh(&served.vertices, &served.indices, hf.size())
            .unwrap_or_else(|e| panic!("{at}: {e}"));
        assert!(g.triangles() <= budget, "{at}");
        check_frustum_guarded(&hf, &vt, &cam, f64::from(GUARD_DEG), g.split_diamonds())
            .unwrap_or_else(|e| panic!("{at}: {e}"));
        // The error in the view: the same by both measures, and within what the cut
        // knows of its own (which covers the band too, so it is at least the view's).
        let split: Vec<(u32, u32)> = g.split_diamonds().collect();
        let measured = measured_both(&hf, &vt, &cam, guarded, &split, &at);
        let bound = g.error_bound_px();
        assert!(
            measured <= bound * 1.025,
            "{at}: {measured} px in the view, the cut knows of {bound} px"
        );
        let s = scales();
        let centre = |&(x, z): &(u32, u32)| {
            [
                f64::from(x) * s.h,
                f64::from(hf.get(x, z)) * s.v,
                f64::from(z) * s.h,
            ]
        };
        let (view, wide) = (cam.frustum(), cam.frustum_widened(f64::from(GUARD_DEG)));
        let band = |d: &(u32, u32)| in_band(&view, &wide, centre(d));
        band_g += split.iter().filter(|d| band(d)).count() as u32;
        band_p += p.split_diamonds().filter(|d| band(d)).count() as u32;
    }
    assert!(
        band_g * 4 > band_p * 5,
        "{name}: {band_g} splits in the band with the guard, {band_p} without"
    );
}

#[test]
fn guarded_cuts_are_conforming_culled_refine_the_band_and_are_charged_for_the_view() {
    drive(7, 11, (20.0, 64.0), 3.0, 3000, 0.0);
    drive(7, 12, (30.0, 40.0), 1.5, 2000, 5e-3);
    drive(8, 13, (60.0, 128.0), 6.0, 6000, 2.3e-3);
}
