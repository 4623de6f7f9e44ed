"""The stage functions with upstream's names give the golden fixtures' bits."""

import numpy as np
import pytest

import liquid_splat as ls
from conftest import CASES, GOLDEN, bits_equal, raster_inputs, raster_kwargs, weights


def case(name):
    t, m = ls.load(CASES / f"{name}.input.safetensors")
    e, _ = ls.load(CASES / f"{name}.expected.safetensors")
    return t, m, e


@pytest.mark.parametrize("name", [n for n in GOLDEN if n.startswith("rasterize")])
def test_rasterize_and_vjp(name):
    t, m, e = case(name)
    r = ls.rasterize(**raster_inputs(t), **raster_kwargs(t, m))
    bits_equal(r._asdict(), {k: e[k] for k in r._fields})
    assert (r.radii > 0).sum() >= 5 and not np.allclose(r.color, t["bg"][:, None, None])
    g = ls.rasterize_vjp(**raster_inputs(t), **raster_kwargs(t, m), grad_color=t["grad_out_color"],
                         grad_depth=t["grad_out_depth"], gradient=m["gradient"])
    bits_equal(g, {k: v for k, v in e.items() if k.startswith("grad_")})


@pytest.mark.parametrize("name", [n for n in GOLDEN if n.startswith("deform")])
def test_fields(name):
    t, m, e = case(name)
    sd = weights(t)
    field = ls.load_field(sd, activation=m["activation"])
    assert type(field) is (ls.CfCField if m["field"] == "cfc" else ls.DeformNetwork)
    for k in ("depth", "width", "variant"):
        assert str(field.config[k]) == m[k]
    out = field.forward(t["xyz"], t["t"])
    bits_equal({k: getattr(out, k) for k in ("d_xyz", "d_rotation", "d_scaling")},
               {k: e[k] for k in ("d_xyz", "d_rotation", "d_scaling")})
    g = field.vjp(t["xyz"], t["t"], t["grad_d_xyz"], t["grad_d_rotation"], t["grad_d_scaling"])
    bits_equal(g, {k: v for k, v in e.items() if k.startswith("grad")})
    # Counts, independently: every Linear runs once per Gaussian, so the ptflops `aten`
    # count (in·out + out per Linear) equals the number of parameters.
    assert field.param_count == sum(v.size for v in sd.values())
    assert field.macs("aten") == field.param_count
    if m["field"] == "mlp":
        # + functional F.relu after each of the D trunk layers, + the timenet's nn.ReLU
        # module (counted twice by the pytorch backend with count_functional=True).
        extra = int(m["depth"]) * int(m["width"]) + 2 * 256
        assert field.macs("pytorch") == field.param_count + extra


def test_6dof_field_from_the_step_fixture():
    t, m, _ = case("step_f64_6dof")
    field = ls.DeformNetwork(weights(t))
    assert field.config["is_6dof"] is True and field.config["variant"] == "real"
    rng = np.random.default_rng(1)
    x = rng.standard_normal((5, 3))
    out = field.forward(x, 0.3)
    assert out.d_xyz_se3.shape == (5, 4, 4)
    R, p = out.d_xyz_se3[:, :3, :3], out.d_xyz_se3[:, :3, 3]
    np.testing.assert_allclose(out.d_xyz, np.einsum("nij,nj->ni", R, x) + p - x, atol=1e-12)
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-6)
    g = rng.standard_normal((5, 3))
    grads = field.vjp(x, np.full((5, 1), 0.3), g, np.zeros((5, 4)), np.zeros((5, 3)))
    np.testing.assert_allclose(grads["grad_xyz"],
                               np.einsum("nji,nj->ni", R - np.eye(3), g), atol=1e-12)


@pytest.mark.parametrize("dtype", ["f32", "f64"])
def test_loss(dtype):
    t, m, e = case(f"loss_{dtype}")
    bits_equal(ls.loss(t["image"], t["gt"], float(m["lambda_dssim"])), e)


@pytest.mark.parametrize("name", [n for n in GOLDEN if n.startswith("step")])
def test_step(name):
    t, m, e = case(name)
    meta = {k: v for k, v in m.items() if k != "stage"}
    out, _ = ls.step(t, meta)
    bits_equal(out, e)


def test_float32_and_float64_select_the_precision():
    t, m, _ = case("loss_f64")
    out64 = ls.loss(t["image"], t["gt"])
    out32 = ls.loss(t["image"].astype(np.float32), t["gt"].astype(np.float32))
    assert out64["loss"].dtype == np.float64 and out32["loss"].dtype == np.float32
    assert abs(float(out64["loss"]) - float(out32["loss"])) < 1e-5
    field = ls.load_field(weights(case("deform_f64_mlp")[0]))
    f32 = field.astype(np.float32)
    x = np.zeros((2, 3), np.float32)
    assert f32.forward(x, np.zeros((2, 1), np.float32)).d_xyz.dtype == np.float32
