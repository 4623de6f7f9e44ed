//! The configuration of a deformation field: which network, which time
//! input, and the network's size; the limits a configuration must respect.

use super::activation::Activation;
use super::encoding;
use crate::error::{Error, Result};
use std::fmt;

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
    /// The kind named `mlp` or `cfc` (as the CLI and case files spell it).
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
    /// The name [`parse`](Self::parse) reads.
    pub fn name(self) -> &'static str {
        match self {
            FieldKind::Mlp => "mlp",
            FieldKind::Cfc => "cfc",
        }
    }
}

impl Variant {
    /// The variant named `synthetic` or `real`.
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
    /// The name [`parse`](Self::parse) reads.
    pub fn name(self) -> &'static str {
        match self {
            Variant::Synthetic => "synthetic",
            Variant::Real => "real",
        }
    }
}

impl Variant {
    /// Width of the time feature: 30 (timenet) or 21 (γ₁₀(t)).
    pub fn time_feature_dim(self) -> usize {
        match self {
            Variant::Synthetic => TIMENET_OUT,
            Variant::Real => encoding::encoded_dim(1, T_LEVELS_REAL),
        }
    }

    /// Width of a field's input `[γ₁₀(x), time feature]`: 93 or 84.
    pub fn input_dim(self) -> usize {
        encoding::encoded_dim(3, XYZ_LEVELS) + self.time_feature_dim()
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
/// Frequencies of γ(t) for synthetic scenes (into the timenet).
pub const T_LEVELS_SYNTHETIC: usize = 6;
/// Frequencies of γ(t) for real scenes (the time feature itself).
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

/// Options of the MLP field (D-3DGS `DeformNetwork`): a ReLU trunk of
/// `depth` layers, `width` wide, with one skip concatenation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MlpConfig {
    /// Which time input.
    pub variant: Variant,
    /// Number of trunk layers D (at least 3).
    pub depth: usize,
    /// Trunk width W.
    pub width: usize,
    /// The 6-DoF (SE(3)) variant ([`se3`](super::se3)).
    pub is_6dof: bool,
}

/// Options of the CfC (liquid) field: `depth` CfC cells of hidden size
/// `width`, each with a backbone of `backbone_layers` layers of
/// `backbone_units` units and activation `activation`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct CfcConfig {
    /// Which time input.
    pub variant: Variant,
    /// Number of cells D (at least 1).
    pub depth: usize,
    /// Hidden size W.
    pub width: usize,
    /// The backbone activation.
    pub activation: Activation,
    /// Backbone width (units per layer).
    pub backbone_units: usize,
    /// Backbone depth (layers per cell).
    pub backbone_layers: usize,
}

impl MlpConfig {
    /// The paper's MLP: D=8, W=256, 3-DoF, synthetic variant.
    pub fn paper() -> Self {
        MlpConfig {
            variant: Variant::Synthetic,
            depth: 8,
            width: 256,
            is_6dof: false,
        }
    }
}

impl CfcConfig {
    /// The paper's CfC field: D=6 cells, W=128, GELU backbone of 2 layers
    /// × 64 units, synthetic variant.
    pub fn paper() -> Self {
        CfcConfig {
            variant: Variant::Synthetic,
            depth: 6,
            width: 128,
            activation: Activation::Gelu,
            backbone_units: 64,
            backbone_layers: 2,
        }
    }
}

impl Default for MlpConfig {
    fn default() -> Self {
        Self::paper()
    }
}
impl Default for CfcConfig {
    fn default() -> Self {
        Self::paper()
    }
}

/// Architecture of a deformation field: one variant per network, each
/// holding only the options that network uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FieldConfig {
    /// The MLP field.
    Mlp(MlpConfig),
    /// The CfC field.
    Cfc(CfcConfig),
}

impl From<MlpConfig> for FieldConfig {
    fn from(c: MlpConfig) -> Self {
        FieldConfig::Mlp(c)
    }
}
impl From<CfcConfig> for FieldConfig {
    fn from(c: CfcConfig) -> Self {
        FieldConfig::Cfc(c)
    }
}

impl FieldConfig {
    /// The paper's defaults for `kind` ([`MlpConfig::paper`],
    /// [`CfcConfig::paper`]).
    pub fn new(kind: FieldKind) -> Self {
        match kind {
            FieldKind::Mlp => FieldConfig::Mlp(MlpConfig::paper()),
            FieldKind::Cfc => FieldConfig::Cfc(CfcConfig::paper()),
        }
    }

    /// The paper's defaults for `kind` with the shared options set: time
    /// input, depth, width and hidden activation (the CfC backbone's; the
    /// MLP accepts only ReLU, an error naming `activation` otherwise).
    pub fn sized(
        kind: FieldKind,
        variant: Variant,
        depth: usize,
        width: usize,
        activation: Activation,
    ) -> Result<Self> {
        Ok(match kind {
            FieldKind::Mlp => {
                if activation != Activation::Relu {
                    return Err(Error::invalid(
                        "activation",
                        format!("{activation} (the MLP field uses ReLU, as upstream)"),
                    ));
                }
                FieldConfig::Mlp(MlpConfig {
                    variant,
                    depth,
                    width,
                    ..MlpConfig::paper()
                })
            }
            FieldKind::Cfc => FieldConfig::Cfc(CfcConfig {
                variant,
                depth,
                width,
                activation,
                ..CfcConfig::paper()
            }),
        })
    }

    /// Which network.
    pub fn kind(&self) -> FieldKind {
        match self {
            FieldConfig::Mlp(_) => FieldKind::Mlp,
            FieldConfig::Cfc(_) => FieldKind::Cfc,
        }
    }

    /// Which time input.
    pub fn variant(&self) -> Variant {
        match self {
            FieldConfig::Mlp(c) => c.variant,
            FieldConfig::Cfc(c) => c.variant,
        }
    }

    /// MLP: number of trunk layers D. CfC: number of cells D.
    pub fn depth(&self) -> usize {
        match self {
            FieldConfig::Mlp(c) => c.depth,
            FieldConfig::Cfc(c) => c.depth,
        }
    }

    /// MLP: trunk width W. CfC: hidden size W.
    pub fn width(&self) -> usize {
        match self {
            FieldConfig::Mlp(c) => c.width,
            FieldConfig::Cfc(c) => c.width,
        }
    }

    /// The hidden activation: ReLU for the MLP (fixed upstream), the
    /// backbone activation for the CfC field.
    pub fn activation(&self) -> Activation {
        match self {
            FieldConfig::Mlp(_) => Activation::Relu,
            FieldConfig::Cfc(c) => c.activation,
        }
    }

    /// Whether the field is the MLP's 6-DoF (SE(3)) variant (never for CfC).
    pub fn is_6dof(&self) -> bool {
        match self {
            FieldConfig::Mlp(c) => c.is_6dof,
            FieldConfig::Cfc(_) => false,
        }
    }

    /// Set the time input.
    pub fn set_variant(&mut self, variant: Variant) {
        match self {
            FieldConfig::Mlp(c) => c.variant = variant,
            FieldConfig::Cfc(c) => c.variant = variant,
        }
    }

    /// Set the depth (MLP layers or CfC cells).
    pub fn set_depth(&mut self, depth: usize) {
        match self {
            FieldConfig::Mlp(c) => c.depth = depth,
            FieldConfig::Cfc(c) => c.depth = depth,
        }
    }

    /// Set the width (MLP trunk width or CfC hidden size).
    pub fn set_width(&mut self, width: usize) {
        match self {
            FieldConfig::Mlp(c) => c.width = width,
            FieldConfig::Cfc(c) => c.width = width,
        }
    }

    /// Check the configuration is buildable.
    pub fn validate(&self) -> Result<()> {
        let (depth, width) = (self.depth(), self.width());
        if width == 0 {
            return Err(Error::invalid("width", "must be at least 1"));
        }
        for (name, v, max) in [("depth", depth, MAX_DEPTH), ("width", width, MAX_WIDTH)] {
            if v > max {
                return Err(Error::invalid(
                    name,
                    format!("{v} is above the limit {max}"),
                ));
            }
        }
        match self {
            FieldConfig::Mlp(_) => {
                if depth < 3 {
                    return Err(Error::invalid(
                        "depth",
                        format!(
                            "{depth} (the MLP field needs depth >= 3: the skip concatenation after layer depth/2 must feed a later layer)"
                        ),
                    ));
                }
            }
            FieldConfig::Cfc(c) => {
                for (name, v, max) in [
                    ("backbone_units", c.backbone_units, MAX_WIDTH),
                    ("backbone_layers", c.backbone_layers, MAX_BACKBONE_LAYERS),
                ] {
                    if v > max {
                        return Err(Error::invalid(
                            name,
                            format!("{v} is above the limit {max}"),
                        ));
                    }
                }
                if depth == 0 {
                    return Err(Error::invalid(
                        "depth",
                        "the CfC field needs at least one cell",
                    ));
                }
                if c.backbone_units == 0 || c.backbone_layers == 0 {
                    return Err(Error::invalid(
                        "backbone",
                        "backbone_units and backbone_layers must be at least 1",
                    ));
                }
            }
        }
        Ok(())
    }

    /// Width of the time feature: 30 (timenet) or 21 (γ₁₀(t)).
    pub fn time_feature_dim(&self) -> usize {
        self.variant().time_feature_dim()
    }

    /// Width of `[γ₁₀(x), time feature]`: 93 or 84.
    pub fn input_dim(&self) -> usize {
        self.variant().input_dim()
    }
}
