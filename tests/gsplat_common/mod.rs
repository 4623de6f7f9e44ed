//! Seeded scenes and a decision-aware central-difference checker shared by
//! the gsplat-convention tests.
#![allow(dead_code)]

use liquid_splat::camera::Camera;
use liquid_splat::gsplat::projection::Covars;
use liquid_splat::gsplat::raster::decisions;
use liquid_splat::gsplat::rendering::{
    raster_input, rasterization, rasterization_vjp, rows_of, Colors, RasterizationGrads,
    RasterizationInput, RasterizationSettings,
};
use liquid_splat::gsplat::{camera_tensors, GradientMode};
use liquid_splat::math::gradcheck::{compare, cotangent, GroupReport};
use liquid_splat::math::{Real, Rng};

/// Relative tolerance of every central-difference group.
pub const REL_TOL: f64 = 1e-6;
/// Step, relative to `max(1, |x|)`.
pub const STEP: f64 = 1e-6;

/// A scene in f64, converted to `T` when rendered.
#[derive(Clone, Debug)]
pub struct Scene {
    pub n: usize,
    pub c: usize,
    pub width: usize,
    pub height: usize,
    pub means: Vec<f64>,
    pub quats: Vec<f64>,
    pub scales: Vec<f64>,
    pub covars: Vec<f64>,
    pub opacities: Vec<f64>,
    /// `[N, D]` post-activation colours.
    pub colors: Vec<f64>,
    pub channels: usize,
    /// `[N, 16, 3]` SH coefficients.
    pub sh: Vec<f64>,
    pub backgrounds: Vec<f64>,
    pub viewmats: Vec<f64>,
    pub ks: Vec<f64>,
    pub cams: Vec<Camera>,
}

/// How a scene is drawn.
#[derive(Clone, Debug)]
pub struct SceneSpec {
    pub n: usize,
    pub c: usize,
    pub width: usize,
    pub height: usize,
    pub opacity: (f64, f64),
    pub scale: (f64, f64),
    /// Half-extent of the centres (world units, the cameras are 4 away).
    pub spread: f64,
    /// Add one large Gaussian beside the view whose tangent clamp is active.
    pub off_axis: bool,
    pub channels: usize,
}

impl SceneSpec {
    pub fn new(n: usize, c: usize, width: usize, height: usize) -> Self {
        SceneSpec {
            n,
            c,
            width,
            height,
            opacity: (0.2, 0.9),
            scale: (0.08, 0.35),
            spread: 0.8,
            off_axis: false,
            channels: 3,
        }
    }
}

/// [`cotangent`]`(seed, n)` in `T` (each value rounded once from f64).
pub fn cotangent_in<T: Real>(seed: u64, n: usize) -> Vec<T> {
    cotangent(seed, n).into_iter().map(T::from_f64).collect()
}

pub fn scene(spec: &SceneSpec, seed: u64) -> Scene {
    let mut rng = Rng::new(seed);
    let fov_x = 0.9;
    let fov_y = 2.0 * (libm::tan(fov_x / 2.0) * spec.height as f64 / spec.width as f64).atan();
    let mut cams = Vec::new();
    let mut viewmats = Vec::new();
    let mut ks = Vec::new();
    for ci in 0..spec.c {
        let eye = [
            0.4 * ci as f64 + rng.uniform_range(-0.2, 0.2),
            rng.uniform_range(-0.2, 0.2),
            -4.0,
        ];
        let cam = Camera::look_at(
            eye,
            [0.0; 3],
            [0.0, -1.0, 0.0],
            fov_x,
            fov_y,
            spec.width,
            spec.height,
        )
        .unwrap();
        let (v, k) = camera_tensors::<f64>(&cam);
        viewmats.extend(v);
        ks.extend(k);
        cams.push(cam);
    }
    let total = spec.n + spec.off_axis as usize;
    let mut s = Scene {
        n: total,
        c: spec.c,
        width: spec.width,
        height: spec.height,
        means: Vec::new(),
        quats: Vec::new(),
        scales: Vec::new(),
        covars: Vec::new(),
        opacities: Vec::new(),
        colors: Vec::new(),
        channels: spec.channels,
        sh: Vec::new(),
        backgrounds: Vec::new(),
        viewmats,
        ks,
        cams,
    };
    for i in 0..total {
        let off = spec.off_axis && i == spec.n;
        let sp = spec.spread;
        if off {
            s.means.extend([3.0, rng.uniform_range(-0.3, 0.3), 0.0]);
        } else {
            s.means.extend([
                rng.uniform_range(-sp, sp),
                rng.uniform_range(
                    -sp * spec.height as f64 / spec.width as f64,
                    sp * spec.height as f64 / spec.width as f64,
                ),
                rng.uniform_range(-0.8, 0.8),
            ]);
        }
        let q: Vec<f64> = (0..4).map(|_| rng.normal()).collect();
        s.quats.extend(&q);
        let (lo, hi) = if off { (0.8, 1.2) } else { spec.scale };
        let sc: Vec<f64> = (0..3)
            .map(|_| (rng.uniform_range(lo.ln(), hi.ln())).exp())
            .collect();
        s.scales.extend(&sc);
        let m = liquid_splat::gsplat::covar::covar([q[0], q[1], q[2], q[3]], [sc[0], sc[1], sc[2]]);
        s.covars
            .extend([m[0][0], m[0][1], m[0][2], m[1][1], m[1][2], m[2][2]]);
        s.opacities
            .push(rng.uniform_range(spec.opacity.0, spec.opacity.1));
        for _ in 0..spec.channels {
            s.colors.push(rng.uniform_range(0.0, 1.0));
        }
        for b in 0..16 {
            for _ in 0..3 {
                let sd = if b == 0 { 0.8 } else { 0.25 };
                s.sh.push(rng.normal() * sd);
            }
        }
    }
    for _ in 0..spec.c * spec.channels {
        s.backgrounds.push(rng.uniform_range(0.0, 1.0));
    }
    s
}

fn cv<T: Real>(v: &[f64]) -> Vec<T> {
    v.iter().map(|&x| T::from_f64(x)).collect()
}

/// Which inputs the composite reads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Variant {
    pub sh_degree: Option<usize>,
    pub use_covars: bool,
    pub backgrounds: bool,
}

impl Variant {
    /// SH colours of degree 3, scales and rotations, and backgrounds.
    pub const SH3: Variant = Variant {
        sh_degree: Some(3),
        use_covars: false,
        backgrounds: true,
    };
}

/// The composite on a scene: (loss against the base images, decisions).
pub struct Composite<T> {
    pub colors: Vec<T>,
    pub alphas: Vec<T>,
    pub signature: Vec<u64>,
    pub grads: Option<RasterizationGrads<T>>,
}

pub fn run_composite<T: Real>(
    s: &Scene,
    v: Variant,
    settings: &RasterizationSettings,
    backward: Option<(&[T], &[T], GradientMode)>,
) -> Composite<T> {
    let means = cv::<T>(&s.means);
    let quats = cv::<T>(&s.quats);
    let scales = cv::<T>(&s.scales);
    let covars = cv::<T>(&s.covars);
    let opac = cv::<T>(&s.opacities);
    let colors = cv::<T>(&s.colors);
    let sh = cv::<T>(&s.sh);
    let bg = cv::<T>(&s.backgrounds);
    let vm = cv::<T>(&s.viewmats);
    let ks = cv::<T>(&s.ks);
    let input = RasterizationInput {
        means: &means,
        covars: if v.use_covars {
            Covars::Triu(&covars)
        } else {
            Covars::QuatScale {
                quats: &quats,
                scales: &scales,
            }
        },
        opacities: &opac,
        colors: match v.sh_degree {
            Some(degree) => Colors::Sh {
                coeffs: &sh,
                k: 16,
                degree,
            },
            None => Colors::Post {
                colors: &colors,
                channels: s.channels,
            },
        },
        viewmats: &vm,
        ks: &ks,
        backgrounds: v.backgrounds.then_some(&bg[..]),
    };
    let fwd = rasterization(&input, settings).unwrap();
    let mut sig: Vec<u64> = Vec::new();
    sig.extend(fwd.projection.radii.iter().map(|&r| r as u64));
    sig.extend(fwd.projection.flags.iter().map(|&f| f as u64));
    sig.extend(fwd.isects.isect_ids.iter().map(|&k| (k >> 32) as u64));
    sig.extend(fwd.isects.flatten_ids.iter().map(|&f| f as u64));
    sig.extend(fwd.color_clamped.iter().map(|&c| c as u64));
    let rows = rows_of(&fwd);
    let rin = raster_input(&input, settings, &fwd, &rows);
    sig.extend(
        decisions(&rin, settings.version)
            .unwrap()
            .iter()
            .map(|&d| d as u64),
    );
    let grads = backward
        .map(|(vc, va, mode)| rasterization_vjp(&input, settings, &fwd, vc, va, mode).unwrap());
    Composite {
        colors: fwd.render_colors,
        alphas: fwd.render_alphas,
        signature: sig,
        grads,
    }
}

/// Which input group a check perturbs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Group {
    Means,
    Quats,
    Scales,
    Covars,
    Opacities,
    Colors,
    Sh,
    Backgrounds,
}

fn slot(s: &mut Scene, g: Group) -> &mut Vec<f64> {
    match g {
        Group::Means => &mut s.means,
        Group::Quats => &mut s.quats,
        Group::Scales => &mut s.scales,
        Group::Covars => &mut s.covars,
        Group::Opacities => &mut s.opacities,
        Group::Colors => &mut s.colors,
        Group::Sh => &mut s.sh,
        Group::Backgrounds => &mut s.backgrounds,
    }
}

pub fn analytic(g: &RasterizationGrads<f64>, group: Group) -> Vec<f64> {
    match group {
        Group::Means => g.v_means.clone(),
        Group::Quats => g.v_quats.clone(),
        Group::Scales => g.v_scales.clone(),
        Group::Covars => g.v_covars.clone(),
        Group::Opacities => g.v_opacities.clone(),
        Group::Colors | Group::Sh => g.v_colors.clone(),
        Group::Backgrounds => g.v_backgrounds.clone().unwrap_or_default(),
    }
}

/// Central differences of `L = <v_C, C − C₀> + <v_A, A − A₀>` w.r.t. each
/// group, in f64; `None` if any perturbation changes a decision.
pub fn check_composite(
    s: &Scene,
    v: Variant,
    settings: &RasterizationSettings,
    groups: &[Group],
    seed: u64,
) -> Option<Vec<GroupReport>> {
    let base = run_composite::<f64>(s, v, settings, None);
    let vc = cotangent(seed ^ 0x5151, base.colors.len());
    let va = cotangent(seed ^ 0x7373, base.alphas.len());
    let with_grad = run_composite::<f64>(s, v, settings, Some((&vc, &va, GradientMode::Exact)));
    let grads = with_grad.grads.unwrap();
    let loss = |c: &Composite<f64>| -> f64 {
        let mut l = 0.0;
        for (i, x) in c.colors.iter().enumerate() {
            l += vc[i] * (x - base.colors[i]);
        }
        for (i, x) in c.alphas.iter().enumerate() {
            l += va[i] * (x - base.alphas[i]);
        }
        l
    };
    let mut reports = Vec::new();
    for &g in groups {
        let mut scene = s.clone();
        let len = slot(&mut scene, g).len();
        let mut numeric = vec![0.0; len];
        #[allow(clippy::needless_range_loop)]
        for i in 0..len {
            let x0 = slot(&mut scene, g)[i];
            let step = STEP * x0.abs().max(1.0);
            slot(&mut scene, g)[i] = x0 + step;
            let p = run_composite::<f64>(&scene, v, settings, None);
            slot(&mut scene, g)[i] = x0 - step;
            let m = run_composite::<f64>(&scene, v, settings, None);
            slot(&mut scene, g)[i] = x0;
            if p.signature != base.signature || m.signature != base.signature {
                return None;
            }
            numeric[i] = (loss(&p) - loss(&m)) / ((x0 + step) - (x0 - step));
        }
        let a = analytic(&grads, g);
        let floor = 1e-3 * a.iter().fold(0.0f64, |m, x| m.max(x.abs())).max(1e-12);
        reports.push(compare(&format!("{g:?}"), &a, &numeric, floor));
    }
    Some(reports)
}
