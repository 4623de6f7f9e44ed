//! `isect_tiles` and `isect_offset_encode`: which tiles each projected
//! Gaussian is drawn in, sorted by (image, tile, depth).
//!
//! Tile assignment:
//! - **Radius box** (1.5.3, `csrc/IntersectTile.cu` v1.5.3 l.55–113): with
//!   `tile_radius = radius/tile_size` and `tile_xy = mean2d/tile_size`,
//!   tiles `[floor(tile_x − tile_radius_x), ceil(tile_x + tile_radius_x))`
//!   (likewise y), clamped to the grid (a negative bound saturates to 0).
//! - **AccuTile** (1.6, `IntersectTile.cu` 1.6 l.83–207 and l.288–373, from
//!   Speedy-Splat): the ellipse `q = A dx² + 2B dx dy + C dy² ≤ t` with
//!   `t = min(3.33², 2·ln(o·255))` (`o` the opacity passed, compensated in
//!   antialiased mode) has the snug box `x_ext = sqrt(−t/disc·C)`,
//!   `y_ext = sqrt(−t/disc·A)`, `disc = B² − AC`; the box is cut into tile
//!   columns (or rows, whichever are fewer) and each column keeps only the
//!   tile range the ellipse spans inside it. Used when conics and opacities
//!   are given (always, in 1.6's `rasterization`).
//!
//! Keys: `isect_id = image_id << (32 + tile_n_bits) | tile_id << 32 |
//! depth_bits`, with [`key_bits`]: `tile_n_bits = floor(log2(n_tiles)) + 1`
//! at 1.5.3 (`csrc/Intersect.cpp` l.48–51), the bit width of `n_tiles − 1`
//! (0 for one tile) at 1.6 (`bits_for_count`, `csrc/MathUtils.h` l.23–33,
//! commit a5316070 "correct intersect (image, tile) id bit-widths"); and
//! `depth_bits` the IEEE bits of the depth narrowed to f32 (1.6 l.279–285;
//! 1.5.3 reinterprets the low 32 bits of the depth tensor, the same thing for
//! f32 depths). gsplat sorts the keys with a stable radix sort, so equal keys
//! keep ascending entry order: the order here is (key, entry index).

use super::{check_len, Version};
use crate::error::{Error, Result};
use crate::math::Real;
use rayon::prelude::*;

/// How tiles are assigned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TileRule {
    /// The axis-aligned box `mean2d ± radii` (1.5.3; 1.6 without conics).
    RadiusBox,
    /// Speedy-Splat's AccuTile (1.6 with conics and opacities).
    AccuTile,
}

/// The inputs of `isect_tiles`, one row per entry (dense `[C·N]` or packed `[nnz]`).
#[derive(Clone, Copy, Debug)]
pub struct IsectInput<'a, T> {
    /// `[M, 2]`.
    pub means2d: &'a [T],
    /// `[M, 2]`.
    pub radii: &'a [i32],
    /// `[M]`.
    pub depths: &'a [T],
    /// `[M, 3]` and `[M]`: required for [`TileRule::AccuTile`].
    pub conics: Option<&'a [T]>,
    /// `[M]` activated opacities (with `conics`, for [`TileRule::AccuTile`]).
    pub opacities: Option<&'a [T]>,
    /// Image of each entry: `[M]` (packed `camera_ids`); `None` for dense,
    /// where the image is `entry / n`.
    pub image_ids: Option<&'a [i32]>,
    /// Gaussians per image in the dense layout.
    pub n: usize,
}

/// Outputs of `isect_tiles`.
#[derive(Clone, Debug, PartialEq)]
pub struct Isects {
    /// `[M]` int32.
    pub tiles_per_gauss: Vec<i32>,
    /// `[n_isects]` int64, sorted.
    pub isect_ids: Vec<i64>,
    /// `[n_isects]` int32: the entry of each intersection.
    pub flatten_ids: Vec<i32>,
}

/// `floor(log2(v)) + 1` for `v ≥ 1` (the bit width of `v`).
fn bit_width(v: usize) -> u32 {
    usize::BITS - v.leading_zeros()
}

/// Bits of the image or tile field of a key for `count` images or tiles:
/// 1.5.3 `floor(log2(count)) + 1`; 1.6 `bits_for_count`, the bit width of
/// `count − 1` (0 when `count ≤ 1`). They differ for powers of two and 1.
pub fn key_bits(version: Version, count: usize) -> u32 {
    match version {
        Version::V1_5_3 => bit_width(count.max(1)),
        Version::V1_6 => bit_width(count.saturating_sub(1)),
    }
}

fn sat_u32<T: Real>(v: T) -> i64 {
    // CUDA float→uint conversion saturates (negative → 0, NaN → 0).
    let f = v.to_f64();
    if f.is_nan() || f <= 0.0 {
        0
    } else {
        f.min(u32::MAX as f64) as i64
    }
}

/// The most intersections `isect_tiles` lists (2^28; `isect_offsets` and
/// `flatten_ids` are int32 in gsplat, so lists above 2^31 cannot be indexed
/// at all).
pub const MAX_ISECTS: usize = 1 << 28;

/// The most tiles over all images (`n_images · tile_width · tile_height`,
/// the size of `isect_offsets`): 2^26.
pub const MAX_TILES: usize = 1 << 26;

/// Tiles `first + i · stride` for `i` in `0..len`, in that order.
#[derive(Clone, Copy)]
struct Run {
    first: i64,
    len: i64,
    stride: i64,
}

/// Tiles of the radius box, row-major.
fn radius_box<T: Real>(
    mean: [T; 2],
    radii: [i32; 2],
    tile_size: usize,
    tw: usize,
    th: usize,
    out: &mut dyn FnMut(Run),
) {
    let ts = T::from_usize(tile_size);
    let trx = T::from_f64(radii[0] as f64) / ts;
    let try_ = T::from_f64(radii[1] as f64) / ts;
    let tx = mean[0] / ts;
    let ty = mean[1] / ts;
    let x0 = sat_u32((tx - trx).floor()).min(tw as i64);
    let y0 = sat_u32((ty - try_).floor()).min(th as i64);
    let x1 = sat_u32((tx + trx).ceil()).min(tw as i64);
    let y1 = sat_u32((ty + try_).ceil()).min(th as i64);
    for y in y0..y1 {
        out(Run {
            first: y * tw as i64 + x0,
            len: (x1 - x0).max(0),
            stride: 1,
        });
    }
}

/// C `(int)` conversion: truncation toward zero, saturating, NaN → 0.
fn to_int<T: Real>(v: T) -> i64 {
    let f = v.to_f64();
    if f.is_nan() {
        0
    } else {
        f.clamp(i32::MIN as f64, i32::MAX as f64) as i64
    }
}

/// AccuTile (`accutile_process_tiles` and the kernel's SnugBox set-up).
#[allow(clippy::too_many_arguments)]
fn accutile<T: Real>(
    mean: [T; 2],
    conic: [T; 3],
    opacity: T,
    alpha_threshold: T,
    extend: T,
    tile_size: usize,
    tw: usize,
    th: usize,
    out: &mut dyn FnMut(Run),
) {
    let [a, b, c] = conic;
    let disc = b * b - a * c;
    let t = (extend * extend).min(T::from_f64(2.0) * (opacity / alpha_threshold).ln());
    let neg_t_over_disc = -t / disc;
    let x_ext = (neg_t_over_disc * c).sqrt();
    let y_ext = (neg_t_over_disc * a).sqrt();
    let bbox_min = [mean[0] - x_ext, mean[1] - y_ext];
    let bbox_max = [mean[0] + x_ext, mean[1] + y_ext];
    let bx_over_c = b * x_ext / c;
    let by_over_a = b * y_ext / a;
    let bbox_argmin = [mean[1] + bx_over_c, mean[0] + by_over_a];
    let bbox_argmax = [mean[1] - bx_over_c, mean[0] - by_over_a];
    let ts = T::from_usize(tile_size);
    let clampi = |v: i64, hi: usize| v.min(hi as i64).max(0);
    let rect_min = [
        clampi(to_int(bbox_min[0] / ts), tw),
        clampi(to_int(bbox_min[1] / ts), th),
    ];
    let rect_max = [
        clampi(to_int(bbox_max[0] / ts + T::ONE), tw),
        clampi(to_int(bbox_max[1] / ts + T::ONE), th),
    ];
    let y_span = rect_max[1] - rect_min[1];
    let x_span = rect_max[0] - rect_min[0];
    if y_span * x_span == 0 {
        return;
    }
    let is_y = y_span < x_span;
    let sw = |p: [T; 2]| if is_y { [p[1], p[0]] } else { p };
    let swi = |p: [i64; 2]| if is_y { [p[1], p[0]] } else { p };
    let (rmin, rmax) = (swi(rect_min), swi(rect_max));
    let (bmin, bmax) = (sw(bbox_min), sw(bbox_max));
    let (amin, amax) = (sw(bbox_argmin), sw(bbox_argmax));
    // accutile_ellipse_intersection: the ellipse's extent along v on the line u = coord.
    let intersect = |coord: T| -> [T; 2] {
        let (pu, pv, coeff) = if is_y {
            (mean[1], mean[0], a)
        } else {
            (mean[0], mean[1], c)
        };
        let h = coord - pu;
        let sq = (disc * h * h + t * coeff).sqrt();
        [(-b * h - sq) / coeff + pv, (-b * h + sq) / coeff + pv]
    };
    let mut inter_max = [bmax[1], bmin[1]];
    let mut min_line = T::from_f64(rmin[0] as f64) * ts;
    let mut inter_min = if bmin[0] <= min_line {
        intersect(min_line)
    } else {
        inter_max
    };
    for u in rmin[0]..rmax[0] {
        let max_line = min_line + ts;
        if max_line <= bmax[0] {
            inter_max = intersect(max_line);
        }
        let e_min = if min_line <= amin[1] && amin[1] < max_line {
            bmin[1]
        } else {
            inter_min[0].min(inter_max[0])
        };
        let e_max = if min_line <= amax[1] && amax[1] < max_line {
            bmax[1]
        } else {
            inter_min[1].max(inter_max[1])
        };
        let v0 = rmin[1].max(rmax[1].min(to_int(e_min / ts)));
        let v1 = rmax[1].min(rmin[1].max(to_int(e_max / ts + T::ONE)));
        out(if is_y {
            Run {
                first: u * tw as i64 + v0,
                len: (v1 - v0).max(0),
                stride: 1,
            }
        } else {
            Run {
                first: v0 * tw as i64 + u,
                len: (v1 - v0).max(0),
                stride: tw as i64,
            }
        });
        inter_min = inter_max;
        min_line = max_line;
    }
}

/// `gsplat.isect_tiles(means2d, radii, depths, tile_size, tile_width,
/// tile_height, sort=True, packed, n_images, image_ids, gaussian_ids)`, with
/// 1.6's optional `conics` and `opacities` (AccuTile).
pub fn isect_tiles<T: Real>(
    input: &IsectInput<T>,
    tile_size: usize,
    tile_width: usize,
    tile_height: usize,
    n_images: usize,
    version: Version,
    rule: TileRule,
) -> Result<Isects> {
    let m = input.depths.len();
    check_len("means2d", input.means2d.len(), 2 * m)?;
    check_len("radii", input.radii.len(), 2 * m)?;
    if tile_size == 0 || tile_width == 0 || tile_height == 0 || n_images == 0 {
        return Err(Error::invalid(
            "tiles",
            format!("tile_size {tile_size}, grid {tile_width}x{tile_height}, {n_images} images: each must be positive"),
        ));
    }
    if tile_size > 1024 {
        return Err(Error::invalid(
            "tile_size",
            format!("{tile_size} (1 to 1024, as the rasterizing stages take)"),
        ));
    }
    let n_tiles = tile_width.saturating_mul(tile_height);
    let tile_bits = key_bits(version, n_tiles);
    let image_bits = key_bits(version, n_images);
    if tile_bits + image_bits > 31 || n_images.saturating_mul(n_tiles) > MAX_TILES {
        return Err(Error::invalid(
            "tiles",
            format!("{n_images} images of {n_tiles} tiles: more than {MAX_TILES} tiles in all, or more than 31 bits of image and tile key (gsplat allows 32; here the key is a signed int64)"),
        ));
    }
    if let Some(ids) = input.image_ids {
        check_len("image_ids", ids.len(), m)?;
        if let Some(&bad) = ids.iter().find(|&&i| i < 0 || i as usize >= n_images) {
            return Err(Error::invalid(
                "image_ids",
                format!("{bad} is not below {n_images}"),
            ));
        }
    } else if input.n.checked_mul(n_images) != Some(m) {
        return Err(Error::invalid(
            "isect_tiles",
            format!(
                "{m} dense entries for {n_images} images of {} Gaussians",
                input.n
            ),
        ));
    }
    if rule == TileRule::AccuTile {
        match (input.conics, input.opacities) {
            (Some(c), Some(o)) => {
                check_len("conics", c.len(), 3 * m)?;
                check_len("opacities", o.len(), m)?;
            }
            _ => {
                return Err(Error::invalid(
                    "isect_tiles",
                    "AccuTile needs conics and opacities",
                ))
            }
        }
    }
    let alpha_threshold = T::ONE / T::from_f64(255.0);
    let extend = T::from_f64(3.33);
    // Entry `e`'s tiles, each passed to `out`.
    let tiles_of = |e: usize, out: &mut dyn FnMut(Run)| {
        let r = [input.radii[2 * e], input.radii[2 * e + 1]];
        if r[0] <= 0 || r[1] <= 0 {
            return;
        }
        let mean = [input.means2d[2 * e], input.means2d[2 * e + 1]];
        match rule {
            TileRule::RadiusBox => radius_box(mean, r, tile_size, tile_width, tile_height, out),
            TileRule::AccuTile => {
                let c = input.conics.unwrap_or_default();
                let o = input.opacities.unwrap_or_default();
                accutile(
                    mean,
                    [c[3 * e], c[3 * e + 1], c[3 * e + 2]],
                    o[e],
                    alpha_threshold,
                    extend,
                    tile_size,
                    tile_width,
                    tile_height,
                    out,
                )
            }
        }
    };
    // Counted first, so that a list too long to index is refused before it
    // is allocated (a radius or tile grid of up to 2^31 tiles per entry).
    let counts: Vec<u64> = (0..m)
        .into_par_iter()
        .map(|e| {
            let mut k = 0u64;
            tiles_of(e, &mut |r| k += r.len as u64);
            k
        })
        .collect();
    let total: u64 = counts.iter().sum();
    if total > MAX_ISECTS as u64 {
        return Err(Error::invalid(
            "isect_tiles",
            format!("{total} intersections, more than the {MAX_ISECTS} allowed"),
        ));
    }
    let per: Vec<Vec<u32>> = (0..m)
        .into_par_iter()
        .map(|e| {
            let mut tiles = Vec::with_capacity(counts[e] as usize);
            tiles_of(e, &mut |r| {
                tiles.extend((0..r.len).map(|i| (r.first + i * r.stride) as u32))
            });
            tiles
        })
        .collect();
    let mut keys: Vec<(i64, u32)> = Vec::with_capacity(per.iter().map(Vec::len).sum());
    for (e, tiles) in per.iter().enumerate() {
        let image = match input.image_ids {
            Some(ids) => ids[e] as i64,
            None => (e / input.n) as i64,
        };
        let depth = (input.depths[e].to_f64() as f32).to_bits() as i64;
        for &t in tiles {
            keys.push((
                (image << (32 + tile_bits)) | ((t as i64) << 32) | depth,
                e as u32,
            ));
        }
    }
    // Unique (key, entry) pairs: an unstable parallel sort gives one order.
    keys.par_sort_unstable();
    Ok(Isects {
        tiles_per_gauss: per.iter().map(|t| t.len() as i32).collect(),
        isect_ids: keys.iter().map(|k| k.0).collect(),
        flatten_ids: keys.iter().map(|k| k.1 as i32).collect(),
    })
}

/// `gsplat.isect_offset_encode(isect_ids, n_images, tile_width,
/// tile_height)`: `[n_images, tile_height, tile_width]` int32, the first
/// intersection of each (image, tile) (for an empty tile, that of the next
/// non-empty one; `n_isects` past the last).
///
/// Checked before the offsets are allocated: `n_images`, `tile_width` and
/// `tile_height` positive, at most [`MAX_TILES`] tiles over all images and
/// 31 bits of image and tile key (the grids [`isect_tiles`] accepts), and
/// every key of `isect_ids` non-negative, naming an image below `n_images`
/// and a tile below `tile_width·tile_height`, in ascending (image, tile)
/// order (as [`isect_tiles`] lists them).
pub fn isect_offset_encode(
    isect_ids: &[i64],
    n_images: usize,
    tile_width: usize,
    tile_height: usize,
    version: Version,
) -> Result<Vec<i32>> {
    let n_tiles = tile_width.checked_mul(tile_height);
    let total = n_tiles.and_then(|t| t.checked_mul(n_images));
    if n_images == 0
        || tile_width == 0
        || tile_height == 0
        || total.is_none_or(|t| t > MAX_TILES)
        || key_bits(version, n_tiles.unwrap_or(usize::MAX)) + key_bits(version, n_images) > 31
    {
        return Err(Error::invalid(
            "n_images, tile_width, tile_height",
            format!(
                "{n_images} images of {tile_width}x{tile_height} tiles (each positive, at most \
                 {MAX_TILES} tiles over all images and 31 bits of image and tile key)"
            ),
        ));
    }
    let n_tiles = tile_width * tile_height;
    let tile_bits = key_bits(version, n_tiles);
    // Each key's (image, tile) slot, checked as the Python binding does.
    let mut prev = 0usize;
    for (i, &k) in isect_ids.iter().enumerate() {
        let id = k >> 32;
        let (image, tile) = (id >> tile_bits, id & ((1 << tile_bits) - 1));
        let why = if id < 0 {
            "a non-negative key".to_string()
        } else if image as u64 >= n_images as u64 {
            format!("an image index below n_images = {n_images}")
        } else if tile as u64 >= n_tiles as u64 {
            format!("a tile index below tile_width·tile_height = {n_tiles}")
        } else {
            let slot = image as usize * n_tiles + tile as usize;
            if slot < prev {
                "keys sorted by (image, tile)".to_string()
            } else {
                prev = slot;
                continue;
            }
        };
        return Err(Error::invalid(
            "isect_ids",
            format!(
                "expected {why}, found isect_ids[{i}] = {k} (key {id}: image {image}, tile {tile})"
            ),
        ));
    }
    let mut offsets = vec![0i32; n_images * n_tiles];
    let mut pos = 0usize;
    for (slot, off) in offsets.iter_mut().enumerate() {
        while pos < isect_ids.len() {
            let id = isect_ids[pos] >> 32;
            let image = (id >> tile_bits) as usize;
            let tile = (id & ((1 << tile_bits) - 1)) as usize;
            if image * n_tiles + tile >= slot {
                break;
            }
            pos += 1;
        }
        *off = pos as i32;
    }
    Ok(offsets)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `m` copies of one entry at (16, 16).
    fn isect_m(
        m: usize,
        radii: [i32; 2],
        conic: Option<[f64; 3]>,
        tile_size: usize,
        grid: [usize; 2],
    ) -> Result<Isects> {
        let conics = conic.map(|c| c.repeat(m));
        let opacities = conic.map(|_| vec![0.9; m]);
        isect_tiles(
            &IsectInput {
                means2d: &[16.0, 16.0].repeat(m),
                radii: &radii.repeat(m),
                depths: &vec![1.0f64; m],
                conics: conics.as_deref(),
                opacities: opacities.as_deref(),
                image_ids: None,
                n: m,
            },
            tile_size,
            grid[0],
            grid[1],
            1,
            Version::V1_6,
            if conic.is_some() {
                TileRule::AccuTile
            } else {
                TileRule::RadiusBox
            },
        )
    }

    fn isect(
        radii: [i32; 2],
        conic: Option<[f64; 3]>,
        tile_size: usize,
        grid: [usize; 2],
    ) -> Result<Isects> {
        isect_m(1, radii, conic, tile_size, grid)
    }

    #[test]
    fn a_tile_size_above_1024_is_refused() {
        let err = isect([4, 4], None, 1025, [1, 1]).unwrap_err();
        assert!(
            err.to_string().contains("tile_size") && err.to_string().contains("1025"),
            "{err}"
        );
        assert!(isect([4, 4], None, 1024, [1, 1]).is_ok());
    }

    #[test]
    fn a_grid_whose_tile_count_overflows_is_refused() {
        let err = isect([4, 4], None, 16, [1 << 32, 1 << 32]).unwrap_err();
        assert!(err.to_string().contains("31 bits"), "{err}");
    }

    #[test]
    fn a_list_past_the_limit_is_refused_before_it_is_allocated() {
        // 2^31 tiles of 1 pixel, one entry covering all of them.
        // Five entries, each on all 2^26 tiles of one pixel.
        let err = isect_m(5, [i32::MAX, i32::MAX], None, 1, [1 << 13, 1 << 13]).unwrap_err();
        assert!(err.to_string().contains("268435456"), "{err}");
        // A grid above 2^26 tiles (its offsets alone 256 MiB).
        let err = isect([4, 4], None, 1, [1 << 16, 1 << 15]).unwrap_err();
        assert!(err.to_string().contains("67108864 tiles"), "{err}");
        // The same entry on a grid of 2^20 tiles is listed on every tile.
        let is = isect([i32::MAX, i32::MAX], None, 1, [1 << 10, 1 << 10]).unwrap();
        assert_eq!(is.tiles_per_gauss, [1 << 20]);
        assert_eq!(is.flatten_ids.len(), 1 << 20);
    }

    #[test]
    fn counted_runs_list_the_tiles_in_order() {
        // Radius box: tiles (0..2) × (0..2) of a 4×4 grid, row-major.
        let is = isect([8, 8], None, 16, [4, 4]).unwrap();
        let tiles: Vec<i64> = is.isect_ids.iter().map(|k| (k >> 32) & 0xf).collect();
        assert_eq!(tiles, [0, 1, 4, 5]);
        // AccuTile of a round splat, taller than wide: column runs.
        let is = isect([8, 8], Some([0.02, 0.0, 0.005]), 16, [4, 4]).unwrap();
        assert_eq!(is.tiles_per_gauss[0] as usize, is.flatten_ids.len());
        let mut tiles: Vec<i64> = is.isect_ids.iter().map(|k| (k >> 32) & 0xf).collect();
        tiles.sort();
        tiles.dedup();
        assert_eq!(tiles.len(), is.flatten_ids.len());
    }

    #[test]
    fn dense_entry_counts_that_overflow_are_refused() {
        let err = isect_tiles(
            &IsectInput {
                means2d: &[16.0f64, 16.0],
                radii: &[4, 4],
                depths: &[1.0],
                conics: None,
                opacities: None,
                image_ids: None,
                n: usize::MAX,
            },
            16,
            4,
            4,
            2,
            Version::V1_6,
            TileRule::RadiusBox,
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("isect_tiles") && err.contains("1 dense entries"),
            "{err}"
        );
    }

    #[test]
    fn offsets_of_bad_grids_or_keys_are_refused_before_allocation() {
        let v = Version::V1_6;
        for (ni, tw, th) in [
            (usize::MAX / 2, 2, 2),
            (1, usize::MAX, 2),
            (1, usize::MAX, 1),
            (1 << 34, 1, 1),
            (1, 1 << 16, 1 << 11),
            (0, 1, 1),
            (1, 0, 1),
        ] {
            let e = isect_offset_encode(&[], ni, tw, th, v)
                .unwrap_err()
                .to_string();
            assert!(e.contains("n_images, tile_width, tile_height"), "{e}");
        }
        for (ids, ni, tw, version, want) in [
            (
                vec![-1i64 << 32, 0],
                2,
                2,
                v,
                "non-negative key, found isect_ids[0]",
            ),
            (vec![-1], 2, 2, v, "non-negative key"),
            (vec![i64::MAX], 2, 2, v, "image index below n_images = 2"),
            (
                vec![1 << 32, 4 << 32],
                2,
                2,
                v,
                "found isect_ids[1] = 17179869184 (key 4: image 2, tile 0)",
            ),
            (
                vec![3 << 32],
                1,
                3,
                Version::V1_5_3,
                "tile index below tile_width·tile_height = 3",
            ),
            (
                vec![3 << 32, 1 << 32],
                2,
                2,
                v,
                "sorted by (image, tile), found isect_ids[1]",
            ),
        ] {
            let e = isect_offset_encode(&ids, ni, tw, 1, version)
                .unwrap_err()
                .to_string();
            assert!(e.contains("isect_ids") && e.contains(want), "{e}");
        }
        let ok = isect_offset_encode(&[1 << 32, 2 << 32], 2, 2, 1, v).unwrap();
        assert_eq!(ok, [0, 0, 1, 2]);
    }
}
