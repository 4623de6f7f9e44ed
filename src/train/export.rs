//! The deformed Gaussians of a trained model at a time `t`, as an ordinary
//! static 3DGS model in the Inria PLY layout (for any 3DGS viewer).
//!
//! The Inria layout stores raw parameters that a viewer activates:
//! `scale = exp(scale_i)`, `rotation = normalize(rot_i)`,
//! `opacity = sigmoid(opacity)`. D-3DGS renders at time `t`:
//!
//! - `mean = xyz + d_xyz`,
//! - `s' = exp(scaling) + d_scaling` (the linear scale, which may reach 0 or
//!   below),
//! - `q' = normalize(rotation) + d_rotation`, **not** re-normalised: the
//!   rasterizer builds `R(q')` from it as given, which is not a rotation when
//!   `|q'| ≠ 1`, and the covariance is `Σ = R(q') diag(s')² R(q')ᵀ`.
//!
//! Writing `ln s'` and `q'` would not survive a viewer: it normalises `q'`
//! (a different `Σ` whenever `|q'| ≠ 1`) and `ln s'` is undefined for
//! `s' ≤ 0`. So the export writes the covariance D-3DGS renders: `Σ` (in
//! f64) is eigen-decomposed, `Σ = V diag(λ) Vᵀ`, and stored as the unit
//! quaternion of `V` and the log-scales `ln sqrt(λ)`. A viewer rebuilds the
//! same `Σ` (to rounding). A negative `s'` needs no special case (`Σ`
//! depends on `s'²`). A zero eigenvalue (a flat Gaussian, e.g. `s' = 0`) is
//! written as the scale [`MIN_SCALE`] (`ln` = −69.08), whose square is 0 in
//! f32, and counted in [`ExportReport::flat`].
//!
//! Means, SH coefficients (all stored degrees) and opacity logits are
//! written as they are (D-3DGS deforms neither colour nor opacity).

use super::trainer::Trainer;
use crate::error::{Error, Result};
use crate::gaussians::{ply, Gaussians};
use crate::math::covariance::{cov3d, sym3, sym3_eigen};
use crate::math::quat::rotmat_to_quat;
use crate::math::Real;
use std::path::{Path, PathBuf};

/// The scale written for a zero eigenvalue of the covariance.
pub const MIN_SCALE: f64 = 1e-30;

/// What an export did, per time.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ExportReport {
    /// The time exported.
    pub time: f64,
    /// The PLY file written.
    pub path: PathBuf,
    /// Number of Gaussians written.
    pub gaussians: usize,
    /// Gaussians with a deformed linear scale `s' ≤ 0` on some axis.
    pub nonpositive_scales: usize,
    /// Gaussians whose deformed quaternion has `| |q'| − 1 | > 1e-3`.
    pub non_unit_rotations: usize,
    /// Gaussians with a zero eigenvalue, written with [`MIN_SCALE`].
    pub flat: usize,
}

/// The deformed Gaussians of `trainer` at `time` as raw Inria parameters
/// (see the module documentation), and the counts of [`ExportReport`]
/// (`path` empty).
pub fn deformed_gaussians<T: Real>(
    trainer: &Trainer<T>,
    time: f64,
) -> Result<(Gaussians<T>, ExportReport)> {
    if !time.is_finite() {
        return Err(Error::invalid(
            "export time",
            format!("{time} is not finite"),
        ));
    }
    let d = trainer.deformed(time)?;
    let g = &trainer.model().gaussians;
    let n = g.len();
    let mut scaling = Vec::with_capacity(3 * n);
    let mut rotation = Vec::with_capacity(4 * n);
    let mut report = ExportReport {
        time,
        path: PathBuf::new(),
        gaussians: n,
        nonpositive_scales: 0,
        non_unit_rotations: 0,
        flat: 0,
    };
    for i in 0..n {
        let s: [f64; 3] = std::array::from_fn(|k| d.scales[3 * i + k].to_f64());
        let q: [f64; 4] = std::array::from_fn(|k| d.rotations[4 * i + k].to_f64());
        let m: [f64; 3] = std::array::from_fn(|k| d.means[3 * i + k].to_f64());
        if s.iter().chain(&q).chain(&m).any(|v| !v.is_finite()) {
            return Err(Error::invalid(
                "export",
                format!(
                    "Gaussian {i} at time {time}: deformed mean {m:?}, scale {s:?}, rotation {q:?} are not all finite"
                ),
            ));
        }
        if s.iter().any(|&v| v <= 0.0) {
            report.nonpositive_scales += 1;
        }
        let qn = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        if (qn - 1.0).abs() > 1e-3 {
            report.non_unit_rotations += 1;
        }
        let (lam, v) = sym3_eigen(sym3(&cov3d(s, 1.0, q)));
        let mut flat = false;
        for l in lam {
            let sd = l.max(0.0).sqrt();
            let sd = if sd < MIN_SCALE {
                flat = true;
                MIN_SCALE
            } else {
                sd
            };
            scaling.push(T::from_f64(libm::log(sd)));
        }
        report.flat += flat as usize;
        rotation.extend(rotmat_to_quat(v).map(T::from_f64));
    }
    let out = Gaussians {
        max_sh_degree: g.max_sh_degree,
        xyz: d.means,
        sh: g.sh.clone(),
        scaling,
        rotation,
        opacity: g.opacity.clone(),
    };
    Ok((out, report))
}

/// A time as file names show it: 6 decimals, `0.250000`. A time that rounds
/// to zero is `0.000000` whatever its sign (`-0` and `-1e-7` too), so one
/// name never stands for two renderings of the same rounded time.
pub fn time_label(time: f64) -> String {
    let s = format!("{time:.6}");
    match s.strip_prefix('-') {
        Some(rest) if rest.bytes().all(|b| b == b'0' || b == b'.') => rest.to_string(),
        _ => s,
    }
}

/// The file name of the export at `time`: `t0.250000.ply`.
pub fn file_name(time: f64) -> String {
    format!("t{}.ply", time_label(time))
}

/// Write the deformed Gaussians at each of `times` into `dir`
/// ([`file_name`]), in the run's precision (`float` properties for f32).
pub fn export_times<T: Real>(
    trainer: &Trainer<T>,
    times: &[f64],
    dir: &Path,
) -> Result<Vec<ExportReport>> {
    crate::io::create_dir_all(dir)?;
    times
        .iter()
        .map(|&t| {
            let (g, mut r) = deformed_gaussians(trainer, t)?;
            r.path = dir.join(file_name(t));
            ply::write_gaussians(&r.path, &g)?;
            Ok(r)
        })
        .collect()
}
