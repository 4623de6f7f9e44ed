//! Sixteen pixels as one value: the vector type the row functions of the
//! rasterizer are written in ([`super::rasterize`](mod@super::rasterize),
//! [`super::rasterize_vjp`](mod@super::rasterize_vjp)),
//! and sixteen Gaussians as one value in the backward's per-Gaussian chain
//! rule (the register types implement [`crate::math::pack::Arith`]).
//!
//! Three implementations of [`Lanes`] with the same bits: [`Scalar`] (sixteen
//! scalars, any [`Real`], the portable path and the only one for f64),
//! `Avx512` (one 16-lane f32 register) and `Avx2` (two 8-lane f32 halves).
//! Every operation is lane-wise IEEE arithmetic (add, subtract, multiply,
//! divide, each correctly rounded; no fused multiply-add), an ordered
//! comparison, a select or a bit operation, so a lane computes exactly what
//! the scalar code does. The exponential ([`Lanes::exp_above`], with a lower
//! bound) is the crate's f32 [`fastmath::exp_f32`] operation by operation,
//! its lower clamp at `max(bound, −104)` (libm's `exp` per lane in f64).

use super::rasterize::LANES;
use crate::kernels::fastmath;
use crate::math::pack::Pack;
use crate::math::Real;
use std::ops::{Add, Div, Mul, Neg, Sub};

/// Sixteen lanes of `Self::T` with masks `Self::M`.
pub(crate) trait Lanes:
    Copy
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
{
    type T: Real;
    type M: Copy;
    fn splat(v: Self::T) -> Self;
    fn load(a: &[Self::T; LANES]) -> Self;
    fn store(self, a: &mut [Self::T; LANES]);
    /// Ordered `self < o` per lane (false for NaN).
    fn lt(self, o: Self) -> Self::M;
    /// Ordered `self > o` per lane (false for NaN).
    fn gt(self, o: Self) -> Self::M;
    /// `m ? a : b` per lane.
    fn select(m: Self::M, a: Self, b: Self) -> Self;
    fn and(a: Self::M, b: Self::M) -> Self::M;
    /// `a && !b`.
    fn andnot(a: Self::M, b: Self::M) -> Self::M;
    /// Lane `l` is bit `l`.
    fn bits(m: Self::M) -> u16;
    fn from_bits(b: u16) -> Self::M;
    /// `e^x` per lane ([`fastmath::exp`]), where a lane below `lo`
    /// (ordered) takes `e^lo` instead; NaN stays NaN, and a NaN bound acts as
    /// none. Lanes at or above `lo` give exactly `e^x`'s bits. The bound
    /// replaces the exp's own lower clamp (−104), so it costs one `max` of
    /// the bound itself, off the path from `x`. The rasterizer's row walks
    /// pass the splat's `power_min`, so that lanes that cannot blend do not
    /// compute subnormal results (unless `power_min` itself is below about
    /// −87, which takes an opacity above about 3e35).
    fn exp_above(self, lo: Self) -> Self;
    /// `Real::min(a, self)` for a splat `a`: `self < a ? self : a`.
    #[inline(always)]
    fn min_of(self, a: Self) -> Self {
        Self::select(self.lt(a), self, a)
    }
    /// The fixed pairwise sum: lane `l` with `l + 8`, then `+ 4`, `+ 2`, `+ 1`.
    #[inline(always)]
    fn tree_sum(self) -> Self::T {
        let mut v = [Self::T::ZERO; LANES];
        self.store(&mut v);
        let mut a = [Self::T::ZERO; 8];
        for l in 0..8 {
            a[l] = v[l] + v[l + 8];
        }
        let mut b = [Self::T::ZERO; 4];
        for l in 0..4 {
            b[l] = a[l] + a[l + 4];
        }
        (b[0] + b[2]) + (b[1] + b[3])
    }
    /// [`tree_sum`](Self::tree_sum) of each of 16 values at once (element
    /// `k` is the sum of `v[k]`), with the same bits; the vector types
    /// share the shuffles of the four levels among the values.
    #[inline(always)]
    fn tree_sums(v: [Self; 16]) -> [Self::T; 16] {
        let mut out = [Self::T::ZERO; 16];
        for (o, x) in out.iter_mut().zip(v) {
            *o = x.tree_sum();
        }
        out
    }
}

/// The portable implementation: sixteen scalars, each lane the scalar
/// operations of [`Pack`].
pub(crate) type Scalar<T> = Pack<T, LANES>;

impl<T: Real> Lanes for Scalar<T> {
    type T = T;
    type M = u16;
    #[inline(always)]
    fn splat(v: T) -> Self {
        Pack([v; LANES])
    }
    #[inline(always)]
    fn load(a: &[T; LANES]) -> Self {
        Pack(*a)
    }
    #[inline(always)]
    fn store(self, a: &mut [T; LANES]) {
        *a = self.0;
    }
    #[inline(always)]
    fn lt(self, o: Self) -> u16 {
        let mut m = 0;
        for l in 0..LANES {
            m |= ((self.0[l] < o.0[l]) as u16) << l;
        }
        m
    }
    #[inline(always)]
    fn gt(self, o: Self) -> u16 {
        let mut m = 0;
        for l in 0..LANES {
            m |= ((self.0[l] > o.0[l]) as u16) << l;
        }
        m
    }
    #[inline(always)]
    fn select(m: u16, a: Self, b: Self) -> Self {
        Pack(std::array::from_fn(|l| {
            if m >> l & 1 != 0 {
                a.0[l]
            } else {
                b.0[l]
            }
        }))
    }
    #[inline(always)]
    fn and(a: u16, b: u16) -> u16 {
        a & b
    }
    #[inline(always)]
    fn andnot(a: u16, b: u16) -> u16 {
        a & !b
    }
    #[inline(always)]
    fn bits(m: u16) -> u16 {
        m
    }
    #[inline(always)]
    fn from_bits(b: u16) -> u16 {
        b
    }
    #[inline(always)]
    fn exp_above(self, lo: Self) -> Self {
        Pack(std::array::from_fn(|l| {
            let (x, lo) = (self.0[l], lo.0[l]);
            fastmath::exp(if x < lo { lo } else { x })
        }))
    }
}

/// The constants of [`fastmath::exp_f32`], shared by the vector versions.
#[cfg(target_arch = "x86_64")]
mod expc {
    #![allow(clippy::excessive_precision)]
    pub const LOG2E: f32 = std::f32::consts::LOG2_E;
    pub const LN2_HI: f32 = 0.693_359_4;
    pub const LN2_LO: f32 = -2.121_944_4e-4;
    pub const ROUND: f32 = 12_582_912.0;
    pub const P: [f32; 6] = [
        1.987_569_1e-4,
        1.398_199_9e-3,
        8.333_452e-3,
        4.166_579_6e-2,
        1.666_666_5e-1,
        5.000_000_1e-1,
    ];
}

#[cfg(target_arch = "x86_64")]
pub(crate) use x86::{Avx2, Avx512};

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{expc, Lanes, LANES};
    use crate::math::pack::Arith;
    use std::arch::x86_64::*;
    use std::ops::{Add, AddAssign, Div, Mul, Neg, Sub};

    /// One AVX-512 register of 16 f32 lanes. Only built inside functions
    /// compiled with `avx512f` on a CPU that has it.
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Avx512(__m512);

    /// Two AVX2 registers of 8 f32 lanes (lanes 0–7, 8–15). Only built
    /// inside functions compiled with `avx2` on a CPU that has it.
    #[derive(Clone, Copy, Debug)]
    pub(crate) struct Avx2([__m256; 2]);

    // SAFETY (every `unsafe` block below): these types are only operated on
    // inside functions compiled with their target feature, entered after
    // run-time detection (`fastmath::isa`); their `Arith` constants are plain
    // bits, made without an instruction; loads and stores are of 16-element
    // arrays.

    macro_rules! avx512_op {
        ($tr:ident, $f:ident, $intr:ident) => {
            impl $tr for Avx512 {
                type Output = Self;
                #[inline(always)]
                fn $f(self, o: Self) -> Self {
                    // SAFETY: AVX-512F is present (this type only lives in functions
                    // compiled with it, reached after run-time detection).
                    Avx512(unsafe { $intr(self.0, o.0) })
                }
            }
        };
    }
    avx512_op!(Add, add, _mm512_add_ps);
    avx512_op!(Sub, sub, _mm512_sub_ps);
    avx512_op!(Mul, mul, _mm512_mul_ps);
    avx512_op!(Div, div, _mm512_div_ps);
    impl Neg for Avx512 {
        type Output = Self;
        #[inline(always)]
        fn neg(self) -> Self {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                Avx512(_mm512_castsi512_ps(_mm512_xor_si512(
                    _mm512_castps_si512(self.0),
                    _mm512_set1_epi32(i32::MIN),
                )))
            }
        }
    }

    impl Lanes for Avx512 {
        type T = f32;
        type M = u16;
        #[inline(always)]
        fn splat(v: f32) -> Self {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            Avx512(unsafe { _mm512_set1_ps(v) })
        }
        #[inline(always)]
        fn load(a: &[f32; LANES]) -> Self {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection); the pointer
            // addresses a 16-element array.
            Avx512(unsafe { _mm512_loadu_ps(a.as_ptr()) })
        }
        #[inline(always)]
        fn store(self, a: &mut [f32; LANES]) {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection); the pointer
            // addresses a 16-element array.
            unsafe { _mm512_storeu_ps(a.as_mut_ptr(), self.0) }
        }
        #[inline(always)]
        fn lt(self, o: Self) -> u16 {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { _mm512_cmp_ps_mask::<_CMP_LT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn gt(self, o: Self) -> u16 {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { _mm512_cmp_ps_mask::<_CMP_GT_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn select(m: u16, a: Self, b: Self) -> Self {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            Avx512(unsafe { _mm512_mask_blend_ps(m, b.0, a.0) })
        }
        #[inline(always)]
        fn and(a: u16, b: u16) -> u16 {
            a & b
        }
        #[inline(always)]
        fn andnot(a: u16, b: u16) -> u16 {
            a & !b
        }
        #[inline(always)]
        fn bits(m: u16) -> u16 {
            m
        }
        #[inline(always)]
        fn from_bits(b: u16) -> u16 {
            b
        }
        #[inline(always)]
        fn tree_sum(self) -> f32 {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                let lo = _mm512_castps512_ps256(self.0);
                let hi = _mm256_castpd_ps(_mm512_extractf64x4_pd::<1>(_mm512_castps_pd(self.0)));
                sum8(_mm256_add_ps(lo, hi))
            }
        }
        #[inline(always)]
        fn tree_sums(v: [Self; 16]) -> [f32; 16] {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                // Level 1, a[l] = v[l] + v[l + 8], two values per register:
                // 128-bit quarters [a0..3, a4..7] of v[2k], then of v[2k + 1].
                let mut s1 = [_mm512_setzero_ps(); 8];
                for (k, s) in s1.iter_mut().enumerate() {
                    let (a, b) = (v[2 * k].0, v[2 * k + 1].0);
                    *s = _mm512_add_ps(
                        _mm512_shuffle_f32x4::<0x44>(a, b),
                        _mm512_shuffle_f32x4::<0xEE>(a, b),
                    );
                }
                // Level 2, b[l] = a[l] + a[l + 4]: quarter i of s2[k] is
                // value 4k + i's b.
                let mut s2 = [_mm512_setzero_ps(); 4];
                for (k, s) in s2.iter_mut().enumerate() {
                    let (p, q) = (s1[2 * k], s1[2 * k + 1]);
                    *s = _mm512_add_ps(
                        _mm512_shuffle_f32x4::<0x88>(p, q),
                        _mm512_shuffle_f32x4::<0xDD>(p, q),
                    );
                }
                // Level 3, c[l] = b[l] + b[l + 2]: quarter i of s3[k] is
                // [c0, c1] of value 8k + i, then of value 8k + 4 + i.
                let mut s3 = [_mm512_setzero_ps(); 2];
                for (k, s) in s3.iter_mut().enumerate() {
                    let (p, q) = (s2[2 * k], s2[2 * k + 1]);
                    *s = _mm512_add_ps(
                        _mm512_shuffle_ps::<0x44>(p, q),
                        _mm512_shuffle_ps::<0xEE>(p, q),
                    );
                }
                // Level 4, c0 + c1: lane 4i + j is value 4j + i's sum.
                let s4 = _mm512_add_ps(
                    _mm512_shuffle_ps::<0x88>(s3[0], s3[1]),
                    _mm512_shuffle_ps::<0xDD>(s3[0], s3[1]),
                );
                let idx = _mm512_setr_epi32(0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15);
                let mut out = [0.0f32; 16];
                _mm512_storeu_ps(out.as_mut_ptr(), _mm512_permutexvar_ps(idx, s4));
                out
            }
        }
        #[inline(always)]
        fn exp_above(self, lo: Self) -> Self {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                // The lower clamp at `lo' = max(lo, −104)` (−104 for a NaN
                // `lo`): a lane at or above `lo` clamps to the same value as
                // with −104. clamp(x, lo', 89) as f32::clamp: NaN stays NaN
                // (max/min return their second operand when one is NaN).
                let lo = _mm512_max_ps(lo.0, _mm512_set1_ps(-104.0));
                let xc = _mm512_min_ps(_mm512_set1_ps(89.0), _mm512_max_ps(lo, self.0));
                let t = _mm512_add_ps(
                    _mm512_mul_ps(xc, _mm512_set1_ps(expc::LOG2E)),
                    _mm512_set1_ps(expc::ROUND),
                );
                let kf = _mm512_sub_ps(t, _mm512_set1_ps(expc::ROUND));
                let r = _mm512_sub_ps(
                    _mm512_sub_ps(xc, _mm512_mul_ps(kf, _mm512_set1_ps(expc::LN2_HI))),
                    _mm512_mul_ps(kf, _mm512_set1_ps(expc::LN2_LO)),
                );
                let z = _mm512_mul_ps(r, r);
                let mut p = _mm512_set1_ps(expc::P[0]);
                for &c in &expc::P[1..] {
                    p = _mm512_add_ps(_mm512_mul_ps(p, r), _mm512_set1_ps(c));
                }
                let p = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(p, z), r), _mm512_set1_ps(1.0));
                let k = _mm512_sub_epi32(
                    _mm512_castps_si512(t),
                    _mm512_set1_epi32(expc::ROUND.to_bits() as i32),
                );
                let k1 = _mm512_srai_epi32::<1>(k);
                let k2 = _mm512_sub_epi32(k, k1);
                let bias = _mm512_set1_epi32(127);
                let s1 = _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_add_epi32(k1, bias)));
                let s2 = _mm512_castsi512_ps(_mm512_slli_epi32::<23>(_mm512_add_epi32(k2, bias)));
                Avx512(_mm512_mul_ps(_mm512_mul_ps(p, s1), s2))
            }
        }
    }

    macro_rules! avx2_op {
        ($tr:ident, $f:ident, $intr:ident) => {
            impl $tr for Avx2 {
                type Output = Self;
                #[inline(always)]
                fn $f(self, o: Self) -> Self {
                    // SAFETY: AVX2 is present (this type only lives in functions
                    // compiled with it, reached after run-time detection).
                    unsafe { Avx2([$intr(self.0[0], o.0[0]), $intr(self.0[1], o.0[1])]) }
                }
            }
        };
    }
    avx2_op!(Add, add, _mm256_add_ps);
    avx2_op!(Sub, sub, _mm256_sub_ps);
    avx2_op!(Mul, mul, _mm256_mul_ps);
    avx2_op!(Div, div, _mm256_div_ps);
    impl Neg for Avx2 {
        type Output = Self;
        #[inline(always)]
        fn neg(self) -> Self {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                let m = _mm256_set1_ps(-0.0);
                Avx2([_mm256_xor_ps(self.0[0], m), _mm256_xor_ps(self.0[1], m)])
            }
        }
    }

    /// [`crate::kernels::fastmath::exp_f32`] on 8 lanes, its lower clamp at
    /// `lo' = max(lo, −104)` (−104 for a NaN `lo`), so a lane at or above
    /// `lo` clamps to the same value as with −104; NaN stays NaN, as `max`
    /// and `min` return their second operand when one is NaN.
    #[inline(always)]
    fn exp8(x: __m256, lo: __m256) -> __m256 {
        // SAFETY: AVX2 is present (only called from `Avx2` methods, which run in
        // functions compiled with it, reached after run-time detection).
        unsafe {
            let lo = _mm256_max_ps(lo, _mm256_set1_ps(-104.0));
            let xc = _mm256_min_ps(_mm256_set1_ps(89.0), _mm256_max_ps(lo, x));
            let t = _mm256_add_ps(
                _mm256_mul_ps(xc, _mm256_set1_ps(expc::LOG2E)),
                _mm256_set1_ps(expc::ROUND),
            );
            let kf = _mm256_sub_ps(t, _mm256_set1_ps(expc::ROUND));
            let r = _mm256_sub_ps(
                _mm256_sub_ps(xc, _mm256_mul_ps(kf, _mm256_set1_ps(expc::LN2_HI))),
                _mm256_mul_ps(kf, _mm256_set1_ps(expc::LN2_LO)),
            );
            let z = _mm256_mul_ps(r, r);
            let mut p = _mm256_set1_ps(expc::P[0]);
            for &c in &expc::P[1..] {
                p = _mm256_add_ps(_mm256_mul_ps(p, r), _mm256_set1_ps(c));
            }
            let p = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(p, z), r), _mm256_set1_ps(1.0));
            let k = _mm256_sub_epi32(
                _mm256_castps_si256(t),
                _mm256_set1_epi32(expc::ROUND.to_bits() as i32),
            );
            let k1 = _mm256_srai_epi32::<1>(k);
            let k2 = _mm256_sub_epi32(k, k1);
            let bias = _mm256_set1_epi32(127);
            let s1 = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(k1, bias)));
            let s2 = _mm256_castsi256_ps(_mm256_slli_epi32::<23>(_mm256_add_epi32(k2, bias)));
            _mm256_mul_ps(_mm256_mul_ps(p, s1), s2)
        }
    }

    /// The last three levels of [`Lanes::tree_sum`] on `a[l] = v[l] + v[l + 8]`.
    #[inline(always)]
    fn sum8(a: __m256) -> f32 {
        // SAFETY: AVX2 is present (only called from `Avx2` and `Avx512` methods, which run in
        // functions compiled with it, reached after run-time detection).
        unsafe {
            // b[l] = a[l] + a[l + 4]
            let b = _mm_add_ps(_mm256_castps256_ps128(a), _mm256_extractf128_ps::<1>(a));
            // c[l] = b[l] + b[l + 2]
            let c = _mm_add_ps(b, _mm_movehl_ps(b, b));
            // c[0] + c[1]
            let d = _mm_add_ss(c, _mm_shuffle_ps::<0b01>(c, c));
            _mm_cvtss_f32(d)
        }
    }

    /// All-ones in the lanes of `h`'s low 8 bits.
    #[inline(always)]
    fn mask8(h: i32) -> __m256 {
        // SAFETY: AVX2 is present (only called from `Avx2` methods, which run in
        // functions compiled with it, reached after run-time detection).
        unsafe {
            let sel = _mm256_setr_epi32(1, 2, 4, 8, 16, 32, 64, 128);
            let v = _mm256_and_si256(_mm256_set1_epi32(h), sel);
            _mm256_castsi256_ps(_mm256_cmpeq_epi32(v, sel))
        }
    }

    impl Lanes for Avx2 {
        type T = f32;
        /// Two all-ones/all-zeros lane masks.
        type M = [__m256; 2];
        #[inline(always)]
        fn splat(v: f32) -> Self {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { Avx2([_mm256_set1_ps(v); 2]) }
        }
        #[inline(always)]
        fn load(a: &[f32; LANES]) -> Self {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection); the pointer
            // addresses a 16-element array.
            unsafe {
                Avx2([
                    _mm256_loadu_ps(a.as_ptr()),
                    _mm256_loadu_ps(a.as_ptr().add(8)),
                ])
            }
        }
        #[inline(always)]
        fn store(self, a: &mut [f32; LANES]) {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection); the pointer
            // addresses a 16-element array.
            unsafe {
                _mm256_storeu_ps(a.as_mut_ptr(), self.0[0]);
                _mm256_storeu_ps(a.as_mut_ptr().add(8), self.0[1]);
            }
        }
        #[inline(always)]
        fn lt(self, o: Self) -> Self::M {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                [
                    _mm256_cmp_ps::<_CMP_LT_OQ>(self.0[0], o.0[0]),
                    _mm256_cmp_ps::<_CMP_LT_OQ>(self.0[1], o.0[1]),
                ]
            }
        }
        #[inline(always)]
        fn gt(self, o: Self) -> Self::M {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                [
                    _mm256_cmp_ps::<_CMP_GT_OQ>(self.0[0], o.0[0]),
                    _mm256_cmp_ps::<_CMP_GT_OQ>(self.0[1], o.0[1]),
                ]
            }
        }
        #[inline(always)]
        fn select(m: Self::M, a: Self, b: Self) -> Self {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                Avx2([
                    _mm256_blendv_ps(b.0[0], a.0[0], m[0]),
                    _mm256_blendv_ps(b.0[1], a.0[1], m[1]),
                ])
            }
        }
        #[inline(always)]
        fn and(a: Self::M, b: Self::M) -> Self::M {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { [_mm256_and_ps(a[0], b[0]), _mm256_and_ps(a[1], b[1])] }
        }
        #[inline(always)]
        fn andnot(a: Self::M, b: Self::M) -> Self::M {
            // _mm256_andnot_ps(x, y) = !x & y.
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { [_mm256_andnot_ps(b[0], a[0]), _mm256_andnot_ps(b[1], a[1])] }
        }
        #[inline(always)]
        fn bits(m: Self::M) -> u16 {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { (_mm256_movemask_ps(m[0]) as u16) | ((_mm256_movemask_ps(m[1]) as u16) << 8) }
        }
        #[inline(always)]
        fn from_bits(b: u16) -> Self::M {
            [mask8((b & 0xff) as i32), mask8((b >> 8) as i32)]
        }
        #[inline(always)]
        fn tree_sum(self) -> f32 {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { sum8(_mm256_add_ps(self.0[0], self.0[1])) }
        }
        #[inline(always)]
        fn tree_sums(v: [Self; 16]) -> [f32; 16] {
            // As Avx512's, in 128-bit halves, eight values at a time.
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                let mut out = [0.0f32; 16];
                for (h, o) in out.chunks_exact_mut(8).enumerate() {
                    let w = &v[8 * h..8 * h + 8];
                    // Level 1, a[l] = v[l] + v[l + 8].
                    let mut a = [_mm256_setzero_ps(); 8];
                    for (x, y) in a.iter_mut().zip(w) {
                        *x = _mm256_add_ps(y.0[0], y.0[1]);
                    }
                    // Level 2, b[l] = a[l] + a[l + 4]: halves [b of 2k, b of 2k + 1].
                    let mut b = [_mm256_setzero_ps(); 4];
                    for (k, x) in b.iter_mut().enumerate() {
                        let (p, q) = (a[2 * k], a[2 * k + 1]);
                        *x = _mm256_add_ps(
                            _mm256_permute2f128_ps::<0x20>(p, q),
                            _mm256_permute2f128_ps::<0x31>(p, q),
                        );
                    }
                    // Level 3, c[l] = b[l] + b[l + 2]: half i of c[k] is
                    // [c0, c1] of value 4k + i, then of value 4k + 2 + i.
                    let mut c = [_mm256_setzero_ps(); 2];
                    for (k, x) in c.iter_mut().enumerate() {
                        let (p, q) = (b[2 * k], b[2 * k + 1]);
                        *x = _mm256_add_ps(
                            _mm256_shuffle_ps::<0x44>(p, q),
                            _mm256_shuffle_ps::<0xEE>(p, q),
                        );
                    }
                    // Level 4, c0 + c1: lane 4i + j is value 2j + i's sum.
                    let d = _mm256_add_ps(
                        _mm256_shuffle_ps::<0x88>(c[0], c[1]),
                        _mm256_shuffle_ps::<0xDD>(c[0], c[1]),
                    );
                    let idx = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
                    _mm256_storeu_ps(o.as_mut_ptr(), _mm256_permutevar8x32_ps(d, idx));
                }
                out
            }
        }
        #[inline(always)]
        fn exp_above(self, lo: Self) -> Self {
            Avx2([exp8(self.0[0], lo.0[0]), exp8(self.0[1], lo.0[1])])
        }
    }

    // The chain rules' arithmetic ([`Arith`]) on the same registers: the
    // per-Gaussian backward runs its packs of 16 Gaussians in them, so the
    // values stay in registers instead of 16-element arrays.
    const fn splat16(v: f32) -> [f32; 16] {
        [v; 16]
    }

    impl AddAssign for Avx512 {
        #[inline(always)]
        fn add_assign(&mut self, o: Self) {
            *self = *self + o;
        }
    }

    impl Arith for Avx512 {
        type Elem = f32;
        type Mask = u16;
        // SAFETY: `__m512` is sixteen f32 lanes, the size and layout of the array.
        const ZERO: Self =
            Avx512(unsafe { std::mem::transmute::<[f32; 16], __m512>(splat16(0.0)) });
        // SAFETY: as for ZERO.
        const ONE: Self = Avx512(unsafe { std::mem::transmute::<[f32; 16], __m512>(splat16(1.0)) });
        #[inline(always)]
        fn splat(v: f32) -> Self {
            <Self as Lanes>::splat(v)
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            Avx512(unsafe { _mm512_sqrt_ps(self.0) })
        }
        #[inline(always)]
        fn clamp(self, lo: Self, hi: Self) -> Self {
            // Real::clamp: min(hi, max(lo, v)), max(v, o) = o > v ? o : v,
            // min(v, o) = o < v ? o : v.
            let m = <Self as Lanes>::select(lo.gt(self), lo, self);
            <Self as Lanes>::select(hi.lt(m), hi, m)
        }
        #[inline(always)]
        fn eq_mask(self, o: Self) -> u16 {
            // SAFETY: AVX-512F is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { _mm512_cmp_ps_mask::<_CMP_EQ_OQ>(self.0, o.0) }
        }
        #[inline(always)]
        fn select(m: u16, a: Self, b: Self) -> Self {
            <Self as Lanes>::select(m, a, b)
        }
    }

    impl AddAssign for Avx2 {
        #[inline(always)]
        fn add_assign(&mut self, o: Self) {
            *self = *self + o;
        }
    }

    impl Arith for Avx2 {
        type Elem = f32;
        type Mask = [__m256; 2];
        // SAFETY: `__m256` is eight f32 lanes, the size and layout of the array.
        const ZERO: Self =
            Avx2(unsafe { std::mem::transmute::<[f32; 16], [__m256; 2]>(splat16(0.0)) });
        // SAFETY: as for ZERO.
        const ONE: Self =
            Avx2(unsafe { std::mem::transmute::<[f32; 16], [__m256; 2]>(splat16(1.0)) });
        #[inline(always)]
        fn splat(v: f32) -> Self {
            <Self as Lanes>::splat(v)
        }
        #[inline(always)]
        fn sqrt(self) -> Self {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe { Avx2([_mm256_sqrt_ps(self.0[0]), _mm256_sqrt_ps(self.0[1])]) }
        }
        #[inline(always)]
        fn clamp(self, lo: Self, hi: Self) -> Self {
            // As for Avx512.
            let m = <Self as Lanes>::select(lo.gt(self), lo, self);
            <Self as Lanes>::select(hi.lt(m), hi, m)
        }
        #[inline(always)]
        fn eq_mask(self, o: Self) -> Self::Mask {
            // SAFETY: AVX2 is present (this type only lives in functions
            // compiled with it, reached after run-time detection).
            unsafe {
                [
                    _mm256_cmp_ps::<_CMP_EQ_OQ>(self.0[0], o.0[0]),
                    _mm256_cmp_ps::<_CMP_EQ_OQ>(self.0[1], o.0[1]),
                ]
            }
        }
        #[inline(always)]
        fn select(m: Self::Mask, a: Self, b: Self) -> Self {
            <Self as Lanes>::select(m, a, b)
        }
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
mod arith_tests {
    use super::{Avx2, Avx512, Lanes, LANES};
    use crate::kernels::fastmath;
    use crate::math::pack::Arith;

    /// Signed zeros, infinities, NaN, subnormals and ordinary values.
    const V: [f32; LANES] = [
        0.0,
        -0.0,
        1.0,
        -1.0,
        0.5,
        -2.5,
        f32::INFINITY,
        f32::NEG_INFINITY,
        f32::NAN,
        1e-38,
        -1e-40,
        3.0,
        7.25,
        -0.75,
        2.0,
        f32::MAX,
    ];

    /// The bits of `v`, every NaN as one pattern (which NaN an operation
    /// returns is not specified, and the compiler may fold constants to
    /// another one).
    fn bits(v: f32) -> u32 {
        if v.is_nan() {
            f32::NAN.to_bits()
        } else {
            v.to_bits()
        }
    }

    /// Every [`Arith`] operation of `N` on lanes `a`, `b`, `lo`, `hi`, as
    /// bits (masks as 0/1), in a fixed order.
    #[inline(always)]
    fn ops<N: Arith<Elem = f32> + Lanes<T = f32>>(
        a: [f32; LANES],
        b: [f32; LANES],
        lo: [f32; LANES],
        hi: [f32; LANES],
        mask_bits: impl Fn(<N as Arith>::Mask) -> u16,
    ) -> Vec<u32> {
        let (a, b, lo, hi) = (N::load(&a), N::load(&b), N::load(&lo), N::load(&hi));
        let mut out = Vec::new();
        let mut put = |v: N| {
            let mut x = [0.0f32; LANES];
            v.store(&mut x);
            out.extend(x.map(bits));
        };
        put(a + b);
        put(a - b);
        put(a * b);
        put(a / b);
        put(-a);
        let mut c = a;
        c += b;
        put(c);
        put(Arith::sqrt(a));
        put(Arith::clamp(a, lo, hi));
        let m = a.eq_mask(b);
        put(<N as Arith>::select(m, a, b));
        put(<N as Arith>::ZERO);
        put(<N as Arith>::ONE);
        put(<N as Arith>::splat(-3.5));
        out.push(mask_bits(m) as u32);
        out
    }

    /// The same on one lane at a time, as [`Arith`] for `f32` computes it.
    fn scalar(a: [f32; LANES], b: [f32; LANES], lo: [f32; LANES], hi: [f32; LANES]) -> Vec<u32> {
        let mut out = Vec::new();
        let each = |f: &dyn Fn(usize) -> f32| (0..LANES).map(|l| bits(f(l))).collect::<Vec<_>>();
        out.extend(each(&|l| a[l] + b[l]));
        out.extend(each(&|l| a[l] - b[l]));
        out.extend(each(&|l| a[l] * b[l]));
        out.extend(each(&|l| a[l] / b[l]));
        out.extend(each(&|l| -a[l]));
        out.extend(each(&|l| {
            let mut c = a[l];
            c += b[l];
            c
        }));
        out.extend(each(&|l| Arith::sqrt(a[l])));
        out.extend(each(&|l| Arith::clamp(a[l], lo[l], hi[l])));
        out.extend(each(&|l| {
            <f32 as Arith>::select(a[l].eq_mask(b[l]), a[l], b[l])
        }));
        out.extend(each(&|_| <f32 as Arith>::ZERO));
        out.extend(each(&|_| <f32 as Arith>::ONE));
        out.extend(each(&|_| <f32 as Arith>::splat(-3.5)));
        let mask = (0..LANES).fold(0u16, |m, l| m | (a[l].eq_mask(b[l]) as u16) << l);
        out.push(mask as u32);
        out
    }

    #[target_feature(enable = "avx512f")]
    fn on_avx512(a: [f32; LANES], b: [f32; LANES], lo: [f32; LANES], hi: [f32; LANES]) -> Vec<u32> {
        ops::<Avx512>(a, b, lo, hi, |m| m)
    }

    #[target_feature(enable = "avx2")]
    fn on_avx2(a: [f32; LANES], b: [f32; LANES], lo: [f32; LANES], hi: [f32; LANES]) -> Vec<u32> {
        ops::<Avx2>(a, b, lo, hi, <Avx2 as Lanes>::bits)
    }

    /// `tree_sums` of 16 values against `tree_sum` of each, as bits.
    #[inline(always)]
    fn sums<N: Lanes<T = f32>>(x: &[[f32; LANES]; 16]) -> (Vec<u32>, Vec<u32>) {
        let v: [N; 16] = std::array::from_fn(|k| N::load(&x[k]));
        let got = N::tree_sums(v).map(bits).to_vec();
        let want = v.map(|y| bits(y.tree_sum())).to_vec();
        (got, want)
    }

    #[target_feature(enable = "avx512f")]
    fn sums_avx512(x: &[[f32; LANES]; 16]) -> (Vec<u32>, Vec<u32>) {
        sums::<Avx512>(x)
    }

    #[target_feature(enable = "avx2")]
    fn sums_avx2(x: &[[f32; LANES]; 16]) -> (Vec<u32>, Vec<u32>) {
        sums::<Avx2>(x)
    }

    #[test]
    fn batched_tree_sums_give_the_bits_of_one_at_a_time() {
        // Values whose sums depend on the order (large and small of both
        // signs, signed zeros, infinities), a different mix per value.
        let mut r = crate::math::rng::Rng::new(7);
        for round in 0..200 {
            let x: [[f32; LANES]; 16] = std::array::from_fn(|k| {
                std::array::from_fn(|l| match (round + k + l) % 9 {
                    0 => V[(k * 3 + l) % LANES],
                    1 => r.uniform_range(-1e8, 1e8) as f32,
                    _ => r.uniform_range(-1.0, 1.0) as f32 * 10f32.powi((l % 7) as i32 - 3),
                })
            });
            // Each value's tree, and the Scalar one, give the same bits.
            let scalar: Vec<u32> = x
                .iter()
                .map(|v| bits(super::Scalar::load(v).tree_sum()))
                .collect();
            let defaults: Vec<u32> =
                super::Scalar::tree_sums(std::array::from_fn(|k| super::Scalar::load(&x[k])))
                    .map(bits)
                    .to_vec();
            assert_eq!(defaults, scalar, "portable, round {round}");
            if std::is_x86_feature_detected!("avx512f") {
                // SAFETY: the CPU has AVX-512F (checked above).
                let (got, want) = unsafe { sums_avx512(&x) };
                assert_eq!(want, scalar, "AVX-512 tree_sum, round {round}");
                assert_eq!(got, want, "AVX-512 tree_sums, round {round}");
            }
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2 (checked above).
                let (got, want) = unsafe { sums_avx2(&x) };
                assert_eq!(want, scalar, "AVX2 tree_sum, round {round}");
                assert_eq!(got, want, "AVX2 tree_sums, round {round}");
            }
        }
    }

    #[test]
    fn register_arithmetic_gives_the_scalar_bits() {
        let rot = |k: usize| -> [f32; LANES] { std::array::from_fn(|l| V[(l + k) % LANES]) };
        for k in 0..LANES {
            let (a, b) = (V, rot(k));
            // Bounds in order, reversed, and with NaN among them.
            let (lo, hi) = (rot((k + 3) % LANES), rot((k + 7) % LANES));
            let want = scalar(a, b, lo, hi);
            let first_diff = |got: &[u32]| {
                got.iter().zip(&want).position(|(g, w)| g != w).map(|i| {
                    let names = [
                        "add",
                        "sub",
                        "mul",
                        "div",
                        "neg",
                        "add_assign",
                        "sqrt",
                        "clamp",
                        "select",
                        "zero",
                        "one",
                        "splat",
                        "mask",
                    ];
                    format!(
                        "{} lane {}: got {:#x}, want {:#x} (a {}, b {}, lo {}, hi {})",
                        names[i / LANES],
                        i % LANES,
                        got[i],
                        want[i],
                        a[i % LANES],
                        b[i % LANES],
                        lo[i % LANES],
                        hi[i % LANES]
                    )
                })
            };
            if std::is_x86_feature_detected!("avx512f") {
                // SAFETY: the CPU has AVX-512F (checked above).
                let got = unsafe { on_avx512(a, b, lo, hi) };
                assert!(got == want, "AVX-512, rotation {k}: {:?}", first_diff(&got));
            }
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2 (checked above).
                let got = unsafe { on_avx2(a, b, lo, hi) };
                assert!(got == want, "AVX2, rotation {k}: {:?}", first_diff(&got));
            }
        }
    }

    #[target_feature(enable = "avx512f")]
    fn exp_above_avx512(x: &[f32; LANES], lo: &[f32; LANES]) -> [f32; LANES] {
        let mut out = [0.0; LANES];
        Avx512::load(x).exp_above(Avx512::load(lo)).store(&mut out);
        out
    }

    #[target_feature(enable = "avx2")]
    fn exp_above_avx2(x: &[f32; LANES], lo: &[f32; LANES]) -> [f32; LANES] {
        let mut out = [0.0; LANES];
        Avx2::load(x).exp_above(Avx2::load(lo)).store(&mut out);
        out
    }

    #[test]
    fn exp_above_is_exp_at_or_above_the_bound_on_every_path() {
        // Around the clamps (−104, 89) and the subnormal range (below
        // −87.3), bounds like the splats' `power_min` (finite, ±∞), and
        // NaN and infinite arguments.
        let mut r = crate::math::rng::Rng::new(11);
        let special = [
            f32::NAN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            -104.5,
            -104.0,
            -103.9,
            -87.4,
            -87.3,
            -5.0,
            -0.0,
            0.0,
            89.0,
            89.5,
        ];
        let bounds = [
            f32::NAN,
            f32::NEG_INFINITY,
            f32::INFINITY,
            -200.0,
            -104.0,
            -90.0,
            -87.0,
            -5.55,
            -0.01,
        ];
        for round in 0..400 {
            let x: [f32; LANES] = std::array::from_fn(|l| match (round + l) % 4 {
                0 => special[(round * 7 + l) % special.len()],
                _ => r.uniform_range(-120.0, 95.0) as f32,
            });
            let lo: [f32; LANES] = std::array::from_fn(|l| match (round + l) % 3 {
                0 => bounds[(round + l) % bounds.len()],
                _ => r.uniform_range(-110.0, 0.0) as f32,
            });
            // The definition: a lane below the bound (ordered; never for a
            // NaN bound) takes the bound.
            let want: [f32; LANES] =
                std::array::from_fn(|l| fastmath::exp_f32(if x[l] < lo[l] { lo[l] } else { x[l] }));
            let portable = super::Scalar::load(&x).exp_above(super::Scalar::load(&lo));
            let mut got = [0.0; LANES];
            portable.store(&mut got);
            assert_eq!(got.map(bits), want.map(bits), "portable, round {round}");
            if std::is_x86_feature_detected!("avx512f") {
                // SAFETY: the CPU has AVX-512F (checked above).
                let got = unsafe { exp_above_avx512(&x, &lo) };
                assert_eq!(got.map(bits), want.map(bits), "AVX-512, round {round}");
            }
            if std::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2 (checked above).
                let got = unsafe { exp_above_avx2(&x, &lo) };
                assert_eq!(got.map(bits), want.map(bits), "AVX2, round {round}");
            }
        }
    }
}
