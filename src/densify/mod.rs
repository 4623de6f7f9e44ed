//! Adaptive density control of D-3DGS (docs/UPSTREAM.md §6.5, paper-branch values):
//! gradient statistics, the clone / split / prune policy, and its application
//! to parameters, Adam state and statistics in one place.
//!
//! - [`stats`]: `accum`, `denom`, `max_radii` updated from each render.
//! - [`policy`]: which Gaussians to clone, split, prune.
//! - [`apply`]: [`apply::densify_and_prune`] and [`apply::reset_opacity`].
//!
//! Schedule (the trainer's job): statistics every iteration below 15,000;
//! densify when `iteration > 500 && iteration % 100 == 0`; reset opacity when
//! `iteration % 3000 == 0`. On a densify iteration upstream updates no
//! Gaussian parameter (the optimizer sees fresh tensors without gradients);
//! on a reset-only iteration the opacity group is not updated
//! (see [`crate::optim::StepGroups`]).

pub mod apply;
pub mod policy;
pub mod stats;

pub use apply::{densify_and_prune, reset_opacity, DensifyReport};
pub use policy::DensifyConfig;
pub use stats::DensifyStats;

#[cfg(test)]
mod tests;
