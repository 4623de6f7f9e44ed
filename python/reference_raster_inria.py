"""The Inria rasterizer's backward formulas as written: the `inria` gradient mode.

A port to PyTorch (no autograd: every formula spelled out, in the case dtype) of
diff-gaussian-rasterization's cuda_rasterizer/backward.cu at 59f5f77 (R1 in docs/UPSTREAM.md
§0, the formulas in §4; the D-3DGS fork R1p has the same backward.cu and no depth backward),
written from that code and docs/UPSTREAM.md, not from the Rust code. The forward values it
needs (pixel centres, conics, clamped colours, final transmittance, last contributors, tile
lists) come from `reference_raster.forward`.

Where these formulas are not the exact derivative of the forward (docs/UPSTREAM.md §4.6):
the 0.99 alpha clamp is ignored by the gradient, the transmittance is recovered by division
from T_final, the tz term under the tangent clamp is 2 fx tx'/tz^3 (twice the derivative), the
conic inverse uses det^2 + 1e-7, the depth output has no backward, the scale gradient is
with respect to scale_modifier * scales. The per-Gaussian sums run in tile order and, inside
a tile, over pixels in row-major order (upstream adds them with float atomics in no fixed
order).

Kernel order as upstream: renderCUDA (per pixel, back to front), computeCov2DCUDA (2D
covariance -> 3D covariance and mean, assigning the mean gradient), preprocessCUDA
(projection -> mean, then SH -> mean and coefficients, then scale/rotation).
"""

import torch

from reference_raster import BLOCK, SH_C0, SH_C1, SH_C2, SH_C3, quat_to_rot, sh_to_rgb
from reference_raster import tile_pixels, transform_point


def render_backward(st, cam, fwd, grad_color):
    """renderCUDA's backward. Returns, per visible Gaussian: dL/dmean2D [V,2] (NDC units),
    dL/dconic [V,3] (x, half of y, w as upstream stores them), dL/dopacity [V],
    dL/dcolour [V,3]."""
    c = st.c
    dtype = st.dtype
    H, W = st.H, st.W
    V = fwd["vis"].shape[0]
    mx, my = fwd["mx"].detach(), fwd["my"].detach()
    conic = fwd["conic"].detach()
    opac = fwd["opac_v"].detach()
    colour = fwd["colour"].detach()
    final_T = fwd["final_T"].detach()
    n_contrib = fwd["n_contrib"]
    bg = cam.bg
    g_mean2d = torch.zeros(V, 2, dtype=dtype)
    g_conic = torch.zeros(V, 3, dtype=dtype)
    g_opac = torch.zeros(V, dtype=dtype)
    g_colour = torch.zeros(V, 3, dtype=dtype)
    one, zero = c(1.0), c(0.0)
    # ddelx_dx = 0.5 * W in f64, stored as f32 (exact).
    ddelx_dx, ddely_dy = c(0.5 * W), c(0.5 * H)
    gx, gy = (W + BLOCK - 1) // BLOCK, (H + BLOCK - 1) // BLOCK
    for ty_ in range(gy):
        for tx_ in range(gx):
            lst = fwd["tiles"].get(ty_ * gx + tx_, [])
            if not lst:
                continue
            pxf, pyf = tile_pixels(st, ty_, tx_)
            px, py = pxf.to(torch.int64), pyf.to(torch.int64)
            T_final = final_T[py, px]
            T = T_final.clone()
            last_contributor = n_contrib[py, px].to(torch.int64)
            dpix = [grad_color[ch, py, px] for ch in range(3)]
            accum_rec = [torch.zeros_like(T) for _ in range(3)]
            last_alpha = torch.zeros_like(T)
            last_color = [torch.zeros_like(T) for _ in range(3)]
            # bg . dL/dpixel, summed from 0 in channel order.
            bg_dot_dpixel = zero
            for ch in range(3):
                bg_dot_dpixel = bg_dot_dpixel + bg[ch] * dpix[ch]
            # Back to front; `contributor` is the 0-based position in the tile's list.
            for contributor in range(len(lst) - 1, -1, -1):
                j = lst[contributor]
                ok = contributor < last_contributor
                d_x = mx[j] - pxf
                d_y = my[j] - pyf
                A, B, C = conic[j, 0], conic[j, 1], conic[j, 2]
                power = c(-0.5) * (A * d_x * d_x + C * d_y * d_y) - B * d_x * d_y
                ok = ok & ~(power > 0.0)
                G = torch.exp(torch.where(ok, power, zero))
                alpha = torch.minimum(c(0.99), opac[j] * G)
                ok = ok & ~(alpha < c(1.0 / 255.0))
                # Pixels that skip this Gaussian keep their state: all updates are masked.
                T = torch.where(ok, T / (one - alpha), T)
                dchannel_dcolor = alpha * T
                dL_dalpha = zero
                for ch in range(3):
                    col = colour[j, ch]
                    accum_rec[ch] = torch.where(
                        ok, last_alpha * last_color[ch] + (one - last_alpha) * accum_rec[ch],
                        accum_rec[ch])
                    last_color[ch] = torch.where(ok, col, last_color[ch])
                    dL_dalpha = dL_dalpha + (col - accum_rec[ch]) * dpix[ch]
                    g_colour[j, ch] += torch.where(ok, dchannel_dcolor * dpix[ch], zero).sum()
                dL_dalpha = dL_dalpha * T
                last_alpha = torch.where(ok, alpha, last_alpha)
                dL_dalpha = dL_dalpha + (-T_final / (one - alpha)) * bg_dot_dpixel
                dL_dG = opac[j] * dL_dalpha
                gdx = G * d_x
                gdy = G * d_y
                dG_ddelx = -gdx * A - gdy * B
                dG_ddely = -gdy * C - gdx * B
                masked = lambda v: torch.where(ok, v, zero).sum()
                g_mean2d[j, 0] += masked(dL_dG * dG_ddelx * ddelx_dx)
                g_mean2d[j, 1] += masked(dL_dG * dG_ddely * ddely_dy)
                g_conic[j, 0] += masked(c(-0.5) * gdx * d_x * dL_dG)
                g_conic[j, 1] += masked(c(-0.5) * gdx * d_y * dL_dG)
                g_conic[j, 2] += masked(c(-0.5) * gdy * d_y * dL_dG)
                g_opac[j] += masked(G * dL_dalpha)
    return g_mean2d, g_conic, g_opac, g_colour


def cov2d_backward(st, cam, means, cov6, g_conic):
    """computeCov2DCUDA for the visible Gaussians: (dL/dmeans3D [V,3] from the conic,
    dL/dcov3D [V,6])."""
    c = st.c
    view = cam.view
    # vm[4j + i] = view[j, i]; glm W[col][row] = vm[col + 4 row] = view[row, col].
    Wg = [[view[r, col] for r in range(3)] for col in range(3)]
    tx, ty, tz = transform_point(view, means, [0, 1, 2])
    limx, limy = c(1.3) * st.tanfovx, c(1.3) * st.tanfovy
    txtz, tytz = tx / tz, ty / tz
    tx = torch.minimum(limx, torch.maximum(-limx, txtz)) * tz
    ty = torch.minimum(limy, torch.maximum(-limy, tytz)) * tz
    x_grad_mul = torch.where((txtz < -limx) | (txtz > limx), c(0.0), c(1.0))
    y_grad_mul = torch.where((tytz < -limy) | (tytz > limy), c(0.0), c(1.0))
    h_x, h_y = st.fx, st.fy
    # glm J (columns): J[0] = (h_x/tz, 0, -(h_x tx)/tz^2), J[1] = (0, h_y/tz, -(h_y ty)/tz^2).
    J = [[h_x / tz, torch.zeros_like(tz), -(h_x * tx) / (tz * tz)],
         [torch.zeros_like(tz), h_y / tz, -(h_y * ty) / (tz * tz)],
         [torch.zeros_like(tz)] * 3]
    # T = W * J (glm): T[col][row] = sum_k W[k][row] J[col][k].
    T = [[(Wg[0][r] * J[col][0] + Wg[1][r] * J[col][1]) + Wg[2][r] * J[col][2]
          for r in range(3)] for col in range(3)]
    V = [[cov6[:, 0], cov6[:, 1], cov6[:, 2]],
         [cov6[:, 1], cov6[:, 3], cov6[:, 4]],
         [cov6[:, 2], cov6[:, 4], cov6[:, 5]]]
    # cov2D = T^T Vrk^T T (glm): entry [p][q] = T[q] . (Vrk T[p]), the three used.
    def cov2d(p, q):
        return sum_ordered([sum_ordered([T[p][l] * V[k][l] for l in range(3)]) * T[q][k]
                            for k in range(3)])
    a = cov2d(0, 0) + c(0.3)
    b = cov2d(0, 1)
    cc = cov2d(1, 1) + c(0.3)
    gA, gB, gC = g_conic[:, 0], g_conic[:, 1], g_conic[:, 2]
    denom = a * cc - b * b
    denom2inv = c(1.0) / ((denom * denom) + c(0.0000001))
    nz = denom2inv != 0
    zero = torch.zeros_like(a)
    dL_da = torch.where(nz, denom2inv * (-cc * cc * gA + c(2) * b * cc * gB
                                         + (denom - a * cc) * gC), zero)
    dL_dc = torch.where(nz, denom2inv * (-a * a * gC + c(2) * a * b * gB
                                         + (denom - a * cc) * gA), zero)
    dL_db = torch.where(nz, denom2inv * c(2) * (b * cc * gA - (denom + c(2) * b * b) * gB
                                                + a * b * gC), zero)
    two = c(2)
    g_cov = torch.stack([
        T[0][0] * T[0][0] * dL_da + T[0][0] * T[1][0] * dL_db + T[1][0] * T[1][0] * dL_dc,
        two * T[0][0] * T[0][1] * dL_da + (T[0][0] * T[1][1] + T[0][1] * T[1][0]) * dL_db
        + two * T[1][0] * T[1][1] * dL_dc,
        two * T[0][0] * T[0][2] * dL_da + (T[0][0] * T[1][2] + T[0][2] * T[1][0]) * dL_db
        + two * T[1][0] * T[1][2] * dL_dc,
        T[0][1] * T[0][1] * dL_da + T[0][1] * T[1][1] * dL_db + T[1][1] * T[1][1] * dL_dc,
        two * T[0][2] * T[0][1] * dL_da + (T[0][1] * T[1][2] + T[0][2] * T[1][1]) * dL_db
        + two * T[1][1] * T[1][2] * dL_dc,
        T[0][2] * T[0][2] * dL_da + T[0][2] * T[1][2] * dL_db + T[1][2] * T[1][2] * dL_dc,
    ], dim=1)
    g_cov = torch.where(nz[:, None], g_cov, torch.zeros_like(g_cov))
    # dL/dT for the upper 2x3 of T: Vrk[k][m] multiplies T[.][m].
    def row_v(i, k):
        return (T[i][0] * V[k][0] + T[i][1] * V[k][1]) + T[i][2] * V[k][2]
    dL_dT0 = [two * row_v(0, k) * dL_da + row_v(1, k) * dL_db for k in range(3)]
    dL_dT1 = [two * row_v(1, k) * dL_dc + row_v(0, k) * dL_db for k in range(3)]
    # T = W * J: dL/dJ[col][k] = sum_m W[k][m] dL/dT[col][m].
    dL_dJ00 = (Wg[0][0] * dL_dT0[0] + Wg[0][1] * dL_dT0[1]) + Wg[0][2] * dL_dT0[2]
    dL_dJ02 = (Wg[2][0] * dL_dT0[0] + Wg[2][1] * dL_dT0[1]) + Wg[2][2] * dL_dT0[2]
    dL_dJ11 = (Wg[1][0] * dL_dT1[0] + Wg[1][1] * dL_dT1[1]) + Wg[1][2] * dL_dT1[2]
    dL_dJ12 = (Wg[2][0] * dL_dT1[0] + Wg[2][1] * dL_dT1[1]) + Wg[2][2] * dL_dT1[2]
    itz = c(1.0) / tz
    tz2 = itz * itz
    tz3 = tz2 * itz
    dL_dtx = x_grad_mul * -h_x * tz2 * dL_dJ02
    dL_dty = y_grad_mul * -h_y * tz2 * dL_dJ12
    dL_dtz = (-h_x * tz2 * dL_dJ00 - h_y * tz2 * dL_dJ11 + (two * h_x * tx) * tz3 * dL_dJ02
              + (two * h_y * ty) * tz3 * dL_dJ12)
    # transformVec4x3Transpose: row i of the view matrix's memory dotted with dL/dt.
    g_mean = torch.stack([(view[i, 0] * dL_dtx + view[i, 1] * dL_dty) + view[i, 2] * dL_dtz
                          for i in range(3)], dim=1)
    return g_mean, g_cov


def sum_ordered(terms):
    """Left-to-right sum, as the CUDA expressions are written."""
    s = terms[0]
    for t in terms[1:]:
        s = s + t
    return s


def projection_backward(st, cam, means, g_mean2d):
    """preprocessCUDA's mean gradient through ndc = p_hom.xy / (p_hom.w + 1e-7)."""
    c = st.c
    proj = cam.proj.reshape(-1)  # memory layout: proj[4 r + k]
    x, y, z = means[:, 0], means[:, 1], means[:, 2]
    m_w_hom = ((proj[3] * x + proj[7] * y) + proj[11] * z) + proj[15]
    m_w = c(1.0) / (m_w_hom + c(0.0000001))
    mul1 = (((proj[0] * x + proj[4] * y) + proj[8] * z) + proj[12]) * m_w * m_w
    mul2 = (((proj[1] * x + proj[5] * y) + proj[9] * z) + proj[13]) * m_w * m_w
    gx, gy = g_mean2d[:, 0], g_mean2d[:, 1]
    return torch.stack([
        (proj[0] * m_w - proj[3] * mul1) * gx + (proj[1] * m_w - proj[3] * mul2) * gy,
        (proj[4] * m_w - proj[7] * mul1) * gx + (proj[5] * m_w - proj[7] * mul2) * gy,
        (proj[8] * m_w - proj[11] * mul1) * gx + (proj[9] * m_w - proj[11] * mul2) * gy,
    ], dim=1)


def sh_backward(st, cam, means, sh, g_colour):
    """computeColorFromSH's backward: (dL/dmeans3D [V,3] through the view direction,
    dL/dsh [V,M,3] (0 above the active degree))."""
    deg = st.sh_degree
    raw = sh_to_rgb(deg, sh, means, cam.campos, clamp=False)
    dL_dRGB = torch.where(raw < 0, torch.zeros_like(g_colour), g_colour)
    dir_orig = means - cam.campos
    length = torch.sqrt((dir_orig[:, 0] * dir_orig[:, 0] + dir_orig[:, 1] * dir_orig[:, 1])
                        + dir_orig[:, 2] * dir_orig[:, 2])
    d = dir_orig / length[:, None]
    x, y, z = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    g_sh = torch.zeros_like(sh)
    g_sh[:, 0] = SH_C0 * dL_dRGB
    zero = torch.zeros_like(dL_dRGB)
    dRGBdx, dRGBdy, dRGBdz = zero, zero, zero
    if deg > 0:
        g_sh[:, 1] = (-SH_C1 * y) * dL_dRGB
        g_sh[:, 2] = (SH_C1 * z) * dL_dRGB
        g_sh[:, 3] = (-SH_C1 * x) * dL_dRGB
        dRGBdx = -SH_C1 * sh[:, 3]
        dRGBdy = -SH_C1 * sh[:, 1]
        dRGBdz = SH_C1 * sh[:, 2]
        if deg > 1:
            xx, yy, zz = x * x, y * y, z * z
            xy, yz, xz = x * y, y * z, x * z
            g_sh[:, 4] = (SH_C2[0] * xy) * dL_dRGB
            g_sh[:, 5] = (SH_C2[1] * yz) * dL_dRGB
            g_sh[:, 6] = (SH_C2[2] * (2.0 * zz - xx - yy)) * dL_dRGB
            g_sh[:, 7] = (SH_C2[3] * xz) * dL_dRGB
            g_sh[:, 8] = (SH_C2[4] * (xx - yy)) * dL_dRGB
            dRGBdx = dRGBdx + (SH_C2[0] * y * sh[:, 4] + SH_C2[2] * 2.0 * -x * sh[:, 6]
                               + SH_C2[3] * z * sh[:, 7] + SH_C2[4] * 2.0 * x * sh[:, 8])
            dRGBdy = dRGBdy + (SH_C2[0] * x * sh[:, 4] + SH_C2[1] * z * sh[:, 5]
                               + SH_C2[2] * 2.0 * -y * sh[:, 6] + SH_C2[4] * 2.0 * -y * sh[:, 8])
            dRGBdz = dRGBdz + (SH_C2[1] * y * sh[:, 5] + SH_C2[2] * 2.0 * 2.0 * z * sh[:, 6]
                               + SH_C2[3] * x * sh[:, 7])
            if deg > 2:
                g_sh[:, 9] = (SH_C3[0] * y * (3.0 * xx - yy)) * dL_dRGB
                g_sh[:, 10] = (SH_C3[1] * xy * z) * dL_dRGB
                g_sh[:, 11] = (SH_C3[2] * y * (4.0 * zz - xx - yy)) * dL_dRGB
                g_sh[:, 12] = (SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy)) * dL_dRGB
                g_sh[:, 13] = (SH_C3[4] * x * (4.0 * zz - xx - yy)) * dL_dRGB
                g_sh[:, 14] = (SH_C3[5] * z * (xx - yy)) * dL_dRGB
                g_sh[:, 15] = (SH_C3[6] * x * (xx - 3.0 * yy)) * dL_dRGB
                dRGBdx = dRGBdx + (
                    SH_C3[0] * sh[:, 9] * 3.0 * 2.0 * xy
                    + SH_C3[1] * sh[:, 10] * yz
                    + SH_C3[2] * sh[:, 11] * -2.0 * xy
                    + SH_C3[3] * sh[:, 12] * -3.0 * 2.0 * xz
                    + SH_C3[4] * sh[:, 13] * (-3.0 * xx + 4.0 * zz - yy)
                    + SH_C3[5] * sh[:, 14] * 2.0 * xz
                    + SH_C3[6] * sh[:, 15] * 3.0 * (xx - yy))
                dRGBdy = dRGBdy + (
                    SH_C3[0] * sh[:, 9] * 3.0 * (xx - yy)
                    + SH_C3[1] * sh[:, 10] * xz
                    + SH_C3[2] * sh[:, 11] * (-3.0 * yy + 4.0 * zz - xx)
                    + SH_C3[3] * sh[:, 12] * -3.0 * 2.0 * yz
                    + SH_C3[4] * sh[:, 13] * -2.0 * xy
                    + SH_C3[5] * sh[:, 14] * -2.0 * yz
                    + SH_C3[6] * sh[:, 15] * -3.0 * 2.0 * xy)
                dRGBdz = dRGBdz + (
                    SH_C3[1] * sh[:, 10] * xy
                    + SH_C3[2] * sh[:, 11] * 4.0 * 2.0 * yz
                    + SH_C3[3] * sh[:, 12] * 3.0 * (2.0 * zz - xx - yy)
                    + SH_C3[4] * sh[:, 13] * 4.0 * 2.0 * xz
                    + SH_C3[5] * sh[:, 14] * (xx - yy))
    dot = lambda a: (a[:, 0] * dL_dRGB[:, 0] + a[:, 1] * dL_dRGB[:, 1]) + a[:, 2] * dL_dRGB[:, 2]
    dv = [dot(dRGBdx), dot(dRGBdy), dot(dRGBdz)]
    # dnormvdv: the normalisation's Jacobian.
    v = [dir_orig[:, 0], dir_orig[:, 1], dir_orig[:, 2]]
    sum2 = (v[0] * v[0] + v[1] * v[1]) + v[2] * v[2]
    invsum32 = 1.0 / torch.sqrt(sum2 * sum2 * sum2)
    g_mean = torch.stack([
        (((sum2 - v[0] * v[0]) * dv[0] - v[1] * v[0] * dv[1]) - v[2] * v[0] * dv[2]) * invsum32,
        ((-v[0] * v[1] * dv[0] + (sum2 - v[1] * v[1]) * dv[1]) - v[2] * v[1] * dv[2]) * invsum32,
        ((-v[0] * v[2] * dv[0] - v[1] * v[2] * dv[1]) + (sum2 - v[2] * v[2]) * dv[2]) * invsum32,
    ], dim=1)
    return g_mean, g_sh


def cov3d_backward(st, scales, rotations, g_cov):
    """computeCov3D's backward: (dL/dscales [V,3] with respect to scale_modifier * scales,
    dL/drotations [V,4]) of the unnormalised quaternion."""
    c = st.c
    r, x, y, z = rotations[:, 0], rotations[:, 1], rotations[:, 2], rotations[:, 3]
    Rs = quat_to_rot(rotations)  # Rs[i][j]: the standard rotation matrix (math)
    s = scales * st.scale_modifier
    # glm: R = R_std^T, M = S * R, so M(i, j) = s_i R_std(j, i) (math).
    M = [[s[:, i] * Rs[j][i] for j in range(3)] for i in range(3)]
    half = c(0.5)
    G = [[g_cov[:, 0], half * g_cov[:, 1], half * g_cov[:, 2]],
         [half * g_cov[:, 1], g_cov[:, 3], half * g_cov[:, 4]],
         [half * g_cov[:, 2], half * g_cov[:, 4], g_cov[:, 5]]]
    # dL/dM = 2 M dL/dSigma (math).
    dM = [[c(2.0) * ((M[i][0] * G[0][j] + M[i][1] * G[1][j]) + M[i][2] * G[2][j])
           for j in range(3)] for i in range(3)]
    # dL/ds_i = dot(row i of R^T (glm Rt[i]), row i of dL/dM (glm dL_dMt[i])).
    g_s = torch.stack([(Rs[0][i] * dM[i][0] + Rs[1][i] * dM[i][1]) + Rs[2][i] * dM[i][2]
                       for i in range(3)], dim=1)
    # glm dL_dMt[a][b] = dL/dM(a, b) scaled by s_a.
    Mt = [[dM[a][b] * s[:, a] for b in range(3)] for a in range(3)]
    two, four = c(2.0), c(4.0)
    g_q = torch.stack([
        two * z * (Mt[0][1] - Mt[1][0]) + two * y * (Mt[2][0] - Mt[0][2])
        + two * x * (Mt[1][2] - Mt[2][1]),
        two * y * (Mt[1][0] + Mt[0][1]) + two * z * (Mt[2][0] + Mt[0][2])
        + two * r * (Mt[1][2] - Mt[2][1]) - four * x * (Mt[2][2] + Mt[1][1]),
        two * x * (Mt[1][0] + Mt[0][1]) + two * r * (Mt[2][0] - Mt[0][2])
        + two * z * (Mt[1][2] + Mt[2][1]) - four * y * (Mt[2][2] + Mt[0][0]),
        two * r * (Mt[0][1] - Mt[1][0]) + two * x * (Mt[2][0] + Mt[0][2])
        + two * y * (Mt[1][2] + Mt[2][1]) - four * z * (Mt[1][1] + Mt[0][0]),
    ], dim=1)
    return g_s, g_q


def backward(st, cam, inputs, fwd, grad_color):
    """Every input gradient of the rasterizer in the `inria` mode, for the loss
    sum(color * grad_color). `inputs` holds the forward's inputs (means, opac, shs or
    colors_precomp, scales + rotations or cov3D_precomp). Returns a dict keyed like
    `inputs`, plus `means2D` [N,3] (NDC units, third column 0); culled Gaussians get 0."""
    with torch.no_grad():
        vis = fwd["vis"]
        means = inputs["means"].detach()
        N = means.shape[0]
        mv = means[vis]
        g_mean2d, g_conic, g_opac, g_colour = render_backward(st, cam, fwd, grad_color)
        g_mean, g_cov = cov2d_backward(st, cam, mv, fwd["cov6"].detach(), g_conic)
        g_mean = g_mean + projection_backward(st, cam, mv, g_mean2d)
        out = {}
        if "shs" in inputs:
            sh = inputs["shs"].detach()
            g_mean_sh, g_sh = sh_backward(st, cam, mv, sh[vis], g_colour)
            g_mean = g_mean + g_mean_sh
            out["shs"] = torch.zeros_like(sh)
            out["shs"][vis] = g_sh
        else:
            out["colors_precomp"] = torch.zeros_like(inputs["colors_precomp"])
            out["colors_precomp"][vis] = g_colour
        if "cov3D_precomp" in inputs:
            out["cov3D_precomp"] = torch.zeros_like(inputs["cov3D_precomp"])
            out["cov3D_precomp"][vis] = g_cov
        else:
            g_s, g_q = cov3d_backward(st, inputs["scales"][vis].detach(),
                                      inputs["rotations"][vis].detach(), g_cov)
            out["scales"] = torch.zeros_like(inputs["scales"])
            out["scales"][vis] = g_s
            out["rotations"] = torch.zeros_like(inputs["rotations"])
            out["rotations"][vis] = g_q
        out["means"] = torch.zeros_like(means)
        out["means"][vis] = g_mean
        out["opac"] = torch.zeros_like(inputs["opac"])
        out["opac"][vis, 0] = g_opac
        g2 = torch.zeros(N, 3, dtype=st.dtype)
        g2[vis, :2] = g_mean2d
        out["means2D"] = g2
    return out
