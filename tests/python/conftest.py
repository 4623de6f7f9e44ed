"""Shared helpers of the Python package's tests (run: scripts/test, or pytest after
`pip install .`)."""

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
CASES = ROOT / "fixtures" / "cases"
GOLDEN = sorted(p.name[: -len(".input.safetensors")] for p in CASES.glob("*.input.safetensors"))


def bits_equal(a: dict, b: dict) -> None:
    """Same names, dtypes, shapes and bytes."""
    assert sorted(a) == sorted(b)
    for k in a:
        assert a[k].dtype == b[k].dtype, k
        assert a[k].shape == b[k].shape, k
        assert a[k].tobytes() == b[k].tobytes(), k


@pytest.fixture(params=GOLDEN)
def golden(request):
    import liquid_splat as ls

    name = request.param
    t, m = ls.load(CASES / f"{name}.input.safetensors")
    e, em = ls.load(CASES / f"{name}.expected.safetensors")
    return name, t, m, e, em


def raster_kwargs(t: dict, m: dict) -> dict:
    """rasterize() keywords from a rasterize case."""
    kw = dict(
        viewmatrix=t["viewmatrix"], projmatrix=t["projmatrix"], campos=t["campos"], bg=t["bg"],
        image_height=int(m["image_height"]), image_width=int(m["image_width"]),
        tanfovx=float(m["tanfovx"]), tanfovy=float(m["tanfovy"]),
        scale_modifier=float(m["scale_modifier"]),
    )
    if "sh_degree" in m:
        kw["sh_degree"] = int(m["sh_degree"])
    return kw


def raster_inputs(t: dict) -> dict:
    names = ("means3D", "opacities", "shs", "colors_precomp", "scales", "rotations", "cov3D_precomp")
    return {k: t[k] for k in names if k in t}


def weights(t: dict) -> dict:
    """The field weights of a deform or step case (everything under a module name)."""
    prefixes = ("timenet.", "linear.", "gaussian_", "branch_", "cells.", "skip.", "head.")
    return {k: v for k, v in t.items() if k.startswith(prefixes)}
