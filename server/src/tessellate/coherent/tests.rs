//! The cut carried across odometer rebases (`super::Coherent`'s own unit tests).

use super::*;

/// A cut carried across odometer rebases (both odometers started just short of one)
/// passes the audit every frame: every schedule shifted with its odometer, nothing due
/// left behind, evaluations still made.
#[test]
fn a_cut_is_carried_across_rebases() {
    let side = 65;
    let samples = (0..side * side)
        .map(|i| {
            let (x, z) = (f64::from(i % side), f64::from(i / side));
            (20_000.0 + 3_000.0 * (x * 0.37).sin() * (z * 0.23).cos() + 40.0 * x) as u16
        })
        .collect();
    let hf = Heightfield::new(side, samples).expect("side is 2^N + 1");
    let vt = VarianceTree::build(&hf, 1, &mut |_, _| {});
    let scales = Scales { h: 10.0, v: 0.02 };
    let limits = Limits {
        budget: 600,
        threshold_px: 0.0,
        fog_density: 0.0,
        guard_deg: 0.0,
    };
    let scratch = Scratch::new(side, 1);
    let mut c = Coherent::new(side);
    let mut evaluated = 0;
    let camera_at = |k: u32| {
        let t = f64::from(k);
        Camera {
            eye: [200.0 + 3.0 * t, 300.0, 150.0 + 1.0 * t],
            yaw_deg: 20.0 + 6.0 * (t * 0.7).sin(),
            pitch_deg: -15.0,
            fov_y_deg: 60.0,
            width: 640,
            height: 480,
        }
    };
    for k in 0..40 {
        let camera = camera_at(k);
        if k == 1 {
            // A few metres and milliradians short of their keys' limit.
            for o in &mut c.odometers {
                o.reading = o.base + (f64::from(1u32 << 31) - 20_000.0) / o.scale;
            }
        }
        c.frame(&hf, &vt, scales, &camera, limits, false, &scratch);
        c.audit(&hf, &vt, scales, &camera, limits)
            .unwrap_or_else(|e| panic!("frame {k}: {e}"));
        evaluated += c.stats().evaluated;
    }
    for o in &c.odometers {
        assert!(o.base > 0.0 && o.now() < 1 << 30, "rebased");
    }
    assert!(evaluated > 0);
    // A count kept wrong fails the audit, which names the counts kept and recounted.
    let (triangles, splits) = (c.triangles, c.split_count);
    c.triangles += 2;
    let e = c
        .audit(&hf, &vt, scales, &camera_at(39), limits)
        .expect_err("a triangle count two off");
    assert_eq!(
        e,
        AuditError::Counts {
            triangles: triangles + 2,
            splits,
            cut_triangles: triangles,
            cut_splits: splits as usize,
        }
    );
    assert_eq!(
        e.to_string(),
        format!(
            "{} triangles and {splits} splits counted, {triangles} and {splits} in the cut",
            triangles + 2
        )
    );
}
