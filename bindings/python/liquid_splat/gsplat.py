"""gsplat's Python API on the oracle: numpy functions with gsplat's names, argument names and
order, and output shapes, in gsplat's conventions (docs/GSPLAT.md) at gsplat 1.5.3 or 1.6.

Every function takes the keywords ``version`` (``"1.5.3"`` or ``"1.6"``, default ``"1.6"``),
``gradient`` (``"exact"``, default: the true derivative of the forward as computed, or
``"gsplat"``: gsplat's backward formulas as written) and ``threads``, and runs a
``gsplat_*`` stage of :func:`liquid_splat.run_case` (docs/ORACLE.md, "gsplat stages"): the
same bits as ``liquid-splat case run`` for any thread count. Each forward has a ``*_vjp``
twin taking the same arguments plus gsplat's cotangents (``v_<output>``) and returning
``{"v_<input>": gradient}``.

- :func:`quat_scale_to_covar_preci` / :func:`quat_scale_to_covar_preci_vjp`
- :func:`spherical_harmonics` / :func:`spherical_harmonics_vjp`
- :func:`fully_fused_projection` / :func:`fully_fused_projection_vjp` (pinhole; dense and
  packed; classic and with compensations)
- :func:`isect_tiles` and :func:`isect_offset_encode` (no gradient)
- :func:`rasterize_to_pixels` / :func:`rasterize_to_pixels_vjp`
- :func:`rasterization` / :func:`rasterization_vjp`

One batch: gsplat's leading ``...`` dimensions are absent (``C`` cameras, ``N`` Gaussians).
Integer outputs have gsplat's dtypes: int64 for ``isect_ids`` and the packed ``camera_ids`` and
``gaussian_ids``, int32 for the others.
float32 or float64 inputs select the precision. Arguments gsplat has and the oracle does not
model (``sparse_grad``, ``camera_model``, ``render_mode``, ``distributed``, ``segmented``,
``masks``) accept only their default values; ``absgrad`` and ``channel_chunk`` do not change
any value (the vjp functions always return ``v_means2d_abs``).
"""

from __future__ import annotations

from typing import Any, Dict, NamedTuple, Optional, Tuple, Union

import numpy as np

from . import (_MAX_PIXELS, _MAX_SIDE, _MAX_TILE_SIZE, MetaValue, Tensors, _Args, _not_masked, _run_case,
               _shape)

__all__ = [
    "VERSIONS",
    "GRADIENTS",
    "quat_scale_to_covar_preci",
    "quat_scale_to_covar_preci_vjp",
    "spherical_harmonics",
    "spherical_harmonics_vjp",
    "fully_fused_projection",
    "fully_fused_projection_vjp",
    "isect_tiles",
    "isect_offset_encode",
    "rasterize_to_pixels",
    "rasterize_to_pixels_vjp",
    "rasterization",
    "rasterization_vjp",
    "RasterizationResult",
]

VERSIONS: Tuple[str, ...] = ("1.5.3", "1.6")
GRADIENTS: Tuple[str, ...] = ("exact", "gsplat")


# ---------------------------------------------------------------------------
# Shared checks
# ---------------------------------------------------------------------------


def _common(a: _Args, version: Any, gradient: Any, stage: str) -> Dict[str, MetaValue]:
    return {
        "stage": stage,
        "version": a.choice("version", version, VERSIONS),
        "gradient": a.choice("gradient", gradient, GRADIENTS),
    }


def _ints(a: _Args, name: str, x: Any, shape: Tuple[Union[int, str], ...]) -> np.ndarray:
    """An integer array (any integer dtype, values in int32's range) as C-order int32,
    with named dimensions bound as in ``_Args.array``."""
    where = f"{a.func}(): argument `{name}`"
    if not isinstance(x, np.ndarray):
        raise TypeError(f"{where}: expected a numpy.ndarray of integers, found {type(x).__name__}")
    _not_masked(where, x)
    if not np.issubdtype(x.dtype, np.integer):
        raise TypeError(f"{where}: expected an integer dtype (int32), found dtype {x.dtype}")
    a.check_shape(where, name, x, shape)
    if x.size and (x.min() < -(2**31) or x.max() >= 2**31):
        raise ValueError(f"{where}: expected values in int32's range, found {x.min()}..{x.max()}")
    return np.ascontiguousarray(x, dtype=np.int32)


def _only(a: _Args, name: str, x: Any, default: Any) -> None:
    if default is None:
        other = x is not None
    elif isinstance(default, bool):  # (numpy's bools too)
        other = not isinstance(x, (bool, np.bool_)) or bool(x) != default
    else:
        other = not isinstance(x, type(default)) or x != default
    if other:
        found = type(x).__name__ if isinstance(x, np.ndarray) else repr(x)
        raise ValueError(
            f"{a.func}(): argument `{name}`: only {default!r} is supported by the oracle, found {found}"
        )


def _flag(a: _Args, name: str, x: Any) -> bool:
    if not isinstance(x, (bool, np.bool_)):
        raise TypeError(f"{a.func}(): argument `{name}`: expected a bool, found {type(x).__name__}")
    return bool(x)


def _run(a: _Args, t: Tensors, meta: Dict[str, MetaValue], threads: Optional[int]) -> Tensors:
    out, _ = _run_case(a.func, t, meta, threads)
    return out


def _long(ids: np.ndarray) -> np.ndarray:
    """int32 ids (as the stages write them) as gsplat's int64."""
    return ids.astype(np.int64)


def _join_ids(words: np.ndarray) -> np.ndarray:
    """``[n, 2]`` int32 words (high, low) as gsplat's int64 ``isect_ids``."""
    w = words.astype(np.int64)
    return (w[:, 0] << 32) | (w[:, 1] & 0xFFFFFFFF)


# ---------------------------------------------------------------------------
# quat_scale_to_covar_preci
# ---------------------------------------------------------------------------


def _covar_case(func, quats, scales, compute_covar, compute_preci, triu, version, gradient):
    a = _Args(func)
    t: Tensors = {"quats": a.array("quats", quats, ("N", 4)),
                  "scales": a.array("scales", scales, ("N", 3))}
    meta = _common(a, version, gradient, "gsplat_quat_scale_to_covar_preci")
    meta["compute_covar"] = _flag(a, "compute_covar", compute_covar)
    meta["compute_preci"] = _flag(a, "compute_preci", compute_preci)
    meta["triu"] = _flag(a, "triu", triu)
    n = quats.shape[0]
    shape = (n, 6) if triu else (n, 3, 3)
    return a, t, meta, shape


def quat_scale_to_covar_preci(
    quats: np.ndarray,
    scales: np.ndarray,
    compute_covar: bool = True,
    compute_preci: bool = True,
    triu: bool = False,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tuple[Optional[np.ndarray], Optional[np.ndarray]]:
    """``(covars, precis)``: ``[N,3,3]`` (``[N,6]`` with ``triu``) or ``None`` when not
    computed. ``quats [N,4]`` (w, x, y, z, any norm; normalised inside), ``scales [N,3]``."""
    a, t, meta, shape = _covar_case("quat_scale_to_covar_preci", quats, scales, compute_covar,
                                    compute_preci, triu, version, gradient)
    out = _run(a, t, meta, threads)
    return out.get("covars"), out.get("precis")


def quat_scale_to_covar_preci_vjp(
    quats: np.ndarray,
    scales: np.ndarray,
    compute_covar: bool = True,
    compute_preci: bool = True,
    triu: bool = False,
    v_covars: Optional[np.ndarray] = None,
    v_precis: Optional[np.ndarray] = None,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tensors:
    """``{"v_quats", "v_scales"}`` for ``L = Σ covars·v_covars + Σ precis·v_precis`` (a
    cotangent left ``None`` is zero)."""
    func = "quat_scale_to_covar_preci_vjp"
    a, t, meta, shape = _covar_case(func, quats, scales, compute_covar, compute_preci, triu,
                                    version, gradient)
    for key, name, v in (("compute_covar", "v_covars", v_covars),
                         ("compute_preci", "v_precis", v_precis)):
        if meta[key]:
            if v is not None:
                t[name] = a.array(name, v, shape)
        elif v is not None:
            raise ValueError(f"{func}(): argument `{name}`: given, but {key}=False")
    out = _run(a, t, meta, threads)
    return {"v_quats": out["v_quats"], "v_scales": out["v_scales"]}


# ---------------------------------------------------------------------------
# spherical_harmonics
# ---------------------------------------------------------------------------


def _sh_case(func, degrees_to_use, dirs, coeffs, masks, version, gradient):
    a = _Args(func)
    deg = a.integer("degrees_to_use", degrees_to_use, 0, 4)
    t: Tensors = {"dirs": a.array("dirs", dirs, ("M", 3)),
                  "coeffs": a.array("coeffs", coeffs, ("M", "K", "D"))}
    if (deg + 1) ** 2 > coeffs.shape[1]:
        raise ValueError(
            f"{func}(): argument `coeffs`: expected at least (degrees_to_use+1)^2 = "
            f"{(deg + 1) ** 2} coefficients, found shape {_shape(coeffs.shape)}"
        )
    _only(a, "masks", masks, None)
    meta = _common(a, version, gradient, "gsplat_spherical_harmonics")
    meta["degrees_to_use"] = deg
    return a, t, meta


def spherical_harmonics(
    degrees_to_use: int,
    dirs: np.ndarray,
    coeffs: np.ndarray,
    masks: None = None,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> np.ndarray:
    """``colors [M,D]`` (no ``+0.5``) of SH ``coeffs [M,K,D]`` at directions ``dirs [M,3]``
    (any length) up to degree ``degrees_to_use`` (0–4)."""
    a, t, meta = _sh_case("spherical_harmonics", degrees_to_use, dirs, coeffs, masks, version,
                          gradient)
    return _run(a, t, meta, threads)["colors"]


def spherical_harmonics_vjp(
    degrees_to_use: int,
    dirs: np.ndarray,
    coeffs: np.ndarray,
    masks: None = None,
    *,
    v_colors: np.ndarray,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tensors:
    """``{"v_dirs", "v_coeffs"}`` for ``L = Σ colors·v_colors``."""
    a, t, meta = _sh_case("spherical_harmonics_vjp", degrees_to_use, dirs, coeffs, masks,
                          version, gradient)
    t["v_colors"] = a.array("v_colors", v_colors, ("M", "D"))
    out = _run(a, t, meta, threads)
    return {"v_dirs": out["v_dirs"], "v_coeffs": out["v_coeffs"]}


# ---------------------------------------------------------------------------
# fully_fused_projection
# ---------------------------------------------------------------------------


class _Proj(NamedTuple):
    a: _Args
    t: Tensors
    meta: Dict[str, MetaValue]
    c: int
    n: int


def _proj_case(func, means, covars, quats, scales, viewmats, Ks, width, height, eps2d,
               near_plane, far_plane, radius_clip, packed, sparse_grad, calc_compensations,
               camera_model, opacities, version, gradient) -> _Proj:
    a = _Args(func)
    t: Tensors = {"means": a.array("means", means, ("N", 3))}
    if covars is not None:
        if quats is not None or scales is not None:
            raise ValueError(f"{func}(): expected `covars` or `quats` and `scales`, found both")
        t["covars"] = a.array("covars", covars, ("N", 6))
    else:
        if quats is None or scales is None:
            raise ValueError(
                f"{func}(): expected `quats` and `scales` (or `covars`), found "
                f"{'no `quats`' if quats is None else 'no `scales`'}"
            )
        t["quats"] = a.array("quats", quats, ("N", 4))
        t["scales"] = a.array("scales", scales, ("N", 3))
    t["viewmats"] = a.array("viewmats", viewmats, ("C", 4, 4))
    t["Ks"] = a.array("Ks", Ks, ("C", 3, 3))
    if opacities is not None:
        t["opacities"] = a.array("opacities", opacities, ("N",))
    meta = _common(a, version, gradient, "gsplat_fully_fused_projection")
    meta["width"] = a.integer("width", width, 1, _MAX_SIDE)
    meta["height"] = a.integer("height", height, 1, _MAX_SIDE)
    meta["eps2d"] = a.scalar("eps2d", eps2d)
    meta["near_plane"] = a.scalar("near_plane", near_plane)
    meta["far_plane"] = a.scalar("far_plane", far_plane)
    meta["radius_clip"] = a.scalar("radius_clip", radius_clip)
    meta["packed"] = _flag(a, "packed", packed)
    _only(a, "sparse_grad", sparse_grad, False)
    meta["calc_compensations"] = _flag(a, "calc_compensations", calc_compensations)
    _only(a, "camera_model", camera_model, "pinhole")
    return _Proj(a, t, meta, viewmats.shape[0], means.shape[0])


def fully_fused_projection(
    means: np.ndarray,
    covars: Optional[np.ndarray],
    quats: Optional[np.ndarray],
    scales: Optional[np.ndarray],
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    packed: bool = False,
    sparse_grad: bool = False,
    calc_compensations: bool = False,
    camera_model: str = "pinhole",
    opacities: Optional[np.ndarray] = None,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tuple[Any, ...]:
    """gsplat's projection of ``N`` Gaussians into ``C`` pinhole cameras.

    ``means [N,3]``; ``covars [N,6]`` (``[00,01,02,11,12,22]``) or ``quats [N,4]`` +
    ``scales [N,3]`` (the other ``None``); ``viewmats [C,4,4]`` (row-major world-to-camera);
    ``Ks [C,3,3]``; optional ``opacities [N]`` (opacity-aware radii). Returns dense
    ``(radii [C,N,2], means2d [C,N,2], depths [C,N], conics [C,N,3], compensations [C,N] or
    None)``, or packed ``(camera_ids, gaussian_ids, radii, means2d, depths, conics,
    compensations)`` with ``nnz`` rows."""
    p = _proj_case("fully_fused_projection", means, covars, quats, scales, viewmats, Ks, width,
                   height, eps2d, near_plane, far_plane, radius_clip, packed, sparse_grad,
                   calc_compensations, camera_model, opacities, version, gradient)
    # No cotangents: the stage reads them as zeros (one run, packed or dense).
    out = _run(p.a, p.t, p.meta, threads)
    if p.meta["packed"]:
        return (_long(out["camera_ids"]), _long(out["gaussian_ids"]), out["radii"], out["means2d"],
                out["depths"], out["conics"], out.get("compensations"))
    return out["radii"], out["means2d"], out["depths"], out["conics"], out.get("compensations")


def fully_fused_projection_vjp(
    means: np.ndarray,
    covars: Optional[np.ndarray],
    quats: Optional[np.ndarray],
    scales: Optional[np.ndarray],
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    eps2d: float = 0.3,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    packed: bool = False,
    sparse_grad: bool = False,
    calc_compensations: bool = False,
    camera_model: str = "pinhole",
    opacities: Optional[np.ndarray] = None,
    *,
    v_means2d: np.ndarray,
    v_depths: np.ndarray,
    v_conics: np.ndarray,
    v_compensations: Optional[np.ndarray] = None,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tensors:
    """``{"v_means", "v_quats", "v_scales"}`` (or ``"v_covars"``) for
    ``L = Σ means2d·v_means2d + Σ depths·v_depths + Σ conics·v_conics (+ Σ
    compensations·v_compensations)``; cotangents in the output layout (``[C,N,·]`` dense,
    ``[nnz,·]`` packed). ``v_compensations`` (``None``: zero) only with
    ``calc_compensations``."""
    func = "fully_fused_projection_vjp"
    p = _proj_case(func, means, covars, quats, scales, viewmats, Ks, width, height, eps2d,
                   near_plane, far_plane, radius_clip, packed, sparse_grad, calc_compensations,
                   camera_model, opacities, version, gradient)
    lead: Tuple[Union[int, str], ...] = ("nnz",) if p.meta["packed"] else (p.c, p.n)
    t = dict(p.t)
    t["v_means2d"] = p.a.array("v_means2d", v_means2d, lead + (2,))
    t["v_depths"] = p.a.array("v_depths", v_depths, lead)
    t["v_conics"] = p.a.array("v_conics", v_conics, lead + (3,))
    if p.meta["calc_compensations"]:
        if v_compensations is not None:
            t["v_compensations"] = p.a.array("v_compensations", v_compensations, lead)
    elif v_compensations is not None:
        raise ValueError(f"{func}(): argument `v_compensations`: given, but calc_compensations=False")
    out = _run(p.a, t, p.meta, threads)
    return {k: v for k, v in out.items() if k in ("v_means", "v_quats", "v_scales", "v_covars")}


# ---------------------------------------------------------------------------
# isect_tiles, isect_offset_encode
# ---------------------------------------------------------------------------


def isect_tiles(
    means2d: np.ndarray,
    radii: np.ndarray,
    depths: np.ndarray,
    tile_size: int,
    tile_width: int,
    tile_height: int,
    sort: bool = True,
    segmented: bool = False,
    packed: bool = False,
    n_images: Optional[int] = None,
    image_ids: Optional[np.ndarray] = None,
    gaussian_ids: Optional[np.ndarray] = None,
    conics: Optional[np.ndarray] = None,
    opacities: Optional[np.ndarray] = None,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(tiles_per_gauss, isect_ids, flatten_ids)``: the tiles each projected Gaussian
    touches, keys sorted by (image, tile, depth) (int64) and their rows.

    Dense: ``means2d [C,N,2]``, ``radii [C,N,2]``, ``depths [C,N]`` (``tiles_per_gauss``
    ``[C,N]``). Packed: ``[nnz,·]`` rows with ``n_images`` and ``image_ids [nnz]``
    (``gaussian_ids`` is checked and not needed). With ``version="1.6"``, ``conics`` and
    ``opacities`` (same layout) select AccuTile's exact ellipse-vs-tile test; otherwise the
    radius box. No gradient."""
    out = _isect(means2d, radii, depths, tile_size, tile_width, tile_height, sort, segmented,
                 packed, n_images, image_ids, gaussian_ids, conics, opacities, version, gradient,
                 threads)
    return out["tiles_per_gauss"], _join_ids(out["isect_ids"]), out["flatten_ids"]


def _isect(means2d, radii, depths, tile_size, tile_width, tile_height, sort, segmented, packed,
           n_images, image_ids, gaussian_ids, conics, opacities, version, gradient,
           threads) -> Tensors:
    func = "isect_tiles"
    a = _Args(func)
    meta = _common(a, version, gradient, "gsplat_isect_tiles")
    _only(a, "sort", sort, True)
    _only(a, "segmented", segmented, False)
    packed = _flag(a, "packed", packed)
    lead: Tuple[Union[int, str], ...] = ("nnz",) if packed else ("C", "N")
    t: Tensors = {"means2d": a.array("means2d", means2d, lead + (2,))}
    t["radii"] = _ints(a, "radii", radii, lead + (2,))
    t["depths"] = a.array("depths", depths, lead)
    if (conics is None) != (opacities is None):
        raise ValueError(f"{func}(): expected both `conics` and `opacities` or neither, found one")
    if conics is not None:
        t["conics"] = a.array("conics", conics, lead + (3,))
        t["opacities"] = a.array("opacities", opacities, lead)
    if packed:
        if n_images is None or image_ids is None:
            raise ValueError(f"{func}(): expected `n_images` and `image_ids` with packed=True")
        meta["n_images"] = a.integer("n_images", n_images, 1)
        t["image_ids"] = _ints(a, "image_ids", image_ids, ("nnz",))
        if gaussian_ids is not None:
            _ints(a, "gaussian_ids", gaussian_ids, ("nnz",))
    else:
        for name, v in (("image_ids", image_ids), ("gaussian_ids", gaussian_ids)):
            if v is not None:
                raise ValueError(f"{func}(): argument `{name}`: only with packed=True")
        meta["n_images"] = means2d.shape[0]
        if n_images is not None and a.integer("n_images", n_images, 1) != means2d.shape[0]:
            raise ValueError(
                f"{func}(): argument `n_images`: expected C={means2d.shape[0]} from `means2d`, "
                f"found {n_images}"
            )
        t = {k: v.reshape((v.shape[0] * v.shape[1],) + v.shape[2:]) for k, v in t.items()}
    meta["tile_size"] = a.integer("tile_size", tile_size, 1, _MAX_TILE_SIZE)
    meta["tile_width"] = a.integer("tile_width", tile_width, 1)
    meta["tile_height"] = a.integer("tile_height", tile_height, 1)
    _check_tiles(func, int(meta["n_images"]), int(meta["tile_width"]), int(meta["tile_height"]),
                 meta["version"], images="`n_images`" if packed else "`means2d`'s C")
    out = _run(a, t, meta, threads)
    if not packed:
        out["tiles_per_gauss"] = out["tiles_per_gauss"].reshape(means2d.shape[:2])
    return out


def _check_tiles(func: str, n_images: int, tile_width: int, tile_height: int, version: str,
                 images: str = "`n_images`") -> None:
    """The library's limit on a tile grid (docs/ORACLE.md): images × tiles at most 2^26 and
    the image and tile fields of a key in 31 bits. ``images`` names where the image count
    came from."""
    tiles = tile_width * tile_height
    if (n_images * tiles > _MAX_PIXELS
            or _key_bits(version, n_images) + _key_bits(version, tiles) > 31):
        raise ValueError(
            f"{func}(): arguments {images}, `tile_width`, `tile_height`: expected at most "
            f"{_MAX_PIXELS} tiles over all images and a key of at most 31 bits of image and "
            f"tile, found {n_images} images of {tile_width}x{tile_height} tiles"
        )


def _key_bits(version: str, count: int) -> int:
    """Bits of the image or tile field of a key (docs/GSPLAT.md, "Versions")."""
    return int(count).bit_length() if version == "1.5.3" else max(int(count) - 1, 0).bit_length()


def isect_offset_encode(
    isect_ids: np.ndarray,
    n_images: int,
    tile_width: int,
    tile_height: int,
    *,
    version: str = "1.6",
) -> np.ndarray:
    """``isect_offsets [n_images, tile_height, tile_width]`` (int32): the index of the first
    intersection of each tile in the sorted ``isect_ids`` (int64, from :func:`isect_tiles`),
    that of the next occupied tile (or ``n_isects``) for an empty one. The key layout
    (image bits above tile bits) depends on ``version``. Keys must be sorted, non-negative,
    and name an image below ``n_images`` and a tile below ``tile_width·tile_height``
    (``ValueError`` naming the first key that does not)."""
    a = _Args("isect_offset_encode")
    version = a.choice("version", version, VERSIONS)
    where = "isect_offset_encode(): argument `isect_ids`"
    if not isinstance(isect_ids, np.ndarray):
        raise TypeError(f"{where}: expected a numpy.ndarray of int64, found {type(isect_ids).__name__}")
    if isect_ids.dtype != np.int64 or isect_ids.ndim != 1:
        raise TypeError(
            f"{where}: expected int64 of shape [n_isects], found dtype {isect_ids.dtype} "
            f"shape {_shape(isect_ids.shape)}"
        )
    ni = a.integer("n_images", n_images, 1)
    tw = a.integer("tile_width", tile_width, 1)
    th = a.integer("tile_height", tile_height, 1)
    _check_tiles("isect_offset_encode", ni, tw, th, version)
    bits = _key_bits(version, tw * th)
    key = isect_ids >> 32
    image, tile = key >> bits, key & ((1 << bits) - 1)
    for bad, what in ((key < 0, "non-negative keys"),
                      (image >= ni, f"image indices below n_images={ni}"),
                      (tile >= tw * th, f"tile indices below tile_width*tile_height={tw * th}")):
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"{where}: expected {what}, found isect_ids[{i}] = {int(isect_ids[i])} "
                f"(key {int(key[i])}: image {int(image[i])}, tile {int(tile[i])})"
            )
    slot = image * (tw * th) + tile
    if slot.size and np.any(np.diff(slot) < 0):
        raise ValueError(f"{where}: expected keys sorted by (image, tile), found them unsorted")
    offsets = np.searchsorted(slot, np.arange(ni * tw * th), side="left")
    return offsets.astype(np.int32).reshape(ni, th, tw)


# ---------------------------------------------------------------------------
# rasterize_to_pixels
# ---------------------------------------------------------------------------


def _r2p_case(func, means2d, conics, colors, opacities, image_width, image_height, tile_size,
              isect_offsets, flatten_ids, backgrounds, masks, packed, absgrad, version,
              gradient):
    a = _Args(func)
    meta = _common(a, version, gradient, "gsplat_rasterize_to_pixels")
    packed = _flag(a, "packed", packed)
    _flag(a, "absgrad", absgrad)
    _only(a, "masks", masks, None)
    lead: Tuple[Union[int, str], ...] = ("nnz",) if packed else ("C", "N")
    t: Tensors = {"means2d": a.array("means2d", means2d, lead + (2,)),
                  "conics": a.array("conics", conics, lead + (3,)),
                  "colors": a.array("colors", colors, lead + ("D",)),
                  "opacities": a.array("opacities", opacities, lead)}
    t["isect_offsets"] = _ints(a, "isect_offsets", isect_offsets, ("I", "th", "tw"))
    t["flatten_ids"] = _ints(a, "flatten_ids", flatten_ids, ("n_isects",))
    if not packed and isect_offsets.shape[0] != means2d.shape[0]:
        raise ValueError(
            f"{func}(): argument `isect_offsets`: expected {means2d.shape[0]} images (C from "
            f"`means2d`), found shape {_shape(isect_offsets.shape)}"
        )
    if backgrounds is not None:
        t["backgrounds"] = a.array("backgrounds", backgrounds, ("I", "D"))
    w = meta["image_width"] = a.integer("image_width", image_width, 1, _MAX_SIDE)
    h = meta["image_height"] = a.integer("image_height", image_height, 1, _MAX_SIDE)
    ts = meta["tile_size"] = a.integer("tile_size", tile_size, 1, _MAX_TILE_SIZE)
    grid = (-(-h // ts), -(-w // ts))
    if isect_offsets.shape[1:] != grid:
        raise ValueError(
            f"{func}(): argument `isect_offsets`: expected shape [I,{grid[0]},{grid[1]}] (the "
            f"tile grid of a {w}x{h} image with tile_size {ts}), found shape {_shape(isect_offsets.shape)}"
        )
    if not packed:
        for k in ("means2d", "conics", "colors", "opacities"):
            t[k] = t[k].reshape((t[k].shape[0] * t[k].shape[1],) + t[k].shape[2:])
    shape = (isect_offsets.shape[0], meta["image_height"], meta["image_width"])
    return a, t, meta, shape


def rasterize_to_pixels(
    means2d: np.ndarray,
    conics: np.ndarray,
    colors: np.ndarray,
    opacities: np.ndarray,
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: np.ndarray,
    flatten_ids: np.ndarray,
    backgrounds: Optional[np.ndarray] = None,
    masks: None = None,
    packed: bool = False,
    absgrad: bool = False,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tuple[np.ndarray, np.ndarray]:
    """``(render_colors [I,H,W,D], render_alphas [I,H,W,1])``: front-to-back compositing of
    the projected Gaussians (dense ``[C,N,·]`` or packed ``[nnz,·]`` rows; ``colors`` with
    any ``D ≥ 1`` channels) over the tiles of ``isect_offsets [I,th,tw]`` and
    ``flatten_ids``; optional ``backgrounds [I,D]``."""
    a, t, meta, _ = _r2p_case(
        "rasterize_to_pixels", means2d, conics, colors, opacities, image_width, image_height,
        tile_size, isect_offsets, flatten_ids, backgrounds, masks, packed, absgrad, version,
        gradient)
    out = _run(a, t, meta, threads)
    return out["render_colors"], out["render_alphas"]


def rasterize_to_pixels_vjp(
    means2d: np.ndarray,
    conics: np.ndarray,
    colors: np.ndarray,
    opacities: np.ndarray,
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: np.ndarray,
    flatten_ids: np.ndarray,
    backgrounds: Optional[np.ndarray] = None,
    masks: None = None,
    packed: bool = False,
    absgrad: bool = False,
    *,
    v_render_colors: np.ndarray,
    v_render_alphas: np.ndarray,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tensors:
    """Gradients of ``L = Σ render_colors·v_render_colors + Σ render_alphas·v_render_alphas``:
    ``v_means2d`` (pixels), ``v_means2d_abs`` (gsplat's ``absgrad``), ``v_conics``,
    ``v_colors``, ``v_opacities`` in the shapes of the inputs, and ``v_backgrounds`` when
    ``backgrounds`` is given."""
    a, t, meta, (i, h, w) = _r2p_case(
        "rasterize_to_pixels_vjp", means2d, conics, colors, opacities, image_width,
        image_height, tile_size, isect_offsets, flatten_ids, backgrounds, masks, packed,
        absgrad, version, gradient)
    d = colors.shape[-1]
    t["v_render_colors"] = a.array("v_render_colors", v_render_colors, (i, h, w, d))
    t["v_render_alphas"] = a.array("v_render_alphas", v_render_alphas, (i, h, w, 1))
    out = _run(a, t, meta, threads)
    shapes = {"v_means2d": means2d.shape, "v_means2d_abs": means2d.shape,
              "v_conics": conics.shape, "v_colors": colors.shape,
              "v_opacities": opacities.shape}
    g = {k: out[k].reshape(s) for k, s in shapes.items()}
    if "v_backgrounds" in out:
        g["v_backgrounds"] = out["v_backgrounds"]
    return g


# ---------------------------------------------------------------------------
# rasterization
# ---------------------------------------------------------------------------


class RasterizationResult(NamedTuple):
    """gsplat's ``render_colors, render_alphas, meta = rasterization(...)``."""

    render_colors: np.ndarray  #: [C,H,W,D]
    render_alphas: np.ndarray  #: [C,H,W,1]
    meta: Dict[str, Any]  #: gsplat's ``meta`` (arrays and ints)


def _raster_case(func, means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                 near_plane, far_plane, radius_clip, eps2d, sh_degree, packed, tile_size,
                 backgrounds, render_mode, sparse_grad, absgrad, rasterize_mode, channel_chunk,
                 distributed, camera_model, segmented, covars, version, gradient):
    a = _Args(func)
    meta = _common(a, version, gradient, "gsplat_rasterization")
    t: Tensors = {"means": a.array("means", means, ("N", 3))}
    if covars is not None:
        if quats is not None or scales is not None:
            raise ValueError(f"{func}(): expected `covars` or `quats` and `scales`, found both")
        t["covars"] = a.array("covars", covars, ("N", 6))
    else:
        if quats is None or scales is None:
            raise ValueError(
                f"{func}(): expected `quats` and `scales` (or `covars`), found "
                f"{'no `quats`' if quats is None else 'no `scales`'}"
            )
        t["quats"] = a.array("quats", quats, ("N", 4))
        t["scales"] = a.array("scales", scales, ("N", 3))
    t["opacities"] = a.array("opacities", opacities, ("N",))
    if sh_degree is None:
        t["colors"] = a.array("colors", colors, ("N", "D"))
        d = colors.shape[1]
    else:
        deg = a.integer("sh_degree", sh_degree, 0, 4)
        t["colors"] = a.array("colors", colors, ("N", "K", 3))
        if (deg + 1) ** 2 > colors.shape[1]:
            raise ValueError(
                f"{func}(): argument `colors`: expected at least (sh_degree+1)^2 = "
                f"{(deg + 1) ** 2} SH coefficients, found shape {_shape(colors.shape)}"
            )
        meta["sh_degree"] = deg
        d = 3
    t["viewmats"] = a.array("viewmats", viewmats, ("C", 4, 4))
    t["Ks"] = a.array("Ks", Ks, ("C", 3, 3))
    if backgrounds is not None:
        t["backgrounds"] = a.array("backgrounds", backgrounds, ("C", d))
    meta["width"] = a.integer("width", width, 1, _MAX_SIDE)
    meta["height"] = a.integer("height", height, 1, _MAX_SIDE)
    meta["near_plane"] = a.scalar("near_plane", near_plane)
    meta["far_plane"] = a.scalar("far_plane", far_plane)
    meta["radius_clip"] = a.scalar("radius_clip", radius_clip)
    meta["eps2d"] = a.scalar("eps2d", eps2d)
    meta["packed"] = _flag(a, "packed", packed)
    meta["tile_size"] = a.integer("tile_size", tile_size, 1, _MAX_TILE_SIZE)
    _only(a, "render_mode", render_mode, "RGB")
    _only(a, "sparse_grad", sparse_grad, False)
    _flag(a, "absgrad", absgrad)
    meta["rasterize_mode"] = a.choice("rasterize_mode", rasterize_mode, ("classic", "antialiased"))
    a.integer("channel_chunk", channel_chunk, 1)
    _only(a, "distributed", distributed, False)
    _only(a, "camera_model", camera_model, "pinhole")
    _only(a, "segmented", segmented, False)
    shape = (viewmats.shape[0], meta["height"], meta["width"], d)
    return a, t, meta, shape


def rasterization(
    means: np.ndarray,
    quats: Optional[np.ndarray],
    scales: Optional[np.ndarray],
    opacities: np.ndarray,
    colors: np.ndarray,
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Optional[np.ndarray] = None,
    render_mode: str = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    channel_chunk: int = 32,
    distributed: bool = False,
    camera_model: str = "pinhole",
    segmented: bool = False,
    covars: Optional[np.ndarray] = None,
    *,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> RasterizationResult:
    """gsplat's ``rasterization`` with its defaults: ``(render_colors [C,H,W,D],
    render_alphas [C,H,W,1], meta)``.

    ``means [N,3]``; ``quats [N,4]`` + ``scales [N,3]`` (activated; or ``covars [N,6]`` with
    both ``None``); ``opacities [N]`` (activated); ``colors [N,D]``, or SH coefficients
    ``[N,K,3]`` with ``sh_degree``; ``viewmats [C,4,4]``, ``Ks [C,3,3]``; optional
    ``backgrounds [C,D]``. ``meta`` has gsplat's keys: ``radii``, ``means2d``, ``depths``,
    ``conics``, ``opacities``, ``tiles_per_gauss`` (packed adds ``camera_ids``,
    ``gaussian_ids``), ``isect_ids`` (int64), ``flatten_ids``, ``isect_offsets``,
    ``width``, ``height``, ``tile_size``, ``tile_width``, ``tile_height``, ``n_cameras``."""
    a, t, meta, shape = _raster_case(
        "rasterization", means, quats, scales, opacities, colors, viewmats, Ks, width, height,
        near_plane, far_plane, radius_clip, eps2d, sh_degree, packed, tile_size, backgrounds,
        render_mode, sparse_grad, absgrad, rasterize_mode, channel_chunk, distributed,
        camera_model, segmented, covars, version, gradient)
    out = _run(a, t, meta, threads)
    m: Dict[str, Any] = {k[len("meta."):]: v for k, v in out.items() if k.startswith("meta.")}
    m["isect_ids"] = _join_ids(m["isect_ids"])
    for k in ("camera_ids", "gaussian_ids"):
        if k in m:
            m[k] = _long(m[k])
    ts = int(meta["tile_size"])
    m.update(width=int(meta["width"]), height=int(meta["height"]), tile_size=ts,
             tile_width=-(-int(meta["width"]) // ts), tile_height=-(-int(meta["height"]) // ts),
             n_cameras=shape[0])
    return RasterizationResult(out["render_colors"], out["render_alphas"], m)


def rasterization_vjp(
    means: np.ndarray,
    quats: Optional[np.ndarray],
    scales: Optional[np.ndarray],
    opacities: np.ndarray,
    colors: np.ndarray,
    viewmats: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    radius_clip: float = 0.0,
    eps2d: float = 0.3,
    sh_degree: Optional[int] = None,
    packed: bool = True,
    tile_size: int = 16,
    backgrounds: Optional[np.ndarray] = None,
    render_mode: str = "RGB",
    sparse_grad: bool = False,
    absgrad: bool = False,
    rasterize_mode: str = "classic",
    channel_chunk: int = 32,
    distributed: bool = False,
    camera_model: str = "pinhole",
    segmented: bool = False,
    covars: Optional[np.ndarray] = None,
    *,
    v_render_colors: np.ndarray,
    v_render_alphas: np.ndarray,
    version: str = "1.6",
    gradient: str = "exact",
    threads: Optional[int] = None,
) -> Tensors:
    """Gradients of ``L = Σ render_colors·v_render_colors + Σ render_alphas·v_render_alphas``
    (``v_render_colors [C,H,W,D]``, ``v_render_alphas [C,H,W,1]``): ``v_means``,
    ``v_quats`` + ``v_scales`` (or ``v_covars``), ``v_opacities``, ``v_colors`` (the shape
    of ``colors``), ``v_backgrounds`` (with ``backgrounds``), and ``v_means2d``,
    ``v_means2d_abs``: the gradient (and gsplat's ``absgrad``) of ``meta["means2d"]``, in
    pixels, what gsplat's densification reads."""
    a, t, meta, shape = _raster_case(
        "rasterization_vjp", means, quats, scales, opacities, colors, viewmats, Ks, width,
        height, near_plane, far_plane, radius_clip, eps2d, sh_degree, packed, tile_size,
        backgrounds, render_mode, sparse_grad, absgrad, rasterize_mode, channel_chunk,
        distributed, camera_model, segmented, covars, version, gradient)
    t["v_render_colors"] = a.array("v_render_colors", v_render_colors, shape)
    t["v_render_alphas"] = a.array("v_render_alphas", v_render_alphas, shape[:3] + (1,))
    out = _run(a, t, meta, threads)
    return {k: v for k, v in out.items() if k.startswith("v_")}
