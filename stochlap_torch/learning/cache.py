"""On-disk cache of per-mesh results (features, operators, structures), keyed by content.

The key (:func:`content_key`) hashes what determines the numbers: the source of the code that
computes them and torch's version
(:func:`~stochlap_torch.learning.feature_files.numerics_fingerprint`), the mesh's bytes and every
parameter. A release that changes no number keeps the cache; any change to that code
invalidates it, whatever the package version says.

Entries are ``.npz`` files read with ``allow_pickle=False``, each storing its full key. Nothing
loaded is trusted: a file that cannot be read, holds another key, or whose arrays are not what
the key promises gives a :class:`CacheWarning` and is recomputed and replaced. Writes are
atomic (a temporary file, then ``os.replace``). A FIFO, device or folder at an entry's path is
the user's: it is left alone and the value computed uncached. A cache that cannot be written
warns once per folder and returns what it computed.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import threading
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from .._common.errors import CacheError, ParameterError
from .._common.files import NotARegularFileError, atomic_write, node_kind, open_regular
from .._common.tensors import to_numpy
from ..diffusion import multiscale_representation
from ..features import channel_names, feature_params, multiscale_features
from ..mesh import as_mesh_tensors
from ..params import PaperFeatureParams, PaperParams, RobustParams, resolve_params
from ..robust.structure import RobustStructure, build_structure
from ..sparse import CSR
from .feature_files import numerics_fingerprint

logger = logging.getLogger(__name__)

_KEY_FIELD = "__cache_key__"
_NUMERICS_FIELD = "__cache_numerics__"


class CacheWarning(UserWarning):
    """A cache file was unreadable or did not match its key; it was recomputed."""


def _canonical(value):
    """JSON-ready form of a parameter value (floats exact via repr)."""
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
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {type(value).__name__: _canonical(dataclasses.asdict(value))}
    raise ParameterError(f"cache parameters must be JSON-like, got {type(value).__name__}")


def content_key(vertices, faces, params: Mapping, kind: str = "features") -> str:
    """64 hex digits: SHA-256 of the numerics fingerprint, kind, mesh bytes and ``params``.

    Args:
        vertices: ``(V, 3)`` float tensor or array.
        faces: ``(F, 3)`` integer tensor or array.
        params: every parameter the cached value depends on (JSON-like values).
        kind: a label separating different cached quantities of one mesh.
    """
    digest = hashlib.sha256()
    header = {"numerics": numerics_fingerprint(), "kind": kind, "params": _canonical(params)}
    for name, array in (("vertices", vertices), ("faces", faces)):
        data = np.ascontiguousarray(to_numpy(array))
        header[name] = [str(data.dtype), list(data.shape)]
        digest.update(data.tobytes())
    digest.update(json.dumps(header, sort_keys=True).encode())
    return digest.hexdigest()


def features_key(vertices, faces, params: RobustParams | PaperFeatureParams) -> str:
    """The key of the features of resolved ``params`` (:func:`cached_features`)."""
    return content_key(vertices, faces, {"params": params}, kind="multiscale_features")


def operators_key(vertices, faces, params: PaperParams) -> str:
    """The key of the operators ``F^(1..K)`` of ``params`` (:func:`cached_operators`)."""
    return content_key(vertices, faces, {"params": params}, kind="operators")


class MeshCache:
    """A folder of ``.npz`` files, one per key.

    Args:
        directory: created if missing.

    Raises:
        CacheError: the folder cannot be created.
    """

    def __init__(self, directory: str | os.PathLike):
        self.directory = Path(directory)
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise CacheError(f"cache folder {self.directory} cannot be created: {error}") from error

    def path(self, key: str) -> Path:
        """The file of ``key`` (named by its first 32 hex digits; the full key is inside)."""
        if len(key) != 64 or any(c not in "0123456789abcdef" for c in key):
            raise ParameterError(f"cache keys are 64 lowercase hex digits, got {key!r}")
        return self.directory / f"{key[:32]}.npz"

    def load(self, key: str) -> dict[str, np.ndarray] | None:
        """The arrays stored under ``key``, or ``None`` (missing, or warned about)."""
        path = self.path(key)
        try:
            handle = open_regular(path)
        except NotARegularFileError as error:
            _warn(path, f"is {error.kind}, not a regular file; it is left alone and not cached")
            return None
        except OSError as error:
            _warn(path, f"cannot be opened ({type(error).__name__}: {error})")
            return None
        if handle is None:
            return None
        try:
            with handle, np.load(handle, allow_pickle=False) as archive:
                arrays = {name: archive[name] for name in archive.files}
        except Exception as error:
            _warn(path, f"is unreadable ({type(error).__name__}: {error})")
            return None
        stored_key = arrays.pop(_KEY_FIELD, None)
        stored_numerics = arrays.pop(_NUMERICS_FIELD, None)
        if stored_key is None or str(stored_key) != key:
            _warn(path, "holds another key")
            return None
        if stored_numerics is None or str(stored_numerics) != numerics_fingerprint():
            _warn(path, "was computed by other numerics")
            return None
        return arrays

    def store(self, key: str, arrays: Mapping[str, np.ndarray | Tensor]) -> Path:
        """Write ``arrays`` under ``key`` atomically; return the file.

        Raises:
            CacheError: the file cannot be written, or is not a regular file (left as it is).
        """
        payload = {}
        for name, value in arrays.items():
            if name.startswith("__"):
                raise ParameterError(f"array names starting with '__' are reserved, got {name!r}")
            payload[name] = to_numpy(value)
        payload[_KEY_FIELD] = np.array(key)
        payload[_NUMERICS_FIELD] = np.array(numerics_fingerprint())
        path = self.path(key)
        try:
            with atomic_write(path, "wb") as handle:  # refuses a path that is no regular file
                np.savez(handle, **payload)
        except NotARegularFileError as error:
            raise CacheError(f"cache file {error}") from error
        except OSError as error:
            raise CacheError(f"cache file {path} cannot be written ({error})") from error
        return path

    def get_or_compute(
        self,
        key: str,
        compute: Callable[[], Mapping[str, np.ndarray | Tensor]],
        check: Callable[[Mapping[str, np.ndarray]], None] | None = None,
    ) -> dict[str, Tensor]:
        """Stored arrays of ``key`` as tensors; else ``compute()``, stored, and returned.

        ``check(arrays)`` raises ``ValueError`` (or ``KeyError``) when loaded arrays are not
        what the key promises; they are then recomputed and the file replaced.
        """
        arrays = self.load(key)
        if arrays is not None and check is not None:
            try:
                check(arrays)
            except (ValueError, KeyError) as error:
                _warn(self.path(key), f"holds invalid data ({error})")
                arrays = None
        if arrays is None:
            logger.debug("cache miss %s", key[:12])
            computed = compute()
            # A FIFO, device or folder at the path is the user's: load warned, nothing cached.
            if node_kind(self.path(key)) is None:
                try:
                    self.store(key, computed)
                except CacheError as error:
                    warn_unwritable(self.directory, error)
            arrays = {name: to_numpy(value) for name, value in computed.items()}
        return {name: torch.from_numpy(np.array(value)) for name, value in arrays.items()}


def _warn(path: Path, problem: str) -> None:
    warnings.warn(f"cache file {path} {problem}; recomputing", CacheWarning, stacklevel=4)


_unwritable_lock = threading.Lock()
_unwritable_folders: set[str] = set()


def warn_unwritable(directory: Path, error: CacheError) -> None:
    """Warn that ``directory`` cannot be written, once per process: every miss would say it
    (the cache's, and the feature files of a dataset)."""
    folder = os.path.abspath(directory)
    with _unwritable_lock:
        if folder in _unwritable_folders:
            return
        _unwritable_folders.add(folder)
    warnings.warn(
        f"{error}; values computed with the cache in {directory} are returned uncached "
        "(warned once)",
        CacheWarning,
        stacklevel=4,
    )


def feature_ceiling(dtype) -> float:
    """The largest magnitude a cached feature of ``dtype`` may have: the square root of the
    dtype's largest value. Every channel is a logarithm, a difference map in ``[0, 2]`` or a
    ratio of lengths: a larger value in a cache file is corruption or tampering (and would
    overflow when squared anyway)."""
    return float(np.sqrt(np.finfo(dtype).max))


def check_row_stochastic(name: str, crow: np.ndarray, val: np.ndarray) -> None:
    """Raise ``ValueError`` (naming ``name``) unless the finite CSR values ``val`` (rows
    ``crow``) lie in ``[0, 1]`` and every row sums to 1, both within ``sqrt(eps)`` of the dtype
    (every ``F^(k)`` sums its rows to 1 within a few ``eps``)."""
    tolerance = float(np.sqrt(np.finfo(val.dtype).eps))
    if val.size and (val.min() < 0 or val.max() > 1 + tolerance):
        raise ValueError(f"{name}: values outside [0, 1]")
    num_rows = crow.shape[0] - 1
    rows = np.repeat(np.arange(num_rows), np.diff(crow))
    sums = np.bincount(rows, weights=val.astype(np.float64), minlength=num_rows)
    if sums.size and np.abs(sums - 1).max() > tolerance:
        raise ValueError(f"{name}: rows do not sum to 1")


def cached_features(
    vertices,
    faces,
    cache: MeshCache | str | os.PathLike,
    *,
    variant: str | None = None,
    max_memory: int | None = None,
    **options,
) -> Tensor:
    """``(V, C)`` :func:`~stochlap_torch.features.multiscale_features` of one mesh, through
    the cache: on the CPU, in the dtype of ``vertices``, without gradient.

    The variant and options are those of ``multiscale_features``, but ``batch`` and
    ``differentiable_operator``. The key holds the resolved options
    (:func:`~stochlap_torch.features.feature_params`), so spellings of one computation share
    one entry; ``max_memory`` changes no number and is not part of it.

    Raises:
        ParameterError: an unknown or bad option, or one the variant does not use.
    """
    if "batch" in options or "differentiable_operator" in options:
        raise ParameterError(
            "cached_features caches one mesh at a time, without gradients: it takes the "
            "options of multiscale_features but batch and differentiable_operator"
        )
    params = feature_params(variant, **options)
    cache = cache if isinstance(cache, MeshCache) else MeshCache(cache)
    paper = isinstance(params, PaperFeatureParams)  # the robust variant takes zero-length edges
    points, faces = as_mesh_tensors(vertices, faces, check_edge_lengths=paper)
    key = features_key(points, faces, params)
    shape = (points.shape[0], len(channel_names(params)))
    dtype = to_numpy(points).dtype

    def compute():
        with torch.no_grad():
            features = multiscale_features(points, faces, params=params, max_memory=max_memory)
        return {"features": features}

    def check(arrays):
        features = arrays["features"]
        if features.shape != shape or features.dtype != dtype:
            raise ValueError(
                f"features {features.shape} {features.dtype}, expected {shape} {dtype}"
            )
        if not np.isfinite(features).all():
            raise ValueError("features hold NaN or Inf")
        if features.size and np.abs(features).max() > feature_ceiling(dtype):
            raise ValueError(f"features exceed {feature_ceiling(dtype):.3g} in magnitude")

    return cache.get_or_compute(key, compute, check)["features"]


def cached_operators(
    vertices,
    faces,
    cache: MeshCache | str | os.PathLike,
    **options,
) -> list[Tensor]:
    """``F^(1..K)`` of the paper's Algorithm 1 as ``(V, V)`` ``torch.sparse_csr`` tensors,
    through the cache. ``options``: fields of :class:`~stochlap_torch.params.PaperParams` or
    the object as ``params=`` / ``paper=``."""
    params = resolve_params(PaperParams, "paper", options)
    cache = cache if isinstance(cache, MeshCache) else MeshCache(cache)
    points, faces = as_mesh_tensors(vertices, faces)
    num_scales, threshold = params.num_scales, params.threshold
    key = operators_key(points, faces, params)
    size = points.shape[0]
    dtype = to_numpy(points).dtype

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

    def check(arrays):
        """Every ``F^(k)`` a valid ``(V, V)`` CSR of the mesh's dtype, and row-stochastic."""
        for k in range(num_scales):
            crow, col, val = arrays[f"crow{k}"], arrays[f"col{k}"], arrays[f"val{k}"]
            if crow.shape != (size + 1,) or crow.dtype != np.int64 or col.dtype != np.int64:
                raise ValueError(f"operator {k + 1}: row pointers or columns of the wrong shape")
            if val.dtype != dtype or col.shape != val.shape or col.ndim != 1:
                raise ValueError(f"operator {k + 1}: values of the wrong shape or dtype")
            if crow[0] != 0 or crow[-1] != col.shape[0] or (np.diff(crow) < 0).any():
                raise ValueError(f"operator {k + 1}: row pointers are not a CSR's")
            if col.size and (col.min() < 0 or col.max() >= size):
                raise ValueError(f"operator {k + 1}: column indices outside [0, {size})")
            if not np.isfinite(val).all():
                raise ValueError(f"operator {k + 1}: values hold NaN or Inf")
            check_row_stochastic(f"operator {k + 1}", crow, val)

    arrays = cache.get_or_compute(key, compute, check)
    return [
        CSR(arrays[f"crow{k}"], arrays[f"col{k}"], arrays[f"val{k}"], size).to_sparse_csr()
        for k in range(num_scales)
    ]


def cached_structure(
    vertices,
    faces,
    cache: MeshCache | str | os.PathLike,
    **options,
) -> RobustStructure:
    """:func:`~stochlap_torch.robust_structure` of one mesh, through the cache, on the device
    of ``vertices``. ``options``: fields of :class:`~stochlap_torch.params.RobustParams` or the
    object as ``params=`` / ``robust=``. A stored structure is checked array by array
    (:meth:`~stochlap_torch.RobustStructure.from_state_dict`) and recomputed if it is not one
    for this mesh.

    Raises:
        MeshError: bad mesh. ParameterError: bad settings.
    """
    params = resolve_params(RobustParams, "robust", options)
    cache = cache if isinstance(cache, MeshCache) else MeshCache(cache)
    points, faces = as_mesh_tensors(vertices, faces, check_edge_lengths=False)
    key = content_key(points, faces, {"params": params}, kind="robust_structure")
    counts = (points.shape[0], faces.shape[0])

    # The structure built (a miss) or checked (a hit) is returned: no second pass over it.
    found: dict[str, RobustStructure] = {}

    def compute():
        found["structure"] = build_structure(points.detach().cpu(), faces.cpu(), params)
        return found["structure"].state_dict()

    def check(arrays):
        structure = RobustStructure.from_state_dict(arrays)
        if structure.params != params or (structure.num_vertices, structure.num_faces) != counts:
            raise ValueError("a structure of another mesh or other options")
        found["structure"] = structure

    cache.get_or_compute(key, compute, check)
    return found["structure"].to(points.device)
