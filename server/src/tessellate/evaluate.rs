//! Queuing the children of a split diamond: their corner heights and stored errors, the
//! frustum test and the priority, for all of a split's children at once (one per lane).
//!
//! **Fog** (issue 24): the priority is the screen-space error `e · px / d` times the fog's
//! transmission `exp(−density · max(clear, 0))`, `clear` the distance from the eye to the
//! bounding prism (nearest: the transmission is the largest the diamond's error could be
//! seen with). The viewer's fog hides far error anyway, so the budget goes nearer. Without
//! fog (density 0: the map has none, the viewer turned it off, or `--fog-priority off`)
//! the product is skipped and the cut is bit for bit the fog-unaware one (`tests/fog.rs`
//! pins digests taken before). The transmission is [`F4::exp2_neg`] of
//! `max(clear, 0) · ρ·log2 e` (the frame's `fog_log2e`), IEEE arithmetic only, so every
//! build and machine still ranks alike.
//!
//! Its cost is latency, not instructions (issue 41): this priority is what a batch's queue
//! entries wait on, so the fog's product lengthened the chain the split loop waits on.
//! With the shorter transmission (`lanes.rs`: one multiply fewer here, rounding by a
//! shifted add, Estrin's scheme) the from-scratch cut with fog went from 1.07× to 0.97×
//! the time without on `data/kossou` (36.4 → 33.9 ns a triangle, 34.2–34.8 without), and
//! from 1.05× to 0.90× on a steep map (`bench DIR --budget 65536 --json
//! --fog-priority on|off`; the table and commands in `lanes.rs`).

use super::lanes::F4;
use super::{Frame, MIN_DISTANCE, Tessellator, pack};
use crate::tessellate::queue::{TOP, bucket_of};
use roam_protocol::bintree::Shape;

/// Up to four diamonds of one shape and half-size, one per lane.
pub(super) struct Batch {
    /// Centres, grid units.
    pub x: F4,
    pub z: F4,
    /// Centres, packed as queue entries carry them.
    pub pos: [u32; 4],
    /// Stored errors, sample units.
    pub e: F4,
    /// Smallest and largest corner heights.
    pub lo: F4,
    pub hi: F4,
    /// Bit `i`: lane `i` holds a diamond to evaluate (the others hold safe stand-ins).
    pub valid: u32,
}

/// What the priority needs of each lane's shape and size.
pub(super) struct Shape4 {
    /// Half-size, grid units.
    pub h: F4,
    /// `h_scale · h · k`: the footprint's reach, world units (`k` = √2 for squares, 1 for
    /// rotated diamonds).
    pub reach: F4,
    /// Bit `i`: lane `i` is a square (0 or 0xf in a batch of one shape).
    pub square: u32,
    /// Per plane, `d` plus the footprint's reach across it.
    pub offsets: [F4; 4],
}

/// A batch's priorities and what decides how long they stay true.
pub(super) struct Priority {
    /// Screen-space error in pixels, weighed by the fog's transmission.
    pub prio: F4,
    /// Lanes wholly outside one frustum plane, and lanes whose footprint holds the eye's
    /// ground position.
    pub outside: u32,
    pub under: u32,
    /// Distance from the eye to the centre less the prism's reach (before the floor), and
    /// plus it: world units.
    pub clear: F4,
    pub far: F4,
    /// The smallest of the four planes' largest signed distance over the prism (how far it
    /// is from leaving the view), and the largest distance wholly behind one (how far from
    /// entering it): world units.
    pub inside_by: F4,
    pub outside_by: F4,
    /// The same over the two side planes alone (left and right: the guard band widens
    /// them) and over the bottom and top ones.
    pub inside_by_sides: F4,
    pub outside_by_sides: F4,
    pub inside_by_ends: F4,
    pub outside_by_ends: F4,
    /// A lower bound on how far the prism is from the vertical through the eye: its
    /// horizontal distance, less the vertical one and the reach (world units; negative
    /// near the eye).
    pub aside: F4,
    /// The eye's ground position from the centre, grid units.
    pub ex: F4,
    pub ez: F4,
}

/// The priority of each lane (screen-space error in pixels, times the fog's transmission
/// `exp(−density · max(clear, 0))`), and the masks of lanes wholly
/// outside one frustum plane and of lanes whose footprint holds the eye's ground position.
/// One computation for the from-scratch and the frame-coherent tessellators, so both rank
/// a diamond identically, bit for bit (what a caller does not read is compiled out).
#[inline(always)]
pub(super) fn priority(f: &Frame, b: &Batch, s: &Shape4) -> Priority {
    let (lo, hi) = (b.lo.sub(b.e), b.hi.add(b.e));
    let half = F4::splat(0.5);
    let (yc, hy) = (half.mul(lo.add(hi)), half.mul(hi.sub(lo)));
    let (xf, zf) = (b.x, b.z);
    // Outside if any of the four planes puts the bounding prism wholly behind it.
    let mut outside = 0;
    let mut inside = [F4::splat(f32::INFINITY); 2];
    let mut outside_by = [F4::splat(0.0); 2];
    for (k, (p, offset)) in f.planes.iter().zip(&s.offsets).enumerate() {
        let d =
            p.a.mul(xf)
                .add(p.b.mul(yc))
                .add(p.c.mul(zf))
                .add(*offset)
                .add(hy.mul(p.abs_b));
        outside |= d.lt(F4::splat(0.0));
        inside[k / 2] = inside[k / 2].min(d);
        outside_by[k / 2] = F4::splat(0.0).sub(d).max(outside_by[k / 2]);
    }
    // The ground under the eye is refined first, in view or not.
    let (ex, ez) = (f.eye_x.sub(xf), f.eye_z.sub(zf));
    let boxed = || ex.abs().le(s.h) & ez.abs().le(s.h);
    let l1 = || ex.abs().add(ez.abs()).le(s.h);
    let under = match s.square {
        0xf => boxed(),
        0 => l1(),
        sq => (boxed() & sq) | (l1() & !sq & 0xf),
    };
    let (dx, dy, dz) = (ex.mul(f.hs), f.eye_y.sub(yc.mul(f.vs)), ez.mul(f.hs));
    let reach = s.reach.add(f.vs.mul(hy));
    let dist = dx.mul(dx).add(dy.mul(dy)).add(dz.mul(dz)).sqrt();
    let clear = dist.sub(reach);
    let aside = dx.mul(dx).add(dz.mul(dz)).sqrt().sub(dy.abs()).sub(reach);
    let d = clear.max(F4::splat(MIN_DISTANCE));
    let prio = b.e.mul(f.px).div(d);
    // What the fog lets through of the error, at the nearest distance to the prism: the
    // most of it the diamond could show. Without fog nothing is multiplied (by `exp(0)` =
    // 1 it would be exact too): the priority is the fog-unaware one, bit for bit.
    let prio = if f.fogged {
        prio.mul(clear.max(F4::splat(0.0)).mul(f.fog_log2e).exp2_neg())
    } else {
        prio
    };
    Priority {
        prio,
        outside,
        under,
        clear,
        far: dist.add(reach),
        inside_by: inside[0].min(inside[1]),
        outside_by: outside_by[0].max(outside_by[1]),
        inside_by_sides: inside[0],
        outside_by_sides: outside_by[0],
        inside_by_ends: inside[1],
        outside_by_ends: outside_by[1],
        aside,
        ex,
        ez,
    }
}

/// The smallest and largest of four corner heights, per lane.
#[inline(always)]
pub(super) fn bounds(a: F4, b: F4, c: F4, d: F4) -> (F4, F4) {
    (a.min(b).min(c).min(d), a.max(b).max(c).max(d))
}

#[inline(always)]
pub(super) fn heights(v: [u16; 4]) -> F4 {
    F4::new(v.map(f32::from))
}

impl Tessellator {
    /// Children of a square: rotated diamonds on the cell's edge midpoints (east, west,
    /// south, north), each sharing an edge and the centre with this cell; the far corner of
    /// each is the centre of its other parent, the next cell over. A child is queued by
    /// whichever of its parents is split first; a missing far corner (map edge) repeats a
    /// hypotenuse end.
    #[inline(always)]
    pub(super) fn commit_square(&mut self, f: &Frame, x: u32, z: u32, m: u32) {
        let h = 1 << m;
        let (s, side) = (self.size, self.side);
        let row = z * side;
        let (up, down) = (row - h * side, row + h * side);
        let inside = [x + 2 * h <= s, x >= 2 * h, z + 2 * h <= s, z >= 2 * h];
        // Index of each far corner where it is on the map (else the centre, unused).
        let far_i = [
            if inside[0] { row + x + 2 * h } else { row + x },
            if inside[1] { row + x - 2 * h } else { row + x },
            if inside[2] {
                row + 2 * h * side + x
            } else {
                row + x
            },
            if inside[3] {
                row - 2 * h * side + x
            } else {
                row + x
            },
        ];
        let mut valid = 0;
        for i in 0..4 {
            valid |= u32::from(!inside[i] || !self.is_active_at(far_i[i])) << i;
        }
        if valid == 0 {
            return; // every child was queued by its other parent
        }
        let (nw, ne) = (f.h(up + x - h), f.h(up + x + h));
        let (sw, se) = (f.h(down + x - h), f.h(down + x + h));
        let far: [u16; 4] = std::array::from_fn(|i| f.h(far_i[i]));
        // Hypotenuse ends of each child.
        let (p, q) = ([ne, nw, sw, nw], [se, sw, se, ne]);
        let far = std::array::from_fn(|i| if inside[i] { far[i] } else { p[i] });
        let (p, q, far) = (heights(p), heights(q), heights(far));
        let (lo, hi) = bounds(p, q, F4::splat(f32::from(f.h(row + x))), far);
        let e = if m == 0 {
            // `variance::finest` for finest rotated diamonds, with the hypotenuse ends
            // already read.
            let centre = heights([
                f.h(row + x + h),
                f.h(row + x - h),
                f.h(down + x),
                f.h(up + x),
            ]);
            centre.sub(F4::splat(0.5).mul(p.add(q))).abs()
        } else {
            // Slots in the variance tree: vertical children (east, west) share a row,
            // horizontal ones (north, south) a column.
            let n = (s >> (m + 1)) as usize;
            let base = f.rotated_offset[m as usize];
            let (ha, hb) = ((x >> (m + 1)) as usize, (z >> (m + 1)) as usize);
            let vbase = base + n * (n + 1) + hb * (n + 1);
            F4::new([
                f.error_at(vbase + ha + 1),
                f.error_at(vbase + ha),
                f.error_at(base + ha + (hb + 1) * n),
                f.error_at(base + ha + hb * n),
            ])
        };
        let (cx, cz) = ([x + h, x - h, x, x], [z, z, z + h, z - h]);
        let batch = Batch {
            x: F4::from_u32(cx),
            z: F4::from_u32(cz),
            pos: std::array::from_fn(|i| pack(cx[i], cz[i])),
            e,
            lo,
            hi,
            valid,
        };
        self.evaluate(f, &batch, m, false);
    }

    /// Children of a rotated diamond: squares of half-size h/2 in the four quarter cells
    /// around the centre that lie on the map; each cell's corners are this centre, a
    /// hypotenuse end, an apex, and the far corner: the child's other parent. Lanes: (first
    /// apex, first end), (first apex, second end), (second apex, first end), (second apex,
    /// second end).
    #[inline(always)]
    pub(super) fn commit_rotated(&mut self, f: &Frame, x: u32, z: u32, m: u32, horizontal: bool) {
        let h = 1 << m;
        let (s, side) = (self.size, self.side);
        let k = h / 2;
        let centre = z * side + x;
        // `u` runs along the hypotenuse, `v` towards the apices, as coordinates and as index
        // offsets.
        let (u, v, du, dv) = if horizontal {
            (x, z, h, h * side)
        } else {
            (z, x, h * side, h)
        };
        let (has_lo, has_hi) = (v >= h, v + h <= s);
        // A missing apex (map edge) is stood in for by the centre: its lanes are not valid.
        let apex_lo = if has_lo { centre - dv } else { centre };
        let apex_hi = if has_hi { centre + dv } else { centre };
        let far_i = [apex_lo - du, apex_lo + du, apex_hi - du, apex_hi + du];
        let has = [has_lo, has_lo, has_hi, has_hi];
        let mut valid = 0;
        for i in 0..4 {
            valid |= u32::from(has[i] && !self.is_active_at(far_i[i])) << i;
        }
        if valid == 0 {
            return;
        }
        let (e0, e1) = (f.h(centre - du), f.h(centre + du));
        let (alo, ahi) = (f.h(apex_lo), f.h(apex_hi));
        let far = std::array::from_fn(|i| f.h(far_i[i]));
        let (cu, cv) = (
            [u - k, u + k, u - k, u + k],
            [
                if has_lo { v - k } else { v + k },
                if has_lo { v - k } else { v + k },
                if has_hi { v + k } else { v - k },
                if has_hi { v + k } else { v - k },
            ],
        );
        let (cx, cz) = if horizontal { (cu, cv) } else { (cv, cu) };
        let n = (s >> m) as usize; // squares of level m - 1 per row
        let base = f.square_offset[m as usize - 1];
        let e = F4::new(std::array::from_fn(|i| {
            f.error_at(base + (cz[i] >> m) as usize * n + (cx[i] >> m) as usize)
        }));
        let (lo, hi) = bounds(
            F4::splat(f32::from(f.h(centre))),
            heights([e0, e1, e0, e1]),
            heights([alo, alo, ahi, ahi]),
            heights(far),
        );
        let batch = Batch {
            x: F4::from_u32(cx),
            z: F4::from_u32(cz),
            pos: std::array::from_fn(|i| pack(cx[i], cz[i])),
            e,
            lo,
            hi,
            valid,
        };
        self.evaluate(f, &batch, m - 1, true);
    }

    /// Queues the root diamond.
    pub(super) fn evaluate_root(&mut self, f: &Frame) {
        let r = self.size / 2;
        let s = self.size;
        let corners = heights([f.at(0, 0), f.at(s, 0), f.at(0, s), f.at(s, s)]).to_array();
        let (lo, hi) = (
            corners.into_iter().fold(f32::INFINITY, f32::min),
            corners.into_iter().fold(0.0, f32::max),
        );
        let batch = Batch {
            x: F4::splat(r as f32),
            z: F4::splat(r as f32),
            pos: [pack(r, r); 4],
            e: F4::splat(f.stored(r, r, r.trailing_zeros(), Shape::Square)),
            lo: F4::splat(lo),
            hi: F4::splat(hi),
            valid: 1,
        };
        self.evaluate(f, &batch, r.trailing_zeros(), true);
    }

    /// Computes the priorities of a batch's diamonds (half-size `2^m`) and queues each, lanes
    /// in order, unless it is exact already, wholly outside the frustum (never queued) or
    /// below the threshold (remembered for the error bound).
    #[inline(always)]
    fn evaluate(&mut self, f: &Frame, b: &Batch, m: u32, square: bool) {
        let h = 1u32 << m;
        self.stats.evaluated += b.valid.count_ones();
        // A diamond with no error is exact already: splitting adds nothing.
        let live = b.valid & F4::splat(0.0).lt(b.e);
        if live == 0 {
            return;
        }
        let k = if square {
            std::f32::consts::SQRT_2
        } else {
            1.0
        };
        let shape = Shape4 {
            h: F4::splat(h as f32),
            reach: F4::splat(f.hs_scalar * h as f32 * k),
            square: if square { 0xf } else { 0 },
            offsets: f.plane_offsets[usize::from(square) << 4 | m as usize],
        };
        let Priority {
            prio,
            outside,
            under,
            ..
        } = priority(f, b, &shape);
        let shown = live & (!outside | under);
        self.stats.culled += (live & !shown).count_ones();
        let above = f.threshold.le(prio);
        let dropped = shown & !under & !above;
        if dropped != 0 {
            // `max` with the old value second, so a NaN priority would be ignored.
            self.dropped = prio.keep(dropped).max(self.dropped);
        }
        let prio = prio.to_array();
        let queued = shown & (under | above);
        // All four lanes, in order: the ones not queued go to the trash, so no branch
        // depends on how many are.
        for (i, (p, pos)) in prio.into_iter().zip(b.pos).enumerate() {
            let bucket = if under >> i & 1 != 0 {
                TOP
            } else {
                bucket_of(p)
            };
            let entry = (u64::from(p.to_bits()) << 32) | u64::from(pos);
            self.queue.push_if(queued >> i & 1 != 0, bucket, entry);
        }
    }
}
