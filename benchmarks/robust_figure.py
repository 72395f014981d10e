"""The README's picture of the two saliency variants at two resolutions.

A 2x2 grid: rows the paper's saliency (Algorithm 2) and the robust one, columns the full mesh
and its quadric decimation to 1/10 of the vertices; one view, one colour map. Colour is each
vertex's percentile within its own mesh (the rank the benchmark's Spearman correlations
compare), so the four panels share one scale whatever the variants' units. Run from the
repository root::

    python benchmarks/robust_figure.py [--mesh horse_48k.ply] [--out PATH]

(``python benchmarks/robust.py --figure`` draws it too.)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import robust_common as robust

OUT = robust.REPO / "docs" / "figures" / "variants_two_resolutions.png"
VARIANTS = ("paper", "robust")
CMAP = "inferno"
#: Up axes of the meshes whose guess (:func:`~stochlap_torch.viz.guess_up`) is wrong.
UP = {"horse_48k.ply": "z"}


def percentile(values: np.ndarray) -> np.ndarray:
    """``(V,)`` rank of every value, scaled to ``[0, 1]``."""
    return np.argsort(np.argsort(values, kind="stable"), kind="stable") / max(len(values) - 1, 1)


def draw(meshes, saliency, rho, out: Path, view, up: str | None, title: str) -> Path:
    """The 2x2 figure: ``meshes`` = [(v, f) full, (v, f) decimated], ``saliency[variant][i]``
    per mesh, ``rho[variant]`` the Spearman correlation of the decimated one with the full."""
    from stochlap_torch.viz.backend import new_figure, save_figure
    from stochlap_torch.viz.colors import face_colors
    from stochlap_torch.viz.drawing import add_colorbar, add_title, draw_mesh, mesh_axes
    from stochlap_torch.viz.framing import frame_axes
    from stochlap_torch.viz.shading import Geometry

    width, height = 7.2, 7.0
    fig = new_figure((width, height), dpi=100)
    rotation, centre, radius = frame_axes(meshes[0][0], up, meshes[0][1])
    frames = [(v - centre) @ rotation.T for v, _ in meshes]
    bottom, top = 0.85 / height, 1.0 - 0.55 / height
    panel = (top - bottom) / 2
    elev, azim = view
    for row, variant in enumerate(VARIANTS):
        for col, ((v, f), frame) in enumerate(zip(meshes, frames, strict=True)):
            rect = [0.5 * col, top - (row + 1) * panel, 0.5, panel - 0.3 / height]
            ax = mesh_axes(fig, rect, frames[0], radius, elev, azim)
            colours = face_colors(percentile(saliency[variant][col]), f, CMAP, 0.0, 1.0)
            draw_mesh(ax, frame, f, Geometry(frame, f), colours, elev, azim)
            label = f"{variant} saliency, {len(v)} vertices"
            if col:
                label += f"\nSpearman with full mesh: {rho[variant]:.2f}"
            fig.text(
                rect[0] + 0.25,
                rect[1] + rect[3] + 0.02 / height,
                label,
                ha="center",
                va="bottom",
                fontsize=10,
            )
    add_colorbar(
        fig,
        [0.25, 0.45 / height, 0.5, 0.14 / height],
        CMAP,
        0.0,
        1.0,
        "saliency percentile within the mesh",
    )
    add_title(fig, title)
    return save_figure(fig, out)


def main(argv=None) -> Path:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--mesh", default="horse_48k.ply")
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument("--view", default="5,-90", help="elevation,azimuth in degrees")
    parser.add_argument("--up", default=None, help="the file's up axis (default: guessed)")
    args = parser.parse_args(argv)
    from scipy.spatial import cKDTree

    robust.pin_threads()
    full = robust.load(args.mesh)
    low = robust.copy_of(args.mesh, *full, "dec10")
    nearest = cKDTree(low[0]).query(full[0])[1]
    saliency, rho = {}, {}
    for variant in VARIANTS:
        saliency[variant] = [robust.saliency(*mesh, variant) for mesh in (full, low)]
        rho[variant] = robust.spearman(saliency[variant][0], saliency[variant][1][nearest])
    view = tuple(float(x) for x in args.view.split(","))
    title = f"{Path(args.mesh).stem}: the same surface at two resolutions"
    up = args.up or UP.get(args.mesh)
    return draw([full, low], saliency, rho, Path(args.out), view, up, title)


if __name__ == "__main__":
    print(main(sys.argv[1:]))
