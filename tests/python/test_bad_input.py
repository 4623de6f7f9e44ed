"""The bad inputs of tests/bad_input.rs, through the package: each is a ValueError that names
the argument and the field (or tensor and flat index), never a crash or a result."""

import numpy as np
import pytest

import liquid_splat as ls
from conftest import CASES


def case(name):
    return ls.load(CASES / f"{name}.input.safetensors")


def test_counters_and_sizes_are_refused():
    t, m = case("step_f32")
    with pytest.raises(ValueError, match=r"`__metadata__\.adam\.xyz\.step`: 18446744073709551615"):
        ls.run_case(t, {**m, "adam.xyz.step": "18446744073709551615"})
    t, m = case("deform_f32_cfc")
    with pytest.raises(ValueError, match=r"`backbone_layers`: 4611686018427387904 is above the limit"):
        ls.run_case(t, {**m, "backbone_layers": "4611686018427387904"})
    # A width the weights do not have is refused by shape before the parameters are allocated.
    with pytest.raises(ValueError, match=r"`cells\.0\.backbone\.0\.weight`: expected shape \[16,65629\]"):
        ls.run_case(t, {**m, "width": "65536"})


@pytest.mark.parametrize("tensor,index,value", [
    ("viewmatrix", 5, np.nan), ("projmatrix", 0, np.inf), ("means3D", 4, np.nan),
    ("scales", 2, -np.inf), ("rotations", 7, np.nan)])
@pytest.mark.parametrize("dtype", ["f32", "f64"])
def test_non_finite_inputs_name_tensor_and_flat_index(tensor, index, value, dtype):
    t, m = case(f"rasterize_{dtype}_exact")
    bad = t[tensor].copy()
    bad.flat[index] = value
    with pytest.raises(ValueError, match=rf"tensors\['{tensor}'\]: expected finite values, found .* at flat index {index}"):
        ls.run_case({**t, tensor: bad}, m)


@pytest.mark.parametrize("key,value", [("scale_modifier", "NaN"), ("tanfovx", "inf"), ("tanfovy", float("nan"))])
def test_non_finite_settings_are_refused(key, value):
    t, m = case("rasterize_f64_exact")
    with pytest.raises(ValueError, match=rf"`__metadata__\.{key}`: .* not finite"):
        ls.run_case(t, {**m, key: value})


def test_loss_weight_outside_its_range_is_refused():
    t, m = case("loss_f64")
    with pytest.raises(ValueError, match=r"`__metadata__\.lambda_dssim`: 1\.5 \(must be in \[0, 1\]\)"):
        ls.run_case(t, {**m, "lambda_dssim": "1.5"})


def test_a_learning_rate_whose_step_overflows_the_dtype_is_refused():
    """lr.xyz = 1e300 is finite (the f64 check) but its step is not in f32: new.xyz came
    back inf without a word."""
    t, m = case("step_f32")
    with pytest.raises(ValueError, match=r"learning rate`?: 1e300: step 8's size lr/\(1 − β1\^8\) = 1\.7.*e300 "
                                         r"is not finite in f32"):
        ls.run_case(t, {**m, "lr.xyz": "1e300"})
    t, m = case("step_f64")
    out, _ = ls.run_case(t, {**m, "lr.xyz": "1e300"})
    assert np.isfinite(out["new.xyz"]).all()
