"""Meshes: the containers, input checks, files, geometry and vertex orders.

This is the bottom of the data flow: everything else takes a mesh validated here. Each module
lists its public names in its ``__all__``; this package exports them all.
"""

from . import container, geometry, io, ordering, validation
from .container import *  # noqa: F403
from .geometry import *  # noqa: F403
from .io import *  # noqa: F403
from .ordering import *  # noqa: F403
from .validation import *  # noqa: F403

__all__ = [
    name for module in (container, geometry, io, ordering, validation) for name in module.__all__
]
