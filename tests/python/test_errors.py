"""Bad arguments raise TypeError / ValueError naming the argument, what was expected and
what was found; nothing crashes the interpreter."""

import numpy as np
import pytest

import liquid_splat as ls
from conftest import CASES, raster_inputs, raster_kwargs, weights


@pytest.fixture
def raster():
    t, m = ls.load(CASES / "rasterize_f64_exact.input.safetensors")
    return raster_inputs(t), raster_kwargs(t, m)


def test_rasterize_bad_arguments(raster):
    ins, kw = raster
    cases = [
        (dict(means3D=ins["means3D"][:, :2].copy()), ValueError, r"`means3D`: expected shape \[N,3\], found shape \[9,2\]"),
        (dict(opacities=ins["opacities"][:4]), ValueError, r"`opacities`: expected shape \[N,1\] with N=9 from `means3D`, found shape \[4,1\]"),
        (dict(scales=ins["scales"].astype(np.float32)), TypeError, r"`scales`: expected dtype float64 \(the dtype of `means3D`\), found dtype float32"),
        (dict(rotations=ins["rotations"].astype(np.int64)), TypeError, r"`rotations`: expected dtype float32 or float64, found dtype int64"),
        (dict(means3D=ins["means3D"].tolist()), TypeError, r"`means3D`: expected a numpy.ndarray .* found list"),
        (dict(shs=np.asfortranarray(ins["shs"])), ValueError, r"`shs`: expected a C-contiguous array"),
        (dict(means3D=np.where(np.arange(27).reshape(9, 3) == 4, np.nan, ins["means3D"])), ValueError, r"`means3D`: expected finite values, found nan at flat index 4"),
    ]
    for change, exc, msg in cases:
        with pytest.raises(exc, match=msg):
            ls.rasterize(**{**ins, **change}, **kw)
    with pytest.raises(ValueError, match="exactly one of `shs` and `colors_precomp`, found both"):
        ls.rasterize(**ins, colors_precomp=ins["means3D"], **kw)
    with pytest.raises(ValueError, match="`sh_degree`: expected an integer in 0..=3, found 4"):
        ls.rasterize(**ins, **{**kw, "sh_degree": 4})
    with pytest.raises(ValueError, match="`tanfovx`: expected a finite positive number, found -1.0"):
        ls.rasterize(**ins, **{**kw, "tanfovx": -1.0})
    with pytest.raises(ValueError, match="`image_width`: expected an integer >= 1, found 0"):
        ls.rasterize(**ins, **{**kw, "image_width": 0})
    with pytest.raises(ValueError, match=r"`viewmatrix`: expected shape \[4,4\], found shape \[16\]"):
        ls.rasterize(**ins, **{**kw, "viewmatrix": kw["viewmatrix"].ravel()})
    with pytest.raises(ValueError, match=r"`grad_color`: expected shape \[3,24,32\], found shape \[3,32,24\]"):
        ls.rasterize_vjp(**ins, **kw, grad_color=np.zeros((3, 32, 24)))
    with pytest.raises(ValueError, match="`gradient`: expected one of 'exact', 'inria', found 'fast'"):
        ls.rasterize_vjp(**ins, **kw, grad_color=np.zeros((3, 24, 32)), gradient="fast")


def test_run_case_bad_inputs():
    t, m = ls.load(CASES / "loss_f64.input.safetensors")
    with pytest.raises(ValueError, match="unknown stage `blend`"):
        ls.run_case(t, {**m, "stage": "blend"})
    with pytest.raises(ValueError, match="missing tensor `gt`"):
        ls.run_case({"image": t["image"]}, m)
    with pytest.raises(ValueError, match=r"unexpected tensor\(s\): extra"):
        ls.run_case({**t, "extra": t["gt"]}, m)
    with pytest.raises(TypeError, match=r"tensors\['gt'\]: expected dtype float32, float64 or int32 .*found dtype float16"):
        ls.run_case({**t, "gt": t["gt"].astype(np.float16)}, m)
    with pytest.raises(TypeError, match=r"tensor `image`: expected dtype F32 like `gt`, found F64"):
        ls.run_case({**t, "gt": t["gt"].astype(np.float32)}, m)
    with pytest.raises(ValueError, match=r"tensors\['gt'\]: expected a C-contiguous array"):
        ls.run_case({**t, "gt": t["gt"][:, ::2]}, m)
    with pytest.raises(ValueError, match=r"tensors\['gt'\]: expected finite values, found inf"):
        ls.run_case({**t, "gt": np.full_like(t["gt"], np.inf)}, m)
    with pytest.raises(TypeError, match=r"tensors\['gt'\]: expected a numpy.ndarray"):
        ls.run_case({**t, "gt": 1.0}, m)
    with pytest.raises(TypeError, match=r"metadata\['lambda_dssim'\]: expected str, bool, int or float, found list"):
        ls.run_case(t, {**m, "lambda_dssim": [0.2]})
    with pytest.raises(ValueError, match="threads: expected a positive number"):
        ls.run_case(t, m, threads=0)
    with pytest.raises(ValueError, match="lambda_dssim"):
        ls.loss(t["image"], t["gt"], lambda_dssim=1.5)
    with pytest.raises(ValueError, match=r"`gt`: expected shape \[3,H,W\] with H=24 from `image`"):
        ls.loss(t["image"], t["gt"][:, :10].copy())


def test_field_bad_inputs():
    t, m = ls.load(CASES / "deform_f64_mlp.input.safetensors")
    sd = weights(t)
    with pytest.raises(ValueError, match="linear.0.weight"):
        ls.DeformNetwork({"foo.weight": sd["linear.0.weight"]})
    bad = dict(sd)
    bad["gaussian_warp.weight"] = bad["gaussian_warp.weight"][:, :5].copy()
    with pytest.raises(ValueError, match=r"tensor `gaussian_warp.weight`: expected shape \[3,32\], found shape \[3,5\]"):
        ls.DeformNetwork(bad)
    with pytest.raises(ValueError, match=r"unexpected tensor\(s\): branch_v.weight"):
        ls.DeformNetwork({**sd, "branch_v.weight": sd["gaussian_warp.weight"]})
    with pytest.raises(TypeError, match=r"state_dict\['linear.1.bias'\]: expected dtype float64 like the other weights"):
        ls.DeformNetwork({**sd, "linear.1.bias": sd["linear.1.bias"].astype(np.float32)})
    field = ls.DeformNetwork(sd)
    with pytest.raises(TypeError, match=r"`xyz`: expected dtype float64 \(the dtype of the state_dict\), found dtype float32"):
        field.forward(t["xyz"].astype(np.float32), t["t"])
    with pytest.raises(ValueError, match=r"`t`: expected shape \[N,1\] with N=8 from `xyz`"):
        field.forward(t["xyz"], t["t"][:3])
    with pytest.raises(ValueError, match="convention"):
        field.macs("flops")
    with pytest.raises(ValueError, match="activation"):
        ls.CfCField(weights(ls.load(CASES / "deform_f64_cfc.input.safetensors")[0]), activation="softmax")


def test_compare_unusable_input(tmp_path):
    from liquid_splat.testing import compare

    with pytest.raises(ValueError, match="no tensors"):
        compare({}, {})
    with pytest.raises(ValueError, match="nope.safetensors"):
        compare(tmp_path / "nope.safetensors", {})
    with pytest.raises(TypeError, match="expected a dict"):
        compare(3, {})


def test_cli_usage_errors_are_exit_codes(capfd):
    assert ls.cli("case", "frobnicate") == 2
    assert ls.cli("--help") == 0
