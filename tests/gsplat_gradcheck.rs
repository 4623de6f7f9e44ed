//! f64 central differences of every gsplat-convention stage's `exact`
//! backward, on seeded scenes kept away from discontinuities (any
//! perturbation that changes a discrete decision rejects the scene and the
//! next seed is drawn).

mod gsplat_common;

use gsplat_common::*;
use liquid_splat::gsplat::covar::{quat_scale_to_covar_preci, quat_scale_to_covar_preci_vjp};
use liquid_splat::gsplat::projection::{
    flags, fully_fused_projection, fully_fused_projection_vjp, Covars, ProjectionCotangents,
    ProjectionInput, ProjectionSettings,
};
use liquid_splat::gsplat::rendering::{RasterizationSettings, RasterizeMode};
use liquid_splat::gsplat::sh::{spherical_harmonics, spherical_harmonics_vjp};
use liquid_splat::gsplat::{GradientMode, Version};
use liquid_splat::math::gradcheck::{compare, cotangent, numeric_gradient};

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

fn floor_of(a: &[f64]) -> f64 {
    1e-3 * a.iter().fold(0.0f64, |m, x| m.max(x.abs())).max(1e-12)
}

#[test]
fn quat_scale_to_covar_preci_matches_central_differences() {
    let s = scene(&SceneSpec::new(5, 1, 16, 16), 3);
    for triu in [false, true] {
        let out = quat_scale_to_covar_preci(&s.quats, &s.scales, true, true, triu).unwrap();
        let vc = cotangent(1, out.covars.len());
        let vp = cotangent(2, out.precis.len());
        let (gq, gs) =
            quat_scale_to_covar_preci_vjp(&s.quats, &s.scales, Some(&vc), Some(&vp), triu).unwrap();
        let loss = |q: &[f64], sc: &[f64]| {
            let o = quat_scale_to_covar_preci(q, sc, true, true, triu).unwrap();
            dot(&vc, &o.covars) + dot(&vp, &o.precis)
        };
        let mut q = s.quats.clone();
        let nq = numeric_gradient(&mut q, STEP, |q| loss(q, &s.scales));
        let mut sc = s.scales.clone();
        let ns = numeric_gradient(&mut sc, STEP, |sc| loss(&s.quats, sc));
        for r in [
            compare("quats", &gq, &nq, floor_of(&gq)),
            compare("scales", &gs, &ns, floor_of(&gs)),
        ] {
            println!("triu={triu} {r}");
            assert!(r.passes(REL_TOL), "{r}");
        }
    }
}

#[test]
fn spherical_harmonics_matches_central_differences() {
    let s = scene(&SceneSpec::new(6, 1, 16, 16), 5);
    // Directions of any length (normalised inside), 3 and 5 channels.
    let dirs: Vec<f64> = s.means.iter().map(|x| x * 3.0 + 0.5).collect();
    for degree in 0..=4 {
        for d in [3usize, 5] {
            let k = 25;
            let coeffs = cotangent(10 + d as u64, 6 * k * d);
            let v = cotangent(20 + degree as u64, 6 * d);
            let (vd, vk) = spherical_harmonics_vjp(degree, &dirs, &coeffs, k, d, None, &v).unwrap();
            let mut x = dirs.clone();
            let nd = numeric_gradient(&mut x, STEP, |x| {
                dot(
                    &v,
                    &spherical_harmonics(degree, x, &coeffs, k, d, None).unwrap(),
                )
            });
            let mut c = coeffs.clone();
            let nk = numeric_gradient(&mut c, STEP, |c| {
                dot(
                    &v,
                    &spherical_harmonics(degree, &dirs, c, k, d, None).unwrap(),
                )
            });
            for r in [
                compare("dirs", &vd, &nd, floor_of(&vd).max(1e-9)),
                compare("coeffs", &vk, &nk, floor_of(&vk)),
            ] {
                println!("degree {degree} D={d} {r}");
                assert!(r.passes(REL_TOL), "{r}");
            }
        }
    }
}

#[test]
fn fully_fused_projection_matches_central_differences() {
    let mut checked = 0;
    for version in Version::ALL {
        for (antialiased, covars) in [(false, false), (true, false), (true, true)] {
            let spec = SceneSpec {
                off_axis: true,
                ..SceneSpec::new(6, 2, 40, 30)
            };
            let mut done = false;
            for seed in 0..20 {
                let s = scene(&spec, seed);
                let settings = ProjectionSettings {
                    calc_compensations: antialiased,
                    ..ProjectionSettings::new(s.width, s.height, version)
                };
                let eval = |means: &[f64], a: &[f64], b: &[f64], cov: &[f64]| {
                    let input = ProjectionInput {
                        means,
                        covars: if covars {
                            Covars::Triu(cov)
                        } else {
                            Covars::QuatScale {
                                quats: a,
                                scales: b,
                            }
                        },
                        opacities: Some(&s.opacities),
                        viewmats: &s.viewmats,
                        ks: &s.ks,
                    };
                    fully_fused_projection(&input, &settings).unwrap()
                };
                let base = eval(&s.means, &s.quats, &s.scales, &s.covars);
                if !base.flags.iter().any(|f| f & flags::CLAMP_X != 0) {
                    continue;
                }
                let cn = s.c * s.n;
                let (vm, vd, vc, vcomp) = (
                    cotangent(seed + 1, 2 * cn),
                    cotangent(seed + 2, cn),
                    cotangent(seed + 3, 3 * cn),
                    cotangent(seed + 4, cn),
                );
                let sig = |p: &liquid_splat::gsplat::projection::Projection<f64>| {
                    (p.radii.clone(), p.flags.clone())
                };
                // Differences from the base keep the rounding of the sum small.
                let loss = |p: &liquid_splat::gsplat::projection::Projection<f64>| {
                    let mut l = 0.0;
                    for e in 0..cn {
                        if !p.visible(e) {
                            continue;
                        }
                        for q in 0..2 {
                            l += vm[2 * e + q] * (p.means2d[2 * e + q] - base.means2d[2 * e + q]);
                        }
                        l += vd[e] * (p.depths[e] - base.depths[e]);
                        for q in 0..3 {
                            l += vc[3 * e + q] * (p.conics[3 * e + q] - base.conics[3 * e + q]);
                        }
                        if let (Some(cv), Some(cb)) = (&p.compensations, &base.compensations) {
                            l += vcomp[e] * (cv[e] - cb[e]);
                        }
                    }
                    l
                };
                let input = ProjectionInput {
                    means: &s.means,
                    covars: if covars {
                        Covars::Triu(&s.covars)
                    } else {
                        Covars::QuatScale {
                            quats: &s.quats,
                            scales: &s.scales,
                        }
                    },
                    opacities: Some(&s.opacities),
                    viewmats: &s.viewmats,
                    ks: &s.ks,
                };
                let g = fully_fused_projection_vjp(
                    &input,
                    &settings,
                    &base,
                    &ProjectionCotangents {
                        v_means2d: &vm,
                        v_depths: &vd,
                        v_conics: &vc,
                        v_compensations: antialiased.then_some(&vcomp[..]),
                    },
                    GradientMode::Exact,
                )
                .unwrap();
                let mut stable = true;
                let mut fd = |which: usize, x0: &[f64]| {
                    let mut x = x0.to_vec();
                    numeric_gradient(&mut x, STEP, |x| {
                        let p = match which {
                            0 => eval(x, &s.quats, &s.scales, &s.covars),
                            1 => eval(&s.means, x, &s.scales, &s.covars),
                            2 => eval(&s.means, &s.quats, x, &s.covars),
                            _ => eval(&s.means, &s.quats, &s.scales, x),
                        };
                        if sig(&p) != sig(&base) {
                            stable = false;
                        }
                        loss(&p)
                    })
                };
                let mut reports = vec![compare(
                    "means",
                    &g.v_means,
                    &fd(0, &s.means),
                    floor_of(&g.v_means),
                )];
                if covars {
                    reports.push(compare(
                        "covars",
                        &g.v_covars,
                        &fd(3, &s.covars),
                        floor_of(&g.v_covars),
                    ));
                } else {
                    reports.push(compare(
                        "quats",
                        &g.v_quats,
                        &fd(1, &s.quats),
                        floor_of(&g.v_quats),
                    ));
                    reports.push(compare(
                        "scales",
                        &g.v_scales,
                        &fd(2, &s.scales),
                        floor_of(&g.v_scales),
                    ));
                }
                if !stable {
                    continue;
                }
                for r in &reports {
                    println!(
                        "{} aa={antialiased} covars={covars} seed {seed}: {r}",
                        version.name()
                    );
                    assert!(r.passes(REL_TOL), "{r}");
                }
                done = true;
                checked += 1;
                break;
            }
            assert!(done, "no stable scene for {version:?} aa={antialiased}");
        }
    }
    assert_eq!(checked, 6);
}

/// The composite, every input group, each variant and version; the scene
/// must show the features the variant is about.
#[test]
fn rasterization_matches_central_differences() {
    let cases: Vec<(&str, Variant, RasterizeMode, bool, SceneSpec)> = vec![
        (
            "post colours, 4 channels, backgrounds, dense",
            Variant {
                sh_degree: None,
                use_covars: false,
                backgrounds: true,
            },
            RasterizeMode::Classic,
            false,
            SceneSpec {
                channels: 4,
                off_axis: true,
                ..SceneSpec::new(7, 2, 40, 30)
            },
        ),
        (
            "SH degree 3, packed, occlusion",
            Variant::SH3,
            RasterizeMode::Classic,
            true,
            SceneSpec {
                opacity: (0.6, 0.999),
                scale: (0.15, 0.4),
                ..SceneSpec::new(10, 1, 36, 20)
            },
        ),
        (
            "antialiased, covars",
            Variant {
                sh_degree: Some(1),
                use_covars: true,
                backgrounds: false,
            },
            RasterizeMode::Antialiased,
            true,
            SceneSpec::new(7, 2, 40, 30),
        ),
        (
            "antialiased, quats",
            Variant {
                sh_degree: None,
                use_covars: false,
                backgrounds: true,
            },
            RasterizeMode::Antialiased,
            false,
            SceneSpec {
                scale: (0.01, 0.2),
                ..SceneSpec::new(7, 2, 40, 30)
            },
        ),
    ];
    let mut failures = Vec::new();
    for version in Version::ALL {
        for (name, v, mode, packed, spec) in &cases {
            let groups: Vec<Group> = [
                Some(Group::Means),
                (!v.use_covars).then_some(Group::Quats),
                (!v.use_covars).then_some(Group::Scales),
                v.use_covars.then_some(Group::Covars),
                Some(Group::Opacities),
                Some(if v.sh_degree.is_some() {
                    Group::Sh
                } else {
                    Group::Colors
                }),
                v.backgrounds.then_some(Group::Backgrounds),
            ]
            .into_iter()
            .flatten()
            .collect();
            let settings = RasterizationSettings {
                rasterize_mode: *mode,
                packed: *packed,
                ..RasterizationSettings::new(spec.width, spec.height, version)
            };
            let mut found = false;
            for seed in 0..30 {
                let s = scene(spec, 100 + seed);
                let Some(reports) = check_composite(&s, *v, &settings, &groups, seed) else {
                    continue;
                };
                found = true;
                for r in reports {
                    println!("[{} {name} seed {seed}] {r}", version.name());
                    if !r.passes(REL_TOL) {
                        failures.push(format!("{} {name}: {r}", version.name()));
                    }
                }
                break;
            }
            assert!(
                found,
                "{} {name}: no scene away from discontinuities",
                version.name()
            );
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
}
