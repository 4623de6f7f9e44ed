//! Deformation fields in tensor files: a field's configuration as metadata
//! keys, and its weights as tensors under their PyTorch `state_dict` names.
//! Case files (the `deform` and `step` stages), `case new` and training
//! checkpoints read and write fields through these functions.
//!
//! Metadata keys: `field` (`mlp` or `cfc`, required), `variant`, `depth`,
//! `width`, `activation`, `backbone_units`, `backbone_layers`, `is_6dof`
//! (each optional, defaulting per kind as [`FieldConfig::new`]). Every key is
//! written for every kind; a value present in a file must parse, whatever
//! the kind, or the file is refused with an error naming the file, the key
//! and the value. A key for an option the kind does not have (`activation`,
//! `backbone_units`, `backbone_layers` for the MLP; `is_6dof` for the CfC
//! field) may only hold the value [`config_to_meta`] writes there (`relu`,
//! 64, 2; `false`); any other value is refused the same way.

use crate::deform::{Activation, CfcConfig, Field, FieldConfig, FieldKind, MlpConfig, Variant};
use crate::error::{Error, Result};
use crate::io::TensorFile;
use crate::math::Real;
use std::str::FromStr;

/// The configuration keys, in the order [`config_to_meta`] writes them.
pub const CONFIG_KEYS: [&str; 8] = [
    "field",
    "variant",
    "depth",
    "width",
    "activation",
    "backbone_units",
    "backbone_layers",
    "is_6dof",
];

/// An optional metadata value parsed by `parse`, or `default` when the key
/// is absent; a value that does not parse is an error naming the file, the
/// key and the value.
fn optional<V>(
    file: &TensorFile,
    key: &str,
    default: V,
    parse: impl FnOnce(&str) -> std::result::Result<V, String>,
) -> Result<V> {
    let Some(s) = file.metadata.get(key) else {
        return Ok(default);
    };
    parse(s.trim()).map_err(|why| {
        Error::field(
            &file.path,
            format!("__metadata__.{key}"),
            format!("{s:?}: {why}"),
        )
    })
}

/// A number (or `true`/`false`) with `FromStr`.
fn number<V: FromStr>(s: &str) -> std::result::Result<V, String> {
    s.parse()
        .map_err(|_| format!("not a {}", std::any::type_name::<V>()))
}

/// A name parsed by one of the configuration enums' `parse`.
fn name<V>(parse: fn(&str) -> Result<V>) -> impl FnOnce(&str) -> std::result::Result<V, String> {
    move |s| parse(s).map_err(|e| e.to_string())
}

/// Read a field configuration from a file's metadata (see the module docs
/// for the keys). The combination is checked where the field is built
/// ([`FieldConfig::validate`]).
pub fn config_from_meta(file: &TensorFile) -> Result<FieldConfig> {
    let kind = optional(file, "field", None, |s| name(FieldKind::parse)(s).map(Some))?
        .ok_or_else(|| Error::field(&file.path, "__metadata__.field", "missing"))?;
    let (mlp, cfc) = (MlpConfig::paper(), CfcConfig::paper());
    let variant = optional(file, "variant", Variant::Synthetic, name(Variant::parse))?;
    let activation = optional(file, "activation", None, |s| {
        name(Activation::parse)(s).map(Some)
    })?;
    let backbone_units = optional(file, "backbone_units", None, |s| {
        number::<usize>(s).map(Some)
    })?;
    let backbone_layers = optional(file, "backbone_layers", None, |s| {
        number::<usize>(s).map(Some)
    })?;
    let is_6dof = optional(file, "is_6dof", None, |s| number::<bool>(s).map(Some))?;
    // An option of the other architecture may only hold the value
    // `config_to_meta` writes in its place.
    let foreign = |key: &str, value: String, written: String| -> Result<()> {
        if value == written {
            return Ok(());
        }
        Err(Error::field(
            &file.path,
            format!("__metadata__.{key}"),
            format!(
                "{value:?}: the {kind} field has no {key} option (only {written:?} may be written)"
            ),
        ))
    };
    Ok(match kind {
        FieldKind::Mlp => {
            if let Some(a) = activation {
                foreign("activation", a.to_string(), Activation::Relu.to_string())?;
            }
            if let Some(u) = backbone_units {
                foreign(
                    "backbone_units",
                    u.to_string(),
                    cfc.backbone_units.to_string(),
                )?;
            }
            if let Some(l) = backbone_layers {
                foreign(
                    "backbone_layers",
                    l.to_string(),
                    cfc.backbone_layers.to_string(),
                )?;
            }
            FieldConfig::Mlp(MlpConfig {
                variant,
                depth: optional(file, "depth", mlp.depth, number)?,
                width: optional(file, "width", mlp.width, number)?,
                is_6dof: is_6dof.unwrap_or(mlp.is_6dof),
            })
        }
        FieldKind::Cfc => {
            if let Some(six) = is_6dof {
                foreign("is_6dof", six.to_string(), false.to_string())?;
            }
            FieldConfig::Cfc(CfcConfig {
                variant,
                depth: optional(file, "depth", cfc.depth, number)?,
                width: optional(file, "width", cfc.width, number)?,
                activation: activation.unwrap_or(cfc.activation),
                backbone_units: backbone_units.unwrap_or(cfc.backbone_units),
                backbone_layers: backbone_layers.unwrap_or(cfc.backbone_layers),
            })
        }
    })
}

/// Write the keys [`config_from_meta`] reads. Every key is written for
/// every kind: an option the field does not have holds the value it would
/// have in the other architecture's defaults (`activation` `relu` for the
/// MLP, `backbone_units` 64 and `backbone_layers` 2 for the MLP, `is_6dof`
/// `false` for the CfC field), so the format is the same for both.
pub fn config_to_meta(config: &FieldConfig, file: &mut TensorFile) {
    let cfc = CfcConfig::paper();
    let (units, layers) = match config {
        FieldConfig::Mlp(_) => (cfc.backbone_units, cfc.backbone_layers),
        FieldConfig::Cfc(c) => (c.backbone_units, c.backbone_layers),
    };
    file.set_meta("field", config.kind());
    file.set_meta("variant", config.variant());
    file.set_meta("depth", config.depth());
    file.set_meta("width", config.width());
    file.set_meta("activation", config.activation());
    file.set_meta("backbone_units", units);
    file.set_meta("backbone_layers", layers);
    file.set_meta("is_6dof", config.is_6dof());
}

/// The field's weights as a tensor file under their `state_dict` names,
/// with its configuration in the metadata.
pub fn field_to_tensor_file<T: Real>(field: &Field<T>) -> TensorFile {
    let mut f = TensorFile::new("field");
    config_to_meta(field.config(), &mut f);
    for s in field.layout() {
        f.insert_real(&s.name, s.shape.clone(), &field.params()[s.range()]);
    }
    f
}

/// A field of architecture `config` with the weights of `file`, loaded by
/// `state_dict` name. Missing, misshaped (or wrong dtype) and unexpected
/// tensors are errors naming them. A file that carries a configuration in
/// its metadata (a `field` key, as [`field_to_tensor_file`] writes) must
/// describe `config`: a malformed value, or one that differs, is an error
/// naming the key and both values.
pub fn field_from_tensor_file<T: Real>(config: FieldConfig, file: &TensorFile) -> Result<Field<T>> {
    if file.metadata.contains_key("field") {
        let found = config_from_meta(file)?;
        if found != config {
            let mut expected = TensorFile::new(&file.path);
            config_to_meta(&config, &mut expected);
            let mut written = TensorFile::new(&file.path);
            config_to_meta(&found, &mut written);
            for key in CONFIG_KEYS {
                let (f, e) = (&written.metadata[key], &expected.metadata[key]);
                if f != e {
                    return Err(Error::field(
                        &file.path,
                        format!("__metadata__.{key}"),
                        format!("{f:?}, but the field is {e:?}"),
                    ));
                }
            }
        }
    }
    let specs = Field::<T>::layout_of(config)?;
    // Every tensor present with its shape before the vector is allocated:
    // a small file cannot claim a huge architecture.
    for s in &specs {
        file.expect_shape(&s.name, &s.shape)?;
    }
    let total = specs.iter().map(|s| s.len()).sum();
    let mut params = vec![T::ZERO; total];
    for s in &specs {
        let v = file.get_real::<T>(&s.name, &s.shape)?;
        params[s.range()].copy_from_slice(&v);
    }
    file.reject_unknown(specs.iter().map(|s| s.name.as_str()))?;
    Field::from_params(config, params)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn small_mlp() -> FieldConfig {
        FieldConfig::Mlp(MlpConfig {
            depth: 3,
            width: 4,
            ..MlpConfig::paper()
        })
    }

    #[test]
    fn round_trip_keeps_the_configuration_and_the_weights() {
        let cfc = FieldConfig::Cfc(CfcConfig {
            depth: 2,
            width: 3,
            backbone_units: 5,
            backbone_layers: 1,
            variant: Variant::Real,
            ..CfcConfig::paper()
        });
        for config in [small_mlp(), cfc] {
            let field = Field::<f32>::new(config, 3).unwrap();
            let file = TensorFile::from_bytes(
                std::path::Path::new("f.safetensors"),
                &field_to_tensor_file(&field).to_bytes().unwrap(),
            )
            .unwrap();
            assert_eq!(config_from_meta(&file).unwrap(), config);
            let back = field_from_tensor_file::<f32>(config, &file).unwrap();
            assert_eq!(back.params(), field.params());
        }
    }

    /// A malformed value is an error naming the key and the value, for
    /// every key, whichever kind of field the file describes (a CfC-only key
    /// in an MLP file too).
    #[test]
    fn malformed_values_are_errors_naming_key_and_value() {
        let field = Field::<f64>::new(small_mlp(), 1).unwrap();
        for (key, bad) in [
            ("field", "transformer"),
            ("variant", "blender"),
            ("depth", "three"),
            ("width", "wide"),
            ("width", "-4"),
            ("activation", "swish"),
            ("backbone_units", "many"),
            ("backbone_layers", "1.5"),
            ("is_6dof", "yes"),
        ] {
            let mut file = field_to_tensor_file(&field);
            file.set_meta(key, bad);
            let e = config_from_meta(&file).unwrap_err().to_string();
            assert!(e.contains(key) && e.contains(bad), "{key}={bad}: {e}");
            // Loading weights that carry the malformed configuration fails
            // the same way (the old loader ignored the metadata).
            let e = field_from_tensor_file::<f64>(small_mlp(), &file)
                .unwrap_err()
                .to_string();
            assert!(e.contains(key) && e.contains(bad), "{key}={bad}: {e}");
        }
    }

    /// An option of the other architecture is refused naming the key and
    /// the value, unless it holds the value `config_to_meta` writes there.
    #[test]
    fn options_of_the_other_architecture_are_errors_naming_key_and_value() {
        let mlp = field_to_tensor_file(&Field::<f64>::new(small_mlp(), 1).unwrap());
        let cfc =
            field_to_tensor_file(&Field::<f64>::new(FieldConfig::new(FieldKind::Cfc), 1).unwrap());
        // What the writer puts there reads back.
        assert_eq!(config_from_meta(&mlp).unwrap(), small_mlp());
        for (file, key, bad) in [
            (&mlp, "activation", "gelu"),
            (&mlp, "backbone_units", "16"),
            (&mlp, "backbone_layers", "1"),
            (&cfc, "is_6dof", "true"),
        ] {
            let mut file = file.clone();
            file.set_meta(key, bad);
            let e = config_from_meta(&file).unwrap_err().to_string();
            assert!(e.contains(key) && e.contains(bad), "{key}={bad}: {e}");
        }
    }

    #[test]
    fn weights_of_another_configuration_are_refused_naming_the_key() {
        let field = Field::<f32>::new(small_mlp(), 1).unwrap();
        let mut file = field_to_tensor_file(&field);
        file.set_meta("is_6dof", true);
        let e = field_from_tensor_file::<f32>(small_mlp(), &file)
            .unwrap_err()
            .to_string();
        assert!(e.contains("is_6dof") && e.contains("true"), "{e}");
        // Without configuration metadata the weights load by name alone.
        file.metadata.clear();
        let back = field_from_tensor_file::<f32>(small_mlp(), &file).unwrap();
        assert_eq!(back.params(), field.params());
    }

    #[test]
    fn absent_keys_take_the_defaults_of_the_kind() {
        let mut file = TensorFile::new("case");
        file.set_meta("field", "cfc");
        assert_eq!(
            config_from_meta(&file).unwrap(),
            FieldConfig::new(FieldKind::Cfc)
        );
        let e = config_from_meta(&TensorFile::new("case"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("field") && e.contains("missing"), "{e}");
    }
}
