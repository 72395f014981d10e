"""``stochlap saliency``: per-vertex saliency to a coloured PLY file and a picture."""

from __future__ import annotations

import time

from . import common
from .outputs import check_outputs, default_output

NAME = "saliency"
HELP = "per-vertex saliency (Algorithm 2) to a coloured PLY and a picture"
DESCRIPTION = (
    "Compute mesh saliency and write a binary PLY with saliency as vertex colours and a "
    "'saliency' float property, plus a PNG picture. Default outputs: <stem>_saliency.ply and "
    "<stem>_saliency.png in the current directory."
)


def add_parser(commands, parents):
    parser = commands.add_parser(NAME, parents=parents, help=HELP, description=DESCRIPTION)
    common.add_mesh_argument(parser)
    parser.add_argument("-o", "--output", metavar="PLY", help="output PLY file")
    common.add_compute_options(parser)
    common.add_picture_options(parser)
    parser.set_defaults(handler=run)
    return parser


def stats(values) -> str:
    """``min .., max .., mean ..`` of a tensor."""
    values = values.detach().double()
    low, high, mean = values.min().item(), values.max().item(), values.mean().item()
    return f"min {low:.4g}, max {high:.4g}, mean {mean:.4g}"


def compute_saliency(args, mesh):
    """Saliency of ``mesh`` with the command's ``-K`` and ``--threshold``, progress on stderr."""
    from ..saliency_maps import mesh_saliency

    return mesh_saliency(
        mesh.vertices,
        mesh.faces,
        num_scales=args.num_scales,
        threshold=args.threshold,
        progress=common.Progress("saliency", args.quiet),
    )


def run(args) -> int:
    path = common.mesh_path(args.mesh)
    ply_path = default_output(args.output, path, NAME, "ply")
    png_path = default_output(args.png, path, NAME, "png")
    check_outputs([("mesh", path)], [("-o", ply_path), ("--png", png_path)])
    if not common.want_picture(args):
        png_path = None
    mesh = common.load_mesh_arg(args, path)

    start = time.perf_counter()
    values = compute_saliency(args, mesh)
    common.say(
        args,
        f"saliency (K={args.num_scales}, threshold={args.threshold:g}) in "
        f"{time.perf_counter() - start:.2f} s: {stats(values)}",
    )

    from ..mesh import save_ply
    from ..viz import robust_range, scalar_colors

    saliency = values.detach().cpu().double().numpy()
    vmin, vmax = robust_range(saliency, mesh.faces)  # of the vertices the faces use
    colors = scalar_colors(saliency, vmin=vmin, vmax=vmax)
    save_ply(ply_path, mesh.vertices, mesh.faces, colors=colors, scalars={"saliency": saliency})
    common.say(args, f"wrote {ply_path}")
    if png_path is not None:
        from ..viz import render_scalar

        title = f"{path.name}: saliency (K={args.num_scales}, threshold={args.threshold:g})"
        render_scalar(
            mesh.vertices, mesh.faces, saliency, png_path, title=title, label=NAME, up=args.up
        )
        common.say(args, f"wrote {png_path}")
    return 0
