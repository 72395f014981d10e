"""Resolution consistency of saliency (paper Sec. 4.3, Fig. 9), measured.

For each mesh, the full-resolution saliency is compared with the saliency computed on quadric
decimations of the same mesh (fast-simplification, ~15k and ~5k vertices), transferred back to
the full-resolution vertices by nearest vertex. The score is the Spearman rank correlation over
the full-resolution vertices (1 = the same ranking of vertices at both resolutions).

Methods: the stochastic Laplacian saliency (Algorithm 2, K=8, lambda=1e-3) and its variants
(:mod:`stochlap_torch.saliency_maps`), Lee et al. 2005, Algorithm 2 on the uniform and cotangent
Laplacians, and the heat kernel signature at the middle of Sun et al.'s 16 time samples.

Run from the repository root::

    python examples/resolution_consistency.py            # all four meshes (a few minutes)
    python examples/resolution_consistency.py --meshes horse_48k.ply --no-write

Needs ``pip install fast-simplification scipy``. Writes the table into the ``resolution``
block of ``docs/RESULTS_EVALUATION.md`` (between its BEGIN/END markers).
"""

# The gallery shows a committed figure: the build does not run this script.
# sphinx_gallery_thumbnail_path = "figures/variants_two_resolutions.png"

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import torch
from report_blocks import write_block  # examples/ is on sys.path when run
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

import stochlap_torch as sl
from stochlap_torch.baselines import heat_kernel_signature, laplacian_saliency, lee_saliency
from stochlap_torch.saliency_maps import saliency_from_representation

ROOT = Path(__file__).resolve().parents[1]
MESH_DIR = ROOT.parent / "shared" / "meshes"
RESULTS = ROOT / "docs" / "RESULTS_EVALUATION.md"
DEFAULT_MESHES = ("horse_48k.ply", "gargoyle_50k.off", "armadillo.obj", "bunny.obj")
TARGETS = (15000, 5000)

METHODS = (
    "stochastic (paper)",
    "stochastic normal_coefficients",
    "stochastic normal_displacement",
    "stochastic valence_normalised",
    "Lee et al.",
    "uniform Lap. + Alg. 2",
    "cotangent Lap. + Alg. 2",
    "HKS (mid t)",
)


def referenced_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices no face uses; ``(V', 3)`` float64 and ``(F, 3)`` int64."""
    used = np.unique(faces)
    remap = np.full(vertices.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return vertices[used], remap[faces]


def decimate(vertices: np.ndarray, faces: np.ndarray, target: int):
    """Quadric decimation to about ``target`` vertices (fast-simplification)."""
    import fast_simplification

    reduction = 1.0 - target / vertices.shape[0]
    points, tris = fast_simplification.simplify(
        vertices.astype(np.float32), faces.astype(np.int32), target_reduction=reduction
    )
    return referenced_mesh(points.astype(np.float64), tris.astype(np.int64))


def hks_mid(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Heat kernel signature at the 8th of 16 log-spaced times (100 eigenpairs)."""
    return heat_kernel_signature(vertices, faces, num_eigenpairs=100, num_times=16)[:, 8]


def all_saliencies(vertices: np.ndarray, faces: np.ndarray) -> dict[str, np.ndarray]:
    """Every method's ``(V,)`` saliency on one mesh."""
    v = torch.from_numpy(vertices)
    f = torch.from_numpy(faces)
    rep = sl.multiscale_representation(v, f, 8, 1e-3)

    out = {
        "stochastic (paper)": rep.saliency(),
        "stochastic normal_coefficients": saliency_from_representation(
            rep, v, f, "normal_coefficients"
        ),
        "stochastic normal_displacement": saliency_from_representation(
            rep, v, f, "normal_displacement"
        ),
        "stochastic valence_normalised": saliency_from_representation(
            rep, v, f, "valence_normalised"
        ),
        "Lee et al.": lee_saliency(v, f),
        "uniform Lap. + Alg. 2": laplacian_saliency(v, f, "uniform"),
        "cotangent Lap. + Alg. 2": laplacian_saliency(v, f, "cotangent"),
        "HKS (mid t)": hks_mid(v, f),
    }
    return {name: value.double().numpy() for name, value in out.items()}


def transfer_correlation(
    full_vertices: np.ndarray, full_values: np.ndarray, low_vertices: np.ndarray, low_values
) -> float:
    """Spearman correlation of ``full_values`` with ``low_values`` at the nearest low vertex."""
    _, nearest = cKDTree(low_vertices).query(full_vertices)
    return float(spearmanr(full_values, low_values[nearest])[0])


def measure(name: str) -> dict[int, dict[str, float]]:
    mesh = sl.load_mesh(MESH_DIR / name)
    vertices, faces = referenced_mesh(mesh.vertices.double().numpy(), mesh.faces.numpy())
    start = time.perf_counter()
    full = all_saliencies(vertices, faces)
    print(f"{name}: {vertices.shape[0]} vertices, {time.perf_counter() - start:.1f} s")
    rows: dict[int, dict[str, float]] = {}
    for target in TARGETS:
        low_vertices, low_faces = decimate(vertices, faces, target)
        low = all_saliencies(low_vertices, low_faces)
        rows[low_vertices.shape[0]] = {
            method: transfer_correlation(vertices, full[method], low_vertices, low[method])
            for method in METHODS
        }
        print(
            f"  -> {low_vertices.shape[0]} vertices: "
            + ", ".join(f"{m}={r:.3f}" for m, r in rows[low_vertices.shape[0]].items())
        )
    return rows


def markdown(results: dict[str, dict[int, dict[str, float]]]) -> str:
    header = "| mesh (V) | decimated V | " + " | ".join(METHODS) + " |"
    lines = [header, "|" + " --- |" * (len(METHODS) + 2)]
    means = {m: [] for m in METHODS}
    for name, rows in results.items():
        for size, scores in rows.items():
            best = max(scores.values())
            cells = []
            for m in METHODS:
                means[m].append(scores[m])
                text = f"{scores[m]:.3f}"
                cells.append(f"**{text}**" if scores[m] == best else text)
            lines.append(f"| {name} | {size} | " + " | ".join(cells) + " |")
    lines.append("| **mean** | | " + " | ".join(f"{np.mean(means[m]):.3f}" for m in METHODS) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=list(DEFAULT_MESHES))
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args()
    torch.manual_seed(0)
    results = {name: measure(name) for name in args.meshes}
    table = markdown(results)
    print(table)
    if not args.no_write:
        write_block(RESULTS, "resolution", table)
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
