//! Experiment reports: one JSON record per training run, and a report folder
//! (Markdown, CSV, PNG plots) built from whichever records exist.
//!
//! Layout of a report folder:
//! ```text
//! runs/<scene>__<field>__seed<S>.json   one RunRecord per finished run (resume key)
//! report.md                             every table and plot, with seeds, settings, machine
//! runs.csv, curves.csv                  the records, flat
//! table_<name>.csv                      each table at full precision
//! plots/<scene>-loss.png, -psnr.png     curves against iteration, one line per field
//! meta.json                             the ReportMeta the report was written with
//! ```
//! A run is resumable per configuration: [`record_path`] exists once it has
//! finished, and [`write_report`] can be called again after each run.

pub mod plot;
pub mod smooth;
pub mod tables;

pub use smooth::{temporal_smoothness, uniform_times};
pub use tables::AblationBase;

use crate::deform::{Activation, FieldConfig, FieldKind, Variant};
use crate::error::{Error, Result};
use crate::io::write_atomic;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use tables::{
    by_field, csv_line, field_order, BEST_LPIPS, BEST_PSNR, BEST_SSIM, LPIPS, MS_PER_ITER, PSNR,
    SMOOTHNESS, SSIM,
};

/// One logged point of a training curve.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CurvePoint {
    /// The training iteration (from 1).
    pub iteration: usize,
    /// Training loss at this iteration (as logged by the trainer).
    pub loss: f64,
    /// Test-set PSNR (dB) when it was evaluated at this iteration.
    pub test_psnr: Option<f64>,
    /// Test-set SSIM and LPIPS of the same evaluation (LPIPS only with weights).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_ssim: Option<f64>,
    /// Test-set LPIPS of the same evaluation, with LPIPS weights only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_lpips: Option<f64>,
}

/// The best value of one metric over a run's periodic test evaluations, and
/// the iteration it was evaluated at (the first such iteration on ties).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BestValue {
    /// The metric's best value.
    pub value: f64,
    /// The iteration it was evaluated at.
    pub iteration: usize,
}

/// Best of the periodic test evaluations (highest PSNR and SSIM, lowest
/// LPIPS, each metric on its own): how D-3DGS's published numbers were
/// chosen (its author: the best test metrics of evaluations every 1,000
/// iterations), as opposed to the final model's metrics.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct BestOfEvaluations {
    /// Number of evaluations the best was chosen from (the last iteration included).
    pub evaluations: usize,
    /// Highest test PSNR (dB).
    pub psnr: BestValue,
    /// Highest test SSIM, when evaluated.
    pub ssim: Option<BestValue>,
    /// Lowest test LPIPS, when evaluated (with weights only).
    pub lpips: Option<BestValue>,
}

/// [`BestOfEvaluations`] of a curve; `None` when no point has a test PSNR.
pub fn best_of_evaluations(curve: &[CurvePoint]) -> Option<BestOfEvaluations> {
    fn best(
        curve: &[CurvePoint],
        get: impl Fn(&CurvePoint) -> Option<f64>,
        higher: bool,
    ) -> Option<BestValue> {
        let mut b: Option<BestValue> = None;
        for p in curve {
            if let Some(v) = get(p) {
                let better = match b {
                    None => true,
                    Some(o) => (higher && v > o.value) || (!higher && v < o.value),
                };
                if better {
                    b = Some(BestValue {
                        value: v,
                        iteration: p.iteration,
                    });
                }
            }
        }
        b
    }
    Some(BestOfEvaluations {
        evaluations: curve.iter().filter(|p| p.test_psnr.is_some()).count(),
        psnr: best(curve, |p| p.test_psnr, true)?,
        ssim: best(curve, |p| p.test_ssim, true),
        lpips: best(curve, |p| p.test_lpips, false),
    })
}

/// Everything measured in one training run (one scene, field, seed).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    /// The scene's name (built-in scene or dataset folder name).
    pub scene: String,
    /// Field label, `<kind>-d<depth>-w<width>-<activation>` (see [`field_label`]).
    pub field: String,
    /// `mlp` or `cfc`.
    pub kind: String,
    /// `synthetic` (timenet time input) or `real`.
    pub variant: String,
    /// MLP layers / CfC cells.
    pub depth: usize,
    /// MLP width / CfC hidden size.
    pub width: usize,
    /// The CfC backbone's activation by name (the MLP's: `relu`).
    pub activation: String,
    /// The run's seed.
    pub seed: u64,
    /// Training iterations.
    pub iterations: usize,
    /// Training image size `[width, height]` in pixels.
    pub resolution: [usize; 2],
    /// Worker threads the run used.
    pub threads: usize,
    /// Trainable parameters of the field.
    pub params: usize,
    /// MACs per Gaussian, ptflops aten convention (linear layers only).
    pub macs_per_gaussian: u64,
    /// Gaussians after the last iteration.
    pub final_gaussians: usize,
    /// Test PSNR (dB) of the final model (after the last iteration).
    pub test_psnr: f64,
    /// Test SSIM of the final model.
    pub test_ssim: f64,
    /// Final test LPIPS; absent when the run had no LPIPS weights.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub test_lpips: Option<f64>,
    /// How LPIPS was computed (convention, weight files), when it was.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lpips_info: Option<crate::lpips::MetricInfo>,
    /// Best of the periodic test evaluations (see [`BestOfEvaluations`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub best: Option<BestOfEvaluations>,
    /// Mean wall-clock milliseconds per training iteration.
    pub ms_per_iteration: f64,
    /// Optional mean milliseconds per iteration of each stage.
    #[serde(default)]
    pub stage_ms: BTreeMap<String, f64>,
    /// [`temporal_smoothness`] of the learned field, when measured.
    pub temporal_smoothness: Option<f64>,
    /// The smoothness sweep's uniform times and Gaussians, when measured
    /// (absent in records written before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub smoothness_sweep: Option<[usize; 2]>,
    /// The training curve: loss, and test metrics where evaluated.
    pub curves: Vec<CurvePoint>,
    /// Wall-clock seconds of the run in the process that finished it
    /// (training, final evaluation and smoothness sweep).
    pub wall_seconds: f64,
}

/// The label of a field configuration, e.g. `cfc-d6-w128-gelu`.
pub fn field_label(c: &FieldConfig) -> String {
    format!(
        "{}-d{}-w{}-{}",
        c.kind(),
        c.depth(),
        c.width(),
        c.activation().name()
    )
}

impl RunRecord {
    /// The field configuration this run trained (default backbone).
    pub fn field_config(&self) -> Result<FieldConfig> {
        let c = FieldConfig::sized(
            FieldKind::parse(&self.kind)?,
            Variant::parse(&self.variant)?,
            self.depth,
            self.width,
            Activation::parse(&self.activation)?,
        )?;
        c.validate()?;
        Ok(c)
    }

    fn check(&self) -> Result<()> {
        let scalars = [
            ("test_psnr", self.test_psnr),
            ("test_ssim", self.test_ssim),
            ("ms_per_iteration", self.ms_per_iteration),
            ("wall_seconds", self.wall_seconds),
            (
                "temporal_smoothness",
                self.temporal_smoothness.unwrap_or(0.0),
            ),
            ("test_lpips", self.test_lpips.unwrap_or(0.0)),
        ];
        let curves = self.curves.iter().map(|p| ("curves.loss", p.loss));
        let psnrs = self.curves.iter().flat_map(|p| {
            [
                ("curves.test_psnr", p.test_psnr.unwrap_or(0.0)),
                ("curves.test_ssim", p.test_ssim.unwrap_or(0.0)),
                ("curves.test_lpips", p.test_lpips.unwrap_or(0.0)),
            ]
        });
        let best = self.best.iter().flat_map(|b| {
            [
                ("best.psnr", b.psnr.value),
                ("best.ssim", b.ssim.map_or(0.0, |v| v.value)),
                ("best.lpips", b.lpips.map_or(0.0, |v| v.value)),
            ]
        });
        let stages = self.stage_ms.values().map(|v| ("stage_ms", *v));
        match scalars
            .into_iter()
            .chain(curves)
            .chain(psnrs)
            .chain(best)
            .chain(stages)
            .find(|x| !x.1.is_finite())
        {
            Some((name, v)) => Err(Error::invalid(
                format!(
                    "run record {}/{}/seed {}",
                    self.scene, self.field, self.seed
                ),
                format!("{name} is {v}; only finite values can be recorded"),
            )),
            None => Ok(()),
        }
    }
}

fn safe_name(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Where the record of (scene, field, seed) lives in report folder `dir`.
pub fn record_path(dir: &Path, scene: &str, field: &str, seed: u64) -> PathBuf {
    dir.join("runs").join(format!(
        "{}__{}__seed{seed}.json",
        safe_name(scene),
        safe_name(field)
    ))
}

/// Write a finished run's record (atomically) into `dir/runs/`.
pub fn write_record(dir: &Path, r: &RunRecord) -> Result<()> {
    r.check()?;
    let path = record_path(dir, &r.scene, &r.field, r.seed);
    create_dir(path.parent().unwrap_or(dir))?;
    let json = serde_json::to_vec_pretty(r).map_err(|e| Error::format(&path, e.to_string()))?;
    write_atomic(&path, &json)
}

/// All records in `dir/runs/`, in file-name order (none if the folder is absent).
pub fn read_records(dir: &Path) -> Result<Vec<RunRecord>> {
    let runs = dir.join("runs");
    if !runs.exists() {
        return Ok(Vec::new());
    }
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&runs)
        .map_err(|e| Error::io(&runs, e))?
        .map(|e| e.map(|e| e.path()).map_err(|e| Error::io(&runs, e)))
        .collect::<Result<_>>()?;
    paths.retain(|p| p.extension().is_some_and(|x| x == "json"));
    paths.sort();
    paths.iter().map(|p| read_record(p)).collect()
}

/// Read one run record.
pub fn read_record(path: &Path) -> Result<RunRecord> {
    let bytes = crate::io::read(path)?;
    serde_json::from_slice(&bytes)
        .map_err(|e| Error::format(path, format!("not a run record: {e}")))
}

/// The machine a report was measured on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MachineInfo {
    /// CPU model name from /proc/cpuinfo, when readable.
    pub cpu_model: Option<String>,
    /// Logical CPUs available to this process.
    pub logical_cpus: usize,
    /// Threads of the rayon pool the runs used.
    pub threads: usize,
    /// Operating system and architecture, e.g. `linux x86_64`.
    pub os: String,
    /// This crate's version.
    pub crate_version: String,
    /// The pinned math library ([`crate::math::MATH_LIBRARY`]).
    pub math_library: String,
}

impl MachineInfo {
    /// The machine this process runs on, with the current rayon pool's
    /// thread count.
    pub fn detect() -> Self {
        let cpu_model = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        });
        MachineInfo {
            cpu_model,
            logical_cpus: std::thread::available_parallelism().map_or(1, |n| n.get()),
            threads: rayon::current_num_threads(),
            os: format!("{} {}", std::env::consts::OS, std::env::consts::ARCH),
            crate_version: env!("CARGO_PKG_VERSION").to_string(),
            math_library: crate::math::MATH_LIBRARY.to_string(),
        }
    }
}

/// What the report states besides the records.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ReportMeta {
    /// The command line that produced the runs.
    pub command: String,
    /// Settings shared by the runs (name, value), in the order to print them;
    /// should say how the smoothness sweep was taken (times, which offsets).
    pub settings: Vec<(String, String)>,
    /// The machine the runs were measured on.
    pub machine: MachineInfo,
    /// The configuration the ablation tables vary one setting of.
    pub ablation_base: AblationBase,
}

fn create_dir(d: &Path) -> Result<()> {
    crate::io::create_dir_all(d)
}

fn distinct<T: Ord + ToString>(v: impl Iterator<Item = T>) -> String {
    let mut v: Vec<T> = v.collect();
    v.sort();
    v.dedup();
    v.iter().map(T::to_string).collect::<Vec<_>>().join(", ")
}

/// The colour of each field label (by field order), shared by every plot.
fn field_colours(records: &[RunRecord]) -> BTreeMap<String, [u8; 3]> {
    by_field(records)
        .iter()
        .enumerate()
        .map(|(i, g)| (g.0.clone(), plot::PALETTE[i % plot::PALETTE.len()]))
        .collect()
}

const COST_NOTE: &str = "Counted for one point (batch 1) as ptflops counts them: one \
    multiply-add is one MAC, and a Linear layer counts in·out + out. `aten`: linear layers only (the ptflops \
    0.7.3 default; equals the parameter count). `pytorch` (count_functional=True, the ptflops ≥ 0.7.4 \
    default): also ReLU/GELU modules twice, SiLU modules and functional ReLU once. `pytorch no-functional`: \
    ReLU/GELU modules once. Tanh, sigmoid, lecun_tanh and element-wise arithmetic count 0. The parameter \
    counts of the paper configurations reproduce the paper's 0.5223 M, 0.7829 M and 0.3345 M.";

const SMOOTHNESS_NOTE: &str = "S = 1/((K−2)·M) · Σ_k Σ_j |o_j(t_{k+1}) − 2·o_j(t_k) + o_j(t_{k−1})| / Δt², \
    over K uniform times t_k with spacing Δt and the M offset values o_j of the swept Gaussians: the mean \
    magnitude of the discrete second time derivative of the offsets. Lower is smoother.";

/// How the records' LPIPS was computed (convention, weights), or that it was not.
fn lpips_note(records: &[RunRecord]) -> String {
    let infos: Vec<&crate::lpips::MetricInfo> = records
        .iter()
        .filter_map(|r| r.lpips_info.as_ref())
        .collect();
    if infos.is_empty() {
        return " LPIPS not computed (no weights given).".into();
    }
    let mut lines: Vec<String> = infos
        .iter()
        .map(|i| {
            let w = |f: &crate::lpips::WeightFile| {
                if f.official {
                    format!("{} (published file)", f.path.display())
                } else {
                    format!(
                        "{} (not the published file, SHA-256 {})",
                        f.path.display(),
                        f.sha256
                    )
                }
            };
            format!("{}; weights {} and {}", i.description, w(&i.vgg), w(&i.lin))
        })
        .collect();
    lines.sort();
    lines.dedup();
    let missing = records.iter().filter(|r| r.test_lpips.is_none()).count();
    let mut s = format!(" LPIPS: {}.", lines.join("; "));
    if missing > 0 {
        s += &format!(" {missing} run(s) have no LPIPS (trained without weights).");
    }
    s
}

/// Write `report.md`, the CSV files, `meta.json` and the plots into `dir`.
pub fn write_report(dir: &Path, records: &[RunRecord], meta: &ReportMeta) -> Result<()> {
    create_dir(&dir.join("plots"))?;
    let mut md = String::from("# Experiment report: MLP vs liquid (CfC) deformation field\n\n");
    md += &format!(
        "Only what was run is reported: every number below comes from the {} run record(s) in \
         `runs/`; configurations that were not trained have no rows (the cost table's paper \
         configurations are computed counts, marked `not run`).\n\n",
        records.len()
    );
    md += "## Settings\n\n";
    md += &format!("- command: `{}`\n", meta.command);
    md += &format!(
        "- scenes: {}\n",
        distinct(records.iter().map(|r| r.scene.clone()))
    );
    md += &format!("- seeds: {}\n", distinct(records.iter().map(|r| r.seed)));
    let iters = distinct(records.iter().map(|r| r.iterations));
    let res = distinct(
        records
            .iter()
            .map(|r| format!("{}x{}", r.resolution[0], r.resolution[1])),
    );
    md += &format!("- iterations: {iters}\n- resolution: {res}\n");
    md += &format!(
        "- threads: {}\n",
        distinct(records.iter().map(|r| r.threads))
    );
    if iters.contains(',') || res.contains(',') {
        md += "- **warning**: the runs differ in iterations or resolution; tables average them per field.\n";
    }
    for (k, v) in &meta.settings {
        md += &format!("- {k}: {v}\n");
    }
    let m = &meta.machine;
    md += "\n## Machine\n\n";
    md += &format!(
        "- CPU: {} ({} logical CPUs)\n",
        m.cpu_model.as_deref().unwrap_or("unknown"),
        m.logical_cpus
    );
    md += &format!("- thread pool: {} threads\n- OS: {}\n", m.threads, m.os);
    md += &format!("- liquid-splat {}, {}\n\n", m.crate_version, m.math_library);

    let best =
        "Best value of each column in bold; several seeds of one configuration are averaged.";
    let b = &meta.ablation_base;
    let base = format!(
        "CfC runs at the base configuration D{} W{} {} with one setting varied. {best}",
        b.depth, b.width, b.activation
    );
    let threads = distinct(records.iter().map(|r| r.threads));
    let time_note = if threads.contains(',') {
        format!(
            "Runs used different thread counts ({threads}): compare times only at equal counts."
        )
    } else {
        format!("Wall-clock mean over each run, {threads} thread(s), on the machine above.")
    };
    let fields = by_field(records);
    let has_lpips = records.iter().any(|r| r.test_lpips.is_some());
    let final_metrics: &[tables::Metric] = if has_lpips {
        &[PSNR, SSIM, LPIPS]
    } else {
        &[PSNR, SSIM]
    };
    let best_metrics: &[tables::Metric] = if has_lpips {
        &[BEST_PSNR, BEST_SSIM, BEST_LPIPS]
    } else {
        &[BEST_PSNR, BEST_SSIM]
    };
    let lpips_note = lpips_note(records);
    let sections = [
        (
            "1. Test-set quality per scene (final model)",
            format!(
                "Metrics of the model after the last iteration. PSNR in dB, SSIM{}. {best}",
                if has_lpips {
                    ", LPIPS (lower is better)"
                } else {
                    ""
                }
            ) + &lpips_note,
            "quality",
            tables::matrix("field", &fields, final_metrics),
        ),
        (
            "1b. Best of the periodic test evaluations",
            format!(
                "The best value of each metric over the test evaluations made during each run \
                 (the last iteration included), each metric on its own: how D-3DGS's published \
                 numbers were chosen (best of evaluations every 1,000 iterations), so higher \
                 than the final model's. Table 1c gives the iteration of each. {best}"
            ),
            "quality_best",
            tables::matrix("field", &fields, best_metrics),
        ),
        (
            "1c. Final and best-of-evaluations metrics of every run",
            "`final`: after the last iteration. `best (iteration)`: best of the periodic \
             evaluations and the iteration it came from."
                .to_string(),
            "final_and_best",
            tables::final_and_best(records),
        ),
        (
            "2. Parameters and MACs per Gaussian",
            COST_NOTE.to_string(),
            "cost",
            Some(tables::cost_table(records)?),
        ),
        (
            "3a. Ablation: number of CfC cells",
            base.clone(),
            "ablation_depth",
            tables::depth_ablation(records, b),
        ),
        (
            "3b. Ablation: backbone activation",
            base,
            "ablation_activation",
            tables::activation_ablation(records, b),
        ),
        (
            "4. Time per training iteration (ms)",
            time_note,
            "time",
            tables::matrix("field", &fields, &[MS_PER_ITER]),
        ),
        (
            "4b. Time per stage (ms per iteration)",
            String::new(),
            "stages",
            tables::stage_table(records),
        ),
        (
            "5. Temporal smoothness of the learned deformation",
            SMOOTHNESS_NOTE.to_string(),
            "smoothness",
            tables::matrix("field", &fields, &[SMOOTHNESS]),
        ),
    ];
    for (title, note, name, table) in sections {
        match table {
            Some(t) => {
                md += &format!(
                    "## {title}\n\n{note}\n\n{}\n(`table_{name}.csv`)\n\n",
                    t.to_markdown()
                );
                write_atomic(
                    &dir.join(format!("table_{name}.csv")),
                    t.to_csv().as_bytes(),
                )?;
            }
            None if name == "stages" => {}
            None => md += &format!("## {title}\n\nNo runs of this kind were made.\n\n"),
        }
    }

    md += "## 6. Training curves\n\nOne line per field (colour legend in each plot); loss as logged by the trainer, test PSNR where it was evaluated.\n\n";
    let colours = field_colours(records);
    let mut scenes: Vec<&str> = records.iter().map(|r| r.scene.as_str()).collect();
    scenes.sort();
    scenes.dedup();
    let mut any_plot = false;
    for scene in scenes {
        let mut runs: Vec<&RunRecord> = records
            .iter()
            .filter(|r| r.scene == scene && !r.curves.is_empty())
            .collect();
        runs.sort_by_key(|r| (field_order(r), r.seed));
        let series = |y: fn(&CurvePoint) -> Option<f64>| -> Vec<plot::Series> {
            runs.iter()
                .map(|r| {
                    let seeds = runs.iter().filter(|o| o.field == r.field).count();
                    plot::Series {
                        label: if seeds > 1 {
                            format!("{} s{}", r.field, r.seed)
                        } else {
                            r.field.clone()
                        },
                        color: colours[&r.field],
                        points: r
                            .curves
                            .iter()
                            .filter_map(|p| y(p).map(|v| (p.iteration as f64, v)))
                            .collect(),
                    }
                })
                .filter(|s| !s.points.is_empty())
                .collect()
        };
        for (what, file, s) in [
            ("training loss", "loss", series(|p| Some(p.loss))),
            ("test psnr (db)", "psnr", series(|p| p.test_psnr)),
        ] {
            if s.is_empty() {
                continue;
            }
            let name = format!("{}-{file}.png", safe_name(scene));
            write_atomic(
                &dir.join("plots").join(&name),
                &plot::line_plot_png(&format!("{scene}: {what}"), "iteration", &s)?,
            )?;
            md += &format!("![{scene}: {what}](plots/{name})\n\n");
            any_plot = true;
        }
    }
    if !any_plot {
        md += "No curves were recorded.\n\n";
    }

    write_atomic(&dir.join("runs.csv"), runs_csv(records).as_bytes())?;
    let mut curves = csv_line(
        [
            "scene",
            "field",
            "seed",
            "iteration",
            "loss",
            "test_psnr",
            "test_ssim",
            "test_lpips",
        ]
        .into_iter(),
    );
    let opt = |v: Option<f64>| v.map_or(String::new(), |v| v.to_string());
    for r in records {
        for p in &r.curves {
            let v = [
                r.seed.to_string(),
                p.iteration.to_string(),
                p.loss.to_string(),
                opt(p.test_psnr),
                opt(p.test_ssim),
                opt(p.test_lpips),
            ];
            curves += &csv_line(
                [r.scene.as_str(), r.field.as_str()]
                    .into_iter()
                    .chain(v.iter().map(String::as_str)),
            );
        }
    }
    write_atomic(&dir.join("curves.csv"), curves.as_bytes())?;
    let meta_json = serde_json::to_vec_pretty(meta)
        .map_err(|e| Error::format(dir.join("meta.json"), e.to_string()))?;
    write_atomic(&dir.join("meta.json"), &meta_json)?;
    md += "## Files\n\n`runs/*.json` (one record per run), `runs.csv`, `curves.csv`, `table_*.csv` (full precision), `plots/*.png`, `meta.json`.\n";
    write_atomic(&dir.join("report.md"), md.as_bytes())
}

/// Column names of `runs.csv`.
pub const RUNS_CSV_COLUMNS: [&str; 28] = [
    "scene",
    "field",
    "kind",
    "variant",
    "depth",
    "width",
    "activation",
    "seed",
    "iterations",
    "width_px",
    "height_px",
    "threads",
    "params",
    "macs_per_gaussian",
    "final_gaussians",
    "test_psnr",
    "test_ssim",
    "test_lpips",
    "best_psnr",
    "best_psnr_iteration",
    "best_ssim",
    "best_ssim_iteration",
    "best_lpips",
    "best_lpips_iteration",
    "ms_per_iteration",
    "temporal_smoothness",
    "wall_seconds",
    "curve_points",
];

/// One row per run, every scalar at full precision (shortest round-trip form).
pub fn runs_csv(records: &[RunRecord]) -> String {
    let mut s = csv_line(RUNS_CSV_COLUMNS.into_iter());
    let opt = |v: Option<f64>| v.map_or(String::new(), |v| v.to_string());
    let it = |v: Option<BestValue>| v.map_or(String::new(), |v| v.iteration.to_string());
    for r in records {
        let b = r.best.as_ref();
        let v = [
            r.scene.clone(),
            r.field.clone(),
            r.kind.clone(),
            r.variant.clone(),
            r.depth.to_string(),
            r.width.to_string(),
            r.activation.clone(),
            r.seed.to_string(),
            r.iterations.to_string(),
            r.resolution[0].to_string(),
            r.resolution[1].to_string(),
            r.threads.to_string(),
            r.params.to_string(),
            r.macs_per_gaussian.to_string(),
            r.final_gaussians.to_string(),
            r.test_psnr.to_string(),
            r.test_ssim.to_string(),
            opt(r.test_lpips),
            opt(b.map(|b| b.psnr.value)),
            it(b.map(|b| b.psnr)),
            opt(b.and_then(|b| b.ssim).map(|v| v.value)),
            it(b.and_then(|b| b.ssim)),
            opt(b.and_then(|b| b.lpips).map(|v| v.value)),
            it(b.and_then(|b| b.lpips)),
            r.ms_per_iteration.to_string(),
            r.temporal_smoothness
                .map_or(String::new(), |v| v.to_string()),
            r.wall_seconds.to_string(),
            r.curves.len().to_string(),
        ];
        s += &csv_line(v.iter().map(String::as_str));
    }
    s
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::deform::count::{macs_per_gaussian, param_count, MacConvention};

    /// A synthetic record with real parameter and MAC counts for its configuration.
    #[allow(clippy::too_many_arguments)]
    pub fn record(
        scene: &str,
        kind: &str,
        depth: usize,
        width: usize,
        act: &str,
        seed: u64,
        psnr: f64,
        ssim: f64,
    ) -> RunRecord {
        let mut r = RunRecord {
            scene: scene.into(),
            field: String::new(),
            kind: kind.into(),
            variant: "synthetic".into(),
            depth,
            width,
            activation: act.into(),
            seed,
            iterations: 200,
            resolution: [100, 100],
            threads: 2,
            params: 0,
            macs_per_gaussian: 0,
            final_gaussians: 1000 + depth,
            test_psnr: psnr,
            test_ssim: ssim,
            test_lpips: None,
            lpips_info: None,
            best: None,
            ms_per_iteration: 10.0 + width as f64 / 64.0,
            stage_ms: BTreeMap::new(),
            temporal_smoothness: None,
            smoothness_sweep: None,
            curves: (0..5)
                .map(|i| CurvePoint {
                    iteration: 50 * i,
                    loss: 0.1 / (1.0 + i as f64),
                    test_psnr: (i % 2 == 0).then_some(psnr - 4.0 + i as f64),
                    test_ssim: (i % 2 == 0).then_some(ssim),
                    test_lpips: None,
                })
                .collect(),
            wall_seconds: 3.5,
        };
        r.best = best_of_evaluations(&r.curves);
        let c = r.field_config().unwrap();
        r.field = field_label(&c);
        r.params = param_count(&c).unwrap();
        r.macs_per_gaussian = macs_per_gaussian(&c, MacConvention::Aten).unwrap();
        r
    }

    /// Split one CSV line (RFC 4180 quoting), the inverse of `csv_line`.
    fn parse_csv_line(line: &str) -> Vec<String> {
        let (mut out, mut cur, mut quoted, mut chars) =
            (Vec::new(), String::new(), false, line.chars().peekable());
        while let Some(c) = chars.next() {
            match (c, quoted) {
                ('"', true) if chars.peek() == Some(&'"') => {
                    cur.push('"');
                    chars.next();
                }
                ('"', _) => quoted = !quoted,
                (',', false) => out.push(std::mem::take(&mut cur)),
                _ => cur.push(c),
            }
        }
        out.push(cur);
        out
    }

    fn tmp(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("liquid-splat-report-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn runs_csv_parses_back_to_the_records() {
        let mut a = record(
            "lego, small",
            "cfc",
            6,
            128,
            "gelu",
            3,
            1.0 / 3.0,
            0.912345678901,
        );
        a.temporal_smoothness = Some(0.1 + 0.2);
        let recs = vec![a, record("lego", "mlp", 8, 256, "relu", 0, 30.0, 0.9)];
        let csv = runs_csv(&recs);
        let lines: Vec<Vec<String>> = csv.lines().map(parse_csv_line).collect();
        assert_eq!(lines[0], RUNS_CSV_COLUMNS);
        for (row, r) in lines[1..].iter().zip(&recs) {
            let col = |n: &str| &row[RUNS_CSV_COLUMNS.iter().position(|c| *c == n).unwrap()];
            assert_eq!(col("scene"), &r.scene);
            assert_eq!(col("test_psnr").parse::<f64>().unwrap(), r.test_psnr);
            assert_eq!(col("test_ssim").parse::<f64>().unwrap(), r.test_ssim);
            assert_eq!(col("params").parse::<usize>().unwrap(), r.params);
            assert_eq!(
                col("temporal_smoothness").parse::<f64>().ok(),
                r.temporal_smoothness
            );
        }
    }

    #[test]
    fn records_round_trip_and_resume() {
        let dir = tmp("resume");
        assert!(read_records(&dir).unwrap().is_empty());
        let mut a = record("lego", "cfc", 6, 128, "gelu", 0, 31.0, 0.95);
        a.stage_ms.insert("render".into(), 4.25);
        let b = record("lego", "mlp", 8, 256, "relu", 0, 30.0, 0.94);
        write_record(&dir, &a).unwrap();
        assert!(record_path(&dir, "lego", &a.field, 0).exists());
        assert!(!record_path(&dir, "lego", &b.field, 0).exists());
        write_record(&dir, &b).unwrap();
        assert_eq!(read_records(&dir).unwrap(), vec![a.clone(), b]);
        a.test_psnr = f64::NAN;
        assert!(write_record(&dir, &a).is_err());
        std::fs::write(dir.join("runs").join("bad.json"), b"{}").unwrap();
        assert!(read_records(&dir).is_err());
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn report_folder_has_every_part() {
        let dir = tmp("write");
        let mut recs = vec![
            record("lego", "mlp", 8, 256, "relu", 0, 30.0, 0.94),
            record("lego", "cfc", 6, 128, "gelu", 0, 31.0, 0.95),
            record("lego", "cfc", 8, 128, "gelu", 0, 31.5, 0.95),
            record("lego", "cfc", 6, 128, "tanh", 0, 29.5, 0.93),
        ];
        recs[1].temporal_smoothness = Some(0.5);
        let meta = ReportMeta {
            command: "liquid-splat experiment --iterations 200".into(),
            settings: vec![("background".into(), "black".into())],
            machine: MachineInfo::detect(),
            ablation_base: AblationBase::default(),
        };
        assert!(meta.machine.threads >= 1 && meta.machine.math_library.contains("0.2.11"));
        write_report(&dir, &recs, &meta).unwrap();
        let md = std::fs::read_to_string(dir.join("report.md")).unwrap();
        for needle in [
            "Only what was run",
            "- seeds: 0\n",
            "- threads: 2\n",
            "- background: black",
            "| D=8 |",
            "| tanh |",
            "](plots/lego-loss.png)",
            "paper config, not run",
            "5.000e-1",
        ] {
            assert!(md.contains(needle), "{needle:?} missing from\n{md}");
        }
        for f in [
            "runs.csv",
            "curves.csv",
            "meta.json",
            "table_quality.csv",
            "table_cost.csv",
            "table_ablation_depth.csv",
            "table_ablation_activation.csv",
            "table_time.csv",
            "table_smoothness.csv",
            "plots/lego-loss.png",
            "plots/lego-psnr.png",
        ] {
            assert!(dir.join(f).exists(), "{f}");
        }
        assert!(!dir.join("table_stages.csv").exists());
        let curves = std::fs::read_to_string(dir.join("curves.csv")).unwrap();
        assert_eq!(curves.lines().count(), 1 + 4 * 5);
        assert!(!md.contains("warning"));
        let first = std::fs::read(dir.join("plots/lego-psnr.png")).unwrap();
        write_report(&dir, &recs, &meta).unwrap();
        assert_eq!(
            std::fs::read(dir.join("plots/lego-psnr.png")).unwrap(),
            first
        );
        recs[3].iterations = 400;
        write_report(&dir, &recs, &meta).unwrap();
        let md = std::fs::read_to_string(dir.join("report.md")).unwrap();
        assert!(
            md.contains("- iterations: 200, 400\n")
                && md.contains("- **warning**: the runs differ")
        );
        let _ = std::fs::remove_dir_all(&dir);
    }
}
