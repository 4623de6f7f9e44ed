"""Compare the oracle with the CUDA rasterizers it reproduces, on a machine with a GPU.

    python python/cuda_crosscheck.py inria                    [--frame DIR] [--json OUT]
    python python/cuda_crosscheck.py gsplat --version 1.5.3   [--frame DIR] [--json OUT]
    python python/cuda_crosscheck.py gsplat --version 1.6     [--frame DIR] [--json OUT]

`inria` imports `diff_gaussian_rasterization` (build the D-3DGS fork, ingra14m
diff-gaussian-rasterization-extentions f2d8fa9, whose backward is Inria's 59f5f77); `gsplat`
imports `gsplat` (built with fast math off: `FAST_MATH=0` at 1.6, `--use_fast_math` removed
from setup.py at 1.5.3). Each scene is rendered and differentiated on the GPU in float32
twice, and by the oracle (`liquid_splat`, on the CPU) from the same float32 inputs:

- `ls32`: the oracle in float32 in the backend's own gradient mode (`inria` / `gsplat`),
- `ls64`: the same mode in float64 on the same values (the mode's formulas in near-exact
  arithmetic),
- `exact64`: the true derivative (`exact` mode) in float64.

Printed per tensor: the CUDA result against `ls64` and `ls32`, the oracle's float32 against
`ls64` (max |difference| over the tensor's max |entry|, and relative L2), CUDA's run-to-run
difference (atomic sums), the backend mode against the true derivative, and whether CUDA
passes the recommended float32 tolerances (`fixtures/cases/tolerances_f32.json`) against
`ls32`, with its mismatch fraction. Integer outputs are counted as entries that differ.

Scenes: `random` (seeded Gaussians in front of a rotated camera, SH degree 3, 250x190 so the
last tile row and column are partial) and with `--frame DIR` a saved frame of
`benches/opensplat_scene` (`gaussians0.f32`, `camera0.f32`, `meta.txt`: a trained D-NeRF
frame). `--standin` replaces the CUDA module by the oracle's own drop-in
(`liquid_splat.torch`, `exact` mode, on the CPU) to test this script without a GPU.
"""

import argparse
import json
import math
import os
import sys

import numpy as np
import torch

import liquid_splat as ls
import liquid_splat.gsplat as lsg
from liquid_splat.testing import compare, recommended_tolerances

from gen_cases import projection  # noqa: E402  (this folder: Inria's getProjectionMatrix)


# ---------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------


def camera(w2c, width, height, tanx, tany):
    """Inria's settings (transposed matrices) and gsplat's viewmat and K, float32."""
    full = projection(tanx, tany).numpy() @ w2c  # Inria's, znear 0.01, zfar 100
    campos = np.linalg.inv(w2c)[:3, 3]
    fx, fy = width / (2 * tanx), height / (2 * tany)
    return dict(
        viewmatrix=np.ascontiguousarray(w2c.T, np.float32),
        projmatrix=np.ascontiguousarray(full.T, np.float32),
        campos=campos.astype(np.float32), tanfovx=float(np.float32(tanx)),
        tanfovy=float(np.float32(tany)), width=width, height=height,
        viewmat=w2c.astype(np.float32),
        K=np.array([[fx, 0, width / 2], [0, fy, height / 2], [0, 0, 1]], np.float32),
    )


def random_scene(seed=0, n=4000, width=250, height=190):
    rng = np.random.default_rng(seed)
    a, b = 0.15, -0.1  # a rotated, translated camera
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    w2c = np.eye(4)
    w2c[:3, :3] = rx @ ry
    w2c[:3, 3] = [0.2, -0.1, 4.0]
    cam = camera(w2c, width, height, 0.45, 0.45 * height / width)
    q = rng.normal(size=(n, 4))
    g = dict(
        means=rng.uniform([-1.6, -1.2, -1.5], [1.6, 1.2, 1.5], size=(n, 3)),
        scales=np.exp(rng.normal(-3.6, 0.6, size=(n, 3))),
        quats=q / np.linalg.norm(q, axis=1, keepdims=True),
        opacities=1 / (1 + np.exp(-rng.normal(0.0, 2.0, size=n))),
        sh=np.concatenate([rng.normal(0, 0.6, size=(n, 1, 3)),
                           rng.normal(0, 0.15, size=(n, 15, 3))], axis=1),
    )
    g = {k: v.astype(np.float32) for k, v in g.items()}
    return dict(name="random", gaussians=g, cam=cam, bg=np.array([0.2, 0.3, 0.1], np.float32))


def frame_scene(directory):
    n, width, height, _, _ = (int(x) for x in open(os.path.join(directory, "meta.txt")).read().split())
    v = np.fromfile(os.path.join(directory, "gaussians0.f32"), dtype="<f4")
    parts, o = {}, 0
    for k, size in (("means", 3), ("scales", 3), ("quats", 4), ("opacities", 1), ("sh", 48)):
        parts[k] = v[o:o + n * size].reshape((n, 16, 3) if k == "sh" else (n, size) if size > 1 else (n,))
        o += n * size
    c = np.fromfile(os.path.join(directory, "camera0.f32"), dtype="<f4")
    w2c = c[:16].reshape(4, 4).astype(np.float64)
    tanx, tany = float(c[32]), float(c[33])
    cam = camera(w2c, width, height, tanx, tany)
    # Keep the file's own matrices (the trainer's float32 values) for the Inria settings.
    cam.update(viewmatrix=np.ascontiguousarray(c[:16].reshape(4, 4).T),
               projmatrix=np.ascontiguousarray(c[16:32].reshape(4, 4).T),
               campos=c[34:37].copy(), tanfovx=tanx, tanfovy=tany)
    return dict(name="hellwarrior frame", gaussians=parts, cam=cam, bg=c[37:40].copy())


# ---------------------------------------------------------------------------
# Statistics
# ---------------------------------------------------------------------------


def errors(a, ref):
    a = np.asarray(a, np.float64).ravel()
    ref = np.asarray(ref, np.float64).ravel()
    if a.shape != ref.shape:
        return {"shape": f"{a.shape} vs {ref.shape}"}
    scale = float(np.max(np.abs(ref))) if ref.size else 0.0
    d = np.abs(a - ref)
    l2 = float(np.linalg.norm(ref))
    return {"max": float(d.max()) / scale if scale > 0 else float(d.max()),
            "rel_l2": float(np.linalg.norm(a - ref)) / l2 if l2 > 0 else float(np.linalg.norm(a - ref))}


def differing(a, b):
    a, b = np.asarray(a).ravel(), np.asarray(b).ravel()
    return int(np.count_nonzero(a != b)) if a.shape == b.shape else -1


def table(rows, out):
    cols = ["tensor", "CUDA vs ls64", "CUDA vs ls32", "ls32 vs ls64", "CUDA run2-run1",
            "mode vs exact64", "f32 tolerances"]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(str(r.get(c, "")) for c in cols) + " |")
    print("\n".join(lines), file=out)


def fmt(e):
    if "shape" in e:
        return e["shape"]
    return f"{e['max']:.1e} / {e['rel_l2']:.1e}"


def summarise(cuda, cuda2, ls32, ls64, exact64, tol_report):
    """Rows for the tensors present in all results (floats: error pairs; ints: counts)."""
    rows, record = [], {}
    status = {t["name"]: t for t in tol_report.tensors}
    for k in sorted(ls32):
        if k not in cuda:
            continue
        t = status.get(k)
        tol = "" if t is None else (
            f"{t['status']} ({t['stats'].get('mismatches', 0)}/{t['stats'].get('numel', 0)})"
            if "stats" in t else t["status"])
        if np.issubdtype(np.asarray(ls32[k]).dtype, np.integer):
            r = {"tensor": k, "CUDA vs ls32": f"{differing(cuda[k], ls32[k])} differ",
                 "CUDA vs ls64": f"{differing(cuda[k], ls64[k])} differ",
                 "ls32 vs ls64": f"{differing(ls32[k], ls64[k])} differ",
                 "CUDA run2-run1": f"{differing(cuda[k], cuda2[k])} differ",
                 "f32 tolerances": tol}
            record[k] = {c: r[c] for c in r if c != "tensor"}
        else:
            e = {"CUDA vs ls64": errors(cuda[k], ls64[k]), "CUDA vs ls32": errors(cuda[k], ls32[k]),
                 "ls32 vs ls64": errors(ls32[k], ls64[k]),
                 "CUDA run2-run1": errors(cuda2[k], cuda[k])}
            if k in exact64:
                e["mode vs exact64"] = errors(ls64[k], exact64[k])
            r = {"tensor": k, **{c: fmt(v) for c, v in e.items()}, "f32 tolerances": tol}
            record[k] = {**e, "f32 tolerances": tol}
        rows.append(r)
    return rows, record


# ---------------------------------------------------------------------------
# Inria
# ---------------------------------------------------------------------------


def inria_backend(standin):
    if standin:
        import liquid_splat.torch as m
        return m, "cpu"
    import diff_gaussian_rasterization as m
    return m, "cuda"


def run_inria_cuda(mod, dev, scene, grad_color):
    g, cam = scene["gaussians"], scene["cam"]
    t = {k: torch.tensor(v, device=dev, requires_grad=True) for k, v in g.items()}
    settings = mod.GaussianRasterizationSettings(
        image_height=cam["height"], image_width=cam["width"], tanfovx=cam["tanfovx"],
        tanfovy=cam["tanfovy"], bg=torch.tensor(scene["bg"], device=dev), scale_modifier=1.0,
        viewmatrix=torch.tensor(cam["viewmatrix"], device=dev),
        projmatrix=torch.tensor(cam["projmatrix"], device=dev), sh_degree=3,
        campos=torch.tensor(cam["campos"], device=dev), prefiltered=False, debug=False)
    means2D = torch.zeros_like(t["means"], requires_grad=True)
    color, radii, depth = mod.GaussianRasterizer(settings)(
        means3D=t["means"], means2D=means2D, opacities=t["opacities"][:, None], shs=t["sh"],
        scales=t["scales"], rotations=t["quats"])
    (color * torch.tensor(grad_color, device=dev)).sum().backward()
    n = lambda x: x.detach().cpu().numpy()
    return {"color": n(color), "depth": n(depth), "radii": n(radii).astype(np.int32),
            "grad_means3D": n(t["means"].grad), "grad_means2D": n(means2D.grad),
            "grad_shs": n(t["sh"].grad), "grad_opacities": n(t["opacities"].grad)[:, None],
            "grad_scales": n(t["scales"].grad), "grad_rotations": n(t["quats"].grad)}


def run_inria_oracle(scene, grad_color, dtype, gradient):
    g, cam = scene["gaussians"], scene["cam"]
    c = lambda x: np.ascontiguousarray(x, dtype)
    kw = dict(means3D=c(g["means"]), opacities=c(g["opacities"])[:, None], shs=c(g["sh"]),
              scales=c(g["scales"]), rotations=c(g["quats"]), viewmatrix=c(cam["viewmatrix"]),
              projmatrix=c(cam["projmatrix"]), campos=c(cam["campos"]), bg=c(scene["bg"]),
              image_height=cam["height"], image_width=cam["width"], tanfovx=cam["tanfovx"],
              tanfovy=cam["tanfovy"], sh_degree=3)
    f = ls.rasterize(**kw)
    out = {"color": f.color, "depth": f.depth, "radii": f.radii}
    out.update(ls.rasterize_vjp(**kw, grad_color=c(grad_color), gradient=gradient))
    return out


def check_inria(scene, standin, seed):
    mod, dev = inria_backend(standin)
    cam = scene["cam"]
    grad_color = np.random.default_rng(seed + 100).normal(
        size=(3, cam["height"], cam["width"])).astype(np.float32)
    cuda = run_inria_cuda(mod, dev, scene, grad_color)
    cuda2 = run_inria_cuda(mod, dev, scene, grad_color)
    mode = "exact" if standin else "inria"
    ls32 = run_inria_oracle(scene, grad_color, np.float32, mode)
    ls64 = run_inria_oracle(scene, grad_color, np.float64, mode)
    exact64 = run_inria_oracle(scene, grad_color, np.float64, "exact")
    exact64 = {k: v for k, v in exact64.items() if k.startswith("grad_")}
    rep = compare(ls32, {k: v for k, v in cuda.items() if k in ls32},
                  tolerances=recommended_tolerances("float32"))
    return summarise(cuda, cuda2, ls32, ls64, exact64, rep)


# ---------------------------------------------------------------------------
# gsplat
# ---------------------------------------------------------------------------


def gsplat_backend(standin, version):
    if standin:
        import liquid_splat.torch as m
        return m.rasterization, "cpu"
    import gsplat
    if not gsplat.__version__.startswith(version):
        raise SystemExit(f"--version {version}, but the gsplat imported is {gsplat.__version__}")
    try:
        # The extension built beforehand (python/cuda_peers.sh); without it gsplat would
        # compile one on first use, with fast math unless FAST_MATH=0 is set.
        import gsplat.csrc  # noqa: F401
    except ImportError as e:
        raise SystemExit(f"gsplat.csrc is not built next to {gsplat.__file__}: {e}")
    return gsplat.rasterization, "cuda"


GS_META = ("radii", "means2d", "depths", "conics", "tiles_per_gauss", "isect_ids",
           "flatten_ids", "isect_offsets")


def zero_culled(d):
    """Set to 0 the dense `means2d`, `depths` and `conics` rows of Gaussians whose radii (in
    `d` itself) are 0: gsplat leaves them uninitialised (`at::empty`), the oracle writes 0."""
    culled = np.all(d["meta.radii"].reshape(-1, 2) == 0, axis=1)
    for k in ("meta.means2d", "meta.depths", "meta.conics"):
        if k in d:
            v = d[k].reshape(culled.size, -1).copy()
            v[culled] = 0
            d[k] = v.reshape(d[k].shape)


def gs_args(scene, packed, mode):
    cam = scene["cam"]
    return dict(width=cam["width"], height=cam["height"], sh_degree=3, packed=packed,
                rasterize_mode=mode)


def run_gsplat_cuda(fn, dev, scene, cot, packed, mode, extra, with_bg):
    g, cam = scene["gaussians"], scene["cam"]
    t = {k: torch.tensor(v, device=dev, requires_grad=True) for k, v in g.items()}
    bg = torch.tensor(scene["bg"][None], device=dev, requires_grad=True) if with_bg else None
    colors, alphas, meta = fn(t["means"], t["quats"], t["scales"], t["opacities"], t["sh"],
                              torch.tensor(cam["viewmat"][None], device=dev),
                              torch.tensor(cam["K"][None], device=dev), backgrounds=bg,
                              **gs_args(scene, packed, mode), **extra)
    m2d = meta["means2d"] if isinstance(meta["means2d"], torch.Tensor) else None
    if m2d is not None and m2d.requires_grad:
        m2d.retain_grad()
    loss = (colors * torch.tensor(cot[0], device=dev)).sum() + \
        (alphas * torch.tensor(cot[1], device=dev)).sum()
    loss.backward()
    n = lambda x: x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    out = {"render_colors": n(colors), "render_alphas": n(alphas),
           "v_means": n(t["means"].grad), "v_quats": n(t["quats"].grad),
           "v_scales": n(t["scales"].grad), "v_opacities": n(t["opacities"].grad),
           "v_colors": n(t["sh"].grad)}
    if with_bg:
        out["v_backgrounds"] = n(bg.grad)
    if m2d is not None and m2d.grad is not None:
        out["v_means2d"] = n(m2d.grad)
    for k in GS_META:
        if k in meta:
            v = n(meta[k])
            out["meta." + k] = v.astype(np.int32) if k in ("radii", "tiles_per_gauss",
                                                           "flatten_ids", "isect_offsets") else v
    return out


def run_gsplat_oracle(scene, cot, dtype, version, gradient, packed, mode, with_bg):
    g, cam = scene["gaussians"], scene["cam"]
    c = lambda x: np.ascontiguousarray(x, dtype)
    args = (c(g["means"]), c(g["quats"]), c(g["scales"]), c(g["opacities"]), c(g["sh"]),
            c(cam["viewmat"][None]), c(cam["K"][None]))
    kw = dict(backgrounds=c(scene["bg"][None]) if with_bg else None, version=version,
              gradient=gradient,
              **gs_args(scene, packed, mode))
    r = lsg.rasterization(*args, **kw)
    out = {"render_colors": r.render_colors, "render_alphas": r.render_alphas}
    for k in GS_META:
        if k in r.meta:
            out["meta." + k] = r.meta[k]
    out.update(lsg.rasterization_vjp(*args, **kw, v_render_colors=c(cot[0]),
                                     v_render_alphas=c(cot[1])))
    out.pop("v_means2d_abs", None)
    return out


def check_gsplat(scene, standin, seed, version, packed, mode):
    fn, dev = gsplat_backend(standin, version)
    cam = scene["cam"]
    rng = np.random.default_rng(seed + 200)
    cot = (rng.normal(size=(1, cam["height"], cam["width"], 3)).astype(np.float32),
           rng.normal(size=(1, cam["height"], cam["width"], 1)).astype(np.float32))
    extra = {"version": version} if standin else {}  # the drop-in's default is 1.6
    # gsplat 1.5.3 refuses backgrounds with packed=True (rasterize_to_pixels takes the
    # image dimensions from the packed means2d [nnz,2], so it expects backgrounds [D]).
    bg = not (packed and version == "1.5.3")
    cuda = run_gsplat_cuda(fn, dev, scene, cot, packed, mode, extra, bg)
    cuda2 = run_gsplat_cuda(fn, dev, scene, cot, packed, mode, extra, bg)
    gm = "exact" if standin else "gsplat"
    ls32 = run_gsplat_oracle(scene, cot, np.float32, version, gm, packed, mode, bg)
    ls64 = run_gsplat_oracle(scene, cot, np.float64, version, gm, packed, mode, bg)
    exact64 = run_gsplat_oracle(scene, cot, np.float64, version, "exact", packed, mode, bg)
    if not packed:
        for d in (cuda, cuda2, ls32, ls64):
            zero_culled(d)
    exact64 = {k: v for k, v in exact64.items() if k.startswith("v_")}
    # CUDA's tensors in the oracle's shapes (gsplat's leading camera axis, for one).
    for d in (cuda, cuda2):
        for k in d:
            if k in ls32 and d[k].shape != ls32[k].shape and d[k].size == ls32[k].size:
                d[k] = d[k].reshape(ls32[k].shape)
    # isect_ids (int64 keys whose low word is the depth's float bits) are only counted
    # (entries that differ), not checked against the tolerances; tensors of another length
    # (the tiles' entries, where a tile decision differs) are counted as `-1 differ`.
    common = [k for k in cuda
              if k in ls32 and k != "meta.isect_ids" and cuda[k].shape == ls32[k].shape]
    rep = compare({k: ls32[k] for k in common}, {k: cuda[k] for k in common},
                  tolerances=recommended_tolerances("float32"))
    return summarise(cuda, cuda2, ls32, ls64, exact64, rep)


# ---------------------------------------------------------------------------


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("backend", choices=["inria", "gsplat"])
    p.add_argument("--version", choices=lsg.VERSIONS, default="1.6",
                   help="gsplat version the imported gsplat is (default 1.6)")
    p.add_argument("--frame", help="a benches/opensplat_scene output folder (uses camera 0)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--standin", action="store_true",
                   help="use liquid_splat.torch's drop-ins instead of the CUDA module (no GPU)")
    p.add_argument("--json", help="write every number to this file")
    a = p.parse_args(argv)
    if not a.standin and not torch.cuda.is_available():
        print("no CUDA device: run with --standin to test the script on the CPU", file=sys.stderr)
        return 2
    scenes = [random_scene(a.seed)]
    if a.frame:
        scenes.append(frame_scene(a.frame))
    results = {"backend": a.backend, "version": a.version if a.backend == "gsplat" else None,
               "standin": a.standin, "torch": torch.__version__,
               "device": torch.cuda.get_device_name() if not a.standin else "cpu", "scenes": []}
    print(f"# {a.backend}{' ' + a.version if a.backend == 'gsplat' else ''} on "
          f"{results['device']}, torch {torch.__version__}")
    runs = [(s, None, None) for s in scenes] if a.backend == "inria" else \
        [(s, packed, mode) for s in scenes
         for packed, mode in ((False, "classic"), (True, "antialiased"))]
    for scene, packed, mode in runs:
        g = scene["gaussians"]
        what = f"{scene['name']}: {len(g['opacities'])} Gaussians, " \
               f"{scene['cam']['width']}x{scene['cam']['height']}"
        if a.backend == "inria":
            rows, record = check_inria(scene, a.standin, a.seed)
        else:
            what += f", packed={packed}, {mode}"
            rows, record = check_gsplat(scene, a.standin, a.seed, a.version, packed, mode)
        print(f"\n## {what}\n")
        table(rows, sys.stdout)
        results["scenes"].append({"scene": what, "tensors": record})
    if a.json:
        with open(a.json, "w") as f:
            json.dump(results, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
