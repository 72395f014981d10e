"""Per-vertex multiscale features for learning pipelines: ``(V, 3)``, ``(F, 3)`` -> ``(V, C)``.

:func:`multiscale_features` is the one entry point; ``variant=`` picks the representation:
``"robust"`` (default: channels that survive remeshing, :mod:`.robust`) or ``"paper"`` (the
coefficients and difference maps of the paper's Algorithm 1, :mod:`.paper`).
"""

from __future__ import annotations

import dataclasses

from torch import Tensor

from .._common.checks import check_choice
from .._common.threads import serial_glue
from .._common.variants import DEFAULT_FEATURE_VARIANT, FEATURE_VARIANTS
from ..diffusion.robust import RobustParams
from ..diffusion.robust_api import robust_representation
from .paper import (
    FEATURE_GROUPS,
    NORMALISATIONS,
    check_feature_parameters,
    features_from_representation,
    mesh_lengths,
    paper_channel_names,
    paper_features,
)
from .robust import robust_channel_names, robust_features_from_representation

__all__ = [
    "DEFAULT_FEATURE_VARIANT",
    "FEATURE_GROUPS",
    "FEATURE_VARIANTS",
    "NORMALISATIONS",
    "PAPER_SCALES",
    "check_feature_parameters",
    "feature_channel_names",
    "features_from_representation",
    "mesh_lengths",
    "multiscale_features",
    "robust_channel_names",
    "robust_features_from_representation",
]

#: Scales of the paper's features when none are given.
PAPER_SCALES = 6


def _robust_params(num_scales: int | None, robust: RobustParams | None) -> RobustParams:
    params = RobustParams() if robust is None else robust
    return params if num_scales is None else dataclasses.replace(params, num_scales=num_scales)


def feature_channel_names(
    num_scales: int | None = None,
    include: tuple[str, ...] = FEATURE_GROUPS,
    rotation_invariant: bool = True,
    variant: str = DEFAULT_FEATURE_VARIANT,
    robust: RobustParams | None = None,
) -> list[str]:
    """Names of the channels :func:`multiscale_features` returns with these arguments."""
    check_choice("variant", variant, FEATURE_VARIANTS)
    if variant == "robust":
        return robust_channel_names(_robust_params(num_scales, robust))
    scales = PAPER_SCALES if num_scales is None else num_scales
    return paper_channel_names(scales, tuple(include), rotation_invariant)


@serial_glue()
def multiscale_features(
    vertices,
    faces,
    num_scales: int | None = None,
    threshold: float = 1e-3,
    batch: Tensor | None = None,
    include: tuple[str, ...] = FEATURE_GROUPS,
    rotation_invariant: bool = True,
    normalisation: str = "mean_edge",
    differentiable_operator: bool = False,
    max_memory: int | None = None,
    variant: str = DEFAULT_FEATURE_VARIANT,
    robust: RobustParams | None = None,
) -> Tensor:
    """``(V, C)`` per-vertex multiscale features of a mesh or packed batch.

    Args:
        vertices: ``(V, 3)`` float tensor; the features come in its dtype and device.
        faces: ``(F, 3)`` integer tensor.
        num_scales: scales (default: 7 for ``"robust"``, 6 for ``"paper"``).
        threshold: ``lambda`` in ``(0, 1)`` (``"paper"`` only).
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch.
        include, rotation_invariant, normalisation, differentiable_operator: the paper
            variant's options (:func:`~.paper.paper_features`).
        max_memory: byte budget (default: the library's).
        variant: ``"robust"`` (default) or ``"paper"``.
        robust: the robust variant's settings (:class:`~stochlap_torch.diffusion.RobustParams`).

    Returns:
        ``(V, C)`` float, ``C = len(feature_channel_names(...))`` for the same arguments.
        Gradients reach the vertices with the operators held constant (``"paper"`` with
        ``differentiable_operator=True``: through the operators too).
    """
    check_choice("variant", variant, FEATURE_VARIANTS)
    if variant == "robust":
        params = _robust_params(num_scales, robust)
        rep = robust_representation(vertices, faces, params, batch, max_memory)
        return robust_features_from_representation(rep)
    return paper_features(
        vertices,
        faces,
        PAPER_SCALES if num_scales is None else num_scales,
        threshold,
        batch=batch,
        include=include,
        rotation_invariant=rotation_invariant,
        normalisation=normalisation,
        differentiable_operator=differentiable_operator,
        max_memory=max_memory,
    )
