//! Canonical Gaussians: the raw (unactivated) parameters that training
//! optimises, in the Inria / D-3DGS layout, and their activations.
//!
//! All arrays are flat, row-major, Gaussian-major:
//!
//! | field      | shape           | meaning                                              |
//! |------------|-----------------|------------------------------------------------------|
//! | `xyz`      | `[N, 3]`        | canonical mean                                       |
//! | `sh`       | `[N, K, 3]`     | SH coefficients, K = (max_degree+1)², coefficient 0 is the DC term (`f_dc`), 1.. are `f_rest`; element (i,k,c) at `(i*K + k)*3 + c` |
//! | `opacity`  | `[N]`           | opacity logit (`[N, 1]` in files)                    |
//! | `scaling`  | `[N, 3]`        | log of the standard deviations                       |
//! | `rotation` | `[N, 4]`        | raw quaternion (w, x, y, z), not normalised          |
//!
//! These five arrays are the parameter groups ([`Group`]): one table gives
//! each group's name and row width, and everything that handles the groups
//! one by one (the optimizer, densification, checkpoints and case files,
//! the state hash, PLY files) iterates [`Group::ALL`].
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

/// The highest SH degree a set of Gaussians may store (the most the PLY
/// reader accepts; rendering and training use at most
/// [`crate::math::sh::MAX_SH_DEGREE`]). [`Gaussians::validate`] refuses
/// more, before any size is computed from it.
pub const MAX_STORED_SH_DEGREE: usize = 8;

/// `torch.nn.functional.normalize`'s epsilon.
pub const NORMALIZE_EPS: f64 = 1e-12;

/// One of the five per-Gaussian parameter groups (one raw parameter array
/// each, one Adam state each).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Group {
    /// Canonical means, 3 per Gaussian.
    Xyz,
    /// SH coefficients, `K × 3` per Gaussian (upstream's `f_dc` and `f_rest`).
    Sh,
    /// Opacity logits, 1 per Gaussian.
    Opacity,
    /// Log standard deviations, 3 per Gaussian.
    Scaling,
    /// Raw quaternions, 4 per Gaussian.
    Rotation,
}

/// The table of groups, in [`Group::ALL`]'s order: name (of the tensor in
/// case files and checkpoints, and of the Adam group), values per row, and
/// whether the row holds that many values per SH coefficient (`[K, 3]`).
const GROUP_TABLE: [(&str, usize, bool); 5] = [
    ("xyz", 3, false),
    ("sh", 3, true),
    ("opacity", 1, false),
    ("scaling", 3, false),
    ("rotation", 4, false),
];

impl Group {
    /// Every group, in upstream's order (the param groups of
    /// `GaussianModel.training_setup` and the PLY properties of
    /// `construct_list_of_attributes`, with `f_dc` and `f_rest` as one).
    pub const ALL: [Group; 5] = [
        Group::Xyz,
        Group::Sh,
        Group::Opacity,
        Group::Scaling,
        Group::Rotation,
    ];

    /// The group's name: `xyz`, `sh`, `opacity`, `scaling` or `rotation`.
    pub fn name(self) -> &'static str {
        GROUP_TABLE[self as usize].0
    }

    /// Values per Gaussian with `coeffs` SH coefficients (K).
    pub fn width(self, coeffs: usize) -> usize {
        let (_, w, per_coeff) = GROUP_TABLE[self as usize];
        if per_coeff {
            w * coeffs
        } else {
            w
        }
    }

    /// The shape of one Gaussian's row in files: `[3]`, `[K, 3]`, `[1]`,
    /// `[3]`, `[4]`.
    pub fn row_shape(self, coeffs: usize) -> Vec<usize> {
        let (_, w, per_coeff) = GROUP_TABLE[self as usize];
        if per_coeff {
            vec![coeffs, w]
        } else {
            vec![w]
        }
    }
}

/// Canonical Gaussians with raw parameters (one array per [`Group`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Gaussians<T> {
    /// Highest SH degree stored (K = (max_sh_degree + 1)² coefficients).
    pub max_sh_degree: usize,
    /// Canonical means `[N, 3]`.
    pub xyz: Vec<T>,
    /// SH coefficients `[N, K, 3]`, coefficient-major per Gaussian.
    pub sh: Vec<T>,
    /// Opacity logits `[N]`.
    pub opacity: Vec<T>,
    /// Log standard deviations `[N, 3]`.
    pub scaling: Vec<T>,
    /// Raw quaternions (w, x, y, z) `[N, 4]`.
    pub rotation: Vec<T>,
}

impl<T: Real> Gaussians<T> {
    /// Coefficients per Gaussian for a degree.
    ///
    /// # Panics
    /// If `(degree + 1)²` overflows `usize` (a degree of 2³² or more on 64-bit
    /// targets); [`validate`](Self::validate) refuses any degree above
    /// [`MAX_STORED_SH_DEGREE`] before computing this.
    pub fn coeffs_for_degree(degree: usize) -> usize {
        match degree.checked_add(1).and_then(|d| d.checked_mul(d)) {
            Some(k) => k,
            None => panic!("Gaussians::coeffs_for_degree: degree {degree} is far too large"),
        }
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

    /// Number of Gaussians (N, the length of `opacity`).
    pub fn len(&self) -> usize {
        self.opacity.len()
    }

    /// True when there are no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.opacity.is_empty()
    }

    /// SH coefficients per Gaussian (K).
    pub fn coeffs(&self) -> usize {
        Self::coeffs_for_degree(self.max_sh_degree)
    }

    /// The array of `group`.
    pub fn group(&self, group: Group) -> &Vec<T> {
        match group {
            Group::Xyz => &self.xyz,
            Group::Sh => &self.sh,
            Group::Opacity => &self.opacity,
            Group::Scaling => &self.scaling,
            Group::Rotation => &self.rotation,
        }
    }

    /// The array of `group`, mutable.
    pub fn group_mut(&mut self, group: Group) -> &mut Vec<T> {
        match group {
            Group::Xyz => &mut self.xyz,
            Group::Sh => &mut self.sh,
            Group::Opacity => &mut self.opacity,
            Group::Scaling => &mut self.scaling,
            Group::Rotation => &mut self.rotation,
        }
    }

    /// Every array with its group, in [`Group::ALL`]'s order, mutable.
    pub fn groups_mut(&mut self) -> [(Group, &mut Vec<T>); 5] {
        [
            (Group::Xyz, &mut self.xyz),
            (Group::Sh, &mut self.sh),
            (Group::Opacity, &mut self.opacity),
            (Group::Scaling, &mut self.scaling),
            (Group::Rotation, &mut self.rotation),
        ]
    }

    /// Values per Gaussian of `group` ([`Group::width`] at this SH degree).
    pub fn width(&self, group: Group) -> usize {
        group.width(self.coeffs())
    }

    /// The file shape of `group`'s array: `[N]` followed by its
    /// [`row_shape`](Group::row_shape).
    pub fn shape(&self, group: Group) -> Vec<usize> {
        let mut s = vec![self.len()];
        s.extend(group.row_shape(self.coeffs()));
        s
    }

    /// Check that the SH degree is at most [`MAX_STORED_SH_DEGREE`] and that
    /// every array has the length its shape requires.
    pub fn validate(&self) -> Result<()> {
        if self.max_sh_degree > MAX_STORED_SH_DEGREE {
            return Err(Error::invalid(
                "Gaussians.max_sh_degree",
                format!("{} (at most {MAX_STORED_SH_DEGREE})", self.max_sh_degree),
            ));
        }
        let n = self.len();
        for group in Group::ALL {
            let (len, want) = (self.group(group).len(), self.width(group).checked_mul(n));
            if want != Some(len) {
                let want = want.map_or("more than usize holds".into(), |w| w.to_string());
                return Err(Error::invalid(
                    format!("Gaussians.{}", group.name()),
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
        let mut out = vec![T::ZERO; self.rotation.len()];
        for (q, y) in self.rotation.chunks_exact(4).zip(out.chunks_exact_mut(4)) {
            normalize(q, y);
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

/// `y = q / max(|q|, eps)` for one vector (`F.normalize`).
#[inline]
pub fn normalize<T: Real>(q: &[T], y: &mut [T]) {
    let n = normalize_norm(q);
    for (y, &v) in y.iter_mut().zip(q) {
        *y = v / n;
    }
}

/// Backward of [`normalize`]: `y = q / max(|q|, eps)` for one vector: returns dL/dq given dL/dy.
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
    fn group_table_matches_the_arrays() {
        let g = Gaussians::<f64> {
            max_sh_degree: 2,
            xyz: vec![0.0; 6],
            sh: vec![0.0; 54],
            opacity: vec![0.0; 2],
            scaling: vec![0.0; 6],
            rotation: vec![0.0; 8],
        };
        g.validate().unwrap();
        let names: Vec<&str> = Group::ALL.iter().map(|g| g.name()).collect();
        assert_eq!(names, ["xyz", "sh", "opacity", "scaling", "rotation"]);
        for group in Group::ALL {
            let shape = g.shape(group);
            assert_eq!(shape.iter().product::<usize>(), g.group(group).len());
            assert_eq!(g.width(group) * g.len(), g.group(group).len());
        }
        assert_eq!(g.shape(Group::Sh), [2, 9, 3]);
        assert_eq!(g.shape(Group::Opacity), [2, 1]);
    }

    /// A huge SH degree is an error of `validate`, not an overflow.
    #[test]
    fn validate_refuses_a_huge_sh_degree() {
        let mut g = Gaussians::<f64>::empty(1 << 33);
        let e = g.validate().unwrap_err();
        assert!(e.to_string().contains("max_sh_degree"), "{e}");
        g.max_sh_degree = MAX_STORED_SH_DEGREE + 1;
        assert!(g.validate().is_err());
        g.max_sh_degree = MAX_STORED_SH_DEGREE;
        g.validate().unwrap();
    }

    #[test]
    #[should_panic(expected = "Gaussians::coeffs_for_degree: degree")]
    fn coeffs_for_a_huge_degree_panics_with_a_message() {
        Gaussians::<f64>::coeffs_for_degree(usize::MAX / 2);
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
