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
pub use schedule::{GroupLrs, LearningRates, StepRates};

use crate::error::{Error, Result};
use crate::gaussians::{Gaussians, Group};
use crate::math::Real;

/// The Adam states of the canonical Gaussians, one per [`Group`].
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianOptimizer<T> {
    /// Indexed by `Group as usize` ([`Group::ALL`]'s order).
    states: [AdamState<T>; 5],
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

impl StepGroups {
    /// Whether `group` steps.
    pub fn includes(self, group: Group) -> bool {
        match self {
            StepGroups::All => true,
            StepGroups::AllButOpacity => group != Group::Opacity,
            StepGroups::None => false,
        }
    }
}

impl<T: Real> GaussianOptimizer<T> {
    /// Zero state for `gaussians` (their sizes), default hyper-parameters.
    pub fn new(gaussians: &Gaussians<T>) -> Self {
        GaussianOptimizer {
            states: Group::ALL.map(|g| AdamState::new(gaussians.group(g).len())),
        }
    }

    /// The state of `group` (f_dc and f_rest together for [`Group::Sh`],
    /// `[N, K, 3]`).
    pub fn state(&self, group: Group) -> &AdamState<T> {
        &self.states[group as usize]
    }

    /// The state of `group`, mutable.
    pub fn state_mut(&mut self, group: Group) -> &mut AdamState<T> {
        &mut self.states[group as usize]
    }

    /// Number of Gaussians the state is sized for.
    pub fn len(&self) -> usize {
        self.state(Group::Opacity).len()
    }

    /// True when the state is sized for no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Whether every group's state has the length of its array in `g`.
    pub fn fits(&self, g: &Gaussians<T>) -> bool {
        Group::ALL
            .iter()
            .all(|&group| self.state(group).len() == g.group(group).len())
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
            || !self.fits(params)
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
        let k = params.coeffs();
        // Every group's checks (lengths, hyper-parameters, rates) before any
        // group steps, so that an error changes nothing.
        let mut plans = Vec::with_capacity(Group::ALL.len());
        for group in Group::ALL {
            plans.push(if groups.includes(group) {
                let rates = lrs.periodic(group, k);
                let (p, g) = (params.group(group), grads.group(group));
                Some(self.states[group as usize].plan(p.len(), g.len(), &rates)?)
            } else {
                None
            });
        }
        for ((group, p), plan) in params.groups_mut().into_iter().zip(&plans) {
            if let Some(plan) = plan {
                self.states[group as usize].apply(plan, p, grads.group(group));
            }
        }
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
        for (_, v) in g.groups_mut() {
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
        let step = |g| opt.state(g).step;
        assert_eq!(
            (step(Group::Xyz), step(Group::Sh), step(Group::Opacity)),
            (1, 1, 0)
        );
        let before = p.clone();
        opt.step(&mut p, &g, &lrs, StepGroups::None).unwrap();
        assert_eq!(p, before);
        let mut wrong = two_gaussians();
        wrong.opacity.push(0.0);
        assert!(opt.step(&mut p, &wrong, &lrs, StepGroups::All).is_err());
    }

    /// A huge SH degree, or a bad state in the last group, is an error
    /// before any group steps.
    #[test]
    fn bad_degree_or_state_changes_nothing() {
        let lrs = LearningRates::default().gaussian(0);
        let mut p = Gaussians::<f64>::empty(1 << 33);
        let g = p.clone();
        let mut opt = GaussianOptimizer::new(&Gaussians::empty(0));
        let e = opt.step(&mut p, &g, &lrs, StepGroups::All).unwrap_err();
        assert!(e.to_string().contains("max_sh_degree"), "{e}");

        let (mut p, g) = (two_gaussians(), two_gaussians());
        let mut opt = GaussianOptimizer::new(&p);
        opt.state_mut(Group::Rotation).config.beta2 = 1.0;
        let (p0, opt0) = (p.clone(), opt.clone());
        let e = opt.step(&mut p, &g, &lrs, StepGroups::All).unwrap_err();
        assert!(e.to_string().contains("beta2"), "{e}");
        assert_eq!((p, opt), (p0, opt0));
    }
}
