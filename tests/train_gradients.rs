//! `Model::gradients`: the canonical means' gradient against central
//! differences of the whole loss (field, rasterizer, L1 + SSIM), for every
//! field: the additive MLP, the CfC field and the 6-DoF MLP.
//!
//! Upstream feeds the field `x.detach()`, so the derivative checked is the
//! one with the field's *input* frozen at the canonical means `x₀` and `x`
//! moving only where upstream's renderer uses it: `means3D = x + d_xyz` for
//! the additive fields, `means3D = from_homogenous(T·[x; 1])` with the
//! field's transform `T = [[R, p], [0, 1]]` for the 6-DoF MLP (written out
//! here from the transform, not through the field's `d_xyz`), whose
//! derivative is `Rᵀ·g` rather than `g`.

use approx::abs_diff_eq;
use liquid_splat::deform::{Activation, CfcConfig, Field, FieldConfig, MlpConfig, Variant};
use liquid_splat::gaussians::Gaussians;
use liquid_splat::loss::loss_and_grad;
use liquid_splat::loss::LAMBDA_DSSIM;
use liquid_splat::math::gradcheck::{compare, numeric_gradient};
use liquid_splat::math::Rng;
use liquid_splat::render::scene::{random_scene, SceneSpec};
use liquid_splat::render::{rasterize, Colors, Covariances, RasterInput};
use liquid_splat::train::deformed::deform_gaussians;
use liquid_splat::train::{Model, View};

const TIME: f64 = 0.37;

fn mlp(variant: Variant, six_dof: bool) -> FieldConfig {
    FieldConfig::Mlp(MlpConfig {
        variant,
        depth: 4,
        width: 16,
        is_6dof: six_dof,
    })
}

fn cfc(variant: Variant) -> FieldConfig {
    FieldConfig::Cfc(CfcConfig {
        variant,
        depth: 2,
        width: 8,
        backbone_units: 8,
        backbone_layers: 1,
        activation: Activation::Gelu,
    })
}

/// A model of a small random scene (raw parameters of its Gaussians) with
/// the field seeded by `seed`, and a view with a random ground truth.
fn setup(field: FieldConfig, seed: u64) -> (Model<f64>, View<f64>) {
    let mut spec = SceneSpec::small(12, seed);
    spec.width = 24;
    spec.height = 20;
    let scene = random_scene(&spec).unwrap();
    let gaussians = Gaussians {
        max_sh_degree: 3,
        xyz: scene.means3d.clone(),
        sh: scene.sh.clone(),
        scaling: scene.scales.iter().map(|&s| libm::log(s)).collect(),
        rotation: scene.rotations.clone(),
        opacity: scene
            .opacities
            .iter()
            .map(|&o| libm::log(o / (1.0 - o)))
            .collect(),
    };
    let model = Model {
        gaussians,
        field: Field::new(field, seed).unwrap(),
        active_sh_degree: 2,
        background: [0.2, 0.5, 0.9],
    };
    let (h, w) = (spec.height, spec.width);
    let mut rng = Rng::new(seed ^ 0x5eed);
    let view = View {
        name: "gt".into(),
        camera: scene.raster_camera.clone(),
        time: TIME,
        image: (0..3 * h * w).map(|_| rng.uniform()).collect(),
        width: w,
        height: h,
    };
    (model, view)
}

/// The loss with the field's outputs computed at the canonical means of
/// `model` and the means the renderer uses built from `xyz`.
fn loss_at(model: &Model<f64>, view: &View<f64>, xyz: &[f64]) -> f64 {
    let g = &model.gaussians;
    let n = g.len();
    let (offsets, cache) = model.field.forward(&g.xyz, &vec![TIME; n]).unwrap();
    let moved = Gaussians {
        xyz: xyz.to_vec(),
        ..g.clone()
    };
    let mut d = deform_gaussians(&moved, Some(&offsets));
    if let Some(m) = model.field.se3_transforms(&cache) {
        // Upstream's renderer: from_homogenous(bmm(T, to_homogenous(x))).
        for i in 0..n {
            let (t, x) = (&m[16 * i..16 * i + 16], &xyz[3 * i..3 * i + 3]);
            for r in 0..3 {
                d.means[3 * i + r] =
                    t[4 * r] * x[0] + t[4 * r + 1] * x[1] + t[4 * r + 2] * x[2] + t[4 * r + 3];
            }
        }
    }
    let input = RasterInput {
        means3d: &d.means,
        colors: Colors::Sh {
            coeffs: &g.sh,
            stride: g.coeffs(),
            degree: model.active_sh_degree,
        },
        opacities: &d.opacities,
        covariances: Covariances::ScaleRotation {
            scales: &d.scales,
            rotations: &d.rotations,
            scale_modifier: 1.0,
        },
        camera: &view.camera,
        background: model.background,
    };
    let (out, _) = rasterize(&input).unwrap();
    let lambda = LAMBDA_DSSIM;
    loss_and_grad(&out.color, &view.image, view.height, view.width, lambda)
        .unwrap()
        .0
        .loss
}

fn check_xyz(field: FieldConfig, seed: u64) {
    let (model, view) = setup(field, seed);
    let (grads, _) = model.gradients(&view, TIME, true, LAMBDA_DSSIM).unwrap();
    let x0 = model.gaussians.xyz.clone();
    // The reference forward is the model's forward (to rounding).
    let l0 = loss_at(&model, &view, &x0);
    let l = grads.loss.loss;
    assert!(
        abs_diff_eq!(l0, l, epsilon = 1e-14 * l.abs()),
        "{field:?}: {l0} vs {l}"
    );
    if field.is_6dof() {
        // The warp's rotations are far from the identity: the check tells
        // Rᵀ·g from g.
        let n = x0.len() / 3;
        let (_, cache) = model.field.forward(&x0, &vec![TIME; n]).unwrap();
        let m = model.field.se3_transforms(&cache).unwrap();
        let off = (0..n)
            .flat_map(|i| (0..3).flat_map(move |r| (0..3).map(move |c| (i, r, c))))
            .map(|(i, r, c)| (m[16 * i + 4 * r + c] - (r == c) as u8 as f64).abs())
            .fold(0.0f64, f64::max);
        assert!(off > 0.1, "{field:?}: R − I is only {off}");
    }
    let visible: Vec<usize> = grads
        .radii
        .iter()
        .enumerate()
        .filter(|(_, &r)| r > 0)
        .flat_map(|(i, _)| [3 * i, 3 * i + 1, 3 * i + 2])
        .collect();
    assert!(
        visible.len() >= 3 * 6,
        "{field:?}: too few visible Gaussians"
    );
    let floor = 1e-3
        * grads
            .model
            .gaussians
            .xyz
            .iter()
            .fold(0.0f64, |m, g| m.max(g.abs()));
    let (mut analytic, mut numeric) = (vec![], vec![]);
    for &k in &visible {
        let mut x = x0.clone();
        let mut probe = vec![x0[k]];
        let num = numeric_gradient(&mut probe, 1e-6, |v| {
            x[k] = v[0];
            loss_at(&model, &view, &x)
        });
        analytic.push(grads.model.gaussians.xyz[k]);
        numeric.push(num[0]);
    }
    let r = compare("xyz", &analytic, &numeric, floor);
    eprintln!("{field:?}\n{r}");
    assert!(r.passes(1e-5), "{field:?}\n{r}");
}

#[test]
fn canonical_means_gradient_additive_mlp() {
    check_xyz(mlp(Variant::Synthetic, false), 11);
    check_xyz(mlp(Variant::Real, false), 12);
}

#[test]
fn canonical_means_gradient_cfc() {
    check_xyz(cfc(Variant::Synthetic), 13);
    check_xyz(cfc(Variant::Real), 14);
}

#[test]
fn canonical_means_gradient_6dof_mlp() {
    check_xyz(mlp(Variant::Synthetic, true), 15);
    check_xyz(mlp(Variant::Real, true), 16);
}
