//! Initial Gaussians from a point cloud (upstream `create_from_pcd`, docs/UPSTREAM.md §6.8).
//!
//! - Positions are rounded to f32 first: upstream writes the initial cloud to a PLY with
//!   `float` positions and reads it back.
//! - Colour `c` per channel is `byte / 255`; points without colours get byte 127 (upstream's
//!   random colours all truncate to 127). `features_dc = (c − 0.5) / C0`, `features_rest = 0`.
//! - Scale: `log(sqrt(max(d², 1e-7)))` on all three axes, where `d²` is the mean squared
//!   distance to the 3 nearest other points ([`mean_dist2_3nn`], simple-knn's `distCUDA2`).
//! - Rotation `(1, 0, 0, 0)`, opacity logit `inverse_sigmoid(0.1) = ln(0.1 / 0.9)`.
//! - `max_sh_degree` is 3.
//!
//! All of this is evaluated in the Gaussians' precision `T` (f32 follows upstream's f32
//! arithmetic). Random initial points come from the project's seeded [`Rng`], not numpy's
//! MT19937, so the positions differ from upstream's (same distribution).

use super::ply::PointCloud;
use super::Gaussians;
use crate::error::{Error, Result};
use crate::math::{Real, Rng};

/// Upstream's count of random initial points.
pub const DEFAULT_RANDOM_POINTS: usize = 100_000;
/// Half the side of upstream's random cube: points in `[-1.3, 1.3)³`.
pub const RANDOM_CUBE_HALF_EXTENT: f64 = 1.3;
/// SH band-0 constant.
pub const C0: f64 = 0.28209479177387814;
/// Byte colour of points without colour.
pub const DEFAULT_COLOUR: u8 = 127;
/// The fewest initial points (each needs 3 neighbours for its scale).
pub const MIN_POINTS: usize = 4;
/// The most random initial points (`init_points`): larger counts are
/// refused before anything is allocated.
pub const MAX_INIT_POINTS: usize = 1 << 24;

/// `Err(reason)` when `n` initial points cannot be used: fewer than
/// [`MIN_POINTS`] or more than [`MAX_INIT_POINTS`].
pub fn check_count(n: usize) -> std::result::Result<(), String> {
    if n < MIN_POINTS {
        Err(format!(
            "{n} points; at least {MIN_POINTS} are needed for the 3-nearest-neighbour scales"
        ))
    } else if n > MAX_INIT_POINTS {
        Err(format!("{n} points, more than the limit {MAX_INIT_POINTS}"))
    } else {
        Ok(())
    }
}

/// SH degree of the initial Gaussians.
pub const MAX_SH_DEGREE: usize = 3;

/// Where the initial Gaussians come from.
#[derive(Clone, Debug, PartialEq)]
pub enum InitialPoints {
    /// A point cloud from the dataset (`points3d.ply`, or nerfies' `points.npy` already
    /// transformed by `(p − center)·scale`). Positions `[N, 3]`, optional byte colours.
    Cloud {
        /// Positions, `[N, 3]` row-major.
        xyz: Vec<f64>,
        /// Colours, `[N, 3]` bytes, if the file has them.
        rgb: Option<Vec<u8>>,
    },
    /// `count` points uniform in `[-h, h)³` drawn from `Rng::new(seed)`, three uniforms per
    /// point in x, y, z order: `x = u·2h − h`.
    RandomCube {
        /// Number of points.
        count: usize,
        /// `h`: half the side of the cube.
        half_extent: f64,
        /// Seed of the generator.
        seed: u64,
    },
}

impl InitialPoints {
    /// The point cloud this describes (random points drawn now, deterministically).
    pub fn points(&self) -> PointCloud {
        match self {
            InitialPoints::Cloud { xyz, rgb } => PointCloud {
                xyz: xyz.clone(),
                rgb: rgb.clone(),
            },
            InitialPoints::RandomCube {
                count,
                half_extent,
                seed,
            } => {
                let mut r = Rng::new(*seed);
                let h = *half_extent;
                let xyz = (0..3 * count)
                    .map(|_| r.uniform() * (2.0 * h) - h)
                    .collect();
                PointCloud { xyz, rgb: None }
            }
        }
    }

    /// Number of points.
    pub fn len(&self) -> usize {
        match self {
            InitialPoints::Cloud { xyz, .. } => xyz.len() / 3,
            InitialPoints::RandomCube { count, .. } => *count,
        }
    }

    /// True when there are no points.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// The initial Gaussians for `init` (see the module documentation).
pub fn initial_gaussians<T: Real>(init: &InitialPoints) -> Result<Gaussians<T>> {
    if let InitialPoints::RandomCube { count, .. } = init {
        check_count(*count).map_err(|w| Error::invalid("init_points", w))?;
    }
    gaussians_from_points(&init.points())
}

/// Upstream's `create_from_pcd` for a point cloud. Needs at least 4 points (3 neighbours each).
pub fn gaussians_from_points<T: Real>(pc: &PointCloud) -> Result<Gaussians<T>> {
    let n = pc.len();
    if n < MIN_POINTS {
        return Err(Error::invalid(
            "initial point cloud",
            format!(
                "{n} points; at least {MIN_POINTS} are needed for the 3-nearest-neighbour scales"
            ),
        ));
    }
    if let Some(rgb) = &pc.rgb {
        if rgb.len() != 3 * n {
            return Err(Error::invalid(
                "initial point cloud",
                format!("{} colour bytes for {n} points", rgb.len()),
            ));
        }
    }
    if pc.xyz.iter().any(|v| !v.is_finite()) {
        return Err(Error::invalid("initial point cloud", "non-finite position"));
    }
    let xyz: Vec<T> = pc
        .xyz
        .iter()
        .map(|&v| T::from_f64(v as f32 as f64))
        .collect();
    let dist2 = mean_dist2_3nn(&xyz);
    let k = Gaussians::<T>::coeffs_for_degree(MAX_SH_DEGREE);
    let half = T::from_f64(0.5);
    let c0 = T::from_f64(C0);
    let floor = T::from_f64(1e-7);
    let opacity = {
        let y = T::from_f64(0.1);
        (y / (T::ONE - y)).ln()
    };
    let mut g = Gaussians::<T>::empty(MAX_SH_DEGREE);
    g.sh = vec![T::ZERO; 3 * k * n];
    for i in 0..n {
        for c in 0..3 {
            let byte = pc.rgb.as_ref().map_or(DEFAULT_COLOUR, |rgb| rgb[3 * i + c]);
            let col = T::from_f64(byte as f64 / 255.0);
            g.sh[3 * k * i + c] = (col - half) / c0;
        }
        let s = dist2[i].max(floor).sqrt().ln();
        g.scaling.extend([s, s, s]);
        g.rotation.extend([T::ONE, T::ZERO, T::ZERO, T::ZERO]);
        g.opacity.push(opacity);
    }
    g.xyz = xyz;
    Ok(g)
}

#[inline]
fn dist2<T: Real>(p: &[T], a: usize, b: usize) -> T {
    let dx = p[3 * a] - p[3 * b];
    let dy = p[3 * a + 1] - p[3 * b + 1];
    let dz = p[3 * a + 2] - p[3 * b + 2];
    dx * dx + dy * dy + dz * dz
}

/// Keep the 3 smallest values seen, ascending.
#[inline]
fn push_best<T: Real>(best: &mut [T; 3], d: T) {
    if d < best[2] {
        if d < best[1] {
            best[2] = best[1];
            if d < best[0] {
                best[1] = best[0];
                best[0] = d;
            } else {
                best[1] = d;
            }
        } else {
            best[2] = d;
        }
    }
}

/// For each point, the mean of the squared distances to its 3 nearest other points,
/// `(b0 + b1 + b2) / 3` with `b0 ≤ b1 ≤ b2` and each distance `dx² + dy² + dz²` in `T`
/// (simple-knn's `distCUDA2`; duplicates count with distance 0). Exact: a uniform grid is
/// searched ring by ring until no unvisited cell can hold a closer point. Needs ≥ 4 points.
/// Parallel over points; each result is independent of scheduling.
pub fn mean_dist2_3nn<T: Real>(xyz: &[T]) -> Vec<T> {
    use rayon::prelude::*;
    let n = xyz.len() / 3;
    if n == 0 {
        return vec![];
    }
    let p64: Vec<f64> = xyz.iter().map(|v| v.to_f64()).collect();
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    for i in 0..n {
        for a in 0..3 {
            lo[a] = lo[a].min(p64[3 * i + a]);
            hi[a] = hi[a].max(p64[3 * i + a]);
        }
    }
    let ext = (0..3).map(|a| hi[a] - lo[a]).fold(0.0f64, f64::max);
    // About 2 points per cell along the largest extent's cube.
    let per_axis = ((n as f64 / 2.0).cbrt().ceil() as usize).clamp(1, 1024);
    let h = if ext > 0.0 {
        ext / per_axis as f64
    } else {
        1.0
    };
    let dims: [usize; 3] =
        std::array::from_fn(|a| (((hi[a] - lo[a]) / h) as usize + 1).min(per_axis + 1));
    let cell_of = |i: usize| -> [usize; 3] {
        std::array::from_fn(|a| (((p64[3 * i + a] - lo[a]) / h) as usize).min(dims[a] - 1))
    };
    let ncells = dims[0] * dims[1] * dims[2];
    let flat = |c: [usize; 3]| (c[2] * dims[1] + c[1]) * dims[0] + c[0];
    let mut start = vec![0usize; ncells + 1];
    let cells: Vec<usize> = (0..n).map(|i| flat(cell_of(i))).collect();
    for &c in &cells {
        start[c + 1] += 1;
    }
    for c in 0..ncells {
        start[c + 1] += start[c];
    }
    let mut fill = start.clone();
    let mut order = vec![0usize; n];
    for (i, &c) in cells.iter().enumerate() {
        order[fill[c]] = i;
        fill[c] += 1;
    }
    let max_ring = dims.iter().copied().max().unwrap_or(1);
    let inf = T::from_f64(f64::MAX);
    let three = T::from_f64(3.0);
    (0..n)
        .into_par_iter()
        .with_min_len(256)
        .map(|i| {
            let c = cell_of(i);
            let mut best = [inf; 3];
            let mut found = 0usize;
            for r in 0..=max_ring {
                let r_i = r as isize;
                for dz in -r_i..=r_i {
                    for dy in -r_i..=r_i {
                        for dx in -r_i..=r_i {
                            if dx.abs().max(dy.abs()).max(dz.abs()) != r_i {
                                continue;
                            }
                            let q = [c[0] as isize + dx, c[1] as isize + dy, c[2] as isize + dz];
                            if (0..3).any(|a| q[a] < 0 || q[a] >= dims[a] as isize) {
                                continue;
                            }
                            let f = flat([q[0] as usize, q[1] as usize, q[2] as usize]);
                            for &j in &order[start[f]..start[f + 1]] {
                                if j != i {
                                    push_best(&mut best, dist2(xyz, i, j));
                                    found += 1;
                                }
                            }
                        }
                    }
                }
                // Every unvisited point is at least r·h away (less a margin for the cell
                // assignment's rounding); stop once none can beat the third best.
                if found >= 3 {
                    let bound = (r as f64 - 1e-6).max(0.0) * h;
                    if best[2].to_f64() < bound * bound * (1.0 - 1e-5) {
                        break;
                    }
                }
            }
            (best[0] + best[1] + best[2]) / three
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute<T: Real>(p: &[T]) -> Vec<T> {
        let n = p.len() / 3;
        (0..n)
            .map(|i| {
                let mut d: Vec<T> = (0..n).filter(|&j| j != i).map(|j| dist2(p, i, j)).collect();
                d.sort_by(|a, b| a.partial_cmp(b).unwrap());
                (d[0] + d[1] + d[2]) / T::from_f64(3.0)
            })
            .collect()
    }

    #[test]
    fn knn_matches_brute_force() {
        let mut r = Rng::new(5);
        for (n, spread) in [(4usize, 1.0), (50, 1.0), (700, 3.0), (900, 0.01)] {
            let mut p: Vec<f64> = (0..3 * n).map(|_| r.normal() * spread).collect();
            // Clusters, duplicates and an outlier.
            for k in 0..n / 10 {
                let (a, b) = (3 * k, 3 * (n - 1 - k));
                p.copy_within(a..a + 3, b);
            }
            p[0] = 40.0;
            let p32: Vec<f32> = p.iter().map(|&v| v as f32).collect();
            let got = mean_dist2_3nn(&p32);
            let want = brute(&p32);
            assert_eq!(
                got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                want.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
            assert_eq!(mean_dist2_3nn(&p), brute(&p));
        }
        // All points identical: every distance is 0.
        assert_eq!(mean_dist2_3nn(&[1.0f64; 15]), vec![0.0; 5]);
    }

    #[test]
    fn initial_gaussians_follow_upstream() {
        let init = InitialPoints::RandomCube {
            count: 500,
            half_extent: 1.3,
            seed: 0,
        };
        let g: Gaussians<f32> = initial_gaussians(&init).unwrap();
        g.validate().unwrap();
        assert_eq!(g.max_sh_degree, 3);
        assert!(g.xyz.iter().all(|&v| (-1.3..1.3).contains(&v)));
        // (127/255 − 0.5)/C0 in f32 ≈ −0.0069508 (docs/UPSTREAM.md §6.8).
        let dc = (127.0f32 / 255.0 - 0.5) / C0 as f32;
        assert!((dc + 0.0069508).abs() < 1e-6);
        assert_eq!(g.sh[0], dc);
        assert!(g.sh[3..48].iter().all(|&v| v == 0.0));
        assert!((g.opacity[0] + 2.1972246).abs() < 1e-6);
        assert_eq!(&g.rotation[..4], &[1.0, 0.0, 0.0, 0.0]);
        let d = brute(&g.xyz);
        for (i, di) in d.iter().enumerate().take(g.len()) {
            assert_eq!(g.scaling[3 * i], libm::logf(libm::sqrtf(di.max(1e-7))));
        }
        // Same seed, same points; fewer than 4 points is an error.
        let g2: Gaussians<f32> = initial_gaussians(&init).unwrap();
        assert_eq!(g, g2);
        let small = InitialPoints::Cloud {
            xyz: vec![0.0; 9],
            rgb: None,
        };
        assert!(initial_gaussians::<f32>(&small).is_err());
    }
}
