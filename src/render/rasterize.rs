//! Per-pixel forward blending (Inria `renderCUDA`, plus the depth output of
//! the fork the D-3DGS paper uses).
//!
//! Each pixel walks its tile's sorted list front to back:
//! `power = −0.5(A dx² + C dy²) − B dx dy` with `d = centre − pixel`; skip if
//! `power > 0`; `alpha = min(0.99, o·exp(power))`; skip if `alpha < 1/255`
//! (the constant `1/255` evaluated in `T`); stop, without blending, when
//! `T·(1 − alpha) < 1e-4`; otherwise `C += (c·alpha)·T`, `D += (z·alpha)·T`,
//! `T ← T·(1 − alpha)`. Output `C + T·bg`, `D` (no background), final `T` and
//! the 1-based position of the last blended entry.
//!
//! `exp` is [`crate::kernels::fastmath::exp`]: in f32 the crate's vectorisable
//! `exp_f32` (at most 1 ulp from the correctly rounded value, measured against
//! libm by its tests), in f64 the pinned libm.
//!
//! ## Vectorisation
//! A row of a 16×16 tile is one group of [`LANES`] pixels. The row walks the
//! tile's list once; each pixel (lane) applies exactly the rules above, with
//! the skips and its stop expressed as lane masks, and the walk ends when
//! every lane has stopped. Every lane does the scalar operations of one pixel
//! in the scalar order (IEEE additions, multiplications, divisions,
//! comparisons and selects; Rust never contracts `a·b + c` into an FMA), so a
//! lane of a 16-wide AVX-512 loop, of two 8-wide AVX2 halves or of the
//! portable loop gives the same bits. The row functions are compiled for each
//! instruction set and picked at run time ([`crate::kernels::fastmath::isa`]).
//!
//! A pair whose `power` is below the splat's `power_min` is skipped before
//! the `exp`: `power_min = ln(alpha_min / o) − 0.01` (computed in `T` with
//! the pinned `libm`, `logf` for f32; its roundings move it by at most a few
//! ulp, under 1e-4 for any finite `o` whose ratio does not overflow, where
//! it is `+∞`), so `o·exp(power) < alpha_min·e^{−0.0099}`, well inside the
//! alpha-skip rule whatever the rounding of `exp` (≤ 1 ulp) and of the
//! product. A row whose lanes all skip an entry does no further work for it.
//! The lanes of an entry that skip it this way while another lane goes on
//! take the `exp` of `power_min` instead of their power (the exp's lower
//! clamp moved up to it, [`Lanes::exp_above`]; the backward's replay does
//! the same): far from a splat the power is below about −87, where `exp` in
//! f32 is subnormal, and CPUs compute subnormal results and operands with
//! slow microcode assists. No output reads those lanes' values, so the bits
//! are the same; the 64×64 bench frame's forward on one thread went from
//! 0.55 to 0.35 ms on the development machine (AMD Zen 5) and from 4.5 to
//! 0.7 ms on an Intel Xeon.
//!
//! Rows that cannot reach `power_min` are not looked at: each splat carries
//! the image rows where its computed power can reach `power_min` at some
//! pixel ([`candidate_rows_lanes`], a bound on the row's largest power with every
//! rounding of [`power_lanes`] accounted for, tested against it). A row walk
//! first picks, without branches, the entries whose candidate rows hold it
//! and walks only those; every other entry would have been skipped at
//! every lane, so the results are the same bits. Small splats in a 16-row
//! tile reach a few of its rows, and the walk stops paying for the rest.
//!
//! Image rows are independent and own their pixels, so the forward runs in
//! parallel over rows with no reduction across threads.

use super::lanes::{Lanes, Scalar};
use super::BLOCK;
use crate::kernels::fastmath;
use crate::math::Real;
use std::mem::MaybeUninit;
use std::sync::atomic::{AtomicU8, Ordering};

/// Pixels per row group (one tile row).
pub(crate) const LANES: usize = BLOCK;

/// List entries a row walk picks its candidates from at a time (does not
/// affect results).
const PICK_CHUNK: usize = 64;
// The picking loop masks its slot index with `PICK_CHUNK − 1`.
const _: () = assert!(PICK_CHUNK.is_power_of_two());

/// The per-Gaussian data a pixel reads, gathered in list order per tile.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Splat<T> {
    pub xy: [T; 2],
    pub conic: [T; 3],
    pub opacity: T,
    pub color: [T; 3],
    pub depth: T,
    /// Powers below this are certainly skipped by the alpha rule (see the
    /// module docs); `+∞` for `o ≤ 0`, `−∞` when `o` is not finite.
    pub power_min: T,
    /// Image rows `[first, end)` outside which every pixel's computed
    /// `power` is below `power_min` ([`candidate_rows_lanes`]).
    pub rows: [u32; 2],
}

/// [`Splat::power_min`] for opacity `o` (see the module docs).
pub(crate) fn power_min<T: Real>(o: T) -> T {
    if let crate::math::Precision::F32 = T::PRECISION {
        // In f32 (`logf`: within an ulp, about two thirds of the f64 `log`'s
        // time).
        let o = o.to_f64() as f32;
        return T::from_f64(if !o.is_finite() {
            f32::NEG_INFINITY
        } else if o <= 0.0 {
            f32::INFINITY
        } else {
            libm::logf(Blend::<f32>::new().alpha_min / o) - 0.01
        } as f64);
    }
    let o = o.to_f64();
    T::from_f64(if !o.is_finite() {
        f64::NEG_INFINITY
    } else if o <= 0.0 {
        f64::INFINITY
    } else {
        libm::log(Blend::<T>::new().alpha_min.to_f64() / o) - 0.01
    })
}

/// One splat's [`candidate_rows_lanes`].
#[cfg(test)]
pub(crate) fn candidate_rows<T: Real>(
    xy: [T; 2],
    conic: [T; 3],
    power_min: T,
    height: usize,
) -> [u32; 2] {
    candidate_rows_lanes(xy.map(|v| [v]), conic.map(|v| [v]), [power_min], height)[0]
}

/// Per lane `l` (`xy[·][l]`, `conic[·][l]`, `power_min[l]`), the image rows
/// `[first, end)` (within `0..height`) at which a splat
/// centred at row coordinate `xy[1]` with conic `conic` and
/// [`Splat::power_min`] `power_min` can pass the power test at some pixel:
/// at every other row, the `power` that [`power_lanes`] computes, rounding
/// included, is below `power_min` at every pixel, so the row skips the
/// entry whatever its `x` (the row walk need not look at it).
///
/// The bound. With `d = (dx, dy)`, `Q = A dx² + 2B dx dy + C dy²` and
/// `p = −Q/2`, the largest `p` on a row is `−dy²·det/(2A)` (`det = AC − B²`,
/// at `dx = −B dy/A`). The computed power rounds five products and sums of
/// non-negative terms and one difference: it is at most
/// `p + 2.51·ε·(A dx² + C dy²) ≤ p·(1 − 5.02·ε·κ)`, then the last rounding,
/// where `ε` is the unit roundoff of `T` and `κ ≥ λmax/λmin ≥ (A dx² + C dy²)/Q`
/// bounds the conic's condition number (taken as `(A + C)²/det`). With the margin `m = 6εκ + 2ε` the row is
/// skipped when `dy² > −2·power_min·A/(det·(1 − m))`, `dy` being the rounded
/// `y − row` the lanes use (`|dy| ≥ |y − row|·(1 − ε)`); a further
/// relative 1e-5 on `dy²` and on `|dy|` covers that and the f64 evaluation
/// of the bound. The bound is only
/// used where it holds comfortably: finite values of moderate size (no
/// overflow, no NaN power, which would count as a candidate), a positive
/// definite conic with `κ ≤ 10⁶`, and `power_min < 0`; otherwise every row
/// is a candidate (or none, for `power_min > 0`: no power is both `≤ 0` and
/// above it).
///
/// Written without branches (every quantity computed, the cases chosen by
/// selects) so that the loop over the `N` lanes runs in vector registers;
/// the tests hold it to the definition written with early returns.
#[inline(always)]
pub(crate) fn candidate_rows_lanes<T: Real, const N: usize>(
    xy: [[T; N]; 2],
    conic: [[T; N]; 3],
    power_min: [T; N],
    height: usize,
) -> [[u32; 2]; N] {
    let all = height.min(u32::MAX as usize) as u32;
    let h = all as f64;
    let eps = match T::PRECISION {
        crate::math::Precision::F32 => f32::EPSILON as f64 / 2.0,
        crate::math::Precision::F64 => f64::EPSILON / 2.0,
    };
    // The f64 evaluation and `|dy| ≥ |y − row|·(1 − ε)`, generously.
    let slack = 1.0 + 1e-5;
    // `v.clamp(0, h)`, NaN kept (as `f64::clamp`), without its assertion.
    let clamp = |v: f64| {
        if v < 0.0 {
            0.0
        } else if v > h {
            h
        } else {
            v
        }
    };
    let mut out = [[0u32; 2]; N];
    for (l, o) in out.iter_mut().enumerate() {
        let [a, b, c] = [conic[0][l], conic[1][l], conic[2][l]].map(|v| v.to_f64());
        let (x, y, pm) = (xy[0][l].to_f64(), xy[1][l].to_f64(), power_min[l].to_f64());
        // Moderate finite values only (a NaN fails every comparison here).
        let usable = (a > 1e-20)
            & (a < 1e20)
            & (c > 1e-20)
            & (c < 1e20)
            & (b.abs() < 1e20)
            & (x.abs() < 1e7)
            & (y.abs() < 1e7);
        let det = a * c - b * b;
        // κ ≤ (λmax + λmin)²/(λmax·λmin) = (A + C)²/det.
        let trace2 = (a + c) * (a + c);
        let bounded = (pm < 0.0) & (pm > f64::NEG_INFINITY) & (det > 0.0) & (trace2 <= 1e6 * det);
        // det·(1 − m) with m = 6εκ + 2ε, κ = (A + C)²/det (at least 0.64·det).
        let shrunk = det * (1.0 - 2.0 * eps) - 6.0 * eps * trace2;
        let r = (-2.0 * pm * a / shrunk * slack).sqrt() * slack;
        let lo = clamp((y - r).ceil()) as u32;
        let hi = clamp((y + r).floor() + 1.0) as u32;
        *o = if !usable {
            [0, all]
        } else if pm > 0.0 {
            [0, 0]
        } else if !bounded {
            [0, all]
        } else {
            [lo, hi]
        };
    }
    out
}

/// Constants of the blending rule in `T`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Blend<T> {
    pub neg_half: T,
    pub alpha_max: T,
    pub alpha_min: T,
    pub t_min: T,
}

impl<T: Real> Blend<T> {
    pub fn new() -> Self {
        Blend {
            neg_half: T::from_f64(-0.5),
            alpha_max: T::from_f64(0.99),
            alpha_min: T::ONE / T::from_f64(255.0),
            t_min: T::from_f64(1e-4),
        }
    }
}

/// `power` of splat `s` at pixel offset `(dx, dy)`.
#[inline(always)]
pub(crate) fn power<T: Real>(s: &Splat<T>, dx: T, dy: T, k: &Blend<T>) -> T {
    k.neg_half * (s.conic[0] * dx * dx + s.conic[2] * dy * dy) - s.conic[1] * dx * dy
}

/// `alpha = min(0.99, o·g)` (as `Real::min`: 0.99 unless `o·g < 0.99`).
#[inline(always)]
pub(crate) fn alpha<T: Real>(s: &Splat<T>, g: T, k: &Blend<T>) -> T {
    k.alpha_max.min(s.opacity * g)
}

/// One list entry evaluated at one pixel.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Hit<T> {
    pub alpha: T,
    /// `o·G > 0.99`: alpha is the constant 0.99.
    pub clamped: bool,
}

/// What an entry does at a pixel.
#[derive(Clone, Copy, Debug)]
pub(crate) enum Step<T> {
    /// `power > 0` or `alpha < 1/255`.
    Skip,
    /// Passes the alpha test; the caller decides stop vs blend from `T`.
    Hit(Hit<T>),
}

/// The rule for one pixel and one entry, scalar (the reference the row
/// functions are tested against, and the decision signature of the
/// gradient checks).
pub(crate) fn evaluate<T: Real>(s: &Splat<T>, px: T, py: T, k: &Blend<T>) -> Step<T> {
    let p = power(s, s.xy[0] - px, s.xy[1] - py, k);
    if p > T::ZERO {
        return Step::Skip;
    }
    let g = fastmath::exp(p);
    let a = alpha(s, g, k);
    if a < k.alpha_min {
        return Step::Skip;
    }
    Step::Hit(Hit {
        alpha: a,
        clamped: s.opacity * g > k.alpha_max,
    })
}

/// One row of one tile: pixels `x0 .. x0 + nx` of image row `py`.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Row {
    pub x0: usize,
    pub nx: usize,
    pub py: usize,
}

/// Per-lane state of a row walk.
#[derive(Clone, Copy, Debug)]
pub(crate) struct RowState<T> {
    pub t: [T; LANES],
    pub c: [[T; LANES]; 3],
    pub d: [T; LANES],
    pub last: [u32; LANES],
    /// Pairs the row evaluated: Σ over pixels of the entries up to and
    /// including the one that stopped it.
    pub evaluated: u64,
}

/// A list entry at which at least one lane of a row blended, as the forward
/// saves it for the backward: the entry's position in its tile's list and
/// the mask of blending lanes (bit `l` for lane `l`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Blended {
    pub j: u32,
    pub mask: u16,
}

/// A [`Blended`] entry as the backward replays it: the lanes'
/// transmittance before the entry and `exp(power)` (of `power_min` in the
/// lanes below it, which do not blend).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Record<T> {
    pub j: u32,
    pub t: [T; LANES],
    pub g: [T; LANES],
    pub blend: u16,
}

/// Pixel x coordinates of a row's lanes.
#[inline(always)]
pub(crate) fn lane_x<T: Real>(row: Row) -> [T; LANES] {
    let mut x = [T::ZERO; LANES];
    for (l, v) in x.iter_mut().enumerate() {
        *v = T::from_usize(row.x0 + l);
    }
    x
}

/// `power` at every lane of a row: the scalar expression with `dx` per lane
/// and the row's `dy` (`C·dy·dy` is the same for every lane).
#[inline(always)]
pub(crate) fn power_lanes<V: Lanes>(s: &Splat<V::T>, dx: V, dy: V::T, k: &Blend<V::T>) -> V {
    let cdy = s.conic[2] * dy * dy;
    V::splat(k.neg_half) * (V::splat(s.conic[0]) * dx * dx + V::splat(cdy))
        - V::splat(s.conic[1]) * dx * V::splat(dy)
}

/// Walk `splats` front to back for one row, pushing a [`Blended`] onto
/// `blended` for every entry at which some lane blends.
#[inline(always)]
pub(crate) fn walk_row<V: Lanes>(
    splats: &[Splat<V::T>],
    row: Row,
    k: &Blend<V::T>,
    blended: &mut Vec<Blended>,
) -> RowState<V::T> {
    let zero = V::T::ZERO;
    let px = V::load(&lane_x::<V::T>(row));
    let pyf = V::T::from_usize(row.py);
    let mut t = V::splat(V::T::ONE);
    let mut c = [V::splat(zero); 3];
    let mut d = V::splat(zero);
    let start = blended.len();
    let mut evaluated = 0u64;
    let mut active_bits: u16 = if row.nx >= LANES {
        u16::MAX
    } else {
        (1u16 << row.nx) - 1
    };
    let mut active = V::from_bits(active_bits);
    let (vzero, one) = (V::splat(zero), V::splat(V::T::ONE));
    let (amax, amin, tmin) = (
        V::splat(k.alpha_max),
        V::splat(k.alpha_min),
        V::splat(k.t_min),
    );
    // The entries whose candidate rows hold this row, a chunk at a time
    // (positions in the tile's list, ascending; written without branches).
    let row_u32 = row.py as u32;
    let mut picked = [0u32; PICK_CHUNK];
    let mut base = 0;
    'walk: while active_bits != 0 && base < splats.len() {
        let end = (base + PICK_CHUNK).min(splats.len());
        let mut n = 0;
        for (j, s) in splats[base..end].iter().enumerate() {
            // `n ≤ j < PICK_CHUNK`; the mask only spares the bounds check.
            picked[n & (PICK_CHUNK - 1)] = (base + j) as u32;
            let [first, last] = s.rows;
            n += (row_u32.wrapping_sub(first) < last.wrapping_sub(first)) as usize;
        }
        base = end;
        for &j in &picked[..n] {
            let j = j as usize;
            let s = &splats[j];
            let dx = V::splat(s.xy[0]) - px;
            let p = power_lanes(s, dx, s.xy[1] - pyf, k);
            let pmin = V::splat(s.power_min);
            let cand = V::andnot(V::andnot(active, p.gt(vzero)), p.lt(pmin));
            if V::bits(cand) == 0 {
                continue;
            }
            // Lanes below `power_min` never blend: their `exp` is taken of
            // `power_min` instead of their power, whose far-away values
            // would give subnormal results that the CPU computes slowly
            // (microcode assists) and that no output reads.
            let g = p.exp_above(pmin);
            let a = (V::splat(s.opacity) * g).min_of(amax);
            let hit = V::andnot(cand, a.lt(amin));
            let test_t = t * (one - a);
            let stop = V::and(hit, test_t.lt(tmin));
            let b = V::andnot(hit, stop);
            let b_bits = V::bits(b);
            // Without a branch on `b` (whether some lane blends varies from
            // entry to entry): the selects keep lanes that do not blend as
            // they are, and the entry is written past the end and kept only
            // if some lane blends.
            for (cv, &col) in c.iter_mut().zip(&s.color) {
                *cv = V::select(b, *cv + V::splat(col) * a * t, *cv);
            }
            d = V::select(b, d + V::splat(s.depth) * a * t, d);
            t = V::select(b, test_t, t);
            if blended.len() == blended.capacity() {
                blended.reserve(1);
            }
            let len = blended.len();
            // SAFETY: `len < capacity` (reserved above), so the slot is
            // allocated; `Blended` is `Copy` (nothing to drop), and the new
            // length covers only written slots.
            unsafe {
                blended.as_mut_ptr().add(len).write(Blended {
                    j: j as u32,
                    mask: b_bits,
                });
                blended.set_len(len + (b_bits != 0) as usize);
            }
            let stop_bits = V::bits(stop);
            if stop_bits != 0 {
                // A lane that stops here evaluated entries 0..=j.
                evaluated += (j as u64 + 1) * stop_bits.count_ones() as u64;
                active_bits &= !stop_bits;
                active = V::from_bits(active_bits);
                if active_bits == 0 {
                    break 'walk;
                }
            }
        }
    }
    // Lanes that never stopped evaluated the whole list.
    evaluated += splats.len() as u64 * active_bits.count_ones() as u64;
    // Each lane's last blended entry (1-based; 0 if none): the row's entries
    // read backwards until every lane that blended has been seen.
    let mut last = [0u32; LANES];
    let all = blended[start..].iter().fold(0u16, |m, b| m | b.mask);
    let mut seen = 0u16;
    for b in blended[start..].iter().rev() {
        let mut m = b.mask & !seen;
        seen |= m;
        while m != 0 {
            last[m.trailing_zeros() as usize] = b.j + 1;
            m &= m - 1;
        }
        if seen == all {
            break;
        }
    }
    let mut st = RowState {
        t: [zero; LANES],
        c: [[zero; LANES]; 3],
        d: [zero; LANES],
        last,
        evaluated,
    };
    t.store(&mut st.t);
    for (cv, out) in c.iter().zip(st.c.iter_mut()) {
        cv.store(out);
    }
    d.store(&mut st.d);
    st
}

/// The backward's replay of one row's [`Blended`] entries (as the forward
/// saved them, in list order): per entry the same `power`, `exp`, alpha and
/// transmittance products as [`walk_row`], so the same bits, without the
/// skip and stop tests or the entries no lane blends. Pushes one [`Record`]
/// per entry onto `rec` and returns the lanes' final transmittance.
#[inline(always)]
pub(crate) fn replay_row<V: Lanes>(
    splats: &[Splat<V::T>],
    blended: &[Blended],
    row: Row,
    k: &Blend<V::T>,
    rec: &mut Vec<Record<V::T>>,
) -> V {
    let zero = V::T::ZERO;
    let px = V::load(&lane_x::<V::T>(row));
    let pyf = V::T::from_usize(row.py);
    let one = V::splat(V::T::ONE);
    let amax = V::splat(k.alpha_max);
    let mut t = one;
    for b in blended {
        let s = &splats[b.j as usize];
        let dx = V::splat(s.xy[0]) - px;
        // As in `walk_row`, lanes below `power_min` take its `exp` (they do
        // not blend, and every use of their `g` is masked); the lanes that
        // blend are at or above it.
        let g = power_lanes(s, dx, s.xy[1] - pyf, k).exp_above(V::splat(s.power_min));
        let a = (V::splat(s.opacity) * g).min_of(amax);
        let mut r = Record {
            j: b.j,
            t: [zero; LANES],
            g: [zero; LANES],
            blend: b.mask,
        };
        t.store(&mut r.t);
        g.store(&mut r.g);
        rec.push(r);
        t = V::select(V::from_bits(b.mask), t * (one - a), t);
    }
    t
}

/// Output slices of one image row (channel-major image, so each channel's
/// row is contiguous).
///
/// The pixel slices and `blended_end` start unwritten; the row writes each
/// slot once.
pub(crate) struct RowOut<'a, T> {
    pub color: [&'a mut [MaybeUninit<T>]; 3],
    pub depth: &'a mut [MaybeUninit<T>],
    pub final_t: &'a mut [MaybeUninit<T>],
    pub n_contrib: &'a mut [MaybeUninit<u32>],
    /// The row's [`Blended`] entries, tile after tile (cleared first).
    pub blended: &'a mut Vec<Blended>,
    /// Per tile the row crosses: the end of its entries in `blended`.
    pub blended_end: &'a mut [MaybeUninit<u32>],
}

impl<T> RowOut<'_, T> {
    /// Ask for the lines of the row's pixel outputs and tile ends for
    /// writing (only a hint), so that lines the other core may have read
    /// in the pass before come over while the row is computed
    /// ([`crate::kernels::prefetch_write`]).
    pub(crate) fn prefetch_write(&self) {
        use crate::kernels::prefetch_write as pw;
        for c in &self.color {
            pw(c, 0, c.len());
        }
        pw(self.depth, 0, self.depth.len());
        pw(self.final_t, 0, self.final_t.len());
        pw(self.n_contrib, 0, self.n_contrib.len());
        pw(self.blended_end, 0, self.blended_end.len());
    }
}

/// The positions in image row `py`'s saved [`Blended`] entries of tile
/// column `tx`'s, from the rows' per-tile ends (`[H, grid_x]`, as
/// [`RowOut::blended_end`] writes them: each row's ends restart from 0).
#[inline(always)]
pub(crate) fn row_tile_entries(
    blended_end: &[u32],
    grid_x: usize,
    py: usize,
    tx: usize,
) -> std::ops::Range<usize> {
    let ends = &blended_end[py * grid_x..(py + 1) * grid_x];
    let start = if tx == 0 { 0 } else { ends[tx - 1] as usize };
    start..ends[tx] as usize
}

/// What a row of a frame reads: its tile row's part of the frame.
pub(crate) struct Frame<'a, T> {
    /// Gathered splats, in list order: every entry of the row's tiles.
    pub splats: &'a [Splat<T>],
    /// Per tile of the row's tile row, `[start, end)` in `splats`.
    pub ranges: &'a [[u32; 2]],
    pub width: usize,
    pub bg: [T; 3],
}

/// A small frame's list and splat copies, written a tile row at a time by
/// the first blend row that asks for that tile row
/// ([`TileRowSplats::tile_row`]), with `fill(t, list, copies)` for each of
/// its tiles `t`: the other rows of the tile row wait until it is written.
/// On the small frames' path, `fill` merges the tile's entries of the two
/// workers' runs (`tiles::merge_tile`), so the list is written where it is
/// first needed, with no step of its own, and the copies a worker blends
/// are mostly ones it wrote (benches/README.md, "Rasterizer: small frames'
/// splats gathered by the blend", "Rasterizer: small frames' tiles merged
/// by the blend").
pub(crate) struct TileRowSplats<T, F> {
    fill: F,
    /// The spare slots of the list: as many as the ranges cover.
    list: *mut MaybeUninit<u32>,
    /// The spare slots of the splat copies: as many.
    out: *mut MaybeUninit<Splat<T>>,
    /// Per tile row.
    rows: Vec<TileRow>,
    /// Per tile (row-major), its slots counted from its tile row's first.
    ranges: Vec<[u32; 2]>,
    grid_x: usize,
}

/// One tile row of [`TileRowSplats`].
struct TileRow {
    /// Its slots `[start, end)` in the list.
    slots: [usize; 2],
    /// [`PENDING`], [`TAKEN`] (some row is writing), [`WRITTEN`] or
    /// [`FAILED`].
    state: AtomicU8,
}

const PENDING: u8 = 0;
const TAKEN: u8 = 1;
const WRITTEN: u8 = 2;
const FAILED: u8 = 3;

// SAFETY: `list` and `out` are written only at a tile row's slots, by the
// one thread that took that tile row, and read only after they are
// written (`tile_row`); `fill` is shared.
unsafe impl<T: Sync, F: Sync> Sync for TileRowSplats<T, F> {}

impl<T: Copy, F> TileRowSplats<T, F>
where
    F: Fn(usize, &mut [MaybeUninit<u32>], &mut [MaybeUninit<Splat<T>>]),
{
    /// The list and copies written into `list`'s and `gathered`'s spare
    /// capacity (at least as many slots as `ranges` covers each) by
    /// `fill`, which writes every slot of the tile it is given, tile rows
    /// of `grid_x` tiles as `ranges` gives them (row-major, consecutive
    /// from slot 0).
    ///
    /// # Safety
    /// `fill` writes every slot of the slices it is given (or panics), and
    /// `list` and `gathered` are not used (moved, resized, read or written)
    /// while the value returned lives.
    pub(crate) unsafe fn new(
        fill: F,
        ranges: &[[u32; 2]],
        grid_x: usize,
        list: &mut Vec<u32>,
        gathered: &mut Vec<Splat<T>>,
    ) -> Self {
        assert!(grid_x > 0);
        let mut rows = Vec::with_capacity(ranges.len() / grid_x);
        let mut rebased = Vec::with_capacity(ranges.len());
        let mut next = 0;
        for r in ranges.chunks(grid_x) {
            let first = next;
            for &[s, e] in r {
                assert!(s as usize == next && s <= e, "tiles' slots are consecutive");
                next = e as usize;
                rebased.push([s - first as u32, e - first as u32]);
            }
            rows.push(TileRow {
                slots: [first, next],
                state: AtomicU8::new(PENDING),
            });
        }
        assert!(
            list.capacity() >= next && gathered.capacity() >= next,
            "room for every slot"
        );
        TileRowSplats {
            fill,
            list: list.spare_capacity_mut().as_mut_ptr(),
            out: gathered.spare_capacity_mut().as_mut_ptr(),
            rows,
            ranges: rebased,
            grid_x,
        }
    }

    /// Tile row `ty`'s copies and its tiles' ranges in them, written here
    /// if no row has taken them on yet, else once the row that has is done
    /// with them. Panics if that row's `fill` panicked.
    #[inline]
    pub(crate) fn tile_row(&self, ty: usize) -> (&[Splat<T>], &[[u32; 2]]) {
        let row = &self.rows[ty];
        let [s, e] = row.slots;
        let ranges = &self.ranges[ty * self.grid_x..(ty + 1) * self.grid_x];
        if row.state.load(Ordering::Acquire) != WRITTEN {
            let took = row
                .state
                .compare_exchange(PENDING, TAKEN, Ordering::Acquire, Ordering::Relaxed)
                .is_ok();
            if took {
                // Marks the tile row failed if `fill` unwinds, so that a
                // row waiting for it panics instead of waiting for ever.
                struct Failed<'s>(&'s AtomicU8);
                impl Drop for Failed<'_> {
                    fn drop(&mut self) {
                        self.0.store(FAILED, Ordering::Release);
                    }
                }
                let failed = Failed(&row.state);
                // SAFETY: the slots `s..e` are within the spare capacity
                // (`new`), and this thread alone took them.
                let (list, out) = unsafe {
                    (
                        std::slice::from_raw_parts_mut(self.list.add(s), e - s),
                        std::slice::from_raw_parts_mut(self.out.add(s), e - s),
                    )
                };
                for (tx, &[a, b]) in ranges.iter().enumerate() {
                    let (a, b) = (a as usize, b as usize);
                    (self.fill)(ty * self.grid_x + tx, &mut list[a..b], &mut out[a..b]);
                }
                std::mem::forget(failed);
                row.state.store(WRITTEN, Ordering::Release);
            } else {
                // (Taken, written or failed: never pending again.)
                crate::threads::wait_until(|| row.state.load(Ordering::Acquire) != TAKEN);
                assert!(
                    row.state.load(Ordering::Acquire) == WRITTEN,
                    "the copy of tile row {ty}'s splats panicked on another worker"
                );
            }
        }
        // SAFETY: the slots `s..e` were written (above, or by the thread
        // that took them, whose writes the `Acquire` load has made seen:
        // `fill` writes every slot of each tile, and the tiles' ranges
        // cover the tile row's slots) and are not written again.
        let copies = unsafe { std::slice::from_raw_parts(self.out.add(s).cast(), e - s) };
        (copies, ranges)
    }

    /// The number of slots the ranges cover, if every tile row's list and
    /// copies are written (so that all those slots are); `None` if some
    /// tile row's are not.
    pub(crate) fn written_len(&self) -> Option<usize> {
        self.rows
            .iter()
            .all(|r| r.state.load(Ordering::Acquire) == WRITTEN)
            .then(|| self.rows.last().map_or(0, |r| r.slots[1]))
    }
}

/// Render image row `py` (every tile it crosses); adds the pairs evaluated
/// to `evaluated`.
#[inline(always)]
fn forward_row_body<V: Lanes>(
    f: &Frame<'_, V::T>,
    py: usize,
    out: &mut RowOut<'_, V::T>,
    evaluated: &mut u64,
) {
    let k = Blend::<V::T>::new();
    // One allocation per row, of the most entries the row can blend (every
    // entry of the tiles it crosses), shrunk when the row is done:
    // growing the vector step by step cost reallocations whose allocator
    // locks the threads contended for.
    out.blended.clear();
    out.blended
        .reserve(f.ranges.iter().map(|[s, e]| (e - s) as usize).sum());
    for (tx, &[s, e]) in f.ranges.iter().enumerate() {
        let x0 = tx * BLOCK;
        let nx = BLOCK.min(f.width - x0);
        let st = walk_row::<V>(
            &f.splats[s as usize..e as usize],
            Row { x0, nx, py },
            &k,
            out.blended,
        );
        for l in 0..nx {
            let t = st.t[l];
            for ch in 0..3 {
                out.color[ch][x0 + l].write(st.c[ch][l] + t * f.bg[ch]);
            }
            out.depth[x0 + l].write(st.d[l]);
            out.final_t[x0 + l].write(t);
            out.n_contrib[x0 + l].write(st.last[l]);
        }
        out.blended_end[tx].write(out.blended.len() as u32);
        *evaluated += st.evaluated;
    }
    out.blended.shrink_to_fit();
}

/// Which [`Lanes`] implementation the row functions run on for `T`: a vector
/// one for f32 where the CPU has it ([`fastmath::isa`], which tests can pin),
/// [`Scalar`] otherwise.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Path {
    #[cfg(target_arch = "x86_64")]
    Avx512,
    #[cfg(target_arch = "x86_64")]
    Avx2,
    Portable,
}

pub(crate) fn path<T: Real>() -> Path {
    // The vector paths reinterpret `T` data as `f32`.
    if std::any::TypeId::of::<T>() != std::any::TypeId::of::<f32>() {
        return Path::Portable;
    }
    match fastmath::isa() {
        #[cfg(target_arch = "x86_64")]
        fastmath::Isa::Avx512 => Path::Avx512,
        #[cfg(target_arch = "x86_64")]
        fastmath::Isa::Avx2 => Path::Avx2,
        _ => Path::Portable,
    }
}

/// Reinterpret a `&mut X<T>` as `&mut X<f32>`.
///
/// # Safety
/// `T` is `f32`.
#[cfg(target_arch = "x86_64")]
pub(crate) unsafe fn as_f32<X, Y>(x: &mut X) -> &mut Y {
    // SAFETY: the caller guarantees `T` is `f32`, so `X` and `Y` are the same type.
    unsafe { &mut *(x as *mut X as *mut Y) }
}

/// Reinterpret a `&X<T>` as `&X<f32>`.
///
/// # Safety
/// `T` is `f32`.
#[cfg(target_arch = "x86_64")]
pub(crate) unsafe fn as_f32_ref<X, Y>(x: &X) -> &Y {
    // SAFETY: the caller guarantees `T` is `f32`, so `X` and `Y` are the same type.
    unsafe { &*(x as *const X as *const Y) }
}

/// Render image row `py` of frame `f` into `out`; adds the pairs evaluated
/// to `evaluated`.
pub(crate) fn forward_row<T: Real>(
    f: &Frame<'_, T>,
    py: usize,
    out: &mut RowOut<'_, T>,
    evaluated: &mut u64,
) {
    #[cfg(target_arch = "x86_64")]
    {
        use super::lanes::{Avx2, Avx512};
        #[target_feature(enable = "avx512f")]
        unsafe fn avx512(f: &Frame<'_, f32>, py: usize, out: &mut RowOut<'_, f32>, ev: &mut u64) {
            forward_row_body::<Avx512>(f, py, out, ev)
        }
        #[target_feature(enable = "avx2")]
        unsafe fn avx2(f: &Frame<'_, f32>, py: usize, out: &mut RowOut<'_, f32>, ev: &mut u64) {
            forward_row_body::<Avx2>(f, py, out, ev)
        }
        let p = path::<T>();
        if p != Path::Portable {
            // SAFETY: a vector path is chosen only for T = f32, on a CPU
            // with its feature.
            unsafe {
                let f32f: &Frame<'_, f32> = as_f32_ref(f);
                let o32: &mut RowOut<'_, f32> = as_f32(out);
                match p {
                    Path::Avx512 => avx512(f32f, py, o32, evaluated),
                    _ => avx2(f32f, py, o32, evaluated),
                }
            }
            return;
        }
    }
    forward_row_body::<Scalar<T>>(f, py, out, evaluated)
}

/// Pixel bounds `[x0, x1) × [y0, y1)` of tile `tile`.
#[inline]
pub(crate) fn tile_bounds(tile: usize, grid_x: usize, w: usize, h: usize) -> [usize; 4] {
    let tx = tile % grid_x;
    let ty = tile / grid_x;
    [
        tx * BLOCK,
        (tx * BLOCK + BLOCK).min(w),
        ty * BLOCK,
        (ty * BLOCK + BLOCK).min(h),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Rng;
    use crate::render::lanes::Scalar;
    use rayon::prelude::*;

    // A splat with a random rotated 2D covariance (condition numbers from 1
    // to 10^7, beyond the bound's limit too), centre around rows 0..height,
    // and opacity from almost nothing to 1; `rows` computed for `height`.
    fn random_splat<T: Real>(rng: &mut Rng, height: usize) -> Splat<T> {
        let theta = rng.uniform_range(0.0, std::f64::consts::PI);
        let s1 = 10f64.powf(rng.uniform_range(-0.5, 1.3));
        let s2 = s1 / 10f64.powf(rng.uniform_range(0.0, 3.5));
        let (c, s) = (theta.cos(), theta.sin());
        let (v1, v2) = (s1 * s1 + 0.3, s2 * s2 + 0.3);
        let cov = [
            c * c * v1 + s * s * v2,
            c * s * (v1 - v2),
            s * s * v1 + c * c * v2,
        ];
        let det = cov[0] * cov[2] - cov[1] * cov[1];
        let conic = [cov[2] / det, -cov[1] / det, cov[0] / det].map(T::from_f64);
        let opacity = T::from_f64(match rng.below(4) {
            0 => 1.0,
            1 => 1.0 / 255.0,
            2 => rng.uniform_range(0.002, 0.01),
            _ => rng.uniform_range(0.01, 1.0),
        });
        let h = height as f64;
        let xy = [
            T::from_f64(rng.uniform_range(-8.0, 24.0)),
            T::from_f64(rng.uniform_range(-0.3 * h, 1.3 * h)),
        ];
        let pm = power_min(opacity);
        Splat {
            xy,
            conic,
            opacity,
            color: [0.2, 0.5, 0.9].map(T::from_f64),
            depth: T::from_f64(rng.uniform_range(1.0, 5.0)),
            power_min: pm,
            rows: candidate_rows(xy, conic, pm, height),
        }
    }

    /// The splat data of [`TileRowSplats`]' tests: Gaussian `g`'s, with its
    /// index as depth so that a copy shows which it is.
    fn indexed_splats(n: usize) -> Vec<Splat<f32>> {
        let mut rng = Rng::new(5);
        (0..n)
            .map(|g| Splat {
                depth: g as f32,
                ..random_splat::<f32>(&mut rng, 64)
            })
            .collect()
    }

    /// A fill of [`TileRowSplats`].
    type Fill<'a> =
        Box<dyn Fn(usize, &mut [MaybeUninit<u32>], &mut [MaybeUninit<Splat<f32>>]) + Sync + 'a>;

    /// A [`TileRowSplats`] into `written` and `gathered` whose fill copies
    /// each tile's entries of `list` (its `ranges`) and their splats.
    ///
    /// # Safety
    /// As for [`TileRowSplats::new`], for `written` and `gathered`.
    unsafe fn copying<'a>(
        list: &'a [u32],
        splats: &'a [Splat<f32>],
        ranges: &'a [[u32; 2]],
        grid_x: usize,
        written: &mut Vec<u32>,
        gathered: &mut Vec<Splat<f32>>,
    ) -> TileRowSplats<f32, Fill<'a>> {
        let fill: Fill<'a> = Box::new(move |t, l, c| {
            let [s, e] = ranges[t];
            assert!(l.len() == (e - s) as usize && c.len() == l.len());
            for (k, &g) in list[s as usize..e as usize].iter().enumerate() {
                l[k].write(g);
                c[k].write(splats[g as usize]);
            }
        });
        written.reserve(list.len());
        gathered.reserve(list.len());
        // SAFETY: `fill` writes every slot it is given or panics (on a
        // Gaussian past `splats`); the caller's promise for the rest.
        unsafe { TileRowSplats::new(fill, ranges, grid_x, written, gathered) }
    }

    #[test]
    fn tile_rows_are_gathered_once_whoever_asks_first() {
        // 3×4 tiles with uneven and empty tiles; list entries in no
        // particular order, repeated Gaussians included.
        let counts = [3u32, 0, 5, 0, 0, 0, 7, 1, 2, 4, 0, 9];
        let mut ranges = Vec::new();
        let mut at = 0;
        for c in counts {
            ranges.push([at, at + c]);
            at += c;
        }
        let splats = indexed_splats(11);
        let list: Vec<u32> = (0..at).map(|k| (k * 7 + 3) % 11).collect();
        for threads in [1, 2, 3] {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            // Every image row of every tile row asks, in parallel, in an
            // order that starts at the bottom.
            let (mut written, mut gathered) = (Vec::new(), Vec::new());
            // SAFETY: `written` and `gathered` are untouched while `t` lives.
            let t = unsafe { copying(&list, &splats, &ranges, 3, &mut written, &mut gathered) };
            let seen: Vec<(usize, Vec<u32>, Vec<[u32; 2]>)> = pool.install(|| {
                (0..4 * BLOCK)
                    .into_par_iter()
                    .map(|k| {
                        let ty = 3 - k / BLOCK;
                        let (copies, r) = t.tile_row(ty);
                        (
                            ty,
                            copies.iter().map(|s| s.depth as u32).collect(),
                            r.to_vec(),
                        )
                    })
                    .collect()
            });
            assert_eq!(t.written_len(), Some(list.len()));
            drop(t);
            // SAFETY: every slot was written (`written_len`).
            unsafe {
                written.set_len(list.len());
                gathered.set_len(list.len());
            }
            assert_eq!(written, list, "{threads} threads: the list");
            let by_depth: Vec<u32> = gathered.iter().map(|s| s.depth as u32).collect();
            assert_eq!(
                by_depth, list,
                "{threads} threads: the copies in list order"
            );
            for (ty, copies, r) in seen {
                let first = ranges[3 * ty][0];
                let want: Vec<[u32; 2]> = ranges[3 * ty..3 * ty + 3]
                    .iter()
                    .map(|&[s, e]| [s - first, e - first])
                    .collect();
                assert_eq!(r, want, "tile row {ty}'s ranges");
                let [s, e] = [first as usize, ranges[3 * ty + 2][1] as usize];
                assert_eq!(copies, list[s..e], "tile row {ty}'s copies");
            }
        }
    }

    #[test]
    fn a_failed_gather_makes_its_waiters_panic_not_hang() {
        // Tile row 0 lists a Gaussian that does not exist: its copy panics,
        // on whichever worker takes it, and the other panics too.
        let splats = indexed_splats(2);
        let list = vec![0u32, 1, 7, 1];
        let ranges = vec![[0u32, 3], [3, 4]];
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let (mut written, mut gathered) = (Vec::new(), Vec::new());
        // SAFETY: `written` and `gathered` are untouched while `t` lives.
        let t = unsafe { copying(&list, &splats, &ranges, 1, &mut written, &mut gathered) };
        let asks = pool.install(|| {
            rayon::join(
                || std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| t.tile_row(0).0.len())),
                || std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| t.tile_row(0).0.len())),
            )
        });
        assert!(asks.0.is_err() && asks.1.is_err());
        assert_eq!(
            t.tile_row(1).0[0].depth,
            1.0,
            "another tile row still gathers"
        );
        assert_eq!(t.written_len(), None);
    }

    // At every row outside a splat's candidate rows, the power the lanes
    // compute is below `power_min` at every pixel, the row's maximum
    // (around dx = −B·dy/A) included; and the bound culls rows.
    fn rows_outside_are_skipped<T: Real>() {
        let mut rng = Rng::new(7);
        let k = Blend::<T>::new();
        let height = 64;
        let (mut culled, mut tight) = (0usize, 0usize);
        for _ in 0..3000 {
            let s = random_splat::<T>(&mut rng, height);
            for py in 0..height as u32 {
                if s.rows[0] <= py && py < s.rows[1] {
                    continue;
                }
                culled += 1;
                let dy = s.xy[1] - T::from_usize(py as usize);
                let peak = -(s.conic[1].to_f64() * dy.to_f64()) / s.conic[0].to_f64();
                let base = s.xy[0].to_f64() - peak;
                for off in [-6.0, -2.0, 0.0, 2.0, 6.0] {
                    let px: [T; LANES] = std::array::from_fn(|l| {
                        T::from_f64(base + off + (l as f64 - 7.5) * 0.0625)
                    });
                    let dx = crate::math::pack::Pack::<T, LANES>(std::array::from_fn(|l| {
                        s.xy[0] - px[l]
                    }));
                    let p = power_lanes(&s, dx, dy, &k);
                    for (l, &v) in p.0.iter().enumerate() {
                        assert!(
                            v < s.power_min,
                            "row {py} outside {:?} but power {v} >= power_min {} at x {} (splat {s:?})",
                            s.rows,
                            s.power_min,
                            px[l]
                        );
                    }
                }
            }
            // Where the bound applies, it is close to the exact one: the
            // range is within a row of {dy² ≤ −2·power_min·A/det}.
            let [a, b, c] = s.conic.map(|v| v.to_f64());
            let det = a * c - b * b;
            let pm = s.power_min.to_f64();
            if pm < 0.0 && det > 0.0 && (a + c) * (a + c) <= 1e5 * det {
                let r = (-2.0 * pm * a / det).sqrt();
                let y = s.xy[1].to_f64();
                let lo = (y - r - 1.0).ceil().max(0.0) as u32;
                let hi = ((y + r + 1.0).floor() + 1.0).clamp(0.0, height as f64) as u32;
                assert!(
                    s.rows[1] <= s.rows[0] || (lo <= s.rows[0] && s.rows[1] <= hi),
                    "rows {:?} looser than [{lo}, {hi}) (splat {s:?})",
                    s.rows
                );
                tight += 1;
            }
        }
        assert!(
            culled > 50_000 && tight > 1000,
            "culled {culled}, tight {tight}"
        );
    }

    #[test]
    fn rows_outside_are_skipped_f32() {
        rows_outside_are_skipped::<f32>();
    }

    #[test]
    fn rows_outside_are_skipped_f64() {
        rows_outside_are_skipped::<f64>();
    }

    // A row walk with the candidate rows gives the bits, blended entries and
    // pair count of the walk that looks at every entry.
    fn walk_equals_unfiltered<T: Real>() {
        let mut rng = Rng::new(11);
        let k = Blend::<T>::new();
        for case in 0..200 {
            let n = 1 + rng.below(150) as usize;
            let splats: Vec<Splat<T>> = (0..n).map(|_| random_splat(&mut rng, BLOCK)).collect();
            let unfiltered: Vec<Splat<T>> = splats
                .iter()
                .map(|s| Splat {
                    rows: [0, BLOCK as u32],
                    ..*s
                })
                .collect();
            let nx = if case % 3 == 0 { 11 } else { BLOCK };
            for py in 0..BLOCK {
                let row = Row { x0: 0, nx, py };
                let (mut b1, mut b2) = (Vec::new(), Vec::new());
                let s1 = walk_row::<Scalar<T>>(&splats, row, &k, &mut b1);
                let s2 = walk_row::<Scalar<T>>(&unfiltered, row, &k, &mut b2);
                let bits = |st: &RowState<T>| {
                    let mut v: Vec<u64> =
                        st.t.iter()
                            .chain(&st.d)
                            .map(|x| x.to_f64().to_bits())
                            .collect();
                    v.extend(st.c.iter().flatten().map(|x| x.to_f64().to_bits()));
                    v.extend(st.last.iter().map(|&l| l as u64));
                    v.push(st.evaluated);
                    v
                };
                assert_eq!(bits(&s1), bits(&s2), "case {case} row {py}");
                assert_eq!(b1, b2, "case {case} row {py}");
            }
        }
    }

    /// The definition of [`candidate_rows_lanes`] as first written, with early
    /// returns.
    fn candidate_rows_reference<T: Real>(
        xy: [T; 2],
        conic: [T; 3],
        power_min: T,
        height: usize,
    ) -> [u32; 2] {
        let all = [0, height.min(u32::MAX as usize) as u32];
        let [a, b, c] = conic.map(|v| v.to_f64());
        let (x, y, pm) = (xy[0].to_f64(), xy[1].to_f64(), power_min.to_f64());
        let usable = a > 1e-20
            && a < 1e20
            && c > 1e-20
            && c < 1e20
            && b.abs() < 1e20
            && x.abs() < 1e7
            && y.abs() < 1e7;
        if !usable {
            return all;
        }
        if pm > 0.0 {
            return [0, 0];
        }
        let det = a * c - b * b;
        let trace2 = (a + c) * (a + c);
        if !(pm < 0.0 && pm > f64::NEG_INFINITY && det > 0.0 && trace2 <= 1e6 * det) {
            return all;
        }
        let eps = match T::PRECISION {
            crate::math::Precision::F32 => f32::EPSILON as f64 / 2.0,
            crate::math::Precision::F64 => f64::EPSILON / 2.0,
        };
        let shrunk = det * (1.0 - 2.0 * eps) - 6.0 * eps * trace2;
        let slack = 1.0 + 1e-5;
        let r = (-2.0 * pm * a / shrunk * slack).sqrt() * slack;
        let h = all[1] as f64;
        let lo = (y - r).ceil().clamp(0.0, h);
        let hi = ((y + r).floor() + 1.0).clamp(0.0, h);
        [lo as u32, hi as u32]
    }

    /// The branch-free lanes give the rows of the definition, 16 at a time,
    /// on random splats and on every special case (unusable, non-finite or
    /// extreme values, positive or infinite thresholds, indefinite or
    /// ill-conditioned conics, heights 0 and huge).
    fn lanes_match_the_definition<T: Real>() {
        let mut rng = Rng::new(21);
        let specials = [
            0.0,
            -0.0,
            1e-21,
            1e-20,
            1e20,
            2e20,
            -1.0,
            1e7,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            1e300,
        ];
        // A special value one time in six, else a typical one of `kind`.
        let pick = |rng: &mut Rng, kind: u8| -> T {
            let typical = match kind {
                0 => rng.uniform_range(-30.0, 450.0),
                1 => 10f64.powf(rng.uniform_range(-4.0, 2.0)),
                2 => rng.uniform_range(-0.5, 0.5),
                _ if rng.below(8) == 0 => 0.5,
                _ => rng.uniform_range(-9.0, 0.0),
            };
            T::from_f64(if rng.below(6) == 0 {
                specials[rng.below(specials.len() as u64) as usize]
            } else {
                typical
            })
        };
        let mut bounded = 0;
        for case in 0..4000 {
            let height = [0usize, 1, 16, 64, 400, usize::MAX][case % 6];
            let mut lanes = |kind: u8| -> [T; 16] { std::array::from_fn(|_| pick(&mut rng, kind)) };
            let xy = [lanes(0), lanes(0)];
            let conic = [lanes(1), lanes(2), lanes(1)];
            let pm = lanes(3);
            let got = candidate_rows_lanes(xy, conic, pm, height);
            for l in 0..16 {
                let want = candidate_rows_reference(
                    [xy[0][l], xy[1][l]],
                    [conic[0][l], conic[1][l], conic[2][l]],
                    pm[l],
                    height,
                );
                assert_eq!(got[l], want, "case {case} lane {l}");
                assert_eq!(
                    candidate_rows(
                        [xy[0][l], xy[1][l]],
                        [conic[0][l], conic[1][l], conic[2][l]],
                        pm[l],
                        height
                    ),
                    want
                );
                bounded +=
                    (want != [0, 0] && want[1] < height.min(u32::MAX as usize) as u32) as usize;
            }
        }
        assert!(bounded > 2500, "{bounded}");
    }

    #[test]
    fn candidate_rows_lanes_match_the_definition() {
        lanes_match_the_definition::<f32>();
        lanes_match_the_definition::<f64>();
    }

    /// The f32 threshold (`logf`) stays within 1e-4 of `ln(alpha_min / o) −
    /// 0.01` evaluated in f64, so below `ln(alpha_min / o) − 0.0099`, over
    /// opacities from the smallest subnormal to the largest finite f32, and
    /// keeps the special values.
    #[test]
    fn f32_power_min_is_close_to_the_f64_one() {
        let amin = (1.0f32 / 255.0) as f64;
        let mut rng = Rng::new(5);
        let mut checked = 0;
        for i in 0..200_000 {
            // Log-uniform over the positive finite f32 values, plus 1 and
            // the ends.
            let o = match i {
                0 => f32::from_bits(1),
                1 => f32::MAX,
                2 => 1.0,
                _ => f32::from_bits(1 + rng.below(0x7f7f_ffff) as u32),
            };
            let got = power_min(o) as f64;
            let ratio = amin / o as f64;
            if ratio > f32::MAX as f64 {
                // The f32 ratio overflows: every pair is skipped, as the
                // alpha rule would (o < alpha_min).
                assert_eq!(got, f64::INFINITY, "o {o:e}");
                continue;
            }
            let exact = libm::log(ratio) - 0.01;
            assert!((got - exact).abs() < 1e-4, "o {o:e}: {got} against {exact}");
            assert!(got < libm::log(ratio) - 0.0099, "o {o:e}");
            checked += 1;
        }
        assert!(checked > 190_000, "{checked}");
        assert_eq!(power_min(0.0f32), f32::INFINITY);
        assert_eq!(power_min(-1.0f32), f32::INFINITY);
        assert_eq!(power_min(f32::NAN), f32::NEG_INFINITY);
        assert_eq!(power_min(f32::INFINITY), f32::NEG_INFINITY);
    }

    #[test]
    fn walk_equals_unfiltered_f32() {
        walk_equals_unfiltered::<f32>();
    }

    #[test]
    fn walk_equals_unfiltered_f64() {
        walk_equals_unfiltered::<f64>();
    }
}
