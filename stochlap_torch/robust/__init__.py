"""The robust variant (``variant="robust"``): heat diffusion for physical times on a pyramid
of the mesh, as one operator object per mesh (:class:`RobustStructure`)."""

from ..diffusion.robust import RobustStructure, as_robust_params, build_structure
from ..diffusion.robust_api import (
    RobustRepresentation,
    check_structure,
    robust_memory,
    robust_representation,
    robust_structure,
    semigroup_memory,
)
from ..params import RobustParams
from .channels import SPREAD_FLOOR, robust_channel_names, robust_features, robust_saliency

__all__ = [
    "SPREAD_FLOOR",
    "RobustParams",
    "RobustRepresentation",
    "RobustStructure",
    "as_robust_params",
    "build_structure",
    "check_structure",
    "robust_channel_names",
    "robust_features",
    "robust_memory",
    "robust_representation",
    "robust_saliency",
    "robust_structure",
    "semigroup_memory",
]
