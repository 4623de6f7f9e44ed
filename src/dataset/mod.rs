//! Files → frames: each frame an image, a camera and a time.
//!
//! [`load`] detects the layout by the files present, as upstream's `Scene` does:
//! `transforms_train.json` → D-NeRF ([`dnerf`]); `dataset.json` → nerfies / NeRF-DS / HyperNeRF
//! ([`nerfies`]). [`synth::builtin`] makes a dataset in memory from a built-in analytic scene.
//!
//! Conventions shared by every loader:
//! - `Frame::image` is channel-major `[3, H, W]` f32 in `[0, 1]`, each value a byte divided by
//!   255 in f32 (upstream's `PILtoTorch`), so the images are exactly 8-bit quantised.
//! - `Frame::time` is the deformation field's time `fid` in `[0, 1]`.
//! - `Dataset::scene_extent` is upstream's `cameras_extent`: 1.1 × the largest distance of a
//!   training camera centre from the mean of the training camera centres.
//! - Loading is parallel over frames and deterministic: the frames come in file order and the
//!   first failing frame (in file order) is the error reported.

pub mod dnerf;
pub mod image;
mod json;
pub mod nerfies;
pub mod npy;
pub mod synth;

use crate::gaussians::init;
/// Initial points and Gaussians: [`crate::gaussians::init`], under the name the loaders use.
pub use crate::gaussians::init::InitialPoints;

use crate::camera::Camera;
use crate::error::{Error, Result};
use glam::DVec3;
use std::path::Path;

/// One training or evaluation view.
#[derive(Clone, Debug, PartialEq)]
pub struct Frame {
    /// The image's name (file stem or id), unique within its split.
    pub name: String,
    /// The view's camera.
    pub camera: Camera,
    /// Time `fid` in `[0, 1]`.
    pub time: f64,
    /// `[3, H, W]`, channel-major, values `byte / 255`.
    pub image: Vec<f32>,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
}

/// Which reader produced a dataset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DatasetKind {
    /// D-NeRF / Blender layout (`transforms_{train,val,test}.json`).
    DNerf,
    /// Nerfies / HyperNeRF / NeRF-DS layout (`dataset.json`, `camera/`, `rgb/`).
    Nerfies,
    /// A built-in analytic scene generated in memory.
    Synthetic,
}

impl DatasetKind {
    /// Lower-case name for reports.
    pub fn name(self) -> &'static str {
        match self {
            DatasetKind::DNerf => "dnerf",
            DatasetKind::Nerfies => "nerfies",
            DatasetKind::Synthetic => "synthetic",
        }
    }
}

/// The background an RGBA image is composited onto (D-NeRF), also used for the loss.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Background {
    /// Upstream's default (`--white_background` not given).
    #[default]
    Black,
    /// `--white_background`: 1 in every channel.
    White,
}

impl Background {
    /// The background value in `[0, 1]`.
    pub fn value(self) -> f64 {
        match self {
            Background::Black => 0.0,
            Background::White => 1.0,
        }
    }
}

/// Which splits to decode images for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Splits {
    /// Decode the training images.
    pub train: bool,
    /// Decode the validation images.
    pub val: bool,
    /// Decode the test images.
    pub test: bool,
}

impl Default for Splits {
    fn default() -> Self {
        Splits {
            train: true,
            val: true,
            test: true,
        }
    }
}

/// How a nerfies-layout dataset is split into train and test views (upstream §6.9).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum NerfiesSplit {
    /// Upstream's rule, chosen from the name of the dataset folder's parent: `vrig*` →
    /// [`TrainVal`](Self::TrainVal) at ratio 0.25; `NeRF*` → `TrainVal` at ratio 1;
    /// `interp*` → [`Interp`](Self::Interp) at ratio 0.5; anything else →
    /// [`EveryFourth`](Self::EveryFourth) at ratio 0.5. The compatible default.
    #[default]
    Auto,
    /// `train_ids` / `val_ids` of `dataset.json`.
    TrainVal,
    /// `ids[::4]` for training, `ids[2::4]` for testing.
    Interp,
    /// `ids[::4]` for training, no test set.
    EveryFourth,
}

/// Options of [`load`].
#[derive(Clone, Debug, PartialEq)]
pub struct LoadOptions {
    /// Background for RGBA images (D-NeRF). Default black, as upstream's default.
    pub background: Background,
    /// Integer downscale factor: 1, 2, 4 or 8 (see [`image::box_downscale`]).
    pub downscale: usize,
    /// Splits whose images are decoded (cameras of every split are always parsed).
    pub splits: Splits,
    /// Nerfies split rule.
    pub nerfies_split: NerfiesSplit,
    /// Nerfies image ratio override (1.0, 0.5 or 0.25 → `rgb/1x`, `2x`, `4x`); `None` takes
    /// the ratio from the split rule ([`NerfiesSplit::Auto`]) or 1.0.
    pub nerfies_ratio: Option<f64>,
    /// Number of random initial points when the scene has no point cloud (upstream 100,000).
    pub init_points: usize,
    /// Seed of the random initial points.
    pub init_seed: u64,
}

impl Default for LoadOptions {
    fn default() -> Self {
        LoadOptions {
            background: Background::Black,
            downscale: 1,
            splits: Splits::default(),
            nerfies_split: NerfiesSplit::Auto,
            nerfies_ratio: None,
            init_points: init::DEFAULT_RANDOM_POINTS,
            init_seed: 0,
        }
    }
}

/// A loaded dataset.
#[derive(Clone, Debug, PartialEq)]
pub struct Dataset {
    /// The layout it was read from.
    pub kind: DatasetKind,
    /// Training frames, in file order.
    pub train: Vec<Frame>,
    /// Validation frames, in file order (may be empty).
    pub val: Vec<Frame>,
    /// Test frames, in file order.
    pub test: Vec<Frame>,
    /// True when images were composited on white (and training should use a white background).
    pub white_background: bool,
    /// Upstream's `cameras_extent` (see the module documentation).
    pub scene_extent: f64,
    /// Where the initial Gaussians come from ([`init::initial_gaussians`]).
    pub init: InitialPoints,
    /// Things the loader ignored that may matter (e.g. an off-centre principal point).
    pub warnings: Vec<String>,
}

/// The fields of view a camera may have, in radians (both loaders): a
/// narrower one gives a tangent that rounds to 0 in f32, one of pi or more
/// no finite tangent.
pub const FOV_RANGE: std::ops::RangeInclusive<f64> = 1e-6..=std::f64::consts::PI - 1e-6;

/// Load the dataset in `dir`, detecting its layout.
pub fn load(dir: &Path, opts: &LoadOptions) -> Result<Dataset> {
    if !matches!(opts.downscale, 1 | 2 | 4 | 8) {
        return Err(Error::invalid(
            "downscale",
            format!("{} is not 1, 2, 4 or 8", opts.downscale),
        ));
    }
    init::check_count(opts.init_points).map_err(|w| Error::invalid("init_points", w))?;
    if dir.join("transforms_train.json").is_file() {
        dnerf::load(dir, opts)
    } else if dir.join("dataset.json").is_file() {
        nerfies::load(dir, opts)
    } else if !dir.is_dir() {
        let why = if dir.exists() {
            "not a folder: a dataset is a folder (D-NeRF or nerfies layout)"
        } else {
            "dataset folder not found"
        };
        Err(Error::io(
            dir,
            std::io::Error::new(std::io::ErrorKind::NotFound, why),
        ))
    } else {
        Err(Error::format(
            dir,
            "unknown dataset layout: neither transforms_train.json (D-NeRF) nor dataset.json (nerfies) is present",
        ))
    }
}

/// [`scene_extent`], refused when it is not finite (camera centres too far
/// apart for `f64`: densification would compare with infinity); `file` and
/// `field` name what holds the cameras.
pub fn finite_scene_extent(centres: &[[f64; 3]], file: &Path, field: &str) -> Result<f64> {
    let e = scene_extent(centres);
    if !e.is_finite() {
        // The centre farthest from the origin, which the sums overflowed on.
        let (i, c) = centres
            .iter()
            .enumerate()
            .max_by(|a, b| {
                DVec3::from(*a.1)
                    .length()
                    .total_cmp(&DVec3::from(*b.1).length())
            })
            .expect("an infinite extent has centres");
        return Err(Error::field(
            file,
            field,
            format!(
                "the camera centres are too far apart: scene extent {e} (training camera {i}'s \
                 centre is [{:e}, {:e}, {:e}])",
                c[0], c[1], c[2]
            ),
        ));
    }
    Ok(e)
}

/// Upstream's `cameras_extent`: 1.1 × max distance of the centres from their mean.
/// Zero centres give 0.
pub fn scene_extent(centres: &[[f64; 3]]) -> f64 {
    if centres.is_empty() {
        return 0.0;
    }
    let n = centres.len() as f64;
    let mut mean = DVec3::ZERO;
    for &c in centres {
        mean += DVec3::from(c);
    }
    mean /= n;
    let mut max = 0.0f64;
    for &c in centres {
        let d = (DVec3::from(c) - mean).length();
        if d > max {
            max = d;
        }
    }
    max * 1.1
}

/// A JSON summary of a dataset (what `liquid-splat inspect` prints): kind, frames per split,
/// image size, field of view, time range, bounding box of the camera centres, scene extent,
/// initial points, warnings.
pub fn summary(ds: &Dataset) -> serde_json::Value {
    use serde_json::json;
    let all: Vec<&Frame> = ds.train.iter().chain(&ds.val).chain(&ds.test).collect();
    let first = all.first();
    let mut lo = [f64::INFINITY; 3];
    let mut hi = [f64::NEG_INFINITY; 3];
    let (mut t0, mut t1) = (f64::INFINITY, f64::NEG_INFINITY);
    for f in &all {
        let c = f.camera.centre();
        for a in 0..3 {
            lo[a] = lo[a].min(c[a]);
            hi[a] = hi[a].max(c[a]);
        }
        t0 = t0.min(f.time);
        t1 = t1.max(f.time);
    }
    let deg = |r: f64| r * 180.0 / std::f64::consts::PI;
    json!({
        "kind": ds.kind.name(),
        "frames": {"train": ds.train.len(), "val": ds.val.len(), "test": ds.test.len()},
        "image_size": first.map(|f| json!([f.width, f.height])),
        "fov_x_deg": first.map(|f| deg(f.camera.fov_x)),
        "fov_y_deg": first.map(|f| deg(f.camera.fov_y)),
        "time_range": first.map(|_| json!([t0, t1])),
        "camera_centres_bbox": first.map(|_| json!({"min": lo, "max": hi})),
        "scene_extent": ds.scene_extent,
        "white_background": ds.white_background,
        "initial_points": match &ds.init {
            InitialPoints::Cloud { xyz, .. } => json!({"source": "file", "count": xyz.len() / 3}),
            InitialPoints::RandomCube { count, half_extent, seed } =>
                json!({"source": "random_cube", "count": count, "half_extent": half_extent, "seed": seed}),
        },
        "warnings": ds.warnings,
    })
}

/// Run `f` over `items` in parallel, keeping their order; the first error in item order wins.
pub(crate) fn par_map_ordered<I: Sync, O: Send>(
    items: &[I],
    f: impl Fn(&I) -> Result<O> + Sync + Send,
) -> Result<Vec<O>> {
    use rayon::prelude::*;
    let results: Vec<Result<O>> = items.par_iter().map(&f).collect();
    results.into_iter().collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn extent_of_a_ring() {
        // Four centres on a circle of radius 2 around (1, 1, 1): extent 2.2.
        let c = [
            [3.0, 1.0, 1.0],
            [-1.0, 1.0, 1.0],
            [1.0, 3.0, 1.0],
            [1.0, -1.0, 1.0],
        ];
        assert!((scene_extent(&c) - 2.2).abs() < 1e-12);
    }

    #[test]
    fn unknown_layout_is_an_error() {
        let dir = std::env::temp_dir().join(format!("ls-empty-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let e = load(&dir, &LoadOptions::default()).unwrap_err().to_string();
        assert!(e.contains("unknown dataset layout"), "{e}");
        let e = load(&dir.join("nope"), &LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("not found"), "{e}");
        let opts = LoadOptions {
            downscale: 3,
            ..Default::default()
        };
        assert!(load(&dir, &opts).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
