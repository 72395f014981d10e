"""``stochlap interest``: interest points (local saliency maxima) to a text file and a picture.

Detect interest points and write one per line, most salient first, as 'vertex x y z
saliency' after a '#' header line. Default outputs: <stem>_interest.txt and
<stem>_interest.png.

In the points file, the vertex index is 0-based and coordinates and saliency have 9 digits.
"""

from __future__ import annotations

import itertools
import time

from . import common, options
from .outputs import write_lines
from .saliency import compute_saliency, draw_saliency, resolve_settings

HELP = "interest points (local saliency maxima) to a text file and a picture"


def add_arguments(parser) -> None:
    options.add_mesh_arguments(parser, output=("TXT", "output points file"), variant=True)
    options.add_detector_options(parser, t_global=True)
    options.add_picture_options(parser)


def point_line(index: int, xyz, saliency: float) -> str:
    """One line of the points file: ``vertex x y z saliency``."""
    x, y, z = xyz
    return f"{index} {x:.9g} {y:.9g} {z:.9g} {saliency:.9g}"


def resolve_detector(args) -> None:
    """Check the detector's options before any work (``--radius`` is ``nms``'s alone: a user
    error with ``--mode paper``) and fill in ``args.radius``'s default."""
    from ..interest import check_interest_parameters

    with common.usage_errors():
        _, args.radius, _, _ = check_interest_parameters(
            args.mode, args.radius, args.top_k, args.t_global
        )


def run(args) -> int:
    resolve_settings(args)
    resolve_detector(args)
    path, mesh, txt_path, png_path = common.open_mesh_and_outputs(args, "interest", "txt")

    from ..interest import interest_points

    start = time.perf_counter()
    values = compute_saliency(args, mesh)
    detector = {name: getattr(args, name) for name in ("mode", "radius", "top_k", "t_global")}
    points = interest_points(values, mesh.vertices, mesh.faces, **detector)
    radius = f", radius={args.radius:g}" if args.radius is not None else ""
    seconds = time.perf_counter() - start
    settings = f"mode={args.mode}{radius}, {common.compute_settings(args)}"
    common.say(args, f"{points.numel()} interest points ({settings}) in {seconds:.2f} s")

    indices = points.detach().cpu().tolist()
    xyz = mesh.vertices.detach().cpu().double()[points.cpu()].tolist()
    saliency = values.detach().cpu().double().numpy()
    header = (
        f"# vertex x y z saliency  ({path.name}, mode={args.mode}{radius}, "
        f"top_k={args.top_k}, t_global={args.t_global:g}, {common.compute_settings(args)}; "
        "most salient first)"
    )
    listed = saliency.tolist()
    lines = (point_line(i, p, listed[i]) for i, p in zip(indices, xyz, strict=True))
    write_lines(txt_path, itertools.chain([header], lines))
    common.say(args, f"wrote {txt_path}")
    title = f"{path.name}: {len(indices)} interest points ({args.mode})"
    draw_saliency(args, png_path, mesh, saliency, title, indices)
    return 0
