//! Four `f32` lanes: a split's (up to) four children are evaluated together, one per lane.
//!
//! On x86-64 the lanes are an SSE register (SSE2 is part of the baseline, and the
//! x86-64-v3 build encodes the same operations with VEX); elsewhere they are an array.
//! Every operation is the IEEE operation of each lane, so both give bit-identical results,
//! and equal to the same arithmetic on scalars.

#[cfg(target_arch = "x86_64")]
mod imp {
    use std::arch::x86_64::*;

    #[derive(Clone, Copy)]
    pub struct F4(__m128);

    impl F4 {
        #[inline(always)]
        pub fn new(v: [f32; 4]) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_setr_ps(v[0], v[1], v[2], v[3])) }
        }
        #[inline(always)]
        pub fn splat(v: f32) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_set1_ps(v)) }
        }
        /// Lanes from integers below 2^24 (exact).
        #[inline(always)]
        pub fn from_u32(v: [u32; 4]) -> F4 {
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
        pub fn to_array(self) -> [f32; 4] {
            let mut out = [0f32; 4];
            // SAFETY: `out` has room for four unaligned floats.
            unsafe { _mm_storeu_ps(out.as_mut_ptr(), self.0) };
            out
        }
        #[inline(always)]
        pub fn add(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_add_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn sub(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_sub_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn mul(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_mul_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn div(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_div_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn sqrt(self) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_sqrt_ps(self.0)) }
        }
        /// Lane-wise minimum (operands are never NaN).
        #[inline(always)]
        pub fn min(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_min_ps(self.0, o.0)) }
        }
        /// Lane-wise maximum; a NaN in `self` gives `o`, as `f32::max` does.
        #[inline(always)]
        pub fn max(self, o: F4) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_max_ps(self.0, o.0)) }
        }
        #[inline(always)]
        pub fn abs(self) -> F4 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { F4(_mm_andnot_ps(_mm_set1_ps(-0.0), self.0)) }
        }
        /// Bit `i` set where lane `i` of `self < o`.
        #[inline(always)]
        pub fn lt(self, o: F4) -> u32 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { _mm_movemask_ps(_mm_cmplt_ps(self.0, o.0)) as u32 }
        }
        /// Bit `i` set where lane `i` of `self <= o`.
        #[inline(always)]
        pub fn le(self, o: F4) -> u32 {
            // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
            unsafe { _mm_movemask_ps(_mm_cmple_ps(self.0, o.0)) as u32 }
        }
        /// `self` where bit `i` of `mask` is set, else 0.
        #[inline(always)]
        pub fn keep(self, mask: u32) -> F4 {
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
    pub fn max_lane(self) -> f32 {
        self.to_array().into_iter().fold(0f32, f32::max)
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

    #[test]
    fn max_ignores_nan_in_the_first_operand() {
        let got = F4::splat(f32::NAN).max(F4::splat(2.0)).to_array();
        assert_eq!(got, [2.0; 4]);
        assert_eq!(F4::new([0.5, 3.0, 1.0, 2.0]).max_lane(), 3.0);
    }
}
