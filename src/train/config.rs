//! Training configuration with upstream (D-3DGS paper branch) defaults, and
//! the rule that scales every schedule to a shorter run.
//!
//! Upstream trains for 40,000 iterations. A run of `iterations = n` uses
//! `s = n / 40,000`:
//! - every *position in the run* is multiplied by `s`: the warm-up (3,000),
//!   the SH degree interval (1,000), densification start (500) and end
//!   (15,000), the learning-rate decay lengths (30,000 for positions, 40,000
//!   for the field) and the AST noise decay (20,000);
//! - the two *intervals between interventions*, densification (100) and
//!   opacity reset (3,000), are multiplied by `√s`. After a densification or
//!   an opacity reset the optimizer needs a number of steps to recover that
//!   does not shrink with the run; scaling these linearly would densify every
//!   iteration and reset opacities faster than they recover in short runs.
//!   With `√s` the number of interventions falls as `√s` instead.
//!
//! Counts are rounded to the nearest integer (halves away from zero), with a
//! floor of 1. Thresholds, learning rates and everything else keep their
//! upstream values. With `n = 40,000`, `s = 1` and the schedule is exactly
//! upstream's.

/// Upstream's total iteration count, the reference for scaling.
pub const REFERENCE_ITERATIONS: u64 = 40_000;

use crate::deform::{FieldConfig, Variant};
use crate::densify::DensifyConfig;
use crate::error::{Error, Result};
use crate::optim::LearningRates;

/// Every iteration count of the schedule.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Schedule {
    /// Iterations with the deformation field off.
    pub warm_up: u64,
    /// The SH degree rises by one at every multiple of this (up to the maximum).
    pub sh_degree_interval: u64,
    /// First iteration after which densification runs.
    pub densify_from: u64,
    /// Iteration from which statistics and densification stop.
    pub densify_until: u64,
    /// Densify at every multiple of this (after `densify_from`).
    pub densification_interval: u64,
    /// Reset opacities at every multiple of this.
    pub opacity_reset_interval: u64,
    /// Decay length of the position learning rate.
    pub position_lr_steps: u64,
    /// Decay length of the field's learning rate.
    pub deform_lr_steps: u64,
    /// Decay length of the AST time noise.
    pub ast_steps: u64,
}

impl Schedule {
    /// Upstream's schedule (for 40,000 iterations).
    pub fn upstream() -> Self {
        Schedule {
            warm_up: 3_000,
            sh_degree_interval: 1_000,
            densify_from: 500,
            densify_until: 15_000,
            densification_interval: 100,
            opacity_reset_interval: 3_000,
            position_lr_steps: 30_000,
            deform_lr_steps: 40_000,
            ast_steps: 20_000,
        }
    }

    /// Upstream's schedule scaled to `iterations` (see the module docs).
    pub fn scaled_to(iterations: u64) -> Self {
        let s = iterations as f64 / REFERENCE_ITERATIONS as f64;
        let f = |n: u64| ((n as f64 * s).round() as u64).max(1);
        let g = |n: u64| ((n as f64 * s.sqrt()).round() as u64).max(1);
        let u = Self::upstream();
        Schedule {
            warm_up: f(u.warm_up),
            sh_degree_interval: f(u.sh_degree_interval),
            densify_from: f(u.densify_from),
            densify_until: f(u.densify_until),
            densification_interval: g(u.densification_interval),
            opacity_reset_interval: g(u.opacity_reset_interval),
            position_lr_steps: f(u.position_lr_steps),
            deform_lr_steps: f(u.deform_lr_steps),
            ast_steps: f(u.ast_steps),
        }
    }
}

/// Everything that defines a training run besides the data. Two runs with
/// equal configurations and equal data give bit-identical results.
#[derive(Clone, Debug, PartialEq)]
pub struct TrainConfig {
    /// Total iterations (upstream 40,000).
    pub iterations: u64,
    /// Seed of the run: camera order, field initialisation, AST noise and
    /// split sampling all derive from it.
    pub seed: u64,
    /// The deformation field.
    pub field: FieldConfig,
    /// Every iteration count, scaled to `iterations`.
    pub schedule: Schedule,
    /// Learning rates; decay lengths scaled to `iterations`.
    pub lr: LearningRates,
    /// Densification thresholds (`screen_size_after` follows the schedule's
    /// opacity-reset interval).
    pub densify: DensifyConfig,
    /// Weight of `1 − SSIM` in the loss (0.2).
    pub lambda_dssim: f64,
    /// Highest SH degree (3).
    pub max_sh_degree: usize,
    /// AST time noise (upstream: on for real scenes, off for D-NeRF).
    pub ast: bool,
}

/// The most training iterations a run may have (the paper's runs have
/// 40,000; the schedules' arithmetic stays far from overflow).
pub const MAX_ITERATIONS: u64 = 1_000_000_000;

impl TrainConfig {
    /// Upstream's settings scaled to `iterations` (module docs), with `field`.
    /// AST noise follows the field's variant: on for [`Variant::Real`].
    pub fn new(iterations: u64, seed: u64, field: FieldConfig) -> Self {
        let schedule = Schedule::scaled_to(iterations);
        let densify = DensifyConfig {
            screen_size_after: schedule.opacity_reset_interval,
            ..DensifyConfig::default()
        };
        TrainConfig {
            iterations,
            seed,
            ast: field.variant() == Variant::Real,
            field,
            lr: LearningRates::default().scaled_to(iterations, REFERENCE_ITERATIONS),
            schedule,
            densify,
            lambda_dssim: crate::loss::LAMBDA_DSSIM,
            max_sh_degree: 3,
        }
    }

    /// Check the values a run depends on.
    pub fn validate(&self) -> Result<()> {
        if !(1..=MAX_ITERATIONS).contains(&self.iterations) {
            return Err(Error::invalid(
                "iterations",
                format!("{} (1 to {MAX_ITERATIONS})", self.iterations),
            ));
        }
        if self.max_sh_degree > 3 {
            return Err(Error::invalid(
                "max_sh_degree",
                format!("{} (at most 3)", self.max_sh_degree),
            ));
        }
        if !(0.0..=1.0).contains(&self.lambda_dssim) {
            return Err(Error::invalid(
                "lambda_dssim",
                format!("{} (must be in [0, 1])", self.lambda_dssim),
            ));
        }
        self.field.validate()
    }

    /// A stable text form of the configuration, stored in checkpoints: a
    /// resumed run must have the same one.
    pub fn fingerprint(&self) -> String {
        format!("{self:?}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn full_length_schedule_is_upstream() {
        assert_eq!(Schedule::scaled_to(40_000), Schedule::upstream());
    }

    #[test]
    fn short_run_scales_every_count() {
        let s = Schedule::scaled_to(4_000);
        assert_eq!(s.warm_up, 300);
        // s = 0.1: positions × 0.1, intervals × √0.1.
        assert_eq!(s.densification_interval, 32);
        assert_eq!(s.opacity_reset_interval, 949);
        assert_eq!(s.densify_from, 50);
        assert_eq!(s.deform_lr_steps, 4_000);
        let tiny = Schedule::scaled_to(10);
        assert!(tiny.densification_interval >= 1 && tiny.sh_degree_interval >= 1);
    }
}
