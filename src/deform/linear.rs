//! A fully connected layer `y = x·Wᵀ + b`, PyTorch layout (`W` `[out, in]`,
//! `b` `[out]`), on a batch `x` `[n, in]`, with its vjp: [`Linear`], with one
//! [`forward`](Linear::forward) and one [`backward`](Linear::backward).
//!
//! Each output is `(Σ_k x_k·W_jk, k ascending from zero) + b_j`: the bias is
//! added after the dot product. The forward reads its input as column
//! blocks ([`Input`], never concatenated; optionally continuing sums over
//! earlier columns computed elsewhere) and runs an [`Epilogue`] (bias,
//! activation, then any function, for example the next layer) on each block
//! of output rows while it is in cache. The backward takes the output
//! gradient given or produced chunk by chunk ([`OutputGrad`], for example by
//! an activation's vjp) and computes the weight, bias and input gradients
//! from each chunk while it is in cache.

use super::activation::Activation;
use super::profile;
use crate::kernels::matmul::{
    column_sums, matmul_block_into, matmul_from_parts_then, matmul_tn, pack, MatRef, Packed,
    REDUCTION_CHUNK,
};
use crate::math::Real;
use rayon::prelude::*;
use std::borrow::Cow;
use std::mem::MaybeUninit;

/// Shape of a linear layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LinearShape {
    /// Input width (columns of `W`).
    pub in_dim: usize,
    /// Output width (rows of `W`).
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

/// A linear layer's parameters: `W` `[out, in]` (PyTorch layout) and `b`
/// `[out]`, borrowed from the flat parameter vector, or owned when several
/// layers with the same input are stacked into one (their rows one after
/// the other; the outputs are the same bits as running them one by one).
///
/// One [`forward`](Self::forward) (input as column blocks, an epilogue on
/// each block of output rows) and one [`backward`](Self::backward) (the
/// output gradient given or produced chunk by chunk).
#[derive(Clone, Debug)]
pub struct Linear<'a, T: Clone> {
    weight: Cow<'a, [T]>,
    bias: Cow<'a, [T]>,
    shape: LinearShape,
}

/// The input of a linear layer's forward: column blocks `[x₁ | x₂ | …]`
/// (each `[n, widthᵢ]`, row-major), read in place, never concatenated; the
/// result has the same bits as on the concatenated input.
#[derive(Clone, Copy, Debug)]
pub struct Input<'a, T> {
    /// Sums over `W`'s first `done` columns already computed, `[n, out]`
    /// (any strides), that the product continues term by term.
    sums: Option<MatRef<'a, T>>,
    done: usize,
    blocks: &'a [(&'a [T], usize)],
    /// Whether the blocks may end before the last column (the rest is an
    /// input known to be zero, skipped).
    zero_rest: bool,
}

impl<'a, T: Real> Input<'a, T> {
    /// The column blocks `(xᵢ, widthᵢ)`, widths adding up to `in`.
    pub fn blocks(blocks: &'a [(&'a [T], usize)]) -> Self {
        Input {
            sums: None,
            done: 0,
            blocks,
            zero_rest: false,
        }
    }

    /// Sums `[n, out]` over `W`'s first `done` columns, already computed
    /// (for example a column block of a wider product over a shared input),
    /// continued over `blocks` (the next columns), the same bits as one sum
    /// over all the columns in order. The columns after the blocks, if any,
    /// are an input known to be zero: they are skipped, which gives the same
    /// bits whenever no sum is −0 before them (a sum that starts from +0 and
    /// has a non-zero term is never −0 in round-to-nearest, so adding the
    /// exact zeros `0·w` changes nothing).
    pub fn continuing(sums: MatRef<'a, T>, done: usize, blocks: &'a [(&'a [T], usize)]) -> Self {
        Input {
            sums: Some(sums),
            done,
            blocks,
            zero_rest: true,
        }
    }
}

/// What a linear layer's forward runs on each block of output rows right
/// after computing it (while it is in cache), after adding the bias: an
/// activation in place, then a function of the block.
pub struct Epilogue<'e, T> {
    act: Option<Activation>,
    then: Option<Then<'e, T>>,
}

/// `f(first_row, y_rows, side_rows)` on a block of output rows (see
/// [`Epilogue::then`]).
pub type BlockFn<'f, T> = dyn Fn(usize, &mut [T], &mut [MaybeUninit<T>]) + Sync + 'f;

/// `produce(first_row, chunk, side_rows)`: writes a chunk of an output
/// gradient (see [`OutputGrad::Produced`]).
pub type ChunkFn<'f, T> = dyn Fn(usize, &mut [T], &mut [T]) + Sync + 'f;

/// A function run on each block of output rows (see [`Epilogue::then`]).
struct Then<'e, T> {
    side: &'e mut [MaybeUninit<T>],
    side_w: usize,
    f: &'e BlockFn<'e, T>,
}

impl<'e, T: Real> Epilogue<'e, T> {
    /// Nothing after the bias: `y = x·Wᵀ + b`.
    pub fn none() -> Self {
        Epilogue {
            act: None,
            then: None,
        }
    }

    /// `y = act(x·Wᵀ + b)`, the bias and the activation in one pass.
    pub fn act(act: Activation) -> Self {
        Epilogue {
            act: Some(act),
            then: None,
        }
    }

    /// Then `f(first_row, y_rows, side_rows)` on each block of output rows,
    /// with the matching rows of `side` (`side_w` values per row; `side`
    /// may start uninitialised: an `f` that writes every value of its side
    /// rows fills it, as each block of rows is visited once). For example
    /// the next layer on the block ([`PackedLinear::forward_block_into`]),
    /// or an activation written apart from the kept pre-activation.
    pub fn then(
        self,
        side: &'e mut [MaybeUninit<T>],
        side_w: usize,
        f: &'e BlockFn<'e, T>,
    ) -> Self {
        Epilogue {
            act: self.act,
            then: Some(Then { side, side_w, f }),
        }
    }
}

impl<'a, T: Real> Linear<'a, T> {
    /// A layer over `W` `[out, in]` and `b` `[out]`.
    pub fn new(weight: &'a [T], bias: &'a [T], shape: LinearShape) -> Self {
        assert_eq!(
            weight.len(),
            shape.in_dim * shape.out_dim,
            "linear: weight size"
        );
        assert_eq!(bias.len(), shape.out_dim, "linear: bias size");
        Linear {
            weight: Cow::Borrowed(weight),
            bias: Cow::Borrowed(bias),
            shape,
        }
    }

    /// Layers with the same input stacked into one: the outputs side by
    /// side, `[n, Σ out]`, the same bits as each layer alone.
    pub fn stacked(layers: &[Linear<'_, T>]) -> Linear<'static, T> {
        let in_dim = layers.first().map_or(0, |l| l.shape.in_dim);
        assert!(
            layers.iter().all(|l| l.shape.in_dim == in_dim),
            "linear: stacked layers differ in input width"
        );
        let out_dim = layers.iter().map(|l| l.shape.out_dim).sum();
        let mut weight = Vec::with_capacity(out_dim * in_dim);
        let mut bias = Vec::with_capacity(out_dim);
        for l in layers {
            weight.extend_from_slice(&l.weight);
            bias.extend_from_slice(&l.bias);
        }
        Linear {
            weight: Cow::Owned(weight),
            bias: Cow::Owned(bias),
            shape: LinearShape { in_dim, out_dim },
        }
    }

    /// The weight `W`, `[out, in]` row-major.
    pub fn weight(&self) -> &[T] {
        &self.weight
    }

    /// The layer's shape.
    pub fn shape(&self) -> LinearShape {
        self.shape
    }

    /// The layer packed for forwards one block of rows at a time (inside
    /// another product's epilogue).
    pub fn packed(&self) -> PackedLinear<T> {
        PackedLinear::new(&self.weight, &self.bias, self.shape)
    }

    /// `y = x·Wᵀ + b` on `n` rows, `[n, out]`, with the epilogue run on each
    /// block of output rows (see [`Epilogue`]).
    pub fn forward(&self, x: Input<'_, T>, n: usize, epilogue: Epilogue<'_, T>) -> Vec<T> {
        let LinearShape { in_dim, out_dim } = self.shape;
        let width: usize = x.blocks.iter().map(|&(_, d)| d).sum();
        assert!(
            x.done + width == in_dim || (x.zero_rest && x.done + width <= in_dim),
            "linear: input blocks do not add up to the input width"
        );
        if let Some(s) = x.sums {
            assert_eq!(
                (s.rows, s.cols),
                (n, out_dim),
                "linear: sums differ in shape"
            );
        }
        let wt = MatRef::row_major(&self.weight, out_dim, in_dim).t();
        let mut c0 = x.done;
        let parts: Vec<_> = x
            .blocks
            .iter()
            .map(|&(xb, d)| {
                let part = (MatRef::row_major(xb, n, d), wt.rows(c0, d));
                c0 += d;
                part
            })
            .collect();
        let Epilogue { act, then } = epilogue;
        let bias = &self.bias[..];
        let (side, side_w, f) = match then {
            Some(Then { side, side_w, f }) => (side, side_w, Some(f)),
            None => (&mut [][..], 0, None),
        };
        let label = || {
            format!(
                "{}x·Wᵀ + b{}{}",
                if x.sums.is_some() { "(sums) + " } else { "" },
                act.map_or(String::new(), |a| format!(", {a}")),
                if f.is_some() { ", epilogue" } else { "" }
            )
        };
        profile::product(label, n, width, out_dim, || {
            let epi = |r0: usize, blk: &mut [T], sb: &mut [MaybeUninit<T>]| {
                match act {
                    Some(a) => a.add_bias_apply_block(blk, bias),
                    None => add_bias(blk, bias, out_dim),
                }
                if let Some(f) = f {
                    f(r0, blk, sb)
                }
            };
            if parts.is_empty() {
                // Nothing to continue the sums over: a product over an
                // empty block gives the sums themselves.
                let empty = [(MatRef::row_major(&[], n, 0), wt.rows(c0, 0))];
                matmul_from_parts_then(x.sums, &empty, side, side_w, epi)
            } else {
                matmul_from_parts_then(x.sums, &parts, side, side_w, epi)
            }
        })
    }

    /// vjp of [`forward`](Self::forward) (without its epilogue) given the
    /// layer input as column blocks `x` (the whole input, widths adding up
    /// to `in`) and the output gradient `g` `[n, out]`: `Gᵀ·X`, the column
    /// sums of `G` and, per block, `G·W` on its columns at or after
    /// `InputGrad::From(c)`. The same bits as on the concatenated input and
    /// as the plain products over all rows: the work runs by chunks of
    /// [`REDUCTION_CHUNK`] rows, the chunks of the fixed-order reductions of
    /// [`matmul_tn`] and [`column_sums`], whose partials are added in chunk
    /// order.
    pub fn backward(
        &self,
        x: &[(&[T], usize)],
        g: OutputGrad<'_, T>,
        n: usize,
        input: InputGrad,
    ) -> LinearGradients<T> {
        linear_backward_parts(x, g, n, self.shape, &self.weight, input)
    }
}

/// `y += b` on each row of a block `[rows, out]`.
pub(crate) fn add_bias<T: Real>(blk: &mut [T], b: &[T], out_dim: usize) {
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
/// its input block is in cache): the same bits as [`Linear::forward`].
pub struct PackedLinear<T> {
    wt: Packed<T>,
    b: Vec<T>,
    shape: LinearShape,
}

impl<T: Real> PackedLinear<T> {
    /// Pack `W` `[out, in]` and keep `b` `[out]`.
    fn new(w: &[T], b: &[T], shape: LinearShape) -> Self {
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

    /// The bias `b` `[out]`.
    pub fn bias(&self) -> &[T] {
        &self.b
    }

    /// `y = x·Wᵀ` without the bias, as [`forward_block_into`](Self::forward_block_into)
    /// computes it before adding the bias.
    pub fn product_block_into<'o>(
        &self,
        x: &[T],
        rows: usize,
        out: &'o mut [MaybeUninit<T>],
    ) -> &'o mut [T] {
        matmul_block_into(MatRef::row_major(x, rows, self.shape.in_dim), &self.wt, out)
    }

    /// `y = x·Wᵀ + b` for the `rows` rows of `x` (`[rows, in]`), written into
    /// `out` (`[rows, out]`, may start uninitialised); returns `out`, written.
    pub fn forward_block_into<'o>(
        &self,
        x: &[T],
        rows: usize,
        out: &'o mut [MaybeUninit<T>],
    ) -> &'o mut [T] {
        let y = self.product_block_into(x, rows, out);
        add_bias(y, &self.b, self.shape.out_dim);
        y
    }
}

/// Gradients of a linear layer (see [`Linear::backward`]).
pub struct LinearGradients<T> {
    /// `Gᵀ·X`, `[out, in]` (the input blocks' columns side by side).
    pub weight: Vec<T>,
    /// Column sums of `G`, `[out]`.
    pub bias: Vec<T>,
    /// Per input block, `G·W` on its requested columns (`[n, count]`), or
    /// `None` where none of its columns is requested.
    pub input: Vec<Option<Vec<T>>>,
}

impl<T> LinearGradients<T> {
    /// Take the input gradient of block `i` (`None` if it was not
    /// requested or was taken already).
    pub fn take_input(&mut self, i: usize) -> Option<Vec<T>> {
        self.input.get_mut(i).and_then(Option::take)
    }
}

/// The gradient of a linear layer's output, `[n, out]`, for its backward.
pub enum OutputGrad<'a, T> {
    /// In memory.
    Given(&'a [T]),
    /// Computed for one chunk of rows at a time (a chunk of
    /// [`REDUCTION_CHUNK`] rows, so it is in cache while all three
    /// gradients read it), for example an activation's or a gate's vjp:
    /// `produce(first_row, chunk, side_rows)` writes every value of `chunk`
    /// (`[rows, out]`, holding stale values on entry) and may update the
    /// matching rows of `side` (`side_w` values a row).
    Produced {
        /// Writes a chunk of the output gradient.
        produce: &'a ChunkFn<'a, T>,
        /// Per-row values the producer updates (for example a gradient
        /// it accumulates), `[n, side_w]`; empty when `side_w` is 0.
        side: &'a mut [T],
        /// Values of `side` per row.
        side_w: usize,
    },
}

/// vjp of [`Linear::forward`] with the input as column blocks
/// `xs`: the same bits as on the concatenated input (every element of `Gᵀ·X`
/// and of `G·W` is a sum of its own, unaffected by how the columns are
/// grouped).
/// With `InputGrad::From(c)`, block `i` gets the gradient of its columns at
/// or after input column `c`.
///
/// The work runs chunk by chunk of [`REDUCTION_CHUNK`] rows (in parallel
/// over chunks): the chunk's output gradient (given, or produced there, see
/// [`OutputGrad`]) is read by the chunk's weight-gradient partial `Gᵀ·X`,
/// its bias partial (column sums) and its rows of the input gradient `G·W`
/// while it is in cache; the partials are added in chunk order. These are
/// the same chunks and the same order as [`matmul_tn`] and [`column_sums`]
/// over all rows, so the bits are the same as three separate passes.
fn linear_backward_parts<T: Real>(
    xs: &[(&[T], usize)],
    g: OutputGrad<'_, T>,
    n: usize,
    shape: LinearShape,
    w: &[T],
    input: InputGrad,
) -> LinearGradients<T> {
    let LinearShape { in_dim, out_dim } = shape;
    let requested = match input {
        InputGrad::Skip => 0,
        InputGrad::From(from) => in_dim.saturating_sub(from),
    };
    let produced = matches!(g, OutputGrad::Produced { .. });
    profile::op(
        profile::Kind::Product,
        || {
            format!(
                "{}weight grad Gᵀ·X, bias grad, input grad G·W (by chunks)",
                if produced { "G produced, " } else { "" }
            )
        },
        || format!("Gᵀ·[{n},{in_dim}], G·[{out_dim},{requested}], G [{n},{out_dim}]"),
        2.0 * (n * out_dim * (in_dim + requested)) as f64,
        || backward_by_chunks(xs, g, n, shape, w, input),
    )
}

/// The body of [`linear_backward_parts`].
fn backward_by_chunks<T: Real>(
    xs: &[(&[T], usize)],
    g: OutputGrad<'_, T>,
    n: usize,
    shape: LinearShape,
    w: &[T],
    input: InputGrad,
) -> LinearGradients<T> {
    let LinearShape { in_dim, out_dim } = shape;
    assert_eq!(
        xs.iter().map(|&(_, d)| d).sum::<usize>(),
        in_dim,
        "linear: input blocks do not add up to the input width"
    );
    for &(x, d) in xs {
        assert!(x.len() >= n * d, "linear: input block too short");
    }
    let wm = MatRef::row_major(w, out_dim, in_dim);
    // Per input block: its first column and the columns of it whose
    // gradient is requested (first, count), with Wᵀ's rows for them packed.
    type Block<T> = (usize, usize, Option<(usize, Packed<T>)>);
    let mut c0 = 0;
    let blocks: Vec<Block<T>> = xs
        .iter()
        .map(|&(_, d)| {
            let req = match input {
                InputGrad::From(from) if from < c0 + d => {
                    let s = from.max(c0);
                    let cols = c0 + d - s;
                    Some((cols, pack(wm.cols(s, cols))))
                }
                _ => None,
            };
            let b = (c0, d, req);
            c0 += d;
            b
        })
        .collect();
    // The input gradients, written chunk by chunk (never zeroed first).
    let mut grads: Vec<Option<Vec<T>>> = blocks
        .iter()
        .map(|(_, _, req)| req.as_ref().map(|(cols, _)| Vec::with_capacity(n * cols)))
        .collect();
    let (given, produce, side, side_w) = match g {
        OutputGrad::Given(g) => {
            assert!(g.len() >= n * out_dim, "linear: output gradient too short");
            (Some(g), None, &mut [][..], 0)
        }
        OutputGrad::Produced {
            produce,
            side,
            side_w,
        } => {
            assert_eq!(side.len(), n * side_w, "linear: side has the wrong size");
            (None, Some(produce), side, side_w)
        }
    };
    // One task per chunk, holding its rows of every output.
    struct Task<'o, T> {
        r0: usize,
        rows: usize,
        side: &'o mut [T],
        outs: Vec<Option<&'o mut [MaybeUninit<T>]>>,
    }
    let chunks = n.div_ceil(REDUCTION_CHUNK);
    let mut tasks: Vec<Task<'_, T>> = (0..chunks)
        .map(|c| {
            let r0 = c * REDUCTION_CHUNK;
            Task {
                r0,
                rows: REDUCTION_CHUNK.min(n - r0),
                side: &mut [],
                outs: Vec::with_capacity(blocks.len()),
            }
        })
        .collect();
    if side_w > 0 {
        for (task, s) in tasks
            .iter_mut()
            .zip(side.chunks_mut(REDUCTION_CHUNK * side_w))
        {
            task.side = s;
        }
    }
    for (out, (_, _, req)) in grads.iter_mut().zip(&blocks) {
        match (out, req) {
            (Some(v), Some((cols, _))) if *cols > 0 => {
                let mut parts =
                    v.spare_capacity_mut()[..n * cols].chunks_mut(REDUCTION_CHUNK * cols);
                for task in tasks.iter_mut() {
                    task.outs.push(parts.next());
                }
            }
            _ => tasks.iter_mut().for_each(|task| task.outs.push(None)),
        }
    }
    // Per chunk: the weight partial of every block and the bias partial.
    let partials: Vec<(Vec<Vec<T>>, Vec<T>)> = tasks
        .into_par_iter()
        .map_init(Vec::new, |buf: &mut Vec<T>, task| {
            let Task {
                r0,
                rows,
                side,
                outs,
            } = task;
            let gc: &[T] = match (given, produce) {
                (Some(g), _) => &g[r0 * out_dim..(r0 + rows) * out_dim],
                (None, Some(produce)) => {
                    // Reused across the chunks of a task (the producer
                    // writes every value).
                    buf.resize(rows * out_dim, T::ZERO);
                    produce(r0, buf, side);
                    buf
                }
                (None, None) => unreachable!("an output gradient is given or produced"),
            };
            let gm = MatRef::row_major(gc, rows, out_dim);
            let weights = xs
                .iter()
                .map(|&(x, d)| {
                    matmul_tn(gm, MatRef::row_major(&x[r0 * d..(r0 + rows) * d], rows, d))
                })
                .collect();
            for ((_, _, req), out) in blocks.iter().zip(outs) {
                if let (Some((_, packed)), Some(out)) = (req, out) {
                    matmul_block_into(gm, packed, out);
                }
            }
            (weights, column_sums(gc, rows, out_dim))
        })
        .collect();
    for (out, (_, _, req)) in grads.iter_mut().zip(&blocks) {
        if let (Some(v), Some((cols, _))) = (out, req) {
            // SAFETY: every chunk's task wrote all of its rows of this
            // input gradient (matmul_block_into writes its whole output).
            unsafe { v.set_len(n * cols) };
        }
    }
    // The partials added in chunk order (the first taken as is).
    let mut weight = vec![T::ZERO; out_dim * in_dim];
    let mut bias = vec![T::ZERO; out_dim];
    for (c, (wp, bp)) in partials.iter().enumerate() {
        for ((c0, d, _), part) in blocks.iter().zip(wp) {
            if *d == 0 {
                continue;
            }
            for (dst, src) in weight.chunks_exact_mut(in_dim).zip(part.chunks_exact(*d)) {
                add_or_copy(&mut dst[*c0..c0 + d], src, c == 0);
            }
        }
        add_or_copy(&mut bias, bp, c == 0);
    }
    LinearGradients {
        weight,
        bias,
        input: grads,
    }
}

/// `dst = src` (`first`) or `dst += src`, element-wise.
fn add_or_copy<T: Real>(dst: &mut [T], src: &[T], first: bool) {
    if first {
        dst.copy_from_slice(src);
    } else {
        for (a, &b) in dst.iter_mut().zip(src) {
            *a += b;
        }
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
            let layer = Linear::new(&w, &b, shape);
            let want = layer.forward(Input::blocks(&[(&x, in_dim)]), n, Epilogue::none());
            let packed = layer.packed();
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
        let layer = Linear::new(&w, &b, shape);
        let fwd = layer.forward(Input::blocks(&[(&x, in_dim)]), n, Epilogue::none());
        let fwd_parts = layer.forward(Input::blocks(&xs), n, Epilogue::none());
        assert!(fwd
            .iter()
            .zip(&fwd_parts)
            .all(|(a, b)| a.to_bits() == b.to_bits()));
        // Input gradient from column 7: nothing of the first two blocks
        // (columns 0..5), columns 7..14 of the third, all of the fourth.
        let mut whole = layer.backward(
            &[(&x, in_dim)],
            OutputGrad::Given(&g),
            n,
            InputGrad::From(7),
        );
        let parts = layer.backward(&xs, OutputGrad::Given(&g), n, InputGrad::From(7));
        let same = |a: &[f32], b: &[f32]| {
            a.len() == b.len() && a.iter().zip(b).all(|(a, b)| a.to_bits() == b.to_bits())
        };
        assert!(same(&whole.weight, &parts.weight));
        assert!(same(&whole.bias, &parts.bias));
        assert!(parts.input[0].is_none() && parts.input[1].is_none());
        let gin = whole.take_input(0).unwrap();
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

    /// The chunked backward gives the bits of the plain reference products
    /// over all rows (weight gradient `Gᵀ·X` and bias gradient with the
    /// fixed chunked reduction, input gradient `G·W`), with the output
    /// gradient given or produced chunk by chunk, on every kernel path and
    /// with 1 or 3 threads.
    #[test]
    fn chunked_backward_matches_the_reference_products() {
        let _isa = crate::kernels::fastmath::isa_test_lock();
        use crate::kernels::fastmath::{force_isa, Isa};
        use crate::kernels::matmul::reference;
        // Three chunks and a partial one; two input blocks.
        let (n, widths, out) = (2 * REDUCTION_CHUNK + 301, [13usize, 40], 70);
        let in_dim: usize = widths.iter().sum();
        let shape = LinearShape {
            in_dim,
            out_dim: out,
        };
        let f =
            |seed, len| -> Vec<f32> { cotangent(seed, len).iter().map(|&v| v as f32).collect() };
        let (x, w, g) = (f(21, n * in_dim), f(22, out * in_dim), f(23, n * out));
        let (x1, x2): (Vec<f32>, Vec<f32>) = (
            x.chunks_exact(in_dim)
                .flat_map(|r| r[..13].to_vec())
                .collect(),
            x.chunks_exact(in_dim)
                .flat_map(|r| r[13..].to_vec())
                .collect(),
        );
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        let gm = MatRef::row_major(&g, n, out);
        let want_w = reference::matmul_tn(gm, MatRef::row_major(&x, n, in_dim));
        let want_b = reference::column_sums(&g, n, out);
        let want_in = reference::matmul(gm, MatRef::row_major(&w, out, in_dim).cols(5, in_dim - 5));
        // The rows 2·g + 1 "produced" from the row number, and a side
        // column counting the rows each chunk saw.
        let g_half: Vec<f32> = g.iter().map(|&v| (v - 1.0) / 2.0).collect();
        let produce = |r0: usize, chunk: &mut [f32], side: &mut [f32]| {
            let rows = side.len();
            for (c, &h) in chunk.iter_mut().zip(&g_half[r0 * out..(r0 + rows) * out]) {
                *c = 2.0 * h + 1.0;
            }
            for s in side.iter_mut() {
                *s += 1.0;
            }
        };
        let g_prod: Vec<f32> = g_half.iter().map(|&h| 2.0 * h + 1.0).collect();
        let want_w_prod = reference::matmul_tn(
            MatRef::row_major(&g_prod, n, out),
            MatRef::row_major(&x, n, in_dim),
        );
        for isa in [
            Some(Isa::Baseline),
            Some(Isa::Avx2),
            Some(Isa::Avx512),
            None,
        ] {
            if !force_isa(isa) {
                continue;
            }
            for threads in [1, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                pool.install(|| {
                    let xs = [(&x1[..], 13), (&x2[..], 40)];
                    let r = linear_backward_parts(
                        &xs,
                        OutputGrad::Given(&g),
                        n,
                        shape,
                        &w,
                        InputGrad::From(5),
                    );
                    assert_eq!(bits(&r.weight), bits(&want_w));
                    assert_eq!(bits(&r.bias), bits(&want_b));
                    let (g1, g2) = (r.input[0].as_ref().unwrap(), r.input[1].as_ref().unwrap());
                    let got_in: Vec<f32> = g1
                        .chunks_exact(8)
                        .zip(g2.chunks_exact(40))
                        .flat_map(|(a, b)| [a, b].concat())
                        .collect();
                    assert_eq!(bits(&got_in), bits(&want_in));
                    let mut side = vec![0.0f32; n];
                    let r = linear_backward_parts(
                        &xs,
                        OutputGrad::Produced {
                            produce: &produce,
                            side: &mut side,
                            side_w: 1,
                        },
                        n,
                        shape,
                        &w,
                        InputGrad::Skip,
                    );
                    assert_eq!(bits(&r.weight), bits(&want_w_prod));
                    assert!(r.input.iter().all(Option::is_none));
                    assert!(side.iter().all(|&s| s == 1.0), "every row produced once");
                });
            }
        }
        force_isa(None);
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
            Linear::new(w, b, shape)
                .forward(Input::blocks(&[(x, 5)]), n, Epilogue::none())
                .iter()
                .zip(&v)
                .map(|(a, b)| a * b)
                .sum()
        };
        let mut gr = Linear::new(&w, &[0.0; 4], shape).backward(
            &[(&x, 5)],
            OutputGrad::Given(&v),
            n,
            InputGrad::From(2),
        );
        let g_in = gr.take_input(0).unwrap();
        let nw = numeric_gradient(&mut w.clone(), 1e-6, |w| loss(&x, w, &b));
        let nb = numeric_gradient(&mut b.clone(), 1e-6, |b| loss(&x, &w, b));
        let nx = numeric_gradient(&mut x.clone(), 1e-6, |x| loss(x, &w, &b));
        let nx_tail: Vec<f64> = nx.chunks(5).flat_map(|r| r[2..].to_vec()).collect();
        for r in [
            compare("weight", &gr.weight, &nw, 1e-6),
            compare("bias", &gr.bias, &nb, 1e-6),
            compare("input", &g_in, &nx_tail, 1e-6),
        ] {
            assert!(r.passes(1e-8), "{r}");
        }
    }
}
