"""Meshes: the containers, input checks, files, geometry and vertex orders (the bottom of the
data flow: everything else takes a mesh validated here). Exports every module's ``__all__``."""

from . import container, geometry, io, ordering, validation
from .container import *  # noqa: F403
from .geometry import *  # noqa: F403
from .io import *  # noqa: F403
from .ordering import *  # noqa: F403
from .validation import *  # noqa: F403

__all__ = [
    name for module in (container, geometry, io, ordering, validation) for name in module.__all__
]
