//! The fields' parameter layout and linear layers: each tensor's place in
//! the flat parameter vector ([`ParamSpec`]), how a linear layer reads its
//! weight and bias there and runs, alone or stacked with others of the same
//! input, and the builder of the layout in `state_dict` order.

use super::activation::Activation;
use super::linear::{
    linear_backward, linear_backward_parts, linear_forward, linear_forward_parts_then, InputGrad,
    LinearShape, PackedLinear,
};
use crate::kernels::vec_written_by;
use crate::math::Real;
use std::mem::MaybeUninit;

/// One named tensor's place in the flat parameter vector.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParamSpec {
    /// PyTorch `state_dict` key.
    pub name: String,
    /// Tensor shape (PyTorch's, e.g. `[out, in]` for a weight).
    pub shape: Vec<usize>,
    /// Index of the first value in the flat parameter vector.
    pub offset: usize,
}

impl ParamSpec {
    /// Number of values.
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }
    /// Whether the tensor has no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The tensor's range in the flat parameter vector.
    pub fn range(&self) -> std::ops::Range<usize> {
        self.offset..self.offset + self.len()
    }
}

/// How a linear layer's weight is initialised (biases are always
/// `U(±1/√fan_in)`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Init {
    /// PyTorch's default: kaiming-uniform with a = √5, i.e. `U(±1/√fan_in)`.
    TorchDefault,
    /// Xavier-uniform, gain 1: `U(±√(6/(fan_in + fan_out)))` (ncps CfC cells).
    Xavier,
}

/// A linear layer's place in the flat parameter vector.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LinearParams {
    pub shape: LinearShape,
    pub w: usize,
    pub b: usize,
    pub init: Init,
}

impl LinearParams {
    /// The weight `[out, in]` in the flat parameters `p`.
    pub(crate) fn weight<'a, T>(&self, p: &'a [T]) -> &'a [T] {
        &p[self.w..self.w + self.shape.in_dim * self.shape.out_dim]
    }
    /// The bias `[out]` in the flat parameters `p`.
    pub(crate) fn bias<'a, T>(&self, p: &'a [T]) -> &'a [T] {
        &p[self.b..self.b + self.shape.out_dim]
    }

    /// Forward on `x` `[n, in]`.
    pub fn forward<T: Real>(&self, p: &[T], x: &[T], n: usize) -> Vec<T> {
        linear_forward(x, n, self.shape, self.weight(p), self.bias(p))
    }

    /// The layer packed for forwards one block of rows at a time (the same
    /// bits as [`forward`](Self::forward)).
    pub fn packed<T: Real>(&self, p: &[T]) -> PackedLinear<T> {
        PackedLinear::new(self.weight(p), self.bias(p), self.shape)
    }

    /// [`forward_parts_act`](Self::forward_parts_act) with the next layer
    /// `next` run on each block of output rows as it leaves this product,
    /// while the block is in cache. Returns (this layer's output, `next`'s
    /// output), the same bits as two separate forwards.
    pub fn forward_parts_act_chain<T: Real>(
        &self,
        p: &[T],
        xs: &[(&[T], usize)],
        n: usize,
        act: Activation,
        next: &PackedLinear<T>,
    ) -> (Vec<T>, Vec<T>) {
        let nw = next.out_dim();
        let mut h = Vec::new();
        let y = vec_written_by(n * nw, |y| {
            h = self.forward_parts_act_then(p, xs, n, act, y, nw, |_, blk, out| {
                next.forward_block_into(blk, out.len() / nw.max(1), out)
            });
            // SAFETY: the epilogue wrote every row of `y` (each block of rows
            // is visited once, and forward_block_into writes all of its
            // output).
            unsafe { &mut *(y as *mut [MaybeUninit<T>] as *mut [T]) }
        });
        (h, y)
    }

    /// `act(x·Wᵀ + b)` for an input given as column blocks `xs` (see
    /// [`forward_parts_then`](Self::forward_parts_then)): the bias and the
    /// activation in one pass over each block of output rows while it is in
    /// cache (the same values as [`forward`](Self::forward) on the
    /// concatenated input, then the activation).
    pub fn forward_parts_act<T: Real>(
        &self,
        p: &[T],
        xs: &[(&[T], usize)],
        n: usize,
        act: Activation,
    ) -> Vec<T> {
        self.forward_parts_act_then::<T, T, _>(p, xs, n, act, &mut [], 0, |_, _, _| {})
    }

    /// [`forward_parts_act`](Self::forward_parts_act), then `epilogue` on
    /// each block of output rows, after the activation (see
    /// [`linear_forward_parts_then`]).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_parts_act_then<T: Real, S: Send, F>(
        &self,
        p: &[T],
        xs: &[(&[T], usize)],
        n: usize,
        act: Activation,
        side: &mut [S],
        side_w: usize,
        epilogue: F,
    ) -> Vec<T>
    where
        F: Fn(usize, &mut [T], &mut [S]) + Sync,
    {
        let bias = self.bias(p);
        linear_forward_parts_then(
            xs,
            n,
            self.shape,
            self.weight(p),
            &[],
            side,
            side_w,
            |r0, blk, sb| {
                act.add_bias_apply_block(blk, bias);
                epilogue(r0, blk, sb)
            },
        )
    }

    /// [`forward_then`](Self::forward_then) for an input given as column
    /// blocks `xs` (`(block, width)`, see [`linear_forward_parts_then`]):
    /// the same bits as on the concatenated input, without building it.
    pub fn forward_parts_then<T: Real, S: Send, F>(
        &self,
        p: &[T],
        xs: &[(&[T], usize)],
        n: usize,
        side: &mut [S],
        side_w: usize,
        epilogue: F,
    ) -> Vec<T>
    where
        F: Fn(usize, &mut [T], &mut [S]) + Sync,
    {
        linear_forward_parts_then(
            xs,
            n,
            self.shape,
            self.weight(p),
            self.bias(p),
            side,
            side_w,
            epilogue,
        )
    }

    /// [`backward`](Self::backward) for an input given as column blocks:
    /// writes the weight and bias gradients into `grad` and returns, per
    /// block, the gradient of its requested columns (see
    /// [`linear_backward_parts`]).
    pub fn backward_parts<T: Real>(
        &self,
        p: &[T],
        xs: &[(&[T], usize)],
        g: &[T],
        n: usize,
        input: InputGrad,
        grad: &mut [T],
    ) -> Vec<Option<Vec<T>>> {
        let r = linear_backward_parts(xs, g, n, self.shape, self.weight(p), input);
        self.store_grads(grad, &r.weight, &r.bias);
        r.input
    }

    /// [`forward`](Self::forward) with an epilogue on each block of output
    /// rows (see [`linear_forward_parts_then`]).
    pub fn forward_then<T: Real, S: Send, F>(
        &self,
        p: &[T],
        x: &[T],
        n: usize,
        side: &mut [S],
        side_w: usize,
        epilogue: F,
    ) -> Vec<T>
    where
        F: Fn(usize, &mut [T], &mut [S]) + Sync,
    {
        self.forward_parts_then(p, &[(x, self.shape.in_dim)], n, side, side_w, epilogue)
    }

    /// Backward: writes the weight and bias gradients into `grad` (same
    /// layout as the parameters) and returns the requested input gradient.
    pub fn backward<T: Real>(
        &self,
        p: &[T],
        x: &[T],
        g: &[T],
        n: usize,
        input: InputGrad,
        grad: &mut [T],
    ) -> Option<Vec<T>> {
        let r = linear_backward(x, g, n, self.shape, self.weight(p), input);
        self.store_grads(grad, &r.weight, &r.bias);
        r.input
    }

    /// Write a weight and a bias gradient into `grad` (same layout as the
    /// parameters).
    pub(crate) fn store_grads<T: Real>(&self, grad: &mut [T], weight: &[T], bias: &[T]) {
        grad[self.w..self.w + weight.len()].copy_from_slice(weight);
        grad[self.b..self.b + bias.len()].copy_from_slice(bias);
    }
}

/// Several linear layers with the same input run as one (their weights
/// stacked by rows): the outputs are the same bits as running them one by one.
pub(crate) struct Stacked<'a>(pub &'a [LinearParams]);

impl Stacked<'_> {
    pub(crate) fn in_dim(&self) -> usize {
        self.0[0].shape.in_dim
    }
    pub fn out_dim(&self) -> usize {
        self.0.iter().map(|l| l.shape.out_dim).sum()
    }
    pub(crate) fn gather<T: Real>(&self, p: &[T]) -> (Vec<T>, Vec<T>) {
        let mut w = Vec::with_capacity(self.out_dim() * self.in_dim());
        let mut b = Vec::with_capacity(self.out_dim());
        for l in self.0 {
            w.extend_from_slice(l.weight(p));
            b.extend_from_slice(l.bias(p));
        }
        (w, b)
    }
    pub(crate) fn shape(&self) -> LinearShape {
        LinearShape {
            in_dim: self.in_dim(),
            out_dim: self.out_dim(),
        }
    }
    /// The stacked layers packed for forwards one block of rows at a time:
    /// `[rows, Σ out]`, the layers' outputs side by side.
    pub fn packed<T: Real>(&self, p: &[T]) -> PackedLinear<T> {
        let (w, b) = self.gather(p);
        PackedLinear::new(&w, &b, self.shape())
    }
    /// [`forward`](Self::forward) with an epilogue on each block of output
    /// rows (see [`linear_forward_parts_then`]).
    pub fn forward_then<T: Real, S: Send, F>(
        &self,
        p: &[T],
        x: &[T],
        n: usize,
        side: &mut [S],
        side_w: usize,
        epilogue: F,
    ) -> Vec<T>
    where
        F: Fn(usize, &mut [T], &mut [S]) + Sync,
    {
        let (w, b) = self.gather(p);
        let xs = [(x, self.in_dim())];
        linear_forward_parts_then(&xs, n, self.shape(), &w, &b, side, side_w, epilogue)
    }
    /// Backward; `g` is `[n, Σ out]`.
    pub fn backward<T: Real>(
        &self,
        p: &[T],
        x: &[T],
        g: &[T],
        n: usize,
        input: InputGrad,
        grad: &mut [T],
    ) -> Option<Vec<T>> {
        let (w, _) = self.gather(p);
        let r = linear_backward(x, g, n, self.shape(), &w, input);
        let in_dim = self.in_dim();
        let mut row = 0;
        for l in self.0 {
            let o = l.shape.out_dim;
            l.store_grads(
                grad,
                &r.weight[row * in_dim..(row + o) * in_dim],
                &r.bias[row..row + o],
            );
            row += o;
        }
        r.input
    }
}

/// Builds the flat layout in `state_dict` order.
#[derive(Default)]
pub(crate) struct LayoutBuilder {
    pub specs: Vec<ParamSpec>,
    pub linears: Vec<LinearParams>,
    pub(crate) len: usize,
}

impl LayoutBuilder {
    pub(crate) fn push(&mut self, name: String, shape: Vec<usize>) -> usize {
        let off = self.len;
        self.len += shape.iter().product::<usize>();
        self.specs.push(ParamSpec {
            name,
            shape,
            offset: off,
        });
        off
    }
    /// Register `{prefix}.weight` `[out, in]` and `{prefix}.bias` `[out]`.
    pub fn linear(
        &mut self,
        prefix: &str,
        in_dim: usize,
        out_dim: usize,
        init: Init,
    ) -> LinearParams {
        let w = self.push(format!("{prefix}.weight"), vec![out_dim, in_dim]);
        let b = self.push(format!("{prefix}.bias"), vec![out_dim]);
        let l = LinearParams {
            shape: LinearShape { in_dim, out_dim },
            w,
            b,
            init,
        };
        self.linears.push(l);
        l
    }
}
