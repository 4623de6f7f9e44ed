//! The benchmark harness shared by `liquid-splat bench` and `benches/`:
//! timing (untimed warm-up runs, repetitions, median and fastest), the
//! machine and thread description every measurement is printed with, the
//! machine's FMA peak, a cache line's round trip between two workers,
//! process CPU time, and fixed-width tables.

use crate::error::{Error, Result};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Instant;

/// Wall-clock times of the repetitions of one measurement, in seconds.
#[derive(Clone, Debug, Default)]
pub struct Samples(Vec<f64>);

impl Samples {
    /// No samples yet.
    pub fn new() -> Self {
        Samples(Vec::new())
    }

    /// Add one repetition's time in seconds.
    pub fn push(&mut self, seconds: f64) {
        self.0.push(seconds);
    }

    /// Number of repetitions.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The median (the upper one of an even count); NaN without samples.
    pub fn median(&self) -> f64 {
        median(self.0.clone())
    }

    /// The fastest repetition; infinity without samples.
    pub fn min(&self) -> f64 {
        self.0.iter().copied().fold(f64::INFINITY, f64::min)
    }
}

/// The median of `v` (the upper one of an even count); NaN when empty.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// `f()` and its wall-clock time in seconds.
pub fn timed<R>(f: impl FnOnce() -> R) -> (R, f64) {
    let t0 = Instant::now();
    let r = f();
    (r, t0.elapsed().as_secs_f64())
}

/// Time `f`: `warmup` untimed calls (allocations, page faults, caches),
/// then `reps` timed ones (at least one). Stops at the first error.
pub fn repeat<R, E>(
    warmup: usize,
    reps: usize,
    mut f: impl FnMut() -> std::result::Result<R, E>,
) -> std::result::Result<Samples, E> {
    for _ in 0..warmup {
        drop(f()?);
    }
    let mut s = Samples::new();
    for _ in 0..reps.max(1) {
        let (r, t) = timed(&mut f);
        drop(r?);
        s.push(t);
    }
    Ok(s)
}

/// Logical CPUs available to this process ([`crate::threads::cores`]).
pub fn available_cores() -> usize {
    crate::threads::cores()
}

/// The thread counts a scaling measurement runs on: 1 and the current
/// rayon pool's workers (`--threads N`, by default every core; 1 alone on
/// a pool of one).
pub fn one_and_pool_threads() -> Vec<usize> {
    let threads = rayon::current_num_threads();
    if threads > 1 {
        vec![1, threads]
    } else {
        vec![1]
    }
}

/// A rayon pool of `threads` workers, to run a measurement on with
/// `pool.install`.
pub fn thread_pool(threads: usize) -> Result<rayon::ThreadPool> {
    thread_pool_from(threads, 0)
}

/// [`thread_pool`] with its workers pinned from CPU `first` on, when
/// pinning is on ([`crate::threads::pool_from`]).
pub fn thread_pool_from(threads: usize, first: usize) -> Result<rayon::ThreadPool> {
    crate::threads::pool_from(threads, first)
        .map_err(|e| Error::invalid("thread pool", e.to_string()))
}

/// The line every measurement states its threads with: the current rayon
/// pool's workers and the cores the machine reports.
pub fn threads_line() -> String {
    format!(
        "threads: {} (rayon pool{}; machine reports {} available)",
        rayon::current_num_threads(),
        if crate::threads::current_thread_is_pinned() {
            ", each worker pinned to a CPU"
        } else {
            ""
        },
        available_cores()
    )
}

/// The machine's f32 FMA peak in GFLOP/s (2 FLOPs per lane per fused
/// multiply-add) on `threads` threads, each running `iters` rounds of 24
/// (AVX-512) or 12 (AVX2) independent vector FMAs, and the instruction set
/// used; `None` without AVX2+FMA or AVX-512. The ceiling `benches/fma_peak`
/// prints and `bench raster` compares against.
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
            .map(|i| {
                std::thread::spawn(move || {
                    crate::threads::pin_current_thread(i);
                    run(iters)
                })
            })
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

    /// `iters` rounds of 24 independent AVX-512 FMAs; returns their sum so
    /// that nothing is optimised away.
    ///
    /// # Safety
    /// The CPU must support AVX-512F.
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

    /// `iters` rounds of 12 independent AVX2 FMAs; returns their sum so
    /// that nothing is optimised away.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA.
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
        // SAFETY: `out` holds 8 f32, the 32 bytes one unaligned store writes.
        unsafe { _mm256_storeu_ps(out.as_mut_ptr(), s) };
        out.iter().sum()
    }
}

/// Nanoseconds per round trip of one atomic between workers 0 and 1 of
/// `pool`, over `trips` round trips timed by worker 0 after one untimed
/// trip (which both workers reach wherever the pool started them): worker
/// 0 writes each odd value and waits for the next even one, which worker 1
/// writes on seeing it. `None` for a pool of fewer than two workers, or
/// for no trips.
pub fn round_trip_ns(pool: &rayon::ThreadPool, trips: u32) -> Option<f64> {
    if pool.current_num_threads() < 2 || trips == 0 {
        return None;
    }
    let flag = AtomicU32::new(0);
    let times = pool.broadcast(|ctx| {
        let mut start = Instant::now();
        if ctx.index() < 2 {
            for i in 0..=trips {
                if i == 1 {
                    start = Instant::now();
                }
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
        }
        start.elapsed().as_secs_f64() * 1e9 / trips as f64
    });
    Some(times[0])
}

/// [`round_trip_ns`] as the benches report it: the median of 5 batches of
/// 2,000 round trips. `None` for a pool of fewer than two workers.
pub fn round_trip_median_ns(pool: &rayon::ThreadPool) -> Option<f64> {
    let mut v = (0..5)
        .map(|_| round_trip_ns(pool, 2_000))
        .collect::<Option<Vec<f64>>>()?;
    v.sort_by(f64::total_cmp);
    Some(v[2])
}

/// CPU time of the whole process (all threads) in seconds; `None` where not
/// available. On a shared machine, CPU time ÷ threads estimates the wall
/// time the same work would take with the cores to itself.
pub fn process_cpu_seconds() -> Option<f64> {
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

/// A fixed-width text table: each column a header and a width, left-aligned
/// when the width is negative (as `{:<w}`), right-aligned otherwise.
pub struct Table {
    columns: Vec<(String, isize)>,
}

impl Table {
    /// A table of `(header, width)` columns.
    pub fn new(columns: &[(&str, isize)]) -> Self {
        Table {
            columns: columns.iter().map(|&(h, w)| (h.to_string(), w)).collect(),
        }
    }

    /// One line of `cells`, each padded to its column's width (a longer
    /// cell is kept whole), separated by single spaces.
    pub fn line<S: AsRef<str>>(&self, cells: &[S]) -> String {
        self.columns
            .iter()
            .zip(cells)
            .map(|((_, w), c)| {
                let (c, n) = (c.as_ref(), w.unsigned_abs());
                if *w < 0 {
                    format!("{c:<n$}")
                } else {
                    format!("{c:>n$}")
                }
            })
            .collect::<Vec<_>>()
            .join(" ")
    }

    /// The header line.
    pub fn header(&self) -> String {
        let h: Vec<&str> = self.columns.iter().map(|(h, _)| h.as_str()).collect();
        self.line(&h)
    }

    /// Print the header line on stdout.
    pub fn print_header(&self) {
        outln!("{}", self.header());
    }

    /// Print one row on stdout.
    pub fn print_row<S: AsRef<str>>(&self, cells: &[S]) {
        outln!("{}", self.line(cells));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_needs_two_workers_and_returns_a_time() {
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        assert_eq!(round_trip_ns(&one, 100), None);
        // Three workers: the third takes no part and does not hold up the
        // other two.
        let three = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .unwrap();
        let ns = round_trip_ns(&three, 200).expect("a pool of three");
        assert!(ns.is_finite() && ns > 0.0, "{ns}");
        assert_eq!(round_trip_ns(&three, 0), None);
    }

    #[test]
    fn median_min_and_table_layout() {
        let mut s = Samples::new();
        for v in [3.0, 1.0, 2.0, 5.0] {
            s.push(v);
        }
        // Sorted 1, 2, 3, 5: index 4 / 2 = 2.
        assert_eq!(s.median(), 3.0);
        assert_eq!(s.min(), 1.0);
        let t = Table::new(&[("a", -4), ("bb", 5)]);
        assert_eq!(t.header(), "a       bb");
        assert_eq!(t.line(&["xy", "1.5"]), "xy     1.5");
        assert_eq!(t.line(&["toolong", "1"]), "toolong     1");
    }
}
