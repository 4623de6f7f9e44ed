//! Typed access to JSON fields with the file and field path in every error.

use crate::error::{Error, Result};
use serde_json::Value;
use std::path::Path;

/// Marks a non-finite literal (`NaN`, `Infinity`, `-Infinity`, as Python's `json` writes them)
/// that [`read`] turned into a string so that the error can name its field.
const NON_FINITE: &str = "\u{0}non-finite:";

/// Read and parse a JSON file. Python's non-standard `NaN` / `Infinity` literals are accepted
/// by the parser and reported as "not finite" by [`num`] with the field they sit in.
pub(crate) fn read(path: &Path) -> Result<Value> {
    let bytes = crate::io::read(path)?;
    let text =
        std::str::from_utf8(&bytes).map_err(|_| Error::format(path, "invalid JSON: not UTF-8"))?;
    serde_json::from_str(&quote_non_finite(text))
        .map_err(|e| Error::format(path, format!("invalid JSON: {e}")))
}

/// Replace `NaN`, `Infinity` and `-Infinity` outside strings by marked strings.
fn quote_non_finite(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    let mut in_str = false;
    let mut escaped = false;
    let mut rest = text;
    while let Some(c) = rest.chars().next() {
        if in_str {
            if escaped {
                escaped = false;
            } else if c == '\\' {
                escaped = true;
            } else if c == '"' {
                in_str = false;
            }
        } else if c == '"' {
            in_str = true;
        } else {
            let lit = ["-Infinity", "Infinity", "NaN"]
                .into_iter()
                .find(|l| rest.starts_with(l));
            if let Some(l) = lit {
                out.push('"');
                out.push_str("\\u0000non-finite:");
                out.push_str(l);
                out.push('"');
                rest = &rest[l.len()..];
                continue;
            }
        }
        out.push(c);
        rest = &rest[c.len_utf8()..];
    }
    out
}

/// A JSON object's member; `field` is the full field path used in errors.
pub(crate) fn get<'a>(path: &Path, v: &'a Value, key: &str, field: &str) -> Result<&'a Value> {
    let obj = v
        .as_object()
        .ok_or_else(|| Error::field(path, field, "expected a JSON object around it"))?;
    obj.get(key)
        .ok_or_else(|| Error::field(path, field, "missing"))
}

pub(crate) fn num(path: &Path, v: &Value, field: &str) -> Result<f64> {
    if let Some(l) = v.as_str().and_then(|s| s.strip_prefix(NON_FINITE)) {
        return Err(Error::field(path, field, format!("not finite ({l})")));
    }
    let x = v.as_f64().ok_or_else(|| {
        Error::field(path, field, format!("expected a number, found {}", kind(v)))
    })?;
    if !x.is_finite() {
        return Err(Error::field(path, field, "not finite"));
    }
    Ok(x)
}

pub(crate) fn string<'a>(path: &Path, v: &'a Value, field: &str) -> Result<&'a str> {
    v.as_str()
        .ok_or_else(|| Error::field(path, field, format!("expected a string, found {}", kind(v))))
}

pub(crate) fn array<'a>(path: &Path, v: &'a Value, field: &str) -> Result<&'a Vec<Value>> {
    v.as_array()
        .ok_or_else(|| Error::field(path, field, format!("expected an array, found {}", kind(v))))
}

/// A numeric vector of exactly `n` finite entries.
pub(crate) fn vector(path: &Path, v: &Value, n: usize, field: &str) -> Result<Vec<f64>> {
    let a = array(path, v, field)?;
    if a.len() != n {
        return Err(Error::field(
            path,
            field,
            format!("expected {n} entries, found {}", a.len()),
        ));
    }
    a.iter()
        .enumerate()
        .map(|(i, x)| num(path, x, &format!("{field}[{i}]")))
        .collect()
}

/// A `rows × cols` numeric matrix of finite entries (array of row arrays).
pub(crate) fn matrix(
    path: &Path,
    v: &Value,
    rows: usize,
    cols: usize,
    field: &str,
) -> Result<Vec<Vec<f64>>> {
    let a = array(path, v, field)?;
    if a.len() != rows {
        return Err(Error::field(
            path,
            field,
            format!("expected {rows} rows, found {}", a.len()),
        ));
    }
    a.iter()
        .enumerate()
        .map(|(i, r)| vector(path, r, cols, &format!("{field}[{i}]")))
        .collect()
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "an array",
        Value::Object(_) => "an object",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn non_finite_literals_are_named() {
        let v: Value = serde_json::from_str(&quote_non_finite(
            r#"{"a": [1, NaN, -Infinity], "s": "NaN \" x"}"#,
        ))
        .unwrap();
        let p = Path::new("t.json");
        let e = vector(p, &v["a"], 3, "a").unwrap_err().to_string();
        assert_eq!(e, "t.json: field `a[1]`: not finite (NaN)");
        assert_eq!(v["s"], "NaN \" x");
        assert!(num(p, &v["a"][2], "a[2]")
            .unwrap_err()
            .to_string()
            .contains("-Infinity"));
    }
}
