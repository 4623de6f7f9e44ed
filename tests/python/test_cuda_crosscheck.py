"""python/cuda_crosscheck.py without a GPU: with `--standin` the oracle's own torch drop-ins
take the CUDA modules' place (same call signatures), so the script's plumbing is checked
here; its comparisons with the CUDA code need a GPU (python/README.md)."""

import json
import sys

import pytest

from conftest import ROOT

pytest.importorskip("torch")
sys.path.insert(0, str(ROOT / "python"))
import cuda_crosscheck  # noqa: E402


@pytest.mark.parametrize("args", [["inria"], ["gsplat", "--version", "1.5.3"],
                                  ["gsplat", "--version", "1.6"]])
def test_standin_agrees_with_the_oracle_it_calls(args, tmp_path, capsys):
    out = tmp_path / "r.json"
    assert cuda_crosscheck.main(args + ["--standin", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert r["standin"] and len(r["scenes"]) == (1 if args[0] == "inria" else 2)
    for scene in r["scenes"]:
        t = scene["tensors"]
        # The drop-in is the float32 oracle in the exact mode, which the standin run compares
        # with: every float tensor agrees to the bit, every integer tensor entry for entry.
        for name, rec in t.items():
            v = rec["CUDA vs ls32"]
            assert v == "0 differ" or (v["max"] == 0 and v["rel_l2"] == 0), (scene["scene"], name)
            assert rec["f32 tolerances"].startswith("pass") or name.endswith("isect_ids"), name
        grads = [k for k in t if k.startswith(("grad_", "v_"))]
        assert len(grads) >= 5, grads
        # The float64 run is a different computation: its difference is measured, not zero.
        assert any(t[k]["ls32 vs ls64"]["max"] > 0 for k in grads)
    assert "| tensor |" in capsys.readouterr().out


def test_culled_dense_rows_are_zeroed_by_their_own_radii():
    import numpy as np

    radii = np.array([[[3, 2], [0, 0], [0, 5]]], np.int32)  # the middle Gaussian is culled
    d = {"meta.radii": radii,
         "meta.means2d": np.array([[[1.0, 2.0], [9e9, -7.0], [3.0, 4.0]]], np.float32),
         "meta.depths": np.array([[5.0, np.nan, 6.0]], np.float32),
         "meta.conics": np.arange(9, dtype=np.float32).reshape(1, 3, 3)}
    cuda_crosscheck.zero_culled(d)
    assert d["meta.means2d"].tolist() == [[[1.0, 2.0], [0.0, 0.0], [3.0, 4.0]]]
    assert d["meta.depths"].tolist() == [[5.0, 0.0, 6.0]]
    assert d["meta.conics"].tolist() == [[[0, 1, 2], [0, 0, 0], [6, 7, 8]]]
    assert d["meta.radii"] is radii
