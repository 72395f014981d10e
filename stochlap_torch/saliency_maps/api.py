"""``mesh_saliency``: the one entry point from a mesh to a saliency, any variant."""

from __future__ import annotations

from torch import Tensor

from .._common.checks import check_choice, check_int, refuse_unused
from .._common.variants import DEFAULT_VARIANT, VARIANTS
from ..diffusion import BACKENDS, ProgressCallback, multiscale_representation
from ..mesh import extent_scale, to_mesh_tensors
from ..params import PaperParams, RobustParams, method_of, resolve_params
from ..robust import RobustStructure, robust_representation, robust_saliency
from .variants import (
    DEFAULT_MIN_COUNT,
    POSITION_VARIANTS,
    saliency_from_representation,
)


def saliency_params(variant: str | None = None, **options) -> RobustParams | PaperParams:
    """The options of the saliency of ``variant`` as its parameters object:
    :class:`~stochlap_torch.params.RobustParams` for ``"robust"``, else
    :class:`~stochlap_torch.params.PaperParams` (see
    :func:`~stochlap_torch.params.resolve_params`). Without ``variant``: the method of a
    ``params=`` object, else :data:`DEFAULT_VARIANT` (``"robust"``).

    Raises:
        ParameterError: a bad value, or an option the variant does not use.
    """
    variant = _variant(variant, options.get("params"))
    return resolve_params(RobustParams if variant == "robust" else PaperParams, variant, options)


def check_min_count(variant: str, min_count) -> int:
    """``min_count`` of ``variant``: ``"valence_normalised"``'s (default 30, at least 1);
    refused by the other variants."""
    if variant != "valence_normalised":
        refuse_unused(variant, {"min_count": min_count})
    return check_int("min_count", DEFAULT_MIN_COUNT if min_count is None else min_count, 1)


def _variant(variant: str | None, params) -> str:
    if variant is None:
        return method_of(params, DEFAULT_VARIANT)
    return check_choice("variant", variant, VARIANTS)


def mesh_saliency(
    vertices,
    faces,
    batch: Tensor | None = None,
    *,
    variant: str | None = None,
    structure: RobustStructure | list[RobustStructure] | None = None,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    backend: str | None = None,
    min_count: int | None = None,
    **options,
) -> Tensor:
    """Saliency of every vertex: the robust variant's, Algorithm 2, or a variant of
    :mod:`.variants`.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        batch: optional ``(V,)`` mesh index of every vertex of a packed batch (``None``: one
            mesh); results equal separate runs.
        variant: one of :data:`~.variants.VARIANTS` (default :data:`DEFAULT_VARIANT`,
            ``"robust"``; or the method of a ``params=`` object).
        structure: ``"robust"`` only: the mesh's :class:`~stochlap_torch.RobustStructure`
            (:func:`~stochlap_torch.robust_structure` with the same options; for a batch, a
            list of one per mesh), reused (``None``: built on every call).
        max_memory: byte budget for the operators (default: ``$STOCHLAP_MAX_MEMORY``, else half the
            physical memory).
        progress: called as ``progress(k, K)`` as the run advances (``None``: no reports).
        backend: the paper's variants only: ``"auto"`` (default), ``"torch"``, ``"numba"`` or
            ``"cuda"`` (experimental).
        min_count: ``"valence_normalised"`` only (default 30); see
            :func:`~.variants.valence_normalised_differences`.
        **options: the variant's options: fields of
            :class:`~stochlap_torch.params.RobustParams` (``num_scales=7``, ``t0=1e-3``, ...)
            or of :class:`~stochlap_torch.params.PaperParams` (``num_scales=8``,
            ``threshold=1e-3``); or the whole object as ``params=`` (also ``robust=`` /
            ``paper=``).

    Returns:
        ``(V,)`` saliency in the dtype and on the device of ``vertices``; never NaN or Inf.

    Raises:
        ParameterError: unknown variant, bad options, an option the variant does not use.
        MeshError: bad mesh. MemoryBudgetError: the operators would not fit the budget.
    """
    variant = _variant(variant, options.get("params"))
    params = saliency_params(variant, **options)
    if variant == "robust":
        refuse_unused(variant, {"backend": backend, "min_count": min_count})
        rep = robust_representation(
            vertices, faces, params, batch, max_memory, progress, dn_only=True, structure=structure
        )
        return robust_saliency(rep)
    refuse_unused(variant, {"structure": structure})
    min_count = check_min_count(variant, min_count)
    backend = check_choice("backend", "auto" if backend is None else backend, BACKENDS)
    points, faces = to_mesh_tensors(vertices, faces)  # validated by the representation
    # Saliency is scale invariant: compute at a safe size (an exact power-of-two scale).
    scale = extent_scale(points)
    points = points if scale == 1.0 else points * scale
    rep = multiscale_representation(
        points,
        faces,
        params.num_scales,
        params.threshold,
        max_memory=max_memory,
        progress=progress,
        backend=backend,
        batch=batch,
        positions=variant in POSITION_VARIANTS,
    )
    return saliency_from_representation(rep, points, faces, variant, min_count)
