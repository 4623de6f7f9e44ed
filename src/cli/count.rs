//! `liquid-splat count`: parameters and multiply-accumulates (MACs) of a
//! deformation field, per Gaussian and for N Gaussians, under the ptflops
//! counting conventions of docs/UPSTREAM.md §8.3 (see `crate::deform::count`).

use crate::deform::count::{macs_per_gaussian, param_count, MacConvention};
use crate::deform::{CfcConfig, FieldConfig, Variant};
use crate::error::Outcome;
use crate::report::tables::thousands;
use crate::Error;
use clap::Args;

/// Arguments of `count`.
#[derive(Args)]
pub struct CountArgs {
    /// The field to count.
    #[command(flatten)]
    pub field: super::train::FieldArgs,
    /// Number of Gaussians for the totals.
    #[arg(long, default_value_t = 1)]
    pub gaussians: u64,
    /// Print one JSON object instead of a table.
    #[arg(long)]
    pub json: bool,
}

fn config(a: &CountArgs) -> crate::Result<FieldConfig> {
    a.field.spec().config(Variant::Synthetic)
}

fn convention_key(c: MacConvention) -> &'static str {
    match c {
        MacConvention::Pytorch => "pytorch",
        MacConvention::PytorchNoFunctional => "pytorch_no_functional",
        MacConvention::Aten => "aten",
    }
}

/// Run `count`.
pub fn run(a: CountArgs) -> crate::Result<Outcome> {
    let c = config(&a)?;
    let params = param_count(&c)? as u64;
    let n = a.gaussians;
    let mut rows = Vec::new();
    for conv in MacConvention::ALL {
        let per = macs_per_gaussian(&c, conv)?;
        let total = per.checked_mul(n).ok_or_else(|| {
            Error::invalid("gaussians", format!("{n}: the MAC total overflows 64 bits"))
        })?;
        rows.push((conv, per, total));
    }
    let arch = match &c {
        FieldConfig::Mlp(m) => format!(
            "mlp, variant {}, depth {}, width {}, activation relu{}",
            m.variant,
            m.depth,
            m.width,
            if m.is_6dof { ", 6-DoF (SE(3))" } else { "" }
        ),
        FieldConfig::Cfc(m) => format!(
            "cfc, variant {}, {} cells, width {}, backbone {}x{} {}",
            m.variant, m.depth, m.width, m.backbone_layers, m.backbone_units, m.activation
        ),
    };
    // The JSON keeps one shape for both kinds: the MLP, which has no
    // backbone, reports the CfC defaults there, as case-file metadata does.
    let (units, layers) = match &c {
        FieldConfig::Mlp(_) => {
            let d = CfcConfig::paper();
            (d.backbone_units, d.backbone_layers)
        }
        FieldConfig::Cfc(m) => (m.backbone_units, m.backbone_layers),
    };
    if a.json {
        let macs: serde_json::Map<String, serde_json::Value> = rows
            .iter()
            .map(|(conv, per, total)| {
                (
                    convention_key(*conv).to_string(),
                    serde_json::json!({
                        "convention": conv.name(),
                        "per_gaussian": per,
                        "total": total,
                    }),
                )
            })
            .collect();
        let v = serde_json::json!({
            "field": c.kind().name(),
            "variant": c.variant().name(),
            "depth": c.depth(),
            "width": c.width(),
            "activation": c.activation().name(),
            "backbone_units": units,
            "backbone_layers": layers,
            "is_6dof": c.is_6dof(),
            "parameters": params,
            "gaussians": n,
            "macs": macs,
            "default_convention": convention_key(MacConvention::Pytorch),
        });
        outln!(
            "{}",
            serde_json::to_string_pretty(&v).expect("JSON of plain values")
        );
        return Ok(Outcome::Success);
    }
    outln!("field: {arch}");
    outln!(
        "parameters: {} ({:.4} M)",
        thousands(params),
        params as f64 / 1e6
    );
    outln!("gaussians: {}", thousands(n));
    outln!("MACs (ptflops conventions, docs/UPSTREAM.md §8.3; a Linear layer counts in·out + out per Gaussian;");
    outln!("      sin/cos, tanh, sigmoid and element-wise arithmetic count 0):");
    outln!(
        "  {:<52} {:>16} {:>22}",
        "convention",
        "per Gaussian",
        "total"
    );
    for (conv, per, total) in &rows {
        let mark = if *conv == MacConvention::Pytorch {
            " (ptflops 0.7.4+ default)"
        } else if *conv == MacConvention::Aten {
            " (ptflops 0.7.3 default)"
        } else {
            ""
        };
        outln!(
            "  {:<52} {:>16} {:>22}{mark}",
            conv.name(),
            thousands(*per),
            thousands(*total)
        );
    }
    Ok(Outcome::Success)
}
