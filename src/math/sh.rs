//! Real spherical harmonics colour (degrees 0 to 3) and its vector-Jacobian product.
//!
//! The colour of a Gaussian seen from the camera centre `campos` is
//! `max(Σ_k Y_k(dir)·sh_k + 0.5, 0)` per channel, with `dir = v / |v|` and
//! `v = mean − campos`. The constants, the basis polynomials and the strictly
//! left-to-right accumulation order are the Inria rasterizer's
//! (`computeColorFromSH`). There is no upper clamp; the lower clamp is recorded
//! per channel so the backward can zero the gradient of a clamped channel
//! (`result < 0`, strict: a result of exactly 0 keeps its gradient).
//!
//! Coefficients of one Gaussian are `[M, 3]` (coefficient-major, then channel),
//! where `M ≥ (degree + 1)²` is the per-Gaussian stride; coefficients above the
//! active degree are ignored and receive zero gradient.

use crate::math::pack::Arith;
use crate::math::Real;

/// Degree-0 constant.
pub const SH_C0: f64 = 0.28209479177387814;
/// Degree-1 constant.
pub const SH_C1: f64 = 0.4886025119029199;
/// Degree-2 constants.
pub const SH_C2: [f64; 5] = [
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
];
/// Degree-3 constants.
pub const SH_C3: [f64; 7] = [
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
];

/// Highest supported SH degree.
pub const MAX_SH_DEGREE: usize = 3;

/// Number of coefficients used by `degree`: `(degree + 1)²`.
pub const fn coeffs_for_degree(degree: usize) -> usize {
    (degree + 1) * (degree + 1)
}

/// Forward result of [`sh_to_color`]: what the backward needs besides the inputs.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShColorSaved<T> {
    /// `max(result, 0)` per channel.
    pub color: [T; 3],
    /// `result < 0` per channel (the gradient of such a channel is zero).
    pub clamped: [bool; 3],
}

/// Unit view direction `v / sqrt(v·v)` as the forward computes it.
#[inline(always)]
fn direction<N: Arith>(mean: [N; 3], campos: [N; 3]) -> ([N; 3], [N; 3]) {
    let v = [
        mean[0] - campos[0],
        mean[1] - campos[1],
        mean[2] - campos[2],
    ];
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    (v, [v[0] / n, v[1] / n, v[2] / n])
}

/// The 16 scalar basis factors `Y_k(dir)` exactly as the forward multiplies
/// them into the coefficients (`Y_k · sh_k`); entries above `degree` are 0.
#[inline(always)]
pub fn sh_basis<N: Arith>(degree: usize, dir: [N; 3]) -> [N; 16] {
    let c = |v: f64| N::from_f64(v);
    let [x, y, z] = dir;
    let mut b = [N::ZERO; 16];
    b[0] = c(SH_C0);
    if degree > 0 {
        // result - (C1 y) sh1 equals result + (-(C1 y)) sh1 bit for bit.
        b[1] = -(c(SH_C1) * y);
        b[2] = c(SH_C1) * z;
        b[3] = -(c(SH_C1) * x);
    }
    if degree > 1 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        let (xy, yz, xz) = (x * y, y * z, x * z);
        b[4] = c(SH_C2[0]) * xy;
        b[5] = c(SH_C2[1]) * yz;
        b[6] = c(SH_C2[2]) * (c(2.0) * zz - xx - yy);
        b[7] = c(SH_C2[3]) * xz;
        b[8] = c(SH_C2[4]) * (xx - yy);
        if degree > 2 {
            b[9] = c(SH_C3[0]) * y * (c(3.0) * xx - yy);
            b[10] = c(SH_C3[1]) * xy * z;
            b[11] = c(SH_C3[2]) * y * (c(4.0) * zz - xx - yy);
            b[12] = c(SH_C3[3]) * z * (c(2.0) * zz - c(3.0) * xx - c(3.0) * yy);
            b[13] = c(SH_C3[4]) * x * (c(4.0) * zz - xx - yy);
            b[14] = c(SH_C3[5]) * z * (xx - yy);
            b[15] = c(SH_C3[6]) * x * (xx - c(3.0) * yy);
        }
    }
    b
}

/// Partial derivatives of the basis factors with respect to the direction
/// components, `[d/dx, d/dy, d/dz]` per coefficient, treating x, y, z as
/// independent (the normalisation is chained separately).
#[inline(always)]
fn sh_basis_jacobian<N: Arith>(degree: usize, dir: [N; 3]) -> [[N; 3]; 16] {
    let c = |v: f64| N::from_f64(v);
    let [x, y, z] = dir;
    let z0 = N::ZERO;
    let mut d = [[z0; 3]; 16];
    if degree > 0 {
        d[1] = [z0, -c(SH_C1), z0];
        d[2] = [z0, z0, c(SH_C1)];
        d[3] = [-c(SH_C1), z0, z0];
    }
    if degree > 1 {
        let (xx, yy, zz) = (x * x, y * y, z * z);
        d[4] = [c(SH_C2[0]) * y, c(SH_C2[0]) * x, z0];
        d[5] = [z0, c(SH_C2[1]) * z, c(SH_C2[1]) * y];
        d[6] = [
            c(-2.0 * SH_C2[2]) * x,
            c(-2.0 * SH_C2[2]) * y,
            c(4.0 * SH_C2[2]) * z,
        ];
        d[7] = [c(SH_C2[3]) * z, z0, c(SH_C2[3]) * x];
        d[8] = [c(2.0 * SH_C2[4]) * x, c(-2.0 * SH_C2[4]) * y, z0];
        if degree > 2 {
            let (xy, yz, xz) = (x * y, y * z, x * z);
            d[9] = [
                c(SH_C3[0]) * c(6.0) * xy,
                c(SH_C3[0]) * c(3.0) * (xx - yy),
                z0,
            ];
            d[10] = [c(SH_C3[1]) * yz, c(SH_C3[1]) * xz, c(SH_C3[1]) * xy];
            d[11] = [
                c(SH_C3[2]) * c(-2.0) * xy,
                c(SH_C3[2]) * (c(4.0) * zz - xx - c(3.0) * yy),
                c(SH_C3[2]) * c(8.0) * yz,
            ];
            d[12] = [
                c(SH_C3[3]) * c(-6.0) * xz,
                c(SH_C3[3]) * c(-6.0) * yz,
                c(SH_C3[3]) * (c(6.0) * zz - c(3.0) * xx - c(3.0) * yy),
            ];
            d[13] = [
                c(SH_C3[4]) * (c(4.0) * zz - c(3.0) * xx - yy),
                c(SH_C3[4]) * c(-2.0) * xy,
                c(SH_C3[4]) * c(8.0) * xz,
            ];
            d[14] = [
                c(SH_C3[5]) * c(2.0) * xz,
                c(SH_C3[5]) * c(-2.0) * yz,
                c(SH_C3[5]) * (xx - yy),
            ];
            d[15] = [
                c(SH_C3[6]) * c(3.0) * (xx - yy),
                c(SH_C3[6]) * c(-6.0) * xy,
                z0,
            ];
        }
    }
    d
}

/// Colour of one Gaussian from its SH coefficients `coeffs` (`[M, 3]`, M ≥
/// (degree+1)²) seen from `campos`. The caller guarantees `degree ≤ 3` and
/// the slice length.
pub fn sh_to_color<T: Real>(
    degree: usize,
    coeffs: &[T],
    mean: [T; 3],
    campos: [T; 3],
) -> ShColorSaved<T> {
    sh_to_color_with(degree, |j| coeffs[j], mean, campos)
}

/// [`sh_to_color`] reading coefficient `j` of the `[M, 3]` layout (`3·k +
/// channel`) through `coeff`: the same operations in the same order. With
/// a constant `degree` it has no branches, so a loop over a batch of
/// Gaussians, each reading its coefficients from a transposed block, runs
/// it lane by lane in vector registers (the rasterizer's preprocessing does).
#[inline(always)]
pub fn sh_to_color_with<T: Real>(
    degree: usize,
    coeff: impl Fn(usize) -> T,
    mean: [T; 3],
    campos: [T; 3],
) -> ShColorSaved<T> {
    let (_, dir) = direction(mean, campos);
    let basis = sh_basis(degree, dir);
    let n = coeffs_for_degree(degree);
    let mut color = [T::ZERO; 3];
    let mut clamped = [false; 3];
    for ch in 0..3 {
        let mut r = basis[0] * coeff(ch);
        for (k, &b) in basis.iter().enumerate().take(n).skip(1) {
            r += b * coeff(3 * k + ch);
        }
        r += T::from_f64(0.5);
        clamped[ch] = r < T::ZERO;
        color[ch] = r.max(T::ZERO);
    }
    ShColorSaved { color, clamped }
}

/// Backward of [`sh_to_color`]: writes `dL/dcoeffs` (entries above the degree
/// are set to 0) and returns `dL/dmean` through the unnormalised view direction.
pub fn sh_to_color_vjp<T: Real>(
    degree: usize,
    coeffs: &[T],
    mean: [T; 3],
    campos: [T; 3],
    fwd: &ShColorSaved<T>,
    grad_color: [T; 3],
    grad_coeffs: &mut [T],
) -> [T; 3] {
    for x in grad_coeffs.iter_mut() {
        *x = T::ZERO;
    }
    color_vjp(
        degree,
        |j| coeffs[j],
        mean,
        campos,
        fwd.clamped,
        grad_color,
        |j, g| grad_coeffs[j] = g,
    )
}

/// [`sh_to_color_vjp`] on any [`Arith`] (on a
/// [`Pack`](crate::math::pack::Pack), one Gaussian per lane): `coeff(j)` is
/// coefficient slot `j` (`3·k + channel`), `clamped` the forward's
/// per-channel clamp. Calls `put(j, dL/dcoeff_j)` for the `3·(degree + 1)²`
/// used slots in ascending order and returns `dL/dmean`.
#[inline(always)]
#[allow(clippy::needless_range_loop)] // indices as in the formula
pub fn color_vjp<N: Arith>(
    degree: usize,
    coeff: impl Fn(usize) -> N,
    mean: [N; 3],
    campos: [N; 3],
    clamped: [N::Mask; 3],
    grad_color: [N; 3],
    mut put: impl FnMut(usize, N),
) -> [N; 3] {
    let (v, dir) = direction(mean, campos);
    let basis = sh_basis(degree, dir);
    let n = coeffs_for_degree(degree);
    let mut g = grad_color;
    for (gc, &clamped) in g.iter_mut().zip(&clamped) {
        *gc = N::select(clamped, N::ZERO, *gc);
    }
    for k in 0..n {
        for ch in 0..3 {
            put(3 * k + ch, basis[k] * g[ch]);
        }
    }
    if degree == 0 {
        return [N::ZERO; 3];
    }
    let jac = sh_basis_jacobian(degree, dir);
    let mut gdir = [N::ZERO; 3];
    for k in 1..n {
        let s = coeff(3 * k) * g[0] + coeff(3 * k + 1) * g[1] + coeff(3 * k + 2) * g[2];
        for a in 0..3 {
            gdir[a] += jac[k][a] * s;
        }
    }
    direction_vjp(v, gdir)
}

/// Backward of `dir = v / sqrt(v·v)`: `dL/dv = (s2·g − v (v·g)) / s2^{3/2}`.
#[inline(always)]
fn direction_vjp<N: Arith>(v: [N; 3], g: [N; 3]) -> [N; 3] {
    let s2 = v[0] * v[0] + v[1] * v[1] + v[2] * v[2];
    let inv = N::ONE / (s2 * s2.sqrt());
    let vg = v[0] * g[0] + v[1] * g[1] + v[2] * g[2];
    [
        (s2 * g[0] - v[0] * vg) * inv,
        (s2 * g[1] - v[1] * vg) * inv,
        (s2 * g[2] - v[2] * vg) * inv,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};

    #[test]
    fn degree_zero_is_c0_times_dc_plus_half() {
        let coeffs = [1.0f64, -2.0, 0.25];
        let r = sh_to_color(0, &coeffs, [1.0, 2.0, 3.0], [0.0; 3]);
        assert_eq!(r.color[0], SH_C0 * 1.0 + 0.5);
        assert_eq!(r.color[1], 0.0);
        assert!(r.clamped[1] && !r.clamped[0]);
        assert_eq!(r.color[2], SH_C0 * 0.25 + 0.5);
    }

    #[test]
    fn basis_is_orthonormal_on_the_sphere() {
        // Monte-Carlo-free check: a fixed quadrature (Fibonacci sphere) of Y_j Y_k.
        let n = 20000;
        let mut gram = [[0.0f64; 16]; 16];
        for i in 0..n {
            let z = 1.0 - (2.0 * i as f64 + 1.0) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = i as f64 * 2.399963229728653;
            let d = [r * libm::cos(phi), r * libm::sin(phi), z];
            let b = sh_basis(3, d);
            for (gj, &bj) in gram.iter_mut().zip(&b) {
                for (gjk, &bk) in gj.iter_mut().zip(&b) {
                    *gjk += bj * bk * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for (j, gj) in gram.iter().enumerate() {
            for (k, &gjk) in gj.iter().enumerate() {
                let want = if j == k { 1.0 } else { 0.0 };
                assert!((gjk - want).abs() < 2e-3, "({j},{k}) {gjk}");
            }
        }
    }

    #[test]
    fn vjp_matches_finite_differences() {
        for degree in 0..=3 {
            let m = 16;
            let coeffs0 = cotangent(10 + degree as u64, 3 * m);
            let mean0 = [0.4, -0.3, 1.7];
            let campos = [0.1, 0.2, -2.0];
            let g = cotangent(20 + degree as u64, 3);
            let fwd = sh_to_color(degree, &coeffs0, mean0, campos);
            let mut gc = vec![0.0; 3 * m];
            let gm = sh_to_color_vjp(
                degree,
                &coeffs0,
                mean0,
                campos,
                &fwd,
                [g[0], g[1], g[2]],
                &mut gc,
            );
            // Differences from the base colour keep the rounding of the loss small.
            let loss = |coeffs: &[f64], mean: [f64; 3]| {
                let r = sh_to_color(degree, coeffs, mean, campos);
                (0..3)
                    .map(|c| (r.color[c] - fwd.color[c]) * g[c])
                    .sum::<f64>()
            };
            let mut c = coeffs0.clone();
            // The colour is linear in the coefficients: a larger step has no
            // truncation error and less rounding noise.
            let nc = numeric_gradient(&mut c, 1e-3, |c| loss(c, mean0));
            let mut p = mean0.to_vec();
            let nm = numeric_gradient(&mut p, 1e-6, |p| loss(&coeffs0, [p[0], p[1], p[2]]));
            // Floor: 1e-3 of the largest entry (the finite-difference noise is ~1e-10 absolute).
            let floor = |v: &[f64]| 1e-3 * v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            let rc = compare("sh", &gc, &nc, floor(&nc));
            let rm = compare("mean", &gm, &nm, floor(&nm).max(1e-12));
            assert!(rc.passes(1e-7), "degree {degree}: {rc}");
            assert!(rm.passes(1e-7), "degree {degree}: {rm}");
        }
    }
}
