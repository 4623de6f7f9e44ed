//! Central-difference gradient checks of the rasterizer in f64 (used by the
//! test suite and by `liquid-splat gradcheck raster`).
//!
//! The loss is `L = <v_C, C − C₀> + <v_D, D − D₀>` for seeded cotangents
//! `v_C`, `v_D` (subtracting the base image `C₀` keeps the rounding of the
//! sum small). The rasterizer has hard decisions (culling, radii, tile lists,
//! the 1/255 skip, the transmittance stop, the 0.99 and tangent clamps, the
//! SH colour clamp); a check is only meaningful where no perturbation flips
//! one. Every finite-difference evaluation therefore recomputes a signature
//! of all those decisions and the check reports the scene as unusable
//! (`None`) if any differs from the base; callers draw another scene.

use super::scene::{random_scene, ColorSource, CovSource, Scene, SceneSpec};
use super::{
    rasterize as render, rasterize_vjp, rasterize_with_ndc_offset, Colors, Covariances,
    GradientMode, RasterInput,
};
use crate::error::Result;
use crate::math::gradcheck::{
    compare, cotangent, numeric_gradient, numeric_gradient_richardson, GroupReport,
};
use crate::math::Real;

/// Relative tolerance every gradient group must meet.
pub const REL_TOL: f64 = 1e-6;
/// Central-difference step (relative to `max(1, |x|)`).
pub const STEP: f64 = 1e-6;

/// Every discrete decision of a forward pass, as one comparable vector.
pub fn decisions<T: Real>(input: &RasterInput<T>, ndc_offset: Option<&[T]>) -> Result<Vec<u64>> {
    let (out, state) = match ndc_offset {
        Some(o) => rasterize_with_ndc_offset(input, o)?,
        None => render(input)?,
    };
    let mut sig: Vec<u64> = Vec::new();
    sig.extend(out.radii.iter().map(|&r| r as u64));
    sig.extend(state.binning.list.iter().map(|&g| g as u64));
    sig.extend(out.n_contrib.iter().map(|&c| c as u64));
    for p in &state.proj {
        sig.push(p.clamped_x as u64 | (p.clamped_y as u64) << 1);
    }
    for c in &state.colors {
        sig.push(c.clamped[0] as u64 | (c.clamped[1] as u64) << 1 | (c.clamped[2] as u64) << 2);
    }
    let k = super::rasterize::Blend::new();
    let intr = &state.intr;
    let grid_x = intr.grid[0] as usize;
    for tile in 0..state.binning.ranges.len() {
        let [s, e] = state.binning.ranges[tile];
        let splats = &state.splats[s as usize..e as usize];
        let [x0, x1, y0, y1] = super::rasterize::tile_bounds(tile, grid_x, intr.width, intr.height);
        for py in y0..y1 {
            for px in x0..x1 {
                let mut t = T::ONE;
                for s in splats {
                    match super::rasterize::evaluate(s, T::from_usize(px), T::from_usize(py), &k) {
                        super::rasterize::Step::Skip => sig.push(0),
                        super::rasterize::Step::Hit(h) => {
                            let test_t = t * (T::ONE - h.alpha);
                            if test_t < k.t_min {
                                sig.push(3);
                                break;
                            }
                            sig.push(1 + h.clamped as u64);
                            t = test_t;
                        }
                    }
                }
            }
        }
    }
    Ok(sig)
}

/// Which scene variant a check uses.
#[derive(Clone, Debug)]
pub struct CheckCase {
    /// Case name in reports.
    pub name: String,
    /// The random scene drawn.
    pub spec: SceneSpec,
    /// Colour input variant.
    pub colors: ColorSource,
    /// Covariance input variant.
    pub cov: CovSource,
    /// Include a depth cotangent.
    pub depth: bool,
}

/// Result of one case: the scene seed actually used and one report per input group.
#[derive(Clone, Debug)]
pub struct CaseReport {
    /// Case name.
    pub name: String,
    /// Seed of the scene actually used.
    pub seed: u64,
    /// One report per input group.
    pub groups: Vec<GroupReport>,
    /// Which rasterizer features the scene exercised.
    pub features: Features,
}

/// What a checked scene exercises (so tests can require it).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Features {
    /// Visible Gaussians with an active tangent clamp.
    pub tangent_clamped: usize,
    /// Pixels stopped by the transmittance rule.
    pub stopped_pixels: usize,
    /// (pixel, Gaussian) pairs blended with alpha clamped at 0.99.
    pub alpha_clamped: usize,
    /// Colour channels cut by the SH lower clamp (visible Gaussians).
    pub color_clamped: usize,
    /// Visible Gaussians.
    pub visible: usize,
}

impl CaseReport {
    /// Whether every group passes [`REL_TOL`].
    pub fn passes(&self) -> bool {
        self.groups.iter().all(|g| g.passes(REL_TOL))
    }
}

/// Check every gradient of one scene. `Ok(None)` when a perturbation flips a
/// discrete decision (the scene is too close to a discontinuity).
pub fn check_scene(
    scene: &Scene<f64>,
    colors: ColorSource,
    cov: CovSource,
    depth: bool,
    seed: u64,
) -> Result<Option<(Vec<GroupReport>, Features)>> {
    let n = scene.len();
    let base = scene.input(colors, cov);
    let (out0, state) = render(&base)?;
    let sig0 = decisions(&base, None)?;
    // The per-pixel codes are the tail of the signature after the per-Gaussian parts.
    let head = out0.radii.len() * 3 + state.binning.list.len() + out0.n_contrib.len();
    let visible: Vec<bool> = out0.radii.iter().map(|&r| r > 0).collect();
    let features = Features {
        tangent_clamped: (0..n)
            .filter(|&i| visible[i] && (state.proj[i].clamped_x || state.proj[i].clamped_y))
            .count(),
        stopped_pixels: sig0[head..].iter().filter(|&&c| c == 3).count(),
        alpha_clamped: sig0[head..].iter().filter(|&&c| c == 2).count(),
        color_clamped: (0..n)
            .filter(|&i| visible[i])
            .map(|i| state.colors[i].clamped.iter().filter(|&&c| c).count())
            .sum(),
        visible: visible.iter().filter(|&&v| v).count(),
    };
    let vc = cotangent(seed ^ 0xC0, out0.color.len());
    let vd: Vec<f64> = if depth {
        cotangent(seed ^ 0xD0, out0.depth.len())
    } else {
        Vec::new()
    };
    let grads = rasterize_vjp(
        &base,
        &state,
        &vc,
        depth.then_some(vd.as_slice()),
        GradientMode::Exact,
    )?;
    let loss = |inp: &RasterInput<f64>, off: Option<&[f64]>, flipped: &mut bool| -> f64 {
        let res = match off {
            Some(o) => rasterize_with_ndc_offset(inp, o),
            None => render(inp),
        };
        let Ok((out, _)) = res else {
            *flipped = true;
            return f64::NAN;
        };
        match decisions(inp, off) {
            Ok(s) if s == sig0 => {}
            _ => *flipped = true,
        }
        let mut l = 0.0;
        for (i, v) in vc.iter().enumerate() {
            l += v * (out.color[i] - out0.color[i]);
        }
        for (i, v) in vd.iter().enumerate() {
            l += v * (out.depth[i] - out0.depth[i]);
        }
        l
    };
    let mut flipped = false;
    let mut reports = Vec::new();
    let mut report = |name: &str, analytic: &[f64], numeric: &[f64]| {
        let scale = analytic
            .iter()
            .chain(numeric)
            .fold(0.0f64, |m, v| m.max(v.abs()));
        reports.push(compare(name, analytic, numeric, (1e-3 * scale).max(1e-12)));
    };

    // means3D
    let mut x = scene.means3d.clone();
    let num = numeric_gradient(&mut x, STEP, |x| {
        let inp = RasterInput { means3d: x, ..base };
        loss(&inp, None, &mut flipped)
    });
    report("means3D", &grads.means3d, &num);

    // means2D (NDC offset)
    let mut x = vec![0.0; 2 * n];
    let num = numeric_gradient(&mut x, STEP, |x| loss(&base, Some(x), &mut flipped));
    let ana: Vec<f64> = grads.means2d.chunks(3).flat_map(|c| [c[0], c[1]]).collect();
    report("means2D", &ana, &num);

    // colours
    match base.colors {
        Colors::Sh {
            coeffs,
            stride,
            degree,
        } => {
            let mut x = coeffs.to_vec();
            let num = numeric_gradient(&mut x, STEP, |x| {
                let inp = RasterInput {
                    colors: Colors::Sh {
                        coeffs: x,
                        stride,
                        degree,
                    },
                    ..base
                };
                loss(&inp, None, &mut flipped)
            });
            report("shs", &grads.colors, &num);
        }
        Colors::Precomputed(c) => {
            let mut x = c.to_vec();
            let num = numeric_gradient(&mut x, STEP, |x| {
                let inp = RasterInput {
                    colors: Colors::Precomputed(x),
                    ..base
                };
                loss(&inp, None, &mut flipped)
            });
            report("colors_precomp", &grads.colors, &num);
        }
    }

    // opacities
    let mut x = scene.opacities.clone();
    let num = numeric_gradient(&mut x, STEP, |x| {
        let inp = RasterInput {
            opacities: x,
            ..base
        };
        loss(&inp, None, &mut flipped)
    });
    report("opacities", &grads.opacities, &num);

    // covariance inputs
    match base.covariances {
        Covariances::ScaleRotation {
            scales,
            rotations,
            scale_modifier,
        } => {
            let mut x = scales.to_vec();
            let num = numeric_gradient(&mut x, STEP, |x| {
                let inp = RasterInput {
                    covariances: Covariances::ScaleRotation {
                        scales: x,
                        rotations,
                        scale_modifier,
                    },
                    ..base
                };
                loss(&inp, None, &mut flipped)
            });
            report("scales", &grads.scales_or_cov, &num);
            let mut x = rotations.to_vec();
            let num = numeric_gradient(&mut x, STEP, |x| {
                let inp = RasterInput {
                    covariances: Covariances::ScaleRotation {
                        scales,
                        rotations: x,
                        scale_modifier,
                    },
                    ..base
                };
                loss(&inp, None, &mut flipped)
            });
            report("rotations", &grads.rotations, &num);
        }
        Covariances::Precomputed(c) => {
            let mut x = c.to_vec();
            // (Entries of order 1e-3 beside a step of 1e-6: the plain
            // quotient's truncation error reached 2e-6 relative on some
            // seeds.)
            let num = numeric_gradient_richardson(&mut x, STEP, |x| {
                let inp = RasterInput {
                    covariances: Covariances::Precomputed(x),
                    ..base
                };
                loss(&inp, None, &mut flipped)
            });
            report("cov3D_precomp", &grads.scales_or_cov, &num);
        }
    }
    Ok(if flipped {
        None
    } else {
        Some((reports, features))
    })
}

/// Run one case, redrawing the scene (seed + 1000·k) until no perturbation
/// flips a decision (at most 20 draws).
pub fn run_case(case: &CheckCase) -> Result<Option<CaseReport>> {
    for k in 0..20u64 {
        let mut spec = case.spec.clone();
        spec.seed = case.spec.seed.wrapping_add(1000 * k);
        let scene = random_scene(&spec)?;
        if let Some((groups, features)) =
            check_scene(&scene, case.colors, case.cov, case.depth, spec.seed)?
        {
            return Ok(Some(CaseReport {
                name: case.name.clone(),
                seed: spec.seed,
                groups,
                features,
            }));
        }
    }
    Ok(None)
}

/// The built-in cases: SH degree 3 with scale/rotation and depth; an
/// off-axis Gaussian under the tangent clamp; precomputed colours and
/// covariances; dense overlap with occlusion and transmittance stops.
pub fn builtin_cases(seed: u64) -> Vec<CheckCase> {
    let mut clamp = SceneSpec::small(5, seed.wrapping_add(1));
    clamp.off_axis = 2;
    let mut dense = SceneSpec::small(12, seed.wrapping_add(2));
    dense.opacity_range = (0.93, 1.0);
    dense.scale_range = (0.2, 0.4);
    dense.spread = 0.3;
    let mut low = SceneSpec::small(6, seed.wrapping_add(3));
    low.sh_degree = 1;
    vec![
        CheckCase {
            name: "sh3+scale/rot+depth".into(),
            spec: SceneSpec::small(8, seed),
            colors: ColorSource::Sh,
            cov: CovSource::ScaleRotation,
            depth: true,
        },
        CheckCase {
            name: "tangent clamp".into(),
            spec: clamp,
            colors: ColorSource::Sh,
            cov: CovSource::ScaleRotation,
            depth: true,
        },
        CheckCase {
            name: "precomputed".into(),
            spec: SceneSpec::small(6, seed.wrapping_add(4)),
            colors: ColorSource::Precomputed,
            cov: CovSource::Precomputed,
            depth: true,
        },
        CheckCase {
            name: "dense/occlusion".into(),
            spec: dense,
            colors: ColorSource::Precomputed,
            cov: CovSource::ScaleRotation,
            depth: false,
        },
        CheckCase {
            name: "sh1+precomputed cov".into(),
            spec: low,
            colors: ColorSource::Sh,
            cov: CovSource::Precomputed,
            depth: false,
        },
    ]
}
