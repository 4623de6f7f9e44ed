//! The `liquid-splat` command-line tool: a thin layer over the library. This
//! is the only place errors become messages and exit codes.
//!
//! Exit codes: 0 success; 1 a check or comparison failed; 2 unusable input
//! (bad arguments, missing or malformed files).

use clap::{Parser, Subcommand};
use liquid_splat::io::TensorFile;
use liquid_splat::render::{self, check, scene};
use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

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
    /// Central-difference gradient checks in f64.
    Gradcheck {
        #[command(subcommand)]
        what: GradcheckWhat,
    },
    /// Timings.
    Bench {
        #[command(subcommand)]
        what: BenchWhat,
    },
    /// Oracle case files.
    Case {
        #[command(subcommand)]
        what: CaseWhat,
    },
}

#[derive(Subcommand)]
enum GradcheckWhat {
    /// The rasterizer's gradients on built-in random scenes (exit 1 if any
    /// relative error exceeds 1e-6).
    Raster {
        #[arg(long, default_value_t = 7)]
        seed: u64,
    },
}

#[derive(Subcommand)]
enum BenchWhat {
    /// Rasterizer forward and backward at 800x800/50k and 400x400/20k Gaussians, 1 and 2 threads.
    Raster {
        /// Repetitions per measurement (the median is reported).
        #[arg(long, default_value_t = 3)]
        reps: usize,
    },
}

#[derive(Subcommand)]
enum CaseWhat {
    /// Run the stage a case file names and write the outputs.
    Run { input: PathBuf, output: PathBuf },
}

fn main() -> ExitCode {
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
    let res = match cli.command {
        Command::Gradcheck {
            what: GradcheckWhat::Raster { seed },
        } => gradcheck_raster(seed),
        Command::Bench {
            what: BenchWhat::Raster { reps },
        } => bench_raster(reps),
        Command::Case {
            what: CaseWhat::Run { input, output },
        } => case_run(&input, &output),
    };
    match res {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}

fn gradcheck_raster(seed: u64) -> liquid_splat::Result<ExitCode> {
    let mut ok = true;
    println!(
        "{:<22} {:<16} {:>6} {:>11} {:>11}",
        "case (scene seed)", "input", "n", "max abs", "max rel"
    );
    for case in check::builtin_cases(seed) {
        match check::run_case(&case)? {
            None => {
                println!(
                    "{:<22} no scene away from discontinuities in 20 draws",
                    case.name
                );
                ok = false;
            }
            Some(r) => {
                for g in &r.groups {
                    let pass = g.passes(check::REL_TOL);
                    ok &= pass;
                    println!(
                        "{:<22} {:<16} {:>6} {:>11.3e} {:>11.3e}{}",
                        format!("{} ({})", r.name, r.seed),
                        g.name,
                        g.count,
                        g.max_abs,
                        g.max_rel,
                        if pass { "" } else { "  FAIL" }
                    );
                }
            }
        }
    }
    println!(
        "tolerance: relative {:e}; {}",
        check::REL_TOL,
        if ok { "all passed" } else { "FAILED" }
    );
    Ok(if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::from(1)
    })
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn bench_raster(reps: usize) -> liquid_splat::Result<ExitCode> {
    let reps = reps.max(1);
    println!(
        "machine threads: {}",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    println!(
        "{:<18} {:>7} {:>12} {:>12} {:>14} {:>14}",
        "scene", "threads", "forward ms", "backward ms", "fwd pairs/s", "bwd pairs/s"
    );
    for (w, h, n) in [(800usize, 800usize, 50_000usize), (400, 400, 20_000)] {
        let s = scene::random_scene(&scene::SceneSpec::bench(w, h, n, 1))?.cast::<f32>();
        let input = s.input(scene::ColorSource::Sh, scene::CovSource::ScaleRotation);
        let grad: Vec<f32> = liquid_splat::math::gradcheck::cotangent(5, 3 * w * h)
            .into_iter()
            .map(|v| v as f32)
            .collect();
        for threads in [1usize, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .map_err(|e| liquid_splat::Error::invalid("thread pool", e.to_string()))?;
            let (fwd, bwd, pairs) = pool.install(|| -> liquid_splat::Result<_> {
                let mut f = Vec::new();
                let mut b = Vec::new();
                let mut pairs = 0;
                for _ in 0..reps {
                    let t0 = Instant::now();
                    let (_, state) = render::rasterize(&input)?;
                    f.push(t0.elapsed().as_secs_f64());
                    pairs = state.tile_pairs();
                    let t1 = Instant::now();
                    render::rasterize_backward(
                        &input,
                        &state,
                        &grad,
                        None,
                        render::GradientMode::Exact,
                    )?;
                    b.push(t1.elapsed().as_secs_f64());
                }
                Ok((median(f), median(b), pairs))
            })?;
            println!(
                "{:<18} {:>7} {:>12.1} {:>12.1} {:>14.3e} {:>14.3e}",
                format!("{w}x{h} {n}"),
                threads,
                fwd * 1e3,
                bwd * 1e3,
                pairs as f64 / fwd,
                pairs as f64 / bwd
            );
        }
    }
    println!("(pairs: pixels x entries of their tile list, an upper bound on evaluated pairs; f32, SH degree 3)");
    Ok(ExitCode::SUCCESS)
}

fn case_run(input: &PathBuf, output: &PathBuf) -> liquid_splat::Result<ExitCode> {
    let case = TensorFile::load(input)?;
    let stage = case.meta("stage")?;
    if stage != liquid_splat::oracle::rasterize::STAGE {
        eprintln!(
            "error: {}: stage `{stage}` is not handled here (known: {})",
            input.display(),
            liquid_splat::oracle::rasterize::STAGE
        );
        return Ok(ExitCode::from(2));
    }
    let mut out = liquid_splat::oracle::rasterize::run(&case)?;
    out.path = output.clone();
    out.save(output)?;
    Ok(ExitCode::SUCCESS)
}
