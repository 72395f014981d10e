"""The names and defaults of the evaluation, importable without torch or numpy.

``stochlap evaluate --help`` shows them from here, so the command line never spells them out
again and its help screen stays fast.
"""

from __future__ import annotations

__all__ = ["DEFAULT_RADII", "EVALUATE_METHODS", "GEODESIC_METHODS", "SCALED_METHODS"]

#: Detector names: ``robust`` (the robust variant's saliency), ``stochastic`` (the paper's
#: Algorithm 2), its variants, ``lee`` (Lee et al. 2005), ``hks`` (heat kernel signature),
#: ``uniform`` and ``cotangent`` (Algorithm 2 on them).
EVALUATE_METHODS = (
    "robust",
    "stochastic",
    "normal_coefficients",
    "normal_displacement",
    "valence_normalised",
    "lee",
    "hks",
    "uniform",
    "cotangent",
)

#: Geodesic distances: ``heat`` (potpourri3d), ``dijkstra`` (along the edges), or ``auto``
#: (heat when it can, Dijkstra otherwise; :func:`~.geodesics.choose_geodesic_method`).
GEODESIC_METHODS = ("auto", "heat", "dijkstra")

#: Localisation radii of Dutagaci et al.'s plots, as fractions of the mesh diameter: 0, 0.01,
#: ..., 0.12.
DEFAULT_RADII = tuple(round(0.01 * i, 6) for i in range(13))
#: The detectors that take ``num_scales`` and ``threshold`` (Algorithm 2 and its variants,
#: on the stochastic, uniform or cotangent Laplacian); the others refuse them.
SCALED_METHODS = (
    "stochastic",
    "normal_coefficients",
    "normal_displacement",
    "valence_normalised",
    "uniform",
    "cotangent",
)
