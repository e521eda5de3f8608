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
    stats: Stats,
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
}

/// Everything `evaluate` needs about the frame, precomputed.
struct Frame<'a> {
    heights: &'a [u16],
    codes: &'a [u8],
    table: &'a [f32; 256],
    square_offset: [usize; 16],
    rotated_offset: [usize; 16],
    side: u32,
    size: u32,
    /// The four side planes of the view pyramid (its apex, the eye, makes a near plane
    /// unnecessary), as columns: `a·x_grid + b·sample + c·z_grid + d >= 0` inside; `|b|`,
    /// and the footprint extents `|a| + |c|` (square) and `max(|a|, |c|)` (rotated).
    pa: [f32; 4],
    pb: [f32; 4],
    pc: [f32; 4],
    pd: [f32; 4],
    abs_b: [f32; 4],
    ext_square: [f32; 4],
    ext_rotated: [f32; 4],
    eye_grid: [f32; 2],
    eye: [f32; 3],
    hs: f32,
    vs: f32,
    /// `v_scale · pixels_per_radian`: turns sample-unit error over world distance into px.
    px: f32,
    threshold: f32,
}

impl Frame<'_> {
    #[inline(always)]
    fn at(&self, x: u32, z: u32) -> u16 {
        self.heights[(z * self.side + x) as usize]
    }

    /// Stored error of a diamond with `m >= 1`, sample units.
    #[inline(always)]
    fn stored(&self, x: u32, z: u32, m: u32, shape: Shape) -> f32 {
        let i = variance::slot(&self.square_offset, &self.rotated_offset, self.size, x, z, m, shape);
        self.table[self.codes[i] as usize]
    }
}

#[inline(always)]
fn dev(c: u16, p: u16, q: u16) -> f32 {
    (f32::from(c) - 0.5 * (f32::from(p) + f32::from(q))).abs()
}

#[inline(always)]
fn min4(a: u16, b: u16, c: u16, d: u16) -> u16 {
    a.min(b).min(c.min(d))
}

#[inline(always)]
fn max4(a: u16, b: u16, c: u16, d: u16) -> u16 {
    a.max(b).max(c.max(d))
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
            stats: Stats::default(),
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

    /// Counts from the last frame.
    pub fn stats(&self) -> Stats {
        self.stats
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
        self.evaluate_root(&frame);
        while let Some(entry) = self.pop() {
            self.stats.popped += 1;
            let (x, z) = unpack(entry as u32);
            if self.is_active(x, z) {
                continue; // taken earlier by a forced split
            }
            if let Some(tris) = self.parents_split(x, z) {
                // The common case: nothing to force.
                if self.triangles + tris > budget {
                    self.push(entry);
                    break;
                }
                self.triangles += tris;
                self.commit(&frame, x, z);
                continue;
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
        let planes = camera.frustum();
        let col = |k: usize| -> [f32; 4] {
            std::array::from_fn(|i| {
                let p = &planes[i + 1];
                let (a, b, c) = (p.n[0] * scales.h, p.n[1] * scales.v, p.n[2] * scales.h);
                (match k {
                    0 => a,
                    1 => b,
                    2 => c,
                    3 => p.d,
                    4 => b.abs(),
                    5 => a.abs() + c.abs(),
                    _ => a.abs().max(c.abs()),
                }) as f32
            })
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
            side: self.side,
            size: self.size,
            pa: col(0),
            pb: col(1),
            pc: col(2),
            pd: col(3),
            abs_b: col(4),
            ext_square: col(5),
            ext_rotated: col(6),
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
        self.stats = Stats::default();
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

    /// `Some(triangles the split adds)` when every parent of `(x, z)` is split already.
    #[inline(always)]
    fn parents_split(&self, x: u32, z: u32) -> Option<u32> {
        let (m, shape) = classify(x, z);
        let h = 1 << m;
        let s = self.size;
        match shape {
            Shape::Square if 2 * h == s => Some(2),
            Shape::Square => {
                let ok = if ((x + h) >> (m + 1)) + ((z + h) >> (m + 1)) & 1 == 1 {
                    self.is_active(x + h, z + h) && self.is_active(x - h, z - h)
                } else {
                    self.is_active(x + h, z - h) && self.is_active(x - h, z + h)
                };
                ok.then_some(2)
            }
            Shape::Rotated { horizontal } => {
                let (c, ox, oz) = if horizontal { (z, 0, h) } else { (x, h, 0) };
                let lo = c >= h;
                let hi = c + h <= s;
                let ok = (!lo || self.is_active(x - ox, z - oz)) && (!hi || self.is_active(x + ox, z + oz));
                ok.then_some(u32::from(lo) + u32::from(hi))
            }
        }
    }

    /// Splits `(x, z)` (its parents are split) and queues the children it uncovers. A
    /// child is queued by whichever of its two parents is split first.
    #[inline(always)]
    fn commit(&mut self, f: &Frame, x: u32, z: u32) {
        self.set_active(x, z);
        self.active_list.push(pack(x, z));
        self.stats.split += 1;
        let (m, shape) = classify(x, z);
        let h = 1 << m;
        let s = self.size;
        match shape {
            Shape::Square => {
                // Children: rotated diamonds on the cell's edge midpoints, each sharing an
                // edge and the centre with this cell; the far corner of each is the centre
                // of its other parent, the next cell over.
                let (nw, ne, sw, se) = (f.at(x - h, z - h), f.at(x + h, z - h), f.at(x - h, z + h), f.at(x + h, z + h));
                let c = f.at(x, z);
                let vertical = Shape::Rotated { horizontal: false };
                let horizontal = Shape::Rotated { horizontal: true };
                // (child centre, its hypotenuse ends, far corner, far corner on the map)
                let kids = [
                    (x + h, z, ne, se, x + 2 * h, z, x + 2 * h <= s, vertical),
                    (x - h, z, nw, sw, x.wrapping_sub(2 * h), z, x >= 2 * h, vertical),
                    (x, z + h, sw, se, x, z + 2 * h, z + 2 * h <= s, horizontal),
                    (x, z - h, nw, ne, x, z.wrapping_sub(2 * h), z >= 2 * h, horizontal),
                ];
                for (cx, cz, p, q, fx, fz, far_on_map, shape) in kids {
                    if far_on_map && self.is_active(fx, fz) {
                        continue; // queued when its other parent was split
                    }
                    // A missing far corner (map edge) repeats a hypotenuse end.
                    let far = if far_on_map { f.at(fx, fz) } else { p };
                    let e = if m == 0 { dev(f.at(cx, cz), p, q) } else { f.stored(cx, cz, m, shape) };
                    self.evaluate(f, cx, cz, h, false, e, min4(p, q, c, far), max4(p, q, c, far));
                }
            }
            Shape::Rotated { .. } if m == 0 => {}
            Shape::Rotated { horizontal } => {
                // Children: squares of half-size h/2 in the four quarter cells around the
                // centre that lie on the map; each cell's corners are this centre, a
                // hypotenuse end, an apex, and the far corner: the child's other parent.
                let c = f.at(x, z);
                let k = h / 2;
                let (ux, uz, vx, vz) = if horizontal { (h, 0, 0, h) } else { (0, h, h, 0) };
                for (su, sv) in [(false, false), (true, false), (false, true), (true, true)] {
                    // `u` runs along the hypotenuse, `v` towards an apex.
                    let (ax, az) = if sv { (x.wrapping_sub(vx), z.wrapping_sub(vz)) } else { (x + vx, z + vz) };
                    if ax > s || az > s {
                        continue; // no apex: the child is off the map
                    }
                    let (ex, ez) = if su { (x.wrapping_sub(ux), z.wrapping_sub(uz)) } else { (x + ux, z + uz) };
                    let (fx, fz) = (ex + ax - x, ez + az - z);
                    if self.is_active(fx, fz) {
                        continue; // queued when its other parent was split
                    }
                    let (cx, cz) = ((x + fx) / 2, (z + fz) / 2);
                    let (end, apex, far) = (f.at(ex, ez), f.at(ax, az), f.at(fx, fz));
                    let e = if m == 1 {
                        // Finest square: exact, from its centre and edge midpoints. Its
                        // hypotenuse joins `end` and `apex`.
                        let mid = |ax: u32, az: u32, bx: u32, bz: u32| f.at((ax + bx) / 2, (az + bz) / 2);
                        dev(f.at(cx, cz), end, apex)
                            .max(dev(mid(x, z, ex, ez), c, end))
                            .max(dev(mid(ex, ez, fx, fz), end, far))
                            .max(dev(mid(fx, fz, ax, az), far, apex))
                            .max(dev(mid(ax, az, x, z), apex, c))
                    } else {
                        f.stored(cx, cz, m - 1, Shape::Square)
                    };
                    self.evaluate(f, cx, cz, k, true, e, min4(c, end, apex, far), max4(c, end, apex, far));
                }
            }
        }
    }

    /// Queues the root diamond.
    fn evaluate_root(&mut self, f: &Frame) {
        let r = self.size / 2;
        let s = self.size;
        let (nw, ne, sw, se) = (f.at(0, 0), f.at(s, 0), f.at(0, s), f.at(s, s));
        let e = if r == 1 {
            // Side 3: the root is the finest square.
            let c = f.at(1, 1);
            dev(c, nw, se)
                .max(dev(f.at(1, 0), nw, ne))
                .max(dev(f.at(2, 1), ne, se))
                .max(dev(f.at(1, 2), sw, se))
                .max(dev(f.at(0, 1), nw, sw))
        } else {
            f.stored(r, r, r.trailing_zeros(), Shape::Square)
        };
        self.evaluate(f, r, r, r, true, e, min4(nw, ne, sw, se), max4(nw, ne, sw, se));
    }

    /// Computes the priority of diamond `(x, z)` (half-size `h`, error `e` in sample units,
    /// corner heights within `lo..=hi`) and queues it, unless it is wholly outside the
    /// frustum (never queued) or below the threshold (remembered for the error bound).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn evaluate(&mut self, f: &Frame, x: u32, z: u32, h: u32, square: bool, e: f32, lo: u16, hi: u16) {
        self.stats.evaluated += 1;
        if e <= 0.0 {
            return; // exact already: splitting adds nothing
        }
        let lo = f32::from(lo) - e;
        let hi = f32::from(hi) + e;
        let (yc, hy) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        let (xf, zf, hf) = (x as f32, z as f32, h as f32);
        let ext = if square { &f.ext_square } else { &f.ext_rotated };
        let mut outside = false;
        for i in 0..4 {
            let dist = f.pa[i] * xf + f.pb[i] * yc + f.pc[i] * zf + f.pd[i] + hf * ext[i] + hy * f.abs_b[i];
            outside |= dist < 0.0;
        }
        if outside {
            self.stats.culled += 1;
            return; // wholly outside one plane
        }
        let (ex, ez) = (f.eye_grid[0] - xf, f.eye_grid[1] - zf);
        let under = if square {
            ex.abs() <= hf && ez.abs() <= hf
        } else {
            ex.abs() + ez.abs() <= hf
        };
        let (dx, dy, dz) = (ex * f.hs, f.eye[1] - yc * f.vs, ez * f.hs);
        let reach = f.hs * hf * if square { std::f32::consts::SQRT_2 } else { 1.0 } + f.vs * hy;
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

    #[inline(never)]
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
    #[inline(never)]
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
