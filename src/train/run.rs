//! A whole training run: train, checkpoint, evaluate, write renders and
//! metrics. The CLI's `train` is a thin layer over [`run`].
//!
//! Output folder:
//! ```text
//! OUT/checkpoints/iteration_NNNNNN/   state, field weights, PLY, curve.json (see checkpoint)
//! OUT/test/renders/NAME.png           8-bit renders (torchvision save_image rounding)
//! OUT/test/renders_exr/NAME.exr       float renders
//! OUT/test/gt/NAME.png                ground truth, saved the same way
//! OUT/results.json, OUT/per_view.json test PSNR / SSIM, LPIPS with weights (upstream
//!                                     metrics.py layout)
//! ```

use super::checkpoint;
use super::config::TrainConfig;
use super::trainer::{StepReport, Trainer, View, ViewMetrics};
use crate::dataset::{Dataset, Frame};
use crate::error::{Error, Result};
use crate::gaussians::init::initial_gaussians;
use crate::gaussians::Gaussians;
use crate::io::{image, write_atomic};
use crate::math::Real;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// How a run is driven (not part of its result).
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// The output folder.
    pub out: PathBuf,
    /// Write a checkpoint every this many iterations (0: only at the end).
    pub checkpoint_every: u64,
    /// Evaluate the test views every this many iterations for the curve
    /// (0: only at the end).
    pub eval_every: u64,
    /// Continue from the newest checkpoint in `OUT/checkpoints` if there is
    /// one. Without it, a folder that holds checkpoints is refused (it is
    /// another run's, or this one's to be resumed).
    pub resume: bool,
    /// The data's name, recorded in checkpoints and used in messages.
    pub data_name: String,
    /// LPIPS for every evaluation (periodic and final) when given; without
    /// it LPIPS is absent from every record.
    pub lpips: Option<Arc<crate::lpips::Metric>>,
}

/// One point of the training curve.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CurvePoint {
    /// The iteration of this point.
    pub iteration: u64,
    /// Mean training loss over the iterations since the previous point.
    pub loss: f64,
    /// Mean test metrics when the test views were evaluated at this
    /// iteration (LPIPS only with weights).
    pub test_psnr: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Mean test SSIM at an evaluation.
    pub test_ssim: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    /// Mean test LPIPS at an evaluation with weights.
    pub test_lpips: Option<f64>,
    /// Number of Gaussians.
    pub gaussians: usize,
}

/// What the caller hears while a run goes on.
#[derive(Debug)]
pub enum Event<'a> {
    /// The run continues from a checkpoint.
    Resumed {
        /// The checkpoint's iteration.
        iteration: u64,
    },
    /// An iteration finished.
    Step(&'a StepReport),
    /// The test views were evaluated.
    Eval {
        /// The iteration evaluated.
        iteration: u64,
        /// Mean test PSNR.
        psnr: f64,
        /// Mean test SSIM.
        ssim: f64,
        /// Mean test LPIPS (with weights).
        lpips: Option<f64>,
    },
    /// A checkpoint was written into this folder.
    Checkpoint(&'a Path),
}

/// The result of a run.
#[derive(Clone, Debug, serde::Serialize)]
pub struct RunSummary {
    /// Completed iterations.
    pub iterations: u64,
    /// Final number of Gaussians.
    pub gaussians: usize,
    /// Mean test PSNR.
    pub psnr: f64,
    /// Mean test SSIM.
    pub ssim: f64,
    /// Mean test LPIPS, with [`RunOptions::lpips`] only.
    pub lpips: Option<f64>,
    /// Metrics of each test view.
    pub per_view: Vec<ViewMetrics>,
    /// [`Trainer::state_hash`] of the final state, hexadecimal.
    pub state_hash: String,
    /// Wall-clock seconds spent in training iterations in this process.
    pub train_seconds: f64,
    /// Iterations run in this process (fewer than `iterations` after a resume).
    pub iterations_run: u64,
    /// The training curve.
    pub curve: Vec<CurvePoint>,
}

/// Convert dataset frames to views in the run's precision.
pub fn views<T: Real>(frames: &[Frame]) -> Vec<View<T>> {
    frames
        .iter()
        .map(|f| View::new(&f.name, &f.camera, f.time, &f.image))
        .collect()
}

/// Mean LPIPS over views: `None` unless every view has one.
pub fn mean_lpips(per_view: &[ViewMetrics]) -> Option<f64> {
    let v: Option<Vec<f64>> = per_view.iter().map(|m| m.lpips).collect();
    v.filter(|v| !v.is_empty())
        .map(|v| v.iter().sum::<f64>() / v.len() as f64)
}

/// Mean PSNR and SSIM over views (0 views: an error).
pub fn mean_metrics(per_view: &[ViewMetrics]) -> Result<(f64, f64)> {
    if per_view.is_empty() {
        return Err(Error::invalid("evaluation", "no views to evaluate"));
    }
    let n = per_view.len() as f64;
    Ok((
        per_view.iter().map(|m| m.psnr).sum::<f64>() / n,
        per_view.iter().map(|m| m.ssim).sum::<f64>() / n,
    ))
}

/// A fresh run on `data`: its initial Gaussians (sized for the run's SH
/// degree), train views, scene extent and background.
pub fn new_trainer<T: Real>(config: &TrainConfig, data: &Dataset) -> Result<Trainer<T>> {
    let g = with_sh_degree(initial_gaussians::<T>(&data.init)?, config.max_sh_degree);
    let background = [if data.white_background { 1.0 } else { 0.0 }; 3];
    Trainer::new(
        config.clone(),
        g,
        data.train.len(),
        data.scene_extent,
        background,
    )
}

/// Train on `data` with `config`, writing into `opts.out`.
pub fn run<T: Real>(
    config: &TrainConfig,
    data: &Dataset,
    opts: &RunOptions,
    on_event: &mut dyn FnMut(Event),
) -> Result<RunSummary> {
    let train = views::<T>(&data.train);
    let test = views::<T>(eval_frames(data));
    if opts.lpips.is_some() {
        if let Some(v) = test.iter().find(|v| v.height < 16 || v.width < 16) {
            return Err(Error::invalid(
                "LPIPS",
                format!(
                    "test view {} is {}x{}: VGG16 needs at least 16x16 pixels",
                    v.name, v.width, v.height
                ),
            ));
        }
    }
    if test.is_empty() {
        return Err(Error::invalid(
            "evaluation split",
            "the dataset has no test or val views to evaluate (for a nerfies-layout folder, the split rule picked none)",
        ));
    }
    let ckpt_dir = opts.out.join("checkpoints");
    let existing = checkpoint::latest(&ckpt_dir)?;
    if let (false, Some(dir)) = (opts.resume, &existing) {
        return Err(Error::invalid(
            "output folder",
            format!(
                "{} holds a checkpoint of an earlier run ({}); continue it with --resume, or train into another folder",
                ckpt_dir.display(),
                dir.file_name().map_or(String::new(), |n| n.to_string_lossy().into_owned())
            ),
        ));
    }
    // Every output folder exists before the first iteration: a path that
    // cannot be written fails now, not after training.
    for sub in [
        ckpt_dir.clone(),
        opts.out.join("test").join("renders"),
        opts.out.join("test").join("renders_exr"),
        opts.out.join("test").join("gt"),
    ] {
        crate::io::create_dir_all(&sub)?;
    }
    let binding = checkpoint::DataBinding::of(data, &opts.data_name);

    let (mut trainer, mut curve) = match existing.filter(|_| opts.resume) {
        Some(dir) => {
            let t = checkpoint::load::<T>(&dir, config, &binding)?;
            if t.sampler().count() != train.len() {
                return Err(Error::invalid(
                    "resume",
                    format!(
                        "{} was trained on {} views, the dataset has {}",
                        dir.display(),
                        t.sampler().count(),
                        train.len()
                    ),
                ));
            }
            on_event(Event::Resumed {
                iteration: t.iteration(),
            });
            (t, read_curve(&dir)?)
        }
        None => (new_trainer(config, data)?, Vec::new()),
    };

    let start = trainer.iteration();
    let clock = Instant::now();
    let (mut loss_sum, mut loss_n) = (0.0, 0u64);
    let curve_every = (config.iterations / 100).max(1);
    while trainer.iteration() < config.iterations {
        let r = trainer.step(&train)?;
        on_event(Event::Step(&r));
        loss_sum += r.loss;
        loss_n += 1;
        let it = r.iteration;
        let last = it == config.iterations;
        let eval = last || (opts.eval_every > 0 && it % opts.eval_every == 0);
        if eval || it % curve_every == 0 {
            let (test_psnr, test_ssim, test_lpips) = if eval && !test.is_empty() {
                let per_view = trainer.evaluate_with(&test, opts.lpips.as_deref())?;
                let (psnr, ssim) = mean_metrics(&per_view)?;
                let lpips = mean_lpips(&per_view);
                on_event(Event::Eval {
                    iteration: it,
                    psnr,
                    ssim,
                    lpips,
                });
                (Some(psnr), Some(ssim), lpips)
            } else {
                (None, None, None)
            };
            curve.push(CurvePoint {
                iteration: it,
                loss: loss_sum / loss_n as f64,
                test_psnr,
                test_ssim,
                test_lpips,
                gaussians: r.gaussians,
            });
            (loss_sum, loss_n) = (0.0, 0);
        }
        if last || (opts.checkpoint_every > 0 && it % opts.checkpoint_every == 0) {
            let dir = checkpoint::save(
                &trainer,
                &ckpt_dir,
                &binding,
                &[(CURVE_FILE, &json_bytes(&dir_curve_path(&ckpt_dir), &curve)?)],
            )?;
            on_event(Event::Checkpoint(&dir));
        }
    }
    let train_seconds = clock.elapsed().as_secs_f64();

    let lpips = opts.lpips.as_deref();
    let per_view = render_views(&trainer, &test, &opts.out.join("test"), lpips)?;
    let (psnr, ssim) = mean_metrics(&per_view)?;
    write_metrics(&opts.out, &per_view, lpips.map(|m| m.info()).as_ref())?;
    Ok(RunSummary {
        iterations: trainer.iteration(),
        gaussians: trainer.model().gaussians.len(),
        psnr,
        ssim,
        lpips: mean_lpips(&per_view),
        per_view,
        state_hash: format!("{:016x}", trainer.state_hash()),
        train_seconds,
        iterations_run: trainer.iteration() - start,
        curve,
    })
}

/// The test split, or the val split when a dataset has no test frames.
pub fn eval_frames(data: &Dataset) -> &[Frame] {
    if data.test.is_empty() {
        &data.val
    } else {
        &data.test
    }
}

/// `g` with its SH array resized for degree `deg` (coefficients kept in
/// order, new ones zero).
fn with_sh_degree<T: Real>(mut g: Gaussians<T>, deg: usize) -> Gaussians<T> {
    let (n, old_k) = (g.len(), g.coeffs());
    g.max_sh_degree = deg;
    let k = g.coeffs();
    if k != old_k {
        let m = 3 * old_k.min(k);
        let mut sh = vec![T::ZERO; 3 * k * n];
        for i in 0..n {
            sh[3 * k * i..3 * k * i + m].copy_from_slice(&g.sh[3 * old_k * i..3 * old_k * i + m]);
        }
        g.sh = sh;
    }
    g
}

/// Render `views`, save renders (PNG, EXR) and ground truth (PNG) under
/// `dir`, and return the 8-bit metrics of each view (LPIPS with `lpips`).
pub fn render_views<T: Real>(
    trainer: &Trainer<T>,
    views: &[View<T>],
    dir: &Path,
    lpips: Option<&crate::lpips::Metric>,
) -> Result<Vec<ViewMetrics>> {
    for sub in ["renders", "renders_exr", "gt"] {
        crate::io::create_dir_all(&dir.join(sub))?;
    }
    let mut per_view = Vec::with_capacity(views.len());
    for v in views {
        let out = trainer.render(&v.camera, v.time)?;
        let name = file_stem(&v.name);
        image::write_png(
            &dir.join("renders").join(format!("{name}.png")),
            &out.color,
            v.height,
            v.width,
        )?;
        image::write_exr(
            &dir.join("renders_exr").join(format!("{name}.exr")),
            &out.color,
            v.height,
            v.width,
        )?;
        image::write_png(
            &dir.join("gt").join(format!("{name}.png")),
            &v.image,
            v.height,
            v.width,
        )?;
        per_view.push(super::trainer::view_metrics_with(
            &name, &out.color, &v.image, v.height, v.width, lpips,
        )?);
    }
    Ok(per_view)
}

/// Render `view`'s camera at each of `times` (any finite time, not only the
/// dataset's) into `dir` as `NAME.png` (8-bit, `save_image` rounding) and
/// `NAME.exr` (float), with `NAME = name(k, t)`. Returns the PNG paths.
pub fn render_times<T: Real>(
    trainer: &Trainer<T>,
    view: &View<T>,
    times: &[f64],
    dir: &Path,
    name: impl Fn(usize, f64) -> String,
) -> Result<Vec<PathBuf>> {
    crate::io::create_dir_all(dir)?;
    let mut out = Vec::with_capacity(times.len());
    for (k, &t) in times.iter().enumerate() {
        if !t.is_finite() {
            return Err(Error::invalid("render time", format!("{t} is not finite")));
        }
        // (Far outside the trained span the field can overflow; such a frame
        // would render as background.)
        let d = trainer.deformed(t)?;
        let parts = [&d.means, &d.scales, &d.rotations, &d.opacities];
        if let Some(v) = parts.iter().flat_map(|p| p.iter()).find(|v| !v.is_finite()) {
            return Err(Error::invalid(
                "render time",
                format!(
                    "{t}: the deformed Gaussians are not all finite (e.g. {}); the field \
                     overflows at this time",
                    v.to_f64()
                ),
            ));
        }
        let img = trainer.model().render_deformed(&d, &view.camera)?;
        let n = name(k, t);
        let png = dir.join(format!("{n}.png"));
        image::write_png(&png, &img.color, view.height, view.width)?;
        image::write_exr(
            &dir.join(format!("{n}.exr")),
            &img.color,
            view.height,
            view.width,
        )?;
        out.push(png);
    }
    Ok(out)
}

/// A frame name usable as a file name (`./test/r_000` → `r_000`).
pub fn file_stem(name: &str) -> String {
    let base = name.rsplit(['/', '\\']).next().unwrap_or(name);
    base.strip_suffix(".png").unwrap_or(base).to_string()
}

/// `results.json` (`{"psnr", "ssim", "views"}`) and `per_view.json`
/// (`{"psnr": {name: v}, "ssim": {name: v}}`), as upstream's metrics.py.
/// With LPIPS (every view has a value and `lpips` says how it was computed):
/// `"lpips"` in both, and `"lpips_info"` (convention, weight files and
/// their SHA-256) in `results.json`; without, no `lpips` key at all.
pub fn write_metrics(
    out: &Path,
    per_view: &[ViewMetrics],
    lpips: Option<&crate::lpips::MetricInfo>,
) -> Result<()> {
    let (psnr, ssim) = mean_metrics(per_view)?;
    let mut results = serde_json::json!({ "psnr": psnr, "ssim": ssim, "views": per_view.len() });
    let mut p = serde_json::Map::new();
    let mut s = serde_json::Map::new();
    let mut l = serde_json::Map::new();
    for m in per_view {
        p.insert(m.name.clone(), m.psnr.into());
        s.insert(m.name.clone(), m.ssim.into());
        if let Some(v) = m.lpips {
            l.insert(m.name.clone(), v.into());
        }
    }
    let mut views = serde_json::json!({ "psnr": p, "ssim": s });
    if let (Some(mean), Some(info)) = (mean_lpips(per_view), lpips) {
        results["lpips"] = mean.into();
        results["lpips_info"] =
            serde_json::to_value(info).map_err(|e| Error::invalid("lpips_info", e.to_string()))?;
        views["lpips"] = l.into();
    }
    // Both or neither: a folder in either's place is refused before the
    // first is written.
    let files = [
        (out.join("results.json"), results),
        (out.join("per_view.json"), views),
    ];
    if let Some((path, _)) = files.iter().find(|(p, _)| p.is_dir()) {
        return Err(Error::invalid(
            "output path",
            format!("{} is a folder", path.display()),
        ));
    }
    for (path, v) in &files {
        write_json(path, v)?;
    }
    Ok(())
}

/// Write `v` as pretty JSON to `path`, atomically.
pub fn write_json(path: &Path, v: &impl serde::Serialize) -> Result<()> {
    write_atomic(path, &json_bytes(path, v)?)
}

/// `v` as pretty JSON with a final newline (`path` names the file in errors).
fn json_bytes(path: &Path, v: &impl serde::Serialize) -> Result<Vec<u8>> {
    let mut bytes = serde_json::to_vec_pretty(v).map_err(|e| Error::format(path, e.to_string()))?;
    bytes.push(b'\n');
    Ok(bytes)
}

/// The training curve's file in a checkpoint folder.
pub const CURVE_FILE: &str = "curve.json";

fn dir_curve_path(ckpt_dir: &Path) -> PathBuf {
    ckpt_dir.join(CURVE_FILE)
}

/// The curve of a checkpoint folder: written with the checkpoint, so a
/// missing one is an error, not an empty curve.
fn read_curve(dir: &Path) -> Result<Vec<CurvePoint>> {
    let path = dir.join(CURVE_FILE);
    let bytes = crate::io::read(&path)?;
    serde_json::from_slice(&bytes).map_err(|e| Error::format(&path, e.to_string()))
}
