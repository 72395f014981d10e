"""``stochlap evaluate``: interest-point detectors against human-marked ground truth (Fig. 15).

Usage::

    stochlap evaluate MESH TRUTH [MESH TRUTH ...] [--methods stochastic,lee,hks]
                      [--png curves.png] [--json results.json] [--sigma 0.03]
                      [--min-subjects 2] [--radii 0 0.01 ...] [--top-k N] [--radius 0.1]

**Ground-truth file format** (one file per mesh, plain text, UTF-8): one line per human
subject, holding the vertex indices that subject marked, separated by spaces, tabs or commas.
Indices are 0-based (``--one-based`` for 1-based files, as exported by MATLAB tools). Text
after ``#`` is a comment; blank lines are skipped; a line with only a comment is skipped too,
so a subject who marked nothing is written as ``-`` alone on its line. Example::

    # spot.obj, 3 subjects
    12 512 1033
    14 509
    -

From the marks, :func:`~stochlap_torch.evaluation.build_ground_truth` forms the ground-truth
points (Dutagaci et al. 2012: marks of at least ``--min-subjects`` subjects within
``--sigma`` of the mesh diameter). Each method turns its saliency into interest points with the
same detector (:func:`~stochlap_torch.interest.interest_points`), and the false negative,
false positive and weighted miss errors are printed against the localisation radius ``r``
(fraction of the mesh diameter), per mesh and averaged over the meshes, and drawn as three
panels (``--png``).

Methods (``--methods``, comma separated): ``stochastic`` (Algorithm 2), the variants
``normal_coefficients``, ``normal_displacement``, ``valence_normalised``
(:mod:`~stochlap_torch.variants`), ``lee`` (Lee et al. 2005), ``hks`` (heat kernel signature at
the middle of 16 log-spaced times), ``uniform`` and ``cotangent`` (Algorithm 2 on those
Laplacians).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..evaluation.detectors import EVALUATE_METHODS, detector_saliency
from ..evaluation.truth import read_marks
from ..mesh import Mesh, load_mesh

__all__ = [
    "EVALUATE_METHODS",
    "add_evaluate_parser",
    "detector_saliency",
    "main",
    "plot_error_curves",
    "read_marks",
    "run_evaluate",
]

logger = logging.getLogger(__name__)

PROG = "stochlap"

DEFAULT_METHODS = "stochastic,normal_displacement,lee,hks"


def _parse_methods(text: str) -> list[str]:
    methods = [m.strip() for m in text.split(",") if m.strip()]
    bad = [m for m in methods if m not in EVALUATE_METHODS]
    if bad or not methods:
        raise ValueError(
            f"--methods: unknown {', '.join(bad) or '(none given)'}; "
            f"choose from {', '.join(EVALUATE_METHODS)}"
        )
    return list(dict.fromkeys(methods))


def _pairs(items: list[str]) -> list[tuple[Path, Path]]:
    if len(items) % 2:
        raise ValueError(
            f"expected MESH TRUTH pairs, got {len(items)} paths (the last mesh has no truth file)"
        )
    return [(Path(items[i]), Path(items[i + 1])) for i in range(0, len(items), 2)]


def _curves_dict(curves) -> dict[str, list[float]]:
    return {
        "fne": curves.fne.tolist(),
        "fpe": curves.fpe.tolist(),
        "wme": curves.wme.tolist(),
        "num_correct": curves.num_correct.tolist(),
    }


def _evaluate_mesh(
    mesh: Mesh, marks: list[list[int]], methods: list[str], args, say: Callable[[str], None]
) -> dict:
    from ..evaluation import build_ground_truth, evaluate_interest_points, mesh_diameter
    from ..interest import interest_points

    vertices, faces = mesh.vertices.double(), mesh.faces
    diameter = mesh_diameter(vertices, faces, args.geodesics)
    truth = build_ground_truth(
        vertices, faces, marks, args.sigma, args.min_subjects, diameter, args.geodesics
    )
    if truth.num_points == 0:
        raise ValueError(
            f"no ground-truth point has {args.min_subjects} subjects agreeing within sigma="
            f"{args.sigma:g}; lower --min-subjects or raise --sigma"
        )
    say(f"  ground truth: {truth.num_points} points from {len(marks)} subjects")
    result = {"num_truth": truth.num_points, "methods": {}}
    for method in methods:
        start = time.perf_counter()
        values = detector_saliency(method, vertices, faces, args.num_scales, args.threshold)
        points = interest_points(
            values, vertices, faces, mode=args.mode, radius=args.radius, top_k=args.top_k
        )
        curves = evaluate_interest_points(
            vertices, faces, truth, points, args.radii, diameter, args.geodesics
        )
        say(f"  {method}: {points.numel()} points in {time.perf_counter() - start:.1f} s")
        result["methods"][method] = {"num_points": int(points.numel()), **_curves_dict(curves)}
    return result


def _table(radii: list[float], per_method: dict[str, dict]) -> str:
    lines = []
    for method, values in per_method.items():
        lines.append(f"  {method}")
        lines.append("    r       FNE     FPE     WME")
        for i, r in enumerate(radii):
            lines.append(
                f"    {r:<7.3f} {values['fne'][i]:<7.3f} {values['fpe'][i]:<7.3f} "
                f"{values['wme'][i]:.3f}"
            )
    return "\n".join(lines)


def plot_error_curves(
    radii: list[float], per_method: dict[str, dict], path: str | Path, title: str | None = None
) -> Path:
    """Draw FNE, FPE and WME against ``r`` as three panels, one line per method (Fig. 15).

    Args:
        radii: ``R`` radii (fractions of the mesh diameter).
        per_method: ``{method: {"fne": [R], "fpe": [R], "wme": [R]}}``.
        path: PNG file to write.
        title: optional figure title.

    Returns:
        The path written.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(12.0, 3.8), dpi=110)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3)
    markers = "osD^v<>p"
    for ax, key, name in zip(axes, ("fne", "fpe", "wme"), ("FNE", "FPE", "WME"), strict=True):
        for i, (method, values) in enumerate(per_method.items()):
            ax.plot(radii, values[key], marker=markers[i % len(markers)], ms=4, label=method)
        ax.set_xlabel("tolerance r (fraction of mesh diameter)")
        ax.set_ylabel(name)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path


def run_evaluate(args) -> int:
    """Handler of ``stochlap evaluate`` (parsed ``args``); returns the exit status."""
    methods = _parse_methods(args.methods)
    if not 0 < args.sigma < 1:
        raise ValueError(f"--sigma must lie in (0, 1), got {args.sigma:g}")
    if args.min_subjects < 1:
        raise ValueError(f"--min-subjects must be >= 1, got {args.min_subjects}")
    if args.radius <= 0:
        raise ValueError(f"--radius must be positive, got {args.radius:g}")
    if any(r < 0 for r in args.radii):
        raise ValueError("--radii must be non-negative")
    if args.png:
        import matplotlib  # noqa: F401  (fail before the long computation)
    from ..diffusion import check_parameters

    check_parameters(args.num_scales, args.threshold)
    pairs = _pairs(args.inputs)

    def say(text: str) -> None:
        if not args.quiet:
            print(text, flush=True)

    results: dict[str, dict] = {}
    for mesh_path, truth_path in pairs:
        mesh = load_mesh(mesh_path, merge_seams=args.merge_seams)
        marks = read_marks(truth_path, mesh.num_vertices, args.one_based)
        say(f"{mesh_path.name}: {mesh.num_vertices} vertices, truth {truth_path.name}")
        results[str(mesh_path)] = _evaluate_mesh(mesh, marks, methods, args, say)
        print(f"{mesh_path.name}")
        print(_table(args.radii, results[str(mesh_path)]["methods"]))
    mean = {
        method: {
            key: np.mean([r["methods"][method][key] for r in results.values()], axis=0).tolist()
            for key in ("fne", "fpe", "wme")
        }
        for method in methods
    }
    if len(results) > 1:
        print(f"mean over {len(results)} meshes")
        print(_table(args.radii, mean))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(
            json.dumps({"radii": list(args.radii), "meshes": results, "mean": mean}, indent=2)
        )
        say(f"wrote {args.json}")
    if args.png:
        names = ", ".join(Path(p).name for p in results)
        plot_error_curves(args.radii, mean, args.png, title=f"interest points: {names}")
        say(f"wrote {args.png}")
    return 0


def _configure(parser: argparse.ArgumentParser) -> None:
    from ..evaluation import DEFAULT_RADII

    parser.add_argument(
        "inputs",
        nargs="+",
        metavar="MESH TRUTH",
        help="pairs of a mesh file and its ground-truth file (one line of vertex indices per "
        "subject, '#' comments)",
    )
    parser.add_argument(
        "--methods",
        default=DEFAULT_METHODS,
        help=f"comma-separated, from {','.join(EVALUATE_METHODS)} (default: {DEFAULT_METHODS})",
    )
    parser.add_argument("--one-based", action="store_true", help="truth indices start at 1")
    parser.add_argument("--merge-seams", action="store_true", help="merge duplicate vertices")
    parser.add_argument(
        "--sigma",
        type=float,
        default=0.03,
        help="ground-truth region radius, fraction of the mesh diameter (default: 0.03)",
    )
    parser.add_argument(
        "--min-subjects",
        type=int,
        default=2,
        help="subjects that must agree on a ground-truth point (default: 2)",
    )
    parser.add_argument(
        "--radii",
        type=float,
        nargs="+",
        default=list(DEFAULT_RADII),
        metavar="R",
        help="localisation radii, fractions of the mesh diameter (default: 0, 0.01, ..., 0.12)",
    )
    parser.add_argument("-K", "--num-scales", type=int, default=8, metavar="K")
    parser.add_argument("--threshold", type=float, default=1e-3, metavar="LAMBDA")
    parser.add_argument("--mode", choices=("nms", "paper"), default="nms")
    parser.add_argument(
        "--radius", type=float, default=0.1, help="nms radius, fraction of the box diagonal"
    )
    parser.add_argument("--top-k", type=int, default=None, metavar="N")
    parser.add_argument(
        "--geodesics", choices=("auto", "heat", "dijkstra"), default="auto", help="distances"
    )
    parser.add_argument("--png", metavar="PNG", help="draw FNE/FPE/WME against r")
    parser.add_argument("--json", metavar="JSON", help="write all curves as JSON")
    parser.set_defaults(handler=run_evaluate)


def add_evaluate_parser(commands, common: argparse.ArgumentParser | None = None):
    """Add the ``evaluate`` subcommand to an ``add_subparsers()`` object; returns its parser."""
    parser = commands.add_parser(
        "evaluate",
        parents=[] if common is None else [common],
        help="interest-point errors (FNE/FPE/WME against r) against ground-truth files",
        description=__doc__.split("\n\n")[2],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _configure(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """``stochlap evaluate`` on its own (``python -m stochlap_torch.cli_evaluate ...``): the
    same options, one-line errors and exit status 2 for bad input."""
    parser = argparse.ArgumentParser(prog=f"{PROG} evaluate", description=__doc__.split("\n")[0])
    parser.add_argument("-q", "--quiet", action="store_true", help="tables only")
    _configure(parser)
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 2
    try:
        return run_evaluate(args)
    except OSError as exc:
        message = f"{exc.filename}: {exc.strerror}" if exc.filename else str(exc)
    except (ValueError, ImportError, MemoryError) as exc:
        message = str(exc) or type(exc).__name__
    sys.stderr.write(f"{PROG}: error: {' '.join(message.split())}\n")
    return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
