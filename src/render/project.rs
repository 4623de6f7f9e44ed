//! Per-Gaussian preprocessing (Inria `preprocessCUDA`) and its backward.
//!
//! Forward, for one Gaussian, in the upstream order:
//! 1. view-space point `t = W2C·[p; 1]`; cull if `t.z ≤ 0.2`;
//! 2. homogeneous projection, `ndc = p_hom.xy / (p_hom.w + 1e-7)`;
//! 3. EWA 2D covariance with the tangent clamp `|t.x/t.z| ≤ 1.3·tanfovx`
//!    (only the Jacobian sees the clamped point) and the 0.3 dilation;
//! 4. conic = inverse 2D covariance, cull if `det == 0`;
//! 5. radius `ceil(3·sqrt(λmax))` with the 0.1 floor on the discriminant;
//! 6. pixel centre `ndc2Pix`, evaluated in f64 and rounded to `T`;
//! 7. tile rectangle, cull if empty.
//!
//! The rasterizer runs it on batches of Gaussians as vectors (the private
//! module `preprocess`), in three parts with the same operations:
//! [`project_core`] (steps 1 to 5 without the culls), [`footprint`] (the
//! radius, centre, rectangle and culls, without branches or library calls)
//! and [`assemble`]; [`project`] composes them for one Gaussian.
//!
//! The backward is the exact derivative of the forward as computed (see
//! [`super::GradientMode::Exact`]), or upstream's formulas
//! ([`super::GradientMode::Inria`]).

use super::{GradientMode, BLOCK};
use crate::math::covariance::sym3;
use crate::math::pack::Arith;
use crate::math::Real;

/// Camera quantities shared by every Gaussian.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Intrinsics<T> {
    pub view: [T; 16],
    pub proj: [T; 16],
    pub fx: T,
    pub fy: T,
    pub limx: T,
    pub limy: T,
    pub width: usize,
    pub height: usize,
    pub grid: [u32; 2],
}

impl<T: Real> Intrinsics<T> {
    pub fn new(cam: &crate::camera::RasterCamera<T>) -> Self {
        let w = T::from_usize(cam.width);
        let h = T::from_usize(cam.height);
        let two = T::from_f64(2.0);
        let lim = T::from_f64(1.3);
        Intrinsics {
            view: cam.viewmatrix,
            proj: cam.projmatrix,
            fx: w / (two * cam.tanfovx),
            fy: h / (two * cam.tanfovy),
            limx: lim * cam.tanfovx,
            limy: lim * cam.tanfovy,
            width: cam.width,
            height: cam.height,
            grid: [
                cam.width.div_ceil(BLOCK) as u32,
                cam.height.div_ceil(BLOCK) as u32,
            ],
        }
    }

    /// `W2C(i, j)` for the rotation part.
    #[inline]
    fn wr(&self, i: usize, j: usize) -> T {
        self.view[4 * j + i]
    }
}

/// Everything the forward computes for one Gaussian and the backward reuses.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Projected<T> {
    /// Integer radius in pixels; 0 when culled.
    pub radius: i32,
    /// View-space depth `t.z` (the sort key).
    pub depth: T,
    /// Pixel-space centre.
    pub xy: [T; 2],
    /// Conic `(A, B, C)`: `power = −0.5(A dx² + C dy²) − B dx dy`.
    pub conic: [T; 3],
    /// Dilated 2D covariance `(a, b, c)`.
    pub cov2d: [T; 3],
    /// Tile rectangle `[min, max)`.
    pub rect_min: [u32; 2],
    pub rect_max: [u32; 2],
    /// Whether `t.x/t.z` (resp. `t.y/t.z`) was clamped (strictly outside the limit).
    pub clamped_x: bool,
    pub clamped_y: bool,
}

impl<T: Real> Projected<T> {
    pub fn culled() -> Self {
        Projected {
            radius: 0,
            depth: T::ZERO,
            xy: [T::ZERO; 2],
            conic: [T::ZERO; 3],
            cov2d: [T::ZERO; 3],
            rect_min: [0; 2],
            rect_max: [0; 2],
            clamped_x: false,
            clamped_y: false,
        }
    }
}

/// `m·[p; 1]` for a row-vector 4×4 stored row-major: component `i` is
/// `m[i]·px + m[4+i]·py + m[8+i]·pz + m[12+i]`, summed left to right.
#[inline]
fn transform<T: Real>(m: &[T; 16], p: [T; 3], i: usize) -> T {
    m[i] * p[0] + m[4 + i] * p[1] + m[8 + i] * p[2] + m[12 + i]
}

/// `((v + 1)·S − 1)·0.5` in f64, rounded to `T` (upstream uses double literals).
#[inline]
fn ndc2pix<T: Real>(v: T, size: usize) -> T {
    T::from_f64(((v.to_f64() + 1.0) * size as f64 - 1.0) * 0.5)
}

/// C float→int conversion (truncation), saturating; NaN gives 0.
#[inline]
#[cfg(test)]
fn trunc_i64<T: Real>(v: T) -> i64 {
    v.to_f64() as i64
}

/// Rows 0 and 1 of `J·Wr` for the view-space point `t` (clamped as upstream).
struct Ewa<T> {
    a: [[T; 3]; 2],
    clamped_x: bool,
    clamped_y: bool,
}

#[inline(always)]
fn ewa<T: Real>(k: &Intrinsics<T>, t: [T; 3]) -> Ewa<T> {
    let txtz = t[0] / t[2];
    let tytz = t[1] / t[2];
    let tx = txtz.clamp(-k.limx, k.limx) * t[2];
    let ty = tytz.clamp(-k.limy, k.limy) * t[2];
    let tz2 = t[2] * t[2];
    let j00 = k.fx / t[2];
    let j02 = -(k.fx * tx) / tz2;
    let j11 = k.fy / t[2];
    let j12 = -(k.fy * ty) / tz2;
    // glm: T = W·J, element (r, c) = Σ_k Wr(k, r)·J(c, k); the zero entries of J are skipped.
    let mut a = [[T::ZERO; 3]; 2];
    #[allow(clippy::needless_range_loop)] // indices as in the formula
    for r in 0..3 {
        a[0][r] = k.wr(0, r) * j00 + k.wr(2, r) * j02;
        a[1][r] = k.wr(1, r) * j11 + k.wr(2, r) * j12;
    }
    Ewa {
        a,
        clamped_x: txtz < -k.limx || txtz > k.limx,
        clamped_y: tytz < -k.limy || tytz > k.limy,
    }
}

/// The branch-free part of [`project`] for one Gaussian: the same operations
/// for every Gaussian, culled or not, so that a loop over a batch of
/// Gaussians runs it lane by lane in vector registers (see
/// `super::preprocess`). Values of a Gaussian that [`project_finish`] culls
/// are meaningless (possibly NaN or infinite).
#[derive(Clone, Copy, Debug)]
pub(crate) struct ProjectCore<T> {
    /// View-space depth `t.z`.
    pub depth: T,
    /// Projected NDC centre, offset added.
    pub ndc: [T; 2],
    /// Dilated 2D covariance `(a, b, c)`.
    pub cov2d: [T; 3],
    /// `a·c − b²`.
    pub det: T,
    /// Conic `(c, −b, a)/det`.
    pub conic: [T; 3],
    /// `3·sqrt(λmax)`, the radius before rounding up.
    pub radius3: T,
    /// Whether `t.x/t.z` (resp. `t.y/t.z`) was clamped.
    pub clamped_x: bool,
    pub clamped_y: bool,
}

/// Steps 1 to 5 of [`project`] without the culls (see [`ProjectCore`]).
#[inline(always)]
pub(crate) fn project_core<T: Real>(
    k: &Intrinsics<T>,
    mean: [T; 3],
    cov3d: &[T; 6],
    ndc_offset: [T; 2],
) -> ProjectCore<T> {
    let t = [
        transform(&k.view, mean, 0),
        transform(&k.view, mean, 1),
        transform(&k.view, mean, 2),
    ];
    let hx = transform(&k.proj, mean, 0);
    let hy = transform(&k.proj, mean, 1);
    let hw = transform(&k.proj, mean, 3);
    let pw = T::ONE / (hw + T::from_f64(1e-7));
    let ndc = [hx * pw + ndc_offset[0], hy * pw + ndc_offset[1]];

    let e = ewa(k, t);
    let v = sym3(cov3d);
    // X = A·V (rows 0, 1), cov(r, c) = Σ_k X(r, k)·A(c, k).
    let mut x = [[T::ZERO; 3]; 2];
    #[allow(clippy::needless_range_loop)] // indices as in the formula
    for r in 0..2 {
        for c in 0..3 {
            x[r][c] = e.a[r][0] * v[0][c] + e.a[r][1] * v[1][c] + e.a[r][2] * v[2][c];
        }
    }
    let dot = |r: usize, c: usize| x[r][0] * e.a[c][0] + x[r][1] * e.a[c][1] + x[r][2] * e.a[c][2];
    let dil = T::from_f64(0.3);
    let a = dot(0, 0) + dil;
    let b = dot(1, 0);
    let c = dot(1, 1) + dil;

    let det = a * c - b * b;
    let det_inv = T::ONE / det;
    let conic = [c * det_inv, -b * det_inv, a * det_inv];
    let mid = T::from_f64(0.5) * (a + c);
    let disc = T::from_f64(0.1).max(mid * mid - det).sqrt();
    let l1 = mid + disc;
    let l2 = mid - disc;
    ProjectCore {
        depth: t[2],
        ndc,
        cov2d: [a, b, c],
        det,
        conic,
        radius3: T::from_f64(3.0) * l1.max(l2).sqrt(),
        clamped_x: e.clamped_x,
        clamped_y: e.clamped_y,
    }
}

/// Where a projected Gaussian lands on the screen: steps 5 to 7 of
/// [`project`] and its culls, written without branches or library calls so
/// that a loop over a batch runs it in vector registers.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Footprint<T> {
    /// Whether the Gaussian survives every cull.
    pub visible: bool,
    /// Integer radius in pixels (`ceil(3·sqrt(λmax))`, 0 for NaN).
    pub radius: i32,
    /// Pixel-space centre.
    pub xy: [T; 2],
    /// Tile rectangle `[min, max)`.
    pub rect_min: [u32; 2],
    pub rect_max: [u32; 2],
}

/// The [`Footprint`] of the result of [`project_core`]. Equal to upstream's
/// order of operations: `ceil` then the conversion to `i32` (saturating,
/// NaN to 0) is computed on the radius clamped to `[0, 2³¹]` by rounding
/// with `2^(mantissa bits)` (exact below it; larger values are integers);
/// each tile bound `clamp(trunc(v), 0, grid)` is `trunc(clamp(v, 0, grid))`
/// (NaN to 0). The tests compare it with the direct form.
#[inline(always)]
pub(crate) fn footprint<T: Real>(k: &Intrinsics<T>, p: &ProjectCore<T>) -> Footprint<T> {
    let magic = T::from_f64(if T::PRECISION == crate::math::Precision::F32 {
        8_388_608.0 // 2^23
    } else {
        4_503_599_627_370_496.0 // 2^52
    });
    let x = T::ZERO.max(p.radius3).min(T::from_f64(2_147_483_648.0));
    let r = (x + magic) - magic;
    let up = if r < x { r + T::ONE } else { r };
    let ceil = if x < magic { up } else { x };
    let radius = ceil.to_f64() as i32;
    let xy = [ndc2pix(p.ndc[0], k.width), ndc2pix(p.ndc[1], k.height)];

    let rf = T::from_f64(radius as f64);
    let blk = T::from_usize(BLOCK);
    let blk1 = T::from_usize(BLOCK - 1);
    let bound = |v: T, hi: u32| T::ZERO.max(v).min(T::from_f64(hi as f64)).to_f64() as u32;
    let rect_min = [
        bound((xy[0] - rf) / blk, k.grid[0]),
        bound((xy[1] - rf) / blk, k.grid[1]),
    ];
    let rect_max = [
        bound((xy[0] + rf + blk1) / blk, k.grid[0]),
        bound((xy[1] + rf + blk1) / blk, k.grid[1]),
    ];
    let visible = p.depth > T::from_f64(0.2)
        && p.det != T::ZERO
        && radius != 0
        && rect_max[0] != rect_min[0]
        && rect_max[1] != rect_min[1];
    Footprint {
        visible,
        radius,
        xy,
        rect_min,
        rect_max,
    }
}

/// The [`Projected`] record of a Gaussian from its two parts.
#[inline(always)]
pub(crate) fn assemble<T: Real>(p: &ProjectCore<T>, f: &Footprint<T>) -> Projected<T> {
    if !f.visible {
        return Projected::culled();
    }
    Projected {
        radius: f.radius,
        depth: p.depth,
        xy: f.xy,
        conic: p.conic,
        cov2d: p.cov2d,
        rect_min: f.rect_min,
        rect_max: f.rect_max,
        clamped_x: p.clamped_x,
        clamped_y: p.clamped_y,
    }
}

/// Steps 5 to 7 of [`project`] and its culls, on the result of
/// [`project_core`].
#[inline(always)]
pub(crate) fn project_finish<T: Real>(k: &Intrinsics<T>, p: &ProjectCore<T>) -> Projected<T> {
    assemble(p, &footprint(k, p))
}

/// Steps 5 to 7 of [`project`] and its culls in upstream's direct form
/// (`ceil`, saturating conversions, then clamps): the reference
/// [`footprint`] is tested against.
#[cfg(test)]
fn project_finish_direct<T: Real>(k: &Intrinsics<T>, p: &ProjectCore<T>) -> Projected<T> {
    if p.depth <= T::from_f64(0.2) || p.depth.is_nan() || p.det == T::ZERO {
        return Projected::culled();
    }
    let radius_f = p.radius3.ceil();
    let radius = radius_f.to_f64().clamp(0.0, i32::MAX as f64) as i32;
    let xy = [ndc2pix(p.ndc[0], k.width), ndc2pix(p.ndc[1], k.height)];

    let rf = T::from_f64(radius as f64);
    let blk = T::from_usize(BLOCK);
    let blk1 = T::from_usize(BLOCK - 1);
    let clampi = |v: i64, hi: u32| v.max(0).min(hi as i64) as u32;
    let rect_min = [
        clampi(trunc_i64((xy[0] - rf) / blk), k.grid[0]),
        clampi(trunc_i64((xy[1] - rf) / blk), k.grid[1]),
    ];
    let rect_max = [
        clampi(trunc_i64((xy[0] + rf + blk1) / blk), k.grid[0]),
        clampi(trunc_i64((xy[1] + rf + blk1) / blk), k.grid[1]),
    ];
    if (rect_max[0] - rect_min[0]) as u64 * (rect_max[1] - rect_min[1]) as u64 == 0 || radius == 0 {
        return Projected::culled();
    }
    Projected {
        radius,
        depth: p.depth,
        xy,
        conic: p.conic,
        cov2d: p.cov2d,
        rect_min,
        rect_max,
        clamped_x: p.clamped_x,
        clamped_y: p.clamped_y,
    }
}

/// Forward for one Gaussian. `ndc_offset` is added to the projected NDC
/// centre (zero for ordinary rendering; see `rasterize_with_ndc_offset`).
/// The rasterizer runs it in batches (`super::preprocess`), as
/// [`project_core`] then [`project_finish`]; this is the one-Gaussian form
/// the batches are tested against.
#[cfg_attr(not(test), allow(dead_code))]
pub(crate) fn project<T: Real>(
    k: &Intrinsics<T>,
    mean: [T; 3],
    cov3d: &[T; 6],
    ndc_offset: [T; 2],
) -> Projected<T> {
    project_finish(k, &project_core(k, mean, cov3d, ndc_offset))
}

/// Gradients arriving at one Gaussian's projected quantities.
#[derive(Clone, Copy, Debug)]
pub(crate) struct ProjectedGrad<T> {
    /// dL/d(pixel-space centre).
    pub xy: [T; 2],
    /// dL/d(A, B, C), each the derivative w.r.t. the scalar used in `power`.
    pub conic: [T; 3],
    /// dL/d(view-space depth) (from the depth image).
    pub depth: T,
}

/// [`transform`] on any [`Arith`]: `m·[p; 1]`, component `i`.
#[inline(always)]
fn transform_n<N: Arith>(m: &[N::Elem; 16], p: [N; 3], i: usize) -> N {
    N::splat(m[i]) * p[0]
        + N::splat(m[4 + i]) * p[1]
        + N::splat(m[8 + i]) * p[2]
        + N::splat(m[12 + i])
}

/// `[f(0), f(1), f(2)]` for `three!(|i| f(i))`, written out: the closure of
/// `std::array::from_fn` may be left out of line, and an out-of-line
/// function runs without the caller's vector instruction set (each vector
/// operation in it then becomes a call).
macro_rules! three {
    (|$i:ident| $e:expr) => {
        [
            {
                let $i = 0;
                $e
            },
            {
                let $i = 1;
                $e
            },
            {
                let $i = 2;
                $e
            },
        ]
    };
}

/// Backward of [`project`] for visible Gaussians, on any [`Arith`] (one
/// Gaussian, or one per lane of a [`Pack`](crate::math::pack::Pack)): from
/// the forward's dilated 2D covariance `cov2d` ([`Projected::cov2d`]) and
/// tangent clamps `clamped` (x, y), returns `(dL/dmean (projection, EWA and
/// depth paths), dL/dcov3d slots, dL/dndc)`. In [`GradientMode::Inria`],
/// `g.xy` is already in NDC units, `g.conic[1]` is half of dL/dB, `g.depth`
/// is ignored, and the conic and tangent-clamp formulas are upstream's (see
/// the mode's documentation).
#[inline(always)]
#[allow(clippy::needless_range_loop)] // indices as in the formula
pub(crate) fn project_vjp<N: Arith>(
    k: &Intrinsics<N::Elem>,
    mean: [N; 3],
    cov3d: [N; 6],
    cov2d: [N; 3],
    clamped: [N::Mask; 2],
    g: ProjectedGrad<N>,
    mode: GradientMode,
) -> ([N; 3], [N; 6], [N; 2]) {
    let inria = mode == GradientMode::Inria;
    let [a, b, c] = cov2d;
    let [ga, gb, gc] = g.conic;
    let two = N::from_f64(2.0);
    let (da, db, dc) = if inria {
        // Upstream computeCov2DCUDA: `gb` is half of dL/dB; 1/(det² + 1e-7).
        let denom = a * c - b * b;
        let denom2inv = N::ONE / (denom * denom + N::from_f64(1e-7));
        let zero = denom2inv.eq_mask(N::ZERO);
        (
            N::select(
                zero,
                N::ZERO,
                denom2inv * (-c * c * ga + two * b * c * gb + (denom - a * c) * gc),
            ),
            N::select(
                zero,
                N::ZERO,
                denom2inv * two * (b * c * ga - (denom + two * b * b) * gb + a * b * gc),
            ),
            N::select(
                zero,
                N::ZERO,
                denom2inv * (-a * a * gc + two * a * b * gb + (denom - a * c) * ga),
            ),
        )
    } else {
        // Conic (A, B, C) = (c, −b, a)/det, det = ac − b².
        let det = a * c - b * b;
        let inv2 = N::ONE / (det * det);
        (
            (-(c * c) * ga + b * c * gb - b * b * gc) * inv2,
            (two * b * c * ga - (det + two * b * b) * gb + two * a * b * gc) * inv2,
            (-(b * b) * ga + a * b * gb - a * a * gc) * inv2,
        )
    };

    let t = [
        transform_n(&k.view, mean, 0),
        transform_n(&k.view, mean, 1),
        transform_n(&k.view, mean, 2),
    ];
    // Rows 0 and 1 of J·Wr and the clamped tx, ty, the operations of [`ewa`].
    let wr = |i: usize, j: usize| N::splat(k.wr(i, j));
    let (fx, fy) = (N::splat(k.fx), N::splat(k.fy));
    let txtz = t[0] / t[2];
    let tytz = t[1] / t[2];
    let e_tx = txtz.clamp(N::splat(-k.limx), N::splat(k.limx)) * t[2];
    let e_ty = tytz.clamp(N::splat(-k.limy), N::splat(k.limy)) * t[2];
    let tz2 = t[2] * t[2];
    let j00 = fx / t[2];
    let j02 = -(fx * e_tx) / tz2;
    let j11 = fy / t[2];
    let j12 = -(fy * e_ty) / tz2;
    let a0: [N; 3] = three!(|r| wr(0, r) * j00 + wr(2, r) * j02);
    let a1: [N; 3] = three!(|r| wr(1, r) * j11 + wr(2, r) * j12);
    let v = sym3(&cov3d);
    // a = A0ᵀVA0, b = A1ᵀVA0, c = A1ᵀVA1.
    let mut gcov = [N::ZERO; 6];
    let slots = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)];
    // (A function, not a closure: a closure the compiler leaves out of line
    // would run without the caller's vector instruction set.)
    #[inline(always)]
    fn full<N: Arith>(a0: &[N; 3], a1: &[N; 3], d: [N; 3], i: usize, j: usize) -> N {
        a0[i] * a0[j] * d[0] + a1[i] * a0[j] * d[1] + a1[i] * a1[j] * d[2]
    }
    for (s, &(i, j)) in slots.iter().enumerate() {
        let d = [da, db, dc];
        gcov[s] = if i == j {
            full(&a0, &a1, d, i, i)
        } else {
            full(&a0, &a1, d, i, j) + full(&a0, &a1, d, j, i)
        };
    }
    let va0: [N; 3] = three!(|i| v[i][0] * a0[0] + v[i][1] * a0[1] + v[i][2] * a0[2]);
    let va1: [N; 3] = three!(|i| v[i][0] * a1[0] + v[i][1] * a1[1] + v[i][2] * a1[2]);
    let ga0: [N; 3] = three!(|i| two * va0[i] * da + va1[i] * db);
    let ga1: [N; 3] = three!(|i| two * va1[i] * dc + va0[i] * db);
    // A(0, r) = Wr(0, r)·J00 + Wr(2, r)·J02; A(1, r) = Wr(1, r)·J11 + Wr(2, r)·J12.
    let mut dj00 = N::ZERO;
    let mut dj02 = N::ZERO;
    let mut dj11 = N::ZERO;
    let mut dj12 = N::ZERO;
    for r in 0..3 {
        dj00 += wr(0, r) * ga0[r];
        dj02 += wr(2, r) * ga0[r];
        dj11 += wr(1, r) * ga1[r];
        dj12 += wr(2, r) * ga1[r];
    }
    let tz = N::ONE / t[2];
    let tz2 = tz * tz;
    let tz3 = tz2 * tz;
    // J02 = −fx·tx'/tz² with tx' = tx (unclamped) or ±lim·tz (clamped):
    // ∂J02/∂tz is 2·fx·tx'/tz³ unclamped and fx·tx'/tz³ clamped. Upstream
    // (inria mode) uses the unclamped factor 2 in both cases.
    let kc = if inria { two } else { N::ONE };
    let (mx, kx) = (
        N::select(clamped[0], N::ZERO, N::ONE),
        N::select(clamped[0], kc, two),
    );
    let (my, ky) = (
        N::select(clamped[1], N::ZERO, N::ONE),
        N::select(clamped[1], kc, two),
    );
    let dtx = mx * N::splat(-k.fx) * tz2 * dj02;
    let dty = my * N::splat(-k.fy) * tz2 * dj12;
    let dtz = N::splat(-k.fx) * tz2 * dj00 - fy * tz2 * dj11
        + kx * fx * e_tx * tz3 * dj02
        + ky * fy * e_ty * tz3 * dj12
        + if inria { N::ZERO } else { g.depth };
    let dt = [dtx, dty, dtz];
    let mut gmean: [N; 3] = three!(|j| wr(0, j) * dt[0] + wr(1, j) * dt[1] + wr(2, j) * dt[2]);

    // Pixel = ((ndc + 1)·S − 1)/2, so d pixel / d ndc = S/2. Inria mode
    // accumulates the centre gradient in NDC units already.
    let gndc = if inria {
        g.xy
    } else {
        [
            g.xy[0] * N::from_f64(0.5 * k.width as f64),
            g.xy[1] * N::from_f64(0.5 * k.height as f64),
        ]
    };
    // ndc = p_hom.xy · m_w, m_w = 1/(p_hom.w + 1e-7).
    let m = &k.proj;
    let hx = transform_n(m, mean, 0);
    let hy = transform_n(m, mean, 1);
    let hw = transform_n(m, mean, 3);
    let mw = N::ONE / (hw + N::from_f64(1e-7));
    let mul1 = hx * mw * mw;
    let mul2 = hy * mw * mw;
    let mc = |i: usize| N::splat(m[i]);
    for j in 0..3 {
        gmean[j] += (mc(4 * j) * mw - mc(4 * j + 3) * mul1) * gndc[0]
            + (mc(4 * j + 1) * mw - mc(4 * j + 3) * mul2) * gndc[1];
    }
    (gmean, gcov, gndc)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::rng::Rng;

    fn intrinsics<T: Real>(w: usize, h: usize) -> Intrinsics<T> {
        let mut view = [T::ZERO; 16];
        for i in 0..4 {
            view[5 * i] = T::ONE;
        }
        Intrinsics::new(&crate::camera::RasterCamera {
            viewmatrix: view,
            projmatrix: view,
            campos: [T::ZERO; 3],
            tanfovx: T::from_f64(0.5),
            tanfovy: T::from_f64(0.4),
            width: w,
            height: h,
        })
    }

    fn same<T: Real>(a: &Projected<T>, b: &Projected<T>) -> bool {
        a.radius == b.radius
            && a.depth.bits() == b.depth.bits()
            && (0..2).all(|c| a.xy[c].bits() == b.xy[c].bits())
            && (0..3).all(|c| a.conic[c].bits() == b.conic[c].bits())
            && (0..3).all(|c| a.cov2d[c].bits() == b.cov2d[c].bits())
            && a.rect_min == b.rect_min
            && a.rect_max == b.rect_max
            && a.clamped_x == b.clamped_x
            && a.clamped_y == b.clamped_y
    }

    /// The branch-free footprint against the direct form, on radii and
    /// centres that are random, integers, half-integers, near the rounding
    /// and conversion limits, negative, zero of either sign, infinite or
    /// NaN, in f32 and f64.
    fn footprint_is_the_direct_form<T: Real>() {
        let mut rng = Rng::new(11);
        let special = [
            0.0,
            -0.0,
            1.0,
            1.5,
            2.5,
            0.499_999_9,
            3.000_000_1,
            8_388_607.5,
            8_388_608.0,
            8_388_609.0,
            16_777_217.0,
            4_503_599_627_370_495.5,
            2_147_483_520.0,
            2_147_483_647.5,
            2_147_483_648.0,
            3e9,
            1e30,
            -1.0,
            -1e30,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        for (w, h) in [(61usize, 47usize), (400, 400), (1 << 20, 3)] {
            let k = intrinsics::<T>(w, h);
            for trial in 0..20_000 {
                let mut pick = |scale: f64| {
                    let r = rng.uniform();
                    if r < 0.3 {
                        T::from_f64(special[(rng.next_u64() % special.len() as u64) as usize])
                    } else if r < 0.5 {
                        T::from_f64((rng.uniform() * scale).round() * 0.5)
                    } else {
                        T::from_f64((rng.uniform() - 0.3) * scale)
                    }
                };
                let p = ProjectCore {
                    depth: if trial % 7 == 0 { pick(1.0) } else { T::ONE },
                    ndc: [pick(4.0), pick(4.0)],
                    cov2d: [T::ONE, T::ZERO, T::ONE],
                    det: if trial % 11 == 0 { T::ZERO } else { T::ONE },
                    conic: [T::ONE, T::ZERO, T::ONE],
                    radius3: pick(if trial % 3 == 0 { 1e3 } else { 40.0 }),
                    clamped_x: false,
                    clamped_y: true,
                };
                let a = project_finish(&k, &p);
                let b = project_finish_direct(&k, &p);
                assert!(same(&a, &b), "{p:?}: {a:?} vs {b:?}");
            }
        }
    }

    #[test]
    fn footprint_is_the_direct_form_f32() {
        footprint_is_the_direct_form::<f32>();
    }

    #[test]
    fn footprint_is_the_direct_form_f64() {
        footprint_is_the_direct_form::<f64>();
    }
}
