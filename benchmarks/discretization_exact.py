"""How far a remeshing moves the quantity the robust saliency measures (issue 31's ``mc``).

``discretization.py`` ranks the robust saliency of a remeshed body against its ``iso`` mesh's.
Part of what it finds moved is the method's approximation (the pyramid, the heat operator's
mass cap and edge clamp, the Chebyshev truncation); the rest is the surface: marching cubes
joins parts that touch and rounds thin ones. This script separates the two. On every mesh it
computes the saliency's channels without any approximation,

    dn_k = n . (P - exp(-t_k L) P) / sqrt(t_k),    t_k = t0 2^k A,

with ``L = M^-1 S`` robust_laplacian's intrinsic Delaunay Laplacian of the unit-area mesh as it
is, the semigroup by a float64 Chebyshev series truncated at 1e-12, and ``n`` the library's
outward vertex normal (each component's own outward sign) smoothed as the library smooths
it (for ``normal_time A``, plus a quarter of it smoothed for a sixteenth of that); then the
saliency of these channels by the library's formula, written out (the area-weighted
standard score, clamped at 0, averaged over scales).

Ranked across the remeshing exactly as ``discretization.py`` ranks them (Spearman at the true
``iso`` vertex of every remeshed vertex), the exact channels say how far the surface itself
moves the quantity: what a method that computed these channels exactly would score. (Not a
bound: an approximation that smooths more can move less.) Beside them, the library's
figures, and, as the check that the two compute one quantity, their agreement on the same
``iso`` mesh. From the repository root::

    python benchmarks/discretization_exact.py DATA_DIR [--bodies 080-089] [--policies mc]
                                                [--out benchmarks/DISCRETIZATION_EXACT.md]
"""

from __future__ import annotations

import os
import sys

if __name__ == "__main__":  # one thread everywhere; BLAS reads these when numpy loads
    for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[_name] = "1"

import argparse
import math
import time
import warnings
from pathlib import Path

import numpy as np
from discretization import POLICIES, RADIUS, TOP_K, bodies_of, geodesics, read
from robust_common import BENCH, log, spearman
from robust_common import surface_area as area

TOLERANCE = 1e-12


def exact_heat(stiffness, mass: np.ndarray, time_: float, fields: np.ndarray) -> np.ndarray:
    """``(n, C)`` ``exp(-t M^-1 S) fields`` for ``(n, n)`` sparse stiffness ``S`` (symmetric,
    positive semi-definite) and ``(n,)`` lumped ``mass``: a float64 Chebyshev series of the
    symmetric ``M^-1/2 S M^-1/2`` on ``[0, bound]`` (Gershgorin), truncated at 1e-12."""
    from scipy import sparse
    from scipy.special import ive

    root = 1.0 / np.sqrt(mass)
    symmetric = (sparse.diags(root) @ stiffness @ sparse.diags(root)).tocsr()
    half = float(abs(symmetric).sum(axis=1).max()) / 2.0  # spectrum in [0, 2 half]
    a = time_ * half
    terms = 2
    while 2.0 * ive(terms, a) > TOLERANCE:
        terms += 1
    # exp(-a (x + 1)) = sum_k (2 - [k = 0]) (-1)^k e^-a I_k(a) T_k(x) on x in [-1, 1]
    signs = np.where(np.arange(terms) % 2 == 0, 1.0, -1.0)
    coefficients = signs * ive(np.arange(terms), a) * np.where(np.arange(terms) == 0, 1.0, 2.0)

    def step(z):
        return symmetric @ z / half - z

    previous = fields * np.sqrt(mass)[:, None]
    current = step(previous)
    total = coefficients[0] * previous + coefficients[1] * current
    for k in range(2, terms):
        previous, current = current, 2.0 * step(current) - previous
        total += coefficients[k] * current
    return total * root[:, None]


def exact_channels(v: np.ndarray, f: np.ndarray, params) -> tuple[np.ndarray, np.ndarray]:
    """``((V, T) dn, (V,) mass)`` of the unit-area mesh, exactly (the module docstring)."""
    import robust_laplacian
    import torch

    from stochlap_torch.mesh import connected_components, unique_edges
    from stochlap_torch.mesh.geometry import outward_sign, vertex_normals

    unit = (v - v.mean(axis=0)) / math.sqrt(area(v, f))
    stiffness, mass_matrix = robust_laplacian.mesh_laplacian(unit, f)
    mass = np.asarray(mass_matrix.diagonal(), dtype=np.float64)
    points, faces = torch.from_numpy(unit), torch.from_numpy(f)
    labels = connected_components(len(v), unique_edges(faces, len(v)).numpy())
    sign = outward_sign(points, faces, torch.from_numpy(np.asarray(labels, dtype=np.int64)))
    normal = (vertex_normals(points, faces) * sign[:, None]).numpy()
    smoothed = normal
    if params.normal_time > 0:
        smoothed = exact_heat(stiffness, mass, params.normal_time, normal)
        smoothed = smoothed + 0.25 * exact_heat(stiffness, mass, params.normal_time / 16, normal)
    smoothed /= np.maximum(np.linalg.norm(smoothed, axis=1, keepdims=True), 1e-300)
    dn = []
    for t in params.times:
        moved = unit - exact_heat(stiffness, mass, t, unit)
        dn.append(np.einsum("ij,ij->i", smoothed, moved) / math.sqrt(t))
    return np.stack(dn, axis=1), mass


def saliency_of(dn: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """``(V,)`` the robust saliency's formula on ``(V, T)`` channels with ``(V,)`` areas."""
    weight = mass / mass.sum()
    centred = dn - weight @ dn
    deviation = np.sqrt(weight @ centred**2)
    return np.maximum(centred / deviation, 0.0).mean(axis=1)


def library(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``((V, T) dn, (V,) saliency)`` of the library's robust variant."""
    import torch

    import stochlap_torch as sl

    vt, ft = torch.from_numpy(np.ascontiguousarray(v)), torch.from_numpy(f)
    structure = sl.robust_structure(vt, ft)
    names = structure.channel_names()
    features = structure.features(vt).numpy()
    dn = features[:, [names.index(f"dn{k}") for k in range(structure.params.num_scales)]]
    return dn, structure.saliency(vt).numpy()


def top_points(saliency: np.ndarray, v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """The ``TOP_K`` interest points of a saliency, as ``discretization.py`` finds them."""
    import torch

    import stochlap_torch as sl
    from stochlap_torch.interest import InterestPointWarning

    with warnings.catch_warnings():  # fewer than TOP_K points is the benchmark's case too
        warnings.simplefilter("ignore", InterestPointWarning)
        found = sl.interest_points(torch.from_numpy(saliency), v, f, top_k=TOP_K)
    return found.numpy()


def point_distance(points: np.ndarray, v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``(V,)`` geodesic distance (heat method) to the nearest of ``points``, in sqrt(area)."""
    return geodesics(v, f, points, math.sqrt(area(v, f))).min(axis=0)


def evaluate(data_dir, body: str, policies) -> list[dict]:
    """One row per policy: exact and library Spearman against ``iso``, per scale and for the
    saliency, the repeatability of the saliency's top interest points, and the two
    saliencies' agreement on ``iso``."""
    from scipy.spatial import cKDTree

    from stochlap_torch import RobustParams

    params = RobustParams()
    vi, fi = read(data_dir, "iso", body)
    exact_iso, mass_iso = exact_channels(vi, fi, params)
    ours_iso, ours_saliency_iso = library(vi, fi)
    exact_saliency_iso = saliency_of(exact_iso, mass_iso)
    agreement = spearman(exact_saliency_iso, ours_saliency_iso)
    near_exact = point_distance(top_points(exact_saliency_iso, vi, fi), vi, fi)
    near_ours = point_distance(top_points(ours_saliency_iso, vi, fi), vi, fi)
    rows = []
    for policy in policies:
        v, f = read(data_dir, policy, body)
        truth = cKDTree(vi).query(v)[1]
        exact, mass = exact_channels(v, f, params)
        exact_saliency = saliency_of(exact, mass)
        ours, ours_saliency = library(v, f)
        scales = range(exact.shape[1])
        rows.append(
            {
                "body": body,
                "policy": policy,
                "exact": [spearman(exact_iso[truth, k], exact[:, k]) for k in scales],
                "ours": [spearman(ours_iso[truth, k], ours[:, k]) for k in scales],
                "exact_saliency": spearman(exact_saliency_iso[truth], exact_saliency),
                "ours_saliency": spearman(ours_saliency_iso[truth], ours_saliency),
                "exact_repeat": repeatability(exact_saliency, v, f, truth, near_exact),
                "ours_repeat": repeatability(ours_saliency, v, f, truth, near_ours),
                "agreement": agreement,
            }
        )
    return rows


def repeatability(saliency, v, f, truth: np.ndarray, near: np.ndarray) -> float:
    """Share of the remeshed mesh's top points whose true ``iso`` vertex lies within
    ``RADIUS`` of an ``iso`` point (``near``: the distance to them on ``iso``)."""
    return float(np.mean(near[truth[top_points(saliency, v, f)]] <= RADIUS))


def render(rows: list[dict], command: str) -> str:
    lines = [
        "# The surface's share: exact robust channels across the remeshing",
        "",
        "Generated by `benchmarks/discretization_exact.py` (see its docstring); do not edit.",
        f"Command: `{command}`.",
        "",
        "Spearman against the body's `iso` mesh at the true vertices. *exact*: the saliency's",
        "channels computed without approximation on each mesh (no pyramid, no mass cap or edge",
        "clamp, Chebyshev to 1e-12): how far the surface itself moves them. *library*: the",
        "robust variant as shipped. *agreement*: the two saliencies on the same `iso` mesh.",
        "",
        f"Repeatability: the share of the top {TOP_K} interest points within {RADIUS} sqrt(area)",
        "(geodesic) of the `iso` mesh's, as in `discretization.py` (there each remesh is also",
        "moved by a random similarity, so its figures differ slightly).",
        "",
        "| body | policy | saliency: exact | saliency: library | repeatability: exact | "
        "repeatability: library | agreement on iso | dn per scale: exact | dn per scale: library |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['body']} | {r['policy']} | {r['exact_saliency']:.3f} | "
            f"{r['ours_saliency']:.3f} | {r['exact_repeat']:.2f} | {r['ours_repeat']:.2f} | "
            f"{r['agreement']:.3f} | "
            f"{' '.join(f'{x:.3f}' for x in r['exact'])} | "
            f"{' '.join(f'{x:.3f}' for x in r['ours'])} |"
        )
    lines += ["", "Means over the bodies:", ""]
    lines += [
        "| policy | saliency: exact | saliency: library | repeatability: exact | "
        "repeatability: library |",
        "| --- | --- | --- | --- | --- |",
    ]
    for policy in dict.fromkeys(r["policy"] for r in rows):
        chosen = [r for r in rows if r["policy"] == policy]
        means = [
            np.mean([r[key] for r in chosen])
            for key in ("exact_saliency", "ours_saliency", "exact_repeat", "ours_repeat")
        ]
        lines.append(
            f"| {policy} | {means[0]:.3f} | {means[1]:.3f} | {means[2]:.2f} | {means[3]:.2f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("data_dir", type=Path, help="the benchmark's data/ folder")
    parser.add_argument("--bodies", default="080-089")
    parser.add_argument("--policies", default="mc", help="comma-separated, of qes,mc,dense")
    parser.add_argument("--out", type=Path, default=BENCH / "DISCRETIZATION_EXACT.md")
    args = parser.parse_args(argv)
    policies = args.policies.split(",")
    if not set(policies) <= set(POLICIES):
        parser.error(f"--policies must be among {','.join(POLICIES)}")
    rows = []
    for body in bodies_of(args.bodies):
        start = time.perf_counter()
        rows += evaluate(args.data_dir, body, policies)
        log(f"{body}: {time.perf_counter() - start:.0f} s")
    command = (
        f"python benchmarks/discretization_exact.py DATA_DIR --bodies {args.bodies} "
        f"--policies {args.policies}"
    )
    args.out.write_text(render(rows, command))
    log(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
