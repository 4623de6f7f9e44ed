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
//! The computation is [`Trainer::gradients`] followed by
//! [`DensifyStats::update`], [`GaussianOptimizer::step`] and
//! [`AdamState::step`]: the code the training loop runs.
//!
//! Tensor names, shapes and conventions are in `docs/ORACLE.md`.

use super::rasterize::{read_camera, CAMERA_TENSORS};
use crate::densify::DensifyStats;
use crate::error::{Error, Result};
use crate::gaussians::Gaussians;
use crate::io::TensorFile;
use crate::math::{Precision, Real};
use crate::optim::{AdamState, GaussianOptimizer, GroupLrs, LearningRates, StepGroups};
use crate::train::{TrainConfig, Trainer, View};

/// The `stage` metadata value of a step case.
pub const STAGE: &str = "step";

/// The Adam groups, in the order of the case's `adam.<group>.*` entries.
/// `sh` holds upstream's `f_dc` and `f_rest` (one state, two rates).
pub const ADAM_GROUPS: [&str; 6] = ["xyz", "sh", "opacity", "scaling", "rotation", "field"];

/// The learning-rate metadata keys (`lr.<name>`) and their defaults:
/// upstream's initial rates ([`LearningRates::default`]).
pub fn default_learning_rates() -> [(&'static str, f64); 7] {
    let d = LearningRates::default();
    [
        ("xyz", d.xyz_init),
        ("f_dc", d.f_dc),
        ("f_rest", d.f_rest),
        ("opacity", d.opacity),
        ("scaling", d.scaling),
        ("rotation", d.rotation),
        ("field", d.deform_init),
    ]
}

/// The canonical Gaussian tensors: name and row width (`sh` is `[N,K,3]`).
const GAUSSIAN_TENSORS: [(&str, usize); 5] = [
    ("xyz", 3),
    ("sh", 3),
    ("scaling", 3),
    ("rotation", 4),
    ("opacity", 1),
];

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

fn shape_error(case: &TensorFile, name: &str, expected: String, found: &[usize]) -> Error {
    Error::Tensor {
        context: case.path.display().to_string(),
        name: name.into(),
        expected,
        found: format!("shape {found:?}"),
    }
}

/// The canonical Gaussians of the case (`opacity` `[N,1]` read into `[N]`).
fn read_gaussians<T: Real>(case: &TensorFile) -> Result<Gaussians<T>> {
    let (shape, xyz) = case.get_real_any::<T>("xyz")?;
    if shape.len() != 2 || shape[1] != 3 || shape[0] == 0 {
        return Err(shape_error(
            case,
            "xyz",
            "shape [N,3], N ≥ 1".into(),
            &shape,
        ));
    }
    let n = shape[0];
    let (shape, sh) = case.get_real_any::<T>("sh")?;
    let degree = match shape.as_slice() {
        [m, k, 3] if *m == n => (0..=3).find(|&d| Gaussians::<T>::coeffs_for_degree(d) == *k),
        _ => None,
    };
    let max_sh_degree = degree.ok_or_else(|| {
        shape_error(
            case,
            "sh",
            format!("shape [{n},K,3], K = 1, 4, 9 or 16"),
            &shape,
        )
    })?;
    let g = Gaussians {
        max_sh_degree,
        xyz,
        sh,
        scaling: case.get_real::<T>("scaling", &[n, 3])?,
        rotation: case.get_real::<T>("rotation", &[n, 4])?,
        opacity: case.get_real::<T>("opacity", &[n, 1])?,
    };
    g.validate()?;
    Ok(g)
}

/// Case shape of a Gaussian group's tensor.
fn group_shape(g: &Gaussians<impl Real>, group: &str) -> Vec<usize> {
    let n = g.len();
    match group {
        "xyz" | "scaling" => vec![n, 3],
        "sh" => vec![n, g.coeffs(), 3],
        "rotation" => vec![n, 4],
        _ => vec![n, 1],
    }
}

/// Adam state of one group: `adam.<group>.m`/`.v` (both or neither; zeros
/// if neither) of `shape`, `adam.<group>.step` (default 0).
fn read_adam<T: Real>(case: &TensorFile, group: &str, shape: &[usize]) -> Result<AdamState<T>> {
    let len = shape.iter().product();
    let mut state = AdamState::new(len);
    let (m, v) = (format!("adam.{group}.m"), format!("adam.{group}.v"));
    match (case.contains(&m), case.contains(&v)) {
        (false, false) => {}
        (true, true) => {
            state.m = case.get_real::<T>(&m, shape)?;
            state.v = case.get_real::<T>(&v, shape)?;
            if let Some(i) = state.v.iter().position(|x| x.is_nan() || *x < T::ZERO) {
                return Err(Error::Tensor {
                    context: case.path.display().to_string(),
                    name: v,
                    expected: "second moments ≥ 0".into(),
                    found: format!("{} at flat index {i}", state.v[i].to_f64()),
                });
            }
        }
        (has_m, _) => {
            let (given, missing) = if has_m { (m, v) } else { (v, m) };
            return Err(Error::MissingTensor {
                context: format!("{} (`{given}` is given)", case.path.display()),
                name: missing,
            });
        }
    }
    let key = format!("adam.{group}.step");
    state.step = case.meta_or(&key, 0u64)?;
    if state.step == u64::MAX {
        return Err(Error::field(
            &case.path,
            format!("__metadata__.{key}"),
            format!("{} (the step counter cannot advance)", state.step),
        ));
    }
    Ok(state)
}

/// Incoming densification statistics (zeros for absent tensors).
fn read_stats<T: Real>(case: &TensorFile, n: usize) -> Result<DensifyStats<T>> {
    let mut stats = DensifyStats::new(n);
    if case.contains("stats.accum") {
        stats.accum = case.get_real::<T>("stats.accum", &[n])?;
    }
    let counts = |name: &str| -> Result<Option<Vec<i32>>> {
        if !case.contains(name) {
            return Ok(None);
        }
        let (shape, v) = case.get_i32(name)?;
        if shape != [n] {
            return Err(shape_error(case, name, format!("shape [{n}]"), &shape));
        }
        if let Some(i) = v.iter().position(|&x| x < 0) {
            return Err(Error::Tensor {
                context: case.path.display().to_string(),
                name: name.into(),
                expected: "values ≥ 0".into(),
                found: format!("{} at index {i}", v[i]),
            });
        }
        Ok(Some(v))
    };
    if let Some(d) = counts("stats.denom")? {
        stats.denom = d.into_iter().map(|x| x as u32).collect();
    }
    if let Some(r) = counts("stats.max_radii")? {
        stats.max_radii = r;
    }
    Ok(stats)
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
    let mut k: Vec<String> = GAUSSIAN_TENSORS
        .iter()
        .map(|(n, _)| n.to_string())
        .collect();
    k.extend(CAMERA_TENSORS.iter().map(|s| s.to_string()));
    k.extend(["bg", "gt", "stats.accum", "stats.denom", "stats.max_radii"].map(String::from));
    for g in ADAM_GROUPS {
        k.push(format!("adam.{g}.m"));
        k.push(format!("adam.{g}.v"));
    }
    k
}

fn run_t<T: Real>(case: &TensorFile) -> Result<TensorFile> {
    let field_config = crate::oracle::field::config_from_meta(case)?;
    let gaussians = read_gaussians::<T>(case)?;
    let n = gaussians.len();
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

    let mut optimizer = GaussianOptimizer::new(&gaussians);
    for (group, state) in [
        ("xyz", &mut optimizer.xyz),
        ("sh", &mut optimizer.sh),
        ("opacity", &mut optimizer.opacity),
        ("scaling", &mut optimizer.scaling),
        ("rotation", &mut optimizer.rotation),
    ] {
        *state = read_adam(case, group, &group_shape(&gaussians, group))?;
    }
    let field_state = read_adam::<T>(case, "field", &[field.param_count()])?;
    let stats = read_stats::<T>(case, n)?;

    // The trainer runs the forward and backward exactly as training does.
    let mut config = TrainConfig::new(1, 0, field_config);
    config.lambda_dssim = lambda;
    config.max_sh_degree = gaussians.max_sh_degree;
    let background = [bg[0].to_f64(), bg[1].to_f64(), bg[2].to_f64()];
    let mut trainer = Trainer::new(config, gaussians, 1, 1.0, background)?;
    trainer.field = field;
    trainer.active_sh_degree = active_sh_degree;
    trainer.optimizer = optimizer;
    trainer.field_optimizer = field_state;
    trainer.stats = stats;
    let view = View {
        name: "case".into(),
        camera,
        time,
        image: gt,
        width: w,
        height: h,
    };
    let (grads, _) = trainer.gradients(&view, time, field_on)?;

    // Statistics, then Adam (upstream's order; no densification here).
    trainer.stats.update(&grads.radii, &grads.grad_means2d)?;
    let lrs = GroupLrs {
        xyz: lr[0],
        f_dc: lr[1],
        f_rest: lr[2],
        opacity: lr[3],
        scaling: lr[4],
        rotation: lr[5],
    };
    trainer.optimizer.step(
        &mut trainer.gaussians,
        &grads.gaussians,
        &lrs,
        StepGroups::All,
    )?;
    if let Some(fg) = &grads.field {
        trainer
            .field_optimizer
            .step(trainer.field.params_mut(), fg, lr[6])?;
    }

    let mut out = TensorFile::new(&case.path);
    out.set_meta("stage", STAGE);
    crate::oracle::field::config_to_meta(&field_config, &mut out);
    out.set_meta("active_sh_degree", active_sh_degree);
    out.set_meta("field_on", field_on);
    out.set_meta("time", format!("{time:?}"));
    out.set_meta("lambda_dssim", format!("{lambda:?}"));
    for ((name, _), v) in default_learning_rates().iter().zip(lr) {
        out.set_meta(&format!("lr.{name}"), format!("{v:?}"));
    }
    let l = &grads.loss;
    out.insert_real("loss", vec![], &[l.loss]);
    out.insert_real("l1", vec![], &[l.l1]);
    out.insert_real("ssim", vec![], &[l.ssim]);
    out.insert_real("image", vec![3, h, w], &grads.image);
    out.insert_i32("radii", vec![n], grads.radii.clone());
    out.insert_real("grad_means2d", vec![n, 3], &grads.grad_means2d);
    let new = &trainer.gaussians;
    for (name, _) in GAUSSIAN_TENSORS {
        let shape = group_shape(new, name);
        let (g, p) = match name {
            "xyz" => (&grads.gaussians.xyz, &new.xyz),
            "sh" => (&grads.gaussians.sh, &new.sh),
            "scaling" => (&grads.gaussians.scaling, &new.scaling),
            "rotation" => (&grads.gaussians.rotation, &new.rotation),
            _ => (&grads.gaussians.opacity, &new.opacity),
        };
        out.insert_real(&format!("grad.{name}"), shape.clone(), g);
        out.insert_real(&format!("new.{name}"), shape, p);
    }
    for s in trainer.field.layout() {
        if let Some(fg) = &grads.field {
            out.insert_real(&format!("grad.{}", s.name), s.shape.clone(), &fg[s.range()]);
        }
        let p = &trainer.field.params()[s.range()];
        out.insert_real(&format!("new.{}", s.name), s.shape.clone(), p);
    }
    let st = &trainer.stats;
    out.insert_real("stats.accum", vec![n], &st.accum);
    out.insert_i32(
        "stats.denom",
        vec![n],
        st.denom.iter().map(|&d| d as i32).collect(),
    );
    out.insert_i32("stats.max_radii", vec![n], st.max_radii.clone());
    let o = &trainer.optimizer;
    let param_count = trainer.field.param_count();
    for (group, state) in [
        ("xyz", &o.xyz),
        ("sh", &o.sh),
        ("opacity", &o.opacity),
        ("scaling", &o.scaling),
        ("rotation", &o.rotation),
        ("field", &trainer.field_optimizer),
    ] {
        let shape = if group == "field" {
            vec![param_count]
        } else {
            group_shape(new, group)
        };
        out.insert_real(&format!("new.adam.{group}.m"), shape.clone(), &state.m);
        out.insert_real(&format!("new.adam.{group}.v"), shape, &state.v);
        out.set_meta(&format!("new.adam.{group}.step"), state.step);
    }
    Ok(out)
}
