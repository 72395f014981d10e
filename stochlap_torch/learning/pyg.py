"""The PyTorch Geometric transform ``StochasticFeatures`` (needs ``torch_geometric``; the
package imports this module on first use of the name)."""

from __future__ import annotations

import torch
from torch_geometric.transforms import BaseTransform

from .._common.errors import ParameterError
from ..diffusion import RobustParams
from ..features import DEFAULT_FEATURE_VARIANT, FEATURE_GROUPS, multiscale_features
from .datasets import channel_names_of, feature_params

__all__ = ["StochasticFeatures"]


class StochasticFeatures(BaseTransform):
    """PyG transform: multiscale features of ``data.pos`` and ``data.face`` as node features.

    As PyG's transforms do (``AddLaplacianEigenvectorPE``, ``AddRandomWalkPE``), the features
    are concatenated to ``data.x`` (created if absent) unless ``attr_name`` names another
    attribute, which is then set.

    Args:
        num_scales, threshold, include, rotation_invariant, normalisation, variant, robust: the
            parameters of :func:`~stochlap_torch.features.multiscale_features`, with its
            defaults (the robust channels).
        attr_name: attribute to set (default ``None``: concatenate to ``data.x``).

    ``data.pos`` is ``(V, 3)``, ``data.face`` PyG's ``(3, F)``; a ``Batch`` (with a ``batch``
    vector) is handled per mesh. Picklable, so it runs in ``DataLoader`` workers.
    """

    def __init__(
        self,
        num_scales: int | None = None,
        threshold: float = 1e-3,
        include: tuple[str, ...] = FEATURE_GROUPS,
        rotation_invariant: bool = True,
        normalisation: str = "mean_edge",
        attr_name: str | None = None,
        variant: str = DEFAULT_FEATURE_VARIANT,
        robust: RobustParams | None = None,
    ):
        self.params = feature_params(
            num_scales, threshold, include, rotation_invariant, normalisation, variant, robust
        )
        self.attr_name = attr_name

    def channel_names(self) -> list[str]:
        """Names of the feature columns this transform adds."""
        return channel_names_of(self.params)

    def forward(self, data):
        pos, face = getattr(data, "pos", None), getattr(data, "face", None)
        if pos is None or face is None:
            raise ParameterError("StochasticFeatures needs data.pos (V, 3) and data.face (3, F)")
        if face.dim() != 2 or face.shape[0] != 3:
            raise ParameterError(f"data.face must be (3, F), got {tuple(face.shape)}")
        batch = getattr(data, "batch", None)
        features = multiscale_features(pos, face.t(), batch=batch, **self.params)
        if self.attr_name is not None:
            setattr(data, self.attr_name, features)
            return data
        existing = getattr(data, "x", None)
        if existing is not None:
            existing = existing.unsqueeze(1) if existing.dim() == 1 else existing
            features = torch.cat([existing, features.to(existing.dtype)], dim=1)
        data.x = features
        return data

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}(variant={self.params['variant']!r}, "
            f"channels={len(self.channel_names())}, attr_name={self.attr_name!r})"
        )
