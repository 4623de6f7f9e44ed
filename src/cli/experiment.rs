//! `liquid-splat experiment`: the arguments and progress output of
//! [`crate::experiment::Experiment`] (MLP vs liquid field on several scenes,
//! with identical seeds and settings except the field, and a report
//! folder). Rerunning the same command skips finished runs and resumes
//! unfinished ones.

use crate::error::{Error, Outcome, Result};
use crate::experiment::{Experiment, ExperimentEvent};
use crate::train::Event;
use clap::Args;
use std::path::PathBuf;

/// `--downscale` when dataset folders are given without it.
pub const DEFAULT_DOWNSCALE: usize = 4;

/// Arguments of `experiment`.
#[derive(Args)]
pub struct ExperimentArgs {
    /// Dataset folders (D-NeRF or NeRF-DS layout). Without any, the built-in scenes are used.
    pub data: Vec<PathBuf>,
    /// Built-in scenes to use when no dataset folder is given (refused with dataset folders).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "bouncing,swing,blob",
        conflicts_with = "data"
    )]
    pub scenes: Vec<String>,
    /// Report folder (runs, training folders, report.md, CSV, plots).
    #[arg(long, short)]
    pub out: PathBuf,
    /// Training iterations per run.
    #[arg(long, default_value_t = 1000)]
    pub iterations: u64,
    /// Built-in scenes: image size (refused with dataset folders).
    #[arg(long, default_value_t = 64, conflicts_with = "data")]
    pub resolution: usize,
    /// Dataset folders: downscale factor 1, 2, 4 or 8 (default 4; refused without dataset
    /// folders).
    #[arg(long)]
    pub downscale: Option<usize>,
    /// Random initial points (scenes without a point cloud).
    #[arg(long, default_value_t = super::DEFAULT_INIT_POINTS)]
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
    /// Smoothness sweep: number of uniform times in [0, 1] (3 to 100000).
    #[arg(long, default_value_t = 101)]
    pub sweep_times: usize,
    /// Smoothness sweep: number of Gaussians (the first ones of the canonical set).
    #[arg(long, default_value_t = 1000)]
    pub sweep_gaussians: usize,
    /// LPIPS weights for every evaluation.
    #[command(flatten)]
    pub lpips: super::train::LpipsArgs,
}

/// `experiment`: run the plan with one progress line per run, every tenth
/// of its iterations and every evaluation; print where the report is.
pub fn experiment(a: ExperimentArgs) -> Result<Outcome> {
    if a.downscale.is_some() && a.data.is_empty() {
        return Err(Error::invalid(
            "--downscale",
            "applies to dataset folders only; the built-in scenes are generated at --resolution",
        ));
    }
    let mut exp = Experiment {
        data: a.data,
        scenes: a.scenes,
        out: a.out,
        iterations: a.iterations,
        resolution: a.resolution,
        downscale: a.downscale.unwrap_or(DEFAULT_DOWNSCALE),
        init_points: a.init_points,
        seeds: a.seeds,
        ablations: a.ablations,
        evals: a.evals,
        sweep_times: a.sweep_times,
        sweep_gaussians: a.sweep_gaussians,
        lpips: None,
        command: std::env::args().collect::<Vec<_>>().join(" "),
    };
    // Unusable settings are refused before the LPIPS weights are read.
    exp.plan()?;
    exp.lpips = a.lpips.metric()?;
    let (iterations, out) = (exp.iterations, exp.out.clone());
    let report = exp.run(&mut |e| match e {
        ExperimentEvent::Planned { runs } => eprintln!(
            "experiment: {runs} runs of {iterations} iterations into {}",
            out.display()
        ),
        ExperimentEvent::Run {
            index,
            runs,
            run,
            label,
            kept,
        } => eprintln!(
            "[{}/{runs}] {} {label} seed {}: {}",
            index + 1,
            run.scene,
            run.spec.seed,
            if kept {
                "done earlier, kept"
            } else {
                "training"
            }
        ),
        ExperimentEvent::Train(Event::Step(r)) => {
            if r.iteration % (iterations / 10).max(1) == 0 {
                eprintln!(
                    "  iteration {}/{}  loss {:.5}  gaussians {}",
                    r.iteration, iterations, r.loss, r.gaussians
                );
            }
        }
        ExperimentEvent::Train(Event::Eval {
            iteration,
            psnr,
            lpips,
            ..
        }) => eprintln!(
            "  iteration {iteration}: test PSNR {psnr:.3}{}",
            lpips.map_or(String::new(), |v| format!(", LPIPS {v:.4}"))
        ),
        ExperimentEvent::Train(Event::Resumed { iteration }) => {
            eprintln!("  resumed from iteration {iteration}")
        }
        ExperimentEvent::Train(Event::Checkpoint(_)) => {}
        ExperimentEvent::Finished(r) => eprintln!(
            "  test PSNR {:.3} dB, SSIM {:.4}, smoothness {:.4}",
            r.test_psnr,
            r.test_ssim,
            r.temporal_smoothness.unwrap_or(f64::NAN)
        ),
    })?;
    outln!("report: {}", report.display());
    Ok(Outcome::Success)
}
