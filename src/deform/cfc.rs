//! The liquid deformation field: D CfC cells stacked in depth (docs/DECISIONS.md §2).
//!
//! `u = [γ₁₀(x), t_feat]` (93 synthetic, 84 real), `h = 0`. For cell
//! `l = 0..D`: if `l == D/2`, first `h += skip(u)`; then
//! `z = φ([u; h])` with the backbone `φ = Linear(|u|+W, U) → act → (Linear(U, U) → act)…`,
//! and with `τ = t` (the field's time input, per Gaussian):
//! `σ = sigmoid(time_a(z)·τ + time_b(z))`,
//! `h ← tanh(ff1(z))·(1 − σ) + σ·tanh(ff2(z))` (ncps CfCCell, mode "default").
//! Output: `head(h)` = Linear(W, 10) split 3 | 4 | 3.
//!
//! The four heads of a cell run as one stacked product, and the gate, both
//! tanh's and the new state are computed in one fused pass over the `N × W`
//! block, which keeps what the backward needs (tanh(ff1), tanh(ff2),
//! time_a(z) and σ). tanh and sigmoid are [`fastmath`]'s (vectorised in f32).

use super::activation::Activation;
use super::encoding::{encode, encoded_dim};
use super::fastmath::{self, multiversion};
use super::linear::InputGrad;
use super::{
    Deformation, FieldConfig, Init, LayoutBuilder, LinearParams, Stacked, TimeCache, TimeEmbedding,
    XYZ_LEVELS,
};
use crate::math::Real;
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// Rows per parallel task of the fused cell pass (does not affect results).
const ROWS_PER_TASK: usize = 64;

/// One CfC cell's parameter places.
#[derive(Clone, Debug)]
struct Cell {
    backbone: Vec<LinearParams>,
    /// ff1, ff2, time_a, time_b.
    heads: [LinearParams; 4],
}

/// Architecture and parameter places of the CfC field.
#[derive(Clone, Debug)]
pub(crate) struct CfcNet {
    time: TimeEmbedding,
    cells: Vec<Cell>,
    skip: LinearParams,
    head: LinearParams,
    /// The cell before which `skip(u)` is added to the state (D/2).
    skip_at: usize,
    u_dim: usize,
    width: usize,
    act: Activation,
}

struct CellCache<T> {
    /// The state entering the cell (after the skip, at cell D/2): with `u`,
    /// the first backbone layer's input `[u; h]`, read as column blocks
    /// (never concatenated).
    h_in: Vec<T>,
    /// Input of each backbone layer after the first.
    inputs: Vec<Vec<T>>,
    /// Pre-activation of each backbone layer.
    pres: Vec<Vec<T>>,
    /// Backbone output z `[n, U]`.
    z: Vec<T>,
    /// Per row, 4W values: tanh(ff1) | tanh(ff2) | time_a(z) | σ.
    gate: Vec<T>,
}

/// What the CfC field's backward needs.
pub(crate) struct CfcCache<T> {
    time: TimeCache<T>,
    /// The two blocks of `u`: `γ(x)` `[n, 63]` and `t_feat`.
    x_emb: Vec<T>,
    t_feat: Vec<T>,
    cells: Vec<CellCache<T>>,
    head_in: Vec<T>,
}

impl CfcNet {
    pub fn build(c: &FieldConfig, lb: &mut LayoutBuilder) -> Self {
        let time = TimeEmbedding::build(c.variant, lb);
        let u_dim = c.input_dim();
        let (w, units) = (c.width, c.backbone_units);
        let mut cells = Vec::with_capacity(c.depth);
        for l in 0..c.depth {
            let mut backbone = Vec::with_capacity(c.backbone_layers);
            for j in 0..c.backbone_layers {
                let fan_in = if j == 0 { u_dim + w } else { units };
                backbone.push(lb.linear(
                    &format!("cells.{l}.backbone.{}", 2 * j),
                    fan_in,
                    units,
                    Init::Xavier,
                ));
            }
            let heads = ["ff1", "ff2", "time_a", "time_b"]
                .map(|h| lb.linear(&format!("cells.{l}.{h}"), units, w, Init::Xavier));
            cells.push(Cell { backbone, heads });
        }
        let skip = lb.linear("skip", u_dim, w, Init::TorchDefault);
        let head = lb.linear("head", w, 10, Init::TorchDefault);
        CfcNet {
            time,
            cells,
            skip,
            head,
            skip_at: c.depth / 2,
            u_dim,
            width: w,
            act: c.activation,
        }
    }

    pub fn forward<T: Real>(&self, p: &[T], xyz: &[T], t: &[T]) -> (Deformation<T>, CfcCache<T>) {
        let n = t.len();
        let w = self.width;
        let xd = encoded_dim(3, XYZ_LEVELS);
        let x_emb = encode(xyz, 3, XYZ_LEVELS);
        let (t_feat, time) = self.time.forward(p, t);
        let td = self.u_dim - xd;
        let mut h = vec![T::ZERO; n * w];
        let mut cells = Vec::with_capacity(self.cells.len());
        for (l, cell) in self.cells.iter().enumerate() {
            let u = [(&x_emb[..], xd), (&t_feat[..], td)];
            if l == self.skip_at {
                let s = self
                    .skip
                    .forward_parts_then::<T, T, _>(p, &u, n, &mut [], 0, |_, _, _| {});
                let step = (ROWS_PER_TASK * w).max(1);
                h.par_chunks_mut(step)
                    .zip(s.par_chunks(step))
                    .for_each(|(hb, sb)| {
                        for (hv, &sv) in hb.iter_mut().zip(sb) {
                            *hv += sv;
                        }
                    });
            }
            let mut inputs = Vec::with_capacity(cell.backbone.len() - 1);
            let mut pres = Vec::with_capacity(cell.backbone.len());
            let mut cur: Vec<T> = Vec::new();
            for (j, lin) in cell.backbone.iter().enumerate() {
                // The activation on each block of rows as it leaves the
                // product, written into `out` (which is never zeroed: every
                // value is written once). The first layer reads [u; h] as
                // column blocks.
                let units = lin.shape.out_dim;
                let mut out: Vec<T> = Vec::with_capacity(n * units);
                let ob = &mut out.spare_capacity_mut()[..n * units];
                let act = |_: usize, blk: &mut [T], ob: &mut [MaybeUninit<T>]| {
                    self.act.apply_block_uninit(blk, ob)
                };
                let pre = if j == 0 {
                    let xs = [u[0], u[1], (&h[..], w)];
                    lin.forward_parts_then(p, &xs, n, ob, units, act)
                } else {
                    lin.forward_then(p, &cur, n, ob, units, act)
                };
                // SAFETY: the epilogue ran once on every block of rows and
                // wrote every value of its rows of `out`.
                unsafe { out.set_len(n * units) };
                let prev = std::mem::replace(&mut cur, out);
                if j > 0 {
                    inputs.push(prev);
                }
                pres.push(pre);
            }
            let z = cur;
            // The four heads, then the fused cell pass on each block of rows
            // while it is in cache, writing the new state (never zeroed).
            let mut h_next: Vec<T> = Vec::with_capacity(n * w);
            let hb = &mut h_next.spare_capacity_mut()[..n * w];
            let gate = Stacked(&cell.heads).forward_then(p, &z, n, hb, w, |r0, g, hb| {
                let rows = hb.len() / w;
                cell_forward_rows(g, hb, &t[r0..r0 + rows], w)
            });
            // SAFETY: the cell pass wrote every value of every block of rows.
            unsafe { h_next.set_len(n * w) };
            cells.push(CellCache {
                h_in: std::mem::replace(&mut h, h_next),
                inputs,
                pres,
                z,
                gate,
            });
        }
        let out = self.head.forward(p, &h, n);
        (
            Deformation::from_head(&out),
            CfcCache {
                time,
                x_emb,
                t_feat,
                cells,
                head_in: h,
            },
        )
    }

    pub fn backward<T: Real>(
        &self,
        p: &[T],
        t: &[T],
        c: &CfcCache<T>,
        g: &Deformation<T>,
        gp: &mut [T],
    ) -> Vec<T> {
        let n = t.len();
        let w = self.width;
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = self.u_dim - xd;
        let mut dh = self
            .head
            .backward(p, &c.head_in, &g.to_head(), n, InputGrad::From(0), gp)
            .expect("input gradient requested");
        let mut g_tfeat = vec![T::ZERO; n * td];
        let mut gate_dt = vec![T::ZERO; n];
        for l in (0..self.cells.len()).rev() {
            let (cell, cc) = (&self.cells[l], &c.cells[l]);
            let g_heads = cell_backward_fused(&cc.gate, &dh, t, w, &mut gate_dt);
            let mut dz = Stacked(&cell.heads)
                .backward(p, &cc.z, &g_heads, n, InputGrad::From(0), gp)
                .expect("input gradient requested");
            let u = [(&c.x_emb[..], xd), (&c.t_feat[..], td)];
            for j in (0..cell.backbone.len()).rev() {
                self.act.backward_in_place(&cc.pres[j], &mut dz);
                if j > 0 {
                    dz = cell.backbone[j]
                        .backward(p, &cc.inputs[j - 1], &dz, n, InputGrad::From(0), gp)
                        .expect("input gradient requested");
                    continue;
                }
                // The first layer's input is [γ(x) | t_feat | h]: γ(x) is
                // stop-gradient; t_feat's gradient is collected, h's flows on.
                let xs = [u[0], u[1], (&cc.h_in[..], w)];
                let mut gin =
                    cell.backbone[0].backward_parts(p, &xs, &dz, n, InputGrad::From(xd), gp);
                let g_t = gin[1].take().expect("input gradient requested");
                for (acc, v) in g_tfeat.iter_mut().zip(g_t) {
                    *acc += v;
                }
                dh = gin[2].take().expect("input gradient requested");
            }
            if l == self.skip_at {
                // h_in = h_prev + skip(u): the same gradient flows to both.
                let mut gs = self
                    .skip
                    .backward_parts(p, &u, &dh, n, InputGrad::From(xd), gp);
                let g_t = gs[1].take().expect("input gradient requested");
                for (acc, v) in g_tfeat.iter_mut().zip(g_t) {
                    *acc += v;
                }
            }
        }
        let mut gt = self.time.backward(p, t, &c.time, &g_tfeat, gp);
        for (a, b) in gt.iter_mut().zip(gate_dt) {
            *a += b;
        }
        gt
    }
}

// The fused element-wise pass of a cell on a block of rows. `g` holds the
// four head outputs per row (ff1 | ff2 | time_a | time_b, each W wide) on
// entry and tanh(ff1) | tanh(ff2) | time_a | σ on exit; `h` receives the new
// state; `t` is τ per row.
multiversion!(fn cell_forward_rows<T: Real>(g: &mut [T], h: &mut [MaybeUninit<T>], t: &[T], w: usize) => cell_forward_rows_body);

#[inline(always)]
fn cell_forward_rows_body<T: Real>(g: &mut [T], h: &mut [MaybeUninit<T>], t: &[T], w: usize) {
    // Four simple loops per row (each a zip of at most four slices, which
    // the compiler vectorises; one loop with five streams it would not).
    // The row stays in L1 between them; the arithmetic per element is the
    // same as one fused loop.
    for ((g, h), &tau) in g.chunks_exact_mut(4 * w).zip(h.chunks_exact_mut(w)).zip(t) {
        let (f1, rest) = g.split_at_mut(w);
        let (f2, rest) = rest.split_at_mut(w);
        let (ta, tb) = rest.split_at_mut(w);
        for v in f1.iter_mut() {
            *v = fastmath::tanh(*v);
        }
        for v in f2.iter_mut() {
            *v = fastmath::tanh(*v);
        }
        for (s, &a) in tb.iter_mut().zip(ta.iter()) {
            *s = a * tau + *s;
        }
        for s in tb.iter_mut() {
            *s = fastmath::sigmoid(*s);
        }
        for (((h, &a), &b), &s) in h.iter_mut().zip(f1.iter()).zip(f2.iter()).zip(tb.iter()) {
            h.write(a * (T::ONE - s) + s * b);
        }
    }
}

/// vjp of [`cell_forward_rows`]: the gradient of the four head outputs
/// `[n, 4W]` given the state gradient `dh` `[n, W]`; adds each row's
/// gradient with respect to τ (summed over j in order) to `dt`.
fn cell_backward_fused<T: Real>(gate: &[T], dh: &[T], t: &[T], w: usize, dt: &mut [T]) -> Vec<T> {
    // Every value is written once below (never zeroed first).
    let mut out: Vec<T> = Vec::with_capacity(gate.len());
    out.spare_capacity_mut()[..gate.len()]
        .par_chunks_mut(4 * w * ROWS_PER_TASK)
        .zip(gate.par_chunks(4 * w * ROWS_PER_TASK))
        .zip(dh.par_chunks(w * ROWS_PER_TASK))
        .zip(t.par_chunks(ROWS_PER_TASK))
        .zip(dt.par_chunks_mut(ROWS_PER_TASK))
        .for_each(|((((o, g), dh), t), dt)| {
            let mut prod = vec![T::ZERO; w];
            cell_backward_rows(o, g, dh, t, dt, &mut prod, w)
        });
    // SAFETY: cell_backward_rows wrote all 4W values of every row.
    unsafe { out.set_len(gate.len()) };
    out
}

multiversion!(fn cell_backward_rows<T: Real>(o: &mut [MaybeUninit<T>], g: &[T], dh: &[T], t: &[T], dt: &mut [T], prod: &mut [T], w: usize) => cell_backward_rows_body);

/// Rows of [`cell_backward_fused`]. The per-row sum for τ runs in its own
/// loop over `prod` (j ascending), so the element-wise loop vectorises.
#[inline(always)]
fn cell_backward_rows_body<T: Real>(
    o: &mut [MaybeUninit<T>],
    g: &[T],
    dh: &[T],
    t: &[T],
    dt: &mut [T],
    prod: &mut [T],
    w: usize,
) {
    for ((((o, g), dh), &tau), dt) in o
        .chunks_exact_mut(4 * w)
        .zip(g.chunks_exact(4 * w))
        .zip(dh.chunks_exact(w))
        .zip(t)
        .zip(dt.iter_mut())
    {
        let (o1, rest) = o.split_at_mut(w);
        let (o2, rest) = rest.split_at_mut(w);
        let (o3, o4) = rest.split_at_mut(w);
        let (ga, rest) = g.split_at(w);
        let (gb, rest) = rest.split_at(w);
        let (gta, gs) = rest.split_at(w);
        for (((((((((o1, o2), o3), o4), &a), &b), &ta), &s), &gh), pr) in o1
            .iter_mut()
            .zip(o2.iter_mut())
            .zip(o3.iter_mut())
            .zip(o4.iter_mut())
            .zip(ga)
            .zip(gb)
            .zip(gta)
            .zip(gs)
            .zip(dh)
            .zip(prod.iter_mut())
        {
            let da = gh * (T::ONE - s);
            let db = gh * s;
            let ds = gh * (b - a);
            let dpre = ds * (s * (T::ONE - s));
            o1.write(da * (T::ONE - a * a));
            o2.write(db * (T::ONE - b * b));
            o3.write(dpre * tau);
            o4.write(dpre);
            *pr = dpre * ta;
        }
        let mut sum = T::ZERO;
        for &p in prod.iter() {
            sum += p;
        }
        *dt += sum;
    }
}
