//! `rasterize_to_pixels`: front-to-back alpha compositing of the sorted
//! intersections of each tile, any number of channels, optional
//! backgrounds, and the backward.
//!
//! Forward (`csrc/RasterizeToPixels3DGSFwd.cu` v1.5.3 l.62–187;
//! 1.6 `RasterizeToPixels3DGSDevice.cuh` l.44–97): pixel `(i, j)` is sampled
//! at `(j + 0.5, i + 0.5)`; with `d = mean2d − pixel`,
//! `σ = 0.5·(a dx² + c dy²) + b dx dy`, `vis = exp(−σ)`,
//! `α = min(MAX_ALPHA, o·vis)`; skip if `σ < 0 || α < 1/255`;
//! `next_T = T·(1 − α)`; if `next_T ≤ 1e-4` the pixel is done, **without**
//! this Gaussian; else `C += c·(α·T)`, `T = next_T`. Outputs
//! `render_colors = C + T·background`, `render_alphas = 1 − T` and
//! `last_ids`, the index of the last blended intersection (0 if none).
//! Pairs with `σ ≥ 20` and `|o| ≤ 1e6` are skipped before the exponential:
//! there `exp(−σ) ≤ 2.1e-9` and the rule skips them anyway (the same
//! decisions and bits, without the subnormal numbers the exponential gives
//! far out).
//!
//! Backward, [`GradientMode::Gsplat`] (v1.5.3 `RasterizeToPixels3DGSBwd.cu`
//! l.106–242; 1.6 `RasterizeToPixels3DGSDevice.cuh` l.105–173): back to
//! front from `T = 1 − render_alpha`, `ra = 1/(1 − α)` (1.6:
//! `1/max(1e-6, 1 − α)`), `T ← T·ra`, `v_α = Σ_k (c_k T − buffer_k ra) v_C_k +
//! T_final ra v_A − T_final ra Σ_k bg_k v_C_k`; `σ` and opacity gradients
//! only if `o·vis ≤ MAX_ALPHA`; `v_backgrounds = Σ_pixels v_C·(1 − render_alpha)`
//! (`cuda/_wrapper.py`), a pairwise sum over each image's pixels ([`pairwise_sum_by`]). [`GradientMode::Exact`] uses the forward's
//! transmittances and the recursion `R_{i−1} = α_i w_i + (1 − α_i) R_i`
//! (no division), and the stored final transmittance for the background.

#![allow(clippy::needless_range_loop)]

use super::{check_len, Constants, GradientMode, Version};
use crate::error::{Error, Result};
use crate::math::sum::pairwise_sum_by;
use crate::math::Real;
use rayon::prelude::*;

/// The inputs of `rasterize_to_pixels` (entries dense `[C·N]` or packed `[nnz]`).
#[derive(Clone, Copy, Debug)]
pub struct RasterInput<'a, T> {
    /// `[M, 2]`.
    pub means2d: &'a [T],
    /// `[M, 3]`.
    pub conics: &'a [T],
    /// `[M, D]`.
    pub colors: &'a [T],
    /// `[M]`.
    pub opacities: &'a [T],
    /// `[I, D]`, optional.
    pub backgrounds: Option<&'a [T]>,
    /// Channels `D`.
    pub channels: usize,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Tile side in pixels.
    pub tile_size: usize,
    /// `[I, tile_height, tile_width]`.
    pub isect_offsets: &'a [i32],
    /// `[n_isects]`.
    pub flatten_ids: &'a [i32],
}

/// Forward outputs.
#[derive(Clone, Debug, PartialEq)]
pub struct RasterOutput<T> {
    /// `[I, H, W, D]`.
    pub render_colors: Vec<T>,
    /// `[I, H, W, 1]`.
    pub render_alphas: Vec<T>,
    /// `[I, H, W]` int32.
    pub last_ids: Vec<i32>,
    /// `[I, H, W]` final transmittance `T` (before `1 − T` rounds it).
    pub final_t: Vec<T>,
}

/// Gradients of `rasterize_to_pixels`'s inputs.
#[derive(Clone, Debug, PartialEq)]
pub struct RasterGrads<T> {
    /// `[M, 2]` (pixels).
    pub v_means2d: Vec<T>,
    /// `[M, 2]`: Σ over pixels of `|v_means2d|` per pixel (gsplat's `absgrad`).
    pub v_means2d_abs: Vec<T>,
    /// `[M, 3]`.
    pub v_conics: Vec<T>,
    /// `[M, D]`.
    pub v_colors: Vec<T>,
    /// `[M]`.
    pub v_opacities: Vec<T>,
    /// `[I, D]` when backgrounds were given.
    pub v_backgrounds: Option<Vec<T>>,
}

struct Grid {
    images: usize,
    tw: usize,
    th: usize,
    n_isects: usize,
}

impl<T: Real> RasterInput<'_, T> {
    fn validate(&self) -> Result<Grid> {
        let d = self.channels;
        if d == 0 || self.width == 0 || self.height == 0 || self.tile_size == 0 {
            return Err(Error::invalid(
                "rasterize_to_pixels",
                format!(
                    "channels {d}, image {}x{}, tile_size {}: each must be positive",
                    self.width, self.height, self.tile_size
                ),
            ));
        }
        if self.tile_size > 1024 {
            return Err(Error::invalid(
                "tile_size",
                format!("{} (1 to 1024)", self.tile_size),
            ));
        }
        let m = self.opacities.len();
        check_len("means2d", self.means2d.len(), 2 * m)?;
        check_len("conics", self.conics.len(), 3 * m)?;
        match d.checked_mul(m) {
            Some(want) => check_len("colors", self.colors.len(), want)?,
            None => {
                return Err(Error::invalid(
                    "channels",
                    format!("{d} channels of {m} entries: more values than a slice holds"),
                ))
            }
        }
        let tw = self.width.div_ceil(self.tile_size);
        let th = self.height.div_ceil(self.tile_size);
        let Some(per_image) = tw.checked_mul(th) else {
            // `check_frame`'s refusal, before the grid's size is used.
            return Err(Error::invalid(
                "image size",
                format!(
                    "{}x{} pixels (each side 1 to 65536)",
                    self.width, self.height
                ),
            ));
        };
        if self.isect_offsets.is_empty() || !self.isect_offsets.len().is_multiple_of(per_image) {
            return Err(Error::invalid(
                "isect_offsets",
                format!(
                    "{} values, expected [I, {th}, {tw}]",
                    self.isect_offsets.len()
                ),
            ));
        }
        let images = self.isect_offsets.len() / per_image;
        super::check_frame(images, self.width, self.height, d)?;
        if let Some(bg) = self.backgrounds {
            check_len("backgrounds", bg.len(), images * d)?;
        }
        let n = self.flatten_ids.len();
        let mut prev = 0i32;
        for (i, &o) in self.isect_offsets.iter().enumerate() {
            if o < prev || o as usize > n {
                let was = if i == 0 {
                    String::new()
                } else {
                    format!(" after {prev}")
                };
                return Err(Error::invalid(
                    "isect_offsets",
                    format!(
                        "expected ascending values within [0, {n}] (the length of flatten_ids), \
                         found {o} at flat index {i}{was}"
                    ),
                ));
            }
            prev = o;
        }
        if let Some(&bad) = self.flatten_ids.iter().find(|&&f| f < 0 || f as usize >= m) {
            return Err(Error::invalid(
                "flatten_ids",
                format!("{bad} is not an entry index below {m}"),
            ));
        }
        Ok(Grid {
            images,
            tw,
            th,
            n_isects: n,
        })
    }

    /// `[start, end)` of tile `t` (over all images).
    fn range(&self, g: &Grid, t: usize) -> (usize, usize) {
        let s = self.isect_offsets[t] as usize;
        let e = if t + 1 == g.images * g.tw * g.th {
            g.n_isects
        } else {
            self.isect_offsets[t + 1] as usize
        };
        (s, e.max(s))
    }

    /// Pixel bounds `[x0, x1) × [y0, y1)` and image of tile `t`.
    fn bounds(&self, g: &Grid, t: usize) -> (usize, [usize; 4]) {
        let per = g.tw * g.th;
        let (img, local) = (t / per, t % per);
        let (tx, ty) = (local % g.tw, local / g.tw);
        let ts = self.tile_size;
        (
            img,
            [
                tx * ts,
                (tx * ts + ts).min(self.width),
                ty * ts,
                (ty * ts + ts).min(self.height),
            ],
        )
    }
}

/// One intersection evaluated at one pixel.
#[derive(Clone, Copy, Debug)]
struct Hit<T> {
    pos: usize,
    dx: T,
    dy: T,
    vis: T,
    alpha: T,
    /// Transmittance in front of this Gaussian.
    t: T,
}

/// What happened at each intersection of a pixel's walk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Decision {
    /// `σ < 0` or `α < 1/255`.
    Skip = 0,
    /// Blended, `o·vis ≤ MAX_ALPHA`.
    Blend = 1,
    /// Blended with the alpha clamp active.
    BlendClamped = 2,
    /// `T·(1 − α) ≤ 1e-4`: the walk ends here.
    Stop = 3,
}

/// Walk one pixel front to back; returns the final transmittance and calls
/// `on_hit` for each blended intersection, `on_decision` for every one.
#[inline]
#[allow(clippy::too_many_arguments)]
fn walk<T: Real>(
    inp: &RasterInput<T>,
    k: &Constants<T>,
    range: (usize, usize),
    px: T,
    py: T,
    mut on_hit: impl FnMut(&Hit<T>, usize),
    mut on_decision: impl FnMut(Decision),
) -> T {
    let half = T::from_f64(0.5);
    let (far_sigma, far_opacity) = (T::from_f64(20.0), T::from_f64(1e6));
    let mut t = T::ONE;
    for pos in range.0..range.1 {
        let g = inp.flatten_ids[pos] as usize;
        let dx = inp.means2d[2 * g] - px;
        let dy = inp.means2d[2 * g + 1] - py;
        let [a, b, c] = [
            inp.conics[3 * g],
            inp.conics[3 * g + 1],
            inp.conics[3 * g + 2],
        ];
        let sigma = half * (a * dx * dx + c * dy * dy) + b * dx * dy;
        let o = inp.opacities[g];
        // Far from the splat, `σ ≥ 20`: `vis = exp(−σ) ≤ 2.1e-9`, so for an
        // opacity in [−1e6, 1e6], `α ≤ o·vis ≤ 2.1e-3 < 1/255` and the pair
        // is skipped below whatever else holds. It is skipped here without
        // the exponential, whose result (and `o·vis`) farther out is
        // subnormal or 0 in f32, computed slowly in microcode: the same
        // decisions and bits. (A NaN `σ` or opacity, or an opacity outside
        // that range, takes the full test: an infinite one times a `vis`
        // of 0 is NaN, which the `min` turns into `MAX_ALPHA`.)
        if sigma >= far_sigma && o >= -far_opacity && o <= far_opacity {
            on_decision(Decision::Skip);
            continue;
        }
        let vis = (-sigma).exp();
        let alpha = k.max_alpha.min(o * vis);
        if sigma < T::ZERO || alpha < k.alpha_threshold {
            on_decision(Decision::Skip);
            continue;
        }
        let next_t = t * (T::ONE - alpha);
        if next_t <= k.transmittance_threshold {
            on_decision(Decision::Stop);
            break;
        }
        on_decision(if o * vis <= k.max_alpha {
            Decision::Blend
        } else {
            Decision::BlendClamped
        });
        on_hit(
            &Hit {
                pos,
                dx,
                dy,
                vis,
                alpha,
                t,
            },
            g,
        );
        t = next_t;
    }
    t
}

struct TileOut<T> {
    colors: Vec<T>,
    t: Vec<T>,
    last: Vec<i32>,
}

/// `gsplat.rasterize_to_pixels(means2d, conics, colors, opacities, image_width,
/// image_height, tile_size, isect_offsets, flatten_ids, backgrounds)`.
pub fn rasterize_to_pixels<T: Real>(
    inp: &RasterInput<T>,
    version: Version,
) -> Result<RasterOutput<T>> {
    let g = inp.validate()?;
    let k = Constants::<T>::new(version);
    let d = inp.channels;
    let (w, h) = (inp.width, inp.height);
    let half = T::from_f64(0.5);
    let n_tiles = g.images * g.tw * g.th;
    let tiles: Vec<TileOut<T>> = (0..n_tiles)
        .into_par_iter()
        .map(|tile| {
            let (img, [x0, x1, y0, y1]) = inp.bounds(&g, tile);
            let range = inp.range(&g, tile);
            let np = (x1 - x0) * (y1 - y0);
            let mut out = TileOut {
                colors: Vec::with_capacity(np * d),
                t: Vec::with_capacity(np),
                last: Vec::with_capacity(np),
            };
            let mut c = vec![T::ZERO; d];
            for py in y0..y1 {
                for px in x0..x1 {
                    c.iter_mut().for_each(|v| *v = T::ZERO);
                    let mut last = 0usize;
                    let t = walk(
                        inp,
                        &k,
                        range,
                        T::from_usize(px) + half,
                        T::from_usize(py) + half,
                        |hit, gi| {
                            let vis = hit.alpha * hit.t;
                            for ch in 0..d {
                                c[ch] += inp.colors[gi * d + ch] * vis;
                            }
                            last = hit.pos;
                        },
                        |_| {},
                    );
                    for ch in 0..d {
                        out.colors.push(match inp.backgrounds {
                            Some(bg) => c[ch] + t * bg[img * d + ch],
                            None => c[ch],
                        });
                    }
                    out.t.push(t);
                    out.last.push(last as i32);
                }
            }
            out
        })
        .collect();
    let hw = w * h;
    let mut out = RasterOutput {
        render_colors: vec![T::ZERO; g.images * hw * d],
        render_alphas: vec![T::ZERO; g.images * hw],
        last_ids: vec![0; g.images * hw],
        final_t: vec![T::ZERO; g.images * hw],
    };
    for (tile, to) in tiles.iter().enumerate() {
        let (img, [x0, x1, y0, y1]) = inp.bounds(&g, tile);
        let mut q = 0;
        for py in y0..y1 {
            for px in x0..x1 {
                let pix = img * hw + py * w + px;
                out.render_colors[pix * d..(pix + 1) * d]
                    .copy_from_slice(&to.colors[q * d..(q + 1) * d]);
                out.render_alphas[pix] = T::ONE - to.t[q];
                out.final_t[pix] = to.t[q];
                out.last_ids[pix] = to.last[q];
                q += 1;
            }
        }
    }
    Ok(out)
}

/// Every decision of every pixel's walk, tile by tile (tests use it to keep
/// finite differences away from discontinuities).
pub fn decisions<T: Real>(inp: &RasterInput<T>, version: Version) -> Result<Vec<u8>> {
    let g = inp.validate()?;
    let k = Constants::<T>::new(version);
    let half = T::from_f64(0.5);
    let mut sig = Vec::new();
    for tile in 0..g.images * g.tw * g.th {
        let (_, [x0, x1, y0, y1]) = inp.bounds(&g, tile);
        let range = inp.range(&g, tile);
        for py in y0..y1 {
            for px in x0..x1 {
                walk(
                    inp,
                    &k,
                    range,
                    T::from_usize(px) + half,
                    T::from_usize(py) + half,
                    |_, _| {},
                    |dcs| sig.push(dcs as u8),
                );
            }
        }
    }
    Ok(sig)
}

/// Backward of [`rasterize_to_pixels`]: gradients of
/// `<v_render_colors, render_colors> + <v_render_alphas, render_alphas>`.
/// `fwd` must be the forward of the same input.
pub fn rasterize_to_pixels_vjp<T: Real>(
    inp: &RasterInput<T>,
    version: Version,
    fwd: &RasterOutput<T>,
    v_render_colors: &[T],
    v_render_alphas: &[T],
    mode: GradientMode,
) -> Result<RasterGrads<T>> {
    let g = inp.validate()?;
    let k = Constants::<T>::new(version);
    let d = inp.channels;
    let (w, h) = (inp.width, inp.height);
    let hw = w * h;
    check_len("v_render_colors", v_render_colors.len(), g.images * hw * d)?;
    check_len("v_render_alphas", v_render_alphas.len(), g.images * hw)?;
    check_len("render_alphas", fwd.render_alphas.len(), g.images * hw)?;
    if inp.backgrounds.is_some() && mode == GradientMode::Exact {
        check_len("final_t", fwd.final_t.len(), g.images * hw)?;
    }
    let half = T::from_f64(0.5);
    let stride = d + 8;
    let n_tiles = g.images * g.tw * g.th;

    // 1. Per tile, per intersection: [v_colors (D), v_xy (2), v_conic (3), v_opacity, |v_xy| (2)].
    let mut entry = vec![T::ZERO; g.n_isects * stride];
    {
        let mut rest: &mut [T] = &mut entry;
        let mut chunks = Vec::new();
        let mut pos = 0usize;
        for tile in 0..n_tiles {
            let (s, e) = inp.range(&g, tile);
            if e == s {
                continue;
            }
            let (_, tail) = rest.split_at_mut((s - pos) * stride);
            let (head, tail) = tail.split_at_mut((e - s) * stride);
            chunks.push((tile, head));
            rest = tail;
            pos = e;
        }
        chunks.into_par_iter().for_each(|(tile, buf)| {
            let (img, [x0, x1, y0, y1]) = inp.bounds(&g, tile);
            let range = inp.range(&g, tile);
            let bg = inp.backgrounds.map(|b| &b[img * d..(img + 1) * d]);
            let mut hits: Vec<(Hit<T>, usize)> = Vec::new();
            let mut buffer = vec![T::ZERO; d];
            for py in y0..y1 {
                for px in x0..x1 {
                    let pix = img * hw + py * w + px;
                    let vc = &v_render_colors[pix * d..(pix + 1) * d];
                    let va = v_render_alphas[pix];
                    hits.clear();
                    walk(
                        inp,
                        &k,
                        range,
                        T::from_usize(px) + half,
                        T::from_usize(py) + half,
                        |hit, gi| hits.push((*hit, gi)),
                        |_| {},
                    );
                    let mut put = |hit: &Hit<T>, gi: usize, v_alpha: T, fac: T| {
                        let e = &mut buf
                            [(hit.pos - range.0) * stride..(hit.pos - range.0 + 1) * stride];
                        for ch in 0..d {
                            e[ch] += fac * vc[ch];
                        }
                        let o = inp.opacities[gi];
                        if o * hit.vis <= k.max_alpha {
                            let [a, b, c] = [
                                inp.conics[3 * gi],
                                inp.conics[3 * gi + 1],
                                inp.conics[3 * gi + 2],
                            ];
                            let v_sigma = -o * hit.vis * v_alpha;
                            let vx = v_sigma * (a * hit.dx + b * hit.dy);
                            let vy = v_sigma * (b * hit.dx + c * hit.dy);
                            e[d] += vx;
                            e[d + 1] += vy;
                            e[d + 2] += half * v_sigma * hit.dx * hit.dx;
                            e[d + 3] += v_sigma * hit.dx * hit.dy;
                            e[d + 4] += half * v_sigma * hit.dy * hit.dy;
                            e[d + 5] += hit.vis * v_alpha;
                            e[d + 6] += vx.abs();
                            e[d + 7] += vy.abs();
                        }
                    };
                    match mode {
                        GradientMode::Exact => {
                            let mut r = -va;
                            if let Some(bg) = bg {
                                for ch in 0..d {
                                    r += bg[ch] * vc[ch];
                                }
                            }
                            for (hit, gi) in hits.iter().rev() {
                                let mut wsum = T::ZERO;
                                for ch in 0..d {
                                    wsum += vc[ch] * inp.colors[gi * d + ch];
                                }
                                let v_alpha = hit.t * (wsum - r);
                                r = hit.alpha * wsum + (T::ONE - hit.alpha) * r;
                                put(hit, *gi, v_alpha, hit.alpha * hit.t);
                            }
                        }
                        GradientMode::Gsplat => {
                            let t_final = T::ONE - fwd.render_alphas[pix];
                            let mut t = t_final;
                            buffer.iter_mut().for_each(|v| *v = T::ZERO);
                            for (hit, gi) in hits.iter().rev() {
                                let oma = T::ONE - hit.alpha;
                                let ra = T::ONE
                                    / match k.min_one_minus_alpha {
                                        Some(m) => m.max(oma),
                                        None => oma,
                                    };
                                t *= ra;
                                let fac = hit.alpha * t;
                                let mut v_alpha = T::ZERO;
                                for ch in 0..d {
                                    v_alpha +=
                                        (inp.colors[gi * d + ch] * t - buffer[ch] * ra) * vc[ch];
                                }
                                v_alpha += t_final * ra * va;
                                if let Some(bg) = bg {
                                    let mut accum = T::ZERO;
                                    for ch in 0..d {
                                        accum += bg[ch] * vc[ch];
                                    }
                                    v_alpha += -t_final * ra * accum;
                                }
                                put(hit, *gi, v_alpha, fac);
                                for ch in 0..d {
                                    buffer[ch] += inp.colors[gi * d + ch] * fac;
                                }
                            }
                        }
                    }
                }
            }
        });
    }

    // 2. Per entry: its intersections in ascending order.
    let m = inp.opacities.len();
    let mut start = vec![0usize; m + 1];
    for &f in inp.flatten_ids {
        start[f as usize + 1] += 1;
    }
    for i in 0..m {
        start[i + 1] += start[i];
    }
    let mut fill = start.clone();
    let mut index = vec![0u32; g.n_isects];
    for (pos, &f) in inp.flatten_ids.iter().enumerate() {
        index[fill[f as usize]] = pos as u32;
        fill[f as usize] += 1;
    }
    let sums: Vec<Vec<T>> = (0..m)
        .into_par_iter()
        .map(|e| {
            let mut acc = vec![T::ZERO; stride];
            for &pos in &index[start[e]..start[e + 1]] {
                let src = &entry[pos as usize * stride..(pos as usize + 1) * stride];
                for q in 0..stride {
                    acc[q] += src[q];
                }
            }
            acc
        })
        .collect();
    let mut out = RasterGrads {
        v_means2d: Vec::with_capacity(2 * m),
        v_means2d_abs: Vec::with_capacity(2 * m),
        v_conics: Vec::with_capacity(3 * m),
        v_colors: Vec::with_capacity(d * m),
        v_opacities: Vec::with_capacity(m),
        v_backgrounds: None,
    };
    for acc in &sums {
        out.v_colors.extend_from_slice(&acc[..d]);
        out.v_means2d.extend_from_slice(&acc[d..d + 2]);
        out.v_conics.extend_from_slice(&acc[d + 2..d + 5]);
        out.v_opacities.push(acc[d + 5]);
        out.v_means2d_abs.extend_from_slice(&acc[d + 6..d + 8]);
    }

    // 3. Backgrounds: Σ over pixels of v_C·T_final, a pairwise sum over the
    // image's pixels in row-major order per channel (a running f32 sum over
    // a 400×400 frame was 7e-3 off, 1.6e-5 of the largest value).
    if inp.backgrounds.is_some() {
        let mut vb = vec![T::ZERO; g.images * d];
        for img in 0..g.images {
            let t = |p: usize| match mode {
                GradientMode::Exact => fwd.final_t[img * hw + p],
                GradientMode::Gsplat => T::ONE - fwd.render_alphas[img * hw + p],
            };
            for ch in 0..d {
                vb[img * d + ch] =
                    pairwise_sum_by(hw, |p| v_render_colors[(img * hw + p) * d + ch] * t(p));
            }
        }
        out.v_backgrounds = Some(vb);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The pixel walk's decision on one Gaussian against the full rule
    /// (`vis = exp(−σ)`, skip if `σ < 0 || min(MAX_ALPHA, o·vis) < 1/255`),
    /// for `σ` from 0 to 800 (across the early skip's bound at 20 and past
    /// the exponential's underflow to 0 in f32 and f64), `σ` infinite and
    /// NaN (an infinite conic), and opacities from −∞ to +∞ and NaN.
    fn early_skip_keeps_every_decision<T: Real>() {
        let opacities = [
            0.0,
            1e-30,
            0.004,
            0.5,
            1.0,
            2.0,
            1e6,
            1.5e6,
            1e30,
            f64::INFINITY,
            -1.0,
            -1e6,
            -1.5e6,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for version in Version::ALL {
            let k = Constants::<T>::new(version);
            for o in opacities {
                for a in [T::ONE, T::from_f64(f64::INFINITY)] {
                    let (m, conic, color, opacity) = (
                        [T::ZERO; 2],
                        [a, T::ZERO, T::ONE],
                        [T::ONE],
                        [T::from_f64(o)],
                    );
                    let inp = RasterInput {
                        means2d: &m,
                        conics: &conic,
                        colors: &color,
                        opacities: &opacity,
                        backgrounds: None,
                        channels: 1,
                        width: 16,
                        height: 16,
                        tile_size: 16,
                        isect_offsets: &[0],
                        flatten_ids: &[0],
                    };
                    for step in 0..4000 {
                        let px = T::from_f64(step as f64 * 0.01);
                        let mut got = Vec::new();
                        walk(&inp, &k, (0, 1), px, T::ZERO, |_, _| {}, |d| got.push(d));
                        // The walk's `σ` with `b = 0`, `dy = 0`.
                        let (dx, z) = (-px, T::ZERO);
                        let sigma = T::from_f64(0.5) * (a * dx * dx + T::ONE * z * z) + z * dx * z;
                        let vis = (-sigma).exp();
                        let alpha = k.max_alpha.min(opacity[0] * vis);
                        let want = if sigma < T::ZERO || alpha < k.alpha_threshold {
                            Decision::Skip
                        } else if T::ONE - alpha <= k.transmittance_threshold {
                            Decision::Stop
                        } else if opacity[0] * vis <= k.max_alpha {
                            Decision::Blend
                        } else {
                            Decision::BlendClamped
                        };
                        assert_eq!(got, [want], "{version:?}, o {o}, a {a:?}, pixel {px:?}");
                    }
                }
            }
        }
    }

    #[test]
    fn early_skip_keeps_every_decision_f32() {
        early_skip_keeps_every_decision::<f32>();
    }

    #[test]
    fn early_skip_keeps_every_decision_f64() {
        early_skip_keeps_every_decision::<f64>();
    }

    fn one_entry<'a>(
        channels: usize,
        colors: &'a [f64],
        size: usize,
        tile_size: usize,
        isect_offsets: &'a [i32],
    ) -> RasterInput<'a, f64> {
        RasterInput {
            means2d: &[1.0, 1.0, 2.0, 2.0],
            conics: &[1.0, 0.0, 1.0, 1.0, 0.0, 1.0],
            colors,
            opacities: &[0.5, 0.5],
            backgrounds: None,
            channels,
            width: size,
            height: size,
            tile_size,
            isect_offsets,
            flatten_ids: &[0, 1],
        }
    }

    /// Sizes whose products overflow are refused, in the forward and the
    /// backward, before anything of their size is allocated.
    #[test]
    fn overflowing_sizes_are_refused() {
        let v = Version::V1_6;
        let fwd = rasterize_to_pixels(&one_entry(1, &[1.0, 1.0], 4, 4, &[0]), v).unwrap();
        for (inp, want) in [
            (
                one_entry(usize::MAX, &[1.0, 1.0], 4, 4, &[0]),
                "invalid channels",
            ),
            (
                one_entry(1, &[1.0, 1.0], 1 << 40, 1, &[0]),
                "invalid image size",
            ),
            (
                one_entry(1, &[1.0, 1.0], usize::MAX, 1, &[0]),
                "invalid image size",
            ),
        ] {
            let e = rasterize_to_pixels(&inp, v).unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
            let e = rasterize_to_pixels_vjp(&inp, v, &fwd, &[], &[], GradientMode::Exact)
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{e}");
        }
    }

    /// A forward without its final transmittances is refused by the exact
    /// background gradient, which reads them.
    #[test]
    fn a_short_forward_state_is_refused() {
        let v = Version::V1_6;
        let mut inp = one_entry(1, &[1.0, 1.0], 4, 4, &[0]);
        inp.backgrounds = Some(&[0.5]);
        let mut fwd = rasterize_to_pixels(&inp, v).unwrap();
        let (vc, va) = (vec![1.0; 16], vec![1.0; 16]);
        assert!(rasterize_to_pixels_vjp(&inp, v, &fwd, &vc, &va, GradientMode::Exact).is_ok());
        fwd.final_t.clear();
        let e = rasterize_to_pixels_vjp(&inp, v, &fwd, &vc, &va, GradientMode::Exact)
            .unwrap_err()
            .to_string();
        assert!(e.contains("final_t: 0 values, expected 16"), "{e}");
    }
}
