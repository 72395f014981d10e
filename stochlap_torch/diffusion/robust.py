"""The discretization-robust multiscale representation (``variant="robust"``).

Scale ``k`` is a physical diffusion time ``t_k = t_0 2^k A`` (``A`` the surface area), not a
number of steps, and diffusion is the heat semigroup of an intrinsic-Delaunay Laplacian with
lumped areas (:mod:`stochlap_torch.operators.heat_operator`), so a scale covers the same
surface on any triangulation. Large times run on coarser copies of the mesh
(:mod:`stochlap_torch.operators.pyramid`): scale ``t`` goes to the coarsest level whose mean
vertex area is at most ``t / resolution`` and whose surface lies within ``fidelity sqrt(t)``
of the mesh; there the semigroup (:mod:`.semigroup`) diffuses nine fields (the positions and
their products; three for the saliency, which needs ``dn`` alone) to all the level's scales at
once, and the channels are brought back to the mesh by barycentric interpolation. The cost is
linear in the number of vertices.

Channels, per scale, all dimensionless and invariant to rigid motion and uniform scaling:

* ``dn``: ``(P - F_t P) . n / sqrt(t)``, the normal displacement in units of the scale (a
  multiscale mean curvature, ``~ 2 H sqrt(t)``; ``n`` the outward normal of the scale's level,
  smoothed over about one ring: ``normal_time``);
* ``spread``: the eigenvalues of ``F_t[P P^T] - F_t[P] F_t[P]^T`` over ``2 t`` (where heat from
  a vertex spreads to; ``(1, 1, 0)`` on a plane);
* ``heat``: ``log(4 pi t h_t(i, i))`` at the largest scales, the heat kernel diagonal (an HKS
  without the eigendecomposition of the mesh: it is taken on a coarse level).

Gradients reach the vertices through the fields and the channels, with the operators, the
pyramid and the interpolation weights held constant (as the paper mode holds ``F^(k)``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from .._common.checks import check_int, check_number
from .._common.errors import ParameterError
from .._common.threads import worker_threads
from .._common.variants import ROBUST_NUM_SCALES
from ..mesh import face_areas, outward_sign, vertex_normals
from ..mesh.surface import check_not_soup, orient_faces
from ..operators.heat_operator import DEFAULT_CAP, DEFAULT_CLAMP, HeatOperator, heat_operator
from ..operators.pyramid import Level, build_pyramid
from .parameters import ProgressCallback
from .semigroup import DEFAULT_TOLERANCE, HeatSemigroup, heat_diagonal

__all__ = [
    "RobustChannels",
    "RobustParams",
    "RobustStructure",
    "as_robust_params",
    "level_times",
    "robust_channels",
    "robust_structure",
]


#: The settings of :class:`RobustParams` that must be positive numbers.
_POSITIVE_FIELDS = (
    "t0",
    "resolution",
    "fidelity",
    "cap",
    "clamp",
    "tolerance",
    "heat_from",
    "heat_resolution",
)


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
        cap: mass cap of the heat operator
            (:func:`~stochlap_torch.operators.heat_operator.capped_mass`).
        clamp: largest edge rate of the heat operator, in median rates, applied before the
            mass cap (:func:`~stochlap_torch.operators.heat_operator.clamped_weights`).
        tolerance: Chebyshev truncation of the semigroup.
        heat_from: the ``heat`` channel is computed for scales ``t >= heat_from A``.
        heat_resolution: vertex areas per scale the ``heat`` channel's level must resolve.
        normal_time: ``dn``'s normal is the level's outward vertex normal diffused for this
            many of the level's mean vertex areas (about one ring; chosen among 0, 1, 2 and 8
            in ``benchmarks/robust.py``).
    """

    num_scales: int = ROBUST_NUM_SCALES
    t0: float = 1e-3
    resolution: float = 8.0
    fidelity: float = 0.1
    ratio: float = 4.0
    min_vertices: int = 1000
    cap: float = DEFAULT_CAP
    clamp: float = DEFAULT_CLAMP
    tolerance: float = DEFAULT_TOLERANCE
    heat_from: float = 0.032
    heat_resolution: float = 16.0
    normal_time: float = 1.0

    def __post_init__(self) -> None:
        checked = {
            "num_scales": check_int("num_scales", self.num_scales, minimum=1, maximum=16),
            "min_vertices": check_int("min_vertices", self.min_vertices, minimum=4),
            "normal_time": check_number("normal_time", self.normal_time, 0.0, None),
            "ratio": check_number("ratio", self.ratio, 1.0, None, open_low=True),
        }
        for name in _POSITIVE_FIELDS:
            checked[name] = check_number(name, getattr(self, name), 0.0, None, open_low=True)
        # Stored as Python numbers, so that equal settings compare, hash, print and key a cache
        # equal whatever type they were spelled in (1 or 1.0, np.float32, a 0-d tensor).
        for name, value in checked.items():
            object.__setattr__(self, name, value)

    @property
    def times(self) -> list[float]:
        """The scales ``t_k / A``."""
        return [self.t0 * 2.0**k for k in range(self.num_scales)]


@dataclass
class RobustChannels:
    """Per-scale channels on the vertices of one mesh (every vertex referenced by a face).

    Attributes:
        dn: ``(V, T)`` normal displacement over ``sqrt(t)``.
        spread: ``(V, T, 3)`` ascending eigenvalues of the spread over ``2 t``; ``None`` when
            only ``dn`` was asked for.
        heat: ``(V, H)`` log heat kernel diagonal at the ``H`` largest scales (``t >=
            heat_from``); ``None`` when only ``dn`` was asked for or the structure has none.
        mass: ``(V,)`` lumped vertex areas of the mesh at unit total area.
        levels: vertex count of every pyramid level.
        assignment: the level of every scale.
    """

    dn: Tensor
    spread: Tensor | None
    heat: Tensor | None
    mass: Tensor
    levels: list[int] = field(default_factory=list)
    assignment: list[int] = field(default_factory=list)


def as_robust_params(value) -> RobustParams:
    """``value`` as :class:`RobustParams`: ``None`` gives the defaults, a mapping (a config
    file's section) gives its fields; :class:`ParameterError` names anything else."""
    if value is None:
        return RobustParams()
    if isinstance(value, RobustParams):
        return value
    if isinstance(value, Mapping):
        unknown = sorted(set(map(str, value)) - {f.name for f in fields(RobustParams)})
        if unknown:
            raise ParameterError(
                f"robust has unknown settings {unknown}; RobustParams has "
                f"{[f.name for f in fields(RobustParams)]}"
            )
        return RobustParams(**value)
    raise ParameterError(
        f"robust must be a RobustParams (or a mapping of its fields), got {type(value).__name__}"
    )


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


def _fields(centred: Tensor, products: bool) -> Tensor:
    """``(n, 9)``: the centred positions and their six products (``(n, 3)`` without the
    products)."""
    x, y, z = centred.unbind(dim=1)
    fields = [x, y, z]
    if products:
        fields += [x * x, y * y, z * z, x * y, y * z, z * x]
    return torch.stack(fields, 1)


def _level_normals(points: Tensor, level: Level, operator: HeatOperator, time: float,
                   tolerance: float) -> Tensor:  # fmt: skip
    """``(n, 3)`` unit outward vertex normals of a level, diffused for ``time``.

    Not the normal diffused to each scale: over a closed surface the normals integrate to
    zero, so at coarse scales (and across thin parts at every scale) the diffused normal all
    but cancels, its direction is rounding, and ``dn`` follows neither the shape nor a
    rotation of it.
    """
    faces = torch.from_numpy(level.faces)
    normals = vertex_normals(points, faces) * outward_sign(
        points, faces, torch.from_numpy(level.labels))[:, None]  # fmt: skip
    if time > 0.0:
        normals = HeatSemigroup.apply(normals, operator, (time,), tolerance)[0]
    return normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-30)


def _level_channels(points: Tensor, level: Level, operator: HeatOperator, times: list[float],
                    params: RobustParams, dn_only: bool) -> Tensor:  # fmt: skip
    """``(n, 4 T)`` on the vertices of one level: ``dn`` at the ``T`` scales, then the
    spread's three eigenvalues at each scale in turn (``(n, T)``, ``dn`` alone, if
    ``dn_only``)."""
    centred = points - points.detach().mean(dim=0)
    fields = _fields(centred, products=not dn_only)
    diffused = HeatSemigroup.apply(fields, operator, tuple(times), params.tolerance)
    normal_time = min(params.normal_time * level.mean_vertex_area, min(times))
    normal = _level_normals(points, level, operator, normal_time, params.tolerance)
    dn, spread = [], []
    for index, t in enumerate(times):
        out = diffused[index]
        mean = out[:, :3]
        dn.append(((centred - mean) * normal).sum(dim=1) / math.sqrt(t))
        if dn_only:
            continue
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
    if dn_only:
        return torch.stack(dn, dim=1)
    return torch.cat([torch.stack(dn, dim=1), torch.cat(spread, dim=1)], dim=1)


class Interpolation(NamedTuple):
    """A level's barycentric interpolation to the level above (weights held fixed).

    Attributes:
        corners: ``(n_above, 3)`` int64 the corners of the closest triangle of every vertex
            of the level above.
        weights: ``(n_above, 3)`` float64 their barycentric weights.
    """

    corners: Tensor
    weights: Tensor

    @classmethod
    def of(cls, level: Level) -> Interpolation:
        face, bary = level.prolong
        return cls(torch.from_numpy(level.faces[face]), torch.from_numpy(bary))

    def __call__(self, values: Tensor) -> Tensor:
        """``(n_above, ...)`` from ``(n, ...)`` values (gathers: differentiable). Corner by
        corner, so that no ``(n_above, 3, ...)`` intermediate is made."""
        weights = self.weights.to(values.dtype)
        shape = (-1, *([1] * (values.dim() - 1)))
        out = values[self.corners[:, 0]] * weights[:, 0].reshape(shape)
        for corner in (1, 2):
            out = torch.addcmul(out, values[self.corners[:, corner]],
                                weights[:, corner].reshape(shape))  # fmt: skip
        return out


def _prolong(prolongations: list, level: int, values: Tensor) -> Tensor:
    """Values on level ``level`` interpolated to level 0."""
    for index in range(level, 0, -1):
        values = prolongations[index](values)
    return values


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
        prolongations: per level, its :class:`Interpolation` to the level above (``None`` on
            level 0).
        assignment: the level of every scale.
        operators: the heat operator of every level a scale runs on.
        heat: ``(V, H)`` log heat kernel diagonal at the scales ``t >= heat_from``; ``None``
            if built without it.
    """

    levels: list[Level]
    prolongations: list[Interpolation | None]
    assignment: list[int]
    operators: dict[int, HeatOperator]
    heat: Tensor | None


def robust_structure(
    vertices: Tensor, faces: Tensor, params: RobustParams, heat: bool = True
) -> RobustStructure:
    """The :class:`RobustStructure` of a mesh (every vertex referenced by a face); without
    the heat channel if not ``heat``.

    Raises:
        TriangleSoupError: most faces share no vertex with another
            (:func:`~stochlap_torch.mesh.surface.check_not_soup`).
    """
    check_not_soup(faces.numpy())
    vertices = vertices.detach().double()
    faces = _canonical(vertices, faces)
    return _structure(_unit_area(vertices, faces).numpy(), faces, params, heat)


def _canonical(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F, 3)`` the faces wound one way (:func:`~stochlap_torch.mesh.surface.orient_faces`):
    the decimation follows the winding, which says nothing about the shape (reversing every
    face changed the saliency by a fifth of its range), and so, in their last bits, do the
    areas. Faces already wound consistently outward come back unchanged.

    A flat patch (zero volume) is wound by a rank of its vertices from the geometry: their
    distance to the centroid, then their coordinates along the principal axes, in float32, so
    that neither a renumbering of the vertices nor a rigid motion changes it.
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
    """``(V, 3)`` centred points in the frame of their principal axes, each axis signed so
    that the third moment along it is positive.

    The decimation rounds to float32 and breaks ties by coordinates, so a rotated mesh could
    get another pyramid (the octopus did: features off by up to 3 deviations at its tips);
    in this frame every rotation of a mesh gives the decimation the same numbers, up to the
    rounding of the frame itself (and to the choice of axes of a shape with equal moments).
    """
    _, axes = np.linalg.eigh(points.T @ points)
    projected = points @ axes
    signs = np.where(np.sum(projected**3, axis=0) < 0.0, -1.0, 1.0)
    return projected * signs


def _structure(fine: np.ndarray, faces: Tensor, params: RobustParams, heat: bool):
    """:func:`robust_structure` of the mesh at unit area (``(V, 3)`` float64, centred) and
    :func:`_canonical` faces."""
    times = params.times
    largest_level = max(params.min_vertices, int(params.resolution / max(times) * 1.2))
    levels = build_pyramid(
        _principal_frame(fine), faces.numpy(), params.ratio, largest_level, worker_threads()
    )
    prolongations = [None] + [Interpolation.of(level) for level in levels[1:]]
    assignment = level_times(levels, times, params.resolution, params.fidelity)
    operators = {
        index: heat_operator(levels[index].vertices, levels[index].faces, params.cap, params.clamp)
        for index in sorted(set(assignment))
    }
    values = None
    if heat:
        heat_times = np.array([t for t in times if t >= params.heat_from])
        values = torch.zeros(fine.shape[0], heat_times.size, dtype=torch.float64)
        if heat_times.size:
            index = level_times(levels, [float(heat_times[0])], params.heat_resolution,
                                params.fidelity)[0]  # fmt: skip
            operator = operators[index] if index in operators else heat_operator(
                levels[index].vertices, levels[index].faces, params.cap, params.clamp)  # fmt: skip
            values = _prolong(prolongations, index,
                              torch.from_numpy(heat_diagonal(operator, heat_times)))  # fmt: skip
    return RobustStructure(levels, prolongations, assignment, operators, values)


def robust_channels(
    vertices: Tensor,
    faces: Tensor,
    params: RobustParams,
    structure: RobustStructure | None = None,
    progress: ProgressCallback | None = None,
    dn_only: bool = False,
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
        dn_only: compute ``dn`` alone (what the saliency needs): a third of the fields to
            diffuse, no spread and no heat channel.

    The channels do not depend on the faces' winding or corner order (:func:`_canonical`).

    Raises:
        TriangleSoupError: building the structure of a triangle soup
            (:func:`~stochlap_torch.mesh.surface.check_not_soup`), before any other work.
    """
    if structure is None:
        check_not_soup(faces.numpy())
    faces = _canonical(vertices, faces)
    points = _unit_area(vertices, faces)
    if structure is None:
        structure = _structure(points.detach().numpy(), faces, params, heat=not dn_only)
    times = params.times
    per_level = {}
    for index, operator in structure.operators.items():
        scales = [k for k, level in enumerate(structure.assignment) if level == index]
        level = structure.levels[index]
        level_points = points[torch.from_numpy(level.vertex_ids)]
        keys = [("dn", k) for k in scales]
        keys += [] if dn_only else [("spread", k, axis) for k in scales for axis in range(3)]
        per_level[index] = (keys, _level_channels(
            level_points, level, operator, [times[k] for k in scales], params, dn_only
        ))  # fmt: skip
        if progress is not None:
            progress(max(scales) + 1, len(times))
    keys, values = _to_mesh(structure.prolongations, per_level)
    column = {key: position for position, key in enumerate(keys)}
    count = len(times)
    dn = values[:, [column["dn", k] for k in range(count)]]
    spread = None
    if not dn_only:
        spread_columns = [column["spread", k, axis] for k in range(count) for axis in range(3)]
        spread = values[:, spread_columns].reshape(-1, count, 3)
    mass = torch.zeros_like(points[:, 0]).index_add_(
        0, faces.reshape(-1), (face_areas(points.detach(), faces) / 3.0).repeat_interleave(3)
    )
    heat = None if dn_only or structure.heat is None else structure.heat.to(points.dtype)
    levels = [level.vertices.shape[0] for level in structure.levels]
    return RobustChannels(dn, spread, heat, mass, levels, structure.assignment)


def _to_mesh(prolongations: list, per_level: dict) -> tuple[list, Tensor]:
    """``(keys, (V, C) values)``: the channels of every level brought to the mesh. Coarsest
    first, each level's columns are joined to those carried up to it, so that one
    interpolation per level serves them all. ``per_level`` maps a level to ``(keys, (n, c))``
    with a key for each column; the keys come back in the order of the returned columns."""
    carried, keys = None, []
    for index in range(max(per_level), -1, -1):
        if index in per_level:
            level_keys, values = per_level[index]
            carried = values if carried is None else torch.cat([carried, values], dim=1)
            keys = keys + level_keys
        if index > 0 and carried is not None:
            carried = prolongations[index](carried)
    return keys, carried
