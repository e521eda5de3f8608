//! Four `f32` lanes: a split's (up to) four children are evaluated together, one per lane.
//!
//! On x86-64 the lanes are an SSE register (SSE2 is part of the baseline, and the
//! x86-64-v3 build encodes the same operations with VEX); elsewhere they are an array.
//! Every operation is the IEEE operation of each lane, so both give bit-identical results,
//! and equal to the same arithmetic on scalars; [`F4::exp2_neg`] (the fog's transmission)
//! is built from such operations too, not taken from the platform's library.
//!
//! **The transmission is short in latency** (issue 41). It sits between a batch's
//! distances and its queue entries, and the split loop waits on that chain: the first
//! version (`t = x·log2 e`, rounding by truncation and back, a Taylor polynomial by
//! Horner, about 100 cycles) made the from-scratch cut with fog slower than without
//! although it ran *fewer* instructions (callgrind, 40 frames of the fly-over: 1.315 G
//! against 1.321 G, with fewer cache misses and mispredicted branches: it evaluates 57,445
//! diamonds a frame to 68,897, the fog's cut being nearer the eye). Now `ρ·log2 e` is one
//! constant of the frame, `t` is rounded by adding and taking off `1.5·2^23` (its bits
//! give `2^−n` off the chain), and a minimax polynomial is evaluated by Estrin's scheme:
//! about 45 cycles, 1.294 G instructions, `exp(−x)` within 3.9e-6 over the test's range
//! (most of it `t`'s rounding; the bound stays 1e-5). `target/release/roam-server bench DIR --budget 65536
//! --json`, `--fog-priority on` and `off` in turn, five runs each, medians of
//! `tessellate_ns_per_triangle_median` (ns a triangle, on / off, ratio), on a shared,
//! busy two-core machine:
//!
//! | map | before | after |
//! |---|---|---|
//! | `data/kossou` (fog 5e-5) | 36.4 / 34.2, 1.07 | 33.9 / 34.8, 0.97 |
//! | steep (fog 5e-4) | 35.8 / 34.2, 1.05 | 31.3 / 34.9, 0.90 |
//!
//! Steep: `roam-server import data/srtm/n07_w006_3arc_v2.tif /tmp/steep --h-scale 10
//! --v-scale 5 --crop 0,0,1025` (the importer gives it fog 5e-4). Without fog nothing
//! changed (the same cuts, bit for bit); with fog the priorities move by the
//! approximations' difference, a few parts in a million.

#[cfg(target_arch = "x86_64")]
mod imp {
    use std::arch::x86_64::*;

    #[derive(Clone, Copy)]
    pub(crate) struct F4(__m128);

    impl F4 {
        #[inline(always)]
        pub(crate) fn new(v: [f32; 4]) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_setr_ps(v[0], v[1], v[2], v[3])) }
        }
        #[inline(always)]
        pub(crate) fn splat(v: f32) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_set1_ps(v)) }
        }
        /// Lanes from integers below 2^24 (exact).
        #[inline(always)]
        pub(crate) fn from_u32(v: [u32; 4]) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe {
                F4(_mm_cvtepi32_ps(_mm_setr_epi32(
                    v[0] as i32,
                    v[1] as i32,
                    v[2] as i32,
                    v[3] as i32,
                )))
            }
        }
        #[inline(always)]
        pub(crate) fn to_array(self) -> [f32; 4] {
            let mut out = [0f32; 4];
            // SAFETY: `out` has room for four unaligned floats.
            unsafe { _mm_storeu_ps(out.as_mut_ptr(), self.0) };
            out
        }
        #[inline(always)]
        pub(crate) fn add(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_add_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub(crate) fn sub(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_sub_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub(crate) fn mul(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_mul_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub(crate) fn div(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_div_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub(crate) fn sqrt(self) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_sqrt_ps(self.0)) }
        }
        /// Lane-wise minimum (operands are never NaN).
        #[inline(always)]
        pub(crate) fn min(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_min_ps(self.0, o.0)) }
        }
        /// Lane-wise maximum; a NaN in `self` gives `o`, as `f32::max` does.
        #[inline(always)]
        pub(crate) fn max(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_max_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub(crate) fn abs(self) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_andnot_ps(_mm_set1_ps(-0.0), self.0)) }
        }
        /// Bit `i` set where lane `i` of `self < o`.
        #[inline(always)]
        pub(crate) fn lt(self, o: F4) -> u32 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { _mm_movemask_ps(_mm_cmplt_ps(self.0, o.0)) as u32 }
        }
        /// Bit `i` set where lane `i` of `self <= o`.
        #[inline(always)]
        pub(crate) fn le(self, o: F4) -> u32 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { _mm_movemask_ps(_mm_cmple_ps(self.0, o.0)) as u32 }
        }
        /// `2^−n` of each lane [`SHIFT`] `+ n`, `n` a whole number in 0 ..= 126 (held in
        /// the float's low bits): a normal float built from its exponent bits.
        #[inline(always)]
        pub(crate) fn exp2_neg_shifted(self) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe {
                let bits = _mm_castps_si128(self.0);
                let e = _mm_sub_epi32(_mm_set1_epi32(super::SHIFT_BITS + 127), bits);
                F4(_mm_castsi128_ps(_mm_slli_epi32::<23>(e)))
            }
        }
        /// `self` where `a < b`, else 0, lane by lane.
        #[inline(always)]
        pub(crate) fn where_lt(self, a: F4, b: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_and_ps(self.0, _mm_cmplt_ps(a.0, b.0))) }
        }
        /// `self` where bit `i` of `mask` is set, else 0.
        #[inline(always)]
        pub(crate) fn keep(self, mask: u32) -> F4 {
            let m = |b: u32| if mask >> b & 1 != 0 { -1 } else { 0 };
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe {
                let m = _mm_castsi128_ps(_mm_setr_epi32(m(0), m(1), m(2), m(3)));
                F4(_mm_and_ps(self.0, m))
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod imp {
    #[derive(Clone, Copy)]
    pub struct F4([f32; 4]);

    impl F4 {
        #[inline(always)]
        fn map(self, o: F4, f: impl Fn(f32, f32) -> f32) -> F4 {
            F4(std::array::from_fn(|i| f(self.0[i], o.0[i])))
        }
        #[inline(always)]
        fn mask(self, o: F4, f: impl Fn(f32, f32) -> bool) -> u32 {
            (0..4).map(|i| u32::from(f(self.0[i], o.0[i])) << i).sum()
        }
        #[inline(always)]
        pub fn new(v: [f32; 4]) -> F4 {
            F4(v)
        }
        #[inline(always)]
        pub fn splat(v: f32) -> F4 {
            F4([v; 4])
        }
        #[inline(always)]
        pub fn from_u32(v: [u32; 4]) -> F4 {
            F4(v.map(|x| x as f32))
        }
        #[inline(always)]
        pub fn to_array(self) -> [f32; 4] {
            self.0
        }
        #[inline(always)]
        pub fn add(self, o: F4) -> F4 {
            self.map(o, |a, b| a + b)
        }
        #[inline(always)]
        pub fn sub(self, o: F4) -> F4 {
            self.map(o, |a, b| a - b)
        }
        #[inline(always)]
        pub fn mul(self, o: F4) -> F4 {
            self.map(o, |a, b| a * b)
        }
        #[inline(always)]
        pub fn div(self, o: F4) -> F4 {
            self.map(o, |a, b| a / b)
        }
        #[inline(always)]
        pub fn sqrt(self) -> F4 {
            F4(self.0.map(f32::sqrt))
        }
        #[inline(always)]
        pub fn min(self, o: F4) -> F4 {
            self.map(o, |a, b| if a < b { a } else { b })
        }
        #[inline(always)]
        pub fn max(self, o: F4) -> F4 {
            self.map(o, |a, b| if a > b { a } else { b })
        }
        #[inline(always)]
        pub fn abs(self) -> F4 {
            F4(self.0.map(f32::abs))
        }
        #[inline(always)]
        pub fn lt(self, o: F4) -> u32 {
            self.mask(o, |a, b| a < b)
        }
        #[inline(always)]
        pub fn le(self, o: F4) -> u32 {
            self.mask(o, |a, b| a <= b)
        }
        #[inline(always)]
        pub fn exp2_neg_shifted(self) -> F4 {
            let e = |v: f32| (super::SHIFT_BITS as u32 + 127).wrapping_sub(v.to_bits()) << 23;
            F4(self.0.map(|v| f32::from_bits(e(v))))
        }
        #[inline(always)]
        pub fn where_lt(self, a: F4, b: F4) -> F4 {
            F4(std::array::from_fn(|i| {
                if a.0[i] < b.0[i] { self.0[i] } else { 0.0 }
            }))
        }
        #[inline(always)]
        pub fn keep(self, mask: u32) -> F4 {
            F4(std::array::from_fn(|i| {
                if mask >> i & 1 != 0 { self.0[i] } else { 0.0 }
            }))
        }
    }
}

pub(super) use imp::F4;

impl F4 {
    /// The largest lane.
    pub(super) fn max_lane(self) -> f32 {
        self.to_array().into_iter().fold(0f32, f32::max)
    }

    /// `2^−t` of each lane `t >= 0` (0 for NaN and from 126 on, where it is below the
    /// smallest normal `f32`): the fog's transmission `exp(−ρ·d)`, with `t = d · ρ·log2 e`.
    /// From the lanes' IEEE operations alone, so that every build and machine gives the
    /// same bits (a library `expf` may differ between machines, and its FMA variant from
    /// the one without), four lanes at once. Relative error below 3e-7 (the polynomial's
    /// own 1e-7, and its rounding); exactly 1 at 0.
    ///
    /// Short in latency, since a batch's queue entries wait on it (issue 41): `t` rounded
    /// to the nearest whole `n` by adding and taking off [`SHIFT`] (whose low bits then
    /// hold `n`, turned into `2^−n` by integer operations beside the polynomial), and
    /// `2^−f`, `f = t − n` (exact) in −1/2 ..= 1/2, by a degree-5 minimax polynomial
    /// evaluated by Estrin's scheme (three levels of multiply and add, not five).
    #[inline(always)]
    pub(super) fn exp2_neg(self) -> F4 {
        let c = F4::splat;
        let r = self.add(c(SHIFT));
        let f = self.sub(r.sub(c(SHIFT)));
        let (f2, k) = (f.mul(f), EXP2_NEG);
        let f4 = f2.mul(f2);
        let lo = c(k[0]).add(c(k[1]).mul(f));
        let mid = c(k[2]).add(c(k[3]).mul(f));
        let hi = c(k[4]).add(c(k[5]).mul(f));
        let p = lo.add(f2.mul(mid)).add(f4.mul(hi));
        p.mul(r.exp2_neg_shifted()).where_lt(self, c(126.0))
    }
}

/// `1.5 · 2^23`: added to a float in 0 ..= 2^22, leaves it rounded to the nearest whole
/// number `n` (ties to even), held in the low bits: the sum's bits are [`SHIFT_BITS`] `+ n`.
const SHIFT: f32 = 12_582_912.0;
const SHIFT_BITS: i32 = 0x4B40_0000;

/// `2^−f ≈ Σ k[i]·f^i` for `|f| <= 1/2`, relative error 9.2e-8 (minimax fitted with
/// `k[0] = 1`, so that `2^−0` is exactly 1). `k[1]` is near `−ln 2` (Taylor's), not it.
#[allow(clippy::approx_constant)]
const EXP2_NEG: [f32; 6] = [
    1.0,
    -0.693_147,
    0.240_222_42,
    -0.055_507_336,
    0.009_671_513,
    -0.001_326_472_8,
];

#[cfg(test)]
mod tests {
    use super::F4;

    const A: [f32; 4] = [1.5, -0.0, 3.0e-3, 65535.0];
    const B: [f32; 4] = [-2.25, 7.0, 3.0e-3, 0.1];

    /// Each lane operation equals the scalar operation on every lane.
    fn check(op: impl Fn(F4, F4) -> F4, scalar: impl Fn(f32, f32) -> f32) {
        let got = op(F4::new(A), F4::new(B)).to_array();
        for i in 0..4 {
            assert_eq!(got[i].to_bits(), scalar(A[i], B[i]).to_bits(), "lane {i}");
        }
    }

    #[test]
    fn lanes_are_scalar_arithmetic() {
        check(F4::add, |a, b| a + b);
        check(F4::sub, |a, b| a - b);
        check(F4::mul, |a, b| a * b);
        check(F4::div, |a, b| a / b);
        check(F4::min, f32::min);
        check(F4::max, f32::max);
        check(|a, _| a.abs(), |a, _| a.abs());
        check(|a, _| a.abs().sqrt(), |a, _| a.abs().sqrt());
        check(|a, _| a.keep(0b1111), |a, _| a);
        let masked = F4::new(A).keep(0b0101).to_array();
        assert_eq!(
            masked.map(f32::to_bits),
            [1.5f32, 0.0, 3.0e-3, 0.0].map(f32::to_bits)
        );
    }

    #[test]
    fn comparisons_give_lane_bits() {
        let (a, b) = (F4::new(A), F4::new(B));
        assert_eq!(a.lt(b), 0b0010);
        assert_eq!(a.le(b), 0b0110);
        assert_eq!(
            F4::from_u32([0, 1, 1 << 23, 1025]).to_array(),
            [0.0, 1.0, 8388608.0, 1025.0]
        );
    }

    /// `exp(−x)`, as `2^−(x · log2 e)`, within 1e-5 of the exact value over the range fog
    /// gives it, exactly 1 at 0, 0 past the normal floats, each lane on its own.
    #[test]
    fn exp2_neg_is_close_and_exact_at_0() {
        let exp2_neg = |t: f32| F4::splat(t).exp2_neg().to_array()[0];
        let exp_neg = |x: f32| exp2_neg(x * std::f32::consts::LOG2_E);
        assert_eq!(exp_neg(0.0).to_bits(), 1f32.to_bits());
        assert_eq!(exp_neg(-0.0).to_bits(), 1f32.to_bits());
        assert_eq!(exp_neg(88.0), 0.0);
        assert_eq!(exp2_neg(126.0), 0.0);
        assert_eq!(exp_neg(f32::INFINITY), 0.0);
        assert_eq!(exp_neg(f32::NAN), 0.0);
        let mut worst = 0f64;
        for i in 0..200_000 {
            let x = i as f32 * 4.3e-4; // 0 .. 86
            let got = f64::from(exp_neg(x));
            let want = (-f64::from(x)).exp();
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 1e-5, "relative error {worst}");
        // The approximation's own error, `t` exact: whole numbers are exact.
        let mut worst = 0f64;
        for i in 0..=1_000_000 {
            let t = i as f32 * 1.25e-4; // 0 .. 125
            let got = f64::from(exp2_neg(t));
            let want = (-f64::from(t)).exp2();
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 3e-7, "relative error {worst}");
        for n in 0..126 {
            assert_eq!(exp2_neg(n as f32), 2f32.powi(-n), "2^-{n}");
        }
        let v = [0.0, 0.25, 130.0, 57.7];
        let lanes = F4::new(v).exp2_neg().to_array();
        assert_eq!(lanes.map(f32::to_bits), v.map(exp2_neg).map(f32::to_bits));
        assert_eq!(
            F4::new([1.0, 2.5, 3.0, 4.0])
                .where_lt(
                    F4::new([0.0, 1.0, 2.0, 3.0]),
                    F4::new([1.0, 1.0, f32::NAN, 9.0])
                )
                .to_array(),
            [1.0, 0.0, 0.0, 4.0]
        );
    }

    #[test]
    fn max_ignores_nan_in_the_first_operand() {
        let got = F4::splat(f32::NAN).max(F4::splat(2.0)).to_array();
        assert_eq!(got, [2.0; 4]);
        assert_eq!(F4::new([0.5, 3.0, 1.0, 2.0]).max_lane(), 3.0);
    }
}
