//! Structural similarity (SSIM) as D-3DGS computes it (`utils/loss_utils.py`),
//! and its hand-written backward with respect to the first image.
//!
//! ## Definition (docs/UPSTREAM.md §6.7)
//! For each channel of a `[C, H, W]` image pair (x, y), with `*` a zero-padded
//! (pad 5), stride-1 correlation with the 11×11 window `w = g gᵀ`:
//!
//! ```text
//! μx = w*x   μy = w*y   σxx = w*(x²) − μx²   σyy = w*(y²) − μy²   σxy = w*(xy) − μx μy
//! S  = ((2 μx μy + C1)(2 σxy + C2)) / ((μx² + μy² + C1)(σxx + σyy + C2)),  C1 = 0.01², C2 = 0.03²
//! ```
//! and SSIM is the mean of S over channels and pixels.
//!
//! ## Window
//! `g_k ∝ exp(−(k − 5)² / (2·1.5²))`, k = 0..10. In f32 the window is the
//! upstream f32 values (stored bit-exactly in [`WINDOW_F32_BITS`]); a test
//! shows that they are what the formula gives when evaluated in f64, rounded
//! to f32 and normalised by the f32 sum. In f64 the same formula is evaluated
//! in f64 and normalised by the f64 sum (summed in index order).
//!
//! ## Evaluation order and determinism
//! The 2-D correlation is done separably: first along rows (taps k = 0..10 in
//! order, out-of-image taps skipped, which is what zero padding adds), then
//! along columns in the same way. Every output value is a fixed sequence of
//! roundings, so the result is the same for any thread count. It is **not**
//! bit-equal to PyTorch's `conv2d` with the 2-D window `g gᵀ` (which rounds
//! `g_a g_b` to f32 and sums 121 products in an order chosen by the
//! convolution backend, TF32 included on recent GPUs); the difference is a few
//! f32 ulp per value. The mean over pixels sums each row in column order and
//! then the row sums in row order.
//!
//! ## Backward
//! With `ḡ = dL/dSSIM / (C·H·W)` per pixel, `A1 = 2μxμy + C1`, `A2 = 2σxy + C2`,
//! `B1 = μx² + μy² + C1`, `B2 = σxx + σyy + C2`, `D = B1 B2`:
//!
//! ```text
//! dS/dμx      = 2μy (A2 − A1)/D − 2μx S (B2 − B1)/D      (through μx, σxx and σxy)
//! dS/d(w*x²)  = −S / B2
//! dS/d(w*xy)  = 2 A1 / D
//! dL/dx       = w*(ḡ dS/dμx) + 2x · w*(ḡ dS/d(w*x²)) + y · w*(ḡ dS/d(w*xy))
//! ```
//! The adjoint of a zero-padded correlation with a symmetric window is the
//! same zero-padded correlation, so the backward reuses [`blur`].

use crate::kernels::fastmath::multiversion;
use crate::math::Real;
use rayon::prelude::*;

/// Side of the square window.
pub const WINDOW_SIZE: usize = 11;
/// Zero padding on each side (`WINDOW_SIZE / 2`).
pub const PAD: usize = 5;
/// Standard deviation of the window, in pixels.
pub const SIGMA: f64 = 1.5;
/// `C1 = 0.01²` (as Python computes it, in f64).
pub const C1: f64 = 0.01 * 0.01;
/// `C2 = 0.03²` (as Python computes it, in f64).
pub const C2: f64 = 0.03 * 0.03;

/// Bits of the upstream f32 window (docs/UPSTREAM.md §6.7): 0x1.0d956cp-10,
/// 0x1.f1fe02p-8, 0x1.26eb18p-5, 0x1.bff0fep-4, 0x1.b43c3ep-3, 0x1.106560p-2,
/// then the mirror image.
pub const WINDOW_F32_BITS: [u32; WINDOW_SIZE] = [
    0x3a86cab6, 0x3bf8ff01, 0x3d13758c, 0x3ddff87f, 0x3e5a1e1f, 0x3e8832b0, 0x3e5a1e1f, 0x3ddff87f,
    0x3d13758c, 0x3bf8ff01, 0x3a86cab6,
];

/// Unnormalised window tap `exp(−(k − 5)² / (2σ²))` in f64 (pinned libm).
fn tap_f64(k: usize) -> f64 {
    let d = k as f64 - PAD as f64;
    libm::exp(-(d * d) / (2.0 * SIGMA * SIGMA))
}

/// The window in f64: taps in f64, normalised by their f64 sum (index order).
pub fn window_f64() -> [f64; WINDOW_SIZE] {
    let mut g = [0.0; WINDOW_SIZE];
    let mut sum = 0.0;
    for (k, v) in g.iter_mut().enumerate() {
        *v = tap_f64(k);
        sum += *v;
    }
    for v in g.iter_mut() {
        *v /= sum;
    }
    g
}

/// How the f32 taps are summed before normalising.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WindowSum {
    /// The f32 taps summed exactly (in f64, exact for these 11 values to well
    /// below an f32 ulp) and rounded to f32 once. Reproduces the upstream bits.
    RoundedOnce,
    /// A naive f32 sum in index order: 1 ulp below the rounded-once sum, which
    /// moves taps 0, 1, 3, 4 and 5 (and their mirrors) up by 1 ulp.
    SequentialF32,
}

/// The window evaluated as upstream does: taps in f64, rounded to f32, then
/// divided (in f32) by their f32 sum, summed as `sum` says. Used by a test to
/// show where [`WINDOW_F32_BITS`] come from; the f32 path uses the stored bits.
pub fn window_f32_from_formula(sum: WindowSum) -> [f32; WINDOW_SIZE] {
    let mut g = [0.0f32; WINDOW_SIZE];
    for (k, v) in g.iter_mut().enumerate() {
        *v = tap_f64(k) as f32;
    }
    let total = match sum {
        WindowSum::RoundedOnce => {
            let mut s = 0.0f64;
            for &v in &g {
                s += v as f64;
            }
            s as f32
        }
        WindowSum::SequentialF32 => {
            let mut s = 0.0f32;
            for &v in &g {
                s += v;
            }
            s
        }
    };
    for v in g.iter_mut() {
        *v /= total;
    }
    g
}

/// The 1-D window for precision `T`: the upstream f32 bits for f32, the f64
/// formula for f64.
pub fn window<T: Real>() -> [T; WINDOW_SIZE] {
    match T::PRECISION {
        crate::math::Precision::F32 => WINDOW_F32_BITS.map(|b| T::from_f32(f32::from_bits(b))),
        crate::math::Precision::F64 => window_f64().map(T::from_f64),
    }
}

/// Zero-padded separable correlation of every `[h, w]` plane of `src` with
/// the window `g` (rows first, then columns; taps in index order).
///
/// Both passes run across a row's pixels as vectors, each pixel adding its
/// in-image taps in index order from +0 (the row pass's first and last
/// `PAD` pixels, whose taps the edge cuts, one at a time).
///
/// # Panics
/// If `src` is not whole `[h, w]` planes (its length a multiple of `h·w`;
/// an empty `src`, or `h` or `w` zero, gives zeros).
pub fn blur<T: Real>(src: &[T], h: usize, w: usize, g: &[T; WINDOW_SIZE]) -> Vec<T> {
    if src.is_empty() || h == 0 || w == 0 {
        return vec![T::ZERO; src.len()];
    }
    assert_planes("blur", "src", src.len(), h, w);
    let tmp = super::par_rows(src.len(), w, |r, o| {
        blur_row(o, &src[r * w..(r + 1) * w], g)
    });
    let plane = h * w;
    super::par_rows(src.len(), w, |r, o| {
        let base = (r / h) * plane;
        blur_column_row(o, &tmp[base..base + plane], r % h, w, g);
    })
}

multiversion!(fn blur_row<T: Real>(o: &mut [T], s: &[T], g: &[T; WINDOW_SIZE]) => blur_row_body);

/// `o[j] = Σ_k g[k]·s[j + k − PAD]` over the taps inside the row, k
/// ascending from +0 (`o` is zero on entry).
#[inline(always)]
fn blur_row_body<T: Real>(o: &mut [T], s: &[T], g: &[T; WINDOW_SIZE]) {
    let w = s.len();
    let edge = |j: usize| {
        let k0 = PAD.saturating_sub(j);
        let k1 = WINDOW_SIZE.min(w + PAD - j);
        let mut acc = T::ZERO;
        for (k, &gk) in g.iter().enumerate().take(k1).skip(k0) {
            acc += gk * s[j + k - PAD];
        }
        acc
    };
    if w <= 2 * PAD {
        for (j, oj) in o.iter_mut().enumerate() {
            *oj = edge(j);
        }
        return;
    }
    // Pixels PAD..w−PAD see every tap: the k-th tap of pixel j is
    // s[j − PAD + k], so o[PAD..] gains g[k]·s[k..] for each k in turn.
    let inner = w - 2 * PAD;
    for (k, &gk) in g.iter().enumerate() {
        for (oj, &v) in o[PAD..PAD + inner].iter_mut().zip(&s[k..k + inner]) {
            *oj += gk * v;
        }
    }
    for j in (0..PAD).chain(w - PAD..w) {
        o[j] = edge(j);
    }
}

multiversion!(fn blur_column_row<T: Real>(o: &mut [T], plane: &[T], i: usize, w: usize, g: &[T; WINDOW_SIZE]) => blur_column_row_body);

/// Row `i` of the column pass over one `[h, w]` plane: `o[j] = Σ_k g[k]·
/// plane[i + k − PAD][j]` over the in-image taps, k ascending from +0 (`o`
/// is zero on entry).
#[inline(always)]
fn blur_column_row_body<T: Real>(
    o: &mut [T],
    plane: &[T],
    i: usize,
    w: usize,
    g: &[T; WINDOW_SIZE],
) {
    let h = plane.len() / w;
    let k0 = PAD.saturating_sub(i);
    let k1 = WINDOW_SIZE.min(h + PAD - i);
    for (k, &gk) in g.iter().enumerate().take(k1).skip(k0) {
        let row = &plane[(i + k - PAD) * w..][..w];
        for (oj, &v) in o.iter_mut().zip(row) {
            *oj += gk * v;
        }
    }
}

/// What the SSIM backward needs: the local statistics of every pixel.
#[derive(Clone, Debug)]
pub struct SsimSaved<T> {
    /// Mean of the SSIM map over channels and pixels.
    pub value: T,
    /// Image height, pixels.
    pub h: usize,
    /// Image width, pixels.
    pub w: usize,
    /// `w*x`, `[C, H, W]`.
    pub mu_x: Vec<T>,
    /// `w*y`.
    pub mu_y: Vec<T>,
    /// `w*(x²) − μx²`.
    pub sigma_xx: Vec<T>,
    /// `w*(y²) − μy²`.
    pub sigma_yy: Vec<T>,
    /// `w*(xy) − μx μy`.
    pub sigma_xy: Vec<T>,
}

/// The four factors of the SSIM map at one pixel: `(A1, A2, B1, B2)`.
#[inline(always)]
fn factors<T: Real>(mx: T, my: T, sxx: T, syy: T, sxy: T) -> (T, T, T, T) {
    let two = T::from_f64(2.0);
    let c1 = T::from_f64(C1);
    let c2 = T::from_f64(C2);
    let a1 = two * (mx * my) + c1;
    let a2 = two * sxy + c2;
    let b1 = (mx * mx + my * my) + c1;
    let b2 = (sxx + syy) + c2;
    (a1, a2, b1, b2)
}

/// Panics unless `len` values are whole `[h, w]` planes (none at all, or
/// `h, w > 0` and `len` a multiple of `h·w`).
fn assert_planes(f: &str, what: &str, len: usize, h: usize, w: usize) {
    let plane = h.checked_mul(w).filter(|&p| p > 0);
    assert!(
        len == 0 || plane.is_some_and(|p| len.is_multiple_of(p)),
        "ssim::{f}: {what} has {len} values, not a whole number of {h}x{w} planes"
    );
}

/// SSIM of `x` against `y`, both `[C, H, W]` with `C = x.len() / (h w)`
/// (see [`crate::loss::loss_and_grad`] for the checked entry point).
///
/// The element-wise passes run a row at a time across the row's pixels as
/// vectors; every value is the same sequence of roundings as the formulas
/// above, pixel by pixel.
///
/// # Panics
/// If `x.len() != y.len()`, or the length is not a whole number of
/// `[h, w]` planes (a multiple of `h·w > 0`; empty images are allowed).
pub fn ssim<T: Real>(x: &[T], y: &[T], h: usize, w: usize) -> SsimSaved<T> {
    assert!(
        x.len() == y.len(),
        "ssim::ssim: x has {} values and y {}",
        x.len(),
        y.len()
    );
    assert_planes("ssim", "x", x.len(), h, w);
    let g = window::<T>();
    let n = x.len();
    let row = w.max(1);
    let (mut xx, mut yy, mut xy) = (zeroed(n), zeroed(n), zeroed(n));
    (
        xx.par_chunks_mut(row),
        yy.par_chunks_mut(row),
        xy.par_chunks_mut(row),
        x.par_chunks(row),
        y.par_chunks(row),
    )
        .into_par_iter()
        .for_each(|(xx, yy, xy, x, y)| products_row(xx, yy, xy, x, y));
    let mu_x = blur(x, h, w, &g);
    let mu_y = blur(y, h, w, &g);
    let mut sigma_xx = blur(&xx, h, w, &g);
    let mut sigma_yy = blur(&yy, h, w, &g);
    let mut sigma_xy = blur(&xy, h, w, &g);
    let row_sums: Vec<T> = (
        sigma_xx.par_chunks_mut(row),
        sigma_yy.par_chunks_mut(row),
        sigma_xy.par_chunks_mut(row),
        mu_x.par_chunks(row),
        mu_y.par_chunks(row),
    )
        .into_par_iter()
        .map_init(Vec::new, |map, (sxx, syy, sxy, mx, my)| {
            map.clear();
            map.resize(mx.len(), T::ZERO);
            ssim_row(sxx, syy, sxy, mx, my, map);
            // The row's map values summed in column order.
            let mut s = T::ZERO;
            for &v in map.iter() {
                s += v;
            }
            s
        })
        .collect();
    let mut total = T::ZERO;
    for s in row_sums {
        total += s;
    }
    let value = if n == 0 {
        T::ZERO
    } else {
        total / T::from_usize(n)
    };
    SsimSaved {
        value,
        h,
        w,
        mu_x,
        mu_y,
        sigma_xx,
        sigma_yy,
        sigma_xy,
    }
}

multiversion!(fn products_row<T: Real>(xx: &mut [T], yy: &mut [T], xy: &mut [T], x: &[T], y: &[T]) => products_row_body);

/// `x²`, `y²` and `xy` of one row.
#[inline(always)]
fn products_row_body<T: Real>(xx: &mut [T], yy: &mut [T], xy: &mut [T], x: &[T], y: &[T]) {
    for (v, &a) in xx.iter_mut().zip(x) {
        *v = a * a;
    }
    for (v, &b) in yy.iter_mut().zip(y) {
        *v = b * b;
    }
    for ((v, &a), &b) in xy.iter_mut().zip(x).zip(y) {
        *v = a * b;
    }
}

multiversion!(fn ssim_row<T: Real>(sxx: &mut [T], syy: &mut [T], sxy: &mut [T], mx: &[T], my: &[T], map: &mut [T]) => ssim_row_body);

/// One row: the blurred squares and product become the (co)variances
/// (`σ = w*(··) − μ·μ`), and `map` receives the SSIM map.
#[inline(always)]
fn ssim_row_body<T: Real>(
    sxx: &mut [T],
    syy: &mut [T],
    sxy: &mut [T],
    mx: &[T],
    my: &[T],
    map: &mut [T],
) {
    for (((sxx, syy), sxy), (&mx, &my)) in sxx
        .iter_mut()
        .zip(syy.iter_mut())
        .zip(sxy.iter_mut())
        .zip(mx.iter().zip(my))
    {
        *sxx -= mx * mx;
        *syy -= my * my;
        *sxy -= mx * my;
    }
    for (((((m, &mx), &my), &sxx), &syy), &sxy) in map
        .iter_mut()
        .zip(mx)
        .zip(my)
        .zip(sxx.iter())
        .zip(syy.iter())
        .zip(sxy.iter())
    {
        let (a1, a2, b1, b2) = factors(mx, my, sxx, syy, sxy);
        *m = (a1 * a2) / (b1 * b2);
    }
}

/// Backward of [`ssim`] with respect to `x`: `dL/dx` given `grad_out = dL/dSSIM`.
///
/// # Panics
/// If `fwd` is not [`ssim`]'s result for images of the size of `x` and `y`
/// (every length equal, a whole number of `[fwd.h, fwd.w]` planes).
pub fn ssim_vjp<T: Real>(fwd: &SsimSaved<T>, x: &[T], y: &[T], grad_out: T) -> Vec<T> {
    let n = x.len();
    let lens = [
        y.len(),
        fwd.mu_x.len(),
        fwd.mu_y.len(),
        fwd.sigma_xx.len(),
        fwd.sigma_yy.len(),
        fwd.sigma_xy.len(),
    ];
    assert!(
        lens.iter().all(|&l| l == n),
        "ssim::ssim_vjp: x has {n} values, y and the saved statistics {lens:?}"
    );
    assert_planes("ssim_vjp", "x", n, fwd.h, fwd.w);
    if n == 0 {
        return vec![];
    }
    let gbar = grad_out / T::from_usize(n);
    let row = fwd.w.max(1);
    let (mut d_mu, mut d_xx, mut d_xy) = (zeroed(n), zeroed(n), zeroed(n));
    (
        d_mu.par_chunks_mut(row),
        d_xx.par_chunks_mut(row),
        d_xy.par_chunks_mut(row),
        (
            fwd.mu_x.par_chunks(row),
            fwd.mu_y.par_chunks(row),
            fwd.sigma_xx.par_chunks(row),
            fwd.sigma_yy.par_chunks(row),
            fwd.sigma_xy.par_chunks(row),
        ),
    )
        .into_par_iter()
        .for_each(|(dm, dxx, dxy, stats)| map_vjp_row(dm, dxx, dxy, stats, gbar));
    let g = window::<T>();
    let (h, w) = (fwd.h, fwd.w);
    let b_mu = blur(&d_mu, h, w, &g);
    let b_xx = blur(&d_xx, h, w, &g);
    let b_xy = blur(&d_xy, h, w, &g);
    let mut grad = zeroed(n);
    (
        grad.par_chunks_mut(row),
        b_mu.par_chunks(row),
        b_xx.par_chunks(row),
        b_xy.par_chunks(row),
        (x.par_chunks(row), y.par_chunks(row)),
    )
        .into_par_iter()
        .for_each(|(gx, bm, bxx, bxy, (x, y))| input_vjp_row(gx, bm, bxx, bxy, x, y));
    grad
}

/// `n` zeros, written in parallel.
fn zeroed<T: Real>(n: usize) -> Vec<T> {
    super::par_rows(n, 4096, |_, _| {})
}

/// One row of the five statistics `(μx, μy, σxx, σyy, σxy)`.
type Stats<'a, T> = (&'a [T], &'a [T], &'a [T], &'a [T], &'a [T]);

multiversion!(fn map_vjp_row<T: Real>(dm: &mut [T], dxx: &mut [T], dxy: &mut [T], stats: Stats<'_, T>, gbar: T) => map_vjp_row_body);

/// One row of `ḡ·dS/dμx`, `ḡ·dS/d(w*x²)` and `ḡ·dS/d(w*xy)` (module docs).
#[inline(always)]
fn map_vjp_row_body<T: Real>(
    dm: &mut [T],
    dxx: &mut [T],
    dxy: &mut [T],
    (mu_x, mu_y, sigma_xx, sigma_yy, sigma_xy): Stats<'_, T>,
    gbar: T,
) {
    let two = T::from_f64(2.0);
    for ((((((dm, dxx), dxy), &mx), &my), (&sxx, &syy)), &sxy) in dm
        .iter_mut()
        .zip(dxx.iter_mut())
        .zip(dxy.iter_mut())
        .zip(mu_x)
        .zip(mu_y)
        .zip(sigma_xx.iter().zip(sigma_yy))
        .zip(sigma_xy)
    {
        let (a1, a2, b1, b2) = factors(mx, my, sxx, syy, sxy);
        let d = b1 * b2;
        let s = (a1 * a2) / d;
        *dm = gbar * ((two * my * (a2 - a1)) / d - (two * mx * s * (b2 - b1)) / d);
        *dxx = gbar * (-s / b2);
        *dxy = gbar * ((two * a1) / d);
    }
}

multiversion!(fn input_vjp_row<T: Real>(gx: &mut [T], b_mu: &[T], b_xx: &[T], b_xy: &[T], x: &[T], y: &[T]) => input_vjp_row_body);

/// One row of `dL/dx = w*(ḡ dS/dμx) + 2x · w*(ḡ dS/d(w*x²)) + y · w*(ḡ dS/d(w*xy))`.
#[inline(always)]
fn input_vjp_row_body<T: Real>(gx: &mut [T], b_mu: &[T], b_xx: &[T], b_xy: &[T], x: &[T], y: &[T]) {
    let two = T::from_f64(2.0);
    for (((((gx, &bm), &bxx), &bxy), &x), &y) in
        gx.iter_mut().zip(b_mu).zip(b_xx).zip(b_xy).zip(x).zip(y)
    {
        *gx = bm + two * x * bxx + y * bxy;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, numeric_gradient};
    use crate::math::Rng;

    /// Parse a C99 hex float literal such as `0x1.0d956cp-10` (test-only,
    /// so the constants can be checked against the text of the spec).
    fn parse_hex_float(s: &str) -> f64 {
        let s = s.strip_prefix("0x").unwrap();
        let (mant, exp) = s.split_once('p').unwrap();
        let (int, frac) = mant.split_once('.').unwrap();
        let mut v = u64::from_str_radix(int, 16).unwrap() as f64;
        let mut scale = 1.0 / 16.0;
        for c in frac.chars() {
            v += c.to_digit(16).unwrap() as f64 * scale;
            scale /= 16.0;
        }
        v * libm::pow(2.0, exp.parse::<f64>().unwrap())
    }

    #[test]
    fn f32_window_is_the_upstream_hex_and_the_formula() {
        let hex = [
            "0x1.0d956cp-10",
            "0x1.f1fe02p-8",
            "0x1.26eb18p-5",
            "0x1.bff0fep-4",
            "0x1.b43c3ep-3",
            "0x1.106560p-2",
        ];
        let stored = window::<f32>();
        for (k, s) in hex.iter().enumerate() {
            let v = parse_hex_float(s) as f32;
            assert_eq!(stored[k].to_bits(), v.to_bits(), "tap {k}");
            assert_eq!(
                stored[10 - k].to_bits(),
                v.to_bits(),
                "mirror tap {}",
                10 - k
            );
        }
        // The formula evaluated as upstream (f64 exp, rounded to f32, divided
        // in f32 by the correctly rounded f32 sum) gives exactly the stored bits.
        let formula = window_f32_from_formula(WindowSum::RoundedOnce);
        for k in 0..WINDOW_SIZE {
            assert_eq!(formula[k].to_bits(), stored[k].to_bits(), "tap {k}");
        }
        // A naive sequential f32 sum is where the last bit would differ: the
        // sum is 1 ulp lower and taps 0, 1, 3, 4, 5 come out 1 ulp higher.
        let naive = window_f32_from_formula(WindowSum::SequentialF32);
        for k in 0..WINDOW_SIZE {
            let d = naive[k].to_bits() as i64 - stored[k].to_bits() as i64;
            let want = if k == 2 || k == 8 { 0 } else { 1 };
            assert_eq!(d, want, "tap {k}");
        }
    }

    #[test]
    fn f64_window_is_normalised_and_close_to_f32() {
        let g = window::<f64>();
        let s: f64 = g.iter().sum();
        assert!((s - 1.0).abs() < 1e-15);
        let g32 = window::<f32>();
        for k in 0..WINDOW_SIZE {
            assert!((g[k] - g32[k] as f64).abs() < 1e-8, "tap {k}");
            assert_eq!(g[k], g[10 - k]);
        }
    }

    /// Direct (non-separable) zero-padded 2-D correlation in f64: the plain
    /// reference for `blur`.
    fn blur_direct(src: &[f64], h: usize, w: usize) -> Vec<f64> {
        let g = window_f64();
        let mut out = vec![0.0; src.len()];
        for p in 0..src.len() / (h * w) {
            for i in 0..h {
                for j in 0..w {
                    let mut acc = 0.0;
                    for a in 0..WINDOW_SIZE {
                        for b in 0..WINDOW_SIZE {
                            let (ii, jj) = (i as i64 + a as i64 - 5, j as i64 + b as i64 - 5);
                            if ii >= 0 && jj >= 0 && (ii as usize) < h && (jj as usize) < w {
                                acc += g[a] * g[b] * src[p * h * w + ii as usize * w + jj as usize];
                            }
                        }
                    }
                    out[p * h * w + i * w + j] = acc;
                }
            }
        }
        out
    }

    fn random_image(seed: u64, n: usize) -> Vec<f64> {
        let mut r = Rng::new(seed);
        (0..n).map(|_| r.uniform()).collect()
    }

    /// The blur as defined in the module docs, one pixel at a time: taps in
    /// index order from +0, out-of-image taps skipped.
    fn blur_serial<T: Real>(src: &[T], h: usize, w: usize) -> Vec<T> {
        let g = window::<T>();
        let mut tmp = vec![T::ZERO; src.len()];
        for (o, s) in tmp.chunks_mut(w).zip(src.chunks(w)) {
            for (j, oj) in o.iter_mut().enumerate() {
                let mut acc = T::ZERO;
                for (k, &gk) in g.iter().enumerate() {
                    if (PAD..w + PAD).contains(&(j + k)) {
                        acc += gk * s[j + k - PAD];
                    }
                }
                *oj = acc;
            }
        }
        let mut out = vec![T::ZERO; src.len()];
        for (p, o) in out.iter_mut().enumerate() {
            let (c, i, j) = (p / (h * w), (p / w) % h, p % w);
            let mut acc = T::ZERO;
            for (k, &gk) in g.iter().enumerate() {
                if (PAD..h + PAD).contains(&(i + k)) {
                    acc += gk * tmp[c * h * w + (i + k - PAD) * w + j];
                }
            }
            *o = acc;
        }
        out
    }

    /// Images with negative values, exact zeros and negative zeros.
    fn signed_image(seed: u64, n: usize) -> Vec<f32> {
        let mut r = Rng::new(seed);
        (0..n)
            .map(|i| match i % 7 {
                3 => 0.0,
                5 => -0.0,
                _ => (r.uniform() - 0.5) as f32,
            })
            .collect()
    }

    #[test]
    fn blur_has_the_bits_of_the_serial_definition_on_every_path() {
        let _isa = crate::kernels::fastmath::isa_test_lock();
        use crate::kernels::fastmath::{force_isa, Isa};
        let g = window::<f32>();
        for &(h, w) in &[
            (1, 1),
            (3, 4),
            (7, 10),
            (13, 11),
            (12, 12),
            (5, 23),
            (11, 37),
        ] {
            let x = signed_image((h * 100 + w) as u64, 2 * h * w);
            let want: Vec<u32> = blur_serial(&x, h, w).iter().map(|v| v.to_bits()).collect();
            let x64: Vec<f64> = x.iter().map(|&v| v as f64 * 1.000_000_1).collect();
            let want64: Vec<u64> = blur_serial(&x64, h, w)
                .iter()
                .map(|v| v.to_bits())
                .collect();
            for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
                if force_isa(Some(isa)) {
                    let got: Vec<u32> = blur(&x, h, w, &g).iter().map(|v| v.to_bits()).collect();
                    assert_eq!(got, want, "{h}x{w} on {isa:?}");
                    let got: Vec<u64> = blur(&x64, h, w, &window::<f64>())
                        .iter()
                        .map(|v| v.to_bits())
                        .collect();
                    assert_eq!(got, want64, "{h}x{w} on {isa:?}, f64");
                }
            }
            force_isa(None);
        }
    }

    #[test]
    fn ssim_and_its_gradient_have_the_same_bits_on_every_path() {
        let _isa = crate::kernels::fastmath::isa_test_lock();
        use crate::kernels::fastmath::{force_isa, Isa};
        let (h, w) = (19, 27);
        let x = signed_image(21, 3 * h * w);
        let y = signed_image(22, 3 * h * w);
        let run = || {
            let f = ssim(&x, &y, h, w);
            let g = ssim_vjp(&f, &x, &y, 0.7f32);
            let (l, gl) = crate::loss::loss_and_grad(&x, &y, h, w, 0.2).unwrap();
            (
                f.value.to_bits(),
                g.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                l.loss.to_bits(),
                gl.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            )
        };
        force_isa(Some(Isa::Baseline));
        let want = run();
        for isa in [Isa::Avx2, Isa::Avx512] {
            if force_isa(Some(isa)) {
                assert!(run() == want, "{isa:?} differs from the baseline");
            }
        }
        force_isa(None);
    }

    #[test]
    fn separable_blur_matches_direct_correlation() {
        let (h, w) = (9, 14);
        let x = random_image(5, 2 * h * w);
        let a = blur(&x, h, w, &window_f64());
        let b = blur_direct(&x, h, w);
        for (p, (u, v)) in a.iter().zip(&b).enumerate() {
            assert!((u - v).abs() < 1e-14, "pixel {p}: {u} vs {v}");
        }
    }

    /// SSIM written out pixel by pixel from the definition, in f64.
    fn ssim_reference(x: &[f64], y: &[f64], h: usize, w: usize) -> f64 {
        let sq = |v: &[f64]| v.iter().map(|a| a * a).collect::<Vec<_>>();
        let prod: Vec<f64> = x.iter().zip(y).map(|(a, b)| a * b).collect();
        let (mx, my) = (blur_direct(x, h, w), blur_direct(y, h, w));
        let (exx, eyy, exy) = (
            blur_direct(&sq(x), h, w),
            blur_direct(&sq(y), h, w),
            blur_direct(&prod, h, w),
        );
        let mut s = 0.0;
        for p in 0..x.len() {
            let (sx, sy, sxy) = (
                exx[p] - mx[p] * mx[p],
                eyy[p] - my[p] * my[p],
                exy[p] - mx[p] * my[p],
            );
            s += ((2.0 * mx[p] * my[p] + C1) * (2.0 * sxy + C2))
                / ((mx[p] * mx[p] + my[p] * my[p] + C1) * (sx + sy + C2));
        }
        s / x.len() as f64
    }

    #[test]
    fn ssim_matches_reference_and_is_one_on_equal_images() {
        let (h, w) = (12, 10);
        let x = random_image(1, 3 * h * w);
        let y = random_image(2, 3 * h * w);
        let s = ssim(&x, &y, h, w).value;
        let r = ssim_reference(&x, &y, h, w);
        assert!((s - r).abs() < 1e-13, "{s} vs {r}");
        assert!(s < 0.5);
        let same = ssim(&x, &x, h, w).value;
        assert!((same - 1.0).abs() < 1e-14, "{same}");
    }

    #[test]
    fn ssim_gradient_matches_finite_differences() {
        let (h, w) = (13, 11);
        let x0 = random_image(3, 3 * h * w);
        // y correlated with x so that the SSIM is neither ~0 nor ~1.
        let noise = random_image(4, 3 * h * w);
        let y: Vec<f64> = x0
            .iter()
            .zip(&noise)
            .map(|(a, b)| 0.6 * a + 0.4 * b)
            .collect();
        let scale = 1.7;
        let fwd = ssim(&x0, &y, h, w);
        let ga = ssim_vjp(&fwd, &x0, &y, scale);
        // Step 1e-4: the SSIM is a mean of ~400 rounded terms, so with h = 1e-6
        // the f64 rounding noise of the difference quotient (~1e-16/h) is
        // already ~1e-10, comparable to the smallest entries checked; the
        // truncation error at 1e-4 is O(h²) (measured: the error falls 100x
        // from h = 1e-3 to 1e-4, then rises again as 1/h below 1e-5).
        let mut x = x0.clone();
        let gn = numeric_gradient(&mut x, 1e-4, |x| scale * ssim(x, &y, h, w).value);
        let floor = 1e-3 * gn.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let r = compare("ssim dx", &ga, &gn, floor);
        assert!(r.passes(1e-6), "{r}");
    }

    #[test]
    fn ssim_is_identical_for_any_thread_count() {
        let (h, w) = (31, 23);
        let x: Vec<f32> = random_image(8, 3 * h * w)
            .iter()
            .map(|&v| v as f32)
            .collect();
        let y: Vec<f32> = random_image(9, 3 * h * w)
            .iter()
            .map(|&v| v as f32)
            .collect();
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let f = ssim(&x, &y, h, w);
                let g = ssim_vjp(&f, &x, &y, 1.0f32);
                (
                    f.value.to_bits(),
                    g.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                )
            })
        };
        let one = run(1);
        assert_eq!(one, run(3));
        assert_eq!(one, run(8));
    }

    #[test]
    #[should_panic(expected = "ssim::blur: src has 10 values, not a whole number of 2x3 planes")]
    fn blur_of_a_partial_plane_panics() {
        blur(&[0.0f32; 10], 2, 3, &window());
    }

    #[test]
    #[should_panic(expected = "ssim::ssim: x has 10 values, not a whole number of 2x3 planes")]
    fn ssim_of_a_partial_plane_panics() {
        ssim(&[0.0f32; 10], &[0.0; 10], 2, 3);
    }

    #[test]
    #[should_panic(expected = "ssim::ssim: x has 12 values and y 6")]
    fn ssim_of_mismatched_lengths_panics() {
        ssim(&[0.0f32; 12], &[0.0; 6], 2, 3);
    }

    #[test]
    #[should_panic(expected = "ssim::ssim_vjp: x has 12 values, y and the saved statistics")]
    fn ssim_vjp_with_statistics_of_another_size_panics() {
        let fwd = ssim(&[0.5f32; 6], &[0.25; 6], 2, 3);
        ssim_vjp(&fwd, &[0.5; 12], &[0.25; 12], 1.0);
    }

    #[test]
    #[should_panic(expected = "ssim::ssim_vjp: x has 6 values, not a whole number of 2x4 planes")]
    fn ssim_vjp_with_another_image_size_panics() {
        let mut fwd = ssim(&[0.5f32; 6], &[0.25; 6], 2, 3);
        fwd.w = 4;
        ssim_vjp(&fwd, &[0.5; 6], &[0.25; 6], 1.0);
    }
}
