//! Training configuration with upstream (D-3DGS paper branch) defaults, and
//! the rule that scales every schedule to a shorter run.
//!
//! Upstream trains for 40,000 iterations. A run of `iterations = n` uses
//! `s = n / 40,000` and multiplies every iteration count in the schedule by
//! `s`, rounding to the nearest integer with a floor of 1: the warm-up
//! (3,000), the SH degree interval (1,000), densification start (500), end
//! (15,000) and interval (100), the opacity-reset interval (3,000), the
//! learning-rate decay lengths (30,000 for positions, 40,000 for the field)
//! and the AST noise decay (20,000). Thresholds, learning rates and
//! everything else keep their upstream values. With `n = 40,000` the
//! schedule is exactly upstream's.

/// Upstream's total iteration count, the reference for scaling.
pub const REFERENCE_ITERATIONS: u64 = 40_000;

/// Every iteration count of the schedule.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Schedule {
    /// Iterations with the deformation field off.
    pub warm_up: u64,
    /// The SH degree rises by one at every multiple of this (up to the maximum).
    pub sh_degree_interval: u64,
    pub densify_from: u64,
    pub densify_until: u64,
    pub densification_interval: u64,
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
        let u = Self::upstream();
        Schedule {
            warm_up: f(u.warm_up),
            sh_degree_interval: f(u.sh_degree_interval),
            densify_from: f(u.densify_from),
            densify_until: f(u.densify_until),
            densification_interval: f(u.densification_interval),
            opacity_reset_interval: f(u.opacity_reset_interval),
            position_lr_steps: f(u.position_lr_steps),
            deform_lr_steps: f(u.deform_lr_steps),
            ast_steps: f(u.ast_steps),
        }
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
        assert_eq!(s.densification_interval, 10);
        assert_eq!(s.densify_from, 50);
        assert_eq!(s.deform_lr_steps, 4_000);
        let tiny = Schedule::scaled_to(10);
        assert!(tiny.densification_interval >= 1 && tiny.sh_degree_interval >= 1);
    }
}
