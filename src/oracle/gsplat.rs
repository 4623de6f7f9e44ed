//! Oracle stages in gsplat's conventions (see [`crate::gsplat`]): one stage
//! per gsplat function, tensors under gsplat's argument names, cotangents
//! `v_<output>` and gradients `v_<input>` (gsplat's naming). Every cotangent
//! is optional: an absent one reads as zeros ([`super::cotangent`]).
//!
//! Common metadata: `version` (`1.5.3` or `1.6`, default `1.6`) and
//! `gradient` (`exact`, the default, or `gsplat`). Booleans are `true` /
//! `false`. The floating-point dtype (all F32 or all F64) selects the
//! precision. docs/ORACLE.md lists every stage's tensors.

use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::gsplat::covar::{quat_scale_to_covar_preci, quat_scale_to_covar_preci_vjp};
use crate::gsplat::isect::{isect_offset_encode, isect_tiles, IsectInput, TileRule};
use crate::gsplat::projection::{
    fully_fused_projection, fully_fused_projection_vjp, unpack, Covars, ProjectionCotangents,
    ProjectionInput, ProjectionSettings,
};
use crate::gsplat::raster::{rasterize_to_pixels, rasterize_to_pixels_vjp, RasterInput};
use crate::gsplat::rendering::{
    rasterization, rasterization_vjp, Colors, RasterizationInput, RasterizationSettings,
    RasterizeMode,
};
use crate::gsplat::sh::{spherical_harmonics, spherical_harmonics_vjp};
use crate::gsplat::{camera_tensors, GradientMode, Version};
use crate::io::tensor_file::into_row_major;
use crate::io::TensorFile;
use crate::math::{Precision, Real, Rng};

use super::cotangent;

/// `gsplat.quat_scale_to_covar_preci`.
pub const COVAR: &str = "gsplat_quat_scale_to_covar_preci";
/// `gsplat.spherical_harmonics`.
pub const SH: &str = "gsplat_spherical_harmonics";
/// `gsplat.fully_fused_projection`.
pub const PROJECTION: &str = "gsplat_fully_fused_projection";
/// `gsplat.isect_tiles` + `gsplat.isect_offset_encode`.
pub const ISECT: &str = "gsplat_isect_tiles";
/// `gsplat.rasterize_to_pixels`.
pub const RASTERIZE: &str = "gsplat_rasterize_to_pixels";
/// `gsplat.rasterization`.
pub const RASTERIZATION: &str = "gsplat_rasterization";

/// Every gsplat stage name.
pub const STAGES: [&str; 6] = [COVAR, SH, PROJECTION, ISECT, RASTERIZE, RASTERIZATION];

/// Run the gsplat stage the case names.
pub fn run(case: &TensorFile) -> Result<TensorFile> {
    match case.precision()? {
        Precision::F32 => run_t::<f32>(case),
        Precision::F64 => run_t::<f64>(case),
    }
}

fn version(case: &TensorFile) -> Result<Version> {
    match case.metadata.get("version") {
        None => Ok(Version::default()),
        Some(v) => Version::from_name(v).map_err(|_| {
            Error::field(
                &case.path,
                "__metadata__.version",
                format!("`{v}` is not a supported gsplat version (1.5.3, 1.6)"),
            )
        }),
    }
}

fn mode(case: &TensorFile) -> Result<GradientMode> {
    match case.metadata.get("gradient") {
        None => Ok(GradientMode::Exact),
        Some(v) => GradientMode::from_name(v).map_err(|_| {
            Error::field(
                &case.path,
                "__metadata__.gradient",
                format!("`{v}` is not a supported mode (exact, gsplat)"),
            )
        }),
    }
}

fn shape_err(case: &TensorFile, name: &str, expected: String, found: &[usize]) -> Error {
    Error::Tensor {
        context: case.path.display().to_string(),
        name: name.into(),
        expected,
        found: format!("shape {found:?}"),
    }
}

/// `[rows, width]` real tensor: `rows` and the row-major values.
fn rows<T: Real>(case: &TensorFile, name: &str, width: usize) -> Result<(usize, Vec<T>)> {
    let a = case.real_array::<T>(name)?;
    match *a.shape() {
        [m, w] if w == width => Ok((m, into_row_major(a))),
        ref s => Err(shape_err(case, name, format!("shape [M,{width}]"), s)),
    }
}

/// `[M]` real tensor.
fn vec1<T: Real>(case: &TensorFile, name: &str) -> Result<Vec<T>> {
    let a = case.real_array::<T>(name)?;
    match a.shape() {
        [_] => Ok(into_row_major(a)),
        s => Err(shape_err(case, name, "shape [M]".into(), s)),
    }
}

/// `viewmats [C,4,4]` and `Ks [C,3,3]`, `C > 0`: `C` and both row-major.
fn cameras<T: Real>(case: &TensorFile) -> Result<(usize, Vec<T>, Vec<T>)> {
    let vm = case.real_array::<T>("viewmats")?;
    let c = match *vm.shape() {
        [c, 4, 4] if c > 0 => c,
        ref s => return Err(shape_err(case, "viewmats", "shape [C,4,4]".into(), s)),
    };
    let ks = case.get_real::<T>("Ks", &[c, 3, 3])?;
    Ok((c, into_row_major(vm), ks))
}

/// I32 tensor `name` of shape `expected`, row-major.
fn ints(case: &TensorFile, name: &str, expected: &[usize]) -> Result<Vec<i32>> {
    let a = case.i32_array(name)?;
    if a.shape() != expected {
        let want = format!(
            "shape [{}]",
            expected
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(",")
        );
        return Err(shape_err(case, name, want, a.shape()));
    }
    Ok(a.iter().copied().collect())
}

fn run_t<T: Real>(case: &TensorFile) -> Result<TensorFile> {
    let stage = case.meta("stage")?.to_string();
    let mut res = TensorFile::new(case.path.clone());
    res.metadata = case.metadata.clone();
    let version = version(case)?;
    let mode = mode(case)?;
    res.set_meta("version", version.name());
    res.set_meta("gradient", mode.name());
    match stage.as_str() {
        COVAR => run_covar::<T>(case, &mut res)?,
        SH => run_sh::<T>(case, &mut res)?,
        PROJECTION => run_projection::<T>(case, &mut res, version, mode)?,
        ISECT => run_isect::<T>(case, &mut res, version)?,
        RASTERIZE => run_rasterize::<T>(case, &mut res, version, mode)?,
        RASTERIZATION => run_rasterization::<T>(case, &mut res, version, mode)?,
        other => {
            return Err(Error::field(
                &case.path,
                "__metadata__.stage",
                format!("`{other}` is not a gsplat stage"),
            ))
        }
    }
    Ok(res)
}

fn run_covar<T: Real>(case: &TensorFile, res: &mut TensorFile) -> Result<()> {
    let cc: bool = case.meta_or("compute_covar", true)?;
    let cp: bool = case.meta_or("compute_preci", true)?;
    let triu: bool = case.meta_or("triu", false)?;
    let (n, quats) = rows::<T>(case, "quats", 4)?;
    let scales = case.get_real::<T>("scales", &[n, 3])?;
    let shape = if triu { vec![n, 6] } else { vec![n, 3, 3] };
    let mut known = vec!["quats", "scales"];
    let v_covars = if cc {
        known.push("v_covars");
        Some(cotangent::<T>(case, "v_covars", &shape)?)
    } else {
        None
    };
    let v_precis = if cp {
        known.push("v_precis");
        Some(cotangent::<T>(case, "v_precis", &shape)?)
    } else {
        None
    };
    case.reject_unknown(known)?;
    let out = quat_scale_to_covar_preci(&quats, &scales, cc, cp, triu)
        .map_err(|e| e.in_file(&case.path))?;
    let (vq, vs) = quat_scale_to_covar_preci_vjp(
        &quats,
        &scales,
        v_covars.as_deref(),
        v_precis.as_deref(),
        triu,
    )
    .map_err(|e| e.in_file(&case.path))?;
    if cc {
        res.insert_real("covars", shape.clone(), &out.covars);
    }
    if cp {
        res.insert_real("precis", shape, &out.precis);
    }
    res.insert_real("v_quats", vec![n, 4], &vq);
    res.insert_real("v_scales", vec![n, 3], &vs);
    Ok(())
}

fn run_sh<T: Real>(case: &TensorFile, res: &mut TensorFile) -> Result<()> {
    let degree: usize = case.meta_parse("degrees_to_use")?;
    let (m, dirs) = rows::<T>(case, "dirs", 3)?;
    let coeffs = case.real_array::<T>("coeffs")?;
    let (k, d) = match *coeffs.shape() {
        [rows, k, d] if rows == m && d > 0 => (k, d),
        ref s => return Err(shape_err(case, "coeffs", format!("shape [{m},K,D]"), s)),
    };
    let coeffs = into_row_major(coeffs);
    if degree > crate::gsplat::sh::MAX_DEGREE || (degree + 1) * (degree + 1) > k {
        return Err(Error::field(
            &case.path,
            "__metadata__.degrees_to_use",
            format!("{degree} with K = {k} (at most 4, (degree+1)² ≤ K)"),
        ));
    }
    let v = cotangent::<T>(case, "v_colors", &[m, d])?;
    case.reject_unknown(["dirs", "coeffs", "v_colors"])?;
    let colors = spherical_harmonics(degree, &dirs, &coeffs, k, d, None)
        .map_err(|e| e.in_file(&case.path))?;
    let (vd, vk) = spherical_harmonics_vjp(degree, &dirs, &coeffs, k, d, None, &v)
        .map_err(|e| e.in_file(&case.path))?;
    res.insert_real("colors", vec![m, d], &colors);
    res.insert_real("v_dirs", vec![m, 3], &vd);
    res.insert_real("v_coeffs", vec![m, k, d], &vk);
    Ok(())
}

/// `width`, `height`, `eps2d`, `near_plane`, `far_plane`, `radius_clip` (gsplat's defaults when absent).
fn projection_settings(case: &TensorFile, version: Version) -> Result<ProjectionSettings> {
    let d = ProjectionSettings::new(
        case.meta_parse("width")?,
        case.meta_parse("height")?,
        version,
    );
    Ok(ProjectionSettings {
        eps2d: case.meta_finite_or("eps2d", d.eps2d)?,
        near_plane: case.meta_finite_or("near_plane", d.near_plane)?,
        far_plane: case.meta_finite_or("far_plane", d.far_plane)?,
        radius_clip: case.meta_finite_or("radius_clip", d.radius_clip)?,
        calc_compensations: case.meta_or("calc_compensations", false)?,
        ..d
    })
}

fn run_projection<T: Real>(
    case: &TensorFile,
    res: &mut TensorFile,
    version: Version,
    mode: GradientMode,
) -> Result<()> {
    let s = projection_settings(case, version)?;
    let packed: bool = case.meta_or("packed", false)?;
    let (n, means) = rows::<T>(case, "means", 3)?;
    let (c, vm, ks) = cameras::<T>(case)?;
    let mut known = vec![
        "means",
        "viewmats",
        "Ks",
        "v_means2d",
        "v_depths",
        "v_conics",
    ];
    let (a, b) = if case.contains("covars") {
        known.push("covars");
        (case.get_real::<T>("covars", &[n, 6])?, Vec::new())
    } else {
        known.extend(["quats", "scales"]);
        (
            case.get_real::<T>("quats", &[n, 4])?,
            case.get_real::<T>("scales", &[n, 3])?,
        )
    };
    let opac = if case.contains("opacities") {
        known.push("opacities");
        Some(case.get_real::<T>("opacities", &[n])?)
    } else {
        None
    };
    if s.calc_compensations {
        known.push("v_compensations");
    }
    case.reject_unknown(known)?;
    let input = ProjectionInput {
        means: &means,
        covars: if case.contains("covars") {
            Covars::Triu(&a)
        } else {
            Covars::QuatScale {
                quats: &a,
                scales: &b,
            }
        },
        opacities: opac.as_deref(),
        viewmats: &vm,
        ks: &ks,
    };
    let p = fully_fused_projection(&input, &s)?;
    let cn = c * n;
    let entries = p.packed_entries();
    let (lead, dense_of) = if packed {
        (vec![entries.len()], Some(&entries))
    } else {
        (vec![c, n], None)
    };
    let shp = |w: Option<usize>| {
        let mut v = lead.clone();
        v.extend(w);
        v
    };
    // Cotangents in the output layout, as dense `[C,N,w]` rows.
    let read = |name: &str, w: usize, last: Option<usize>| -> Result<Vec<T>> {
        if !case.contains(name) {
            return Ok(vec![T::ZERO; cn * w]);
        }
        let v = case.get_real::<T>(name, &shp(last))?;
        Ok(match dense_of {
            Some(e) => unpack(e, &v, w, cn),
            None => v,
        })
    };
    let vmeans2d = read("v_means2d", 2, Some(2))?;
    let vdepths = read("v_depths", 1, None)?;
    let vconics = read("v_conics", 3, Some(3))?;
    let vcomp = if s.calc_compensations {
        Some(read("v_compensations", 1, None)?)
    } else {
        None
    };
    let g = fully_fused_projection_vjp(
        &input,
        &s,
        &p,
        &ProjectionCotangents {
            v_means2d: &vmeans2d,
            v_depths: &vdepths,
            v_conics: &vconics,
            v_compensations: vcomp.as_deref(),
        },
        mode,
    )?;
    if packed {
        let q = p.pack();
        res.insert_i32("camera_ids", shp(None), q.camera_ids);
        res.insert_i32("gaussian_ids", shp(None), q.gaussian_ids);
        res.insert_i32("radii", shp(Some(2)), q.radii);
        res.insert_real("means2d", shp(Some(2)), &q.means2d);
        res.insert_real("depths", shp(None), &q.depths);
        res.insert_real("conics", shp(Some(3)), &q.conics);
        if let Some(cv) = &q.compensations {
            res.insert_real("compensations", shp(None), cv);
        }
    } else {
        res.insert_i32("radii", shp(Some(2)), p.radii.clone());
        res.insert_real("means2d", shp(Some(2)), &p.means2d);
        res.insert_real("depths", shp(None), &p.depths);
        res.insert_real("conics", shp(Some(3)), &p.conics);
        if let Some(cv) = &p.compensations {
            res.insert_real("compensations", shp(None), cv);
        }
    }
    res.insert_real("v_means", vec![n, 3], &g.v_means);
    if case.contains("covars") {
        res.insert_real("v_covars", vec![n, 6], &g.v_covars);
    } else {
        res.insert_real("v_quats", vec![n, 4], &g.v_quats);
        res.insert_real("v_scales", vec![n, 3], &g.v_scales);
    }
    Ok(())
}

/// int64 isect ids as `[n, 2]` int32 words (high, low), the tensor files
/// holding 32-bit integers only.
fn split_ids(ids: &[i64]) -> Vec<i32> {
    ids.iter()
        .flat_map(|&k| [(k >> 32) as i32, k as u32 as i32])
        .collect()
}

fn run_isect<T: Real>(case: &TensorFile, res: &mut TensorFile, version: Version) -> Result<()> {
    let (m, means2d) = rows::<T>(case, "means2d", 2)?;
    let radii = ints(case, "radii", &[m, 2])?;
    let depths = case.get_real::<T>("depths", &[m])?;
    let tile_size: usize = case.meta_parse("tile_size")?;
    let tw: usize = case.meta_parse("tile_width")?;
    let th: usize = case.meta_parse("tile_height")?;
    let n_images: usize = case.meta_parse("n_images")?;
    let mut known = vec!["means2d", "radii", "depths"];
    let image_ids = if case.contains("image_ids") {
        known.push("image_ids");
        Some(ints(case, "image_ids", &[m])?)
    } else {
        None
    };
    let (conics, opac) = if case.contains("conics") || case.contains("opacities") {
        known.extend(["conics", "opacities"]);
        (
            Some(case.get_real::<T>("conics", &[m, 3])?),
            Some(case.get_real::<T>("opacities", &[m])?),
        )
    } else {
        (None, None)
    };
    case.reject_unknown(known)?;
    let rule = if version.accutile() && conics.is_some() {
        TileRule::AccuTile
    } else {
        TileRule::RadiusBox
    };
    let n = if image_ids.is_some() {
        0
    } else {
        m / n_images.max(1)
    };
    let is = isect_tiles(
        &IsectInput {
            means2d: &means2d,
            radii: &radii,
            depths: &depths,
            conics: conics.as_deref(),
            opacities: opac.as_deref(),
            image_ids: image_ids.as_deref(),
            n,
        },
        tile_size,
        tw,
        th,
        n_images,
        version,
        rule,
    )
    .map_err(|e| Error::field(&case.path, "isect_tiles", e.to_string()))?;
    let off = isect_offset_encode(&is.isect_ids, n_images, tw, th, version)
        .map_err(|e| Error::field(&case.path, "isect_offset_encode", e.to_string()))?;
    let ni = is.flatten_ids.len();
    res.insert_i32("tiles_per_gauss", vec![m], is.tiles_per_gauss);
    res.insert_i32("isect_ids", vec![ni, 2], split_ids(&is.isect_ids));
    res.insert_i32("flatten_ids", vec![ni], is.flatten_ids);
    res.insert_i32("isect_offsets", vec![n_images, th, tw], off);
    Ok(())
}

/// The per-image tensors of the two rasterizing stages.
struct ImageTensors<T> {
    /// Optional `backgrounds [I,D]`.
    backgrounds: Option<Vec<T>>,
    /// Cotangent `v_render_colors [I,H,W,D]` (absent = zeros).
    v_render_colors: Vec<T>,
    /// Cotangent `v_render_alphas [I,H,W,1]` (absent = zeros).
    v_render_alphas: Vec<T>,
}

/// Read [`ImageTensors`] for `[images, height, width, channels]` and add
/// their names to `known`.
fn image_tensors<T: Real>(
    case: &TensorFile,
    known: &mut Vec<&str>,
    [images, h, w, d]: [usize; 4],
) -> Result<ImageTensors<T>> {
    known.extend(["backgrounds", "v_render_colors", "v_render_alphas"]);
    // (Before the absent cotangents' zeros are allocated.)
    crate::gsplat::check_frame(images, w, h, d)
        .map_err(|e| Error::field(&case.path, "__metadata__.image_width", e.to_string()))?;
    let backgrounds = if case.contains("backgrounds") {
        Some(case.get_real::<T>("backgrounds", &[images, d])?)
    } else {
        None
    };
    Ok(ImageTensors {
        backgrounds,
        v_render_colors: cotangent::<T>(case, "v_render_colors", &[images, h, w, d])?,
        v_render_alphas: cotangent::<T>(case, "v_render_alphas", &[images, h, w, 1])?,
    })
}

fn run_rasterize<T: Real>(
    case: &TensorFile,
    res: &mut TensorFile,
    version: Version,
    mode: GradientMode,
) -> Result<()> {
    let w: usize = case.meta_parse("image_width")?;
    let h: usize = case.meta_parse("image_height")?;
    let tile_size: usize = case.meta_parse("tile_size")?;
    let (m, means2d) = rows::<T>(case, "means2d", 2)?;
    let conics = case.get_real::<T>("conics", &[m, 3])?;
    let colors = case.real_array::<T>("colors")?;
    let d = match *colors.shape() {
        [rows, d] if rows == m && d > 0 => d,
        ref s => return Err(shape_err(case, "colors", format!("shape [{m},D]"), s)),
    };
    let colors = into_row_major(colors);
    let opac = vec1::<T>(case, "opacities")?;
    let offsets = case.i32_array("isect_offsets")?;
    let images = match *offsets.shape() {
        [images, _, _] => images,
        ref s => {
            return Err(shape_err(
                case,
                "isect_offsets",
                "shape [I,th,tw]".into(),
                s,
            ))
        }
    };
    let offsets: Vec<i32> = offsets.iter().copied().collect();
    let flatten: Vec<i32> = case.i32_array("flatten_ids")?.iter().copied().collect();
    let mut known = vec![
        "means2d",
        "conics",
        "colors",
        "opacities",
        "isect_offsets",
        "flatten_ids",
    ];
    let im = image_tensors::<T>(case, &mut known, [images, h, w, d])?;
    case.reject_unknown(known)?;
    let input = RasterInput {
        means2d: &means2d,
        conics: &conics,
        colors: &colors,
        opacities: &opac,
        backgrounds: im.backgrounds.as_deref(),
        channels: d,
        width: w,
        height: h,
        tile_size,
        isect_offsets: &offsets,
        flatten_ids: &flatten,
    };
    let out = rasterize_to_pixels(&input, version)?;
    let g = rasterize_to_pixels_vjp(
        &input,
        version,
        &out,
        &im.v_render_colors,
        &im.v_render_alphas,
        mode,
    )?;
    res.insert_real("render_colors", vec![images, h, w, d], &out.render_colors);
    res.insert_real("render_alphas", vec![images, h, w, 1], &out.render_alphas);
    res.insert_i32("last_ids", vec![images, h, w], out.last_ids);
    res.insert_real("v_means2d", vec![m, 2], &g.v_means2d);
    res.insert_real("v_means2d_abs", vec![m, 2], &g.v_means2d_abs);
    res.insert_real("v_conics", vec![m, 3], &g.v_conics);
    res.insert_real("v_colors", vec![m, d], &g.v_colors);
    res.insert_real("v_opacities", vec![m], &g.v_opacities);
    if let Some(vb) = &g.v_backgrounds {
        res.insert_real("v_backgrounds", vec![images, d], vb);
    }
    Ok(())
}

fn run_rasterization<T: Real>(
    case: &TensorFile,
    res: &mut TensorFile,
    version: Version,
    mode: GradientMode,
) -> Result<()> {
    let w: usize = case.meta_parse("width")?;
    let h: usize = case.meta_parse("height")?;
    let d0 = RasterizationSettings::new(w, h, version);
    let s = RasterizationSettings {
        near_plane: case.meta_finite_or("near_plane", d0.near_plane)?,
        far_plane: case.meta_finite_or("far_plane", d0.far_plane)?,
        radius_clip: case.meta_finite_or("radius_clip", d0.radius_clip)?,
        eps2d: case.meta_finite_or("eps2d", d0.eps2d)?,
        packed: case.meta_or("packed", d0.packed)?,
        tile_size: case.meta_or("tile_size", d0.tile_size)?,
        rasterize_mode: RasterizeMode::from_name(
            &case.meta_or("rasterize_mode", "classic".to_string())?,
        )
        .map_err(|e| Error::field(&case.path, "__metadata__.rasterize_mode", e.to_string()))?,
        ..d0
    };
    let (n, means) = rows::<T>(case, "means", 3)?;
    let (c, vm, ks) = cameras::<T>(case)?;
    let opac = case.get_real::<T>("opacities", &[n])?;
    let mut known = vec!["means", "opacities", "colors", "viewmats", "Ks"];
    let use_covars = case.contains("covars");
    let (a, b) = if use_covars {
        known.push("covars");
        (case.get_real::<T>("covars", &[n, 6])?, Vec::new())
    } else {
        known.extend(["quats", "scales"]);
        (
            case.get_real::<T>("quats", &[n, 4])?,
            case.get_real::<T>("scales", &[n, 3])?,
        )
    };
    let colors = case.real_array::<T>("colors")?;
    let cs = colors.shape().to_vec();
    let colors = into_row_major(colors);
    let sh_degree: Option<usize> = match case.metadata.get("sh_degree") {
        Some(_) => Some(case.meta_parse("sh_degree")?),
        None => None,
    };
    let col = match sh_degree {
        Some(degree) => {
            if cs.len() != 3 || cs[0] != n || cs[2] != 3 {
                return Err(shape_err(case, "colors", format!("shape [{n},K,3]"), &cs));
            }
            Colors::Sh {
                coeffs: &colors,
                k: cs[1],
                degree,
            }
        }
        None => {
            if cs.len() != 2 || cs[0] != n || cs[1] == 0 {
                return Err(shape_err(case, "colors", format!("shape [{n},D]"), &cs));
            }
            Colors::Post {
                colors: &colors,
                channels: cs[1],
            }
        }
    };
    let d = col.channels();
    let im = image_tensors::<T>(case, &mut known, [c, h, w, d])?;
    case.reject_unknown(known)?;
    let input = RasterizationInput {
        means: &means,
        covars: if use_covars {
            Covars::Triu(&a)
        } else {
            Covars::QuatScale {
                quats: &a,
                scales: &b,
            }
        },
        opacities: &opac,
        colors: col,
        viewmats: &vm,
        ks: &ks,
        backgrounds: im.backgrounds.as_deref(),
    };
    let f = rasterization(&input, &s)?;
    let g = rasterization_vjp(
        &input,
        &s,
        &f,
        &im.v_render_colors,
        &im.v_render_alphas,
        mode,
    )?;
    res.insert_real("render_colors", vec![c, h, w, d], &f.render_colors);
    res.insert_real("render_alphas", vec![c, h, w, 1], &f.render_alphas);
    let nr = f.rows.len();
    let lead = if s.packed { vec![nr] } else { vec![c, n] };
    let shp = |w: Option<usize>| {
        let mut v = lead.clone();
        v.extend(w);
        v
    };
    let pick = |src: &[T], w: usize| -> Vec<T> {
        f.rows
            .iter()
            .flat_map(|&e| src[e * w..(e + 1) * w].iter().copied())
            .collect()
    };
    if s.packed {
        res.insert_i32(
            "meta.camera_ids",
            shp(None),
            f.rows.iter().map(|&e| (e / n) as i32).collect(),
        );
        res.insert_i32(
            "meta.gaussian_ids",
            shp(None),
            f.rows.iter().map(|&e| (e % n) as i32).collect(),
        );
    }
    let p = &f.projection;
    res.insert_i32(
        "meta.radii",
        shp(Some(2)),
        f.rows
            .iter()
            .flat_map(|&e| [p.radii[2 * e], p.radii[2 * e + 1]])
            .collect(),
    );
    res.insert_real("meta.means2d", shp(Some(2)), &pick(&p.means2d, 2));
    res.insert_real("meta.depths", shp(None), &pick(&p.depths, 1));
    res.insert_real("meta.conics", shp(Some(3)), &pick(&p.conics, 3));
    res.insert_real("meta.opacities", shp(None), &f.opacities);
    let ni = f.isects.flatten_ids.len();
    res.insert_i32(
        "meta.tiles_per_gauss",
        shp(None),
        f.isects.tiles_per_gauss.clone(),
    );
    res.insert_i32(
        "meta.isect_ids",
        vec![ni, 2],
        split_ids(&f.isects.isect_ids),
    );
    res.insert_i32("meta.flatten_ids", vec![ni], f.isects.flatten_ids.clone());
    res.insert_i32(
        "meta.isect_offsets",
        vec![c, f.tile_height, f.tile_width],
        f.isect_offsets.clone(),
    );
    res.insert_real("v_means", vec![n, 3], &g.v_means);
    if use_covars {
        res.insert_real("v_covars", vec![n, 6], &g.v_covars);
    } else {
        res.insert_real("v_quats", vec![n, 4], &g.v_quats);
        res.insert_real("v_scales", vec![n, 3], &g.v_scales);
    }
    res.insert_real("v_opacities", vec![n], &g.v_opacities);
    res.insert_real("v_colors", cs.clone(), &g.v_colors);
    if let Some(vb) = &g.v_backgrounds {
        res.insert_real("v_backgrounds", vec![c, d], vb);
    }
    res.insert_real("v_means2d", shp(Some(2)), &g.v_means2d);
    res.insert_real("v_means2d_abs", shp(Some(2)), &g.v_means2d_abs);
    Ok(())
}

// ---------------------------------------------------------------- case new

/// Options of generated gsplat cases.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GsplatOptions {
    /// The gsplat version reproduced (metadata `version`).
    pub version: Version,
    /// The gradient mode (metadata `gradient`).
    pub gradient: GradientMode,
    /// Antialiased rasterization (projection: `calc_compensations`;
    /// rasterization: `rasterize_mode=antialiased`).
    pub antialiased: bool,
    /// Packed `[nnz,·]` rows instead of dense `[C,N,·]` (projection and
    /// rasterization).
    pub packed: bool,
}

impl Default for GsplatOptions {
    fn default() -> Self {
        GsplatOptions {
            version: Version::V1_6,
            gradient: GradientMode::Exact,
            antialiased: false,
            packed: true,
        }
    }
}

struct GenScene {
    n: usize,
    c: usize,
    means: Vec<f64>,
    quats: Vec<f64>,
    scales: Vec<f64>,
    opacities: Vec<f64>,
    sh: Vec<f64>,
    viewmats: Vec<f64>,
    ks: Vec<f64>,
    backgrounds: Vec<f64>,
}

/// `count` Gaussians in view of two cameras 4 units away, plus one beside
/// the view whose tangent clamp is active and one tiny one (for the
/// antialiasing compensation), unnormalised quaternions, SH degree 3.
fn gen_scene(seed: u64, count: usize, w: usize, h: usize) -> Result<GenScene> {
    let mut r = Rng::stream(seed, 3 << 40);
    let fov_x: f64 = 0.9;
    let fov_y = 2.0 * (libm::tan(fov_x / 2.0) * h as f64 / w as f64).atan();
    let c = 2;
    let mut viewmats = Vec::new();
    let mut ks = Vec::new();
    for ci in 0..c {
        let eye = [0.5 * ci as f64 - 0.25, r.uniform_range(-0.2, 0.2), -4.0];
        let cam = Camera::look_at(eye, [0.0; 3], [0.0, -1.0, 0.0], fov_x, fov_y, w, h)?;
        let (v, k) = camera_tensors::<f64>(&cam);
        viewmats.extend(v);
        ks.extend(k);
    }
    let n = count + 2;
    let mut s = GenScene {
        n,
        c,
        means: Vec::new(),
        quats: Vec::new(),
        scales: Vec::new(),
        opacities: Vec::new(),
        sh: Vec::new(),
        viewmats,
        ks,
        backgrounds: Vec::new(),
    };
    let aspect = h as f64 / w as f64;
    for i in 0..n {
        let (mean, lo, hi) = if i == count {
            ([3.0, r.uniform_range(-0.3, 0.3), 0.0], 0.8, 1.2)
        } else if i == count + 1 {
            (
                [r.uniform_range(-0.5, 0.5), r.uniform_range(-0.3, 0.3), -1.0],
                1e-3,
                2e-3,
            )
        } else {
            (
                [
                    r.uniform_range(-0.8, 0.8),
                    r.uniform_range(-0.8 * aspect, 0.8 * aspect),
                    r.uniform_range(-0.8, 0.8),
                ],
                0.08,
                0.35,
            )
        };
        s.means.extend(mean);
        for _ in 0..4 {
            s.quats.push(r.normal());
        }
        for _ in 0..3 {
            s.scales
                .push(r.uniform_range(f64::ln(lo), f64::ln(hi)).exp());
        }
        s.opacities.push(if i == count + 1 {
            0.95
        } else {
            r.uniform_range(0.2, 0.995)
        });
        for b in 0..16 {
            for _ in 0..3 {
                s.sh.push(r.normal() * if b == 0 { 0.8 } else { 0.25 });
            }
        }
    }
    for _ in 0..3 * c {
        s.backgrounds.push(r.uniform());
    }
    Ok(s)
}

fn to_t<T: Real>(v: &[f64]) -> Vec<T> {
    v.iter().map(|&x| T::from_f64(x)).collect()
}

fn cot(seed: u64, stream: u64, n: usize) -> Vec<f64> {
    let mut r = Rng::stream(seed, (1 << 40) + stream);
    (0..n).map(|_| r.normal()).collect()
}

/// A seeded case for gsplat stage `stage` (inputs only; metadata `stage`
/// and `seed` are set by the caller).
pub fn new_case<T: Real>(
    stage: &str,
    seed: u64,
    width: usize,
    height: usize,
    count: usize,
    o: &GsplatOptions,
) -> Result<TensorFile> {
    let sc = gen_scene(seed, count, width, height)?;
    let (n, c) = (sc.n, sc.c);
    let mut f = TensorFile::new(format!("{stage}.safetensors"));
    f.set_meta("version", o.version.name());
    f.set_meta("gradient", o.gradient.name());
    let means = to_t::<T>(&sc.means);
    let quats = to_t::<T>(&sc.quats);
    let scales = to_t::<T>(&sc.scales);
    let opac = to_t::<T>(&sc.opacities);
    let vm = to_t::<T>(&sc.viewmats);
    let ks = to_t::<T>(&sc.ks);
    // The projection the downstream stages' inputs come from.
    let ps = ProjectionSettings {
        calc_compensations: o.antialiased,
        ..ProjectionSettings::new(width, height, o.version)
    };
    let pin = ProjectionInput {
        means: &means,
        covars: Covars::QuatScale {
            quats: &quats,
            scales: &scales,
        },
        opacities: Some(&opac),
        viewmats: &vm,
        ks: &ks,
    };
    match stage {
        COVAR => {
            f.set_meta("compute_covar", true);
            f.set_meta("compute_preci", true);
            f.set_meta("triu", true);
            f.insert_real("quats", vec![n, 4], &quats);
            f.insert_real("scales", vec![n, 3], &scales);
            f.insert_real("v_covars", vec![n, 6], &to_t::<T>(&cot(seed, 0, 6 * n)));
            f.insert_real("v_precis", vec![n, 6], &to_t::<T>(&cot(seed, 1, 6 * n)));
        }
        SH => {
            f.set_meta("degrees_to_use", 3);
            let dirs: Vec<f64> = sc.means.iter().map(|x| x + 0.3).collect();
            f.insert_real("dirs", vec![n, 3], &to_t::<T>(&dirs));
            f.insert_real("coeffs", vec![n, 16, 3], &to_t::<T>(&sc.sh));
            f.insert_real("v_colors", vec![n, 3], &to_t::<T>(&cot(seed, 0, 3 * n)));
        }
        PROJECTION => {
            f.set_meta("width", width);
            f.set_meta("height", height);
            f.set_meta("calc_compensations", o.antialiased);
            f.set_meta("packed", o.packed);
            f.insert_real("means", vec![n, 3], &means);
            f.insert_real("quats", vec![n, 4], &quats);
            f.insert_real("scales", vec![n, 3], &scales);
            f.insert_real("opacities", vec![n], &opac);
            f.insert_real("viewmats", vec![c, 4, 4], &vm);
            f.insert_real("Ks", vec![c, 3, 3], &ks);
            let p = fully_fused_projection(&pin, &ps)?;
            let lead = if o.packed {
                vec![p.packed_entries().len()]
            } else {
                vec![c, n]
            };
            let m: usize = lead.iter().product();
            let with = |w: usize| {
                let mut v = lead.clone();
                if w > 1 {
                    v.push(w);
                }
                v
            };
            f.insert_real("v_means2d", with(2), &to_t::<T>(&cot(seed, 0, 2 * m)));
            f.insert_real("v_depths", with(1), &to_t::<T>(&cot(seed, 1, m)));
            f.insert_real("v_conics", with(3), &to_t::<T>(&cot(seed, 2, 3 * m)));
            if o.antialiased {
                f.insert_real("v_compensations", with(1), &to_t::<T>(&cot(seed, 3, m)));
            }
        }
        ISECT | RASTERIZE => {
            let p = fully_fused_projection(&pin, &ps)?;
            let q = p.pack();
            let m = q.depths.len();
            let op: Vec<T> = q
                .gaussian_ids
                .iter()
                .enumerate()
                .map(|(i, &g)| {
                    let o = opac[g as usize];
                    q.compensations.as_ref().map_or(o, |cv| o * cv[i])
                })
                .collect();
            let tile_size = 16;
            let (tw, th) = (width.div_ceil(tile_size), height.div_ceil(tile_size));
            if stage == ISECT {
                f.set_meta("tile_size", tile_size);
                f.set_meta("tile_width", tw);
                f.set_meta("tile_height", th);
                f.set_meta("n_images", c);
                f.insert_real("means2d", vec![m, 2], &q.means2d);
                f.insert_i32("radii", vec![m, 2], q.radii.clone());
                f.insert_real("depths", vec![m], &q.depths);
                f.insert_real("conics", vec![m, 3], &q.conics);
                f.insert_real("opacities", vec![m], &op);
                f.insert_i32("image_ids", vec![m], q.camera_ids.clone());
            } else {
                let rule = if o.version.accutile() {
                    TileRule::AccuTile
                } else {
                    TileRule::RadiusBox
                };
                let is = isect_tiles(
                    &IsectInput {
                        means2d: &q.means2d,
                        radii: &q.radii,
                        depths: &q.depths,
                        conics: Some(&q.conics),
                        opacities: Some(&op),
                        image_ids: Some(&q.camera_ids),
                        n,
                    },
                    tile_size,
                    tw,
                    th,
                    c,
                    o.version,
                    rule,
                )?;
                let off = isect_offset_encode(&is.isect_ids, c, tw, th, o.version)?;
                let d = 4;
                let colors = cot(seed, 4, m * d)
                    .iter()
                    .map(|x| 0.5 + 0.3 * x)
                    .collect::<Vec<_>>();
                f.set_meta("image_width", width);
                f.set_meta("image_height", height);
                f.set_meta("tile_size", tile_size);
                f.insert_real("means2d", vec![m, 2], &q.means2d);
                f.insert_real("conics", vec![m, 3], &q.conics);
                f.insert_real("colors", vec![m, d], &to_t::<T>(&colors));
                f.insert_real("opacities", vec![m], &op);
                let bg: Vec<f64> = (0..c * d)
                    .map(|i| sc.backgrounds[i % sc.backgrounds.len()])
                    .collect();
                f.insert_real("backgrounds", vec![c, d], &to_t::<T>(&bg));
                f.insert_i32("isect_offsets", vec![c, th, tw], off);
                let ni = is.flatten_ids.len();
                f.insert_i32("flatten_ids", vec![ni], is.flatten_ids);
                let hw = width * height;
                f.insert_real(
                    "v_render_colors",
                    vec![c, height, width, d],
                    &to_t::<T>(&cot(seed, 0, c * hw * d)),
                );
                f.insert_real(
                    "v_render_alphas",
                    vec![c, height, width, 1],
                    &to_t::<T>(&cot(seed, 1, c * hw)),
                );
            }
        }
        RASTERIZATION => {
            f.set_meta("width", width);
            f.set_meta("height", height);
            f.set_meta("packed", o.packed);
            f.set_meta(
                "rasterize_mode",
                if o.antialiased {
                    "antialiased"
                } else {
                    "classic"
                },
            );
            f.set_meta("sh_degree", 3);
            f.insert_real("means", vec![n, 3], &means);
            f.insert_real("quats", vec![n, 4], &quats);
            f.insert_real("scales", vec![n, 3], &scales);
            f.insert_real("opacities", vec![n], &opac);
            f.insert_real("colors", vec![n, 16, 3], &to_t::<T>(&sc.sh));
            f.insert_real("viewmats", vec![c, 4, 4], &vm);
            f.insert_real("Ks", vec![c, 3, 3], &ks);
            f.insert_real("backgrounds", vec![c, 3], &to_t::<T>(&sc.backgrounds));
            let hw = width * height;
            f.insert_real(
                "v_render_colors",
                vec![c, height, width, 3],
                &to_t::<T>(&cot(seed, 0, c * hw * 3)),
            );
            f.insert_real(
                "v_render_alphas",
                vec![c, height, width, 1],
                &to_t::<T>(&cot(seed, 1, c * hw)),
            );
        }
        other => {
            return Err(Error::invalid(
                "stage",
                format!("`{other}` is not a gsplat stage"),
            ))
        }
    }
    Ok(f)
}
