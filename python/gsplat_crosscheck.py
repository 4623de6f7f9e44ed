"""Cross-check the gsplat oracle stages against gsplat's own CPU-runnable torch reference.

gsplat's `gsplat/cuda/_torch_impl.py` (and, at 1.6, `_math.py` / `_constants.py`) holds plain
torch versions of `quat_scale_to_covar_preci`, `spherical_harmonics`, `fully_fused_projection`,
`isect_tiles` and `isect_offset_encode`. Their `rasterize_to_pixels` calls a CUDA kernel
(`rasterize_to_indices_in_range`), so it cannot run here. This script loads those files from a
gsplat git checkout at the requested revision (so no CUDA build is needed), builds cases with
`liquid-splat case new`, runs `liquid-splat case run`, evaluates gsplat's torch functions in
float64 on the same inputs, takes their gradients with autograd for the same cotangents, and
prints the largest relative difference per tensor.

    python python/gsplat_crosscheck.py --repo PATH/TO/gsplat --rev v1.5.3 --version 1.5.3
    python python/gsplat_crosscheck.py --repo PATH/TO/gsplat --rev c3d59bbb --version 1.6

The torch reference is "a minimal implementation" (its own docstrings): its radii ignore the
opacities and `radius_clip`, so the projection case is run without `opacities` (then the
oracle's radii follow the same 3.33-sigma rule), and its `isect_tiles` is the radius box at both
versions (AccuTile is CUDA-only), so `isect_tiles` is compared without conics (radius box at
both versions; the key bit widths follow the version).
Exit status 0 when every tensor agrees to `--rtol` (relative to the tensor's largest entry).
"""

import argparse
import enum
import os
import subprocess
import sys
import tempfile
import types
import typing

import torch
from safetensors.torch import load_file, save_file


def load_torch_impl(repo, rev):
    """gsplat.cuda._torch_impl (plus _math, _constants) at `rev`, as a module, without CUDA."""

    def show(path):
        return subprocess.run(
            ["git", "-C", repo, "show", f"{rev}:{path}"], check=True, capture_output=True, text=True
        ).stdout

    pkg = types.ModuleType("gsplat")
    pkg.__path__ = []
    cuda = types.ModuleType("gsplat.cuda")
    cuda.__path__ = []
    sys.modules["gsplat"] = pkg
    sys.modules["gsplat.cuda"] = cuda
    helper = types.ModuleType("gsplat._helper")
    helper.assert_shape = lambda name, x, shape: None
    sys.modules["gsplat._helper"] = helper
    # Only names the torch reference imports at module level; nothing here reaches CUDA.
    wrapper = types.ModuleType("gsplat.cuda._wrapper")
    wrapper.CameraModel = typing.Literal["pinhole", "ortho", "fisheye", "ftheta"]

    class RollingShutterType(enum.IntEnum):
        GLOBAL = 0

    wrapper.RollingShutterType = RollingShutterType
    sys.modules["gsplat.cuda._wrapper"] = wrapper
    for name in ["_constants", "_math"]:
        try:
            src = show(f"gsplat/cuda/{name}.py")
        except subprocess.CalledProcessError:
            continue
        mod = types.ModuleType(f"gsplat.cuda.{name}")
        mod.__package__ = "gsplat.cuda"
        exec(compile(src, f"{rev}:gsplat/cuda/{name}.py", "exec"), mod.__dict__)
        sys.modules[f"gsplat.cuda.{name}"] = mod
    mod = types.ModuleType("gsplat.cuda._torch_impl")
    mod.__package__ = "gsplat.cuda"
    exec(compile(show("gsplat/cuda/_torch_impl.py"), f"{rev}:_torch_impl.py", "exec"), mod.__dict__)
    if not hasattr(mod, "_quat_scale_to_covar_preci"):
        mod._quat_scale_to_covar_preci = sys.modules["gsplat.cuda._math"]._quat_scale_to_covar_preci
    return mod


def cli(binary, *args):
    subprocess.run([binary, *args], check=True)


def rel(a, b):
    a = a.double()
    b = b.double()
    scale = max(a.abs().max().item(), b.abs().max().item(), 1e-300)
    return (a - b).abs().max().item() / scale


def report(rows, name, ours, theirs, rtol):
    r = rel(ours, theirs) if ours.numel() else 0.0
    ok = r <= rtol
    rows.append(ok)
    print(f"  {name:<16} {list(ours.shape)!s:<14} max rel diff {r:.2e}  {'ok' if ok else 'FAIL'}")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--repo", required=True, help="a gsplat git checkout (any branch)")
    ap.add_argument("--rev", required=True, help="the revision to read, e.g. v1.5.3 or c3d59bbb")
    ap.add_argument("--version", required=True, choices=["1.5.3", "1.6"])
    ap.add_argument("--bin", default="target/release/liquid-splat")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rtol", type=float, default=1e-10)
    a = ap.parse_args()
    ti = load_torch_impl(a.repo, a.rev)
    torch.set_default_dtype(torch.float64)
    tmp = tempfile.mkdtemp(prefix="gsplat-xcheck-")
    rows = []
    seed = str(a.seed)
    base = ["--dtype", "f64", "--seed", seed, "--gsplat-version", a.version]

    # quat_scale_to_covar_preci (triu=True, covariance and precision).
    print(f"gsplat {a.version} ({a.rev}): quat_scale_to_covar_preci")
    c = os.path.join(tmp, "covar.safetensors")
    o = os.path.join(tmp, "covar.out.safetensors")
    cli(a.bin, "case", "new", "gsplat_quat_scale_to_covar_preci", c, *base)
    cli(a.bin, "case", "run", c, o)
    x, y = load_file(c), load_file(o)
    q = x["quats"].clone().requires_grad_(True)
    s = x["scales"].clone().requires_grad_(True)
    cov, pre = ti._quat_scale_to_covar_preci(q, s, True, True, triu=True)
    ((cov * x["v_covars"]).sum() + (pre * x["v_precis"]).sum()).backward()
    report(rows, "covars", y["covars"], cov.detach(), a.rtol)
    report(rows, "precis", y["precis"], pre.detach(), a.rtol)
    report(rows, "v_quats", y["v_quats"], q.grad, a.rtol)
    report(rows, "v_scales", y["v_scales"], s.grad, a.rtol)

    # spherical_harmonics (degree 3).
    print(f"gsplat {a.version}: spherical_harmonics")
    c = os.path.join(tmp, "sh.safetensors")
    o = os.path.join(tmp, "sh.out.safetensors")
    cli(a.bin, "case", "new", "gsplat_spherical_harmonics", c, *base)
    cli(a.bin, "case", "run", c, o)
    x, y = load_file(c), load_file(o)
    d = x["dirs"].clone().requires_grad_(True)
    k = x["coeffs"].clone().requires_grad_(True)
    col = ti._spherical_harmonics(3, d, k)
    (col * x["v_colors"]).sum().backward()
    report(rows, "colors", y["colors"], col.detach(), a.rtol)
    report(rows, "v_dirs", y["v_dirs"], d.grad, a.rtol)
    report(rows, "v_coeffs", y["v_coeffs"], k.grad, a.rtol)

    # fully_fused_projection, dense, with compensations, without opacities.
    print(f"gsplat {a.version}: fully_fused_projection (dense, compensations, no opacities)")
    c = os.path.join(tmp, "proj.safetensors")
    o = os.path.join(tmp, "proj.out.safetensors")
    cli(a.bin, "case", "new", "gsplat_fully_fused_projection", c, *base, "--dense", "--antialiased")
    x = load_file(c)
    from safetensors import safe_open

    with safe_open(c, "pt") as f:
        meta = f.metadata()
    del x["opacities"]
    save_file(x, c, metadata=meta)
    cli(a.bin, "case", "run", c, o)
    y = load_file(o)
    W, H = int(meta["width"]), int(meta["height"])
    means = x["means"].clone().requires_grad_(True)
    q = x["quats"].clone().requires_grad_(True)
    s = x["scales"].clone().requires_grad_(True)
    covars, _ = ti._quat_scale_to_covar_preci(q, s, True, False, triu=False)
    radii, m2, dep, con, comp = ti._fully_fused_projection(
        means, covars, x["viewmats"], x["Ks"], W, H, calc_compensations=True
    )
    vis = (radii > 0).all(-1)
    loss = (
        (m2 * x["v_means2d"])[vis].sum()
        + (dep * x["v_depths"])[vis].sum()
        + (con * x["v_conics"])[vis].sum()
        + (comp * x["v_compensations"])[vis].sum()
    )
    loss.backward()
    report(rows, "radii", y["radii"].double(), radii.double(), 0.0)
    for name, t in [("means2d", m2), ("depths", dep), ("conics", con), ("compensations", comp)]:
        report(rows, name, y[name][vis], t.detach()[vis], a.rtol)
    report(rows, "v_means", y["v_means"], means.grad, a.rtol)
    report(rows, "v_quats", y["v_quats"], q.grad, a.rtol)
    report(rows, "v_scales", y["v_scales"], s.grad, a.rtol)

    # isect_tiles + isect_offset_encode (radius box), dense rows of the projection above.
    print(f"gsplat {a.version}: isect_tiles + isect_offset_encode (radius box)")
    C, N = y["radii"].shape[:2]
    ts = 16
    tw, th = -(-W // ts), -(-H // ts)
    ic = {
        "means2d": y["means2d"].reshape(C * N, 2).contiguous(),
        "radii": y["radii"].reshape(C * N, 2).contiguous(),
        "depths": y["depths"].reshape(C * N).contiguous(),
    }
    c = os.path.join(tmp, "isect.safetensors")
    o = os.path.join(tmp, "isect.out.safetensors")
    save_file(
        ic,
        c,
        metadata={
            "stage": "gsplat_isect_tiles",
            "version": a.version,
            "tile_size": str(ts),
            "tile_width": str(tw),
            "tile_height": str(th),
            "n_images": str(C),
        },
    )
    cli(a.bin, "case", "run", c, o)
    z = load_file(o)
    tpg, ids, flat = ti._isect_tiles(y["means2d"], y["radii"], y["depths"], ts, tw, th)
    off = ti._isect_offset_encode(ids, C, tw, th)
    ours_ids = (z["isect_ids"][:, 0].long() << 32) | (z["isect_ids"][:, 1].long() & 0xFFFFFFFF)
    report(rows, "tiles_per_gauss", z["tiles_per_gauss"].double(), tpg.reshape(-1).double(), 0.0)
    report(rows, "isect_ids", ours_ids.double(), ids.double(), 0.0)
    same = bool((ours_ids == ids).all())
    rows.append(same)
    print(f"  isect_ids bit-equal: {same}")
    report(rows, "flatten_ids", z["flatten_ids"].double(), flat.double(), 0.0)
    report(rows, "isect_offsets", z["isect_offsets"].double(), off.double(), 0.0)

    print("rasterize_to_pixels: not compared (gsplat's torch reference calls a CUDA kernel)")
    ok = all(rows)
    print("PASS" if ok else "FAIL")
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
