"""matplotlib without pyplot: importing it, a figure on the Agg canvas, and writing PNG files.

Nothing here changes the caller's matplotlib backend or opens a window. Every PNG is written
through :func:`~stochlap_torch._common.files.atomic_write`: an existing file is replaced only
once the new one is complete.
"""

from __future__ import annotations

import io
import logging
from pathlib import Path

from .._common.errors import MissingDependencyError
from .._common.files import atomic_write

__all__ = ["VIZ_HINT", "mpl", "new_figure", "save_figure"]

logger = logging.getLogger(__name__)

#: How to install the pictures' dependency.
VIZ_HINT = 'pip install "stochlap_torch[viz]"'

#: Figures are drawn this many times larger and filtered down (anti-aliasing of the meshes),
#: keeping the large intermediate image within about this many pixels.
SUPERSAMPLE = 3
_MAX_DRAW_PIXELS = 40_000_000


def mpl():
    """Import matplotlib (and register the 3D projection), or explain how to install it.

    Raises:
        MissingDependencyError: matplotlib is not installed.
    """
    try:
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
        from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers projection="3d")
    except ImportError as exc:
        raise MissingDependencyError(f"stochlap_torch.viz needs matplotlib: {VIZ_HINT}") from exc
    return matplotlib


def new_figure(figsize: tuple[float, float], dpi: float):
    """A white ``matplotlib.figure.Figure`` of ``figsize`` inches on its own Agg canvas."""
    mpl()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def _supersample_factor(width: int, height: int, requested: int) -> int:
    """``requested``, lowered so that the drawing stays within ``_MAX_DRAW_PIXELS``."""
    return max(1, min(requested, int((_MAX_DRAW_PIXELS / max(1, width * height)) ** 0.5)))


def save_figure(fig, path, supersample: int = SUPERSAMPLE) -> Path:
    """Write ``fig`` as an RGB PNG of ``figsize * dpi`` pixels.

    The figure is drawn ``supersample`` times larger and box-filtered down, so that the
    (non anti-aliased) mesh triangles come out smooth. The output is a function of the figure
    only (no time stamp or version in the file), so renders are reproducible.

    Returns:
        The path written.
    """
    from PIL import Image  # a dependency of matplotlib

    path = Path(path)
    width, height = (round(x * fig.dpi) for x in fig.get_size_inches())
    factor = _supersample_factor(width, height, supersample)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=fig.dpi * factor, facecolor="white")
    buffer.seek(0)
    with Image.open(buffer) as drawn:
        image = drawn.convert("RGB")
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
