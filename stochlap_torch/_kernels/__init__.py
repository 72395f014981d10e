"""Compiled CPU kernels (numba): the diffusion step and the construction of ``Lhat``.

They work on numpy arrays and import nothing else from the package; the torch-facing code in
:mod:`stochlap_torch.operators` and :mod:`stochlap_torch.diffusion` calls them and is tested
against the torch ops that do the same on every device. Every kernel leaves the caller's numba
thread settings as it found them (:func:`kernel_threads`).
"""

from ._numba import numba_available
from .block import LANES, SplitLhat
from .buffers import WORKSPACES, Workspace, WorkspacePool, prefaulted_zeros
from .mesh import LhatParts, lhat_parts
from .rows import Rows, first_rows, index_dtype, split_lhat
from .steps import SERIAL_ENTRIES, SERIAL_ROWS, fused_step, stream_steps
from .threads import kernel_threads, max_threads

__all__ = [
    "LANES",
    "SERIAL_ENTRIES",
    "SERIAL_ROWS",
    "WORKSPACES",
    "LhatParts",
    "Rows",
    "SplitLhat",
    "Workspace",
    "WorkspacePool",
    "first_rows",
    "fused_step",
    "index_dtype",
    "kernel_threads",
    "lhat_parts",
    "max_threads",
    "numba_available",
    "prefaulted_zeros",
    "split_lhat",
    "stream_steps",
]
