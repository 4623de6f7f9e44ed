//! Named tensors with string metadata, stored as safetensors.
//!
//! This is the format of the oracle's case files, of deformation-field
//! weights (PyTorch state_dict names) and of optimizer checkpoints. Tensors
//! are kept in a `BTreeMap`, so files are written in a fixed order and the same
//! content always gives the same bytes.

use crate::error::{Error, Result};
use crate::math::{Precision, Real};
use ndarray::{ArrayD, ArrayViewD, IxDyn};
use safetensors::tensor::{Dtype, SafeTensors};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// A tensor: an n-dimensional array of one element type. Files store the
/// elements in row-major (C) order whatever the array's memory layout.
#[derive(Clone, Debug, PartialEq)]
pub enum Tensor {
    /// 32-bit floats (safetensors `F32`).
    F32(ArrayD<f32>),
    /// 64-bit floats (safetensors `F64`).
    F64(ArrayD<f64>),
    /// 32-bit signed integers (safetensors `I32`).
    I32(ArrayD<i32>),
    /// 64-bit signed integers (safetensors `I64`): no stage reads them;
    /// they are compared (gsplat's `isect_ids`, `camera_ids` and
    /// `gaussian_ids` are int64).
    I64(ArrayD<i64>),
}

/// `a`'s elements in row-major order, mapped by `f`, as a standard-layout
/// array of the same shape.
fn map_row_major<A: Copy, B>(a: &ArrayD<A>, f: impl Fn(A) -> B) -> ArrayD<B> {
    let values: Vec<B> = a.iter().map(|&x| f(x)).collect();
    ArrayD::from_shape_vec(a.raw_dim(), values).expect("one value per element of the shape")
}

/// An array's elements in row-major order (no copy for a standard-layout
/// array).
pub fn into_row_major<A: Clone>(a: ArrayD<A>) -> Vec<A> {
    if a.is_standard_layout() {
        a.into_raw_vec_and_offset().0
    } else {
        a.iter().cloned().collect()
    }
}

impl Tensor {
    /// A tensor of `shape` from row-major `values` of a real type, stored in
    /// that type's precision.
    ///
    /// # Panics
    /// If `values.len()` is not the product of `shape` (a caller's bug: every
    /// reader checks shapes before it builds a tensor).
    pub fn real<T: Real>(shape: Vec<usize>, values: &[T]) -> Self {
        fn shaped<A>(shape: Vec<usize>, v: Vec<A>) -> ArrayD<A> {
            let len = v.len();
            ArrayD::from_shape_vec(IxDyn(&shape), v)
                .unwrap_or_else(|_| panic!("{len} values do not fill a tensor of shape {shape:?}"))
        }
        match T::PRECISION {
            Precision::F32 => Tensor::F32(shaped(
                shape,
                values.iter().map(|v| v.to_f64() as f32).collect(),
            )),
            Precision::F64 => {
                Tensor::F64(shaped(shape, values.iter().map(|v| v.to_f64()).collect()))
            }
        }
    }

    /// A real tensor of the array's shape, stored in `T`'s precision.
    pub fn from_real<T: Real>(array: &ArrayD<T>) -> Self {
        match T::PRECISION {
            Precision::F32 => Tensor::F32(map_row_major(array, |v| v.to_f64() as f32)),
            Precision::F64 => Tensor::F64(map_row_major(array, |v| v.to_f64())),
        }
    }

    /// An I32 tensor of `shape` from row-major `values`.
    ///
    /// # Panics
    /// If `values.len()` is not the product of `shape`.
    pub fn i32(shape: Vec<usize>, values: Vec<i32>) -> Self {
        let len = values.len();
        Tensor::I32(
            ArrayD::from_shape_vec(IxDyn(&shape), values)
                .unwrap_or_else(|_| panic!("{len} values do not fill a tensor of shape {shape:?}")),
        )
    }

    /// The safetensors dtype name: `F32`, `F64`, `I32` or `I64`.
    pub fn dtype_name(&self) -> &'static str {
        match self {
            Tensor::F32(_) => "F32",
            Tensor::F64(_) => "F64",
            Tensor::I32(_) => "I32",
            Tensor::I64(_) => "I64",
        }
    }

    /// Whether the elements are integers (`I32`, `I64`).
    pub fn is_integer(&self) -> bool {
        matches!(self, Tensor::I32(_) | Tensor::I64(_))
    }

    /// The elements of an integer tensor widened to i64, in row-major
    /// order; `None` for a real one.
    pub fn to_i64(&self) -> Option<Vec<i64>> {
        match self {
            Tensor::I32(a) => Some(a.iter().map(|&x| i64::from(x)).collect()),
            Tensor::I64(a) => Some(a.iter().copied().collect()),
            Tensor::F32(_) | Tensor::F64(_) => None,
        }
    }

    /// The shape (empty for a scalar).
    pub fn shape(&self) -> &[usize] {
        match self {
            Tensor::F32(a) => a.shape(),
            Tensor::F64(a) => a.shape(),
            Tensor::I32(a) => a.shape(),
            Tensor::I64(a) => a.shape(),
        }
    }

    /// The number of elements.
    pub fn len(&self) -> usize {
        match self {
            Tensor::F32(a) => a.len(),
            Tensor::F64(a) => a.len(),
            Tensor::I32(a) => a.len(),
            Tensor::I64(a) => a.len(),
        }
    }

    /// Whether the tensor has no elements (some dimension is 0).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Every element as f64 (exact for F32, F64, I32, and for I64 within
    /// ±2^53; larger I64 values are rounded to nearest), as a
    /// standard-layout array of the same shape.
    pub fn to_f64(&self) -> ArrayD<f64> {
        match self {
            Tensor::F32(a) => map_row_major(a, f64::from),
            Tensor::F64(a) => map_row_major(a, |x| x),
            Tensor::I32(a) => map_row_major(a, f64::from),
            Tensor::I64(a) => map_row_major(a, |x| x as f64),
        }
    }

    /// Bytes per element in a file.
    fn element_size(&self) -> usize {
        match self {
            Tensor::F64(_) | Tensor::I64(_) => 8,
            Tensor::F32(_) | Tensor::I32(_) => 4,
        }
    }
}

/// A shape as messages and reports show it: `[2,3]`.
pub(crate) fn shape_str<D: std::fmt::Display>(s: &[D]) -> String {
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
    /// Where the file came from or will be written (named in errors).
    pub path: PathBuf,
    /// String metadata (safetensors `__metadata__`), sorted by key.
    pub metadata: BTreeMap<String, String>,
    /// The tensors, sorted by name.
    pub tensors: BTreeMap<String, Tensor>,
}

/// Refuses a header whose tensors' `data_offsets` reach past the file's
/// data before the `safetensors` crate reads it: the crate checks each
/// tensor's size with checked arithmetic but then adds the last offset to
/// the header's length unchecked, which overflows (a panic) for offsets near
/// `u64::MAX`. Headers that are not JSON objects of this shape are left to
/// the crate, which refuses them.
fn check_offsets(path: &Path, bytes: &[u8]) -> Result<()> {
    let bad = |why: String| Error::format(path, format!("not a valid safetensors file: {why}"));
    let Some(head) = bytes.first_chunk::<8>() else {
        return Err(bad(format!(
            "{} bytes, shorter than the 8-byte header length",
            bytes.len()
        )));
    };
    let n = u64::from_le_bytes(*head);
    let rest = (bytes.len() - 8) as u64;
    if n > rest {
        return Err(bad(format!(
            "header length {n} reaches past the file's {} bytes",
            bytes.len()
        )));
    }
    let data = rest - n;
    let Ok(header) = serde_json::from_slice::<serde_json::Map<String, serde_json::Value>>(
        &bytes[8..8 + n as usize],
    ) else {
        return Ok(());
    };
    // (The crate's own error for a number here names nothing.)
    if let Some(serde_json::Value::Object(m)) = header.get("__metadata__") {
        if let Some((k, v)) = m.iter().find(|(_, v)| !v.is_string()) {
            return Err(Error::field(
                path,
                format!("__metadata__.{k}"),
                format!("{v} is not a string (metadata values are strings, e.g. \"0.2\")"),
            ));
        }
    }
    let tensor_err = |name: &str, expected: String, found: String| Error::Tensor {
        context: path.display().to_string(),
        name: name.to_string(),
        expected,
        found,
    };
    // (name, dtype, shape, start, end) of each tensor whose entry has this shape.
    let mut entries = Vec::new();
    for (name, info) in header.iter().filter(|(k, _)| *k != "__metadata__") {
        let Some(offsets) = info.get("data_offsets").and_then(|o| o.as_array()) else {
            continue;
        };
        let offsets: Vec<u64> = offsets.iter().filter_map(|o| o.as_u64()).collect();
        if let Some(o) = offsets.iter().find(|&&o| o > data) {
            return Err(tensor_err(
                name,
                format!("data_offsets within the file's {data} bytes of data"),
                format!("offset {o}"),
            ));
        }
        let dtype = info.get("dtype").and_then(|d| d.as_str());
        let shape = info
            .get("shape")
            .and_then(|d| d.as_array())
            .map(|a| a.iter().map(|x| x.as_u64()).collect::<Option<Vec<u64>>>());
        if let (&[a, b], Some(dtype), Some(Some(shape))) = (&offsets[..], dtype, shape) {
            entries.push((name, dtype, shape, a, b));
        }
    }
    // The crate's own errors for what follows name no tensor
    // (`TensorInvalidInfo`) or the one after a gap (`InvalidOffset`).
    let complete = entries.len() == header.keys().filter(|k| *k != "__metadata__").count();
    entries.sort_by_key(|e| (e.3, e.4));
    let mut end = 0;
    for (name, dtype, shape, a, b) in entries {
        let offsets = format!("data_offsets [{a}, {b}]");
        if a != end || b < a {
            let before = if end == 0 {
                "the data begins at byte 0".to_string()
            } else {
                format!("the tensors before it end at byte {end}")
            };
            return Err(tensor_err(
                name,
                format!("offsets that cover the data in order without gaps or overlaps ({before})"),
                offsets,
            ));
        }
        end = b;
        let size = match dtype {
            "BOOL" | "U8" | "I8" | "F8_E5M2" | "F8_E4M3" => 1u64,
            "I16" | "U16" | "F16" | "BF16" => 2,
            "I32" | "U32" | "F32" => 4,
            "I64" | "U64" | "F64" => 8,
            _ => continue,
        };
        let bytes = shape
            .iter()
            .try_fold(size, |n, &d| n.checked_mul(d))
            .filter(|&n| usize::try_from(n).is_ok());
        if bytes != Some(b - a) {
            let want = match bytes {
                Some(n) => format!("{n} bytes"),
                None => "a size that overflows".to_string(),
            };
            return Err(tensor_err(
                name,
                format!("{want} for dtype {dtype} and shape {}", shape_str(&shape)),
                format!("{offsets}: {} bytes", b - a),
            ));
        }
    }
    if complete && end != data {
        return Err(bad(format!(
            "the tensors' data ends at byte {end}, but the file holds {data} bytes after the header"
        )));
    }
    Ok(())
}

impl TensorFile {
    /// An empty file for `path` (nothing is read or written).
    pub fn new(path: impl Into<PathBuf>) -> Self {
        TensorFile {
            path: path.into(),
            ..Default::default()
        }
    }

    fn ctx(&self) -> String {
        self.path.display().to_string()
    }

    /// Read a safetensors file. Accepts F32, F64, I32 and I64 tensors.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = super::read(path)?;
        Self::from_bytes(path, &bytes)
    }

    /// Parse safetensors `bytes` (F32, F64, I32 and I64 tensors); `path` names
    /// the file in errors.
    pub fn from_bytes(path: &Path, bytes: &[u8]) -> Result<Self> {
        check_offsets(path, bytes)?;
        let (_, meta) = SafeTensors::read_metadata(bytes)
            .map_err(|e| Error::format(path, format!("not a valid safetensors file: {e}")))?;
        let st = SafeTensors::deserialize(bytes)
            .map_err(|e| Error::format(path, format!("not a valid safetensors file: {e}")))?;
        let mut out = TensorFile::new(path);
        if let Some(m) = meta.metadata() {
            out.metadata = m.iter().map(|(k, v)| (k.clone(), v.clone())).collect();
        }
        for (name, view) in st.tensors() {
            let shape = IxDyn(view.shape());
            let raw = view.data();
            let bad_size = |_| Error::Tensor {
                context: path.display().to_string(),
                name: name.clone(),
                expected: format!(
                    "{} elements for shape {}",
                    view.shape().iter().product::<usize>(),
                    shape_str(view.shape())
                ),
                found: format!("{} bytes", raw.len()),
            };
            let tensor = match view.dtype() {
                Dtype::F32 => Tensor::F32(
                    ArrayD::from_shape_vec(
                        shape.clone(),
                        raw.chunks_exact(4)
                            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                            .collect(),
                    )
                    .map_err(bad_size)?,
                ),
                Dtype::F64 => Tensor::F64(
                    ArrayD::from_shape_vec(
                        shape.clone(),
                        raw.chunks_exact(8)
                            .map(|c| {
                                f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]])
                            })
                            .collect(),
                    )
                    .map_err(bad_size)?,
                ),
                Dtype::I32 => Tensor::I32(
                    ArrayD::from_shape_vec(
                        shape.clone(),
                        raw.chunks_exact(4)
                            .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                            .collect(),
                    )
                    .map_err(bad_size)?,
                ),
                Dtype::I64 => Tensor::I64(
                    ArrayD::from_shape_vec(
                        shape.clone(),
                        raw.chunks_exact(8)
                            .map(|c| {
                                i64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]])
                            })
                            .collect(),
                    )
                    .map_err(bad_size)?,
                ),
                other => {
                    return Err(Error::Tensor {
                        context: path.display().to_string(),
                        name,
                        expected: "dtype F32, F64, I32 or I64".into(),
                        found: format!("{other:?}"),
                    })
                }
            };
            out.tensors.insert(name, tensor);
        }
        Ok(out)
    }

    /// Serialise to safetensors bytes. Deterministic: the header lists
    /// `__metadata__` first with its keys sorted, then the tensors in data
    /// order (I64, F64, F32, I32, then by name, as the `safetensors`
    /// crate lays them out); the header is padded with spaces to a multiple
    /// of 8 bytes. (The `safetensors` crate's own writer emits metadata in
    /// hash-map order, which changes from run to run.)
    pub fn to_bytes(&self) -> Result<Vec<u8>> {
        // (The header's key for the metadata: a tensor of that name would
        // make a file no reader accepts.)
        if self.tensors.contains_key("__metadata__") {
            return Err(Error::invalid(
                format!("{}: tensor name", self.ctx()),
                "`__metadata__` is the safetensors header's metadata key, not a tensor name",
            ));
        }
        fn align(t: &Tensor) -> u8 {
            match t {
                Tensor::I64(_) => 0,
                Tensor::F64(_) => 1,
                Tensor::F32(_) => 2,
                Tensor::I32(_) => 3,
            }
        }
        let mut order: Vec<(&String, &Tensor)> = self.tensors.iter().collect();
        order.sort_by(|(ln, lt), (rn, rt)| align(lt).cmp(&align(rt)).then(ln.cmp(rn)));
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
            let bytes = t.len() * t.element_size();
            if i > 0 || !self.metadata.is_empty() {
                header.push(',');
            }
            header.push_str(&format!(
                "{}:{{\"dtype\":\"{}\",\"shape\":[{}],\"data_offsets\":[{},{}]}}",
                json(name),
                t.dtype_name(),
                t.shape()
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
        // Elements in row-major order (`iter` walks an array logically,
        // whatever its memory layout).
        for (_, t) in order {
            match t {
                Tensor::F32(a) => a
                    .iter()
                    .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
                Tensor::F64(a) => a
                    .iter()
                    .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
                Tensor::I32(a) => a
                    .iter()
                    .for_each(|x| out.extend_from_slice(&x.to_le_bytes())),
                Tensor::I64(a) => a
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

    /// Set metadata `key` to `value`'s text.
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
        fn first_bad<A: Copy + Into<f64>>(a: &ArrayD<A>) -> Option<(usize, f64)> {
            a.iter()
                .map(|&x| x.into())
                .enumerate()
                .find(|(_, x): &(usize, f64)| !x.is_finite())
        }
        for (name, t) in &self.tensors {
            let bad = match t {
                Tensor::F32(a) => first_bad(a),
                Tensor::F64(a) => first_bad(a),
                Tensor::I32(_) | Tensor::I64(_) => None,
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

    /// Whether the file holds tensor `name`.
    pub fn contains(&self, name: &str) -> bool {
        self.tensors.contains_key(name)
    }

    /// Tensor `name`, or an error naming it.
    pub fn get(&self, name: &str) -> Result<&Tensor> {
        self.tensors.get(name).ok_or_else(|| Error::MissingTensor {
            context: self.ctx(),
            name: name.to_string(),
        })
    }

    /// The shape of tensor `name`.
    pub fn shape(&self, name: &str) -> Result<&[usize]> {
        self.get(name).map(Tensor::shape)
    }

    /// The precision of the floating-point tensors: all must agree.
    pub fn precision(&self) -> Result<Precision> {
        let mut found: Option<(Precision, &str)> = None;
        for (name, t) in &self.tensors {
            let p = match t {
                Tensor::F32(_) => Precision::F32,
                Tensor::F64(_) => Precision::F64,
                Tensor::I32(_) | Tensor::I64(_) => continue,
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
                        found: t.dtype_name().into(),
                    })
                }
                _ => {}
            }
        }
        found
            .map(|(p, _)| p)
            .ok_or_else(|| Error::format(&self.path, "no floating-point tensors"))
    }

    /// Real tensor `name` as an array of element type `T` (row-major, its
    /// own shape). Its dtype must be `T`'s.
    pub fn real_array<T: Real>(&self, name: &str) -> Result<ArrayD<T>> {
        match (self.get(name)?, T::PRECISION) {
            (Tensor::F32(a), Precision::F32) => Ok(map_row_major(a, T::from_f32)),
            (Tensor::F64(a), Precision::F64) => Ok(map_row_major(a, T::from_f64)),
            (t, p) => Err(Error::Tensor {
                context: self.ctx(),
                name: name.into(),
                expected: format!("dtype {}", if p == Precision::F32 { "F32" } else { "F64" }),
                found: format!("dtype {}", t.dtype_name()),
            }),
        }
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

    /// Real tensor `name` of element type `T`, whose shape must equal
    /// `expected`, as its row-major elements.
    pub fn get_real<T: Real>(&self, name: &str, expected: &[usize]) -> Result<Vec<T>> {
        let array = self.real_array::<T>(name)?;
        self.expect_shape(name, expected)?;
        Ok(into_row_major(array))
    }

    /// I32 tensor `name` as a view of its array (any shape).
    pub fn i32_array(&self, name: &str) -> Result<ArrayViewD<'_, i32>> {
        match self.get(name)? {
            Tensor::I32(a) => Ok(a.view()),
            t => Err(Error::Tensor {
                context: self.ctx(),
                name: name.into(),
                expected: "dtype I32".into(),
                found: format!("dtype {}", t.dtype_name()),
            }),
        }
    }

    /// Insert (or replace) tensor `name`.
    pub fn insert(&mut self, name: &str, tensor: Tensor) {
        self.tensors.insert(name.to_string(), tensor);
    }

    /// Insert a real tensor of `shape` from row-major `values`, stored in
    /// `T`'s precision.
    ///
    /// # Panics
    /// If `values.len()` is not the product of `shape`.
    pub fn insert_real<T: Real>(&mut self, name: &str, shape: Vec<usize>, values: &[T]) {
        self.insert(name, Tensor::real(shape, values));
    }

    /// Insert an I32 tensor of `shape` from row-major `values`.
    ///
    /// # Panics
    /// If `values.len()` is not the product of `shape`.
    pub fn insert_i32(&mut self, name: &str, shape: Vec<usize>, values: Vec<i32>) {
        self.insert(name, Tensor::i32(shape, values));
    }

    /// Fail if the file holds tensors outside `known` (catches typos in
    /// hand-written case files and state dicts).
    pub fn reject_unknown<'a>(&self, known: impl IntoIterator<Item = &'a str>) -> Result<()> {
        let order: Vec<&str> = known.into_iter().collect();
        let known: BTreeSet<&str> = order.iter().copied().collect();
        let extra: Vec<&str> = self
            .tensors
            .keys()
            .map(|s| s.as_str())
            .filter(|k| !known.contains(k))
            .collect();
        if extra.is_empty() {
            Ok(())
        } else {
            const SHOWN: usize = 40;
            let mut shown = order[..order.len().min(SHOWN)].join(", ");
            if order.len() > SHOWN {
                shown += &format!(" and {} more", order.len() - SHOWN);
            }
            Err(Error::UnexpectedTensors {
                context: self.ctx(),
                names: extra.join(", "),
                known: shown,
            })
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_tensors_are_named_with_those_the_file_may_hold() {
        let mut f = TensorFile::new("case.safetensors");
        f.insert_i32("imgae", vec![1], vec![0]);
        let err = f.reject_unknown(["image", "gt"]).unwrap_err().to_string();
        assert!(
            err.contains("unexpected tensor(s): imgae (the tensors it may hold: image, gt)"),
            "{err}"
        );
        let many: Vec<String> = (0..45).map(|i| format!("w{i}")).collect();
        let err = f
            .reject_unknown(many.iter().map(String::as_str))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("w0, w1,") && err.contains("w39 and 5 more)"),
            "{err}"
        );
        assert!(!err.contains("w40"), "{err}");
    }

    #[test]
    fn round_trip_preserves_bits_and_metadata() {
        let mut f = TensorFile::new("mem");
        f.set_meta("stage", "rasterize");
        f.insert_real::<f32>("a", vec![2, 2], &[1.0, -0.0, f32::MIN_POSITIVE, 3.5]);
        f.insert_real::<f64>("b", vec![1], &[0.1]);
        f.insert_i32("c", vec![3], vec![1, -2, 3]);
        f.insert(
            "d",
            Tensor::I64(
                ArrayD::from_shape_vec(IxDyn(&[2]), vec![i64::MIN, (1 << 60) + 1]).unwrap(),
            ),
        );
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
        let big = [i64::MAX, -3];
        f.insert(
            "t",
            Tensor::I64(ArrayD::from_shape_vec(IxDyn(&[2]), big.to_vec()).unwrap()),
        );
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
            (
                "t".into(),
                Dtype::I64,
                vec![2],
                big.iter().flat_map(|x| x.to_le_bytes()).collect(),
            ),
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
        assert_eq!(st.names().len(), 5);
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
                r#"{"__metadata__":{"a":"x\"y","b":"2","stage":"rasterize","z":"é"},"t":"#
            ),
            "{header}"
        );
        // Same content inserted in another order: same bytes.
        let mut g = TensorFile::new("other");
        g.insert_real::<f32>("e", vec![0, 3], &[]);
        g.insert_i32("u", vec![], vec![7]);
        g.insert_real::<f64>("v", vec![1, 3], &[0.5, -1.0, 3.0]);
        g.insert_real::<f32>("w", vec![2], &[1.0, 2.0]);
        g.insert(
            "t",
            Tensor::I64(ArrayD::from_shape_vec(IxDyn(&[2]), big.to_vec()).unwrap()),
        );
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
    fn arrays_keep_their_shapes_and_any_layout_is_written_row_major() {
        // A transposed (column-major) array holds the same logical tensor as
        // its row-major copy: the bytes are the same.
        let a = ndarray::array![[1.0f32, 2.0, 3.0], [4.0, 5.0, 6.0]].into_dyn();
        let mut t = TensorFile::new("mem");
        t.insert("a", Tensor::F32(a.t().to_owned()));
        assert!(!a.t().to_owned().is_standard_layout());
        let mut r = TensorFile::new("mem");
        r.insert_real::<f32>("a", vec![3, 2], &[1.0, 4.0, 2.0, 5.0, 3.0, 6.0]);
        assert_eq!(t.to_bytes().unwrap(), r.to_bytes().unwrap());
        let back = TensorFile::from_bytes(Path::new("mem"), &t.to_bytes().unwrap()).unwrap();
        let x = back.real_array::<f64>("a");
        assert!(x.unwrap_err().to_string().contains("dtype F64"));
        let x = back.real_array::<f32>("a").unwrap();
        assert_eq!(x.shape(), &[3, 2]);
        assert_eq!(x, a.t());
        assert_eq!(
            back.get_real::<f32>("a", &[3, 2]).unwrap(),
            [1.0, 4.0, 2.0, 5.0, 3.0, 6.0]
        );
        r.insert_i32("ids", vec![2, 1], vec![7, -1]);
        let ids = r.i32_array("ids").unwrap();
        assert_eq!(ids.shape(), &[2, 1]);
        assert_eq!(ids.iter().copied().collect::<Vec<_>>(), [7, -1]);
        assert!(r.i32_array("a").is_err());
        assert_eq!(r.get("ids").unwrap().to_f64().iter().sum::<f64>(), 6.0);
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

    #[test]
    fn offsets_past_the_data_are_refused_before_the_crate_adds_them() {
        // An F64 tensor of 2^61 - 1 elements whose byte size, 2^64 - 8, is
        // consistent with its offsets: the crate's size check passes it and
        // its sum of the offset and the header's length overflows.
        let header = br#"{"t":{"dtype":"F64","shape":[2305843009213693951],"data_offsets":[0,18446744073709551608]}}"#;
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend_from_slice(header);
        let err = TensorFile::from_bytes(Path::new("x.safetensors"), &bytes)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("x.safetensors") && err.contains("18446744073709551608"),
            "{err}"
        );
        // Offsets within the data pass the check and the crate reads them.
        let mut f = TensorFile::new("x");
        f.insert_real::<f32>("a", vec![2], &[1.0, 2.0]);
        assert!(check_offsets(Path::new("x"), &f.to_bytes().unwrap()).is_ok());
        // A metadata value written as a JSON number is named.
        let header = br#"{"__metadata__":{"lambda_dssim":0.2}}"#;
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend_from_slice(header);
        let err = TensorFile::from_bytes(Path::new("m.safetensors"), &bytes)
            .unwrap_err()
            .to_string();
        assert!(err.contains("lambda_dssim") && err.contains("0.2"), "{err}");
    }

    #[test]
    fn a_tensor_named_like_the_metadata_key_is_not_written() {
        let mut f = TensorFile::new("m.safetensors");
        f.insert_real::<f32>("__metadata__", vec![1], &[0.0]);
        let err = f.to_bytes().unwrap_err().to_string();
        assert!(
            err.contains("__metadata__") && err.contains("m.safetensors"),
            "{err}"
        );
    }
}
