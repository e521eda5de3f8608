//! Fog-aware priority (issue 24): a diamond's screen-space error times the fog's
//! transmission over the nearest distance to its bounding prism. Density 0 gives exactly
//! the cuts of before; with fog the cuts stay conforming, within budget and culled, and
//! the far ground is refined less.

use crate::tess;

use roam_protocol::validate::check_mesh;
use roam_server::Heightfield;
use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::camera::Camera;
use roam_server::tessellate::{Coherent, Limits, Mesh, Mode, Scratch, fogged_error_px};
use tess::{camera, check_frustum, is_split, measured_both, run, scales, terrain};

fn limits(budget: u32, threshold_px: f32, fog_density: f32) -> Limits {
    Limits {
        budget,
        threshold_px,
        fog_density,
        guard_deg: 0.0,
    }
}

/// FNV-1a over 64-bit words: a digest of cuts.
struct Digest(u64);

impl Digest {
    fn new() -> Digest {
        Digest(0xcbf2_9ce4_8422_2325)
    }

    fn add(&mut self, v: u64) {
        for b in v.to_le_bytes() {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x100_0000_01b3);
        }
    }
}

/// The from-scratch tessellator's meshes (vertices, indices, error bound, counts) over two
/// terrains, four cameras and three limits.
fn scratch_digest() -> u64 {
    let mut d = Digest::new();
    for (seed, rough) in [(1, 0.3), (2, 1.0)] {
        let hf = terrain(7, seed, rough);
        let vt = VarianceTree::build(&hf, 1, &mut |_, _| {});
        for (gx, gz, above, yaw, pitch, fov) in [
            (64.0, 64.0, 40.0, 0.0, -10.0, 60.0),
            (5.0, 120.0, 10.0, 135.0, -20.0, 60.0),
            (100.0, 30.0, 300.0, 250.0, -45.0, 90.0),
            (-20.0, -20.0, 50.0, 45.0, -5.0, 40.0),
        ] {
            let cam = camera(&hf, gx, gz, above, yaw, pitch, fov);
            for (budget, threshold) in [(300, 0.0), (4000, 0.0), (4000, 1.0)] {
                let (mesh, t) = run(&hf, &vt, &cam, limits(budget, threshold, 0.0));
                for [x, z] in &mesh.vertices {
                    d.add(u64::from(*x) << 16 | u64::from(*z));
                }
                for i in &mesh.indices {
                    d.add(u64::from(*i));
                }
                d.add(u64::from(mesh.error_bound_px.to_bits()));
                let s = t.stats();
                for v in [s.evaluated, s.culled, s.popped, s.split, s.forcing] {
                    d.add(u64::from(v));
                }
            }
        }
    }
    d.0
}

/// The split/merge tessellator along a drive with turns, a pitch wobble and a jump, with
/// and without a threshold: every frame's changes in order, mode, triangles, error bound
/// and counts (what was evaluated follows from each evaluation's slack).
fn coherent_digest() -> u64 {
    let mut d = Digest::new();
    let hf = terrain(7, 5, 0.8);
    let vt = VarianceTree::build(&hf, 1, &mut |_, _| {});
    let pool = Scratch::new(hf.side(), 1);
    for threshold in [0.0, 0.5] {
        let mut c = Coherent::new(hf.side());
        for k in 0..80 {
            let f = f64::from(k);
            let jump = if k >= 50 { 50.0 } else { 0.0 };
            let (gx, gz) = (20.0 + 0.7 * f + jump, 30.0 + 0.4 * f);
            let yaw = 40.0 + f64::from(k % 20) * 0.8;
            let pitch = -10.0 + f64::from(k % 7) * 0.5;
            let cam = camera(&hf, gx, gz, 20.0, yaw, pitch, 60.0);
            let l = limits(2000, threshold, 0.0);
            let mode = c.frame(&hf, &vt, scales(), &cam, l, false, &pool);
            c.audit(&hf, &vt, scales(), &cam, l)
                .unwrap_or_else(|e| panic!("frame {k}: {e}"));
            for &p in c.changes() {
                d.add(u64::from(p));
            }
            d.add(u64::from(mode == Mode::Rebuild));
            d.add(u64::from(c.triangles()));
            d.add(u64::from(c.error_bound_px().to_bits()));
            let s = c.stats();
            for v in [s.evaluated, s.splits, s.merges, s.popped] {
                d.add(u64::from(v));
            }
        }
    }
    d.0
}

/// With no fog, the cuts are bit for bit those of the fog-unaware priority: digests taken
/// with the code before fog-aware priority (the multiplication by `exp(0)` = 1 is exact,
/// and the frame-coherent validity bound reduces to `clear · r / (1 + r)` exactly).
#[test]
fn density_0_gives_exactly_the_cuts_of_before() {
    assert_eq!(scratch_digest(), 0xdd36_abc5_96bf_e7d3, "from scratch");
    assert_eq!(coherent_digest(), 0x5040_0690_4587_8db7, "split/merge");
}

/// A camera: grid position, height above the ground, yaw, pitch, field of view.
type At = (f64, f64, f64, f64, f64, f64);

/// A cut's split diamonds.
type Cut = Vec<(u32, u32)>;

/// The from-scratch cut at `at` with fog of `density`, and the split/merge cut carried
/// to `at` along a short drive (turning into the view) in the same fog: both conforming,
/// within the budget, splitting nothing outside the view unless forced; the split/merge
/// cut passes its audit every frame (kept priorities where their evaluation puts them)
/// and knows its own error within the 2 % its kept priorities may drift; and the error a
/// cut leaves, measured through the fog, is the same by `measured_error` (a list of split
/// diamonds) and `fogged_error_px` (a predicate over grid indices).
fn check(levels: u32, seed: u64, rough: f64, at: At, budget: u32, density: f32) {
    let name = format!("levels {levels} seed {seed} at {at:?} budget {budget} fog {density}");
    let hf = terrain(levels, seed, rough);
    let vt = VarianceTree::build(&hf, 1, &mut |_, _| {});
    let (gx, gz, above, yaw, pitch, fov) = at;
    let cam = camera(&hf, gx, gz, above, yaw, pitch, fov);
    let l = limits(budget, 0.0, density);
    let (mesh, t) = run(&hf, &vt, &cam, l);
    check_mesh(&mesh.vertices, &mesh.indices, hf.size()).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert!(mesh.triangle_count() <= budget as usize, "{name}");
    check_frustum(&hf, &vt, &cam, t.split_diamonds()).unwrap_or_else(|e| panic!("{name}: {e}"));
    let split: Vec<(u32, u32)> = t.split_diamonds().collect();
    let measured = measured_both(&hf, &vt, &cam, l, &split, &name);
    // From scratch reports what its queue reached, which the measure includes.
    assert!(mesh.error_bound_px <= measured, "{name}");
    let pool = Scratch::new(hf.side(), 1);
    let mut c = Coherent::new(hf.side());
    let mut served = Mesh::default();
    for k in 0..24 {
        let f = f64::from(k);
        let cam = camera(
            &hf,
            gx - 0.5 * f,
            gz - 0.3 * f,
            above,
            yaw - 24.0 + f,
            pitch,
            fov,
        );
        c.frame(&hf, &vt, scales(), &cam, l, false, &pool);
        c.audit(&hf, &vt, scales(), &cam, l)
            .unwrap_or_else(|e| panic!("{name}, frame {k}: {e}"));
        c.mesh(&pool, &mut served);
        check_mesh(&served.vertices, &served.indices, hf.size())
            .unwrap_or_else(|e| panic!("{name}, frame {k}: {e}"));
        assert!(c.triangles() <= budget, "{name}, frame {k}");
        check_frustum(&hf, &vt, &cam, c.split_diamonds())
            .unwrap_or_else(|e| panic!("{name}, frame {k}: {e}"));
        let split: Vec<(u32, u32)> = c.split_diamonds().collect();
        let measured = measured_both(&hf, &vt, &cam, l, &split, &format!("{name}, frame {k}"));
        let bound = c.error_bound_px();
        assert!(
            (bound - measured).abs() <= 0.025 * measured,
            "{name}, frame {k}: {bound} px reported, {measured} measured"
        );
    }
}

#[test]
fn fogged_cuts_are_conforming_within_budget_culled_and_know_their_error() {
    // Light fog (a twentieth of the error left across the map) to fog that hides all but
    // the nearest cells; low and high eyes, looking across and down, a wide and a narrow
    // view, budgets from a few hundred to more than the map needs.
    check(
        7,
        1,
        0.5,
        (64.0, 64.0, 20.0, 30.0, -10.0, 60.0),
        3000,
        2.3e-3,
    );
    check(7, 2, 1.0, (10.0, 10.0, 5.0, 45.0, -5.0, 60.0), 800, 1e-2);
    check(
        7,
        3,
        0.2,
        (120.0, 60.0, 400.0, 270.0, -60.0, 90.0),
        6000,
        2.3e-3,
    );
    check(
        6,
        4,
        0.8,
        (32.0, 60.0, 30.0, 180.0, -15.0, 30.0),
        1500,
        5e-2,
    );
    check(
        5,
        5,
        1.0,
        (16.0, 16.0, 10.0, 90.0, -20.0, 60.0),
        100_000,
        5e-3,
    );
    check(7, 6, 0.6, (-10.0, 70.0, 50.0, 90.0, -8.0, 60.0), 2000, 1e-3);
}

/// How far each split diamond's centre is from the eye, world units.
fn distances(hf: &Heightfield, cam: &Camera, split: impl Iterator<Item = (u32, u32)>) -> Vec<f64> {
    let s = scales();
    split
        .map(|(x, z)| {
            let p = [
                f64::from(x) * s.h,
                f64::from(hf.get(x, z)) * s.v,
                f64::from(z) * s.h,
            ];
            (0..3)
                .map(|i| (p[i] - cam.eye[i]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect()
}

/// With fog, the same camera and budget refine the far ground less: the split diamonds are
/// nearer on average, fewer lie beyond the median distance of the fog-unaware cut's, and
/// the error the fog lets through is smaller (what the fog-aware priority is for). So do
/// the split/merge cuts, carried along a short drive.
#[test]
fn with_fog_the_far_ground_is_refined_less() {
    let check = |levels: u32, seed: u64, at: At, budget: u32, density: f32| {
        let name = format!("levels {levels} seed {seed} at {at:?} budget {budget} fog {density}");
        let hf = terrain(levels, seed, 0.7);
        let vt = VarianceTree::build(&hf, 1, &mut |_, _| {});
        let (gx, gz, above, yaw, pitch, fov) = at;
        let pool = Scratch::new(hf.side(), 1);
        let (mut plain_cut, mut fog_cut) = (Coherent::new(hf.side()), Coherent::new(hf.side()));
        let (plain, fog) = (limits(budget, 0.0, 0.0), limits(budget, 0.0, density));
        for k in 0..=8 {
            let cam = camera(&hf, gx + f64::from(k), gz, above, yaw, pitch, fov);
            plain_cut.frame(&hf, &vt, scales(), &cam, plain, false, &pool);
            fog_cut.frame(&hf, &vt, scales(), &cam, fog, false, &pool);
            if k < 8 {
                continue;
            }
            let (_, a) = run(&hf, &vt, &cam, plain);
            let (_, b) = run(&hf, &vt, &cam, fog);
            let (a, b): (Cut, Cut) = (a.split_diamonds().collect(), b.split_diamonds().collect());
            let (c, d): (Cut, Cut) = (
                plain_cut.split_diamonds().collect(),
                fog_cut.split_diamonds().collect(),
            );
            for (how, without, with) in [("from scratch", a, b), ("split/merge", c, d)] {
                let (d0, d1) = (
                    distances(&hf, &cam, without.iter().copied()),
                    distances(&hf, &cam, with.iter().copied()),
                );
                let mean = |d: &[f64]| d.iter().sum::<f64>() / d.len() as f64;
                assert!(
                    mean(&d1) < mean(&d0),
                    "{name}, {how}: mean {} !< {}",
                    mean(&d1),
                    mean(&d0)
                );
                let mut sorted = d0.clone();
                sorted.sort_by(f64::total_cmp);
                let median = sorted[sorted.len() / 2];
                let beyond = |d: &[f64]| d.iter().filter(|&&x| x > median).count();
                assert!(
                    beyond(&d1) < beyond(&d0),
                    "{name}, {how}: {} beyond {median:.0} with fog, {} without",
                    beyond(&d1),
                    beyond(&d0)
                );
                let seen = |split: &[(u32, u32)]| {
                    fogged_error_px(&hf, &vt, scales(), &cam, density, 0.0, is_split(&hf, split))
                };
                let (e0, e1) = (seen(&without), seen(&with));
                assert!(
                    e1 < e0,
                    "{name}, {how}: {e1} px through the fog, {e0} without fog priority"
                );
            }
        }
    };
    check(7, 11, (20.0, 64.0, 15.0, 90.0, -5.0, 60.0), 3000, 2.3e-3);
    check(7, 12, (64.0, 10.0, 40.0, 0.0, -10.0, 60.0), 2500, 5e-3);
    check(8, 13, (30.0, 30.0, 20.0, 45.0, -5.0, 60.0), 8000, 1.2e-3);
}
