//! Deformation fields, f32, N = 20,000 Gaussians, 2 threads: forward and
//! forward+backward of the MLP (D8 W256) and the CfC field (D6 W128), the
//! workloads of `liquid-splat bench deform` (see benches/README.md).

use criterion::{criterion_group, criterion_main, Criterion};
use liquid_splat::deform::{Deformation, Field, FieldConfig, FieldKind};
use liquid_splat::math::gradcheck::cotangent;
use liquid_splat::math::Rng;

const N: usize = 20_000;

fn bench(c: &mut Criterion) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let mut r = Rng::new(11);
    let xyz: Vec<f32> = (0..3 * N)
        .map(|_| r.uniform_range(-1.3, 1.3) as f32)
        .collect();
    let t: Vec<f32> = (0..N).map(|_| r.uniform() as f32).collect();
    let cast = |v: Vec<f64>| v.into_iter().map(|x| x as f32).collect::<Vec<f32>>();
    let g = Deformation {
        d_xyz: cast(cotangent(12, 3 * N)),
        d_rotation: cast(cotangent(13, 4 * N)),
        d_scaling: cast(cotangent(14, 3 * N)),
    };
    let mut group = c.benchmark_group("deform");
    group.sample_size(10);
    for (name, kind) in [
        ("mlp D8 W256", FieldKind::Mlp),
        ("cfc D6 W128", FieldKind::Cfc),
    ] {
        let field = Field::<f32>::new(FieldConfig::new(kind), 0).unwrap();
        group.bench_function(format!("forward {name} N{N} t2"), |b| {
            b.iter(|| pool.install(|| field.forward(&xyz, &t).unwrap()))
        });
        group.bench_function(format!("forward+backward {name} N{N} t2"), |b| {
            b.iter(|| {
                pool.install(|| {
                    let (_, cache) = field.forward(&xyz, &t).unwrap();
                    field.backward(&cache, &g).unwrap()
                })
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
