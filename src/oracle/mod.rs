//! The oracle: what backend authors run in their CI against this reference.
//!
//! A *case file* is a safetensors file whose string metadata names the stage
//! (`stage=rasterize|deform|loss|step|gsplat_*`) and its settings, and whose tensors are the
//! stage's inputs under the names of the upstream Python APIs. [`run_case`]
//! computes the stage's outputs and gradients into another tensor file; the
//! tensors' dtype (F32 or F64) selects the precision.
//!
//! A stage differentiates the sum of its outputs weighted by cotangent
//! tensors (`grad_out_*`, `grad_d_*`, gsplat's `v_<output>`). Every
//! cotangent is optional: an absent one reads as zeros of its shape
//! ([`cotangent`]), so a case without cotangents is a forward-only run whose
//! gradients are zero.
//!
//! - [`rasterize`]: the Inria rasterizer's forward and backward.
//! - [`deform`]: the MLP and CfC deformation fields' forward and backward.
//! - [`field`](mod@field): deformation fields in tensor files (configuration
//!   metadata and `state_dict` weights), for the case files and checkpoints.
//! - [`loss`]: L1 + SSIM training loss and its gradient.
//! - [`step`]: one whole training iteration (field, rasterizer, loss,
//!   backward, densification statistics, Adam).
//! - [`gsplat`](mod@gsplat): gsplat's functions (`quat_scale_to_covar_preci`,
//!   `spherical_harmonics`, `fully_fused_projection`, `isect_tiles`,
//!   `rasterize_to_pixels`, `rasterization`) at versions 1.5.3 and 1.6.
//! - [`new`]: seeded random, well-formed case files for every stage, and
//!   the golden fixtures (`fixtures/cases/`).
//! - [`compare`](mod@compare): tensor-by-tensor comparison of an expected case output with
//!   an actual one, with a report richer than a max-abs number (relative L2,
//!   cosine similarity, signed bias, ULP distance, NaN/Inf counts, the worst
//!   element) and PyTorch's `allclose` rule for pass/fail.

pub mod compare;
pub mod deform;
pub mod field;
pub mod gsplat;
pub mod loss;
pub mod new;
pub mod rasterize;
pub mod step;

pub use compare::{
    compare, CompareReport, ElementStats, Status, TensorReport, Tolerance, ToleranceSpec,
    Tolerances, Worst,
};

use crate::error::{Error, Result};
use crate::io::TensorFile;
use crate::math::Real;

/// Stage names [`run_case`] understands.
pub const STAGES: &[&str] = &[
    rasterize::STAGE,
    deform::STAGE,
    loss::STAGE,
    step::STAGE,
    gsplat::COVAR,
    gsplat::SH,
    gsplat::PROJECTION,
    gsplat::ISECT,
    gsplat::RASTERIZE,
    gsplat::RASTERIZATION,
];

/// Run the stage named by the case's `stage` metadata.
///
/// Every floating-point input must be finite: a `NaN` or `±inf` element of
/// any tensor is an error naming the tensor and its flat index (a backend
/// that propagates `NaN` must not be compared against a result computed
/// from culled Gaussians). Errors name the case file.
pub fn run_case(case: &TensorFile) -> Result<TensorFile> {
    run_stage(case).map_err(|e| e.in_file(&case.path))
}

fn run_stage(case: &TensorFile) -> Result<TensorFile> {
    case.check_finite()?;
    match case.meta("stage")? {
        s if s == rasterize::STAGE => rasterize::run(case),
        s if s == deform::STAGE => deform::run(case),
        s if s == loss::STAGE => loss::run(case),
        s if s == step::STAGE => step::run(case),
        s if gsplat::STAGES.contains(&s) => gsplat::run(case),
        other => Err(Error::field(
            &case.path,
            "__metadata__.stage",
            format!("unknown stage `{other}` (known: {})", STAGES.join(", ")),
        )),
    }
}

/// Cotangent tensor `name` of shape `shape`, or zeros of that shape when the
/// case does not hold it (a forward-only case). A present tensor of another
/// shape or dtype is an error naming it.
pub fn cotangent<T: Real>(case: &TensorFile, name: &str, shape: &[usize]) -> Result<Vec<T>> {
    if case.contains(name) {
        case.get_real::<T>(name, shape)
    } else {
        Ok(vec![T::ZERO; shape.iter().product()])
    }
}
