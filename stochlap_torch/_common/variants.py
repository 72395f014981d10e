"""The names of the variants and the defaults of their settings, importable without torch
(the command line lists them in its help). Each default is stated here once."""

from __future__ import annotations

__all__ = [
    "DEFAULT_FEATURE_VARIANT",
    "DEFAULT_RADIUS",
    "DEFAULT_THRESHOLD",
    "DEFAULT_T_GLOBAL",
    "DEFAULT_VARIANT",
    "FEATURE_VARIANTS",
    "PAPER_FEATURE_SCALES",
    "PAPER_NUM_SCALES",
    "ROBUST_NUM_SCALES",
    "VARIANTS",
]

#: Saliency variants: ``"robust"`` and the paper's Algorithm 2 with the variants built on its
#: representation.
VARIANTS = ("robust", "paper", "normal_coefficients", "normal_displacement", "valence_normalised")
#: The saliency every entry point computes unless told otherwise: the robust one, the same for
#: the same surface meshed twice.
DEFAULT_VARIANT = "robust"
#: Representations the features can come from.
FEATURE_VARIANTS = ("robust", "paper")
#: The features' default: the robust channels (the paper's change with the triangulation).
DEFAULT_FEATURE_VARIANT = "robust"

#: The paper's number of scales ``K`` (its experiments use 8).
PAPER_NUM_SCALES = 8
#: Scales of the paper variant's features (fewer than the saliency's: each scale adds channels).
PAPER_FEATURE_SCALES = 6
#: The paper's precision ``lambda``: operator entries below it are dropped at every scale.
DEFAULT_THRESHOLD = 1e-3
#: Scales of the robust variant (:class:`~stochlap_torch.RobustParams`).
ROBUST_NUM_SCALES = 7
#: The interest points' ``"nms"`` suppression radius, a fraction of the bounding-box diagonal.
DEFAULT_RADIUS = 0.1
#: The fraction of the saliency range an interest point must reach (the paper's ``T_global``).
DEFAULT_T_GLOBAL = 0.4
