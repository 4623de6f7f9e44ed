"""Example: checking a PyTorch "backend" against the liquid-splat oracle from pytest.

The backend under test here is a plain torch implementation of the `loss` stage
((1 - 0.2) L1 + 0.2 (1 - SSIM) and its gradient); a real backend would call its own
kernels instead. The flow is the one docs/ORACLE.md describes:

1. build the case's inputs in torch and write them with safetensors (metadata = strings);
2. `liquid-splat case run` writes the expected outputs;
3. the backend writes its outputs under the same names;
4. `liquid-splat case compare --tolerances ... --report r.json` decides (exit 0 pass,
   1 fail, 2 unusable input) and the JSON report says where and by how much.

Run:  cargo build --release && pytest python/example_pytest.py
Needs CPU PyTorch and safetensors; skipped when they or the binary are missing. Not part of
`cargo test`.
"""

import json
import math
import os
import shutil
import subprocess
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")
st_torch = pytest.importorskip("safetensors.torch")

ROOT = Path(__file__).resolve().parent.parent


def binary():
    """$LIQUID_SPLAT_BIN, else target/release/liquid-splat, else liquid-splat on PATH."""
    for cand in (os.environ.get("LIQUID_SPLAT_BIN"),
                 ROOT / "target" / "release" / "liquid-splat",
                 shutil.which("liquid-splat")):
        if cand and Path(cand).is_file() and os.access(cand, os.X_OK):
            return str(cand)
    return None


BIN = binary()
pytestmark = pytest.mark.skipif(BIN is None, reason="liquid-splat binary not found "
                                "(cargo build --release, or set LIQUID_SPLAT_BIN)")


# ---- the "backend": torch L1 + SSIM, written from the stage's definition ----

def ssim(img, gt):
    """Mean SSIM of [C,H,W] images: 11x11 Gaussian window (sigma 1.5) whose 1-D values are
    computed in f64 and stored in the image dtype, normalised in that dtype; zero padding 5."""
    c = img.shape[0]
    g = torch.tensor([math.exp(-((k - 5) ** 2) / (2 * 1.5 ** 2)) for k in range(11)],
                     dtype=img.dtype)
    g = (g / g.sum())[:, None]
    w = (g @ g.T).expand(c, 1, 11, 11).contiguous()
    conv = lambda x: torch.nn.functional.conv2d(x[None], w, padding=5, groups=c)[0]
    mu1, mu2 = conv(img), conv(gt)
    s1 = conv(img * img) - mu1 * mu1
    s2 = conv(gt * gt) - mu2 * mu2
    s12 = conv(img * gt) - mu1 * mu2
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    m = ((2 * mu1 * mu2 + c1) * (2 * s12 + c2)) / ((mu1 * mu1 + mu2 * mu2 + c1) * (s1 + s2 + c2))
    return m.mean()


def backend_loss(image, gt, lam=0.2):
    """The outputs of stage `loss`, under the oracle's names and shapes."""
    img = image.clone().requires_grad_(True)
    l1 = (img - gt).abs().mean()
    s = ssim(img, gt)
    loss = (1 - lam) * l1 + lam * (1 - s)
    loss.backward()
    scalar = lambda v: v.detach().reshape(())          # rank-0 tensors, shape []
    return {"l1": scalar(l1), "ssim": scalar(s), "loss": scalar(loss), "grad_image": img.grad}


# ---- helpers around the CLI ----

def write(path, tensors, meta=None):
    st_torch.save_file({k: v.detach().contiguous() for k, v in tensors.items()}, str(path),
                       metadata=meta)


def run_case(case, out):
    r = subprocess.run([BIN, "case", "run", str(case), str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return st_torch.load_file(str(out))


def compare(expected, actual, tolerances, report):
    r = subprocess.run([BIN, "case", "compare", str(expected), str(actual),
                        "--tolerances", str(tolerances), "--report", str(report)],
                       capture_output=True, text=True)
    assert r.returncode in (0, 1), f"unusable input (exit {r.returncode}): {r.stderr}"
    return r.returncode, json.loads(Path(report).read_text()), r.stdout


def make_case(tmp_path, dtype, seed=0, h=24, w=32):
    g = torch.Generator().manual_seed(seed)
    gt = torch.rand(3, h, w, generator=g, dtype=torch.float64)
    image = gt + 0.1 * torch.randn(3, h, w, generator=g, dtype=torch.float64)
    inputs = {"image": image.to(dtype), "gt": gt.to(dtype)}
    case = tmp_path / "case.safetensors"
    write(case, inputs, {"stage": "loss", "lambda_dssim": "0.2"})
    return case, inputs


# ---- the tests ----

@pytest.mark.parametrize("dtype,tol", [(torch.float32, "tolerances_f32.json"),
                                       (torch.float64, "tolerances_f64.json")])
def test_backend_matches_the_oracle(tmp_path, dtype, tol):
    case, inputs = make_case(tmp_path, dtype)
    expected = tmp_path / "expected.safetensors"
    run_case(case, expected)
    actual = tmp_path / "actual.safetensors"
    write(actual, backend_loss(inputs["image"], inputs["gt"]))
    code, report, table = compare(expected, actual, ROOT / "fixtures" / "cases" / tol,
                                  tmp_path / "report.json")
    print(table)
    assert code == 0 and report["passed"], table
    for t in report["tensors"]:
        assert t["stats"]["cosine"] > 0.999999, t["name"]


def test_a_crafted_mismatch_fails_with_exit_1(tmp_path):
    case, inputs = make_case(tmp_path, torch.float64, seed=1)
    expected = tmp_path / "expected.safetensors"
    run_case(case, expected)
    out = backend_loss(inputs["image"], inputs["gt"])
    out["grad_image"][1, 2, 3] += 1e-6                 # one wrong element, relative ~3e-3
    actual = tmp_path / "actual.safetensors"
    write(actual, out)
    code, report, table = compare(expected, actual,
                                  ROOT / "fixtures" / "cases" / "tolerances_f64.json",
                                  tmp_path / "report.json")
    assert code == 1 and not report["passed"]
    bad = [t for t in report["tensors"] if t["status"] == "fail"]
    assert [t["name"] for t in bad] == ["grad_image"]
    assert bad[0]["stats"]["mismatches"] == 1
    assert bad[0]["stats"]["worst"]["index"] == [1, 2, 3]


def test_golden_fixture_without_running_the_oracle(tmp_path):
    """Backend CI can also compare against the committed expected outputs directly."""
    d = ROOT / "fixtures" / "cases"
    inputs = st_torch.load_file(str(d / "loss_f64.input.safetensors"))
    actual = tmp_path / "actual.safetensors"
    write(actual, backend_loss(inputs["image"], inputs["gt"]))
    code, report, table = compare(d / "loss_f64.expected.safetensors", actual,
                                  d / "tolerances_f64.json", tmp_path / "report.json")
    assert code == 0, table
