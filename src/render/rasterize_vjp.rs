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
//! Vectorised as the forward: a tile row is one group of
//! [`LANES`](super::rasterize::LANES) pixels. Per row, the forward walk
//! ([`walk_row`]) records every entry at which some pixel blends (its
//! transmittance before the entry, `exp(power)` and the blend mask); the
//! backward then walks these records in reverse, each lane applying the
//! per-pixel rule above (lanes that did not blend an entry contribute exactly
//! zero to it and keep their state).
//!
//! Determinism: the contributions of a row's 16 pixels to an entry are summed
//! by a fixed pairwise tree (lane `l` with `l + 8`, then `+ 4`, `+ 2`, `+ 1`),
//! whatever the instruction set; each entry adds its rows' sums in ascending
//! row order (only rows at which some pixel blended it); per-Gaussian sums
//! are formed afterwards in ascending list position (ascending tile). No sum
//! depends on the number of threads or the vector width.

use super::lanes::{Lanes, Scalar};
use super::rasterize::{lane_x, walk_row, Blend, Record, Row, Splat, LANES};
use super::GradientMode;
use crate::math::Real;

/// Per list entry gradient: colour (3), pixel centre (2), conic (3),
/// opacity (1), depth (1). In [`GradientMode::Inria`] the centre gradient is
/// already in NDC units and the conic's `B` slot holds half of `dL/dB`, as
/// upstream accumulates them.
pub(crate) type EntryGrad<T> = [T; 10];

/// What the backward of one tile reads.
pub(crate) struct TileJob<'a, T> {
    /// The tile's gathered list.
    pub splats: &'a [Splat<T>],
    /// Starting at this tile's column: every `grid_x`-th value is, per image
    /// row, the last list position any pixel of the row blends in the tile.
    pub row_last: &'a [u32],
    pub grid_x: usize,
    /// Pixel bounds `[x0, x1, y0, y1]`.
    pub bounds: [usize; 4],
    pub width: usize,
    pub height: usize,
    pub bg: [T; 3],
    /// `[3, H, W]`.
    pub grad_color: &'a [T],
    /// `[H, W]`, or `None` for zero.
    pub grad_depth: Option<&'a [T]>,
    pub mode: GradientMode,
}

#[inline(always)]
fn tile_vjp_body<V: Lanes>(
    job: &TileJob<'_, V::T>,
    grads: &mut [EntryGrad<V::T>],
    rec: &mut Vec<Record<V::T>>,
) {
    let k = Blend::<V::T>::new();
    let zero = V::T::ZERO;
    let [x0, x1, y0, y1] = job.bounds;
    let nx = x1 - x0;
    let hw = job.width * job.height;
    for py in y0..y1 {
        rec.clear();
        let row = Row { x0, nx, py };
        // Past the last blended entry the walk records nothing and changes
        // no state: stop there.
        let last = job.row_last[py * job.grid_x] as usize;
        let st = walk_row::<V, true>(&job.splats[..last], row, &k, rec);
        if rec.is_empty() {
            continue;
        }
        let base = py * job.width + x0;
        let mut g = [[zero; LANES]; 3];
        for (ch, gc) in g.iter_mut().enumerate() {
            gc[..nx].copy_from_slice(&job.grad_color[ch * hw + base..ch * hw + base + nx]);
        }
        let g = g.map(|v| V::load(&v));
        match job.mode {
            GradientMode::Exact => {
                let mut gd = [zero; LANES];
                if let Some(d) = job.grad_depth {
                    gd[..nx].copy_from_slice(&d[base..base + nx]);
                }
                exact_row::<V>(job, row, &k, rec, &g, V::load(&gd), grads);
            }
            GradientMode::Inria => inria_row::<V>(job, row, &k, rec, &g, V::load(&st.t), grads),
        }
    }
}

/// Exact-mode reverse walk of one row.
#[inline(always)]
fn exact_row<V: Lanes>(
    job: &TileJob<'_, V::T>,
    row: Row,
    k: &Blend<V::T>,
    rec: &[Record<V::T>],
    g: &[V; 3],
    gd: V,
    grads: &mut [EntryGrad<V::T>],
) {
    let bg = job.bg;
    let px = V::load(&lane_x::<V::T>(row));
    let pyf = V::T::from_usize(row.py);
    let half = V::T::from_f64(0.5);
    let zero = V::splat(V::T::ZERO);
    let one = V::splat(V::T::ONE);
    let amax = V::splat(k.alpha_max);
    let mut r = g[0] * V::splat(bg[0]) + g[1] * V::splat(bg[1]) + g[2] * V::splat(bg[2]);
    for rc in rec.iter().rev() {
        let s = &job.splats[rc.j as usize];
        let dys = s.xy[1] - pyf;
        let dy = V::splat(dys);
        let [ca, cb, cc] = s.conic;
        let dx = V::splat(s.xy[0]) - px;
        let gg = V::load(&rc.g);
        let o = V::splat(s.opacity);
        let raw = o * gg;
        let a = raw.min_of(amax);
        let clamped = raw.gt(amax);
        let t_i = V::load(&rc.t);
        let b = V::from_bits(rc.blend);
        let live = V::andnot(b, clamped);
        let w = g[0] * V::splat(s.color[0])
            + g[1] * V::splat(s.color[1])
            + g[2] * V::splat(s.color[2])
            + gd * V::splat(s.depth);
        let dalpha = t_i * (w - r);
        r = V::select(b, a * w + (one - a) * r, r);
        let at = a * t_i;
        let e = &mut grads[rc.j as usize];
        e[0] += V::select(b, g[0] * at, zero).tree_sum();
        e[1] += V::select(b, g[1] * at, zero).tree_sum();
        e[2] += V::select(b, g[2] * at, zero).tree_sum();
        e[9] += V::select(b, gd * at, zero).tree_sum();
        if V::bits(live) == 0 {
            continue;
        }
        // alpha = o·G, G = exp(power).
        let gp = dalpha * o * gg;
        e[8] += V::select(live, dalpha * gg, zero).tree_sum();
        e[3] += V::select(live, gp * (V::splat(-ca) * dx - V::splat(cb) * dy), zero).tree_sum();
        e[4] += V::select(live, gp * (V::splat(-cc) * dy - V::splat(cb) * dx), zero).tree_sum();
        e[5] += V::select(live, gp * (V::splat(-half) * dx * dx), zero).tree_sum();
        e[6] += V::select(live, gp * (-dx * dy), zero).tree_sum();
        e[7] += V::select(live, gp * V::splat(-half * dys * dys), zero).tree_sum();
    }
}

/// One row's backward in [`GradientMode::Inria`]: upstream `renderCUDA`
/// backward as written, per lane. Transmittance is recovered by division
/// from the pixel's final `T`, the alpha clamp is ignored, the depth image
/// has no gradient, the centre gradient is scaled to NDC per pixel and the
/// conic's `B` gradient is accumulated at half its value.
#[inline(always)]
fn inria_row<V: Lanes>(
    job: &TileJob<'_, V::T>,
    row: Row,
    k: &Blend<V::T>,
    rec: &[Record<V::T>],
    g: &[V; 3],
    t_final: V,
    grads: &mut [EntryGrad<V::T>],
) {
    let bg = job.bg;
    let px = V::load(&lane_x::<V::T>(row));
    let pyf = V::T::from_usize(row.py);
    let neg_half = V::splat(-V::T::from_f64(0.5));
    let zero = V::splat(V::T::ZERO);
    let one = V::splat(V::T::ONE);
    let amax = V::splat(k.alpha_max);
    let ndc = [
        V::splat(V::T::from_f64(0.5 * job.width as f64)),
        V::splat(V::T::from_f64(0.5 * job.height as f64)),
    ];
    let mut t = t_final;
    let mut accum = [zero; 3];
    let mut last_alpha = zero;
    let mut last_color = [zero; 3];
    let mut bg_dot = zero;
    for ch in 0..3 {
        bg_dot = bg_dot + V::splat(bg[ch]) * g[ch];
    }
    for rc in rec.iter().rev() {
        let s = &job.splats[rc.j as usize];
        let dy = V::splat(s.xy[1] - pyf);
        let [ca, cb, cc] = s.conic;
        let b = V::from_bits(rc.blend);
        let dx = V::splat(s.xy[0]) - px;
        let gg = V::load(&rc.g);
        let a = (V::splat(s.opacity) * gg).min_of(amax);
        let tn = t / (one - a);
        let dchannel_dcolor = a * tn;
        let mut dl_dalpha = zero;
        let e = &mut grads[rc.j as usize];
        for ch in 0..3 {
            let c = V::splat(s.color[ch]);
            let acc = last_alpha * last_color[ch] + (one - last_alpha) * accum[ch];
            dl_dalpha = dl_dalpha + (c - acc) * g[ch];
            e[ch] += V::select(b, dchannel_dcolor * g[ch], zero).tree_sum();
            accum[ch] = V::select(b, acc, accum[ch]);
            last_color[ch] = V::select(b, c, last_color[ch]);
        }
        dl_dalpha = dl_dalpha * tn;
        dl_dalpha = dl_dalpha + (-t_final / (one - a)) * bg_dot;
        let dl_dg = V::splat(s.opacity) * dl_dalpha;
        let gdx = gg * dx;
        let gdy = gg * dy;
        let dg_ddelx = -gdx * V::splat(ca) - gdy * V::splat(cb);
        let dg_ddely = -gdy * V::splat(cc) - gdx * V::splat(cb);
        e[3] += V::select(b, dl_dg * dg_ddelx * ndc[0], zero).tree_sum();
        e[4] += V::select(b, dl_dg * dg_ddely * ndc[1], zero).tree_sum();
        e[5] += V::select(b, neg_half * gdx * dx * dl_dg, zero).tree_sum();
        e[6] += V::select(b, neg_half * gdx * dy * dl_dg, zero).tree_sum();
        e[7] += V::select(b, neg_half * gdy * dy * dl_dg, zero).tree_sum();
        e[8] += V::select(b, gg * dl_dalpha, zero).tree_sum();
        t = V::select(b, tn, t);
        last_alpha = V::select(b, a, last_alpha);
    }
}

/// The backward of one tile: `grads` has one slot per list entry of the
/// tile and is accumulated into; `rec` is scratch.
pub(crate) fn tile_vjp<T: Real>(
    job: &TileJob<'_, T>,
    grads: &mut [EntryGrad<T>],
    rec: &mut Vec<Record<T>>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        use super::lanes::{Avx2, Avx512};
        use super::rasterize::{as_f32, path, Path};
        type G = EntryGrad<f32>;
        type R = Vec<Record<f32>>;
        #[target_feature(enable = "avx512f")]
        unsafe fn avx512(job: &TileJob<'_, f32>, grads: &mut [G], rec: &mut R) {
            tile_vjp_body::<Avx512>(job, grads, rec)
        }
        #[target_feature(enable = "avx2")]
        unsafe fn avx2(job: &TileJob<'_, f32>, grads: &mut [G], rec: &mut R) {
            tile_vjp_body::<Avx2>(job, grads, rec)
        }
        let p = path::<T>();
        if p != Path::Portable {
            // SAFETY: a vector path is chosen only for T = f32, on a CPU
            // with its feature.
            unsafe {
                let j32 = &*(job as *const TileJob<'_, T> as *const TileJob<'_, f32>);
                let g32: &mut [G] =
                    std::slice::from_raw_parts_mut(grads.as_mut_ptr() as *mut G, grads.len());
                let r32: &mut R = as_f32(rec);
                match p {
                    Path::Avx512 => avx512(j32, g32, r32),
                    _ => avx2(j32, g32, r32),
                }
            }
            return;
        }
    }
    tile_vjp_body::<Scalar<T>>(job, grads, rec)
}
