//! A reusable central-difference gradient checker in f64.
//!
//! A backward pass computes the vector-Jacobian product `vᵀ J` for a cotangent
//! `v`. To check it, define the scalar `L(x) = <v, f(x)>` and compare each
//! entry of the analytic gradient with `(L(x + h e_i) - L(x - h e_i)) / 2h`.
//! Central differences have O(h²) truncation error, so with h ≈ 1e-6 and
//! well-conditioned inputs the relative error is ~1e-9 or better.
//!
//! The error metric per entry is `|a - n| / max(|a|, |n|, floor)`, where the
//! floor keeps entries that are zero in both from dividing by zero; callers
//! choose it from the magnitude of the gradient being checked (for example
//! 1e-3 times the largest entry of the group).

/// Result of checking one named input group.
#[derive(Clone, Debug)]
pub struct GroupReport {
    /// The group's name.
    pub name: String,
    /// Entries compared.
    pub count: usize,
    /// Largest `|analytic − numeric|`.
    pub max_abs: f64,
    /// Largest `|analytic − numeric| / max(|analytic|, |numeric|, floor)`.
    pub max_rel: f64,
    /// Index of the entry with the largest relative error.
    pub worst: usize,
    /// The analytic value at [`GroupReport::worst`].
    pub worst_analytic: f64,
    /// The numeric value at [`GroupReport::worst`].
    pub worst_numeric: f64,
}

impl GroupReport {
    /// True when the largest relative error is within `rel_tol` and every
    /// difference is finite.
    pub fn passes(&self, rel_tol: f64) -> bool {
        self.max_rel <= rel_tol && self.max_abs.is_finite()
    }
}

impl std::fmt::Display for GroupReport {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "{:<24} n={:<6} max_abs={:.3e} max_rel={:.3e} (worst #{}: analytic {:.12e}, numeric {:.12e})",
            self.name, self.count, self.max_abs, self.max_rel, self.worst, self.worst_analytic, self.worst_numeric
        )
    }
}

/// Central difference of a scalar function with respect to each entry of `x`.
///
/// `f` is evaluated at `x` with entry `i` moved by `±h`; `x` is restored
/// afterwards. The step is relative: `h * max(1, |x_i|)`.
pub fn numeric_gradient(x: &mut [f64], h: f64, mut f: impl FnMut(&[f64]) -> f64) -> Vec<f64> {
    let mut g = vec![0.0; x.len()];
    for i in 0..x.len() {
        let x0 = x[i];
        let step = h * x0.abs().max(1.0);
        x[i] = x0 + step;
        let fp = f(x);
        x[i] = x0 - step;
        let fm = f(x);
        x[i] = x0;
        // Divide by the step actually taken (x0 ± step may round).
        g[i] = (fp - fm) / ((x0 + step) - (x0 - step));
    }
    g
}

/// Central differences with one Richardson step: `(4·D(h) − D(2h)) / 3`,
/// where `D(s)` is [`numeric_gradient`]'s quotient with step `s`; the `h²`
/// term of the truncation error cancels. For inputs whose function is far
/// from quadratic over the step (a precomputed covariance, whose entries
/// are small beside the step scale `max(|x|, 1)`).
pub fn numeric_gradient_richardson(
    x: &mut [f64],
    h: f64,
    mut f: impl FnMut(&[f64]) -> f64,
) -> Vec<f64> {
    let near = numeric_gradient(x, h, &mut f);
    let far = numeric_gradient(x, 2.0 * h, &mut f);
    near.iter()
        .zip(&far)
        .map(|(&a, &b)| (4.0 * a - b) / 3.0)
        .collect()
}

/// Compare an analytic gradient with a numeric one.
pub fn compare(name: &str, analytic: &[f64], numeric: &[f64], floor: f64) -> GroupReport {
    assert_eq!(
        analytic.len(),
        numeric.len(),
        "gradient length mismatch for {name}"
    );
    let mut r = GroupReport {
        name: name.to_string(),
        count: analytic.len(),
        max_abs: 0.0,
        max_rel: 0.0,
        worst: 0,
        worst_analytic: analytic.first().copied().unwrap_or(0.0),
        worst_numeric: numeric.first().copied().unwrap_or(0.0),
    };
    for (i, (&a, &n)) in analytic.iter().zip(numeric).enumerate() {
        let abs = (a - n).abs();
        // NaN anywhere must fail, so map it to infinity.
        let abs = if abs.is_nan() { f64::INFINITY } else { abs };
        let rel = abs / a.abs().max(n.abs()).max(floor);
        let rel = if rel.is_nan() { f64::INFINITY } else { rel };
        r.max_abs = r.max_abs.max(abs);
        if rel > r.max_rel {
            r.max_rel = rel;
            r.worst = i;
            r.worst_analytic = a;
            r.worst_numeric = n;
        }
    }
    r
}

/// Deterministic pseudo-random cotangent in [-1, 1) for entry `i` of a check
/// seeded by `seed` (a vector-Jacobian product with a random direction tests
/// every output's contribution at once).
pub fn cotangent(seed: u64, n: usize) -> Vec<f64> {
    let mut rng = super::Rng::new(seed);
    (0..n).map(|_| rng.uniform_range(-1.0, 1.0)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numeric_gradient_of_known_function() {
        // L(x) = x0^2 * sin(x1), dL/dx = (2 x0 sin x1, x0^2 cos x1)
        let mut x = vec![1.3, 0.7];
        let g = numeric_gradient(&mut x, 1e-6, |x| x[0] * x[0] * libm::sin(x[1]));
        let a = [2.0 * 1.3 * libm::sin(0.7), 1.3 * 1.3 * libm::cos(0.7)];
        let r = compare("f", &a, &g, 1e-12);
        assert!(r.passes(1e-8), "{r}");
    }

    #[test]
    fn richardson_cancels_the_quadratic_error_term() {
        // L(x) = exp(50 x): the plain quotient's relative error is
        // (50 h)²/6 = 4e-10 at h = 1e-6; Richardson's is of order (50 h)⁴.
        let mut x = vec![0.2];
        let f = |x: &[f64]| libm::exp(50.0 * x[0]);
        let a = [50.0 * libm::exp(10.0)];
        let plain = compare("f", &a, &numeric_gradient(&mut x, 1e-6, f), 1e-12);
        let rich = compare(
            "f",
            &a,
            &numeric_gradient_richardson(&mut x, 1e-6, f),
            1e-12,
        );
        assert!(
            plain.max_rel > 1e-10 && rich.max_rel < plain.max_rel / 10.0,
            "{plain} {rich}"
        );
    }

    #[test]
    fn compare_detects_a_wrong_gradient() {
        let r = compare("f", &[1.0, 2.0], &[1.0, 2.1], 1e-12);
        assert!(!r.passes(1e-6));
        assert_eq!(r.worst, 1);
    }
}
