"""The PyTorch Geometric transform ``StochasticFeatures`` (needs ``torch_geometric``; the
package imports this module on first use of the name)."""

from __future__ import annotations

import dataclasses

import torch
from torch_geometric.transforms import BaseTransform

from .._common.errors import ParameterError
from ..features import channel_names, feature_params, multiscale_features
from ..params import method_of

#: Attributes PyG gives a meaning of their own: the features never overwrite them.
_RESERVED = ("pos", "face", "batch", "ptr", "edge_index", "edge_attr", "y", "normal")


class StochasticFeatures(BaseTransform):
    """PyG transform: multiscale features of ``data.pos`` and ``data.face`` as node features,
    concatenated to ``data.x`` (created if absent) unless ``attr_name`` names another
    attribute, as PyG's ``AddLaplacianEigenvectorPE`` does.

    Args:
        attr_name: attribute to set, not one of PyG's own (``pos``, ``face``, ``batch``, ...).
        variant: ``"robust"`` (default) or ``"paper"``, with its ``options``, as for
            :func:`~stochlap_torch.features.multiscale_features`; checked here.
        options: that variant's options.

    ``data.pos`` is ``(V, 3)``, ``data.face`` PyG's ``(3, F)``; a ``Batch`` (with a ``batch``
    vector) is handled per mesh. Picklable, so it runs in ``DataLoader`` workers.
    """

    def __init__(self, attr_name: str | None = None, variant: str | None = None, **options):
        self.params = feature_params(variant, **options)
        if attr_name is not None and (not isinstance(attr_name, str) or not attr_name):
            raise ParameterError(f"attr_name must be a non-empty string or None, got {attr_name!r}")
        if attr_name in _RESERVED:
            raise ParameterError(
                f"attr_name={attr_name!r} is PyG's own attribute: the features would replace "
                "it; choose another name, or None to concatenate them to data.x"
            )
        self.attr_name = attr_name

    def channel_names(self) -> list[str]:
        """Names of the feature columns this transform adds."""
        return channel_names(self.params)

    def forward(self, data):
        pos, face = getattr(data, "pos", None), getattr(data, "face", None)
        if pos is None or face is None:
            raise ParameterError("StochasticFeatures needs data.pos (V, 3) and data.face (3, F)")
        if face.dim() != 2 or face.shape[0] != 3:
            raise ParameterError(f"data.face must be (3, F), got {tuple(face.shape)}")
        existing = getattr(data, "x", None)
        if self.attr_name is None and existing is not None and existing.shape[0] != pos.shape[0]:
            raise ParameterError(
                f"data.x has {existing.shape[0]} rows, data.pos {pos.shape[0]}: the features "
                "(one row per vertex) cannot be concatenated to it"
            )
        batch = getattr(data, "batch", None)
        features = multiscale_features(pos, face.t(), batch, params=self.params)
        if self.attr_name is not None:
            setattr(data, self.attr_name, features)
            return data
        if existing is not None:
            existing = existing.unsqueeze(1) if existing.dim() == 1 else existing
            # Integer (or boolean) node labels would truncate the features: promote both.
            dtype = torch.promote_types(existing.dtype, features.dtype)
            features = torch.cat([existing.to(dtype), features.to(dtype)], dim=1)
        data.x = features
        return data

    def __repr__(self) -> str:
        # PyG compares this text with the one saved beside a processed dataset to decide
        # whether it is stale: it names every setting that differs from the defaults.
        default = type(self.params)()
        changed = [
            f"{field.name}={getattr(self.params, field.name)!r}"
            for field in dataclasses.fields(self.params)
            if getattr(self.params, field.name) != getattr(default, field.name)
        ]
        variant = method_of(self.params)
        attr = [] if self.attr_name is None else [f"attr_name={self.attr_name!r}"]
        return f"{type(self).__name__}({', '.join([f'variant={variant!r}', *changed, *attr])})"
