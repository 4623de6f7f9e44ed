//! Canonical Gaussians: the raw (unactivated) parameters that training
//! optimises, in the Inria / D-3DGS layout, and their activations.
//!
//! All arrays are flat, row-major, Gaussian-major:
//!
//! | field      | shape           | meaning                                              |
//! |------------|-----------------|------------------------------------------------------|
//! | `xyz`      | `[N, 3]`        | canonical mean                                       |
//! | `sh`       | `[N, K, 3]`     | SH coefficients, K = (max_degree+1)², coefficient 0 is the DC term (`f_dc`), 1.. are `f_rest`; element (i,k,c) at `(i*K + k)*3 + c` |
//! | `scaling`  | `[N, 3]`        | log of the standard deviations                       |
//! | `rotation` | `[N, 4]`        | raw quaternion (w, x, y, z), not normalised          |
//! | `opacity`  | `[N]`           | opacity logit                                        |
//!
//! Activations (done before the rasterizer, as upstream): `scale = exp(scaling)`,
//! `opacity = sigmoid(opacity)`, `rotation = q / max(|q|, 1e-12)`.
//!
//! [`ply`] reads and writes them in the Inria PLY layout; [`init`] makes the
//! initial Gaussians from a point cloud (3-nearest-neighbour scales).

pub mod init;
pub mod ply;

use crate::error::{Error, Result};
use crate::math::Real;

/// `torch.nn.functional.normalize`'s epsilon.
pub const NORMALIZE_EPS: f64 = 1e-12;

/// Canonical Gaussians with raw parameters.
#[derive(Clone, Debug, PartialEq)]
pub struct Gaussians<T> {
    /// Highest SH degree stored (K = (max_sh_degree + 1)² coefficients).
    pub max_sh_degree: usize,
    pub xyz: Vec<T>,
    pub sh: Vec<T>,
    pub scaling: Vec<T>,
    pub rotation: Vec<T>,
    pub opacity: Vec<T>,
}

impl<T: Real> Gaussians<T> {
    /// Coefficients per Gaussian for a degree.
    pub fn coeffs_for_degree(degree: usize) -> usize {
        (degree + 1) * (degree + 1)
    }

    /// An empty set with room for `max_sh_degree`.
    pub fn empty(max_sh_degree: usize) -> Self {
        Gaussians {
            max_sh_degree,
            xyz: vec![],
            sh: vec![],
            scaling: vec![],
            rotation: vec![],
            opacity: vec![],
        }
    }

    pub fn len(&self) -> usize {
        self.opacity.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity.is_empty()
    }

    /// SH coefficients per Gaussian (K).
    pub fn coeffs(&self) -> usize {
        Self::coeffs_for_degree(self.max_sh_degree)
    }

    /// Check that every array has the length its shape requires.
    pub fn validate(&self) -> Result<()> {
        let n = self.len();
        let k = self.coeffs();
        for (name, len, want) in [
            ("xyz", self.xyz.len(), 3 * n),
            ("sh", self.sh.len(), 3 * k * n),
            ("scaling", self.scaling.len(), 3 * n),
            ("rotation", self.rotation.len(), 4 * n),
        ] {
            if len != want {
                return Err(Error::invalid(
                    format!("Gaussians.{name}"),
                    format!("{len} values for {n} Gaussians, expected {want}"),
                ));
            }
        }
        Ok(())
    }

    /// Activated scales `exp(scaling)`, `[N, 3]`.
    pub fn scales(&self) -> Vec<T> {
        self.scaling.iter().map(|&s| s.exp()).collect()
    }

    /// Activated opacities `sigmoid(opacity)`, `[N]`.
    pub fn opacities(&self) -> Vec<T> {
        self.opacity.iter().map(|&o| o.sigmoid()).collect()
    }

    /// Normalised rotations `q / max(|q|, 1e-12)`, `[N, 4]`.
    pub fn rotations(&self) -> Vec<T> {
        let mut out = Vec::with_capacity(self.rotation.len());
        for q in self.rotation.chunks_exact(4) {
            let n = normalize_norm(q);
            out.extend(q.iter().map(|&v| v / n));
        }
        out
    }
}

/// The denominator `max(|q|, eps)` of `F.normalize`.
#[inline]
pub fn normalize_norm<T: Real>(q: &[T]) -> T {
    let mut s = T::ZERO;
    for &v in q {
        s += v * v;
    }
    s.sqrt().max(T::from_f64(NORMALIZE_EPS))
}

/// Backward of `y = q / max(|q|, eps)` for one vector: returns dL/dq given dL/dy.
/// Where the norm is below eps the map is a plain scaling by 1/eps.
pub fn normalize_vjp<T: Real>(q: &[T], grad_y: &[T], grad_q: &mut [T]) {
    let mut s = T::ZERO;
    for &v in q {
        s += v * v;
    }
    let norm = s.sqrt();
    let eps = T::from_f64(NORMALIZE_EPS);
    if norm <= eps {
        for (g, &gy) in grad_q.iter_mut().zip(grad_y) {
            *g = gy / eps;
        }
        return;
    }
    // dy/dq = (I - y yᵀ) / |q|
    let mut dot = T::ZERO;
    for (&v, &gy) in q.iter().zip(grad_y) {
        dot += v * gy;
    }
    let inv = T::ONE / norm;
    for ((g, &v), &gy) in grad_q.iter_mut().zip(q).zip(grad_y) {
        *g = (gy - v * inv * inv * dot) * inv;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};

    #[test]
    fn normalize_vjp_matches_finite_differences() {
        let q0 = vec![0.3, -1.2, 0.5, 2.0];
        let gy = cotangent(3, 4);
        let mut ga = vec![0.0; 4];
        normalize_vjp(&q0, &gy, &mut ga);
        let mut q = q0.clone();
        let gn = numeric_gradient(&mut q, 1e-6, |q| {
            let n = normalize_norm(q);
            q.iter().zip(&gy).map(|(v, g)| v / n * g).sum()
        });
        let r = compare("normalize", &ga, &gn, 1e-9);
        assert!(r.passes(1e-7), "{r}");
    }

    #[test]
    fn activations() {
        let g = Gaussians::<f64> {
            max_sh_degree: 0,
            xyz: vec![0.0; 3],
            sh: vec![0.0; 3],
            scaling: vec![0.0, 1.0, -1.0],
            rotation: vec![2.0, 0.0, 0.0, 0.0],
            opacity: vec![0.0],
        };
        g.validate().unwrap();
        assert_eq!(g.opacities(), vec![0.5]);
        assert_eq!(g.rotations(), vec![1.0, 0.0, 0.0, 0.0]);
        assert_eq!(g.scales()[0], 1.0);
    }
}
