//! Vectorisable, deterministic `exp`, `erf`, `tanh` and `sigmoid` for the f32
//! deformation fields, written in plain arithmetic (no libm, no FMA).
//!
//! **Decision (deform DECISIONS).** In f32 the deformation fields evaluate
//! every `exp`, `erf`, `tanh` and `sigmoid` of their activations and of the CfC
//! cell — forward and backward alike — with the functions of this module and
//! nothing else; f64 keeps the pinned libm of [`Real`] (it is the
//! gradient-check and reference precision). Why: libm's scalar `tanhf` costs
//! about 25 ns and cannot be vectorised; these cost about 1 ns per value in
//! 16-wide AVX-512 loops and made the CfC field several times faster.
//! Determinism is kept: each function is a fixed sequence of IEEE additions,
//! multiplications, divisions, comparisons, exact conversions and bit
//! operations (`abs`, `copysign`, building `2^k`), each correctly rounded or
//! exact, so a lane of an AVX-512, AVX2 or SSE2 loop and a scalar call give
//! the same bits. Rust never fuses `a*b + c` into an FMA.
//!
//! Algorithms (the Cephes `expf`/`tanhf`/`erff` coefficients):
//! - `exp`: `x` clamped to [−104, 89] (outside, the result is 0 or +∞
//!   anyway), `k = round(x·log₂e)` (by adding and subtracting 1.5·2²³),
//!   `r = (x − k·ln2_hi) − k·ln2_lo` (Cody–Waite, `k·ln2_hi` exact),
//!   `e^r ≈ 1 + r + r²·P₅(r)`, scaled by `2^⌊k/2⌋·2^(k−⌊k/2⌋)` (two exact
//!   powers of two, so results in the subnormal range round once). NaN in,
//!   NaN out.
//! - `tanh`: `|x| < 0.625`: `x + x·x²·P₄(x²)`; otherwise
//!   `sign(x)·(1 − 2/(e^{2|x|} + 1))`.
//! - `sigmoid(x) = 1/(1 + exp(−x))`.
//! - `erf`: `|x| < 1`: `x·T₆(x²)`; otherwise `sign(x)·(1 − erfc|x|)` with
//!   `erfc a = e^{−a²}·(1/a)·P₈(1/a²)` (`R₇` for `a ≥ 2`), `a` capped at 10.
//!
//! Accuracy against the correctly rounded value (tested on a dense sweep
//! against libm in f64, `tests` below): `exp` ≤ 1 ulp, `tanh` ≤ 1 ulp,
//! `sigmoid` ≤ 2 ulp, `erf` ≤ 2 ulp for normal results (libm's own f32
//! functions are ≤ 1 ulp). A rounding difference of this size is far below
//! the f32 tolerance of the oracle comparisons with PyTorch.

// The polynomial coefficients are written as published (Cephes), with more
// digits than f32 holds; the compiler rounds each to the nearest f32.
#![allow(clippy::excessive_precision)]

use crate::math::Real;
use std::any::TypeId;
use std::sync::atomic::{AtomicU8, Ordering};

/// Maximum errors in ulp asserted by the tests (see the module docs).
pub const EXP_MAX_ULP: u32 = 1;
pub const TANH_MAX_ULP: u32 = 1;
pub const SIGMOID_MAX_ULP: u32 = 2;
pub const ERF_MAX_ULP: u32 = 2;

/// `e^x` in f32.
#[inline(always)]
pub fn exp_f32(x: f32) -> f32 {
    const LOG2E: f32 = std::f32::consts::LOG2_E;
    const LN2_HI: f32 = 0.693_359_4; // 0.693359375, exact in 12 bits
    const LN2_LO: f32 = -2.121_944_4e-4;
    const ROUND: f32 = 12_582_912.0; // 1.5·2²³
                                     // Outside [−104, 89] the result is 0 or +∞ anyway; NaN stays NaN.
    let xc = x.clamp(-104.0, 89.0);
    // t holds round(xc·log₂e) in its low mantissa bits (|k| ≤ 151 < 2²²).
    let t = xc * LOG2E + ROUND;
    let kf = t - ROUND;
    let r = (xc - kf * LN2_HI) - kf * LN2_LO;
    let z = r * r;
    let p = (((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2)
        * r
        + 1.666_666_5e-1)
        * r
        + 5.000_000_1e-1)
        * z
        + r
        + 1.0;
    // k from the bits of t (exact; integer ops that vectorise, wrapping so
    // that no overflow check breaks the vector loop; for NaN, p is NaN).
    let k = (t.to_bits() as i32).wrapping_sub(ROUND.to_bits() as i32);
    let k1 = k >> 1;
    let k2 = k.wrapping_sub(k1);
    let s1 = f32::from_bits((k1.wrapping_add(127) as u32).wrapping_shl(23));
    let s2 = f32::from_bits((k2.wrapping_add(127) as u32).wrapping_shl(23));
    p * s1 * s2
}

/// `tanh x` in f32.
#[inline(always)]
pub fn tanh_f32(x: f32) -> f32 {
    let a = x.abs();
    let z = x * x;
    let small =
        ((((-5.704_988_7e-3 * z + 2.063_908_9e-2) * z - 5.373_971_6e-2) * z + 1.333_144_2e-1) * z
            - 3.333_328_2e-1)
            * z
            * x
            + x;
    let e = exp_f32(a + a);
    let large = 1.0 - 2.0 / (e + 1.0);
    // Both have the sign of x (copysign also makes tanh(−0) = −0).
    if a < 0.625 {
        small.copysign(x)
    } else {
        large.copysign(x)
    }
}

/// Evaluate `c[0]·x^(n−1) + … + c[n−1]` by Horner's rule, left to right.
#[inline(always)]
fn horner(x: f32, c: &[f32]) -> f32 {
    let mut y = c[0];
    for &ci in &c[1..] {
        y = y * x + ci;
    }
    y
}

/// `erf x` in f32.
#[inline(always)]
pub fn erf_f32(x: f32) -> f32 {
    const T: [f32; 7] = [
        7.853_861_4e-5,
        -8.010_193_6e-4,
        5.188_327_7e-3,
        -2.685_381_2e-2,
        1.128_358_5e-1,
        -3.761_262_6e-1,
        std::f32::consts::FRAC_2_SQRT_PI,
    ];
    const P: [f32; 9] = [
        2.326_82e-2,
        -1.387_039_4e-1,
        3.687_424_7e-1,
        -5.824_733e-1,
        6.210_004_6e-1,
        -4.944_515_3e-1,
        3.404_879_9e-1,
        -2.741_127e-1,
        5.638_259_4e-1,
    ];
    const R: [f32; 8] = [
        -1.047_766_4e1,
        1.297_72e1,
        -7.495_518_7,
        2.921_019,
        -1.015_265_3,
        4.218_463_4e-1,
        -2.820_767_4e-1,
        5.641_895e-1,
    ];
    let a = x.abs();
    // |x| < 1: x·T(x²).
    let small = x * horner(x * x, &T);
    // |x| ≥ 1: 1 − erfc|x|, erfc a = e^{−a²}·(1/a)·P(1/a²) (R for a ≥ 2).
    let ac = if a > 10.0 { 10.0 } else { a };
    let q = 1.0 / ac;
    let y = q * q;
    let p = if ac < 2.0 {
        horner(y, &P)
    } else {
        horner(y, &R)
    };
    let erfc = exp_f32(-(ac * ac)) * q * p;
    let large = 1.0 - erfc;
    if a < 1.0 {
        small
    } else {
        large.copysign(x)
    }
}

/// `1/(1 + e^{−x})` in f32.
#[inline(always)]
pub fn sigmoid_f32(x: f32) -> f32 {
    1.0 / (1.0 + exp_f32(-x))
}

#[inline(always)]
fn is_f32<T: 'static>() -> bool {
    TypeId::of::<T>() == TypeId::of::<f32>()
}

#[inline(always)]
fn to_f32<T: Real>(x: T) -> f32 {
    // SAFETY: only called when T is f32 (checked by the caller).
    unsafe { std::mem::transmute_copy::<T, f32>(&x) }
}

#[inline(always)]
fn from_f32<T: Real>(x: f32) -> T {
    // SAFETY: only called when T is f32 (checked by the caller).
    unsafe { std::mem::transmute_copy::<f32, T>(&x) }
}

/// `e^x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn exp<T: Real>(x: T) -> T {
    if is_f32::<T>() {
        from_f32(exp_f32(to_f32(x)))
    } else {
        x.exp()
    }
}

/// `erf x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn erf<T: Real>(x: T) -> T {
    if is_f32::<T>() {
        from_f32(erf_f32(to_f32(x)))
    } else {
        x.erf()
    }
}

/// `tanh x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn tanh<T: Real>(x: T) -> T {
    if is_f32::<T>() {
        from_f32(tanh_f32(to_f32(x)))
    } else {
        x.tanh()
    }
}

/// `sigmoid x` as the fields compute it: this module's f32 function,
/// `1/(1 + exp(−x))` with libm's exp in f64.
#[inline(always)]
pub fn sigmoid<T: Real>(x: T) -> T {
    if is_f32::<T>() {
        from_f32(sigmoid_f32(to_f32(x)))
    } else {
        x.sigmoid()
    }
}

/// Which instruction set the element-wise loops and the matrix kernels of
/// the fields run on (all give the same bits; see the module docs).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// AVX-512F (its vector FMA included).
    Avx512,
    /// AVX2 with FMA.
    Avx2,
    /// The build target's baseline (SSE2 on x86-64).
    Baseline,
}

/// 0: the widest the CPU supports; otherwise a pinned [`Isa`] (1 baseline,
/// 2 AVX2, 3 AVX-512).
static FORCED: AtomicU8 = AtomicU8::new(0);

/// Pin the fields' kernels to `isa` (`None`: the widest available), for
/// tests and benchmarks that compare paths; a path the CPU lacks is refused
/// (returns false). Never changes results, only speed.
pub fn force_isa(isa: Option<Isa>) -> bool {
    let code = match isa {
        None => 0,
        Some(Isa::Baseline) => 1,
        Some(Isa::Avx2) if supported(Isa::Avx2) => 2,
        Some(Isa::Avx512) if supported(Isa::Avx512) => 3,
        Some(_) => return false,
    };
    FORCED.store(code, Ordering::Relaxed);
    true
}

fn supported(isa: Isa) -> bool {
    match isa {
        Isa::Baseline => true,
        #[cfg(target_arch = "x86_64")]
        // The AVX2 matrix tile uses FMA (AVX2 CPUs without it are rare).
        Isa::Avx2 => std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"),
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => std::is_x86_feature_detected!("avx512f"),
        #[cfg(not(target_arch = "x86_64"))]
        _ => false,
    }
}

/// The [`Isa`] the kernels run on now: the pinned one, or the widest this
/// CPU supports.
#[inline]
pub fn isa() -> Isa {
    match FORCED.load(Ordering::Relaxed) {
        1 => return Isa::Baseline,
        2 => return Isa::Avx2,
        3 => return Isa::Avx512,
        _ => {}
    }
    if supported(Isa::Avx512) {
        Isa::Avx512
    } else if supported(Isa::Avx2) {
        Isa::Avx2
    } else {
        Isa::Baseline
    }
}

/// Define `$name(args)` that runs the `#[inline(always)]` generic function
/// `$body(args)` compiled for AVX-512, AVX2 or the baseline, picked at run
/// time: the loop inside `$body` is vectorised as wide as the CPU allows.
macro_rules! multiversion {
    ($vis:vis fn $name:ident<T: Real>($($arg:ident: $ty:ty),*) => $body:ident) => {
        $vis fn $name<T: Real>($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                unsafe fn avx512<T: Real>($($arg: $ty),*) {
                    $body($($arg),*)
                }
                #[target_feature(enable = "avx2")]
                unsafe fn avx2<T: Real>($($arg: $ty),*) {
                    $body($($arg),*)
                }
                match $crate::deform::fastmath::isa() {
                    // SAFETY: the CPU supports the feature (checked by isa()).
                    $crate::deform::fastmath::Isa::Avx512 => return unsafe { avx512::<T>($($arg),*) },
                    $crate::deform::fastmath::Isa::Avx2 => return unsafe { avx2::<T>($($arg),*) },
                    $crate::deform::fastmath::Isa::Baseline => {}
                }
            }
            $body($($arg),*)
        }
    };
}
pub(crate) use multiversion;

#[cfg(test)]
mod tests {
    use super::*;

    /// Distance in ulp between an f32 and the exact value `want` (f64).
    fn ulp(got: f32, want: f64) -> u32 {
        let w = want as f32; // correctly rounded (within ½ ulp of f64's error)
        if got == w {
            return 0;
        }
        let key = |v: f32| {
            let b = v.to_bits() as i64;
            if b < 0x8000_0000 {
                b
            } else {
                0x8000_0000 - b
            }
        };
        (key(got) - key(w)).unsigned_abs() as u32
    }

    fn sweep(lo: f32, hi: f32, steps: usize) -> impl Iterator<Item = f32> {
        (0..=steps).map(move |i| lo + (hi - lo) * (i as f32 / steps as f32))
    }

    /// Every f32 in [lo, hi] with a bit-pattern stride (dense near zero).
    fn bits_sweep(lo: f32, hi: f32, stride: u32) -> Vec<f32> {
        let mut v = Vec::new();
        for sign in [1.0f32, -1.0] {
            let mut b = 0u32;
            loop {
                let x = f32::from_bits(b) * sign;
                if x.abs() > hi.abs().max(lo.abs()) {
                    break;
                }
                if x >= lo && x <= hi {
                    v.push(x);
                }
                b += stride;
            }
        }
        v
    }

    #[test]
    fn exp_error_bound() {
        let mut worst = 0;
        for x in bits_sweep(-87.0, 88.7, 97)
            .into_iter()
            .chain(sweep(-87.0, 88.7, 2_000_000))
        {
            let e = ulp(exp_f32(x), libm::exp(x as f64));
            assert!(
                e <= EXP_MAX_ULP,
                "exp({x:e}): {} vs {}",
                exp_f32(x),
                libm::exp(x as f64)
            );
            worst = worst.max(e);
        }
        assert_eq!(worst, EXP_MAX_ULP, "the documented bound is tight");
        // Limits and special values.
        assert_eq!(exp_f32(0.0), 1.0);
        assert_eq!(exp_f32(89.0), f32::INFINITY);
        assert_eq!(exp_f32(1e30), f32::INFINITY);
        assert_eq!(exp_f32(f32::INFINITY), f32::INFINITY);
        assert_eq!(exp_f32(-200.0), 0.0);
        assert_eq!(exp_f32(f32::NEG_INFINITY), 0.0);
        assert!(exp_f32(f32::NAN).is_nan());
        // Subnormal results: within 1 ulp of the subnormal spacing.
        for x in sweep(-103.0, -87.5, 10_000) {
            let want = libm::exp(x as f64);
            let got = exp_f32(x) as f64;
            assert!((got - want).abs() <= 1.5 * f32::from_bits(1) as f64, "{x}");
        }
    }

    #[test]
    fn erf_error_bound() {
        let mut worst = 0;
        for x in bits_sweep(-6.0, 6.0, 61)
            .into_iter()
            .chain(sweep(-6.0, 6.0, 2_000_000))
        {
            let e = ulp(erf_f32(x), libm::erf(x as f64));
            assert!(
                e <= ERF_MAX_ULP,
                "erf({x:e}) = {} vs {}",
                erf_f32(x),
                libm::erf(x as f64)
            );
            worst = worst.max(e);
        }
        assert_eq!(worst, ERF_MAX_ULP, "the documented erf bound is tight");
        assert_eq!(erf_f32(0.0), 0.0);
        assert_eq!(erf_f32(30.0), 1.0);
        assert_eq!(erf_f32(f32::NEG_INFINITY), -1.0);
        assert!(erf_f32(f32::NAN).is_nan());
    }

    #[test]
    fn tanh_and_sigmoid_error_bounds() {
        let (mut wt, mut ws) = (0, 0);
        for x in bits_sweep(-12.0, 12.0, 61)
            .into_iter()
            .chain(sweep(-12.0, 12.0, 2_000_000))
        {
            let e = ulp(tanh_f32(x), libm::tanh(x as f64));
            assert!(
                e <= TANH_MAX_ULP,
                "tanh({x:e}) = {} vs {}",
                tanh_f32(x),
                libm::tanh(x as f64)
            );
            wt = wt.max(e);
            let want = 1.0 / (1.0 + libm::exp(-(x as f64)));
            let e = ulp(sigmoid_f32(x), want);
            assert!(
                e <= SIGMOID_MAX_ULP,
                "sigmoid({x:e}) = {} vs {want}",
                sigmoid_f32(x)
            );
            ws = ws.max(e);
        }
        assert_eq!(wt, TANH_MAX_ULP, "the documented tanh bound is tight");
        assert_eq!(ws, SIGMOID_MAX_ULP, "the documented sigmoid bound is tight");
        assert_eq!(tanh_f32(0.0), 0.0);
        assert_eq!(tanh_f32(-0.0).to_bits(), (-0.0f32).to_bits());
        assert_eq!(tanh_f32(50.0), 1.0);
        assert_eq!(tanh_f32(-1e30), -1.0);
        assert_eq!(tanh_f32(f32::INFINITY), 1.0);
        assert!(tanh_f32(f32::NAN).is_nan());
        assert_eq!(sigmoid_f32(200.0), 1.0);
        assert_eq!(sigmoid_f32(-200.0), 0.0);
        assert_eq!(sigmoid_f32(0.0), 0.5);
        // Odd symmetry is exact.
        for x in sweep(0.0, 10.0, 10_000) {
            assert_eq!(tanh_f32(-x).to_bits(), (-tanh_f32(x)).to_bits());
        }
    }

    multiversion!(fn tanh_all<T: Real>(x: &mut [T]) => tanh_all_body);

    #[inline(always)]
    fn tanh_all_body<T: Real>(x: &mut [T]) {
        for v in x.iter_mut() {
            *v = tanh(*v);
        }
    }

    #[test]
    fn vector_loops_give_the_scalar_bits() {
        let xs: Vec<f32> = sweep(-20.0, 20.0, 100_003).collect();
        let mut v = xs.clone();
        tanh_all(&mut v);
        for (x, y) in xs.iter().zip(&v) {
            assert_eq!(y.to_bits(), tanh_f32(std::hint::black_box(*x)).to_bits());
        }
        // f64 keeps libm.
        let mut d: Vec<f64> = xs.iter().map(|&x| x as f64).collect();
        tanh_all(&mut d);
        for (x, y) in xs.iter().zip(&d) {
            assert_eq!(y.to_bits(), libm::tanh(*x as f64).to_bits());
        }
    }
}
