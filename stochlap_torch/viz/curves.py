"""Interest-point error curves: FNE, FPE and WME against the localisation radius (Fig. 15)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from ._arrays import check_dpi
from .backend import new_figure, save_figure

_PANELS = (("fne", "FNE"), ("fpe", "FPE"), ("wme", "WME"))
_MARKERS = "osD^v<>p"


def plot_error_curves(
    radii: Sequence[float],
    per_method: Mapping[str, Mapping[str, Sequence[float]]],
    path: str | Path,
    title: str | None = None,
    dpi: float = 110,
) -> Path:
    """Draw FNE, FPE and WME against the ``(R,)`` ``radii`` (fractions of the mesh diameter)
    as three panels of a ``12 x 3.8`` inch figure, one line per method of ``per_method``
    (``{method: {"fne": (R,), "fpe": (R,), "wme": (R,)}}``, e.g. the ``mean`` of
    :func:`~stochlap_torch.evaluation.mean_error_curves`); returns the PNG ``path``."""
    fig = new_figure((12.0, 3.8), check_dpi(dpi))
    axes = fig.subplots(1, len(_PANELS))
    for ax, (key, name) in zip(axes, _PANELS, strict=True):
        for i, (method, values) in enumerate(per_method.items()):
            marker = _MARKERS[i % len(_MARKERS)]
            ax.plot(list(radii), list(values[key]), marker=marker, ms=4, label=method)
        ax.set_xlabel("tolerance r (fraction of mesh diameter)")
        ax.set_ylabel(name)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path, supersample=1)
