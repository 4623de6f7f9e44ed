//! The differentiable 3D Gaussian splatting rasterizer: forward and exact backward.
//!
//! ```text
//! means3D, cov3D (scale, rotation | precomputed), colours (SH | precomputed), opacity
//!   └─► project (per Gaussian) ─► tiles (sorted list) ─► rasterize (per pixel)
//!         project_vjp ◄── per-Gaussian sums ◄── rasterize_vjp (per tile)
//! ```
//!
//! Semantics follow the Inria rasterizer (and the depth output of the fork
//! used by the D-3DGS paper) exactly; see the private modules `project`, `tiles`,
//! `rasterize` and `rasterize_vjp` for each stage's rules and orders.
//!
//! ## Conventions
//! - Inputs use the Inria Python API's layouts: `means3D [N,3]`, SH
//!   coefficients `[N,M,3]` (M the per-Gaussian stride, coefficient 0 = DC),
//!   precomputed colours `[N,3]`, opacities `[N]` (activated), scales `[N,3]`
//!   (activated), rotations `[N,4]` (w, x, y, z, **not normalised**),
//!   precomputed covariances `[N,6]` (upper triangle, row-major).
//! - Images are channel-major: colour `[3,H,W]`, depth `[1,H,W]`.
//! - Pixel `(i, j)` is sampled at `(i, j)` in the rasterizer's pixel space
//!   (`ndc2Pix`); `means2d` outputs are in that space.
//! - Gradients of `means2d` are in NDC units (pixel gradient × W/2, H/2), the
//!   quantity densification thresholds are calibrated for; third column 0.
//!
//! ## Deliberate deviations from upstream
//! - The scale gradient is `d/d(scale)` (includes `scale_modifier`).
//! - A Gaussian whose radius rounds to 0 is culled (upstream would still
//!   rasterize it if its tile rectangle is non-empty, possible only for an
//!   indefinite covariance).
//! - Per-Gaussian gradient sums have a fixed order instead of atomics.
//! - `GradientMode::Exact` is the true derivative (see its documentation);
//!   `GradientMode::Inria` reproduces upstream's backward formulas instead.
//!
//! ## Determinism and speed
//! The per-pixel stages work on one row of a tile (16 pixels) at a time, as
//! one vector: AVX-512, two AVX2 halves or portable scalar lanes, chosen at
//! run time ([`crate::kernels::fastmath::force_isa`] pins it), with the same
//! bits on every path (see the private modules `lanes` and `rasterize`). In f32
//! the rasterizer's `exp` is [`crate::kernels::fastmath::exp_f32`] (≤ 1 ulp);
//! f64 uses the pinned libm.
//! Forward: the per-Gaussian stage (covariance, projection, SH colour) runs
//! in parallel over batches of 16 Gaussians, each batch as vectors compiled
//! for the same instruction sets and tested against the one-Gaussian
//! functions (see the private module `preprocess`); then the binned list
//! gathers one record per entry, and the blend runs in parallel over image
//! rows (each row owns its pixels). Small frames on two or more threads
//! run on two workers that take their work from both ends (the private
//! `threads::from_both_ends`): each projects a consecutive run of
//! the Gaussians and sorts its keys, the two merge the two runs' orders
//! (see the private module `tiles`), so that no sort runs on one thread
//! while the other waits, and, on a pool of two, they blend the rows.
//! Backward: each tile accumulates into a buffer
//! indexed by list position, per entry the fixed pairwise sum of a row's 16
//! pixels, rows in ascending order; each Gaussian then sums its entries in
//! ascending list position; the chain rule runs per Gaussian. No result
//! depends on the number of threads or on the instruction set.

pub mod check;
pub(crate) mod lanes;
pub(crate) mod preprocess;
pub(crate) mod project;
pub(crate) mod rasterize;
pub(crate) mod rasterize_vjp;
pub mod scene;
pub mod stages;
pub(crate) mod tiles;
pub(crate) mod transpose;

use crate::camera::RasterCamera;
use crate::error::{Error, Result};
use crate::math::covariance::cov3d;
use crate::math::sh::{sh_to_color, ShColorSaved, MAX_SH_DEGREE};
use crate::math::Real;
use project::{Intrinsics, Projected};
use rasterize::{Blended, Splat};
use rayon::prelude::*;
use std::mem::MaybeUninit;

pub use rasterize_vjp::rasterize_vjp;

/// Tile side in pixels (`BLOCK_X = BLOCK_Y = 16`).
pub const BLOCK: usize = 16;

/// The most pixels an image may have (8192 × 8192): larger sizes are
/// refused before any buffer is allocated.
pub const MAX_PIXELS: usize = 1 << 26;

/// Where Gaussian colours come from.
#[derive(Clone, Copy, Debug)]
pub enum Colors<'a, T> {
    /// SH coefficients `[N, stride, 3]`, evaluated up to `degree` (≤ 3,
    /// `(degree+1)² ≤ stride`).
    Sh {
        /// `[N, stride, 3]` coefficients.
        coeffs: &'a [T],
        /// Coefficients per Gaussian.
        stride: usize,
        /// SH degree evaluated.
        degree: usize,
    },
    /// RGB per Gaussian, `[N, 3]`, used as given (no clamp).
    Precomputed(&'a [T]),
}

/// Where Gaussian 3D covariances come from.
#[derive(Clone, Copy, Debug)]
pub enum Covariances<'a, T> {
    /// Activated scales `[N, 3]`, unnormalised quaternions `[N, 4]` (w, x, y, z)
    /// and the global `scale_modifier`.
    ScaleRotation {
        /// `[N, 3]` activated scales.
        scales: &'a [T],
        /// `[N, 4]` quaternions (w, x, y, z), normalised inside.
        rotations: &'a [T],
        /// Global factor on every scale.
        scale_modifier: T,
    },
    /// `[N, 6]`: `[Σ00, Σ01, Σ02, Σ11, Σ12, Σ22]`.
    Precomputed(&'a [T]),
}

/// Everything the rasterizer reads.
#[derive(Clone, Copy, Debug)]
pub struct RasterInput<'a, T> {
    /// `[N, 3]` world-space means.
    pub means3d: &'a [T],
    /// Where colours come from.
    pub colors: Colors<'a, T>,
    /// `[N]` activated opacities.
    pub opacities: &'a [T],
    /// Where 3D covariances come from.
    pub covariances: Covariances<'a, T>,
    /// The camera.
    pub camera: &'a RasterCamera<T>,
    /// Background colour composited behind the Gaussians.
    pub background: [T; 3],
}

/// Forward outputs.
#[derive(Clone, Debug, PartialEq)]
pub struct RasterOutput<T> {
    /// `[3, H, W]` colour, background composited.
    pub color: Vec<T>,
    /// `[1, H, W]` `Σ z·α·T` (no background, no normalisation).
    pub depth: Vec<T>,
    /// `[N]` integer radius in pixels, 0 for culled Gaussians.
    pub radii: Vec<i32>,
    /// `[H, W]` final transmittance.
    pub final_t: Vec<T>,
    /// `[H, W]` 1-based list position of the last blended Gaussian (0: none).
    pub n_contrib: Vec<u32>,
    /// `[N, 2]` pixel-space centres (0 for culled Gaussians).
    pub means2d: Vec<T>,
}

/// What [`rasterize()`] saves for its backward, [`rasterize_vjp()`].
#[derive(Clone, Debug)]
pub struct RasterizeSaved<T> {
    intr: Intrinsics<T>,
    proj: Vec<Projected<T>>,
    colors: Vec<ShColorSaved<T>>,
    cov3d: Vec<[T; 6]>,
    binning: tiles::Binning,
    /// The splat data of each sorted entry, in list order.
    splats: Vec<Splat<T>>,
    /// (pixel, Gaussian) pairs the forward evaluated.
    evaluated: u64,
    /// Per image row: the entries at which some pixel of the row blends,
    /// with the mask of blending pixels, tile after tile.
    blended: Vec<Vec<Blended>>,
    /// `[H, grid_x]`: per image row and tile, the end of the tile's entries
    /// in the row's `blended`.
    blended_end: Vec<u32>,
    /// Per image row: the pool worker that blended it
    /// ([`crate::threads::worker_index`]), for the backward to offer each
    /// tile first to the worker that wrote its rows' records (speed only).
    row_worker: Vec<u16>,
}

impl<T: Real> RasterizeSaved<T> {
    /// Number of Gaussians rendered.
    pub fn len(&self) -> usize {
        self.proj.len()
    }
    /// Whether there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.proj.is_empty()
    }
    /// Number of (tile, Gaussian) entries in the sorted list.
    pub fn num_rendered(&self) -> usize {
        self.binning.list.len()
    }

    /// Per row of tiles: the pool worker that blended most of its image
    /// rows (the lowest-numbered on a tie).
    fn tile_row_workers(&self) -> Vec<usize> {
        self.row_worker
            .chunks(BLOCK)
            .map(|rows| {
                let count = |w: u16| rows.iter().filter(|&&x| x == w).count();
                rows.iter()
                    .copied()
                    .max_by_key(|&w| (count(w), std::cmp::Reverse(w)))
                    .unwrap_or(0) as usize
            })
            .collect()
    }

    /// (pixel, Gaussian) pairs the tile lists put in front of pixels:
    /// Σ over tiles of (pixels in the tile × entries in its list). Pixels that
    /// stop early evaluate fewer; this is the work measure benchmarks report.
    pub fn tile_pairs(&self) -> u64 {
        let grid_x = self.intr.grid[0] as usize;
        let mut total = 0u64;
        for (tile, r) in self.binning.ranges.iter().enumerate() {
            let [x0, x1, y0, y1] =
                rasterize::tile_bounds(tile, grid_x, self.intr.width, self.intr.height);
            total += ((x1 - x0) * (y1 - y0)) as u64 * (r[1] - r[0]) as u64;
        }
        total
    }
    /// (pixel, Gaussian) pairs the forward evaluated: Σ over pixels of the
    /// entries of its tile's list up to and including the one that stopped
    /// it (all of them if none did). Entries a row passes over because they
    /// cannot reach it (`rasterize::candidate_rows`) count too, as pairs
    /// decided without arithmetic; the count does not depend on that
    /// shortcut. The backward usually evaluates fewer
    /// ([`Self::pairs_replayed`]).
    pub fn pairs_evaluated(&self) -> u64 {
        self.evaluated
    }
    /// (pixel, Gaussian) pairs the backward evaluates: for each image row,
    /// each tile's pixels in that row times the entries at which at least
    /// one of them blends (the backward replays those entries, all the
    /// row's pixels of the tile at once, and walks back over them).
    pub fn pairs_replayed(&self) -> u64 {
        let grid_x = self.intr.grid[0] as usize;
        let (w, h) = (self.intr.width, self.intr.height);
        let mut total = 0u64;
        for py in 0..h {
            for tx in 0..grid_x {
                let entries = rasterize::row_tile_entries(&self.blended_end, grid_x, py, tx).len();
                total += (entries * BLOCK.min(w - tx * BLOCK)) as u64;
            }
        }
        total
    }
    /// Gaussian index of each sorted entry (tile-major, then depth, then index).
    pub fn sorted_list(&self) -> &[u32] {
        &self.binning.list
    }
    /// Whether each visible Gaussian's tangent clamp (x, y) was active.
    pub fn tangent_clamps(&self) -> Vec<[bool; 2]> {
        self.proj
            .iter()
            .map(|p| [p.clamped_x, p.clamped_y])
            .collect()
    }
    /// Whether each Gaussian's colour channel hit the lower clamp.
    pub fn color_clamps(&self) -> Vec<[bool; 3]> {
        self.colors.iter().map(|c| c.clamped).collect()
    }
}

/// How the backward differentiates the forward.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum GradientMode {
    /// The true derivative of the forward function as computed: zero gradient
    /// through the 0.99 alpha clamp where it is active; under the tangent clamp
    /// `t.x/t.z`, zero `t.x` gradient and the correct `t.z` term (upstream's is
    /// twice too large); transmittances from forward products, not division;
    /// `1/det²` exactly; the depth output differentiated (w.r.t. `z` and every
    /// alpha); the scale gradient is `d/d(scale)` (includes `scale_modifier`).
    /// Hard thresholds (power > 0, alpha < 1/255, transmittance stop, tiles,
    /// culling) are constants almost everywhere and contribute nothing.
    #[default]
    Exact,
    /// The Inria rasterizer's backward formulas as written (`backward.cu` of
    /// graphdeco-inria/diff-gaussian-rasterization @ 59f5f77, with the
    /// forward-only depth output of the fork the D-3DGS paper pins), so a port
    /// of that CUDA code can be compared tightly. Differences from
    /// [`GradientMode::Exact`], each a property of upstream, not a choice:
    ///
    /// 1. **Alpha clamp ignored**: where `o·G > 0.99` the forward uses 0.99
    ///    but the backward still uses `dα/dG = o`, `dα/do = G`.
    /// 2. **Transmittance recovered by division**: walking back to front from
    ///    the stored final `T`, `T ← T/(1 − α)`; the background enters as
    ///    `−T_final/(1 − α)·(bg·g)` per Gaussian. Same value as exact up to
    ///    rounding, which grows with `α` near 0.99.
    /// 3. **Tangent clamp, `t.z` term twice too large**: when `|t.x/t.z|` is
    ///    clamped, `dL/dt.x = 0` (correct) but `dL/dt.z` uses
    ///    `2·fx·tx'/tz³·dL/dJ02` with the clamped `tx' = ±lim·tz`, where the
    ///    true term is `fx·tx'/tz³·dL/dJ02`; likewise for y. Only
    ///    `grad_means3D` changes.
    /// 4. **Conic inverse regularised**: `1/(det² + 1e-7)` in place of
    ///    `1/det²` (relative change `1e-7/det²`, at most about 1.2e-5 since
    ///    the 0.3 dilation keeps `det ≥ 0.09`). Affects the gradients that
    ///    flows through the conic: means3D, scales and rotations or cov3D.
    /// 5. **No depth gradient**: the depth image is forward-only upstream, so
    ///    `grad_depth` is ignored.
    /// 6. **Scale gradient without `scale_modifier`**: the returned gradient
    ///    is `d/d(scale_modifier·scale)`; equal to exact when the modifier is 1.
    ///
    /// Same mathematics, different rounding (kept to follow upstream's order):
    /// the `means2D` gradient is scaled to NDC units (`× W/2, H/2`) per pixel
    /// before summing; the conic's `B` gradient is accumulated as half its
    /// value and doubled in the 2D-covariance formulas, which use `det − a·c`
    /// for `−b²`. Hard thresholds and the terminating Gaussian are treated as
    /// in exact mode. Sums over pixels keep the deterministic order of exact
    /// mode (upstream uses atomics, whose order is not reproducible).
    Inria,
}

impl GradientMode {
    /// Every mode, in a fixed order.
    pub const ALL: [GradientMode; 2] = [GradientMode::Exact, GradientMode::Inria];

    /// The mode's name in case-file metadata (`gradient=...`) and on the CLI.
    pub fn name(self) -> &'static str {
        match self {
            GradientMode::Exact => "exact",
            GradientMode::Inria => "inria",
        }
    }

    /// The mode called `name` (see [`GradientMode::name`]).
    pub fn from_name(name: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|m| m.name() == name)
            .ok_or_else(|| {
                Error::invalid(
                    "gradient mode",
                    format!("`{name}` is not one of: exact, inria"),
                )
            })
    }
}

/// Gradients of the rasterizer's inputs.
#[derive(Clone, Debug, PartialEq)]
pub struct RasterGrads<T> {
    /// `[N, 3]`.
    pub means3d: Vec<T>,
    /// `[N, 3]` gradient w.r.t. the NDC centre (pixel gradient × W/2, H/2);
    /// third column 0. Not an input: this is the statistic densification uses.
    pub means2d: Vec<T>,
    /// `[N, M, 3]` for SH (0 above the active degree) or `[N, 3]` for
    /// precomputed colours.
    pub colors: Vec<T>,
    /// `[N]`.
    pub opacities: Vec<T>,
    /// `[N, 3]` d/d(scale) or `[N, 6]` for precomputed covariances (an
    /// off-diagonal slot's gradient is w.r.t. the scalar filling both positions).
    pub scales_or_cov: Vec<T>,
    /// `[N, 4]`, empty for precomputed covariances.
    pub rotations: Vec<T>,
}

fn check_len(what: &str, len: usize, want: usize, n: usize) -> Result<()> {
    if len != want {
        return Err(Error::invalid(
            what,
            format!("{len} values for {n} Gaussians, expected {want}"),
        ));
    }
    Ok(())
}

impl<T: Real> RasterInput<'_, T> {
    /// Number of Gaussians, after checking every length against it.
    pub fn validate(&self) -> Result<usize> {
        if !self.means3d.len().is_multiple_of(3) {
            return Err(Error::invalid(
                "means3d",
                format!("length {} is not a multiple of 3", self.means3d.len()),
            ));
        }
        let n = self.means3d.len() / 3;
        check_len("opacities", self.opacities.len(), n, n)?;
        match self.colors {
            Colors::Sh {
                coeffs,
                stride,
                degree,
            } => {
                if degree > MAX_SH_DEGREE {
                    return Err(Error::invalid(
                        "sh degree",
                        format!("{degree} > {MAX_SH_DEGREE}"),
                    ));
                }
                if stride < (degree + 1) * (degree + 1) {
                    return Err(Error::invalid(
                        "sh stride",
                        format!("{stride} coefficients cannot hold degree {degree}"),
                    ));
                }
                // Checked: a huge stride must come back as an error, and the
                // kernels index `(i + 2·BATCH)·3·stride` (prefetch), so that
                // must fit too.
                let want = stride
                    .checked_mul(3)
                    .filter(|&s| (n + 2 * preprocess::BATCH).checked_mul(s).is_some())
                    .ok_or_else(|| {
                        Error::invalid(
                            "sh stride",
                            format!("{stride} coefficients per Gaussian overflow the index range"),
                        )
                    })?
                    * n;
                check_len("sh coefficients", coeffs.len(), want, n)?;
            }
            Colors::Precomputed(c) => check_len("colors_precomp", c.len(), 3 * n, n)?,
        }
        match self.covariances {
            Covariances::ScaleRotation {
                scales, rotations, ..
            } => {
                check_len("scales", scales.len(), 3 * n, n)?;
                check_len("rotations", rotations.len(), 4 * n, n)?;
            }
            Covariances::Precomputed(c) => check_len("cov3D_precomp", c.len(), 6 * n, n)?,
        }
        let cam = self.camera;
        if cam.width == 0 || cam.height == 0 {
            return Err(Error::invalid(
                "image size",
                format!("{}x{}", cam.width, cam.height),
            ));
        }
        if cam.width.saturating_mul(cam.height) > MAX_PIXELS {
            return Err(Error::invalid(
                "image size",
                format!(
                    "{}x{} pixels, more than {MAX_PIXELS}",
                    cam.width, cam.height
                ),
            ));
        }
        if cam.width.div_ceil(BLOCK) as u64 * cam.height.div_ceil(BLOCK) as u64 >= 1 << 31
            || n >= u32::MAX as usize
        {
            return Err(Error::invalid(
                "problem size",
                "too many tiles or Gaussians",
            ));
        }
        if !(cam.tanfovx > T::ZERO
            && cam.tanfovy > T::ZERO
            && cam.tanfovx.to_f64().is_finite()
            && cam.tanfovy.to_f64().is_finite())
        {
            return Err(Error::invalid(
                "camera",
                format!(
                    "tanfovx {} and tanfovy {} must be finite and > 0",
                    cam.tanfovx, cam.tanfovy
                ),
            ));
        }
        // (A NaN matrix culled every Gaussian without a word; an infinite
        // campos or background gave NaN pixels.)
        for (name, values) in [
            ("viewmatrix", &cam.viewmatrix[..]),
            ("projmatrix", &cam.projmatrix[..]),
            ("campos", &cam.campos[..]),
            ("background", &self.background[..]),
        ] {
            crate::error::check_finite(name, values)?;
        }
        Ok(n)
    }

    fn mean(&self, i: usize) -> [T; 3] {
        [
            self.means3d[3 * i],
            self.means3d[3 * i + 1],
            self.means3d[3 * i + 2],
        ]
    }

    /// The 3D covariance of Gaussian `i` (the one-Gaussian form the
    /// preprocessing batches are tested against).
    #[cfg_attr(not(test), allow(dead_code))]
    fn cov3d(&self, i: usize) -> [T; 6] {
        match self.covariances {
            Covariances::ScaleRotation {
                scales,
                rotations,
                scale_modifier,
            } => cov3d(
                [scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]],
                scale_modifier,
                [
                    rotations[4 * i],
                    rotations[4 * i + 1],
                    rotations[4 * i + 2],
                    rotations[4 * i + 3],
                ],
            ),
            Covariances::Precomputed(c) => std::array::from_fn(|k| c[6 * i + k]),
        }
    }

    fn color(&self, i: usize) -> ShColorSaved<T> {
        match self.colors {
            Colors::Sh {
                coeffs,
                stride,
                degree,
            } => sh_to_color(
                degree,
                &coeffs[i * stride * 3..(i + 1) * stride * 3],
                self.mean(i),
                self.camera.campos,
            ),
            Colors::Precomputed(c) => ShColorSaved {
                color: [c[3 * i], c[3 * i + 1], c[3 * i + 2]],
                clamped: [false; 3],
            },
        }
    }
}

/// Render: the forward pass. Fails with [`Error::Invalid`] on inconsistent
/// lengths or an unusable camera; never panics.
pub fn rasterize<T: Real>(input: &RasterInput<T>) -> Result<(RasterOutput<T>, RasterizeSaved<T>)> {
    forward(input, None)
}

/// The forward pass as a function of an additive offset on each projected NDC
/// centre (`[N, 2]`; upstream's dummy `means2D` input plays this role, with
/// value 0). [`RasterGrads::means2d`] is the gradient with respect to this
/// offset; this entry point exists so it can be checked by finite differences.
pub fn rasterize_with_ndc_offset<T: Real>(
    input: &RasterInput<T>,
    ndc_offset: &[T],
) -> Result<(RasterOutput<T>, RasterizeSaved<T>)> {
    forward(input, Some(ndc_offset))
}

/// The forward pass, with the pool's workers kept polling for work between
/// its stages (where the binning, between the per-Gaussian and per-pixel
/// stages, runs partly on one thread; [`crate::threads::keep_awake`]).
fn forward<T: Real>(
    input: &RasterInput<T>,
    ndc_offset: Option<&[T]>,
) -> Result<(RasterOutput<T>, RasterizeSaved<T>)> {
    crate::threads::keep_awake(|| forward_stages(input, ndc_offset))
}

/// A small frame's two [`tiles::Run`]s, with keys of `f32`'s width or of
/// `f64`'s.
enum Runs {
    Narrow([tiles::Run<u64>; 2]),
    Wide([tiles::Run<u128>; 2]),
}

impl Runs {
    /// [`tiles::merge_tile`] on these runs.
    #[inline]
    fn merge_tile<S: Copy>(
        &self,
        data: &[S],
        t: usize,
        list: &mut [MaybeUninit<u32>],
        copies: &mut [MaybeUninit<S>],
    ) {
        match self {
            Runs::Narrow(r) => tiles::merge_tile(r, data, t, list, copies),
            Runs::Wide(r) => tiles::merge_tile(r, data, t, list, copies),
        }
    }
}

/// The per-Gaussian stage and the binning of a small frame on two or more
/// threads ([`tiles::two_runs_apply`]): each of two workers projects a
/// consecutive run of the Gaussians (`preprocess::preprocess_in_two_runs`)
/// and sorts them into a [`tiles::Run`], so that the sort runs in parallel
/// on data its thread has just written; then the tiles' ranges. The list
/// and the splat copies are merged from the runs by the blend
/// ([`tiles::merge_tile`], [`rasterize::TileRowSplats`]). Stage `project`
/// includes the runs, `bin` the ranges.
fn project_and_bin_in_two_runs<T: Real>(
    intr: &Intrinsics<T>,
    input: &RasterInput<T>,
    n: usize,
    ndc_offset: Option<&[T]>,
) -> Result<(preprocess::Preprocessed<T>, Runs, Vec<[u32; 2]>)> {
    fn sorted<T: Real, K: tiles::Key>(
        intr: &Intrinsics<T>,
        input: &RasterInput<T>,
        n: usize,
        ndc_offset: Option<&[T]>,
    ) -> Result<(preprocess::Preprocessed<T>, [tiles::Run<K>; 2])> {
        let (pre, [a, b]) =
            preprocess::preprocess_in_two_runs(intr, input, n, ndc_offset, |first, proj| {
                tiles::run::<T, K>(first, proj, intr.grid)
            });
        Ok((pre, [a?, b?]))
    }
    let (pre, runs) = if std::mem::size_of::<T>() <= 4 {
        let (pre, runs) = sorted::<T, u64>(intr, input, n, ndc_offset)?;
        (pre, Runs::Narrow(runs))
    } else {
        let (pre, runs) = sorted::<T, u128>(intr, input, n, ndc_offset)?;
        (pre, Runs::Wide(runs))
    };
    stages::mark("project");
    let ranges = match &runs {
        Runs::Narrow(r) => tiles::ranges_of_runs(r),
        Runs::Wide(r) => tiles::ranges_of_runs(r),
    }?;
    stages::mark("bin");
    Ok((pre, runs, ranges))
}

/// One image row's pieces of the forward's outputs: its three colour
/// rows, depth, final transmittance and contributor count (not yet
/// written), its blend records, their per-tile ends (not yet written), and
/// the slot for the worker that blends it.
type RowSlices<'a, T> = (
    &'a mut [MaybeUninit<T>],
    &'a mut [MaybeUninit<T>],
    &'a mut [MaybeUninit<T>],
    &'a mut [MaybeUninit<T>],
    &'a mut [MaybeUninit<T>],
    &'a mut [MaybeUninit<u32>],
    &'a mut Vec<Blended>,
    &'a mut [MaybeUninit<u32>],
    &'a mut u16,
);

fn forward_stages<T: Real>(
    input: &RasterInput<T>,
    ndc_offset: Option<&[T]>,
) -> Result<(RasterOutput<T>, RasterizeSaved<T>)> {
    let n = input.validate()?;
    if let Some(o) = ndc_offset {
        check_len("ndc offset", o.len(), 2 * n, n)?;
    }
    let intr = Intrinsics::new(input.camera);
    let (w, h) = (intr.width, intr.height);

    // 1. Per-Gaussian preprocessing, and 2. binning, with the splat data
    //    of every entry in list order (on a small frame's path, the list
    //    and the copies are merged from the two runs by the blend, a tile
    //    row at a time).
    // A small frame on two or more threads: the two runs' path, and the rows'
    // write hints ([`rasterize::RowOut::prefetch_write`]).
    let small = tiles::two_runs_apply(n);
    let (pre, mut binning, mut splats, runs) = if small {
        let (pre, runs, ranges) = project_and_bin_in_two_runs(&intr, input, n, ndc_offset)?;
        // Written by the blend, below.
        let total = ranges.last().map_or(0, |r| r[1]) as usize;
        let binning = tiles::Binning {
            list: Vec::with_capacity(total),
            ranges,
        };
        (pre, binning, Vec::with_capacity(total), Some(runs))
    } else {
        let pre = preprocess::preprocess(&intr, input, n, ndc_offset);
        stages::mark("project");
        let binning = tiles::bin(&pre.proj, intr.grid)?;
        stages::mark("bin");
        // (`with_min_len`: a short list is copied on this thread, where
        // handing it out would cost more than the copy.)
        let splats: Vec<Splat<T>> = binning
            .list
            .par_iter()
            .with_min_len(1 << 14)
            .map(|&g| pre.splats[g as usize])
            .collect();
        stages::mark("gather");
        (pre, binning, splats, None)
    };

    // 3. Per-row blending.
    let grid_x = intr.grid[0] as usize;
    let hw = w * h;
    // The per-pixel outputs are written once each by the rows (every row
    // covers every tile it crosses, every pixel of each), so they are not
    // zeroed first: their pages are first touched by the row tasks, in
    // parallel. The rows' tiles cover the width exactly:
    assert_eq!(grid_x, w.div_ceil(BLOCK), "tile grid of the image width");
    let mut out = RasterOutput {
        color: Vec::with_capacity(3 * hw),
        depth: Vec::with_capacity(hw),
        radii: pre.radii,
        final_t: Vec::with_capacity(hw),
        n_contrib: Vec::with_capacity(hw),
        means2d: pre.means2d,
    };
    // SAFETY: `Runs::merge_tile` writes every slot it is given (or panics);
    // while `gather` lives, the list and `splats` are reached only through
    // it (the rows below read `splats` directly only when there is no
    // `gather`); `gather` is dropped after the blend, before they are used
    // again.
    let gather = runs.as_ref().map(|runs| unsafe {
        rasterize::TileRowSplats::new(
            |t, list, copies| runs.merge_tile(&pre.splats, t, list, copies),
            &binning.ranges,
            grid_x,
            &mut binning.list,
            &mut splats,
        )
    });
    // Row `py`'s view of the frame.
    let frame = |py: usize| {
        let ty = py / BLOCK;
        let (splats, ranges) = match &gather {
            Some(g) => g.tile_row(ty),
            None => (&splats[..], &binning.ranges[ty * grid_x..(ty + 1) * grid_x]),
        };
        rasterize::Frame {
            splats,
            ranges,
            width: w,
            bg: input.background,
        }
    };
    let mut blended: Vec<Vec<Blended>> = vec![Vec::new(); h];
    let mut blended_end: Vec<u32> = Vec::with_capacity(h * grid_x);
    let mut row_worker: Vec<u16> = vec![0; h];
    stages::mark("allocate");
    let (c0, rest) = out.color.spare_capacity_mut()[..3 * hw].split_at_mut(hw);
    let (c1, c2) = rest.split_at_mut(hw);
    // One row's blend: its pixels' outputs and records, and its worker.
    let blend_row = |py: usize,
                     (c0, c1, c2, depth, final_t, n_contrib, blended, blended_end, rw): RowSlices<
        '_,
        T,
    >| {
        *rw = crate::threads::worker_index() as u16;
        let mut row = rasterize::RowOut {
            color: [c0, c1, c2],
            depth,
            final_t,
            n_contrib,
            blended,
            blended_end,
        };
        if small {
            row.prefetch_write();
        }
        let mut ev = 0u64;
        rasterize::forward_row(&frame(py), py, &mut row, &mut ev);
        ev
    };
    let rows: Vec<RowSlices<'_, T>> = c0
        .chunks_mut(w)
        .zip(c1.chunks_mut(w))
        .zip(c2.chunks_mut(w))
        .zip(out.depth.spare_capacity_mut()[..hw].chunks_mut(w))
        .zip(out.final_t.spare_capacity_mut()[..hw].chunks_mut(w))
        .zip(out.n_contrib.spare_capacity_mut()[..hw].chunks_mut(w))
        .zip(blended.iter_mut())
        .zip(blended_end.spare_capacity_mut()[..h * grid_x].chunks_mut(grid_x))
        .zip(row_worker.iter_mut())
        .map(|((((((((c0, c1), c2), d), f), n), b), e), rw)| (c0, c1, c2, d, f, n, b, e, rw))
        .collect();
    let evaluated: u64 = if small && rayon::current_num_threads() == 2 {
        // A small frame on two workers: rows from both ends
        // ([`crate::threads::from_both_ends`]), so that each worker walks
        // one run of tile rows and the two end within about a row's time of
        // each other. On the 64×64 bench frame on a 2-core shared machine
        // (one binary alternating the two by pass), the forward's median
        // pass was 0.3–4.4 µs shorter (of about 300) than with rayon's
        // pieces of 8 rows in quiet minutes (benches/README.md,
        // "Rasterizer: small frames' steps handed out from both ends").
        let (a, b) = crate::threads::from_both_ends(
            rows,
            |_| 0u64,
            |ev, py, row| *ev += blend_row(py, row),
            |ev, _| ev,
        );
        a + b
    } else {
        rows.into_par_iter()
            // Stealable pieces of at most half a tile row: the rows' costs
            // are very uneven, and rayon's adaptive split alone left one
            // thread idle for up to a third of the blend.
            .with_max_len(8)
            .enumerate()
            .map(|(py, row)| blend_row(py, row))
            .sum()
    };
    if let Some(g) = gather {
        // Every tile row was gathered (each has at most `BLOCK` image rows
        // and at least one, and every image row asked for its copies).
        let total = g.written_len();
        drop(g);
        let total = total.expect("a tile row's list and splats were not written");
        // SAFETY: every slot of the list and the copies was written
        // (`written_len`: the ranges cover `0..total`); a panic in a row
        // propagates before these lines, leaving them empty.
        unsafe {
            binning.list.set_len(total);
            splats.set_len(total);
        }
    }
    // SAFETY: the rows are the consecutive `w`-long (`grid_x`-long) pieces
    // of each buffer's first `hw` (`h·grid_x`) spare slots, and every row
    // wrote every slot of its pieces (`forward_row`: each of the `grid_x`
    // tiles of the row, which cover `0..w` (asserted above), each pixel of
    // each tile); a panic in a row propagates before these lines, leaving
    // the buffers empty.
    unsafe {
        out.color.set_len(3 * hw);
        out.depth.set_len(hw);
        out.final_t.set_len(hw);
        out.n_contrib.set_len(hw);
        blended_end.set_len(h * grid_x);
    }
    stages::mark("blend");
    let state = RasterizeSaved {
        intr,
        proj: pre.proj,
        colors: pre.colors,
        cov3d: pre.cov3d,
        binning,
        splats,
        evaluated,
        blended,
        blended_end,
        row_worker,
    };
    Ok((out, state))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> RasterCamera<f32> {
        let mut view = [0.0f32; 16];
        for i in 0..4 {
            view[5 * i] = 1.0;
        }
        RasterCamera {
            viewmatrix: view,
            projmatrix: view,
            campos: [0.0; 3],
            tanfovx: 0.5,
            tanfovy: 0.5,
            width: 4,
            height: 4,
        }
    }

    fn input<'a>(
        cam: &'a RasterCamera<f32>,
        means: &'a [f32],
        coeffs: &'a [f32],
        stride: usize,
    ) -> RasterInput<'a, f32> {
        RasterInput {
            means3d: means,
            colors: Colors::Sh {
                coeffs,
                stride,
                degree: 0,
            },
            opacities: &means[..means.len() / 3],
            covariances: Covariances::Precomputed(&[]),
            camera: cam,
            background: [0.0; 3],
        }
    }

    /// A stride whose `N·stride·3` (or `3·stride`) overflows is an error, not
    /// an overflow panic, in both the forward and the backward pass.
    #[test]
    fn huge_sh_stride_is_an_error() {
        let cam = camera();
        let means = [0.0f32, 0.0, 2.0];
        for stride in [usize::MAX / 2, usize::MAX / 3 + 1, usize::MAX] {
            let e = rasterize(&input(&cam, &means, &[0.0; 3], stride)).unwrap_err();
            assert!(e.to_string().contains("sh stride"), "{e}");
        }
        // No Gaussians: `0·stride` fits, `3·stride` (the backward pass's
        // per-Gaussian width) does not.
        let (out, saved) = rasterize(&input(&cam, &[], &[], 1)).unwrap();
        let grad = vec![0.0f32; out.color.len()];
        let bad = input(&cam, &[], &[], usize::MAX / 2);
        assert!(rasterize(&bad).is_err());
        let e = rasterize_vjp(&bad, &saved, &grad, None, GradientMode::Inria).unwrap_err();
        assert!(e.to_string().contains("sh stride"), "{e}");
    }

    /// A camera matrix, centre or background that is not finite is an error
    /// naming it (a NaN matrix culled everything; an infinite centre or
    /// background gave NaN pixels).
    #[test]
    fn non_finite_camera_or_background_is_an_error() {
        let means = [0.0f32, 0.0, 2.0];
        let coeffs = [0.5f32; 3];
        let cov = [0.01f32, 0.0, 0.0, 0.01, 0.0, 0.01];
        let run = |cam: &RasterCamera<f32>, background: [f32; 3]| -> Result<()> {
            let i = RasterInput {
                covariances: Covariances::Precomputed(&cov),
                background,
                ..input(cam, &means, &coeffs, 1)
            };
            rasterize(&i).map(|_| ())
        };
        type Edit = fn(&mut RasterCamera<f32>);
        let edits: [(&str, Edit); 3] = [
            ("viewmatrix", |c| c.viewmatrix[5] = f32::NAN),
            ("projmatrix", |c| c.projmatrix[0] = f32::INFINITY),
            ("campos", |c| c.campos[2] = f32::NEG_INFINITY),
        ];
        for (name, edit) in edits {
            let mut cam = camera();
            edit(&mut cam);
            let e = run(&cam, [0.0; 3]).unwrap_err().to_string();
            assert!(e.contains(name) && e.contains("not finite"), "{e}");
        }
        let e = run(&camera(), [0.0, f32::NAN, 0.0])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("background") && e.contains("flat index 1"),
            "{e}"
        );
        run(&camera(), [0.0; 3]).unwrap();
    }
}
