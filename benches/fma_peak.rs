//! The machine's peak f32 FMA rate, the ceiling for the fields' matrix
//! kernels: each thread runs independent AVX-512 (or AVX2) fused
//! multiply-adds on 24 accumulators, enough to cover the FMA latency.
//! `cargo bench --bench fma_peak` prints GFLOP/s (2 FLOPs per lane per FMA)
//! for 1 thread and for every core.

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

#[cfg(target_arch = "x86_64")]
fn main() {
    let (name, flop_per_iter, run): (&str, f64, fn(usize) -> f32) =
        if std::is_x86_feature_detected!("avx512f") {
            // SAFETY: the CPU has AVX-512F (checked above).
            ("AVX-512", 24.0 * 16.0 * 2.0, |n| unsafe { peak::avx512(n) })
        } else if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX2 and FMA (checked above).
            ("AVX2", 12.0 * 8.0 * 2.0, |n| unsafe { peak::avx2(n) })
        } else {
            println!("fma_peak: no AVX2+FMA or AVX-512 on this CPU");
            return;
        };
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let iters = 50_000_000;
    for threads in [1, cores] {
        let t0 = std::time::Instant::now();
        let sum: f32 = (0..threads)
            .map(|_| std::thread::spawn(move || run(iters)))
            .collect::<Vec<_>>()
            .into_iter()
            .map(|h| h.join().expect("worker thread"))
            .sum();
        let s = t0.elapsed().as_secs_f64();
        println!(
            "{name} f32 FMA peak, {threads} thread(s): {:.1} GFLOP/s (checksum {sum:.3})",
            threads as f64 * iters as f64 * flop_per_iter / s / 1e9
        );
    }
}

#[cfg(not(target_arch = "x86_64"))]
fn main() {
    println!("fma_peak: x86-64 only");
}
