//! Adam with PyTorch 1.13 semantics (the single-tensor path of
//! `torch.optim.Adam`, no weight decay, no amsgrad), element-wise.
//!
//! For step `t` (counted from 1), per element, in this order and with each
//! operation rounded to `T`:
//!
//! ```text
//! m ← m·β1 + g·(1−β1)                 (exp_avg.mul_(β1).add_(g, alpha=1−β1))
//! v ← v·β2 + ((1−β2)·g)·g             (exp_avg_sq.mul_(β2).addcmul_(g, g, value=1−β2))
//! denom = sqrt(v) / sqrt(bc2) + eps    (exp_avg_sq.sqrt() / bc2_sqrt).add_(eps)
//! p ← p + (−step_size)·(m / denom)     (param.addcdiv_(m, denom, value=−step_size))
//! ```
//!
//! The host scalars are computed in f64 as Python does: `bc1 = 1 − β1^t`,
//! `bc2 = 1 − β2^t` (powers from the pinned `libm::pow`, as Python's `**`
//! calls the C `pow`), `step_size = lr / bc1`, `bc2_sqrt = sqrt(bc2)`; each is
//! then rounded to `T` once, as a CUDA kernel receiving a Python scalar does.
//! `1 − β1`, `1 − β2` are likewise computed in f64 and rounded. The CUDA
//! kernels may fuse some of these into FMAs; this reference never does.
//!
//! Every element's update depends only on that element, so the result is the
//! same for any thread count; the work is split into fixed chunks.

use crate::error::{Error, Result};
use crate::math::Real;
use rayon::prelude::*;

/// Adam hyper-parameters (the learning rate is passed per step).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdamConfig {
    /// Decay of the first moment (β1).
    pub beta1: f64,
    /// Decay of the second moment (β2).
    pub beta2: f64,
    /// Added to the denominator (ε).
    pub eps: f64,
}

impl Default for AdamConfig {
    /// D-3DGS values: betas (0.9, 0.999), eps 1e-15.
    fn default() -> Self {
        AdamConfig {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-15,
        }
    }
}

impl AdamConfig {
    /// Check every hyper-parameter's domain: `beta1`, `beta2` in `[0, 1)`,
    /// `eps` finite and `> 0`. Errors name the field.
    pub fn validate(&self) -> Result<()> {
        for (name, b) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&b) {
                return Err(Error::invalid(
                    format!("Adam {name}"),
                    format!("{b} (must be in [0, 1))"),
                ));
            }
        }
        if !(self.eps > 0.0 && self.eps.is_finite()) {
            return Err(Error::invalid(
                "Adam eps",
                format!("{:e} (must be finite and > 0)", self.eps),
            ));
        }
        Ok(())
    }
}

/// The checked host scalars of one step ([`AdamState::plan`]).
pub(crate) struct StepPlan<T> {
    /// The step counter after the step.
    step: u64,
    /// `sqrt(1 − β2^t)` rounded to `T`.
    bc2_sqrt: T,
    /// `−lr/(1 − β1^t)` per learning rate, rounded to `T`.
    neg_step: Vec<T>,
}

/// Elements per parallel work item (fixed, independent of the thread count).
const CHUNK: usize = 1 << 14;

/// Adam state of one parameter tensor (one PyTorch param group).
#[derive(Clone, Debug, PartialEq)]
pub struct AdamState<T> {
    /// First moment (`exp_avg`).
    pub m: Vec<T>,
    /// Second moment (`exp_avg_sq`).
    pub v: Vec<T>,
    /// Number of steps taken (`state["step"]`).
    pub step: u64,
    /// The hyper-parameters.
    pub config: AdamConfig,
}

impl<T: Real> AdamState<T> {
    /// Zero moments for `len` elements, step 0, default hyper-parameters.
    pub fn new(len: usize) -> Self {
        Self::with_config(len, AdamConfig::default())
    }

    /// Zero moments for `len` elements, step 0, hyper-parameters `config`.
    pub fn with_config(len: usize, config: AdamConfig) -> Self {
        AdamState {
            m: vec![T::ZERO; len],
            v: vec![T::ZERO; len],
            step: 0,
            config,
        }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.m.len()
    }

    /// True when the state has no elements.
    pub fn is_empty(&self) -> bool {
        self.m.is_empty()
    }

    /// One Adam step with learning rate `lr` for every element.
    pub fn step(&mut self, params: &mut [T], grads: &[T], lr: f64) -> Result<()> {
        self.step_periodic(params, grads, &[lr])
    }

    /// One Adam step where element `i` uses learning rate `lrs[i % lrs.len()]`.
    ///
    /// This is how one state serves several PyTorch param groups that are laid
    /// out interleaved and always step together (the SH DC and rest
    /// coefficients of `[N, K, 3]`: period `3K`, first 3 entries the DC rate).
    ///
    /// Errors, without changing anything, when the lengths of `params`,
    /// `grads`, [`m`](Self::m) and [`v`](Self::v) differ, when `lrs` does not
    /// tile them, when the [`config`](Self::config) is out of its domain
    /// ([`AdamConfig::validate`]), or when a learning rate is negative, not
    /// finite, or makes a step that is not finite in `T`.
    pub fn step_periodic(&mut self, params: &mut [T], grads: &[T], lrs: &[f64]) -> Result<()> {
        let plan = self.plan(params.len(), grads.len(), lrs)?;
        self.apply(&plan, params, grads);
        Ok(())
    }

    /// Every check of a step and its host scalars, before anything changes.
    pub(crate) fn plan(
        &self,
        params_len: usize,
        grads_len: usize,
        lrs: &[f64],
    ) -> Result<StepPlan<T>> {
        let n = self.m.len();
        if params_len != n || grads_len != n || self.v.len() != n {
            return Err(Error::invalid(
                "Adam step",
                format!(
                    "state has {n} elements (m) and {} (v), params {params_len} and grads {grads_len}",
                    self.v.len(),
                ),
            ));
        }
        if lrs.is_empty() || !n.is_multiple_of(lrs.len()) {
            return Err(Error::invalid(
                "Adam step",
                format!("{} learning rates do not tile {n} elements", lrs.len()),
            ));
        }
        self.config.validate()?;
        if let Some(&lr) = lrs.iter().find(|&&lr| !(lr >= 0.0 && lr.is_finite())) {
            return Err(Error::invalid(
                "learning rate",
                format!("{lr:e} (must be finite and >= 0)"),
            ));
        }
        let step = self.step.checked_add(1).ok_or_else(|| {
            Error::invalid(
                "Adam step",
                format!("the step counter {} cannot advance", self.step),
            )
        })?;
        let c = self.config;
        let t = step as f64;
        let bc1 = 1.0 - libm::pow(c.beta1, t);
        let bc2 = 1.0 - libm::pow(c.beta2, t);
        let bc2_sqrt = T::from_f64(libm::sqrt(bc2));
        let neg_step: Vec<T> = lrs.iter().map(|&lr| T::from_f64(-(lr / bc1))).collect();
        // (Checked before anything changes: a rate whose step overflows `T`
        // would turn every parameter it moves into ±∞.)
        if let Some((&lr, _)) = lrs.iter().zip(&neg_step).find(|(_, s)| !s.is_finite()) {
            return Err(Error::invalid(
                "learning rate",
                format!(
                    "{lr:e}: step {step}'s size lr/(1 − β1^{step}) = {:e} is not finite in {}",
                    lr / bc1,
                    T::PRECISION
                ),
            ));
        }
        Ok(StepPlan {
            step,
            bc2_sqrt,
            neg_step,
        })
    }

    /// The step `plan` (from [`plan`](Self::plan) on this state, unchanged
    /// since, with these lengths).
    pub(crate) fn apply(&mut self, plan: &StepPlan<T>, params: &mut [T], grads: &[T]) {
        let c = self.config;
        let StepPlan {
            step,
            bc2_sqrt,
            ref neg_step,
        } = *plan;
        self.step = step;
        let b1 = T::from_f64(c.beta1);
        let b2 = T::from_f64(c.beta2);
        let a1 = T::from_f64(1.0 - c.beta1);
        let a2 = T::from_f64(1.0 - c.beta2);
        let eps = T::from_f64(c.eps);
        let period = neg_step.len();
        params
            .par_chunks_mut(CHUNK)
            .zip(grads.par_chunks(CHUNK))
            .zip(
                self.m
                    .par_chunks_mut(CHUNK)
                    .zip(self.v.par_chunks_mut(CHUNK)),
            )
            .enumerate()
            .for_each(|(ci, ((p, g), (m, v)))| {
                let base = ci * CHUNK;
                for i in 0..p.len() {
                    let gi = g[i];
                    m[i] = m[i] * b1 + gi * a1;
                    v[i] = v[i] * b2 + (a2 * gi) * gi;
                    let denom = v[i].sqrt() / bc2_sqrt + eps;
                    p[i] += neg_step[(base + i) % period] * (m[i] / denom);
                }
            });
    }

    /// Keep only the rows (of `width` elements) listed in `rows`, in that
    /// order (pruning). The step counter is unchanged.
    ///
    /// # Panics
    /// If a row is out of range (`(row + 1)·width` beyond [`m`](Self::m)'s
    /// length) or [`v`](Self::v)'s length differs from `m`'s: the rows come
    /// from the caller's own arrays of the same length.
    pub fn select_rows(&mut self, width: usize, rows: &[usize]) {
        let len = self.m.len();
        let end = rows.iter().max().map_or(Some(0), |&r| {
            r.checked_add(1).and_then(|e| e.checked_mul(width))
        });
        assert!(
            self.v.len() == len && end.is_some_and(|e| e <= len),
            "AdamState::select_rows: row {:?} of width {width} is out of range of {len} elements (v: {})",
            rows.iter().max(),
            self.v.len()
        );
        self.m = gather_rows(&self.m, width, rows);
        self.v = gather_rows(&self.v, width, rows);
    }

    /// Append `count` rows of zero moments (new points). The step counter is
    /// unchanged.
    ///
    /// # Panics
    /// If `width·count` or the new length overflows `usize`, or the memory
    /// for the new rows cannot be reserved (the caller grows its own arrays
    /// by as many rows).
    pub fn extend_zero(&mut self, width: usize, count: usize) {
        let add = width
            .checked_mul(count)
            .filter(|&a| self.m.len().max(self.v.len()).checked_add(a).is_some());
        let Some(add) = add else {
            panic!(
                "AdamState::extend_zero: {count} rows of {width} elements overflow the length of {}",
                self.m.len()
            );
        };
        if let Err(e) = self.m.try_reserve(add).and(self.v.try_reserve(add)) {
            panic!("AdamState::extend_zero: {count} rows of {width} elements: {e}");
        }
        self.m.extend(std::iter::repeat_n(T::ZERO, add));
        self.v.extend(std::iter::repeat_n(T::ZERO, add));
    }

    /// Zero the moments of every element (opacity reset); step kept.
    pub fn zero_moments(&mut self) {
        self.m.iter_mut().for_each(|x| *x = T::ZERO);
        self.v.iter_mut().for_each(|x| *x = T::ZERO);
    }
}

/// The rows of `src` (each `width` long) listed in `rows`, concatenated.
pub(crate) fn gather_rows<T: Copy>(src: &[T], width: usize, rows: &[usize]) -> Vec<T> {
    let mut out = Vec::with_capacity(rows.len() * width);
    for &r in rows {
        out.extend_from_slice(&src[r * width..(r + 1) * width]);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The torch 1.13 formula for one scalar, written out independently in f64.
    fn reference(p: &mut f64, m: &mut f64, v: &mut f64, g: f64, t: u64, lr: f64) {
        let (b1, b2, eps) = (0.9f64, 0.999f64, 1e-15f64);
        *m = b1 * *m + (1.0 - b1) * g;
        *v = b2 * *v + (1.0 - b2) * g * g;
        let mut p1 = 1.0;
        let mut p2 = 1.0;
        for _ in 0..t {
            p1 *= b1;
            p2 *= b2;
        }
        let (bc1, bc2) = (1.0 - p1, 1.0 - p2);
        *p -= (lr / bc1) * *m / (v.sqrt() / bc2.sqrt() + eps);
    }

    #[test]
    fn adam_matches_scalar_reference() {
        let n = 7;
        let mut params: Vec<f64> = (0..n).map(|i| 0.1 * i as f64 - 0.3).collect();
        let mut refp = params.clone();
        let (mut rm, mut rv) = (vec![0.0; n], vec![0.0; n]);
        let mut st = AdamState::<f64>::new(n);
        for t in 1..=25u64 {
            let grads: Vec<f64> = (0..n)
                .map(|i| libm::sin(0.7 * t as f64 + i as f64) * (i as f64 - 2.0))
                .collect();
            let lr = 1e-3 * (1.0 + 0.01 * t as f64);
            st.step(&mut params, &grads, lr).unwrap();
            for i in 0..n {
                reference(&mut refp[i], &mut rm[i], &mut rv[i], grads[i], t, lr);
            }
            for i in 0..n {
                assert!((params[i] - refp[i]).abs() < 1e-14, "t={t} i={i}");
                assert!((st.m[i] - rm[i]).abs() < 1e-15);
            }
        }
        assert_eq!(st.step, 25);
    }

    #[test]
    fn first_step_moves_by_lr_times_sign() {
        // At t = 1, m/bc1 = g and sqrt(v/bc2) = |g|: the step is lr·sign(g)
        // (up to eps and rounding).
        let mut p = vec![1.0f32, 1.0, 1.0];
        let mut st = AdamState::<f32>::new(3);
        st.step(&mut p, &[0.5, -3.0, 0.0], 0.01).unwrap();
        assert!((p[0] - 0.99).abs() < 1e-6);
        assert!((p[1] - 1.01).abs() < 1e-6);
        assert_eq!(p[2], 1.0);
    }

    #[test]
    fn periodic_rates_and_errors() {
        let mut p = vec![0.0f64; 6];
        let mut st = AdamState::<f64>::new(6);
        st.step_periodic(&mut p, &[1.0; 6], &[0.1, 0.2, 0.3])
            .unwrap();
        for (i, want) in [0.1, 0.2, 0.3, 0.1, 0.2, 0.3].iter().enumerate() {
            assert!((p[i] + want).abs() < 1e-12, "{i}: {}", p[i]);
        }
        assert!(st.step_periodic(&mut p, &[1.0; 6], &[0.1; 4]).is_err());
        assert!(st.step(&mut p, &[1.0; 5], 0.1).is_err());
        assert_eq!(st.step, 1, "a rejected step must not advance the counter");
    }

    /// Mismatched moments, a config out of its domain and a bad learning
    /// rate are errors that change nothing.
    #[test]
    fn bad_state_config_or_rate_is_an_error() {
        let fresh = || AdamState::<f64>::new(2);
        let mut p = vec![1.0f64, 2.0];
        let g = [0.5, -0.5];
        let mut st = fresh();
        st.v.pop();
        let e = st.step(&mut p, &g, 0.1).unwrap_err();
        assert!(e.to_string().contains("(v)"), "{e}");
        let configs = [
            (
                "beta1",
                AdamConfig {
                    beta1: 2.0,
                    ..Default::default()
                },
            ),
            (
                "beta1",
                AdamConfig {
                    beta1: -0.1,
                    ..Default::default()
                },
            ),
            (
                "beta1",
                AdamConfig {
                    beta1: f64::NAN,
                    ..Default::default()
                },
            ),
            (
                "beta2",
                AdamConfig {
                    beta2: 1.0,
                    ..Default::default()
                },
            ),
            (
                "eps",
                AdamConfig {
                    eps: -1.0,
                    ..Default::default()
                },
            ),
            (
                "eps",
                AdamConfig {
                    eps: 0.0,
                    ..Default::default()
                },
            ),
            (
                "eps",
                AdamConfig {
                    eps: f64::INFINITY,
                    ..Default::default()
                },
            ),
        ];
        for (field, config) in configs {
            let mut st = AdamState::<f64>::with_config(2, config);
            let e = st.step(&mut p, &g, 0.1).unwrap_err();
            assert!(e.to_string().contains(field), "{field}: {e}");
            assert_eq!((st.m, st.v, st.step), (vec![0.0; 2], vec![0.0; 2], 0));
        }
        for lr in [-1e-3, f64::NAN, f64::INFINITY] {
            let mut st = fresh();
            let e = st.step_periodic(&mut p, &g, &[0.1, lr]).unwrap_err();
            assert!(e.to_string().contains("learning rate"), "{lr}: {e}");
            assert_eq!(st, fresh());
        }
        assert_eq!(p, [1.0, 2.0]);
        // The edges of the domains still step.
        let edge = AdamConfig {
            beta1: 0.0,
            beta2: 0.0,
            eps: f64::MIN_POSITIVE,
        };
        AdamState::with_config(2, edge)
            .step(&mut p, &g, 0.0)
            .unwrap();
    }

    #[test]
    #[should_panic(expected = "AdamState::select_rows: row Some(2) of width 3")]
    fn select_rows_out_of_range_panics_with_a_message() {
        AdamState::<f32>::new(6).select_rows(3, &[1, 2]);
    }

    #[test]
    #[should_panic(expected = "AdamState::extend_zero: 2 rows of")]
    fn extend_zero_overflow_panics_with_a_message() {
        AdamState::<f32>::new(1).extend_zero(usize::MAX, 2);
    }

    #[test]
    #[should_panic(expected = "AdamState::extend_zero: 2147483648 rows of 2147483648 elements")]
    fn extend_zero_beyond_memory_panics_before_allocating() {
        // 2⁶² f64 values: more bytes than a Vec may hold.
        AdamState::<f64>::new(1).extend_zero(1 << 31, 1 << 31);
    }

    #[test]
    fn select_rows_and_extend_zero_in_range() {
        let mut st = AdamState::<f32>::new(6);
        st.m = (0..6).map(|i| i as f32).collect();
        st.select_rows(3, &[1, 1, 0]);
        assert_eq!(st.m, [3.0, 4.0, 5.0, 3.0, 4.0, 5.0, 0.0, 1.0, 2.0]);
        st.select_rows(3, &[]);
        assert!(st.is_empty());
        st.extend_zero(3, 2);
        assert_eq!((st.m.len(), st.v.len()), (6, 6));
    }

    #[test]
    fn identical_for_any_thread_count() {
        let n = 3 * CHUNK + 18;
        let grads: Vec<f32> = (0..n).map(|i| libm::sinf(i as f32 * 0.37)).collect();
        let run = |threads| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let mut p = vec![0.5f32; n];
                let mut st = AdamState::<f32>::new(n);
                for _ in 0..3 {
                    st.step_periodic(&mut p, &grads, &[1e-3, 2e-3]).unwrap();
                }
                p.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
            })
        };
        assert_eq!(run(1), run(4));
    }
}
