"""``mesh_saliency``: the one entry point from a mesh to a saliency, any variant."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

from torch import Tensor

from .._common.checks import check_choice, check_int, refuse_unused
from .._common.variants import DEFAULT_VARIANT
from ..diffusion import BACKENDS, ProgressCallback, multiscale_representation
from ..diffusion.parameters import PaperParams, as_paper_params
from ..diffusion.robust import RobustParams, RobustStructure, as_robust_params
from ..diffusion.robust_api import robust_representation
from ..mesh import extent_scale, to_mesh_tensors
from .robust import robust_saliency
from .variants import (
    DEFAULT_MIN_COUNT,
    POSITION_VARIANTS,
    check_variant,
    saliency_from_representation,
)

__all__ = [
    "DEFAULT_VARIANT",
    "SaliencySettings",
    "mesh_saliency",
    "saliency_settings",
    "saliency_with_settings",
    "variant_saliency",
]


@dataclass(frozen=True)
class SaliencySettings:
    """The resolved settings of a saliency: everything its numbers depend on.

    Attributes:
        variant: one of :data:`~stochlap_torch.saliency_maps.VARIANTS`.
        params: :class:`~stochlap_torch.diffusion.RobustParams` for ``"robust"``, else
            :class:`~stochlap_torch.diffusion.PaperParams`.
        min_count: ``"valence_normalised"``'s smallest valence population (else ``None``).
    """

    variant: str
    params: RobustParams | PaperParams
    min_count: int | None = None


def saliency_settings(
    variant: str = DEFAULT_VARIANT,
    num_scales: int | None = None,
    threshold: float | None = None,
    min_count: int | None = None,
    backend: str | None = None,
    robust: RobustParams | None = None,
    paper: PaperParams | None = None,
) -> SaliencySettings:
    """The :class:`SaliencySettings` of the arguments of :func:`mesh_saliency` (``None`` is
    "not given"); ``num_scales`` and ``threshold`` override the fields of ``robust`` or
    ``paper``. ``backend`` does not change the numbers and is only checked.

    Raises:
        ParameterError: a bad value, or an option the variant does not use (``"robust"``:
            ``threshold``, ``backend``, ``min_count``, ``paper``; the paper's variants:
            ``robust``, and ``min_count`` but for ``"valence_normalised"``).
    """
    check_variant(variant)
    if variant == "robust":
        refuse_unused(
            variant,
            {"threshold": threshold, "backend": backend, "min_count": min_count, "paper": paper},
        )
        return SaliencySettings(variant, as_robust_params(robust, num_scales))
    refuse_unused(variant, {"robust": robust})
    if variant == "valence_normalised":
        min_count = check_int(
            "min_count", DEFAULT_MIN_COUNT if min_count is None else min_count, minimum=1
        )
    else:
        refuse_unused(variant, {"min_count": min_count})
    if backend is not None:
        check_choice("backend", backend, BACKENDS)
    return SaliencySettings(variant, as_paper_params(paper, num_scales, threshold), min_count)


def mesh_saliency(
    vertices,
    faces,
    num_scales: int | None = None,
    threshold: float | None = None,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    batch: Tensor | None = None,
    backend: str | None = None,
    variant: str = DEFAULT_VARIANT,
    min_count: int | None = None,
    robust: RobustParams | None = None,
    paper: PaperParams | None = None,
    structure: RobustStructure | list[RobustStructure] | None = None,
) -> Tensor:
    """Saliency of every vertex: Algorithm 2, or a variant of :mod:`.variants`.

    Options left ``None`` take the variant's defaults; an option the variant does not use is
    refused (:func:`saliency_settings`).

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        num_scales: scales (default: 8 for the paper's variants, ``RobustParams().num_scales``
            for ``"robust"``).
        threshold: ``lambda`` in ``(0, 1)`` (the paper's variants; default ``1e-3``).
        max_memory: byte budget for the operators (see
            :func:`~stochlap_torch.diffusion.multiscale_representation`).
        progress: called as ``progress(k, K)`` as the run advances.
        batch: optional ``(V,)`` mesh index of every vertex of a packed batch; results equal
            separate runs.
        backend: ``"auto"`` (default), ``"torch"`` or ``"numba"`` (the paper's variants).
        variant: one of :data:`~.variants.VARIANTS`; :data:`DEFAULT_VARIANT` by default.
        min_count: ``"valence_normalised"`` only; see
            :func:`~.variants.valence_normalised_differences`.
        robust: settings of the ``"robust"`` variant
            (:class:`~stochlap_torch.diffusion.RobustParams`, or a mapping of its fields).
        paper: settings of the paper's variants (:class:`~stochlap_torch.diffusion.PaperParams`).
        structure: ``"robust"`` only: the mesh's
            :class:`~stochlap_torch.diffusion.robust.RobustStructure`
            (:func:`~stochlap_torch.robust_structure` with the same ``robust`` settings; for a
            batch, a list of one per mesh), reused instead of built.

    Returns:
        ``(V,)`` saliency in the dtype and on the device of ``vertices``; never NaN or Inf.

    Raises:
        ParameterError: unknown variant, bad parameters, an option the variant does not use.
        MeshError: bad mesh. MemoryBudgetError: the operators would not fit the budget.
    """
    settings = saliency_settings(variant, num_scales, threshold, min_count, backend, robust, paper)
    return saliency_with_settings(
        vertices, faces, settings, max_memory, progress, batch, backend, structure
    )


def saliency_with_settings(
    vertices,
    faces,
    settings: SaliencySettings,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    batch: Tensor | None = None,
    backend: str | None = None,
    structure: RobustStructure | list[RobustStructure] | None = None,
) -> Tensor:
    """``(V,)`` saliency of resolved ``settings`` (:func:`mesh_saliency` without the
    resolution: layers resolve their options once, at construction). The options of one
    variant are refused by the others with a :class:`ParameterError` (``backend``: the
    paper's variants only; ``structure``: ``"robust"`` only)."""
    if settings.variant == "robust":
        refuse_unused(settings.variant, {"backend": backend})
        rep = robust_representation(
            vertices,
            faces,
            settings.params,
            batch,
            max_memory,
            progress,
            dn_only=True,
            structure=structure,
        )
        return robust_saliency(rep)
    refuse_unused(settings.variant, {"structure": structure})
    points, faces = to_mesh_tensors(vertices, faces)  # validated by the representation
    # Saliency is scale invariant: compute at a safe size (an exact power-of-two scale).
    scale = extent_scale(points)
    points = points if scale == 1.0 else points * scale
    rep = multiscale_representation(
        points,
        faces,
        settings.params.num_scales,
        settings.params.threshold,
        max_memory=max_memory,
        progress=progress,
        backend=backend or "auto",
        batch=batch,
        positions=settings.variant in POSITION_VARIANTS,
    )
    min_count = DEFAULT_MIN_COUNT if settings.min_count is None else settings.min_count
    return saliency_from_representation(rep, points, faces, settings.variant, min_count)


def variant_saliency(vertices, faces, variant: str = "normal_coefficients", **kwargs) -> Tensor:
    """Deprecated: :func:`mesh_saliency` with ``variant=`` (this name defaulted to
    ``"normal_coefficients"``, which it keeps until it is removed)."""
    warnings.warn(
        "variant_saliency is deprecated; call saliency(vertices, faces, variant=...) "
        f"(stochlap_torch.saliency), whose default variant is {DEFAULT_VARIANT!r}",
        DeprecationWarning,
        stacklevel=2,
    )
    return mesh_saliency(vertices, faces, variant=variant, **kwargs)
