#!/usr/bin/env python3
"""Write random, well-formed, seeded case files for the rasterize, deform and loss stages.

Usage:
    python gen_cases.py OUT_DIR [--seed 0] [--dtype f32|f64|both] [--size 32] [--n 40]

Writes OUT_DIR/{rasterize_sh,rasterize_precomp,deform_mlp,deform_cfc,loss}_<dtype>.safetensors.
The same seed gives the same files (torch CPU generator, no other randomness).

Rasterize cases: a look-at camera at distance 4 from the origin, Gaussians scattered in
front of it (a few placed partly off-screen, one behind the near plane, some with
opacity > 0.99 so the alpha clamp is exercised), SH degree 3 (or precomputed colours and
covariances), random cotangents for color and depth.
"""

import argparse
import math
import os
import sys

import torch

from common import save_case

ZNEAR, ZFAR = 0.01, 100.0


def look_at_w2c(eye, target, up):
    """World-to-camera 4x4 (f64), OpenCV axes: x right, y down, z forward."""
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    f = target - eye
    f = f / f.norm()
    r = torch.linalg.cross(f, up)
    r = r / r.norm()
    d = torch.linalg.cross(f, r)  # down
    R = torch.stack([r, d, f])  # rows: camera axes in world coordinates
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ eye
    return w2c


def projection(tanfovx, tanfovy):
    """getProjectionMatrix (UPSTREAM 2.2), f64."""
    top = tanfovy * ZNEAR
    right = tanfovx * ZNEAR
    P = torch.zeros(4, 4, dtype=torch.float64)
    P[0, 0] = 2.0 * ZNEAR / (2 * right)
    P[1, 1] = 2.0 * ZNEAR / (2 * top)
    P[3, 2] = 1.0
    P[2, 2] = ZFAR / (ZFAR - ZNEAR)
    P[2, 3] = -(ZFAR * ZNEAR) / (ZFAR - ZNEAR)
    return P


def camera_tensors(w2c, tanfovx, tanfovy, dtype):
    """viewmatrix = W2C^T, projmatrix = (P W2C)^T, campos = camera centre."""
    P = projection(tanfovx, tanfovy)
    c2w = torch.linalg.inv(w2c)
    return {
        "viewmatrix": w2c.T.contiguous().to(dtype),
        "projmatrix": (P @ w2c).T.contiguous().to(dtype),
        "campos": c2w[:3, 3].contiguous().to(dtype),
    }


def raster_case(seed, dtype, n=40, H=32, W=32, sh_degree=3, precomp=False):
    g = torch.Generator().manual_seed(seed)
    U = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)
    Nrm = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)
    fovx = 0.9
    tanfovx = math.tan(fovx / 2)
    tanfovy = tanfovx * H / W
    w2c = look_at_w2c([0.3, -0.4, -4.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0])
    t = camera_tensors(w2c, tanfovx, tanfovy, dtype)
    # Means in camera space, mapped back to world.
    z = 2.5 + 3.0 * U(n)
    x = (U(n) * 2.0 - 1.0) * tanfovx * z * 1.1
    y = (U(n) * 2.0 - 1.0) * tanfovy * z * 1.1
    x[0] = tanfovx * z[0] * 1.6  # beyond the 1.3 tan(fov) clamp
    z[1] = 0.1  # behind the near plane: culled
    cam = torch.stack([x, y, z, torch.ones(n, dtype=torch.float64)], dim=1)
    world = (cam @ torch.linalg.inv(w2c).T)[:, :3]
    t["means3D"] = world.to(dtype)
    t["opacities"] = (0.05 + 0.9 * U(n, 1)).to(dtype)
    t["opacities"][2:5] = 0.999  # exercise the 0.99 clamp
    if precomp:
        t["colors_precomp"] = U(n, 3).to(dtype)
        A = Nrm(n, 3, 3) * 0.15
        cov = A @ A.transpose(1, 2) + 0.002 * torch.eye(3, dtype=torch.float64)
        iu = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
        t["cov3D_precomp"] = torch.stack([cov[:, i, j] for i, j in iu], dim=1).to(dtype)
    else:
        M = (sh_degree + 1) ** 2
        sh = Nrm(n, 16, 3) * 0.3
        sh[:, 0] += 0.8
        t["shs"] = sh.to(dtype)
        t["scales"] = torch.exp(math.log(0.05) + 1.2 * Nrm(n, 3)).to(dtype)
        q = Nrm(n, 4)
        q = q / q.norm(dim=1, keepdim=True) * (0.8 + 0.4 * U(n, 1))  # not unit: used as given
        t["rotations"] = q.to(dtype)
    t["bg"] = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    t["grad_out_color"] = Nrm(3, H, W).to(dtype)
    t["grad_out_depth"] = (0.1 * Nrm(1, H, W)).to(dtype)
    meta = {"stage": "rasterize", "image_height": H, "image_width": W,
            "tanfovx": repr(tanfovx), "tanfovy": repr(tanfovy), "scale_modifier": "1.0",
            "sh_degree": sh_degree, "seed": seed}
    return t, meta


def loss_case(seed, dtype, H=24, W=20):
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(3, H, W, generator=g, dtype=torch.float64) * 1.1  # may exceed 1: not clamped
    gt = torch.clamp(img + 0.2 * torch.randn(3, H, W, generator=g, dtype=torch.float64), 0, 1)
    return ({"image": img.to(dtype), "gt": gt.to(dtype)},
            {"stage": "loss", "lambda_dssim": "0.2", "seed": seed})


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out_dir")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--dtype", choices=["f32", "f64", "both"], default="both")
    ap.add_argument("--size", type=int, default=32)
    ap.add_argument("--n", type=int, default=40)
    args = ap.parse_args(argv)
    os.makedirs(args.out_dir, exist_ok=True)
    import reference_deform
    dtypes = {"f32": [torch.float32], "f64": [torch.float64],
              "both": [torch.float32, torch.float64]}[args.dtype]
    for dt in dtypes:
        tag = "f32" if dt == torch.float32 else "f64"
        p = lambda name: os.path.join(args.out_dir, f"{name}_{tag}.safetensors")
        t, m = raster_case(args.seed, dt, n=args.n, H=args.size, W=args.size)
        save_case(p("rasterize_sh"), t, m)
        t, m = raster_case(args.seed + 1, dt, n=args.n, H=args.size, W=args.size + 8, precomp=True)
        save_case(p("rasterize_precomp"), t, m)
        t, m = reference_deform.new_case("mlp", "synthetic", dt, args.seed, depth=8, width=64, n=16)
        save_case(p("deform_mlp"), t, m)
        t, m = reference_deform.new_case("cfc", "synthetic", dt, args.seed, depth=4, width=32, n=16)
        save_case(p("deform_cfc"), t, m)
        t, m = loss_case(args.seed, dt)
        save_case(p("loss"), t, m)
    print(f"wrote cases to {args.out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
