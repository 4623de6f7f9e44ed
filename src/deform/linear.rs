//! A fully connected layer `y = x·Wᵀ + b`, PyTorch layout (`W` `[out, in]`,
//! `b` `[out]`), on a batch `x` `[n, in]`, with its vjp.
//!
//! Each output is `(Σ_k x_k·W_jk, k ascending from zero) + b_j`: the bias is
//! added after the dot product.

use super::profile;
use crate::kernels::matmul::{
    column_sums, matmul, matmul_block_into, matmul_parts_then, matmul_tn, pack, MatRef, Packed,
};
use crate::math::Real;
use std::mem::MaybeUninit;

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
    let xs = [(x, shape.in_dim)];
    linear_forward_parts_then::<T, T, _>(&xs, n, shape, w, b, &mut [], 0, |_, _, _| {})
}

/// `y = x·Wᵀ + b` for an input given as column blocks `x = [x₁ | x₂ | …]`
/// (`xs[i] = (xᵢ, width of xᵢ)`, each `[n, widthᵢ]`, widths adding up to
/// `in`; one block for a plain input), without concatenating them: the same
/// bits as on the concatenated input. Then `epilogue(first_row, y_rows,
/// side_rows)` on each block of output rows while it is in cache (see
/// [`matmul_parts_then`]); the bias is already added.
#[allow(clippy::too_many_arguments)]
pub fn linear_forward_parts_then<T: Real, S: Send, F>(
    xs: &[(&[T], usize)],
    n: usize,
    shape: LinearShape,
    w: &[T],
    b: &[T],
    side: &mut [S],
    side_w: usize,
    epilogue: F,
) -> Vec<T>
where
    F: Fn(usize, &mut [T], &mut [S]) + Sync,
{
    let LinearShape { in_dim, out_dim } = shape;
    assert_eq!(
        xs.iter().map(|&(_, d)| d).sum::<usize>(),
        in_dim,
        "linear: input blocks do not add up to the input width"
    );
    let wt = MatRef::row_major(w, out_dim, in_dim).t();
    let mut c0 = 0;
    let parts: Vec<_> = xs
        .iter()
        .map(|&(x, d)| {
            let part = (MatRef::row_major(x, n, d), wt.rows(c0, d));
            c0 += d;
            part
        })
        .collect();
    profile::product(
        || "x·Wᵀ + b (+ epilogue)".into(),
        n,
        in_dim,
        out_dim,
        || {
            matmul_parts_then(&parts, side, side_w, |r0, blk, sb| {
                add_bias(blk, b, out_dim);
                epilogue(r0, blk, sb)
            })
        },
    )
}

/// `y += b` on each row of a block `[rows, out]` (nothing when `b` is
/// empty: the bias is added elsewhere).
fn add_bias<T: Real>(blk: &mut [T], b: &[T], out_dim: usize) {
    if out_dim > 0 {
        for row in blk.chunks_exact_mut(out_dim) {
            for (v, &bj) in row.iter_mut().zip(b) {
                *v += bj;
            }
        }
    }
}

/// A linear layer with `Wᵀ` packed once, for forwards on one block of rows
/// at a time on the calling thread (inside another product's epilogue, while
/// its input block is in cache): the same bits as [`linear_forward`].
pub struct PackedLinear<T> {
    wt: Packed<T>,
    b: Vec<T>,
    shape: LinearShape,
}

impl<T: Real> PackedLinear<T> {
    /// Pack `W` `[out, in]` and keep `b` `[out]`.
    pub fn new(w: &[T], b: &[T], shape: LinearShape) -> Self {
        let wt = MatRef::row_major(w, shape.out_dim, shape.in_dim).t();
        PackedLinear {
            wt: pack(wt),
            b: b.to_vec(),
            shape,
        }
    }

    /// Output width.
    pub fn out_dim(&self) -> usize {
        self.shape.out_dim
    }

    /// `y = x·Wᵀ + b` for the `rows` rows of `x` (`[rows, in]`), written into
    /// `out` (`[rows, out]`, may start uninitialised).
    pub fn forward_block_into(&self, x: &[T], rows: usize, out: &mut [MaybeUninit<T>]) {
        let y = matmul_block_into(MatRef::row_major(x, rows, self.shape.in_dim), &self.wt, out);
        add_bias(y, &self.b, self.shape.out_dim);
    }
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
/// output gradient `g` `[n, out]` (the one-block case of
/// [`linear_backward_parts`]).
pub fn linear_backward<T: Real>(
    x: &[T],
    g: &[T],
    n: usize,
    shape: LinearShape,
    w: &[T],
    input: InputGrad,
) -> LinearGrads<T> {
    let mut r = linear_backward_parts(&[(x, shape.in_dim)], g, n, shape, w, input);
    LinearGrads {
        weight: r.weight,
        bias: r.bias,
        // Requested from column `in`: an empty gradient, not none.
        input: match input {
            InputGrad::Skip => None,
            InputGrad::From(_) => Some(r.input.pop().flatten().unwrap_or_default()),
        },
    }
}

/// Gradients of a linear layer whose input was given as column blocks.
pub struct LinearPartsGrads<T> {
    /// `Gᵀ·X`, `[out, in]` (the blocks' columns side by side).
    pub weight: Vec<T>,
    /// Column sums of `G`, `[out]`.
    pub bias: Vec<T>,
    /// Per input block, `G·W` on its requested columns (`[n, count]`), or
    /// `None` where none of its columns is requested.
    pub input: Vec<Option<Vec<T>>>,
}

/// vjp of [`linear_forward_parts_then`] with the input as column blocks
/// `xs`: the same bits as on the concatenated input (every element of `Gᵀ·X`
/// and of `G·W` is a sum of its own, unaffected by how the columns are
/// grouped).
/// With `InputGrad::From(c)`, block `i` gets the gradient of its columns at
/// or after input column `c`.
pub fn linear_backward_parts<T: Real>(
    xs: &[(&[T], usize)],
    g: &[T],
    n: usize,
    shape: LinearShape,
    w: &[T],
    input: InputGrad,
) -> LinearPartsGrads<T> {
    let LinearShape { in_dim, out_dim } = shape;
    assert_eq!(
        xs.iter().map(|&(_, d)| d).sum::<usize>(),
        in_dim,
        "linear: input blocks do not add up to the input width"
    );
    let gm = MatRef::row_major(g, n, out_dim);
    let wm = MatRef::row_major(w, out_dim, in_dim);
    let mut weight = vec![T::ZERO; out_dim * in_dim];
    let mut grads = Vec::with_capacity(xs.len());
    let mut c0 = 0;
    for &(x, d) in xs {
        let part = profile::product(
            || "weight grad Gᵀ·X".into(),
            out_dim,
            n,
            d,
            || matmul_tn(gm, MatRef::row_major(x, n, d)),
        );
        if d > 0 {
            for (dst, src) in weight.chunks_exact_mut(in_dim).zip(part.chunks_exact(d)) {
                dst[c0..c0 + d].copy_from_slice(src);
            }
        }
        grads.push(match input {
            InputGrad::From(from) if from < c0 + d => {
                let s = from.max(c0);
                let cols = c0 + d - s;
                Some(profile::product(
                    || "input grad G·W".into(),
                    n,
                    out_dim,
                    cols,
                    || matmul(gm, wm.cols(s, cols)),
                ))
            }
            _ => None,
        });
        c0 += d;
    }
    LinearPartsGrads {
        weight,
        bias: profile::elementwise(
            || "bias grad (column sums of G)".into(),
            n,
            out_dim,
            || column_sums(g, n, out_dim),
        ),
        input: grads,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};

    /// A packed layer run block by block (blocks of any height, as inside
    /// another product's epilogue) gives the same bits as the whole forward.
    #[test]
    fn packed_blocks_match_the_whole_forward() {
        for (n, in_dim, out) in [(150, 256, 10), (97, 13, 30), (5, 7, 40)] {
            let shape = LinearShape {
                in_dim,
                out_dim: out,
            };
            let f = |seed, len| -> Vec<f32> {
                cotangent(seed, len).iter().map(|&v| v as f32).collect()
            };
            let (x, w, b) = (f(5, n * in_dim), f(6, out * in_dim), f(7, out));
            let want = linear_forward(&x, n, shape, &w, &b);
            let packed = PackedLinear::new(&w, &b, shape);
            let mut got = vec![MaybeUninit::new(f32::NAN); n * out];
            let mut r0 = 0;
            for rows in [1, 12, 47, 48, 13].iter().cycle() {
                let rows = (*rows).min(n - r0);
                packed.forward_block_into(
                    &x[r0 * in_dim..(r0 + rows) * in_dim],
                    rows,
                    &mut got[r0 * out..(r0 + rows) * out],
                );
                r0 += rows;
                if r0 == n {
                    break;
                }
            }
            // SAFETY: initialised with NaN above (a value left unwritten
            // would show as a mismatch).
            let got: Vec<u32> = got
                .iter()
                .map(|v| unsafe { v.assume_init() }.to_bits())
                .collect();
            let want: Vec<u32> = want.iter().map(|v| v.to_bits()).collect();
            assert_eq!(got, want, "{n}x{in_dim}->{out}");
        }
    }

    /// An input given as column blocks gives the same bits, forward and
    /// backward, as the concatenated input.
    #[test]
    fn column_blocks_match_the_concatenated_input() {
        let (n, widths, out) = (700, [5usize, 0, 9, 4], 6);
        let in_dim: usize = widths.iter().sum();
        let shape = LinearShape {
            in_dim,
            out_dim: out,
        };
        let x: Vec<f32> = cotangent(1, n * in_dim).iter().map(|&v| v as f32).collect();
        let w: Vec<f32> = cotangent(2, out * in_dim)
            .iter()
            .map(|&v| v as f32)
            .collect();
        let b: Vec<f32> = cotangent(3, out).iter().map(|&v| v as f32).collect();
        let g: Vec<f32> = cotangent(4, n * out).iter().map(|&v| v as f32).collect();
        let mut blocks = Vec::new();
        let mut c0 = 0;
        for &d in &widths {
            let blk: Vec<f32> = x
                .chunks_exact(in_dim)
                .flat_map(|r| r[c0..c0 + d].to_vec())
                .collect();
            blocks.push(blk);
            c0 += d;
        }
        let xs: Vec<(&[f32], usize)> = blocks.iter().map(|v| &v[..]).zip(widths).collect();
        let fwd = linear_forward(&x, n, shape, &w, &b);
        let fwd_parts = linear_forward_parts_then::<f32, f32, _>(
            &xs,
            n,
            shape,
            &w,
            &b,
            &mut [],
            0,
            |_, _, _| {},
        );
        assert!(fwd
            .iter()
            .zip(&fwd_parts)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        // Input gradient from column 7: nothing of the first two blocks
        // (columns 0..5), columns 7..14 of the third, all of the fourth.
        let whole = linear_backward(&x, &g, n, shape, &w, InputGrad::From(7));
        let parts = linear_backward_parts(&xs, &g, n, shape, &w, InputGrad::From(7));
        let same = |a: &[f32], b: &[f32]| {
            a.len() == b.len() && a.iter().zip(b).all(|(a, b)| a.to_bits() == b.to_bits())
        };
        assert!(same(&whole.weight, &parts.weight));
        assert!(same(&whole.bias, &parts.bias));
        assert!(parts.input[0].is_none() && parts.input[1].is_none());
        let gin = whole.input.unwrap();
        let (g2, g3) = (
            parts.input[2].as_ref().unwrap(),
            parts.input[3].as_ref().unwrap(),
        );
        let want2: Vec<f32> = gin
            .chunks_exact(in_dim - 7)
            .flat_map(|r| r[..7].to_vec())
            .collect();
        let want3: Vec<f32> = gin
            .chunks_exact(in_dim - 7)
            .flat_map(|r| r[7..].to_vec())
            .collect();
        assert!(same(g2, &want2));
        assert!(same(g3, &want3));
    }

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
