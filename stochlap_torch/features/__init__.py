"""Per-vertex multiscale features for learning pipelines: ``(V, 3)``, ``(F, 3)`` -> ``(V, C)``.

:func:`multiscale_features` is the one entry point; ``variant=`` picks the method: ``"robust"``
(default: channels that survive remeshing, :class:`~stochlap_torch.params.RobustParams`) or
``"paper"`` (the coefficients and difference maps of the paper's Algorithm 1,
:class:`~stochlap_torch.params.PaperFeatureParams`). Each method's options are the fields of
its parameters class, given as keywords or as the object itself (``params=``).
"""

from __future__ import annotations

from torch import Tensor

from .._common.checks import check_choice, refuse_unused
from ..params import PaperFeatureParams, RobustParams, method_of, resolve_params
from ..robust import RobustStructure, robust_channel_names, robust_features, robust_representation
from .paper import mesh_lengths, paper_channel_names, paper_features

__all__ = [
    "FEATURE_PARAMS",
    "channel_names",
    "feature_channel_names",
    "feature_params",
    "mesh_lengths",
    "multiscale_features",
]

#: The parameters class of each features variant (the first is the default).
FEATURE_PARAMS = {"robust": RobustParams, "paper": PaperFeatureParams}


def feature_params(variant: str | None = None, **options) -> RobustParams | PaperFeatureParams:
    """The options of the features of ``variant`` (default ``"robust"``, or the method of a
    ``params=`` object) as its parameters object; see
    :func:`~stochlap_torch.params.resolve_params`.

    Raises:
        ParameterError: a bad value, or an option the variant does not use.
    """
    if variant is None:
        variant = method_of(options.get("params"))
    check_choice("variant", variant, tuple(FEATURE_PARAMS))
    return resolve_params(FEATURE_PARAMS[variant], variant, options)


def channel_names(params: RobustParams | PaperFeatureParams) -> list[str]:
    """The ``C`` names of the feature columns of resolved ``params``, in order."""
    if isinstance(params, RobustParams):
        return robust_channel_names(params)
    return paper_channel_names(params)


def feature_channel_names(variant: str | None = None, **options) -> list[str]:
    """Names of the channels :func:`multiscale_features` returns with these options
    (``variant``: ``"robust"`` by default, or the method of a ``params=`` object)."""
    return channel_names(feature_params(variant, **options))


def multiscale_features(
    vertices,
    faces,
    batch: Tensor | None = None,
    *,
    structure: RobustStructure | list[RobustStructure] | None = None,
    variant: str | None = None,
    max_memory: int | None = None,
    **options,
) -> Tensor:
    """``(V, C)`` per-vertex multiscale features of a mesh or packed batch.

    Args:
        vertices: ``(V, 3)`` float tensor; the features come in its dtype and on its device.
        faces: ``(F, 3)`` integer tensor.
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch (``None``:
            one mesh).
        structure: ``"robust"`` only: the mesh's :class:`~stochlap_torch.RobustStructure`
            (:func:`~stochlap_torch.robust_structure`, built with the same options; for a
            batch, a list of one per mesh), reused (``None``: built on every call).
        variant: ``"robust"`` (default, or the method of a ``params=`` object) or ``"paper"``.
        max_memory: byte budget (default: ``$STOCHLAP_MAX_MEMORY``, else half the physical memory).
        **options: the variant's options: fields of
            :class:`~stochlap_torch.params.RobustParams` (``num_scales=7``, ``t0=1e-3``, ...)
            or of :class:`~stochlap_torch.params.PaperFeatureParams` (``num_scales=6``,
            ``threshold=1e-3``, ``include`` = every group, ``rotation_invariant=True``,
            ``normalisation="mean_edge"``, ``differentiable_operator=False``); or the whole
            object as ``params=`` (also ``robust=`` / ``paper=``).

    Returns:
        ``(V, C)`` float, ``C = len(feature_channel_names(...))`` for the same options.
        Gradients reach the vertices with the operators held constant (``"paper"`` with
        ``differentiable_operator=True``: through the operators too).

    Raises:
        ParameterError: a bad option, or one the variant does not use.
        MeshError: a bad mesh.
    """
    params = feature_params(variant, **options)
    if isinstance(params, RobustParams):
        rep = robust_representation(vertices, faces, params, batch, max_memory, structure=structure)
        return robust_features(rep)
    refuse_unused("paper", {"structure": structure})
    return paper_features(vertices, faces, params, batch, max_memory)
