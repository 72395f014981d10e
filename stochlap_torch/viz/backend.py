"""matplotlib without pyplot (no backend change, no window): a figure on the Agg canvas, and
PNG files written atomically."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .._common.errors import MissingDependencyError
from .._common.files import atomic_write

logger = logging.getLogger(__name__)

#: Figures are drawn this many times larger and filtered down (anti-aliasing of triangles
#: smaller than a pixel, silhouettes and markers), the large image within about this many pixels.
SUPERSAMPLE = 3
_MAX_DRAW_PIXELS = 40_000_000


def mpl():
    """Import matplotlib, or a :class:`MissingDependencyError` saying how to install it."""
    try:
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
    except ImportError as exc:
        hint = 'pip install "stochlap_torch[viz]"'
        raise MissingDependencyError(f"stochlap_torch.viz needs matplotlib: {hint}") from exc
    return matplotlib


def new_figure(figsize: tuple[float, float], dpi: float):
    """A white ``matplotlib.figure.Figure`` of ``figsize`` inches on its own Agg canvas."""
    mpl()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig, path, supersample: int = SUPERSAMPLE) -> Path:
    """Write ``fig`` as an RGB PNG of ``figsize * dpi`` pixels, drawn ``supersample`` times
    larger on its canvas and box-filtered down (:data:`SUPERSAMPLE`); a function of the
    figure only (no time stamp), so renders are reproducible. Returns the path."""
    from PIL import Image  # a dependency of matplotlib

    path = Path(path)
    width, height = (round(x * fig.dpi) for x in fig.get_size_inches())
    factor = max(1, min(supersample, int((_MAX_DRAW_PIXELS / max(1, width * height)) ** 0.5)))
    dpi = fig.dpi
    fig.set_dpi(dpi * factor)
    try:
        fig.canvas.draw()
        image = Image.fromarray(np.asarray(fig.canvas.buffer_rgba())).convert("RGB")
    finally:
        fig.set_dpi(dpi)
    if image.size != (width, height):
        image = image.resize((width, height), Image.Resampling.BOX)
    try:
        with atomic_write(path, "wb") as handle:
            image.save(handle, "PNG")
    except OSError as exc:
        if exc.filename is None:  # a failed write names the file it was for
            exc.filename = str(path)
        raise
    logger.info("wrote %s", path)
    return path
