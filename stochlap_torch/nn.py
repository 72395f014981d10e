"""``nn.Module`` layers for training scripts: they hold their method's options, no learnable
weights, so that the method composes with ``nn.Sequential``, ``.to(device)`` and hooks like any
other layer. Inputs keep their dtype and device."""

from __future__ import annotations

import warnings

from torch import Tensor, nn

from ._common.checks import check_bool, check_choice, refuse_unused
from ._common.errors import ParameterError
from .diffusion import (
    MultiscaleRepresentation,
    differentiable_multiscale,
    multiscale_representation,
)
from .diffusion.memory import resolve_budget
from .features import channel_names, feature_params, multiscale_features
from .interest import DEFAULT_T_GLOBAL, check_interest_parameters, interest_points
from .params import PaperParams, RobustParams, method_of, resolve_params
from .robust import RobustRepresentation, RobustStructure, robust_representation
from .saliency_maps import mesh_saliency, saliency_params
from .saliency_maps.api import check_min_count

__all__ = [
    "InterestPointHead",
    "MultiscaleFeatures",
    "MultiscaleSaliency",
    "RobustMultiscale",
    "StochasticLaplacian",
]


def _checked_max_memory(max_memory):
    """``max_memory`` checked at construction, not at the first ``forward`` of a training
    loop; ``None`` stays "the library's budget at call time"."""
    return None if max_memory is None else resolve_budget(max_memory)


class _Layer(nn.Module):
    """A layer whose method options are resolved once, at construction (``self.params``)."""

    params: RobustParams | PaperParams
    variant: str

    @property
    def num_scales(self) -> int:
        return self.params.num_scales

    def extra_repr(self) -> str:
        return f"variant={self.variant!r}, params={self.params!r}"


class _MeshLayer(_Layer):
    """A layer of a mesh or packed batch that may reuse the mesh's robust structure."""

    def __init__(self, params: RobustParams | PaperParams, max_memory: int | None):
        super().__init__()
        self.params = params
        self.max_memory = _checked_max_memory(max_memory)

    def forward(
        self,
        vertices: Tensor,
        faces: Tensor,
        batch: Tensor | None = None,
        structure: RobustStructure | list[RobustStructure] | None = None,
    ):
        """``structure``: the robust variant's :class:`~stochlap_torch.RobustStructure` of the
        mesh (a list of one per mesh of a batch), reused instead of built."""
        run = {"params": self.params, "structure": structure, "max_memory": self.max_memory}
        return self._run(vertices, faces, batch, run)


class StochasticLaplacian(_Layer):
    """The paper's multiscale representation (Algorithm 1) of a mesh or packed batch.

    Args:
        num_scales, threshold: ``K`` and ``lambda`` (fields of
            :class:`~stochlap_torch.params.PaperParams`: default 8 and ``1e-3``).
        return_operators: also return ``F^(1..K)`` as ``torch.sparse_csr`` tensors (default
            ``False``: they cost memory).
        max_memory: byte budget (default: ``$STOCHLAP_MAX_MEMORY``, else half the physical memory).
        differentiable_operator: gradients also flow through the edge weights and ``alpha``
            into every ``F^(k)`` (threshold pattern fixed at the forward pass, ``O(K nnz)``
            memory; :func:`~stochlap_torch.diffusion.differentiable_multiscale`). Default
            ``False``: the operators are held constant.
        **options: the :class:`~stochlap_torch.params.PaperParams` object as ``params=`` /
            ``paper=``.

    ``variant="robust"`` is deprecated: it builds a :class:`RobustMultiscale` (with a
    ``DeprecationWarning``), the robust variant's own layer.

    Shapes:
        vertices ``(V, 3)`` float, faces ``(F, 3)`` int64, optional batch ``(V,)`` int64 (a
        packed :class:`~stochlap_torch.mesh.MeshBatch`; ``None``: one mesh) ->
        :class:`~stochlap_torch.diffusion.MultiscaleRepresentation`.
    """

    def __new__(cls, *args, variant: str = "paper", **options):
        if check_choice("variant", variant, ("paper", "robust")) == "robust":
            warnings.warn(
                "StochasticLaplacian(variant='robust') is deprecated: use RobustMultiscale(...)",
                DeprecationWarning,
                stacklevel=2,
            )
            if args:
                raise ParameterError("StochasticLaplacian(variant='robust') takes keywords only")
            paper_only = ("return_operators", "differentiable_operator")
            refuse_unused("robust", {name: options.pop(name, None) for name in paper_only})
            return RobustMultiscale(**options)
        return super().__new__(cls)

    def __init__(
        self,
        num_scales: int | None = None,
        threshold: float | None = None,
        return_operators: bool = False,
        max_memory: int | None = None,
        differentiable_operator: bool = False,
        variant: str = "paper",
        **options,
    ):
        super().__init__()
        options.update(num_scales=num_scales, threshold=threshold)  # the paper's K and lambda
        self.params = resolve_params(PaperParams, "paper", options)
        self.return_operators = check_bool("return_operators", return_operators)
        self.differentiable_operator = check_bool(
            "differentiable_operator", differentiable_operator
        )
        self.max_memory = _checked_max_memory(max_memory)

    variant = "paper"

    def forward(
        self, vertices: Tensor, faces: Tensor, batch: Tensor | None = None
    ) -> MultiscaleRepresentation:
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
        return (
            f"{super().extra_repr()}, return_operators={self.return_operators}, "
            f"differentiable_operator={self.differentiable_operator}"
        )


class RobustMultiscale(_MeshLayer):
    """The robust variant's multiscale representation of a mesh or packed batch (heat
    diffusion for physical times on a pyramid of the mesh).

    Args:
        max_memory: byte budget (default: ``$STOCHLAP_MAX_MEMORY``, else half the physical memory).
        **options: fields of :class:`~stochlap_torch.params.RobustParams` (``num_scales=7``,
            ``t0=1e-3``, ...), or the object as ``params=`` / ``robust=``.

    Shapes:
        vertices ``(V, 3)`` float, faces ``(F, 3)`` int64, optional batch ``(V,)`` int64 ->
        :class:`~stochlap_torch.robust.RobustRepresentation`. ``forward`` also takes the
        mesh's ``structure`` (:func:`~stochlap_torch.robust_structure` with the same options).
    """

    variant = "robust"

    def __init__(self, max_memory: int | None = None, **options):
        super().__init__(resolve_params(RobustParams, "robust", options), max_memory)

    def _run(self, vertices, faces, batch, run: dict) -> RobustRepresentation:
        return robust_representation(vertices, faces, batch=batch, **run)


class MultiscaleSaliency(_MeshLayer):
    """Per-vertex saliency: vertices ``(V, 3)``, faces ``(F, 3)`` -> ``(V,)``.

    The options of :func:`~stochlap_torch.saliency_maps.mesh_saliency`, checked at
    construction.

    Args:
        variant: one of :data:`~stochlap_torch.saliency_maps.VARIANTS`; default ``"robust"``
            (or the method of a ``params=`` object).
        max_memory: byte budget (default: ``$STOCHLAP_MAX_MEMORY``, else half the physical memory).
        min_count: ``"valence_normalised"``'s smallest valence population (default 30).
        **options: the variant's options: fields of
            :class:`~stochlap_torch.params.RobustParams` or
            :class:`~stochlap_torch.params.PaperParams`, or the object as ``params=``.

    ``forward(vertices, faces, batch=None, structure=None)``: ``structure`` is the robust
    variant's :class:`~stochlap_torch.RobustStructure` of the mesh, reused (``None``: built).
    """

    def __init__(
        self,
        variant: str | None = None,
        max_memory: int | None = None,
        min_count: int | None = None,
        **options,
    ):
        super().__init__(saliency_params(variant, **options), max_memory)
        self.variant = variant or method_of(self.params)
        self.min_count = None if min_count is None else check_min_count(self.variant, min_count)

    def _run(self, vertices, faces, batch, run: dict) -> Tensor:
        return mesh_saliency(
            vertices, faces, batch, variant=self.variant, min_count=self.min_count, **run
        )

    def extra_repr(self) -> str:
        text = super().extra_repr()
        return text if self.min_count is None else f"{text}, min_count={self.min_count}"


class MultiscaleFeatures(_MeshLayer):
    """Per-vertex multiscale features: ``(V, 3)``, ``(F, 3)`` -> ``(V, C)``.

    The options of :func:`~stochlap_torch.features.multiscale_features`, checked at
    construction.

    Args:
        variant: ``"robust"`` (default, or the method of a ``params=`` object) or ``"paper"``.
        max_memory: byte budget (default: ``$STOCHLAP_MAX_MEMORY``, else half the physical memory).
        **options: the variant's options: fields of
            :class:`~stochlap_torch.params.RobustParams` or
            :class:`~stochlap_torch.params.PaperFeatureParams`, or the object as ``params=``.

    Shapes:
        vertices ``(V, 3)`` float, faces ``(F, 3)`` int64, optional batch ``(V,)`` int64 ->
        ``(V, C)`` with ``C = self.num_channels``; :meth:`channel_names` names the channels.
        ``forward`` also takes the robust variant's ``structure`` of the mesh.
    """

    def __init__(self, variant: str | None = None, max_memory: int | None = None, **options):
        super().__init__(feature_params(variant, **options), max_memory)

    @property
    def variant(self) -> str:
        return method_of(self.params)

    def channel_names(self) -> list[str]:
        """The ``C`` channel names, in the order of the feature columns."""
        return channel_names(self.params)

    @property
    def num_channels(self) -> int:
        return len(self.channel_names())

    def _run(self, vertices, faces, batch, run: dict) -> Tensor:
        return multiscale_features(vertices, faces, batch, **run)


class InterestPointHead(nn.Module):
    """Interest points from saliency (Sec. 4.5): ``(V,)`` saliency -> ``(N,)`` int64 indices.

    Args:
        mode: ``"nms"`` (default: a few tens of well separated points) or ``"paper"`` (every
            1-ring maximum above the global threshold).
        radius: ``"nms"`` suppression radius as a fraction of the bounding-box diagonal
            (default 0.1; ``"paper"`` refuses it).
        top_k: at most this many points (``None``: no cap).
        t_global: fraction of the saliency range a point must reach (0.4, as in the paper).
        include_boundary: let vertices on the rim of a hole be points (default ``False``).

    ``forward(saliency, vertices, faces, batch=None)``: ``batch`` (``None``: one mesh) as for
    :func:`~stochlap_torch.interest_points`.
    """

    def __init__(
        self,
        mode: str = "nms",
        radius: float | None = None,
        top_k: int | None = None,
        t_global: float = DEFAULT_T_GLOBAL,
        include_boundary: bool = False,
    ):
        super().__init__()
        checked = check_interest_parameters(mode, radius, top_k, t_global)
        self.mode, self.radius, self.top_k, self.t_global = checked
        self.include_boundary = check_bool("include_boundary", include_boundary)

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
            include_boundary=self.include_boundary,
        )

    def extra_repr(self) -> str:
        return (
            f"mode={self.mode!r}, radius={self.radius}, top_k={self.top_k}, "
            f"t_global={self.t_global}, include_boundary={self.include_boundary}"
        )
