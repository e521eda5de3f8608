//! Queuing the children of a split diamond: their corner heights and stored errors, the
//! frustum test and the priority.

use super::{Frame, MIN_DISTANCE, Tessellator, dev, max4, min4, offset, pack};
use crate::diamond::Shape;
use crate::queue::{TOP, bucket_of};

impl Tessellator {
    /// Children of a square: rotated diamonds on the cell's edge midpoints, each sharing an
    /// edge and the centre with this cell; the far corner of each is the centre of its other
    /// parent, the next cell over. A missing far corner (map edge) repeats a hypotenuse end.
    #[inline(always)]
    pub(super) fn commit_square(&mut self, f: &Frame, x: u32, z: u32, m: u32) {
        let h = 1 << m;
        let (s, side) = (self.size, self.side);
        let row = z * side;
        let (up, down) = (row - h * side, row + h * side);
        let (nw, ne) = (f.h(up + x - h), f.h(up + x + h));
        let (sw, se) = (f.h(down + x - h), f.h(down + x + h));
        let c = f.h(row + x);
        // Slots of the four children in the variance tree: vertical ones (east, west) share
        // a row, horizontal ones (north, south) a column.
        let n = (s >> (m + 1)) as usize;
        let vbase = f.rotated_offset[m as usize] + n * (n + 1) + (z >> (m + 1)) as usize * (n + 1);
        let (ha, hb) = ((x >> (m + 1)) as usize, (z >> (m + 1)) as usize);
        let hbase = f.rotated_offset[m as usize] + ha;
        let error = |slot: usize, centre: u32, p: u16, q: u16| {
            if m == 0 {
                // `variance::finest` for a finest rotated diamond, with the hypotenuse ends
                // this parent has already read.
                dev(f.h(centre), p, q)
            } else {
                f.error_at(slot)
            }
        };
        if x + 2 * h > s || !self.is_active_at(row + x + 2 * h) {
            let far = if x + 2 * h <= s {
                f.h(row + x + 2 * h)
            } else {
                ne
            };
            let e = error(vbase + ha + 1, row + x + h, ne, se);
            self.evaluate(
                f,
                x + h,
                z,
                h,
                false,
                e,
                min4(ne, se, c, far),
                max4(ne, se, c, far),
            );
        }
        if x < 2 * h || !self.is_active_at(row + x - 2 * h) {
            let far = if x >= 2 * h { f.h(row + x - 2 * h) } else { nw };
            let e = error(vbase + ha, row + x - h, nw, sw);
            self.evaluate(
                f,
                x - h,
                z,
                h,
                false,
                e,
                min4(nw, sw, c, far),
                max4(nw, sw, c, far),
            );
        }
        if z + 2 * h > s || !self.is_active_at(row + 2 * h * side + x) {
            let far = if z + 2 * h <= s {
                f.h(row + 2 * h * side + x)
            } else {
                sw
            };
            let e = error(hbase + (hb + 1) * n, down + x, sw, se);
            self.evaluate(
                f,
                x,
                z + h,
                h,
                false,
                e,
                min4(sw, se, c, far),
                max4(sw, se, c, far),
            );
        }
        if z < 2 * h || !self.is_active_at(row - 2 * h * side + x) {
            let far = if z >= 2 * h {
                f.h(row - 2 * h * side + x)
            } else {
                nw
            };
            let e = error(hbase + hb * n, up + x, nw, ne);
            self.evaluate(
                f,
                x,
                z - h,
                h,
                false,
                e,
                min4(nw, ne, c, far),
                max4(nw, ne, c, far),
            );
        }
    }

    /// Children of a rotated diamond: squares of half-size h/2 in the four quarter cells
    /// around the centre that lie on the map; each cell's corners are this centre, a
    /// hypotenuse end, an apex, and the far corner: the child's other parent.
    #[inline(always)]
    pub(super) fn commit_rotated(&mut self, f: &Frame, x: u32, z: u32, m: u32, horizontal: bool) {
        let h = 1 << m;
        let (s, side) = (self.size, self.side);
        let k = h / 2;
        let row = z * side;
        let c = f.h(row + x);
        // `u` runs along the hypotenuse, `v` towards the apices, as index offsets.
        let (du, dv) = if horizontal {
            (h, h * side)
        } else {
            (h * side, h)
        };
        let (e0, e1) = (f.h(row + x - du), f.h(row + x + du));
        let (has_lo, has_hi) = if horizontal {
            (z >= h, z + h <= s)
        } else {
            (x >= h, x + h <= s)
        };
        let n = (s >> m) as usize; // squares of level m - 1 per row
        let slot = |cx: u32, cz: u32| {
            f.square_offset[m as usize - 1] + (cz >> m) as usize * n + (cx >> m) as usize
        };
        let (ku, kv) = if horizontal {
            ((k, 0), (0, k))
        } else {
            ((0, k), (k, 0))
        };
        for (apex_ok, sign_v) in [(has_lo, false), (has_hi, true)] {
            if !apex_ok {
                continue; // no apex: the children on that side are off the map
            }
            let apex_i = if sign_v { row + x + dv } else { row + x - dv };
            let apex = f.h(apex_i);
            for (end, sign_u) in [(e0, false), (e1, true)] {
                let far_i = if sign_u { apex_i + du } else { apex_i - du };
                if self.is_active_at(far_i) {
                    continue; // queued when its other parent was split
                }
                let far = f.h(far_i);
                let cx = offset(offset(x, ku.0, sign_u), kv.0, sign_v);
                let cz = offset(offset(z, ku.1, sign_u), kv.1, sign_v);
                let e = f.error_at(slot(cx, cz));
                self.evaluate(
                    f,
                    cx,
                    cz,
                    k,
                    true,
                    e,
                    min4(c, end, apex, far),
                    max4(c, end, apex, far),
                );
            }
        }
    }

    /// Queues the root diamond.
    pub(super) fn evaluate_root(&mut self, f: &Frame) {
        let r = self.size / 2;
        let s = self.size;
        let (nw, ne, sw, se) = (f.at(0, 0), f.at(s, 0), f.at(0, s), f.at(s, s));
        let e = f.stored(r, r, r.trailing_zeros(), Shape::Square);
        self.evaluate(
            f,
            r,
            r,
            r,
            true,
            e,
            min4(nw, ne, sw, se),
            max4(nw, ne, sw, se),
        );
    }

    /// Computes the priority of diamond `(x, z)` (half-size `h`, error `e` in sample units,
    /// corner heights within `lo..=hi`) and queues it, unless it is wholly outside the
    /// frustum (never queued) or below the threshold (remembered for the error bound).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn evaluate(
        &mut self,
        f: &Frame,
        x: u32,
        z: u32,
        h: u32,
        square: bool,
        e: f32,
        lo: u16,
        hi: u16,
    ) {
        self.stats.evaluated += 1;
        if e <= 0.0 {
            return; // exact already: splitting adds nothing
        }
        let (lo, hi) = (f32::from(lo) - e, f32::from(hi) + e);
        let (yc, hy) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        let (xf, zf, hf) = (x as f32, z as f32, h as f32);
        let ext = if square {
            &f.ext_square
        } else {
            &f.ext_rotated
        };
        // The four planes at once (lanes are planes): outside if any distance is negative.
        let mut outside = false;
        #[allow(clippy::needless_range_loop)] // four planes, four parallel arrays
        for p in 0..4 {
            let d = f.pa[p] * xf
                + f.pb[p] * yc
                + f.pc[p] * zf
                + f.pd[p]
                + hf * ext[p]
                + hy * f.abs_b[p];
            outside |= d < 0.0;
        }
        // The ground under the eye is refined first, in view or not.
        let (ex, ez) = (f.eye_grid[0] - xf, f.eye_grid[1] - zf);
        let under = if square {
            ex.abs() <= hf && ez.abs() <= hf
        } else {
            ex.abs() + ez.abs() <= hf
        };
        if outside && !under {
            self.stats.culled += 1;
            return;
        }
        let (dx, dy, dz) = (ex * f.hs, f.eye_y - yc * f.vs, ez * f.hs);
        let reach = f.hs
            * hf
            * if square {
                std::f32::consts::SQRT_2
            } else {
                1.0
            }
            + f.vs * hy;
        let d = ((dx * dx + dy * dy + dz * dz).sqrt() - reach).max(MIN_DISTANCE);
        let prio = e * f.px / d;
        let bucket = if under {
            TOP
        } else if prio >= f.threshold {
            bucket_of(prio)
        } else {
            self.dropped_max = self.dropped_max.max(prio);
            return;
        };
        self.queue.push(
            bucket,
            (u64::from(prio.to_bits()) << 32) | u64::from(pack(x, z)),
        );
    }
}
