"""Moved to :mod:`stochlap_torch.robust`; re-exported until its importers switch."""

from ..params import RobustParams
from ..robust.structure import RobustStructure, as_robust_params, build_structure

__all__ = ["RobustParams", "RobustStructure", "as_robust_params", "build_structure"]
