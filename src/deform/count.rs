//! Parameter and multiply-accumulate (MAC) counts of the deformation fields,
//! with the conventions of ptflops (docs/UPSTREAM.md §8.3).
//!
//! MACs per Gaussian are the figure ptflops reports for a batch of one point.
//! Every convention counts each Linear layer as `in·out + out`. They differ in
//! the activations:
//! - [`MacConvention::Aten`] (ptflops `aten` backend, the 0.7.3 default):
//!   Linear layers only.
//! - [`MacConvention::Pytorch`] (`pytorch` backend, `count_functional`
//!   on, the default from 0.7.4): `nn.ReLU`/`nn.GELU` modules count
//!   `2·numel` (module hook plus the patched functional), `nn.SiLU` counts
//!   `numel` (functional only), a functional `F.relu` (the D-3DGS trunk)
//!   counts `numel`; tanh, sigmoid, lecun_tanh, sin/cos, concatenation and
//!   element-wise arithmetic count 0.
//! - [`MacConvention::PytorchNoFunctional`] (`count_functional=False`):
//!   only the module hooks, so `nn.ReLU`/`nn.GELU` count `numel`, the rest 0.
//!
//! Totals for N Gaussians are N × the per-Gaussian figure (what ptflops
//! reports when all N points are passed through a dict input constructor;
//! with one positional batch tensor it mixes per-point and total counts).

use super::{Activation, Field, FieldConfig, Variant, TIMENET_HIDDEN};
use crate::error::Result;
use std::fmt;

/// A ptflops counting convention.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MacConvention {
    /// ptflops' aten backend: linear layers only.
    Aten,
    /// ptflops' pytorch backend with `count_functional=True`.
    Pytorch,
    /// ptflops' pytorch backend with `count_functional=False`.
    PytorchNoFunctional,
}

impl MacConvention {
    /// Every convention, in the order reports list them.
    pub const ALL: [MacConvention; 3] = [
        MacConvention::Aten,
        MacConvention::Pytorch,
        MacConvention::PytorchNoFunctional,
    ];
    /// A description of the convention for reports.
    pub fn name(self) -> &'static str {
        match self {
            MacConvention::Aten => "ptflops aten backend (linear layers only)",
            MacConvention::Pytorch => "ptflops pytorch backend, count_functional=True",
            MacConvention::PytorchNoFunctional => "ptflops pytorch backend, count_functional=False",
        }
    }
}

impl fmt::Display for MacConvention {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Number of learned parameters of a field (no weights are allocated).
pub fn param_count(config: &FieldConfig) -> Result<usize> {
    let (_, lb) = Field::<f32>::build(*config)?;
    Ok(lb.specs.iter().map(|s| s.len()).sum())
}

/// MACs ptflops counts for one activation module of `numel` outputs.
fn module_act(act: Activation, numel: u64, conv: MacConvention) -> u64 {
    match (conv, act) {
        (MacConvention::Aten, _) => 0,
        (MacConvention::Pytorch, Activation::Relu | Activation::Gelu) => 2 * numel,
        (MacConvention::Pytorch, Activation::Silu) => numel,
        (MacConvention::PytorchNoFunctional, Activation::Relu | Activation::Gelu) => numel,
        _ => 0,
    }
}

/// MACs per Gaussian under `conv`.
pub fn macs_per_gaussian(config: &FieldConfig, conv: MacConvention) -> Result<u64> {
    let (_, lb) = Field::<f32>::build(*config)?;
    let linear: u64 = lb
        .linears
        .iter()
        .map(|l| (l.shape.in_dim * l.shape.out_dim + l.shape.out_dim) as u64)
        .sum();
    let mut acts = 0;
    if config.variant() == Variant::Synthetic {
        // timenet: nn.ReLU(inplace=True) module on 256 values.
        acts += module_act(Activation::Relu, TIMENET_HIDDEN as u64, conv);
    }
    match config {
        FieldConfig::Mlp(c) => {
            // The trunk calls F.relu: counted only by the functional patch.
            if conv == MacConvention::Pytorch {
                acts += (c.depth * c.width) as u64;
            }
        }
        FieldConfig::Cfc(c) => {
            let per_cell = (c.backbone_layers * c.backbone_units) as u64;
            acts += c.depth as u64 * module_act(c.activation, per_cell, conv);
        }
    }
    Ok(linear + acts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deform::FieldKind;
    use crate::deform::{CfcConfig, MlpConfig};

    fn cfg(
        kind: FieldKind,
        depth: usize,
        width: usize,
        act: Activation,
        variant: Variant,
    ) -> FieldConfig {
        match kind {
            FieldKind::Mlp => {
                assert_eq!(act, Activation::Relu, "the MLP field is ReLU");
                FieldConfig::Mlp(MlpConfig {
                    depth,
                    width,
                    variant,
                    ..MlpConfig::paper()
                })
            }
            FieldKind::Cfc => FieldConfig::Cfc(CfcConfig {
                depth,
                width,
                activation: act,
                variant,
                ..CfcConfig::paper()
            }),
        }
    }

    #[test]
    fn parameter_counts_match_the_paper() {
        use Activation::*;
        use FieldKind::*;
        use Variant::*;
        // docs/UPSTREAM.md §6.3 and §8.2 (counts of the PyTorch modules).
        assert_eq!(
            param_count(&cfg(Mlp, 8, 256, Relu, Synthetic)).unwrap(),
            522_280
        );
        assert_eq!(param_count(&cfg(Mlp, 8, 256, Relu, Real)).unwrap(), 506_378);
        // docs/UPSTREAM.md §6.3: the 6-DoF MLP (branch_w and branch_v replace the warp head).
        let six = FieldConfig::Mlp(MlpConfig {
            is_6dof: true,
            ..MlpConfig::paper()
        });
        assert_eq!(param_count(&six).unwrap(), 523_051);
        assert_eq!(
            param_count(&cfg(Cfc, 8, 256, Gelu, Synthetic)).unwrap(),
            782_888
        );
        assert_eq!(
            param_count(&cfg(Cfc, 6, 128, Gelu, Synthetic)).unwrap(),
            334_504
        );
        assert_eq!(param_count(&cfg(Cfc, 8, 256, Gelu, Real)).unwrap(), 764_682);
        assert_eq!(param_count(&cfg(Cfc, 6, 128, Gelu, Real)).unwrap(), 318_602);
        // The closed form of §8.2: D·cell + skip + head + timenet.
        for (d, w) in [(8usize, 256usize), (6, 128), (3, 8)] {
            let cell = (93 + w) * 64 + 64 + (64 * 64 + 64) + 4 * (64 * w + w);
            let total = d * cell + (93 * w + w) + (10 * w + 10) + 11_294;
            assert_eq!(
                param_count(&cfg(Cfc, d, w, Gelu, Synthetic)).unwrap(),
                total
            );
        }
    }

    #[test]
    fn mac_counts_match_ptflops_reference_table() {
        use Activation::*;
        use FieldKind::*;
        use MacConvention::*;
        use Variant::*;
        // docs/UPSTREAM.md §8.3 reference counts (one point), columns:
        // pytorch (functional on), pytorch (functional off), aten.
        let table: &[(FieldConfig, [u64; 3])] = &[
            (
                cfg(Mlp, 8, 256, Relu, Synthetic),
                [524_840, 522_536, 522_280],
            ),
            (cfg(Mlp, 8, 256, Relu, Real), [508_426, 506_378, 506_378]),
            (
                cfg(Cfc, 8, 256, Relu, Synthetic),
                [785_448, 784_168, 782_888],
            ),
            (
                cfg(Cfc, 8, 256, Gelu, Synthetic),
                [785_448, 784_168, 782_888],
            ),
            (
                cfg(Cfc, 8, 256, Silu, Synthetic),
                [784_424, 783_144, 782_888],
            ),
            (
                cfg(Cfc, 8, 256, Tanh, Synthetic),
                [783_400, 783_144, 782_888],
            ),
            (
                cfg(Cfc, 8, 256, LecunTanh, Synthetic),
                [783_400, 783_144, 782_888],
            ),
            (
                cfg(Cfc, 6, 128, Relu, Synthetic),
                [336_552, 335_528, 334_504],
            ),
            (
                cfg(Cfc, 6, 128, Gelu, Synthetic),
                [336_552, 335_528, 334_504],
            ),
            (
                cfg(Cfc, 6, 128, Silu, Synthetic),
                [335_784, 334_760, 334_504],
            ),
            (
                cfg(Cfc, 6, 128, Tanh, Synthetic),
                [335_016, 334_760, 334_504],
            ),
            (
                cfg(Cfc, 6, 128, LecunTanh, Synthetic),
                [335_016, 334_760, 334_504],
            ),
        ];
        for (c, [pt, ptnf, aten]) in table {
            assert_eq!(macs_per_gaussian(c, Pytorch).unwrap(), *pt, "{c:?}");
            assert_eq!(
                macs_per_gaussian(c, PytorchNoFunctional).unwrap(),
                *ptnf,
                "{c:?}"
            );
            assert_eq!(macs_per_gaussian(c, Aten).unwrap(), *aten, "{c:?}");
        }
    }
}
