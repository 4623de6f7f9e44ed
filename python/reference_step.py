#!/usr/bin/env python3
"""Independent PyTorch reference of one D-3DGS training iteration: the `step` stage.

Written from the project's notes (docs/UPSTREAM.md §A.2–§A.3, §6.2, §6.4–§6.5;
docs/DECISIONS.md §1–§2b), not from the Rust code, the way upstream's train.py runs an
iteration:

1. the field on the detached canonical means (`deform.step(xyz.detach(), t)`), skipped with
   field_on=false (warm-up): upstream's DeformNetwork (is_6dof included) or the CfC field,
   from reference_deform.py;
2. upstream's renderer: means3D = xyz + d_xyz, or with is_6dof
   from_homogenous(bmm(d_xyz, to_homogenous(xyz))) on the **non-detached** xyz;
   scales = exp(scaling) + d_scaling; rotations = normalize(rotation) + d_rotation;
   opacity = sigmoid(opacity); shs = cat(features_dc, features_rest); the rasterizer
   forward of reference_raster.py with the active SH degree;
3. loss = (1 - l) L1 + l (1 - SSIM) as reference_loss.py;
4. loss.backward() (autograd: the `exact` gradient mode);
5. densification statistics: max_radii2D, xyz_gradient_accum += |grad means2D[:, :2]|,
   denom += 1 for the Gaussians with radii > 0;
6. torch.optim.Adam (eps 1e-15, betas 0.9/0.999) over upstream's parameter groups, xyz,
   f_dc, f_rest, opacity, scaling, rotation (each its own rate), and one Adam over the
   field's parameters (stepped only when the field was used: torch skips a parameter whose
   .grad is None).

Usage:
    python reference_step.py CASE.safetensors OUT.safetensors

Case and output tensors as docs/ORACLE.md, stage `step`. The case's Adam state is loaded
into the optimizers' state (`step`, `exp_avg`, `exp_avg_sq`); `adam.sh.*` [N,K,3] is split
into f_dc [N,1,3] and f_rest [N,K-1,3], `adam.field.*` [P] into the field's parameters in
state_dict order.
"""

import argparse
import sys

import torch
import torch.nn.functional as F

import reference_deform
import reference_loss
import reference_raster
from common import case_dtype, load_case, require, save_case

GAUSSIAN = ["xyz", "sh", "scaling", "rotation", "opacity"]
LR_DEFAULTS = {"xyz": 0.0008, "f_dc": 0.0025, "f_rest": 0.000125, "opacity": 0.05,
               "scaling": 0.005, "rotation": 0.001, "field": 0.0008}


def to_homogenous(x):
    return torch.cat([x, torch.ones_like(x[..., :1])], dim=-1)


def from_homogenous(x):
    return x[..., :3] / x[..., 3:]


def load_adam(opt, param, t, group, meta, part=None):
    """Put the case's Adam state of `group` (sliced by `part`) on `param`; nothing (fresh
    state) if the case has none."""
    step = int(meta.get(f"adam.{group}.step", "0"))
    m, v = t.get(f"adam.{group}.m"), t.get(f"adam.{group}.v")
    if m is None and step == 0:
        return
    if m is None:
        m, v = torch.zeros(param.numel()), torch.zeros(param.numel())
    if part is not None:
        m, v = part(m), part(v)
    opt.state[param] = {
        "step": torch.tensor(float(step)),
        "exp_avg": m.to(param.dtype).reshape(param.shape).clone(),
        "exp_avg_sq": v.to(param.dtype).reshape(param.shape).clone(),
    }


def run(meta, t):
    dtype = case_dtype(t, "xyz")
    if meta.get("stage") != "step":
        raise SystemExit(f"stage is {meta.get('stage')!r}, expected 'step'")
    field_on = meta.get("field_on", "true").lower() == "true"
    time = float(require(meta, "time"))
    lam = float(meta.get("lambda_dssim", "0.2"))
    lr = {k: float(meta.get(f"lr.{k}", v)) for k, v in LR_DEFAULTS.items()}
    is_6dof = meta.get("field") == "mlp" and meta.get("is_6dof", "false").lower() == "true"

    net = reference_deform.build(meta).to(dtype)
    names = list(net.state_dict().keys())
    net.load_state_dict({k: t[k].to(dtype) for k in names}, strict=True)

    p = lambda name: torch.nn.Parameter(t[name].to(dtype).clone())
    xyz, scaling, rotation, opacity = p("xyz"), p("scaling"), p("rotation"), p("opacity")
    sh = t["sh"].to(dtype)
    f_dc = torch.nn.Parameter(sh[:, :1].clone())
    f_rest = torch.nn.Parameter(sh[:, 1:].clone())
    N, K = sh.shape[0], sh.shape[1]

    # 1. The field on the detached means.
    if field_on:
        time_input = torch.full((N, 1), time, dtype=dtype)
        d_xyz, d_rotation, d_scaling = net(xyz.detach(), time_input)
    else:
        d_xyz, d_rotation, d_scaling = 0.0, 0.0, 0.0

    # 2. Upstream's renderer.
    if is_6dof and torch.is_tensor(d_xyz):
        means3D = from_homogenous(torch.bmm(d_xyz, to_homogenous(xyz).unsqueeze(-1)).squeeze(-1))
    else:
        means3D = xyz + d_xyz
    scales = torch.exp(scaling) + d_scaling
    rotations = F.normalize(rotation) + d_rotation
    opac = torch.sigmoid(opacity)
    shs = torch.cat((f_dc, f_rest), dim=1)
    rmeta = {"image_height": require(meta, "image_height"),
             "image_width": require(meta, "image_width"),
             "tanfovx": require(meta, "tanfovx"), "tanfovy": require(meta, "tanfovy"),
             "scale_modifier": "1.0", "sh_degree": require(meta, "active_sh_degree")}
    st = reference_raster.Settings(rmeta, dtype)
    cam = reference_raster.Camera(t, dtype)
    fwd = reference_raster.forward(st, cam, means3D, opac, shs=shs, scales=scales,
                                   rotations=rotations)
    image = fwd["color"]

    # 3. The loss.
    gt = t["gt"].to(dtype)
    l1 = (image - gt).abs().mean()
    ssim = reference_loss.ssim(image, gt)
    loss = (1.0 - lam) * l1 + lam * (1.0 - ssim)

    # 4. Backward.
    loss.backward()
    g2 = reference_raster.grad_means2d(fwd, N, st)
    radii = fwd["radii"]

    # 5. Densification statistics.
    accum = t["stats.accum"].to(dtype).clone() if "stats.accum" in t else torch.zeros(N, dtype=dtype)
    denom = t["stats.denom"].clone() if "stats.denom" in t else torch.zeros(N, dtype=torch.int32)
    max_radii = (t["stats.max_radii"].clone() if "stats.max_radii" in t
                 else torch.zeros(N, dtype=torch.int32))
    vis = radii > 0
    max_radii[vis] = torch.max(max_radii[vis], radii[vis])
    accum[vis] += torch.norm(g2[vis, :2], dim=-1)
    denom[vis] += 1

    # Gradients, before Adam changes anything.
    out = {"loss": loss.detach().reshape(()), "l1": l1.detach().reshape(()),
           "ssim": ssim.detach().reshape(()), "image": image.detach(),
           "radii": radii, "grad_means2d": g2}
    out["grad.xyz"] = xyz.grad.clone()
    out["grad.sh"] = torch.cat((f_dc.grad, f_rest.grad), dim=1)
    out["grad.scaling"] = scaling.grad.clone()
    out["grad.rotation"] = rotation.grad.clone()
    out["grad.opacity"] = opacity.grad.clone()
    if field_on:
        for name, q in net.named_parameters():
            out["grad." + name] = q.grad.clone()

    # 6. Adam: upstream's groups for the Gaussians, one for the field.
    gauss = torch.optim.Adam([
        {"params": [xyz], "lr": lr["xyz"], "name": "xyz"},
        {"params": [f_dc], "lr": lr["f_dc"], "name": "f_dc"},
        {"params": [f_rest], "lr": lr["f_rest"], "name": "f_rest"},
        {"params": [opacity], "lr": lr["opacity"], "name": "opacity"},
        {"params": [scaling], "lr": lr["scaling"], "name": "scaling"},
        {"params": [rotation], "lr": lr["rotation"], "name": "rotation"},
    ], lr=0.0, eps=1e-15)
    load_adam(gauss, xyz, t, "xyz", meta)
    load_adam(gauss, f_dc, t, "sh", meta, part=lambda s: s.reshape(N, K, 3)[:, :1])
    load_adam(gauss, f_rest, t, "sh", meta, part=lambda s: s.reshape(N, K, 3)[:, 1:])
    load_adam(gauss, opacity, t, "opacity", meta)
    load_adam(gauss, scaling, t, "scaling", meta)
    load_adam(gauss, rotation, t, "rotation", meta)
    field_params = list(net.parameters())
    deform = torch.optim.Adam(field_params, lr=lr["field"], eps=1e-15)
    offset = 0
    for q in field_params:
        n = q.numel()
        load_adam(deform, q, t, "field", meta, part=lambda s, o=offset, n=n: s[o:o + n])
        offset += n
    gauss.step()
    deform.step()

    def state(opt, q, key):
        s = opt.state.get(q)
        return s[key] if s else torch.zeros_like(q)

    def step_of(opt, q):
        s = opt.state.get(q)
        return int(s["step"]) if s else 0

    out["new.xyz"] = xyz.detach()
    out["new.sh"] = torch.cat((f_dc.detach(), f_rest.detach()), dim=1)
    out["new.scaling"] = scaling.detach()
    out["new.rotation"] = rotation.detach()
    out["new.opacity"] = opacity.detach()
    for name, q in net.named_parameters():
        out["new." + name] = q.detach()
    out["stats.accum"] = accum
    out["stats.denom"] = denom
    out["stats.max_radii"] = max_radii
    out_meta = {"stage": "step", "producer": "python/reference_step.py",
                "torch": torch.__version__}
    for group, params in [("xyz", [xyz]), ("opacity", [opacity]), ("scaling", [scaling]),
                          ("rotation", [rotation])]:
        out[f"new.adam.{group}.m"] = state(gauss, params[0], "exp_avg")
        out[f"new.adam.{group}.v"] = state(gauss, params[0], "exp_avg_sq")
        out_meta[f"new.adam.{group}.step"] = step_of(gauss, params[0])
    for key, name in [("exp_avg", "m"), ("exp_avg_sq", "v")]:
        out[f"new.adam.sh.{name}"] = torch.cat((state(gauss, f_dc, key),
                                                state(gauss, f_rest, key)), dim=1)
        out[f"new.adam.field.{name}"] = torch.cat(
            [state(deform, q, key).flatten() for q in field_params])
    out_meta["new.adam.sh.step"] = step_of(gauss, f_dc)
    out_meta["new.adam.field.step"] = step_of(deform, field_params[0])
    return out, out_meta


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case")
    ap.add_argument("out")
    args = ap.parse_args(argv)
    meta, t = load_case(args.case)
    out, out_meta = run(meta, t)
    save_case(args.out, out, out_meta)
    return 0


if __name__ == "__main__":
    sys.exit(main())
