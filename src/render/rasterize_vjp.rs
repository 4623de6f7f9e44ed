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
/// opacity (1), depth (1). In [`GradientMode::Inria`] the centre gradient is
/// already in NDC units and the conic's `B` slot holds half of `dL/dB`, as
/// upstream accumulates them.
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
            if mode == GradientMode::Inria {
                let ndc_scale = [
                    T::from_f64(0.5 * width as f64),
                    T::from_f64(0.5 * height as f64),
                ];
                inria_pixel(splats, &hits, t, g, bg, ndc_scale, grads);
                continue;
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

/// One pixel's backward in [`GradientMode::Inria`]: upstream `renderCUDA`
/// backward as written. `hits` are the blended entries front to back,
/// `t_final` the pixel's final transmittance. Transmittance is recovered by
/// division, the alpha clamp is ignored, the depth image has no gradient, the
/// centre gradient is scaled to NDC per pixel and the conic's `B` gradient is
/// accumulated at half its value.
fn inria_pixel<T: Real>(
    splats: &[Splat<T>],
    hits: &[(usize, Hit<T>, T)],
    t_final: T,
    g: [T; 3],
    bg: [T; 3],
    ndc_scale: [T; 2],
    grads: &mut [EntryGrad<T>],
) {
    let half = T::from_f64(0.5);
    let mut t = t_final;
    let mut accum = [T::ZERO; 3];
    let mut last_alpha = T::ZERO;
    let mut last_color = [T::ZERO; 3];
    let mut bg_dot = T::ZERO;
    for ch in 0..3 {
        bg_dot += bg[ch] * g[ch];
    }
    for &(j, h, _) in hits.iter().rev() {
        let s = &splats[j];
        let alpha = h.alpha;
        t /= T::ONE - alpha;
        let dchannel_dcolor = alpha * t;
        let mut dl_dalpha = T::ZERO;
        let e = &mut grads[j];
        for ch in 0..3 {
            let c = s.color[ch];
            accum[ch] = last_alpha * last_color[ch] + (T::ONE - last_alpha) * accum[ch];
            last_color[ch] = c;
            dl_dalpha += (c - accum[ch]) * g[ch];
            e[ch] += dchannel_dcolor * g[ch];
        }
        dl_dalpha *= t;
        last_alpha = alpha;
        dl_dalpha += (-t_final / (T::ONE - alpha)) * bg_dot;
        let dl_dg = s.opacity * dl_dalpha;
        let gdx = h.g * h.dx;
        let gdy = h.g * h.dy;
        let [ca, cb, cc] = s.conic;
        let dg_ddelx = -gdx * ca - gdy * cb;
        let dg_ddely = -gdy * cc - gdx * cb;
        e[3] += dl_dg * dg_ddelx * ndc_scale[0];
        e[4] += dl_dg * dg_ddely * ndc_scale[1];
        e[5] += -half * gdx * h.dx * dl_dg;
        e[6] += -half * gdx * h.dy * dl_dg;
        e[7] += -half * gdy * h.dy * dl_dg;
        e[8] += h.g * dl_dalpha;
    }
}
