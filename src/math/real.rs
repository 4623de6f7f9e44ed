//! The scalar type every numeric path is generic over: `f32` (to match GPU
//! backends) and `f64` (the higher-precision reference used by gradient checks).
//!
//! Every transcendental function goes through the pinned, pure-Rust `libm`
//! crate, never the platform's math library, so results are the same bits on
//! every CPU, operating system and build (`-C target-cpu=native` included).
//! `sqrt` is IEEE correctly rounded everywhere and is taken from `core`.
//!
//! Rust never contracts `a * b + c` into a fused multiply-add on its own, so
//! arithmetic written here rounds the same way whatever instructions the
//! compiler selects.

use std::fmt::{Debug, Display, LowerExp};
use std::iter::Sum;
use std::ops::{Add, AddAssign, Div, DivAssign, Mul, MulAssign, Neg, Sub, SubAssign};

/// Element type of a tensor file, selected by the precision of the data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Precision {
    /// IEEE binary32.
    F32,
    /// IEEE binary64.
    F64,
}

impl Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Precision::F32 => "f32",
            Precision::F64 => "f64",
        })
    }
}

/// Only `f32` and `f64` are [`Real`] (code that finds `T` to be of f32
/// precision reinterprets its data as `f32`, which relies on it).
mod sealed {
    pub trait Sealed {}
    impl Sealed for f32 {}
    impl Sealed for f64 {}
}

/// A real number type: `f32` or `f64` (sealed: no other type implements it).
pub trait Real:
    sealed::Sealed
    + Copy
    + Clone
    + Send
    + Sync
    + Debug
    + Display
    + LowerExp
    + Default
    + PartialEq
    + PartialOrd
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + Neg<Output = Self>
    + AddAssign
    + SubAssign
    + MulAssign
    + DivAssign
    + Sum
    + 'static
{
    /// `0.0`.
    const ZERO: Self;
    /// `1.0`.
    const ONE: Self;
    /// Which of the two types this is.
    const PRECISION: Precision;
    /// Bytes per element.
    const SIZE: usize;

    /// Round an `f64` to the nearest representable value.
    fn from_f64(x: f64) -> Self;
    /// The value as an `f64` (exact).
    fn to_f64(self) -> f64;
    /// From an `f32` (exact).
    fn from_f32(x: f32) -> Self;
    /// Exact for integers below 2^24 (f32) / 2^53 (f64).
    fn from_usize(x: usize) -> Self {
        Self::from_f64(x as f64)
    }
    /// The value stored little-endian in the first [`SIZE`](Self::SIZE) bytes.
    fn from_bits_le(bytes: &[u8]) -> Self;
    /// Append the value's little-endian bytes.
    fn write_le(self, out: &mut Vec<u8>);
    /// Raw IEEE bits widened to u64 (for hashing and bit comparisons).
    fn bits(self) -> u64;

    /// `e^self`.
    fn exp(self) -> Self;
    /// Natural logarithm.
    fn ln(self) -> Self;
    /// Square root (correctly rounded).
    fn sqrt(self) -> Self;
    /// Sine (radians).
    fn sin(self) -> Self;
    /// Cosine (radians).
    fn cos(self) -> Self;
    /// Tangent (radians).
    fn tan(self) -> Self;
    /// Arc tangent (radians).
    fn atan(self) -> Self;
    /// Hyperbolic tangent.
    fn tanh(self) -> Self;
    /// Error function.
    fn erf(self) -> Self;
    /// Base-10 logarithm.
    fn log10(self) -> Self;
    /// `self^e`.
    fn powf(self, e: Self) -> Self;
    /// Smallest integer not below `self`.
    fn ceil(self) -> Self;
    /// Largest integer not above `self`.
    fn floor(self) -> Self;
    /// The integer part (rounded toward zero).
    fn trunc(self) -> Self;
    /// Absolute value.
    fn abs(self) -> Self;
    /// Neither infinite nor NaN.
    fn is_finite(self) -> bool;
    /// Whether the value is NaN.
    fn is_nan(self) -> bool;
    /// `self · a + b` rounded once (IEEE 754 fusedMultiplyAdd). The result
    /// is exactly specified, so the hardware instruction (used where the
    /// build target guarantees one) and the pinned library's software
    /// version (used otherwise) give the same bits.
    fn mul_add(self, a: Self, b: Self) -> Self;

    /// `e^self` as the fields and the rasterizer compute it: in f32
    /// [`fast::exp_f32`](crate::math::fast::exp_f32) (plain arithmetic that
    /// vectorises, ≤ 1 ulp), in f64 the pinned libm.
    fn fast_exp(self) -> Self;
    /// `erf self`: [`fast::erf_f32`](crate::math::fast::erf_f32) in f32, the
    /// pinned libm in f64.
    fn fast_erf(self) -> Self;
    /// `tanh self`: [`fast::tanh_f32`](crate::math::fast::tanh_f32) in f32,
    /// the pinned libm in f64.
    fn fast_tanh(self) -> Self;
    /// `1/(1 + e^(−self))`: [`fast::sigmoid_f32`](crate::math::fast::sigmoid_f32)
    /// in f32, [`sigmoid`](Self::sigmoid) in f64.
    fn fast_sigmoid(self) -> Self;
    /// `(sin self, cos self)`: [`fast::sin_cos_f32`](crate::math::fast::sin_cos_f32)
    /// in f32 (libm's bits for `|x| < 2²⁸·π/2`), the pinned libm in f64.
    fn fast_sin_cos(self) -> (Self, Self);
    /// The slice as `&mut [f32]` when `Self` is `f32`, `None` when it is
    /// `f64` (for a pass that only the f32 version of a kernel needs).
    fn as_f32_slice_mut(x: &mut [Self]) -> Option<&mut [f32]>;

    /// `max` as CUDA's `fmaxf` for non-NaN inputs: the larger value.
    #[inline(always)]
    fn max(self, o: Self) -> Self {
        if o > self {
            o
        } else {
            self
        }
    }
    #[inline(always)]
    /// `min` as CUDA's `fminf` for non-NaN inputs: the smaller value.
    fn min(self, o: Self) -> Self {
        if o < self {
            o
        } else {
            self
        }
    }
    #[inline(always)]
    /// `min(hi, max(lo, self))`.
    fn clamp(self, lo: Self, hi: Self) -> Self {
        // min(hi, max(lo, v)), the order the Inria code uses.
        self.max(lo).min(hi)
    }
    #[inline(always)]
    /// `1 / self`.
    fn recip(self) -> Self {
        Self::ONE / self
    }
    #[inline(always)]
    /// `1 / (1 + e^(−self))` with the pinned `exp`.
    fn sigmoid(self) -> Self {
        Self::ONE / (Self::ONE + (-self).exp())
    }
}

macro_rules! impl_real {
    (@slice first, $x:ident) => {
        Some($x)
    };
    (@slice second, $x:ident) => {{
        let _ = $x;
        None
    }};
    ($t:ty, $prec:expr, $size:expr, $exp:path, $ln:path, $sin:path, $cos:path, $tan:path,
     $atan:path, $tanh:path, $erf:path, $log10:path, $pow:path, $ceil:path, $floor:path, $trunc:path,
     $fma:path, $pick:ident, $fexp:path, $ferf:path, $ftanh:path, $fsigmoid:path,
     $fsincos:path) => {
        impl Real for $t {
            const ZERO: Self = 0.0;
            const ONE: Self = 1.0;
            const PRECISION: Precision = $prec;
            const SIZE: usize = $size;
            #[inline(always)]
            fn from_f64(x: f64) -> Self {
                x as $t
            }
            #[inline(always)]
            fn to_f64(self) -> f64 {
                self as f64
            }
            #[inline(always)]
            fn from_f32(x: f32) -> Self {
                x as $t
            }
            #[inline(always)]
            fn from_bits_le(bytes: &[u8]) -> Self {
                let mut b = [0u8; $size];
                b.copy_from_slice(&bytes[..$size]);
                <$t>::from_le_bytes(b)
            }
            #[inline(always)]
            fn write_le(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
            #[inline(always)]
            fn bits(self) -> u64 {
                self.to_bits() as u64
            }
            #[inline(always)]
            fn exp(self) -> Self {
                $exp(self)
            }
            #[inline(always)]
            fn ln(self) -> Self {
                $ln(self)
            }
            #[inline(always)]
            fn sqrt(self) -> Self {
                <$t>::sqrt(self)
            }
            #[inline(always)]
            fn sin(self) -> Self {
                $sin(self)
            }
            #[inline(always)]
            fn cos(self) -> Self {
                $cos(self)
            }
            #[inline(always)]
            fn tan(self) -> Self {
                $tan(self)
            }
            #[inline(always)]
            fn atan(self) -> Self {
                $atan(self)
            }
            #[inline(always)]
            fn tanh(self) -> Self {
                $tanh(self)
            }
            #[inline(always)]
            fn erf(self) -> Self {
                $erf(self)
            }
            #[inline(always)]
            fn log10(self) -> Self {
                $log10(self)
            }
            #[inline(always)]
            fn powf(self, e: Self) -> Self {
                $pow(self, e)
            }
            #[inline(always)]
            fn ceil(self) -> Self {
                $ceil(self)
            }
            #[inline(always)]
            fn floor(self) -> Self {
                $floor(self)
            }
            #[inline(always)]
            fn trunc(self) -> Self {
                $trunc(self)
            }
            #[inline(always)]
            fn abs(self) -> Self {
                <$t>::abs(self)
            }
            #[inline(always)]
            fn is_finite(self) -> bool {
                <$t>::is_finite(self)
            }
            #[inline(always)]
            fn is_nan(self) -> bool {
                <$t>::is_nan(self)
            }
            #[inline(always)]
            fn fast_exp(self) -> Self {
                $fexp(self)
            }
            #[inline(always)]
            fn fast_erf(self) -> Self {
                $ferf(self)
            }
            #[inline(always)]
            fn fast_tanh(self) -> Self {
                $ftanh(self)
            }
            #[inline(always)]
            fn fast_sigmoid(self) -> Self {
                $fsigmoid(self)
            }
            #[inline(always)]
            fn fast_sin_cos(self) -> (Self, Self) {
                $fsincos(self)
            }
            #[inline(always)]
            fn as_f32_slice_mut(x: &mut [Self]) -> Option<&mut [f32]> {
                impl_real!(@slice $pick, x)
            }
            #[inline(always)]
            fn mul_add(self, a: Self, b: Self) -> Self {
                #[cfg(any(target_feature = "fma", target_arch = "aarch64"))]
                {
                    <$t>::mul_add(self, a, b)
                }
                #[cfg(not(any(target_feature = "fma", target_arch = "aarch64")))]
                {
                    $fma(self, a, b)
                }
            }
        }
    };
}

impl_real!(
    f32,
    Precision::F32,
    4,
    libm::expf,
    libm::logf,
    libm::sinf,
    libm::cosf,
    libm::tanf,
    libm::atanf,
    libm::tanhf,
    libm::erff,
    libm::log10f,
    libm::powf,
    libm::ceilf,
    libm::floorf,
    libm::truncf,
    libm::fmaf,
    first,
    super::fast::exp_f32,
    super::fast::erf_f32,
    super::fast::tanh_f32,
    super::fast::sigmoid_f32,
    super::fast::sin_cos_f32
);
impl_real!(
    f64,
    Precision::F64,
    8,
    libm::exp,
    libm::log,
    libm::sin,
    libm::cos,
    libm::tan,
    libm::atan,
    libm::tanh,
    libm::erf,
    libm::log10,
    libm::pow,
    libm::ceil,
    libm::floor,
    libm::trunc,
    libm::fma,
    second,
    libm::exp,
    libm::erf,
    libm::tanh,
    sigmoid_f64,
    sin_cos_f64
);

/// `1/(1 + e^(−x))` with the pinned `exp` ([`Real::sigmoid`] in f64).
#[inline(always)]
fn sigmoid_f64(x: f64) -> f64 {
    Real::sigmoid(x)
}

/// `(sin x, cos x)` with the pinned libm.
#[inline(always)]
fn sin_cos_f64(x: f64) -> (f64, f64) {
    (libm::sin(x), libm::cos(x))
}

/// Version string of the pinned math library, recorded beside every
/// bit-exact golden value.
pub const MATH_LIBRARY: &str = "libm 0.2.11";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clamp_matches_min_max_order() {
        assert_eq!(5.0f32.clamp(-1.0, 1.0), 1.0);
        assert_eq!((-5.0f64).clamp(-1.0, 1.0), -1.0);
        assert_eq!(Real::clamp(0.25f32, -1.0, 1.0), 0.25);
    }

    #[test]
    fn transcendentals_agree_with_f64_reference() {
        // f32 results must be within 2 ulp of the f64 value rounded to f32.
        for i in 0..200 {
            let xf = (-4.0 + i as f64 * 0.04) as f32;
            let x = xf as f64;
            let pairs: [(f32, f64); 4] = [
                (Real::exp(xf), Real::exp(x)),
                (Real::tanh(xf), Real::tanh(x)),
                (Real::erf(xf), Real::erf(x)),
                (Real::sin(xf), Real::sin(x)),
            ];
            for (a, b) in pairs {
                let r = b as f32;
                let ulp = (r.to_bits() as i64 - a.to_bits() as i64).abs();
                assert!(ulp <= 2 || (a - r).abs() < 1e-7, "x={x} f32={a} f64={b}");
            }
        }
    }

    /// The pinned software fma is correctly rounded: it agrees bit for bit
    /// with the CPU's FMA instruction (an independent implementation) on
    /// random operands of every magnitude and on halfway cases, where a
    /// product-then-sum in f64 would round twice.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn software_fma_matches_the_hardware_instruction() {
        use std::arch::x86_64::*;
        if !std::is_x86_feature_detected!("fma") {
            eprintln!("no FMA instruction on this CPU: not compared");
            return;
        }
        #[target_feature(enable = "fma")]
        unsafe fn hw32(a: f32, b: f32, c: f32) -> f32 {
            _mm_cvtss_f32(_mm_fmadd_ss(_mm_set_ss(a), _mm_set_ss(b), _mm_set_ss(c)))
        }
        #[target_feature(enable = "fma")]
        unsafe fn hw64(a: f64, b: f64, c: f64) -> f64 {
            _mm_cvtsd_f64(_mm_fmadd_sd(_mm_set_sd(a), _mm_set_sd(b), _mm_set_sd(c)))
        }
        let mut rng = crate::math::Rng::new(7);
        // Random sign and mantissa, exponent within `span` of 0 (so sums
        // cancel and products over/underflow sometimes).
        let f32s = |rng: &mut crate::math::Rng, span: u32| -> f32 {
            let bits = rng.next_u64();
            let e = 127 + (bits >> 32) as u32 % (2 * span + 1) - span;
            f32::from_bits(
                ((bits >> 63) as u32) << 31 | e.clamp(0, 254) << 23 | bits as u32 & 0x7f_ffff,
            )
        };
        let mut cases32 = vec![
            (
                f32::from_bits(1266679807),
                f32::from_bits(1300234242),
                f32::from_bits(1115553792),
            ),
            // (1 + 2^-23)(1 - 2^-23) - 1: the exact result -2^-46 is lost
            // by a separate multiply and add.
            (1.0 + f32::EPSILON, 1.0 - f32::EPSILON, -1.0),
            (0.0, -1.0, 0.0),
            (f32::MAX, 2.0, -f32::MAX),
            (f32::from_bits(1), 0.5, 0.0),
        ];
        for span in [3, 20, 126] {
            for _ in 0..20_000 {
                cases32.push((
                    f32s(&mut rng, span),
                    f32s(&mut rng, span),
                    f32s(&mut rng, span),
                ));
            }
        }
        for &(a, b, c) in &cases32 {
            // SAFETY: the test returned early unless the CPU has FMA.
            let want = unsafe { hw32(a, b, c) };
            for got in [libm::fmaf(a, b, c), Real::mul_add(a, b, c)] {
                assert!(
                    got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()),
                    "fmaf({a:e}, {b:e}, {c:e}) = {got:e}, hardware {want:e}"
                );
            }
        }
        let mut cases64 = vec![
            (1.0 + f64::EPSILON, 1.0 - f64::EPSILON, -1.0),
            (0.1, 10.0, -1.0),
            (f64::MAX, 2.0, -f64::MAX),
        ];
        for _ in 0..60_000 {
            let (a, b, c) = (
                f32s(&mut rng, 20) as f64,
                f32s(&mut rng, 20) as f64,
                f32s(&mut rng, 20) as f64,
            );
            // Spread the mantissas over all 52 bits.
            let j = |x: f64, r: u64| f64::from_bits(x.to_bits() ^ (r & 0x1fff_ffff));
            let r = rng.next_u64();
            cases64.push((j(a, r), j(b, r >> 20), j(c, r >> 40)));
        }
        for &(a, b, c) in &cases64 {
            // SAFETY: the test returned early unless the CPU has FMA.
            let want = unsafe { hw64(a, b, c) };
            for got in [libm::fma(a, b, c), Real::mul_add(a, b, c)] {
                assert!(
                    got.to_bits() == want.to_bits() || (got.is_nan() && want.is_nan()),
                    "fma({a:e}, {b:e}, {c:e}) = {got:e}, hardware {want:e}"
                );
            }
        }
    }
}
