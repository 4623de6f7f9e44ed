//! Named tensors with string metadata, stored as safetensors.
//!
//! This is the format of the oracle's case files, of deformation-field
//! weights (PyTorch state_dict names) and of optimizer checkpoints. Tensors
//! are kept in a `BTreeMap`, so files are written in a fixed order and the same
//! content always gives the same bytes.

use crate::error::{Error, Result};
use crate::math::Real;
use safetensors::tensor::{Dtype, SafeTensors};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Element storage of a tensor.
#[derive(Clone, Debug, PartialEq)]
pub enum TensorData {
    /// 32-bit floats.
    F32(Vec<f32>),
    /// 64-bit floats.
    F64(Vec<f64>),
    /// 32-bit signed integers.
    I32(Vec<i32>),
}

impl TensorData {
    /// The safetensors dtype name: `F32`, `F64` or `I32`.
    pub fn dtype_name(&self) -> &'static str {
        match self {
            TensorData::F32(_) => "F32",
            TensorData::F64(_) => "F64",
            TensorData::I32(_) => "I32",
        }
    }
    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            TensorData::F32(v) => v.len(),
            TensorData::F64(v) => v.len(),
            TensorData::I32(v) => v.len(),
        }
    }
    /// True when there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Every element widened to f64 (exact for all three types).
    pub fn to_f64(&self) -> Vec<f64> {
        match self {
            TensorData::F32(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::F64(v) => v.clone(),
            TensorData::I32(v) => v.iter().map(|&x| x as f64).collect(),
        }
    }
}

/// A tensor: row-major data and its shape.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// Size of each dimension, outermost first.
    pub shape: Vec<usize>,
    /// The elements, row-major.
    pub data: TensorData,
}

impl Tensor {
    /// An F32 or F64 tensor (by `T`'s precision) holding `values`.
    pub fn real<T: Real>(shape: Vec<usize>, values: &[T]) -> Self {
        debug_assert_eq!(shape.iter().product::<usize>(), values.len());
        let data = match T::PRECISION {
            crate::math::Precision::F32 => {
                TensorData::F32(values.iter().map(|v| v.to_f64() as f32).collect())
            }
            crate::math::Precision::F64 => {
                TensorData::F64(values.iter().map(|v| v.to_f64()).collect())
            }
        };
        Tensor { shape, data }
    }
    /// An I32 tensor holding `values`.
    pub fn i32(shape: Vec<usize>, values: Vec<i32>) -> Self {
        Tensor {
            shape,
            data: TensorData::I32(values),
        }
    }
}

fn shape_str(s: &[usize]) -> String {
    format!(
        "[{}]",
        s.iter()
            .map(|d| d.to_string())
            .collect::<Vec<_>>()
            .join(",")
    )
}

/// A set of named tensors plus string metadata, tied to the path it came
/// from (or will be written to) for error messages.
#[derive(Clone, Debug, Default)]
pub struct TensorFile {
    /// The file it came from or will be written to (named in errors).
    pub path: PathBuf,
    /// The safetensors `__metadata__` strings.
    pub metadata: BTreeMap<String, String>,
    /// The tensors by name.
    pub tensors: BTreeMap<String, Tensor>,
}

impl TensorFile {
    /// An empty file for `path`.
    pub fn new(path: impl Into<PathBuf>) -> Self {
        TensorFile {
            path: path.into(),
            ..Default::default()
        }
    }

    fn ctx(&self) -> String {
        self.path.display().to_string()
    }

    /// Read a safetensors file. Accepts F32, F64 and I32 tensors.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = super::read(path)?;
        Self::from_bytes(path, &bytes)
    }

    /// Parse safetensors `bytes` (`path` names them in errors).
    pub fn from_bytes(path: &Path, bytes: &[u8]) -> Result<Self> {
        let (_, meta) = SafeTensors::read_metadata(bytes)
            .map_err(|e| Error::format(path, format!("not a valid safetensors file: {e}")))?;
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| Error::format(path, format!("not a valid safetensors file: {e}")))?;
        let mut out = TensorFile::new(path);
        if let Some(m) = meta.metadata() {
            out.metadata = m.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        }
        for (name, view) in st.tensors() {
            let shape = view.shape().to_vec();
            let raw = view.data();
            let data = match view.dtype() {
                Dtype::F32 => TensorData::F32(
                    raw.chunks_exact(4)
                        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
                        .collect(),
                ),
                Dtype::F64 => TensorData::F64(
                    raw.chunks_exact(8)
                        .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                        .collect(),
                ),
                Dtype::I32 => TensorData::I32(
                    raw.chunks_exact(4)
                        .map(|c| i32::from_le_bytes(c.try_into().unwrap()))
                        .collect(),
                ),
                other => {
                    return Err(Error::Tensor {
                        context: path.display().to_string(),
                        name,
                        expected: "dtype F32, F64 or I32".into(),
                        found: format!("{other:?}"),
                    })
                }
            };
            out.tensors.insert(name, Tensor { shape, data });
        }
        Ok(out)
    }

    /// Serialise to safetensors bytes. Deterministic: the header lists
    /// `__metadata__` first with its keys sorted, then the tensors in data
    /// order (F64 before F32 and I32, then by name, as the `safetensors`
    /// crate lays them out); the header is padded with spaces to a multiple
    /// of 8 bytes. (The `safetensors` crate's own writer emits metadata in
    /// hash-map order, which changes from run to run.)
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        fn align(d: &TensorData) -> u8 {
            match d {
                TensorData::F64(_) => 0,
                TensorData::F32(_) => 1,
                TensorData::I32(_) => 2,
            }
        }
        let mut order: Vec<(&String, &Tensor)> = self.tensors.iter().collect();
        order.sort_by(|(ln, lt), (rn, rt)| align(&lt.data).cmp(&align(&rt.data)).then(ln.cmp(rn)));
        let json = |s: &str| serde_json::to_string(s).expect("a string always serialises");
        let mut header = String::from("{");
        if !self.metadata.is_empty() {
            header.push_str("\"__metadata__\":{");
            for (i, (k, v)) in self.metadata.iter().enumerate() {
                if i > 0 {
                    header.push(',');
                }
                header.push_str(&format!("{}:{}", json(k), json(v)));
            }
            header.push('}');
        }
        let mut offset = 0usize;
        for (i, (name, t)) in order.iter().enumerate() {
            let elems: usize = t.shape.iter().product();
            if elems != t.data.len() {
                return Err(Error::Tensor {
                    context: self.ctx(),
                    name: name.to_string(),
                    expected: format!("{elems} elements for shape {}", shape_str(&t.shape)),
                    found: format!("{} elements", t.data.len()),
                });
            }
            let bytes = elems
                * match t.data {
                    TensorData::F64(_) => 8,
                    _ => 4,
                };
            if i > 0 || !self.metadata.is_empty() {
                header.push(',');
            }
            header.push_str(&format!(
                "{}:{{\"dtype\":\"{}\",\"shape\":[{}],\"data_offsets\":[{},{}]}}",
                json(name),
                t.data.dtype_name(),
                t.shape
                    .iter()
                    .map(|d| d.to_string())
                    .collect::<Vec<_>>()
                    .join(","),
                offset,
                offset + bytes
            ));
            offset += bytes;
        }
        header.push('}');
        let mut header = header.into_bytes();
        header.resize(header.len().div_ceil(8) * 8, b' ');
        let mut out = Vec::with_capacity(8 + header.len() + offset);
        out.extend_from_slice(&(header.len() as u64).to_le_bytes());
        out.extend_from_slice(&header);
        for (_, t) in order {
            match &t.data {
                TensorData::F32(v) => v
                    .iter()
                    .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
                TensorData::F64(v) => v
                    .iter()
                    .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
                TensorData::I32(v) => v
                    .iter()
                    .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
            }
        }
        Ok(out)
    }

    /// Write atomically to `path`.
    pub fn save(&self, path: &Path) -> Result<()> {
        super::write_atomic(path, &self.to_bytes()?)
    }

    // ---- metadata ----

    /// Set a metadata string.
    pub fn set_meta(&mut self, key: &str, value: impl ToString) {
        self.metadata.insert(key.to_string(), value.to_string());
    }

    /// A required metadata string.
    pub fn meta(&self, key: &str) -> Result<&str> {
        self.metadata
            .get(key)
            .map(|s| s.as_str())
            .ok_or_else(|| Error::field(&self.path, format!("__metadata__.{key}"), "missing"))
    }

    /// A required metadata value parsed with `FromStr`.
    pub fn meta_parse<F: std::str::FromStr>(&self, key: &str) -> Result<F> {
        let s = self.meta(key)?;
        s.trim().parse::<F>().map_err(|_| {
            Error::field(
                &self.path,
                format!("__metadata__.{key}"),
                format!("cannot parse {s:?} as {}", std::any::type_name::<F>()),
            )
        })
    }

    /// An optional metadata value parsed with `FromStr`, or `default`.
    pub fn meta_or<F: std::str::FromStr>(&self, key: &str, default: F) -> Result<F> {
        if self.metadata.contains_key(key) {
            self.meta_parse(key)
        } else {
            Ok(default)
        }
    }

    /// A required finite metadata number (`NaN` and `±inf` are refused,
    /// naming the key).
    pub fn meta_finite(&self, key: &str) -> Result<f64> {
        let v: f64 = self.meta_parse(key)?;
        if !v.is_finite() {
            return Err(Error::field(
                &self.path,
                format!("__metadata__.{key}"),
                format!("{v} is not finite"),
            ));
        }
        Ok(v)
    }

    /// [`meta_finite`](Self::meta_finite) with a default for an absent key.
    pub fn meta_finite_or(&self, key: &str, default: f64) -> Result<f64> {
        if self.metadata.contains_key(key) {
            self.meta_finite(key)
        } else {
            Ok(default)
        }
    }

    // ---- tensors ----

    /// Fail on the first `NaN` or `±inf` element of a floating-point tensor
    /// (tensors in name order, elements in row-major order), naming the
    /// tensor, the flat index and the value.
    pub fn check_finite(&self) -> Result<()> {
        for (name, t) in &self.tensors {
            let bad = match &t.data {
                TensorData::F32(v) => v
                    .iter()
                    .position(|x| !x.is_finite())
                    .map(|i| (i, v[i] as f64)),
                TensorData::F64(v) => v.iter().position(|x| !x.is_finite()).map(|i| (i, v[i])),
                TensorData::I32(_) => None,
            };
            if let Some((i, x)) = bad {
                return Err(Error::Tensor {
                    context: self.ctx(),
                    name: name.clone(),
                    expected: "finite values".into(),
                    found: format!("{x} at flat index {i}"),
                });
            }
        }
        Ok(())
    }

    /// True when a tensor `name` is present.
    pub fn contains(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }

    /// The shape of tensor `name` (an error if missing).
    pub fn shape(&self, name: &str) -> Result<&[usize]> {
        self.tensors
            .get(name)
            .map(|t| t.shape.as_slice())
            .ok_or_else(|| Error::MissingTensor {
                context: self.ctx(),
                name: name.to_string(),
            })
    }

    /// The precision of the floating-point tensors: all must agree.
    pub fn precision(&self) -> Result<crate::math::Precision> {
        use crate::math::Precision;
        let mut found: Option<(Precision, &str)> = None;
        for (name, t) in &self.tensors {
            let p = match t.data {
                TensorData::F32(_) => Precision::F32,
                TensorData::F64(_) => Precision::F64,
                TensorData::I32(_) => continue,
            };
            match found {
                None => found = Some((p, name)),
                Some((q, first)) if q != p => {
                    return Err(Error::Tensor {
                        context: self.ctx(),
                        name: name.clone(),
                        expected: format!(
                            "dtype {} like `{first}`",
                            if q == Precision::F32 { "F32" } else { "F64" }
                        ),
                        found: t.data.dtype_name().into(),
                    })
                }
                _ => {}
            }
        }
        found
            .map(|(p, _)| p)
            .ok_or_else(|| Error::format(&self.path, "no floating-point tensors"))
    }

    /// A real tensor of element type `T` and any shape.
    pub fn get_real_any<T: Real>(&self, name: &str) -> Result<(Vec<usize>, Vec<T>)> {
        let t = self.tensors.get(name).ok_or_else(|| Error::MissingTensor {
            context: self.ctx(),
            name: name.to_string(),
        })?;
        let want = match T::PRECISION {
            crate::math::Precision::F32 => "F32",
            crate::math::Precision::F64 => "F64",
        };
        let v: Vec<T> = match (&t.data, T::PRECISION) {
            (TensorData::F32(v), crate::math::Precision::F32) => {
                v.iter().map(|&x| T::from_f32(x)).collect()
            }
            (TensorData::F64(v), crate::math::Precision::F64) => {
                v.iter().map(|&x| T::from_f64(x)).collect()
            }
            (d, _) => {
                return Err(Error::Tensor {
                    context: self.ctx(),
                    name: name.into(),
                    expected: format!("dtype {want}"),
                    found: format!("dtype {}", d.dtype_name()),
                })
            }
        };
        Ok((t.shape.clone(), v))
    }

    /// Fail unless tensor `name` is present with shape `expected` (reads
    /// no data: a check before allocating for it).
    pub fn expect_shape(&self, name: &str, expected: &[usize]) -> Result<()> {
        let shape = self.shape(name)?;
        if shape != expected {
            return Err(Error::Tensor {
                context: self.ctx(),
                name: name.into(),
                expected: format!("shape {}", shape_str(expected)),
                found: format!("shape {}", shape_str(shape)),
            });
        }
        Ok(())
    }

    /// A real tensor of element type `T` whose shape must equal `expected`.
    pub fn get_real<T: Real>(&self, name: &str, expected: &[usize]) -> Result<Vec<T>> {
        let (shape, v) = self.get_real_any::<T>(name)?;
        if shape != expected {
            return Err(Error::Tensor {
                context: self.ctx(),
                name: name.into(),
                expected: format!("shape {}", shape_str(expected)),
                found: format!("shape {}", shape_str(&shape)),
            });
        }
        Ok(v)
    }

    /// An I32 tensor of any shape.
    pub fn get_i32(&self, name: &str) -> Result<(Vec<usize>, Vec<i32>)> {
        let t = self.tensors.get(name).ok_or_else(|| Error::MissingTensor {
            context: self.ctx(),
            name: name.to_string(),
        })?;
        match &t.data {
            TensorData::I32(v) => Ok((t.shape.clone(), v.clone())),
            d => Err(Error::Tensor {
                context: self.ctx(),
                name: name.into(),
                expected: "dtype I32".into(),
                found: format!("dtype {}", d.dtype_name()),
            }),
        }
    }

    /// Insert (or replace) a float tensor ([`Tensor::real`]).
    pub fn insert_real<T: Real>(&mut self, name: &str, shape: Vec<usize>, values: &[T]) {
        self.tensors
            .insert(name.to_string(), Tensor::real(shape, values));
    }

    /// Insert (or replace) an I32 tensor.
    pub fn insert_i32(&mut self, name: &str, shape: Vec<usize>, values: Vec<i32>) {
        self.tensors
            .insert(name.to_string(), Tensor::i32(shape, values));
    }

    /// Fail if the file holds tensors outside `known` (catches typos in
    /// hand-written case files and state dicts).
    pub fn reject_unknown<'a>(&self, known: impl IntoIterator<Item = &'a str>) -> Result<()> {
        let known: BTreeSet<&str> = known.into_iter().collect();
        let extra: Vec<&str> = self
            .tensors
            .keys()
            .map(|s| s.as_str())
            .filter(|k| !known.contains(k))
            .collect();
        if extra.is_empty() {
            Ok(())
        } else {
            Err(Error::UnexpectedTensors {
                context: self.ctx(),
                names: extra.join(", "),
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_preserves_bits_and_metadata() {
        let mut f = TensorFile::new("mem");
        f.set_meta("stage", "rasterize");
        f.insert_real::<f32>("a", vec![2, 2], &[1.0, -0.0, f32::MIN_POSITIVE, 3.5]);
        f.insert_real::<f64>("b", vec![1], &[0.1]);
        f.insert_i32("c", vec![3], vec![1, -2, 3]);
        let bytes = f.to_bytes().unwrap();
        let g = TensorFile::from_bytes(Path::new("mem"), &bytes).unwrap();
        assert_eq!(g.metadata, f.metadata);
        assert_eq!(g.tensors, f.tensors);
        assert_eq!(g.to_bytes().unwrap(), bytes);
    }

    #[test]
    fn bytes_match_the_safetensors_crate_and_do_not_depend_on_insertion_order() {
        let mut f = TensorFile::new("mem");
        for (k, v) in [
            ("stage", "rasterize"),
            ("b", "2"),
            ("a", "x\"y"),
            ("z", "é"),
        ] {
            f.set_meta(k, v);
        }
        f.insert_real::<f32>("w", vec![2], &[1.0, 2.0]);
        f.insert_real::<f64>("v", vec![1, 3], &[0.5, -1.0, 3.0]);
        f.insert_i32("u", vec![], vec![7]);
        f.insert_real::<f32>("e", vec![0, 3], &[]);
        let bytes = f.to_bytes().unwrap();
        // The reference writer lays out the same data section.
        let raw: Vec<(String, Dtype, Vec<usize>, Vec<u8>)> = vec![
            (
                "w".into(),
                Dtype::F32,
                vec![2],
                [1.0f32, 2.0].iter().flat_map(|x| x.to_le_bytes()).collect(),
            ),
            (
                "v".into(),
                Dtype::F64,
                vec![1, 3],
                [0.5f64, -1.0, 3.0]
                    .iter()
                    .flat_map(|x| x.to_le_bytes())
                    .collect(),
            ),
            ("u".into(), Dtype::I32, vec![], 7i32.to_le_bytes().to_vec()),
            ("e".into(), Dtype::F32, vec![0, 3], vec![]),
        ];
        let views = raw.iter().map(|(n, d, s, b)| {
            (
                n.clone(),
                safetensors::tensor::TensorView::new(*d, s.clone(), b).unwrap(),
            )
        });
        let theirs = safetensors::serialize(views, &None).unwrap();
        let their_n = u64::from_le_bytes(theirs[..8].try_into().unwrap()) as usize;
        let st = SafeTensors::deserialize(&bytes).unwrap();
        assert_eq!(st.names().len(), 4);
        let (n, meta) = SafeTensors::read_metadata(&bytes).unwrap();
        assert_eq!(n % 8, 0);
        let m = meta.metadata().clone().unwrap();
        assert_eq!(m.len(), 4);
        assert_eq!(m["a"], "x\"y");
        assert_eq!(m["z"], "é");
        assert_eq!(&bytes[8 + n..], &theirs[8 + their_n..]);
        let header = std::str::from_utf8(&bytes[8..8 + n]).unwrap();
        assert!(
            header.starts_with(
                r#"{"__metadata__":{"a":"x\"y","b":"2","stage":"rasterize","z":"é"},"v":"#
            ),
            "{header}"
        );
        // Same content inserted in another order: same bytes.
        let mut g = TensorFile::new("other");
        g.insert_real::<f32>("e", vec![0, 3], &[]);
        g.insert_i32("u", vec![], vec![7]);
        g.insert_real::<f64>("v", vec![1, 3], &[0.5, -1.0, 3.0]);
        g.insert_real::<f32>("w", vec![2], &[1.0, 2.0]);
        for (k, v) in [
            ("z", "é"),
            ("a", "x\"y"),
            ("stage", "rasterize"),
            ("b", "2"),
        ] {
            g.set_meta(k, v);
        }
        assert_eq!(g.to_bytes().unwrap(), bytes);
        let back = TensorFile::from_bytes(Path::new("mem"), &bytes).unwrap();
        assert_eq!(back.tensors, f.tensors);
        assert_eq!(back.metadata, f.metadata);
    }

    #[test]
    fn wrong_shape_and_dtype_are_named() {
        let mut f = TensorFile::new("case.safetensors");
        f.insert_real::<f32>("means3D", vec![4, 2], &[0.0; 8]);
        let e = f
            .get_real::<f32>("means3D", &[4, 3])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("means3D") && e.contains("[4,3]") && e.contains("[4,2]"),
            "{e}"
        );
        let e = f
            .get_real::<f64>("means3D", &[4, 2])
            .unwrap_err()
            .to_string();
        assert!(e.contains("F64") && e.contains("F32"), "{e}");
        let e = f
            .get_real::<f32>("scales", &[4, 3])
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing tensor `scales`"), "{e}");
    }

    #[test]
    fn truncated_file_is_an_error_not_a_panic() {
        let mut f = TensorFile::new("x");
        f.insert_real::<f64>("a", vec![8], &[1.0; 8]);
        let bytes = f.to_bytes().unwrap();
        for cut in [0, 4, 8, 20, bytes.len() - 1] {
            assert!(TensorFile::from_bytes(Path::new("x"), &bytes[..cut]).is_err());
        }
    }
}
