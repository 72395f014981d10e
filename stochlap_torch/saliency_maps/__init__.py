"""Saliency from the multiscale representation: the robust variant's, Algorithm 2 and its
variants.

:func:`mesh_saliency` (``stochlap_torch.saliency``) is the one entry point; the paper's variants
(:data:`VARIANTS`) change only how the per-scale outputs of one run become a saliency.
"""

from ..diffusion.representation import saliency_from_differences
from .api import DEFAULT_VARIANT, mesh_saliency, saliency_params
from .variants import VARIANTS, saliency_from_representation, valence_normalised_differences

__all__ = [
    "DEFAULT_VARIANT",
    "VARIANTS",
    "mesh_saliency",
    "saliency_from_differences",
    "saliency_from_representation",
    "saliency_params",
    "valence_normalised_differences",
]
