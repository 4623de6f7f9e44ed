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

/// Architecture of a deformation field.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FieldConfig {
    /// Which network.
    pub kind: FieldKind,
    /// Which time input.
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
}
