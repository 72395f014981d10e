"""Pictures of meshes, per-vertex scalar fields and evaluation curves (PNG files).

matplotlib is an optional dependency (``pip install "stochlap_torch[viz]"``), imported only
when a picture is drawn; :func:`scalar_colors` works without it.
"""

from .colors import robust_range, scalar_colors
from .decimate import DRAW_FACES
from .framing import UP_AXES, VIEW_NAMES, default_views, guess_up, resolve_views
from .render import plot_error_curves, render_interest_points, render_multiscale, render_scalar

__all__ = [
    "DRAW_FACES",
    "UP_AXES",
    "VIEW_NAMES",
    "default_views",
    "guess_up",
    "plot_error_curves",
    "render_interest_points",
    "render_multiscale",
    "render_scalar",
    "resolve_views",
    "robust_range",
    "scalar_colors",
]
