"""Pictures of meshes, per-vertex scalar fields and evaluation curves (PNG files).

matplotlib is an optional dependency (``pip install "stochlap_torch[viz]"``), imported only
when a picture is drawn; :func:`scalar_colors` works without it. Figures are drawn on
matplotlib's Agg canvas without pyplot, and every file is written atomically.

Modules, in drawing order:

* :mod:`.colors`: the robust colour range, where it clips, and colormaps (numpy only);
* :mod:`.framing`: which way is up (``up``, and the guess when it is not given, which stands
  a mesh lying on its side upright), the drawing frame of a mesh and the views (a count,
  names such as ``"front,side,top"`` or ``(elevation, azimuth)`` pairs);
* :mod:`.decimate`: large meshes are drawn from a decimated copy (``max_faces``);
* :mod:`.shading`: normals, shading, back faces and the visibility of points (numpy only);
* :mod:`.drawing`: mesh panels, colour bar and title on a figure;
* :mod:`.backend`: importing matplotlib, new figures, writing PNG files;
* :mod:`.render`: the mesh figures; :mod:`.curves`: the interest-point error curves.
"""

from .colors import robust_range, scalar_colors
from .curves import plot_error_curves
from .decimate import DRAW_FACES
from .framing import UP_AXES, VIEW_NAMES, default_views, guess_up, resolve_views
from .render import render_interest_points, render_multiscale, render_scalar

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
