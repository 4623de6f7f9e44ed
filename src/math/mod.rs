//! Math at the bottom of the crate: depends on nothing else in it.
//!
//! - [`real`]: the `Real` scalar trait (f32 / f64) over one pinned math library.
//! - [`rng`]: the seeded, portable random number generator.
//! - [`vec`](mod@vec), [`quat`]: small vectors and 3×3 matrices (arrays generic over
//!   `Real`, glam's f64 types for camera geometry), quaternions and their
//!   rotation matrices.
//! - [`sh`], [`covariance`]: spherical-harmonics colour and 3D covariance, each with its vjp.
//! - [`pack`]: the arithmetic the per-Gaussian vjps are written in, on one
//!   number or on several lanes with the same bits.
//! - [`sum`]: pairwise sums in a fixed order (error growing with log n).
//! - [`gradcheck`]: central finite differences in f64 for every hand-written backward.

pub mod covariance;
pub mod fast;
pub mod gradcheck;
pub mod pack;
pub mod quat;
pub mod real;
pub mod rng;
pub mod sh;
pub mod sum;
pub mod vec;

pub use real::{Precision, Real, MATH_LIBRARY};

/// The first value of `values` that is NaN or infinite, with its index.
pub fn first_non_finite<T: Real>(values: &[T]) -> Option<(usize, T)> {
    values
        .iter()
        .copied()
        .enumerate()
        .find(|(_, v)| !v.to_f64().is_finite())
}
pub use rng::Rng;
