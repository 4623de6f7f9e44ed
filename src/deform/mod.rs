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
//!   (`exp` ≤ 1 ulp, `sigmoid` ≤ 2, `tanh` and `erf` ≤ 6); f64 uses the pinned libm. Both are the same bits on every CPU
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
pub mod config;
pub mod count;
pub mod encoding;
pub mod field;
pub mod layers;
pub mod linear;
pub mod mlp;
pub mod profile;
pub mod se3;
pub mod time;

pub use activation::Activation;
pub use config::{
    CfcConfig, FieldConfig, FieldKind, MlpConfig, Variant, MAX_BACKBONE_LAYERS, MAX_DEPTH,
    MAX_FIELD_PARAMS, MAX_WIDTH, TIMENET_HIDDEN, TIMENET_OUT, T_LEVELS_REAL, T_LEVELS_SYNTHETIC,
    XYZ_LEVELS,
};
pub use field::{Deformation, Field, FieldGradients, FieldSaved};
pub use layers::ParamSpec;
pub(crate) use layers::{Init, LayoutBuilder, LinearParams, Stacked};
pub(crate) use time::{TimeEmbedding, TimeEmbeddingSaved};
