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
use super::deformed::{deform_gaussians, deform_gaussians_vjp, Offsets};
use crate::camera::{Camera, RasterCamera};
use crate::deform::{Field, FieldSaved};
use crate::densify::{densify_and_prune, reset_opacity, DensifyReport, DensifyStats};
use crate::error::{Error, Result};
use crate::gaussians::Gaussians;
use crate::loss::{loss_and_grad, metrics, LossOutput};
use crate::math::{Real, Rng};
use crate::optim::{AdamState, GaussianOptimizer, StepGroups};
use crate::render::{
    rasterize, rasterize_backward, Colors, Covariances, GradientMode, RasterInput, RasterOutput,
};
use std::time::Instant;

/// Stream indices of the run seed's generators.
const STREAM_FIELD_INIT: u64 = 1;
const STREAM_AST: u64 = 2;
const STREAM_SPLIT: u64 = 3;

/// A training view: camera, time and ground truth in the run's precision.
#[derive(Clone, Debug)]
pub struct View<T> {
    pub name: String,
    pub camera: RasterCamera<T>,
    pub time: f64,
    /// `[3, H, W]`.
    pub image: Vec<T>,
    pub width: usize,
    pub height: usize,
}

impl<T: Real> View<T> {
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
    pub iteration: u64,
    pub loss: f64,
    pub l1: f64,
    /// PSNR of the unclamped render against the view (logging only).
    pub psnr: f64,
    pub view: usize,
    pub gaussians: usize,
    pub densify: Option<DensifyReport>,
    pub opacity_reset: bool,
    /// Wall-clock time of each stage (measurement only, not state).
    pub times: StageTimes,
}

/// Seconds spent in each stage of one iteration.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct StageTimes {
    pub field_forward: f64,
    pub raster_forward: f64,
    pub loss: f64,
    pub raster_backward: f64,
    /// The field's backward and the activations' chain rule.
    pub field_backward: f64,
    pub densify: f64,
    pub optimizer: f64,
}

impl StageTimes {
    pub const NAMES: [&'static str; 7] = [
        "field forward",
        "raster forward",
        "loss",
        "raster backward",
        "field backward",
        "densify",
        "optimizer",
    ];
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
struct Lap(Instant);

impl Lap {
    fn lap(&mut self) -> f64 {
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
    pub name: String,
    pub psnr: f64,
    pub ssim: f64,
    /// Absent when no LPIPS weights were given (never a placeholder number).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub lpips: Option<f64>,
}

/// The complete state of a run: everything a checkpoint stores.
#[derive(Clone, Debug)]
pub struct Trainer<T> {
    pub config: TrainConfig,
    /// Completed iterations.
    pub iteration: u64,
    pub active_sh_degree: usize,
    pub gaussians: Gaussians<T>,
    pub field: Field<T>,
    pub optimizer: GaussianOptimizer<T>,
    pub field_optimizer: AdamState<T>,
    pub stats: DensifyStats<T>,
    pub sampler: CameraSampler,
    pub ast_rng: Rng,
    /// Scene extent for densification (`cameras_extent`).
    pub extent: f64,
    pub background: [f64; 3],
}

/// Loss and gradients of one view ([`Trainer::gradients`]).
#[derive(Clone, Debug)]
pub struct Gradients<T> {
    pub loss: LossOutput<T>,
    /// The render `[3, H, W]`.
    pub image: Vec<T>,
    pub radii: Vec<i32>,
    /// `[N, 3]` NDC means2D gradient (densification statistic).
    pub grad_means2d: Vec<T>,
    /// Gradients of the canonical raw parameters (same layout). The means'
    /// is upstream's: the field reads them stop-gradient, so it is the
    /// rasterizer's means gradient `g` for the additive fields and `Rᵀ·g`
    /// for the 6-DoF MLP (whose warp moves the non-detached mean to
    /// `R·x + p`); with the field on it is not the total derivative of the loss.
    pub gaussians: Gaussians<T>,
    /// Gradient of the field weights; `None` with the field off.
    pub field: Option<Vec<T>>,
}

/// The forward pass of one view, kept for the backward.
struct Forward<T> {
    offsets: Option<(Offsets<T>, FieldSaved<T>)>,
    scales: Vec<T>,
    rotations: Vec<T>,
    means: Vec<T>,
    opacities: Vec<T>,
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
        Ok(Trainer {
            iteration: 0,
            active_sh_degree: 0,
            optimizer: GaussianOptimizer::new(&gaussians),
            field_optimizer: AdamState::new(field.param_count()),
            stats: DensifyStats::new(gaussians.len()),
            sampler: CameraSampler::new(views, config.seed),
            ast_rng: Rng::stream(config.seed, STREAM_AST),
            config,
            gaussians,
            field,
            extent,
            background,
        })
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
            && self.active_sh_degree < cfg.max_sh_degree
        {
            self.active_sh_degree += 1;
        }
        let pick = self.sampler.next();
        let view = views.get(pick.index).ok_or_else(|| {
            Error::invalid(
                "training views",
                format!("{} views, sampler picked {}", views.len(), pick.index),
            )
        })?;
        let mut time = view.time;
        if cfg.ast && self.field_active(it) {
            let noise =
                self.ast_rng.normal() / pick.remaining as f64 * cfg.lr.ast_smooth(it as i64);
            time += noise;
        }

        let (g, mut times) = self.gradients(view, time, self.field_active(it))?;
        let mut clock = Lap(Instant::now());

        // Densification, then Adam with the rates of iteration it − 1.
        let (densify, reset, groups) = self.densify(it, &g.radii, &g.grad_means2d)?;
        times.densify = clock.lap();
        if it < self.config.iterations {
            let step = it as i64 - 1;
            if groups != StepGroups::None {
                let lrs = self.config.lr.gaussian(step);
                self.optimizer
                    .step(&mut self.gaussians, &g.gaussians, &lrs, groups)?;
            }
            if let Some(fg) = &g.field {
                let lr = self.config.lr.deform(step);
                self.field_optimizer.step(self.field.params_mut(), fg, lr)?;
            }
        }
        times.optimizer = clock.lap();
        self.iteration = it;
        Ok(StepReport {
            iteration: it,
            loss: g.loss.loss.to_f64(),
            l1: g.loss.l1.to_f64(),
            psnr: metrics::psnr_raw(&g.image, &view.image).to_f64(),
            view: pick.index,
            gaussians: self.gaussians.len(),
            densify,
            opacity_reset: reset,
            times,
        })
    }

    /// Loss and the gradient of every canonical parameter and field weight
    /// for one view at `time` (exact gradient mode), changing nothing: the
    /// forward and backward half of [`step`](Self::step).
    pub fn gradients(
        &self,
        view: &View<T>,
        time: f64,
        field_on: bool,
    ) -> Result<(Gradients<T>, StageTimes)> {
        let mut times = StageTimes::default();
        let mut clock = Lap(Instant::now());
        let fwd = self.forward(time, field_on)?;
        times.field_forward = clock.lap();
        let input = self.raster_input(&fwd, &view.camera);
        let (out, state) = rasterize(&input)?;
        times.raster_forward = clock.lap();
        let (loss, grad_image) = loss_and_grad(
            &out.color,
            &view.image,
            view.height,
            view.width,
            self.config.lambda_dssim,
        )?;
        times.loss = clock.lap();

        // Backward, stage by stage in reverse. The field's backward runs
        // inside the activations' ([`deform_gaussians_vjp`]), which adds its
        // gradient of the canonical means to the identity path.
        let rg = rasterize_backward(&input, &state, &grad_image, None, GradientMode::Exact)?;
        times.raster_backward = clock.lap();
        let field = fwd.offsets.as_ref().map(|(_, cache)| (&self.field, cache));
        let (gaussians, field) = deform_gaussians_vjp(&self.gaussians, field, &rg)?;
        let field = field.map(|f| f.params);
        times.field_backward = clock.lap();
        Ok((
            Gradients {
                loss,
                image: out.color,
                radii: out.radii,
                grad_means2d: rg.means2d,
                gaussians,
                field,
            },
            times,
        ))
    }

    /// Field (if `active`) and the rasterizer's inputs at `time`.
    fn forward(&self, time: f64, active: bool) -> Result<Forward<T>> {
        let g = &self.gaussians;
        let offsets = if active {
            let t = vec![T::from_f64(time); g.len()];
            Some(self.field.forward(&g.xyz, &t)?)
        } else {
            None
        };
        let d = deform_gaussians(g, offsets.as_ref().map(|(o, _)| o));
        Ok(Forward {
            offsets,
            means: d.means,
            scales: d.scales,
            rotations: d.rotations,
            opacities: d.opacities,
        })
    }

    fn raster_input<'a>(
        &'a self,
        f: &'a Forward<T>,
        camera: &'a RasterCamera<T>,
    ) -> RasterInput<'a, T> {
        RasterInput {
            means3d: &f.means,
            colors: Colors::Sh {
                coeffs: &self.gaussians.sh,
                stride: self.gaussians.coeffs(),
                degree: self.active_sh_degree,
            },
            opacities: &f.opacities,
            covariances: Covariances::ScaleRotation {
                scales: &f.scales,
                rotations: &f.rotations,
                scale_modifier: T::ONE,
            },
            camera,
            background: self.background.map(T::from_f64),
        }
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
        let mut report = None;
        if it > s.densify_from && it.is_multiple_of(s.densification_interval) {
            let seed = Rng::stream(self.config.seed ^ STREAM_SPLIT, it).next_u64();
            report = Some(densify_and_prune(
                &mut self.gaussians,
                &mut self.optimizer,
                &mut self.stats,
                self.extent,
                it,
                &self.config.densify,
                seed,
            )?);
        }
        let white = self.background == [1.0; 3];
        let reset = it.is_multiple_of(s.opacity_reset_interval) || (white && it == s.densify_from);
        if reset {
            reset_opacity(&mut self.gaussians, &mut self.optimizer)?;
        }
        let groups = match (report.is_some(), reset) {
            (true, _) => StepGroups::None,
            (false, true) => StepGroups::AllButOpacity,
            (false, false) => StepGroups::All,
        };
        Ok((report, reset, groups))
    }

    /// Render the current model from `camera` at `time` (no AST noise; the
    /// field is used once warm-up is over, as in upstream's render.py).
    pub fn render(&self, camera: &RasterCamera<T>, time: f64) -> Result<RasterOutput<T>> {
        let active = self.field_active(self.iteration.max(1));
        let fwd = self.forward(time, active)?;
        Ok(rasterize(&self.raster_input(&fwd, camera))?.0)
    }

    /// The deformed, activated Gaussians the renderer receives at `time`
    /// (means, scales, rotations, opacities; the SH are `self.gaussians.sh`).
    pub fn deformed(&self, time: f64) -> Result<super::deformed::Deformed<T>> {
        let f = self.forward(time, self.field_active(self.iteration.max(1)))?;
        Ok(super::deformed::Deformed {
            means: f.means,
            scales: f.scales,
            rotations: f.rotations,
            opacities: f.opacities,
        })
    }

    /// The field's offsets at `time` for every Gaussian (zeros during warm-up).
    pub fn offsets(&self, time: f64) -> Result<Offsets<T>> {
        let n = self.gaussians.len();
        if !self.field_active(self.iteration.max(1)) {
            return Ok(Offsets::zeros(n));
        }
        Ok(self
            .field
            .forward(&self.gaussians.xyz, &vec![T::from_f64(time); n])?
            .0)
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
        h.u64(self.active_sh_degree as u64);
        let g = &self.gaussians;
        for v in [&g.xyz, &g.sh, &g.scaling, &g.rotation, &g.opacity] {
            h.reals(v);
        }
        h.reals(self.field.params());
        let o = &self.optimizer;
        for a in [
            &o.xyz,
            &o.sh,
            &o.opacity,
            &o.scaling,
            &o.rotation,
            &self.field_optimizer,
        ] {
            h.reals(&a.m);
            h.reals(&a.v);
            h.u64(a.step);
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

/// 64-bit FNV-1a.
/// 64-bit FNV-1a, the hash of the state and of checkpoint files.
pub(crate) struct Fnv(pub u64);

impl Fnv {
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
    pub fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 = (self.0 ^ x as u64).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    pub fn u64(&mut self, v: u64) {
        self.bytes(&v.to_le_bytes());
    }
    pub fn reals<T: Real>(&mut self, v: &[T]) {
        self.u64(v.len() as u64);
        for x in v {
            self.u64(x.bits());
        }
    }
}
