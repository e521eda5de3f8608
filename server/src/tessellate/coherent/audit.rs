//! A check of the carried cut against what it must be, recomputed from the split set
//! alone: for tests (it walks the whole map).

use super::eval::fixed;
use super::{Coherent, Frontier, pack, unpack};
use crate::terrain::heightfield::Heightfield;
use crate::terrain::variance::VarianceTree;
use crate::tessellate::Frame;
use crate::tessellate::camera::Camera;
use crate::tessellate::queue::{TOP, bucket_of};
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
        let is_split = |p: u32| self.split.contains(p);
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
            ("split", self.splits.cands.as_slice(), &splits),
            ("merge", self.merges.cands.as_slice(), &merges),
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
        let f = Frame::new(hf, variance, scales, camera, limits);
        for set in [&self.splits.cands, &self.merges.cands] {
            for (&p, v) in set.as_slice().iter().zip(set.values()) {
                if fixed(&f, p) != v.fixed {
                    return Err(format!("stale values kept beside {:?}", unpack(p)));
                }
            }
        }
        queued("split", &self.splits, |e| {
            (e.flags & 1 != 0).then(|| {
                if e.flags & 2 != 0 {
                    TOP
                } else {
                    bucket_of(e.prio)
                }
            })
        })?;
        queued("merge", &self.merges, |e| {
            (e.flags & 2 == 0).then(|| {
                if e.flags & 1 == 0 {
                    TOP
                } else {
                    TOP - 1 - bucket_of(e.prio)
                }
            })
        })?;
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

/// Checks that each member of a frontier has its newest evaluation queued exactly once,
/// in the bucket `bucket` gives (none: not queued), and scheduled on both odometers
/// unless it is never due.
fn queued(
    name: &str,
    fr: &Frontier,
    bucket: impl Fn(&super::eval::Entry) -> Option<usize>,
) -> Result<(), String> {
    let mut count = std::collections::HashMap::<u32, usize>::new();
    for (b, s) in fr.queue.entries() {
        if let Some(e) = fr.live(s) {
            if bucket(e) != Some(b) {
                return Err(format!(
                    "{name} candidate {:?} queued in bucket {b}, {:?} by its evaluation",
                    unpack(s.pos),
                    bucket(e)
                ));
            }
            *count.entry(s.pos).or_default() += 1;
        }
    }
    for (&p, e) in fr.cands.as_slice().iter().zip(fr.cands.values()) {
        let want = usize::from(bucket(e).is_some());
        let got = count.get(&p).copied().unwrap_or(0);
        if got != want {
            return Err(format!(
                "{name} candidate {:?} queued {got} times, {want} by its evaluation",
                unpack(p)
            ));
        }
    }
    for (odometer, schedule, reading) in [
        (
            "travel",
            &fr.due_moved,
            (|e| e.due_moved) as fn(&super::eval::Entry) -> f64,
        ),
        ("turn", &fr.due_turned, |e| e.due_turned),
    ] {
        let mut scheduled = std::collections::HashSet::new();
        for (at, s) in schedule.entries() {
            if let Some(e) = fr.live(s)
                && at == reading(e)
            {
                scheduled.insert(s.pos);
            }
        }
        for (&p, e) in fr.cands.as_slice().iter().zip(fr.cands.values()) {
            if reading(e).is_finite() && !scheduled.contains(&p) {
                return Err(format!(
                    "{name} candidate {:?} is not scheduled by its {odometer}",
                    unpack(p)
                ));
            }
        }
    }
    Ok(())
}

/// The screen-space error a cut leaves at `camera`, in pixels, measured the same way for
/// any cut: the highest priority among the diamonds that could be split next (unsplit,
/// with a split parent) and are worth splitting (in view or under the eye, with error).
/// Split-only from scratch reports only what its queue reached, which misses a diamond
/// poking into the view below a parent wholly outside it; this measure does not, so the
/// served cut and the from-scratch one are compared fairly. Slow (a walk of the cut): for tests and benchmarks.
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
        c.split.insert_with(p, || ());
    }
    let mut candidates: Vec<u32> = Vec::new();
    for &p in &split {
        let (x, z) = unpack(p);
        for ch in c.children(x, z).into_iter().flatten() {
            if !c.split.contains(ch) {
                candidates.push(ch);
            }
        }
    }
    if split.is_empty() {
        candidates.push(c.root());
    }
    candidates.sort_unstable();
    candidates.dedup();
    let f = Frame::new(hf, variance, scales, camera, limits);
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
