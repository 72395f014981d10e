"""Pictures of meshes, per-vertex scalar fields and evaluation curves (PNG files).

matplotlib is an optional dependency (``pip install "stochlap_torch[viz]"``), imported only
when a picture is drawn; :func:`scalar_colors` works without it. Figures are drawn on
matplotlib's Agg canvas without pyplot, and every file is written atomically.

Modules, in drawing order:

* :mod:`.colors`: the robust colour range and colormaps (numpy only);
* :mod:`.framing`: which way is up (``up``, and the guess when it is not given), the drawing
  frame of a mesh and the views;
* :mod:`.shading`: normals, shading, back faces and the visibility of points (numpy only);
* :mod:`.drawing`: mesh panels, colour bar and title on a figure;
* :mod:`.backend`: importing matplotlib, new figures, writing PNG files;
* :mod:`.render`: the mesh figures; :mod:`.curves`: the interest-point error curves.
"""

from .colors import robust_range, scalar_colors
from .curves import plot_error_curves
from .framing import UP_AXES, default_views, guess_up
from .render import render_interest_points, render_multiscale, render_scalar

__all__ = [
    "UP_AXES",
    "default_views",
    "guess_up",
    "plot_error_curves",
    "render_interest_points",
    "render_multiscale",
    "render_scalar",
    "robust_range",
    "scalar_colors",
]
