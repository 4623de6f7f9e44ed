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
//! against libm in f64, in the tests of `kernels::fastmath`): `exp` ≤ 1 ulp, `tanh` ≤ 1 ulp,
//! `sigmoid` ≤ 2 ulp, `erf` ≤ 2 ulp for normal results (libm's own f32
//! functions are ≤ 1 ulp). A rounding difference of this size is far below
//! the f32 tolerance of the oracle comparisons with PyTorch.

// The polynomial coefficients are written as published (Cephes), with more
// digits than f32 holds; the compiler rounds each to the nearest f32.
#![allow(clippy::excessive_precision)]

/// Maximum error of [`exp_f32`] in ulp, asserted by the tests (see the
/// module docs).
pub const EXP_MAX_ULP: u32 = 1;
/// Maximum error of [`tanh_f32`] in ulp.
pub const TANH_MAX_ULP: u32 = 1;
/// Maximum error of [`sigmoid_f32`] in ulp.
pub const SIGMOID_MAX_ULP: u32 = 2;
/// Maximum error of [`erf_f32`] in ulp (normal results).
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
