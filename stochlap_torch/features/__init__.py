"""Per-vertex multiscale features for learning pipelines: ``(V, 3)``, ``(F, 3)`` -> ``(V, C)``.

:func:`multiscale_features` is the one entry point; ``variant=`` picks the representation:
``"robust"`` (default: channels that survive remeshing, :mod:`.robust`) or ``"paper"`` (the
coefficients and difference maps of the paper's Algorithm 1, :mod:`.paper`).
"""

from __future__ import annotations

from torch import Tensor

from .._common.checks import refuse_unused
from .._common.variants import DEFAULT_FEATURE_VARIANT, FEATURE_VARIANTS, PAPER_FEATURE_SCALES
from ..diffusion.parameters import PaperParams
from ..diffusion.robust import RobustParams, RobustStructure
from ..diffusion.robust_api import robust_representation
from .paper import (
    FEATURE_GROUPS,
    NORMALISATIONS,
    check_feature_parameters,
    features_from_representation,
    mesh_lengths,
    paper_features,
)
from .robust import robust_channel_names, robust_features_from_representation
from .settings import FeatureSettings, feature_settings

__all__ = [
    "DEFAULT_FEATURE_VARIANT",
    "FEATURE_GROUPS",
    "FEATURE_VARIANTS",
    "NORMALISATIONS",
    "PAPER_FEATURE_SCALES",
    "FeatureSettings",
    "check_feature_parameters",
    "feature_channel_names",
    "feature_settings",
    "features_from_representation",
    "features_with_settings",
    "mesh_lengths",
    "multiscale_features",
    "robust_channel_names",
    "robust_features_from_representation",
]


def feature_channel_names(
    num_scales: int | None = None,
    include: tuple[str, ...] | None = None,
    rotation_invariant: bool | None = None,
    variant: str = DEFAULT_FEATURE_VARIANT,
    robust: RobustParams | None = None,
    paper: PaperParams | None = None,
) -> list[str]:
    """Names of the channels :func:`multiscale_features` returns with these arguments."""
    return feature_settings(
        variant,
        num_scales,
        include=include,
        rotation_invariant=rotation_invariant,
        robust=robust,
        paper=paper,
    ).channel_names()


def multiscale_features(
    vertices,
    faces,
    num_scales: int | None = None,
    threshold: float | None = None,
    batch: Tensor | None = None,
    include: tuple[str, ...] | None = None,
    rotation_invariant: bool | None = None,
    normalisation: str | None = None,
    differentiable_operator: bool | None = None,
    max_memory: int | None = None,
    variant: str = DEFAULT_FEATURE_VARIANT,
    robust: RobustParams | None = None,
    paper: PaperParams | None = None,
    structure: RobustStructure | list[RobustStructure] | None = None,
) -> Tensor:
    """``(V, C)`` per-vertex multiscale features of a mesh or packed batch.

    Options left ``None`` take the variant's defaults; an option the variant does not use is
    refused (:func:`~.settings.feature_settings`).

    Args:
        vertices: ``(V, 3)`` float tensor; the features come in its dtype and device.
        faces: ``(F, 3)`` integer tensor.
        num_scales: scales (default: ``RobustParams().num_scales`` for ``"robust"``,
            :data:`~stochlap_torch._common.variants.PAPER_FEATURE_SCALES` for ``"paper"``).
        threshold: ``lambda`` in ``(0, 1)`` (``"paper"`` only; default ``1e-3``).
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch.
        include, rotation_invariant, normalisation, differentiable_operator: the paper
            variant's options (``features.paper.paper_features``; defaults: every group,
            ``True``, ``"mean_edge"``, ``False``).
        max_memory: byte budget (default: the library's).
        variant: ``"robust"`` (default) or ``"paper"``.
        robust: the robust variant's settings (:class:`~stochlap_torch.diffusion.RobustParams`
            or a mapping of its fields).
        paper: the paper variant's settings (:class:`~stochlap_torch.diffusion.PaperParams`).
        structure: ``"robust"`` only: the mesh's
            :class:`~stochlap_torch.diffusion.robust.RobustStructure`
            (:func:`~stochlap_torch.robust_structure`, built with the same ``robust``
            settings; for a batch, a list of one per mesh), reused instead of built.

    Returns:
        ``(V, C)`` float, ``C = len(feature_channel_names(...))`` for the same arguments.
        Gradients reach the vertices with the operators held constant (``"paper"`` with
        ``differentiable_operator=True``: through the operators too).

    Raises:
        ParameterError: a bad option, or one the variant does not use.
    """
    settings = feature_settings(
        variant,
        num_scales,
        threshold,
        include,
        rotation_invariant,
        normalisation,
        differentiable_operator,
        robust,
        paper,
    )
    return features_with_settings(
        vertices, faces, settings, batch, max_memory, differentiable_operator, structure
    )


def features_with_settings(
    vertices,
    faces,
    settings: FeatureSettings,
    batch: Tensor | None = None,
    max_memory: int | None = None,
    differentiable_operator: bool | None = None,
    structure: RobustStructure | list[RobustStructure] | None = None,
) -> Tensor:
    """``(V, C)`` features of resolved ``settings`` (:func:`multiscale_features` without the
    resolution: the layers, datasets and caches resolve their options once). The options of
    one variant are refused by the other with a :class:`ParameterError`
    (``differentiable_operator``: ``"paper"`` only; ``structure``: ``"robust"`` only)."""
    if settings.variant == "robust":
        refuse_unused(settings.variant, {"differentiable_operator": differentiable_operator})
        rep = robust_representation(
            vertices, faces, settings.params, batch, max_memory, structure=structure
        )
        return robust_features_from_representation(rep)
    refuse_unused(settings.variant, {"structure": structure})
    return paper_features(
        vertices,
        faces,
        settings.params.num_scales,
        settings.params.threshold,
        batch=batch,
        include=settings.include,
        rotation_invariant=settings.rotation_invariant,
        normalisation=settings.normalisation,
        differentiable_operator=bool(differentiable_operator),
        max_memory=max_memory,
    )
