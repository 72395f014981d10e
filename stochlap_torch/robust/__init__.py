"""The robust variant (``variant="robust"``): heat diffusion for physical times on a pyramid
of the mesh, one operator object per mesh (:class:`RobustStructure`).

* :mod:`.pyramid`: the coarser copies of the mesh and the interpolation between them;
* :mod:`.heat`: a level's heat operator, its Chebyshev semigroup and the heat diagonal;
* :mod:`.channels`: the channels, :class:`RobustRepresentation`, saliency and features;
* :mod:`.structure`: :class:`RobustStructure`, its building, checks and serialization.
"""

from ..params import RobustParams
from .channels import (
    SPREAD_FLOOR,
    RobustRepresentation,
    robust_channel_names,
    robust_features,
    robust_saliency,
)
from .structure import RobustStructure, robust_representation, robust_structure

__all__ = [
    "SPREAD_FLOOR",
    "RobustParams",
    "RobustRepresentation",
    "RobustStructure",
    "robust_channel_names",
    "robust_features",
    "robust_representation",
    "robust_saliency",
    "robust_structure",
]
