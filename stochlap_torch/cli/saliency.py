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


def stats(values) -> str:
    """``min .., max .., mean ..`` of a tensor."""
    values = values.detach().double()
    low, high, mean = values.min().item(), values.max().item(), values.mean().item()
    return f"min {low:.4g}, max {high:.4g}, mean {mean:.4g}"


def resolve_settings(args) -> None:
    """Set ``args.params`` from ``--variant``, ``-K`` and ``--threshold``, before any file is
    read or written: an option the variant does not use is a user error (exit 2)."""
    from ..saliency_maps import saliency_params

    with common.usage_errors():
        args.params = saliency_params(
            args.variant, num_scales=args.num_scales, threshold=args.threshold
        )


def compute_saliency(args, mesh):
    """Saliency of ``mesh`` with the command's resolved settings (:func:`resolve_settings`),
    progress on stderr."""
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
    values = compute_saliency(args, mesh)
    seconds = time.perf_counter() - start
    common.say(
        args, f"saliency ({common.compute_settings(args)}) in {seconds:.2f} s: {stats(values)}"
    )

    from ..mesh import save_ply
    from ..viz import robust_range, scalar_colors

    saliency = values.detach().cpu().double().numpy()
    vmin, vmax = robust_range(saliency, mesh.faces)  # of the vertices the faces use
    colors = scalar_colors(saliency, vmin=vmin, vmax=vmax)
    save_ply(ply_path, mesh.vertices, mesh.faces, colors=colors, scalars={"saliency": saliency})
    common.say(args, f"wrote {ply_path}")
    title = f"{path.name}: saliency ({common.compute_settings(args)})"
    draw_saliency(args, png_path, mesh, saliency, title)
    return 0
