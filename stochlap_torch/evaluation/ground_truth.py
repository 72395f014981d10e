"""Ground-truth interest points from the marks of human subjects (Dutagaci et al. 2012, Sec. 3).

Distances are geodesic (:mod:`.geodesics`); ``sigma`` is given, as in that paper, as a fraction
of the mesh diameter ``d_M`` (:func:`.mesh_diameter`) unless a function says it takes absolute
distances. The measures against this ground truth are in :mod:`.interest_metrics`.

**Ground truth** (Dutagaci et al., Sec. 3). Each of ``K`` human subjects marked a set of
vertices. A surface point counts as an interest point if at least ``n`` subjects marked a
point within geodesic distance ``sigma`` of it:

1. for every mark ``p``, its region ``R(p)`` is the set of marks within ``sigma`` of ``p`` and
   its votes are the number of distinct subjects with a mark in ``R(p)``;
2. marks with at least ``n`` votes are candidates; the representative of a candidate's region
   is the mark of ``R(p)`` with the smallest sum of geodesic distances to the other marks of
   ``R(p)`` (the region's geodesic medoid);
3. candidates are taken by decreasing votes (ties: smaller distance sum, then input order) and
   a representative is kept unless it lies within ``separation * sigma`` (default ``2 sigma``)
   of one already kept, so that one region gives one point.

Steps 1 and 2 are the paper's criteria; step 3's order and tie-breaking are this module's
choice, made explicit so that results are reproducible.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .._common.errors import ParameterError
from ..mesh import as_mesh_tensors
from .geodesics import geodesic_distances, mesh_diameter

__all__ = ["GroundTruth", "build_ground_truth", "ground_truth_from_distances"]

logger = logging.getLogger(__name__)


def as_distance_matrix(distances, name: str = "distances") -> np.ndarray:
    """``(G, D)`` float64 array of non-negative distances (``inf`` allowed), or
    :class:`ParameterError`."""
    array = np.asarray(
        distances.detach().cpu() if isinstance(distances, Tensor) else distances, dtype=np.float64
    )
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

    vertices: Tensor
    votes: Tensor
    num_subjects: int
    sigma: float
    min_subjects: int

    @property
    def num_points(self) -> int:
        return int(self.vertices.shape[0])


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
    matrix = as_distance_matrix(distances, "mark distances")
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
    present = np.zeros((marks.size, max(num_subjects, 1)), dtype=bool)
    for subject in range(num_subjects):
        present[:, subject] = within[:, subject_ids == subject].any(axis=1)
    votes = present.sum(axis=1)
    spread = np.where(within, matrix, 0.0)
    # Medoid of each region: sums[p, q] = sum_{r in R(p)} d(q, r), kept for members q of R(p).
    finite = np.where(np.isfinite(matrix), matrix, 0.0)
    sums = within.astype(np.float64) @ finite
    medoid = np.argmin(np.where(within, sums, np.inf), axis=1)
    candidates = np.nonzero(votes >= min_subjects)[0]
    order = candidates[np.lexsort((candidates, spread[candidates].sum(axis=1), -votes[candidates]))]
    kept_marks: list[int] = []
    kept_votes: list[int] = []
    for p in order.tolist():
        rep = int(medoid[p])
        if any(matrix[rep, k] <= separation * sigma for k in kept_marks):
            continue
        kept_marks.append(rep)
        kept_votes.append(int(votes[p]))
    logger.debug("ground truth: %d points from %d marks", len(kept_marks), marks.size)
    return GroundTruth(
        vertices=torch.tensor(marks[kept_marks], dtype=torch.int64).reshape(-1),
        votes=torch.tensor(kept_votes, dtype=torch.int64).reshape(-1),
        num_subjects=num_subjects,
        sigma=float(sigma),
        min_subjects=int(min_subjects),
    )


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
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        marks: one sequence of marked vertex indices per subject.
        sigma: region radius as a fraction of the mesh diameter (Dutagaci et al. vary it; the
            default is one choice, not the benchmark's only setting).
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
