"""Moved to :mod:`stochlap_torch.robust` (kept until its importers switch)."""

from ..robust import SPREAD_FLOOR, robust_channel_names
from ..robust import robust_features as robust_features_from_representation

__all__ = ["SPREAD_FLOOR", "robust_channel_names", "robust_features_from_representation"]
