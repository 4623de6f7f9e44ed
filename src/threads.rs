//! Worker pools for the command-line tool and the benchmarks: `n` rayon
//! workers, optionally each pinned to a CPU of its own (`--pin-threads`).
//!
//! Why pinning exists: on a machine with few cores, Linux sometimes wakes a
//! pool's second worker on the CPU where the first is running, and short
//! parallel stages then run on one CPU. Measured on a 2-core machine with
//! `bench raster`: the 64×64 frame's forward at 2 threads took 0.48–0.50 ms
//! in three pinned runs, and 0.44–0.81 ms unpinned, the slow runs with every
//! stage on one CPU. Pinned, worker `i` runs only on the `i`-th CPU (modulo
//! their count) of the CPUs the process could use when pinning was turned
//! on.
//!
//! Off by default: two pinned processes started side by side would share the
//! same CPUs. Pinning changes speed only, never results; where the operating
//! system is not Linux it does nothing.

use std::sync::atomic::{AtomicBool, Ordering};

/// Whether pools built by [`pool`] pin their workers.
static PIN: AtomicBool = AtomicBool::new(false);

/// The CPUs the process could use when pinning was first turned on (a
/// pinned worker's own set is one CPU, so it is read once, beforehand).
#[cfg(target_os = "linux")]
static CPUS: std::sync::OnceLock<Vec<usize>> = std::sync::OnceLock::new();

/// Make every later [`pool`] pin its workers (`true`) or not. Call it from
/// a thread that is not pinned (the command-line tool does, first thing):
/// the CPUs to pin to are the ones the calling thread may use then.
pub fn set_pinning(on: bool) {
    #[cfg(target_os = "linux")]
    if on {
        CPUS.get_or_init(allowed_cpus);
    }
    PIN.store(on, Ordering::Relaxed);
}

/// Whether [`pool`] pins its workers (and the platform can).
pub fn pinning() -> bool {
    PIN.load(Ordering::Relaxed) && cfg!(target_os = "linux")
}

/// A rayon pool of `threads` workers, pinned one per CPU when
/// [`pinning`] is on.
pub fn pool(threads: usize) -> Result<rayon::ThreadPool, rayon::ThreadPoolBuildError> {
    let builder = rayon::ThreadPoolBuilder::new().num_threads(threads);
    #[cfg(target_os = "linux")]
    if pinning() {
        let cpus = CPUS.get_or_init(allowed_cpus).clone();
        if !cpus.is_empty() {
            return builder
                .start_handler(move |i| pin_to(cpus[i % cpus.len()]))
                .build();
        }
    }
    builder.build()
}

/// Start rayon's global pool with one worker per core, pinned when
/// [`pinning`] is on; does nothing if the global pool already runs.
pub fn pin_global_pool() {
    let builder = rayon::ThreadPoolBuilder::new();
    #[cfg(target_os = "linux")]
    if pinning() {
        let cpus = CPUS.get_or_init(allowed_cpus).clone();
        if !cpus.is_empty() {
            let _ = builder
                .num_threads(cpus.len())
                .start_handler(move |i| pin_to(cpus[i % cpus.len()]))
                .build_global();
        }
    }
}

/// The CPUs this process may run on, ascending (empty if the system does
/// not say).
#[cfg(target_os = "linux")]
fn allowed_cpus() -> Vec<usize> {
    // SAFETY: `cpu_set_t` is plain data for which all-zero is the empty set;
    // `sched_getaffinity` writes at most `size_of::<cpu_set_t>()` bytes into
    // it, and `CPU_ISSET` reads it within bounds (`CPU_SETSIZE`).
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut set) != 0 {
            return Vec::new();
        }
        (0..libc::CPU_SETSIZE as usize)
            .filter(|&c| libc::CPU_ISSET(c, &set))
            .collect()
    }
}

/// Restrict the calling thread to `cpu` (best effort: a refusal leaves it
/// unpinned, which changes only speed).
#[cfg(target_os = "linux")]
fn pin_to(cpu: usize) {
    // SAFETY: as in `allowed_cpus`; `cpu < CPU_SETSIZE` since it came from
    // that range, and pid 0 is the calling thread.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        let _ = libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &set);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pinned_pools_run_and_give_the_same_sums() {
        use rayon::prelude::*;
        let v: Vec<f64> = (0..10_000).map(|i| (i as f64).sin()).collect();
        let sum = |p: &rayon::ThreadPool| {
            p.install(|| {
                v.par_chunks(100)
                    .map(|c| c.iter().sum::<f64>())
                    .collect::<Vec<_>>()
            })
        };
        let plain = sum(&pool(3).unwrap());
        set_pinning(true);
        let pinned = pool(3).unwrap();
        set_pinning(false);
        assert_eq!(sum(&pinned), plain);
        #[cfg(target_os = "linux")]
        {
            // Each worker runs on exactly one CPU.
            let counts = pinned.broadcast(|_| allowed_cpus().len());
            assert!(counts.iter().all(|&c| c == 1), "{counts:?}");
        }
    }
}
