//! Rasterizer properties: thread-count determinism, background, transmittance
//! range, order independence, near-plane culling, f32 vs f64, and a single
//! Gaussian computed by hand.

mod support;

use liquid_splat::camera::Camera;
use liquid_splat::math::Real;
use liquid_splat::render::scene::{random_scene, ColorSource, CovSource, Scene, SceneSpec};
use liquid_splat::render::{
    rasterize, rasterize_vjp, Colors, Covariances, GradientMode, RasterGrads, RasterInput,
    RasterOutput,
};
use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed};

fn run<T: Real>(
    scene: &Scene<T>,
    colors: ColorSource,
    cov: CovSource,
) -> (RasterOutput<T>, RasterGrads<T>) {
    run_mode(scene, colors, cov, GradientMode::Exact)
}

fn run_mode<T: Real>(
    scene: &Scene<T>,
    colors: ColorSource,
    cov: CovSource,
    mode: GradientMode,
) -> (RasterOutput<T>, RasterGrads<T>) {
    let input = scene.input(colors, cov);
    let (out, state) = rasterize(&input).unwrap();
    let gc: Vec<T> = liquid_splat::math::gradcheck::cotangent(3, out.color.len())
        .into_iter()
        .map(T::from_f64)
        .collect();
    let gd: Vec<T> = liquid_splat::math::gradcheck::cotangent(4, out.depth.len())
        .into_iter()
        .map(T::from_f64)
        .collect();
    let g = rasterize_vjp(&input, &state, &gc, Some(&gd), mode).unwrap();
    (out, g)
}

fn bits<T: Real>(v: &[T]) -> Vec<u64> {
    v.iter().map(|x| x.bits()).collect()
}

fn fingerprint<T: Real>(o: &RasterOutput<T>, g: &RasterGrads<T>) -> Vec<Vec<u64>> {
    vec![
        bits(&o.color),
        bits(&o.depth),
        bits(&o.final_t),
        bits(&o.means2d),
        o.radii.iter().map(|&r| r as u64).collect(),
        o.n_contrib.iter().map(|&r| r as u64).collect(),
        bits(&g.means3d),
        bits(&g.means2d),
        bits(&g.colors),
        bits(&g.opacities),
        bits(&g.scales_or_cov),
        bits(&g.rotations),
    ]
}

#[test]
fn bit_identical_for_1_2_3_threads() {
    let mut spec = SceneSpec::bench(128, 96, 300, 21);
    spec.scale_range = (0.02, 0.2);
    spec.off_axis = 4;
    let s64 = random_scene(&spec).unwrap();
    let s32 = s64.cast::<f32>();
    for (colors, cov, mode) in [
        (
            ColorSource::Sh,
            CovSource::ScaleRotation,
            GradientMode::Exact,
        ),
        (
            ColorSource::Precomputed,
            CovSource::Precomputed,
            GradientMode::Exact,
        ),
        (
            ColorSource::Sh,
            CovSource::ScaleRotation,
            GradientMode::Inria,
        ),
    ] {
        let mut prints64 = Vec::new();
        let mut prints32 = Vec::new();
        for threads in [1, 2, 3] {
            support::with_threads(threads, || {
                let (o, g) = run_mode(&s64, colors, cov, mode);
                prints64.push(fingerprint(&o, &g));
                let (o, g) = run_mode(&s32, colors, cov, mode);
                prints32.push(fingerprint(&o, &g));
            });
        }
        assert!(prints64[0][0].iter().any(|&b| b != 0));
        for t in 1..3 {
            assert!(
                prints64[0] == prints64[t],
                "f64 differs at {} threads",
                t + 1
            );
            assert!(
                prints32[0] == prints32[t],
                "f32 differs at {} threads",
                t + 1
            );
        }
    }
}

fn config() -> Config {
    Config {
        cases: 6,
        rng_seed: RngSeed::Fixed(0x5eed),
        failure_persistence: None,
        ..Config::default()
    }
}

fn small(count: usize, seed: u64) -> Scene<f64> {
    random_scene(&SceneSpec::small(count, seed)).unwrap()
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn empty_scene_is_the_background(seed in 0u64..1000) {
        let s = small(0, seed);
        let (out, _) = rasterize(&s.input(ColorSource::Sh, CovSource::ScaleRotation)).unwrap();
        let hw = 32 * 24;
        for ch in 0..3 {
            prop_assert!(out.color[ch * hw..(ch + 1) * hw].iter().all(|&c| c == s.background[ch]));
        }
        prop_assert!(out.depth.iter().all(|&d| d == 0.0));
        prop_assert!(out.final_t.iter().all(|&t| t == 1.0));
    }

    #[test]
    fn final_transmittance_is_in_unit_interval(seed in 0u64..1000, count in 1usize..20) {
        let s = small(count, seed);
        let (out, _) = rasterize(&s.input(ColorSource::Sh, CovSource::ScaleRotation)).unwrap();
        prop_assert!(out.final_t.iter().all(|&t| (0.0..=1.0).contains(&t)));
        prop_assert!(out.final_t.iter().any(|&t| t < 1.0));
    }

    /// Blending order depends only on (tile, depth), so permuting Gaussians
    /// with distinct depths performs the same arithmetic in the same order:
    /// the image is bitwise identical and the gradients are permuted bitwise.
    #[test]
    fn reordering_gaussians_changes_nothing(seed in 0u64..1000, count in 2usize..16) {
        let s = small(count, seed);
        let mut perm: Vec<usize> = (0..count).collect();
        liquid_splat::math::Rng::new(seed).shuffle(&mut perm);
        let take = |v: &[f64], w: usize| perm.iter().flat_map(|&i| v[w * i..w * (i + 1)].to_vec()).collect::<Vec<f64>>();
        let mut p = s.clone();
        p.means3d = take(&s.means3d, 3);
        p.sh = take(&s.sh, 48);
        p.opacities = take(&s.opacities, 1);
        p.scales = take(&s.scales, 3);
        p.rotations = take(&s.rotations, 4);
        let (o1, g1) = run(&s, ColorSource::Sh, CovSource::ScaleRotation);
        let (o2, g2) = run(&p, ColorSource::Sh, CovSource::ScaleRotation);
        prop_assert_eq!(bits(&o1.color), bits(&o2.color));
        prop_assert_eq!(bits(&o1.depth), bits(&o2.depth));
        prop_assert_eq!(bits(&take(&g1.means3d, 3)), bits(&g2.means3d));
        prop_assert_eq!(bits(&take(&g1.colors, 48)), bits(&g2.colors));
        prop_assert_eq!(bits(&take(&g1.rotations, 4)), bits(&g2.rotations));
    }

    #[test]
    fn gaussian_behind_near_plane_changes_nothing(seed in 0u64..1000, count in 1usize..10) {
        let s = small(count, seed);
        let mut b = s.clone();
        // Camera-space depth 0.15 < 0.2, centred in the view: would cover the image if drawn.
        let cam = &s.camera;
        let centre = cam.centre();
        let fwd = cam.rotation[2];
        b.means3d.extend((0..3).map(|k| centre[k] + 0.15 * fwd[k]));
        b.sh.extend(vec![1.0; 48]);
        b.opacities.push(0.9);
        b.scales.extend([0.5, 0.5, 0.5]);
        b.rotations.extend([1.0, 0.0, 0.0, 0.0]);
        let (o1, g1) = run(&s, ColorSource::Sh, CovSource::ScaleRotation);
        let (o2, g2) = run(&b, ColorSource::Sh, CovSource::ScaleRotation);
        prop_assert_eq!(bits(&o1.color), bits(&o2.color));
        prop_assert_eq!(o2.radii[count], 0);
        prop_assert!(g2.means3d[3 * count..].iter().chain(&g2.colors[48 * count..])
            .chain(&g2.opacities[count..]).chain(&g2.scales_or_cov[3 * count..])
            .chain(&g2.rotations[4 * count..]).all(|&g| g == 0.0));
        prop_assert_eq!(bits(&g1.means3d), bits(&g2.means3d[..3 * count]));
    }

    /// f32 and f64 renders agree to f32 rounding except where a hard decision
    /// (1/255 skip, transmittance stop) falls differently, which moves a
    /// pixel by at most about one skipped contribution (< 1/255 · colour).
    #[test]
    fn f32_agrees_with_f64(seed in 0u64..1000, count in 1usize..12) {
        let s = small(count, seed);
        let (o64, _) = run(&s, ColorSource::Sh, CovSource::ScaleRotation);
        let (o32, _) = run(&s.cast::<f32>(), ColorSource::Sh, CovSource::ScaleRotation);
        let mut close = 0;
        for (a, b) in o64.color.iter().zip(&o32.color) {
            let d = (a - *b as f64).abs();
            prop_assert!(d < 2e-2, "{a} vs {b}");
            if d < 1e-5 * a.abs().max(1.0) {
                close += 1;
            }
        }
        prop_assert!(close as f64 >= 0.99 * o64.color.len() as f64, "{close} of {}", o64.color.len());
    }
}

/// One isotropic Gaussian in front of an axis-aligned camera, against the
/// EWA formula written out independently.
#[test]
fn single_gaussian_pixel_values_by_hand() {
    // Inside the image; and reaching into its last tile column, 8 pixels
    // wide.
    single_gaussian_by_hand(0.15, -0.1, 0.06);
    single_gaussian_by_hand(0.33, 0.05, 0.12);
}

/// One Gaussian at camera-space `(x, y, 2)` of scale `s`: its pixels and the
/// pairs the backward replays against a formula written out here.
fn single_gaussian_by_hand(x: f64, y: f64, s: f64) {
    let (w, h) = (40usize, 30usize);
    let (fovx, fovy) = (0.9f64, 0.7f64);
    let cam = Camera::from_w2c(
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        [0.0; 3],
        fovx,
        fovy,
        w,
        h,
    )
    .unwrap();
    let rc = cam.raster::<f64>();
    let (z, o) = (2.0, 0.8);
    let col = [0.9, 0.4, 0.1];
    let bg = [0.1, 0.2, 0.3];
    let input = RasterInput {
        means3d: &[x, y, z],
        colors: Colors::Precomputed(&col),
        opacities: &[o],
        covariances: Covariances::ScaleRotation {
            scales: &[s, s, s],
            rotations: &[1.0, 0.0, 0.0, 0.0],
            scale_modifier: 1.0,
        },
        camera: &rc,
        background: bg,
    };
    let (out, saved) = rasterize(&input).unwrap();
    // Independent formula.
    let fx = w as f64 / (2.0 * libm::tan(fovx / 2.0));
    let fy = h as f64 / (2.0 * libm::tan(fovy / 2.0));
    let j = [
        [fx / z, 0.0, -fx * x / (z * z)],
        [0.0, fy / z, -fy * y / (z * z)],
    ];
    let dotj = |a: usize, b: usize| s * s * (0..3).map(|k| j[a][k] * j[b][k]).sum::<f64>();
    let (a, b, c) = (dotj(0, 0) + 0.3, dotj(0, 1), dotj(1, 1) + 0.3);
    let det = a * c - b * b;
    let (ia, ib, ic) = (c / det, -b / det, a / det);
    let u = w as f64 / 2.0 + fx * x / z - 0.5;
    let v = h as f64 / 2.0 + fy * y / z - 0.5;
    assert!((out.means2d[0] - u).abs() < 1e-5 && (out.means2d[1] - v).abs() < 1e-5);
    let mut checked = 0;
    // The pairs the backward replays: in each row, the pixels of every
    // 16-pixel tile segment in which the Gaussian blends at some pixel.
    let mut replayed = 0u64;
    let mut last_column = 0;
    for py in 0..h {
        for px in 0..w {
            let (dx, dy) = (u - px as f64, v - py as f64);
            let alpha =
                (o * libm::exp(-0.5 * (ia * dx * dx + ic * dy * dy) - ib * dx * dy)).min(0.99);
            let pix = py * w + px;
            let segment = px / 16 * 16..(px / 16 * 16 + 16).min(w);
            if alpha >= 1.0 / 255.0
                && !segment.clone().take_while(|&q| q < px).any(|q| {
                    let (dx, dy) = (u - q as f64, v - py as f64);
                    o * libm::exp(-0.5 * (ia * dx * dx + ic * dy * dy) - ib * dx * dy)
                        >= 1.0 / 255.0
                })
            {
                // The segment's first blending pixel.
                replayed += segment.len() as u64;
            }
            if alpha >= 1.0 / 255.0 && px >= 32 {
                last_column += 1;
            }
            if alpha < 1.0 / 255.0 {
                assert_eq!(out.final_t[pix], 1.0);
                continue;
            }
            for ch in 0..3 {
                let want = alpha * col[ch] + (1.0 - alpha) * bg[ch];
                let got = out.color[ch * w * h + pix];
                assert!(
                    (got - want).abs() < 1e-6,
                    "({px},{py}) ch {ch}: {got} vs {want}"
                );
            }
            assert!((out.depth[pix] - z * alpha).abs() < 1e-6);
            checked += 1;
        }
    }
    assert!(checked > 20, "only {checked} pixels covered");
    assert_eq!(saved.pairs_replayed(), replayed);
    assert!(saved.pairs_replayed() < saved.pairs_evaluated());
    if x > 0.3 {
        assert!(
            last_column > 0,
            "the Gaussian reaches the 8-pixel tile column"
        );
    }
}
