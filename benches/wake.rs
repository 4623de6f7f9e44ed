//! What a sleeping worker costs a short parallel stage, and what
//! `threads::keep_awake` saves (`cargo bench --bench wake [-- THREADS]`,
//! default 2): on a pool of THREADS workers, a serial step of G µs on the
//! calling thread (G = 0, 20, 100, 1000), then a parallel stage of THREADS
//! tasks of 50 µs each (ideal: 50 µs), 400 times; the stage's time in µs,
//! minimum / median / 90th percentile / maximum, with the loop run as is
//! and inside `keep_awake`.
use std::time::{Duration, Instant};

fn spin(us: u64) {
    let t = Instant::now();
    while t.elapsed() < Duration::from_micros(us) {}
}

fn stage_times(threads: usize, gap_us: u64) -> Vec<f64> {
    (0..400)
        .map(|_| {
            spin(gap_us);
            let t = Instant::now();
            rayon::scope(|s| {
                for _ in 0..threads {
                    s.spawn(|_| spin(50));
                }
            });
            t.elapsed().as_secs_f64() * 1e6
        })
        .collect()
}

fn main() {
    let threads: usize = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .map(|a| a.parse().expect("THREADS: a whole number"))
        .unwrap_or(2);
    let pool = liquid_splat::threads::pool(threads).expect("a thread pool");
    println!("{threads} workers; parallel stage: {threads} tasks of 50 us");
    println!(
        "{:>10} {:>12} {:>34}",
        "serial gap", "loop", "stage us: min / median / p90 / max"
    );
    for gap in [0u64, 20, 100, 1000] {
        for awake in [false, true] {
            // Each run starts once the previous run's polls are over (they
            // end 1 ms after its call), with the workers asleep.
            std::thread::sleep(Duration::from_millis(5));
            let mut t = pool.install(|| {
                if awake {
                    liquid_splat::threads::keep_awake(|| stage_times(threads, gap))
                } else {
                    stage_times(threads, gap)
                }
            });
            t.sort_by(f64::total_cmp);
            let q = |p: f64| t[((t.len() - 1) as f64 * p) as usize];
            println!(
                "{:>7} us {:>12} {:>10.1} / {:>6.1} / {:>6.1} / {:>7.1}",
                gap,
                if awake { "keep_awake" } else { "as is" },
                q(0.0),
                q(0.5),
                q(0.9),
                q(1.0)
            );
        }
    }
}
