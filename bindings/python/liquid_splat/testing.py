"""Comparison of a backend's outputs with the oracle's, for test suites.

:func:`compare` returns the report of ``liquid-splat case compare`` (computed by the same Rust
code: the same pass/fail rule, statistics, worst element and table); :func:`assert_close`
raises ``AssertionError`` with the report's table as its message. Tolerances: the dtype
defaults (F32 ``atol 1e-5, rtol 1.3e-6``; F64 ``atol 1e-7, rtol 1e-7``; int32 and int64
exact), or a tolerance file as the CLI reads it (a path, or the same structure as a dict;
format in docs/ORACLE.md), or :func:`recommended_tolerances`; ``atol``/``rtol``/
``max_mismatch_fraction``/``equal_nan`` replace the fields of its ``default``.
"""

from __future__ import annotations

import json
import math
import os
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

import numpy as np

from . import _native, _not_masked, _path

__all__ = ["CompareReport", "compare", "assert_close", "recommended_tolerances"]

Tolerances = Union[str, "os.PathLike[str]", Mapping[str, Any]]
Outputs = Union[str, "os.PathLike[str]", Mapping[str, Any], Tuple[Mapping[str, Any], Mapping[str, str]]]


class CompareReport:
    """The comparison report: ``passed``, one entry per compared tensor in ``tensors``
    (name, status, dtypes, shapes, tolerance, problems, stats with the worst element),
    ``missing`` (expected tensors absent from actual: failures), ``extra`` (only in
    actual: listed, not failed) and ``unused_tolerances`` (entries of the tolerances'
    ``tensors`` that apply to no expected tensor, such as a misspelt name: listed, not
    failed). ``str(report)`` is the table ``case compare`` prints;
    ``report.json`` is the JSON ``case compare --report`` writes."""

    def __init__(self, passed: bool, table: str, text: str):
        self.passed: bool = passed
        self.table: str = table
        self.json: str = text
        d = json.loads(text)
        self.tensors: List[Dict[str, Any]] = d["tensors"]
        self.missing: List[str] = d["missing"]
        self.extra: List[str] = d["extra"]
        self.unused_tolerances: List[str] = d["unused_tolerances"]

    def to_dict(self) -> Dict[str, Any]:
        """The report as the JSON object ``case compare --report`` writes."""
        return json.loads(self.json)

    def failures(self) -> List[str]:
        """Names of the tensors that failed or are missing."""
        return [t["name"] for t in self.tensors if t["status"] != "pass"] + list(self.missing)

    def __str__(self) -> str:
        return self.table

    def __repr__(self) -> str:
        return f"<CompareReport passed={self.passed} tensors={len(self.tensors)} failures={self.failures()}>"


def _array(name: str, v: Any) -> np.ndarray:
    _not_masked(f"compare(): {name}", v)
    try:
        if hasattr(v, "detach") and hasattr(v, "cpu"):  # a torch tensor
            v = v.detach().cpu().numpy()
        return np.ascontiguousarray(np.asarray(v))
    # (A ragged list, a bfloat16 tensor, a tensor on the meta device, ...)
    except (TypeError, ValueError, NotImplementedError, RuntimeError) as e:
        raise TypeError(f"compare(): {name}: expected an array, found {type(v).__name__} ({e})") from None


def _outputs(which: str, x: Outputs) -> Union[str, Dict[str, np.ndarray]]:
    if isinstance(x, (str, bytes, os.PathLike)):
        return _path("compare", which, x)
    if isinstance(x, tuple) and len(x) == 2 and isinstance(x[0], Mapping):
        x = x[0]  # (tensors, metadata) from run_case / load
    if not isinstance(x, Mapping):
        raise TypeError(
            f"{which}: expected a dict of arrays, a (tensors, metadata) pair or a path to a "
            f"safetensors file, found {type(x).__name__}"
        )
    return {str(k): _array(f"{which}[{k!r}]", v) for k, v in x.items()}


def _tolerance(name: str, x: Any) -> Optional[float]:
    """``atol``, ``rtol`` or ``max_mismatch_fraction``: None or a number (not a bool); the
    library checks the range and names the field."""
    if x is None:
        return None
    x = _zero_d(x)
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
        raise TypeError(f"compare(): argument `{name}`: expected a float or None, found {type(x).__name__}")
    try:
        return float(x)
    except OverflowError:  # an int beyond float's range
        raise ValueError(
            f"compare(): argument `{name}`: expected a finite number, found an integer of "
            f"{int(x).bit_length()} bits, beyond float's range"
        ) from None


def _zero_d(x: Any) -> Any:
    """A 0-d numpy array or torch tensor as its scalar; anything else as it is."""
    if isinstance(x, np.ndarray) and x.ndim == 0:
        return x[()]
    if hasattr(x, "detach") and hasattr(x, "dim") and x.dim() == 0:  # a 0-d torch tensor
        return x.item()
    return x


def _json_number(x: Any) -> Any:
    """numpy scalars (and 0-d arrays and tensors) in a tolerances dict as the Python numbers
    ``json`` writes."""
    x = _zero_d(x)
    if isinstance(x, (bool, int, float)):
        return x
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.floating):  # (float(), not .item(): a longdouble's item is itself)
        return float(x)
    raise TypeError(f"expected JSON values (numbers, bools, strings, dicts), found {type(x).__name__}")


def _check_finite(path: str, x: Any) -> None:
    """A NaN or infinity anywhere in a tolerances dict, named by its path (``json`` would
    write it as ``NaN``, which no JSON reader takes)."""
    x = _zero_d(x)
    if isinstance(x, Mapping):
        for k, v in x.items():
            _check_finite(f"{path}.{k}" if path else str(k), v)
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            _check_finite(f"{path}[{i}]", v)
    elif isinstance(x, (float, np.floating)) and not math.isfinite(float(x)):
        raise ValueError(f"compare(): argument `tolerances`: `{path}`: expected a finite number, found {x}")


def recommended_tolerances(dtype: Any = "float32") -> Dict[str, Any]:
    """The recommended tolerance file for a backend in ``dtype`` (float32 or float64;
    ``fixtures/cases/tolerances_f32.json`` / ``tolerances_f64.json``), as a dict."""
    where = "recommended_tolerances(): argument `dtype`"
    if type(dtype).__module__ == "torch" and type(dtype).__name__ == "dtype":  # torch.float32
        dtype = str(dtype).removeprefix("torch.")
    try:
        key = np.dtype(dtype).name
    except (TypeError, ValueError):
        raise TypeError(f"{where}: expected float32 or float64, found {dtype!r}") from None
    if key not in _native.RECOMMENDED_TOLERANCES:
        raise TypeError(f"{where}: expected float32 or float64, found {key}")
    return json.loads(_native.RECOMMENDED_TOLERANCES[key])


def compare(
    expected: Outputs,
    actual: Outputs,
    *,
    tolerances: Optional[Tolerances] = None,
    atol: Optional[float] = None,
    rtol: Optional[float] = None,
    max_mismatch_fraction: Optional[float] = None,
    equal_nan: Optional[bool] = None,
) -> CompareReport:
    """Compare every tensor of ``expected`` (the oracle's outputs) with ``actual``.

    Each is a dict of arrays (numpy, or torch tensors, copied to C order), a
    ``(tensors, metadata)`` pair, or a path to a safetensors file. Element ``(a, e)``
    matches when ``|a − e| ≤ atol + rtol·|e|`` (in float32 for float32 tensors, as
    ``torch.isclose`` evaluates it); a tensor passes when its mismatches are at
    most ``floor(max_mismatch_fraction · numel)``. Unusable input (bad tolerances, an
    unreadable file, an empty ``expected``, an unsupported dtype) raises ``ValueError`` or
    ``TypeError``; mismatches never raise, they are in the report.
    """
    tol_json: Optional[str] = None
    tol_path: Optional[str] = None
    if isinstance(tolerances, (str, bytes, os.PathLike)):
        tol_path = _path("compare", "tolerances", tolerances)
    elif isinstance(tolerances, Mapping):
        _check_finite("", tolerances)
        try:
            tol_json = json.dumps(tolerances, default=_json_number)
        except (TypeError, ValueError) as e:
            raise TypeError(f"compare(): argument `tolerances`: {e}") from None
    elif tolerances is not None:
        raise TypeError(
            "compare(): argument `tolerances`: expected a path to a tolerance file or a dict, "
            f"found {type(tolerances).__name__}"
        )
    if equal_nan is not None and not isinstance(equal_nan, (bool, np.bool_)):
        raise TypeError(f"compare(): argument `equal_nan`: expected a bool, found {type(equal_nan).__name__}")
    passed, table, text = _native.compare(
        _outputs("expected", expected),
        _outputs("actual", actual),
        tol_json,
        tol_path,
        _tolerance("atol", atol),
        _tolerance("rtol", rtol),
        _tolerance("max_mismatch_fraction", max_mismatch_fraction),
        None if equal_nan is None else bool(equal_nan),
    )
    return CompareReport(passed, table, text)


def assert_close(
    actual: Outputs,
    expected: Outputs,
    *,
    tolerances: Optional[Tolerances] = None,
    atol: Optional[float] = None,
    rtol: Optional[float] = None,
    max_mismatch_fraction: Optional[float] = None,
    equal_nan: Optional[bool] = None,
) -> CompareReport:
    """Raise ``AssertionError`` (message: the report's table) unless :func:`compare`
    passes; return the report otherwise. Argument order as ``torch.testing.assert_close``:
    ``actual`` (the backend's outputs) first, then ``expected`` (the oracle's)."""
    report = compare(
        expected,
        actual,
        tolerances=tolerances,
        atol=atol,
        rtol=rtol,
        max_mismatch_fraction=max_mismatch_fraction,
        equal_nan=equal_nan,
    )
    if not report.passed:
        raise AssertionError(
            f"outputs differ from the oracle's ({', '.join(report.failures())}):\n{report.table}"
        )
    return report
