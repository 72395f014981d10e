"""Algorithm 1: the steps from ``F^(1)`` to ``F^(K)`` (:mod:`.step`), the one driver that
runs them (:mod:`.engine`), budgets (:mod:`.memory`), the result (:mod:`.representation`) and
the entry points built on the engine; the options are :class:`~stochlap_torch.params.PaperParams`.
"""

from .api import multiscale_representation
from .autodiff import differentiable_multiscale
from .distributed import init_loopback_group, partitioned_multiscale, row_partition
from .engine import Steps, run_steps
from .memory import (
    MEMORY_ENV,
    MemoryBudgetError,
    MemoryEstimate,
    default_memory_budget,
    estimate_memory,
    streamed_memory,
)
from .parameters import BACKENDS, ProgressCallback
from .representation import (
    MultiscaleRepresentation,
    saliency_from_differences,
    scale_coefficients,
)
from .step import ConstantOperatorStep

__all__ = [
    "BACKENDS",
    "MEMORY_ENV",
    "ConstantOperatorStep",
    "MemoryBudgetError",
    "MemoryEstimate",
    "MultiscaleRepresentation",
    "ProgressCallback",
    "Steps",
    "default_memory_budget",
    "differentiable_multiscale",
    "estimate_memory",
    "init_loopback_group",
    "multiscale_representation",
    "partitioned_multiscale",
    "row_partition",
    "run_steps",
    "saliency_from_differences",
    "scale_coefficients",
    "streamed_memory",
]
