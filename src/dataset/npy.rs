//! A minimal `.npy` reader and writer for `(N, 3)` point arrays (`points.npy`): format
//! versions 1–3, little-endian `<f4` or `<f8`, C order.

use crate::error::{Error, Result};
use std::path::Path;

const MAGIC: &[u8] = b"\x93NUMPY";

/// Parse an `(N, 3)` float array from `.npy` bytes into f64 values (row-major).
pub fn decode_points(path: &Path, bytes: &[u8]) -> Result<Vec<f64>> {
    let fmt = |what: String| Error::format(path, what);
    if bytes.len() < 10 || &bytes[..6] != MAGIC {
        return Err(fmt("not a .npy file (bad magic)".into()));
    }
    let (hlen, start): (usize, usize) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err(fmt("truncated .npy header".into()));
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => return Err(fmt(format!(".npy format version {v} is not supported"))),
    };
    let end = start
        .checked_add(hlen)
        .filter(|&e| e <= bytes.len())
        .ok_or_else(|| fmt("truncated .npy header".into()))?;
    let header = std::str::from_utf8(&bytes[start..end])
        .map_err(|_| fmt(".npy header is not text".into()))?;
    let field = |key: &str| -> Result<&str> {
        let k = format!("'{key}':");
        let i = header
            .find(&k)
            .ok_or_else(|| Error::field(path, key, "missing from the .npy header"))?;
        Ok(header[i + k.len()..].trim_start())
    };
    let descr = field("descr")?;
    let size = if descr.starts_with("'<f4'") {
        4
    } else if descr.starts_with("'<f8'") {
        8
    } else {
        return Err(Error::field(
            path,
            "descr",
            format!(
                "unsupported dtype {}, expected '<f4' or '<f8'",
                descr.split(',').next().unwrap_or("")
            ),
        ));
    };
    if !field("fortran_order")?.starts_with("False") {
        return Err(Error::field(
            path,
            "fortran_order",
            "Fortran order is not supported",
        ));
    }
    let shape = field("shape")?;
    let inner = shape
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .ok_or_else(|| Error::field(path, "shape", "not a tuple"))?;
    let dims: Vec<usize> = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| s.parse::<usize>())
        .collect::<std::result::Result<_, _>>()
        .map_err(|_| Error::field(path, "shape", format!("bad shape ({inner})")))?;
    if dims.len() != 2 || dims[1] != 3 {
        return Err(Error::field(
            path,
            "shape",
            format!("({inner}) is not (N, 3)"),
        ));
    }
    let n = dims[0];
    let body = &bytes[end..];
    if n.saturating_mul(3 * size) > body.len() {
        return Err(fmt(format!(
            "truncated .npy body: {} bytes for {n} points",
            body.len()
        )));
    }
    let mut out = Vec::with_capacity(3 * n);
    for i in 0..3 * n {
        let b = &body[i * size..(i + 1) * size];
        let v = if size == 4 {
            f32::from_le_bytes(b.try_into().unwrap()) as f64
        } else {
            f64::from_le_bytes(b.try_into().unwrap())
        };
        if !v.is_finite() {
            return Err(fmt(format!("non-finite value in point {}", i / 3)));
        }
        out.push(v);
    }
    Ok(out)
}

/// Read an `(N, 3)` `.npy` file.
pub fn read_points(path: &Path) -> Result<Vec<f64>> {
    decode_points(path, &crate::io::read(path)?)
}

/// Encode `(N, 3)` points as a version-1 `.npy` with dtype `<f4`.
pub fn encode_points_f32(xyz: &[f32]) -> Vec<u8> {
    let n = xyz.len() / 3;
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({n}, 3), }}");
    // Pad with spaces so that magic + len + header + '\n' is a multiple of 64.
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = MAGIC.to_vec();
    out.extend([1u8, 0u8]);
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.bytes());
    for v in xyz {
        out.extend(v.to_le_bytes());
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let pts = [1.5f32, -2.0, 0.25, 3.0, 4.0, 5.0];
        let b = encode_points_f32(&pts);
        let p = Path::new("points.npy");
        let back = decode_points(p, &b).unwrap();
        assert_eq!(back, pts.iter().map(|&v| v as f64).collect::<Vec<_>>());
        for cut in 0..b.len() {
            assert!(decode_points(p, &b[..cut]).is_err());
        }
        let at = b.windows(6).position(|w| w == b"(2, 3)").unwrap();
        let mut bad = b.clone();
        bad[at..at + 6].copy_from_slice(b"(3, 2)");
        assert!(decode_points(p, &bad)
            .unwrap_err()
            .to_string()
            .contains("shape"));
        // f8, hand-made header.
        let mut h = "{'descr': '<f8', 'fortran_order': False, 'shape': (1, 3), }".to_string();
        h.push('\n');
        let mut b = MAGIC.to_vec();
        b.extend([1u8, 0]);
        b.extend((h.len() as u16).to_le_bytes());
        b.extend(h.bytes());
        for v in [0.1f64, 0.2, 0.3] {
            b.extend(v.to_le_bytes());
        }
        assert_eq!(decode_points(p, &b).unwrap(), vec![0.1, 0.2, 0.3]);
    }
}
