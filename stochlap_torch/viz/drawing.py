"""Drawing on a figure: orthographic mesh panels (one ``Poly3DCollection`` each, sorted far
to near by matplotlib, zoomed to fill the panel), the colour bar, titles and layout."""

from __future__ import annotations

import numpy as np

from .backend import save_figure
from .colors import clipped_ends, colormap
from .shading import Geometry

#: Inches below the mesh panels kept for the colour bar, and the bar's distance from the bottom.
BAR_SPACE = 0.95
_BAR_BOTTOM = 0.5
#: Inches above the panels kept for a title.
TITLE_SPACE = 0.45


def panel_rects(count: int, bottom: float, top: float) -> list[list[float]]:
    """``count`` side-by-side ``[left, bottom, width, height]`` rectangles (figure fractions)
    between the heights ``bottom`` and ``top``."""
    width = 1.0 / count
    return [[i * width, bottom, width, top - bottom] for i in range(count)]


def grid_rects(rows: int, columns: int, bottom: float, top: float) -> list[list[list[float]]]:
    """``rows`` lists (top row first) of ``columns`` :func:`panel_rects`, stacked between the
    heights ``bottom`` and ``top``."""
    height = (top - bottom) / rows
    return [panel_rects(columns, top - (r + 1) * height, top - r * height) for r in range(rows)]


def mesh_axes(
    fig, rect, frame: np.ndarray, radius: float, elev: float, azim: float, fill: float = 0.94
):
    """A bare orthographic 3D axes on the cube ``[-radius, radius]^3`` seen from
    ``(elev, azim)``, zoomed so that the ``(V, 3)`` points ``frame`` fill the fraction
    ``fill`` of the panel ``rect``."""
    from mpl_toolkits.mplot3d import proj3d

    ax = fig.add_axes(rect, projection="3d")
    ax.set_proj_type("ortho")
    ax.view_init(elev=elev, azim=azim)
    for setter in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
        setter(-radius, radius)
    ax.set_box_aspect((1.0, 1.0, 1.0), zoom=1.0)
    ax.set_axis_off()
    ax.computed_zorder = False
    # The projection is known before drawing: measure the mesh at zoom 1 and scale to fit.
    xs, ys, _ = proj3d.proj_transform(frame[:, 0], frame[:, 1], frame[:, 2], ax.get_proj())
    pixels = ax.transData.transform(np.column_stack([xs, ys]))
    x0, y0, width, height = ax.bbox.bounds
    reach_x = np.abs(pixels[:, 0] - (x0 + width / 2)).max()
    reach_y = np.abs(pixels[:, 1] - (y0 + height / 2)).max()
    if np.isfinite(reach_x) and np.isfinite(reach_y) and max(reach_x, reach_y) > 0:
        zoom = fill * min(width / 2 / max(reach_x, 1e-9), height / 2 / max(reach_y, 1e-9))
        ax.set_box_aspect((1.0, 1.0, 1.0), zoom=float(np.clip(zoom, 0.1, 10.0)))
    return ax


def draw_mesh(ax, frame, faces, geometry: Geometry, face_rgb, elev: float, azim: float):
    """Add the shaded faces of ``(V, 3)`` ``frame`` visible from ``(elev, azim)`` to ``ax``,
    coloured by ``(F, 3)`` ``face_rgb``; returns the ``Poly3DCollection``."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    keep = geometry.front_faces(elev, azim)
    shade = geometry.shade(faces, keep, elev, azim)
    colors = np.clip(face_rgb[keep] * shade[:, None], 0.0, 1.0)
    # Anti-aliased triangles leave seams that let the background and hidden faces show
    # through; save_figure supersamples the whole figure instead.
    style = {"edgecolors": "none", "linewidths": 0.0, "antialiased": False, "zsort": "average"}
    collection = Poly3DCollection(frame[faces[keep]], facecolors=colors, **style)
    collection.set_zorder(1)
    ax.add_collection3d(collection)
    return collection


def add_colorbar(fig, rect, cmap, vmin: float, vmax: float, label: str | None, span=None):
    """A horizontal colour bar for ``[vmin, vmax]`` in ``rect`` (figure fractions).

    ``span`` is the ``(min, max)`` of the values shown (or ``None``): an end of the range
    that clips values gets an arrow (matplotlib's ``extend``) and, beyond it, the true extreme
    (``max 2.86``), so that a clipped value is never read off as the end of the bar."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.ticker import MaxNLocator

    cax = fig.add_axes(rect)
    mappable = ScalarMappable(norm=Normalize(vmin=vmin, vmax=vmax), cmap=colormap(cmap))
    extend = clipped_ends(span, vmin, vmax)
    bar = fig.colorbar(mappable, cax=cax, orientation="horizontal", extend=extend)
    if label:
        bar.set_label(label, fontsize=10)
    width_inches = rect[2] * fig.get_size_inches()[0]
    bar.locator = MaxNLocator(nbins=max(3, int(width_inches * 2.2)))
    bar.update_ticks()
    bar.ax.tick_params(labelsize=8)
    # The true extreme past the arrow (drawn outside the axes, about a bar height long).
    height_points = cax.get_position().height * fig.get_size_inches()[1] * 72.0
    where = {"xycoords": "axes fraction", "textcoords": "offset points", "annotation_clip": False}
    for end, side, align in (("min", 0, "right"), ("max", 1, "left")):
        if extend in (end, "both"):
            offset = ((2 * side - 1) * (1.5 * height_points + 4.0), 0.0)
            text = f"{end} {span[side]:.3g}"
            cax.annotate(text, (side, 0.5), offset, ha=align, va="center", fontsize=8, **where)
    return bar


def add_title(fig, title: str | None) -> None:
    """The figure title at the top, if any."""
    if title:
        height = fig.get_size_inches()[1]
        fig.suptitle(title, fontsize=13, y=1.0 - 0.08 / height, va="top")


def finish_with_colorbar(fig, cmap, vmin: float, vmax: float, label, title, path, span=None):
    """Add the centred colour bar (:func:`add_colorbar`) and the title; write the figure."""
    width, height = fig.get_size_inches()
    bar_width = min(0.6, 3.6 / width)
    rect = [0.5 - bar_width / 2, _BAR_BOTTOM / height, bar_width, 0.16 / height]
    add_colorbar(fig, rect, cmap, vmin, vmax, label, span)
    add_title(fig, title)
    return save_figure(fig, path)
