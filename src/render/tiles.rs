//! Binning of projected Gaussians into 16×16 tiles, in the order the Inria
//! rasterizer blends them.
//!
//! Upstream emits one `(tile << 32 | depth bits, gaussian)` pair per touched
//! tile and radix-sorts the pairs stably, so equal keys keep ascending
//! Gaussian index. Sorting the triple `(tile, depth bits, gaussian index)`
//! gives exactly that order; because the triple is unique, an unstable
//! (parallel) sort gives the same result on any thread count. Depth is
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
    // Offsets by an exclusive prefix sum in Gaussian order.
    let mut offsets = Vec::with_capacity(proj.len() + 1);
    let mut total = 0usize;
    offsets.push(0);
    for p in proj {
        if p.radius > 0 {
            total += p.tiles_touched();
        }
        offsets.push(total);
    }
    // Key: tile (bits 96..128), depth bits (32..96), index (0..32).
    let mut keys = vec![0u128; total];
    {
        let mut rest: &mut [u128] = &mut keys;
        let mut chunks = Vec::with_capacity(proj.len());
        for i in 0..proj.len() {
            let (head, tail) = rest.split_at_mut(offsets[i + 1] - offsets[i]);
            chunks.push(head);
            rest = tail;
        }
        chunks.into_par_iter().enumerate().for_each(|(i, out)| {
            if out.is_empty() {
                return;
            }
            let p = &proj[i];
            let depth = p.depth.bits() as u128;
            let mut o = 0;
            for y in p.rect_min[1]..p.rect_max[1] {
                for x in p.rect_min[0]..p.rect_max[0] {
                    let tile = (y * grid[0] + x) as u128;
                    out[o] = (tile << 96) | (depth << 32) | i as u128;
                    o += 1;
                }
            }
        });
    }
    keys.par_sort_unstable();
    let mut ranges = vec![[0u32; 2]; n_tiles];
    let list: Vec<u32> = keys.iter().map(|k| *k as u32).collect();
    let mut start = 0usize;
    while start < keys.len() {
        let tile = (keys[start] >> 96) as usize;
        let mut end = start + 1;
        while end < keys.len() && (keys[end] >> 96) as usize == tile {
            end += 1;
        }
        ranges[tile] = [start as u32, end as u32];
        start = end;
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
