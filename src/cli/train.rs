//! `liquid-splat train`, `render`, `eval` and `export`: arguments, progress
//! output and messages around [`crate::experiment`].
//!
//! `train` records its arguments in `OUT/run.json` ([`RunSpec`]); `render OUT`,
//! `eval OUT` and `export OUT` read them back, so they need only the output
//! folder.

use crate::error::{Error, Outcome, Result};
use crate::experiment::{
    self, FieldChoice, FieldSpec, OpenedRun, PrecisionChoice, RunSpec, VariantChoice,
};
use crate::lpips;
use crate::math::Real;
use crate::train::{self, run::file_stem, Event, RunOptions, StageTimes, View, ViewMetrics};
use clap::Args;
use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::time::Instant;

/// The deformation field's architecture (defaults per kind: MLP D8 W256;
/// CfC D6 W128 GELU, backbone 2×64).
#[derive(Args, Clone, Debug)]
pub struct FieldArgs {
    /// Deformation field.
    #[arg(long, value_enum, default_value_t = FieldChoice::Cfc)]
    pub field: FieldChoice,
    /// MLP layers / CfC cells.
    #[arg(long)]
    pub depth: Option<usize>,
    /// MLP width / CfC hidden size.
    #[arg(long)]
    pub width: Option<usize>,
    /// CfC backbone activation: gelu, relu, silu, tanh, lecun_tanh (refused with `--field mlp`).
    #[arg(long)]
    pub activation: Option<String>,
    /// CfC backbone width (default 64; refused with `--field mlp`).
    #[arg(long)]
    pub backbone_units: Option<usize>,
    /// CfC backbone layers (default 2; refused with `--field mlp`).
    #[arg(long)]
    pub backbone_layers: Option<usize>,
    /// The MLP's 6-DoF (SE(3)) variant.
    #[arg(long = "6dof")]
    pub six_dof: bool,
    /// Time input: synthetic (D-NeRF timenet) or real (NeRF-DS); default from the dataset
    /// (real for the NeRF-DS/nerfies layout, synthetic otherwise; `count`: synthetic).
    #[arg(long, value_enum)]
    pub variant: Option<VariantChoice>,
}

impl FieldArgs {
    /// The library's description of the field.
    pub fn spec(&self) -> FieldSpec {
        FieldSpec {
            field: self.field,
            depth: self.depth,
            width: self.width,
            activation: self.activation.clone(),
            backbone_units: self.backbone_units,
            backbone_layers: self.backbone_layers,
            six_dof: self.six_dof,
            variant: self.variant,
        }
    }
}

/// LPIPS weight files and convention (`train`, `eval`, `experiment`).
#[derive(Args, Clone, Debug, Default)]
pub struct LpipsArgs {
    /// torchvision's VGG16 ImageNet weights, vgg16-397923af.pth (torchvision puts it in
    /// ~/.cache/torch/hub/checkpoints/). With --lpips-lin: report LPIPS (VGG, v0.1).
    #[arg(long, requires = "lpips_lin", value_name = "PTH")]
    pub lpips_vgg: Option<PathBuf>,
    /// The lpips package's weights/v0.1/vgg.pth (inside the installed package).
    #[arg(long, requires = "lpips_vgg", value_name = "PTH")]
    pub lpips_lin: Option<PathBuf>,
    /// LPIPS with normalize=True (\[0,1\] mapped to \[-1,1\] first). Default: as D-3DGS's
    /// metrics.py calls it, \[0,1\] images passed as they are.
    #[arg(long, requires = "lpips_vgg")]
    pub lpips_normalize: bool,
    /// Accept weight files other than the published ones (reported with their SHA-256).
    #[arg(long, requires = "lpips_vgg")]
    pub lpips_unverified: bool,
}

impl LpipsArgs {
    /// The metric, when weights were given.
    pub fn metric(&self) -> Result<Option<std::sync::Arc<lpips::Metric>>> {
        let (Some(vgg), Some(lin)) = (&self.lpips_vgg, &self.lpips_lin) else {
            return Ok(None);
        };
        let verify = if self.lpips_unverified {
            lpips::Verify::Any
        } else {
            lpips::Verify::Official
        };
        let convention = if self.lpips_normalize {
            lpips::Convention::Normalize
        } else {
            lpips::Convention::D3dgs
        };
        let m = lpips::Metric::load(vgg, lin, verify, convention)?;
        let info = m.info();
        for w in [&info.vgg, &info.lin] {
            if !w.official {
                eprintln!(
                    "warning: {} is not the published file (SHA-256 {}); LPIPS is reported with this hash",
                    w.path.display(),
                    w.sha256
                );
            }
        }
        eprintln!("{}", info.description);
        Ok(Some(std::sync::Arc::new(m)))
    }
}

/// The arguments that make up a [`RunSpec`] (`train`, `bench train`).
#[derive(Args, Clone, Debug)]
pub struct RunArgs {
    /// Dataset folder (D-NeRF or NeRF-DS/nerfies layout). Give this or --scene.
    #[arg(required_unless_present = "scene", conflicts_with = "scene")]
    pub data: Option<PathBuf>,
    /// Built-in synthetic scene generated in memory: bouncing, swing or blob.
    #[arg(long)]
    pub scene: Option<String>,
    /// Built-in scene: image width and height.
    #[arg(long, default_value_t = 64, conflicts_with = "data")]
    pub resolution: usize,
    /// Built-in scene: training frames.
    #[arg(long, default_value_t = 24, conflicts_with = "data")]
    pub frames: usize,
    /// Random initial points when the scene has no point cloud (upstream: 100,000;
    /// fewer keep CPU runs fast, densification adds more where needed).
    #[arg(long, default_value_t = super::DEFAULT_INIT_POINTS)]
    pub init_points: usize,
    /// Dataset folder: downscale factor 1, 2, 4 or 8.
    #[arg(long, default_value_t = 1, conflicts_with = "scene")]
    pub downscale: usize,
    /// Composite RGBA on white and train with a white background.
    #[arg(long)]
    pub white_background: bool,
    /// The deformation field.
    #[command(flatten)]
    pub field: FieldArgs,
    /// Training iterations; every schedule scales with this (see docs).
    #[arg(long, default_value_t = 2000)]
    pub iterations: u64,
    /// Seed of the run (camera order, field init, noise, splits).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Floating-point precision of the whole run.
    #[arg(long, value_enum, default_value_t = PrecisionChoice::F32)]
    pub precision: PrecisionChoice,
}

impl RunArgs {
    /// The library's description of the run.
    pub fn spec(&self) -> RunSpec {
        RunSpec {
            // (Absolute, so that render and export find it from any folder.)
            data: self
                .data
                .as_ref()
                .map(|d| std::path::absolute(d).unwrap_or_else(|_| d.clone())),
            scene: self.scene.clone(),
            resolution: self.resolution,
            frames: self.frames,
            init_points: self.init_points,
            downscale: self.downscale,
            white_background: self.white_background,
            field: self.field.spec(),
            iterations: self.iterations,
            seed: self.seed,
            precision: self.precision,
        }
    }
}

/// Arguments of `train`.
#[derive(Args)]
pub struct TrainArgs {
    /// The run.
    #[command(flatten)]
    pub run: RunArgs,
    /// Output folder (checkpoints, renders, metrics).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Continue from the newest checkpoint in OUT/checkpoints (with none there, start the run,
    /// and say so).
    #[arg(long)]
    pub resume: bool,
    /// Write a checkpoint every K iterations (0: only at the end).
    #[arg(long, default_value_t = 0)]
    pub checkpoint_every: u64,
    /// Evaluate the test views every K iterations (0: only at the end).
    #[arg(long, default_value_t = 0)]
    pub eval_every: u64,
    /// No progress output.
    #[arg(long, short)]
    pub quiet: bool,
    /// LPIPS weights for every evaluation.
    #[command(flatten)]
    pub lpips: LpipsArgs,
}

/// `train`: set up the run folder ([`experiment::prepare_run`]), train
/// with progress output, print the final metrics.
pub fn train(a: TrainArgs) -> Result<Outcome> {
    let spec = a.run.spec();
    let data = spec.load_dataset()?;
    for w in &data.warnings {
        eprintln!("warning: {w}");
    }
    let ckpt_dir = a.out.join("checkpoints");
    // (An unreadable folder is `prepare_run`'s to report.)
    let fresh = a.resume && matches!(train::checkpoint::latest(&ckpt_dir), Ok(None));
    let config = experiment::prepare_run(&spec, &data, &a.out, a.resume)?;
    if fresh {
        // (Even with --quiet: a mistyped OUT would otherwise pass unseen.)
        eprintln!(
            "note: no checkpoint in {}: --resume starts the run from its beginning",
            ckpt_dir.display()
        );
    }
    if !a.quiet {
        eprintln!(
            "training {} field ({} parameters) on {}: {} train / {} test views, {} initial Gaussians, {} iterations, {} threads",
            crate::report::field_label(&config.field),
            crate::deform::count::param_count(&config.field)?,
            spec.data_name(),
            data.train.len(),
            train::run::eval_frames(&data).len(),
            data.init.len(),
            config.iterations,
            rayon::current_num_threads(),
        );
    }
    let opts = RunOptions {
        out: a.out.clone(),
        checkpoint_every: a.checkpoint_every,
        eval_every: a.eval_every,
        resume: a.resume,
        data_name: spec.data_name(),
        lpips: a.lpips.metric()?,
    };
    let mut progress = Progress::new(config.iterations, a.quiet);
    let summary = experiment::train_run(&spec, &config, &data, &opts, &mut |e| progress.event(e))?;
    progress.finish();
    outln!(
        "test PSNR {:.3} dB  SSIM {:.4}  {}({} views, {} Gaussians, {} iterations, {:.1} ms/iteration)",
        summary.psnr,
        summary.ssim,
        lpips_text(summary.lpips),
        summary.per_view.len(),
        summary.gaussians,
        summary.iterations,
        1e3 * summary.train_seconds / summary.iterations_run.max(1) as f64,
    );
    outln!("state hash {}", summary.state_hash);
    outln!(
        "renders in {}, metrics in {}",
        a.out.join("test").display(),
        a.out.join("results.json").display()
    );
    Ok(Outcome::Success)
}

/// Progress: a one-line bar on a terminal, plain log lines otherwise,
/// each followed by the milliseconds per iteration of every stage since the
/// line before.
struct Progress {
    total: u64,
    quiet: bool,
    tty: bool,
    start: Instant,
    last_draw: Option<Instant>,
    loss_ema: Option<f64>,
    psnr_ema: Option<f64>,
    /// The stages' seconds, the steps and the time of the last log line
    /// (or of the start) since then.
    since: (StageTimes, u64, Instant),
}

impl Progress {
    fn new(total: u64, quiet: bool) -> Self {
        Progress {
            total,
            quiet,
            tty: std::io::stderr().is_terminal(),
            start: Instant::now(),
            last_draw: None,
            loss_ema: None,
            psnr_ema: None,
            since: (StageTimes::default(), 0, Instant::now()),
        }
    }

    /// The milliseconds per iteration of every stage since the last log
    /// line, and of the wall clock (which includes checkpoints and
    /// evaluations); starts the next interval.
    fn stage_line(&mut self) -> String {
        let (times, steps, lap) =
            std::mem::replace(&mut self.since, (StageTimes::default(), 0, Instant::now()));
        let per = |sec: f64| 1e3 * sec / steps.max(1) as f64;
        let stages: Vec<String> = StageTimes::NAMES
            .iter()
            .zip(times.values())
            .map(|(name, sec)| format!("{name} {:.2}", per(sec)))
            .collect();
        format!(
            "  ms/iteration over the last {steps}: {}; all stages {:.2}, wall {:.2}",
            stages.join(", "),
            per(times.values().iter().sum()),
            per(lap.elapsed().as_secs_f64())
        )
    }

    fn event(&mut self, e: Event) {
        if self.quiet {
            return;
        }
        match e {
            Event::Resumed { iteration } => {
                eprintln!("resumed from iteration {iteration}");
                self.since = (StageTimes::default(), 0, Instant::now());
            }
            Event::Step(r) => {
                self.since.0.add(&r.times);
                self.since.1 += 1;
                let ema = |old: Option<f64>, v: f64| Some(old.map_or(v, |o| 0.6 * v + 0.4 * o));
                self.loss_ema = ema(self.loss_ema, r.loss);
                if r.psnr.is_finite() {
                    self.psnr_ema = ema(self.psnr_ema, r.psnr);
                }
                let line = format!(
                    "iteration {:>6}/{}  loss {:.5}  psnr {:.2}  gaussians {}",
                    r.iteration,
                    self.total,
                    self.loss_ema.unwrap_or(0.0),
                    self.psnr_ema.unwrap_or(0.0),
                    r.gaussians
                );
                if self.tty {
                    let due = self
                        .last_draw
                        .is_none_or(|t| t.elapsed().as_millis() >= 100);
                    if due || r.iteration == self.total {
                        let frac = r.iteration as f64 / self.total as f64;
                        let filled = (frac * 30.0) as usize;
                        eprint!(
                            "\r[{}{}] {}  {:.0}s ",
                            "#".repeat(filled),
                            ".".repeat(30 - filled),
                            line,
                            self.start.elapsed().as_secs_f64()
                        );
                        let _ = std::io::stderr().flush();
                        self.last_draw = Some(Instant::now());
                    }
                } else if r.iteration % (self.total / 20).max(1) == 0 || r.iteration == self.total {
                    eprintln!("{line}  {:.1}s", self.start.elapsed().as_secs_f64());
                    eprintln!("{}", self.stage_line());
                }
            }
            Event::Eval {
                iteration,
                psnr,
                ssim,
                lpips,
            } => {
                self.clear();
                eprintln!(
                    "[eval] iteration {iteration}: test PSNR {psnr:.3} dB, SSIM {ssim:.4} {}",
                    lpips_text(lpips)
                );
            }
            Event::Checkpoint(p) => {
                self.clear();
                eprintln!("checkpoint {}", p.display());
            }
        }
    }

    fn clear(&mut self) {
        if self.tty && self.last_draw.is_some() {
            eprintln!();
            self.last_draw = None;
        }
    }

    fn finish(&mut self) {
        if !self.quiet {
            self.clear();
        }
    }
}

/// The most frames of `render`'s time sweep.
pub const MAX_SWEEP_FRAMES: usize = 100_000;

/// Arguments of `render`.
#[derive(Args)]
pub struct RenderArgs {
    /// Output folder of a `train` run.
    pub out: PathBuf,
    /// Frames of the time sweep (0: no sweep; at most 100000).
    #[arg(long, default_value_t = 30)]
    pub sweep_frames: usize,
    /// Test view (index) the time sweep and --times are rendered from [default: 0]; refused
    /// with neither.
    #[arg(long)]
    pub sweep_view: Option<usize>,
    /// Also render these times (comma-separated, finite, |t| at most 1e9; the dataset's span
    /// is 0..1) into OUT/times/VIEW_tT.png and .exr (T with 6 decimals; files of earlier
    /// calls at other times stay). Prints the names written.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub times: Vec<f64>,
}

/// `render OUT`: test views to `OUT/test/`, a time sweep to `OUT/sweep/`,
/// `--times` to `OUT/times/`.
pub fn render(a: RenderArgs) -> Result<Outcome> {
    match RunSpec::read(&a.out)?.precision {
        PrecisionChoice::F32 => render_as::<f32>(&a),
        PrecisionChoice::F64 => render_as::<f64>(&a),
    }
}

fn render_as<T: Real>(a: &RenderArgs) -> Result<Outcome> {
    let OpenedRun {
        data,
        checkpoint: ckpt,
        trainer,
        ..
    } = experiment::open_run::<T>(&a.out)?;
    let test: Vec<View<T>> = train::run::views(train::run::eval_frames(&data));
    // The options before any rendering: a bad one fails at once.
    if a.sweep_frames > MAX_SWEEP_FRAMES {
        return Err(Error::invalid(
            "--sweep-frames",
            format!("{} (at most {MAX_SWEEP_FRAMES})", a.sweep_frames),
        ));
    }
    let sweep_index = a.sweep_view.unwrap_or(0);
    let sweep_view = if a.sweep_frames == 0 && a.times.is_empty() {
        if a.sweep_view.is_some() {
            return Err(Error::invalid(
                "--sweep-view",
                "given without a time sweep (--sweep-frames 0) or --times, which it applies to",
            ));
        }
        None
    } else {
        Some(test.get(sweep_index).ok_or_else(|| {
            Error::invalid(
                "--sweep-view",
                format!("{sweep_index} (there are {} test views)", test.len()),
            )
        })?)
    };
    // The stem of `--times`' files: `r_000_t0.250000`.
    let time_stem = |stem: &str, t: f64| format!("{stem}_t{}", train::export::time_label(t));
    if let Some(v) = sweep_view {
        let stem = file_stem(&v.name);
        check_times(&a.times, |t| format!("{}.png", time_stem(&stem, t)))?;
    }
    let per_view = train::run::render_views(&trainer, &test, &a.out.join("test"), None)?;
    eprintln!(
        "rendered {} test views from {} into {}",
        per_view.len(),
        ckpt.display(),
        a.out.join("test").display()
    );
    let Some(v) = sweep_view else {
        return Ok(Outcome::Success);
    };
    if a.sweep_frames > 0 {
        let dir = a.out.join("sweep");
        let times: Vec<f64> = (0..a.sweep_frames)
            .map(|k| {
                if a.sweep_frames == 1 {
                    0.0
                } else {
                    k as f64 / (a.sweep_frames - 1) as f64
                }
            })
            .collect();
        train::run::render_times(&trainer, v, &times, &dir, |k, _| format!("{k:04}"))?;
        // Frames of an earlier, longer sweep would follow these ones.
        for k in a.sweep_frames.. {
            let stale = [
                dir.join(format!("{k:04}.png")),
                dir.join(format!("{k:04}.exr")),
            ];
            if !stale.iter().any(|p| p.is_file()) {
                break;
            }
            for p in stale.iter().filter(|p| p.is_file()) {
                std::fs::remove_file(p).map_err(|e| Error::io(p, e))?;
            }
        }
        eprintln!(
            "time sweep of test view {} ({}): {} frames, t = {}, in {}",
            sweep_index,
            file_stem(&v.name),
            a.sweep_frames,
            if a.sweep_frames == 1 { "0" } else { "0..1" },
            dir.display()
        );
    }
    if !a.times.is_empty() {
        let dir = a.out.join("times");
        let stem = file_stem(&v.name);
        let files =
            train::run::render_times(&trainer, v, &a.times, &dir, |_, t| time_stem(&stem, t))?;
        for f in files {
            outln!("{}", f.display());
        }
    }
    Ok(Outcome::Success)
}

/// Arguments of `export`.
#[derive(Args)]
pub struct ExportArgs {
    /// Output folder of a `train` run.
    pub out: PathBuf,
    /// Times to export (comma-separated, finite, |t| at most 1e9; the dataset's span is 0..1).
    #[arg(
        long,
        value_delimiter = ',',
        required = true,
        allow_hyphen_values = true
    )]
    pub times: Vec<f64>,
    /// Folder for the PLY files (default OUT/export).
    #[arg(long)]
    pub dir: Option<PathBuf>,
}

/// The largest `|t|` of `--times`.
pub const MAX_TIME: f64 = 1e9;

/// Checks `--times` before anything is rendered or written: finite, within
/// ±[`MAX_TIME`], and no two giving the same file name (`name`).
fn check_times(times: &[f64], name: impl Fn(f64) -> String) -> Result<()> {
    if let Some(t) = times.iter().find(|t| !t.is_finite() || t.abs() > MAX_TIME) {
        return Err(Error::invalid(
            "--times",
            format!(
                "{} (finite, at most {MAX_TIME:e} in magnitude)",
                crate::error::shown(*t)
            ),
        ));
    }
    let mut names: Vec<String> = times.iter().map(|&t| name(t)).collect();
    names.sort();
    if let Some(w) = names.windows(2).find(|w| w[0] == w[1]) {
        return Err(Error::invalid(
            "--times",
            format!("two times give the same file name {} (6 decimals)", w[0]),
        ));
    }
    Ok(())
}

/// `export OUT --times ...`: the deformed Gaussians at each time as an Inria PLY.
pub fn export(a: ExportArgs) -> Result<Outcome> {
    match RunSpec::read(&a.out)?.precision {
        PrecisionChoice::F32 => export_as::<f32>(&a),
        PrecisionChoice::F64 => export_as::<f64>(&a),
    }
}

fn export_as<T: Real>(a: &ExportArgs) -> Result<Outcome> {
    let OpenedRun {
        checkpoint: ckpt,
        trainer,
        ..
    } = experiment::open_run::<T>(&a.out)?;
    check_times(&a.times, train::export::file_name)?;
    let dir = a.dir.clone().unwrap_or_else(|| a.out.join("export"));
    let reports = train::export::export_times(&trainer, &a.times, &dir)?;
    eprintln!(
        "deformed Gaussians of {} ({} each):",
        ckpt.display(),
        trainer.model().gaussians.len()
    );
    for r in &reports {
        outln!("{}", r.path.display());
        if r.nonpositive_scales + r.flat > 0 {
            eprintln!(
                "  t = {}: {} Gaussians with a deformed scale <= 0 (written from their covariance), {} flat (scale {:e})",
                r.time,
                r.nonpositive_scales,
                r.flat,
                train::export::MIN_SCALE
            );
        }
    }
    Ok(Outcome::Success)
}

/// Arguments of `eval`.
#[derive(Args)]
pub struct EvalArgs {
    /// Output folder holding test/renders and test/gt (PNG).
    pub out: PathBuf,
    /// LPIPS weights.
    #[command(flatten)]
    pub lpips: LpipsArgs,
}

/// `eval OUT`: PSNR, SSIM (and LPIPS with weights) of `OUT/test/renders/*.png`
/// against `OUT/test/gt/*.png` (8-bit images, as upstream's metrics.py),
/// written to `OUT/results.json` and `OUT/per_view.json`.
pub fn eval(a: EvalArgs) -> Result<Outcome> {
    let metric = a.lpips.metric()?;
    let per_view = experiment::evaluate_renders(&a.out, metric.as_deref())?;
    print_metrics(&per_view)?;
    Ok(Outcome::Success)
}

fn print_metrics(per_view: &[ViewMetrics]) -> Result<()> {
    for m in per_view {
        outln!(
            "{:<24} PSNR {:>8.3}  SSIM {:.4}  {}",
            m.name,
            m.psnr,
            m.ssim,
            lpips_text(m.lpips)
        );
    }
    let (p, s) = train::run::mean_metrics(per_view)?;
    let l = train::run::mean_lpips(per_view);
    outln!(
        "{:<24} PSNR {:>8.3}  SSIM {:.4}  {}",
        "mean",
        p,
        s,
        lpips_text(l)
    );
    if l.is_none() {
        outln!("LPIPS not computed (no weights: --lpips-vgg and --lpips-lin)");
    }
    Ok(())
}

/// `LPIPS 0.1234 ` or nothing: absent, never a placeholder number.
fn lpips_text(v: Option<f64>) -> String {
    v.map_or(String::new(), |v| format!("LPIPS {v:.4} "))
}
