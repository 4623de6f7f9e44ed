//! Throughput measurements (never asserted in tests), run by
//! `liquid-splat bench ...` and by `cargo bench` (`benches/`): what each
//! benchmark measures lives here, how it is timed, described and printed
//! in [`harness`].
//!
//! - [`raster`]: the rasterizer's forward and backward at three sizes, on 1
//!   thread and all cores, against the machine's FMA peak.
//! - [`deform`]: the deformation fields' forward and forward+backward, their
//!   per-operation profiles and the matrix kernels alone.
//! - [`lpips`](fn@lpips): LPIPS (VGG16) of one image pair.
//! - [`train`]: milliseconds per training iteration by stage.

pub mod harness;

use self::harness::{median, process_cpu_seconds, Table};
use crate::deform::count::{macs_per_gaussian, MacConvention};
use crate::deform::{Deformation, Field, FieldConfig, FieldKind};
use crate::experiment::{PrecisionChoice, RunSpec};
use crate::lpips;
use crate::math::{gradcheck::cotangent, Real, Rng};
use crate::render::{self, scene};
use std::time::Instant;

/// LPIPS weights of the right shapes with uniform random values (for timing only).
pub fn random_lpips_weights(seed: u64) -> crate::Result<lpips::LpipsWeights> {
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

/// LPIPS of one `size`×`size` pair with weights `w`: the median of `reps`
/// runs, and the convolutions' GFLOP/s.
pub fn lpips<T: Real>(w: &lpips::LpipsWeights, size: usize, reps: usize) -> crate::Result<()> {
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
    let mut value = 0.0;
    let times = harness::repeat(0, reps, || -> crate::Result<()> {
        value = net
            .distance(&a, &b, size, size, lpips::Convention::D3dgs)?
            .value
            .to_f64();
        Ok(())
    })?;
    let t = times.median();
    outln!(
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
    Ok(())
}

/// Nominal FLOPs of one (pixel, Gaussian) pair, counted from the code of a
/// pair that blends (f32): forward `power` 8, `exp` 23, alpha and
/// transmittance 3, colour and depth 12; the backward replays the entries
/// that blend ([`render::RasterizeSaved::pairs_replayed`]: `power`, `exp`,
/// alpha and transmittance, 34) and adds 35 for the per-pixel gradient
/// (lane reductions not counted). These count the per-pair work only, per
/// pixel: the forward's rejected pairs cost fewer FLOPs, and the rest of
/// each pass (the binning, the backward's per-Gaussian sums and chain rule)
/// counts none, so the percentages below are not a bound on the whole
/// pass's use of the FMA units.
pub const RASTER_FLOP_PER_PAIR: [f64; 2] = [46.0, 69.0];

/// The least time, in seconds, each thread count of [`raster`] spends on
/// its timed passes in one round.
pub const RASTER_BLOCK_S: f64 = 0.25;

/// The rasterizer's forward and backward (f32, SH degree 3, exact
/// gradients) at 800x800/50k, 400x400/20k and 64x64/2.6k Gaussians on each
/// of `thread_counts`: the fastest pass, pairs evaluated, pairs/s, % of
/// the FMA peak and the speed-up over the first thread count; on two or
/// more threads (at most one per core), the round trip of a cache line
/// between workers 0 and 1 before the first round and after the last
/// ([`harness::round_trip_ns`]), which on a shared machine tells a slow
/// period from a quiet one.
///
/// Each frame is timed in `rounds` rounds. In each, every thread count in
/// turn (the order reversed every other round, so that none always follows
/// another) runs one untimed forward and backward, then forward and
/// backward passes, each timed, for at least [`RASTER_BLOCK_S`] (at least
/// one pair of passes), then one pass of each with the stage clock on. So
/// the thread counts are timed in the same minutes: a shared machine's
/// slow periods come and go within minutes, and timing every pass of one
/// thread count before the next made their ratio swing by a tenth
/// (benches/README.md, "Rasterizer: `bench raster` in rounds"). The
/// untimed pair wakes the pool's workers, which sleep while another pool
/// runs (a small frame's first pass would otherwise wait for them), and
/// short frames get many timed passes, whose fastest is steadier than the
/// fastest of a few. With pinned workers (`--pin-threads`), a thread count
/// below the machine's cores runs on the first CPUs in even rounds and on
/// the next ones in odd rounds: one CPU of a shared machine can run a third
/// slower than the other for minutes (benches/README.md, "Rasterizer: one
/// CPU slowed for minutes"), and one thread always on the first would then
/// make the others' speed-up look larger than it is.
pub fn raster(rounds: usize, thread_counts: &[usize]) -> crate::Result<()> {
    let rounds = rounds.max(1);
    outln!("machine threads: {}", harness::available_cores());
    let peaks: Vec<Option<(&str, f64)>> = thread_counts
        .iter()
        .map(|&t| harness::fma_peak(t, 20_000_000))
        .collect();
    for (&t, p) in thread_counts.iter().zip(&peaks) {
        match p {
            Some((isa, gflops)) => {
                outln!("f32 FMA peak ({isa}), {t} thread(s): {gflops:.1} GFLOP/s")
            }
            None => outln!("f32 FMA peak: no AVX2+FMA or AVX-512 on this CPU"),
        }
    }
    outln!(
        "instruction set of the row functions: {:?}",
        crate::kernels::fastmath::isa()
    );
    let table = Table::new(&[
        ("scene", -16),
        ("thr", 3),
        ("passes", 6),
        ("fwd ms", 10),
        ("bwd ms", 10),
        ("fwd x", 6),
        ("bwd x", 6),
        ("pairs eval", 12),
        ("bwd replayed", 12),
        ("fwd pair/s", 11),
        ("bwd pair/s", 11),
        ("fwd %", 6),
        ("bwd %", 6),
        ("x-CPU ns", 11),
    ]);
    table.print_header();
    let mut stage_lines = Vec::new();
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
        // The backward of a forward's saved state, as timed below.
        let backward = |state: &render::RasterizeSaved<f32>| {
            render::rasterize_vjp(&input, state, &grad, None, render::GradientMode::Exact)
        };
        // Per thread count, its pools: with pinned workers and fewer
        // threads than cores, one on the first CPUs and one on the next
        // (rounds alternate between them), else one.
        let pools = thread_counts
            .iter()
            .map(|&t| {
                let firsts = if crate::threads::pinning() && t < harness::available_cores() {
                    vec![0, t]
                } else {
                    vec![0]
                };
                firsts
                    .into_iter()
                    .map(|first| harness::thread_pool_from(t, first))
                    .collect::<crate::Result<Vec<_>>>()
            })
            .collect::<crate::Result<Vec<_>>>()?;
        // (Only where each worker can have a CPU: the round trip spins on
        // both sides.)
        let round_trip = |i: usize| {
            (thread_counts[i] <= harness::available_cores())
                .then(|| harness::round_trip_ns(&pools[i][0], 2_000))
                .flatten()
        };
        let trips_before: Vec<Option<f64>> = (0..pools.len()).map(round_trip).collect();
        let k = pools.len();
        let mut times = vec![[harness::Samples::new(), harness::Samples::new()]; k];
        let mut stages = vec![[Vec::new(), Vec::new()]; k];
        let mut pairs = [0; 2];
        for round in 0..rounds {
            let order: Vec<usize> = if round % 2 == 0 {
                (0..k).collect()
            } else {
                (0..k).rev().collect()
            };
            for i in order {
                let [f, b] = &mut times[i];
                let staged = &mut stages[i];
                let placements = &pools[i];
                placements[round % placements.len()].install(|| -> crate::Result<()> {
                    let (_, state) = render::rasterize(&input)?;
                    backward(&state)?;
                    let block = Instant::now();
                    loop {
                        let (r, t) = harness::timed(|| render::rasterize(&input));
                        let (_, state) = r?;
                        f.push(t);
                        pairs = [state.pairs_evaluated(), state.pairs_replayed()];
                        let (r, t) = harness::timed(|| backward(&state));
                        r?;
                        b.push(t);
                        if block.elapsed().as_secs_f64() >= RASTER_BLOCK_S {
                            break;
                        }
                    }
                    // Stage times in a pass of their own (each mark reads
                    // the process CPU clock): the stages of the fastest.
                    let (r, fs) = render::stages::record(|| render::rasterize(&input));
                    let (_, state) = r?;
                    let (r, bs) = render::stages::record(|| backward(&state));
                    r?;
                    for (acc, new) in staged.iter_mut().zip([fs, bs]) {
                        fastest_stages(acc, new);
                    }
                    Ok(())
                })?;
            }
        }
        let fastest: Vec<[f64; 2]> = times.iter().map(|[f, b]| [f.min(), b.min()]).collect();
        for (i, ((&threads, peak), stages)) in
            thread_counts.iter().zip(&peaks).zip(stages).enumerate()
        {
            stage_lines.push((format!("{w}x{h} {n}"), threads, stages));
            let [fwd, bwd] = fastest[i];
            let trips = match (trips_before[i], round_trip(i)) {
                (Some(a), Some(b)) => format!("{a:.0}/{b:.0}"),
                _ => "-".into(),
            };
            // Both passes' pairs/s count the frame's pairs (the forward's),
            // so they compare as times do; the backward's FLOP rate counts
            // the pairs it replays.
            let rate = [pairs[0] as f64 / fwd, pairs[0] as f64 / bwd];
            let flop_rate = [
                rate[0] * RASTER_FLOP_PER_PAIR[0],
                pairs[1] as f64 / bwd * RASTER_FLOP_PER_PAIR[1],
            ];
            let pct = |i: usize| match peak {
                Some((_, g)) => format!("{:.1}", 100.0 * flop_rate[i] / (g * 1e9)),
                None => "-".into(),
            };
            table.print_row(&[
                format!("{w}x{h} {n}"),
                format!("{threads}"),
                format!("{}", times[i][0].len()),
                format!("{:.2}", fwd * 1e3),
                format!("{:.2}", bwd * 1e3),
                format!("{:.3}", fastest[0][0] / fwd),
                format!("{:.3}", fastest[0][1] / bwd),
                format!("{}", pairs[0]),
                format!("{}", pairs[1]),
                format!("{:.3e}", rate[0]),
                format!("{:.3e}", rate[1]),
                pct(0),
                pct(1),
                trips,
            ]);
        }
    }
    outln!(
        "(f32, SH degree 3, exact gradients; {rounds} rounds, each running every thread count in \
         turn: one untimed forward and backward, then passes for at least {RASTER_BLOCK_S} s, then \
         one with the stage clock on; with pinned workers, fewer threads than cores run on the \
         first CPUs in even rounds and on the next ones in odd rounds; passes: the timed \
         forward and backward passes of each thread count; ms: the fastest of them; x: the \
         first thread count's fastest over this one's; pairs eval: (pixel, Gaussian) \
         pairs the forward evaluated, up to each pixel's stop, and pair/s of both passes those \
         pairs over the pass's time; bwd replayed: the pairs the backward evaluates, each row's \
         pixels of a tile times the entries that blend in one of them; %: FLOP/s over the FMA \
         peak, {} FLOP per pair evaluated (forward) or {} per pair replayed (backward); \
         x-CPU ns: one cache line's round trip between workers 0 and 1, before the first round \
         / after the last, which tells a shared machine's slow periods from its quiet minutes: \
         on the 2-core development VMs 40-70 ns quiet and 300-450 ns slow, when small frames on 2 \
         threads take up to half as long again (benches/README.md, \"The machine's slow \
         periods\"), and 27-30 ns at times when the two CPUs apparently shared one core and 2 \
         threads were only 1.1-1.5x 1 on the small frame (benches/README.md, \"Rasterizer: \
         `bench raster` in rounds\"))",
        RASTER_FLOP_PER_PAIR[0],
        RASTER_FLOP_PER_PAIR[1]
    );
    outln!(
        "stages, ms wall (ms CPU of the process, all threads), of the fastest of the {rounds} \
         stage-clocked passes:"
    );
    for (scene, threads, passes) in &stage_lines {
        for (pass, st) in ["fwd", "bwd"].iter().zip(passes) {
            let cells: Vec<String> = st
                .iter()
                .map(|s| match s.cpu {
                    Some(c) => format!("{} {:.2} ({:.2})", s.name, s.wall * 1e3, c * 1e3),
                    None => format!("{} {:.2}", s.name, s.wall * 1e3),
                })
                .collect();
            outln!("  {scene:<14} {threads:>2} {pass}: {}", cells.join(", "));
        }
    }
    Ok(())
}

/// Keep in `acc` the stages of the faster run (by total wall time) of `acc`
/// and `new`.
fn fastest_stages(acc: &mut Vec<render::stages::StageTime>, new: Vec<render::stages::StageTime>) {
    let total = |v: &[render::stages::StageTime]| v.iter().map(|s| s.wall).sum::<f64>();
    if acc.is_empty() || total(&new) < total(acc) {
        *acc = new;
    }
}

/// Train `spec` in memory (no files) in its precision and print the mean
/// time of each stage, over all iterations and over those with the field
/// on.
pub fn train(spec: &RunSpec) -> crate::Result<()> {
    match spec.precision {
        PrecisionChoice::F32 => train_as::<f32>(spec),
        PrecisionChoice::F64 => train_as::<f64>(spec),
    }
}

fn train_as<T: crate::math::Real>(spec: &RunSpec) -> crate::Result<()> {
    use crate::train::{run, StageTimes};
    let data = spec.load_dataset()?;
    let config = spec.train_config(&data)?;
    let views = run::views::<T>(&data.train);
    let mut trainer = run::new_trainer::<T>(&config, &data)?;
    let (mut all, mut active) = (StageTimes::default(), StageTimes::default());
    let (mut n_active, mut gaussians) = (0u64, 0u64);
    let t0 = Instant::now();
    while trainer.iteration() < config.iterations {
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
    outln!(
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
    let table = Table::new(&[
        ("stage", -16),
        ("ms/it (all)", 14),
        ("ms/it (field on)", 18),
    ]);
    table.print_header();
    for (i, name) in StageTimes::NAMES.iter().enumerate() {
        table.print_row(&[
            name.to_string(),
            format!("{:.2}", 1e3 * all.values()[i] / n as f64),
            format!("{:.2}", 1e3 * active.values()[i] / n_active.max(1) as f64),
        ]);
    }
    table.print_row(&[
        "total".to_string(),
        format!("{:.2}", 1e3 * total / n as f64),
        format!(
            "{:.2}",
            1e3 * active.values().iter().sum::<f64>() / n_active.max(1) as f64
        ),
    ]);
    Ok(())
}

/// Seeded inputs of the deform benchmark: positions in [-1.3, 1.3]³, and
/// one time in [0, 1] for every Gaussian, as in training and rendering (a
/// frame's Gaussians share its time).
fn deform_inputs<T: Real>(n: usize) -> (Vec<T>, Vec<T>, Deformation<T>) {
    let mut r = Rng::new(11);
    let xyz = (0..3 * n)
        .map(|_| T::from_f64(r.uniform_range(-1.3, 1.3)))
        .collect();
    let t = vec![T::from_f64(r.uniform()); n];
    let cast = |v: Vec<f64>| v.into_iter().map(T::from_f64).collect::<Vec<T>>();
    let g = Deformation {
        d_xyz: cast(cotangent(12, 3 * n)),
        d_rotation: cast(cotangent(13, 4 * n)),
        d_scaling: cast(cotangent(14, 3 * n)),
    };
    (xyz, t, g)
}

/// The deformation fields (MLP D8 W256, CfC D6 W128; `only` one kind) on
/// `n` seeded Gaussians: forward and forward+backward (median and fastest
/// of `reps` runs after one warm-up), GFLOP/s and process CPU time; with
/// `profile`, then each field's per-operation profile and the matrix
/// kernels alone on the fields' shapes.
pub fn deform<T: Real>(
    n: usize,
    reps: usize,
    only: Option<FieldKind>,
    profile: bool,
) -> crate::Result<()> {
    let reps = reps.max(1);
    if n == 0 {
        return Err(crate::Error::invalid("n", "must be at least 1"));
    }
    outln!(
        "{}; precision {}; N = {n}; median of {reps}",
        harness::threads_line(),
        T::PRECISION,
    );
    outln!(
        "matrix kernel path: {:?}",
        crate::kernels::matmul::kernel_path()
    );
    let table = Table::new(&[
        ("field", -16),
        ("forward ms", 11),
        ("GFLOP/s", 10),
        ("fwd+bwd ms", 16),
        ("GFLOP/s", 11),
        ("backward ms", 12),
        ("min fwd / fwd+bwd", 18),
        ("CPU/threads fwd / f+b", 22),
    ]);
    table.print_header();
    let (xyz, t, g) = deform_inputs::<T>(n);
    {
        // One trunk-layer-sized product alone: the matrix kernel's rate.
        use crate::kernels::matmul::{matmul, MatRef};
        let (k, w) = (256, 256);
        let cast = |v: Vec<f64>| v.into_iter().map(T::from_f64).collect::<Vec<T>>();
        let (a, b) = (cast(cotangent(15, n * k)), cast(cotangent(16, k * w)));
        let run = || matmul(MatRef::row_major(&a, n, k), MatRef::row_major(&b, k, w));
        let times = harness::repeat(1, reps, || Ok::<_, crate::Error>(run()))?;
        let s = times.median();
        outln!(
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
        if only.is_some_and(|k| k != config.kind()) {
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
        table.print_row(&[
            name.to_string(),
            format!("{:.1}", f * 1e3),
            format!("{:.1}", flop / f / 1e9),
            format!("{:.1}", fb * 1e3),
            format!("{:.1}", 3.0 * flop / fb / 1e9),
            format!("{:.1}", b * 1e3),
            format!("{:.1} / {:.1}", fmin * 1e3, fbmin * 1e3),
            cpu,
        ]);
    }
    outln!("(medians, then the fastest run; GFLOP/s: 2 FLOPs per ptflops-aten MAC of the forward; forward+backward counts 3x the forward's FLOPs;");
    outln!(" CPU/threads: median process CPU time / threads, the wall time with idle cores if the threads never wait; includes spin-waiting)");
    if !profile {
        return Ok(());
    }
    for (name, config) in [
        ("mlp D8 W256", FieldConfig::new(FieldKind::Mlp)),
        ("cfc D6 W128", FieldConfig::new(FieldKind::Cfc)),
    ] {
        if only.is_some_and(|k| k != config.kind()) {
            continue;
        }
        deform_profile::<T>(name, config, &xyz, &t, &g, reps)?;
    }
    kernel_shapes::<T>(n, reps);
    Ok(())
}

/// The matrix kernels alone on the shapes of the fields' products (no
/// epilogue): `[N, K]·[K, M]` as in a forward or an input gradient, and
/// `Gᵀ·X` (`[M, N]·[N, K]`) as in a weight gradient.
fn kernel_shapes<T: Real>(n: usize, reps: usize) {
    use crate::kernels::matmul::{matmul, matmul_tn, MatRef};
    let cast = |v: Vec<f64>| v.into_iter().map(T::from_f64).collect::<Vec<T>>();
    outln!();
    outln!(
        "matrix kernels alone on the fields' shapes, {} threads, path {:?}, median of {} (fastest)",
        rayon::current_num_threads(),
        crate::kernels::matmul::kernel_path(),
        reps.max(1)
    );
    outln!(
        "{:<10} {:>26} {:>16} {:>14}   used in",
        "product",
        "shape",
        "ms",
        "GFLOP/s"
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
        ("x·W", 64, 384, "CfC heads (3W)"),
        ("x·W", 384, 64, "CfC heads' input gradient"),
        ("Gᵀ·X", 256, 256, "MLP trunk weight gradients"),
        ("Gᵀ·X", 384, 64, "CfC heads' weight gradient"),
    ];
    let more: [(&str, usize, usize, &str); 4] = [
        ("x·W", 64, 128, "CfC time_a(z) in the backward"),
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
        let Ok(times) = harness::repeat(1, reps, || Ok::<_, std::convert::Infallible>(run()));
        let (s, fastest) = (times.median(), times.min());
        let shape = if *kind == "x·W" {
            format!("[{n},{k}]·[{k},{m}]")
        } else {
            format!("[{k},{n}]·[{n},{m}]")
        };
        let flop = 2.0 * (n * k * m) as f64;
        outln!(
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
    outln!();
    outln!(
        "{name}: per-operation profile, {} threads, N = {}, median of {} profiled runs (forward {:.1} ms, backward {:.1} ms while profiled)",
        rayon::current_num_threads(),
        t.len(),
        reps.max(1),
        tf * 1e3,
        tb * 1e3
    );
    outln!(
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
        outln!(
            "{:<100} {:>26} {:>6} {:>9.2} {:>6.1} {:>12}",
            label,
            shape,
            calls,
            s * 1e3,
            100.0 * s / total,
            rate
        );
    }
    outln!("(% of the profiled forward or backward; rate: FLOPs (2 per multiply-add) per second of a product, elements per second of a pass;");
    outln!(" cells: summed over the cells that run it (calls); time outside the listed operations: allocation, gathering weights, small copies)");
    Ok(())
}
