//! `liquid-splat bench ...`: throughput measurements (never asserted in tests).

use clap::Subcommand;
use liquid_splat::render::{self, scene};
use std::process::ExitCode;
use std::time::Instant;

#[derive(Subcommand)]
pub enum BenchWhat {
    /// Rasterizer forward and backward at 800x800/50k and 400x400/20k Gaussians, 1 and 2 threads.
    Raster {
        /// Repetitions per measurement (the median is reported).
        #[arg(long, default_value_t = 3)]
        reps: usize,
    },
}

/// Run a `bench` subcommand.
pub fn run(what: BenchWhat) -> liquid_splat::Result<ExitCode> {
    match what {
        BenchWhat::Raster { reps } => bench_raster(reps),
    }
}

pub(crate) fn median(mut v: Vec<f64>) -> f64 {
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
