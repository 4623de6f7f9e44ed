"""Example: checking a backend against the liquid-splat oracle from pytest, in-process.

The backend under test here is a plain numpy implementation of the `loss` stage's forward
((1 - 0.2) L1 + 0.2 (1 - SSIM)); a real backend would call its own kernels (CUDA, Triton,
...) and convert their outputs to numpy (or pass torch tensors: `liquid_splat.testing`
accepts both). The flow docs/ORACLE.md describes:

1. make the inputs (any float32 or float64 arrays);
2. the oracle computes the expected outputs (`liquid_splat.loss`, or `run_case` for any stage);
3. the backend computes its outputs under the same names;
4. `liquid_splat.testing.assert_close` fails the test with the comparison table (worst
   element, ULP distance, relative L2, ...) when a tensor is outside its tolerance.

Run:  pip install . && pytest python/example_pytest.py     (numpy and pytest only)
"""

import math

import numpy as np
import pytest

import liquid_splat
from liquid_splat.testing import assert_close, compare, recommended_tolerances


# ---- the "backend": numpy L1 + SSIM forward, written from the stage's definition ----

def ssim(img, gt):
    """Mean SSIM of [C,H,W] images: 11x11 Gaussian window (sigma 1.5), zero padding 5."""
    g = np.array([math.exp(-((k - 5) ** 2) / (2 * 1.5 ** 2)) for k in range(11)])
    w = np.outer(g, g) / g.sum() ** 2
    h, wd = img.shape[1:]

    def conv(x):
        p = np.pad(x, ((0, 0), (5, 5), (5, 5)))
        return sum(w[i, j] * p[:, i:i + h, j:j + wd] for i in range(11) for j in range(11))

    mu1, mu2 = conv(img), conv(gt)
    s1, s2, s12 = conv(img * img) - mu1 ** 2, conv(gt * gt) - mu2 ** 2, conv(img * gt) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    return (((2 * mu1 * mu2 + c1) * (2 * s12 + c2))
            / ((mu1 ** 2 + mu2 ** 2 + c1) * (s1 + s2 + c2))).mean()


def backend_loss(image, gt, lam=0.2):
    """The forward outputs of stage `loss` under the oracle's names (rank-0 arrays)."""
    l1 = np.abs(image - gt).mean()
    s = ssim(image, gt)
    out = {"l1": l1, "ssim": s, "loss": (1 - lam) * l1 + lam * (1 - s)}
    return {k: np.asarray(v, dtype=image.dtype) for k, v in out.items()}


def make_inputs(dtype, seed=0, h=24, w=32):
    rng = np.random.default_rng(seed)
    gt = rng.random((3, h, w))
    image = gt + 0.1 * rng.standard_normal((3, h, w))
    return image.astype(dtype), gt.astype(dtype)


# ---- the tests ----

@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_backend_matches_the_oracle(dtype):
    image, gt = make_inputs(dtype)
    oracle = liquid_splat.loss(image, gt, lambda_dssim=0.2)
    expected = {k: oracle[k] for k in ("l1", "ssim", "loss")}   # forward outputs only
    # The backend computes in float64 whatever the input: within float32 tolerances.
    report = assert_close(backend_loss(image, gt), expected,
                          tolerances=recommended_tolerances(dtype))
    assert report.passed and len(report.tensors) == 3


def test_a_broken_backend_fails_with_the_table():
    image, gt = make_inputs(np.float64)
    oracle = liquid_splat.loss(image, gt)
    broken = backend_loss(image, gt, lam=0.25)                   # wrong lambda
    with pytest.raises(AssertionError) as e:
        assert_close(broken, {k: oracle[k] for k in ("l1", "ssim", "loss")})
    assert "loss" in str(e.value) and "FAIL" in str(e.value).upper()
    report = compare({k: oracle[k] for k in ("l1", "ssim", "loss")}, broken)
    assert report.failures() == ["loss"]                        # l1 and ssim still agree
    worst = report.tensors[[t["name"] for t in report.tensors].index("loss")]["stats"]["worst"]
    assert worst["expected"] == pytest.approx(float(oracle["loss"]))
