"""The PyTorch Geometric transform ``StochasticFeatures`` (needs ``torch_geometric``; the
package imports this module on first use of the name)."""

from __future__ import annotations

import torch
from torch_geometric.transforms import BaseTransform

from .._common.errors import ParameterError
from ..features import FEATURE_GROUPS, multiscale_features
from .datasets import feature_params

__all__ = ["StochasticFeatures"]


class StochasticFeatures(BaseTransform):
    """PyG transform: multiscale features of ``data.pos`` / ``data.face`` into ``data.x``.

    Args:
        num_scales, threshold, include, rotation_invariant, normalisation: the parameters
            of :func:`~stochlap_torch.features.multiscale_features`.
        attr: attribute to write (``"x"``).
        concat: append to an existing ``attr`` along the channel dimension instead of
            replacing it.

    ``data.pos`` is ``(V, 3)``, ``data.face`` PyG's ``(3, F)``; a ``Batch`` (with a
    ``batch`` vector) is handled per mesh.
    """

    def __init__(
        self,
        num_scales: int = 6,
        threshold: float = 1e-3,
        include: tuple[str, ...] = FEATURE_GROUPS,
        rotation_invariant: bool = True,
        normalisation: str = "mean_edge",
        attr: str = "x",
        concat: bool = False,
    ):
        self.params = feature_params(
            num_scales, threshold, include, rotation_invariant, normalisation
        )
        self.attr = attr
        self.concat = concat

    def forward(self, data):
        pos, face = getattr(data, "pos", None), getattr(data, "face", None)
        if pos is None or face is None:
            raise ParameterError("StochasticFeatures needs data.pos (V, 3) and data.face (3, F)")
        if face.dim() != 2 or face.shape[0] != 3:
            raise ParameterError(f"data.face must be (3, F), got {tuple(face.shape)}")
        batch = getattr(data, "batch", None)
        features = multiscale_features(pos, face.t(), batch=batch, **self.params)
        existing = getattr(data, self.attr, None)
        if self.concat and existing is not None:
            existing = existing.unsqueeze(1) if existing.dim() == 1 else existing
            features = torch.cat([existing, features.to(existing.dtype)], dim=1)
        setattr(data, self.attr, features)
        return data

    def __repr__(self) -> str:
        return (
            f"{self.__class__.__name__}(num_scales={self.params['num_scales']}, "
            f"threshold={self.params['threshold']:g}, attr={self.attr!r})"
        )
