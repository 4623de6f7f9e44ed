//! `quat_scale_to_covar_preci`: 3D covariance `Σ = (R S)(R S)ᵀ` and precision
//! `P = (R S⁻¹)(R S⁻¹)ᵀ` from a quaternion and activated scales, and the
//! backward.
//!
//! gsplat `include/Utils.cuh` (v1.5.3 l.142–303; 1.6 l.228–442):
//! `quat_to_rotmat` **normalises** the quaternion `(w, x, y, z)` with
//! `rsqrt(x² + y² + z² + w²)` before forming `R`; the backward
//! `quat_to_rotmat_vjp` projects the gradient of the unit quaternion `n` back
//! through the normalisation, `(v_n − (v_n·n) n)/|q|`. Both are exact, so the
//! two gradient modes coincide for this stage.

use super::{add3, check_len, matmul3, transpose3, Mat3};
use crate::error::{Error, Result};
use crate::math::Real;

/// Rotation matrix (row-major) of the normalised quaternion `q = (w, x, y, z)`,
/// and `1/|q|`.
pub fn quat_to_rotmat<T: Real>(q: [T; 4]) -> (Mat3<T>, T) {
    let [w, x, y, z] = q;
    let inv_norm = T::ONE / (x * x + y * y + z * z + w * w).sqrt();
    let (w, x, y, z) = (w * inv_norm, x * inv_norm, y * inv_norm, z * inv_norm);
    let two = T::from_f64(2.0);
    let (x2, y2, z2) = (x * x, y * y, z * z);
    let (xy, xz, yz) = (x * y, x * z, y * z);
    let (wx, wy, wz) = (w * x, w * y, w * z);
    (
        [
            [T::ONE - two * (y2 + z2), two * (xy - wz), two * (xz + wy)],
            [two * (xy + wz), T::ONE - two * (x2 + z2), two * (yz - wx)],
            [two * (xz - wy), two * (yz + wx), T::ONE - two * (x2 + y2)],
        ],
        inv_norm,
    )
}

/// Gradient of the raw quaternion from the gradient `v` of the row-major
/// rotation matrix (`quat_to_rotmat_vjp`).
pub fn quat_to_rotmat_vjp<T: Real>(q: [T; 4], v: &Mat3<T>) -> [T; 4] {
    let [w, x, y, z] = q;
    let inv_norm = T::ONE / (x * x + y * y + z * z + w * w).sqrt();
    let (w, x, y, z) = (w * inv_norm, x * inv_norm, y * inv_norm, z * inv_norm);
    let two = T::from_f64(2.0);
    let vn = [
        two * (x * (v[2][1] - v[1][2]) + y * (v[0][2] - v[2][0]) + z * (v[1][0] - v[0][1])),
        two * (-two * x * (v[1][1] + v[2][2])
            + y * (v[1][0] + v[0][1])
            + z * (v[2][0] + v[0][2])
            + w * (v[2][1] - v[1][2])),
        two * (x * (v[1][0] + v[0][1]) - two * y * (v[0][0] + v[2][2])
            + z * (v[2][1] + v[1][2])
            + w * (v[0][2] - v[2][0])),
        two * (x * (v[2][0] + v[0][2]) + y * (v[2][1] + v[1][2]) - two * z * (v[0][0] + v[1][1])
            + w * (v[1][0] - v[0][1])),
    ];
    let n = [w, x, y, z];
    let dot = vn[0] * n[0] + vn[1] * n[1] + vn[2] * n[2] + vn[3] * n[3];
    std::array::from_fn(|k| (vn[k] - dot * n[k]) * inv_norm)
}

/// `M Mᵀ` with `M = R·diag(s)`.
fn outer_self<T: Real>(r: &Mat3<T>, s: [T; 3]) -> Mat3<T> {
    let m: Mat3<T> = std::array::from_fn(|i| std::array::from_fn(|j| r[i][j] * s[j]));
    matmul3(&m, &transpose3(&m))
}

/// Covariance `R S Sᵀ Rᵀ` of one Gaussian.
pub fn covar<T: Real>(q: [T; 4], s: [T; 3]) -> Mat3<T> {
    outer_self(&quat_to_rotmat(q).0, s)
}

/// Precision `R S⁻¹ S⁻ᵀ Rᵀ` of one Gaussian.
pub fn preci<T: Real>(q: [T; 4], s: [T; 3]) -> Mat3<T> {
    let inv = [T::ONE / s[0], T::ONE / s[1], T::ONE / s[2]];
    outer_self(&quat_to_rotmat(q).0, inv)
}

/// Backward of [`covar`] (`v_covar` a full 3×3 gradient): `(v_quat, v_scale)`.
pub fn covar_vjp<T: Real>(q: [T; 4], s: [T; 3], v_covar: &Mat3<T>) -> ([T; 4], [T; 3]) {
    mat_vjp(q, s, v_covar, false)
}

/// Backward of [`preci`]: `(v_quat, v_scale)`.
pub fn preci_vjp<T: Real>(q: [T; 4], s: [T; 3], v_preci: &Mat3<T>) -> ([T; 4], [T; 3]) {
    mat_vjp(q, s, v_preci, true)
}

fn mat_vjp<T: Real>(q: [T; 4], s: [T; 3], g: &Mat3<T>, inverse: bool) -> ([T; 4], [T; 3]) {
    let r = quat_to_rotmat(q).0;
    let d = if inverse {
        [T::ONE / s[0], T::ONE / s[1], T::ONE / s[2]]
    } else {
        s
    };
    let m: Mat3<T> = std::array::from_fn(|i| std::array::from_fn(|j| r[i][j] * d[j]));
    // D = M Mᵀ: dL/dM = (G + Gᵀ) M; M = R diag(d): dL/dR = dL/dM diag(d).
    let vm = matmul3(&add3(g, &transpose3(g)), &m);
    let vr: Mat3<T> = std::array::from_fn(|i| std::array::from_fn(|j| vm[i][j] * d[j]));
    let vq = quat_to_rotmat_vjp(q, &vr);
    let vs = std::array::from_fn(|j| {
        let dd = r[0][j] * vm[0][j] + r[1][j] * vm[1][j] + r[2][j] * vm[2][j];
        if inverse {
            -d[j] * d[j] * dd
        } else {
            dd
        }
    });
    (vq, vs)
}

/// Outputs of [`quat_scale_to_covar_preci`]: `[N, 3, 3]`, or `[N, 6]`
/// (`[00, 01, 02, 11, 12, 22]`) with `triu`; empty when not computed.
#[derive(Clone, Debug, PartialEq)]
pub struct CovarPreci<T> {
    /// Covariances `Σ = R·S·Sᵀ·Rᵀ`.
    pub covars: Vec<T>,
    /// Precision matrices `Σ⁻¹`.
    pub precis: Vec<T>,
}

fn pack<T: Real>(m: &Mat3<T>, triu: bool, out: &mut Vec<T>) {
    if triu {
        out.extend([m[0][0], m[0][1], m[0][2], m[1][1], m[1][2], m[2][2]]);
    } else {
        out.extend(m.iter().flatten().copied());
    }
}

/// Gradient of a packed matrix as a full 3×3 gradient: with `triu`, an
/// off-diagonal slot is one scalar filling both positions, so each position
/// gets half of its gradient (gsplat's `v_covars[1] * .5f`).
fn unpack<T: Real>(v: &[T], triu: bool) -> Mat3<T> {
    if triu {
        let h = T::from_f64(0.5);
        [
            [v[0], v[1] * h, v[2] * h],
            [v[1] * h, v[3], v[4] * h],
            [v[2] * h, v[4] * h, v[5]],
        ]
    } else {
        std::array::from_fn(|i| std::array::from_fn(|j| v[3 * i + j]))
    }
}

/// `N` of `quats [N,4]` after checking that `quats` is a whole number of
/// rows and `scales` holds `[N,3]`.
fn rows<T>(quats: &[T], scales: &[T]) -> Result<usize> {
    if !quats.len().is_multiple_of(4) {
        return Err(Error::invalid(
            "quats",
            format!("length {} is not a multiple of 4", quats.len()),
        ));
    }
    let n = quats.len() / 4;
    check_len("scales", scales.len(), 3 * n)?;
    Ok(n)
}

/// `gsplat.quat_scale_to_covar_preci(quats [N,4], scales [N,3],
/// compute_covar, compute_preci, triu)`, with every length checked: an
/// error names `quats` (not a multiple of 4) or `scales` (not `[N,3]`).
pub fn quat_scale_to_covar_preci<T: Real>(
    quats: &[T],
    scales: &[T],
    compute_covar: bool,
    compute_preci: bool,
    triu: bool,
) -> Result<CovarPreci<T>> {
    let n = rows(quats, scales)?;
    let mut out = CovarPreci {
        covars: Vec::new(),
        precis: Vec::new(),
    };
    for i in 0..n {
        let q = std::array::from_fn(|k| quats[4 * i + k]);
        let s = std::array::from_fn(|k| scales[3 * i + k]);
        if compute_covar {
            pack(&covar(q, s), triu, &mut out.covars);
        }
        if compute_preci {
            pack(&preci(q, s), triu, &mut out.precis);
        }
    }
    Ok(out)
}

/// Backward of [`quat_scale_to_covar_preci`]: `(v_quats [N,4], v_scales
/// [N,3])` from `v_covars` and/or `v_precis` (same layout as the forward's
/// outputs: `[N,6]` with `triu`, else `[N,3,3]`), every length checked.
pub fn quat_scale_to_covar_preci_vjp<T: Real>(
    quats: &[T],
    scales: &[T],
    v_covars: Option<&[T]>,
    v_precis: Option<&[T]>,
    triu: bool,
) -> Result<(Vec<T>, Vec<T>)> {
    let n = rows(quats, scales)?;
    let w = if triu { 6 } else { 9 };
    if let Some(v) = v_covars {
        check_len("v_covars", v.len(), w * n)?;
    }
    if let Some(v) = v_precis {
        check_len("v_precis", v.len(), w * n)?;
    }
    let mut vq = vec![T::ZERO; 4 * n];
    let mut vs = vec![T::ZERO; 3 * n];
    for i in 0..n {
        let q = std::array::from_fn(|k| quats[4 * i + k]);
        let s = std::array::from_fn(|k| scales[3 * i + k]);
        let mut gq = [T::ZERO; 4];
        let mut gs = [T::ZERO; 3];
        if let Some(v) = v_covars {
            let (a, b) = covar_vjp(q, s, &unpack(&v[w * i..w * (i + 1)], triu));
            gq = a;
            gs = b;
        }
        if let Some(v) = v_precis {
            let (a, b) = preci_vjp(q, s, &unpack(&v[w * i..w * (i + 1)], triu));
            for k in 0..4 {
                gq[k] += a[k];
            }
            for k in 0..3 {
                gs[k] += b[k];
            }
        }
        vq[4 * i..4 * i + 4].copy_from_slice(&gq);
        vs[3 * i..3 * i + 3].copy_from_slice(&gs);
    }
    Ok((vq, vs))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err<V: std::fmt::Debug>(r: Result<V>) -> String {
        r.unwrap_err().to_string()
    }

    #[test]
    fn inconsistent_lengths_are_refused() {
        let q = [1.0f64, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0];
        let s = [1.0f64; 6];
        // Short scales (used to index out of bounds).
        let e = err(quat_scale_to_covar_preci(&q, &s[..3], true, true, false));
        assert!(
            e.contains("scales") && e.contains("3 values, expected 6"),
            "{e}"
        );
        // Quats not a whole number of rows (used to be dropped silently).
        let e = err(quat_scale_to_covar_preci(
            &q[..7],
            &s[..3],
            true,
            false,
            true,
        ));
        assert!(e.contains("quats") && e.contains("7"), "{e}");
        let e = err(quat_scale_to_covar_preci_vjp(
            &q[..5],
            &s[..3],
            None,
            None,
            true,
        ));
        assert!(e.contains("quats") && e.contains("5"), "{e}");
        let e = err(quat_scale_to_covar_preci_vjp(&q, &s[..5], None, None, true));
        assert!(e.contains("scales"), "{e}");
        // Short cotangents.
        let v = [0.5f64; 18];
        let e = err(quat_scale_to_covar_preci_vjp(
            &q,
            &s,
            Some(&v[..17]),
            None,
            false,
        ));
        assert!(
            e.contains("v_covars") && e.contains("17 values, expected 18"),
            "{e}"
        );
        let e = err(quat_scale_to_covar_preci_vjp(
            &q,
            &s,
            Some(&v[..12]),
            Some(&v[..11]),
            true,
        ));
        assert!(
            e.contains("v_precis") && e.contains("11 values, expected 12"),
            "{e}"
        );
        // Consistent lengths pass.
        let out = quat_scale_to_covar_preci(&q, &s, true, true, true).unwrap();
        assert_eq!(out.covars.len(), 12);
        let (vq, vs) = quat_scale_to_covar_preci_vjp(&q, &s, Some(&v), Some(&v), false).unwrap();
        assert_eq!((vq.len(), vs.len()), (8, 6));
    }
}
