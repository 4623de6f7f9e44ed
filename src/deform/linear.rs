//! A fully connected layer `y = x·Wᵀ + b`, PyTorch layout (`W` `[out, in]`,
//! `b` `[out]`), on a batch `x` `[n, in]`, with its vjp.
//!
//! Each output is `(Σ_k x_k·W_jk, k ascending from zero) + b_j`: the bias is
//! added after the dot product.

use super::matmul::{column_sums, matmul, matmul_then, matmul_tn, MatRef};
use crate::math::Real;

/// Shape of a linear layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LinearShape {
    pub in_dim: usize,
    pub out_dim: usize,
}

/// Which part of the input gradient the backward computes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputGrad {
    /// Not needed (the input is a constant or stop-gradient).
    Skip,
    /// Only input columns `from..in_dim` (for example the time part of a
    /// `[γ(x), t]` input whose x part is stop-gradient); returned `[n, in_dim − from]`.
    From(usize),
}

/// `y = x·Wᵀ + b` for `x` `[n, in]`; returns `[n, out]`.
pub fn linear_forward<T: Real>(x: &[T], n: usize, shape: LinearShape, w: &[T], b: &[T]) -> Vec<T> {
    linear_forward_then(x, n, shape, w, b, &mut [], 0, |_, _, _| {})
}

/// [`linear_forward`], then `epilogue(first_row, y_rows, side_rows)` on each
/// block of output rows while it is in cache (see
/// [`super::matmul::matmul_then`]); the bias is already added.
#[allow(clippy::too_many_arguments)]
pub fn linear_forward_then<T: Real, F>(
    x: &[T],
    n: usize,
    shape: LinearShape,
    w: &[T],
    b: &[T],
    side: &mut [T],
    side_w: usize,
    epilogue: F,
) -> Vec<T>
where
    F: Fn(usize, &mut [T], &mut [T]) + Sync,
{
    let LinearShape { in_dim, out_dim } = shape;
    let xm = MatRef::row_major(x, n, in_dim);
    let wt = MatRef::row_major(w, out_dim, in_dim).t();
    matmul_then(xm, wt, side, side_w, |r0, blk, sb| {
        if out_dim > 0 {
            for row in blk.chunks_exact_mut(out_dim) {
                for (v, &bj) in row.iter_mut().zip(b) {
                    *v += bj;
                }
            }
        }
        epilogue(r0, blk, sb)
    })
}

/// Gradients of a linear layer.
pub struct LinearGrads<T> {
    /// `Gᵀ·X`, `[out, in]`.
    pub weight: Vec<T>,
    /// Column sums of `G`, `[out]`.
    pub bias: Vec<T>,
    /// `G·W` restricted to the requested input columns, if requested.
    pub input: Option<Vec<T>>,
}

/// vjp of [`linear_forward`] given the layer input `x` `[n, in]` and the
/// output gradient `g` `[n, out]`.
pub fn linear_backward<T: Real>(
    x: &[T],
    g: &[T],
    n: usize,
    shape: LinearShape,
    w: &[T],
    input: InputGrad,
) -> LinearGrads<T> {
    let LinearShape { in_dim, out_dim } = shape;
    let gm = MatRef::row_major(g, n, out_dim);
    let xm = MatRef::row_major(x, n, in_dim);
    let weight = matmul_tn(gm, xm);
    let bias = column_sums(g, n, out_dim);
    let input = match input {
        InputGrad::Skip => None,
        InputGrad::From(c0) => {
            let wm = MatRef::row_major(w, out_dim, in_dim).cols(c0, in_dim - c0);
            Some(matmul(gm, wm))
        }
    };
    LinearGrads {
        weight,
        bias,
        input,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};

    #[test]
    fn vjp_matches_central_differences() {
        let shape = LinearShape {
            in_dim: 5,
            out_dim: 4,
        };
        let n = 3;
        let x = cotangent(1, n * 5);
        let w = cotangent(2, 20);
        let b = cotangent(3, 4);
        let v = cotangent(4, n * 4);
        let loss = |x: &[f64], w: &[f64], b: &[f64]| -> f64 {
            linear_forward(x, n, shape, w, b)
                .iter()
                .zip(&v)
                .map(|(a, b)| a * b)
                .sum()
        };
        let gr = linear_backward(&x, &v, n, shape, &w, InputGrad::From(2));
        let nw = numeric_gradient(&mut w.clone(), 1e-6, |w| loss(&x, w, &b));
        let nb = numeric_gradient(&mut b.clone(), 1e-6, |b| loss(&x, &w, b));
        let nx = numeric_gradient(&mut x.clone(), 1e-6, |x| loss(x, &w, &b));
        let nx_tail: Vec<f64> = nx.chunks(5).flat_map(|r| r[2..].to_vec()).collect();
        for r in [
            compare("weight", &gr.weight, &nw, 1e-6),
            compare("bias", &gr.bias, &nb, 1e-6),
            compare("input", gr.input.as_ref().unwrap(), &nx_tail, 1e-6),
        ] {
            assert!(r.passes(1e-8), "{r}");
        }
    }
}
