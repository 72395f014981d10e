"""Colours of per-vertex scalar fields: the robust colour range and the colormap (the
default, "inferno", also without matplotlib, for the PLY colours of ``stochlap saliency``)."""

from __future__ import annotations

import numpy as np

from .._common.errors import ParameterError
from ._arrays import as_numpy, used_vertices
from .backend import mpl

#: Colormaps named when an unknown one is refused (all are matplotlib's).
SUGGESTED_CMAPS = ("inferno", "viridis", "magma", "plasma", "cividis", "coolwarm", "RdBu_r")

#: matplotlib's "inferno" sampled at 17 evenly spaced points (RGB, 0-255).
_INFERNO_HEX = (
    "000004 0b0724 210c4a 3d0965 57106e 71196e 8a226a a32c61 bc3754 d24644 e45a31 f1731d "
    "f98e09 fcac11 f9cb35 f2ea69 fcffa4"
)
_INFERNO_17 = np.array(list(bytes.fromhex(_INFERNO_HEX)), dtype=np.float64).reshape(17, 3)


def _finite(values: np.ndarray, faces=None) -> np.ndarray:
    """The finite ``values`` of the vertices ``faces`` uses (of all without ``faces``)."""
    if faces is not None:
        values = values[used_vertices(as_numpy(faces), values.shape[0])]
    return values[np.isfinite(values)]


def robust_range(
    values,
    faces=None,
    vmin: float | None = None,
    vmax: float | None = None,
    percentiles: tuple[float, float] = (1.0, 99.0),
) -> tuple[float, float]:
    """The colour range ``(vmin, vmax)`` of ``(V,)`` values: a bound left ``None`` is its
    ``percentiles`` value (1st, 99th) over the vertices ``faces`` uses (``None``: all; an
    unreferenced vertex is invisible but may carry an extreme value); a constant field gets a
    tiny range around its value, so that it maps to the middle of the colormap."""
    if vmin is None or vmax is None:
        finite = _finite(as_numpy(values, np.float64).reshape(-1), faces)
        lo, hi = np.percentile(finite, percentiles) if finite.size else (0.0, 1.0)
        vmin = float(lo) if vmin is None else float(vmin)
        vmax = float(hi) if vmax is None else float(vmax)
    if not vmax > vmin:  # constant field (or inverted bounds): a tiny range around the value
        centre = 0.5 * (vmin + vmax)
        if np.isfinite(centre):
            half = 0.5 * max(abs(centre) * 1e-6, 1e-12)
        else:
            centre, half = 0.0, 0.5
        vmin, vmax = centre - half, centre + half
    return float(vmin), float(vmax)


def value_span(values: np.ndarray, faces: np.ndarray | None = None) -> tuple[float, float] | None:
    """``(min, max)`` of the finite ``(V,)`` values (of the vertices ``faces`` uses, when
    given), or ``None`` when there is none."""
    finite = _finite(values, faces)
    return (float(finite.min()), float(finite.max())) if finite.size else None


def clipped_ends(span: tuple[float, float] | None, vmin: float, vmax: float) -> str:
    """matplotlib's colour bar ``extend`` (``"neither"``, ``"min"``, ``"max"``, ``"both"``):
    the ends of ``[vmin, vmax]`` that clip values whose ``(min, max)`` is ``span``."""
    low, high = span is not None and span[0] < vmin, span is not None and span[1] > vmax
    return ("neither", "max", "min", "both")[2 * low + high]


def check_cmap(cmap):
    """``cmap`` if it is a colormap object or the name of one (without matplotlib only
    ``"inferno"``), else :class:`ParameterError`."""
    if not isinstance(cmap, str):
        if callable(cmap):
            return cmap
        raise ParameterError(f"cmap must be a colormap name, got {cmap!r}")
    try:
        known = mpl().colormaps
    except ImportError:
        known = ("inferno",)
    if cmap not in known:
        raise ParameterError(
            f"unknown colormap {cmap!r}; matplotlib's include {', '.join(SUGGESTED_CMAPS)} "
            "(and each reversed with _r)"
        )
    return cmap


def colormap(cmap):
    """The matplotlib colormap named ``cmap`` (or ``cmap`` itself if it is one)."""
    return mpl().colormaps[cmap] if isinstance(cmap, str) else cmap


def _rgba(values: np.ndarray, cmap, vmin: float, vmax: float) -> np.ndarray:
    """``(N, 4)`` float RGBA in ``[0, 1]`` of ``(N,)`` values clipped to ``[vmin, vmax]``;
    non-finite values are mid grey."""
    with np.errstate(invalid="ignore"):
        unit = np.clip((values - vmin) / (vmax - vmin), 0.0, 1.0)
    finite = np.isfinite(unit)
    unit = np.where(finite, unit, 0.0)
    try:
        rgba = np.asarray(colormap(cmap)(unit), dtype=np.float64)
    except ImportError:
        if cmap != "inferno":
            raise
        knots = np.linspace(0.0, 1.0, _INFERNO_17.shape[0])
        rgb = np.stack([np.interp(unit, knots, _INFERNO_17[:, i]) for i in range(3)], axis=1)
        rgba = np.concatenate([rgb / 255.0, np.ones((unit.shape[0], 1))], axis=1)
    rgba[~finite] = (0.5, 0.5, 0.5, 1.0)
    return rgba


def scalar_colors(
    values, cmap: str = "inferno", vmin: float | None = None, vmax: float | None = None
) -> np.ndarray:
    """``(V, 4)`` uint8 RGBA colours of ``(V,)`` values (array or tensor), e.g. a PLY's
    vertex colours: ``cmap`` a colormap name or object; ``vmin`` / ``vmax`` ``None``: the 1st /
    99th percentile (:func:`robust_range`); non-finite values are mid grey."""
    values = as_numpy(values, np.float64).reshape(-1)
    lo, hi = robust_range(values, vmin=vmin, vmax=vmax)
    return np.round(_rgba(values, cmap, lo, hi) * 255.0).astype(np.uint8)


def vertex_colors(values: np.ndarray, cmap, vmin: float, vmax: float) -> np.ndarray:
    """``(V, 3)`` float RGB in ``[0, 1]`` of ``(V,)`` vertex ``values`` (mid grey where not
    finite)."""
    return _rgba(values, cmap, vmin, vmax)[:, :3]


def face_colors(values: np.ndarray, faces: np.ndarray, cmap, vmin: float, vmax: float):
    """``(F, 3)`` float RGB in ``[0, 1]``: each face coloured by the mean of its ``(V,)``
    vertex ``values`` (mid grey where that mean is not finite)."""
    return _rgba(values[faces].mean(axis=1), cmap, vmin, vmax)[:, :3]
