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
from .saliency import compute_saliency, draw_saliency, resolve_settings

HELP = "interest points (local saliency maxima) to a text file and a picture"


def add_arguments(parser) -> None:
    options.add_mesh_arguments(parser, output=("TXT", "output points file"), variant=True)
    options.add_detector_options(parser, t_global=True)
    parser.add_argument(
        "--include-boundary",
        action="store_true",
        help="let vertices on the rim of a hole be interest points (default: not, the "
        "saliency jumps along an open edge)",
    )
    options.add_picture_options(parser)


def point_line(index: int, xyz, saliency: float) -> str:
    """One line of the points file: ``vertex x y z saliency``."""
    x, y, z = xyz
    return f"{index} {x:.9g} {y:.9g} {z:.9g} {saliency:.9g}"


def run(args) -> int:
    from ..interest import check_interest_parameters, interest_points

    resolve_settings(args)
    with common.usage_errors():  # --radius is nms's alone; its default filled in
        _, args.radius, _, _ = check_interest_parameters(
            args.mode, args.radius, args.top_k, args.t_global
        )
    path, mesh, txt_path, png_path = common.open_mesh_and_outputs(args, "interest", "txt")
    start = time.perf_counter()
    values = compute_saliency(args, mesh)
    detector = {name: getattr(args, name) for name in ("mode", "radius", "top_k", "t_global")}
    points = interest_points(
        values, mesh.vertices, mesh.faces, **detector, include_boundary=args.include_boundary
    )
    seconds = time.perf_counter() - start
    radius = f", radius={args.radius:g}" if args.radius is not None else ""
    settings = f"mode={args.mode}{radius}, {common.compute_settings(args)}"
    common.say(args, f"{points.numel()} interest points ({settings}) in {seconds:.2f} s")

    indices = points.detach().cpu().tolist()
    xyz = mesh.vertices.detach().cpu().double()[points.cpu()].tolist()
    saliency = values.detach().cpu().double().numpy()
    listed = saliency.tolist()
    header = (
        f"# vertex x y z saliency  ({path.name}, mode={args.mode}{radius}, "
        f"top_k={args.top_k}, t_global={args.t_global:g}, "
        f"include_boundary={args.include_boundary}, {common.compute_settings(args)}; "
        "most salient first)"
    )
    lines = (point_line(i, p, listed[i]) + "\n" for i, p in zip(indices, xyz, strict=True))
    common.write_text(txt_path, itertools.chain([header + "\n"], lines))
    common.say(args, f"wrote {txt_path}")
    title = f"{path.name}: {len(indices)} interest points ({args.mode})"
    draw_saliency(args, png_path, mesh, saliency, title, indices)
    return 0
