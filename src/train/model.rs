//! The model D-3DGS trains: canonical Gaussians, a deformation field, the SH
//! degree in use and the background, with its forward (render at a camera
//! and time), backward (gradients of every parameter) and the optimizer
//! update that [`Trainer::step`](super::Trainer::step) and the oracle's
//! `step` stage share.
//!
//! The data flow of one view (docs/UPSTREAM.md §6.4):
//! camera + time → field → deformed Gaussians ([`super::deformed`]) →
//! rasterizer → loss, and back through each stage in reverse.

use super::deformed::{deform_gaussians, deform_gaussians_vjp, Deformed, Offsets};
use super::trainer::{Lap, StageTimes, View};
use crate::camera::RasterCamera;
use crate::deform::{Field, FieldSaved};
use crate::error::{Error, Result};
use crate::gaussians::Gaussians;
use crate::loss::{loss_and_grad, LossOutput};
use crate::math::Real;
use crate::optim::{AdamState, GaussianOptimizer, StepGroups, StepRates};
use crate::render::{
    rasterize, rasterize_vjp, Colors, Covariances, GradientMode, RasterGrads, RasterInput,
    RasterOutput, RasterizeSaved,
};
use std::time::Instant;

/// Canonical Gaussians, field, active SH degree and background: everything
/// a render depends on besides the camera and the time.
#[derive(Clone, Debug)]
pub struct Model<T> {
    /// Canonical Gaussians (raw parameters).
    pub gaussians: Gaussians<T>,
    /// The deformation field.
    pub field: Field<T>,
    /// SH degree used for colour, at most `gaussians.max_sh_degree`.
    pub active_sh_degree: usize,
    /// Background RGB composited behind the Gaussians.
    pub background: [f64; 3],
}

/// What [`Model::forward`] keeps for [`Model::backward`].
pub struct ModelSaved<T> {
    /// The field's forward state, `None` with the field off.
    field: Option<FieldSaved<T>>,
    deformed: Deformed<T>,
    camera: RasterCamera<T>,
    raster: RasterizeSaved<T>,
}

/// Gradients of a [`Model`]'s parameters for one view ([`Model::backward`]).
#[derive(Clone, Debug)]
pub struct ModelGradients<T> {
    /// Gradients of the canonical raw parameters (a [`Gaussians`] used as a
    /// gradient container, same layout). The means' is upstream's: the
    /// field reads them stop-gradient, so it is the rasterizer's means
    /// gradient `g` for the additive fields and `Rᵀ·g` for the 6-DoF MLP
    /// (whose warp moves the non-detached mean to `R·x + p`); with the field
    /// on it is not the total derivative of the loss.
    pub gaussians: Gaussians<T>,
    /// Gradient of the field weights; `None` with the field off.
    pub field: Option<Vec<T>>,
    /// `[N, 3]` gradient of the projected means in NDC (not a parameter:
    /// upstream's `viewspace_point_tensor.grad`, the densification statistic).
    pub means2d: Vec<T>,
}

/// Loss, render and gradients of one view ([`Model::gradients`]).
#[derive(Clone, Debug)]
pub struct Gradients<T> {
    /// The loss and its parts.
    pub loss: LossOutput<T>,
    /// The render `[3, H, W]`.
    pub image: Vec<T>,
    /// Screen radii `[N]` (0: culled).
    pub radii: Vec<i32>,
    /// The gradients of the model's parameters.
    pub model: ModelGradients<T>,
}

impl<T: Real> Model<T> {
    /// Check that the parts fit together: valid Gaussians and an active SH
    /// degree they hold.
    pub fn validate(&self) -> Result<()> {
        self.gaussians.validate()?;
        if self.active_sh_degree > self.gaussians.max_sh_degree {
            return Err(Error::invalid(
                "active SH degree",
                format!(
                    "{}, above the degree {} the Gaussians hold",
                    self.active_sh_degree, self.gaussians.max_sh_degree
                ),
            ));
        }
        Ok(())
    }

    /// The field's offsets at `time` for every Gaussian and their forward
    /// state; `None` with the field off.
    fn field_forward(
        &self,
        time: f64,
        field_on: bool,
    ) -> Result<Option<(Offsets<T>, FieldSaved<T>)>> {
        if !field_on {
            return Ok(None);
        }
        let g = &self.gaussians;
        let t = vec![T::from_f64(time); g.len()];
        Ok(Some(self.field.forward(&g.xyz, &t)?))
    }

    /// The deformed, activated Gaussians and the field's forward state.
    fn deform_forward(
        &self,
        time: f64,
        field_on: bool,
    ) -> Result<(Deformed<T>, Option<FieldSaved<T>>)> {
        let (offsets, cache) = match self.field_forward(time, field_on)? {
            Some((o, cache)) => (Some(o), Some(cache)),
            None => (None, None),
        };
        Ok((deform_gaussians(&self.gaussians, offsets.as_ref()), cache))
    }

    /// The field's offsets at `time` for every Gaussian (zeros with the
    /// field off).
    pub fn offsets(&self, time: f64, field_on: bool) -> Result<Offsets<T>> {
        Ok(match self.field_forward(time, field_on)? {
            Some((o, _)) => o,
            None => Offsets::zeros(self.gaussians.len()),
        })
    }

    /// The deformed, activated Gaussians the renderer receives at `time`
    /// (means, scales, rotations, opacities; the SH are `gaussians.sh`).
    pub fn deformed(&self, time: f64, field_on: bool) -> Result<Deformed<T>> {
        Ok(self.deform_forward(time, field_on)?.0)
    }

    /// The rasterizer's input for `deformed` Gaussians seen from `camera`.
    fn raster_input<'a>(
        &'a self,
        deformed: &'a Deformed<T>,
        camera: &'a RasterCamera<T>,
    ) -> RasterInput<'a, T> {
        RasterInput {
            means3d: &deformed.means,
            colors: Colors::Sh {
                coeffs: &self.gaussians.sh,
                stride: self.gaussians.coeffs(),
                degree: self.active_sh_degree,
            },
            opacities: &deformed.opacities,
            covariances: Covariances::ScaleRotation {
                scales: &deformed.scales,
                rotations: &deformed.rotations,
                scale_modifier: T::ONE,
            },
            camera,
            background: self.background.map(T::from_f64),
        }
    }

    /// The rasterizer's forward of deformed Gaussians, saving every stage's
    /// state.
    fn raster_forward(
        &self,
        deformed: Deformed<T>,
        field: Option<FieldSaved<T>>,
        camera: &RasterCamera<T>,
    ) -> Result<(RasterOutput<T>, ModelSaved<T>)> {
        let (out, raster) = rasterize(&self.raster_input(&deformed, camera))?;
        let saved = ModelSaved {
            field,
            deformed,
            camera: camera.clone(),
            raster,
        };
        Ok((out, saved))
    }

    /// Render from `camera` at `time` (field, deformation, rasterizer),
    /// keeping what [`backward`](Self::backward) needs.
    pub fn forward(
        &self,
        camera: &RasterCamera<T>,
        time: f64,
        field_on: bool,
    ) -> Result<(RasterOutput<T>, ModelSaved<T>)> {
        let (deformed, field) = self.deform_forward(time, field_on)?;
        self.raster_forward(deformed, field, camera)
    }

    /// The rasterizer's backward (exact gradient mode).
    fn raster_backward(&self, saved: &ModelSaved<T>, grad_image: &[T]) -> Result<RasterGrads<T>> {
        let input = self.raster_input(&saved.deformed, &saved.camera);
        rasterize_vjp(&input, &saved.raster, grad_image, None, GradientMode::Exact)
    }

    /// The backward of the activations and the field: the field's backward
    /// runs inside the activations' ([`deform_gaussians_vjp`]), which adds
    /// its gradient of the canonical means to the identity path.
    fn deform_backward(
        &self,
        saved: &ModelSaved<T>,
        rg: RasterGrads<T>,
    ) -> Result<ModelGradients<T>> {
        let field = saved.field.as_ref().map(|cache| (&self.field, cache));
        let (gaussians, field) = deform_gaussians_vjp(&self.gaussians, field, &rg)?;
        Ok(ModelGradients {
            gaussians,
            field: field.map(|f| f.params),
            means2d: rg.means2d,
        })
    }

    /// The gradients of every parameter from the render's cotangent
    /// `grad_image` (`[3, H, W]`), stage by stage in reverse.
    pub fn backward(&self, saved: &ModelSaved<T>, grad_image: &[T]) -> Result<ModelGradients<T>> {
        let rg = self.raster_backward(saved, grad_image)?;
        self.deform_backward(saved, rg)
    }

    /// Render from `camera` at `time` (no AST noise).
    pub fn render(
        &self,
        camera: &RasterCamera<T>,
        time: f64,
        field_on: bool,
    ) -> Result<RasterOutput<T>> {
        self.render_deformed(&self.deformed(time, field_on)?, camera)
    }

    /// The render of Gaussians already deformed ([`deformed`](Self::deformed)).
    pub fn render_deformed(
        &self,
        deformed: &Deformed<T>,
        camera: &RasterCamera<T>,
    ) -> Result<RasterOutput<T>> {
        Ok(rasterize(&self.raster_input(deformed, camera))?.0)
    }

    /// Loss `(1 − λ)·L1 + λ·(1 − SSIM)` of the render of `view` at `time`
    /// (`λ = lambda_dssim`) and the gradient of every parameter, changing
    /// nothing, with the time each stage took: [`forward`](Self::forward),
    /// the loss and [`backward`](Self::backward).
    pub fn gradients(
        &self,
        view: &View<T>,
        time: f64,
        field_on: bool,
        lambda_dssim: f64,
    ) -> Result<(Gradients<T>, StageTimes)> {
        let mut times = StageTimes::default();
        let mut clock = Lap(Instant::now());
        let (deformed, field) = self.deform_forward(time, field_on)?;
        times.field_forward = clock.lap();
        let (out, saved) = self.raster_forward(deformed, field, &view.camera)?;
        times.raster_forward = clock.lap();
        let (h, w) = (view.height, view.width);
        let (loss, grad_image) = loss_and_grad(&out.color, &view.image, h, w, lambda_dssim)?;
        times.loss = clock.lap();
        let rg = self.raster_backward(&saved, &grad_image)?;
        times.raster_backward = clock.lap();
        let model = self.deform_backward(&saved, rg)?;
        times.field_backward = clock.lap();
        let g = Gradients {
            loss,
            image: out.color,
            radii: out.radii,
            model,
        };
        Ok((g, times))
    }
}

/// The Adam states of a [`Model`]'s parameters: one per Gaussian group and
/// one for the field weights.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelOptimizer<T> {
    /// The Gaussian groups' states.
    pub gaussians: GaussianOptimizer<T>,
    /// The field weights' state (`[P]`, the weights in `state_dict` order).
    pub field: AdamState<T>,
}

impl<T: Real> ModelOptimizer<T> {
    /// Zero state sized for `model`, default hyper-parameters.
    pub fn new(model: &Model<T>) -> Self {
        ModelOptimizer {
            gaussians: GaussianOptimizer::new(&model.gaussians),
            field: AdamState::new(model.field.param_count()),
        }
    }

    /// One Adam step of `model` with `grads`: the Gaussian groups that
    /// `groups` selects, and the field weights when they have a gradient
    /// (`torch.optim.Adam` skips a parameter whose `.grad` is `None`). The
    /// update of [`Trainer::step`](super::Trainer::step) and of the
    /// oracle's `step` stage.
    pub fn step(
        &mut self,
        model: &mut Model<T>,
        grads: &ModelGradients<T>,
        rates: &StepRates,
        groups: StepGroups,
    ) -> Result<()> {
        if groups != StepGroups::None {
            self.gaussians.step(
                &mut model.gaussians,
                &grads.gaussians,
                &rates.gaussians,
                groups,
            )?;
        }
        if let Some(fg) = &grads.field {
            self.field.step(model.field.params_mut(), fg, rates.field)?;
        }
        Ok(())
    }
}
