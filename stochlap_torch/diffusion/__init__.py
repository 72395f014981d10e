"""Algorithm 1: the steps from ``F^(1)`` to ``F^(K)`` (:mod:`.step`), the one driver that
runs them (:mod:`.engine`), budgets (:mod:`.memory`), the result (:mod:`.representation`) and
the entry points built on the engine; the options are :class:`~stochlap_torch.params.PaperParams`.
"""

from .api import multiscale_representation
from .autodiff import DifferentiableStep, differentiable_multiscale
from .distributed import init_loopback_group, partitioned_multiscale, row_partition
from .engine import Steps, run_steps
from .memory import (
    MEMORY_ENV,
    MemoryBudgetError,
    MemoryEstimate,
    check_memory,
    default_memory_budget,
    estimate_memory,
    resolve_budget,
    streamed_memory,
)
from .parameters import BACKENDS, ProgressCallback, check_parameters, resolve_backend
from .representation import (
    MultiscaleRepresentation,
    saliency_from_differences,
    scale_coefficients,
)
from .step import ConstantOperatorStep, diffusion_step, fused_step, scale_steps

__all__ = [
    "BACKENDS",
    "MEMORY_ENV",
    "ConstantOperatorStep",
    "DifferentiableStep",
    "MemoryBudgetError",
    "MemoryEstimate",
    "MultiscaleRepresentation",
    "ProgressCallback",
    "Steps",
    "check_memory",
    "check_parameters",
    "default_memory_budget",
    "differentiable_multiscale",
    "diffusion_step",
    "estimate_memory",
    "fused_step",
    "init_loopback_group",
    "multiscale_representation",
    "partitioned_multiscale",
    "resolve_backend",
    "resolve_budget",
    "row_partition",
    "run_steps",
    "saliency_from_differences",
    "scale_coefficients",
    "scale_steps",
    "streamed_memory",
]
