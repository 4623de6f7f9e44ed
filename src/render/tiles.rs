//! Binning of projected Gaussians into 16×16 tiles, in the order the Inria
//! rasterizer blends them.
//!
//! Upstream emits one `(tile << 32 | depth bits, gaussian)` pair per touched
//! tile and radix-sorts the pairs stably, so equal keys keep ascending
//! Gaussian index: the order is `(tile, depth bits, gaussian index)`. Here a
//! counting sort by tile (in ascending Gaussian index) is followed by a sort
//! of each tile's entries by `(depth bits, gaussian index)`; because that pair
//! is unique within a tile, an unstable sort gives one result, and tiles are
//! sorted in parallel with the same result on any thread count. Depth is
//! positive (> 0.2), so its IEEE bit pattern orders like its value.

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

pub(crate) fn bin<T: Real>(proj: &[Projected<T>], grid: [u32; 2]) -> Binning {
    let n_tiles = grid[0] as usize * grid[1] as usize;
    // Entries per tile, then each tile's start by an exclusive prefix sum.
    let mut ranges = vec![[0u32; 2]; n_tiles];
    for p in proj {
        if p.radius > 0 {
            for y in p.rect_min[1]..p.rect_max[1] {
                let row = (y * grid[0]) as usize;
                for x in p.rect_min[0]..p.rect_max[0] {
                    ranges[row + x as usize][1] += 1;
                }
            }
        }
    }
    let mut total = 0u32;
    for r in ranges.iter_mut() {
        let n = r[1];
        *r = [total, total];
        total += n;
    }
    // Fill in ascending Gaussian index; `ranges[t][1]` is the fill cursor and
    // ends at the tile's end.
    let mut list = vec![0u32; total as usize];
    for (i, p) in proj.iter().enumerate() {
        if p.radius > 0 {
            for y in p.rect_min[1]..p.rect_max[1] {
                let row = (y * grid[0]) as usize;
                for x in p.rect_min[0]..p.rect_max[0] {
                    let r = &mut ranges[row + x as usize];
                    list[r[1] as usize] = i as u32;
                    r[1] += 1;
                }
            }
        }
    }
    // Per tile: by depth bits, then index, as one packed integer key.
    let mut chunks = Vec::with_capacity(n_tiles);
    let mut rest: &mut [u32] = &mut list;
    for r in &ranges {
        let (head, tail) = rest.split_at_mut((r[1] - r[0]) as usize);
        if head.len() > 1 {
            chunks.push(head);
        }
        rest = tail;
    }
    let depth_bits = |g: u32| proj[g as usize].depth.bits();
    if std::mem::size_of::<T>() <= 4 {
        chunks.into_par_iter().for_each_init(Vec::new, |keys, c| {
            keys.clear();
            keys.extend(c.iter().map(|&g| depth_bits(g) << 32 | g as u64));
            keys.sort_unstable();
            for (o, k) in c.iter_mut().zip(keys.iter()) {
                *o = *k as u32;
            }
        });
    } else {
        chunks.into_par_iter().for_each_init(Vec::new, |keys, c| {
            keys.clear();
            keys.extend(c.iter().map(|&g| (depth_bits(g) as u128) << 32 | g as u128));
            keys.sort_unstable();
            for (o, k) in c.iter_mut().zip(keys.iter()) {
                *o = *k as u32;
            }
        });
    }
    Binning { list, ranges }
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
