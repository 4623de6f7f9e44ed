//! `fully_fused_projection` (pinhole; classic and antialiased; dense and
//! packed) and its backward.
//!
//! Forward, per (camera, Gaussian), as gsplat's
//! `projection_ewa_3dgs_fused_fwd_kernel` (`csrc/ProjectionEWA3DGSFused.cu`,
//! v1.5.3 l.17–212, 1.6 l.44–220) with `persp_proj` and `add_blur`
//! (`include/Utils.cuh`, v1.5.3 l.380–388 and l.498–537):
//! 1. `mean_c = R·mean + t` (`viewmats` row-major world-to-camera); cull if
//!    `z < near_plane || z > far_plane`;
//! 2. `covar_c = R Σ Rᵀ`, Σ from `covars` or `quat_scale_to_covar_preci`;
//! 3. `tx = z·min(lim_x_pos, max(−lim_x_neg, x/z))` with
//!    `lim_x_pos = (W − cx)/fx + 0.3·tan_fovx`, `lim_x_neg = cx/fx + 0.3·tan_fovx`,
//!    `tan_fovx = 0.5·W/fx` (likewise y); `J = [[fx/z, 0, −fx·tx/z²], [0, fy/z, −fy·ty/z²]]`;
//!    `cov2d = J covar_c Jᵀ`; `mean2d = (fx·x/z + cx, fy·y/z + cy)`;
//! 4. `det_orig = det(cov2d)`, `cov2d += eps2d·I`, `det_blur = det(cov2d)`,
//!    `compensation = sqrt(max(m², det_orig/det_blur))` with `m = 0` (1.5.3)
//!    or `MIN_COMPENSATION = 0.005` (1.6); cull if `det_blur ≤ 0`;
//! 5. `conics = inverse(cov2d)` as `(inv00, inv01, inv11)`;
//! 6. with opacities: `o' = o·compensation` when compensations are computed;
//!    cull if `o' < 1/255`; `extend = min(3.33, sqrt(2·ln(o'·255)))`
//!    (else 3.33); `radius = ceil(extend·sqrt(cov2d_ii))` per axis;
//! 7. cull if both radii `≤ radius_clip`, or if the box `mean2d ± radius` lies
//!    entirely off the image (`x + rx ≤ 0 || x − rx ≥ W || ...`).
//!
//! Culled entries have radii `(0, 0)` and every other output 0.
//!
//! The backward (`projection_ewa_3dgs_fused_bwd_kernel`, `persp_proj_vjp`,
//! `add_blur_vjp`, `inverse_vjp`) is the exact derivative except for
//! `add_blur_vjp`: gsplat uses `dcomp/dratio = 0.5/(comp + 1e-6)` and applies
//! it even where the compensation is clamped (`max(m², ·)`), where the exact
//! derivative is 0 ([`GradientMode::Gsplat`] follows gsplat). The tangent
//! clamp's derivative is routed into `z` (`Utils.cuh` v1.5.3 l.603–615),
//! which is the exact derivative: `∂J02/∂z = fx·tx/z³` when clamped.

use super::covar::{covar, covar_vjp};
use super::{
    check_len, matmul3, sym_from_triu, transpose3, Constants, GradientMode, Mat3, Version,
};
use crate::error::{Error, Result};
use crate::math::Real;
use rayon::prelude::*;

/// One camera: world-to-camera rotation and translation, pinhole intrinsics.
#[derive(Clone, Copy, Debug)]
pub struct Camera<T> {
    /// World-to-camera rotation.
    pub r: Mat3<T>,
    /// World-to-camera translation.
    pub t: [T; 3],
    /// Focal length in x, pixels.
    pub fx: T,
    /// Focal length in y, pixels.
    pub fy: T,
    /// Principal point x, pixels.
    pub cx: T,
    /// Principal point y, pixels.
    pub cy: T,
}

impl<T: Real> Camera<T> {
    /// Camera `c` of `viewmats [C,4,4]` (row-major) and `Ks [C,3,3]`.
    ///
    /// # Panics
    ///
    /// If `viewmats` holds fewer than `16·(c+1)` values or `ks` fewer than
    /// `9·(c+1)` (a low-level helper: [`ProjectionInput::validate`] checks
    /// the tensors of a call).
    pub fn from_tensors(viewmats: &[T], ks: &[T], c: usize) -> Self {
        let v = &viewmats[16 * c..16 * c + 16];
        let k = &ks[9 * c..9 * c + 9];
        Camera {
            r: [[v[0], v[1], v[2]], [v[4], v[5], v[6]], [v[8], v[9], v[10]]],
            t: [v[3], v[7], v[11]],
            fx: k[0],
            fy: k[4],
            cx: k[2],
            cy: k[5],
        }
    }

    /// `R·p + t`, each row summed left to right, then `t` added.
    pub fn to_camera(&self, p: [T; 3]) -> [T; 3] {
        std::array::from_fn(|i| {
            self.r[i][0] * p[0] + self.r[i][1] * p[1] + self.r[i][2] * p[2] + self.t[i]
        })
    }

    /// `Rᵀ t`: the view direction of a point is `mean + Rᵀ t` (= `mean − campos`).
    pub fn rt_t(&self) -> [T; 3] {
        let (r, t) = (&self.r, &self.t);
        std::array::from_fn(|j| r[0][j] * t[0] + r[1][j] * t[1] + r[2][j] * t[2])
    }
}

/// Where the 3D covariances come from.
#[derive(Clone, Copy, Debug)]
pub enum Covars<'a, T> {
    /// `quats [N,4]` (w, x, y, z; normalised inside), activated `scales [N,3]`.
    QuatScale {
        /// `[N, 4]` quaternions (w, x, y, z).
        quats: &'a [T],
        /// `[N, 3]` activated scales.
        scales: &'a [T],
    },
    /// `covars [N,6]`: `[00, 01, 02, 11, 12, 22]`.
    Triu(&'a [T]),
}

/// The settings of `fully_fused_projection` (gsplat's keyword arguments).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ProjectionSettings {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Blur added to the 2D covariance's diagonal (pixels²).
    pub eps2d: f64,
    /// Entries with camera-space z at or below this are culled.
    pub near_plane: f64,
    /// Entries with camera-space z at or above this are culled.
    pub far_plane: f64,
    /// Entries whose radius is at most this many pixels are culled (0: none).
    pub radius_clip: f64,
    /// Whether to compute the antialiasing compensations.
    pub calc_compensations: bool,
    /// The gsplat version whose conventions apply.
    pub version: Version,
}

impl ProjectionSettings {
    /// gsplat's defaults (`eps2d = 0.3`, `near_plane = 0.01`,
    /// `far_plane = 1e10`, `radius_clip = 0`, no compensations).
    pub fn new(width: usize, height: usize, version: Version) -> Self {
        ProjectionSettings {
            width,
            height,
            eps2d: 0.3,
            near_plane: 0.01,
            far_plane: 1e10,
            radius_clip: 0.0,
            calc_compensations: false,
            version,
        }
    }
}

/// The most (camera, Gaussian) pairs a dense projection holds (2^26: its
/// `[C, N]` outputs take about 2.3 GiB in f32, more while they are built).
pub const MAX_PROJECTED: usize = 1 << 26;

/// The tensors `fully_fused_projection` reads.
#[derive(Clone, Copy, Debug)]
pub struct ProjectionInput<'a, T> {
    /// `[N, 3]`.
    pub means: &'a [T],
    /// Where the 3D covariances come from.
    pub covars: Covars<'a, T>,
    /// `[N]`, optional: enables the opacity-aware radius and the `1/255` cull.
    pub opacities: Option<&'a [T]>,
    /// `[C, 4, 4]`.
    pub viewmats: &'a [T],
    /// `[C, 3, 3]`.
    pub ks: &'a [T],
}

impl<T: Real> ProjectionInput<'_, T> {
    /// `(C, N)` after checking every length.
    pub fn validate(&self, s: &ProjectionSettings) -> Result<(usize, usize)> {
        if !self.means.len().is_multiple_of(3) {
            return Err(Error::invalid(
                "means",
                format!("length {} is not a multiple of 3", self.means.len()),
            ));
        }
        let n = self.means.len() / 3;
        match self.covars {
            Covars::QuatScale { quats, scales } => {
                check_len("quats", quats.len(), 4 * n)?;
                check_len("scales", scales.len(), 3 * n)?;
            }
            Covars::Triu(c) => check_len("covars", c.len(), 6 * n)?,
        }
        if let Some(o) = self.opacities {
            check_len("opacities", o.len(), n)?;
        }
        if !self.viewmats.len().is_multiple_of(16) || self.viewmats.is_empty() {
            return Err(Error::invalid(
                "viewmats",
                format!(
                    "length {} is not a positive multiple of 16",
                    self.viewmats.len()
                ),
            ));
        }
        let c = self.viewmats.len() / 16;
        check_len("Ks", self.ks.len(), 9 * c)?;
        if s.width == 0 || s.height == 0 || s.width > 1 << 16 || s.height > 1 << 16 {
            return Err(Error::invalid(
                "image size",
                format!("{}x{} (each side 1 to 65536)", s.width, s.height),
            ));
        }
        // (Infinite intrinsics gave NaN conics; a NaN view matrix culled
        // every Gaussian without a word.)
        crate::error::check_finite("viewmats", self.viewmats)?;
        crate::error::check_finite("Ks", self.ks)?;
        for (name, v) in [
            ("eps2d", s.eps2d),
            ("near_plane", s.near_plane),
            ("far_plane", s.far_plane),
            ("radius_clip", s.radius_clip),
        ] {
            if !v.is_finite() {
                return Err(Error::invalid(name, format!("{v} is not finite")));
            }
        }
        // (Checked before the `[C, N]` outputs are allocated.)
        if c.checked_mul(n).is_none_or(|cn| cn > MAX_PROJECTED) {
            return Err(Error::invalid(
                "viewmats, means",
                format!(
                    "{c} cameras x {n} Gaussians: the dense projection holds one entry per \
                     pair, at most {MAX_PROJECTED}; project fewer cameras or Gaussians per call"
                ),
            ));
        }
        Ok((c, n))
    }

    fn covar(&self, g: usize) -> Mat3<T> {
        match self.covars {
            Covars::QuatScale { quats, scales } => covar(
                std::array::from_fn(|k| quats[4 * g + k]),
                std::array::from_fn(|k| scales[3 * g + k]),
            ),
            Covars::Triu(c) => sym_from_triu(&c[6 * g..6 * g + 6]),
        }
    }

    fn mean(&self, g: usize) -> [T; 3] {
        std::array::from_fn(|k| self.means[3 * g + k])
    }
}

/// Bit flags of one projected entry.
pub mod flags {
    /// `x/z` was outside `[−lim_x_neg, lim_x_pos]` (tangent clamp active).
    pub const CLAMP_X: u8 = 1;
    /// Likewise for `y/z`.
    pub const CLAMP_Y: u8 = 2;
    /// The compensation took the floor (`max(m², ratio)` chose `m²`).
    pub const COMP_FLOOR: u8 = 4;
}

/// Dense outputs `[C, N, ...]`.
#[derive(Clone, Debug, PartialEq)]
pub struct Projection<T> {
    /// Number of cameras `C`.
    pub c: usize,
    /// Number of Gaussians `N`.
    pub n: usize,
    /// `[C, N, 2]` int32; `(0, 0)` for culled entries.
    pub radii: Vec<i32>,
    /// `[C, N, 2]` pixels.
    pub means2d: Vec<T>,
    /// `[C, N]` camera-space z.
    pub depths: Vec<T>,
    /// `[C, N, 3]` `(inv00, inv01, inv11)` of the blurred 2D covariance.
    pub conics: Vec<T>,
    /// `[C, N]` when computed.
    pub compensations: Option<Vec<T>>,
    /// `[C, N]` [`flags`] (diagnostics, not a gsplat output).
    pub flags: Vec<u8>,
}

/// Packed outputs: the visible entries (both radii > 0) in ascending
/// `camera·N + gaussian` order.
#[derive(Clone, Debug, PartialEq)]
pub struct Packed<T> {
    /// `[nnz]`.
    pub camera_ids: Vec<i32>,
    /// `[nnz]`.
    pub gaussian_ids: Vec<i32>,
    /// `[nnz, 2]` int32 radii.
    pub radii: Vec<i32>,
    /// `[nnz, 2]` pixel-space centres.
    pub means2d: Vec<T>,
    /// `[nnz]` camera-space z.
    pub depths: Vec<T>,
    /// `[nnz, 3]` conics.
    pub conics: Vec<T>,
    /// `[nnz]` compensations, when computed.
    pub compensations: Option<Vec<T>>,
}

impl<T: Real> Projection<T> {
    /// Whether entry `e = c·N + g` is visible (both radii positive).
    ///
    /// # Panics
    ///
    /// If `radii` holds fewer than `2·(e+1)` values (`e` at least `C·N` in
    /// a projection of [`fully_fused_projection`]).
    pub fn visible(&self, e: usize) -> bool {
        self.radii[2 * e] > 0 && self.radii[2 * e + 1] > 0
    }

    /// Checks that every output holds the `C·N` entries of `c` and `n` (a
    /// forward state may have been altered through its public fields); the
    /// error names the field (`projection.radii`, ...).
    pub(crate) fn check_state(&self) -> Result<()> {
        let Some(ce) = self.c.checked_mul(self.n).filter(|&ce| ce <= MAX_PROJECTED) else {
            return Err(Error::invalid(
                "projection state",
                format!(
                    "{} cameras x {} Gaussians, more than {MAX_PROJECTED} pairs",
                    self.c, self.n
                ),
            ));
        };
        check_len("projection.radii", self.radii.len(), 2 * ce)?;
        check_len("projection.means2d", self.means2d.len(), 2 * ce)?;
        check_len("projection.depths", self.depths.len(), ce)?;
        check_len("projection.conics", self.conics.len(), 3 * ce)?;
        if let Some(cv) = &self.compensations {
            check_len("projection.compensations", cv.len(), ce)?;
        }
        check_len("projection.flags", self.flags.len(), ce)
    }

    /// The packed layout of the same numbers.
    ///
    /// # Panics
    ///
    /// If an output holds fewer values than `c·n` entries take (see
    /// [`Projection::visible`]).
    pub fn pack(&self) -> Packed<T> {
        let mut p = Packed {
            camera_ids: Vec::new(),
            gaussian_ids: Vec::new(),
            radii: Vec::new(),
            means2d: Vec::new(),
            depths: Vec::new(),
            conics: Vec::new(),
            compensations: self.compensations.as_ref().map(|_| Vec::new()),
        };
        for e in 0..self.c * self.n {
            if !self.visible(e) {
                continue;
            }
            p.camera_ids.push((e / self.n) as i32);
            p.gaussian_ids.push((e % self.n) as i32);
            p.radii.extend_from_slice(&self.radii[2 * e..2 * e + 2]);
            p.means2d.extend_from_slice(&self.means2d[2 * e..2 * e + 2]);
            p.depths.push(self.depths[e]);
            p.conics.extend_from_slice(&self.conics[3 * e..3 * e + 3]);
            if let (Some(out), Some(comp)) = (p.compensations.as_mut(), &self.compensations) {
                out.push(comp[e]);
            }
        }
        p
    }

    /// Dense entry index of each packed entry.
    ///
    /// # Panics
    ///
    /// If `radii` holds fewer than `2·c·n` values.
    pub fn packed_entries(&self) -> Vec<usize> {
        (0..self.c * self.n).filter(|&e| self.visible(e)).collect()
    }
}

/// One entry's forward result.
#[derive(Clone, Copy, Debug, Default)]
struct Entry<T> {
    radii: [i32; 2],
    mean2d: [T; 2],
    depth: T,
    conic: [T; 3],
    comp: T,
    flags: u8,
}

/// Projection quantities of one camera shared by every Gaussian.
struct Persp<T> {
    lim_x_pos: T,
    lim_x_neg: T,
    lim_y_pos: T,
    lim_y_neg: T,
}

fn persp<T: Real>(cam: &Camera<T>, w: usize, h: usize) -> Persp<T> {
    let half = T::from_f64(0.5);
    let k = T::from_f64(0.3);
    let (wf, hf) = (T::from_usize(w), T::from_usize(h));
    let tan_fovx = half * wf / cam.fx;
    let tan_fovy = half * hf / cam.fy;
    Persp {
        lim_x_pos: (wf - cam.cx) / cam.fx + k * tan_fovx,
        lim_x_neg: cam.cx / cam.fx + k * tan_fovx,
        lim_y_pos: (hf - cam.cy) / cam.fy + k * tan_fovy,
        lim_y_neg: cam.cy / cam.fy + k * tan_fovy,
    }
}

/// `J` (2×3) and the clamped `tx`, `ty` at the camera-space point `p`.
fn jacobian<T: Real>(cam: &Camera<T>, lim: &Persp<T>, p: [T; 3]) -> ([[T; 3]; 2], T, T, u8) {
    let [x, y, z] = p;
    let rz = T::ONE / z;
    let rz2 = rz * rz;
    let ux = x * rz;
    let uy = y * rz;
    let tx = z * ux.max(-lim.lim_x_neg).min(lim.lim_x_pos);
    let ty = z * uy.max(-lim.lim_y_neg).min(lim.lim_y_pos);
    let mut f = 0;
    if !(ux <= lim.lim_x_pos && ux >= -lim.lim_x_neg) {
        f |= flags::CLAMP_X;
    }
    if !(uy <= lim.lim_y_pos && uy >= -lim.lim_y_neg) {
        f |= flags::CLAMP_Y;
    }
    (
        [
            [cam.fx * rz, T::ZERO, -cam.fx * tx * rz2],
            [T::ZERO, cam.fy * rz, -cam.fy * ty * rz2],
        ],
        tx,
        ty,
        f,
    )
}

/// `J V Jᵀ` for 2×3 `J` and 3×3 `V`.
fn jvjt<T: Real>(j: &[[T; 3]; 2], v: &Mat3<T>) -> [[T; 2]; 2] {
    let jv: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| j[r][0] * v[0][c] + j[r][1] * v[1][c] + j[r][2] * v[2][c])
    });
    std::array::from_fn(|r| {
        std::array::from_fn(|c| jv[r][0] * j[c][0] + jv[r][1] * j[c][1] + jv[r][2] * j[c][2])
    })
}

fn project_one<T: Real>(
    cam: &Camera<T>,
    lim: &Persp<T>,
    mean: [T; 3],
    cov: &Mat3<T>,
    opacity: Option<T>,
    s: &ProjectionSettings,
    k: &Constants<T>,
) -> Entry<T> {
    let culled = Entry::default();
    let p = cam.to_camera(mean);
    if p[2] < T::from_f64(s.near_plane) || p[2] > T::from_f64(s.far_plane) {
        return culled;
    }
    let cov_c = matmul3(&matmul3(&cam.r, cov), &transpose3(&cam.r));
    let (j, _, _, f) = jacobian(cam, lim, p);
    let mut c2 = jvjt(&j, &cov_c);
    let rz = T::ONE / p[2];
    let mean2d = [cam.fx * p[0] * rz + cam.cx, cam.fy * p[1] * rz + cam.cy];

    // add_blur
    let eps = T::from_f64(s.eps2d);
    let det_orig = c2[0][0] * c2[1][1] - c2[0][1] * c2[1][0];
    c2[0][0] += eps;
    c2[1][1] += eps;
    let det_blur = c2[0][0] * c2[1][1] - c2[0][1] * c2[1][0];
    let ratio = det_orig / det_blur;
    let floor = ratio <= k.min_compensation_sq || ratio.is_nan();
    let comp = k.min_compensation_sq.max(ratio).sqrt();
    if det_blur <= T::ZERO {
        return culled;
    }
    // glm::inverse (2×2).
    let ood = T::ONE / (c2[0][0] * c2[1][1] - c2[1][0] * c2[0][1]);
    let conic = [c2[1][1] * ood, -c2[0][1] * ood, c2[0][0] * ood];

    let mut extend = k.gaussian_extend;
    if let Some(o) = opacity {
        let o = if s.calc_compensations { o * comp } else { o };
        if o < k.alpha_threshold {
            return culled;
        }
        extend = extend.min((T::from_f64(2.0) * (o / k.alpha_threshold).ln()).sqrt());
    }
    let rx = (extend * c2[0][0].sqrt()).ceil();
    let ry = (extend * c2[1][1].sqrt()).ceil();
    let clip = T::from_f64(s.radius_clip);
    if rx <= clip && ry <= clip {
        return culled;
    }
    let (wf, hf) = (T::from_usize(s.width), T::from_usize(s.height));
    if mean2d[0] + rx <= T::ZERO
        || mean2d[0] - rx >= wf
        || mean2d[1] + ry <= T::ZERO
        || mean2d[1] - ry >= hf
    {
        return culled;
    }
    let to_i32 = |v: T| v.to_f64().clamp(i32::MIN as f64, i32::MAX as f64) as i32;
    Entry {
        radii: [to_i32(rx), to_i32(ry)],
        mean2d,
        depth: p[2],
        conic,
        comp,
        flags: f | if floor { flags::COMP_FLOOR } else { 0 },
    }
}

/// `gsplat.fully_fused_projection(means, covars, quats, scales, viewmats, Ks,
/// width, height, eps2d, near_plane, far_plane, radius_clip,
/// calc_compensations, camera_model="pinhole", opacities)`, dense layout
/// (use [`Projection::pack`] for `packed=True`).
pub fn fully_fused_projection<T: Real>(
    input: &ProjectionInput<T>,
    s: &ProjectionSettings,
) -> Result<Projection<T>> {
    let (c, n) = input.validate(s)?;
    let k = Constants::<T>::new(s.version);
    let cams: Vec<(Camera<T>, Persp<T>)> = (0..c)
        .map(|ci| {
            let cam = Camera::from_tensors(input.viewmats, input.ks, ci);
            let lim = persp(&cam, s.width, s.height);
            (cam, lim)
        })
        .collect();
    let entries: Vec<Entry<T>> = (0..c * n)
        .into_par_iter()
        .map(|e| {
            let (ci, g) = (e / n, e % n);
            let (cam, lim) = &cams[ci];
            project_one(
                cam,
                lim,
                input.mean(g),
                &input.covar(g),
                input.opacities.map(|o| o[g]),
                s,
                &k,
            )
        })
        .collect();
    let mut out = Projection {
        c,
        n,
        radii: Vec::with_capacity(2 * c * n),
        means2d: Vec::with_capacity(2 * c * n),
        depths: Vec::with_capacity(c * n),
        conics: Vec::with_capacity(3 * c * n),
        compensations: s.calc_compensations.then(|| Vec::with_capacity(c * n)),
        flags: Vec::with_capacity(c * n),
    };
    for e in &entries {
        out.radii.extend(e.radii);
        out.means2d.extend(e.mean2d);
        out.depths.push(e.depth);
        out.conics.extend(e.conic);
        if let Some(cv) = out.compensations.as_mut() {
            cv.push(e.comp);
        }
        out.flags.push(e.flags);
    }
    Ok(out)
}

/// Gradients arriving at the dense projection outputs (`[C,N,2]`, `[C,N]`,
/// `[C,N,3]`, optional `[C,N]`); entries of culled Gaussians are ignored.
#[derive(Clone, Copy, Debug)]
pub struct ProjectionCotangents<'a, T> {
    /// `[C, N, 2]` gradient of `means2d`.
    pub v_means2d: &'a [T],
    /// `[C, N]` gradient of `depths`.
    pub v_depths: &'a [T],
    /// `[C, N, 3]` gradient of `conics`.
    pub v_conics: &'a [T],
    /// `[C, N]` gradient of `compensations`, when computed.
    pub v_compensations: Option<&'a [T]>,
}

/// Gradients of `fully_fused_projection`'s inputs.
#[derive(Clone, Debug, PartialEq)]
pub struct ProjectionGrads<T> {
    /// `[N, 3]`.
    pub v_means: Vec<T>,
    /// `[N, 4]` and `[N, 3]` for quats/scales input; empty for covars.
    pub v_quats: Vec<T>,
    /// `[N, 3]` scale gradient for quats/scales input; empty for covars.
    pub v_scales: Vec<T>,
    /// `[N, 6]` for covars input (an off-diagonal slot's gradient is w.r.t.
    /// the scalar filling both positions); empty otherwise.
    pub v_covars: Vec<T>,
}

/// Per-entry gradient w.r.t. the Gaussian's mean and world covariance.
#[allow(clippy::too_many_arguments)]
fn project_one_vjp<T: Real>(
    cam: &Camera<T>,
    lim: &Persp<T>,
    mean: [T; 3],
    cov: &Mat3<T>,
    conic: [T; 3],
    comp: Option<(T, T, bool)>,
    v_mean2d: [T; 2],
    v_depth: T,
    v_conic: [T; 3],
    eps2d: T,
    mode: GradientMode,
) -> ([T; 3], Mat3<T>) {
    let half = T::from_f64(0.5);
    // inverse_vjp: v_cov2d = −P V P.
    let p2 = [[conic[0], conic[1]], [conic[1], conic[2]]];
    let vp = [
        [v_conic[0], v_conic[1] * half],
        [v_conic[1] * half, v_conic[2]],
    ];
    let mp: [[T; 2]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| -p2[r][0] * vp[0][c] - p2[r][1] * vp[1][c])
    });
    let mut g: [[T; 2]; 2] =
        std::array::from_fn(|r| std::array::from_fn(|c| mp[r][0] * p2[0][c] + mp[r][1] * p2[1][c]));
    if let Some((comp, v_comp, floored)) = comp {
        // add_blur_vjp.
        let v_sqr = match mode {
            GradientMode::Exact if floored => T::ZERO,
            GradientMode::Exact => v_comp * half / comp,
            GradientMode::Gsplat => v_comp * half / (comp + T::from_f64(1e-6)),
        };
        let det_conic = conic[0] * conic[2] - conic[1] * conic[1];
        let om = T::ONE - comp * comp;
        g[0][0] += v_sqr * (om * conic[0] - eps2d * det_conic);
        g[0][1] += v_sqr * (om * conic[1]);
        g[1][0] += v_sqr * (om * conic[1]);
        g[1][1] += v_sqr * (om * conic[2] - eps2d * det_conic);
    }

    let pc = cam.to_camera(mean);
    let cov_c = matmul3(&matmul3(&cam.r, cov), &transpose3(&cam.r));
    let (j, tx, ty, f) = jacobian(cam, lim, pc);
    let [x, y, z] = pc;
    let (fx, fy) = (cam.fx, cam.fy);
    let rz = T::ONE / z;
    let rz2 = rz * rz;
    let rz3 = rz2 * rz;
    // v_cov3d = Jᵀ G J.
    let gj: [[T; 3]; 2] =
        std::array::from_fn(|r| std::array::from_fn(|c| g[r][0] * j[0][c] + g[r][1] * j[1][c]));
    let v_cov_c: Mat3<T> =
        std::array::from_fn(|r| std::array::from_fn(|c| j[0][r] * gj[0][c] + j[1][r] * gj[1][c]));
    let mut vm = [
        fx * rz * v_mean2d[0],
        fy * rz * v_mean2d[1],
        -(fx * x * v_mean2d[0] + fy * y * v_mean2d[1]) * rz2,
    ];
    // v_J = G J Vᵀ + Gᵀ J V (V symmetric).
    let gt = [[g[0][0], g[1][0]], [g[0][1], g[1][1]]];
    let gtj: [[T; 3]; 2] =
        std::array::from_fn(|r| std::array::from_fn(|c| gt[r][0] * j[0][c] + gt[r][1] * j[1][c]));
    let vj: [[T; 3]; 2] = std::array::from_fn(|r| {
        std::array::from_fn(|c| {
            (gj[r][0] * cov_c[c][0] + gj[r][1] * cov_c[c][1] + gj[r][2] * cov_c[c][2])
                + (gtj[r][0] * cov_c[0][c] + gtj[r][1] * cov_c[1][c] + gtj[r][2] * cov_c[2][c])
        })
    });
    let two = T::from_f64(2.0);
    if f & flags::CLAMP_X == 0 {
        vm[0] += -fx * rz2 * vj[0][2];
    } else {
        vm[2] += -fx * rz3 * vj[0][2] * tx;
    }
    if f & flags::CLAMP_Y == 0 {
        vm[1] += -fy * rz2 * vj[1][2];
    } else {
        vm[2] += -fy * rz3 * vj[1][2] * ty;
    }
    vm[2] += -fx * rz2 * vj[0][0] - fy * rz2 * vj[1][1]
        + two * fx * tx * rz3 * vj[0][2]
        + two * fy * ty * rz3 * vj[1][2];
    vm[2] += v_depth;
    // posW2C_VJP, covarW2C_VJP.
    let r = &cam.r;
    let v_mean = std::array::from_fn(|jx| r[0][jx] * vm[0] + r[1][jx] * vm[1] + r[2][jx] * vm[2]);
    let v_cov = matmul3(&matmul3(&transpose3(r), &v_cov_c), r);
    (v_mean, v_cov)
}

/// Backward of [`fully_fused_projection`] (dense cotangents). Every
/// difference between the modes is in `add_blur_vjp` (module docs).
pub fn fully_fused_projection_vjp<T: Real>(
    input: &ProjectionInput<T>,
    s: &ProjectionSettings,
    fwd: &Projection<T>,
    v: &ProjectionCotangents<T>,
    mode: GradientMode,
) -> Result<ProjectionGrads<T>> {
    let (c, n) = input.validate(s)?;
    if fwd.c != c || fwd.n != n {
        return Err(Error::invalid(
            "projection state",
            format!("computed for {}x{}, called with {c}x{n}", fwd.c, fwd.n),
        ));
    }
    fwd.check_state()?;
    check_len("v_means2d", v.v_means2d.len(), 2 * c * n)?;
    check_len("v_depths", v.v_depths.len(), c * n)?;
    check_len("v_conics", v.v_conics.len(), 3 * c * n)?;
    if let Some(vc) = v.v_compensations {
        check_len("v_compensations", vc.len(), c * n)?;
        if fwd.compensations.is_none() {
            return Err(Error::invalid(
                "v_compensations",
                "given, but the forward computed no compensations",
            ));
        }
    }
    let eps = T::from_f64(s.eps2d);
    let cams: Vec<(Camera<T>, Persp<T>)> = (0..c)
        .map(|ci| {
            let cam = Camera::from_tensors(input.viewmats, input.ks, ci);
            let lim = persp(&cam, s.width, s.height);
            (cam, lim)
        })
        .collect();
    let per_g: Vec<([T; 3], Vec<T>)> = (0..n)
        .into_par_iter()
        .map(|g| {
            let mean = input.mean(g);
            let cov = input.covar(g);
            let mut gm = [T::ZERO; 3];
            let mut gc = [[T::ZERO; 3]; 3];
            for (ci, (cam, lim)) in cams.iter().enumerate() {
                let e = ci * n + g;
                if !fwd.visible(e) {
                    continue;
                }
                let comp = match (v.v_compensations, &fwd.compensations) {
                    (Some(vc), Some(cv)) => {
                        Some((cv[e], vc[e], fwd.flags[e] & flags::COMP_FLOOR != 0))
                    }
                    _ => None,
                };
                let (dm, dc) = project_one_vjp(
                    cam,
                    lim,
                    mean,
                    &cov,
                    std::array::from_fn(|k| fwd.conics[3 * e + k]),
                    comp,
                    [v.v_means2d[2 * e], v.v_means2d[2 * e + 1]],
                    v.v_depths[e],
                    std::array::from_fn(|k| v.v_conics[3 * e + k]),
                    eps,
                    mode,
                );
                for a in 0..3 {
                    gm[a] += dm[a];
                    for b in 0..3 {
                        gc[a][b] += dc[a][b];
                    }
                }
            }
            let rest = match input.covars {
                Covars::QuatScale { quats, scales } => {
                    let (vq, vs) = covar_vjp(
                        std::array::from_fn(|k| quats[4 * g + k]),
                        std::array::from_fn(|k| scales[3 * g + k]),
                        &gc,
                    );
                    vq.into_iter().chain(vs).collect()
                }
                Covars::Triu(_) => vec![
                    gc[0][0],
                    gc[0][1] + gc[1][0],
                    gc[0][2] + gc[2][0],
                    gc[1][1],
                    gc[1][2] + gc[2][1],
                    gc[2][2],
                ],
            };
            (gm, rest)
        })
        .collect();
    let mut out = ProjectionGrads {
        v_means: Vec::with_capacity(3 * n),
        v_quats: Vec::new(),
        v_scales: Vec::new(),
        v_covars: Vec::new(),
    };
    for (gm, rest) in per_g {
        out.v_means.extend(gm);
        match input.covars {
            Covars::QuatScale { .. } => {
                out.v_quats.extend_from_slice(&rest[..4]);
                out.v_scales.extend_from_slice(&rest[4..]);
            }
            Covars::Triu(_) => out.v_covars.extend(rest),
        }
    }
    Ok(out)
}

/// Scatter packed per-entry values (`width` per entry) to the dense `[C·N, width]` layout.
///
/// # Panics
///
/// If an entry is at least `dense_len`, `packed` holds fewer than
/// `entries.len()·width` values, or `dense_len·width` overflows.
pub fn unpack<T: Real>(entries: &[usize], packed: &[T], width: usize, dense_len: usize) -> Vec<T> {
    let mut out = vec![T::ZERO; dense_len * width];
    for (i, &e) in entries.iter().enumerate() {
        out[e * width..(e + 1) * width].copy_from_slice(&packed[i * width..(i + 1) * width]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// More (camera, Gaussian) pairs than [`MAX_PROJECTED`] are refused by
    /// the check itself, before the outputs' allocation; the limit passes.
    #[test]
    fn pairs_past_the_limit_are_refused() {
        let n = 1 << 14;
        let (means, quats, scales) = (vec![0.0f32; 3 * n], vec![1.0; 4 * n], vec![1.0; 3 * n]);
        let s = ProjectionSettings::new(8, 8, Version::V1_6);
        for (c, ok) in [(MAX_PROJECTED / n, true), (MAX_PROJECTED / n + 1, false)] {
            let (vm, ks) = (vec![0.0f32; 16 * c], vec![0.0f32; 9 * c]);
            let input = ProjectionInput {
                means: &means,
                covars: Covars::QuatScale {
                    quats: &quats,
                    scales: &scales,
                },
                opacities: None,
                viewmats: &vm,
                ks: &ks,
            };
            let r = input.validate(&s);
            if ok {
                assert_eq!(r.unwrap(), (c, n));
            } else {
                let e = r.unwrap_err().to_string();
                assert!(e.contains("4097 cameras x 16384 Gaussians"), "{e}");
            }
        }
    }

    /// Intrinsics or a view matrix that are not finite are refused, naming
    /// the tensor and the flat index (infinite Ks gave NaN conics).
    #[test]
    fn non_finite_cameras_are_refused() {
        let (means, quats, scales, vm, ks) = one_gaussian();
        let s = ProjectionSettings::new(16, 16, Version::V1_6);
        for (name, index) in [("viewmats", 3), ("Ks", 0)] {
            let (mut vm, mut ks) = (vm.clone(), ks.clone());
            let v = if name == "Ks" { &mut ks } else { &mut vm };
            v[index] = f64::INFINITY;
            let input = ProjectionInput {
                means: &means,
                covars: Covars::QuatScale {
                    quats: &quats,
                    scales: &scales,
                },
                opacities: None,
                viewmats: &vm,
                ks: &ks,
            };
            let e = fully_fused_projection(&input, &s).unwrap_err().to_string();
            assert!(
                e.contains(name) && e.contains(&format!("flat index {index}")),
                "{e}"
            );
        }
    }

    /// `means`, `quats`, `scales`, `viewmats`, `Ks`.
    type Scene = (Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>, Vec<f64>);

    fn one_gaussian() -> Scene {
        let view = vec![
            1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 4.0, 0.0, 0.0, 0.0, 1.0,
        ];
        let ks = vec![20.0, 0.0, 8.0, 0.0, 20.0, 8.0, 0.0, 0.0, 1.0];
        (
            vec![0.0; 3],
            vec![1.0, 0.1, 0.2, 0.3],
            vec![0.5; 3],
            view,
            ks,
        )
    }

    /// A forward state whose vectors disagree with its `c` and `n` is
    /// refused by the backward, naming the field.
    #[test]
    fn an_inconsistent_forward_state_is_refused() {
        let (means, quats, scales, vm, ks) = one_gaussian();
        let input = ProjectionInput {
            means: &means,
            covars: Covars::QuatScale {
                quats: &quats,
                scales: &scales,
            },
            opacities: None,
            viewmats: &vm,
            ks: &ks,
        };
        let mut s = ProjectionSettings::new(16, 16, Version::V1_6);
        s.calc_compensations = true;
        let fwd = fully_fused_projection(&input, &s).unwrap();
        assert!(fwd.visible(0));
        let (v2, v1, v3) = ([1.0; 2], [1.0], [1.0; 3]);
        let v = ProjectionCotangents {
            v_means2d: &v2,
            v_depths: &v1,
            v_conics: &v3,
            v_compensations: Some(&v1),
        };
        let mode = GradientMode::Exact;
        assert!(fully_fused_projection_vjp(&input, &s, &fwd, &v, mode).is_ok());
        type Edit = fn(&mut Projection<f64>);
        let edits: [(Edit, &str); 6] = [
            (
                |p| p.radii.clear(),
                "projection.radii: 0 values, expected 2",
            ),
            (
                |p| p.means2d.push(0.0),
                "projection.means2d: 3 values, expected 2",
            ),
            (|p| p.depths.clear(), "projection.depths"),
            (
                |p| p.conics.truncate(2),
                "projection.conics: 2 values, expected 3",
            ),
            (
                |p| p.compensations = Some(Vec::new()),
                "projection.compensations: 0 values",
            ),
            (|p| p.flags.clear(), "projection.flags"),
        ];
        for (edit, want) in edits {
            let mut bad = fwd.clone();
            edit(&mut bad);
            let e = fully_fused_projection_vjp(&input, &s, &bad, &v, mode)
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{e}");
        }
    }
}
