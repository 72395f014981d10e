"""Evaluation of interest points: geodesic distances and the measures of Dutagaci et al. 2012.

* :mod:`.geodesics`: distances from source vertices (heat method via potpourri3d when it is
  installed and the mesh allows it, graph Dijkstra otherwise), mesh diameter.
* :mod:`.ground_truth`: ground-truth points from the marks of human subjects.
* :mod:`.interest_metrics`: false negative, false positive and weighted miss errors of
  detected points as functions of the localisation radius.
* :mod:`.truth`: the ground-truth file format (one line of marked vertices per subject).
* :mod:`.detectors`: the saliency each compared detector takes its points from.
* :mod:`.benchmark`: every detector against the ground truth of a mesh, and the mean curves.
* :mod:`.remesh`: other triangulations of the same surface (quadric decimation, isotropic
  remeshing) and values carried between them by closest point, for robustness measurements.
* :mod:`.constants`: the names of the detectors and geodesic methods, the default radii
  (no torch needed).

scipy (a core dependency) does the graphs and matchings. The heat method needs potpourri3d,
in the ``evaluation`` extra: ``pip install "stochlap_torch[evaluation]"``; without it, or on a
mesh with non-manifold edges, distances fall back to graph Dijkstra with a
:class:`GeodesicFallbackWarning`.

The names below are imported from their submodule on first use (PEP 562): importing this
package, or :mod:`.constants`, loads neither torch nor numpy (``stochlap evaluate --help``
shows the methods and radii from there).
"""

from __future__ import annotations

import importlib

__all__ = [
    "DEFAULT_RADII",
    "EVALUATE_METHODS",
    "GEODESIC_METHODS",
    "MATCHINGS",
    "Correspondence",
    "DetectionErrors",
    "DetectorResult",
    "ErrorCurves",
    "EvaluationSettings",
    "GeodesicDistances",
    "GeodesicFallbackWarning",
    "GroundTruth",
    "MeshEvaluation",
    "build_ground_truth",
    "check_evaluation_parameters",
    "choose_geodesic_method",
    "compact",
    "correspondence",
    "decimate",
    "detection_errors",
    "detector_saliency",
    "error_curves",
    "evaluate_detectors",
    "evaluate_interest_points",
    "geodesic_distances",
    "ground_truth_from_distances",
    "isotropic_remesh",
    "match_points",
    "mean_error_curves",
    "mesh_diameter",
    "nonmanifold_edges",
    "random_similarity",
    "read_marks",
]

#: Where the public names are looked up, in this order (each submodule's ``__all__`` lists
#: its own): the torch-free :mod:`.constants` first.
_SUBMODULES = (
    "constants",
    "benchmark",
    "detectors",
    "geodesics",
    "ground_truth",
    "interest_metrics",
    "truth",
    "remesh",
)


def __getattr__(name: str):
    if name in __all__:
        for home in _SUBMODULES:
            module = importlib.import_module(f".{home}", __name__)
            if name in module.__all__:
                globals()[name] = value = getattr(module, name)  # later look-ups skip this
                return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
