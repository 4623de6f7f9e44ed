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

/// The first coordinate of `xyz` that is not a finite f32 once rounded to f32 (NaN,
/// infinite, or beyond ±3.4·10³⁸), if any. Initial positions are f32 (upstream stores
/// them as PLY `float`s); one that rounds to infinity has no distance to its neighbours.
pub fn first_unusable_coordinate(xyz: &[f64]) -> Option<usize> {
    xyz.iter().position(|&v| !(v as f32).is_finite())
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
    if let Some(k) = first_unusable_coordinate(&pc.xyz) {
        return Err(Error::invalid(
            "initial point cloud",
            format!(
                "point {}: coordinate {:e} is not a finite f32 (positions are stored as f32)",
                k / 3,
                pc.xyz[k]
            ),
        ));
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

#[cfg(test)]
fn dist2<T: Real>(p: &[T], a: usize, b: usize) -> T {
    dist2_to(
        [p[3 * a], p[3 * a + 1], p[3 * a + 2]],
        [p[3 * b], p[3 * b + 1], p[3 * b + 2]],
    )
}

/// Squared distance from `a` to `b`: `dx² + dy² + dz²` with `dx = a.x − b.x`, in `T`.
#[inline]
fn dist2_to<T: Real>(a: [T; 3], b: [T; 3]) -> T {
    let dx = a[0] - b[0];
    let dy = a[1] - b[1];
    let dz = a[2] - b[2];
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

/// Points per leaf of [`KdTree`] (a node splits when it holds more).
const KD_LEAF: usize = 32;
/// Subtrees of at least this many points are split in parallel.
const KD_PAR_SPLIT: usize = 1 << 14;

/// A node of [`KdTree`]: the bounding box of its points `pts[start..end]`
/// (each bound is one of its points' coordinates), and its children: the
/// left one is the next node, the right one `right` (0 for a leaf).
struct KdNode<T> {
    lo: [T; 3],
    hi: [T; 3],
    start: usize,
    end: usize,
    right: usize,
}

/// A k-d tree over points: each node splits its points at the median of its
/// widest axis (ties ordered by point index), so the tree is balanced
/// whatever the points, duplicates and outliers included; the leaves hold
/// the points in order.
struct KdTree<T> {
    nodes: Vec<KdNode<T>>,
    /// Points in leaf order, and their indices.
    pts: Vec<[T; 3]>,
    ids: Vec<usize>,
}

/// The bounding box of `pts`.
fn bounds<T: Real>(pts: &[([T; 3], usize)]) -> ([T; 3], [T; 3]) {
    let mut lo = pts[0].0;
    let mut hi = lo;
    for (p, _) in &pts[1..] {
        for a in 0..3 {
            lo[a] = lower(lo[a], p[a]);
            hi[a] = upper(hi[a], p[a]);
        }
    }
    (lo, hi)
}

/// The smaller of `a` and `b`, NaN if either is: a box bound that is NaN
/// bounds nothing ([`KdTree::gap2`] is then 0 on that axis).
#[inline]
fn lower<T: Real>(a: T, b: T) -> T {
    if b < a || b.is_nan() {
        b
    } else {
        a
    }
}

/// The larger of `a` and `b`, NaN if either is.
#[inline]
fn upper<T: Real>(a: T, b: T) -> T {
    if b > a || b.is_nan() {
        b
    } else {
        a
    }
}

/// Reorder `pts` (points with their indices) so that each range the tree
/// makes a node of is split at its median: the first half of every range
/// holds the points smallest along the range's widest axis (ties ordered by
/// index).
fn kd_split<T: Real>(pts: &mut [([T; 3], usize)]) {
    let n = pts.len();
    if n <= KD_LEAF {
        return;
    }
    let (lo, hi) = bounds(pts);
    let mut axis = 0;
    let mut widest = f64::NEG_INFINITY;
    for a in 0..3 {
        let w = hi[a].to_f64() - lo[a].to_f64();
        if w > widest {
            axis = a;
            widest = w;
        }
    }
    pts.select_nth_unstable_by(n / 2, |(p, i), (q, j)| {
        p[axis].to_f64().total_cmp(&q[axis].to_f64()).then(i.cmp(j))
    });
    let (left, right) = pts.split_at_mut(n / 2);
    if n >= KD_PAR_SPLIT {
        rayon::join(|| kd_split(left), || kd_split(right));
    } else {
        kd_split(left);
        kd_split(right);
    }
}

impl<T: Real> KdTree<T> {
    fn new(xyz: &[T]) -> KdTree<T> {
        let n = xyz.len() / 3;
        let mut items: Vec<([T; 3], usize)> = (0..n)
            .map(|j| ([xyz[3 * j], xyz[3 * j + 1], xyz[3 * j + 2]], j))
            .collect();
        kd_split(&mut items);
        let (pts, ids) = items.into_iter().unzip();
        let mut tree = KdTree {
            nodes: Vec::with_capacity(n.div_ceil(KD_LEAF / 2) + 1),
            pts,
            ids,
        };
        tree.node(0, n);
        tree
    }

    /// Append the node of `pts[start..end]` and its subtree (preorder), the
    /// same ranges [`kd_split`] split.
    fn node(&mut self, start: usize, end: usize) -> usize {
        let k = self.nodes.len();
        let p = self.pts[start];
        self.nodes.push(KdNode {
            lo: p,
            hi: p,
            start,
            end,
            right: 0,
        });
        let (lo, hi) = if end - start <= KD_LEAF {
            let mut lo = p;
            let mut hi = p;
            for q in &self.pts[start + 1..end] {
                for a in 0..3 {
                    lo[a] = lower(lo[a], q[a]);
                    hi[a] = upper(hi[a], q[a]);
                }
            }
            (lo, hi)
        } else {
            let mid = start + (end - start) / 2;
            let l = self.node(start, mid);
            let r = self.node(mid, end);
            self.nodes[k].right = r;
            let (l, r) = (&self.nodes[l], &self.nodes[r]);
            (
                std::array::from_fn(|a| lower(l.lo[a], r.lo[a])),
                std::array::from_fn(|a| upper(l.hi[a], r.hi[a])),
            )
        };
        self.nodes[k].lo = lo;
        self.nodes[k].hi = hi;
        k
    }

    /// A lower bound of [`dist2_to`] from `q` to every point of node `k`: the
    /// same operations in the same order in `T`, on the gap from `q` to the
    /// box on each axis (0 inside it; e.g. `lo − q` when `q < lo`). Rounding
    /// is monotonic and symmetric, so for a point `p` of the box,
    /// `|p − q| ≥ lo − q` gives `|fl(q − p)| ≥ fl(lo − q)`; squares and sums
    /// of non-negative values keep the order.
    #[inline]
    fn gap2(&self, k: usize, q: [T; 3]) -> T {
        let n = &self.nodes[k];
        let g = |a: usize| {
            if q[a] < n.lo[a] {
                n.lo[a] - q[a]
            } else if q[a] > n.hi[a] {
                q[a] - n.hi[a]
            } else {
                T::ZERO
            }
        };
        let (gx, gy, gz) = (g(0), g(1), g(2));
        gx * gx + gy * gy + gz * gz
    }

    /// Offer every point but `i` that could be closer to `q` than `best[2]`
    /// to `best`. A node is skipped only when its lower bound is `≥ best[2]`:
    /// none of its points is then `< best[2]`, and [`push_best`] keeps only
    /// such points, so skipping changes nothing (ties included).
    fn search(&self, i: usize, q: [T; 3], best: &mut [T; 3]) {
        // Depth-first, nearer child first; the stack holds at most one node
        // per level besides the current one.
        let mut stack = [0usize; 130];
        let mut len = 1;
        while len > 0 {
            len -= 1;
            let k = stack[len];
            if self.gap2(k, q) >= best[2] {
                continue;
            }
            let n = &self.nodes[k];
            if n.right == 0 {
                for (p, &j) in self.pts[n.start..n.end]
                    .iter()
                    .zip(&self.ids[n.start..n.end])
                {
                    if j != i {
                        push_best(best, dist2_to(q, *p));
                    }
                }
                continue;
            }
            let (l, r) = (k + 1, n.right);
            let (gl, gr) = (self.gap2(l, q), self.gap2(r, q));
            // Pushed last, popped first: the nearer child.
            let (near, far) = if gr < gl { (r, l) } else { (l, r) };
            stack[len] = far;
            stack[len + 1] = near;
            len += 2;
        }
    }
}

/// For each point, the mean of the squared distances to its 3 nearest other points,
/// `(b0 + b1 + b2) / 3` with `b0 ≤ b1 ≤ b2` and each distance `dx² + dy² + dz²` in `T`
/// (simple-knn's `distCUDA2`; duplicates count with distance 0). Exact: a k-d tree with
/// median splits is searched, skipping only subtrees none of whose points can be nearer
/// than the third best so far, so the three values are those of a search of every
/// point; building is O(n log n) and each search about O(log n) whatever the points
/// (duplicates, clusters, outliers). Needs ≥ 4 points. Parallel over points; each result
/// is independent of scheduling and thread count.
pub fn mean_dist2_3nn<T: Real>(xyz: &[T]) -> Vec<T> {
    use rayon::prelude::*;
    let n = xyz.len() / 3;
    if n == 0 {
        return vec![];
    }
    let tree = KdTree::new(&xyz[..3 * n]);
    let inf = T::from_f64(f64::MAX);
    let three = T::from_f64(3.0);
    // Points in leaf order (neighbours search the same nodes, which stay in
    // cache), then each result to its point.
    let by_leaf: Vec<T> = (0..n)
        .into_par_iter()
        .with_min_len(256)
        .map(|k| {
            let mut best = [inf; 3];
            tree.search(tree.ids[k], tree.pts[k], &mut best);
            (best[0] + best[1] + best[2]) / three
        })
        .collect();
    let mut out = vec![T::ZERO; n];
    for (&i, v) in tree.ids.iter().zip(by_leaf) {
        out[i] = v;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every pair's distance, sorted: the mean of the three smallest.
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

    fn bits<T: Real>(v: &[T]) -> Vec<u64> {
        v.iter().map(|x| x.to_f64().to_bits()).collect()
    }

    /// `mean_dist2_3nn` of `p` in f32 and in f64 (of the f32-rounded points), bit for
    /// bit against the search of every pair.
    fn assert_matches_brute(p: &[f64], what: &str) {
        let p32: Vec<f32> = p.iter().map(|&v| v as f32).collect();
        assert_eq!(
            bits(&mean_dist2_3nn(&p32)),
            bits(&brute(&p32)),
            "{what}: f32"
        );
        let p64: Vec<f64> = p32.iter().map(|&v| v as f64).collect();
        assert_eq!(
            bits(&mean_dist2_3nn(&p64)),
            bits(&brute(&p64)),
            "{what}: f64"
        );
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
            assert_matches_brute(&p, &format!("normal {n}"));
            assert_eq!(mean_dist2_3nn(&p), brute(&p));
        }
        // All points identical: every distance is 0.
        assert_eq!(mean_dist2_3nn(&[1.0f64; 15]), vec![0.0; 5]);
        // Sizes around the tree's leaves, and points with many equal distances
        // (lattices, duplicates), tiny and huge scales (f32 distances that
        // overflow to infinity), a far outlier.
        for (trial, &n) in [4usize, 5, 31, 32, 33, 64, 65, 100, 257, 1000, 2000]
            .iter()
            .enumerate()
        {
            for kind in 0..6 {
                let mut p: Vec<f64> = (0..3 * n)
                    .map(|_| match kind {
                        0 => (r.uniform() * 8.0).floor() * 0.25,
                        1 => (r.uniform() * 3.0).floor(),
                        2 => r.normal() * 1e-30,
                        3 => r.normal() * 1e37,
                        4 => r.uniform() * 2.6 - 1.3,
                        _ => (r.uniform() * 1e6).floor() * 1e-3,
                    })
                    .collect();
                if trial % 2 == 0 {
                    for k in 0..n / 4 {
                        let (a, b) = (3 * k, 3 * (n - 1 - k));
                        p.copy_within(a..a + 3, b);
                    }
                    p[3 * (n / 2)] = if kind == 3 { -3e38 } else { 1e7 };
                }
                assert_matches_brute(&p, &format!("n {n}, kind {kind}"));
            }
        }
    }

    #[test]
    fn knn_of_identical_points_ends_with_their_value() {
        // One cell of a grid held every point: quadratic, days for 2^24 points.
        let small = mean_dist2_3nn(&[0.25f32, -1.5, 3.0].repeat(5));
        assert_eq!(bits(&small), bits(&[0.0f32; 5]));
        let n = 200_000;
        let d = mean_dist2_3nn(&[0.25f32, -1.5, 3.0].repeat(n));
        let d64 = mean_dist2_3nn(&[0.25f64, -1.5, 3.0].repeat(n));
        assert!(d.iter().all(|v| v.to_bits() == small[0].to_bits()));
        assert!(d64.iter().all(|v| v.to_bits() == 0));
        // Identical points with one other point.
        let mut p = [0.25f32, -1.5, 3.0].repeat(1000);
        p[3..6].copy_from_slice(&[1.0, 1.0, 1.0]);
        assert_eq!(bits(&mean_dist2_3nn(&p)), bits(&brute(&p)));
    }

    #[test]
    fn knn_with_a_far_outlier_matches_brute_force() {
        // The outlier stretched a grid's cells over the other points.
        let mut r = Rng::new(8);
        for (n, far) in [
            (3000usize, 1e6),
            (3000, 1e30),
            (200_000, 1e6),
            (200_000, 1e30),
        ] {
            let mut p: Vec<f64> = (0..3 * n).map(|_| r.uniform()).collect();
            p[3 * (n / 3)..3 * (n / 3) + 3].copy_from_slice(&[far, -far, far]);
            let p32: Vec<f32> = p.iter().map(|&v| v as f32).collect();
            let d = mean_dist2_3nn(&p32);
            if n <= 3000 {
                assert_matches_brute(&p, &format!("outlier {far}"));
            }
            // The outlier's neighbours are all far: f32 distances overflow at 1e30.
            assert_eq!(d[n / 3].is_infinite(), far > 1e19);
        }
    }

    #[test]
    fn knn_is_independent_of_thread_count() {
        let mut r = Rng::new(11);
        let mut p: Vec<f32> = (0..3 * 50_000)
            .map(|_| (r.normal() * 4.0).round() as f32)
            .collect();
        p.extend([7.0f32, 7.0, 7.0].repeat(5000));
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| mean_dist2_3nn(&p))
        };
        let one = on(1);
        assert_eq!(bits(&one), bits(&on(2)));
        assert_eq!(bits(&one), bits(&on(3)));
    }

    #[test]
    fn positions_beyond_f32_are_refused() {
        let mut xyz = vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        assert_eq!(first_unusable_coordinate(&xyz), None);
        xyz[7] = 1e39;
        assert_eq!(first_unusable_coordinate(&xyz), Some(7));
        let e = gaussians_from_points::<f32>(&PointCloud { xyz, rgb: None }).unwrap_err();
        assert!(e.to_string().contains("point 2"), "{e}");
        // The largest f32 is fine.
        let xyz = vec![
            f32::MAX as f64,
            0.0,
            0.0,
            0.0,
            0.0,
            0.0,
            1.0,
            0.0,
            0.0,
            0.0,
            1.0,
            0.0,
        ];
        assert_eq!(first_unusable_coordinate(&xyz), None);
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
