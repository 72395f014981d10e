"""The checks every entry point runs once on its input mesh (a :class:`MeshError` naming the
problem and the offending indices, so that no NaN or Inf reaches the operators; the helpers
behind an entry point take validated tensors), and :func:`mesh_report`.
"""

from __future__ import annotations

import numpy as np
import torch

from .._common.errors import MeshError, UnsupportedInputError
from .geometry import connected_components, extent_scale

__all__ = ["MeshError", "as_mesh_tensors", "mesh_report", "to_mesh_tensors", "validate_mesh"]

#: The vertex dtypes the library computes in.
SUPPORTED_DTYPES = (torch.float32, torch.float64)
#: How many offending indices an error message lists before it says "and N more".
_MAX_LISTED = 8
#: A mesh has no surface area when the sum of its faces' ``|cross|`` (twice their areas) is at
#: most this many rounding units of its coordinates times its extent: the cross product of a
#: face whose vertices lie on a line, each rounded to the dtype, is a few such units.
_AREA_ROUNDING = 64.0


def _listing(items: list, brackets: str = "[]") -> str:
    """Up to :data:`_MAX_LISTED` items: ``"[3, 7]"`` or ``"[1, 2, ...] (+5 more)"``."""
    more = len(items) - _MAX_LISTED
    shown = ", ".join(map(str, items[:_MAX_LISTED]))
    return brackets[:1] + shown + brackets[1:] + (f" (+{more} more)" if more > 0 else "")


def _read(array, what: str, error: type[Exception], kind: str) -> torch.Tensor:
    """``array`` as a tensor, or ``error`` saying that ``what`` could not be read as ``kind``."""
    if isinstance(array, torch.Tensor):
        return array
    try:
        return torch.as_tensor(array)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise error(f"{what} could not be read as {kind}: {exc}") from exc


def to_mesh_tensors(vertices, faces) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`as_mesh_tensors` without the validation (for callers that validate later).

    Raises:
        UnsupportedInputError: vertices of a dtype other than float32 or float64 (integers are
            read as float64), complex vertices, or tensors on the ``meta`` device.
        MeshError: faces that are not integer indices.
    """
    vertices = _read(vertices, "vertices", UnsupportedInputError, "an array")
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
    faces = _read(faces, "faces", MeshError, "an integer array")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise MeshError(f"faces must hold integer vertex indices, got {faces.dtype}")
    return vertices, faces.to(device=vertices.device, dtype=torch.int64)


def as_mesh_tensors(
    vertices, faces, check_edge_lengths: bool = True
) -> tuple[torch.Tensor, torch.Tensor]:
    """Array-likes as validated ``(V, 3)`` float and ``(F, 3)`` int64 tensors: float tensors
    keep their dtype and device, other inputs become float64, faces move to the vertices'
    device. ``check_edge_lengths`` as in :func:`validate_mesh`."""
    vertices, faces = to_mesh_tensors(vertices, faces)
    validate_mesh(vertices, faces, check_edge_lengths)
    return vertices, faces


def validate_mesh(
    vertices: torch.Tensor, faces: torch.Tensor, check_edge_lengths: bool = True
) -> None:
    """Check a mesh and raise :class:`MeshError` naming the first problem found.

    Args:
        vertices, faces: ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        check_edge_lengths: also reject zero-length edges (callers whose edge weights raise
            the same error skip it).

    Raises:
        MeshError: a wrong shape (with a hint for PyG's ``(3, F)`` faces and batched
            ``(B, V, 3)`` tensors) or dtype, an empty mesh, non-finite coordinates, face
            indices outside ``[0, V)``, a face that repeats a vertex, a zero-length edge.
    """
    batched = "; for several meshes, pack them with batch= (stochlap_torch.MeshBatch)"
    if vertices.ndim != 2 or vertices.shape[-1] != 3:
        hint = batched if vertices.ndim == 3 and vertices.shape[-1] == 3 else ""
        raise MeshError(f"vertices must have shape (V, 3), got {tuple(vertices.shape)}{hint}")
    if not vertices.is_floating_point():
        raise MeshError(f"vertices must be a float tensor, got {vertices.dtype}")
    if faces.ndim != 2 or faces.shape[-1] != 3:
        hint = batched if faces.ndim == 3 and faces.shape[-1] == 3 else ""
        if faces.ndim == 2 and faces.shape[0] == 3:
            hint = "; PyG stores faces as (3, F): pass face.T"
        raise MeshError(f"faces must have shape (F, 3) (triangles), got {tuple(faces.shape)}{hint}")
    if faces.is_floating_point() or faces.is_complex() or faces.dtype == torch.bool:
        raise MeshError(f"faces must hold integer vertex indices, got {faces.dtype}")
    num_vertices = vertices.shape[0]
    if num_vertices == 0:
        raise MeshError("empty mesh: it has no vertices")
    if faces.shape[0] == 0:
        raise MeshError("empty mesh: it has no faces, so no edges to build a Laplacian from")

    bad_rows = (~torch.isfinite(vertices)).any(dim=1).nonzero().flatten().tolist()
    if bad_rows:
        raise MeshError(
            f"{len(bad_rows)} vertices have non-finite coordinates (NaN or Inf): "
            f"vertex indices {_listing(bad_rows)}"
        )

    faces = faces.to(device=vertices.device, dtype=torch.int64)
    outside = f"faces have vertex indices outside [0, {num_vertices})"
    for problem, bad in (
        (outside, (faces < 0) | (faces >= num_vertices)),
        ("degenerate faces repeat a vertex", faces == faces.roll(-1, dims=1)),
    ):
        rows = bad.any(dim=1).nonzero().flatten().tolist()
        if rows:
            raise MeshError(
                f"{len(rows)} {problem}: face indices {_listing(rows)}; face {rows[0]} is "
                f"{faces[rows[0]].tolist()}"
            )

    if check_edge_lengths:
        # At the size the operators are built at (extent_scale): edges merely tiny in the
        # caller's units pass.
        corners = vertices.detach()[faces]
        scale = extent_scale(vertices.detach())
        if scale != 1.0:
            corners.mul_(scale)
        lengths_sq = (corners - corners.roll(-1, dims=1)).square_().sum(dim=2)
        too_short = ~torch.isfinite(lengths_sq.reciprocal_())
        if too_short.any():
            raise zero_length_error(torch.stack([faces, faces.roll(-1, dims=1)], dim=2)[too_short])


def zero_length_error(edges: torch.Tensor) -> MeshError:
    """The error for ``(E, 2)`` edges whose ``1/|Pi-Pj|^2`` weight is not finite."""
    pairs = [tuple(pair) for pair in torch.unique(edges.sort(dim=1).values, dim=0).tolist()]
    return MeshError(
        f"{len(pairs)} edges have zero length (coincident vertices joined by an edge give an "
        f"infinite 1/|Pi-Pj|^2 weight): vertex pairs {_listing(pairs, '')}. "
        "Merge duplicate vertices first (load_mesh(..., merge_seams=True) or trimesh's "
        "merge_vertices) and drop the faces that collapse."
    )


def check_surface_area(vertices: torch.Tensor, faces: torch.Tensor) -> None:
    """Raise :class:`MeshError` if the validated mesh has no surface area: the vertices of
    every face are collinear, exactly or to the precision of the dtype of ``vertices`` (the
    robust variant's scales are fractions of the surface area)."""
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
    flat = (doubled <= threshold).nonzero().flatten().tolist()
    raise MeshError(
        f"the mesh has no surface area: all {faces.shape[0]} faces are degenerate (the three "
        f"vertices of each are collinear, to the precision of {vertices.dtype}): face indices "
        f"{_listing(flat)}. The robust variant measures its scales in units of the surface "
        "area; use variant='paper', or give the mesh faces that span an area."
    )


def mesh_report(mesh) -> dict:
    """Counts and checks of a :class:`~stochlap_torch.mesh.Mesh`, as ``stochlap info`` prints.

    Returns:
        A JSON-serialisable dict: vertex, face, edge, boundary-edge, non-manifold-edge,
        unreferenced-vertex and component counts, orientation consistency, bounding box,
        mean edge length, and whether :func:`validate_mesh` passes in float64 and in float32
        (``True`` or the error message).
    """
    vertices = mesh.vertices.detach().cpu().double().numpy()
    faces = mesh.faces.detach().cpu().numpy().astype(np.int64)
    num_vertices = vertices.shape[0]
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges, per_edge = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    _, per_directed = np.unique(directed, axis=0, return_counts=True)
    referenced = np.zeros(num_vertices, dtype=bool)
    referenced[faces.reshape(-1)] = True
    labels = connected_components(num_vertices, edges)
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    low, high = vertices[referenced].min(axis=0), vertices[referenced].max(axis=0)

    def check(dtype: torch.dtype):
        try:
            validate_mesh(mesh.vertices.to(dtype), mesh.faces)
        except MeshError as exc:
            return str(exc)
        return True

    boundary, non_manifold = int((per_edge == 1).sum()), int((per_edge > 2).sum())
    return {
        "vertices": int(num_vertices),
        "faces": int(faces.shape[0]),
        "edges": int(edges.shape[0]),
        "boundary_edges": boundary,
        "non_manifold_edges": non_manifold,
        "unreferenced_vertices": int((~referenced).sum()),
        "components": int(np.unique(labels[referenced]).size),
        "consistently_oriented": bool((per_directed == 1).all()),
        "closed": boundary == 0 and non_manifold == 0,
        "euler_characteristic": int(referenced.sum()) - int(edges.shape[0]) + int(faces.shape[0]),
        "bbox_min": low.tolist(),
        "bbox_max": high.tolist(),
        "bbox_size": (high - low).tolist(),
        "mean_edge_length": float(lengths.mean()),
        "min_edge_length": float(lengths.min()),
        "valid_float64": check(torch.float64),
        "valid_float32": check(torch.float32),
    }
