"""stochlap_torch: multiscale analysis of triangle meshes with the stochastic mesh Laplacian.

The subpackages follow the data flow (``docs/ARCHITECTURE.md``)::

    mesh -> operators -> diffusion -> saliency_maps -> features, interest -> nn -> learning
         (sparse, _kernels underneath)             baselines, evaluation -> viz -> cli

The names below are the public API; each is defined once, in the subpackage that owns it, and
imported from there on first use (PEP 562), so that ``import stochlap_torch.cli`` (the
``stochlap`` command, whose ``--help`` must not load torch) stays cheap.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from ._common.version import __version__

#: Public name -> (the submodule that defines it, its name there).
_EXPORTS: dict[str, tuple[str, str]] = {
    name: (module, name)
    for module, names in {
        ".diffusion": (
            "MemoryBudgetError",
            "MultiscaleRepresentation",
            "PaperParams",
            "RobustParams",
            "differentiable_multiscale",
            "estimate_memory",
            "multiscale_representation",
            "partitioned_multiscale",
        ),
        ".diffusion.robust": ("RobustStructure",),
        ".diffusion.robust_api": ("robust_structure",),
        ".features": ("multiscale_features",),
        ".interest": ("interest_points",),
        ".learning": (
            "MeshCache",
            "MeshFeatureDataset",
            "StochasticFeatures",
            "cached_features",
            "cached_operators",
            "collate_meshes",
        ),
        ".learning.cache": ("cached_structure",),
        ".mesh": (
            "Mesh",
            "MeshBatch",
            "MeshError",
            "bundled_mesh_path",
            "from_trimesh",
            "load_mesh",
            "save_ply",
            "to_trimesh",
            "unique_edges",
            "validate_mesh",
            "vertex_normals",
        ),
        ".nn": (
            "InterestPointHead",
            "MultiscaleFeatures",
            "MultiscaleSaliency",
            "StochasticLaplacian",
        ),
        ".operators": ("mesh_operators", "scale_invariance", "stochastic_laplacian"),
        ".saliency_maps": (
            "VARIANTS",
            "mesh_saliency",
            "saliency_from_differences",
            "variant_saliency",
        ),
        ".warmup": ("warmup",),
        "._common.errors": (
            "ParameterError",
            "StochlapError",
            "UnsupportedInputError",
        ),
    }.items()
    for name in names
}
#: ``saliency`` is :func:`mesh_saliency`, the one entry point from a mesh to a saliency.
_EXPORTS["saliency"] = (".saliency_maps", "mesh_saliency")

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
    "PaperParams",
    "ParameterError",
    "RobustParams",
    "RobustStructure",
    "StochasticFeatures",
    "StochasticLaplacian",
    "StochlapError",
    "UnsupportedInputError",
    "__version__",
    "bundled_mesh_path",
    "cached_features",
    "cached_operators",
    "cached_structure",
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
    "robust_structure",
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
    "warmup",
]


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    module, attribute = _EXPORTS[name]
    value = getattr(importlib.import_module(module, __name__), attribute)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})


if TYPE_CHECKING:  # static analysers and IDEs see the names
    from ._common.errors import ParameterError, StochlapError, UnsupportedInputError
    from .diffusion import (
        MemoryBudgetError,
        MultiscaleRepresentation,
        PaperParams,
        RobustParams,
        differentiable_multiscale,
        estimate_memory,
        multiscale_representation,
        partitioned_multiscale,
    )
    from .diffusion.robust import RobustStructure
    from .diffusion.robust_api import robust_structure
    from .features import multiscale_features
    from .interest import interest_points
    from .learning import (
        MeshCache,
        MeshFeatureDataset,
        StochasticFeatures,
        cached_features,
        cached_operators,
        collate_meshes,
    )
    from .learning.cache import cached_structure
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
    from .saliency_maps import VARIANTS, mesh_saliency, saliency_from_differences, variant_saliency
    from .warmup import warmup

    saliency = mesh_saliency
