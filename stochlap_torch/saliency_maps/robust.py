"""Moved to :mod:`stochlap_torch.robust` (kept until its importers switch)."""

from ..robust import robust_saliency

__all__ = ["robust_saliency"]
