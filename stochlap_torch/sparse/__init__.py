"""Sparse CSR matrices: the container, the registered ``stochlap::`` torch operators and the
differentiable pattern operations. This package exports every module's ``__all__``."""

from . import autograd, csr, ops
from .autograd import *  # noqa: F403
from .csr import *  # noqa: F403
from .ops import *  # noqa: F403

__all__ = [name for module in (autograd, csr, ops) for name in module.__all__]
