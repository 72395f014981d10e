"""Measures of detected interest points against a ground truth (paper Sec. 4.5, Fig. 15).

The measures and the ground truth follow Dutagaci, Cheung and Godil, "Evaluation of 3D
interest point detection techniques via human-generated ground truth", The Visual Computer
28 (2012) 901-917 (the benchmark of the paper's ref. [49]). All distances are geodesic
(:mod:`.geodesics`); radii ``r`` and ``sigma`` are given, as in that paper, as fractions of the
mesh diameter ``d_M`` (the largest geodesic distance on the mesh, :func:`.mesh_diameter`),
unless a function says it takes absolute distances. The ground truth itself comes from
:mod:`.ground_truth`.

**Measures** (Dutagaci et al., Sec. 4). For ``N_G`` ground-truth points ``g_i`` with votes
``n_i`` and ``N_D`` detected points, at localisation radius ``r``: a ground-truth point is
correctly detected if a detected point lies within geodesic distance ``r`` of it, with a
one-to-one matching (a detected point matches at most one ground-truth point). With ``N_C``
correct detections:

* false negative error ``FNE(r) = 1 - N_C / N_G``;
* false positive error ``FPE(r) = 1 - N_C / N_D`` (0 when nothing is detected);
* weighted miss error ``WME(r) = 1 - sum_i n_i delta_i / sum_i n_i``, ``delta_i = 1`` if
  ``g_i`` is detected: the share of the human votes that falls on missed points.

The paper leaves the order of the one-to-one matching open. ``matching="greedy"`` (default)
pairs the closest (ground truth, detection) pair within ``r`` first, then the next closest
among the unmatched, and so on; ``matching="optimal"`` maximises the number of matches, then
the matched votes, then minimises the total distance (``scipy.optimize.linear_sum_assignment``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .._common.errors import ParameterError
from ..mesh import as_mesh_tensors
from .constants import DEFAULT_RADII
from .geodesics import geodesic_distances, mesh_diameter
from .ground_truth import GroundTruth, as_distance_matrix

__all__ = [
    "DEFAULT_RADII",
    "MATCHINGS",
    "DetectionErrors",
    "ErrorCurves",
    "detection_errors",
    "error_curves",
    "evaluate_interest_points",
    "match_points",
]

MATCHINGS = ("greedy", "optimal")


@dataclass(frozen=True)
class DetectionErrors:
    """The three measures at one radius.

    Attributes:
        fne: false negative error in ``[0, 1]``.
        fpe: false positive error in ``[0, 1]``.
        wme: weighted miss error in ``[0, 1]``.
        num_correct: ``N_C``.
        matched_truth: ``(G,)`` bool, ground-truth points correctly detected.
        matched_detections: ``(D,)`` bool, detected points matched to a ground-truth point.
    """

    fne: float
    fpe: float
    wme: float
    num_correct: int
    matched_truth: Tensor
    matched_detections: Tensor


@dataclass(frozen=True)
class ErrorCurves:
    """The three measures as functions of the localisation radius.

    Attributes:
        radii: ``(R,)`` float64 radii (in the units they were given in).
        fne: ``(R,)`` float64 false negative error.
        fpe: ``(R,)`` float64 false positive error.
        wme: ``(R,)`` float64 weighted miss error.
        num_correct: ``(R,)`` int64 ``N_C``.
    """

    radii: Tensor
    fne: Tensor
    fpe: Tensor
    wme: Tensor
    num_correct: Tensor


def match_points(distances, radius: float, votes=None, matching: str = "greedy") -> np.ndarray:
    """One-to-one matching of ground-truth to detected points within ``radius``.

    Args:
        distances: ``(G, D)`` geodesic distances, ground truth by detections (absolute).
        radius: the localisation radius ``r`` (absolute, ``>= 0``).
        votes: ``(G,)`` votes (used by ``"optimal"`` to prefer matching well-voted points).
        matching: ``"greedy"`` or ``"optimal"`` (see the module docstring).

    Returns:
        ``(G,)`` int64: the detection matched to each ground-truth point, ``-1`` if none.
    """
    if matching not in MATCHINGS:
        raise ParameterError(f"matching must be one of {MATCHINGS}, got {matching!r}")
    if not radius >= 0:
        raise ParameterError(f"radius must be >= 0, got {radius!r}")
    matrix = as_distance_matrix(distances)
    num_truth, num_detected = matrix.shape
    match = np.full(num_truth, -1, dtype=np.int64)
    rows, cols = np.nonzero(matrix <= radius)
    if rows.size == 0:
        return match
    if matching == "greedy":
        order = np.lexsort((cols, rows, matrix[rows, cols]))
        taken = np.zeros(num_detected, dtype=bool)
        for row, col in zip(rows[order].tolist(), cols[order].tolist(), strict=True):
            if match[row] < 0 and not taken[col]:
                match[row], taken[col] = col, True
        return match
    from scipy import optimize

    weight = np.ones(num_truth) if votes is None else np.asarray(votes, dtype=np.float64)
    # Lexicographic objective: one more match beats any vote total, which beats any distance.
    per_match = weight.sum() + 1.0
    finite = matrix[rows, cols]
    scale = finite.max() + 1.0
    cost = np.zeros((num_truth, num_detected))
    cost[rows, cols] = -(per_match + weight[rows] - 0.5 * finite / scale)
    assigned_rows, assigned_cols = optimize.linear_sum_assignment(cost)
    feasible = matrix[assigned_rows, assigned_cols] <= radius
    match[assigned_rows[feasible]] = assigned_cols[feasible]
    return match


def detection_errors(distances, votes, radius: float, matching: str = "greedy") -> DetectionErrors:
    """FNE, FPE and WME at one localisation radius.

    Args:
        distances: ``(G, D)`` geodesic distances from the ground-truth points to the detected
            points (absolute), e.g. columns of :func:`.geodesic_distances` from ``G`` sources.
        votes: ``(G,)`` positive votes ``n_i`` of the ground-truth points.
        radius: ``r``, absolute.
        matching: ``"greedy"`` or ``"optimal"``.

    Returns:
        :class:`DetectionErrors`.

    Raises:
        ValueError: no ground-truth point, shapes that disagree, or non-positive votes.
    """
    matrix = as_distance_matrix(distances)
    weight = np.asarray(votes.cpu() if isinstance(votes, Tensor) else votes, dtype=np.float64)
    num_truth, num_detected = matrix.shape
    if num_truth == 0:
        raise ParameterError("no ground-truth points: the errors are undefined")
    if weight.shape != (num_truth,):
        raise ParameterError(f"votes must have shape ({num_truth},), got {weight.shape}")
    if not bool((weight > 0).all()):
        raise ParameterError("votes must be positive")
    match = match_points(matrix, radius, weight, matching)
    matched = match >= 0
    correct = int(matched.sum())
    detections = np.zeros(num_detected, dtype=bool)
    detections[match[matched]] = True
    return DetectionErrors(
        fne=1.0 - correct / num_truth,
        fpe=1.0 - correct / num_detected if num_detected else 0.0,
        wme=1.0 - float(weight[matched].sum() / weight.sum()),
        num_correct=correct,
        matched_truth=torch.from_numpy(matched),
        matched_detections=torch.from_numpy(detections),
    )


def error_curves(distances, votes, radii: Sequence[float], matching: str = "greedy") -> ErrorCurves:
    """:func:`detection_errors` at each radius.

    Args:
        distances: ``(G, D)`` absolute geodesic distances (ground truth by detections).
        votes: ``(G,)`` votes.
        radii: ``(R,)`` absolute radii.
        matching: ``"greedy"`` or ``"optimal"``.

    Returns:
        :class:`ErrorCurves` with ``radii`` as given.
    """
    radii = [float(r) for r in radii]
    if not radii:
        raise ParameterError("radii is empty")
    results = [detection_errors(distances, votes, r, matching) for r in radii]
    return ErrorCurves(
        radii=torch.tensor(radii, dtype=torch.float64),
        fne=torch.tensor([e.fne for e in results], dtype=torch.float64),
        fpe=torch.tensor([e.fpe for e in results], dtype=torch.float64),
        wme=torch.tensor([e.wme for e in results], dtype=torch.float64),
        num_correct=torch.tensor([e.num_correct for e in results], dtype=torch.int64),
    )


def evaluate_interest_points(
    vertices,
    faces,
    ground_truth: GroundTruth,
    detected,
    radii: Sequence[float] = DEFAULT_RADII,
    diameter: float | None = None,
    method: str = "auto",
    matching: str = "greedy",
) -> ErrorCurves:
    """FNE, FPE and WME of detected interest points against a ground truth, over radii.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        ground_truth: from :func:`build_ground_truth` (or made by hand).
        detected: ``(D,)`` detected vertex indices, e.g. from
            :func:`~stochlap_torch.interest.interest_points`.
        radii: localisation radii as fractions of the mesh diameter.
        diameter: ``d_M``; default :func:`.mesh_diameter`.
        method: geodesic method, see :func:`.geodesic_distances`.
        matching: ``"greedy"`` or ``"optimal"``.

    Returns:
        :class:`ErrorCurves` whose ``radii`` are the given fractions.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    if ground_truth.num_points == 0:
        raise ParameterError("the ground truth has no points")
    detected = torch.as_tensor(detected, dtype=torch.int64).reshape(-1)
    if bool(((detected < 0) | (detected >= vertices.shape[0])).any()):
        raise ParameterError(f"detected indices must lie in [0, {vertices.shape[0]})")
    if diameter is None:
        diameter = mesh_diameter(vertices, faces, method)
    geodesic = geodesic_distances(vertices, faces, ground_truth.vertices, method).distances
    distances = geodesic[:, detected]
    curves = error_curves(distances, ground_truth.votes, [r * diameter for r in radii], matching)
    return ErrorCurves(
        torch.tensor([float(r) for r in radii], dtype=torch.float64),
        curves.fne,
        curves.fpe,
        curves.wme,
        curves.num_correct,
    )
