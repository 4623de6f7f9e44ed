//! `liquid-splat train`, `render` and `eval`.
//!
//! `train` records its arguments in `OUT/run.json`; `render OUT` and
//! `eval OUT` read them back, so they need only the output folder.

use crate::dataset::{self, synth, Dataset, DatasetKind, LoadOptions};
use crate::deform::{Activation, FieldConfig, FieldKind, Variant};
use crate::error::{Error, Result};
use crate::lpips;
use crate::math::Real;
use crate::train::{
    self, checkpoint, run::file_stem, Event, RunOptions, TrainConfig, View, ViewMetrics,
};
use clap::{Args, ValueEnum};
use serde::{Deserialize, Serialize};
use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FieldArg {
    Cfc,
    Mlp,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VariantArg {
    Synthetic,
    Real,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PrecisionArg {
    F32,
    F64,
}

/// The deformation field's architecture (defaults per kind: MLP D8 W256;
/// CfC D6 W128 GELU, backbone 2×64).
#[derive(Args, Clone, Debug, Serialize, Deserialize)]
pub struct FieldArgs {
    /// Deformation field.
    #[arg(long, value_enum, default_value_t = FieldArg::Cfc)]
    pub field: FieldArg,
    /// MLP layers / CfC cells.
    #[arg(long)]
    pub depth: Option<usize>,
    /// MLP width / CfC hidden size.
    #[arg(long)]
    pub width: Option<usize>,
    /// CfC backbone activation: gelu, relu, silu, tanh, lecun_tanh.
    #[arg(long)]
    pub activation: Option<String>,
    /// CfC backbone width (default 64).
    #[arg(long)]
    pub backbone_units: Option<usize>,
    /// CfC backbone layers (default 2).
    #[arg(long)]
    pub backbone_layers: Option<usize>,
    /// The MLP's 6-DoF (SE(3)) variant.
    #[arg(long = "6dof")]
    #[serde(default)]
    pub six_dof: bool,
    /// Time input: synthetic (D-NeRF timenet) or real (NeRF-DS); default from the dataset.
    #[arg(long, value_enum)]
    pub variant: Option<VariantArg>,
}

impl FieldArgs {
    pub fn config(&self, default_variant: Variant) -> Result<FieldConfig> {
        let mut c = FieldConfig::new(match self.field {
            FieldArg::Cfc => FieldKind::Cfc,
            FieldArg::Mlp => FieldKind::Mlp,
        });
        c.variant = match self.variant {
            Some(VariantArg::Synthetic) => Variant::Synthetic,
            Some(VariantArg::Real) => Variant::Real,
            None => default_variant,
        };
        if let Some(d) = self.depth {
            c.depth = d;
        }
        if let Some(w) = self.width {
            c.width = w;
        }
        if let Some(a) = &self.activation {
            c.activation = Activation::parse(a)?;
        }
        if let Some(u) = self.backbone_units {
            c.backbone_units = u;
        }
        if let Some(l) = self.backbone_layers {
            c.backbone_layers = l;
        }
        c.is_6dof = self.six_dof;
        c.validate()?;
        Ok(c)
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
    /// LPIPS with normalize=True ([0,1] mapped to [-1,1] first). Default: as D-3DGS's
    /// metrics.py calls it, [0,1] images passed as they are.
    #[arg(long)]
    pub lpips_normalize: bool,
    /// Accept weight files other than the published ones (reported with their SHA-256).
    #[arg(long)]
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

/// Where the frames come from and how a run is set up: everything that
/// determines its result. Saved as `OUT/run.json`.
#[derive(Args, Clone, Debug, Serialize, Deserialize)]
pub struct RunSpec {
    /// Dataset folder (D-NeRF or NeRF-DS/nerfies layout). Give this or --scene.
    #[arg(required_unless_present = "scene", conflicts_with = "scene")]
    pub data: Option<PathBuf>,
    /// Built-in synthetic scene generated in memory: bouncing, swing or blob.
    #[arg(long)]
    pub scene: Option<String>,
    /// Built-in scene: image width and height.
    #[arg(long, default_value_t = 64)]
    pub resolution: usize,
    /// Built-in scene: training frames.
    #[arg(long, default_value_t = 24)]
    pub frames: usize,
    /// Random initial points when the scene has no point cloud (upstream: 100,000;
    /// fewer keep CPU runs fast, densification adds more where needed).
    #[arg(long, default_value_t = 2000)]
    pub init_points: usize,
    /// Dataset folder: downscale factor 1, 2, 4 or 8.
    #[arg(long, default_value_t = 1)]
    pub downscale: usize,
    /// Composite RGBA on white and train with a white background.
    #[arg(long)]
    pub white_background: bool,
    #[command(flatten)]
    #[serde(flatten)]
    pub field: FieldArgs,
    /// Training iterations; every schedule scales with this (see docs).
    #[arg(long, default_value_t = 2000)]
    pub iterations: u64,
    /// Seed of the run (camera order, field init, noise, splits).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Floating-point precision of the whole run.
    #[arg(long, value_enum, default_value_t = PrecisionArg::F32)]
    pub precision: PrecisionArg,
}

impl RunSpec {
    pub fn load_dataset(&self) -> Result<Dataset> {
        let background = super::data::background(self.white_background);
        match (&self.data, &self.scene) {
            (Some(dir), _) => dataset::load(
                dir,
                &LoadOptions {
                    background,
                    downscale: self.downscale,
                    init_points: self.init_points,
                    ..Default::default()
                },
            ),
            (None, Some(name)) => synth::builtin(
                name,
                &synth::SynthOptions {
                    resolution: self.resolution,
                    frames: self.frames,
                    background,
                    init_points: self.init_points,
                    ..Default::default()
                },
            ),
            (None, None) => Err(Error::invalid(
                "dataset",
                "give a dataset folder or --scene NAME",
            )),
        }
    }

    pub fn train_config(&self, data: &Dataset) -> Result<TrainConfig> {
        let variant = match data.kind {
            DatasetKind::Nerfies => Variant::Real,
            DatasetKind::DNerf | DatasetKind::Synthetic => Variant::Synthetic,
        };
        Ok(TrainConfig::new(
            self.iterations,
            self.seed,
            self.field.config(variant)?,
        ))
    }

    /// Refuse data with no views to evaluate before any work is done
    /// (a nerfies-layout folder whose split rule picks no test views).
    pub fn check_eval_split(&self, data: &Dataset) -> Result<()> {
        if !train::run::eval_frames(data).is_empty() {
            return Ok(());
        }
        match (&self.data, data.kind) {
            (Some(dir), DatasetKind::Nerfies) => Err(Error::field(
                dir.join("dataset.json"),
                "ids",
                "the split rule for this folder (its parent folder's name is not vrig*, NeRF* or interp*: every fourth id trains, none is a test view) picks no test views, so nothing could be evaluated",
            )),
            (Some(dir), _) => Err(Error::format(dir, "no test or val views to evaluate")),
            (None, _) => Err(Error::invalid(
                "--scene",
                "no test views to evaluate",
            )),
        }
    }

    /// A short name of the data for messages.
    pub fn data_name(&self) -> String {
        match (&self.data, &self.scene) {
            (Some(d), _) => d.display().to_string(),
            (None, Some(s)) => format!("built-in scene {s} ({0}x{0})", self.resolution),
            _ => String::new(),
        }
    }
}

#[derive(Args)]
pub struct TrainArgs {
    #[command(flatten)]
    pub spec: RunSpec,
    /// Output folder (checkpoints, renders, metrics).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Continue from the newest checkpoint in OUT/checkpoints.
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
    #[command(flatten)]
    pub lpips: LpipsArgs,
}

fn mkdir(p: &Path) -> Result<()> {
    std::fs::create_dir_all(p).map_err(|e| Error::io(p, e))
}

pub fn train(a: TrainArgs) -> Result<ExitCode> {
    let data = a.spec.load_dataset()?;
    for w in &data.warnings {
        eprintln!("warning: {w}");
    }
    let config = a.spec.train_config(&data)?;
    a.spec.check_eval_split(&data)?;
    mkdir(&a.out)?;
    let spec_path = a.out.join("run.json");
    let ckpt_dir = a.out.join("checkpoints");
    if let (false, Some(dir)) = (a.resume, checkpoint::latest(&ckpt_dir)?) {
        return Err(Error::invalid(
            "--out",
            format!(
                "{} holds a checkpoint of an earlier run ({}); continue it with --resume, or train into another folder (nothing was written)",
                ckpt_dir.display(),
                dir.display()
            ),
        ));
    }
    if a.resume && spec_path.exists() {
        let old = read_spec(&a.out)?;
        if serde_json::to_value(&old).ok() != serde_json::to_value(&a.spec).ok() {
            return Err(Error::invalid(
                "--resume",
                format!(
                    "{} records different run arguments; resume with the same ones",
                    spec_path.display()
                ),
            ));
        }
    }
    train::run::write_json(&spec_path, &a.spec)?;
    if !a.quiet {
        eprintln!(
            "training {} field ({} parameters) on {}: {} train / {} test views, {} initial Gaussians, {} iterations, {} threads",
            crate::report::field_label(&config.field),
            crate::deform::count::param_count(&config.field)?,
            a.spec.data_name(),
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
        data_name: a.spec.data_name(),
        lpips: a.lpips.metric()?,
    };
    let mut progress = Progress::new(config.iterations, a.quiet);
    let summary = match a.spec.precision {
        PrecisionArg::F32 => train::run::<f32>(&config, &data, &opts, &mut |e| progress.event(e))?,
        PrecisionArg::F64 => train::run::<f64>(&config, &data, &opts, &mut |e| progress.event(e))?,
    };
    progress.finish();
    println!(
        "test PSNR {:.3} dB  SSIM {:.4}  {}({} views, {} Gaussians, {} iterations, {:.1} ms/iteration)",
        summary.psnr,
        summary.ssim,
        lpips_text(summary.lpips),
        summary.per_view.len(),
        summary.gaussians,
        summary.iterations,
        1e3 * summary.train_seconds / summary.iterations_run.max(1) as f64,
    );
    println!("state hash {}", summary.state_hash);
    println!(
        "renders in {}, metrics in {}",
        a.out.join("test").display(),
        a.out.join("results.json").display()
    );
    Ok(ExitCode::SUCCESS)
}

/// Progress: a one-line bar on a terminal, plain log lines otherwise.
struct Progress {
    total: u64,
    quiet: bool,
    tty: bool,
    start: Instant,
    last_draw: Option<Instant>,
    loss_ema: Option<f64>,
    psnr_ema: Option<f64>,
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
        }
    }

    fn event(&mut self, e: Event) {
        if self.quiet {
            return;
        }
        match e {
            Event::Resumed { iteration } => eprintln!("resumed from iteration {iteration}"),
            Event::Step(r) => {
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

fn read_spec(out: &Path) -> Result<RunSpec> {
    let path = out.join("run.json");
    let bytes = crate::io::read(&path)?;
    serde_json::from_slice(&bytes).map_err(|e| Error::format(&path, e.to_string()))
}

#[derive(Args)]
pub struct RenderArgs {
    /// Output folder of a `train` run.
    pub out: PathBuf,
    /// Frames of the time sweep (0: no sweep).
    #[arg(long, default_value_t = 30)]
    pub sweep_frames: usize,
    /// Test view (index) the time sweep and --times are rendered from.
    #[arg(long, default_value_t = 0)]
    pub sweep_view: usize,
    /// Also render these times (comma-separated, any finite value; the dataset's span
    /// is 0..1) into OUT/times/.
    #[arg(long, value_delimiter = ',', allow_hyphen_values = true)]
    pub times: Vec<f64>,
}

/// The newest checkpoint of a `train` run folder, loaded, with its dataset.
fn load_run<T: Real>(out: &Path) -> Result<(RunSpec, Dataset, PathBuf, train::Trainer<T>)> {
    let spec = read_spec(out)?;
    let data = spec.load_dataset()?;
    let config = spec.train_config(&data)?;
    let ckpt_dir = out.join("checkpoints");
    let ckpt = checkpoint::latest(&ckpt_dir)?.ok_or_else(|| {
        Error::invalid(
            "run folder",
            format!("no checkpoint in {}", ckpt_dir.display()),
        )
    })?;
    let binding = checkpoint::DataBinding::of(&data, &spec.data_name());
    let trainer = checkpoint::load::<T>(&ckpt, &config, &binding).map_err(|e| match e {
        Error::Field { path, field, what }
            if field.starts_with("__metadata__.data") || field == "__metadata__.background" =>
        {
            Error::Field {
                path,
                field,
                what: format!(
                    "{what}; {} records the arguments the data was loaded with",
                    out.join("run.json").display()
                ),
            }
        }
        e => e,
    })?;
    Ok((spec, data, ckpt, trainer))
}

/// `render OUT`: test views to `OUT/test/`, a time sweep to `OUT/sweep/`,
/// `--times` to `OUT/times/`.
pub fn render(a: RenderArgs) -> Result<ExitCode> {
    let spec = read_spec(&a.out)?;
    match spec.precision {
        PrecisionArg::F32 => render_as::<f32>(&a),
        PrecisionArg::F64 => render_as::<f64>(&a),
    }
}

fn render_as<T: Real>(a: &RenderArgs) -> Result<ExitCode> {
    let (_, data, ckpt, trainer) = load_run::<T>(&a.out)?;
    let test: Vec<View<T>> = train::run::views(train::run::eval_frames(&data));
    // The sweep view before any rendering: a bad index fails at once.
    let sweep_view = if a.sweep_frames == 0 && a.times.is_empty() {
        None
    } else {
        Some(test.get(a.sweep_view).ok_or_else(|| {
            Error::invalid(
                "--sweep-view",
                format!("{} (there are {} test views)", a.sweep_view, test.len()),
            )
        })?)
    };
    let per_view = train::run::render_views(&trainer, &test, &a.out.join("test"), None)?;
    eprintln!(
        "rendered {} test views from {} into {}",
        per_view.len(),
        ckpt.display(),
        a.out.join("test").display()
    );
    let Some(v) = sweep_view else {
        return Ok(ExitCode::SUCCESS);
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
        eprintln!(
            "time sweep of test view {} ({}): {} frames, t = 0..1, in {}",
            a.sweep_view,
            file_stem(&v.name),
            a.sweep_frames,
            dir.display()
        );
    }
    if !a.times.is_empty() {
        let dir = a.out.join("times");
        let stem = file_stem(&v.name);
        let files = train::run::render_times(&trainer, v, &a.times, &dir, |_, t| {
            format!("{stem}_t{t:.6}")
        })?;
        for f in files {
            println!("{}", f.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

#[derive(Args)]
pub struct ExportArgs {
    /// Output folder of a `train` run.
    pub out: PathBuf,
    /// Times to export (comma-separated, any finite value; the dataset's span is 0..1).
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

/// `export OUT --times ...`: the deformed Gaussians at each time as an Inria PLY.
pub fn export(a: ExportArgs) -> Result<ExitCode> {
    match read_spec(&a.out)?.precision {
        PrecisionArg::F32 => export_as::<f32>(&a),
        PrecisionArg::F64 => export_as::<f64>(&a),
    }
}

fn export_as<T: Real>(a: &ExportArgs) -> Result<ExitCode> {
    let (_, _, ckpt, trainer) = load_run::<T>(&a.out)?;
    let dir = a.dir.clone().unwrap_or_else(|| a.out.join("export"));
    let reports = train::export::export_times(&trainer, &a.times, &dir)?;
    eprintln!(
        "deformed Gaussians of {} ({} each):",
        ckpt.display(),
        trainer.model().gaussians.len()
    );
    for r in &reports {
        println!("{}", r.path.display());
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
    Ok(ExitCode::SUCCESS)
}

#[derive(Args)]
pub struct EvalArgs {
    /// Output folder holding test/renders and test/gt (PNG).
    pub out: PathBuf,
    #[command(flatten)]
    pub lpips: LpipsArgs,
}

/// `eval OUT`: PSNR, SSIM (and LPIPS with weights) of `OUT/test/renders/*.png`
/// against `OUT/test/gt/*.png` (8-bit images, as upstream's metrics.py),
/// written to `OUT/results.json` and `OUT/per_view.json`.
pub fn eval(a: EvalArgs) -> Result<ExitCode> {
    let metric = a.lpips.metric()?;
    let renders = a.out.join("test").join("renders");
    let gt_dir = a.out.join("test").join("gt");
    let mut names: Vec<String> = std::fs::read_dir(&renders)
        .map_err(|e| Error::io(&renders, e))?
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().to_string())
        .filter(|n| n.ends_with(".png"))
        .collect();
    names.sort();
    if names.is_empty() {
        return Err(Error::invalid(
            "eval",
            format!("no PNG renders in {}", renders.display()),
        ));
    }
    let mut per_view = Vec::new();
    for n in &names {
        let (r, h, w) = read_rgb(&renders.join(n))?;
        let (g, gh, gw) = read_rgb(&gt_dir.join(n))?;
        if (h, w) != (gh, gw) {
            return Err(Error::invalid(
                "eval",
                format!("{n}: render is {w}x{h}, ground truth {gw}x{gh}"),
            ));
        }
        let m = train::trainer::view_metrics_with::<f32>(
            n.trim_end_matches(".png"),
            &r,
            &g,
            h,
            w,
            metric.as_deref(),
        )?;
        per_view.push(m);
    }
    let info = metric.as_ref().map(|m| m.info());
    train::run::write_metrics(&a.out, &per_view, info.as_ref())?;
    print_metrics(&per_view)?;
    Ok(ExitCode::SUCCESS)
}

/// A PNG as `[3, H, W]` values `u8 / 255`.
fn read_rgb(path: &Path) -> Result<(Vec<f32>, usize, usize)> {
    let img = dataset::image::read_png(path)?;
    let (w, h) = (img.width, img.height);
    Ok((dataset::image::to_chw(&img.rgb(), w, h), h, w))
}

fn print_metrics(per_view: &[ViewMetrics]) -> Result<()> {
    for m in per_view {
        println!(
            "{:<24} PSNR {:>8.3}  SSIM {:.4}  {}",
            m.name,
            m.psnr,
            m.ssim,
            lpips_text(m.lpips)
        );
    }
    let (p, s) = train::run::mean_metrics(per_view)?;
    let l = train::run::mean_lpips(per_view);
    println!(
        "{:<24} PSNR {:>8.3}  SSIM {:.4}  {}",
        "mean",
        p,
        s,
        lpips_text(l)
    );
    if l.is_none() {
        println!("LPIPS not computed (no weights: --lpips-vgg and --lpips-lin)");
    }
    Ok(())
}

/// `LPIPS 0.1234 ` or nothing: absent, never a placeholder number.
fn lpips_text(v: Option<f64>) -> String {
    v.map_or(String::new(), |v| format!("LPIPS {v:.4} "))
}
