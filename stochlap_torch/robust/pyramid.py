"""A pyramid of coarser copies of a mesh, for reaching large diffusion times at linear cost:
each level a quadric decimation (fast-simplification) of every connected component of the one
above, snapped to its vertices (so a gather of the mesh's positions, which gradients reach).
Values come back up by barycentric interpolation on the closest coarse triangle, held fixed.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .. import _kernels
from .._common.errors import MeshError
from ..mesh import connected_components, face_areas
from ..mesh.geometry import orient_faces
from ..params import RobustParams
from ..sparse.autograd import constant_matmul
from ..sparse.csr import CSR, compress_rows
from .heat import LevelSemigroup, heat_diagonal, heat_operator

#: Components with fewer vertices than this are carried to the next level unchanged.
_MIN_COMPONENT = 128
#: Candidate coarse vertices per fine point when looking for its closest coarse triangle.
_CANDIDATES = 4

#: fast-simplification keeps the mesh being decimated in C++ globals, filled and read back by
#: separate calls between which Python may switch threads: one decimation at a time.
_DECIMATION_LOCK = threading.Lock()


def _new_decimation_lock() -> None:
    global _DECIMATION_LOCK
    _DECIMATION_LOCK = threading.Lock()  # a fork child owns no thread that could hold it


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_new_decimation_lock)


@dataclass
class Level:
    """One level of a :func:`build_pyramid`, as numpy arrays.

    Attributes:
        vertices: ``(n, 3)`` float64 positions.
        faces: ``(m, 3)`` int64 triangles.
        vertex_ids: ``(n,)`` int64 index of every vertex in level 0.
        labels: ``(n,)`` int64 connected component of every vertex.
        prolong: ``(face (n_above,), bary (n_above, 3))``: the closest triangle of this level
            to every vertex of the level above, and the closest point's barycentric
            coordinates; ``None`` on level 0.
        deviation: a bound on the distance of the mesh's surface to this level's.
        mean_vertex_area: total area over the vertex count.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_ids: np.ndarray
    labels: np.ndarray
    prolong: tuple[np.ndarray, np.ndarray] | None
    deviation: float
    mean_vertex_area: float


def _unstacked(triangles: np.ndarray) -> np.ndarray:
    """``(m,)`` bool: the triangles no other has the three vertices of (snapping can stack two
    on a collapsed fold: both go, which leaves the rest a closed surface)."""
    _, inverse, counts = np.unique(
        np.sort(triangles, axis=1), axis=0, return_inverse=True, return_counts=True
    )
    return counts[inverse.reshape(-1)] == 1


def _decimate_component(vertices, faces, ratio: float, threads: int):
    """Quadric decimation of one component to about ``1/ratio`` of its vertices, snapped to
    its own vertices: ``(kept, faces)`` (indices into ``vertices``)."""
    import fast_simplification
    from scipy.spatial import cKDTree

    target = max(int(vertices.shape[0] / ratio), 4)
    with np.errstate(over="ignore"):  # checked on the next line
        single = vertices.astype(np.float32)  # fast-simplification works in float32
    if not np.isfinite(single).all():  # a vertex 1e100 away from the others, say
        raise MeshError(
            "the mesh's triangles differ in size by more than the robust variant can represent "
            "(its decimation works in float32): some vertices lie orders of magnitude farther "
            "out than the rest; remove them, or use variant='paper'"
        )
    with _DECIMATION_LOCK:
        points, triangles = fast_simplification.simplify(
            single,
            faces.astype(np.int32),
            target_reduction=1.0 - target / vertices.shape[0],
        )
    _, snapped = cKDTree(vertices).query(np.asarray(points, dtype=np.float64), workers=threads)
    triangles = np.asarray(snapped, dtype=np.int64)[np.asarray(triangles, dtype=np.int64)]
    triangles = triangles[(triangles != np.roll(triangles, 1, axis=1)).all(axis=1)]
    triangles = triangles[_unstacked(triangles)]
    kept = np.unique(triangles)
    if kept.size < 4:  # decimation destroyed the component: keep it whole
        return np.arange(vertices.shape[0]), faces
    return kept, triangles


def _coarser(level: Level, ratio: float, threads: int) -> tuple[np.ndarray, np.ndarray]:
    """``(parent, faces)`` of the next level: the kept vertices of ``level`` (indices into it)
    and the coarse triangles in the coarse numbering; component by component."""
    parents, triangles, offset = [], [], 0
    for label in np.unique(level.labels):
        members = np.flatnonzero(level.labels == label)
        local = np.full(level.vertices.shape[0], -1, dtype=np.int64)
        local[members] = np.arange(members.size)
        component_faces = local[level.faces[level.labels[level.faces[:, 0]] == label]]
        if members.size >= _MIN_COMPONENT and component_faces.shape[0]:
            kept, faces = _decimate_component(
                level.vertices[members], component_faces, ratio, threads
            )
        else:
            kept, faces = np.arange(members.size), component_faces
        remap = np.full(members.size, -1, dtype=np.int64)
        remap[kept] = np.arange(kept.size) + offset
        parents.append(members[kept])
        triangles.append(remap[faces])
        offset += kept.size
    return np.concatenate(parents), np.concatenate(triangles)


def _prolongation(fine: Level, vertices, faces, labels, threads: int):
    """Closest coarse triangle of every fine vertex (candidates: the coarse vertices of its
    own component nearest to it), and the 95th percentile of the distances."""
    from scipy.spatial import cKDTree

    count = fine.vertices.shape[0]
    near = np.empty((count, _CANDIDATES), dtype=np.int64)
    for label in np.unique(fine.labels):
        points = np.flatnonzero(fine.labels == label)
        coarse = np.flatnonzero(labels == label)
        k = min(_CANDIDATES, coarse.size)
        _, index = cKDTree(vertices[coarse]).query(fine.vertices[points], k=k, workers=threads)
        index = coarse[np.asarray(index).reshape(points.size, k)]
        near[points] = np.concatenate([index, np.repeat(index[:, :1], _CANDIDATES - k, 1)], 1)
    face, bary = _kernels.closest_triangles(fine.vertices, vertices, faces, near, threads)
    closest = np.einsum("ij,ijc->ic", bary, vertices[faces[face]])
    distance = np.linalg.norm(closest - fine.vertices, axis=1)
    return (face, bary), float(np.percentile(distance, 95)) if count else 0.0


def _mean_vertex_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    area = float(face_areas(torch.from_numpy(vertices), torch.from_numpy(faces)).sum())
    return area / max(vertices.shape[0], 1)


def build_pyramid(
    vertices: np.ndarray,
    faces: np.ndarray,
    ratio: float = 4.0,
    min_vertices: int = 1000,
    threads: int = 1,
) -> list[Level]:
    """Level 0 (the mesh) and coarser levels, each about ``ratio`` times smaller, until the
    next would have fewer than about ``min_vertices`` vertices or the decimation stalls.

    Args:
        vertices: ``(V, 3)`` float64, every vertex referenced by a face.
        faces: ``(F, 3)`` int64.
        ratio: vertex-count ratio between levels.
        min_vertices: size below which no coarser level is built.
        threads: threads for the nearest-vertex and closest-triangle queries.
    """
    labels = connected_components(
        vertices.shape[0], np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    )
    area = _mean_vertex_area(vertices, faces)
    levels = [Level(vertices, faces, np.arange(vertices.shape[0]), labels, None, 0.0, area)]
    while levels[-1].vertices.shape[0] > min_vertices * ratio / 2:
        above = levels[-1]
        parent, coarse_faces = _coarser(above, ratio, threads)
        if parent.size > 0.8 * above.vertices.shape[0]:
            break
        coarse_vertices = above.vertices[parent]
        coarse_labels = above.labels[parent]
        prolong, distance = _prolongation(
            above, coarse_vertices, coarse_faces, coarse_labels, threads
        )
        levels.append(
            Level(
                coarse_vertices,
                coarse_faces,
                above.vertex_ids[parent],
                coarse_labels,
                prolong,
                above.deviation + distance,
                _mean_vertex_area(coarse_vertices, coarse_faces),
            )
        )
    return levels


def level_times(levels: list[Level], times: list[float], resolution: float, fidelity: float):
    """The level of every scale ``t``: the coarsest whose mean vertex area is at most ``t /
    resolution`` and whose surface lies within ``fidelity sqrt(t)`` of the mesh (else 0)."""
    chosen = []
    for t in times:
        usable = [
            i
            for i, level in enumerate(levels)
            if resolution * level.mean_vertex_area <= t
            and level.deviation <= fidelity * math.sqrt(t)
        ]
        chosen.append(max(usable) if usable else 0)
    return chosen


class Interpolation:
    """A level's barycentric interpolation to the level above.

    Attributes:
        corners: ``(n_above, 3)`` int64 the corners of the closest triangle of every vertex
            of the level above.
        weights: ``(n_above, 3)`` float64 their barycentric weights.
    """

    def __init__(self, corners: Tensor, weights: Tensor):
        self.corners = corners
        self.weights = weights
        self._cache: dict = {}

    @classmethod
    def of(cls, level: Level) -> Interpolation:
        face, bary = level.prolong
        return cls(torch.from_numpy(level.faces[face]), torch.from_numpy(bary))

    def to(self, device) -> Interpolation:
        return Interpolation(self.corners.to(device), self.weights.to(device))

    def matrices(self, num_vertices: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """The ``(n_above, n)`` interpolation from ``n = num_vertices`` vertices and its
        transpose, ``torch.sparse_csr`` in ``dtype`` (built once per ``n`` and ``dtype``)."""
        key = (num_vertices, dtype)
        if key not in self._cache:
            above = self.corners.shape[0]
            if above and int(self.corners.max()) >= num_vertices:  # built unchecked below
                raise ValueError(
                    f"values of {num_vertices} vertices for an interpolation from a level of "
                    f"more than {int(self.corners.max())}"
                )
            corners, slot = self.corners.sort(dim=1)  # CSR columns ascend within a row
            weights = self.weights.gather(1, slot).to(dtype).reshape(-1)
            rows = torch.arange(above, device=corners.device).repeat_interleave(3)
            by_corner = torch.sort(corners.reshape(-1), stable=True)
            crow = torch.arange(0, 3 * above + 1, 3, device=corners.device)
            matrix = CSR(crow, corners.reshape(-1), weights, num_vertices)
            transpose = CSR(
                compress_rows(by_corner.values, num_vertices),
                rows[by_corner.indices],
                weights[by_corner.indices],
                above,
            )
            self._cache[key] = (
                matrix.to_sparse_csr(compact=True),
                transpose.to_sparse_csr(compact=True),
            )
        return self._cache[key]

    def __call__(self, values: Tensor) -> Tensor:
        """``(n_above, ...)`` from ``(n, ...)`` values (differentiable w.r.t. them)."""
        matrix, transpose = self.matrices(values.shape[0], values.dtype)
        flat = values.reshape(values.shape[0], -1)
        out = constant_matmul(matrix, transpose, flat)
        return out.reshape(self.corners.shape[0], *values.shape[1:])


class StateReader:
    """The checked reading of an untrusted state dict (names to tensors or numpy arrays)."""

    def __init__(self, state: Mapping):
        if not isinstance(state, Mapping):
            raise ValueError(f"a state dict is a mapping of names to tensors, not {type(state)}")
        self.state, self.unread = dict(state), set(state)

    def __contains__(self, name: str) -> bool:
        return name in self.state

    def get(self, name: str, dtype: torch.dtype, shape: tuple, low=None, high=None) -> Tensor:
        """``state[name]`` as a CPU tensor (a copy) of ``dtype`` and ``shape`` (``None``: any
        length), integers in ``[low, high)``, floats finite and above ``low``; else
        ``ValueError`` naming the entry."""
        if name not in self.state:
            raise ValueError(f"{name}: missing")
        self.unread.discard(name)
        value = self.state[name]
        try:
            if isinstance(value, Tensor):
                value = value.detach().to("cpu", copy=True)
            else:  # a copy: loaded arrays may be read-only or of the other byte order
                value = torch.from_numpy(np.array(value, copy=True))
        except (TypeError, ValueError, RuntimeError) as error:
            raise ValueError(f"{name}: not an array ({error})") from None
        if (
            value.layout != torch.strided
            or value.dtype != dtype
            or value.dim() != len(shape)
            or any(want not in (None, got) for want, got in zip(shape, value.shape, strict=True))
        ):
            raise ValueError(f"{name}: {value.dtype} {tuple(value.shape)}, not {dtype} {shape}")
        if value.numel() and value.is_floating_point():
            if not bool(torch.isfinite(value).all()) or (low is not None and value.min() <= low):
                raise ValueError(f"{name}: values not finite or not above {low}")
        elif value.numel() and (
            (low is not None and value.min() < low) or (high is not None and value.max() >= high)
        ):
            raise ValueError(f"{name}: indices outside [{low}, {high})")
        return value

    def count(self, name: str, high: int = 2**62) -> int:
        return int(self.get(name, torch.int64, (), 0, high))

    def check_all_read(self) -> None:
        """Refuse the entries never read."""
        if self.unread:
            raise ValueError(f"unknown entries: {sorted(map(str, self.unread))}")


@dataclass
class StructureLevel:
    """One pyramid level of a :class:`RobustStructure`, as tensors on its device.

    Attributes:
        vertex_ids: ``(n,)`` int64 the level's vertices among the mesh's referenced ones.
        faces: ``(m, 3)`` int64 its triangles (level numbering).
        labels: ``(n,)`` int64 the connected component of every vertex.
        prolongation: its ``Interpolation`` to the level above (``None`` on level 0).
        semigroup: its :class:`~stochlap_torch.robust.heat.LevelSemigroup` if a scale runs
            on it, else ``None``.
    """

    vertex_ids: Tensor
    faces: Tensor
    labels: Tensor
    prolongation: Interpolation | None = None
    semigroup: LevelSemigroup | None = None

    @property
    def num_vertices(self) -> int:
        return int(self.vertex_ids.shape[0])

    def state_dict(self, prefix: str) -> dict[str, Tensor]:
        """Its entries of :meth:`~stochlap_torch.robust.RobustStructure.state_dict`."""
        state = {"vertex_ids": self.vertex_ids, "faces": self.faces, "labels": self.labels}
        if self.prolongation is not None:
            state |= {"corners": self.prolongation.corners, "weights": self.prolongation.weights}
        state = {prefix + name: value for name, value in state.items()}
        return state | ({} if self.semigroup is None else self.semigroup.state_dict(prefix))

    @classmethod
    def from_state(cls, reader: StateReader, prefix: str, size: int, above: int | None):
        """The level of :meth:`state_dict`'s entries, checked: some of the mesh's ``size``
        referenced vertices, interpolated to the ``above`` vertices of the level above
        (``None``: level 0)."""
        ids = reader.get(prefix + "vertex_ids", torch.int64, (None,), 0, size)
        n = ids.numel()
        faces = reader.get(prefix + "faces", torch.int64, (None, 3), 0, n)
        labels = reader.get(prefix + "labels", torch.int64, (n,), 0, n)
        prolongation = None
        if above is not None:
            weights = reader.get(prefix + "weights", torch.float64, (above, 3))
            if weights.numel() and (
                float(weights.min()) < 0.0
                or float(weights.max()) > 1.0 + 1e-9
                or float((weights.sum(dim=1) - 1.0).abs().max()) > 1e-9
            ):
                raise ValueError(f"{prefix}weights: not barycentric")
            corners = reader.get(prefix + "corners", torch.int64, (above, 3), 0, n)
            prolongation = Interpolation(corners, weights)
        return cls(ids, faces, labels, prolongation, LevelSemigroup.from_state(reader, prefix, n))

    def to(self, device) -> StructureLevel:
        return StructureLevel(
            self.vertex_ids.to(device),
            self.faces.to(device),
            self.labels.to(device),
            None if self.prolongation is None else self.prolongation.to(device),
            None if self.semigroup is None else self.semigroup.to(device),
        )


def canonical_faces(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F, 3)`` the faces wound one way (:func:`~stochlap_torch.mesh.geometry.orient_faces`;
    consistently outward ones unchanged): the decimation follows the winding, which says
    nothing about the shape. A flat patch is wound by a rank of its vertices that neither a
    renumbering nor a rigid motion changes (distance to the centroid, then principal axes).
    """
    array = vertices.detach().numpy()
    centred = array - array.mean(axis=0)
    largest = float(np.abs(centred).max(initial=0.0))
    if largest > 0.0:  # a power of two: exact, and float32 neither overflows nor underflows
        centred = centred * 2.0 ** -math.floor(math.log2(largest))
    frame = _principal_frame(centred).astype(np.float32)
    distance = np.einsum("ij,ij->i", centred, centred).astype(np.float32)
    order = np.lexsort((np.abs(frame[:, 0]), frame[:, 1], frame[:, 2], distance))
    rank = np.empty(array.shape[0], dtype=np.int64)
    rank[order] = np.arange(array.shape[0])
    return torch.from_numpy(orient_faces(array, faces.numpy(), rank))


def _principal_frame(points: np.ndarray) -> np.ndarray:
    """``(V, 3)`` centred points in the frame of their principal axes, each signed so that the
    third moment along it is positive: the decimation rounds to float32 and breaks ties by
    coordinates, and in this frame every rotation of a mesh gives it the same numbers."""
    _, axes = np.linalg.eigh(points.T @ points)
    projected = points @ axes
    signs = np.where(np.sum(projected**3, axis=0) < 0.0, -1.0, 1.0)
    return projected * signs


def structure_levels(
    unit: np.ndarray, faces: Tensor, params: RobustParams, heat: bool
) -> tuple[list[StructureLevel], list[int], Tensor | None]:
    """The pyramid of a mesh at unit area (``(U, 3)`` float64, centred) and its
    :func:`canonical_faces` ``(F, 3)``, as the robust structure holds it: ``(levels, the
    level of every scale, the (U, H) float64 heat channel or None if not heat)``."""
    times = params.times
    largest_level = max(params.min_vertices, int(params.resolution / max(times) * 1.2))
    pyramid = build_pyramid(
        _principal_frame(unit), faces.numpy(), params.ratio, largest_level, torch.get_num_threads()
    )
    assignment = level_times(pyramid, times, params.resolution, params.fidelity)

    def operator(index: int):
        level = pyramid[index]
        return heat_operator(level.vertices, level.faces, params.cap, params.clamp)

    operators = {index: operator(index) for index in sorted(set(assignment))}
    levels = [
        StructureLevel(
            torch.from_numpy(level.vertex_ids),
            torch.from_numpy(level.faces),
            torch.from_numpy(level.labels),
            Interpolation.of(level) if index else None,
            LevelSemigroup.of(operators[index]) if index in operators else None,
        )
        for index, level in enumerate(pyramid)
    ]
    values = None
    if heat:
        heat_times = np.array([times[k] for k in params.heat_scales])
        values = torch.zeros(unit.shape[0], heat_times.size, dtype=torch.float64)
        if heat_times.size:
            index = level_times(
                pyramid, [float(heat_times[0])], params.heat_resolution, params.fidelity
            )[0]
            values = torch.from_numpy(
                heat_diagonal(operators.get(index) or operator(index), heat_times)
            )
            for coarse in range(index, 0, -1):  # interpolated to the mesh
                values = levels[coarse].prolongation(values)
    return levels, assignment, values
