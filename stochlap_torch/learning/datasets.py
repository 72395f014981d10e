"""Feature datasets: :class:`MeshFeatureDataset`, meshes from a folder or a list of files
with their :func:`~stochlap_torch.features.multiscale_features` computed once, kept in the
feature files of ``stochlap features`` (:mod:`.feature_files`)."""

from __future__ import annotations

import logging
import os
import warnings
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import Dataset

from .._common.errors import CacheError, FileFormatError, ParameterError
from ..features import channel_names, feature_params
from ..mesh.validation import SUPPORTED_DTYPES
from . import feature_files as files
from .batching import MeshSample
from .cache import CacheWarning, warn_unwritable
from .feature_files import MESH_SUFFIXES
from .targets import TargetSource, check_target_source, check_vertex_target, read_target

logger = logging.getLogger(__name__)
#: Why a feature file is recomputed without a warning: none yet, or the mesh or code changed.
_EXPECTED = (files.ABSENT, files.OTHER_SOURCE, files.OTHER_NUMERICS)


def find_mesh_files(source: str | os.PathLike | Iterable[str | os.PathLike]) -> list[Path]:
    """Mesh files of a folder (sorted, by :data:`MESH_SUFFIXES`) or of an explicit list.

    Raises:
        FileNotFoundError: a listed file or the folder does not exist.
        ValueError: no mesh files found.
    """
    if isinstance(source, (str, os.PathLike)):
        folder = Path(source)
        if not folder.is_dir():
            raise FileNotFoundError(f"no such folder: {folder}")
        paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    else:
        paths = [Path(p) for p in source]
        missing = [str(p) for p in paths if not p.is_file()]
        if missing:
            raise FileNotFoundError(f"no such mesh files: {missing}")
    if not paths:
        raise ParameterError(f"no mesh files ({', '.join(MESH_SUFFIXES)}) in {source}")
    return paths


def _progress(items: Sequence, description: str, enabled: bool) -> Iterator:
    """Iterate with a tqdm bar if tqdm is installed, else with one log line per item."""
    try:
        from tqdm.auto import tqdm
    except ImportError:
        tqdm = None
    if tqdm is not None:
        yield from tqdm(items, desc=description, disable=not enabled)
        return
    for position, item in enumerate(items, start=1):
        if enabled:
            logger.info("%s: %d/%d", description, position, len(items))
        yield item


def _feature_folder(folder: str | os.PathLike, paths: Sequence[Path]) -> Path:
    """``folder`` created, once no two of ``paths`` share a stem (their feature file)."""
    stems: dict[str, Path] = {}
    for path in paths:
        other = stems.setdefault(path.stem, path)
        if other != path:
            raise ParameterError(
                f"{other} and {path} would share the feature file {path.stem}.npz in "
                f"cache_dir={folder}; rename one, or give them different cache folders"
            )
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CacheError(f"cache folder {folder} cannot be created: {error}") from error
    return folder


def _warn(message: str) -> None:
    warnings.warn(message, CacheWarning, stacklevel=5)


def _check_dtype(dtype) -> torch.dtype:
    """``dtype`` if it is float32 or float64, else :class:`ParameterError` (strings are
    refused as in :func:`~stochlap_torch.load_mesh`)."""
    if isinstance(dtype, torch.dtype) and dtype in SUPPORTED_DTYPES:
        return dtype
    hint = " (a string: pass the torch.dtype itself)" if isinstance(dtype, str) else ""
    raise ParameterError(f"dtype must be torch.float32 or torch.float64, got {dtype!r}{hint}")


class MeshFeatureDataset(Dataset):
    """Meshes with their multiscale features, computed once at construction.

    Args:
        source: a folder (every file with a suffix of :data:`MESH_SUFFIXES`, sorted by name)
            or a sequence of mesh files.
        variant: ``"robust"`` (default) or ``"paper"``, with its ``options``, as for
            :func:`~stochlap_torch.features.multiscale_features`; checked at construction.
        options: that variant's options.
        cache_dir: optional folder of feature files, the format of ``stochlap features``
            (:func:`~stochlap_torch.load_features`): mesh file ``<stem>.<suffix>`` has
            ``cache_dir/<stem>.npz``. A file of the same settings (``dtype`` float64 and
            ``merge_seams`` included) and of the same mesh bytes is read without parsing the
            mesh, so ``stochlap features DIR -o OUT`` then ``MeshFeatureDataset(DIR,
            cache_dir=OUT)`` computes nothing; any other file is recomputed and replaced (with a
            :class:`~stochlap_torch.learning.CacheWarning` when it is damaged or holds other
            settings: give each setting its own folder).
        merge_seams: passed to :func:`~stochlap_torch.load_mesh`.
        dtype: ``torch.float32`` or ``torch.float64``, the dtype of the returned vertices,
            features and floating-point targets (features are computed in float64).
        in_memory: keep meshes and features in memory (default); with ``False`` each item is
            re-read from its feature file (``cache_dir`` is then required).
        progress: show a progress bar (tqdm if installed, else log lines).
        targets: optional per-mesh targets (a class label, or a tensor of one shape for every
            mesh), as a ``TargetSource``: a callable ``path -> target``, a mapping from a
            file's path or name (``"cow.obj"``) to its target, or a sequence with one target
            per file in ``paths`` order.
        vertex_targets: optional per-vertex targets ``(V,)`` or ``(V, ...)`` (e.g.
            segmentation labels, read from a sidecar file by a callable), from the same kinds
            of source; rows follow the vertices of the loaded mesh (after ``merge_seams``).
            With ``in_memory=False`` a callable is called for each item (picklable for
            worker processes under ``spawn``).

    Items are :class:`MeshSample` (``target`` / ``vertex_target`` ``None`` when not given);
    integer and boolean targets keep their dtype. Vertices no face uses get placeholder rows,
    not features of the surface (their ``referenced`` is ``False`` in the feature files). Use
    ``collate_fn=collate_meshes`` in a ``DataLoader``; the batch's ``unbatch`` splits a
    per-vertex output back per mesh.

    Raises:
        ParameterError: a bad parameter or dtype, a target source of the wrong kind or length
            (before any mesh is read), two mesh files of one stem with a ``cache_dir``; a
            missing, non-array or wrongly shaped target, or targets of different shapes or
            dtypes across files (naming the files).
        CacheError: ``cache_dir`` cannot be created.
    """

    def __init__(
        self,
        source: str | os.PathLike | Iterable[str | os.PathLike],
        cache_dir: str | os.PathLike | None = None,
        merge_seams: bool = False,
        dtype: torch.dtype = torch.float32,
        in_memory: bool = True,
        progress: bool = True,
        targets: TargetSource | None = None,
        vertex_targets: TargetSource | None = None,
        variant: str | None = None,
        **options,
    ):
        self.dtype = _check_dtype(dtype)
        if not in_memory and cache_dir is None:
            raise ParameterError("in_memory=False needs a cache_dir to read the features from")
        self.paths = find_mesh_files(source)
        self.params = feature_params(variant, **options)
        self._target_source = check_target_source("targets", targets, len(self.paths))
        self._vertex_target_source = check_target_source(
            "vertex_targets", vertex_targets, len(self.paths)
        )
        self.merge_seams = merge_seams
        self.in_memory = in_memory
        self._record = files.settings_record(self.params, "float64", merge_seams)
        self.cache_dir = None if cache_dir is None else _feature_folder(cache_dir, self.paths)
        # Shape and dtype of the first file's targets, which every other file must share.
        self._layouts: dict[str, tuple[tuple[int, ...], torch.dtype, Path]] = {}
        self._items: list[MeshSample] = []
        for position in _progress(range(len(self.paths)), "multiscale features", progress):
            item = self._load(position)
            if in_memory:
                self._items.append(item)

    def _load(self, position: int) -> MeshSample:
        path = self.paths[position]
        arrays = self._arrays(path)
        vertices = torch.from_numpy(arrays["vertices"])
        target = vertex_target = None
        if self._target_source is not None:
            target = read_target("targets", self._target_source, path, position, self.dtype)
            self._check_layout("targets", target, path)
        if self._vertex_target_source is not None:
            vertex_target = read_target(
                "vertex_targets", self._vertex_target_source, path, position, self.dtype
            )
            check_vertex_target(vertex_target, path, vertices.shape[0], self.merge_seams)
            self._check_layout("vertex_targets", vertex_target, path)
        return MeshSample(
            vertices.to(self.dtype),
            torch.from_numpy(arrays["faces"]),
            torch.from_numpy(arrays["features"]).to(self.dtype),
            str(path),
            position,
            target,
            vertex_target,
        )

    def _arrays(self, path: Path) -> dict[str, np.ndarray]:
        """The feature file's arrays of mesh file ``path``: read from ``cache_dir`` when done
        there, else computed (and written there)."""
        if self.cache_dir is None:
            return files.compute_arrays(path, self.params, self._record)
        stored = self.cache_dir / f"{path.stem}.npz"
        data = path.read_bytes()  # read once: hashed, and parsed on a miss
        digest = files.source_digest(data)
        status = files.feature_file_status(stored, self._record, digest)
        if status.done:
            try:
                return files.read_arrays(stored)
            except (FileFormatError, OSError) as error:
                _warn(f"{error}; recomputing")
        elif status.reason not in _EXPECTED:
            _warn(f"feature file {stored} {status.reason}; recomputing and replacing it")
        arrays = files.compute_arrays(path, self.params, self._record, data)
        try:
            files.write_feature_file(stored, arrays, self._record, digest)
        except OSError as error:  # a folder or FIFO in its place, a full or read-only disk
            warn_unwritable(self.cache_dir, CacheError(f"feature file {stored}: {error}"))
        return arrays

    def _check_layout(self, name: str, target: torch.Tensor, path: Path):
        """Record the first file's target layout (the shape after the vertex dimension for
        ``vertex_targets``); refuse another file's that differs."""
        per_vertex = name == "vertex_targets"
        shape, dtype = tuple(target.shape[1:] if per_vertex else target.shape), target.dtype
        first = self._layouts.setdefault(name, (shape, dtype, path))
        if first[:2] != (shape, dtype):
            what = "shape after the vertex dimension" if per_vertex else "shape"
            raise ParameterError(
                f"{name} of every file must share a {what} and dtype to be batched: {path} has "
                f"{shape} {dtype}, {first[2]} has {first[0]} {first[1]}"
            )

    def channel_names(self) -> list[str]:
        """Names of the ``C`` feature channels."""
        return channel_names(self.params)

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> MeshSample:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} meshes")
        index = index % len(self)
        return self._items[index] if self.in_memory else self._load(index)
