//! A deformation field: its configuration, its network and one flat
//! parameter vector, with the forward ([`Field::forward`]) and the backward
//! ([`Field::backward`]) that returns every gradient of the field.

use super::config::{FieldConfig, MAX_FIELD_PARAMS};
use super::layers::{Init, LayoutBuilder, ParamSpec};
use super::linear::LinearShape;
use super::{cfc, mlp};
use crate::error::{Error, Result};
use crate::math::{Real, Rng};

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
    /// Whether there are no Gaussians.
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
pub(super) enum Net {
    Mlp(mlp::MlpNet),
    Cfc(cfc::CfcNet),
}

/// What [`Field::backward`] needs from [`Field::forward`].
pub struct FieldSaved<T> {
    n: usize,
    /// The architecture of the field that made it: [`Field::backward`]
    /// refuses a cache from another one (its buffers have other sizes).
    config: FieldConfig,
    t: Vec<T>,
    inner: SavedInner<T>,
}

enum SavedInner<T> {
    Mlp(mlp::MlpCache<T>),
    Cfc(cfc::CfcCache<T>),
}

impl<T> FieldSaved<T> {
    /// Number of Gaussians of the forward pass.
    pub fn len(&self) -> usize {
        self.n
    }
    /// Whether the forward pass had no Gaussians.
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
    /// The network and the parameter layout of `config` (validated, and
    /// within [`MAX_FIELD_PARAMS`]), before any parameter is allocated.
    pub(super) fn build(config: FieldConfig) -> Result<(Net, LayoutBuilder)> {
        config.validate()?;
        let mut lb = LayoutBuilder::default();
        let net = match &config {
            FieldConfig::Mlp(c) => Net::Mlp(mlp::MlpNet::build(c, &mut lb)),
            FieldConfig::Cfc(c) => Net::Cfc(cfc::CfcNet::build(c, &mut lb)),
        };
        if lb.len > MAX_FIELD_PARAMS {
            // (The CfC's backbone counts too.)
            let backbone = match &config {
                FieldConfig::Cfc(c) => format!(
                    " with a backbone of {} layers of {} units",
                    c.backbone_layers, c.backbone_units
                ),
                FieldConfig::Mlp(_) => String::new(),
            };
            return Err(Error::invalid(
                "field size",
                format!(
                    "{} D{} W{}{backbone} has {} parameters, more than the limit {MAX_FIELD_PARAMS}",
                    config.kind(),
                    config.depth(),
                    config.width(),
                    lb.len
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

    /// Each tensor's name, shape and offset for a field of `config`, in
    /// `state_dict` order, without allocating the parameters (errors as
    /// [`new`](Self::new)).
    pub fn layout_of(config: FieldConfig) -> Result<Vec<ParamSpec>> {
        Ok(Self::build(config)?.1.specs)
    }

    /// A field of `config` with the given parameters, flat in
    /// [`layout`](Self::layout) order; their count must match the layout.
    pub fn from_params(config: FieldConfig, params: Vec<T>) -> Result<Self> {
        let (net, lb) = Self::build(config)?;
        if params.len() != lb.len {
            return Err(Error::invalid(
                "field parameters",
                format!(
                    "{} values, expected {} for {} D{} W{}",
                    params.len(),
                    lb.len,
                    config.kind(),
                    config.depth(),
                    config.width()
                ),
            ));
        }
        Ok(Field {
            config,
            params,
            layout: lb.specs,
            net,
        })
    }

    /// The architecture.
    pub fn config(&self) -> &FieldConfig {
        &self.config
    }
    /// All parameters, flat, in [`layout`](Self::layout) order.
    pub fn params(&self) -> &[T] {
        &self.params
    }
    /// All parameters, flat, for the optimizer to update in place.
    pub fn params_mut(&mut self) -> &mut [T] {
        &mut self.params
    }
    /// Each tensor's name, shape and offset, in `state_dict` order.
    pub fn layout(&self) -> &[ParamSpec] {
        &self.layout
    }
    /// Number of learned parameters.
    pub fn param_count(&self) -> usize {
        self.params.len()
    }

    /// Evaluate the field for `xyz` `[N, 3]` and per-Gaussian times `t` `[N]`.
    pub fn forward(&self, xyz: &[T], t: &[T]) -> Result<(Deformation<T>, FieldSaved<T>)> {
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
        // (The MLP's ReLU turned a NaN time or position into finite
        // offsets without a word.)
        for (name, values) in [("xyz", xyz), ("t", t)] {
            if let Some((i, v)) = crate::math::first_non_finite(values) {
                return Err(Error::invalid(
                    "field input",
                    format!("{name}[{i}] = {v} is not finite"),
                ));
            }
        }
        let (d, inner) = match &self.net {
            Net::Mlp(m) => {
                let (d, c) = m.forward(&self.params, xyz, t);
                (d, SavedInner::Mlp(c))
            }
            Net::Cfc(m) => {
                let (d, c) = m.forward(&self.params, xyz, t);
                (d, SavedInner::Cfc(c))
            }
        };
        Ok((
            d,
            FieldSaved {
                n,
                config: self.config,
                t: t.to_vec(),
                inner,
            },
        ))
    }

    /// Backward: every gradient of the field given the gradient `grad` of
    /// its outputs ([`FieldGradients`]). `cache` must come from the
    /// [`forward`](Self::forward) of a field of the same architecture
    /// ([`config`](Self::config)); another is an error.
    pub fn backward(
        &self,
        cache: &FieldSaved<T>,
        grad: &Deformation<T>,
    ) -> Result<FieldGradients<T>> {
        if cache.config != self.config {
            return Err(Error::invalid(
                "field cache",
                format!(
                    "the cache comes from a field of {:?}, not this one's {:?}",
                    cache.config, self.config
                ),
            ));
        }
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
            (Net::Mlp(m), SavedInner::Mlp(c)) => {
                m.backward(&self.params, &cache.t, c, grad, &mut params)
            }
            (Net::Cfc(m), SavedInner::Cfc(c)) => (
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
    pub fn se3_transforms(&self, cache: &FieldSaved<T>) -> Option<Vec<T>> {
        match (&self.net, &cache.inner) {
            (Net::Mlp(m), SavedInner::Mlp(c)) => m.se3_transforms(c),
            _ => None,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::deform::config::{CfcConfig, MlpConfig};

    /// A cache from a field of the same kind but another architecture is an
    /// error, not a panic in the layers.
    #[test]
    fn backward_refuses_a_cache_of_another_architecture() {
        let mlp = |depth, width, is_6dof| {
            FieldConfig::Mlp(MlpConfig {
                depth,
                width,
                is_6dof,
                ..MlpConfig::paper()
            })
        };
        let cfc = |depth, width| {
            FieldConfig::Cfc(CfcConfig {
                depth,
                width,
                backbone_units: 8,
                ..CfcConfig::paper()
            })
        };
        let pairs = [
            (mlp(4, 8, false), mlp(6, 16, false)),
            (mlp(4, 8, false), mlp(4, 8, true)),
            (cfc(1, 4), cfc(2, 8)),
            (cfc(1, 4), mlp(4, 8, false)),
        ];
        let (xyz, t) = ([0.1f64, 0.2, 0.3, -0.1, 0.0, 0.5], [0.25f64, 0.75]);
        for (from, to) in pairs {
            let a = Field::<f64>::new(from, 1).unwrap();
            let b = Field::<f64>::new(to, 2).unwrap();
            let (d, cache) = a.forward(&xyz, &t).unwrap();
            assert!(a.backward(&cache, &d).is_ok());
            let e = b.backward(&cache, &d).unwrap_err();
            assert!(e.to_string().contains("field cache"), "{e}");
        }
    }

    /// A position or time that is not finite is an error naming it: the
    /// MLP's ReLU turned a NaN time into finite offsets.
    #[test]
    fn non_finite_inputs_are_refused() {
        let config = FieldConfig::Mlp(MlpConfig {
            depth: 4,
            width: 8,
            ..MlpConfig::paper()
        });
        let f = Field::<f32>::new(config, 1).unwrap();
        let (xyz, t) = ([0.1f32, 0.2, 0.3, -0.1, 0.0, 0.5], [0.25f32, 0.75]);
        assert!(f.forward(&xyz, &t).is_ok());
        let mut bad_t = t;
        bad_t[1] = f32::NAN;
        let e = f.forward(&xyz, &bad_t).err().unwrap().to_string();
        assert!(e.contains("t[1] = NaN"), "{e}");
        let mut bad_x = xyz;
        bad_x[4] = f32::INFINITY;
        let e = f.forward(&bad_x, &t).err().unwrap().to_string();
        assert!(e.contains("xyz[4] = inf"), "{e}");
    }
}
