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
//! The computation is arranged around its shapes:
//! - Every cell's first backbone layer and the skip read the same `u`, so
//!   their `u` columns are one product `[N, |u|]·[|u|, D·U + W]` per pass;
//!   each cell's first layer then continues those sums over its state
//!   columns ([`Input::continuing`]), the same bits as one sum over
//!   `[u; h]` in order. The backward collects the gradients of those outputs
//!   of all cells and of the skip, and computes their weight gradients over
//!   `u` as one product `[D·U + W, N]·[N, |u|]` and their bias gradients as
//!   one column sum (each element its own fixed-order sum, as layer by layer).
//! - Before the first cell the state is zero (unless the skip is added
//!   there, D = 1). A sum over `k` that starts from +0 is never −0 (round to
//!   nearest), so the terms `0·w` of the zero state would add exact zeros:
//!   the first cell's product over the state and its gradients are not run,
//!   with the same bits for finite weights.
//! - The four heads of a cell run as one stacked product `4W` wide, and the
//!   gate, both tanh's and the new state are computed in its epilogue on each
//!   block of rows while it is in cache, which keeps what the backward needs
//!   (tanh(ff1), tanh(ff2), time_a(z) and σ). In the backward, the gate and
//!   update vjp produces the heads' output gradient chunk by chunk inside
//!   the heads' backward ([`OutputGrad::Produced`]), where the weight, bias
//!   and input gradients read each chunk while it is in cache (the `[n, 4W]`
//!   gradient is never stored whole); the backbone layers' activation vjps
//!   are produced the same way. tanh and sigmoid are [`fastmath`]'s
//!   (vectorised in f32).
//!
//! Every product and element-wise pass is timed by [`profile`] when it is on
//! (`liquid-splat bench deform`).

use super::activation::Activation;
use super::encoding::{encode, encoded_dim};
use super::linear::{Epilogue, Input, InputGrad, OutputGrad};
use super::profile;
use super::{
    CfcConfig, Deformation, Init, LayoutBuilder, LinearParams, Stacked, TimeEmbedding,
    TimeEmbeddingSaved, XYZ_LEVELS,
};
use crate::kernels::fastmath::{self, multiversion};
use crate::kernels::matmul::{column_sums, matmul, matmul_tn, MatRef};
use crate::kernels::vec_written_by;
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
    time: TimeEmbeddingSaved<T>,
    /// `u = [γ(x) | t_feat]` `[n, |u|]`.
    u: Vec<T>,
    cells: Vec<CellCache<T>>,
    head_in: Vec<T>,
}

impl CfcNet {
    pub fn build(c: &CfcConfig, lb: &mut LayoutBuilder) -> Self {
        let time = TimeEmbedding::build(c.variant, lb);
        let u_dim = c.variant.input_dim();
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

    /// Rows of the wide product over `u`: every cell's first backbone
    /// layer (`units` rows each, cell by cell), then the skip (`W` rows).
    fn wide_rows(&self) -> usize {
        self.cells.len() * self.units() + self.width
    }

    fn units(&self) -> usize {
        self.cells[0].backbone[0].shape.out_dim
    }

    /// The weights of the wide product over `u`, `[wide_rows, |u|]`: the
    /// `u` columns of every cell's first backbone layer, then the skip's.
    fn wide_weight<T: Real>(&self, p: &[T]) -> Vec<T> {
        let ud = self.u_dim;
        let mut out = Vec::with_capacity(self.wide_rows() * ud);
        for cell in &self.cells {
            let lin = &cell.backbone[0];
            for row in lin.weight(p).chunks_exact(lin.shape.in_dim) {
                out.extend_from_slice(&row[..ud]);
            }
        }
        out.extend_from_slice(self.skip.weight(p));
        out
    }

    /// Whether cell `l`'s first layer reads a state that may be non-zero:
    /// before the first cell the state is zero unless the skip is added
    /// there, and its terms `0·w` would add exact zeros (see the module
    /// docs), so that part of the product and its gradients are not run.
    fn reads_state(&self, l: usize) -> bool {
        l > 0 || self.skip_at == 0
    }

    pub fn forward<T: Real>(&self, p: &[T], xyz: &[T], t: &[T]) -> (Deformation<T>, CfcCache<T>) {
        let n = t.len();
        let (w, ud, units) = (self.width, self.u_dim, self.units());
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = ud - xd;
        let x_emb = profile::elementwise(
            || "γ(x) encoding".into(),
            n,
            xd,
            || encode(xyz, 3, XYZ_LEVELS),
        );
        let (t_feat, time) = profile::layer(|| "timenet".into(), || self.time.forward(p, t));
        // u = [γ(x) | t_feat], one row per Gaussian.
        let u = profile::elementwise(
            || "u = [γ(x) | t_feat] (copy)".into(),
            n,
            ud,
            || concat_columns(&x_emb, xd, &t_feat, td, n),
        );
        drop((x_emb, t_feat));
        // Every cell's first layer and the skip see the same u: their u
        // parts are one product [n, |u|]·[|u|, D·units + W]. Each cell's
        // first layer then continues these sums over its state columns
        // (the same bits as one sum over [u; h]).
        let wide_n = self.wide_rows();
        let wide_w = self.wide_weight(p);
        let pu = profile::layer(
            || "u part of every cell's backbone.0 and of the skip".into(),
            || {
                profile::product(
                    || "u·Wᵤᵀ".into(),
                    n,
                    ud,
                    wide_n,
                    || {
                        matmul(
                            MatRef::row_major(&u, n, ud),
                            MatRef::row_major(&wide_w, wide_n, ud).t(),
                        )
                    },
                )
            },
        );
        let pum = MatRef::row_major(&pu, n, wide_n);
        let mut h = vec![T::ZERO; n * w];
        let mut cells = Vec::with_capacity(self.cells.len());
        for l in 0..self.cells.len() {
            if l == self.skip_at {
                // h += skip(u), the skip's sums plus its bias (added after
                // the sum, as in every linear layer).
                let (bias, s0) = (self.skip.bias(p), self.cells.len() * units);
                profile::elementwise(
                    || "skip: h += (u·Wᵀ + b)".into(),
                    n,
                    w,
                    || {
                        h.par_chunks_mut((ROWS_PER_TASK * w).max(1))
                            .enumerate()
                            .for_each(|(blk, hb)| {
                                let r0 = blk * ROWS_PER_TASK;
                                for (r, hr) in hb.chunks_exact_mut(w).enumerate() {
                                    let o = (r0 + r) * wide_n + s0;
                                    let sr = &pu[o..o + w];
                                    for ((hv, &sv), &b) in hr.iter_mut().zip(sr).zip(bias) {
                                        *hv += sv + b;
                                    }
                                }
                            })
                    },
                );
            }
            let cc = profile::layer(
                || format!("cell {l}"),
                || self.cell_forward(p, l, pum.cols(l * units, units), h, t, n),
            );
            h = cc.1;
            cells.push(cc.0);
        }
        let out = profile::layer(
            || "head".into(),
            || {
                self.head
                    .linear(p)
                    .forward(Input::blocks(&[(&h, w)]), n, Epilogue::none())
            },
        );
        (
            Deformation::from_head(&out),
            CfcCache {
                time,
                u,
                cells,
                head_in: h,
            },
        )
    }

    /// One cell's forward from the sums of its first layer over `u`
    /// (`pu`, `[n, units]`) and the state `h` entering it; returns its cache
    /// and the new state.
    fn cell_forward<T: Real>(
        &self,
        p: &[T],
        l: usize,
        pu: MatRef<'_, T>,
        h: Vec<T>,
        t: &[T],
        n: usize,
    ) -> (CellCache<T>, Vec<T>) {
        let (w, ud) = (self.width, self.u_dim);
        let cell = &self.cells[l];
        let mut inputs = Vec::with_capacity(cell.backbone.len() - 1);
        let mut pres = Vec::with_capacity(cell.backbone.len());
        let mut cur: Vec<T> = Vec::new();
        for (j, lin) in cell.backbone.iter().enumerate() {
            // The activation on each block of rows as it leaves the product,
            // written into `out` (which is never zeroed: every value is
            // written once).
            let units = lin.shape.out_dim;
            let act = self.act;
            let apply = |_: usize, blk: &mut [T], ob: &mut [MaybeUninit<T>]| {
                act.apply_block_uninit(blk, ob)
            };
            let mut pre = Vec::new();
            let out = vec_written_by(n * units, |ob| {
                pre = if j == 0 {
                    // The u sums continued over the state columns (none before
                    // the first cell, see reads_state), then the bias and the
                    // activation.
                    let k = if self.reads_state(l) { w } else { 0 };
                    profile::layer(
                        || format!("backbone.0, u sums continued, {} in the epilogue", self.act),
                        || {
                            lin.linear(p).forward(
                                Input::continuing(pu, ud, &[(&h, k)]),
                                n,
                                Epilogue::none().then(ob, units, &apply),
                            )
                        },
                    )
                } else {
                    profile::layer(
                        || format!("backbone.{j}, {} in the epilogue", self.act),
                        || {
                            lin.linear(p).forward(
                                Input::blocks(&[(&cur, lin.shape.in_dim)]),
                                n,
                                Epilogue::none().then(ob, units, &apply),
                            )
                        },
                    )
                };
                // SAFETY: the epilogue ran once on every block of rows and wrote
                // every value of its rows of `ob`.
                unsafe { &mut *(ob as *mut [MaybeUninit<T>] as *mut [T]) }
            });
            let prev = std::mem::replace(&mut cur, out);
            if j > 0 {
                inputs.push(prev);
            }
            pres.push(pre);
        }
        let z = cur;
        // The four heads as one product 4W wide, then the fused cell pass on
        // each block of rows while it is in cache, writing the new state
        // (never zeroed).
        let pass = |r0: usize, g: &mut [T], hb: &mut [MaybeUninit<T>]| {
            let rows = hb.len() / w;
            cell_forward_rows(g, hb, &t[r0..r0 + rows], w)
        };
        let mut gate = Vec::new();
        let h_next = vec_written_by(n * w, |hb| {
            gate = profile::layer(
                || "heads ff1|ff2|time_a|time_b, gate and update in the epilogue".into(),
                || {
                    Stacked(&cell.heads).linear(p).forward(
                        Input::blocks(&[(&z, cell.heads[0].shape.in_dim)]),
                        n,
                        Epilogue::none().then(hb, w, &pass),
                    )
                },
            );
            // SAFETY: the cell pass wrote every value of every block of rows.
            unsafe { &mut *(hb as *mut [MaybeUninit<T>] as *mut [T]) }
        });
        (
            CellCache {
                h_in: h,
                inputs,
                pres,
                z,
                gate,
            },
            h_next,
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
        let (w, ud, units) = (self.width, self.u_dim, self.units());
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = ud - xd;
        let mut dh = profile::layer(
            || "head".into(),
            || {
                let mut r = self.head.linear(p).backward(
                    &[(&c.head_in, w)],
                    OutputGrad::Given(&g.to_head()),
                    n,
                    InputGrad::From(0),
                );
                self.head.store(&r, gp);
                r.take_input(0)
            },
        )
        .expect("input gradient requested");
        // The gradients of the wide product's outputs (each cell's first
        // layer, then the skip), for its weight and bias gradients at the end.
        let wide_n = self.wide_rows();
        let mut gu = vec![T::ZERO; n * wide_n];
        let mut g_tfeat = vec![T::ZERO; n * td];
        let mut gate_dt = vec![T::ZERO; n];
        for l in (0..self.cells.len()).rev() {
            let (cell, cc) = (&self.cells[l], &c.cells[l]);
            profile::layer(
                || format!("cell {l}"),
                || {
                    // The gate and update vjp produces the heads' output
                    // gradient chunk by chunk, read there by the heads'
                    // weight, bias and input gradients while in cache.
                    let produce = |r0: usize, chunk: &mut [T], dt: &mut [T]| {
                        let rows = dt.len();
                        let mut prod = vec![T::ZERO; w];
                        cell_backward_rows(
                            chunk,
                            &cc.gate[r0 * 4 * w..(r0 + rows) * 4 * w],
                            &dh[r0 * w..(r0 + rows) * w],
                            &t[r0..r0 + rows],
                            dt,
                            &mut prod,
                            w,
                        )
                    };
                    let mut dz = profile::layer(
                        || "heads ff1|ff2|time_a|time_b, gate and update vjp producing G".into(),
                        || {
                            let heads = Stacked(&cell.heads);
                            let mut r = heads.linear(p).backward(
                                &[(&cc.z, units)],
                                OutputGrad::Produced {
                                    produce: &produce,
                                    side: &mut gate_dt,
                                    side_w: 1,
                                },
                                n,
                                InputGrad::From(0),
                            );
                            heads.store(&r, gp);
                            r.take_input(0)
                        },
                    )
                    .expect("input gradient requested");
                    for j in (1..cell.backbone.len()).rev() {
                        // The activation's vjp produces the layer's output
                        // gradient chunk by chunk inside its backward.
                        let (pre, g_out, act) = (&cc.pres[j], &dz, self.act);
                        let produce = |r0: usize, chunk: &mut [T], _: &mut [T]| {
                            let rows = chunk.len() / units;
                            chunk.copy_from_slice(&g_out[r0 * units..(r0 + rows) * units]);
                            act.backward_block(&pre[r0 * units..(r0 + rows) * units], chunk)
                        };
                        let lin = &cell.backbone[j];
                        let next = profile::layer(
                            || format!("backbone.{j}, {} vjp producing G", self.act),
                            || {
                                let mut r = lin.linear(p).backward(
                                    &[(&cc.inputs[j - 1], units)],
                                    OutputGrad::Produced {
                                        produce: &produce,
                                        side: &mut [],
                                        side_w: 0,
                                    },
                                    n,
                                    InputGrad::From(0),
                                );
                                lin.store(&r, gp);
                                r.take_input(0)
                            },
                        );
                        dz = next.expect("input gradient requested");
                    }
                    // The first layer's input is [γ(x) | t_feat | h]: γ(x) is
                    // stop-gradient; t_feat's gradient is collected, h's
                    // flows on. Its weight gradient over u and its bias
                    // gradient come from the wide product at the end.
                    profile::layer(
                        || "backbone.0".into(),
                        || {
                            let lin = &cell.backbone[0];
                            let in_dim = lin.shape.in_dim;
                            profile::elementwise(
                                || format!("{} vjp, into the wide gradient", self.act),
                                n,
                                units,
                                || {
                                    self.act.backward_in_place(&cc.pres[0], &mut dz);
                                    set_columns(&mut gu, wide_n, l * units, &dz, units);
                                },
                            );
                            let gm = MatRef::row_major(&dz, n, units);
                            let wm = MatRef::row_major(lin.weight(p), units, in_dim);
                            if self.reads_state(l) {
                                let wh = profile::product(
                                    || "weight grad Gᵀ·h".into(),
                                    units,
                                    n,
                                    w,
                                    || matmul_tn(gm, MatRef::row_major(&cc.h_in, n, w)),
                                );
                                let wg = &mut gp[lin.w..lin.w + units * in_dim];
                                for (dst, src) in
                                    wg.chunks_exact_mut(in_dim).zip(wh.chunks_exact(w))
                                {
                                    dst[ud..].copy_from_slice(src);
                                }
                            }
                            let g_t = profile::product(
                                || "input grad G·Wₜ".into(),
                                n,
                                units,
                                td,
                                || matmul(gm, wm.cols(xd, td)),
                            );
                            add_into(&mut g_tfeat, &g_t);
                            if self.reads_state(l) {
                                dh = profile::product(
                                    || "input grad G·Wₕ".into(),
                                    n,
                                    units,
                                    w,
                                    || matmul(gm, wm.cols(ud, w)),
                                );
                            }
                        },
                    );
                },
            );
            if l == self.skip_at {
                // h_in = h_prev + skip(u): the same gradient flows to both.
                profile::layer(
                    || "skip".into(),
                    || {
                        set_columns(&mut gu, wide_n, self.cells.len() * units, &dh, w);
                        let wm = MatRef::row_major(self.skip.weight(p), w, ud);
                        let g_t = profile::product(
                            || "input grad G·Wₜ".into(),
                            n,
                            w,
                            td,
                            || matmul(MatRef::row_major(&dh, n, w), wm.cols(xd, td)),
                        );
                        add_into(&mut g_tfeat, &g_t);
                    },
                );
            }
        }
        // The weight and bias gradients of the wide product over u: one
        // product [D·units + W, n]·[n, |u|] and one column sum (each element
        // its own fixed-order sum, as layer by layer).
        profile::layer(
            || "u part of every cell's backbone.0 and of the skip".into(),
            || {
                let wg = profile::product(
                    || "weight grad Gᵀ·u".into(),
                    wide_n,
                    n,
                    ud,
                    || {
                        matmul_tn(
                            MatRef::row_major(&gu, n, wide_n),
                            MatRef::row_major(&c.u, n, ud),
                        )
                    },
                );
                let bg = profile::elementwise(
                    || "bias grad (column sums of G)".into(),
                    n,
                    wide_n,
                    || column_sums(&gu, n, wide_n),
                );
                let mut rows = wg.chunks_exact(ud).zip(&bg);
                for cell in &self.cells {
                    let lin = &cell.backbone[0];
                    let in_dim = lin.shape.in_dim;
                    for (r, (src, &b)) in rows.by_ref().take(units).enumerate() {
                        gp[lin.w + r * in_dim..lin.w + r * in_dim + ud].copy_from_slice(src);
                        gp[lin.b + r] = b;
                    }
                }
                for (r, (src, &b)) in rows.enumerate() {
                    gp[self.skip.w + r * ud..self.skip.w + (r + 1) * ud].copy_from_slice(src);
                    gp[self.skip.b + r] = b;
                }
            },
        );
        let mut gt = profile::layer(
            || "timenet".into(),
            || self.time.backward(p, t, &c.time, &g_tfeat, gp),
        );
        for (a, b) in gt.iter_mut().zip(gate_dt) {
            *a += b;
        }
        gt
    }
}

/// `[a | b]` row by row (`a` `[n, da]`, `b` `[n, db]`).
fn concat_columns<T: Real>(a: &[T], da: usize, b: &[T], db: usize, n: usize) -> Vec<T> {
    let d = da + db;
    let mut out = vec![T::ZERO; n * d];
    out.par_chunks_mut((ROWS_PER_TASK * d).max(1))
        .enumerate()
        .for_each(|(blk, o)| {
            let r0 = blk * ROWS_PER_TASK;
            for (r, row) in o.chunks_exact_mut(d).enumerate() {
                let i = r0 + r;
                row[..da].copy_from_slice(&a[i * da..(i + 1) * da]);
                row[da..].copy_from_slice(&b[i * db..(i + 1) * db]);
            }
        });
    out
}

/// Columns `c0..c0 + d` of the row-major `dst` (`ld` wide) set to `src`
/// `[n, d]`.
fn set_columns<T: Real>(dst: &mut [T], ld: usize, c0: usize, src: &[T], d: usize) {
    if d == 0 || ld == 0 {
        return;
    }
    dst.par_chunks_mut(ROWS_PER_TASK * ld)
        .zip(src.par_chunks(ROWS_PER_TASK * d))
        .for_each(|(o, s)| {
            for (orow, srow) in o.chunks_exact_mut(ld).zip(s.chunks_exact(d)) {
                orow[c0..c0 + d].copy_from_slice(srow);
            }
        });
}

/// `acc += v` element-wise.
fn add_into<T: Real>(acc: &mut [T], v: &[T]) {
    for (a, &b) in acc.iter_mut().zip(v) {
        *a += b;
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

// vjp of `cell_forward_rows` on a block of rows: the gradient of the four
// head outputs `o` (`[rows, 4W]`) given the cell pass's saved values `g`
// (tanh(ff1) | tanh(ff2) | time_a | σ) and the state gradient `dh`
// `[rows, W]`; adds each row's gradient with respect to τ (summed over j in
// order) to `dt`. `prod` is scratch, W long.
multiversion!(fn cell_backward_rows<T: Real>(o: &mut [T], g: &[T], dh: &[T], t: &[T], dt: &mut [T], prod: &mut [T], w: usize) => cell_backward_rows_body);

// The per-row sum for τ runs in its own loop over `prod` (j ascending), so
// the element-wise loop vectorises.
#[inline(always)]
fn cell_backward_rows_body<T: Real>(
    o: &mut [T],
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
            *o1 = da * (T::ONE - a * a);
            *o2 = db * (T::ONE - b * b);
            *o3 = dpre * tau;
            *o4 = dpre;
            *pr = dpre * ta;
        }
        let mut sum = T::ZERO;
        for &p in prod.iter() {
            sum += p;
        }
        *dt += sum;
    }
}
