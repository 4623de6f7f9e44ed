//! The training state as named tensors: one layout, read and written here,
//! for checkpoints ([`super::checkpoint`]) and the oracle's `step` stage.
//!
//! With a name prefix `p` (empty, or `new.` for the `step` stage's updated
//! parameters and moments), in the run's precision unless stated:
//!
//! | tensor | shape | meaning |
//! |---|---|---|
//! | `p` + group name (`xyz`, `sh`, `opacity`, `scaling`, `rotation`) | `[N]` + [`Group::row_shape`]: `[N,3]`, `[N,K,3]`, `[N,1]`, `[N,3]`, `[N,4]` | raw parameters |
//! | `p` + `adam.<group>.m`, `adam.<group>.v` | the group's shape; `field`: `[P]` | Adam moments |
//! | `p` + `stats.accum` | `[N]` | summed NDC gradient norms |
//! | `p` + `stats.denom`, `stats.max_radii` | `[N]` I32 | visible-view counts, largest radii |
//!
//! and the metadata `p` + `adam.<group>.step` (the step counter). The Adam
//! groups are the Gaussian groups in [`Group::ALL`]'s order, then `field`
//! (the field weights' moments, concatenated in `state_dict` order).
//!
//! The readers check shapes, that second moments are ≥ 0 and not NaN, that
//! counts are ≥ 0 and that a step counter can advance. What may be absent
//! depends on the [`Source`].

use super::model::ModelOptimizer;
use crate::densify::DensifyStats;
use crate::error::{Error, Result};
use crate::gaussians::{Gaussians, Group};
use crate::io::tensor_file::into_row_major;
use crate::io::TensorFile;
use crate::math::Real;
use crate::optim::{AdamState, GaussianOptimizer};

/// The name of the field weights' Adam group.
pub const FIELD_GROUP: &str = "field";

/// The Adam groups, in file order: the Gaussian groups, then the field.
pub fn adam_groups() -> [&'static str; 6] {
    let g = Group::ALL.map(Group::name);
    [g[0], g[1], g[2], g[3], g[4], FIELD_GROUP]
}

/// What a file may leave out.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Source {
    /// A `step` case: a group's moments (both or neither) and each
    /// statistic may be absent (zeros), a step counter too (0).
    Case,
    /// A checkpoint: everything is required. Moments are also accepted
    /// flat (`[len]`), as checkpoints of version 0.1.0 and earlier wrote them.
    Checkpoint,
}

fn tensor_error(f: &TensorFile, name: &str, expected: impl Into<String>, found: String) -> Error {
    Error::Tensor {
        context: f.path.display().to_string(),
        name: name.into(),
        expected: expected.into(),
        found,
    }
}

/// Write the raw parameters of `g` as `prefix` + group name.
pub fn write_gaussians<T: Real>(f: &mut TensorFile, prefix: &str, g: &Gaussians<T>) {
    for group in Group::ALL {
        let name = format!("{prefix}{}", group.name());
        f.insert_real(&name, g.shape(group), g.group(group));
    }
}

/// Read the raw parameters written by [`write_gaussians`]: N from `xyz`
/// (`[N,3]`), the SH degree from `sh` (`[N,K,3]`, K = 1, 4, 9 or 16).
pub fn read_gaussians<T: Real>(f: &TensorFile, prefix: &str) -> Result<Gaussians<T>> {
    let xyz_name = format!("{prefix}xyz");
    let xyz = f.real_array::<T>(&xyz_name)?;
    let shape = xyz.shape().to_vec();
    let xyz = into_row_major(xyz);
    let n = match shape.as_slice() {
        [n, 3] => *n,
        _ => {
            let found = format!("shape {shape:?}");
            return Err(tensor_error(f, &xyz_name, "shape [N,3]", found));
        }
    };
    let sh_name = format!("{prefix}sh");
    let shape = f.shape(&sh_name)?;
    let degree = match shape {
        [m, k, 3] if *m == n => (0..=3).find(|&d| Gaussians::<T>::coeffs_for_degree(d) == *k),
        _ => None,
    };
    let max_sh_degree = degree.ok_or_else(|| {
        let expected = format!("shape [{n},K,3], K = 1, 4, 9 or 16");
        tensor_error(f, &sh_name, expected, format!("shape {shape:?}"))
    })?;
    let mut g = Gaussians::empty(max_sh_degree);
    g.xyz = xyz;
    for (group, v) in g.groups_mut() {
        if group != Group::Xyz {
            let mut shape = vec![n];
            shape.extend(group.row_shape(Gaussians::<T>::coeffs_for_degree(max_sh_degree)));
            *v = f.get_real::<T>(&format!("{prefix}{}", group.name()), &shape)?;
        }
    }
    g.validate()?;
    Ok(g)
}

/// Write the Adam states of `opt` (sized for `g`) as `prefix` +
/// `adam.<group>.*`.
pub fn write_optimizer<T: Real>(
    f: &mut TensorFile,
    prefix: &str,
    opt: &ModelOptimizer<T>,
    g: &Gaussians<T>,
) {
    let states = Group::ALL.map(|group| (g.shape(group), opt.gaussians.state(group)));
    let field = (vec![opt.field.len()], &opt.field);
    for (name, (shape, state)) in adam_groups()
        .into_iter()
        .zip(states.into_iter().chain([field]))
    {
        let key = format!("{prefix}adam.{name}");
        f.insert_real(&format!("{key}.m"), shape.clone(), &state.m);
        f.insert_real(&format!("{key}.v"), shape, &state.v);
        f.set_meta(&format!("{key}.step"), state.step);
    }
}

/// Read the Adam states written by [`write_optimizer`] for the Gaussians
/// `g` and a field of `field_params` weights.
pub fn read_optimizer<T: Real>(
    f: &TensorFile,
    prefix: &str,
    g: &Gaussians<T>,
    field_params: usize,
    source: Source,
) -> Result<ModelOptimizer<T>> {
    let mut gaussians = GaussianOptimizer::new(g);
    for group in Group::ALL {
        let key = format!("{prefix}adam.{}", group.name());
        *gaussians.state_mut(group) = read_adam(f, &key, &g.shape(group), source)?;
    }
    let key = format!("{prefix}adam.{FIELD_GROUP}");
    let field = read_adam(f, &key, &[field_params], source)?;
    Ok(ModelOptimizer { gaussians, field })
}

/// One Adam state: `key.m`, `key.v` of `shape` and the counter `key.step`.
fn read_adam<T: Real>(
    f: &TensorFile,
    key: &str,
    shape: &[usize],
    source: Source,
) -> Result<AdamState<T>> {
    let mut state = AdamState::<T>::new(shape.iter().product());
    let (m, v) = (format!("{key}.m"), format!("{key}.v"));
    match (f.contains(&m), f.contains(&v), source) {
        (false, false, Source::Case) => {}
        (true, true, _) => {
            state.m = read_moment(f, &m, shape, source)?;
            state.v = read_moment(f, &v, shape, source)?;
            if let Some(i) = state.v.iter().position(|x| x.is_nan() || *x < T::ZERO) {
                let found = format!("{} at flat index {i}", state.v[i].to_f64());
                return Err(tensor_error(f, &v, "second moments ≥ 0", found));
            }
        }
        (has_m, has_v, _) => {
            let path = f.path.display();
            let (context, missing) = match (has_m, has_v) {
                (true, _) => (format!("{path} (`{m}` is given)"), v),
                (_, true) => (format!("{path} (`{v}` is given)"), m),
                _ => (path.to_string(), m),
            };
            return Err(Error::MissingTensor {
                context,
                name: missing,
            });
        }
    }
    let step_key = format!("{key}.step");
    state.step = match source {
        Source::Case => f.meta_or(&step_key, 0u64)?,
        Source::Checkpoint => f.meta_parse(&step_key)?,
    };
    if state.step == u64::MAX {
        return Err(Error::field(
            &f.path,
            format!("__metadata__.{step_key}"),
            format!("{} (the step counter cannot advance)", state.step),
        ));
    }
    Ok(state)
}

/// A moment tensor of `shape` (or, from a checkpoint, flat).
fn read_moment<T: Real>(
    f: &TensorFile,
    name: &str,
    shape: &[usize],
    source: Source,
) -> Result<Vec<T>> {
    let len: usize = shape.iter().product();
    if source == Source::Checkpoint && f.shape(name)? == [len] {
        return f.get_real::<T>(name, &[len]);
    }
    f.get_real::<T>(name, shape)
}

/// Write the densification statistics as `prefix` + `stats.*`.
pub fn write_stats<T: Real>(
    f: &mut TensorFile,
    prefix: &str,
    stats: &DensifyStats<T>,
) -> Result<()> {
    let n = stats.len();
    let denom = stats
        .denom
        .iter()
        .map(|&d| {
            i32::try_from(d)
                .map_err(|_| Error::invalid("stats.denom", format!("{d} does not fit in i32")))
        })
        .collect::<Result<Vec<i32>>>()?;
    f.insert_real(&format!("{prefix}stats.accum"), vec![n], &stats.accum);
    f.insert_i32(&format!("{prefix}stats.denom"), vec![n], denom);
    f.insert_i32(
        &format!("{prefix}stats.max_radii"),
        vec![n],
        stats.max_radii.clone(),
    );
    Ok(())
}

/// Read the statistics written by [`write_stats`] for `n` Gaussians.
pub fn read_stats<T: Real>(
    f: &TensorFile,
    prefix: &str,
    n: usize,
    source: Source,
) -> Result<DensifyStats<T>> {
    let mut stats = DensifyStats::new(n);
    let present = |name: &str| source == Source::Checkpoint || f.contains(name);
    let accum = format!("{prefix}stats.accum");
    if present(&accum) {
        stats.accum = f.get_real::<T>(&accum, &[n])?;
    }
    let counts = |name: String| -> Result<Option<Vec<i32>>> {
        if !present(&name) {
            return Ok(None);
        }
        let v = f.i32_array(&name)?;
        let shape = v.shape().to_vec();
        let v: Vec<i32> = v.iter().copied().collect();
        if shape != [n] {
            let expected = format!("shape [{n}]");
            return Err(tensor_error(f, &name, expected, format!("shape {shape:?}")));
        }
        if let Some(i) = v.iter().position(|&x| x < 0) {
            let found = format!("{} at index {i}", v[i]);
            return Err(tensor_error(f, &name, "values ≥ 0", found));
        }
        Ok(Some(v))
    };
    if let Some(d) = counts(format!("{prefix}stats.denom"))? {
        stats.denom = d.into_iter().map(|x| x as u32).collect();
    }
    if let Some(r) = counts(format!("{prefix}stats.max_radii"))? {
        stats.max_radii = r;
    }
    Ok(stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Three Gaussians of SH degree 1 with every value distinct, moments
    /// (and those of 10 field weights) and statistics.
    fn state() -> (Gaussians<f64>, ModelOptimizer<f64>, DensifyStats<f64>) {
        let mut g = Gaussians::<f64>::empty(1);
        let mut x = 0.0;
        for group in Group::ALL {
            *g.group_mut(group) = (0..3 * group.width(4))
                .map(|_| {
                    x += 0.5;
                    x
                })
                .collect();
        }
        g.validate().unwrap();
        let mut opt = ModelOptimizer {
            gaussians: GaussianOptimizer::new(&g),
            field: AdamState::new(10),
        };
        for (k, group) in Group::ALL.into_iter().enumerate() {
            let s = opt.gaussians.state_mut(group);
            s.m.iter_mut()
                .enumerate()
                .for_each(|(i, m)| *m = (k * 100 + i) as f64);
            s.v.iter_mut()
                .enumerate()
                .for_each(|(i, v)| *v = (k * 100 + i) as f64 * 2.0);
            s.step = 3 + k as u64;
        }
        opt.field.m.fill(-1.5);
        opt.field.step = 9;
        let mut stats = DensifyStats::new(3);
        stats.accum = vec![0.25, 0.0, 3.0];
        stats.denom = vec![1, 0, 4];
        stats.max_radii = vec![7, 0, 2];
        (g, opt, stats)
    }

    #[test]
    fn round_trip_with_a_prefix() {
        let (g, opt, stats) = state();
        let mut f = TensorFile::new("state.safetensors");
        write_gaussians(&mut f, "new.", &g);
        write_optimizer(&mut f, "new.", &opt, &g);
        write_stats(&mut f, "new.", &stats).unwrap();
        assert_eq!(f.shape("new.sh").unwrap(), [3, 4, 3]);
        assert_eq!(f.shape("new.opacity").unwrap(), [3, 1]);
        assert_eq!(f.shape("new.adam.rotation.m").unwrap(), [3, 4]);
        let bytes = f.to_bytes().unwrap();
        let back = TensorFile::from_bytes(std::path::Path::new("x"), &bytes).unwrap();
        for source in [Source::Case, Source::Checkpoint] {
            let g2 = read_gaussians::<f64>(&back, "new.").unwrap();
            assert_eq!(g2, g);
            let o2 = read_optimizer(&back, "new.", &g2, opt.field.len(), source).unwrap();
            assert_eq!(o2, opt);
            assert_eq!(read_stats::<f64>(&back, "new.", 3, source).unwrap(), stats);
        }
    }

    #[test]
    fn what_may_be_absent_depends_on_the_source() {
        let (g, opt, _) = state();
        let mut f = TensorFile::new("case.safetensors");
        write_gaussians(&mut f, "", &g);
        let o = read_optimizer(&f, "", &g, opt.field.len(), Source::Case).unwrap();
        assert_eq!(
            o,
            ModelOptimizer {
                gaussians: GaussianOptimizer::new(&g),
                field: AdamState::new(opt.field.len())
            }
        );
        assert_eq!(
            read_stats::<f64>(&f, "", 3, Source::Case).unwrap(),
            DensifyStats::new(3)
        );
        assert!(read_optimizer(&f, "", &g, opt.field.len(), Source::Checkpoint).is_err());
        assert!(read_stats::<f64>(&f, "", 3, Source::Checkpoint).is_err());
        // One moment without the other is an error either way.
        let s = opt.gaussians.state(Group::Xyz);
        f.insert_real("adam.xyz.m", vec![3, 3], &s.m);
        let e = read_optimizer(&f, "", &g, opt.field.len(), Source::Case).unwrap_err();
        assert!(e.to_string().contains("adam.xyz.v"), "{e}");
    }

    /// Checkpoints of earlier versions stored moments flat (`[len]`): they
    /// are still read; a case must give the group's shape.
    #[test]
    fn flat_moments_are_read_from_checkpoints_only() {
        let (g, opt, _) = state();
        let mut f = TensorFile::new("state.safetensors");
        write_optimizer(&mut f, "", &opt, &g);
        for group in Group::ALL {
            let s = opt.gaussians.state(group);
            let key = format!("adam.{}", group.name());
            f.insert_real(&format!("{key}.m"), vec![s.len()], &s.m);
            f.insert_real(&format!("{key}.v"), vec![s.len()], &s.v);
        }
        let o = read_optimizer(&f, "", &g, opt.field.len(), Source::Checkpoint).unwrap();
        assert_eq!(o, opt);
        assert!(read_optimizer(&f, "", &g, opt.field.len(), Source::Case).is_err());
    }

    #[test]
    fn bad_moments_and_counters_are_errors() {
        let (g, opt, _) = state();
        let mut f = TensorFile::new("case.safetensors");
        write_optimizer(&mut f, "", &opt, &g);
        let mut v = opt.gaussians.state(Group::Sh).v.clone();
        v[5] = -1.0;
        f.insert_real("adam.sh.v", vec![3, 4, 3], &v);
        let e = read_optimizer(&f, "", &g, opt.field.len(), Source::Case).unwrap_err();
        assert!(e.to_string().contains("adam.sh.v"), "{e}");
        let mut f = TensorFile::new("case.safetensors");
        write_optimizer(&mut f, "", &opt, &g);
        f.set_meta("adam.field.step", u64::MAX);
        assert!(read_optimizer(&f, "", &g, opt.field.len(), Source::Case).is_err());
    }
}
