"""The robust variant's operator object (:class:`RobustStructure`), built once per mesh, and
the calls that build or check it."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from .._common.checks import format_bytes
from .._common.errors import ParameterError
from ..diffusion.memory import MEMORY_ENV, MemoryBudgetError, resolve_budget
from ..diffusion.parameters import ProgressCallback
from ..mesh import as_mesh_tensors, check_batch, extent_scale
from ..mesh.geometry import check_not_soup
from ..mesh.validation import check_surface_area, to_mesh_tensors, validate_mesh
from ..params import RobustParams, resolve_params
from .channels import (
    RobustRepresentation,
    plane_values,
    robust_channel_names,
    robust_features,
    robust_saliency,
    scale_channels,
    unit_area,
)
from .heat import MAX_CHEBYSHEV_TERMS, chebyshev_terms
from .pyramid import StateReader, StructureLevel, canonical_faces, structure_levels

#: The version of :meth:`RobustStructure.state_dict`'s layout.
FORMAT_VERSION = 4
#: A structure serves positions within this RMS distance (in sqrt(area), after the best
#: similarity) of those it was built on: the small moves of gradient steps and an
#: augmentation's jitter (a third of an edge on spot is 0.024), not another pose or a stretch.
SHAPE_TOLERANCE = 0.05
#: More pyramid levels than this is no pyramid of a mesh (each level is ``ratio`` smaller).
_MAX_LEVELS = 64


@dataclass
class RobustStructure:
    """The robust variant's operator of one mesh: what its channels need besides its
    positions, built once (:func:`robust_structure`) and applied to positions on any device
    (:meth:`to`), held constant. Saved and pickled through :meth:`state_dict`.

    Attributes:
        params: the :class:`RobustParams` it was built with.
        num_vertices: ``V``, the mesh's vertices (those no face uses included).
        num_faces: ``F``.
        used: ``(U,)`` int64 the vertices faces use, ascending.
        faces: ``(F, 3)`` int64 the faces among ``used``, wound one way.
        levels: the pyramid, level 0 the mesh
            (:class:`~stochlap_torch.robust.pyramid.StructureLevel`); empty without faces.
        assignment: the level of every scale.
        heat: ``(U, H)`` float64 log heat kernel diagonal at the scales ``t >= heat_from``;
            ``None`` if built without it (the saliency does not need it).
        shape: ``(U, 3)`` float64 the used vertices as built, centred at unit area: a call
            at positions farther than ``SHAPE_TOLERANCE`` from them is refused.
    """

    params: RobustParams
    num_vertices: int
    num_faces: int
    used: Tensor
    faces: Tensor
    levels: list[StructureLevel]
    assignment: list[int]
    heat: Tensor | None
    shape: Tensor

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
            shape=self.shape.to(device),
        )

    def channel_names(self) -> list[str]:
        """The names of the columns of :meth:`features`."""
        return robust_channel_names(self.params)

    def representation(
        self,
        vertices,
        *,
        dn_only: bool = False,
        progress: ProgressCallback | None = None,
        max_memory: int | None = None,
    ) -> RobustRepresentation:
        """The robust channels of the mesh at new positions.

        Args:
            vertices: ``(V, 3)`` float32 or float64 positions of the mesh it was built on, up
                to a similarity and ``SHAPE_TOLERANCE``, on its device; the channels come in
                their dtype, and gradients reach them.
            dn_only: compute ``dn`` alone, all the saliency needs (``spread`` and ``heat``
                are then ``None``).
            progress: called as ``progress(k, T)`` as the scales are done (``None``: no reports).
            max_memory: byte budget (default: ``$STOCHLAP_MAX_MEMORY``, else half the physical
                memory).

        Raises:
            MeshError: bad positions. ParameterError: another vertex count, another device,
                another shape, or no heat channel for the features. MemoryBudgetError: over
                the budget.
        """
        points, faces = to_mesh_tensors(vertices, self.used[self.faces])
        self._check_call(points.shape[0], points.device, dn_only)
        validate_mesh(points, faces.to(points.device), check_edge_lengths=False)
        spare = _spare_memory(points.shape[0], self.params, max_memory)
        return self._representation(points, spare, progress, dn_only)

    def features(self, vertices) -> Tensor:
        """``(V, C)`` the robust features at ``vertices`` ``(V, 3)`` (:meth:`channel_names`)."""
        return robust_features(self.representation(vertices))

    def saliency(self, vertices) -> Tensor:
        """``(V,)`` the robust saliency at ``vertices`` ``(V, 3)``."""
        return robust_saliency(self.representation(vertices, dn_only=True))

    def _check_call(self, count: int, device: torch.device, dn_only: bool) -> None:
        if count != self.num_vertices:
            raise ParameterError(
                f"structure was built for a mesh of {self.num_vertices} vertices, not "
                f"{count}: build it from the same mesh (robust_structure(vertices, faces))"
            )
        if self.device != device:
            raise ParameterError(
                f"structure is on {self.device}, the vertices on {device}: move it once with "
                "structure.to(device)"
            )
        if not dn_only and self.heat is None and self.num_faces:
            raise ParameterError("structure was built without the heat channel the features need")

    def _check_shape(self, unit: Tensor) -> None:
        """Refuse positions (``unit``: ``(U, 3)`` centred at unit area) that are not, up to a
        similarity, those it was built on: they would get the other shape's pyramid, silently."""
        unit = unit.detach().to(torch.float64)
        # Orthogonal Procrustes: the rotation, or a reflection (the structure serves a mirror
        # image, whose channels are the same but the twist's sign).
        left, _, right = torch.linalg.svd(unit.T @ self.shape)
        deviation = float((unit @ (left @ right) - self.shape).square().sum(dim=1).mean().sqrt())
        if not deviation <= SHAPE_TOLERANCE:
            raise ParameterError(
                f"structure was built for another shape of this mesh: these positions are "
                f"{deviation:.3g} sqrt(area) RMS from those it was built on after the best "
                f"rotation, translation and scale (over {SHAPE_TOLERANCE}: another pose, or a "
                "stretched copy). Build it from these positions (robust_structure(vertices, "
                "faces))"
            )

    def _representation(
        self, points: Tensor, spare: int, progress, dn_only: bool
    ) -> RobustRepresentation:
        """:meth:`representation` of validated ``points`` ``(V, 3)``; ``spare``: the budget's
        bytes left for the semigroup's coefficients (:func:`semigroup_memory`)."""
        params, count, used = self.params, self.num_vertices, self.used
        referenced = torch.zeros(count, dtype=torch.bool, device=points.device)
        referenced[used] = True
        if self.num_faces == 0:
            values = plane_values(count, params, dn_only, points)
            return RobustRepresentation(**values, referenced=referenced, params=params)
        # Checked before any diffusion runs (the cost follows the operators' spectral bounds).
        needed = semigroup_memory(self, params)
        if needed > spare:
            raise MemoryBudgetError(
                f"diffusing a mesh of {used.numel()} vertices to the robust variant's scales "
                f"needs {format_bytes(needed)} for its Chebyshev coefficients besides the rest "
                f"of the run, over the {format_bytes(max(spare, 0))} the budget leaves: its "
                "triangles differ in size by orders of magnitude (tiny ones beside large "
                f"ones). Raise the budget (max_memory=..., or ${MEMORY_ENV}), or remesh to a "
                "more even triangulation."
            )
        whole = used.numel() == count  # every vertex referenced: no copies in and out
        inside = points if whole else points[used]
        # Scale invariant: an exact power-of-two scale keeps squares finite and normal.
        unit, mass = unit_area(inside * extent_scale(inside.detach()), self.faces)
        self._check_shape(unit)
        dn, spread, twist = scale_channels(
            unit, self.levels, self.assignment, params, progress, dn_only
        )
        heat = None if dn_only else self.heat.to(points.dtype)
        values = {"dn": dn, "spread": spread, "twist": twist, "heat": heat, "mass": mass}
        if not whole:
            plane = plane_values(count, params, dn_only, points)
            values = {
                name: None if value is None else plane[name].index_put((used,), value)
                for name, value in values.items()
            }
        return RobustRepresentation(**values, referenced=referenced, params=params)

    def state_dict(self) -> dict[str, Tensor]:
        """The structure as flat named CPU tensors: ``format_version``, ``params.<field>``,
        the attributes, ``num_levels`` and per level ``levels.<i>.vertex_ids``, ``faces``,
        ``labels``, its interpolation's ``corners``, ``weights`` (``i > 0``) and its operator's
        ``crow``, ``col``, ``val``, ``order``, ``capped_mass``, ``bound`` (if it has one).
        Loadable with ``torch.load(weights_only=True)``, or as numpy arrays."""
        state = {"format_version": torch.tensor(FORMAT_VERSION)}
        for field in dataclasses.fields(RobustParams):
            value = getattr(self.params, field.name)
            state[f"params.{field.name}"] = torch.tensor(value, dtype=_param_dtype(field))
        state |= {
            "num_vertices": torch.tensor(self.num_vertices),
            "num_faces": torch.tensor(self.num_faces),
            "used": self.used,
            "faces": self.faces,
            "assignment": torch.tensor(self.assignment, dtype=torch.int64),
            "num_levels": torch.tensor(len(self.levels)),
        }
        if self.heat is not None:
            state["heat"] = self.heat
        state["shape"] = self.shape
        for index, level in enumerate(self.levels):
            state |= level.state_dict(f"levels.{index}.")
        return {name: value.detach().to("cpu", copy=True) for name, value in state.items()}

    @classmethod
    @torch.inference_mode(False)  # a structure loaded under inference mode serves gradients too
    def from_state_dict(cls, state: Mapping) -> RobustStructure:
        """The structure of a :meth:`state_dict` (tensors or numpy arrays), on the CPU, every
        entry checked: ``ValueError`` names one missing, unknown, malformed or out of range."""
        reader = StateReader(state)
        if reader.count("format_version") != FORMAT_VERSION:
            raise ValueError(f"format_version: not {FORMAT_VERSION}")
        values = {
            field.name: reader.get(f"params.{field.name}", _param_dtype(field), ()).item()
            for field in dataclasses.fields(RobustParams)
        }
        try:
            params = RobustParams(**values)
        except ParameterError as error:
            raise ValueError(f"params: {error}") from None
        count, num_faces = reader.count("num_vertices"), reader.count("num_faces")
        used = reader.get("used", torch.int64, (None,), 0, count)
        size = used.numel()
        if size > 1 and bool((used.diff() <= 0).any()):
            raise ValueError("used: not strictly ascending")
        faces = reader.get("faces", torch.int64, (num_faces, 3), 0, size)
        num_levels = reader.count("num_levels", _MAX_LEVELS + 1)
        if (num_levels == 0) != (num_faces == 0):
            raise ValueError(f"num_levels: {num_levels} for {num_faces} faces")
        scales = params.num_scales if num_levels else 0
        assignment = reader.get("assignment", torch.int64, (scales,), 0, num_levels).tolist()
        # Centred at unit area: a coordinate beyond 1e6 is a strip of width 1e-6, no mesh.
        shape = reader.get("shape", torch.float64, (size, 3))
        if shape.numel() and float(shape.abs().max()) > 1e6:
            raise ValueError("shape: positions far outside a unit-area mesh")
        heat = None
        if "heat" in reader:
            width = len(params.heat_scales)
            heat = reader.get("heat", torch.float64, (size, width))
            # A log of a float64 lies within +-709.8: anything past it is no heat channel.
            if heat.numel() and float(heat.abs().max()) > 710.0:
                raise ValueError("heat: values outside the range of a log heat kernel")
        levels, above = [], None
        for index in range(num_levels):
            levels.append(StructureLevel.from_state(reader, f"levels.{index}.", size, above))
            above = levels[-1].num_vertices
        if levels and not (
            torch.equal(levels[0].vertex_ids, torch.arange(size))
            and torch.equal(levels[0].faces, faces)
        ):
            raise ValueError("levels.0.vertex_ids, levels.0.faces: not the mesh itself")
        if any(levels[index].semigroup is None for index in assignment):
            raise ValueError("assignment: a scale runs on a level without an operator")
        reader.check_all_read()
        return cls(params, count, num_faces, used, faces, levels, assignment, heat, shape)

    def __reduce__(self):
        return (RobustStructure.from_state_dict, (self.state_dict(),))

    def __deepcopy__(self, memo) -> RobustStructure:
        return RobustStructure.from_state_dict(self.state_dict()).to(self.device)

    def __repr__(self) -> str:
        sizes = [level.num_vertices for level in self.levels]
        return (
            f"RobustStructure(num_vertices={self.num_vertices}, num_faces={self.num_faces}, "
            f"levels={sizes}, assignment={self.assignment}, heat={self.heat is not None}, "
            f"device={self.device}, params={self.params!r})"
        )


def _param_dtype(field: dataclasses.Field) -> torch.dtype:
    return torch.int64 if isinstance(field.default, int) else torch.float64


@torch.inference_mode(False)  # a structure built under inference mode serves gradients too
def build_structure(
    vertices: Tensor, faces: Tensor, params: RobustParams, heat: bool = True
) -> RobustStructure:
    """The :class:`RobustStructure` of a validated mesh (``(V, 3)`` float on any device, read
    on the CPU; ``(F, 3)`` int64), on the device of ``vertices``; without the heat channel if
    not ``heat``. The decimation rounds to float32: a float32 copy can get another pyramid.

    Raises:
        MeshError: the mesh has no area (``check_surface_area``).
        TriangleSoupError: most faces share no vertex with another
            (:func:`~stochlap_torch.mesh.geometry.check_not_soup`).
    """
    device = vertices.device
    points = vertices.detach().to("cpu", torch.float64)
    faces = faces.to("cpu")
    count = points.shape[0]
    if faces.shape[0] == 0:
        nothing = torch.zeros(0, dtype=torch.int64)
        empty = torch.zeros(0, 3, dtype=torch.float64)
        return RobustStructure(params, count, 0, nothing, faces, [], [], None, empty).to(device)
    check_surface_area(points, faces)
    used = torch.unique(faces)
    local = torch.full((count,), -1, dtype=torch.int64)
    local[used] = torch.arange(used.numel())
    local_faces = local[faces]
    check_not_soup(local_faces.numpy())
    # Scale invariant: an exact power-of-two scale keeps squares finite and normal.
    scaled = points[used] * extent_scale(points[used])
    canonical = canonical_faces(scaled, local_faces)
    unit = unit_area(scaled, canonical)[0]
    levels, assignment, values = structure_levels(unit.numpy(), canonical, params, heat)
    structure = RobustStructure(
        params, count, faces.shape[0], used, canonical, levels, assignment, values, unit
    )
    return structure.to(device)


def semigroup_memory(structure: RobustStructure, params: RobustParams) -> int:
    """Bytes the heat semigroup's Chebyshev coefficients take at their peak: per level a ``(T,
    terms)`` float64 table for its largest time, two while it is built, and a few rows."""
    times = params.times
    peak = 0
    for index, level in enumerate(structure.levels):
        if level.semigroup is None:
            continue
        level_times = [times[k] for k, chosen in enumerate(structure.assignment) if chosen == index]
        if not level_times:
            continue
        scaled = max(level_times) * level.semigroup.bound / 2.0
        if not scaled <= MAX_CHEBYSHEV_TERMS:
            continue  # the semigroup refuses such a level (MeshError) before it allocates
        terms = chebyshev_terms(scaled, params.tolerance)
        peak = max(peak, (2 * len(level_times) + 8) * terms * 8)
    return peak


#: Bytes per vertex and scale a robust run holds at its peak (twelve float64 fields' worth).
_BYTES_PER_VERTEX_SCALE = 12 * 8 * 6
#: ... and independent of the scales (the pyramid, the operators, the interpolation).
_BYTES_PER_VERTEX = 1600


def robust_memory(num_vertices: int, params: RobustParams) -> int:
    """Bytes a robust run on ``num_vertices`` vertices needs at its peak (linear in both),
    besides the heat semigroup's coefficients (:func:`semigroup_memory`)."""
    return num_vertices * (_BYTES_PER_VERTEX + _BYTES_PER_VERTEX_SCALE * params.num_scales)


def _spare_memory(count: int, params: RobustParams, max_memory: int | None) -> int:
    """The bytes of the budget a run on ``count`` vertices leaves for the semigroup's
    coefficients; :class:`MemoryBudgetError` if the rest of the run exceeds it."""
    budget = resolve_budget(max_memory)
    needed = robust_memory(count, params)
    if needed > budget:
        raise MemoryBudgetError(
            f"the robust representation of {count} vertices at {params.num_scales} scales "
            f"needs about {format_bytes(needed)}, over the budget of {format_bytes(budget)}. "
            f"Raise the budget (max_memory=..., or ${MEMORY_ENV})."
        )
    return budget - needed


def check_structure(
    structure, vertices: Tensor, faces: Tensor, params: RobustParams, dn_only: bool
) -> RobustStructure:
    """``structure`` if it is the :class:`RobustStructure` of ``vertices`` ``(V, 3)`` and
    ``faces`` ``(F, 3)`` at ``params`` (with the heat channel unless ``dn_only``), on their
    device; else :class:`ParameterError` saying what differs."""
    if not isinstance(structure, RobustStructure):
        raise ParameterError(
            "structure must be a RobustStructure (stochlap_torch.robust_structure(vertices, "
            f"faces)), got {type(structure).__name__}"
        )
    structure._check_call(vertices.shape[0], vertices.device, dn_only)
    if structure.params != params:
        raise ParameterError(
            f"structure was built with {structure.params!r}, the call asks for {params!r}: "
            "build it with the call's settings (robust_structure(..., robust=...))"
        )
    if not _same_faces(structure, faces):
        raise ParameterError(
            f"structure was built for other faces ({structure.num_faces}, this mesh has "
            f"{faces.shape[0]}; or these vertices renumbered): build it from this mesh "
            "(robust_structure(vertices, faces))"
        )
    return structure


def _same_faces(structure: RobustStructure, faces: Tensor) -> bool:
    """Whether ``faces`` ``(F, 3)`` int64 are the structure's, each as built or reversed."""
    built = structure.used[structure.faces]
    if faces.shape != built.shape:
        return False
    if torch.equal(faces, built):  # the usual case, in one pass
        return True
    return bool(((faces == built).all(dim=1) | (faces == built.flip(1)).all(dim=1)).all())


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
        vertices: ``(V, 3)`` float32 or float64 tensor.
        faces: ``(F, 3)`` integer tensor.
        params: :class:`RobustParams` (``None``: ``RobustParams()``, the defaults).
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch (``None``:
            one mesh; results equal separate runs).
        max_memory, dn_only: as :meth:`RobustStructure.representation`.
        progress: called as ``progress(k, T)`` as the scales of a mesh are done; for a batch,
            as ``progress(i, B)`` after each of its ``B`` meshes (``None``: no reports).
        structure: the mesh's :class:`RobustStructure` (:func:`robust_structure`) at
            ``params``; for a batch, a list of one per mesh. Default: built on every call.

    Raises:
        MeshError: bad mesh. ParameterError: bad settings, or a structure of another mesh,
            other settings or another device. MemoryBudgetError: over the budget.
    """
    params = resolve_params(RobustParams, "robust", {"robust": params})
    points, faces = as_mesh_tensors(vertices, faces, check_edge_lengths=False)
    spare = _spare_memory(points.shape[0], params, max_memory)

    def one(points: Tensor, faces: Tensor, given, progress) -> RobustRepresentation:
        if given is None:
            given = build_structure(points, faces, params, heat=not dn_only)
        else:
            check_structure(given, points, faces, params, dn_only)
        return given._representation(points, spare, progress, dn_only)

    if batch is None:
        if isinstance(structure, (list, tuple)):
            raise ParameterError("a list of structures is for a packed batch: pass batch=")
        return one(points, faces, structure, progress)
    batch = check_batch(batch, points.shape[0], faces)
    slices = _mesh_slices(points, faces, batch)
    if structure is None:
        structure = [None] * len(slices)
    elif not isinstance(structure, (list, tuple)) or len(structure) != len(slices):
        raise ParameterError(
            f"structure of a packed batch of {len(slices)} meshes must be a list of "
            f"{len(slices)} RobustStructure, one per mesh in batch order (robust_structure("
            f"vertices, faces, batch=batch)), got {type(structure).__name__}"
            + (f" of {len(structure)}" if isinstance(structure, (list, tuple)) else "")
        )
    parts, members = [], []
    for mesh, ((index, mesh_faces), own) in enumerate(zip(slices, structure, strict=True)):
        parts.append(one(points[index], mesh_faces, own, None))
        members.append(index)
        if progress is not None:
            progress(mesh + 1, len(slices))
    order = torch.argsort(torch.cat(members))
    merged = {
        name: None
        if getattr(parts[0], name) is None
        else torch.cat([getattr(part, name) for part in parts])[order]
        for name in ("dn", "spread", "twist", "heat", "mass", "referenced")
    }
    return RobustRepresentation(**merged, params=params, batch=batch)


def robust_structure(
    vertices,
    faces,
    robust: RobustParams | None = None,
    batch: Tensor | None = None,
    **options,
) -> RobustStructure | list[RobustStructure]:
    """The :class:`RobustStructure` of a mesh: what depends on the mesh and the settings, not
    on the positions. Build it once and apply it (:meth:`RobustStructure.features`, ...), or
    pass it as ``structure=`` to the robust calls on the mesh.

    Args:
        vertices: ``(V, 3)`` float tensor, on the device the structure comes on.
        faces: ``(F, 3)`` integer tensor.
        robust: the settings (:class:`RobustParams` or a mapping of its fields; ``None``: the
            defaults, or ``**options``).
        batch: optional ``(V,)`` mesh index of a packed batch: then a list of one structure per
            mesh (``None``: one mesh, one structure).
        **options: fields of :class:`RobustParams` as keywords (``num_scales=5``, ...), or the
            object as ``params=``, as the robust calls take them.

    Raises:
        MeshError: bad mesh. ParameterError: bad settings.
    """
    params = resolve_params(RobustParams, "robust", {"robust": robust, **options})
    points, faces = as_mesh_tensors(vertices, faces, check_edge_lengths=False)
    if batch is None:
        return build_structure(points, faces, params)
    batch = check_batch(batch, points.shape[0], faces)
    return [
        build_structure(points[index], mesh_faces, params)
        for index, mesh_faces in _mesh_slices(points, faces, batch)
    ]
