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
    F32,
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

/// A real number type: `f32` or `f64`.
pub trait Real:
    Copy
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
    const ZERO: Self;
    const ONE: Self;
    const PRECISION: Precision;
    /// Bytes per element.
    const SIZE: usize;

    /// Round an `f64` to the nearest representable value.
    fn from_f64(x: f64) -> Self;
    fn to_f64(self) -> f64;
    fn from_f32(x: f32) -> Self;
    /// Exact for integers below 2^24 (f32) / 2^53 (f64).
    fn from_usize(x: usize) -> Self {
        Self::from_f64(x as f64)
    }
    fn from_bits_le(bytes: &[u8]) -> Self;
    fn write_le(self, out: &mut Vec<u8>);
    /// Raw IEEE bits widened to u64 (for hashing and bit comparisons).
    fn bits(self) -> u64;

    fn exp(self) -> Self;
    fn ln(self) -> Self;
    fn sqrt(self) -> Self;
    fn sin(self) -> Self;
    fn cos(self) -> Self;
    fn tan(self) -> Self;
    fn atan(self) -> Self;
    fn tanh(self) -> Self;
    fn erf(self) -> Self;
    fn log10(self) -> Self;
    fn powf(self, e: Self) -> Self;
    fn ceil(self) -> Self;
    fn floor(self) -> Self;
    fn trunc(self) -> Self;
    fn abs(self) -> Self;
    fn is_finite(self) -> bool;
    fn is_nan(self) -> bool;

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
    fn min(self, o: Self) -> Self {
        if o < self {
            o
        } else {
            self
        }
    }
    #[inline(always)]
    fn clamp(self, lo: Self, hi: Self) -> Self {
        // min(hi, max(lo, v)), the order the Inria code uses.
        self.max(lo).min(hi)
    }
    #[inline(always)]
    fn recip(self) -> Self {
        Self::ONE / self
    }
    #[inline(always)]
    fn sigmoid(self) -> Self {
        Self::ONE / (Self::ONE + (-self).exp())
    }
}

macro_rules! impl_real {
    ($t:ty, $prec:expr, $size:expr, $exp:path, $ln:path, $sin:path, $cos:path, $tan:path,
     $atan:path, $tanh:path, $erf:path, $log10:path, $pow:path, $ceil:path, $floor:path, $trunc:path) => {
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
    libm::truncf
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
    libm::trunc
);

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
}
