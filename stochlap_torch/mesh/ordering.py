"""Vertex orders that put neighbours close together in memory, and renumbering by them."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["LOCALITY_MIN_VERTICES", "Renumbering", "locality_order"]

#: Meshes at least this large are renumbered along a space-filling curve before the steps (the
#: kernel computes four consecutive rows together, which pays when they are neighbours).
LOCALITY_MIN_VERTICES = 4096


#: ``(shift, mask)`` rounds that spread the low 21 bits of an int64 two bits apart (Morton).
_SPREAD_ROUNDS = (
    (32, 0x1F00000000FFFF),
    (16, 0x1F0000FF0000FF),
    (8, 0x100F00F00F00F00F),
    (4, 0x10C30C30C30C30C3),
    (2, 0x1249249249249249),
)


def locality_order(vertices: Tensor) -> Tensor:
    """``(V,)`` int64 vertex order along a Morton (Z-order) curve of the positions (ties keep
    the file order): it speeds up the row-by-row products on meshes whose file order is poor.
    The codes are built in place in three ``(V,)`` buffers."""
    low = vertices.min(dim=0).values
    extent = (vertices.max(dim=0).values - low).max().clamp_min(torch.finfo(vertices.dtype).tiny)
    cells = (vertices - low).div_(extent).mul_(2**21 - 1)  # (V, 3) float in [0, 2**21 - 1]
    code = torch.zeros(vertices.shape[0], dtype=torch.int64, device=vertices.device)
    part, scratch = torch.empty_like(code), torch.empty_like(code)
    for axis in range(3):
        part.copy_(cells[:, axis]).bitwise_and_(0x1FFFFF)  # copy_ truncates, as .to(int64) does
        for shift, mask in _SPREAD_ROUNDS:
            torch.bitwise_left_shift(part, shift, out=scratch)
            part.bitwise_or_(scratch).bitwise_and_(mask)
        code.bitwise_or_(part.bitwise_left_shift_(axis))
    del cells, part, scratch
    return torch.argsort(code, stable=True)


@dataclass(frozen=True)
class Renumbering:
    """A mesh put in another vertex order, and the way back.

    Attributes:
        order: ``(V,)`` int64 original index of each renumbered vertex.
        new_index: ``(V,)`` int64 renumbered index of each original vertex (the inverse).
    """

    order: Tensor
    new_index: Tensor

    @classmethod
    def from_order(cls, order: Tensor) -> Renumbering:
        new_index = torch.empty_like(order)
        new_index[order] = torch.arange(order.shape[0], device=order.device)
        return cls(order, new_index)

    @classmethod
    def for_locality(cls, vertices: Tensor) -> Renumbering | None:
        """The Morton renumbering of a mesh of :data:`LOCALITY_MIN_VERTICES` vertices or
        more; ``None`` (keep the file order) for smaller ones."""
        if vertices.shape[0] < LOCALITY_MIN_VERTICES:
            return None
        return cls.from_order(locality_order(vertices.detach()))

    def mesh(
        self, vertices: Tensor, faces: Tensor, batch: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """``(vertices, faces, batch)`` in the new order (a ``None`` batch stays ``None``)."""
        return (
            vertices[self.order],
            self.new_index[faces],
            None if batch is None else batch[self.order],
        )

    def restore(self, values: Tensor, dim: int = 0) -> Tensor:
        """Per-vertex ``values`` (vertex axis ``dim``) from the new order back to the original."""
        return values.index_select(dim, self.new_index)
