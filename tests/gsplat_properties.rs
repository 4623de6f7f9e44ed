//! Properties of the gsplat-convention stages: agreement with the Inria stage
//! where the conventions coincide, agreement between the two versions where
//! their differences cannot act, hand-made cases on each side of every
//! convention difference, the two gradient modes, and thread-count
//! independence.

mod gsplat_common;
mod support;

use gsplat_common::*;
use liquid_splat::camera::Camera;
use liquid_splat::gsplat::isect::{isect_offset_encode, isect_tiles, IsectInput, TileRule};
use liquid_splat::gsplat::projection::{
    fully_fused_projection, Covars, ProjectionInput, ProjectionSettings,
};
use liquid_splat::gsplat::rendering::{
    rasterization, rasterization_vjp, Colors as GColors, RasterizationInput, RasterizationSettings,
    RasterizeMode,
};
use liquid_splat::gsplat::{camera_tensors, GradientMode, Version};
use liquid_splat::math::gradcheck::cotangent;
use liquid_splat::render::{rasterize, rasterize_vjp, Colors, Covariances, RasterInput};

fn max_rel(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let scale = a
        .iter()
        .chain(b)
        .fold(0.0f64, |m, x| m.max(x.abs()))
        .max(1e-300);
    a.iter()
        .zip(b)
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
        / scale
}

fn unit_quats(q: &[f64]) -> Vec<f64> {
    q.chunks(4)
        .flat_map(|c| {
            let n = (c.iter().map(|x| x * x).sum::<f64>()).sqrt();
            c.iter().map(move |x| x / n).collect::<Vec<_>>()
        })
        .collect()
}

/// With `cx = W/2`, `cy = H/2`, unit quaternions, opacities below 0.35 (so
/// every pixel with `α ≥ 1/255` lies inside the 3σ radius of the Inria stage
/// and `o·G` never reaches either alpha clamp), every centre inside the image
/// and deeper than 0.2, an image no larger than one 16×16 tile (the Inria
/// stage's tile rectangle `(int)((p + r + 15)/16)` can leave out a partly
/// covered tile when `p + r` has a fractional part; gsplat's boxes cannot),
/// SH colours and a background, classic mode, the default `eps2d = 0.3`:
/// gsplat's composite (either version, packed or dense) and the Inria stage
/// render the same image, and their exact gradients of means, scales,
/// opacities and SH coefficients agree (the quaternion gradient is gsplat's
/// projected onto the unit sphere's tangent). "The same" means to 1e-6
/// relative: the Inria stage divides by `w + 1e-7` in its projection, which
/// moves centres by about 1e-7 pixel (measured 1.4e-7).
#[test]
fn composite_equals_the_inria_stage_where_conventions_coincide() {
    for seed in 0..4u64 {
        let spec = SceneSpec {
            opacity: (0.02, 0.35),
            spread: 0.7,
            ..SceneSpec::new(10, 1, 16, 13)
        };
        let mut s = scene(&spec, 500 + seed);
        s.quats = unit_quats(&s.quats);
        let cam: &Camera = &s.cams[0];
        let rc = cam.raster::<f64>();
        let degree = 3;
        let bg = [s.backgrounds[0], s.backgrounds[1], s.backgrounds[2]];
        let inria_in = RasterInput {
            means3d: &s.means,
            colors: Colors::Sh {
                coeffs: &s.sh,
                stride: 16,
                degree,
            },
            opacities: &s.opacities,
            covariances: Covariances::ScaleRotation {
                scales: &s.scales,
                rotations: &s.quats,
                scale_modifier: 1.0,
            },
            camera: &rc,
            background: bg,
        };
        let (io, state) = rasterize(&inria_in).unwrap();
        assert!(io.radii.iter().all(|&r| r > 0), "every Gaussian visible");
        let (h, w) = (s.height, s.width);
        let hw = h * w;
        let gcol = cotangent(seed, 3 * hw);
        let ig = rasterize_vjp(&inria_in, &state, &gcol, None, Default::default()).unwrap();
        for version in Version::ALL {
            for packed in [true, false] {
                let settings = RasterizationSettings {
                    packed,
                    ..RasterizationSettings::new(w, h, version)
                };
                let gin = RasterizationInput {
                    means: &s.means,
                    covars: Covars::QuatScale {
                        quats: &s.quats,
                        scales: &s.scales,
                    },
                    opacities: &s.opacities,
                    colors: GColors::Sh {
                        coeffs: &s.sh,
                        k: 16,
                        degree,
                    },
                    viewmats: &s.viewmats,
                    ks: &s.ks,
                    backgrounds: Some(&bg),
                };
                let fwd = rasterization(&gin, &settings).unwrap();
                // [H, W, 3] → [3, H, W].
                let mut img = vec![0.0; 3 * hw];
                let mut vc = vec![0.0; 3 * hw];
                for p in 0..hw {
                    for ch in 0..3 {
                        img[ch * hw + p] = fwd.render_colors[3 * p + ch];
                        vc[3 * p + ch] = gcol[ch * hw + p];
                    }
                }
                let e = max_rel(&img, &io.color);
                assert!(
                    e < 1e-6,
                    "{version:?} packed={packed}: image differs by {e:e}"
                );
                let alpha_t: Vec<f64> = fwd.render_alphas.iter().map(|a| 1.0 - a).collect();
                assert!(max_rel(&alpha_t, &io.final_t) < 1e-6);
                let gg = rasterization_vjp(
                    &gin,
                    &settings,
                    &fwd,
                    &vc,
                    &vec![0.0; hw],
                    GradientMode::Exact,
                )
                .unwrap();
                for (name, a, b, tol) in [
                    ("means", &gg.v_means, &ig.means3d, 1e-6),
                    ("scales", &gg.v_scales, &ig.scales_or_cov, 1e-6),
                    ("opacities", &gg.v_opacities, &ig.opacities, 1e-6),
                    ("sh", &gg.v_colors, &ig.colors, 1e-6),
                ] {
                    let e = max_rel(a, b);
                    println!("{version:?} packed={packed} {name}: {e:e}");
                    assert!(e < tol, "{version:?} packed={packed} {name}: {e:e}");
                }
                // gsplat normalises q: its gradient is the tangential part of Inria's.
                let proj: Vec<f64> = ig
                    .rotations
                    .chunks(4)
                    .zip(s.quats.chunks(4))
                    .flat_map(|(v, n)| {
                        let d: f64 = v.iter().zip(n).map(|(a, b)| a * b).sum();
                        (0..4).map(move |k| v[k] - d * n[k]).collect::<Vec<_>>()
                    })
                    .collect();
                let e = max_rel(&gg.v_quats, &proj);
                assert!(e < 1e-6, "{version:?} quats: {e:e}");
            }
        }
    }
}

/// With `o·G < 0.99` everywhere and classic mode, the versions differ only in
/// the tile assignment, and both assignments are conservative: same image.
/// AccuTile assigns no more tiles than the radius box.
#[test]
fn versions_agree_below_the_alpha_clamp_and_accutile_is_tighter() {
    let spec = SceneSpec {
        opacity: (0.3, 0.98),
        scale: (0.05, 0.5),
        ..SceneSpec::new(20, 2, 61, 47)
    };
    for seed in 0..3 {
        let s = scene(&spec, 900 + seed);
        let v = Variant {
            sh_degree: Some(2),
            use_covars: false,
            backgrounds: true,
        };
        let a = run_composite::<f64>(
            &s,
            v,
            &RasterizationSettings::new(61, 47, Version::V1_5_3),
            None,
        );
        let b = run_composite::<f64>(
            &s,
            v,
            &RasterizationSettings::new(61, 47, Version::V1_6),
            None,
        );
        assert!(max_rel(&a.colors, &b.colors) == 0.0, "images differ");
        assert!(max_rel(&a.alphas, &b.alphas) == 0.0, "alphas differ");
    }
    // Tile counts of one thin diagonal Gaussian.
    let m2 = [30.0f64, 30.0];
    let conic = {
        // Σ = R diag(100, 1) Rᵀ at 45°: inverse.
        let (a, b, c) = (50.5, 49.5, 50.5);
        let det: f64 = a * c - b * b;
        [c / det, -b / det, a / det]
    };
    let radii = [
        (3.33f64 * 50.5f64.sqrt()).ceil() as i32,
        (3.33f64 * 50.5f64.sqrt()).ceil() as i32,
    ];
    let input = IsectInput {
        means2d: &m2,
        radii: &radii,
        depths: &[1.0],
        conics: Some(&conic),
        opacities: Some(&[0.9]),
        image_ids: None,
        n: 1,
    };
    let bx = isect_tiles(&input, 4, 16, 16, 1, Version::V1_6, TileRule::RadiusBox).unwrap();
    let ac = isect_tiles(&input, 4, 16, 16, 1, Version::V1_6, TileRule::AccuTile).unwrap();
    println!(
        "radius box {} tiles, AccuTile {} tiles",
        bx.isect_ids.len(),
        ac.isect_ids.len()
    );
    assert!(ac.isect_ids.len() < bx.isect_ids.len());
    assert!(ac.flatten_ids.iter().all(|&f| f == 0));
    // Offsets: per tile, the number of intersections in earlier tiles.
    let off = isect_offset_encode(&ac.isect_ids, 1, 16, 16, Version::V1_6).unwrap();
    assert_eq!(off.len(), 256);
    for (t, &o) in off.iter().enumerate() {
        let before = ac
            .isect_ids
            .iter()
            .filter(|&&k| ((k >> 32) as usize) < t)
            .count();
        assert_eq!(o as usize, before, "tile {t}");
    }
}

/// Key field widths: 1.5.3 `floor(log2(n)) + 1`, 1.6 the bit width of `n − 1`
/// (found by the cross-check against gsplat 1.6's torch `_isect_tiles`).
#[test]
fn key_bit_widths_per_version() {
    use liquid_splat::gsplat::isect::key_bits;
    for (n, old, new) in [
        (1, 1, 0),
        (2, 2, 1),
        (4, 3, 2),
        (6, 3, 3),
        (8, 4, 3),
        (9, 4, 4),
        (300, 9, 9),
    ] {
        assert_eq!(key_bits(Version::V1_5_3, n), old, "{n}");
        assert_eq!(key_bits(Version::V1_6, n), new, "{n}");
    }
}

/// One Gaussian straight in front of a 15×15 camera (`cx = 7.5`: its centre
/// is pixel (7, 7)'s sample point, σ = 0 there).
fn single(
    opacities: &[f64],
    depths: &[f64],
    colors: &[f64],
    version: Version,
) -> (Vec<f64>, Vec<f64>, Vec<i32>) {
    let n = opacities.len();
    let cam = Camera::look_at(
        [0.0, 0.0, -4.0],
        [0.0; 3],
        [0.0, -1.0, 0.0],
        0.8,
        0.8,
        15,
        15,
    )
    .unwrap();
    let (vm, k) = camera_tensors::<f64>(&cam);
    let means: Vec<f64> = depths.iter().flat_map(|&z| [0.0, 0.0, z]).collect();
    let quats: Vec<f64> = (0..n).flat_map(|_| [1.0, 0.0, 0.0, 0.0]).collect();
    let scales: Vec<f64> = (0..n).flat_map(|_| [0.2, 0.2, 0.2]).collect();
    let bg = [0.25];
    let input = RasterizationInput {
        means: &means,
        covars: Covars::QuatScale {
            quats: &quats,
            scales: &scales,
        },
        opacities,
        colors: GColors::Post {
            colors,
            channels: 1,
        },
        viewmats: &vm,
        ks: &k,
        backgrounds: Some(&bg),
    };
    let r = rasterization(&input, &RasterizationSettings::new(15, 15, version)).unwrap();
    let p = 7 * 15 + 7;
    (
        vec![r.render_colors[p]],
        vec![r.render_alphas[p]],
        r.projection.radii.clone(),
    )
}

#[test]
fn alpha_clamp_differs_between_versions() {
    // o = 0.995 at σ = 0: 1.5.3 keeps it (MAX_ALPHA 0.999), 1.6 clamps to 0.99.
    for (version, alpha) in [(Version::V1_5_3, 0.995), (Version::V1_6, 0.99)] {
        let (c, a, _) = single(&[0.995], &[0.0], &[0.8], version);
        let want = 0.8 * alpha + (1.0 - alpha) * 0.25;
        assert!(
            (c[0] - want).abs() < 1e-15,
            "{version:?}: {} vs {want}",
            c[0]
        );
        assert!((a[0] - alpha).abs() < 1e-15);
    }
}

#[test]
fn transmittance_stop_is_inclusive_and_excludes_the_stopping_gaussian() {
    // Front to back (depths ascending): α = 0.99, 0.99, 0.5 at pixel (7, 7) in 1.6.
    let (ops, depths, cols) = ([0.995, 0.995, 0.5], [-1.0, 0.0, 1.0], [0.9, 0.5, 0.1]);
    let (c, a, _) = single(&ops, &depths, &cols, Version::V1_6);
    let a1 = 0.99f64;
    let t1 = 1.0 - a1;
    let t2 = t1 * (1.0 - a1);
    assert!(t2 > 1e-4, "second Gaussian blends: T = {t2:e}");
    assert!(t2 * 0.5 <= 1e-4, "third stops the pixel");
    let want = 0.9 * a1 + 0.5 * a1 * t1 + 0.25 * t2;
    assert!((c[0] - want).abs() < 1e-15, "{} vs {want}", c[0]);
    assert!((a[0] - (1.0 - t2)).abs() < 1e-15);
}

#[test]
fn near_plane_and_image_edge_culling() {
    let cam = Camera::look_at(
        [0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        [0.0, -1.0, 0.0],
        0.8,
        0.8,
        32,
        32,
    )
    .unwrap();
    let (vm, k) = camera_tensors::<f64>(&cam);
    let fx = k[0];
    // z = 0.005 (behind the 0.01 near plane), z = 0.05 (kept by gsplat; the
    // Inria stage culls below 0.2), and two Gaussians beside the left edge.
    let s = 0.05f64;
    let z = 2.0;
    // Pixel-space standard deviation on x: fx·s/z (plus the 0.3 blur).
    let sig = ((fx * s / z).powi(2) + 0.3).sqrt();
    let r = (3.33 * sig).ceil();
    // Centre at x_pix = −r + 0.25 (box reaches the image) and −r − 0.25 (does not).
    let xw = |xp: f64| (xp - 16.0) * z / fx;
    let means = [
        0.0,
        0.0,
        0.005, //
        0.0,
        0.0,
        0.05, //
        xw(-r + 0.25),
        0.0,
        z, //
        xw(-r - 0.25),
        0.0,
        z,
    ];
    let quats = [1.0, 0.0, 0.0, 0.0].repeat(4);
    // Flat along z, so the x/z term of J adds nothing measurable to Σ2D00.
    let scales = [s, s, 1e-4].repeat(4);
    for version in Version::ALL {
        let p = fully_fused_projection(
            &ProjectionInput {
                means: &means,
                covars: Covars::QuatScale {
                    quats: &quats,
                    scales: &scales,
                },
                opacities: None,
                viewmats: &vm,
                ks: &k,
            },
            &ProjectionSettings::new(32, 32, version),
        )
        .unwrap();
        assert_eq!(&p.radii[0..2], &[0, 0], "behind the near plane");
        assert!(p.radii[2] > 0, "in front of the near plane");
        assert_eq!(p.radii[4], r as i32, "box reaching the image is kept");
        assert_eq!(&p.radii[6..8], &[0, 0], "box off the image is culled");
    }
}

#[test]
fn tiny_gaussians_in_antialiased_mode() {
    // A Gaussian far below a pixel: det_orig/det_blur ≈ 1e-11. 1.5.3's
    // compensation ≈ 3e-6 culls it (o·comp < 1/255); 1.6 floors the
    // compensation at 0.005, so with o = 0.9 it survives with o' = 0.0045.
    let cam = Camera::look_at(
        [0.0, 0.0, -4.0],
        [0.0; 3],
        [0.0, -1.0, 0.0],
        0.8,
        0.8,
        15,
        15,
    )
    .unwrap();
    let (vm, k) = camera_tensors::<f64>(&cam);
    let means = [0.0, 0.0, 0.0];
    let quats = [1.0, 0.0, 0.0, 0.0];
    let scales = [1e-5, 1e-5, 1e-5];
    let colors = [1.0];
    for (version, kept) in [(Version::V1_5_3, false), (Version::V1_6, true)] {
        let input = RasterizationInput {
            means: &means,
            covars: Covars::QuatScale {
                quats: &quats,
                scales: &scales,
            },
            opacities: &[0.9],
            colors: GColors::Post {
                colors: &colors,
                channels: 1,
            },
            viewmats: &vm,
            ks: &k,
            backgrounds: None,
        };
        let settings = RasterizationSettings {
            rasterize_mode: RasterizeMode::Antialiased,
            ..RasterizationSettings::new(15, 15, version)
        };
        let r = rasterization(&input, &settings).unwrap();
        assert_eq!(r.projection.radii[0] > 0, kept, "{version:?}");
        let comp = r.projection.compensations.as_ref().unwrap()[0];
        if kept {
            assert!((comp - 0.005).abs() < 1e-15, "{comp}");
            // At the centre pixel: α = 0.9·0.005.
            let p = 7 * 15 + 7;
            assert!(
                (r.render_colors[p] - 0.0045).abs() < 1e-12,
                "{}",
                r.render_colors[p]
            );
        }
    }
}

/// Exact and gsplat modes: in classic mode they differ only by rounding (the
/// transmittance rebuilt by division); in antialiased 1.6 with a floored
/// compensation, gsplat still sends a gradient through the floor.
#[test]
fn gradient_modes_differ_where_documented() {
    let spec = SceneSpec {
        channels: 3,
        ..SceneSpec::new(12, 2, 40, 30)
    };
    let s = scene(&spec, 77);
    let v = Variant::SH3;
    for version in Version::ALL {
        let settings = RasterizationSettings::new(40, 30, version);
        let base = run_composite::<f64>(&s, v, &settings, None);
        let vc = cotangent(1, base.colors.len());
        let va = cotangent(2, base.alphas.len());
        let e = run_composite::<f64>(&s, v, &settings, Some((&vc, &va, GradientMode::Exact)));
        let g = run_composite::<f64>(&s, v, &settings, Some((&vc, &va, GradientMode::Gsplat)));
        let (e, g) = (e.grads.unwrap(), g.grads.unwrap());
        for (name, a, b) in [
            ("means", &e.v_means, &g.v_means),
            ("quats", &e.v_quats, &g.v_quats),
            ("opacities", &e.v_opacities, &g.v_opacities),
            ("sh", &e.v_colors, &g.v_colors),
        ] {
            let r = max_rel(a, b);
            println!("{} classic {name}: exact vs gsplat {r:e}", version.name());
            assert!(r < 1e-10, "{name}: {r:e}");
        }
    }
}

/// Bit-identical forward and backward on 1 and 3 threads, f32, both modes.
#[test]
fn thread_count_does_not_change_a_bit() {
    let spec = SceneSpec {
        channels: 5,
        off_axis: true,
        ..SceneSpec::new(40, 2, 53, 41)
    };
    let s = scene(&spec, 4242);
    for version in Version::ALL {
        for (mode, v) in [
            (
                RasterizeMode::Classic,
                Variant {
                    sh_degree: None,
                    use_covars: false,
                    backgrounds: true,
                },
            ),
            (
                RasterizeMode::Antialiased,
                Variant {
                    sh_degree: Some(3),
                    use_covars: false,
                    backgrounds: false,
                },
            ),
        ] {
            for grad in GradientMode::ALL {
                let settings = RasterizationSettings {
                    rasterize_mode: mode,
                    ..RasterizationSettings::new(53, 41, version)
                };
                let run = |threads: usize| {
                    support::with_threads(threads, || {
                        let base = run_composite::<f32>(&s, v, &settings, None);
                        let vc: Vec<f32> = cotangent_in(9, base.colors.len());
                        let va: Vec<f32> = cotangent_in(8, base.alphas.len());
                        let r = run_composite::<f32>(&s, v, &settings, Some((&vc, &va, grad)));
                        let g = r.grads.unwrap();
                        let mut bits: Vec<u32> = r.colors.iter().map(|x| x.to_bits()).collect();
                        for t in [
                            &g.v_means,
                            &g.v_quats,
                            &g.v_scales,
                            &g.v_opacities,
                            &g.v_colors,
                            &g.v_means2d,
                        ] {
                            bits.extend(t.iter().map(|x| x.to_bits()));
                        }
                        bits
                    })
                };
                let one = run(1);
                assert_eq!(one, run(3), "{version:?} {mode:?} {grad:?}");
            }
        }
    }
}

/// The composite computes no subnormal number, forward or backward, in
/// either gradient mode, either version and either rasterize mode, on
/// a frame of many overlapping splats (each tile's list holds Gaussians
/// far from many of its pixels, where `exp(−σ)` is subnormal or 0 in f32).
/// Subnormal arithmetic gives the same bits but runs through slow microcode
/// assists (benches/README.md, "gsplat-convention rasterizer: subnormal
/// pairs"). One thread, so that all the work runs on the thread whose flags
/// are read.
#[cfg(target_arch = "x86_64")]
#[test]
fn no_subnormal_arithmetic() {
    let spec = SceneSpec {
        scale: (0.02, 0.3),
        ..SceneSpec::new(600, 1, 48, 40)
    };
    let s = scene(&spec, 77);
    let v = Variant::SH3;
    for version in Version::ALL {
        for mode in [RasterizeMode::Classic, RasterizeMode::Antialiased] {
            let settings = RasterizationSettings {
                rasterize_mode: mode,
                ..RasterizationSettings::new(spec.width, spec.height, version)
            };
            let base = run_composite::<f32>(&s, v, &settings, None);
            let vc: Vec<f32> = cotangent_in(9, base.colors.len());
            let va: Vec<f32> = cotangent_in(8, base.alphas.len());
            for grad in GradientMode::ALL {
                let flags = support::with_threads(1, || {
                    support::subnormal_flags(|| {
                        drop(run_composite::<f32>(
                            &s,
                            v,
                            &settings,
                            Some((&vc, &va, grad)),
                        ))
                    })
                });
                assert_eq!(flags, 0, "{version:?} {mode:?} {grad:?}: flags {flags:#b}");
            }
        }
    }
}
