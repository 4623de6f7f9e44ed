//! `liquid-splat experiment`: MLP vs liquid field on several scenes, with
//! identical seeds and settings except the field, and a report folder.
//!
//! Each (scene, field, seed) trains in `OUT/training/<scene>__<field>__seed<S>/`
//! with periodic checkpoints; when it finishes its record is written to
//! `OUT/runs/`. Rerunning the same command skips finished runs and resumes
//! unfinished ones from their newest checkpoint, so a sweep can be
//! interrupted at any point. The report is rewritten after every run.

use super::train::{FieldArg, FieldArgs, PrecisionArg, RunSpec};
use crate::deform::count::{macs_per_gaussian, param_count, MacConvention};
use crate::error::{Error, Result};
use crate::report::{self, MachineInfo, ReportMeta, RunRecord};
use crate::train::{self, checkpoint, Event, RunOptions, StageTimes};
use clap::Args;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Args)]
pub struct ExperimentArgs {
    /// Dataset folders (D-NeRF or NeRF-DS layout). Without any, the built-in scenes are used.
    pub data: Vec<PathBuf>,
    /// Built-in scenes to use when no dataset folder is given.
    #[arg(long, value_delimiter = ',', default_value = "bouncing,swing,blob")]
    pub scenes: Vec<String>,
    /// Report folder (runs, training folders, report.md, CSV, plots).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Training iterations per run.
    #[arg(long, default_value_t = 1000)]
    pub iterations: u64,
    /// Built-in scenes: image size.
    #[arg(long, default_value_t = 64)]
    pub resolution: usize,
    /// Dataset folders: downscale factor 1, 2, 4 or 8.
    #[arg(long, default_value_t = 4)]
    pub downscale: usize,
    /// Random initial points (scenes without a point cloud).
    #[arg(long, default_value_t = 2000)]
    pub init_points: usize,
    /// Seeds; every configuration runs once per seed.
    #[arg(long, value_delimiter = ',', default_value = "0")]
    pub seeds: Vec<u64>,
    /// Also run the ablations on the first scene: CfC depth 6/8/10 and
    /// activation gelu/relu/silu/lecun_tanh/tanh (W128).
    #[arg(long)]
    pub ablations: bool,
    /// Evaluate the test views this many times during each run (PSNR curve).
    #[arg(long, default_value_t = 10)]
    pub evals: u64,
    /// Smoothness sweep: number of uniform times in [0, 1].
    #[arg(long, default_value_t = 101)]
    pub sweep_times: usize,
    /// Smoothness sweep: number of Gaussians (the first ones of the canonical set).
    #[arg(long, default_value_t = 1000)]
    pub sweep_gaussians: usize,
    #[command(flatten)]
    pub lpips: super::train::LpipsArgs,
}

/// The field configurations of a sweep: the paper's comparison (MLP D8 W256
/// vs CfC D6 W128 GELU), plus the ablations when asked.
fn fields(ablations: bool) -> Vec<FieldArgs> {
    let f = |field, depth, width, act: &str| FieldArgs {
        field,
        depth: Some(depth),
        width: Some(width),
        activation: (field == FieldArg::Cfc).then(|| act.to_string()),
        backbone_units: None,
        backbone_layers: None,
        six_dof: false,
        variant: None,
    };
    let mut v = vec![
        f(FieldArg::Mlp, 8, 256, "relu"),
        f(FieldArg::Cfc, 6, 128, "gelu"),
    ];
    if ablations {
        for d in [8, 10] {
            v.push(f(FieldArg::Cfc, d, 128, "gelu"));
        }
        for a in ["relu", "silu", "lecun_tanh", "tanh"] {
            v.push(f(FieldArg::Cfc, 6, 128, a));
        }
    }
    v
}

pub fn experiment(a: ExperimentArgs) -> Result<ExitCode> {
    if a.iterations == 0 || a.seeds.is_empty() {
        return Err(Error::invalid(
            "experiment",
            "need at least one iteration and one seed",
        ));
    }
    let scenes: Vec<(String, RunSpec)> = if a.data.is_empty() {
        a.scenes
            .iter()
            .map(|s| (s.clone(), spec(&a, None, Some(s.clone()))))
            .collect()
    } else {
        a.data
            .iter()
            .map(|d| {
                let name = d
                    .file_name()
                    .map_or("scene".into(), |n| n.to_string_lossy().to_string());
                (name, spec(&a, Some(d.clone()), None))
            })
            .collect()
    };
    let lpips = a.lpips.metric()?;
    let eval_every = (a.iterations / a.evals.max(1)).max(1);
    let meta = ReportMeta {
        command: std::env::args().collect::<Vec<_>>().join(" "),
        settings: settings(&a, eval_every),
        machine: MachineInfo::detect(),
        ablation_base: Default::default(),
    };
    let all_fields = fields(a.ablations);
    let mut plan = Vec::new();
    for (i, (scene, base)) in scenes.iter().enumerate() {
        let n = if i == 0 { all_fields.len() } else { 2 };
        for f in &all_fields[..n] {
            for &seed in &a.seeds {
                plan.push((
                    scene.clone(),
                    RunSpec {
                        field: f.clone(),
                        seed,
                        ..base.clone()
                    },
                ));
            }
        }
    }
    eprintln!(
        "experiment: {} runs of {} iterations into {}",
        plan.len(),
        a.iterations,
        a.out.display()
    );
    for (k, (scene, s)) in plan.iter().enumerate() {
        let data = s.load_dataset()?;
        let config = s.train_config(&data)?;
        s.check_eval_split(&data)?;
        let label = report::field_label(&config.field);
        let rec_path = report::record_path(&a.out, scene, &label, s.seed);
        if rec_path.exists() {
            eprintln!(
                "[{}/{}] {scene} {label} seed {}: done earlier, kept",
                k + 1,
                plan.len(),
                s.seed
            );
            continue;
        }
        eprintln!(
            "[{}/{}] {scene} {label} seed {}: training",
            k + 1,
            plan.len(),
            s.seed
        );
        let work = a
            .out
            .join("training")
            .join(format!("{scene}__{label}__seed{}", s.seed));
        let opts = RunOptions {
            out: work.clone(),
            checkpoint_every: (a.iterations / 4).max(1),
            eval_every,
            resume: true,
            data_name: s.data_name(),
            lpips: lpips.clone(),
        };
        let mut stages = StageTimes::default();
        let mut stage_n = 0u64;
        let clock = std::time::Instant::now();
        let summary = train::run::<f32>(&config, &data, &opts, &mut |e| match e {
            Event::Step(r) => {
                stages.add(&r.times);
                stage_n += 1;
                if r.iteration % (a.iterations / 10).max(1) == 0 {
                    eprintln!(
                        "  iteration {}/{}  loss {:.5}  gaussians {}",
                        r.iteration, a.iterations, r.loss, r.gaussians
                    );
                }
            }
            Event::Eval {
                iteration,
                psnr,
                lpips,
                ..
            } => eprintln!(
                "  iteration {iteration}: test PSNR {psnr:.3}{}",
                lpips.map_or(String::new(), |v| format!(", LPIPS {v:.4}"))
            ),
            Event::Resumed { iteration } => eprintln!("  resumed from iteration {iteration}"),
            Event::Checkpoint(_) => {}
        })?;
        let ckpt = checkpoint::latest(&work.join("checkpoints"))?.ok_or_else(|| {
            Error::invalid("experiment", format!("no checkpoint in {}", work.display()))
        })?;
        let binding = checkpoint::DataBinding::of(&data, &s.data_name());
        let trainer = checkpoint::load::<f32>(&ckpt, &config, &binding)?;
        let m = a.sweep_gaussians.min(trainer.model().gaussians.len());
        let smooth = report::temporal_smoothness(
            |t| match trainer.offsets(t) {
                Ok(o) => o.d_xyz[..3 * m].iter().map(|&v| v as f64).collect(),
                Err(_) => vec![f64::NAN; 3 * m],
            },
            &report::uniform_times(a.sweep_times),
        )?;
        let n = stage_n.max(1) as f64;
        let stage_ms: BTreeMap<String, f64> = StageTimes::NAMES
            .iter()
            .zip(stages.values())
            .map(|(name, v)| (name.to_string(), 1e3 * v / n))
            .collect();
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
        let record = RunRecord {
            scene: scene.clone(),
            field: label,
            kind: config.field.kind.name().into(),
            variant: config.field.variant.name().into(),
            depth: config.field.depth,
            width: config.field.width,
            activation: config.field.activation.name().into(),
            seed: s.seed,
            iterations: a.iterations as usize,
            resolution: [data.train[0].width, data.train[0].height],
            threads: rayon::current_num_threads(),
            params: param_count(&config.field)?,
            macs_per_gaussian: macs_per_gaussian(&config.field, MacConvention::Aten)?,
            final_gaussians: summary.gaussians,
            test_psnr: summary.psnr,
            test_ssim: summary.ssim,
            test_lpips: summary.lpips,
            lpips_info: lpips.as_ref().map(|m| m.info()),
            best: report::best_of_evaluations(&curves),
            ms_per_iteration: 1e3 * summary.train_seconds / summary.iterations_run.max(1) as f64,
            stage_ms,
            temporal_smoothness: Some(smooth),
            curves,
            wall_seconds: clock.elapsed().as_secs_f64(),
        };
        report::write_record(&a.out, &record)?;
        eprintln!(
            "  test PSNR {:.3} dB, SSIM {:.4}, smoothness {smooth:.4}",
            summary.psnr, summary.ssim
        );
        report::write_report(&a.out, &report::read_records(&a.out)?, &meta)?;
    }
    let records = report::read_records(&a.out)?;
    report::write_report(&a.out, &records, &meta)?;
    println!("report: {}", a.out.join("report.md").display());
    Ok(ExitCode::SUCCESS)
}

fn spec(a: &ExperimentArgs, data: Option<PathBuf>, scene: Option<String>) -> RunSpec {
    RunSpec {
        data,
        scene,
        resolution: a.resolution,
        frames: 24,
        init_points: a.init_points,
        downscale: a.downscale,
        white_background: false,
        field: fields(false).remove(1),
        iterations: a.iterations,
        seed: 0,
        precision: PrecisionArg::F32,
    }
}

fn settings(a: &ExperimentArgs, eval_every: u64) -> Vec<(String, String)> {
    let s = |k: &str, v: String| (k.to_string(), v);
    vec![
        s("precision", "f32".into()),
        s("background", "black".into()),
        s("initial points", format!("{} random (scenes without a point cloud)", a.init_points)),
        s("built-in scenes", format!("{}x{} pixels, 24 train / 8 test frames", a.resolution, a.resolution)),
        s("dataset folders", format!("downscale {}, test split", a.downscale)),
        s(
            "schedule",
            "upstream D-3DGS scaled to the iteration count (positions × s, intervals × √s, s = iterations / 40,000)".into(),
        ),
        s("test PSNR / SSIM / LPIPS", "8-bit quantised renders, mean over the test views (upstream metrics.py); LPIPS only with --lpips-vgg/--lpips-lin".into()),
        s(
            "periodic test evaluations",
            format!("every {eval_every} iterations and at the last one; the best of them is reported apart from the final metrics"),
        ),
        s(
            "smoothness sweep",
            format!(
                "d_xyz of the first {} canonical Gaussians of each trained model, {} uniform times in [0, 1]",
                a.sweep_gaussians, a.sweep_times
            ),
        ),
        s("ms per iteration", "wall clock of the training iterations run in the last process (resumed runs: the resumed part)".into()),
    ]
}
