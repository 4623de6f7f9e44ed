//! Small vectors and 3×3 matrices.
//!
//! Two kinds, for two jobs:
//! - Code generic over [`Real`] (f32 and f64: the deformation field's SE(3)
//!   warp, covariances) uses the plain arrays [`Vec3`] and [`Mat3`] and the
//!   functions here. Matrices are row-major: `m[i][j]` is row `i`, column `j`.
//! - f64 geometry (cameras, the built-in scenes, dataset camera files) uses
//!   `glam`'s `DVec3`, `DMat3` and `DMat4`, which are plain scalar IEEE
//!   arithmetic in f64 (the same bits on every CPU). glam stores matrices by
//!   column; [`dmat3_from_rows`], [`dmat3_rows`] and [`dmat4_rows`] convert
//!   from and to the row-major arrays the crate's file formats use.
//!
//! Every sum here is evaluated left to right in index order
//! (`a₀b₀ + a₁b₁ + a₂b₂`), as glam does, so either kind gives the same bits
//! for the same formula.

use crate::math::Real;
use glam::{DMat3, DMat4};

/// A 3-vector.
pub type Vec3<T> = [T; 3];
/// A 3×3 matrix, row-major.
pub type Mat3<T> = [[T; 3]; 3];

/// `a · b`.
#[inline]
pub fn dot<T: Real>(a: Vec3<T>, b: Vec3<T>) -> T {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// `a × b`.
#[inline]
pub fn cross<T: Real>(a: Vec3<T>, b: Vec3<T>) -> Vec3<T> {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// The cross-product matrix `[w]×`, so that `[w]×·v = w × v`.
#[inline]
pub fn skew<T: Real>(w: Vec3<T>) -> Mat3<T> {
    let z = T::ZERO;
    [[z, -w[2], w[1]], [w[2], z, -w[0]], [-w[1], w[0], z]]
}

/// `aᵀ`.
#[inline]
pub fn transpose<T: Real>(a: &Mat3<T>) -> Mat3<T> {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| a[j][i]))
}

/// `a·b`.
#[inline]
pub fn mat_mul<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> Mat3<T> {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j]))
}

/// `a·v`.
#[inline]
pub fn mat_vec<T: Real>(a: &Mat3<T>, v: Vec3<T>) -> Vec3<T> {
    [0, 1, 2].map(|i| a[i][0] * v[0] + a[i][1] * v[1] + a[i][2] * v[2])
}

/// `aᵀ·v`.
#[inline]
pub fn mat_t_vec<T: Real>(a: &Mat3<T>, v: Vec3<T>) -> Vec3<T> {
    [0, 1, 2].map(|j| a[0][j] * v[0] + a[1][j] * v[1] + a[2][j] * v[2])
}

/// The Frobenius inner product `Σᵢⱼ aᵢⱼ bᵢⱼ`, summed row by row.
#[inline]
pub fn frobenius<T: Real>(a: &Mat3<T>, b: &Mat3<T>) -> T {
    let mut s = T::ZERO;
    for i in 0..3 {
        for j in 0..3 {
            s += a[i][j] * b[i][j];
        }
    }
    s
}

/// A glam matrix from a row-major array.
#[inline]
pub fn dmat3_from_rows(rows: &[[f64; 3]; 3]) -> DMat3 {
    DMat3::from_cols_array_2d(rows).transpose()
}

/// The row-major array of a glam matrix.
#[inline]
pub fn dmat3_rows(m: &DMat3) -> [[f64; 3]; 3] {
    m.transpose().to_cols_array_2d()
}

/// A glam 4×4 matrix from a row-major array.
#[inline]
pub fn dmat4_from_rows(rows: &[[f64; 4]; 4]) -> DMat4 {
    DMat4::from_cols_array_2d(rows).transpose()
}

/// The row-major array of a glam 4×4 matrix.
#[inline]
pub fn dmat4_rows(m: &DMat4) -> [[f64; 4]; 4] {
    m.transpose().to_cols_array_2d()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::Rng;
    use glam::DVec3;

    fn random3(r: &mut Rng) -> [f64; 3] {
        [(); 3].map(|_| r.uniform_range(-2.0, 2.0))
    }

    /// The array functions and glam give the same bits for the same formula
    /// (the property the camera and scene code relies on).
    #[test]
    fn arrays_and_glam_agree_bit_for_bit() {
        let mut r = Rng::new(3);
        for _ in 0..1000 {
            let (a, b) = (random3(&mut r), random3(&mut r));
            let m = [random3(&mut r), random3(&mut r), random3(&mut r)];
            let n = [random3(&mut r), random3(&mut r), random3(&mut r)];
            let (ga, gb, gm, gn) = (
                DVec3::from(a),
                DVec3::from(b),
                dmat3_from_rows(&m),
                dmat3_from_rows(&n),
            );
            assert_eq!(dot(a, b).to_bits(), ga.dot(gb).to_bits());
            assert_eq!(cross(a, b), ga.cross(gb).to_array());
            assert_eq!(mat_vec(&m, a), (gm * ga).to_array());
            assert_eq!(mat_t_vec(&m, a), (gm.transpose() * ga).to_array());
            assert_eq!(mat_mul(&m, &n), dmat3_rows(&(gm * gn)));
            assert_eq!(transpose(&m), dmat3_rows(&gm.transpose()));
            assert_eq!(mat_vec(&skew(a), b), cross(a, b));
        }
    }

    #[test]
    fn row_major_conversions_round_trip() {
        let m = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]];
        let g = dmat3_from_rows(&m);
        assert_eq!(g.row(1).to_array(), [4.0, 5.0, 6.0]);
        assert_eq!(dmat3_rows(&g), m);
        let m4 = [
            [1.0, 2.0, 3.0, 4.0],
            [5.0, 6.0, 7.0, 8.0],
            [9.0, 10.0, 11.0, 12.0],
            [0.0, 0.0, 0.0, 1.0],
        ];
        let g4 = dmat4_from_rows(&m4);
        assert_eq!(g4.w_axis.to_array(), [4.0, 8.0, 12.0, 1.0]);
        assert_eq!(dmat4_rows(&g4), m4);
    }

    #[test]
    fn frobenius_is_the_trace_of_a_transpose_product() {
        let a = [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]];
        let b = [[0.5, -1.0, 2.0], [1.5, 0.0, -2.0], [3.0, 1.0, 0.25]];
        let p = mat_mul(&transpose(&a), &b);
        assert_eq!(frobenius(&a, &b), p[0][0] + p[1][1] + p[2][2]);
    }
}
