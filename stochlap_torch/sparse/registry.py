"""Registration of the ``stochlap`` torch operators: a schema, a fake kernel (for
``torch.compile`` and ``torch.export``) and, where it has one, an autograd formula. With
:class:`torch.library.Library`, not ``torch.library.custom_op``, whose kernels import
``torch._dynamo`` (a large import, paid by every command-line run) on their first call.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

NAMESPACE = "stochlap"
LIBRARY = torch.library.Library(NAMESPACE, "DEF")


def define_op(
    schema: str,
    fake: Callable,
    cpu: Callable | None = None,
    backward: Callable | None = None,
    setup_context: Callable | None = None,
) -> Callable[[Callable], Callable]:
    """Decorator: define ``stochlap::<schema>`` (e.g. ``"normalize_rows(Tensor crow, Tensor
    val) -> Tensor"``) with the decorated function, returned as is, as its kernel for every
    device, ``cpu`` (optional) in its place for CPU tensors and ``fake`` as its shape-only
    kernel; ``backward`` and ``setup_context``, when given, are its autograd formula
    (``torch.library.register_autograd``)."""

    def register(kernel: Callable) -> Callable:
        name = schema.split("(", 1)[0]
        qualified = f"{NAMESPACE}::{name}"
        LIBRARY.define(schema)
        LIBRARY.impl(name, kernel, "CompositeExplicitAutograd")
        if cpu is not None:
            LIBRARY.impl(name, cpu, "CPU")
        torch.library.register_fake(qualified, fake, lib=LIBRARY)
        if backward is not None:
            torch.library.register_autograd(
                qualified, backward, setup_context=setup_context, lib=LIBRARY
            )
        return kernel

    return register
