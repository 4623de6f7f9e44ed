//! The `liquid-splat` command-line tool as a library function, [`run`], so
//! that the binary and the Python package (`python -m liquid_splat`) run the
//! same tool. Argument parsing, progress and messages only; the work is done
//! by the library ([`crate::experiment`] for training runs and experiments,
//! [`crate::bench`] for the measurements). Every subcommand returns a
//! [`crate::Result`]`<`[`Outcome`]`>`; [`run`] prints an error as one line and
//! maps the result to an exit code with [`crate::error::exit_code`].
//!
//! Exit codes: 0 success; 1 a check or comparison failed; 2 unusable input
//! (bad arguments, missing or malformed files).

pub mod benchmark;
pub mod case;
pub mod count;
pub mod data;
pub mod experiment;
pub mod gradcheck;
pub mod train;

use crate::error::{exit_code, Outcome, EXIT_SUCCESS, EXIT_UNUSABLE_INPUT};
use crate::Error;
use clap::{Parser, Subcommand};
use std::ffi::OsString;

#[derive(Parser)]
#[command(
    name = "liquid-splat",
    version,
    about = "Deterministic CPU reference for deformable 3D Gaussian splatting with a liquid (CfC) deformation field"
)]
struct Cli {
    /// Worker threads, 1 to 1024 (default: all cores). Results are bit-identical for any value.
    #[arg(long, global = true)]
    threads: Option<usize>,
    /// Pin worker i to the i-th CPU the process may use, wrapping (Linux; speed only, never
    /// results). Off by default: pinned processes started side by side would share CPUs.
    #[arg(long, global = true)]
    pin_threads: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Oracle case files: run a stage, compare outputs.
    Case {
        #[command(subcommand)]
        command: case::CaseCommand,
    },
    /// Central-difference gradient checks in f64.
    Gradcheck {
        #[command(subcommand)]
        what: gradcheck::GradcheckWhat,
    },
    /// Load a dataset (D-NeRF or nerfies layout) and print a JSON summary.
    Inspect(data::InspectArgs),
    /// Generate a built-in synthetic dynamic scene (bouncing, swing, blob) on disk.
    Synth(data::SynthArgs),
    /// Train a deformable Gaussian model (liquid CfC or MLP field) on a dataset or built-in scene.
    Train(train::TrainArgs),
    /// Render a trained run's test views, a time sweep and any times (PNG and EXR).
    Render(train::RenderArgs),
    /// PSNR, SSIM (and LPIPS with weights) of a run's saved renders (results.json, per_view.json).
    Eval(train::EvalArgs),
    /// The deformed Gaussians of a trained run at given times, as Inria PLY files.
    Export(train::ExportArgs),
    /// Train and compare the MLP and liquid fields on several scenes; write a report folder.
    Experiment(experiment::ExperimentArgs),
    /// Parameters and MACs of a deformation field (ptflops conventions).
    Count(count::CountArgs),
    /// Throughput measurements.
    Bench {
        #[command(subcommand)]
        what: benchmark::BenchWhat,
    },
}

/// The payload of the unwind that ends a command whose standard output
/// cannot be written (closed, or any other write error). On Unix a closed
/// pipe never gets here (SIGPIPE ends the binary first, as it ends other
/// tools); otherwise the binary exits quietly with 141 for a closed output,
/// as a shell reports a process that SIGPIPE ended, and with a message and
/// [`EXIT_UNUSABLE_INPUT`] for other errors. The Python package's `cli`
/// raises `BrokenPipeError` or `OSError` with the error's errno, as
/// Python's own `print` does.
#[derive(Debug)]
pub struct StdoutError(pub std::io::Error);

/// Write the tool's output to standard output (what `outln!` expands to).
/// A write error unwinds with [`StdoutError`] without running the panic
/// hook (nothing is printed about a closed output), instead of the panic
/// of `println!`.
pub fn print_out(args: std::fmt::Arguments<'_>) {
    use std::io::Write;
    if let Err(e) = std::io::stdout().lock().write_fmt(args) {
        std::panic::resume_unwind(Box::new(StdoutError(e)));
    }
}

/// `--init-points`' default (`train`, `experiment`, `inspect`): random initial
/// points for a scene without a point cloud (upstream's 100,000; fewer keep
/// CPU runs fast, densification adds more where needed).
pub const DEFAULT_INIT_POINTS: usize = 2000;

/// The most worker threads `--threads` accepts (far above any core count
/// the tool is run on; each thread is an OS thread with its own stack).
pub const MAX_THREADS: usize = 1024;

/// The exit code of a subcommand's result, after printing its error (if
/// any) as one line on stderr.
fn finish(result: crate::Result<Outcome>) -> u8 {
    if let Err(e) = &result {
        eprintln!("error: {e}");
    }
    exit_code(&result)
}

/// Run the command-line tool on `args` (the first item is the program
/// name) and return its exit code. `--threads N` runs the command on a pool
/// of its own with `N` workers (results are bit-identical for any `N`);
/// without it, on rayon's global pool. Help and usage errors are printed as
/// clap prints them (usage errors exit with 2).
pub fn run<I, T>(args: I) -> u8
where
    I: IntoIterator<Item = T>,
    T: Into<OsString> + Clone,
{
    let cli = match Cli::try_parse_from(args) {
        Ok(cli) => cli,
        Err(e) => {
            // Help and version requests are successes; usage errors are
            // unusable input. clap prints both itself.
            let code = e.exit_code();
            let _ = e.print();
            return if code == 0 {
                EXIT_SUCCESS
            } else {
                EXIT_UNUSABLE_INPUT
            };
        }
    };
    // The CPUs to pin to are read here, before any worker is pinned (a
    // pinned worker sees only its own CPU).
    crate::threads::set_pinning(cli.pin_threads);
    if let Some(n) = cli.threads {
        if !(1..=MAX_THREADS).contains(&n) {
            return finish(Err(Error::invalid(
                "--threads",
                format!("{n} (expected 1 to {MAX_THREADS})"),
            )));
        }
    }
    // Pinned, the command runs on this thread with rayon's global pool
    // pinned (so that the benchmarks' own pools and threads are not started
    // from a pinned worker); if that pool already runs (a second call in one
    // process), on a pool of its own as without pinning.
    let global = cli.pin_threads && crate::threads::pin_global_pool(cli.threads);
    if cli.pin_threads && !global && (cli.threads.is_none() || !cfg!(target_os = "linux")) {
        eprintln!(
            "note: --pin-threads: {}",
            if cfg!(target_os = "linux") {
                "this process's worker pool was already running (or its CPUs could not be \
                 read) and stays unpinned; add --threads N for a new, pinned pool"
            } else {
                "pinning is available on Linux only; the threads stay unpinned"
            }
        );
    }
    finish(match cli.threads {
        Some(n) if !global => match crate::threads::pool(n) {
            Ok(pool) => pool.install(|| dispatch(cli.command)),
            Err(e) => Err(Error::invalid(
                "--threads",
                format!("{n}: cannot start {n} threads: {e}"),
            )),
        },
        _ => dispatch(cli.command),
    })
}

fn dispatch(command: Command) -> crate::Result<Outcome> {
    match command {
        Command::Case { command } => case::run(command),
        Command::Gradcheck { what } => gradcheck::run(what),
        Command::Train(a) => train::train(a),
        Command::Render(a) => train::render(a),
        Command::Eval(a) => train::eval(a),
        Command::Export(a) => train::export(a),
        Command::Experiment(a) => experiment::experiment(a),
        Command::Bench { what } => benchmark::run(what),
        Command::Count(a) => count::run(a),
        Command::Inspect(a) => data::inspect(a),
        Command::Synth(a) => data::synth(a),
    }
}
