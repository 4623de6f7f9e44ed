//! Training: the D-3DGS pipeline with a selectable deformation field.
//!
//! - [`config`]: [`TrainConfig`] and the rule that scales schedules to short runs.
//! - [`cameras`]: the order of training views.
//! - [`deformed`]: canonical Gaussians + offsets → rasterizer inputs, and back.
//! - [`trainer`]: [`Trainer::step`], one iteration.
//! - [`checkpoint`]: atomic, verified checkpoints; resume.
//! - [`export`]: the deformed Gaussians at a time as a static Inria PLY.
//! - [`run`](mod@run): a whole run with evaluation and outputs.

pub mod cameras;
pub mod checkpoint;
pub mod config;
pub mod deformed;
pub mod export;
pub mod run;
pub mod trainer;

pub use config::{Schedule, TrainConfig};
pub use run::{run, CurvePoint, Event, RunOptions, RunSummary};
pub use trainer::{Gradients, StageTimes, StepReport, Trainer, View, ViewMetrics};
