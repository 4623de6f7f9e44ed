"""liquid_splat.torch: autograd wrappers, drop-in rasterizer and field modules.
Skipped when torch is not installed."""

import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")

import liquid_splat as ls  # noqa: E402
from liquid_splat import torch as lt  # noqa: E402
from conftest import CASES, ROOT, bits_equal, weights  # noqa: E402


def tensors(name):
    t, m = ls.load(CASES / f"{name}.input.safetensors")
    e, _ = ls.load(CASES / f"{name}.expected.safetensors")
    return {k: torch.from_numpy(v) for k, v in t.items()}, m, e


def settings(T, m, sh_degree=None):
    return lt.GaussianRasterizationSettings(
        image_height=int(m["image_height"]), image_width=int(m["image_width"]),
        tanfovx=float(m["tanfovx"]), tanfovy=float(m["tanfovy"]), bg=T["bg"],
        scale_modifier=float(m["scale_modifier"]), viewmatrix=T["viewmatrix"],
        projmatrix=T["projmatrix"], sh_degree=int(m["sh_degree"]) if sh_degree is None else sh_degree,
        campos=T["campos"], prefiltered=False, debug=False)


@pytest.mark.parametrize("dtype", ["f32", "f64"])
def test_rasterizer_is_the_golden_case(dtype):
    T, m, e = tensors(f"rasterize_{dtype}_exact")
    raster = lt.GaussianRasterizer(settings(T, m))
    leaves = {k: T[k].clone().requires_grad_() for k in ("means3D", "opacities", "shs", "scales", "rotations")}
    means2D = torch.zeros_like(T["means3D"], requires_grad=True)
    color, radii, depth = raster(leaves["means3D"], means2D, leaves["opacities"], shs=leaves["shs"],
                                 scales=leaves["scales"], rotations=leaves["rotations"])
    bits_equal({"color": color.detach().numpy(), "radii": radii.numpy(), "depth": depth.detach().numpy()},
               {k: e[k] for k in ("color", "radii", "depth")})
    ((color * T["grad_out_color"]).sum() + (depth * T["grad_out_depth"]).sum()).backward()
    got = {f"grad_{k}": v.grad.numpy() for k, v in leaves.items()}
    got["grad_means2D"] = means2D.grad.numpy()
    bits_equal(got, {k: v for k, v in e.items() if k.startswith("grad_")})
    vis = raster.markVisible(T["means3D"])
    assert vis.dtype == torch.bool and bool(vis[radii > 0].all())


def test_rasterizer_gradcheck_float64():
    T, m, _ = tensors("rasterize_f64_exact")
    st = settings(T, m, sh_degree=1)
    shs = T["shs"][:, :4].contiguous()          # degree 1: fewer coefficients to perturb
    raster = lt.GaussianRasterizer(st)
    color, radii, depth = raster(T["means3D"], None, T["opacities"], shs=shs, scales=T["scales"],
                                 rotations=T["rotations"])
    # Non-empty: most Gaussians visible, the image is not just the background, depth > 0.
    assert int((radii > 0).sum()) >= 5
    assert float((color - T["bg"][:, None, None]).abs().max()) > 0.1 and float(depth.max()) > 0

    def render(means3D, opacities, shs, scales, rotations):
        c, _, d = raster(means3D, None, opacities, shs=shs, scales=scales, rotations=rotations)
        return c, d

    args = tuple(x.clone().requires_grad_() for x in
                 (T["means3D"], T["opacities"], shs, T["scales"], T["rotations"]))
    assert torch.autograd.gradcheck(render, args)

    # Precomputed colours and covariances.
    q = torch.nn.functional.normalize(T["rotations"], dim=1)
    w, x, y, z = q.unbind(1)
    R = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                     2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                     2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], 1).view(-1, 3, 3)
    M = R * T["scales"][:, None, :]
    S = M @ M.transpose(1, 2)
    cov = torch.stack([S[:, 0, 0], S[:, 0, 1], S[:, 0, 2], S[:, 1, 1], S[:, 1, 2], S[:, 2, 2]], 1)
    colors = torch.rand(T["means3D"].shape[0], 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))

    def render2(opacities, colors_precomp, cov3D_precomp):
        c, _, d = raster(T["means3D"], None, opacities, colors_precomp=colors_precomp,
                         cov3D_precomp=cov3D_precomp)
        return c, d

    args = tuple(v.clone().requires_grad_() for v in (T["opacities"], colors, cov))
    assert torch.autograd.gradcheck(render2, args)


def test_rasterizer_rejects_bad_arguments():
    T, m, _ = tensors("rasterize_f64_exact")
    raster = lt.GaussianRasterizer(settings(T, m))
    with pytest.raises(ValueError, match="exactly one of either SHs or precomputed colors"):
        raster(T["means3D"], None, T["opacities"], scales=T["scales"], rotations=T["rotations"])
    with pytest.raises(TypeError, match=r"`opacities`: expected dtype float64 \(the dtype of `means3D`\)"):
        raster(T["means3D"], None, T["opacities"].float(), shs=T["shs"], scales=T["scales"],
               rotations=T["rotations"])
    if torch.cuda.is_available():
        with pytest.raises(ValueError, match="CPU tensor"):
            raster(T["means3D"].cuda(), None, T["opacities"], shs=T["shs"], scales=T["scales"],
                   rotations=T["rotations"])


@pytest.mark.parametrize("name", ["deform_f64_mlp", "deform_f32_cfc", "deform_f32_mlp", "deform_f64_cfc"])
def test_field_modules_are_the_golden_case(name, tmp_path):
    T, m, e = tensors(name)
    sd = weights(T)
    cls = lt.CfCField if m["field"] == "cfc" else lt.DeformNetwork
    dtype = T["xyz"].dtype
    if cls is lt.DeformNetwork:
        net = lt.DeformNetwork(D=int(m["depth"]), W=int(m["width"]), is_blender=True, dtype=dtype)
    else:
        net = lt.CfCField(D=int(m["depth"]), W=int(m["width"]), activation=m["activation"],
                          backbone_units=int(m["backbone_units"]), dtype=dtype)
    torch.save(sd, tmp_path / "deform.pth")
    net.load_state_dict(torch.load(tmp_path / "deform.pth"))   # strict: upstream's keys
    assert sorted(net.state_dict()) == sorted(sd)
    t = T["t"].clone().requires_grad_()
    d_xyz, d_rot, d_scale = net(T["xyz"], t)
    bits_equal({"d_xyz": d_xyz.detach().numpy(), "d_rotation": d_rot.detach().numpy(),
                "d_scaling": d_scale.detach().numpy()}, {k: e[k] for k in ("d_xyz", "d_rotation", "d_scaling")})
    L = (d_xyz * T["grad_d_xyz"]).sum() + (d_rot * T["grad_d_rotation"]).sum() + (d_scale * T["grad_d_scaling"]).sum()
    names, params = zip(*net.named_parameters())
    grads = torch.autograd.grad(L, (t, *params))
    got = {"grad_t": grads[0].numpy(), **{f"grad.{n}": g.numpy() for n, g in zip(names, grads[1:])}}
    bits_equal(got, {k: v for k, v in e.items() if k.startswith("grad")})
    assert net.param_count == sum(v.numel() for v in sd.values())
    again = cls.from_state_dict(sd, **({"activation": m["activation"]} if cls is lt.CfCField else {}))
    assert torch.equal(again(T["xyz"], T["t"])[0], d_xyz)


def _gradcheck_field(net, n=4, with_xyz=False):
    g = torch.Generator().manual_seed(3)
    x = torch.randn(n, 3, dtype=torch.float64, generator=g)
    t = torch.rand(n, 1, dtype=torch.float64, generator=g).requires_grad_()
    names, params = zip(*net.named_parameters())
    some = [p for nme, p in zip(names, params) if nme.endswith("bias")][:3] + [params[0]]

    def f(t, *ws):
        return net(x, t)

    assert torch.autograd.gradcheck(f, (t, *some))


def test_field_gradcheck_float64():
    _gradcheck_field(lt.DeformNetwork(D=4, W=16, is_blender=True, dtype=torch.float64))
    _gradcheck_field(lt.DeformNetwork(D=4, W=16, is_6dof=True, dtype=torch.float64))
    _gradcheck_field(lt.CfCField(D=2, W=8, backbone_units=8, dtype=torch.float64))
    _gradcheck_field(lt.CfCField(D=2, W=8, variant="real", activation="tanh", backbone_units=8,
                                 dtype=torch.float64))


def test_6dof_gradient_reaches_xyz_through_the_warp():
    net = lt.DeformNetwork(D=4, W=16, is_6dof=True, dtype=torch.float64, seed=5)
    g = torch.Generator().manual_seed(4)
    x = torch.randn(6, 3, dtype=torch.float64, generator=g).requires_grad_()
    t = torch.rand(6, 1, dtype=torch.float64, generator=g)
    d_xyz, _, _ = net(x, t)
    T = net.transform(x, t)
    R, p = T[:, :3, :3], T[:, :3, 3]
    torch.testing.assert_close(d_xyz, (R @ x.detach()[:, :, None])[:, :, 0] + p - x.detach())
    cot = torch.randn(6, 3, dtype=torch.float64, generator=g)
    (gx,) = torch.autograd.grad((x + d_xyz).mul(cot).sum(), x)
    torch.testing.assert_close(gx, (R.transpose(1, 2) @ cot[:, :, None])[:, :, 0])


def test_mlp_matches_the_independent_reference():
    sys.path.insert(0, str(ROOT / "python"))
    try:
        import reference_deform
    finally:
        sys.path.pop(0)
    T, m, _ = tensors("deform_f64_mlp")
    sd = weights(T)
    ref = reference_deform.DeformNetwork(D=int(m["depth"]), W=int(m["width"]), variant="synthetic").double()
    ref.load_state_dict(sd)
    net = lt.DeformNetwork.from_state_dict(sd)
    for a, b in zip(net(T["xyz"], T["t"]), ref(T["xyz"], T["t"])):
        torch.testing.assert_close(a, b, atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("dtype", ["f32", "f64"])
def test_loss_is_the_golden_case(dtype):
    T, m, e = tensors(f"loss_{dtype}")
    image = T["image"].clone().requires_grad_()
    L = lt.loss(image, T["gt"], float(m["lambda_dssim"]))
    (g,) = torch.autograd.grad(L, image)
    bits_equal({"loss": L.detach().numpy(), "grad_image": g.numpy()},
               {k: e[k] for k in ("loss", "grad_image")})


def test_loss_gradcheck_float64():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(3, 10, 12, dtype=torch.float64, generator=g)
    image = (gt + 0.2 * torch.randn(3, 10, 12, dtype=torch.float64, generator=g)).requires_grad_()
    assert torch.autograd.gradcheck(lambda im: lt.loss(im, gt) * 3.0, (image,))


def _gaussians(T, n=None, requires_grad=False):
    keys = ("means3D", "opacities", "shs", "scales", "rotations")
    return {k: T[k][:n].clone().requires_grad_(requires_grad) for k in keys}


def test_rasterizer_renders_the_background_without_gaussians():
    T, m, _ = tensors("rasterize_f64_exact")
    raster = lt.GaussianRasterizer(settings(T, m))
    g = _gaussians(T, 0, requires_grad=True)          # N = 0: shs of shape [0,16,3]
    means2D = torch.zeros_like(g["means3D"], requires_grad=True)
    color, radii, depth = raster(g["means3D"], means2D, g["opacities"], shs=g["shs"],
                                 scales=g["scales"], rotations=g["rotations"])
    assert radii.shape == (0,) and float(depth.detach().abs().max()) == 0.0
    assert torch.equal(color, T["bg"][:, None, None].expand(3, 24, 32))
    color.sum().backward()
    assert g["means3D"].grad.shape == (0, 3) and g["shs"].grad.shape == (0, 16, 3)
    # Inria's "absent" is None or the 1-D empty tensor, as before.
    c2, _, _ = lt.rasterize_gaussians(g["means3D"], means2D, g["shs"], torch.Tensor([]),
                                      g["opacities"], g["scales"], g["rotations"],
                                      torch.Tensor([]), settings(T, m))
    assert torch.equal(c2, color)


def test_inplace_change_of_a_saved_input_fails_the_backward():
    T, m, _ = tensors("rasterize_f64_exact")
    inplace = "modified by an inplace operation"

    def render(st):
        g = _gaussians(T, requires_grad=True)
        color, _, _ = lt.GaussianRasterizer(st)(g["means3D"], None, g["opacities"], shs=g["shs"],
                                                scales=g["scales"], rotations=g["rotations"])
        return g, color

    g, color = render(settings(T, m))
    with torch.no_grad():
        g["scales"].mul_(2.0)
    with pytest.raises(RuntimeError, match=f"GaussianRasterizer: backward: scales changed.*{inplace}"):
        color.sum().backward()
    # The settings' tensors too (a camera moved between forward and backward).
    st = settings({**T, "viewmatrix": T["viewmatrix"].clone()}, m)
    g, color = render(st)
    st.viewmatrix[3, 2] += 0.5
    with pytest.raises(RuntimeError, match=f": raster_settings.viewmatrix changed.*{inplace}"):
        color.sum().backward()
    # Fields: a weight or the time changed in place.
    net = lt.DeformNetwork(D=4, W=16, is_blender=True, dtype=torch.float64)
    x = torch.rand(5, 3, dtype=torch.float64)
    t = torch.rand(5, 1, dtype=torch.float64, requires_grad=True)
    d_xyz, _, _ = net(x, t)
    with torch.no_grad():
        net.get_parameter("linear.0.weight").add_(1.0)
    with pytest.raises(RuntimeError, match=f"DeformNetwork: backward: linear.0.weight changed.*{inplace}"):
        d_xyz.sum().backward()
    # A second backward through a freed graph after an optimizer step is torch's own error,
    # not blamed on the parameters the step changed.
    d_xyz, _, _ = net(x, t)
    d_xyz.sum().backward()
    torch.optim.SGD(net.parameters(), lr=0.1).step()
    with pytest.raises(RuntimeError) as err:
        d_xyz.sum().backward()
    assert "changed in place" not in str(err.value), str(err.value)
    # gsplat: the camera matrices are read again by the backward.
    t2, _ = ls.load(CASES / "gsplat_rasterization_f64_v16.input.safetensors")
    x = {k: torch.from_numpy(t2[k].copy()).requires_grad_() for k in
         ("means", "quats", "scales", "opacities", "colors")}
    viewmats = torch.from_numpy(t2["viewmats"].copy())
    rc, _, _ = lt.rasterization(x["means"], x["quats"], x["scales"], x["opacities"], x["colors"],
                                viewmats, torch.from_numpy(t2["Ks"]), 24, 16, sh_degree=3)
    viewmats[:, 0, 3] += 0.1
    with pytest.raises(RuntimeError, match=f"rasterization: backward: viewmats changed.*{inplace}"):
        rc.sum().backward()
    t3, _ = ls.load(CASES / "gsplat_rasterize_to_pixels_f64_v16_gsplat.input.safetensors")
    d = {k: torch.from_numpy(t3[k].copy()).requires_grad_() for k in
         ("means2d", "conics", "colors", "opacities")}
    rc, _ = lt.rasterize_to_pixels(*d.values(), 24, 16, 16, torch.from_numpy(t3["isect_offsets"]),
                                   torch.from_numpy(t3["flatten_ids"]), packed=True)
    with torch.no_grad():
        d["conics"].mul_(0.5)
    with pytest.raises(RuntimeError, match=f"rasterize_to_pixels: backward: conics changed.*{inplace}"):
        rc.sum().backward()


def test_inference_mode_tensors_are_taken():
    """Tensors made under ``torch.inference_mode`` (deform, then render, as an evaluation
    loop does) give the outputs of the same call under ``no_grad``."""
    T, m, _ = tensors("rasterize_f64_exact")
    net = lt.DeformNetwork(D=4, W=16, is_blender=True, dtype=torch.float64)
    x = torch.rand(5, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    t2, _ = ls.load(CASES / "gsplat_rasterization_f64_v16.input.safetensors")
    t3, _ = ls.load(CASES / "gsplat_rasterize_to_pixels_f64_v16_gsplat.input.safetensors")

    def run():
        t = torch.full((5, 1), 0.25, dtype=torch.float64)
        d_xyz, _, _ = net(x, t)
        d2, _, _ = net(x + d_xyz, t)              # a field's input made in the same mode
        g = {k: v.clone() for k, v in _gaussians(T).items()}
        g["means3D"] = g["means3D"] + 0.0         # made in the mode
        color, _, _ = lt.GaussianRasterizer(settings(T, m))(g["means3D"], None, g["opacities"], shs=g["shs"],
                                                            scales=g["scales"], rotations=g["rotations"])
        a = {k: torch.from_numpy(t2[k]) + 0 for k in ("means", "quats", "scales", "opacities", "colors",
                                                      "viewmats", "Ks")}
        rc, _, _ = lt.rasterization(a["means"], a["quats"], a["scales"], a["opacities"], a["colors"],
                                    a["viewmats"], a["Ks"], 24, 16, sh_degree=3)
        b = {k: torch.from_numpy(t3[k]) + 0 for k in ("means2d", "conics", "colors", "opacities")}
        rp, _ = lt.rasterize_to_pixels(*b.values(), 24, 16, 16, torch.from_numpy(t3["isect_offsets"]),
                                       torch.from_numpy(t3["flatten_ids"]), packed=True)
        return [d2, color, rc, rp]

    with torch.inference_mode():
        got = run()
    assert all(v.is_inference() for v in got)
    with torch.no_grad():
        want = run()
    for a, b in zip(got, want):
        assert torch.equal(a, b)


def test_raster_settings_numbers_are_checked_not_coerced():
    T, m, e = tensors("rasterize_f64_exact")
    g = _gaussians(T)

    def render(**change):
        st = settings(T, m)._replace(**change)
        return lt.GaussianRasterizer(st)(g["means3D"], None, g["opacities"], shs=g["shs"],
                                         scales=g["scales"], rotations=g["rotations"])

    for name, value, found in (("image_height", 24.9, "float"), ("image_height", "24", "str"),
                               ("image_width", True, "bool"), ("sh_degree", 2.7, "float"),
                               ("image_height", torch.tensor(24.0), "float"),
                               ("tanfovx", "0.4", "str"), ("scale_modifier", True, "bool")):
        kind = "an int" if name in ("image_height", "image_width", "sh_degree") else "a float"
        with pytest.raises(TypeError, match=rf"argument `raster_settings.{name}`: expected {kind}, found {found}"):
            render(**{name: value})
    with pytest.raises(ValueError, match="`image_width`: expected an integer in 1..=67108864, found 0"):
        render(image_width=0)
    # numpy scalars and 0-d tensors holding such values are the numbers they hold.
    color, _, _ = render(image_height=np.int64(24), image_width=torch.tensor(32),
                         tanfovx=np.float64(float(m["tanfovx"])), sh_degree=torch.tensor(3))
    assert color.numpy().tobytes() == e["color"].tobytes()


def test_means2D_is_checked():
    T, m, _ = tensors("rasterize_f64_exact")
    g = _gaussians(T)
    raster = lt.GaussianRasterizer(settings(T, m))

    def render(means2D):
        return raster(g["means3D"], means2D, g["opacities"], shs=g["shs"], scales=g["scales"],
                      rotations=g["rotations"])

    with pytest.raises(ValueError, match=r"`means2D`: expected shape \[N,3\] with N=9 from `means3D` \(Inria's screenspace points\), found shape \[9,2\]"):
        render(torch.zeros(9, 2, dtype=torch.float64, requires_grad=True))
    with pytest.raises(ValueError, match=r"`means2D`: expected shape \[N,3\] with N=9 .*found shape \[4,3\]"):
        render(torch.zeros(4, 3, dtype=torch.float64))
    for bad in (np.zeros((9, 3)), "means2D"):
        with pytest.raises(TypeError, match=r"`means2D`: expected a torch.Tensor of shape \[N,3\] .*or None, found"):
            render(bad)


def test_unsupported_dtypes_and_field_arguments_are_named():
    T, m, _ = tensors("rasterize_f64_exact")
    g = _gaussians(T)
    raster = lt.GaussianRasterizer(settings(T, m))
    with pytest.raises(TypeError, match=r"argument `opacities`: expected dtype torch.float32 or torch.float64, found torch.bfloat16"):
        raster(g["means3D"], None, g["opacities"].bfloat16(), shs=g["shs"], scales=g["scales"],
               rotations=g["rotations"])
    with pytest.raises(TypeError, match=r"argument `[a-z_.0-9]+`: expected dtype torch.float32 or torch.float64, found torch.bfloat16"):
        lt.DeformNetwork.from_state_dict({k: v.bfloat16() for k, v in lt.DeformNetwork(D=4, W=8).state_dict().items()})
    with pytest.raises(ValueError, match=r"DeformNetwork\(\): argument `D`: expected an integer >= 3, found -1"):
        lt.DeformNetwork(D=-1)
    with pytest.raises(TypeError, match=r"DeformNetwork\(\): argument `D`: expected an int, found str"):
        lt.DeformNetwork(D="4")
    with pytest.raises(TypeError, match=r"CfCField\(\): argument `backbone_units`: expected an int, found float"):
        lt.CfCField(backbone_units=8.0)
    with pytest.raises(ValueError, match=r"CfCField\(\): argument `seed`: expected an integer in 0..=18446744073709551615, found -1"):
        lt.CfCField(D=1, W=4, seed=-1)


def test_loss_weight_is_checked_as_in_numpy():
    """lambda_dssim went through float(): True and "0.5" were accepted, 10**400 was an
    OverflowError; now the numpy loss's checks apply, naming the argument."""
    T, m, _ = tensors("loss_f64")
    for bad, exc in ((True, TypeError), ("0.5", TypeError), (10**400, ValueError), (1.5, ValueError)):
        with pytest.raises(exc, match=r"loss\(\): argument `lambda_dssim`"):
            lt.loss(T["image"], T["gt"], bad)
    want = lt.loss(T["image"], T["gt"], 0.5)
    for ok in (np.float32(0.5), torch.tensor(0.5), np.array(0.5)):
        assert lt.loss(T["image"], T["gt"], ok).item() == want.item()


def test_from_state_dict_takes_a_dict():
    with pytest.raises(TypeError, match=r"CfCField.from_state_dict\(\): argument `state_dict`: expected a dict, found list"):
        lt.CfCField.from_state_dict([("skip.weight", torch.zeros(1))])


def test_testing_takes_torch_numbers_and_names_unreadable_tensors():
    from liquid_splat.testing import compare, recommended_tolerances
    assert recommended_tolerances(torch.float64) == recommended_tolerances("float64")
    e = {"x": torch.tensor([1.0, 2.0], dtype=torch.float64)}
    a = {"x": torch.tensor([1.0, 2.0 + 1e-6], dtype=torch.float64)}
    assert compare(e, a, atol=torch.tensor(1e-5)).passed
    with pytest.raises(TypeError, match=r"compare\(\): actual\['x'\]: expected an array, found Tensor"):
        compare(e, {"x": torch.zeros(2, dtype=torch.bfloat16)})
