//! 3D covariance `Σ = R S² Rᵀ` from a scale and an **unnormalised** quaternion,
//! and its vector-Jacobian product.
//!
//! Conventions (Inria `computeCov3D`):
//! - `q = (r, x, y, z)`, real part first, used as given (no normalisation), so
//!   `R(q)` is not orthogonal when `|q| ≠ 1`.
//! - `S = diag(modifier · s)`; `M = S Rᵀ`; `Σ = Mᵀ M`, element `(i, j)` summed
//!   over `k = 0, 1, 2` in order: `Σ_ij = Σ_k M_ki M_kj`.
//! - Stored as the upper triangle, row-major: `[Σ00, Σ01, Σ02, Σ11, Σ12, Σ22]`.
//! - Gradient convention for the stored slots: the gradient of an
//!   off-diagonal slot is the derivative with respect to the one scalar that
//!   fills both symmetric positions.
//!
//! Deviation from upstream, deliberate: the scale gradient is `d/ds` and
//! includes the factor `modifier` (upstream returns `d/d(modifier·s)`).

use crate::math::pack::Arith;
use crate::math::quat::{quat_to_rotmat, quat_to_rotmat_vjp};
use crate::math::Real;

/// `M = S Rᵀ` (math): `M_ij = s'_i R_ji`.
#[inline(always)]
fn m_matrix<N: Arith>(scale: [N; 3], modifier: N, rot: &[[N; 3]; 3]) -> ([N; 3], [[N; 3]; 3]) {
    let s = [
        modifier * scale[0],
        modifier * scale[1],
        modifier * scale[2],
    ];
    let mut m = [[N::ZERO; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = s[i] * rot[j][i];
        }
    }
    (s, m)
}

/// The 6 stored values of `Σ` for one Gaussian.
#[inline]
pub fn cov3d<T: Real>(scale: [T; 3], modifier: T, q: [T; 4]) -> [T; 6] {
    let rot = quat_to_rotmat(q);
    let (_, m) = m_matrix(scale, modifier, &rot);
    let e = |i: usize, j: usize| m[0][i] * m[0][j] + m[1][i] * m[1][j] + m[2][i] * m[2][j];
    [e(0, 0), e(0, 1), e(0, 2), e(1, 1), e(1, 2), e(2, 2)]
}

/// Eigen-decomposition of a symmetric 3×3 matrix by cyclic Jacobi rotations
/// (f64, a fixed sequence of operations: deterministic): eigenvalues `λ` and
/// the matrix `V` whose columns are the eigenvectors, `A = V diag(λ) Vᵀ`,
/// with `det V = +1`.
pub fn sym3_eigen(a: [[f64; 3]; 3]) -> ([f64; 3], [[f64; 3]; 3]) {
    let mut a = a;
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let mul = |x: &[[f64; 3]; 3], y: &[[f64; 3]; 3]| {
        let mut z = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                z[i][j] = x[i][0] * y[0][j] + x[i][1] * y[1][j] + x[i][2] * y[2][j];
            }
        }
        z
    };
    for _sweep in 0..64 {
        let off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        let diag = a[0][0] * a[0][0] + a[1][1] * a[1][1] + a[2][2] * a[2][2];
        if off == 0.0 || off <= 1e-36 * diag {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            // Numerical Recipes' rotation: zeroes a[p][q].
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = if theta.abs() > 1e150 {
                0.5 / theta
            } else {
                theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt())
            };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            let mut j = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
            j[p][p] = c;
            j[q][q] = c;
            j[p][q] = s;
            j[q][p] = -s;
            let mut jt = j;
            jt[p][q] = -s;
            jt[q][p] = s;
            a = mul(&mul(&jt, &a), &j);
            a[p][q] = 0.0;
            a[q][p] = 0.0;
            v = mul(&v, &j);
        }
    }
    let det = v[0][0] * (v[1][1] * v[2][2] - v[1][2] * v[2][1])
        - v[0][1] * (v[1][0] * v[2][2] - v[1][2] * v[2][0])
        + v[0][2] * (v[1][0] * v[2][1] - v[1][1] * v[2][0]);
    if det < 0.0 {
        for row in v.iter_mut() {
            row[2] = -row[2];
        }
    }
    ([a[0][0], a[1][1], a[2][2]], v)
}

/// The full symmetric 3×3 from the 6 stored values.
#[inline(always)]
pub fn sym3<T: Copy>(c: &[T; 6]) -> [[T; 3]; 3] {
    [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]]
}

/// Backward of [`cov3d`]: `(dL/dscale, dL/dq)` given the gradient of the 6
/// stored slots (off-diagonal slots: derivative w.r.t. the shared scalar).
/// On a [`crate::math::pack::Pack`], each lane is that Gaussian's result.
#[inline(always)]
pub fn cov3d_vjp<N: Arith>(
    scale: [N; 3],
    modifier: N,
    q: [N; 4],
    grad_cov: [N; 6],
) -> ([N; 3], [N; 4]) {
    let (gs, gq) = cov3d_vjp_scaled(scale, modifier, q, grad_cov);
    // (Written out, not `gs.map(..)`: a closure left out of line would run
    // without the caller's vector instruction set.)
    ([modifier * gs[0], modifier * gs[1], modifier * gs[2]], gq)
}

/// Backward of [`cov3d`] as upstream returns it: `(dL/d(modifier·scale),
/// dL/dq)`, i.e. the scale gradient without the factor `modifier`.
#[inline(always)]
pub fn cov3d_vjp_scaled<N: Arith>(
    scale: [N; 3],
    modifier: N,
    q: [N; 4],
    grad_cov: [N; 6],
) -> ([N; 3], [N; 4]) {
    let rot = quat_to_rotmat(q);
    let (s, m) = m_matrix(scale, modifier, &rot);
    // dΣ as a symmetric matrix whose entries are the per-position derivatives.
    let half = N::from_f64(0.5);
    let g = [
        [grad_cov[0], half * grad_cov[1], half * grad_cov[2]],
        [half * grad_cov[1], grad_cov[3], half * grad_cov[4]],
        [half * grad_cov[2], half * grad_cov[4], grad_cov[5]],
    ];
    // Σ = MᵀM  =>  dL/dM = M (G + Gᵀ) = 2 M G for symmetric G.
    let two = N::from_f64(2.0);
    let mut gm = [[N::ZERO; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            gm[i][j] = two * (m[i][0] * g[0][j] + m[i][1] * g[1][j] + m[i][2] * g[2][j]);
        }
    }
    // M_ij = s'_i R_ji
    let mut gs = [N::ZERO; 3];
    let mut gr = [[N::ZERO; 3]; 3];
    for i in 0..3 {
        gs[i] = gm[i][0] * rot[0][i] + gm[i][1] * rot[1][i] + gm[i][2] * rot[2][i];
        for j in 0..3 {
            gr[j][i] = s[i] * gm[i][j];
        }
    }
    (gs, quat_to_rotmat_vjp(q, gr))
}

#[cfg(test)]
mod decompose_tests {
    use super::*;
    use crate::math::quat::rotmat_to_quat;
    use crate::math::Rng;

    /// `Σ` of random non-unit quaternions and scales of both signs is
    /// recovered from its eigen-decomposition as a unit quaternion and
    /// positive scales.
    #[test]
    fn covariance_is_recovered_from_a_unit_quaternion_and_positive_scales() {
        let mut r = Rng::new(9);
        for k in 0..2000 {
            let q = [(); 4].map(|_| r.uniform_range(-1.5, 1.5));
            let mut s = [(); 3].map(|_| r.uniform_range(-0.5, 0.5));
            if k % 7 == 0 {
                s[1] = s[0]; // repeated eigenvalues
            }
            let c = cov3d(s, 1.0, q);
            let (lam, v) = sym3_eigen(sym3(&c));
            let u = rotmat_to_quat(v);
            let norm: f64 = u.iter().map(|x| x * x).sum::<f64>().sqrt();
            assert!((norm - 1.0).abs() < 1e-14 && u[0] >= 0.0);
            let s2 = lam.map(|l| l.max(0.0).sqrt());
            let c2 = cov3d(s2, 1.0, u);
            let scale = c.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            for (a, b) in c.iter().zip(&c2) {
                assert!((a - b).abs() <= 1e-12 * scale, "{k}: {c:?} vs {c2:?}");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};

    #[test]
    fn unit_quaternion_gives_r_s2_rt() {
        // 90° about z: x -> y. Σ = diag(s1², s0², s2²).
        let h = libm::sqrt(0.5);
        let c = cov3d([0.5f64, 2.0, 3.0], 1.0, [h, 0.0, 0.0, h]);
        assert!((c[0] - 4.0).abs() < 1e-12);
        assert!((c[3] - 0.25).abs() < 1e-12);
        assert!((c[5] - 9.0).abs() < 1e-12);
        assert!(c[1].abs() < 1e-12 && c[2].abs() < 1e-12 && c[4].abs() < 1e-12);
    }

    #[test]
    fn vjp_matches_finite_differences() {
        let g = cotangent(5, 6);
        let gc = [g[0], g[1], g[2], g[3], g[4], g[5]];
        let loss = |p: &[f64]| {
            let c = cov3d([p[0], p[1], p[2]], 1.7, [p[3], p[4], p[5], p[6]]);
            (0..6).map(|i| c[i] * gc[i]).sum::<f64>()
        };
        // Non-unit quaternion on purpose.
        let mut p = vec![0.3, 0.8, 0.05, 0.9, -0.4, 0.7, 0.2];
        let (gs, gq) = cov3d_vjp([p[0], p[1], p[2]], 1.7, [p[3], p[4], p[5], p[6]], gc);
        let num = numeric_gradient(&mut p, 1e-6, loss);
        let ana: Vec<f64> = gs.iter().chain(gq.iter()).copied().collect();
        let r = compare("cov3d", &ana, &num, 1e-6);
        assert!(r.passes(1e-7), "{r}");
    }
}
