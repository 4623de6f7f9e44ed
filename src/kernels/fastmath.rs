//! Vectorisable, deterministic `exp`, `erf`, `tanh` and `sigmoid` for the f32
//! deformation fields, written in plain arithmetic (no libm, no FMA); and
//! libm's own f32 `sin`/`cos`, rewritten so that it vectorises.
//!
//! **`sin`/`cos`** ([`sin_cos_f32`], used by the positional encoding) are not
//! approximations of this module's own: they are the pinned libm's `sinf` and
//! `cosf`, the same f64 operations in the same order, with the branches
//! replaced by selects. They give libm's bits for every one of the 2³² f32
//! inputs (the ignored test `sin_cos_every_f32` checks them all, in a few
//! minutes; every test run checks a strided sample and each range boundary),
//! so the encoding's values are unchanged, about 8× cheaper.
//!
//! **Decision (docs/DECISIONS.md §3).** In f32 the deformation fields evaluate
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

/// `(sin x, cos x)` in f32, the same bits as the pinned libm's `sinf` and
/// `cosf` for `|x| < 2²⁸·π/2` (larger or non-finite `x`: see
/// [`sin_cos_slices`], which hands those to libm).
///
/// This is libm 0.2.11's algorithm (FreeBSD's `s_sinf.c`/`s_cosf.c`, kernels
/// `k_sinf`/`k_cosf`, medium branch of `rem_pio2f`), the same f64
/// operations in the same order, rearranged without branches so that a loop
/// over it vectorises:
/// - `a` is the reduced argument: `x` for `|x| ≲ π/4`; `x ∓ k·π/2` (k = 1…4,
///   the same double constants, sign of `x` chooses) up to `9π/4`; beyond,
///   `rem_pio2f`'s `x − n·pio2_1 − n·pio2_1t` with `n = rint(x·2/π)`.
/// - With quadrant `q` (`k` or `n` mod 4; `−k` mod 4 for negative `x`),
///   `sin x = [s, c, −s, −c][q]` and `cos x = [c, −s, −c, s][q]` where
///   `s = k_sinf(a)`, `c = k_cosf(a)`. libm's branches compute the same
///   values: each calls one kernel on `±a`, and `k_sinf(−a) = −k_sinf(a)`,
///   `k_cosf(−a) = k_cosf(a)` exactly (round-to-nearest is symmetric; `a` is
///   never zero there, as no multiple of the double π/2 is an f32).
/// - `|x| < 2⁻¹²`: `sin x = x`, `cos x = 1`, as libm returns.
#[inline(always)]
pub fn sin_cos_f32(x: f32) -> (f32, f32) {
    use std::f64::consts::FRAC_PI_2;
    // rem_pio2f's constants, as libm writes them (INV_PIO2 is 2/π).
    const TOINT: f64 = 1.5 / f64::EPSILON;
    #[allow(clippy::approx_constant)]
    const INV_PIO2: f64 = 6.366_197_723_675_813_824_33e-1;
    const PIO2_1: f64 = 1.570_796_310_901_641_845_70e0;
    const PIO2_1T: f64 = 1.589_325_477_352_819_669_16e-8;
    #[inline(always)]
    fn k_sin(x: f64) -> f32 {
        const S1: f64 = -0.166_666_666_416_265_235_595;
        const S2: f64 = 0.008_333_329_385_889_463_175_6;
        const S3: f64 = -0.000_198_393_348_360_966_317_347;
        const S4: f64 = 0.000_002_718_311_493_989_821_906_4;
        let z = x * x;
        let w = z * z;
        let r = S3 + z * S4;
        let s = z * x;
        ((x + s * (S1 + z * S2)) + s * w * r) as f32
    }
    #[inline(always)]
    fn k_cos(x: f64) -> f32 {
        const C0: f64 = -0.499_999_997_251_031_003_120;
        const C1: f64 = 0.041_666_623_323_739_063_189_4;
        const C2: f64 = -0.001_388_676_377_460_992_946_92;
        const C3: f64 = 0.000_024_390_448_796_277_409_065_4;
        let z = x * x;
        let w = z * z;
        let r = C2 + z * C3;
        (((1.0 + z * C0) + w * C1) + (w * z) * r) as f32
    }
    let x64 = x as f64;
    let ix = x.to_bits() & 0x7fff_ffff;
    let negative = x.to_bits() >> 31 != 0;
    // Which of sinf's ranges: |x| ≲ π/4, 3π/4, 5π/4, 7π/4, 9π/4, beyond.
    let k = (ix > 0x3f49_0fda) as u32
        + (ix > 0x4016_cbe3) as u32
        + (ix > 0x407b_53d1) as u32
        + (ix > 0x40af_eddf) as u32
        + (ix > 0x40e2_31d5) as u32;
    // rem_pio2f (medium): n = rint(x·2/π) by adding and subtracting 1.5·2⁵²;
    // n mod 4 from the low bits of tmp (tmp = 1.5·2⁵² + n, exactly).
    let tmp = x64 * INV_PIO2 + TOINT;
    let f_n = tmp - TOINT;
    let n = (tmp.to_bits().wrapping_sub(TOINT.to_bits()) & 3) as u32;
    let y = x64 - f_n * PIO2_1 - f_n * PIO2_1T;
    // Small ranges: x ∓ k·π/2 (k·π/2 rounded as libm's constants are; the
    // sign of x chooses: x − (−o) is the same operation as x + o).
    let off = ((k as f64) * FRAC_PI_2).copysign(x64);
    let a = if k == 5 { y } else { x64 - off };
    let q = if k == 5 {
        n
    } else if negative {
        (4 - k) & 3
    } else {
        k & 3
    };
    let (s, c) = (k_sin(a), k_cos(a));
    // Quadrant q: sin = [s, c, −s, −c][q], cos = [c, −s, −c, s][q]
    // (written as selects and sign flips so that the loop vectorises).
    let odd = q & 1 != 0;
    let sin = f32::from_bits(if odd { c } else { s }.to_bits() ^ ((q & 2) << 30));
    let cos = f32::from_bits(if odd { s } else { c }.to_bits() ^ (((q + 1) & 2) << 30));
    if ix < 0x3980_0000 {
        (x, 1.0)
    } else {
        (sin, cos)
    }
}

/// `sin[i] = sin x[i]`, `cos[i] = cos x[i]` with the pinned libm's bits in
/// both precisions: f32 runs [`sin_cos_f32`] in a vector loop (libm for the
/// rare `|x| ≥ 2²⁸·π/2`, infinities and NaN), f64 calls libm.
pub fn sin_cos_slices<T: Real>(x: &[T], sin: &mut [T], cos: &mut [T]) {
    assert!(
        sin.len() == x.len() && cos.len() == x.len(),
        "sin_cos_slices: sizes differ"
    );
    sin_cos_loop(x, sin, cos);
    if let (Some(sin), Some(cos)) = (T::as_f32_slice_mut(sin), T::as_f32_slice_mut(cos)) {
        for ((&v, s), c) in x.iter().zip(sin).zip(cos) {
            let v = v.to_f64() as f32; // exact: T is f32 here
            if v.to_bits() & 0x7fff_ffff >= 0x4dc9_0fdb {
                *s = libm::sinf(v);
                *c = libm::cosf(v);
            }
        }
    }
}

/// `e^x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn exp<T: Real>(x: T) -> T {
    x.per_precision(exp_f32, libm::exp)
}

/// `erf x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn erf<T: Real>(x: T) -> T {
    x.per_precision(erf_f32, libm::erf)
}

/// `tanh x` as the fields compute it: this module's f32 function, libm in f64.
#[inline(always)]
pub fn tanh<T: Real>(x: T) -> T {
    x.per_precision(tanh_f32, libm::tanh)
}

/// `sigmoid x` as the fields compute it: this module's f32 function,
/// `1/(1 + exp(−x))` with libm's exp in f64.
#[inline(always)]
pub fn sigmoid<T: Real>(x: T) -> T {
    x.per_precision(sigmoid_f32, Real::sigmoid)
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
                match $crate::kernels::fastmath::isa() {
                    // SAFETY: the CPU supports the feature (checked by isa()).
                    $crate::kernels::fastmath::Isa::Avx512 => return unsafe { avx512::<T>($($arg),*) },
                    $crate::kernels::fastmath::Isa::Avx2 => return unsafe { avx2::<T>($($arg),*) },
                    $crate::kernels::fastmath::Isa::Baseline => {}
                }
            }
            $body($($arg),*)
        }
    };
}
pub(crate) use multiversion;

multiversion!(fn sin_cos_loop<T: Real>(x: &[T], sin: &mut [T], cos: &mut [T]) => sin_cos_body);

#[inline(always)]
fn sin_cos_body<T: Real>(x: &[T], sin: &mut [T], cos: &mut [T]) {
    for ((&v, s), c) in x.iter().zip(sin.iter_mut()).zip(cos.iter_mut()) {
        (*s, *c) = v.per_precision_pair(sin_cos_f32, |v| (libm::sin(v), libm::cos(v)));
    }
}

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

    /// f32 inputs for the sin/cos checks: a stride through all 2³² bit
    /// patterns, every value within 3000 ulp of each range boundary of
    /// libm's sinf/cosf (both signs), and special values.
    fn sin_cos_inputs() -> Vec<f32> {
        let mut v: Vec<f32> = (0..=u32::MAX).step_by(4093).map(f32::from_bits).collect();
        for b in [
            0x3980_0000u32,
            0x3f49_0fda,
            0x4016_cbe3,
            0x407b_53d1,
            0x40af_eddf,
            0x40e2_31d5,
            0x4dc9_0fdb,
        ] {
            for bits in b - 3000..=b + 3000 {
                v.push(f32::from_bits(bits));
                v.push(-f32::from_bits(bits));
            }
        }
        v.extend([0.0, -0.0, f32::MIN_POSITIVE, 1e-45, f32::MAX, f32::INFINITY]);
        v.extend([f32::NEG_INFINITY, f32::NAN, 1.0, -1.0, 665.6, -1300.0]);
        v
    }

    fn assert_libm_sin_cos(xs: &[f32], sin: &[f32], cos: &[f32]) {
        for ((&x, s), c) in xs.iter().zip(sin).zip(cos) {
            assert_eq!(
                s.to_bits(),
                libm::sinf(x).to_bits(),
                "sin {x:e} ({:#x})",
                x.to_bits()
            );
            assert_eq!(
                c.to_bits(),
                libm::cosf(x).to_bits(),
                "cos {x:e} ({:#x})",
                x.to_bits()
            );
        }
    }

    #[test]
    fn sin_cos_gives_the_libm_bits() {
        let xs = sin_cos_inputs();
        // The scalar function, on its whole range.
        for &x in &xs {
            if x.to_bits() & 0x7fff_ffff < 0x4dc9_0fdb {
                let (s, c) = sin_cos_f32(std::hint::black_box(x));
                assert_libm_sin_cos(&[x], &[s], &[c]);
            }
        }
        // The vector loops on every path, huge and non-finite values included.
        for isa in [
            Some(Isa::Baseline),
            Some(Isa::Avx2),
            Some(Isa::Avx512),
            None,
        ] {
            if !force_isa(isa) {
                continue;
            }
            let (mut s, mut c) = (vec![0.0; xs.len()], vec![0.0; xs.len()]);
            sin_cos_slices(&xs, &mut s, &mut c);
            assert_libm_sin_cos(&xs, &s, &c);
        }
        force_isa(None);
        // f64 is libm's.
        let xd: Vec<f64> = xs.iter().map(|&x| x as f64 * 1.000_000_1).collect();
        let (mut s, mut c) = (vec![0.0; xd.len()], vec![0.0; xd.len()]);
        sin_cos_slices(&xd, &mut s, &mut c);
        for ((&x, s), c) in xd.iter().zip(&s).zip(&c) {
            assert_eq!(s.to_bits(), libm::sin(x).to_bits());
            assert_eq!(c.to_bits(), libm::cos(x).to_bits());
        }
    }

    /// Every one of the 2³² f32 values (a few minutes in release:
    /// `cargo test --release --lib -- --ignored sin_cos_every_f32`).
    #[test]
    #[ignore]
    fn sin_cos_every_f32() {
        use rayon::prelude::*;
        (0..=u16::MAX).into_par_iter().for_each(|hi| {
            let xs: Vec<f32> = (0..=u16::MAX)
                .map(|lo| f32::from_bits((hi as u32) << 16 | lo as u32))
                .collect();
            let (mut s, mut c) = (vec![0.0; xs.len()], vec![0.0; xs.len()]);
            sin_cos_slices(&xs, &mut s, &mut c);
            assert_libm_sin_cos(&xs, &s, &c);
        });
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
