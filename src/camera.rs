//! Pinhole cameras and the matrices the rasterizer consumes.
//!
//! Conventions (the Inria / D-3DGS ones, restated):
//! - Camera space is OpenCV's: x right, y down, z forward (into the scene).
//! - A [`Camera`] stores the world-to-camera transform `W2C = [R | t]` in f64
//!   (R is the world-to-camera rotation itself, not its transpose).
//! - The principal point is the image centre; there is no skew or distortion.
//! - The projection uses znear = 0.01 and zfar = 100 with `P(3,2) = +1`, so the
//!   homogeneous w of a projected point is its view-space depth.
//! - The rasterizer receives row-vector matrices, as the Inria Python API
//!   passes them: `viewmatrix = W2Cᵀ` and `projmatrix = (P·W2C)ᵀ`, both stored
//!   row-major, so `viewmatrix[4j + i] = W2C(i, j)`.
//!
//! Geometry is f64 with glam's `DMat3`/`DVec3`/`DMat4` (plain scalar IEEE
//! arithmetic); the stored fields stay row-major arrays, the layout of the
//! dataset and case files ([`crate::math::vec`] converts).
//!
//! Precision: matrices are formed in f64 and rounded once to the rasterizer's
//! type `T`; `projmatrix` is then the product `viewmatrix · Pᵀ` evaluated in `T`
//! with a fixed summation order, as the upstream f32 `bmm` forms it. Upstream
//! computes the camera centre with an f32 matrix inverse on the GPU; here it is
//! `-Rᵀ t` in f64, rounded once (the exact value rather than an inverse's).

use crate::error::{Error, Result};
use crate::math::vec::{dmat3_from_rows, dmat3_rows, dmat4_rows};
use crate::math::Real;
use glam::{DMat3, DMat4, DVec3, DVec4};

/// Near plane distance (view-space depth), hard-coded upstream.
pub const ZNEAR: f64 = 0.01;
/// Far plane distance (view-space depth), hard-coded upstream.
pub const ZFAR: f64 = 100.0;

/// A camera: extrinsics, field of view and image size.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// World-to-camera rotation, row-major (OpenCV camera axes).
    pub rotation: [[f64; 3]; 3],
    /// World-to-camera translation.
    pub translation: [f64; 3],
    /// Horizontal field of view, radians.
    pub fov_x: f64,
    /// Vertical field of view, radians.
    pub fov_y: f64,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
}

/// The camera as the rasterizer receives it (the Inria Python API's arguments).
#[derive(Clone, Debug, PartialEq)]
pub struct RasterCamera<T> {
    /// `W2Cᵀ`, row-major 4×4.
    pub viewmatrix: [T; 16],
    /// `(P·W2C)ᵀ`, row-major 4×4.
    pub projmatrix: [T; 16],
    /// Camera centre in world space.
    pub campos: [T; 3],
    /// `tan(fov_x / 2)`.
    pub tanfovx: T,
    /// `tan(fov_y / 2)`.
    pub tanfovy: T,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
}

/// `fov = 2·atan(pixels / (2·focal))`.
pub fn focal2fov(focal: f64, pixels: f64) -> f64 {
    2.0 * libm::atan(pixels / (2.0 * focal))
}

/// `focal = pixels / (2·tan(fov/2))`.
pub fn fov2focal(fov: f64, pixels: f64) -> f64 {
    pixels / (2.0 * libm::tan(fov / 2.0))
}

/// How far a camera rotation may be from orthonormal: every element of
/// `RᵀR − I` within this, and `det R` within this of 1 (dataset files store
/// rotations to about 7 significant digits; a scaled, sheared or reflected
/// matrix is off by far more).
pub const ROTATION_TOLERANCE: f64 = 1e-4;

/// `Err(reason)` unless `r` is a rotation within [`ROTATION_TOLERANCE`]
/// (finite, orthonormal, determinant +1).
pub fn check_rotation(r: &[[f64; 3]; 3]) -> std::result::Result<(), String> {
    if r.iter().flatten().any(|v| !v.is_finite()) {
        return Err(format!("{r:?} has a non-finite element"));
    }
    let m = dmat3_from_rows(r);
    let off = m.transpose() * m - DMat3::IDENTITY;
    let worst = [off.x_axis, off.y_axis, off.z_axis]
        .iter()
        .fold(0.0f64, |w, c| w.max(c.abs().max_element()));
    let det = m.determinant();
    if worst > ROTATION_TOLERANCE || (det - 1.0).abs() > ROTATION_TOLERANCE {
        // A huge determinant in `{:.6}` would be hundreds of digits.
        let det = if det.abs() < 1e6 {
            format!("{det:.6}")
        } else {
            format!("{det:.3e}")
        };
        return Err(format!(
            "{r:?} is not a rotation: max |RᵀR − I| = {worst:.3e}, det = {det} (tolerance {ROTATION_TOLERANCE:e})"
        ));
    }
    Ok(())
}

/// `Err(reason)` unless `m` is a rigid transform: its upper-left 3×3 a
/// rotation ([`check_rotation`]), its translation finite and its bottom
/// row exactly `[0, 0, 0, 1]`.
pub fn check_rigid(m: &[[f64; 4]; 4]) -> std::result::Result<(), String> {
    if m[3] != [0.0, 0.0, 0.0, 1.0] {
        return Err(format!("bottom row {:?} is not [0, 0, 0, 1]", m[3]));
    }
    if !(m[0][3].is_finite() && m[1][3].is_finite() && m[2][3].is_finite()) {
        return Err("the translation has a non-finite element".into());
    }
    check_rotation(&[
        [m[0][0], m[0][1], m[0][2]],
        [m[1][0], m[1][1], m[1][2]],
        [m[2][0], m[2][1], m[2][2]],
    ])
}

fn check_finite(what: &str, vals: &[f64]) -> Result<()> {
    if vals.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(Error::invalid(
            what,
            format!("non-finite value in {vals:?}"),
        ))
    }
}

impl Camera {
    /// From an explicit world-to-camera transform (OpenCV axes).
    pub fn from_w2c(
        rotation: [[f64; 3]; 3],
        translation: [f64; 3],
        fov_x: f64,
        fov_y: f64,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        check_finite("camera rotation", &rotation.concat())?;
        check_finite("camera translation", &translation)?;
        for (name, fov) in [("fov_x", fov_x), ("fov_y", fov_y)] {
            if !(fov > 0.0 && fov < std::f64::consts::PI) {
                return Err(Error::invalid(
                    name,
                    format!("{} is not in (0, pi)", crate::error::shown(fov)),
                ));
            }
        }
        if width == 0 || height == 0 {
            return Err(Error::invalid("image size", format!("{width}x{height}")));
        }
        Ok(Camera {
            rotation,
            translation,
            fov_x,
            fov_y,
            width,
            height,
        })
    }

    /// From a camera-to-world matrix in Blender/OpenGL axes (x right, y up,
    /// z backward), as D-NeRF's `transform_matrix`. This is the correct
    /// conversion: `W2C = inverse(C2W · diag(1, -1, -1, 1))`. (Upstream's
    /// reader flips the sign of the x translation; see `dataset::dnerf`.)
    pub fn from_c2w_opengl(
        c2w: [[f64; 4]; 4],
        fov_x: f64,
        fov_y: f64,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        check_finite("camera-to-world matrix", &c2w.concat())?;
        let m = dmat3_from_rows(&[
            [c2w[0][0], c2w[0][1], c2w[0][2]],
            [c2w[1][0], c2w[1][1], c2w[1][2]],
            [c2w[2][0], c2w[2][1], c2w[2][2]],
        ]);
        // Flip the y and z axes of the camera frame: columns 1 and 2 of the rotation.
        let r_c2w = DMat3::from_cols(m.x_axis, -m.y_axis, -m.z_axis);
        let centre = DVec3::new(c2w[0][3], c2w[1][3], c2w[2][3]);
        Self::from_c2w(r_c2w, centre, fov_x, fov_y, width, height)
    }

    /// From a camera-to-world rotation and camera centre in OpenCV axes.
    /// The inverse of a rigid transform is `[Rᵀ | -Rᵀ c]`; the rotation is
    /// orthonormalised by nothing, so callers pass a proper rotation.
    pub fn from_c2w_opencv(
        r_c2w: [[f64; 3]; 3],
        centre: [f64; 3],
        fov_x: f64,
        fov_y: f64,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        Self::from_c2w(
            dmat3_from_rows(&r_c2w),
            DVec3::from(centre),
            fov_x,
            fov_y,
            width,
            height,
        )
    }

    /// From a camera-to-world rotation and camera centre (OpenCV axes):
    /// `R = R_c2wᵀ`, `t = −R·c`.
    fn from_c2w(
        r_c2w: DMat3,
        centre: DVec3,
        fov_x: f64,
        fov_y: f64,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        let r = r_c2w.transpose();
        let t = -(r * centre);
        Self::from_w2c(dmat3_rows(&r), t.to_array(), fov_x, fov_y, width, height)
    }

    /// The world-to-camera rotation `R`.
    pub fn rotation_matrix(&self) -> DMat3 {
        dmat3_from_rows(&self.rotation)
    }

    /// The 4×4 world-to-camera transform `[R | t]` (column-vector convention).
    pub fn w2c_matrix(&self) -> DMat4 {
        let r = self.rotation_matrix();
        DMat4::from_cols(
            r.x_axis.extend(0.0),
            r.y_axis.extend(0.0),
            r.z_axis.extend(0.0),
            DVec4::new(
                self.translation[0],
                self.translation[1],
                self.translation[2],
                1.0,
            ),
        )
    }

    /// The 4×4 world-to-camera matrix (column-vector convention), row-major.
    pub fn w2c(&self) -> [[f64; 4]; 4] {
        dmat4_rows(&self.w2c_matrix())
    }

    /// Camera centre in world space, `-Rᵀ t`.
    pub fn centre(&self) -> [f64; 3] {
        (-(self.rotation_matrix().transpose() * DVec3::from(self.translation))).to_array()
    }

    /// `(tan(fov_x / 2), tan(fov_y / 2))`.
    pub fn tan_half_fov(&self) -> (f64, f64) {
        (libm::tan(self.fov_x * 0.5), libm::tan(self.fov_y * 0.5))
    }

    /// The projection matrix `P` (column-vector convention), row-major, f64.
    pub fn projection(&self) -> [[f64; 4]; 4] {
        let (tx, ty) = self.tan_half_fov();
        let top = ty * ZNEAR;
        let bottom = -top;
        let right = tx * ZNEAR;
        let left = -right;
        let mut p = [[0.0; 4]; 4];
        p[0][0] = 2.0 * ZNEAR / (right - left);
        p[1][1] = 2.0 * ZNEAR / (top - bottom);
        p[0][2] = (right + left) / (right - left);
        p[1][2] = (top + bottom) / (top - bottom);
        p[3][2] = 1.0;
        p[2][2] = ZFAR / (ZFAR - ZNEAR);
        p[2][3] = -(ZFAR * ZNEAR) / (ZFAR - ZNEAR);
        p
    }

    /// Focal lengths in pixels, `(fx, fy)`.
    pub fn focal(&self) -> (f64, f64) {
        (
            fov2focal(self.fov_x, self.width as f64),
            fov2focal(self.fov_y, self.height as f64),
        )
    }

    /// The rasterizer's view of this camera in precision `T`.
    pub fn raster<T: Real>(&self) -> RasterCamera<T> {
        let w2c = self.w2c();
        let p = self.projection();
        let mut view = [T::ZERO; 16];
        let mut proj_t = [T::ZERO; 16];
        for i in 0..4 {
            for j in 0..4 {
                view[4 * j + i] = T::from_f64(w2c[i][j]);
                proj_t[4 * j + i] = T::from_f64(p[i][j]);
            }
        }
        // full = view · Pᵀ in T, summing k = 0..3 in order.
        let mut full = [T::ZERO; 16];
        for r in 0..4 {
            for c in 0..4 {
                let mut acc = view[4 * r] * proj_t[c];
                for k in 1..4 {
                    acc += view[4 * r + k] * proj_t[4 * k + c];
                }
                full[4 * r + c] = acc;
            }
        }
        let c = self.centre();
        let (tx, ty) = self.tan_half_fov();
        RasterCamera {
            viewmatrix: view,
            projmatrix: full,
            campos: [T::from_f64(c[0]), T::from_f64(c[1]), T::from_f64(c[2])],
            tanfovx: T::from_f64(tx),
            tanfovy: T::from_f64(ty),
            width: self.width,
            height: self.height,
        }
    }

    /// A copy rendering at a different resolution with the same field of view.
    pub fn with_size(&self, width: usize, height: usize) -> Self {
        Camera {
            width,
            height,
            ..self.clone()
        }
    }

    /// A camera at `eye` looking at `target` with world `up`, in OpenCV axes.
    pub fn look_at(
        eye: [f64; 3],
        target: [f64; 3],
        up: [f64; 3],
        fov_x: f64,
        fov_y: f64,
        width: usize,
        height: usize,
    ) -> Result<Self> {
        let (eye, target, up) = (DVec3::from(eye), DVec3::from(target), DVec3::from(up));
        let unit = |a: DVec3| a / a.length();
        let z = unit(target - eye); // forward
        let x = unit(z.cross(up)); // right (y down)
        let y = z.cross(x);
        if !(x.is_finite() && y.is_finite() && z.is_finite()) {
            return Err(Error::invalid(
                "look_at",
                "eye equals target or up is parallel to the view direction",
            ));
        }
        // Camera-to-world columns are the camera axes.
        Self::from_c2w(DMat3::from_cols(x, y, z), eye, fov_x, fov_y, width, height)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn apply(m: &[[f64; 4]; 4], p: [f64; 3]) -> [f64; 4] {
        let mut o = [0.0; 4];
        for (i, oi) in o.iter_mut().enumerate() {
            *oi = m[i][0] * p[0] + m[i][1] * p[1] + m[i][2] * p[2] + m[i][3];
        }
        o
    }

    #[test]
    fn look_at_puts_target_on_the_optical_axis() {
        let cam = Camera::look_at(
            [3.0, -2.0, 1.0],
            [0.1, 0.2, 0.3],
            [0.0, 0.0, 1.0],
            0.8,
            0.8,
            64,
            48,
        )
        .unwrap();
        let v = apply(&cam.w2c(), [0.1, 0.2, 0.3]);
        assert!(v[0].abs() < 1e-12 && v[1].abs() < 1e-12 && v[2] > 0.0);
        let c = cam.centre();
        assert!(
            (c[0] - 3.0).abs() < 1e-12 && (c[1] + 2.0).abs() < 1e-12 && (c[2] - 1.0).abs() < 1e-12
        );
        // World up maps to camera -y (y points down in the image).
        let up = apply(&cam.w2c(), [0.0, 0.0, 1.0 + 0.3]);
        assert!(up[1] < v[1]);
    }

    #[test]
    fn opengl_c2w_round_trip() {
        // OpenGL camera at (0, 0, 4) looking down -z: identity rotation.
        let c2w = [
            [1.0, 0.0, 0.0, 0.0],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 4.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let cam = Camera::from_c2w_opengl(c2w, 0.7, 0.7, 32, 32).unwrap();
        let v = apply(&cam.w2c(), [0.0, 0.0, 0.0]);
        assert_eq!(v, [0.0, 0.0, 4.0, 1.0]);
        assert_eq!(cam.centre(), [0.0, 0.0, 4.0]);
    }

    #[test]
    fn raster_matrices_follow_the_row_vector_layout() {
        let cam =
            Camera::look_at([1.0, 2.0, 3.0], [0.0; 3], [0.0, 0.0, 1.0], 0.9, 0.7, 40, 30).unwrap();
        let rc = cam.raster::<f64>();
        let w2c = cam.w2c();
        let p = cam.projection();
        for (i, w2c_i) in w2c.iter().enumerate() {
            for (j, &w2c_ij) in w2c_i.iter().enumerate() {
                assert_eq!(rc.viewmatrix[4 * j + i], w2c_ij);
                let pw: f64 = (0..4).map(|k| p[i][k] * w2c[k][j]).sum();
                assert!((rc.projmatrix[4 * j + i] - pw).abs() < 1e-12);
            }
        }
        // P(3,2) = 1: homogeneous w equals view depth.
        let x = [0.3, -0.2, 0.5];
        let view = apply(&w2c, x);
        let m = &rc.projmatrix;
        let w = m[3] * x[0] + m[7] * x[1] + m[11] * x[2] + m[15];
        assert!((w - view[2]).abs() < 1e-12);
    }

    #[test]
    fn bad_values_are_rejected() {
        assert!(Camera::from_w2c([[f64::NAN; 3]; 3], [0.0; 3], 0.5, 0.5, 8, 8).is_err());
        assert!(Camera::from_w2c(
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            [0.0; 3],
            0.0,
            0.5,
            8,
            8
        )
        .is_err());
        assert!(Camera::from_w2c(
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            [0.0; 3],
            0.5,
            0.5,
            0,
            8
        )
        .is_err());
    }
}
