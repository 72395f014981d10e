"""What the stochastic-Laplacian saliency responds to, measured on real meshes.

For horse, camel, armadillo and gargoyle:

1. mean log saliency by vertex valence (number of 1-ring neighbours);
2. Spearman correlation of saliency with ``|mean curvature|`` (cotangent Laplacian, Voronoi area)
   and with the valence;
3. whether interest points land on shape extremities more often than random vertices.

**Extremities** (definition used here): the average geodesic distance ``AGD(v)`` is estimated
as the mean heat-method geodesic distance from ``v`` to 64 random vertices; the extremity
*tips* are the well-separated local maxima of AGD (the library's non-maximum suppression,
radius 0.1 of the bounding-box diagonal) that reach half of the AGD range; a point is *on an
extremity* if it lies within geodesic distance ``0.05 * d_M`` of a tip (``d_M`` the mesh
diameter). The random baseline is the share of vertices on an extremity (the expected hit rate
of a uniformly random vertex) and, alongside, the share of the surface area.

Interest points: every method's saliency through the same detector (``mode="nms"``, radius
0.1, ``t_global`` 0.4, the 20 most salient), so only the saliency differs.

Run from the repository root (about two minutes)::

    python examples/saliency_analysis.py [--no-write]

Writes its tables into the ``analysis`` block of ``docs/RESULTS_EVALUATION.md``.
"""

# The gallery shows a committed figure: the build does not run this script.
# sphinx_gallery_thumbnail_path = "figures/fig12_gargoyle_interest.png"

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from report_blocks import write_block  # examples/ is on sys.path when run
from scipy.stats import spearmanr

import stochlap_torch as sl
from stochlap_torch.baselines import heat_kernel_signature, lee_saliency, mean_curvature
from stochlap_torch.evaluation import geodesic_distances, mesh_diameter
from stochlap_torch.mesh import vertex_valence
from stochlap_torch.operators import lumped_mass
from stochlap_torch.saliency_maps import saliency_from_representation

ROOT = Path(__file__).resolve().parents[1]
MESH_DIR = ROOT.parent / "shared" / "meshes"
RESULTS = ROOT / "docs" / "RESULTS_EVALUATION.md"
MESHES = ("horse.off", "camel.off", "armadillo.obj", "gargoyle.off")
AGD_SOURCES = 64
TIP_RADIUS = 0.05  # fraction of the mesh diameter
TOP_K = 20  # interest points per method (people mark about 10-25 on these models)


def saliencies(vertices: torch.Tensor, faces: torch.Tensor) -> dict[str, torch.Tensor]:
    rep = sl.multiscale_representation(vertices, faces, 8, 1e-3)
    out = {
        "paper": rep.saliency(),
        "normal_coefficients": saliency_from_representation(
            rep, vertices, faces, "normal_coefficients"
        ),
        "normal_displacement": saliency_from_representation(
            rep, vertices, faces, "normal_displacement"
        ),
        "valence_normalised": saliency_from_representation(
            rep, vertices, faces, "valence_normalised"
        ),
        "Lee et al.": lee_saliency(vertices, faces),
    }
    out["HKS (mid t)"] = heat_kernel_signature(vertices, faces, 100, 16)[:, 8]
    return out


def extremity_mask(vertices, faces, rng) -> tuple[np.ndarray, np.ndarray, float]:
    """``(V,)`` bool on-extremity mask, the tip vertices, and the mesh diameter."""
    sources = rng.choice(vertices.shape[0], size=AGD_SOURCES, replace=False)
    agd = geodesic_distances(vertices, faces, sources).distances.mean(dim=0)
    tips = sl.interest_points(agd.to(vertices.dtype), vertices, faces, t_global=0.5)
    diameter = mesh_diameter(vertices, faces)
    to_tip = geodesic_distances(vertices, faces, tips).distances.min(dim=0).values.numpy()
    return to_tip <= TIP_RADIUS * diameter, tips.numpy(), diameter


def analyse(name: str, rng) -> dict:
    mesh = sl.load_mesh(MESH_DIR / name)
    vertices, faces = mesh.vertices.double(), mesh.faces
    start = time.perf_counter()
    maps = saliencies(vertices, faces)
    valence = vertex_valence(faces, vertices.shape[0]).numpy()
    curvature = mean_curvature(vertices, faces).abs().numpy()
    on_tip, tips, _ = extremity_mask(vertices, faces, rng)
    area = lumped_mass(vertices, faces).numpy()
    result = {
        "V": vertices.shape[0],
        "valence": valence,
        "paper": maps["paper"].numpy(),
        "tips": len(tips),
        "random_vertex": float(on_tip.mean()),
        "random_area": float(area[on_tip].sum() / area.sum()),
        "rho": {},
        "hits": {},
    }
    for method, values in maps.items():
        v = values.numpy()
        result["rho"][method] = (
            float(spearmanr(v, curvature)[0]),
            float(spearmanr(v, valence)[0]),
        )
        points = sl.interest_points(values, vertices, faces, top_k=TOP_K).numpy()
        result["hits"][method] = (int(on_tip[points].sum()), len(points))
    print(f"{name}: {time.perf_counter() - start:.1f} s, {len(tips)} tips")
    return result


def valence_table(results: dict) -> str:
    valences = sorted({int(v) for r in results.values() for v in np.unique(r["valence"])})
    lines = [
        "| valence | " + " | ".join(f"{n} (count)" for n in results) + " |",
        "|" + " --- |" * (len(results) + 1),
    ]
    for value in valences:
        cells = []
        for r in results.values():
            chosen = r["valence"] == value
            count = int(chosen.sum())
            cells.append(f"{r['paper'][chosen].mean():.3f} ({count})" if count else "")
        lines.append(f"| {value} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def correlation_table(results: dict) -> str:
    methods = list(next(iter(results.values()))["rho"])
    lines = [
        "| mesh | " + " | ".join(methods) + " |",
        "|" + " --- |" * (len(methods) + 1),
    ]
    for name, r in results.items():
        cells = [f"{r['rho'][m][0]:+.3f} / {r['rho'][m][1]:+.3f}" for m in methods]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def extremity_table(results: dict) -> str:
    methods = list(next(iter(results.values()))["hits"])
    lines = [
        "| mesh | tips | random vertex | random area | " + " | ".join(methods) + " |",
        "|" + " --- |" * (len(methods) + 4),
    ]
    for name, r in results.items():
        cells = [
            f"{h}/{n} = {h / n:.2f}" if n else "0/0" for h, n in (r["hits"][m] for m in methods)
        ]
        lines.append(
            f"| {name} | {r['tips']} | {r['random_vertex']:.2f} | {r['random_area']:.2f} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=list(MESHES))
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    results = {name: analyse(name, rng) for name in args.meshes}
    text = "\n\n".join(
        [
            "Mean paper-mode log saliency by valence (vertex count in brackets):",
            valence_table(results),
            "Spearman correlation of saliency with |mean curvature| / with valence:",
            correlation_table(results),
            "Interest points on an extremity (hits / points) against the random rates:",
            extremity_table(results),
        ]
    )
    print(text)
    if not args.no_write:
        write_block(RESULTS, "analysis", text)
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
