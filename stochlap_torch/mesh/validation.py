"""The checks every entry point runs on its input mesh.

A mesh is a pair of tensors: ``vertices`` ``(V, 3)`` float and ``faces`` ``(F, 3)`` int64.
:func:`validate_mesh` turns every way such a pair can be unusable into a :class:`MeshError`
that names the problem and the offending indices, so that no NaN or Inf ever reaches the
operators.
"""

from __future__ import annotations

import threading
import weakref

import torch

from .._common.errors import MeshError, UnsupportedInputError
from .geometry import extent_scale

__all__ = [
    "SUPPORTED_DTYPES",
    "MeshError",
    "as_mesh_tensors",
    "check_surface_area",
    "to_mesh_tensors",
    "validate_mesh",
    "zero_length_error",
]

#: How many offending indices an error message lists before it says "and N more".
_MAX_LISTED = 8


def _listing(indices: torch.Tensor) -> str:
    """Format up to :data:`_MAX_LISTED` indices: ``"[3, 7]"`` or ``"[1, 2, ...] (+5 more)"``."""
    flat = indices.reshape(-1).tolist()
    shown = ", ".join(str(i) for i in flat[:_MAX_LISTED])
    more = len(flat) - _MAX_LISTED
    return f"[{shown}]" + (f" (+{more} more)" if more > 0 else "")


def as_mesh_tensors(
    vertices, faces, check_edge_lengths: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Convert array-likes to ``(V, 3)`` float and ``(F, 3)`` int64 tensors and validate them.

    Float tensors keep their dtype and device; other inputs become float64. Faces move to the
    device of the vertices. ``check_edge_lengths`` as in :func:`validate_mesh`.
    """
    vertices, faces = to_mesh_tensors(vertices, faces)
    validate_mesh(vertices, faces, check_edge_lengths)
    return vertices, faces


#: The vertex dtypes the library computes in.
SUPPORTED_DTYPES = (torch.float32, torch.float64)


def to_mesh_tensors(vertices, faces) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`as_mesh_tensors` without the validation (for callers that validate later).

    Raises:
        UnsupportedInputError: vertices of a dtype other than float32 or float64 (integers are
            read as float64), complex vertices, or tensors on the ``meta`` device.
        MeshError: faces that are not integer indices.
    """
    if not isinstance(vertices, torch.Tensor):
        try:
            vertices = torch.as_tensor(vertices)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise UnsupportedInputError(f"vertices could not be read as an array: {exc}") from exc
    if vertices.is_complex() or vertices.dtype == torch.bool:
        raise UnsupportedInputError(
            f"vertices must be real coordinates (float32 or float64), got {vertices.dtype}"
        )
    if not vertices.is_floating_point():
        vertices = vertices.to(torch.float64)
    if vertices.dtype not in SUPPORTED_DTYPES:
        raise UnsupportedInputError(
            f"vertices must be float32 or float64, got {vertices.dtype}; cast them first, "
            "e.g. vertices.float()"
        )
    if vertices.device.type == "meta":
        raise UnsupportedInputError(
            "vertices are on the 'meta' device: they hold no values; vertices must be float32 "
            "or float64 tensors on a real device"
        )
    if not isinstance(faces, torch.Tensor):
        try:
            faces = torch.as_tensor(faces)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise MeshError(f"faces could not be read as an integer array: {exc}") from exc
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise MeshError(f"faces must hold integer vertex indices, got {faces.dtype}")
    return vertices, faces.to(device=vertices.device, dtype=torch.int64)


def validate_mesh(
    vertices: torch.Tensor, faces: torch.Tensor, check_edge_lengths: bool = True
) -> None:
    """Check a mesh and raise :class:`MeshError` naming the first problem found.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        check_edge_lengths: also reject zero-length edges. Callers that build the edge
            weights anyway (:func:`~stochlap_torch.operators.abs_laplacian` raises the same
            error) skip it here to avoid a second pass over every edge.

    A pair of tensors that passed is remembered (by identity and version counter, weakly):
    checking it again, unmodified, costs nothing, so entry points can validate every call.

    Raises:
        MeshError: for a wrong shape or dtype, an empty mesh, non-finite coordinates, face
            indices that are negative or ``>= V``, a face that repeats a vertex, or an edge of
            zero length.
    """
    if _VALIDATED.passed(vertices, faces, check_edge_lengths):
        return
    _check(vertices, faces, check_edge_lengths)
    _VALIDATED.remember(vertices, faces, check_edge_lengths)


def _check(vertices: torch.Tensor, faces: torch.Tensor, check_edge_lengths: bool) -> None:
    """The checks of :func:`validate_mesh`."""
    if vertices.ndim != 2 or vertices.shape[-1] != 3:
        raise MeshError(f"vertices must have shape (V, 3), got {tuple(vertices.shape)}")
    if not vertices.is_floating_point():
        raise MeshError(f"vertices must be a float tensor, got {vertices.dtype}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        raise MeshError(f"faces must have shape (F, 3) (triangles), got {tuple(faces.shape)}")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise MeshError(f"faces must hold integer vertex indices, got {faces.dtype}")
    num_vertices = vertices.shape[0]
    if num_vertices == 0:
        raise MeshError("empty mesh: it has no vertices")
    if faces.shape[0] == 0:
        raise MeshError("empty mesh: it has no faces, so no edges to build a Laplacian from")

    bad_rows = (~torch.isfinite(vertices)).any(dim=1).nonzero().flatten()
    if bad_rows.numel():
        raise MeshError(
            f"{bad_rows.numel()} vertices have non-finite coordinates (NaN or Inf): "
            f"vertex indices {_listing(bad_rows)}"
        )

    faces = faces.to(device=vertices.device, dtype=torch.int64)
    out_of_range = ((faces < 0) | (faces >= num_vertices)).any(dim=1).nonzero().flatten()
    if out_of_range.numel():
        first = faces[out_of_range[0]].tolist()
        raise MeshError(
            f"{out_of_range.numel()} faces have vertex indices outside [0, {num_vertices}): "
            f"face indices {_listing(out_of_range)}; face {out_of_range[0].item()} is {first}"
        )

    a, b, c = faces.unbind(dim=1)
    repeated = ((a == b) | (b == c) | (c == a)).nonzero().flatten()
    if repeated.numel():
        first = faces[repeated[0]].tolist()
        raise MeshError(
            f"{repeated.numel()} degenerate faces repeat a vertex: face indices "
            f"{_listing(repeated)}; face {repeated[0].item()} is {first}"
        )

    if check_edge_lengths:
        # Edge (c, c + 1 mod 3) of every face; one gather of the corners keeps the
        # temporaries small. At the size the operators are built at (extent_scale), so that
        # only edges that are zero there, not merely tiny or huge in the caller's units, count.
        corners = vertices.detach()[faces]
        scale = extent_scale(vertices.detach())
        if scale != 1.0:
            corners.mul_(scale)
        lengths_sq = (corners - corners.roll(-1, dims=1)).square_().sum(dim=2)
        too_short = ~torch.isfinite(lengths_sq.reciprocal_())
        if too_short.any():
            raise zero_length_error(torch.stack([faces, faces.roll(-1, dims=1)], dim=2)[too_short])


#: A mesh has no surface area when the sum of its faces' ``|cross|`` (twice their areas) is at
#: most this many rounding units of its coordinates times its extent: the cross product of a
#: face whose vertices lie on a line, each rounded to the dtype, is a few such units.
_AREA_ROUNDING = 64.0


def check_surface_area(vertices: torch.Tensor, faces: torch.Tensor) -> None:
    """Raise :class:`MeshError` if the mesh has no surface area: the vertices of every face
    are collinear, exactly or to the precision of the dtype of ``vertices``.

    A measure the robust variant needs (its scales are fractions of the surface area); the
    paper variant's weights need edge lengths only. ``vertices`` ``(V, 3)`` float, ``faces``
    ``(F, 3)`` int64, already validated (:func:`validate_mesh`).
    """
    points = vertices.detach().double()
    scale = extent_scale(vertices.detach())  # exact: no overflow or underflow in the squares
    corners = points[faces] * scale
    cross = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    doubled = cross.norm(dim=1)
    used = points[faces.reshape(-1)] * scale
    extent = float((used.amax(dim=0) - used.amin(dim=0)).max())
    rounding = torch.finfo(vertices.dtype).eps * float(used.abs().max())
    threshold = _AREA_ROUNDING * rounding * extent
    if float(doubled.sum()) > threshold:
        return
    flat = (doubled <= threshold).nonzero().flatten()
    raise MeshError(
        f"the mesh has no surface area: all {faces.shape[0]} faces are degenerate (the three "
        f"vertices of each are collinear, to the precision of {vertices.dtype}): face indices "
        f"{_listing(flat)}. The robust variant measures its scales in units of the surface "
        "area; use variant='paper', or give the mesh faces that span an area."
    )


class _ValidatedMeshes:
    """Tensor pairs that passed :func:`validate_mesh`, by identity and version counter.

    Entries hold weak references only and go when either tensor is freed; a tensor changed in
    place (its version counter moved) is checked again. Inference tensors, which carry no
    version counter, are never remembered.
    """

    def __init__(self) -> None:
        self._entries: dict[tuple[int, int], tuple] = {}
        self._lock = threading.RLock()  # a weakref callback may run inside remember()

    @staticmethod
    def _state(vertices: torch.Tensor, faces: torch.Tensor):
        if vertices.is_inference() or faces.is_inference():
            return None
        return (vertices._version, faces._version)

    def passed(self, vertices: torch.Tensor, faces: torch.Tensor, edge_lengths: bool) -> bool:
        state = self._state(vertices, faces)
        if state is None:
            return False
        with self._lock:
            entry = self._entries.get((id(vertices), id(faces)))
        if entry is None:
            return False
        refs, versions, checked_lengths = entry
        same = refs[0]() is vertices and refs[1]() is faces and versions == state
        return same and (checked_lengths or not edge_lengths)

    def remember(self, vertices: torch.Tensor, faces: torch.Tensor, edge_lengths: bool) -> None:
        state = self._state(vertices, faces)
        if state is None:
            return
        key = (id(vertices), id(faces))

        def forget(_, key=key):
            with self._lock:
                self._entries.pop(key, None)

        refs = (weakref.ref(vertices, forget), weakref.ref(faces, forget))
        with self._lock:
            self._entries[key] = (refs, state, edge_lengths)


_VALIDATED = _ValidatedMeshes()


def zero_length_error(edges: torch.Tensor) -> MeshError:
    """The error for ``(E, 2)`` edges whose ``1/|Pi-Pj|^2`` weight is not finite."""
    zero_edges = torch.unique(edges.sort(dim=1).values, dim=0)
    pairs = ", ".join(f"({i}, {j})" for i, j in zero_edges[:_MAX_LISTED].tolist())
    more = zero_edges.shape[0] - _MAX_LISTED
    return MeshError(
        f"{zero_edges.shape[0]} edges have zero length (coincident vertices joined by an "
        f"edge give an infinite 1/|Pi-Pj|^2 weight): vertex pairs {pairs}"
        + (f" (+{more} more)" if more > 0 else "")
        + ". Merge duplicate vertices first (load_mesh(..., merge_seams=True) or "
        "trimesh's merge_vertices) and drop the faces that collapse."
    )
