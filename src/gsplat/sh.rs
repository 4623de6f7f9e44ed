//! `spherical_harmonics(degrees_to_use, dirs, coeffs)`: colours from real SH
//! coefficients up to degree 4, evaluated at the normalised direction with
//! Sloan's recurrences ("Efficient Spherical Harmonic Evaluation", JCGT
//! 2013) exactly as gsplat's `sh_coeffs_to_color_fast`
//! (`csrc/SphericalHarmonicsCUDA.cu`, v1.5.3 l.21–110), and the backward.
//!
//! No `+0.5` and no clamp here: `rasterization` adds them
//! (`clamp_min(colors + 0.5, 0)`, `rendering.py` v1.5.3 l.525).
//!
//! The backward is the exact derivative: `v_coeffs[k] = Y_k(n)·v_color`, and
//! `v_dirs = (v_n − (v_n·n) n)/|d|` with `v_n = Σ_k coeffs_k v_color ∇Y_k(n)`.
//! gsplat's `sh_coeffs_to_color_fast_vjp` (l.113–) writes out the same
//! partial derivatives by hand; here they come from evaluating the same
//! recurrences on dual numbers, so the two gradient modes coincide.

#![allow(clippy::needless_range_loop)]

use super::check_len;
use crate::error::{Error, Result};
use crate::math::Real;
use std::ops::{Add, Mul, Sub};

/// Highest SH degree gsplat evaluates.
pub const MAX_DEGREE: usize = 4;

/// A value with its partial derivatives along x, y, z.
#[derive(Clone, Copy, Debug)]
struct Dual<T> {
    v: T,
    d: [T; 3],
}

trait Num: Copy + Add<Output = Self> + Sub<Output = Self> + Mul<Output = Self> {
    fn c(x: f64) -> Self;
}

impl<T: Real> Num for T {
    #[inline]
    fn c(x: f64) -> Self {
        T::from_f64(x)
    }
}

impl<T: Real> Add for Dual<T> {
    type Output = Self;
    #[inline]
    fn add(self, o: Self) -> Self {
        Dual {
            v: self.v + o.v,
            d: std::array::from_fn(|k| self.d[k] + o.d[k]),
        }
    }
}
impl<T: Real> Sub for Dual<T> {
    type Output = Self;
    #[inline]
    fn sub(self, o: Self) -> Self {
        Dual {
            v: self.v - o.v,
            d: std::array::from_fn(|k| self.d[k] - o.d[k]),
        }
    }
}
#[allow(clippy::suspicious_arithmetic_impl)]
impl<T: Real> Mul for Dual<T> {
    type Output = Self;
    #[inline]
    fn mul(self, o: Self) -> Self {
        Dual {
            v: self.v * o.v,
            d: std::array::from_fn(|k| self.d[k] * o.v + self.v * o.d[k]),
        }
    }
}
impl<T: Real> Num for Dual<T> {
    #[inline]
    fn c(x: f64) -> Self {
        Dual {
            v: T::from_f64(x),
            d: [T::ZERO; 3],
        }
    }
}

/// The SH basis `Y_0 .. Y_{(degree+1)²−1}` at the unit vector `(x, y, z)`
/// (gsplat's `pSH*` values; entries above the degree are left at zero).
fn basis<F: Num>(degree: usize, x: F, y: F, z: F, out: &mut [F; 25]) {
    let c = F::c;
    out[0] = c(0.2820947917738781);
    if degree < 1 {
        return;
    }
    out[1] = c(-0.48860251190292) * y;
    out[2] = c(0.48860251190292) * z;
    out[3] = c(-0.48860251190292) * x;
    if degree < 2 {
        return;
    }
    let z2 = z * z;
    let f_tmp0b = c(-1.092548430592079) * z;
    let f_c1 = x * x - y * y;
    let f_s1 = c(2.0) * x * y;
    let p6 = c(0.9461746957575601) * z2 - c(0.3153915652525201);
    out[4] = c(0.5462742152960395) * f_s1;
    out[5] = f_tmp0b * y;
    out[6] = p6;
    out[7] = f_tmp0b * x;
    out[8] = c(0.5462742152960395) * f_c1;
    if degree < 3 {
        return;
    }
    let f_tmp0c = c(-2.285228997322329) * z2 + c(0.4570457994644658);
    let f_tmp1b = c(1.445305721320277) * z;
    let f_c2 = x * f_c1 - y * f_s1;
    let f_s2 = x * f_s1 + y * f_c1;
    let p12 = z * (c(1.865881662950577) * z2 - c(1.119528997770346));
    out[9] = c(-0.5900435899266435) * f_s2;
    out[10] = f_tmp1b * f_s1;
    out[11] = f_tmp0c * y;
    out[12] = p12;
    out[13] = f_tmp0c * x;
    out[14] = f_tmp1b * f_c1;
    out[15] = c(-0.5900435899266435) * f_c2;
    if degree < 4 {
        return;
    }
    let f_tmp0d = z * (c(-4.683325804901025) * z2 + c(2.007139630671868));
    let f_tmp1c = c(3.31161143515146) * z2 - c(0.47308734787878);
    let f_tmp2b = c(-1.770130769779931) * z;
    let f_c3 = x * f_c2 - y * f_s2;
    let f_s3 = x * f_s2 + y * f_c2;
    out[16] = c(0.6258357354491763) * f_s3;
    out[17] = f_tmp2b * f_s2;
    out[18] = f_tmp1c * f_s1;
    out[19] = f_tmp0d * y;
    out[20] = c(1.984313483298443) * z * p12 - c(1.006230589874905) * p6;
    out[21] = f_tmp0d * x;
    out[22] = f_tmp1c * f_c1;
    out[23] = f_tmp2b * f_c2;
    out[24] = c(0.6258357354491763) * f_c3;
}

fn unit<T: Real>(dir: [T; 3]) -> ([T; 3], T) {
    let inorm = T::ONE / (dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]).sqrt();
    ([dir[0] * inorm, dir[1] * inorm, dir[2] * inorm], inorm)
}

/// Colour of one Gaussian: `D` channels from `coeffs [K, D]` at `dir`.
/// Degree 0 does not read the direction.
///
/// # Panics
///
/// If `degree > MAX_DEGREE`, `coeffs` holds fewer than `(degree+1)²·d`
/// values or `out` fewer than `d` (a low-level helper:
/// [`spherical_harmonics`] checks its arguments).
pub fn sh_color<T: Real>(degree: usize, dir: [T; 3], coeffs: &[T], d: usize, out: &mut [T]) {
    let mut y = [T::ZERO; 25];
    if degree == 0 {
        y[0] = T::from_f64(0.2820947917738781);
    } else {
        let (n, _) = unit(dir);
        basis(degree, n[0], n[1], n[2], &mut y);
    }
    for ch in 0..d {
        // One partial sum per degree, added in degree order, as gsplat does.
        let mut acc = y[0] * coeffs[ch];
        for l in 1..=degree {
            let (lo, hi) = (l * l, (l + 1) * (l + 1));
            let mut part = y[lo] * coeffs[lo * d + ch];
            for b in lo + 1..hi {
                part += y[b] * coeffs[b * d + ch];
            }
            acc += part;
        }
        out[ch] = acc;
    }
}

/// Backward of [`sh_color`]: writes `v_coeffs [K, D]` (zero above the
/// degree) and returns `v_dir`.
///
/// # Panics
///
/// If `degree > MAX_DEGREE`, or `coeffs` or `v_coeffs` holds fewer than
/// `(degree+1)²·d` values or `v_color` fewer than `d`.
pub fn sh_color_vjp<T: Real>(
    degree: usize,
    dir: [T; 3],
    coeffs: &[T],
    d: usize,
    v_color: &[T],
    v_coeffs: &mut [T],
) -> [T; 3] {
    v_coeffs.iter_mut().for_each(|v| *v = T::ZERO);
    let k = (degree + 1) * (degree + 1);
    if degree == 0 {
        for ch in 0..d {
            v_coeffs[ch] = T::from_f64(0.2820947917738781) * v_color[ch];
        }
        return [T::ZERO; 3];
    }
    let (n, inorm) = unit(dir);
    let var = |i: usize| Dual {
        v: n[i],
        d: std::array::from_fn(|k| if k == i { T::ONE } else { T::ZERO }),
    };
    let mut y = [Dual::<T>::c(0.0); 25];
    basis(degree, var(0), var(1), var(2), &mut y);
    let mut vn = [T::ZERO; 3];
    for ch in 0..d {
        let vc = v_color[ch];
        for (b, yb) in y.iter().enumerate().take(k) {
            v_coeffs[b * d + ch] = yb.v * vc;
            let cv = coeffs[b * d + ch] * vc;
            for a in 0..3 {
                vn[a] += cv * yb.d[a];
            }
        }
    }
    let dot = vn[0] * n[0] + vn[1] * n[1] + vn[2] * n[2];
    std::array::from_fn(|a| (vn[a] - dot * n[a]) * inorm)
}

/// `M` after checking the arguments of [`spherical_harmonics`]: the
/// degree, `dirs [M,3]`, `coeffs [M,K,D]` and `masks [M]`.
fn check<T>(
    degree: usize,
    dirs: &[T],
    coeffs: &[T],
    k: usize,
    d: usize,
    masks: Option<&[bool]>,
) -> Result<usize> {
    if degree > MAX_DEGREE || (degree + 1) * (degree + 1) > k {
        return Err(Error::invalid(
            "degrees_to_use",
            format!("{degree} with K = {k} coefficients (at most {MAX_DEGREE}, (degree+1)² ≤ K)"),
        ));
    }
    if !dirs.len().is_multiple_of(3) {
        return Err(Error::invalid(
            "dirs",
            format!("length {} is not a multiple of 3", dirs.len()),
        ));
    }
    let m = dirs.len() / 3;
    match m.checked_mul(k).and_then(|v| v.checked_mul(d)) {
        Some(want) => check_len("coeffs", coeffs.len(), want)?,
        None => {
            return Err(Error::invalid(
                "coeffs",
                format!(
                    "{} values, expected [{m}, {k}, {d}] (more than a slice holds)",
                    coeffs.len()
                ),
            ))
        }
    }
    if let Some(mk) = masks {
        check_len("masks", mk.len(), m)?;
    }
    Ok(m)
}

/// `gsplat.spherical_harmonics(degrees_to_use, dirs [M,3], coeffs [M,K,D],
/// masks [M])`: colours `[M, D]`; masked-out rows are 0. An error names the
/// argument that is out of range or of the wrong length
/// (`degrees_to_use` above [`MAX_DEGREE`] or with `(degree+1)² > K`,
/// `dirs`, `coeffs`, `masks`).
pub fn spherical_harmonics<T: Real>(
    degree: usize,
    dirs: &[T],
    coeffs: &[T],
    k: usize,
    d: usize,
    masks: Option<&[bool]>,
) -> Result<Vec<T>> {
    let m = check(degree, dirs, coeffs, k, d, masks)?;
    let mut out = vec![T::ZERO; m * d];
    for i in 0..m {
        if masks.is_some_and(|mk| !mk[i]) {
            continue;
        }
        let dir = [dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]];
        sh_color(
            degree,
            dir,
            &coeffs[i * k * d..(i + 1) * k * d],
            d,
            &mut out[i * d..(i + 1) * d],
        );
    }
    Ok(out)
}

/// Backward of [`spherical_harmonics`]: `(v_dirs [M,3], v_coeffs
/// [M,K,D])` from `v_colors [M,D]`, with the forward's checks and that of
/// `v_colors`'s length.
pub fn spherical_harmonics_vjp<T: Real>(
    degree: usize,
    dirs: &[T],
    coeffs: &[T],
    k: usize,
    d: usize,
    masks: Option<&[bool]>,
    v_colors: &[T],
) -> Result<(Vec<T>, Vec<T>)> {
    let m = check(degree, dirs, coeffs, k, d, masks)?;
    // `m·d ≤ m·k·d` (k ≥ 1), which did not overflow.
    check_len("v_colors", v_colors.len(), m * d)?;
    let mut v_dirs = vec![T::ZERO; 3 * m];
    let mut v_coeffs = vec![T::ZERO; m * k * d];
    for i in 0..m {
        if masks.is_some_and(|mk| !mk[i]) {
            continue;
        }
        let dir = [dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]];
        let vd = sh_color_vjp(
            degree,
            dir,
            &coeffs[i * k * d..(i + 1) * k * d],
            d,
            &v_colors[i * d..(i + 1) * d],
            &mut v_coeffs[i * k * d..(i + 1) * k * d],
        );
        v_dirs[3 * i..3 * i + 3].copy_from_slice(&vd);
    }
    Ok((v_dirs, v_coeffs))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn err<V: std::fmt::Debug>(r: Result<V>) -> String {
        r.unwrap_err().to_string()
    }

    #[test]
    fn bad_arguments_are_refused() {
        let dirs = [0.0f64, 0.0, 1.0, 1.0, 0.0, 0.0];
        let (k, d) = (4, 3);
        let coeffs = vec![0.25f64; 2 * k * d];
        let sh = |deg, dirs: &[f64], c: &[f64], k, m: Option<&[bool]>| {
            spherical_harmonics(deg, dirs, c, k, d, m)
        };
        // Degree above MAX_DEGREE, and (degree+1)² > K.
        let e = err(sh(5, &dirs, &vec![0.0; 2 * 36 * d], 36, None));
        assert!(
            e.contains("degrees_to_use") && e.contains("5 with K = 36"),
            "{e}"
        );
        let e = err(sh(2, &dirs, &coeffs, k, None));
        assert!(
            e.contains("degrees_to_use") && e.contains("2 with K = 4"),
            "{e}"
        );
        // Short coefficients, masks, dirs; K·D past usize.
        let e = err(sh(1, &dirs, &coeffs[..2 * k * d - 1], k, None));
        assert!(
            e.contains("coeffs") && e.contains("23 values, expected 24"),
            "{e}"
        );
        let e = err(sh(1, &dirs, &coeffs, k, Some(&[true])));
        assert!(
            e.contains("masks") && e.contains("1 values, expected 2"),
            "{e}"
        );
        let e = err(sh(1, &dirs[..5], &coeffs, k, None));
        assert!(e.contains("dirs") && e.contains("5"), "{e}");
        let e = err(sh(1, &dirs, &coeffs, usize::MAX / 2, None));
        assert!(e.contains("coeffs"), "{e}");
        // Short v_colors in the backward.
        let v = [1.0f64; 6];
        let e = err(spherical_harmonics_vjp(
            1,
            &dirs,
            &coeffs,
            k,
            d,
            None,
            &v[..5],
        ));
        assert!(
            e.contains("v_colors") && e.contains("5 values, expected 6"),
            "{e}"
        );
        let e = err(spherical_harmonics_vjp(7, &dirs, &coeffs, k, d, None, &v));
        assert!(e.contains("degrees_to_use"), "{e}");
        // Valid arguments pass (a masked-out Gaussian's colour is 0).
        let masks = [true, false];
        let c = sh(1, &dirs, &coeffs, k, Some(&masks)).unwrap();
        assert_eq!(c[3..], [0.0; 3]);
        spherical_harmonics_vjp(1, &dirs, &coeffs, k, d, None, &v).unwrap();
    }
}
