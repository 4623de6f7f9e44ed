//! Two threads against one on the 64×64 frame of `bench raster` (seed 1,
//! 2,600 Gaussians, f32, SH degree 3), the way benches/README.md reports
//! the ratio (`cargo bench --bench two_threads -- [ROUNDS] [PASSES]`,
//! default 8 rounds of 400 passes).
//!
//! Single runs of this frame vary by ±2% on a shared 2-core VM, and in its
//! slow periods (benches/README.md, "The machine's slow periods") the
//! two-thread times alone go up, so each round:
//!
//! 1. waits, for up to two minutes, until a cache line's round trip between
//!    the two pinned workers takes under 100 ns but not under 35 ns (the
//!    median of five batches' means, 2,000 round trips a batch; 40–50 ns in
//!    quiet minutes on the Zen 5 development VM, 60–70 on the Zen 4 one,
//!    340–400 ns in slow periods, and 27–30 ns on the Zen 4 when its two
//!    CPUs apparently ran on one core, where two threads gained only
//!    1.1–1.5×: [`SHARED_CORE_NS`]);
//! 2. runs `PASSES` forward and backward passes on one thread pinned to the
//!    first CPU, `PASSES` on one thread pinned to the second, and `PASSES`
//!    on two (the two-thread passes first in odd rounds, last in even
//!    ones), and takes the fastest forward and backward of each;
//! 3. times the round trip again. A round that did not start quiet (the
//!    wait ran out) or ended slow or on one core is printed but left out of
//!    the summary, and so is one whose two CPUs did not run alike: their
//!    one-thread forwards (or backwards) more than [`ALIKE`] apart. Such a
//!    CPU shares its core with another tenant's work for a while (on the
//!    Zen 4 development VM one CPU's one-thread forward went from 0.51 to
//!    0.69 ms for minutes while the round trip stayed quiet), and a round
//!    timed there compares a slowed thread with two others.
//!
//! The one-thread time of a round is the faster CPU's. It prints each
//! round's times and two-over-one ratios, then, per direction, the median
//! (of an even count, the mean of the middle two) and range of the kept
//! rounds' ratios and the ratio of the fastest passes over the kept rounds.
//! Linux with pinning and two CPUs only (elsewhere it says so); with less
//! than two CPUs' worth of time, every round waits out its two minutes.
use liquid_splat::bench::harness;
use liquid_splat::render::{self, scene};
use std::time::{Duration, Instant};

/// The round trip (ns, see [`round_trip_ns`]) under which a minute is quiet.
const QUIET_NS: f64 = 100.0;

/// The round trip (ns) under which the two CPUs apparently share one core:
/// faster than any quiet minute's on either development VM (40–50 ns on the
/// Zen 5, 60–70 on the Zen 4), and at 27–30 ns on the Zen 4 two threads
/// gained only 1.1–1.5× (benches/README.md, "Rasterizer: `bench raster` in
/// rounds", the end).
const SHARED_CORE_NS: f64 = 35.0;

/// Whether a round trip of `ns` is a quiet minute's, on two cores.
fn quiet(ns: f64) -> bool {
    (SHARED_CORE_NS..QUIET_NS).contains(&ns)
}

/// The largest relative difference between the two CPUs' fastest
/// one-thread passes of a kept round.
const ALIKE: f64 = 0.03;

/// The ns per round trip of one atomic between the pool's two workers: the
/// median of 5 batches' means, 2,000 round trips a batch.
fn round_trip_ns(pool: &rayon::ThreadPool) -> f64 {
    harness::round_trip_median_ns(pool).expect("a pool of 2 threads")
}

/// The median (of an even count, the mean of the middle two), smallest and
/// largest of `v` (not empty).
fn spread(mut v: Vec<f64>) -> (f64, f64, f64) {
    v.sort_by(f64::total_cmp);
    let k = v.len();
    let median = if k % 2 == 1 {
        v[k / 2]
    } else {
        (v[k / 2 - 1] + v[k / 2]) / 2.0
    };
    (median, v[0], v[k - 1])
}

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let rounds = args.first().copied().unwrap_or(8).max(1);
    let passes = args.get(1).copied().unwrap_or(400).max(1);
    liquid_splat::memory::keep_freed_memory();
    liquid_splat::threads::set_pinning(true);
    if !liquid_splat::threads::pinning() || liquid_splat::threads::cores() < 2 {
        println!("needs Linux, pinning and two CPUs: nothing to measure here");
        return;
    }
    let (w, h, n) = (64, 64, 2_600);
    let s = scene::random_scene(&scene::SceneSpec::bench(w, h, n, 1))
        .expect("the bench scene")
        .cast::<f32>();
    let input = s.input(scene::ColorSource::Sh, scene::CovSource::ScaleRotation);
    let grad: Vec<f32> = liquid_splat::math::gradcheck::cotangent(5, 3 * w * h)
        .into_iter()
        .map(|v| v as f32)
        .collect();
    // One thread on the first CPU, one on the second, two threads.
    let pools = [
        liquid_splat::threads::pool(1).expect("a pool of pinned threads"),
        liquid_splat::threads::pool_from(1, 1).expect("a pool of pinned threads"),
        liquid_splat::threads::pool(2).expect("a pool of pinned threads"),
    ];
    // The fastest forward and backward (ms) of `passes` passes on `pool`.
    let fastest = |pool: &rayon::ThreadPool| {
        pool.install(|| {
            let mut best = [f64::MAX; 2];
            for _ in 0..passes {
                let t0 = Instant::now();
                let (_, saved) = render::rasterize(&input).expect("the forward");
                let t1 = Instant::now();
                let g =
                    render::rasterize_vjp(&input, &saved, &grad, None, render::GradientMode::Exact);
                let t2 = Instant::now();
                std::hint::black_box(g.expect("the backward"));
                best[0] = best[0].min((t1 - t0).as_secs_f64() * 1e3);
                best[1] = best[1].min((t2 - t1).as_secs_f64() * 1e3);
            }
            best
        })
    };
    println!(
        "64x64, {n} Gaussians, f32; {rounds} rounds of {passes} passes; fastest pass, ms, \
         1 thread (first CPU, second CPU) / 2 threads"
    );
    let mut kept = [Vec::new(), Vec::new()];
    let mut best = [[f64::MAX; 2]; 2];
    for r in 0..rounds {
        let start = Instant::now();
        let mut started_quiet = quiet(round_trip_ns(&pools[2]));
        while !started_quiet && start.elapsed() < Duration::from_secs(120) {
            std::thread::sleep(Duration::from_millis(500));
            started_quiet = quiet(round_trip_ns(&pools[2]));
        }
        let waited = start.elapsed().as_secs_f64();
        let order = if r % 2 == 0 { [0, 1, 2] } else { [2, 0, 1] };
        let mut times = [[0.0; 2]; 3];
        for k in order {
            times[k] = fastest(&pools[k]);
        }
        let [cpu0, cpu1, two] = times;
        let one = [0, 1].map(|d| cpu0[d].min(cpu1[d]));
        let alike = (0..2).all(|d| (cpu0[d] - cpu1[d]).abs() <= ALIKE * one[d]);
        let after = round_trip_ns(&pools[2]);
        let ratio = [one[0] / two[0], one[1] / two[1]];
        let kept_round = started_quiet && quiet(after) && alike;
        println!(
            "round {r}: forward {:.4} ({:.4}, {:.4}) / {:.4} ({:.3}x), backward {:.4} ({:.4}, \
             {:.4}) / {:.4} ({:.3}x); waited {waited:.0} s, round trip after {after:.0} ns{}",
            one[0],
            cpu0[0],
            cpu1[0],
            two[0],
            ratio[0],
            one[1],
            cpu0[1],
            cpu1[1],
            two[1],
            ratio[1],
            if !started_quiet {
                " (no quiet start: left out)"
            } else if after >= QUIET_NS {
                " (ended slow: left out)"
            } else if after < SHARED_CORE_NS {
                " (ended on one core: left out)"
            } else if !alike {
                " (CPUs unlike: left out)"
            } else {
                ""
            }
        );
        if kept_round {
            for d in 0..2 {
                kept[d].push(ratio[d]);
                best[0][d] = best[0][d].min(one[d]);
                best[1][d] = best[1][d].min(two[d]);
            }
        }
    }
    if kept[0].is_empty() {
        println!("no round started and ended quiet with its CPUs alike: no summary");
        return;
    }
    for (d, name) in ["forward", "backward"].iter().enumerate() {
        let (med, lo, hi) = spread(kept[d].clone());
        println!(
            "{name}: two over one, median of {} kept rounds {med:.3}x ({lo:.3}-{hi:.3}x); \
             their fastest passes {:.4} / {:.4} ms ({:.3}x)",
            kept[d].len(),
            best[0][d],
            best[1][d],
            best[0][d] / best[1][d]
        );
    }
}
