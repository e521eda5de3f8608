//! Four `f32` lanes: a split's (up to) four children are evaluated together, one per lane.
//!
//! On x86-64 the lanes are an SSE register (SSE2 is part of the baseline, and the
//! x86-64-v3 build encodes the same operations with VEX); elsewhere they are an array.
//! Every operation is the IEEE operation of each lane, so both give bit-identical results,
//! and equal to the same arithmetic on scalars; [`F4::exp_neg`] (the fog's transmission)
//! is built from such operations too, not taken from the platform's library.

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
        /// Each lane rounded towards zero (lanes within ±2^31).
        #[inline(always)]
        pub(crate) fn trunc(self) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_cvtepi32_ps(_mm_cvttps_epi32(self.0))) }
        }
        /// `2^−n` of each lane `n`, a whole number in 0 ..= 126 (a normal float built from
        /// its exponent bits).
        #[inline(always)]
        pub(crate) fn exp2_neg_whole(self) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe {
                let n = _mm_cvttps_epi32(self.0);
                let bits = _mm_slli_epi32::<23>(_mm_sub_epi32(_mm_set1_epi32(127), n));
                F4(_mm_castsi128_ps(bits))
            }
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
        pub fn trunc(self) -> F4 {
            F4(self.0.map(|v| v as i32 as f32))
        }
        #[inline(always)]
        pub fn exp2_neg_whole(self) -> F4 {
            F4(self.0.map(|n| f32::from_bits((127 - n as u32) << 23)))
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

    /// `exp(−x)` of each lane `x >= 0` (0 for NaN and past 87, where it is below the
    /// smallest normal `f32`): the fog's transmission. From the lanes' IEEE operations
    /// alone, so that every build and machine gives the same bits (a library `expf` may
    /// differ between machines, and its FMA variant from the one without), four lanes at
    /// once. Relative error below 1e-5 (the rounding of `x · log2 e`; the polynomial's
    /// own is 2e-7); exactly 1 at 0.
    #[inline(always)]
    pub(super) fn exp_neg(self) -> F4 {
        let c = F4::splat;
        // exp(−x) = 2^−t = 2^−n · 2^−f, with t = x · log2 e, n = round(t), |f| <= 1/2.
        let t = self.mul(c(std::f32::consts::LOG2_E));
        let live = t.lt(c(126.0)); // not NaN, and 2^−t normal
        let t = t.max(c(0.0)).min(c(126.0));
        let n = t.add(c(0.5)).trunc(); // t >= 0: truncation rounds down
        let f = t.sub(n);
        // 2^−f = e^u, u = −f · ln 2 in [−0.35, 0.35]: Taylor to u^6 (error u^7 / 7! < 2e-7).
        let u = c(0.0).sub(f.mul(c(std::f32::consts::LN_2)));
        let p = [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0]
            .into_iter()
            .fold(c(1.0 / 720.0), |p, k| p.mul(u).add(c(k)));
        p.mul(n.exp2_neg_whole()).keep(live)
    }
}

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

    /// `exp(−x)` within 1e-5 of the exact value over the range fog gives it, exactly 1 at
    /// 0, 0 past the normal floats, each lane on its own.
    #[test]
    fn exp_neg_is_close_and_exact_at_0() {
        let exp_neg = |x: f32| F4::splat(x).exp_neg().to_array()[0];
        assert_eq!(exp_neg(0.0).to_bits(), 1f32.to_bits());
        assert_eq!(exp_neg(-0.0).to_bits(), 1f32.to_bits());
        assert_eq!(exp_neg(88.0), 0.0);
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
        let v = [0.0, 0.25, 90.0, 40.0];
        let lanes = F4::new(v).exp_neg().to_array();
        assert_eq!(lanes.map(f32::to_bits), v.map(exp_neg).map(f32::to_bits));
        assert_eq!(
            F4::new([0.0, 1.0, 126.0, 3.0]).exp2_neg_whole().to_array(),
            [1.0, 0.5, 2f32.powi(-126), 0.125]
        );
        assert_eq!(
            F4::new([2.9, 0.5, 7.0, 0.0]).trunc().to_array(),
            [2.0, 0.0, 7.0, 0.0]
        );
    }

    #[test]
    fn max_ignores_nan_in_the_first_operand() {
        let got = F4::splat(f32::NAN).max(F4::splat(2.0)).to_array();
        assert_eq!(got, [2.0; 4]);
        assert_eq!(F4::new([0.5, 3.0, 1.0, 2.0]).max_lane(), 3.0);
    }
}
