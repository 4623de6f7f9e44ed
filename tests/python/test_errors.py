"""Bad arguments raise TypeError / ValueError naming the argument, what was expected and
what was found; nothing crashes the interpreter."""

import os
import sys

import numpy as np
import pytest

import liquid_splat as ls
from conftest import CASES, raster_inputs, raster_kwargs, weights


@pytest.fixture
def raster():
    t, m = ls.load(CASES / "rasterize_f64_exact.input.safetensors")
    return raster_inputs(t), raster_kwargs(t, m)


def test_rasterize_bad_arguments(raster):
    ins, kw = raster
    cases = [
        (dict(means3D=ins["means3D"][:, :2].copy()), ValueError, r"`means3D`: expected shape \[N,3\], found shape \[9,2\]"),
        (dict(opacities=ins["opacities"][:4]), ValueError, r"`opacities`: expected shape \[N,1\] with N=9 from `means3D`, found shape \[4,1\]"),
        (dict(scales=ins["scales"].astype(np.float32)), TypeError, r"`scales`: expected dtype float64 \(the dtype of `means3D`\), found dtype float32"),
        (dict(rotations=ins["rotations"].astype(np.int64)), TypeError, r"`rotations`: expected dtype float32 or float64, found dtype int64"),
        (dict(means3D=ins["means3D"].tolist()), TypeError, r"`means3D`: expected a numpy.ndarray .* found list"),
        (dict(shs=np.asfortranarray(ins["shs"])), ValueError, r"`shs`: expected a C-contiguous array"),
        (dict(means3D=np.where(np.arange(27).reshape(9, 3) == 4, np.nan, ins["means3D"])), ValueError, r"`means3D`: expected finite values, found nan at flat index 4"),
    ]
    for change, exc, msg in cases:
        with pytest.raises(exc, match=msg):
            ls.rasterize(**{**ins, **change}, **kw)
    with pytest.raises(ValueError, match="exactly one of `shs` and `colors_precomp`, found both"):
        ls.rasterize(**ins, colors_precomp=ins["means3D"], **kw)
    with pytest.raises(ValueError, match="`sh_degree`: expected an integer in 0..=3, found 4"):
        ls.rasterize(**ins, **{**kw, "sh_degree": 4})
    with pytest.raises(ValueError, match="`tanfovx`: expected a finite positive number, found -1.0"):
        ls.rasterize(**ins, **{**kw, "tanfovx": -1.0})
    with pytest.raises(ValueError, match="`image_width`: expected an integer in 1..=67108864, found 0"):
        ls.rasterize(**ins, **{**kw, "image_width": 0})
    with pytest.raises(ValueError, match=r"`viewmatrix`: expected shape \[4,4\], found shape \[16\]"):
        ls.rasterize(**ins, **{**kw, "viewmatrix": kw["viewmatrix"].ravel()})
    with pytest.raises(ValueError, match=r"`grad_color`: expected shape \[3,24,32\], found shape \[3,32,24\]"):
        ls.rasterize_vjp(**ins, **kw, grad_color=np.zeros((3, 32, 24)))
    with pytest.raises(ValueError, match="`gradient`: expected one of 'exact', 'inria', found 'fast'"):
        ls.rasterize_vjp(**ins, **kw, grad_color=np.zeros((3, 24, 32)), gradient="fast")


def test_run_case_bad_inputs():
    t, m = ls.load(CASES / "loss_f64.input.safetensors")
    with pytest.raises(ValueError, match="unknown stage `blend`"):
        ls.run_case(t, {**m, "stage": "blend"})
    with pytest.raises(ValueError, match="missing tensor `gt`"):
        ls.run_case({"image": t["image"]}, m)
    with pytest.raises(ValueError, match=r"unexpected tensor\(s\): extra"):
        ls.run_case({**t, "extra": t["gt"]}, m)
    with pytest.raises(TypeError, match=r"tensors\['gt'\]: expected dtype float32, float64, int32 or int64 .*found dtype float16"):
        ls.run_case({**t, "gt": t["gt"].astype(np.float16)}, m)
    with pytest.raises(TypeError, match=r"tensor `image`: expected dtype F32 like `gt`, found F64"):
        ls.run_case({**t, "gt": t["gt"].astype(np.float32)}, m)
    with pytest.raises(ValueError, match=r"tensors\['gt'\]: expected a C-contiguous array"):
        ls.run_case({**t, "gt": t["gt"][:, ::2]}, m)
    with pytest.raises(ValueError, match=r"tensors\['gt'\]: expected finite values, found inf"):
        ls.run_case({**t, "gt": np.full_like(t["gt"], np.inf)}, m)
    with pytest.raises(TypeError, match=r"tensors\['gt'\]: expected a numpy.ndarray"):
        ls.run_case({**t, "gt": 1.0}, m)
    with pytest.raises(TypeError, match=r"metadata\['lambda_dssim'\]: expected str, bool, int or float, found list"):
        ls.run_case(t, {**m, "lambda_dssim": [0.2]})
    with pytest.raises(ValueError, match=r"run_case\(\): argument `threads`: expected an integer in 1..=1024, found 0"):
        ls.run_case(t, m, threads=0)
    with pytest.raises(ValueError, match="lambda_dssim"):
        ls.loss(t["image"], t["gt"], lambda_dssim=1.5)
    with pytest.raises(ValueError, match=r"`gt`: expected shape \[3,H,W\] with H=24 from `image`"):
        ls.loss(t["image"], t["gt"][:, :10].copy())


def test_field_bad_inputs():
    t, m = ls.load(CASES / "deform_f64_mlp.input.safetensors")
    sd = weights(t)
    with pytest.raises(ValueError, match="linear.0.weight"):
        ls.DeformNetwork({"foo.weight": sd["linear.0.weight"]})
    bad = dict(sd)
    bad["gaussian_warp.weight"] = bad["gaussian_warp.weight"][:, :5].copy()
    with pytest.raises(ValueError, match=r"tensor `gaussian_warp.weight`: expected shape \[3,32\], found shape \[3,5\]"):
        ls.DeformNetwork(bad)
    with pytest.raises(ValueError, match=r"unexpected tensor\(s\): branch_v.weight"):
        ls.DeformNetwork({**sd, "branch_v.weight": sd["gaussian_warp.weight"]})
    with pytest.raises(TypeError, match=r"state_dict\['linear.1.bias'\]: expected dtype float64 like the other weights"):
        ls.DeformNetwork({**sd, "linear.1.bias": sd["linear.1.bias"].astype(np.float32)})
    field = ls.DeformNetwork(sd)
    with pytest.raises(TypeError, match=r"`xyz`: expected dtype float64 \(the dtype of the state_dict\), found dtype float32"):
        field.forward(t["xyz"].astype(np.float32), t["t"])
    with pytest.raises(ValueError, match=r"`t`: expected shape \[N,1\] with N=8 from `xyz`"):
        field.forward(t["xyz"], t["t"][:3])
    with pytest.raises(ValueError, match="convention"):
        field.macs("flops")
    with pytest.raises(ValueError, match="activation"):
        ls.CfCField(weights(ls.load(CASES / "deform_f64_cfc.input.safetensors")[0]), activation="softmax")


def test_compare_unusable_input(tmp_path):
    from liquid_splat.testing import compare

    with pytest.raises(ValueError, match="no tensors"):
        compare({}, {})
    with pytest.raises(ValueError, match="nope.safetensors"):
        compare(tmp_path / "nope.safetensors", {})
    with pytest.raises(TypeError, match="expected a dict"):
        compare(3, {})


def test_cli_usage_errors_are_exit_codes(capfd):
    assert ls.cli("case", "frobnicate") == 2
    assert ls.cli("--help") == 0


def test_threads_and_seed_are_bounded_and_named():
    t, m = ls.load(CASES / "loss_f64.input.safetensors")
    for call in (lambda th: ls.run_case(t, m, threads=th),
                 lambda th: ls.loss(t["image"], t["gt"], threads=th)):
        for bad, exc, msg in ((10000, ValueError, "an integer in 1..=1024, found 10000"),
                              (1025, ValueError, "an integer in 1..=1024, found 1025"),
                              (-1, ValueError, "an integer in 1..=1024, found -1"),
                              (True, TypeError, "an int, found bool"),
                              (2.0, TypeError, "an int, found float")):
            with pytest.raises(exc, match=rf"\(\): argument `threads`: expected {msg}$"):
                call(bad)
        call(1)
        call(np.int64(2))
    for bad, exc in ((-1, ValueError), (2**64, ValueError), (True, TypeError), ("1", TypeError)):
        with pytest.raises(exc, match=r"DeformNetwork.new\(\): argument `seed`: expected"):
            ls.DeformNetwork.new(D=3, W=4, seed=bad)
        with pytest.raises(exc, match=r"CfCField.new\(\): argument `seed`: expected"):
            ls.CfCField.new(D=1, W=4, seed=bad)
    assert ls.DeformNetwork.new(D=3, W=4, seed=2**64 - 1).param_count > 0


def test_metadata_numbers_are_written_exactly(tmp_path):
    t, m = ls.load(CASES / "step_f64.input.safetensors")
    meta = {"stage": "loss", "big": 2**64 - 1, "np_int": np.int64(-7), "np_true": np.True_,
            "false": False, "float": 0.1, "np_float32": np.float32(0.1), "huge": 1e300}
    ls.save(tmp_path / "m.safetensors", {"x": np.zeros(1)}, meta)
    _, back = ls.load(tmp_path / "m.safetensors")
    assert back == {"stage": "loss", "big": "18446744073709551615", "np_int": "-7",
                    "np_true": "true", "false": "false", "float": "0.1",
                    "np_float32": repr(float(np.float32(0.1))), "huge": "1e+300"}
    # A numpy bool is a bool to the library (field_on), and a too-large size is named exactly.
    out, _ = ls.step(t, {**m, "field_on": np.True_})
    ref, _ = ls.step(t, m)
    assert sorted(out) == sorted(ref) and all(out[k].tobytes() == ref[k].tobytes() for k in ref)
    r, rm = ls.load(CASES / "rasterize_f64_exact.input.safetensors")
    ins, kw = raster_inputs(r), raster_kwargs(r, rm)
    with pytest.raises(ValueError, match='"18446744073709551616"'):
        ls.run_case(r, {**rm, "image_height": 2**64})
    with pytest.raises(ValueError, match="`image_height`: expected an integer in 1..=67108864, found 18446744073709551616$"):
        ls.rasterize(**ins, **{**kw, "image_height": 2**64})


def test_field_construction_errors_are_named():
    t, _ = ls.load(CASES / "deform_f64_mlp.input.safetensors")
    sd = weights(t)
    with pytest.raises(ValueError, match=r"DeformNetwork: state_dict\['linear.0.weight'\]: expected a weight of shape \[W,in\], found shape \[\]"):
        ls.DeformNetwork({**sd, "linear.0.weight": np.array(1.0)})
    cfc = weights(ls.load(CASES / "deform_f64_cfc.input.safetensors")[0])
    with pytest.raises(ValueError, match=r"CfCField: state_dict\['cells.0.ff1.weight'\]: expected a weight of shape \[W,in\], found shape \[3\]"):
        ls.CfCField({**cfc, "cells.0.ff1.weight": np.zeros(3)})
    with pytest.raises(ValueError, match=r"DeformNetwork.new\(\): argument `D`: expected an integer >= 3, found -1"):
        ls.DeformNetwork.new(D=-1)
    with pytest.raises(TypeError, match=r"DeformNetwork.new\(\): argument `D`: expected an int, found str"):
        ls.DeformNetwork.new(D="4")
    with pytest.raises(TypeError, match=r"DeformNetwork.new\(\): argument `is_6dof`: expected a bool, found int"):
        ls.DeformNetwork.new(is_6dof=1)
    with pytest.raises(ValueError, match=r"CfCField.new\(\): argument `backbone_layers`: expected an integer >= 1, found -1"):
        ls.CfCField.new(backbone_layers=-1)
    with pytest.raises(TypeError, match=r"CfCField.new\(\): argument `variant`: expected a str, found NoneType"):
        ls.CfCField.new(variant=None)
    assert ls.DeformNetwork.new(D=np.int64(3), W=4).config["depth"] == 3


def test_astype_takes_only_float32_or_float64():
    field = ls.DeformNetwork.new(D=3, W=4)
    for bad, found in ((np.int32, "int32"), ("float16", "float16"), ("bogus", "'bogus'")):
        with pytest.raises(TypeError, match=rf"DeformNetwork.astype\(\): argument `dtype`: expected float32 or float64, found {found}"):
            field.astype(bad)
    assert field.astype(np.float64).dtype == np.float64


def test_field_time_may_be_any_real_scalar():
    field = ls.DeformNetwork.new(D=3, W=4, dtype=np.float64)
    x = np.zeros((2, 3))
    want = field.forward(x, np.ones((2, 1))).d_xyz.tobytes()
    for t in (1, 1.0, np.int64(1), np.float32(1.0), np.array(1.0), np.array(1)):
        assert field.forward(x, t).d_xyz.tobytes() == want, repr(t)
    with pytest.raises(TypeError, match=r"`t`: expected a float, found bool"):
        field.forward(x, np.array(True))


def test_load_and_save_raise_os_errors(tmp_path):
    with pytest.raises(FileNotFoundError) as e:
        ls.load(tmp_path / "nope.safetensors")
    assert e.value.filename == str(tmp_path / "nope.safetensors")
    with pytest.raises(IsADirectoryError):
        ls.load(tmp_path)
    with pytest.raises(FileNotFoundError):
        ls.save(tmp_path / "no" / "x.safetensors", {"x": np.zeros(1)})
    (tmp_path / "bad.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(ValueError, match="bad.safetensors"):
        ls.load(tmp_path / "bad.safetensors")


def test_paths_the_file_system_cannot_encode_are_named(tmp_path):
    """A lone surrogate in a path was a PanicException (a BaseException) out of the
    extension's path conversion; it is a ValueError naming the argument."""
    from liquid_splat.testing import compare

    x = {"x": np.zeros(1)}
    with pytest.raises(ValueError, match=r"load\(\): argument `path`: expected a path the file system can encode"):
        ls.load("nope\ud800.safetensors")
    with pytest.raises(ValueError, match=r"save\(\): argument `path`: expected a path the file system can encode"):
        ls.save(tmp_path / "x\ud800.safetensors", x)
    with pytest.raises(ValueError, match=r"compare\(\): argument `expected`: expected a path"):
        compare("\ud800", x)
    with pytest.raises(ValueError, match=r"compare\(\): argument `tolerances`: expected a path"):
        compare(x, x, tolerances="\ud800.json")
    with pytest.raises(ValueError, match=r"cli\(\): argument `args\[1\]`: expected an argument the file system can encode"):
        ls.cli("case", "\ud800")
    for call, msg in ((lambda: ls.load(3), r"load\(\): argument `path`: expected a path .* found int"),
                      (lambda: ls.save(None, x), r"save\(\): argument `path`: expected a path .* found NoneType"),
                      (lambda: ls.cli("case", 2), r"cli\(\): argument `args\[1\]`: expected an argument \(str, bytes or os.PathLike\), found int")):
        with pytest.raises(TypeError, match=msg):
            call()
    # bytes paths name the same files as their decoded str.
    ls.save(os.fsencode(tmp_path / "b.safetensors"), x)
    assert ls.load(os.fsencode(tmp_path / "b.safetensors"))[0]["x"].shape == (1,)
    # The tool in-process gets arguments as the binary does: a file name that is not
    # UTF-8 is its usage error (exit 2), not a Python one.
    if sys.platform != "win32":
        assert ls.cli("case", "compare", os.fsencode(tmp_path) + b"/\xff.st", b"x") == 2


def test_integers_beyond_float_range_are_named(raster):
    """An int too large for a float was an OverflowError out of float(); it is the
    ValueError of any other non-finite number, naming the argument."""
    from liquid_splat.testing import compare

    ins, kw = raster
    for key in ("tanfovx", "scale_modifier"):
        with pytest.raises(ValueError, match=rf"rasterize\(\): argument `{key}`: expected a finite .*number, found an integer of 1329 bits"):
            ls.rasterize(**ins, **{**kw, key: 10**400})
    t, _ = ls.load(CASES / "loss_f64.input.safetensors")
    with pytest.raises(ValueError, match=r"loss\(\): argument `lambda_dssim`: expected a finite number, found an integer"):
        ls.loss(t["image"], t["gt"], 10**400)
    with pytest.raises(ValueError, match=r"compare\(\): argument `rtol`: expected a finite number, found an integer"):
        compare(t, t, rtol=-(10**400))
    field = ls.DeformNetwork.new(D=3, W=4)
    with pytest.raises(ValueError, match=r"DeformNetwork.forward\(\): argument `t`: expected a finite number"):
        field.forward(np.zeros((2, 3), np.float32), 10**400)


def test_dicts_choices_and_dtypes_are_named():
    """Non-dict tensors/metadata/state_dicts, string choices given as arrays, dtypes numpy
    cannot read and tolerances json cannot write raised Python's or numpy's own errors
    (AttributeError, 'truth value of an array is ambiguous', 'data type not understood')
    that named no argument."""
    from liquid_splat import gsplat as gs
    from liquid_splat.testing import compare, recommended_tolerances

    t, m = ls.load(CASES / "loss_f64.input.safetensors")
    for call, msg in ((lambda: ls.run_case(None, m), r"run_case\(\): argument `tensors`: expected a dict, found NoneType"),
                      (lambda: ls.run_case(t, list(m.items())), r"run_case\(\): argument `metadata`: expected a dict, found list"),
                      (lambda: ls.step(t, "stage=step"), r"step\(\): argument `metadata`: expected a dict, found str"),
                      (lambda: ls.save("x.safetensors", t, ["a"]), r"save\(\): argument `metadata`: expected a dict, found list"),
                      (lambda: ls.DeformNetwork(None), r"DeformNetwork: argument `state_dict`: expected a dict, found NoneType"),
                      (lambda: ls.CfCField({1: np.zeros(1), "cells.0.ff1.weight": np.zeros((2, 2))}), r"CfCField: state_dict: expected str keys \(parameter names\), found int 1"),
                      (lambda: ls.DeformNetwork.new(D=3, W=4, dtype="bogus"), r"DeformNetwork.new\(\): argument `dtype`: expected float32 or float64, found 'bogus'"),
                      (lambda: ls.CfCField.new(D=1, W=4, dtype=np.float16), r"CfCField.new\(\): argument `dtype`: expected float32 or float64, found float16"),
                      (lambda: recommended_tolerances("bogus"), r"recommended_tolerances\(\): argument `dtype`: expected float32 or float64, found 'bogus'"),
                      (lambda: recommended_tolerances(np.int8), r"recommended_tolerances\(\): argument `dtype`: expected float32 or float64, found int8"),
                      (lambda: compare(t, t, tolerances={"default": {"atol": object()}}), r"compare\(\): argument `tolerances`: expected JSON values"),
                      (lambda: compare({"a": [[1.0], [1.0, 2.0]]}, t), r"compare\(\): expected\['a'\]: expected an array, found list")):
        with pytest.raises(TypeError, match=msg):
            call()
    q, _ = ls.load(CASES / "gsplat_quat_scale_to_covar_preci_f64.input.safetensors")
    with pytest.raises(ValueError, match=r"quat_scale_to_covar_preci\(\): argument `version`: expected one of '1.5.3', '1.6', found array"):
        gs.quat_scale_to_covar_preci(q["quats"], q["scales"], version=np.array(["1.6", "1.6"]))
    # numpy scalars and 0-d arrays still do where a str or a number is expected.
    gs.quat_scale_to_covar_preci(q["quats"], q["scales"], version=np.array("1.6"))
    assert compare(t, t, tolerances={"default": {"atol": np.float32(1e-3), "equal_nan": np.True_}}).passed


def test_masked_arrays_and_non_finite_tolerances_are_named():
    """A fully masked numpy.ma array reached numpy's IndexError in the finite check (a
    partly masked one lost its mask without a word), and a NaN in a tolerances dict was
    written as JSON that named a column of text the user never wrote."""
    from liquid_splat.testing import compare

    t, m = ls.load(CASES / "loss_f64.input.safetensors")
    masked = np.ma.masked_all(t["image"].shape)
    with pytest.raises(TypeError, match=r"loss\(\): argument `image`: expected a numpy.ndarray, found a masked "
                                        r"array \(numpy.ma\)"):
        ls.loss(masked, t["gt"], 0.2)
    with pytest.raises(TypeError, match=r"compare\(\): actual\['image'\]: expected a numpy.ndarray, found a masked"):
        compare(t, {**t, "image": np.ma.masked_array(t["image"], mask=True)})
    with pytest.raises(ValueError, match=r"compare\(\): argument `tolerances`: `default.atol`: expected a finite "
                                         r"number, found nan"):
        compare(t, t, tolerances={"default": {"atol": float("nan")}})
    with pytest.raises(ValueError, match=r"`tensors.image.rtol`: expected a finite number, found inf"):
        compare(t, t, tolerances={"tensors": {"image": {"rtol": np.float32("inf")}}})


def test_sizes_are_bounded_naming_the_argument(raster):
    """Image and tile sizes past the library's limits were refused by the library naming
    the wrong key (`image_width` for a too-tall image, `backgrounds` for a tile grid that
    did not match isect_offsets), accepted (isect_tiles' tile_size 2**63), or, in
    isect_offset_encode, ran into numpy's MemoryError / OverflowError; each is a ValueError
    naming the argument."""
    from liquid_splat import gsplat as gs

    ins, kw = raster
    with pytest.raises(ValueError, match=r"rasterize\(\): argument `image_height`: expected an integer in 1..=67108864, found 2147483648"):
        ls.rasterize(**ins, **{**kw, "image_height": 2**31})
    with pytest.raises(ValueError, match=r"rasterize\(\): arguments `image_height`, `image_width`: expected at most 67108864 pixels, found 4194304x32 = 134217728"):
        ls.rasterize(**ins, **{**kw, "image_height": 2**22})
    t, m = ls.load(CASES / "gsplat_isect_tiles_f64_v16.input.safetensors")
    isect = dict(means2d=t["means2d"], radii=t["radii"], depths=t["depths"], tile_size=16, tile_width=2,
                 tile_height=1, packed=True, n_images=2, image_ids=t["image_ids"])
    with pytest.raises(ValueError, match=r"isect_tiles\(\): argument `tile_size`: expected an integer in 1..=1024, found 9223372036854775808"):
        gs.isect_tiles(**{**isect, "tile_size": 2**63})
    with pytest.raises(ValueError, match=r"isect_tiles\(\): arguments `n_images`, `tile_width`, `tile_height`: .* found 2 images of 2147483648x1 tiles"):
        gs.isect_tiles(**{**isect, "tile_width": 2**31})
    dense = dict(means2d=t["means2d"][None], radii=t["radii"][None], depths=t["depths"][None],
                 tile_size=16, tile_width=2**31, tile_height=1)
    with pytest.raises(ValueError, match=r"isect_tiles\(\): arguments `means2d`'s C, `tile_width`, `tile_height`: .* found 1 images of 2147483648x1 tiles"):
        gs.isect_tiles(**dense)
    _, ids, _ = gs.isect_tiles(**isect)
    for key, value in (("n_images", 2**31), ("tile_width", 2**63), ("tile_height", 2**40)):
        with pytest.raises(ValueError, match=r"isect_offset_encode\(\): arguments `n_images`, `tile_width`, `tile_height`: expected at most 67108864 tiles"):
            gs.isect_offset_encode(ids, **{"n_images": 2, "tile_width": 2, "tile_height": 1, key: value})
    r, rm = ls.load(CASES / "gsplat_rasterize_to_pixels_f64_v16_gsplat.input.safetensors")
    args = [r[k] for k in ("means2d", "conics", "colors", "opacities")]
    rest = dict(isect_offsets=r["isect_offsets"], flatten_ids=r["flatten_ids"], backgrounds=r["backgrounds"], packed=True)
    with pytest.raises(ValueError, match=r"rasterize_to_pixels\(\): argument `isect_offsets`: expected shape \[I,1,1\] \(the tile grid of a 1x16 image with tile_size 16\), found shape \[2,1,2\]"):
        gs.rasterize_to_pixels(*args, 1, 16, 16, **rest)
    with pytest.raises(ValueError, match=r"rasterize_to_pixels\(\): argument `image_height`: expected an integer in 1..=65536, found 100000"):
        gs.rasterize_to_pixels(*args, 24, 100000, 16, **rest)
    with pytest.raises(ValueError, match=r"rasterize_to_pixels\(\): argument `tile_size`: expected an integer in 1..=1024, found 2048"):
        gs.rasterize_to_pixels(*args, 24, 16, 2048, **rest)


def test_metadata_text_and_tolerance_numbers():
    """A metadata string with a lone surrogate was a UnicodeEncodeError naming no key; a
    numpy longdouble in a tolerances dict recursed without end."""
    from liquid_splat.testing import compare

    t, m = ls.load(CASES / "loss_f64.input.safetensors")
    with pytest.raises(ValueError, match=r"metadata\['stage'\]: expected UTF-8 text, found 'loss\\ud800'"):
        ls.run_case(t, {**m, "stage": "loss\ud800"})
    with pytest.raises(ValueError, match=r"metadata\['activation'\]: expected UTF-8 text"):
        ls.CfCField.new(D=1, W=4, activation="\ud800")
    assert compare(t, t, tolerances={"default": {"atol": np.longdouble(1e-3)}}).passed
    # Keys too: a tensor name or a metadata key with a lone surrogate.
    with pytest.raises(ValueError, match=r"tensor names: expected UTF-8 text, found 'x\\ud800'"):
        ls.run_case({**t, "x\ud800": t["image"]}, m)
    with pytest.raises(ValueError, match=r"metadata: keys: expected UTF-8 text"):
        ls.run_case(t, {**m, "k\ud800": "v"})
    with pytest.raises(TypeError, match=r"tensor names: expected str, found int"):
        ls.run_case({**t, 1: t["image"]}, m)
