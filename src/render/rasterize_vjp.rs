//! Per-pixel backward of the blending ([`super::rasterize`]).
//!
//! For a pixel with blended entries `i = 0..n` (front to back), transmittance
//! `T_i = Π_{j<i} (1 − α_j)` and per-entry weight `w_i = g·c_i + g_D·z_i`
//! (`g`, `g_D` the incoming colour and depth gradients):
//! `dL/dα_i = T_i·(w_i − R_i)` with `R_{n−1} = g·bg` and
//! `R_{i−1} = α_i·w_i + (1 − α_i)·R_i`. The transmittances are recomputed by
//! the same products as the forward (same bits), never recovered by division.
//! Through `α = min(0.99, o·G)` the gradient is zero where the clamp is active.
//!
//! Determinism: each tile accumulates the contributions of its pixels, in
//! row-major pixel order, into a buffer indexed by list position; per-Gaussian
//! sums are formed afterwards in ascending list position (ascending tile).

use super::rasterize::{evaluate, Blend, Hit, Splat, Step};
use super::GradientMode;
use crate::math::Real;

/// Per list entry gradient: colour (3), pixel centre (2), conic (3),
/// opacity (1), depth (1).
pub(crate) type EntryGrad<T> = [T; 10];

/// Backward of one tile. `grads` has one slot per list entry of the tile and
/// is accumulated into.
#[allow(clippy::too_many_arguments)]
pub(crate) fn tile_vjp<T: Real>(
    splats: &[Splat<T>],
    bounds: [usize; 4],
    width: usize,
    height: usize,
    bg: [T; 3],
    grad_color: &[T],
    grad_depth: Option<&[T]>,
    k: &Blend<T>,
    mode: GradientMode,
    grads: &mut [EntryGrad<T>],
) {
    match mode {
        GradientMode::Exact => {}
    }
    let [x0, x1, y0, y1] = bounds;
    let hw = width * height;
    let mut hits: Vec<(usize, Hit<T>, T)> = Vec::with_capacity(splats.len());
    let half = T::from_f64(0.5);
    for py in y0..y1 {
        for px in x0..x1 {
            let pix = py * width + px;
            let g = [
                grad_color[pix],
                grad_color[hw + pix],
                grad_color[2 * hw + pix],
            ];
            let gd = grad_depth.map_or(T::ZERO, |d| d[pix]);
            let pxf = T::from_usize(px);
            let pyf = T::from_usize(py);
            // Forward walk, as in the forward pass, keeping the blended entries.
            hits.clear();
            let mut t = T::ONE;
            for (j, s) in splats.iter().enumerate() {
                let h = match evaluate(s, pxf, pyf, k) {
                    Step::Skip => continue,
                    Step::Hit(h) => h,
                };
                let test_t = t * (T::ONE - h.alpha);
                if test_t < k.t_min {
                    break;
                }
                hits.push((j, h, t));
                t = test_t;
            }
            // Backward walk.
            let mut r = g[0] * bg[0] + g[1] * bg[1] + g[2] * bg[2];
            for &(j, h, t_i) in hits.iter().rev() {
                let s = &splats[j];
                let w = g[0] * s.color[0] + g[1] * s.color[1] + g[2] * s.color[2] + gd * s.depth;
                let dalpha = t_i * (w - r);
                r = h.alpha * w + (T::ONE - h.alpha) * r;
                let at = h.alpha * t_i;
                let e = &mut grads[j];
                e[0] += g[0] * at;
                e[1] += g[1] * at;
                e[2] += g[2] * at;
                e[9] += gd * at;
                if h.clamped {
                    continue;
                }
                // alpha = o·G, G = exp(power).
                e[8] += dalpha * h.g;
                let gp = dalpha * s.opacity * h.g;
                let [ca, cb, cc] = s.conic;
                e[3] += gp * (-ca * h.dx - cb * h.dy);
                e[4] += gp * (-cc * h.dy - cb * h.dx);
                e[5] += gp * (-half * h.dx * h.dx);
                e[6] += gp * (-h.dx * h.dy);
                e[7] += gp * (-half * h.dy * h.dy);
            }
        }
    }
}
