//! `liquid-splat bench ...`: the arguments of the measurements in
//! [`crate::bench`] (never asserted in tests).

use crate::bench;
use crate::deform::FieldKind;
use crate::error::Outcome;
use crate::lpips;
use clap::Subcommand;

/// A clap parser for a count in `LO..=HI` (refused with exit 2 otherwise).
fn count_in<const LO: usize, const HI: usize>(s: &str) -> Result<usize, String> {
    let v: usize = s.parse().map_err(|e| format!("{s:?}: {e}"))?;
    if (LO..=HI).contains(&v) {
        Ok(v)
    } else {
        Err(format!("{v} is not in {LO}..={HI}"))
    }
}

/// Subcommands of `bench`.
#[derive(Subcommand)]
pub enum BenchWhat {
    /// Rasterizer forward and backward at 800x800/50k, 400x400/20k and 64x64/2.6k Gaussians,
    /// on 1 thread and on --threads (default all cores), timed in alternating rounds: the
    /// fastest pass in ms, the speed-up over 1 thread, pairs evaluated, pairs/s and % of the
    /// FMA peak.
    Raster {
        /// Rounds: in each, every thread count in turn runs one untimed forward and backward,
        /// then timed ones for at least 0.25 s (the fastest of all rounds is reported).
        #[arg(long, default_value_t = 5, value_parser = count_in::<1, 1_000_000>)]
        reps: usize,
    },
    /// Milliseconds per training iteration split by stage, on a dataset or built-in scene.
    Train {
        /// The run to time.
        #[command(flatten)]
        run: super::train::RunArgs,
    },
    /// Deformation fields forward and forward+backward (MLP D8 W256, CfC D6 W128), f32.
    Deform {
        /// Number of Gaussians (at most 2^24).
        #[arg(long, default_value_t = 20_000, value_parser = count_in::<1, 16_777_216>)]
        n: usize,
        /// Repetitions per measurement (the median is reported).
        #[arg(long, default_value_t = 5, value_parser = count_in::<1, 1_000_000>)]
        reps: usize,
        /// Run in f64 instead of f32.
        #[arg(long)]
        f64: bool,
        /// Only this field (mlp or cfc); both by default.
        #[arg(long)]
        field: Option<String>,
    },
    /// LPIPS (VGG16) of one image pair: milliseconds per pair and the convolutions' GFLOP/s.
    Lpips {
        /// Image width and height (16 to 4096).
        #[arg(long, default_value_t = 800, value_parser = count_in::<16, 4096>)]
        size: usize,
        /// Repetitions (the median is reported).
        #[arg(long, default_value_t = 3, value_parser = count_in::<1, 1_000_000>)]
        reps: usize,
        /// Run in f64 instead of f32.
        #[arg(long)]
        f64: bool,
        /// torchvision's vgg16-397923af.pth and the lpips package's vgg.pth; without them,
        /// random weights of the same shapes (the time does not depend on the values).
        #[arg(long, num_args = 2, value_names = ["VGG16_PTH", "LIN_PTH"])]
        weights: Option<Vec<std::path::PathBuf>>,
    },
}

/// Run a `bench` subcommand.
pub fn run(what: BenchWhat) -> crate::Result<Outcome> {
    match what {
        BenchWhat::Raster { reps } => bench::raster(reps, &bench::harness::one_and_pool_threads())?,
        BenchWhat::Train { run } => bench::train(&run.spec())?,
        BenchWhat::Deform {
            n,
            reps,
            f64,
            field,
        } => {
            let only = field.as_deref().map(FieldKind::parse).transpose()?;
            if f64 {
                bench::deform::<f64>(n, reps, only, true)?
            } else {
                bench::deform::<f32>(n, reps, only, true)?
            }
        }
        BenchWhat::Lpips {
            size,
            reps,
            f64,
            weights,
        } => {
            let w = match weights.as_deref() {
                Some([vgg, lin]) => lpips::LpipsWeights::load(vgg, lin, lpips::Verify::Any)?,
                _ => bench::random_lpips_weights(0)?,
            };
            if f64 {
                bench::lpips::<f64>(&w, size, reps)?
            } else {
                bench::lpips::<f32>(&w, size, reps)?
            }
        }
    }
    Ok(Outcome::Success)
}
