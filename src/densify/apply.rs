//! Applying densification and opacity reset to the Gaussian parameters, their
//! Adam moments and the densification statistics **together**, so the three
//! can never fall out of step (docs/UPSTREAM.md §6.5).
//!
//! ## Order (as upstream `densify_and_prune`)
//! 1. mean gradients `accum / denom` (0/0 → 0);
//! 2. clone: append exact copies of the selected Gaussians' raw parameters;
//! 3. split: among the post-clone set (clones have gradient 0), for each
//!    selected Gaussian append `split_copies` children, then remove the
//!    selected originals;
//! 4. statistics are reset to zero for every Gaussian (upstream's postfix);
//! 5. prune: opacity below `min_opacity`, and after `screen_size_after` the
//!    size tests; the screen-size test sees the reset radii (all zero), so it
//!    never fires: this reproduces upstream, where the postfix resets
//!    `max_radii2D` before the prune mask is computed.
//!
//! New rows get zero Adam moments; removed rows take their moments with them;
//! step counters are unchanged. Children are appended copy-major (all first
//! children, then all second children), as `repeat(N, 1)` lays them out.
//!
//! ## Split sampling
//! Child `c` of Gaussian `i` (its index before densification) gets
//! `xyz_i + R(q_i / |q_i|) · (z ∘ scale_i)`, where `z` are standard normals
//! drawn from `Rng::stream(seed, i)`: three for child 0, then three for
//! child 1, and so on. The result does not depend on threads or on which
//! other Gaussians are split. Upstream draws with the CUDA Philox generator,
//! which a CPU cannot reproduce (docs/UPSTREAM.md §0). The quaternion is normalised
//! with `max(|q|, 1e-12)` (upstream divides by `|q|` alone, NaN for a zero
//! quaternion). The sample is `T(z) · scale` (upstream `torch.normal(0, std)`).

use super::policy::{prune_mask, select_clone, select_split, DensifyConfig};
use super::stats::DensifyStats;
use crate::error::{Error, Result};
use crate::gaussians::{normalize_norm, Gaussians, Group};
use crate::math::quat::quat_to_rotmat;
use crate::math::{Real, Rng};
use crate::optim::GaussianOptimizer;

/// What one densification did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DensifyReport {
    /// Gaussians before densification.
    pub before: usize,
    /// Gaussians cloned.
    pub cloned: usize,
    /// Gaussians split (each replaced by `split_copies` children).
    pub split: usize,
    /// Gaussians removed by the final prune.
    pub pruned: usize,
    /// Gaussians after densification.
    pub after: usize,
}

fn check_aligned<T: Real>(
    g: &Gaussians<T>,
    opt: &GaussianOptimizer<T>,
    stats: &DensifyStats<T>,
) -> Result<()> {
    g.validate()?;
    if opt.fits(g) && stats.len() == g.len() {
        Ok(())
    } else {
        Err(Error::invalid(
            "densification",
            format!(
                "{} Gaussians but optimizer state for {} and statistics for {}",
                g.len(),
                opt.len(),
                stats.len()
            ),
        ))
    }
}

/// Append copies of `rows` to the parameters and zero moments to the state.
fn append_rows<T: Real>(g: &mut Gaussians<T>, opt: &mut GaussianOptimizer<T>, rows: &[usize]) {
    let k = g.coeffs();
    for (group, v) in g.groups_mut() {
        let w = group.width(k);
        for &r in rows {
            v.extend_from_within(r * w..(r + 1) * w);
        }
        opt.state_mut(group).extend_zero(w, rows.len());
    }
}

/// Keep only the Gaussians for which `remove` is false, in order, with their
/// Adam moments.
fn retain<T: Real>(g: &mut Gaussians<T>, opt: &mut GaussianOptimizer<T>, remove: &[bool]) {
    let keep: Vec<usize> = (0..remove.len()).filter(|&i| !remove[i]).collect();
    let k = g.coeffs();
    for (group, v) in g.groups_mut() {
        let w = group.width(k);
        *v = crate::optim::adam::gather_rows(v, w, &keep);
        opt.state_mut(group).select_rows(w, &keep);
    }
}

/// Rotation matrix (row-major) of a quaternion (w, x, y, z) after
/// normalisation, as upstream `build_rotation`.
fn rotation_matrix<T: Real>(q: &[T]) -> [[T; 3]; 3] {
    let n = normalize_norm(q);
    quat_to_rotmat([q[0] / n, q[1] / n, q[2] / n, q[3] / n])
}

/// Append the split children of `selected` (indices into the current set):
/// copies of their rows, copy-major, then each child's mean and scale.
fn append_split_children<T: Real>(
    g: &mut Gaussians<T>,
    opt: &mut GaussianOptimizer<T>,
    selected: &[usize],
    cfg: &DensifyConfig,
    seed: u64,
) {
    let copies = cfg.split_copies;
    let div = T::from_f64(cfg.split_scale_divisor);
    // Normals per selected Gaussian: copy-major, 3 per copy.
    let normals: Vec<Vec<f64>> = selected
        .iter()
        .map(|&i| {
            let mut rng = Rng::stream(seed, i as u64);
            (0..3 * copies).map(|_| rng.normal()).collect()
        })
        .collect();
    let first = g.len();
    let rows: Vec<usize> = (0..copies).flat_map(|_| selected.iter().copied()).collect();
    append_rows(g, opt, &rows);
    for c in 0..copies {
        for (s, &i) in selected.iter().enumerate() {
            let child = first + c * selected.len() + s;
            let scale: [T; 3] = std::array::from_fn(|d| g.scaling[3 * i + d].exp());
            let sample: [T; 3] =
                std::array::from_fn(|d| T::from_f64(normals[s][3 * c + d]) * scale[d]);
            let r = rotation_matrix(&g.rotation[4 * i..4 * i + 4]);
            for (row, rrow) in r.iter().enumerate() {
                let v = rrow[0] * sample[0] + rrow[1] * sample[1] + rrow[2] * sample[2];
                g.xyz[3 * child + row] = v + g.xyz[3 * i + row];
            }
            for (d, sd) in scale.into_iter().enumerate() {
                g.scaling[3 * child + d] = (sd / div).ln();
            }
        }
    }
}

/// Clone, split and prune (upstream `densify_and_prune`), updating the
/// parameters, the Adam moments and the statistics together. `extent` is the
/// scene extent (`cameras_extent`), `iteration` the training iteration (it
/// switches the size tests on after `cfg.screen_size_after`), `seed` the seed
/// of this densification's split sampling (the trainer should derive it from
/// its run seed and the iteration, so that every call differs).
///
/// On return the statistics are all zero for the new set. Errors, changing
/// nothing, if the three inputs are not sized for the same Gaussians or
/// `extent` is not finite.
pub fn densify_and_prune<T: Real>(
    g: &mut Gaussians<T>,
    opt: &mut GaussianOptimizer<T>,
    stats: &mut DensifyStats<T>,
    extent: f64,
    iteration: u64,
    cfg: &DensifyConfig,
    seed: u64,
) -> Result<DensifyReport> {
    check_aligned(g, opt, stats)?;
    if !extent.is_finite() {
        return Err(Error::invalid(
            "scene extent",
            format!("{extent} is not finite"),
        ));
    }
    let before = g.len();
    let grads = stats.mean_grads();

    let clone = select_clone(&grads, &g.scales(), extent, cfg);
    append_rows(g, opt, &clone);

    let mut padded = grads;
    padded.resize(g.len(), T::ZERO);
    let split = select_split(&padded, &g.scales(), extent, cfg);
    append_split_children(g, opt, &split, cfg, seed);
    let mut remove = vec![false; g.len()];
    for &i in &split {
        remove[i] = true;
    }
    retain(g, opt, &remove);

    *stats = DensifyStats::new(g.len());
    let remove = prune_mask(
        &g.opacities(),
        &g.scales(),
        &stats.max_radii,
        extent,
        iteration,
        cfg,
    );
    let pruned = remove.iter().filter(|&&r| r).count();
    retain(g, opt, &remove);
    *stats = DensifyStats::new(g.len());
    Ok(DensifyReport {
        before,
        cloned: clone.len(),
        split: split.len(),
        pruned,
        after: g.len(),
    })
}

/// Opacity reset: `opacity_raw = inverse_sigmoid(min(sigmoid(opacity_raw), 0.01))`
/// with `inverse_sigmoid(y) = ln(y / (1 − y))`; the opacity group's Adam
/// moments are zeroed and its step counter kept.
pub fn reset_opacity<T: Real>(g: &mut Gaussians<T>, opt: &mut GaussianOptimizer<T>) -> Result<()> {
    let state = opt.state_mut(Group::Opacity);
    if state.len() != g.opacity.len() {
        return Err(Error::invalid(
            "opacity reset",
            format!(
                "{} opacities but optimizer state for {}",
                g.opacity.len(),
                state.len()
            ),
        ));
    }
    let cap = T::from_f64(0.01);
    for o in g.opacity.iter_mut() {
        let a = o.sigmoid().min(cap);
        *o = (a / (T::ONE - a)).ln();
    }
    state.zero_moments();
    Ok(())
}
