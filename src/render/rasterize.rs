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
//! the `exp`: `power_min = ln(alpha_min / o) − 0.01` (computed in f64), so
//! `o·exp(power) < alpha_min·e^{−0.01}`, well inside the alpha-skip rule
//! whatever the rounding of `exp` (≤ 1 ulp) and of the product. A row whose
//! lanes all skip an entry does no further work for it.
//!
//! Image rows are independent and own their pixels, so the forward runs in
//! parallel over rows with no reduction across threads.

use super::lanes::{Lanes, Scalar};
use super::BLOCK;
use crate::kernels::fastmath;
use crate::math::Real;

/// Pixels per row group (one tile row).
pub(crate) const LANES: usize = BLOCK;

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
}

/// [`Splat::power_min`] for opacity `o` (see the module docs).
pub(crate) fn power_min<T: Real>(o: T) -> T {
    let o = o.to_f64();
    T::from_f64(if !o.is_finite() {
        f64::NEG_INFINITY
    } else if o <= 0.0 {
        f64::INFINITY
    } else {
        libm::log(Blend::<T>::new().alpha_min.to_f64() / o) - 0.01
    })
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

/// A list entry at which at least one lane of a row blended, recorded by the
/// backward's forward walk: the transmittance before the entry, `exp(power)`
/// and the mask of blending lanes (bit `l` for lane `l`).
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

/// Walk `splats` front to back for one row; with `REC`, push a [`Record`]
/// for every entry at which some lane blends.
#[inline(always)]
pub(crate) fn walk_row<V: Lanes, const REC: bool>(
    splats: &[Splat<V::T>],
    row: Row,
    k: &Blend<V::T>,
    rec: &mut Vec<Record<V::T>>,
) -> RowState<V::T> {
    let zero = V::T::ZERO;
    let px = V::load(&lane_x::<V::T>(row));
    let pyf = V::T::from_usize(row.py);
    let mut t = V::splat(V::T::ONE);
    let mut c = [V::splat(zero); 3];
    let mut d = V::splat(zero);
    let mut last = [0u32; LANES];
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
    if active_bits != 0 {
        for (j, s) in splats.iter().enumerate() {
            evaluated += active_bits.count_ones() as u64;
            let dx = V::splat(s.xy[0]) - px;
            let p = power_lanes(s, dx, s.xy[1] - pyf, k);
            let cand = V::andnot(V::andnot(active, p.gt(vzero)), p.lt(V::splat(s.power_min)));
            if V::bits(cand) == 0 {
                continue;
            }
            let g = p.exp();
            let a = (V::splat(s.opacity) * g).min_of(amax);
            let hit = V::andnot(cand, a.lt(amin));
            let test_t = t * (one - a);
            let stop = V::and(hit, test_t.lt(tmin));
            let b = V::andnot(hit, stop);
            let b_bits = V::bits(b);
            if b_bits != 0 {
                for (cv, &col) in c.iter_mut().zip(&s.color) {
                    *cv = V::select(b, *cv + V::splat(col) * a * t, *cv);
                }
                d = V::select(b, d + V::splat(s.depth) * a * t, d);
                if REC {
                    let mut r = Record {
                        j: j as u32,
                        t: [zero; LANES],
                        g: [zero; LANES],
                        blend: b_bits,
                    };
                    t.store(&mut r.t);
                    g.store(&mut r.g);
                    rec.push(r);
                }
                t = V::select(b, test_t, t);
                let mut m = b_bits;
                while m != 0 {
                    last[m.trailing_zeros() as usize] = j as u32 + 1;
                    m &= m - 1;
                }
            }
            let stop_bits = V::bits(stop);
            if stop_bits != 0 {
                active_bits &= !stop_bits;
                active = V::from_bits(active_bits);
                if active_bits == 0 {
                    break;
                }
            }
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

/// Output slices of one image row (channel-major image, so each channel's
/// row is contiguous).
pub(crate) struct RowOut<'a, T> {
    pub color: [&'a mut [T]; 3],
    pub depth: &'a mut [T],
    pub final_t: &'a mut [T],
    pub n_contrib: &'a mut [u32],
    /// Per tile the row crosses: the largest `n_contrib` of its pixels there
    /// (the backward's forward walk of the row ends at it).
    pub row_last: &'a mut [u32],
}

/// What every row of a frame reads.
pub(crate) struct Frame<'a, T> {
    /// The gathered list of every tile, in list order.
    pub splats: &'a [Splat<T>],
    /// `[start, end)` into `splats` per tile (row-major tile order).
    pub ranges: &'a [[u32; 2]],
    pub grid_x: usize,
    pub width: usize,
    pub bg: [T; 3],
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
    let ty = py / BLOCK;
    let mut none = Vec::new();
    for tx in 0..f.grid_x {
        let x0 = tx * BLOCK;
        let nx = BLOCK.min(f.width - x0);
        let [s, e] = f.ranges[ty * f.grid_x + tx];
        let st = walk_row::<V, false>(
            &f.splats[s as usize..e as usize],
            Row { x0, nx, py },
            &k,
            &mut none,
        );
        for l in 0..nx {
            let t = st.t[l];
            for ch in 0..3 {
                out.color[ch][x0 + l] = st.c[ch][l] + t * f.bg[ch];
            }
            out.depth[x0 + l] = st.d[l];
            out.final_t[x0 + l] = t;
            out.n_contrib[x0 + l] = st.last[l];
        }
        out.row_last[tx] = st.last.iter().copied().max().unwrap_or(0);
        *evaluated += st.evaluated;
    }
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
    if T::PRECISION != crate::math::Precision::F32 {
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
    unsafe { &mut *(x as *mut X as *mut Y) }
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
                let f32f: &Frame<'_, f32> = &*(f as *const Frame<'_, T> as *const Frame<'_, f32>);
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
