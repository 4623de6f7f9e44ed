//! The 64×64 frame of `bench raster` repeated, against frames that change
//! from one pass to the next as they do in training
//! (`cargo bench --bench frames`), on 1 and 2 pinned threads:
//!
//! - **repeated**: each of eight random scenes (seeds 1 to 8, 2,600
//!   Gaussians, f32, SH degree 3) rendered and differentiated `PASSES`
//!   times in a row, as `bench raster` does with one; per scene the
//!   fastest forward, backward and binning (with the gather), averaged
//!   over the scenes.
//! - **in turn**: the same eight scenes taken in turn, `PASSES` passes
//!   each; the same statistics.
//! - **training**: 1,000 iterations of the `swing` fixture scene (CfC
//!   field, 64×64), the median per iteration of the rasterizer's forward
//!   and backward and of the binning (with the gather).
//!
//! The binning column is the stages `bin` and `gather`. On two threads
//! these frames sort each worker's run of the Gaussians inside the
//! projection (`render::project_and_bin_in_two_runs`), so there it holds
//! the merge of the two runs and the gather only.
//!
//! The passes' forwards run with the stage clock on (`render::stages`),
//! so their times include its clock reads (a few µs), which `bench
//! raster` leaves out of its timed runs; training runs inside its step's
//! `threads::keep_awake`, the passes do not.
//!
//! A repeated frame leaves its inputs in the core's caches and its
//! branches' outcomes in the branch predictor's history; a frame that
//! changes does neither (benches/README.md, "Repeated frames and training").
use clap::Parser;
use liquid_splat::render::{self, scene, stages};
use std::time::Instant;

const PASSES: usize = 500;
const SCENES: u64 = 8;

#[derive(Parser)]
struct Run {
    #[command(flatten)]
    run: liquid_splat::cli::train::RunArgs,
}

fn ms(d: std::time::Duration) -> f64 {
    d.as_secs_f64() * 1e3
}

/// The milliseconds of the stages named in `names` among `stages` (0 if
/// absent).
fn stage_ms(stages: &[stages::StageTime], names: &[&str]) -> f64 {
    stages
        .iter()
        .filter(|s| names.contains(&s.name))
        .fold(0.0, |sum, s| sum + s.wall * 1e3)
}

/// The stages of the binning and the gather.
const BINNING: [&str; 2] = ["bin", "gather"];

/// Per scene, the fastest forward, backward and binning (with the gather) over `PASSES`
/// passes of it, the scenes taken in turn (`in_turn`) or each repeated
/// `PASSES` times in a row; each averaged over the scenes.
fn passes(scenes: &[scene::Scene<f32>], grad: &[f32], in_turn: bool) -> [f64; 3] {
    let inputs: Vec<_> = scenes
        .iter()
        .map(|s| s.input(scene::ColorSource::Sh, scene::CovSource::ScaleRotation))
        .collect();
    let mut best = vec![[f64::MAX; 3]; scenes.len()];
    let n = scenes.len();
    for i in 0..PASSES * n {
        let k = if in_turn { i % n } else { i / PASSES };
        let t0 = Instant::now();
        let ((_, saved), st) = stages::record(|| render::rasterize(&inputs[k]).unwrap());
        let t1 = Instant::now();
        let g = render::rasterize_vjp(&inputs[k], &saved, grad, None, render::GradientMode::Exact);
        let t2 = Instant::now();
        std::hint::black_box(g.unwrap());
        let b = &mut best[k];
        b[0] = b[0].min(ms(t1 - t0));
        b[1] = b[1].min(ms(t2 - t1));
        b[2] = b[2].min(stage_ms(&st, &BINNING));
    }
    std::array::from_fn(|j| best.iter().map(|b| b[j]).sum::<f64>() / best.len() as f64)
}

/// Medians per iteration of 1,000 iterations on `swing`: forward,
/// backward, binning with the gather (ms).
fn training() -> [f64; 3] {
    use liquid_splat::train::run;
    let a = Run::parse_from(["frames", "fixtures/scenes/swing", "--iterations", "1000"]);
    let spec = a.run.spec();
    let data = spec.load_dataset().expect("the swing fixture scene");
    let config = spec.train_config(&data).unwrap();
    let views = run::views::<f32>(&data.train);
    let mut trainer = run::new_trainer::<f32>(&config, &data).unwrap();
    let mut v: [Vec<f64>; 3] = Default::default();
    while trainer.iteration() < config.iterations {
        let (r, st) = stages::record(|| trainer.step(&views).unwrap());
        v[0].push(r.times.raster_forward * 1e3);
        v[1].push(r.times.raster_backward * 1e3);
        v[2].push(stage_ms(&st, &BINNING));
    }
    v.map(liquid_splat::bench::harness::median)
}

fn main() {
    liquid_splat::memory::keep_freed_memory();
    liquid_splat::threads::set_pinning(true);
    let (w, h, n) = (64, 64, 2600);
    let scenes: Vec<scene::Scene<f32>> = (1..=SCENES)
        .map(|seed| {
            scene::random_scene(&scene::SceneSpec::bench(w, h, n, seed))
                .unwrap()
                .cast::<f32>()
        })
        .collect();
    let grad: Vec<f32> = liquid_splat::math::gradcheck::cotangent(5, 3 * w * h)
        .into_iter()
        .map(|v| v as f32)
        .collect();
    println!("64x64, {n} Gaussians, f32, ms: forward / backward / binning and gather");
    let mut rows = Vec::new();
    for threads in [1, 2] {
        let pool = liquid_splat::threads::pool(threads).unwrap();
        let rep = pool.install(|| passes(&scenes, &grad, false));
        let rot = pool.install(|| passes(&scenes, &grad, true));
        let tr = pool.install(training);
        println!(
            "{threads} thread(s): repeated {:.4} / {:.4} / {:.4}; in turn {:.4} / {:.4} / {:.4}; \
             training (swing, medians) {:.4} / {:.4} / {:.4}",
            rep[0], rep[1], rep[2], rot[0], rot[1], rot[2], tr[0], tr[1], tr[2]
        );
        rows.push((rep, rot, tr));
    }
    let (r1, r2) = (&rows[0], &rows[1]);
    println!(
        "2 threads over 1, forward / backward: repeated {:.2}x / {:.2}x; in turn {:.2}x / {:.2}x; \
         training {:.2}x / {:.2}x",
        r1.0[0] / r2.0[0],
        r1.0[1] / r2.0[1],
        r1.1[0] / r2.1[0],
        r1.1[1] / r2.1[1],
        r1.2[0] / r2.2[0],
        r1.2[1] / r2.2[1]
    );
}
