//! Reading PyTorch `.pth` files (`torch.save` of a `state_dict`) without
//! Python: the subset of the format that holds named tensors.
//!
//! `torch.save` writes one of two containers:
//!
//! - **zip** (PyTorch 1.6 and later): `NAME/data.pkl` (the pickled object)
//!   and one entry `NAME/data/KEY` per storage, stored uncompressed.
//! - **legacy** (earlier; still written with
//!   `_use_new_zipfile_serialization=False`, and the format of torchvision's
//!   2017 model files and of the `lpips` package's weights): five pickles in a
//!   row (magic number, protocol version, system info, the object, the list of
//!   storage keys), then each storage as a little-endian `u64` element count
//!   followed by its raw bytes.
//!
//! The pickled object is read by a small pickle interpreter that builds plain
//! values and **never runs anything**: a global (`torch._utils._rebuild_tensor_v2`,
//! `collections.OrderedDict`, …) is only a name. It understands the opcodes
//! of pickle protocols 2 to 4 that `torch.save` and Python 2 era files use,
//! tensor rebuild calls (`_rebuild_tensor` and `_rebuild_tensor_v2`),
//! persistent storage ids (with the legacy view metadata) and
//! `OrderedDict` in both of its pickled forms. Anything else is an error that
//! names the file and the byte offset.
//!
//! Tensor data is read on request ([`PthFile::read_f64`], [`PthFile::read_f32`])
//! from `float32`, `float64`, `float16` or `bfloat16` storages, little-endian.
//!
//! A crafted file cannot make the reader panic, exhaust memory or run for long:
//! one pickle may be at most [`MAX_PICKLE_BYTES`] long, create at most
//! [`MAX_VALUES`] values and [`MAX_VALUE_BYTES`] bytes of text (the copies
//! that `DUP` and the memo make count as created) and nest them at most
//! [`MAX_DEPTH`] deep; dictionary keys are found through a hash index, so
//! building a dictionary is linear; tensor offsets, strides and sizes are
//! checked arithmetic bounded by their storage, and a zip storage's declared
//! size must be its entry's size before anything is read. Each limit is far
//! above what `torch.save` writes for a `state_dict`, and exceeding one is an
//! error naming the file.

use crate::error::{Error, Result};
use std::collections::HashMap;
use std::fs::File;
use std::hash::{Hash, Hasher};
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// Element type of a storage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum DType {
    /// `torch.float32`.
    F32,
    /// `torch.float64`.
    F64,
    /// `torch.float16` (IEEE half).
    F16,
    /// `torch.bfloat16`.
    BF16,
}

impl DType {
    fn from_storage(name: &str) -> Option<DType> {
        match name {
            "FloatStorage" => Some(DType::F32),
            "DoubleStorage" => Some(DType::F64),
            "HalfStorage" => Some(DType::F16),
            "BFloat16Storage" => Some(DType::BF16),
            _ => None,
        }
    }
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            DType::F32 => 4,
            DType::F64 => 8,
            DType::F16 | DType::BF16 => 2,
        }
    }
    fn decode(self, b: &[u8]) -> f64 {
        match self {
            DType::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            DType::F64 => f64::from_le_bytes(b[..8].try_into().expect("8 bytes")),
            DType::F16 => f16_to_f64(u16::from_le_bytes([b[0], b[1]])),
            DType::BF16 => f32::from_bits((u16::from_le_bytes([b[0], b[1]]) as u32) << 16) as f64,
        }
    }
}

/// IEEE half precision to f64 (exact).
fn f16_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f64;
    match exp {
        0 => sign * frac * 2f64.powi(-24),
        31 if frac == 0.0 => sign * f64::INFINITY,
        31 => f64::NAN,
        e => sign * (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

/// Which container a file uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Container {
    /// The zip archive `torch.save` writes since PyTorch 1.6.
    Zip,
    /// The older pickle-stream format (`_use_new_zipfile_serialization=False`).
    Legacy,
}

/// A storage named by a persistent id.
#[derive(Clone, Debug, PartialEq, Hash)]
struct StorageRef {
    key: String,
    dtype: DType,
    /// Elements of the root storage, as the persistent id records them.
    numel: u64,
    /// Legacy view storages: (element offset into the root, elements).
    view: Option<(u64, u64)>,
}

/// A tensor's metadata: where its elements are.
#[derive(Clone, Debug, PartialEq, Hash)]
struct TensorRef {
    storage: StorageRef,
    offset: u64,
    shape: Vec<usize>,
    stride: Vec<usize>,
}

/// A pickled value (only what a `state_dict` needs).
///
/// Values are plain trees: `DUP` and the memo copy them (the copies count
/// against [`MAX_VALUES`]), and the interpreter keeps every tree at most
/// [`MAX_DEPTH`] deep, so the recursive `Drop`, `Clone`, `PartialEq` and
/// `Debug` never recurse deeper than that.
#[derive(Clone, Debug, PartialEq)]
enum Value {
    None,
    Bool(bool),
    Int(i64),
    /// An integer outside `i64` (the legacy magic number; at most 16 bytes).
    BigInt(i128),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    Tuple(Vec<Value>),
    List(Vec<Value>),
    Dict(Box<Dict>),
    Global(String, String),
    Storage(Box<StorageRef>),
    Tensor(Box<TensorRef>),
    /// A call of a global this reader does not interpret (kept, never run).
    Object(String, String),
    Mark,
}

impl Value {
    /// Bytes of text or data this value holds itself (not its children's).
    fn own_bytes(&self) -> u64 {
        match self {
            Value::Str(s) => s.len() as u64,
            Value::Bytes(b) => b.len() as u64,
            Value::Global(m, n) | Value::Object(m, n) => (m.len() + n.len()) as u64,
            Value::Storage(s) => s.key.len() as u64,
            Value::Tensor(t) => t.storage.key.len() as u64,
            _ => 0,
        }
    }

    /// Hash of a dictionary key, consistent with `==`; `false` (and the key
    /// is never looked up) when it holds a NaN, which makes it unequal to
    /// every key, itself included.
    fn hash_key(&self, h: &mut impl Hasher) -> bool {
        std::mem::discriminant(self).hash(h);
        match self {
            Value::None | Value::Mark => true,
            Value::Bool(b) => {
                b.hash(h);
                true
            }
            Value::Int(i) => {
                i.hash(h);
                true
            }
            Value::BigInt(i) => {
                i.hash(h);
                true
            }
            Value::Float(f) => {
                // 0.0 == -0.0: hash both as +0.0.
                (if *f == 0.0 { 0 } else { f.to_bits() }).hash(h);
                !f.is_nan()
            }
            Value::Str(s) => {
                s.hash(h);
                true
            }
            Value::Bytes(b) => {
                b.hash(h);
                true
            }
            Value::Tuple(v) | Value::List(v) => {
                v.len().hash(h);
                v.iter().all(|x| x.hash_key(h))
            }
            Value::Dict(d) => {
                d.items.len().hash(h);
                d.items.iter().all(|(k, v)| k.hash_key(h) && v.hash_key(h))
            }
            Value::Global(m, n) | Value::Object(m, n) => {
                m.hash(h);
                n.hash(h);
                true
            }
            Value::Storage(s) => {
                s.hash(h);
                true
            }
            Value::Tensor(t) => {
                t.hash(h);
                true
            }
        }
    }
}

/// A pickled dictionary: its items in insertion order (what the reader
/// returns), with an index from key hashes to positions so that setting an
/// item does not scan the others.
#[derive(Clone, Default)]
struct Dict {
    items: Vec<(Value, Value)>,
    /// [`Value::hash_key`] of each indexable key → its positions in `items`.
    index: HashMap<u64, Vec<usize>>,
}

impl PartialEq for Dict {
    fn eq(&self, other: &Dict) -> bool {
        self.items == other.items
    }
}

impl std::fmt::Debug for Dict {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_map()
            .entries(self.items.iter().map(|(k, v)| (k, v)))
            .finish()
    }
}

impl Dict {
    fn key_hash(k: &Value) -> Option<u64> {
        let mut h = std::hash::DefaultHasher::new();
        k.hash_key(&mut h).then(|| h.finish())
    }
    /// Append an item (`OrderedDict([...])` keeps repeated keys).
    fn push(&mut self, k: Value, v: Value) {
        if let Some(h) = Self::key_hash(&k) {
            self.index.entry(h).or_default().push(self.items.len());
        }
        self.items.push((k, v));
    }
    /// Set the value of the first key equal to `k`, or append the item.
    fn set(&mut self, k: Value, v: Value) {
        let Some(h) = Self::key_hash(&k) else {
            self.items.push((k, v));
            return;
        };
        let at = self
            .index
            .get(&h)
            .and_then(|at| at.iter().copied().find(|&i| self.items[i].0 == k));
        match at {
            Some(i) => self.items[i].1 = v,
            None => {
                self.index.entry(h).or_default().push(self.items.len());
                self.items.push((k, v));
            }
        }
    }
}

/// `v`'s `Debug` form cut to about 200 characters (error messages only: a
/// value may be large).
fn brief(v: &impl std::fmt::Debug) -> String {
    struct Cut(String);
    impl std::fmt::Write for Cut {
        fn write_str(&mut self, s: &str) -> std::fmt::Result {
            for c in s.chars() {
                if self.0.len() >= 200 {
                    return Err(std::fmt::Error);
                }
                self.0.push(c);
            }
            Ok(())
        }
    }
    let mut out = Cut(String::new());
    match std::fmt::write(&mut out, format_args!("{v:?}")) {
        Ok(()) => out.0,
        Err(_) => out.0 + "…",
    }
}

/// A `.pth` file opened for reading: its named tensors' metadata, with the
/// data read on request.
pub struct PthFile {
    path: PathBuf,
    container: Container,
    tensors: Vec<(String, TensorRef)>,
    /// Legacy files: byte offset of each storage's data.
    legacy_offsets: HashMap<String, u64>,
    /// Zip files: the archive's folder name (`NAME/` of `NAME/data.pkl`).
    zip_prefix: String,
}

impl std::fmt::Debug for PthFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PthFile")
            .field("path", &self.path)
            .field("container", &self.container)
            .field("tensors", &self.tensors.len())
            .finish()
    }
}

/// Most bytes one pickle may take (a `state_dict` pickle is kilobytes:
/// torchvision's VGG16, 32 tensors, takes about 4.5 KB).
pub const MAX_PICKLE_BYTES: u64 = 64 << 20;
/// Most values one pickle may create, the copies made by `DUP` and memo
/// `GET`/`PUT` included (torchvision's VGG16 `state_dict`, 32 tensors, creates
/// about 2,000: the limit is some 30,000 tensors' worth).
pub const MAX_VALUES: u64 = 1 << 21;
/// Most bytes of text and binary data one pickle may create, copies included.
pub const MAX_VALUE_BYTES: u64 = 2 * MAX_PICKLE_BYTES;
/// Deepest nesting of a pickled value (a `state_dict` of tensors nests 2
/// deep, the legacy header 3).
pub const MAX_DEPTH: u32 = 1000;
/// Most elements a tensor whose strides overlap (a stride of 0 from
/// `expand`) may have beyond its storage's: the elements are copied out, and
/// a dense tensor's are bounded by the file's size.
pub const MAX_OVERLAPPING_ELEMENTS: u64 = 1 << 24;

impl PthFile {
    /// Open `path` and read its tensor metadata (not the data). The top-level
    /// object must be a dictionary of tensors (other entries are ignored).
    pub fn open(path: &Path) -> Result<PthFile> {
        let mut f = super::open(path)?;
        let mut magic = [0u8; 4];
        let n = read_up_to(&mut f, &mut magic).map_err(|e| Error::io(path, e))?;
        f.seek(SeekFrom::Start(0)).map_err(|e| Error::io(path, e))?;
        if n == 4 && magic == *b"PK\x03\x04" {
            Self::open_zip(path, f)
        } else if n >= 2 && magic[0] == 0x80 {
            Self::open_legacy(path, f)
        } else {
            Err(Error::format(
                path,
                "not a PyTorch file (neither a zip archive nor a legacy pickle stream)",
            ))
        }
    }

    fn open_zip(path: &Path, f: File) -> Result<PthFile> {
        let mut zip = zip::ZipArchive::new(BufReader::new(f))
            .map_err(|e| Error::format(path, format!("zip container: {e}")))?;
        let pkl = zip
            .file_names()
            .filter_map(|n| n.ok().map(|n| n.to_string()))
            .find(|n| n.ends_with("data.pkl") && n.matches('/').count() == 1)
            .ok_or_else(|| Error::format(path, "zip container without NAME/data.pkl"))?;
        let prefix = pkl.trim_end_matches("data.pkl").to_string();
        if let Ok(mut e) = zip.by_name(&format!("{prefix}byteorder")) {
            let mut s = String::new();
            e.read_to_string(&mut s)
                .map_err(|e| Error::format(path, format!("{prefix}byteorder: {e}")))?;
            if s.trim() != "little" {
                return Err(Error::format(
                    path,
                    format!(
                        "byte order `{}`: only little-endian files are supported",
                        s.trim()
                    ),
                ));
            }
        }
        let bytes = {
            let e = zip
                .by_name(&pkl)
                .map_err(|e| Error::format(path, format!("{pkl}: {e}")))?;
            if e.size() > MAX_PICKLE_BYTES {
                return Err(Error::format(path, format!("{pkl} is {} bytes", e.size())));
            }
            let mut b = Vec::with_capacity(e.size() as usize);
            e.take(MAX_PICKLE_BYTES)
                .read_to_end(&mut b)
                .map_err(|e| Error::format(path, format!("{pkl}: {e}")))?;
            b
        };
        let mut r = PickleReader::new(path, &bytes[..]);
        let obj = r.load()?;
        Ok(PthFile {
            path: path.to_path_buf(),
            container: Container::Zip,
            tensors: tensors_of(path, obj)?,
            legacy_offsets: HashMap::new(),
            zip_prefix: prefix,
        })
    }

    fn open_legacy(path: &Path, f: File) -> Result<PthFile> {
        let len = f.metadata().map_err(|e| Error::io(path, e))?.len();
        let mut br = BufReader::new(f);
        let (magic, proto, info, obj, keys, pos) = {
            let mut r = PickleReader::new(path, &mut br);
            let magic = r.load()?;
            let proto = r.load()?;
            let info = r.load()?;
            let obj = r.load()?;
            let keys = r.load()?;
            (magic, proto, info, obj, keys, r.pos)
        };
        const MAGIC: i128 = 0x1950a86a20f9469cfc6c;
        let magic_ok = matches!(magic, Value::BigInt(m) if m == MAGIC);
        if !magic_ok {
            return Err(Error::format(
                path,
                "not a PyTorch file (wrong magic number in the legacy header)",
            ));
        }
        if proto != Value::Int(1001) {
            return Err(Error::format(
                path,
                format!("legacy protocol version {}, expected 1001", brief(&proto)),
            ));
        }
        if let Value::Dict(d) = &info {
            for (k, v) in &d.items {
                if *k == Value::Str("little_endian".into()) && *v == Value::Bool(false) {
                    return Err(Error::format(
                        path,
                        "big-endian file: only little-endian files are supported",
                    ));
                }
            }
        }
        let tensors = tensors_of(path, obj)?;
        let Value::List(keys) = keys else {
            return Err(Error::format(path, "legacy storage key list is not a list"));
        };
        // The storages as the object references them (their element type and
        // size): every reference to one storage must agree.
        let mut roots: HashMap<String, StorageRef> = HashMap::new();
        for (name, t) in &tensors {
            match roots.get(&t.storage.key) {
                Some(s) if s.dtype != t.storage.dtype || s.numel != t.storage.numel => {
                    return Err(Error::format(
                        path,
                        format!(
                            "tensor {name}: storage {} is {:?} of {} elements here, {:?} of {} elsewhere",
                            t.storage.key, t.storage.dtype, t.storage.numel, s.dtype, s.numel
                        ),
                    ));
                }
                Some(_) => {}
                None => {
                    roots.insert(t.storage.key.clone(), t.storage.clone());
                }
            }
        }
        let mut offsets = HashMap::new();
        let mut at = pos;
        for k in keys {
            let key = match k {
                Value::Str(s) => s,
                other => {
                    return Err(Error::format(
                        path,
                        format!("legacy storage key {} is not a string", brief(&other)),
                    ))
                }
            };
            let mut hdr = [0u8; 8];
            br.seek(SeekFrom::Start(at))
                .map_err(|e| Error::io(path, e))?;
            br.read_exact(&mut hdr)
                .map_err(|_| truncated(path, &key, at))?;
            let numel = u64::from_le_bytes(hdr);
            // Storages no tensor uses (none in a state_dict) have unknown
            // element size: they would have to be last.
            let elem = match roots.get(&key) {
                Some(s) => {
                    if s.numel != numel {
                        return Err(Error::format(
                            path,
                            format!(
                                "storage {key}: {numel} elements in the data, {} in the pickle",
                                s.numel
                            ),
                        ));
                    }
                    s.dtype.size() as u64
                }
                None => {
                    return Err(Error::format(
                        path,
                        format!("storage {key} is listed but no tensor uses it"),
                    ))
                }
            };
            let data = at + 8;
            let end = numel
                .checked_mul(elem)
                .and_then(|b| b.checked_add(data))
                .ok_or_else(|| Error::format(path, format!("storage {key}: size overflows")))?;
            if end > len {
                return Err(truncated(path, &key, data));
            }
            offsets.insert(key, data);
            at = end;
        }
        for (name, t) in &tensors {
            if !offsets.contains_key(&t.storage.key) {
                return Err(Error::format(
                    path,
                    format!(
                        "tensor {name}: storage {} is not in the file",
                        t.storage.key
                    ),
                ));
            }
        }
        Ok(PthFile {
            path: path.to_path_buf(),
            container: Container::Legacy,
            tensors,
            legacy_offsets: offsets,
            zip_prefix: String::new(),
        })
    }

    /// The file's container format.
    pub fn container(&self) -> Container {
        self.container
    }

    /// Tensor names, in the file's order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.tensors.iter().map(|(n, _)| n.as_str())
    }

    fn get(&self, name: &str) -> Option<&TensorRef> {
        self.tensors.iter().find(|(n, _)| n == name).map(|(_, t)| t)
    }

    /// The shape of tensor `name`, if the file has it.
    pub fn shape(&self, name: &str) -> Option<&[usize]> {
        self.get(name).map(|t| t.shape.as_slice())
    }

    /// The element type of tensor `name`, if the file has it.
    pub fn dtype(&self, name: &str) -> Option<DType> {
        self.get(name).map(|t| t.storage.dtype)
    }

    /// The elements of tensor `name` in row-major order, as f64 (exact for
    /// every supported element type).
    pub fn read_f64(&self, name: &str) -> Result<Vec<f64>> {
        let t = self.get(name).ok_or_else(|| Error::MissingTensor {
            context: self.path.display().to_string(),
            name: name.to_string(),
        })?;
        let bad = |what: String| Error::format(&self.path, format!("tensor {name}: {what}"));
        let s = &t.storage;
        let esz = s.dtype.size() as u64;
        // The element range [first, limit) of the root storage this tensor
        // indexes: the whole root, or a legacy view inside it.
        let (first, limit) = match s.view {
            None => (0, s.numel),
            Some((off, size)) => match off.checked_add(size) {
                Some(end) if end <= s.numel => (off, end),
                _ => {
                    return Err(bad(format!(
                        "storage view of {size} elements from {off} outside its storage of {}",
                        s.numel
                    )))
                }
            },
        };
        let numel = if t.shape.contains(&0) {
            Some(0)
        } else {
            t.shape
                .iter()
                .try_fold(1u64, |a, &n| a.checked_mul(n as u64))
        };
        // Elements from the first one read to the last, inclusive.
        let span = match numel {
            Some(0) => Some(0),
            Some(_) => t
                .shape
                .iter()
                .zip(&t.stride)
                .try_fold(1u64, |a, (&n, &st)| {
                    (n as u64 - 1)
                        .checked_mul(st as u64)
                        .and_then(|x| a.checked_add(x))
                }),
            None => None,
        };
        let base = first.checked_add(t.offset);
        let (numel, base, span) = match (numel, base, span) {
            (Some(n), Some(b), Some(sp)) if b.checked_add(sp).is_some_and(|e| e <= limit) => {
                (n, b, sp)
            }
            _ => {
                return Err(bad(format!(
                    "offset {}, shape {} and stride {} reach outside its storage of {} elements",
                    t.offset,
                    brief(&t.shape),
                    brief(&t.stride),
                    limit - first
                )))
            }
        };
        if numel > limit - first && numel > MAX_OVERLAPPING_ELEMENTS {
            return Err(bad(format!(
                "{numel} elements from a storage of {} (overlapping strides {}): more than the limit {MAX_OVERLAPPING_ELEMENTS}",
                limit - first,
                brief(&t.stride)
            )));
        }
        let (Some(start), Some(len)) = (base.checked_mul(esz), span.checked_mul(esz)) else {
            return Err(bad(format!(
                "storage {} of {} elements of {esz} bytes overflows",
                s.key, s.numel
            )));
        };
        let bytes = self.storage_bytes(s, start, len)?;
        let esz = esz as usize;
        let mut out = Vec::new();
        out.try_reserve_exact(numel as usize)
            .map_err(|_| bad(format!("{numel} elements do not fit in memory")))?;
        let mut idx = vec![0usize; t.shape.len()];
        for _ in 0..numel {
            let off: usize = idx.iter().zip(&t.stride).map(|(i, s)| i * s).sum();
            out.push(s.dtype.decode(&bytes[off * esz..]));
            for d in (0..idx.len()).rev() {
                idx[d] += 1;
                if idx[d] < t.shape[d] {
                    break;
                }
                idx[d] = 0;
            }
        }
        Ok(out)
    }

    /// [`read_f64`](Self::read_f64) rounded to f32 (exact for f32, f16 and
    /// bf16 storages).
    pub fn read_f32(&self, name: &str) -> Result<Vec<f32>> {
        Ok(self.read_f64(name)?.into_iter().map(|v| v as f32).collect())
    }

    /// `len` bytes of storage `s` from byte `start`; `start + len` is at most
    /// the storage's declared size, which is checked against the file before
    /// anything is allocated.
    fn storage_bytes(&self, s: &StorageRef, start: u64, len: u64) -> Result<Vec<u8>> {
        let path = &self.path;
        let key = &s.key;
        match self.container {
            Container::Legacy => {
                // open_legacy checked that the file holds all of the storage.
                let data = self.legacy_offsets[key];
                let mut f = super::open(path)?;
                f.seek(SeekFrom::Start(data + start))
                    .map_err(|e| Error::io(path, e))?;
                let mut buf = vec![0u8; len as usize];
                f.read_exact(&mut buf)
                    .map_err(|_| truncated(path, key, data + start))?;
                Ok(buf)
            }
            Container::Zip => {
                let f = super::open(path)?;
                let file_len = f.metadata().map_err(|e| Error::io(path, e))?.len();
                let mut zip = zip::ZipArchive::new(BufReader::new(f))
                    .map_err(|e| Error::format(path, format!("zip container: {e}")))?;
                let entry = format!("{}data/{key}", self.zip_prefix);
                let mut e = zip
                    .by_name(&entry)
                    .map_err(|e| Error::format(path, format!("{entry}: {e}")))?;
                let declared = s.numel.checked_mul(s.dtype.size() as u64);
                if declared != Some(e.size()) {
                    return Err(Error::format(
                        path,
                        format!(
                            "{entry}: {} bytes, but the pickle declares {} elements of {} bytes",
                            e.size(),
                            s.numel,
                            s.dtype.size()
                        ),
                    ));
                }
                // torch.save stores storages uncompressed: the data is in the file.
                if e.size() > file_len {
                    return Err(Error::format(
                        path,
                        format!("{entry}: {} bytes in a file of {file_len}", e.size()),
                    ));
                }
                std::io::copy(&mut (&mut e).take(start), &mut std::io::sink())
                    .map_err(|err| Error::format(path, format!("{entry}: {err}")))?;
                let mut buf = vec![0u8; len as usize];
                e.read_exact(&mut buf)
                    .map_err(|err| Error::format(path, format!("{entry}: {err}")))?;
                Ok(buf)
            }
        }
    }
}

fn truncated(path: &Path, key: &str, at: u64) -> Error {
    Error::format(
        path,
        format!("truncated: storage {key} (from byte {at}) extends past the end of the file"),
    )
}

fn read_up_to(f: &mut File, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match f.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

/// The named tensors of a pickled `state_dict` (other values are skipped).
fn tensors_of(path: &Path, obj: Value) -> Result<Vec<(String, TensorRef)>> {
    let Value::Dict(dict) = obj else {
        return Err(Error::format(
            path,
            "the pickled object is not a dictionary of tensors (a state_dict)",
        ));
    };
    let mut out = Vec::new();
    for (k, v) in dict.items {
        if let (Value::Str(name), Value::Tensor(t)) = (k, v) {
            out.push((name, *t));
        }
    }
    Ok(out)
}

/// A value on the interpreter's stack or in its memo, with the depth of its
/// nesting (1 for a scalar or an empty container, 0 for a mark).
struct Entry {
    v: Value,
    depth: u32,
}

/// A pickle interpreter over a byte stream (see the module docs).
struct PickleReader<'p, R> {
    path: &'p Path,
    r: R,
    /// Bytes consumed so far (for messages and the legacy data offset).
    pos: u64,
    /// Where the current pickle began.
    start: u64,
    stack: Vec<Entry>,
    memo: HashMap<u64, Entry>,
    /// Values and bytes of text created by the current pickle.
    values: u64,
    value_bytes: u64,
}

impl<'p, R: Read> PickleReader<'p, R> {
    fn new(path: &'p Path, r: R) -> Self {
        PickleReader {
            path,
            r,
            pos: 0,
            start: 0,
            stack: Vec::new(),
            memo: HashMap::new(),
            values: 0,
            value_bytes: 0,
        }
    }

    fn err(&self, what: impl std::fmt::Display) -> Error {
        Error::format(self.path, format!("pickle at byte {}: {what}", self.pos))
    }

    fn bytes(&mut self, n: u64) -> Result<Vec<u8>> {
        if n > MAX_PICKLE_BYTES - (self.pos - self.start) {
            return Err(self.err(format!(
                "a {n}-byte value: the pickle would be longer than {MAX_PICKLE_BYTES} bytes"
            )));
        }
        let mut b = vec![0u8; n as usize];
        self.r
            .read_exact(&mut b)
            .map_err(|_| self.err("truncated (the file ends inside a pickle)"))?;
        self.pos += n;
        Ok(b)
    }
    fn u8(&mut self) -> Result<u8> {
        Ok(self.bytes(1)?[0])
    }
    fn u16(&mut self) -> Result<u16> {
        let b = self.bytes(2)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }
    fn u32(&mut self) -> Result<u32> {
        let b = self.bytes(4)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn u64(&mut self) -> Result<u64> {
        let b = self.bytes(8)?;
        Ok(u64::from_le_bytes(b[..8].try_into().expect("8 bytes")))
    }
    fn line(&mut self) -> Result<String> {
        let mut s = Vec::new();
        loop {
            let c = self.u8()?;
            if c == b'\n' {
                break;
            }
            if s.len() > 4096 {
                return Err(self.err("a text line longer than 4096 bytes"));
            }
            s.push(c);
        }
        String::from_utf8(s).map_err(|_| self.err("a text line that is not UTF-8"))
    }
    fn text(&mut self, n: u64) -> Result<String> {
        let b = self.bytes(n)?;
        String::from_utf8(b).map_err(|_| self.err("a string that is not UTF-8"))
    }
    /// Python 2 `str` (bytes): read as text when it is UTF-8.
    fn py2_str(&mut self, n: u64) -> Result<Value> {
        let b = self.bytes(n)?;
        Ok(match String::from_utf8(b) {
            Ok(s) => Value::Str(s),
            Err(e) => Value::Bytes(e.into_bytes()),
        })
    }

    /// Count `values` new values holding `bytes` bytes of text against the
    /// limits.
    fn made(&mut self, values: u64, bytes: u64) -> Result<()> {
        self.values += values;
        self.value_bytes += bytes;
        if self.values > MAX_VALUES {
            return Err(self.err(format!(
                "more than {MAX_VALUES} values (copies by DUP and the memo included)"
            )));
        }
        if self.value_bytes > MAX_VALUE_BYTES {
            return Err(self.err(format!(
                "more than {MAX_VALUE_BYTES} bytes of strings (copies by DUP and the memo included)"
            )));
        }
        Ok(())
    }
    /// A copy of `v`, counted as created: its values and bytes are counted
    /// (stopping as soon as the count passes a limit) before it is made.
    fn copy(&mut self, v: &Value) -> Result<Value> {
        let (left, left_bytes) = (MAX_VALUES - self.values, MAX_VALUE_BYTES - self.value_bytes);
        let (mut n, mut b) = (0u64, 0u64);
        let mut todo = vec![v];
        while let Some(x) = todo.pop() {
            n += 1;
            b += x.own_bytes();
            if n > left || b > left_bytes {
                break;
            }
            match x {
                Value::Tuple(c) | Value::List(c) => todo.extend(c),
                Value::Dict(d) => todo.extend(d.items.iter().flat_map(|(k, v)| [k, v])),
                _ => {}
            }
        }
        self.made(n, b)?;
        Ok(v.clone())
    }
    /// Push a value of nesting `depth`.
    fn push(&mut self, v: Value, depth: u32) -> Result<()> {
        if depth > MAX_DEPTH {
            return Err(self.err(format!("values nested more than {MAX_DEPTH} deep")));
        }
        self.stack.push(Entry { v, depth });
        Ok(())
    }
    /// Push a newly created value (one value, counted) of nesting `depth`.
    fn push_new(&mut self, v: Value, depth: u32) -> Result<()> {
        self.made(1, v.own_bytes())?;
        self.push(v, depth)
    }

    fn pop_entry(&mut self) -> Result<Entry> {
        match self.stack.pop() {
            Some(Entry { v: Value::Mark, .. }) | None => Err(self.err("stack underflow")),
            Some(e) => Ok(e),
        }
    }
    fn pop(&mut self) -> Result<Value> {
        Ok(self.pop_entry()?.v)
    }
    /// The values above the topmost mark (removed with it) and their
    /// deepest nesting.
    fn pop_mark(&mut self) -> Result<(Vec<Value>, u32)> {
        let at = self
            .stack
            .iter()
            .rposition(|e| matches!(e.v, Value::Mark))
            .ok_or_else(|| self.err("no mark on the stack"))?;
        let items = self.stack.split_off(at + 1);
        self.stack.pop();
        let depth = items.iter().map(|e| e.depth).max().unwrap_or(0);
        Ok((items.into_iter().map(|e| e.v).collect(), depth))
    }
    fn top(&mut self) -> Result<&mut Entry> {
        let at = self.pos;
        match self.stack.last_mut() {
            Some(Entry { v: Value::Mark, .. }) | None => Err(Error::format(
                self.path,
                format!("pickle at byte {at}: stack underflow"),
            )),
            Some(e) => Ok(e),
        }
    }
    /// The container on top of the stack now holds values `depth` deep.
    fn deepen(&mut self, depth: u32) -> Result<()> {
        let d = self.top()?.depth.max(depth.saturating_add(1));
        if d > MAX_DEPTH {
            return Err(self.err(format!("values nested more than {MAX_DEPTH} deep")));
        }
        self.top()?.depth = d;
        Ok(())
    }
    fn memo_put(&mut self, k: u64) -> Result<()> {
        let e = self
            .stack
            .pop()
            .ok_or_else(|| self.err("memo of an empty stack"))?;
        let copied = self.copy(&e.v);
        let depth = e.depth;
        self.stack.push(e);
        self.memo.insert(k, Entry { v: copied?, depth });
        Ok(())
    }
    fn memo_get(&mut self, k: u64) -> Result<()> {
        let e = self
            .memo
            .remove(&k)
            .ok_or_else(|| self.err(format!("memo key {k} not set")))?;
        let copied = self.copy(&e.v);
        let depth = e.depth;
        self.memo.insert(k, e);
        self.push(copied?, depth)
    }
    fn set_items(&mut self, items: Vec<Value>, depth: u32) -> Result<()> {
        if !items.len().is_multiple_of(2) {
            return Err(self.err("odd number of dictionary items"));
        }
        let (at, path) = (self.pos, self.path);
        match &mut self.top()?.v {
            Value::Dict(d) => {
                let mut it = items.into_iter();
                while let (Some(k), Some(v)) = (it.next(), it.next()) {
                    d.set(k, v);
                }
            }
            Value::Object(..) => return Ok(()),
            other => {
                return Err(Error::format(
                    path,
                    format!("pickle at byte {at}: set items on {}", brief(other)),
                ))
            }
        }
        self.deepen(depth)
    }
    fn append(&mut self, items: Vec<Value>, depth: u32) -> Result<()> {
        let (at, path) = (self.pos, self.path);
        match &mut self.top()?.v {
            Value::List(l) => l.extend(items),
            Value::Object(..) => return Ok(()),
            other => {
                return Err(Error::format(
                    path,
                    format!("pickle at byte {at}: append to {}", brief(other)),
                ))
            }
        }
        self.deepen(depth)
    }

    /// Read one pickle (up to and including STOP) and return its value.
    fn load(&mut self) -> Result<Value> {
        self.stack.clear();
        self.memo.clear();
        self.start = self.pos;
        self.values = 0;
        self.value_bytes = 0;
        loop {
            let op = self.u8()?;
            match op {
                0x80 => {
                    let p = self.u8()?;
                    if p > 5 {
                        return Err(self.err(format!("pickle protocol {p}")));
                    }
                }
                0x95 => {
                    self.u64()?; // FRAME: a length hint only
                }
                b'.' => return self.pop(),
                b'(' => self.push_new(Value::Mark, 0)?,
                b'}' => self.push_new(Value::Dict(Box::default()), 1)?,
                b']' => self.push_new(Value::List(Vec::new()), 1)?,
                b')' => self.push_new(Value::Tuple(Vec::new()), 1)?,
                b't' => {
                    let (items, d) = self.pop_mark()?;
                    self.push_new(Value::Tuple(items), d.saturating_add(1))?;
                }
                b'l' => {
                    let (items, d) = self.pop_mark()?;
                    self.push_new(Value::List(items), d.saturating_add(1))?;
                }
                b'd' => {
                    let (items, d) = self.pop_mark()?;
                    self.push_new(Value::Dict(Box::default()), 1)?;
                    self.set_items(items, d)?;
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    if self.stack.len() < n {
                        return Err(self.err("stack underflow"));
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    if items.iter().any(|e| matches!(e.v, Value::Mark)) {
                        return Err(self.err("mark inside a tuple"));
                    }
                    let d = items.iter().map(|e| e.depth).max().unwrap_or(0);
                    let items = items.into_iter().map(|e| e.v).collect();
                    self.push_new(Value::Tuple(items), d.saturating_add(1))?;
                }
                b'q' => {
                    let k = self.u8()? as u64;
                    self.memo_put(k)?;
                }
                b'r' => {
                    let k = self.u32()? as u64;
                    self.memo_put(k)?;
                }
                0x94 => {
                    let k = self.memo.len() as u64;
                    self.memo_put(k)?;
                }
                b'h' => {
                    let k = self.u8()? as u64;
                    self.memo_get(k)?;
                }
                b'j' => {
                    let k = self.u32()? as u64;
                    self.memo_get(k)?;
                }
                b'K' => {
                    let v = self.u8()? as i64;
                    self.push_new(Value::Int(v), 1)?;
                }
                b'M' => {
                    let v = self.u16()? as i64;
                    self.push_new(Value::Int(v), 1)?;
                }
                b'J' => {
                    let v = self.u32()? as i32 as i64;
                    self.push_new(Value::Int(v), 1)?;
                }
                0x8a => {
                    let n = self.u8()? as u64;
                    let b = self.bytes(n)?;
                    if n > 16 {
                        return Err(self.err(format!("a {n}-byte integer")));
                    }
                    // Little-endian two's complement.
                    let mut v: i128 = 0;
                    for (i, &x) in b.iter().enumerate() {
                        v |= (x as i128) << (8 * i);
                    }
                    if n > 0 && n < 16 && b[n as usize - 1] & 0x80 != 0 {
                        v -= 1i128 << (8 * n);
                    }
                    let v = match i64::try_from(v) {
                        Ok(v) => Value::Int(v),
                        Err(_) => Value::BigInt(v),
                    };
                    self.push_new(v, 1)?;
                }
                b'N' => self.push_new(Value::None, 1)?,
                0x88 => self.push_new(Value::Bool(true), 1)?,
                0x89 => self.push_new(Value::Bool(false), 1)?,
                b'G' => {
                    let b = self.bytes(8)?;
                    let v = f64::from_be_bytes(b[..8].try_into().expect("8 bytes"));
                    self.push_new(Value::Float(v), 1)?;
                }
                b'X' => {
                    let n = self.u32()? as u64;
                    let s = self.text(n)?;
                    self.push_new(Value::Str(s), 1)?;
                }
                0x8c => {
                    let n = self.u8()? as u64;
                    let s = self.text(n)?;
                    self.push_new(Value::Str(s), 1)?;
                }
                0x8d => {
                    let n = self.u64()?;
                    let s = self.text(n)?;
                    self.push_new(Value::Str(s), 1)?;
                }
                b'U' => {
                    let n = self.u8()? as u64;
                    let v = self.py2_str(n)?;
                    self.push_new(v, 1)?;
                }
                b'T' => {
                    let n = self.u32()? as u64;
                    let v = self.py2_str(n)?;
                    self.push_new(v, 1)?;
                }
                b'C' => {
                    let n = self.u8()? as u64;
                    let b = self.bytes(n)?;
                    self.push_new(Value::Bytes(b), 1)?;
                }
                b'B' => {
                    let n = self.u32()? as u64;
                    let b = self.bytes(n)?;
                    self.push_new(Value::Bytes(b), 1)?;
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.push_new(Value::Global(module, name), 1)?;
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    match (module, name) {
                        (Value::Str(m), Value::Str(n)) => self.push_new(Value::Global(m, n), 1)?,
                        _ => return Err(self.err("STACK_GLOBAL of non-strings")),
                    }
                }
                b'R' | 0x81 => {
                    let args = self.pop_entry()?;
                    let f = self.pop()?;
                    let (v, depth) = self.call(f, args)?;
                    self.push_new(v, depth)?;
                }
                b'b' => {
                    // BUILD: object state (OrderedDict `_metadata`, …) is not needed.
                    self.pop()?;
                    self.top()?;
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let v = self.persistent(pid)?;
                    self.push_new(v, 1)?;
                }
                b's' => {
                    let v = self.pop_entry()?;
                    let k = self.pop_entry()?;
                    self.set_items(vec![k.v, v.v], k.depth.max(v.depth))?;
                }
                b'u' => {
                    let (items, d) = self.pop_mark()?;
                    self.set_items(items, d)?;
                }
                b'a' => {
                    let v = self.pop_entry()?;
                    self.append(vec![v.v], v.depth)?;
                }
                b'e' => {
                    let (items, d) = self.pop_mark()?;
                    self.append(items, d)?;
                }
                b'0' => {
                    self.stack
                        .pop()
                        .ok_or_else(|| self.err("stack underflow"))?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let e = self.pop_entry()?;
                    let copied = self.copy(&e.v);
                    let depth = e.depth;
                    self.stack.push(e);
                    self.push(copied?, depth)?;
                }
                other => {
                    return Err(self.err(format!(
                        "opcode 0x{other:02x} is not supported (not a plain state_dict?)"
                    )))
                }
            }
        }
    }

    /// A persistent id: `('storage', type, key, location, numel[, view])`.
    fn persistent(&mut self, pid: Value) -> Result<Value> {
        let Value::Tuple(t) = pid else {
            return Err(self.err(format!("persistent id {} is not a tuple", brief(&pid))));
        };
        match t.as_slice() {
            [Value::Str(kind), Value::Global(_, ty), Value::Str(key), _loc, Value::Int(n), rest @ ..]
                if kind == "storage" =>
            {
                let dtype = DType::from_storage(ty)
                    .ok_or_else(|| self.err(format!("storage type {ty} is not supported")))?;
                if *n < 0 {
                    return Err(self.err(format!("storage {key} has {n} elements")));
                }
                let view = match rest {
                    [] | [Value::None] => None,
                    [Value::Tuple(v)] => match v.as_slice() {
                        [_, Value::Int(off), Value::Int(size)] if *off >= 0 && *size >= 0 => {
                            Some((*off as u64, *size as u64))
                        }
                        _ => return Err(self.err(format!("storage view {}", brief(v)))),
                    },
                    _ => return Err(self.err(format!("persistent id {}", brief(&t)))),
                };
                Ok(Value::Storage(Box::new(StorageRef {
                    key: key.clone(),
                    dtype,
                    numel: *n as u64,
                    view,
                })))
            }
            _ => Err(self.err(format!("persistent id {} is not a storage", brief(&t)))),
        }
    }

    /// REDUCE / NEWOBJ: interpret the calls a state_dict needs; keep others
    /// as opaque objects. Returns the value and its nesting depth.
    fn call(&mut self, f: Value, args: Entry) -> Result<(Value, u32)> {
        let Value::Global(module, name) = f else {
            return Err(self.err(format!("call of {}", brief(&f))));
        };
        let Value::Tuple(args_v) = args.v else {
            return Err(self.err(format!("{module}.{name} called with {}", brief(&args.v))));
        };
        match (module.as_str(), name.as_str()) {
            ("torch._utils", "_rebuild_tensor" | "_rebuild_tensor_v2") => {
                let ints = |v: &Value| -> Option<Vec<usize>> {
                    match v {
                        Value::Tuple(x) | Value::List(x) => x
                            .iter()
                            .map(|e| match e {
                                Value::Int(i) if *i >= 0 => Some(*i as usize),
                                _ => None,
                            })
                            .collect(),
                        _ => None,
                    }
                };
                match args_v.as_slice() {
                    [Value::Storage(s), Value::Int(off), size, stride, ..] if *off >= 0 => {
                        let (Some(shape), Some(stride)) = (ints(size), ints(stride)) else {
                            return Err(self.err("tensor size or stride is not a tuple of ints"));
                        };
                        if shape.len() != stride.len() {
                            return Err(self.err("tensor size and stride differ in length"));
                        }
                        let t = TensorRef {
                            storage: (**s).clone(),
                            offset: *off as u64,
                            shape,
                            stride,
                        };
                        Ok((Value::Tensor(Box::new(t)), 1))
                    }
                    _ => {
                        Err(self.err(format!("{module}.{name} with arguments {}", brief(&args_v))))
                    }
                }
            }
            ("collections", "OrderedDict") => {
                let mut args_v = args_v;
                match args_v.as_mut_slice() {
                    [] => Ok((Value::Dict(Box::default()), 1)),
                    [Value::List(pairs)] => {
                        let mut d = Dict::default();
                        for p in std::mem::take(pairs) {
                            match p {
                                Value::List(mut kv) | Value::Tuple(mut kv) if kv.len() == 2 => {
                                    if let (Some(v), Some(k)) = (kv.pop(), kv.pop()) {
                                        d.push(k, v)
                                    }
                                }
                                _ => return Err(self.err("OrderedDict item is not a pair")),
                            }
                        }
                        // args: a tuple holding a list of pairs.
                        Ok((
                            Value::Dict(Box::new(d)),
                            args.depth.saturating_sub(2).max(1),
                        ))
                    }
                    _ => Err(self.err("OrderedDict with unexpected arguments")),
                }
            }
            _ => Ok((Value::Object(module, name), 1)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_precision_decodes_exactly() {
        assert_eq!(f16_to_f64(0x3c00), 1.0);
        assert_eq!(f16_to_f64(0xc000), -2.0);
        assert_eq!(f16_to_f64(0x0001), 2f64.powi(-24));
        assert_eq!(f16_to_f64(0x7bff), 65504.0);
        assert!(f16_to_f64(0x7c00).is_infinite());
        assert!(f16_to_f64(0x7e00).is_nan());
    }

    #[test]
    fn pickle_of_nested_values() {
        // pickle.dumps({'a': (1, -2, 300, 70000, 2**40), 'b': [1.5, None, True]}, protocol=2)
        let bytes: &[u8] = b"\x80\x02}q\x00(X\x01\x00\x00\x00aq\x01(K\x01J\xfe\xff\xff\xffM,\x01J\x70\x11\x01\x00\x8a\x06\x00\x00\x00\x00\x00\x01tq\x02X\x01\x00\x00\x00bq\x03]q\x04(G?\xf8\x00\x00\x00\x00\x00\x00N\x88eu.";
        let path = Path::new("x");
        let v = PickleReader::new(path, bytes).load().unwrap();
        let mut want = Dict::default();
        for (k, v) in [
            (
                Value::Str("a".into()),
                Value::Tuple(vec![
                    Value::Int(1),
                    Value::Int(-2),
                    Value::Int(300),
                    Value::Int(70000),
                    Value::Int(1 << 40),
                ]),
            ),
            (
                Value::Str("b".into()),
                Value::List(vec![Value::Float(1.5), Value::None, Value::Bool(true)]),
            ),
        ] {
            want.push(k, v);
        }
        assert_eq!(v, Value::Dict(Box::new(want)));
        // Cut short: an error naming the offset, never a panic.
        for cut in 0..bytes.len() {
            assert!(PickleReader::new(path, &bytes[..cut]).load().is_err());
        }
    }

    // ---- crafted files: errors, never a panic, an abort or a hang ----

    /// A file in the temporary folder, removed when dropped.
    struct TmpFile(PathBuf);
    impl TmpFile {
        fn new(name: &str, bytes: &[u8]) -> TmpFile {
            let p = std::env::temp_dir().join(format!("ls-pth-{}-{name}", std::process::id()));
            std::fs::write(&p, bytes).unwrap();
            TmpFile(p)
        }
    }
    impl Drop for TmpFile {
        fn drop(&mut self) {
            let _ = std::fs::remove_file(&self.0);
        }
    }

    fn text(o: &mut Vec<u8>, v: &str) {
        o.push(b'X');
        o.extend((v.len() as u32).to_le_bytes());
        o.extend(v.as_bytes());
    }
    /// An integer as `BININT` when it fits, else `LONG1` (8 bytes).
    fn int(o: &mut Vec<u8>, v: i64) {
        if let Ok(v) = i32::try_from(v) {
            o.push(b'J');
            o.extend(v.to_le_bytes());
        } else {
            o.extend(b"\x8a\x08");
            o.extend(v.to_le_bytes());
        }
    }

    /// One tensor's metadata, as `torch.save` pickles it.
    struct Spec {
        numel: i64,
        view: Option<(i64, i64)>,
        offset: i64,
        shape: Vec<i64>,
        stride: Vec<i64>,
    }

    /// `pickle.dumps({'w': tensor})` of the tensor `s` over float storage `0`.
    fn state_dict_pickle(s: &Spec) -> Vec<u8> {
        let mut o = b"\x80\x02}(".to_vec();
        text(&mut o, "w");
        o.extend(b"ctorch._utils\n_rebuild_tensor_v2\n((");
        text(&mut o, "storage");
        o.extend(b"ctorch\nFloatStorage\n");
        text(&mut o, "0");
        text(&mut o, "cpu");
        int(&mut o, s.numel);
        if let Some((off, size)) = s.view {
            o.push(b'(');
            text(&mut o, "0");
            int(&mut o, off);
            int(&mut o, size);
            o.push(b't');
        }
        o.extend(b"tQ");
        int(&mut o, s.offset);
        o.push(b'(');
        for &d in &s.shape {
            int(&mut o, d);
        }
        o.extend(b"t(");
        for &d in &s.stride {
            int(&mut o, d);
        }
        o.extend(b"t\x89NtRu.");
        o
    }

    /// A legacy file: the header pickles, `object`, the key list `['0']`,
    /// then storage `0` as `numel` and `data`.
    fn legacy_file(object: &[u8], numel: u64, data: &[u8]) -> Vec<u8> {
        let mut o = Vec::new();
        o.extend(b"\x80\x02\x8a\x0a\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19.");
        o.extend(b"\x80\x02M\xe9\x03.");
        o.extend(b"\x80\x02}(");
        text(&mut o, "little_endian");
        o.extend(b"\x88u.");
        o.extend(object);
        o.extend(b"\x80\x02](");
        text(&mut o, "0");
        o.extend(b"e.");
        o.extend(numel.to_le_bytes());
        o.extend(data);
        o
    }

    /// A zip file: `archive/data.pkl` is `pickle`, `archive/data/0` is `data`.
    fn zip_file(pickle: &[u8], data: &[u8]) -> Vec<u8> {
        use std::io::Write;
        let mut z = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        let opt = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Stored)
            .large_file(true);
        for (name, bytes) in [
            ("archive/data.pkl", pickle),
            ("archive/byteorder", b"little".as_slice()),
            ("archive/data/0", data),
        ] {
            z.start_file(name, opt).unwrap();
            z.write_all(bytes).unwrap();
        }
        z.finish().unwrap().into_inner()
    }

    /// Reading tensor `w` of both containers is an error naming the file
    /// (the legacy reader may already refuse the file when opening it).
    fn read_fails(tag: &str, s: &Spec, data: &[u8], want: &str) {
        let pickle = state_dict_pickle(s);
        let files = [
            ("zip", zip_file(&pickle, data)),
            ("legacy", legacy_file(&pickle, s.numel as u64, data)),
        ];
        for (kind, bytes) in files {
            if kind == "legacy" && s.numel as u64 != (data.len() / 4) as u64 {
                // The legacy header repeats the element count: write the data's.
                let f = TmpFile::new(&format!("{tag}-{kind}"), &bytes);
                let e = PthFile::open(&f.0)
                    .and_then(|p| p.read_f64("w"))
                    .unwrap_err();
                assert!(e.to_string().contains(&*f.0.to_string_lossy()), "{e}");
                continue;
            }
            let f = TmpFile::new(&format!("{tag}-{kind}"), &bytes);
            let e = match PthFile::open(&f.0) {
                Ok(p) => p.read_f64("w").unwrap_err(),
                Err(e) => e,
            };
            let m = e.to_string();
            assert!(m.contains(&*f.0.to_string_lossy()), "{kind}: {m}");
            assert!(m.contains(want), "{kind}: {m}");
        }
    }

    fn floats(n: usize) -> Vec<u8> {
        (0..n).flat_map(|i| (i as f32).to_le_bytes()).collect()
    }

    #[test]
    fn a_valid_crafted_file_reads_in_both_containers() {
        // The helpers write what the reader accepts: a [2, 3] transposed view.
        let s = Spec {
            numel: 8,
            view: None,
            offset: 1,
            shape: vec![2, 3],
            stride: vec![1, 2],
        };
        let pickle = state_dict_pickle(&s);
        for (kind, bytes) in [
            ("zip", zip_file(&pickle, &floats(8))),
            ("legacy", legacy_file(&pickle, 8, &floats(8))),
        ] {
            let f = TmpFile::new(&format!("valid-{kind}"), &bytes);
            let p = PthFile::open(&f.0).unwrap();
            assert_eq!(p.read_f64("w").unwrap(), [1.0, 3.0, 5.0, 2.0, 4.0, 6.0]);
        }
    }

    #[test]
    fn tensor_offsets_strides_and_sizes_that_overflow_are_errors() {
        let reach = "reach outside its storage";
        // (64 − 1)·2^62 overflows u64.
        let s = Spec {
            numel: 64,
            view: None,
            offset: 0,
            shape: vec![1, 64, 1, 1],
            stride: vec![0, 1 << 62, 0, 0],
        };
        read_fails("stride", &s, &floats(64), reach);
        // Offset 2^63 − 1 plus the elements read overflows u64 (zip), or
        // passes the storage (legacy, where the storage is small).
        let s = Spec {
            numel: 64,
            view: None,
            offset: i64::MAX,
            shape: vec![4],
            stride: vec![1],
        };
        read_fails("offset", &s, &floats(64), reach);
        // A legacy view at 2^63 − 1 plus a tensor offset of 2^63 − 1.
        let s = Spec {
            numel: 64,
            view: Some((i64::MAX, 4)),
            offset: i64::MAX,
            shape: vec![4],
            stride: vec![1],
        };
        read_fails("view", &s, &floats(64), "storage view");
        // The element range fits, its byte range (×4) does not.
        let s = Spec {
            numel: i64::MAX,
            view: None,
            offset: 1 << 62,
            shape: vec![4],
            stride: vec![1],
        };
        read_fails("bytes", &s, &floats(64), "overflows");
        // A storage declared as 2^41 elements (8 TiB) read over 4 TiB with
        // a 256-byte entry: refused before anything is allocated.
        let s = Spec {
            numel: 1 << 41,
            view: None,
            offset: 0,
            shape: vec![1, 64, 1, 1],
            stride: vec![0, 1 << 34, 0, 0],
        };
        read_fails("alloc", &s, &floats(64), "declares 2199023255552 elements");
        // 2^40 elements from one (stride 0).
        let s = Spec {
            numel: 1,
            view: None,
            offset: 0,
            shape: vec![1 << 20, 1 << 20],
            stride: vec![0, 0],
        };
        read_fails("broadcast", &s, &floats(1), "overlapping strides");
        // A shape whose element count overflows.
        let s = Spec {
            numel: 1,
            view: None,
            offset: 0,
            shape: vec![1 << 32, 1 << 32, 1 << 32],
            stride: vec![0, 0, 0],
        };
        read_fails("numel", &s, &floats(1), reach);
    }

    /// `pickle` fails with a message containing `want`, read from
    /// memory and as the object of a legacy file and the `data.pkl` of a zip.
    fn pickle_fails(tag: &str, pickle: &[u8], want: &str) {
        let e = PickleReader::new(Path::new("mem"), pickle)
            .load()
            .unwrap_err();
        assert!(e.to_string().contains(want), "{e}");
        for (kind, bytes) in [
            ("zip", zip_file(pickle, &[])),
            ("legacy", legacy_file(pickle, 0, &[])),
        ] {
            let f = TmpFile::new(&format!("{tag}-{kind}"), &bytes);
            let m = PthFile::open(&f.0).unwrap_err().to_string();
            assert!(
                m.contains(&*f.0.to_string_lossy()) && m.contains(want),
                "{kind}: {m}"
            );
        }
    }

    #[test]
    fn deep_nesting_is_an_error() {
        // A list nested 10^7 deep from 20 MB: the value limit stops it.
        let n = 10_000_000;
        let mut p = b"\x80\x02".to_vec();
        p.extend(std::iter::repeat_n(b']', n));
        p.extend(std::iter::repeat_n(b'a', n - 1));
        p.push(b'.');
        pickle_fails("deep", &p, "values");
        // Nested 5000 deep from 10 kB: the depth limit stops it.
        let n = 5000;
        let mut p = b"\x80\x02".to_vec();
        p.extend(std::iter::repeat_n(b']', n));
        p.extend(std::iter::repeat_n(b'a', n - 1));
        p.push(b'.');
        pickle_fails("deep2", &p, "nested more than 1000 deep");
        // Tuples and dictionaries nest too.
        let mut p = b"\x80\x02N".to_vec();
        p.extend(std::iter::repeat_n(b"\x85".as_slice(), n).flatten());
        p.push(b'.');
        pickle_fails("tuples", &p, "nested more than 1000 deep");
        // d = {0: {0: ... {0: None}}}, 1200 deep.
        let mut inner = b"N".to_vec();
        for _ in 0..1200 {
            inner = [b"}K\x00".as_slice(), &inner, b"s"].concat();
        }
        let p = [b"\x80\x02".as_slice(), &inner, b"."].concat();
        pickle_fails("dicts", &p, "nested more than 1000 deep");
        // At the limit: fine.
        let n = 1000;
        let mut p = b"\x80\x02".to_vec();
        p.extend(std::iter::repeat_n(b']', n));
        p.extend(std::iter::repeat_n(b'a', n - 1));
        p.push(b'.');
        PickleReader::new(Path::new("mem"), &p[..]).load().unwrap();
    }

    #[test]
    fn copies_that_double_a_value_are_counted() {
        // DUP a list and append it to itself, 40 times: 2^40 values from 84 bytes.
        let mut p = b"\x80\x02]".to_vec();
        p.extend(std::iter::repeat_n(b"2a".as_slice(), 40).flatten());
        p.push(b'.');
        pickle_fails("dup", &p, "more than 2097152 values");
        // The same through the memo: PUT the list, GET it and append.
        let mut p = b"\x80\x02]".to_vec();
        p.extend(std::iter::repeat_n(b"q\x00h\x00a".as_slice(), 40).flatten());
        p.push(b'.');
        pickle_fails("memo", &p, "more than 2097152 values");
        // A 1 MB string copied 200 times.
        let mut p = b"\x80\x02".to_vec();
        text(&mut p, &"x".repeat(1 << 20));
        p.extend(std::iter::repeat_n(b'2', 200));
        p.push(b'.');
        pickle_fails("strings", &p, "bytes of strings");
    }

    #[test]
    fn large_dictionaries_are_built_in_linear_time() {
        // 400,000 distinct keys set one by one, then each set again, then
        // 400,000 NaN keys (never equal to one another): each lookup is a
        // hash, not a scan.
        let n = 400_000;
        let mut p = b"\x80\x02}".to_vec();
        for i in 0..n {
            int(&mut p, i);
            p.extend(b"Ns");
        }
        for i in 0..n {
            int(&mut p, i);
            p.extend(b"\x88s");
        }
        p.push(b'.');
        let Value::Dict(d) = PickleReader::new(Path::new("mem"), &p[..]).load().unwrap() else {
            panic!("not a dict")
        };
        assert_eq!(d.items.len(), n as usize);
        assert!(d.items.iter().all(|(_, v)| *v == Value::Bool(true)));
        let mut p = b"\x80\x02}".to_vec();
        for _ in 0..n {
            p.push(b'G');
            p.extend(f64::NAN.to_be_bytes());
            p.extend(b"Ns");
        }
        p.push(b'.');
        let Value::Dict(d) = PickleReader::new(Path::new("mem"), &p[..]).load().unwrap() else {
            panic!("not a dict")
        };
        assert_eq!(d.items.len(), n as usize);
    }

    #[test]
    fn an_endless_pickle_stops_at_the_length_limit() {
        // FRAME opcodes forever: nothing is created, the length limit ends it.
        struct Frames(u64);
        impl Read for Frames {
            fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
                for b in buf.iter_mut() {
                    *b = if self.0.is_multiple_of(9) { 0x95 } else { 0 };
                    self.0 += 1;
                }
                Ok(buf.len())
            }
        }
        let e = PickleReader::new(Path::new("mem"), std::io::BufReader::new(Frames(0)))
            .load()
            .unwrap_err();
        assert!(e.to_string().contains("longer than 67108864 bytes"), "{e}");
    }

    #[test]
    fn integers_beyond_i64_are_not_truncated() {
        // 2^64 + 3 as a LONG1 of 9 bytes, as a tensor's stride.
        let p = b"\x80\x02\x8a\x09\x03\x00\x00\x00\x00\x00\x00\x00\x01.";
        let v = PickleReader::new(Path::new("mem"), &p[..]).load().unwrap();
        assert_eq!(v, Value::BigInt((1 << 64) + 3));
        let mut p = state_dict_pickle(&Spec {
            numel: 4,
            view: None,
            offset: 0,
            shape: vec![4],
            stride: vec![1],
        });
        let at = p
            .windows(7)
            .position(|w| w == b"J\x01\x00\x00\x00t\x89")
            .unwrap();
        p.splice(
            at..at + 5,
            b"\x8a\x09\x01\x00\x00\x00\x00\x00\x00\x00\x01"
                .iter()
                .copied(),
        );
        let e = PickleReader::new(Path::new("mem"), &p[..])
            .load()
            .unwrap_err();
        assert!(e.to_string().contains("not a tuple of ints"), "{e}");
    }
}
