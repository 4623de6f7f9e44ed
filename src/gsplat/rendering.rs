//! `rasterization(means, quats, scales, opacities, colors, viewmats, Ks,
//! width, height, ...)`: gsplat's composite renderer (`gsplat/rendering.py`;
//! 1.5.3 in Python, l.33–; 1.6 in C++ `csrc/Rendering.cpp` l.745–), and its
//! backward (the chain of the stages' backwards, as torch autograd runs it).
//!
//! 1. `fully_fused_projection` with the opacities (opacity-aware radii) and
//!    `calc_compensations = (rasterize_mode == "antialiased")`;
//! 2. per rasterized row (packed: visible (camera, Gaussian) pairs; dense:
//!    all), `opacities = o·compensation` in antialiased mode, else `o`;
//! 3. colours: post-activation `[N, D]` broadcast to each camera, or SH
//!    `[N, K, 3]` evaluated at `dirs = mean − campos` (`campos = −Rᵀt`) for
//!    visible rows and turned into `clamp_min(SH + 0.5, 0)` (`rendering.py`
//!    v1.5.3 l.491–525; 1.6 `Rendering.cpp` l.631–643);
//! 4. `isect_tiles` (1.5.3 radius box; 1.6 AccuTile with the conics and the
//!    row opacities, `Rendering.cpp` l.1303–1328) and `isect_offset_encode`;
//! 5. `rasterize_to_pixels` with the backgrounds (`render_mode = "RGB"`).

use super::isect::{isect_offset_encode, isect_tiles, IsectInput, Isects, TileRule};
use super::projection::{
    fully_fused_projection, fully_fused_projection_vjp, Camera, Covars, Projection,
    ProjectionCotangents, ProjectionInput, ProjectionSettings,
};
use super::raster::{
    rasterize_to_pixels, rasterize_to_pixels_vjp, RasterGrads, RasterInput, RasterOutput,
};
use super::sh::{sh_color, sh_color_vjp, MAX_DEGREE};
use super::{check_len, GradientMode, Version};
use crate::error::{Error, Result};
use crate::math::Real;

/// Where the colours come from.
#[derive(Clone, Copy, Debug)]
pub enum Colors<'a, T> {
    /// Post-activation colours `[N, D]`, used as given.
    Post {
        /// `[N, D]` colours.
        colors: &'a [T],
        /// Channels `D`.
        channels: usize,
    },
    /// SH coefficients `[N, K, 3]` with `sh_degree` (`(degree+1)² ≤ K`).
    Sh {
        /// `[N, K, 3]` coefficients.
        coeffs: &'a [T],
        /// Coefficients per Gaussian `K`.
        k: usize,
        /// SH degree evaluated.
        degree: usize,
    },
}

impl<T> Colors<'_, T> {
    /// Channels `D` of the rendered image.
    pub fn channels(&self) -> usize {
        match self {
            Colors::Post { channels, .. } => *channels,
            Colors::Sh { .. } => 3,
        }
    }
}

/// `rasterize_mode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum RasterizeMode {
    #[default]
    /// Opacities used as given.
    Classic,
    /// Opacities multiplied by the EWA-blur compensation (Mip-Splatting's 2D filter).
    Antialiased,
}

impl RasterizeMode {
    /// The mode's name as gsplat spells it (`classic`, `antialiased`).
    pub fn name(self) -> &'static str {
        match self {
            RasterizeMode::Classic => "classic",
            RasterizeMode::Antialiased => "antialiased",
        }
    }
    /// The mode called `s` (see [`RasterizeMode::name`]).
    pub fn from_name(s: &str) -> Result<Self> {
        match s.trim() {
            "classic" => Ok(RasterizeMode::Classic),
            "antialiased" => Ok(RasterizeMode::Antialiased),
            other => Err(Error::invalid(
                "rasterize_mode",
                format!("`{other}` is not one of: classic, antialiased"),
            )),
        }
    }
}

/// `rasterization`'s keyword arguments.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RasterizationSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Entries with camera-space z at or below this are culled.
    pub near_plane: f64,
    /// Entries with camera-space z at or above this are culled.
    pub far_plane: f64,
    /// Entries whose radius is at most this many pixels are culled (0: none).
    pub radius_clip: f64,
    /// Blur added to the 2D covariance's diagonal (pixels²).
    pub eps2d: f64,
    /// The packed layout (visible entries only) instead of the dense one.
    pub packed: bool,
    /// Tile side in pixels.
    pub tile_size: usize,
    /// Classic or antialiased.
    pub rasterize_mode: RasterizeMode,
    /// The gsplat version whose conventions apply.
    pub version: Version,
}

impl RasterizationSettings {
    /// gsplat's defaults: `near_plane=0.01`, `far_plane=1e10`,
    /// `radius_clip=0.0`, `eps2d=0.3`, `packed=True`, `tile_size=16`,
    /// `rasterize_mode="classic"`.
    pub fn new(width: usize, height: usize, version: Version) -> Self {
        RasterizationSettings {
            width,
            height,
            near_plane: 0.01,
            far_plane: 1e10,
            radius_clip: 0.0,
            eps2d: 0.3,
            packed: true,
            tile_size: 16,
            rasterize_mode: RasterizeMode::Classic,
            version,
        }
    }

    fn projection(&self) -> ProjectionSettings {
        ProjectionSettings {
            width: self.width,
            height: self.height,
            eps2d: self.eps2d,
            near_plane: self.near_plane,
            far_plane: self.far_plane,
            radius_clip: self.radius_clip,
            calc_compensations: self.rasterize_mode == RasterizeMode::Antialiased,
            version: self.version,
        }
    }
}

/// The tensors `rasterization` reads.
#[derive(Clone, Copy, Debug)]
pub struct RasterizationInput<'a, T> {
    /// `[N, 3]`.
    pub means: &'a [T],
    /// quats `[N,4]` + scales `[N,3]`, or covars `[N,6]`.
    pub covars: Covars<'a, T>,
    /// `[N]` activated.
    pub opacities: &'a [T],
    /// Post-activation colours or SH coefficients.
    pub colors: Colors<'a, T>,
    /// `[C, 4, 4]`.
    pub viewmats: &'a [T],
    /// `[C, 3, 3]`.
    pub ks: &'a [T],
    /// `[C, D]`, optional.
    pub backgrounds: Option<&'a [T]>,
}

/// Outputs: the images and gsplat's `meta`.
#[derive(Clone, Debug)]
pub struct Rasterization<T> {
    /// `[C, H, W, D]`.
    pub render_colors: Vec<T>,
    /// `[C, H, W, 1]`.
    pub render_alphas: Vec<T>,
    /// Dense projection (`meta["radii"]` etc. in the dense layout).
    pub projection: Projection<T>,
    /// Dense entry `c·N + g` of each rasterized row (packed: the visible ones).
    pub rows: Vec<usize>,
    /// `meta["opacities"]` per row.
    pub opacities: Vec<T>,
    /// Colours per row `[rows, D]` (after SH, `+0.5` and the clamp).
    pub colors: Vec<T>,
    /// `meta["tiles_per_gauss"]`, `meta["isect_ids"]`, `meta["flatten_ids"]`.
    pub isects: Isects,
    /// `meta["isect_offsets"]` `[C, tile_height, tile_width]`.
    pub isect_offsets: Vec<i32>,
    /// Tiles per image row.
    pub tile_width: usize,
    /// Tiles per image column.
    pub tile_height: usize,
    /// The rasterizer's outputs (final transmittance, `last_ids`).
    pub raster: RasterOutput<T>,
    /// For SH colours: whether `SH + 0.5` was clamped, per row and channel.
    pub color_clamped: Vec<bool>,
}

/// Gradients of `rasterization`'s inputs (and of `meta["means2d"]`).
#[derive(Clone, Debug, PartialEq)]
pub struct RasterizationGrads<T> {
    /// `[N, 3]`.
    pub v_means: Vec<T>,
    /// `[N, 4]` for quats/scales input; empty for covars.
    pub v_quats: Vec<T>,
    /// `[N, 3]` for quats/scales input; empty for covars.
    pub v_scales: Vec<T>,
    /// `[N, 6]` for covars input; empty for quats/scales.
    pub v_covars: Vec<T>,
    /// `[N]`.
    pub v_opacities: Vec<T>,
    /// `[N, D]` or `[N, K, 3]` (zero above the degree).
    pub v_colors: Vec<T>,
    /// `[C, D]` when backgrounds were given.
    pub v_backgrounds: Option<Vec<T>>,
    /// Per row `[rows, 2]` (packed `[nnz, 2]`, dense `[C, N, 2]`): the
    /// gradient of `meta["means2d"]`, in pixels, and its `absgrad`.
    pub v_means2d: Vec<T>,
    /// Per row, like `v_means2d`: gsplat's `absgrad` (sums of absolute per-pixel gradients).
    pub v_means2d_abs: Vec<T>,
}

impl<T: Real> RasterizationInput<'_, T> {
    fn validate(&self, s: &RasterizationSettings) -> Result<(usize, usize)> {
        let (c, n) = self.projection_input().validate(&s.projection())?;
        check_len("opacities", self.opacities.len(), n)?;
        match self.colors {
            Colors::Post { colors, channels } => {
                if channels == 0 {
                    return Err(Error::invalid("colors", "0 channels"));
                }
                match n.checked_mul(channels) {
                    Some(want) => check_len("colors", colors.len(), want)?,
                    None => {
                        return Err(Error::invalid(
                            "colors",
                            format!(
                                "{} values, expected [{n}, {channels}] (more than a slice holds)",
                                colors.len()
                            ),
                        ))
                    }
                }
            }
            Colors::Sh { coeffs, k, degree } => {
                if degree > MAX_DEGREE || (degree + 1) * (degree + 1) > k {
                    return Err(Error::invalid(
                        "sh_degree",
                        format!("{degree} with {k} coefficients (at most degree {MAX_DEGREE}, (degree+1)² ≤ K)"),
                    ));
                }
                match n.checked_mul(k).and_then(|v| v.checked_mul(3)) {
                    Some(want) => check_len("colors", coeffs.len(), want)?,
                    None => {
                        return Err(Error::invalid(
                            "colors",
                            format!(
                                "{} values, expected [{n}, {k}, 3] (more than a slice holds)",
                                coeffs.len()
                            ),
                        ))
                    }
                }
            }
        }
        super::check_frame(c, s.width, s.height, self.colors.channels())?;
        if let Some(bg) = self.backgrounds {
            check_len("backgrounds", bg.len(), c * self.colors.channels())?;
        }
        if s.tile_size == 0 || s.tile_size > 1024 {
            return Err(Error::invalid(
                "tile_size",
                format!("{} (1 to 1024)", s.tile_size),
            ));
        }
        Ok((c, n))
    }

    fn projection_input(&self) -> ProjectionInput<'_, T> {
        ProjectionInput {
            means: self.means,
            covars: self.covars,
            opacities: Some(self.opacities),
            viewmats: self.viewmats,
            ks: self.ks,
        }
    }

    fn dir(&self, cam: &Camera<T>, g: usize) -> [T; 3] {
        let off = cam.rt_t();
        std::array::from_fn(|a| self.means[3 * g + a] + off[a])
    }
}

/// Forward of `gsplat.rasterization` (`render_mode="RGB"`, pinhole camera).
pub fn rasterization<T: Real>(
    input: &RasterizationInput<T>,
    s: &RasterizationSettings,
) -> Result<Rasterization<T>> {
    let (c, n) = input.validate(s)?;
    let ps = s.projection();
    let proj = fully_fused_projection(&input.projection_input(), &ps)?;
    let rows: Vec<usize> = if s.packed {
        proj.packed_entries()
    } else {
        (0..c * n).collect()
    };
    let d = input.colors.channels();
    let mut opacities = Vec::with_capacity(rows.len());
    let mut colors = vec![T::ZERO; rows.len() * d];
    let mut color_clamped = vec![false; rows.len() * d];
    let cams: Vec<Camera<T>> = (0..c)
        .map(|ci| Camera::from_tensors(input.viewmats, input.ks, ci))
        .collect();
    let half = T::from_f64(0.5);
    for (row, &e) in rows.iter().enumerate() {
        let g = e % n;
        let o = input.opacities[g];
        opacities.push(match &proj.compensations {
            Some(cv) => o * cv[e],
            None => o,
        });
        let out = &mut colors[row * d..(row + 1) * d];
        match input.colors {
            Colors::Post { colors: src, .. } => out.copy_from_slice(&src[g * d..(g + 1) * d]),
            Colors::Sh { coeffs, k, degree } => {
                if proj.visible(e) {
                    let dir = input.dir(&cams[e / n], g);
                    sh_color(degree, dir, &coeffs[g * k * 3..(g + 1) * k * 3], 3, out);
                }
                for ch in 0..3 {
                    let v = out[ch] + half;
                    color_clamped[row * 3 + ch] = v < T::ZERO;
                    out[ch] = v.max(T::ZERO);
                }
            }
        }
    }
    let (row_means2d, row_radii, row_depths, row_conics, image_ids) = gather_rows(&proj, &rows);
    let tile_width = s.width.div_ceil(s.tile_size);
    let tile_height = s.height.div_ceil(s.tile_size);
    let rule = if s.version.accutile() {
        TileRule::AccuTile
    } else {
        TileRule::RadiusBox
    };
    let isects = isect_tiles(
        &IsectInput {
            means2d: &row_means2d,
            radii: &row_radii,
            depths: &row_depths,
            conics: Some(&row_conics),
            opacities: Some(&opacities),
            image_ids: Some(&image_ids),
            n,
        },
        s.tile_size,
        tile_width,
        tile_height,
        c,
        s.version,
        rule,
    )?;
    let isect_offsets =
        isect_offset_encode(&isects.isect_ids, c, tile_width, tile_height, s.version)?;
    let raster = rasterize_to_pixels(
        &RasterInput {
            means2d: &row_means2d,
            conics: &row_conics,
            colors: &colors,
            opacities: &opacities,
            backgrounds: input.backgrounds,
            channels: d,
            width: s.width,
            height: s.height,
            tile_size: s.tile_size,
            isect_offsets: &isect_offsets,
            flatten_ids: &isects.flatten_ids,
        },
        s.version,
    )?;
    Ok(Rasterization {
        render_colors: raster.render_colors.clone(),
        render_alphas: raster.render_alphas.clone(),
        projection: proj,
        rows,
        opacities,
        colors,
        isects,
        isect_offsets,
        tile_width,
        tile_height,
        raster,
        color_clamped,
    })
}

type Rows<T> = (Vec<T>, Vec<i32>, Vec<T>, Vec<T>, Vec<i32>);

fn gather_rows<T: Real>(p: &Projection<T>, rows: &[usize]) -> Rows<T> {
    let mut m2 = Vec::with_capacity(2 * rows.len());
    let mut r = Vec::with_capacity(2 * rows.len());
    let mut dp = Vec::with_capacity(rows.len());
    let mut cn = Vec::with_capacity(3 * rows.len());
    let mut img = Vec::with_capacity(rows.len());
    for &e in rows {
        m2.extend_from_slice(&p.means2d[2 * e..2 * e + 2]);
        r.extend_from_slice(&p.radii[2 * e..2 * e + 2]);
        dp.push(p.depths[e]);
        cn.extend_from_slice(&p.conics[3 * e..3 * e + 3]);
        img.push((e / p.n) as i32);
    }
    (m2, r, dp, cn, img)
}

/// Checks the per-row vectors of a forward state (altered through its
/// public fields, it could index past the projection or the rows): `rows`
/// strictly ascending below `C·N`, one opacity per row, `D` colours and
/// clamp flags per row, `tile_width·tile_height` tiles per image.
fn check_state<T>(fwd: &Rasterization<T>, ce: usize, d: usize) -> Result<()> {
    let mut next = 0usize;
    for (i, &e) in fwd.rows.iter().enumerate() {
        if e < next || e >= ce {
            return Err(Error::invalid(
                "rasterization state",
                format!(
                    "rows[{i}] = {e}: expected strictly ascending dense entries below C·N = {ce}"
                ),
            ));
        }
        next = e + 1;
    }
    // `rows.len() ≤ C·N ≤ MAX_PROJECTED` and `d` passed `check_frame`.
    let r = fwd.rows.len();
    check_len("rasterization.opacities", fwd.opacities.len(), r)?;
    check_len("rasterization.colors", fwd.colors.len(), r * d)?;
    check_len(
        "rasterization.color_clamped",
        fwd.color_clamped.len(),
        r * d,
    )
}

/// Rasterizer inputs of a forward (for the backward and for diagnostics).
pub fn raster_input<'a, T: Real>(
    input: &'a RasterizationInput<T>,
    s: &RasterizationSettings,
    fwd: &'a Rasterization<T>,
    rows: &'a Rows<T>,
) -> RasterInput<'a, T> {
    RasterInput {
        means2d: &rows.0,
        conics: &rows.3,
        colors: &fwd.colors,
        opacities: &fwd.opacities,
        backgrounds: input.backgrounds,
        channels: input.colors.channels(),
        width: s.width,
        height: s.height,
        tile_size: s.tile_size,
        isect_offsets: &fwd.isect_offsets,
        flatten_ids: &fwd.isects.flatten_ids,
    }
}

/// The rows of a forward, gathered (see [`raster_input`]).
///
/// # Panics
///
/// If a row is not an entry of the projection (a forward state altered
/// through its public fields; [`rasterization_vjp`] checks it first).
pub fn rows_of<T: Real>(fwd: &Rasterization<T>) -> Rows<T> {
    gather_rows(&fwd.projection, &fwd.rows)
}

/// Backward of [`rasterization`]: gradients of `<v_render_colors,
/// render_colors> + <v_render_alphas, render_alphas>` (`[C,H,W,D]`,
/// `[C,H,W,1]`).
pub fn rasterization_vjp<T: Real>(
    input: &RasterizationInput<T>,
    s: &RasterizationSettings,
    fwd: &Rasterization<T>,
    v_render_colors: &[T],
    v_render_alphas: &[T],
    mode: GradientMode,
) -> Result<RasterizationGrads<T>> {
    let (c, n) = input.validate(s)?;
    if fwd.projection.c != c || fwd.projection.n != n {
        return Err(Error::invalid(
            "rasterization state",
            format!(
                "computed for {}x{}, called with {c}x{n}",
                fwd.projection.c, fwd.projection.n
            ),
        ));
    }
    fwd.projection.check_state()?;
    check_state(fwd, c * n, input.colors.channels())?;
    let d = input.colors.channels();
    let rows = rows_of(fwd);
    let rin = raster_input(input, s, fwd, &rows);
    let rg: RasterGrads<T> = rasterize_to_pixels_vjp(
        &rin,
        s.version,
        &fwd.raster,
        v_render_colors,
        v_render_alphas,
        mode,
    )?;
    // Rows → dense entries, and the opacity / colour chains per Gaussian.
    let ce = c * n;
    let mut v_means2d = vec![T::ZERO; 2 * ce];
    let mut v_conics = vec![T::ZERO; 3 * ce];
    let mut v_comp = fwd
        .projection
        .compensations
        .as_ref()
        .map(|_| vec![T::ZERO; ce]);
    let mut v_opacities = vec![T::ZERO; n];
    let mut v_colors = vec![T::ZERO; input.colors.channels() * n];
    let mut v_sh_means = vec![T::ZERO; 3 * n];
    if let Colors::Sh { k, .. } = input.colors {
        v_colors = vec![T::ZERO; n * k * 3];
    }
    let cams: Vec<Camera<T>> = (0..c)
        .map(|ci| Camera::from_tensors(input.viewmats, input.ks, ci))
        .collect();
    // Rows are in ascending dense order, so each Gaussian's sums run in
    // ascending camera order.
    let mut vc_row = vec![T::ZERO; d];
    for (row, &e) in fwd.rows.iter().enumerate() {
        let g = e % n;
        v_means2d[2 * e..2 * e + 2].copy_from_slice(&rg.v_means2d[2 * row..2 * row + 2]);
        v_conics[3 * e..3 * e + 3].copy_from_slice(&rg.v_conics[3 * row..3 * row + 3]);
        let vo = rg.v_opacities[row];
        match (&fwd.projection.compensations, v_comp.as_mut()) {
            (Some(cv), Some(vcomp)) => {
                v_opacities[g] += vo * cv[e];
                vcomp[e] = vo * input.opacities[g];
            }
            _ => v_opacities[g] += vo,
        }
        let vc = &rg.v_colors[row * d..(row + 1) * d];
        match input.colors {
            Colors::Post { .. } => {
                for ch in 0..d {
                    v_colors[g * d + ch] += vc[ch];
                }
            }
            Colors::Sh { coeffs, k, degree } => {
                if !fwd.projection.visible(e) {
                    continue;
                }
                for ch in 0..3 {
                    vc_row[ch] = if fwd.color_clamped[row * 3 + ch] {
                        T::ZERO
                    } else {
                        vc[ch]
                    };
                }
                let dir = input.dir(&cams[e / n], g);
                let mut vk = vec![T::ZERO; k * 3];
                let vd = sh_color_vjp(
                    degree,
                    dir,
                    &coeffs[g * k * 3..(g + 1) * k * 3],
                    3,
                    &vc_row,
                    &mut vk,
                );
                for q in 0..k * 3 {
                    v_colors[g * k * 3 + q] += vk[q];
                }
                for a in 0..3 {
                    v_sh_means[3 * g + a] += vd[a];
                }
            }
        }
    }
    let zeros = vec![T::ZERO; ce];
    let pg = fully_fused_projection_vjp(
        &input.projection_input(),
        &s.projection(),
        &fwd.projection,
        &ProjectionCotangents {
            v_means2d: &v_means2d,
            v_depths: &zeros,
            v_conics: &v_conics,
            v_compensations: v_comp.as_deref(),
        },
        mode,
    )?;
    let mut v_means = pg.v_means;
    for (a, b) in v_means.iter_mut().zip(&v_sh_means) {
        *a += *b;
    }
    Ok(RasterizationGrads {
        v_means,
        v_quats: pg.v_quats,
        v_scales: pg.v_scales,
        v_covars: pg.v_covars,
        v_opacities,
        v_colors,
        v_backgrounds: rg.v_backgrounds,
        v_means2d: rg.v_means2d,
        v_means2d_abs: rg.v_means2d_abs,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `means`, `quats`, `scales`, `opacities`, `viewmats`, `Ks`.
    type Scene = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>);

    fn scene() -> Scene {
        let view = vec![
            1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0, 0.0, 0.0, 0.0, 1.0,
        ];
        let ks = vec![20.0, 0.0, 8.0, 0.0, 20.0, 8.0, 0.0, 0.0, 1.0];
        let means = vec![0.0, 0.0, 0.0, 0.3, 0.2, 0.5];
        let quats = vec![1.0, 0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0];
        (means, quats, vec![0.3; 6], vec![0.8, 0.6], view, ks)
    }

    fn input<'a>(t: &'a Scene, colors: Colors<'a, f64>) -> RasterizationInput<'a, f64> {
        RasterizationInput {
            means: &t.0,
            covars: Covars::QuatScale {
                quats: &t.1,
                scales: &t.2,
            },
            opacities: &t.3,
            colors,
            viewmats: &t.4,
            ks: &t.5,
            backgrounds: None,
        }
    }

    /// Colour counts whose sizes overflow are refused by the forward and
    /// the backward.
    #[test]
    fn overflowing_colour_sizes_are_refused() {
        let t = scene();
        let s = RasterizationSettings::new(16, 16, Version::V1_6);
        let sh = [0.1; 2 * 4 * 3];
        let good = input(
            &t,
            Colors::Sh {
                coeffs: &sh,
                k: 4,
                degree: 1,
            },
        );
        let fwd = rasterization(&good, &s).unwrap();
        let (vc, va) = (vec![1.0; 16 * 16 * 3], vec![0.5; 16 * 16]);
        for colors in [
            Colors::Post {
                colors: &[1.0, 2.0],
                channels: usize::MAX,
            },
            Colors::Sh {
                coeffs: &sh,
                k: usize::MAX / 2,
                degree: 1,
            },
        ] {
            let bad = input(&t, colors);
            let e = rasterization(&bad, &s).unwrap_err().to_string();
            assert!(
                e.contains("invalid colors") && e.contains("more than a slice"),
                "{e}"
            );
            let e = rasterization_vjp(&bad, &s, &fwd, &vc, &va, GradientMode::Exact)
                .unwrap_err()
                .to_string();
            assert!(e.contains("invalid colors"), "{e}");
        }
    }

    /// A forward state altered through its public fields is refused by the
    /// backward, naming what disagrees.
    #[test]
    fn an_altered_forward_state_is_refused() {
        let t = scene();
        let s = RasterizationSettings::new(16, 16, Version::V1_6);
        let sh = [0.1; 2 * 4 * 3];
        let inp = input(
            &t,
            Colors::Sh {
                coeffs: &sh,
                k: 4,
                degree: 1,
            },
        );
        let fwd = rasterization(&inp, &s).unwrap();
        assert_eq!(fwd.rows, [0, 1]);
        let (vc, va) = (vec![1.0; 16 * 16 * 3], vec![0.5; 16 * 16]);
        let mode = GradientMode::Gsplat;
        assert!(rasterization_vjp(&inp, &s, &fwd, &vc, &va, mode).is_ok());
        type Edit = fn(&mut Rasterization<f64>);
        let edits: [(Edit, &str); 7] = [
            (
                |f| f.rows[1] = 2,
                "rows[1] = 2: expected strictly ascending",
            ),
            (
                |f| f.rows[0] = 1,
                "rows[1] = 1: expected strictly ascending",
            ),
            (
                |f| f.projection.radii.clear(),
                "projection.radii: 0 values, expected 4",
            ),
            (
                |f| f.projection.compensations = Some(Vec::new()),
                "projection.compensations",
            ),
            (
                |f| {
                    f.opacities.pop();
                },
                "rasterization.opacities",
            ),
            (
                |f| f.color_clamped.clear(),
                "rasterization.color_clamped: 0 values, expected 6",
            ),
            (
                |f| f.colors.push(0.0),
                "rasterization.colors: 7 values, expected 6",
            ),
        ];
        for (edit, want) in edits {
            let mut bad = fwd.clone();
            edit(&mut bad);
            let e = rasterization_vjp(&inp, &s, &bad, &vc, &va, mode)
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{e}");
        }
    }
}
