//! [`RunSpec`]: everything that determines a training run's result, saved
//! as `OUT/run.json` by `train` and read back by `render`, `eval` and
//! `export`; and the rules for starting, resuming and reopening a run folder.

use crate::dataset::{self, synth, Background, Dataset, DatasetKind, LoadOptions};
use crate::deform::{Activation, CfcConfig, FieldConfig, MlpConfig, Variant};
use crate::error::{Error, Result};
use crate::math::Real;
use crate::train::{self, checkpoint, TrainConfig, Trainer};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The deformation field's kind, as `run.json` and `--field` name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FieldChoice {
    /// The liquid field: a stack of CfC cells.
    Cfc,
    /// The D-3DGS MLP field.
    Mlp,
}

/// The field's time input, as `run.json` and `--variant` name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VariantChoice {
    /// D-NeRF's time network (synthetic scenes).
    Synthetic,
    /// NeRF-DS's plain time encoding (real captures).
    Real,
}

/// The floating-point precision of a whole run, as `run.json` and
/// `--precision` name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PrecisionChoice {
    /// Every tensor in f32.
    F32,
    /// Every tensor in f64.
    F64,
}

/// The deformation field's architecture; `None` takes the kind's default
/// (MLP D8 W256; CfC D6 W128 GELU, backbone 2×64).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FieldSpec {
    /// The field's kind.
    pub field: FieldChoice,
    /// MLP layers / CfC cells.
    pub depth: Option<usize>,
    /// MLP width / CfC hidden size.
    pub width: Option<usize>,
    /// CfC backbone activation by name: gelu, relu, silu, tanh, lecun_tanh
    /// (an error for the MLP field, as are the backbone options).
    pub activation: Option<String>,
    /// CfC backbone width.
    pub backbone_units: Option<usize>,
    /// CfC backbone layers.
    pub backbone_layers: Option<usize>,
    /// The MLP's 6-DoF (SE(3)) variant.
    #[serde(default)]
    pub six_dof: bool,
    /// Time input; `None` takes the dataset's (real for nerfies-layout
    /// folders, synthetic otherwise).
    pub variant: Option<VariantChoice>,
}

impl FieldSpec {
    /// The kind's default architecture with `depth` and `width` set (and,
    /// for the CfC field, the backbone activation `activation`).
    pub fn sized(field: FieldChoice, depth: usize, width: usize, activation: &str) -> Self {
        FieldSpec {
            field,
            depth: Some(depth),
            width: Some(width),
            activation: (field == FieldChoice::Cfc).then(|| activation.to_string()),
            backbone_units: None,
            backbone_layers: None,
            six_dof: false,
            variant: None,
        }
    }

    /// The field configuration, with `default_variant` when no variant is
    /// given; an error names the first unusable setting (a CfC-only option
    /// for the MLP field, the 6-DoF variant for the CfC field included).
    pub fn config(&self, default_variant: Variant) -> Result<FieldConfig> {
        let variant = match self.variant {
            Some(VariantChoice::Synthetic) => Variant::Synthetic,
            Some(VariantChoice::Real) => Variant::Real,
            None => default_variant,
        };
        let c = match self.field {
            FieldChoice::Mlp => {
                // The CfC-only options have no meaning for the MLP: refuse
                // them rather than ignore them.
                let cfc_only = [
                    ("activation", self.activation.clone()),
                    ("backbone_units", self.backbone_units.map(|u| u.to_string())),
                    (
                        "backbone_layers",
                        self.backbone_layers.map(|l| l.to_string()),
                    ),
                ];
                if let Some((key, Some(v))) = cfc_only.into_iter().find(|(_, v)| v.is_some()) {
                    return Err(Error::invalid(
                        key,
                        format!("{v} (only the CfC field has this option; the MLP field is ReLU without a backbone)"),
                    ));
                }
                let d = MlpConfig::paper();
                FieldConfig::Mlp(MlpConfig {
                    variant,
                    depth: self.depth.unwrap_or(d.depth),
                    width: self.width.unwrap_or(d.width),
                    is_6dof: self.six_dof,
                })
            }
            FieldChoice::Cfc => {
                if self.six_dof {
                    return Err(Error::invalid(
                        "is_6dof",
                        "only the MLP field has a 6-DoF variant",
                    ));
                }
                let d = CfcConfig::paper();
                FieldConfig::Cfc(CfcConfig {
                    variant,
                    depth: self.depth.unwrap_or(d.depth),
                    width: self.width.unwrap_or(d.width),
                    activation: match &self.activation {
                        Some(a) => Activation::parse(a)?,
                        None => d.activation,
                    },
                    backbone_units: self.backbone_units.unwrap_or(d.backbone_units),
                    backbone_layers: self.backbone_layers.unwrap_or(d.backbone_layers),
                })
            }
        };
        c.validate()?;
        Ok(c)
    }
}

/// Where the frames come from and how a run is set up: everything that
/// determines its result. Saved as `OUT/run.json` (the field's settings
/// flattened into the top-level object).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunSpec {
    /// Dataset folder (D-NeRF or NeRF-DS/nerfies layout); this or `scene`.
    pub data: Option<PathBuf>,
    /// Built-in synthetic scene generated in memory: bouncing, swing or blob.
    pub scene: Option<String>,
    /// Built-in scene: image width and height in pixels.
    pub resolution: usize,
    /// Built-in scene: training frames.
    pub frames: usize,
    /// Random initial points when the scene has no point cloud.
    pub init_points: usize,
    /// Dataset folder: downscale factor 1, 2, 4 or 8.
    pub downscale: usize,
    /// Composite RGBA on white and train with a white background.
    pub white_background: bool,
    /// The deformation field.
    #[serde(flatten)]
    pub field: FieldSpec,
    /// Training iterations; every schedule scales with this.
    pub iterations: u64,
    /// Seed of the run (camera order, field init, noise, splits).
    pub seed: u64,
    /// Floating-point precision of the whole run.
    pub precision: PrecisionChoice,
}

/// The name of a run folder's description file.
pub const RUN_FILE: &str = "run.json";

impl RunSpec {
    /// Load the frames: the dataset folder, or the built-in scene.
    pub fn load_dataset(&self) -> Result<Dataset> {
        let background = if self.white_background {
            Background::White
        } else {
            Background::Black
        };
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

    /// The training configuration for `data` (its kind picks the field's
    /// default time input).
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

    /// The description saved in run folder `out` ([`RUN_FILE`]).
    pub fn read(out: &Path) -> Result<RunSpec> {
        let path = out.join(RUN_FILE);
        let bytes = crate::io::read(&path)?;
        let spec: RunSpec =
            serde_json::from_slice(&bytes).map_err(|e| Error::format(&path, e.to_string()))?;
        // (`train` records exactly one of the two.)
        match (&spec.data, &spec.scene) {
            (Some(_), None) | (None, Some(_)) => Ok(spec),
            (d, _) => Err(Error::field(
                &path,
                if d.is_some() { "data, scene" } else { "data" },
                format!(
                    "{}: a run names its dataset folder (`data`) or its built-in scene \
                     (`scene`), exactly one",
                    if d.is_some() {
                        "both are set"
                    } else {
                        "neither is set"
                    }
                ),
            )),
        }
    }

    /// Save this description in run folder `out` ([`RUN_FILE`]).
    pub fn write(&self, out: &Path) -> Result<()> {
        train::run::write_json(&out.join(RUN_FILE), self)
    }
}

/// The arguments in which `given` differs from `recorded`, each as
/// `key: recorded X, given Y`. Dataset folders are the same when they are
/// the same folder (however the path was written).
fn spec_differences(recorded: &RunSpec, given: &RunSpec) -> Vec<String> {
    let same_folder = match (&recorded.data, &given.data) {
        (Some(a), Some(b)) => {
            a == b
                || std::fs::canonicalize(a)
                    .is_ok_and(|a| std::fs::canonicalize(b).is_ok_and(|b| a == b))
        }
        (a, b) => a == b,
    };
    let (Ok(serde_json::Value::Object(r)), Ok(serde_json::Value::Object(g))) =
        (serde_json::to_value(recorded), serde_json::to_value(given))
    else {
        return vec!["unreadable".into()];
    };
    r.iter()
        .filter(|(k, v)| g.get(*k) != Some(*v) && !(*k == "data" && same_folder))
        .map(|(k, v)| {
            let now = g.get(k).map_or("none".to_string(), |v| v.to_string());
            format!("{k}: recorded {v}, given {now}")
        })
        .collect()
}

/// Set up run folder `out` to train `spec` on `data` (loaded with
/// [`RunSpec::load_dataset`]): check the data, apply the resume rule, save
/// `spec` as `out/run.json`, and return the training configuration.
///
/// The resume rule: a folder holding a checkpoint is refused unless
/// `resume` is set (it is an earlier run's), and a run is resumed only with
/// the description it was started with. Nothing is written when refused.
pub fn prepare_run(
    spec: &RunSpec,
    data: &Dataset,
    out: &Path,
    resume: bool,
) -> Result<TrainConfig> {
    let config = spec.train_config(data)?;
    // (Refused before anything is written into `out`.)
    config.validate()?;
    spec.check_eval_split(data)?;
    crate::io::create_dir_all(out)?;
    let spec_path = out.join(RUN_FILE);
    let ckpt_dir = out.join("checkpoints");
    if let (false, Some(dir)) = (resume, checkpoint::latest(&ckpt_dir)?) {
        return Err(Error::invalid(
            "--out",
            format!(
                "{} holds a checkpoint of an earlier run ({}); continue it with --resume, or train into another folder (nothing was written)",
                ckpt_dir.display(),
                dir.display()
            ),
        ));
    }
    if resume && spec_path.exists() {
        let old = RunSpec::read(out)?;
        let differs = spec_differences(&old, spec);
        if !differs.is_empty() {
            return Err(Error::invalid(
                "--resume",
                format!(
                    "{} records other run arguments ({}); resume with the same ones",
                    spec_path.display(),
                    differs.join("; ")
                ),
            ));
        }
    }
    spec.write(out)?;
    Ok(config)
}

/// Train the run [`prepare_run`] set up, in the precision of `spec`,
/// calling `on_event` as it goes (see [`train::run`](fn@crate::train::run)).
pub fn train_run(
    spec: &RunSpec,
    config: &TrainConfig,
    data: &Dataset,
    opts: &train::RunOptions,
    on_event: &mut dyn FnMut(train::Event),
) -> Result<train::RunSummary> {
    match spec.precision {
        PrecisionChoice::F32 => train::run::<f32>(config, data, opts, on_event),
        PrecisionChoice::F64 => train::run::<f64>(config, data, opts, on_event),
    }
}

/// A finished run folder reopened: its description, data, newest
/// checkpoint and the model loaded from it.
pub struct OpenedRun<T: Real> {
    /// The run's description (`run.json`).
    pub spec: RunSpec,
    /// The frames, loaded as the run loaded them.
    pub data: Dataset,
    /// The checkpoint the model was loaded from.
    pub checkpoint: PathBuf,
    /// The trained state.
    pub trainer: Trainer<T>,
}

/// Reopen run folder `out` at its newest checkpoint, in precision `T` (the
/// caller picks `T` from [`RunSpec::precision`]).
pub fn open_run<T: Real>(out: &Path) -> Result<OpenedRun<T>> {
    let spec = RunSpec::read(out)?;
    let data = spec.load_dataset().map_err(|e| match &spec.data {
        Some(d) if !d.is_dir() => Error::format(
            out.join(RUN_FILE),
            format!(
                "the run's dataset folder {} is not found ({e})",
                d.display()
            ),
        ),
        _ => e,
    })?;
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
                    out.join(RUN_FILE).display()
                ),
            }
        }
        e => e,
    })?;
    Ok(OpenedRun {
        spec,
        data,
        checkpoint: ckpt,
        trainer,
    })
}

/// Score the saved renders of run folder `out`: PSNR, SSIM (and LPIPS with
/// `metric`) of each `out/test/renders/*.png` against `out/test/gt/` (8-bit
/// images, as upstream's metrics.py), in file-name order, written to
/// `out/results.json` and `out/per_view.json`.
pub fn evaluate_renders(
    out: &Path,
    metric: Option<&crate::lpips::Metric>,
) -> Result<Vec<train::ViewMetrics>> {
    let renders = out.join("test").join("renders");
    let gt_dir = out.join("test").join("gt");
    // The PNG files of `dir`, sorted.
    let pngs = |dir: &Path| -> Result<Vec<String>> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .filter_map(|e| e.ok())
            .map(|e| e.file_name().to_string_lossy().to_string())
            .filter(|n| n.ends_with(".png"))
            .collect();
        v.sort();
        Ok(v)
    };
    let names = pngs(&renders)?;
    if names.is_empty() {
        return Err(Error::invalid(
            "eval",
            format!("no PNG renders in {}", renders.display()),
        ));
    }
    // A view with ground truth but no render would leave the mean over
    // fewer views than the test split without a word.
    let gts = pngs(&gt_dir)?;
    if let Some(n) = gts.iter().find(|n| !names.contains(n)) {
        return Err(Error::invalid(
            "eval",
            format!(
                "{} has no render {}",
                gt_dir.join(n).display(),
                renders.join(n).display()
            ),
        ));
    }
    // And a render with no ground truth is not scored against nothing.
    if let Some(n) = names.iter().find(|n| !gts.contains(n)) {
        return Err(Error::invalid(
            "eval",
            format!(
                "{} has no ground truth {}",
                renders.join(n).display(),
                gt_dir.join(n).display()
            ),
        ));
    }
    let mut per_view = Vec::new();
    for n in &names {
        let (r, h, w) = read_rgb(&renders.join(n))?;
        let (g, gh, gw) = read_rgb(&gt_dir.join(n))?;
        if (h, w) != (gh, gw) {
            return Err(Error::invalid(
                "eval",
                format!(
                    "{} is {w}x{h}, its ground truth {} {gw}x{gh}",
                    renders.join(n).display(),
                    gt_dir.join(n).display()
                ),
            ));
        }
        let m = train::trainer::view_metrics_with::<f32>(
            n.trim_end_matches(".png"),
            &r,
            &g,
            h,
            w,
            metric,
        )?;
        per_view.push(m);
    }
    let info = metric.map(|m| m.info());
    train::run::write_metrics(out, &per_view, info.as_ref())?;
    Ok(per_view)
}

/// A PNG as `[3, H, W]` values `u8 / 255`.
fn read_rgb(path: &Path) -> Result<(Vec<f32>, usize, usize)> {
    let img = crate::io::png::read(path)?;
    let (w, h) = (img.width, img.height);
    Ok((dataset::image::to_chw(&img.rgb(), w, h), h, w))
}
