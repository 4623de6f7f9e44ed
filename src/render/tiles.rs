//! Binning of projected Gaussians into 16×16 tiles, in the order the Inria
//! rasterizer blends them.
//!
//! Upstream emits one `(tile << 32 | depth bits, gaussian)` pair per touched
//! tile and radix-sorts the pairs stably, so equal keys keep ascending
//! Gaussian index: the order is `(tile, depth bits, gaussian index)`. Depth
//! is positive (> 0.2), so its IEEE bit pattern orders like its value.
//!
//! Here the Gaussians that touch a tile are sorted once by
//! `(depth bits, index)`: their packed keys (depth bits above the index;
//! `u64` for `f32`, `u128` for `f64`) are collected in ascending index and
//! sorted stably by depth bits with a least-significant-digit radix sort.
//! A counting sort by tile in that order then gives every tile its entries
//! already in `(depth bits, index)` order, with no per-tile sort. The
//! counting sort runs in parallel with the result of a serial one: the
//! sorted Gaussians are split into contiguous chunks whose number depends
//! only on how many there are ([`chunk_len`]); one parallel pass counts each
//! chunk's entries per tile, an exclusive prefix sum over tiles, then over
//! chunks in order, gives every (chunk, tile) pair its first slot, and a
//! second parallel pass writes each chunk's entries in its sorted order.
//! Chunk `c`'s entries of a tile therefore follow those of chunks `0..c`,
//! which is the serial order, on any thread count.
//! With one chunk (at most 4,096 Gaussians that touch a tile) the counts
//! are the tiles' totals, which do not depend on the order: they are taken
//! from the projected Gaussians alongside the radix sort.
//!
//! Small frames on two or more threads ([`two_runs_apply`]) are binned
//! another way, with no serial step and no step of its own: each of two
//! workers sorts the consecutive Gaussians it has just projected into a
//! [`Run`], their entries tile by tile
//! (`render::project_and_bin_in_two_runs`); then the blend merges each
//! tile's entries of the two runs where it first needs them
//! ([`merge_tile`], `rasterize::TileRowSplats`). The list and ranges are
//! the same.

use super::project::Projected;
use crate::error::{Error, Result};
use crate::math::Real;
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// The sorted list and per-tile ranges.
#[derive(Clone, Debug, Default)]
pub(crate) struct Binning {
    /// Gaussian index of each sorted entry.
    pub list: Vec<u32>,
    /// `[start, end)` into `list` per tile (row-major tile order).
    pub ranges: Vec<[u32; 2]>,
}

/// The fewest Gaussians per task of the element-wise steps.
const MIN_TASK: usize = 4096;

/// Gaussians per chunk of the counting sort for `n` Gaussians: chunks of
/// about 4096, at most 32 of them (so the per-(chunk, tile) counts stay
/// small), all but the last of equal length. Depends on `n` only; the
/// result of [`bin`] does not depend on it at all.
fn chunk_len(n: usize) -> usize {
    const TARGET: usize = 4096;
    const MAX_CHUNKS: usize = 32;
    let chunks = n.div_ceil(TARGET).clamp(1, MAX_CHUNKS);
    n.div_ceil(chunks).max(1)
}

/// A sort key: depth bits in the high part, Gaussian index in the
/// low 32 bits, so integer order is `(depth bits, index)` order.
pub(crate) trait Key: Copy + Ord + Send + Sync {
    /// Significant bits of the depth's IEEE pattern.
    const DEPTH_BITS: u32;
    /// Above every key of a Gaussian (index below `u32::MAX`).
    const LAST: Self;
    fn new(depth_bits: u64, index: u32) -> Self;
    fn depth(self) -> u64;
    fn index(self) -> u32;
}

impl Key for u64 {
    const DEPTH_BITS: u32 = 32;
    const LAST: Self = u64::MAX;
    #[inline(always)]
    fn depth(self) -> u64 {
        self >> 32
    }
    #[inline(always)]
    fn new(depth_bits: u64, index: u32) -> Self {
        depth_bits << 32 | index as u64
    }
    #[inline(always)]
    fn index(self) -> u32 {
        self as u32
    }
}

impl Key for u128 {
    const DEPTH_BITS: u32 = 64;
    const LAST: Self = (1 << 96) - 1;
    #[inline(always)]
    fn depth(self) -> u64 {
        (self >> 32) as u64
    }
    #[inline(always)]
    fn new(depth_bits: u64, index: u32) -> Self {
        (depth_bits as u128) << 32 | index as u128
    }
    #[inline(always)]
    fn index(self) -> u32 {
        self as u32
    }
}

/// Bin `proj` on a `grid` of `[tiles x, tiles y]` (see the module docs).
///
/// Fails when the list would hold more than `u32::MAX` entries.
pub(crate) fn bin<T: Real>(proj: &[Projected<T>], grid: [u32; 2]) -> Result<Binning> {
    if std::mem::size_of::<T>() <= 4 {
        bin_keyed::<T, u64>(proj, grid)
    } else {
        bin_keyed::<T, u128>(proj, grid)
    }
}

/// Whether [`run`] and [`merge_tile`] bin a frame of `n` Gaussians on this
/// pool: small frames (at most `2·MIN_TASK` = 8,192 Gaussians; on larger
/// ones [`bin`] measured faster, benches/README.md, "Rasterizer: small
/// frames sorted in two halves") on two or more threads.
pub(crate) fn two_runs_apply(n: usize) -> bool {
    n <= 2 * MIN_TASK && rayon::current_num_threads() >= 2
}

/// One piece of the Gaussians (consecutive indices) binned on its own:
/// each tile's entries of the piece, in `(depth bits, index)` order, tile
/// after tile.
pub(crate) struct Run<K> {
    /// Per tile (row-major), its entries' `[start, end)` counted without
    /// the bounds: its keys start at `ranges[t][0] + t` in `keys`.
    ranges: Vec<[u32; 2]>,
    /// The entries' keys, each tile's followed by [`Key::LAST`] (above
    /// every real key: no Gaussian has index `u32::MAX`), so that a merge
    /// never runs past a tile's end.
    keys: Vec<K>,
}

impl<K> Run<K> {
    /// Tile `t`'s number of entries.
    #[inline(always)]
    fn count(&self, t: usize) -> u32 {
        self.ranges[t][1] - self.ranges[t][0]
    }
}

/// The [`Run`] of the Gaussians `first..first + piece.len()`, whose
/// projections are `piece`, on a `grid` of tiles.
///
/// The piece's Gaussians that touch a tile are sorted by `(depth bits,
/// index)` ([`radix_sort_by_depth`]); then a counting sort by tile writes
/// each one's key into every tile it touches, in that order. All of it
/// runs on the thread that has just projected the piece, on its own lines.
/// Fails as [`bin`] does when the piece's entries alone are more than the
/// list may hold, before they are allocated.
pub(crate) fn run<T: Real, K: Key>(
    first: usize,
    piece: &[Projected<T>],
    grid: [u32; 2],
) -> Result<Run<K>> {
    let n_tiles = grid[0] as usize * grid[1] as usize;
    let mut keys: Vec<K> = Vec::with_capacity(piece.len());
    let mut counts = vec![0u32; n_tiles];
    for (i, p) in piece.iter().enumerate() {
        if touches_a_tile(p) {
            keys.push(K::new(p.depth.bits(), (first + i) as u32));
            count_tiles(std::iter::once(rect_of(p)), grid[0], &mut counts);
        }
    }
    radix_sort_by_depth(&mut keys);
    // (Sorted, so the last key is the largest.)
    assert!(
        keys.last().is_none_or(|&k| k < K::LAST),
        "a Gaussian that touches a tile has a key below the bound"
    );
    let ranges = tile_ranges(counts.iter().map(|&c| u64::from(c)))?;
    // Each tile's next key, one slot on per earlier tile (for its bound);
    // every slot not written below is a bound.
    let mut next: Vec<usize> = ranges
        .iter()
        .enumerate()
        .map(|(t, r)| r[0] as usize + t)
        .collect();
    let mut tile_keys = vec![K::LAST; ranges.last().map_or(0, |r| r[1] as usize) + n_tiles];
    for &k in &keys {
        let r = rect_of(&piece[k.index() as usize - first]);
        for y in r[1]..r[3] {
            let row = (y * grid[0]) as usize;
            for s in &mut next[row + r[0] as usize..row + r[2] as usize] {
                tile_keys[*s] = k;
                *s += 1;
            }
        }
    }
    Ok(Run {
        ranges,
        keys: tile_keys,
    })
}

/// Each tile's `[start, end)` in the list of two runs of one grid: the
/// ranges of [`bin`] for the Gaussians of both. Fails as [`bin`] does.
pub(crate) fn ranges_of_runs<K>(runs: &[Run<K>; 2]) -> Result<Vec<[u32; 2]>> {
    let [a, b] = runs;
    assert_eq!(a.ranges.len(), b.ranges.len(), "runs of one grid");
    tile_ranges((0..a.ranges.len()).map(|t| u64::from(a.count(t)) + u64::from(b.count(t))))
}

/// Tile `t`'s entries of two runs of one grid (of two consecutive pieces
/// of the Gaussians) merged into `list`, their Gaussians, and `copies`,
/// copies of their data in `data` (indexed by Gaussian): the tile's
/// entries of [`bin`], in its order. `list` and `copies` hold exactly the
/// tile's entries of both runs.
///
/// The merge of two tiles' entries sorted by `(depth bits, index)`, with
/// distinct indices, is the one sorted order. Each step takes the smaller
/// of the two next keys with no branch in the source on which run it
/// comes from: that varies from entry to entry, so a branch would be
/// mispredicted about half the time.
#[inline]
pub(crate) fn merge_tile<K: Key, S: Copy>(
    runs: &[Run<K>; 2],
    data: &[S],
    t: usize,
    list: &mut [MaybeUninit<u32>],
    copies: &mut [MaybeUninit<S>],
) {
    let [a, b] = runs;
    let [ca, cb] = [a.count(t) as usize, b.count(t) as usize];
    assert!(
        list.len() == ca + cb && copies.len() == ca + cb,
        "tile {t} holds {} entries of the runs, not {}",
        ca + cb,
        list.len()
    );
    // The tile's keys with their bounds.
    let ka = &a.keys[a.ranges[t][0] as usize + t..][..=ca];
    let kb = &b.keys[b.ranges[t][0] as usize + t..][..=cb];
    let (mut i, mut j) = (0, 0);
    for (l, c) in list.iter_mut().zip(copies.iter_mut()) {
        let (x, y) = (ka[i], kb[j]);
        let take_a = x < y;
        let g = x.min(y).index();
        // The data `MERGE_AHEAD` entries on in the run this entry comes
        // from, asked for (only a hint; none for a bound, whose index is
        // past the data): the list's order is not the data's, which the
        // hardware prefetcher does not follow, and about half of it was
        // written by the other core.
        let ahead = std::hint::select_unpredictable(
            take_a,
            ka[(i + MERGE_AHEAD).min(ca)],
            kb[(j + MERGE_AHEAD).min(cb)],
        );
        crate::kernels::prefetch_value(data, ahead.index() as usize);
        l.write(g);
        c.write(data[g as usize]);
        i += take_a as usize;
        j += !take_a as usize;
    }
}

/// How many entries ahead in its run [`merge_tile`] asks for an entry's
/// data. (On the 64×64 bench frame on two threads, one binary switching
/// the hint on and off by blocks of passes: the same 2nd-percentile
/// forward, and a median 0.4–2.6 µs shorter with it, in quiet minutes.)
const MERGE_AHEAD: usize = 8;

/// The most entries a frame's list may hold (2^28: with each entry's splat
/// copy about 16 GiB in f32), refused before the list is allocated.
pub const MAX_LIST_ENTRIES: u64 = 1 << 28;

/// Each tile's `[start, end)` in the list from its number of entries
/// (`totals`, row-major). Fails when the list would hold more than
/// [`MAX_LIST_ENTRIES`] (a frame where many Gaussians cover many tiles).
fn tile_ranges(totals: impl IntoIterator<Item = u64>) -> Result<Vec<[u32; 2]>> {
    let mut ranges = Vec::new();
    let mut start = 0u64;
    for k in totals {
        let end = start + k;
        if end > MAX_LIST_ENTRIES {
            return Err(Error::invalid(
                "Gaussians",
                format!(
                    "their tile rectangles hold more than {MAX_LIST_ENTRIES} list entries in \
                     all; render fewer or smaller Gaussians, or a smaller image"
                ),
            ));
        }
        // (Below 2^28.)
        ranges.push([start as u32, end as u32]);
        start = end;
    }
    Ok(ranges)
}

/// A pointer to the storage of a list that the fill tasks share; each
/// writes only its own slots.
struct Slots<E>(*mut MaybeUninit<E>);
// SAFETY: the pointer is only used to write disjoint slots from different
// threads (see the fill in `bin_keyed`).
unsafe impl<E: Send> Sync for Slots<E> {}

/// Whether a projected Gaussian has at least one entry.
#[inline(always)]
fn touches_a_tile<T: Real>(p: &Projected<T>) -> bool {
    p.radius > 0 && p.rect_min[0] < p.rect_max[0] && p.rect_min[1] < p.rect_max[1]
}

/// A projected Gaussian's tile rectangle `[x0, y0, x1, y1]`.
#[inline(always)]
fn rect_of<T: Real>(p: &Projected<T>) -> [u32; 4] {
    [p.rect_min[0], p.rect_min[1], p.rect_max[0], p.rect_max[1]]
}

/// Add each rectangle's tiles to `counts` (row-major, `grid_x` tiles a row).
#[inline(always)]
fn count_tiles(rects: impl Iterator<Item = [u32; 4]>, grid_x: u32, counts: &mut [u32]) {
    for r in rects {
        for y in r[1]..r[3] {
            let row = (y * grid_x) as usize;
            for c in &mut counts[row + r[0] as usize..row + r[2] as usize] {
                *c += 1;
            }
        }
    }
}

fn bin_keyed<T: Real, K: Key>(proj: &[Projected<T>], grid: [u32; 2]) -> Result<Binning> {
    let n_tiles = grid[0] as usize * grid[1] as usize;

    // 1. The Gaussians that touch a tile, sorted by `(depth bits, index)`,
    //    and their tile rectangles in that order.
    // (`with_min_len`: small scenes stay on one thread, where handing the
    // work out costs more than it saves.)
    // Each task collects the keys of one piece of `MIN_TASK` Gaussians into
    // a vector of its own, sized for all of them; the pieces are then
    // concatenated in order (a small scene is one piece, on this thread).
    let pieces: Vec<Vec<K>> = proj
        .par_chunks(MIN_TASK)
        .enumerate()
        .map(|(c, piece)| {
            let mut keys = Vec::with_capacity(piece.len());
            for (i, p) in piece.iter().enumerate() {
                if touches_a_tile(p) {
                    keys.push(K::new(p.depth.bits(), (c * MIN_TASK + i) as u32));
                }
            }
            keys
        })
        .collect();
    let mut keys: Vec<K> = match <[Vec<K>; 1]>::try_from(pieces) {
        Ok([keys]) => keys,
        Err(pieces) => pieces.concat(),
    };
    let chunk = chunk_len(keys.len());
    let n_chunks = keys.len().div_ceil(chunk);
    let rect = |k: &K| rect_of(&proj[k.index() as usize]);
    // 2. The entries per tile of each chunk of the sorted order: with one
    //    chunk, the tiles' totals, which do not depend on the order, so
    //    they are counted alongside the sort; otherwise per chunk in
    //    parallel after it.
    let mut counts = vec![0u32; n_chunks * n_tiles];
    let rects: Vec<[u32; 4]>;
    if n_chunks == 1 {
        rayon::join(
            || radix_sort_by_depth(&mut keys),
            || {
                let rects = proj.iter().filter(|p| touches_a_tile(*p)).map(rect_of);
                count_tiles(rects, grid[0], &mut counts)
            },
        );
        rects = keys.iter().map(rect).collect();
    } else {
        radix_sort_by_depth(&mut keys);
        rects = keys.par_iter().with_min_len(MIN_TASK).map(rect).collect();
        if n_tiles > 0 {
            rects
                .par_chunks(chunk)
                .zip(counts.par_chunks_mut(n_tiles))
                .for_each(|(rects, counts)| count_tiles(rects.iter().copied(), grid[0], counts));
        }
    }

    // 3. Each tile's range (an exclusive prefix sum over tiles of the
    //    chunks' totals), then each (chunk, tile) pair's first slot: the
    //    tile's start plus the entries of the earlier chunks.
    let mut totals = vec![0u64; n_tiles];
    for c in counts.chunks(n_tiles.max(1)) {
        for (t, &k) in totals.iter_mut().zip(c) {
            *t += k as u64;
        }
    }
    // (Every partial sum below is at most the list's length, which
    // `tile_ranges` checks fits in `u32`.)
    let ranges = tile_ranges(totals)?;
    let total = ranges.last().map_or(0, |r| r[1]);
    let mut cursor: Vec<u32> = ranges.iter().map(|r| r[0]).collect();
    for c in counts.chunks_mut(n_tiles.max(1)) {
        for (cur, k) in cursor.iter_mut().zip(c) {
            let start = *cur;
            *cur += *k;
            *k = start;
        }
    }
    let total = total as usize;

    // 4. Per chunk in parallel: each Gaussian's index at its slot in every
    //    tile it touches, in the sorted order within the chunk.
    let mut list: Vec<u32> = Vec::with_capacity(total);
    let slots = Slots(list.spare_capacity_mut().as_mut_ptr());
    if n_tiles > 0 {
        keys.par_chunks(chunk)
            .zip(rects.par_chunks(chunk))
            .zip(counts.par_chunks_mut(n_tiles))
            .for_each(|((keys, rects), next)| {
                let slots = &slots;
                for (k, r) in keys.iter().zip(rects) {
                    let g = k.index();
                    for y in r[1]..r[3] {
                        let row = (y * grid[0]) as usize;
                        for s in &mut next[row + r[0] as usize..row + r[2] as usize] {
                            // SAFETY: `*s` runs from this (chunk, tile)
                            // pair's first slot over exactly as many slots
                            // as step 2 counted for it, so it stays below
                            // `total` (the capacity) and no two writes,
                            // in this task or another, hit the same slot.
                            unsafe { (*slots.0.add(*s as usize)).write(g) };
                            *s += 1;
                        }
                    }
                }
            });
    }
    // SAFETY: the fill wrote every one of the first `total` slots (the
    // counts sum to `total` and every counted entry was written, see above);
    // a panic in a task propagates before this line, leaving `list` empty.
    unsafe { list.set_len(total) };
    Ok(Binning { list, ranges })
}

/// Sort keys that are in ascending index order by depth bits, stably (so
/// into `(depth bits, index)` order): a least-significant-digit radix sort,
/// 11 bits a pass (8 for fewer than 2¹⁴ keys, whose histograms would
/// otherwise cost more than the passes), all histograms from one read,
/// passes whose digit is the same for every key skipped. The digit width
/// changes only the speed: every width gives the one stable order.
fn radix_sort_by_depth<K: Key>(keys: &mut Vec<K>) {
    let n = keys.len();
    let bits: u32 = if n < 1 << 14 { 8 } else { 11 };
    let buckets = 1usize << bits;
    let passes = K::DEPTH_BITS.div_ceil(bits) as usize;
    let mut hist = vec![0u32; passes * buckets];
    for k in keys.iter() {
        let d = k.depth();
        for (p, h) in hist.chunks_exact_mut(buckets).enumerate() {
            h[(d >> (p as u32 * bits)) as usize & (buckets - 1)] += 1;
        }
    }
    let mut from = std::mem::take(keys);
    let mut to = from.clone();
    for (p, h) in hist.chunks_exact_mut(buckets).enumerate() {
        if h.iter().any(|&c| c as usize == n) {
            continue;
        }
        let mut sum = 0u32;
        for c in h.iter_mut() {
            let k = *c;
            *c = sum;
            sum += k;
        }
        let shift = p as u32 * bits;
        for &k in from.iter() {
            let b = &mut h[(k.depth() >> shift) as usize & (buckets - 1)];
            to[*b as usize] = k;
            *b += 1;
        }
        std::mem::swap(&mut from, &mut to);
    }
    *keys = from;
}

#[cfg(test)]
mod tests {
    use super::*;

    fn splat(depth: f64, rmin: [u32; 2], rmax: [u32; 2]) -> Projected<f64> {
        let mut p = Projected::culled();
        p.radius = 1;
        p.depth = depth;
        p.rect_min = rmin;
        p.rect_max = rmax;
        p
    }

    #[test]
    fn order_is_tile_then_depth_then_index() {
        let proj = vec![
            splat(2.0, [0, 0], [2, 1]),
            splat(1.0, [1, 0], [2, 1]),
            splat(2.0, [0, 0], [1, 1]),
            Projected::culled(),
        ];
        let b = bin(&proj, [2, 1]).unwrap();
        assert_eq!(b.list, vec![0, 2, 1, 0]);
        assert_eq!(b.ranges, vec![[0, 2], [2, 4]]);
    }

    /// The binning against one sort of every `(tile, depth bits, index)`
    /// key, on grids of one tile row, one column and several of each, with
    /// rectangles spanning many tile rows, empty rectangles, culled Gaussians
    /// and tied depths.
    #[test]
    fn order_is_that_of_one_global_sort() {
        let mut rng = crate::math::rng::Rng::new(17);
        let mut next = |m: u32| (rng.next_u64() % m as u64) as u32;
        for grid in [[6u32, 1u32], [5, 11], [4, 37], [1, 50]] {
            let proj: Vec<Projected<f64>> = (0..400)
                .map(|_| {
                    if next(10) == 0 {
                        return Projected::culled();
                    }
                    let x0 = next(grid[0]);
                    let y0 = next(grid[1]);
                    let x1 = (x0 + next(3)).min(grid[0]);
                    let tall = next(4) == 0;
                    let y1 = (y0 + 1 + next(if tall { grid[1] } else { 3 })).min(grid[1]);
                    splat(1.0 + next(7) as f64, [x0, y0], [x1, y1])
                })
                .collect();
            let mut keys = Vec::new();
            for (i, p) in proj.iter().enumerate() {
                if p.radius > 0 {
                    for y in p.rect_min[1]..p.rect_max[1] {
                        for x in p.rect_min[0]..p.rect_max[0] {
                            let tile = (y * grid[0] + x) as u64;
                            keys.push((tile, p.depth.to_bits(), i as u32));
                        }
                    }
                }
            }
            keys.sort_unstable();
            let b = bin(&proj, grid).unwrap();
            let want: Vec<u32> = keys.iter().map(|k| k.2).collect();
            assert_eq!(b.list, want, "grid {grid:?}");
            let n_tiles = (grid[0] * grid[1]) as usize;
            let ranges: Vec<[u32; 2]> = (0..n_tiles as u64)
                .map(|t| {
                    let s = keys.partition_point(|k| k.0 < t) as u32;
                    [s, keys.partition_point(|k| k.0 <= t) as u32]
                })
                .collect();
            assert_eq!(b.ranges, ranges, "grid {grid:?}");
        }
    }

    /// The definition of the binning, tile by tile: every visible Gaussian
    /// whose rectangle holds the tile, sorted by `(depth bits, index)`.
    fn reference<T: Real>(proj: &[Projected<T>], grid: [u32; 2]) -> Binning {
        let mut b = Binning::default();
        for ty in 0..grid[1] {
            for tx in 0..grid[0] {
                let mut keys: Vec<(u64, u32)> = proj
                    .iter()
                    .enumerate()
                    .filter(|(_, p)| {
                        p.radius > 0
                            && (p.rect_min[0]..p.rect_max[0]).contains(&tx)
                            && (p.rect_min[1]..p.rect_max[1]).contains(&ty)
                    })
                    .map(|(i, p)| (p.depth.bits(), i as u32))
                    .collect();
                keys.sort();
                let start = b.list.len() as u32;
                b.list.extend(keys.iter().map(|k| k.1));
                b.ranges.push([start, b.list.len() as u32]);
            }
        }
        b
    }

    /// `n` Gaussians on `grid`, badly balanced: about half on one tile,
    /// some covering the whole grid, culled ones (some with a rectangle),
    /// visible ones with an empty rectangle, and depths drawn from a few
    /// values (ties) or a continuous range.
    fn imbalanced<T: Real>(n: usize, grid: [u32; 2], seed: u64) -> Vec<Projected<T>> {
        let mut rng = crate::math::rng::Rng::new(seed);
        (0..n)
            .map(|_| {
                let mut p = Projected::culled();
                p.radius = 1 + rng.below(20) as i32;
                p.depth = if rng.below(2) == 0 {
                    T::from_f64(0.5 * (1 + rng.below(4)) as f64)
                } else {
                    T::from_f64(rng.uniform_range(0.3, 40.0))
                };
                let (x0, y0) = (
                    rng.below(grid[0] as u64) as u32,
                    rng.below(grid[1] as u64) as u32,
                );
                let (rmin, rmax) = match rng.below(20) {
                    // One crowded tile (clamped into small grids).
                    0..=9 => (
                        [2.min(grid[0] - 1), 3.min(grid[1] - 1)],
                        [3.min(grid[0]), 4.min(grid[1])],
                    ),
                    10 => ([0, 0], grid),
                    11 => {
                        p.radius = 0;
                        ([0, 0], grid)
                    }
                    12 => ([x0, y0], [x0, y0]),
                    _ => {
                        let x1 = (x0 + 1 + rng.below(3) as u32).min(grid[0]);
                        let y1 = (y0 + 1 + rng.below(grid[1] as u64) as u32).min(grid[1]);
                        ([x0, y0], [x1, y1])
                    }
                };
                p.rect_min = rmin;
                p.rect_max = rmax;
                p
            })
            .collect()
    }

    fn parallel_matches_reference<T: Real>() {
        let grid = [5u32, 11];
        let (mut short_last, mut most_chunks) = (false, false);
        for (seed, n) in [0usize, 1, 2, 4095, 4097, 14_000, 160_001]
            .into_iter()
            .enumerate()
        {
            let proj = imbalanced::<T>(n, grid, 100 + seed as u64);
            // The chunks are taken from the visible Gaussians.
            let v = proj
                .iter()
                .filter(|p| {
                    p.radius > 0 && p.rect_min[0] < p.rect_max[0] && p.rect_min[1] < p.rect_max[1]
                })
                .count();
            let c = chunk_len(v);
            short_last |= v > c && v % c != 0;
            most_chunks |= v.div_ceil(c) == 32 && c > 4096;
            let want = reference(&proj, grid);
            for threads in [1, 2, 3] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let got = pool.install(|| bin(&proj, grid).unwrap());
                assert_eq!(got.ranges, want.ranges, "n {n}, {threads} threads");
                assert!(got.list == want.list, "n {n}, {threads} threads");
            }
        }
        // Several chunks with a shorter last one, and the most chunks.
        assert!(short_last && most_chunks);
    }

    /// Every tile of two runs merged with [`merge_tile`], one after the
    /// other: the list and the copies of `data`.
    fn merged<K: Key, S: Copy>(
        runs: &[Run<K>; 2],
        data: &[S],
        ranges: &[[u32; 2]],
    ) -> (Vec<u32>, Vec<S>) {
        let total = ranges.last().map_or(0, |r| r[1]) as usize;
        let mut list = Vec::with_capacity(total);
        let mut splats = Vec::with_capacity(total);
        let (l, s) = (list.spare_capacity_mut(), splats.spare_capacity_mut());
        for (t, &[a, b]) in ranges.iter().enumerate() {
            let slots = a as usize..b as usize;
            merge_tile(runs, data, t, &mut l[slots.clone()], &mut s[slots]);
        }
        // SAFETY: the ranges cover `0..total`, and `merge_tile` writes every
        // slot it is given.
        unsafe {
            list.set_len(total);
            splats.set_len(total);
        }
        (list, splats)
    }

    fn two_runs_match_reference<T: Real, K: Key>() {
        for (seed, n) in [0usize, 1, 2, 17, 1000, 4095, 8192].into_iter().enumerate() {
            for grid in [[5u32, 11], [4, 4], [1, 9], [7, 1], [1, 1]] {
                let proj = imbalanced::<T>(n, grid, 200 + seed as u64);
                // Each Gaussian's data: its index plus 1,000.
                let data: Vec<u32> = (0..n as u32).map(|g| g + 1000).collect();
                let want = reference(&proj, grid);
                // Halves at a batch boundary, uneven, and one empty.
                for half in [n / 32 * 16, n / 3, 0, n] {
                    let runs = [
                        run::<T, K>(0, &proj[..half], grid).unwrap(),
                        run::<T, K>(half, &proj[half..], grid).unwrap(),
                    ];
                    let ranges = ranges_of_runs(&runs).unwrap();
                    let (list, copies) = merged(&runs, &data, &ranges);
                    let at = format!("n {n}, grid {grid:?}, half {half}");
                    assert_eq!(ranges, want.ranges, "{at}");
                    assert!(list == want.list, "{at}");
                    assert!(
                        copies.iter().zip(&list).all(|(&c, &g)| c == g + 1000),
                        "{at}"
                    );
                }
            }
        }
    }

    #[test]
    fn tile_ranges_refuse_a_list_past_the_limit() {
        assert_eq!(
            tile_ranges([1, 0, 2]).unwrap(),
            vec![[0, 1], [1, 1], [1, 3]]
        );
        let max = MAX_LIST_ENTRIES;
        assert_eq!(
            tile_ranges([max - 1, 1]).unwrap(),
            vec![[0, max as u32 - 1], [max as u32 - 1, max as u32]]
        );
        for totals in [[max, 1], [u64::MAX / 2, u64::MAX / 2]] {
            let err = tile_ranges(totals).unwrap_err().to_string();
            assert!(
                err.contains("Gaussians") && err.contains("268435456"),
                "{err}"
            );
        }
    }

    /// Every interleaving of two runs' entries of one tile, up to 7 each,
    /// behind entries of another tile: the merge is the sorted order, each
    /// entry with its own data.
    fn merge_every_interleaving<K: Key>() {
        // Gaussian `g`'s data: `g + 100`.
        let data: Vec<u32> = (0..20).map(|g| g + 100).collect();
        for na in 0..=7usize {
            for nb in 0..=7usize {
                let n = na + nb;
                for mask in 0u32..1 << n {
                    if mask.count_ones() as usize != na {
                        continue;
                    }
                    // Position `p` of the merged order has depth bits
                    // `p + 1`; the first run holds the lower indices.
                    let (mut ka, mut kb) = (vec![], vec![]);
                    for p in 0..n {
                        if mask >> p & 1 == 1 {
                            ka.push(K::new(p as u64 + 1, ka.len() as u32));
                        } else {
                            kb.push(K::new(p as u64 + 1, (na + kb.len()) as u32));
                        }
                    }
                    // Tile 1 of two, after two entries of tile 0 (Gaussians
                    // 18 and 19) and its bound.
                    let run = |tile: &[K]| {
                        let mut keys = vec![K::new(1, 18), K::new(2, 19), K::LAST];
                        keys.extend(tile);
                        keys.push(K::LAST);
                        Run {
                            ranges: vec![[0, 2], [2, 2 + tile.len() as u32]],
                            keys,
                        }
                    };
                    let runs = [run(&ka), run(&kb)];
                    let mut list = vec![MaybeUninit::uninit(); n];
                    let mut copies = vec![MaybeUninit::uninit(); n];
                    merge_tile(&runs, &data, 1, &mut list, &mut copies);
                    // SAFETY: `merge_tile` writes every slot it is given.
                    let (list, copies): (Vec<u32>, Vec<u32>) = unsafe {
                        (
                            list.iter().map(|x| x.assume_init()).collect(),
                            copies.iter().map(|x| x.assume_init()).collect(),
                        )
                    };
                    // Position `p` holds the first run's next Gaussian (the
                    // number of its keys before `p`) or the second's.
                    let want: Vec<u32> = (0..n as u32)
                        .map(|p| {
                            let before = (mask & ((1 << p) - 1)).count_ones();
                            if mask >> p & 1 == 1 {
                                before
                            } else {
                                na as u32 + p - before
                            }
                        })
                        .collect();
                    let tag = format!("na {na}, nb {nb}, mask {mask:b}");
                    assert_eq!(list, want, "{tag}");
                    assert!(
                        copies.iter().zip(&want).all(|(&c, &g)| c == g + 100),
                        "{tag}"
                    );
                }
            }
        }
    }

    #[test]
    fn merges_on_every_interleaving() {
        merge_every_interleaving::<u64>();
        merge_every_interleaving::<u128>();
    }

    #[test]
    fn a_merge_into_the_wrong_number_of_slots_panics() {
        let proj: Vec<Projected<f64>> = (0..5)
            .map(|k| splat(1.0 + k as f64, [0, 0], [1, 1]))
            .collect();
        let runs: [Run<u64>; 2] = [0, 5].map(|first| run(first, &proj, [1, 1]).unwrap());
        let mut list = vec![MaybeUninit::uninit(); 9];
        let mut copies = vec![MaybeUninit::uninit(); 9];
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            merge_tile(&runs, &[7u32; 10], 0, &mut list, &mut copies)
        }));
        assert!(r.is_err());
    }

    #[test]
    fn runs_past_the_list_limit_are_refused_before_they_are_built() {
        // 4096×4096 tiles, 34 Gaussians over all of them: more entries than
        // the list may hold in a run of all of them and in one of 17.
        let grid = [4096u32, 4096];
        let proj: Vec<Projected<f64>> = (0..34)
            .map(|k| splat(1.0 + k as f64, [0, 0], grid))
            .collect();
        for half in [0, 17] {
            let runs: [Result<Run<u64>>; 2] =
                [run(0, &proj[..half], grid), run(half, &proj[half..], grid)];
            // (An empty run holds only its tiles' bounds.)
            if half == 0 {
                assert_eq!(runs[0].as_ref().unwrap().keys.len(), 4096 * 4096);
            }
            for r in &runs[usize::from(half == 0)..] {
                let err = r.as_ref().err().expect("refused").to_string();
                assert!(err.contains("268435456"), "half {half}: {err}");
            }
        }
    }

    /// Two runs merged against the serial definition on imbalanced inputs
    /// (ties in depth, culled and empty rectangles, a crowded tile), for
    /// several ways to cut the Gaussians in two and both key widths.
    #[test]
    fn merged_runs_match_the_serial_definition() {
        two_runs_match_reference::<f32, u64>();
        two_runs_match_reference::<f64, u128>();
    }

    /// The parallel binning against its serial definition on imbalanced
    /// inputs, for 1, 2 and 3 threads and both key widths.
    #[test]
    fn parallel_binning_matches_the_serial_definition() {
        parallel_matches_reference::<f32>();
        parallel_matches_reference::<f64>();
    }
}
