"""What every operator construction hands to the diffusion steps."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor

from ..sparse import CSR, normalize_rows

__all__ = ["MeshOperators"]


@dataclass(frozen=True)
class MeshOperators:
    """Everything the diffusion steps need from the mesh.

    Attributes:
        lhat: ``Lhat`` as a ``(V, V)`` :class:`~stochlap_torch.sparse.CSR` with non-negative
            values, every edge of the mesh stored (whatever its weight) and every diagonal
            entry; ``F^(1)`` is ``Lhat`` normalised by rows.
        alpha: ``(V,)`` the factor every column of a step's product is multiplied by
            (Eq. 9 for the paper's operators).
    """

    lhat: CSR
    alpha: Tensor

    @cached_property
    def edges(self) -> Tensor:
        """``(E, 2)`` int64 unique undirected edges ``i < j``, lexicographic: the entries of
        ``Lhat`` above its diagonal (read from it on first access; the steps never need
        them, and at 10M vertices they are half a gigabyte)."""
        crow, col = self.lhat.crow, self.lhat.col
        rows = torch.arange(self.num_vertices, device=col.device).repeat_interleave(crow.diff())
        upper = col > rows
        return torch.stack([rows[upper], col[upper]], dim=1)

    @property
    def num_vertices(self) -> int:
        return self.lhat.num_rows

    def stochastic_laplacian(self) -> CSR:
        """``F^(1)``: ``Lhat`` normalised by rows."""
        return normalize_rows(self.lhat)
