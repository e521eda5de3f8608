//! A check of the carried cut against what it must be, recomputed from the split set
//! alone: for tests (it walks the whole map). And the error a cut leaves, measured the
//! same way for any cut ([`measured_error`]; [`fogged_error_px`] through the viewer's fog,
//! whichever priority chose the cut): for tests and benchmarks.

use super::audit_error::AuditError;
use super::eval::fixed;
use super::frontier::Frontier;
use super::frontier::{Member, UNDER, WANTED};
use super::{Coherent, pack, unpack};
use crate::terrain::heightfield::Heightfield;
use crate::terrain::variance::VarianceTree;
use crate::tessellate::Frame;
use crate::tessellate::camera::Camera;
use crate::tessellate::queue::{TOP, bucket_of};
use crate::tessellate::{Limits, Scales};

impl Coherent {
    /// Checks the cut after a frame at `camera`: the triangle and split counts and both
    /// frontiers equal a recomputation from the split set; the cut is closed under parent;
    /// each frontier's index finds every member where it is, each member is queued exactly
    /// once, in the bucket its kept evaluation gives (or in none), and scheduled on both
    /// odometers when it has error (on neither when it is exact), each schedule's lists
    /// well formed; and, unless the frame stopped at its allowance, every split diamond
    /// that nothing forces (a merge candidate) is worth splitting at this camera: in view
    /// (or under the eye), with error, at or above the threshold.
    pub fn audit(
        &self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) -> Result<(), AuditError> {
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
                return Err(AuditError::UnsplitParent {
                    split: unpack(p),
                    parent: unpack(q),
                });
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
            return Err(AuditError::Counts {
                triangles: self.triangles,
                splits: self.split_count,
                cut_triangles: triangles,
                cut_splits: split.len(),
            });
        }
        let sorted = |v: &[u32]| {
            let mut v = v.to_vec();
            v.sort_unstable();
            v.dedup();
            v
        };
        for (frontier, fr, want) in [
            ("split", &self.splits, &splits),
            ("merge", &self.merges, &merges),
        ] {
            let kept: Vec<u32> = fr.members().map(|m| m.pos).collect();
            if sorted(&kept).len() != kept.len() {
                return Err(AuditError::ListedTwice { frontier });
            }
            let (kept, want) = (sorted(&kept), sorted(want));
            if kept != want {
                let missing = want
                    .iter()
                    .filter(|p| kept.binary_search(p).is_err())
                    .count();
                let extra = kept
                    .iter()
                    .filter(|p| want.binary_search(p).is_err())
                    .count();
                return Err(AuditError::Candidates {
                    frontier,
                    missing,
                    extra,
                });
            }
        }
        let f = Frame::new(hf, variance, scales, camera, limits);
        let now = [self.odometers[0].now(), self.odometers[1].now()];
        queued("split", &self.splits, &f, now, |m| {
            (m.flags & WANTED != 0).then(|| {
                if m.flags & UNDER != 0 {
                    TOP
                } else {
                    bucket_of(m.prio)
                }
            })
        })?;
        queued("merge", &self.merges, &f, now, |m| {
            (m.flags & UNDER == 0).then(|| {
                if m.flags & WANTED == 0 {
                    TOP
                } else {
                    TOP - 1 - bucket_of(m.prio)
                }
            })
        })?;
        // A frame stopped at its allowance may leave splits that are no longer wanted,
        // for the frames after to merge.
        if self.stats.short {
            return Ok(());
        }
        for chunk in merges.chunks(4) {
            let lanes = self.evaluate_at(&f, chunk);
            for (i, &p) in chunk.iter().enumerate() {
                if lanes.wanted >> i & 1 == 0 {
                    return Err(AuditError::Unforced {
                        at: unpack(p),
                        prio: lanes.prio[i],
                    });
                }
            }
        }
        Ok(())
    }
}

/// Checks a frontier's index, queue and schedules: each member indexed where it is;
/// queued exactly once, in the bucket `bucket` gives its kept evaluation (none: not
/// queued), which the frontier's own rule agrees with; scheduled exactly once on each
/// odometer when it has error, on neither when it is exact (never due again), and not
/// before the odometers' keys `now` (what was due was taken); the lists well formed (each
/// member's previous names the one before it, each bucket marked as it is, each schedule
/// key in its bucket).
fn queued(
    frontier: &'static str,
    fr: &Frontier,
    f: &Frame,
    now: [u32; 2],
    bucket: impl Fn(&Member) -> Option<usize>,
) -> Result<(), AuditError> {
    // By place, free places' records included (neither queued nor scheduled).
    let members: Vec<Member> = fr.records().copied().collect();
    if !fr.free_listed() {
        return Err(AuditError::FreeListedWrong { frontier });
    }
    let (queue, schedules) = fr
        .lists()
        .map_err(|error| AuditError::Lists { frontier, error })?;
    let mut count = vec![0usize; members.len()];
    for &(b, i) in &queue {
        let m = &members[i as usize];
        if bucket(m) != Some(b) {
            return Err(AuditError::Bucket {
                frontier,
                at: unpack(m.pos),
                bucket: b,
                by_evaluation: bucket(m),
            });
        }
        count[i as usize] += 1;
    }
    for (i, m) in members.iter().enumerate() {
        if m.is_free() {
            if count[i] != 0 || m.queued() || m.due(0).is_some() || m.due(1).is_some() {
                return Err(AuditError::FreeQueued { frontier, place: i });
            }
            continue;
        }
        if !fr.indexed(i) {
            let at = unpack(m.pos);
            return Err(AuditError::NotIndexed { frontier, at });
        }
        let want = usize::from(bucket(m).is_some());
        if count[i] != want || bucket(m) != fr.queue_bucket(m) || m.queued() != (want == 1) {
            return Err(AuditError::Queued {
                frontier,
                at: unpack(m.pos),
                times: count[i],
                want,
            });
        }
    }
    for (k, (odometer, list)) in ["travel", "turn"].iter().zip(schedules).enumerate() {
        let mut count = vec![0usize; members.len()];
        for i in list {
            count[i as usize] += 1;
        }
        for (i, m) in members.iter().enumerate() {
            if m.is_free() {
                if count[i] != 0 {
                    return Err(AuditError::FreeScheduled { frontier, place: i });
                }
                continue;
            }
            let exact = fixed(f, m.pos).exact();
            let want = usize::from(!exact);
            if count[i] != want || m.due(k).is_some() == exact {
                return Err(AuditError::Scheduled {
                    frontier,
                    at: unpack(m.pos),
                    times: count[i],
                    odometer,
                    want,
                });
            }
            if let Some(key) = m.due(k)
                && key < now[k]
            {
                return Err(AuditError::Overdue {
                    frontier,
                    at: unpack(m.pos),
                    odometer,
                    key,
                    now: now[k],
                });
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
/// served cut and the from-scratch one are compared fairly. The priority is `limits`'s:
/// with a fog density, the error the fog lets through. "In view" is the view's frustum,
/// whatever guard band `limits` has; the guard band's frustum only culls more of what the
/// conservative test lets through ([`view_frames`]). Slow (a walk of the cut): for
/// tests and benchmarks.
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
        c.split.insert(p);
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
    worst(
        &c,
        &view_frames(hf, variance, scales, camera, limits),
        &candidates,
    )
}

/// The screen-space error a cut shows through the viewer's fog, in pixels, whichever
/// priority chose the cut: the largest `e · px / d · exp(−density · max(clear, 0))` over
/// the diamonds that hold the mesh's triangles (unsplit, with a split parent) and are in
/// view or under the eye, `clear` the distance from the eye to the diamond's bounding
/// prism (`d` that, at least 1 mm). The fog-aware priority's error bound is this, for the
/// fog-unaware one it is not.
///
/// The cut is `is_split`: whether the diamond centred at row-major grid index `i` (`z ·
/// side + x`, as `roam_protocol::Grid::index` numbers it and a decoded cut's split set
/// holds it) is split; it must be closed under parent, as every cut the tessellators make
/// and the codec decodes is (a split diamond below an unsplit one is not reached).
/// `camera` is the one the server tessellated that frame for (its eye, yaw, pitch, field
/// of view and viewport), `fog_density` the map's (the viewer's `Welcome::fog_density`),
/// per world unit, `guard_deg` the cut's guard band (`Limits::guard_deg`; in view is the
/// view's frustum, which the guard band's holds: [`view_frames`]). Slow (a walk of the cut from the root): for tests and benchmarks.
pub fn fogged_error_px(
    hf: &Heightfield,
    variance: &VarianceTree,
    scales: Scales,
    camera: &Camera,
    fog_density: f32,
    guard_deg: f32,
    is_split: impl Fn(u32) -> bool,
) -> f32 {
    let c = Coherent::new(hf.side());
    let side = hf.side();
    let split = |p: u32| {
        let (x, z) = unpack(p);
        is_split(z * side + x)
    };
    let mut seen = std::collections::HashSet::from([c.root()]);
    let (mut stack, mut candidates) = (vec![c.root()], Vec::new());
    while let Some(p) = stack.pop() {
        if !split(p) {
            candidates.push(p);
            continue;
        }
        let (x, z) = unpack(p);
        for ch in c.children(x, z).into_iter().flatten() {
            if seen.insert(ch) {
                stack.push(ch);
            }
        }
    }
    candidates.sort_unstable();
    let limits = Limits {
        budget: 2,
        threshold_px: 0.0,
        fog_density,
        guard_deg,
    };
    worst(
        &c,
        &view_frames(hf, variance, scales, camera, limits),
        &candidates,
    )
}

/// The frames a measure tests a diamond against: the view's (no guard band) and, with a
/// guard band, the cut's. The frustum test is conservative (a prism is culled only when it
/// is wholly outside one plane), so a prism beside the eye, straddling the near plane, can
/// pass the view's test though nothing of it is in the view; the cut's widened planes may
/// cull it, and since they hold the view's in front of the near plane (a side plane turned
/// out keeps every point in front of the eye it kept), what they cull is not in the view
/// either. Measured against the view's planes alone, a guarded cut was charged such a
/// diamond's error at its distance from the eye (under 1 mm): `serve_fogged_error_px_p99`
/// 598,597 px with `bench --guard-deg 10` on a rough 4097² map, 1.78 with both (1.63
/// without the guard band, whose cut splits such diamonds: its own test lets them
/// through).
fn view_frames<'a>(
    hf: &'a Heightfield,
    variance: &'a VarianceTree,
    scales: Scales,
    camera: &Camera,
    limits: Limits,
) -> Vec<Frame<'a>> {
    let view = Limits {
        guard_deg: 0.0,
        ..limits
    };
    let mut frames = vec![Frame::new(hf, variance, scales, camera, view)];
    if limits.guard_deg > 0.0 {
        frames.push(Frame::new(hf, variance, scales, camera, limits));
    }
    frames
}

/// The highest priority among `candidates` in view (or under the eye) with error, in view
/// in every one of `frames` (the same camera and priority; [`view_frames`]).
fn worst(c: &Coherent, frames: &[Frame], candidates: &[u32]) -> f32 {
    let mut worst = 0f32;
    for chunk in candidates.chunks(4) {
        let mut shown = u32::MAX;
        let mut prio = [0f32; 4];
        for f in frames {
            let lanes = c.evaluate_at(f, chunk);
            shown &= lanes.wanted | lanes.dropped;
            prio = lanes.prio;
        }
        for (i, p) in prio.iter().enumerate().take(chunk.len()) {
            if shown >> i & 1 != 0 {
                worst = worst.max(*p);
            }
        }
    }
    worst
}
