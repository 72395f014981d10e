"""``mesh_saliency``: the one entry point from a mesh to a saliency, any variant."""

from __future__ import annotations

import dataclasses
import warnings

from torch import Tensor

from .._common.threads import serial_glue
from .._common.variants import DEFAULT_VARIANT
from ..diffusion import ProgressCallback, multiscale_representation
from ..diffusion.robust import RobustParams
from ..diffusion.robust_api import robust_representation
from ..mesh import extent_scale, to_mesh_tensors
from .robust import robust_saliency
from .variants import (
    DEFAULT_MIN_COUNT,
    POSITION_VARIANTS,
    check_variant,
    saliency_from_representation,
)

__all__ = ["DEFAULT_VARIANT", "mesh_saliency", "variant_saliency"]


@serial_glue()
def mesh_saliency(
    vertices,
    faces,
    num_scales: int | None = None,
    threshold: float = 1e-3,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    batch: Tensor | None = None,
    backend: str = "auto",
    variant: str = DEFAULT_VARIANT,
    min_count: int = DEFAULT_MIN_COUNT,
    robust: RobustParams | None = None,
) -> Tensor:
    """Saliency of every vertex: Algorithm 2, or a variant of :mod:`.variants`.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        num_scales: scales (default: 8 for the paper's variants, 7 for ``"robust"``).
        threshold: ``lambda`` in ``(0, 1)`` (the paper's variants).
        max_memory: byte budget for the operators (see
            :func:`~stochlap_torch.diffusion.multiscale_representation`).
        progress: called as ``progress(k, K)`` as the run advances.
        batch: optional ``(V,)`` mesh index of every vertex of a packed batch; results equal
            separate runs.
        backend: ``"auto"``, ``"torch"`` or ``"numba"``.
        variant: one of :data:`~.variants.VARIANTS`; :data:`DEFAULT_VARIANT` by default.
        min_count: see :func:`~.variants.valence_normalised_differences`.
        robust: settings of the ``"robust"`` variant
            (:class:`~stochlap_torch.diffusion.robust.RobustParams`; ``num_scales``, when
            given, overrides theirs).

    Returns:
        ``(V,)`` saliency in the dtype and on the device of ``vertices``; never NaN or Inf.

    Raises:
        ValueError: unknown variant, bad parameters. MeshError: bad mesh.
        MemoryBudgetError: the operators would not fit the budget.
    """
    check_variant(variant)
    if variant == "robust":
        params = RobustParams() if robust is None else robust
        if num_scales is not None:
            params = dataclasses.replace(params, num_scales=num_scales)
        rep = robust_representation(vertices, faces, params, batch, max_memory, progress,
                                   dn_only=True)  # fmt: skip
        return robust_saliency(rep)
    num_scales = 8 if num_scales is None else num_scales
    points, faces = to_mesh_tensors(vertices, faces)  # validated by the representation
    # Saliency is scale invariant: compute at a safe size (an exact power-of-two scale).
    scale = extent_scale(points)
    points = points if scale == 1.0 else points * scale
    rep = multiscale_representation(
        points, faces, num_scales, threshold, max_memory=max_memory, progress=progress,
        backend=backend, batch=batch, positions=variant in POSITION_VARIANTS,
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
