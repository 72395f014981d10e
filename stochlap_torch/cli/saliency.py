"""``stochlap saliency``: per-vertex saliency to a coloured PLY file and a picture.

Compute mesh saliency and write a binary PLY with saliency as vertex colours and a
'saliency' float property, plus a PNG picture. Default outputs: <stem>_saliency.ply and
<stem>_saliency.png in the current directory.
"""

from __future__ import annotations

import time

from . import common, options

HELP = "per-vertex saliency to a coloured PLY and a picture"


def add_arguments(parser) -> None:
    options.add_mesh_arguments(parser, output=("PLY", "output PLY file"), variant=True)
    options.add_picture_options(parser)


def resolve_settings(args) -> None:
    """Set ``args.params`` from ``--variant``, ``-K`` and ``--threshold``, before any file is
    read or written: an option the variant does not use is a user error (exit 2)."""
    from ..saliency_maps import saliency_params

    with common.usage_errors():
        args.params = saliency_params(
            args.variant, num_scales=args.num_scales, threshold=args.threshold
        )


def compute_saliency(args, mesh):
    """``(V,)`` saliency of ``mesh`` with the settings of :func:`resolve_settings`, progress
    on stderr."""
    from ..saliency_maps import mesh_saliency

    progress = common.Progress("saliency", args.quiet)
    return mesh_saliency(
        mesh.vertices, mesh.faces, variant=args.variant, params=args.params, progress=progress
    )


def draw_saliency(args, png_path, mesh, saliency, title: str, points=None) -> None:
    """The picture (if any) of ``(V,)`` ``saliency`` on ``mesh``, ``points`` as markers."""
    from ..viz import render_scalar

    arrays = (mesh.vertices, mesh.faces, saliency)
    common.draw_picture(
        args, png_path, render_scalar, *arrays, title=title, up=args.up, points=points
    )


def run(args) -> int:
    resolve_settings(args)
    path, mesh, ply_path, png_path = common.open_mesh_and_outputs(args, "saliency", "ply")
    start = time.perf_counter()
    saliency = compute_saliency(args, mesh).detach().cpu().double().numpy()
    seconds = time.perf_counter() - start
    settings = common.compute_settings(args)
    stats = f"min {saliency.min():.4g}, max {saliency.max():.4g}, mean {saliency.mean():.4g}"
    common.say(args, f"saliency ({settings}) in {seconds:.2f} s: {stats}")

    from ..mesh import save_ply
    from ..viz import robust_range, scalar_colors

    vmin, vmax = robust_range(saliency, mesh.faces)  # of the vertices the faces use
    colors = scalar_colors(saliency, vmin=vmin, vmax=vmax)
    save_ply(ply_path, mesh.vertices, mesh.faces, colors=colors, scalars={"saliency": saliency})
    common.say(args, f"wrote {ply_path}")
    draw_saliency(args, png_path, mesh, saliency, f"{path.name}: saliency ({settings})")
    return 0
