//! Seeded random scenes for gradient checks, tests and benchmarks: Gaussians
//! in front of a camera, with every input variant (SH or precomputed colours,
//! scale/rotation or precomputed covariances).

use super::{Colors, Covariances, RasterInput};
use crate::camera::{Camera, RasterCamera};
use crate::error::Result;
use crate::math::covariance::cov3d;
use crate::math::{Real, Rng};

/// Which colour input a scene feeds the rasterizer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ColorSource {
    /// SH coefficients.
    Sh,
    /// Precomputed RGB colours.
    Precomputed,
}

/// Which covariance input a scene feeds the rasterizer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CovSource {
    /// Scales and rotations.
    ScaleRotation,
    /// Precomputed 3D covariances.
    Precomputed,
}

/// How to draw a random scene.
#[derive(Clone, Debug)]
pub struct SceneSpec {
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
    /// Gaussians inside the view volume.
    pub count: usize,
    /// Extra large Gaussians just outside the side of the view, whose
    /// tangent clamp (`|t.x/t.z| > 1.3·tanfovx`) is active but whose
    /// footprint reaches the image.
    pub off_axis: usize,
    /// Half-extent of the in-view centres as a fraction of the half field of view.
    pub spread: f64,
    /// Range of the scales (world units), drawn log-uniformly per axis.
    pub scale_range: (f64, f64),
    /// Range of opacities.
    pub opacity_range: (f64, f64),
    /// Active SH degree (coefficients are stored for degree 3).
    pub sh_degree: usize,
    /// Horizontal field of view in radians.
    pub fov_x: f64,
    /// Seed of every random draw.
    pub seed: u64,
}

impl SceneSpec {
    /// A small scene for gradient checks: `count` Gaussians, 32×24 pixels.
    pub fn small(count: usize, seed: u64) -> Self {
        SceneSpec {
            width: 32,
            height: 24,
            count,
            off_axis: 0,
            spread: 0.95,
            scale_range: (0.06, 0.3),
            opacity_range: (0.3, 0.95),
            sh_degree: 3,
            fov_x: 0.8,
            seed,
        }
    }

    /// A benchmark-sized scene: `count` small Gaussians at `width`×`height`.
    pub fn bench(width: usize, height: usize, count: usize, seed: u64) -> Self {
        SceneSpec {
            width,
            height,
            count,
            off_axis: 0,
            spread: 0.95,
            scale_range: (0.004, 0.03),
            opacity_range: (0.05, 0.95),
            sh_degree: 3,
            fov_x: 0.8,
            seed,
        }
    }
}

/// A scene's camera and per-Gaussian parameters (every input variant).
#[derive(Clone, Debug)]
pub struct Scene<T> {
    /// The camera.
    pub camera: Camera,
    /// The camera as the rasterizer receives it.
    pub raster_camera: RasterCamera<T>,
    /// `[N, 3]` world-space means.
    pub means3d: Vec<T>,
    /// `[N, 16, 3]`.
    pub sh: Vec<T>,
    /// SH degree the scene evaluates.
    pub sh_degree: usize,
    /// `[N, 3]`.
    pub colors: Vec<T>,
    /// `[N]` activated opacities.
    pub opacities: Vec<T>,
    /// `[N, 3]` activated scales.
    pub scales: Vec<T>,
    /// Unnormalised quaternions.
    pub rotations: Vec<T>,
    /// `cov3d` of the scales and rotations, `[N, 6]`.
    pub cov3d: Vec<T>,
    /// Global factor on every scale.
    pub scale_modifier: T,
    /// Background colour.
    pub background: [T; 3],
}

/// SH coefficients stored per Gaussian.
pub const SCENE_SH_STRIDE: usize = 16;

/// Draw a scene. The camera sits at `(0.2, -0.3, -4)` looking at the origin.
pub fn random_scene(spec: &SceneSpec) -> Result<Scene<f64>> {
    let fov_y =
        2.0 * libm::atan(libm::tan(spec.fov_x / 2.0) * spec.height as f64 / spec.width as f64);
    let camera = Camera::look_at(
        [0.2, -0.3, -4.0],
        [0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        spec.fov_x,
        fov_y,
        spec.width,
        spec.height,
    )?;
    let (tx, ty) = camera.tan_half_fov();
    let (r, t) = (camera.rotation, camera.translation);
    let w2c_inv = |v: [f64; 3]| {
        // camera-space point -> world: Rᵀ (v − t)
        let d = [v[0] - t[0], v[1] - t[1], v[2] - t[2]];
        [
            r[0][0] * d[0] + r[1][0] * d[1] + r[2][0] * d[2],
            r[0][1] * d[0] + r[1][1] * d[1] + r[2][1] * d[2],
            r[0][2] * d[0] + r[1][2] * d[1] + r[2][2] * d[2],
        ]
    };
    let n = spec.count + spec.off_axis;
    let mut s = Scene {
        raster_camera: camera.raster::<f64>(),
        camera,
        means3d: Vec::with_capacity(3 * n),
        sh: Vec::with_capacity(48 * n),
        sh_degree: spec.sh_degree,
        colors: Vec::with_capacity(3 * n),
        opacities: Vec::with_capacity(n),
        scales: Vec::with_capacity(3 * n),
        rotations: Vec::with_capacity(4 * n),
        cov3d: Vec::with_capacity(6 * n),
        scale_modifier: 1.0,
        background: [0.2, 0.5, 0.9],
    };
    let (lo, hi) = (libm::log(spec.scale_range.0), libm::log(spec.scale_range.1));
    for i in 0..n {
        let mut rng = Rng::stream(spec.seed, i as u64);
        let z = rng.uniform_range(3.0, 5.0);
        let (u, v, scale_mul) = if i < spec.count {
            (
                rng.uniform_range(-spec.spread, spec.spread),
                rng.uniform_range(-spec.spread, spec.spread),
                1.0,
            )
        } else {
            // Outside the clamp limit (1.3) on the x side, drawn large.
            let side = if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
            (
                side * rng.uniform_range(1.4, 1.55),
                rng.uniform_range(-0.5, 0.5),
                1.0,
            )
        };
        let p = w2c_inv([u * tx * z, v * ty * z, z]);
        s.means3d.extend_from_slice(&p);
        for k in 0..16 {
            for _ in 0..3 {
                let sd = if k == 0 { 0.8 } else { 0.25 };
                s.sh.push(sd * rng.normal());
            }
        }
        for _ in 0..3 {
            s.colors.push(rng.uniform_range(0.0, 1.0));
        }
        s.opacities
            .push(rng.uniform_range(spec.opacity_range.0, spec.opacity_range.1));
        let mut sc = [0.0; 3];
        for a in &mut sc {
            *a = libm::exp(rng.uniform_range(lo, hi)) * scale_mul;
        }
        if i >= spec.count {
            // Big enough to reach the image from outside the clamp limit.
            sc = [0.45 * z / 4.0, 0.3 * z / 4.0, 0.3];
        }
        s.scales.extend_from_slice(&sc);
        let mut q = [rng.normal(), rng.normal(), rng.normal(), rng.normal()];
        let norm = libm::sqrt(q.iter().map(|v| v * v).sum::<f64>()).max(1e-3);
        let target = rng.uniform_range(0.7, 1.4);
        for c in &mut q {
            *c *= target / norm;
        }
        s.rotations.extend_from_slice(&q);
        s.cov3d.extend_from_slice(&cov3d(sc, 1.0, q));
    }
    Ok(s)
}

impl<T: Real> Scene<T> {
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.opacities.len()
    }

    /// Whether the scene is empty.
    pub fn is_empty(&self) -> bool {
        self.opacities.is_empty()
    }

    /// The same scene in precision `U` (values rounded once from f64).
    pub fn cast<U: Real>(&self) -> Scene<U> {
        let c = |v: &[T]| {
            v.iter()
                .map(|x| U::from_f64(x.to_f64()))
                .collect::<Vec<U>>()
        };
        Scene {
            camera: self.camera.clone(),
            raster_camera: self.camera.raster::<U>(),
            means3d: c(&self.means3d),
            sh: c(&self.sh),
            sh_degree: self.sh_degree,
            colors: c(&self.colors),
            opacities: c(&self.opacities),
            scales: c(&self.scales),
            rotations: c(&self.rotations),
            cov3d: c(&self.cov3d),
            scale_modifier: U::from_f64(self.scale_modifier.to_f64()),
            background: self.background.map(|x| U::from_f64(x.to_f64())),
        }
    }

    /// The rasterizer input for the chosen variants.
    pub fn input(&self, colors: ColorSource, cov: CovSource) -> RasterInput<'_, T> {
        RasterInput {
            means3d: &self.means3d,
            colors: match colors {
                ColorSource::Sh => Colors::Sh {
                    coeffs: &self.sh,
                    stride: SCENE_SH_STRIDE,
                    degree: self.sh_degree,
                },
                ColorSource::Precomputed => Colors::Precomputed(&self.colors),
            },
            opacities: &self.opacities,
            covariances: match cov {
                CovSource::ScaleRotation => Covariances::ScaleRotation {
                    scales: &self.scales,
                    rotations: &self.rotations,
                    scale_modifier: self.scale_modifier,
                },
                CovSource::Precomputed => Covariances::Precomputed(&self.cov3d),
            },
            camera: &self.raster_camera,
            background: self.background,
        }
    }
}
