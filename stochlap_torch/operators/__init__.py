"""From a mesh to the operators the diffusion steps run on.

* :mod:`.paper`: the paper's ``Lhat = |D - W|`` with ``W = 1/|Pi-Pj|^2`` and ``alpha`` (Eq. 9).
* :mod:`.laplacians`: the uniform, cotangent and intrinsic Delaunay Laplacians with lumped
  masses, and the same steps run on ``|L|`` (paper Fig. 11).

Every construction returns a :class:`MeshOperators`; the steps never know which one it was.
"""

from .laplacians import (
    LAPLACIANS,
    MASS_TYPES,
    MeshLaplacian,
    cotangent_laplacian,
    face_cotangents,
    intrinsic_laplacian,
    laplacian_operators,
    lumped_mass,
    mesh_laplacian,
    uniform_laplacian,
)
from .paper import (
    MeshOperators,
    abs_laplacian,
    alpha_from_edges,
    mesh_operators,
    operators_of_valid_mesh,
    scale_invariance,
    stochastic_laplacian,
)

__all__ = [
    "LAPLACIANS",
    "MASS_TYPES",
    "MeshLaplacian",
    "MeshOperators",
    "abs_laplacian",
    "alpha_from_edges",
    "cotangent_laplacian",
    "face_cotangents",
    "intrinsic_laplacian",
    "laplacian_operators",
    "lumped_mass",
    "mesh_laplacian",
    "mesh_operators",
    "operators_of_valid_mesh",
    "scale_invariance",
    "stochastic_laplacian",
    "uniform_laplacian",
]
