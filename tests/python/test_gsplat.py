"""liquid_splat.gsplat: every gsplat golden fixture bit for bit through the gsplat-named
functions; dense and packed layouts agree; bad arguments are named; the torch wrappers pass
torch.autograd.gradcheck in float64 (skipped without torch)."""

import numpy as np
import pytest

import liquid_splat as ls
from conftest import CASES, GOLDEN, bits_equal
from liquid_splat import gsplat as gs

GSPLAT = [n for n in GOLDEN if n.startswith("gsplat_")]


def _b(s: str) -> bool:
    return {"true": True, "false": False}[s]


def _words(ids: np.ndarray) -> np.ndarray:
    """int64 isect_ids as the case file's [n, 2] int32 words (high, low)."""
    return np.stack([(ids >> 32).astype(np.int32), (ids & 0xFFFFFFFF).astype(np.uint32).view(np.int32)], 1)


def _through_functions(t: dict, m: dict) -> dict:
    """A gsplat case's outputs computed by the gsplat-named functions, under the case's names."""
    opt = dict(version=m["version"], gradient=m["gradient"])
    stage = m["stage"]
    if stage == "gsplat_quat_scale_to_covar_preci":
        args = (t["quats"], t["scales"], _b(m["compute_covar"]), _b(m["compute_preci"]), _b(m["triu"]))
        covars, precis = gs.quat_scale_to_covar_preci(*args, **opt)
        out = {"covars": covars, "precis": precis}
        out.update(gs.quat_scale_to_covar_preci_vjp(*args, v_covars=t["v_covars"], v_precis=t["v_precis"], **opt))
        return out
    if stage == "gsplat_spherical_harmonics":
        args = (int(m["degrees_to_use"]), t["dirs"], t["coeffs"])
        out = {"colors": gs.spherical_harmonics(*args, **opt)}
        out.update(gs.spherical_harmonics_vjp(*args, v_colors=t["v_colors"], **opt))
        return out
    if stage == "gsplat_fully_fused_projection":
        packed = _b(m["packed"])
        args = (t["means"], None, t["quats"], t["scales"], t["viewmats"], t["Ks"], int(m["width"]), int(m["height"]))
        kw = dict(packed=packed, calc_compensations=_b(m["calc_compensations"]), opacities=t["opacities"], **opt)
        r = gs.fully_fused_projection(*args, **kw)
        names = ("camera_ids", "gaussian_ids") if packed else ()
        names += ("radii", "means2d", "depths", "conics", "compensations")
        out = dict(zip(names, r))
        for k in names[:2 if packed else 0]:  # int64 as in gsplat; I32 in case files
            assert out[k].dtype == np.int64
            out[k] = out[k].astype(np.int32)
        cot = {k: t[k] for k in ("v_means2d", "v_depths", "v_conics", "v_compensations")}
        out.update(gs.fully_fused_projection_vjp(*args, **kw, **cot))
        return out
    if stage == "gsplat_isect_tiles":
        n_images, tw, th = int(m["n_images"]), int(m["tile_width"]), int(m["tile_height"])
        tpg, ids, flat = gs.isect_tiles(
            t["means2d"], t["radii"], t["depths"], int(m["tile_size"]), tw, th, packed=True,
            n_images=n_images, image_ids=t["image_ids"], conics=t["conics"], opacities=t["opacities"], **opt)
        assert ids.dtype == np.int64
        offsets = gs.isect_offset_encode(ids, n_images, tw, th, version=m["version"])
        return {"tiles_per_gauss": tpg, "isect_ids": _words(ids), "flatten_ids": flat, "isect_offsets": offsets}
    if stage == "gsplat_rasterize_to_pixels":
        args = (t["means2d"], t["conics"], t["colors"], t["opacities"], int(m["image_width"]),
                int(m["image_height"]), int(m["tile_size"]), t["isect_offsets"], t["flatten_ids"], t["backgrounds"])
        rc, ra = gs.rasterize_to_pixels(*args, packed=True, **opt)
        out = {"render_colors": rc, "render_alphas": ra}
        out.update(gs.rasterize_to_pixels_vjp(*args, packed=True, v_render_colors=t["v_render_colors"],
                                              v_render_alphas=t["v_render_alphas"], **opt))
        return out
    if stage == "gsplat_rasterization":
        args = (t["means"], t["quats"], t["scales"], t["opacities"], t["colors"], t["viewmats"], t["Ks"],
                int(m["width"]), int(m["height"]))
        kw = dict(sh_degree=int(m["sh_degree"]), packed=_b(m["packed"]), backgrounds=t["backgrounds"],
                  rasterize_mode=m["rasterize_mode"], **opt)
        rc, ra, meta = gs.rasterization(*args, **kw)
        assert meta["n_cameras"] == 2 and (meta["tile_width"], meta["tile_height"]) == (2, 1)
        out = {"render_colors": rc, "render_alphas": ra}
        for k, v in meta.items():
            if k in ("camera_ids", "gaussian_ids"):  # int64 as in gsplat
                assert v.dtype == np.int64
                v = v.astype(np.int32)
            if isinstance(v, np.ndarray):
                out[f"meta.{k}"] = _words(v) if k == "isect_ids" else v
        out.update(gs.rasterization_vjp(*args, **kw, v_render_colors=t["v_render_colors"],
                                        v_render_alphas=t["v_render_alphas"]))
        return out
    raise AssertionError(f"no function for stage {stage}")


@pytest.mark.parametrize("name", GSPLAT)
def test_golden_fixture_through_the_gsplat_functions(name):
    t, m = ls.load(CASES / f"{name}.input.safetensors")
    e, _ = ls.load(CASES / f"{name}.expected.safetensors")
    out = {k: v for k, v in _through_functions(t, m).items() if v is not None}
    if m["stage"] == "gsplat_rasterize_to_pixels":
        del e["last_ids"]  # internal to gsplat's kernels: its rasterize_to_pixels returns two tensors
    bits_equal(out, e)


def test_every_gsplat_stage_has_a_fixture_here():
    stages = {ls.load(CASES / f"{n}.input.safetensors")[1]["stage"] for n in GSPLAT}
    assert stages == {s for s in ls.STAGES if s.startswith("gsplat_")}


def _projection_case():
    t, m = ls.load(CASES / "gsplat_fully_fused_projection_f64_v16_aa_gsplat.input.safetensors")
    args = (t["means"], None, t["quats"], t["scales"], t["viewmats"], t["Ks"], int(m["width"]), int(m["height"]))
    return t, args


def test_dense_and_packed_layouts_agree():
    t, args = _projection_case()
    kw = dict(opacities=t["opacities"], calc_compensations=True, near_plane=4.0, version="1.6")
    radii, means2d, depths, conics, comp = gs.fully_fused_projection(*args, packed=False, **kw)
    cam, gid, p_radii, p_means2d, p_depths, p_conics, p_comp = gs.fully_fused_projection(*args, packed=True, **kw)
    vis = (radii > 0).all(-1)
    assert 0 < vis.sum() < vis.size  # some entries culled: the packing is exercised
    c, n = np.nonzero(vis)
    np.testing.assert_array_equal(cam, c)
    np.testing.assert_array_equal(gid, n)
    for dense, packed in ((radii, p_radii), (means2d, p_means2d), (depths, p_depths), (conics, p_conics), (comp, p_comp)):
        assert dense[c, n].tobytes() == packed.tobytes()
    # Tiles: the dense rows (culled ones have no tile) give the same keys; flatten_ids name
    # dense rows c·N + n instead of packed rows.
    w, h, ts = int(args[6]), int(args[7]), 16
    tw, th = -(-w // ts), -(-h // ts)
    op = np.broadcast_to(t["opacities"], depths.shape).copy()
    d_tpg, d_ids, d_flat = gs.isect_tiles(means2d, radii, depths, ts, tw, th, conics=conics, opacities=op)
    p_tpg, p_ids, p_flat = gs.isect_tiles(p_means2d, p_radii, p_depths, ts, tw, th, packed=True, n_images=2,
                                          image_ids=cam, gaussian_ids=gid, conics=p_conics,
                                          opacities=t["opacities"][gid].copy())
    assert p_ids.size > 0
    np.testing.assert_array_equal(d_ids, p_ids)
    np.testing.assert_array_equal(d_tpg[c, n], p_tpg)
    np.testing.assert_array_equal(d_flat, (cam * t["means"].shape[0] + gid)[p_flat])
    # The same pixels from either layout.
    rng = np.random.default_rng(5)
    colors = rng.random((2, t["means"].shape[0], 4))
    d_off = gs.isect_offset_encode(d_ids, 2, tw, th)
    dense_px = gs.rasterize_to_pixels(means2d, conics, colors, op, w, h, ts, d_off, d_flat)
    packed_px = gs.rasterize_to_pixels(p_means2d, p_conics, colors[c, n], op[c, n], w, h, ts, d_off, p_flat,
                                       packed=True)
    for a, b in zip(dense_px, packed_px):
        assert a.tobytes() == b.tobytes()
    assert dense_px[1].max() > 0.1


def test_forward_functions_run_their_stage_once_without_cotangents(monkeypatch):
    t, args = _projection_case()
    calls = []
    native_run = ls._native.run_case

    def counting(tensors, meta, threads=None):
        calls.append((meta["stage"], meta.get("packed"), sorted(tensors)))
        return native_run(tensors, meta, threads)

    monkeypatch.setattr(ls._native, "run_case", counting)
    kw = dict(opacities=t["opacities"], calc_compensations=True, near_plane=4.0)
    for packed in (False, True):
        calls.clear()
        r = gs.fully_fused_projection(*args, packed=packed, **kw)
        assert len(calls) == 1, calls
        stage, flag, names = calls[0]
        assert (stage, flag) == ("gsplat_fully_fused_projection", "true" if packed else "false")
        assert not [n for n in names if n.startswith("v_")], names
        # The same outputs as a run of the stage given zero cotangents of the output layout.
        lead = (r[2] if packed else r[0]).shape[:-1]  # of radii [..., 2]
        zeros = {"v_means2d": np.zeros(lead + (2,)), "v_depths": np.zeros(lead),
                 "v_conics": np.zeros(lead + (3,)), "v_compensations": np.zeros(lead)}
        case = {k: v for k, v in t.items() if not k.startswith("v_")}
        meta = {"stage": "gsplat_fully_fused_projection", "width": int(args[6]),
                "height": int(args[7]), "near_plane": 4.0, "calc_compensations": True,
                "packed": packed}
        want, _ = native_run({**case, **zeros}, meta)
        names = ("camera_ids", "gaussian_ids") if packed else ()
        names += ("radii", "means2d", "depths", "conics", "compensations")
        for name, got in zip(names, r):
            if name in ("camera_ids", "gaussian_ids"):  # int64 as in gsplat
                assert got.dtype == np.int64
                got = got.astype(want[name].dtype)
            assert got.tobytes() == want[name].tobytes(), name
        for name in ("v_means", "v_quats", "v_scales"):
            assert not want[name].any()


def test_version_and_gradient_select_the_stage_options():
    t, m = ls.load(CASES / "gsplat_rasterization_f64_v16.input.safetensors")
    args = (t["means"], t["quats"], t["scales"], t["opacities"], t["colors"], t["viewmats"], t["Ks"], 24, 16)
    kw = dict(sh_degree=3, backgrounds=t["backgrounds"])
    cot = dict(v_render_colors=t["v_render_colors"], v_render_alphas=t["v_render_alphas"])
    for version in ("1.5.3", "1.6"):
        for gradient in ("exact", "gsplat"):
            meta = {**m, "version": version, "gradient": gradient}
            want, _ = ls.run_case(t, meta)
            rc, ra, _ = gs.rasterization(*args, **kw, version=version, gradient=gradient)
            g = gs.rasterization_vjp(*args, **kw, **cot, version=version, gradient=gradient)
            assert rc.tobytes() == want["render_colors"].tobytes()
            assert ra.tobytes() == want["render_alphas"].tobytes()
            bits_equal(g, {k: v for k, v in want.items() if k.startswith("v_")})
    # The options reach the stage: 1.5.3's radius box gives more intersections than 1.6's
    # AccuTile here, and the two gradient modes differ.
    n153 = gs.rasterization(*args, **kw, version="1.5.3").meta["isect_ids"].size
    assert n153 > gs.rasterization(*args, **kw, version="1.6").meta["isect_ids"].size
    exact = gs.rasterization_vjp(*args, **kw, **cot, gradient="exact")["v_means"]
    assert exact.tobytes() != gs.rasterization_vjp(*args, **kw, **cot, gradient="gsplat")["v_means"].tobytes()


@pytest.fixture
def raster():
    t, _ = ls.load(CASES / "gsplat_rasterization_f64_v16.input.safetensors")
    args = dict(means=t["means"], quats=t["quats"], scales=t["scales"], opacities=t["opacities"],
                colors=t["colors"], viewmats=t["viewmats"], Ks=t["Ks"], width=24, height=16)
    return args, t


def _sh(args: dict) -> dict:
    return {**args, "sh_degree": 3}


def test_bad_arguments_are_named(raster):
    args, t = raster
    cases = [
        (dict(means=args["means"][:, :2].copy()), ValueError, r"rasterization\(\): argument `means`: expected shape \[N,3\], found shape \[10,2\]"),
        (dict(opacities=args["opacities"][:4]), ValueError, r"`opacities`: expected shape \[N\] with N=10 from `means`, found shape \[4\]"),
        (dict(scales=args["scales"].astype(np.float32)), TypeError, r"`scales`: expected dtype float64 \(the dtype of `means`\), found dtype float32"),
        (dict(quats=args["quats"].tolist()), TypeError, r"`quats`: expected a numpy.ndarray .* found list"),
        (dict(Ks=args["Ks"][:1]), ValueError, r"`Ks`: expected shape \[C,3,3\] with C=2 from `viewmats`, found shape \[1,3,3\]"),
        (dict(colors=args["colors"][:, :4], sh_degree=None), ValueError, r"`colors`: expected shape \[N,D\], found shape \[10,4,3\]"),
        (dict(width=0), ValueError, r"`width`: expected an integer in 1..=65536, found 0"),
        (dict(render_mode="RGB+D"), ValueError, r"`render_mode`: only 'RGB' is supported by the oracle, found 'RGB\+D'"),
        (dict(rasterize_mode="fast"), ValueError, r"`rasterize_mode`: expected one of 'classic', 'antialiased', found 'fast'"),
        (dict(version="1.5"), ValueError, r"`version`: expected one of '1.5.3', '1.6', found '1.5'"),
        (dict(gradient="inria"), ValueError, r"`gradient`: expected one of 'exact', 'gsplat', found 'inria'"),
        (dict(packed=1), TypeError, r"`packed`: expected a bool, found int"),
        (dict(covars=np.zeros((10, 6))), ValueError, r"expected `covars` or `quats` and `scales`, found both"),
        (dict(scales=None), ValueError, r"expected `quats` and `scales` \(or `covars`\), found no `scales`"),
    ]
    for change, exc, msg in cases:
        with pytest.raises(exc, match=msg):
            gs.rasterization(**{**_sh(args), **change})
    with pytest.raises(ValueError, match=r"`colors`: expected at least \(sh_degree\+1\)\^2 = 16 SH coefficients, found shape \[10,9,3\]"):
        gs.rasterization(**{**_sh(args), "colors": args["colors"][:, :9].copy()})
    with pytest.raises(ValueError, match=r"rasterization_vjp\(\): argument `v_render_colors`: expected shape \[2,16,24,3\], found shape \[2,24,16,3\]"):
        gs.rasterization_vjp(**args, sh_degree=3, v_render_colors=np.zeros((2, 24, 16, 3)),
                             v_render_alphas=t["v_render_alphas"])
    with pytest.raises(ValueError, match=r"`backgrounds`: expected shape \[C,3\] with C=2 from `viewmats`"):
        gs.rasterization(**args, sh_degree=3, backgrounds=np.zeros((1, 3)))


def test_bad_arguments_of_the_stage_functions():
    t, m = ls.load(CASES / "gsplat_rasterize_to_pixels_f64_v16_gsplat.input.safetensors")
    args = dict(means2d=t["means2d"], conics=t["conics"], colors=t["colors"], opacities=t["opacities"],
                image_width=24, image_height=16, tile_size=16, isect_offsets=t["isect_offsets"],
                flatten_ids=t["flatten_ids"], packed=True)
    with pytest.raises(TypeError, match=r"rasterize_to_pixels\(\): argument `flatten_ids`: expected an integer dtype \(int32\), found dtype float64"):
        gs.rasterize_to_pixels(**{**args, "flatten_ids": t["flatten_ids"].astype(np.float64)})
    with pytest.raises(ValueError, match=r"`means2d`: expected shape \[C,N,2\], found shape \[20,2\]"):
        gs.rasterize_to_pixels(**{**args, "packed": False})
    with pytest.raises(ValueError, match=r"`isect_offsets`: expected ascending values within \[0, 31\] \(the "
                                         r"length of flatten_ids\), found 9 at flat index 2 after 10"):
        gs.rasterize_to_pixels(**{**args, "isect_offsets": np.array([0, 10, 9, 26], np.int32).reshape(2, 1, 2)})
    with pytest.raises(ValueError, match=r"found 32 at flat index 3 after 16"):
        gs.rasterize_to_pixels(**{**args, "isect_offsets": np.array([0, 10, 16, 32], np.int32).reshape(2, 1, 2)})
    with pytest.raises(ValueError, match=r"`masks`: only None is supported"):
        gs.rasterize_to_pixels(**args, masks=np.ones((2, 1, 2), bool))
    with pytest.raises(ValueError, match=r"`conics`: expected finite values, found inf at flat index 3"):
        gs.rasterize_to_pixels(**{**args, "conics": np.where(np.arange(60).reshape(20, 3) == 3, np.inf, t["conics"])})
    with pytest.raises(ValueError, match=r"`degrees_to_use`: expected an integer in 0..=4, found 5"):
        gs.spherical_harmonics(5, np.zeros((2, 3)), np.zeros((2, 36, 3)))
    with pytest.raises(ValueError, match=r"`coeffs`: expected at least \(degrees_to_use\+1\)\^2 = 9 coefficients"):
        gs.spherical_harmonics(2, np.zeros((2, 3)), np.zeros((2, 4, 3)))
    with pytest.raises(ValueError, match=r"`v_precis`: given, but compute_preci=False"):
        gs.quat_scale_to_covar_preci_vjp(np.ones((1, 4)), np.ones((1, 3)), True, False, False,
                                         v_covars=np.zeros((1, 3, 3)), v_precis=np.zeros((1, 3, 3)))
    with pytest.raises(ValueError, match=r"`sparse_grad`: only False is supported"):
        gs.fully_fused_projection(np.zeros((1, 3)), None, np.ones((1, 4)), np.ones((1, 3)),
                                  np.eye(4)[None], np.eye(3)[None], 8, 8, sparse_grad=True)
    # 4,097 cameras x 16,384 Gaussians: more pairs than the dense projection holds (2^26),
    # refused before its outputs are allocated (from inputs of a few MB).
    n, c = 1 << 14, (1 << 12) + 1
    for f in (lambda: gs.fully_fused_projection(np.zeros((n, 3)), None, np.ones((n, 4)), np.ones((n, 3)),
                                                np.broadcast_to(np.eye(4), (c, 4, 4)).copy(),
                                                np.broadcast_to(np.eye(3), (c, 3, 3)).copy(), 8, 8),
              lambda: gs.rasterization(np.zeros((n, 3)), np.ones((n, 4)), np.ones((n, 3)), np.ones(n),
                                       np.zeros((n, 3)), np.broadcast_to(np.eye(4), (c, 4, 4)).copy(),
                                       np.broadcast_to(np.eye(3), (c, 3, 3)).copy(), 1, 1)):
        with pytest.raises(ValueError, match=r"`viewmats, means`: 4097 cameras x 16384 Gaussians: the dense "
                                             r"projection holds one entry per pair, at most 67108864"):
            f()
    # Dense colours of no channels are named (not a reshape's error); numpy's bools are
    # bools; a dense intersection of no Gaussians is empty, as the packed one is.
    z = lambda *s: np.zeros(s)  # noqa: E731
    with pytest.raises(ValueError, match=r"colors"):
        gs.rasterize_to_pixels(z(2, 10, 2), z(2, 10, 3), z(2, 10, 0), z(2, 10), 24, 16, 16,
                               np.zeros((2, 1, 2), np.int32), np.zeros(0, np.int32))
    proj = gs.fully_fused_projection(np.zeros((1, 3)), None, np.ones((1, 4)), np.ones((1, 3)),
                                     np.eye(4)[None], np.eye(3)[None], 8, 8, sparse_grad=np.bool_(False))
    assert proj[0].shape == (1, 1, 2)
    tiles, ids, flat = gs.isect_tiles(z(2, 0, 2), np.zeros((2, 0, 2), np.int32), z(2, 0), 16, 2, 1,
                                      sort=np.bool_(True))
    assert tiles.shape == (2, 0) and ids.shape == (0,) and flat.shape == (0,)
    with pytest.raises(ValueError, match=r"`sort`: only True is supported by the oracle, found np.False_"):
        gs.isect_tiles(z(2, 0, 2), np.zeros((2, 0, 2), np.int32), z(2, 0), 16, 2, 1, sort=np.bool_(False))
    with pytest.raises(ValueError, match=r"expected `n_images` and `image_ids` with packed=True"):
        gs.isect_tiles(t["means2d"], np.ones((20, 2), np.int32), t["opacities"], 16, 2, 1, packed=True)
    ids = np.array([3 << 32, 1 << 32], np.int64)
    with pytest.raises(ValueError, match=r"`isect_ids`: expected keys sorted by \(image, tile\)"):
        gs.isect_offset_encode(ids, 2, 2, 1)
    with pytest.raises(TypeError, match=r"`isect_ids`: expected int64 of shape \[n_isects\], found dtype int32"):
        gs.isect_offset_encode(ids.astype(np.int32), 2, 2, 1)
    # Keys must name an existing image and tile (1.6: 1 tile bit for 2 tiles; 1.5.3: 2 bits).
    with pytest.raises(ValueError, match=r"`isect_ids`: expected image indices below n_images=2, found isect_ids\[1\] = 17179869184 \(key 4: image 2, tile 0\)"):
        gs.isect_offset_encode(np.array([1 << 32, 4 << 32], np.int64), 2, 2, 1)
    with pytest.raises(ValueError, match=r"`isect_ids`: expected non-negative keys, found isect_ids\[0\] = -4294967296"):
        gs.isect_offset_encode(np.array([-1 << 32, 0], np.int64), 2, 2, 1)
    with pytest.raises(ValueError, match=r"`isect_ids`: expected tile indices below tile_width\*tile_height=3, found isect_ids\[0\] = 12884901888 \(key 3: image 0, tile 3\)"):
        gs.isect_offset_encode(np.array([3 << 32], np.int64), 1, 3, 1, version="1.5.3")
    np.testing.assert_array_equal(gs.isect_offset_encode(np.array([1 << 32, 2 << 32], np.int64), 2, 2, 1),
                                  [[[0, 0]], [[1, 2]]])


def test_torch_rasterization_gradcheck_float64(raster):
    torch = pytest.importorskip("torch")
    import liquid_splat.torch as lt

    args, t = raster
    x = {k: torch.from_numpy(v.copy()).requires_grad_(True) for k, v in args.items()
         if k in ("means", "quats", "scales", "opacities", "colors")}
    bg = torch.from_numpy(t["backgrounds"].copy()).requires_grad_(True)
    cams = (torch.from_numpy(args["viewmats"]), torch.from_numpy(args["Ks"]))

    def f(means, quats, scales, opacities, colors, backgrounds):
        rc, ra, _ = lt.rasterization(means, quats, scales, opacities, colors, *cams, 24, 16,
                                     sh_degree=3, backgrounds=backgrounds)
        return rc, ra

    rc, ra = f(*x.values(), bg)
    assert rc.dtype == torch.float64 and ra.max() > 0.1  # a non-empty render
    _, _, meta = lt.rasterization(*x.values(), *cams, 24, 16, sh_degree=3, backgrounds=bg)
    np_meta = gs.rasterization(**args, sh_degree=3, backgrounds=t["backgrounds"]).meta
    assert meta["isect_ids"].numpy().tobytes() == np_meta["isect_ids"].tobytes()
    assert torch.autograd.gradcheck(f, (*x.values(), bg), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=False)
    # The gradients are the numpy vjp's.
    cot = (torch.from_numpy(t["v_render_colors"]), torch.from_numpy(t["v_render_alphas"]))
    grads = torch.autograd.grad(f(*x.values(), bg), (*x.values(), bg), cot)
    want = gs.rasterization_vjp(**args, sh_degree=3, backgrounds=t["backgrounds"],
                                v_render_colors=t["v_render_colors"], v_render_alphas=t["v_render_alphas"])
    for name, g in zip(list(x) + ["backgrounds"], grads):
        assert g.numpy().tobytes() == want[f"v_{name}"].tobytes(), name


def test_torch_rasterize_to_pixels_gradcheck_float64():
    torch = pytest.importorskip("torch")
    import liquid_splat.torch as lt

    t, _ = ls.load(CASES / "gsplat_rasterize_to_pixels_f64_v16_gsplat.input.safetensors")
    diff = [torch.from_numpy(t[k].copy()).requires_grad_(True)
            for k in ("means2d", "conics", "colors", "opacities", "backgrounds")]
    ints = (torch.from_numpy(t["isect_offsets"]), torch.from_numpy(t["flatten_ids"]))

    def f(means2d, conics, colors, opacities, backgrounds):
        return lt.rasterize_to_pixels(means2d, conics, colors, opacities, 24, 16, 16, *ints,
                                      backgrounds=backgrounds, packed=True)

    rc, ra = f(*diff)
    assert ra.max() > 0.1
    assert torch.autograd.gradcheck(f, tuple(diff), eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=False)


def test_background_gradient_of_a_large_f32_image_is_summed_accurately():
    # v_backgrounds sums v_C·T over every pixel: 160,000 terms per channel here, mostly
    # background, values up to about 490. A running f32 sum was 6.6e-3 off the f64 value on
    # this input, the pairwise sum is 8.8e-5 off (the f64 run gets the same f32 inputs).
    t, _ = ls.load(CASES / "gsplat_rasterization_f64_v16.input.safetensors")
    f32 = {k: t[k].astype(np.float32)
           for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks")}
    rng = np.random.default_rng(3)
    cot = dict(v_render_colors=rng.normal(size=(2, 400, 400, 3)).astype(np.float32),
               v_render_alphas=np.zeros((2, 400, 400, 1), np.float32))
    bg = np.full((2, 3), 0.25, np.float32)

    def v_backgrounds(dtype):
        return gs.rasterization_vjp(
            **{k: v.astype(dtype) for k, v in f32.items()}, width=400, height=400, sh_degree=3,
            backgrounds=bg.astype(dtype), **{k: v.astype(dtype) for k, v in cot.items()},
            version="1.6")["v_backgrounds"]

    err = np.abs(v_backgrounds(np.float32) - v_backgrounds(np.float64)).max()
    assert err < 1e-3, err
