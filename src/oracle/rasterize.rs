//! Oracle stage `rasterize`: one forward and backward of the rasterizer on a
//! case file whose tensor names and layouts are the Inria Python API's.
//!
//! Inputs: `means3D [N,3]`, `shs [N,M,3]` or `colors_precomp [N,3]`,
//! `opacities [N,1]`, `scales [N,3]` and `rotations [N,4]` or
//! `cov3D_precomp [N,6]`, `viewmatrix [4,4]`, `projmatrix [4,4]` (Inria memory
//! layout), `campos [3]`, `bg [3]`, and the cotangents `grad_out_color
//! [3,H,W]` and `grad_out_depth [1,H,W]` (each optional, absent = zeros). Metadata: `stage=rasterize`, `image_height`,
//! `image_width`, `tanfovx`, `tanfovy`, `scale_modifier`, `sh_degree`
//! (required with `shs`), optional `gradient` (`exact`, the default, or
//! `inria`: see [`GradientMode`]). The floating-point dtype of the tensors
//! (all F32 or all F64) selects the precision.
//!
//! Outputs: `color`, `depth`, `radii` (I32), `final_T`, `n_contrib` (I32),
//! `means2D [N,2]`, `grad_means3D`, `grad_means2D [N,3]`, `grad_shs` or
//! `grad_colors_precomp`, `grad_opacities [N,1]`, `grad_scales` and
//! `grad_rotations` or `grad_cov3D_precomp`. The output's metadata is the
//! case's, with `gradient` set to the mode used.

use crate::camera::RasterCamera;
use crate::error::{Error, Result};
use crate::io::tensor_file::into_row_major;
use crate::io::TensorFile;
use crate::math::{Precision, Real};
use crate::render::{rasterize, rasterize_vjp, Colors, Covariances, GradientMode, RasterInput};

/// The stage name this entry handles.
pub const STAGE: &str = "rasterize";

/// Run the stage on a loaded case; the result holds the outputs (and the
/// same metadata).
pub fn run(case: &TensorFile) -> Result<TensorFile> {
    match case.precision()? {
        Precision::F32 => run_t::<f32>(case),
        Precision::F64 => run_t::<f64>(case),
    }
}

fn array<T: Real, const K: usize>(
    case: &TensorFile,
    name: &str,
    shape: &[usize],
) -> Result<[T; K]> {
    let v = case.get_real::<T>(name, shape)?;
    let mut a = [T::ZERO; K];
    a.copy_from_slice(&v);
    Ok(a)
}

/// The camera as this stage encodes it: metadata `image_height`,
/// `image_width`, `tanfovx`, `tanfovy` and tensors `viewmatrix [4,4]`,
/// `projmatrix [4,4]`, `campos [3]` (Inria layout). Shared with the `step`
/// stage.
pub fn read_camera<T: Real>(case: &TensorFile) -> Result<RasterCamera<T>> {
    let width: usize = case.meta_parse("image_width")?;
    let height: usize = case.meta_parse("image_height")?;
    if width == 0 || height == 0 || width.saturating_mul(height) > crate::render::MAX_PIXELS {
        // (The side that is 0, or both for too many pixels.)
        let field = match (width, height) {
            (0, _) => "__metadata__.image_width",
            (_, 0) => "__metadata__.image_height",
            _ => "__metadata__.image_width, image_height",
        };
        return Err(Error::field(
            &case.path,
            field,
            format!(
                "{width}x{height} pixels: each side at least 1, at most {} pixels",
                crate::render::MAX_PIXELS
            ),
        ));
    }
    Ok(RasterCamera {
        viewmatrix: array::<T, 16>(case, "viewmatrix", &[4, 4])?,
        projmatrix: array::<T, 16>(case, "projmatrix", &[4, 4])?,
        campos: array::<T, 3>(case, "campos", &[3])?,
        tanfovx: T::from_f64(case.meta_finite("tanfovx")?),
        tanfovy: T::from_f64(case.meta_finite("tanfovy")?),
        width,
        height,
    })
}

/// The camera tensors [`read_camera`] reads.
pub const CAMERA_TENSORS: [&str; 3] = ["viewmatrix", "projmatrix", "campos"];

/// Write `camera` the way [`read_camera`] reads it (floats as shortest
/// round-trip decimals).
pub fn write_camera<T: Real>(file: &mut TensorFile, camera: &RasterCamera<T>) {
    file.set_meta("image_height", camera.height);
    file.set_meta("image_width", camera.width);
    file.set_meta("tanfovx", format!("{:?}", camera.tanfovx.to_f64()));
    file.set_meta("tanfovy", format!("{:?}", camera.tanfovy.to_f64()));
    file.insert_real("viewmatrix", vec![4, 4], &camera.viewmatrix);
    file.insert_real("projmatrix", vec![4, 4], &camera.projmatrix);
    file.insert_real("campos", vec![3], &camera.campos);
}

fn run_t<T: Real>(case: &TensorFile) -> Result<TensorFile> {
    let stage = case.meta("stage")?;
    if stage != STAGE {
        return Err(Error::field(
            &case.path,
            "stage",
            format!("`{stage}`, expected `{STAGE}`"),
        ));
    }
    let mode = match case.metadata.get("gradient") {
        None => GradientMode::Exact,
        Some(name) => GradientMode::from_name(name.trim()).map_err(|_| {
            Error::field(
                &case.path,
                "__metadata__.gradient",
                format!("`{name}` is not a supported mode (exact, inria)"),
            )
        })?,
    };
    let camera = read_camera::<T>(case)?;
    let (h, w) = (camera.height, camera.width);
    let scale_modifier = case.meta_finite("scale_modifier")?;

    let means = case.real_array::<T>("means3D")?;
    let n = match *means.shape() {
        [n, 3] => n,
        ref shape => {
            return Err(Error::Tensor {
                context: case.path.display().to_string(),
                name: "means3D".into(),
                expected: "shape [N,3]".into(),
                found: format!("shape {shape:?}"),
            })
        }
    };
    let means = into_row_major(means);
    let mut known = vec![
        "means3D",
        "opacities",
        "viewmatrix",
        "projmatrix",
        "campos",
        "bg",
        "grad_out_color",
        "grad_out_depth",
    ];
    let sh_data;
    let colors = if case.contains("shs") {
        known.push("shs");
        let shs = case.real_array::<T>("shs")?;
        let stride = match *shs.shape() {
            [rows, m, 3] if rows == n => m,
            ref s => {
                return Err(Error::Tensor {
                    context: case.path.display().to_string(),
                    name: "shs".into(),
                    expected: format!("shape [{n},M,3]"),
                    found: format!("shape {s:?}"),
                })
            }
        };
        let degree: usize = case.meta_parse("sh_degree")?;
        sh_data = (stride, degree, into_row_major(shs));
        Colors::Sh {
            coeffs: &sh_data.2,
            stride: sh_data.0,
            degree: sh_data.1,
        }
    } else {
        known.push("colors_precomp");
        sh_data = (0, 0, case.get_real::<T>("colors_precomp", &[n, 3])?);
        Colors::Precomputed(&sh_data.2)
    };
    let opacities = case.get_real::<T>("opacities", &[n, 1])?;
    let cov_data;
    let covariances = if case.contains("cov3D_precomp") {
        known.push("cov3D_precomp");
        cov_data = (case.get_real::<T>("cov3D_precomp", &[n, 6])?, Vec::new());
        Covariances::Precomputed(&cov_data.0)
    } else {
        known.extend(["scales", "rotations"]);
        cov_data = (
            case.get_real::<T>("scales", &[n, 3])?,
            case.get_real::<T>("rotations", &[n, 4])?,
        );
        Covariances::ScaleRotation {
            scales: &cov_data.0,
            rotations: &cov_data.1,
            scale_modifier: T::from_f64(scale_modifier),
        }
    };
    case.reject_unknown(known)?;
    let background = array::<T, 3>(case, "bg", &[3])?;
    let grad_color = super::cotangent::<T>(case, "grad_out_color", &[3, h, w])?;
    let grad_depth = if case.contains("grad_out_depth") {
        Some(case.get_real::<T>("grad_out_depth", &[1, h, w])?)
    } else {
        None
    };
    let input = RasterInput {
        means3d: &means,
        colors,
        opacities: &opacities,
        covariances,
        camera: &camera,
        background,
    };
    let (out, state) = rasterize(&input)?;
    let g = rasterize_vjp(&input, &state, &grad_color, grad_depth.as_deref(), mode)?;

    let mut res = TensorFile::new(case.path.clone());
    res.metadata = case.metadata.clone();
    res.set_meta("gradient", mode.name());
    res.insert_real("color", vec![3, h, w], &out.color);
    res.insert_real("depth", vec![1, h, w], &out.depth);
    res.insert_i32("radii", vec![n], out.radii.clone());
    res.insert_real("final_T", vec![h, w], &out.final_t);
    res.insert_i32(
        "n_contrib",
        vec![h, w],
        out.n_contrib.iter().map(|&c| c as i32).collect(),
    );
    res.insert_real("means2D", vec![n, 2], &out.means2d);
    res.insert_real("grad_means3D", vec![n, 3], &g.means3d);
    res.insert_real("grad_means2D", vec![n, 3], &g.means2d);
    match input.colors {
        Colors::Sh { stride, .. } => res.insert_real("grad_shs", vec![n, stride, 3], &g.colors),
        Colors::Precomputed(_) => res.insert_real("grad_colors_precomp", vec![n, 3], &g.colors),
    }
    res.insert_real("grad_opacities", vec![n, 1], &g.opacities);
    match input.covariances {
        Covariances::ScaleRotation { .. } => {
            res.insert_real("grad_scales", vec![n, 3], &g.scales_or_cov);
            res.insert_real("grad_rotations", vec![n, 4], &g.rotations);
        }
        Covariances::Precomputed(_) => {
            res.insert_real("grad_cov3D_precomp", vec![n, 6], &g.scales_or_cov)
        }
    }
    Ok(res)
}
