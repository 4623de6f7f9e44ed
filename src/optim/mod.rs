//! Optimisation: Adam with PyTorch semantics, the D-3DGS learning-rate
//! schedules, and the Adam groups of the Gaussian parameters.
//!
//! - [`adam`]: element-wise Adam (torch 1.13 single-tensor formula order).
//! - [`schedule`]: `get_expon_lr_func`, the AST noise scale, [`LearningRates`].
//!
//! ## Gaussian groups
//! Upstream has six param groups: xyz, f_dc, f_rest, opacity, scaling,
//! rotation. Here the SH coefficients are one array `[N, K, 3]`, so f_dc
//! (coefficient 0) and f_rest (coefficients 1..K) share **one** [`AdamState`]
//! stepped with a per-coefficient learning rate
//! ([`AdamState::step_periodic`] with period `3K`). This is exact because
//! Adam is element-wise and the two upstream groups always step together:
//! their step counters are always equal (densification and opacity reset
//! never touch one without the other).

pub mod adam;
pub mod schedule;

pub use adam::{AdamConfig, AdamState};
pub use schedule::{GroupLrs, LearningRates};

use crate::error::{Error, Result};
use crate::gaussians::Gaussians;
use crate::math::Real;

/// The Adam states of the canonical Gaussians, one per parameter array.
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianOptimizer<T> {
    pub xyz: AdamState<T>,
    /// f_dc and f_rest together, `[N, K, 3]`.
    pub sh: AdamState<T>,
    pub opacity: AdamState<T>,
    pub scaling: AdamState<T>,
    pub rotation: AdamState<T>,
}

/// Which groups an optimizer step updates.
///
/// Upstream, a densify/prune iteration replaces every parameter tensor before
/// `optimizer.step()`, so no Gaussian group steps that iteration; a reset-only
/// iteration replaces the opacity tensor only, so every group but opacity
/// steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StepGroups {
    /// Every group steps.
    All,
    /// Every group except opacity steps (reset-only iteration).
    AllButOpacity,
    /// Nothing steps (densification iteration).
    None,
}

impl<T: Real> GaussianOptimizer<T> {
    /// Zero state for `gaussians` (their sizes), default hyper-parameters.
    pub fn new(gaussians: &Gaussians<T>) -> Self {
        GaussianOptimizer {
            xyz: AdamState::new(gaussians.xyz.len()),
            sh: AdamState::new(gaussians.sh.len()),
            opacity: AdamState::new(gaussians.opacity.len()),
            scaling: AdamState::new(gaussians.scaling.len()),
            rotation: AdamState::new(gaussians.rotation.len()),
        }
    }

    /// Number of Gaussians the state is sized for.
    pub fn len(&self) -> usize {
        self.opacity.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity.is_empty()
    }

    /// One step of the selected groups. `grads` holds `dL/d(raw parameter)`
    /// in the same layout as `params` (a [`Gaussians`] used as a gradient
    /// container). Errors, without changing anything, if the sizes disagree.
    pub fn step(
        &mut self,
        params: &mut Gaussians<T>,
        grads: &Gaussians<T>,
        lrs: &GroupLrs,
        groups: StepGroups,
    ) -> Result<()> {
        params.validate()?;
        grads.validate()?;
        if grads.len() != params.len()
            || grads.max_sh_degree != params.max_sh_degree
            || self.len() != params.len()
            || self.sh.len() != params.sh.len()
        {
            return Err(Error::invalid(
                "Gaussian optimizer step",
                format!(
                    "{} Gaussians (degree {}), gradients for {} (degree {}), state for {}",
                    params.len(),
                    params.max_sh_degree,
                    grads.len(),
                    grads.max_sh_degree,
                    self.len()
                ),
            ));
        }
        if groups == StepGroups::None {
            return Ok(());
        }
        let k = params.coeffs();
        let mut sh_lrs = vec![lrs.f_rest; 3 * k];
        sh_lrs[..3].fill(lrs.f_dc);
        self.xyz.step(&mut params.xyz, &grads.xyz, lrs.xyz)?;
        self.sh.step_periodic(&mut params.sh, &grads.sh, &sh_lrs)?;
        if groups == StepGroups::All {
            self.opacity
                .step(&mut params.opacity, &grads.opacity, lrs.opacity)?;
        }
        self.scaling
            .step(&mut params.scaling, &grads.scaling, lrs.scaling)?;
        self.rotation
            .step(&mut params.rotation, &grads.rotation, lrs.rotation)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two_gaussians() -> Gaussians<f64> {
        Gaussians {
            max_sh_degree: 1,
            xyz: vec![0.0; 6],
            sh: vec![0.0; 24],
            scaling: vec![0.0; 6],
            rotation: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            opacity: vec![0.0; 2],
        }
    }

    #[test]
    fn groups_use_their_rates() {
        let mut p = two_gaussians();
        let mut g = two_gaussians();
        for v in [
            &mut g.xyz,
            &mut g.sh,
            &mut g.scaling,
            &mut g.rotation,
            &mut g.opacity,
        ] {
            v.fill(1.0);
        }
        let mut opt = GaussianOptimizer::new(&p);
        let lrs = LearningRates::default().gaussian(0);
        opt.step(&mut p, &g, &lrs, StepGroups::AllButOpacity)
            .unwrap();
        // First Adam step moves each element by ≈ −lr.
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        assert!(close(p.xyz[0], -lrs.xyz));
        // sh of Gaussian 1: coefficient 0 (DC) at 12..15, coefficient 1 at 15..18.
        assert!(close(p.sh[12], -lrs.f_dc) && close(p.sh[14], -lrs.f_dc));
        assert!(close(p.sh[15], -lrs.f_rest) && close(p.sh[23], -lrs.f_rest));
        assert!(close(p.scaling[5], -lrs.scaling));
        assert!(close(p.rotation[4], 1.0 - lrs.rotation));
        assert_eq!(p.opacity, vec![0.0, 0.0]);
        assert_eq!((opt.xyz.step, opt.sh.step, opt.opacity.step), (1, 1, 0));
        let before = p.clone();
        opt.step(&mut p, &g, &lrs, StepGroups::None).unwrap();
        assert_eq!(p, before);
        let mut wrong = two_gaussians();
        wrong.opacity.push(0.0);
        assert!(opt.step(&mut p, &wrong, &lrs, StepGroups::All).is_err());
    }
}
