//! The time input of a field: `timenet(γ₆(t))` for synthetic scenes,
//! `γ₁₀(t)` for real ones, with its backward.

use super::activation::{self, Activation};
use super::config::{Variant, TIMENET_HIDDEN, TIMENET_OUT, T_LEVELS_REAL, T_LEVELS_SYNTHETIC};
use super::encoding;
use super::layers::{Init, LayoutBuilder, LinearParams};
use super::linear::{Epilogue, Input, InputGrad, OutputGrad};
use super::profile;
use crate::kernels::vec_written_by;
use crate::math::Real;
use std::mem::MaybeUninit;

/// The time input of a field: `timenet(γ₆(t))` or `γ₁₀(t)`.
#[derive(Clone, Debug)]
pub(crate) enum TimeEmbedding {
    Timenet { l0: LinearParams, l1: LinearParams },
    Encoded,
}

/// What the time embedding's backward needs.
pub(crate) enum TimeEmbeddingSaved<T> {
    Timenet {
        /// γ₆(t) `[n, 13]`.
        enc: Vec<T>,
        /// ReLU output of the hidden layer `[n, 256]` (its backward needs
        /// only the output, so no pre-activation is kept).
        hidden: Vec<T>,
    },
    Encoded,
}

impl TimeEmbedding {
    pub fn build(variant: Variant, lb: &mut LayoutBuilder) -> Self {
        match variant {
            Variant::Synthetic => {
                let e = encoding::encoded_dim(1, T_LEVELS_SYNTHETIC);
                let l0 = lb.linear("timenet.0", e, TIMENET_HIDDEN, Init::TorchDefault);
                let l1 = lb.linear("timenet.2", TIMENET_HIDDEN, TIMENET_OUT, Init::TorchDefault);
                TimeEmbedding::Timenet { l0, l1 }
            }
            Variant::Real => TimeEmbedding::Encoded,
        }
    }

    /// The time feature `[n, 30 | 21]`.
    pub fn forward<T: Real>(&self, p: &[T], t: &[T]) -> (Vec<T>, TimeEmbeddingSaved<T>) {
        let n = t.len();
        match self {
            TimeEmbedding::Timenet { l0, l1 } => {
                let enc = encoding::encode(t, 1, T_LEVELS_SYNTHETIC);
                // timenet.2 runs on each block of hidden rows as it leaves
                // timenet.0 (bias, ReLU), while the block is in cache.
                let next = l1.linear(p).packed();
                let nw = next.out_dim();
                let chain = |_: usize, blk: &mut [T], out: &mut [MaybeUninit<T>]| {
                    next.forward_block_into(blk, out.len() / nw.max(1), out);
                };
                let mut hidden = Vec::new();
                let feat = vec_written_by(n * nw, |feat| {
                    hidden = profile::layer(
                        || "timenet.0 + ReLU, timenet.2 in its epilogue".into(),
                        || {
                            l0.linear(p).forward(
                                Input::blocks(&[(&enc, l0.shape.in_dim)]),
                                n,
                                Epilogue::act(Activation::Relu).then(feat, nw, &chain),
                            )
                        },
                    );
                    // SAFETY: the epilogue wrote every row of `feat` (each
                    // block of rows is visited once, and forward_block_into
                    // writes all of its output).
                    unsafe { &mut *(feat as *mut [MaybeUninit<T>] as *mut [T]) }
                });
                (feat, TimeEmbeddingSaved::Timenet { enc, hidden })
            }
            TimeEmbedding::Encoded => (
                encoding::encode(t, 1, T_LEVELS_REAL),
                TimeEmbeddingSaved::Encoded,
            ),
        }
    }

    /// Gradient with respect to `t` `[n]` given the feature gradient.
    pub fn backward<T: Real>(
        &self,
        p: &[T],
        t: &[T],
        cache: &TimeEmbeddingSaved<T>,
        g_feat: &[T],
        grad: &mut [T],
    ) -> Vec<T> {
        let n = t.len();
        match (self, cache) {
            (TimeEmbedding::Timenet { l0, l1 }, TimeEmbeddingSaved::Timenet { enc, hidden }) => {
                let mut gh = profile::layer(
                    || "timenet.2".into(),
                    || {
                        let mut r = l1.linear(p).backward(
                            &[(hidden, TIMENET_HIDDEN)],
                            OutputGrad::Given(g_feat),
                            n,
                            InputGrad::From(0),
                        );
                        l1.store(&r, grad);
                        r.take_input(0)
                    },
                )
                .expect("input gradient requested");
                profile::elementwise(
                    || "timenet.0 / ReLU vjp".into(),
                    n,
                    TIMENET_HIDDEN,
                    || activation::relu_backward_from_output(hidden, &mut gh),
                );
                let genc = profile::layer(
                    || "timenet.0".into(),
                    || {
                        let mut r = l0.linear(p).backward(
                            &[(enc, l0.shape.in_dim)],
                            OutputGrad::Given(&gh),
                            n,
                            InputGrad::From(0),
                        );
                        l0.store(&r, grad);
                        r.take_input(0)
                    },
                )
                .expect("input gradient requested");
                encoding::encode_vjp(t, &genc, 1, T_LEVELS_SYNTHETIC)
            }
            _ => encoding::encode_vjp(t, g_feat, 1, T_LEVELS_REAL),
        }
    }
}
