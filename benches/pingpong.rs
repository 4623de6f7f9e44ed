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
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Instant;

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
        let flag = AtomicU32::new(0);
        // Worker 0 sends odd values and waits for the next even one; worker
        // 1 answers each odd value with the next even one. Worker 0 times
        // each batch.
        let times = pool.broadcast(|ctx| {
            let mut batches = Vec::with_capacity(BATCHES);
            for b in 0..BATCHES as u32 {
                let t = Instant::now();
                for i in b * TRIPS..(b + 1) * TRIPS {
                    let (wait_for, send) = if ctx.index() == 0 {
                        (2 * i, 2 * i + 1)
                    } else {
                        (2 * i + 1, 2 * i + 2)
                    };
                    while flag.load(Ordering::Acquire) != wait_for {
                        std::hint::spin_loop();
                    }
                    flag.store(send, Ordering::Release);
                }
                batches.push(t.elapsed().as_secs_f64() * 1e9 / TRIPS as f64);
            }
            batches
        });
        let mut t = times[0].clone();
        t.sort_by(f64::total_cmp);
        println!(
            "ns per round trip, fastest / median batch: {:.1} / {:.1}",
            t[0],
            t[t.len() / 2]
        );
    }
}
