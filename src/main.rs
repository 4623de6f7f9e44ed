//! The `liquid-splat` command-line tool: a thin layer over the library. This
//! is the only place errors become messages and exit codes.
//!
//! Exit codes: 0 success; 1 a check or comparison failed; 2 unusable input
//! (bad arguments, missing or malformed files).

use clap::{Parser, Subcommand};
use std::process::ExitCode;

mod cli;

#[derive(Parser)]
#[command(
    name = "liquid-splat",
    version,
    about = "Deterministic CPU reference for deformable 3D Gaussian splatting with a liquid (CfC) deformation field"
)]
struct Cli {
    /// Worker threads (default: all cores). Results are bit-identical for any value.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Oracle case files: run a stage, compare outputs.
    Case {
        #[command(subcommand)]
        command: cli::case::CaseCommand,
    },
    /// Central-difference gradient checks in f64.
    Gradcheck {
        #[command(subcommand)]
        what: cli::gradcheck::GradcheckWhat,
    },
    /// Load a dataset (D-NeRF or nerfies layout) and print a JSON summary.
    Inspect(cli::data::InspectArgs),
    /// Generate a built-in synthetic dynamic scene (bouncing, swing, blob) on disk.
    Synth(cli::data::SynthArgs),
    /// Train a deformable Gaussian model (liquid CfC or MLP field) on a dataset or built-in scene.
    Train(cli::train::TrainArgs),
    /// Render a trained run's test views, a time sweep and any times (PNG and EXR).
    Render(cli::train::RenderArgs),
    /// PSNR, SSIM (and LPIPS with weights) of a run's saved renders (results.json, per_view.json).
    Eval(cli::train::EvalArgs),
    /// The deformed Gaussians of a trained run at given times, as Inria PLY files.
    Export(cli::train::ExportArgs),
    /// Train and compare the MLP and liquid fields on several scenes; write a report folder.
    Experiment(cli::experiment::ExperimentArgs),
    /// Parameters and MACs of a deformation field (ptflops conventions).
    Count(cli::count::CountArgs),
    /// Throughput measurements.
    Bench {
        #[command(subcommand)]
        what: cli::bench::BenchWhat,
    },
}

/// Print a library error as one line and map it to exit code 2.
fn report(result: liquid_splat::Result<ExitCode>) -> ExitCode {
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}

/// Keep freed memory in the process instead of returning it to the
/// operating system (glibc only): the fields and the rasterizer allocate and
/// free buffers of tens of MB every pass, and fresh pages from the kernel
/// cost a page fault each (measured: more than half the time of a 20000×64
/// by 64×512 product). Large blocks come from the heap (no `mmap`), and the
/// heap is never trimmed. Changes speed only, never results.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn keep_freed_memory() {
    extern "C" {
        fn mallopt(param: i32, value: i32) -> i32;
    }
    const M_TRIM_THRESHOLD: i32 = -1;
    const M_MMAP_MAX: i32 = -4;
    // SAFETY: mallopt only changes allocator tuning; called before any
    // thread is started.
    unsafe {
        mallopt(M_MMAP_MAX, 0);
        mallopt(M_TRIM_THRESHOLD, i32::MAX);
    }
}
#[cfg(not(all(target_os = "linux", target_env = "gnu")))]
fn keep_freed_memory() {}

fn main() -> ExitCode {
    keep_freed_memory();
    let cli = Cli::parse();
    if let Some(n) = cli.threads {
        if let Err(e) = rayon::ThreadPoolBuilder::new()
            .num_threads(n.max(1))
            .build_global()
        {
            eprintln!("error: cannot start {n} threads: {e}");
            return ExitCode::from(2);
        }
    }
    match cli.command {
        Command::Case { command } => cli::case::run(command),
        Command::Gradcheck { what } => report(cli::gradcheck::run(what)),
        Command::Train(a) => report(cli::train::train(a)),
        Command::Render(a) => report(cli::train::render(a)),
        Command::Eval(a) => report(cli::train::eval(a)),
        Command::Export(a) => report(cli::train::export(a)),
        Command::Experiment(a) => report(cli::experiment::experiment(a)),
        Command::Bench { what } => report(cli::bench::run(what)),
        Command::Count(a) => report(cli::count::run(a)),
        Command::Inspect(a) => report(cli::data::inspect(a)),
        Command::Synth(a) => report(cli::data::synth(a)),
    }
}
