//! Built-in dynamic scenes drawn by an analytic ray caster ([`scene`]), written to disk in the
//! D-NeRF layout (and optionally the nerfies layout) or built in memory by [`builtin`].
//!
//! Capture (D-NeRF-like, monocular): every frame has its own time and its own camera. Cameras
//! sit at distance `radius` from the origin and look at it, world z up. Camera `i` of a split:
//! - [`Orbit::Hemisphere`]: azimuth uniform in `[0, 2π)` and elevation uniform in
//!   `[10°, 60°]`, drawn from `Rng::stream(seed, split_index·2³² + i)`;
//! - [`Orbit::Circle`]: azimuth `2π·i/n` (plus a split-dependent offset), elevation 30°.
//!
//! Times: train frame `i` of `n` has `t = i/(n−1)`; val and test frame `k` of `m` have
//! `t = (k + ¼)/m` and `(k + ¾)/m`, between the training times.
//!
//! Determinism: the same options give the same bytes (fixed PNG encoder settings, JSON
//! written by serde_json with shortest round-trip floats, all randomness seeded).

pub mod scene;

pub use scene::SceneName;

use super::dnerf::fov_pair;
use super::image::{composite, to_chw};
use super::{scene_extent, Background, Dataset, DatasetKind, Frame};
use crate::camera::Camera;
use crate::error::{Error, Result};
use crate::gaussians::init::{InitialPoints, RANDOM_CUBE_HALF_EXTENT};
use crate::io::png::{encode as encode_png, Image8};
use crate::math::Rng;
use serde_json::{json, Value};
use std::path::Path;

/// How the cameras are placed.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Orbit {
    /// Random positions on the upper hemisphere (D-NeRF-like).
    #[default]
    Hemisphere,
    /// Evenly spaced on a circle at 30° elevation.
    Circle,
}

/// Options of the scene generator.
#[derive(Clone, Debug, PartialEq)]
pub struct SynthOptions {
    /// Image width and height in pixels.
    pub resolution: usize,
    /// Training frames.
    pub frames: usize,
    /// Frames in each of the val and test splits.
    pub eval_frames: usize,
    /// Seed of the camera placement and the initial points.
    pub seed: u64,
    /// How the cameras are placed.
    pub orbit: Orbit,
    /// Camera distance from the origin.
    pub radius: f64,
    /// Horizontal (= vertical) field of view, radians.
    pub fov: f64,
    /// Sub-pixel samples per axis (`ss × ss` per pixel).
    pub supersampling: usize,
    /// Background for [`builtin`] (files keep alpha).
    pub background: Background,
    /// Random initial points for [`builtin`].
    pub init_points: usize,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            resolution: 64,
            frames: 24,
            eval_frames: 8,
            seed: 0,
            orbit: Orbit::Hemisphere,
            radius: 4.0,
            fov: 0.6911112070083618,
            supersampling: 4,
            background: Background::Black,
            init_points: crate::gaussians::init::DEFAULT_RANDOM_POINTS,
        }
    }
}

/// Which on-disk layout [`write`](fn@write) produces.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Layout {
    /// `transforms_{train,val,test}.json` and RGBA PNGs (see [`super::dnerf`]).
    #[default]
    DNerf,
    /// `dataset.json`, `metadata.json`, `camera/` and RGB PNGs at 1x, 2x and 4x (see
    /// [`super::nerfies`]).
    Nerfies,
}

/// The most frames per split a built-in scene may have.
pub const MAX_FRAMES: usize = 4096;
/// The most pixels of all a built-in scene's images together (3 GiB of f32
/// RGB).
pub const MAX_TOTAL_PIXELS: usize = 1 << 28;

impl SynthOptions {
    fn check(&self) -> Result<()> {
        if !(1..=4096).contains(&self.resolution) {
            return Err(Error::invalid(
                "resolution",
                format!("{} is not in 1..=4096", self.resolution),
            ));
        }
        if self.frames > MAX_FRAMES || self.eval_frames > MAX_FRAMES {
            return Err(Error::invalid(
                "frames",
                format!(
                    "{} train and {} evaluation frames, more than the limit {MAX_FRAMES}",
                    self.frames, self.eval_frames
                ),
            ));
        }
        let views = self.frames + 2 * self.eval_frames;
        if views.saturating_mul(self.resolution * self.resolution) > MAX_TOTAL_PIXELS {
            return Err(Error::invalid(
                "frames",
                format!(
                    "{views} images of {0}x{0} pixels, more than {MAX_TOTAL_PIXELS} pixels in all",
                    self.resolution
                ),
            ));
        }
        crate::gaussians::init::check_count(self.init_points)
            .map_err(|w| Error::invalid("init_points", w))?;
        if self.frames == 0 || self.eval_frames == 0 {
            return Err(Error::invalid(
                "frames",
                "every split needs at least one frame",
            ));
        }
        if !(1..=16).contains(&self.supersampling) {
            return Err(Error::invalid(
                "supersampling",
                format!("{} is not in 1..=16", self.supersampling),
            ));
        }
        if !(self.fov > 0.0 && self.fov < 3.0 && self.radius > 2.0 && self.radius.is_finite()) {
            return Err(Error::invalid(
                "camera",
                "fov must be in (0, 3) and radius finite and > 2",
            ));
        }
        Ok(())
    }
}

/// A rendered frame before compositing: name, OpenGL camera-to-world, time, RGBA bytes.
struct RawFrame {
    name: String,
    c2w: [[f64; 4]; 4],
    time: f64,
    rgba: Vec<u8>,
}

/// The OpenGL camera-to-world matrix of a camera at `eye` looking at the origin, z up.
fn c2w_at(eye: [f64; 3]) -> Result<[[f64; 4]; 4]> {
    let cam = Camera::look_at(eye, [0.0; 3], [0.0, 0.0, 1.0], 1.0, 1.0, 1, 1)?;
    let r = cam.rotation;
    let mut m = [[0.0; 4]; 4];
    for i in 0..3 {
        m[i] = [r[0][i], -r[1][i], -r[2][i], eye[i]];
    }
    m[3] = [0.0, 0.0, 0.0, 1.0];
    Ok(m)
}

fn eye(opts: &SynthOptions, split: u64, i: usize, n: usize) -> [f64; 3] {
    let (az, el) = match opts.orbit {
        Orbit::Hemisphere => {
            let mut r = Rng::stream(opts.seed, (split << 32) + i as u64);
            let az = 2.0 * std::f64::consts::PI * r.uniform();
            let el = (10.0 + 50.0 * r.uniform()).to_radians();
            (az, el)
        }
        Orbit::Circle => (
            2.0 * std::f64::consts::PI * (i as f64 + 0.37 * split as f64) / n as f64,
            30f64.to_radians(),
        ),
    };
    let (ce, se) = (libm::cos(el), libm::sin(el));
    [
        opts.radius * ce * libm::cos(az),
        opts.radius * ce * libm::sin(az),
        opts.radius * se,
    ]
}

fn split_times(split: u64, n: usize) -> Vec<f64> {
    match split {
        0 => (0..n)
            .map(|i| {
                if n == 1 {
                    0.0
                } else {
                    i as f64 / (n - 1) as f64
                }
            })
            .collect(),
        1 => (0..n).map(|k| (k as f64 + 0.25) / n as f64).collect(),
        _ => (0..n).map(|k| (k as f64 + 0.75) / n as f64).collect(),
    }
}

/// The camera the loader builds from a camera-to-world matrix (shared so that [`builtin`]
/// equals loading the written files).
fn camera_of(c2w: [[f64; 4]; 4], opts: &SynthOptions) -> Result<Camera> {
    let res = opts.resolution;
    let (fx, fy) = fov_pair(opts.fov, res, res);
    Camera::from_c2w_opengl(c2w, fx, fy, res, res)
}

/// Render the frames of one split (0 train, 1 val, 2 test), in parallel, in order.
fn render_split(name: SceneName, opts: &SynthOptions, split: u64) -> Result<Vec<RawFrame>> {
    let n = if split == 0 {
        opts.frames
    } else {
        opts.eval_frames
    };
    let times = split_times(split, n);
    let items: Vec<usize> = (0..n).collect();
    super::par_map_ordered(&items, |&i| {
        let c2w = c2w_at(eye(opts, split, i, n))?;
        let cam = camera_of(c2w, opts)?;
        let rgba = scene::render(&name.shapes(times[i]), &cam, opts.supersampling);
        Ok(RawFrame {
            name: format!("r_{i:03}"),
            c2w,
            time: times[i],
            rgba,
        })
    })
}

const SPLITS: [&str; 3] = ["train", "val", "test"];

/// Build a built-in scene in memory, as [`super::load`] would load it from the D-NeRF files
/// [`write`](fn@write) produces (same pixels, cameras and times), with `opts.background` and random
/// initial points in `[-1.3, 1.3)³` (no `points3d.ply`).
pub fn builtin(name: &str, opts: &SynthOptions) -> Result<Dataset> {
    let scene = SceneName::parse_named("scene name", name)?;
    opts.check()?;
    let res = opts.resolution;
    let mut splits: Vec<Vec<Frame>> = Vec::new();
    let mut centres = Vec::new();
    for split in 0..3u64 {
        let raw = render_split(scene, opts, split)?;
        let mut frames = Vec::with_capacity(raw.len());
        for f in raw {
            if split == 0 {
                centres.push([f.c2w[0][3], f.c2w[1][3], f.c2w[2][3]]);
            }
            let img = Image8 {
                width: res,
                height: res,
                channels: 4,
                data: f.rgba,
            };
            frames.push(Frame {
                name: f.name,
                camera: camera_of(f.c2w, opts)?,
                time: f.time,
                image: to_chw(&composite(&img, opts.background), res, res),
                width: res,
                height: res,
            });
        }
        splits.push(frames);
    }
    let mut it = splits.into_iter();
    Ok(Dataset {
        kind: DatasetKind::Synthetic,
        train: it.next().unwrap_or_default(),
        val: it.next().unwrap_or_default(),
        test: it.next().unwrap_or_default(),
        white_background: opts.background == Background::White,
        scene_extent: scene_extent(&centres),
        init: InitialPoints::RandomCube {
            count: opts.init_points,
            half_extent: RANDOM_CUBE_HALF_EXTENT,
            seed: opts.seed,
        },
        warnings: vec![],
    })
}

fn write_json(path: &Path, v: &Value) -> Result<()> {
    let mut s =
        serde_json::to_string_pretty(v).map_err(|e| Error::invalid("JSON", e.to_string()))?;
    s.push('\n');
    crate::io::write_atomic(path, s.as_bytes())
}

fn mkdir(p: &Path) -> Result<()> {
    crate::io::create_dir_all(p)
}

/// Generate scene `name` into `out` in the given layout.
pub fn write(name: &str, out: &Path, opts: &SynthOptions, layout: Layout) -> Result<()> {
    let scene = SceneName::parse_named("scene name", name)?;
    opts.check()?;
    match layout {
        Layout::DNerf => write_dnerf(scene, out, opts),
        Layout::Nerfies => write_nerfies(scene, out, opts),
    }
}

fn write_dnerf(scene: SceneName, out: &Path, opts: &SynthOptions) -> Result<()> {
    let res = opts.resolution;
    for (split, sname) in SPLITS.iter().enumerate() {
        let raw = render_split(scene, opts, split as u64)?;
        mkdir(&out.join(sname))?;
        let mut frames = Vec::new();
        for f in &raw {
            let png = encode_png(res, res, 4, &f.rgba)?;
            crate::io::write_atomic(&out.join(sname).join(format!("{}.png", f.name)), &png)?;
            frames.push(json!({
                "file_path": format!("./{sname}/{}", f.name),
                "time": f.time,
                "transform_matrix": f.c2w.iter().map(|r| r.to_vec()).collect::<Vec<_>>(),
            }));
        }
        write_json(
            &out.join(format!("transforms_{sname}.json")),
            &json!({ "camera_angle_x": opts.fov, "frames": frames }),
        )?;
    }
    Ok(())
}

/// Nerfies layout: one monocular sequence of `frames` images (train = even, val = odd ids),
/// cameras on the orbit, `rgb/{1x,2x,4x}` (the smaller ones box-downscaled when divisible),
/// images composited on `opts.background`, `points.npy` with 2000 surface points at time 0.
fn write_nerfies(scene: SceneName, out: &Path, opts: &SynthOptions) -> Result<()> {
    let res = opts.resolution;
    let n = opts.frames;
    let times = split_times(0, n);
    let items: Vec<usize> = (0..n).collect();
    let rendered = super::par_map_ordered(&items, |&i| {
        let e = eye(opts, 0, i, n);
        let cam = Camera::look_at(e, [0.0; 3], [0.0, 0.0, 1.0], opts.fov, opts.fov, res, res)?;
        let rgba = scene::render(&scene.shapes(times[i]), &cam, opts.supersampling);
        Ok((cam, rgba))
    })?;
    let ids: Vec<String> = (0..n).map(|i| format!("{i:05}")).collect();
    for k in ["camera", "rgb/1x", "rgb/2x", "rgb/4x"] {
        mkdir(&out.join(k))?;
    }
    let mut meta = serde_json::Map::new();
    for (i, (cam, rgba)) in rendered.iter().enumerate() {
        let id = &ids[i];
        let img = Image8 {
            width: res,
            height: res,
            channels: 4,
            data: rgba.clone(),
        };
        let rgb = composite(&img, opts.background);
        for r in [1usize, 2, 4] {
            if res.is_multiple_of(r) {
                let small = super::image::box_downscale(out, &rgb, res, res, r)?;
                let png = encode_png(res / r, res / r, 3, &small)?;
                crate::io::write_atomic(&out.join(format!("rgb/{r}x/{id}.png")), &png)?;
            }
        }
        let (f, _) = cam.focal();
        write_json(
            &out.join(format!("camera/{id}.json")),
            &json!({
                "orientation": cam.rotation.iter().map(|r| r.to_vec()).collect::<Vec<_>>(),
                "position": cam.centre().to_vec(),
                "focal_length": f,
                "principal_point": [res as f64 / 2.0, res as f64 / 2.0],
                "skew": 0.0,
                "pixel_aspect_ratio": 1.0,
                "radial_distortion": [0.0, 0.0, 0.0],
                "tangential_distortion": [0.0, 0.0],
                "image_size": [res, res],
            }),
        )?;
        meta.insert(
            id.clone(),
            json!({"time_id": i, "warp_id": i, "appearance_id": i, "camera_id": 0}),
        );
    }
    write_json(&out.join("metadata.json"), &Value::Object(meta))?;
    write_json(
        &out.join("dataset.json"),
        &json!({
            "count": n,
            "num_exemplars": n.div_ceil(2),
            "ids": ids,
            "train_ids": ids.iter().step_by(2).collect::<Vec<_>>(),
            "val_ids": ids.iter().skip(1).step_by(2).collect::<Vec<_>>(),
        }),
    )?;
    write_json(
        &out.join("scene.json"),
        &json!({"scale": 1.0, "center": [0.0, 0.0, 0.0], "near": 0.1, "far": 2.0 * opts.radius}),
    )?;
    let pts: Vec<f32> = scene
        .surface_points(2000, opts.seed)
        .iter()
        .map(|&v| v as f32)
        .collect();
    crate::io::write_atomic(
        &out.join("points.npy"),
        &super::npy::encode_points_f32(&pts),
    )?;
    Ok(())
}
