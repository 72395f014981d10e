"""Moved to :mod:`stochlap_torch.robust`; re-exported until its importers switch."""

from ..robust.channels import RobustRepresentation
from ..robust.structure import robust_representation, robust_structure

__all__ = ["RobustRepresentation", "robust_representation", "robust_structure"]
