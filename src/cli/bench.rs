//! `liquid-splat bench ...`: throughput measurements (never asserted in tests).

use crate::deform::count::{macs_per_gaussian, MacConvention};
use crate::deform::{Deformation, Field, FieldConfig, FieldKind};
use crate::lpips;
use crate::math::{gradcheck::cotangent, Real, Rng};
use crate::render::{self, scene};
use clap::Subcommand;
use std::process::ExitCode;
use std::time::Instant;

#[derive(Subcommand)]
pub enum BenchWhat {
    /// Rasterizer forward and backward at 800x800/50k, 400x400/20k and 64x64/2.6k Gaussians,
    /// on 1 thread and all cores: ms, pairs evaluated, pairs/s and % of the FMA peak.
    Raster {
        /// Repetitions per measurement (the minimum is reported).
        #[arg(long, default_value_t = 3)]
        reps: usize,
    },
    /// Milliseconds per training iteration split by stage, on a dataset or built-in scene.
    Train {
        #[command(flatten)]
        spec: super::train::RunSpec,
    },
    /// Deformation fields forward and forward+backward (MLP D8 W256, CfC D6 W128), f32.
    Deform {
        /// Number of Gaussians.
        #[arg(long, default_value_t = 20_000)]
        n: usize,
        /// Repetitions per measurement (the median is reported).
        #[arg(long, default_value_t = 5)]
        reps: usize,
        /// Run in f64 instead of f32.
        #[arg(long)]
        f64: bool,
        /// Only this field (mlp or cfc); both by default.
        #[arg(long)]
        field: Option<String>,
    },
    /// LPIPS (VGG16) of one image pair: milliseconds per pair and the convolutions' GFLOP/s.
    Lpips {
        /// Image width and height.
        #[arg(long, default_value_t = 800)]
        size: usize,
        /// Repetitions (the median is reported).
        #[arg(long, default_value_t = 3)]
        reps: usize,
        /// Run in f64 instead of f32.
        #[arg(long)]
        f64: bool,
        /// torchvision's vgg16-397923af.pth and the lpips package's vgg.pth; without them,
        /// random weights of the same shapes (the time does not depend on the values).
        #[arg(long, num_args = 2, value_names = ["VGG16_PTH", "LIN_PTH"])]
        weights: Option<Vec<std::path::PathBuf>>,
    },
}

/// Run a `bench` subcommand.
pub fn run(what: BenchWhat) -> crate::Result<ExitCode> {
    match what {
        BenchWhat::Raster { reps } => bench_raster(reps),
        BenchWhat::Train { spec } => match spec.precision {
            super::train::PrecisionArg::F32 => bench_train::<f32>(&spec),
            super::train::PrecisionArg::F64 => bench_train::<f64>(&spec),
        },
        BenchWhat::Deform {
            n,
            reps,
            f64,
            field,
        } => {
            let only = field.as_deref().map(FieldKind::parse).transpose()?;
            if f64 {
                bench_deform::<f64>(n, reps, only)
            } else {
                bench_deform::<f32>(n, reps, only)
            }
        }
        BenchWhat::Lpips {
            size,
            reps,
            f64,
            weights,
        } => {
            let w = match weights.as_deref() {
                Some([vgg, lin]) => lpips::LpipsWeights::load(vgg, lin, lpips::Verify::Any)?,
                _ => random_lpips_weights(0)?,
            };
            if f64 {
                bench_lpips::<f64>(&w, size, reps)
            } else {
                bench_lpips::<f32>(&w, size, reps)
            }
        }
    }
}

/// LPIPS weights of the right shapes with uniform random values (for timing only).
fn random_lpips_weights(seed: u64) -> crate::Result<lpips::LpipsWeights> {
    let mut r = Rng::new(seed);
    let mut u =
        |n: usize, s: f64| -> Vec<f32> { (0..n).map(|_| r.uniform_range(-s, s) as f32).collect() };
    let convs = lpips::VGG16_CONVS
        .iter()
        .map(|&(cin, cout)| {
            (
                u(cout * cin * 9, (6.0 / (9 * cin) as f64).sqrt()),
                u(cout, 0.05),
            )
        })
        .collect();
    let lins = lpips::LAYER_CHANNELS.iter().map(|&c| u(c, 0.1)).collect();
    let id = || lpips::WeightFile {
        path: "random weights (benchmark)".into(),
        sha256: String::new(),
        official: false,
    };
    lpips::LpipsWeights::from_parts(convs, lins, id(), id())
}

fn bench_lpips<T: Real>(
    w: &lpips::LpipsWeights,
    size: usize,
    reps: usize,
) -> crate::Result<ExitCode> {
    let net = lpips::Lpips::<T>::new(w);
    let mut r = Rng::new(1);
    let n = 3 * size * size;
    let a: Vec<T> = (0..n).map(|_| T::from_f64(r.uniform())).collect();
    let b: Vec<T> = a
        .iter()
        .map(|&v| (v + T::from_f64(r.uniform_range(-0.1, 0.1))).clamp(T::ZERO, T::ONE))
        .collect();
    // Multiply-adds of the 13 convolutions of one image (pool floors included).
    let (mut h, mut wd, mut flops) = (size, size, 0.0f64);
    for (i, &(cin, cout)) in lpips::VGG16_CONVS.iter().enumerate() {
        if [2, 4, 7, 10].contains(&i) {
            (h, wd) = (h / 2, wd / 2);
        }
        flops += 2.0 * 9.0 * (cin * cout * h * wd) as f64;
    }
    let mut times = Vec::new();
    let mut value = 0.0;
    for _ in 0..reps.max(1) {
        let t0 = Instant::now();
        value = net
            .distance(&a, &b, size, size, lpips::Convention::D3dgs)?
            .value
            .to_f64();
        times.push(t0.elapsed().as_secs_f64());
    }
    let t = median(times);
    println!(
        "lpips vgg {size}x{size} pair, {} ({}), {} threads: {:.0} ms per pair (median of {}), {:.1} GFLOP/s in the convolutions ({:.0} GFLOP per pair); value {value:.6}",
        std::any::type_name::<T>(),
        if w.vgg.official && w.lin.official {
            "published weights"
        } else {
            "unpublished weights"
        },
        rayon::current_num_threads(),
        t * 1e3,
        reps.max(1),
        2.0 * flops / t / 1e9,
        2.0 * flops / 1e9,
    );
    Ok(ExitCode::SUCCESS)
}

pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Nominal FLOPs of one (pixel, Gaussian) pair, counted from the code of a
/// pair that blends (f32): forward `power` 8, `exp` 23, alpha and
/// transmittance 3, colour and depth 12; the backward repeats the forward walk
/// and adds 35 for the per-pixel gradient (lane reductions not counted).
/// Rejected pairs cost fewer, so the percentages below are upper bounds on
/// the FMA units' use.
pub const RASTER_FLOP_PER_PAIR: [f64; 2] = [46.0, 81.0];

fn bench_raster(reps: usize) -> crate::Result<ExitCode> {
    let reps = reps.max(1);
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!("machine threads: {cores}");
    let mut thread_counts = vec![1usize];
    if cores > 1 {
        thread_counts.push(cores);
    }
    let peaks: Vec<Option<(&str, f64)>> = thread_counts
        .iter()
        .map(|&t| fma_peak(t, 20_000_000))
        .collect();
    for (&t, p) in thread_counts.iter().zip(&peaks) {
        match p {
            Some((isa, gflops)) => {
                println!("f32 FMA peak ({isa}), {t} thread(s): {gflops:.1} GFLOP/s")
            }
            None => println!("f32 FMA peak: no AVX2+FMA or AVX-512 on this CPU"),
        }
    }
    println!(
        "instruction set of the row functions: {:?}",
        crate::kernels::fastmath::isa()
    );
    println!(
        "{:<16} {:>3} {:>10} {:>10} {:>12} {:>11} {:>11} {:>6} {:>6}",
        "scene",
        "thr",
        "fwd ms",
        "bwd ms",
        "pairs eval",
        "fwd pair/s",
        "bwd pair/s",
        "fwd %",
        "bwd %"
    );
    for (w, h, n) in [
        (800usize, 800usize, 50_000usize),
        (400, 400, 20_000),
        (64, 64, 2_600),
    ] {
        let s = scene::random_scene(&scene::SceneSpec::bench(w, h, n, 1))?.cast::<f32>();
        let input = s.input(scene::ColorSource::Sh, scene::CovSource::ScaleRotation);
        let grad: Vec<f32> = crate::math::gradcheck::cotangent(5, 3 * w * h)
            .into_iter()
            .map(|v| v as f32)
            .collect();
        for (&threads, peak) in thread_counts.iter().zip(&peaks) {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .map_err(|e| crate::Error::invalid("thread pool", e.to_string()))?;
            let (fwd, bwd, pairs) = pool.install(|| -> crate::Result<_> {
                let mut f = Vec::new();
                let mut b = Vec::new();
                let mut pairs = 0;
                for _ in 0..reps {
                    let t0 = Instant::now();
                    let (_, state) = render::rasterize(&input)?;
                    f.push(t0.elapsed().as_secs_f64());
                    pairs = state.pairs_evaluated();
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
                let min = |v: Vec<f64>| v.into_iter().fold(f64::INFINITY, f64::min);
                Ok((min(f), min(b), pairs))
            })?;
            let rate = [pairs as f64 / fwd, pairs as f64 / bwd];
            let pct = |i: usize| match peak {
                Some((_, g)) => format!(
                    "{:.1}",
                    100.0 * rate[i] * RASTER_FLOP_PER_PAIR[i] / (g * 1e9)
                ),
                None => "-".into(),
            };
            println!(
                "{:<16} {:>3} {:>10.2} {:>10.2} {:>12} {:>11.3e} {:>11.3e} {:>6} {:>6}",
                format!("{w}x{h} {n}"),
                threads,
                fwd * 1e3,
                bwd * 1e3,
                pairs,
                rate[0],
                rate[1],
                pct(0),
                pct(1)
            );
        }
    }
    println!(
        "(f32, SH degree 3, exact gradients, minimum over {reps} runs; pairs eval: (pixel, Gaussian) \
         pairs the forward evaluated, up to each pixel's stop; %: pairs/s x {} (forward) or {} \
         (backward) FLOP per pair over the FMA peak)",
        RASTER_FLOP_PER_PAIR[0], RASTER_FLOP_PER_PAIR[1]
    );
    Ok(ExitCode::SUCCESS)
}

/// The machine's f32 FMA peak in GFLOP/s (2 FLOPs per lane per fused
/// multiply-add) on `threads` threads, each running `iters` rounds of 24
/// (AVX-512) or 12 (AVX2) independent vector FMAs, and the instruction set
/// used; `None` without AVX2+FMA or AVX-512. The ceiling `benches/fma_peak`
/// prints.
pub fn fma_peak(threads: usize, iters: usize) -> Option<(&'static str, f64)> {
    #[cfg(target_arch = "x86_64")]
    {
        let (name, flop_per_iter, run): (&str, f64, fn(usize) -> f32) =
            if std::is_x86_feature_detected!("avx512f") {
                // SAFETY: the CPU has AVX-512F (checked above).
                ("AVX-512", 24.0 * 16.0 * 2.0, |n| unsafe { peak::avx512(n) })
            } else if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
            {
                // SAFETY: the CPU has AVX2 and FMA (checked above).
                ("AVX2", 12.0 * 8.0 * 2.0, |n| unsafe { peak::avx2(n) })
            } else {
                return None;
            };
        let t0 = Instant::now();
        let sum: f32 = (0..threads.max(1))
            .map(|_| std::thread::spawn(move || run(iters)))
            .collect::<Vec<_>>()
            .into_iter()
            .map(|h| h.join().unwrap_or(0.0))
            .sum();
        let s = t0.elapsed().as_secs_f64();
        std::hint::black_box(sum);
        Some((
            name,
            threads.max(1) as f64 * iters as f64 * flop_per_iter / s / 1e9,
        ))
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (threads, iters);
        None
    }
}

#[cfg(target_arch = "x86_64")]
mod peak {
    use std::arch::x86_64::*;

    #[target_feature(enable = "avx512f")]
    pub unsafe fn avx512(iters: usize) -> f32 {
        let mut c = [_mm512_set1_ps(0.0); 24];
        let a = _mm512_set1_ps(0.999_999);
        let b = _mm512_set1_ps(1e-7);
        for _ in 0..iters {
            for v in c.iter_mut() {
                *v = _mm512_fmadd_ps(a, *v, b);
            }
        }
        let s = c
            .iter()
            .fold(_mm512_set1_ps(0.0), |s, &v| _mm512_add_ps(s, v));
        _mm512_reduce_add_ps(s)
    }

    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn avx2(iters: usize) -> f32 {
        let mut c = [_mm256_set1_ps(0.0); 12];
        let a = _mm256_set1_ps(0.999_999);
        let b = _mm256_set1_ps(1e-7);
        for _ in 0..iters {
            for v in c.iter_mut() {
                *v = _mm256_fmadd_ps(a, *v, b);
            }
        }
        let mut out = [0.0f32; 8];
        let s = c
            .iter()
            .fold(_mm256_set1_ps(0.0), |s, &v| _mm256_add_ps(s, v));
        _mm256_storeu_ps(out.as_mut_ptr(), s);
        out.iter().sum()
    }
}

/// Train in memory (no files) and print the mean time of each stage, over
/// all iterations and over those with the field on.
fn bench_train<T: crate::math::Real>(spec: &super::train::RunSpec) -> crate::Result<ExitCode> {
    use crate::train::{run, StageTimes};
    let data = spec.load_dataset()?;
    let config = spec.train_config(&data)?;
    let views = run::views::<T>(&data.train);
    let mut trainer = run::new_trainer::<T>(&config, &data)?;
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
        crate::report::field_label(&config.field),
        spec.data_name(),
        views.len(),
        n,
        if T::PRECISION == crate::math::Precision::F32 {
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

/// CPU time of the whole process (all threads) in seconds; `None` where not
/// available. On a shared machine, CPU time ÷ threads estimates the wall
/// time the same work would take with the cores to itself.
fn process_cpu_seconds() -> Option<f64> {
    #[cfg(target_os = "linux")]
    {
        #[repr(C)]
        struct Timespec {
            sec: i64,
            nsec: i64,
        }
        extern "C" {
            fn clock_gettime(clock: i32, tp: *mut Timespec) -> i32;
        }
        const CLOCK_PROCESS_CPUTIME_ID: i32 = 2;
        let mut ts = Timespec { sec: 0, nsec: 0 };
        // SAFETY: clock_gettime writes one timespec (two 64-bit fields on
        // 64-bit Linux) into the buffer we own.
        let rc = unsafe { clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
        if rc == 0 && cfg!(target_pointer_width = "64") {
            return Some(ts.sec as f64 + ts.nsec as f64 * 1e-9);
        }
    }
    None
}

/// Seeded inputs of the deform benchmark: positions in [-1.3, 1.3]³, times in [0, 1].
fn deform_inputs<T: Real>(n: usize) -> (Vec<T>, Vec<T>, Deformation<T>) {
    let mut r = Rng::new(11);
    let xyz = (0..3 * n)
        .map(|_| T::from_f64(r.uniform_range(-1.3, 1.3)))
        .collect();
    let t = (0..n).map(|_| T::from_f64(r.uniform())).collect();
    let cast = |v: Vec<f64>| v.into_iter().map(T::from_f64).collect::<Vec<T>>();
    let g = Deformation {
        d_xyz: cast(cotangent(12, 3 * n)),
        d_rotation: cast(cotangent(13, 4 * n)),
        d_scaling: cast(cotangent(14, 3 * n)),
    };
    (xyz, t, g)
}

fn bench_deform<T: Real>(
    n: usize,
    reps: usize,
    only: Option<FieldKind>,
) -> crate::Result<ExitCode> {
    let reps = reps.max(1);
    if n == 0 {
        return Err(crate::Error::invalid("n", "must be at least 1"));
    }
    println!(
        "threads: {} (rayon pool; machine reports {} available); precision {}; N = {n}; median of {reps}",
        rayon::current_num_threads(),
        std::thread::available_parallelism().map_or(1, |n| n.get()),
        T::PRECISION,
    );
    println!(
        "matrix kernel path: {:?}",
        crate::kernels::matmul::kernel_path()
    );
    println!(
        "{:<16} {:>11} {:>10} {:>16} {:>11} {:>12} {:>18} {:>22}",
        "field",
        "forward ms",
        "GFLOP/s",
        "fwd+bwd ms",
        "GFLOP/s",
        "backward ms",
        "min fwd / fwd+bwd",
        "CPU/threads fwd / f+b"
    );
    let (xyz, t, g) = deform_inputs::<T>(n);
    {
        // One trunk-layer-sized product alone: the matrix kernel's rate.
        use crate::kernels::matmul::{matmul, MatRef};
        let (k, w) = (256, 256);
        let cast = |v: Vec<f64>| v.into_iter().map(T::from_f64).collect::<Vec<T>>();
        let (a, b) = (cast(cotangent(15, n * k)), cast(cotangent(16, k * w)));
        let run = || matmul(MatRef::row_major(&a, n, k), MatRef::row_major(&b, k, w));
        drop(run());
        let times: Vec<f64> = (0..reps)
            .map(|_| {
                let t0 = Instant::now();
                drop(run());
                t0.elapsed().as_secs_f64()
            })
            .collect();
        let s = median(times);
        println!(
            "{:<16} {:>11.1} {:>10.1}   (one [N, 256]·[256, 256] product, as in a trunk layer)",
            "matmul N×256×256",
            s * 1e3,
            2.0 * (n * k * w) as f64 / s / 1e9
        );
    }
    for (name, config) in [
        ("mlp D8 W256", FieldConfig::new(FieldKind::Mlp)),
        ("cfc D6 W128", FieldConfig::new(FieldKind::Cfc)),
    ] {
        if only.is_some_and(|k| k != config.kind) {
            continue;
        }
        let field = Field::<T>::new(config, 0)?;
        // FLOPs: 2 per ptflops-aten MAC (every Linear's in·out + out) per Gaussian;
        // forward+backward counts 3× that (forward, weight and input gradients).
        let flop = 2.0 * macs_per_gaussian(&config, MacConvention::Aten)? as f64 * n as f64;
        // One warm-up pass (allocations, page faults), not timed.
        let (_, cache) = field.forward(&xyz, &t)?;
        field.backward(&cache, &g)?;
        drop(cache);
        let mut fwd = Vec::new();
        let mut both = Vec::new();
        let mut bwd = Vec::new();
        let (mut cpu_f, mut cpu_b) = (Vec::new(), Vec::new());
        for _ in 0..reps {
            let c0 = process_cpu_seconds();
            let t0 = Instant::now();
            let (_, cache) = field.forward(&xyz, &t)?;
            let t1 = Instant::now();
            let c1 = process_cpu_seconds();
            field.backward(&cache, &g)?;
            let t2 = Instant::now();
            let c2 = process_cpu_seconds();
            drop(cache);
            fwd.push((t1 - t0).as_secs_f64());
            bwd.push((t2 - t1).as_secs_f64());
            both.push((t2 - t0).as_secs_f64());
            if let (Some(c0), Some(c1), Some(c2)) = (c0, c1, c2) {
                cpu_f.push(c1 - c0);
                cpu_b.push(c2 - c0);
            }
        }
        let threads = rayon::current_num_threads() as f64;
        let cpu = if cpu_f.is_empty() {
            "n/a".to_string()
        } else {
            format!(
                "{:.1} / {:.1}",
                median(cpu_f) / threads * 1e3,
                median(cpu_b) / threads * 1e3
            )
        };
        let min = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
        let (fmin, fbmin) = (min(&fwd), min(&both));
        let (f, b, fb) = (median(fwd), median(bwd), median(both));
        println!(
            "{:<16} {:>11.1} {:>10.1} {:>16.1} {:>11.1} {:>12.1} {:>18} {:>22}",
            name,
            f * 1e3,
            flop / f / 1e9,
            fb * 1e3,
            3.0 * flop / fb / 1e9,
            b * 1e3,
            format!("{:.1} / {:.1}", fmin * 1e3, fbmin * 1e3),
            cpu
        );
    }
    println!("(medians, then the fastest run; GFLOP/s: 2 FLOPs per ptflops-aten MAC of the forward; forward+backward counts 3x the forward's FLOPs;");
    println!(" CPU/threads: median process CPU time / threads, the wall time with idle cores if the threads never wait; includes spin-waiting)");
    for (name, config) in [
        ("mlp D8 W256", FieldConfig::new(FieldKind::Mlp)),
        ("cfc D6 W128", FieldConfig::new(FieldKind::Cfc)),
    ] {
        if only.is_some_and(|k| k != config.kind) {
            continue;
        }
        deform_profile::<T>(name, config, &xyz, &t, &g, reps)?;
    }
    kernel_shapes::<T>(n, reps);
    Ok(ExitCode::SUCCESS)
}

/// The matrix kernels alone on the shapes of the fields' products (no
/// epilogue): `[N, K]·[K, M]` as in a forward or an input gradient, and
/// `Gᵀ·X` (`[M, N]·[N, K]`) as in a weight gradient.
fn kernel_shapes<T: Real>(n: usize, reps: usize) {
    use crate::kernels::matmul::{matmul, matmul_tn, MatRef};
    let cast = |v: Vec<f64>| v.into_iter().map(T::from_f64).collect::<Vec<T>>();
    println!();
    println!(
        "matrix kernels alone on the fields' shapes, {} threads, path {:?}, median of {} (fastest)",
        rayon::current_num_threads(),
        crate::kernels::matmul::kernel_path(),
        reps.max(1)
    );
    println!(
        "{:<10} {:>26} {:>16} {:>14}   used in",
        "product", "shape", "ms", "GFLOP/s"
    );
    let shapes: [(&str, usize, usize, &str); 8] = [
        ("x·W", 256, 256, "MLP trunk layers"),
        (
            "x·W",
            93,
            512,
            "CfC u part of every first layer and the skip",
        ),
        ("x·W", 128, 64, "CfC backbone.0 state part"),
        ("x·W", 64, 64, "CfC backbone.1"),
        ("x·W", 64, 512, "CfC heads (4W)"),
        ("x·W", 512, 64, "CfC heads' input gradient"),
        ("Gᵀ·X", 256, 256, "MLP trunk weight gradients"),
        ("Gᵀ·X", 512, 64, "CfC heads' weight gradient"),
    ];
    let more: [(&str, usize, usize, &str); 3] = [
        ("Gᵀ·X", 64, 128, "CfC backbone.0 state weight gradient"),
        ("Gᵀ·X", 64, 64, "CfC backbone.1 weight gradient"),
        ("Gᵀ·X", 512, 93, "CfC u part weight gradients"),
    ];
    for (kind, k, m, used) in shapes.iter().chain(&more) {
        // x·W: A [N, k], B [k, m]. Gᵀ·X: G [N, k] (the output gradient,
        // k = out), X [N, m].
        let (rows_b, cols_b) = if *kind == "x·W" { (*k, *m) } else { (n, *m) };
        let (a, b) = (
            cast(cotangent(15, n * k)),
            cast(cotangent(16, rows_b * cols_b)),
        );
        let run = || {
            let am = MatRef::row_major(&a, n, *k);
            let bm = MatRef::row_major(&b, rows_b, cols_b);
            if *kind == "x·W" {
                matmul(am, bm)
            } else {
                matmul_tn(am, bm)
            }
        };
        drop(run());
        let times: Vec<f64> = (0..reps.max(1))
            .map(|_| {
                let t0 = Instant::now();
                drop(run());
                t0.elapsed().as_secs_f64()
            })
            .collect();
        let fastest = times.iter().copied().fold(f64::INFINITY, f64::min);
        let s = median(times);
        let shape = if *kind == "x·W" {
            format!("[{n},{k}]·[{k},{m}]")
        } else {
            format!("[{k},{n}]·[{n},{m}]")
        };
        let flop = 2.0 * (n * k * m) as f64;
        println!(
            "{:<10} {:>26} {:>16} {:>14}   {used}",
            kind,
            shape,
            format!("{:.2} ({:.2})", s * 1e3, fastest * 1e3),
            format!("{:.0} ({:.0})", flop / s / 1e9, flop / fastest / 1e9),
        );
    }
}

/// `"… / cell 3 / …"` as `"… / cells / …"`: the cells' rows of the
/// profile are summed over the cells (their count is the calls column).
fn every_cell(label: &str) -> String {
    label
        .split(" / ")
        .map(|part| match part.strip_prefix("cell ") {
            Some(d) if !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()) => "cells",
            _ => part,
        })
        .collect::<Vec<_>>()
        .join(" / ")
}

/// The per-operation profile of one field's forward and backward: every
/// product (with what is fused into its epilogue) and every separate
/// element-wise pass, its shape, its median time over `reps` profiled runs,
/// and its rate.
fn deform_profile<T: Real>(
    name: &str,
    config: FieldConfig,
    xyz: &[T],
    t: &[T],
    g: &Deformation<T>,
    reps: usize,
) -> crate::Result<()> {
    use crate::deform::profile;
    let field = Field::<T>::new(config, 0)?;
    // Rows keyed by (label, shape), in first-seen order; per run, the time
    // summed over the calls with that key.
    let mut rows: Vec<(String, String, profile::Kind, f64, usize, Vec<f64>)> = Vec::new();
    let mut totals = (Vec::new(), Vec::new());
    for rep in 0..reps.max(1) + 1 {
        profile::take();
        profile::enable(true);
        let t0 = Instant::now();
        let r = profile::layer(|| "forward".into(), || field.forward(xyz, t));
        let t1 = Instant::now();
        let b = r.and_then(|(_, cache)| {
            profile::layer(|| "backward".into(), || field.backward(&cache, g))
        });
        let t2 = Instant::now();
        profile::enable(false);
        let recs = profile::take();
        b?;
        if rep == 0 {
            // Warm-up run, not counted.
            continue;
        }
        totals.0.push((t1 - t0).as_secs_f64());
        totals.1.push((t2 - t1).as_secs_f64());
        let mut seen = vec![false; rows.len()];
        for mut rec in recs {
            rec.label = every_cell(&rec.label);
            let i = match rows
                .iter()
                .position(|r| r.0 == rec.label && r.1 == rec.shape)
            {
                Some(i) => i,
                None => {
                    rows.push((rec.label, rec.shape, rec.kind, 0.0, 0, Vec::new()));
                    seen.push(false);
                    rows.len() - 1
                }
            };
            let row = &mut rows[i];
            if !seen[i] {
                seen[i] = true;
                row.5.push(0.0);
                if rep == 1 {
                    row.3 = 0.0;
                    row.4 = 0;
                }
            }
            if rep == 1 {
                row.3 += rec.work;
                row.4 += 1;
            }
            *row.5.last_mut().expect("pushed above") += rec.seconds;
        }
    }
    let (tf, tb) = (median(totals.0), median(totals.1));
    println!();
    println!(
        "{name}: per-operation profile, {} threads, N = {}, median of {} profiled runs (forward {:.1} ms, backward {:.1} ms while profiled)",
        rayon::current_num_threads(),
        t.len(),
        reps.max(1),
        tf * 1e3,
        tb * 1e3
    );
    println!(
        "{:<100} {:>26} {:>6} {:>9} {:>6} {:>12}",
        "operation (product: x·Wᵀ etc. with its fused epilogue; pass: a separate element-wise pass)",
        "shape",
        "calls",
        "ms",
        "%",
        "rate"
    );
    for (label, shape, kind, work, calls, times) in rows {
        let s = median(times);
        let total = if label.starts_with("forward") { tf } else { tb };
        let rate = match kind {
            profile::Kind::Product => format!("{:.1} GFLOP/s", work / s / 1e9),
            profile::Kind::Elementwise => format!("{:.2} Gel/s", work / s / 1e9),
        };
        println!(
            "{:<100} {:>26} {:>6} {:>9.2} {:>6.1} {:>12}",
            label,
            shape,
            calls,
            s * 1e3,
            100.0 * s / total,
            rate
        );
    }
    println!("(% of the profiled forward or backward; rate: FLOPs (2 per multiply-add) per second of a product, elements per second of a pass;");
    println!(" cells: summed over the cells that run it (calls); time outside the listed operations: allocation, gathering weights, small copies)");
    Ok(())
}
