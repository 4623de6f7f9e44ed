//! The nerfies / HyperNeRF / NeRF-DS layout (upstream `readNerfiesCameras`,
//! docs/UPSTREAM.md §6.9).
//!
//! Files: `dataset.json` (`ids`, `train_ids`, `val_ids`), `metadata.json` (per id `time_id`,
//! `camera_id`; the other keys are ignored), `scene.json` (`scale`, `center`),
//! `camera/<id>.json` (`orientation` 3×3, `position` 3, `focal_length`, `principal_point`,
//! `image_size`), `rgb/<k>x/<id>.png`, and optionally `points.npy` (`(N, 3)` float).
//!
//! - Split and image ratio: [`NerfiesSplit`]; `Auto` applies upstream's rule from the name of
//!   the dataset folder's parent (the compatible default). `nerfies_ratio` overrides the ratio.
//! - `fid = time_id / max(time_id)` over the train and test images (0 when all are 0).
//! - Camera: `position ← (position − center)·scale`; `W2C = [orientation | −orientation·position]`
//!   (already OpenCV axes); `focal ← focal_length·ratio`; `fov_y = focal2fov(focal, H)`,
//!   `fov_x = focal2fov(focal, W)` with the same focal for both. The principal point, skew,
//!   pixel aspect ratio and distortion are ignored, as upstream; a principal point more than
//!   one pixel from the image centre (after scaling) adds a warning to the dataset.
//! - Images are used as they are: the first three channels, no compositing. Their size must be
//!   `round(image_size·ratio)` (halves to even, as Python's `round`).
//! - `LoadOptions::downscale` applies the box filter on top of the ratio.
//! - Initial points: `points.npy` mapped by `(p − center)·scale`; without it, the random cube.

use super::image::{box_downscale, to_chw};
use super::{json, par_map_ordered, Dataset, DatasetKind, Frame, LoadOptions, NerfiesSplit};
use crate::camera::{focal2fov, Camera};
use crate::error::{shown, Error, Result};
use crate::gaussians::init::{InitialPoints, RANDOM_CUBE_HALF_EXTENT};
use crate::io::png::read as read_png;
use crate::math::vec::dmat3_from_rows;
use glam::DVec3;
use serde_json::Value;
use std::path::{Path, PathBuf};

/// The split rule and image ratio upstream derives from the parent folder's name.
pub fn upstream_rule(dir: &Path) -> (NerfiesSplit, f64) {
    let abs = std::fs::canonicalize(dir).unwrap_or_else(|_| dir.to_path_buf());
    let parent = abs
        .parent()
        .and_then(|p| p.file_name())
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    if parent.starts_with("vrig") {
        (NerfiesSplit::TrainVal, 0.25)
    } else if parent.starts_with("NeRF") {
        (NerfiesSplit::TrainVal, 1.0)
    } else if parent.starts_with("interp") {
        (NerfiesSplit::Interp, 0.5)
    } else {
        (NerfiesSplit::EveryFourth, 0.5)
    }
}

fn id_list(path: &Path, v: &Value, key: &str) -> Result<Vec<String>> {
    let a = json::array(path, json::get(path, v, key, key)?, key)?;
    a.iter()
        .enumerate()
        .map(|(i, x)| json::string(path, x, &format!("{key}[{i}]")).map(str::to_string))
        .collect()
}

/// Python's `round` to an integer: halves go to the even neighbour.
fn round_half_even(x: f64) -> f64 {
    let r = x.round();
    if (x - x.trunc()).abs() == 0.5 && r % 2.0 != 0.0 {
        r - x.signum()
    } else {
        r
    }
}

struct CamSpec {
    id: String,
    time: f64,
    camera: Camera,
    image: PathBuf,
}

/// Load a nerfies-layout dataset. The test split goes to `Dataset::test`; val is empty.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    // (Its images' alpha is dropped and its frames keep a black background;
    // a white one would be recorded but not used.)
    if opts.background == super::Background::White {
        return Err(Error::invalid(
            "--white-background",
            format!(
                "{}: the NeRF-DS/nerfies layout is trained on its RGB as is, on black; \
                 the option applies to the D-NeRF layout and the built-in scenes",
                dir.display()
            ),
        ));
    }
    let ds_path = dir.join("dataset.json");
    let ds = json::read(&ds_path)?;
    let (auto_split, auto_ratio) = upstream_rule(dir);
    let split = match opts.nerfies_split {
        NerfiesSplit::Auto => auto_split,
        s => s,
    };
    let ratio = opts.nerfies_ratio.unwrap_or(match opts.nerfies_split {
        NerfiesSplit::Auto => auto_ratio,
        _ => 1.0,
    });
    let folder = if ratio == 1.0 {
        "1x"
    } else if ratio == 0.5 {
        "2x"
    } else if ratio == 0.25 {
        "4x"
    } else {
        return Err(Error::invalid(
            "nerfies ratio",
            format!("{ratio} is not 1, 0.5 or 0.25"),
        ));
    };
    let (train_ids, test_ids) = match split {
        NerfiesSplit::TrainVal => (
            id_list(&ds_path, &ds, "train_ids")?,
            id_list(&ds_path, &ds, "val_ids")?,
        ),
        NerfiesSplit::Interp => {
            let ids = id_list(&ds_path, &ds, "ids")?;
            (
                ids.iter().step_by(4).cloned().collect(),
                ids.iter().skip(2).step_by(4).cloned().collect(),
            )
        }
        NerfiesSplit::EveryFourth | NerfiesSplit::Auto => {
            let ids = id_list(&ds_path, &ds, "ids")?;
            (ids.iter().step_by(4).cloned().collect(), vec![])
        }
    };
    if train_ids.is_empty() {
        return Err(Error::field(&ds_path, "ids", "empty training split"));
    }
    let meta_path = dir.join("metadata.json");
    let meta = json::read(&meta_path)?;
    let scene_path = dir.join("scene.json");
    let scene = json::read(&scene_path)?;
    let scale = json::num(
        &scene_path,
        json::get(&scene_path, &scene, "scale", "scale")?,
        "scale",
    )?;
    if !(scale > 0.0 && scale.is_finite()) {
        return Err(Error::field(
            &scene_path,
            "scale",
            format!("{} (must be finite and > 0)", shown(scale)),
        ));
    }
    let center = json::vector(
        &scene_path,
        json::get(&scene_path, &scene, "center", "center")?,
        3,
        "center",
    )?;

    let time_id = |id: &str| -> Result<f64> {
        let f = format!("{id}.time_id");
        let entry = json::get(&meta_path, &meta, id, id)?;
        let t = json::num(&meta_path, json::get(&meta_path, entry, "time_id", &f)?, &f)?;
        if !(t >= 0.0 && t.is_finite()) {
            return Err(Error::field(
                &meta_path,
                &f,
                format!("{} (must be finite and >= 0)", shown(t)),
            ));
        }
        Ok(t)
    };
    let mut max_t = 0.0f64;
    for id in train_ids.iter().chain(&test_ids) {
        max_t = max_t.max(time_id(id)?);
    }
    let mut warnings = Vec::new();
    let mut spec = |id: &String| -> Result<CamSpec> {
        let cp = dir.join("camera").join(format!("{id}.json"));
        let c = json::read(&cp)?;
        let o = json::matrix(
            &cp,
            json::get(&cp, &c, "orientation", "orientation")?,
            3,
            3,
            "orientation",
        )?;
        let p = json::vector(
            &cp,
            json::get(&cp, &c, "position", "position")?,
            3,
            "position",
        )?;
        let focal = json::num(
            &cp,
            json::get(&cp, &c, "focal_length", "focal_length")?,
            "focal_length",
        )? * ratio;
        let size = json::vector(
            &cp,
            json::get(&cp, &c, "image_size", "image_size")?,
            2,
            "image_size",
        )?;
        let w = round_half_even(size[0] * ratio);
        let h = round_half_even(size[1] * ratio);
        if !(w >= 1.0 && h >= 1.0 && w * h <= crate::render::MAX_PIXELS as f64) {
            return Err(Error::field(
                &cp,
                "image_size",
                format!(
                    "{}x{} pixels at this scale (each side at least 1, at most {} pixels)",
                    shown(w),
                    shown(h),
                    crate::render::MAX_PIXELS
                ),
            ));
        }
        // Both fields of view in [1e-6, pi - 1e-6], as D-NeRF's
        // `camera_angle_x` (narrower ones give a tangent that rounds to 0 in
        // f32; a focal length of 1e308 gave 1e-308).
        let (fx, fy) = (focal2fov(focal, w), focal2fov(focal, h));
        let fovs = super::FOV_RANGE;
        if !(focal > 0.0 && fovs.contains(&fx) && fovs.contains(&fy)) {
            return Err(Error::field(
                &cp,
                "focal_length",
                format!(
                    "{} pixels at this scale for a {w}x{h} image: fields of view {} and {} \
                     radians (each must be in [1e-6, pi - 1e-6])",
                    shown(focal),
                    shown(fx),
                    shown(fy)
                ),
            ));
        }
        let (w, h) = (w as usize, h as usize);
        if let Some(pp) = c.get("principal_point") {
            let pp = json::vector(&cp, pp, 2, "principal_point")?;
            let (dx, dy) = (
                pp[0] * ratio - w as f64 / 2.0,
                pp[1] * ratio - h as f64 / 2.0,
            );
            if dx.abs() > 1.0 || dy.abs() > 1.0 {
                warnings.push(format!(
                    "{}: principal point is ({dx:.2}, {dy:.2}) pixels from the image centre; it is ignored",
                    cp.display()
                ));
            }
        }
        let pos: Vec<f64> = (0..3).map(|a| (p[a] - center[a]) * scale).collect();
        let rot = [
            [o[0][0], o[0][1], o[0][2]],
            [o[1][0], o[1][1], o[1][2]],
            [o[2][0], o[2][1], o[2][2]],
        ];
        crate::camera::check_rotation(&rot).map_err(|w| Error::field(&cp, "orientation", w))?;
        let t = (-(dmat3_from_rows(&rot) * DVec3::from_slice(&pos))).to_array();
        let r = opts.downscale;
        // The box filter takes whole r×r blocks: a size it does not divide
        // would give a camera of another size than the filtered image.
        if !w.is_multiple_of(r) || !h.is_multiple_of(r) {
            return Err(Error::field(
                &cp,
                "image_size",
                format!(
                    "{w}x{h} pixels at this scale ({folder}) are not divisible by the \
                     downscale factor {r} (--downscale)"
                ),
            ));
        }
        let camera = Camera::from_w2c(rot, t, fx, fy, w, h)
            .map_err(|e| Error::field(&cp, "orientation/position", e.to_string()))?;
        let time = if max_t > 0.0 {
            time_id(id)? / max_t
        } else {
            0.0
        };
        Ok(CamSpec {
            id: id.clone(),
            time,
            camera: if r == 1 {
                camera
            } else {
                camera.with_size(w / r, h / r)
            },
            image: dir.join("rgb").join(folder).join(format!("{id}.png")),
        })
    };
    let train: Vec<CamSpec> = train_ids.iter().map(&mut spec).collect::<Result<_>>()?;
    let test: Vec<CamSpec> = test_ids.iter().map(&mut spec).collect::<Result<_>>()?;
    let centres: Vec<[f64; 3]> = train.iter().map(|c| c.camera.centre()).collect();

    let load_split = |cams: &[CamSpec]| -> Result<Vec<Frame>> {
        par_map_ordered(cams, |c| {
            let img = read_png(&c.image)?;
            let r = opts.downscale;
            let (w, h) = (c.camera.width * r, c.camera.height * r);
            if (img.width, img.height) != (w, h) {
                return Err(Error::format(
                    &c.image,
                    format!(
                        "image is {}x{}, its camera says {w}x{h}",
                        img.width, img.height
                    ),
                ));
            }
            let rgb = box_downscale(&c.image, &img.rgb(), w, h, r)?;
            Ok(Frame {
                name: c.id.clone(),
                camera: c.camera.clone(),
                time: c.time,
                image: to_chw(&rgb, w / r, h / r),
                width: w / r,
                height: h / r,
            })
        })
    };
    let train_frames = if opts.splits.train {
        load_split(&train)?
    } else {
        vec![]
    };
    let test_frames = if opts.splits.test {
        load_split(&test)?
    } else {
        vec![]
    };

    let npy = dir.join("points.npy");
    // (As the D-NeRF loader's points3d.ply: anything of that name is read.)
    let init = if npy.exists() {
        let mut xyz = super::npy::read_points(&npy)?;
        crate::gaussians::init::check_count(xyz.len() / 3)
            .map_err(|w| Error::field(&npy, "points", w))?;
        for (k, v) in xyz.iter_mut().enumerate() {
            *v = (*v - center[k % 3]) * scale;
        }
        if let Some(k) = crate::gaussians::init::first_unusable_coordinate(&xyz) {
            return Err(Error::field(
                &npy,
                "points",
                format!(
                    "point {}: coordinate {:e} of (p − center)·scale is beyond the f32 range \
                     (positions are stored as f32)",
                    k / 3,
                    xyz[k]
                ),
            ));
        }
        InitialPoints::Cloud { xyz, rgb: None }
    } else {
        InitialPoints::RandomCube {
            count: opts.init_points,
            half_extent: RANDOM_CUBE_HALF_EXTENT,
            seed: opts.init_seed,
        }
    };
    Ok(Dataset {
        kind: DatasetKind::Nerfies,
        train: train_frames,
        val: vec![],
        test: test_frames,
        white_background: false,
        scene_extent: super::finite_scene_extent(
            &centres,
            &dir.join("camera"),
            "position (with scene.json's center and scale)",
        )?,
        init,
        warnings,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn python_rounding() {
        assert_eq!(round_half_even(2.5), 2.0);
        assert_eq!(round_half_even(3.5), 4.0);
        assert_eq!(round_half_even(3.4), 3.0);
        assert_eq!(round_half_even(270.0), 270.0);
    }

    #[test]
    fn rule_from_parent_name() {
        assert_eq!(
            upstream_rule(Path::new("/x/NeRF-DS/as")),
            (NerfiesSplit::TrainVal, 1.0)
        );
        assert_eq!(
            upstream_rule(Path::new("/x/vrig/b")),
            (NerfiesSplit::TrainVal, 0.25)
        );
        assert_eq!(
            upstream_rule(Path::new("/x/interp/b")),
            (NerfiesSplit::Interp, 0.5)
        );
        assert_eq!(
            upstream_rule(Path::new("/x/other/b")),
            (NerfiesSplit::EveryFourth, 0.5)
        );
    }
}
