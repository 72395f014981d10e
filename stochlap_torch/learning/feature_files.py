"""Feature files: one ``.npz`` of per-vertex features per mesh file, written by ``stochlap
features`` and by :class:`~stochlap_torch.learning.MeshFeatureDataset` (``cache_dir=``), read
by both and by :func:`load_features`; ``DIR/a/b.obj`` found in ``DIR`` has ``OUT/a/b.npz``, a
file named on its own ``OUT/<stem>.npz``.

The members (the CLI guide, "Features of a data set", says what each holds): ``features``
``(V, C)``, ``channel_names`` ``(C,)``, ``vertices`` ``(V, 3)``, ``faces`` ``(F, 3)``,
``referenced`` ``(V,)`` bool (rows where it is ``False`` are placeholders), ``file_vertices``
``(N,)`` (merged files only), and the strings ``settings`` (JSON: :func:`settings_record`),
``source_sha256``, ``numerics`` (:func:`numerics_fingerprint`) and ``version``.

A file is *done* for a mesh when its settings, source digest and numerics are those asked and
its arrays have consistent shapes (:func:`feature_file_status`, reading the small members and
the arrays' headers only); anything else is recomputed. Files are written atomically, whole or
absent. This module does not import torch: the command line sorts out what is done first.
"""

from __future__ import annotations

import dataclasses
import functools
import glob
import hashlib
import json
import os
import tempfile
import time
import zipfile
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.lib import format as npy

from .._common.errors import FileFormatError, ParameterError
from .._common.files import atomic_write
from .._common.version import __version__

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["FeatureFile", "load_features"]

#: File suffixes of the meshes a folder holds.
MESH_SUFFIXES = (".obj", ".off", ".ply", ".stl", ".glb", ".gltf")
#: The subpackages and modules whose code determines the numbers of a feature or cache file.
NUMERICS_SOURCES = (
    "_common",
    "_kernels",
    "diffusion",
    "features",
    "mesh",
    "operators",
    "params.py",
    "robust",
    "saliency_maps",
    "sparse",
)
#: A temporary of a file untouched this long is a killed run's, not a live writer's.
STALE_SECONDS = 600.0
#: The arrays whose headers :func:`feature_file_status` checks.
_ARRAYS = ("features", "channel_names", "vertices", "faces", "referenced")
_TEXTS = ("settings", "source_sha256", "numerics", "version")

#: :attr:`FileStatus.reason` of a file that is not there (or is no regular file).
ABSENT = "does not exist"
#: :attr:`FileStatus.reason` of the features of other bytes of the mesh file.
OTHER_SOURCE = "holds the features of another version of the mesh file"
#: :attr:`FileStatus.reason` of features computed by other code (another release).
OTHER_NUMERICS = "was computed by other numerics"


@functools.lru_cache(maxsize=1)
def numerics_fingerprint() -> str:
    """16 hex digits: a hash of the source of every module that computes the numbers
    (:data:`NUMERICS_SOURCES`) and of the installed torch's version (read without importing
    torch)."""
    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256(metadata.version("torch").encode())
    for name in NUMERICS_SOURCES:
        path = root / name
        files = sorted(path.rglob("*.py")) if path.is_dir() else [path]
        for file in files:
            digest.update(str(file.relative_to(root)).encode())
            digest.update(file.read_bytes())
    return digest.hexdigest()[:16]


def settings_record(params, dtype: str, merge_seams: bool) -> dict:
    """The JSON-ready ``settings`` of features of resolved ``params`` (``RobustParams`` or
    ``PaperFeatureParams``) computed in ``dtype`` (``"float32"``, ``"float64"``)."""
    record = {"method": type(params).__name__, **dataclasses.asdict(params), "dtype": dtype}
    record["merge_seams"] = bool(merge_seams)
    # Through JSON once, so that it compares equal to what a file holds (tuples as lists).
    return json.loads(json.dumps(record, sort_keys=True))


def source_digest(data: bytes) -> str:
    """``source_sha256``: the SHA-256 of a mesh file's bytes, in hex."""
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True)
class FileStatus:
    """What :func:`feature_file_status` found: a done file's vertex count, else ``None`` and
    why (a phrase after the file's name: :data:`ABSENT`, :data:`OTHER_SOURCE`, ...)."""

    num_vertices: int | None
    reason: str = ""

    @property
    def done(self) -> bool:
        return self.num_vertices is not None


def feature_file_status(path: str | os.PathLike, record: dict, digest: str) -> FileStatus:
    """Whether ``path`` holds the features of the mesh whose bytes hash to ``digest`` with
    ``settings`` ``record`` (:func:`settings_record`) and these numerics, with arrays of
    consistent shapes. Reads the small members and the arrays' headers only, so that checking
    a finished data set does not read its features."""
    if not Path(path).is_file():
        return FileStatus(None, ABSENT)  # nothing, or a node the write refuses
    try:
        with zipfile.ZipFile(path) as archive:
            members = set(archive.namelist())
            settings = json.loads(_read_text(archive, "settings"))
            if settings != record:
                return FileStatus(None, "holds other settings")
            if _read_text(archive, "source_sha256") != digest:
                return FileStatus(None, OTHER_SOURCE)
            if "numerics.npy" not in members or (
                _read_text(archive, "numerics") != numerics_fingerprint()
            ):
                return FileStatus(None, OTHER_NUMERICS)
            headers = {name: _read_header(archive, name) for name in _ARRAYS}
    except Exception:  # damaged in any of many ways (zip, header, JSON, a member)
        return FileStatus(None, "is unreadable or incomplete")
    (features, dtype), (names, _), (vertices, _), (faces, _), (referenced, mask) = (
        headers[name] for name in _ARRAYS
    )
    consistent = (
        len(names) == len(referenced) == 1
        and len(vertices) == len(faces) == 2
        and (vertices[1], faces[1]) == (3, 3)
        and features == (vertices[0], names[0])
        and referenced == (vertices[0],)
        and dtype == np.dtype(record["dtype"])
        and mask == np.dtype(bool)
    )
    if not consistent:
        return FileStatus(None, "holds arrays of inconsistent shapes or dtypes")
    return FileStatus(int(vertices[0]))


def _read_header(archive: zipfile.ZipFile, name: str) -> tuple[tuple[int, ...], np.dtype]:
    with archive.open(f"{name}.npy") as member:
        version = npy.read_magic(member)
        read = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
        shape, _, dtype = read(member)
    return shape, dtype


def _read_text(archive: zipfile.ZipFile, name: str) -> str:
    with archive.open(f"{name}.npy") as member:
        return str(npy.read_array(member, allow_pickle=False))


def compute_arrays(source: Path, params, record: dict, data: bytes | None = None) -> dict:
    """The arrays of the feature file of mesh file ``source`` (NumPy; all but the texts), with
    resolved ``params`` and the ``dtype`` and ``merge_seams`` of ``record``. With ``data``
    (the file's bytes, hashed by the caller) the mesh is parsed from a private copy of them,
    so that a file rewritten meanwhile cannot leave other bytes' features under their digest
    (a ``.gltf`` in place: its buffers lie beside it)."""
    import torch

    from ..features import channel_names, multiscale_features
    from ..mesh import load_mesh

    options = {"merge_seams": record["merge_seams"], "dtype": getattr(torch, record["dtype"])}
    if data is None or source.suffix.lower() == ".gltf":
        mesh = load_mesh(source, **options)
    else:
        with tempfile.TemporaryDirectory(prefix="stochlap-") as folder:
            copy = Path(folder, source.name)
            copy.write_bytes(data)
            try:
                mesh = load_mesh(copy, **options)
            except Exception as error:  # named by the user's file, not the copy
                error.args = tuple(
                    arg.replace(str(copy), str(source)) if isinstance(arg, str) else arg
                    for arg in error.args
                )
                if isinstance(error, OSError) and error.filename == str(copy):
                    error.filename = str(source)
                raise
    with torch.no_grad():
        features = multiscale_features(mesh.vertices, mesh.faces, params=params)
    faces = mesh.faces.detach().cpu().numpy()
    arrays = {
        "features": features.detach().cpu().numpy(),
        "channel_names": np.array(channel_names(params), dtype=str),
        "vertices": mesh.vertices.detach().cpu().numpy(),
        "faces": faces,
        "referenced": referenced_vertices(mesh.num_vertices, faces),
    }
    if mesh.file_vertices is not None:
        arrays["file_vertices"] = mesh.file_vertices.cpu().numpy()
    return arrays


def referenced_vertices(num_vertices: int, faces: np.ndarray) -> np.ndarray:
    """``(V,)`` bool: whether some of the ``(F, 3)`` ``faces`` uses each vertex."""
    return np.bincount(faces.reshape(-1), minlength=num_vertices) > 0


def write_feature_file(path: str | os.PathLike, arrays: dict, record: dict, digest: str) -> None:
    """Write ``arrays`` (:func:`compute_arrays`) with their texts to ``path``, atomically,
    after removing the stale temporaries a killed run left there.

    Raises:
        NotARegularFileError: ``path`` is a folder, a FIFO, a device (nothing written).
        OSError: it cannot be written.
    """
    remove_stale_temporaries(path)
    texts = {
        "settings": json.dumps(record, sort_keys=True),
        "source_sha256": digest,
        "numerics": numerics_fingerprint(),
        "version": __version__,
    }
    with atomic_write(path, "wb") as handle:
        np.savez(handle, **arrays, **{name: np.array(text) for name, text in texts.items()})


def remove_stale_temporaries(path: str | os.PathLike) -> None:
    """Remove the temporaries (``.<name>.*.tmp``) of ``path`` that a killed run left, only
    :data:`STALE_SECONDS` old ones (another run may be writing it right now)."""
    target = Path(os.path.realpath(path))
    if target.parent.is_dir():
        now = time.time()
        for leftover in target.parent.glob(f".{glob.escape(target.name)}.*.tmp"):
            try:
                if now - leftover.stat().st_mtime > STALE_SECONDS:
                    leftover.unlink(missing_ok=True)
            except OSError:  # gone meanwhile: its writer finished or cleaned up
                pass


def read_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every member of the feature file ``path``, checked (nothing loaded is trusted).

    Raises:
        FileFormatError: not a feature file, or one whose members disagree (named).
        OSError: it cannot be opened.
    """
    with open(path, "rb") as handle:  # np.load leaves a file it opened open when damaged
        try:
            with np.load(handle, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except Exception as error:
            raise FileFormatError(f"{path}: not a readable .npz ({error})") from error
    problem = _problem(arrays)
    if problem:
        raise FileFormatError(f"{path}: not a stochlap_torch feature file: {problem}")
    return arrays


def _problem(arrays: dict[str, np.ndarray]) -> str | None:
    """What is wrong with the members of a feature file, or ``None``."""
    missing = [name for name in (*_ARRAYS, *_TEXTS) if name not in arrays]
    if missing:
        return f"no {', '.join(missing)} (rerun stochlap features on it)"
    features, names, vertices, faces, referenced = (arrays[name] for name in _ARRAYS)
    if any(arrays[name].shape != () or arrays[name].dtype.kind != "U" for name in _TEXTS):
        return f"{', '.join(_TEXTS)} must be strings"
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.dtype.kind != "f":
        return f"vertices of shape {vertices.shape} and dtype {vertices.dtype}, not (V, 3) float"
    count = len(vertices)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype != np.int64:
        return f"faces of shape {faces.shape} and dtype {faces.dtype}, not (F, 3) int64"
    if faces.size and (faces.min() < 0 or faces.max() >= count):
        return f"face indices outside [0, {count})"
    if names.ndim != 1 or names.dtype.kind != "U":
        return "channel_names are not a list of strings"
    if features.shape != (count, len(names)) or features.dtype.kind != "f":
        return f"features of shape {features.shape}, not ({count}, {len(names)}) float"
    if not np.isfinite(features).all() or not np.isfinite(vertices).all():
        return "features or vertices hold NaN or Inf"
    if referenced.dtype != bool or not np.array_equal(
        referenced, referenced_vertices(count, faces)
    ):
        return "referenced is not the (V,) mask of the vertices the faces use"
    file_vertices = arrays.get("file_vertices")
    if file_vertices is not None and (
        file_vertices.ndim != 1
        or file_vertices.dtype != np.int64
        or (file_vertices.size and (file_vertices.min() < 0 or file_vertices.max() >= count))
    ):
        return f"file_vertices are not (N,) int64 indices in [0, {count})"
    try:
        if not isinstance(json.loads(str(arrays["settings"])), dict):
            return "settings are not a JSON object"
    except ValueError:
        return "settings are not JSON"
    return None


@dataclass(frozen=True)
class FeatureFile:
    """One mesh's feature file, as :func:`load_features` reads it (tensors on the CPU, sharing
    memory with the arrays read).

    Attributes:
        path: the ``.npz`` file.
        features: ``(V, C)`` float features (the ``dtype`` of ``settings``); row ``i`` is
            vertex ``i`` of ``vertices``.
        channel_names: the ``C`` names of the columns of ``features``.
        vertices: ``(V, 3)`` float, the mesh as loaded (after ``merge_seams``).
        faces: ``(F, 3)`` int64.
        referenced: ``(V,)`` bool, whether some face uses the vertex; ``features`` rows of the
            others are placeholders, not features of the surface.
        file_vertices: ``(N,)`` int64, the row of each of the mesh file's vertices when its
            corners were merged (a triangle soup, or ``merge_seams``), else ``None``.
        settings: ``method`` (the parameters class), its fields, ``dtype``, ``merge_seams``.
        source_sha256: the SHA-256 of the mesh file the features were computed from.
        version: the version of the library that wrote the file.
    """

    path: Path
    features: Tensor
    channel_names: tuple[str, ...]
    vertices: Tensor
    faces: Tensor
    referenced: Tensor
    file_vertices: Tensor | None
    settings: dict
    source_sha256: str
    version: str


def load_features(path: str | os.PathLike) -> FeatureFile | dict[str, FeatureFile]:
    """The feature file ``path`` (``stochlap features`` or ``MeshFeatureDataset(...,
    cache_dir=...)`` wrote it) as a :class:`FeatureFile`; for a folder, every ``.npz`` under
    it (searched recursively) as ``{name: FeatureFile}``, ``name`` the file's path in the
    folder without its suffix (``"a/b"`` for ``a/b.npz``), sorted by name.

    Raises:
        FileFormatError: a file that is not a feature file, or one whose members disagree
            (the message names it).
        ParameterError: a folder without ``.npz`` files.
        FileNotFoundError: nothing at ``path``.
    """
    path = Path(path)
    if not path.is_dir():
        return _feature_file(path)
    files = {p.relative_to(path).with_suffix("").as_posix(): p for p in path.rglob("*.npz")}
    if not files:
        raise ParameterError(f"no feature files (.npz) under {path}")
    return {name: _feature_file(files[name]) for name in sorted(files)}


def _feature_file(path: Path) -> FeatureFile:
    import torch

    arrays = read_arrays(path)
    tensors = {name: torch.from_numpy(arrays[name]) for name in ("features", "vertices", "faces")}
    file_vertices = arrays.get("file_vertices")
    return FeatureFile(
        path=path,
        channel_names=tuple(arrays["channel_names"].tolist()),
        referenced=torch.from_numpy(arrays["referenced"]),
        file_vertices=None if file_vertices is None else torch.from_numpy(file_vertices),
        settings=json.loads(str(arrays["settings"])),
        source_sha256=str(arrays["source_sha256"]),
        version=str(arrays["version"]),
        **tensors,
    )
