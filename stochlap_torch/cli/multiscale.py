"""``stochlap multiscale``: the meshes P^(k) of every scale, and a picture strip.

Write the multiscale representation: DIR/<stem>_kNN.ply for k = 1..K (with the difference
map D^(k) as a 'difference' vertex property) and DIR/<stem>_multiscale.png. Default DIR:
<stem>_multiscale.
"""

from __future__ import annotations

import time
from pathlib import Path

from . import common, options

HELP = "the meshes P^(k) at every scale, and a picture strip"


def add_arguments(parser) -> None:
    options.add_mesh_arguments(parser, output=("DIR", "output directory"))
    shown = "scales (1..K) shown in the picture (default: about 5 evenly spaced)"
    parser.add_argument("--scales", type=options.positive_int, nargs="+", metavar="k", help=shown)
    options.add_picture_options(parser, png=False, cmap=False)


def run(args) -> int:
    bad = [k for k in args.scales or () if not 1 <= k <= args.num_scales]
    if bad:
        raise common.CommandError(f"--scales must lie in 1..{args.num_scales}, got {bad}")
    path = common.mesh_path(args.mesh)
    stem = path.stem
    out_dir = Path(args.output or f"{stem}_multiscale")
    if out_dir.exists() and not out_dir.is_dir():
        raise common.CommandError(f"output {out_dir} exists and is not a directory")
    plys = [out_dir / f"{stem}_k{k:02d}.ply" for k in range(1, args.num_scales + 1)]
    png_path = out_dir / f"{stem}_multiscale.png"
    mesh, png_path = common.open_mesh(
        args, path, [(ply.name, ply) for ply in plys], ("picture", png_path)
    )

    from ..diffusion import multiscale_representation

    start = time.perf_counter()
    progress = common.Progress("multiscale", args.quiet)
    given = {"num_scales": args.num_scales, "threshold": args.threshold, "progress": progress}
    representation = multiscale_representation(mesh.vertices, mesh.faces, **given)
    seconds = time.perf_counter() - start
    settings = common.compute_settings(args)
    common.say(args, f"multiscale representation ({settings}) in {seconds:.2f} s")

    from ..mesh import save_ply

    positions = representation.positions.detach().cpu().double()
    differences = representation.differences.detach().cpu().double().numpy()
    for k, ply in enumerate(plys):
        save_ply(ply, positions[k], mesh.faces, scalars={"difference": differences[k]})
    common.say(args, f"wrote {len(plys)} meshes {plys[0]} .. {plys[-1].name}")

    from ..viz import render_multiscale

    scales = None if args.scales is None else [k - 1 for k in args.scales]
    title = f"{path.name}: multiscale representation P^(k)"
    options = {"scales": scales, "title": title, "up": args.up}
    common.draw_picture(args, png_path, render_multiscale, positions, mesh.faces, **options)
    return 0
