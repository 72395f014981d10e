"""``nn.Module`` wrappers for training scripts: the layers hold the parameters, not state.

The modules have no learnable weights; they exist so that the method composes with
``nn.Sequential``, ``state_dict``-free configs, ``.to(device)`` and hooks like any other layer.
Inputs keep their dtype and device.
"""

from __future__ import annotations

from torch import Tensor, nn

from ._common.checks import check_choice, refuse_unused
from ._common.errors import ParameterError
from .diffusion import (
    MultiscaleRepresentation,
    PaperParams,
    RobustParams,
    RobustRepresentation,
    as_paper_params,
    as_robust_params,
    differentiable_multiscale,
    multiscale_representation,
    resolve_budget,
    robust_representation,
)
from .diffusion.robust import RobustStructure
from .features import (
    DEFAULT_FEATURE_VARIANT,
    FeatureSettings,
    feature_settings,
    features_with_settings,
)
from .interest import DEFAULT_T_GLOBAL, check_interest_parameters, interest_points
from .saliency_maps import (
    DEFAULT_VARIANT,
    SaliencySettings,
    saliency_settings,
    saliency_with_settings,
)

__all__ = ["InterestPointHead", "MultiscaleFeatures", "MultiscaleSaliency", "StochasticLaplacian"]


def _checked_max_memory(max_memory):
    """``max_memory`` checked at construction (a bad budget is refused here, not at the
    first ``forward`` inside a training loop); ``None`` stays "the library's budget at call
    time"."""
    return None if max_memory is None else resolve_budget(max_memory)


def _laplacian_params(
    variant, num_scales, threshold, return_operators, differentiable_operator, robust, paper
) -> RobustParams | PaperParams:
    """The settings of :class:`StochasticLaplacian`'s ``variant``; options it does not use
    are refused."""
    check_choice("variant", variant, ("paper", "robust"))
    for name, value in (
        ("return_operators", return_operators),
        ("differentiable_operator", differentiable_operator),
    ):
        if value is not None and not isinstance(value, bool):
            raise ParameterError(f"{name} must be True or False, got {value!r}")
    if variant == "robust":
        refuse_unused(
            variant,
            {
                "threshold": threshold,
                "return_operators": return_operators,
                "differentiable_operator": differentiable_operator,
                "paper": paper,
            },
        )
        return as_robust_params(robust, num_scales)
    refuse_unused(variant, {"robust": robust})
    return as_paper_params(paper, num_scales, threshold)


class StochasticLaplacian(nn.Module):
    """Multiscale representation of a mesh: Algorithm 1 (default) or the robust variant.

    Options left ``None`` take the variant's defaults; an option the variant does not use
    raises :class:`~stochlap_torch.ParameterError` at construction.

    Args:
        num_scales: ``K >= 2`` scales; scale 1 is the input (default: 8; ``"robust"``:
            ``RobustParams().num_scales``).
        threshold: ``lambda`` in ``(0, 1)``, the paper's precision (default ``1e-3``;
            ``"paper"`` only).
        return_operators: also return ``F^(1..K)`` as ``torch.sparse_csr`` tensors (off by
            default: they cost memory; ``"paper"`` only).
        max_memory: byte budget (default: the library's).
        differentiable_operator: gradients also flow through the edge weights and ``alpha``
            into every ``F^(k)`` (threshold pattern fixed at the forward pass, ``O(K nnz)``
            memory; :func:`~stochlap_torch.diffusion.differentiable_multiscale`). Off by
            default: the operators are then held constant (``"paper"`` only).
        variant: ``"paper"`` (default: the paper's method, exactly) or ``"robust"``
            (:mod:`stochlap_torch.diffusion.robust`).
        robust: the robust variant's settings (:class:`~stochlap_torch.diffusion.RobustParams`).
        paper: the paper variant's settings (:class:`~stochlap_torch.diffusion.PaperParams`).

    Shapes:
        vertices ``(V, 3)`` float, faces ``(F, 3)`` int64, optional batch ``(V,)`` int64 (a
        packed :class:`~stochlap_torch.mesh.MeshBatch`) ->
        :class:`~stochlap_torch.diffusion.MultiscaleRepresentation` (``"robust"``:
        :class:`~stochlap_torch.diffusion.RobustRepresentation`).
    """

    def __init__(
        self,
        num_scales: int | None = None,
        threshold: float | None = None,
        return_operators: bool | None = None,
        max_memory: int | None = None,
        differentiable_operator: bool | None = None,
        variant: str = "paper",
        robust: RobustParams | None = None,
        paper: PaperParams | None = None,
    ):
        super().__init__()
        self.params = _laplacian_params(
            variant,
            num_scales,
            threshold,
            return_operators,
            differentiable_operator,
            robust,
            paper,
        )
        self.variant = variant
        self.return_operators = bool(return_operators)
        self.differentiable_operator = bool(differentiable_operator)
        self.max_memory = _checked_max_memory(max_memory)

    @property
    def num_scales(self) -> int:
        return self.params.num_scales

    def forward(
        self, vertices: Tensor, faces: Tensor, batch: Tensor | None = None
    ) -> MultiscaleRepresentation | RobustRepresentation:
        if self.variant == "robust":
            return robust_representation(vertices, faces, self.params, batch, self.max_memory)
        run = (
            differentiable_multiscale if self.differentiable_operator else multiscale_representation
        )
        return run(
            vertices,
            faces,
            self.params.num_scales,
            self.params.threshold,
            batch=batch,
            return_operators=self.return_operators,
            max_memory=self.max_memory,
        )

    def extra_repr(self) -> str:
        text = f"variant={self.variant!r}, params={self.params!r}"
        if self.variant == "paper":
            text += (
                f", return_operators={self.return_operators}, "
                f"differentiable_operator={self.differentiable_operator}"
            )
        return text


class _ResolvedLayer(nn.Module):
    """A layer whose options are resolved once, at construction, into ``self.settings``."""

    settings: SaliencySettings | FeatureSettings

    @property
    def variant(self) -> str:
        return self.settings.variant

    @property
    def num_scales(self) -> int:
        return self.settings.params.num_scales


class MultiscaleSaliency(_ResolvedLayer):
    """Per-vertex saliency: vertices ``(V, 3)``, faces ``(F, 3)`` -> ``(V,)``.

    The options are those of :func:`~stochlap_torch.saliency_maps.mesh_saliency`, resolved
    and checked at construction (an option the variant does not use raises
    :class:`~stochlap_torch.ParameterError`).

    Args:
        num_scales: scales (default: the variant's: ``RobustParams().num_scales`` for
            ``"robust"``, 8 for the others).
        threshold: ``lambda`` in ``(0, 1)`` (the paper's variants; default ``1e-3``).
        max_memory: byte budget for the operators.
        variant: one of :data:`~stochlap_torch.saliency_maps.VARIANTS`; ``"robust"`` by
            default (:data:`~stochlap_torch.saliency_maps.DEFAULT_VARIANT`).
        robust: the robust variant's settings.
        paper: the paper variant's settings.
        min_count: ``"valence_normalised"``'s smallest valence population.
    """

    def __init__(
        self,
        num_scales: int | None = None,
        threshold: float | None = None,
        max_memory: int | None = None,
        variant: str = DEFAULT_VARIANT,
        robust: RobustParams | None = None,
        paper: PaperParams | None = None,
        min_count: int | None = None,
    ):
        super().__init__()
        self.settings = saliency_settings(
            variant, num_scales, threshold, min_count, robust=robust, paper=paper
        )
        self.max_memory = _checked_max_memory(max_memory)

    def forward(
        self,
        vertices: Tensor,
        faces: Tensor,
        batch: Tensor | None = None,
        structure: RobustStructure | list[RobustStructure] | None = None,
    ) -> Tensor:
        """``structure``: ``"robust"`` only, the mesh's
        :class:`~stochlap_torch.diffusion.robust.RobustStructure` built with this layer's
        settings (:func:`~stochlap_torch.robust_structure`), reused instead of built."""
        return saliency_with_settings(
            vertices,
            faces,
            self.settings,
            max_memory=self.max_memory,
            batch=batch,
            structure=structure,
        )

    def extra_repr(self) -> str:
        return repr(self.settings)


class MultiscaleFeatures(_ResolvedLayer):
    """Per-vertex multiscale features: ``(V, 3)``, ``(F, 3)`` -> ``(V, C)``.

    The options are those of :func:`~stochlap_torch.features.multiscale_features`, resolved
    and checked at construction (:func:`~stochlap_torch.features.feature_settings`; an option
    the variant does not use raises :class:`~stochlap_torch.ParameterError`).

    Args:
        num_scales: scales (default: the variant's: ``RobustParams().num_scales`` for
            ``"robust"``, 6 for ``"paper"``).
        threshold: ``lambda`` in ``(0, 1)`` (``"paper"``; default ``1e-3``).
        include: groups of :data:`~stochlap_torch.features.FEATURE_GROUPS` (``"paper"``;
            default: all).
        rotation_invariant: coefficients as (normal component, tangential norm) instead of
            xyz (``"paper"``, default ``True``; the robust channels are always invariant).
        normalisation: per-mesh length the coefficients are divided by (``"paper"``, default
            ``"mean_edge"``).
        differentiable_operator: gradients also through the operators (``"paper"``).
        max_memory: byte budget for the operators.
        variant: ``"robust"`` (default,
            :data:`~stochlap_torch.features.DEFAULT_FEATURE_VARIANT`) or ``"paper"``.
        robust: the robust variant's settings.
        paper: the paper variant's settings.

    Shapes:
        vertices ``(V, 3)`` float, faces ``(F, 3)`` int64, optional batch ``(V,)`` int64 ->
        ``(V, C)`` with ``C = self.num_channels``; :meth:`channel_names` names the channels.
    """

    def __init__(
        self,
        num_scales: int | None = None,
        threshold: float | None = None,
        include: tuple[str, ...] | None = None,
        rotation_invariant: bool | None = None,
        normalisation: str | None = None,
        differentiable_operator: bool | None = None,
        max_memory: int | None = None,
        variant: str = DEFAULT_FEATURE_VARIANT,
        robust: RobustParams | None = None,
        paper: PaperParams | None = None,
    ):
        super().__init__()
        self.settings = feature_settings(
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
        self.differentiable_operator = differentiable_operator  # None: not given
        self.max_memory = _checked_max_memory(max_memory)

    def channel_names(self) -> list[str]:
        """The ``C`` channel names, in the order of the feature columns."""
        return self.settings.channel_names()

    @property
    def num_channels(self) -> int:
        return len(self.channel_names())

    def forward(
        self,
        vertices: Tensor,
        faces: Tensor,
        batch: Tensor | None = None,
        structure: RobustStructure | list[RobustStructure] | None = None,
    ) -> Tensor:
        """``structure``: ``"robust"`` only, the mesh's
        :class:`~stochlap_torch.diffusion.robust.RobustStructure` built with this layer's
        settings (:func:`~stochlap_torch.robust_structure`), reused instead of built."""
        return features_with_settings(
            vertices,
            faces,
            self.settings,
            batch,
            self.max_memory,
            self.differentiable_operator,
            structure,
        )

    def extra_repr(self) -> str:
        text = repr(self.settings)
        if self.differentiable_operator:
            text += ", differentiable_operator=True"
        return text


class InterestPointHead(nn.Module):
    """Interest points from saliency (Sec. 4.5): ``(V,)`` saliency -> ``(N,)`` int64 indices.

    Args:
        mode: ``"nms"`` (default: a few tens of well separated points) or ``"paper"`` (every
            1-ring maximum above the global threshold).
        radius: ``"nms"`` suppression radius as a fraction of the bounding-box diagonal
            (default :data:`~stochlap_torch.interest.DEFAULT_RADIUS`; ``"paper"`` refuses it).
        top_k: at most this many points (``None``: no cap).
        t_global: fraction of the saliency range a point must reach (0.4, as in the paper).
    """

    def __init__(
        self,
        mode: str = "nms",
        radius: float | None = None,
        top_k: int | None = None,
        t_global: float = DEFAULT_T_GLOBAL,
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
