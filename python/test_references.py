#!/usr/bin/env python3
"""Self-tests of the PyTorch references, each against an independent computation.

Run:  python test_references.py      (or: python -m pytest test_references.py)

- rasterizer: one Gaussian against a closed-form hand calculation (pixels, depth, final_T,
  n_contrib, radius, mean, and the opacity/colour gradients, with and without the 0.99
  clamp); autograd gradients against f64 central differences on a random case.
- deform: parameter counts 522,280 / 782,888 / 334,504 (and the other published counts),
  state_dict names, autograd against central differences.
- loss: the upstream f32 window bits, SSIM against a plain-loop implementation, gradient
  against central differences.
- inria mode: the port of the Inria backward equals autograd where its formulas are the exact
  derivative (no alpha clamp, no tangent clamp, no depth cotangent, large footprints), and
  ignores the depth cotangent.
- step: the Adam update of every group (f_dc and f_rest with their own rates, the field's
  flat state split in state_dict order) against the written-out torch 1.13 formula; a step
  with the field off leaves the field and its state alone.
"""

import math
import random
import sys

import torch

import gen_cases
import reference_deform as rd
import reference_loss as rl
import reference_raster as rr
import reference_step as rs

F64 = torch.float64


# ---------------------------------------------------------------- rasterizer

def single_gaussian_case(opacity):
    H = W = 32
    tanfov = 0.5
    w2c = torch.eye(4, dtype=F64)
    t = gen_cases.camera_tensors(w2c, tanfov, tanfov, F64)
    t["means3D"] = torch.tensor([[0.3, -0.2, 5.0]], dtype=F64)
    t["colors_precomp"] = torch.tensor([[0.2, 0.5, 0.9]], dtype=F64)
    t["opacities"] = torch.tensor([[opacity]], dtype=F64)
    t["scales"] = torch.tensor([[0.1, 0.1, 0.1]], dtype=F64)
    t["rotations"] = torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64)
    t["bg"] = torch.tensor([0.1, 0.1, 0.1], dtype=F64)
    g = torch.zeros(3, H, W, dtype=F64)
    g[0] = 1.0
    t["grad_out_color"] = g
    meta = {"stage": "rasterize", "image_height": "32", "image_width": "32",
            "tanfovx": "0.5", "tanfovy": "0.5", "scale_modifier": "1.0", "sh_degree": "0"}
    return meta, t


def hand_single_gaussian(opacity):
    """Closed form for one isotropic Gaussian seen by an identity camera (plain Python f64)."""
    W = H = 32
    fx = fy = W / (2 * 0.5)
    x, y, z = 0.3, -0.2, 5.0
    s2 = 0.1 ** 2
    ndc_x, ndc_y = 2.0 * x / (z + 1e-7), 2.0 * y / (z + 1e-7)  # P(0,0) = 1/tanfov = 2
    u = ((ndc_x + 1.0) * W - 1.0) * 0.5
    v = ((ndc_y + 1.0) * H - 1.0) * 0.5
    j02, j12 = -fx * x / z ** 2, -fy * y / z ** 2
    a = s2 * ((fx / z) ** 2 + j02 ** 2) + 0.3
    b = s2 * (j02 * j12)
    c = s2 * ((fy / z) ** 2 + j12 ** 2) + 0.3
    det = a * c - b * b
    A, B, C = c / det, -b / det, a / det
    mid = 0.5 * (a + c)
    lam = mid + math.sqrt(max(0.1, mid * mid - det))
    radius = math.ceil(3 * math.sqrt(lam))
    col, bg = [0.2, 0.5, 0.9], 0.1
    img = [[[bg] * W for _ in range(H)] for _ in range(3)]
    depth = [[0.0] * W for _ in range(H)]
    final_T = [[1.0] * W for _ in range(H)]
    n_contrib = [[0] * W for _ in range(H)]
    g_op = 0.0
    g_col0 = 0.0
    for py in range(H):
        for px in range(W):
            dx, dy = u - px, v - py
            power = -0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy
            if power > 0:
                continue
            G = math.exp(power)
            alpha = min(0.99, opacity * G)
            if alpha < 1 / 255:
                continue
            for ch in range(3):
                img[ch][py][px] = col[ch] * alpha + (1 - alpha) * bg
            depth[py][px] = z * alpha
            final_T[py][px] = 1 - alpha
            n_contrib[py][px] = 1
            # d/d(opacity) of channel 0 (gradient only where the clamp is inactive)
            if opacity * G < 0.99:
                g_op += G * (col[0] - bg)
            g_col0 += alpha
    return dict(u=u, v=v, radius=radius, img=img, depth=depth, final_T=final_T,
                n_contrib=n_contrib, g_op=g_op, g_col0=g_col0)


def test_raster_single_gaussian_matches_hand_calculation():
    for opacity in (0.7, 0.999):
        meta, t = single_gaussian_case(opacity)
        out = rr.render(meta, t)
        h = hand_single_gaussian(opacity)
        assert out["radii"].tolist() == [h["radius"]], (out["radii"], h["radius"])
        assert abs(out["means2D"][0, 0] - h["u"]) < 1e-12
        assert abs(out["means2D"][0, 1] - h["v"]) < 1e-12
        img = torch.tensor(h["img"], dtype=F64)
        assert (out["color"] - img).abs().max() < 1e-12
        assert (out["depth"][0] - torch.tensor(h["depth"], dtype=F64)).abs().max() < 1e-12
        assert (out["final_T"] - torch.tensor(h["final_T"], dtype=F64)).abs().max() < 1e-12
        assert out["n_contrib"].tolist() == h["n_contrib"]
        go = float(out["grad_opacities"][0, 0])
        assert abs(go - h["g_op"]) < 1e-10 * max(1, abs(h["g_op"])), (go, h["g_op"])
        gc = float(out["grad_colors_precomp"][0, 0])
        assert abs(gc - h["g_col0"]) < 1e-10 * h["g_col0"]
        assert out["grad_colors_precomp"][0, 1:].abs().max() == 0
    # The clamp is active at the centre for opacity 0.999: the exact gradient drops those pixels.
    assert hand_single_gaussian(0.999)["g_op"] < hand_single_gaussian(0.7)["g_op"] * 1.5


def raster_loss(meta, t):
    out = rr.render(meta, t)
    loss = (out["color"] * t["grad_out_color"]).sum()
    if "grad_out_depth" in t:
        loss = loss + (out["depth"] * t["grad_out_depth"]).sum()
    return float(loss), out


def check_raster_fd(precomp, seed):
    t, meta = gen_cases.raster_case(seed, F64, n=12, H=32, W=32, precomp=precomp)
    meta = {k: str(v) for k, v in meta.items()}
    _, out = raster_loss(meta, t)
    names = (["means3D", "opacities", "colors_precomp", "cov3D_precomp"] if precomp else
             ["means3D", "opacities", "shs", "scales", "rotations"])
    grad_name = {"means3D": "grad_means3D", "opacities": "grad_opacities",
                 "colors_precomp": "grad_colors_precomp", "cov3D_precomp": "grad_cov3D_precomp",
                 "shs": "grad_shs", "scales": "grad_scales", "rotations": "grad_rotations"}
    rng = random.Random(seed)
    vis = [i for i, r in enumerate(out["radii"].tolist()) if r > 0]
    checked = 0
    h = 1e-6
    for name in names:
        ga = out[grad_name[name]]
        for _ in range(4):
            i = rng.choice(vis)
            flat = t[name][i].flatten()
            k = rng.randrange(flat.numel())
            if name == "shs":
                k = rng.randrange(3 * (int(meta["sh_degree"]) + 1) ** 2)
            base = t[name].clone()
            tp = dict(t); tm = dict(t)
            tp[name] = base.clone(); tp[name][i].view(-1)[k] += h
            tm[name] = base.clone(); tm[name][i].view(-1)[k] -= h
            lp, op = raster_loss(meta, tp)
            lm, om = raster_loss(meta, tm)
            # Only compare where the discrete structure is unchanged (no discontinuity crossed).
            if not (torch.equal(op["n_contrib"], om["n_contrib"])
                    and torch.equal(op["radii"], om["radii"])):
                continue
            num = (lp - lm) / (2 * h)
            ana = float(ga[i].flatten()[k])
            err = abs(num - ana) / max(abs(num), abs(ana), 1e-3)
            assert err < 1e-6, (name, i, k, num, ana, err)
            checked += 1
    assert checked >= 3 * len(names), checked


def test_raster_autograd_matches_central_differences():
    check_raster_fd(precomp=False, seed=3)
    check_raster_fd(precomp=True, seed=4)


def test_raster_f32_close_to_f64():
    t64, meta = gen_cases.raster_case(5, F64)
    meta = {k: str(v) for k, v in meta.items()}
    t32 = {k: v.to(torch.float32) for k, v in t64.items()}
    o64, o32 = rr.render(meta, t64), rr.render(meta, t32)
    assert torch.equal(o64["radii"], o32["radii"])
    assert (o64["color"] - o32["color"].double()).abs().max() < 1e-4


# ---------------------------------------------------------------- deform

def test_deform_parameter_counts():
    assert rd.param_count(rd.DeformNetwork(8, 256)) == 522280
    assert rd.param_count(rd.DeformNetwork(8, 256, is_6dof=True)) == 523051
    assert rd.param_count(rd.DeformNetwork(8, 256, "real")) == 506378
    assert rd.param_count(rd.CfCField(8, 256)) == 782888
    assert rd.param_count(rd.CfCField(6, 128)) == 334504
    assert rd.param_count(rd.CfCField(8, 256, "real")) == 764682
    assert rd.param_count(rd.CfCField(6, 128, "real")) == 318602


def test_deform_state_dict_names():
    names = set(rd.CfCField(6, 128).state_dict())
    for n in ["timenet.0.weight", "timenet.2.bias", "cells.0.backbone.0.weight",
              "cells.5.backbone.2.bias", "cells.3.ff1.weight", "cells.3.ff2.bias",
              "cells.3.time_a.weight", "cells.3.time_b.bias", "skip.weight", "head.bias"]:
        assert n in names, n
    assert len(names) == 2 * (2 + 6 * 6 + 2)
    names = set(rd.DeformNetwork(8, 256).state_dict())
    for n in ["timenet.0.weight", "linear.0.weight", "linear.5.weight", "linear.7.bias",
              "gaussian_warp.weight", "gaussian_rotation.bias", "gaussian_scaling.weight"]:
        assert n in names, n
    assert rd.DeformNetwork(8, 256).state_dict()["linear.5.weight"].shape == (256, 256 + 93)


def check_deform_fd(field, variant, activation="gelu"):
    t, meta = rd.new_case(field, variant, F64, 7, depth=4, width=16, activation=activation, n=5)
    out = rd.run(meta, t)

    def loss(tt):
        """The scalar loss and the ReLU pattern (signs of every ReLU input)."""
        net = rd.build(meta).to(F64)
        net.load_state_dict({k: tt[k] for k in net.state_dict()})
        pattern = []
        relu_inputs = list(getattr(net, "linear", [])) + (
            [net.timenet[0]] if hasattr(net, "timenet") else [])
        for m in relu_inputs:
            m.register_forward_hook(lambda _m, _i, o: pattern.append(o > 0))
        with torch.no_grad():
            a, b, c = net(tt["xyz"], tt["t"])
        return float((a * tt["grad_d_xyz"]).sum() + (b * tt["grad_d_rotation"]).sum()
                     + (c * tt["grad_d_scaling"]).sum()), pattern

    rng = random.Random(1)
    h = 1e-5
    skipped = 0
    wnames = [k for k in t if k not in ("xyz", "t", "grad_d_xyz", "grad_d_rotation", "grad_d_scaling")]
    for name, idx in [("t", (i, 0)) for i in range(5)] + [
            (n, None) for n in rng.sample(wnames, 6)]:
        if idx is None:
            idx = tuple(rng.randrange(s) for s in t[name].shape)
        vals, pats = [], []
        for step in (-2 * h, -h, h, 2 * h):
            tt = dict(t)
            tt[name] = t[name].clone()
            tt[name][idx] += step
            v, p = loss(tt)
            vals.append(v)
            pats.append(p)
        # Skip a coordinate whose steps cross a ReLU kink (the loss is not smooth there).
        if any(not torch.equal(x, y) for p in pats[1:] for x, y in zip(pats[0], p)):
            skipped += 1
            continue
        # Five-point central difference: O(h^4) truncation, round-off ~ eps |L| / h.
        num = (8 * (vals[2] - vals[1]) - (vals[3] - vals[0])) / (12 * h)
        ana = float((out["grad_t"] if name == "t" else out["grad." + name])[idx])
        err = abs(num - ana) / max(abs(num), abs(ana), 1e-4)
        assert err < 1e-6, (field, variant, name, idx, num, ana)
    assert skipped <= 2, skipped


def test_deform_autograd_matches_central_differences():
    check_deform_fd("mlp", "synthetic")
    check_deform_fd("mlp", "real")
    check_deform_fd("cfc", "synthetic", "gelu")
    check_deform_fd("cfc", "real", "lecun_tanh")


# ---------------------------------------------------------------- loss

def test_ssim_window_is_the_upstream_f32_window():
    want = ["0x1.0d956cp-10", "0x1.f1fe02p-8", "0x1.26eb18p-5", "0x1.bff0fep-4",
            "0x1.b43c3ep-3", "0x1.106560p-2"]
    got = rl.gaussian_1d(torch.float32).tolist()
    for k, w in enumerate(want):
        assert got[k] == float.fromhex(w) and got[10 - k] == float.fromhex(w), (k, got[k], w)


def ssim_loops(x, y):
    """SSIM with explicit loops, zero padding 5, f64 window (independent of conv2d)."""
    C, H, W = len(x), len(x[0]), len(x[0][0])
    g = [math.exp(-((k - 5) ** 2) / 4.5) for k in range(11)]
    sg = sum(g)
    g = [v / sg for v in g]
    def filt(img):
        return [[[sum(g[i] * g[j] * img[c][py + i - 5][px + j - 5]
                      for i in range(11) for j in range(11)
                      if 0 <= py + i - 5 < H and 0 <= px + j - 5 < W)
                  for px in range(W)] for py in range(H)] for c in range(C)]
    prod = lambda a, b: [[[a[c][i][j] * b[c][i][j] for j in range(W)] for i in range(H)]
                         for c in range(C)]
    m1, m2 = filt(x), filt(y)
    s11, s22, s12 = filt(prod(x, x)), filt(prod(y, y)), filt(prod(x, y))
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    tot = 0.0
    for c in range(C):
        for i in range(H):
            for j in range(W):
                a, b = m1[c][i][j], m2[c][i][j]
                v1, v2, v12 = s11[c][i][j] - a * a, s22[c][i][j] - b * b, s12[c][i][j] - a * b
                tot += ((2 * a * b + C1) * (2 * v12 + C2)) / ((a * a + b * b + C1) * (v1 + v2 + C2))
    return tot / (C * H * W)


def test_ssim_matches_plain_loops_and_gradient_matches_differences():
    t, meta = gen_cases.loss_case(3, F64, H=7, W=6)
    out = rl.run(meta, t)
    want = ssim_loops(t["image"].tolist(), t["gt"].tolist())
    assert abs(float(out["ssim"]) - want) < 1e-12, (float(out["ssim"]), want)
    l1 = float((t["image"] - t["gt"]).abs().mean())
    assert abs(float(out["loss"]) - (0.8 * l1 + 0.2 * (1 - want))) < 1e-12
    same = rl.run(meta, {"image": t["gt"], "gt": t["gt"]})
    assert abs(float(same["ssim"]) - 1.0) < 1e-12 and abs(float(same["loss"])) < 1e-12
    h = 1e-6
    for idx in [(0, 0, 0), (1, 3, 2), (2, 6, 5), (0, 4, 1)]:
        tp, tm = dict(t), dict(t)
        tp["image"] = t["image"].clone(); tp["image"][idx] += h
        tm["image"] = t["image"].clone(); tm["image"][idx] -= h
        num = (float(rl.run(meta, tp)["loss"]) - float(rl.run(meta, tm)["loss"])) / (2 * h)
        ana = float(out["grad_image"][idx])
        assert abs(num - ana) <= 1e-6 * max(abs(num), abs(ana), 1e-3), (idx, num, ana)


# ---------------------------------------------------------------- inria mode

def inria_agreeing_case(seed):
    """A rasterize case without the places where the Inria backward departs from the exact
    derivative: opacities below 0.9 (no alpha clamp), no Gaussian beyond the tangent clamp,
    no depth cotangent, footprints of several pixels (det^2 + 1e-7 ~ det^2)."""
    t, meta = gen_cases.raster_case(seed, F64, n=14, H=32, W=32)
    keep = slice(2, None)  # drop the one beyond the tangent clamp and the one behind the camera
    for k in ["means3D", "shs", "opacities", "scales", "rotations"]:
        t[k] = t[k][keep].clone()
    t["opacities"] = torch.clamp(t["opacities"], max=0.9)
    # Standard deviations of 0.4 to 0.6 world units: 2.6 to 8 pixels at depth 2.5 to 5.5,
    # so det >= ~50 and the 1e-7 changes det^2 by under 1e-10.
    t["scales"] = 0.4 + 0.2 * torch.rand(t["scales"].shape, generator=torch.Generator()
                                         .manual_seed(seed), dtype=F64)
    del t["grad_out_depth"]
    return t, {k: str(v) for k, v in meta.items()}


def test_inria_port_equals_autograd_where_the_formulas_agree():
    t, meta = inria_agreeing_case(7)
    exact = rr.render(meta, t)
    inria = rr.render(dict(meta, gradient="inria"), t)
    assert int((exact["radii"] > 0).sum()) >= 8
    for k in ["grad_means3D", "grad_means2D", "grad_shs", "grad_opacities", "grad_scales",
              "grad_rotations"]:
        scale = float(exact[k].abs().max())
        err = float((exact[k] - inria[k]).abs().max())
        assert scale > 0 and err <= 1e-9 * scale, (k, err, scale)


def test_inria_port_ignores_the_depth_cotangent():
    t, meta = gen_cases.raster_case(8, F64, n=12, H=32, W=32)
    meta = dict({k: str(v) for k, v in meta.items()}, gradient="inria")
    with_depth = rr.render(meta, t)
    t2 = dict(t)
    del t2["grad_out_depth"]
    without = rr.render(meta, t2)
    exact = rr.render(dict(meta, gradient="exact"), t)
    for k in ["grad_means3D", "grad_opacities", "grad_scales", "grad_rotations"]:
        assert torch.equal(with_depth[k], without[k]), k
    assert (exact["grad_means3D"] - with_depth["grad_means3D"]).abs().max() > 1e-3


# ---------------------------------------------------------------- step

def adam_formula(p, g, m, v, step, lr):
    """torch 1.13 single-tensor Adam, betas 0.9/0.999, eps 1e-15, written out."""
    t = step + 1
    m = 0.9 * m + 0.1 * g
    v = 0.999 * v + 0.001 * g * g
    bc1, bc2 = 1 - 0.9 ** t, 1 - 0.999 ** t
    return p - lr / bc1 * m / (v.sqrt() / math.sqrt(bc2) + 1e-15), m, v


def test_step_adam_matches_the_formula_for_every_group():
    t, meta = gen_cases.step_case(3, F64, "mlp", "real", is_6dof=True, warm=True)
    out, out_meta = rs.run(meta, t)
    lr = rs.LR_DEFAULTS
    N, K = t["sh"].shape[:2]
    rate = {"xyz": lr["xyz"], "opacity": lr["opacity"], "scaling": lr["scaling"],
            "rotation": lr["rotation"]}
    for group, r in rate.items():
        want, m, v = adam_formula(t[group], out[f"grad.{group}"], t[f"adam.{group}.m"],
                                  t[f"adam.{group}.v"], 7, r)
        assert (out[f"new.{group}"] - want).abs().max() <= 1e-15 * want.abs().max(), group
        assert (out[f"new.adam.{group}.m"] - m).abs().max() <= 1e-18, group
        assert out_meta[f"new.adam.{group}.step"] == 8
    sh_rate = torch.full((N, K, 3), lr["f_rest"], dtype=F64)
    sh_rate[:, 0] = lr["f_dc"]
    want, _, _ = adam_formula(t["sh"], out["grad.sh"], t["adam.sh.m"], t["adam.sh.v"], 7, sh_rate)
    assert (out["new.sh"] - want).abs().max() <= 1e-15 * want.abs().max()
    # The field's flat state, split in state_dict order.
    net = rd.build(meta)
    off = 0
    for name, q in net.named_parameters():
        n = q.numel()
        m, v = t["adam.field.m"][off:off + n], t["adam.field.v"][off:off + n]
        want, _, _ = adam_formula(t[name].flatten(), out[f"grad.{name}"].flatten(), m, v, 7,
                                  lr["field"])
        assert (out[f"new.{name}"].flatten() - want).abs().max() <= 1e-15 * want.abs().max()
        off += n
    assert off == t["adam.field.m"].numel()


def test_step_with_the_field_off_leaves_the_field_alone():
    t, meta = gen_cases.step_case(4, F64, "cfc", "real", warm=True, field_on=False)
    out, out_meta = rs.run(meta, t)
    assert not any(k.startswith("grad.cells") for k in out)
    assert torch.equal(out["new.head.weight"], t["head.weight"])
    assert torch.equal(out["new.adam.field.m"], t["adam.field.m"])
    assert out_meta["new.adam.field.step"] == 7 and out_meta["new.adam.xyz.step"] == 8


if __name__ == "__main__":
    failed = 0
    for name, fn in list(globals().items()):
        if name.startswith("test_") and callable(fn):
            try:
                fn()
                print(f"ok    {name}")
            except Exception as e:  # report every test, then fail
                failed += 1
                print(f"FAIL  {name}: {type(e).__name__}: {e}")
    sys.exit(1 if failed else 0)
