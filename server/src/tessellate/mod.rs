//! Split-only ROAM from the two root triangles: the spec's algorithm, and what the
//! frame-coherent tessellator ([`Coherent`]) rebuilds from on a jump (a viewer's cut is
//! otherwise carried from frame to frame by splits and merges).
//!
//! The mesh is the set of split ("active") diamonds; see [`roam_protocol::bintree`]. From scratch:
//!
//! 1. Queue the root diamond. Repeatedly pop the diamond of highest priority and split it.
//!    Splitting first splits, recursively, any parent diamond not yet split (ROAM's forced
//!    split of a coarser base neighbour), so the mesh never has cracks or T-junctions.
//! 2. Splitting a diamond queues each child diamond the first time one of its parents is
//!    split. Priorities do not change within a frame, so each diamond is evaluated once.
//! 3. Stop when the next split would pass the triangle budget, or when the queue holds
//!    nothing at or above the pixel threshold.
//!
//! **Priority** is the screen-space error in pixels: the diamond's error bound (variance
//! tree, world units) over the distance from the eye to the diamond's bounding volume, times
//! `height / (2 tan(fov_y / 2))`, times what the viewer's fog lets through of it,
//! `exp(−density · distance)` over the same (nearest) distance: the most of its error the
//! diamond could show through the fog ([`Limits::fog_density`]; 0 without fog, when the
//! priority is bit for bit the fog-unaware one, see `evaluate.rs`), computed as
//! `2^−(distance · density · log2 e)`, the product a constant of the frame (issue 41: one
//! multiply less on the chain the split loop waits on; with the shorter transmission of
//! `lanes.rs`, from scratch with fog 33.9 against 34.8 ns a triangle without on
//! `data/kossou`, 36.4 against 34.2 before: `roam-server bench data/kossou --budget 65536
//! --json --fog-priority on|off`). A diamond whose bounding prism (its square footprint ×
//! its height bounds, which follow from its corner heights and error) lies wholly outside one
//! frustum plane is never queued, so it is split only when a split elsewhere forces it. A
//! diamond whose footprint contains the eye's ground position gets the top priority.
//!
//! **Queue**: priority buckets ([`queue`]): constant-time insert and pop. Removing a
//! diamond that a forced split took is lazy (constant time): popping skips diamonds already
//! split.
//!
//! **Speed**: each child's corner heights come from its parent but one; the four plane
//! tests run as one vector operation; the variance tree is read at a computed slot (no
//! pointers); the queue is first-in first-out within a bucket, so a pop does not wait on
//! the priorities just computed.
//!
//! **Memory**: one bit per grid vertex for the active set (and a rank table turning it into
//! vertex indices), plus pools sized by the budget, all reused: no allocation per frame
//! once warm.

use crate::terrain::heightfield::Heightfield;
use crate::terrain::variance::{self, VarianceTree};
use camera::Camera;
use queue::{BucketQueue, bucket_of};
use roam_protocol::bintree::{self, Shape, shape_of};

pub mod camera;
mod coherent;
mod emit;
mod evaluate;
mod frontier;
mod lanes;
pub mod queue;
mod scratch;

pub use coherent::{
    AuditError, Coherent, CoherentStats, ListError, Mode, Step, fogged_error_px, measured_error,
};
pub use scratch::Scratch;

use lanes::F4;

/// The smallest distance used in priorities, world units.
const MIN_DISTANCE: f32 = 1e-3;

/// What a frame may spend.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    /// Most triangles in the mesh (at least 2: the roots).
    pub budget: u32,
    /// Do not split diamonds whose screen-space error is below this, in pixels.
    pub threshold_px: f32,
    /// The viewer's fog, per world unit (transmission `exp(−density · distance)`): each
    /// diamond's error is weighed by the fog's transmission over the nearest distance to
    /// its bounding prism. 0 (or anything not a positive finite number) for none.
    pub fog_density: f32,
    /// A guard band: the frustum's left and right planes turned out by this many degrees
    /// each, so that what a turning viewer is about to see is refined before it comes into
    /// view ([`Camera::frustum_widened`]). 0 (or anything not a positive finite number) for
    /// none, the spec's culling.
    pub guard_deg: f32,
}

/// World scales of a heightfield: `(h_scale·x, v_scale·sample, h_scale·z)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Scales {
    pub h: f64,
    pub v: f64,
}

/// One frame's mesh: an indexed triangle list in grid coordinates.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Grid vertices `[x, z]`, in row-major order.
    pub vertices: Vec<[u16; 2]>,
    /// Three indices per triangle, counter-clockwise seen from above, grouped by the split
    /// diamond they belong to, diamonds in row-major order (deterministic).
    pub indices: Vec<u32>,
    /// The largest screen-space error left unsplit, in pixels (0 when nothing was left).
    pub error_bound_px: f32,
}

impl Mesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }
}

/// Counts from the last frame, for benchmarks and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Diamonds whose priority was computed.
    pub evaluated: u32,
    /// Of those, wholly outside the frustum (never queued).
    pub culled: u32,
    /// Entries popped from the queue (some already taken by forced splits).
    pub popped: u32,
    /// Diamonds split, forced ones included.
    pub split: u32,
    /// Pops whose parents were not all split (forced splits needed).
    pub forcing: u32,
}

/// Split-only tessellation state for one map size (a bit per grid vertex, and pools):
/// build one per heightfield size and reuse it. Serving keeps no one per viewer: the
/// viewers' [`Coherent`] cuts borrow them from a shared [`Scratch`].
pub struct Tessellator {
    side: u32,
    size: u32,
    /// One bit per grid vertex: the diamond centred there is split (corners: set while
    /// emitting, so they get vertex indices).
    active: Vec<u64>,
    /// Split diamonds of this frame, in order.
    active_list: Vec<u32>,
    /// For emission: each `active` word beside its rank (set bits before it).
    ranked: Vec<[u64; 2]>,
    queue: BucketQueue,
    chain: Vec<u32>,
    triangles: u32,
    /// Largest priority left below the threshold, per lane.
    dropped: F4,
    stats: Stats,
    /// Run the x86-64-v3 build of the hot loops: decided once, in `new` (the CPU has it)
    /// and `set_portable`.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    v3: bool,
}

/// Everything the evaluation needs about the frame, precomputed.
struct Frame<'a> {
    heights: &'a [u16],
    codes: &'a [u8],
    table: &'a [f32; 256],
    square_offset: [usize; 16],
    rotated_offset: [usize; 16],
    side: u32,
    size: u32,
    /// The four side planes of the view pyramid (its apex, the eye, makes a near plane
    /// unnecessary), each coefficient in all four lanes.
    planes: [Plane; 4],
    /// Per plane, `d` plus the footprint's reach across it, `2^m · extent`, for squares
    /// (index `16 + m`) and rotated diamonds (`m`).
    plane_offsets: [[F4; 4]; 32],
    /// The same, one `f32` each, for lanes of mixed shapes and sizes.
    offsets_scalar: [[f32; 4]; 32],
    eye_x: F4,
    eye_z: F4,
    eye_y: F4,
    hs: F4,
    hs_scalar: f32,
    vs: F4,
    /// `v_scale · pixels_per_radian`: turns sample-unit error over world distance into px.
    px: F4,
    threshold: F4,
    /// The fog's density, per world unit (0: none), the same times `log2 e` (the
    /// transmission is `2^−(distance · fog_log2e)`), and whether it is not 0.
    fog: F4,
    fog_log2e: F4,
    fogged: bool,
}

/// A frustum plane in grid units: `a·x_grid + b·sample + c·z_grid + d >= 0` inside; `|b|`,
/// and the footprint extents `|a| + |c|` (square) and `max(|a|, |c|)` (rotated).
struct Plane {
    a: F4,
    b: F4,
    c: F4,
    abs_b: F4,
}

impl Frame<'_> {
    #[inline(always)]
    fn at(&self, x: u32, z: u32) -> u16 {
        self.heights[(z * self.side + x) as usize]
    }

    /// Height at a row-major index.
    #[inline(always)]
    fn h(&self, i: u32) -> u16 {
        debug_assert!((i as usize) < self.heights.len());
        // SAFETY: every index the tessellator reads is a grid vertex of a diamond on the
        // map (a corner, centre or stand-in), so below `side²`; `tessellate` checks that
        // the heightfield has this side.
        unsafe { *self.heights.get_unchecked(i as usize) }
    }

    /// Error stored at a variance-tree slot, sample units.
    #[inline(always)]
    fn error_at(&self, slot: usize) -> f32 {
        debug_assert!(slot < self.codes.len());
        // SAFETY: slots are computed for diamonds on the map by the tree's own layout, and
        // `tessellate` checks that the tree was built for a map of this size.
        unsafe { self.table[*self.codes.get_unchecked(slot) as usize] }
    }

    /// Stored error of a diamond (not a rotated one of level 0), sample units.
    #[inline(always)]
    fn stored(&self, x: u32, z: u32, m: u32, shape: Shape) -> f32 {
        let i = variance::slot(
            &self.square_offset,
            &self.rotated_offset,
            self.size,
            x,
            z,
            m,
            shape,
        );
        self.table[self.codes[i] as usize]
    }
}

#[inline(always)]
fn pack(x: u32, z: u32) -> u32 {
    x | (z << 16)
}

#[inline(always)]
fn unpack(v: u32) -> (u32, u32) {
    (v & 0xffff, v >> 16)
}

/// Whether the CPU offers x86-64-v3 (AVX2, BMI1/2, FMA, LZCNT, POPCNT): the hot loops are
/// compiled twice, for it and for the x86-64 baseline, and chosen at run time.
fn has_v3() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::is_x86_feature_detected as has;
        has!("avx2")
            && has!("bmi1")
            && has!("bmi2")
            && has!("fma")
            && has!("lzcnt")
            && has!("popcnt")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

impl Tessellator {
    /// A tessellator for heightfields of this `side` (`2^N + 1`).
    pub fn new(side: u32) -> Self {
        let words = (side as usize * side as usize).div_ceil(64);
        Tessellator {
            side,
            size: side - 1,
            active: vec![0; words],
            active_list: Vec::new(),
            ranked: vec![[0; 2]; words],
            queue: BucketQueue::default(),
            chain: Vec::new(),
            triangles: 0,
            dropped: F4::splat(0.0),
            stats: Stats::default(),
            v3: has_v3(),
        }
    }

    /// Bytes of per-viewer state (bitsets and pools) currently reserved.
    pub fn heap_bytes(&self) -> usize {
        self.active.capacity() * 8
            + self.ranked.capacity() * 16
            + self.active_list.capacity() * 4
            + self.queue.heap_bytes()
            + self.chain.capacity() * 4
    }

    /// Runs the x86-64 baseline build of the hot loops even on a CPU with x86-64-v3, so
    /// tests can check that both builds give the same mesh.
    pub fn set_portable(&mut self, portable: bool) {
        self.v3 = !portable && has_v3();
    }

    /// Counts from the last frame.
    pub fn stats(&self) -> Stats {
        self.stats
    }

    /// The last frame's split diamonds as the mesh codec's split set (row-major indices on
    /// `grid`, which must be this map's).
    pub fn split_set(&self, grid: &roam_protocol::Grid, out: &mut roam_protocol::BitSet) {
        out.reset(grid.vertices());
        for (x, z) in self.split_diamonds() {
            out.insert(grid.index(x, z));
        }
    }

    /// Centres of the diamonds split in the last frame, in the order they were split.
    pub fn split_diamonds(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        self.active_list.iter().map(|&v| unpack(v))
    }

    #[inline(always)]
    fn is_active(&self, x: u32, z: u32) -> bool {
        self.is_active_at(z * self.side + x)
    }

    /// Whether the diamond centred at row-major index `i` is split.
    #[inline(always)]
    fn is_active_at(&self, i: u32) -> bool {
        let i = i as usize;
        debug_assert!(i >> 6 < self.active.len());
        // SAFETY: callers pass grid vertices of diamonds on the map, below `side²`, and
        // `active` has a bit for each.
        unsafe { *self.active.get_unchecked(i >> 6) >> (i & 63) & 1 != 0 }
    }

    #[inline(always)]
    fn set_active(&mut self, x: u32, z: u32) {
        let i = (z * self.side + x) as usize;
        self.active[i >> 6] |= 1 << (i & 63);
    }

    /// Tessellates the heightfield for `camera` into `out` (its buffers are reused).
    pub fn tessellate(
        &mut self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
        out: &mut Mesh,
    ) {
        let budget = limits.budget.max(2) as usize;
        out.vertices
            .reserve((budget + 4).saturating_sub(out.vertices.len()));
        out.indices
            .reserve((3 * budget + 12).saturating_sub(out.indices.len()));
        out.error_bound_px = self.cut(hf, variance, scales, camera, limits);
        self.emit(out);
    }

    /// The split-only cut for `camera`, from scratch, in `active` and `active_list`;
    /// returns the largest screen-space error left unsplit.
    fn cut(
        &mut self,
        hf: &Heightfield,
        variance: &VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) -> f32 {
        assert_eq!(hf.side(), self.side, "a tessellator serves one map size");
        assert_eq!(
            variance.size(),
            self.size,
            "the variance tree is of another map size"
        );
        self.reset();
        let frame = self.frame(hf, variance, scales, camera, limits);
        let budget = limits.budget.max(2);
        // Worst cases, so the frame allocates nothing once these have grown: a split adds
        // at least one triangle and queues at most four children.
        let most_splits = budget as usize;
        self.queue.reserve(4 * most_splits + 8);
        self.active_list
            .reserve(most_splits.saturating_sub(self.active_list.len()));
        self.triangles = 2;
        self.evaluate_root(&frame);
        self.split_loop(&frame, budget);
        self.stats.split = self.active_list.len() as u32;
        self.remaining_max().max(self.dropped.max_lane())
    }

    /// Pops and splits until the budget or the queue runs out, on the best instruction set
    /// the CPU offers.
    fn split_loop(&mut self, frame: &Frame, budget: u32) {
        #[cfg(target_arch = "x86_64")]
        if self.v3 {
            // SAFETY: `v3` is set only when the CPU supports these features.
            unsafe { self.split_loop_v3(frame, budget) };
            return;
        }
        self.split_loop_body(frame, budget);
    }

    /// [`Self::split_loop_body`] compiled for x86-64-v3 (AVX2, BMI, FMA, LZCNT, POPCNT).
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,bmi1,bmi2,fma,lzcnt,popcnt")]
    fn split_loop_v3(&mut self, frame: &Frame, budget: u32) {
        self.split_loop_body(frame, budget);
    }

    #[inline(always)]
    fn split_loop_body(&mut self, frame: &Frame, budget: u32) {
        while let Some(entry) = self.queue.pop() {
            self.stats.popped += 1;
            let (x, z) = unpack(entry as u32);
            if self.is_active(x, z) {
                continue; // taken earlier by a forced split
            }
            if let Some(tris) = self.parents_split(x, z) {
                // The common case: nothing to force.
                if self.triangles + tris > budget {
                    self.requeue(entry);
                    break;
                }
                self.triangles += tris;
                self.commit(frame, x, z);
                continue;
            }
            self.stats.forcing += 1;
            let mut delta = 0;
            self.chain.clear();
            self.collect(x, z, &mut delta);
            if self.triangles + delta > budget {
                self.requeue(entry);
                break;
            }
            self.triangles += delta;
            for i in 0..self.chain.len() {
                let (cx, cz) = unpack(self.chain[i]);
                self.commit(frame, cx, cz);
            }
        }
    }

    fn frame<'a>(
        &self,
        hf: &'a Heightfield,
        variance: &'a VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) -> Frame<'a> {
        Frame::new(hf, variance, scales, camera, limits)
    }
    fn reset(&mut self) {
        if self.active_list.len() > self.active.len() / 2 {
            // Dense: clearing every word (a memset) beats a store per split diamond.
            self.active.fill(0);
        } else {
            for &w in &self.active_list {
                let (x, z) = unpack(w);
                let i = (z * self.side + x) as usize;
                self.active[i >> 6] = 0;
            }
        }
        let s = self.size;
        for (x, z) in [(0, 0), (s, 0), (0, s), (s, s)] {
            let i = (z * self.side + x) as usize;
            self.active[i >> 6] = 0;
        }
        self.active_list.clear();
        self.queue.clear();
        self.dropped = F4::splat(0.0);
        self.stats = Stats::default();
    }

    /// Collects, parents first, the unsplit diamonds that splitting `(x, z)` needs, and the
    /// triangles their splits add. Recursion depth is bounded by the tree's depth.
    fn collect(&mut self, x: u32, z: u32, delta: &mut u32) {
        let parents = bintree::parents(self.size, x, z);
        let tris = bintree::added(self.size, x, z);
        for (px, pz) in parents.into_iter().flatten() {
            if !self.is_active(px, pz) && !self.chain.contains(&pack(px, pz)) {
                self.collect(px, pz, delta);
            }
        }
        self.chain.push(pack(x, z));
        *delta += tris;
    }

    /// `Some(triangles the split adds)` when every parent of `(x, z)` is split already.
    ///
    /// Both shapes are one computation, without branches on the shape: the parents are
    /// `i ± d` (a square's one diagonal pair, a rotated diamond's two apices), either of
    /// which may be off the map (a rotated diamond on its edge, or the root).
    #[inline(always)]
    fn parents_split(&self, x: u32, z: u32) -> Option<u32> {
        let (tx, tz) = (x.trailing_zeros(), z.trailing_zeros());
        let m = tx.min(tz);
        let h = 1 << m;
        let (s, side) = (self.size, self.side);
        let square = tx == tz;
        // A square's parents are on the diagonal through the coarser cell's centre.
        let anti = (((x + h) >> (m + 1)) + ((z + h) >> (m + 1))) & 1 == 0;
        let horizontal = tx < tz;
        let (dx, dz_plus, dz_minus) = if square {
            (h, !anti, anti)
        } else if horizontal {
            (0, true, false)
        } else {
            (h, false, false)
        };
        // d = dx + dz·side, where dz is +h, −h or 0.
        let row = h * side;
        let d_plus = if dz_plus { dx + row } else { dx };
        let d = if dz_minus {
            d_plus.wrapping_sub(row)
        } else {
            d_plus
        };
        let (c, root) = (if horizontal { z } else { x }, 2 * h == s);
        let has_lo = (square && !root) || (!square && c >= h);
        let has_hi = (square && !root) || (!square && c + h <= s);
        let i = z * side + x;
        let lo_ok = !has_lo | self.is_active_at(if has_lo { i.wrapping_sub(d) } else { i });
        let hi_ok = !has_hi | self.is_active_at(if has_hi { i.wrapping_add(d) } else { i });
        let tris = if square {
            2
        } else {
            u32::from(has_lo) + u32::from(has_hi)
        };
        (lo_ok & hi_ok).then_some(tris)
    }

    /// Splits `(x, z)` (its parents are split) and queues the children it uncovers. A
    /// child is queued by whichever of its two parents is split first.
    #[inline(always)]
    fn commit(&mut self, f: &Frame, x: u32, z: u32) {
        self.set_active(x, z);
        self.active_list.push(pack(x, z));
        let (m, shape) = shape_of(x, z);
        match shape {
            Shape::Square => self.commit_square(f, x, z, m),
            Shape::Rotated { .. } if m == 0 => {}
            Shape::Rotated { horizontal } => self.commit_rotated(f, x, z, m, horizontal),
        }
    }

    /// Re-queues a popped entry that did not fit, by its priority, so the error bound sees
    /// it.
    fn requeue(&mut self, entry: u64) {
        let prio = f32::from_bits((entry >> 32) as u32);
        self.queue.push(bucket_of(prio), entry);
    }

    /// The highest priority still queued, skipping diamonds already split.
    fn remaining_max(&self) -> f32 {
        self.queue.remaining_max(|e| {
            let (x, z) = unpack(e as u32);
            !self.is_active(x, z)
        })
    }
}

impl<'a> Frame<'a> {
    /// The frame's constants for `camera` over this map (`hf`'s side, `variance`'s size).
    fn new(
        hf: &'a Heightfield,
        variance: &'a VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) -> Frame<'a> {
        let planes = camera.frustum_widened(f64::from(limits.guard_deg));
        let grid = |i: usize| {
            let p = &planes[i + 1];
            (p.n[0] * scales.h, p.n[1] * scales.v, p.n[2] * scales.h, p.d)
        };
        let plane = |i: usize| {
            let (a, b, c, _) = grid(i);
            let l = |v: f64| F4::splat(v as f32);
            Plane {
                a: l(a),
                b: l(b),
                c: l(c),
                abs_b: l(b.abs()),
            }
        };
        // A square of half-size h reaches h·(|a| + |c|) across a plane, a rotated diamond
        // h·max(|a|, |c|).
        let offsets_scalar: [[f32; 4]; 32] = std::array::from_fn(|k| {
            let (square, h) = (k >= 16, f64::from(1u32 << (k % 16)));
            std::array::from_fn(|i| {
                let (a, _, c, d) = grid(i);
                let extent = if square {
                    a.abs() + c.abs()
                } else {
                    a.abs().max(c.abs())
                };
                (d + h * extent) as f32
            })
        });
        let plane_offsets = offsets_scalar.map(|o| o.map(F4::splat));
        let fog = limits.fog_density;
        let fog = if fog.is_finite() && fog > 0.0 {
            fog
        } else {
            0.0
        };
        let mut square_offset = [0; 16];
        let mut rotated_offset = [0; 16];
        for (m, (so, ro)) in variance
            .square_offsets()
            .iter()
            .zip(variance.rotated_offsets())
            .enumerate()
        {
            square_offset[m] = *so;
            rotated_offset[m] = *ro;
        }
        Frame {
            heights: hf.samples(),
            codes: variance.codes(),
            table: variance.table(),
            square_offset,
            rotated_offset,
            side: hf.side(),
            size: hf.size(),
            planes: std::array::from_fn(plane),
            plane_offsets,
            offsets_scalar,
            eye_x: F4::splat((camera.eye[0] / scales.h) as f32),
            eye_z: F4::splat((camera.eye[2] / scales.h) as f32),
            eye_y: F4::splat(camera.eye[1] as f32),
            hs: F4::splat(scales.h as f32),
            hs_scalar: scales.h as f32,
            vs: F4::splat(scales.v as f32),
            px: F4::splat((scales.v * camera.pixels_per_radian()) as f32),
            threshold: F4::splat(limits.threshold_px),
            fog: F4::splat(fog),
            fog_log2e: F4::splat((f64::from(fog) * std::f64::consts::LOG2_E) as f32),
            fogged: fog > 0.0,
        }
    }
}
