"""``stochlap info``: counts and checks of a mesh file.

Report vertices, faces, edges, boundary and non-manifold edges, unreferenced vertices,
connected components, bounding box, edge lengths, and whether the mesh passes the input
checks in float64 and float32, and the robust variant's (a surface area).
"""

from __future__ import annotations

import json
from pathlib import Path

from . import common, options

NAME = "info"
HELP = "counts and checks of a mesh file"
DESCRIPTION = __doc__.split("\n\n")[1]


def add_arguments(parser) -> None:
    options.add_mesh_arguments(parser, compute=False)
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


def add_parser(commands, parents):
    return options.add_command(commands, parents, NAME, HELP, DESCRIPTION, run, add_arguments)


def format_report(path: Path, report: dict) -> str:
    """The report of :func:`~stochlap_torch.mesh.mesh_report` as aligned ``name  value`` rows."""

    def vec(values) -> str:
        return "(" + ", ".join(f"{v:.4g}" for v in values) + ")"

    def verdict(value) -> str:
        return "yes" if value is True else f"no: {value}"

    rows = [
        ("mesh", str(path)),
        ("vertices", report["vertices"]),
        ("faces", report["faces"]),
        ("edges", report["edges"]),
        ("boundary edges", report["boundary_edges"]),
        ("non-manifold edges", report["non_manifold_edges"]),
        ("unreferenced vertices", report["unreferenced_vertices"]),
        ("connected components", report["components"]),
        ("closed", "yes" if report["closed"] else "no"),
        ("consistently oriented", "yes" if report["consistently_oriented"] else "no"),
        ("Euler characteristic", report["euler_characteristic"]),
        ("bounding box min", vec(report["bbox_min"])),
        ("bounding box max", vec(report["bbox_max"])),
        ("bounding box size", vec(report["bbox_size"])),
        ("mean edge length", f"{report['mean_edge_length']:.4g}"),
        ("shortest edge", f"{report['min_edge_length']:.4g}"),
        ("valid (float64)", verdict(report["valid_float64"])),
        ("valid (float32)", verdict(report["valid_float32"])),
        ("valid (robust variant)", verdict(report["valid_robust"])),
    ]
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def robust_verdict(mesh) -> bool | str:
    """``True`` if the robust variant accepts a valid mesh, else why not (it also needs a
    surface area: :func:`~stochlap_torch.mesh.validation.check_surface_area`)."""
    from ..mesh import MeshError
    from ..mesh.validation import check_surface_area

    try:
        check_surface_area(mesh.vertices, mesh.faces)
    except MeshError as exc:
        return str(exc)
    return True


def run(args) -> int:
    from ..mesh import load_mesh, mesh_report

    path = common.mesh_path(args.mesh)
    # load_mesh validates in float64: a mesh that fails is reported as one error line.
    mesh = load_mesh(path, merge_seams=args.merge_seams)
    report = {**mesh_report(mesh), "valid_robust": robust_verdict(mesh)}
    if args.json:
        print(json.dumps({"mesh": str(path), **report}, indent=2))
    else:
        print(format_report(path, report))
    return 0
