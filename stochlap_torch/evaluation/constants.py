"""The names and defaults of the evaluation, importable without torch or numpy: ``stochlap
evaluate --help`` shows them from here."""

from __future__ import annotations

#: The paper's Algorithm 2 (``stochastic``) and its variants.
_ALGORITHM_2 = ("stochastic", "normal_coefficients", "normal_displacement", "valence_normalised")
#: Detector names: ``robust`` (the robust variant's saliency), Algorithm 2 and its variants,
#: ``lee`` (Lee et al. 2005), ``hks`` (heat kernel signature), ``uniform`` and ``cotangent``
#: (Algorithm 2 on them).
EVALUATE_METHODS = ("robust", *_ALGORITHM_2, "lee", "hks", "uniform", "cotangent")
#: The detectors that take ``num_scales`` and ``threshold``; the others refuse them.
SCALED_METHODS = (*_ALGORITHM_2, "uniform", "cotangent")
#: Geodesic distances: ``heat`` (potpourri3d), ``dijkstra`` (along the edges), or ``auto``
#: (heat when it can, Dijkstra otherwise; :func:`~.geodesics.choose_geodesic_method`).
GEODESIC_METHODS = ("auto", "heat", "dijkstra")
#: Localisation radii of Dutagaci et al.'s plots, as fractions of the mesh diameter: 0, 0.01,
#: ..., 0.12.
DEFAULT_RADII = tuple(round(0.01 * i, 6) for i in range(13))
#: The methods of ``stochlap compare`` (:func:`~.compare.compare_methods`).
COMPARE_METHODS = ("robust", "stochastic", "hks", "spectral", "lee", "uniform", "cotangent")
#: What ``stochlap compare`` runs when no method is named.
DEFAULT_COMPARE_METHODS = ("robust", "stochastic", "hks", "spectral", "lee")
