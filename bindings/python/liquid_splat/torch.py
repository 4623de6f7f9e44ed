"""PyTorch wrappers of the oracle (needs ``torch``; CPU tensors, float32 or float64).

- :func:`rasterize_gaussians`, :class:`GaussianRasterizationSettings`,
  :class:`GaussianRasterizer`: drop-in replacements of the Inria rasterizer's Python API
  (the D-3DGS fork: ``forward`` returns ``(color, radii, depth)``), differentiable in the
  ``exact`` gradient mode, depth included. ``means2D`` receives Inria's
  ``viewspace_points.grad`` (the NDC-scaled screen-space gradient).
- :class:`DeformNetwork` (D-3DGS MLP, incl. 6-DoF) and :class:`CfCField` (the liquid
  field) as ``torch.nn.Module``s whose ``state_dict`` keys are upstream's, so a D-3DGS
  ``deform.pth`` loads as is.
- :func:`loss`: ``(1 − λ)·L1 + λ·(1 − SSIM)``, differentiable w.r.t. the image.
- :func:`rasterization` and :func:`rasterize_to_pixels`: gsplat's functions (gsplat's
  arguments and outputs, :mod:`liquid_splat.gsplat`), differentiable w.r.t. the Gaussians'
  tensors and ``backgrounds`` in the chosen ``gradient`` mode.

Every forward and backward is the oracle's (the same bits as ``liquid-splat case run``),
so ``torch.autograd.grad`` and ``torch.autograd.gradcheck`` (float64) work. Inputs are
read stop-gradient where upstream reads them so: a field's network reads ``xyz``
detached (only the 6-DoF warp passes a gradient to ``xyz``), the loss treats ``gt`` as a
constant, the rasterizer's settings (matrices, camera, background) get no gradient.
``gradcheck`` w.r.t. a field's ``xyz`` therefore does not apply: the analytic ``grad_xyz``
is upstream's (none, or ``(Rᵀ − I)·g`` through the 6-DoF warp), not the derivative of the
network's output w.r.t. ``xyz``. The tensors a backward reads are saved with
``save_for_backward``: changing one in place between forward and backward raises
``RuntimeError`` in backward, as torch's own functions do, naming the argument.
"""

from __future__ import annotations

import weakref
from typing import Any, Dict, List, Mapping, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import nn
from torch.autograd.function import once_differentiable

from . import _native
from . import gsplat as _gs
from . import _cfc_config, _init_weights, _mlp_config, _metadata, _run_case
from . import CfCField as _NpCfCField
from . import DeformNetwork as _NpDeformNetwork
from . import loss as _np_loss
from . import rasterize as _np_rasterize
from . import rasterize_vjp as _np_rasterize_vjp

__all__ = [
    "GaussianRasterizationSettings",
    "GaussianRasterizer",
    "rasterize_gaussians",
    "DeformNetwork",
    "CfCField",
    "loss",
    "rasterization",
    "rasterize_to_pixels",
]


def _np(name: str, t: Any) -> Any:
    """A CPU tensor as a C-order numpy array (a copy only if not contiguous)."""
    if t is None:
        return None
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"argument `{name}`: expected a torch.Tensor, found {type(t).__name__}")
    if t.device.type != "cpu":
        raise ValueError(
            f"argument `{name}`: expected a CPU tensor (the oracle runs on the CPU), "
            f"found device {t.device}"
        )
    try:
        return t.detach().contiguous().numpy()
    except TypeError:  # a dtype numpy has no equivalent of (bfloat16, ...)
        raise TypeError(
            f"argument `{name}`: expected dtype torch.float32 or torch.float64, found {t.dtype}"
        ) from None


def _t(a: Optional[np.ndarray]) -> Optional[torch.Tensor]:
    return None if a is None else torch.from_numpy(a)


# ---------------------------------------------------------------------------
# Rasterizer
# ---------------------------------------------------------------------------


class GaussianRasterizationSettings(NamedTuple):
    """Inria's ``GaussianRasterizationSettings`` (same fields, same order). ``prefiltered``
    and ``debug`` are accepted and have no effect on the results. ``image_height``,
    ``image_width`` and ``sh_degree`` are ints, ``tanfovx``, ``tanfovy`` and
    ``scale_modifier`` floats (Python or numpy scalars, or 0-d tensors): a string, a bool or
    a fractional size is refused (``TypeError``), never rounded."""

    image_height: int
    image_width: int
    tanfovx: float
    tanfovy: float
    bg: torch.Tensor
    scale_modifier: float
    viewmatrix: torch.Tensor
    projmatrix: torch.Tensor
    sh_degree: int
    campos: torch.Tensor
    prefiltered: bool = False
    debug: bool = False


_SETTINGS_TENSORS = ("viewmatrix", "projmatrix", "campos", "bg")


def _setting(s: Any, name: str, integer: bool) -> Any:
    """A number of the settings as given (an int, a float, a numpy scalar or a 0-d tensor's
    value), never converted: ``rasterize`` checks its range. Bools and strings are refused."""
    v = getattr(s, name)
    if isinstance(v, torch.Tensor) and v.dim() == 0:
        v = v.item()
    kinds = (int, np.integer) if integer else (int, float, np.integer, np.floating)
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, kinds):
        raise TypeError(
            f"rasterize_gaussians(): argument `raster_settings.{name}`: expected "
            f"{'an int' if integer else 'a float'}, found {type(v).__name__}"
        )
    return v


def _settings_kwargs(s: Any) -> Dict[str, Any]:
    kw = {n: _np(f"raster_settings.{n}", getattr(s, n)) for n in _SETTINGS_TENSORS}
    kw.update(
        image_height=_setting(s, "image_height", True),
        image_width=_setting(s, "image_width", True),
        tanfovx=_setting(s, "tanfovx", False),
        tanfovy=_setting(s, "tanfovy", False),
        scale_modifier=_setting(s, "scale_modifier", False),
    )
    return kw


def _means2D(means3D: Any, means2D: Any) -> None:
    """Inria's screenspace points: None or a CPU tensor of ``means3D``'s shape [N,3] (it
    receives the gradient, its values are not read)."""
    where = "rasterize_gaussians(): argument `means2D`"
    if means2D is None:
        return
    if not isinstance(means2D, torch.Tensor):
        raise TypeError(
            f"{where}: expected a torch.Tensor of shape [N,3] (Inria's screenspace points) or "
            f"None, found {type(means2D).__name__}"
        )
    n = means3D.shape[0] if isinstance(means3D, torch.Tensor) and means3D.dim() == 2 else None
    if means2D.dim() != 2 or means2D.shape[1] != 3 or (n is not None and means2D.shape[0] != n):
        note = "" if n is None else f" with N={n} from `means3D`"
        raise ValueError(
            f"{where}: expected shape [N,3]{note} (Inria's screenspace points), found shape "
            f"[{','.join(str(d) for d in means2D.shape)}]"
        )
    if means2D.device.type != "cpu":
        raise ValueError(f"{where}: expected a CPU tensor, found device {means2D.device}")


_RASTER_INPUTS = (
    "means3D", "means2D", "shs", "colors_precomp", "opacities", "scales", "rotations",
    "cov3D_precomp",
)


def _save(ctx: Any, func: str, named: Sequence[Tuple[str, Optional[torch.Tensor]]]) -> None:
    """``ctx.save_for_backward`` of the tensors, remembering each one's name and version so
    that :func:`_saved` can name the ones changed in place."""
    ctx.save_for_backward(*(t for _, t in named))
    ctx.saved_func = func
    # (Tensors made under ``torch.inference_mode`` have no version counter, and cannot be
    # changed in place outside it.)
    ctx.saved_names = [(n, weakref.ref(t), t._version) for n, t in named
                       if t is not None and not t.is_inference()]


def _saved(ctx: Any) -> Tuple[Any, ...]:
    """``ctx.saved_tensors``; when torch refuses them because one was changed in place, its
    ``RuntimeError`` names the arguments whose version moved."""
    try:
        return ctx.saved_tensors
    except RuntimeError as e:
        changed = [n for n, ref, v in ctx.saved_names if ref() is not None and ref()._version != v]
        # Only torch's version-counter error is about them (a second backward through a
        # freed graph, say, is not, even when an optimizer step has changed them since).
        if not changed or "modified by an inplace operation" not in str(e):
            raise
        them = "them" if len(changed) > 1 else "it"
        raise RuntimeError(f"{ctx.saved_func}: backward: {', '.join(changed)} changed in place "
                           f"after the forward, which saved {them} for the backward ({e})") from e


# The tensors the rasterizer's backward reads again: the Gaussians', then the settings'.
_RASTER_SAVED = ("means3D", "opacities", "shs", "colors_precomp", "scales", "rotations",
                 "cov3D_precomp") + _SETTINGS_TENSORS


class _RasterizeGaussians(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means3D, means2D, shs, colors_precomp, opacities, scales, rotations,
                cov3D_precomp, raster_settings):
        _means2D(means3D, means2D)
        arrays = dict(
            means3D=_np("means3D", means3D),
            opacities=_np("opacities", opacities),
            shs=_np("shs", shs),
            colors_precomp=_np("colors_precomp", colors_precomp),
            scales=_np("scales", scales),
            rotations=_np("rotations", rotations),
            cov3D_precomp=_np("cov3D_precomp", cov3D_precomp),
        )
        kw = _settings_kwargs(raster_settings)
        sh_degree = _setting(raster_settings, "sh_degree", True) if shs is not None else None
        r = _np_rasterize(**arrays, **kw, sh_degree=sh_degree)
        inputs = dict(means3D=means3D, opacities=opacities, shs=shs,
                      colors_precomp=colors_precomp, scales=scales, rotations=rotations,
                      cov3D_precomp=cov3D_precomp)
        _save(ctx, "GaussianRasterizer",
              [*((n, inputs[n]) for n in _RASTER_SAVED[:7]),
               *((f"raster_settings.{n}", getattr(raster_settings, n)) for n in _SETTINGS_TENSORS)])
        ctx.numbers = {k: v for k, v in kw.items() if k not in _SETTINGS_TENSORS}
        ctx.sh_degree = sh_degree
        ctx.present = [x is not None for x in
                       (means3D, means2D, shs, colors_precomp, opacities, scales, rotations,
                        cov3D_precomp)]
        radii = torch.from_numpy(r.radii)
        ctx.mark_non_differentiable(radii)
        return torch.from_numpy(r.color), radii, torch.from_numpy(r.depth)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_color, grad_radii, grad_depth):
        saved = {n: _np(n, x) for n, x in zip(_RASTER_SAVED, _saved(ctx))}
        g = _np_rasterize_vjp(
            **saved, **ctx.numbers, sh_degree=ctx.sh_degree,
            grad_color=_np("grad_color", grad_color),
            grad_depth=_np("grad_depth", grad_depth),
            gradient="exact",
        )
        out: List[Optional[torch.Tensor]] = []
        for name, present in zip(_RASTER_INPUTS, ctx.present):
            key = "grad_means2D" if name == "means2D" else f"grad_{name}"
            out.append(_t(g.get(key)) if present else None)
        return (*out, None)


def rasterize_gaussians(means3D, means2D, sh, colors_precomp, opacities, scales, rotations,
                        cov3Ds_precomp, raster_settings):
    """Inria's ``rasterize_gaussians`` (same arguments, same order): ``(color, radii,
    depth)``. Pass ``None`` (or ``torch.Tensor([])``, the 1-D empty tensor Inria's wrapper
    passes) for unused inputs; any other empty tensor is an input with N = 0 Gaussians
    (the image is then the background). ``means2D``: None or a tensor of shape [N,3]."""

    def opt(x):
        absent = isinstance(x, torch.Tensor) and x.dim() == 1 and x.numel() == 0
        return None if absent else x

    return _RasterizeGaussians.apply(
        means3D, means2D, opt(sh), opt(colors_precomp), opacities, opt(scales),
        opt(rotations), opt(cov3Ds_precomp), raster_settings,
    )


class GaussianRasterizer(nn.Module):
    """Inria's ``GaussianRasterizer``: ``forward(means3D, means2D, opacities, shs=None,
    colors_precomp=None, scales=None, rotations=None, cov3D_precomp=None)`` →
    ``(color [3,H,W], radii [N], depth [1,H,W])``."""

    def __init__(self, raster_settings: GaussianRasterizationSettings):
        super().__init__()
        self.raster_settings = raster_settings

    def markVisible(self, positions: torch.Tensor) -> torch.Tensor:
        """Inria's frustum test: view-space z > 0.2 (``in_frustum``)."""
        with torch.no_grad():
            v = self.raster_settings.viewmatrix.to(positions.dtype)
            z = positions @ v[:3, 2] + v[3, 2]
            return z > 0.2

    def forward(self, means3D, means2D, opacities, shs=None, colors_precomp=None, scales=None,
                rotations=None, cov3D_precomp=None):
        if (shs is None and colors_precomp is None) or (shs is not None and colors_precomp is not None):
            raise ValueError("Please provide exactly one of either SHs or precomputed colors!")
        if ((scales is None or rotations is None) and cov3D_precomp is None) or (
            (scales is not None or rotations is not None) and cov3D_precomp is not None
        ):
            raise ValueError(
                "Please provide exactly one of either scale/rotation pair or precomputed 3D covariance!"
            )
        return rasterize_gaussians(means3D, means2D, shs, colors_precomp, opacities, scales,
                                   rotations, cov3D_precomp, self.raster_settings)


# ---------------------------------------------------------------------------
# Deformation fields
# ---------------------------------------------------------------------------


def _deform_case(names: Sequence[str], xyz: Any, t: Any, params: Sequence[Any]) -> Dict[str, np.ndarray]:
    case: Dict[str, np.ndarray] = {"xyz": _np("xyz", xyz), "t": _np("t", t)}
    case.update({n: _np(n, p) for n, p in zip(names, params)})
    return case


class _Deform(torch.autograd.Function):
    @staticmethod
    def forward(ctx, config, names, xyz, t, *params):
        case = _deform_case(names, xyz, t, params)
        meta = {"stage": "deform", **config}
        func = "CfCField" if config["field"] == "cfc" else "DeformNetwork"
        out, _ = _run_case(f"{func}.forward", case, meta, None)
        _save(ctx, func, [("x", xyz), ("t", t), *zip(names, params)])
        ctx.meta, ctx.names, ctx.func = meta, names, func
        return (torch.from_numpy(out["d_xyz"]), torch.from_numpy(out["d_rotation"]),
                torch.from_numpy(out["d_scaling"]))

    @staticmethod
    @once_differentiable
    def backward(ctx, g_xyz, g_rot, g_scale):
        xyz, t, *params = _saved(ctx)
        case = _deform_case(ctx.names, xyz, t, params)
        case["grad_d_xyz"] = _np("grad_d_xyz", g_xyz)
        case["grad_d_rotation"] = _np("grad_d_rotation", g_rot)
        case["grad_d_scaling"] = _np("grad_d_scaling", g_scale)
        out, _ = _run_case(f"{ctx.func}.vjp", case, ctx.meta, None)
        grad_xyz = _t(out.get("grad_xyz"))
        grad_t = torch.from_numpy(out["grad_t"])
        return (None, None, grad_xyz, grad_t,
                *(torch.from_numpy(out[f"grad.{n}"]) for n in ctx.names))


class _FieldModule(nn.Module):
    """A field whose parameters are registered under upstream's state_dict names."""

    _config: Dict[str, Any]

    def _build(self, config: Dict[str, Any], seed: int, dtype: torch.dtype) -> None:
        self._config = dict(config)
        name = {torch.float32: "float32", torch.float64: "float64"}.get(dtype)
        if name is None:
            raise TypeError(f"argument `dtype`: expected torch.float32 or torch.float64, found {dtype}")
        weights = _init_weights(type(self).__name__, self._config, seed, name)
        for key in sorted(weights):
            *path, leaf = key.split(".")
            module: nn.Module = self
            for part in path:
                child = module._modules.get(part)
                if child is None:
                    child = nn.Module()
                    module.add_module(part, child)
                module = child
            module.register_parameter(leaf, nn.Parameter(torch.from_numpy(weights[key])))

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(d_xyz, d_rotation, d_scaling)`` at canonical centres ``x`` [N,3] and time
        ``t`` [N,1]. With the 6-DoF MLP, ``d_xyz`` is the offset ``R·x + p − x`` that
        upstream's renderer applies (its network returns the transform; see
        :meth:`transform`)."""
        names, params = zip(*self.named_parameters())
        return _Deform.apply(self._config, list(names), x, t, *params)

    def transform(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """6-DoF MLP only: the [N,4,4] SE(3) transform upstream's network returns
        (not differentiable here; differentiate through :meth:`forward`)."""
        if not self._config.get("is_6dof"):
            raise ValueError("transform(): only the 6-DoF DeformNetwork returns a transform")
        sd = {k: _np(k, v) for k, v in self.state_dict().items()}
        field = _NpDeformNetwork(sd)
        tt = _np("t", t)
        return torch.from_numpy(field.forward(_np("x", x), tt).d_xyz_se3)

    @property
    def param_count(self) -> int:
        return int(_native.field_counts(_metadata(self._config))["params"])

    def macs(self, convention: str = "pytorch") -> int:
        """MACs per Gaussian as ptflops counts them (``aten``, ``pytorch``,
        ``pytorch_no_functional``)."""
        key = f"macs_{convention}"
        counts = _native.field_counts(_metadata(self._config))
        if key not in counts:
            raise ValueError(
                "macs(): argument `convention`: expected 'aten', 'pytorch' or "
                f"'pytorch_no_functional', found {convention!r}"
            )
        return int(counts[key])

    def extra_repr(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self._config.items() if k != "field")


class DeformNetwork(_FieldModule):
    """D-3DGS's ``DeformNetwork`` with upstream's constructor: ``is_blender=True`` is the
    synthetic variant (timenet), ``is_6dof`` the SE(3) variant. Its ``state_dict`` keys
    are ``deform.pth``'s: ``m.load_state_dict(torch.load("deform.pth"))`` works as is.
    Weights start from the oracle's seeded ``nn.Linear``-default initialisation."""

    def __init__(self, D: int = 8, W: int = 256, input_ch: int = 3, output_ch: int = 59,
                 multires: int = 10, is_blender: bool = False, is_6dof: bool = False, *,
                 seed: int = 0, dtype: torch.dtype = torch.float32):
        super().__init__()
        if (input_ch, output_ch, multires) != (3, 59, 10):
            raise ValueError(
                "DeformNetwork: expected input_ch=3, output_ch=59, multires=10 (the values "
                f"D-3DGS uses), found {input_ch}, {output_ch}, {multires}"
            )
        self._build(_mlp_config("DeformNetwork", D, W, is_blender, is_6dof), seed, dtype)

    @classmethod
    def from_state_dict(cls, state_dict: Mapping[str, torch.Tensor]) -> "DeformNetwork":
        """The network a ``deform.pth`` state_dict describes (sizes read from its keys and
        shapes), with those weights."""
        if not isinstance(state_dict, Mapping):
            raise TypeError(f"{cls.__name__}.from_state_dict(): argument `state_dict`: expected a "
                            f"dict, found {type(state_dict).__name__}")
        sd = {k: _np(k, v) for k, v in state_dict.items()}
        c = _NpDeformNetwork(sd).config
        dtype = torch.float64 if next(iter(sd.values())).dtype == np.float64 else torch.float32
        m = cls(D=int(c["depth"]), W=int(c["width"]), is_blender=c["variant"] == "synthetic",
                is_6dof=bool(c["is_6dof"]), dtype=dtype)
        m.load_state_dict(state_dict)
        return m


class CfCField(_FieldModule):
    """The liquid field (``D`` stacked ``ncps.torch.CfCCell``s of width ``W``), with the
    constructor of ``python/reference_deform.py``; ``state_dict`` keys as there
    (``cells.L.backbone.0.weight``, ..., ``skip.*``, ``head.*``, ``timenet.*``)."""

    def __init__(self, D: int = 6, W: int = 128, variant: str = "synthetic",
                 activation: str = "gelu", backbone_units: int = 64, backbone_layers: int = 2,
                 *, seed: int = 0, dtype: torch.dtype = torch.float32):
        super().__init__()
        self._build(_cfc_config("CfCField", D, W, variant, activation, backbone_units,
                                backbone_layers), seed, dtype)

    @classmethod
    def from_state_dict(cls, state_dict: Mapping[str, torch.Tensor],
                        activation: str = "gelu") -> "CfCField":
        """The field a state_dict describes (sizes from its keys and shapes; the
        activation is not stored, so give it), with those weights."""
        if not isinstance(state_dict, Mapping):
            raise TypeError(f"{cls.__name__}.from_state_dict(): argument `state_dict`: expected a "
                            f"dict, found {type(state_dict).__name__}")
        sd = {k: _np(k, v) for k, v in state_dict.items()}
        c = _NpCfCField(sd, activation).config
        dtype = torch.float64 if next(iter(sd.values())).dtype == np.float64 else torch.float32
        m = cls(D=int(c["depth"]), W=int(c["width"]), variant=str(c["variant"]),
                activation=activation, backbone_units=int(c["backbone_units"]),
                backbone_layers=int(c["backbone_layers"]), dtype=dtype)
        m.load_state_dict(state_dict)
        return m


# ---------------------------------------------------------------------------
# Loss
# ---------------------------------------------------------------------------


class _Loss(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image, gt, lambda_dssim):
        out = _np_loss(_np("image", image), _np("gt", gt), lambda_dssim)
        ctx.grad_image = torch.from_numpy(out["grad_image"])
        return torch.from_numpy(out["loss"])

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        return g * ctx.grad_image, None, None


def loss(image: torch.Tensor, gt: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """D-3DGS's ``(1 − λ)·l1_loss(image, gt) + λ·(1 − ssim(image, gt))`` of [3,H,W]
    images, differentiable w.r.t. ``image``. ``lambda_dssim``: a float in [0, 1] (a Python
    or numpy scalar, or a 0-d tensor)."""
    if isinstance(lambda_dssim, torch.Tensor) and lambda_dssim.dim() == 0:
        lambda_dssim = lambda_dssim.item()
    # Passed as given: the numpy loss refuses (and names) a bool, a string, a number out of range.
    return _Loss.apply(image, gt, lambda_dssim)


# ---------------------------------------------------------------------------
# gsplat
# ---------------------------------------------------------------------------

_GS_RASTERIZATION_INPUTS = ("means", "quats", "scales", "covars", "opacities", "colors",
                            "backgrounds")


class _GsRasterization(torch.autograd.Function):
    @staticmethod
    def forward(ctx, holder, kw, means, quats, scales, covars, opacities, colors, backgrounds,
                viewmats, Ks):
        inputs = (means, quats, scales, covars, opacities, colors, backgrounds, viewmats, Ks)
        arrays = {n: _np(n, x) for n, x in zip(_GS_RASTERIZATION_INPUTS + ("viewmats", "Ks"),
                                                inputs)}
        r = _gs.rasterization(**arrays, **kw)
        holder.update(r.meta)
        _save(ctx, "rasterization", list(zip(_GS_RASTERIZATION_INPUTS + ("viewmats", "Ks"), inputs)))
        ctx.kw = kw
        ctx.present = [arrays[n] is not None for n in _GS_RASTERIZATION_INPUTS]
        return torch.from_numpy(r.render_colors), torch.from_numpy(r.render_alphas)

    @staticmethod
    @once_differentiable
    def backward(ctx, v_render_colors, v_render_alphas):
        arrays = {n: _np(n, x) for n, x in zip(_GS_RASTERIZATION_INPUTS + ("viewmats", "Ks"),
                                                _saved(ctx))}
        g = _gs.rasterization_vjp(
            **arrays, **ctx.kw,
            v_render_colors=_np("v_render_colors", v_render_colors),
            v_render_alphas=_np("v_render_alphas", v_render_alphas),
        )
        out = [_t(g.get(f"v_{n}")) if p else None
               for n, p in zip(_GS_RASTERIZATION_INPUTS, ctx.present)]
        return (None, None, *out, None, None)


def rasterization(
    means: torch.Tensor,
    quats: Optional[torch.Tensor],
    scales: Optional[torch.Tensor],
    opacities: torch.Tensor,
    colors: torch.Tensor,
    viewmats: torch.Tensor,
    Ks: torch.Tensor,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Optional[torch.Tensor] = None,
    render_mode: str = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    channel_chunk: int = 32,
    distributed: bool = False,
    camera_model: str = "pinhole",
    segmented: bool = False,
    covars: Optional[torch.Tensor] = None,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tuple[torch.Tensor, torch.Tensor, Dict[str, Any]]:
    """gsplat's ``rasterization`` (same arguments, same order, same defaults):
    ``(render_colors [C,H,W,D], render_alphas [C,H,W,1], meta)``, differentiable w.r.t.
    ``means``, ``quats``, ``scales`` (or ``covars``), ``opacities``, ``colors`` and
    ``backgrounds`` (``viewmats`` and ``Ks`` get no gradient). ``meta`` holds tensors
    that carry no gradient; ``meta["means2d"]``'s gradient is ``v_means2d`` of
    :func:`liquid_splat.gsplat.rasterization_vjp`."""
    kw = dict(width=width, height=height, near_plane=near_plane, far_plane=far_plane,
              radius_clip=radius_clip, eps2d=eps2d, sh_degree=sh_degree, packed=packed,
              tile_size=tile_size, render_mode=render_mode, sparse_grad=sparse_grad,
              absgrad=absgrad, rasterize_mode=rasterize_mode, channel_chunk=channel_chunk,
              distributed=distributed, camera_model=camera_model, segmented=segmented,
              version=version, gradient=gradient, threads=threads)
    holder: Dict[str, Any] = {}
    render_colors, render_alphas = _GsRasterization.apply(
        holder, kw, means, quats, scales, covars, opacities, colors, backgrounds, viewmats, Ks)
    meta = {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v
            for k, v in holder.items()}
    return render_colors, render_alphas, meta


_GS_R2P_INPUTS = ("means2d", "conics", "colors", "opacities", "backgrounds")


class _GsRasterizeToPixels(torch.autograd.Function):
    @staticmethod
    def forward(ctx, kw, means2d, conics, colors, opacities, backgrounds, isect_offsets,
                flatten_ids):
        inputs = (means2d, conics, colors, opacities, backgrounds, isect_offsets, flatten_ids)
        arrays = {n: _np(n, x) for n, x in zip(_GS_R2P_INPUTS + ("isect_offsets", "flatten_ids"),
                                                inputs)}
        rc, ra = _gs.rasterize_to_pixels(**arrays, **kw)
        _save(ctx, "rasterize_to_pixels",
              list(zip(_GS_R2P_INPUTS + ("isect_offsets", "flatten_ids"), inputs)))
        ctx.kw = kw
        ctx.has_bg = backgrounds is not None
        return torch.from_numpy(rc), torch.from_numpy(ra)

    @staticmethod
    @once_differentiable
    def backward(ctx, v_render_colors, v_render_alphas):
        arrays = {n: _np(n, x) for n, x in zip(_GS_R2P_INPUTS + ("isect_offsets", "flatten_ids"),
                                                _saved(ctx))}
        g = _gs.rasterize_to_pixels_vjp(
            **arrays, **ctx.kw,
            v_render_colors=_np("v_render_colors", v_render_colors),
            v_render_alphas=_np("v_render_alphas", v_render_alphas),
        )
        out = [_t(g.get(f"v_{n}")) for n in _GS_R2P_INPUTS[:4]]
        return (None, *out, _t(g.get("v_backgrounds")) if ctx.has_bg else None, None, None)


def rasterize_to_pixels(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    colors: torch.Tensor,
    opacities: torch.Tensor,
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: torch.Tensor,
    flatten_ids: torch.Tensor,
    backgrounds: Optional[torch.Tensor] = None,
    masks: None = None,
    packed: bool = False,
    absgrad: bool = False,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tuple[torch.Tensor, torch.Tensor]:
    """gsplat's ``rasterize_to_pixels`` (same arguments, same order): ``(render_colors,
    render_alphas)``, differentiable w.r.t. ``means2d`` (pixels), ``conics``, ``colors``,
    ``opacities`` and ``backgrounds``. ``isect_offsets`` and ``flatten_ids`` are int32
    tensors (as gsplat's)."""
    kw = dict(image_width=image_width, image_height=image_height, tile_size=tile_size,
              masks=masks, packed=packed, absgrad=absgrad, version=version,
              gradient=gradient, threads=threads)
    return _GsRasterizeToPixels.apply(kw, means2d, conics, colors, opacities, backgrounds,
                                      isect_offsets, flatten_ids)
