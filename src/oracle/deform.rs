//! Oracle stage `deform`: run a deformation field forward and backward on a
//! case file and return every output and gradient.
//!
//! Case metadata: `stage=deform`, `field=mlp|cfc`, and optionally `variant`,
//! `depth`, `width`, `activation`, `backbone_units`, `backbone_layers`,
//! `is_6dof` (defaults per field kind, see [`FieldConfig::new`](crate::deform::FieldConfig::new)). Case tensors:
//! the weights under their PyTorch `state_dict` names, `xyz` `[N,3]`, `t`
//! `[N,1]`, and the cotangents `grad_d_xyz` `[N,3]`, `grad_d_rotation` `[N,4]`,
//! `grad_d_scaling` `[N,3]` (each optional, absent = zeros), all of one dtype (F32 or F64, which selects the
//! precision). Outputs: `d_xyz`, `d_rotation`, `d_scaling`, `grad_t` `[N,1]`
//! and `grad.<name>` for every weight. For the 6-DoF MLP (`is_6dof=true`)
//! `d_xyz` is `R·x + p − x` (see `deform::se3`), and two more outputs:
//! `d_xyz_se3` `[N,4,4]`, upstream's transform `[[R, p], [0, 0, 0, 1]]`
//! (what `DeformNetwork` returns as d_xyz), and `grad_xyz` `[N,3]`, the
//! gradient the canonical `xyz` receives through the warp,
//! `(R − I)ᵀ·grad_d_xyz` (PyTorch: `x.grad` of
//! `from_homogenous(T @ to_homogenous(x)) − x` with the network fed `x.detach()`).

use crate::deform::Deformation;
use crate::error::{Error, Result};
use crate::io::tensor_file::into_row_major;
use crate::io::TensorFile;
use crate::math::{Precision, Real};

use super::cotangent;

const INPUTS: [&str; 5] = [
    "xyz",
    "t",
    "grad_d_xyz",
    "grad_d_rotation",
    "grad_d_scaling",
];

/// The `stage` metadata value of a deform case.
pub const STAGE: &str = "deform";

/// Run the `deform` stage on `case`.
pub fn run(case: &TensorFile) -> Result<TensorFile> {
    let stage = case.meta("stage")?;
    if stage != "deform" {
        return Err(Error::field(
            &case.path,
            "__metadata__.stage",
            format!("{stage:?}, expected \"deform\""),
        ));
    }
    match case.precision()? {
        Precision::F32 => run_typed::<f32>(case),
        Precision::F64 => run_typed::<f64>(case),
    }
}

fn run_typed<T: Real>(case: &TensorFile) -> Result<TensorFile> {
    let config = crate::oracle::field::config_from_meta(case)?;
    // Weights: every tensor that is not one of the inputs.
    let mut weights = TensorFile::new(&case.path);
    for (name, t) in &case.tensors {
        if !INPUTS.contains(&name.as_str()) {
            weights.tensors.insert(name.clone(), t.clone());
        }
    }
    let field = crate::oracle::field::field_from_tensor_file::<T>(config, &weights)?;
    let xyz = case.real_array::<T>("xyz")?;
    let n = match *xyz.shape() {
        [n, 3] => n,
        ref shape => {
            return Err(Error::Tensor {
                context: case.path.display().to_string(),
                name: "xyz".into(),
                expected: "shape [N,3]".into(),
                found: format!("shape {shape:?}"),
            })
        }
    };
    let xyz = into_row_major(xyz);
    let t = case.get_real::<T>("t", &[n, 1])?;
    let grad = Deformation {
        d_xyz: cotangent::<T>(case, "grad_d_xyz", &[n, 3])?,
        d_rotation: cotangent::<T>(case, "grad_d_rotation", &[n, 4])?,
        d_scaling: cotangent::<T>(case, "grad_d_scaling", &[n, 3])?,
    };
    let (d, cache) = field.forward(&xyz, &t)?;
    let fg = field.backward(&cache, &grad)?;
    let mut out = TensorFile::new(&case.path);
    out.set_meta("stage", "deform");
    crate::oracle::field::config_to_meta(&config, &mut out);
    out.insert_real("d_xyz", vec![n, 3], &d.d_xyz);
    out.insert_real("d_rotation", vec![n, 4], &d.d_rotation);
    out.insert_real("d_scaling", vec![n, 3], &d.d_scaling);
    out.insert_real("grad_t", vec![n, 1], &fg.t);
    if config.is_6dof() {
        out.insert_real("grad_xyz", vec![n, 3], &fg.xyz);
        if let Some(m) = field.se3_transforms(&cache) {
            out.insert_real("d_xyz_se3", vec![n, 4, 4], &m);
        }
    }
    for s in field.layout() {
        out.insert_real(
            &format!("grad.{}", s.name),
            s.shape.clone(),
            &fg.params[s.range()],
        );
    }
    Ok(out)
}
