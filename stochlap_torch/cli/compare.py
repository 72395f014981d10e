"""``stochlap compare``: the multiscale saliency beside eigendecomposition baselines.

Run each method on the mesh, each in a fresh process warmed up on the bundled cow (unless
--in-process), and print a table: seconds, the peak memory the run added, the Spearman rank
correlation of its saliency with the reference method's, and the fraction of the reference's
interest points it finds within 0.05 of the bounding-box diagonal. Methods: robust and
stochastic (this library: the robust saliency and the paper's Algorithm 2), hks (heat kernel
signature), spectral (detail removed by a 64-eigenvector low-pass), lee (Lee et al. 2005),
uniform and cotangent (Algorithm 2 on those Laplacians).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from . import common, options

HELP = "the multiscale saliency beside eigendecomposition baselines: time, memory, agreement"


def method_list(text: str) -> list[str]:
    """An argparse ``type``: comma-separated method names, each known and named once."""
    from ..evaluation.constants import COMPARE_METHODS

    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in COMPARE_METHODS]
    if unknown or not names or len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(
            f"distinct names from {','.join(COMPARE_METHODS)}, got {text!r}"
        )
    return names


def add_arguments(parser) -> None:
    from ..evaluation.constants import DEFAULT_COMPARE_METHODS

    options.add_mesh_arguments(parser, compute=False)
    add = parser.add_argument
    default = ",".join(DEFAULT_COMPARE_METHODS)
    add(
        "--methods",
        type=method_list,
        default=list(DEFAULT_COMPARE_METHODS),
        metavar="LIST",
        help=f"comma-separated methods, in table order (default: {default})",
    )
    add(
        "--reference",
        metavar="METHOD",
        help="the method the others are compared with (default: the first of --methods)",
    )
    add(
        "--json",
        metavar="FILE",
        help="also write the figures as JSON ('-': standard output, instead of the table)",
    )
    add(
        "--png",
        metavar="PNG",
        help="draw each method's saliency and interest points, one row per method",
    )
    add(
        "--in-process",
        action="store_true",
        help="run every method in this process: faster "
        "to start, but no memory figures and the first call of each pays its warm-up",
    )
    add(
        "--up",
        choices=options.UP_CHOICES,
        default=None,
        metavar="AXIS",
        help="vertical axis of the mesh file in the picture (default: guessed)",
    )
    add(
        "--dpi",
        type=options.dpi,
        default=None,
        metavar="N",
        help=f"picture resolution ({options.DPI_MIN} to {options.DPI_MAX}, default: 100)",
    )


def run(args) -> int:
    from ..evaluation.compare import compare_methods

    if args.reference is not None and args.reference not in args.methods:
        raise common.CommandError(f"--reference {args.reference} is not among --methods")
    path = common.mesh_path(args.mesh)
    json_path = None if args.json in (None, "-") else Path(args.json)
    picture = ("--png", Path(args.png)) if args.png else ("--png", None)
    outputs = [("--json", json_path)] if json_path else []
    args.dtype, args.no_png = "float64", not args.png
    mesh, png_path = common.open_mesh(args, path, outputs, picture)
    start = time.perf_counter()

    def progress(line: str) -> None:
        common.say(args, f"compare: {line} ({time.perf_counter() - start:.0f} s)")

    comparison = compare_methods(
        mesh.vertices,
        mesh.faces,
        args.methods,
        reference=args.reference,
        isolate=not args.in_process,
        progress=progress,
    )
    figures = {"mesh": str(path), **comparison.to_dict()}
    if args.json == "-":
        sys.stdout.write(json.dumps(figures, indent=1) + "\n")
    else:
        print(comparison.table())
    if json_path is not None:
        common.write_text(json_path, [json.dumps(figures, indent=1) + "\n"])
        common.say(args, f"wrote {json_path}")
    if png_path is not None:
        draw_comparison(args, png_path, mesh, comparison, path.name)
    return 0


def draw_comparison(args, png_path: Path, mesh, comparison, name: str) -> None:
    """One row per method: its saliency from the front and the side, its interest points."""
    import matplotlib.pyplot as plt

    from .._common.files import atomic_write
    from ..viz import render_scalar

    rows = list(comparison.runs.values())
    dpi = args.dpi or 100
    with tempfile.TemporaryDirectory() as tmp:
        images = []
        for run in rows:
            title = f"{run.method}: {run.seconds:.2f} s, {run.points.numel()} points"
            panel = Path(tmp) / f"{run.method}.png"
            render_scalar(
                mesh.vertices,
                mesh.faces,
                run.saliency,
                panel,
                views="front,side",
                title=title,
                up=args.up,
                dpi=dpi,
                points=run.points,
            )
            images.append(plt.imread(panel))
    height = sum(image.shape[0] for image in images) / dpi
    figure = plt.figure(figsize=(images[0].shape[1] / dpi, height), dpi=dpi)
    top = 1.0
    for image in images:
        share = image.shape[0] / dpi / height
        axes = figure.add_axes((0.0, top - share, 1.0, share))
        axes.imshow(image)
        axes.set_axis_off()
        top -= share
    try:
        with atomic_write(png_path, "wb") as handle:
            figure.savefig(handle, format="png", dpi=dpi)
    finally:
        plt.close(figure)
    common.say(args, f"wrote {png_path} ({name})")
