#!/usr/bin/env python3
"""Independent PyTorch reference of the deformation fields: the D-3DGS MLP and the CfC field.

Written from the project's notes (docs/UPSTREAM.md §6.1–§6.2, docs/DECISIONS.md §2), not from
the Rust code. The CfC cells are the real `ncps.torch.CfCCell` (mode 'default').

Usage:
    python reference_deform.py CASE.safetensors OUT.safetensors
    python reference_deform.py --new CASE.safetensors --field cfc [--variant synthetic]
        [--depth 6] [--width 128] [--activation gelu] [--dtype f32] [--n 16] [--seed 0]

Case (stage `deform`): metadata field=mlp|cfc, variant=synthetic|real, depth, width,
activation (cfc), backbone_units, backbone_layers (cfc), is_6dof (mlp); tensors: the
weights under their PyTorch state_dict names, xyz [N,3], t [N,1], grad_d_xyz [N,3],
grad_d_rotation [N,4], grad_d_scaling [N,3].

Output: d_xyz, d_rotation, d_scaling, grad_t [N,1] and grad.<name> for every weight, the
gradients of sum(d_xyz*grad_d_xyz) + sum(d_rotation*grad_d_rotation) +
sum(d_scaling*grad_d_scaling) by autograd. xyz is detached (stop-gradient), as upstream.

Conventions written down here (upstream leaves them open; docs/DECISIONS.md §2):
- gamma_L(p) = [p, sin(2^0 p), cos(2^0 p), ..., sin(2^(L-1) p), cos(2^(L-1) p)], no pi.
- The timenet (synthetic variant) is Linear(13, 256) -> ReLU -> Linear(256, 30) whatever the
  field width W: its 11,294 parameters are in every published count.
- CfC: u = [gamma_10(x); timenet(gamma_6(t))] (synthetic) or [gamma_10(x); gamma_10(t)]
  (real); h0 = 0; before cell D//2 runs, h += skip(u); ts = t per row, shape (N,1);
  head Linear(W, 10) -> d_xyz (3), d_rotation (4), d_scaling (3).
- MLP with is_6dof: upstream returns the per-Gaussian [N,4,4] SE(3) transform exp_se3 and
  moves the mean to R x + p. Outputs, as the Rust oracle: d_xyz = (R x + p) - x [N,3] (the
  offset the caller adds), d_xyz_se3 = the [N,4,4] transform, and grad_xyz [N,3], the
  gradient of the canonical xyz through R x (the network itself sees xyz.detach()).
"""

import argparse
import sys

import torch
import torch.nn as nn
import torch.nn.functional as F

from common import case_dtype, load_case, require, save_case


def embed(p, L):
    """gamma_L(p): raw input first, then sin/cos of 2^k p for k = 0..L-1 (no pi)."""
    freqs = 2.0 ** torch.linspace(0.0, L - 1, L, dtype=p.dtype)
    out = [p]
    for f in freqs:
        out.append(torch.sin(p * f))
        out.append(torch.cos(p * f))
    return torch.cat(out, dim=-1)


def make_timenet():
    return nn.Sequential(nn.Linear(13, 256), nn.ReLU(), nn.Linear(256, 30))


class DeformNetwork(nn.Module):
    """The D-3DGS MLP (docs/UPSTREAM.md §6.2); parameter names equal upstream deform.pth keys."""

    def __init__(self, D=8, W=256, variant="synthetic", is_6dof=False):
        super().__init__()
        self.D, self.W = D, W
        self.synthetic = variant == "synthetic"
        self.is_6dof = is_6dof
        self.t_L = 6 if self.synthetic else 10
        self.skips = [D // 2]
        xyz_ch = 3 + 3 * 2 * 10
        if self.synthetic:
            self.timenet = make_timenet()
            t_ch = 30
        else:
            t_ch = 1 + 2 * 10
        in_ch = xyz_ch + t_ch
        layers = [nn.Linear(in_ch, W)]
        for i in range(D - 1):
            layers.append(nn.Linear(W + in_ch, W) if i in self.skips else nn.Linear(W, W))
        self.linear = nn.ModuleList(layers)
        if is_6dof:
            self.branch_w = nn.Linear(W, 3)
            self.branch_v = nn.Linear(W, 3)
        else:
            self.gaussian_warp = nn.Linear(W, 3)
        self.gaussian_rotation = nn.Linear(W, 4)
        self.gaussian_scaling = nn.Linear(W, 3)

    def forward(self, x, t):
        t_emb = embed(t, self.t_L)
        if self.synthetic:
            t_emb = self.timenet(t_emb)
        x_emb = embed(x, 10)
        h = torch.cat([x_emb, t_emb], dim=-1)
        for i, layer in enumerate(self.linear):
            h = F.relu(layer(h))
            if i in self.skips:
                h = torch.cat([x_emb, t_emb, h], dim=-1)
        if self.is_6dof:
            w = self.branch_w(h)
            v = self.branch_v(h)
            theta = torch.norm(w, dim=-1, keepdim=True)
            w = w / theta + 1e-5
            v = v / theta + 1e-5
            d_xyz = exp_se3(w, v, theta)
        else:
            d_xyz = self.gaussian_warp(h)
        return d_xyz, self.gaussian_rotation(h), self.gaussian_scaling(h)


def skew(w):
    z = torch.zeros_like(w[:, 0])
    return torch.stack([
        torch.stack([z, -w[:, 2], w[:, 1]], -1),
        torch.stack([w[:, 2], z, -w[:, 0]], -1),
        torch.stack([-w[:, 1], w[:, 0], z], -1)], 1)


def exp_se3(w, v, theta):
    """Per-row 4x4 [[R, p], [0, 1]] with R = I + sin(th) W + (1 - cos(th)) W^2 and
    p = (th I + (1 - cos(th)) W + (th - sin(th)) W^2) v."""
    Wm = skew(w)
    W2 = Wm @ Wm
    th = theta[:, :, None]
    I = torch.eye(3, dtype=w.dtype).expand_as(Wm)
    R = I + torch.sin(th) * Wm + (1.0 - torch.cos(th)) * W2
    p = ((th * I + (1.0 - torch.cos(th)) * Wm + (th - torch.sin(th)) * W2) @ v[:, :, None])
    top = torch.cat([R, p], dim=2)
    bottom = torch.zeros(w.shape[0], 1, 4, dtype=w.dtype)
    bottom[:, 0, 3] = 1.0
    return torch.cat([top, bottom], dim=1)


class CfCField(nn.Module):
    """The liquid field (docs/DECISIONS.md §2): D stacked ncps CfC cells in depth."""

    def __init__(self, D=6, W=128, variant="synthetic", activation="gelu",
                 backbone_units=64, backbone_layers=2):
        super().__init__()
        from ncps.torch import CfCCell
        self.D, self.W = D, W
        self.synthetic = variant == "synthetic"
        if self.synthetic:
            self.timenet = make_timenet()
            u_dim = 63 + 30
        else:
            u_dim = 63 + 21
        self.cells = nn.ModuleList([
            CfCCell(input_size=u_dim, hidden_size=W, mode="default",
                    backbone_activation=activation, backbone_units=backbone_units,
                    backbone_layers=backbone_layers)
            for _ in range(D)])
        self.skip = nn.Linear(u_dim, W)
        self.head = nn.Linear(W, 10)

    def forward(self, x, t):
        t_emb = self.timenet(embed(t, 6)) if self.synthetic else embed(t, 10)
        u = torch.cat([embed(x, 10), t_emb], dim=-1)
        h = torch.zeros(x.shape[0], self.W, dtype=x.dtype)
        for l, cell in enumerate(self.cells):
            if l == self.D // 2:
                h = h + self.skip(u)
            h, _ = cell(u, h, t)  # ts has shape (N, 1): broadcasts over the W columns
        out = self.head(h)
        return out[:, 0:3], out[:, 3:7], out[:, 7:10]


def build(meta):
    field = require(meta, "field")
    variant = meta.get("variant", "synthetic")
    if variant not in ("synthetic", "real"):
        raise SystemExit(f"variant {variant!r}: expected synthetic or real")
    depth = int(meta.get("depth", "8" if field == "mlp" else "6"))
    width = int(meta.get("width", "256" if field == "mlp" else "128"))
    if field == "mlp":
        return DeformNetwork(depth, width, variant, meta.get("is_6dof", "false").lower() == "true")
    if field == "cfc":
        return CfCField(depth, width, variant, meta.get("activation", "gelu"),
                        int(meta.get("backbone_units", "64")),
                        int(meta.get("backbone_layers", "2")))
    raise SystemExit(f"field {field!r}: expected mlp or cfc")


def param_count(module):
    return sum(p.numel() for p in module.parameters())


def new_case(field, variant, dtype, seed, depth=None, width=None, activation="gelu",
             is_6dof=False, n=16):
    """A deform case with PyTorch-initialised weights (torch.manual_seed(seed))."""
    meta = {"stage": "deform", "field": field, "variant": variant,
            "depth": depth if depth is not None else (8 if field == "mlp" else 6),
            "width": width if width is not None else (256 if field == "mlp" else 128),
            "seed": seed}
    if field == "cfc":
        meta.update(activation=activation, backbone_units=64, backbone_layers=2)
    else:
        meta["is_6dof"] = "true" if is_6dof else "false"
    meta = {k: str(v) for k, v in meta.items()}
    torch.manual_seed(seed)
    net = build(meta).to(dtype)
    g = torch.Generator().manual_seed(seed + 1)
    t = {k: v.detach().clone() for k, v in net.state_dict().items()}
    t["xyz"] = ((torch.rand(n, 3, generator=g, dtype=torch.float64) * 2 - 1) * 1.3).to(dtype)
    t["t"] = torch.rand(n, 1, generator=g, dtype=torch.float64).to(dtype)
    t["grad_d_xyz"] = torch.randn(n, 3, generator=g, dtype=torch.float64).to(dtype)
    t["grad_d_rotation"] = torch.randn(n, 4, generator=g, dtype=torch.float64).to(dtype)
    t["grad_d_scaling"] = torch.randn(n, 3, generator=g, dtype=torch.float64).to(dtype)
    return t, meta


def run(meta, t):
    dtype = case_dtype(t, "xyz")
    net = build(meta).to(dtype)
    names = set(net.state_dict().keys())
    inputs = {"xyz", "t", "grad_d_xyz", "grad_d_rotation", "grad_d_scaling"}
    missing = sorted(names - set(t))
    unknown = sorted(set(t) - names - inputs)
    if missing or unknown:
        raise SystemExit(f"weights do not match the field: missing {missing}, unexpected {unknown}")
    net.load_state_dict({k: t[k].to(dtype) for k in names}, strict=True)
    xyz_live = t["xyz"].to(dtype).clone().requires_grad_(True)
    xyz = xyz_live.detach()  # stop-gradient into the network, as upstream
    time = t["t"].to(dtype).clone().requires_grad_(True)
    d_xyz, d_rot, d_scale = net(xyz, time)
    loss = ((d_rot * t["grad_d_rotation"].to(dtype)).sum()
            + (d_scale * t["grad_d_scaling"].to(dtype)).sum())
    se3 = None
    if d_xyz.dim() == 2:
        loss = loss + (d_xyz * t["grad_d_xyz"].to(dtype)).sum()
    else:
        # 6-DoF: the mean moves to R x + p, with x not detached (upstream's bmm);
        # the offset is (R x + p) - x.
        se3 = d_xyz
        moved = (se3[:, :3, :3] @ xyz_live[:, :, None])[:, :, 0] + se3[:, :3, 3]
        d_xyz = moved - xyz_live
        loss = loss + (d_xyz * t["grad_d_xyz"].to(dtype)).sum()
    loss.backward()
    out = {"d_xyz": d_xyz.detach(), "d_rotation": d_rot.detach(), "d_scaling": d_scale.detach(),
           "grad_t": time.grad}
    if se3 is not None:
        out["d_xyz_se3"] = se3.detach()
        out["grad_xyz"] = xyz_live.grad
    for name, p in net.named_parameters():
        out["grad." + name] = p.grad if p.grad is not None else torch.zeros_like(p)
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case")
    ap.add_argument("out", nargs="?")
    ap.add_argument("--new", action="store_true", help="write a random case to CASE instead")
    ap.add_argument("--field", choices=["mlp", "cfc"], default="cfc")
    ap.add_argument("--variant", choices=["synthetic", "real"], default="synthetic")
    ap.add_argument("--depth", type=int)
    ap.add_argument("--width", type=int)
    ap.add_argument("--activation", default="gelu",
                    choices=["gelu", "relu", "silu", "tanh", "lecun_tanh"])
    ap.add_argument("--is-6dof", action="store_true")
    ap.add_argument("--dtype", choices=["f32", "f64"], default="f32")
    ap.add_argument("--n", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.new:
        dtype = torch.float32 if args.dtype == "f32" else torch.float64
        t, meta = new_case(args.field, args.variant, dtype, args.seed, args.depth, args.width,
                           args.activation, args.is_6dof, args.n)
        save_case(args.case, t, meta)
        return 0
    if args.out is None:
        ap.error("OUT is required unless --new is given")
    meta, t = load_case(args.case)
    if meta.get("stage") != "deform":
        raise SystemExit(f"{args.case}: stage is {meta.get('stage')!r}, expected 'deform'")
    out = run(meta, t)
    save_case(args.out, out, {"stage": "deform", "producer": "python/reference_deform.py",
                              "torch": torch.__version__})
    return 0


if __name__ == "__main__":
    sys.exit(main())
