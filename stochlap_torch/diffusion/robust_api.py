"""``robust_representation``: a mesh (or a packed batch) in, the robust channels out."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .._common.checks import format_bytes
from .._common.errors import ParameterError
from ..mesh import as_mesh_tensors, check_batch, extent_scale
from ..operators.heat_operator import chebyshev_terms
from .memory import MEMORY_ENV, MemoryBudgetError, resolve_budget
from .parameters import ProgressCallback
from .robust import (
    RobustParams,
    RobustStructure,
    as_robust_params,
    build_structure,
    robust_channels,
)
from .semigroup import MAX_CHEBYSHEV_TERMS

__all__ = [
    "RobustRepresentation",
    "check_structure",
    "robust_memory",
    "robust_representation",
    "robust_structure",
    "semigroup_memory",
]


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


def _plane_values(count: int, params: RobustParams, dn_only: bool, like: Tensor) -> dict:
    """The channels of ``count`` vertices no face uses: those of a flat plane (``dn = 0``,
    spread ``(0, 1, 1)``, ``heat = 0``) and no mass; in the dtype and on the device of
    ``like``."""
    dn = like.new_zeros(count, params.num_scales)
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
    built, and the few rows of that width that build it. The terms grow with the square root
    of the level's stiffness: a few hundred tiny triangles beside a large one need thousands."""
    times = params.times
    peak = 0
    for index, level in enumerate(structure.levels):
        if level.semigroup is None:
            continue
        level_times = [times[k] for k, chosen in enumerate(structure.assignment) if chosen == index]
        scaled = max(level_times) * level.semigroup.bound / 2.0
        if not scaled <= MAX_CHEBYSHEV_TERMS:
            continue  # the semigroup refuses such a level (MeshError) before it allocates
        terms = chebyshev_terms(scaled, params.tolerance)
        peak = max(peak, (2 * len(level_times) + 8) * terms * 8)
    return peak


def check_structure(
    structure, vertices: Tensor, faces: Tensor, params: RobustParams, dn_only: bool
) -> RobustStructure:
    """``structure`` if it is the :class:`RobustStructure` of a mesh of ``vertices`` ``(V,
    3)`` and ``faces`` ``(F, 3)`` at ``params``, on their device (and with the heat channel
    unless ``dn_only``); else :class:`ParameterError` saying what differs."""
    if not isinstance(structure, RobustStructure):
        raise ParameterError(
            "structure must be a RobustStructure (stochlap_torch.robust_structure(vertices, "
            f"faces)), got {type(structure).__name__}"
        )
    counts = (vertices.shape[0], faces.shape[0])
    if (structure.num_vertices, structure.num_faces) != counts:
        raise ParameterError(
            f"structure was built for a mesh of {structure.num_vertices} vertices and "
            f"{structure.num_faces} faces, not this one of {counts[0]} and {counts[1]}: build "
            "it from the same mesh (robust_structure(vertices, faces))"
        )
    if structure.params != params:
        raise ParameterError(
            f"structure was built with {structure.params!r}, the call asks for {params!r}: "
            "build it with the call's settings (robust_structure(..., robust=...))"
        )
    if structure.device != vertices.device:
        raise ParameterError(
            f"structure is on {structure.device}, the vertices on {vertices.device}: move it "
            "once with structure.to(device)"
        )
    if not dn_only and structure.heat is None and structure.num_faces:
        raise ParameterError("structure was built without the heat channel the features need")
    if not _same_faces(structure, faces):
        raise ParameterError(
            "structure was built for other faces (another mesh of the same counts, or these "
            "vertices renumbered): build it from this mesh (robust_structure(vertices, faces))"
        )
    return structure


def _same_faces(structure: RobustStructure, faces: Tensor) -> bool:
    """Whether ``faces`` ``(F, 3)`` are the structure's (each as built, or reversed: the
    structure winds faces one way, and the call may wind them either way); O(F), on the
    device."""
    if faces.shape[0] == 0:
        return structure.num_faces == 0
    mapped = faces
    if structure.used.numel() != structure.num_vertices:  # else ``used`` is every vertex
        local = torch.full((structure.num_vertices,), -1, dtype=torch.int64, device=faces.device)
        local[structure.used] = torch.arange(structure.used.numel(), device=faces.device)
        mapped = local[faces]
    built = structure.faces
    if torch.equal(mapped, built):  # the usual case, in one pass
        return True
    return bool(((mapped == built).all(dim=1) | (mapped == built.flip(1)).all(dim=1)).all())


def _one_mesh(
    vertices: Tensor,
    faces: Tensor,
    params: RobustParams,
    spare: int,
    progress: ProgressCallback | None = None,
    dn_only: bool = False,
    structure: RobustStructure | None = None,
) -> dict[str, Tensor | None]:
    """The channels of one mesh on all its vertices (unreferenced ones, and all of a mesh
    without faces, get plane values), in the dtype and on the device of ``vertices``.
    ``spare``: the bytes of the budget left for the heat semigroup's coefficients
    (:func:`semigroup_memory`); ``structure``: the mesh's, checked (default: built here)."""
    count = vertices.shape[0]
    if structure is None:
        structure = build_structure(vertices, faces, params, heat=not dn_only)
    else:
        structure = check_structure(structure, vertices, faces, params, dn_only)
    if faces.shape[0] == 0:
        return _plane_values(count, params, dn_only, vertices)
    # Checked before any diffusion runs: the semigroup's cost is known only from the
    # operators' spectral bounds.
    needed = semigroup_memory(structure, params)
    if needed > spare:
        raise MemoryBudgetError(
            f"diffusing a mesh of {structure.used.numel()} vertices to the robust variant's "
            f"scales needs {format_bytes(needed)} for its Chebyshev coefficients besides the "
            f"rest of the run, over the {format_bytes(max(spare, 0))} the budget leaves: its "
            "triangles differ in size by orders of magnitude (tiny ones beside large ones). "
            f"Raise the budget (max_memory=..., or ${MEMORY_ENV}), or remesh to a more even "
            "triangulation."
        )
    used = structure.used
    whole = used.numel() == count  # every vertex referenced: no copies in and out
    inside = vertices if whole else vertices[used]
    # Scale invariant: an exact power-of-two scale keeps squares finite and normal.
    points = inside * extent_scale(inside.detach())
    channels = robust_channels(points, structure, progress=progress, dn_only=dn_only)
    names = ("dn", "mass") if dn_only else ("dn", "spread", "heat", "mass")
    computed = {name: getattr(channels, name) for name in names}
    if whole:
        return {"spread": None, "heat": None, **computed}
    values = _plane_values(count, params, dn_only, vertices)
    for name, value in computed.items():
        values[name] = values[name].index_put((used,), value)
    return values


def _mesh_slices(points: Tensor, faces: Tensor, batch: Tensor):
    """Per mesh of a packed batch: ``(members (n,), faces (m, 3) local)``."""
    face_mesh = batch[faces[:, 0]]
    slices = []
    for mesh in range(int(batch.max()) + 1 if batch.numel() else 0):
        index = (batch == mesh).nonzero().flatten()
        local = torch.full_like(batch, -1)
        local[index] = torch.arange(index.numel(), device=batch.device)
        slices.append((index, local[faces[face_mesh == mesh]]))
    return slices


def _structures(structure, count: int) -> list:
    """``structure=`` of a packed batch of ``count`` meshes as a list (``None`` for each mesh
    when not given); a list or tuple of one structure per mesh."""
    if structure is None:
        return [None] * count
    if not isinstance(structure, (list, tuple)) or len(structure) != count:
        raise ParameterError(
            f"structure of a packed batch of {count} meshes must be a list of {count} "
            "RobustStructure, one per mesh in batch order (robust_structure(vertices, faces, "
            f"batch=batch)), got {type(structure).__name__}"
            + (f" of {len(structure)}" if isinstance(structure, (list, tuple)) else "")
        )
    return list(structure)


#: Bytes per vertex a robust run holds at its peak, per scale (the float64 fields and their
#: diffused copies, the channels and their prolongations: twelve fields' worth, an upper bound
#: of the nine diffused).
_BYTES_PER_VERTEX_SCALE = 12 * 8 * 6
#: ... and independent of the scales (the pyramid, the operators, the interpolation).
_BYTES_PER_VERTEX = 1600


def robust_memory(num_vertices: int, params: RobustParams) -> int:
    """Bytes a robust run on ``num_vertices`` vertices needs at its peak (linear in both),
    besides the heat semigroup's coefficients (:func:`semigroup_memory`)."""
    return num_vertices * (_BYTES_PER_VERTEX + _BYTES_PER_VERTEX_SCALE * params.num_scales)


def robust_representation(
    vertices,
    faces,
    params: RobustParams | None = None,
    batch: Tensor | None = None,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    dn_only: bool = False,
    structure: RobustStructure | list[RobustStructure] | None = None,
) -> RobustRepresentation:
    """The robust multiscale channels of a mesh, or of each mesh of a packed batch.

    Args:
        vertices: ``(V, 3)`` float32 or float64 tensor; computed on its device (only
            building a structure reads it on the CPU) and returned in its dtype, in which the
            fields are diffused; for the spread, the squared positions, the recurrence's first
            term and the 3 x 3 covariance are float64, which keeps digits float32 loses.
            Gradients reach it with the structure held constant.
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
        structure: the mesh's :class:`~stochlap_torch.diffusion.robust.RobustStructure`
            (:func:`robust_structure`), on the device of ``vertices``, built with ``params``;
            for a batch, a list of one per mesh. Default: built on every call.

    Raises:
        MeshError: bad mesh. ParameterError: bad settings, or a structure of another mesh,
            other settings or another device.
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
    spare = budget - needed
    if batch is None:
        if isinstance(structure, (list, tuple)):
            raise ParameterError("a list of structures is for a packed batch: pass batch=")
        parts = [_one_mesh(points, faces, params, spare, progress, dn_only, structure)]
        order = None
    else:
        batch = check_batch(batch, points.shape[0], faces)
        slices = _mesh_slices(points, faces, batch)
        structures = _structures(structure, len(slices))
        parts, members = [], []
        for mesh, ((index, mesh_faces), own) in enumerate(zip(slices, structures, strict=True)):
            parts.append(
                _one_mesh(points[index], mesh_faces, params, spare, dn_only=dn_only, structure=own)
            )
            members.append(index)
            if progress is not None:
                progress(mesh + 1, len(slices))
        order = torch.argsort(torch.cat(members))
    merged = {}
    for name in ("dn", "spread", "heat", "mass"):
        if parts[0][name] is None:
            merged[name] = None
            continue
        values = torch.cat([part[name] for part in parts])
        merged[name] = values if order is None else values[order]
    referenced = torch.zeros(points.shape[0], dtype=torch.bool, device=points.device)
    referenced[faces.reshape(-1)] = True
    return RobustRepresentation(**merged, referenced=referenced, params=params, batch=batch)


def robust_structure(
    vertices, faces, robust: RobustParams | None = None, batch: Tensor | None = None
) -> RobustStructure | list[RobustStructure]:
    """The :class:`~stochlap_torch.diffusion.robust.RobustStructure` of a mesh: its pyramid,
    the levels' intrinsic Laplacians and masses, the interpolation weights and the heat
    channel's coarse eigenpairs, which depend on the mesh and the settings, not on the call.

    Build it once and pass it as ``structure=`` to every robust call on the mesh
    (:func:`~stochlap_torch.features.multiscale_features`, :func:`~stochlap_torch.saliency`,
    :class:`~stochlap_torch.MultiscaleFeatures`, :class:`~stochlap_torch.MultiscaleSaliency`):
    the same numbers as a call that builds its own, without the cost of building it. Move it
    with ``.to(device)``; it pickles, and :func:`~stochlap_torch.cached_structure` keeps it on
    disk.

    Args:
        vertices: ``(V, 3)`` float tensor (any device: read on the CPU; the structure comes
            on its device).
        faces: ``(F, 3)`` integer tensor.
        robust: the settings (:class:`~stochlap_torch.diffusion.RobustParams` or a mapping of
            its fields); those of the calls it is passed to.
        batch: optional ``(V,)`` mesh index of a packed batch: then a list of one structure per
            mesh, in mesh order.

    Raises:
        MeshError: bad mesh. ParameterError: bad settings.
    """
    params = as_robust_params(robust)
    points, faces = as_mesh_tensors(vertices, faces)
    if batch is None:
        return build_structure(points, faces, params)
    batch = check_batch(batch, points.shape[0], faces)
    return [
        build_structure(points[index], mesh_faces, params)
        for index, mesh_faces in _mesh_slices(points, faces, batch)
    ]
