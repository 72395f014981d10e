"""Evaluation of interest points: :mod:`.geodesics` (distances, diameter),
:mod:`.interest_metrics` (ground truth from human marks; the errors of Dutagaci et al. 2012
against the localisation radius), :mod:`.truth` (the ground-truth files), :mod:`.benchmark`
(every detector on a mesh), :mod:`.compare` (the saliency beside the eigendecomposition
baselines: time, memory, agreement), :mod:`.remesh` (other triangulations of a surface).

The names are imported from their submodule on first use (PEP 562): importing this package,
or :mod:`.constants`, loads neither torch nor numpy (``stochlap evaluate --help``).
"""

from __future__ import annotations

import importlib

#: The public names, by the submodule they live in.
_HOMES = {
    "constants": "COMPARE_METHODS DEFAULT_COMPARE_METHODS DEFAULT_RADII EVALUATE_METHODS "
    "GEODESIC_METHODS",
    "compare": "Comparison MethodRun compare_methods method_saliency",
    "benchmark": "DetectorResult EvaluationSettings MeshEvaluation check_evaluation_parameters "
    "detector_saliency evaluate_detectors mean_error_curves",
    "geodesics": "GeodesicDistances GeodesicFallbackWarning choose_geodesic_method "
    "geodesic_distances mesh_diameter nonmanifold_edges",
    "interest_metrics": "MATCHINGS DetectionErrors ErrorCurves GroundTruth build_ground_truth "
    "detection_errors error_curves evaluate_interest_points ground_truth_from_distances "
    "match_points",
    "truth": "read_marks",
    "remesh": "Correspondence compact correspondence decimate isotropic_remesh random_similarity",
}
_HOME = {name: home for home, names in _HOMES.items() for name in names.split()}
__all__ = sorted(_HOME)


def __getattr__(name: str):
    if name not in _HOME:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{_HOME[name]}", __name__), name)
    globals()[name] = value  # later look-ups skip this
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
