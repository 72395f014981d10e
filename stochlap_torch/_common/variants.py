"""The names of the saliency variants and the interest points' defaults, importable without
torch (the command line lists them in its help). The methods' numeric defaults are their
parameters dataclasses' (:mod:`stochlap_torch.params`)."""

from __future__ import annotations

#: Saliency variants: ``"robust"`` and the paper's Algorithm 2 with the variants built on its
#: representation.
VARIANTS = ("robust", "paper", "normal_coefficients", "normal_displacement", "valence_normalised")
#: The saliency every entry point computes unless told otherwise: the robust one, the same for
#: the same surface meshed twice.
DEFAULT_VARIANT = "robust"

#: The interest points' ``"nms"`` suppression radius, a fraction of the bounding-box diagonal.
DEFAULT_RADIUS = 0.1
#: The fraction of the saliency range an interest point must reach (the paper's ``T_global``).
DEFAULT_T_GLOBAL = 0.4
