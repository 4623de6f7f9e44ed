"""liquid-splat in-process: the deterministic CPU oracle of deformable 3D Gaussian splatting.

numpy arrays in, numpy arrays out; float32 or float64 inputs select the precision, as in
case files. Every function runs the same Rust code as ``liquid-splat case run`` and gives the
same bits, whatever ``threads`` is.

- :func:`rasterize` / :func:`rasterize_vjp`: the Inria rasterizer (``GaussianRasterizer``
  inputs and settings) and every gradient.
- :class:`DeformNetwork` (D-3DGS MLP, incl. 6-DoF) and :class:`CfCField` (the liquid field),
  built from a state_dict, with ``forward`` / ``vjp`` and parameter and MAC counts.
- :func:`loss`, :func:`step`: the training loss and one whole training iteration.
- :mod:`liquid_splat.gsplat`: gsplat's functions (``rasterization``, ``rasterize_to_pixels``,
  ``fully_fused_projection``, ...) with gsplat's names and conventions, at gsplat 1.5.3 or
  1.6, and their vjps.
- :func:`run_case`: any stage from case-file tensors and metadata.
- :func:`load` / :func:`save`: case files (safetensors) without other packages.
- :mod:`liquid_splat.testing`: ``compare`` and ``assert_close`` (the ``case compare`` report).
- :mod:`liquid_splat.torch`: autograd wrappers and drop-in modules (needs torch).
- ``python -m liquid_splat ...``: the command-line tool.
"""

from __future__ import annotations

import math
import os
import re
from typing import Any, Dict, Mapping, NamedTuple, Optional, Tuple, Union

import numpy as np

from . import _native

__version__: str = _native.__version__

__all__ = [
    "__version__",
    "STAGES",
    "run_case",
    "load",
    "save",
    "rasterize",
    "rasterize_vjp",
    "RasterizeResult",
    "DeformNetwork",
    "CfCField",
    "DeformResult",
    "load_field",
    "loss",
    "step",
    "cli",
    "gsplat",
]

STAGES: Tuple[str, ...] = tuple(_native.STAGES)

Tensors = Dict[str, np.ndarray]
MetaValue = Union[str, bool, int, float]
PathLike = Union[str, "os.PathLike[str]"]

_FLOATS = (np.dtype(np.float32), np.dtype(np.float64))

#: The largest ``threads`` (the CLI's ``--threads`` range is 1..=1024).
_MAX_THREADS = 1024

#: The library's size limits (docs/ORACLE.md, "Sizes are bounded"): pixels of an image (the
#: gsplat stages: over all images), a side of a gsplat image, a gsplat tile's side.
_MAX_PIXELS = 1 << 26
_MAX_SIDE = 65536
_MAX_TILE_SIZE = 1024


def _meta_value(v: Any) -> Any:
    """A metadata value as the string a case file stores: bools as ``true``/``false`` (what
    the library parses), integers exactly, floats by ``repr`` (round-trips); numpy scalars
    alike. Anything else is passed on for the library to refuse, naming the key."""
    if isinstance(v, (bool, np.bool_)):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return v


def _meta_text(k: Any, v: Any) -> Any:
    """A str metadata value the library can read (UTF-8); others as :func:`_meta_value`."""
    v = _meta_value(v)
    if isinstance(v, str):
        try:
            v.encode("utf-8")
        except UnicodeEncodeError as e:
            raise ValueError(
                f"metadata[{k!r}]: expected UTF-8 text, found {v!r} ({e.reason} at position {e.start})"
            ) from None
    return v


def _metadata(metadata: Mapping[Any, Any]) -> Dict[Any, Any]:
    return {k: _meta_text(k, v) for k, v in metadata.items()}


def _mapping(func: str, name: str, x: Any) -> Dict[Any, Any]:
    """A dict argument (tensors, metadata) as a new dict; anything else is a ``TypeError``
    naming the argument."""
    if not isinstance(x, Mapping):
        raise TypeError(f"{func}(): argument `{name}`: expected a dict, found {type(x).__name__}")
    return dict(x)


def _float_dtype(func: str, name: str, dtype: Any) -> np.dtype:
    """float32 or float64 from anything ``numpy.dtype`` reads; anything else is a
    ``TypeError`` naming the argument."""
    where = f"{func}(): argument `{name}`"
    try:
        dt = np.dtype(dtype)
    except (TypeError, ValueError):
        raise TypeError(f"{where}: expected float32 or float64, found {dtype!r}") from None
    if dt not in _FLOATS:
        raise TypeError(f"{where}: expected float32 or float64, found {dt}")
    return dt


def _threads(func: str, threads: Any) -> Optional[int]:
    """``threads``: None (all cores) or an integer in 1..=1024 (the CLI's `--threads`)."""
    if threads is None:
        return None
    return _Args(func).integer("threads", threads, 1, _MAX_THREADS)


def _seed(func: str, seed: Any) -> int:
    return _Args(func).integer("seed", seed, 0, 2**64 - 1)


def _run_case(
    func: str, tensors: Mapping[str, np.ndarray], metadata: Mapping[str, Any], threads: Any
) -> Tuple[Tensors, Dict[str, str]]:
    tensors = _mapping(func, "tensors", tensors)
    metadata = _mapping(func, "metadata", metadata)
    return _native.run_case(tensors, _metadata(metadata), _threads(func, threads))


def _path(func: str, name: str, x: Any, what: str = "a path") -> str:
    """A path argument as the ``str`` the library opens: a ``str``, ``bytes`` or
    ``os.PathLike``. A name the file system cannot encode (a lone surrogate such as
    ``"\\ud800"``) is a ``ValueError`` naming the argument; ``what`` says what was expected."""
    where = f"{func}(): argument `{name}`"
    try:
        p = os.fspath(x)
    except TypeError:
        raise TypeError(
            f"{where}: expected {what} (str, bytes or os.PathLike), found {type(x).__name__}"
        ) from None
    if isinstance(p, bytes):
        p = os.fsdecode(p)
    try:
        os.fsencode(p)
    except UnicodeEncodeError as e:
        raise ValueError(
            f"{where}: expected {what} the file system can encode, found {p!r} "
            f"({e.reason} at position {e.start})"
        ) from None
    return p


# A library error about a file that the operating system refused: "PATH: REASON (os error N)".
_OS_ERROR = re.compile(r"(?P<path>.*): (?P<reason>[^:]*) \(os error (?P<code>\d+)\)", re.S)


def _os_error(e: ValueError) -> Exception:
    """The ``OSError`` subclass (``FileNotFoundError``, ``IsADirectoryError``,
    ``PermissionError``, ...) of an operating-system failure, ``e`` itself otherwise."""
    m = _OS_ERROR.fullmatch(str(e))
    if m is None:
        return e
    code = int(m["code"])
    if os.name == "nt":  # the code is a Windows error code; OSError maps it to errno
        return OSError(None, m["reason"], m["path"], code)
    return OSError(code, m["reason"], m["path"])


# ---------------------------------------------------------------------------
# Case level
# ---------------------------------------------------------------------------


def run_case(
    tensors: Mapping[str, np.ndarray],
    metadata: Mapping[str, MetaValue],
    *,
    threads: Optional[int] = None,
) -> Tuple[Tensors, Dict[str, str]]:
    """Run the stage ``metadata["stage"]`` names on case-file tensors.

    Returns ``(outputs, output_metadata)``: bit for bit what ``liquid-splat case run``
    writes for a case file holding ``tensors`` and ``metadata`` (docs/ORACLE.md lists every
    stage's tensor names and metadata keys). Metadata values may be ``str``, ``bool``,
    ``int`` or ``float`` or numpy scalars (integers are written exactly, bools as
    ``true``/``false``, floats in the shortest form that round-trips). ``threads``: worker
    threads for this call, 1 to 1024 (default: all cores); results do not depend on it.
    """
    return _run_case("run_case", tensors, metadata, threads)


def load(path: PathLike) -> Tuple[Tensors, Dict[str, str]]:
    """Read a safetensors file (F32, F64, I32, I64 tensors): ``(tensors, metadata)``.

    A file the operating system cannot open raises the matching ``OSError``
    (``FileNotFoundError``, ``IsADirectoryError``, ``PermissionError``, ...); a file that
    is not a usable safetensors file raises ``ValueError`` (``TypeError`` for a dtype)."""
    path = _path("load", "path", path)
    try:
        return _native.load(path)
    except ValueError as e:
        err = _os_error(e)
        if err is e:
            raise
        raise err from None


def save(
    path: PathLike,
    tensors: Mapping[str, np.ndarray],
    metadata: Optional[Mapping[str, MetaValue]] = None,
) -> None:
    """Write tensors (float32, float64, int32, int64; C order) and metadata as a safetensors file.

    Metadata values as in :func:`run_case`. Bad tensors or metadata raise ``TypeError`` or
    ``ValueError``; a file the operating system refuses (a missing folder, a directory, no
    permission) raises the matching ``OSError`` subclass."""
    path = _path("save", "path", path)
    tensors = _mapping("save", "tensors", tensors)
    meta = None if metadata is None else _metadata(_mapping("save", "metadata", metadata))
    try:
        _native.save(path, tensors, meta)
    except ValueError as e:
        err = _os_error(e)
        if err is e:
            raise
        raise err from None


def cli(*args: Union[str, bytes, "os.PathLike[str]"]) -> int:
    """Run the ``liquid-splat`` command-line tool in-process; returns its exit code.

    Arguments are passed as a process's arguments are (``str`` encoded as ``os.fsencode``
    does, ``bytes`` as they are), so the tool sees what the ``liquid-splat`` binary would.
    A standard output that cannot be written raises ``BrokenPipeError`` (closed) or
    ``OSError``, as Python's ``print`` does.

    The tool writes to file descriptors 1 and 2 directly, not through ``sys.stdout``: in
    pytest, capture it with ``capfd`` (``capsys`` sees nothing). ``--pin-threads`` starts the
    process's global worker pool pinned (unless an earlier call started it), and every later
    call with ``threads=None`` in this process runs on that pinned pool."""
    argv = [_path("cli", f"args[{i}]", a, "an argument") for i, a in enumerate(args)]
    return _native.cli(argv)


def _not_masked(where: str, x: Any) -> None:
    """Refuse a ``numpy.ma`` array: its mask would be dropped without a word."""
    if isinstance(x, np.ma.MaskedArray):
        raise TypeError(
            f"{where}: expected a numpy.ndarray, found a masked array (numpy.ma), whose mask "
            "the oracle cannot take: pass .filled(value) or .data"
        )


def _shape(shape: Tuple[int, ...]) -> str:
    return "[" + ",".join(str(d) for d in shape) + "]"


# ---------------------------------------------------------------------------
# Argument checks: name the argument, what was expected and what was found.
# ---------------------------------------------------------------------------


class _Args:
    """Checks the arrays of one call: type, dtype (one float dtype for all), C order,
    shape (with named dimensions bound by the first array that uses them), finiteness."""

    def __init__(self, func: str):
        self.func = func
        self.dtype: Optional[np.dtype] = None
        self.dtype_from = ""
        self.dims: Dict[str, Tuple[int, str]] = {}

    def check_shape(
        self, where: str, name: str, x: np.ndarray, shape: Tuple[Union[int, str], ...]
    ) -> None:
        """Check ``x.shape`` against ``shape``; a named dimension seen for the first time is
        bound to this array's size."""
        want = "[" + ",".join(str(d) for d in shape) + "]"
        if x.ndim != len(shape):
            raise ValueError(f"{where}: expected shape {want}, found shape {_shape(x.shape)}")
        for d, n in zip(shape, x.shape):
            if isinstance(d, int):
                ok, note = (n == d), ""
            elif d in self.dims:
                size, src = self.dims[d]
                ok, note = (n == size), f" with {d}={size} from `{src}`"
            else:
                self.dims[d] = (n, name)
                ok, note = True, ""
            if not ok:
                raise ValueError(
                    f"{where}: expected shape {want}{note}, found shape {_shape(x.shape)}"
                )

    def array(self, name: str, x: Any, shape: Tuple[Union[int, str], ...]) -> np.ndarray:
        where = f"{self.func}(): argument `{name}`"
        if not isinstance(x, np.ndarray):
            raise TypeError(
                f"{where}: expected a numpy.ndarray of float32 or float64, found {type(x).__name__}"
            )
        _not_masked(where, x)
        if x.dtype not in _FLOATS:
            raise TypeError(f"{where}: expected dtype float32 or float64, found dtype {x.dtype}")
        if self.dtype is None:
            self.dtype, self.dtype_from = x.dtype, f"`{name}`"
        elif x.dtype != self.dtype:
            raise TypeError(
                f"{where}: expected dtype {self.dtype} (the dtype of {self.dtype_from}), "
                f"found dtype {x.dtype}"
            )
        self.check_shape(where, name, x, shape)
        if not x.flags.c_contiguous:
            raise ValueError(
                f"{where}: expected a C-contiguous array (numpy.ascontiguousarray), "
                f"found a non-contiguous array of shape {_shape(x.shape)}"
            )
        if not np.isfinite(x).all():
            bad = int(np.flatnonzero(~np.isfinite(x.ravel()))[0])
            raise ValueError(
                f"{where}: expected finite values, found {x.ravel()[bad]} at flat index {bad}"
            )
        return x

    def scalar(self, name: str, x: Any, *, positive: bool = False) -> float:
        where = f"{self.func}(): argument `{name}`"
        if isinstance(x, np.ndarray) and x.ndim == 0:
            x = x[()]
        if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)):
            raise TypeError(f"{where}: expected a float, found {type(x).__name__}")
        try:
            v = float(x)
        except OverflowError:  # an int beyond float's range: not finite either
            raise ValueError(
                f"{where}: expected a finite{' positive' if positive else ''} number, found an "
                f"integer of {int(x).bit_length()} bits, beyond float's range"
            ) from None
        if not math.isfinite(v) or (positive and not v > 0):
            raise ValueError(
                f"{where}: expected a finite{' positive' if positive else ''} number, found {v!r}"
            )
        return v

    def integer(self, name: str, x: Any, lo: int, hi: Optional[int] = None) -> int:
        where = f"{self.func}(): argument `{name}`"
        if isinstance(x, np.ndarray) and x.ndim == 0:
            x = x[()]
        if isinstance(x, bool) or not isinstance(x, (int, np.integer)):
            raise TypeError(f"{where}: expected an int, found {type(x).__name__}")
        v = int(x)
        if v < lo or (hi is not None and v > hi):
            rng = f">= {lo}" if hi is None else f"in {lo}..={hi}"
            raise ValueError(f"{where}: expected an integer {rng}, found {v}")
        return v

    def flag(self, name: str, x: Any) -> bool:
        if not isinstance(x, (bool, np.bool_)):
            raise TypeError(f"{self.func}(): argument `{name}`: expected a bool, found {type(x).__name__}")
        return bool(x)

    def string(self, name: str, x: Any) -> str:
        if not isinstance(x, str):
            raise TypeError(f"{self.func}(): argument `{name}`: expected a str, found {type(x).__name__}")
        return x

    def choice(self, name: str, x: Any, options: Tuple[str, ...]) -> str:
        if isinstance(x, np.ndarray) and x.ndim == 0:
            x = x[()]
        if not isinstance(x, str) or x not in options:
            raise ValueError(
                f"{self.func}(): argument `{name}`: expected one of "
                f"{', '.join(repr(o) for o in options)}, found {x!r}"
            )
        return str(x)


# ---------------------------------------------------------------------------
# Rasterizer
# ---------------------------------------------------------------------------


class RasterizeResult(NamedTuple):
    """Forward outputs of the rasterizer (docs/ORACLE.md, stage ``rasterize``)."""

    color: np.ndarray  #: [3,H,W], background composited
    depth: np.ndarray  #: [1,H,W], sum of view-space z·α·T
    radii: np.ndarray  #: [N] int32, 0 for culled Gaussians
    final_T: np.ndarray  #: [H,W] transmittance after the last blended Gaussian
    n_contrib: np.ndarray  #: [H,W] int32, 1-based position of the last blended Gaussian
    means2D: np.ndarray  #: [N,2] pixel-space centres


def _raster_case(
    func: str,
    means3D: np.ndarray,
    opacities: np.ndarray,
    shs: Optional[np.ndarray],
    colors_precomp: Optional[np.ndarray],
    scales: Optional[np.ndarray],
    rotations: Optional[np.ndarray],
    cov3D_precomp: Optional[np.ndarray],
    viewmatrix: np.ndarray,
    projmatrix: np.ndarray,
    campos: np.ndarray,
    bg: np.ndarray,
    image_height: int,
    image_width: int,
    tanfovx: float,
    tanfovy: float,
    scale_modifier: float,
    sh_degree: Optional[int],
    gradient: str,
) -> Tuple[_Args, Tensors, Dict[str, MetaValue]]:
    a = _Args(func)
    t: Tensors = {"means3D": a.array("means3D", means3D, ("N", 3))}
    t["opacities"] = a.array("opacities", opacities, ("N", 1))
    if (shs is None) == (colors_precomp is None):
        raise ValueError(
            f"{func}(): expected exactly one of `shs` and `colors_precomp`, found "
            f"{'both' if shs is not None else 'neither'}"
        )
    meta: Dict[str, MetaValue] = {"stage": "rasterize"}
    if shs is not None:
        t["shs"] = a.array("shs", shs, ("N", "M", 3))
        if sh_degree is None:
            raise ValueError(f"{func}(): argument `sh_degree`: required with `shs`, found None")
        deg = a.integer("sh_degree", sh_degree, 0, 3)
        if (deg + 1) ** 2 > shs.shape[1]:
            raise ValueError(
                f"{func}(): argument `shs`: expected at least (sh_degree+1)^2 = {(deg + 1) ** 2} "
                f"coefficients for sh_degree={deg}, found shape {_shape(shs.shape)}"
            )
        meta["sh_degree"] = deg
    else:
        t["colors_precomp"] = a.array("colors_precomp", colors_precomp, ("N", 3))
        if sh_degree is not None:
            meta["sh_degree"] = a.integer("sh_degree", sh_degree, 0, 3)
    if cov3D_precomp is not None:
        if scales is not None or rotations is not None:
            raise ValueError(
                f"{func}(): expected `cov3D_precomp` or `scales` and `rotations`, found both"
            )
        t["cov3D_precomp"] = a.array("cov3D_precomp", cov3D_precomp, ("N", 6))
    else:
        if scales is None or rotations is None:
            raise ValueError(
                f"{func}(): expected `scales` and `rotations` (or `cov3D_precomp`), found "
                f"{'no `scales`' if scales is None else 'no `rotations`'}"
            )
        t["scales"] = a.array("scales", scales, ("N", 3))
        t["rotations"] = a.array("rotations", rotations, ("N", 4))
    t["viewmatrix"] = a.array("viewmatrix", viewmatrix, (4, 4))
    t["projmatrix"] = a.array("projmatrix", projmatrix, (4, 4))
    t["campos"] = a.array("campos", campos, (3,))
    t["bg"] = a.array("bg", bg, (3,))
    h = meta["image_height"] = a.integer("image_height", image_height, 1, _MAX_PIXELS)
    w = meta["image_width"] = a.integer("image_width", image_width, 1, _MAX_PIXELS)
    if h * w > _MAX_PIXELS:
        raise ValueError(
            f"{func}(): arguments `image_height`, `image_width`: expected at most {_MAX_PIXELS} "
            f"pixels, found {h}x{w} = {h * w}"
        )
    meta["tanfovx"] = a.scalar("tanfovx", tanfovx, positive=True)
    meta["tanfovy"] = a.scalar("tanfovy", tanfovy, positive=True)
    meta["scale_modifier"] = a.scalar("scale_modifier", scale_modifier)
    meta["gradient"] = a.choice("gradient", gradient, ("exact", "inria"))
    return a, t, meta


def rasterize(
    means3D: np.ndarray,
    opacities: np.ndarray,
    shs: Optional[np.ndarray] = None,
    colors_precomp: Optional[np.ndarray] = None,
    scales: Optional[np.ndarray] = None,
    rotations: Optional[np.ndarray] = None,
    cov3D_precomp: Optional[np.ndarray] = None,
    *,
    viewmatrix: np.ndarray,
    projmatrix: np.ndarray,
    campos: np.ndarray,
    bg: np.ndarray,
    image_height: int,
    image_width: int,
    tanfovx: float,
    tanfovy: float,
    scale_modifier: float = 1.0,
    sh_degree: Optional[int] = None,
    threads: Optional[int] = None,
) -> RasterizeResult:
    """The Inria rasterizer's forward (with the depth output of the D-3DGS fork).

    Arguments are ``GaussianRasterizer.forward``'s (``means2D`` aside, which only carries a
    gradient in torch) in its order, then the ``GaussianRasterizationSettings`` fields as
    keywords. ``opacities`` and ``scales`` are activated; ``rotations`` are ``(w,x,y,z)``
    used as given; ``viewmatrix``/``projmatrix`` are Inria's ``world_view_transform`` and
    ``full_proj_transform`` (transposed). Conventions: docs/ORACLE.md, stage ``rasterize``.
    """
    _, t, meta = _raster_case(
        "rasterize", means3D, opacities, shs, colors_precomp, scales, rotations,
        cov3D_precomp, viewmatrix, projmatrix, campos, bg, image_height, image_width,
        tanfovx, tanfovy, scale_modifier, sh_degree, "exact",
    )
    out, _ = _run_case("rasterize", t, meta, threads)
    return RasterizeResult(
        out["color"], out["depth"], out["radii"], out["final_T"], out["n_contrib"], out["means2D"]
    )


def rasterize_vjp(
    means3D: np.ndarray,
    opacities: np.ndarray,
    shs: Optional[np.ndarray] = None,
    colors_precomp: Optional[np.ndarray] = None,
    scales: Optional[np.ndarray] = None,
    rotations: Optional[np.ndarray] = None,
    cov3D_precomp: Optional[np.ndarray] = None,
    *,
    viewmatrix: np.ndarray,
    projmatrix: np.ndarray,
    campos: np.ndarray,
    bg: np.ndarray,
    image_height: int,
    image_width: int,
    tanfovx: float,
    tanfovy: float,
    grad_color: np.ndarray,
    grad_depth: Optional[np.ndarray] = None,
    scale_modifier: float = 1.0,
    sh_degree: Optional[int] = None,
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tensors:
    """Gradients of ``L = Σ color·grad_color + Σ depth·grad_depth`` w.r.t. every input.

    Same arguments as :func:`rasterize`, plus ``grad_color [3,H,W]``, optional
    ``grad_depth [1,H,W]`` and ``gradient`` (``"exact"``: the true derivative; ``"inria"``:
    upstream ``backward.cu``'s formulas, which ignore ``grad_depth``). Returns the case
    file's names: ``grad_means3D``, ``grad_means2D`` ([N,3], Inria's
    ``viewspace_points.grad``), ``grad_opacities``, ``grad_shs`` or
    ``grad_colors_precomp``, ``grad_scales`` and ``grad_rotations`` or
    ``grad_cov3D_precomp``.
    """
    a, t, meta = _raster_case(
        "rasterize_vjp", means3D, opacities, shs, colors_precomp, scales, rotations,
        cov3D_precomp, viewmatrix, projmatrix, campos, bg, image_height, image_width,
        tanfovx, tanfovy, scale_modifier, sh_degree, gradient,
    )
    h, w = meta["image_height"], meta["image_width"]
    t["grad_out_color"] = a.array("grad_color", grad_color, (3, h, w))
    if grad_depth is not None:
        t["grad_out_depth"] = a.array("grad_depth", grad_depth, (1, h, w))
    out, _ = _run_case("rasterize_vjp", t, meta, threads)
    return {k: v for k, v in out.items() if k.startswith("grad_")}


# ---------------------------------------------------------------------------
# Deformation fields
# ---------------------------------------------------------------------------


class DeformResult(NamedTuple):
    """A field's outputs: offsets added to the mean, the normalised quaternion and the
    activated scale. ``d_xyz_se3`` ([N,4,4], the 6-DoF MLP only) is the transform upstream's
    network returns; ``d_xyz`` is then the offset ``R·x + p − x`` its renderer applies."""

    d_xyz: np.ndarray
    d_rotation: np.ndarray
    d_scaling: np.ndarray
    d_xyz_se3: Optional[np.ndarray] = None


def _state_dict(cls: str, state_dict: Any) -> Dict[str, Any]:
    """A state_dict argument as a new dict with str keys (parameter names)."""
    if not isinstance(state_dict, Mapping):
        raise TypeError(f"{cls}: argument `state_dict`: expected a dict, found {type(state_dict).__name__}")
    for k in state_dict:
        if not isinstance(k, str):
            raise TypeError(
                f"{cls}: state_dict: expected str keys (parameter names), found {type(k).__name__} {k!r}"
            )
    return dict(state_dict)


def _count(sd: Mapping[str, Any], fmt: str) -> int:
    n = 0
    while fmt.format(n) in sd:
        n += 1
    return n


def _rows(cls: str, sd: Mapping[str, Any], key: str, shape: str) -> int:
    """The first dimension of the 2-D weight ``sd[key]`` (a layer's width)."""
    found = np.shape(sd[key])
    if len(found) != 2:
        raise ValueError(
            f"{cls}: state_dict[{key!r}]: expected a weight of shape {shape}, "
            f"found shape {_shape(found)}"
        )
    return int(found[0])


def _mlp_config(func: str, D: Any, W: Any, is_blender: Any, is_6dof: Any) -> Dict[str, MetaValue]:
    """The ``deform`` stage's keys for ``DeformNetwork(D, W, is_blender, is_6dof)``; the
    library refuses sizes above its limits."""
    a = _Args(func)
    return {"field": "mlp", "depth": a.integer("D", D, 3), "width": a.integer("W", W, 1),
            "is_6dof": a.flag("is_6dof", is_6dof),
            "variant": "synthetic" if a.flag("is_blender", is_blender) else "real"}


def _cfc_config(func: str, D: Any, W: Any, variant: Any, activation: Any, backbone_units: Any,
                backbone_layers: Any) -> Dict[str, MetaValue]:
    """The ``deform`` stage's keys for ``CfCField(D, W, variant, ...)``."""
    a = _Args(func)
    return {"field": "cfc", "depth": a.integer("D", D, 1), "width": a.integer("W", W, 1),
            "variant": a.string("variant", variant),
            "activation": a.string("activation", activation),
            "backbone_units": a.integer("backbone_units", backbone_units, 1),
            "backbone_layers": a.integer("backbone_layers", backbone_layers, 1)}


def _init_weights(func: str, config: Dict[str, MetaValue], seed: Any, dtype: str) -> Tensors:
    """A freshly initialised field's weights (the library's seeded initialisation)."""
    return _native.field_init(_metadata(config), _seed(func, seed), dtype)


class _Field:
    kind = ""

    def __init__(self, state_dict: Mapping[str, np.ndarray], config: Dict[str, MetaValue]):
        sd = dict(state_dict)
        if not sd:
            raise ValueError(f"{type(self).__name__}: the state_dict is empty")
        dtype = None
        for k, v in sd.items():
            if not isinstance(v, np.ndarray):
                raise TypeError(
                    f"{type(self).__name__}: state_dict[{k!r}]: expected a numpy.ndarray "
                    f"(from torch: {{k: v.numpy()}}), found {type(v).__name__}"
                )
            if v.dtype not in _FLOATS:
                raise TypeError(
                    f"{type(self).__name__}: state_dict[{k!r}]: expected dtype float32 or "
                    f"float64, found dtype {v.dtype}"
                )
            if dtype is None:
                dtype = v.dtype
            elif v.dtype != dtype:
                raise TypeError(
                    f"{type(self).__name__}: state_dict[{k!r}]: expected dtype {dtype} like "
                    f"the other weights, found dtype {v.dtype}"
                )
        self.state_dict: Tensors = {k: np.ascontiguousarray(v) for k, v in sd.items()}
        self.dtype: np.dtype = np.dtype(dtype)
        self.config: Dict[str, MetaValue] = dict(config)
        self.config["field"] = self.kind
        # Validate names and shapes now (the library names any wrong tensor).
        n = 1
        z = np.zeros((n, 3), self.dtype)
        self.forward(z, np.zeros((n, 1), self.dtype))

    def _inputs(self, func: str, xyz: Any, t: Any) -> Tuple[_Args, Tensors]:
        a = _Args(f"{type(self).__name__}.{func}")
        a.dtype, a.dtype_from = self.dtype, "the state_dict"
        x = a.array("xyz", xyz, ("N", 3))
        scalar = isinstance(t, (int, float, np.integer, np.floating)) or (
            isinstance(t, np.ndarray) and t.ndim == 0
        )
        if scalar and not isinstance(t, bool):
            tt = np.full((x.shape[0], 1), a.scalar("t", t), self.dtype)
        else:
            tt = a.array("t", t, ("N", 1))
        return a, {"xyz": x, "t": tt}

    def _run(self, func: str, tensors: Tensors, threads: Optional[int]) -> Tensors:
        tensors.update(self.state_dict)
        meta: Dict[str, MetaValue] = {"stage": "deform", **self.config}
        out, _ = _run_case(f"{type(self).__name__}.{func}", tensors, meta, threads)
        return out

    def forward(
        self, xyz: np.ndarray, t: Union[np.ndarray, float], *, threads: Optional[int] = None
    ) -> DeformResult:
        """``(d_xyz, d_rotation, d_scaling[, d_xyz_se3])`` at canonical centres ``xyz``
        [N,3] and normalised time ``t`` ([N,1], or one number for every point: a float, an
        int, a numpy scalar or a 0-d array)."""
        _, ins = self._inputs("forward", xyz, t)
        out = self._run("forward", ins, threads)
        return DeformResult(out["d_xyz"], out["d_rotation"], out["d_scaling"], out.get("d_xyz_se3"))

    __call__ = forward

    def vjp(
        self,
        xyz: np.ndarray,
        t: Union[np.ndarray, float],
        grad_d_xyz: np.ndarray,
        grad_d_rotation: np.ndarray,
        grad_d_scaling: np.ndarray,
        *,
        threads: Optional[int] = None,
    ) -> Tensors:
        """Gradients of ``Σ d_xyz·grad_d_xyz + Σ d_rotation·grad_d_rotation +
        Σ d_scaling·grad_d_scaling``: ``grad_t`` [N,1], ``grad.<name>`` for every weight,
        and (6-DoF only) ``grad_xyz``, the canonical centres' gradient through the warp
        (the network itself reads ``xyz`` stop-gradient, as upstream)."""
        a, ins = self._inputs("vjp", xyz, t)
        ins["grad_d_xyz"] = a.array("grad_d_xyz", grad_d_xyz, ("N", 3))
        ins["grad_d_rotation"] = a.array("grad_d_rotation", grad_d_rotation, ("N", 4))
        ins["grad_d_scaling"] = a.array("grad_d_scaling", grad_d_scaling, ("N", 3))
        out = self._run("vjp", ins, threads)
        return {k: v for k, v in out.items() if k.startswith("grad")}

    def astype(self, dtype: Any) -> "_Field":
        """The same field with its weights converted to ``dtype`` (float32 or float64)."""
        dt = _float_dtype(f"{type(self).__name__}.astype", "dtype", dtype)
        new = object.__new__(type(self))
        new.state_dict = {k: v.astype(dt) for k, v in self.state_dict.items()}
        new.dtype = dt
        new.config = dict(self.config)
        return new

    @property
    def param_count(self) -> int:
        """Number of learned parameters."""
        return int(_native.field_counts(_metadata(self.config))["params"])

    def macs(self, convention: str = "pytorch") -> int:
        """MACs per Gaussian as ptflops counts them: ``"aten"`` (linear layers only),
        ``"pytorch"`` (pytorch backend, count_functional=True) or
        ``"pytorch_no_functional"``."""
        counts = _native.field_counts(_metadata(self.config))
        key = f"macs_{convention}"
        if key not in counts:
            raise ValueError(
                "macs(): argument `convention`: expected 'aten', 'pytorch' or "
                f"'pytorch_no_functional', found {convention!r}"
            )
        return int(counts[key])

    def __repr__(self) -> str:
        cfg = ", ".join(f"{k}={v}" for k, v in self.config.items() if k != "field")
        return f"{type(self).__name__}({cfg}, dtype={self.dtype})"


class DeformNetwork(_Field):
    """The D-3DGS MLP field (``DeformNetwork``, incl. the 6-DoF variant) from its
    ``deform.pth`` state_dict (numpy arrays under the PyTorch names). Depth, width, the
    variant (``timenet.*`` present: synthetic, ``is_blender=True``) and 6-DoF
    (``branch_w.*`` present) are read from the keys and shapes."""

    kind = "mlp"

    def __init__(self, state_dict: Mapping[str, np.ndarray]):
        sd = _state_dict("DeformNetwork", state_dict)
        depth = _count(sd, "linear.{}.weight")
        if depth == 0:
            raise ValueError(
                "DeformNetwork: state_dict: expected `linear.0.weight` ... (a D-3DGS "
                f"DeformNetwork), found keys {sorted(sd)[:6]}"
            )
        config: Dict[str, MetaValue] = {
            "variant": "synthetic" if "timenet.0.weight" in sd else "real",
            "depth": depth,
            "width": _rows("DeformNetwork", sd, "linear.0.weight", "[W,in]"),
            "is_6dof": "branch_w.weight" in sd,
        }
        super().__init__(sd, config)

    @classmethod
    def new(cls, D: int = 8, W: int = 256, is_blender: bool = False, is_6dof: bool = False, *,
            seed: int = 0, dtype: Any = np.float32) -> "DeformNetwork":
        """A freshly initialised network with upstream's constructor arguments
        (``nn.Linear``'s default initialisation scheme, drawn from ``seed``, 0 to 2^64 − 1)."""
        meta = _mlp_config("DeformNetwork.new", D, W, is_blender, is_6dof)
        dt = _float_dtype("DeformNetwork.new", "dtype", dtype)
        return cls(_init_weights("DeformNetwork.new", meta, seed, dt.name))


class CfCField(_Field):
    """The liquid field (stacked ``ncps.torch.CfCCell``s) from its state_dict (numpy
    arrays under the PyTorch names). Depth, width, backbone size and variant are read from
    the keys and shapes; the activation is not stored in a state_dict, so give it."""

    kind = "cfc"

    def __init__(self, state_dict: Mapping[str, np.ndarray], activation: str = "gelu"):
        sd = _state_dict("CfCField", state_dict)
        depth = _count(sd, "cells.{}.ff1.weight")
        if depth == 0:
            raise ValueError(
                "CfCField: state_dict: expected `cells.0.ff1.weight` ... (a CfC field), "
                f"found keys {sorted(sd)[:6]}"
            )
        config: Dict[str, MetaValue] = {
            "variant": "synthetic" if "timenet.0.weight" in sd else "real",
            "depth": depth,
            "width": _rows("CfCField", sd, "cells.0.ff1.weight", "[W,in]"),
            "activation": activation,
            "backbone_units": (
                _rows("CfCField", sd, "cells.0.backbone.0.weight", "[units,in]")
                if "cells.0.backbone.0.weight" in sd else 0
            ),
            "backbone_layers": sum(
                1 for k in sd if k.startswith("cells.0.backbone.") and k.endswith(".weight")
            ),
        }
        super().__init__(sd, config)

    @classmethod
    def new(cls, D: int = 6, W: int = 128, variant: str = "synthetic", activation: str = "gelu",
            backbone_units: int = 64, backbone_layers: int = 2, *, seed: int = 0,
            dtype: Any = np.float32) -> "CfCField":
        """A freshly initialised field (``nn.Linear``'s default initialisation scheme,
        drawn from ``seed``, 0 to 2^64 − 1)."""
        meta = _cfc_config("CfCField.new", D, W, variant, activation, backbone_units,
                           backbone_layers)
        dt = _float_dtype("CfCField.new", "dtype", dtype)
        return cls(_init_weights("CfCField.new", meta, seed, dt.name), activation)


def load_field(state_dict: Mapping[str, np.ndarray], activation: str = "gelu") -> _Field:
    """A :class:`DeformNetwork` or :class:`CfCField`, whichever the state_dict's keys are."""
    if isinstance(state_dict, Mapping) and "cells.0.ff1.weight" in state_dict:
        return CfCField(state_dict, activation)
    return DeformNetwork(state_dict)


# ---------------------------------------------------------------------------
# Loss and step
# ---------------------------------------------------------------------------


def loss(
    image: np.ndarray,
    gt: np.ndarray,
    lambda_dssim: float = 0.2,
    *,
    threads: Optional[int] = None,
) -> Tensors:
    """D-3DGS's training loss ``(1 − λ)·L1 + λ·(1 − SSIM)`` of ``image`` [3,H,W] against
    ``gt``: ``{"loss", "l1", "ssim"}`` (rank-0 arrays) and ``grad_image`` = dloss/dimage."""
    a = _Args("loss")
    t = {"image": a.array("image", image, (3, "H", "W")), "gt": a.array("gt", gt, (3, "H", "W"))}
    lam = a.scalar("lambda_dssim", lambda_dssim)
    if not 0.0 <= lam <= 1.0:
        raise ValueError(f"loss(): argument `lambda_dssim`: expected a number in [0, 1], found {lam!r}")
    out, _ = _run_case("loss", t, {"stage": "loss", "lambda_dssim": lam}, threads)
    return out


def step(
    tensors: Mapping[str, np.ndarray],
    metadata: Mapping[str, MetaValue],
    *,
    threads: Optional[int] = None,
) -> Tuple[Tensors, Dict[str, str]]:
    """One whole D-3DGS training iteration (field, rasterizer, loss, backward,
    densification statistics, Adam) from case-file tensors and metadata (docs/ORACLE.md,
    stage ``step``; ``stage`` may be left out). Returns ``(outputs, output_metadata)``.

    Unlike :func:`rasterize`, which renders the background when there are no Gaussians,
    ``step`` refuses N = 0 (``ValueError`` naming ``xyz``): a training iteration needs at
    least one Gaussian."""
    meta = _mapping("step", "metadata", metadata)
    if meta.setdefault("stage", "step") != "step":
        raise ValueError(f"step(): argument `metadata`: expected stage 'step', found {meta['stage']!r}")
    return _run_case("step", tensors, meta, threads)


from . import gsplat  # noqa: E402  (uses the helpers above)
