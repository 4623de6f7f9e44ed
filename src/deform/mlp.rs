//! The D-3DGS `DeformNetwork` (UPSTREAM §6.2), exactly.
//!
//! `h₀ = [γ₁₀(x), t_feat]` (93 or 84 wide); for `k = 0..D`:
//! `h = ReLU(linear[k](h))`, and after layer `D/2` the input is concatenated
//! in front: `h = [γ₁₀(x), t_feat, h]`, so `linear[D/2 + 1]` takes `W + in`.
//! Three heads on the last `h`: `gaussian_warp` (3), `gaussian_rotation` (4),
//! `gaussian_scaling` (3), no output activation.

use super::activation::Activation;
use super::encoding::{encode, encoded_dim};
use super::linear::InputGrad;
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
    /// Heads in output order: warp, rotation, scaling.
    heads: [LinearParams; 3],
    /// The layer after which the input is concatenated (D/2).
    skip: usize,
    in_dim: usize,
    width: usize,
}

/// What the MLP's backward needs.
pub(crate) struct MlpCache<T> {
    time: TimeCache<T>,
    /// Input of each trunk layer (`inputs[0]` = h₀).
    inputs: Vec<Vec<T>>,
    /// Pre-activation of each trunk layer.
    pres: Vec<Vec<T>>,
    /// Input of the heads `[n, W]`.
    head_in: Vec<T>,
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
        let heads = [
            lb.linear("gaussian_warp", w, 3, Init::TorchDefault),
            lb.linear("gaussian_rotation", w, 4, Init::TorchDefault),
            lb.linear("gaussian_scaling", w, 3, Init::TorchDefault),
        ];
        MlpNet {
            time,
            layers,
            heads,
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
        let mut pres = Vec::with_capacity(self.layers.len());
        let mut cur = h0;
        for (i, l) in self.layers.iter().enumerate() {
            let pre = l.forward(p, &cur, n);
            let out = Activation::Relu.forward(&pre);
            let next = if i == self.skip {
                concat_cols(&inputs[0], self.in_dim, &out, self.width, n)
            } else {
                out
            };
            inputs.push(std::mem::replace(&mut cur, next));
            pres.push(pre);
        }
        let head_out = Stacked(&self.heads).forward(p, &cur, n);
        (
            Deformation::from_head(&head_out),
            MlpCache {
                time,
                inputs,
                pres,
                head_in: cur,
            },
        )
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
        let g_head = g.to_head();
        let mut dh = Stacked(&self.heads)
            .backward(p, &c.head_in, &g_head, n, InputGrad::From(0), gp)
            .expect("input gradient requested");
        let mut g_tfeat = vec![T::ZERO; n * td];
        for i in (0..self.layers.len()).rev() {
            if i == self.skip {
                // dh is the gradient of [γ(x), t_feat, h]: keep the t_feat part.
                let wcat = self.in_dim + self.width;
                for (acc, v) in g_tfeat.iter_mut().zip(take_cols(&dh, wcat, xd, td)) {
                    *acc += v;
                }
                dh = take_cols(&dh, wcat, self.in_dim, self.width);
            }
            Activation::Relu.backward_in_place(&c.pres[i], &mut dh);
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
