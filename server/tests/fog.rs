//! Fog-aware priority (issue 24): a diamond's screen-space error times the fog's
//! transmission over the nearest distance to its bounding prism. Density 0 gives exactly
//! the cuts of before; with fog the cuts stay conforming, within budget and culled, and
//! the far ground is refined less.

mod tess;

use roam_server::terrain::variance::VarianceTree;
use roam_server::tessellate::{Coherent, Limits, Scratch};
use tess::{camera, run, scales, terrain};

fn limits(budget: u32, threshold_px: f32) -> Limits {
    Limits {
        budget,
        threshold_px,
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
                let (mesh, t) = run(&hf, &vt, &cam, limits(budget, threshold));
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
    let pool = Scratch::new(hf.side());
    for threshold in [0.0, 0.5] {
        let mut c = Coherent::new(hf.side());
        for k in 0..80 {
            let f = f64::from(k);
            let jump = if k >= 50 { 50.0 } else { 0.0 };
            let (gx, gz) = (20.0 + 0.7 * f + jump, 30.0 + 0.4 * f);
            let yaw = 40.0 + f64::from(k % 20) * 0.8;
            let pitch = -10.0 + f64::from(k % 7) * 0.5;
            let cam = camera(&hf, gx, gz, 20.0, yaw, pitch, 60.0);
            let l = limits(2000, threshold);
            let mode = c.frame(&hf, &vt, scales(), &cam, l, false, &pool);
            c.audit(&hf, &vt, scales(), &cam, l)
                .unwrap_or_else(|e| panic!("frame {k}: {e}"));
            for &p in c.changes() {
                d.add(u64::from(p));
            }
            d.add(u64::from(mode == roam_server::tessellate::Mode::Rebuild));
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
