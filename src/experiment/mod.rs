//! Training runs and experiments as library calls, used by the CLI's
//! `train`, `render`, `eval`, `export`, `experiment` and `bench train` and
//! callable from the Python package.
//!
//! - [`spec`]: [`RunSpec`], the persisted description of one training run
//!   (`OUT/run.json`), the resume rule ([`prepare_run`]), training it
//!   ([`train_run`]), reopening a finished run ([`open_run`]) and scoring its
//!   saved renders ([`evaluate_renders`]).
//! - This module: the experiment driver. An [`Experiment`] compares the MLP
//!   and liquid fields on several scenes with identical seeds and settings
//!   except the field: [`Experiment::plan`] lists the runs, [`Experiment::run`]
//!   trains each, sweeps the trained field's offsets over time for the
//!   temporal smoothness ([`crate::report::temporal_smoothness`]), assembles
//!   a [`RunRecord`] and rewrites the report ([`crate::report`]) after every
//!   run.
//!
//! Each (scene, field, seed) trains in `OUT/training/<scene>__<field>__seed<S>/`
//! with periodic checkpoints; when it finishes its record is written to
//! `OUT/runs/`. Running the same experiment again skips finished runs (their
//! record exists) and resumes unfinished ones from their newest checkpoint,
//! so a sweep can be interrupted at any point.

pub mod spec;

pub use spec::{
    evaluate_renders, open_run, prepare_run, train_run, FieldChoice, FieldSpec, OpenedRun,
    PrecisionChoice, RunSpec, VariantChoice,
};

use crate::deform::count::{macs_per_gaussian, param_count, MacConvention};
use crate::error::{Error, Result};
use crate::report::{self, MachineInfo, ReportMeta, RunRecord};
use crate::train::{self, checkpoint, Event, RunOptions, RunSummary, StageTimes, TrainConfig};
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;

/// The most uniform times and Gaussians of the smoothness sweep.
pub const MAX_SWEEP: usize = 100_000;

/// The settings of an experiment: which scenes, how long, which seeds,
/// and the smoothness sweep.
#[derive(Clone)]
pub struct Experiment {
    /// Dataset folders (D-NeRF or NeRF-DS layout); when empty, `scenes`.
    pub data: Vec<PathBuf>,
    /// Built-in scenes used when no dataset folder is given.
    pub scenes: Vec<String>,
    /// Report folder (runs, training folders, report.md, CSV, plots).
    pub out: PathBuf,
    /// Training iterations per run (at least 1).
    pub iterations: u64,
    /// Built-in scenes: image width and height in pixels.
    pub resolution: usize,
    /// Dataset folders: downscale factor 1, 2, 4 or 8.
    pub downscale: usize,
    /// Random initial points (scenes without a point cloud).
    pub init_points: usize,
    /// Seeds; every configuration runs once per seed (at least one).
    pub seeds: Vec<u64>,
    /// Also run the ablations on the first scene ([`fields`]).
    pub ablations: bool,
    /// Test evaluations during each run (the PSNR curve).
    pub evals: u64,
    /// Smoothness sweep: number of uniform times in [0, 1].
    pub sweep_times: usize,
    /// Smoothness sweep: number of Gaussians (the first of the canonical set).
    pub sweep_gaussians: usize,
    /// LPIPS for every evaluation, when given.
    pub lpips: Option<Arc<crate::lpips::Metric>>,
    /// The command line that started the experiment, for the report.
    pub command: String,
}

/// One run of an experiment's plan.
#[derive(Clone, Debug)]
pub struct PlannedRun {
    /// The scene's name (built-in scene, or the dataset folder's name).
    pub scene: String,
    /// The run's description.
    pub spec: RunSpec,
}

/// What an experiment reports while it runs.
pub enum ExperimentEvent<'a> {
    /// The plan is made: `runs` runs, before any is trained.
    Planned {
        /// Number of runs.
        runs: usize,
    },
    /// Run `index` (from 0) of `runs` starts: `kept` when its record exists
    /// and it is skipped.
    Run {
        /// Index of the run in the plan, from 0.
        index: usize,
        /// Number of runs in the plan.
        runs: usize,
        /// The run.
        run: &'a PlannedRun,
        /// The field's label ([`report::field_label`]).
        label: &'a str,
        /// Finished earlier: its record is kept and it is not trained.
        kept: bool,
    },
    /// An event of the run being trained.
    Train(Event<'a>),
    /// The run being trained finished and its record was written.
    Finished(&'a RunRecord),
}

/// The field configurations of a sweep: the paper's comparison (MLP D8 W256
/// vs CfC D6 W128 GELU), plus, with `ablations`, CfC depth 8 and 10 and the
/// backbone activations relu, silu, lecun_tanh and tanh (D6 W128).
pub fn fields(ablations: bool) -> Vec<FieldSpec> {
    let f = FieldSpec::sized;
    let mut v = vec![
        f(FieldChoice::Mlp, 8, 256, "relu"),
        f(FieldChoice::Cfc, 6, 128, "gelu"),
    ];
    if ablations {
        for d in [8, 10] {
            v.push(f(FieldChoice::Cfc, d, 128, "gelu"));
        }
        for a in ["relu", "silu", "lecun_tanh", "tanh"] {
            v.push(f(FieldChoice::Cfc, 6, 128, a));
        }
    }
    v
}

impl Experiment {
    /// Test evaluations happen every this many iterations (and at the last).
    pub fn eval_every(&self) -> u64 {
        (self.iterations / self.evals.max(1)).max(1)
    }

    /// The runs, in order: per scene, per field, per seed. Every scene runs
    /// the two fields of the comparison; the first also runs the ablations
    /// when asked.
    pub fn plan(&self) -> Result<Vec<PlannedRun>> {
        if self.iterations == 0 || self.seeds.is_empty() {
            return Err(Error::invalid(
                "experiment",
                "need at least one iteration and one seed",
            ));
        }
        // Settings used after the first run trains, refused before it.
        // (The smoothness figure's second differences need 3 times.)
        if !(3..=MAX_SWEEP).contains(&self.sweep_times) {
            return Err(Error::invalid(
                "--sweep-times",
                format!("{} (3 to {MAX_SWEEP} uniform times)", self.sweep_times),
            ));
        }
        if !(1..=MAX_SWEEP).contains(&self.sweep_gaussians) {
            return Err(Error::invalid(
                "--sweep-gaussians",
                format!("{} (1 to {MAX_SWEEP})", self.sweep_gaussians),
            ));
        }
        if let Some(d) = self.data.iter().find(|d| !d.is_dir()) {
            return Err(Error::invalid(
                "dataset folder",
                format!("{}: not found", d.display()),
            ));
        }
        let scenes: Vec<(String, RunSpec)> = if self.data.is_empty() {
            self.scenes
                .iter()
                .map(|s| (s.clone(), self.base_spec(None, Some(s.clone()))))
                .collect()
        } else {
            self.data
                .iter()
                .map(|d| {
                    let name = d
                        .file_name()
                        .map_or("scene".into(), |n| n.to_string_lossy().to_string());
                    (name, self.base_spec(Some(d.clone()), None))
                })
                .collect()
        };
        // Every name and seed before the first run trains: runs are recorded
        // by scene name, field and seed, so a repeated one would be reported
        // as "done earlier, kept" with another run's results.
        if self.data.is_empty() {
            for s in &self.scenes {
                crate::dataset::synth::SceneName::parse_named("--scenes", s)?;
            }
        }
        for (i, (scene, _)) in scenes.iter().enumerate() {
            if let Some((_, (_, first))) = scenes[..i]
                .iter()
                .enumerate()
                .find(|(_, (s, _))| s == scene)
            {
                return Err(if self.data.is_empty() {
                    Error::invalid("--scenes", format!("`{scene}` is given twice"))
                } else {
                    let shown = |s: &RunSpec| {
                        s.data
                            .as_ref()
                            .map_or(String::new(), |d| d.display().to_string())
                    };
                    Error::invalid(
                        "dataset folder",
                        format!(
                            "{} and {} have the same name `{scene}` (runs are recorded by \
                             folder name)",
                            shown(first),
                            shown(&scenes[i].1)
                        ),
                    )
                });
            }
        }
        if let Some((_, seed)) = self
            .seeds
            .iter()
            .enumerate()
            .find(|(i, s)| self.seeds[..*i].contains(s))
        {
            return Err(Error::invalid("--seeds", format!("{seed} is given twice")));
        }
        let all_fields = fields(self.ablations);
        let mut plan = Vec::new();
        for (i, (scene, base)) in scenes.iter().enumerate() {
            let n = if i == 0 { all_fields.len() } else { 2 };
            for f in &all_fields[..n] {
                for &seed in &self.seeds {
                    plan.push(PlannedRun {
                        scene: scene.clone(),
                        spec: RunSpec {
                            field: f.clone(),
                            seed,
                            ..base.clone()
                        },
                    });
                }
            }
        }
        Ok(plan)
    }

    fn base_spec(&self, data: Option<PathBuf>, scene: Option<String>) -> RunSpec {
        RunSpec {
            data: data.map(|d| std::path::absolute(&d).unwrap_or(d)),
            scene,
            resolution: self.resolution,
            frames: 24,
            init_points: self.init_points,
            downscale: self.downscale,
            white_background: false,
            field: fields(false).remove(1),
            iterations: self.iterations,
            seed: 0,
            precision: PrecisionChoice::F32,
        }
    }

    /// What the report states besides the records.
    pub fn meta(&self) -> ReportMeta {
        ReportMeta {
            command: self.command.clone(),
            settings: self.settings(),
            machine: MachineInfo::detect(),
            ablation_base: Default::default(),
        }
    }

    /// Refuses a finished run's record made with other settings than this
    /// experiment's (its iterations, training image size or smoothness
    /// sweep): the report would mix them.
    fn check_kept(&self, path: &std::path::Path, data: &crate::dataset::Dataset) -> Result<()> {
        let r = report::read_record(path)?;
        let size = data
            .train
            .first()
            .map_or(r.resolution, |f| [f.width, f.height]);
        let sweep = [self.sweep_times, self.sweep_gaussians];
        let differs = if r.iterations as u64 != self.iterations {
            Some(format!(
                "{} iterations, not {}",
                r.iterations, self.iterations
            ))
        } else if r.resolution != size {
            Some(format!(
                "training images of {}x{}, not {}x{}",
                r.resolution[0], r.resolution[1], size[0], size[1]
            ))
        } else if r.smoothness_sweep.is_some_and(|s| s != sweep) {
            Some(format!(
                "a smoothness sweep of {:?} (times, Gaussians), not {sweep:?}",
                r.smoothness_sweep.unwrap_or_default()
            ))
        } else {
            None
        };
        match differs {
            Some(why) => Err(Error::format(
                path,
                format!(
                    "this finished run was made with {why}; use another --out, or remove \
                     the record to train the run again"
                ),
            )),
            None => Ok(()),
        }
    }

    /// Run the plan into `out`: train every run without a record (resuming
    /// from its newest checkpoint), write its record, and rewrite the report
    /// after each run and at the end. Returns the path of `report.md`.
    pub fn run(&self, on_event: &mut dyn FnMut(ExperimentEvent)) -> Result<PathBuf> {
        let plan = self.plan()?;
        let meta = self.meta();
        on_event(ExperimentEvent::Planned { runs: plan.len() });
        for (index, run) in plan.iter().enumerate() {
            let s = &run.spec;
            let data = s.load_dataset()?;
            let config = s.train_config(&data)?;
            s.check_eval_split(&data)?;
            let label = report::field_label(&config.field);
            let record = report::record_path(&self.out, &run.scene, &label, s.seed);
            let kept = record.exists();
            if kept {
                self.check_kept(&record, &data)?;
            }
            on_event(ExperimentEvent::Run {
                index,
                runs: plan.len(),
                run,
                label: &label,
                kept,
            });
            if kept {
                continue;
            }
            let record = self.train_one(run, &data, &config, label, on_event)?;
            report::write_record(&self.out, &record)?;
            on_event(ExperimentEvent::Finished(&record));
            report::write_report(&self.out, &report::read_records(&self.out)?, &meta)?;
        }
        let records = report::read_records(&self.out)?;
        report::write_report(&self.out, &records, &meta)?;
        Ok(self.out.join("report.md"))
    }

    /// Train (or resume) one run in its training folder, then sweep its
    /// field for the smoothness and assemble its record.
    fn train_one(
        &self,
        run: &PlannedRun,
        data: &crate::dataset::Dataset,
        config: &TrainConfig,
        label: String,
        on_event: &mut dyn FnMut(ExperimentEvent),
    ) -> Result<RunRecord> {
        let s = &run.spec;
        let work = self
            .out
            .join("training")
            .join(format!("{}__{label}__seed{}", run.scene, s.seed));
        // (So that render and export open the training folder as a run.)
        crate::io::create_dir_all(&work)?;
        s.write(&work)?;
        let opts = RunOptions {
            out: work.clone(),
            checkpoint_every: (self.iterations / 4).max(1),
            eval_every: self.eval_every(),
            resume: true,
            data_name: s.data_name(),
            lpips: self.lpips.clone(),
        };
        let mut stages = StageTimes::default();
        let mut stage_n = 0u64;
        let clock = std::time::Instant::now();
        let summary = train::run::<f32>(config, data, &opts, &mut |e| {
            if let Event::Step(r) = &e {
                stages.add(&r.times);
                stage_n += 1;
            }
            on_event(ExperimentEvent::Train(e));
        })?;
        let ckpt = checkpoint::latest(&work.join("checkpoints"))?.ok_or_else(|| {
            Error::invalid("experiment", format!("no checkpoint in {}", work.display()))
        })?;
        let binding = checkpoint::DataBinding::of(data, &s.data_name());
        let trainer = checkpoint::load::<f32>(&ckpt, config, &binding)?;
        let smoothness = self.smoothness(&trainer)?;
        let n = stage_n.max(1) as f64;
        let stage_ms: BTreeMap<String, f64> = StageTimes::NAMES
            .iter()
            .zip(stages.values())
            .map(|(name, v)| (name.to_string(), 1e3 * v / n))
            .collect();
        let mut record = self.record(run, data, config, label, &summary, stage_ms)?;
        record.temporal_smoothness = Some(smoothness);
        record.smoothness_sweep = Some([self.sweep_times, self.sweep_gaussians]);
        record.wall_seconds = clock.elapsed().as_secs_f64();
        Ok(record)
    }

    /// The smoothness sweep: [`report::temporal_smoothness`] of `d_xyz` of
    /// the first [`Experiment::sweep_gaussians`] canonical Gaussians at
    /// [`Experiment::sweep_times`] uniform times in [0, 1].
    pub fn smoothness(&self, trainer: &train::Trainer<f32>) -> Result<f64> {
        let m = self.sweep_gaussians.min(trainer.model().gaussians.len());
        report::temporal_smoothness(
            |t| match trainer.offsets(t) {
                Ok(o) => o.d_xyz[..3 * m].iter().map(|&v| v as f64).collect(),
                Err(_) => vec![f64::NAN; 3 * m],
            },
            &report::uniform_times(self.sweep_times),
        )
    }

    /// The record of a finished run, from its summary and mean stage times
    /// in milliseconds (smoothness absent and wall time 0: the caller fills
    /// them in).
    pub fn record(
        &self,
        run: &PlannedRun,
        data: &crate::dataset::Dataset,
        config: &TrainConfig,
        label: String,
        summary: &RunSummary,
        stage_ms: BTreeMap<String, f64>,
    ) -> Result<RunRecord> {
        let curves: Vec<report::CurvePoint> = summary
            .curve
            .iter()
            .map(|c| report::CurvePoint {
                iteration: c.iteration as usize,
                loss: c.loss,
                test_psnr: c.test_psnr,
                test_ssim: c.test_ssim,
                test_lpips: c.test_lpips,
            })
            .collect();
        Ok(RunRecord {
            scene: run.scene.clone(),
            field: label,
            kind: config.field.kind().name().into(),
            variant: config.field.variant().name().into(),
            depth: config.field.depth(),
            width: config.field.width(),
            activation: config.field.activation().name().into(),
            seed: run.spec.seed,
            iterations: self.iterations as usize,
            resolution: [data.train[0].width, data.train[0].height],
            threads: rayon::current_num_threads(),
            params: param_count(&config.field)?,
            macs_per_gaussian: macs_per_gaussian(&config.field, MacConvention::Aten)?,
            final_gaussians: summary.gaussians,
            test_psnr: summary.psnr,
            test_ssim: summary.ssim,
            test_lpips: summary.lpips,
            lpips_info: self.lpips.as_ref().map(|m| m.info()),
            best: report::best_of_evaluations(&curves),
            ms_per_iteration: 1e3 * summary.train_seconds / summary.iterations_run.max(1) as f64,
            stage_ms,
            temporal_smoothness: None,
            smoothness_sweep: None,
            curves,
            wall_seconds: 0.0,
        })
    }

    /// The settings shared by every run, as the report lists them.
    pub fn settings(&self) -> Vec<(String, String)> {
        let s = |k: &str, v: String| (k.to_string(), v);
        vec![
            s("precision", "f32".into()),
            s("background", "black".into()),
            s("initial points", format!("{} random (scenes without a point cloud)", self.init_points)),
            s("built-in scenes", format!("{}x{} pixels, 24 train / 8 test frames", self.resolution, self.resolution)),
            s("dataset folders", format!("downscale {}, test split", self.downscale)),
            s(
                "schedule",
                "upstream D-3DGS scaled to the iteration count (positions × s, intervals × √s, s = iterations / 40,000)".into(),
            ),
            s("test PSNR / SSIM / LPIPS", "8-bit quantised renders, mean over the test views (upstream metrics.py); LPIPS only with --lpips-vgg/--lpips-lin".into()),
            s(
                "periodic test evaluations",
                format!("every {} iterations and at the last one; the best of them is reported apart from the final metrics", self.eval_every()),
            ),
            s(
                "smoothness sweep",
                format!(
                    "d_xyz of the first {} canonical Gaussians of each trained model (all of them where a model holds fewer), {} uniform times in [0, 1]",
                    self.sweep_gaussians, self.sweep_times
                ),
            ),
            s("ms per iteration", "wall clock of the training iterations run in the last process (resumed runs: the resumed part)".into()),
        ]
    }
}
