//! The forward's per-Gaussian stage: 3D covariance, projection ([`project`]),
//! colour and the data a pixel reads ([`Splat`]), in batches of [`BATCH`]
//! Gaussians.
//!
//! A batch is evaluated as vectors: the inputs are transposed so that lane
//! `l` holds Gaussian `first + l`, then one loop over the lanes runs the
//! branch-free part of the stage for every lane ([`cov3d`],
//! [`project_core`], [`sh_to_color_with`] at a constant degree, then the
//! radius, pixel centre, tile rectangle and culls, [`footprint`]), which
//! the compiler turns into vector instructions; the records and the
//! opacity threshold ([`power_min`], only for visible Gaussians) are then
//! written per Gaussian. The loop is compiled for AVX-512, AVX2 and the
//! baseline and picked at run time ([`crate::kernels::fastmath::isa`]).
//! Every lane does the scalar operations of one Gaussian in the scalar order
//! (IEEE additions, multiplications, divisions and square roots, comparisons
//! and selects; Rust never contracts `a·b + c` into an FMA), so every path
//! gives the bits of the one-Gaussian functions, which the tests check.
//! Lanes past the end of the last batch repeat its first Gaussian and are
//! discarded; lanes of culled Gaussians compute values that are not used.
//! The SH coefficients of a batch (up to 48 values per Gaussian) are
//! transposed with vector shuffles where `T` is f32
//! ([`super::transpose::RowMover`]; only bits move) and prefetched two
//! batches ahead:
//! they are read once per frame, and their cache misses dominated the stage.
//!
//! The outputs are written once, by index, into buffers that are not
//! initialised beforehand: the per-Gaussian state the backward reads, the
//! radii and centres the caller returns, and one [`Splat`] per Gaussian that
//! the binned list gathers from (one read per list entry).
//!
//! [`project`]: super::project::project

use super::project::{
    assemble, footprint, project_core, Footprint, Intrinsics, ProjectCore, Projected,
};
use super::rasterize::{candidate_rows_lanes, power_min, Splat};
use super::transpose::RowMover;
use super::{Colors, Covariances, RasterInput};
use crate::kernels::fastmath::multiversion;
use crate::kernels::prefetch;
use crate::math::covariance::cov3d;
use crate::math::pack::Pack;
use crate::math::sh::{sh_to_color_with, ShColorSaved};
use crate::math::Real;
use rayon::prelude::*;
use std::mem::MaybeUninit;

/// Gaussians per batch (one AVX-512 register of f32).
pub(crate) const BATCH: usize = 16;

/// Largest number of SH coefficient values per Gaussian (degree 3: 16 × 3).
const MAX_SH_VALUES: usize = 48;

/// The per-Gaussian results of the forward's first stage, `[N]` each.
#[derive(Debug)]
pub(crate) struct Preprocessed<T> {
    /// Projection of each Gaussian ([`Projected::culled`] when culled).
    pub proj: Vec<Projected<T>>,
    /// Colour of each Gaussian (0, unclamped, when culled).
    pub colors: Vec<ShColorSaved<T>>,
    /// 3D covariance of each Gaussian (upper triangle, row-major).
    pub cov3d: Vec<[T; 6]>,
    /// What a pixel reads of each visible Gaussian (all 0 when culled).
    pub splats: Vec<Splat<T>>,
    /// `[N]` integer radius in pixels, 0 when culled.
    pub radii: Vec<i32>,
    /// `[N, 2]` pixel-space centre, 0 when culled.
    pub means2d: Vec<T>,
}

/// The output slots of consecutive Gaussians: of one batch (`proj.len() ≤
/// BATCH`, every element written by [`batch`]) or, split into batches, of
/// all of them ([`Preprocessed::spare`], [`BatchOut::batches`]).
struct BatchOut<'a, T> {
    proj: &'a mut [MaybeUninit<Projected<T>>],
    colors: &'a mut [MaybeUninit<ShColorSaved<T>>],
    cov3d: &'a mut [MaybeUninit<[T; 6]>],
    splats: &'a mut [MaybeUninit<Splat<T>>],
    radii: &'a mut [MaybeUninit<i32>],
    means2d: &'a mut [MaybeUninit<T>],
}

/// Evaluate the `n` Gaussians of `input` (already validated; `ndc_offset`
/// `[N, 2]` when given), in parallel over batches.
pub(crate) fn preprocess<T: Real>(
    k: &Intrinsics<T>,
    input: &RasterInput<T>,
    n: usize,
    ndc_offset: Option<&[T]>,
) -> Preprocessed<T> {
    let mut pre = Preprocessed::with_capacity(n);
    let out = pre.spare(n);
    (
        out.proj.par_chunks_mut(BATCH),
        out.colors.par_chunks_mut(BATCH),
        out.cov3d.par_chunks_mut(BATCH),
        out.splats.par_chunks_mut(BATCH),
        out.radii.par_chunks_mut(BATCH),
        out.means2d.par_chunks_mut(2 * BATCH),
    )
        .into_par_iter()
        .with_min_len(4)
        .enumerate()
        .for_each(|(b, (proj, colors, cov3d, splats, radii, means2d))| {
            let mut out = BatchOut {
                proj,
                colors,
                cov3d,
                splats,
                radii,
                means2d,
            };
            // The batch's output lines, asked for before its arithmetic
            // ([`BatchOut::prefetch_write`]): in the machine's slow periods
            // the trained hellwarrior frames' projection on two threads
            // took 5.8 ms for 10 cameras against 8.2 without (4.8 against
            // 4.7 in quiet minutes).
            out.prefetch_write();
            batch(k, input, ndc_offset, b * BATCH, &mut out);
        });
    // SAFETY: the chunks above cover all of `out`, and `batch_body` writes
    // every element of the chunks it is given (its final loop runs over
    // all of them).
    unsafe { pre.set_len(n) };
    pre
}

impl<T> Preprocessed<T> {
    /// Empty buffers with room for `n` Gaussians.
    fn with_capacity(n: usize) -> Self {
        Preprocessed {
            proj: Vec::with_capacity(n),
            colors: Vec::with_capacity(n),
            cov3d: Vec::with_capacity(n),
            splats: Vec::with_capacity(n),
            radii: Vec::with_capacity(n),
            means2d: Vec::with_capacity(2 * n),
        }
    }

    /// The uninitialised slots of the first `n` Gaussians (capacity at
    /// least `n`).
    fn spare(&mut self, n: usize) -> BatchOut<'_, T> {
        BatchOut {
            proj: &mut self.proj.spare_capacity_mut()[..n],
            colors: &mut self.colors.spare_capacity_mut()[..n],
            cov3d: &mut self.cov3d.spare_capacity_mut()[..n],
            splats: &mut self.splats.spare_capacity_mut()[..n],
            radii: &mut self.radii.spare_capacity_mut()[..n],
            means2d: &mut self.means2d.spare_capacity_mut()[..2 * n],
        }
    }

    /// Take the first `n` Gaussians' slots as written.
    ///
    /// # Safety
    /// Every element of [`Self::spare`]`(n)` has been written.
    unsafe fn set_len(&mut self, n: usize) {
        // SAFETY: the caller's guarantee.
        unsafe {
            self.proj.set_len(n);
            self.colors.set_len(n);
            self.cov3d.set_len(n);
            self.splats.set_len(n);
            self.radii.set_len(n);
            self.means2d.set_len(2 * n);
        }
    }
}

/// [`preprocess`] on two workers, batch by batch from both ends
/// ([`crate::threads::from_both_ends`]: one worker takes batches from the
/// first, the other from the last, until they meet); each worker then calls
/// `then(first, proj)` on the projections of the batches it ran (the
/// Gaussians `first..first + proj.len()`, consecutive), so that the work
/// that follows on them runs on the worker that has their data at hand.
/// Returns both results, the first Gaussians' first. Same values as
/// [`preprocess`]; where the two parts meet depends on timing only.
///
/// Against two fixed halves, measured on a 2-core shared machine on the
/// 64×64 bench frame (one binary alternating the two by pass): about the
/// same in quiet minutes, and the forward's median pass 15–24 µs shorter
/// (of 355–390) in rounds slowed by the machine's other tenants, where one
/// core at a time can run much slower than the other (benches/README.md,
/// "Rasterizer: small frames' steps handed out from both ends").
pub(crate) fn preprocess_in_two_runs<T: Real, R: Send>(
    k: &Intrinsics<T>,
    input: &RasterInput<T>,
    n: usize,
    ndc_offset: Option<&[T]>,
    then: impl Fn(usize, &[Projected<T>]) -> R + Sync,
) -> (Preprocessed<T>, [R; 2]) {
    let mut pre = Preprocessed::with_capacity(n);
    let all = pre.spare(n);
    let proj = Projections(all.proj.as_ptr());
    let batches = all.batches();
    let n_batches = batches.len();
    let (a, b) = crate::threads::from_both_ends(
        batches,
        // The number of batches a worker ran: consecutive, from the first
        // (the front) or up to the last (`from_both_ends`).
        |_| 0usize,
        |ran, b, mut out| {
            // The batch's output lines, asked for before its arithmetic
            // ([`BatchOut::prefetch_write`]).
            out.prefetch_write();
            batch(k, input, ndc_offset, b * BATCH, &mut out);
            *ran += 1;
        },
        |ran, front| {
            let [lo, hi] = if front {
                [0, ran]
            } else {
                [n_batches - ran, n_batches]
            };
            let (first, end) = ((lo * BATCH).min(n), (hi * BATCH).min(n));
            // SAFETY: this worker ran the batches `lo..hi`, and `batch_body`
            // writes every element of the batch it is given; the other
            // worker writes only its own batches.
            then(first, unsafe { proj.get(first, end) })
        },
    );
    // SAFETY: the two workers together ran every batch (a panic in one
    // propagates before this line), and the batches cover all of `all`.
    unsafe { pre.set_len(n) };
    (pre, [a, b])
}

/// The projections' slots of [`preprocess_in_two_runs`], shared by its two
/// workers, each reading only the ones it wrote.
struct Projections<T>(*const MaybeUninit<Projected<T>>);

// SAFETY: each worker reads only the slots it wrote itself (see `get`).
unsafe impl<T: Sync> Sync for Projections<T> {}

impl<T> Projections<T> {
    /// Slots `first..end` as written values.
    ///
    /// # Safety
    /// They are inside the buffer, the calling thread wrote every one of
    /// them, and no thread writes them while the result lives.
    unsafe fn get(&self, first: usize, end: usize) -> &[Projected<T>] {
        // SAFETY: as the caller promises.
        unsafe { assume_init(std::slice::from_raw_parts(self.0.add(first), end - first)) }
    }
}

/// `s` as initialised values, for as long as `s` is borrowed.
///
/// # Safety
/// Every element of `s` has been written.
unsafe fn assume_init<X>(s: &[MaybeUninit<X>]) -> &[X] {
    // SAFETY: `MaybeUninit<X>` has the layout of `X`, and the caller
    // guarantees every element is initialised.
    unsafe { std::slice::from_raw_parts(s.as_ptr() as *const X, s.len()) }
}

impl<'a, T> BatchOut<'a, T> {
    /// Ask for all the lines of these outputs for writing (only a hint).
    /// The other core may have read them in the pass before (when the
    /// allocator hands back the same blocks, as it usually does for a frame
    /// rendered again), and in the machine's slow periods each such line
    /// costs a long round trip between the CPUs: asked for before a batch's
    /// arithmetic, the round trips overlap it (benches/README.md, "Lines
    /// the other core read, asked for before writing").
    fn prefetch_write(&self) {
        use crate::kernels::prefetch_write as pw;
        let len = self.proj.len();
        pw(self.proj, 0, len);
        pw(self.colors, 0, len);
        pw(self.cov3d, 0, len);
        pw(self.splats, 0, len);
        pw(self.radii, 0, len);
        pw(self.means2d, 0, 2 * len);
    }

    /// The outputs of each batch of [`BATCH`] Gaussians, in order (the last
    /// may be shorter).
    fn batches(self) -> Vec<BatchOut<'a, T>> {
        self.proj
            .chunks_mut(BATCH)
            .zip(self.colors.chunks_mut(BATCH))
            .zip(self.cov3d.chunks_mut(BATCH))
            .zip(self.splats.chunks_mut(BATCH))
            .zip(self.radii.chunks_mut(BATCH))
            .zip(self.means2d.chunks_mut(2 * BATCH))
            .map(
                |(((((proj, colors), cov3d), splats), radii), means2d)| BatchOut {
                    proj,
                    colors,
                    cov3d,
                    splats,
                    radii,
                    means2d,
                },
            )
            .collect()
    }
}

multiversion!(fn batch<T: Real>(k: &Intrinsics<T>, input: &RasterInput<'_, T>, ndc_offset: Option<&[T]>, first: usize, out: &mut BatchOut<'_, T>) => batch_body);

/// One batch (see the module docs); `out` holds `1..=BATCH` Gaussians.
#[inline(always)]
#[allow(clippy::needless_range_loop)] // lanes index several arrays at once
fn batch_body<T: Real>(
    k: &Intrinsics<T>,
    input: &RasterInput<'_, T>,
    ndc_offset: Option<&[T]>,
    first: usize,
    out: &mut BatchOut<'_, T>,
) {
    let len = out.proj.len();
    // The Gaussian of lane `l`.
    let g = |l: usize| first + if l < len { l } else { 0 };
    let z = [T::ZERO; BATCH];
    let mut mean = [z; 3];
    let mut off = [z; 2];
    for l in 0..BATCH {
        let i = g(l);
        for c in 0..3 {
            mean[c][l] = input.means3d[3 * i + c];
        }
        if let Some(o) = ndc_offset {
            off[0][l] = o[2 * i];
            off[1][l] = o[2 * i + 1];
        }
    }
    let mut cov = [z; 6];
    match input.covariances {
        Covariances::ScaleRotation {
            scales,
            rotations,
            scale_modifier,
        } => {
            let mut s = [z; 3];
            let mut q = [z; 4];
            for l in 0..BATCH {
                let i = g(l);
                for c in 0..3 {
                    s[c][l] = scales[3 * i + c];
                }
                for c in 0..4 {
                    q[c][l] = rotations[4 * i + c];
                }
            }
            for l in 0..BATCH {
                let c = cov3d(
                    [s[0][l], s[1][l], s[2][l]],
                    scale_modifier,
                    [q[0][l], q[1][l], q[2][l], q[3][l]],
                );
                for j in 0..6 {
                    cov[j][l] = c[j];
                }
            }
        }
        Covariances::Precomputed(c) => {
            for l in 0..BATCH {
                let i = g(l);
                for j in 0..6 {
                    cov[j][l] = c[6 * i + j];
                }
            }
        }
    }

    let mut depth = z;
    let mut ndc = [z; 2];
    let mut cov2d = [z; 3];
    let mut det = z;
    let mut conic = [z; 3];
    let mut radius3 = z;
    let mut clamped = [[false; BATCH]; 2];
    for l in 0..BATCH {
        let p = project_core(
            k,
            [mean[0][l], mean[1][l], mean[2][l]],
            &[
                cov[0][l], cov[1][l], cov[2][l], cov[3][l], cov[4][l], cov[5][l],
            ],
            [off[0][l], off[1][l]],
        );
        depth[l] = p.depth;
        ndc[0][l] = p.ndc[0];
        ndc[1][l] = p.ndc[1];
        for c in 0..3 {
            cov2d[c][l] = p.cov2d[c];
            conic[c][l] = p.conic[c];
        }
        det[l] = p.det;
        radius3[l] = p.radius3;
        clamped[0][l] = p.clamped_x;
        clamped[1][l] = p.clamped_y;
    }

    let mut color = [z; 3];
    let mut color_clamped = [[false; BATCH]; 3];
    if let Colors::Sh {
        coeffs,
        stride,
        degree,
    } = input.colors
    {
        let campos = input.camera.campos;
        let sh = ShBatch {
            coeffs,
            stride,
            campos,
            mean: &mean,
        };
        match degree {
            0 => sh.colors::<0>(&g, &mut color, &mut color_clamped),
            1 => sh.colors::<1>(&g, &mut color, &mut color_clamped),
            2 => sh.colors::<2>(&g, &mut color, &mut color_clamped),
            _ => sh.colors::<3>(&g, &mut color, &mut color_clamped),
        }
    }

    let core = |l: usize| ProjectCore {
        depth: depth[l],
        ndc: [ndc[0][l], ndc[1][l]],
        cov2d: [cov2d[0][l], cov2d[1][l], cov2d[2][l]],
        det: det[l],
        conic: [conic[0][l], conic[1][l], conic[2][l]],
        radius3: radius3[l],
        clamped_x: clamped[0][l],
        clamped_y: clamped[1][l],
    };
    let mut visible = [false; BATCH];
    let mut radius = [0i32; BATCH];
    let mut xy = [z; 2];
    let mut rect = [[[0u32; BATCH]; 2]; 2];
    for l in 0..BATCH {
        let f = footprint(k, &core(l));
        visible[l] = f.visible;
        radius[l] = f.radius;
        for c in 0..2 {
            xy[c][l] = f.xy[c];
            rect[0][c][l] = f.rect_min[c];
            rect[1][c][l] = f.rect_max[c];
        }
    }

    // The visible lanes' opacity thresholds, and every lane's candidate
    // rows at once (kept for the visible ones).
    let pm: [T; BATCH] = std::array::from_fn(|l| {
        if visible[l] {
            power_min(input.opacities[g(l)])
        } else {
            T::ZERO
        }
    });
    let rows = candidate_rows_lanes(xy, conic, pm, k.height);

    for l in 0..len {
        let i = first + l;
        let p = assemble(
            &core(l),
            &Footprint {
                visible: visible[l],
                radius: radius[l],
                xy: [xy[0][l], xy[1][l]],
                rect_min: [rect[0][0][l], rect[0][1][l]],
                rect_max: [rect[1][0][l], rect[1][1][l]],
            },
        );
        let (c, s) = if p.radius > 0 {
            let c = match input.colors {
                Colors::Sh { .. } => ShColorSaved {
                    color: [color[0][l], color[1][l], color[2][l]],
                    clamped: [
                        color_clamped[0][l],
                        color_clamped[1][l],
                        color_clamped[2][l],
                    ],
                },
                Colors::Precomputed(_) => input.color(i),
            };
            let s = Splat {
                xy: p.xy,
                conic: p.conic,
                opacity: input.opacities[i],
                color: c.color,
                depth: p.depth,
                power_min: pm[l],
                rows: rows[l],
            };
            (c, s)
        } else {
            let c = ShColorSaved {
                color: [T::ZERO; 3],
                clamped: [false; 3],
            };
            let s = Splat {
                xy: [T::ZERO; 2],
                conic: [T::ZERO; 3],
                opacity: T::ZERO,
                color: [T::ZERO; 3],
                depth: T::ZERO,
                power_min: T::ZERO,
                rows: [0, 0],
            };
            (c, s)
        };
        out.radii[l].write(p.radius);
        out.means2d[2 * l].write(p.xy[0]);
        out.means2d[2 * l + 1].write(p.xy[1]);
        out.proj[l].write(p);
        out.colors[l].write(c);
        out.splats[l].write(s);
        out.cov3d[l].write([
            cov[0][l], cov[1][l], cov[2][l], cov[3][l], cov[4][l], cov[5][l],
        ]);
    }
}

/// What the SH colours of a batch read.
struct ShBatch<'a, T> {
    coeffs: &'a [T],
    stride: usize,
    campos: [T; 3],
    mean: &'a [[T; BATCH]; 3],
}

impl<T: Real> ShBatch<'_, T> {
    /// Colours at degree `D` of the lanes' Gaussians (`g(l)`): the
    /// coefficients transposed to one row per value, then
    /// [`sh_to_color_with`] per lane.
    #[inline(always)]
    #[allow(clippy::needless_range_loop)] // lanes index several arrays at once
    fn colors<const D: usize>(
        &self,
        g: &impl Fn(usize) -> usize,
        color: &mut [[T; BATCH]; 3],
        clamped: &mut [[bool; BATCH]; 3],
    ) {
        let n = 3 * (D + 1) * (D + 1);
        prefetch(
            self.coeffs,
            (g(0) + 2 * BATCH) * self.stride * 3,
            BATCH * self.stride * 3,
        );
        let mut c = [Pack([T::ZERO; BATCH]); MAX_SH_VALUES];
        let at: [usize; BATCH] = std::array::from_fn(|l| g(l) * self.stride * 3);
        RowMover::new::<T>().load(self.coeffs, &at, &mut c[..n]);
        for l in 0..BATCH {
            let m = [self.mean[0][l], self.mean[1][l], self.mean[2][l]];
            let r = sh_to_color_with(D, |j| c[j].0[l], m, self.campos);
            for ch in 0..3 {
                color[ch][l] = r.color[ch];
                clamped[ch][l] = r.clamped[ch];
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::rasterize::candidate_rows;
    use super::*;
    use crate::camera::RasterCamera;
    use crate::kernels::fastmath::{force_isa, Isa};
    use crate::math::rng::Rng;

    /// A camera at the origin looking down +z (row-vector matrices).
    fn camera<T: Real>(w: usize, h: usize) -> RasterCamera<T> {
        let f = |v: f64| T::from_f64(v);
        let (tx, ty) = (0.6, 0.45);
        let (near, far) = (0.01, 100.0);
        let mut view = [T::ZERO; 16];
        for i in 0..4 {
            view[5 * i] = T::ONE;
        }
        // Perspective projection, transposed (row vectors).
        let mut proj = [T::ZERO; 16];
        proj[0] = f(1.0 / tx);
        proj[5] = f(1.0 / ty);
        proj[10] = f(far / (far - near));
        proj[11] = T::ONE;
        proj[14] = f(-(far * near) / (far - near));
        RasterCamera {
            viewmatrix: view,
            projmatrix: proj,
            campos: [f(0.1), f(-0.2), f(-0.3)],
            tanfovx: f(tx),
            tanfovy: f(ty),
            width: w,
            height: h,
        }
    }

    fn same<T: Real>(a: T, b: T) -> bool {
        a.bits() == b.bits()
    }

    /// Compare [`preprocess`] with the one-Gaussian functions, bit for bit.
    fn check_against_scalar<T: Real>(
        input: &RasterInput<T>,
        n: usize,
        off: Option<&[T]>,
        what: &str,
    ) -> usize {
        let k = Intrinsics::new(input.camera);
        let got = preprocess(&k, input, n, off);
        let mut visible = 0;
        for i in 0..n {
            let cov = input.cov3d(i);
            let o = off.map_or([T::ZERO; 2], |o| [o[2 * i], o[2 * i + 1]]);
            let p = super::super::project::project(&k, input.mean(i), &cov, o);
            let q = &got.proj[i];
            let ok = p.radius == q.radius
                && same(p.depth, q.depth)
                && (0..2).all(|c| same(p.xy[c], q.xy[c]))
                && (0..3).all(|c| same(p.conic[c], q.conic[c]) && same(p.cov2d[c], q.cov2d[c]))
                && p.rect_min == q.rect_min
                && p.rect_max == q.rect_max
                && p.clamped_x == q.clamped_x
                && p.clamped_y == q.clamped_y;
            assert!(ok, "{what}: projection of Gaussian {i}: {p:?} vs {q:?}");
            assert!(
                (0..6).all(|j| same(cov[j], got.cov3d[i][j])),
                "{what}: cov3d of {i}"
            );
            assert_eq!(got.radii[i], p.radius, "{what}: radius of {i}");
            assert!(same(got.means2d[2 * i], p.xy[0]) && same(got.means2d[2 * i + 1], p.xy[1]));
            let want = if p.radius > 0 {
                visible += 1;
                input.color(i)
            } else {
                ShColorSaved {
                    color: [T::ZERO; 3],
                    clamped: [false; 3],
                }
            };
            assert!(
                (0..3).all(|ch| same(want.color[ch], got.colors[i].color[ch]))
                    && want.clamped == got.colors[i].clamped,
                "{what}: colour of {i}: {want:?} vs {:?}",
                got.colors[i]
            );
            if p.radius > 0 {
                let s = &got.splats[i];
                let o = input.opacities[i];
                assert!(
                    same(s.opacity, o)
                        && same(s.power_min, power_min(o))
                        && s.rows
                            == candidate_rows(p.xy, p.conic, power_min(o), input.camera.height)
                        && same(s.depth, p.depth)
                        && (0..2).all(|c| same(s.xy[c], p.xy[c]))
                        && (0..3).all(|c| same(s.conic[c], p.conic[c]))
                        && (0..3).all(|c| same(s.color[c], want.color[c])),
                    "{what}: splat of {i}"
                );
            }
        }
        visible
    }

    /// Random Gaussians around the view, some behind the camera, off
    /// screen, degenerate (zero scale) or with non-finite values.
    /// Means, scales, rotations, opacities, SH (16 per Gaussian), then 3D
    /// covariances followed by NDC offsets.
    type Scene<T> = [Vec<T>; 6];

    fn scene<T: Real>(n: usize, seed: u64) -> Scene<T> {
        let mut rng = Rng::new(seed);
        let mut u = |lo: f64, hi: f64| T::from_f64(lo + (hi - lo) * rng.uniform());
        let mut means = Vec::new();
        let mut scales = Vec::new();
        let mut rots = Vec::new();
        let mut opac = Vec::new();
        let mut sh = Vec::new();
        let mut cov = Vec::new();
        for i in 0..n {
            let z = match i % 11 {
                0 => u(-2.0, 0.25),
                _ => u(0.3, 12.0),
            };
            means.extend([
                u(-4.0, 4.0) * z / T::from_f64(3.0),
                u(-3.0, 3.0) * z / T::from_f64(3.0),
                z,
            ]);
            if i % 13 == 5 {
                scales.extend([T::ZERO; 3]);
            } else if i % 29 == 7 {
                scales.extend([T::from_f64(f64::NAN), u(0.0, 1.0), u(0.0, 1.0)]);
            } else {
                scales.extend([u(0.001, 0.5), u(0.001, 0.5), u(0.001, 0.5)]);
            }
            rots.extend([u(-1.0, 1.0), u(-1.0, 1.0), u(-1.0, 1.0), u(-1.0, 1.0)]);
            opac.push(match i % 17 {
                0 => T::ZERO,
                1 => T::from_f64(f64::INFINITY),
                _ => u(0.0, 1.0),
            });
            for _ in 0..48 {
                sh.push(u(-1.0, 1.0));
            }
            for _ in 0..6 {
                cov.push(u(-0.1, 0.3));
            }
        }
        let mut rng = Rng::new(seed + 1);
        let off: Vec<T> = (0..2 * n)
            .map(|_| T::from_f64(rng.uniform() - 0.5))
            .collect();
        [
            means,
            scales,
            rots,
            opac,
            sh,
            cov.into_iter().chain(off).collect(),
        ]
    }

    /// [`preprocess_in_two_runs`] gives the results of [`preprocess`], and
    /// hands each worker's projections to its callback: two consecutive
    /// runs of whole batches that cover all the Gaussians.
    fn check_two_runs<T: Real>() {
        for (n, seed) in [(203usize, 7u64), (33, 8), (16, 9), (1, 10), (0, 11)] {
            let [means, scales, rots, opac, sh, _] = scene::<T>(n, seed);
            let cam = camera::<T>(61, 47);
            let input = RasterInput {
                means3d: &means,
                colors: Colors::Sh {
                    coeffs: &sh,
                    stride: 16,
                    degree: 3,
                },
                opacities: &opac,
                covariances: Covariances::ScaleRotation {
                    scales: &scales,
                    rotations: &rots,
                    scale_modifier: T::ONE,
                },
                camera: &cam,
                background: [T::ZERO; 3],
            };
            let k = Intrinsics::new(input.camera);
            let want = preprocess(&k, &input, n, None);
            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let (got, runs) = pool.install(|| {
                    preprocess_in_two_runs(&k, &input, n, None, |first, proj| {
                        (first, format!("{proj:?}"))
                    })
                });
                // Debug prints every value's shortest round trip: equal
                // text, equal values.
                assert_eq!(format!("{got:?}"), format!("{want:?}"), "n {n}");
                let cut = runs[1].0;
                assert!(cut % BATCH == 0 || cut == n, "n {n}: {cut}");
                assert!(cut <= n, "n {n}: {cut}");
                if threads == 1 {
                    assert_eq!(cut, n, "one thread runs every batch from the front");
                }
                assert_eq!(runs[0], (0, format!("{:?}", &want.proj[..cut])), "n {n}");
                assert_eq!(runs[1].1, format!("{:?}", &want.proj[cut..]), "n {n}");
            }
        }
    }

    #[test]
    fn two_runs_match_the_parallel_stage() {
        check_two_runs::<f32>();
        check_two_runs::<f64>();
    }

    fn check_all_paths<T: Real>() {
        let _isa = crate::kernels::fastmath::isa_test_lock();
        // Sizes with a partial last batch, one Gaussian, and none.
        for (n, seed) in [(203usize, 3u64), (16, 4), (1, 5), (0, 6)] {
            let [means, scales, rots, opac, sh, rest] = scene::<T>(n, seed);
            let (cov, off) = rest.split_at(6 * n);
            let cam = camera::<T>(61, 47);
            for isa in [Isa::Baseline, Isa::Avx2, Isa::Avx512] {
                if !force_isa(Some(isa)) {
                    continue;
                }
                for degree in 0..=3 {
                    let input = RasterInput {
                        means3d: &means,
                        colors: Colors::Sh {
                            coeffs: &sh,
                            stride: 16,
                            degree,
                        },
                        opacities: &opac,
                        covariances: Covariances::ScaleRotation {
                            scales: &scales,
                            rotations: &rots,
                            scale_modifier: T::from_f64(1.3),
                        },
                        camera: &cam,
                        background: [T::ZERO; 3],
                    };
                    let what = format!("{isa:?}, n {n}, degree {degree}");
                    let v = check_against_scalar(&input, n, None, &what);
                    // The scene has both visible and culled Gaussians.
                    assert!(
                        n < 100 || (v > n / 10 && v < n * 9 / 10),
                        "{what}: {v} visible"
                    );
                    check_against_scalar(&input, n, Some(off), &what);
                }
                let input = RasterInput {
                    means3d: &means,
                    colors: Colors::Precomputed(&sh[..3 * n]),
                    opacities: &opac,
                    covariances: Covariances::Precomputed(cov),
                    camera: &cam,
                    background: [T::ZERO; 3],
                };
                check_against_scalar(&input, n, None, &format!("{isa:?}, precomputed"));
            }
            force_isa(None);
        }
    }

    /// Every instruction-set path gives the one-Gaussian functions' bits.
    #[test]
    fn batches_match_one_gaussian_functions_on_every_path_f32() {
        check_all_paths::<f32>();
    }

    /// The same in f64.
    #[test]
    fn batches_match_one_gaussian_functions_on_every_path_f64() {
        check_all_paths::<f64>();
    }
}
