//! Binning of projected Gaussians into 16×16 tiles, in the order the Inria
//! rasterizer blends them.
//!
//! Upstream emits one `(tile << 32 | depth bits, gaussian)` pair per touched
//! tile and radix-sorts the pairs stably, so equal keys keep ascending
//! Gaussian index: the order is `(tile, depth bits, gaussian index)`. Here a
//! counting sort by tile (in ascending Gaussian index) is followed by a sort
//! of each tile's entries by `(depth bits, gaussian index)`; because that pair
//! is unique within a tile, an unstable sort gives one result. Depth is
//! positive (> 0.2), so its IEEE bit pattern orders like its value.
//!
//! The work runs in parallel over bands of tile rows (about 16 per image,
//! fixed by the image size): one serial pass lists the Gaussians crossing
//! each band in ascending index and counts the band's entries, which fixes
//! where each band's part of the list starts; then each band counts its
//! tiles, fills them and sorts them on its own. The list is the same on any
//! thread count.

use super::project::Projected;
use crate::math::Real;
use rayon::prelude::*;

/// The sorted list and per-tile ranges.
#[derive(Clone, Debug, Default)]
pub(crate) struct Binning {
    /// Gaussian index of each sorted entry.
    pub list: Vec<u32>,
    /// `[start, end)` into `list` per tile (row-major tile order).
    pub ranges: Vec<[u32; 2]>,
}

/// Tile rows per band of the binning: about 16 bands per image, each a
/// parallel task (the same bands on every thread count).
fn band_rows(grid_y: usize) -> usize {
    grid_y.div_ceil(16).max(1)
}

pub(crate) fn bin<T: Real>(proj: &[Projected<T>], grid: [u32; 2]) -> Binning {
    let (gx, gy) = (grid[0] as usize, grid[1] as usize);
    let rows = band_rows(gy);
    let n_bands = gy.div_ceil(rows);
    // The visible Gaussians crossing each band of tile rows, in ascending
    // index, with their tile rectangles `[x0, x1, y0, y1]`, and the number
    // of entries each band receives.
    let mut members: Vec<Vec<(u32, [u32; 4])>> = vec![Vec::new(); n_bands];
    let mut band_len = vec![0usize; n_bands];
    for (i, p) in proj.iter().enumerate() {
        if p.radius > 0 && p.rect_min[0] < p.rect_max[0] {
            let [x0, y0] = p.rect_min;
            let [x1, y1] = p.rect_max;
            let mut y = y0;
            while y < y1 {
                let b = y as usize / rows;
                let end = y1.min(((b + 1) * rows) as u32);
                members[b].push((i as u32, [x0, x1, y0, y1]));
                band_len[b] += (x1 - x0) as usize * (end - y) as usize;
                y = end;
            }
        }
    }
    // Per band in parallel: entries per tile, each tile's range by an
    // exclusive prefix sum from the band's start, the fill in ascending
    // Gaussian index, then each tile sorted by depth bits, then index.
    let mut ranges = vec![[0u32; 2]; gx * gy];
    let mut list = vec![0u32; band_len.iter().sum()];
    let mut pieces = Vec::with_capacity(n_bands);
    let (mut rest_r, mut rest_l): (&mut [[u32; 2]], &mut [u32]) = (&mut ranges, &mut list);
    let mut base = 0usize;
    for (b, (m, &len)) in members.iter().zip(&band_len).enumerate() {
        let (r, tail_r) = rest_r.split_at_mut((rows * gx).min(rest_r.len()));
        let (l, tail_l) = rest_l.split_at_mut(len);
        pieces.push(((b * rows) as u32, m, base as u32, r, l));
        (rest_r, rest_l) = (tail_r, tail_l);
        base += len;
    }
    pieces
        .into_par_iter()
        .for_each(|(ty0, members, base, ranges, out)| {
            let ty1 = ty0 + (ranges.len() / gx) as u32;
            for &(_, [x0, x1, y0, y1]) in members.iter() {
                for y in y0.max(ty0)..y1.min(ty1) {
                    let row = (y - ty0) as usize * gx;
                    for r in &mut ranges[row + x0 as usize..row + x1 as usize] {
                        r[1] += 1;
                    }
                }
            }
            // `r[1]` becomes the fill cursor and ends at the tile's end.
            let mut total = base;
            for r in ranges.iter_mut() {
                let n = r[1];
                *r = [total, total];
                total += n;
            }
            for &(g, [x0, x1, y0, y1]) in members.iter() {
                for y in y0.max(ty0)..y1.min(ty1) {
                    let row = (y - ty0) as usize * gx;
                    for r in &mut ranges[row + x0 as usize..row + x1 as usize] {
                        out[(r[1] - base) as usize] = g;
                        r[1] += 1;
                    }
                }
            }
            let mut keys = (Vec::new(), Vec::new());
            for r in ranges.iter() {
                let tile = &mut out[(r[0] - base) as usize..(r[1] - base) as usize];
                sort_tile(proj, tile, &mut keys);
            }
        });
    Binning { list, ranges }
}

/// Sort one tile's Gaussians by (depth bits, index); the pair is unique, so
/// the order is one. `keys` is scratch (u64 keys for f32 depths, u128 for
/// f64).
fn sort_tile<T: Real>(proj: &[Projected<T>], tile: &mut [u32], keys: &mut (Vec<u64>, Vec<u128>)) {
    if tile.len() < 2 {
        return;
    }
    let depth_bits = |g: u32| proj[g as usize].depth.bits();
    if std::mem::size_of::<T>() <= 4 {
        let k = &mut keys.0;
        k.clear();
        k.extend(tile.iter().map(|&g| depth_bits(g) << 32 | g as u64));
        k.sort_unstable();
        for (o, k) in tile.iter_mut().zip(k.iter()) {
            *o = *k as u32;
        }
    } else {
        let k = &mut keys.1;
        k.clear();
        k.extend(
            tile.iter()
                .map(|&g| (depth_bits(g) as u128) << 32 | g as u128),
        );
        k.sort_unstable();
        for (o, k) in tile.iter_mut().zip(k.iter()) {
            *o = *k as u32;
        }
    }
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
        let b = bin(&proj, [2, 1]);
        assert_eq!(b.list, vec![0, 2, 1, 0]);
        assert_eq!(b.ranges, vec![[0, 2], [2, 4]]);
    }

    /// The banded binning against one sort of every `(tile, depth bits,
    /// index)` key, on grids of one band, of one-row bands and of several-row
    /// bands with a short last band, with rectangles spanning many bands,
    /// empty rectangles, culled Gaussians and tied depths.
    #[test]
    fn bands_give_the_order_of_one_global_sort() {
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
            let b = bin(&proj, grid);
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
}
