//! The SE(3) warp of the 6-DoF D-3DGS MLP (docs/UPSTREAM.md §6.2, `is_6dof`), with
//! its vjp.
//!
//! From the two 3-wide heads `w = branch_w(h)` and `v = branch_v(h)`:
//! `θ = ‖w‖`, `w' = w/θ + 1e-5`, `v' = v/θ + 1e-5` (**upstream adds the 1e-5
//! after the division**, not to the denominator, so `w'` is not a unit
//! vector), `W = [w']×`, and
//! - `R = I + sin θ·W + (1 − cos θ)·W²`,
//! - `p = (θ·I + (1 − cos θ)·W + (θ − sin θ)·W²)·v'`.
//!
//! Upstream turns this into a 4×4 matrix and moves the canonical mean to
//! `R·x + p` (the rotation does not touch the Gaussian's orientation). Here
//! the field keeps its additive interface: `d_xyz = (R·x + p) − x`, so the
//! caller's `xyz + d_xyz` is upstream's deformed mean (to rounding). Because
//! upstream's `R·x` uses the canonical mean without stop-gradient, the
//! canonical mean also receives `(R − I)ᵀ·g` through the warp
//! ([`WarpGrad::x`], returned by [`Field::backward`](super::Field::backward)
//! as [`FieldGradients::xyz`](super::FieldGradients::xyz)), on top of the
//! identity path of `xyz + d_xyz`.
//!
//! **θ = 0.** Upstream divides 0 by 0 and returns NaN. Here, when `w` is
//! exactly zero, the warp takes its limit as θ → 0: `R = I` and `p = v` (the
//! raw `branch_v` output; `θ·(v/θ + 1e-5) → v` and the other terms vanish),
//! so `d_xyz = v`. Its gradient there is the gradient of the first-order
//! expansion `d_xyz ≈ v + w × (x + v/2) + ‖w‖·c` with
//! `c = 1e-5·(𝟙 + 𝟙 × (x + v/2))`, `𝟙 = (1, 1, 1)`: `∂/∂v = I`,
//! `∂/∂w · g = (x + v/2) × g`, taking 0 for the `‖w‖·c` term (it comes from
//! the 1e-5 offsets and has no derivative at 0; 0 is in its
//! subdifferential, and a central difference sees exactly this value
//! because the term is even in `w`).
//!
//! Evaluation order follows the PyTorch code: `W² = W·W` summed over k in
//! order; `R = (I + sin θ·W) + (1 − cos θ)·W²`; the 3×3 matrix of `p`
//! likewise; `R·x + p` summed over columns in order, then `+ p`.

use crate::math::vec::{cross, dot, frobenius, mat_mul, mat_t_vec, mat_vec, skew, transpose, Mat3};
use crate::math::Real;

/// The 1e-5 upstream adds to `w/θ` and `v/θ`.
pub const OFFSET: f64 = 1e-5;

/// Everything the forward computes for one Gaussian with θ ≠ 0.
struct Parts<T> {
    theta: T,
    sin: T,
    cos: T,
    v1: [T; 3],
    w: Mat3<T>,
    w2: Mat3<T>,
    r: Mat3<T>,
    a: Mat3<T>,
}

/// `None` when θ = 0 (the limit case).
fn parts<T: Real>(w: [T; 3], v: [T; 3]) -> Option<Parts<T>> {
    let theta = dot(w, w).sqrt();
    if theta == T::ZERO {
        return None;
    }
    let eps = T::from_f64(OFFSET);
    let w1 = w.map(|c| c / theta + eps);
    let v1 = v.map(|c| c / theta + eps);
    let (sin, cos) = (theta.sin(), theta.cos());
    let wm = skew(w1);
    let w2 = mat_mul(&wm, &wm);
    let mut r = [[T::ZERO; 3]; 3];
    let mut a = [[T::ZERO; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            let id = if i == j { T::ONE } else { T::ZERO };
            r[i][j] = (id + sin * wm[i][j]) + (T::ONE - cos) * w2[i][j];
            a[i][j] = (theta * id + (T::ONE - cos) * wm[i][j]) + (theta - sin) * w2[i][j];
        }
    }
    Some(Parts {
        theta,
        sin,
        cos,
        v1,
        w: wm,
        w2,
        r,
        a,
    })
}

/// Upstream's 4×4 transform `[[R, p], [0, 0, 0, 1]]` for one Gaussian
/// (row-major; `R = I`, `p = v` at θ = 0).
pub fn transform<T: Real>(w: [T; 3], v: [T; 3]) -> [[T; 4]; 4] {
    let (r, p) = match parts(w, v) {
        None => {
            let mut id = [[T::ZERO; 3]; 3];
            for (i, row) in id.iter_mut().enumerate() {
                row[i] = T::ONE;
            }
            (id, v)
        }
        Some(q) => (q.r, mat_vec(&q.a, q.v1)),
    };
    let mut m = [[T::ZERO; 4]; 4];
    for i in 0..3 {
        m[i][..3].copy_from_slice(&r[i]);
        m[i][3] = p[i];
    }
    m[3][3] = T::ONE;
    m
}

/// `d_xyz = R·x + p − x` for one Gaussian (`v` itself at θ = 0).
pub fn warp<T: Real>(w: [T; 3], v: [T; 3], x: [T; 3]) -> [T; 3] {
    match parts(w, v) {
        None => v,
        Some(q) => {
            let p = mat_vec(&q.a, q.v1);
            let rx = mat_vec(&q.r, x);
            [0, 1, 2].map(|i| (rx[i] + p[i]) - x[i])
        }
    }
}

/// Every gradient of one Gaussian's warp.
pub struct WarpGrad<T> {
    /// With respect to the `branch_w` output.
    pub w: [T; 3],
    /// With respect to the `branch_v` output.
    pub v: [T; 3],
    /// With respect to the canonical mean `x` through `R·x` (the explicit
    /// dependence of `d_xyz = R·x + p − x` on `x`, heads held fixed):
    /// `(R − I)ᵀ·g`, zero at θ = 0 where `R = I`.
    pub x: [T; 3],
}

/// vjp of [`warp`] with respect to `w`, `v` and `x`, given `g = ∂L/∂d_xyz`.
pub fn warp_vjp<T: Real>(w: [T; 3], v: [T; 3], x: [T; 3], g: [T; 3]) -> WarpGrad<T> {
    let Some(q) = parts(w, v) else {
        let half = T::from_f64(0.5);
        let a = [0, 1, 2].map(|i| x[i] + half * v[i]);
        return WarpGrad {
            w: cross(a, g),
            v: g,
            x: [T::ZERO; 3],
        };
    };
    // (R − I)ᵀ·g.
    let rtg = mat_t_vec(&q.r, g);
    let gx = [0, 1, 2].map(|j| rtg[j] - g[j]);
    // d_xyz = R x + A v' − x.
    let mut g_r = [[T::ZERO; 3]; 3];
    let mut g_a = [[T::ZERO; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            g_r[i][j] = g[i] * x[j];
            g_a[i][j] = g[i] * q.v1[j];
        }
    }
    let g_v1 = mat_t_vec(&q.a, g);
    // d⟨G, W·W⟩/dW = G·Wᵀ + Wᵀ·G.
    let wt = transpose(&q.w);
    let sq = |gm: &Mat3<T>| -> Mat3<T> {
        let (a, b) = (mat_mul(gm, &wt), mat_mul(&wt, gm));
        [0, 1, 2].map(|i| [0, 1, 2].map(|j| a[i][j] + b[i][j]))
    };
    let one_m_cos = T::ONE - q.cos;
    let t_m_sin = q.theta - q.sin;
    let (sq_r, sq_a) = (sq(&g_r), sq(&g_a));
    let mut g_w = [[T::ZERO; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            g_w[i][j] = q.sin * g_r[i][j]
                + one_m_cos * sq_r[i][j]
                + one_m_cos * g_a[i][j]
                + t_m_sin * sq_a[i][j];
        }
    }
    let trace_ga = g_a[0][0] + g_a[1][1] + g_a[2][2];
    let mut g_theta = q.cos * frobenius(&g_r, &q.w)
        + q.sin * frobenius(&g_r, &q.w2)
        + trace_ga
        + q.sin * frobenius(&g_a, &q.w)
        + one_m_cos * frobenius(&g_a, &q.w2);
    // W = skew(w').
    let g_w1 = [
        g_w[2][1] - g_w[1][2],
        g_w[0][2] - g_w[2][0],
        g_w[1][0] - g_w[0][1],
    ];
    // w' = w/θ + ε, v' = v/θ + ε.
    let th2 = q.theta * q.theta;
    let mut gw = [T::ZERO; 3];
    let mut gv = [T::ZERO; 3];
    for j in 0..3 {
        gw[j] = g_w1[j] / q.theta;
        gv[j] = g_v1[j] / q.theta;
        g_theta -= (g_w1[j] * w[j] + g_v1[j] * v[j]) / th2;
    }
    // θ = ‖w‖.
    for j in 0..3 {
        gw[j] += g_theta * (w[j] / q.theta);
    }
    WarpGrad {
        w: gw,
        v: gv,
        x: gx,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::cotangent;

    fn loss(w: [f64; 3], v: [f64; 3], x: [f64; 3], g: [f64; 3]) -> f64 {
        let d = warp(w, v, x);
        d[0] * g[0] + d[1] * g[1] + d[2] * g[2]
    }

    /// Fourth-order central difference of `f` along coordinate `k`.
    fn num(f: &dyn Fn([f64; 3]) -> f64, at: [f64; 3], k: usize, h: f64) -> f64 {
        let at_off = |o: f64| {
            let mut p = at;
            p[k] += o;
            f(p)
        };
        (8.0 * (at_off(h) - at_off(-h)) - (at_off(2.0 * h) - at_off(-2.0 * h))) / (12.0 * h)
    }

    fn rel(a: f64, b: f64) -> f64 {
        (a - b).abs() / a.abs().max(b.abs()).max(1e-3)
    }

    fn arr(v: &[f64]) -> [f64; 3] {
        [v[0], v[1], v[2]]
    }

    #[test]
    fn vjp_matches_central_differences() {
        for seed in 0..20u64 {
            let c = cotangent(100 + seed, 12);
            // |w| between ~0.2 and ~1.7: away from θ = 0.
            let w = arr(&c[0..3]).map(|v| v + 0.1f64.copysign(v));
            let (v, x, g) = (arr(&c[3..6]), arr(&c[6..9]), arr(&c[9..12]));
            let an = warp_vjp(w, v, x, g);
            for k in 0..3 {
                let nw = num(&|w| loss(w, v, x, g), w, k, 1e-4);
                let nv = num(&|v| loss(w, v, x, g), v, k, 1e-4);
                let nx = num(&|x| loss(w, v, x, g), x, k, 1e-4);
                let ax = an.x[k];
                assert!(
                    rel(an.w[k], nw) < 1e-8,
                    "seed {seed} w{k}: {} vs {nw}",
                    an.w[k]
                );
                assert!(
                    rel(an.v[k], nv) < 1e-8,
                    "seed {seed} v{k}: {} vs {nv}",
                    an.v[k]
                );
                assert!(rel(ax, nx) < 1e-8, "seed {seed} x{k}: {ax} vs {nx}");
            }
        }
    }

    #[test]
    fn theta_zero_is_the_finite_limit() {
        let (v, x, g) = ([0.3, -0.7, 0.2], [0.5, 0.1, -0.9], [0.4, -0.2, 0.8]);
        let d0 = warp([0.0; 3], v, x);
        assert_eq!(d0, v);
        // The limit from nearby θ agrees to first order in θ.
        for dir in [[1.0, 0.0, 0.0], [0.3, -0.5, 0.8], [-0.2, -0.9, 0.1]] {
            let w = dir.map(|c: f64| c * 1e-7);
            let d = warp(w, v, x);
            for k in 0..3 {
                assert!((d[k] - v[k]).abs() < 1e-6, "{d:?} vs {v:?}");
            }
        }
        // The defined gradient at 0 equals a central difference there (the
        // non-differentiable ‖w‖ term is even in w and cancels). Step 1e-3:
        // the 1e-5 offsets leave an O(step·1e-5) error from terms in ‖w‖²
        // that depend on the direction of w, and cancellation in
        // `1 − cos θ` an O(1e-16/step²) one.
        let an = warp_vjp([0.0; 3], v, x, g);
        for k in 0..3 {
            let nw = num(&|w| loss(w, v, x, g), [0.0; 3], k, 1e-3);
            let nv = num(&|v| loss([0.0; 3], v, x, g), v, k, 1e-4);
            assert!((an.w[k] - nw).abs() < 1e-8, "w{k}: {} vs {nw}", an.w[k]);
            assert!((an.v[k] - nv).abs() < 1e-8, "v{k}: {} vs {nv}", an.v[k]);
            assert!(an.w[k].is_finite() && an.v[k].is_finite());
        }
        assert_eq!(an.x, [0.0; 3]);
    }

    #[test]
    fn upstream_offset_is_added_after_the_division() {
        // w = (2, 0, 0): θ = 2, w' = (1 + 1e-5, 1e-5, 1e-5). With v = 0, x = 0:
        // p = A·v' with v' = (1e-5, 1e-5, 1e-5), so d_xyz = A·(1e-5·1).
        let d = warp([2.0, 0.0, 0.0], [0.0; 3], [0.0; 3]);
        let e = 1e-5;
        let w1 = [1.0 + e, e, e];
        let wm = skew(w1);
        let w2 = mat_mul(&wm, &wm);
        let (s, c) = (2.0f64.sin(), 2.0f64.cos());
        for i in 0..3 {
            let mut want = 0.0;
            for j in 0..3 {
                let id = if i == j { 1.0 } else { 0.0 };
                want += (2.0 * id + (1.0 - c) * wm[i][j] + (2.0 - s) * w2[i][j]) * e;
            }
            assert!((d[i] - want).abs() < 1e-18, "{d:?}");
        }
        // A rotation about x by θ = 2 (to the 1e-5 perturbation): x-axis fixed.
        let d = warp([2.0, 0.0, 0.0], [0.0; 3], [1.0, 0.0, 0.0]);
        assert!(d.iter().all(|v| v.abs() < 1e-4), "{d:?}");
        let d = warp([2.0, 0.0, 0.0], [0.0; 3], [0.0, 1.0, 0.0]);
        assert!(
            (d[1] - (c - 1.0)).abs() < 1e-4 && (d[2] - s).abs() < 1e-4,
            "{d:?}"
        );
    }
}
