"""Evaluation of interest points: geodesic distances and the measures of Dutagaci et al. 2012.

* :mod:`.geodesics`: distances from source vertices (heat method via potpourri3d when it is
  installed and the mesh allows it, graph Dijkstra otherwise), mesh diameter.
* :mod:`.ground_truth`: ground-truth points from the marks of human subjects.
* :mod:`.interest_metrics`: false negative, false positive and weighted miss errors of
  detected points as functions of the localisation radius.
* :mod:`.truth`: the ground-truth file format (one line of marked vertices per subject).
* :mod:`.detectors`: the saliency each compared detector takes its points from.
* :mod:`.benchmark`: every detector against the ground truth of a mesh, and the mean curves.

scipy (a core dependency) does the graphs and matchings. The heat method needs potpourri3d,
in the ``evaluation`` extra: ``pip install "stochlap_torch[evaluation]"``; without it, or on a
mesh with non-manifold edges, distances fall back to graph Dijkstra with a
:class:`GeodesicFallbackWarning`.
"""

from .benchmark import (
    DetectorResult,
    MeshEvaluation,
    check_evaluation_parameters,
    evaluate_detectors,
    mean_error_curves,
)
from .detectors import EVALUATE_METHODS, detector_saliency
from .geodesics import (
    GEODESIC_METHODS,
    GeodesicDistances,
    GeodesicFallbackWarning,
    choose_geodesic_method,
    geodesic_distances,
    mesh_diameter,
    nonmanifold_edges,
)
from .ground_truth import GroundTruth, build_ground_truth, ground_truth_from_distances
from .interest_metrics import (
    DEFAULT_RADII,
    MATCHINGS,
    DetectionErrors,
    ErrorCurves,
    detection_errors,
    error_curves,
    evaluate_interest_points,
    match_points,
)
from .truth import read_marks

__all__ = [
    "DEFAULT_RADII",
    "EVALUATE_METHODS",
    "GEODESIC_METHODS",
    "MATCHINGS",
    "DetectionErrors",
    "DetectorResult",
    "ErrorCurves",
    "GeodesicDistances",
    "GeodesicFallbackWarning",
    "GroundTruth",
    "MeshEvaluation",
    "build_ground_truth",
    "check_evaluation_parameters",
    "choose_geodesic_method",
    "detection_errors",
    "detector_saliency",
    "error_curves",
    "evaluate_detectors",
    "evaluate_interest_points",
    "geodesic_distances",
    "ground_truth_from_distances",
    "match_points",
    "mean_error_curves",
    "mesh_diameter",
    "nonmanifold_edges",
    "read_marks",
]
