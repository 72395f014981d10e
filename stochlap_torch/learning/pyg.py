"""The PyTorch Geometric transform ``StochasticFeatures`` (needs ``torch_geometric``; the
package imports this module on first use of the name)."""

from __future__ import annotations

import torch
from torch_geometric.transforms import BaseTransform

from .._common.errors import ParameterError
from ..diffusion import PaperParams, RobustParams
from ..features import DEFAULT_FEATURE_VARIANT, feature_settings, features_with_settings

__all__ = ["StochasticFeatures"]


class StochasticFeatures(BaseTransform):
    """PyG transform: multiscale features of ``data.pos`` and ``data.face`` as node features.

    As PyG's transforms do (``AddLaplacianEigenvectorPE``, ``AddRandomWalkPE``), the features
    are concatenated to ``data.x`` (created if absent) unless ``attr_name`` names another
    attribute, which is then set.

    Args:
        num_scales, threshold, include, rotation_invariant, normalisation, variant, robust, paper:
            the options of :func:`~stochlap_torch.features.multiscale_features`, with
            its defaults (the robust channels), resolved and checked here.
        attr_name: attribute to set (default ``None``: concatenate to ``data.x``).

    ``data.pos`` is ``(V, 3)``, ``data.face`` PyG's ``(3, F)``; a ``Batch`` (with a ``batch``
    vector) is handled per mesh. Picklable, so it runs in ``DataLoader`` workers.
    """

    def __init__(
        self,
        num_scales: int | None = None,
        threshold: float | None = None,
        include: tuple[str, ...] | None = None,
        rotation_invariant: bool | None = None,
        normalisation: str | None = None,
        attr_name: str | None = None,
        variant: str = DEFAULT_FEATURE_VARIANT,
        robust: RobustParams | None = None,
        paper: PaperParams | None = None,
    ):
        self.settings = feature_settings(
            variant,
            num_scales,
            threshold,
            include,
            rotation_invariant,
            normalisation,
            robust=robust,
            paper=paper,
        )
        if attr_name is not None and not isinstance(attr_name, str):
            raise ParameterError(f"attr_name must be a string or None, got {attr_name!r}")
        self.attr_name = attr_name

    def channel_names(self) -> list[str]:
        """Names of the feature columns this transform adds."""
        return self.settings.channel_names()

    def forward(self, data):
        pos, face = getattr(data, "pos", None), getattr(data, "face", None)
        if pos is None or face is None:
            raise ParameterError("StochasticFeatures needs data.pos (V, 3) and data.face (3, F)")
        if face.dim() != 2 or face.shape[0] != 3:
            raise ParameterError(f"data.face must be (3, F), got {tuple(face.shape)}")
        batch = getattr(data, "batch", None)
        features = features_with_settings(pos, face.t(), self.settings, batch=batch)
        if self.attr_name is not None:
            setattr(data, self.attr_name, features)
            return data
        existing = getattr(data, "x", None)
        if existing is not None:
            existing = existing.unsqueeze(1) if existing.dim() == 1 else existing
            # Integer (or boolean) node labels would truncate the features: promote both.
            dtype = torch.promote_types(existing.dtype, features.dtype)
            features = torch.cat([existing.to(dtype), features.to(dtype)], dim=1)
        data.x = features
        return data

    def __repr__(self) -> str:
        # PyG compares this text with the one saved beside a processed dataset to decide
        # whether it is stale: it names every setting that changes the features.
        return (
            f"{self.__class__.__name__}(settings={self.settings!r}, attr_name={self.attr_name!r})"
        )
