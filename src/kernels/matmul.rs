//! Deterministic, fast matrix products for the deformation fields.
//!
//! Every output element is one sum over `k` in increasing order, starting
//! from zero, each term added by a fused multiply-add (`s = a·b + s`,
//! rounded once). A fused multiply-add is exactly specified by IEEE 754, so
//! the vector FMA instructions and the pinned library's software version
//! ([`Real::mul_add`]) give the same bits; the sum does not depend on the
//! tiling, on the instruction set the kernel was compiled for, or on the
//! number of threads, so the fast kernels give the same bits as the plain
//! [`reference`](mod@reference) loops on every CPU and build. (FMA doubles
//! the peak rate over a separate multiply and add on CPUs where both share
//! the same ports.)
//!
//! Speed comes from a register-tiled micro-kernel (a tile of `MR` rows by
//! `NR` columns of the output kept in registers, vectorised across output
//! columns) compiled three times: for AVX-512, for AVX2 and for the baseline
//! target. The widest one the CPU supports is picked at run time, so a default
//! build reaches the fast path too. Work is split over rayon threads by fixed
//! blocks of output rows ([`matmul_tn`]: by chunks of its reduction).
//!
//! The reduction over rows in [`matmul_tn`] (the weight gradient `Gᵀ X`) and
//! [`column_sums`] (the bias gradient) is split into fixed chunks of
//! [`REDUCTION_CHUNK`] rows, independent of the thread count: each chunk's
//! partial sum is computed in row order, and the partials are added in chunk
//! order (`((p0 + p1) + p2) + ...`).

use super::{as_slots, par_blocks_written, vec_written_by};
use crate::math::{Precision, Real};
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// Rows per chunk of the fixed-order reductions over rows (weight and bias
/// gradients). Part of the definition of the result: changing it changes bits.
pub const REDUCTION_CHUNK: usize = 512;

/// Output rows per parallel task of [`matmul`] (does not affect results).
const ROW_BLOCK: usize = 48;

/// A read-only matrix view with arbitrary row and column strides.
#[derive(Clone, Copy, Debug)]
pub struct MatRef<'a, T> {
    /// The elements; `(r, c)` is at `r·row_stride + c·col_stride`.
    pub data: &'a [T],
    /// Number of rows.
    pub rows: usize,
    /// Number of columns.
    pub cols: usize,
    /// Distance in elements between consecutive rows.
    pub row_stride: usize,
    /// Distance in elements between consecutive columns.
    pub col_stride: usize,
}

impl<'a, T: Real> MatRef<'a, T> {
    /// A row-major `rows × cols` matrix.
    pub fn row_major(data: &'a [T], rows: usize, cols: usize) -> Self {
        assert!(data.len() >= rows * cols, "matrix data too short");
        MatRef {
            data,
            rows,
            cols,
            row_stride: cols,
            col_stride: 1,
        }
    }
    /// The transpose (no copy).
    pub fn t(self) -> Self {
        MatRef {
            data: self.data,
            rows: self.cols,
            cols: self.rows,
            row_stride: self.col_stride,
            col_stride: self.row_stride,
        }
    }
    /// Columns `c0..c0+n` (no copy).
    pub fn cols(self, c0: usize, n: usize) -> Self {
        assert!(c0 + n <= self.cols, "column range out of bounds");
        MatRef {
            data: &self.data[(c0 * self.col_stride).min(self.data.len())..],
            rows: self.rows,
            cols: n,
            row_stride: self.row_stride,
            col_stride: self.col_stride,
        }
    }
    /// Rows `r0..r0+n` (no copy).
    pub fn rows(self, r0: usize, n: usize) -> Self {
        assert!(r0 + n <= self.rows, "row range out of bounds");
        MatRef {
            data: &self.data[(r0 * self.row_stride).min(self.data.len())..],
            rows: n,
            cols: self.cols,
            row_stride: self.row_stride,
            col_stride: self.col_stride,
        }
    }
    #[inline(always)]
    fn at(&self, r: usize, c: usize) -> T {
        self.data[r * self.row_stride + c * self.col_stride]
    }
}

/// `C = A · B` for `A` `[m, k]` and `B` `[k, n]` (any strides); `C` is
/// returned row-major `[m, n]`.
pub fn matmul<T: Real>(a: MatRef<'_, T>, b: MatRef<'_, T>) -> Vec<T> {
    matmul_parts_then::<T, T, _>(&[(a, b)], &mut [], 0, |_, _, _| {})
}

/// `C = [A₁ | A₂ | …] · [B₁; B₂; …]` for `A` given as column blocks and `B`
/// as the matching row blocks (`parts[i] = (Aᵢ, Bᵢ)`; one part for a plain
/// product), without copying them into one matrix: each sum runs over
/// `A₁`'s columns, then continues over `A₂`'s, and so on, so the result has
/// the same bits as the product of the concatenated matrices.
///
/// Then `epilogue(first_row, c_rows, side_rows)` on each block of output
/// rows right after it is computed (while it is in cache), with the
/// matching rows of `side` (row-major, `side_w` values per row of `A`; empty
/// when `side_w` is 0). Blocks are disjoint and each is visited once, so an
/// element-wise epilogue gives the same bits as a separate pass, and an
/// epilogue that writes every value of its side rows fills `side` (which may
/// then start uninitialised: `S = MaybeUninit<T>`).
pub fn matmul_parts_then<T: Real, S: Send, F>(
    parts: &[(MatRef<'_, T>, MatRef<'_, T>)],
    side: &mut [S],
    side_w: usize,
    epilogue: F,
) -> Vec<T>
where
    F: Fn(usize, &mut [T], &mut [S]) + Sync,
{
    matmul_from_parts_then(None, parts, side, side_w, epilogue)
}

/// [`matmul_parts_then`] with every sum starting from the matching element
/// of `init` (`[m, n]`, any strides) instead of zero: `C = S + [A₁ | A₂ | …]
/// · [B₁; B₂; …]`, each term fused onto the running sum in order. When `S`
/// holds the sums of a product over earlier columns of `A` (read in place,
/// for example a column block of a wider product), the result has the same
/// bits as the product over all the columns.
pub fn matmul_from_parts_then<T: Real, S: Send, F>(
    init: Option<MatRef<'_, T>>,
    parts: &[(MatRef<'_, T>, MatRef<'_, T>)],
    side: &mut [S],
    side_w: usize,
    epilogue: F,
) -> Vec<T>
where
    F: Fn(usize, &mut [T], &mut [S]) + Sync,
{
    let (first_a, first_b) = parts.first().expect("matmul: at least one part");
    let (m, n) = (first_a.rows, first_b.cols);
    if let Some(s) = init {
        assert_eq!(
            (s.rows, s.cols),
            (m, n),
            "matmul: initial sums differ in shape"
        );
    }
    for (a, b) in parts {
        assert_eq!(a.cols, b.rows, "matmul: inner dimensions differ");
        assert_eq!((a.rows, b.cols), (m, n), "matmul: parts differ in shape");
    }
    assert_eq!(side.len(), m * side_w, "matmul: side has the wrong size");
    if m == 0 {
        return Vec::new();
    }
    if n == 0 {
        // No output, but the epilogue still sees every block of rows.
        for (blk, sb) in side.chunks_mut((ROW_BLOCK * side_w).max(1)).enumerate() {
            epilogue(blk * ROW_BLOCK, &mut [], sb);
        }
        return Vec::new();
    }
    let packed: Vec<PackedB<T>> = parts.iter().map(|&(_, b)| pack_b(b)).collect();
    // The output is written once, tile by tile, without being zeroed first
    // (zeroing cost as much as a tenth of a product), in parallel blocks of
    // rows (one block runs on the calling thread).
    vec_written_by(m * n, |out| {
        par_blocks_written(
            out,
            ROW_BLOCK * n,
            side,
            ROW_BLOCK * side_w,
            |blk, cb, sb| {
                let r0 = blk * ROW_BLOCK;
                let rows = cb.len() / n;
                if let Some(s) = init {
                    for (r, dst) in cb.chunks_exact_mut(n).enumerate() {
                        if s.col_stride == 1 {
                            let o = (r0 + r) * s.row_stride;
                            for (d, &v) in dst.iter_mut().zip(&s.data[o..o + n]) {
                                d.write(v);
                            }
                        } else {
                            for (q, d) in dst.iter_mut().enumerate() {
                                d.write(s.at(r0 + r, q));
                            }
                        }
                    }
                }
                for (i, ((a, _), pb)) in parts.iter().zip(&packed).enumerate() {
                    // The first part writes the block (unless it starts from
                    // `init`); the others continue its sums.
                    let resume = i > 0 || init.is_some();
                    block_product(
                        ASource::View(a.rows(r0, rows)),
                        pb.panels(),
                        a.cols,
                        n,
                        cb,
                        resume,
                    );
                }
                // SAFETY: `init` or the first block_product call wrote every element
                // of cb.
                let cb = unsafe { &mut *(cb as *mut [MaybeUninit<T>] as *mut [T]) };
                epilogue(r0, cb, sb);
                cb
            },
        )
    })
}

/// `B` `[k, n]` packed once for products with many blocks of rows of `A`
/// (see [`matmul_block_into`]).
pub struct Packed<T> {
    b: PackedB<T>,
    k: usize,
    n: usize,
}

/// Pack `B` for [`matmul_block_into`].
pub fn pack<T: Real>(b: MatRef<'_, T>) -> Packed<T> {
    Packed {
        b: pack_b(b),
        k: b.rows,
        n: b.cols,
    }
}

/// `A` and `B` (of the same shape) packed for the same kernel, for
/// [`pack_axpy`] (the kernel is read once: a test that pins the instruction
/// set in between cannot make them differ).
pub fn pack_pair<T: Real>(a: MatRef<'_, T>, b: MatRef<'_, T>) -> (Packed<T>, Packed<T>) {
    let path = kernel_path();
    let packed = |m: MatRef<'_, T>| Packed {
        b: pack_b_for(m, path),
        k: m.rows,
        n: m.cols,
    };
    (packed(a), packed(b))
}

/// The packing of `τ·A + B` (each value rounded after the product and after
/// the sum) from the packings of `A` and `B` ([`pack_pair`]), which must have
/// the same shape:
/// one pass over the packed values, in their packed order, instead of
/// packing again (the padding stays zero for finite `τ`, and padded values
/// are never stored).
pub fn pack_axpy<T: Real>(tau: T, a: &Packed<T>, b: &Packed<T>) -> Packed<T> {
    assert!(
        a.k == b.k && a.n == b.n && a.b.width == b.b.width && a.b.path == b.b.path,
        "pack_axpy: the packings differ in shape"
    );
    let data =
        a.b.data
            .iter()
            .zip(&b.b.data)
            .map(|(&x, &y)| tau * x + y)
            .collect();
    Packed {
        b: PackedB {
            data,
            width: a.b.width,
            path: a.b.path,
        },
        k: a.k,
        n: a.n,
    }
}

/// `c = A · B` for a block of rows of `A` (`[rows, k]`, any strides) and a
/// packed `B`, on the calling thread (for example inside another product's
/// epilogue, on a block of rows while it is in cache): the same bits as
/// [`matmul`]. Writes every element of `c` (`rows × n`) and returns it.
pub fn matmul_block_into<'c, T: Real>(
    a: MatRef<'_, T>,
    b: &Packed<T>,
    c: &'c mut [MaybeUninit<T>],
) -> &'c mut [T] {
    assert_eq!(a.cols, b.k, "matmul: inner dimensions differ");
    assert_eq!(c.len(), a.rows * b.n, "matmul: output has the wrong size");
    if c.is_empty() {
        // SAFETY: an empty slice has nothing to initialise.
        return unsafe { &mut *(c as *mut [MaybeUninit<T>] as *mut [T]) };
    }
    block_product(ASource::View(a), b.b.panels(), b.k, b.n, c, false)
}

/// `c += A · B` for a block of rows of `A` (`[rows, k]`, any strides) and a
/// packed `B`, on the calling thread: each sum in `c` (`rows × n`) is
/// continued term by term, the same bits as [`matmul_from_parts_then`] with
/// `c` as its initial sums (a product over earlier columns of a wider `A`
/// continued over these).
pub fn matmul_block_resume<T: Real>(a: MatRef<'_, T>, b: &Packed<T>, c: &mut [T]) {
    assert_eq!(a.cols, b.k, "matmul: inner dimensions differ");
    assert_eq!(c.len(), a.rows * b.n, "matmul: output has the wrong size");
    if c.is_empty() {
        return;
    }
    // SAFETY: block_product only reads `c`'s values (resumed sums) and
    // writes initialised ones.
    let cu = unsafe { as_slots(c) };
    block_product(ASource::View(a), b.b.panels(), b.k, b.n, cu, true);
}

/// `C = Aᵀ · B` for `A` `[r, m]` and `B` `[r, n]`: a reduction over the `r`
/// rows, done in fixed chunks of [`REDUCTION_CHUNK`] rows whose partials are
/// added in chunk order. Returns `[m, n]` row-major.
///
/// Element `(i, j)` is the same chain of fused multiply-adds
/// `s = A[p][i]·B[p][j] + s` whichever operand the kernel treats as the left
/// one (a fused multiply-add is exact before its single rounding, so the
/// order of its two factors changes no bit). The product is therefore run as
/// `(Bᵀ·A)ᵀ` when that wastes less of the register tile on padding (for
/// example `m` = 64 against the tile's 12 rows), and the small result
/// transposed.
pub fn matmul_tn<T: Real>(a: MatRef<'_, T>, b: MatRef<'_, T>) -> Vec<T> {
    assert_eq!(a.rows, b.rows, "matmul_tn: row counts differ");
    let (r, m, n) = (a.rows, a.cols, b.cols);
    if r == 0 || m == 0 || n == 0 {
        return vec![T::ZERO; m * n];
    }
    let path = kernel_path();
    let (mr, nr) = tile_shape::<T>(path);
    // Per row of the reduction: the multiply-adds the tiles do (padding
    // included), plus the values copied into the kernel's layout, weighted
    // as 32 multiply-adds each (measured order of magnitude): the left
    // operand is read in place when its rows are contiguous, the right one
    // is always packed.
    let cost = |l: MatRef<'_, T>, r: MatRef<'_, T>| {
        let (lp, rp) = (l.cols.div_ceil(mr) * mr, r.cols.div_ceil(nr) * nr);
        let packed = rp + if tn_in_place(path, l) { 0 } else { lp };
        lp * rp + 32 * packed
    };
    if cost(b, a) < cost(a, b) {
        let ct = tn_chunked(b, a);
        transposed(&ct, n, m)
    } else {
        tn_chunked(a, b)
    }
}

/// Whether [`tn_chunk`] reads the left operand `A` of `Aᵀ·B` in place: the
/// vector tiles read `MR` consecutive values of a row of `A` per term
/// (contiguous when its columns are), instead of a packed copy.
fn tn_in_place<T>(path: KernelPath, a: MatRef<'_, T>) -> bool {
    path != KernelPath::Baseline && a.col_stride == 1
}

/// `c` (`[rows, cols]` row-major) transposed, in tiles that stay in cache.
fn transposed<T: Real>(c: &[T], rows: usize, cols: usize) -> Vec<T> {
    const B: usize = 32;
    let mut out = Vec::with_capacity(rows * cols);
    let dst = &mut out.spare_capacity_mut()[..rows * cols];
    for i0 in (0..rows).step_by(B) {
        for j0 in (0..cols).step_by(B) {
            for i in i0..(i0 + B).min(rows) {
                for j in j0..(j0 + B).min(cols) {
                    dst[j * rows + i].write(c[i * cols + j]);
                }
            }
        }
    }
    // SAFETY: the tiles cover every (i, j) of the `rows × cols` result once,
    // so all `rows·cols` values were written.
    unsafe { out.set_len(rows * cols) };
    out
}

/// [`matmul_tn`] with `A` as the kernel's left operand.
fn tn_chunked<T: Real>(a: MatRef<'_, T>, b: MatRef<'_, T>) -> Vec<T> {
    let (r, m, n) = (a.rows, a.cols, b.cols);
    let chunks = r.div_ceil(REDUCTION_CHUNK);
    // With fewer chunks than tasks to keep the threads busy, each chunk's
    // output rows are split over the threads too (no effect on results).
    let split = chunks < 2 * rayon::current_num_threads();
    // Every chunk's partial, written in place in this thread's scratch.
    let mut scratch = take_scratch::<T>(PARTIALS);
    if scratch.len() < chunks * m * n {
        scratch.resize(chunks * m * n, T::ZERO);
    }
    let partials = &mut scratch[..chunks * m * n];
    // SAFETY: par_blocks_written's writers (tn_chunk) write values only.
    let slots = unsafe { as_slots(partials) };
    par_blocks_written(slots, m * n, &mut [(); 0], 0, |c, dst, _| {
        let r0 = c * REDUCTION_CHUNK;
        let rows = REDUCTION_CHUNK.min(r - r0);
        tn_chunk(a.rows(r0, rows), b.rows(r0, rows), dst, split)
    });
    // The partials added in chunk order, the first taken as is.
    let (total, rest) = partials.split_at_mut(m * n);
    if !rest.is_empty() {
        total.par_chunks_mut(4096).enumerate().for_each(|(i, out)| {
            let o = i * 4096;
            let len = out.len();
            for p in rest.chunks_exact(m * n) {
                for (acc, &v) in out.iter_mut().zip(&p[o..o + len]) {
                    *acc += v;
                }
            }
        });
    }
    let total = total.to_vec();
    put_scratch(PARTIALS, scratch);
    total
}

/// One chunk of [`tn_chunked`]: `out = Aᵀ · B` (`[m, n]`) for the chunk's
/// rows of `A` `[rows, m]` and `B` `[rows, n]`, in passes of [`KC`] rows,
/// each pass's sums resumed from the previous one's (exact). `A` is read in
/// place where [`tn_in_place`] allows (else packed in strips of `MR`), `B`
/// packed in panels of `NR` in this thread's scratch (for `Aᵀ·B` both are
/// copies of row segments), used while it is in cache. Writes every value of
/// `out` and returns it.
fn tn_chunk<'o, T: Real>(
    a: MatRef<'_, T>,
    b: MatRef<'_, T>,
    out: &'o mut [MaybeUninit<T>],
    split: bool,
) -> &'o mut [T] {
    let (rows, m, n) = (a.rows, a.cols, b.cols);
    debug_assert!(rows > 0 && out.len() == m * n);
    let path = kernel_path();
    let (mr, nr) = tile_shape::<T>(path);
    let mut scratch = take_scratch::<T>(PACK);
    for (pass, s0) in (0..rows).step_by(KC).enumerate() {
        let kc = KC.min(rows - s0);
        let in_place = tn_in_place(path, a);
        let a_len = if in_place {
            0
        } else {
            m.div_ceil(mr) * kc * mr
        };
        let b_len = n.div_ceil(nr) * kc * nr;
        if scratch.len() < a_len + b_len {
            scratch.resize(a_len + b_len, T::ZERO);
        }
        let (strips, rest) = scratch.split_at_mut(a_len);
        if !in_place {
            // SAFETY: pack_panels writes values only.
            let slots = unsafe { as_slots(strips) };
            pack_panels(a.rows(s0, kc), mr, slots);
        }
        // SAFETY: pack_panels writes values only.
        let slots = unsafe { as_slots(&mut rest[..b_len]) };
        pack_panels(b.rows(s0, kc), nr, slots);
        let (strips, panels) = (
            &*strips,
            Panels {
                data: &rest[..b_len],
                width: nr,
                path,
            },
        );
        // The first pass writes the output, the others resume its sums.
        let resume = pass > 0;
        if split {
            par_blocks_written(out, ROW_BLOCK * n, &mut [(); 0], 0, |blk, cb, _| {
                let o0 = blk * ROW_BLOCK;
                let a = if in_place {
                    ASource::Columns(a.rows(s0, kc).cols(o0, cb.len() / n).t())
                } else {
                    ASource::Strips {
                        data: &strips[o0 / mr * kc * mr..],
                        rows: cb.len() / n,
                    }
                };
                block_product(a, panels, kc, n, cb, resume)
            });
        } else {
            let a = if in_place {
                ASource::Columns(a.rows(s0, kc).t())
            } else {
                ASource::Strips {
                    data: strips,
                    rows: m,
                }
            };
            block_product(a, panels, kc, n, out, resume);
        }
    }
    put_scratch(PACK, scratch);
    // SAFETY: the first pass wrote every value of `out` (block_product and
    // par_blocks_written write their whole output).
    unsafe { &mut *(out as *mut [MaybeUninit<T>] as *mut [T]) }
}

/// Slot of the per-thread scratch that holds packed operands.
const PACK: usize = 0;
/// Slot of the per-thread scratch that holds a reduction's partials.
const PARTIALS: usize = 1;
/// Scratch vectors above this many bytes are freed after use, not kept.
const KEEP_BYTES: usize = 64 << 20;

thread_local! {
    /// Per-thread scratch for packed operands and partial sums, kept
    /// between calls so that they do not allocate, fault in and zero fresh
    /// pages every time (at most [`KEEP_BYTES`] each).
    static SCRATCH_F32: [std::cell::Cell<Vec<f32>>; 2] =
        const { [std::cell::Cell::new(Vec::new()), std::cell::Cell::new(Vec::new())] };
    /// The f64 counterpart of `SCRATCH_F32`.
    static SCRATCH_F64: [std::cell::Cell<Vec<f64>>; 2] =
        const { [std::cell::Cell::new(Vec::new()), std::cell::Cell::new(Vec::new())] };
}

/// This thread's scratch vector `slot` for `T` (stale contents), taken out
/// of its slot until [`put_scratch`]: a nested use on the same thread (a
/// parallel task run here while this one waits) gets an empty vector
/// instead.
fn take_scratch<T: Real>(slot: usize) -> Vec<T> {
    use std::any::Any;
    let mut v: Vec<T> = Vec::new();
    let any = &mut v as &mut dyn Any;
    if let Some(s) = any.downcast_mut::<Vec<f32>>() {
        *s = SCRATCH_F32.with(|c| c[slot].take());
    } else if let Some(s) = any.downcast_mut::<Vec<f64>>() {
        *s = SCRATCH_F64.with(|c| c[slot].take());
    }
    v
}

/// Give a scratch vector back to this thread's slot (keeping the larger
/// one when a nested use left one there; dropping one over
/// [`KEEP_BYTES`]).
fn put_scratch<T: Real>(slot: usize, mut v: Vec<T>) {
    use std::any::Any;
    fn keep<U>(cell: &std::cell::Cell<Vec<U>>, v: Vec<U>) {
        let old = cell.take();
        let v = if old.capacity() > v.capacity() {
            old
        } else {
            v
        };
        if v.capacity() * std::mem::size_of::<U>() <= KEEP_BYTES {
            cell.set(v);
        }
    }
    let any = &mut v as &mut dyn Any;
    if let Some(s) = any.downcast_mut::<Vec<f32>>() {
        let v = std::mem::take(s);
        SCRATCH_F32.with(|c| keep(&c[slot], v));
    } else if let Some(s) = any.downcast_mut::<Vec<f64>>() {
        let v = std::mem::take(s);
        SCRATCH_F64.with(|c| keep(&c[slot], v));
    }
}

/// Column sums of a row-major `[r, n]` matrix, reduced over fixed chunks of
/// [`REDUCTION_CHUNK`] rows (row order inside a chunk, chunk order outside).
pub fn column_sums<T: Real>(g: &[T], r: usize, n: usize) -> Vec<T> {
    assert!(g.len() >= r * n, "column_sums: data too short");
    if r == 0 || n == 0 {
        return vec![T::ZERO; n];
    }
    let chunks = r.div_ceil(REDUCTION_CHUNK);
    let partials: Vec<Vec<T>> = (0..chunks)
        .into_par_iter()
        .map(|c| {
            let r0 = c * REDUCTION_CHUNK;
            let r1 = (r0 + REDUCTION_CHUNK).min(r);
            let mut s = vec![T::ZERO; n];
            for row in g[r0 * n..r1 * n].chunks_exact(n) {
                for (acc, &v) in s.iter_mut().zip(row) {
                    *acc += v;
                }
            }
            s
        })
        .collect();
    sum_in_order(partials)
}

/// `p0 + p1 + ...` element-wise, in order (the first partial is taken as is).
fn sum_in_order<T: Real>(mut partials: Vec<Vec<T>>) -> Vec<T> {
    let rest = partials.split_off(1);
    let mut total = partials.pop().expect("at least one partial");
    if rest.is_empty() {
        return total;
    }
    total.par_chunks_mut(4096).enumerate().for_each(|(i, out)| {
        let o = i * 4096;
        let len = out.len();
        for p in &rest {
            for (acc, &v) in out.iter_mut().zip(&p[o..o + len]) {
                *acc += v;
            }
        }
    });
    total
}

/// `B` `[k, n]` copied into column panels of `width` columns, the tile
/// width of the kernel that reads them (see [`pack_panels`]).
struct PackedB<T> {
    data: Vec<T>,
    width: usize,
    /// The kernel the panels are laid out for.
    path: KernelPath,
}

impl<T> PackedB<T> {
    /// The panels, borrowed.
    fn panels(&self) -> Panels<'_, T> {
        Panels {
            data: &self.data,
            width: self.width,
            path: self.path,
        }
    }
}

/// Packed column panels of `B` as the micro-kernel driver reads them.
#[derive(Clone, Copy)]
struct Panels<'a, T> {
    /// Panel `j` holds rows `0..k` of columns `j·width..`, `width` a row.
    data: &'a [T],
    /// The panel width: the tile width `NR` of the kernel below.
    width: usize,
    /// The kernel the panels are laid out for.
    path: KernelPath,
}

/// Pack `B` for the kernel that runs now ([`kernel_path`]).
fn pack_b<T: Real>(b: MatRef<'_, T>) -> PackedB<T> {
    pack_b_for(b, kernel_path())
}

/// [`pack_b`] for the kernel `path`.
fn pack_b_for<T: Real>(b: MatRef<'_, T>, path: KernelPath) -> PackedB<T> {
    let width = tile_shape::<T>(path).1;
    let len = b.cols.div_ceil(width) * b.rows * width;
    let data = vec_written_by(len, |buf| {
        pack_panels(b, width, buf);
        // SAFETY: pack_panels wrote every value of `buf`.
        unsafe { &mut *(buf as *mut [MaybeUninit<T>] as *mut [T]) }
    });
    PackedB { data, width, path }
}

/// `M` `[k, c]` copied into `dst` as column panels `width` wide: panel `j`
/// holds rows `0..k` of columns `j·width..`, each row `width` wide, at
/// `j·k·width + p·width + q`, so a tile streams one contiguous block. Every
/// value of `dst` (`c.div_ceil(width)·k·width` long) is written, the last
/// panel's columns past `c` with zeros (read by the tile, never stored).
///
/// Used for `B` (panels `NR` wide) and, in `Aᵀ·B`, for `A` (strips `MR`
/// wide: row `i` of `Aᵀ` is column `i` of `A`). Reads `M` in its own memory
/// order: rows of a row-major `M` (each row split over the panels), columns
/// of a transposed view.
fn pack_panels<T: Real>(b: MatRef<'_, T>, width: usize, dst: &mut [MaybeUninit<T>]) {
    let (k, n) = (b.rows, b.cols);
    assert_eq!(dst.len(), n.div_ceil(width) * k * width, "pack: wrong size");
    if k == 0 || n == 0 {
        return;
    }
    if b.col_stride == 1 {
        // The kernels' widths as fixed-size moves.
        match width {
            4 => pack_rows::<T, 4>(b, dst),
            6 => pack_rows::<T, 6>(b, dst),
            8 => pack_rows::<T, 8>(b, dst),
            12 => pack_rows::<T, 12>(b, dst),
            16 => pack_rows::<T, 16>(b, dst),
            32 => pack_rows::<T, 32>(b, dst),
            _ => unreachable!("no kernel has panels {width} wide"),
        }
    } else {
        // Column by column (contiguous in a transposed view), each written
        // down its panel (which stays in cache).
        for (p, panel) in dst.chunks_exact_mut(k * width).enumerate() {
            let j0 = p * width;
            let w = width.min(n - j0);
            for q in 0..w {
                let c0 = (j0 + q) * b.col_stride;
                for (kk, d) in panel.chunks_exact_mut(width).enumerate() {
                    d[q].write(b.data[kk * b.row_stride + c0]);
                }
            }
            if w < width {
                for d in panel.chunks_exact_mut(width) {
                    d[w..].iter_mut().for_each(|z| {
                        z.write(T::ZERO);
                    });
                }
            }
        }
    }
}

/// [`pack_panels`] of a matrix with contiguous rows into panels `W` wide,
/// full panels as fixed-size moves, in blocks of rows: the panels of a
/// `KC`-row pass start a multiple of 4 KiB apart, so writing one row to
/// every panel in turn would put all the writes in the same few cache sets
/// (measured: packing then cost as much as the arithmetic); a block of rows
/// (in cache) is written panel by panel instead, whole lines at a time.
#[inline(always)]
fn pack_rows<T: Real, const W: usize>(b: MatRef<'_, T>, dst: &mut [MaybeUninit<T>]) {
    const ROWS: usize = 16;
    let (k, n) = (b.rows, b.cols);
    let full = n / W;
    let tail = n - full * W;
    for k0 in (0..k).step_by(ROWS) {
        let k1 = (k0 + ROWS).min(k);
        for p in 0..full {
            for kk in k0..k1 {
                let s0 = kk * b.row_stride + p * W;
                copy_fixed::<T, W>(&mut dst[(p * k + kk) * W..], &b.data[s0..s0 + W]);
            }
        }
        if tail > 0 {
            for kk in k0..k1 {
                let s0 = kk * b.row_stride + full * W;
                let d = &mut dst[(full * k + kk) * W..(full * k + kk + 1) * W];
                for (z, &v) in d.iter_mut().zip(&b.data[s0..s0 + tail]) {
                    z.write(v);
                }
                d[tail..].iter_mut().for_each(|z| {
                    z.write(T::ZERO);
                });
            }
        }
    }
}

/// `dst.copy_from_slice(src)` for the short rows of packing, with the
/// common lengths as fixed-size moves (a `memmove` call per row of 6 or 16
/// values cost a third of a weight-gradient product).
#[inline(always)]
fn copy_short<T: Copy>(dst: &mut [MaybeUninit<T>], src: &[T]) {
    assert_eq!(dst.len(), src.len(), "copy: lengths differ");
    match dst.len() {
        4 => copy_fixed::<T, 4>(dst, src),
        6 => copy_fixed::<T, 6>(dst, src),
        8 => copy_fixed::<T, 8>(dst, src),
        12 => copy_fixed::<T, 12>(dst, src),
        16 => copy_fixed::<T, 16>(dst, src),
        32 => copy_fixed::<T, 32>(dst, src),
        _ => {
            for (d, &v) in dst.iter_mut().zip(src) {
                d.write(v);
            }
        }
    }
}

/// The first `N` values of `src` into the first `N` slots of `dst`, as one
/// fixed-size move (a few vector loads and stores).
#[inline(always)]
fn copy_fixed<T: Copy, const N: usize>(dst: &mut [MaybeUninit<T>], src: &[T]) {
    let (d, s) = (&mut dst[..N], &src[..N]);
    // SAFETY: both slices are N values long (the slicing above checks it),
    // and they do not overlap (`dst` is borrowed mutably, `src` shared);
    // `MaybeUninit<T>` has the layout of `T`.
    unsafe { std::ptr::copy_nonoverlapping(s.as_ptr(), d.as_mut_ptr().cast::<T>(), N) }
}

/// Where a block's rows of `A` come from.
#[derive(Clone, Copy)]
enum ASource<'a, T> {
    /// A view: full tiles of rows read in place by the vector kernels,
    /// other tiles gathered into a strip.
    View(MatRef<'a, T>),
    /// A view whose rows are adjacent (`row_stride` 1, columns apart: `Aᵀ`
    /// of a row-major `A`), full tiles read in place by the vector tiles
    /// (`MR` consecutive values per term), partial ones gathered.
    Columns(MatRef<'a, T>),
    /// Strips from [`pack_panels`] (`MR` wide), starting at
    /// the block's first tile.
    Strips { data: &'a [T], rows: usize },
}

/// Which compiled version of the micro-kernel runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum KernelPath {
    /// The AVX-512F tile (12 rows × 2 vectors).
    Avx512,
    /// The AVX2 + FMA tile (6 rows × 2 vectors).
    Avx2,
    /// The portable loop (4 × 8), the build target's baseline.
    Baseline,
}

/// The kernel version that runs now (all give identical results): the
/// widest this CPU supports, unless pinned by
/// [`fastmath::force_isa`](super::fastmath::force_isa).
pub fn kernel_path() -> KernelPath {
    match crate::kernels::fastmath::isa() {
        crate::kernels::fastmath::Isa::Avx512 => KernelPath::Avx512,
        crate::kernels::fastmath::Isa::Avx2 => KernelPath::Avx2,
        crate::kernels::fastmath::Isa::Baseline => KernelPath::Baseline,
    }
}

/// The tile shape `(MR, NR)` of a kernel path for `T`; `NR` is also the
/// width of the packed panels of `B`. AVX-512 has 32 vector registers: a
/// 12 × 2-vector tile keeps 24 sums in registers, so each loaded panel row
/// serves 12 rows of `A` (measured: the f32 MLP forward 6% faster than with
/// 6 rows); AVX2's 16 registers hold a 6 × 2-vector tile.
fn tile_shape<T: Real>(path: KernelPath) -> (usize, usize) {
    match (path, T::PRECISION) {
        (KernelPath::Avx512, Precision::F32) => (12, 32),
        (KernelPath::Avx512, Precision::F64) => (12, 16),
        (KernelPath::Avx2, Precision::F32) => (6, 16),
        (KernelPath::Avx2, Precision::F64) => (6, 8),
        (KernelPath::Baseline, _) => (4, 8),
    }
}

/// A tile routine: `out[r][q] = Σ_p A[r][p] · panel[p][q]` for `r < MR`,
/// `q < NR` (p ascending, from zero, one fused multiply-add per term), type-erased
/// pointers: `A[r][p]` is at `a + r·rs + p·cs` (elements), `panel` points at
/// the tile's `k × NR` panel, row `r` of the output is written at
/// `out + r·ldo`. With `resume`, the sums start from the values in `out`
/// instead of zero.
type TileFn = unsafe fn(*const u8, usize, usize, *const u8, usize, *mut u8, usize, bool);

/// One block of output rows: `c[rows, n] = a[rows, k] · B` (B packed), or
/// with `resume`, `c += a · B` continuing the sums already in `c` term by
/// term. Writes every element of `c` and returns it, initialised.
fn block_product<'c, T: Real>(
    a: ASource<'_, T>,
    b: Panels<'_, T>,
    k: usize,
    n: usize,
    c: &'c mut [MaybeUninit<T>],
    resume: bool,
) -> &'c mut [T] {
    debug_assert_eq!(b.width, tile_shape::<T>(b.path).1);
    #[cfg(target_arch = "x86_64")]
    {
        match (b.path, T::PRECISION) {
            (KernelPath::Avx512, Precision::F32) => {
                block_body::<T, 12, 32>(a, b, k, n, c, resume, Some(simd::f32_avx512))
            }
            (KernelPath::Avx512, Precision::F64) => {
                block_body::<T, 12, 16>(a, b, k, n, c, resume, Some(simd::f64_avx512))
            }
            (KernelPath::Avx2, Precision::F32) => {
                block_body::<T, 6, 16>(a, b, k, n, c, resume, Some(simd::f32_avx2))
            }
            (KernelPath::Avx2, Precision::F64) => {
                block_body::<T, 6, 8>(a, b, k, n, c, resume, Some(simd::f64_avx2))
            }
            (KernelPath::Baseline, _) => block_body::<T, 4, 8>(a, b, k, n, c, resume, None),
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    block_body::<T, 4, 8>(a, b, k, n, c, resume, None);
    // SAFETY: block_body wrote every element of `c` (every (row, column)
    // lies in exactly one tile, and each tile is stored in full).
    unsafe { &mut *(c as *mut [MaybeUninit<T>] as *mut [T]) }
}

/// Inner-dimension block of the micro-kernel driver: a tile sums `KC`
/// terms, stores its running sums, and the next block starts from them.
/// Storing and reloading an f32/f64 sum is exact, so this changes no bit; it
/// keeps the tile's slice of `B` (`KC × NR`) and of `A` in L1 when `k` is
/// large (the weight gradient's chunks of [`REDUCTION_CHUNK`] rows).
const KC: usize = 256;

/// The micro-kernel driver for `B` packed in panels `NR` wide; `tile`
/// (matching `T`, `MR` and `NR`) is the vector version, `None` the portable
/// loop.
#[inline(always)]
fn block_body<T: Real, const MR: usize, const NR: usize>(
    a: ASource<'_, T>,
    b: Panels<'_, T>,
    k: usize,
    n: usize,
    c: &mut [MaybeUninit<T>],
    resume_first: bool,
    simd: Option<TileFn>,
) {
    let rows = match a {
        ASource::View(v) | ASource::Columns(v) => v.rows,
        ASource::Strips { rows, .. } => rows,
    };
    let a_src = a;
    debug_assert_eq!(c.len(), rows * n);
    debug_assert_eq!(b.width, NR);
    // The vector kernels read full blocks of MR rows of A in place; the
    // portable loop and the last, partial block read a k-major strip:
    // strip[p*MR + r] = A[i+r, k0+p], missing rows zero. Same products, same
    // order: the same bits either way.
    let kc_max = KC.min(k).max(1);
    // Allocated when a tile first needs a gather (most products never do).
    let mut strip: Vec<T> = Vec::new();
    let mut k0 = 0;
    loop {
        let kc = kc_max.min(k - k0);
        // Later blocks continue the sums stored by the earlier ones.
        let resume = resume_first || k0 > 0;
        // Full tiles with A read in place run panel by panel: each panel of
        // B (kc × NR) stays in L1 while the block's row tiles pass over it,
        // instead of every row tile streaming all the panels from L2. The
        // loop below then does only the partial tiles. Each tile is the
        // same computation either way (same bits).
        let (full_rows, full_cols) = (rows / MR * MR, n / NR * NR);
        // A of row tile i: (pointer, row stride, column stride).
        let tile_a = |i: usize| -> Option<(*const T, usize, usize)> {
            match a {
                ASource::Columns(v) => {
                    Some((v.data[i + k0 * v.col_stride..].as_ptr(), 1, v.col_stride))
                }
                ASource::View(v) if v.row_stride != 1 => Some((
                    v.data[i * v.row_stride + k0 * v.col_stride..].as_ptr(),
                    v.row_stride,
                    v.col_stride,
                )),
                ASource::Strips { data, .. } => {
                    Some((data[(i / MR) * k * MR + k0 * MR..].as_ptr(), 1, MR))
                }
                _ => None,
            }
        };
        let panel_major = match simd {
            Some(f) if kc > 0 && full_rows > 0 && tile_a(0).is_some() => {
                for j in (0..full_cols).step_by(NR) {
                    let p0 = (j / NR) * k * NR + k0 * NR;
                    let bp = &b.data[p0..p0 + kc * NR];
                    for i in (0..full_rows).step_by(MR) {
                        let ap = tile_a(i).expect("checked above");
                        // SAFETY: see run_tile; A of a full row tile, the
                        // tile's panel, the full tile of `c` at (i, j).
                        unsafe {
                            run_tile(
                                f,
                                ap,
                                bp,
                                kc,
                                c.as_mut_ptr().add(i * n + j).cast(),
                                n,
                                resume,
                            )
                        };
                    }
                }
                true
            }
            _ => false,
        };
        let mut i = 0;
        while i < rows {
            let mr = MR.min(rows - i);
            // A transposed view (the weight gradient's `Gᵀ`) has each A
            // column contiguous but its rows far apart: gathering the strip
            // once per row of tiles is cheaper than the strided reads.
            let (a, packed) = match a {
                ASource::View(v) => (v, None),
                ASource::Columns(v) => (v, None),
                ASource::Strips { data, .. } => {
                    let s0 = (i / MR) * k * MR + k0 * MR;
                    (MatRef::row_major(&[], 0, 0), Some(&data[s0..s0 + kc * MR]))
                }
            };
            let in_place = a.row_stride != 1 || matches!(a_src, ASource::Columns(_));
            let direct = simd.is_some() && mr == MR && kc > 0 && in_place && packed.is_none();
            if !direct && packed.is_none() && strip.is_empty() {
                strip = vec![T::ZERO; kc_max * MR];
            } else if mr < MR && packed.is_none() {
                strip.fill(T::ZERO);
            }
            if direct || packed.is_some() {
                // No gather.
            } else if a.row_stride == 1 {
                // Columns of A are contiguous (a transposed view).
                for (p, dst) in strip[..kc * MR].chunks_exact_mut(MR).enumerate() {
                    let s0 = (k0 + p) * a.col_stride + i;
                    // SAFETY: copy_short writes values only.
                    let slots = unsafe { as_slots(dst) };
                    copy_short(&mut slots[..mr], &a.data[s0..s0 + mr]);
                }
            } else {
                for r in 0..mr {
                    let s0 = (i + r) * a.row_stride + k0 * a.col_stride;
                    for (p, dst) in strip[..kc * MR].chunks_exact_mut(MR).enumerate() {
                        dst[r] = a.data[s0 + p * a.col_stride];
                    }
                }
            }
            let mut j = 0;
            while j < n {
                let nr = NR.min(n - j);
                let panel = j / NR;
                let p0 = panel * k * NR + k0 * NR;
                let bp = &b.data[p0..p0 + kc * NR];
                let full = mr == MR && nr == NR;
                if panel_major && full {
                    // Done above.
                    j += NR;
                    continue;
                }
                // A for the vector routine: read in place (MR full rows of
                // the view from column k0, or the tile's packed strip), or
                // the gathered strip.
                let ap = if direct || packed.is_some() {
                    tile_a(i).expect("a view with rows apart, or strips")
                } else {
                    (strip.as_ptr(), 1, MR)
                };
                // Full tiles of the vector path are summed in place in `c`
                // (no scratch to set up); the others in `acc`.
                if let (Some(f), true, true) = (simd, full, kc > 0) {
                    // SAFETY: see run_tile; the full tile of `c` at (i, j).
                    unsafe {
                        run_tile(
                            f,
                            ap,
                            bp,
                            kc,
                            c.as_mut_ptr().add(i * n + j).cast(),
                            n,
                            resume,
                        )
                    };
                    j += NR;
                    continue;
                }
                let mut acc = [[T::ZERO; NR]; MR];
                if resume {
                    for (r, row) in acc.iter_mut().enumerate().take(mr) {
                        for (q, v) in row.iter_mut().enumerate().take(nr) {
                            // SAFETY: written by the previous block.
                            *v = unsafe { c[(i + r) * n + j + q].assume_init() };
                        }
                    }
                }
                match simd {
                    // SAFETY: see run_tile; `acc` (NR values a row) as the
                    // output, loaded from `c` above when `resume`.
                    Some(f) if kc > 0 => unsafe {
                        run_tile(f, ap, bp, kc, acc.as_mut_ptr().cast(), NR, resume)
                    },
                    _ => tile::<T, MR, NR>(packed.unwrap_or(&strip), bp, kc, &mut acc),
                }
                for r in 0..mr {
                    let dst = &mut c[(i + r) * n + j..(i + r) * n + j + nr];
                    for (d, &v) in dst.iter_mut().zip(&acc[r][..nr]) {
                        d.write(v);
                    }
                }
                j += NR;
            }
            i += MR;
        }
        k0 += kc;
        if k0 >= k {
            break;
        }
    }
}

/// Run the vector tile routine `f` (type-erasing its arguments).
///
/// # Safety
/// `f` was chosen for this CPU, for `T` and for the tile shape `(MR, NR)`
/// of the driver; `a = (pointer, row stride, column stride)` addresses MR
/// rows of `kc` values of A (MR full rows of a view read in place from the
/// block's column k0, whose strides keep every element inside the view's
/// data, or a strip of kc·MR values); `panel` holds the kc·NR values the
/// tile reads; `out` is the MR × NR output tile, rows `ldo` apart (a full
/// tile of `c`, or the `acc` scratch), holding the running sums when
/// `resume`.
unsafe fn run_tile<T>(
    f: TileFn,
    a: (*const T, usize, usize),
    panel: &[T],
    kc: usize,
    out: *mut T,
    ldo: usize,
    resume: bool,
) {
    let (ap, rs, cs) = a;
    // SAFETY: the caller guarantees what `f` requires (see `# Safety`):
    // `f` suits this CPU, `T` and the tile shape, and every pointer
    // addresses the values the tile reads and writes.
    unsafe {
        f(
            ap as *const u8,
            rs,
            cs,
            panel.as_ptr() as *const u8,
            kc,
            out as *mut u8,
            ldo,
            resume,
        )
    }
}

/// `acc[r][q] += Σ_p strip[p][r] · panel[p][q]`, p ascending, one term at a
/// time fused onto the running sum. Rows or columns beyond the matrix read zeros
/// (padding) and are not stored.
#[inline(always)]
fn tile<T: Real, const MR: usize, const NR: usize>(
    strip: &[T],
    panel: &[T],
    k: usize,
    acc: &mut [[T; NR]; MR],
) {
    for (av, bv) in strip[..k * MR]
        .chunks_exact(MR)
        .zip(panel[..k * NR].chunks_exact(NR))
    {
        for r in 0..MR {
            let x = av[r];
            for q in 0..NR {
                acc[r][q] = x.mul_add(bv[q], acc[r][q]);
            }
        }
    }
}

/// Vector tiles: the same arithmetic as [`tile`], lane by lane (one fused
/// multiply-add per term, rounded once), so every path gives the same bits.
#[cfg(target_arch = "x86_64")]
mod simd {
    use std::arch::x86_64::*;

    macro_rules! tile_fn {
        ($name:ident, $feat:literal, $t:ty, $vec:ty, $lanes:expr, $mr:expr, $zero:ident, $load:ident,
         $set1:ident, $fma:ident, $store:ident) => {
            /// # Safety
            /// The CPU supports the feature; pointers as documented on `TileFn`.
            #[allow(clippy::too_many_arguments)]
            #[target_feature(enable = $feat)]
            pub unsafe fn $name(
                a: *const u8,
                rs: usize,
                cs: usize,
                panel: *const u8,
                k: usize,
                out: *mut u8,
                ldo: usize,
                resume: bool,
            ) {
                // SAFETY: the caller guarantees the CPU feature and that the
                // pointers address what `TileFn` documents: MR rows of `k`
                // values of A (`rs`, `cs` apart), `k` panel rows of 2·lanes
                // values, and an MR × 2·lanes output tile, rows `ldo` apart.
                unsafe {
                    let a = a as *const $t;
                    let out = out as *mut $t;
                    let mut panel = panel as *const $t;
                    let mut c: [[$vec; 2]; $mr] = [[$zero(); 2]; $mr];
                    if resume {
                        for r in 0..$mr {
                            c[r][0] = $load(out.add(r * ldo));
                            c[r][1] = $load(out.add(r * ldo + $lanes));
                        }
                    }
                    let rows: [*const $t; $mr] = core::array::from_fn(|r| a.add(r * rs));
                    let mut p = 0;
                    for _ in 0..k {
                        let b0 = $load(panel);
                        let b1 = $load(panel.add($lanes));
                        for r in 0..$mr {
                            let x = $set1(*rows[r].add(p));
                            c[r][0] = $fma(x, b0, c[r][0]);
                            c[r][1] = $fma(x, b1, c[r][1]);
                        }
                        p = p.wrapping_add(cs);
                        panel = panel.add(2 * $lanes);
                    }
                    for r in 0..$mr {
                        $store(out.add(r * ldo), c[r][0]);
                        $store(out.add(r * ldo + $lanes), c[r][1]);
                    }
                }
            }
        };
    }

    tile_fn!(
        f32_avx512,
        "avx512f",
        f32,
        __m512,
        16,
        12,
        _mm512_setzero_ps,
        _mm512_loadu_ps,
        _mm512_set1_ps,
        _mm512_fmadd_ps,
        _mm512_storeu_ps
    );
    tile_fn!(
        f64_avx512,
        "avx512f",
        f64,
        __m512d,
        8,
        12,
        _mm512_setzero_pd,
        _mm512_loadu_pd,
        _mm512_set1_pd,
        _mm512_fmadd_pd,
        _mm512_storeu_pd
    );
    tile_fn!(
        f32_avx2,
        "avx2,fma",
        f32,
        __m256,
        8,
        6,
        _mm256_setzero_ps,
        _mm256_loadu_ps,
        _mm256_set1_ps,
        _mm256_fmadd_ps,
        _mm256_storeu_ps
    );
    tile_fn!(
        f64_avx2,
        "avx2,fma",
        f64,
        __m256d,
        4,
        6,
        _mm256_setzero_pd,
        _mm256_loadu_pd,
        _mm256_set1_pd,
        _mm256_fmadd_pd,
        _mm256_storeu_pd
    );
}

/// Plain, slow, obviously correct versions of the products above, with the
/// same summation order by design: the fast ones must match them bit for bit.
pub mod reference {
    use super::{MatRef, REDUCTION_CHUNK};
    use crate::math::Real;

    /// `C = A · B`, each element summed over k ascending from zero.
    pub fn matmul<T: Real>(a: MatRef<'_, T>, b: MatRef<'_, T>) -> Vec<T> {
        let (m, k, n) = (a.rows, a.cols, b.cols);
        let mut c = vec![T::ZERO; m * n];
        for i in 0..m {
            for j in 0..n {
                let mut s = T::ZERO;
                for p in 0..k {
                    s = a.at(i, p).mul_add(b.at(p, j), s);
                }
                c[i * n + j] = s;
            }
        }
        c
    }

    /// `C = Aᵀ · B` with the chunked reduction over rows.
    pub fn matmul_tn<T: Real>(a: MatRef<'_, T>, b: MatRef<'_, T>) -> Vec<T> {
        let (r, m, n) = (a.rows, a.cols, b.cols);
        let mut total = vec![T::ZERO; m * n];
        for (ci, r0) in (0..r).step_by(REDUCTION_CHUNK).enumerate() {
            let r1 = (r0 + REDUCTION_CHUNK).min(r);
            for i in 0..m {
                for j in 0..n {
                    let mut s = T::ZERO;
                    for p in r0..r1 {
                        s = a.at(p, i).mul_add(b.at(p, j), s);
                    }
                    if ci == 0 {
                        total[i * n + j] = s;
                    } else {
                        total[i * n + j] += s;
                    }
                }
            }
        }
        total
    }

    /// Column sums with the chunked reduction over rows.
    pub fn column_sums<T: Real>(g: &[T], r: usize, n: usize) -> Vec<T> {
        let mut total = vec![T::ZERO; n];
        for (ci, r0) in (0..r).step_by(REDUCTION_CHUNK).enumerate() {
            let r1 = (r0 + REDUCTION_CHUNK).min(r);
            for j in 0..n {
                let mut s = T::ZERO;
                for p in r0..r1 {
                    s += g[p * n + j];
                }
                if ci == 0 {
                    total[j] = s;
                } else {
                    total[j] += s;
                }
            }
        }
        total
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::Rng;

    fn random<T: Real>(seed: u64, len: usize) -> Vec<T> {
        let mut r = Rng::new(seed);
        (0..len)
            .map(|_| T::from_f64(r.uniform_range(-1.0, 1.0)))
            .collect()
    }

    fn bits<T: Real>(v: &[T]) -> Vec<u64> {
        v.iter().map(|x| x.bits()).collect()
    }

    fn check_all<T: Real>() {
        // Odd sizes exercise every remainder path of the tiles.
        for &(m, k, n) in &[
            (1, 1, 1),
            (7, 5, 3),
            (13, 37, 33),
            (50, 64, 70),
            (97, 93, 256),
            // k over the inner block KC: sums resumed from the stored tile.
            (19, 2 * KC + 77, 37),
        ] {
            let a = random::<T>(1 + m as u64, m * k);
            let b = random::<T>(2 + n as u64, k * n);
            let am = MatRef::row_major(&a, m, k);
            let bm = MatRef::row_major(&b, k, n);
            assert_eq!(
                bits(&matmul(am, bm)),
                bits(&reference::matmul(am, bm)),
                "nn {m}x{k}x{n}"
            );
            // Transposed and column-sliced views.
            let bt = MatRef::row_major(&b, n, k).t();
            assert_eq!(bits(&matmul(am, bt)), bits(&reference::matmul(am, bt)));
            if n > 2 {
                let bs = bm.cols(1, n - 2);
                assert_eq!(bits(&matmul(am, bs)), bits(&reference::matmul(am, bs)));
            }
        }
        for &(r, m, n) in &[(1, 3, 2), (700, 5, 9), (1500, 33, 40)] {
            let a = random::<T>(3, r * m);
            let b = random::<T>(4, r * n);
            let am = MatRef::row_major(&a, r, m);
            let bm = MatRef::row_major(&b, r, n);
            assert_eq!(
                bits(&matmul_tn(am, bm)),
                bits(&reference::matmul_tn(am, bm)),
                "tn {r}x{m}x{n}"
            );
            assert_eq!(
                bits(&column_sums(&b, r, n)),
                bits(&reference::column_sums(&b, r, n))
            );
        }
    }

    /// Every kernel path this CPU has (the portable one always), then the
    /// automatic choice. Results are the same on all paths by design, so
    /// pinning the path here cannot change what other tests compute.
    fn on_every_path(check: impl Fn()) {
        let _isa = crate::kernels::fastmath::isa_test_lock();
        use crate::kernels::fastmath::{force_isa, Isa};
        for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
            if force_isa(Some(isa)) {
                check();
            }
        }
        force_isa(None);
        check();
    }

    #[test]
    fn fast_products_match_reference_bits_f32() {
        on_every_path(check_all::<f32>);
    }

    #[test]
    fn fast_products_match_reference_bits_f64() {
        on_every_path(check_all::<f64>);
    }

    /// `A` `[rows, cols]` as a row-major matrix, a transposed view of its
    /// transpose, and a view with padding columns (row stride above the
    /// width): the same matrix in three layouts.
    fn layouts<T: Real>(seed: u64, rows: usize, cols: usize) -> [(Vec<T>, MatRef<'static, T>); 3] {
        let plain = random::<T>(seed, rows * cols);
        let mut tr = vec![T::ZERO; rows * cols];
        let mut padded = random::<T>(seed + 1, rows * (cols + 3));
        for i in 0..rows {
            for j in 0..cols {
                tr[j * rows + i] = plain[i * cols + j];
                padded[i * (cols + 3) + 2 + j] = plain[i * cols + j];
            }
        }
        let leak = |v: Vec<T>| -> &'static [T] { Box::leak(v.into_boxed_slice()) };
        let (p, t, d) = (leak(plain.clone()), leak(tr.clone()), leak(padded.clone()));
        [
            (plain, MatRef::row_major(p, rows, cols)),
            (tr, MatRef::row_major(t, cols, rows).t()),
            (padded, MatRef::row_major(d, rows, cols + 3).cols(2, cols)),
        ]
    }

    /// Both products on shapes around the tile sizes (`m < MR`, `m`, `n`
    /// and `k` off the tile multiples, `k` below and above `KC`, reductions
    /// over one and several chunks, both orientations of `Aᵀ·B`) and on
    /// row-major, transposed and strided views: the same bits as the plain
    /// scalar loops.
    fn check_shapes_and_views<T: Real>() {
        for &(m, k, n) in &[
            (5, 300, 40),
            (11, 64, 64),
            (64, 64, 64),
            (61, 512, 64),
            (37, KC - 1, 33),
            (25, KC + 1, 97),
            (1, 3, 31),
        ] {
            for (_, a) in layouts::<T>(20 + m as u64, m, k) {
                for (_, b) in layouts::<T>(30 + n as u64, k, n) {
                    assert_eq!(
                        bits(&matmul(a, b)),
                        bits(&reference::matmul(a, b)),
                        "nn {m}x{k}x{n} strides {:?} {:?}",
                        (a.row_stride, a.col_stride),
                        (b.row_stride, b.col_stride)
                    );
                }
            }
        }
        for &(r, m, n) in &[
            (100, 7, 33),
            (300, 64, 512),
            (300, 512, 64),
            (513, 5, 70),
            (2 * REDUCTION_CHUNK + KC + 3, 13, 37),
            (REDUCTION_CHUNK, 64, 64),
            (700, 93, 12),
            // More chunks than twice the threads of a small machine: chunks
            // not split over output rows.
            (5 * REDUCTION_CHUNK + 7, 29, 40),
        ] {
            for (_, a) in layouts::<T>(40 + m as u64, r, m) {
                for (_, b) in layouts::<T>(50 + n as u64, r, n) {
                    assert_eq!(
                        bits(&matmul_tn(a, b)),
                        bits(&reference::matmul_tn(a, b)),
                        "tn {r}x{m}x{n} strides {:?} {:?}",
                        (a.row_stride, a.col_stride),
                        (b.row_stride, b.col_stride)
                    );
                }
            }
        }
    }

    #[test]
    fn odd_shapes_and_views_match_reference_bits() {
        on_every_path(check_shapes_and_views::<f32>);
        on_every_path(check_shapes_and_views::<f64>);
    }

    /// `[A₁ | A₂]·[B₁; B₂]` from the blocks equals the product of the
    /// concatenated matrices, bit for bit (a sum resumed across blocks).
    fn check_parts<T: Real>() {
        for &(m, k1, k2, n) in &[
            (7, 5, 3, 9),
            (50, 93, 128, 64),
            (97, 0, 40, 33),
            (13, KC + 44, 10, 40),
        ] {
            let k = k1 + k2;
            let a = random::<T>(8 + m as u64, m * k);
            let b = random::<T>(9 + n as u64, k * n);
            let (am, bm) = (MatRef::row_major(&a, m, k), MatRef::row_major(&b, k, n));
            let block = |c0: usize, w: usize| -> Vec<T> {
                a.chunks_exact(k.max(1))
                    .flat_map(|r| r[c0..c0 + w].to_vec())
                    .collect()
            };
            let (a1, a2) = (block(0, k1), block(k1, k2));
            let parts = [
                (MatRef::row_major(&a1, m, k1), bm.rows(0, k1)),
                (MatRef::row_major(&a2, m, k2), bm.rows(k1, k2)),
            ];
            assert_eq!(
                bits(&matmul_parts_then::<T, T, _>(
                    &parts,
                    &mut [],
                    0,
                    |_, _, _| {}
                )),
                bits(&matmul(am, bm)),
                "parts {m}x({k1}+{k2})x{n}"
            );
        }
    }

    /// Sums started from a column block of a wider product over the first
    /// columns of `A` and continued over the rest give the same bits as
    /// the product over all the columns (also with no further columns).
    fn check_from<T: Real>() {
        for &(m, k1, k2, n, wide) in &[
            (7, 5, 3, 9, 20),
            (130, 93, 128, 64, 512),
            (97, 40, 0, 33, 40),
            (13, KC + 44, 10, 40, 45),
        ] {
            let k = k1 + k2;
            let a = random::<T>(10 + m as u64, m * k);
            let b = random::<T>(11 + n as u64, k * n);
            let (am, bm) = (MatRef::row_major(&a, m, k), MatRef::row_major(&b, k, n));
            // A wider product over the first k1 columns: B's first k1 rows
            // as columns 3..3+n of a [k1, wide] matrix.
            let c0 = 3.min(wide - n);
            let mut bw = random::<T>(12, k1 * wide);
            for p in 0..k1 {
                for q in 0..n {
                    bw[p * wide + c0 + q] = b[p * n + q];
                }
            }
            let first = matmul(am.cols(0, k1), MatRef::row_major(&bw, k1, wide));
            let init = MatRef::row_major(&first, m, wide).cols(c0, n);
            let got = matmul_from_parts_then::<T, T, _>(
                Some(init),
                &[(am.cols(k1, k2), bm.rows(k1, k2))],
                &mut [],
                0,
                |_, _, _| {},
            );
            assert_eq!(
                bits(&got),
                bits(&matmul(am, bm)),
                "from {m}x({k1}+{k2})x{n}"
            );
        }
    }

    #[test]
    fn products_from_initial_sums_match_the_whole_product() {
        on_every_path(check_from::<f32>);
        on_every_path(check_from::<f64>);
    }

    #[test]
    fn products_from_column_blocks_match_the_concatenated_product() {
        on_every_path(check_parts::<f32>);
        on_every_path(check_parts::<f64>);
    }

    /// The sums are fused: `1·(−1) + (1+ε)(1−ε)` is exactly `−ε²` with a
    /// fused multiply-add, but 0 with a rounded product (`1 − ε²` rounds
    /// to 1), on every path and in the reference.
    #[test]
    fn each_term_is_a_fused_multiply_add() {
        let e = f32::EPSILON;
        let a = [1.0f32, 1.0 + e];
        let b = [-1.0f32, 1.0 - e];
        let (am, bm) = (MatRef::row_major(&a, 1, 2), MatRef::row_major(&b, 2, 1));
        assert_eq!(reference::matmul(am, bm), vec![-e * e]);
        on_every_path(|| assert_eq!(matmul(am, bm), vec![-e * e]));
    }

    #[test]
    fn reference_matches_f64_dot_products() {
        // Independent check of the reference itself on small integers (exact).
        let a: Vec<f64> = (0..6).map(|v| v as f64).collect(); // [[0,1,2],[3,4,5]]
        let b: Vec<f64> = (0..6).map(|v| (v as f64) - 2.0).collect(); // [[-2,-1],[0,1],[2,3]]
        let c = reference::matmul(MatRef::row_major(&a, 2, 3), MatRef::row_major(&b, 3, 2));
        assert_eq!(c, vec![4.0, 7.0, 4.0, 16.0]);
    }

    #[test]
    fn products_are_identical_across_thread_counts() {
        let (r, k, n) = (1300, 40, 70);
        let a = random::<f32>(5, r * k);
        let b = random::<f32>(6, k * n);
        let g = random::<f32>(7, r * n);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| {
                let am = MatRef::row_major(&a, r, k);
                let c = matmul(am, MatRef::row_major(&b, k, n));
                let w = matmul_tn(MatRef::row_major(&g, r, n), am);
                let s = column_sums(&g, r, n);
                (bits(&c), bits(&w), bits(&s))
            })
        };
        let one = run(1);
        assert_eq!(one, run(2));
        assert_eq!(one, run(3));
    }
}
