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

use crate::error::{Error, Result};
use std::collections::HashMap;
use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

/// Element type of a storage.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
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
#[derive(Clone, Debug, PartialEq)]
struct StorageRef {
    key: String,
    dtype: DType,
    /// Elements of the root storage, as the persistent id records them.
    numel: u64,
    /// Legacy view storages: (element offset into the root, elements).
    view: Option<(u64, u64)>,
}

/// A tensor's metadata: where its elements are.
#[derive(Clone, Debug, PartialEq)]
struct TensorRef {
    storage: StorageRef,
    offset: u64,
    shape: Vec<usize>,
    stride: Vec<usize>,
}

/// A pickled value (only what a `state_dict` needs).
#[derive(Clone, Debug, PartialEq)]
enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    Str(String),
    Bytes(Vec<u8>),
    Tuple(Vec<Value>),
    List(Vec<Value>),
    Dict(Vec<(Value, Value)>),
    Global(String, String),
    Storage(StorageRef),
    Tensor(TensorRef),
    /// A call of a global this reader does not interpret (kept, never run).
    Object(String, String),
    Mark,
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

/// Most bytes one pickled string or the zip's `data.pkl` may take (a
/// `state_dict` pickle is kilobytes; this only bounds a corrupt length).
const MAX_PICKLE_BYTES: u64 = 64 << 20;

impl PthFile {
    /// Open `path` and read its tensor metadata (not the data). The top-level
    /// object must be a dictionary of tensors (other entries are ignored).
    pub fn open(path: &Path) -> Result<PthFile> {
        let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
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
        const MAGIC: i64 = 0x1950a86a20f9469cfc6c_i128 as i64;
        let magic_ok = matches!(magic, Value::Int(m) if m == MAGIC);
        if !magic_ok {
            return Err(Error::format(
                path,
                "not a PyTorch file (wrong magic number in the legacy header)",
            ));
        }
        if proto != Value::Int(1001) {
            return Err(Error::format(
                path,
                format!("legacy protocol version {proto:?}, expected 1001"),
            ));
        }
        if let Value::Dict(items) = &info {
            for (k, v) in items {
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
        // The storages as the object references them (their element type and size).
        let mut roots: HashMap<String, StorageRef> = HashMap::new();
        for (_, t) in &tensors {
            roots.insert(t.storage.key.clone(), t.storage.clone());
        }
        let mut offsets = HashMap::new();
        let mut at = pos;
        for k in keys {
            let key = match k {
                Value::Str(s) => s,
                other => {
                    return Err(Error::format(
                        path,
                        format!("legacy storage key {other:?} is not a string"),
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
        let numel: usize = t.shape.iter().product();
        let esz = t.storage.dtype.size();
        // Element range of the storage this tensor reads.
        let base = t.storage.view.map_or(0, |v| v.0) + t.offset;
        let span = if numel == 0 {
            0
        } else {
            1 + t
                .shape
                .iter()
                .zip(&t.stride)
                .map(|(&n, &s)| (n as u64 - 1) * s as u64)
                .sum::<u64>()
        };
        let limit = t.storage.view.map_or(t.storage.numel, |v| v.0 + v.1);
        if base + span > limit {
            return Err(Error::format(
                &self.path,
                format!(
                    "tensor {name}: elements {base}..{} outside its storage of {limit}",
                    base + span
                ),
            ));
        }
        let bytes = self.storage_bytes(&t.storage.key, base * esz as u64, span * esz as u64)?;
        let mut out = Vec::with_capacity(numel);
        let mut idx = vec![0usize; t.shape.len()];
        for _ in 0..numel {
            let off: usize = idx.iter().zip(&t.stride).map(|(i, s)| i * s).sum();
            out.push(t.storage.dtype.decode(&bytes[off * esz..]));
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

    /// `len` bytes of storage `key` from byte `start`.
    fn storage_bytes(&self, key: &str, start: u64, len: u64) -> Result<Vec<u8>> {
        let path = &self.path;
        let mut buf = vec![0u8; len as usize];
        match self.container {
            Container::Legacy => {
                let data = self.legacy_offsets[key];
                let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
                f.seek(SeekFrom::Start(data + start))
                    .map_err(|e| Error::io(path, e))?;
                f.read_exact(&mut buf)
                    .map_err(|_| truncated(path, key, data + start))?;
            }
            Container::Zip => {
                let f = File::open(path).map_err(|e| Error::io(path, e))?;
                let mut zip = zip::ZipArchive::new(BufReader::new(f))
                    .map_err(|e| Error::format(path, format!("zip container: {e}")))?;
                let entry = format!("{}data/{key}", self.zip_prefix);
                let mut e = zip
                    .by_name(&entry)
                    .map_err(|e| Error::format(path, format!("{entry}: {e}")))?;
                if e.size() < start + len {
                    return Err(Error::format(
                        path,
                        format!(
                            "{entry}: {} bytes, the tensor needs {}",
                            e.size(),
                            start + len
                        ),
                    ));
                }
                std::io::copy(&mut (&mut e).take(start), &mut std::io::sink())
                    .map_err(|err| Error::format(path, format!("{entry}: {err}")))?;
                e.read_exact(&mut buf)
                    .map_err(|err| Error::format(path, format!("{entry}: {err}")))?;
            }
        }
        Ok(buf)
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
    let Value::Dict(items) = obj else {
        return Err(Error::format(
            path,
            "the pickled object is not a dictionary of tensors (a state_dict)",
        ));
    };
    let mut out = Vec::new();
    for (k, v) in items {
        if let (Value::Str(name), Value::Tensor(t)) = (k, v) {
            out.push((name, t));
        }
    }
    Ok(out)
}

/// A pickle interpreter over a byte stream (see the module docs).
struct PickleReader<'p, R> {
    path: &'p Path,
    r: R,
    /// Bytes consumed so far (for messages and the legacy data offset).
    pos: u64,
    stack: Vec<Value>,
    memo: HashMap<u64, Value>,
}

impl<'p, R: Read> PickleReader<'p, R> {
    fn new(path: &'p Path, r: R) -> Self {
        PickleReader {
            path,
            r,
            pos: 0,
            stack: Vec::new(),
            memo: HashMap::new(),
        }
    }

    fn err(&self, what: impl std::fmt::Display) -> Error {
        Error::format(self.path, format!("pickle at byte {}: {what}", self.pos))
    }

    fn bytes(&mut self, n: u64) -> Result<Vec<u8>> {
        if n > MAX_PICKLE_BYTES {
            return Err(self.err(format!("a {n}-byte value")));
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

    fn pop(&mut self) -> Result<Value> {
        match self.stack.pop() {
            Some(Value::Mark) | None => Err(self.err("stack underflow")),
            Some(v) => Ok(v),
        }
    }
    fn pop_mark(&mut self) -> Result<Vec<Value>> {
        let at = self
            .stack
            .iter()
            .rposition(|v| *v == Value::Mark)
            .ok_or_else(|| self.err("no mark on the stack"))?;
        let items = self.stack.split_off(at + 1);
        self.stack.pop();
        Ok(items)
    }
    fn top(&mut self) -> Result<&mut Value> {
        let at = self.pos;
        match self.stack.last_mut() {
            Some(Value::Mark) | None => Err(Error::format(
                self.path,
                format!("pickle at byte {at}: stack underflow"),
            )),
            Some(v) => Ok(v),
        }
    }
    fn memo_put(&mut self, k: u64) -> Result<()> {
        let v = self
            .stack
            .last()
            .cloned()
            .ok_or_else(|| self.err("memo of an empty stack"))?;
        self.memo.insert(k, v);
        Ok(())
    }
    fn memo_get(&mut self, k: u64) -> Result<()> {
        let v = self
            .memo
            .get(&k)
            .cloned()
            .ok_or_else(|| self.err(format!("memo key {k} not set")))?;
        self.stack.push(v);
        Ok(())
    }
    fn set_items(&mut self, items: Vec<Value>) -> Result<()> {
        if !items.len().is_multiple_of(2) {
            return Err(self.err("odd number of dictionary items"));
        }
        let (at, path) = (self.pos, self.path);
        match self.top()? {
            Value::Dict(d) => {
                let mut it = items.into_iter();
                while let (Some(k), Some(v)) = (it.next(), it.next()) {
                    match d.iter_mut().find(|(dk, _)| *dk == k) {
                        Some(e) => e.1 = v,
                        None => d.push((k, v)),
                    }
                }
                Ok(())
            }
            Value::Object(..) => Ok(()),
            other => Err(Error::format(
                path,
                format!("pickle at byte {at}: set items on {other:?}"),
            )),
        }
    }
    fn append(&mut self, items: Vec<Value>) -> Result<()> {
        let (at, path) = (self.pos, self.path);
        match self.top()? {
            Value::List(l) => {
                l.extend(items);
                Ok(())
            }
            Value::Object(..) => Ok(()),
            other => Err(Error::format(
                path,
                format!("pickle at byte {at}: append to {other:?}"),
            )),
        }
    }

    /// Read one pickle (up to and including STOP) and return its value.
    fn load(&mut self) -> Result<Value> {
        self.stack.clear();
        self.memo.clear();
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
                b'(' => self.stack.push(Value::Mark),
                b'}' => self.stack.push(Value::Dict(Vec::new())),
                b']' => self.stack.push(Value::List(Vec::new())),
                b')' => self.stack.push(Value::Tuple(Vec::new())),
                b't' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Value::Tuple(items));
                }
                b'l' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Value::List(items));
                }
                b'd' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Value::Dict(Vec::new()));
                    self.set_items(items)?;
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    if self.stack.len() < n {
                        return Err(self.err("stack underflow"));
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    if items.contains(&Value::Mark) {
                        return Err(self.err("mark inside a tuple"));
                    }
                    self.stack.push(Value::Tuple(items));
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
                    self.stack.push(Value::Int(v));
                }
                b'M' => {
                    let v = self.u16()? as i64;
                    self.stack.push(Value::Int(v));
                }
                b'J' => {
                    let v = self.u32()? as i32 as i64;
                    self.stack.push(Value::Int(v));
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
                    self.stack.push(Value::Int(v as i64));
                }
                b'N' => self.stack.push(Value::None),
                0x88 => self.stack.push(Value::Bool(true)),
                0x89 => self.stack.push(Value::Bool(false)),
                b'G' => {
                    let b = self.bytes(8)?;
                    let v = f64::from_be_bytes(b[..8].try_into().expect("8 bytes"));
                    self.stack.push(Value::Float(v));
                }
                b'X' => {
                    let n = self.u32()? as u64;
                    let s = self.text(n)?;
                    self.stack.push(Value::Str(s));
                }
                0x8c => {
                    let n = self.u8()? as u64;
                    let s = self.text(n)?;
                    self.stack.push(Value::Str(s));
                }
                0x8d => {
                    let n = self.u64()?;
                    let s = self.text(n)?;
                    self.stack.push(Value::Str(s));
                }
                b'U' => {
                    let n = self.u8()? as u64;
                    let v = self.py2_str(n)?;
                    self.stack.push(v);
                }
                b'T' => {
                    let n = self.u32()? as u64;
                    let v = self.py2_str(n)?;
                    self.stack.push(v);
                }
                b'C' => {
                    let n = self.u8()? as u64;
                    let b = self.bytes(n)?;
                    self.stack.push(Value::Bytes(b));
                }
                b'B' => {
                    let n = self.u32()? as u64;
                    let b = self.bytes(n)?;
                    self.stack.push(Value::Bytes(b));
                }
                b'c' => {
                    let module = self.line()?;
                    let name = self.line()?;
                    self.stack.push(Value::Global(module, name));
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    match (module, name) {
                        (Value::Str(m), Value::Str(n)) => self.stack.push(Value::Global(m, n)),
                        _ => return Err(self.err("STACK_GLOBAL of non-strings")),
                    }
                }
                b'R' | 0x81 => {
                    let args = self.pop()?;
                    let f = self.pop()?;
                    let v = self.call(f, args)?;
                    self.stack.push(v);
                }
                b'b' => {
                    // BUILD: object state (OrderedDict `_metadata`, …) is not needed.
                    self.pop()?;
                    self.top()?;
                }
                b'Q' => {
                    let pid = self.pop()?;
                    let v = self.persistent(pid)?;
                    self.stack.push(v);
                }
                b's' => {
                    let v = self.pop()?;
                    let k = self.pop()?;
                    self.set_items(vec![k, v])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    self.set_items(items)?;
                }
                b'a' => {
                    let v = self.pop()?;
                    self.append(vec![v])?;
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    self.append(items)?;
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
                    let v = self.top()?.clone();
                    self.stack.push(v);
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
            return Err(self.err(format!("persistent id {pid:?} is not a tuple")));
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
                        _ => return Err(self.err(format!("storage view {v:?}"))),
                    },
                    _ => return Err(self.err(format!("persistent id {t:?}"))),
                };
                Ok(Value::Storage(StorageRef {
                    key: key.clone(),
                    dtype,
                    numel: *n as u64,
                    view,
                }))
            }
            _ => Err(self.err(format!("persistent id {t:?} is not a storage"))),
        }
    }

    /// REDUCE / NEWOBJ: interpret the calls a state_dict needs; keep others
    /// as opaque objects.
    fn call(&mut self, f: Value, args: Value) -> Result<Value> {
        let Value::Global(module, name) = f else {
            return Err(self.err(format!("call of {f:?}")));
        };
        let Value::Tuple(args) = args else {
            return Err(self.err(format!("{module}.{name} called with {args:?}")));
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
                match args.as_slice() {
                    [Value::Storage(s), Value::Int(off), size, stride, ..] if *off >= 0 => {
                        let (Some(shape), Some(stride)) = (ints(size), ints(stride)) else {
                            return Err(self.err("tensor size or stride is not a tuple of ints"));
                        };
                        if shape.len() != stride.len() {
                            return Err(self.err("tensor size and stride differ in length"));
                        }
                        Ok(Value::Tensor(TensorRef {
                            storage: s.clone(),
                            offset: *off as u64,
                            shape,
                            stride,
                        }))
                    }
                    _ => Err(self.err(format!("{module}.{name} with arguments {args:?}"))),
                }
            }
            ("collections", "OrderedDict") => match args.as_slice() {
                [] => Ok(Value::Dict(Vec::new())),
                [Value::List(pairs)] => {
                    let mut d = Vec::new();
                    for p in pairs {
                        match p {
                            Value::List(kv) | Value::Tuple(kv) if kv.len() == 2 => {
                                d.push((kv[0].clone(), kv[1].clone()))
                            }
                            _ => return Err(self.err("OrderedDict item is not a pair")),
                        }
                    }
                    Ok(Value::Dict(d))
                }
                _ => Err(self.err("OrderedDict with unexpected arguments")),
            },
            _ => Ok(Value::Object(module, name)),
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
        let want = Value::Dict(vec![
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
        ]);
        assert_eq!(v, want);
        // Cut short: an error naming the offset, never a panic.
        for cut in 0..bytes.len() {
            assert!(PickleReader::new(path, &bytes[..cut]).load().is_err());
        }
    }
}
