//! Learning-rate schedules and the AST noise scale of D-3DGS (docs/UPSTREAM.md §6.4,
//! §6.6), computed in f64 as the upstream numpy code does.
//!
//! The transcendental functions are the pinned `libm`'s, not numpy's, so a
//! value may differ from upstream in the last bit of an f64.

use crate::gaussians::Group;

/// `get_expon_lr_func` with `lr_delay_steps = 0` (so the delay factor is 1):
/// 0 for `step < 0` (or when both rates are 0), otherwise
/// `exp(ln(lr_init)·(1 − t) + ln(lr_final)·t)` with `t = clip(step / max_steps, 0, 1)`.
pub fn expon_lr(step: i64, lr_init: f64, lr_final: f64, max_steps: u64) -> f64 {
    if step < 0 || (lr_init == 0.0 && lr_final == 0.0) {
        return 0.0;
    }
    let t = clip01(step as f64 / max_steps.max(1) as f64);
    libm::exp(libm::log(lr_init) * (1.0 - t) + libm::log(lr_final) * t)
}

/// `get_linear_noise_func` with no delay: 0 for `step < 0`, otherwise
/// `init·(1 − t) + final·t`, `t = clip(step / max_steps, 0, 1)`.
pub fn linear_lr(step: i64, init: f64, fin: f64, max_steps: u64) -> f64 {
    if step < 0 || (init == 0.0 && fin == 0.0) {
        return 0.0;
    }
    let t = clip01(step as f64 / max_steps.max(1) as f64);
    init * (1.0 - t) + fin * t
}

fn clip01(t: f64) -> f64 {
    t.clamp(0.0, 1.0)
}

/// Learning rates of one Gaussian optimizer step, one per upstream param
/// group (the [`Sh`](Group::Sh) group has two: `f_dc` and `f_rest`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GroupLrs {
    /// Canonical means.
    pub xyz: f64,
    /// SH coefficient 0.
    pub f_dc: f64,
    /// SH coefficients 1..K.
    pub f_rest: f64,
    /// Opacity logits.
    pub opacity: f64,
    /// Log scales.
    pub scaling: f64,
    /// Raw quaternions.
    pub rotation: f64,
}

impl GroupLrs {
    /// The rates of `group`'s elements as [`AdamState::step_periodic`]
    /// takes them, with `coeffs` SH coefficients: one rate, or for
    /// [`Group::Sh`] one row `[K, 3]` (`f_dc` for coefficient 0, `f_rest`
    /// for the others).
    ///
    /// [`AdamState::step_periodic`]: super::AdamState::step_periodic
    pub fn periodic(&self, group: Group, coeffs: usize) -> Vec<f64> {
        match group {
            Group::Xyz => vec![self.xyz],
            Group::Sh => {
                let mut rates = vec![self.f_rest; 3 * coeffs];
                rates[..3].fill(self.f_dc);
                rates
            }
            Group::Opacity => vec![self.opacity],
            Group::Scaling => vec![self.scaling],
            Group::Rotation => vec![self.rotation],
        }
    }
}

/// Learning rates of one optimizer step of a whole model: the Gaussian
/// groups' and the field weights'.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepRates {
    /// The Gaussian groups' rates.
    pub gaussians: GroupLrs,
    /// The field weights' rate.
    pub field: f64,
}

impl StepRates {
    /// The names of the seven rates, in [`to_array`](Self::to_array)'s order.
    pub const NAMES: [&'static str; 7] = [
        "xyz", "f_dc", "f_rest", "opacity", "scaling", "rotation", "field",
    ];

    /// The rates in [`NAMES`](Self::NAMES)' order.
    pub fn to_array(&self) -> [f64; 7] {
        let g = &self.gaussians;
        [
            g.xyz, g.f_dc, g.f_rest, g.opacity, g.scaling, g.rotation, self.field,
        ]
    }

    /// The rates from values in [`NAMES`](Self::NAMES)' order.
    pub fn from_array(v: [f64; 7]) -> Self {
        StepRates {
            gaussians: GroupLrs {
                xyz: v[0],
                f_dc: v[1],
                f_rest: v[2],
                opacity: v[3],
                scaling: v[4],
                rotation: v[5],
            },
            field: v[6],
        }
    }
}

/// Every learning rate and schedule of D-3DGS training, with the upstream
/// defaults (R2p, `spatial_lr_scale = 5` already applied).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LearningRates {
    /// xyz: `position_lr_init · 5`.
    pub xyz_init: f64,
    /// xyz: `position_lr_final · 5`.
    pub xyz_final: f64,
    /// xyz: `position_lr_max_steps`.
    pub xyz_max_steps: u64,
    /// Deformation network: `position_lr_init · 5`.
    pub deform_init: f64,
    /// Deformation network: final rate (not multiplied by 5 upstream).
    pub deform_final: f64,
    /// Deformation network: `deform_lr_max_steps`.
    pub deform_max_steps: u64,
    /// SH coefficient 0 (`feature_lr`).
    pub f_dc: f64,
    /// `feature_lr / 20`.
    pub f_rest: f64,
    /// Opacity logits.
    pub opacity: f64,
    /// `scaling_lr · 5`.
    pub scaling: f64,
    /// Raw quaternions.
    pub rotation: f64,
    /// AST smooth term at step 0.
    pub ast_init: f64,
    /// AST smooth term at and after `ast_max_steps`.
    pub ast_final: f64,
    /// Steps over which the AST term decays linearly.
    pub ast_max_steps: u64,
}

/// Training length the upstream schedules are written for.
pub const REFERENCE_ITERATIONS: u64 = 40_000;

impl Default for LearningRates {
    fn default() -> Self {
        LearningRates {
            xyz_init: 0.00016 * 5.0,
            xyz_final: 0.0000016 * 5.0,
            xyz_max_steps: 30_000,
            deform_init: 0.00016 * 5.0,
            deform_final: 0.0000016,
            deform_max_steps: 40_000,
            f_dc: 0.0025,
            f_rest: 0.0025 / 20.0,
            opacity: 0.05,
            scaling: 0.001 * 5.0,
            rotation: 0.001,
            ast_init: 0.1,
            ast_final: 1e-15,
            ast_max_steps: 20_000,
        }
    }
}

impl LearningRates {
    /// The rates of every group before any step: the initial rates of the
    /// xyz and field schedules (not evaluated through `exp`/`ln`).
    pub fn initial(&self) -> StepRates {
        StepRates {
            gaussians: GroupLrs {
                xyz: self.xyz_init,
                ..self.gaussian(0)
            },
            field: self.deform_init,
        }
    }

    /// The rates of the optimizer step at `step` (iteration `step + 1`):
    /// [`gaussian`](Self::gaussian) and [`deform`](Self::deform) at `step`.
    pub fn at(&self, step: i64) -> StepRates {
        StepRates {
            gaussians: self.gaussian(step),
            field: self.deform(step),
        }
    }

    /// The same schedules compressed (or stretched) for a run of `iterations`
    /// steps instead of `reference` (normally [`REFERENCE_ITERATIONS`]): every
    /// step count (`xyz_max_steps`, `deform_max_steps`, `ast_max_steps`) is
    /// multiplied by `iterations / reference`, rounded to the nearest integer
    /// (halves up) and at least 1. Rates are unchanged, so a short run sweeps
    /// the same range of rates. `scaled_to(40_000, 40_000)` is the identity.
    /// A `reference` of 0 is treated as 1.
    pub fn scaled_to(&self, iterations: u64, reference: u64) -> Self {
        let r = reference.max(1) as u128;
        let scale = |steps: u64| -> u64 {
            let s = (steps as u128 * iterations as u128 + r / 2) / r;
            s.clamp(1, u64::MAX as u128) as u64
        };
        LearningRates {
            xyz_max_steps: scale(self.xyz_max_steps),
            deform_max_steps: scale(self.deform_max_steps),
            ast_max_steps: scale(self.ast_max_steps),
            ..*self
        }
    }

    /// xyz learning rate `lr_xyz(step)`.
    pub fn xyz(&self, step: i64) -> f64 {
        expon_lr(step, self.xyz_init, self.xyz_final, self.xyz_max_steps)
    }

    /// Deformation-network learning rate `lr_deform(step)`.
    pub fn deform(&self, step: i64) -> f64 {
        expon_lr(
            step,
            self.deform_init,
            self.deform_final,
            self.deform_max_steps,
        )
    }

    /// AST smooth term `0.1·(1 − t) + 1e-15·t`, `t = clip(step / 20000, 0, 1)`.
    pub fn ast_smooth(&self, step: i64) -> f64 {
        linear_lr(step, self.ast_init, self.ast_final, self.ast_max_steps)
    }

    /// The Gaussian groups' rates with xyz at `lr_xyz(xyz_step)`.
    ///
    /// Upstream sets the xyz rate after each optimizer step, so the update at
    /// iteration `i` uses `xyz_step = i − 1` (iteration 1 uses `lr_xyz(0)`,
    /// which equals the initial rate).
    pub fn gaussian(&self, xyz_step: i64) -> GroupLrs {
        GroupLrs {
            xyz: self.xyz(xyz_step),
            f_dc: self.f_dc,
            f_rest: self.f_rest,
            opacity: self.opacity,
            scaling: self.scaling,
            rotation: self.rotation,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xyz_schedule_end_points_and_midpoint() {
        let lr = LearningRates::default();
        assert_eq!(lr.xyz(-1), 0.0);
        assert!((lr.xyz(0) - 8e-4).abs() < 1e-18);
        assert!((lr.xyz(30_000) - 8e-6).abs() < 1e-19);
        assert!((lr.xyz(100_000) - 8e-6).abs() < 1e-19);
        // Log-linear: the midpoint is the geometric mean.
        assert!((lr.xyz(15_000) - (8e-4f64 * 8e-6).sqrt()).abs() < 1e-18);
        assert!((lr.deform(40_000) - 1.6e-6).abs() < 1e-20);
        // docs/UPSTREAM.md §9.9: at 20k of a 40k deform schedule the rate is ≈ 3.58e-5.
        assert!((lr.deform(20_000) - 3.5777e-5).abs() < 1e-8);
    }

    #[test]
    fn ast_term_is_linear() {
        let lr = LearningRates::default();
        assert_eq!(lr.ast_smooth(0), 0.1);
        assert!((lr.ast_smooth(10_000) - (0.05 + 0.5e-15)).abs() < 1e-17);
        assert_eq!(lr.ast_smooth(20_000), 1e-15);
        assert_eq!(lr.ast_smooth(50_000), 1e-15);
        assert_eq!(lr.ast_smooth(-5), 0.0);
    }

    #[test]
    fn scaling_the_schedules() {
        let lr = LearningRates::default();
        assert_eq!(lr.scaled_to(40_000, REFERENCE_ITERATIONS), lr);
        let s = lr.scaled_to(2_000, REFERENCE_ITERATIONS);
        assert_eq!(
            (s.xyz_max_steps, s.deform_max_steps, s.ast_max_steps),
            (1_500, 2_000, 1_000)
        );
        assert_eq!(s.xyz(750), lr.xyz(15_000));
        assert_eq!(lr.scaled_to(0, 40_000).xyz_max_steps, 1);
        let g = lr.gaussian(0);
        let got = [g.f_dc, g.f_rest, g.opacity, g.scaling, g.rotation];
        for (a, b) in got.iter().zip([0.0025, 0.000125, 0.05, 0.005, 0.001]) {
            assert!((a - b).abs() < 1e-18, "{a} vs {b}");
        }
    }
}
