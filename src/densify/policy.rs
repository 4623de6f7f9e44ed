//! What to clone, split and prune (docs/UPSTREAM.md §6.5, R2p values). Pure
//! selection functions; [`super::apply`] applies them to the parameters,
//! the Adam state and the statistics together.
//!
//! Comparisons are done in `T` with the thresholds rounded to `T`, as a
//! PyTorch comparison of an f32 tensor with a Python float is.

use crate::math::Real;

/// Densification thresholds and constants (upstream defaults).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DensifyConfig {
    /// Mean NDC gradient norm at or above which a Gaussian is densified
    /// (0.0002, paper branch).
    pub grad_threshold: f64,
    /// Clone if `max(scale) <= percent_dense · extent`, split otherwise (0.01).
    pub percent_dense: f64,
    /// Prune if opacity < this (0.005, hard-coded in train.py).
    pub min_opacity: f64,
    /// Screen-size prune threshold in pixels (20), used only for iterations
    /// strictly after `screen_size_after`.
    pub max_screen_size: i32,
    /// Upstream `opacity_reset_interval` (3000).
    pub screen_size_after: u64,
    /// World-size prune: `max(scale) > world_size_factor · extent` (0.1), with
    /// the screen-size test.
    pub world_size_factor: f64,
    /// New Gaussians per split (2).
    pub split_copies: usize,
    /// Split children's scale divisor `0.8 · split_copies` (1.6).
    pub split_scale_divisor: f64,
}

impl Default for DensifyConfig {
    fn default() -> Self {
        DensifyConfig {
            grad_threshold: 0.0002,
            percent_dense: 0.01,
            min_opacity: 0.005,
            max_screen_size: 20,
            screen_size_after: 3000,
            world_size_factor: 0.1,
            split_copies: 2,
            split_scale_divisor: 0.8 * 2.0,
        }
    }
}

/// Largest of each row of 3 values.
pub fn max_per_row3<T: Real>(v: &[T]) -> Vec<T> {
    v.chunks_exact(3)
        .map(|r| r[0].max(r[1]).max(r[2]))
        .collect()
}

/// Indices to clone: `grad >= threshold` and `max(scale) <= percent_dense · extent`.
/// `scales` are activated (`exp(scaling)`), `[N, 3]`.
pub fn select_clone<T: Real>(
    grads: &[T],
    scales: &[T],
    extent: f64,
    cfg: &DensifyConfig,
) -> Vec<usize> {
    let thr = T::from_f64(cfg.grad_threshold);
    let lim = T::from_f64(cfg.percent_dense * extent);
    max_per_row3(scales)
        .iter()
        .zip(grads)
        .enumerate()
        .filter(|(_, (&s, &g))| g >= thr && s <= lim)
        .map(|(i, _)| i)
        .collect()
}

/// Indices to split among the Gaussians after cloning: `grads` are the
/// pre-clone mean gradients, zero-padded for the clones (so clones are never
/// split for a positive threshold); `scales` are the post-clone activated
/// scales. Selects `grad >= threshold` and `max(scale) > percent_dense · extent`.
pub fn select_split<T: Real>(
    grads_padded: &[T],
    scales: &[T],
    extent: f64,
    cfg: &DensifyConfig,
) -> Vec<usize> {
    let thr = T::from_f64(cfg.grad_threshold);
    let lim = T::from_f64(cfg.percent_dense * extent);
    max_per_row3(scales)
        .iter()
        .zip(grads_padded)
        .enumerate()
        .filter(|(_, (&s, &g))| g >= thr && s > lim)
        .map(|(i, _)| i)
        .collect()
}

/// Prune mask after densification: `opacity < min_opacity`, and for
/// `iteration > screen_size_after` also `max_radii > max_screen_size` or
/// `max(scale) > world_size_factor · extent`. `opacities` and `scales` are
/// activated.
///
/// Upstream evaluates this after the clone and split postfixes have reset
/// `max_radii2D` to zero, so its screen-size test never fires; callers that
/// reproduce upstream pass the reset (all-zero) radii, as
/// [`super::apply::densify_and_prune`] does.
pub fn prune_mask<T: Real>(
    opacities: &[T],
    scales: &[T],
    max_radii: &[i32],
    extent: f64,
    iteration: u64,
    cfg: &DensifyConfig,
) -> Vec<bool> {
    let min_o = T::from_f64(cfg.min_opacity);
    let big = T::from_f64(cfg.world_size_factor * extent);
    let size_test = iteration > cfg.screen_size_after;
    let smax = max_per_row3(scales);
    (0..opacities.len())
        .map(|i| {
            let low = opacities[i] < min_o;
            if size_test {
                low || max_radii[i] > cfg.max_screen_size || smax[i] > big
            } else {
                low
            }
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clone_and_split_selection() {
        let cfg = DensifyConfig::default();
        let extent = 2.0; // clone if max scale <= 0.02
        let grads = [0.0003f64, 0.0001, 0.0002, 0.0005];
        let scales = [
            0.01, 0.02, 0.0, // small, high grad: clone
            0.01, 0.01, 0.01, // small, low grad: nothing
            0.03, 0.0, 0.0, // large, grad == threshold: split
            0.02, 0.0, 0.0, // exactly at the limit: clone
        ];
        assert_eq!(select_clone(&grads, &scales, extent, &cfg), vec![0, 3]);
        let mut padded = grads.to_vec();
        padded.extend([0.0, 0.0]);
        let mut post = scales.to_vec();
        post.extend_from_slice(&scales[0..3]);
        post.extend_from_slice(&scales[9..12]);
        assert_eq!(select_split(&padded, &post, extent, &cfg), vec![2]);
    }

    #[test]
    fn prune_rules() {
        let cfg = DensifyConfig::default();
        let op = [0.004f64, 0.5, 0.5, 0.5];
        let sc = [0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.1, 0.3, 0.1, 0.1, 0.1, 0.1];
        let radii = [0, 0, 0, 21];
        // extent 2: world limit 0.2.
        assert_eq!(
            prune_mask(&op, &sc, &radii, 2.0, 3000, &cfg),
            vec![true, false, false, false]
        );
        assert_eq!(
            prune_mask(&op, &sc, &radii, 2.0, 3100, &cfg),
            vec![true, false, true, true]
        );
    }
}
