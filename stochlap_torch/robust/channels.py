"""The robust variant's channels, and its saliency and features.

Scale ``k`` is a diffusion time ``t_k = t_0 2^k A`` (``A`` the surface area) of the heat
semigroup ``F_t``, run on the coarsest pyramid level that resolves it and interpolated back to
the mesh. Per scale, dimensionless and invariant to rigid motion and uniform scaling:

* ``dn``: ``(P - F_t P) . n / sqrt(t)``, a multiscale mean curvature (``~ 2 H sqrt(t)``; ``n``
  the outward normal smoothed for a time ``normal_time A``);
* ``spread``: the eigenvalues of ``F_t[P P^T] - F_t[P] F_t[P]^T`` over ``2 t`` (``(1, 1, 0)``
  on a plane);
* ``twist``: ``n . (d_k x d_{k+1})`` with ``d_k = (F_t P - P) / sqrt(t)`` between consecutive
  coarse scales: how the diffused surface's pull turns about the normal from one scale to the next.
  It changes sign under a reflection, and is the one channel that tells a left hand from a
  right one: on a mirror-symmetric body every other channel is equal at a point and its mirror;
* ``heat``: ``log(4 pi t h_t(i, i))`` at the largest scales, the heat kernel diagonal.

Gradients reach the vertices with the operators, pyramid and interpolation held constant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from .._common.tensors import symmetric_eigenvalues
from ..mesh import face_areas, outward_sign, vertex_normals
from ..params import RobustParams
from .heat import HeatSemigroups
from .pyramid import StructureLevel

#: The spread's eigenvalues are clipped here before the logarithm (the smallest is 0 on a plane).
SPREAD_FLOOR = 1e-4


@dataclass
class RobustRepresentation:
    """The robust channels of a mesh or packed batch, in the dtype and on the device of the
    vertices.

    Attributes:
        dn: ``(V, T)`` normal displacement over ``sqrt(t)`` at every scale.
        spread: ``(V, T, 3)`` ascending eigenvalues of the spread of heat over ``2 t``;
            ``None`` if computed with ``dn_only``.
        twist: ``(V, W)`` the displacement's turn about the normal from each scale of
            ``params.twist_scales`` to the next (changes sign under a reflection); ``None`` if
            computed with ``dn_only``.
        heat: ``(V, H)`` log heat kernel diagonal at the largest scales; ``None`` if computed
            with ``dn_only``.
        mass: ``(V,)`` vertex areas, each mesh scaled to unit total area.
        referenced: ``(V,)`` bool: the vertex belongs to a face. The others carry the values of
            a flat plane (``dn = 0``, spread ``(0, 1, 1)``, ``twist = heat = 0``) and no mass.
        params: the settings.
        batch: the ``(V,)`` mesh index of every vertex of a packed batch, else ``None``.
    """

    dn: Tensor
    spread: Tensor | None
    twist: Tensor | None
    heat: Tensor | None
    mass: Tensor
    referenced: Tensor
    params: RobustParams
    batch: Tensor | None = None

    @property
    def num_scales(self) -> int:
        return int(self.dn.shape[1])


def plane_values(count: int, params: RobustParams, dn_only: bool, like: Tensor) -> dict:
    """The channels of ``count`` vertices no face uses, in the dtype and device of ``like``."""
    dn = like.new_zeros(count, params.num_scales)
    spread = twist = heat = None
    if not dn_only:
        spread = dn.new_zeros(count, params.num_scales, 3)
        spread[:, :, 1:] = 1.0
        twist = dn.new_zeros(count, len(params.twist_scales))
        heat = dn.new_zeros(count, len(params.heat_scales))
    return {
        "dn": dn,
        "spread": spread,
        "twist": twist,
        "heat": heat,
        "mass": dn.new_zeros(count),
    }


def _fixed_order_sum(values: Tensor) -> Tensor:
    """The float64 sum of ``values`` over their first dimension, in the same order on any
    thread count: the pyramid's discrete choices must not follow a parallel sum's rounding."""
    return values.to(torch.float64).cumsum(0)[-1]


def unit_area(vertices: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """The mesh centred and scaled to unit area, and its lumped vertex areas there.

    Args:
        vertices: ``(V, 3)`` float, every vertex referenced (gradients reach them).
        faces: ``(F, 3)`` int64, ``F > 0``.

    Returns:
        ``((V, 3), (V,))`` in the dtype and on the device of ``vertices``; the areas (a third
        of every face's) held constant.
    """
    areas = face_areas(vertices, faces)
    total = _fixed_order_sum(areas).to(vertices.dtype)
    centre = (_fixed_order_sum(vertices.detach()) / vertices.shape[0]).to(vertices.dtype)
    shares = (areas.detach() / (3.0 * total.detach())).repeat_interleave(3)
    mass = torch.zeros_like(vertices[:, 0].detach()).index_add_(0, faces.reshape(-1), shares)
    return (vertices - centre) / total.sqrt(), mass


def _fields(centred: Tensor, products: bool) -> Tensor:
    """``(n, 9)``: the centred positions and their six products (``(n, 3)`` without the
    products)."""
    x, y, z = centred.unbind(dim=1)
    fields = [x, y, z]
    if products:
        fields += [x * x, y * y, z * z, x * y, y * z, z * x]
    return torch.stack(fields, 1)


def _level_normals(points: Tensor, level: StructureLevel) -> Tensor:
    """``(n, 3)`` area-weighted outward vertex normals of one level at its ``points``."""
    sign = outward_sign(points, level.faces, level.labels)
    return vertex_normals(points, level.faces) * sign[:, None]


def _smoothed_normals(normals: Tensor, moved: Tensor | None) -> Tensor:
    """The level's normals smoothed for the normal time, from their increments ``moved``
    ``(2, n, 3)`` at that time and a sixteenth of it (``None``: not smoothed).

    Across a part thinner than the smoothing reaches (a finger) the smoothed normals cancel;
    there a normal smoothed for ``time / 16``, added with a quarter of the weight, takes over.
    """
    if moved is None:
        return normals
    return (normals + moved[0]) + 0.25 * (normals + moved[1])


def _mesh_normals(
    normals: Tensor, levels: list[StructureLevel], finest: int, dtype: torch.dtype
) -> Tensor:
    """``(U, 3)`` unit outward normals of the mesh's vertices from the smoothed ``normals`` of
    level ``finest`` (smoothed for a time in units of the area, so every triangulation gets
    the same), interpolated."""
    for index in range(finest, 0, -1):
        normals = levels[index].prolongation(normals)
    return normals / normals.norm(dim=1, keepdim=True).clamp_min(torch.finfo(dtype).tiny)


def _level_channels(
    points: Tensor,
    level: StructureLevel,
    times: list[float],
    params: RobustParams,
    dn_only: bool,
    normals: bool,
) -> tuple[Tensor, Tensor | None]:
    """``(n, 6 T)`` on one level's ``points`` ``(n, 3)``, in their dtype: the displacement
    ``(F_t P - P) / sqrt(t)`` at the ``T`` scales, then the spread's eigenvalues (``(n, 3 T)``,
    the displacement alone, if ``dn_only``); with ``normals``, the level's smoothed normals
    (:func:`_smoothed_normals`, diffused by the same recurrence), else ``None``."""
    dtype = points.dtype
    centred = points - points.detach().mean(dim=0)
    # The spread's smallest eigenvalue is down to 1e-7 of the squared positions: the products
    # and the recurrence's first term (which rounds relative to them) are in float64.
    wide = centred if dn_only else centred.to(torch.float64)
    fields = [_fields(wide, products=not dn_only)]
    groups = [tuple(times)]
    plain = _level_normals(points, level) if normals else None
    time = params.normal_time
    if normals and time > 0.0:
        fields.append(plain)
        groups.append((time, time / 16.0))
    # Increments F x - x: the channels are differences of nearly equal diffused values.
    moved, *others = HeatSemigroups.apply(
        level.semigroup, tuple(groups), params.tolerance, dtype, *fields
    )
    smoothed = None if plain is None else _smoothed_normals(plain, others[0] if others else None)
    x, y, z = wide.unbind(dim=1)
    shift, spread = [], []
    for index, t in enumerate(times):
        out = moved[index]
        shift.append(out[:, :3] / math.sqrt(t))
        if dn_only:
            continue
        # F[a b] - F[a] F[b] = D_ab - a d_b - b d_a - d_a d_b, with F[a] = a + d_a and
        # F[a b] = a b + D_ab; in float64 (the positions').
        dx, dy, dz = out[:, 0], out[:, 1], out[:, 2]
        xx, yy, zz, xy, yz, zx = (out[:, 3 + c] for c in range(6))
        cxx = xx - 2.0 * x * dx - dx * dx
        cyy = yy - 2.0 * y * dy - dy * dy
        czz = zz - 2.0 * z * dz - dz * dz
        cxy = xy - x * dy - y * dx - dx * dy
        cyz = yz - y * dz - z * dy - dy * dz
        czx = zx - z * dx - x * dz - dz * dx
        spread.append(symmetric_eigenvalues(cxx, cyy, czz, cxy, cyz, czx) / (2.0 * t))
    return torch.cat(shift + spread, dim=1).to(dtype), smoothed


def scale_channels(
    points: Tensor,
    levels: list[StructureLevel],
    assignment: list[int],
    params: RobustParams,
    progress=None,
    dn_only: bool = False,
) -> tuple[Tensor, Tensor | None, Tensor | None]:
    """``(dn (U, T), spread (U, T, 3), twist (U, W))`` (the last two ``None`` if
    ``dn_only``) of the mesh at unit area
    ``points`` ``(U, 3)`` (:func:`unit_area`), in their dtype, on the pyramid ``levels`` with
    the level of every scale in ``assignment``; ``progress(k, T)`` as the scales are done.

    The displacement vector is interpolated to the mesh, where ``dn`` takes its component
    along the mesh's own normal: a coarse level's normals would follow its decimation. The
    normal is smoothed on the finest level with a scale, by that level's recurrence.
    """
    times, count = params.times, len(params.times)
    finest = min(assignment)
    per_level, normals = {}, None
    for index, level in enumerate(levels):
        scales = [k for k, chosen in enumerate(assignment) if chosen == index]
        if scales:
            points_here = points.index_select(0, level.vertex_ids)
            values, smoothed = _level_channels(
                points_here, level, [times[k] for k in scales], params, dn_only, index == finest
            )
            normals = smoothed if index == finest else normals
            per_level[index] = (scales, values)
            if progress is not None:
                progress(max(scales) + 1, count)
    # Coarsest first, each level's columns join those carried up: one interpolation per level.
    # ``positions``: their columns in the result (displacement 3 k + a, spread 3 T + 3 k + a).
    carried, positions = None, []
    for index in range(max(per_level), -1, -1):
        if index in per_level:
            scales, values = per_level[index]
            positions += [3 * k + a for k in scales for a in range(3)]
            positions += (
                [] if dn_only else [3 * count + 3 * k + a for k in scales for a in range(3)]
            )
            carried = values if carried is None else torch.cat([carried, values], dim=1)
        if index > 0:
            carried = levels[index].prolongation(carried)
    order = torch.argsort(torch.tensor(positions, device=carried.device))
    channels = carried.index_select(1, order)
    normals = _mesh_normals(normals, levels, finest, points.dtype)
    shift = channels[:, : 3 * count].reshape(-1, count, 3)
    dn = -(shift * normals[:, None, :]).sum(dim=2)
    if dn_only:
        return dn, None, None
    # Outward normals follow the shape, not the winding: a true vector, as the displacements
    # are, so the triple product flips under a reflection only.
    turns = torch.tensor(params.twist_scales, dtype=torch.int64, device=shift.device)
    turn = torch.linalg.cross(shift[:, turns], shift[:, turns + 1], dim=2)
    twist = (turn * normals[:, None, :]).sum(dim=2)
    return dn, channels[:, 3 * count :].reshape(-1, count, 3), twist


def _per_mesh_mean(values: Tensor, weights: Tensor, batch: Tensor, num_meshes: int) -> Tensor:
    """``(B, T)`` weighted mean of ``(V, T)`` values per mesh."""
    total = weights.new_zeros(num_meshes).index_add_(0, batch, weights).clamp_min(1e-300)
    summed = values.new_zeros(num_meshes, values.shape[1]).index_add_(
        0, batch, values * weights[:, None]
    )
    return summed / total[:, None]


def robust_saliency(rep: RobustRepresentation) -> Tensor:
    """``(V,)`` saliency: the mean over scales of ``max(0, (dn - mean) / deviation)``, mean and
    deviation weighted by vertex area, per mesh of a batch. Unreferenced vertices (no area) get
    0, the value of a flat or concave region."""
    dn, batch = rep.dn, rep.batch
    if batch is None:
        batch = torch.zeros(dn.shape[0], dtype=torch.int64, device=dn.device)
    num_meshes = int(batch.max()) + 1 if batch.numel() else 1
    mean = _per_mesh_mean(dn, rep.mass, batch, num_meshes)
    centred = dn - mean[batch]
    variance = _per_mesh_mean(centred.square(), rep.mass, batch, num_meshes)
    deviation = variance.clamp_min(torch.finfo(dn.dtype).tiny).sqrt()
    standard = centred / deviation[batch]
    saliency = standard.clamp_min(0.0).mean(dim=1)
    return torch.where(rep.referenced, saliency, torch.zeros_like(saliency))


def robust_channel_names(params: RobustParams) -> list[str]:
    """Names of the columns of :func:`robust_features`: ``dn{k}`` (``T``), ``spread{k}_{1,2,3}``
    (``3 T``, largest first), ``twist{k}`` (from scale ``k`` to ``k + 1``, at the scales
    ``t >= twist_from``), ``heat{k}`` at the scales ``t >= heat_from``."""
    scales = range(params.num_scales)
    return (
        [f"dn{k}" for k in scales]
        + [f"spread{k}_{axis}" for k in scales for axis in (1, 2, 3)]
        + [f"twist{k}" for k in params.twist_scales]
        + [f"heat{k}" for k in params.heat_scales]
    )


def robust_features(rep: RobustRepresentation) -> Tensor:
    """``(V, C)`` features (channel order of :func:`robust_channel_names`); unreferenced
    vertices get the values of a flat plane (0, except the smallest spread: its floor)."""
    spread = torch.log(rep.spread.clamp_min(SPREAD_FLOOR)).flip(-1)  # largest first
    return torch.cat([rep.dn, spread.reshape(spread.shape[0], -1), rep.twist, rep.heat], dim=1)
