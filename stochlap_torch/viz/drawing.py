"""Drawing on a figure: orthographic mesh panels (2D axes, each mesh projected here and drawn
far to near as one artist of Gouraud-shaded triangles, zoomed to fill the panel), the colour
bar, titles and layout."""

from __future__ import annotations

from functools import cache

import numpy as np

from .backend import save_figure
from .colors import clipped_ends, colormap
from .framing import screen_axes
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
    """A bare 2D axes in the panel ``rect`` for the orthographic view ``(elev, azim)`` of the
    drawing frame (:func:`~stochlap_torch.viz.framing.screen_axes`; its origin at the panel's
    centre, equal scales), zoomed so that the ``(V, 3)`` points ``frame`` fill the fraction
    ``fill`` of the panel (the sphere of ``radius`` when they have no extent)."""
    ax = fig.add_axes(rect)
    ax.set_axis_off()
    flat = frame[np.isfinite(frame).all(axis=1)] @ screen_axes(elev, azim)[:2].T
    reach = np.abs(flat).max(axis=0) if flat.size else np.zeros(2)
    width, height = rect[2] * fig.get_size_inches()[0], rect[3] * fig.get_size_inches()[1]
    # Data units per inch: the larger of what each direction needs.
    scale = max(reach[0] / (fill * width / 2), reach[1] / (fill * height / 2))
    if not (np.isfinite(scale) and scale > 0):
        scale = radius / (fill * min(width, height) / 2)
    ax.set_xlim(-scale * width / 2, scale * width / 2)
    ax.set_ylim(-scale * height / 2, scale * height / 2)
    return ax


@cache
def _triangles_class():
    """An artist of triangles with a colour at each corner, interpolated across the triangle
    (Gouraud) and drawn in the order given, in one call of the renderer."""
    from matplotlib.artist import Artist

    class Triangles(Artist):
        def __init__(self, corners: np.ndarray, rgba: np.ndarray):
            super().__init__()
            self.corners, self.rgba = corners, rgba

        def draw(self, renderer):
            if not self.get_visible() or not len(self.corners):
                return
            gc = renderer.new_gc()
            transform = self.get_transform().frozen()
            renderer.draw_gouraud_triangles(gc, self.corners, self.rgba, transform)
            gc.restore()

    return Triangles


def draw_mesh(ax, frame, faces, geometry: Geometry, rgb, elev: float, azim: float, smooth=True):
    """Add the faces of ``(V, 3)`` ``frame`` drawn from ``(elev, azim)`` to the 2D ``ax`` of
    :func:`mesh_axes`, far to near (painter's algorithm; the back faces of a closed mesh
    culled), coloured by ``rgb``: ``(F, 3)`` per face or ``(F, 3, 3)`` per corner, lit per
    corner (:meth:`Geometry.shade`, flat unless ``smooth``). Returns the artist."""
    screen = frame @ screen_axes(elev, azim).T
    keep = geometry.front_faces(elev, azim)
    keep = keep[np.argsort(screen[faces[keep], 2].sum(axis=1), kind="stable")]
    shade = geometry.shade(faces, keep, elev, azim, smooth)
    rgb = np.asarray(rgb, dtype=np.float64)[keep]
    corners = rgb[:, None, :] if rgb.ndim == 2 else rgb
    rgba = np.ones((keep.shape[0], 3, 4))
    rgba[..., :3] = np.clip(corners * shade[..., None], 0.0, 1.0)
    artist = _triangles_class()(screen[faces[keep], :2], rgba)
    artist.set_zorder(1)
    ax.add_artist(artist)
    return artist


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
    # Room beside the bar for the notes of clipped ends ("min -0.737"), about an inch each.
    bar_width = min(0.6, 3.6 / width, max(0.3, 1.0 - 2.2 / width))
    rect = [0.5 - bar_width / 2, _BAR_BOTTOM / height, bar_width, 0.16 / height]
    add_colorbar(fig, rect, cmap, vmin, vmax, label, span)
    add_title(fig, title)
    return save_figure(fig, path)
