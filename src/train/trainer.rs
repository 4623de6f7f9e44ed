//! The training state and one iteration of D-3DGS (docs/UPSTREAM.md §6.4–6.6).
//!
//! [`Trainer::step`] is the whole data flow of an iteration:
//! camera + time → field → deformed Gaussians → rasterizer → loss → the
//! backward of each stage in reverse → densification → Adam.
//!
//! Deliberate deviations from upstream, each for determinism or clarity:
//! - Random numbers come from the run's seed through [`Rng`] streams (camera
//!   order, AST noise, split sampling), not Python/torch/CUDA generators.
//! - f_dc and f_rest share one Adam state with per-coefficient rates (exact,
//!   see [`crate::optim`]).
//! - Every schedule is scaled to the run's length ([`super::config`]).

use super::cameras::CameraSampler;
use super::config::TrainConfig;
use super::deformed::{Deformed, Offsets};
use super::model::{Model, ModelOptimizer};
use crate::camera::{Camera, RasterCamera};
use crate::deform::Field;
use crate::densify::{densify_and_prune, reset_opacity, DensifyReport, DensifyStats};
use crate::error::{Error, Result};
use crate::gaussians::{Gaussians, Group};
use crate::loss::metrics;
use crate::math::{Real, Rng};
use crate::optim::{AdamState, StepGroups};
use crate::render::RasterOutput;
use std::time::Instant;

/// Stream indices of the run seed's generators.
const STREAM_FIELD_INIT: u64 = 1;
const STREAM_AST: u64 = 2;
const STREAM_SPLIT: u64 = 3;

/// A training view: camera, time and ground truth in the run's precision.
#[derive(Clone, Debug)]
pub struct View<T> {
    /// The frame's name (its file path in the dataset).
    pub name: String,
    /// The camera in the rasterizer's form.
    pub camera: RasterCamera<T>,
    /// Normalised time of the frame.
    pub time: f64,
    /// Ground truth `[3, H, W]`.
    pub image: Vec<T>,
    /// Image width W in pixels.
    pub width: usize,
    /// Image height H in pixels.
    pub height: usize,
}

impl<T: Real> View<T> {
    /// The view of `camera` at `time` with ground truth `image` (`[3, H, W]`).
    pub fn new(name: &str, camera: &Camera, time: f64, image: &[f32]) -> Self {
        View {
            name: name.to_string(),
            camera: camera.raster(),
            time,
            image: image.iter().map(|&v| T::from_f32(v)).collect(),
            width: camera.width,
            height: camera.height,
        }
    }
}

/// What one iteration did.
#[derive(Clone, Debug, PartialEq)]
pub struct StepReport {
    /// The iteration (1-based) this report is of.
    pub iteration: u64,
    /// The training loss.
    pub loss: f64,
    /// The L1 part of the loss.
    pub l1: f64,
    /// PSNR of the unclamped render against the view (logging only).
    pub psnr: f64,
    /// Index of the training view used.
    pub view: usize,
    /// Number of Gaussians after the iteration.
    pub gaussians: usize,
    /// What densification did, on a densification iteration.
    pub densify: Option<DensifyReport>,
    /// Whether the opacities were reset.
    pub opacity_reset: bool,
    /// Wall-clock time of each stage (measurement only, not state).
    pub times: StageTimes,
}

/// Seconds spent in each stage of one iteration.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct StageTimes {
    /// The field's forward and the deformation.
    pub field_forward: f64,
    /// The rasterizer's forward.
    pub raster_forward: f64,
    /// The loss and its gradient.
    pub loss: f64,
    /// The rasterizer's backward.
    pub raster_backward: f64,
    /// The field's backward and the activations' chain rule.
    pub field_backward: f64,
    /// Statistics, densification and opacity reset.
    pub densify: f64,
    /// The Adam steps.
    pub optimizer: f64,
}

impl StageTimes {
    /// Names of the stages, in [`values`](Self::values)' order.
    pub const NAMES: [&'static str; 7] = [
        "field forward",
        "raster forward",
        "loss",
        "raster backward",
        "field backward",
        "densify",
        "optimizer",
    ];
    /// The seconds of each stage, in [`NAMES`](Self::NAMES)' order.
    pub fn values(&self) -> [f64; 7] {
        [
            self.field_forward,
            self.raster_forward,
            self.loss,
            self.raster_backward,
            self.field_backward,
            self.densify,
            self.optimizer,
        ]
    }
    /// Add `o`'s seconds stage by stage.
    pub fn add(&mut self, o: &StageTimes) {
        self.field_forward += o.field_forward;
        self.raster_forward += o.raster_forward;
        self.loss += o.loss;
        self.raster_backward += o.raster_backward;
        self.field_backward += o.field_backward;
        self.densify += o.densify;
        self.optimizer += o.optimizer;
    }
}

/// Seconds since the last lap.
pub(super) struct Lap(pub(super) Instant);

impl Lap {
    pub(super) fn lap(&mut self) -> f64 {
        let now = Instant::now();
        let d = now.duration_since(self.0).as_secs_f64();
        self.0 = now;
        d
    }
}

/// PSNR, SSIM and (when weights were given) LPIPS of one test view (8-bit
/// quantised, as upstream's metrics).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ViewMetrics {
    /// The view's name.
    pub name: String,
    /// PSNR in dB.
    pub psnr: f64,
    /// SSIM.
    pub ssim: f64,
    /// Absent when no LPIPS weights were given (never a placeholder number).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
}

/// The complete state of a run, everything a checkpoint stores: the model,
/// its optimizer, the densification statistics, the view sampler and AST
/// generator, and the schedules (in the configuration).
#[derive(Clone, Debug)]
pub struct Trainer<T> {
    config: TrainConfig,
    /// Completed iterations.
    iteration: u64,
    model: Model<T>,
    optimizer: ModelOptimizer<T>,
    stats: DensifyStats<T>,
    sampler: CameraSampler,
    ast_rng: Rng,
    /// Scene extent for densification (`cameras_extent`).
    extent: f64,
}

/// Where a run stands besides its model, optimizer and statistics (what a
/// checkpoint restores).
pub(super) struct Progress {
    /// Completed iterations.
    pub iteration: u64,
    /// The view sampler's state.
    pub sampler: CameraSampler,
    /// The AST noise generator's state.
    pub ast_rng: Rng,
}

/// The order in which [`Trainer::state_hash`] hashes the Gaussian
/// parameters (the Adam states follow [`Group::ALL`]): part of the hashes
/// recorded in `fixtures/training/record.json`.
const HASH_PARAMETER_ORDER: [Group; 5] = [
    Group::Xyz,
    Group::Sh,
    Group::Scaling,
    Group::Rotation,
    Group::Opacity,
];

/// A non-finite loss would spread to every parameter it reaches: the run
/// stops at the iteration that gave it, before its update.
fn check_loss(it: u64, loss: f64, view: usize) -> Result<()> {
    if loss.is_finite() {
        return Ok(());
    }
    Err(Error::invalid(
        "training",
        format!(
            "iteration {it}: the loss is {loss} on view {view}; the run diverged and stops \
             here (the model is as before this iteration)"
        ),
    ))
}

impl<T: Real> Trainer<T> {
    /// A fresh run from initial Gaussians, for `views` training cameras.
    pub fn new(
        config: TrainConfig,
        gaussians: Gaussians<T>,
        views: usize,
        extent: f64,
        background: [f64; 3],
    ) -> Result<Self> {
        config.validate()?;
        gaussians.validate()?;
        // (Finite points far apart can give scales that overflow.)
        for group in Group::ALL {
            let w = gaussians.width(group).max(1);
            let values = gaussians.group(group);
            if let Some(k) = values.iter().position(|v| !v.is_finite()) {
                return Err(Error::invalid(
                    "Gaussians",
                    format!(
                        "{} of Gaussian {} is {}, not finite (from a point cloud whose \
                         coordinates or spacing overflow {}? rescale the scene)",
                        group.name(),
                        k / w,
                        values[k].to_f64(),
                        std::any::type_name::<T>()
                    ),
                ));
            }
        }
        if views == 0 {
            return Err(Error::invalid("training views", "the train split is empty"));
        }
        if gaussians.max_sh_degree != config.max_sh_degree {
            return Err(Error::invalid(
                "initial Gaussians",
                format!(
                    "SH degree {} but the run uses {}",
                    gaussians.max_sh_degree, config.max_sh_degree
                ),
            ));
        }
        let field = Field::new(
            config.field,
            Rng::stream(config.seed, STREAM_FIELD_INIT).next_u64(),
        )?;
        let model = Model {
            gaussians,
            field,
            active_sh_degree: 0,
            background,
        };
        Ok(Trainer {
            iteration: 0,
            optimizer: ModelOptimizer::new(&model),
            stats: DensifyStats::new(model.gaussians.len()),
            sampler: CameraSampler::new(views, config.seed),
            ast_rng: Rng::stream(config.seed, STREAM_AST),
            config,
            model,
            extent,
        })
    }

    /// A run restored from its parts (a checkpoint): errors if they are not
    /// sized for the same Gaussians and field.
    pub(super) fn restore(
        config: TrainConfig,
        model: Model<T>,
        optimizer: ModelOptimizer<T>,
        stats: DensifyStats<T>,
        progress: Progress,
        extent: f64,
    ) -> Result<Self> {
        model.validate()?;
        if progress.sampler.count() == 0 {
            return Err(Error::invalid("training views", "the sampler has no views"));
        }
        let n = model.gaussians.len();
        if !optimizer.gaussians.fits(&model.gaussians)
            || optimizer.field.len() != model.field.param_count()
            || stats.len() != n
        {
            return Err(Error::invalid(
                "training state",
                format!(
                    "{n} Gaussians and {} field weights, optimizer state for {} and {}, statistics for {}",
                    model.field.param_count(),
                    optimizer.gaussians.len(),
                    optimizer.field.len(),
                    stats.len()
                ),
            ));
        }
        Ok(Trainer {
            config,
            iteration: progress.iteration,
            model,
            optimizer,
            stats,
            sampler: progress.sampler,
            ast_rng: progress.ast_rng,
            extent,
        })
    }

    /// The run's configuration (schedules included).
    pub fn config(&self) -> &TrainConfig {
        &self.config
    }

    /// Completed iterations.
    pub fn iteration(&self) -> u64 {
        self.iteration
    }

    /// The model being trained.
    pub fn model(&self) -> &Model<T> {
        &self.model
    }

    /// The Adam states of the model's parameters.
    pub fn optimizer(&self) -> &ModelOptimizer<T> {
        &self.optimizer
    }

    /// The densification statistics.
    pub fn stats(&self) -> &DensifyStats<T> {
        &self.stats
    }

    /// The training-view sampler.
    pub fn sampler(&self) -> &CameraSampler {
        &self.sampler
    }

    /// The generator of the AST time noise.
    pub(super) fn ast_rng(&self) -> &Rng {
        &self.ast_rng
    }

    /// Scene extent for densification (`cameras_extent`).
    pub fn extent(&self) -> f64 {
        self.extent
    }

    /// Whether the field is used at iteration `it` (1-based).
    pub fn field_active(&self, it: u64) -> bool {
        it >= self.config.schedule.warm_up
    }

    /// One training iteration on `views` (the train split, in the order the
    /// sampler was created for).
    pub fn step(&mut self, views: &[View<T>]) -> Result<StepReport> {
        let it = self.iteration + 1;
        let cfg = &self.config;
        if it.is_multiple_of(cfg.schedule.sh_degree_interval)
            && self.model.active_sh_degree < cfg.max_sh_degree
        {
            self.model.active_sh_degree += 1;
        }
        let pick = self.sampler.draw();
        let view = views.get(pick.index).ok_or_else(|| {
            Error::invalid(
                "training views",
                format!("{} views, sampler picked {}", views.len(), pick.index),
            )
        })?;
        let field_on = self.field_active(it);
        let mut time = view.time;
        if cfg.ast && field_on {
            time += self.ast_rng.normal() / pick.remaining as f64 * cfg.lr.ast_smooth(it as i64);
        }

        // (The pool's workers poll for work between the stages.)
        let (g, mut times) = crate::threads::keep_awake(|| {
            self.model.gradients(view, time, field_on, cfg.lambda_dssim)
        })?;
        check_loss(it, g.loss.loss.to_f64(), pick.index)?;
        let mut clock = Lap(Instant::now());

        // Densification, then Adam with the rates of iteration it − 1.
        let (densify, reset, groups) = self.densify(it, &g.radii, &g.model.means2d)?;
        times.densify = clock.lap();
        if it < self.config.iterations {
            let rates = self.config.lr.at(it as i64 - 1);
            self.optimizer
                .step(&mut self.model, &g.model, &rates, groups)?;
        }
        times.optimizer = clock.lap();
        self.iteration = it;
        Ok(StepReport {
            iteration: it,
            loss: g.loss.loss.to_f64(),
            l1: g.loss.l1.to_f64(),
            psnr: metrics::psnr_raw(&g.image, &view.image).to_f64(),
            view: pick.index,
            gaussians: self.model.gaussians.len(),
            densify,
            opacity_reset: reset,
            times,
        })
    }

    /// Statistics, densify/prune and opacity reset for iteration `it`
    /// (docs/UPSTREAM.md §6.5). Returns which Gaussian groups may still step.
    fn densify(
        &mut self,
        it: u64,
        radii: &[i32],
        grad_means2d: &[T],
    ) -> Result<(Option<DensifyReport>, bool, StepGroups)> {
        let s = &self.config.schedule;
        if it >= s.densify_until {
            return Ok((None, false, StepGroups::All));
        }
        self.stats.update(radii, grad_means2d)?;
        let (gaussians, optimizer) = (&mut self.model.gaussians, &mut self.optimizer.gaussians);
        let mut report = None;
        if it > s.densify_from && it.is_multiple_of(s.densification_interval) {
            let seed = Rng::stream(self.config.seed ^ STREAM_SPLIT, it).next_u64();
            report = Some(densify_and_prune(
                gaussians,
                optimizer,
                &mut self.stats,
                self.extent,
                it,
                &self.config.densify,
                seed,
            )?);
        }
        let white = self.model.background == [1.0; 3];
        let reset = it.is_multiple_of(s.opacity_reset_interval) || (white && it == s.densify_from);
        if reset {
            reset_opacity(gaussians, optimizer)?;
        }
        let groups = match (report.is_some(), reset) {
            (true, _) => StepGroups::None,
            (false, true) => StepGroups::AllButOpacity,
            (false, false) => StepGroups::All,
        };
        Ok((report, reset, groups))
    }

    /// Whether the field is on for renders of the current state: once
    /// warm-up is over, as in upstream's render.py.
    fn field_on_now(&self) -> bool {
        self.field_active(self.iteration.max(1))
    }

    /// Render the current model from `camera` at `time` (no AST noise; the
    /// field is used once warm-up is over, as in upstream's render.py).
    pub fn render(&self, camera: &RasterCamera<T>, time: f64) -> Result<RasterOutput<T>> {
        self.model.render(camera, time, self.field_on_now())
    }

    /// The deformed, activated Gaussians the renderer receives at `time`
    /// (means, scales, rotations, opacities; the SH are the model's).
    pub fn deformed(&self, time: f64) -> Result<Deformed<T>> {
        self.model.deformed(time, self.field_on_now())
    }

    /// The field's offsets at `time` for every Gaussian (zeros during warm-up).
    pub fn offsets(&self, time: f64) -> Result<Offsets<T>> {
        self.model.offsets(time, self.field_on_now())
    }

    /// PSNR and SSIM of each view on 8-bit quantised renders.
    pub fn evaluate(&self, views: &[View<T>]) -> Result<Vec<ViewMetrics>> {
        self.evaluate_with(views, None)
    }

    /// [`evaluate`](Self::evaluate), with LPIPS too when `lpips` is given.
    pub fn evaluate_with(
        &self,
        views: &[View<T>],
        lpips: Option<&crate::lpips::Metric>,
    ) -> Result<Vec<ViewMetrics>> {
        views
            .iter()
            .map(|v| {
                let out = self.render(&v.camera, v.time)?;
                view_metrics_with(&v.name, &out.color, &v.image, v.height, v.width, lpips)
            })
            .collect()
    }

    /// FNV-1a hash of the whole state (every parameter, moment, statistic
    /// and generator), in a fixed order: equal hashes mean bit-identical runs.
    pub fn state_hash(&self) -> u64 {
        let mut h = Fnv::new();
        h.u64(self.iteration);
        h.u64(self.model.active_sh_degree as u64);
        for group in HASH_PARAMETER_ORDER {
            h.reals(self.model.gaussians.group(group));
        }
        h.reals(self.model.field.params());
        let o = &self.optimizer;
        let adam = Group::ALL.iter().map(|&g| o.gaussians.state(g));
        for a in adam.chain([&o.field]) {
            hash_adam(&mut h, a);
        }
        h.reals(&self.stats.accum);
        for &d in &self.stats.denom {
            h.u64(d as u64);
        }
        for &r in &self.stats.max_radii {
            h.u64(r as u64);
        }
        for &i in self.sampler.stack() {
            h.u64(i as u64);
        }
        h.u64(self.sampler.rng_state());
        h.u64(self.ast_rng.state());
        h.0
    }
}

/// Moments and step counter of one Adam state, into `h`.
fn hash_adam<T: Real>(h: &mut Fnv, a: &AdamState<T>) {
    h.reals(&a.m);
    h.reals(&a.v);
    h.u64(a.step);
}

/// PSNR and SSIM of `render` against `gt` (`[3, h, w]`) after both are
/// quantised to 8 bits as torchvision's `save_image` does.
pub fn view_metrics<T: Real>(
    name: &str,
    render: &[T],
    gt: &[T],
    h: usize,
    w: usize,
) -> Result<ViewMetrics> {
    view_metrics_with(name, render, gt, h, w, None)
}

/// [`view_metrics`], with LPIPS ([`crate::lpips::Metric::view`], on the
/// same 8-bit images) when `lpips` is given.
pub fn view_metrics_with<T: Real>(
    name: &str,
    render: &[T],
    gt: &[T],
    h: usize,
    w: usize,
    lpips: Option<&crate::lpips::Metric>,
) -> Result<ViewMetrics> {
    Ok(ViewMetrics {
        name: name.to_string(),
        psnr: metrics::psnr(render, gt, h, w)?.to_f64(),
        ssim: metrics::ssim_u8(render, gt, h, w)?.to_f64(),
        lpips: lpips.map(|m| m.view(render, gt, h, w)).transpose()?,
    })
}

/// 64-bit FNV-1a, the hash of the state and of checkpoint files.
pub(crate) struct Fnv(pub u64);

impl Fnv {
    /// The FNV-1a offset basis.
    pub fn new() -> Self {
        Fnv(0xcbf2_9ce4_8422_2325)
    }
    /// FNV-1a over 64-bit words instead of bytes (for large inputs such as
    /// images; a different hash from [`bytes`](Self::bytes)).
    pub fn words(&mut self, w: impl IntoIterator<Item = u64>) {
        for x in w {
            self.0 = (self.0 ^ x).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    /// FNV-1a over bytes.
    pub fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 = (self.0 ^ x as u64).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    /// The eight little-endian bytes of `v`.
    pub fn u64(&mut self, v: u64) {
        self.bytes(&v.to_le_bytes());
    }
    /// The length of `v`, then the bits of each value.
    pub fn reals<T: Real>(&mut self, v: &[T]) {
        self.u64(v.len() as u64);
        for x in v {
            self.u64(x.bits());
        }
    }
}
