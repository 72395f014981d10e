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
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from .._common.tensors import symmetric_eigenvalues
from ..mesh import face_areas, outward_sign, vertex_normals
from ..mesh.geometry import extent_scale
from ..mesh.surface import check_not_soup, orient_faces
from ..mesh.validation import check_surface_area
from ..operators.heat_operator import HeatOperator, heat_operator
from ..operators.pyramid import Level, build_pyramid
from .parameters import ProgressCallback
from .semigroup import HeatSemigroup, LevelSemigroup, heat_diagonal
from .structure import (
    Interpolation,
    RobustParams,
    RobustStructure,
    StructureLevel,
    as_robust_params,
)

__all__ = [
    "RobustChannels",
    "RobustParams",
    "RobustStructure",
    "StructureLevel",
    "as_robust_params",
    "build_structure",
    "level_times",
    "robust_channels",
]


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


def _level_normals(points: Tensor, level: StructureLevel, time: float, tolerance: float) -> Tensor:
    """``(n, 3)`` unit outward vertex normals of a level, diffused for ``time``.

    Not the normal diffused to each scale: over a closed surface the normals integrate to
    zero, so at coarse scales (and across thin parts at every scale) the diffused normal all
    but cancels, its direction is rounding, and ``dn`` follows neither the shape nor a
    rotation of it.
    """
    sign = outward_sign(points, level.faces, level.labels)
    normals = vertex_normals(points, level.faces) * sign[:, None]
    if time > 0.0:
        normals = normals + HeatSemigroup.apply(normals, level.semigroup, (time,), tolerance)[0]
    return normals / normals.norm(dim=1, keepdim=True).clamp_min(torch.finfo(points.dtype).tiny)


def _level_channels(
    points: Tensor, level: StructureLevel, times: list[float], params: RobustParams, dn_only: bool
) -> Tensor:
    """``(n, 4 T)`` on the vertices of one level: ``dn`` at the ``T`` scales, then the
    spread's three eigenvalues at each scale in turn (``(n, T)``, ``dn`` alone, if
    ``dn_only``); in the dtype and on the device of ``points`` ``(n, 3)``."""
    dtype = points.dtype
    centred = points - points.detach().mean(dim=0)
    # The spread's smallest eigenvalue is down to 1e-7 of the squared positions, of which
    # float32 keeps a digit or two: the products are formed in float64, and so is the
    # recurrence's first term, the one step whose rounding is relative to them.
    wide = centred if dn_only else centred.to(torch.float64)
    fields = _fields(wide, products=not dn_only)
    # Increments F x - x (HeatSemigroup): the channels are differences of nearly equal
    # diffused values, which the increments give without cancellation.
    moved = HeatSemigroup.apply(fields, level.semigroup, tuple(times), params.tolerance, dtype)
    normal_time = min(params.normal_time * level.mean_vertex_area, min(times))
    normal = _level_normals(points, level, normal_time, params.tolerance)
    x, y, z = wide.unbind(dim=1)
    dn, spread = [], []
    for index, t in enumerate(times):
        out = moved[index]
        dn.append(-(out[:, :3] * normal).sum(dim=1) / math.sqrt(t))
        if dn_only:
            continue
        # F[a b] - F[a] F[b] = D_ab - a d_b - b d_a - d_a d_b, with F[a] = a + d_a and
        # F[a b] = a b + D_ab; in float64 (the positions'), a difference of nearly equal
        # numbers down to the smallest eigenvalue.
        dx, dy, dz = out[:, 0], out[:, 1], out[:, 2]
        xx, yy, zz, xy, yz, zx = (out[:, 3 + c] for c in range(6))
        cxx = xx - 2.0 * x * dx - dx * dx
        cyy = yy - 2.0 * y * dy - dy * dy
        czz = zz - 2.0 * z * dz - dz * dz
        cxy = xy - x * dy - y * dx - dx * dy
        cyz = yz - y * dz - z * dy - dy * dz
        czx = zx - z * dx - x * dz - dz * dx
        spread.append(symmetric_eigenvalues(cxx, cyy, czz, cxy, cyz, czx) / (2.0 * t))
    if dn_only:
        return torch.stack(dn, dim=1)
    return torch.cat([torch.stack(dn, dim=1), torch.cat(spread, dim=1)], dim=1).to(dtype)


def _prolong(levels: list[StructureLevel], level: int, values: Tensor) -> Tensor:
    """Values on level ``level`` interpolated to level 0."""
    for index in range(level, 0, -1):
        values = levels[index].prolongation(values)
    return values


def _unit_area(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V, 3)`` the mesh centred and scaled to unit area, for building the structure. The
    centre and the area's value come from numpy (the same on any thread count: the pyramid's
    discrete choices must not depend on the rounding of a parallel sum); the area's gradient
    from torch."""
    array = vertices.detach().numpy()
    corners = array[faces.numpy()]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area_value = 0.5 * float(np.sqrt(np.einsum("ij,ij->i", cross, cross)).sum())
    area = face_areas(vertices, faces).sum()
    area = area - area.detach() + area_value  # the value from numpy, the gradient from torch
    centre = torch.from_numpy(array.mean(axis=0))
    return (vertices - centre) / area.sqrt()


def _call_unit_area(vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """``((V, 3), (V,))`` the mesh centred and scaled to unit area, and its lumped vertex
    areas at unit area (a third of every face's; held constant), in torch on its device (the
    structure holds every discrete choice, so the rounding of a parallel sum changes no
    pyramid here)."""
    areas = face_areas(vertices, faces)
    total = areas.sum()
    shares = (areas.detach() / (3.0 * total.detach())).repeat_interleave(3)
    mass = torch.zeros_like(vertices[:, 0].detach()).index_add_(0, faces.reshape(-1), shares)
    return (vertices - vertices.detach().mean(dim=0)) / total.sqrt(), mass


def _canonical(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F, 3)`` the faces wound one way (:func:`~stochlap_torch.mesh.surface.orient_faces`):
    the decimation follows the winding, which says nothing about the shape, and so, in their
    last bits, do the areas. Faces already wound consistently outward come back unchanged.

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
    get another pyramid, and features that differ where it does; in this frame every rotation
    of a mesh gives the decimation the same numbers, up to the rounding of the frame itself
    (and to the choice of axes of a shape with equal moments).
    """
    _, axes = np.linalg.eigh(points.T @ points)
    projected = points @ axes
    signs = np.where(np.sum(projected**3, axis=0) < 0.0, -1.0, 1.0)
    return projected * signs


def build_structure(
    vertices: Tensor, faces: Tensor, params: RobustParams, heat: bool = True
) -> RobustStructure:
    """The :class:`RobustStructure` of a validated mesh (``(V, 3)`` float on any device, read
    on the CPU; ``(F, 3)`` int64), on the device of ``vertices``; without the heat channel if
    not ``heat``.

    The pyramid's decimation rounds to float32 in the mesh's principal frame (invariant to
    rigid motion), so a float32 copy of a mesh can get another pyramid than the mesh: build
    the structure once and pass it to both to compare them.

    Raises:
        MeshError: the mesh has no area
            (:func:`~stochlap_torch.mesh.validation.check_surface_area`).
        TriangleSoupError: most faces share no vertex with another
            (:func:`~stochlap_torch.mesh.surface.check_not_soup`).
    """
    device = vertices.device
    points = vertices.detach().to("cpu", torch.float64)
    faces = faces.to("cpu")
    count = points.shape[0]
    if faces.shape[0] == 0:
        nothing = torch.zeros(0, dtype=torch.int64)
        return RobustStructure(params, count, 0, nothing, faces, [], [], None).to(device)
    check_surface_area(points, faces)
    used = torch.unique(faces)
    local = torch.full((count,), -1, dtype=torch.int64)
    local[used] = torch.arange(used.numel())
    local_faces = local[faces]
    check_not_soup(local_faces.numpy())
    # The channels are scale invariant: scale by a power of two (exact) so that areas and
    # squared lengths neither overflow nor underflow (coordinates of 1e155 or 1e-155).
    scaled = points[used] * extent_scale(points[used])
    canonical = _canonical(scaled, local_faces)
    unit = _unit_area(scaled, canonical).numpy()
    levels, assignment, values = _pyramid(unit, canonical, params, heat)
    structure = RobustStructure(
        params, count, faces.shape[0], used, canonical, levels, assignment, values
    )
    return structure.to(device)


def _pyramid(
    unit: np.ndarray, faces: Tensor, params: RobustParams, heat: bool
) -> tuple[list[StructureLevel], list[int], Tensor | None]:
    """``(levels, assignment, heat)`` of :class:`RobustStructure` from the mesh at unit area
    (``(U, 3)`` float64, centred) and its :func:`_canonical` faces."""
    times = params.times
    largest_level = max(params.min_vertices, int(params.resolution / max(times) * 1.2))
    pyramid = build_pyramid(
        _principal_frame(unit), faces.numpy(), params.ratio, largest_level, torch.get_num_threads()
    )
    assignment = level_times(pyramid, times, params.resolution, params.fidelity)

    def operator(index: int) -> HeatOperator:
        level = pyramid[index]
        return heat_operator(level.vertices, level.faces, params.cap, params.clamp)

    operators = {index: operator(index) for index in sorted(set(assignment))}
    levels = [
        StructureLevel(
            torch.from_numpy(level.vertex_ids),
            torch.from_numpy(level.faces),
            torch.from_numpy(level.labels),
            level.mean_vertex_area,
            Interpolation.of(level) if index else None,
            LevelSemigroup.of(operators[index]) if index in operators else None,
        )
        for index, level in enumerate(pyramid)
    ]
    values = None
    if heat:
        heat_times = np.array([t for t in times if t >= params.heat_from])
        values = torch.zeros(unit.shape[0], heat_times.size, dtype=torch.float64)
        if heat_times.size:
            index = level_times(
                pyramid, [float(heat_times[0])], params.heat_resolution, params.fidelity
            )[0]
            diagonal = heat_diagonal(operators.get(index) or operator(index), heat_times)
            values = _prolong(levels, index, torch.from_numpy(diagonal))
    return levels, assignment, values


def robust_channels(
    points: Tensor,
    structure: RobustStructure,
    progress: ProgressCallback | None = None,
    dn_only: bool = False,
) -> RobustChannels:
    """The channels of the referenced vertices of a mesh, in the dtype and on the device of
    ``points`` (those of ``structure``).

    Args:
        points: ``(U, 3)`` float, the positions of ``structure.used`` (may carry gradients:
            they reach them with the structure held constant).
        structure: the mesh's :class:`RobustStructure`.
        progress: called as ``progress(k, T)`` when the first ``k`` of the ``T`` scales are done
            (a level's scales at once).
        dn_only: compute ``dn`` alone (what the saliency needs): a third of the fields to
            diffuse, no spread and no heat channel.

    The channels do not depend on the faces' winding or corner order (:func:`_canonical`).
    """
    params = structure.params
    faces = structure.faces
    points, mass = _call_unit_area(points, faces)
    times = params.times
    per_level = {}
    for index, level in enumerate(structure.levels):
        if level.semigroup is None:
            continue
        scales = [k for k, chosen in enumerate(structure.assignment) if chosen == index]
        keys = [("dn", k) for k in scales]
        keys += [] if dn_only else [("spread", k, axis) for k in scales for axis in range(3)]
        values = _level_channels(
            points.index_select(0, level.vertex_ids),
            level,
            [times[k] for k in scales],
            params,
            dn_only,
        )
        per_level[index] = (keys, values)
        if progress is not None:
            progress(max(scales) + 1, len(times))
    keys, values = _to_mesh(structure.levels, per_level)
    column = {key: position for position, key in enumerate(keys)}
    count = len(times)

    def columns(wanted: list) -> Tensor:
        positions = torch.tensor([column[key] for key in wanted], device=values.device)
        return values.index_select(1, positions)

    dn = columns([("dn", k) for k in range(count)])
    spread = None
    if not dn_only:
        spread = columns([("spread", k, axis) for k in range(count) for axis in range(3)])
        spread = spread.reshape(-1, count, 3)
    heat = None if dn_only or structure.heat is None else structure.heat.to(points.dtype)
    sizes = [level.num_vertices for level in structure.levels]
    return RobustChannels(dn, spread, heat, mass, sizes, structure.assignment)


def _to_mesh(levels: list[StructureLevel], per_level: dict) -> tuple[list, Tensor]:
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
            carried = levels[index].prolongation(carried)
    return keys, carried
