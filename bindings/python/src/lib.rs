//! `liquid_splat._native`: the Python extension module of liquid-splat.
//!
//! A thin layer over the library's case-file API: named numpy arrays and
//! string metadata in, named numpy arrays and metadata out, computed by
//! [`liquid_splat::oracle::run_case`] exactly as `liquid-splat case run`
//! computes them (same code, same bits). The Python package
//! (`liquid_splat`) builds its stage functions, fields, testing helpers and
//! torch wrappers on these few functions.
//!
//! At the boundary: numpy arrays and the library's tensors
//! ([`liquid_splat::io::Tensor`], ndarray arrays) convert into each other
//! directly, shape and dtype kept. Arrays must be numpy arrays of float32,
//! float64, int32 or int64 in C order (a `TypeError` or `ValueError` names the
//! tensor, what was expected and what was found); case inputs must be
//! finite; library errors
//! become `ValueError` (`TypeError` for a wrong dtype); a panic becomes a
//! `RuntimeError` instead of crossing the boundary; the GIL is released
//! during every computation.

use liquid_splat::deform::count::{macs_per_gaussian, param_count, MacConvention};
use liquid_splat::deform::Field;
use liquid_splat::io::{Tensor, TensorFile};
use liquid_splat::oracle::{self, Tolerances};
use numpy::ndarray::ArrayD;
use numpy::PyUntypedArrayMethods;
use numpy::{PyArray, PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyUntypedArray};
use pyo3::exceptions::{PyBrokenPipeError, PyOSError, PyRuntimeError, PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyInt, PyString};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;

/// A library error as a Python exception: a wrong dtype is a `TypeError`,
/// everything else a `ValueError`. The message is the library's sentence.
fn to_py_err(e: liquid_splat::Error) -> PyErr {
    let msg = e.to_string();
    match &e {
        liquid_splat::Error::Tensor { expected, .. } if expected.starts_with("dtype") => {
            PyTypeError::new_err(msg)
        }
        _ => PyValueError::new_err(msg),
    }
}

/// Run `f` with the GIL released, on a pool of `threads` workers (or
/// rayon's global pool), turning a panic into a `RuntimeError`.
fn compute<R: Send>(
    py: Python<'_>,
    threads: Option<usize>,
    f: impl FnOnce() -> liquid_splat::Result<R> + Send,
) -> PyResult<R> {
    let pool = match threads {
        None => None,
        Some(n) if !(1..=1024).contains(&n) => {
            return Err(PyValueError::new_err(format!(
                "threads: expected 1 to 1024 worker threads or None, found {n}"
            )))
        }
        Some(n) => Some(
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .map_err(|e| PyRuntimeError::new_err(format!("cannot start {n} threads: {e}")))?,
        ),
    };
    let outcome = py.allow_threads(move || {
        catch_unwind(AssertUnwindSafe(move || match pool {
            Some(pool) => pool.install(f),
            None => f(),
        }))
    });
    match outcome {
        Ok(result) => result.map_err(to_py_err),
        Err(payload) => match payload.downcast::<liquid_splat::cli::StdoutError>() {
            Ok(e) => {
                let errno = e.0.raw_os_error().unwrap_or(0);
                Err(if e.0.kind() == std::io::ErrorKind::BrokenPipe {
                    PyBrokenPipeError::new_err((errno, "Broken pipe: standard output was closed"))
                } else {
                    PyOSError::new_err((
                        errno,
                        format!("cannot write the standard output: {}", e.0),
                    ))
                })
            }
            Err(payload) => {
                let what = payload
                    .downcast_ref::<&str>()
                    .map(|s| s.to_string())
                    .or_else(|| payload.downcast_ref::<String>().cloned())
                    .unwrap_or_else(|| "unknown panic".to_string());
                Err(PyRuntimeError::new_err(format!(
                    "liquid-splat internal error (a bug, please report it): {what}"
                )))
            }
        },
    }
}

fn type_name(obj: &Bound<'_, PyAny>) -> String {
    obj.get_type()
        .name()
        .map(|n| n.to_string())
        .unwrap_or_else(|_| "?".to_string())
}

/// One numpy array as a library tensor: its ndarray copy, same shape and
/// dtype. `what` names it in errors.
fn tensor_from_array(what: &str, obj: &Bound<'_, PyAny>, finite: bool) -> PyResult<Tensor> {
    let py = obj.py();
    let arr = obj.downcast::<PyUntypedArray>().map_err(|_| {
        PyTypeError::new_err(format!(
            "{what}: expected a numpy.ndarray (float32, float64, int32 or int64), found {}",
            type_name(obj)
        ))
    })?;
    let dtype = arr.dtype();
    let shape: Vec<usize> = arr.shape().to_vec();
    let kind = if dtype.is_equiv_to(&numpy::dtype::<f32>(py)) {
        "float32"
    } else if dtype.is_equiv_to(&numpy::dtype::<f64>(py)) {
        "float64"
    } else if dtype.is_equiv_to(&numpy::dtype::<i32>(py)) {
        "int32"
    } else if dtype.is_equiv_to(&numpy::dtype::<i64>(py)) {
        "int64"
    } else {
        let found = dtype
            .str()
            .map(|s| s.to_string())
            .unwrap_or_else(|_| "?".into());
        return Err(PyTypeError::new_err(format!(
            "{what}: expected dtype float32, float64, int32 or int64 (native byte order), found dtype {found}"
        )));
    };
    if !arr.is_c_contiguous() {
        return Err(PyValueError::new_err(format!(
            "{what}: expected a C-contiguous array (numpy.ascontiguousarray, torch .contiguous()), \
             found a non-contiguous {kind} array of shape {shape:?}"
        )));
    }
    fn array<T: numpy::Element + Copy>(obj: &Bound<'_, PyAny>) -> PyResult<ArrayD<T>> {
        Ok(obj
            .downcast::<PyArrayDyn<T>>()?
            .readonly()
            .as_array()
            .to_owned())
    }
    /// The first non-finite element in row-major order: (flat index, value).
    fn first_bad<T: Copy + Into<f64>>(a: &ArrayD<T>) -> Option<(usize, f64)> {
        a.iter()
            .map(|&x| x.into())
            .enumerate()
            .find(|(_, x): &(usize, f64)| !x.is_finite())
    }
    let tensor = match kind {
        "float32" => Tensor::F32(array::<f32>(obj)?),
        "float64" => Tensor::F64(array::<f64>(obj)?),
        "int32" => Tensor::I32(array::<i32>(obj)?),
        _ => Tensor::I64(array::<i64>(obj)?),
    };
    if finite {
        let bad = match &tensor {
            Tensor::F32(a) => first_bad(a),
            Tensor::F64(a) => first_bad(a),
            Tensor::I32(_) | Tensor::I64(_) => None,
        };
        if let Some((i, x)) = bad {
            return Err(PyValueError::new_err(format!(
                "{what}: expected finite values, found {x} at flat index {i} (shape {shape:?})"
            )));
        }
    }
    Ok(tensor)
}

/// A metadata value as the string a case file stores: `str` as is, `bool`
/// as `true`/`false`, integers in decimal, floats in the shortest form that
/// round-trips.
fn meta_value(key: &str, v: &Bound<'_, PyAny>) -> PyResult<String> {
    let numpy_bool = v
        .get_type()
        .name()
        .is_ok_and(|n| n == "bool" || n == "bool_");
    if v.downcast::<PyBool>().is_ok() || numpy_bool {
        return Ok(if v.is_truthy()? { "true" } else { "false" }.to_string());
    }
    if let Ok(s) = v.downcast::<PyString>() {
        return s.extract::<String>();
    }
    // (A Python int of any size, exactly.)
    if v.downcast::<PyInt>().is_ok() {
        return v.str()?.extract::<String>();
    }
    if let Ok(i) = v.extract::<i64>() {
        return Ok(i.to_string());
    }
    if let Ok(u) = v.extract::<u64>() {
        return Ok(u.to_string());
    }
    if let Ok(x) = v.extract::<f64>() {
        return Ok(format!("{x:?}"));
    }
    Err(PyTypeError::new_err(format!(
        "metadata['{key}']: expected str, bool, int or float, found {}",
        type_name(v)
    )))
}

/// A dict key as text: a `TypeError` for a key that is not a `str`, a
/// `ValueError` for a `str` that is not UTF-8 (a lone surrogate); `what`
/// names the keys in both.
fn dict_key(k: &Bound<'_, PyAny>, what: impl Fn() -> String) -> PyResult<String> {
    if let Ok(s) = k.downcast::<PyString>() {
        return s.to_cow().map(|c| c.into_owned()).map_err(|_| {
            PyValueError::new_err(format!(
                "{}: expected UTF-8 text, found {} (a lone surrogate)",
                what(),
                k.repr().map_or_else(|_| "?".to_string(), |r| r.to_string())
            ))
        });
    }
    Err(PyTypeError::new_err(format!(
        "{}: expected str, found {}",
        what(),
        type_name(k)
    )))
}

/// A dict of arrays plus a metadata dict as an in-memory tensor file.
fn tensor_file(
    label: &str,
    tensors: &Bound<'_, PyDict>,
    metadata: Option<&Bound<'_, PyDict>>,
    finite: bool,
) -> PyResult<TensorFile> {
    let mut file = TensorFile::new(label);
    for (k, v) in tensors.iter() {
        let name = dict_key(&k, || format!("{label}: tensor names"))?;
        let t = tensor_from_array(&format!("{label}['{name}']"), &v, finite)?;
        file.tensors.insert(name, t);
    }
    if let Some(meta) = metadata {
        for (k, v) in meta.iter() {
            let key = dict_key(&k, || "metadata: keys".to_string())?;
            let value = meta_value(&key, &v)?;
            file.metadata.insert(key, value);
        }
    }
    Ok(file)
}

/// A tensor file as `(tensors, metadata)` dicts of numpy arrays and strings.
fn to_dicts<'py>(
    py: Python<'py>,
    file: TensorFile,
) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
    let tensors = PyDict::new(py);
    for (name, t) in file.tensors {
        let arr = match t {
            Tensor::F32(a) => PyArray::from_owned_array(py, a).into_any(),
            Tensor::F64(a) => PyArray::from_owned_array(py, a).into_any(),
            Tensor::I32(a) => PyArray::from_owned_array(py, a).into_any(),
            Tensor::I64(a) => PyArray::from_owned_array(py, a).into_any(),
        };
        tensors.set_item(name, arr)?;
    }
    let metadata = PyDict::new(py);
    for (k, v) in file.metadata {
        metadata.set_item(k, v)?;
    }
    Ok((tensors, metadata))
}

/// Run the stage that `metadata["stage"]` names on `tensors` (case-file
/// names): `(outputs, output_metadata)`, bit for bit what `case run` writes.
#[pyfunction]
#[pyo3(signature = (tensors, metadata, threads=None))]
fn run_case<'py>(
    py: Python<'py>,
    tensors: &Bound<'py, PyDict>,
    metadata: &Bound<'py, PyDict>,
    threads: Option<usize>,
) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
    let case = tensor_file("tensors", tensors, Some(metadata), true)?;
    let out = compute(py, threads, move || oracle::run_case(&case))?;
    to_dicts(py, out)
}

/// Read a safetensors file (F32, F64, I32, I64): `(tensors, metadata)`.
#[pyfunction]
fn load<'py>(py: Python<'py>, path: PathBuf) -> PyResult<(Bound<'py, PyDict>, Bound<'py, PyDict>)> {
    let file = compute(py, None, move || TensorFile::load(&path))?;
    to_dicts(py, file)
}

/// Write `tensors` and string `metadata` as a safetensors file (atomically).
#[pyfunction]
#[pyo3(signature = (path, tensors, metadata=None))]
fn save(
    py: Python<'_>,
    path: PathBuf,
    tensors: &Bound<'_, PyDict>,
    metadata: Option<&Bound<'_, PyDict>>,
) -> PyResult<()> {
    let mut file = tensor_file("tensors", tensors, metadata, false)?;
    file.path = path.clone();
    compute(py, None, move || file.save(&path))
}

/// Either a dict of arrays or a path to a safetensors file.
fn tensors_or_path(label: &str, obj: &Bound<'_, PyAny>) -> PyResult<TensorFile> {
    if let Ok(d) = obj.downcast::<PyDict>() {
        return tensor_file(label, d, None, false);
    }
    let path: PathBuf = obj.extract().map_err(|_| {
        PyTypeError::new_err(format!(
            "{label}: expected a dict of numpy arrays or a path to a safetensors file, found {}",
            type_name(obj)
        ))
    })?;
    TensorFile::load(&path).map_err(to_py_err)
}

/// Compare `expected` with `actual` (dicts of arrays or safetensors paths)
/// as `case compare` does: `(passed, table, report_json)`.
#[allow(clippy::too_many_arguments)]
#[pyfunction]
#[pyo3(signature = (expected, actual, tolerances_json=None, tolerances_path=None, atol=None, rtol=None, max_mismatch_fraction=None, equal_nan=None))]
fn compare<'py>(
    py: Python<'py>,
    expected: &Bound<'py, PyAny>,
    actual: &Bound<'py, PyAny>,
    tolerances_json: Option<String>,
    tolerances_path: Option<PathBuf>,
    atol: Option<f64>,
    rtol: Option<f64>,
    max_mismatch_fraction: Option<f64>,
    equal_nan: Option<bool>,
) -> PyResult<(bool, String, String)> {
    let expected = tensors_or_path("expected", expected)?;
    let actual = tensors_or_path("actual", actual)?;
    compute(py, None, move || {
        let mut tol = match (&tolerances_path, &tolerances_json) {
            (Some(p), _) => Tolerances::load(p)?,
            (None, Some(text)) => Tolerances::from_json(&PathBuf::from("tolerances"), text)?,
            (None, None) => Tolerances::default(),
        };
        if atol.is_some() {
            tol.default.atol = atol;
        }
        if rtol.is_some() {
            tol.default.rtol = rtol;
        }
        if max_mismatch_fraction.is_some() {
            tol.default.max_mismatch_fraction = max_mismatch_fraction;
        }
        if equal_nan.is_some() {
            tol.default.equal_nan = equal_nan;
        }
        let report = oracle::compare(&expected, &actual, &tol)?;
        Ok((report.passed, report.to_string(), report.to_json()))
    })
}

/// Parameter count and MACs per Gaussian (each ptflops convention) of the
/// field that `metadata` configures (the `deform` stage's keys).
#[pyfunction]
fn field_counts<'py>(
    py: Python<'py>,
    metadata: &Bound<'py, PyDict>,
) -> PyResult<Bound<'py, PyDict>> {
    let file = tensor_file("metadata", &PyDict::new(py), Some(metadata), false)?;
    let (params, aten, pytorch, no_functional) = compute(py, None, move || {
        let config = liquid_splat::oracle::field::config_from_meta(&file)?;
        Ok((
            param_count(&config)?,
            macs_per_gaussian(&config, MacConvention::Aten)?,
            macs_per_gaussian(&config, MacConvention::Pytorch)?,
            macs_per_gaussian(&config, MacConvention::PytorchNoFunctional)?,
        ))
    })?;
    let d = PyDict::new(py);
    d.set_item("params", params)?;
    d.set_item("macs_aten", aten)?;
    d.set_item("macs_pytorch", pytorch)?;
    d.set_item("macs_pytorch_no_functional", no_functional)?;
    Ok(d)
}

/// The weights of a freshly initialised field (the library's seeded
/// initialisation, PyTorch's `nn.Linear` default scheme) as a state_dict
/// of `dtype` ("float32" or "float64") arrays.
#[pyfunction]
#[pyo3(signature = (metadata, seed=0, dtype="float32"))]
fn field_init<'py>(
    py: Python<'py>,
    metadata: &Bound<'py, PyDict>,
    seed: u64,
    dtype: &str,
) -> PyResult<Bound<'py, PyDict>> {
    let file = tensor_file("metadata", &PyDict::new(py), Some(metadata), false)?;
    let f64_weights = match dtype {
        "float32" => false,
        "float64" => true,
        other => {
            return Err(PyValueError::new_err(format!(
                "dtype: expected \"float32\" or \"float64\", found {other:?}"
            )))
        }
    };
    let weights = compute(py, None, move || {
        let config = liquid_splat::oracle::field::config_from_meta(&file)?;
        Ok(if f64_weights {
            liquid_splat::oracle::field::field_to_tensor_file(&Field::<f64>::new(config, seed)?)
        } else {
            liquid_splat::oracle::field::field_to_tensor_file(&Field::<f32>::new(config, seed)?)
        })
    })?;
    Ok(to_dicts(py, weights)?.0)
}

/// Run the command-line tool on `args` (without the program name) and
/// return its exit code (0 ok, 1 check failed, 2 unusable input).
#[pyfunction]
fn cli(py: Python<'_>, args: Vec<std::ffi::OsString>) -> PyResult<u8> {
    let argv: Vec<std::ffi::OsString> =
        std::iter::once("liquid-splat".into()).chain(args).collect();
    compute(py, None, move || Ok(liquid_splat::cli::run(argv)))
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(run_case, m)?)?;
    m.add_function(wrap_pyfunction!(load, m)?)?;
    m.add_function(wrap_pyfunction!(save, m)?)?;
    m.add_function(wrap_pyfunction!(compare, m)?)?;
    m.add_function(wrap_pyfunction!(field_counts, m)?)?;
    m.add_function(wrap_pyfunction!(field_init, m)?)?;
    m.add_function(wrap_pyfunction!(cli, m)?)?;
    let tolerances = PyDict::new(m.py());
    tolerances.set_item(
        "float32",
        include_str!("../../../fixtures/cases/tolerances_f32.json"),
    )?;
    tolerances.set_item(
        "float64",
        include_str!("../../../fixtures/cases/tolerances_f64.json"),
    )?;
    m.add("RECOMMENDED_TOLERANCES", tolerances)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("STAGES", oracle::STAGES.to_vec())?;
    Ok(())
}
