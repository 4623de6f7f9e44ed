//! Moving a block of Gaussians' values between their rows (one Gaussian's
//! values side by side, as the arrays store them) and value-major
//! [`Pack`]s (one value of every Gaussian side by side, as the lane-parallel
//! code computes with them).
//!
//! In f32 with AVX-512 and 16 lanes, or AVX2 and a multiple of 8 lanes (in
//! groups of 8), rows of any length move in column blocks of 16 (or 8)
//! values, each by masked loads, a transpose in registers and masked
//! stores; with AVX-512, rows (or a last column block) of at most four
//! values move by a 4×4 transpose within each 128-bit lane instead, an
//! eighth of the shuffles (the chain rule's means, scales and rotations: on
//! one thread of the Zen 4 machine the 64×64 bench frame's backward took
//! 5–7 µs less, benches/README.md, "Rasterizer: narrow rows moved with
//! fewer shuffles"); otherwise (f64, other lane counts, the portable path)
//! value by value. All only move bits, so every path gives the same values. Rows
//! may be anywhere ([`RowMover::load`], [`RowMover::store`]: a bounds check
//! per lane) or evenly spaced ([`RowMover::load_strided`],
//! [`RowMover::store_strided`]: one check per block).

use super::rasterize::{path, Path};
use crate::math::pack::Pack;
use crate::math::Real;

/// Moves rows on the path the CPU runs, read once when made (by
/// [`RowMover::new`]; its field cannot be set otherwise, so it only names
/// a path the CPU has).
#[derive(Clone, Copy)]
pub(crate) struct RowMover {
    p: Path,
}

impl RowMover {
    /// The path of `T` now ([`path`]).
    #[inline(always)]
    pub(crate) fn new<T: Real>() -> Self {
        RowMover { p: path::<T>() }
    }

    /// Whether blocks of `L` lanes of `T` move by vector shuffles.
    #[inline(always)]
    fn wide<T: Real, const L: usize>(self) -> bool {
        // The vector code reinterprets the values as f32.
        if std::any::TypeId::of::<T>() != std::any::TypeId::of::<f32>() {
            return false;
        }
        match self.p {
            #[cfg(target_arch = "x86_64")]
            Path::Avx512 => L == 16,
            #[cfg(target_arch = "x86_64")]
            Path::Avx2 => L.is_multiple_of(8),
            Path::Portable => false,
        }
    }

    /// `out[a]`, lane `l`, is `src[at[l] + a]` for every `a < out.len()`.
    ///
    /// Panics when a row `at[l] .. at[l] + out.len()` runs past `src`.
    #[inline(always)]
    pub(crate) fn load<T: Real, const L: usize>(
        self,
        src: &[T],
        at: &[usize; L],
        out: &mut [Pack<T, L>],
    ) {
        let w = out.len();
        for &a in at {
            assert!(
                w <= src.len() && a <= src.len() - w,
                "RowMover::load: a row runs past the values"
            );
        }
        // SAFETY: every row is inside `src` (asserted above).
        unsafe { self.load_unchecked(src, |l| at[l], out) }
    }

    /// [`RowMover::load`] with lane `l`'s row at `first + l·stride` (one
    /// bounds check for the block, no per-lane offsets to form).
    ///
    /// Panics when the last lane's row runs past `src`.
    #[inline(always)]
    pub(crate) fn load_strided<T: Real, const L: usize>(
        self,
        src: &[T],
        first: usize,
        stride: usize,
        out: &mut [Pack<T, L>],
    ) {
        assert!(
            last_row_end::<L>(first, stride, out.len()).is_some_and(|e| e <= src.len()),
            "RowMover::load_strided: a row runs past the values"
        );
        // SAFETY: the rows start at `first + l·stride`, ascending in `l`,
        // and the last one ends inside `src` (asserted above).
        unsafe { self.load_unchecked(src, |l| first + l * stride, out) }
    }

    /// `out[a]`, lane `l`, is `src[at(l) + a]`.
    ///
    /// # Safety
    /// `at(l) + out.len() <= src.len()` for every lane `l < L`.
    #[inline(always)]
    unsafe fn load_unchecked<T: Real, const L: usize>(
        self,
        src: &[T],
        at: impl Fn(usize) -> usize,
        out: &mut [Pack<T, L>],
    ) {
        let w = out.len();
        #[cfg(target_arch = "x86_64")]
        {
            let p = self.p;
            let wide = self.wide::<T, L>();
            if wide {
                let s = src.as_ptr() as *const f32;
                let o = out.as_mut_ptr() as *mut f32;
                let step = if p == Path::Avx512 { 16 } else { 8 };
                for c in (0..w).step_by(step) {
                    let n = step.min(w - c);
                    for g in (0..L).step_by(step) {
                        // SAFETY: `wide` holds only for T = f32 and a path of
                        // this CPU (`RowMover::new`); `Pack` is a transparent
                        // `[T; L]`, so `out` is `w` rows of `L` f32 values and
                        // value `c + j`, lane `g + l` is at `o + L·(c + j) + g + l`;
                        // row `at(g + l)` holds values `c .. c + n` (the
                        // caller's guarantee); `g + l < L` (L is 16 with
                        // AVX-512, a multiple of 8 with AVX2).
                        unsafe {
                            if p == Path::Avx512 {
                                x86::load16(|l| s.add(at(l) + c), n, o.add(L * c), L);
                            } else {
                                x86::load8(|l| s.add(at(g + l) + c), n, o.add(L * c + g), L);
                            }
                        }
                    }
                }
                return;
            }
        }
        for (a, o) in out.iter_mut().enumerate() {
            *o = Pack(std::array::from_fn(|l| src[at(l) + a]));
        }
    }

    /// `dst[at[l] + a] = vals[a]`, lane `l`, for every `a < vals.len()` and
    /// every lane `l` whose bit is set in `lanes`; the other values of `dst`
    /// are left as they are.
    ///
    /// Panics when the row `at[l] .. at[l] + vals.len()` of a written lane runs
    /// past `dst`.
    #[inline(always)]
    pub(crate) fn store<T: Real, const L: usize>(
        self,
        dst: &mut [T],
        at: &[usize; L],
        lanes: u32,
        vals: &[Pack<T, L>],
    ) {
        let w = vals.len();
        for (l, &a) in at.iter().enumerate() {
            assert!(
                lanes >> l & 1 == 0 || (w <= dst.len() && a <= dst.len() - w),
                "RowMover::store: a row runs past the values"
            );
        }
        // SAFETY: the row of every written lane is inside `dst` (asserted
        // above).
        unsafe { self.store_unchecked(dst, |l| at[l], lanes, vals) }
    }

    /// [`RowMover::store`] with lane `l`'s row at `first + l·stride` (one
    /// bounds check for the block, no per-lane offsets to form).
    ///
    /// Panics when the last lane's row runs past `dst`, written or not.
    #[inline(always)]
    pub(crate) fn store_strided<T: Real, const L: usize>(
        self,
        dst: &mut [T],
        first: usize,
        stride: usize,
        lanes: u32,
        vals: &[Pack<T, L>],
    ) {
        assert!(
            last_row_end::<L>(first, stride, vals.len()).is_some_and(|e| e <= dst.len()),
            "RowMover::store_strided: a row runs past the values"
        );
        // SAFETY: the rows start at `first + l·stride`, ascending in `l`,
        // and the last one ends inside `dst` (asserted above).
        unsafe { self.store_unchecked(dst, |l| first + l * stride, lanes, vals) }
    }

    /// `dst[at(l) + a] = vals[a]`, lane `l`, for the lanes set in `lanes`.
    ///
    /// # Safety
    /// `at(l) + vals.len() <= dst.len()` for every lane `l` set in `lanes`.
    #[inline(always)]
    unsafe fn store_unchecked<T: Real, const L: usize>(
        self,
        dst: &mut [T],
        at: impl Fn(usize) -> usize,
        lanes: u32,
        vals: &[Pack<T, L>],
    ) {
        let w = vals.len();
        #[cfg(target_arch = "x86_64")]
        {
            let p = self.p;
            let wide = self.wide::<T, L>();
            if wide {
                let d = dst.as_mut_ptr() as *mut f32;
                let v = vals.as_ptr() as *const f32;
                let step = if p == Path::Avx512 { 16 } else { 8 };
                for c in (0..w).step_by(step) {
                    let n = step.min(w - c);
                    for g in (0..L).step_by(step) {
                        let live = (lanes >> g) & ((1 << step) - 1);
                        if live == 0 {
                            continue;
                        }
                        // SAFETY: as in `load_unchecked`; the rows of the
                        // lanes written hold values `c .. c + n` (the
                        // caller's guarantee), and the kernels address only
                        // the lanes written.
                        unsafe {
                            if p == Path::Avx512 {
                                x86::store16(|l| d.add(at(l) + c), live, n, v.add(L * c), L);
                            } else {
                                x86::store8(|l| d.add(at(g + l) + c), live, n, v.add(L * c + g), L);
                            }
                        }
                    }
                }
                return;
            }
        }
        for (a, v) in vals.iter().enumerate() {
            for l in (0..L).filter(|&l| lanes >> l & 1 != 0) {
                dst[at(l) + a] = v.0[l];
            }
        }
    }
}

/// The end of the last of `L` rows of `w` values starting at `first`,
/// `first + stride`, …; `None` on overflow.
#[inline(always)]
fn last_row_end<const L: usize>(first: usize, stride: usize, w: usize) -> Option<usize> {
    (L.checked_sub(1)?)
        .checked_mul(stride)?
        .checked_add(first)?
        .checked_add(w)
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    /// The 16×16 transpose: lane `l` of result `j` is lane `j` of `r[l]`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn t16(mut r: [__m512; 16]) -> [__m512; 16] {
        let mut t = [_mm512_setzero_ps(); 16];
        // 32-bit interleave of row pairs, then 64-bit of pair pairs: each
        // 128-bit lane q of r[4a + b] then holds column 4q + b of rows
        // 4a .. 4a + 3.
        for k in 0..8 {
            t[2 * k] = _mm512_unpacklo_ps(r[2 * k], r[2 * k + 1]);
            t[2 * k + 1] = _mm512_unpackhi_ps(r[2 * k], r[2 * k + 1]);
        }
        let pd = |x: __m512| _mm512_castps_pd(x);
        let ps = |x: __m512d| _mm512_castpd_ps(x);
        for k in 0..4 {
            let b = 4 * k;
            r[b] = ps(_mm512_unpacklo_pd(pd(t[b]), pd(t[b + 2])));
            r[b + 1] = ps(_mm512_unpackhi_pd(pd(t[b]), pd(t[b + 2])));
            r[b + 2] = ps(_mm512_unpacklo_pd(pd(t[b + 1]), pd(t[b + 3])));
            r[b + 3] = ps(_mm512_unpackhi_pd(pd(t[b + 1]), pd(t[b + 3])));
        }
        // Gather the 128-bit lanes in two steps.
        for k in 0..4 {
            t[k] = _mm512_shuffle_f32x4::<0x88>(r[k], r[k + 4]);
            t[k + 4] = _mm512_shuffle_f32x4::<0xdd>(r[k], r[k + 4]);
            t[k + 8] = _mm512_shuffle_f32x4::<0x88>(r[k + 8], r[k + 12]);
            t[k + 12] = _mm512_shuffle_f32x4::<0xdd>(r[k + 8], r[k + 12]);
        }
        for k in 0..8 {
            r[k] = _mm512_shuffle_f32x4::<0x88>(t[k], t[k + 8]);
            r[k + 8] = _mm512_shuffle_f32x4::<0xdd>(t[k], t[k + 8]);
        }
        r
    }

    /// `out[stride·j + l] = row(l)[j]` for `l < 16`, `j < n ≤ 16`.
    ///
    /// # Safety
    /// AVX-512F is present; `row(l)` can be read for `n` values and `out`
    /// written at `stride·j + l` for `l < 16`, `j < n`, `stride ≥ 16`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(super) unsafe fn load16(
        row: impl Fn(usize) -> *const f32,
        n: usize,
        out: *mut f32,
        stride: usize,
    ) {
        let m = ((1u32 << n) - 1) as __mmask16;
        if n <= 4 {
            // SAFETY: the caller guarantees the extents; each masked load
            // reads the `n` values of one row only, and the stores write
            // `out` at `stride·j + l` for `j < n`.
            unsafe {
                // `x[k]`, 128-bit lane `q`: the values of row `4q + k`.
                let x: [__m512; 4] = std::array::from_fn(|k| {
                    let part =
                        |q: usize| _mm512_castps512_ps128(_mm512_maskz_loadu_ps(m, row(4 * q + k)));
                    let z = _mm512_castps128_ps512(part(0));
                    let z = _mm512_insertf32x4::<1>(z, part(1));
                    let z = _mm512_insertf32x4::<2>(z, part(2));
                    _mm512_insertf32x4::<3>(z, part(3))
                });
                let t = t4_lanes(x);
                for (j, v) in t.iter().enumerate().take(n) {
                    _mm512_storeu_ps(out.add(stride * j), *v);
                }
            }
            return;
        }
        // SAFETY: the caller guarantees the extents; masked-off values are
        // not read.
        unsafe {
            let t = t16(std::array::from_fn(|l| _mm512_maskz_loadu_ps(m, row(l))));
            for (j, v) in t.iter().enumerate().take(n) {
                _mm512_storeu_ps(out.add(stride * j), *v);
            }
        }
    }

    /// The 4×4 transpose within each 128-bit lane: lane `q`, element `i` of
    /// result `j` is lane `q`, element `j` of `r[i]`. Moves rows of at
    /// most four values: 8 shuffles, against the 64 of [`t16`].
    #[target_feature(enable = "avx512f")]
    #[inline]
    fn t4_lanes(r: [__m512; 4]) -> [__m512; 4] {
        let pd = |x: __m512| _mm512_castps_pd(x);
        let ps = |x: __m512d| _mm512_castpd_ps(x);
        // Per lane: [r0.0 r1.0 r0.1 r1.1], [r0.2 r1.2 r0.3 r1.3], and the
        // same of r2 and r3.
        let t0 = pd(_mm512_unpacklo_ps(r[0], r[1]));
        let t1 = pd(_mm512_unpackhi_ps(r[0], r[1]));
        let t2 = pd(_mm512_unpacklo_ps(r[2], r[3]));
        let t3 = pd(_mm512_unpackhi_ps(r[2], r[3]));
        [
            ps(_mm512_unpacklo_pd(t0, t2)),
            ps(_mm512_unpackhi_pd(t0, t2)),
            ps(_mm512_unpacklo_pd(t1, t3)),
            ps(_mm512_unpackhi_pd(t1, t3)),
        ]
    }

    /// `row(l)[j] = vals[stride·j + l]` for `j < n ≤ 16` and the lanes `l`
    /// whose bit is set in `lanes`.
    ///
    /// # Safety
    /// AVX-512F is present; `vals` can be read at `stride·j + l` for
    /// `l < 16`, `j < n`, and `row(l)` written for `n` values for every
    /// lane set in `lanes`.
    #[target_feature(enable = "avx512f")]
    #[inline]
    pub(super) unsafe fn store16(
        row: impl Fn(usize) -> *mut f32,
        lanes: u32,
        n: usize,
        vals: *const f32,
        stride: usize,
    ) {
        let m = ((1u32 << n) - 1) as __mmask16;
        // Value `j` of the 16 lanes (zeros past `n`).
        let value = |j: usize| {
            if j < n {
                // SAFETY: the caller guarantees `vals` can be read here.
                unsafe { _mm512_loadu_ps(vals.add(stride * j)) }
            } else {
                _mm512_setzero_ps()
            }
        };
        if n <= 4 {
            let y = t4_lanes(std::array::from_fn(value));
            for l in (0..16).filter(|&l| lanes >> l & 1 != 0) {
                let (q, k) = (l / 4, l % 4);
                // SAFETY: the caller guarantees row `l` can be written for
                // `n` values, and this store writes those only: the lane `q`
                // of `y[k]` holds row `4q + k`, and the masked store of the
                // whole vector at the row's address less `4q` writes its
                // elements `4q .. 4q + n` (the pointer is only formed,
                // wrapping: no value outside the row is touched).
                unsafe { _mm512_mask_storeu_ps(row(l).wrapping_sub(4 * q), m << (4 * q), y[k]) };
            }
            return;
        }
        // SAFETY: the caller guarantees the extents; masked-off values and
        // lanes are not written.
        unsafe {
            let t = t16(std::array::from_fn(value));
            for (l, v) in t.iter().enumerate() {
                if lanes >> l & 1 != 0 {
                    _mm512_mask_storeu_ps(row(l), m, *v);
                }
            }
        }
    }

    /// The 8×8 transpose: lane `l` of result `j` is lane `j` of `r[l]`.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn t8(r: [__m256; 8]) -> [__m256; 8] {
        let mut t = [_mm256_setzero_ps(); 8];
        for k in 0..4 {
            t[2 * k] = _mm256_unpacklo_ps(r[2 * k], r[2 * k + 1]);
            t[2 * k + 1] = _mm256_unpackhi_ps(r[2 * k], r[2 * k + 1]);
        }
        let mut u = [_mm256_setzero_ps(); 8];
        for k in 0..2 {
            let b = 4 * k;
            u[b] = _mm256_shuffle_ps::<0x44>(t[b], t[b + 2]);
            u[b + 1] = _mm256_shuffle_ps::<0xEE>(t[b], t[b + 2]);
            u[b + 2] = _mm256_shuffle_ps::<0x44>(t[b + 1], t[b + 3]);
            u[b + 3] = _mm256_shuffle_ps::<0xEE>(t[b + 1], t[b + 3]);
        }
        let mut o = [_mm256_setzero_ps(); 8];
        for k in 0..4 {
            o[k] = _mm256_permute2f128_ps::<0x20>(u[k], u[k + 4]);
            o[k + 4] = _mm256_permute2f128_ps::<0x31>(u[k], u[k + 4]);
        }
        o
    }

    /// The mask of the first `n ≤ 8` values for `maskload` / `maskstore`.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn first(n: usize) -> __m256i {
        let i = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        _mm256_cmpgt_epi32(_mm256_set1_epi32(n as i32), i)
    }

    /// `out[stride·j + l] = row(l)[j]` for `l < 8`, `j < n ≤ 8`.
    ///
    /// # Safety
    /// AVX2 is present; `row(l)` can be read for `n` values and `out`
    /// written at `stride·j + l` for `l < 8`, `j < n`, `stride ≥ 8`.
    #[target_feature(enable = "avx2")]
    #[inline]
    pub(super) unsafe fn load8(
        row: impl Fn(usize) -> *const f32,
        n: usize,
        out: *mut f32,
        stride: usize,
    ) {
        let m = first(n);
        // SAFETY: the caller guarantees the extents; masked-off values are
        // not read.
        unsafe {
            let t = t8(std::array::from_fn(|l| _mm256_maskload_ps(row(l), m)));
            for (j, v) in t.iter().enumerate().take(n) {
                _mm256_storeu_ps(out.add(stride * j), *v);
            }
        }
    }

    /// `row(l)[j] = vals[stride·j + l]` for `j < n ≤ 8` and the lanes `l`
    /// whose bit is set in `lanes`.
    ///
    /// # Safety
    /// AVX2 is present; `vals` can be read at `stride·j + l` for `l < 8`,
    /// `j < n`, and `row(l)` written for `n` values for every lane set in
    /// `lanes`.
    #[target_feature(enable = "avx2")]
    #[inline]
    pub(super) unsafe fn store8(
        row: impl Fn(usize) -> *mut f32,
        lanes: u32,
        n: usize,
        vals: *const f32,
        stride: usize,
    ) {
        let m = first(n);
        // SAFETY: the caller guarantees the extents; masked-off values and
        // lanes are not written.
        unsafe {
            let t = t8(std::array::from_fn(|j| {
                if j < n {
                    _mm256_loadu_ps(vals.add(stride * j))
                } else {
                    _mm256_setzero_ps()
                }
            }));
            for (l, v) in t.iter().enumerate() {
                if lanes >> l & 1 != 0 {
                    _mm256_maskstore_ps(row(l), m, *v);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::fastmath::{force_isa, isa_test_lock, Isa};

    /// Every path moves the same values as the definition, for widths across
    /// the vector blocks, scattered and overlapping rows, and partial lanes.
    fn round_trip<T: Real, const L: usize>() {
        // Long enough for the widest evenly spaced rows below.
        let src: Vec<T> = (0..1200)
            .map(|i| T::from_f64(i as f64 * 0.5 - 3.0))
            .collect();
        for w in [
            1usize, 2, 3, 4, 5, 7, 8, 9, 10, 15, 16, 17, 19, 20, 24, 33, 48,
        ] {
            let at: [usize; L] = std::array::from_fn(|l| (l * 37 + w * 5) % (700 - w));
            let mut packs = vec![Pack([T::ZERO; L]); w];
            RowMover::new::<T>().load(&src, &at, &mut packs);
            for (a, p) in packs.iter().enumerate() {
                for l in 0..L {
                    assert_eq!(p.0[l], src[at[l] + a], "load w {w} value {a} lane {l}");
                }
            }
            // Evenly spaced rows, overlapping (stride below w), touching or
            // apart, against the same rows given lane by lane.
            for stride in [0usize, 1, w, w + 3] {
                let first = (w * 7) % 50;
                let at: [usize; L] = std::array::from_fn(|l| first + l * stride);
                let mut by_lane = vec![Pack([T::ZERO; L]); w];
                RowMover::new::<T>().load(&src, &at, &mut by_lane);
                let mut strided = vec![Pack([T::ONE; L]); w];
                RowMover::new::<T>().load_strided(&src, first, stride, &mut strided);
                assert!(strided == by_lane, "load_strided w {w} stride {stride}");
            }
            for lanes in [
                0u32,
                1,
                (1 << L) - 1,
                0b1010_0110_0101_1001 & ((1 << L) - 1),
            ] {
                // Disjoint rows so that each written value has one writer.
                let at: [usize; L] = std::array::from_fn(|l| 3 + l * (w + 2));
                let mut dst = vec![T::from_f64(-1.0); 3 + L * (w + 2)];
                RowMover::new::<T>().store(&mut dst, &at, lanes, &packs);
                let mut want = vec![T::from_f64(-1.0); dst.len()];
                for l in (0..L).filter(|&l| lanes >> l & 1 != 0) {
                    for a in 0..w {
                        want[at[l] + a] = packs[a].0[l];
                    }
                }
                assert_eq!(dst, want, "store w {w} lanes {lanes:b}");
                let mut strided = vec![T::from_f64(-1.0); dst.len()];
                RowMover::new::<T>().store_strided(&mut strided, 3, w + 2, lanes, &packs);
                assert_eq!(strided, want, "store_strided w {w} lanes {lanes:b}");
            }
        }
    }

    /// Rows that end exactly at the end of the values, on every path: a
    /// mask one value too wide would read or write past it.
    fn last_rows<T: Real, const L: usize>() {
        for w in [1usize, 2, 3, 4, 10, 16, 17, 20, 48] {
            let len = L * w;
            let src: Vec<T> = (0..len).map(|i| T::from_f64(i as f64 + 1.0)).collect();
            // Lane l reads row L − 1 − l, the first lane the last row.
            let at: [usize; L] = std::array::from_fn(|l| (L - 1 - l) * w);
            let mut packs = vec![Pack([T::ZERO; L]); w];
            let mover = RowMover::new::<T>();
            mover.load(&src, &at, &mut packs);
            let mut dst = vec![T::ZERO; len];
            mover.store(&mut dst, &at, u32::MAX >> (32 - L), &packs);
            assert_eq!(dst, src, "w {w}");
            // The same rows evenly spaced: the last lane reads and writes
            // the last row.
            let mut strided = vec![Pack([T::ZERO; L]); w];
            mover.load_strided(&src, 0, w, &mut strided);
            let mut dst = vec![T::ZERO; len];
            mover.store_strided(&mut dst, 0, w, u32::MAX >> (32 - L), &strided);
            assert_eq!(dst, src, "strided w {w}");
        }
    }

    #[test]
    fn rows_ending_at_the_end_of_the_values_move_whole() {
        let _guard = isa_test_lock();
        for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
            if !force_isa(Some(isa)) {
                continue;
            }
            last_rows::<f32, 16>();
            last_rows::<f32, 8>();
            last_rows::<f64, 16>();
        }
        force_isa(None);
    }

    #[test]
    #[should_panic(expected = "a row runs past the values")]
    fn a_row_past_the_end_is_refused_on_load() {
        let src = [0.0f32; 20];
        let mut out = [Pack([0.0f32; 16]); 5];
        RowMover::new::<f32>().load(&src, &[16; 16], &mut out);
    }

    #[test]
    #[should_panic(expected = "a row runs past the values")]
    fn a_written_row_past_the_end_is_refused_on_store() {
        let mut dst = [0.0f32; 20];
        let vals = [Pack([1.0f32; 16]); 5];
        // Lane 3 is written and its row 16..21 runs past 20.
        let mut at = [0usize; 16];
        at[3] = 16;
        RowMover::new::<f32>().store(&mut dst, &at, 1 << 3, &vals);
    }

    #[test]
    #[should_panic(expected = "a row runs past the values")]
    fn an_evenly_spaced_row_past_the_end_is_refused_on_load() {
        let src = [0.0f32; 16 * 3];
        let mut out = [Pack([0.0f32; 16]); 3];
        // Rows 1..4, 4..7, …: the last ends at 48, one past the values.
        RowMover::new::<f32>().load_strided(&src, 1, 3, &mut out);
    }

    #[test]
    #[should_panic(expected = "a row runs past the values")]
    fn an_evenly_spaced_row_past_the_end_is_refused_on_store() {
        let mut dst = [0.0f32; 16 * 3];
        let vals = [Pack([1.0f32; 16]); 3];
        // Checked for every lane, written or not.
        RowMover::new::<f32>().store_strided(&mut dst, 1, 3, 1, &vals);
    }

    #[test]
    #[should_panic(expected = "a row runs past the values")]
    fn an_overflowing_stride_is_refused() {
        let src = [0.0f32; 4];
        let mut out = [Pack([0.0f32; 4]); 1];
        RowMover::new::<f32>().load_strided(&src, 0, usize::MAX / 2, &mut out);
    }

    #[test]
    fn every_path_moves_the_values_of_the_definition() {
        let _guard = isa_test_lock();
        for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
            if !force_isa(Some(isa)) {
                continue;
            }
            round_trip::<f32, 16>();
            round_trip::<f32, 8>();
            round_trip::<f32, 4>();
            round_trip::<f64, 16>();
            round_trip::<f64, 4>();
        }
        force_isa(None);
    }
}
