//! Deformation fields, f32, N = 20,000 Gaussians, 2 threads: forward and
//! forward+backward of the MLP (D8 W256) and the CfC field (D6 W128), the
//! workloads of `liquid-splat bench deform` (see benches/README.md), through
//! the same function `liquid_splat::bench::deform`, median of 10 runs,
//! without the per-operation profiles.

const N: usize = 20_000;

fn main() -> liquid_splat::Result<()> {
    liquid_splat::memory::keep_freed_memory();
    let pool = liquid_splat::bench::harness::thread_pool(2)?;
    pool.install(|| liquid_splat::bench::deform::<f32>(N, 10, None, false))
}
