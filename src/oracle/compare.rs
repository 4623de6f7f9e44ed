//! Compare an expected tensor file with an actual one, tensor by tensor.
//!
//! This is what a GPU-backend author runs in CI: `expected` is this crate's
//! output for a case, `actual` is the backend's output for the same case.
//!
//! ## Pass/fail rule
//! For every tensor of `expected` (a tensor missing from `actual` fails the
//! comparison; tensors only in `actual` are listed but do not fail it):
//! - shape and dtype must be equal;
//! - element `(a, e)` matches when `|a − e| ≤ atol + rtol·|e|` (PyTorch's
//!   `allclose` / `torch.testing` rule, with the tolerance scaled by the
//!   *expected* value), evaluated in the tensors' dtype as `torch.isclose`
//!   and `numpy.isclose` evaluate it (two F32 tensors: `atol` and `rtol`
//!   rounded to f32, `|a − e|` and `atol + |rtol·e|` in f32, so that an
//!   element on the boundary goes the way it goes in PyTorch). Infinities
//!   match only an identical infinity. A NaN matches only a NaN, and only
//!   with `equal_nan`;
//! - the tensor passes when its number of mismatching elements is at most
//!   `floor(max_mismatch_fraction · numel)` (default 0). The allowance exists
//!   for discontinuity bands: a Gaussian that sits exactly on the 1/255 alpha
//!   threshold or a tile boundary may legitimately flip between backends.
//!
//! ## Tolerances
//! Defaults by dtype: F32 `atol = 1e-5, rtol = 1.3e-6` (torch.testing's
//! float32 defaults), F64 `atol = 1e-7, rtol = 1e-7`, I32 and I64 exact
//! (`0, 0`; integers are matched on their exact difference, I64 beyond
//! 2^53 included).
//! They can be overridden by a JSON file:
//!
//! ```json
//! {
//!   "default": {"atol": 1e-5, "rtol": 1e-4},
//!   "tensors": {
//!     "grad_means3D": {"atol": 1e-4, "rtol": 1e-3, "max_mismatch_fraction": 0.001},
//!     "grad_*":       {"rtol": 1e-3},
//!     "n_contrib":    {"max_mismatch_fraction": 0.01}
//!   }
//! }
//! ```
//!
//! Every field of an entry (`atol`, `rtol`, `max_mismatch_fraction`,
//! `equal_nan`) is optional; unknown keys are an error. Resolution for a
//! tensor: the dtype default, then the fields given in `default`, then the
//! fields of the entry in `tensors` that names it. An exact name wins over a
//! pattern; a pattern may hold `*` (any run of characters), and among
//! matching patterns the most specific one (most non-`*` characters; then the
//! lexicographically first) wins. `atol` and `rtol` from `default` apply to
//! floating-point tensors only: integer tensors (radii, n_contrib, gsplat's
//! int64 ids) stay exact
//! unless an entry in `tensors` matches them. The CLI flags `--atol`,
//! `--rtol`, `--max-mismatch-fraction` and `--equal-nan` replace the
//! corresponding fields of `default`. Entries of `tensors` that apply to no
//! tensor of `expected` are listed in the report (`unused_tolerances`), not
//! failed.
//!
//! ## Statistics
//! All computed in f64 in element order (no parallel reduction, so the report
//! is deterministic): max absolute error, max relative error `|a−e|/|e|`
//! (infinite where `e = 0 ≠ a`), relative L2 `‖a−e‖/‖e‖`, cosine similarity,
//! signed bias `mean(a−e)`, the ULP distance (max and mean) in the tensor's own
//! dtype (for integer tensors the integer difference), NaN and Inf counts of each
//! side, the number and fraction of mismatches, and the worst element (largest
//! excess of `|a−e|` over its allowance; a NaN mismatch counts as infinitely
//! bad) as a multi-index with both values. Error and bias statistics skip
//! pairs where either value is NaN; L2, cosine and bias also skip pairs with
//! an infinity. Conventions for degenerate norms: relative L2 is 0 when both
//! `‖a−e‖` and `‖e‖` are 0 and infinite when only `‖e‖` is; cosine similarity
//! is 1 when both norms are 0 and 0 when exactly one is. I64 values beyond
//! ±2^53 enter the statistics and the worst element's values rounded to
//! f64; whether they match is decided on their exact difference.
//!
//! In the JSON report non-finite numbers are written as the strings `"inf"`,
//! `"-inf"` and `"nan"` (JSON has no literal for them).

use crate::error::{Error, Result};
use crate::io::tensor_file::shape_str;
use crate::io::{Tensor, TensorFile};
use serde::{Deserialize, Serialize, Serializer};
use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;

// ---------------------------------------------------------------------------
// Tolerances
// ---------------------------------------------------------------------------

/// A fully resolved tolerance for one tensor.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Tolerance {
    /// Absolute tolerance.
    pub atol: f64,
    /// Relative tolerance, scaled by `|expected|`.
    pub rtol: f64,
    /// Fraction of elements allowed to mismatch, in `[0, 1]`.
    pub max_mismatch_fraction: f64,
    /// Whether a NaN in both files counts as a match.
    pub equal_nan: bool,
}

impl Tolerance {
    /// The default for a dtype name (`"F32"`, `"F64"`, `"I32"`, `"I64"`):
    /// torch.testing's float32 values for F32, 1e-7/1e-7 for F64, exact for
    /// the integers.
    pub fn for_dtype(dtype: &str) -> Tolerance {
        let (atol, rtol) = match dtype {
            "F32" => (1e-5, 1.3e-6),
            "F64" => (1e-7, 1e-7),
            _ => (0.0, 0.0),
        };
        Tolerance {
            atol,
            rtol,
            max_mismatch_fraction: 0.0,
            equal_nan: false,
        }
    }

    /// Whether `actual` matches `expected` under this tolerance.
    pub fn matches(&self, actual: f64, expected: f64) -> bool {
        if actual.is_nan() || expected.is_nan() {
            return self.equal_nan && actual.is_nan() && expected.is_nan();
        }
        if actual == expected {
            return true;
        }
        if actual.is_infinite() || expected.is_infinite() {
            return false;
        }
        (actual - expected).abs() <= self.atol + self.rtol * expected.abs()
    }

    /// [`matches`](Self::matches) evaluated in f32, as PyTorch evaluates
    /// `isclose` for float32 tensors: `atol + |rtol·e|` with `atol` and
    /// `rtol` rounded to f32, and `|a − e|` in f32 (which can overflow: then
    /// no match).
    pub fn matches_f32(&self, actual: f32, expected: f32) -> bool {
        if actual.is_nan() || expected.is_nan() {
            return self.equal_nan && actual.is_nan() && expected.is_nan();
        }
        if actual == expected {
            return true;
        }
        let err = (actual - expected).abs();
        err.is_finite() && err <= self.atol as f32 + (self.rtol as f32 * expected).abs()
    }

    fn allowance(&self, expected: f64) -> f64 {
        self.atol + self.rtol * expected.abs()
    }
}

/// A partial tolerance as written in a tolerance file or given by flags;
/// absent fields keep the value they would otherwise have.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToleranceSpec {
    /// Absolute tolerance.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub atol: Option<f64>,
    /// Relative tolerance.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rtol: Option<f64>,
    /// Fraction of elements allowed to mismatch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_mismatch_fraction: Option<f64>,
    /// Whether NaN equals NaN.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub equal_nan: Option<bool>,
}

impl ToleranceSpec {
    fn apply(&self, t: &mut Tolerance, with_atol_rtol: bool) {
        if with_atol_rtol {
            if let Some(v) = self.atol {
                t.atol = v;
            }
            if let Some(v) = self.rtol {
                t.rtol = v;
            }
        }
        if let Some(v) = self.max_mismatch_fraction {
            t.max_mismatch_fraction = v;
        }
        if let Some(v) = self.equal_nan {
            t.equal_nan = v;
        }
    }

    fn validate(&self, at: &str) -> Result<()> {
        for (field, v) in [("atol", self.atol), ("rtol", self.rtol)] {
            if let Some(v) = v {
                if !(v.is_finite() && v >= 0.0) {
                    return Err(Error::invalid(
                        format!("{at}.{field}"),
                        format!("{} is not a finite number >= 0", crate::error::shown(v)),
                    ));
                }
            }
        }
        if let Some(v) = self.max_mismatch_fraction {
            if !(0.0..=1.0).contains(&v) {
                return Err(Error::invalid(
                    format!("{at}.max_mismatch_fraction"),
                    format!("{} is not in [0, 1]", crate::error::shown(v)),
                ));
            }
        }
        Ok(())
    }
}

/// Tolerances for a whole comparison: a default plus per-tensor entries
/// (exact names or `*` patterns). See the module docs for the file format
/// and the resolution order.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Tolerances {
    /// Applied to every tensor (atol/rtol to floating-point tensors only).
    #[serde(default)]
    pub default: ToleranceSpec,
    /// Per-tensor entries keyed by name or `*` pattern.
    #[serde(default)]
    pub tensors: BTreeMap<String, ToleranceSpec>,
}

impl Tolerances {
    /// Parse the JSON tolerance format; `path` is used in error messages.
    pub fn from_json(path: &Path, text: &str) -> Result<Self> {
        let t: Tolerances = serde_json::from_str(text)
            .map_err(|e| Error::format(path, format!("not a valid tolerance file: {e}")))?;
        t.validate().map_err(|e| e.in_file(path))?;
        Ok(t)
    }

    /// Read and parse a JSON tolerance file.
    pub fn load(path: &Path) -> Result<Self> {
        let bytes = crate::io::read(path)?;
        let text = std::str::from_utf8(&bytes)
            .map_err(|_| Error::format(path, "tolerance file is not UTF-8"))?;
        Self::from_json(path, text)
    }

    /// Check every value is in its domain.
    pub fn validate(&self) -> Result<()> {
        self.default.validate("default")?;
        for (name, spec) in &self.tensors {
            if name.is_empty() {
                return Err(Error::invalid(
                    "tensors",
                    "an entry named \"\" (it can match no tensor)",
                ));
            }
            spec.validate(&format!("tensors.{name}"))?;
        }
        Ok(())
    }

    /// The key and entry in `tensors` that apply to `name`, if any.
    fn entry(&self, name: &str) -> Option<(&str, &ToleranceSpec)> {
        if let Some((k, s)) = self.tensors.get_key_value(name) {
            return Some((k, s));
        }
        let mut best: Option<(usize, &str, &ToleranceSpec)> = None;
        for (pattern, spec) in &self.tensors {
            if pattern.contains('*') && glob_match(pattern, name) {
                let specificity = pattern.chars().filter(|&c| c != '*').count();
                if best.is_none_or(|(s, _, _)| specificity > s) {
                    best = Some((specificity, pattern, spec));
                }
            }
        }
        best.map(|(_, k, s)| (k, s))
    }

    /// The keys of `tensors` that apply to none of `names` (no match, or
    /// every match taken by a more specific entry), in key order.
    pub fn unused<'a>(&self, names: impl IntoIterator<Item = &'a str>) -> Vec<String> {
        let used: std::collections::BTreeSet<&str> = names
            .into_iter()
            .filter_map(|n| self.entry(n).map(|(k, _)| k))
            .collect();
        self.tensors
            .keys()
            .filter(|k| !used.contains(k.as_str()))
            .cloned()
            .collect()
    }

    /// The tolerance for tensor `name` of dtype `dtype` (`"F32"`, `"F64"`,
    /// `"I32"`, `"I64"`).
    pub fn resolve(&self, name: &str, dtype: &str) -> Tolerance {
        let mut t = Tolerance::for_dtype(dtype);
        let is_float = !matches!(dtype, "I32" | "I64");
        self.default.apply(&mut t, is_float);
        if let Some((_, spec)) = self.entry(name) {
            spec.apply(&mut t, true);
        }
        t
    }
}

/// `*` matches any run of characters (including none); everything else
/// matches itself.
fn glob_match(pattern: &str, name: &str) -> bool {
    let p: Vec<char> = pattern.chars().collect();
    let s: Vec<char> = name.chars().collect();
    // Classic greedy matcher with single backtrack point.
    let (mut pi, mut si) = (0usize, 0usize);
    let mut star: Option<(usize, usize)> = None;
    while si < s.len() {
        if pi < p.len() && p[pi] != '*' && p[pi] == s[si] {
            pi += 1;
            si += 1;
        } else if pi < p.len() && p[pi] == '*' {
            star = Some((pi, si));
            pi += 1;
        } else if let Some((sp, ss)) = star {
            pi = sp + 1;
            si = ss + 1;
            star = Some((sp, ss + 1));
        } else {
            return false;
        }
    }
    while pi < p.len() && p[pi] == '*' {
        pi += 1;
    }
    pi == p.len()
}

// ---------------------------------------------------------------------------
// Report
// ---------------------------------------------------------------------------

/// Pass or fail of one tensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Within tolerance.
    Pass,
    /// Shape/dtype mismatch or too many mismatching elements.
    Fail,
}

/// The element with the largest excess of `|a − e|` over its allowance.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Worst {
    /// Multi-index into the tensor's shape.
    pub index: Vec<usize>,
    /// Expected value (widened to f64, exact).
    #[serde(serialize_with = "ser_f64")]
    pub expected: f64,
    /// Actual value (widened to f64, exact).
    #[serde(serialize_with = "ser_f64")]
    pub actual: f64,
}

/// Element-wise statistics of one tensor pair of equal shape.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ElementStats {
    /// Number of elements.
    pub numel: usize,
    /// Elements that fail the `allclose` rule.
    pub mismatches: usize,
    /// `floor(max_mismatch_fraction · numel)`.
    pub allowed_mismatches: usize,
    /// Max `|a − e|` over pairs without NaN.
    #[serde(serialize_with = "ser_f64")]
    pub max_abs_error: f64,
    /// Max `|a − e| / |e|` over pairs without NaN (0 where `a == e`).
    #[serde(serialize_with = "ser_f64")]
    pub max_rel_error: f64,
    /// `‖a − e‖ / ‖e‖` over finite pairs.
    #[serde(serialize_with = "ser_f64")]
    pub rel_l2: f64,
    /// `⟨a, e⟩ / (‖a‖ ‖e‖)` over finite pairs.
    #[serde(serialize_with = "ser_f64")]
    pub cosine: f64,
    /// `mean(a − e)` over finite pairs (positive: actual too large).
    #[serde(serialize_with = "ser_f64")]
    pub bias: f64,
    /// Max ULP distance in the tensor's dtype over pairs without NaN (I32:
    /// max integer difference). `None` if dtypes differ or no such pair exists.
    pub ulp_max: Option<u64>,
    /// Mean ULP distance (I32: mean integer difference).
    #[serde(serialize_with = "ser_opt_f64")]
    pub ulp_mean: Option<f64>,
    /// NaN count in `expected`.
    pub nan_expected: usize,
    /// NaN count in `actual`.
    pub nan_actual: usize,
    /// ±Inf count in `expected`.
    pub inf_expected: usize,
    /// ±Inf count in `actual`.
    pub inf_actual: usize,
    /// The worst element (absent for empty tensors).
    pub worst: Option<Worst>,
}

/// The comparison of one tensor of `expected`.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TensorReport {
    /// Tensor name.
    pub name: String,
    /// Pass or fail.
    pub status: Status,
    /// Dtype in `expected`.
    pub dtype: String,
    /// Dtype in `actual`.
    pub actual_dtype: String,
    /// Shape in `expected`.
    pub shape: Vec<usize>,
    /// Shape in `actual`.
    pub actual_shape: Vec<usize>,
    /// The tolerance applied.
    pub tolerance: Tolerance,
    /// Human sentences for structural problems (shape, dtype, too many mismatches).
    pub problems: Vec<String>,
    /// Element statistics (absent when the shapes differ).
    pub stats: Option<ElementStats>,
}

/// The result of [`compare`]; serialises to JSON and prints as a table.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CompareReport {
    /// Path of the expected file.
    pub expected: String,
    /// Path of the actual file.
    pub actual: String,
    /// True when every tensor of `expected` is present and passes.
    pub passed: bool,
    /// One entry per tensor of `expected` present in `actual`, sorted by name.
    pub tensors: Vec<TensorReport>,
    /// Tensors of `expected` absent from `actual` (each a failure).
    pub missing: Vec<String>,
    /// Tensors of `actual` absent from `expected` (listed, not a failure).
    pub extra: Vec<String>,
    /// Entries of the tolerance file's `tensors` that apply to no tensor of
    /// `expected` (listed, not a failure: a shared tolerance file names
    /// tensors of many stages, but a misspelt name shows up here).
    pub unused_tolerances: Vec<String>,
}

impl CompareReport {
    /// The report as pretty-printed JSON.
    pub fn to_json(&self) -> String {
        // Serialising plain structs with string keys cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"))
    }

    /// Number of failing tensors (missing ones included).
    pub fn failures(&self) -> usize {
        self.missing.len()
            + self
                .tensors
                .iter()
                .filter(|t| t.status == Status::Fail)
                .count()
    }
}

fn ser_f64<S: Serializer>(x: &f64, s: S) -> std::result::Result<S::Ok, S::Error> {
    if x.is_finite() {
        s.serialize_f64(*x)
    } else if x.is_nan() {
        s.serialize_str("nan")
    } else if *x > 0.0 {
        s.serialize_str("inf")
    } else {
        s.serialize_str("-inf")
    }
}

fn ser_opt_f64<S: Serializer>(x: &Option<f64>, s: S) -> std::result::Result<S::Ok, S::Error> {
    match x {
        Some(v) => ser_f64(v, s),
        None => s.serialize_none(),
    }
}

// ---------------------------------------------------------------------------
// Comparison
// ---------------------------------------------------------------------------

/// Compare every tensor of `expected` with the same-named tensor of `actual`.
///
/// Errors only on unusable input: tolerances out of their domain, or an
/// `expected` file without tensors. Mismatches are reported, not errors.
pub fn compare(
    expected: &TensorFile,
    actual: &TensorFile,
    tol: &Tolerances,
) -> Result<CompareReport> {
    tol.validate()?;
    if expected.tensors.is_empty() {
        return Err(Error::format(
            &expected.path,
            "the expected file holds no tensors, so there is nothing to compare",
        ));
    }
    let mut tensors = Vec::new();
    let mut missing = Vec::new();
    for (name, e) in &expected.tensors {
        match actual.tensors.get(name) {
            None => missing.push(name.clone()),
            Some(a) => tensors.push(compare_tensor(name, e, a, tol)),
        }
    }
    let extra: Vec<String> = actual
        .tensors
        .keys()
        .filter(|k| !expected.tensors.contains_key(*k))
        .cloned()
        .collect();
    let passed = missing.is_empty() && tensors.iter().all(|t| t.status == Status::Pass);
    let unused_tolerances = tol.unused(expected.tensors.keys().map(String::as_str));
    Ok(CompareReport {
        expected: expected.path.display().to_string(),
        actual: actual.path.display().to_string(),
        passed,
        tensors,
        missing,
        extra,
        unused_tolerances,
    })
}

fn compare_tensor(name: &str, e: &Tensor, a: &Tensor, tol: &Tolerances) -> TensorReport {
    let dtype = e.dtype_name().to_string();
    let actual_dtype = a.dtype_name().to_string();
    let tolerance = tol.resolve(name, &dtype);
    let mut problems = Vec::new();
    if dtype != actual_dtype {
        problems.push(format!("dtype {actual_dtype}, expected {dtype}"));
    }
    let stats = if e.shape() != a.shape() {
        problems.push(format!(
            "shape {}, expected {}",
            shape_str(a.shape()),
            shape_str(e.shape())
        ));
        None
    } else {
        let s = element_stats(e.shape(), e, a, &tolerance);
        if s.mismatches > s.allowed_mismatches {
            problems.push(format!(
                "{} of {} elements outside tolerance (allowed {})",
                s.mismatches, s.numel, s.allowed_mismatches
            ));
        }
        Some(s)
    };
    let status = if problems.is_empty() {
        Status::Pass
    } else {
        Status::Fail
    };
    TensorReport {
        name: name.to_string(),
        status,
        dtype,
        actual_dtype,
        shape: e.shape().to_vec(),
        actual_shape: a.shape().to_vec(),
        tolerance,
        problems,
        stats,
    }
}

/// Position of `x` on the number line of its type, in ULPs from zero
/// (`-0.0` and `+0.0` both map to 0).
fn ulp_key_f32(x: f32) -> i64 {
    let b = x.to_bits();
    let mag = (b & 0x7fff_ffff) as i64;
    if b >> 31 == 1 {
        -mag
    } else {
        mag
    }
}

fn ulp_key_f64(x: f64) -> i128 {
    let b = x.to_bits();
    let mag = (b & 0x7fff_ffff_ffff_ffff) as i128;
    if b >> 63 == 1 {
        -mag
    } else {
        mag
    }
}

/// ULP (or integer) distance per element for equal dtypes; `None` where
/// either value is NaN.
fn ulp_distances(e: &Tensor, a: &Tensor) -> Option<Vec<Option<u64>>> {
    Some(match (e, a) {
        (Tensor::F32(e), Tensor::F32(a)) => e
            .iter()
            .zip(a)
            .map(|(&x, &y)| {
                (!x.is_nan() && !y.is_nan())
                    .then(|| (ulp_key_f32(y) - ulp_key_f32(x)).unsigned_abs())
            })
            .collect(),
        (Tensor::F64(e), Tensor::F64(a)) => e
            .iter()
            .zip(a)
            .map(|(&x, &y)| {
                (!x.is_nan() && !y.is_nan())
                    .then(|| (ulp_key_f64(y) - ulp_key_f64(x)).unsigned_abs() as u64)
            })
            .collect(),
        (Tensor::I32(_), Tensor::I32(_)) | (Tensor::I64(_), Tensor::I64(_)) => {
            let (e, a) = (e.to_i64()?, a.to_i64()?);
            e.iter()
                .zip(&a)
                .map(|(&x, &y)| Some(int_distance(x, y)))
                .collect()
        }
        _ => return None,
    })
}

/// `|y − x|` of two integers, exact (saturating at `u64::MAX`, which two
/// i64 values can exceed by one).
fn int_distance(x: i64, y: i64) -> u64 {
    u64::try_from((i128::from(y) - i128::from(x)).unsigned_abs()).unwrap_or(u64::MAX)
}

fn unravel(mut flat: usize, shape: &[usize]) -> Vec<usize> {
    let mut idx = vec![0; shape.len()];
    for (k, &d) in shape.iter().enumerate().rev() {
        if d > 0 {
            idx[k] = flat % d;
            flat /= d;
        }
    }
    idx
}

fn element_stats(shape: &[usize], e: &Tensor, a: &Tensor, tol: &Tolerance) -> ElementStats {
    let ev = crate::io::tensor_file::into_row_major(e.to_f64());
    let av = crate::io::tensor_file::into_row_major(a.to_f64());
    // (F32 values are exact in f64 and back.)
    let in_f32 = matches!((e, a), (Tensor::F32(_), Tensor::F32(_)));
    // Integers are matched on their exact difference: I64 values beyond
    // 2^53 are not exact in f64 (the statistics below use the rounded
    // values).
    let ints = e.to_i64().zip(a.to_i64());
    let n = ev.len();
    let allowed_mismatches = (tol.max_mismatch_fraction * n as f64).floor() as usize;

    let mut mismatches = 0usize;
    let (mut nan_e, mut nan_a, mut inf_e, mut inf_a) = (0usize, 0usize, 0usize, 0usize);
    let mut max_abs = 0.0f64;
    let mut max_rel = 0.0f64;
    // Sums over finite pairs, in element order.
    let (mut sum_dd, mut sum_ee, mut sum_aa, mut sum_ae, mut sum_d) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let mut finite_pairs = 0usize;
    let mut worst: Option<(f64, usize)> = None;

    for i in 0..n {
        let (x, y) = (ev[i], av[i]);
        nan_e += x.is_nan() as usize;
        nan_a += y.is_nan() as usize;
        inf_e += x.is_infinite() as usize;
        inf_a += y.is_infinite() as usize;
        let ok = if let Some((ei, ai)) = &ints {
            let d = int_distance(ei[i], ai[i]);
            d == 0 || (d as f64) <= tol.atol + tol.rtol * x.abs()
        } else if in_f32 {
            tol.matches_f32(y as f32, x as f32)
        } else {
            tol.matches(y, x)
        };
        mismatches += (!ok) as usize;

        let score = if x.is_nan() || y.is_nan() {
            if ok {
                f64::NEG_INFINITY
            } else {
                f64::INFINITY
            }
        } else {
            let d = if x == y { 0.0 } else { (y - x).abs() };
            max_abs = max_abs.max(d);
            let rel = if d == 0.0 { 0.0 } else { d / x.abs() };
            max_rel = max_rel.max(rel);
            if x.is_finite() && y.is_finite() {
                let diff = y - x;
                sum_dd += diff * diff;
                sum_ee += x * x;
                sum_aa += y * y;
                sum_ae += x * y;
                sum_d += diff;
                finite_pairs += 1;
            }
            if ok {
                d - tol.allowance(x)
            } else if d.is_finite() {
                // A mismatch always ranks above every match.
                (d - tol.allowance(x)).max(f64::MIN_POSITIVE)
            } else {
                f64::INFINITY
            }
        };
        if worst.is_none_or(|(s, _)| score > s) {
            worst = Some((score, i));
        }
    }

    let rel_l2 = if sum_ee > 0.0 {
        sum_dd.sqrt() / sum_ee.sqrt()
    } else if sum_dd == 0.0 {
        0.0
    } else {
        f64::INFINITY
    };
    let cosine = match (sum_aa > 0.0, sum_ee > 0.0) {
        (true, true) => sum_ae / (sum_aa.sqrt() * sum_ee.sqrt()),
        (false, false) => 1.0,
        _ => 0.0,
    };
    let bias = if finite_pairs > 0 {
        sum_d / finite_pairs as f64
    } else {
        0.0
    };

    let (ulp_max, ulp_mean) = match ulp_distances(e, a) {
        Some(d) => {
            let mut max = 0u64;
            let mut sum = 0u128;
            let mut count = 0u64;
            for v in d.into_iter().flatten() {
                max = max.max(v);
                sum += v as u128;
                count += 1;
            }
            if count > 0 {
                (Some(max), Some(sum as f64 / count as f64))
            } else {
                (None, None)
            }
        }
        None => (None, None),
    };

    ElementStats {
        numel: n,
        mismatches,
        allowed_mismatches,
        max_abs_error: max_abs,
        max_rel_error: max_rel,
        rel_l2,
        cosine,
        bias,
        ulp_max,
        ulp_mean,
        nan_expected: nan_e,
        nan_actual: nan_a,
        inf_expected: inf_e,
        inf_actual: inf_a,
        worst: worst.map(|(_, i)| Worst {
            index: unravel(i, shape),
            expected: ev[i],
            actual: av[i],
        }),
    }
}

// ---------------------------------------------------------------------------
// Human table
// ---------------------------------------------------------------------------

fn sci(x: f64) -> String {
    if x.is_finite() {
        format!("{x:.2e}")
    } else {
        format!("{x}")
    }
}

impl fmt::Display for CompareReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "expected: {}", self.expected)?;
        writeln!(f, "actual:   {}", self.actual)?;
        let w = self
            .tensors
            .iter()
            .map(|t| t.name.len())
            .chain(self.missing.iter().map(|m| m.len()))
            .max()
            .unwrap_or(6)
            .max(6);
        writeln!(
            f,
            "{:<w$}  {:<4}  {:<12}  {:>9}  {:>9}  {:>9}  {:>10}  {:>10}  {:>9}  {:>9}  {:>7}  {:>12}  status",
            "tensor", "type", "shape", "max_abs", "max_rel", "rel_l2", "cosine", "bias",
            "ulp_max", "ulp_mean", "nan e/a", "mismatch"
        )?;
        for t in &self.tensors {
            let status = match t.status {
                Status::Pass => "ok",
                Status::Fail => "FAIL",
            };
            match &t.stats {
                Some(s) => writeln!(
                    f,
                    "{:<w$}  {:<4}  {:<12}  {:>9}  {:>9}  {:>9}  {:>10.7}  {:>10}  {:>9}  {:>9}  {:>7}  {:>12}  {}",
                    t.name,
                    t.dtype,
                    shape_str(&t.shape),
                    sci(s.max_abs_error),
                    sci(s.max_rel_error),
                    sci(s.rel_l2),
                    s.cosine,
                    sci(s.bias),
                    s.ulp_max.map_or("-".into(), |u| u.to_string()),
                    s.ulp_mean.map_or("-".into(), |u| format!("{u:.3}")),
                    format!("{}/{}", s.nan_expected, s.nan_actual),
                    format!("{}/{}", s.mismatches, s.numel),
                    status
                )?,
                None => writeln!(
                    f,
                    "{:<w$}  {:<4}  {:<12}  {:>9}  {:>9}  {:>9}  {:>10}  {:>10}  {:>9}  {:>9}  {:>7}  {:>12}  {}",
                    t.name, t.dtype, shape_str(&t.shape), "-", "-", "-", "-", "-", "-", "-", "-", "-",
                    status
                )?,
            }
        }
        for m in &self.missing {
            writeln!(f, "{m:<w$}  missing in actual  FAIL")?;
        }
        for t in self.tensors.iter().filter(|t| t.status == Status::Fail) {
            for p in &t.problems {
                writeln!(f, "  {}: {p}", t.name)?;
            }
            if let Some(Worst {
                index,
                expected,
                actual,
            }) = t.stats.as_ref().and_then(|s| s.worst.as_ref())
            {
                writeln!(
                    f,
                    "  {}: worst at {:?}: expected {expected:e}, actual {actual:e} (atol {:e}, rtol {:e})",
                    t.name, index, t.tolerance.atol, t.tolerance.rtol
                )?;
            }
        }
        if !self.extra.is_empty() {
            writeln!(f, "extra in actual (ignored): {}", self.extra.join(", "))?;
        }
        if !self.unused_tolerances.is_empty() {
            writeln!(
                f,
                "tolerance entries that apply to no tensor here: {}",
                self.unused_tolerances.join(", ")
            )?;
        }
        let n = self.tensors.len() + self.missing.len();
        if self.passed {
            write!(f, "PASS: {n} tensor(s) within tolerance")
        } else {
            write!(f, "FAIL: {} of {n} tensor(s) failed", self.failures())
        }
    }
}

#[cfg(test)]
mod tests;
