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
//! nothing else; f64 keeps the pinned libm of [`Real`](crate::math::Real) (it is the
//! gradient-check and reference precision). Why: libm's scalar `tanhf` costs
//! about 25 ns and cannot be vectorised; these cost about 1 ns per value in
//! 16-wide AVX-512 loops and made the CfC field several times faster.
//! Determinism is kept: each function is a fixed sequence of IEEE additions,
//! multiplications, divisions, comparisons, exact conversions and bit
//! operations (`abs`, `copysign`, building `2^k`), each correctly rounded or
//! exact, so a lane of an AVX-512, AVX2 or SSE2 loop and a scalar call give
//! the same bits. Rust never fuses `a*b + c` into an FMA.
//!
//! Algorithms:
//! - `exp` (the Cephes `expf` coefficients): `x` clamped to [−104, 89]
//!   (outside, the result is 0 or +∞ anyway), `k = round(x·log₂e)` (by
//!   adding and subtracting 1.5·2²³), `r = (x − k·ln2_hi) − k·ln2_lo`
//!   (Cody–Waite, `k·ln2_hi` exact), `e^r ≈ 1 + r + r²·P₅(r)`, scaled by
//!   `2^⌊k/2⌋·2^(k−⌊k/2⌋)` (two exact powers of two, so results in the
//!   subnormal range round once). NaN in, NaN out.
//! - `tanh`: `c·P₄(c²)/Q₄(c²)`, `c = x` clamped to [−9.1, 9.1];
//!   `erf`: `c·P₇(c²)/Q₄(c²)`, `c` clamped to [−4, 4]. One rational
//!   function over the whole range, no branch: about a third of the cost of
//!   the two-branch (polynomial near zero, `exp` beyond) Cephes forms they
//!   replaced, the CfC field's gate and GELUs being most of its element-wise
//!   work. The coefficients are minimax fits of the relative error made by
//!   `python/fit_fastmath.py` (2.3e-8 and 1.2e-8 before rounding); both
//!   functions are odd to the bit.
//! - `sigmoid(x) = 1/(1 + exp(−x))`.
//!
//! Accuracy against the correctly rounded value, measured against libm in
//! f64 on every f32 input (the ignored test `tanh_erf_every_f32`; every
//! test run checks a dense sweep and the worst inputs): `exp` ≤ 1 ulp,
//! `sigmoid` ≤ 2 ulp, `tanh` ≤ 6 ulp and `erf` ≤ 6 ulp (the rounding of
//! the f32 numerator and denominator, not the fit, sets these: 94% of
//! `tanh` values and 36% of `erf` values are correctly rounded, 99.9% of
//! both within 2 ulp). libm's own f32 functions are ≤ 1 ulp. Errors of this
//! size, a few parts in 10⁷, are far below the f32 tolerance of the oracle
//! comparisons with PyTorch.

// The coefficients are written with more digits than f32 holds (as
// published, or as the fitting script prints them); the compiler rounds each
// to the nearest f32.
#![allow(clippy::excessive_precision)]

/// Maximum error of [`exp_f32`] in ulp, asserted by the tests (see the
/// module docs).
pub const EXP_MAX_ULP: u32 = 1;
/// Maximum error of [`tanh_f32`] in ulp.
pub const TANH_MAX_ULP: u32 = 6;
/// Maximum error of [`sigmoid_f32`] in ulp.
pub const SIGMOID_MAX_ULP: u32 = 2;
/// Maximum error of [`erf_f32`] in ulp.
pub const ERF_MAX_ULP: u32 = 6;

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

/// `tanh x` in f32: `c·P(c²)/Q(c²)` with `c = x` clamped to [−9.1, 9.1]
/// (beyond, tanh x rounds to ±1).
#[inline(always)]
pub fn tanh_f32(x: f32) -> f32 {
    // python/fit_fastmath.py: P and Q of degree 4 in z = x², minimax
    // relative error 2.3e-8 before rounding.
    const P: [f32; 5] = [
        1.317_596_7e-8,
        2.048_006_7e-5,
        3.487_744_4e-3,
        1.337_442e-1,
        1.0,
    ];
    const Q: [f32; 5] = [
        7.703_409e-7,
        3.272_809_8e-4,
        2.584_713_7e-2,
        4.670_773_4e-1,
        1.0,
    ];
    odd_rational(x, 9.1, &P, &Q)
}

/// `c·P(c²)/Q(c²)` with `c = x` clamped to [−limit, limit], kept in [−1, 1].
/// The clamp keeps NaN; the quotient is odd in `c`, so `f(−x) = −f(x)`
/// exactly and `f(±0) = ±0`. Near ±1 the rounded quotient can exceed 1 by an
/// ulp: the last clamp keeps `|f| ≤ 1`.
#[inline(always)]
fn odd_rational(x: f32, limit: f32, p: &[f32], q: &[f32]) -> f32 {
    let c = x.clamp(-limit, limit);
    let z = c * c;
    (c * horner(z, p) / horner(z, q)).clamp(-1.0, 1.0)
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

/// `erf x` in f32: `c·P(c²)/Q(c²)` with `c = x` clamped to [−4, 4]
/// (beyond, erf x rounds to ±1).
#[inline(always)]
pub fn erf_f32(x: f32) -> f32 {
    // python/fit_fastmath.py: P of degree 7 and Q of degree 4 in z = x²,
    // minimax relative error 1.2e-8 before rounding.
    // The constant term is the fit's, close to 2/√π (erf′(0)) as it must be.
    #[allow(clippy::approx_constant)]
    const P: [f32; 8] = [
        -7.736_622_5e-10,
        7.669_391e-8,
        -3.558_293_2e-6,
        1.354_449e-4,
        1.703_451_7e-3,
        4.461_606_2e-2,
        1.444_96e-1,
        1.128_379_1,
    ];
    const Q: [f32; 5] = [
        5.773_71e-4,
        1.028_798_5e-2,
        9.333_867e-2,
        4.613_891_5e-1,
        1.0,
    ];
    odd_rational(x, 4.0, &P, &Q)
}

/// `1/(1 + e^{−x})` in f32.
#[inline(always)]
pub fn sigmoid_f32(x: f32) -> f32 {
    1.0 / (1.0 + exp_f32(-x))
}

/// `(sin x, cos x)` in f32, the same bits as the pinned libm's `sinf` and
/// `cosf` for `|x| < 2²⁸·π/2` (larger or non-finite `x`: see
/// [`crate::kernels::fastmath::sin_cos_slices`], which hands those to libm).
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
