//! Oracle stage `loss`: the training loss and its gradient for one image pair.
//!
//! Inputs: `image` `[3, H, W]`, `gt` `[3, H, W]` (both F32 or both F64; the
//! precision selects the computation), optional metadata `lambda_dssim`
//! (default 0.2). Outputs, in the same precision: `l1`, `ssim`, `loss` as
//! rank-0 tensors (shape `[]`), and `grad_image` `[3, H, W]` = dL/dimage.
//! Metadata `lambda_dssim` is echoed into the output.

/// The `stage` metadata value of a loss case.
pub const STAGE: &str = "loss";

use crate::error::{Error, Result};
use crate::io::tensor_file::into_row_major;
use crate::io::TensorFile;
use crate::loss::{loss_and_grad, LAMBDA_DSSIM};
use crate::math::{Precision, Real};

/// Run the stage on a case file.
pub fn run(case: &TensorFile) -> Result<TensorFile> {
    case.reject_unknown(["image", "gt"])?;
    match case.precision()? {
        Precision::F32 => run_t::<f32>(case),
        Precision::F64 => run_t::<f64>(case),
    }
}

fn run_t<T: Real>(case: &TensorFile) -> Result<TensorFile> {
    use crate::render::MAX_PIXELS;
    // (The shape first: nothing of the image's size is made before it.)
    let (h, w) = match *case.shape("image")? {
        // (The rasterizer's limit: the SSIM's buffers take several times
        // the image.)
        [3, h, w] if h > 0 && w > 0 && h.saturating_mul(w) <= MAX_PIXELS => (h, w),
        ref shape => {
            return Err(Error::Tensor {
                context: case.path.display().to_string(),
                name: "image".into(),
                expected: format!("shape [3,H,W] with H, W > 0 and H·W ≤ {MAX_PIXELS}"),
                found: format!("shape {shape:?}"),
            })
        }
    };
    let image = into_row_major(case.real_array::<T>("image")?);
    let gt = case.get_real::<T>("gt", &[3, h, w])?;
    let lambda = case.meta_finite_or("lambda_dssim", LAMBDA_DSSIM)?;
    if !(0.0..=1.0).contains(&lambda) {
        return Err(Error::field(
            &case.path,
            "__metadata__.lambda_dssim",
            format!("{lambda} (must be in [0, 1])"),
        ));
    }
    let (out, grad) = loss_and_grad(&image, &gt, h, w, lambda)?;
    let mut res = TensorFile::new(&case.path);
    res.set_meta("lambda_dssim", lambda);
    res.insert_real("l1", vec![], &[out.l1]);
    res.insert_real("ssim", vec![], &[out.ssim]);
    res.insert_real("loss", vec![], &[out.loss]);
    res.insert_real("grad_image", vec![3, h, w], &grad);
    Ok(res)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::Rng;
    use std::path::Path;

    fn case(h: usize, w: usize) -> TensorFile {
        let mut r = Rng::new(3);
        let img: Vec<f32> = (0..3 * h * w).map(|_| r.uniform() as f32).collect();
        let gt: Vec<f32> = (0..3 * h * w).map(|_| r.uniform() as f32).collect();
        let mut c = TensorFile::new("case.safetensors");
        c.insert_real("image", vec![3, h, w], &img);
        c.insert_real("gt", vec![3, h, w], &gt);
        c
    }

    #[test]
    fn outputs_round_trip_and_match_the_library() {
        let mut c = case(5, 6);
        c.set_meta("lambda_dssim", 0.3);
        let out = run(&c).unwrap();
        let bytes = out.to_bytes().unwrap();
        let back = TensorFile::from_bytes(Path::new("out"), &bytes).unwrap();
        let loss = back.get_real::<f32>("loss", &[]).unwrap();
        let img = c.get_real::<f32>("image", &[3, 5, 6]).unwrap();
        let gt = c.get_real::<f32>("gt", &[3, 5, 6]).unwrap();
        let (want, grad) = loss_and_grad(&img, &gt, 5, 6, 0.3).unwrap();
        assert_eq!(loss, vec![want.loss]);
        assert_eq!(back.get_real::<f32>("ssim", &[]).unwrap(), vec![want.ssim]);
        assert_eq!(
            back.get_real::<f32>("grad_image", &[3, 5, 6]).unwrap(),
            grad
        );
    }

    #[test]
    fn bad_cases_are_errors() {
        let mut c = case(4, 4);
        c.insert_real("extra", vec![1], &[0.0f32]);
        assert!(run(&c).is_err());
        let mut c = case(4, 4);
        c.insert_real("gt", vec![3, 4, 5], &[0.0f32; 60]);
        assert!(run(&c).is_err());
        let mut c = case(4, 4);
        c.insert_real("gt", vec![3, 4, 4], &[0.0f64; 48]);
        assert!(run(&c).is_err(), "mixed precision");
        let mut c = case(4, 4);
        c.insert_real("image", vec![1, 4, 12], &[0.0f32; 48]);
        assert!(run(&c).is_err());
        let mut c = case(4, 4);
        c.set_meta("lambda_dssim", "abc");
        assert!(run(&c).is_err());
    }

    /// More pixels than the rasterizer's limit are refused from the shape,
    /// before anything of the image's size is made (the zeros below are
    /// never touched).
    #[test]
    fn images_past_the_pixel_limit_are_refused() {
        use crate::io::Tensor;
        use crate::render::MAX_PIXELS;
        let mut c = TensorFile::new("case.safetensors");
        for name in ["image", "gt"] {
            let z = ndarray::ArrayD::<f32>::zeros(ndarray::IxDyn(&[3, 1, MAX_PIXELS + 1]));
            c.insert(name, Tensor::F32(z));
        }
        let e = run(&c).unwrap_err().to_string();
        assert!(e.contains("`image`") && e.contains("H·W ≤ 67108864"), "{e}");
    }
}
