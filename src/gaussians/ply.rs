//! PLY files: Gaussians in the Inria layout, and plain point clouds.
//!
//! **Gaussians.** One `vertex` element with these properties, in this order when written:
//! `x y z nx ny nz f_dc_0 f_dc_1 f_dc_2 f_rest_0 .. f_rest_{3(K-1)-1} opacity scale_0 scale_1
//! scale_2 rot_0 rot_1 rot_2 rot_3` (62 properties at SH degree 3), binary little endian.
//! The normals are written as zeros, as upstream does. `f_rest` is **channel-major** in the
//! file (all K-1 coefficients of red, then green, then blue), while [`Gaussians::sh`] is
//! coefficient-major (`[N, K, 3]`); the conversion is `f_rest_{c(K-1) + (k-1)} = sh[i, k, c]`.
//! Values are written as `float` for `Gaussians<f32>` (the upstream files) and as `double` for
//! `Gaussians<f64>`, so a write/read round trip is bit-exact in both precisions.
//!
//! Reading is by property name: any property order, `float` or `double` (or integer types),
//! no normals, and fewer `f_rest` (a lower SH degree, found from their count) are accepted;
//! unknown extra properties are ignored. `ascii` and `binary_little_endian` / `binary_big_endian`
//! bodies are read. Elements before `vertex` must not have list properties (they are skipped).
//!
//! **Point clouds** (`points3d.ply`): `x y z` and optionally `red green blue` (`uchar`).

use super::{Gaussians, Group};
use crate::error::{Error, Result};
use crate::math::Real;
use std::path::Path;

/// A plain point cloud, as `points3d.ply` holds it.
#[derive(Clone, Debug, PartialEq)]
pub struct PointCloud {
    /// Positions `[N, 3]`.
    pub xyz: Vec<f64>,
    /// Colours `[N, 3]` as bytes, when the file has them.
    pub rgb: Option<Vec<u8>>,
}

impl PointCloud {
    /// Number of points.
    pub fn len(&self) -> usize {
        self.xyz.len() / 3
    }
    /// True when there are no points.
    pub fn is_empty(&self) -> bool {
        self.xyz.is_empty()
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Scalar {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl Scalar {
    fn parse(s: &str) -> Option<Scalar> {
        Some(match s {
            "char" | "int8" => Scalar::I8,
            "uchar" | "uint8" => Scalar::U8,
            "short" | "int16" => Scalar::I16,
            "ushort" | "uint16" => Scalar::U16,
            "int" | "int32" => Scalar::I32,
            "uint" | "uint32" => Scalar::U32,
            "float" | "float32" => Scalar::F32,
            "double" | "float64" => Scalar::F64,
            _ => return None,
        })
    }
    fn size(self) -> usize {
        match self {
            Scalar::I8 | Scalar::U8 => 1,
            Scalar::I16 | Scalar::U16 => 2,
            Scalar::I32 | Scalar::U32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
    fn decode(self, b: &[u8], little: bool) -> f64 {
        macro_rules! num {
            ($t:ty, $n:expr) => {{
                let mut a = [0u8; $n];
                a.copy_from_slice(&b[..$n]);
                if little {
                    <$t>::from_le_bytes(a) as f64
                } else {
                    <$t>::from_be_bytes(a) as f64
                }
            }};
        }
        match self {
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U8 => b[0] as f64,
            Scalar::I16 => num!(i16, 2),
            Scalar::U16 => num!(u16, 2),
            Scalar::I32 => num!(i32, 4),
            Scalar::U32 => num!(u32, 4),
            Scalar::F32 => num!(f32, 4),
            Scalar::F64 => num!(f64, 8),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Encoding {
    Ascii,
    BinaryLe,
    BinaryBe,
}

#[derive(Debug)]
struct Property {
    name: String,
    /// `None` for a list property (only allowed in skipped ASCII elements).
    ty: Option<Scalar>,
}

#[derive(Debug)]
struct Element {
    name: String,
    count: usize,
    props: Vec<Property>,
}

/// The `vertex` element as a row-major table of f64 values (every PLY scalar type
/// converts to f64 exactly).
struct VertexTable {
    names: Vec<String>,
    count: usize,
    data: Vec<f64>,
}

impl VertexTable {
    fn column(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }
}

fn parse_ply(path: &Path, bytes: &[u8]) -> Result<VertexTable> {
    let fmt = |what: String| Error::format(path, what);
    // Header: lines up to and including "end_header\n".
    let mut pos = 0usize;
    let mut lines = Vec::new();
    loop {
        let Some(nl) = bytes[pos..].iter().position(|&b| b == b'\n') else {
            return Err(fmt("PLY header has no `end_header` line".into()));
        };
        let raw = &bytes[pos..pos + nl];
        pos += nl + 1;
        let line = std::str::from_utf8(raw)
            .map_err(|_| fmt(format!("PLY header line {} is not text", lines.len() + 1)))?
            .trim_end_matches('\r')
            .to_string();
        let done = line.trim() == "end_header";
        lines.push(line);
        if done {
            break;
        }
        if lines.len() > 100_000 {
            return Err(fmt("PLY header is too long".into()));
        }
    }
    if lines.first().map(|l| l.trim()) != Some("ply") {
        return Err(fmt("not a PLY file (first line is not `ply`)".into()));
    }
    let mut encoding = None;
    let mut elements: Vec<Element> = Vec::new();
    for (ln, line) in lines.iter().enumerate().skip(1) {
        let toks: Vec<&str> = line.split_whitespace().collect();
        let bad = || fmt(format!("bad PLY header line {}: `{}`", ln + 1, line));
        match toks.first().copied() {
            None | Some("comment") | Some("obj_info") | Some("end_header") => {}
            Some("format") => {
                if toks.len() != 3 {
                    return Err(bad());
                }
                encoding = Some(match toks[1] {
                    "ascii" => Encoding::Ascii,
                    "binary_little_endian" => Encoding::BinaryLe,
                    "binary_big_endian" => Encoding::BinaryBe,
                    _ => return Err(bad()),
                });
            }
            Some("element") => {
                if toks.len() != 3 {
                    return Err(bad());
                }
                let count = toks[2].parse::<usize>().map_err(|_| bad())?;
                elements.push(Element {
                    name: toks[1].to_string(),
                    count,
                    props: vec![],
                });
            }
            Some("property") => {
                let el = elements.last_mut().ok_or_else(bad)?;
                if toks.len() == 3 {
                    let ty = Scalar::parse(toks[1]).ok_or_else(bad)?;
                    el.props.push(Property {
                        name: toks[2].to_string(),
                        ty: Some(ty),
                    });
                } else if toks.len() == 5 && toks[1] == "list" {
                    Scalar::parse(toks[2]).ok_or_else(bad)?;
                    Scalar::parse(toks[3]).ok_or_else(bad)?;
                    el.props.push(Property {
                        name: toks[4].to_string(),
                        ty: None,
                    });
                } else {
                    return Err(bad());
                }
            }
            Some(_) => return Err(bad()),
        }
    }
    let encoding = encoding.ok_or_else(|| fmt("PLY header has no `format` line".into()))?;
    let vi = elements
        .iter()
        .position(|e| e.name == "vertex")
        .ok_or_else(|| fmt("PLY header has no `vertex` element".into()))?;
    let body = &bytes[pos..];
    let vertex = &elements[vi];
    if let Some(p) = vertex.props.iter().find(|p| p.ty.is_none()) {
        return Err(Error::field(
            path,
            format!("vertex.{}", p.name),
            "list properties are not supported in the vertex element",
        ));
    }
    let types: Vec<Scalar> = vertex.props.iter().map(|p| p.ty.unwrap()).collect();
    let names: Vec<String> = vertex.props.iter().map(|p| p.name.clone()).collect();
    let np = types.len();
    let count = vertex.count;
    // Guard the allocation against absurd counts in a short file.
    let min_row = match encoding {
        Encoding::Ascii => np.max(1) * 2 - 1,
        _ => types.iter().map(|t| t.size()).sum::<usize>(),
    };
    if count.saturating_mul(min_row) > body.len() {
        let row = body.len().checked_div(min_row).unwrap_or(0);
        return Err(fmt(format!(
            "truncated PLY body at vertex {row} (header declares {count})"
        )));
    }
    // The same guard for every element before `vertex`: each row of an
    // ASCII body is a line of at least one byte, a binary row its size.
    for e in &elements[..vi] {
        let row = match encoding {
            Encoding::Ascii => 1,
            _ => e
                .props
                .iter()
                .map(|p| p.ty.map_or(1, |t| t.size()))
                .sum::<usize>(),
        };
        if e.count.saturating_mul(row) > body.len() {
            return Err(fmt(format!(
                "truncated PLY body: element `{}` declares {} rows, more than the file holds",
                e.name, e.count
            )));
        }
    }
    let mut data = Vec::with_capacity(count * np);
    match encoding {
        Encoding::Ascii => {
            let text =
                std::str::from_utf8(body).map_err(|_| fmt("ASCII PLY body is not text".into()))?;
            let mut lines = text.lines().filter(|l| !l.trim().is_empty());
            for e in &elements[..vi] {
                for k in 0..e.count {
                    if lines.next().is_none() {
                        return Err(fmt(format!(
                            "truncated PLY body at element `{}` row {k} (header declares {})",
                            e.name, e.count
                        )));
                    }
                }
            }
            for k in 0..count {
                let line = lines
                    .next()
                    .ok_or_else(|| fmt(format!("truncated PLY body at vertex {k}")))?;
                let toks: Vec<&str> = line.split_whitespace().collect();
                if toks.len() < np {
                    return Err(fmt(format!(
                        "vertex {k} has {} values, expected {np}",
                        toks.len()
                    )));
                }
                for (j, t) in toks[..np].iter().enumerate() {
                    let v = t.parse::<f64>().map_err(|_| {
                        Error::field(
                            path,
                            format!("vertex.{}", names[j]),
                            format!("vertex {k}: `{t}` is not a number"),
                        )
                    })?;
                    data.push(v);
                }
            }
        }
        Encoding::BinaryLe | Encoding::BinaryBe => {
            let little = encoding == Encoding::BinaryLe;
            let mut off = 0usize;
            for e in &elements[..vi] {
                if e.props.iter().any(|p| p.ty.is_none()) {
                    return Err(fmt(format!(
                        "element `{}` before `vertex` has a list property",
                        e.name
                    )));
                }
                let row: usize = e.props.iter().map(|p| p.ty.unwrap().size()).sum();
                off = off.saturating_add(row.saturating_mul(e.count));
            }
            if off > body.len() {
                return Err(fmt("truncated PLY body before the vertex element".into()));
            }
            let row: usize = types.iter().map(|t| t.size()).sum();
            for k in 0..count {
                if off + row > body.len() {
                    return Err(fmt(format!(
                        "truncated PLY body at vertex {k} (header declares {count})"
                    )));
                }
                for t in &types {
                    data.push(t.decode(&body[off..], little));
                    off += t.size();
                }
            }
        }
    }
    Ok(VertexTable { names, count, data })
}

fn require(path: &Path, t: &VertexTable, name: &str) -> Result<usize> {
    t.column(name)
        .ok_or_else(|| Error::field(path, format!("vertex.{name}"), "missing property"))
}

/// The PLY properties of `group` with `k` SH coefficients, in file order:
/// `x y z`, `f_dc_0..2 f_rest_0..` (channel-major), `opacity`,
/// `scale_0..2`, `rot_0..3`.
fn properties(group: Group, k: usize) -> Vec<String> {
    fn numbered(prefix: &'static str, count: usize) -> impl Iterator<Item = String> {
        (0..count).map(move |i| format!("{prefix}{i}"))
    }
    match group {
        Group::Xyz => ["x", "y", "z"].map(String::from).to_vec(),
        Group::Sh => numbered("f_dc_", 3)
            .chain(numbered("f_rest_", 3 * (k - 1)))
            .collect(),
        Group::Opacity => vec!["opacity".to_string()],
        Group::Scaling => numbered("scale_", 3).collect(),
        Group::Rotation => numbered("rot_", 4).collect(),
    }
}

/// Where the `j`-th property of `group` (in [`properties`]' order) goes in a
/// Gaussian's row: the identity except for `f_rest`, which the file holds
/// channel-major and [`Gaussians::sh`] coefficient-major
/// (`f_rest_{c(K-1) + (k-1)} = sh[i, k, c]`).
fn row_index(group: Group, k: usize, j: usize) -> usize {
    if group != Group::Sh || j < 3 {
        return j;
    }
    let (channel, coeff) = ((j - 3) / (k - 1), (j - 3) % (k - 1) + 1);
    3 * coeff + channel
}

/// Parse Gaussians from PLY bytes; `path` names the source in errors.
pub fn decode_gaussians<T: Real>(path: &Path, bytes: &[u8]) -> Result<Gaussians<T>> {
    let t = parse_ply(path, bytes)?;
    // Every property but `f_rest` is required (checked in file order).
    for group in Group::ALL {
        for name in properties(group, 1) {
            require(path, &t, &name)?;
        }
    }
    let n_rest = (0..)
        .take_while(|i| t.column(&format!("f_rest_{i}")).is_some())
        .count();
    if t.names.iter().any(|n| {
        n.strip_prefix("f_rest_")
            .and_then(|s| s.parse::<usize>().ok())
            .is_some_and(|i| i >= n_rest)
    }) {
        return Err(Error::field(
            path,
            format!("vertex.f_rest_{n_rest}"),
            "missing property (f_rest indices are not contiguous)",
        ));
    }
    if n_rest % 3 != 0 {
        return Err(Error::field(
            path,
            "vertex.f_rest_*",
            format!("{n_rest} properties is not a multiple of 3"),
        ));
    }
    let k = n_rest / 3 + 1;
    let degree = (0..=super::MAX_STORED_SH_DEGREE)
        .find(|d| (d + 1) * (d + 1) == k)
        .ok_or_else(|| {
            Error::field(
                path,
                "vertex.f_rest_*",
                format!("{n_rest} properties do not make a whole SH degree"),
            )
        })?;
    let columns = Group::ALL.map(|group| {
        properties(group, k)
            .iter()
            .map(|name| require(path, &t, name))
            .collect::<Result<Vec<usize>>>()
    });
    let n = t.count;
    let np = t.names.len();
    let mut g = Gaussians::<T>::empty(degree);
    for ((group, v), cols) in g.groups_mut().into_iter().zip(columns) {
        let cols = cols?;
        *v = vec![T::ZERO; n * cols.len()];
        for (i, out) in v.chunks_exact_mut(cols.len()).enumerate() {
            let row = &t.data[i * np..(i + 1) * np];
            for (j, &c) in cols.iter().enumerate() {
                out[row_index(group, k, j)] = T::from_f64(row[c]);
            }
        }
    }
    Ok(g)
}

/// Read Gaussians from a PLY file (see the module documentation for what is accepted).
pub fn read_gaussians<T: Real>(path: &Path) -> Result<Gaussians<T>> {
    let bytes = crate::io::read(path)?;
    decode_gaussians(path, &bytes)
}

/// The Inria PLY bytes for `g` (`float` properties for f32, `double` for f64).
pub fn encode_gaussians<T: Real>(g: &Gaussians<T>) -> Result<Vec<u8>> {
    g.validate()?;
    let k = g.coeffs();
    let ty = if T::SIZE == 4 { "float" } else { "double" };
    let normals = ["nx", "ny", "nz"];
    let mut names: Vec<String> = Vec::new();
    for group in Group::ALL {
        names.extend(properties(group, k));
        if group == Group::Xyz {
            names.extend(normals.map(String::from));
        }
    }
    let n = g.len();
    let mut out =
        format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n").into_bytes();
    for name in &names {
        out.extend(format!("property {ty} {name}\n").bytes());
    }
    out.extend(b"end_header\n");
    out.reserve(n * names.len() * T::SIZE);
    for i in 0..n {
        for group in Group::ALL {
            let w = g.width(group);
            let row = &g.group(group)[i * w..(i + 1) * w];
            for j in 0..w {
                row[row_index(group, k, j)].write_le(&mut out);
            }
            if group == Group::Xyz {
                for _ in normals {
                    T::ZERO.write_le(&mut out);
                }
            }
        }
    }
    Ok(out)
}

/// Write Gaussians as an Inria PLY file, atomically.
pub fn write_gaussians<T: Real>(path: &Path, g: &Gaussians<T>) -> Result<()> {
    crate::io::write_atomic(path, &encode_gaussians(g)?)
}

/// Parse a point cloud (`x y z`, optional `red green blue`) from PLY bytes.
pub fn decode_points(path: &Path, bytes: &[u8]) -> Result<PointCloud> {
    let t = parse_ply(path, bytes)?;
    let xyz_c: Vec<usize> = ["x", "y", "z"]
        .iter()
        .map(|n| require(path, &t, n))
        .collect::<Result<_>>()?;
    let rgb_c: Vec<Option<usize>> = ["red", "green", "blue"]
        .iter()
        .map(|n| t.column(n))
        .collect();
    let has_rgb = match rgb_c.iter().filter(|c| c.is_some()).count() {
        0 => false,
        3 => true,
        _ => {
            return Err(Error::field(
                path,
                "vertex.red/green/blue",
                "only some of the colour properties are present",
            ))
        }
    };
    let np = t.names.len();
    let mut xyz = Vec::with_capacity(3 * t.count);
    let mut rgb = Vec::new();
    for i in 0..t.count {
        let row = &t.data[i * np..(i + 1) * np];
        for &c in &xyz_c {
            if !row[c].is_finite() {
                return Err(Error::field(
                    path,
                    format!("vertex.{}", t.names[c]),
                    format!("vertex {i}: non-finite value"),
                ));
            }
            xyz.push(row[c]);
        }
        if has_rgb {
            for c in rgb_c.iter().flatten() {
                let v = row[*c];
                if !(0.0..=255.0).contains(&v) || v.fract() != 0.0 {
                    return Err(Error::field(
                        path,
                        format!("vertex.{}", t.names[*c]),
                        format!("vertex {i}: {v} is not a byte"),
                    ));
                }
                rgb.push(v as u8);
            }
        }
    }
    Ok(PointCloud {
        xyz,
        rgb: has_rgb.then_some(rgb),
    })
}

/// Read a point cloud PLY file.
pub fn read_points(path: &Path) -> Result<PointCloud> {
    let bytes = crate::io::read(path)?;
    decode_points(path, &bytes)
}

/// Write a point cloud as binary PLY (`float x y z`, `uchar red green blue` when present;
/// positions are rounded to f32, as upstream stores them), atomically.
pub fn write_points(path: &Path, pc: &PointCloud) -> Result<()> {
    let n = pc.len();
    let mut out = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\nproperty float z\n"
    )
    .into_bytes();
    if pc.rgb.is_some() {
        out.extend(b"property uchar red\nproperty uchar green\nproperty uchar blue\n");
    }
    out.extend(b"end_header\n");
    for i in 0..n {
        for &v in &pc.xyz[3 * i..3 * i + 3] {
            out.extend((v as f32).to_le_bytes());
        }
        if let Some(rgb) = &pc.rgb {
            out.extend(&rgb[3 * i..3 * i + 3]);
        }
    }
    crate::io::write_atomic(path, &out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::Rng;

    fn random<T: Real>(n: usize, degree: usize, seed: u64) -> Gaussians<T> {
        let mut r = Rng::new(seed);
        let k = Gaussians::<T>::coeffs_for_degree(degree);
        let mut v = |m: usize| -> Vec<T> { (0..m).map(|_| T::from_f64(r.normal())).collect() };
        Gaussians {
            max_sh_degree: degree,
            xyz: v(3 * n),
            sh: v(3 * k * n),
            scaling: v(3 * n),
            rotation: v(4 * n),
            opacity: v(n),
        }
    }

    fn bits<T: Real>(g: &Gaussians<T>) -> Vec<u64> {
        [&g.xyz, &g.sh, &g.scaling, &g.rotation, &g.opacity]
            .iter()
            .flat_map(|a| a.iter().map(|v| v.bits()))
            .collect()
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let p = Path::new("mem.ply");
        for degree in 0..=3 {
            let g = random::<f32>(7, degree, degree as u64);
            let back: Gaussians<f32> = decode_gaussians(p, &encode_gaussians(&g).unwrap()).unwrap();
            assert_eq!(back.max_sh_degree, degree);
            assert_eq!(bits(&back), bits(&g));
            let g = random::<f64>(5, degree, 10 + degree as u64);
            let back: Gaussians<f64> = decode_gaussians(p, &encode_gaussians(&g).unwrap()).unwrap();
            assert_eq!(bits(&back), bits(&g));
        }
        // 62 properties at degree 3, as the Inria files.
        let bytes = encode_gaussians(&random::<f32>(1, 3, 0)).unwrap();
        let header = String::from_utf8_lossy(&bytes[..bytes.len() - 62 * 4]);
        assert_eq!(header.matches("property float").count(), 62);
    }

    #[test]
    fn f_rest_is_channel_major_in_the_file() {
        // One Gaussian at degree 1: sh[k][c] = 10k + c.
        let mut g = random::<f32>(1, 1, 3);
        for kk in 0..4 {
            for c in 0..3 {
                g.sh[3 * kk + c] = (10 * kk + c) as f32;
            }
        }
        let bytes = encode_gaussians(&g).unwrap();
        let body = &bytes[bytes.len() - 26 * 4..];
        let f = |j: usize| f32::from_le_bytes(body[4 * j..4 * j + 4].try_into().unwrap());
        // x y z nx ny nz f_dc_0..2 f_rest_0..8
        let rest: Vec<f32> = (9..18).map(f).collect();
        assert_eq!(
            rest,
            vec![10.0, 20.0, 30.0, 11.0, 21.0, 31.0, 12.0, 22.0, 32.0]
        );
    }

    /// Build an ASCII or binary PLY by hand with the given property order and type.
    fn hand_ply(g: &Gaussians<f64>, order: &[String], ty: &str, ascii: bool) -> Vec<u8> {
        let k = g.coeffs();
        let value = |i: usize, name: &str| -> f64 {
            let idx = |p: &str| name.strip_prefix(p).map(|s| s.parse::<usize>().unwrap());
            match name {
                "x" | "y" | "z" => g.xyz[3 * i + "xyz".find(name).unwrap()],
                "nx" | "ny" | "nz" => 0.0,
                "opacity" => g.opacity[i],
                _ => {
                    if let Some(c) = idx("f_dc_") {
                        g.sh[3 * k * i + c]
                    } else if let Some(j) = idx("f_rest_") {
                        let (c, kk) = (j / (k - 1), j % (k - 1) + 1);
                        g.sh[3 * k * i + 3 * kk + c]
                    } else if let Some(j) = idx("scale_") {
                        g.scaling[3 * i + j]
                    } else if let Some(j) = idx("rot_") {
                        g.rotation[4 * i + j]
                    } else {
                        7.0
                    }
                }
            }
        };
        let fmt = if ascii {
            "ascii"
        } else {
            "binary_little_endian"
        };
        let mut out = format!(
            "ply\nformat {fmt} 1.0\ncomment hand made\nelement vertex {}\n",
            g.len()
        )
        .into_bytes();
        for n in order {
            out.extend(format!("property {ty} {n}\n").bytes());
        }
        out.extend(b"end_header\n");
        for i in 0..g.len() {
            for n in order {
                let v = value(i, n);
                if ascii {
                    out.extend(format!("{v:e} ").bytes());
                } else if ty == "double" {
                    out.extend(v.to_le_bytes());
                } else {
                    out.extend((v as f32).to_le_bytes());
                }
            }
            if ascii {
                out.push(b'\n');
            }
        }
        out
    }

    fn names(degree: usize, normals: bool) -> Vec<String> {
        let k = (degree + 1) * (degree + 1);
        let mut v: Vec<String> = ["x", "y", "z"].iter().map(|s| s.to_string()).collect();
        if normals {
            v.extend(["nx", "ny", "nz"].iter().map(|s| s.to_string()));
        }
        v.extend((0..3).map(|i| format!("f_dc_{i}")));
        v.extend((0..3 * (k - 1)).map(|i| format!("f_rest_{i}")));
        v.push("opacity".into());
        v.extend((0..3).map(|i| format!("scale_{i}")));
        v.extend((0..4).map(|i| format!("rot_{i}")));
        v
    }

    #[test]
    fn reordered_double_ascii_and_without_normals() {
        let p = Path::new("hand.ply");
        for degree in [0, 2, 3] {
            let g = random::<f64>(4, degree, 40 + degree as u64);
            let mut order = names(degree, false);
            order.push("extra".into());
            let mut r = Rng::new(9);
            r.shuffle(&mut order);
            let back: Gaussians<f64> =
                decode_gaussians(p, &hand_ply(&g, &order, "double", false)).unwrap();
            assert_eq!(bits(&back), bits(&g));
            let back: Gaussians<f64> =
                decode_gaussians(p, &hand_ply(&g, &order, "double", true)).unwrap();
            assert_eq!(
                bits(&back),
                bits(&g),
                "ascii, {{:e}} prints the shortest round-trip form"
            );
            // float properties read into f64 are the f32 values.
            let back: Gaussians<f64> =
                decode_gaussians(p, &hand_ply(&g, &order, "float", false)).unwrap();
            let want: Vec<f64> = g.xyz.iter().map(|&v| v as f32 as f64).collect();
            assert_eq!(back.xyz, want);
        }
    }

    #[test]
    fn missing_property_is_named() {
        let g = random::<f64>(2, 1, 5);
        let order: Vec<String> = names(1, true)
            .into_iter()
            .filter(|n| n != "rot_2")
            .collect();
        let e = decode_gaussians::<f32>(Path::new("a.ply"), &hand_ply(&g, &order, "float", false))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("a.ply") && e.contains("rot_2") && e.contains("missing"),
            "{e}"
        );
        let order: Vec<String> = names(1, true)
            .into_iter()
            .filter(|n| n != "f_rest_4")
            .collect();
        let e = decode_gaussians::<f32>(Path::new("a.ply"), &hand_ply(&g, &order, "float", false))
            .unwrap_err()
            .to_string();
        assert!(e.contains("f_rest_4"), "{e}");
    }

    #[test]
    fn truncation_at_every_offset_is_an_error() {
        let g = random::<f32>(3, 1, 6);
        let bytes = encode_gaussians(&g).unwrap();
        let p = Path::new("t.ply");
        for cut in 0..bytes.len() {
            let e = decode_gaussians::<f32>(p, &bytes[..cut])
                .unwrap_err()
                .to_string();
            assert!(e.starts_with("t.ply: "), "{e}");
        }
        let header_len = bytes.len() - 3 * 26 * 4;
        let e = decode_gaussians::<f32>(p, &bytes[..header_len + 26 * 4 + 5])
            .unwrap_err()
            .to_string();
        assert!(e.contains("truncated PLY body at vertex 1"), "{e}");
    }

    #[test]
    fn garbage_headers_are_errors() {
        let p = Path::new("g.ply");
        let good = String::from_utf8(encode_gaussians(&random::<f32>(0, 0, 1)).unwrap()).unwrap();
        let cases = [
            "".to_string(),
            "\u{0}\u{1}\u{2}garbage\n".to_string(),
            "ply\nend_header\n".to_string(),
            good.replace(
                "format binary_little_endian 1.0",
                "format binary_middle_endian 1.0",
            ),
            good.replace("element vertex 0", "element vertex -3"),
            good.replace("property float x", "property quad x"),
            good.replace("property float y", "propertyfloat y"),
            good.replace("element vertex 0", "element vertex 99999999999999"),
            good.replace("end_header\n", ""),
            good.replace("ply\n", "PLY\n"),
        ];
        for c in &cases {
            assert!(
                decode_gaussians::<f32>(p, c.as_bytes()).is_err(),
                "accepted {c:?}"
            );
        }
        let mut r = Rng::new(2);
        for _ in 0..200 {
            let mut b = good.clone().into_bytes();
            let i = r.below(b.len() as u64) as usize;
            b[i] = r.below(256) as u8;
            // Must not panic; may or may not be an error.
            let _ = decode_gaussians::<f32>(p, &b);
        }
    }

    #[test]
    fn point_cloud_round_trip() {
        let dir = std::env::temp_dir().join(format!("ls-ply-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("points3d.ply");
        let pc = PointCloud {
            xyz: vec![0.5, -1.25, 3.0, 1.0, 2.0, 0.125],
            rgb: Some(vec![1, 2, 3, 250, 127, 0]),
        };
        write_points(&path, &pc).unwrap();
        assert_eq!(read_points(&path).unwrap(), pc);
        let pc2 = PointCloud { rgb: None, ..pc };
        write_points(&path, &pc2).unwrap();
        assert_eq!(read_points(&path).unwrap(), pc2);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
