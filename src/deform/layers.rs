//! The fields' parameter layout and linear layers: each tensor's place in
//! the flat parameter vector ([`ParamSpec`]), how a linear layer reads its
//! weight and bias there and runs, alone or stacked with others of the same
//! input, and the builder of the layout in `state_dict` order.

use super::linear::{Linear, LinearGradients, LinearShape};
use crate::math::Real;

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

    /// The layer over its parameters in `p`.
    pub fn linear<'a, T: Real>(&self, p: &'a [T]) -> Linear<'a, T> {
        Linear::new(self.weight(p), self.bias(p), self.shape)
    }

    /// Write a weight and a bias gradient into `grad` (same layout as the
    /// parameters).
    pub(crate) fn store_grads<T: Real>(&self, grad: &mut [T], weight: &[T], bias: &[T]) {
        grad[self.w..self.w + weight.len()].copy_from_slice(weight);
        grad[self.b..self.b + bias.len()].copy_from_slice(bias);
    }

    /// Write the layer's weight and bias gradients into `grad`.
    pub fn store<T: Real>(&self, g: &LinearGradients<T>, grad: &mut [T]) {
        self.store_grads(grad, &g.weight, &g.bias);
    }
}

/// Several linear layers with the same input run as one (their weights
/// stacked by rows): the outputs are the same bits as running them one by one.
pub(crate) struct Stacked<'a>(pub &'a [LinearParams]);

impl Stacked<'_> {
    /// The stacked layer over the parameters in `p`: `[n, Σ out]`, the
    /// layers' outputs side by side.
    pub fn linear<T: Real>(&self, p: &[T]) -> Linear<'static, T> {
        let layers: Vec<Linear<'_, T>> = self.0.iter().map(|l| l.linear(p)).collect();
        Linear::stacked(&layers)
    }

    /// Write the stacked layer's gradients into `grad`, layer by layer.
    pub fn store<T: Real>(&self, g: &LinearGradients<T>, grad: &mut [T]) {
        let mut row = 0;
        for l in self.0 {
            let (o, in_dim) = (l.shape.out_dim, l.shape.in_dim);
            l.store_grads(
                grad,
                &g.weight[row * in_dim..(row + o) * in_dim],
                &g.bias[row..row + o],
            );
            row += o;
        }
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
