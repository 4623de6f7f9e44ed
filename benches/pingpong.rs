//! How long a cache line takes to go from one CPU to another and back
//! (`cargo bench --bench pingpong`): two threads, pinned to the first two
//! CPUs the process may use (on a larger machine these may be two
//! hardware threads of one core), hand one atomic back and forth in 200
//! batches of 1,000 round trips, five rounds; prints the CPUs and, per
//! round, the fastest and the median batch in ns per round trip (a batch
//! in which the operating system or the hypervisor paused one thread
//! moves the slow end, not the median). On the development VM the median
//! read 47–49 ns in quiet minutes and 347–382 ns in the slow periods in
//! which the rasterizer's two-thread stages slow down (benches/README.md,
//! "The machine's slow periods"). Linux only (elsewhere it says so).
const BATCHES: usize = 200;
const TRIPS: u32 = 1_000;

fn main() {
    liquid_splat::threads::set_pinning(true);
    if !liquid_splat::threads::pinning() || liquid_splat::threads::cores() < 2 {
        println!("needs Linux, pinning and two CPUs: nothing to measure here");
        return;
    }
    let pool = liquid_splat::threads::pool(2).expect("a pool of 2 pinned threads");
    #[cfg(target_os = "linux")]
    {
        // SAFETY: `sched_getcpu` takes no arguments and only reads.
        let cpus = pool.broadcast(|_| unsafe { libc::sched_getcpu() });
        println!("workers 0 and 1 on CPUs {} and {}", cpus[0], cpus[1]);
        if cpus[0] == cpus[1] {
            println!(
                "both on one CPU (pinning refused?): the numbers below are not a cache line's trip"
            );
        }
    }
    for _ in 0..5 {
        let mut t: Vec<f64> = (0..BATCHES)
            .map(|_| {
                liquid_splat::bench::harness::round_trip_ns(&pool, TRIPS)
                    .expect("a pool of 2 threads")
            })
            .collect();
        t.sort_by(f64::total_cmp);
        println!(
            "ns per round trip, fastest / median batch: {:.1} / {:.1}",
            t[0],
            t[t.len() / 2]
        );
    }
}
