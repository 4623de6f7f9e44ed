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
//! and the value.

use crate::deform::{Activation, Field, FieldConfig, FieldKind, Variant};
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
    let d = FieldConfig::new(kind);
    let c = FieldConfig {
        kind,
        variant: optional(file, "variant", d.variant, name(Variant::parse))?,
        depth: optional(file, "depth", d.depth, number)?,
        width: optional(file, "width", d.width, number)?,
        activation: optional(file, "activation", d.activation, name(Activation::parse))?,
        backbone_units: optional(file, "backbone_units", d.backbone_units, number)?,
        backbone_layers: optional(file, "backbone_layers", d.backbone_layers, number)?,
        is_6dof: optional(file, "is_6dof", d.is_6dof, number)?,
    };
    Ok(c)
}

/// Write the keys [`config_from_meta`] reads.
pub fn config_to_meta(config: &FieldConfig, file: &mut TensorFile) {
    file.set_meta("field", config.kind);
    file.set_meta("variant", config.variant);
    file.set_meta("depth", config.depth);
    file.set_meta("width", config.width);
    file.set_meta("activation", config.activation);
    file.set_meta("backbone_units", config.backbone_units);
    file.set_meta("backbone_layers", config.backbone_layers);
    file.set_meta("is_6dof", config.is_6dof);
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
        let mut c = FieldConfig::new(FieldKind::Mlp);
        c.depth = 3;
        c.width = 4;
        c
    }

    #[test]
    fn round_trip_keeps_the_configuration_and_the_weights() {
        let mut cfc = FieldConfig::new(FieldKind::Cfc);
        cfc.depth = 2;
        cfc.width = 3;
        cfc.backbone_units = 5;
        cfc.backbone_layers = 1;
        cfc.variant = Variant::Real;
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
