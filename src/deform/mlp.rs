//! The D-3DGS `DeformNetwork` (docs/UPSTREAM.md §6.2), exactly.
//!
//! `h₀ = [γ₁₀(x), t_feat]` (93 or 84 wide); for `k = 0..D`:
//! `h = ReLU(linear[k](h))`, and after layer `D/2` the input is concatenated
//! in front: `h = [γ₁₀(x), t_feat, h]`, so `linear[D/2 + 1]` takes `W + in`.
//! Three heads on the last `h`: `gaussian_warp` (3), `gaussian_rotation` (4),
//! `gaussian_scaling` (3), no output activation.
//!
//! 6-DoF variant (`is_6dof`): `branch_w` (3) and `branch_v` (3) replace
//! `gaussian_warp`, and `d_xyz` is the SE(3) warp of [`super::se3`]
//! (`R·x + p − x`); rotation and scaling heads are unchanged. Heads run as one
//! stacked product in `state_dict` order (`branch_w`, `branch_v`,
//! `gaussian_rotation`, `gaussian_scaling`).

use super::activation::{relu_backward_from_output_block, Activation};
use super::encoding::{encode, encoded_dim};
use super::linear::{Epilogue, Input, InputGrad, OutputGrad};
use super::profile;
use super::se3;
use super::{
    Deformation, Init, LayoutBuilder, LinearParams, MlpConfig, Stacked, TimeEmbedding,
    TimeEmbeddingSaved, XYZ_LEVELS,
};
use crate::kernels::vec_written_by;
use crate::math::Real;
use std::mem::MaybeUninit;

/// Architecture and parameter places of the MLP field.
#[derive(Clone, Debug)]
pub(crate) struct MlpNet {
    time: TimeEmbedding,
    layers: Vec<LinearParams>,
    /// Heads in `state_dict` order: warp, rotation, scaling; or, 6-DoF,
    /// branch_w, branch_v, rotation, scaling.
    heads: Vec<LinearParams>,
    is_6dof: bool,
    /// The layer after which the input is concatenated (D/2).
    skip: usize,
    in_dim: usize,
    width: usize,
}

/// What the MLP's backward needs.
pub(crate) struct MlpCache<T> {
    time: TimeEmbeddingSaved<T>,
    /// `γ(x)` `[n, 63]` and `t_feat`: the two blocks of `h₀`, kept apart
    /// (layer 0 and the layer after the skip read them as column blocks of
    /// their input, so `h₀` and the skip's concatenation are never built).
    x_emb: Vec<T>,
    t_feat: Vec<T>,
    /// Output of each trunk layer but the last (`[n, W]`, after ReLU); the
    /// last one's is `head_in`. The ReLU backward needs only that output (no
    /// pre-activations kept).
    outputs: Vec<Vec<T>>,
    /// Input of the heads `[n, W]`.
    head_in: Vec<T>,
    /// 6-DoF only: the canonical positions `[n, 3]` and the raw
    /// `branch_w | branch_v` outputs `[n, 6]`.
    warp: Option<(Vec<T>, Vec<T>)>,
}

impl MlpNet {
    pub fn build(c: &MlpConfig, lb: &mut LayoutBuilder) -> Self {
        let time = TimeEmbedding::build(c.variant, lb);
        let in_dim = c.variant.input_dim();
        let (d, w) = (c.depth, c.width);
        let skip = d / 2;
        let mut layers = vec![lb.linear("linear.0", in_dim, w, Init::TorchDefault)];
        for i in 0..d - 1 {
            let fan_in = if i == skip { w + in_dim } else { w };
            layers.push(lb.linear(&format!("linear.{}", i + 1), fan_in, w, Init::TorchDefault));
        }
        let mut heads = Vec::with_capacity(4);
        if c.is_6dof {
            heads.push(lb.linear("branch_w", w, 3, Init::TorchDefault));
            heads.push(lb.linear("branch_v", w, 3, Init::TorchDefault));
        } else {
            heads.push(lb.linear("gaussian_warp", w, 3, Init::TorchDefault));
        }
        heads.push(lb.linear("gaussian_rotation", w, 4, Init::TorchDefault));
        heads.push(lb.linear("gaussian_scaling", w, 3, Init::TorchDefault));
        MlpNet {
            time,
            layers,
            heads,
            is_6dof: c.is_6dof,
            skip,
            in_dim,
            width: w,
        }
    }

    pub fn forward<T: Real>(&self, p: &[T], xyz: &[T], t: &[T]) -> (Deformation<T>, MlpCache<T>) {
        let n = t.len();
        let xd = encoded_dim(3, XYZ_LEVELS);
        let x_emb = profile::elementwise(
            || "γ(x) encoding".into(),
            n,
            xd,
            || encode(xyz, 3, XYZ_LEVELS),
        );
        let (t_feat, time) = profile::layer(|| "timenet".into(), || self.time.forward(p, t));
        let td = self.in_dim - xd;
        let mut outputs: Vec<Vec<T>> = Vec::with_capacity(self.layers.len());
        let mut cur: Vec<T> = Vec::new();
        // The heads run on each block of rows of the last layer's output as
        // it leaves that layer, while the block is in cache.
        let heads = Stacked(&self.heads).linear(p).packed();
        let hw = heads.out_dim();
        let chain = |_: usize, blk: &mut [T], out: &mut [MaybeUninit<T>]| {
            heads.forward_block_into(blk, out.len() / hw.max(1), out);
        };
        let mut head_out: Vec<T> = Vec::new();
        let last = self.layers.len() - 1;
        for (i, l) in self.layers.iter().enumerate() {
            // Layer 0 reads h₀ = [γ(x) | t_feat], the layer after the skip
            // [γ(x) | t_feat | h], both as column blocks; bias and ReLU on
            // each block of rows as it leaves the product.
            let xs: Vec<(&[T], usize)> = if i == 0 {
                vec![(&x_emb, xd), (&t_feat, td)]
            } else if i == self.skip + 1 {
                vec![(&x_emb, xd), (&t_feat, td), (&cur, self.width)]
            } else {
                vec![(&cur, self.width)]
            };
            let out = if i == last {
                let mut out = Vec::new();
                head_out = vec_written_by(n * hw, |y| {
                    out = profile::layer(
                        || format!("linear.{i} + ReLU, heads in its epilogue"),
                        || {
                            l.linear(p).forward(
                                Input::blocks(&xs),
                                n,
                                Epilogue::act(Activation::Relu).then(y, hw, &chain),
                            )
                        },
                    );
                    // SAFETY: the epilogue wrote every row of `y` (each block
                    // of rows is visited once, and forward_block_into writes
                    // all of its output).
                    unsafe { &mut *(y as *mut [MaybeUninit<T>] as *mut [T]) }
                });
                out
            } else {
                profile::layer(
                    || format!("linear.{i} + ReLU"),
                    || {
                        l.linear(p)
                            .forward(Input::blocks(&xs), n, Epilogue::act(Activation::Relu))
                    },
                )
            };
            if i > 0 {
                outputs.push(std::mem::replace(&mut cur, out));
            } else {
                cur = out;
            }
        }
        let (d, warp) = if self.is_6dof {
            let (d, wv) = warp_forward(&head_out, xyz);
            (d, Some((xyz.to_vec(), wv)))
        } else {
            (Deformation::from_head(&head_out), None)
        };
        (
            d,
            MlpCache {
                time,
                x_emb,
                t_feat,
                outputs,
                head_in: cur,
                warp,
            },
        )
    }

    /// 6-DoF: upstream's per-Gaussian 4×4 transforms `[n, 16]` (row-major);
    /// `None` for the additive field.
    pub fn se3_transforms<T: Real>(&self, c: &MlpCache<T>) -> Option<Vec<T>> {
        let (_, wv) = c.warp.as_ref()?;
        let mut out = Vec::with_capacity(wv.len() / 6 * 16);
        for wv in wv.chunks_exact(6) {
            let m = se3::transform([wv[0], wv[1], wv[2]], [wv[3], wv[4], wv[5]]);
            for row in m {
                out.extend_from_slice(&row);
            }
        }
        Some(out)
    }

    /// Backward: adds the weights' gradient into `gp`; returns the gradient
    /// of `t` `[n]` and, 6-DoF only, of the canonical positions through the
    /// warp, `(R − I)ᵀ·g` per Gaussian `[n, 3]` (`None` for the additive
    /// field, whose only use of the positions is the stop-gradient input).
    pub fn backward<T: Real>(
        &self,
        p: &[T],
        t: &[T],
        c: &MlpCache<T>,
        g: &Deformation<T>,
        gp: &mut [T],
    ) -> (Vec<T>, Option<Vec<T>>) {
        let n = t.len();
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = self.in_dim - xd;
        let (g_head, g_xyz) = match &c.warp {
            None => (g.to_head(), None),
            Some((xyz, wv)) => {
                let (gh, gx) = warp_backward(g, xyz, wv);
                (gh, Some(gx))
            }
        };
        let mut dh = profile::layer(
            || "heads".into(),
            || {
                let heads = Stacked(&self.heads);
                let mut r = heads.linear(p).backward(
                    &[(&c.head_in, self.width)],
                    OutputGrad::Given(&g_head),
                    n,
                    InputGrad::From(0),
                );
                heads.store(&r, gp);
                r.take_input(0)
            },
        )
        .expect("input gradient requested");
        let mut g_tfeat = vec![T::ZERO; n * td];
        let w = self.width;
        for i in (0..self.layers.len()).rev() {
            // ReLU's vjp from the layer's output (see MlpCache::outputs),
            // producing the output gradient chunk by chunk inside the
            // layer's backward.
            let out = c.outputs.get(i).unwrap_or(&c.head_in);
            let g_out = &dh;
            let produce = |r0: usize, chunk: &mut [T], _: &mut [T]| {
                let rows = chunk.len() / w;
                chunk.copy_from_slice(&g_out[r0 * w..(r0 + rows) * w]);
                relu_backward_from_output_block(&out[r0 * w..(r0 + rows) * w], chunk)
            };
            let g = || OutputGrad::Produced {
                produce: &produce,
                side: &mut [],
                side_w: 0,
            };
            let lin = &self.layers[i];
            let name = || format!("linear.{i}, ReLU vjp producing G");
            let next = profile::layer(name, || {
                if i == 0 || i == self.skip + 1 {
                    // Input [γ(x) | t_feat (| h)]: γ(x) is stop-gradient; the
                    // t_feat block's gradient is collected, h's flows on.
                    let mut xs = vec![(&c.x_emb[..], xd), (&c.t_feat[..], td)];
                    if i > 0 {
                        xs.push((&c.outputs[i - 1][..], w));
                    }
                    let mut r = lin.linear(p).backward(&xs, g(), n, InputGrad::From(xd));
                    lin.store(&r, gp);
                    let g_t = r.take_input(1).expect("input gradient requested");
                    for (acc, v) in g_tfeat.iter_mut().zip(g_t) {
                        *acc += v;
                    }
                    (i > 0).then(|| r.take_input(2).expect("input gradient requested"))
                } else {
                    let mut r = lin.linear(p).backward(
                        &[(&c.outputs[i - 1], w)],
                        g(),
                        n,
                        InputGrad::From(0),
                    );
                    lin.store(&r, gp);
                    r.take_input(0)
                }
            });
            match next {
                Some(g) => dh = g,
                None => break,
            }
        }
        let g_t = profile::layer(
            || "timenet".into(),
            || self.time.backward(p, t, &c.time, &g_tfeat, gp),
        );
        (g_t, g_xyz)
    }
}

/// 6-DoF heads `[n, 13]` (w 3 | v 3 | rotation 4 | scaling 3) → the
/// deformation (d_xyz from the SE(3) warp) and the raw `w | v` `[n, 6]`.
fn warp_forward<T: Real>(head: &[T], xyz: &[T]) -> (Deformation<T>, Vec<T>) {
    let n = xyz.len() / 3;
    let mut d = Deformation::zeros(n);
    let mut wv = vec![T::ZERO; 6 * n];
    for i in 0..n {
        let r = &head[13 * i..13 * i + 13];
        let x = &xyz[3 * i..3 * i + 3];
        let dx = se3::warp([r[0], r[1], r[2]], [r[3], r[4], r[5]], [x[0], x[1], x[2]]);
        d.d_xyz[3 * i..3 * i + 3].copy_from_slice(&dx);
        d.d_rotation[4 * i..4 * i + 4].copy_from_slice(&r[6..10]);
        d.d_scaling[3 * i..3 * i + 3].copy_from_slice(&r[10..13]);
        wv[6 * i..6 * i + 6].copy_from_slice(&r[0..6]);
    }
    (d, wv)
}

/// vjp of [`warp_forward`]: the gradient of the `[n, 13]` head outputs and
/// of the canonical positions `[n, 3]` through `R·x` (`(R − I)ᵀ·g`).
fn warp_backward<T: Real>(g: &Deformation<T>, xyz: &[T], wv: &[T]) -> (Vec<T>, Vec<T>) {
    let n = xyz.len() / 3;
    let mut out = vec![T::ZERO; 13 * n];
    let mut g_xyz = vec![T::ZERO; 3 * n];
    for i in 0..n {
        let (w, x, gx) = (&wv[6 * i..6 * i + 6], &xyz[3 * i..], &g.d_xyz[3 * i..]);
        let gr = se3::warp_vjp(
            [w[0], w[1], w[2]],
            [w[3], w[4], w[5]],
            [x[0], x[1], x[2]],
            [gx[0], gx[1], gx[2]],
        );
        let o = &mut out[13 * i..13 * i + 13];
        o[0..3].copy_from_slice(&gr.w);
        o[3..6].copy_from_slice(&gr.v);
        o[6..10].copy_from_slice(&g.d_rotation[4 * i..4 * i + 4]);
        o[10..13].copy_from_slice(&g.d_scaling[3 * i..3 * i + 3]);
        g_xyz[3 * i..3 * i + 3].copy_from_slice(&gr.x);
    }
    (out, g_xyz)
}
