"""liquid_splat.testing: the report of `case compare`, computed by the same code."""

import json

import numpy as np
import pytest

import liquid_splat as ls
from liquid_splat.testing import assert_close, compare, recommended_tolerances
from conftest import CASES


def test_report_equals_the_cli_report(tmp_path):
    e, _ = ls.load(CASES / "rasterize_f32_exact.expected.safetensors")
    a = dict(e)
    a["color"] = e["color"] + np.float32(3e-5)
    a["n_contrib"] = e["n_contrib"].copy()
    a["n_contrib"][0, 0] += 1
    del a["depth"]
    a["extra"] = np.zeros(2, np.float32)
    ls.save(tmp_path / "a.safetensors", a)
    tol = CASES / "tolerances_f32.json"
    report = compare(CASES / "rasterize_f32_exact.expected.safetensors",
                     tmp_path / "a.safetensors", tolerances=tol)
    code = ls.cli("case", "compare", str(CASES / "rasterize_f32_exact.expected.safetensors"),
                  str(tmp_path / "a.safetensors"), "--tolerances", str(tol),
                  "--report", str(tmp_path / "r.json"))
    cli = json.loads((tmp_path / "r.json").read_text())
    assert code == (0 if report.passed else 1)
    assert report.to_dict() == cli
    assert report.missing == ["depth"] and report.extra == ["extra"] and not report.passed
    # In-memory dicts give the same tensors' verdicts and statistics (only the labels differ).
    mem = compare(e, a, tolerances=json.loads(tol.read_text()))
    assert mem.tensors == report.tensors


def test_tolerances_and_overrides():
    e = {"x": np.array([1.0, 2.0, 3.0])}
    a = {"x": np.array([1.0, 2.0, 3.0 + 1e-6])}
    assert not compare(e, a).passed                       # F64 default atol 1e-7, rtol 1e-7
    assert compare(e, a, atol=1e-5).passed
    assert compare(e, a, max_mismatch_fraction=0.34).passed
    assert compare(e, a, tolerances={"tensors": {"x": {"rtol": 1e-6}}}).passed
    nan = {"x": np.array([np.nan])}
    assert not compare(nan, nan).passed and compare(nan, nan, equal_nan=True).passed
    # 0-d arrays are numbers, in arguments and in tolerance dicts.
    assert compare(e, a, atol=np.array(1e-5)).passed
    assert compare(e, a, tolerances={"tensors": {"x": {"rtol": np.array(1e-6)}}}).passed
    assert recommended_tolerances(np.float32) == recommended_tolerances("float32")
    typo = compare(e, a, tolerances={"tensors": {"X": {"rtol": 1e-6}, "x*": {"rtol": 0}}})
    assert not typo.passed and typo.unused_tolerances == ["X"]
    assert "apply to no tensor here: X" in str(typo)
    with pytest.raises(ValueError, match="unknown|bogus"):
        compare(e, a, tolerances={"default": {"bogus": 1}})
    with pytest.raises(ValueError, match="atol"):
        compare(e, a, atol=-1.0)


def test_assert_close_raises_with_the_table():
    e = {"x": np.zeros((2, 2)), "y": np.ones(3, np.float32)}
    a = {"x": np.array([[0.0, 0.5], [0.0, 0.0]]), "y": np.ones(3, np.float32)}
    with pytest.raises(AssertionError) as err:
        assert_close(a, e)
    msg = str(err.value)
    assert "(x)" in msg and "worst at [0,1]" in msg.replace(", ", ",")
    assert assert_close(e, e).passed


def test_recommended_tolerances_are_the_files():
    for dt, f in (("float32", "tolerances_f32.json"), ("float64", "tolerances_f64.json")):
        assert recommended_tolerances(dt) == json.loads((CASES / f).read_text())


def test_torch_tensors_are_accepted():
    torch = pytest.importorskip("torch")
    e = {"x": np.arange(4.0)}
    assert compare(e, {"x": torch.arange(4.0, dtype=torch.float64)}).passed


def test_tolerance_overrides_are_numbers_not_bools():
    e = {"x": np.array([1.0, 2.0])}
    a = {"x": np.array([1.0, 2.5])}
    for name in ("atol", "rtol", "max_mismatch_fraction"):
        for bad, found in ((True, "bool"), (np.False_, "bool"), ("0.1", "str")):
            with pytest.raises(TypeError, match=rf"compare\(\): argument `{name}`: expected a float or None, found {found}"):
                compare(e, a, **{name: bad})
    with pytest.raises(TypeError, match=r"compare\(\): argument `equal_nan`: expected a bool, found int"):
        compare(e, a, equal_nan=1)
    assert compare(e, a, atol=np.float32(1.0)).passed and compare(e, a, atol=1).passed


def test_equal_nan_false_replaces_the_tolerance_files_field():
    nan = {"x": np.array([np.nan])}
    assert compare(nan, nan, tolerances={"default": {"equal_nan": True}}).passed
    assert not compare(nan, nan, tolerances={"default": {"equal_nan": True}}, equal_nan=False).passed


def test_float32_elements_on_the_boundary_go_as_numpy_isclose_says():
    # Pairs within a few ulps of |a - e| = atol + rtol*|e|: the count of elements that
    # numpy.isclose (float32 arithmetic, as torch.isclose) calls not close is the report's
    # mismatch count, in float32 and with every tolerance pair.
    rng = np.random.default_rng(5)
    e = rng.uniform(-2.0, 2.0, 20000).astype(np.float32)
    for atol, rtol in ((0.0, 1e-3), (1e-5, 1.3e-6), (1e-4, 1e-2)):
        bound = atol + rtol * np.abs(e.astype(np.float64))
        side = np.where(rng.integers(0, 2, e.size) == 1, 1.0, -1.0)
        a = (e.astype(np.float64) + side * bound * (1 + rng.uniform(-1e-6, 1e-6, e.size))).astype(np.float32)
        want = int(np.count_nonzero(~np.isclose(a, e, rtol=rtol, atol=atol)))
        report = compare({"x": e}, {"x": a}, atol=atol, rtol=rtol, max_mismatch_fraction=1.0)
        got = json.loads(report.json)["tensors"][0]["stats"]["mismatches"]
        assert got == want, (atol, rtol, got, want)
        assert 0 < want < e.size


def test_int64_outputs_are_compared_exactly(tmp_path):
    """gsplat's int64 outputs (``isect_ids``, ``camera_ids``, ``gaussian_ids``) were refused
    as a dtype; they are compared exactly, beyond 2**53 too, and round-trip through files."""
    from liquid_splat import gsplat as gs

    t, _ = ls.load(CASES / "gsplat_rasterization_f64_v16.input.safetensors")
    _, _, meta = gs.rasterization(t["means"], t["quats"], t["scales"], t["opacities"], t["colors"],
                                  t["viewmats"], t["Ks"], 24, 16, sh_degree=3)
    ints = {k: v for k, v in meta.items() if isinstance(v, np.ndarray) and v.dtype == np.int64}
    assert "isect_ids" in ints and ints["isect_ids"].size > 0
    assert_close(ints, ints)
    big = np.array([(1 << 60) + 1, 5], np.int64)
    report = compare({"ids": big}, {"ids": big - np.array([1, 0], np.int64)})
    assert not report.passed and report.failures() == ["ids"]
    (row,) = report.tensors
    assert row["dtype"] == "I64" and row["stats"]["mismatches"] == 1 and row["stats"]["ulp_max"] == 1
    ls.save(tmp_path / "ids.safetensors", {"ids": big})
    back, _ = ls.load(tmp_path / "ids.safetensors")
    assert back["ids"].dtype == np.int64 and np.array_equal(back["ids"], big)
    assert compare(tmp_path / "ids.safetensors", {"ids": big}).passed
