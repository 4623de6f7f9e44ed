//! Seeded random, well-formed case files for every stage ([`new_case`]), and
//! the golden fixtures built from them ([`golden_files`]).
//!
//! A generated case holds the stage's inputs only (tensors and metadata);
//! [`super::run_case`] computes the outputs. The same spec and seed always
//! give the same bytes. Values are drawn in f64 from [`Rng`] streams and
//! rounded once to the requested precision (the rasterizer's camera matrices
//! are formed in that precision, as upstream forms them in f32).

use super::gsplat::{self as gs, GsplatOptions};
use super::{deform, loss, rasterize, run_case, step, STAGES};
use crate::deform::{CfcConfig, Field, FieldConfig, FieldKind, MlpConfig, Variant};
use crate::error::{Error, Result};
use crate::gaussians::{Gaussians, Group};
use crate::io::{Tensor, TensorFile};
use crate::math::{Precision, Real, Rng};
use crate::render::scene::{random_scene, SceneSpec, SCENE_SH_STRIDE};
use crate::render::GradientMode;
use crate::train::state;

/// What to generate. Fields a stage does not use are ignored by it; see
/// [`CaseSpec::new`] for the defaults.
#[derive(Clone, Debug, PartialEq)]
pub struct CaseSpec {
    /// Any of [`super::STAGES`]: `rasterize`, `deform`, `loss`, `step` or a
    /// `gsplat_*` stage.
    pub stage: String,
    /// Precision of every floating-point tensor (F32 or F64).
    pub precision: Precision,
    /// Seed of the random streams the inputs are drawn from.
    pub seed: u64,
    /// Image width in pixels (rasterize, loss, step, gsplat).
    pub width: usize,
    /// Image height in pixels (rasterize, loss, step, gsplat).
    pub height: usize,
    /// Gaussians (rasterize: in view, plus one beside it whose tangent clamp
    /// is active; deform: points; step: Gaussians).
    pub count: usize,
    /// Rasterize: metadata `gradient`.
    pub gradient: GradientMode,
    /// Deform, step: field kind.
    pub field: FieldKind,
    /// Deform, step: depth D (MLP trunk layers or CfC cells); `None` = small default.
    pub depth: Option<usize>,
    /// Deform, step: width W (MLP trunk or CfC hidden size); `None` = small default.
    pub hidden: Option<usize>,
    /// Deform, step: the field's time input; `None` = `synthetic` for
    /// deform, `real` for step.
    pub variant: Option<Variant>,
    /// Deform, step: the MLP's 6-DoF (SE(3)) variant.
    pub is_6dof: bool,
    /// gsplat stages: version, gradient mode, antialiased, packed.
    pub gsplat: GsplatOptions,
}

/// Defaults for generated deform cases, small so files stay small: the MLP
/// has depth 4 and width 32, the CfC field 2 cells of width 16 with a
/// 16-unit backbone (the timenet is always 1→256→30).
pub const SMALL_MLP: (usize, usize) = (4, 32);
/// See [`SMALL_MLP`].
pub const SMALL_CFC: (usize, usize) = (2, 16);

impl CaseSpec {
    /// Defaults: f64, seed 0, 32×24 pixels, 8 Gaussians, gradient `exact`,
    /// field `mlp` (additive), small field size, `synthetic` variant; for
    /// `step`: 16×16 pixels, 16 Gaussians, field `cfc`, `real` variant.
    pub fn new(stage: &str) -> Self {
        if stage == step::STAGE {
            return CaseSpec {
                width: 16,
                height: 16,
                count: 16,
                field: FieldKind::Cfc,
                ..CaseSpec::new(deform::STAGE)
            }
            .with_stage(stage);
        }
        CaseSpec {
            stage: stage.to_string(),
            precision: Precision::F64,
            seed: 0,
            width: 32,
            height: 24,
            count: 8,
            gradient: GradientMode::Exact,
            field: FieldKind::Mlp,
            depth: None,
            hidden: None,
            variant: None,
            is_6dof: false,
            gsplat: GsplatOptions::default(),
        }
    }
}

impl CaseSpec {
    fn with_stage(mut self, stage: &str) -> Self {
        self.stage = stage.to_string();
        self
    }
}

/// A seeded random case for `spec.stage`.
pub fn new_case(spec: &CaseSpec) -> Result<TensorFile> {
    match spec.precision {
        Precision::F32 => new_typed::<f32>(spec),
        Precision::F64 => new_typed::<f64>(spec),
    }
}

/// The most pixels a generated case's image has (2^22).
pub const MAX_CASE_PIXELS: usize = 1 << 22;

/// The most Gaussians or points a generated case has (2^20).
pub const MAX_CASE_COUNT: usize = 1 << 20;

fn new_typed<T: Real>(spec: &CaseSpec) -> Result<TensorFile> {
    if spec.width == 0
        || spec.height == 0
        || spec.width.saturating_mul(spec.height) > MAX_CASE_PIXELS
    {
        return Err(Error::invalid(
            "image size",
            format!(
                "{}x{} (each side at least 1, at most {MAX_CASE_PIXELS} pixels)",
                spec.width, spec.height
            ),
        ));
    }
    if spec.count > MAX_CASE_COUNT {
        return Err(Error::invalid(
            "count",
            format!("{} (at most {MAX_CASE_COUNT})", spec.count),
        ));
    }
    let mut f = match spec.stage.as_str() {
        s if s == rasterize::STAGE => new_rasterize::<T>(spec)?,
        s if s == deform::STAGE => new_deform::<T>(spec)?,
        s if s == loss::STAGE => new_loss::<T>(spec)?,
        s if s == step::STAGE => new_step::<T>(spec)?,
        s if gs::STAGES.contains(&s) => gs::new_case::<T>(
            s,
            spec.seed,
            spec.width,
            spec.height,
            spec.count,
            &spec.gsplat,
        )?,
        other => {
            return Err(Error::invalid(
                "stage",
                format!("`{other}` (known: {})", STAGES.join(", ")),
            ))
        }
    };
    f.set_meta("stage", &spec.stage);
    f.set_meta("seed", spec.seed);
    Ok(f)
}

/// Stream indices, so each tensor's draws are independent of the others' sizes.
const STREAM_GRAD: u64 = 1 << 40;
const STREAM_INPUT: u64 = 2 << 40;

fn normals(seed: u64, stream: u64, n: usize, sd: f64) -> Vec<f64> {
    let mut r = Rng::stream(seed, stream);
    (0..n).map(|_| sd * r.normal()).collect()
}

fn uniforms(seed: u64, stream: u64, n: usize, lo: f64, hi: f64) -> Vec<f64> {
    let mut r = Rng::stream(seed, stream);
    (0..n).map(|_| r.uniform_range(lo, hi)).collect()
}

fn to_t<T: Real>(v: &[f64]) -> Vec<T> {
    v.iter().map(|&x| T::from_f64(x)).collect()
}

/// Shortest decimal that parses back to the same f64.
fn exact_decimal(v: f64) -> String {
    format!("{v:?}")
}

fn new_rasterize<T: Real>(spec: &CaseSpec) -> Result<TensorFile> {
    let mut ss = SceneSpec::small(spec.count, spec.seed);
    ss.width = spec.width;
    ss.height = spec.height;
    ss.off_axis = 1;
    let scene = random_scene(&ss)?.cast::<T>();
    let n = scene.len();
    let rc = &scene.raster_camera;
    let (h, w) = (spec.height, spec.width);
    let mut f = TensorFile::new(format!("{}.safetensors", spec.stage));
    f.set_meta("image_height", h);
    f.set_meta("image_width", w);
    f.set_meta("tanfovx", exact_decimal(rc.tanfovx.to_f64()));
    f.set_meta("tanfovy", exact_decimal(rc.tanfovy.to_f64()));
    f.set_meta(
        "scale_modifier",
        exact_decimal(scene.scale_modifier.to_f64()),
    );
    f.set_meta("sh_degree", scene.sh_degree);
    f.set_meta("gradient", spec.gradient.name());
    f.insert_real("means3D", vec![n, 3], &scene.means3d);
    f.insert_real("shs", vec![n, SCENE_SH_STRIDE, 3], &scene.sh);
    f.insert_real("opacities", vec![n, 1], &scene.opacities);
    f.insert_real("scales", vec![n, 3], &scene.scales);
    f.insert_real("rotations", vec![n, 4], &scene.rotations);
    f.insert_real("viewmatrix", vec![4, 4], &rc.viewmatrix);
    f.insert_real("projmatrix", vec![4, 4], &rc.projmatrix);
    f.insert_real("campos", vec![3], &rc.campos);
    f.insert_real("bg", vec![3], &scene.background);
    let gc = normals(spec.seed, STREAM_GRAD, 3 * h * w, 1.0);
    let gd = normals(spec.seed, STREAM_GRAD + 1, h * w, 0.1);
    f.insert_real("grad_out_color", vec![3, h, w], &to_t::<T>(&gc));
    f.insert_real("grad_out_depth", vec![1, h, w], &to_t::<T>(&gd));
    Ok(f)
}

/// The small field of generated cases ([`SMALL_MLP`], [`SMALL_CFC`]).
fn small_field(spec: &CaseSpec) -> Result<FieldConfig> {
    let mut config = match spec.field {
        FieldKind::Mlp => FieldConfig::Mlp(MlpConfig {
            depth: spec.depth.unwrap_or(SMALL_MLP.0),
            width: spec.hidden.unwrap_or(SMALL_MLP.1),
            is_6dof: spec.is_6dof,
            ..MlpConfig::paper()
        }),
        FieldKind::Cfc if spec.is_6dof => {
            return Err(Error::invalid(
                "is_6dof",
                "only the MLP field has a 6-DoF variant",
            ))
        }
        FieldKind::Cfc => FieldConfig::Cfc(CfcConfig {
            depth: spec.depth.unwrap_or(SMALL_CFC.0),
            width: spec.hidden.unwrap_or(SMALL_CFC.1),
            backbone_units: 16,
            ..CfcConfig::paper()
        }),
    };
    if let Some(v) = spec.variant {
        config.set_variant(v);
    }
    Ok(config)
}

/// A case file holding freshly initialised weights of `config` (rounded to
/// `T`) and the configuration as metadata.
fn field_case<T: Real>(spec: &CaseSpec, config: FieldConfig) -> Result<TensorFile> {
    let field = Field::<f64>::new(config, spec.seed)?;
    let weights = crate::oracle::field::field_to_tensor_file(&field);
    let mut f = TensorFile::new(format!("{}.safetensors", spec.stage));
    f.metadata = weights.metadata.clone();
    for (name, t) in &weights.tensors {
        f.insert(name, Tensor::from_real(&t.to_f64().mapv(T::from_f64)));
    }
    Ok(f)
}

fn new_deform<T: Real>(spec: &CaseSpec) -> Result<TensorFile> {
    let mut f = field_case::<T>(spec, small_field(spec)?)?;
    let n = spec.count;
    let xyz = uniforms(spec.seed, STREAM_INPUT, 3 * n, -1.5, 1.5);
    let t = uniforms(spec.seed, STREAM_INPUT + 1, n, 0.0, 1.0);
    f.insert_real("xyz", vec![n, 3], &to_t::<T>(&xyz));
    f.insert_real("t", vec![n, 1], &to_t::<T>(&t));
    for (k, (name, width)) in [
        ("grad_d_xyz", 3),
        ("grad_d_rotation", 4),
        ("grad_d_scaling", 3),
    ]
    .into_iter()
    .enumerate()
    {
        let g = normals(spec.seed, STREAM_GRAD + k as u64, width * n, 1.0);
        f.insert_real(name, vec![n, width], &to_t::<T>(&g));
    }
    Ok(f)
}

fn new_loss<T: Real>(spec: &CaseSpec) -> Result<TensorFile> {
    let (h, w) = (spec.height, spec.width);
    let gt = uniforms(spec.seed, STREAM_INPUT, 3 * h * w, 0.0, 1.0);
    let noise = normals(spec.seed, STREAM_INPUT + 1, 3 * h * w, 0.1);
    // A render near the ground truth, not clamped (the loss does not clamp).
    let image: Vec<f64> = gt.iter().zip(&noise).map(|(g, e)| g + e).collect();
    let mut f = TensorFile::new(format!("{}.safetensors", spec.stage));
    f.set_meta("lambda_dssim", exact_decimal(crate::loss::LAMBDA_DSSIM));
    f.insert_real("image", vec![3, h, w], &to_t::<T>(&image));
    f.insert_real("gt", vec![3, h, w], &to_t::<T>(&gt));
    Ok(f)
}

/// The active SH degree of generated step cases (coefficients above it get
/// no gradient but still move under Adam's momentum).
pub const STEP_ACTIVE_SH_DEGREE: usize = 2;

/// Adam step counter of the optimizer state in generated step cases.
pub const STEP_ADAM_STEP: u64 = 7;

fn new_step<T: Real>(spec: &CaseSpec) -> Result<TensorFile> {
    // (The stage refuses a model of no Gaussians, as training does.)
    if spec.count == 0 {
        return Err(Error::invalid(
            "count",
            "0 (the step stage needs at least 1 Gaussian)",
        ));
    }
    // The field: small, by default the `real` variant (time feature γ₁₀(t),
    // no timenet) so the files stay small; the deform cases cover the timenet.
    let mut config = small_field(spec)?;
    config.set_variant(spec.variant.unwrap_or(Variant::Real));
    let mut f = field_case::<T>(spec, config)?;
    let field_params = Field::<f64>::new(config, spec.seed)?.param_count();

    let mut ss = SceneSpec::small(spec.count, spec.seed);
    ss.width = spec.width;
    ss.height = spec.height;
    let scene = random_scene(&ss)?;
    let n = scene.len();
    let (h, w) = (spec.height, spec.width);
    rasterize::write_camera(&mut f, &scene.camera.raster::<T>());
    f.set_meta("active_sh_degree", STEP_ACTIVE_SH_DEGREE);
    f.set_meta("field_on", true);
    let time = uniforms(spec.seed, STREAM_INPUT, 1, 0.0, 1.0)[0];
    f.set_meta("time", exact_decimal(T::from_f64(time).to_f64()));
    f.set_meta("lambda_dssim", exact_decimal(crate::loss::LAMBDA_DSSIM));
    for (name, lr) in step::default_learning_rates() {
        f.set_meta(&format!("lr.{name}"), exact_decimal(lr));
    }

    // Raw (unactivated) parameters of the scene's Gaussians.
    let scaling: Vec<f64> = scene.scales.iter().map(|&s| libm::log(s)).collect();
    let opacity: Vec<f64> = scene
        .opacities
        .iter()
        .map(|&o| libm::log(o / (1.0 - o)))
        .collect();
    let gaussians = Gaussians {
        // SCENE_SH_STRIDE (16) coefficients.
        max_sh_degree: 3,
        xyz: to_t::<T>(&scene.means3d),
        sh: to_t::<T>(&scene.sh),
        opacity: to_t::<T>(&opacity),
        scaling: to_t::<T>(&scaling),
        rotation: to_t::<T>(&scene.rotations),
    };
    state::write_gaussians(&mut f, "", &gaussians);
    f.insert_real("bg", vec![3], &to_t::<T>(&scene.background));
    let gt = uniforms(spec.seed, STREAM_INPUT + 1, 3 * h * w, 0.0, 1.0);
    f.insert_real("gt", vec![3, h, w], &to_t::<T>(&gt));

    // Optimizer state as after a few steps: moments of gradient-like size.
    let shapes = Group::ALL.map(|g| gaussians.shape(g));
    let groups = state::adam_groups()
        .into_iter()
        .zip(shapes.into_iter().chain([vec![field_params]]));
    for (k, (group, shape)) in groups.enumerate() {
        let len = shape.iter().product();
        let stream = STREAM_INPUT + 16 + 2 * k as u64;
        let m = normals(spec.seed, stream, len, 1e-3);
        let spread = uniforms(spec.seed, stream + 1, len, 0.0, 1e-6);
        let v: Vec<f64> = m.iter().zip(&spread).map(|(m, s)| m * m + s).collect();
        f.insert_real(&format!("adam.{group}.m"), shape.clone(), &to_t::<T>(&m));
        f.insert_real(&format!("adam.{group}.v"), shape, &to_t::<T>(&v));
        f.set_meta(&format!("adam.{group}.step"), STEP_ADAM_STEP);
    }

    // Statistics as after a few views.
    let mut r = Rng::stream(spec.seed, STREAM_INPUT + 2);
    let (mut accum, mut denom, mut radii) = (vec![], vec![], vec![]);
    for _ in 0..n {
        let d = (r.uniform() * 6.0) as i32;
        let a = d as f64 * r.uniform_range(0.0, 2e-3);
        let m = if d > 0 {
            1 + (r.uniform() * 8.0) as i32
        } else {
            0
        };
        accum.push(a);
        denom.push(d);
        radii.push(m);
    }
    f.insert_real("stats.accum", vec![n], &to_t::<T>(&accum));
    f.insert_i32("stats.denom", vec![n], denom);
    f.insert_i32("stats.max_radii", vec![n], radii);
    Ok(f)
}

/// One golden fixture: a stage, a name suffix, and how its spec departs from
/// [`CaseSpec::new`]. Each entry is generated in f32 and f64.
#[derive(Clone, Copy, Debug)]
pub struct GoldenEntry {
    /// The stage name (metadata `stage`).
    pub stage: &'static str,
    /// Appended to the file name after the dtype (`<stage>_<dtype>_<variant>`).
    pub variant: Option<&'static str>,
    /// Changes the entry makes to [`CaseSpec::new`]'s defaults.
    pub configure: fn(&mut CaseSpec),
}

fn keep(_: &mut CaseSpec) {}
fn exact(s: &mut CaseSpec) {
    s.gradient = GradientMode::Exact;
}
fn inria(s: &mut CaseSpec) {
    s.gradient = GradientMode::Inria;
}
fn mlp(s: &mut CaseSpec) {
    s.field = FieldKind::Mlp;
}
fn cfc(s: &mut CaseSpec) {
    s.field = FieldKind::Cfc;
}
/// gsplat goldens: 24×16 pixels (two cameras), to keep the fixtures small.
fn gs_small(s: &mut CaseSpec) {
    s.width = 24;
    s.height = 16;
}
fn gs_v153(s: &mut CaseSpec) {
    gs_small(s);
    s.gsplat.version = crate::gsplat::Version::V1_5_3;
}
fn gs_v16(s: &mut CaseSpec) {
    gs_small(s);
    s.gsplat.version = crate::gsplat::Version::V1_6;
}
fn gs_v16_gsplat_aa(s: &mut CaseSpec) {
    gs_small(s);
    s.gsplat.version = crate::gsplat::Version::V1_6;
    s.gsplat.gradient = crate::gsplat::GradientMode::Gsplat;
    s.gsplat.antialiased = true;
}
fn gs_v153_gsplat_aa_dense(s: &mut CaseSpec) {
    gs_small(s);
    s.gsplat.version = crate::gsplat::Version::V1_5_3;
    s.gsplat.gradient = crate::gsplat::GradientMode::Gsplat;
    s.gsplat.antialiased = true;
    s.gsplat.packed = false;
}
fn step_6dof(s: &mut CaseSpec) {
    s.field = FieldKind::Mlp;
    s.is_6dof = true;
    s.hidden = Some(16);
}

/// The golden fixtures, in order. Adding a stage is one entry here.
pub const GOLDEN: &[GoldenEntry] = &[
    GoldenEntry {
        stage: rasterize::STAGE,
        variant: Some("exact"),
        configure: exact,
    },
    GoldenEntry {
        stage: rasterize::STAGE,
        variant: Some("inria"),
        configure: inria,
    },
    GoldenEntry {
        stage: deform::STAGE,
        variant: Some("mlp"),
        configure: mlp,
    },
    GoldenEntry {
        stage: deform::STAGE,
        variant: Some("cfc"),
        configure: cfc,
    },
    GoldenEntry {
        stage: loss::STAGE,
        variant: None,
        configure: keep,
    },
    GoldenEntry {
        stage: step::STAGE,
        variant: None,
        configure: keep,
    },
    GoldenEntry {
        stage: step::STAGE,
        variant: Some("6dof"),
        configure: step_6dof,
    },
    GoldenEntry {
        stage: gs::COVAR,
        variant: None,
        configure: keep,
    },
    GoldenEntry {
        stage: gs::SH,
        variant: None,
        configure: keep,
    },
    GoldenEntry {
        stage: gs::PROJECTION,
        variant: Some("v16_aa_gsplat"),
        configure: gs_v16_gsplat_aa,
    },
    GoldenEntry {
        stage: gs::PROJECTION,
        variant: Some("v153_aa_gsplat_dense"),
        configure: gs_v153_gsplat_aa_dense,
    },
    GoldenEntry {
        stage: gs::ISECT,
        variant: Some("v153"),
        configure: gs_v153,
    },
    GoldenEntry {
        stage: gs::ISECT,
        variant: Some("v16"),
        configure: gs_v16,
    },
    GoldenEntry {
        stage: gs::RASTERIZE,
        variant: Some("v16_gsplat"),
        configure: gs_v16_gsplat_aa,
    },
    GoldenEntry {
        stage: gs::RASTERIZATION,
        variant: Some("v153"),
        configure: gs_v153,
    },
    GoldenEntry {
        stage: gs::RASTERIZATION,
        variant: Some("v16"),
        configure: gs_v16,
    },
    GoldenEntry {
        stage: gs::RASTERIZATION,
        variant: Some("v16_aa_gsplat"),
        configure: gs_v16_gsplat_aa,
    },
];

/// Seed of every golden fixture.
pub const GOLDEN_SEED: u64 = 2024;

/// Every golden file as `(file name, bytes)`: for each [`GOLDEN`] entry and
/// each precision, `<name>.input.safetensors` (from [`new_case`]) and
/// `<name>.expected.safetensors` (from [`run_case`]), `<name>` being
/// `<stage>_<dtype>[_<variant>]`.
pub fn golden_files() -> Result<Vec<(String, Vec<u8>)>> {
    let mut out = Vec::new();
    for entry in GOLDEN {
        for precision in [Precision::F32, Precision::F64] {
            let mut spec = CaseSpec::new(entry.stage);
            spec.precision = precision;
            spec.seed = GOLDEN_SEED;
            (entry.configure)(&mut spec);
            let name = match entry.variant {
                Some(v) => format!("{}_{}_{}", entry.stage, precision, v),
                None => format!("{}_{}", entry.stage, precision),
            };
            let mut input = new_case(&spec)?;
            input.path = format!("{name}.input.safetensors").into();
            let mut expected = run_case(&input)?;
            expected.path = format!("{name}.expected.safetensors").into();
            out.push((input.path.display().to_string(), input.to_bytes()?));
            out.push((expected.path.display().to_string(), expected.to_bytes()?));
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_stage_generates_a_case_that_runs() {
        for stage in STAGES {
            for precision in [Precision::F32, Precision::F64] {
                let mut spec = CaseSpec::new(stage);
                spec.precision = precision;
                spec.seed = 9;
                spec.width = 20;
                spec.height = 17;
                spec.count = 5;
                let case = new_case(&spec).unwrap();
                assert_eq!(case.precision().unwrap(), precision);
                let out = run_case(&case).unwrap();
                assert!(!out.tensors.is_empty());
                // Deterministic.
                assert_eq!(
                    new_case(&spec).unwrap().to_bytes().unwrap(),
                    case.to_bytes().unwrap()
                );
            }
        }
    }

    #[test]
    fn seeds_and_options_change_the_case() {
        let a = new_case(&CaseSpec::new("rasterize")).unwrap();
        let mut s = CaseSpec::new("rasterize");
        s.seed = 1;
        let b = new_case(&s).unwrap();
        assert_ne!(a.tensors["means3D"], b.tensors["means3D"]);
        let mut s = CaseSpec::new("deform");
        s.field = FieldKind::Cfc;
        let c = new_case(&s).unwrap();
        assert_eq!(c.meta("field").unwrap(), "cfc");
        assert!(c.contains("cells.1.ff1.weight") && !c.contains("cells.2.ff1.weight"));
        let mut s = CaseSpec::new("rasterize");
        s.gradient = GradientMode::Inria;
        assert_eq!(new_case(&s).unwrap().meta("gradient").unwrap(), "inria");
    }

    #[test]
    fn bad_specs_are_errors() {
        assert!(new_case(&CaseSpec::new("nope"))
            .unwrap_err()
            .to_string()
            .contains("rasterize"));
        let mut s = CaseSpec::new("loss");
        s.width = 0;
        assert!(new_case(&s).is_err());
        let mut s = CaseSpec::new("deform");
        s.depth = Some(1);
        assert!(new_case(&s).is_err(), "MLP depth must be >= 3");
    }
}
