"""Reading and writing mesh files. :func:`load_mesh` keeps every vertex of the file in file
order, so that per-vertex outputs line up with it: OBJ is parsed here (trimesh splits its
vertices at texture seams and drops unreferenced ones), other formats go through trimesh with
processing switched off.
"""

from __future__ import annotations

import logging
import math
import os
import re
import tarfile
import zipfile
from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from .._common.checks import format_bytes
from .._common.errors import FileFormatError, MeshError, ParameterError
from .._common.files import atomic_write
from .._common.tensors import to_numpy
from .container import Mesh
from .geometry import is_soup
from .validation import SUPPORTED_DTYPES, as_mesh_tensors, validate_mesh

if TYPE_CHECKING:
    import trimesh

__all__ = [
    "bundled_mesh_path",
    "from_trimesh",
    "load_mesh",
    "merge_duplicate_vertices",
    "save_ply",
    "to_trimesh",
]

logger = logging.getLogger(__name__)

#: Archives (zip, tar) that unpack to more bytes than this are refused.
MAX_ARCHIVE_BYTES = 1 << 30
#: Environment variable that overrides :data:`MAX_ARCHIVE_BYTES`.
ARCHIVE_ENV = "STOCHLAP_MAX_ARCHIVE_BYTES"
#: Larger OBJ face indices cannot index any mesh this library can hold (and overflow int64).
_INDEX_LIMIT = 2**62


def bundled_mesh_path(name: str = "spot") -> Path:
    """Path of a mesh shipped with the package (``"spot"``: Keenan Crane's cow, public domain)."""
    path = resources.files("stochlap_torch.mesh") / "assets" / f"{name}.obj"
    if not path.is_file():
        raise FileNotFoundError(f"no bundled mesh named {name!r}")
    return Path(str(path))


def load_mesh(
    path: str | Path, merge_seams: bool = False, dtype: torch.dtype = torch.float64
) -> Mesh:
    """Load a triangle mesh file. A soup (as STL stores every triangle) is always merged;
    ``Mesh.file_vertices`` maps its corners to the merged vertices.

    Args:
        path: an OBJ, OFF, PLY, STL, GLB or any other file trimesh reads as triangles (also
            zip or tar archives, up to ``MAX_ARCHIVE_BYTES`` unpacked). Polygons are
            fan-triangulated; a scene of several geometries is concatenated.
        merge_seams: merge vertices at identical positions (duplicated at texture or normal
            seams) in any file, and drop the faces that collapse.
        dtype: ``torch.float32`` or ``torch.float64`` for the vertices (the mesh is checked
            in ``dtype``: one whose edges vanish in float32 is refused).

    Returns:
        A validated :class:`Mesh`: ``(V, 3)`` vertices in ``dtype``, ``(F, 3)`` int64 faces.

    Raises:
        FileNotFoundError: the file does not exist.
        MeshError: the file cannot be read as triangles, or the mesh fails validation; the
            message starts with the file's path.
    """
    path = Path(path)
    if dtype not in SUPPORTED_DTYPES:
        raise ParameterError(f"dtype must be torch.float32 or torch.float64, got {dtype}")
    if not path.is_file():
        raise FileNotFoundError(f"no such mesh file: {path}")
    if path.suffix.lower() == ".obj":
        vertices, faces = read_obj(path)
    else:
        vertices, faces = _read_with_trimesh(path)
    file_vertices = None
    # Bad indices are validate_mesh's to report, below.
    indexed = faces.size > 0 and 0 <= faces.min() and faces.max() < vertices.shape[0]
    if indexed and (merge_seams or is_soup(faces)):
        vertices, faces, inverse = _merge(vertices, faces)
        if vertices.shape[0] < inverse.shape[0]:
            file_vertices = torch.from_numpy(inverse)
    mesh = Mesh(torch.from_numpy(vertices).to(dtype), torch.from_numpy(faces), file_vertices)
    try:
        validate_mesh(mesh.vertices, mesh.faces, check_edge_lengths=False)
    except MeshError as error:
        raise MeshError(f"{path}: {error}") from error
    logger.info("loaded %s: %d vertices, %d faces", path, mesh.num_vertices, mesh.num_faces)
    return mesh


def merge_duplicate_vertices(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Merge the ``(V, 3)`` float ``vertices`` at identical positions; drop the ``(F, 3)`` int
    ``faces`` that then repeat a vertex.

    Returns:
        ``(V', 3)`` vertices, first occurrences kept in their original order, and ``(F', 3)``
        faces re-indexed into them.
    """
    return _merge(vertices, faces)[:2]


def _merge(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`merge_duplicate_vertices`, and ``(V,)`` int64 the merged vertex of every input
    vertex. Equal positions only: copies of a corner are written from the same number, while a
    tolerance would join distinct vertices of a finely detailed mesh."""
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first)  # unique rows ranked by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    new_faces = rank[inverse][faces]
    keep = (new_faces != np.roll(new_faces, -1, axis=1)).all(axis=1)
    return vertices[first[order]], np.ascontiguousarray(new_faces[keep]), rank[inverse]


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The ``v`` and ``f`` records of an OBJ file: ``(V, 3)`` float64 vertices (a fourth
    coordinate, the weight, is ignored) and ``(F, 3)`` int64 faces, polygons fan-triangulated
    (indices not checked against ``V``).

    Raises:
        MeshError: a record that cannot be read (naming the file and the line), or no faces.
    """
    regular = _read_regular_obj(path.read_bytes())
    return regular if regular is not None else _read_obj_lines(path)


_V_RECORDS = re.compile(rb"^[ \t]*v(?=[ \t\r\n]|$)([^\n]*)", re.MULTILINE)
_F_RECORDS = re.compile(rb"^[ \t]*f(?=[ \t\r\n]|$)([^\n]*)", re.MULTILINE)
_AFTER_SLASH = re.compile(rb"/[^ \t\r\n]*")


def _read_regular_obj(data: bytes) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`read_obj` of the usual file, parsed by numpy's C reader in bulk (a Python loop per
    line is 3x slower than trimesh): every ``v`` record with the same number (3 or more) of
    fields, every ``f`` record with the same number (3 or more) of positive indices. ``None``
    for any other file, which :func:`_read_obj_lines` reads or names the line it cannot read."""
    vertex_records, face_records = _V_RECORDS.findall(data), _F_RECORDS.findall(data)
    if not vertex_records or not face_records:
        return None
    faces_text = _AFTER_SLASH.sub(b"", b"\n".join(face_records))
    try:  # a ragged record or a token that is no number is a ValueError: the line reader's job
        vertices = _table(b"\n".join(vertex_records), np.float64)
        polygons = _table(faces_text, np.int64)
    except (ValueError, OverflowError):
        return None
    if (len(vertices), len(polygons)) != (len(vertex_records), len(face_records)):
        return None  # numpy skips a blank record ("v" alone), which would shift the indices
    if vertices.shape[1] < 3 or polygons.shape[1] < 3:
        return None
    if not ((polygons > 0) & (polygons < _INDEX_LIMIT)).all():
        return None
    polygons -= 1
    fans = [polygons[:, [0, i, i + 1]] for i in range(1, polygons.shape[1] - 1)]
    faces = np.ascontiguousarray(np.stack(fans, axis=1).reshape(-1, 3))
    return np.ascontiguousarray(vertices[:, :3]), faces


def _table(text: bytes, dtype) -> np.ndarray:
    """``(rows, columns)`` of whitespace-separated numbers, one row per line (all alike)."""
    import io

    return np.loadtxt(io.BytesIO(text), dtype=dtype, comments=None, ndmin=2)


def _read_obj_lines(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """:func:`read_obj` line by line, for the files :func:`_read_regular_obj` does not take."""
    vertices: list[list[float]] = []
    triangles: list[tuple[int, int, int]] = []
    with path.open("r", encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            fields = line.split()
            if fields and fields[0] == "v":
                if len(fields) < 4:
                    raise MeshError(f"{path}:{number}: a vertex needs three coordinates")
                try:
                    vertices.append([float(x) for x in fields[1:4]])
                except ValueError:
                    raise MeshError(
                        f"{path}:{number}: vertex coordinates are not numbers: "
                        f"{' '.join(fields[1:4])!r}"
                    ) from None
            elif fields and fields[0] == "f":
                polygon = _polygon(fields, len(vertices), path, number)
                triangles.extend(
                    (polygon[0], polygon[i], polygon[i + 1]) for i in range(1, len(polygon) - 1)
                )
    if not triangles:
        raise MeshError(f"{path}: no faces found (an OBJ mesh needs 'f' records)")
    return (
        np.asarray(vertices, dtype=np.float64).reshape(-1, 3),
        np.asarray(triangles, dtype=np.int64).reshape(-1, 3),
    )


def _polygon(fields: list[str], num_vertices: int, path: Path, number: int) -> list[int]:
    """0-based vertex indices of an ``f`` record (``v``, ``v/vt``, ``v//vn``, ``v/vt/vn``;
    OBJ counts from 1, and negative indices count back from the latest vertex)."""
    polygon = []
    for token in fields[1:]:
        try:
            index = int(token.split("/", 1)[0])
        except ValueError:
            raise MeshError(f"{path}:{number}: face vertex {token!r} is not an index") from None
        if index == 0 or abs(index) >= _INDEX_LIMIT:
            raise MeshError(f"{path}:{number}: face vertex index {index} is out of range")
        polygon.append(index - 1 if index > 0 else num_vertices + index)
    if len(polygon) < 3:
        raise MeshError(f"{path}:{number}: a face needs at least 3 vertices")
    return polygon


def _read_with_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Load any trimesh-readable file without merging, reordering or dropping vertices."""
    import trimesh

    _check_archive(path)
    try:
        loaded = trimesh.load(path, process=False, maintain_order=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"{path}: could not be read as a mesh: {exc}") from exc
    geometries = list(loaded.geometry.values()) if isinstance(loaded, trimesh.Scene) else [loaded]
    meshes = [g for g in geometries if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not meshes:
        raise MeshError(f"{path}: no triangles found")
    offsets = np.cumsum([0] + [len(g.vertices) for g in meshes])
    faces = [np.asarray(g.faces, dtype=np.int64) + o for g, o in zip(meshes, offsets, strict=False)]
    vertices = [np.asarray(g.vertices, dtype=np.float64) for g in meshes]
    return np.concatenate(vertices), np.concatenate(faces)


def _check_archive(path: Path) -> None:
    """Refuse (:class:`MeshError`) an unreadable zip or tar archive, or one that unpacks to
    more than :data:`MAX_ARCHIVE_BYTES` or ``$STOCHLAP_MAX_ARCHIVE_BYTES`` (trimesh reads every
    member into memory); :class:`ParameterError` for a bad variable."""
    name, text = path.name.lower(), os.environ.get(ARCHIVE_ENV)
    try:
        limit = MAX_ARCHIVE_BYTES if text is None else float(text)
    except ValueError:
        limit = math.nan
    if not (math.isfinite(limit) and limit >= 1):
        raise ParameterError(f"${ARCHIVE_ENV} must be a positive number of bytes, got {text!r}")
    limit = int(limit)
    try:
        if name.endswith(".zip") and zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as archive:
                unpacked = sum(member.file_size for member in archive.infolist())
        elif ".tar" in name and tarfile.is_tarfile(path):
            with tarfile.open(path) as archive:
                unpacked = sum(member.size for member in archive.getmembers())
        else:
            return
    except (OSError, zipfile.BadZipFile, tarfile.TarError) as exc:
        raise MeshError(f"{path}: could not be read as an archive: {exc}") from exc
    if unpacked > limit:
        raise MeshError(
            f"{path}: the archive unpacks to {format_bytes(unpacked)}, over the limit of "
            f"{format_bytes(limit)} (${ARCHIVE_ENV} raises it)"
        )


def save_ply(
    path: str | Path,
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    colors: np.ndarray | None = None,
    scalars: dict[str, np.ndarray] | None = None,
    comments: Sequence[str] = (),
) -> Path:
    """Write a binary PLY file keeping every vertex in order, atomically (a failed write leaves
    ``path`` as it was).

    Args:
        path: output file.
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices.
        colors: optional ``(V, 3)`` or ``(V, 4)`` uint8 vertex colours (``None``: none).
        scalars: optional per-vertex ``float`` properties (``{"saliency": (V,) array}``;
            ``None``: none).
        comments: lines written as ``comment <line>`` in the header (what wrote the file).

    Raises:
        ParameterError: a comment that spans lines, or a scalar name that is not one PLY word
            or is taken by the positions or colours.
    """
    import trimesh

    scalars = scalars or {}
    for comment in comments:  # what would corrupt the header
        if "\n" in comment or "\r" in comment:
            raise ParameterError(f"a PLY comment must be one line, got {comment!r}")
    for name in scalars:
        if not isinstance(name, str) or not name or name.split() != [name]:
            raise ParameterError(f"a PLY property name must be one word, got {name!r}")
        if name in ("x", "y", "z", "red", "green", "blue", "alpha"):
            raise ParameterError(f"a PLY scalar cannot be named {name!r}: that property is taken")
    vertices = to_numpy(vertices).astype(np.float64)
    check_ply_positions(vertices, path)
    mesh = trimesh.Trimesh(vertices=vertices, faces=to_numpy(faces).astype(np.int64), process=False)
    if colors is not None:
        mesh.visual.vertex_colors = np.asarray(colors, dtype=np.uint8)
    for name, values in scalars.items():
        column = np.asarray(to_numpy(values), dtype=np.float32).reshape(vertices.shape[0])
        mesh.vertex_attributes[name] = column
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", include_attributes=True)
    if comments:  # after the format line
        magic, format_line, rest = data.split(b"\n", 2)
        lines = b"".join(b"comment " + comment.encode("utf-8") + b"\n" for comment in comments)
        data = magic + b"\n" + format_line + b"\n" + lines + rest
    with atomic_write(path, "wb") as handle:
        handle.write(data)
    return Path(path)


def check_ply_positions(vertices: np.ndarray, path) -> None:
    """Refuse positions that float32 (PLY's, in trimesh's exporter) would turn into ``inf``, or
    whose every coordinate it would lose below its normal range."""
    largest = float(np.abs(vertices).max()) if vertices.size else 0.0
    info = np.finfo(np.float32)
    if largest > float(info.max) or 0.0 < largest < float(info.tiny / info.eps):
        raise FileFormatError(
            f"{path}: PLY positions are float32, which cannot hold coordinates of magnitude "
            f"{largest:.3g} (its range is {info.tiny / info.eps:.3g} to {info.max:.3g}); "
            "rescale the mesh before writing it"
        )


def to_trimesh(mesh: Mesh | tuple) -> trimesh.Trimesh:
    """A ``trimesh.Trimesh`` with the same vertices in the same order (``process=False``)."""
    import trimesh

    vertices, faces = (mesh.vertices, mesh.faces) if isinstance(mesh, Mesh) else mesh
    vertices, faces = as_mesh_tensors(vertices, faces)
    return trimesh.Trimesh(
        vertices=vertices.detach().cpu().numpy(), faces=faces.cpu().numpy(), process=False
    )


def from_trimesh(tm, dtype: torch.dtype = torch.float64) -> Mesh:
    """A validated :class:`~stochlap_torch.mesh.Mesh` from a ``trimesh.Trimesh`` (same order).

    Raises:
        MeshError: the trimesh fails :func:`~stochlap_torch.mesh.validate_mesh`.
    """
    vertices = torch.as_tensor(tm.vertices, dtype=dtype).clone()
    faces = torch.as_tensor(tm.faces, dtype=torch.int64).clone()
    return Mesh(*as_mesh_tensors(vertices, faces))
