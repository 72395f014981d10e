"""From a mesh to the operators the diffusion steps run on: the paper's (:mod:`.paper`) and
those of the mesh Laplacians of :mod:`.laplacians`, each a :class:`MeshOperators`."""

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
