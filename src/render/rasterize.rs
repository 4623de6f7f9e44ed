//! Per-pixel forward blending (Inria `renderCUDA`, plus the depth output of
//! the fork the D-3DGS paper uses).
//!
//! Each pixel walks its tile's sorted list front to back:
//! `power = −0.5(A dx² + C dy²) − B dx dy` with `d = centre − pixel`; skip if
//! `power > 0`; `alpha = min(0.99, o·exp(power))`; skip if `alpha < 1/255`
//! (the constant `1/255` evaluated in `T`); stop, without blending, when
//! `T·(1 − alpha) < 1e-4`; otherwise `C += (c·alpha)·T`, `D += (z·alpha)·T`,
//! `T ← T·(1 − alpha)`. Output `C + T·bg`, `D` (no background), final `T` and
//! the 1-based position of the last blended entry.
//!
//! Tiles are independent and own their pixels, so the forward runs in
//! parallel over tiles with no reduction across threads.

use super::BLOCK;
use crate::math::Real;

/// The per-Gaussian data a pixel reads, gathered in list order per tile.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Splat<T> {
    pub xy: [T; 2],
    pub conic: [T; 3],
    pub opacity: T,
    pub color: [T; 3],
    pub depth: T,
}

/// Constants of the blending rule in `T`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Blend<T> {
    pub neg_half: T,
    pub alpha_max: T,
    pub alpha_min: T,
    pub t_min: T,
}

impl<T: Real> Blend<T> {
    pub fn new() -> Self {
        Blend {
            neg_half: T::from_f64(-0.5),
            alpha_max: T::from_f64(0.99),
            alpha_min: T::ONE / T::from_f64(255.0),
            t_min: T::from_f64(1e-4),
        }
    }
}

/// One list entry evaluated at one pixel.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Hit<T> {
    pub dx: T,
    pub dy: T,
    /// `exp(power)`.
    pub g: T,
    pub alpha: T,
    /// `o·G > 0.99`: alpha is the constant 0.99.
    pub clamped: bool,
}

/// What an entry does at a pixel.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Step<T> {
    /// `power > 0` or `alpha < 1/255`.
    Skip,
    /// Passes the alpha test; the caller decides stop vs blend from `T`.
    Hit(Hit<T>),
}

#[inline(always)]
pub(crate) fn evaluate<T: Real>(s: &Splat<T>, px: T, py: T, k: &Blend<T>) -> Step<T> {
    let dx = s.xy[0] - px;
    let dy = s.xy[1] - py;
    let power = k.neg_half * (s.conic[0] * dx * dx + s.conic[2] * dy * dy) - s.conic[1] * dx * dy;
    if power > T::ZERO {
        return Step::Skip;
    }
    let g = power.exp();
    let raw = s.opacity * g;
    let alpha = k.alpha_max.min(raw);
    if alpha < k.alpha_min {
        return Step::Skip;
    }
    Step::Hit(Hit {
        dx,
        dy,
        g,
        alpha,
        clamped: raw > k.alpha_max,
    })
}

/// Forward output of one tile, pixels row-major within the tile.
pub(crate) struct TileOut<T> {
    pub color: Vec<[T; 3]>,
    pub depth: Vec<T>,
    pub final_t: Vec<T>,
    pub n_contrib: Vec<u32>,
}

/// Pixel bounds `[x0, x1) × [y0, y1)` of tile `tile`.
#[inline]
pub(crate) fn tile_bounds(tile: usize, grid_x: usize, w: usize, h: usize) -> [usize; 4] {
    let tx = tile % grid_x;
    let ty = tile / grid_x;
    [
        tx * BLOCK,
        (tx * BLOCK + BLOCK).min(w),
        ty * BLOCK,
        (ty * BLOCK + BLOCK).min(h),
    ]
}

/// Render one tile.
pub(crate) fn render_tile<T: Real>(
    splats: &[Splat<T>],
    bounds: [usize; 4],
    bg: [T; 3],
    k: &Blend<T>,
) -> TileOut<T> {
    let [x0, x1, y0, y1] = bounds;
    let n = (x1 - x0) * (y1 - y0);
    let mut out = TileOut {
        color: Vec::with_capacity(n),
        depth: Vec::with_capacity(n),
        final_t: Vec::with_capacity(n),
        n_contrib: Vec::with_capacity(n),
    };
    for py in y0..y1 {
        for px in x0..x1 {
            let pxf = T::from_usize(px);
            let pyf = T::from_usize(py);
            let mut t = T::ONE;
            let mut c = [T::ZERO; 3];
            let mut d = T::ZERO;
            let mut last = 0u32;
            for (j, s) in splats.iter().enumerate() {
                let h = match evaluate(s, pxf, pyf, k) {
                    Step::Skip => continue,
                    Step::Hit(h) => h,
                };
                let test_t = t * (T::ONE - h.alpha);
                if test_t < k.t_min {
                    break;
                }
                for ch in 0..3 {
                    c[ch] += s.color[ch] * h.alpha * t;
                }
                d += s.depth * h.alpha * t;
                t = test_t;
                last = j as u32 + 1;
            }
            out.color
                .push([c[0] + t * bg[0], c[1] + t * bg[1], c[2] + t * bg[2]]);
            out.depth.push(d);
            out.final_t.push(t);
            out.n_contrib.push(last);
        }
    }
    out
}
