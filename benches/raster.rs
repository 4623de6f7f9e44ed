//! Rasterizer forward and backward (f32, SH degree 3) at 800x800 with 50,000
//! Gaussians, 400x400 with 20,000 and 64x64 with 2,600, on 1 and 2 threads:
//! `liquid_splat::bench::raster`, the measurement `liquid-splat bench raster`
//! runs (there on 1 thread and every core), in 10 rounds.

fn main() -> liquid_splat::Result<()> {
    liquid_splat::memory::keep_freed_memory();
    liquid_splat::bench::raster(10, &[1, 2])
}
