//! gsplat's conventions, as CPU reference stages: the functions of gsplat's
//! Python API (`gsplat.cuda._wrapper` and `gsplat.rendering`) with their
//! names, argument order, tensor layouts and outputs, at two released
//! versions ([`Version::V1_5_3`], [`Version::V1_6`]).
//!
//! ```text
//! quats, scales ─► quat_scale_to_covar_preci ─┐
//! means, viewmats, Ks ──────────► fully_fused_projection ─► radii, means2d, depths, conics, compensations
//!                                      │
//!                isect_tiles + isect_offset_encode ─► isect_ids, flatten_ids, isect_offsets
//!                                      │
//! colors (SH: spherical_harmonics) ─► rasterize_to_pixels ─► render_colors, render_alphas
//! ```
//!
//! [`rasterization`](rendering::rasterization) composes the stages as
//! `gsplat.rendering.rasterization` does, with its defaults.
//!
//! Every stage has its backward beside it, in two [`GradientMode`]s: `exact`
//! (the true derivative of the forward as computed here) and `gsplat`
//! (gsplat's backward formulas as written). docs/GSPLAT.md records every
//! formula with its source file and line at both versions, and lists the
//! differences between the modes with their measured sizes.
//!
//! ## Layouts
//! One batch (gsplat's leading `...` dimensions are absent), `C` cameras, `N`
//! Gaussians. Dense projection outputs are `[C, N, ...]`; packed outputs are
//! the visible `(camera, gaussian)` pairs in ascending `camera·N + gaussian`
//! order, `[nnz, ...]`, with `camera_ids` and `gaussian_ids`. Images are
//! `[C, H, W, D]` (channel last), alphas `[C, H, W, 1]`.
//!
//! ## Precision
//! gsplat's kernels compute in `float` whatever the tensor dtype. Here every
//! operation runs in the tensor's precision `T` (f32 or f64), in gsplat's
//! order of operations, with the project's pinned math library in place of
//! CUDA's `__expf`/`__logf`/`rsqrtf` (gsplat's `FAST_MATH=0` build uses the
//! correctly rounded forms). f64 is the exact-math reference.
//!
//! ## Determinism
//! Per-(camera, Gaussian) work is independent; the rasterizer owns one tile
//! per task; backward contributions are accumulated per sorted intersection
//! in row-major pixel order, then summed per entry in ascending intersection
//! order, then per Gaussian in ascending camera order. No result depends on
//! the number of threads.

pub mod covar;
pub mod isect;
pub mod projection;
pub mod raster;
pub mod rendering;
pub mod sh;

use crate::error::{Error, Result};
use crate::math::Real;

/// A released gsplat version whose conventions a stage follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Version {
    /// gsplat 1.5.3 (tag `v1.5.3`, the PyPI release of 2025-07-04):
    /// `MAX_ALPHA` 0.999, compensation `sqrt(max(0, det/det_blur))`,
    /// transmittance rebuilt by `1/(1 − α)` unguarded, tiles from the radius box.
    V1_5_3,
    /// gsplat 1.6.0 (commit `c3d59bbb`, "Update v1.6.0"): `MAX_ALPHA` 0.99,
    /// compensation floored at 0.005, `1 − α` floored at 1e-6 in the
    /// backward, tiles by AccuTile (exact ellipse-against-tile tests).
    #[default]
    V1_6,
}

impl Version {
    /// Every version, oldest first.
    pub const ALL: [Version; 2] = [Version::V1_5_3, Version::V1_6];

    /// The version string in case files and on the CLI.
    pub fn name(self) -> &'static str {
        match self {
            Version::V1_5_3 => "1.5.3",
            Version::V1_6 => "1.6",
        }
    }

    /// The version called `name` (`1.5.3`, or `1.6` / `1.6.0`).
    pub fn from_name(name: &str) -> Result<Self> {
        match name.trim() {
            "1.5.3" => Ok(Version::V1_5_3),
            "1.6" | "1.6.0" => Ok(Version::V1_6),
            other => Err(Error::invalid(
                "gsplat version",
                format!("`{other}` is not one of: 1.5.3, 1.6"),
            )),
        }
    }

    /// `MAX_ALPHA`: the clamp on `α = min(MAX_ALPHA, o·exp(−σ))`.
    pub fn max_alpha(self) -> f64 {
        match self {
            Version::V1_5_3 => 0.999,
            Version::V1_6 => 0.99,
        }
    }

    /// `MIN_COMPENSATION`, the floor of the antialiasing compensation (1.6 only).
    pub fn min_compensation(self) -> Option<f64> {
        match self {
            Version::V1_5_3 => None,
            Version::V1_6 => Some(0.005),
        }
    }

    /// `MIN_ONE_MINUS_ALPHA`, the floor of `1 − α` in the backward (1.6 only).
    pub fn min_one_minus_alpha(self) -> Option<f64> {
        match self {
            Version::V1_5_3 => None,
            Version::V1_6 => Some(1e-6),
        }
    }

    /// Whether `rasterization` assigns tiles with AccuTile (1.6) rather than
    /// the radius box (1.5.3).
    pub fn accutile(self) -> bool {
        self == Version::V1_6
    }
}

/// How a backward differentiates its forward.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum GradientMode {
    /// The true derivative of the forward as computed: transmittances from
    /// the forward's products, zero gradient through every clamp where it is
    /// active (the alpha clamp, a floored or zeroed compensation), the
    /// background gradient from the stored transmittance.
    #[default]
    Exact,
    /// gsplat's backward formulas as written at the selected version:
    /// transmittance rebuilt from `1 − render_alpha` by division (1.6: with
    /// `1 − α` floored at 1e-6), `dcomp/dratio = 0.5/(comp + 1e-6)` even
    /// where the compensation is clamped, the background gradient from
    /// `1 − render_alpha`. docs/GSPLAT.md lists each difference and its size.
    Gsplat,
}

impl GradientMode {
    /// Every mode, in a fixed order.
    pub const ALL: [GradientMode; 2] = [GradientMode::Exact, GradientMode::Gsplat];

    /// The mode's name in case files and on the CLI.
    pub fn name(self) -> &'static str {
        match self {
            GradientMode::Exact => "exact",
            GradientMode::Gsplat => "gsplat",
        }
    }

    /// The mode called `name` (`exact` or `gsplat`).
    pub fn from_name(name: &str) -> Result<Self> {
        Self::ALL
            .into_iter()
            .find(|m| m.name() == name.trim())
            .ok_or_else(|| {
                Error::invalid(
                    "gradient mode",
                    format!("`{name}` is not one of: exact, gsplat"),
                )
            })
    }
}

/// gsplat's constants in the working precision.
#[derive(Clone, Copy, Debug)]
pub struct Constants<T> {
    /// `ALPHA_THRESHOLD = 1/255`.
    pub alpha_threshold: T,
    /// `GAUSSIAN_EXTEND = 3.33`.
    pub gaussian_extend: T,
    /// `MAX_ALPHA` of the version.
    pub max_alpha: T,
    /// `TRANSMITTANCE_THRESHOLD = 1e-4`.
    pub transmittance_threshold: T,
    /// `MIN_COMPENSATION²` of the version, or 0 (1.5.3's `max(0, ·)`).
    pub min_compensation_sq: T,
    /// `MIN_ONE_MINUS_ALPHA` of the version, if any.
    pub min_one_minus_alpha: Option<T>,
}

impl<T: Real> Constants<T> {
    /// The constants of `version`, each rounded once from its decimal literal.
    pub fn new(version: Version) -> Self {
        let mc = version.min_compensation().map_or(T::ZERO, |m| {
            let m = T::from_f64(m);
            m * m
        });
        Constants {
            alpha_threshold: T::ONE / T::from_f64(255.0),
            gaussian_extend: T::from_f64(3.33),
            max_alpha: T::from_f64(version.max_alpha()),
            transmittance_threshold: T::from_f64(1e-4),
            min_compensation_sq: mc,
            min_one_minus_alpha: version.min_one_minus_alpha().map(T::from_f64),
        }
    }
}

/// The most values (`images · height · width · channels`) an image tensor
/// of the rasterizing stages may have: 2^30, 4 GiB in f32.
pub const MAX_IMAGE_VALUES: usize = 1 << 30;

/// Checks the size of `images` images of `width × height` pixels and
/// `channels` channels before any buffer of that size is allocated: each
/// side 1 to 65536 (the projection's limit), at most
/// [`crate::render::MAX_PIXELS`] pixels over all images and at most
/// [`MAX_IMAGE_VALUES`] values.
pub(crate) fn check_frame(
    images: usize,
    width: usize,
    height: usize,
    channels: usize,
) -> Result<()> {
    let pixels = images
        .checked_mul(width)
        .and_then(|p| p.checked_mul(height));
    let values = pixels.and_then(|p| p.checked_mul(channels));
    let why = if !(1..=65536).contains(&width) || !(1..=65536).contains(&height) {
        "each side 1 to 65536"
    } else if pixels.is_none_or(|p| p > crate::render::MAX_PIXELS) {
        "at most 2^26 pixels over all images"
    } else if values.is_none_or(|v| v > MAX_IMAGE_VALUES) {
        "at most 2^30 values (images · pixels · channels)"
    } else {
        return Ok(());
    };
    Err(Error::invalid(
        "image size",
        format!("{images} images of {width}x{height} pixels and {channels} channels ({why})"),
    ))
}

/// Checks `len == want` for the tensor `what`.
pub(crate) fn check_len(what: &str, len: usize, want: usize) -> Result<()> {
    if len != want {
        return Err(Error::invalid(
            what,
            format!("{len} values, expected {want}"),
        ));
    }
    Ok(())
}

/// Rows of a 3×3 row-major matrix.
pub(crate) type Mat3<T> = [[T; 3]; 3];

#[inline]
pub(crate) fn matmul3<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> Mat3<T> {
    std::array::from_fn(|i| {
        std::array::from_fn(|j| a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j])
    })
}

#[inline]
pub(crate) fn transpose3<T: Real>(a: &Mat3<T>) -> Mat3<T> {
    std::array::from_fn(|i| std::array::from_fn(|j| a[j][i]))
}

#[inline]
pub(crate) fn add3<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> Mat3<T> {
    std::array::from_fn(|i| std::array::from_fn(|j| a[i][j] + b[i][j]))
}

/// The six upper-triangle entries `[00, 01, 02, 11, 12, 22]` as a symmetric matrix.
#[inline]
pub(crate) fn sym_from_triu<T: Real>(c: &[T]) -> Mat3<T> {
    [[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]]
}

/// gsplat's `viewmats [4,4]` (row-major world-to-camera) and `Ks [3,3]` for
/// a project camera, with the principal point at `(W/2, H/2)`: the
/// convention under which gsplat's pixel offsets equal the Inria
/// rasterizer's (gsplat samples pixel `j` at `j + 0.5`, Inria at `j` with
/// centres shifted by `−0.5`).
pub fn camera_tensors<T: Real>(cam: &crate::camera::Camera) -> ([T; 16], [T; 9]) {
    let w2c = cam.w2c();
    let (fx, fy) = cam.focal();
    let view = std::array::from_fn(|k| T::from_f64(w2c[k / 4][k % 4]));
    let k = [
        fx,
        0.0,
        cam.width as f64 / 2.0,
        0.0,
        fy,
        cam.height as f64 / 2.0,
        0.0,
        0.0,
        1.0,
    ];
    (view, k.map(T::from_f64))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_are_bounded_without_overflow() {
        assert!(check_frame(1, 65536, 1024, 3).is_ok());
        assert!(check_frame(4, 2048, 2048, 64).is_ok());
        for (i, w, h, d, why) in [
            (1, 0, 8, 3, "each side"),
            (1, 65537, 8, 3, "each side"),
            (1, 1 << 16, 1 << 16, 3, "2^26 pixels"),
            (1 << 40, 1 << 16, 1 << 16, 3, "2^26 pixels"),
            (1, 8192, 8192, 17, "2^30 values"),
            (1, 8, 8, usize::MAX, "2^30 values"),
        ] {
            let err = check_frame(i, w, h, d).unwrap_err().to_string();
            assert!(err.contains(why), "{err}");
        }
    }
}
