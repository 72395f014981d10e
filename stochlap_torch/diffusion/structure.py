"""The robust variant's structure (:class:`RobustStructure`): what the channels of a mesh need
besides its positions, as tensors on one device, and its form as named numpy arrays for a
:class:`~stochlap_torch.learning.MeshCache` (:func:`structure_arrays`, read back and checked
array by array by :func:`structure_from_arrays`: nothing loaded is trusted). Built by
:func:`~stochlap_torch.diffusion.robust.build_structure`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import Tensor

from ..operators.pyramid import Level
from ..params import RobustParams, resolve_params
from ..sparse.autograd import constant_matmul
from ..sparse.csr import CSR, compress_rows
from .semigroup import LevelSemigroup

__all__ = [
    "Interpolation",
    "RobustParams",
    "RobustStructure",
    "StructureLevel",
    "as_robust_params",
    "structure_arrays",
    "structure_from_arrays",
]


def as_robust_params(value, num_scales: int | None = None) -> RobustParams:
    """``value`` (``None``, a :class:`RobustParams` or a mapping of its fields) as
    :class:`RobustParams`, ``num_scales`` replacing its field when given."""
    return resolve_params(RobustParams, "robust", {"robust": value, "num_scales": num_scales})


class Interpolation:
    """A level's barycentric interpolation to the level above (weights held fixed).

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

    def __getstate__(self) -> dict:
        return {"corners": self.corners, "weights": self.weights}  # the matrices: rebuilt

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["corners"], state["weights"])

    def matrices(self, num_vertices: int, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
        """``(n_above, n)`` the interpolation as a ``torch.sparse_csr`` matrix (int32
        indices) from a level of ``n = num_vertices``, and its ``(n, n_above)`` transpose,
        in ``dtype`` on the device (built once per ``n`` and ``dtype``): one sparse product
        in place of three gathers of every column."""
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


@dataclass
class StructureLevel:
    """One pyramid level of a :class:`RobustStructure`, as tensors on its device.

    Attributes:
        vertex_ids: ``(n,)`` int64 the level's vertices among the mesh's referenced ones.
        faces: ``(m, 3)`` int64 its triangles (level numbering).
        labels: ``(n,)`` int64 the connected component of every vertex.
        mean_vertex_area: total area over vertex count, at unit total area.
        prolongation: its ``Interpolation`` to the level above (``None`` on level 0).
        semigroup: its ``semigroup.LevelSemigroup`` if a scale runs on it, else
            ``None``.
    """

    vertex_ids: Tensor
    faces: Tensor
    labels: Tensor
    mean_vertex_area: float
    prolongation: Interpolation | None = None
    semigroup: LevelSemigroup | None = None

    @property
    def num_vertices(self) -> int:
        return int(self.vertex_ids.shape[0])

    def to(self, device) -> StructureLevel:
        return StructureLevel(
            self.vertex_ids.to(device),
            self.faces.to(device),
            self.labels.to(device),
            self.mean_vertex_area,
            None if self.prolongation is None else self.prolongation.to(device),
            None if self.semigroup is None else self.semigroup.to(device),
        )


@dataclass
class RobustStructure:
    """What the robust channels of one mesh need besides its positions: built once from them
    (:func:`~stochlap_torch.robust_structure`, on the CPU) and then held constant,
    reused by every call on the same mesh (``structure=``). Gradients do not flow through it.

    Everything in it is a tensor (the operators ``torch.sparse_csr``) on one device, moved by
    :meth:`to`; it pickles, and :meth:`to_arrays` / :meth:`from_arrays` store it in a
    :class:`~stochlap_torch.learning.MeshCache`. A call checks that it fits: the vertex and
    face counts and the settings must be the call's.

    Attributes:
        params: the :class:`RobustParams` it was built for.
        num_vertices: ``V``, the mesh's vertices (those no face uses included).
        num_faces: ``F``.
        used: ``(U,)`` int64 the vertices faces use, ascending.
        faces: ``(F, 3)`` int64 the faces among ``used``, wound one way
            (``mesh.surface.orient_faces``).
        levels: the pyramid, level 0 the mesh (:class:`StructureLevel`); empty without faces.
        assignment: the level of every scale.
        heat: ``(U, H)`` float64 log heat kernel diagonal at the scales ``t >= heat_from``
            (the one part computed from eigenpairs, in float64 on a small level); ``None`` if
            built without it (the saliency does not need it).
    """

    params: RobustParams
    num_vertices: int
    num_faces: int
    used: Tensor
    faces: Tensor
    levels: list[StructureLevel]
    assignment: list[int]
    heat: Tensor | None

    @property
    def device(self) -> torch.device:
        return self.used.device

    def to(self, device) -> RobustStructure:
        """This structure with every tensor on ``device`` (itself if already there)."""
        device = torch.device(device)
        if device == self.device:
            return self
        return dataclasses.replace(
            self,
            used=self.used.to(device),
            faces=self.faces.to(device),
            levels=[level.to(device) for level in self.levels],
            heat=None if self.heat is None else self.heat.to(device),
        )

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The structure as named numpy arrays (:meth:`from_arrays` reads them back)."""
        return structure_arrays(self)

    @classmethod
    def from_arrays(cls, arrays, params: RobustParams) -> RobustStructure:
        """The structure of :meth:`to_arrays`' arrays (numpy arrays or CPU tensors).

        Raises:
            ValueError: the arrays are not a structure's (missing, of the wrong shape or
                dtype, indices out of range, values not finite).
        """
        return structure_from_arrays(arrays, params)

    def __repr__(self) -> str:
        sizes = [level.num_vertices for level in self.levels]
        return (
            f"RobustStructure(num_vertices={self.num_vertices}, num_faces={self.num_faces}, "
            f"levels={sizes}, assignment={self.assignment}, heat={self.heat is not None}, "
            f"device={self.device}, params={self.params!r})"
        )


def _params_array(params: RobustParams) -> np.ndarray:
    """``(P,)`` float64 every field of ``params`` in field order (numbers all: an array the
    cache stores like the others, compared exactly)."""
    return np.array([float(getattr(params, f.name)) for f in fields(RobustParams)])


def structure_arrays(structure: RobustStructure) -> dict[str, np.ndarray]:
    """:meth:`RobustStructure.to_arrays`: flat named arrays (``level{i}_...`` per level)."""

    def array(tensor: Tensor) -> np.ndarray:
        return tensor.detach().cpu().numpy().copy()  # not a view of the live structure

    arrays = {
        "params": _params_array(structure.params),
        "num_vertices": np.array(structure.num_vertices, dtype=np.int64),
        "num_faces": np.array(structure.num_faces, dtype=np.int64),
        "used": array(structure.used),
        "faces": array(structure.faces),
        "assignment": np.array(structure.assignment, dtype=np.int64),
        "num_levels": np.array(len(structure.levels), dtype=np.int64),
    }
    if structure.heat is not None:
        arrays["heat"] = array(structure.heat)
    for index, level in enumerate(structure.levels):
        name = f"level{index}_"
        arrays[name + "vertex_ids"] = array(level.vertex_ids)
        arrays[name + "faces"] = array(level.faces)
        arrays[name + "labels"] = array(level.labels)
        arrays[name + "mean_vertex_area"] = np.array(level.mean_vertex_area)
        if level.prolongation is not None:
            arrays[name + "corners"] = array(level.prolongation.corners)
            arrays[name + "weights"] = array(level.prolongation.weights)
        if level.semigroup is not None:
            matrix = level.semigroup.recurrence
            arrays[name + "crow"] = array(matrix.crow_indices()).astype(np.int64)
            arrays[name + "col"] = array(matrix.col_indices()).astype(np.int64)
            arrays[name + "val"] = array(matrix.values())
            arrays[name + "order"] = array(level.semigroup.order)
            arrays[name + "capped_mass"] = array(level.semigroup.capped_mass)
            arrays[name + "bound"] = np.array(level.semigroup.bound)
    return arrays


def _checked(arrays, name: str, dtype, shape: tuple, low=None, high=None) -> Tensor:
    """``arrays[name]`` as a tensor, after checking its dtype, shape (``None``: any length)
    and range (``[low, high)`` for integers, finite and ``>= low`` for floats)."""
    value = np.asarray(arrays[name])
    if (
        value.dtype != dtype
        or value.ndim != len(shape)
        or any(
            want is not None and want != got for want, got in zip(shape, value.shape, strict=True)
        )
    ):
        raise ValueError(f"{name}: {value.dtype} {value.shape}, expected {np.dtype(dtype)} {shape}")
    if value.size and np.issubdtype(value.dtype, np.floating):
        if not np.isfinite(value).all() or (low is not None and value.min() < low):
            raise ValueError(f"{name}: values not finite or below {low}")
    elif value.size and (
        (low is not None and value.min() < low) or (high is not None and value.max() >= high)
    ):
        raise ValueError(f"{name}: indices outside [{low}, {high})")
    return torch.from_numpy(np.array(value))


def structure_from_arrays(arrays, params: RobustParams) -> RobustStructure:
    """:meth:`RobustStructure.from_arrays` (checks every array, see there)."""
    arrays = {name: np.asarray(value) for name, value in arrays.items()}
    stored = arrays.get("params")
    if stored is None or not np.array_equal(np.asarray(stored), _params_array(params)):
        raise ValueError(f"built with other settings, not {params!r}")
    count = int(_checked(arrays, "num_vertices", np.int64, (), 0))
    num_faces = int(_checked(arrays, "num_faces", np.int64, (), 0))
    used = _checked(arrays, "used", np.int64, (None,), 0, count)
    size = used.numel()
    if size > 1 and bool((used.diff() <= 0).any()):
        raise ValueError("used: not strictly ascending")
    faces = _checked(arrays, "faces", np.int64, (num_faces, 3), 0, max(size, 1))
    num_levels = int(_checked(arrays, "num_levels", np.int64, (), 0, 64))
    assignment = _checked(arrays, "assignment", np.int64, (None,), 0, max(num_levels, 1))
    if num_levels and assignment.numel() != params.num_scales:
        raise ValueError(f"assignment of {assignment.numel()} scales for {params.num_scales}")
    heat = None
    if "heat" in arrays:
        heat = _checked(arrays, "heat", np.float64, (size, None))
    levels, above = [], size
    for index in range(num_levels):
        name = f"level{index}_"
        ids = _checked(arrays, name + "vertex_ids", np.int64, (None,), 0, size)
        n = ids.numel()
        level_faces = _checked(arrays, name + "faces", np.int64, (None, 3), 0, max(n, 1))
        if index == 0 and not (
            torch.equal(ids, torch.arange(size)) and torch.equal(level_faces, faces)
        ):
            raise ValueError("level0: not the mesh itself")
        labels = _checked(arrays, name + "labels", np.int64, (n,), 0, max(n, 1))
        area = float(_checked(arrays, name + "mean_vertex_area", np.float64, (), 0.0))
        if not area > 0.0:
            raise ValueError(f"{name}mean_vertex_area: not positive")
        prolongation = None
        if index:
            weights = _checked(arrays, name + "weights", np.float64, (above, 3), 0.0)
            # Barycentric: in [0, 1], each row summing to 1.
            if weights.numel() and (
                float(weights.max()) > 1.0 + 1e-9
                or float((weights.sum(dim=1) - 1.0).abs().max()) > 1e-9
            ):
                raise ValueError(f"{name}weights: not barycentric")
            prolongation = Interpolation(
                _checked(arrays, name + "corners", np.int64, (above, 3), 0, max(n, 1)), weights
            )
        semigroup = None
        if name + "crow" in arrays:
            crow = _checked(arrays, name + "crow", np.int64, (n + 1,), 0)
            col = _checked(arrays, name + "col", np.int64, (None,), 0, max(n, 1))
            val = _checked(arrays, name + "val", np.float64, (col.numel(),))
            if crow[0] != 0 or crow[-1] != col.numel() or bool((crow.diff() < 0).any()):
                raise ValueError(f"{name}crow: not a CSR's row pointers")
            order = _checked(arrays, name + "order", np.int64, (n,), 0, max(n, 1))
            if not torch.equal(torch.sort(order).values, torch.arange(n)):
                raise ValueError(f"{name}order: not a permutation")
            mass = _checked(arrays, name + "capped_mass", np.float64, (n,), 0.0)
            bound = float(_checked(arrays, name + "bound", np.float64, (), 0.0))
            if (mass.numel() and not float(mass.min()) > 0.0) or not bound > 0.0:
                raise ValueError(f"{name}capped_mass, bound: not positive")
            matrix = CSR(crow, col, val, n).to_sparse_csr(compact=True)
            semigroup = LevelSemigroup(matrix, order, mass, bound)
        levels.append(StructureLevel(ids, level_faces, labels, area, prolongation, semigroup))
        above = n
    assignment = [int(value) for value in assignment]
    if any(levels[index].semigroup is None for index in assignment):
        raise ValueError("a scale runs on a level without an operator")
    return RobustStructure(params, count, num_faces, used, faces, levels, assignment, heat)
