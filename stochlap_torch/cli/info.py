"""``stochlap info``: counts and checks of a mesh file.

Report vertices, faces, edges, boundary and non-manifold edges, unreferenced vertices,
connected components, bounding box, edge lengths, and whether the mesh passes the input
checks in float64 and float32, and the robust variant's (a surface area).
"""

from __future__ import annotations

import json
from pathlib import Path

from . import common, options

HELP = "counts and checks of a mesh file"


def add_arguments(parser) -> None:
    options.add_mesh_arguments(parser, compute=False)
    parser.add_argument("--json", action="store_true", help="print the report as JSON")


#: The rows of the report: label, key of :func:`~stochlap_torch.mesh.mesh_report`, format.
_ROWS = (
    ("vertices", "vertices", str),
    ("faces", "faces", str),
    ("edges", "edges", str),
    ("boundary edges", "boundary_edges", str),
    ("non-manifold edges", "non_manifold_edges", str),
    ("unreferenced vertices", "unreferenced_vertices", str),
    ("connected components", "components", str),
    ("closed", "closed", lambda v: "yes" if v else "no"),
    ("consistently oriented", "consistently_oriented", lambda v: "yes" if v else "no"),
    ("Euler characteristic", "euler_characteristic", str),
    *(
        (f"bounding box {n}", f"bbox_{n}", lambda v: f"({', '.join(f'{x:.4g}' for x in v)})")
        for n in ("min", "max", "size")
    ),
    ("mean edge length", "mean_edge_length", lambda v: f"{v:.4g}"),
    ("shortest edge", "min_edge_length", lambda v: f"{v:.4g}"),
    *(
        (f"valid ({n})", f"valid_{k}", lambda v: "yes" if v is True else f"no: {v}")
        for n, k in (("float64", "float64"), ("float32", "float32"), ("robust variant", "robust"))
    ),
)


def format_report(path: Path, report: dict) -> str:
    """The report of :func:`~stochlap_torch.mesh.mesh_report` as aligned ``name  value`` rows."""
    rows = [("mesh", str(path))] + [(name, fmt(report[key])) for name, key, fmt in _ROWS]
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def run(args) -> int:
    from ..mesh import MeshError, load_mesh, mesh_report
    from ..mesh.validation import check_surface_area

    path = common.mesh_path(args.mesh)
    # load_mesh validates in float64: a mesh that fails is reported as one error line.
    mesh = load_mesh(path, merge_seams=args.merge_seams)
    report = mesh_report(mesh)
    try:  # the robust variant also needs a surface area
        check_surface_area(mesh.vertices, mesh.faces)
        report["valid_robust"] = True
    except MeshError as exc:
        report["valid_robust"] = str(exc)
    if args.json:
        print(json.dumps({"mesh": str(path), **report}, indent=2))
    else:
        print(format_report(path, report))
    return 0
