"""``stochlap evaluate``: interest-point detectors against human-marked ground truth (Fig. 15).

Ground-truth files: one line per subject holding the vertex indices that subject marked,
separated by spaces, tabs or commas, 0-based (--one-based for 1-based files); text after '#'
is a comment, blank lines are skipped, and a subject who marked nothing is a line holding
only '-'. Points that at least --min-subjects subjects marked within --sigma of the mesh
diameter form the ground truth (Dutagaci et al. 2012). Every method turns its saliency into
interest points with the same detector, and the false negative, false positive and weighted
miss errors are printed against the localisation radius r (fraction of the mesh diameter),
per mesh and averaged over the meshes, and drawn as three panels (--png).

Geodesic distances use the heat method when potpourri3d is installed
(pip install "stochlap_torch[evaluation]") and the mesh has no non-manifold edge, graph
Dijkstra otherwise, with a warning: the fallback changes the results.
"""

from __future__ import annotations

import argparse
import json
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import fields
from pathlib import Path

from ..evaluation.constants import DEFAULT_RADII, EVALUATE_METHODS, GEODESIC_METHODS
from . import common, options

HELP = "interest-point errors (FNE/FPE/WME against r) against ground-truth files"
DESCRIPTION = __doc__.split("\n\n", 1)[1]
PARSER_OPTIONS = {"formatter_class": argparse.RawDescriptionHelpFormatter}
DEFAULT_METHODS = "robust,stochastic,lee,hks"


def method_list(text: str) -> list[str]:
    """``a,b,c`` as a list of names, each once (checked against the library's in ``run``)."""
    methods = list(dict.fromkeys(m.strip() for m in text.split(",") if m.strip()))
    if not methods:
        raise argparse.ArgumentTypeError(f"expected comma-separated method names, got {text!r}")
    return methods


# fmt: off
def add_arguments(parser) -> None:
    add = parser.add_argument
    add("inputs", nargs="+", metavar="MESH TRUTH", help="pairs of a mesh file and its "
        "ground-truth file")
    add("--methods", type=method_list, default=method_list(DEFAULT_METHODS), help="comma-"
        f"separated, from {', '.join(EVALUATE_METHODS)} (default: {DEFAULT_METHODS})")
    add("--one-based", action="store_true", help="truth indices start at 1")
    options.add_merge_seams(parser)
    add("--sigma", type=options.open_unit, default=0.03, help="ground-truth region radius, "
        "fraction of the mesh diameter (default: 0.03)")
    add("--min-subjects", type=options.positive_int, default=2, metavar="N", help="subjects "
        "that must agree on a ground-truth point (default: 2)")
    radii = f"{DEFAULT_RADII[0]:g}, {DEFAULT_RADII[1]:g}, ..., {DEFAULT_RADII[-1]:g}"
    add("--radii", type=options.non_negative_float, nargs="+", default=list(DEFAULT_RADII),
        metavar="R", help=f"localisation radii, fractions of the mesh diameter (default: {radii})")
    options.add_compute_options(parser, dtype=False)
    # Unset unless given, so that detectors without scales can refuse them.
    parser.set_defaults(num_scales=None, threshold=None)
    options.add_detector_options(parser)
    add("--geodesics", choices=GEODESIC_METHODS, default="auto", help="distances (default: auto)")
    add("--png", metavar="PNG", help="draw FNE/FPE/WME against r")
    add("--json", metavar="JSON", help="write all curves as JSON")
# fmt: on


def table(radii, per_method: dict[str, dict]) -> str:
    """FNE, FPE and WME of each method, one row per radius."""
    lines = []
    for method, values in per_method.items():
        lines += [f"  {method}", "    r       FNE     FPE     WME"]
        for i, r in enumerate(radii):
            fne, fpe, wme = (values[key][i] for key in ("fne", "fpe", "wme"))
            lines.append(f"    {r:<7.3f} {fne:<7.3f} {fpe:<7.3f} {wme:.3f}")
    return "\n".join(lines)


@contextmanager
def _warnings_about(name: str) -> Iterator[None]:
    """Warnings shown while the block runs start with ``name`` (which mesh they are about)."""
    with warnings.catch_warnings():  # puts showwarning back
        show = warnings.showwarning
        warnings.showwarning = lambda message, *rest: show(f"{name}: {message}", *rest)
        yield


def run(args) -> int:
    from ..evaluation import EvaluationSettings, check_evaluation_parameters

    # Every field of EvaluationSettings is an option of the same name.
    settings = {field.name: getattr(args, field.name) for field in fields(EvaluationSettings)}
    radii, paths = args.radii, [Path(path) for path in args.inputs]
    methods = check_evaluation_parameters(args.methods, **settings)
    if len(paths) % 2:
        raise common.CommandError(
            f"expected MESH TRUTH pairs, got {len(paths)} paths (the last mesh has no truth file)"
        )
    inputs = [(("mesh", "truth")[i % 2], path) for i, path in enumerate(paths)]
    common.check_outputs(inputs, [("--png", args.png), ("--json", args.json)])
    if args.png:
        common.want_picture(args)  # without matplotlib: an error before the long computation

    from ..evaluation import evaluate_detectors, mean_error_curves, read_marks
    from ..mesh import load_mesh

    # Every mesh and truth file is read before the first long computation.
    loaded = []
    for mesh_path, truth_path in zip(paths[::2], paths[1::2], strict=True):
        mesh = load_mesh(mesh_path, merge_seams=args.merge_seams)
        marks = read_marks(truth_path, mesh.num_vertices, args.one_based)
        loaded.append((mesh_path, truth_path, mesh, marks))

    def progress(method: str, result) -> None:
        common.say(args, f"  {method}: {result.num_points} points in {result.seconds:.1f} s")

    evaluations = {}
    for mesh_path, truth_path, mesh, marks in loaded:
        common.say(args, f"{mesh_path.name}: {mesh.num_vertices} vertices, truth {truth_path.name}")
        with _warnings_about(mesh_path.name):
            evaluation = evaluate_detectors(
                mesh.vertices, mesh.faces, marks, methods, progress=progress, **settings
            )
        truth = f"{evaluation.num_truth} points from {len(marks)} subjects"
        common.say(args, f"  ground truth: {truth} ({evaluation.geodesics} geodesics)")
        evaluations[str(mesh_path)] = evaluation
        print(mesh_path.name)
        print(table(radii, evaluation.as_dict()["methods"]))
    mean = mean_error_curves(list(evaluations.values()))
    if len(evaluations) > 1:
        print(f"mean over {len(evaluations)} meshes")
        print(table(radii, mean))
    if args.json:
        meshes = {name: evaluation.as_dict() for name, evaluation in evaluations.items()}
        data = {"radii": radii, "meshes": meshes, "mean": mean}
        common.write_text(args.json, [json.dumps(data, indent=2) + "\n"])
        common.say(args, f"wrote {args.json}")

    from ..viz import plot_error_curves

    title = "interest points: " + ", ".join(Path(name).name for name in evaluations)
    common.draw_picture(args, args.png, plot_error_curves, radii, mean, title=title)
    return 0
