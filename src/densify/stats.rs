//! Per-Gaussian densification statistics (docs/UPSTREAM.md §6.5), accumulated every
//! iteration from the rasterizer's outputs.

use crate::error::{Error, Result};
use crate::math::Real;

/// `xyz_gradient_accum`, `denom` and `max_radii2D` of upstream.
#[derive(Clone, Debug, PartialEq)]
pub struct DensifyStats<T> {
    /// Sum over visible views of `‖(g.x, g.y)‖₂`, g the NDC gradient of the
    /// projected mean.
    pub accum: Vec<T>,
    /// Number of views in which the Gaussian was visible (`radii > 0`).
    pub denom: Vec<u32>,
    /// Largest screen radius (pixels) seen since the last reset. Upstream
    /// keeps it as a float tensor of integer values; an `i32` holds the same.
    pub max_radii: Vec<i32>,
}

impl<T: Real> DensifyStats<T> {
    /// All-zero statistics for `n` Gaussians.
    pub fn new(n: usize) -> Self {
        DensifyStats {
            accum: vec![T::ZERO; n],
            denom: vec![0; n],
            max_radii: vec![0; n],
        }
    }

    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.denom.len()
    }

    /// True when sized for no Gaussians.
    pub fn is_empty(&self) -> bool {
        self.denom.is_empty()
    }

    /// Add one rendered view: for every Gaussian with `radii > 0`,
    /// `max_radii = max(max_radii, radii)`, `accum += sqrt(gx² + gy²)`,
    /// `denom += 1`. `grad_means2d` is `[N, 3]` (the rasterizer's means2D
    /// gradient, NDC units); its third column is ignored.
    pub fn update(&mut self, radii: &[i32], grad_means2d: &[T]) -> Result<()> {
        let n = self.len();
        if radii.len() != n || grad_means2d.len() != 3 * n {
            return Err(Error::invalid(
                "densification statistics",
                format!(
                    "{n} Gaussians, {} radii and {} means2D gradient values (expected {} and {})",
                    radii.len(),
                    grad_means2d.len(),
                    n,
                    3 * n
                ),
            ));
        }
        for i in 0..n {
            let r = radii[i];
            if r > 0 {
                self.max_radii[i] = self.max_radii[i].max(r);
                let (gx, gy) = (grad_means2d[3 * i], grad_means2d[3 * i + 1]);
                self.accum[i] += (gx * gx + gy * gy).sqrt();
                self.denom[i] += 1;
            }
        }
        Ok(())
    }

    /// `accum / denom` per Gaussian, with 0/0 (never visible) set to 0.
    pub fn mean_grads(&self) -> Vec<T> {
        self.accum
            .iter()
            .zip(&self.denom)
            .map(|(&a, &d)| {
                let g = a / T::from_f64(d as f64);
                if g.is_nan() {
                    T::ZERO
                } else {
                    g
                }
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_visible_gaussians_accumulate() {
        let mut s = DensifyStats::<f64>::new(3);
        s.update(&[2, 0, 5], &[3.0, 4.0, 9.0, 1.0, 1.0, 1.0, 0.0, -2.0, 7.0])
            .unwrap();
        s.update(&[4, 0, 1], &[0.0, 1.0, 0.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
            .unwrap();
        assert_eq!(s.accum, vec![6.0, 0.0, 2.0]);
        assert_eq!(s.denom, vec![2, 0, 2]);
        assert_eq!(s.max_radii, vec![4, 0, 5]);
        assert_eq!(s.mean_grads(), vec![3.0, 0.0, 1.0]);
        assert!(s.update(&[1, 1], &[0.0; 6]).is_err());
    }
}
