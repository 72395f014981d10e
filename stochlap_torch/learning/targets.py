"""Where a :class:`~stochlap_torch.learning.MeshFeatureDataset` finds its targets, and their
checks."""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .._common.errors import ParameterError

#: ``path -> target``, a mapping from a file's path or name to its target, or a sequence with
#: one target per file in ``dataset.paths`` order.
TargetSource = Callable[[Path], Any] | Mapping[Any, Any] | Sequence[Any] | Tensor


def check_target_source(name: str, source, num_files: int):
    """``source`` as a :data:`TargetSource` for ``num_files`` files (mapping keys normalised to
    ``str(Path(key))``), or ``None``.

    Raises:
        ParameterError: not a callable, mapping or sequence; or a sequence of another length.
    """
    if source is None or callable(source):
        return source
    if isinstance(source, Mapping):
        return {_path_key(key): value for key, value in source.items()}
    try:
        length = None if isinstance(source, (str, bytes)) else len(source)
    except TypeError:
        length = None
    if length is None or not hasattr(source, "__getitem__"):
        raise ParameterError(
            f"{name} must be a callable path -> target, a mapping from a file's path or name "
            f"to its target, or a sequence with one target per file; got {type(source).__name__}"
        )
    if length != num_files:
        raise ParameterError(f"{name} has {length} entries for {num_files} mesh files")
    return source


def _path_key(key):
    """A mapping key as it is looked up: paths and strings as ``str(Path(key))``."""
    return str(Path(key)) if isinstance(key, (str, os.PathLike)) else key


def read_target(name: str, source, path: Path, position: int, dtype: torch.dtype) -> Tensor:
    """The target of file ``path`` (``position`` in the dataset) from a checked ``source``, as a
    tensor: integer and boolean targets keep their dtype, floating ones become ``dtype``.

    Raises:
        ParameterError: a mapping without the file (by path, then by name), or a value that
            is not array-like.
    """
    if callable(source):
        value = source(path)
    elif isinstance(source, dict):
        key = next((k for k in (str(path), path.name) if k in source), None)
        if key is None:
            raise ParameterError(
                f"{name} has no entry for {path} (keys are matched to the file's path, then "
                f"to its name {path.name!r})"
            )
        value = source[key]
    else:
        value = source[position]
    try:
        tensor = torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ParameterError(f"{name} of {path} is not array-like: {exc}") from exc
    return tensor.to(dtype) if tensor.is_floating_point() else tensor


def check_vertex_target(tensor: Tensor, path: Path, num_vertices: int, merged: bool) -> None:
    """Raise :class:`ParameterError` unless ``tensor`` has one row per vertex."""
    if tensor.ndim == 0 or tensor.shape[0] != num_vertices:
        after = " after merge_seams" if merged else ""
        raise ParameterError(
            f"vertex_targets of {path} has shape {tuple(tensor.shape)}, not one row per vertex "
            f"of the mesh ({num_vertices} vertices{after})"
        )
