"""stochlap_torch: multiscale analysis of triangle meshes with the stochastic mesh Laplacian.

Data flow, one module each: :mod:`.mesh` (container, checks), :mod:`.io` (files) and
:mod:`.batch` (packed batches) -> :mod:`.operators` (``Lhat``, ``alpha``) over
:mod:`.sparse_ops` (custom CSR ops) and :mod:`.kernels` (fused CPU kernel) ->
:mod:`.diffusion` (Algorithm 1) -> :mod:`.saliency_map` (Algorithm 2) -> :mod:`.interest`
(Sec. 4.5) -> :mod:`.modules` (``nn.Module`` layers) -> :mod:`.render` and :mod:`.cli`.
Baselines and metrics live in :mod:`.baselines` and :mod:`.evaluation`.
"""

from .autodiff import differentiable_multiscale
from .batch import MeshBatch
from .cache import MeshCache, cached_features, cached_operators
from .data import MeshFeatureDataset, collate_meshes, from_trimesh, to_trimesh
from .diffusion import (
    MemoryBudgetError,
    MultiscaleRepresentation,
    estimate_memory,
    multiscale_representation,
)
from .distributed import partitioned_multiscale
from .features import MultiscaleFeatures, multiscale_features, vertex_normals
from .interest import interest_points
from .io import bundled_mesh_path, load_mesh, save_ply
from .mesh import Mesh, MeshError, validate_mesh
from .modules import InterestPointHead, MultiscaleSaliency, StochasticLaplacian
from .operators import mesh_operators, scale_invariance, stochastic_laplacian, unique_edges
from .saliency_map import mesh_saliency, saliency_from_differences
from .variants import VARIANTS, variant_saliency

#: Same as :func:`mesh_saliency`; the short name reads well in user code.
saliency = mesh_saliency

__version__ = "0.1.0"

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
