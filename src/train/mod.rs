//! Training: the D-3DGS pipeline with a selectable deformation field.
//!
//! - [`config`]: [`TrainConfig`] and the rule that scales schedules to short runs.
//! - [`cameras`]: the order of training views.
//! - [`deformed`]: canonical Gaussians + offsets → rasterizer inputs, and back.
//! - [`model`]: [`Model`] (Gaussians, field, SH degree, background) with its
//!   forward, backward and render, and [`ModelOptimizer`], the update.
//! - [`trainer`]: [`Trainer`] (model, optimizer, statistics, sampler,
//!   schedules) and [`Trainer::step`], one iteration.
//! - [`state`]: the training state as named tensors, shared by checkpoints
//!   and the oracle's `step` stage.
//! - [`checkpoint`]: atomic, verified checkpoints; resume.
//! - [`export`]: the deformed Gaussians at a time as a static Inria PLY.
//! - [`run`](mod@run): a whole run with evaluation and outputs.

pub mod cameras;
pub mod checkpoint;
pub mod config;
pub mod deformed;
pub mod export;
pub mod model;
pub mod run;
pub mod state;
pub mod trainer;

pub use config::{Schedule, TrainConfig};
pub use model::{Gradients, Model, ModelGradients, ModelOptimizer, ModelSaved};
pub use run::{run, CurvePoint, Event, RunOptions, RunSummary};
pub use trainer::{StageTimes, StepReport, Trainer, View, ViewMetrics};
