//! The rasterizer gives the same bits on every instruction-set path (AVX-512,
//! AVX2, portable; those the CPU has) and every thread count: forward outputs
//! and backward gradients in both gradient modes, f32, on scenes with partial
//! tiles, stopped pixels, clamped alphas and imbalanced tiles (the parallel
//! tile and per-Gaussian stages see different splits on each thread count),
//! SH degrees 1 to 3, clamped centres, culled Gaussians (whose gradients
//! must be +0) and no depth gradient.

mod support;

use liquid_splat::kernels::fastmath::{force_isa, Isa};
use liquid_splat::render::scene::{random_scene, ColorSource, CovSource, SceneSpec};
use liquid_splat::render::{rasterize, rasterize_vjp, GradientMode};

/// Every output and gradient of one scene, as bits.
fn run_bits(spec: &SceneSpec, colors: ColorSource, cov: CovSource) -> Vec<u32> {
    let s = random_scene(spec).unwrap().cast::<f32>();
    let input = s.input(colors, cov);
    let (out, state) = rasterize(&input).unwrap();
    let gc: Vec<f32> = liquid_splat::math::gradcheck::cotangent(3, out.color.len())
        .into_iter()
        .map(|v| v as f32)
        .collect();
    let gd: Vec<f32> = liquid_splat::math::gradcheck::cotangent(4, out.depth.len())
        .into_iter()
        .map(|v| v as f32)
        .collect();
    let mut bits: Vec<u32> = Vec::new();
    let mut push = |v: &[f32]| bits.extend(v.iter().map(|x| x.to_bits()));
    push(&out.color);
    push(&out.depth);
    push(&out.final_t);
    bits.extend(&out.n_contrib);
    bits.push(state.pairs_evaluated() as u32);
    let runs = GradientMode::ALL
        .into_iter()
        .map(|mode| (mode, Some(&gd[..])))
        .chain([(GradientMode::Exact, None)]);
    for (mode, depth) in runs {
        let g = rasterize_vjp(&input, &state, &gc, depth, mode).unwrap();
        let n = out.radii.len();
        for v in [
            &g.means3d,
            &g.means2d,
            &g.colors,
            &g.opacities,
            &g.scales_or_cov,
            &g.rotations,
        ] {
            bits.extend(v.iter().map(|x| x.to_bits()));
            // A culled Gaussian's gradients are +0 (not −0), value by value.
            let w = v.len() / n;
            for (i, &r) in out.radii.iter().enumerate() {
                if r == 0 {
                    assert!(v[w * i..w * (i + 1)].iter().all(|x| x.to_bits() == 0));
                }
            }
        }
    }
    bits
}

fn cases() -> Vec<(SceneSpec, ColorSource, CovSource)> {
    // 70×45: partial tiles on the right and at the bottom. The dense scene
    // stops pixels by transmittance; high opacities clamp alphas at 0.99.
    let mut dense = SceneSpec::bench(70, 45, 3000, 11);
    dense.opacity_range = (0.5, 0.999);
    dense.scale_range = (0.01, 0.08);
    // Imbalanced tiles: Gaussians crowded in the middle of the frame, some
    // large enough to span many tiles and tile rows.
    let mut crowded = SceneSpec::bench(200, 170, 1500, 5);
    crowded.spread = 0.25;
    crowded.scale_range = (0.005, 0.25);
    let mut tall = SceneSpec::bench(96, 300, 1200, 9);
    tall.spread = 0.4;
    tall.scale_range = (0.005, 0.3);
    // Lower SH degrees (colour rows of 3·4 and 3·9 values, not whole
    // vector blocks), centres whose tangent clamp is active, and Gaussians
    // outside the view (culled) scattered through every block.
    let mut degree1 = SceneSpec::bench(83, 61, 900, 13);
    degree1.sh_degree = 1;
    degree1.off_axis = 40;
    degree1.spread = 1.8;
    degree1.scale_range = (0.01, 0.1);
    let mut degree2 = degree1.clone();
    degree2.sh_degree = 2;
    degree2.seed = 17;
    vec![
        (degree1, ColorSource::Sh, CovSource::ScaleRotation),
        (degree2, ColorSource::Sh, CovSource::Precomputed),
        (crowded, ColorSource::Sh, CovSource::ScaleRotation),
        (tall, ColorSource::Precomputed, CovSource::ScaleRotation),
        (
            SceneSpec::bench(70, 45, 400, 3),
            ColorSource::Sh,
            CovSource::ScaleRotation,
        ),
        (dense, ColorSource::Precomputed, CovSource::Precomputed),
    ]
}

/// The instruction-set paths this CPU has (the portable one always).
fn paths() -> Vec<Isa> {
    let mut paths = vec![Isa::Baseline];
    for isa in [Isa::Avx2, Isa::Avx512] {
        if force_isa(Some(isa)) {
            paths.push(isa);
        }
    }
    paths
}

#[test]
fn every_instruction_set_and_thread_count_gives_the_same_bits() {
    let _isa = liquid_splat::kernels::fastmath::isa_test_lock();
    let paths = paths();
    for (spec, colors, cov) in cases() {
        let mut want: Option<Vec<u32>> = None;
        for &isa in &paths {
            assert!(force_isa(Some(isa)));
            for threads in [1, 2, 3] {
                let got = support::with_threads(threads, || run_bits(&spec, colors, cov));
                match &want {
                    None => want = Some(got),
                    Some(w) => assert!(
                        *w == got,
                        "{isa:?} with {threads} threads differs ({} of {} words)",
                        w.iter().zip(&got).filter(|(a, b)| a != b).count(),
                        w.len()
                    ),
                }
            }
        }
    }
    force_isa(None);
    eprintln!("paths compared: {paths:?}");
}

/// No subnormal number is computed or read by the forward or by the
/// backward in either gradient mode, on any instruction-set path, for the
/// scenes above and the 64×64 bench frame (whose many overlapping splats
/// put lanes far from a splat's centre, where `exp` underflows, next to
/// lanes that blend). Subnormal arithmetic gives the same bits but runs
/// through slow microcode assists: before the row walks took the `exp` of
/// `power_min` in lanes below it, this frame's forward and backward raised
/// both flags and ran 1.6–1.8 times slower on one thread (AMD Zen 5) and
/// 5–6.6 times slower (Intel Xeon). One thread, so that all the work runs
/// on the thread whose flags are read. (The compiler does not promise to
/// keep floating-point operations between the flag reads; here they are in
/// calls it cannot move across them.)
///
/// The portable path is checked only in builds whose baseline lacks AVX2
/// (the default x86-64 build): where the build's baseline already has it
/// (`-C target-cpu=native`), the dispatch never picks the portable path.
/// In such a build on an AMD Zen 4, the portable forward raised both flags
/// on the degree-1 scene, while a temporary check of every value the row
/// walk computes (powers and their parts, `exp`, alphas, transmittances,
/// colour and depth terms, the splats' fields) found none subnormal; so, as
/// far as that check can tell, the flags come from operations the compiler
/// added in vectorising that path, not from the program's values. The AVX2
/// and AVX-512 paths raised none there, and the test above compares the
/// bits of every path in every build.
#[cfg(target_arch = "x86_64")]
#[test]
fn no_subnormal_arithmetic_on_any_path() {
    let _isa = liquid_splat::kernels::fastmath::isa_test_lock();
    let paths = paths();
    let mut scenes = cases();
    scenes.push((
        SceneSpec::bench(64, 64, 2600, 1),
        ColorSource::Sh,
        CovSource::ScaleRotation,
    ));
    for (spec, colors, cov) in scenes {
        for &isa in &paths {
            // (See above.)
            if isa == Isa::Baseline && cfg!(target_feature = "avx2") {
                continue;
            }
            assert!(force_isa(Some(isa)));
            let flags = support::with_threads(1, || {
                support::subnormal_flags(|| drop(run_bits(&spec, colors, cov)))
            });
            assert_eq!(
                flags, 0,
                "{isa:?}: subnormal flags {flags:#b} on the {}x{} scene with seed {}",
                spec.width, spec.height, spec.seed
            );
        }
    }
    force_isa(None);
}
