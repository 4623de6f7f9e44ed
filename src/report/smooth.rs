//! Temporal smoothness of a learned deformation: how sharply the offsets bend
//! in time, the property the seed paper attributes to the CfC time gate.
//!
//! Given K uniformly spaced times t_0 < … < t_{K−1} (spacing Δt) and the
//! field's offsets o(t) ∈ R^M at each (M = every offset component of every
//! Gaussian that is swept), the figure is
//!
//! ```text
//! S = 1/((K−2)·M) · Σ_{k=1}^{K−2} Σ_{j=0}^{M−1} |o_j(t_{k+1}) − 2·o_j(t_k) + o_j(t_{k−1})| / Δt²
//! ```
//!
//! the mean absolute second difference divided by Δt², i.e. the mean
//! magnitude of the discrete second time derivative (units: offset / time²).
//! Lower is smoother. Linear motion gives 0, o = a·t² gives 2|a|, and
//! o = sin(ωt) over whole periods gives about ω²·2/π.

use crate::error::{Error, Result};

/// `n` uniformly spaced times covering `[0, 1]`: t_k = k/(n−1).
pub fn uniform_times(n: usize) -> Vec<f64> {
    let d = n.saturating_sub(1).max(1) as f64;
    (0..n).map(|k| k as f64 / d).collect()
}

/// The smoothness figure S (module docs) of `offsets_at` over `times`.
///
/// `times` must hold at least 3 increasing, uniformly spaced values (relative
/// spacing error at most 1e-9), and `offsets_at` must return the same
/// non-zero number of finite values at each time. Sums run in a fixed order.
pub fn temporal_smoothness(offsets_at: impl Fn(f64) -> Vec<f64>, times: &[f64]) -> Result<f64> {
    let bad = |why: String| Error::invalid("temporal smoothness sweep", why);
    if times.len() < 3 {
        return Err(bad(format!("{} times (need at least 3)", times.len())));
    }
    let k = times.len();
    let dt = (times[k - 1] - times[0]) / (k - 1) as f64;
    if !(dt > 0.0 && dt.is_finite()) {
        return Err(bad(format!("times must increase (spacing {dt})")));
    }
    for (i, w) in times.windows(2).enumerate() {
        if ((w[1] - w[0]) - dt).abs() > 1e-9 * dt {
            return Err(bad(format!(
                "times are not uniform: step {i} is {} but the mean step is {dt}",
                w[1] - w[0]
            )));
        }
    }
    let mut prev2 = offsets_at(times[0]);
    let m = prev2.len();
    if m == 0 {
        return Err(bad("no offsets at t = times[0]".into()));
    }
    let mut prev1 = offsets_at(times[1]);
    let mut total = 0.0f64;
    for &t in &times[2..] {
        let cur = offsets_at(t);
        if cur.len() != m || prev1.len() != m {
            return Err(bad(format!(
                "{} offsets at t = {t}, {m} at t = {}",
                cur.len(),
                times[0]
            )));
        }
        for j in 0..m {
            total += (cur[j] - 2.0 * prev1[j] + prev2[j]).abs();
        }
        prev2 = std::mem::replace(&mut prev1, cur);
    }
    let s = total / ((k - 2) * m) as f64 / (dt * dt);
    if !s.is_finite() {
        return Err(bad("offsets are not finite".into()));
    }
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_motion_is_perfectly_smooth() {
        // Offsets linear in t with dyadic coefficients and t_k = k/1024, so
        // every second difference is computed exactly: S = 0 exactly.
        let times: Vec<f64> = (0..=1024).map(|k| k as f64 / 1024.0).collect();
        let s = temporal_smoothness(|t| vec![0.5 + 0.25 * t, -2.0 * t, 0.0], &times).unwrap();
        assert_eq!(s, 0.0);
    }

    #[test]
    fn quadratic_motion_gives_twice_its_coefficient() {
        // o = a·t²: second difference a·((t+h)² − 2t² + (t−h)²) = 2a·h², so
        // S = mean |2a| = 2|a| for every component (here |a| = 3 and 3, M = 2).
        let times = uniform_times(201);
        let s = temporal_smoothness(|t| vec![3.0 * t * t, -3.0 * t * t + t], &times).unwrap();
        assert!((s - 6.0).abs() < 1e-6 * 6.0, "{s}");
    }

    #[test]
    fn sine_gives_the_mean_of_its_rectified_second_derivative() {
        // o = sin(ωt), ω = 2π, over [0, 1] (one period). The exact second
        // difference is −4·sin²(ωh/2)·sin(ωt_k), so S = 4 sin²(ωh/2)/h² ·
        // mean_k |sin(ωt_k)|, which tends to ω²·(2/π) (mean of |sin| over a
        // period is 2/π). With h = 1e-4: the factor is ω²(1 − (ωh)²/12) ≈
        // ω²(1 − 3.3e-9); the grid mean of the periodic |sin| (kinks only at
        // the zeros) differs from 2/π by O(h²) ≈ 1e-8 relative, apart from
        // the two dropped end points (zero there) which give a 1/(K−2)·(2/π)
        // relative shift of ≈ 1e-4 in the opposite direction, accounted below.
        let n = 10_001;
        let times = uniform_times(n);
        let w = 2.0 * std::f64::consts::PI;
        let s = temporal_smoothness(|t| vec![libm::sin(w * t)], &times).unwrap();
        // Σ over the K−2 interior points of |sin| ≈ (K−1)·(2/π) (trapezoid
        // rule over the period, end values 0), so the mean is (K−1)/(K−2)·2/π.
        let expect = w * w * 2.0 / std::f64::consts::PI * (n - 1) as f64 / (n - 2) as f64;
        assert!((s - expect).abs() < 1e-6 * expect, "{s} vs {expect}");
    }

    #[test]
    fn bad_sweeps_are_errors() {
        let f = |t: f64| vec![t];
        assert!(temporal_smoothness(f, &[0.0, 1.0]).is_err());
        assert!(temporal_smoothness(f, &[0.0, 0.1, 0.3]).is_err());
        assert!(temporal_smoothness(f, &[1.0, 0.5, 0.0]).is_err());
        assert!(temporal_smoothness(|_| vec![], &uniform_times(5)).is_err());
        assert!(
            temporal_smoothness(|t| vec![0.0; 1 + (t > 0.5) as usize], &uniform_times(5)).is_err()
        );
        assert!(temporal_smoothness(|_| vec![f64::NAN], &uniform_times(5)).is_err());
    }
}
