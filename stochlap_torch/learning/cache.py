"""On-disk cache of per-mesh results (features, operators), keyed by content.

The key is a SHA-256 over the library version, a kind label, the dtype, shape and bytes of the
vertices and faces, and every parameter (as sorted JSON). Entries are NumPy ``.npz`` files read
with ``allow_pickle=False`` (no code runs on load). Each file stores its own full key; a file
that cannot be read, or whose stored key or version differs from the expected one, is never
trusted: a warning is issued and the value recomputed and rewritten. Writes go to a temporary
file in the same folder, then ``os.replace``: readers and concurrent writers see either a whole
old file or a whole new one.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
import warnings
import zipfile
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._common.errors import ParameterError
from .._common.version import __version__
from ..diffusion import multiscale_representation
from ..features import multiscale_features
from ..mesh import as_mesh_tensors
from ..sparse import CSR

__all__ = ["CacheWarning", "MeshCache", "cached_features", "cached_operators", "content_key"]

logger = logging.getLogger(__name__)

_KEY_FIELD = "__cache_key__"
_VERSION_FIELD = "__cache_version__"


class CacheWarning(UserWarning):
    """A cache file was unreadable or did not match its key; it was recomputed."""


def _library_version() -> str:
    return __version__


def _canonical(value):
    """JSON-ready form of a parameter value (tuples as lists, floats exact via repr)."""
    if isinstance(value, Mapping):
        return {str(k): _canonical(v) for k, v in sorted(value.items())}
    if isinstance(value, (list, tuple)):
        return [_canonical(v) for v in value]
    if isinstance(value, float):
        return repr(value)
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, torch.dtype):
        return str(value)
    raise TypeError(f"cache parameters must be JSON-like, got {type(value).__name__}")


def content_key(vertices, faces, params: Mapping, kind: str = "features") -> str:
    """64 hex digits: SHA-256 of version, kind, mesh bytes and dtypes, and ``params``.

    Args:
        vertices: ``(V, 3)`` float tensor or array.
        faces: ``(F, 3)`` integer tensor or array.
        params: every parameter the cached value depends on (JSON-like values).
        kind: a label separating different cached quantities of one mesh.
    """
    digest = hashlib.sha256()
    header = {"version": _library_version(), "kind": kind, "params": _canonical(params)}
    for name, array in (("vertices", vertices), ("faces", faces)):
        data = np.ascontiguousarray(
            array.detach().cpu().numpy() if isinstance(array, Tensor) else np.asarray(array)
        )
        header[name] = [str(data.dtype), list(data.shape)]
        digest.update(data.tobytes())
    digest.update(json.dumps(header, sort_keys=True).encode())
    return digest.hexdigest()


class MeshCache:
    """A folder of ``.npz`` files, one per key.

    Args:
        directory: created if missing.
    """

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)

    def path(self, key: str) -> Path:
        """The file of ``key`` (named by its first 32 hex digits; the full key is inside)."""
        if len(key) != 64 or any(c not in "0123456789abcdef" for c in key):
            raise ParameterError(f"cache keys are 64 lowercase hex digits, got {key!r}")
        return self.directory / f"{key[:32]}.npz"

    def load(self, key: str) -> dict[str, np.ndarray] | None:
        """The arrays stored under ``key``, or ``None`` (missing, unreadable or mismatched)."""
        path = self.path(key)
        if not path.exists():
            return None
        try:
            with np.load(path, allow_pickle=False) as archive:
                arrays = {name: archive[name] for name in archive.files}
        except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as error:
            warnings.warn(
                f"cache file {path} is unreadable ({type(error).__name__}: {error}); recomputing",
                CacheWarning,
                stacklevel=3,
            )
            return None
        stored_key = arrays.pop(_KEY_FIELD, None)
        stored_version = arrays.pop(_VERSION_FIELD, None)
        if stored_key is None or str(stored_key) != key:
            warnings.warn(
                f"cache file {path} holds another key; recomputing", CacheWarning, stacklevel=3
            )
            return None
        if stored_version is None or str(stored_version) != _library_version():
            warnings.warn(
                f"cache file {path} was written by another library version; recomputing",
                CacheWarning,
                stacklevel=3,
            )
            return None
        return arrays

    def store(self, key: str, arrays: Mapping[str, np.ndarray | Tensor]) -> Path:
        """Write ``arrays`` under ``key`` atomically; return the file."""
        payload = {}
        for name, value in arrays.items():
            if name.startswith("__"):
                raise ParameterError(f"array names starting with '__' are reserved, got {name!r}")
            payload[name] = value.detach().cpu().numpy() if isinstance(value, Tensor) else value
        payload[_KEY_FIELD] = np.array(key)
        payload[_VERSION_FIELD] = np.array(_library_version())
        path = self.path(key)
        handle, temporary = tempfile.mkstemp(dir=self.directory, prefix=".tmp-", suffix=".npz")
        try:
            with os.fdopen(handle, "wb") as file:
                np.savez(file, **payload)
                file.flush()
                os.fsync(file.fileno())
            os.chmod(temporary, 0o644)  # mkstemp creates 0600; cache files are shareable
            os.replace(temporary, path)
        except BaseException:
            Path(temporary).unlink(missing_ok=True)
            raise
        return path

    def get_or_compute(
        self, key: str, compute: Callable[[], Mapping[str, np.ndarray | Tensor]]
    ) -> dict[str, Tensor]:
        """Stored arrays of ``key`` as tensors; else ``compute()``, stored, and returned."""
        arrays = self.load(key)
        if arrays is None:
            logger.debug("cache miss %s", key[:12])
            computed = compute()
            self.store(key, computed)
            arrays = {
                name: value.detach().cpu().numpy() if isinstance(value, Tensor) else value
                for name, value in computed.items()
            }
        return {name: torch.from_numpy(np.array(value)) for name, value in arrays.items()}


def cached_features(vertices, faces, cache: MeshCache | str | os.PathLike, **params) -> Tensor:
    """``(V, C)`` :func:`~stochlap_torch.features.multiscale_features`, through the cache.

    ``params`` are the keyword arguments of ``multiscale_features`` (all part of the key). The
    result is on the CPU, in the dtype of ``vertices``, without gradient.
    """
    if not isinstance(cache, MeshCache):
        cache = MeshCache(cache)
    if "batch" in params:
        raise ParameterError("cached_features caches one mesh at a time; pass meshes separately")
    points, faces = as_mesh_tensors(vertices, faces)
    key = content_key(points, faces, params, kind="multiscale_features")

    def compute():
        with torch.no_grad():
            return {"features": multiscale_features(points, faces, **params)}

    return cache.get_or_compute(key, compute)["features"]


def cached_operators(
    vertices,
    faces,
    cache: MeshCache | str | os.PathLike,
    num_scales: int = 8,
    threshold: float = 1e-3,
) -> list[Tensor]:
    """``F^(1..K)`` as ``(V, V)`` ``torch.sparse_csr`` tensors, through the cache."""
    if not isinstance(cache, MeshCache):
        cache = MeshCache(cache)
    points, faces = as_mesh_tensors(vertices, faces)
    params = {"num_scales": num_scales, "threshold": threshold}
    key = content_key(points, faces, params, kind="operators")

    def compute():
        with torch.no_grad():
            rep = multiscale_representation(
                points, faces, num_scales, threshold, return_operators=True
            )
        arrays = {}
        for k, operator in enumerate(rep.operators):
            arrays[f"crow{k}"] = operator.crow_indices()
            arrays[f"col{k}"] = operator.col_indices()
            arrays[f"val{k}"] = operator.values()
        return arrays

    arrays = cache.get_or_compute(key, compute)
    size = points.shape[0]
    return [
        CSR(arrays[f"crow{k}"], arrays[f"col{k}"], arrays[f"val{k}"], size).to_sparse_csr()
        for k in range(num_scales)
    ]
