//! The `liquid-splat` command-line tool: a thin layer over the library. This
//! is the only place errors become messages and exit codes.
//!
//! Exit codes: 0 success; 1 a check or comparison failed; 2 unusable input
//! (bad arguments, missing or malformed files).

use clap::{Parser, Subcommand, ValueEnum};
use liquid_splat::dataset::{self, synth, Background, LoadOptions};
use std::path::PathBuf;
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "liquid-splat",
    version,
    about = "Deterministic CPU reference for deformable 3D Gaussian splatting with a liquid (CfC) deformation field"
)]
struct Cli {
    /// Worker threads (default: all cores). Results are bit-identical for any value.
    #[arg(long, global = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Load a dataset (D-NeRF or nerfies layout) and print a JSON summary.
    Inspect {
        /// Dataset folder.
        dir: PathBuf,
        /// Downscale factor: 1, 2, 4 or 8.
        #[arg(long, default_value_t = 1)]
        downscale: usize,
        /// Composite RGBA images on white instead of black.
        #[arg(long)]
        white_background: bool,
    },
    /// Generate a built-in synthetic dynamic scene (bouncing, swing, blob) on disk.
    Synth {
        /// Scene name: bouncing, swing or blob.
        name: String,
        /// Output folder (created).
        out_dir: PathBuf,
        /// Image width and height.
        #[arg(long, default_value_t = 64)]
        resolution: usize,
        /// Training frames (nerfies layout: frames of the sequence).
        #[arg(long, default_value_t = 24)]
        frames: usize,
        /// Frames in each of the val and test splits.
        #[arg(long, default_value_t = 8)]
        eval_frames: usize,
        /// Seed of the camera placement (and of the nerfies points).
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Camera placement.
        #[arg(long, value_enum, default_value_t = OrbitArg::Hemisphere)]
        orbit: OrbitArg,
        /// Sub-pixel samples per axis.
        #[arg(long, default_value_t = 4)]
        supersampling: usize,
        /// On-disk layout.
        #[arg(long, value_enum, default_value_t = LayoutArg::Dnerf)]
        layout: LayoutArg,
        /// Background of the nerfies-layout RGB images.
        #[arg(long)]
        white_background: bool,
    },
}

#[derive(Clone, Copy, ValueEnum)]
enum OrbitArg {
    Hemisphere,
    Circle,
}

#[derive(Clone, Copy, ValueEnum)]
enum LayoutArg {
    Dnerf,
    Nerfies,
}

fn background(white: bool) -> Background {
    if white {
        Background::White
    } else {
        Background::Black
    }
}

fn inspect(dir: PathBuf, downscale: usize, white: bool) -> liquid_splat::Result<()> {
    let opts = LoadOptions {
        background: background(white),
        downscale,
        ..Default::default()
    };
    let ds = dataset::load(&dir, &opts)?;
    println!("{:#}", dataset::summary(&ds));
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Some(n) = cli.threads {
        if let Err(e) = rayon::ThreadPoolBuilder::new()
            .num_threads(n.max(1))
            .build_global()
        {
            eprintln!("error: cannot start {n} threads: {e}");
            return ExitCode::from(2);
        }
    }
    let result = match cli.command {
        Command::Inspect {
            dir,
            downscale,
            white_background,
        } => inspect(dir, downscale, white_background),
        Command::Synth {
            name,
            out_dir,
            resolution,
            frames,
            eval_frames,
            seed,
            orbit,
            supersampling,
            layout,
            white_background,
        } => {
            let opts = synth::SynthOptions {
                resolution,
                frames,
                eval_frames,
                seed,
                orbit: match orbit {
                    OrbitArg::Hemisphere => synth::Orbit::Hemisphere,
                    OrbitArg::Circle => synth::Orbit::Circle,
                },
                supersampling,
                background: background(white_background),
                ..Default::default()
            };
            let layout = match layout {
                LayoutArg::Dnerf => synth::Layout::DNerf,
                LayoutArg::Nerfies => synth::Layout::Nerfies,
            };
            synth::write(&name, &out_dir, &opts, layout)
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::from(2)
        }
    }
}
