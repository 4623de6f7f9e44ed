//! Sums in a fixed order whose rounding error grows with log n, not n.

use super::Real;

/// `Σ v` by a fixed pairwise tree: a slice of at most 8 values is summed in
/// order, a longer one is split at `len / 2` and its halves' sums added. The
/// order depends on the length alone, so the bits do too.
pub fn pairwise_sum<T: Real>(v: &[T]) -> T {
    pairwise_sum_by(v.len(), |i| v[i])
}

/// [`pairwise_sum`] of the terms `term(0), …, term(n − 1)`, computed as they are
/// needed (same tree, same bits as summing the collected terms).
pub fn pairwise_sum_by<T: Real>(n: usize, term: impl Fn(usize) -> T + Copy) -> T {
    fn range<T: Real>(lo: usize, hi: usize, term: impl Fn(usize) -> T + Copy) -> T {
        if hi - lo <= 8 {
            let mut s = T::ZERO;
            for i in lo..hi {
                s += term(i);
            }
            return s;
        }
        let mid = lo + (hi - lo) / 2;
        range(lo, mid, term) + range(mid, hi, term)
    }
    range(0, n, term)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairwise_sum_is_exact_on_integers() {
        let v: Vec<f64> = (1..=1000).map(f64::from).collect();
        assert_eq!(pairwise_sum(&v), 500500.0);
        assert_eq!(pairwise_sum::<f64>(&[]), 0.0);
    }

    /// The tree written on slices, as LPIPS had it before this module:
    /// an independent statement of the order the bits depend on.
    fn slice_tree(v: &[f32]) -> f32 {
        if v.len() <= 8 {
            let mut s = 0f32;
            for &x in v {
                s += x;
            }
            return s;
        }
        let mid = v.len() / 2;
        slice_tree(&v[..mid]) + slice_tree(&v[mid..])
    }

    #[test]
    fn sums_give_the_bits_of_the_slice_tree() {
        let mut rng = crate::math::Rng::new(7);
        for n in [0usize, 1, 8, 9, 17, 1000, 4097] {
            // Terms of mixed sizes, so that the order shows in the bits.
            let v: Vec<f32> = (0..n)
                .map(|_| (rng.normal() * 10f64.powf(3.0 * rng.normal())) as f32)
                .collect();
            let want = slice_tree(&v).to_bits();
            assert_eq!(pairwise_sum(&v).to_bits(), want, "n = {n}");
            assert_eq!(pairwise_sum_by(n, |i| v[i]).to_bits(), want, "n = {n}");
        }
    }

    #[test]
    fn the_tree_is_fixed_by_the_length() {
        // 9 terms: [0..4) + [4..9), each leaf summed in order from zero. In
        // f32 (spacing 8 at 1e8) the tree gives 0 where a running sum gives 3.
        let v = [1e8f32, 1.0, 1.0, 1.0, -1e8, 3.0, 0.0, 0.0, 0.0];
        let left = (((0f32 + 1e8) + 1.0) + 1.0) + 1.0;
        let right = ((((0f32 + -1e8) + 3.0) + 0.0) + 0.0) + 0.0;
        assert_eq!(pairwise_sum(&v).to_bits(), (left + right).to_bits());
        let running = v.iter().fold(0f32, |s, &x| s + x);
        assert_eq!((left + right, running), (0.0, 3.0));
    }

    #[test]
    fn error_stays_small_where_a_running_sum_drifts() {
        // 2^20 copies of 0.1 in f32: the running sum drifts far (each addition
        // rounds at the sum's growing magnitude), the tree stays near the f64 value.
        let n = 1 << 20;
        let x = 0.1f32;
        let exact = f64::from(x) * n as f64;
        let mut running = 0f32;
        for _ in 0..n {
            running += x;
        }
        let tree = pairwise_sum_by(n, |_| x);
        let rel = |s: f32| ((f64::from(s) - exact) / exact).abs();
        assert!(rel(running) > 1e-3, "running sum error {}", rel(running));
        assert!(rel(tree) < 1e-6, "pairwise sum error {}", rel(tree));
    }
}
