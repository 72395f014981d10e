"""The mesh container: a pair of tensors, ``(V, 3)`` float vertices and ``(F, 3)`` int64 faces."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .validation import validate_mesh

__all__ = ["Mesh"]


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    Attributes:
        vertices: ``(V, 3)`` float tensor of positions, in the file's vertex order.
        faces: ``(F, 3)`` int64 tensor of vertex indices.
        file_vertices: ``(V_file,)`` int64, the vertex of this mesh that every vertex of the
            file became where :func:`~stochlap_torch.mesh.load_mesh` merged vertices at
            equal positions (``values[mesh.file_vertices]`` puts per-vertex values in the
            file's order); ``None`` when the vertices are the file's.
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    file_vertices: torch.Tensor | None = None

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Mesh:
        """Move to ``device`` and cast the vertices to ``dtype`` (faces stay int64)."""
        file_vertices = self.file_vertices
        if file_vertices is not None:
            file_vertices = file_vertices.to(device=device)
        return Mesh(
            self.vertices.to(device=device, dtype=dtype),
            self.faces.to(device=device),
            file_vertices,
        )

    def validate(self) -> Mesh:
        """Raise :class:`MeshError` if the mesh cannot be processed; return ``self`` otherwise."""
        validate_mesh(self.vertices, self.faces)
        return self
