"""The package against the independent PyTorch references in python/ (written from the
specification, gradients by autograd; the rasterizer's `inria` mode by a port of
backward.cu): every f64 golden case, in-process, within the recommended f64 tolerances and
a relative L2 error of at most 1e-10 per tensor. Skipped without torch and safetensors (and
ncps for the CfC cases). The gsplat stages have no reference here: python/gsplat_crosscheck.py
compares them with gsplat's own torch functions (from a gsplat checkout)."""

import sys

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("safetensors")

import liquid_splat as ls  # noqa: E402
from liquid_splat.testing import compare, recommended_tolerances  # noqa: E402
from conftest import CASES, GOLDEN, ROOT  # noqa: E402


@pytest.fixture(scope="module")
def refs():
    sys.path.insert(0, str(ROOT / "python"))  # the references import each other lazily
    import reference_deform
    import reference_loss
    import reference_raster
    import reference_step

    yield {"rasterize": reference_raster.render, "deform": reference_deform.run,
           "loss": reference_loss.run, "step": reference_step.run}
    sys.path.remove(str(ROOT / "python"))


@pytest.mark.parametrize("name", [n for n in GOLDEN if "f64" in n and not n.startswith("gsplat_")])
def test_matches_the_pytorch_reference(name, refs):
    t, m = ls.load(CASES / f"{name}.input.safetensors")
    if "cfc" in name or m.get("field") == "cfc":
        pytest.importorskip("ncps")
    ours, _ = ls.run_case(t, m)
    theirs = refs[m["stage"]](dict(m), {k: torch.from_numpy(v) for k, v in t.items()})
    report = compare(ours, theirs, tolerances=recommended_tolerances("float64"))
    assert report.passed, report.table
    assert not report.missing
    for r in report.tensors:
        assert r["stats"]["rel_l2"] <= 1e-10 or r["stats"]["max_abs_error"] == 0, (r["name"], r["stats"])
