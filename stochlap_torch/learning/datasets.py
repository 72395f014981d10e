"""Feature datasets: :class:`MeshFeatureDataset`, meshes from a folder or a list of files
with their :func:`~stochlap_torch.features.multiscale_features` computed once."""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import torch
from torch.utils.data import Dataset

from .._common.errors import ParameterError
from ..features import channel_names, feature_params, multiscale_features
from ..mesh import load_mesh
from ..mesh.validation import SUPPORTED_DTYPES
from .batching import MeshSample
from .cache import MeshCache, cached_features
from .targets import TargetSource, check_target_source, check_vertex_target, read_target

logger = logging.getLogger(__name__)

#: File suffixes :func:`find_mesh_files` picks up in a folder.
MESH_SUFFIXES = (".obj", ".off", ".ply", ".stl", ".glb", ".gltf")


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
        cache_dir: optional folder of the on-disk cache (:class:`MeshCache`).
        merge_seams: passed to :func:`~stochlap_torch.load_mesh`.
        dtype: ``torch.float32`` or ``torch.float64``, the dtype of the returned vertices,
            features and floating-point targets (features are computed in float64).
        in_memory: keep meshes and features in memory (default); with ``False`` each item is
            re-read from its file and from the cache (``cache_dir`` is then required).
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
    integer and boolean targets keep their dtype. Use ``collate_fn=collate_meshes`` in a
    ``DataLoader``; the batch's ``unbatch`` splits a per-vertex output back per mesh.

    Raises:
        ParameterError: a bad parameter or dtype, a target source of the wrong kind or length
            (before any mesh is read); a missing, non-array or wrongly shaped target, or
            targets of different shapes or dtypes across files (naming the files).
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
        self.cache = None if cache_dir is None else MeshCache(cache_dir)
        # Shape and dtype of the first file's targets, which every other file must share.
        self._layouts: dict[str, tuple[tuple[int, ...], torch.dtype, Path]] = {}
        self._items: list[MeshSample] = []
        for position in _progress(range(len(self.paths)), "multiscale features", progress):
            item = self._load(position)
            if in_memory:
                self._items.append(item)

    def _load(self, position: int) -> MeshSample:
        path = self.paths[position]
        mesh = load_mesh(path, merge_seams=self.merge_seams)
        target = vertex_target = None
        if self._target_source is not None:
            target = read_target("targets", self._target_source, path, position, self.dtype)
            self._check_layout("targets", target, path)
        if self._vertex_target_source is not None:
            vertex_target = read_target(
                "vertex_targets", self._vertex_target_source, path, position, self.dtype
            )
            check_vertex_target(vertex_target, path, mesh.num_vertices, self.merge_seams)
            self._check_layout("vertex_targets", vertex_target, path)
        if self.cache is not None:
            features = cached_features(mesh.vertices, mesh.faces, self.cache, params=self.params)
        else:
            with torch.no_grad():
                features = multiscale_features(mesh.vertices, mesh.faces, params=self.params)
        return MeshSample(
            mesh.vertices.to(self.dtype),
            mesh.faces,
            features.to(self.dtype),
            str(path),
            position,
            target,
            vertex_target,
        )

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
