"""Interest points against human-marked ground truth (paper Sec. 4.5, Fig. 15), after
Dutagaci, Cheung and Godil, The Visual Computer 28 (2012) 901-917 (the paper's ref. [49]).

Distances are geodesic (:mod:`.geodesics`); ``sigma`` and the radii ``r`` are fractions of
the mesh diameter ``d_M`` (:func:`.mesh_diameter`) unless a function takes absolute ones.

**Ground truth** (Dutagaci et al., Sec. 3): a point counts if at least ``n`` of the ``K``
subjects marked a point within ``sigma`` of it.

1. The region ``R(p)`` of a mark ``p`` holds the marks within ``sigma`` of it; its votes are
   the number of distinct subjects with a mark in ``R(p)``.
2. Marks with at least ``n`` votes are candidates, each represented by the geodesic medoid of
   ``R(p)`` (the mark with the smallest sum of distances to the others).
3. By decreasing votes (ties: smaller distance sum, then input order), a representative is
   kept unless within ``separation * sigma`` (default ``2 sigma``) of one already kept. This
   order is this module's choice (the paper gives none), fixed for reproducibility.

**Measures** (Dutagaci et al., Sec. 4): ``N_G`` ground-truth points ``g_i`` with votes
``n_i``, ``N_D`` detected points; ``g_i`` is detected (``delta_i = 1``) if it is matched,
one-to-one, to a detected point within ``r``. With ``N_C`` such matches:
``FNE = 1 - N_C / N_G``, ``FPE = 1 - N_C / N_D`` (0 when nothing is detected) and
``WME = 1 - sum_i n_i delta_i / sum_i n_i``, the share of the votes on missed points.

The matching's order is left open by the paper: ``matching="greedy"`` (default) pairs the
closest (ground truth, detection) pair within ``r`` first, and so on among the unmatched;
``"optimal"`` maximises the matches, then the matched votes, then minimises the total
distance (``scipy.optimize.linear_sum_assignment``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from scipy import optimize
from torch import Tensor

from .._common.checks import check_choice
from .._common.errors import ParameterError
from .._common.tensors import to_numpy
from ..mesh import as_mesh_tensors
from .constants import DEFAULT_RADII
from .geodesics import geodesic_distances, mesh_diameter

#: ``matching=`` values: see the module docstring.
MATCHINGS = ("greedy", "optimal")


def _distances(distances, name: str = "distances") -> np.ndarray:
    """``(G, D)`` float64 array of non-negative distances (``inf`` allowed)."""
    array = np.asarray(to_numpy(distances), dtype=np.float64)
    if array.ndim != 2:
        raise ParameterError(f"{name} must be a 2-D (G, D) matrix, got shape {array.shape}")
    if np.isnan(array).any() or (array < 0).any():
        raise ParameterError(f"{name} must hold non-negative distances (inf allowed), no NaN")
    return array


@dataclass(frozen=True)
class GroundTruth:
    """Ground-truth interest points of one mesh.

    Attributes:
        vertices: ``(G,)`` int64 vertex index of each ground-truth point.
        votes: ``(G,)`` int64 number of distinct subjects that marked a point within ``sigma``.
        num_subjects: ``K``, the number of subjects whose marks were used.
        sigma: the region radius, absolute (units of the mesh).
        min_subjects: ``n``, the votes a point needed.
    """

    @property
    def num_points(self) -> int:
        """``G``."""
        return int(self.vertices.shape[0])

    vertices: Tensor
    votes: Tensor
    num_subjects: int
    sigma: float
    min_subjects: int


def ground_truth_from_distances(
    mark_vertices,
    mark_subjects,
    distances,
    sigma: float,
    min_subjects: int,
    separation: float = 2.0,
) -> GroundTruth:
    """Ground-truth points from human marks and the geodesic distances between the marks.

    Args:
        mark_vertices: ``(M,)`` vertex index of every mark (all subjects together).
        mark_subjects: ``(M,)`` subject id of every mark.
        distances: ``(M, M)`` symmetric geodesic distances between the marks (absolute).
        sigma: region radius, absolute (``> 0``).
        min_subjects: ``n >= 1``, votes a point needs.
        separation: kept points are more than ``separation * sigma`` apart.

    Returns:
        :class:`GroundTruth`, points in order of decreasing votes.
    """
    marks = np.asarray(mark_vertices, dtype=np.int64).reshape(-1)
    subjects = np.asarray(mark_subjects).reshape(-1)
    matrix = _distances(distances, "mark distances")
    if subjects.shape != marks.shape or matrix.shape != (marks.size, marks.size):
        raise ParameterError(
            f"{marks.size} marks need {marks.size} subject ids and a ({marks.size}, "
            f"{marks.size}) distance matrix, got {subjects.shape} and {matrix.shape}"
        )
    if not sigma > 0:
        raise ParameterError(f"sigma must be positive, got {sigma!r}")
    if min_subjects < 1:
        raise ParameterError(f"min_subjects must be >= 1, got {min_subjects!r}")
    _, subject_ids = np.unique(subjects, return_inverse=True)
    num_subjects = int(subject_ids.max()) + 1 if marks.size else 0
    within = matrix <= sigma  # (M, M): region membership, row p is R(p)
    votes = np.array([np.unique(subject_ids[row]).size for row in within], dtype=np.int64)
    spread = np.where(within, matrix, 0.0)
    # Medoid of each region: sums[p, q] = sum_{r in R(p)} d(q, r), kept for members q of R(p).
    finite = np.where(np.isfinite(matrix), matrix, 0.0)
    sums = within.astype(np.float64) @ finite
    medoid = np.argmin(np.where(within, sums, np.inf), axis=1)
    candidates = np.nonzero(votes >= min_subjects)[0]
    order = candidates[np.lexsort((candidates, spread[candidates].sum(axis=1), -votes[candidates]))]
    kept: list[tuple[int, int]] = []  # (representative mark, votes)
    for p in order.tolist():
        rep = int(medoid[p])
        if not any(matrix[rep, k] <= separation * sigma for k, _ in kept):
            kept.append((rep, int(votes[p])))
    points = torch.tensor(marks[[k for k, _ in kept]], dtype=torch.int64).reshape(-1)
    votes = torch.tensor([n for _, n in kept], dtype=torch.int64).reshape(-1)
    return GroundTruth(points, votes, num_subjects, float(sigma), int(min_subjects))


def build_ground_truth(
    vertices,
    faces,
    marks: Sequence[Sequence[int]],
    sigma: float = 0.03,
    min_subjects: int = 2,
    diameter: float | None = None,
    method: str = "auto",
    separation: float = 2.0,
) -> GroundTruth:
    """Ground-truth points of a mesh from each subject's marked vertices.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        marks: one sequence of marked vertex indices per subject.
        sigma: region radius as a fraction of the mesh diameter.
        min_subjects: ``n``, the number of subjects that must agree.
        diameter: the mesh diameter ``d_M``; default :func:`.mesh_diameter`.
        method: geodesic method, see :func:`.geodesic_distances`.
        separation: see :func:`ground_truth_from_distances`.

    Returns:
        :class:`GroundTruth` with the absolute ``sigma``.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    mark_vertices = [int(v) for subject in marks for v in subject]
    mark_subjects = [s for s, subject in enumerate(marks) for _ in subject]
    if not mark_vertices:
        raise ParameterError("no marks")
    if diameter is None:
        diameter = mesh_diameter(vertices, faces, method)
    unique, inverse = np.unique(mark_vertices, return_inverse=True)
    geodesic = geodesic_distances(vertices, faces, unique, method).distances.numpy()
    pairwise = geodesic[:, unique][inverse][:, inverse]
    pairwise = np.minimum(pairwise, pairwise.T)  # the heat method is not exactly symmetric
    return ground_truth_from_distances(
        mark_vertices, mark_subjects, pairwise, sigma * diameter, min_subjects, separation
    )


@dataclass(frozen=True)
class DetectionErrors:
    """The three measures at one radius.

    Attributes:
        fne, fpe, wme: false negative, false positive and weighted miss error, in ``[0, 1]``.
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
        fne, fpe, wme: ``(R,)`` float64 false negative, false positive and weighted miss error.
        num_correct: ``(R,)`` int64 ``N_C``.
    """

    radii: Tensor
    fne: Tensor
    fpe: Tensor
    wme: Tensor
    num_correct: Tensor


def _votes(votes, num_truth: int) -> np.ndarray:
    """``(G,)`` float64 ``votes`` of the ``num_truth`` ground-truth points, each finite and
    positive (:class:`ParameterError` otherwise)."""
    weight = np.asarray(votes.cpu() if isinstance(votes, Tensor) else votes, dtype=np.float64)
    if weight.shape != (num_truth,):
        raise ParameterError(f"votes must have shape ({num_truth},), got {weight.shape}")
    if not bool((np.isfinite(weight) & (weight > 0)).all()):
        raise ParameterError("votes must be finite and positive")
    return weight


def match_points(distances, radius: float, votes=None, matching: str = "greedy") -> np.ndarray:
    """One-to-one matching of ground-truth to detected points within ``radius``.

    Args:
        distances: ``(G, D)`` absolute geodesic distances, ground truth by detections.
        radius: the localisation radius ``r`` (absolute, ``>= 0``).
        votes: ``(G,)`` finite positive votes (``"optimal"`` prefers matching well-voted points;
            ``None``: equal).
        matching: one of :data:`MATCHINGS`.

    Returns:
        ``(G,)`` int64: the detection matched to each ground-truth point, ``-1`` if none.
    """
    check_choice("matching", matching, MATCHINGS)
    if not radius >= 0:
        raise ParameterError(f"radius must be >= 0, got {radius!r}")
    matrix = _distances(distances)
    num_truth, num_detected = matrix.shape
    weight = np.ones(num_truth) if votes is None else _votes(votes, num_truth)
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
        distances: ``(G, D)`` absolute geodesic distances from the ``G >= 1`` ground-truth
            points to the detected points.
        votes: ``(G,)`` positive votes ``n_i`` of the ground-truth points.
        radius: ``r``, absolute.
        matching: one of :data:`MATCHINGS`.
    """
    matrix = _distances(distances)
    num_truth, num_detected = matrix.shape
    if num_truth == 0:
        raise ParameterError("no ground-truth points: the errors are undefined")
    weight = _votes(votes, num_truth)
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
        distances, votes, matching: as in :func:`detection_errors`.
        radii: ``(R,)`` absolute radii.

    Returns:
        :class:`ErrorCurves` with ``radii`` as given.
    """
    radii = [float(r) for r in radii]
    if not radii:
        raise ParameterError("radii is empty")
    results = [detection_errors(distances, votes, r, matching) for r in radii]
    fne, fpe, wme = (
        torch.tensor([getattr(e, key) for e in results], dtype=torch.float64)
        for key in ("fne", "fpe", "wme")
    )
    correct = torch.tensor([e.num_correct for e in results], dtype=torch.int64)
    return ErrorCurves(torch.tensor(radii, dtype=torch.float64), fne, fpe, wme, correct)


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
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        ground_truth: from :func:`build_ground_truth` (or made by hand).
        detected: ``(D,)`` detected vertex indices, e.g. from
            :func:`~stochlap_torch.interest.interest_points`.
        radii: localisation radii as fractions of the mesh diameter.
        diameter: ``d_M``; default :func:`.mesh_diameter`.
        method: geodesic method, see :func:`.geodesic_distances`.
        matching: one of :data:`MATCHINGS`.

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
    distances = geodesic_distances(vertices, faces, ground_truth.vertices, method).distances
    absolute = [r * diameter for r in radii]
    curves = error_curves(distances[:, detected], ground_truth.votes, absolute, matching)
    return dataclasses.replace(
        curves, radii=torch.tensor([float(r) for r in radii], dtype=torch.float64)
    )
