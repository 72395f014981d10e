"""stochlap_torch: multiscale analysis of triangle meshes with the stochastic mesh Laplacian.

The subpackages follow the data flow (``docs/ARCHITECTURE.md``)::

    mesh -> operators -> diffusion -> saliency -> features, interest -> nn -> learning
         (sparse, _kernels underneath)                        baselines, evaluation -> viz -> cli

The names below are the public API; each is defined once, in the subpackage that owns it.
"""

from ._common.version import __version__
from .diffusion import (
    MemoryBudgetError,
    MultiscaleRepresentation,
    differentiable_multiscale,
    estimate_memory,
    multiscale_representation,
    partitioned_multiscale,
)
from .features import multiscale_features
from .interest import interest_points
from .learning import (
    MeshCache,
    MeshFeatureDataset,
    cached_features,
    cached_operators,
    collate_meshes,
)
from .mesh import (
    Mesh,
    MeshBatch,
    MeshError,
    bundled_mesh_path,
    from_trimesh,
    load_mesh,
    save_ply,
    to_trimesh,
    unique_edges,
    validate_mesh,
    vertex_normals,
)
from .nn import InterestPointHead, MultiscaleFeatures, MultiscaleSaliency, StochasticLaplacian
from .operators import mesh_operators, scale_invariance, stochastic_laplacian
from .saliency import VARIANTS, mesh_saliency, saliency_from_differences, variant_saliency

#: Same as :func:`mesh_saliency`, the one entry point from a mesh to a saliency.
saliency = mesh_saliency


__all__ = [
    "VARIANTS",
    "InterestPointHead",
    "MemoryBudgetError",
    "Mesh",
    "MeshBatch",
    "MeshCache",
    "MeshError",
    "MeshFeatureDataset",
    "MultiscaleFeatures",
    "MultiscaleRepresentation",
    "MultiscaleSaliency",
    "StochasticLaplacian",
    "__version__",
    "bundled_mesh_path",
    "cached_features",
    "cached_operators",
    "collate_meshes",
    "differentiable_multiscale",
    "estimate_memory",
    "from_trimesh",
    "interest_points",
    "load_mesh",
    "mesh_operators",
    "mesh_saliency",
    "multiscale_features",
    "multiscale_representation",
    "partitioned_multiscale",
    "saliency",
    "saliency_from_differences",
    "save_ply",
    "scale_invariance",
    "stochastic_laplacian",
    "to_trimesh",
    "unique_edges",
    "validate_mesh",
    "variant_saliency",
    "vertex_normals",
]
