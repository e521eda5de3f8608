//! Frame-coherent ROAM: a viewer's cut carried from frame to frame with splits and merges
//! (Duchaineau et al. 1997, §5–7), so the work per frame follows what changed.
//!
//! The cut is the split set in the tessellator's `active` bitset. Two frontiers are kept
//! incrementally as [`PosSet`]s: **split candidates** (unsplit diamonds with at least one
//! split parent: what from-scratch split-only would have queued) and **merge candidates**
//! (split diamonds none of whose children are split). Each frame:
//!
//! 1. Frontier diamonds are evaluated with the very function the from-scratch tessellator
//!    uses ([`super::evaluate::priority`]), four at a time, but only when due (ROAM's
//!    deferred priority recomputation, §7.3): each evaluation also says how far the eye may
//!    travel, and how far it may turn, before the diamond's priority could drift by 2 %
//!    (its distance changes by at most the eye's travel), its frustum verdict could flip
//!    (a plane through the eye moves a point at distance `r` by at most travel + `r` ×
//!    turn, and the verdict holds while that stays under the prism's margin to the plane),
//!    or the eye could enter or leave its footprint; two odometers (travel and turn,
//!    summed over frames) say when. Diamonds under the eye are evaluated every frame,
//!    exact ones never again. Every frontier diamond is then queued by its kept
//!    evaluation in two bucket queues: splits highest first, merges lowest first.
//!    Merge candidates that are exact, wholly outside the view pyramid or below the
//!    threshold are *unwanted*: from scratch would not have split them, so they are merged
//!    first, whatever the budget. The diamonds under the eye are never merged.
//! 2. While over budget, the lowest merge candidate is merged. Otherwise the highest split
//!    candidate is split (with its forced splits, exactly as from scratch) if it fits the
//!    budget; if it does not, the lowest merge candidate is merged instead when its
//!    priority is strictly below the split's, and the loop stops when it is not.
//!    Splits and merges update both frontiers and queue the diamonds they uncover.
//! 3. The frame's changes are logged in order (a diamond may appear twice: split, then
//!    merged); the codec composes logs into the difference from any base a viewer holds.
//!
//! The loop is bounded (a quarter of the budget plus 256 changes); a frame that reaches
//! the bound, a camera jump (a turn of more than 30°, a move of more than 64 grid cells),
//! a new field of view or viewport, a budget change of more than ×2, or the caller's say
//! rebuilds the cut from scratch with split-only ROAM, the spec's algorithm, and logs the
//! difference from the old cut.
//!
//! **Cost**: on `kossou` at 32,768 triangles, a frame of driving evaluates 10 to 14 of
//! some 26,000 frontier diamonds, and queuing every frontier diamond (a push each) is most
//! of what is left; the split/merge loop and the log are proportional to the change.

mod audit;
mod eval;

pub use audit::measured_error;

use self::eval::{Entry, Lanes, fixed};
use super::frontier::PosSet;
use super::{Frame, Limits, Mesh, Scales, Tessellator, classify, pack, unpack};
use crate::terrain::heightfield::Heightfield;
use crate::terrain::variance::VarianceTree;
use crate::tessellate::camera::Camera;
use crate::tessellate::diamond::Shape;
use crate::tessellate::queue::{BucketQueue, TOP, bucket_of};

/// How the last frame's cut was made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// From scratch (split-only ROAM), the difference from the old cut logged.
    Rebuild,
    /// The old cut, split and merged.
    Update,
}

/// Counts from the last frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CoherentStats {
    /// Frontier diamonds whose priority was computed.
    pub evaluated: u32,
    /// Diamonds split and merged (forced splits included).
    pub splits: u32,
    pub merges: u32,
}

/// The camera and limits of the last frame, to tell a jump from a step.
#[derive(Clone, Copy)]
struct Last {
    camera: Camera,
    budget: u32,
    threshold_px: f32,
}

/// One viewer's cut, carried from frame to frame.
pub struct Coherent {
    tess: Tessellator,
    split_cands: PosSet<Entry>,
    merge_cands: PosSet<Entry>,
    /// How far the eye has travelled (world units) and turned (radians), summed over the
    /// frames: the odometers a kept evaluation is due against.
    moved: f64,
    turned: f64,
    split_q: BucketQueue,
    /// Buckets inverted (lowest priority first); `TOP` holds unwanted splits.
    merge_q: BucketQueue,
    /// This frame's changes (packed positions), in order.
    log: Vec<u32>,
    /// Scratch for rebuilds: the old split set, row-major.
    old: Vec<u32>,
    triangles: u32,
    split_count: u32,
    error_bound_px: f32,
    dropped: f32,
    last: Option<Last>,
    mode: Mode,
    stats: CoherentStats,
}

/// Rebuild rather than update past these camera changes.
const JUMP_DEGREES: f64 = 30.0;
const JUMP_CELLS: f64 = 64.0;

impl Coherent {
    pub fn new(side: u32) -> Coherent {
        Coherent {
            tess: Tessellator::new(side),
            split_cands: PosSet::default(),
            merge_cands: PosSet::default(),
            moved: 0.0,
            turned: 0.0,
            split_q: BucketQueue::default(),
            merge_q: BucketQueue::default(),
            log: Vec::new(),
            old: Vec::new(),
            triangles: 2,
            split_count: 0,
            error_bound_px: 0.0,
            dropped: 0.0,
            last: None,
            mode: Mode::Rebuild,
            stats: CoherentStats::default(),
        }
    }

    /// Triangles in the cut.
    pub fn triangles(&self) -> u32 {
        self.triangles
    }

    /// Split diamonds in the cut.
    pub fn split_count(&self) -> u32 {
        self.split_count
    }

    /// The largest screen-space error left unsplit at the last frame's camera, pixels.
    pub fn error_bound_px(&self) -> f32 {
        self.error_bound_px
    }

    pub fn mode(&self) -> Mode {
        self.mode
    }

    pub fn stats(&self) -> CoherentStats {
        self.stats
    }

    /// The last frame's changes, as packed positions (`x | z << 16`) in the order they
    /// happened; a diamond split and merged again appears twice.
    pub fn changes(&self) -> &[u32] {
        &self.log
    }

    /// Whether the diamond centred at `(x, z)` is split.
    pub fn is_split(&self, x: u32, z: u32) -> bool {
        self.tess.is_active(x, z)
    }

    /// The split diamonds, row-major (a walk over the map's bitset: for key frames and
    /// tests, not per frame).
    pub fn split_diamonds(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        let side = self.tess.side;
        roam_protocol::bintree::set_bits(&self.tess.active).map(move |i| (i % side, i / side))
    }

    /// Calls `f` with the split set as the codec's row-major bitset over the map (the
    /// tessellator's own bitset, lent without a copy).
    pub fn with_split_set<R>(&mut self, f: impl FnOnce(&roam_protocol::BitSet) -> R) -> R {
        let set = roam_protocol::BitSet::from_words(std::mem::take(&mut self.tess.active));
        let r = f(&set);
        self.tess.active = set.into_words();
        r
    }

    /// Writes the cut's mesh (the from-scratch tessellator's layout and order).
    pub fn mesh(&mut self, out: &mut Mesh) {
        self.tess.triangles = self.triangles;
        self.tess.emit(out);
        out.error_bound_px = self.error_bound_px;
    }

    /// Bytes of per-viewer state currently reserved.
    pub fn heap_bytes(&self) -> usize {
        self.tess.heap_bytes()
            + self.split_cands.heap_bytes()
            + self.merge_cands.heap_bytes()
            + self.split_q.heap_bytes()
            + self.merge_q.heap_bytes()
            + (self.log.capacity() + self.old.capacity()) * 4
    }

    /// Brings the cut up to date for `camera`: split and merge, or rebuild from scratch on
    /// a jump, a bounded update that did not finish, or when `rebuild` says so.
    pub fn frame(
        &mut self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
        rebuild: bool,
    ) -> Mode {
        self.log.clear();
        self.stats = CoherentStats::default();
        let jump = rebuild || self.jumped(camera, limits, scales);
        if let Some(last) = &self.last {
            let (moved, yaw, pitch) = motion(&last.camera, camera);
            self.moved += moved;
            // A yaw and a pitch change compose into a rotation of at most their sum.
            self.turned += (yaw + pitch).to_radians();
        }
        self.last = Some(Last {
            camera: *camera,
            budget: limits.budget,
            threshold_px: limits.threshold_px,
        });
        if !jump && self.update(hf, variance, scales, camera, limits) {
            self.mode = Mode::Update;
        } else {
            self.rebuild(hf, variance, scales, camera, limits);
            self.mode = Mode::Rebuild;
        }
        self.mode
    }

    /// Whether a frame at `camera` would rebuild the cut rather than update it (a jump).
    pub fn jumped(&self, camera: &Camera, limits: Limits, scales: Scales) -> bool {
        let Some(last) = self.last else {
            return true;
        };
        let c = &last.camera;
        let (moved, yaw, pitch) = motion(c, camera);
        yaw > JUMP_DEGREES
            || pitch > JUMP_DEGREES
            || moved > JUMP_CELLS * scales.h
            || camera.fov_y_deg != c.fov_y_deg
            || (camera.width, camera.height) != (c.width, c.height)
            || limits.threshold_px != last.threshold_px
            || limits.budget > 2 * last.budget
            || 2 * limits.budget < last.budget
    }

    /// From scratch: split-only ROAM, then the frontiers rebuilt and the difference from
    /// the old cut logged.
    fn rebuild(
        &mut self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) {
        // The log keeps what an unfinished update did before: the difference logged here is
        // from the cut as that update left it.
        let logged = self.log.len();
        let mut old = std::mem::take(&mut self.old);
        old.clear();
        old.extend(self.split_diamonds().map(|(x, z)| pack(x, z)));
        self.tess.stale = true;
        self.tess.cut(hf, variance, scales, camera, limits);
        self.triangles = self.tess.triangles;
        self.split_count = self.tess.active_list.len() as u32;
        // The difference of two row-major lists (packed positions sort row-major).
        let mut new = std::mem::take(&mut self.tess.active_list);
        new.sort_unstable();
        let (mut i, mut j) = (0, 0);
        while i < old.len() || j < new.len() {
            match (old.get(i), new.get(j)) {
                (Some(a), Some(b)) if a == b => (i, j) = (i + 1, j + 1),
                (Some(&a), Some(&b)) if a < b => {
                    self.log.push(a);
                    i += 1;
                }
                (Some(&a), None) => {
                    self.log.push(a);
                    i += 1;
                }
                (_, Some(&b)) => {
                    self.log.push(b);
                    j += 1;
                }
                (None, None) => break,
            }
        }
        self.tess.active_list = new;
        self.old = old;
        self.split_cands.clear();
        self.merge_cands.clear();
        let f = self.tess.frame(hf, variance, scales, camera, limits);
        let root = self.root();
        if self.split_count == 0 {
            self.split_cands
                .insert_with(root, || Entry::fresh(fixed(&f, root)));
        }
        for k in 0..self.tess.active_list.len() {
            let (x, z) = unpack(self.tess.active_list[k]);
            let mut any = false;
            for c in self.children(x, z).into_iter().flatten() {
                let (cx, cz) = unpack(c);
                if self.tess.is_active(cx, cz) {
                    any = true;
                } else {
                    self.split_cands
                        .insert_with(c, || Entry::fresh(fixed(&f, c)));
                }
            }
            if !any {
                let pos = pack(x, z);
                self.merge_cands
                    .insert_with(pos, || Entry::fresh(fixed(&f, pos)));
            }
        }
        self.stats.splits += (self.log.len() - logged) as u32;
        // Every frontier diamond evaluated now (kept for the next frames), so the bound is
        // measured as an update's is; from scratch's own bound remembers below-threshold
        // priorities of diamonds a forced split took later.
        self.queue_frontiers(&f);
        self.error_bound_px = self.bound(limits);
    }

    fn root(&self) -> u32 {
        let r = self.tess.size / 2;
        pack(r, r)
    }

    /// Children on the map (none for the finest rotated diamonds), packed.
    fn children(&self, x: u32, z: u32) -> [Option<u32>; 4] {
        let (m, shape) = classify(x, z);
        let h = 1 << m;
        let s = self.tess.size;
        match shape {
            Shape::Square => [
                Some(pack(x + h, z)),
                Some(pack(x - h, z)),
                Some(pack(x, z + h)),
                Some(pack(x, z - h)),
            ],
            Shape::Rotated { .. } if m == 0 => [None; 4],
            Shape::Rotated { .. } => {
                let k = h / 2;
                let ok = |dx: i64, dz: i64| {
                    let (cx, cz) = (i64::from(x) + dx, i64::from(z) + dz);
                    (cx >= 0 && cz >= 0 && cx <= i64::from(s) && cz <= i64::from(s))
                        .then(|| pack(cx as u32, cz as u32))
                };
                let k = i64::from(k);
                [ok(k, -k), ok(-k, -k), ok(-k, k), ok(k, k)]
            }
        }
    }

    /// Parents on the map (none for the root, one for a rotated diamond on the edge).
    fn parents(&self, x: u32, z: u32) -> [Option<u32>; 2] {
        let (m, shape) = classify(x, z);
        let h = 1 << m;
        let s = self.tess.size;
        match shape {
            Shape::Square if 2 * h == s => [None, None],
            Shape::Square => {
                if (((x + h) >> (m + 1)) + ((z + h) >> (m + 1))) & 1 == 1 {
                    [Some(pack(x + h, z + h)), Some(pack(x - h, z - h))]
                } else {
                    [Some(pack(x + h, z - h)), Some(pack(x - h, z + h))]
                }
            }
            Shape::Rotated { horizontal: true } => [
                (z >= h).then(|| pack(x, z - h)),
                (z + h <= s).then(|| pack(x, z + h)),
            ],
            Shape::Rotated { horizontal: false } => [
                (x >= h).then(|| pack(x - h, z)),
                (x + h <= s).then(|| pack(x + h, z)),
            ],
        }
    }

    /// Triangles a split of `(x, z)` adds: a square 2, a rotated diamond one per parent
    /// on the map (1 on the map's edge).
    fn added(&self, x: u32, z: u32) -> u32 {
        match classify(x, z).1 {
            Shape::Square => 2,
            Shape::Rotated { .. } => self.parents(x, z).iter().flatten().count() as u32,
        }
    }

    fn any_split(&self, list: &[Option<u32>]) -> bool {
        list.iter().flatten().any(|&p| {
            let (x, z) = unpack(p);
            self.tess.is_active(x, z)
        })
    }

    /// Evaluates again the frontier diamonds that are due (four at a time), and queues
    /// every one by its kept evaluation.
    fn evaluate_all(&mut self, f: &Frame, merges: bool) {
        let mut list = if merges {
            std::mem::take(&mut self.merge_cands)
        } else {
            std::mem::take(&mut self.split_cands)
        };
        let (moved, turned) = (self.moved, self.turned);
        let mut due = [0usize; 4];
        let mut n = 0;
        let mut evaluated = 0;
        let len = list.len();
        for k in 0..=len {
            if k < len && list.values()[k].due(moved, turned) {
                due[n] = k;
                n += 1;
                if n < 4 {
                    continue;
                }
            }
            if n == 4 || (k == len && n > 0) {
                let values = list.values();
                let d = [0, 1, 2, 3].map(|i| &values[due[i.min(n - 1)]].fixed);
                let lanes = self.evaluate(f, d, n);
                for (i, &at) in due.iter().enumerate().take(n) {
                    list.values_mut()[at].keep(&lanes, i, moved, turned);
                }
                evaluated += n;
                n = 0;
            }
        }
        for (&pos, e) in list.as_slice().iter().zip(list.values()) {
            if merges {
                self.queue_merge(e.prio, e.flags, pos);
            } else {
                self.queue_split(e.prio, e.flags, pos);
            }
        }
        self.stats.evaluated += evaluated as u32;
        if merges {
            self.merge_cands = list;
        } else {
            self.split_cands = list;
        }
    }

    /// Keeps lane `i` of an evaluation beside split candidate `pos`, and queues it.
    #[inline]
    fn queue_split_lane(&mut self, l: &Lanes, i: usize, pos: u32) {
        if let Some(e) = self.split_cands.get_mut(pos) {
            e.keep(l, i, self.moved, self.turned);
        }
        self.queue_split(l.prio[i], lane_flags(l, i), pos);
    }

    /// Keeps lane `i` of an evaluation beside merge candidate `pos`, and queues it.
    #[inline]
    fn queue_merge_lane(&mut self, l: &Lanes, i: usize, pos: u32) {
        if let Some(e) = self.merge_cands.get_mut(pos) {
            e.keep(l, i, self.moved, self.turned);
        }
        self.queue_merge(l.prio[i], lane_flags(l, i), pos);
    }

    #[inline]
    fn queue_split(&mut self, p: f32, flags: u8, pos: u32) {
        let (wanted, under) = (flags & 1 != 0, flags & 2 != 0);
        let bucket = if under { TOP } else { bucket_of(p) };
        let entry = (u64::from(p.to_bits()) << 32) | u64::from(pos);
        self.split_q.push_if(wanted, bucket, entry);
    }

    #[inline]
    fn queue_merge(&mut self, p: f32, flags: u8, pos: u32) {
        if flags & 2 != 0 {
            return; // the ground under the eye stays refined
        }
        // Unwanted splits go first (bucket TOP); the others lowest priority first.
        let (bucket, p) = if flags & 1 == 0 {
            (TOP, 0.0f32)
        } else {
            (TOP - 1 - bucket_of(p), p)
        };
        let entry = (u64::from(p.to_bits()) << 32) | u64::from(pos);
        self.merge_q.push(bucket, entry);
    }

    /// Splits and merges the old cut towards the new camera; false when the bounded loop
    /// did not finish (the caller rebuilds).
    fn update(
        &mut self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) -> bool {
        let f = self.tess.frame(hf, variance, scales, camera, limits);
        let budget = limits.budget.max(2);
        self.tess.stale = true;
        self.queue_frontiers(&f);
        let most = budget / 4 + 256;
        let mut changes = 0u32;
        loop {
            if changes > most {
                return false;
            }
            // Unwanted splits, and anything while over budget, are merged first.
            if self.triangles > budget || self.peek_merge().is_some_and(|(b, _)| b == TOP) {
                match self.pop_merge() {
                    Some(pos) => {
                        self.merge(&f, pos);
                        changes += 1;
                        continue;
                    }
                    None if self.triangles > budget => return false,
                    None => {}
                }
            }
            let Some((bucket, entry)) = self.pop_split() else {
                break;
            };
            let (x, z) = unpack(entry as u32);
            self.tess.chain.clear();
            let mut cost = 0;
            self.tess.collect(x, z, &mut cost);
            if self.triangles + cost <= budget {
                for k in 0..self.tess.chain.len() {
                    let c = self.tess.chain[k];
                    self.split(&f, c);
                    changes += 1;
                }
                continue;
            }
            // It does not fit: make room if a merge costs less error than the split gains.
            let gain = if bucket == TOP {
                f32::INFINITY
            } else {
                f32::from_bits((entry >> 32) as u32)
            };
            match self.peek_merge() {
                Some((_, loss)) if loss < gain => {
                    let pos = self.pop_merge().expect("peeked above");
                    self.merge(&f, pos);
                    changes += 1;
                    self.split_q.push(bucket, entry);
                }
                _ => {
                    self.split_q.push(bucket, entry);
                    break;
                }
            }
        }
        self.error_bound_px = self.bound(limits);
        true
    }

    /// The error the cut leaves: the highest split candidate still queued, and with a
    /// threshold the highest of those below it (a walk of the frontier, only then).
    fn bound(&mut self, limits: Limits) -> f32 {
        if limits.threshold_px > 0.0 {
            self.dropped = self
                .split_cands
                .values()
                .iter()
                .filter(|e| e.flags & 4 != 0)
                .map(|e| e.prio)
                .fold(0.0, f32::max);
        }
        self.remaining_max().max(self.dropped)
    }

    /// Empties the queues and evaluates the frontiers' due diamonds into them.
    fn queue_frontiers(&mut self, f: &Frame) {
        let frontier = self.split_cands.len() + self.merge_cands.len();
        self.split_q.clear();
        self.merge_q.clear();
        self.split_q.reserve(frontier + 1024);
        self.merge_q.reserve(frontier + 1024);
        self.dropped = 0.0;
        self.evaluate_all(f, false);
        self.evaluate_all(f, true);
    }

    /// The next split candidate still valid (unsplit, a candidate), with its bucket.
    fn pop_split(&mut self) -> Option<(usize, u64)> {
        loop {
            let b = self.split_q.top_bucket()?;
            let entry = self.split_q.pop()?;
            let pos = entry as u32;
            let (x, z) = unpack(pos);
            if !self.tess.is_active(x, z) && self.split_cands.contains(pos) {
                return Some((b, entry));
            }
        }
    }

    fn merge_valid(&self, entry: u64) -> bool {
        let pos = entry as u32;
        let (x, z) = unpack(pos);
        self.tess.is_active(x, z) && self.merge_cands.contains(pos)
    }

    /// The bucket and priority of the next valid merge candidate (stale entries are dropped
    /// on the way).
    fn peek_merge(&mut self) -> Option<(usize, f32)> {
        loop {
            let b = self.merge_q.top_bucket()?;
            let first = self.merge_q.entries(b).next()?;
            if self.merge_valid(first) {
                return Some((b, f32::from_bits((first >> 32) as u32)));
            }
            self.merge_q.pop();
        }
    }

    /// The next valid merge candidate's position.
    fn pop_merge(&mut self) -> Option<u32> {
        loop {
            let entry = self.merge_q.pop()?;
            if self.merge_valid(entry) {
                return Some(entry as u32);
            }
        }
    }

    /// Splits `pos`, whose parents are split: the frontiers follow and the children it
    /// uncovers are queued.
    fn split(&mut self, f: &Frame, pos: u32) {
        let (x, z) = unpack(pos);
        self.tess.set_active(x, z);
        self.triangles += self.added(x, z);
        self.split_count += 1;
        self.stats.splits += 1;
        self.log.push(pos);
        self.split_cands.remove(pos);
        for p in self.parents(x, z).into_iter().flatten() {
            self.merge_cands.remove(p);
        }
        self.merge_cands
            .insert_with(pos, || Entry::fresh(fixed(f, pos)));
        let mut fresh = [0u32; 4];
        let mut n = 0;
        for c in self.children(x, z).into_iter().flatten() {
            if self
                .split_cands
                .insert_with(c, || Entry::fresh(fixed(f, c)))
            {
                fresh[n] = c;
                n += 1;
            }
        }
        // The diamond itself rides in the children's batch when there is a lane for it.
        let mut pos4 = fresh;
        let lanes = if n < 4 {
            pos4[n] = pos;
            self.evaluate_at(f, &pos4[..=n])
        } else {
            self.evaluate_at(f, &pos4)
        };
        for (i, &c) in fresh.iter().enumerate().take(n) {
            self.queue_split_lane(&lanes, i, c);
        }
        if n < 4 {
            self.queue_merge_lane(&lanes, n, pos);
        } else {
            let lanes = self.evaluate_at(f, &[pos]);
            self.queue_merge_lane(&lanes, 0, pos);
        }
    }

    /// Merges `pos`, split with no split child: the frontiers follow, and it and the
    /// parents it leaves mergeable are queued.
    fn merge(&mut self, f: &Frame, pos: u32) {
        let (x, z) = unpack(pos);
        self.tess.clear_active(x, z);
        self.triangles -= self.added(x, z);
        self.split_count -= 1;
        self.stats.merges += 1;
        self.log.push(pos);
        self.merge_cands.remove(pos);
        self.split_cands
            .insert_with(pos, || Entry::fresh(fixed(f, pos)));
        for c in self.children(x, z).into_iter().flatten() {
            let (cx, cz) = unpack(c);
            if !self.any_split(&self.parents(cx, cz)) {
                self.split_cands.remove(c);
            }
        }
        let mut fresh = [0u32; 4];
        let mut n = 0;
        for p in self.parents(x, z).into_iter().flatten() {
            let (px, pz) = unpack(p);
            if !self.any_split(&self.children(px, pz))
                && self
                    .merge_cands
                    .insert_with(p, || Entry::fresh(fixed(f, p)))
            {
                fresh[n] = p;
                n += 1;
            }
        }
        let mut pos4 = [pos; 4];
        pos4[1..=n].copy_from_slice(&fresh[..n]);
        let lanes = self.evaluate_at(f, &pos4[..=n]);
        self.queue_split_lane(&lanes, 0, pos);
        for (i, &p) in fresh.iter().enumerate().take(n) {
            self.queue_merge_lane(&lanes, i + 1, p);
        }
    }

    /// The highest priority of a split candidate left unsplit.
    fn remaining_max(&self) -> f32 {
        self.split_q.remaining_max(|e| {
            let pos = e as u32;
            let (x, z) = unpack(pos);
            !self.tess.is_active(x, z) && self.split_cands.contains(pos)
        })
    }
}

/// Lane `i`'s verdicts as [`Entry`] flags.
fn lane_flags(l: &Lanes, i: usize) -> u8 {
    (l.wanted >> i & 1) as u8 | ((l.under >> i & 1) as u8) << 1 | ((l.dropped >> i & 1) as u8) << 2
}

/// How far the eye moved between two cameras (world units), and how far the view turned
/// in yaw and in pitch (degrees, the short way round).
fn motion(a: &Camera, b: &Camera) -> (f64, f64, f64) {
    let moved = (0..3)
        .map(|i| (b.eye[i] - a.eye[i]).powi(2))
        .sum::<f64>()
        .sqrt();
    let yaw = crate::sim::physics::wrap_degrees(b.yaw_deg - a.yaw_deg);
    (
        moved,
        yaw.min(360.0 - yaw),
        (b.pitch_deg - a.pitch_deg).abs(),
    )
}
