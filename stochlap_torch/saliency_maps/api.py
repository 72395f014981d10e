"""``mesh_saliency``: the one entry point from a mesh to a saliency, any variant."""

from __future__ import annotations

import warnings

from torch import Tensor

from ..diffusion import ProgressCallback, multiscale_representation
from ..mesh import extent_scale, to_mesh_tensors
from .variants import DEFAULT_MIN_COUNT, check_variant, saliency_from_representation

__all__ = ["DEFAULT_VARIANT", "mesh_saliency", "variant_saliency"]

#: The variant every saliency entry point uses unless told otherwise.
DEFAULT_VARIANT = "paper"


def mesh_saliency(
    vertices,
    faces,
    num_scales: int = 8,
    threshold: float = 1e-3,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    batch: Tensor | None = None,
    backend: str = "auto",
    variant: str = DEFAULT_VARIANT,
    min_count: int = DEFAULT_MIN_COUNT,
) -> Tensor:
    """Saliency of every vertex: Algorithm 2, or a variant of :mod:`.variants`.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``.
        max_memory: byte budget for the operators (see
            :func:`~stochlap_torch.diffusion.multiscale_representation`).
        progress: called as ``progress(k, K)`` as the run advances.
        batch: optional ``(V,)`` mesh index of every vertex of a packed batch; results equal
            separate runs.
        backend: ``"auto"``, ``"torch"`` or ``"numba"``.
        variant: one of :data:`~.variants.VARIANTS`; :data:`DEFAULT_VARIANT` by default.
        min_count: see :func:`~.variants.valence_normalised_differences`.

    Returns:
        ``(V,)`` saliency in the dtype and on the device of ``vertices``; never NaN or Inf.

    Raises:
        ValueError: unknown variant, bad parameters. MeshError: bad mesh.
        MemoryBudgetError: the operators would not fit the budget.
    """
    check_variant(variant)
    points, faces = to_mesh_tensors(vertices, faces)  # validated by the representation
    # Saliency is scale invariant: compute at a safe size (an exact power-of-two scale).
    scale = extent_scale(points)
    points = points if scale == 1.0 else points * scale
    rep = multiscale_representation(
        points, faces, num_scales, threshold, max_memory=max_memory, progress=progress,
        backend=backend, batch=batch,
    )  # fmt: skip
    return saliency_from_representation(rep, points, faces, variant, min_count)


def variant_saliency(vertices, faces, variant: str = "normal_coefficients", **kwargs) -> Tensor:
    """Deprecated: :func:`mesh_saliency` with ``variant=`` (this name defaulted to
    ``"normal_coefficients"``, which it keeps until it is removed)."""
    warnings.warn(
        "variant_saliency is deprecated; call saliency(vertices, faces, variant=...) "
        "(stochlap_torch.saliency), whose default variant is 'paper'",
        DeprecationWarning,
        stacklevel=2,
    )
    return mesh_saliency(vertices, faces, variant=variant, **kwargs)
