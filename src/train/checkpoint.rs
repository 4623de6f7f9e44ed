//! Checkpoints: the whole training state, written atomically.
//!
//! A checkpoint is a folder `iteration_NNNNNN/` holding
//! - `state.safetensors`: canonical Gaussians (raw parameters, run precision),
//!   Adam moments and step counters and densification statistics in the
//!   layout of [`super::state`] (the oracle's `step` stage uses the same),
//!   the camera sampler and AST generator states, with the iteration, the run
//!   configuration's fingerprint and the [state hash](Trainer::state_hash) in
//!   the metadata;
//! - `deform.safetensors`: the field weights under their PyTorch `state_dict`
//!   names (loadable by the D-3DGS / ncps modules after conversion to torch);
//! - `point_cloud.ply`: the canonical Gaussians in the Inria layout (f32);
//! - `curve.json`: the training curve up to this iteration (written by the
//!   caller through `extra` files of [`save`]).
//!
//! The folder is first written as `iteration_NNNNNN.partial/` and renamed when
//! every file is on disk, so an interrupted write never looks like a
//! checkpoint. The state's metadata also records what the run was trained
//! on ([`DataBinding`]: the data's name, resolution, background and a hash of
//! the training frames), the scene extent, a hash of the field weights and
//! of every other file, and a checkpoint hash over the state hash, extent,
//! background and data binding. Loading recomputes every hash and refuses a
//! checkpoint whose contents do not match (corruption, reported against the
//! file that does not match), whose configuration, data, resolution or
//! background differ from the run's, or whose precision differs.

use super::cameras::CameraSampler;
use super::config::TrainConfig;
use super::model::Model;
use super::state::{self, Source};
use super::trainer::{Fnv, Progress, Trainer};
use crate::deform::Field;
use crate::error::{Error, Result};
use crate::gaussians::ply;
use crate::io::TensorFile;
use crate::math::{Real, Rng};
use std::path::{Path, PathBuf};

/// The training state's file in a checkpoint folder ([`super::state`]'s
/// layout, plus the sampler, generators and hashes).
pub const STATE_FILE: &str = "state.safetensors";
/// The field weights' file in a checkpoint folder.
pub const FIELD_FILE: &str = "deform.safetensors";
/// The canonical Gaussians as an Inria PLY in a checkpoint folder.
pub const PLY_FILE: &str = "point_cloud.ply";

/// What a run is trained on, recorded in its checkpoints and compared on
/// loading (resume, render, export): a checkpoint of other data is refused.
#[derive(Clone, Debug, PartialEq)]
pub struct DataBinding {
    /// The data's name for messages (dataset folder or built-in scene);
    /// recorded, not compared (a moved dataset folder is the same data).
    pub source: String,
    /// Width and height of the training images.
    pub resolution: (usize, usize),
    /// The background colour the images are composited onto and trained with.
    pub background: [f64; 3],
    /// Hash of every training frame: name, time, camera and pixels.
    pub data_hash: u64,
}

impl DataBinding {
    /// The binding of `data`, named `source` in messages.
    pub fn of(data: &crate::dataset::Dataset, source: &str) -> Self {
        let mut h = Fnv::new();
        h.u64(data.train.len() as u64);
        for f in &data.train {
            h.bytes(f.name.as_bytes());
            h.u64(f.time.to_bits());
            h.u64(f.width as u64);
            h.u64(f.height as u64);
            // Debug of f64 is exact (shortest round-trip).
            h.bytes(format!("{:?}", f.camera).as_bytes());
            h.words(f.image.iter().map(|&v| v.to_bits() as u64));
        }
        let resolution = data.train.first().map_or((0, 0), |f| (f.width, f.height));
        DataBinding {
            source: source.to_string(),
            resolution,
            background: [if data.white_background { 1.0 } else { 0.0 }; 3],
            data_hash: h.0,
        }
    }
}

/// The hash the checkpoint metadata records over the state hash and what
/// the state hash leaves out: extent, background and data binding.
fn checkpoint_hash(state_hash: u64, extent: f64, background: [f64; 3], b: &DataBinding) -> u64 {
    let mut h = Fnv::new();
    h.u64(state_hash);
    h.u64(extent.to_bits());
    for v in background {
        h.u64(v.to_bits());
    }
    h.u64(b.resolution.0 as u64);
    h.u64(b.resolution.1 as u64);
    h.u64(b.data_hash);
    h.0
}

fn field_hash<T: Real>(field: &Field<T>) -> u64 {
    let mut h = Fnv::new();
    h.reals(field.params());
    h.0
}

fn file_hash(path: &Path) -> Result<u64> {
    let mut h = Fnv::new();
    h.bytes(&crate::io::read(path)?);
    Ok(h.0)
}

/// The folder name of the checkpoint at `iteration`.
pub fn checkpoint_name(iteration: u64) -> String {
    format!("iteration_{iteration:06}")
}

fn to_i32(what: &str, v: impl Iterator<Item = u64>) -> Result<Vec<i32>> {
    v.map(|x| {
        i32::try_from(x).map_err(|_| Error::invalid(what, format!("{x} does not fit in i32")))
    })
    .collect()
}

/// Write the trainer's state, trained on `binding`, to
/// `dir/iteration_NNNNNN/`, with `extra` files (name, bytes) beside it;
/// returns that folder. Every file is written before the folder is renamed
/// into place.
pub fn save<T: Real>(
    trainer: &Trainer<T>,
    dir: &Path,
    binding: &DataBinding,
    extra: &[(&str, &[u8])],
) -> Result<PathBuf> {
    let name = checkpoint_name(trainer.iteration());
    let final_dir = dir.join(&name);
    let partial = dir.join(format!("{name}.partial"));
    let mkdir = crate::io::create_dir_all;
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|e| Error::io(&partial, e))?;
    }
    mkdir(&partial)?;

    let model = trainer.model();
    let g = &model.gaussians;
    let mut f = TensorFile::new(partial.join(STATE_FILE));
    state::write_gaussians(&mut f, "", g);
    state::write_optimizer(&mut f, "", trainer.optimizer(), g);
    state::write_stats(&mut f, "", trainer.stats())?;
    let sampler = trainer.sampler();
    let stack = sampler.stack();
    f.insert_i32(
        "sampler.stack",
        vec![stack.len()],
        to_i32("sampler.stack", stack.iter().map(|&i| i as u64))?,
    );
    f.set_meta("iteration", trainer.iteration());
    f.set_meta("active_sh_degree", model.active_sh_degree);
    f.set_meta("max_sh_degree", g.max_sh_degree);
    f.set_meta("sampler.views", sampler.count());
    f.set_meta("sampler.rng", sampler.rng_state());
    f.set_meta("ast.rng", trainer.ast_rng().state());
    f.set_meta("extent", format!("{:?}", trainer.extent()));
    f.set_meta("background", format!("{:?}", model.background));
    f.set_meta("config", trainer.config().fingerprint());
    let state_hash = trainer.state_hash();
    f.set_meta("state_hash", format!("{state_hash:016x}"));
    f.set_meta("data.source", &binding.source);
    f.set_meta(
        "data.resolution",
        format!("{}x{}", binding.resolution.0, binding.resolution.1),
    );
    f.set_meta("data.hash", format!("{:016x}", binding.data_hash));
    let hash = checkpoint_hash(state_hash, trainer.extent(), model.background, binding);
    f.set_meta("checkpoint_hash", format!("{hash:016x}"));
    f.set_meta("crate_version", env!("CARGO_PKG_VERSION"));
    crate::oracle::field::field_to_tensor_file(&model.field).save(&partial.join(FIELD_FILE))?;
    f.set_meta("field_hash", format!("{:016x}", field_hash(&model.field)));
    let ply_path = partial.join(PLY_FILE);
    ply::write_gaussians(&ply_path, g)?;
    f.set_meta("ply_hash", format!("{:016x}", file_hash(&ply_path)?));
    for (name, bytes) in extra {
        crate::io::write_atomic(&partial.join(name), bytes)?;
    }
    // The state last: its hashes cover the files above.
    f.save(&partial.join(STATE_FILE))?;

    if final_dir.exists() {
        std::fs::remove_dir_all(&final_dir).map_err(|e| Error::io(&final_dir, e))?;
    }
    std::fs::rename(&partial, &final_dir).map_err(|e| Error::io(&final_dir, e))?;
    Ok(final_dir)
}

/// The newest complete checkpoint in `dir` (`.partial` folders are ignored).
pub fn latest(dir: &Path) -> Result<Option<PathBuf>> {
    if !dir.exists() {
        return Ok(None);
    }
    let mut best: Option<(u64, PathBuf)> = None;
    for e in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))? {
        let e = e.map_err(|e| Error::io(dir, e))?;
        let name = e.file_name().to_string_lossy().to_string();
        let Some(num) = name.strip_prefix("iteration_") else {
            continue;
        };
        let Ok(it) = num.parse::<u64>() else { continue };
        if best.as_ref().is_none_or(|(b, _)| it > *b) {
            best = Some((it, e.path()));
        }
    }
    Ok(best.map(|(_, p)| p))
}

/// Where two configuration fingerprints first differ: each from the start
/// of the field holding the difference, at most 100 characters.
fn first_difference(a: &str, b: &str) -> (String, String) {
    let at = a
        .char_indices()
        .zip(b.chars())
        .find(|((_, x), y)| x != y)
        .map_or(a.len().min(b.len()), |((i, _), _)| i);
    // (The prefix before `at` is the same in both, so `start` is a
    // character boundary of each.)
    let start = a[..at].rfind([',', '{', '(']).map_or(0, |k| k + 1);
    let part = |s: &str| {
        s[start..]
            .trim_start()
            .chars()
            .take(100)
            .collect::<String>()
    };
    (part(a), part(b))
}

/// Load a checkpoint folder written by [`save`] for a run with `config` on
/// the data `binding` describes.
pub fn load<T: Real>(
    ckpt: &Path,
    config: &TrainConfig,
    binding: &DataBinding,
) -> Result<Trainer<T>> {
    load_checked(ckpt, config, binding).map_err(|e| e.in_file(ckpt.join(STATE_FILE)))
}

fn load_checked<T: Real>(
    ckpt: &Path,
    config: &TrainConfig,
    binding: &DataBinding,
) -> Result<Trainer<T>> {
    let path = ckpt.join(STATE_FILE);
    let f = TensorFile::load(&path)?;
    if !f.metadata.contains_key("checkpoint_hash") {
        return Err(Error::field(
            &path,
            "__metadata__.checkpoint_hash",
            "missing: written by an earlier version that did not record the data it was trained on; train again",
        ));
    }
    let found = f.meta("config")?;
    let this = config.fingerprint();
    if found != this {
        let (theirs, ours) = first_difference(found, &this);
        return Err(Error::field(
            &path,
            "__metadata__.config",
            format!(
                "the checkpoint was written by a different run configuration; they first \
                 differ at\n  checkpoint: {theirs}\n  this run:   {ours}"
            ),
        ));
    }
    let gaussians = state::read_gaussians::<T>(&f, "")?;
    let deg: usize = f.meta_parse("max_sh_degree")?;
    if deg != gaussians.max_sh_degree {
        return Err(Error::field(
            &path,
            "__metadata__.max_sh_degree",
            format!("{deg}, but `sh` holds degree {}", gaussians.max_sh_degree),
        ));
    }
    let field_path = ckpt.join(FIELD_FILE);
    let field_file = TensorFile::load(&field_path)?;
    let field = crate::oracle::field::field_from_tensor_file::<T>(config.field, &field_file)?;
    let hex = |key: &str| -> Result<u64> {
        let s = f.meta(key)?;
        u64::from_str_radix(s, 16).map_err(|_| {
            Error::field(
                &path,
                format!("__metadata__.{key}"),
                format!("{s:?} is not a hexadecimal hash"),
            )
        })
    };
    if field_hash(&field) != hex("field_hash")? {
        return Err(Error::format(
            &field_path,
            format!(
                "the field weights do not match the hash recorded in {}: the checkpoint is corrupt",
                path.display()
            ),
        ));
    }
    let ply_path = ckpt.join(PLY_FILE);
    if file_hash(&ply_path)? != hex("ply_hash")? {
        return Err(Error::format(
            &ply_path,
            format!(
                "the file does not match the hash recorded in {}: the checkpoint is corrupt",
                path.display()
            ),
        ));
    }
    let optimizer =
        state::read_optimizer(&f, "", &gaussians, field.param_count(), Source::Checkpoint)?;
    let stats = state::read_stats(&f, "", gaussians.len(), Source::Checkpoint)?;
    let i32s = |name: &str| -> Result<Vec<i32>> {
        let v = f.i32_array(name)?;
        let shape = v.shape().to_vec();
        let v: Vec<i32> = v.iter().copied().collect();
        if shape.len() != 1 || v.iter().any(|&x| x < 0) {
            return Err(Error::field(
                &path,
                name,
                format!("shape {shape:?} or a negative value"),
            ));
        }
        Ok(v)
    };
    let views: usize = f.meta_parse("sampler.views")?;
    let stack: Vec<usize> = i32s("sampler.stack")?
        .into_iter()
        .map(|i| i as usize)
        .collect();
    if stack.iter().any(|&i| i >= views) {
        return Err(Error::field(
            &path,
            "sampler.stack",
            format!("an index is not below {views}"),
        ));
    }
    let background = parse_background(&path, f.meta("background")?)?;
    let extent: f64 = f.meta_finite("extent")?;
    if extent < 0.0 {
        return Err(Error::field(
            &path,
            "__metadata__.extent",
            format!("{extent} is negative"),
        ));
    }
    let recorded = DataBinding {
        source: f.meta("data.source")?.to_string(),
        resolution: parse_resolution(&path, f.meta("data.resolution")?)?,
        background,
        data_hash: hex("data.hash")?,
    };
    let model = Model {
        gaussians,
        field,
        active_sh_degree: f.meta_parse("active_sh_degree")?,
        background,
    };
    let iteration: u64 = f.meta_parse("iteration")?;
    // `latest` picks a run's checkpoint by its folder's number, and resumed
    // runs name their next checkpoints from the state's: the two must agree.
    if let Some(named) = ckpt
        .file_name()
        .and_then(|n| n.to_str())
        .and_then(|n| n.strip_prefix("iteration_"))
        .and_then(|n| n.parse::<u64>().ok())
    {
        if named != iteration {
            return Err(Error::field(
                &path,
                "__metadata__.iteration",
                format!(
                    "{iteration}, but the checkpoint's folder is named for iteration {named} (a folder renamed or copied over another)"
                ),
            ));
        }
    }
    let progress = Progress {
        iteration,
        sampler: CameraSampler::from_state(views, stack, f.meta_parse("sampler.rng")?),
        ast_rng: Rng::new(f.meta_parse("ast.rng")?),
    };
    let trainer = Trainer::restore(config.clone(), model, optimizer, stats, progress, extent)?;
    let want = f.meta("state_hash")?;
    let state_hash = trainer.state_hash();
    let got = format!("{state_hash:016x}");
    if want != got {
        return Err(Error::format(
            &path,
            format!(
                "state hash {got} does not match the recorded {want}: the checkpoint is corrupt"
            ),
        ));
    }
    if checkpoint_hash(state_hash, extent, background, &recorded) != hex("checkpoint_hash")? {
        return Err(Error::format(
            &path,
            "the extent, background or data record does not match the recorded checkpoint_hash: the checkpoint is corrupt",
        ));
    }
    check_binding(&path, &recorded, binding)?;
    Ok(trainer)
}

/// Refuse a checkpoint trained on other data than `run`'s.
fn check_binding(path: &Path, ckpt: &DataBinding, run: &DataBinding) -> Result<()> {
    let (cw, ch) = ckpt.resolution;
    let (rw, rh) = run.resolution;
    let mismatch = if ckpt.resolution != run.resolution {
        Some((
            "data.resolution",
            format!("{cw}x{ch} images, this run's are {rw}x{rh}"),
        ))
    } else if ckpt.background != run.background {
        Some((
            "background",
            format!(
                "background {:?}, this run's is {:?}",
                ckpt.background, run.background
            ),
        ))
    } else if ckpt.data_hash != run.data_hash {
        Some((
            "data.hash",
            "other training frames (names, times, cameras or pixels differ)".to_string(),
        ))
    } else {
        None
    };
    match mismatch {
        None => Ok(()),
        Some((field, what)) => Err(Error::field(
            path,
            format!("__metadata__.{field}"),
            format!(
                "the checkpoint was trained on {} with {what} ({}); it is not this run's",
                ckpt.source, run.source
            ),
        )),
    }
}

fn parse_resolution(path: &Path, s: &str) -> Result<(usize, usize)> {
    s.split_once('x')
        .and_then(|(w, h)| Some((w.parse().ok()?, h.parse().ok()?)))
        .ok_or_else(|| {
            Error::field(
                path,
                "__metadata__.data.resolution",
                format!("cannot parse {s:?} as WIDTHxHEIGHT"),
            )
        })
}

fn parse_background(path: &Path, s: &str) -> Result<[f64; 3]> {
    let v: Vec<f64> = s
        .trim_matches(|c| c == '[' || c == ']')
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| {
            Error::field(
                path,
                "__metadata__.background",
                format!("cannot parse {s:?}"),
            )
        })?;
    let b: [f64; 3] = v.try_into().map_err(|_| {
        Error::field(
            path,
            "__metadata__.background",
            format!("{s:?} is not 3 numbers"),
        )
    })?;
    if b.iter()
        .any(|v| !(v.is_finite() && (0.0..=1.0).contains(v)))
    {
        return Err(Error::field(
            path,
            "__metadata__.background",
            format!("{s:?}: every value must be finite and in [0, 1]"),
        ));
    }
    Ok(b)
}
