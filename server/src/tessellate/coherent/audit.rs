//! A check of the carried cut against what it must be, recomputed from the split set
//! alone: for tests (it walks the whole map).

use super::eval::fixed;
use super::{Coherent, pack, unpack};
use crate::terrain::heightfield::Heightfield;
use crate::terrain::variance::VarianceTree;
use crate::tessellate::camera::Camera;
use crate::tessellate::{Limits, Scales};

impl Coherent {
    /// Checks the cut after a frame at `camera`: the triangle and split counts, both
    /// frontiers and the values kept beside their members equal a recomputation from the
    /// split set; the cut is closed under parent; and every split diamond that nothing
    /// forces (a merge candidate) is worth splitting at this camera: in view (or under the
    /// eye), with error, at or above the threshold.
    pub fn audit(
        &self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) -> Result<(), String> {
        let split: Vec<u32> = self.split_diamonds().map(|(x, z)| pack(x, z)).collect();
        let is_split = |p: u32| {
            let (x, z) = unpack(p);
            self.tess.is_active(x, z)
        };
        let mut triangles = 2;
        let (mut splits, mut merges) = (Vec::new(), Vec::new());
        for &p in &split {
            let (x, z) = unpack(p);
            if let Some(q) = self
                .parents(x, z)
                .into_iter()
                .flatten()
                .find(|&q| !is_split(q))
            {
                return Err(format!(
                    "split {:?} has the unsplit parent {:?}",
                    unpack(p),
                    unpack(q)
                ));
            }
            triangles += self.added(x, z);
            let children: Vec<u32> = self.children(x, z).into_iter().flatten().collect();
            splits.extend(children.iter().filter(|&&c| !is_split(c)));
            if !children.iter().any(|&c| is_split(c)) {
                merges.push(p);
            }
        }
        if split.is_empty() {
            splits.push(self.root());
        }
        if (triangles, split.len() as u32) != (self.triangles, self.split_count) {
            return Err(format!(
                "{} triangles and {} splits counted, {triangles} and {} in the cut",
                self.triangles,
                self.split_count,
                split.len()
            ));
        }
        let sorted = |v: &[u32]| {
            let mut v = v.to_vec();
            v.sort_unstable();
            v.dedup();
            v
        };
        for (name, kept, want) in [
            ("split", self.split_cands.as_slice(), &splits),
            ("merge", self.merge_cands.as_slice(), &merges),
        ] {
            let (kept, want) = (sorted(kept), sorted(want));
            if kept != want {
                let missing = want
                    .iter()
                    .filter(|p| kept.binary_search(p).is_err())
                    .count();
                let extra = kept
                    .iter()
                    .filter(|p| want.binary_search(p).is_err())
                    .count();
                return Err(format!(
                    "{name} candidates: {missing} missing, {extra} that should not be there"
                ));
            }
        }
        let f = self.tess.frame(hf, variance, scales, camera, limits);
        for set in [&self.split_cands, &self.merge_cands] {
            for (&p, v) in set.as_slice().iter().zip(set.values()) {
                if fixed(&f, p) != v.fixed {
                    return Err(format!("stale values kept beside {:?}", unpack(p)));
                }
            }
        }
        for chunk in merges.chunks(4) {
            let lanes = self.evaluate_at(&f, chunk);
            for (i, &p) in chunk.iter().enumerate() {
                if lanes.wanted >> i & 1 == 0 {
                    return Err(format!(
                        "{:?} is split, forced by nothing, but not worth splitting here \
                         (priority {} px)",
                        unpack(p),
                        lanes.prio[i]
                    ));
                }
            }
        }
        Ok(())
    }
}

/// The screen-space error a cut leaves at `camera`, in pixels, measured the same way for
/// any cut: the highest priority among the diamonds that could be split next (unsplit,
/// with a split parent) and are worth splitting (in view or under the eye, with error).
/// Split-only from scratch reports only what its queue reached, which misses a diamond
/// poking into the view below a parent wholly outside it; this measure does not, so the
/// served cut and the from-scratch one are compared fairly. Slow (a fresh tessellator's
/// bitset and a walk of the cut): for tests and benchmarks.
pub fn measured_error(
    hf: &Heightfield,
    variance: &VarianceTree,
    scales: Scales,
    camera: &Camera,
    limits: Limits,
    split: impl IntoIterator<Item = (u32, u32)>,
) -> f32 {
    let mut c = Coherent::new(hf.side());
    let split: Vec<u32> = split.into_iter().map(|(x, z)| pack(x, z)).collect();
    for &p in &split {
        let (x, z) = unpack(p);
        c.tess.set_active(x, z);
    }
    let mut candidates: Vec<u32> = Vec::new();
    for &p in &split {
        let (x, z) = unpack(p);
        for ch in c.children(x, z).into_iter().flatten() {
            let (cx, cz) = unpack(ch);
            if !c.tess.is_active(cx, cz) {
                candidates.push(ch);
            }
        }
    }
    if split.is_empty() {
        candidates.push(c.root());
    }
    candidates.sort_unstable();
    candidates.dedup();
    let f = c.tess.frame(hf, variance, scales, camera, limits);
    let mut worst = 0f32;
    for chunk in candidates.chunks(4) {
        let lanes = c.evaluate_at(&f, chunk);
        for (i, p) in lanes.prio.iter().enumerate().take(chunk.len()) {
            if (lanes.wanted | lanes.dropped) >> i & 1 != 0 {
                worst = worst.max(*p);
            }
        }
    }
    worst
}
