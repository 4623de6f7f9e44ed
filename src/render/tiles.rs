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
}
