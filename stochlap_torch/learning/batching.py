"""Samples of a :class:`~stochlap_torch.learning.MeshFeatureDataset` and their packing, as
PyG's ``Batch`` does."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from .._common.errors import ParameterError
from ..mesh import MeshBatch
from .targets import check_vertex_target


class MeshSample(NamedTuple):
    """One mesh of a :class:`MeshFeatureDataset`.

    Attributes:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` int64.
        features: ``(V, C)`` float, channels named by ``dataset.channel_names()``.
        path: the file it came from.
        index: its position in the dataset.
        target: the mesh's target (``()`` for a class label, or any shape), or ``None``.
        vertex_target: ``(V,)`` or ``(V, ...)`` per-vertex target (e.g. segmentation labels),
            or ``None``.
    """

    vertices: Tensor
    faces: Tensor
    features: Tensor
    path: str
    index: int
    target: Tensor | None = None
    vertex_target: Tensor | None = None


class MeshFeatureBatch(NamedTuple):
    """Several samples packed (see :class:`~stochlap_torch.MeshBatch`), as PyG's ``Batch``.

    Attributes:
        vertices: ``(N, 3)`` float, the vertices of every mesh one after the other.
        faces: ``(M, 3)`` int64, offset into the packed ``vertices``.
        features: ``(N, C)`` float.
        batch: ``(N,)`` int64 mesh of every vertex.
        ptr: ``(B + 1,)`` int64 vertex offsets: mesh ``b`` owns rows ``ptr[b]:ptr[b + 1]``.
        paths: ``B`` files.
        indices: ``(B,)`` int64 dataset positions.
        face_ptr: ``(B + 1,)`` int64 face offsets.
        target: ``(B, ...)`` the samples' targets stacked, or ``None`` without targets.
        vertex_target: ``(N, ...)`` the samples' per-vertex targets concatenated (row ``i``
            belongs to vertex ``i``), or ``None``.
    """

    vertices: Tensor
    faces: Tensor
    features: Tensor
    batch: Tensor
    ptr: Tensor
    paths: list[str]
    indices: Tensor
    face_ptr: Tensor
    target: Tensor | None = None
    vertex_target: Tensor | None = None

    @property
    def num_meshes(self) -> int:
        return len(self.paths)

    @property
    def mesh_batch(self) -> MeshBatch:
        """The packed meshes alone, e.g. for ``multiscale_representation(..., batch=)``."""
        return MeshBatch(self.vertices, self.faces, self.batch, self.ptr, self.face_ptr)

    def unbatch(self, values: Tensor) -> list[Tensor]:
        """Split a per-vertex tensor ``(N, ...)`` (a model's output) into ``B`` views
        ``(V_b, ...)`` (:class:`ParameterError` if it has not ``N`` rows)."""
        return self.mesh_batch.unbatch(values)

    def unbatch_faces(self, values: Tensor) -> list[Tensor]:
        """Split a per-face tensor ``(M, ...)`` into ``B`` views ``(F_b, ...)``
        (:class:`ParameterError` if it has not ``M`` rows)."""
        return self.mesh_batch.unbatch_faces(values)

    def to(self, device: torch.device | str, non_blocking: bool = False) -> MeshFeatureBatch:
        """The batch with every tensor on ``device`` (the paths stay as they are)."""
        return self._make(
            value.to(device, non_blocking=non_blocking) if isinstance(value, Tensor) else value
            for value in self
        )


def _stack_targets(samples: Sequence[MeshSample], name: str, per_vertex: bool) -> Tensor | None:
    """The samples' ``name`` targets packed: stacked ``(B, ...)`` per mesh, concatenated
    ``(N, ...)`` per vertex; ``None`` when no sample has one.

    Raises:
        ParameterError: some samples have the target and others not, a per-vertex target
            without one row per vertex, or targets of different shapes.
    """
    values = [getattr(sample, name) for sample in samples]
    missing = [sample.path for sample, value in zip(samples, values, strict=True) if value is None]
    if len(missing) == len(samples):
        return None
    if missing:
        raise ParameterError(f"{name} is None in some samples of the batch only: {missing}")
    tensors = [torch.as_tensor(value) for value in values]
    if per_vertex:
        for sample, tensor in zip(samples, tensors, strict=True):
            check_vertex_target(tensor, sample.path, sample.vertices.shape[0], merged=False)
    shapes = {tuple(t.shape[1:] if per_vertex else t.shape) for t in tensors}
    if len(shapes) > 1:
        raise ParameterError(f"{name}s of one batch must share a shape, got {sorted(shapes)}")
    return torch.cat(tensors) if per_vertex else torch.stack(tensors)


def collate_meshes(samples: Sequence[MeshSample]) -> MeshFeatureBatch:
    """Pack samples of different sizes into one :class:`MeshFeatureBatch` (``collate_fn``).

    Raises:
        ParameterError: no samples, or an item that is not a :class:`MeshSample` (what
            :class:`~stochlap_torch.MeshFeatureDataset` returns).
    """
    if isinstance(samples, MeshSample) or not isinstance(samples, Sequence) or not samples:
        raise ParameterError(
            f"collate_meshes takes a non-empty list of MeshSample, got {type(samples).__name__}"
        )
    wrong = [type(sample).__name__ for sample in samples if not isinstance(sample, MeshSample)]
    if wrong:
        raise ParameterError(
            f"collate_meshes takes MeshSample items (a MeshFeatureDataset's), got {wrong[0]}"
        )
    packed = MeshBatch.from_meshes([(s.vertices, s.faces) for s in samples])
    return MeshFeatureBatch(
        vertices=packed.vertices,
        faces=packed.faces,
        features=torch.cat([s.features for s in samples]),
        batch=packed.batch,
        ptr=packed.ptr,
        paths=[s.path for s in samples],
        indices=torch.tensor([s.index for s in samples], dtype=torch.int64),
        face_ptr=packed.face_ptr,
        target=_stack_targets(samples, "target", per_vertex=False),
        vertex_target=_stack_targets(samples, "vertex_target", per_vertex=True),
    )
