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
    /// Milliseconds per training iteration split by stage, on a dataset or built-in scene.
    Train {
        #[command(flatten)]
        spec: super::train::RunSpec,
    },
}

/// Run a `bench` subcommand.
pub fn run(what: BenchWhat) -> liquid_splat::Result<ExitCode> {
    match what {
        BenchWhat::Raster { reps } => bench_raster(reps),
        BenchWhat::Train { spec } => match spec.precision {
            super::train::PrecisionArg::F32 => bench_train::<f32>(&spec),
            super::train::PrecisionArg::F64 => bench_train::<f64>(&spec),
        },
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

/// Train in memory (no files) and print the mean time of each stage, over
/// all iterations and over those with the field on.
fn bench_train<T: liquid_splat::math::Real>(
    spec: &super::train::RunSpec,
) -> liquid_splat::Result<ExitCode> {
    use liquid_splat::dataset::init::initial_gaussians;
    use liquid_splat::train::{run, StageTimes, Trainer};
    let data = spec.load_dataset()?;
    let config = spec.train_config(&data)?;
    let views = run::views::<T>(&data.train);
    let bg = [if data.white_background { 1.0 } else { 0.0 }; 3];
    let g = initial_gaussians::<T>(&data.init)?;
    let mut trainer = Trainer::new(config.clone(), g, views.len(), data.scene_extent, bg)?;
    let (mut all, mut active) = (StageTimes::default(), StageTimes::default());
    let (mut n_active, mut gaussians) = (0u64, 0u64);
    let t0 = Instant::now();
    while trainer.iteration < config.iterations {
        let r = trainer.step(&views)?;
        all.add(&r.times);
        gaussians += r.gaussians as u64;
        if trainer.field_active(r.iteration) {
            active.add(&r.times);
            n_active += 1;
        }
    }
    let total = t0.elapsed().as_secs_f64();
    let n = config.iterations;
    let (w, h) = (data.train[0].width, data.train[0].height);
    println!(
        "{} on {} ({w}x{h}, {} views), {} iterations, {}, {} threads, mean {:.0} Gaussians",
        liquid_splat::report::field_label(&config.field),
        spec.data_name(),
        views.len(),
        n,
        if T::PRECISION == liquid_splat::math::Precision::F32 {
            "f32"
        } else {
            "f64"
        },
        rayon::current_num_threads(),
        gaussians as f64 / n as f64
    );
    println!(
        "{:<16} {:>14} {:>18}",
        "stage", "ms/it (all)", "ms/it (field on)"
    );
    for (i, name) in StageTimes::NAMES.iter().enumerate() {
        println!(
            "{:<16} {:>14.2} {:>18.2}",
            name,
            1e3 * all.values()[i] / n as f64,
            1e3 * active.values()[i] / n_active.max(1) as f64
        );
    }
    println!(
        "{:<16} {:>14.2} {:>18.2}",
        "total",
        1e3 * total / n as f64,
        1e3 * active.values().iter().sum::<f64>() / n_active.max(1) as f64
    );
    Ok(ExitCode::SUCCESS)
}
