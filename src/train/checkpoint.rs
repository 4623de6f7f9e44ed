//! Checkpoints: the whole training state, written atomically.
//!
//! A checkpoint is a folder `iteration_NNNNNN/` holding
//! - `state.safetensors`: canonical Gaussians (raw parameters, run precision),
//!   Adam moments and step counters, densification statistics, the camera
//!   sampler and AST generator states, with the iteration, the run
//!   configuration's fingerprint and the [state hash](Trainer::state_hash) in
//!   the metadata;
//! - `deform.safetensors`: the field weights under their PyTorch `state_dict`
//!   names (loadable by the D-3DGS / ncps modules after conversion to torch);
//! - `point_cloud.ply`: the canonical Gaussians in the Inria layout (f32).
//!
//! The folder is first written as `iteration_NNNNNN.partial/` and renamed when
//! every file is on disk, so an interrupted write never looks like a
//! checkpoint. Loading recomputes the state hash and refuses a checkpoint whose
//! contents do not match it (corruption), whose configuration differs from the
//! run's, or whose precision differs.

use super::cameras::CameraSampler;
use super::config::TrainConfig;
use super::trainer::Trainer;
use crate::deform::Field;
use crate::densify::DensifyStats;
use crate::error::{Error, Result};
use crate::gaussians::{ply, Gaussians};
use crate::io::TensorFile;
use crate::math::{Real, Rng};
use crate::optim::{AdamState, GaussianOptimizer};
use std::path::{Path, PathBuf};

pub const STATE_FILE: &str = "state.safetensors";
pub const FIELD_FILE: &str = "deform.safetensors";
pub const PLY_FILE: &str = "point_cloud.ply";

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

/// Write the trainer's state to `dir/iteration_NNNNNN/`; returns that folder.
pub fn save<T: Real>(trainer: &Trainer<T>, dir: &Path) -> Result<PathBuf> {
    let name = checkpoint_name(trainer.iteration);
    let final_dir = dir.join(&name);
    let partial = dir.join(format!("{name}.partial"));
    let mkdir = |p: &Path| std::fs::create_dir_all(p).map_err(|e| Error::io(p, e));
    if partial.exists() {
        std::fs::remove_dir_all(&partial).map_err(|e| Error::io(&partial, e))?;
    }
    mkdir(&partial)?;

    let g = &trainer.gaussians;
    let n = g.len();
    let mut f = TensorFile::new(partial.join(STATE_FILE));
    f.insert_real("xyz", vec![n, 3], &g.xyz);
    f.insert_real("sh", vec![n, g.coeffs(), 3], &g.sh);
    f.insert_real("scaling", vec![n, 3], &g.scaling);
    f.insert_real("rotation", vec![n, 4], &g.rotation);
    f.insert_real("opacity", vec![n, 1], &g.opacity);
    for (group, a) in adam_groups(&trainer.optimizer, &trainer.field_optimizer) {
        f.insert_real(&format!("adam.{group}.m"), vec![a.m.len()], &a.m);
        f.insert_real(&format!("adam.{group}.v"), vec![a.v.len()], &a.v);
        f.set_meta(&format!("adam.{group}.step"), a.step);
    }
    let s = &trainer.stats;
    f.insert_real("stats.accum", vec![n], &s.accum);
    f.insert_i32(
        "stats.denom",
        vec![n],
        to_i32("stats.denom", s.denom.iter().map(|&d| d as u64))?,
    );
    f.insert_i32("stats.max_radii", vec![n], s.max_radii.clone());
    let stack = trainer.sampler.stack();
    f.insert_i32(
        "sampler.stack",
        vec![stack.len()],
        to_i32("sampler.stack", stack.iter().map(|&i| i as u64))?,
    );
    f.set_meta("iteration", trainer.iteration);
    f.set_meta("active_sh_degree", trainer.active_sh_degree);
    f.set_meta("max_sh_degree", g.max_sh_degree);
    f.set_meta("sampler.views", trainer.sampler.count());
    f.set_meta("sampler.rng", trainer.sampler.rng_state());
    f.set_meta("ast.rng", trainer.ast_rng.state());
    f.set_meta("extent", trainer.extent);
    f.set_meta("background", format!("{:?}", trainer.background));
    f.set_meta("config", trainer.config.fingerprint());
    f.set_meta("state_hash", format!("{:016x}", trainer.state_hash()));
    f.set_meta("crate_version", env!("CARGO_PKG_VERSION"));
    f.save(&partial.join(STATE_FILE))?;
    trainer
        .field
        .to_tensor_file()
        .save(&partial.join(FIELD_FILE))?;
    ply::write_gaussians(&partial.join(PLY_FILE), g)?;

    if final_dir.exists() {
        std::fs::remove_dir_all(&final_dir).map_err(|e| Error::io(&final_dir, e))?;
    }
    std::fs::rename(&partial, &final_dir).map_err(|e| Error::io(&final_dir, e))?;
    Ok(final_dir)
}

fn adam_groups<'a, T>(
    o: &'a GaussianOptimizer<T>,
    field: &'a AdamState<T>,
) -> [(&'static str, &'a AdamState<T>); 6] {
    [
        ("xyz", &o.xyz),
        ("sh", &o.sh),
        ("opacity", &o.opacity),
        ("scaling", &o.scaling),
        ("rotation", &o.rotation),
        ("field", field),
    ]
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

/// Load a checkpoint folder written by [`save`] for a run with `config`.
pub fn load<T: Real>(ckpt: &Path, config: &TrainConfig) -> Result<Trainer<T>> {
    let path = ckpt.join(STATE_FILE);
    let f = TensorFile::load(&path)?;
    let found = f.meta("config")?;
    if found != config.fingerprint() {
        return Err(Error::field(
            &path,
            "__metadata__.config",
            format!(
                "the checkpoint was written by a different run configuration:\n  checkpoint: {found}\n  this run:   {}",
                config.fingerprint()
            ),
        ));
    }
    let deg: usize = f.meta_parse("max_sh_degree")?;
    let n = f.shape("xyz")?.first().copied().unwrap_or(0);
    let k = Gaussians::<T>::coeffs_for_degree(deg);
    let gaussians = Gaussians {
        max_sh_degree: deg,
        xyz: f.get_real("xyz", &[n, 3])?,
        sh: f.get_real("sh", &[n, k, 3])?,
        scaling: f.get_real("scaling", &[n, 3])?,
        rotation: f.get_real("rotation", &[n, 4])?,
        opacity: f.get_real("opacity", &[n, 1])?,
    };
    gaussians.validate()?;
    let field_file = TensorFile::load(&ckpt.join(FIELD_FILE))?;
    let field = Field::<T>::from_tensor_file(config.field, &field_file)?;
    let adam = |group: &str, len: usize| -> Result<AdamState<T>> {
        let mut a = AdamState::new(len);
        a.m = f.get_real(&format!("adam.{group}.m"), &[len])?;
        a.v = f.get_real(&format!("adam.{group}.v"), &[len])?;
        a.step = f.meta_parse(&format!("adam.{group}.step"))?;
        Ok(a)
    };
    let optimizer = GaussianOptimizer {
        xyz: adam("xyz", gaussians.xyz.len())?,
        sh: adam("sh", gaussians.sh.len())?,
        opacity: adam("opacity", n)?,
        scaling: adam("scaling", gaussians.scaling.len())?,
        rotation: adam("rotation", gaussians.rotation.len())?,
    };
    let field_optimizer = adam("field", field.param_count())?;
    let i32s = |name: &str, len: Option<usize>| -> Result<Vec<i32>> {
        let (shape, v) = f.get_i32(name)?;
        if shape.len() != 1 || len.is_some_and(|l| shape[0] != l) || v.iter().any(|&x| x < 0) {
            return Err(Error::field(
                &path,
                name,
                format!("shape {shape:?} or a negative value"),
            ));
        }
        Ok(v)
    };
    let stats = DensifyStats {
        accum: f.get_real("stats.accum", &[n])?,
        denom: i32s("stats.denom", Some(n))?
            .into_iter()
            .map(|d| d as u32)
            .collect(),
        max_radii: i32s("stats.max_radii", Some(n))?,
    };
    let views: usize = f.meta_parse("sampler.views")?;
    let stack: Vec<usize> = i32s("sampler.stack", None)?
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
    let trainer = Trainer {
        config: config.clone(),
        iteration: f.meta_parse("iteration")?,
        active_sh_degree: f.meta_parse("active_sh_degree")?,
        gaussians,
        field,
        optimizer,
        field_optimizer,
        stats,
        sampler: CameraSampler::from_state(views, stack, f.meta_parse("sampler.rng")?),
        ast_rng: Rng::new(f.meta_parse("ast.rng")?),
        extent: f.meta_parse("extent")?,
        background,
    };
    let want = f.meta("state_hash")?;
    let got = format!("{:016x}", trainer.state_hash());
    if want != got {
        return Err(Error::format(
            &path,
            format!(
                "state hash {got} does not match the recorded {want}: the checkpoint is corrupt"
            ),
        ));
    }
    Ok(trainer)
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
    v.try_into().map_err(|_| {
        Error::field(
            path,
            "__metadata__.background",
            format!("{s:?} is not 3 numbers"),
        )
    })
}
