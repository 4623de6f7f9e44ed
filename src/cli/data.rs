//! `liquid-splat inspect` and `liquid-splat synth`: datasets on disk.

use crate::dataset::{self, synth, Background, LoadOptions};
use crate::error::Outcome;
use clap::{Args, ValueEnum};
use std::path::PathBuf;

/// Arguments of `inspect`.
#[derive(Args)]
pub struct InspectArgs {
    /// Dataset folder.
    pub dir: PathBuf,
    /// Downscale factor: 1, 2, 4 or 8.
    #[arg(long, default_value_t = 1)]
    pub downscale: usize,
    /// Composite RGBA images on white instead of black.
    #[arg(long)]
    pub white_background: bool,
    /// Random initial points when the dataset has no point cloud (as `train`'s option).
    #[arg(long, default_value_t = super::DEFAULT_INIT_POINTS)]
    pub init_points: usize,
}

/// Arguments of `synth`.
#[derive(Args)]
pub struct SynthArgs {
    /// Scene name: bouncing, swing or blob.
    pub name: String,
    /// Output folder (created).
    pub out_dir: PathBuf,
    /// Image width and height.
    #[arg(long, default_value_t = 64)]
    pub resolution: usize,
    /// Training frames (nerfies layout: frames of the sequence).
    #[arg(long, default_value_t = 24)]
    pub frames: usize,
    /// Frames in each of the val and test splits (D-NeRF layout; default 8).
    #[arg(long)]
    pub eval_frames: Option<usize>,
    /// Seed of the camera placement (and of the nerfies points).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Camera placement.
    #[arg(long, value_enum, default_value_t = OrbitArg::Hemisphere)]
    pub orbit: OrbitArg,
    /// Sub-pixel samples per axis.
    #[arg(long, default_value_t = 4)]
    pub supersampling: usize,
    /// On-disk layout.
    #[arg(long, value_enum, default_value_t = LayoutArg::Dnerf)]
    pub layout: LayoutArg,
    /// Background of the nerfies-layout RGB images (the D-NeRF layout's are RGBA).
    #[arg(long)]
    pub white_background: bool,
}

/// Camera placement of `synth`.
#[derive(Clone, Copy, ValueEnum)]
pub enum OrbitArg {
    /// Cameras spread over the upper hemisphere.
    Hemisphere,
    /// Cameras on a horizontal circle.
    Circle,
}

/// On-disk layout of `synth`.
#[derive(Clone, Copy, ValueEnum)]
pub enum LayoutArg {
    /// D-NeRF: transforms_{train,val,test}.json.
    Dnerf,
    /// Nerfies / NeRF-DS: dataset.json, metadata.json, camera/.
    Nerfies,
}

/// White or black background.
pub fn background(white: bool) -> Background {
    if white {
        Background::White
    } else {
        Background::Black
    }
}

/// `inspect DIR`: print the dataset's JSON summary.
pub fn inspect(a: InspectArgs) -> crate::Result<Outcome> {
    let opts = LoadOptions {
        background: background(a.white_background),
        downscale: a.downscale,
        init_points: a.init_points,
        ..Default::default()
    };
    let ds = dataset::load(&a.dir, &opts)?;
    outln!("{:#}", dataset::summary(&ds));
    Ok(Outcome::Success)
}

/// `synth NAME OUT_DIR`: write a built-in scene to disk.
pub fn synth(a: SynthArgs) -> crate::Result<Outcome> {
    // Options of the other layout are refused, not ignored.
    match a.layout {
        LayoutArg::Dnerf if a.white_background => {
            return Err(crate::Error::invalid(
                "--white-background",
                "the D-NeRF layout's images are RGBA, with no background; the option applies to --layout nerfies",
            ))
        }
        LayoutArg::Nerfies if a.eval_frames.is_some() => {
            return Err(crate::Error::invalid(
                "--eval-frames",
                "the nerfies layout is one sequence of --frames frames (dataset.json lists the even ids as train_ids, the odd ones as val_ids); the option applies to --layout dnerf",
            ))
        }
        _ => {}
    }
    let defaults = synth::SynthOptions::default();
    let opts = synth::SynthOptions {
        resolution: a.resolution,
        frames: a.frames,
        eval_frames: a.eval_frames.unwrap_or(defaults.eval_frames),
        seed: a.seed,
        orbit: match a.orbit {
            OrbitArg::Hemisphere => synth::Orbit::Hemisphere,
            OrbitArg::Circle => synth::Orbit::Circle,
        },
        supersampling: a.supersampling,
        background: background(a.white_background),
        ..Default::default()
    };
    let layout = match a.layout {
        LayoutArg::Dnerf => synth::Layout::DNerf,
        LayoutArg::Nerfies => synth::Layout::Nerfies,
    };
    synth::write(&a.name, &a.out_dir, &opts, layout)?;
    if let (synth::Layout::Nerfies, (crate::dataset::NerfiesSplit::EveryFourth, _)) =
        (layout, crate::dataset::nerfies::upstream_rule(&a.out_dir))
    {
        // (Upstream's loader picks the split from the parent folder's name.)
        eprintln!(
            "note: {} is loaded with upstream's rule for a parent folder not named vrig*, NeRF* \
             or interp*: every fourth id trains and none is a test view, so `train` cannot \
             evaluate it; written under a parent named NeRF* (e.g. NeRF-DS/{}), its train_ids \
             and val_ids are used",
            a.out_dir.display(),
            a.name
        );
    }
    Ok(Outcome::Success)
}
