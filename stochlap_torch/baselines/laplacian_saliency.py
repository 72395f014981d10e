"""Algorithm 2 run with the uniform or cotangent Laplacian in place of the stochastic one
(paper Fig. 11): ``Lhat = |L|``, the library's ``alpha`` and the library's steps."""

from __future__ import annotations

import torch
from torch import Tensor

from ..diffusion import run_steps, saliency_from_differences
from ..mesh import as_mesh_tensors, extent_scale
from ..operators import laplacian_operators
from ..params import PaperParams

__all__ = ["laplacian_saliency"]


def laplacian_saliency(
    vertices,
    faces,
    laplacian: str = "uniform",
    num_scales: int = PaperParams.num_scales,
    threshold: float = PaperParams.threshold,
    max_memory: int | None = None,
    backend: str = "auto",
) -> Tensor:
    """Algorithm 2 with the uniform or cotangent Laplacian: the library's steps on
    :func:`~stochlap_torch.operators.laplacian_operators`, the saliency from the difference
    maps ``D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j)``, ``k = 2..K``.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        laplacian: ``"uniform"`` or ``"cotangent"``.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``.
        max_memory: byte budget for the operators (default: ``$STOCHLAP_MAX_MEMORY``, else half the
            physical memory).
        backend: one of :data:`~stochlap_torch.diffusion.BACKENDS`.

    Returns:
        ``(V,)`` saliency in the dtype of ``vertices``.
    """
    params = PaperParams(num_scales, threshold)
    vertices, faces = as_mesh_tensors(vertices, faces)
    scale = extent_scale(vertices)  # scale invariant: an exact power-of-two rescaling
    with torch.no_grad():
        ops = laplacian_operators(vertices if scale == 1.0 else vertices * scale, faces, laplacian)
        # Only the difference maps are used; one channel of zeros keeps F^(k) P cheap.
        points = ops.alpha.new_zeros(ops.num_vertices, 1)
        steps = run_steps(
            ops, points, params.num_scales, params.threshold, backend=backend, max_memory=max_memory
        )
        return saliency_from_differences(steps.differences)
