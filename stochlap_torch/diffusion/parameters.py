"""The parameters every run of the steps takes: scales, threshold, backend, progress."""

from __future__ import annotations

from collections.abc import Callable

import torch

from .._common.errors import ParameterError
from .._kernels import numba_available

__all__ = ["BACKENDS", "ProgressCallback", "check_parameters", "resolve_backend"]

#: ``progress(k, K)``: called as a run advances through the scales ``k = 1..K``.
ProgressCallback = Callable[[int, int], None]

#: ``"auto"``: the fused numba kernel on CPU when numba is installed, torch ops elsewhere;
#: ``"torch"``: the torch ops on every device (the cross-check); ``"numba"``: insist on it.
BACKENDS = ("auto", "torch", "numba")


def check_parameters(num_scales: int, threshold: float) -> None:
    """Raise :class:`ParameterError` (a ``ValueError``) unless ``num_scales >= 2`` and
    ``0 < threshold < 1``."""
    if isinstance(num_scales, bool) or not isinstance(num_scales, int) or num_scales < 2:
        raise ParameterError(f"num_scales must be an integer >= 2, got {num_scales!r}")
    if not (isinstance(threshold, (int, float)) and 0.0 < threshold < 1.0):
        raise ParameterError(f"threshold must lie in the open interval (0, 1), got {threshold!r}")


def resolve_backend(backend: str, device: torch.device) -> str:
    """``"numba"`` or ``"torch"`` for ``backend`` in :data:`BACKENDS` on ``device``."""
    if backend not in BACKENDS:
        raise ParameterError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "numba" and (device.type != "cpu" or not numba_available()):
        raise ParameterError("backend='numba' needs CPU tensors and numba installed")
    if backend == "auto":
        return "numba" if device.type == "cpu" and numba_available() else "torch"
    return backend
