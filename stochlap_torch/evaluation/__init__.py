"""Evaluation of interest points: geodesic distances and the measures of Dutagaci et al. 2012.

* :mod:`.geodesics`: distances from source vertices (heat method via potpourri3d when it is
  installed and the mesh allows it, graph Dijkstra otherwise), mesh diameter.
* :mod:`.interest_metrics`: ground truth from human marks; false negative, false positive and
  weighted miss errors as functions of the localisation radius.

Needs scipy (``pip install "stochlap_torch[baselines]"``); potpourri3d is optional.
"""

from .geodesics import (
    GEODESIC_METHODS,
    GeodesicDistances,
    geodesic_distances,
    mesh_diameter,
    nonmanifold_edges,
)
from .interest_metrics import (
    DEFAULT_RADII,
    MATCHINGS,
    DetectionErrors,
    ErrorCurves,
    GroundTruth,
    build_ground_truth,
    detection_errors,
    error_curves,
    evaluate_interest_points,
    ground_truth_from_distances,
    match_points,
)

__all__ = [
    "DEFAULT_RADII",
    "GEODESIC_METHODS",
    "MATCHINGS",
    "DetectionErrors",
    "ErrorCurves",
    "GeodesicDistances",
    "GroundTruth",
    "build_ground_truth",
    "detection_errors",
    "error_curves",
    "evaluate_interest_points",
    "geodesic_distances",
    "ground_truth_from_distances",
    "match_points",
    "mesh_diameter",
    "nonmanifold_edges",
]
