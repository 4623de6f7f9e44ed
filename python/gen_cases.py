#!/usr/bin/env python3
"""Write random, well-formed, seeded case files for every stage.

Usage:
    python gen_cases.py OUT_DIR [--seed 0] [--dtype f32|f64|both] [--size 32] [--n 40]

Writes OUT_DIR/<name>_<dtype>.safetensors for the names in CASES. The same seed gives the
same files (torch CPU generator, no other randomness).

Rasterize cases: a look-at camera at distance 4 from the origin, Gaussians scattered in
front of it (a few placed partly off-screen, one behind the near plane, some with
opacity > 0.99 so the alpha clamp is exercised), SH degree 3 (or precomputed colours and
covariances), random cotangents for color and depth; each in the `exact` and the `inria`
gradient mode.

Step cases: raw Gaussian parameters in front of the same kind of camera, a small field with
PyTorch-initialised weights (the D-3DGS MLP, 6-DoF or not, or the CfC field; synthetic or
real variant), a random ground truth, and either a fresh optimizer (no Adam state, no
statistics) or a warm one (moments of gradient size after 7 steps, non-zero statistics).
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
    """getProjectionMatrix (docs/UPSTREAM.md §2.2), f64."""
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


def look_at_camera(fovx, H, W, dtype):
    """The cases' camera: at (0.3, -0.4, -4) looking at the origin. Returns W2C (f64),
    tan(fov/2) in x and y, and the camera tensors."""
    tanfovx = math.tan(fovx / 2)
    tanfovy = tanfovx * H / W
    w2c = look_at_w2c([0.3, -0.4, -4.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0])
    return w2c, tanfovx, tanfovy, camera_tensors(w2c, tanfovx, tanfovy, dtype)


def camera_to_world(w2c, x, y, z):
    """Camera-space points [N] x, y, z (f64) in world space [N,3]."""
    cam = torch.stack([x, y, z, torch.ones_like(x)], dim=1)
    return (cam @ torch.linalg.inv(w2c).T)[:, :3]


def raster_case(seed, dtype, n=40, H=32, W=32, sh_degree=3, precomp=False):
    g = torch.Generator().manual_seed(seed)
    U = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)
    Nrm = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)
    w2c, tanfovx, tanfovy, t = look_at_camera(0.9, H, W, dtype)
    # Means in camera space, mapped back to world.
    z = 2.5 + 3.0 * U(n)
    x = (U(n) * 2.0 - 1.0) * tanfovx * z * 1.1
    y = (U(n) * 2.0 - 1.0) * tanfovy * z * 1.1
    x[0] = tanfovx * z[0] * 1.6  # beyond the 1.3 tan(fov) clamp
    z[1] = 0.1  # behind the near plane: culled
    t["means3D"] = camera_to_world(w2c, x, y, z).to(dtype)
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


def step_case(seed, dtype, field, variant, is_6dof=False, warm=True, field_on=True, n=24, H=24,
              W=24):
    """One training iteration's inputs (stage `step`)."""
    import reference_deform
    g = torch.Generator().manual_seed(seed)
    U = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)
    Nrm = lambda *s: torch.randn(*s, generator=g, dtype=torch.float64)
    w2c, tanfovx, tanfovy, t = look_at_camera(0.9, H, W, dtype)
    z = 3.0 + 2.0 * U(n)
    x = (U(n) * 2.0 - 1.0) * tanfovx * z * 0.8
    y = (U(n) * 2.0 - 1.0) * tanfovy * z * 0.8
    t["xyz"] = camera_to_world(w2c, x, y, z).to(dtype)
    sh = Nrm(n, 16, 3) * 0.25
    sh[:, 0] += 0.8
    t["sh"] = sh.to(dtype)
    t["scaling"] = (math.log(0.12) + 0.4 * Nrm(n, 3)).to(dtype)
    t["rotation"] = Nrm(n, 4).to(dtype)
    o = 0.3 + 0.65 * U(n, 1)
    t["opacity"] = torch.log(o / (1.0 - o)).to(dtype)
    t["bg"] = torch.tensor([0.1, 0.2, 0.3], dtype=dtype)
    t["gt"] = U(3, H, W).to(dtype)
    fmeta = {"stage": "step", "field": field, "variant": variant,
             "depth": 4 if field == "mlp" else 2, "width": 32 if field == "mlp" else 16}
    if field == "mlp":
        fmeta["is_6dof"] = "true" if is_6dof else "false"
    else:
        fmeta.update(activation="gelu", backbone_units=16, backbone_layers=2)
    fmeta = {k: str(v) for k, v in fmeta.items()}
    torch.manual_seed(seed)
    net = reference_deform.build(fmeta).to(dtype)
    weights = {k: v.detach().clone() for k, v in net.state_dict().items()}
    t.update(weights)
    time = float(torch.tensor(float(U(1)[0]), dtype=dtype))
    meta = dict(fmeta, image_height=H, image_width=W, tanfovx=repr(tanfovx),
                tanfovy=repr(tanfovy), active_sh_degree=2, field_on=str(field_on).lower(),
                time=repr(time), lambda_dssim="0.2", seed=seed)
    if warm:
        P = sum(v.numel() for v in weights.values())
        for group, shape in [("xyz", (n, 3)), ("sh", (n, 16, 3)), ("opacity", (n, 1)),
                             ("scaling", (n, 3)), ("rotation", (n, 4)), ("field", (P,))]:
            m = 1e-3 * Nrm(*shape)
            t[f"adam.{group}.m"] = m.to(dtype)
            t[f"adam.{group}.v"] = (m * m + 1e-6 * U(*shape)).to(dtype)
            meta[f"adam.{group}.step"] = 7
        denom = (U(n) * 6).to(torch.int32)
        t["stats.denom"] = denom
        t["stats.accum"] = (denom.to(torch.float64) * 2e-3 * U(n)).to(dtype)
        t["stats.max_radii"] = torch.where(denom > 0, 1 + (U(n) * 8).to(torch.int32), 0
                                           ).to(torch.int32)
    return t, {k: str(v) for k, v in meta.items()}


# Step cases: (name, field, variant, is_6dof, warm, field_on).
STEP_CASES = [
    ("step_6dof_synthetic_warm", "mlp", "synthetic", True, True, True),
    ("step_6dof_synthetic_fresh", "mlp", "synthetic", True, False, True),
    ("step_6dof_real_warm", "mlp", "real", True, True, True),
    ("step_6dof_real_fresh", "mlp", "real", True, False, True),
    ("step_6dof_real_warmup", "mlp", "real", True, True, False),
    ("step_mlp_synthetic_warm", "mlp", "synthetic", False, True, True),
    ("step_cfc_real_fresh", "cfc", "real", False, False, True),
    ("step_cfc_synthetic_warm", "cfc", "synthetic", False, True, True),
]


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
        save_case(p("rasterize_sh_inria"), t, dict(m, gradient="inria"))
        t, m = raster_case(args.seed + 1, dt, n=args.n, H=args.size, W=args.size + 8, precomp=True)
        save_case(p("rasterize_precomp"), t, m)
        save_case(p("rasterize_precomp_inria"), t, dict(m, gradient="inria"))
        t, m = reference_deform.new_case("mlp", "synthetic", dt, args.seed, depth=8, width=64, n=16)
        save_case(p("deform_mlp"), t, m)
        t, m = reference_deform.new_case("mlp", "real", dt, args.seed, depth=4, width=32,
                                         is_6dof=True, n=16)
        save_case(p("deform_mlp_6dof_real"), t, m)
        t, m = reference_deform.new_case("cfc", "synthetic", dt, args.seed, depth=4, width=32, n=16)
        save_case(p("deform_cfc"), t, m)
        t, m = reference_deform.new_case("cfc", "real", dt, args.seed, depth=3, width=16,
                                         activation="lecun_tanh", n=16)
        save_case(p("deform_cfc_real"), t, m)
        t, m = loss_case(args.seed, dt)
        save_case(p("loss"), t, m)
        for k, (name, field, variant, six, warm, on) in enumerate(STEP_CASES):
            t, m = step_case(args.seed * 100 + k, dt, field, variant, six, warm, on)
            save_case(p(name), t, m)
    print(f"wrote cases to {args.out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
