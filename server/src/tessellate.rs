//! Split-only ROAM, rebuilt every frame from the two root triangles.
//!
//! The mesh is the set of split ("active") diamonds; see [`crate::diamond`]. Each frame:
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
//! `height / (2 tan(fov_y / 2))`. A diamond whose bounding prism (its square footprint ×
//! its height bounds, which follow from its corner heights and error) lies wholly outside one
//! frustum plane is never queued, so it is split only when a split elsewhere forces it. A
//! diamond whose footprint contains the eye's ground position gets the top priority.
//!
//! **Queue**: priority buckets (8 per octave of priority, the float's exponent and top
//! mantissa bits), each a stack, with a two-level bitmap to find the highest non-empty
//! bucket: constant-time insert and pop. Removing a diamond that a forced split took is
//! lazy (constant time): popping skips diamonds already split.
//!
//! **Memory**: one bit per grid vertex for the active set (and a rank table turning it into
//! vertex indices), plus pools sized by the budget, all reused: no allocation per frame
//! once warm.

use crate::camera::Camera;
use crate::diamond::Shape;
use crate::heightfield::Heightfield;
use crate::variance::{self, VarianceTree};

/// Number of priority buckets: every positive `f32` maps to one by its top 12 bits.
const BUCKETS: usize = 2048;
/// Bucket of diamonds under the eye.
const TOP: usize = BUCKETS - 1;
/// The smallest distance used in priorities, world units.
const MIN_DISTANCE: f32 = 1e-3;

/// What a frame may spend.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    /// Most triangles in the mesh (at least 2: the roots).
    pub budget: u32,
    /// Do not split diamonds whose screen-space error is below this, in pixels.
    pub threshold_px: f32,
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
    /// Three indices per triangle, counter-clockwise seen from above, in bintree order.
    pub indices: Vec<u32>,
    /// The largest screen-space error left unsplit, in pixels (0 when nothing was left).
    pub error_bound_px: f32,
}

impl Mesh {
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }
}

/// Per-viewer tessellation state. Build one per heightfield size and reuse it.
pub struct Tessellator {
    side: u32,
    size: u32,
    /// One bit per grid vertex: the diamond centred there is split (corners: set while
    /// emitting, so they get vertex indices).
    active: Vec<u64>,
    /// Words of `active` touched this frame.
    active_list: Vec<u32>,
    /// Rank of each `active` word: set bits before it.
    rank: Vec<u32>,
    buckets: Vec<Vec<u64>>,
    /// Bit per non-empty bucket, and a bit per non-zero word of that.
    nonempty: [u64; BUCKETS / 64],
    summary: u32,
    chain: Vec<u32>,
    stack: Vec<[u32; 6]>,
    triangles: u32,
    dropped_max: f32,
}

/// Everything `evaluate` needs about the frame, precomputed.
struct Frame<'a> {
    heights: &'a [u16],
    variance: &'a VarianceTree,
    hf: &'a Heightfield,
    side: u32,
    size: u32,
    /// Planes in mixed units: `a·x_grid + b·sample + c·z_grid + d >= 0` inside; with
    /// `|b|`, `|a| + |c|` and `max(|a|, |c|)` for the extents.
    planes: [[f32; 7]; 5],
    eye_grid: [f32; 2],
    eye: [f32; 3],
    hs: f32,
    vs: f32,
    /// `v_scale · pixels_per_radian`: turns sample-unit error over world distance into px.
    px: f32,
    threshold: f32,
}

#[inline(always)]
fn pack(x: u32, z: u32) -> u32 {
    x | (z << 16)
}

#[inline(always)]
fn unpack(v: u32) -> (u32, u32) {
    (v & 0xffff, v >> 16)
}

/// Shape and `m` of the diamond centred at `(x, z)` (not a corner).
#[inline(always)]
fn classify(x: u32, z: u32) -> (u32, Shape) {
    let (tx, tz) = (x.trailing_zeros(), z.trailing_zeros());
    if tx == tz {
        (tx, Shape::Square)
    } else {
        (tx.min(tz), Shape::Rotated { horizontal: tx < tz })
    }
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
            rank: vec![0; words],
            buckets: (0..BUCKETS).map(|_| Vec::new()).collect(),
            nonempty: [0; BUCKETS / 64],
            summary: 0,
            chain: Vec::new(),
            stack: Vec::new(),
            triangles: 0,
            dropped_max: 0.0,
        }
    }

    /// Bytes of per-viewer state (bitsets and pools) currently reserved.
    pub fn heap_bytes(&self) -> usize {
        self.active.capacity() * 8
            + self.rank.capacity() * 4
            + self.active_list.capacity() * 4
            + self.buckets.iter().map(|b| b.capacity() * 8).sum::<usize>()
            + self.chain.capacity() * 4
            + self.stack.capacity() * 24
    }

    /// Centres of the diamonds split in the last frame, in the order they were split.
    pub fn split_diamonds(&self) -> impl Iterator<Item = (u32, u32)> + '_ {
        self.active_list.iter().map(|&v| unpack(v))
    }

    #[inline(always)]
    fn is_active(&self, x: u32, z: u32) -> bool {
        let i = (z * self.side + x) as usize;
        self.active[i >> 6] >> (i & 63) & 1 != 0
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
        assert_eq!(hf.side(), self.side, "a tessellator serves one map size");
        self.reset();
        let frame = self.frame(hf, variance, scales, camera, limits);
        let budget = limits.budget.max(2);
        self.triangles = 2;
        let (rx, rz) = (self.size / 2, self.size / 2);
        self.evaluate(&frame, rx, rz, rx.trailing_zeros(), Shape::Square);
        while let Some(entry) = self.pop() {
            let (x, z) = unpack(entry as u32);
            if self.is_active(x, z) {
                continue; // taken earlier by a forced split
            }
            let mut delta = 0;
            self.chain.clear();
            self.collect(x, z, &mut delta);
            if self.triangles + delta > budget {
                // Put it back so the error bound sees it, and stop.
                self.push(entry);
                break;
            }
            self.triangles += delta;
            for i in 0..self.chain.len() {
                let (cx, cz) = unpack(self.chain[i]);
                self.commit(&frame, cx, cz);
            }
        }
        out.error_bound_px = self.remaining_max().max(self.dropped_max);
        self.emit(out);
    }

    fn frame<'a>(
        &self,
        hf: &'a Heightfield,
        variance: &'a VarianceTree,
        scales: Scales,
        camera: &Camera,
        limits: Limits,
    ) -> Frame<'a> {
        let planes = camera.frustum().map(|p| {
            let (a, b, c) = (p.n[0] * scales.h, p.n[1] * scales.v, p.n[2] * scales.h);
            [
                a as f32,
                b as f32,
                c as f32,
                p.d as f32,
                b.abs() as f32,
                (a.abs() + c.abs()) as f32,
                a.abs().max(c.abs()) as f32,
            ]
        });
        Frame {
            heights: hf.samples(),
            variance,
            hf,
            side: self.side,
            size: self.size,
            planes,
            eye_grid: [
                (camera.eye[0] / scales.h) as f32,
                (camera.eye[2] / scales.h) as f32,
            ],
            eye: camera.eye.map(|v| v as f32),
            hs: scales.h as f32,
            vs: scales.v as f32,
            px: (scales.v * camera.pixels_per_radian()) as f32,
            threshold: limits.threshold_px,
        }
    }

    fn reset(&mut self) {
        for &w in &self.active_list {
            let (x, z) = unpack(w);
            let i = (z * self.side + x) as usize;
            self.active[i >> 6] = 0;
        }
        let s = self.size;
        for (x, z) in [(0, 0), (s, 0), (0, s), (s, s)] {
            let i = (z * self.side + x) as usize;
            self.active[i >> 6] = 0;
        }
        self.active_list.clear();
        while let Some(b) = self.top_bucket() {
            self.buckets[b].clear();
            self.clear_bucket_bit(b);
        }
        self.dropped_max = 0.0;
    }

    /// Collects, parents first, the unsplit diamonds that splitting `(x, z)` needs, and the
    /// triangles their splits add.
    fn collect(&mut self, x: u32, z: u32, delta: &mut u32) {
        let (m, shape) = classify(x, z);
        let h = 1 << m;
        let s = self.size;
        let mut tris = 2;
        let parents: [Option<(u32, u32)>; 2] = match shape {
            Shape::Square if 2 * h == s => [None, None],
            Shape::Square => {
                if ((x + h) >> (m + 1)) + ((z + h) >> (m + 1)) & 1 == 1 {
                    [Some((x + h, z + h)), Some((x - h, z - h))]
                } else {
                    [Some((x + h, z - h)), Some((x - h, z + h))]
                }
            }
            Shape::Rotated { horizontal: true } => {
                tris = u32::from(z >= h) + u32::from(z + h <= s);
                [(z >= h).then(|| (x, z - h)), (z + h <= s).then(|| (x, z + h))]
            }
            Shape::Rotated { horizontal: false } => {
                tris = u32::from(x >= h) + u32::from(x + h <= s);
                [(x >= h).then(|| (x - h, z)), (x + h <= s).then(|| (x + h, z))]
            }
        };
        for (px, pz) in parents.into_iter().flatten() {
            if !self.is_active(px, pz) && !self.chain.contains(&pack(px, pz)) {
                self.collect(px, pz, delta);
            }
        }
        self.chain.push(pack(x, z));
        *delta += tris;
    }

    /// Splits `(x, z)` (its parents are split) and queues the children it uncovers.
    fn commit(&mut self, f: &Frame, x: u32, z: u32) {
        self.set_active(x, z);
        self.active_list.push(pack(x, z));
        let (m, shape) = classify(x, z);
        let h = 1 << m;
        let s = self.size;
        match shape {
            Shape::Square => {
                // Children: rotated diamonds on the cell's edge midpoints; each one's other
                // parent is the next cell over.
                let vertical = Shape::Rotated { horizontal: false };
                let horizontal = Shape::Rotated { horizontal: true };
                if x + 2 * h > s || !self.is_active(x + 2 * h, z) {
                    self.evaluate(f, x + h, z, m, vertical);
                }
                if x < 2 * h || !self.is_active(x - 2 * h, z) {
                    self.evaluate(f, x - h, z, m, vertical);
                }
                if z + 2 * h > s || !self.is_active(x, z + 2 * h) {
                    self.evaluate(f, x, z + h, m, horizontal);
                }
                if z < 2 * h || !self.is_active(x, z - 2 * h) {
                    self.evaluate(f, x, z - h, m, horizontal);
                }
            }
            Shape::Rotated { .. } if m == 0 => {}
            Shape::Rotated { .. } => {
                // Children: squares half as big around the four leg midpoints, those inside
                // the map; each one's other parent is the far corner of its cell.
                let k = h / 2;
                for (dx, dz) in [(1i32, 1i32), (-1, 1), (1, -1), (-1, -1)] {
                    let cx = x as i64 + i64::from(dx) * k as i64;
                    let cz = z as i64 + i64::from(dz) * k as i64;
                    if cx < 0 || cz < 0 || cx > s as i64 || cz > s as i64 {
                        continue;
                    }
                    let ox = x as i64 + i64::from(dx) * h as i64;
                    let oz = z as i64 + i64::from(dz) * h as i64;
                    let other_inside = ox >= 0 && oz >= 0 && ox <= s as i64 && oz <= s as i64;
                    if !other_inside || !self.is_active(ox as u32, oz as u32) {
                        self.evaluate(f, cx as u32, cz as u32, m - 1, Shape::Square);
                    }
                }
            }
        }
    }

    /// Computes the priority of diamond `(x, z)` and queues it, unless it is outside the
    /// frustum (never queued) or below the threshold (remembered for the error bound).
    #[inline(always)]
    fn evaluate(&mut self, f: &Frame, x: u32, z: u32, m: u32, shape: Shape) {
        let h = 1u32 << m;
        let e = if m == 0 {
            variance::finest(
                f.hf,
                &crate::diamond::Diamond { x, z, m, shape },
            )
        } else {
            let slot = variance::slot(
                f.variance.square_offsets(),
                f.variance.rotated_offsets(),
                f.size,
                x,
                z,
                m,
                shape,
            );
            f.variance.code_value(slot)
        };
        if e <= 0.0 {
            return; // exact already: splitting adds nothing
        }
        let s = f.size;
        let hts = f.heights;
        let at = |x: u32, z: u32| hts[(z * f.side + x) as usize];
        let c0_h = if shape == (Shape::Rotated { horizontal: true }) { at(x - h, z) } else { 0 };
        let c0_v = if shape == (Shape::Rotated { horizontal: false }) { at(x, z - h) } else { 0 };
        let (c0, c1, c2, c3, ext_col) = match shape {
            Shape::Square => (
                at(x - h, z - h),
                at(x + h, z - h),
                at(x - h, z + h),
                at(x + h, z + h),
                5,
            ),
            Shape::Rotated { horizontal: true } => (
                c0_h,
                at(x + h, z),
                // A missing apex (map edge) repeats a hypotenuse end: no widening.
                if z >= h { at(x, z - h) } else { c0_h },
                if z + h <= s { at(x, z + h) } else { c0_h },
                6,
            ),
            Shape::Rotated { horizontal: false } => (
                c0_v,
                at(x, z + h),
                if x >= h { at(x - h, z) } else { c0_v },
                if x + h <= s { at(x + h, z) } else { c0_v },
                6,
            ),
        };
        let lo = f32::from(c0.min(c1).min(c2.min(c3))) - e;
        let hi = f32::from(c0.max(c1).max(c2.max(c3))) + e;
        let (yc, hy) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        let (xf, zf, hf) = (x as f32, z as f32, h as f32);
        for p in &f.planes {
            let dist = p[0] * xf + p[1] * yc + p[2] * zf + p[3];
            if dist + hf * p[ext_col] + hy * p[4] < 0.0 {
                return; // wholly outside one plane
            }
        }
        let (ex, ez) = (f.eye_grid[0] - xf, f.eye_grid[1] - zf);
        let under = if ext_col == 5 {
            ex.abs() <= hf && ez.abs() <= hf
        } else {
            ex.abs() + ez.abs() <= hf
        };
        let (dx, dy, dz) = (ex * f.hs, f.eye[1] - yc * f.vs, ez * f.hs);
        let reach = f.hs * hf * if ext_col == 5 { std::f32::consts::SQRT_2 } else { 1.0 } + f.vs * hy;
        let d = ((dx * dx + dy * dy + dz * dz).sqrt() - reach).max(MIN_DISTANCE);
        let prio = e * f.px / d;
        let bucket = if under {
            TOP
        } else if prio >= f.threshold {
            ((prio.to_bits() >> 20) as usize).min(TOP - 1)
        } else {
            self.dropped_max = self.dropped_max.max(prio);
            return;
        };
        self.push_to(bucket, (u64::from(prio.to_bits()) << 32) | u64::from(pack(x, z)));
    }

    /// Re-queues a popped entry (by its priority; the under-the-eye mark is not needed
    /// any more, the frame is over).
    fn push(&mut self, entry: u64) {
        let prio = f32::from_bits((entry >> 32) as u32);
        self.push_to(((prio.to_bits() >> 20) as usize).min(TOP - 1), entry);
    }

    #[inline(always)]
    fn push_to(&mut self, bucket: usize, entry: u64) {
        self.buckets[bucket].push(entry);
        self.nonempty[bucket >> 6] |= 1 << (bucket & 63);
        self.summary |= 1 << (bucket >> 6);
    }

    #[inline(always)]
    fn top_bucket(&self) -> Option<usize> {
        if self.summary == 0 {
            return None;
        }
        let w = 31 - self.summary.leading_zeros() as usize;
        Some(w * 64 + 63 - self.nonempty[w].leading_zeros() as usize)
    }

    #[inline(always)]
    fn clear_bucket_bit(&mut self, b: usize) {
        self.nonempty[b >> 6] &= !(1 << (b & 63));
        if self.nonempty[b >> 6] == 0 {
            self.summary &= !(1 << (b >> 6));
        }
    }

    #[inline(always)]
    fn pop(&mut self) -> Option<u64> {
        let b = self.top_bucket()?;
        let bucket = &mut self.buckets[b];
        let entry = bucket.pop().expect("a bucket marked non-empty has entries");
        if bucket.is_empty() {
            self.clear_bucket_bit(b);
        }
        Some(entry)
    }

    /// The highest priority still queued, skipping diamonds already split. The top bucket
    /// (under the eye) is ranked by position, not priority, so it is read whole and the
    /// search goes on to the first ordinary bucket holding a live entry.
    fn remaining_max(&self) -> f32 {
        let live_max = |b: usize| {
            self.buckets[b]
                .iter()
                .filter(|&&e| {
                    let (x, z) = unpack(e as u32);
                    !self.is_active(x, z)
                })
                .map(|&e| f32::from_bits((e >> 32) as u32))
                .reduce(f32::max)
        };
        let mut best = 0f32;
        for b in (0..BUCKETS).rev() {
            if self.nonempty[b >> 6] >> (b & 63) & 1 == 0 {
                continue;
            }
            if let Some(v) = live_max(b) {
                best = best.max(v);
                if b != TOP {
                    break;
                }
            }
        }
        best
    }

    /// Writes the mesh: vertices are the corners and the split diamonds' centres, indexed by
    /// rank in the active bitset; triangles in bintree order.
    fn emit(&mut self, out: &mut Mesh) {
        let s = self.size;
        for (x, z) in [(0, 0), (s, 0), (0, s), (s, s)] {
            self.set_active(x, z);
        }
        out.vertices.clear();
        out.indices.clear();
        let mut total = 0u32;
        let side = self.side as usize;
        for (w, (&word, rank)) in self.active.iter().zip(self.rank.iter_mut()).enumerate() {
            *rank = total;
            total += word.count_ones();
            let mut bits = word;
            while bits != 0 {
                let i = w * 64 + bits.trailing_zeros() as usize;
                bits &= bits - 1;
                out.vertices.push([(i % side) as u16, (i / side) as u16]);
            }
        }
        let rank = |t: &Self, x: u32, z: u32| -> u32 {
            let i = (z * t.side + x) as usize;
            t.rank[i >> 6] + (t.active[i >> 6] & ((1u64 << (i & 63)) - 1)).count_ones()
        };
        self.stack.clear();
        let (r00, rs0, r0s, rss) = (rank(self, 0, 0), rank(self, s, 0), rank(self, 0, s), rank(self, s, s));
        self.stack.push([pack(0, s), pack(s, s), pack(0, 0), r0s, rss, r00]);
        self.stack.push([pack(s, 0), pack(0, 0), pack(s, s), rs0, r00, rss]);
        while let Some([a, l, r, ra, rl, rr]) = self.stack.pop() {
            let ((lx, lz), (rx, rz)) = (unpack(l), unpack(r));
            let (mx, mz) = ((lx + rx) / 2, (lz + rz) / 2);
            let splittable = (lx + rx) % 2 == 0 && (lz + rz) % 2 == 0;
            if splittable && self.is_active(mx, mz) {
                let mv = pack(mx, mz);
                let rm = rank(self, mx, mz);
                // Right child pushed first so the left one is emitted first.
                self.stack.push([mv, r, a, rm, rr, ra]);
                self.stack.push([mv, a, l, rm, ra, rl]);
            } else {
                out.indices.extend_from_slice(&[ra, rl, rr]);
            }
        }
    }
}
