#!/usr/bin/env python3
"""Independent PyTorch reference of the Inria 3DGS rasterizer forward (R1p: with depth).

Written from the project's notes (docs/UPSTREAM.md §1–§3, docs/DECISIONS.md §1),
not from the Rust code. With `gradient=exact` (the default) gradients come from PyTorch
autograd of this forward: the true derivative of the forward as computed (zero through the
0.99 alpha clamp where it clamps, the exact tz term under the tx/tz clamp, stored
transmittance). With `gradient=inria` they come from `reference_raster_inria.py`, a port of
the Inria backward's formulas as written (docs/UPSTREAM.md §4).

Usage:
    python reference_raster.py CASE.safetensors OUT.safetensors

Case (stage `rasterize`): tensors means3D [N,3], shs [N,M,3] or colors_precomp [N,3],
opacities [N,1], scales [N,3] + rotations [N,4] or cov3D_precomp [N,6], viewmatrix [4,4],
projmatrix [4,4] (Inria memory layout: W2C^T and (P W2C)^T), campos [3], bg [3],
grad_out_color [3,H,W], optional grad_out_depth [1,H,W]; metadata image_height,
image_width, tanfovx, tanfovy, scale_modifier, sh_degree, optional gradient (exact|inria).

Output: color [3,H,W], depth [1,H,W], radii (int32 [N]), final_T [H,W], n_contrib
(int32 [H,W]), means2D [N,2], grad_means3D [N,3], grad_means2D [N,3] (NDC units: pixel
gradient times W/2, H/2; third column 0), grad_shs or grad_colors_precomp, grad_opacities
[N,1], grad_scales [N,3] and grad_rotations [N,4], or grad_cov3D_precomp [N,6].
The differentiated loss is sum(color * grad_out_color) + sum(depth * grad_out_depth)
(`inria`: the depth has no backward upstream, grad_out_depth is ignored).

Conventions of this reference (for culled Gaussians, radius 0): means2D is 0 and every
gradient is 0. All arithmetic is in the case dtype (f32 or f64) in the order
docs/UPSTREAM.md gives, except ndc2Pix, which upstream evaluates in f64 and rounds to f32.
The scale gradient includes the scale_modifier factor (exact derivative; `inria`:
d/d(scale_modifier * scales), as upstream returns it).

Speed is not a goal: small images (e.g. 32x32) and tens of Gaussians.
"""

import argparse
import sys

import torch

from common import case_dtype, load_case, require, save_case

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396]
SH_C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
         0.3731763325901154, -0.4570457994644658, 1.445305721320277,
         -0.5900435899266435]

BLOCK = 16


class Settings:
    """Scalars of a case, each a tensor of the case dtype (so f32 cases compute in f32)."""

    def __init__(self, meta, dtype):
        self.dtype = dtype
        self.H = int(require(meta, "image_height"))
        self.W = int(require(meta, "image_width"))
        c = lambda v: torch.tensor(float(v), dtype=dtype)
        self.tanfovx = c(require(meta, "tanfovx"))
        self.tanfovy = c(require(meta, "tanfovy"))
        self.scale_modifier = c(meta.get("scale_modifier", "1.0"))
        self.sh_degree = int(meta.get("sh_degree", "0"))
        # focal = size / (2 tanfov), in the case dtype.
        self.fx = c(self.W) / (c(2.0) * self.tanfovx)
        self.fy = c(self.H) / (c(2.0) * self.tanfovy)
        self.limx = c(1.3) * self.tanfovx
        self.limy = c(1.3) * self.tanfovy
        self.c = c


def transform_point(m, p, cols):
    """Rows of m (4x4, memory layout) applied as upstream: m0*x + m4*y + m8*z + m12.

    Returns the components listed in `cols` (column indices of the row-major tensor),
    each evaluated left to right."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    return [((m[0, k] * x + m[1, k] * y) + m[2, k] * z) + m[3, k] for k in cols]


def ndc2pix(v, size, dtype):
    """((v + 1) * S - 1) * 0.5, evaluated in f64 and rounded to the case dtype."""
    v64 = v.to(torch.float64)
    return (((v64 + 1.0) * float(size) - 1.0) * 0.5).to(dtype)


def quat_to_rot(q):
    """R(q) of the unnormalised quaternion (r, x, y, z), as a 3x3 nested list of columns."""
    r, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return [
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - r * z), 2.0 * (x * z + r * y)],
        [2.0 * (x * y + r * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - r * x)],
        [2.0 * (x * z - r * y), 2.0 * (y * z + r * x), 1.0 - 2.0 * (x * x + y * y)],
    ]


def cov3d_from(scales, rotations, mod):
    """Sigma = R S^2 R^T with S = diag(mod * s); the 6 upper-triangle values."""
    s = scales * mod
    R = quat_to_rot(rotations)
    # M = S R^T (math): M[k][j] = s_k R[j][k]; Sigma[i][j] = sum_k M[k][i] M[k][j].
    M = [[s[:, k] * R[j][k] for j in range(3)] for k in range(3)]
    def sig(i, j):
        return (M[0][i] * M[0][j] + M[1][i] * M[1][j]) + M[2][i] * M[2][j]
    return torch.stack([sig(0, 0), sig(0, 1), sig(0, 2), sig(1, 1), sig(1, 2), sig(2, 2)], dim=1)


def sh_to_rgb(deg, sh, means, campos, clamp=True):
    """computeColorFromSH: view-dependent colour, lower clamp at 0 (no upper clamp);
    `clamp=False` returns the value before the clamp."""
    d = means - campos
    length = torch.sqrt((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2])
    x = (d[:, 0] / length)[:, None]
    y = (d[:, 1] / length)[:, None]
    z = (d[:, 2] / length)[:, None]
    result = SH_C0 * sh[:, 0]
    if deg > 0:
        result = result - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
        if deg > 1:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            result = (result + SH_C2[0] * xy * sh[:, 4] + SH_C2[1] * yz * sh[:, 5]
                      + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6]
                      + SH_C2[3] * xz * sh[:, 7] + SH_C2[4] * (xx - yy) * sh[:, 8])
            if deg > 2:
                result = (result
                          + SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9]
                          + SH_C3[1] * xy * z * sh[:, 10]
                          + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
                          + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
                          + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13]
                          + SH_C3[5] * z * (xx - yy) * sh[:, 14]
                          + SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15])
    result = result + 0.5
    if not clamp:
        return result
    # torch.clamp passes the gradient at result == 0, like upstream (mask is result < 0).
    return torch.clamp(result, min=0.0)


def preprocess(st, view, proj, means, cov6):
    """Per-Gaussian projection: view depth, pixel mean, 2D conic, radius, tile rectangle.

    Returns a dict of tensors over the given Gaussians; `ok` says which survive culling."""
    c = st.c
    tx, ty, tz = transform_point(view, means, [0, 1, 2])
    hx, hy, hz, hw = transform_point(proj, means, [0, 1, 2, 3])
    p_w = c(1.0) / (hw + c(1e-7))
    px_ndc, py_ndc = hx * p_w, hy * p_w
    in_frustum = tz > c(0.2)

    # EWA with the 1.3 tan(fov) clamp on tx/tz, ty/tz (J uses the clamped t).
    txtz, tytz = tx / tz, ty / tz
    tx_c = torch.clamp(txtz, -st.limx, st.limx) * tz
    ty_c = torch.clamp(tytz, -st.limy, st.limy) * tz
    J00 = st.fx / tz
    J02 = -(st.fx * tx_c) / (tz * tz)
    J11 = st.fy / tz
    J12 = -(st.fy * ty_c) / (tz * tz)
    # Wr(i, j) = W2C(i, j) = view[j, i].
    Wr = [[view[j, i] for j in range(3)] for i in range(3)]
    # T = J Wr (2x3).
    T0 = [J00 * Wr[0][k] + J02 * Wr[2][k] for k in range(3)]
    T1 = [J11 * Wr[1][k] + J12 * Wr[2][k] for k in range(3)]
    S = [[cov6[:, 0], cov6[:, 1], cov6[:, 2]],
         [cov6[:, 1], cov6[:, 3], cov6[:, 4]],
         [cov6[:, 2], cov6[:, 4], cov6[:, 5]]]
    def quad(A, B):
        # A Sigma B^T for rows A, B.
        SB = [(S[k][0] * B[0] + S[k][1] * B[1]) + S[k][2] * B[2] for k in range(3)]
        return (A[0] * SB[0] + A[1] * SB[1]) + A[2] * SB[2]
    a = quad(T0, T0) + c(0.3)
    b = quad(T0, T1)
    cc = quad(T1, T1) + c(0.3)

    det = a * cc - b * b
    det_ok = det != 0.0
    det_inv = c(1.0) / det
    conic = torch.stack([cc * det_inv, -b * det_inv, a * det_inv], dim=1)
    mid = c(0.5) * (a + cc)
    disc = torch.sqrt(torch.clamp(mid * mid - det, min=0.1))
    lam1, lam2 = mid + disc, mid - disc
    radius = torch.ceil(c(3.0) * torch.sqrt(torch.maximum(lam1, lam2))).detach()

    mx = ndc2pix(px_ndc, st.W, st.dtype)
    my = ndc2pix(py_ndc, st.H, st.dtype)
    gx, gy = (st.W + BLOCK - 1) // BLOCK, (st.H + BLOCK - 1) // BLOCK
    r = radius
    with torch.no_grad():
        def rect(v, off, g):
            return torch.clamp(torch.trunc((v + off) / c(BLOCK)), 0, g).to(torch.int64)
        # Guard against NaN/inf of Gaussians culled earlier.
        safe = in_frustum & det_ok & torch.isfinite(mx) & torch.isfinite(my) & torch.isfinite(r)
        mxs = torch.where(safe, mx, torch.zeros_like(mx))
        mys = torch.where(safe, my, torch.zeros_like(my))
        rs = torch.where(safe, r, torch.zeros_like(r))
        rmin_x, rmin_y = rect(mxs, -rs, gx), rect(mys, -rs, gy)
        rmax_x, rmax_y = rect(mxs, rs + c(BLOCK - 1), gx), rect(mys, rs + c(BLOCK - 1), gy)
        area = (rmax_y - rmin_y) * (rmax_x - rmin_x)
        ok = safe & (area > 0)
    return dict(depth=tz, mx=mx, my=my, conic=conic, radius=r, ok=ok,
                rect=(rmin_x, rmin_y, rmax_x, rmax_y))


class Camera:
    """The camera and background of a case, in the case dtype."""

    def __init__(self, t, dtype):
        self.view = t["viewmatrix"].to(dtype)
        self.proj = t["projmatrix"].to(dtype)
        self.campos = t["campos"].to(dtype)
        self.bg = t["bg"].to(dtype)


def forward(st, cam, means, opac, shs=None, colors_precomp=None, scales=None, rotations=None,
            cov3D_precomp=None):
    """The rasterizer forward on (possibly autograd-connected) inputs.

    means [N,3], opac [N,1] (activated), shs [N,M,3] or colors_precomp [N,3], scales [N,3]
    + rotations [N,4] or cov3D_precomp [N,6]. Returns a dict: color [3,H,W], depth [1,H,W],
    radii (int32 [N]), final_T [H,W], n_contrib (int32 [H,W]), means2D [N,2] (detached);
    and what a backward needs: vis (indices of the Gaussians that survive culling), mx, my
    (their pixel centres, with retain_grad), conic [V,3], opac_v [V], colour [V,3] (after the
    clamp), cov6 [V,6], tiles ({tile index: visible positions in blending order})."""
    N = means.shape[0]
    H, W = st.H, st.W
    c = st.c
    dtype = st.dtype
    view, proj, campos = cam.view, cam.proj, cam.campos
    use_sh = shs is not None
    use_cov = cov3D_precomp is not None

    def cov6_of(idx):
        if use_cov:
            return cov3D_precomp[idx]
        return cov3d_from(scales[idx], rotations[idx], st.scale_modifier)

    # Pass 1 (no gradient, all Gaussians): which survive culling.
    all_idx = torch.arange(N)
    with torch.no_grad():
        pre_all = preprocess(st, view, proj, means.detach(), cov6_of(all_idx).detach())
    vis = torch.nonzero(pre_all["ok"]).flatten()

    # Pass 2 (differentiable, visible Gaussians only: no inf/NaN enters autograd).
    cov6 = cov6_of(vis)
    pre = preprocess(st, view, proj, means[vis], cov6)
    assert bool(pre["ok"].all())
    mx, my = pre["mx"], pre["my"]
    if mx.requires_grad:
        mx.retain_grad()
        my.retain_grad()
    conic = pre["conic"]
    depth_g = pre["depth"]
    opac_v = opac[vis, 0]
    if use_sh:
        colour = sh_to_rgb(st.sh_degree, shs[vis], means[vis], campos)
    else:
        colour = colors_precomp[vis]

    radii = torch.zeros(N, dtype=torch.int32)
    radii[vis] = pre["radius"].to(torch.int32)

    # Binning: per tile, the visible Gaussians touching it, stable-sorted by depth
    # (emission order is ascending Gaussian index, so ties keep index order).
    rmin_x, rmin_y, rmax_x, rmax_y = pre["rect"]
    gx, gy = (W + BLOCK - 1) // BLOCK, (H + BLOCK - 1) // BLOCK
    dvals = depth_g.detach().tolist()
    tiles = {}
    for j in range(len(vis)):
        for ty_ in range(int(rmin_y[j]), int(rmax_y[j])):
            for tx_ in range(int(rmin_x[j]), int(rmax_x[j])):
                tiles.setdefault(ty_ * gx + tx_, []).append(j)
    for k in tiles:
        tiles[k] = sorted(tiles[k], key=lambda j: dvals[j])

    one = c(1.0)
    inv255 = c(1.0 / 255.0)
    t_stop = c(0.0001)
    zero = c(0.0)
    depth_parts, final_parts, contrib_parts = {}, {}, {}
    color_parts = {}
    for ty_ in range(gy):
        for tx_ in range(gx):
            pxf, pyf = tile_pixels(st, ty_, tx_)
            P = pxf.shape[0]
            T = torch.ones(P, dtype=dtype)
            C = [torch.zeros(P, dtype=dtype) for _ in range(3)]
            D = torch.zeros(P, dtype=dtype)
            done = torch.zeros(P, dtype=torch.bool)
            contributor = torch.zeros(P, dtype=torch.int32)
            last = torch.zeros(P, dtype=torch.int32)
            for j in tiles.get(ty_ * gx + tx_, []):
                active = ~done
                contributor = contributor + active.to(torch.int32)
                dx = mx[j] - pxf
                dy = my[j] - pyf
                A, B, Cc = conic[j, 0], conic[j, 1], conic[j, 2]
                power = c(-0.5) * (A * dx * dx + Cc * dy * dy) - B * dx * dy
                skip = power > 0.0
                # exp of a positive power is never used; keep it out of autograd (inf).
                G = torch.exp(torch.where(skip, zero, power))
                # clamp(max) passes the gradient only where unclamped: exact derivative.
                alpha = torch.clamp(opac_v[j] * G, max=0.99)
                skip = skip | (alpha < inv255)
                test_T = T * (one - alpha)
                stop = active & ~skip & (test_T < t_stop)
                blend = active & ~skip & ~stop
                done = done | stop
                for ch in range(3):
                    C[ch] = C[ch] + torch.where(blend, colour[j, ch] * alpha * T, zero)
                D = D + torch.where(blend, depth_g[j] * alpha * T, zero)
                T = torch.where(blend, test_T, T)
                last = torch.where(blend, contributor, last)
            key = (ty_, tx_)
            color_parts[key] = [C[ch] + T * cam.bg[ch] for ch in range(3)]
            depth_parts[key], final_parts[key], contrib_parts[key] = D, T, last

    def assemble(get, dt):
        rows = []
        for ty_ in range(gy):
            row = []
            for tx_ in range(gx):
                x0, y0 = tx_ * BLOCK, ty_ * BLOCK
                h, w = min(BLOCK, H - y0), min(BLOCK, W - x0)
                row.append(get((ty_, tx_)).reshape(h, w).to(dt))
            rows.append(torch.cat(row, dim=1))
        return torch.cat(rows, dim=0)

    means2D = torch.zeros(N, 2, dtype=dtype)
    means2D[vis, 0] = mx.detach()
    means2D[vis, 1] = my.detach()
    return {
        "color": torch.stack([assemble(lambda k: color_parts[k][ch], dtype) for ch in range(3)]),
        "depth": assemble(lambda k: depth_parts[k], dtype)[None],
        "final_T": assemble(lambda k: final_parts[k], dtype),
        "n_contrib": assemble(lambda k: contrib_parts[k], torch.int32),
        "radii": radii, "means2D": means2D,
        "vis": vis, "mx": mx, "my": my, "conic": conic, "opac_v": opac_v, "colour": colour,
        "cov6": cov6, "tiles": tiles,
    }


def tile_pixels(st, ty_, tx_):
    """Pixel x and y coordinates (case dtype) of one tile, row-major within the tile."""
    x0, y0 = tx_ * BLOCK, ty_ * BLOCK
    xs = torch.arange(x0, min(x0 + BLOCK, st.W))
    ys = torch.arange(y0, min(y0 + BLOCK, st.H))
    pyg, pxg = torch.meshgrid(ys, xs, indexing="ij")
    return pxg.flatten().to(st.dtype), pyg.flatten().to(st.dtype)


def grad_means2d(fwd, N, st):
    """The NDC-space gradient of the pixel centres [N,3] after a backward (third column 0)."""
    g2 = torch.zeros(N, 3, dtype=st.dtype)
    vis = fwd["vis"]
    if fwd["mx"].grad is not None:
        g2[vis, 0] = fwd["mx"].grad * (0.5 * st.W)
    if fwd["my"].grad is not None:
        g2[vis, 1] = fwd["my"].grad * (0.5 * st.H)
    return g2


def render(meta, t):
    dtype = case_dtype(t, "means3D")
    st = Settings(meta, dtype)
    cam = Camera(t, dtype)
    gradient = meta.get("gradient", "exact")
    if gradient not in ("exact", "inria"):
        raise SystemExit(f"gradient {gradient!r}: expected exact or inria")
    inria = gradient == "inria"

    leaves = {}
    def leaf(name):
        v = t[name].to(dtype).clone().requires_grad_(not inria)
        leaves[name] = v
        return v
    inputs = {"means": leaf("means3D"), "opac": leaf("opacities")}
    use_sh = "shs" in t
    if use_sh:
        inputs["shs"] = leaf("shs")
    else:
        inputs["colors_precomp"] = leaf("colors_precomp")
    use_cov = "cov3D_precomp" in t
    if use_cov:
        inputs["cov3D_precomp"] = leaf("cov3D_precomp")
    else:
        inputs["scales"], inputs["rotations"] = leaf("scales"), leaf("rotations")
    N = inputs["means"].shape[0]

    fwd = forward(st, cam, **inputs)
    out = {k: fwd[k].detach() for k in ("color", "depth", "radii", "final_T", "n_contrib",
                                         "means2D")}
    grad_color = t["grad_out_color"].to(dtype)
    if inria:
        # Upstream's backward formulas, written out (reference_raster_inria.py); the depth
        # output has no backward there, so grad_out_depth is ignored.
        import reference_raster_inria
        grads = reference_raster_inria.backward(st, cam, inputs, fwd, grad_color)
        out["grad_means2D"] = grads.pop("means2D")
        names = {"means": "means3D", "opac": "opacities"}
        for k, v in grads.items():
            out["grad_" + names.get(k, k)] = v
        return out

    loss = (fwd["color"] * grad_color).sum()
    if "grad_out_depth" in t:
        loss = loss + (fwd["depth"] * t["grad_out_depth"].to(dtype)).sum()
    loss.backward()

    def grad(name):
        g = leaves[name].grad
        return torch.zeros_like(leaves[name]) if g is None else g

    out["grad_means3D"] = grad("means3D")
    out["grad_means2D"] = grad_means2d(fwd, N, st)
    out["grad_opacities"] = grad("opacities")
    out["grad_shs" if use_sh else "grad_colors_precomp"] = grad("shs" if use_sh else "colors_precomp")
    if use_cov:
        out["grad_cov3D_precomp"] = grad("cov3D_precomp")
    else:
        out["grad_scales"] = grad("scales")
        out["grad_rotations"] = grad("rotations")
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("case")
    ap.add_argument("out")
    args = ap.parse_args(argv)
    meta, t = load_case(args.case)
    if meta.get("stage", "rasterize") != "rasterize":
        raise SystemExit(f"{args.case}: stage is {meta.get('stage')!r}, expected 'rasterize'")
    out = render(meta, t)
    save_case(args.out, out, {"stage": "rasterize", "producer": "python/reference_raster.py",
                              "torch": torch.__version__})
    return 0


if __name__ == "__main__":
    sys.exit(main())
