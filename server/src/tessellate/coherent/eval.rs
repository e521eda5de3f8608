//! Priorities of frontier diamonds of any shapes and sizes, four at a time, with the same
//! arithmetic as the from-scratch tessellator ([`crate::tessellate::evaluate::priority`]).
//! What does not depend on the camera (centre, error, height bounds, size: [`Fixed`]) is
//! gathered from the map at each evaluation ([`fixed`]): kept beside each frontier
//! diamond it cost 28 bytes a diamond (1.1 MB at 65,536 triangles), for 10 to 14
//! gathers a frame (see [`super::frontier`]).
//!
//! **How long a priority stays true, with fog** ([`by_prio`]). The priority at distance
//! `d` (the eye to the bounding prism, `clear`) is `P(d) = e · px / d · exp(−ρ·d)`. The
//! eye moving by `δ` changes `d` by at most `δ`, so `P` grows by at most the factor
//! `d / (d − δ) · exp(ρ·δ)` (and shrinks by at most its inverse, the same bound
//! downwards). It must stay within `1 + r`. With `exp(ρ·δ) <= 1 / (1 − ρ·δ)` (for
//! `ρ·δ < 1`) it is enough that `d / ((d − δ)(1 − ρ·δ)) <= 1 + r`, i.e.
//! `(1 + r)·ρ·δ² − (1 + r)(1 + ρ·d)·δ + r·d >= 0`, which holds from 0 to the smaller root
//! (below both `d` and `1/ρ`, where the left side is `−d`):
//!
//! `δ = 2·r·d / (a + sqrt(a² − 4·(1 + r)·ρ·r·d))`, `a = (1 + r)(1 + ρ·d)`
//!
//! (the stable form: no cancellation; the discriminant is positive, clamped at 0 against
//! rounding). At `ρ = 0`, `a = 1 + r` and the square root gives `a` back exactly (IEEE:
//! `sqrt(a·a)` is `a`), so `δ = 2·r·d / (2·a)` is today's `d·r / (1 + r)` bit for bit:
//! the exact bound for the distance alone (`d / (d − δ) = 1 + r`), so without fog nothing
//! is evaluated more often than before. The bound `−ln(1 − x) <= x / (1 − x)` on the
//! distance term instead (the fog term exact) gives `L·d / (1 + L)` at `ρ = 0`,
//! `L = ln(1 + r)`: 1 % tighter than today for no gain, so the fog term is the one
//! bounded. As `ρ·d` grows, `δ` tends to `r / ((1 + r)·ρ)`: the fog, not the distance,
//! limits how far the eye may go. Measured on `kossou` at 32,768 triangles (`bench
//! --fog-priority off` / `on`, the figures in `cli/tess.rs`): the tighter bound cost no
//! evaluations there, fewer fall due with fog (a frame's median 20 → 18; 32 viewers in
//! turn 453 → 346 a frame on average; not analysed further: the fog-aware cut holds
//! fewer far diamonds, which turning sweeps in), and the served cut's
//! reported error stays within 2.5 % of a fresh measurement (`tests/tessellate.rs` and
//! `tests/fog.rs`, with fog).

use super::super::evaluate::{Batch, Shape4, priority};
use super::super::lanes::F4;
use super::super::{Frame, unpack};
use super::Coherent;
use roam_protocol::bintree::{Shape, shape_of};

/// The camera-independent part of a frontier diamond's priority, kept beside it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Fixed {
    /// Centre, grid units.
    x: f32,
    z: f32,
    /// Stored error, sample units.
    e: f32,
    /// Smallest and largest corner heights, samples.
    lo: f32,
    hi: f32,
    /// Half-size, grid units, and the footprint's reach per unit of it (√2 or 1).
    h: f32,
    k: f32,
    /// `square << 4 | m`: the index of its plane offsets.
    kind: u16,
}

impl Fixed {
    /// Without error: its priority is 0 wherever the eye is, never due again.
    pub(super) fn exact(&self) -> bool {
        self.e <= 0.0 || self.e.is_nan()
    }
}

/// What a diamond's evaluation says, per lane.
pub(super) struct Lanes {
    pub prio: [f32; 4],
    /// Lanes worth splitting: error, in view (or under the eye), at or above the threshold.
    pub wanted: u32,
    /// Lanes whose footprint holds the eye's ground position.
    pub under: u32,
    /// Lanes in view with error, but below the threshold (for the error bound).
    pub dropped: u32,
    /// Per lane, how far the eye may move (world units) and turn (radians) before the
    /// evaluation must be done again.
    pub slack: [(f32, f32); 4],
}

/// How far a kept priority may drift from the true one before it is computed again: 2 %
/// (the split/merge choices and the error bound are that close to exact).
pub(super) const PRIORITY_TOLERANCE: f32 = 0.02;

/// Lane `i`'s verdicts as [`super::frontier::Member`] flags.
pub(super) fn lane_flags(l: &Lanes, i: usize) -> u8 {
    use super::frontier::{DROPPED, UNDER, WANTED};
    let bit = |mask: u32, flag: u8| if mask >> i & 1 != 0 { flag } else { 0 };
    bit(l.wanted, WANTED) | bit(l.under, UNDER) | bit(l.dropped, DROPPED)
}

impl Coherent {
    /// Priorities of up to four diamonds (lanes past `n` repeat the first).
    #[inline(always)]
    pub(super) fn evaluate(&self, f: &Frame, d: [&Fixed; 4], n: usize) -> Lanes {
        let lane = |g: fn(&Fixed) -> f32| F4::new([g(d[0]), g(d[1]), g(d[2]), g(d[3])]);
        let batch = Batch {
            x: lane(|d| d.x),
            z: lane(|d| d.z),
            pos: [0; 4],
            e: lane(|d| d.e),
            lo: lane(|d| d.lo),
            hi: lane(|d| d.hi),
            valid: (1 << n) - 1,
        };
        let h = lane(|d| d.h);
        let mut square = 0;
        let mut offsets = [[0f32; 4]; 4];
        for (i, d) in d.iter().enumerate() {
            square |= u32::from(d.kind >> 4) << i;
            let o = &f.offsets_scalar[usize::from(d.kind)];
            for (plane, lanes) in offsets.iter_mut().enumerate() {
                lanes[i] = o[plane];
            }
        }
        let shape = Shape4 {
            h,
            reach: F4::splat(f.hs_scalar).mul(h).mul(lane(|d| d.k)),
            square,
            offsets: offsets.map(F4::new),
        };
        let p = priority(f, &batch, &shape);
        let live = batch.valid & F4::splat(0.0).lt(batch.e);
        let shown = live & (!p.outside | p.under);
        let above = f.threshold.le(p.prio);
        // How far the eye may move, and turn, before any of this could change (see the
        // module docs): the priority by more than `PRIORITY_TOLERANCE`, the frustum's
        // verdict, or whether the footprint holds the eye's ground position.
        let zero = F4::splat(0.0);
        let ground = F4::splat(f.hs_scalar);
        let (ax, az) = (p.ex.abs().sub(h), p.ez.abs().sub(h));
        let to_box = ax.max(az);
        let to_l1 = ax
            .add(p.ez.abs())
            .mul(F4::splat(std::f32::consts::FRAC_1_SQRT_2));
        let footprint = F4::new(std::array::from_fn(|i| {
            if square >> i & 1 != 0 {
                to_box.to_array()[i]
            } else {
                to_l1.to_array()[i]
            }
        }))
        .max(zero)
        .mul(ground);
        let margin = F4::new(std::array::from_fn(|i| {
            if p.outside >> i & 1 != 0 {
                p.outside_by.to_array()[i]
            } else {
                p.inside_by.to_array()[i]
            }
        }))
        .max(zero);
        // The priority may drift by the tolerance, and by less when it is that close to the
        // threshold (so it cannot cross it unseen): `by_prio` (the module docs) keeps the
        // drift under a relative `r`, fog included; `clear · r / (1 + r)` without fog.
        let gap = p
            .prio
            .sub(f.threshold)
            .abs()
            .div(p.prio.max(f.threshold).max(F4::splat(1e-30)));
        let r = gap.min(F4::splat(PRIORITY_TOLERANCE));
        let by_prio = by_prio(p.clear, r, f.fog).max(zero);
        // The margin is shared between the eye's travel and its turning (travel + `far` ×
        // turn must stay under it), in proportion to how fast each has been eating it
        // lately (`Coherent::pace`): while the driver turns, the far diamonds' share goes
        // to turning, so they fall due less often (an even split evaluated 463 diamonds a
        // frame along the capacity drive with 32 viewers, this 330; 738 and 532 along the
        // bench's own drive). The share stays within a tenth and nine tenths: evaluations
        // a frame along the capacity drive (the mean, dominated by the turns) 332 with a
        // quarter and three quarters, 281 with this, 270 with a twentieth; a wider range
        // lets the small yaw wobble of a straight drive take more of the far diamonds'
        // travel margin (the median along the bench's own drive 15, 21 and 29).
        let far = p.far.max(F4::splat(1e-3));
        let (v, w) = (F4::splat(self.pace.0), F4::splat(self.pace.1));
        let eps = F4::splat(1e-6);
        let share = v
            .add(eps)
            .div(v.add(far.mul(w)).add(eps).add(eps))
            .max(F4::splat(0.1))
            .min(F4::splat(0.9));
        let moved = margin.mul(share).min(footprint);
        let moved_shown = moved.min(by_prio);
        let turned = margin.mul(F4::splat(1.0).sub(share)).div(far);
        // Under an allowance, a turn may carry a side plane past a diamond by the turn lag
        // (a share of the guard band, which widens the side planes: `TURN_LAG_SHARE`),
        // the bottom and top planes not at all.
        let turned = if self.turn_lag > 0.0 {
            // The band between a side plane and the widened one is as wide as the diamond
            // is far from their common line (near the vertical through the eye): at the
            // foot of the eye it is nothing. So the lag is scaled by how far aside the
            // diamond is (a bound, with a tenth to spare for the pitch).
            let aside = p.aside.mul(F4::splat(0.9)).div(far);
            let lag = aside
                .max(zero)
                .min(F4::splat(1.0))
                .mul(F4::splat(self.turn_lag));
            let per = F4::splat(1.0).sub(share).div(far);
            let scaled = |v: F4| v.max(zero).mul(per);
            let inside = scaled(p.inside_by_sides)
                .add(lag)
                .min(scaled(p.inside_by_ends));
            let behind_sides = zero.lt(p.outside_by_sides);
            let (inside, sides_out, ends_out) = (
                inside.to_array(),
                scaled(p.outside_by_sides).add(lag).to_array(),
                scaled(p.outside_by_ends).to_array(),
            );
            let lagged = F4::new(std::array::from_fn(|i| {
                if p.outside >> i & 1 == 0 {
                    inside[i]
                } else {
                    // In view once no plane has it wholly behind: past a side plane, the
                    // band too.
                    let sides = if behind_sides >> i & 1 != 0 {
                        sides_out[i]
                    } else {
                        0.0
                    };
                    sides.max(ends_out[i])
                }
            }));
            lagged.max(turned)
        } else {
            turned
        };
        let (moved, moved_shown, turned) =
            (moved.to_array(), moved_shown.to_array(), turned.to_array());
        Lanes {
            prio: p.prio.to_array(),
            wanted: shown & (p.under | above),
            under: shown & p.under,
            dropped: shown & !p.under & !above,
            slack: std::array::from_fn(|i| {
                if live >> i & 1 == 0 {
                    // Exact: nothing about it will ever change.
                    (f32::INFINITY, f32::INFINITY)
                } else if p.under >> i & 1 != 0 {
                    (0.0, 0.0)
                } else if shown >> i & 1 != 0 {
                    (moved_shown[i], turned[i])
                } else {
                    (moved[i], turned[i])
                }
            }),
        }
    }

    /// Priorities of up to four diamonds given by position.
    pub(super) fn evaluate_at(&self, f: &Frame, pos: &[u32]) -> Lanes {
        let fixed: [Fixed; 4] = std::array::from_fn(|i| fixed(f, pos[i.min(pos.len() - 1)]));
        self.evaluate(f, [&fixed[0], &fixed[1], &fixed[2], &fixed[3]], pos.len())
    }
}

/// How far the eye may move before a priority at distance `clear` (to its prism, world
/// units) could grow by more than a relative `r` under fog of density `rho` (0: none):
/// `2·r·d / (a + sqrt(a² − 4·(1 + r)·ρ·r·d))`, `a = (1 + r)(1 + ρ·d)`, `d = clear` (see
/// the module docs). Without fog exactly `clear · r / (1 + r)`, bit for bit; 0 or less
/// when `clear` is not positive.
#[inline(always)]
pub(super) fn by_prio(clear: F4, r: F4, rho: F4) -> F4 {
    let one = F4::splat(1.0);
    let r1 = one.add(r);
    let a = r1.mul(one.add(rho.mul(clear)));
    let c = F4::splat(4.0).mul(r1).mul(rho).mul(r.mul(clear));
    let root = a.mul(a).sub(c).max(F4::splat(0.0)).sqrt();
    clear.mul(r).mul(F4::splat(2.0)).div(a.add(root))
}

/// What a diamond's priority needs that does not depend on the camera.
pub(super) fn fixed(f: &Frame, pos: u32) -> Fixed {
    let (s, side) = (f.size, f.side);
    let (x, z) = unpack(pos);
    let (m, shape) = shape_of(x, z);
    let h = 1u32 << m;
    let at = |x: u32, z: u32| f32::from(f.h(z * side + x));
    let corners: [f32; 4] = match shape {
        Shape::Square => [
            at(x + h, z - h),
            at(x - h, z - h),
            at(x - h, z + h),
            at(x + h, z + h),
        ],
        // Hypotenuse ends first, then the apices (one may be off the map: an end
        // stands in for it).
        Shape::Rotated { horizontal: true } => {
            let e0 = at(x - h, z);
            [
                e0,
                at(x + h, z),
                if z >= h { at(x, z - h) } else { e0 },
                if z + h <= s { at(x, z + h) } else { e0 },
            ]
        }
        Shape::Rotated { horizontal: false } => {
            let e0 = at(x, z - h);
            [
                e0,
                at(x, z + h),
                if x >= h { at(x - h, z) } else { e0 },
                if x + h <= s { at(x + h, z) } else { e0 },
            ]
        }
    };
    let e = match shape {
        // `variance::finest`, as the from-scratch evaluation computes it.
        Shape::Rotated { .. } if m == 0 => (at(x, z) - 0.5 * (corners[0] + corners[1])).abs(),
        _ => f.stored(x, z, m, shape),
    };
    let square = shape == Shape::Square;
    Fixed {
        x: x as f32,
        z: z as f32,
        e,
        lo: corners.into_iter().fold(f32::INFINITY, f32::min),
        hi: corners.into_iter().fold(0.0, f32::max),
        h: h as f32,
        k: if square {
            std::f32::consts::SQRT_2
        } else {
            1.0
        },
        kind: (u16::from(square) << 4) | m as u16,
    }
}
