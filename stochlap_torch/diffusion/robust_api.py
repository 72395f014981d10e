"""``robust_representation``: a mesh (or a packed batch) in, the robust channels out."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .._common.checks import format_bytes
from .._common.threads import serial_glue
from ..mesh import as_mesh_tensors, check_batch, extent_scale
from ..mesh.validation import check_surface_area
from ..operators.heat_operator import chebyshev_terms
from .memory import MEMORY_ENV, MemoryBudgetError, resolve_budget
from .parameters import ProgressCallback
from .robust import (
    RobustParams,
    RobustStructure,
    as_robust_params,
    robust_channels,
    robust_structure,
)
from .semigroup import MAX_CHEBYSHEV_TERMS

__all__ = ["RobustRepresentation", "robust_memory", "robust_representation", "semigroup_memory"]


@dataclass
class RobustRepresentation:
    """The robust multiscale representation of a mesh or packed batch (see
    :mod:`stochlap_torch.diffusion.robust`), in the dtype and on the device of the vertices.

    Attributes:
        dn: ``(V, T)`` normal displacement over ``sqrt(t)`` at every scale.
        spread: ``(V, T, 3)`` ascending eigenvalues of the spread of heat over ``2 t``;
            ``None`` if computed with ``dn_only``.
        heat: ``(V, H)`` log heat kernel diagonal at the largest scales; ``None`` if computed
            with ``dn_only``.
        mass: ``(V,)`` vertex areas, each mesh scaled to unit total area.
        referenced: ``(V,)`` bool: the vertex belongs to a face. The others carry the values of
            a flat plane (``dn = 0``, spread ``(0, 1, 1)``, ``heat = 0``) and no mass.
        params: the settings.
        batch: the ``(V,)`` mesh index of every vertex of a packed batch, else ``None``.
    """

    dn: Tensor
    spread: Tensor | None
    heat: Tensor | None
    mass: Tensor
    referenced: Tensor
    params: RobustParams
    batch: Tensor | None = None

    @property
    def num_scales(self) -> int:
        return int(self.dn.shape[1])


def _plane_values(count: int, params: RobustParams, dn_only: bool) -> dict[str, Tensor | None]:
    """The channels of ``count`` vertices no face uses: those of a flat plane (``dn = 0``,
    spread ``(0, 1, 1)``, ``heat = 0``) and no mass; float64."""
    dn = torch.zeros(count, params.num_scales, dtype=torch.float64)
    spread = heat = None
    if not dn_only:
        spread = dn.new_zeros(count, params.num_scales, 3)
        spread[:, :, 1:] = 1.0
        heat_scales = sum(1 for t in params.times if t >= params.heat_from)
        heat = dn.new_zeros(count, heat_scales)
    return {"dn": dn, "spread": spread, "heat": heat, "mass": dn.new_zeros(count)}


def semigroup_memory(structure: RobustStructure, params: RobustParams) -> int:
    """Bytes the heat semigroup's Chebyshev coefficients take at their peak on the levels of
    ``structure``: a ``(T, terms)`` float64 table per level (:func:`~stochlap_torch.operators.
    heat_operator.chebyshev_terms` wide, for the level's largest time), two of them while it is
    built, and a few rows of that width. The terms grow with the level's stiffness: a few hundred
    tiny triangles beside a large one need millions."""
    times = params.times
    peak = 0
    for index, operator in structure.operators.items():
        level_times = [times[k] for k, level in enumerate(structure.assignment) if level == index]
        scaled = max(level_times) * operator.bound / 2.0
        if not scaled <= MAX_CHEBYSHEV_TERMS:
            continue  # the semigroup refuses such a level (MeshError) before it allocates
        terms = chebyshev_terms(scaled)
        peak = max(peak, (2 * len(level_times) + 4) * terms * 8)
    return peak


def _one_mesh(
    vertices: Tensor,
    faces: Tensor,
    params: RobustParams,
    spare: int,
    progress: ProgressCallback | None = None,
    dn_only: bool = False,
) -> dict[str, Tensor | None]:
    """The channels of one mesh on all its vertices (unreferenced ones, and all of a mesh
    without faces, get plane values). ``spare``: the bytes of the budget left for the heat
    semigroup's coefficients (:func:`semigroup_memory`)."""
    count = vertices.shape[0]
    values = _plane_values(count, params, dn_only)
    if faces.shape[0] == 0:
        return values
    check_surface_area(vertices, faces)
    used = torch.unique(faces)
    local = torch.full((count,), -1, dtype=torch.int64)
    local[used] = torch.arange(used.numel())
    # The channels are scale invariant: scale by a power of two (exact) so that areas and
    # squared lengths neither overflow nor underflow (coordinates of 1e155 or 1e-155).
    scale = extent_scale(vertices[used].detach())
    points = vertices[used].double() * scale
    # Built here rather than inside robust_channels so that the semigroup's cost, known only
    # from the operators' spectral bounds, is checked before any diffusion runs.
    structure = robust_structure(points, local[faces], params, heat=not dn_only)
    needed = semigroup_memory(structure, params)
    if needed > spare:
        raise MemoryBudgetError(
            f"diffusing a mesh of {used.numel()} vertices to the robust variant's scales needs "
            f"{format_bytes(needed)} for its Chebyshev coefficients besides the rest of the run, "
            f"over the {format_bytes(max(spare, 0))} the budget leaves: its triangles differ in "
            "size by orders of magnitude (tiny ones beside large ones). Raise the budget "
            f"(max_memory=..., or ${MEMORY_ENV}), or remesh to a more even triangulation."
        )
    channels = robust_channels(
        points, local[faces], params, structure=structure, progress=progress, dn_only=dn_only
    )
    for name in ("dn", "spread", "mass"):
        if values[name] is not None:
            values[name] = values[name].index_put((used,), getattr(channels, name))
    if not dn_only:
        values["heat"] = values["heat"].index_put((used,), channels.heat)
    return values


#: Bytes per vertex a robust run holds at its peak, per scale (the float64 fields and their
#: diffused copies, the channels and their prolongations; measured on gargoyle_50k when twelve
#: fields were diffused, nine now: an upper bound).
_BYTES_PER_VERTEX_SCALE = 12 * 8 * 6
#: ... and independent of the scales (the pyramid, the operators, the interpolation).
_BYTES_PER_VERTEX = 1600


def robust_memory(num_vertices: int, params: RobustParams) -> int:
    """Bytes a robust run on ``num_vertices`` vertices needs at its peak (linear in both),
    besides the heat semigroup's coefficients (:func:`semigroup_memory`)."""
    return num_vertices * (_BYTES_PER_VERTEX + _BYTES_PER_VERTEX_SCALE * params.num_scales)


@serial_glue()
def robust_representation(
    vertices,
    faces,
    params: RobustParams | None = None,
    batch: Tensor | None = None,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    dn_only: bool = False,
) -> RobustRepresentation:
    """The robust multiscale channels of a mesh, or of each mesh of a packed batch.

    Args:
        vertices: ``(V, 3)`` float32 or float64 tensor; computed in float64, returned in its
            dtype. Gradients reach it with the operators held constant.
        faces: ``(F, 3)`` integer tensor.
        params: :class:`~stochlap_torch.diffusion.robust.RobustParams` (defaults if ``None``).
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch; every
            mesh is processed on its own, so results equal separate runs.
        max_memory: byte budget (default: the library's,
            :func:`~stochlap_torch.diffusion.memory.default_memory_budget`).
        progress: called as ``progress(k, T)`` as the scales of a mesh are done; for a batch,
            as ``progress(i, B)`` after each of its ``B`` meshes.
        dn_only: compute ``dn`` alone, all the saliency needs (``spread`` and ``heat`` are
            then ``None``): a third of the fields to diffuse, no spread, no eigenpairs.

    Raises:
        MeshError: bad mesh. ParameterError: bad settings.
        MemoryBudgetError: the run would exceed the budget.
    """
    params = as_robust_params(params)
    points, faces = as_mesh_tensors(vertices, faces)
    budget = resolve_budget(max_memory)
    needed = robust_memory(points.shape[0], params)
    if needed > budget:
        raise MemoryBudgetError(
            f"the robust representation of {points.shape[0]} vertices at {params.num_scales} "
            f"scales needs about {format_bytes(needed)}, over the budget of "
            f"{format_bytes(budget)}. Raise the budget (max_memory=..., or ${MEMORY_ENV})."
        )
    device, dtype = points.device, points.dtype
    cpu_points, cpu_faces = points.cpu(), faces.cpu()
    if batch is None:
        parts = [_one_mesh(cpu_points, cpu_faces, params, budget - needed, progress, dn_only)]
        order = None
    else:
        batch = check_batch(batch, points.shape[0], faces)
        cpu_batch = batch.cpu()
        parts, members = [], []
        face_mesh = cpu_batch[cpu_faces[:, 0]]
        for mesh in range(int(cpu_batch.max()) + 1):
            index = (cpu_batch == mesh).nonzero().flatten()
            local = torch.full_like(cpu_batch, -1)
            local[index] = torch.arange(index.numel())
            mesh_faces = local[cpu_faces[face_mesh == mesh]]
            spare = budget - needed
            parts.append(_one_mesh(cpu_points[index], mesh_faces, params, spare, dn_only=dn_only))
            members.append(index)
            if progress is not None:
                progress(mesh + 1, int(cpu_batch.max()) + 1)
        order = torch.argsort(torch.cat(members))
    merged = {}
    for name in ("dn", "spread", "heat", "mass"):
        if parts[0][name] is None:
            merged[name] = None
            continue
        values = torch.cat([part[name] for part in parts])
        values = values if order is None else values[order]
        merged[name] = values.to(dtype=dtype, device=device)
    referenced = torch.zeros(points.shape[0], dtype=torch.bool, device=device)
    referenced[faces.reshape(-1)] = True
    return RobustRepresentation(**merged, referenced=referenced, params=params, batch=batch)
