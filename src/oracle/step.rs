//! Oracle stage `step`: one whole training iteration of D-3DGS on a case
//! file, in upstream's order, with every intermediate a backend must match.
//!
//! The iteration (docs/UPSTREAM.md §6.4–6.6, `train.py`):
//!
//! 1. field forward at `time` on the detached canonical centres (skipped
//!    with `field_on=false`, upstream's warm-up);
//! 2. deformed, activated Gaussians → rasterizer forward (exact gradient
//!    mode, `scale_modifier = 1`, SH up to `active_sh_degree`); with the
//!    6-DoF MLP the mean is upstream's `R·x + p` on the non-detached
//!    canonical mean `x`, so `grad.xyz` is `Rᵀ·g` (`g` = dL/dmeans3D), not
//!    `g` as for the additive fields;
//! 3. `loss = (1 − λ)·L1 + λ·(1 − SSIM)` against `gt`;
//! 4. backward of the loss, the rasterizer, the activations and the field;
//! 5. densification statistics: `max_radii`, `accum`, `denom` of the
//!    Gaussians with `radii > 0`;
//! 6. one Adam step of every Gaussian group and, when the field is on, of
//!    the field weights (a group without gradient does not step, as
//!    `torch.optim.Adam` skips parameters whose `.grad` is `None`).
//!
//! Not inside the stage, because they are decided by the iteration number
//! and the run's random state, which a case does not have: the learning-rate
//! schedules (the rates are inputs), the SH degree schedule
//! (`active_sh_degree` is an input), AST time noise (`time` is used as
//! given), densification/pruning and opacity reset (upstream runs them
//! between steps 5 and 6 on some iterations; a backend checks those with
//! the statistics this stage outputs).
//!
//! The computation is [`Model::gradients`] followed by
//! [`DensifyStats::update`] and [`ModelOptimizer::step`](crate::train::ModelOptimizer::step): the code
//! [`Trainer::step`](crate::train::Trainer::step) runs. The state is read
//! and written in the layout of [`crate::train::state`], which checkpoints
//! share.
//!
//! Tensor names, shapes and conventions are in `docs/ORACLE.md`.

use super::rasterize::{read_camera, CAMERA_TENSORS};
use crate::densify::DensifyStats;
use crate::error::{Error, Result};
use crate::gaussians::Group;
use crate::io::TensorFile;
use crate::math::{Precision, Real};
use crate::optim::{LearningRates, StepGroups, StepRates};
use crate::train::state::{self, Source};
use crate::train::{Model, View};

/// The `stage` metadata value of a step case.
pub const STAGE: &str = "step";

/// The learning-rate metadata keys (`lr.<name>`) and their defaults:
/// upstream's initial rates ([`LearningRates::initial`]).
pub fn default_learning_rates() -> [(&'static str, f64); 7] {
    let d = LearningRates::default().initial().to_array();
    std::array::from_fn(|i| (StepRates::NAMES[i], d[i]))
}

/// Run the `step` stage on `case`.
pub fn run(case: &TensorFile) -> Result<TensorFile> {
    let stage = case.meta("stage")?;
    if stage != STAGE {
        return Err(Error::field(
            &case.path,
            "__metadata__.stage",
            format!("{stage:?}, expected {STAGE:?}"),
        ));
    }
    match case.precision()? {
        Precision::F32 => run_t::<f32>(case),
        Precision::F64 => run_t::<f64>(case),
    }
}

/// A finite metadata number with a default, at least `min`.
fn meta_number(case: &TensorFile, key: &str, default: f64, min: f64) -> Result<f64> {
    let v: f64 = case.meta_or(key, default)?;
    if !v.is_finite() || v < min {
        return Err(Error::field(
            &case.path,
            format!("__metadata__.{key}"),
            format!("{v} (must be finite and ≥ {min})"),
        ));
    }
    Ok(v)
}

/// Every tensor name the stage reads besides the field weights.
fn known_tensors() -> Vec<String> {
    let mut k: Vec<String> = Group::ALL.iter().map(|g| g.name().to_string()).collect();
    k.extend(CAMERA_TENSORS.iter().map(|s| s.to_string()));
    k.extend(["bg", "gt", "stats.accum", "stats.denom", "stats.max_radii"].map(String::from));
    for g in state::adam_groups() {
        k.push(format!("adam.{g}.m"));
        k.push(format!("adam.{g}.v"));
    }
    k
}

fn run_t<T: Real>(case: &TensorFile) -> Result<TensorFile> {
    let field_config = crate::oracle::field::config_from_meta(case)?;
    let gaussians = state::read_gaussians::<T>(case, "")?;
    let n = gaussians.len();
    if n == 0 {
        return Err(Error::Tensor {
            context: case.path.display().to_string(),
            name: "xyz".into(),
            expected: "shape [N,3], N ≥ 1".into(),
            found: "shape [0, 3]".into(),
        });
    }
    let active_sh_degree: usize = case.meta_parse("active_sh_degree")?;
    if active_sh_degree > gaussians.max_sh_degree {
        return Err(Error::field(
            &case.path,
            "__metadata__.active_sh_degree",
            format!(
                "{active_sh_degree}, above the degree {} that `sh` holds",
                gaussians.max_sh_degree
            ),
        ));
    }
    let field_on: bool = case.meta_or("field_on", true)?;
    let time: f64 = case.meta_parse("time")?;
    if !time.is_finite() {
        return Err(Error::field(&case.path, "__metadata__.time", "not finite"));
    }
    let lambda = meta_number(case, "lambda_dssim", crate::loss::LAMBDA_DSSIM, 0.0)?;
    if lambda > 1.0 {
        return Err(Error::field(
            &case.path,
            "__metadata__.lambda_dssim",
            format!("{lambda} (must be in [0, 1])"),
        ));
    }
    let mut lr = [0.0; 7];
    for (slot, (name, default)) in lr.iter_mut().zip(default_learning_rates()) {
        *slot = meta_number(case, &format!("lr.{name}"), default, 0.0)?;
    }
    let rates = StepRates::from_array(lr);
    let camera = read_camera::<T>(case)?;
    let (h, w) = (camera.height, camera.width);
    if h == 0 || w == 0 {
        return Err(Error::field(
            &case.path,
            "__metadata__.image_height/image_width",
            format!("{h}x{w} (each side at least 1)"),
        ));
    }
    let bg = case.get_real::<T>("bg", &[3])?;
    let gt = case.get_real::<T>("gt", &[3, h, w])?;

    // Field weights: every tensor the stage does not otherwise read.
    let known = known_tensors();
    let mut weights = TensorFile::new(&case.path);
    for (name, t) in &case.tensors {
        if !known.contains(name) {
            weights.tensors.insert(name.clone(), t.clone());
        }
    }
    let field = crate::oracle::field::field_from_tensor_file::<T>(field_config, &weights)?;
    let mut optimizer =
        state::read_optimizer(case, "", &gaussians, field.param_count(), Source::Case)?;
    let mut stats: DensifyStats<T> = state::read_stats(case, "", n, Source::Case)?;
    let mut model = Model {
        gaussians,
        field,
        active_sh_degree,
        background: [bg[0].to_f64(), bg[1].to_f64(), bg[2].to_f64()],
    };
    model.validate()?;

    // The forward and backward, then statistics and Adam (upstream's order;
    // no densification here), exactly as training runs them.
    let view = View {
        name: "case".into(),
        camera,
        time,
        image: gt,
        width: w,
        height: h,
    };
    let (grads, _) = model.gradients(&view, time, field_on, lambda)?;
    stats.update(&grads.radii, &grads.model.means2d)?;
    optimizer.step(&mut model, &grads.model, &rates, StepGroups::All)?;

    let mut out = TensorFile::new(&case.path);
    out.set_meta("stage", STAGE);
    crate::oracle::field::config_to_meta(&field_config, &mut out);
    out.set_meta("active_sh_degree", active_sh_degree);
    out.set_meta("field_on", field_on);
    out.set_meta("time", format!("{time:?}"));
    out.set_meta("lambda_dssim", format!("{lambda:?}"));
    for (name, v) in StepRates::NAMES.iter().zip(rates.to_array()) {
        out.set_meta(&format!("lr.{name}"), format!("{v:?}"));
    }
    let l = &grads.loss;
    out.insert_real("loss", vec![], &[l.loss]);
    out.insert_real("l1", vec![], &[l.l1]);
    out.insert_real("ssim", vec![], &[l.ssim]);
    out.insert_real("image", vec![3, h, w], &grads.image);
    out.insert_i32("radii", vec![n], grads.radii.clone());
    out.insert_real("grad_means2d", vec![n, 3], &grads.model.means2d);
    state::write_gaussians(&mut out, "grad.", &grads.model.gaussians);
    state::write_gaussians(&mut out, "new.", &model.gaussians);
    for s in model.field.layout() {
        if let Some(fg) = &grads.model.field {
            out.insert_real(&format!("grad.{}", s.name), s.shape.clone(), &fg[s.range()]);
        }
        let p = &model.field.params()[s.range()];
        out.insert_real(&format!("new.{}", s.name), s.shape.clone(), p);
    }
    state::write_stats(&mut out, "", &stats)?;
    state::write_optimizer(&mut out, "new.", &optimizer, &model.gaussians);
    Ok(out)
}
