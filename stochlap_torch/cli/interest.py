"""``stochlap interest``: interest points (local saliency maxima) to a text file and a picture.

The points file has a ``#`` header line, then one point per line, most salient first:
``vertex x y z saliency`` (0-based vertex index, coordinates and saliency to 9 digits).
"""

from __future__ import annotations

import time

from . import common
from .outputs import check_outputs, default_output, write_lines
from .saliency import compute_saliency

NAME = "interest"
HELP = "interest points (local saliency maxima) to a text file and a picture"
DESCRIPTION = (
    "Detect interest points and write one per line, most salient first, as "
    "'vertex x y z saliency' after a '#' header line. Default outputs: <stem>_interest.txt "
    "and <stem>_interest.png."
)
MODES = ("nms", "paper")


def add_parser(commands, parents):
    parser = commands.add_parser(NAME, parents=parents, help=HELP, description=DESCRIPTION)
    common.add_mesh_argument(parser)
    parser.add_argument("-o", "--output", metavar="TXT", help="output points file")
    common.add_compute_options(parser)
    parser.add_argument(
        "--mode",
        choices=MODES,
        default="nms",
        help="nms: well-separated maxima (default); paper: every 1-ring maximum above t_global",
    )
    parser.add_argument(
        "--radius",
        type=common.positive_float,
        default=0.1,
        help="nms suppression radius, fraction of the bounding-box diagonal (default: 0.1)",
    )
    parser.add_argument(
        "--top-k", type=common.positive_int, metavar="N", help="keep at most N points"
    )
    parser.add_argument(
        "--t-global",
        type=common.closed_unit,
        default=0.4,
        help="fraction of the saliency range a point must reach (default: 0.4)",
    )
    common.add_picture_options(parser)
    parser.set_defaults(handler=run)
    return parser


def point_line(index: int, xyz, saliency: float) -> str:
    """One line of the points file: ``vertex x y z saliency``."""
    x, y, z = xyz
    return f"{index} {x:.9g} {y:.9g} {z:.9g} {saliency:.9g}"


def _lines(header: str, indices, xyz, saliency):
    yield header
    for index, position in zip(indices, xyz, strict=True):
        yield point_line(index, position, saliency[index])


def run(args) -> int:
    path = common.mesh_path(args.mesh)
    txt_path = default_output(args.output, path, NAME, "txt")
    png_path = default_output(args.png, path, NAME, "png")
    check_outputs([("mesh", path)], [("-o", txt_path), ("--png", png_path)])
    if not common.want_picture(args):
        png_path = None
    mesh = common.load_mesh_arg(args, path)

    from ..interest import interest_points

    start = time.perf_counter()
    values = compute_saliency(args, mesh)
    points = interest_points(
        values,
        mesh.vertices,
        mesh.faces,
        mode=args.mode,
        radius=args.radius,
        top_k=args.top_k,
        t_global=args.t_global,
    )
    radius = f", radius={args.radius:g}" if args.mode == "nms" else ""
    common.say(
        args,
        f"{points.numel()} interest points (mode={args.mode}{radius}, K={args.num_scales}) "
        f"in {time.perf_counter() - start:.2f} s",
    )

    indices = points.detach().cpu().tolist()
    xyz = mesh.vertices.detach().cpu().double()[points.cpu()].tolist()
    saliency = values.detach().cpu().double().numpy()
    header = (
        f"# vertex x y z saliency  ({path.name}, mode={args.mode}, radius={args.radius:g}, "
        f"top_k={args.top_k}, t_global={args.t_global:g}, K={args.num_scales}, "
        f"threshold={args.threshold:g}; most salient first)"
    )
    write_lines(txt_path, _lines(header, indices, xyz, saliency.tolist()))
    common.say(args, f"wrote {txt_path}")
    if png_path is not None:
        from ..viz import render_interest_points

        render_interest_points(
            mesh.vertices,
            mesh.faces,
            saliency,
            indices,
            png_path,
            title=f"{path.name}: {len(indices)} interest points ({args.mode})",
            up=args.up,
        )
        common.say(args, f"wrote {png_path}")
    return 0
