//! The rasterizer's backward ([`rasterize_vjp`]) and the per-pixel backward
//! of the blending ([`super::rasterize`](mod@super::rasterize)).
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
//! [`LANES`] pixels. The forward saved, per row and
//! tile, the entries at which some pixel blends with the mask of blending
//! pixels ([`Blended`]); the backward replays them ([`replay_row`]: the same
//! products, so the same transmittances and `exp(power)`, without the skip
//! and stop tests or the entries no pixel blends) and then walks them in
//! reverse, each lane applying the per-pixel rule above (lanes that did not
//! blend an entry contribute exactly zero to it and keep their state).
//!
//! [`rasterize_vjp`] runs in three named steps: [`Steps::entry_gradients`]
//! (per tile, one [`EntryGrad`] per list entry), [`gaussian_entries`] (each
//! Gaussian's entries in ascending list position; serial, run beside the
//! first step) and [`Steps::gaussian_gradients`] (per Gaussian, the sum of
//! its entries and the chain rule through the projection, the colour and
//! the 3D covariance; in chunks of [`CHUNK`] Gaussians, each task forming
//! its chunk's sums first and then writing every output of its chunk once,
//! into result buffers that are never zeroed beforehand). A small frame on
//! two or more threads runs the same steps in one fixed part per worker
//! that has a CPU ([`crate::threads::workers_with_a_cpu`],
//! [`Steps::in_fixed_parts`]). The chain rule runs
//! several Gaussians per vector, each lane computing exactly the scalar
//! operations of its Gaussian ([`crate::math::pack::Arith`]), so the bits do
//! not depend on the width: in f32, 16 Gaussians in one AVX-512 register or
//! two AVX2 registers per value (the [`super::lanes`] types, whose values
//! stay in registers), 4 per [`crate::math::pack::Pack`] otherwise. A
//! block's inputs move from the Gaussians' rows into value-major packs, and
//! most of its results back, by transposes ([`super::transpose`]); the 2D
//! covariance, the clamp flags, the opacities and the 2D centres' gradients
//! move lane by lane.
//!
//! Determinism: the contributions of a row's 16 pixels to an entry are summed
//! by a fixed pairwise tree (lane `l` with `l + 8`, then `+ 4`, `+ 2`, `+ 1`),
//! whatever the instruction set; each entry adds its rows' sums in ascending
//! row order (only rows at which some pixel blended it); per-Gaussian sums
//! are formed afterwards in ascending list position (ascending tile). No sum
//! depends on the number of threads or the vector width.

use super::lanes::{Lanes, Scalar};
use super::project::{self, ProjectedGrad};
use super::rasterize::{
    self as raster, lane_x, replay_row, Blend, Blended, Record, Row, Splat, LANES,
};
use super::tiles;
use super::transpose::RowMover;
use super::{Colors, Covariances, GradientMode, RasterGrads, RasterInput, RasterizeSaved, BLOCK};
use crate::error::{Error, Result};
use crate::kernels::{filled, prefetch, prefetch_value, prefetch_write};
use crate::math::covariance::{cov3d_vjp, cov3d_vjp_scaled};
use crate::math::pack::Pack;
use crate::math::sh::{coeffs_for_degree, color_vjp};
use crate::math::Real;
use rayon::prelude::*;
use std::mem::MaybeUninit;
use std::sync::OnceLock;

/// The gradient one list entry (a Gaussian in one tile) receives from the
/// tile's pixels. In [`GradientMode::Inria`] the centre gradient is already
/// in NDC units and `conic[1]` holds half of `dL/dB`, as upstream
/// accumulates them.
#[derive(Clone, Copy, Debug, PartialEq)]
#[repr(C)]
pub(crate) struct EntryGrad<T> {
    /// dL/d(colour), RGB.
    pub color: [T; 3],
    /// dL/d(pixel-space centre).
    pub xy: [T; 2],
    /// dL/d(conic A, B, C).
    pub conic: [T; 3],
    /// dL/d(opacity).
    pub opacity: T,
    /// dL/d(view-space depth).
    pub depth: T,
}

/// Values per [`EntryGrad`], as laid out: colour 3, centre 2, conic 3,
/// opacity, depth.
const ENTRY_VALUES: usize = 10;

/// [`EntryGrad::add_sums`] masks: every value, the depth, the colour and
/// the depth.
const ALL_VALUES: u16 = (1 << ENTRY_VALUES) - 1;
const DEPTH: u16 = 1 << 9;
const COLOR_DEPTH: u16 = 0b111 | DEPTH;

impl<T: Real> EntryGrad<T> {
    /// All zeros.
    pub const ZERO: Self = EntryGrad {
        color: [T::ZERO; 3],
        xy: [T::ZERO; 2],
        conic: [T::ZERO; 3],
        opacity: T::ZERO,
        depth: T::ZERO,
    };

    /// The entries' values, [`ENTRY_VALUES`] per entry in field order.
    fn values(e: &[Self]) -> &[T] {
        const { assert!(std::mem::size_of::<EntryGrad<T>>() == ENTRY_VALUES * std::mem::size_of::<T>()) };
        // SAFETY: `EntryGrad` is `repr(C)` with ten `T` fields and no
        // padding (the size asserted above), so `e` is `10·len` `T`s.
        unsafe { std::slice::from_raw_parts(e.as_ptr() as *const T, e.len() * ENTRY_VALUES) }
    }

    /// Add `sums[f]` to value `f` (in [`Self::values`] order: colour 0–2,
    /// centre 3–4, conic 5–7, opacity 8, depth 9) for every bit `f` set in
    /// `which`; the other values are left as they are (not even `+ 0`,
    /// which would turn a `−0` into `+0`).
    #[inline(always)]
    fn add_sums(&mut self, sums: &[T; 16], which: u16) {
        let [c0, c1, c2] = &mut self.color;
        let [x0, x1] = &mut self.xy;
        let [k0, k1, k2] = &mut self.conic;
        let v = [
            c0,
            c1,
            c2,
            x0,
            x1,
            k0,
            k1,
            k2,
            &mut self.opacity,
            &mut self.depth,
        ];
        for (f, x) in v.into_iter().enumerate() {
            if which >> f & 1 != 0 {
                *x += sums[f];
            }
        }
    }

    /// Add `o` field by field.
    #[inline]
    fn add(&mut self, o: &Self) {
        for q in 0..3 {
            self.color[q] += o.color[q];
            self.conic[q] += o.conic[q];
        }
        for q in 0..2 {
            self.xy[q] += o.xy[q];
        }
        self.opacity += o.opacity;
        self.depth += o.depth;
    }
}

/// What the backward of one tile reads.
pub(crate) struct TileJob<'a, T> {
    /// The tile's gathered list.
    pub splats: &'a [Splat<T>],
    /// Per image row, the [`Blended`] entries the forward saved (every tile
    /// the row crosses, tile after tile).
    pub blended: &'a [Vec<Blended>],
    /// `[H, grid_x]`: per image row and tile, the end of the tile's entries
    /// in the row's `blended`.
    pub blended_end: &'a [u32],
    pub grid_x: usize,
    /// The tile's column.
    pub tx: usize,
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
        // `raster::row_tile_entries`, written out: through the helper this
        // loop compiled differently and the 64×64 backward measured 3–5%
        // slower.
        let ends = &job.blended_end[py * job.grid_x..(py + 1) * job.grid_x];
        let start = if job.tx == 0 {
            0
        } else {
            ends[job.tx - 1] as usize
        };
        let blended = &job.blended[py][start..ends[job.tx] as usize];
        if blended.is_empty() {
            continue;
        }
        // The row's cotangents, asked for before its replay: an image's
        // worth does not stay in one core's cache between passes, and
        // loaded after the replay each row waited for them (on one thread
        // of the Zen 4 machine the backward took 5–8% less time at 400×400
        // and 800×800, benches/README.md, "Rasterizer: the backward's
        // cotangents asked for first").
        let base = py * job.width + x0;
        for ch in 0..3 {
            prefetch(job.grad_color, ch * hw + base, nx);
        }
        if let Some(d) = job.grad_depth {
            prefetch(d, base, nx);
        }
        rec.clear();
        let row = Row { x0, nx, py };
        let t_final = replay_row::<V>(job.splats, blended, row, &k, rec);
        let g: [V; 3] = std::array::from_fn(|ch| {
            V::load(&lane_row(
                &job.grad_color[ch * hw + base..ch * hw + base + nx],
            ))
        });
        match job.mode {
            GradientMode::Exact => {
                let gd = match job.grad_depth {
                    Some(d) => lane_row(&d[base..base + nx]),
                    None => [zero; LANES],
                };
                exact_row::<V>(job, row, &k, rec, &g, V::load(&gd), grads);
            }
            GradientMode::Inria => inria_row::<V>(job, row, &k, rec, &g, t_final, grads),
        }
    }
}

/// A row's values (at most [`LANES`]) in lanes, zeros past its end. A full
/// row is one fixed-size copy (a vector load); a variable-length
/// `copy_from_slice` would call `memcpy`, which costs more than the copy
/// here (the call saves the vector registers).
#[inline(always)]
fn lane_row<T: Real>(src: &[T]) -> [T; LANES] {
    match <[T; LANES]>::try_from(src) {
        Ok(full) => full,
        Err(_) => std::array::from_fn(|l| src.get(l).copied().unwrap_or(T::ZERO)),
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
        // The row's contributions in the entry's value order (see
        // `EntryGrad::add_sums`), summed over the lanes together.
        let mut v = [zero; 16];
        v[0] = V::select(b, g[0] * at, zero);
        v[1] = V::select(b, g[1] * at, zero);
        v[2] = V::select(b, g[2] * at, zero);
        v[9] = V::select(b, gd * at, zero);
        if V::bits(live) == 0 {
            e.add_sums(&V::tree_sums(v), COLOR_DEPTH);
            continue;
        }
        // alpha = o·G, G = exp(power).
        let gp = dalpha * o * gg;
        v[8] = V::select(live, dalpha * gg, zero);
        v[3] = V::select(live, gp * (V::splat(-ca) * dx - V::splat(cb) * dy), zero);
        v[4] = V::select(live, gp * (V::splat(-cc) * dy - V::splat(cb) * dx), zero);
        v[5] = V::select(live, gp * (V::splat(-half) * dx * dx), zero);
        v[6] = V::select(live, gp * (-dx * dy), zero);
        v[7] = V::select(live, gp * V::splat(-half * dys * dys), zero);
        e.add_sums(&V::tree_sums(v), ALL_VALUES);
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
        // The row's contributions in the entry's value order (see
        // `EntryGrad::add_sums`), summed over the lanes together.
        let mut v = [zero; 16];
        for ch in 0..3 {
            let c = V::splat(s.color[ch]);
            let acc = last_alpha * last_color[ch] + (one - last_alpha) * accum[ch];
            dl_dalpha = dl_dalpha + (c - acc) * g[ch];
            v[ch] = V::select(b, dchannel_dcolor * g[ch], zero);
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
        v[3] = V::select(b, dl_dg * dg_ddelx * ndc[0], zero);
        v[4] = V::select(b, dl_dg * dg_ddely * ndc[1], zero);
        v[5] = V::select(b, neg_half * gdx * dx * dl_dg, zero);
        v[6] = V::select(b, neg_half * gdx * dy * dl_dg, zero);
        v[7] = V::select(b, neg_half * gdy * dy * dl_dg, zero);
        v[8] = V::select(b, gg * dl_dalpha, zero);
        grads[rc.j as usize].add_sums(&V::tree_sums(v), ALL_VALUES & !DEPTH);
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
        use super::rasterize::{as_f32, as_f32_ref, path, Path};
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
                let j32: &TileJob<'_, f32> = as_f32_ref(job);
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

/// The backward pass of [`super::rasterize()`]: gradients of
/// `<grad_color, color> + <grad_depth, depth>` with respect to every input
/// (`grad_color` `[3,H,W]`, `grad_depth` `[1,H,W]` or `None` for zero),
/// differentiated as `mode` says ([`GradientMode::Inria`] ignores
/// `grad_depth`). `input` must be the one `saved` was computed from; lengths
/// are checked.
pub fn rasterize_vjp<T: Real>(
    input: &RasterInput<T>,
    saved: &RasterizeSaved<T>,
    grad_color: &[T],
    grad_depth: Option<&[T]>,
    mode: GradientMode,
) -> Result<RasterGrads<T>> {
    check_cotangents(input, saved, grad_color, grad_depth)?;
    let steps = Steps {
        input,
        saved,
        grad_color,
        grad_depth,
        mode,
    };
    // The pool's workers keep polling for work between the steps
    // (`threads::keep_awake`).
    Ok(crate::threads::keep_awake(|| {
        let m = saved.num_rendered();
        let mut entry: Vec<EntryGrad<T>> = Vec::with_capacity(m);
        let slots = entry.spare_capacity_mut()[..m].as_mut_ptr();
        // SAFETY: `slots` points to `entry`'s first `m` spare slots, which
        // from here on are reached only through it (and `entry` is neither
        // read nor resized before the last use of the pieces).
        let tiles = tile_pieces(saved, unsafe { std::slice::from_raw_parts_mut(slots, m) });
        if tiles::two_runs_apply(saved.len()) && tiles.len() <= FEW_TILES {
            return steps.in_fixed_parts(tiles, Written(slots.cast_const().cast(), m));
        }
        let (start, index) = steps.entry_gradients(tiles);
        // SAFETY: the tile pieces are consecutive pieces of `entry`'s first
        // `m` spare slots that together cover all of them (`tile_pieces`),
        // and every job wrote each slot of its piece; a panic in a job
        // propagates before this line, leaving `entry` empty.
        unsafe { entry.set_len(m) };
        super::stages::mark("tiles, entry index");
        let grads = steps.gaussian_gradients(&entry, &start, &index);
        super::stages::mark("per Gaussian");
        grads
    }))
}

/// Check that `input` is the one `saved` was computed from (count and image
/// size) and the cotangents' lengths.
fn check_cotangents<T: Real>(
    input: &RasterInput<T>,
    saved: &RasterizeSaved<T>,
    grad_color: &[T],
    grad_depth: Option<&[T]>,
) -> Result<()> {
    let n = input.validate()?;
    let (w, h) = (saved.intr.width, saved.intr.height);
    if n != saved.len() || input.camera.width != w || input.camera.height != h {
        return Err(Error::invalid(
            "forward state",
            format!(
                "computed for {} Gaussians at {}x{}, called with {} at {}x{}",
                saved.len(),
                w,
                h,
                n,
                input.camera.width,
                input.camera.height
            ),
        ));
    }
    let hw = w * h;
    if grad_color.len() != 3 * hw {
        return Err(Error::invalid(
            "grad_color",
            format!("{} values, expected 3x{h}x{w}", grad_color.len()),
        ));
    }
    if let Some(d) = grad_depth {
        if d.len() != hw {
            return Err(Error::invalid(
                "grad_depth",
                format!("{} values, expected 1x{h}x{w}", d.len()),
            ));
        }
    }
    Ok(())
}

/// What the backward's steps read: the forward's input and state, the
/// cotangents and the mode.
struct Steps<'a, T> {
    input: &'a RasterInput<'a, T>,
    saved: &'a RasterizeSaved<T>,
    grad_color: &'a [T],
    grad_depth: Option<&'a [T]>,
    mode: GradientMode,
}

/// One piece per tile with entries of `slots` (the whole list's entry
/// gradients, not yet written), in tile order.
fn tile_pieces<'a, T: Real>(
    saved: &RasterizeSaved<T>,
    mut slots: &'a mut [MaybeUninit<EntryGrad<T>>],
) -> Vec<TilePiece<'a, T>> {
    let m = slots.len();
    let mut tiles = Vec::with_capacity(saved.binning.ranges.len());
    let mut pos = 0usize;
    for (tile, r) in saved.binning.ranges.iter().enumerate() {
        let (s, e) = (r[0] as usize, r[1] as usize);
        // Ranges are contiguous and ascending in tile order, from 0 to `m`.
        assert!(s == pos && e >= s, "tile ranges are not contiguous");
        if e == s {
            continue;
        }
        let (head, tail) = std::mem::take(&mut slots).split_at_mut(e - s);
        tiles.push(TilePiece {
            tile,
            start: s,
            out: head,
        });
        slots = tail;
        pos = e;
    }
    assert!(pos == m, "tile ranges do not cover the list");
    tiles
}

/// The whole list's entry gradients, for step 3 of [`Steps::in_fixed_parts`]
/// to read once step 1 has written them through its pieces.
struct Written<T>(*const EntryGrad<T>, usize);

// SAFETY: only read (`Written::get`), and only after every write.
unsafe impl<T: Sync> Sync for Written<T> {}

impl<T> Written<T> {
    /// # Safety
    /// Every one of the slots has been written, and none is written while
    /// the slice lives.
    unsafe fn get(&self) -> &[EntryGrad<T>] {
        // SAFETY: as the caller promises; `self.0` points to `self.1`
        // slots of one allocation.
        unsafe { std::slice::from_raw_parts(self.0, self.1) }
    }
}

impl<T: Real> Steps<'_, T> {
    /// Step 1 for one tile: its entries' gradients, accumulated in its
    /// piece, which it zeroes first.
    fn tile(&self, rec: &mut Vec<Record<T>>, t: TilePiece<'_, T>) {
        let saved = self.saved;
        let (w, h) = (saved.intr.width, saved.intr.height);
        let grid_x = saved.intr.grid[0] as usize;
        let job = TileJob {
            splats: &saved.splats[t.start..t.start + t.out.len()],
            blended: &saved.blended,
            blended_end: &saved.blended_end,
            grid_x,
            tx: t.tile % grid_x,
            bounds: raster::tile_bounds(t.tile, grid_x, w, h),
            width: w,
            height: h,
            bg: self.input.background,
            grad_color: self.grad_color,
            grad_depth: self.grad_depth,
            mode: self.mode,
        };
        // The rows replay only the entries they blended, a sparse walk the
        // hardware prefetcher does not follow: ask for the tile's whole
        // gathered list first.
        prefetch(job.splats, 0, job.splats.len());
        // On a small frame's path, the tile's entries' lines too, before
        // they are zeroed (the other core may have read them in the pass
        // before, when the allocator hands back the same block).
        if tiles::two_runs_apply(saved.len()) {
            prefetch_write(t.out, 0, t.out.len());
        }
        // Accumulated in place, where a scratch buffer of the task, copied
        // into the piece at the end, left the 64×64 bench frame's backward
        // 4–8 µs slower on one thread and 5–7 on two (benches/README.md,
        // "Rasterizer: the backward's tiles accumulated in place").
        tile_vjp(&job, filled(t.out, EntryGrad::ZERO), rec);
    }

    /// Step 1, per tile in parallel: the gradient of every list entry, each
    /// the sum over the tile's rows in ascending order (see the module
    /// docs); with step 2 ([`gaussian_entries`], serial) run beside it on
    /// the caller. Each tile zeroes its own piece of the result and
    /// accumulates into it, so the result buffer is never zeroed as a whole
    /// and its fresh pages are first touched in parallel.
    /// Each tile is offered first to the worker that blended most of its
    /// rows in the forward ([`crate::threads::run_on_named_workers`]): the
    /// tile pass reads the rows' saved records, which that worker wrote.
    /// On the trained hellwarrior frames (2 threads, 2-core development
    /// machine) the step took 8.1–8.6 ms for 10 cameras against 9.0–10.1
    /// with rayon's split in quiet minutes, and 8.2–8.5 in slow periods,
    /// where rayon's split had taken 16.7–20.6 (benches/README.md, "The
    /// backward's tiles on the workers that blended their rows"). Which
    /// worker computes a tile changes no result.
    fn entry_gradients(&self, tiles: Vec<TilePiece<'_, T>>) -> GaussianEntries {
        let owners = self.saved.tile_row_workers();
        let grid_x = self.saved.intr.grid[0] as usize;
        let most = tiles.iter().map(|t| t.out.len()).max().unwrap_or(0);
        let jobs = tiles
            .into_iter()
            .map(|t| (owners[t.tile / grid_x], t))
            .collect();
        crate::threads::run_on_named_workers(
            jobs,
            || Vec::with_capacity(most),
            |rec, t| self.tile(rec, t),
            || gaussian_entries(self.saved),
        )
    }

    /// Steps 1 to 3 of a small frame on two or more workers
    /// ([`tiles::two_runs_apply`]) with at most [`FEW_TILES`] tiles with
    /// entries, in one fixed part per worker that has a CPU
    /// ([`crate::threads::workers_with_a_cpu`]) and step
    /// ([`crate::threads::run_parts_in_two_steps`]: a worker goes on to its
    /// part of step 3 as soon as every part of steps 1 and 2 has ended,
    /// with no new job for the pool between them). Steps 1 and 2 are split
    /// into parts of about equal estimated cost
    /// ([`crate::threads::balanced_parts`]: a tile costs in proportion to
    /// the records the forward saved for it, see [`tile_costs`]), each
    /// part's jobs in tile order, step 2 among them; step 3 into one part
    /// of consecutive Gaussians per worker of about equal estimated cost
    /// ([`step3_cuts`]), each part's chunks in turn. Step 2 is handed to
    /// the pool before the split, so that a worker runs it while the caller
    /// splits the tiles; it belongs to the last part, and whichever thread
    /// reaches it first runs it ([`crate::threads::OneJob`]). Which worker
    /// computes what changes no result.
    fn in_fixed_parts(&self, tiles: Vec<TilePiece<'_, T>>, entry: Written<T>) -> RasterGrads<T> {
        let saved = self.saved;
        let threads = crate::threads::workers_with_a_cpu();
        let step2: OnceLock<EntriesAndCuts> = OnceLock::new();
        let entries = crate::threads::OneJob::new(|| {
            let (start, index) = gaussian_entries(saved);
            let cuts = step3_cuts(&start, threads);
            // Set once: the job runs once.
            let _ = step2.set((start, index, cuts));
        });
        let ctx = Ctx::new(self.input, saved, self.mode);
        let mut grads = ctx.empty_grads();
        let slots = ctx.out_slots(&mut grads);
        rayon::scope(|s| {
            // Step 2 goes to the pool first, so that a worker runs it while
            // this thread splits the tiles.
            s.spawn(|_| entries.run());
            let costs = tile_costs(saved);
            let mut jobs: Vec<(u64, Step1<T>)> = Vec::with_capacity(tiles.len() + 1);
            jobs.push((entries_cost(saved), Step1::Entries));
            jobs.extend(tiles.into_iter().map(|t| (costs[t.tile], Step1::Tile(t))));
            let mut firsts = crate::threads::balanced_parts(jobs, threads, |j| match j {
                Step1::Entries => 0,
                Step1::Tile(t) => 1 + t.tile,
            });
            // The part with step 2 last: the caller runs the first.
            firsts.sort_by_key(|p| p.iter().any(|j| matches!(j, Step1::Entries)));
            let parts: Vec<_> = firsts.into_iter().zip(0..).collect();
            let first = |part: Vec<Step1<T>>| {
                let most = part.iter().map(Step1::len).max().unwrap_or(0);
                let mut rec = Vec::with_capacity(most);
                for job in part {
                    match job {
                        Step1::Tile(t) => self.tile(&mut rec, t),
                        Step1::Entries => entries.run(),
                    }
                }
            };
            let second = |part: usize| {
                entries.wait();
                let (start, index, cuts) = step2.get().expect("step 2 ran");
                // SAFETY: every part of step 1 has ended, and the tile
                // pieces together cover the list (`tile_pieces`), each
                // slot written by its tile's job; nothing writes them now.
                let entry = unsafe { entry.get() };
                // SAFETY: the parts' ranges `cuts[i]..cuts[i + 1]` do not
                // overlap.
                let chunks = unsafe { slots.chunks(cuts[part], cuts[part + 1]) };
                ctx.chunks(entry, start, index, chunks);
            };
            crate::threads::run_parts_in_two_steps(
                parts,
                first,
                || super::stages::mark("tiles, entry index"),
                second,
            );
        });
        // SAFETY: every part of step 3 ran (a panic in one propagates
        // before this line), writing every slot of its chunks
        // (`Ctx::chunk`), which together cover the Gaussians: the parts'
        // ranges run from `cuts[0] = 0` to `cuts[threads] = n`, and `firsts`
        // has `threads` parts (`balanced_parts`), one per worker that has a
        // CPU.
        unsafe { ctx.set_lens(&mut grads) };
        super::stages::mark("per Gaussian");
        grads
    }

    /// Step 3, per Gaussian in parallel ([`Ctx::chunk`]), in chunks of
    /// at most [`CHUNK`] Gaussians: for a small frame on two or more
    /// workers ([`tiles::two_runs_apply`]) in one part of consecutive
    /// Gaussians per worker that has a CPU, each part's chunks in turn, the
    /// caller waiting
    /// for the others' parts by spinning ([`crate::threads::run_parts`]);
    /// else as rayon hands the chunks out.
    fn gaussian_gradients(
        &self,
        entry: &[EntryGrad<T>],
        start: &[usize],
        index: &[u32],
    ) -> RasterGrads<T> {
        let ctx = Ctx::new(self.input, self.saved, self.mode);
        let mut grads = ctx.empty_grads();
        let threads = crate::threads::workers_with_a_cpu();
        if tiles::two_runs_apply(self.saved.len()) {
            let parts = ctx.chunks_in_parts(&mut grads, threads);
            crate::threads::run_parts(parts, |part| ctx.chunks(entry, start, index, part));
        } else {
            let chunks = ctx.chunks_in_parts(&mut grads, 1).pop().unwrap_or_default();
            chunks.into_par_iter().for_each_init(Vec::new, |acc, out| {
                ctx.chunk(entry, start, index, acc, out)
            });
        }
        // SAFETY: every chunk ran (a panic in one propagates before this
        // line), writing every slot of its pieces (`Ctx::chunk`), which
        // together cover the outputs (`Ctx::chunks_in_parts`).
        unsafe { ctx.set_lens(&mut grads) };
        grads
    }
}

/// At most this many tiles with entries, a small frame's backward runs in
/// fixed parts ([`Steps::in_fixed_parts`]): a 128×128 frame's. At 400×400
/// (625 tiles) the parts' tiles, scattered over the image, measured 5 %
/// slower on two threads than rayon's pieces of neighbouring tiles.
const FEW_TILES: usize = 64;

/// One tile's job of step 1: its list from `start`, its entries' gradients
/// to write to `out`.
struct TilePiece<'a, T> {
    tile: usize,
    start: usize,
    out: &'a mut [MaybeUninit<EntryGrad<T>>],
}

/// A job of step 1 in fixed parts: a tile, or step 2.
enum Step1<'a, T> {
    Tile(TilePiece<'a, T>),
    Entries,
}

impl<T> Step1<'_, T> {
    /// The tile's entries (none for step 2).
    fn len(&self) -> usize {
        match self {
            Step1::Tile(t) => t.out.len(),
            Step1::Entries => 0,
        }
    }
}

/// Each Gaussian's entries ([`gaussian_entries`]).
type GaussianEntries = (Vec<usize>, Vec<u32>);

/// Step 2's result in fixed parts: each Gaussian's entries and the
/// starts of step 3's parts ([`step3_cuts`]).
type EntriesAndCuts = (Vec<usize>, Vec<u32>, Vec<usize>);

/// The estimated cost of every tile's backward in nanoseconds (row-major),
/// for balancing only: 16 per record the forward saved for its rows (a
/// tile replays and walks back exactly those; measured at 15.9–16.4 ns per
/// record over the 16 tiles of the 64×64 bench frame on the 2-core AMD
/// EPYC). One pass over the rows' per-tile ends.
fn tile_costs<T: Real>(saved: &RasterizeSaved<T>) -> Vec<u64> {
    let grid_x = saved.intr.grid[0] as usize;
    let mut costs = vec![0u64; saved.binning.ranges.len()];
    for (py, ends) in saved.blended_end.chunks_exact(grid_x).enumerate() {
        let row = &mut costs[py / BLOCK * grid_x..][..grid_x];
        // Each row's ends restart from 0 (`raster::row_tile_entries`).
        let mut prev = 0;
        for (c, &end) in row.iter_mut().zip(ends) {
            *c += 16 * u64::from(end - prev);
            prev = end;
        }
    }
    costs
}

/// The estimated cost of step 2 in nanoseconds, as [`tile_costs`]': about
/// 1 per list entry and a third per Gaussian (4.9–5.0 µs for the 64×64
/// bench frame's 2,600 Gaussians and their entries on the same machine).
fn entries_cost<T: Real>(saved: &RasterizeSaved<T>) -> u64 {
    (saved.num_rendered() + saved.len() / 3) as u64
}

/// Step 2: each Gaussian's entries in ascending list position (so ascending
/// tile), as `index[start[g]..start[g + 1]]`. A serial counting sort (about
/// 1.2 ns per entry), run beside step 1.
fn gaussian_entries<T: Real>(saved: &RasterizeSaved<T>) -> GaussianEntries {
    let n = saved.len();
    let list = &saved.binning.list;
    let mut start = vec![0usize; n + 1];
    for &g in list {
        start[g as usize + 1] += 1;
    }
    for i in 0..n {
        start[i + 1] += start[i];
    }
    let mut fill = start.clone();
    let mut index = vec![0u32; list.len()];
    for (pos, &g) in list.iter().enumerate() {
        index[fill[g as usize]] = pos as u32;
        fill[g as usize] += 1;
    }
    (start, index)
}

/// The starts of `parts` ranges of consecutive Gaussians, and the end `n`,
/// for step 3 in fixed parts: ranges of about equal estimated cost, 13 per
/// Gaussian and 1 per entry (each Gaussian's entries `start[g]..start[g +
/// 1]`, [`gaussian_entries`]). A least-squares fit of step 3's chunks over
/// four bench frames (64×64 with 1,000, 2,600 and 8,000 Gaussians, 96×96
/// with 6,000) on the 2-core development machine, one thread: 38 ns per
/// Gaussian and 3.0 per entry, within 2.7 % (rms).
fn step3_cuts(start: &[usize], parts: usize) -> Vec<usize> {
    let n = start.len() - 1;
    let cost = |g: usize| 13 * g + start[g];
    let total = cost(n);
    let mut cuts: Vec<usize> = (0..parts)
        .map(|k| {
            // The first Gaussian whose preceding ones cost the target.
            let target = total * k / parts;
            let (mut lo, mut hi) = (0, n);
            while lo < hi {
                let mid = (lo + hi) / 2;
                if cost(mid) < target {
                    lo = mid + 1;
                } else {
                    hi = mid;
                }
            }
            lo
        })
        .collect();
    cuts.push(n);
    cuts
}

/// The most colour values of a Gaussian (SH degree 3: 16 coefficients × RGB).
const MAX_COLOR_VALUES: usize = 3 * coeffs_for_degree(crate::math::sh::MAX_SH_DEGREE);

/// Gaussians per task of step 3: each task writes one contiguous piece of
/// every output.
const CHUNK: usize = 128;

/// One task's pieces of the outputs of step 3, not yet written.
struct OutChunk<'a, T> {
    /// The first Gaussian.
    start: usize,
    means3d: &'a mut [MaybeUninit<T>],
    means2d: &'a mut [MaybeUninit<T>],
    colors: &'a mut [MaybeUninit<T>],
    opacities: &'a mut [MaybeUninit<T>],
    scales_or_cov: &'a mut [MaybeUninit<T>],
    /// Empty for precomputed covariances.
    rotations: &'a mut [MaybeUninit<T>],
}

/// The first `len` spare slots of `v` (whose capacity is at least `len`).
fn spare<T>(v: &mut Vec<T>, len: usize) -> &mut [MaybeUninit<T>] {
    &mut v.spare_capacity_mut()[..len]
}

/// The spare slots of every output buffer ([`Ctx::out_slots`], borrowed for
/// `'g`), from which step 3 takes its chunks (in fixed parts, once a part
/// knows its range).
struct OutSlots<'g, T> {
    /// means3d, means2d, colors, opacities, scales_or_cov, rotations.
    slots: [*mut MaybeUninit<T>; 6],
    /// Values per Gaussian of each.
    widths: [usize; 6],
    /// The Gaussians the buffers have room for.
    n: usize,
    buffers: std::marker::PhantomData<&'g mut [MaybeUninit<T>]>,
}

// SAFETY: the slots are only reached through `OutSlots::chunk`, whose
// callers take disjoint chunks.
unsafe impl<T: Send> Sync for OutSlots<'_, T> {}

impl<'g, T> OutSlots<'g, T> {
    /// The chunks of at most [`CHUNK`] Gaussians, in turn, of the Gaussians
    /// `from..end`.
    ///
    /// # Safety
    /// No chunk taken from another range overlaps `from..end` while they
    /// live.
    unsafe fn chunks(&self, from: usize, end: usize) -> impl Iterator<Item = OutChunk<'g, T>> + '_ {
        assert!(
            from <= end && end <= self.n,
            "Gaussians {from}..{end} of {}",
            self.n
        );
        // SAFETY: within the buffers (asserted), and as the caller promises.
        (from..end)
            .step_by(CHUNK)
            .map(move |s| unsafe { self.chunk(s, CHUNK.min(end - s)) })
    }

    /// The chunk of `len` Gaussians from `s`.
    ///
    /// # Safety
    /// Within the Gaussians the buffers have room for, and no other chunk
    /// taken overlaps it while it lives.
    unsafe fn chunk(&self, s: usize, len: usize) -> OutChunk<'g, T> {
        // SAFETY: as the caller promises.
        let piece = |k: usize| unsafe {
            std::slice::from_raw_parts_mut(
                self.slots[k].add(self.widths[k] * s),
                self.widths[k] * len,
            )
        };
        OutChunk {
            start: s,
            means3d: piece(0),
            means2d: piece(1),
            colors: piece(2),
            opacities: piece(3),
            scales_or_cov: piece(4),
            rotations: piece(5),
        }
    }
}

/// What step 3 reads besides the entries' gradients, and the widths of its
/// outputs.
struct Ctx<'a, T> {
    input: &'a RasterInput<'a, T>,
    saved: &'a RasterizeSaved<T>,
    mode: GradientMode,
    /// Colour values per Gaussian (`3·stride` for SH, 3 precomputed).
    cstride: usize,
    /// Covariance gradient values per Gaussian (3 scales or 6 slots).
    cov_w: usize,
    /// Rotation gradient values per Gaussian (4, or 0 for precomputed
    /// covariances).
    rot_w: usize,
    /// SH coefficients and degree, `None` for precomputed colours.
    sh: Option<(&'a [T], usize)>,
    /// Scales, rotations and scale modifier, `None` for precomputed
    /// covariances.
    scale_rot: Option<(&'a [T], &'a [T], T)>,
}

impl<'a, T: Real> Ctx<'a, T> {
    fn new(
        input: &'a RasterInput<'a, T>,
        saved: &'a RasterizeSaved<T>,
        mode: GradientMode,
    ) -> Self {
        let (cstride, sh) = match input.colors {
            Colors::Sh {
                coeffs,
                stride,
                degree,
            } => (3 * stride, Some((coeffs, degree))),
            Colors::Precomputed(_) => (3, None),
        };
        let (cov_w, rot_w, scale_rot) = match input.covariances {
            Covariances::ScaleRotation {
                scales,
                rotations,
                scale_modifier,
            } => (3, 4, Some((scales, rotations, scale_modifier))),
            Covariances::Precomputed(_) => (6, 0, None),
        };
        Ctx {
            input,
            saved,
            mode,
            cstride,
            cov_w,
            rot_w,
            sh,
            scale_rot,
        }
    }

    /// Empty output buffers with room for every Gaussian's gradients.
    fn empty_grads(&self) -> RasterGrads<T> {
        let n = self.saved.len();
        RasterGrads {
            means3d: Vec::with_capacity(3 * n),
            means2d: Vec::with_capacity(3 * n),
            colors: Vec::with_capacity(self.cstride * n),
            opacities: Vec::with_capacity(n),
            scales_or_cov: Vec::with_capacity(self.cov_w * n),
            rotations: Vec::with_capacity(self.rot_w * n),
        }
    }

    /// The spare slots of `grads` ([`Ctx::empty_grads`]) as chunks of at
    /// most [`CHUNK`] consecutive Gaussians covering every Gaussian, in
    /// `parts` parts of `⌈n / parts⌉` Gaussians (the last may be shorter,
    /// and there are fewer where that leaves nothing), no chunk across the
    /// start of a part.
    fn chunks_in_parts<'g>(
        &self,
        grads: &'g mut RasterGrads<T>,
        parts: usize,
    ) -> Vec<Vec<OutChunk<'g, T>>> {
        let n = self.saved.len();
        let part_len = n.div_ceil(parts.max(1)).max(1);
        let slots = self.out_slots(grads);
        (0..n)
            .step_by(part_len)
            // SAFETY: the parts' ranges do not overlap.
            .map(|s| unsafe { slots.chunks(s, (s + part_len).min(n)) }.collect())
            .collect()
    }

    /// The spare slots of `grads` ([`Ctx::empty_grads`]), for chunks to
    /// be taken later.
    fn out_slots<'g>(&self, grads: &'g mut RasterGrads<T>) -> OutSlots<'g, T> {
        let n = self.saved.len();
        let widths = [3, 3, self.cstride, 1, self.cov_w, self.rot_w];
        OutSlots {
            slots: [
                spare(&mut grads.means3d, widths[0] * n).as_mut_ptr(),
                spare(&mut grads.means2d, widths[1] * n).as_mut_ptr(),
                spare(&mut grads.colors, widths[2] * n).as_mut_ptr(),
                spare(&mut grads.opacities, widths[3] * n).as_mut_ptr(),
                spare(&mut grads.scales_or_cov, widths[4] * n).as_mut_ptr(),
                spare(&mut grads.rotations, widths[5] * n).as_mut_ptr(),
            ],
            widths,
            n,
            buffers: std::marker::PhantomData,
        }
    }

    /// Set the lengths of `grads` to every Gaussian's gradients.
    ///
    /// # Safety
    /// Every slot of the chunks of [`Ctx::chunks_in_parts`] of `grads` was
    /// written.
    unsafe fn set_lens(&self, grads: &mut RasterGrads<T>) {
        let n = self.saved.len();
        // SAFETY: as the caller promises; `empty_grads` gave each buffer
        // room for these lengths.
        unsafe {
            grads.means3d.set_len(3 * n);
            grads.means2d.set_len(3 * n);
            grads.colors.set_len(self.cstride * n);
            grads.opacities.set_len(n);
            grads.scales_or_cov.set_len(self.cov_w * n);
            grads.rotations.set_len(self.rot_w * n);
        }
    }

    /// Step 3 for one chunk: each Gaussian's sum of its entries (`entry`
    /// at `index[start[g]..start[g + 1]]`) in ascending list position, then
    /// the chain rule through the projection, the colour (SH or
    /// precomputed) and the 3D covariance (scale and rotation or
    /// precomputed), writing every slot of `out` once (zeros for culled
    /// Gaussians). The sums of the whole chunk come first, so the
    /// scattered reads of several Gaussians' entries are in flight at once.
    fn chunk(
        &self,
        entry: &[EntryGrad<T>],
        start: &[usize],
        index: &[u32],
        acc: &mut Vec<EntryGrad<T>>,
        out: OutChunk<'_, T>,
    ) {
        let s = out.start;
        let len = out.opacities.len();
        // The chunk's entries lie scattered over the list: ask for all of
        // them in one pass that has no per-Gaussian branch, so their cache
        // misses overlap (in the sums below each Gaussian's loop ends at a
        // data-dependent count).
        for &pos in &index[start[s]..start[s + len]] {
            prefetch_value(entry, pos as usize);
        }
        // On a small frame's path, for the outputs' lines too, to be
        // written (the other core may have read them in the pass before).
        if tiles::two_runs_apply(self.saved.len()) {
            for p in [
                &out.means3d,
                &out.means2d,
                &out.colors,
                &out.opacities,
                &out.scales_or_cov,
                &out.rotations,
            ] {
                prefetch_write(p, 0, p.len());
            }
        }
        // The sums first: the reads of different Gaussians are independent.
        acc.clear();
        acc.extend((s..s + len).map(|i| {
            let mut a = EntryGrad::ZERO;
            if self.saved.proj[i].radius > 0 {
                for &pos in &index[start[i]..start[i + 1]] {
                    a.add(&entry[pos as usize]);
                }
            }
            a
        }));
        let mut o = Outputs {
            means3d: filled(out.means3d, T::ZERO),
            means2d: filled(out.means2d, T::ZERO),
            colors: filled(out.colors, T::ZERO),
            opacities: filled(out.opacities, T::ZERO),
            scales_or_cov: filled(out.scales_or_cov, T::ZERO),
            rotations: filled(out.rotations, T::ZERO),
        };
        chain_rule(self, s, acc, &mut o);
    }

    /// Step 3 for one task's chunks in turn ([`Ctx::chunk`]).
    fn chunks<'o>(
        &self,
        entry: &[EntryGrad<T>],
        start: &[usize],
        index: &[u32],
        chunks: impl IntoIterator<Item = OutChunk<'o, T>>,
    ) where
        T: 'o,
    {
        let mut acc = Vec::new();
        for out in chunks {
            self.chunk(entry, start, index, &mut acc, out);
        }
    }
}

/// One task's pieces of the outputs of step 3, zeroed.
struct Outputs<'a, T> {
    means3d: &'a mut [T],
    means2d: &'a mut [T],
    colors: &'a mut [T],
    opacities: &'a mut [T],
    scales_or_cov: &'a mut [T],
    rotations: &'a mut [T],
}

/// The chain rule of step 3 for the chunk of Gaussians starting at `s`
/// (`acc` their entry sums), several Gaussians per vector: 16 lanes in
/// AVX-512 registers ([`super::lanes::Avx512`]) or pairs of AVX2 registers
/// ([`super::lanes::Avx2`]) in
/// f32, 4 lanes of [`Pack`] otherwise. Every lane computes exactly what the
/// scalar [`project::project_vjp`], [`crate::math::sh::sh_to_color_vjp`] and
/// [`cov3d_vjp`] compute on that Gaussian alone (see
/// [`crate::math::pack`]), so the bits do not depend on the width.
fn chain_rule<T: Real>(ctx: &Ctx<'_, T>, s: usize, acc: &[EntryGrad<T>], o: &mut Outputs<'_, T>) {
    #[cfg(target_arch = "x86_64")]
    {
        use super::lanes::{Avx2, Avx512};
        use super::rasterize::{as_f32, as_f32_ref, path, Path};
        #[target_feature(enable = "avx512f")]
        unsafe fn avx512(
            ctx: &Ctx<'_, f32>,
            s: usize,
            acc: &[EntryGrad<f32>],
            o: &mut Outputs<'_, f32>,
        ) {
            chain_rule_lanes::<f32, 16, Avx512>(ctx, s, acc, o)
        }
        #[target_feature(enable = "avx2")]
        unsafe fn avx2(
            ctx: &Ctx<'_, f32>,
            s: usize,
            acc: &[EntryGrad<f32>],
            o: &mut Outputs<'_, f32>,
        ) {
            chain_rule_lanes::<f32, 16, Avx2>(ctx, s, acc, o)
        }
        let p = path::<T>();
        if p != Path::Portable {
            // SAFETY: `path` chooses a vector path only for T = f32 (so the
            // casts are to the same types) on a CPU with its feature.
            unsafe {
                let ctx: &Ctx<'_, f32> = as_f32_ref(ctx);
                let acc: &[EntryGrad<f32>] =
                    std::slice::from_raw_parts(acc.as_ptr() as *const EntryGrad<f32>, acc.len());
                let o: &mut Outputs<'_, f32> = as_f32(o);
                match p {
                    Path::Avx512 => avx512(ctx, s, acc, o),
                    _ => avx2(ctx, s, acc, o),
                }
            }
            return;
        }
    }
    chain_rule_lanes::<T, 4, Pack<T, 4>>(ctx, s, acc, o)
}

/// A lane-parallel number the chain rule of step 3 computes in, moved from
/// and to a [`Pack`] of `L` lanes.
trait ChainLanes<const L: usize>: crate::math::pack::Arith {
    fn from_pack(p: &Pack<Self::Elem, L>) -> Self;
    fn to_pack(self) -> Pack<Self::Elem, L>;
    fn mask(m: [bool; L]) -> Self::Mask;
}

impl<T: Real, const L: usize> ChainLanes<L> for Pack<T, L> {
    #[inline(always)]
    fn from_pack(p: &Pack<T, L>) -> Self {
        *p
    }
    #[inline(always)]
    fn to_pack(self) -> Pack<T, L> {
        self
    }
    #[inline(always)]
    fn mask(m: [bool; L]) -> [bool; L] {
        m
    }
}

#[cfg(target_arch = "x86_64")]
mod x86_lanes {
    use super::ChainLanes;
    use crate::math::pack::Pack;
    use crate::render::lanes::{Avx2, Avx512, Lanes};

    /// The lanes' bits (lane `l` is bit `l`).
    #[inline(always)]
    fn bits(m: [bool; 16]) -> u16 {
        let mut b = 0u16;
        for (l, &v) in m.iter().enumerate() {
            b |= (v as u16) << l;
        }
        b
    }

    /// The register types move through their 16-element loads and stores.
    macro_rules! chain_lanes {
        ($($t:ty),*) => {$(
            impl ChainLanes<16> for $t {
                #[inline(always)]
                fn from_pack(p: &Pack<f32, 16>) -> Self {
                    <Self as Lanes>::load(&p.0)
                }
                #[inline(always)]
                fn to_pack(self) -> Pack<f32, 16> {
                    let mut p = Pack([0.0; 16]);
                    self.store(&mut p.0);
                    p
                }
                #[inline(always)]
                fn mask(m: [bool; 16]) -> <Self as Lanes>::M {
                    <Self as Lanes>::from_bits(bits(m))
                }
            }
        )*};
    }
    chain_lanes!(Avx512, Avx2);
}

/// `W` packs as `N`s.
#[inline(always)]
fn from_packs<T: Real, const L: usize, N: ChainLanes<L, Elem = T>, const W: usize>(
    p: &[Pack<T, L>; W],
) -> [N; W] {
    let mut out = [N::ZERO; W];
    for a in 0..W {
        out[a] = N::from_pack(&p[a]);
    }
    out
}

/// `W` `N`s as packs.
#[inline(always)]
fn to_packs<T: Real, const L: usize, N: ChainLanes<L, Elem = T>, const W: usize>(
    v: &[N; W],
) -> [Pack<T, L>; W] {
    let mut out = [Pack([T::ZERO; L]); W];
    for a in 0..W {
        out[a] = v[a].to_pack();
    }
    out
}

/// [`chain_rule`] with `L` Gaussians per block, computed in `N`. Lanes past
/// the chunk's end repeat its last Gaussian; lanes of culled Gaussians are
/// computed and not written (their outputs stay zero). Each block's inputs
/// are moved from the Gaussians' rows into packs and its results back into
/// the rows ([`RowMover`]).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // lanes and slots as indices
fn chain_rule_lanes<T: Real, const L: usize, N: ChainLanes<L, Elem = T>>(
    ctx: &Ctx<'_, T>,
    s: usize,
    acc: &[EntryGrad<T>],
    o: &mut Outputs<'_, T>,
) {
    let (input, saved) = (ctx.input, ctx.saved);
    let (cstride, cov_w) = (ctx.cstride, ctx.cov_w);
    let len = acc.len();
    let proj = &saved.proj[s..s + len];
    let colors = &saved.colors[s..s + len];
    let cov3d = &saved.cov3d[s..s + len];
    let means = &input.means3d[3 * s..3 * (s + len)];
    // Colour values used per Gaussian (the rest of its `cstride` stay zero).
    let ncol = match ctx.sh {
        Some((_, degree)) => 3 * coeffs_for_degree(degree),
        None => 3,
    };
    let zero_pack = Pack([T::ZERO; L]);
    let mover = RowMover::new::<T>();
    let mut j0 = 0;
    while j0 < len {
        let cnt = L.min(len - j0);
        // Per lane, the position in the chunk and whether it is written.
        let jl: [usize; L] = std::array::from_fn(|l| j0 + l.min(cnt - 1));
        let live: [bool; L] = std::array::from_fn(|l| l < cnt && proj[jl[l]].radius > 0);
        let b = j0;
        j0 += cnt;
        // Ask for the next block's inputs while this one computes, as for
        // the SH coefficients below: read once per frame, they are far from
        // the caches, and the hardware prefetcher, with a dozen streams in
        // flight, leaves part of their latency exposed.
        let next = L.min(len - j0);
        prefetch(proj, j0, next);
        prefetch(cov3d, j0, next);
        prefetch(means, 3 * j0, 3 * next);
        prefetch(colors, j0, next);
        if let Some((scales, rotations, _)) = ctx.scale_rot {
            prefetch(scales, 3 * (s + j0), 3 * next);
            prefetch(rotations, 4 * (s + j0), 4 * next);
        }
        if !live.contains(&true) {
            continue;
        }
        // Each lane's rows of the inputs, moved into packs: lane `l`'s row
        // of a `w`-wide array whose row 0 is the chunk's first Gaussian
        // (`origin` 0) or the frame's (`origin` `s`). In a full block the
        // rows are evenly spaced.
        let full = cnt == L;
        let rows = |origin: usize, w: usize| -> [usize; L] {
            std::array::from_fn(|l| w * (origin + jl[l]))
        };
        let load = |src: &[T], origin: usize, w: usize, out: &mut [Pack<T, L>]| {
            if full {
                mover.load_strided(src, w * (origin + b), w, out)
            } else {
                mover.load(src, &rows(origin, w), out)
            }
        };
        let mut mean = [zero_pack; 3];
        load(means, 0, 3, &mut mean);
        let mut e = [zero_pack; ENTRY_VALUES];
        load(EntryGrad::values(acc), 0, ENTRY_VALUES, &mut e);
        let mut c3 = [zero_pack; 6];
        load(cov3d.as_flattened(), 0, 6, &mut c3);
        let cov2d: [Pack<T, L>; 3] = std::array::from_fn(|a| Pack(jl.map(|j| proj[j].cov2d[a])));
        let mean_n: [N; 3] = from_packs(&mean);
        let e_n: [N; ENTRY_VALUES] = from_packs(&e);
        let g = ProjectedGrad {
            xy: [e_n[3], e_n[4]],
            conic: [e_n[5], e_n[6], e_n[7]],
            depth: e_n[9],
        };
        let (mut gmean, gcov, gndc) = project::project_vjp(
            &saved.intr,
            mean_n,
            from_packs(&c3),
            from_packs(&cov2d),
            [
                N::mask(jl.map(|j| proj[j].clamped_x)),
                N::mask(jl.map(|j| proj[j].clamped_y)),
            ],
            g,
            ctx.mode,
        );
        let mut col = [zero_pack; MAX_COLOR_VALUES];
        match ctx.sh {
            Some((coeffs, degree)) => {
                // The coefficients are read once per frame, far from the
                // caches: ask for the next block's while this one computes.
                prefetch(coeffs, (s + j0) * cstride, L * cstride);
                let mut coef = [zero_pack; MAX_COLOR_VALUES];
                load(coeffs, s, cstride, &mut coef[..ncol]);
                let clamped: [[bool; L]; 3] =
                    std::array::from_fn(|ch| jl.map(|j| colors[j].clamped[ch]));
                let gd = color_vjp(
                    degree,
                    |q| N::from_pack(&coef[q]),
                    mean_n,
                    input.camera.campos.map(N::splat),
                    [
                        N::mask(clamped[0]),
                        N::mask(clamped[1]),
                        N::mask(clamped[2]),
                    ],
                    [e_n[0], e_n[1], e_n[2]],
                    |q, v| col[q] = v.to_pack(),
                );
                for a in 0..3 {
                    gmean[a] += gd[a];
                }
            }
            None => col[..3].copy_from_slice(&e[..3]),
        }
        let mut cov = [zero_pack; 6];
        let mut rot = [zero_pack; 4];
        match ctx.scale_rot {
            Some((scales, rotations, modifier)) => {
                let mut scale = [zero_pack; 3];
                let mut q = [zero_pack; 4];
                load(scales, s, 3, &mut scale);
                load(rotations, s, 4, &mut q);
                let modifier = N::splat(modifier);
                let (gs, gq) = match ctx.mode {
                    GradientMode::Exact => {
                        cov3d_vjp(from_packs(&scale), modifier, from_packs(&q), gcov)
                    }
                    GradientMode::Inria => {
                        cov3d_vjp_scaled(from_packs(&scale), modifier, from_packs(&q), gcov)
                    }
                };
                cov[..3].copy_from_slice(&to_packs(&gs));
                rot = to_packs(&gq);
            }
            None => cov = to_packs(&gcov),
        }
        let gmean = to_packs(&gmean);
        let gndc = to_packs(&gndc);
        // The live lanes' rows of the outputs (the others stay zero); the
        // chunk's outputs start at its first Gaussian (`origin` 0).
        let lanes = live
            .iter()
            .enumerate()
            .fold(0u32, |m, (l, &v)| m | (v as u32) << l);
        for l in (0..cnt).filter(|&l| live[l]) {
            let j = b + l;
            o.opacities[j] = e[8].0[l];
            o.means2d[3 * j] = gndc[0].0[l];
            o.means2d[3 * j + 1] = gndc[1].0[l];
        }
        let store = |dst: &mut [T], w: usize, vals: &[Pack<T, L>]| {
            if full {
                mover.store_strided(dst, w * b, w, lanes, vals)
            } else {
                mover.store(dst, &rows(0, w), lanes, vals)
            }
        };
        store(o.means3d, 3, &gmean);
        store(o.scales_or_cov, cov_w, &cov[..cov_w]);
        if ctx.scale_rot.is_some() {
            store(o.rotations, 4, &rot);
        }
        store(o.colors, cstride, &col[..ncol]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_costs_count_each_tiles_records_row_by_row() {
        // 40×24: partial tiles in the last column and row.
        let spec = crate::render::scene::SceneSpec::bench(40, 24, 300, 3);
        let s = crate::render::scene::random_scene(&spec).unwrap();
        let input = s.input(
            crate::render::scene::ColorSource::Sh,
            crate::render::scene::CovSource::ScaleRotation,
        );
        let (_, saved) = crate::render::rasterize(&input).unwrap();
        let grid_x = saved.intr.grid[0] as usize;
        let costs = tile_costs(&saved);
        assert_eq!(costs.len(), 3 * 2);
        for (tile, &c) in costs.iter().enumerate() {
            let [_, _, y0, y1] = raster::tile_bounds(tile, grid_x, 40, 24);
            let records: usize = (y0..y1)
                .map(|py| {
                    raster::row_tile_entries(&saved.blended_end, grid_x, py, tile % grid_x).len()
                })
                .sum();
            assert_eq!(c, 16 * records as u64, "tile {tile}");
        }
        assert!(costs.iter().filter(|&&c| c > 0).count() >= 4, "{costs:?}");
    }

    #[test]
    fn step3_cuts_split_the_cost_evenly_at_gaussians() {
        // Entries per Gaussian, uneven: 0, 1, ..., 9, then 40 of 50 each.
        let counts: Vec<usize> = (0..10).chain(std::iter::repeat_n(50, 40)).collect();
        let mut start = vec![0];
        for c in &counts {
            start.push(start.last().unwrap() + c);
        }
        let n = counts.len();
        let cost = |a: usize, b: usize| 13 * (b - a) + start[b] - start[a];
        for parts in 1..=7 {
            let cuts = step3_cuts(&start, parts);
            assert_eq!(cuts.len(), parts + 1);
            assert_eq!((cuts[0], cuts[parts]), (0, n), "{parts} parts");
            assert!(cuts.windows(2).all(|w| w[0] <= w[1]), "{cuts:?}");
            // Each cut is the first Gaussian at which the cost before it
            // reaches its share: one Gaussian earlier it had not.
            let total = cost(0, n);
            for (k, &c) in cuts.iter().enumerate().take(parts).skip(1) {
                let share = total * k / parts;
                assert!(cost(0, c) >= share, "{parts} parts, cut {k}");
                assert!(c == 0 || cost(0, c - 1) < share, "{parts} parts, cut {k}");
            }
        }
        // Two parts: the 10 cheap Gaussians (13·10 + 45) and 40 of 63
        // each, 2,695 in all; half (rounded down) is 1,347, first reached
        // after 10 + 19 (1,309 after 10 + 18).
        assert_eq!(step3_cuts(&start, 2), vec![0, 29, n]);
        assert_eq!(step3_cuts(&[0], 2), vec![0, 0, 0]);
    }

    /// An entry whose every value is distinct: value `f` is `f + 1`.
    fn numbered() -> EntryGrad<f64> {
        EntryGrad {
            color: [1.0, 2.0, 3.0],
            xy: [4.0, 5.0],
            conic: [6.0, 7.0, 8.0],
            opacity: 9.0,
            depth: 10.0,
        }
    }

    #[test]
    fn entry_values_are_in_field_order() {
        let e = [numbered(), EntryGrad::ZERO];
        let v = EntryGrad::values(&e);
        assert_eq!(v.len(), 2 * ENTRY_VALUES);
        for (f, &x) in v[..ENTRY_VALUES].iter().enumerate() {
            assert_eq!(x, (f + 1) as f64);
        }
        assert!(v[ENTRY_VALUES..].iter().all(|&x| x == 0.0));
    }

    #[test]
    fn add_sums_adds_to_the_chosen_values_only() {
        let sums: [f64; 16] = std::array::from_fn(|f| 100.0 * (f + 1) as f64);
        for f in 0..ENTRY_VALUES {
            let mut e = numbered();
            e.add_sums(&sums, 1 << f);
            let v = EntryGrad::values(std::slice::from_ref(&e));
            for (g, &x) in v.iter().enumerate() {
                let want = (g + 1) as f64 + if g == f { 100.0 * (g + 1) as f64 } else { 0.0 };
                assert_eq!(x, want, "mask bit {f}, value {g}");
            }
        }
        // A value not chosen keeps a −0 (adding +0 would make it +0).
        let mut e = EntryGrad {
            depth: -0.0,
            ..numbered()
        };
        e.add_sums(&[0.0; 16], COLOR_DEPTH & !DEPTH);
        assert!(e.depth.is_sign_negative());
        assert_eq!(ALL_VALUES, 0b11_1111_1111);
    }
}
