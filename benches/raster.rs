//! Rasterizer forward and backward (f32, SH degree 3) at 800x800 with 50,000
//! Gaussians, 400x400 with 20,000 and 64x64 with 2,600, on 1 and 2 threads.

use criterion::{criterion_group, criterion_main, Criterion};
use liquid_splat::render::scene::{random_scene, ColorSource, CovSource, SceneSpec};
use liquid_splat::render::{rasterize, rasterize_vjp, GradientMode};

fn bench(c: &mut Criterion) {
    println!(
        "machine threads: {}",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    let mut group = c.benchmark_group("raster");
    group.sample_size(10);
    for (w, h, n) in [
        (64usize, 64usize, 2_600usize),
        (400, 400, 20_000),
        (800, 800, 50_000),
    ] {
        let s = random_scene(&SceneSpec::bench(w, h, n, 1))
            .unwrap()
            .cast::<f32>();
        let input = s.input(ColorSource::Sh, CovSource::ScaleRotation);
        let grad: Vec<f32> = liquid_splat::math::gradcheck::cotangent(5, 3 * w * h)
            .into_iter()
            .map(|v| v as f32)
            .collect();
        for threads in [1usize, 2] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let (_, state) = pool.install(|| rasterize(&input).unwrap());
            println!(
                "{w}x{h} {n}: {} (pixel, Gaussian) pairs evaluated, {} in the tile lists",
                state.pairs_evaluated(),
                state.tile_pairs()
            );
            group.bench_function(format!("forward {w}x{h} {n} t{threads}"), |b| {
                b.iter(|| pool.install(|| rasterize(&input).unwrap()))
            });
            group.bench_function(format!("backward {w}x{h} {n} t{threads}"), |b| {
                b.iter(|| {
                    pool.install(|| {
                        rasterize_vjp(&input, &state, &grad, None, GradientMode::Exact).unwrap()
                    })
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
