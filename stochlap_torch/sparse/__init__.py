"""Sparse CSR matrices: the container, the registered ``stochlap::`` torch operators and the
differentiable pattern operations.

The operators take CSR components as ordinary tensors (torch's fake-tensor machinery does not
accept ``torch.sparse_csr`` inputs); :class:`CSR` converts at the public boundary. Each module
lists its public names in its ``__all__``; this package exports them all.
"""

from . import autograd, csr, ops
from .autograd import *  # noqa: F403
from .csr import *  # noqa: F403
from .ops import *  # noqa: F403

__all__ = [name for module in (autograd, csr, ops) for name in module.__all__]
