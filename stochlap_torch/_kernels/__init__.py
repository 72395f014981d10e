"""Compiled kernels (numba): the diffusion step and the construction of ``Lhat`` on the CPU,
the robust variant's geometry, and the streamed steps on a GPU (:mod:`.cuda_steps`). They work
on numpy arrays, import nothing else from the package and run on a few Python threads
(:func:`run_workers`), never on numba's threading layer.
"""

from .block import LANES, SplitLhat
from .buffers import WORKSPACES, prefaulted_zeros
from .cuda_steps import (
    SCRATCH_BYTES,
    CudaLhat,
    cuda_available,
    cuda_scratch_floor,
    cuda_simulator_enabled,
    kernel_array,
    on_device,
    stream_steps_cuda,
)
from .geometry import closest_triangles, intrinsic_delaunay, intrinsic_delaunay_weights
from .jit import KernelCacheWarning, kernel_jit
from .mesh import lhat_parts
from .rows import Rows, first_rows, index_dtype, split_lhat
from .steps import fused_step, stream_steps
from .threads import kernel_thread_count, numba_available, run_workers

__all__ = [
    "LANES",
    "SCRATCH_BYTES",
    "WORKSPACES",
    "CudaLhat",
    "KernelCacheWarning",
    "Rows",
    "SplitLhat",
    "closest_triangles",
    "cuda_available",
    "cuda_scratch_floor",
    "cuda_simulator_enabled",
    "first_rows",
    "fused_step",
    "index_dtype",
    "intrinsic_delaunay",
    "intrinsic_delaunay_weights",
    "kernel_array",
    "kernel_jit",
    "kernel_thread_count",
    "lhat_parts",
    "numba_available",
    "on_device",
    "prefaulted_zeros",
    "run_workers",
    "split_lhat",
    "stream_steps",
    "stream_steps_cuda",
]
