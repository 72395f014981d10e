"""The parameters every run of the steps takes: scales, threshold, backend, progress."""

from __future__ import annotations

from collections.abc import Callable

import torch

from .._common.checks import check_int, check_number
from .._common.errors import ParameterError
from .._kernels import numba_available

__all__ = ["BACKENDS", "MAX_SCALES", "ProgressCallback", "check_parameters", "resolve_backend"]

#: ``progress(k, K)``: called as a run advances through the scales ``k = 1..K``.
ProgressCallback = Callable[[int, int], None]

#: ``"auto"``: the fused numba kernel on CPU when numba is installed, torch ops elsewhere;
#: ``"torch"``: the torch ops on every device (the cross-check); ``"numba"``: insist on it.
BACKENDS = ("auto", "torch", "numba")


#: More scales than this is a mistake (each scale at least doubles the diffusion time).
MAX_SCALES = 64


def check_parameters(num_scales: int, threshold: float) -> tuple[int, float]:
    """``(num_scales, threshold)`` as Python numbers; :class:`ParameterError` (a
    ``ValueError``) unless ``2 <= num_scales <= MAX_SCALES`` and ``0 < threshold < 1``
    (numpy and 0-d tensor numbers are accepted)."""
    num_scales = check_int("num_scales", num_scales, minimum=2, maximum=MAX_SCALES)
    threshold = check_number("threshold", threshold, 0.0, 1.0, open_low=True, open_high=True)
    return num_scales, threshold


def resolve_backend(backend: str, device: torch.device) -> str:
    """``"numba"`` or ``"torch"`` for ``backend`` in :data:`BACKENDS` on ``device``."""
    if backend not in BACKENDS:
        raise ParameterError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "numba" and (device.type != "cpu" or not numba_available()):
        raise ParameterError("backend='numba' needs CPU tensors and numba installed")
    if backend == "auto":
        return "numba" if device.type == "cpu" and numba_available() else "torch"
    return backend
