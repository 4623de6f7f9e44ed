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
//! **The time heads are merged.** `time_a(z)·τ + time_b(z)` is one linear
//! layer of `z` for a given τ: weight `τ·W_a + W_b` and bias `τ·b_a + b_b`
//! (each value rounded after the product and after the sum). The field
//! evaluates it so, as one head W wide instead of two: every Gaussian of a
//! frame has the same τ, and the heads are a quarter narrower (3W instead
//! of 4W) forward and in the backward's products. Rows are taken in runs of
//! equal τ (bit for bit), each with its own merged layer (built once per
//! pass for the first row's τ, per run for any other), so a row's values
//! depend on its own inputs only, never on the other rows of the batch. The
//! backward recomputes `time_a(z)` for the gradient with respect to τ; the
//! weight gradient of `time_a` is τ times that of `time_b` when every row has
//! the same τ (one product fewer), else its own product.
//!
//! The computation is arranged around its shapes and the memory it moves:
//! - The forward runs every cell on a block of rows (`FORWARD_ROWS`) after
//!   the other while the block is in cache: per cell, the first backbone
//!   layer's sums over `u`, continued over the state columns (the same bits
//!   as one sum over `[u; h]` in order), the bias and activation, the later
//!   backbone layers, the three heads as one stacked product `3W` wide, then
//!   the gate, both tanh's and the new state. Only what the backward needs
//!   is written out: each backbone layer's pre-activation, the state entering
//!   each cell, and per row tanh(ff1) | tanh(ff2) | σ. The
//!   activations' outputs are recomputed from the pre-activations in the
//!   backward (the same function of the same values: the same bits).
//! - The backward runs every cell, last first, on a chunk of
//!   [`REDUCTION_CHUNK`] rows after the other, with the state's gradient, the
//!   heads' output gradient and each layer's output gradient kept in cache
//!   (never stored whole). The weight and bias gradients are partial sums per
//!   chunk, added in chunk order at the end: the chunks and the order of
//!   [`matmul_tn`] and [`column_sums`] over all rows, so every element has the
//!   bits of the layer-by-layer backward over all rows.
//! - Before the first cell the state is zero (unless the skip is added
//!   there, D = 1). A sum over `k` that starts from +0 is never −0 (round to
//!   nearest), so the terms `0·w` of the zero state would add exact zeros:
//!   the first cell's product over the state and its gradients are not run,
//!   with the same bits for finite weights.
//! - tanh and sigmoid are [`fastmath`]'s (vectorised in f32).
//!
//! Every product and element-wise pass is timed by [`profile`] when it is on
//! (`liquid-splat bench deform`); inside the fused passes, as CPU time
//! summed over the threads ([`Tally`]).

use super::activation::Activation;
use super::encoding::{encode_then, encoded_dim};
use super::linear::{InputGrad, Linear, OutputGrad, PackedLinear};
use super::profile::{self, Tally};
use super::time::{equal_runs, same};
use super::{
    CfcConfig, Deformation, Init, LayoutBuilder, LinearParams, TimeEmbedding, TimeEmbeddingSaved,
    XYZ_LEVELS,
};
use crate::kernels::as_slots;
use crate::kernels::fastmath::{self, multiversion};
use crate::kernels::matmul::{
    column_sums, matmul_block_into, matmul_block_resume, matmul_tn, pack, pack_axpy, pack_pair,
    MatRef, Packed, REDUCTION_CHUNK,
};
use crate::math::Real;
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// Rows per block of the forward, which runs every cell on a block of rows
/// after the other (does not affect results).
const FORWARD_ROWS: usize = 96;

/// The operations of the forward timed by the profile, in the order of
/// [`CfcNet::forward_ops`].
#[derive(Clone, Copy)]
enum FwdOp {
    Skip,
    UPart,
    HPart,
    Later,
    Act,
    Heads,
    Gate,
    Head,
}

/// The operations of the backward timed by the profile, in the order of
/// [`CfcNet::backward_ops`].
#[derive(Clone, Copy)]
enum BwdOp {
    Act,
    TimeA,
    Gate,
    HeadsWeight,
    TimeAWeight,
    HeadsInput,
    ActVjp,
    LaterWeight,
    LaterInput,
    UWeight,
    HWeight,
    TInput,
    HInput,
    Skip,
    Wide,
}

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

/// What one cell's backward needs from its forward. The activations'
/// outputs and the heads are recomputed from these, chunk by chunk, in the
/// backward (see the module docs).
struct CellCache<T> {
    /// The state entering the cell (after the skip, at cell D/2), `[n, W]`;
    /// empty for a cell that reads no state ([`CfcNet::reads_state`]).
    h_in: Vec<T>,
    /// Pre-activation of each backbone layer, `[n, U]`.
    pres: Vec<Vec<T>>,
    /// Per row, 3W values: tanh(ff1) | tanh(ff2) | σ.
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

/// One cell's weights packed for the forward's blocks of rows.
struct CellForward<'p, T> {
    /// backbone.0's `u` columns, `Wᵀ` `[|u|, U]`.
    u_part: Packed<T>,
    /// backbone.0's state columns, `Wᵀ` `[W, U]`.
    h_part: Packed<T>,
    /// backbone.0's bias (added after the sums over both).
    bias0: &'p [T],
    /// The backbone layers after the first.
    later: Vec<PackedLinear<T>>,
    /// ff1 | ff2 | time(τ₀) as one layer `3W` wide ([`merged_heads`]).
    heads: PackedLinear<T>,
    /// For runs of rows with another τ (`None` when every row has τ₀):
    /// time_a's and time_b's `Wᵀ` `[U, W]`, packed, and their biases.
    time: Option<TimePair<'p, T>>,
}

/// time_a and time_b packed apart, to merge them for a τ other than τ₀
/// ([`pack_axpy`]: no packing again); the weights are `Wᵀ` in the forward
/// (`z·Wᵀ`) and `W` in the backward (`G·W`).
struct TimePair<'p, T> {
    a: Packed<T>,
    b: Packed<T>,
    bias_a: &'p [T],
    bias_b: &'p [T],
}

impl<'p, T: Real> TimePair<'p, T> {
    /// From time_a's and time_b's weights packed together, and the biases
    /// of the heads (ff1, ff2, time_a, time_b) in `p`.
    fn new((a, b): (Packed<T>, Packed<T>), heads: &[LinearParams; 4], p: &'p [T]) -> Self {
        TimePair {
            a,
            b,
            bias_a: heads[2].bias(p),
            bias_b: heads[3].bias(p),
        }
    }

    /// The merged time head's weights for `tau`, packed.
    fn weights(&self, tau: T) -> Packed<T> {
        pack_axpy(tau, &self.a, &self.b)
    }

    /// The merged time head's bias for `tau`.
    fn bias(&self, tau: T) -> Vec<T> {
        self.bias_a
            .iter()
            .zip(self.bias_b)
            .map(|(&a, &b)| tau * a + b)
            .collect()
    }
}

/// The field's weights packed for the forward.
struct ForwardWeights<'p, T> {
    cells: Vec<CellForward<'p, T>>,
    /// The τ the packed heads are merged for (the first row's).
    tau0: T,
    skip: PackedLinear<T>,
    head: PackedLinear<T>,
}

/// One cell's weights packed for the backward's chunks.
struct CellBackward<'p, T> {
    /// `W` of the stacked heads merged for τ₀ `[3W, U]`, for their input
    /// gradient.
    heads: Packed<T>,
    /// time_a, to recompute `time_a(z)` for the τ gradient.
    time_a: PackedLinear<T>,
    /// For runs of rows with another τ (`None` when every row has τ₀): `W`
    /// of ff1 | ff2 `[2W, U]`, and time_a and time_b packed apart.
    other_tau: Option<(Packed<T>, TimePair<'p, T>)>,
    /// `W` of each backbone layer after the first `[U, U]`.
    later: Vec<Packed<T>>,
    /// backbone.0's `t_feat` columns `[U, |t_feat|]` and state columns `[U, W]`.
    t_part: Packed<T>,
    h_part: Packed<T>,
}

/// The field's weights packed for the backward.
struct BackwardWeights<'p, T> {
    cells: Vec<CellBackward<'p, T>>,
    /// τ₀ (as in [`ForwardWeights`]).
    tau0: T,
    /// The skip's `t_feat` columns `[W, |t_feat|]`.
    skip_t: Packed<T>,
}

/// One block of rows of the forward, with its rows of every saved array
/// (uninitialised until the block is run).
struct ForwardTask<'o, T> {
    r0: usize,
    rows: usize,
    /// Cell by cell, layer by layer.
    pres: Vec<&'o mut [MaybeUninit<T>]>,
    /// Per cell (empty where the cell reads no state).
    h_in: Vec<&'o mut [MaybeUninit<T>]>,
    /// Per cell.
    gates: Vec<&'o mut [MaybeUninit<T>]>,
    head_in: &'o mut [MaybeUninit<T>],
    out: &'o mut [MaybeUninit<T>],
}

/// One chunk of rows of the backward with its rows of the outputs.
struct BackwardTask<'o, T> {
    r0: usize,
    rows: usize,
    g_tfeat: &'o mut [MaybeUninit<T>],
    dt: &'o mut [MaybeUninit<T>],
}

/// A chunk's partial weight and bias gradients: per cell the stacked heads
/// (weight, bias), each backbone layer after the first (weight, bias),
/// backbone.0's state columns (where it reads the state); then the weight
/// and bias gradients over `u` of every backbone.0 and of the skip.
struct ChunkGradients<T> {
    cells: Vec<CellGradients<T>>,
    /// The weight gradients over `u` of every cell's backbone.0 and of the
    /// skip (as rows: cell by cell, then the skip, `[D·U + W, |u|]`), and
    /// their bias gradients.
    wide: (Vec<T>, Vec<T>),
}

struct CellGradients<T> {
    /// ff1 | ff2 | the merged time head (whose gradient is time_b's).
    heads: (Vec<T>, Vec<T>),
    /// time_a's, where the rows' τ differ (empty otherwise: τ times
    /// time_b's, formed after the sum over chunks).
    time_a: (Vec<T>, Vec<T>),
    later: Vec<(Vec<T>, Vec<T>)>,
    h_part: Vec<T>,
}

impl<T: Real> ChunkGradients<T> {
    /// The number of values in all the partials.
    fn len(&self) -> usize {
        let cells: usize = self
            .cells
            .iter()
            .map(|c| {
                c.heads.0.len()
                    + c.heads.1.len()
                    + c.time_a.0.len()
                    + c.time_a.1.len()
                    + c.later
                        .iter()
                        .map(|(w, b)| w.len() + b.len())
                        .sum::<usize>()
                    + c.h_part.len()
            })
            .sum();
        cells + self.wide.0.len() + self.wide.1.len()
    }

    /// Every partial, in a fixed order (for the sum over chunks).
    fn parts_mut(&mut self) -> Vec<&mut Vec<T>> {
        let mut v = Vec::new();
        for c in &mut self.cells {
            v.push(&mut c.heads.0);
            v.push(&mut c.heads.1);
            v.push(&mut c.time_a.0);
            v.push(&mut c.time_a.1);
            for (w, b) in &mut c.later {
                v.push(w);
                v.push(b);
            }
            v.push(&mut c.h_part);
        }
        v.push(&mut self.wide.0);
        v.push(&mut self.wide.1);
        v
    }
}

/// Scratch of a forward block or a backward chunk, reused across the blocks
/// a thread runs (every value is written before it is read).
#[derive(Default)]
struct Scratch<T> {
    /// Backward: the gradient of the state leaving the cell (`[rows, W]`).
    h: Vec<T>,
    /// Backward: the gradient of the state entering it.
    h_next: Vec<T>,
    /// The activations' outputs (forward: one layer's; backward: every
    /// layer's, recomputed).
    xs: Vec<Vec<T>>,
    /// Backward: the activations' derivatives, every layer's.
    ds: Vec<Vec<T>>,
    /// Backward: the gradient of every cell's backbone.0 output and of the
    /// skip, side by side (`[rows, D·U + W]`).
    gu: Vec<T>,
    /// Backward: the heads' output gradient (`[rows, 3W]`).
    gate: Vec<T>,
    /// Backward: `time_a(z)` (`[rows, W]`), and τ times the merged time
    /// head's output gradient (where the rows' τ differ).
    ta: Vec<T>,
    ga: Vec<T>,
    /// Backward: a backbone layer's output gradient, and the next one's.
    dz: Vec<T>,
    dz_next: Vec<T>,
    /// Forward: the skip's sums; backward: a `t_feat` gradient term.
    tmp: Vec<T>,
    /// Backward: the `t_feat` gradient and the gate's τ gradient, summed
    /// over the cells.
    g_tfeat: Vec<T>,
    dt: Vec<T>,
    /// Backward: per-unit products of the τ gradient, summed in order.
    prod: Vec<T>,
}

/// `v` resized to `len` (new values zero; existing ones kept).
fn sized<T: Real>(v: &mut Vec<T>, len: usize) -> &mut [T] {
    v.resize(len, T::ZERO);
    &mut v[..len]
}

/// An initialised slice viewed as slots to overwrite ([`as_slots`]); only
/// handed to writers that write initialised values (the matrix products,
/// the activations, the cell pass).
fn slots<T>(s: &mut [T]) -> &mut [MaybeUninit<T>] {
    // SAFETY: every caller in this file passes the slots to such a writer.
    unsafe { as_slots(s) }
}

/// Slots that have all been written, as values.
///
/// # Safety
/// Every slot must have been written.
unsafe fn assume_init<T>(s: &mut [MaybeUninit<T>]) -> &mut [T] {
    // SAFETY: the caller guarantees every value is initialised, and
    // `MaybeUninit<T>` has the layout of `T`.
    unsafe { &mut *(s as *mut [MaybeUninit<T>] as *mut [T]) }
}

/// `dst = src`, writing every slot of `dst`.
fn write_all<T: Copy>(dst: &mut [MaybeUninit<T>], src: &[T]) {
    assert_eq!(dst.len(), src.len(), "cfc: saved rows differ in size");
    for (d, &s) in dst.iter_mut().zip(src) {
        d.write(s);
    }
}

/// `len` uninitialised slots of `v` (reserved) in blocks of `block`
/// values, one per task; `tasks` empty slices when `len` is 0.
fn blocks_of<T>(
    v: &mut Vec<T>,
    len: usize,
    block: usize,
    tasks: usize,
) -> Vec<&mut [MaybeUninit<T>]> {
    if len == 0 {
        return (0..tasks)
            .map(|_| <&mut [MaybeUninit<T>]>::default())
            .collect();
    }
    v.reserve_exact(len);
    let b: Vec<_> = v.spare_capacity_mut()[..len].chunks_mut(block).collect();
    assert_eq!(b.len(), tasks, "cfc: blocks and tasks differ");
    b
}

/// Marks the `len` values reserved by [`blocks_of`] as written.
///
/// # Safety
/// Every one of the `len` slots must have been written.
unsafe fn assume_written<T>(v: &mut Vec<T>, len: usize) {
    debug_assert!(v.capacity() >= len);
    // SAFETY: the caller guarantees the slots are written.
    unsafe { v.set_len(len) }
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

    fn units(&self) -> usize {
        self.cells[0].backbone[0].shape.out_dim
    }

    fn layers(&self) -> usize {
        self.cells[0].backbone.len()
    }

    /// Whether cell `l`'s first layer reads a state that may be non-zero:
    /// before the first cell the state is zero unless the skip is added
    /// there, and its terms `0·w` would add exact zeros (see the module
    /// docs), so that part of the product and its gradients are not run.
    fn reads_state(&self, l: usize) -> bool {
        l > 0 || self.skip_at == 0
    }

    fn forward_weights<'p, T: Real>(
        &'p self,
        p: &'p [T],
        (tau0, uniform): (T, bool),
    ) -> ForwardWeights<'p, T> {
        let (w, ud) = (self.width, self.u_dim);
        let wt = |lin: &LinearParams| {
            MatRef::row_major(lin.weight(p), lin.shape.out_dim, lin.shape.in_dim).t()
        };
        let cells = self
            .cells
            .iter()
            .map(|cell| {
                let lin = &cell.backbone[0];
                let b0 = MatRef::row_major(lin.weight(p), lin.shape.out_dim, lin.shape.in_dim).t();
                CellForward {
                    u_part: pack(b0.rows(0, ud)),
                    h_part: pack(b0.rows(ud, w)),
                    bias0: lin.bias(p),
                    later: cell.backbone[1..]
                        .iter()
                        .map(|l| l.linear(p).packed())
                        .collect(),
                    heads: merged_heads(&cell.heads, p, tau0).packed(),
                    time: (!uniform).then(|| {
                        TimePair::new(
                            pack_pair(wt(&cell.heads[2]), wt(&cell.heads[3])),
                            &cell.heads,
                            p,
                        )
                    }),
                }
            })
            .collect();
        ForwardWeights {
            cells,
            tau0,
            skip: self.skip.linear(p).packed(),
            head: self.head.linear(p).packed(),
        }
    }

    pub fn forward<T: Real>(&self, p: &[T], xyz: &[T], t: &[T]) -> (Deformation<T>, CfcCache<T>) {
        let n = t.len();
        let (w, ud, units, layers) = (self.width, self.u_dim, self.units(), self.layers());
        let d = self.cells.len();
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = ud - xd;
        let (t_feat, time) = profile::layer(|| "timenet".into(), || self.time.forward(p, t));
        // u = [γ(x) | t_feat], one row per Gaussian, the encoding written
        // straight into it.
        let u = profile::elementwise(
            || "u = [γ(x) | t_feat] (γ(x) encoded into u)".into(),
            n,
            ud,
            || encode_then(xyz, 3, XYZ_LEVELS, &t_feat, td),
        );
        drop(t_feat);
        let fw = self.forward_weights(p, first_tau(t));
        // Every cell runs on a block of rows after the other while the block
        // is in cache; the saved arrays are written once, block by block.
        let tasks_n = n.div_ceil(FORWARD_ROWS);
        let mut pres: Vec<Vec<T>> = (0..d * layers).map(|_| Vec::new()).collect();
        let mut h_in: Vec<Vec<T>> = (0..d).map(|_| Vec::new()).collect();
        let mut gates: Vec<Vec<T>> = (0..d).map(|_| Vec::new()).collect();
        let (mut head_in, mut out) = (Vec::new(), Vec::new());
        let h_len = |l: usize| if self.reads_state(l) { n * w } else { 0 };
        {
            let mut tasks: Vec<ForwardTask<'_, T>> = (0..tasks_n)
                .map(|b| ForwardTask {
                    r0: b * FORWARD_ROWS,
                    rows: FORWARD_ROWS.min(n - b * FORWARD_ROWS),
                    pres: Vec::with_capacity(d * layers),
                    h_in: Vec::with_capacity(d),
                    gates: Vec::with_capacity(d),
                    head_in: &mut [],
                    out: &mut [],
                })
                .collect();
            for v in pres.iter_mut() {
                for (task, s) in
                    tasks
                        .iter_mut()
                        .zip(blocks_of(v, n * units, FORWARD_ROWS * units, tasks_n))
                {
                    task.pres.push(s);
                }
            }
            for (l, v) in h_in.iter_mut().enumerate() {
                for (task, s) in
                    tasks
                        .iter_mut()
                        .zip(blocks_of(v, h_len(l), FORWARD_ROWS * w, tasks_n))
                {
                    task.h_in.push(s);
                }
            }
            for v in gates.iter_mut() {
                for (task, s) in
                    tasks
                        .iter_mut()
                        .zip(blocks_of(v, n * 3 * w, FORWARD_ROWS * 3 * w, tasks_n))
                {
                    task.gates.push(s);
                }
            }
            for (task, s) in
                tasks
                    .iter_mut()
                    .zip(blocks_of(&mut head_in, n * w, FORWARD_ROWS * w, tasks_n))
            {
                task.head_in = s;
            }
            for (task, s) in
                tasks
                    .iter_mut()
                    .zip(blocks_of(&mut out, n * 10, FORWARD_ROWS * 10, tasks_n))
            {
                task.out = s;
            }
            let tally = Tally::new(|| self.forward_ops(n));
            profile::layer(
                || "cells (fused by blocks of rows)".into(),
                || {
                    tasks
                        .into_par_iter()
                        .for_each_init(Scratch::default, |s, task| {
                            self.forward_rows(&fw, s, &u, t, task, tally.as_ref())
                        })
                },
            );
            if let Some(tally) = tally {
                tally.finish();
            }
        }
        // SAFETY: every task wrote all its rows of every saved array and of
        // the output (forward_rows writes each slot it is given).
        unsafe {
            for v in pres.iter_mut() {
                assume_written(v, n * units);
            }
            for (l, v) in h_in.iter_mut().enumerate() {
                assume_written(v, h_len(l));
            }
            for v in gates.iter_mut() {
                assume_written(v, n * 3 * w);
            }
            assume_written(&mut head_in, n * w);
            assume_written(&mut out, n * 10);
        }
        let mut pres = pres.into_iter();
        let cells = h_in
            .into_iter()
            .zip(gates)
            .map(|(h_in, gate)| CellCache {
                h_in,
                pres: pres.by_ref().take(layers).collect(),
                gate,
            })
            .collect();
        (
            Deformation::from_head(&out),
            CfcCache {
                time,
                u,
                cells,
                head_in,
            },
        )
    }

    /// The operations of the fused forward, in [`FwdOp`] order, for the
    /// profile: (what, shape, FLOPs or elements per call, calls).
    fn forward_ops(&self, n: usize) -> Vec<profile::TallyOp> {
        let (w, ud, units, d) = (self.width, self.u_dim, self.units(), self.cells.len());
        let later = d * (self.layers() - 1);
        let states = (0..d).filter(|&l| self.reads_state(l)).count();
        vec![
            profile::TallyOp::product("skip: u·Wᵀ, h += sums + b", n, ud, w, 1),
            profile::TallyOp::product("backbone.0, u columns: u·Wᵤᵀ", n, ud, units, d),
            profile::TallyOp::product(
                "backbone.0, state columns continued: + h·Wₕᵀ",
                n,
                w,
                units,
                states,
            ),
            profile::TallyOp::product("backbone.j > 0: x·Wᵀ", n, units, units, later),
            profile::TallyOp::elementwise(
                &format!("bias and {} (every backbone layer)", self.act),
                n,
                units,
                d * self.layers(),
            ),
            profile::TallyOp::product(
                "heads ff1|ff2|time (τ·time_a + time_b merged): z·Wᵀ",
                n,
                units,
                3 * w,
                d,
            ),
            profile::TallyOp::elementwise(
                "heads' bias, gate and update (2 tanh, sigmoid)",
                n,
                w,
                d,
            ),
            profile::TallyOp::product("head: h·Wᵀ + b", n, w, 10, 1),
        ]
    }

    /// The forward of one block of rows: every cell, then the head.
    fn forward_rows<T: Real>(
        &self,
        fw: &ForwardWeights<'_, T>,
        s: &mut Scratch<T>,
        u: &[T],
        t: &[T],
        task: ForwardTask<'_, T>,
        tally: Option<&profile::Tally>,
    ) {
        let ForwardTask {
            r0,
            rows,
            pres,
            h_in,
            gates,
            head_in,
            out,
        } = task;
        let (w, ud, units) = (self.width, self.u_dim, self.units());
        let u_rows = &u[r0 * ud..(r0 + rows) * ud];
        let um = MatRef::row_major(u_rows, rows, ud);
        let tb = &t[r0..r0 + rows];
        sized(&mut s.tmp, rows * w);
        if s.xs.is_empty() {
            s.xs.push(Vec::new());
        }
        sized(&mut s.xs[0], rows * units);
        // The state lives in the saved arrays: cell l reads its entering
        // state from h_in[l] and writes the next one into h_in[l + 1] (the
        // last cell into head_in). None: the zero state before the first
        // cell.
        let mut states = h_in.into_iter().chain(std::iter::once(head_in));
        let mut first = states.next();
        let mut h: Option<&mut [T]> = None;
        let mut pres = pres.into_iter();
        for ((l, cw), gate) in fw.cells.iter().enumerate().zip(gates) {
            if l == self.skip_at {
                // h += skip(u): the skip's sums plus its bias (added after the
                // sum, as in every linear layer), added to the state (+0 for
                // the zero state).
                Tally::time(tally, FwdOp::Skip as usize, || {
                    let sk =
                        fw.skip
                            .forward_block_into(u_rows, rows, slots(&mut s.tmp[..rows * w]));
                    match h.as_deref_mut() {
                        Some(h) => {
                            for (hv, &sv) in h.iter_mut().zip(sk.iter()) {
                                *hv += sv;
                            }
                        }
                        None => {
                            let slot = first.take().expect("the first cell's state slot");
                            for (hv, &sv) in slot.iter_mut().zip(sk.iter()) {
                                hv.write(T::ZERO + sv);
                            }
                            // SAFETY: every value of the slot was written.
                            h = Some(unsafe { assume_init(slot) });
                        }
                    }
                });
            }
            let reads = self.reads_state(l);
            debug_assert_eq!(reads, h.is_some());
            for j in 0..=cw.later.len() {
                let slot = pres.next().expect("a saved block per layer");
                // The layer's sums plus its bias (added after the sums), written
                // into its saved pre-activation.
                let pre: &mut [T] = if j == 0 {
                    // The u columns, then the sums continued over the state
                    // columns (none where the state is zero, see
                    // reads_state): the same bits as one sum over [u; h].
                    let pre = Tally::time(tally, FwdOp::UPart as usize, || {
                        matmul_block_into(um, &cw.u_part, slot)
                    });
                    if let Some(h) = h.as_deref() {
                        Tally::time(tally, FwdOp::HPart as usize, || {
                            matmul_block_resume(MatRef::row_major(h, rows, w), &cw.h_part, pre)
                        });
                    }
                    pre
                } else {
                    Tally::time(tally, FwdOp::Later as usize, || {
                        cw.later[j - 1].product_block_into(&s.xs[0][..rows * units], rows, slot)
                    })
                };
                let bias = if j == 0 {
                    cw.bias0
                } else {
                    cw.later[j - 1].bias()
                };
                // The bias, added after the sums, and the activation in one
                // pass (the same bits as one after the other).
                Tally::time(tally, FwdOp::Act as usize, || {
                    self.act.add_bias_apply_block_uninit(
                        pre,
                        bias,
                        slots(&mut s.xs[0][..rows * units]),
                    );
                });
            }
            // The heads' sums as one product 3W wide (by runs of equal τ),
            // then their bias (added after the sums), the gate and the new
            // state in one pass (the gate's values are saved).
            let gate = Tally::time(tally, FwdOp::Heads as usize, || {
                let z = &s.xs[0][..rows * units];
                let gate = cw.heads.product_block_into(z, rows, gate);
                // Runs with another τ: their time head's sums again, with
                // the weights merged for their τ (the same sums, in the same
                // order), over the τ₀ ones.
                for (i, j) in equal_runs(tb).filter(|&(i, _)| !same(tb[i], fw.tau0)) {
                    let time_pair = cw.time.as_ref().expect("packed where the rows' τ differ");
                    let zr = MatRef::row_major(&z[i * units..j * units], j - i, units);
                    let time = &mut s.tmp[..(j - i) * w];
                    matmul_block_into(zr, &time_pair.weights(tb[i]), slots(time));
                    set_columns(&mut gate[i * 3 * w..j * 3 * w], 3 * w, 2 * w, time, w);
                }
                gate
            });
            let next = states.next().expect("a state slot per cell");
            Tally::time(tally, FwdOp::Gate as usize, || {
                // Each run of rows with the bias of its τ: the heads' for τ₀,
                // ff1 | ff2 with the time head merged for another τ.
                let mut b = Vec::new();
                for (i, j) in equal_runs(tb) {
                    let bias = if same(tb[i], fw.tau0) {
                        cw.heads.bias()
                    } else {
                        let time_pair = cw.time.as_ref().expect("packed where the rows' τ differ");
                        b.clear();
                        b.extend_from_slice(&cw.heads.bias()[..2 * w]);
                        b.extend_from_slice(&time_pair.bias(tb[i]));
                        &b
                    };
                    cell_forward_rows(
                        &mut gate[i * 3 * w..j * 3 * w],
                        &mut next[i * w..j * w],
                        bias,
                        w,
                    );
                }
            });
            // SAFETY: cell_forward_rows wrote every value of its rows.
            h = Some(unsafe { assume_init(next) });
        }
        let h = h.expect("at least one cell");
        Tally::time(tally, FwdOp::Head as usize, || {
            fw.head.forward_block_into(h, rows, out);
        });
    }

    fn backward_weights<'p, T: Real>(
        &'p self,
        p: &'p [T],
        (tau0, uniform): (T, bool),
    ) -> BackwardWeights<'p, T> {
        let (w, ud, units) = (self.width, self.u_dim, self.units());
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = ud - xd;
        let wm = |lin: &LinearParams| {
            MatRef::row_major(lin.weight(p), lin.shape.out_dim, lin.shape.in_dim)
        };
        let cells = self
            .cells
            .iter()
            .map(|cell| {
                let heads = merged_heads(&cell.heads, p, tau0);
                let b0 = wm(&cell.backbone[0]);
                CellBackward {
                    heads: pack(MatRef::row_major(heads.weight(), 3 * w, units)),
                    time_a: cell.heads[2].linear(p).packed(),
                    other_tau: (!uniform).then(|| {
                        (
                            pack(MatRef::row_major(
                                &heads.weight()[..2 * w * units],
                                2 * w,
                                units,
                            )),
                            TimePair::new(
                                pack_pair(wm(&cell.heads[2]), wm(&cell.heads[3])),
                                &cell.heads,
                                p,
                            ),
                        )
                    }),
                    later: cell.backbone[1..].iter().map(|l| pack(wm(l))).collect(),
                    t_part: pack(b0.cols(xd, td)),
                    h_part: pack(b0.cols(ud, w)),
                }
            })
            .collect();
        BackwardWeights {
            cells,
            tau0,
            skip_t: pack(wm(&self.skip).cols(xd, td)),
        }
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
        let (w, ud) = (self.width, self.u_dim);
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = ud - xd;
        let dh = profile::layer(
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
        // With one τ for every row, time_a's weight gradient is τ times
        // time_b's (formed after the sum over chunks), else a product of its
        // own per chunk.
        let (tau0, uniform) = first_tau(t);
        let bw = self.backward_weights(p, (tau0, uniform));
        // Every cell runs backwards on a chunk of rows after the other while
        // the chunk is in cache; the weight and bias gradients are partial
        // sums per chunk, added in chunk order at the end.
        let tasks_n = n.div_ceil(REDUCTION_CHUNK);
        let (mut g_tfeat, mut gate_dt) = (Vec::new(), Vec::new());
        let partials: Vec<ChunkGradients<T>> = {
            let tasks: Vec<BackwardTask<'_, T>> = (0..tasks_n)
                .zip(blocks_of(
                    &mut g_tfeat,
                    n * td,
                    REDUCTION_CHUNK * td,
                    tasks_n,
                ))
                .zip(blocks_of(&mut gate_dt, n, REDUCTION_CHUNK, tasks_n))
                .map(|((b, g_tfeat), dt)| BackwardTask {
                    r0: b * REDUCTION_CHUNK,
                    rows: REDUCTION_CHUNK.min(n - b * REDUCTION_CHUNK),
                    g_tfeat,
                    dt,
                })
                .collect();
            let tally = Tally::new(|| self.backward_ops(n, uniform));
            let r = profile::layer(
                || "cells (fused by chunks of rows)".into(),
                || {
                    tasks
                        .into_par_iter()
                        .map_init(Scratch::default, |s, task| {
                            self.backward_rows(&bw, s, c, &dh, t, uniform, task, tally.as_ref())
                        })
                        .collect()
                },
            );
            if let Some(tally) = tally {
                tally.finish();
            }
            r
        };
        // SAFETY: every chunk's task wrote all its rows of both.
        unsafe {
            assume_written(&mut g_tfeat, n * td);
            assume_written(&mut gate_dt, n);
        }
        let per_chunk = partials.first().map_or(0, ChunkGradients::len);
        profile::elementwise(
            || "weight and bias gradients: chunk partials added in order".into(),
            partials.len(),
            per_chunk,
            || self.store_partials(partials, uniform.then_some(tau0), gp),
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

    /// The chunks' partial gradients added in chunk order (the first taken
    /// as is) and written into `gp`; `uniform`: the τ of every row, when
    /// they share one (time_a's gradients are then τ times time_b's).
    fn store_partials<T: Real>(
        &self,
        partials: Vec<ChunkGradients<T>>,
        uniform: Option<T>,
        gp: &mut [T],
    ) {
        let (w, ud, units) = (self.width, self.u_dim, self.units());
        let mut chunks = partials.into_iter();
        let Some(mut total) = chunks.next() else {
            return;
        };
        for mut part in chunks {
            for (acc, v) in total.parts_mut().into_iter().zip(part.parts_mut()) {
                for (a, &b) in acc.iter_mut().zip(v.iter()) {
                    *a += b;
                }
            }
        }
        for (l, (cell, cg)) in self.cells.iter().zip(&total.cells).enumerate() {
            // ff1, ff2 and time_b from the merged heads' rows 0, 1 and 2.
            for (k, head) in [0, 1, 3].map(|k| (k.min(2), &cell.heads[k])) {
                head.store_grads(
                    gp,
                    &cg.heads.0[k * w * units..(k + 1) * w * units],
                    &cg.heads.1[k * w..(k + 1) * w],
                );
            }
            match uniform {
                Some(tau) => {
                    let scaled = |g: &[T]| -> Vec<T> { g.iter().map(|&v| tau * v).collect() };
                    cell.heads[2].store_grads(
                        gp,
                        &scaled(&cg.heads.0[2 * w * units..3 * w * units]),
                        &scaled(&cg.heads.1[2 * w..3 * w]),
                    );
                }
                None => cell.heads[2].store_grads(gp, &cg.time_a.0, &cg.time_a.1),
            }
            for (lin, (wg, bg)) in cell.backbone[1..].iter().zip(&cg.later) {
                lin.store_grads(gp, wg, bg);
            }
            let lin = &cell.backbone[0];
            let in_dim = lin.shape.in_dim;
            for r in 0..units {
                let (wide_w, wide_b) = (&total.wide.0, &total.wide.1);
                let i = l * units + r;
                let row = &mut gp[lin.w + r * in_dim..lin.w + (r + 1) * in_dim];
                row[..ud].copy_from_slice(&wide_w[i * ud..(i + 1) * ud]);
                if self.reads_state(l) {
                    row[ud..].copy_from_slice(&cg.h_part[r * w..(r + 1) * w]);
                }
                gp[lin.b + r] = wide_b[i];
            }
        }
        let s0 = self.cells.len() * units;
        self.skip
            .store_grads(gp, &total.wide.0[s0 * ud..], &total.wide.1[s0..]);
    }

    /// The operations of the fused backward, in [`BwdOp`] order, for the
    /// profile.
    fn backward_ops(&self, n: usize, uniform: bool) -> Vec<profile::TallyOp> {
        let (w, ud, units, d) = (self.width, self.u_dim, self.units(), self.cells.len());
        let td = ud - encoded_dim(3, XYZ_LEVELS);
        let layers = self.layers();
        let later = d * (layers - 1);
        let states = (0..d).filter(|&l| self.reads_state(l)).count();
        vec![
            profile::TallyOp::elementwise(
                &format!(
                    "{} and f′ recomputed from the saved pre-activations",
                    self.act
                ),
                n,
                units,
                d * layers,
            ),
            profile::TallyOp::product(
                "time_a(z) recomputed for the τ gradient: z·Wᵀ + b",
                n,
                units,
                w,
                d,
            ),
            profile::TallyOp::elementwise("gate and update vjp", n, w, d),
            profile::TallyOp::product(
                "heads weight grad Gᵀ·z, bias grad (ff1|ff2|time)",
                3 * w,
                n,
                units,
                d,
            ),
            profile::TallyOp::product(
                "time_a weight grad (τ·G)ᵀ·z, bias grad (rows' τ differ)",
                w,
                n,
                units,
                if uniform { 0 } else { d },
            ),
            profile::TallyOp::product("heads input grad G·W", n, 3 * w, units, d),
            profile::TallyOp::elementwise(
                &format!("{} vjp: G·f′ (every backbone layer)", self.act),
                n,
                units,
                d * layers,
            ),
            profile::TallyOp::product(
                "backbone.j > 0 weight grad Gᵀ·x, bias grad",
                units,
                n,
                units,
                later,
            ),
            profile::TallyOp::product("backbone.j > 0 input grad G·W", n, units, units, later),
            profile::TallyOp::elementwise(
                "backbone.0 output gradient into the wide gradient (copy)",
                n,
                units,
                d,
            ),
            profile::TallyOp::product(
                "backbone.0 weight grad over the state: Gᵀ·h",
                units,
                n,
                w,
                states,
            ),
            profile::TallyOp::product("backbone.0 input grad over t_feat: G·Wₜ", n, units, td, d),
            profile::TallyOp::product(
                "backbone.0 input grad over the state: G·Wₕ",
                n,
                units,
                w,
                states,
            ),
            profile::TallyOp::product(
                "skip: input grad G·Wₜ, its gradient into the wide gradient",
                n,
                w,
                td,
                1,
            ),
            profile::TallyOp::product(
                "weight grad over u of every backbone.0 and the skip: Gᵀ·u, bias grad",
                d * units + w,
                n,
                ud,
                1,
            ),
        ]
    }

    /// The backward of one chunk of rows: every cell, last first. Returns
    /// the chunk's partial weight and bias gradients.
    #[allow(clippy::too_many_arguments)]
    fn backward_rows<T: Real>(
        &self,
        bw: &BackwardWeights<T>,
        s: &mut Scratch<T>,
        c: &CfcCache<T>,
        dh_all: &[T],
        t: &[T],
        uniform: bool,
        task: BackwardTask<'_, T>,
        tally: Option<&profile::Tally>,
    ) -> ChunkGradients<T> {
        let BackwardTask {
            r0,
            rows,
            g_tfeat,
            dt,
        } = task;
        let (w, ud, units, layers) = (self.width, self.u_dim, self.units(), self.layers());
        let xd = encoded_dim(3, XYZ_LEVELS);
        let td = ud - xd;
        let um = MatRef::row_major(&c.u[r0 * ud..(r0 + rows) * ud], rows, ud);
        let tb = &t[r0..r0 + rows];
        let rows_of = |d: usize| (r0 * d, (r0 + rows) * d);
        // The state gradient entering the last cell, the t_feat gradient
        // and the gate's τ gradient, accumulated cell by cell (from zero).
        let (a, b) = rows_of(w);
        sized(&mut s.h, rows * w).copy_from_slice(&dh_all[a..b]);
        sized(&mut s.h_next, rows * w);
        sized(&mut s.g_tfeat, rows * td).fill(T::ZERO);
        sized(&mut s.tmp, rows * td);
        sized(&mut s.dt, rows).fill(T::ZERO);
        sized(&mut s.prod, w);
        sized(&mut s.gate, rows * 3 * w);
        sized(&mut s.ta, rows * w);
        if !uniform {
            sized(&mut s.ga, rows * w);
        }
        sized(&mut s.dz, rows * units);
        sized(&mut s.dz_next, rows * units);
        s.xs.resize_with(layers, Vec::new);
        s.ds.resize_with(layers, Vec::new);
        let mut cells: Vec<CellGradients<T>> = Vec::with_capacity(self.cells.len());
        let wide_n = self.cells.len() * units + w;
        sized(&mut s.gu, rows * wide_n);
        for l in (0..self.cells.len()).rev() {
            let (cc, cw) = (&c.cells[l], &bw.cells[l]);
            let reads = self.reads_state(l);
            // The backbone's outputs and the activation's derivatives,
            // recomputed from the saved pre-activations (the same functions:
            // the same bits).
            Tally::time(tally, BwdOp::Act as usize, || {
                for ((x, dx), pre) in s.xs.iter_mut().zip(s.ds.iter_mut()).zip(&cc.pres) {
                    let (a, b) = rows_of(units);
                    self.act.apply_and_derivative_block(
                        &pre[a..b],
                        slots(sized(x, rows * units)),
                        slots(sized(dx, rows * units)),
                    );
                }
            });
            let zm = MatRef::row_major(&s.xs[layers - 1][..rows * units], rows, units);
            // time_a(z) for the τ gradient, then the gate and update vjp:
            // the heads' output gradient G.
            let ta = Tally::time(tally, BwdOp::TimeA as usize, || {
                cw.time_a.forward_block_into(
                    &s.xs[layers - 1][..rows * units],
                    rows,
                    slots(&mut s.ta[..rows * w]),
                )
            });
            let gate = &mut s.gate[..rows * 3 * w];
            Tally::time(tally, BwdOp::Gate as usize, || {
                cell_backward_rows(
                    gate,
                    &cc.gate[r0 * 3 * w..(r0 + rows) * 3 * w],
                    ta,
                    &s.h[..rows * w],
                    &mut s.dt[..rows],
                    &mut s.prod,
                    w,
                )
            });
            let gm = MatRef::row_major(&*gate, rows, 3 * w);
            let heads = Tally::time(tally, BwdOp::HeadsWeight as usize, || {
                (matmul_tn(gm, zm), column_sums(gate, rows, 3 * w))
            });
            let time_a = if uniform {
                (Vec::new(), Vec::new())
            } else {
                Tally::time(tally, BwdOp::TimeAWeight as usize, || {
                    let ga = &mut s.ga[..rows * w];
                    for ((o, g), &tau) in
                        ga.chunks_exact_mut(w).zip(gate.chunks_exact(3 * w)).zip(tb)
                    {
                        for (o, &v) in o.iter_mut().zip(&g[2 * w..]) {
                            *o = tau * v;
                        }
                    }
                    let gam = MatRef::row_major(&*ga, rows, w);
                    (matmul_tn(gam, zm), column_sums(ga, rows, w))
                })
            };
            let mut dz = Tally::time(tally, BwdOp::HeadsInput as usize, || {
                let dz = &mut s.dz[..rows * units];
                for (i, j) in equal_runs(tb) {
                    let g = MatRef::row_major(&gate[i * 3 * w..j * 3 * w], j - i, 3 * w);
                    let out = slots(&mut dz[i * units..j * units]);
                    if same(tb[i], bw.tau0) {
                        matmul_block_into(g, &cw.heads, out);
                    } else {
                        // The sums over ff1 | ff2, continued over the time
                        // head merged for this τ: one sum over 3W in order.
                        let (ff, time_pair) = cw
                            .other_tau
                            .as_ref()
                            .expect("packed where the rows' τ differ");
                        let out = matmul_block_into(g.cols(0, 2 * w), ff, out);
                        matmul_block_resume(g.cols(2 * w, w), &time_pair.weights(tb[i]), out);
                    }
                }
                dz
            });
            let mut later = Vec::with_capacity(layers - 1);
            for j in (1..layers).rev() {
                let ds = &s.ds[j][..rows * units];
                Tally::time(tally, BwdOp::ActVjp as usize, || {
                    Activation::backward_block_from_derivative(ds, dz)
                });
                let xm = MatRef::row_major(&s.xs[j - 1][..rows * units], rows, units);
                let gj = MatRef::row_major(&*dz, rows, units);
                later.push(Tally::time(tally, BwdOp::LaterWeight as usize, || {
                    (matmul_tn(gj, xm), column_sums(dz, rows, units))
                }));
                Tally::time(tally, BwdOp::LaterInput as usize, || {
                    matmul_block_into(gj, &cw.later[j - 1], slots(&mut s.dz_next[..rows * units]));
                });
                std::mem::swap(&mut s.dz, &mut s.dz_next);
                dz = &mut s.dz[..rows * units];
            }
            later.reverse();
            Tally::time(tally, BwdOp::ActVjp as usize, || {
                Activation::backward_block_from_derivative(&s.ds[0][..rows * units], dz)
            });
            let g0 = MatRef::row_major(&*dz, rows, units);
            // backbone.0's input is [γ(x) | t_feat | h]: its weight
            // gradient over u and its bias gradient; γ(x) is stop-gradient,
            // t_feat's gradient is collected, h's flows on.
            Tally::time(tally, BwdOp::UWeight as usize, || {
                set_columns(&mut s.gu[..rows * wide_n], wide_n, l * units, dz, units)
            });
            let h_part = if reads {
                let (a, b) = rows_of(w);
                Tally::time(tally, BwdOp::HWeight as usize, || {
                    matmul_tn(g0, MatRef::row_major(&cc.h_in[a..b], rows, w))
                })
            } else {
                Vec::new()
            };
            Tally::time(tally, BwdOp::TInput as usize, || {
                let g_t = matmul_block_into(g0, &cw.t_part, slots(&mut s.tmp[..rows * td]));
                for (acc, &v) in s.g_tfeat.iter_mut().zip(g_t.iter()) {
                    *acc += v;
                }
            });
            if reads {
                Tally::time(tally, BwdOp::HInput as usize, || {
                    matmul_block_into(g0, &cw.h_part, slots(&mut s.h_next[..rows * w]));
                });
                std::mem::swap(&mut s.h, &mut s.h_next);
            }
            if l == self.skip_at {
                // h_in = h_prev + skip(u): the same gradient flows to both.
                Tally::time(tally, BwdOp::Skip as usize, || {
                    let dhm = MatRef::row_major(&s.h[..rows * w], rows, w);
                    let c0 = self.cells.len() * units;
                    set_columns(&mut s.gu[..rows * wide_n], wide_n, c0, &s.h[..rows * w], w);
                    let g_t = matmul_block_into(dhm, &bw.skip_t, slots(&mut s.tmp[..rows * td]));
                    for (acc, &v) in s.g_tfeat.iter_mut().zip(g_t.iter()) {
                        *acc += v;
                    }
                });
            }
            cells.push(CellGradients {
                heads,
                time_a,
                later,
                h_part,
            });
        }
        cells.reverse();
        // The weight and bias gradients over u of every cell's backbone.0
        // and of the skip: one product [D·U + W, rows]·[rows, |u|] and one
        // column sum (each element its own sum over the chunk's rows, as
        // layer by layer).
        let wide = Tally::time(tally, BwdOp::Wide as usize, || {
            let gu = &s.gu[..rows * wide_n];
            (
                matmul_tn(MatRef::row_major(gu, rows, wide_n), um),
                column_sums(gu, rows, wide_n),
            )
        });
        write_all(g_tfeat, &s.g_tfeat[..rows * td]);
        write_all(dt, &s.dt[..rows]);
        ChunkGradients { cells, wide }
    }
}

/// ff1 | ff2 | time(τ) as one layer `3W` wide over `z`, where time(τ) is
/// `time_a(z)·τ + time_b(z)` merged into one layer: weight `τ·W_a + W_b`,
/// bias `τ·b_a + b_b` (see the module docs).
fn merged_heads<T: Real>(heads: &[LinearParams; 4], p: &[T], tau: T) -> Linear<'static, T> {
    let merge =
        |a: &[T], b: &[T]| -> Vec<T> { a.iter().zip(b).map(|(&a, &b)| tau * a + b).collect() };
    let weight = merge(heads[2].weight(p), heads[3].weight(p));
    let bias = merge(heads[2].bias(p), heads[3].bias(p));
    let time = Linear::new(&weight, &bias, heads[2].shape);
    Linear::stacked(&[heads[0].linear(p), heads[1].linear(p), time])
}

/// τ₀, the first row's τ (+0 for no rows), and whether every row has it.
fn first_tau<T: Real>(t: &[T]) -> (T, bool) {
    let tau0 = t.first().copied().unwrap_or(T::ZERO);
    (tau0, t.iter().all(|&v| same(v, tau0)))
}

/// Columns `c0..c0 + d` of the row-major `dst` (`ld` wide) set to `src`
/// `[rows, d]`.
fn set_columns<T: Copy>(dst: &mut [T], ld: usize, c0: usize, src: &[T], d: usize) {
    if d == 0 || ld == 0 {
        return;
    }
    for (orow, srow) in dst.chunks_exact_mut(ld).zip(src.chunks_exact(d)) {
        orow[c0..c0 + d].copy_from_slice(srow);
    }
}

// The fused element-wise pass of a cell on a block of rows. `g` holds the
// three heads' sums per row (ff1 | ff2 | time, each W wide; time is
// time_a(z)·τ + time_b(z), merged) on entry, `bias` their biases (3W), and
// tanh(ff1) | tanh(ff2) | σ of the sums plus the biases on exit; `h`
// receives the new state.
multiversion!(fn cell_forward_rows<T: Real>(g: &mut [T], h: &mut [MaybeUninit<T>], bias: &[T], w: usize) => cell_forward_rows_body);

#[inline(always)]
fn cell_forward_rows_body<T: Real>(g: &mut [T], h: &mut [MaybeUninit<T>], bias: &[T], w: usize) {
    let (b1, rest) = bias.split_at(w);
    let (b2, bt) = rest.split_at(w);
    // Simple loops per row (each a zip of at most four slices, which the
    // compiler vectorises; one loop with five streams it would not). The
    // row stays in L1 between them; the arithmetic per element is the same
    // as one fused loop.
    for (g, h) in g.chunks_exact_mut(3 * w).zip(h.chunks_exact_mut(w)) {
        let (f1, rest) = g.split_at_mut(w);
        let (f2, ts) = rest.split_at_mut(w);
        for (v, &b) in f1.iter_mut().zip(b1) {
            *v = fastmath::tanh(*v + b);
        }
        for (v, &b) in f2.iter_mut().zip(b2) {
            *v = fastmath::tanh(*v + b);
        }
        for (s, &b) in ts.iter_mut().zip(bt) {
            *s = fastmath::sigmoid(*s + b);
        }
        for (((h, &a), &b), &s) in h.iter_mut().zip(f1.iter()).zip(f2.iter()).zip(ts.iter()) {
            h.write(a * (T::ONE - s) + s * b);
        }
    }
}

// vjp of `cell_forward_rows` on a block of rows: the gradient of the three
// head outputs `o` (`[rows, 3W]`) given the cell pass's saved values `g`
// (tanh(ff1) | tanh(ff2) | σ), `time_a(z)` `ta` (`[rows, W]`) and the state
// gradient `dh` `[rows, W]`; adds each row's gradient with respect to τ
// (summed over j in order) to `dt`. `prod` is scratch, W long.
multiversion!(fn cell_backward_rows<T: Real>(o: &mut [T], g: &[T], ta: &[T], dh: &[T], dt: &mut [T], prod: &mut [T], w: usize) => cell_backward_rows_body);

// The per-row sum for τ runs in its own loop over `prod` (j ascending), so
// the element-wise loop vectorises.
#[inline(always)]
fn cell_backward_rows_body<T: Real>(
    o: &mut [T],
    g: &[T],
    ta: &[T],
    dh: &[T],
    dt: &mut [T],
    prod: &mut [T],
    w: usize,
) {
    for ((((o, g), ta), dh), dt) in o
        .chunks_exact_mut(3 * w)
        .zip(g.chunks_exact(3 * w))
        .zip(ta.chunks_exact(w))
        .zip(dh.chunks_exact(w))
        .zip(dt.iter_mut())
    {
        let (o1, rest) = o.split_at_mut(w);
        let (o2, o3) = rest.split_at_mut(w);
        let (ga, rest) = g.split_at(w);
        let (gb, gs) = rest.split_at(w);
        for ((((((((o1, o2), o3), &a), &b), &s), &gh), &ta), pr) in o1
            .iter_mut()
            .zip(o2.iter_mut())
            .zip(o3.iter_mut())
            .zip(ga)
            .zip(gb)
            .zip(gs)
            .zip(dh)
            .zip(ta)
            .zip(prod.iter_mut())
        {
            let da = gh * (T::ONE - s);
            let db = gh * s;
            let ds = gh * (b - a);
            let dpre = ds * (s * (T::ONE - s));
            *o1 = da * (T::ONE - a * a);
            *o2 = db * (T::ONE - b * b);
            *o3 = dpre;
            *pr = dpre * ta;
        }
        let mut sum = T::ZERO;
        for &p in prod.iter() {
            sum += p;
        }
        *dt += sum;
    }
}
