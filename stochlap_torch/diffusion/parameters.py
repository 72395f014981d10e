"""What every run of the steps takes besides :class:`~stochlap_torch.params.PaperParams`: the
backend and the progress callback."""

from __future__ import annotations

from collections.abc import Callable

import torch

from .._common.errors import ParameterError
from .._kernels import cuda_available, cuda_simulator_enabled, numba_available
from ..params import PaperParams

#: ``progress(k, K)``: called as a run advances through the scales ``k = 1..K``.
ProgressCallback = Callable[[int, int], None]

#: ``"auto"``: the numba kernel on CPU when numba is installed, the torch ops elsewhere;
#: ``"torch"``: the torch ops on every device; ``"numba"``, ``"cuda"``: insist on that kernel
#: (CUDA: the streamed path, no operators kept, no gradient).
BACKENDS = ("auto", "torch", "numba", "cuda")
#: Whether ``"auto"`` takes the CUDA kernel on CUDA tensors: off until checked on a GPU.
CUDA_KERNEL_BY_DEFAULT = False


def check_parameters(num_scales: int, threshold: float) -> tuple[int, float]:
    """``(num_scales, threshold)`` as Python numbers; :class:`ParameterError` unless they make
    a :class:`~stochlap_torch.params.PaperParams`."""
    params = PaperParams(num_scales, threshold)
    return params.num_scales, params.threshold


def _cuda_kernel_runs_on(device: torch.device) -> bool:
    """A CUDA device with numba's CUDA target, or the CPU under numba's CUDA simulator."""
    if device.type == "cuda":
        return cuda_available()
    return device.type == "cpu" and cuda_simulator_enabled()


def resolve_backend(backend: str, device: torch.device) -> str:
    """``"numba"``, ``"cuda"`` or ``"torch"`` for ``backend`` on ``device``;
    :class:`ParameterError` for a name not in :data:`BACKENDS` or a kernel that cannot run."""
    if backend not in BACKENDS:
        raise ParameterError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "numba" and (device.type != "cpu" or not numba_available()):
        raise ParameterError("backend='numba' needs CPU tensors and numba installed")
    if backend == "cuda" and not _cuda_kernel_runs_on(device):
        raise ParameterError(
            f"backend='cuda' needs CUDA tensors and numba's CUDA target "
            f"(numba.cuda.is_available()), got tensors on {device.type}"
        )
    if backend == "auto":
        if device.type == "cpu":
            return "numba" if numba_available() else "torch"
        by_default = CUDA_KERNEL_BY_DEFAULT and device.type == "cuda" and cuda_available()
        return "cuda" if by_default else "torch"
    return backend
