"""Saliency from the multiscale representation: Algorithm 2 and its variants.

:func:`mesh_saliency` (``stochlap_torch.saliency``) is the one entry point; the variants
(:data:`VARIANTS`) change only how the per-scale outputs of one run become a saliency.
"""

from ..diffusion.representation import saliency_from_differences
from .api import (
    DEFAULT_VARIANT,
    SaliencySettings,
    mesh_saliency,
    saliency_settings,
    saliency_with_settings,
    variant_saliency,
)
from .robust import robust_saliency
from .variants import (
    DEFAULT_MIN_COUNT,
    VARIANTS,
    check_variant,
    normal_coefficient_maps,
    saliency_from_representation,
    valence_normalised_differences,
)

__all__ = [
    "DEFAULT_MIN_COUNT",
    "DEFAULT_VARIANT",
    "VARIANTS",
    "SaliencySettings",
    "check_variant",
    "mesh_saliency",
    "normal_coefficient_maps",
    "robust_saliency",
    "saliency_from_differences",
    "saliency_from_representation",
    "saliency_settings",
    "saliency_with_settings",
    "valence_normalised_differences",
    "variant_saliency",
]
