"""From a mesh to the operators the diffusion steps run on: the paper's (:mod:`.paper`) and
those of the mesh Laplacians of :mod:`.laplacians`, each a :class:`MeshOperators`. Exports
every module's ``__all__``."""

from . import laplacians, paper
from .laplacians import *  # noqa: F403
from .paper import *  # noqa: F403

__all__ = [name for module in (laplacians, paper) for name in module.__all__]
