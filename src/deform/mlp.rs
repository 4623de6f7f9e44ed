//! The D-3DGS `DeformNetwork` (UPSTREAM §6.2), exactly.
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

use super::activation::{relu_backward_from_output, Activation};
use super::encoding::{encode, encoded_dim};
use super::linear::InputGrad;
use super::se3;
use super::{
    concat_cols, take_cols, Deformation, FieldConfig, Init, LayoutBuilder, LinearParams, Stacked,
    TimeCache, TimeEmbedding, XYZ_LEVELS,
};
use crate::math::Real;

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
    time: TimeCache<T>,
    /// Input of each trunk layer (`inputs[0]` = h₀). Layer `i`'s output is
    /// `inputs[i + 1]` (its last W columns after the skip), or `head_in`.
    /// The ReLU backward needs only that output (no pre-activations kept).
    inputs: Vec<Vec<T>>,
    /// Input of the heads `[n, W]`.
    head_in: Vec<T>,
    /// 6-DoF only: the canonical positions `[n, 3]` and the raw
    /// `branch_w | branch_v` outputs `[n, 6]`.
    warp: Option<(Vec<T>, Vec<T>)>,
}

impl MlpNet {
    pub fn build(c: &FieldConfig, lb: &mut LayoutBuilder) -> Self {
        let time = TimeEmbedding::build(c.variant, lb);
        let in_dim = c.input_dim();
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
        let x_emb = encode(xyz, 3, XYZ_LEVELS);
        let xd = encoded_dim(3, XYZ_LEVELS);
        let (t_feat, time) = self.time.forward(p, t);
        let h0 = concat_cols(&x_emb, xd, &t_feat, self.in_dim - xd, n);
        let mut inputs: Vec<Vec<T>> = Vec::with_capacity(self.layers.len());
        let mut cur = h0;
        for (i, l) in self.layers.iter().enumerate() {
            // ReLU on each block of rows as it leaves the product.
            let out = l.forward_then(p, &cur, n, &mut [], 0, |_, blk, _| {
                Activation::Relu.apply_block(blk)
            });
            let next = if i == self.skip {
                let first = inputs.first().unwrap_or(&cur);
                concat_cols(first, self.in_dim, &out, self.width, n)
            } else {
                out
            };
            inputs.push(std::mem::replace(&mut cur, next));
        }
        let head_out = Stacked(&self.heads).forward(p, &cur, n);
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
                inputs,
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

    /// 6-DoF: the extra gradient of the canonical positions through the
    /// warp, `(R − I)ᵀ·g` per Gaussian; `None` for the additive field.
    pub fn xyz_vjp<T: Real>(&self, c: &MlpCache<T>, g: &Deformation<T>) -> Option<Vec<T>> {
        let (_, wv) = c.warp.as_ref()?;
        let mut out = vec![T::ZERO; g.d_xyz.len()];
        for ((o, wv), gi) in out
            .chunks_exact_mut(3)
            .zip(wv.chunks_exact(6))
            .zip(g.d_xyz.chunks_exact(3))
        {
            o.copy_from_slice(&se3::warp_xyz_vjp(
                [wv[0], wv[1], wv[2]],
                [wv[3], wv[4], wv[5]],
                [gi[0], gi[1], gi[2]],
            ));
        }
        Some(out)
    }

    pub fn backward<T: Real>(
        &self,
        p: &[T],
        t: &[T],
        c: &MlpCache<T>,
        g: &Deformation<T>,
        gp: &mut [T],
    ) -> Vec<T> {
        let n = t.len();
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = self.in_dim - xd;
        let g_head = match &c.warp {
            None => g.to_head(),
            Some((xyz, wv)) => warp_backward(g, xyz, wv),
        };
        let mut dh = Stacked(&self.heads)
            .backward(p, &c.head_in, &g_head, n, InputGrad::From(0), gp)
            .expect("input gradient requested");
        let mut g_tfeat = vec![T::ZERO; n * td];
        let wcat = self.in_dim + self.width;
        for i in (0..self.layers.len()).rev() {
            if i == self.skip {
                // dh is the gradient of [γ(x), t_feat, h]: keep the t_feat part.
                for (acc, v) in g_tfeat.iter_mut().zip(take_cols(&dh, wcat, xd, td)) {
                    *acc += v;
                }
                dh = take_cols(&dh, wcat, self.in_dim, self.width);
            }
            // ReLU's vjp from the layer's output (see MlpCache::inputs).
            let (out, out_w, c0) = match c.inputs.get(i + 1) {
                None => (&c.head_in, self.width, 0),
                Some(next) if i == self.skip => (next, wcat, self.in_dim),
                Some(next) => (next, self.width, 0),
            };
            relu_backward_from_output(out, out_w, c0, &mut dh, self.width);
            let want = if i == 0 {
                InputGrad::From(xd)
            } else {
                InputGrad::From(0)
            };
            let gin = self.layers[i]
                .backward(p, &c.inputs[i], &dh, n, want, gp)
                .expect("input gradient requested");
            if i == 0 {
                for (acc, v) in g_tfeat.iter_mut().zip(gin) {
                    *acc += v;
                }
                break;
            }
            dh = gin;
        }
        self.time.backward(p, t, &c.time, &g_tfeat, gp)
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

/// vjp of [`warp_forward`]: the gradient of the `[n, 13]` head outputs.
fn warp_backward<T: Real>(g: &Deformation<T>, xyz: &[T], wv: &[T]) -> Vec<T> {
    let n = xyz.len() / 3;
    let mut out = vec![T::ZERO; 13 * n];
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
    }
    out
}
