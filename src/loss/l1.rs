//! Mean absolute error over a `[3, H, W]` image, and its vjp.
//!
//! `L1(x, y) = mean |x - y|` over every element. The sum runs one row (W
//! values) at a time in column order; row partial sums are combined in row
//! order, so the result does not depend on the thread count. (PyTorch's
//! `mean` uses its own cascade order, so the f32 value may differ from it in
//! the last bits; it is deterministic here.)

use crate::kernels::fastmath::multiversion;
use crate::math::Real;
use rayon::prelude::*;

/// Sum of `|x - y|` per row of `w` values, in row order.
pub(crate) fn row_abs_sums<T: Real>(x: &[T], y: &[T], w: usize) -> Vec<T> {
    x.par_chunks(w.max(1))
        .zip(y.par_chunks(w.max(1)))
        .map(|(xr, yr)| {
            let mut s = T::ZERO;
            for (&a, &b) in xr.iter().zip(yr) {
                s += (a - b).abs();
            }
            s
        })
        .collect()
}

/// Mean absolute error `mean |x - y|`; `w` is the row length used to split
/// the work (any positive value gives a valid mean; use the image width).
///
/// # Panics
/// If `x.len() != y.len()`.
pub fn l1<T: Real>(x: &[T], y: &[T], w: usize) -> T {
    assert_lengths("l1", x, y, None);
    let mut total = T::ZERO;
    for s in row_abs_sums(x, y, w) {
        total += s;
    }
    total / T::from_usize(x.len())
}

/// Backward of [`l1`]: `dL/dx_i = grad_out / n * sign(x_i - y_i)`.
///
/// The subgradient at `x_i == y_i` is 0, as PyTorch's `abs` backward
/// (`sgn`) defines it. `grad_out / n` is rounded once, as PyTorch's `mean`
/// backward does, and then multiplied by the sign (exact).
///
/// # Panics
/// If `x`, `y` and `grad_x` do not all have the same length.
pub fn l1_vjp<T: Real>(x: &[T], y: &[T], grad_out: T, grad_x: &mut [T]) {
    assert_lengths("l1_vjp", x, y, Some(grad_x.len()));
    let g = grad_out / T::from_usize(x.len());
    grad_x
        .par_chunks_mut(CHUNK)
        .zip(x.par_chunks(CHUNK).zip(y.par_chunks(CHUNK)))
        .for_each(|(gx, (x, y))| sign_times(gx, x, y, g));
}

/// Panics unless `x`, `y` (and the gradient, when given) have one length.
fn assert_lengths<T>(f: &str, x: &[T], y: &[T], grad: Option<usize>) {
    assert!(
        x.len() == y.len() && grad.is_none_or(|g| g == x.len()),
        "l1::{f}: x has {} values, y {}{}",
        x.len(),
        y.len(),
        grad.map_or(String::new(), |g| format!(" and grad_x {g}"))
    );
}

/// Elements per task of the element-wise passes.
const CHUNK: usize = 4096;

/// `g·sign(d)` (+0 where `d` is zero or NaN), as selects.
#[inline(always)]
fn sign_times_one<T: Real>(d: T, g: T) -> T {
    let pos = if d > T::ZERO { g } else { T::ZERO };
    if d < T::ZERO {
        -g
    } else {
        pos
    }
}

multiversion!(fn sign_times<T: Real>(gx: &mut [T], x: &[T], y: &[T], g: T) => sign_times_body);

/// `gx_i = g·sign(x_i − y_i)`.
#[inline(always)]
fn sign_times_body<T: Real>(gx: &mut [T], x: &[T], y: &[T], g: T) {
    for ((gx, &a), &b) in gx.iter_mut().zip(x).zip(y) {
        *gx = sign_times_one(a - b, g);
    }
}

/// [`l1_vjp`] added onto `grad_x`: `grad_x_i += grad_out / n · sign(x_i −
/// y_i)` (adding +0 where equal). Panics as [`l1_vjp`].
pub(crate) fn l1_vjp_add<T: Real>(x: &[T], y: &[T], grad_out: T, grad_x: &mut [T]) {
    assert_lengths("l1_vjp_add", x, y, Some(grad_x.len()));
    let g = grad_out / T::from_usize(x.len());
    grad_x
        .par_chunks_mut(CHUNK)
        .zip(x.par_chunks(CHUNK).zip(y.par_chunks(CHUNK)))
        .for_each(|(gx, (x, y))| add_sign_times(gx, x, y, g));
}

multiversion!(fn add_sign_times<T: Real>(gx: &mut [T], x: &[T], y: &[T], g: T) => add_sign_times_body);

/// `gx_i += g·sign(x_i − y_i)`.
#[inline(always)]
fn add_sign_times_body<T: Real>(gx: &mut [T], x: &[T], y: &[T], g: T) {
    for ((gx, &a), &b) in gx.iter_mut().zip(x).zip(y) {
        *gx += sign_times_one(a - b, g);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};

    #[test]
    fn l1_value_and_gradient() {
        let n = 3 * 5 * 4;
        let x0 = cotangent(1, n);
        let y = cotangent(2, n);
        let direct: f64 = x0.iter().zip(&y).map(|(a, b)| (a - b).abs()).sum::<f64>() / n as f64;
        assert!((l1(&x0, &y, 4) - direct).abs() < 1e-15);
        let mut ga = vec![0.0; n];
        l1_vjp(&x0, &y, 0.7, &mut ga);
        let mut x = x0.clone();
        let gn = numeric_gradient(&mut x, 1e-6, |x| 0.7 * l1(x, &y, 4));
        let r = compare("l1", &ga, &gn, 1e-6);
        assert!(r.passes(1e-6), "{r}");
    }

    /// `l1_vjp` and `l1_vjp_add` give, on every instruction-set path, the
    /// bits of the branches `d > 0 → g, d < 0 → −g, else +0` (NaN and signed
    /// zeros included), with `g = grad_out / n`.
    #[test]
    fn sign_gradient_has_the_bits_of_the_branches_on_every_path() {
        let _isa = crate::kernels::fastmath::isa_test_lock();
        use crate::kernels::fastmath::{force_isa, Isa};
        let vals = [
            0.0f32,
            -0.0,
            1.0,
            -1.0,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            1e-30,
            -1e-30,
        ];
        let (mut x, mut y) = (Vec::new(), Vec::new());
        for &a in &vals {
            for &b in &vals {
                x.push(a);
                y.push(b);
            }
        }
        let base: Vec<f32> = (0..x.len())
            .map(|i| vals[(i * 7 + 3) % vals.len()])
            .collect();
        for grad_out in [0.75f32, -0.0, 0.0] {
            let g = grad_out / x.len() as f32;
            let branch = |a: f32, b: f32| {
                let d = a - b;
                if d > 0.0 {
                    g
                } else if d < 0.0 {
                    -g
                } else {
                    0.0
                }
            };
            let want: Vec<u32> = x
                .iter()
                .zip(&y)
                .map(|(&a, &b)| branch(a, b).to_bits())
                .collect();
            let want_add: Vec<u32> = x
                .iter()
                .zip(&y)
                .zip(&base)
                .map(|((&a, &b), &c)| (c + branch(a, b)).to_bits())
                .collect();
            for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
                if force_isa(Some(isa)) {
                    let mut got = vec![9.0f32; x.len()];
                    l1_vjp(&x, &y, grad_out, &mut got);
                    let got: Vec<u32> = got.iter().map(|v| v.to_bits()).collect();
                    assert_eq!(got, want, "{isa:?}, grad_out {grad_out}");
                    let mut got = base.clone();
                    l1_vjp_add(&x, &y, grad_out, &mut got);
                    let got: Vec<u32> = got.iter().map(|v| v.to_bits()).collect();
                    assert_eq!(got, want_add, "{isa:?}, grad_out {grad_out}, added");
                }
            }
            force_isa(None);
        }
    }

    #[test]
    fn l1_subgradient_at_zero_is_zero() {
        let x = [0.5f32, 0.25, 1.0];
        let y = [0.5f32, 0.5, 0.0];
        let mut g = [9.0f32; 3];
        l1_vjp(&x, &y, 3.0, &mut g);
        assert_eq!(g, [0.0, -1.0, 1.0]);
    }

    #[test]
    #[should_panic(expected = "l1::l1: x has 4 values, y 3")]
    fn l1_of_mismatched_lengths_panics() {
        l1(&[0.0f32; 4], &[0.0; 3], 2);
    }

    #[test]
    #[should_panic(expected = "l1::l1_vjp: x has 4 values, y 4 and grad_x 2")]
    fn l1_vjp_with_a_short_gradient_panics() {
        l1_vjp(&[0.0f32; 4], &[0.0; 4], 1.0, &mut [0.0; 2]);
    }

    #[test]
    #[should_panic(expected = "l1::l1_vjp: x has 4 values, y 3")]
    fn l1_vjp_of_mismatched_lengths_panics() {
        l1_vjp(&[0.0f32; 4], &[0.0; 3], 1.0, &mut [0.0; 4]);
    }
}
