"""Datasets and interop: precomputed feature datasets, a PyG transform, trimesh conversion.

* :class:`MeshFeatureDataset`: meshes from a folder or a list of files, with their
  :func:`~stochlap_torch.features.multiscale_features` precomputed once (with a progress bar,
  through the on-disk :mod:`~stochlap_torch.cache` when a ``cache_dir`` is given). Works with
  ``torch.utils.data.DataLoader`` and worker processes; :func:`collate_meshes` packs samples
  into one batch.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import torch
from torch import Tensor
from torch.utils.data import Dataset

from .._common.errors import ParameterError
from ..diffusion import PaperParams, RobustParams
from ..features import DEFAULT_FEATURE_VARIANT, feature_settings, features_with_settings
from ..mesh import MeshBatch, load_mesh
from .cache import MeshCache, cached_features_with_settings

__all__ = [
    "MESH_SUFFIXES",
    "MeshFeatureBatch",
    "MeshFeatureDataset",
    "MeshSample",
    "collate_meshes",
    "find_mesh_files",
]

logger = logging.getLogger(__name__)

#: File suffixes :func:`find_mesh_files` picks up in a folder.
MESH_SUFFIXES = (".obj", ".off", ".ply", ".stl", ".glb", ".gltf")


class MeshSample(NamedTuple):
    """One mesh of a :class:`MeshFeatureDataset`.

    Attributes:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` int64.
        features: ``(V, C)`` float, channels named by ``dataset.channel_names()``.
        path: the file it came from.
        index: its position in the dataset.
    """

    vertices: Tensor
    faces: Tensor
    features: Tensor
    path: str
    index: int


class MeshFeatureBatch(NamedTuple):
    """Several samples packed (see :class:`~stochlap_torch.batch.MeshBatch`).

    Attributes:
        vertices: ``(N, 3)``; faces: ``(M, 3)`` offset into them; features: ``(N, C)``;
        batch: ``(N,)`` int64 mesh index; ptr: ``(B + 1,)`` vertex offsets; paths: ``B`` files;
        indices: ``(B,)`` int64 dataset positions.
    """

    vertices: Tensor
    faces: Tensor
    features: Tensor
    batch: Tensor
    ptr: Tensor
    paths: list[str]
    indices: Tensor


def collate_meshes(samples: Sequence[MeshSample]) -> MeshFeatureBatch:
    """Pack samples of different sizes into one :class:`MeshFeatureBatch` (``collate_fn``)."""
    packed = MeshBatch.from_meshes([(s.vertices, s.faces) for s in samples])
    return MeshFeatureBatch(
        vertices=packed.vertices,
        faces=packed.faces,
        features=torch.cat([s.features for s in samples]),
        batch=packed.batch,
        ptr=packed.ptr,
        paths=[s.path for s in samples],
        indices=torch.tensor([s.index for s in samples], dtype=torch.int64),
    )


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


class MeshFeatureDataset(Dataset):
    """Meshes with their multiscale features, computed once at construction.

    Args:
        source: a folder (every file with a suffix of :data:`MESH_SUFFIXES`, sorted by name)
            or a sequence of mesh files.
        num_scales, threshold, include, rotation_invariant, normalisation, variant, robust,
            paper: the options of :func:`~stochlap_torch.features.multiscale_features` (the
            same defaults: the robust channels), resolved and checked at construction.
        cache_dir: optional folder of the on-disk cache; features found there (same mesh
            bytes, parameters and library version) are not recomputed.
        merge_seams: passed to :func:`~stochlap_torch.io.load_mesh`.
        dtype: dtype of the returned vertices and features (computed in float64).
        in_memory: keep meshes and features in memory (default). With ``False`` only the paths
            are kept and each item is re-read from its file and from the cache (``cache_dir``
            is then required); useful for datasets larger than memory.
        progress: show a progress bar (tqdm if installed, else log lines).

    Items are :class:`MeshSample`; use ``collate_fn=collate_meshes`` in a ``DataLoader``.
    """

    def __init__(
        self,
        source: str | os.PathLike | Iterable[str | os.PathLike],
        num_scales: int | None = None,
        threshold: float | None = None,
        include: tuple[str, ...] | None = None,
        rotation_invariant: bool | None = None,
        normalisation: str | None = None,
        cache_dir: str | os.PathLike | None = None,
        merge_seams: bool = False,
        dtype: torch.dtype = torch.float32,
        in_memory: bool = True,
        progress: bool = True,
        variant: str = DEFAULT_FEATURE_VARIANT,
        robust: RobustParams | None = None,
        paper: PaperParams | None = None,
    ):
        if not in_memory and cache_dir is None:
            raise ParameterError("in_memory=False needs a cache_dir to read the features from")
        self.paths = find_mesh_files(source)
        # Validated before any I/O.
        self.settings = feature_settings(
            variant,
            num_scales,
            threshold,
            include,
            rotation_invariant,
            normalisation,
            robust=robust,
            paper=paper,
        )
        self.merge_seams = merge_seams
        self.dtype = dtype
        self.in_memory = in_memory
        self.cache = None if cache_dir is None else MeshCache(cache_dir)
        self._items: list[tuple[Tensor, Tensor, Tensor]] = []
        for path in _progress(self.paths, "multiscale features", progress):
            item = self._compute(path)
            if in_memory:
                self._items.append(item)

    def _compute(self, path: Path) -> tuple[Tensor, Tensor, Tensor]:
        mesh = load_mesh(path, merge_seams=self.merge_seams)
        if self.cache is not None:
            features = cached_features_with_settings(
                mesh.vertices, mesh.faces, self.cache, self.settings
            )
        else:
            with torch.no_grad():
                features = features_with_settings(mesh.vertices, mesh.faces, self.settings)
        return mesh.vertices.to(self.dtype), mesh.faces, features.to(self.dtype)

    def channel_names(self) -> list[str]:
        """Names of the ``C`` feature channels."""
        return self.settings.channel_names()

    def __len__(self) -> int:
        return len(self.paths)

    def __getitem__(self, index: int) -> MeshSample:
        if not -len(self) <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} meshes")
        index = index % len(self)
        if self.in_memory:
            vertices, faces, features = self._items[index]
        else:
            vertices, faces, features = self._compute(self.paths[index])
        return MeshSample(vertices, faces, features, str(self.paths[index]), index)
