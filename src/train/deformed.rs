//! Canonical Gaussians + field offsets → the tensors the rasterizer receives,
//! and the chain rule back (docs/UPSTREAM.md §A.3, docs/DECISIONS.md §1):
//!
//! - `means     = xyz + d_xyz`
//! - `scales    = exp(scaling) + d_scaling` (offset added to the linear scale)
//! - `rotations = normalize(rotation) + d_rotation` (never re-normalised)
//! - `opacities = sigmoid(opacity)`, `sh` unchanged.
//!
//! During warm-up (no deformation) the offsets are absent and the same
//! formulas hold with zero offsets.
//!
//! The backward ([`deform_gaussians_vjp`]) runs the field's backward too, so
//! that the canonical means' gradient is assembled in one place: the
//! identity path of `xyz + d_xyz` plus the field's own
//! [`FieldGradients::xyz`] (the 6-DoF warp's `(R − I)ᵀ·g`; zero for the
//! additive fields).

use crate::deform::{Field, FieldGradients, FieldSaved};
use crate::error::Result;
use crate::gaussians::{normalize_vjp, Gaussians};
use crate::math::Real;
use crate::render::RasterGrads;

/// Per-Gaussian offsets from a deformation field: `[N,3]`, `[N,4]`, `[N,3]`.
pub use crate::deform::Deformation as Offsets;

/// The activated, deformed Gaussians handed to the rasterizer.
#[derive(Clone, Debug)]
pub struct Deformed<T> {
    /// Means `[N, 3]`.
    pub means: Vec<T>,
    /// Linear scales `[N, 3]`.
    pub scales: Vec<T>,
    /// Quaternions `[N, 4]` (not re-normalised).
    pub rotations: Vec<T>,
    /// Opacities `[N]` in (0, 1).
    pub opacities: Vec<T>,
}

/// Assemble the rasterizer inputs; `offsets = None` means no deformation.
pub fn deform_gaussians<T: Real>(g: &Gaussians<T>, offsets: Option<&Offsets<T>>) -> Deformed<T> {
    let mut means = g.xyz.clone();
    let mut scales = g.scales();
    let mut rotations = g.rotations();
    if let Some(o) = offsets {
        for (m, d) in means.iter_mut().zip(&o.d_xyz) {
            *m += *d;
        }
        for (s, d) in scales.iter_mut().zip(&o.d_scaling) {
            *s += *d;
        }
        for (r, d) in rotations.iter_mut().zip(&o.d_rotation) {
            *r += *d;
        }
    }
    Deformed {
        means,
        scales,
        rotations,
        opacities: g.opacities(),
    }
}

/// Backward of [`deform_gaussians`] and of the field whose forward (`cache`)
/// gave the offsets (`None`: no deformation), from the rasterizer's
/// gradients `rg` (of an input with SH colours and scales/rotations, as
/// [`deform_gaussians`] feeds it). Returns the gradients of the
/// raw parameters (in a [`Gaussians`] used as a gradient container, same
/// layout) and every gradient of the field. The offsets receive the
/// rasterizer's gradients unchanged (each is added once); the canonical
/// means receive the identity path plus the field's
/// [`FieldGradients::xyz`].
pub fn deform_gaussians_vjp<T: Real>(
    g: &Gaussians<T>,
    field: Option<(&Field<T>, &FieldSaved<T>)>,
    rg: &RasterGrads<T>,
) -> Result<(Gaussians<T>, Option<FieldGradients<T>>)> {
    let (mut gaussians, offsets) = activations_vjp(g, rg);
    let Some((field, cache)) = field else {
        return Ok((gaussians, None));
    };
    let fg = field.backward(cache, &offsets)?;
    for (a, &b) in gaussians.xyz.iter_mut().zip(&fg.xyz) {
        // Adding an exact zero (every entry of an additive field's) would
        // change nothing but the sign of a −0.
        if b != T::ZERO {
            *a += b;
        }
    }
    Ok((gaussians, Some(fg)))
}

/// The chain rule of [`deform_gaussians`] alone: the gradients of the raw
/// parameters (the means' identity path only) and of the offsets.
fn activations_vjp<T: Real>(g: &Gaussians<T>, rg: &RasterGrads<T>) -> (Gaussians<T>, Offsets<T>) {
    let (grad_means, grad_sh) = (&rg.means3d, &rg.colors);
    let (grad_scales, grad_rotations) = (&rg.scales_or_cov, &rg.rotations);
    let grad_opacities = &rg.opacities;
    let n = g.len();
    let scaling: Vec<T> = g
        .scaling
        .iter()
        .zip(grad_scales)
        .map(|(&s, &gs)| gs * s.exp())
        .collect();
    let mut rotation = vec![T::ZERO; 4 * n];
    for i in 0..n {
        normalize_vjp(
            &g.rotation[4 * i..4 * i + 4],
            &grad_rotations[4 * i..4 * i + 4],
            &mut rotation[4 * i..4 * i + 4],
        );
    }
    let opacity = g
        .opacity
        .iter()
        .zip(grad_opacities)
        .map(|(&o, &go)| {
            let s = o.sigmoid();
            go * s * (T::ONE - s)
        })
        .collect();
    (
        Gaussians {
            max_sh_degree: g.max_sh_degree,
            xyz: grad_means.to_vec(),
            sh: grad_sh.to_vec(),
            scaling,
            rotation,
            opacity,
        },
        Offsets {
            d_xyz: grad_means.to_vec(),
            d_rotation: grad_rotations.to_vec(),
            d_scaling: grad_scales.to_vec(),
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::gradcheck::{compare, cotangent, numeric_gradient};

    fn scene() -> (Gaussians<f64>, Offsets<f64>) {
        let g = Gaussians {
            max_sh_degree: 0,
            xyz: vec![0.1, 0.2, 0.3, -0.4, 0.5, 0.6],
            sh: vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
            scaling: vec![-1.0, -2.0, -0.5, -1.5, -1.2, -0.7],
            rotation: vec![0.9, 0.1, -0.2, 0.3, 0.5, 0.5, 0.4, -0.6],
            opacity: vec![0.3, -1.1],
        };
        let o = Offsets {
            d_xyz: vec![0.01, -0.02, 0.03, 0.0, 0.01, 0.02],
            d_rotation: vec![0.01, 0.0, 0.02, -0.01, 0.0, 0.03, 0.0, 0.01],
            d_scaling: vec![0.001, 0.002, 0.0, -0.001, 0.0, 0.001],
        };
        (g, o)
    }

    #[test]
    fn vjp_matches_finite_differences() {
        let (g, o) = scene();
        let d = deform_gaussians(&g, Some(&o));
        let cm = cotangent(1, d.means.len());
        let cs = cotangent(2, d.scales.len());
        let cr = cotangent(3, d.rotations.len());
        let co = cotangent(4, d.opacities.len());
        let loss = |g: &Gaussians<f64>, o: &Offsets<f64>| {
            let d = deform_gaussians(g, Some(o));
            let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
            dot(&d.means, &cm)
                + dot(&d.scales, &cs)
                + dot(&d.rotations, &cr)
                + dot(&d.opacities, &co)
        };
        let rg = RasterGrads {
            means3d: cm.clone(),
            means2d: vec![],
            colors: vec![0.0; 6],
            opacities: co.clone(),
            scales_or_cov: cs.clone(),
            rotations: cr.clone(),
        };
        let (gg, go) = activations_vjp(&g, &rg);
        type Field = for<'a> fn(&'a mut Gaussians<f64>, &'a mut Offsets<f64>) -> &'a mut Vec<f64>;
        let check = |name: &str, analytic: &[f64], field: Field| {
            let (mut g2, mut o2) = scene();
            let mut x = field(&mut g2, &mut o2).clone();
            let num = numeric_gradient(&mut x, 1e-6, |x| {
                let (mut g3, mut o3) = (g2.clone(), o2.clone());
                field(&mut g3, &mut o3).copy_from_slice(x);
                loss(&g3, &o3)
            });
            let r = compare(name, analytic, &num, 1e-9);
            assert!(r.passes(1e-7), "{r}");
        };
        check("xyz", &gg.xyz, |g, _| &mut g.xyz);
        check("scaling", &gg.scaling, |g, _| &mut g.scaling);
        check("rotation", &gg.rotation, |g, _| &mut g.rotation);
        check("opacity", &gg.opacity, |g, _| &mut g.opacity);
        check("d_xyz", &go.d_xyz, |_, o| &mut o.d_xyz);
        check("d_rotation", &go.d_rotation, |_, o| &mut o.d_rotation);
        check("d_scaling", &go.d_scaling, |_, o| &mut o.d_scaling);
    }
}
