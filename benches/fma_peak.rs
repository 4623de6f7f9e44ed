//! The machine's peak f32 FMA rate, the ceiling for the fields' matrix
//! kernels: each thread runs independent AVX-512 (or AVX2) fused
//! multiply-adds on 24 accumulators, enough to cover the FMA latency.
//! `cargo bench --bench fma_peak` prints GFLOP/s (2 FLOPs per lane per FMA)
//! for 1 thread and for every core. The kernel is
//! `liquid_splat::bench::harness::fma_peak`, which `bench raster` also uses.

fn main() {
    let cores = liquid_splat::bench::harness::available_cores();
    for threads in [1, cores] {
        match liquid_splat::bench::harness::fma_peak(threads, 50_000_000) {
            Some((name, gflops)) => {
                println!("{name} f32 FMA peak, {threads} thread(s): {gflops:.1} GFLOP/s")
            }
            None => {
                println!("fma_peak: no AVX2+FMA or AVX-512 on this CPU (or not x86-64)");
                return;
            }
        }
    }
}
