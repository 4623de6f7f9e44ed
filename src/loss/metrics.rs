//! Evaluation metrics as D-3DGS `metrics.py` computes them (docs/UPSTREAM.md §6.10):
//! on 8-bit-quantised images.
//!
//! Renders and ground truth are saved with torchvision `save_image`
//! (`u8 = trunc(clamp(x·255 + 0.5, 0, 255))`, in f32) and read back as
//! `u8 / 255`. [`quantize_u8`] reproduces that round trip; [`psnr`] and
//! [`ssim_u8`] apply it to both images first. LPIPS is not computed here.

use super::{check_image_pair, ssim};
use crate::error::Result;
use crate::math::Real;

/// `trunc(clamp(x·255 + 0.5, 0, 255))`: the byte `save_image` writes (NaN
/// maps to 0, as a float-to-u8 cast of NaN does in Rust).
pub fn to_u8<T: Real>(x: T) -> u8 {
    let v = (x * T::from_f64(255.0) + T::from_f64(0.5)).clamp(T::ZERO, T::from_f64(255.0));
    v.trunc().to_f64() as u8
}

/// The value the metrics see after saving and reloading: `to_u8(x) / 255`.
pub fn quantize_u8<T: Real>(x: T) -> T {
    T::from_f64(to_u8(x) as f64) / T::from_f64(255.0)
}

/// Quantise every value of an image.
pub fn quantize_image<T: Real>(x: &[T]) -> Vec<T> {
    x.iter().map(|&v| quantize_u8(v)).collect()
}

/// PSNR `20·log10(1/sqrt(MSE))` of two already-quantised (or raw) images.
/// Identical images give +infinity (as upstream).
///
/// # Panics
/// If `a.len() != b.len()` ([`psnr`] is the checked entry point).
pub fn psnr_raw<T: Real>(a: &[T], b: &[T]) -> T {
    assert!(
        a.len() == b.len(),
        "psnr_raw: the images have {} and {} values",
        a.len(),
        b.len()
    );
    let mut s = T::ZERO;
    for (&x, &y) in a.iter().zip(b) {
        let d = x - y;
        s += d * d;
    }
    let mse = s / T::from_usize(a.len());
    T::from_f64(20.0) * (T::ONE / mse.sqrt()).log10()
}

/// PSNR of `[3, h, w]` images after 8-bit quantisation of both.
pub fn psnr<T: Real>(render: &[T], gt: &[T], h: usize, w: usize) -> Result<T> {
    check_image_pair(render.len(), gt.len(), h, w)?;
    Ok(psnr_raw(&quantize_image(render), &quantize_image(gt)))
}

/// SSIM (docs/UPSTREAM.md §6.7) of `[3, h, w]` images after 8-bit quantisation of both.
pub fn ssim_u8<T: Real>(render: &[T], gt: &[T], h: usize, w: usize) -> Result<T> {
    check_image_pair(render.len(), gt.len(), h, w)?;
    Ok(ssim::ssim(&quantize_image(render), &quantize_image(gt), h, w).value)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantisation_is_save_image_rounding() {
        assert_eq!(to_u8(0.0f32), 0);
        assert_eq!(to_u8(1.0f32), 255);
        assert_eq!(to_u8(1.7f32), 255);
        assert_eq!(to_u8(-0.3f32), 0);
        // 0.5·255 + 0.5 = 128.0 exactly: trunc gives 128 (round half up).
        assert_eq!(to_u8(0.5f64), 128);
        // Just below a half step truncates down.
        assert_eq!(to_u8(1.49 / 255.0), 1);
        assert_eq!(to_u8(1.51 / 255.0), 2);
        assert_eq!(to_u8(f32::NAN), 0);
        for b in 0..=255u8 {
            assert_eq!(to_u8(b as f32 / 255.0), b, "byte {b} must round-trip");
        }
    }

    #[test]
    fn psnr_of_a_known_error() {
        // Every value off by exactly 5/255 after quantisation: MSE = (5/255)²,
        // PSNR = 20 log10(255/5).
        let (h, w) = (2, 3);
        let gt: Vec<f64> = (0..18).map(|i| (10 + i) as f64 / 255.0).collect();
        let render: Vec<f64> = gt.iter().map(|v| v + 5.2 / 255.0).collect();
        let p = psnr(&render, &gt, h, w).unwrap();
        let want = 20.0 * libm::log10(255.0 / 5.0);
        assert!((p - want).abs() < 1e-12, "{p} vs {want}");
        assert!(psnr(&gt, &gt, h, w).unwrap().is_infinite());
        assert!(psnr(&gt, &gt[..17], h, w).is_err());
    }

    #[test]
    fn metric_ssim_uses_quantised_images() {
        let (h, w) = (6, 7);
        let gt: Vec<f64> = (0..3 * h * w)
            .map(|i| ((i * 37) % 101) as f64 / 100.0)
            .collect();
        // A perturbation smaller than half a quantisation step disappears.
        let render: Vec<f64> = gt.iter().map(|&v| quantize_u8(v) + 0.1 / 255.0).collect();
        let s = ssim_u8(&render, &gt, h, w).unwrap();
        assert!((s - 1.0).abs() < 1e-14, "{s}");
    }

    #[test]
    #[should_panic(expected = "psnr_raw: the images have 3 and 2 values")]
    fn psnr_raw_of_mismatched_lengths_panics() {
        psnr_raw(&[0.0f32; 3], &[0.0; 2]);
    }
}
