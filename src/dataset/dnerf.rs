//! The D-NeRF (Blender) layout: `transforms_{train,val,test}.json` and RGBA PNGs.
//!
//! Each `transforms_<split>.json` holds `camera_angle_x` (the horizontal field of view in
//! radians) and `frames`, each with `file_path` (relative, without `.png`), `time` (in
//! `[0, 1]`, used as `fid`) and `transform_matrix` (4×4 camera-to-world, Blender/OpenGL axes:
//! x right, y up, z backward). Other keys and other files (e.g. `transforms.json` inside split
//! folders) are ignored. Upstream reads only train and test; val is read here too.
//!
//! **Images** are converted to RGBA and composited exactly as upstream does
//! ([`super::image::composite`]), then optionally box-downscaled
//! ([`super::image::box_downscale`]), then divided by 255 in f32.
//!
//! **Field of view.** Upstream computes `fovy = focal2fov(fov2focal(fovx, W), H)` and then
//! stores `FovY = fovx`, `FovX = fovy`: the two are swapped. For square images (all of
//! D-NeRF) that is harmless and this loader reproduces it bit for bit (`fov_x` is the round
//! trip, `fov_y` is `camera_angle_x`). For non-square images the swap would stretch the image,
//! so there this loader uses the correct assignment `fov_x = camera_angle_x`,
//! `fov_y = focal2fov(fov2focal(fovx, W), H)`.
//!
//! **Axes.** Cameras are built with the correct conversion [`Camera::from_c2w_opengl`]
//! (`W2C = inverse(C2W · diag(1, −1, −1, 1))`). Upstream instead computes
//! `Mi = inverse(C2W)`, `W2C rotation = diag(1, −1, −1)·Mi[:3,:3]` (correct) and
//! `W2C translation = −Mi[:3, 3]`, which has the wrong sign in its x component. The two agree
//! when the optical axis passes through the world origin, as in every D-NeRF camera.
//! [`upstream_w2c`] implements upstream's formula for comparison.

use super::image::{box_downscale, composite, to_chw};
use super::{json, par_map_ordered, Dataset, DatasetKind, Frame, LoadOptions};
use crate::camera::{focal2fov, fov2focal, Camera};
use crate::error::{Error, Result};
use crate::gaussians::init::{InitialPoints, RANDOM_CUBE_HALF_EXTENT};
use crate::io::png::read as read_png;
use crate::math::vec::{dmat4_from_rows, dmat4_rows};
use std::path::{Path, PathBuf};

/// One frame as described by a transforms file, before its image is read.
#[derive(Clone, Debug)]
struct FrameSpec {
    name: String,
    image: PathBuf,
    c2w: [[f64; 4]; 4],
    time: f64,
}

struct SplitSpec {
    file: PathBuf,
    fov: f64,
    frames: Vec<FrameSpec>,
}

fn read_split(dir: &Path, split: &str) -> Result<SplitSpec> {
    let file = dir.join(format!("transforms_{split}.json"));
    let v = json::read(&file)?;
    let fov = json::num(
        &file,
        json::get(&file, &v, "camera_angle_x", "camera_angle_x")?,
        "camera_angle_x",
    )?;
    if !super::FOV_RANGE.contains(&fov) {
        return Err(Error::field(
            &file,
            "camera_angle_x",
            format!("{fov:?} is not in [1e-6, pi - 1e-6] radians"),
        ));
    }
    let frames_v = json::array(&file, json::get(&file, &v, "frames", "frames")?, "frames")?;
    if frames_v.is_empty() {
        return Err(Error::field(&file, "frames", "empty split (no frames)"));
    }
    let mut frames = Vec::with_capacity(frames_v.len());
    for (i, f) in frames_v.iter().enumerate() {
        let fp_field = format!("frames[{i}].file_path");
        let fp = json::string(
            &file,
            json::get(&file, f, "file_path", &fp_field)?,
            &fp_field,
        )?;
        let t_field = format!("frames[{i}].time");
        let time = json::num(&file, json::get(&file, f, "time", &t_field)?, &t_field)?;
        if !(0.0..=1.0).contains(&time) {
            return Err(Error::field(
                &file,
                &t_field,
                format!("{} is not in [0, 1]", crate::error::shown(time)),
            ));
        }
        let m_field = format!("frames[{i}].transform_matrix");
        let m = json::matrix(
            &file,
            json::get(&file, f, "transform_matrix", &m_field)?,
            4,
            4,
            &m_field,
        )?;
        let mut c2w = [[0.0; 4]; 4];
        for r in 0..4 {
            c2w[r].copy_from_slice(&m[r]);
        }
        crate::camera::check_rigid(&c2w).map_err(|w| Error::field(&file, &m_field, w))?;
        let image = dir.join(format!("{fp}.png"));
        let name = Path::new(fp)
            .file_name()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| fp.to_string());
        frames.push(FrameSpec {
            name,
            image,
            c2w,
            time,
        });
    }
    Ok(SplitSpec { file, fov, frames })
}

/// Upstream's field-of-view pair `(fov_x, fov_y)` for an image of `w × h` (see the module
/// documentation for the swap).
pub fn fov_pair(camera_angle_x: f64, w: usize, h: usize) -> (f64, f64) {
    let other = focal2fov(fov2focal(camera_angle_x, w as f64), h as f64);
    if w == h {
        (other, camera_angle_x)
    } else {
        (camera_angle_x, other)
    }
}

fn load_frames(spec: &SplitSpec, opts: &LoadOptions) -> Result<Vec<Frame>> {
    let r = opts.downscale;
    par_map_ordered(&spec.frames, |f| {
        let img = read_png(&f.image)?;
        let rgb = composite(&img, opts.background);
        let rgb = box_downscale(&f.image, &rgb, img.width, img.height, r)?;
        let (w, h) = (img.width / r, img.height / r);
        let (fx, fy) = fov_pair(spec.fov, w, h);
        let camera = Camera::from_c2w_opengl(f.c2w, fx, fy, w, h)
            .map_err(|e| Error::field(&spec.file, format!("frame {}", f.name), e.to_string()))?;
        Ok(Frame {
            name: f.name.clone(),
            camera,
            time: f.time,
            image: to_chw(&rgb, w, h),
            width: w,
            height: h,
        })
    })
}

/// Every image of a dataset must have the size of the first one.
pub(crate) fn check_sizes(dataset_files: &[(&[Frame], &[PathBuf])]) -> Result<()> {
    let mut first: Option<(usize, usize, &PathBuf)> = None;
    for (frames, files) in dataset_files {
        for (f, file) in frames.iter().zip(files.iter()) {
            match first {
                None => first = Some((f.width, f.height, file)),
                Some((w, h, first_file)) if (w, h) != (f.width, f.height) => {
                    return Err(Error::format(
                        file,
                        format!(
                            "image is {}x{} after downscaling, but {} (the dataset's first image) is {w}x{h}: every image must have one size",
                            f.width,
                            f.height,
                            first_file.display()
                        ),
                    ));
                }
                _ => {}
            }
        }
    }
    Ok(())
}

/// Load a D-NeRF-layout dataset. `transforms_train.json` and `transforms_test.json` are
/// required; a missing `transforms_val.json` gives an empty val split and a warning.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    let train = read_split(dir, "train")?;
    let test = read_split(dir, "test")?;
    let val_file = dir.join("transforms_val.json");
    let mut warnings = Vec::new();
    let val = if val_file.is_file() {
        Some(read_split(dir, "val")?)
    } else {
        warnings.push(format!("{}: absent, no val split", val_file.display()));
        None
    };
    let centres: Vec<[f64; 3]> = train
        .frames
        .iter()
        .map(|f| [f.c2w[0][3], f.c2w[1][3], f.c2w[2][3]])
        .collect();
    let mut sets: Vec<(Vec<Frame>, Vec<PathBuf>)> = Vec::new();
    for (want, spec) in [
        (opts.splits.train, Some(&train)),
        (opts.splits.val, val.as_ref()),
        (opts.splits.test, Some(&test)),
    ] {
        match spec {
            Some(s) if want => sets.push((
                load_frames(s, opts)?,
                s.frames.iter().map(|f| f.image.clone()).collect(),
            )),
            _ => sets.push((vec![], vec![])),
        }
    }
    check_sizes(
        &sets
            .iter()
            .map(|(f, p)| (f.as_slice(), p.as_slice()))
            .collect::<Vec<_>>(),
    )?;
    let points = dir.join("points3d.ply");
    // (Anything of that name is read: a folder or a pipe there is an error,
    // not random points without a word.)
    let init = if points.exists() {
        let pc = crate::gaussians::ply::read_points(&points)?;
        crate::gaussians::init::check_count(pc.len())
            .map_err(|w| Error::field(&points, "vertex", w))?;
        if let Some(k) = crate::gaussians::init::first_unusable_coordinate(&pc.xyz) {
            return Err(Error::field(
                &points,
                format!("vertex.{}", ["x", "y", "z"][k % 3]),
                format!(
                    "vertex {}: {:e} is beyond the f32 range (positions are stored as f32)",
                    k / 3,
                    pc.xyz[k]
                ),
            ));
        }
        InitialPoints::Cloud {
            xyz: pc.xyz,
            rgb: pc.rgb,
        }
    } else {
        InitialPoints::RandomCube {
            count: opts.init_points,
            half_extent: RANDOM_CUBE_HALF_EXTENT,
            seed: opts.init_seed,
        }
    };
    let mut it = sets.into_iter().map(|(f, _)| f);
    Ok(Dataset {
        kind: DatasetKind::DNerf,
        train: it.next().unwrap_or_default(),
        val: it.next().unwrap_or_default(),
        test: it.next().unwrap_or_default(),
        white_background: opts.background == super::Background::White,
        scene_extent: super::finite_scene_extent(
            &centres,
            &dir.join("transforms_train.json"),
            "transform_matrix",
        )?,
        init,
        warnings,
    })
}

/// Upstream's D-NeRF camera conversion, for comparison only: returns the world-to-camera
/// rotation and translation `(diag(1,−1,−1)·Mi[:3,:3], −Mi[:3,3])` with `Mi = inverse(c2w)`.
/// The translation's x sign is wrong unless the camera looks through the origin; the loader
/// uses [`Camera::from_c2w_opengl`] instead.
pub fn upstream_w2c(c2w: [[f64; 4]; 4]) -> Result<([[f64; 3]; 3], [f64; 3])> {
    let m = dmat4_from_rows(&c2w);
    let det = m.determinant();
    if det == 0.0 || !det.is_finite() {
        return Err(Error::invalid("transform_matrix", "not invertible"));
    }
    let mi = dmat4_rows(&m.inverse());
    let mut r = [[0.0; 3]; 3];
    for i in 0..3 {
        let s = if i == 0 { 1.0 } else { -1.0 };
        for j in 0..3 {
            r[i][j] = s * mi[i][j];
        }
    }
    let t = [-mi[0][3], -mi[1][3], -mi[2][3]];
    Ok((r, t))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::Rng;

    /// An OpenGL camera-to-world matrix for a camera at `eye` looking at `target` (z up).
    fn c2w_looking_at(eye: [f64; 3], target: [f64; 3]) -> [[f64; 4]; 4] {
        let cam = Camera::look_at(eye, target, [0.0, 0.0, 1.0], 0.7, 0.7, 8, 8).unwrap();
        // OpenCV c2w rotation is Rᵀ; OpenGL flips the y and z camera axes.
        let r = cam.rotation;
        let mut m = [[0.0; 4]; 4];
        for i in 0..3 {
            m[i] = [r[0][i], -r[1][i], -r[2][i], eye[i]];
        }
        m[3] = [0.0, 0.0, 0.0, 1.0];
        m
    }

    #[test]
    fn upstream_formula_agrees_for_cameras_looking_at_the_origin() {
        let mut rng = Rng::new(11);
        for _ in 0..50 {
            let eye = [
                rng.uniform_range(-4.0, 4.0),
                rng.uniform_range(-4.0, 4.0),
                rng.uniform_range(0.5, 4.0),
            ];
            let c2w = c2w_looking_at(eye, [0.0; 3]);
            let cam = Camera::from_c2w_opengl(c2w, 0.7, 0.7, 8, 8).unwrap();
            let (r, t) = upstream_w2c(c2w).unwrap();
            for i in 0..3 {
                assert!(
                    (t[i] - cam.translation[i]).abs() < 1e-12,
                    "{t:?} {:?}",
                    cam.translation
                );
                for (a, b) in r[i].iter().zip(&cam.rotation[i]) {
                    assert!((a - b).abs() < 1e-12);
                }
            }
            // Looking elsewhere, the x translation has the opposite sign.
            let c2w = c2w_looking_at(eye, [1.0, 0.5, 0.2]);
            let cam = Camera::from_c2w_opengl(c2w, 0.7, 0.7, 8, 8).unwrap();
            let (_, t) = upstream_w2c(c2w).unwrap();
            assert!((t[0] + cam.translation[0]).abs() < 1e-12);
            assert!((t[1] - cam.translation[1]).abs() < 1e-12);
            assert!(cam.translation[0].abs() > 1e-3);
        }
    }

    #[test]
    fn fov_pair_square_and_not() {
        let (fx, fy) = fov_pair(0.6911112070083618, 800, 800);
        assert_eq!(fy, 0.6911112070083618);
        assert_eq!(
            fx, 0.6911112070083618,
            "this value round-trips exactly (docs/UPSTREAM.md §6.9)"
        );
        let (fx, fy) = fov_pair(0.8, 200, 100);
        assert_eq!(fx, 0.8);
        assert!((libm::tan(fy / 2.0) - libm::tan(0.4) / 2.0).abs() < 1e-12);
    }
}
