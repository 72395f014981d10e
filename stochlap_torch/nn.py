"""``nn.Module`` wrappers for training scripts: the layers hold the parameters, not state.

The modules have no learnable weights; they exist so that the method composes with
``nn.Sequential``, ``state_dict``-free configs, ``.to(device)`` and hooks like any other layer.
Inputs keep their dtype and device.
"""

from __future__ import annotations

import dataclasses

from torch import Tensor, nn

from ._common.checks import check_choice
from .diffusion import (
    MultiscaleRepresentation,
    RobustParams,
    RobustRepresentation,
    check_parameters,
    differentiable_multiscale,
    multiscale_representation,
    robust_representation,
)
from .features import (
    DEFAULT_FEATURE_VARIANT,
    FEATURE_GROUPS,
    FEATURE_VARIANTS,
    PAPER_SCALES,
    check_feature_parameters,
    feature_channel_names,
    multiscale_features,
)
from .interest import check_interest_parameters, interest_points
from .saliency_maps import DEFAULT_VARIANT, VARIANTS, mesh_saliency

__all__ = ["InterestPointHead", "MultiscaleFeatures", "MultiscaleSaliency", "StochasticLaplacian"]


def _checked(variant: str, variants, num_scales, threshold, robust):
    """``(num_scales, threshold, robust)`` checked for ``variant`` (``num_scales`` ``None``
    keeps the variant's default; the robust settings carry it)."""
    check_choice("variant", variant, variants)
    if variant == "robust":
        params = RobustParams() if robust is None else robust
        if num_scales is not None:
            params = dataclasses.replace(params, num_scales=num_scales)
        return params.num_scales, threshold, params
    if num_scales is None:
        return None, check_parameters(2, threshold)[1], None
    num_scales, threshold = check_parameters(num_scales, threshold)
    return num_scales, threshold, None


class StochasticLaplacian(nn.Module):
    """Multiscale representation of a mesh: Algorithm 1 (default) or the robust variant.

    Args:
        num_scales: ``K >= 2`` scales; scale 1 is the input (``"robust"``: 7 by default).
        threshold: ``lambda`` in ``(0, 1)``, the paper's precision (``1e-3``).
        return_operators: also return ``F^(1..K)`` as ``torch.sparse_csr`` tensors (off by
            default: they cost memory).
        max_memory: byte budget for the operators (default: half the physical memory).
        differentiable_operator: gradients also flow through the edge weights and ``alpha``
            into every ``F^(k)`` (threshold pattern fixed at the forward pass, ``O(K nnz)``
            memory; :func:`~stochlap_torch.diffusion.differentiable_multiscale`). Off by
            default: the operators are then held constant.
        variant: ``"paper"`` (default: the paper's method, exactly) or ``"robust"``
            (:mod:`stochlap_torch.diffusion.robust`; the operator options above do not
            apply).
        robust: the robust variant's settings.

    Shapes:
        vertices ``(V, 3)`` float, faces ``(F, 3)`` int64, optional batch ``(V,)`` int64 (a
        packed :class:`~stochlap_torch.mesh.MeshBatch`) ->
        :class:`~stochlap_torch.diffusion.MultiscaleRepresentation` (``"robust"``:
        :class:`~stochlap_torch.diffusion.RobustRepresentation`).
    """

    def __init__(
        self,
        num_scales: int | None = 8,
        threshold: float = 1e-3,
        return_operators: bool = False,
        max_memory: int | None = None,
        differentiable_operator: bool = False,
        variant: str = "paper",
        robust: RobustParams | None = None,
    ):
        super().__init__()
        if variant == "paper" and num_scales is None:
            num_scales = 8
        self.num_scales, self.threshold, self.robust = _checked(
            variant, ("paper", "robust"), num_scales, threshold, robust
        )
        self.variant = variant
        self.return_operators = return_operators
        self.max_memory = max_memory
        self.differentiable_operator = differentiable_operator

    def forward(
        self, vertices: Tensor, faces: Tensor, batch: Tensor | None = None
    ) -> MultiscaleRepresentation | RobustRepresentation:
        if self.variant == "robust":
            return robust_representation(vertices, faces, self.robust, batch)
        if self.differentiable_operator:
            return differentiable_multiscale(
                vertices, faces, self.num_scales, self.threshold, batch=batch,
                return_operators=self.return_operators, max_memory=self.max_memory,
            )  # fmt: skip
        return multiscale_representation(
            vertices,
            faces,
            self.num_scales,
            self.threshold,
            return_operators=self.return_operators,
            max_memory=self.max_memory,
            batch=batch,
        )

    def extra_repr(self) -> str:
        return (
            f"variant={self.variant!r}, num_scales={self.num_scales}, "
            f"threshold={self.threshold:g}, return_operators={self.return_operators}, "
            f"differentiable_operator={self.differentiable_operator}"
        )


class MultiscaleSaliency(nn.Module):
    """Per-vertex saliency: vertices ``(V, 3)``, faces ``(F, 3)`` -> ``(V,)``.

    Args:
        num_scales: scales (default: the variant's: 7 for ``"robust"``, 8 for the others).
        threshold: ``lambda`` in ``(0, 1)`` (the paper's variants; ``1e-3`` in the paper).
        max_memory: byte budget for the operators.
        variant: one of :data:`~stochlap_torch.saliency_maps.VARIANTS`; ``"robust"`` by
            default (:data:`~stochlap_torch.saliency_maps.DEFAULT_VARIANT`).
        robust: the robust variant's settings.
    """

    def __init__(
        self,
        num_scales: int | None = None,
        threshold: float = 1e-3,
        max_memory: int | None = None,
        variant: str = DEFAULT_VARIANT,
        robust: RobustParams | None = None,
    ):
        super().__init__()
        self.num_scales, self.threshold, self.robust = _checked(
            variant, VARIANTS, num_scales, threshold, robust
        )
        self.max_memory = max_memory
        self.variant = variant

    def forward(self, vertices: Tensor, faces: Tensor, batch: Tensor | None = None) -> Tensor:
        return mesh_saliency(
            vertices, faces, self.num_scales, self.threshold, max_memory=self.max_memory,
            batch=batch, variant=self.variant, robust=self.robust,
        )  # fmt: skip

    def extra_repr(self) -> str:
        return (
            f"variant={self.variant!r}, num_scales={self.num_scales}, threshold={self.threshold:g}"
        )


class MultiscaleFeatures(nn.Module):
    """Per-vertex multiscale features: ``(V, 3)``, ``(F, 3)`` -> ``(V, C)``.

    Args:
        num_scales: scales (default: the variant's: 7 for ``"robust"``, 6 for ``"paper"``).
        threshold: ``lambda`` in ``(0, 1)`` (``"paper"``).
        include: groups of :data:`~stochlap_torch.features.FEATURE_GROUPS` (``"paper"``).
        rotation_invariant: coefficients as (normal component, tangential norm) instead of
            xyz (``"paper"``; the robust channels are always invariant).
        normalisation: per-mesh length the coefficients are divided by (``"paper"``).
        differentiable_operator: gradients also through the operators (``"paper"``).
        max_memory: byte budget for the operators (``"paper"``).
        variant: ``"robust"`` (default, :data:`~stochlap_torch.features.
            DEFAULT_FEATURE_VARIANT`) or ``"paper"``.
        robust: the robust variant's settings.

    Shapes:
        vertices ``(V, 3)`` float, faces ``(F, 3)`` int64, optional batch ``(V,)`` int64 ->
        ``(V, C)`` with ``C = self.num_channels``; :meth:`channel_names` names the channels.
    """

    def __init__(
        self,
        num_scales: int | None = None,
        threshold: float = 1e-3,
        include: tuple[str, ...] = FEATURE_GROUPS,
        rotation_invariant: bool = True,
        normalisation: str = "mean_edge",
        differentiable_operator: bool = False,
        max_memory: int | None = None,
        variant: str = DEFAULT_FEATURE_VARIANT,
        robust: RobustParams | None = None,
    ):
        super().__init__()
        self.num_scales, self.threshold, self.robust = _checked(
            variant, FEATURE_VARIANTS, num_scales, threshold, robust
        )
        if variant == "paper":
            scales = PAPER_SCALES if num_scales is None else num_scales
            self.num_scales, self.threshold, self.include = check_feature_parameters(
                scales, threshold, include, normalisation
            )
        else:
            self.include = tuple(include)
        self.variant = variant
        self.rotation_invariant = rotation_invariant
        self.normalisation = normalisation
        self.differentiable_operator = differentiable_operator
        self.max_memory = max_memory

    def channel_names(self) -> list[str]:
        """The ``C`` channel names, in the order of the feature columns."""
        return feature_channel_names(
            self.num_scales, self.include, self.rotation_invariant, self.variant, self.robust
        )

    @property
    def num_channels(self) -> int:
        return len(self.channel_names())

    def forward(self, vertices: Tensor, faces: Tensor, batch: Tensor | None = None) -> Tensor:
        return multiscale_features(
            vertices,
            faces,
            self.num_scales,
            self.threshold,
            batch=batch,
            include=self.include,
            rotation_invariant=self.rotation_invariant,
            normalisation=self.normalisation,
            differentiable_operator=self.differentiable_operator,
            max_memory=self.max_memory,
            variant=self.variant,
            robust=self.robust,
        )

    def extra_repr(self) -> str:
        return (
            f"variant={self.variant!r}, num_scales={self.num_scales}, "
            f"threshold={self.threshold:g}, include={self.include}, "
            f"rotation_invariant={self.rotation_invariant}, "
            f"normalisation={self.normalisation!r}, "
            f"differentiable_operator={self.differentiable_operator}"
        )


class InterestPointHead(nn.Module):
    """Interest points from saliency (Sec. 4.5): ``(V,)`` saliency -> ``(N,)`` int64 indices.

    Args:
        mode: ``"nms"`` (default: a few tens of well separated points) or ``"paper"`` (every
            1-ring maximum above the global threshold).
        radius: ``"nms"`` suppression radius as a fraction of the bounding-box diagonal (0.1).
        top_k: at most this many points (``None``: no cap).
        t_global: fraction of the saliency range a point must reach (0.4, as in the paper).
    """

    def __init__(
        self,
        mode: str = "nms",
        radius: float = 0.1,
        top_k: int | None = None,
        t_global: float = 0.4,
    ):
        super().__init__()
        mode, radius, top_k, t_global = check_interest_parameters(mode, radius, top_k, t_global)
        self.mode = mode
        self.radius = radius
        self.top_k = top_k
        self.t_global = t_global

    def forward(
        self, saliency: Tensor, vertices: Tensor, faces: Tensor, batch: Tensor | None = None
    ) -> Tensor:
        return interest_points(
            saliency,
            vertices,
            faces,
            mode=self.mode,
            radius=self.radius,
            top_k=self.top_k,
            t_global=self.t_global,
            batch=batch,
        )

    def extra_repr(self) -> str:
        return (
            f"mode={self.mode!r}, radius={self.radius}, top_k={self.top_k}, "
            f"t_global={self.t_global}"
        )
