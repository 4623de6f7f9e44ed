//! Quaternions `q = (r, x, y, z)`, real part first (the Inria and D-3DGS
//! order), and the rotation matrices they stand for, with the vjp.
//!
//! [`quat_to_rotmat`] uses `q` as given, without normalising: callers that
//! want a rotation divide by the norm first (upstream `build_rotation` does,
//! Inria `computeCov3D` does not). Matrices are row-major, acting on column
//! vectors (`v' = R·v`).

use crate::math::pack::Arith;

/// `R(q)` (math, row-major) for `q = (r, x, y, z)`, not normalised.
#[inline(always)]
pub fn quat_to_rotmat<N: Arith>(q: [N; 4]) -> [[N; 3]; 3] {
    let [r, x, y, z] = q;
    let one = N::ONE;
    let two = N::from_f64(2.0);
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - r * z),
            two * (x * z + r * y),
        ],
        [
            two * (x * y + r * z),
            one - two * (x * x + z * z),
            two * (y * z - r * x),
        ],
        [
            two * (x * z - r * y),
            two * (y * z + r * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// Backward of [`quat_to_rotmat`]: `dL/dq` given `dL/dR` (math layout).
#[inline(always)]
pub fn quat_to_rotmat_vjp<N: Arith>(q: [N; 4], gr: [[N; 3]; 3]) -> [N; 4] {
    let [r, x, y, z] = q;
    let two = N::from_f64(2.0);
    let four = N::from_f64(4.0);
    let dr = two * z * (gr[1][0] - gr[0][1])
        + two * y * (gr[0][2] - gr[2][0])
        + two * x * (gr[2][1] - gr[1][2]);
    let dx = two * y * (gr[0][1] + gr[1][0])
        + two * z * (gr[0][2] + gr[2][0])
        + two * r * (gr[2][1] - gr[1][2])
        - four * x * (gr[1][1] + gr[2][2]);
    let dy = two * x * (gr[0][1] + gr[1][0])
        + two * r * (gr[0][2] - gr[2][0])
        + two * z * (gr[1][2] + gr[2][1])
        - four * y * (gr[0][0] + gr[2][2]);
    let dz = two * r * (gr[1][0] - gr[0][1])
        + two * x * (gr[0][2] + gr[2][0])
        + two * y * (gr[1][2] + gr[2][1])
        - four * z * (gr[0][0] + gr[1][1]);
    [dr, dx, dy, dz]
}

/// The unit quaternion `(r, x, y, z)`, `r ≥ 0`, whose [`quat_to_rotmat`] is
/// the rotation matrix `m` (`det m = +1`), by Shepperd's method.
pub fn rotmat_to_quat(m: [[f64; 3]; 3]) -> [f64; 4] {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = 2.0 * (tr + 1.0).sqrt();
        [
            s / 4.0,
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = 2.0 * (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt();
        [
            (m[2][1] - m[1][2]) / s,
            s / 4.0,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = 2.0 * (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt();
        [
            (m[0][2] - m[2][0]) / s,
            (m[0][1] + m[1][0]) / s,
            s / 4.0,
            (m[1][2] + m[2][1]) / s,
        ]
    } else {
        let s = 2.0 * (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt();
        [
            (m[1][0] - m[0][1]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            s / 4.0,
        ]
    };
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
    q.map(|v| sign * v / n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};
    use crate::math::vec::dmat3_rows;
    use crate::math::Rng;
    use glam::{DMat3, DQuat};

    fn random_unit(r: &mut Rng) -> [f64; 4] {
        let q = [(); 4].map(|_| r.normal());
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        q.map(|v| v / n)
    }

    /// For unit quaternions the matrix is glam's (an independent formula).
    #[test]
    fn unit_quaternions_match_glam() {
        let mut r = Rng::new(4);
        for _ in 0..1000 {
            let [w, x, y, z] = random_unit(&mut r);
            let ours = quat_to_rotmat([w, x, y, z]);
            let theirs = dmat3_rows(&DMat3::from_quat(DQuat::from_xyzw(x, y, z, w)));
            for i in 0..3 {
                for j in 0..3 {
                    assert!(
                        (ours[i][j] - theirs[i][j]).abs() < 1e-15,
                        "{ours:?} {theirs:?}"
                    );
                }
            }
            // And back: the same rotation (q and −q are one rotation; ours has r ≥ 0).
            let back = rotmat_to_quat(ours);
            let sign = if w < 0.0 { -1.0 } else { 1.0 };
            for (b, q) in back.iter().zip([w, x, y, z]) {
                assert!(
                    (b - sign * q).abs() < 1e-12,
                    "{back:?} vs {:?}",
                    [w, x, y, z]
                );
            }
        }
    }

    #[test]
    fn vjp_matches_finite_differences() {
        let g = cotangent(8, 9);
        let gr = [[g[0], g[1], g[2]], [g[3], g[4], g[5]], [g[6], g[7], g[8]]];
        let loss = |q: &[f64]| {
            let m = quat_to_rotmat([q[0], q[1], q[2], q[3]]);
            (0..9)
                .map(|k| m[k / 3][k % 3] * gr[k / 3][k % 3])
                .sum::<f64>()
        };
        // Not a unit quaternion: the map is used unnormalised.
        let mut q = vec![0.9, -0.4, 0.7, 0.2];
        let ana = quat_to_rotmat_vjp([q[0], q[1], q[2], q[3]], gr);
        let num = numeric_gradient(&mut q, 1e-6, loss);
        let r = compare("quat_to_rotmat", &ana, &num, 1e-6);
        assert!(r.passes(1e-8), "{r}");
    }
}
