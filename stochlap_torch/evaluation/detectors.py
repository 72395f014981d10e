"""The saliency each interest-point detector of the evaluation takes its points from."""

from __future__ import annotations

from collections.abc import Callable

from torch import Tensor

from .._common.errors import ParameterError
from .._common.variants import DEFAULT_THRESHOLD, PAPER_NUM_SCALES
from ..baselines import heat_kernel_signature, laplacian_saliency, lee_saliency
from ..saliency_maps import mesh_saliency
from .constants import EVALUATE_METHODS

__all__ = ["EVALUATE_METHODS", "detector_saliency", "hks_saliency"]


def hks_saliency(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V,)`` the heat kernel signature at the middle of 16 log-spaced times (100
    eigenpairs): the HKS detector's saliency."""
    return heat_kernel_signature(vertices, faces, num_eigenpairs=100, num_times=16)[:, 8]


def detector_saliency(
    method: str,
    vertices: Tensor,
    faces: Tensor,
    num_scales: int = PAPER_NUM_SCALES,
    threshold: float = DEFAULT_THRESHOLD,
) -> Tensor:
    """The ``(V,)`` saliency a method's interest points are taken from.

    Args:
        method: one of :data:`EVALUATE_METHODS`.
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` int64 tensor.
        num_scales, threshold: ``K`` and ``lambda`` of the Algorithm-2 methods (the robust
            one keeps its own scales).

    Returns:
        ``(V,)`` float saliency.
    """
    table: dict[str, Callable[[], Tensor]] = {
        "robust": lambda: mesh_saliency(vertices, faces, variant="robust"),
        "stochastic": lambda: mesh_saliency(
            vertices, faces, num_scales, threshold, variant="paper"
        ),
        "lee": lambda: lee_saliency(vertices, faces),
        "hks": lambda: hks_saliency(vertices, faces),
        "uniform": lambda: laplacian_saliency(vertices, faces, "uniform", num_scales, threshold),
        "cotangent": lambda: laplacian_saliency(
            vertices, faces, "cotangent", num_scales, threshold
        ),
    }
    for variant in ("normal_coefficients", "normal_displacement", "valence_normalised"):
        table[variant] = lambda v=variant: mesh_saliency(
            vertices, faces, num_scales, threshold, variant=v
        )
    if method not in table:
        raise ParameterError(
            f"unknown method {method!r}; choose from {', '.join(EVALUATE_METHODS)}"
        )
    return table[method]()
