"""The discretization-robust multiscale representation (``variant="robust"``).

Scale ``k`` is a physical diffusion time ``t_k = t_0 2^k A`` (``A`` the surface area), not a
number of steps, and diffusion is the heat semigroup of an intrinsic-Delaunay Laplacian with
lumped areas (:mod:`stochlap_torch.operators.heat`), so a scale covers the same surface on any
triangulation. Large times run on coarser copies of the mesh (:mod:`stochlap_torch.operators.
pyramid`): scale ``t`` goes to the coarsest level whose mean vertex area is at most
``t / resolution`` and whose surface lies within ``fidelity sqrt(t)`` of the mesh; there the
semigroup (:mod:`.heat`) diffuses twelve fields (the positions, their products and the normal)
to all the level's scales at once, and the channels are brought back to the mesh by
barycentric interpolation. The cost is linear in the number of vertices.

Channels, per scale, all dimensionless and invariant to rigid motion and uniform scaling:

* ``dn``: ``(P - F_t P) . n_t / sqrt(t)``, the normal displacement in units of the scale (a
  multiscale mean curvature, ``~ 2 H sqrt(t)``; ``n_t`` the diffused outward normal);
* ``spread``: the eigenvalues of ``F_t[P P^T] - F_t[P] F_t[P]^T`` over ``2 t`` (where heat from
  a vertex spreads to; ``(1, 1, 0)`` on a plane);
* ``heat``: ``log(4 pi t h_t(i, i))`` at the largest scales, the heat kernel diagonal (an HKS
  without the eigendecomposition of the mesh: it is taken on a coarse level).

Gradients reach the vertices through the fields and the channels, with the operators, the
pyramid and the interpolation weights held constant (as the paper mode holds ``F^(k)``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from .._common.checks import check_int, check_number
from .._common.threads import worker_threads
from ..mesh import face_areas, outward_sign, vertex_normals
from ..operators.heat import DEFAULT_CAP, HeatOperator, heat_operator
from ..operators.pyramid import Level, build_pyramid
from ..sparse import CSR, spmm
from .heat import DEFAULT_TOLERANCE, HeatSemigroup
from .parameters import ProgressCallback

__all__ = [
    "RobustChannels",
    "RobustParams",
    "RobustStructure",
    "level_times",
    "robust_channels",
    "robust_structure",
]


@dataclass(frozen=True)
class RobustParams:
    """The robust variant's settings (defaults measured in ``benchmarks/robust.py``).

    Attributes:
        num_scales: scales ``t_k = t0 2^k A``, ``k = 0..num_scales-1``.
        t0: the finest scale, as a fraction of the surface area ``A``.
        resolution: a level carries scale ``t`` if its mean vertex area is ``<= t /
            resolution`` (a scale spans at least this many vertices).
        fidelity: ... and if its surface is within ``fidelity sqrt(t)`` of the mesh.
        ratio: vertex-count ratio between pyramid levels.
        min_vertices: no pyramid level smaller than about this.
        cap: mass cap of the heat operator (:func:`~stochlap_torch.operators.heat.capped_mass`).
        tolerance: Chebyshev truncation of the semigroup.
        heat_from: the ``heat`` channel is computed for scales ``t >= heat_from A``.
        heat_resolution: vertex areas per scale the ``heat`` channel's level must resolve.
    """

    num_scales: int = 7
    t0: float = 1e-3
    resolution: float = 8.0
    fidelity: float = 0.1
    ratio: float = 4.0
    min_vertices: int = 1000
    cap: float = DEFAULT_CAP
    tolerance: float = DEFAULT_TOLERANCE
    heat_from: float = 0.032
    heat_resolution: float = 16.0

    def __post_init__(self) -> None:
        check_int("num_scales", self.num_scales, minimum=1, maximum=16)
        for name in ("t0", "resolution", "fidelity", "cap", "tolerance", "heat_from"):
            check_number(name, getattr(self, name), 0.0, None, open_low=True)
        check_number("ratio", self.ratio, 1.0, None, open_low=True)
        check_int("min_vertices", self.min_vertices, minimum=4)

    @property
    def times(self) -> list[float]:
        """The scales ``t_k / A``."""
        return [self.t0 * 2.0**k for k in range(self.num_scales)]


@dataclass
class RobustChannels:
    """Per-scale channels on the vertices of one mesh (every vertex referenced by a face).

    Attributes:
        dn: ``(V, T)`` normal displacement over ``sqrt(t)``.
        spread: ``(V, T, 3)`` ascending eigenvalues of the spread over ``2 t``.
        heat: ``(V, H)`` log heat kernel diagonal at the ``H`` largest scales (``t >=
            heat_from``).
        mass: ``(V,)`` lumped vertex areas of the mesh at unit total area.
        levels: vertex count of every pyramid level.
        assignment: the level of every scale.
    """

    dn: Tensor
    spread: Tensor
    heat: Tensor
    mass: Tensor
    levels: list[int] = field(default_factory=list)
    assignment: list[int] = field(default_factory=list)


def level_times(levels: list[Level], times: list[float], resolution: float, fidelity: float):
    """The level of every scale: the coarsest that resolves it (see the module docstring);
    level 0 when none does. Times and areas are in units of the total area."""
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


def _fields(points: Tensor, faces: Tensor, labels: Tensor) -> Tensor:
    """``(n, 12)``: centred positions, their six products and the outward normal."""
    centred = points - points.detach().mean(dim=0)
    x, y, z = centred.unbind(dim=1)
    normals = vertex_normals(points, faces) * outward_sign(points, faces, labels)[:, None]
    return torch.stack([x, y, z, x * x, y * y, z * z, x * y, y * z, z * x, *normals.unbind(1)], 1)


def _level_channels(points: Tensor, level: Level, operator: HeatOperator, times: list[float],
                    tolerance: float):  # fmt: skip
    """``(dn (n, T), spread (n, T, 3))`` on the vertices of one level."""
    faces = torch.from_numpy(level.faces)
    labels = torch.from_numpy(level.labels)
    fields = _fields(points, faces, labels)
    diffused = HeatSemigroup.apply(fields, operator, tuple(times), tolerance)
    centred = points - points.detach().mean(dim=0)
    dn, spread = [], []
    for index, t in enumerate(times):
        out = diffused[index]
        mean = out[:, :3]
        normal = out[:, 9:12]
        normal = normal / normal.norm(dim=1, keepdim=True).clamp_min(1e-30)
        dn.append(((centred - mean) * normal).sum(dim=1) / math.sqrt(t))
        xx, yy, zz, xy, yz, zx = (out[:, 3 + c] for c in range(6))
        mx, my, mz = mean.unbind(dim=1)
        covariance = torch.stack(
            [
                torch.stack([xx - mx * mx, xy - mx * my, zx - mz * mx], dim=1),
                torch.stack([xy - mx * my, yy - my * my, yz - my * mz], dim=1),
                torch.stack([zx - mz * mx, yz - my * mz, zz - mz * mz], dim=1),
            ],
            dim=1,
        )
        spread.append(torch.linalg.eigvalsh(covariance) / (2.0 * t))
    return torch.stack(dn, dim=1), torch.stack(spread, dim=1)


def _prolongation(level: Level, num_coarse: int) -> CSR:
    """``(n_above, n)`` CSR of a level's barycentric interpolation to the level above."""
    face, bary = level.prolong
    rows = torch.arange(face.shape[0]).repeat_interleave(3)
    cols = torch.from_numpy(level.faces[face].reshape(-1))
    order = torch.argsort(rows * num_coarse + cols)
    crow = torch.arange(0, 3 * face.shape[0] + 1, 3)
    weights = torch.from_numpy(bary.reshape(-1))[order]
    return CSR(crow, cols[order], weights, num_coarse)


def _prolong(structure: RobustStructure, level: int, values: Tensor) -> Tensor:
    """Values on level ``level`` interpolated to level 0 (weights held fixed)."""
    for index in range(level, 0, -1):
        matrix = structure.prolongations[index]
        flat = values.reshape(values.shape[0], -1)
        values = spmm(matrix.with_values(matrix.val.to(values.dtype)), flat).reshape(
            matrix.num_rows, *values.shape[1:]
        )
    return values


def _heat_diagonal(level: Level, times: np.ndarray, params: RobustParams) -> np.ndarray:
    """``(n, H)`` ``log(4 pi t h_t(i, i))`` on a coarse level, from its eigenpairs.

    The dense case runs in torch, not scipy: torch's LAPACK follows the calling thread's
    setting (one thread inside a library call, :mod:`stochlap_torch._common.threads`) where
    OpenBLAS's own threads, fighting the kernels' for two cores, made this 750-vertex
    ``eigh`` take 0.3 to 4.5 s.
    """
    from scipy.sparse.linalg import eigsh

    operator = heat_operator(level.vertices, level.faces, params.cap)
    mass = operator.capped_mass
    scale = 1.0 / np.sqrt(mass)
    if operator.num_vertices <= 2500:
        symmetric = scale[:, None] * operator.laplacian.toarray() * scale[None, :]
        values, basis = torch.linalg.eigh(torch.from_numpy(0.5 * (symmetric + symmetric.T)))
    else:
        from scipy import sparse

        symmetric = (sparse.diags(scale) @ operator.laplacian @ sparse.diags(scale)).tocsc()
        shift = -1e-6 * float(np.mean(operator.laplacian.diagonal() / mass))
        count = min(200, operator.num_vertices - 2)
        pairs = eigsh(symmetric, k=count, sigma=shift, which="LM")
        values, basis = (torch.from_numpy(a) for a in pairs)
    decay = torch.exp(-values.clamp_min(0.0)[:, None] * torch.from_numpy(times)[None, :])
    diagonal = (basis.square() @ decay).numpy() / mass[:, None]
    return np.log(np.maximum(4.0 * math.pi * times[None, :] * diagonal, 1e-300))


def _unit_area(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V, 3)`` the mesh centred and scaled to unit area. The centre and the area's value
    come from numpy (the same on any thread count: the pyramid's discrete choices must not
    depend on the rounding of a parallel sum); the area's gradient from torch."""
    array = vertices.detach().numpy()
    corners = array[faces.numpy()]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area_value = 0.5 * float(np.sqrt(np.einsum("ij,ij->i", cross, cross)).sum())
    area = face_areas(vertices, faces).sum()
    area = area - area.detach() + area_value  # the value from numpy, the gradient from torch
    centre = torch.from_numpy(array.mean(axis=0))
    return (vertices - centre) / area.sqrt()


@dataclass
class RobustStructure:
    """What the robust channels of a mesh need besides its positions, built once from them
    and then held constant (gradients do not flow through it).

    Attributes:
        levels: the pyramid (:func:`~stochlap_torch.operators.pyramid.build_pyramid`).
        prolongations: per level, its interpolation to the level above (``None`` on level 0).
        assignment: the level of every scale.
        operators: the heat operator of every level a scale runs on.
        heat: ``(V, H)`` log heat kernel diagonal at the scales ``t >= heat_from``.
    """

    levels: list[Level]
    prolongations: list[CSR | None]
    assignment: list[int]
    operators: dict[int, HeatOperator]
    heat: Tensor


def robust_structure(vertices: Tensor, faces: Tensor, params: RobustParams) -> RobustStructure:
    """The :class:`RobustStructure` of a mesh (every vertex referenced by a face)."""
    fine = _unit_area(vertices.detach().double(), faces).numpy()
    times = params.times
    largest_level = max(params.min_vertices, int(params.resolution / max(times) * 1.2))
    levels = build_pyramid(fine, faces.numpy(), params.ratio, largest_level, worker_threads())
    prolongations = [None] + [
        _prolongation(levels[i], levels[i].vertices.shape[0]) for i in range(1, len(levels))
    ]
    assignment = level_times(levels, times, params.resolution, params.fidelity)
    operators = {
        index: heat_operator(levels[index].vertices, levels[index].faces, params.cap)
        for index in sorted(set(assignment))
    }
    structure = RobustStructure(levels, prolongations, assignment, operators, torch.zeros(0))
    heat_times = np.array([t for t in times if t >= params.heat_from])
    structure.heat = torch.zeros(fine.shape[0], heat_times.size, dtype=torch.float64)
    if heat_times.size:
        index = level_times(levels, [float(heat_times[0])], params.heat_resolution,
                            params.fidelity)[0]  # fmt: skip
        values = torch.from_numpy(_heat_diagonal(levels[index], heat_times, params))
        structure.heat = _prolong(structure, index, values)
    return structure


def robust_channels(
    vertices: Tensor,
    faces: Tensor,
    params: RobustParams,
    structure: RobustStructure | None = None,
    progress: ProgressCallback | None = None,
) -> RobustChannels:
    """The channels of one mesh whose every vertex is referenced by a face (float64 inside).

    Args:
        vertices: ``(V, 3)`` float64, may carry gradients.
        faces: ``(F, 3)`` int64.
        params: :class:`RobustParams`.
        structure: the pyramid and operators (default: built from ``vertices``); pass one
            built from other positions to differentiate with them held fixed.
        progress: called as ``progress(k, T)`` when the first ``k`` of the ``T`` scales are done
            (a level's scales at once).
    """
    if structure is None:
        structure = robust_structure(vertices, faces, params)
    points = _unit_area(vertices, faces)
    times = params.times
    dn = points.new_zeros(points.shape[0], len(times))
    spread = points.new_zeros(points.shape[0], len(times), 3)
    for index, operator in structure.operators.items():
        scales = [k for k, level in enumerate(structure.assignment) if level == index]
        level = structure.levels[index]
        level_points = points[torch.from_numpy(level.vertex_ids)]
        level_dn, level_spread = _level_channels(
            level_points, level, operator, [times[k] for k in scales], params.tolerance
        )
        dn[:, scales] = _prolong(structure, index, level_dn)
        spread[:, scales] = _prolong(structure, index, level_spread)
        if progress is not None:
            progress(max(scales) + 1, len(times))
    mass = torch.zeros_like(points[:, 0]).index_add_(
        0, faces.reshape(-1), (face_areas(points.detach(), faces) / 3.0).repeat_interleave(3)
    )
    levels = [level.vertices.shape[0] for level in structure.levels]
    return RobustChannels(dn, spread, structure.heat.to(points.dtype), mass, levels,
                          structure.assignment)  # fmt: skip
