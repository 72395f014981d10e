"""The mesh containers: :class:`Mesh` and :class:`MeshBatch`, meshes of different sizes packed
into one (PyG / PyTorch3D "packed" style). A packed batch's operators are block diagonal, so
every per-vertex result equals that of a separate run on the mesh alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from itertools import accumulate

import torch
from torch import Tensor

from .._common.errors import ParameterError
from .validation import MeshError, _read, as_mesh_tensors, validate_mesh

__all__ = ["Mesh", "MeshBatch", "check_batch"]


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    Attributes:
        vertices: ``(V, 3)`` float tensor of positions, in the file's vertex order.
        faces: ``(F, 3)`` int64 tensor of vertex indices.
        file_vertices: ``(V_file,)`` int64, the vertex every vertex of the file became where
            :func:`~stochlap_torch.mesh.load_mesh` merged vertices (``values[file_vertices]``
            puts per-vertex values in the file's order); ``None`` when they are the file's.
    """

    vertices: Tensor
    faces: Tensor
    file_vertices: Tensor | None = None

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Mesh:
        """Move to ``device`` and cast the vertices to ``dtype`` (``None``: unchanged; faces stay
        int64)."""
        return Mesh(
            self.vertices.to(device=device, dtype=dtype),
            self.faces.to(device=device),
            None if self.file_vertices is None else self.file_vertices.to(device=device),
        )

    def validate(self) -> Mesh:
        """Raise :class:`MeshError` if the mesh cannot be processed; return ``self`` otherwise."""
        validate_mesh(self.vertices, self.faces)
        return self


@dataclass(frozen=True)
class MeshBatch:
    """Several meshes packed into one.

    Attributes:
        vertices: ``(N, 3)`` float, the vertices of every mesh one after the other.
        faces: ``(M, 3)`` int64 indices into ``vertices``.
        batch: ``(N,)`` int64 mesh index of every vertex.
        ptr: ``(B + 1,)`` int64 vertex offsets: mesh ``b`` owns ``vertices[ptr[b]:ptr[b+1]]``.
        face_ptr: ``(B + 1,)`` int64 face offsets.
    """

    vertices: Tensor
    faces: Tensor
    batch: Tensor
    ptr: Tensor
    face_ptr: Tensor

    @classmethod
    def from_meshes(cls, meshes: Sequence[Mesh | tuple[Tensor, Tensor]]) -> MeshBatch:
        """Pack meshes (``Mesh`` or ``(vertices, faces)`` pairs); each is validated."""
        if len(meshes) == 0:
            raise MeshError("empty batch: no meshes given")
        pairs = [(m.vertices, m.faces) if isinstance(m, Mesh) else m for m in meshes]
        # A zero-length edge is the paper's method's to refuse, not the robust variant's.
        pairs = [as_mesh_tensors(*pair, check_edge_lengths=False) for pair in pairs]
        dtypes = {vertices.dtype for vertices, _ in pairs}
        if len(dtypes) > 1:
            raise MeshError(
                f"meshes of one batch must share a dtype, got {sorted(map(str, dtypes))}"
            )
        ptr = torch.tensor([0, *accumulate(v.shape[0] for v, _ in pairs)])
        face_ptr = torch.tensor([0, *accumulate(f.shape[0] for _, f in pairs)])
        device = pairs[0][0].device
        vertices = torch.cat([v for v, _ in pairs])
        faces = torch.cat([f + int(ptr[b]) for b, (_, f) in enumerate(pairs)])
        batch = torch.repeat_interleave(torch.arange(len(pairs)), ptr.diff())
        return cls(vertices, faces, batch.to(device), ptr.to(device), face_ptr.to(device))

    @property
    def num_meshes(self) -> int:
        return int(self.ptr.shape[0]) - 1

    def unbatch(self, values: Tensor) -> list[Tensor]:
        """Split a per-vertex tensor ``(N, ...)`` into ``B`` views ``(V_b, ...)``
        (:class:`ParameterError` if it has not ``N`` rows)."""
        return split_by_offsets(values, self.ptr, "vertex")

    def unbatch_faces(self, values: Tensor) -> list[Tensor]:
        """Split a per-face tensor ``(M, ...)`` into ``B`` views ``(F_b, ...)``
        (:class:`ParameterError` if it has not ``M`` rows)."""
        return split_by_offsets(values, self.face_ptr, "face")

    def to(self, device: torch.device | str, non_blocking: bool = False) -> MeshBatch:
        """The batch with every tensor on ``device``."""
        return MeshBatch(*(t.to(device, non_blocking=non_blocking) for t in vars(self).values()))

    def mesh(self, index: int) -> Mesh:
        """Mesh ``index`` on its own, faces re-based to its vertices; a negative ``index``
        counts from the end, as in a list.

        Raises:
            IndexError: ``index`` is not in ``[-B, B)``.
        """
        count = self.num_meshes
        if not -count <= index < count:
            raise IndexError(f"mesh index {index} is out of range for a batch of {count} meshes")
        index %= count
        start, stop = int(self.ptr[index]), int(self.ptr[index + 1])
        faces = self.faces[int(self.face_ptr[index]) : int(self.face_ptr[index + 1])] - start
        return Mesh(self.vertices[start:stop], faces)


def split_by_offsets(values: Tensor, offsets: Tensor, what: str = "vertex") -> list[Tensor]:
    """Split ``values`` ``(offsets[-1], ...)`` at ``(B + 1,)`` ``offsets`` into views, or raise
    :class:`ParameterError` naming the rows (``what``: ``"vertex"`` or ``"face"``)."""
    total = int(offsets[-1])
    if not isinstance(values, Tensor) or values.ndim == 0 or values.shape[0] != total:
        shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
        raise ParameterError(
            f"unbatch needs a per-{what} tensor with {total} rows (one per {what} of the "
            f"batch), got {shape}"
        )
    return list(torch.split(values, offsets.diff().tolist(), dim=0))


def check_batch(batch, num_vertices: int, faces: Tensor) -> Tensor:
    """Validate a ``(V,)`` mesh-index vector against a validated packed mesh; return it as
    int64 on the device of ``faces``. The labels must be ``0..B-1``, each used: per-mesh
    arrays are sized by the largest label.

    Raises:
        MeshError: not an integer ``(V,)`` vector, labels that are negative or not
            ``0..B-1``, or a face that joins two meshes.
    """
    batch = _read(batch, "batch", MeshError, "an integer vector")
    if batch.shape != (num_vertices,):
        raise MeshError(f"batch must have shape ({num_vertices},), got {tuple(batch.shape)}")
    if batch.is_floating_point() or batch.is_complex() or batch.dtype == torch.bool:
        raise MeshError(f"batch must hold integer mesh indices, got {batch.dtype}")
    batch = batch.to(device=faces.device, dtype=torch.int64)
    if bool((batch < 0).any()):
        raise MeshError("batch holds negative mesh indices")
    labels = torch.unique(batch)
    if labels.numel() and int(labels[-1]) != labels.numel() - 1:
        raise MeshError(
            f"batch labels must be 0..B-1 with every mesh present; got {labels.numel()} "
            f"distinct labels up to {int(labels[-1])}"
        )
    face_mesh = batch[faces]
    mixed = (face_mesh != face_mesh[:, :1]).any(dim=1).nonzero().flatten()
    if mixed.numel():
        raise MeshError(
            f"{mixed.numel()} faces join vertices of different meshes of the batch, e.g. face "
            f"{mixed[0].item()} = {faces[mixed[0]].tolist()}"
        )
    return batch
