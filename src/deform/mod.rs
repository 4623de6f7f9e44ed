//! Deformation fields: `F(γ(sg(x)), t) → (Δx, Δr, Δs)` per Gaussian.
//!
//! Two fields share one interface, [`Field`]:
//! - [`FieldKind::Mlp`]: the D-3DGS `DeformNetwork` (docs/UPSTREAM.md §6.2), the baseline.
//! - [`FieldKind::Cfc`]: the liquid field, a stack of CfC cells in depth
//!   (docs/DECISIONS.md §2).
//!
//! Conventions, for both fields:
//! - The position input is stop-gradient (`x.detach()` upstream). The
//!   backward returns every gradient of the field in one
//!   [`FieldGradients`]: the parameters, `t`, and the canonical positions
//!   through the field's own use of them (zero for the additive fields,
//!   the warp's `(R − I)ᵀ·g` for the 6-DoF MLP).
//! - [`Variant::Synthetic`] (D-NeRF, `is_blender`): the time feature is
//!   `timenet(γ₆(t))`, 30 wide, with `timenet = Linear(13,256) → ReLU →
//!   Linear(256,30)`. [`Variant::Real`]: the time feature is `γ₁₀(t)`, 21 wide.
//! - All parameters live in one flat vector, in PyTorch `state_dict` order;
//!   [`Field::layout`] names each tensor's place ([`ParamSpec`]), so the
//!   optimizer can treat them as one group and weight files load by name.
//! - Outputs have no activation: `d_xyz` `[N,3]`, `d_rotation` `[N,4]`,
//!   `d_scaling` `[N,3]`, applied as `xyz + d_xyz`, `normalize(q) + d_rotation`,
//!   `exp(s) + d_scaling` by the caller.
//! - Linear layers compute `(x·Wᵀ, summed over inputs in order) + b` with the
//!   deterministic products of [`crate::kernels::matmul`]: the same bits for any thread count.
//! - In f32, every `exp`, `erf`, `tanh` and `sigmoid` of the fields (forward
//!   and backward) is [`crate::kernels::fastmath`]'s vectorisable plain-arithmetic version
//!   (≤ 2 ulp); f64 uses the pinned libm. Both are the same bits on every CPU
//!   path (AVX-512, AVX2, baseline) and thread count.
//!
//! Speed (f32, N = 20,000, 2 threads, on the project's 2-core machine): see
//! `benches/README.md` for the measured numbers against the PyTorch CPU
//! targets and `liquid-splat bench deform` to reproduce them.
//!
//! The MLP's 6-DoF variant replaces the additive `d_xyz` head by an SE(3)
//! warp ([`se3`]): `d_xyz = R·x + p − x`, with upstream's 1e-5 quirk kept and
//! a finite limit at θ = 0; [`FieldGradients::xyz`] is the gradient the
//! canonical means receive through `R·x` (upstream multiplies the
//! non-detached mean by `R`), on top of the identity path of `xyz + d_xyz`.
//!
//! Deliberate limit: the MLP needs `depth ≥ 3`
//! because upstream concatenates after layer `depth/2` and feeds the result
//! to a later layer (depth 1 and 2 fail in upstream PyTorch too).

pub mod activation;
pub mod cfc;
pub mod count;
pub mod encoding;
pub mod linear;
pub mod mlp;
pub mod profile;
pub mod se3;

pub use activation::Activation;

use crate::error::{Error, Result};
use crate::io::TensorFile;
use crate::kernels::vec_written_by;
use crate::math::{Real, Rng};
use linear::{Epilogue, Input, InputGrad, Linear, LinearGradients, LinearShape, OutputGrad};
use std::fmt;
use std::mem::MaybeUninit;

/// Which deformation network.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FieldKind {
    /// D-3DGS `DeformNetwork` (ReLU MLP with one skip concatenation).
    Mlp,
    /// Stack of CfC cells (the liquid field).
    Cfc,
}

/// Which time input (docs/UPSTREAM.md §6.2 `is_blender`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Variant {
    /// D-NeRF scenes: `timenet(γ₆(t))`, 30 wide.
    Synthetic,
    /// Real scenes (NeRF-DS, HyperNeRF): `γ₁₀(t)`, 21 wide.
    Real,
}

impl FieldKind {
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "mlp" => Ok(FieldKind::Mlp),
            "cfc" => Ok(FieldKind::Cfc),
            o => Err(Error::invalid(
                "field",
                format!("{o:?} (expected mlp or cfc)"),
            )),
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            FieldKind::Mlp => "mlp",
            FieldKind::Cfc => "cfc",
        }
    }
}

impl Variant {
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "synthetic" => Ok(Variant::Synthetic),
            "real" => Ok(Variant::Real),
            o => Err(Error::invalid(
                "variant",
                format!("{o:?} (expected synthetic or real)"),
            )),
        }
    }
    pub fn name(self) -> &'static str {
        match self {
            Variant::Synthetic => "synthetic",
            Variant::Real => "real",
        }
    }
}

impl fmt::Display for FieldKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}
impl fmt::Display for Variant {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Width of γ₁₀(x) for xyz.
pub const XYZ_LEVELS: usize = 10;
/// Frequencies of γ(t): 6 for synthetic scenes (into the timenet), 10 for real ones.
pub const T_LEVELS_SYNTHETIC: usize = 6;
pub const T_LEVELS_REAL: usize = 10;
/// Hidden width of the timenet (fixed at 256 upstream, whatever W is).
pub const TIMENET_HIDDEN: usize = 256;
/// Output width of the timenet.
pub const TIMENET_OUT: usize = 30;

/// The most layers (MLP) or cells (CfC) a field may have.
pub const MAX_DEPTH: usize = 4096;
/// The largest width (MLP trunk, CfC hidden size, CfC backbone units).
pub const MAX_WIDTH: usize = 1 << 16;
/// The most CfC backbone layers per cell.
pub const MAX_BACKBONE_LAYERS: usize = 64;
/// The most learned parameters a field may have (67,108,864: 512 MiB in
/// f64, before gradients and Adam moments). The count comes from the
/// layout, before any parameter is allocated.
pub const MAX_FIELD_PARAMS: usize = 1 << 26;

/// Architecture of a deformation field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FieldConfig {
    pub kind: FieldKind,
    pub variant: Variant,
    /// MLP: number of trunk layers D. CfC: number of cells D.
    pub depth: usize,
    /// MLP: trunk width W. CfC: hidden size W.
    pub width: usize,
    /// MLP: always ReLU (upstream). CfC: the backbone activation.
    pub activation: Activation,
    /// CfC backbone width (ignored by the MLP).
    pub backbone_units: usize,
    /// CfC backbone depth (ignored by the MLP).
    pub backbone_layers: usize,
    /// MLP 6-DoF (SE(3)) variant ([`se3`]); the CfC field has none.
    pub is_6dof: bool,
}

impl FieldConfig {
    /// Defaults per kind: MLP D=8, W=256, ReLU; CfC D=6, W=128, GELU,
    /// backbone 64 units × 2 layers. Synthetic variant.
    pub fn new(kind: FieldKind) -> Self {
        match kind {
            FieldKind::Mlp => FieldConfig {
                kind,
                variant: Variant::Synthetic,
                depth: 8,
                width: 256,
                activation: Activation::Relu,
                backbone_units: 64,
                backbone_layers: 2,
                is_6dof: false,
            },
            FieldKind::Cfc => FieldConfig {
                kind,
                variant: Variant::Synthetic,
                depth: 6,
                width: 128,
                activation: Activation::Gelu,
                backbone_units: 64,
                backbone_layers: 2,
                is_6dof: false,
            },
        }
    }

    /// Check the configuration is buildable.
    pub fn validate(&self) -> Result<()> {
        if self.width == 0 {
            return Err(Error::invalid("width", "must be at least 1"));
        }
        for (name, v, max) in [
            ("depth", self.depth, MAX_DEPTH),
            ("width", self.width, MAX_WIDTH),
            ("backbone_units", self.backbone_units, MAX_WIDTH),
            ("backbone_layers", self.backbone_layers, MAX_BACKBONE_LAYERS),
        ] {
            if v > max {
                return Err(Error::invalid(
                    name,
                    format!("{v} is above the limit {max}"),
                ));
            }
        }
        match self.kind {
            FieldKind::Mlp => {
                if self.depth < 3 {
                    return Err(Error::invalid(
                        "depth",
                        format!(
                            "{} (the MLP field needs depth >= 3: the skip concatenation after layer depth/2 must feed a later layer)",
                            self.depth
                        ),
                    ));
                }
                if self.activation != Activation::Relu {
                    return Err(Error::invalid(
                        "activation",
                        format!("{} (the MLP field uses ReLU, as upstream)", self.activation),
                    ));
                }
            }
            FieldKind::Cfc => {
                if self.depth == 0 {
                    return Err(Error::invalid(
                        "depth",
                        "the CfC field needs at least one cell",
                    ));
                }
                if self.backbone_units == 0 || self.backbone_layers == 0 {
                    return Err(Error::invalid(
                        "backbone",
                        "backbone_units and backbone_layers must be at least 1",
                    ));
                }
                if self.is_6dof {
                    return Err(Error::invalid(
                        "is_6dof",
                        "only the MLP field has a 6-DoF variant",
                    ));
                }
            }
        }
        Ok(())
    }

    /// Width of the time feature: 30 (timenet) or 21 (γ₁₀(t)).
    pub fn time_feature_dim(&self) -> usize {
        match self.variant {
            Variant::Synthetic => TIMENET_OUT,
            Variant::Real => encoding::encoded_dim(1, T_LEVELS_REAL),
        }
    }

    /// Width of `[γ₁₀(x), time feature]`: 93 or 84.
    pub fn input_dim(&self) -> usize {
        encoding::encoded_dim(3, XYZ_LEVELS) + self.time_feature_dim()
    }

    /// Read a configuration from metadata keys `field`, `variant`, `depth`,
    /// `width`, `activation`, `backbone_units`, `backbone_layers`, `is_6dof`
    /// (all but `field` optional, defaulting per kind).
    pub fn from_meta(file: &TensorFile) -> Result<Self> {
        let kind = FieldKind::parse(file.meta("field")?)?;
        let mut c = FieldConfig::new(kind);
        if let Ok(v) = file.meta("variant") {
            c.variant = Variant::parse(v)?;
        }
        c.depth = file.meta_or("depth", c.depth)?;
        c.width = file.meta_or("width", c.width)?;
        if let Ok(a) = file.meta("activation") {
            c.activation = Activation::parse(a)?;
        }
        c.backbone_units = file.meta_or("backbone_units", c.backbone_units)?;
        c.backbone_layers = file.meta_or("backbone_layers", c.backbone_layers)?;
        c.is_6dof = file.meta_or("is_6dof", c.is_6dof)?;
        Ok(c)
    }

    /// Write the keys [`from_meta`](Self::from_meta) reads.
    pub fn to_meta(&self, file: &mut TensorFile) {
        file.set_meta("field", self.kind);
        file.set_meta("variant", self.variant);
        file.set_meta("depth", self.depth);
        file.set_meta("width", self.width);
        file.set_meta("activation", self.activation);
        file.set_meta("backbone_units", self.backbone_units);
        file.set_meta("backbone_layers", self.backbone_layers);
        file.set_meta("is_6dof", self.is_6dof);
    }
}

/// One named tensor's place in the flat parameter vector.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ParamSpec {
    /// PyTorch `state_dict` key.
    pub name: String,
    pub shape: Vec<usize>,
    pub offset: usize,
}

impl ParamSpec {
    pub fn len(&self) -> usize {
        self.shape.iter().product()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn range(&self) -> std::ops::Range<usize> {
        self.offset..self.offset + self.len()
    }
}

/// How a linear layer's weight is initialised (biases are always
/// `U(±1/√fan_in)`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Init {
    /// PyTorch's default: kaiming-uniform with a = √5, i.e. `U(±1/√fan_in)`.
    TorchDefault,
    /// Xavier-uniform, gain 1: `U(±√(6/(fan_in + fan_out)))` (ncps CfC cells).
    Xavier,
}

/// A linear layer's place in the flat parameter vector.
#[derive(Clone, Copy, Debug)]
pub(crate) struct LinearParams {
    pub shape: LinearShape,
    pub w: usize,
    pub b: usize,
    pub init: Init,
}

impl LinearParams {
    fn weight<'a, T>(&self, p: &'a [T]) -> &'a [T] {
        &p[self.w..self.w + self.shape.in_dim * self.shape.out_dim]
    }
    fn bias<'a, T>(&self, p: &'a [T]) -> &'a [T] {
        &p[self.b..self.b + self.shape.out_dim]
    }

    /// The layer over its parameters in `p`.
    pub fn linear<'a, T: Real>(&self, p: &'a [T]) -> Linear<'a, T> {
        Linear::new(self.weight(p), self.bias(p), self.shape)
    }

    /// Write a weight and a bias gradient into `grad` (same layout as the
    /// parameters).
    fn store_grads<T: Real>(&self, grad: &mut [T], weight: &[T], bias: &[T]) {
        grad[self.w..self.w + weight.len()].copy_from_slice(weight);
        grad[self.b..self.b + bias.len()].copy_from_slice(bias);
    }

    /// Write the layer's weight and bias gradients into `grad`.
    pub fn store<T: Real>(&self, g: &LinearGradients<T>, grad: &mut [T]) {
        self.store_grads(grad, &g.weight, &g.bias);
    }
}

/// Several linear layers with the same input run as one (their weights
/// stacked by rows): the outputs are the same bits as running them one by one.
pub(crate) struct Stacked<'a>(pub &'a [LinearParams]);

impl Stacked<'_> {
    /// The stacked layer over the parameters in `p`: `[n, Σ out]`, the
    /// layers' outputs side by side.
    pub fn linear<T: Real>(&self, p: &[T]) -> Linear<'static, T> {
        let layers: Vec<Linear<'_, T>> = self.0.iter().map(|l| l.linear(p)).collect();
        Linear::stacked(&layers)
    }

    /// Write the stacked layer's gradients into `grad`, layer by layer.
    pub fn store<T: Real>(&self, g: &LinearGradients<T>, grad: &mut [T]) {
        let mut row = 0;
        for l in self.0 {
            let (o, in_dim) = (l.shape.out_dim, l.shape.in_dim);
            l.store_grads(
                grad,
                &g.weight[row * in_dim..(row + o) * in_dim],
                &g.bias[row..row + o],
            );
            row += o;
        }
    }
}

/// Builds the flat layout in `state_dict` order.
#[derive(Default)]
pub(crate) struct LayoutBuilder {
    pub specs: Vec<ParamSpec>,
    pub linears: Vec<LinearParams>,
    len: usize,
}

impl LayoutBuilder {
    fn push(&mut self, name: String, shape: Vec<usize>) -> usize {
        let off = self.len;
        self.len += shape.iter().product::<usize>();
        self.specs.push(ParamSpec {
            name,
            shape,
            offset: off,
        });
        off
    }
    /// Register `{prefix}.weight` `[out, in]` and `{prefix}.bias` `[out]`.
    pub fn linear(
        &mut self,
        prefix: &str,
        in_dim: usize,
        out_dim: usize,
        init: Init,
    ) -> LinearParams {
        let w = self.push(format!("{prefix}.weight"), vec![out_dim, in_dim]);
        let b = self.push(format!("{prefix}.bias"), vec![out_dim]);
        let l = LinearParams {
            shape: LinearShape { in_dim, out_dim },
            w,
            b,
            init,
        };
        self.linears.push(l);
        l
    }
}

/// The time input of a field: `timenet(γ₆(t))` or `γ₁₀(t)`.
#[derive(Clone, Debug)]
pub(crate) enum TimeEmbedding {
    Timenet { l0: LinearParams, l1: LinearParams },
    Encoded,
}

/// What the time embedding's backward needs.
pub(crate) enum TimeCache<T> {
    Timenet {
        /// γ₆(t) `[n, 13]`.
        enc: Vec<T>,
        /// ReLU output of the hidden layer `[n, 256]` (its backward needs
        /// only the output, so no pre-activation is kept).
        hidden: Vec<T>,
    },
    Encoded,
}

impl TimeEmbedding {
    pub fn build(variant: Variant, lb: &mut LayoutBuilder) -> Self {
        match variant {
            Variant::Synthetic => {
                let e = encoding::encoded_dim(1, T_LEVELS_SYNTHETIC);
                let l0 = lb.linear("timenet.0", e, TIMENET_HIDDEN, Init::TorchDefault);
                let l1 = lb.linear("timenet.2", TIMENET_HIDDEN, TIMENET_OUT, Init::TorchDefault);
                TimeEmbedding::Timenet { l0, l1 }
            }
            Variant::Real => TimeEmbedding::Encoded,
        }
    }

    /// The time feature `[n, 30 | 21]`.
    pub fn forward<T: Real>(&self, p: &[T], t: &[T]) -> (Vec<T>, TimeCache<T>) {
        let n = t.len();
        match self {
            TimeEmbedding::Timenet { l0, l1 } => {
                let enc = encoding::encode(t, 1, T_LEVELS_SYNTHETIC);
                // timenet.2 runs on each block of hidden rows as it leaves
                // timenet.0 (bias, ReLU), while the block is in cache.
                let next = l1.linear(p).packed();
                let nw = next.out_dim();
                let chain = |_: usize, blk: &mut [T], out: &mut [MaybeUninit<T>]| {
                    next.forward_block_into(blk, out.len() / nw.max(1), out)
                };
                let mut hidden = Vec::new();
                let feat = vec_written_by(n * nw, |feat| {
                    hidden = profile::layer(
                        || "timenet.0 + ReLU, timenet.2 in its epilogue".into(),
                        || {
                            l0.linear(p).forward(
                                Input::blocks(&[(&enc, l0.shape.in_dim)]),
                                n,
                                Epilogue::act(Activation::Relu).then(feat, nw, &chain),
                            )
                        },
                    );
                    // SAFETY: the epilogue wrote every row of `feat` (each
                    // block of rows is visited once, and forward_block_into
                    // writes all of its output).
                    unsafe { &mut *(feat as *mut [MaybeUninit<T>] as *mut [T]) }
                });
                (feat, TimeCache::Timenet { enc, hidden })
            }
            TimeEmbedding::Encoded => (encoding::encode(t, 1, T_LEVELS_REAL), TimeCache::Encoded),
        }
    }

    /// Gradient with respect to `t` `[n]` given the feature gradient.
    pub fn backward<T: Real>(
        &self,
        p: &[T],
        t: &[T],
        cache: &TimeCache<T>,
        g_feat: &[T],
        grad: &mut [T],
    ) -> Vec<T> {
        let n = t.len();
        match (self, cache) {
            (TimeEmbedding::Timenet { l0, l1 }, TimeCache::Timenet { enc, hidden }) => {
                let mut gh = profile::layer(
                    || "timenet.2".into(),
                    || {
                        let mut r = l1.linear(p).backward(
                            &[(hidden, TIMENET_HIDDEN)],
                            OutputGrad::Given(g_feat),
                            n,
                            InputGrad::From(0),
                        );
                        l1.store(&r, grad);
                        r.take_input(0)
                    },
                )
                .expect("input gradient requested");
                profile::elementwise(
                    || "timenet.0 / ReLU vjp".into(),
                    n,
                    TIMENET_HIDDEN,
                    || activation::relu_backward_from_output(hidden, &mut gh),
                );
                let genc = profile::layer(
                    || "timenet.0".into(),
                    || {
                        let mut r = l0.linear(p).backward(
                            &[(enc, l0.shape.in_dim)],
                            OutputGrad::Given(&gh),
                            n,
                            InputGrad::From(0),
                        );
                        l0.store(&r, grad);
                        r.take_input(0)
                    },
                )
                .expect("input gradient requested");
                encoding::encode_vjp(t, &genc, 1, T_LEVELS_SYNTHETIC)
            }
            _ => encoding::encode_vjp(t, g_feat, 1, T_LEVELS_REAL),
        }
    }
}

/// The output of a field: per-Gaussian offsets.
#[derive(Clone, Debug, PartialEq)]
pub struct Deformation<T> {
    /// `[N, 3]`, added to the canonical means.
    pub d_xyz: Vec<T>,
    /// `[N, 4]` (w, x, y, z), added to the normalised quaternion.
    pub d_rotation: Vec<T>,
    /// `[N, 3]`, added to the activated (linear) scales.
    pub d_scaling: Vec<T>,
}

impl<T: Real> Deformation<T> {
    /// All zeros for `n` Gaussians.
    pub fn zeros(n: usize) -> Self {
        Deformation {
            d_xyz: vec![T::ZERO; 3 * n],
            d_rotation: vec![T::ZERO; 4 * n],
            d_scaling: vec![T::ZERO; 3 * n],
        }
    }
    /// Number of Gaussians.
    pub fn len(&self) -> usize {
        self.d_xyz.len() / 3
    }
    pub fn is_empty(&self) -> bool {
        self.d_xyz.is_empty()
    }
    /// Split a `[n, 10]` head output (3 | 4 | 3).
    pub(crate) fn from_head(out: &[T]) -> Self {
        let n = out.len() / 10;
        let mut d = Self::zeros(n);
        for i in 0..n {
            let r = &out[i * 10..i * 10 + 10];
            d.d_xyz[i * 3..i * 3 + 3].copy_from_slice(&r[0..3]);
            d.d_rotation[i * 4..i * 4 + 4].copy_from_slice(&r[3..7]);
            d.d_scaling[i * 3..i * 3 + 3].copy_from_slice(&r[7..10]);
        }
        d
    }
    /// Join into `[n, 10]` (inverse of `from_head`).
    pub(crate) fn to_head(&self) -> Vec<T> {
        let n = self.len();
        let mut out = vec![T::ZERO; n * 10];
        for i in 0..n {
            let r = &mut out[i * 10..i * 10 + 10];
            r[0..3].copy_from_slice(&self.d_xyz[i * 3..i * 3 + 3]);
            r[3..7].copy_from_slice(&self.d_rotation[i * 4..i * 4 + 4]);
            r[7..10].copy_from_slice(&self.d_scaling[i * 3..i * 3 + 3]);
        }
        out
    }
}

/// Every gradient of one field backward ([`Field::backward`]), given the
/// gradient `g` of the outputs ([`Deformation`]).
#[derive(Clone, Debug, PartialEq)]
pub struct FieldGradients<T> {
    /// The parameters, flat in [`Field::layout`] order.
    pub params: Vec<T>,
    /// The per-Gaussian times `t` `[N]`.
    pub t: Vec<T>,
    /// The canonical positions `xyz` `[N, 3]` through the field itself,
    /// beyond the identity path of `means = xyz + d_xyz` (which the caller
    /// adds: [`crate::train::deformed::deform_gaussians_vjp`]). The network
    /// reads `xyz` stop-gradient, so this is all zeros for the additive
    /// fields. The 6-DoF MLP moves the non-detached mean to `R·x + p`
    /// (upstream's renderer), so `d_xyz = R·x + p − x` depends on `x`
    /// explicitly: `(R − I)ᵀ·g.d_xyz` per Gaussian, and the total gradient of
    /// the canonical mean is `Rᵀ·g.d_xyz`.
    pub xyz: Vec<T>,
}

/// The network of a field.
#[derive(Clone, Debug)]
enum Net {
    Mlp(mlp::MlpNet),
    Cfc(cfc::CfcNet),
}

/// What [`Field::backward`] needs from [`Field::forward`].
pub struct FieldCache<T> {
    n: usize,
    t: Vec<T>,
    inner: CacheInner<T>,
}

enum CacheInner<T> {
    Mlp(mlp::MlpCache<T>),
    Cfc(cfc::CfcCache<T>),
}

impl<T> FieldCache<T> {
    /// Number of Gaussians of the forward pass.
    pub fn len(&self) -> usize {
        self.n
    }
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }
}

/// A deformation field: architecture plus one flat parameter vector.
#[derive(Clone, Debug)]
pub struct Field<T> {
    config: FieldConfig,
    params: Vec<T>,
    layout: Vec<ParamSpec>,
    net: Net,
}

impl<T: Real> Field<T> {
    fn build(config: FieldConfig) -> Result<(Net, LayoutBuilder)> {
        config.validate()?;
        let mut lb = LayoutBuilder::default();
        let net = match config.kind {
            FieldKind::Mlp => Net::Mlp(mlp::MlpNet::build(&config, &mut lb)),
            FieldKind::Cfc => Net::Cfc(cfc::CfcNet::build(&config, &mut lb)),
        };
        if lb.len > MAX_FIELD_PARAMS {
            return Err(Error::invalid(
                "field size",
                format!(
                    "{} D{} W{} has {} parameters, more than the limit {MAX_FIELD_PARAMS}",
                    config.kind, config.depth, config.width, lb.len
                ),
            ));
        }
        Ok((net, lb))
    }

    /// A field with seeded initial weights (docs/DECISIONS.md §2): one generator
    /// `Rng::new(seed)` draws, in layout order, each weight then its bias;
    /// CfC cell weights are xavier-uniform, every other weight and every bias
    /// is `U(±1/√fan_in)` (PyTorch's default Linear init).
    pub fn new(config: FieldConfig, seed: u64) -> Result<Self> {
        let (net, lb) = Self::build(config)?;
        let total = lb.specs.iter().map(|s| s.len()).sum();
        let mut params = vec![T::ZERO; total];
        let mut rng = Rng::new(seed);
        for l in &lb.linears {
            let LinearShape { in_dim, out_dim } = l.shape;
            let wb = match l.init {
                Init::TorchDefault => 1.0 / (in_dim as f64).sqrt(),
                Init::Xavier => (6.0 / (in_dim + out_dim) as f64).sqrt(),
            };
            for v in &mut params[l.w..l.w + in_dim * out_dim] {
                *v = T::from_f64(rng.uniform_range(-wb, wb));
            }
            let bb = 1.0 / (in_dim as f64).sqrt();
            for v in &mut params[l.b..l.b + out_dim] {
                *v = T::from_f64(rng.uniform_range(-bb, bb));
            }
        }
        Ok(Field {
            config,
            params,
            layout: lb.specs,
            net,
        })
    }

    pub fn config(&self) -> &FieldConfig {
        &self.config
    }
    /// All parameters, flat, in [`layout`](Self::layout) order.
    pub fn params(&self) -> &[T] {
        &self.params
    }
    pub fn params_mut(&mut self) -> &mut [T] {
        &mut self.params
    }
    /// Each tensor's name, shape and offset, in `state_dict` order.
    pub fn layout(&self) -> &[ParamSpec] {
        &self.layout
    }
    pub fn param_count(&self) -> usize {
        self.params.len()
    }

    /// Evaluate the field for `xyz` `[N, 3]` and per-Gaussian times `t` `[N]`.
    pub fn forward(&self, xyz: &[T], t: &[T]) -> Result<(Deformation<T>, FieldCache<T>)> {
        let n = t.len();
        if xyz.len() != 3 * n {
            return Err(Error::invalid(
                "field input",
                format!(
                    "xyz has {} values, expected 3 × {n} (one time per Gaussian)",
                    xyz.len()
                ),
            ));
        }
        let (d, inner) = match &self.net {
            Net::Mlp(m) => {
                let (d, c) = m.forward(&self.params, xyz, t);
                (d, CacheInner::Mlp(c))
            }
            Net::Cfc(m) => {
                let (d, c) = m.forward(&self.params, xyz, t);
                (d, CacheInner::Cfc(c))
            }
        };
        Ok((
            d,
            FieldCache {
                n,
                t: t.to_vec(),
                inner,
            },
        ))
    }

    /// Backward: every gradient of the field given the gradient `grad` of
    /// its outputs ([`FieldGradients`]).
    pub fn backward(
        &self,
        cache: &FieldCache<T>,
        grad: &Deformation<T>,
    ) -> Result<FieldGradients<T>> {
        let n = cache.n;
        if grad.d_xyz.len() != 3 * n
            || grad.d_rotation.len() != 4 * n
            || grad.d_scaling.len() != 3 * n
        {
            return Err(Error::invalid(
                "field output gradient",
                format!("expected [{n},3], [{n},4], [{n},3] values"),
            ));
        }
        let mut params = vec![T::ZERO; self.params.len()];
        let (t, xyz) = match (&self.net, &cache.inner) {
            (Net::Mlp(m), CacheInner::Mlp(c)) => {
                m.backward(&self.params, &cache.t, c, grad, &mut params)
            }
            (Net::Cfc(m), CacheInner::Cfc(c)) => (
                m.backward(&self.params, &cache.t, c, grad, &mut params),
                None,
            ),
            _ => {
                return Err(Error::invalid(
                    "field cache",
                    "the cache comes from a different kind of field",
                ))
            }
        };
        Ok(FieldGradients {
            params,
            t,
            xyz: xyz.unwrap_or_else(|| vec![T::ZERO; 3 * n]),
        })
    }

    /// 6-DoF MLP: upstream's per-Gaussian SE(3) transforms `[N, 4, 4]`
    /// (row-major, `[[R, p], [0, 0, 0, 1]]`) of the last forward; `None` for
    /// the other fields.
    pub fn se3_transforms(&self, cache: &FieldCache<T>) -> Option<Vec<T>> {
        match (&self.net, &cache.inner) {
            (Net::Mlp(m), CacheInner::Mlp(c)) => m.se3_transforms(c),
            _ => None,
        }
    }

    /// The weights as a tensor file under their `state_dict` names, with the
    /// configuration in the metadata.
    pub fn to_tensor_file(&self) -> TensorFile {
        let mut f = TensorFile::new("field");
        self.config.to_meta(&mut f);
        for s in &self.layout {
            f.insert_real(&s.name, s.shape.clone(), &self.params[s.range()]);
        }
        f
    }

    /// Load weights by `state_dict` name. Missing, misshaped (or wrong
    /// dtype) and unexpected tensors are errors naming them. Metadata is ignored:
    /// the architecture is `config`.
    pub fn from_tensor_file(config: FieldConfig, file: &TensorFile) -> Result<Self> {
        let (net, lb) = Self::build(config)?;
        // Every tensor present with its shape before the vector is allocated:
        // a small file cannot claim a huge architecture.
        for s in &lb.specs {
            file.expect_shape(&s.name, &s.shape)?;
        }
        let total = lb.specs.iter().map(|s| s.len()).sum();
        let mut params = vec![T::ZERO; total];
        for s in &lb.specs {
            let v = file.get_real::<T>(&s.name, &s.shape)?;
            params[s.range()].copy_from_slice(&v);
        }
        file.reject_unknown(lb.specs.iter().map(|s| s.name.as_str()))?;
        Ok(Field {
            config,
            params,
            layout: lb.specs,
            net,
        })
    }
}
