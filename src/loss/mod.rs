//! The photometric training loss of D-3DGS and its gradient with respect to
//! the rendered image.
//!
//! `loss = (1 − λ)·L1(image, gt) + λ·(1 − SSIM(image, gt))`, λ = `lambda_dssim`
//! = 0.2 by default (docs/UPSTREAM.md §6.4, docs/DECISIONS.md §2b). The render is **not**
//! clamped before the loss; `gt` is used as given (the loader clamps it).
//!
//! Scalars are combined as PyTorch does for an f32 tensor and a Python float:
//! the constants `1 − λ` (computed in f64) and `λ` are rounded to `T`, then
//! `loss = T(1−λ)·L1 + T(λ)·(1 − SSIM)`. The gradient is
//! `T(1−λ)/n · sign(image − gt) + SSIM-vjp(−T(λ))`.
//!
//! - [`l1`]: mean absolute error and its vjp.
//! - [`ssim`]: SSIM (11×11 Gaussian window) and its vjp.
//! - [`metrics`]: PSNR and SSIM on 8-bit-quantised images, as the evaluation does.

pub mod l1;
pub mod metrics;
pub mod ssim;

use crate::error::{Error, Result};
use crate::kernels::{filled, par_blocks_written, vec_written_by};
use crate::math::Real;

/// Default weight of the D-SSIM term.
pub const LAMBDA_DSSIM: f64 = 0.2;

/// The loss and its two terms.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LossOutput<T> {
    /// Mean absolute error.
    pub l1: T,
    /// Mean SSIM (1 for identical images).
    pub ssim: T,
    /// `(1 − λ)·l1 + λ·(1 − ssim)`.
    pub loss: T,
}

/// Check that `image` and `gt` are `[3, h, w]` with `h, w > 0`.
pub fn check_image_pair(image_len: usize, gt_len: usize, h: usize, w: usize) -> Result<()> {
    if h == 0 || w == 0 {
        return Err(Error::invalid(
            "image size",
            format!("{h}x{w}: height and width must be positive"),
        ));
    }
    let want = h.checked_mul(w).and_then(|v| v.checked_mul(3));
    if want != Some(image_len) || image_len != gt_len {
        return Err(Error::invalid(
            "image pair",
            format!(
                "image has {image_len} values and gt {gt_len}, expected 3x{h}x{w} = {} each",
                want.map_or("overflow".to_string(), |v| v.to_string())
            ),
        ));
    }
    Ok(())
}

/// The training loss and `dL/dimage` (`[3, h, w]`, same layout as `image`).
///
/// Errors if the images are not both `[3, h, w]` or `lambda_dssim` is not in
/// `[0, 1]`.
pub fn loss_and_grad<T: Real>(
    image: &[T],
    gt: &[T],
    h: usize,
    w: usize,
    lambda_dssim: f64,
) -> Result<(LossOutput<T>, Vec<T>)> {
    check_image_pair(image.len(), gt.len(), h, w)?;
    if !(0.0..=1.0).contains(&lambda_dssim) {
        return Err(Error::invalid(
            "lambda_dssim",
            format!("{lambda_dssim} (must be in [0, 1])"),
        ));
    }
    let w_l1 = T::from_f64(1.0 - lambda_dssim);
    let w_ssim = T::from_f64(lambda_dssim);

    let l1v = l1::l1(image, gt, w);
    let fwd = ssim::ssim(image, gt, h, w);
    let loss = w_l1 * l1v + w_ssim * (T::ONE - fwd.value);

    // The L1 term is added onto the SSIM term (IEEE addition commutes, so
    // this is `l1 + ssim` element by element).
    let mut grad = ssim::ssim_vjp(&fwd, image, gt, -w_ssim);
    l1::l1_vjp_add(image, gt, w_l1, &mut grad);
    Ok((
        LossOutput {
            l1: l1v,
            ssim: fwd.value,
            loss,
        },
        grad,
    ))
}

/// A vector of `n` values made by rows of `w` in parallel: each task zeroes
/// its row (while it is in cache) and then runs `f(row index, row)` on it.
/// A serial zeroed allocation of a few MB costs as much as the pass that
/// fills it.
pub(crate) fn par_rows<T: Real>(n: usize, w: usize, f: impl Fn(usize, &mut [T]) + Sync) -> Vec<T> {
    vec_written_by(n, |buf| {
        par_blocks_written(buf, w, &mut [(); 0], 0, |r, row, _| {
            let row = filled(row, T::ZERO);
            f(r, row);
            row
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, numeric_gradient};
    use crate::math::Rng;

    #[test]
    fn loss_gradient_matches_finite_differences() {
        let (h, w) = (9, 12);
        let mut r = Rng::new(11);
        // Render values may leave [0, 1]; keep |image - gt| away from 0 so
        // that L1 is differentiable at the check point.
        let gt: Vec<f64> = (0..3 * h * w).map(|_| r.uniform()).collect();
        let image: Vec<f64> = gt
            .iter()
            .map(|&g| {
                let d = r.uniform_range(0.05, 0.3);
                if r.uniform() < 0.5 {
                    g + d
                } else {
                    g - d
                }
            })
            .collect();
        let (out, ga) = loss_and_grad(&image, &gt, h, w, 0.2).unwrap();
        let direct = 0.8 * out.l1 + 0.2 * (1.0 - out.ssim);
        assert!((out.loss - direct).abs() < 1e-15);
        let mut x = image.clone();
        // Step 1e-4: see the SSIM gradient test for why (rounding noise of the
        // SSIM mean at smaller steps); the L1 part is piecewise linear, and
        // |image - gt| >= 0.05 keeps every ±h step on one side of its kink.
        let gn = numeric_gradient(&mut x, 1e-4, |x| {
            loss_and_grad(x, &gt, h, w, 0.2).unwrap().0.loss
        });
        let floor = 1e-3 * gn.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let rep = compare("loss dimage", &ga, &gn, floor);
        assert!(rep.passes(1e-6), "{rep}");
    }

    #[test]
    fn bad_shapes_are_errors() {
        let a = vec![0.0f32; 12];
        assert!(loss_and_grad(&a, &a, 2, 2, 0.2).is_ok());
        assert!(loss_and_grad(&a, &a[..11], 2, 2, 0.2).is_err());
        assert!(loss_and_grad(&a, &a, 3, 2, 0.2).is_err());
        assert!(loss_and_grad(&a, &a, 0, 2, 0.2).is_err());
        assert!(loss_and_grad(&a, &a, 2, 2, f64::NAN).is_err());
        for lambda in [1e300, -0.1, 1.0 + 1e-9, f64::INFINITY] {
            let e = loss_and_grad(&a, &a, 2, 2, lambda).unwrap_err();
            assert!(e.to_string().contains("lambda_dssim"), "{lambda}: {e}");
        }
        assert!(loss_and_grad(&a, &a, 2, 2, 0.0).is_ok());
        assert!(loss_and_grad(&a, &a, 2, 2, 1.0).is_ok());
    }
}
