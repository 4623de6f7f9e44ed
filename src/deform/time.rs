//! The time input of a field: `timenet(γ₆(t))` for synthetic scenes,
//! `γ₁₀(t)` for real ones, with its backward.
//!
//! The timenet is a function of `t` alone, and the Gaussians of a frame share
//! `t`: it runs once per run of equal times (bit for bit) and its output is
//! copied to the run's rows, the same bits as one evaluation per row. Its
//! backward adds each run's output gradients first (in the fixed chunk order
//! of [`column_sums`]) and runs once per run; the gradient with respect to
//! each row's `t` is that row's output gradient times the run's Jacobian
//! `∂timenet/∂t` (30 values, in forward mode), so it too depends on the row
//! alone. With every time distinct, every run is one row and the weight
//! gradients are those of the per-row backward.

use super::activation::{self, Activation};
use super::config::{Variant, TIMENET_HIDDEN, TIMENET_OUT, T_LEVELS_REAL, T_LEVELS_SYNTHETIC};
use super::encoding;
use super::layers::{Init, LayoutBuilder, LinearParams};
use super::linear::{Epilogue, Input, InputGrad, OutputGrad};
use super::profile;
use crate::kernels::matmul::{column_sums, matmul, MatRef};
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
        /// The runs `[i, j)` of rows with equal `t`, in order.
        runs: Vec<(usize, usize)>,
        /// γ₆(t) of each run `[runs, 13]`.
        enc: Vec<T>,
        /// ReLU output of the hidden layer, per run `[runs, 256]` (its
        /// backward needs only the output, so no pre-activation is kept).
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
                let runs: Vec<(usize, usize)> = equal_runs(t).collect();
                let reps: Vec<T> = runs.iter().map(|&(i, _)| t[i]).collect();
                let m = runs.len();
                let enc = encoding::encode(&reps, 1, T_LEVELS_SYNTHETIC);
                // timenet.2 runs on each block of hidden rows as it leaves
                // timenet.0 (bias, ReLU), while the block is in cache.
                let next = l1.linear(p).packed();
                let nw = next.out_dim();
                let chain = |_: usize, blk: &mut [T], out: &mut [MaybeUninit<T>]| {
                    next.forward_block_into(blk, out.len() / nw.max(1), out);
                };
                let mut hidden = Vec::new();
                let feat = vec_written_by(m * nw, |feat| {
                    hidden = profile::layer(
                        || "timenet.0 + ReLU, timenet.2 in its epilogue".into(),
                        || {
                            l0.linear(p).forward(
                                Input::blocks(&[(&enc, l0.shape.in_dim)]),
                                m,
                                Epilogue::act(Activation::Relu).then(feat, nw, &chain),
                            )
                        },
                    );
                    // SAFETY: the epilogue wrote every row of `feat` (each
                    // block of rows is visited once, and forward_block_into
                    // writes all of its output).
                    unsafe { &mut *(feat as *mut [MaybeUninit<T>] as *mut [T]) }
                });
                let feat = if m == n {
                    feat
                } else {
                    let mut rows = Vec::with_capacity(n * nw);
                    for (&(i, j), f) in runs.iter().zip(feat.chunks_exact(nw.max(1))) {
                        for _ in i..j {
                            rows.extend_from_slice(f);
                        }
                    }
                    rows
                };
                (feat, TimeEmbeddingSaved::Timenet { runs, enc, hidden })
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
            (
                TimeEmbedding::Timenet { l0, l1 },
                TimeEmbeddingSaved::Timenet { runs, enc, hidden },
            ) => {
                let m = runs.len();
                let nw = l1.shape.out_dim;
                // Each run's output gradient: its rows' gradients added.
                let summed;
                let g_runs: &[T] = if m == n {
                    g_feat
                } else {
                    summed = profile::elementwise(
                        || "timenet / output gradients added per run of equal t".into(),
                        n,
                        nw,
                        || {
                            runs.iter()
                                .flat_map(|&(i, j)| column_sums(&g_feat[i * nw..j * nw], j - i, nw))
                                .collect::<Vec<T>>()
                        },
                    );
                    &summed
                };
                let mut gh = profile::layer(
                    || "timenet.2".into(),
                    || {
                        let mut r = l1.linear(p).backward(
                            &[(hidden, TIMENET_HIDDEN)],
                            OutputGrad::Given(g_runs),
                            m,
                            InputGrad::From(0),
                        );
                        l1.store(&r, grad);
                        r.take_input(0)
                    },
                )
                .expect("input gradient requested");
                profile::elementwise(
                    || "timenet.0 / ReLU vjp".into(),
                    m,
                    TIMENET_HIDDEN,
                    || activation::relu_backward_from_output(hidden, &mut gh),
                );
                profile::layer(
                    || "timenet.0".into(),
                    || {
                        let r = l0.linear(p).backward(
                            &[(enc, l0.shape.in_dim)],
                            OutputGrad::Given(&gh),
                            m,
                            InputGrad::Skip,
                        );
                        l0.store(&r, grad);
                    },
                );
                let jac = profile::layer(
                    || "timenet: ∂feature/∂t per run (forward mode)".into(),
                    || {
                        let reps: Vec<T> = runs.iter().map(|&(i, _)| t[i]).collect();
                        timenet_jacobian(p, l0, l1, &reps, hidden)
                    },
                );
                // dt of a row: its feature gradient · its run's Jacobian
                // (k ascending).
                let mut gt = vec![T::ZERO; n];
                for (&(i, j), jr) in runs.iter().zip(jac.chunks_exact(nw.max(1))) {
                    for (dt, g) in gt[i..j]
                        .iter_mut()
                        .zip(g_feat[i * nw..j * nw].chunks_exact(nw))
                    {
                        let mut s = T::ZERO;
                        for (&gk, &jk) in g.iter().zip(jr) {
                            s += gk * jk;
                        }
                        *dt = s;
                    }
                }
                gt
            }
            _ => encoding::encode_vjp(t, g_feat, 1, T_LEVELS_REAL),
        }
    }
}

/// `∂timenet(γ₆(t))/∂t` for each of `reps` `[m]`, `[m, 30]`, in forward mode:
/// `dγ/dt`, times timenet.0's weight, masked where the ReLU's output
/// (`hidden`, `[m, 256]`) is zero, times timenet.2's weight.
fn timenet_jacobian<T: Real>(
    p: &[T],
    l0: &LinearParams,
    l1: &LinearParams,
    reps: &[T],
    hidden: &[T],
) -> Vec<T> {
    let denc = encoding::encode_derivative(reps, T_LEVELS_SYNTHETIC);
    let (l0s, l1s) = (l0.shape, l1.shape);
    let w0 = MatRef::row_major(l0.weight(p), l0s.out_dim, l0s.in_dim).t();
    let mut dh = matmul(MatRef::row_major(&denc, reps.len(), l0s.in_dim), w0);
    activation::relu_backward_from_output(hidden, &mut dh);
    let w1 = MatRef::row_major(l1.weight(p), l1s.out_dim, l1s.in_dim).t();
    matmul(MatRef::row_major(&dh, reps.len(), l1s.in_dim), w1)
}

/// Whether two times are the same value, bit for bit.
pub(crate) fn same<T: Real>(a: T, b: T) -> bool {
    a.bits() == b.bits()
}

/// The runs `[i, j)` of rows with the same time (bit for bit), in order.
pub(crate) fn equal_runs<T: Real>(t: &[T]) -> impl Iterator<Item = (usize, usize)> + '_ {
    let mut i = 0;
    std::iter::from_fn(move || {
        if i == t.len() {
            return None;
        }
        let start = i;
        i += 1;
        while i < t.len() && same(t[i], t[start]) {
            i += 1;
        }
        Some((start, i))
    })
}
