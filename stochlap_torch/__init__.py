"""stochlap_torch: multiscale analysis of triangle meshes with the stochastic mesh Laplacian.

The subpackages follow the data flow (``docs/ARCHITECTURE.md``)::

    mesh -> diffusion (the paper's method) / robust (the robust variant) -> saliency_maps
         -> features, interest -> nn -> learning -> baselines, evaluation -> viz -> cli

The public API is the table below, written once: each name is defined in the module it names
and imported from there on first use (PEP 562), so that ``import stochlap_torch.cli`` (the
``stochlap`` command, whose ``--help`` must not load torch) stays cheap.
"""

from __future__ import annotations

from ._common.version import __version__

#: Public name -> the module that defines it (and its name there, when it differs).
_EXPORTS: dict[str, tuple[str, str] | str] = {
    # Errors
    "StochlapError": "._common.errors",
    "ParameterError": "._common.errors",
    "UnsupportedInputError": "._common.errors",
    "FileFormatError": "._common.errors",
    "MissingDependencyError": "._common.errors",
    "CacheError": "._common.errors",
    "DistributedError": "._common.errors",
    "MeshError": ".mesh",
    "MemoryBudgetError": ".diffusion",
    # Meshes
    "Mesh": ".mesh",
    "MeshBatch": ".mesh",
    "bundled_mesh_path": ".mesh",
    "from_trimesh": ".mesh",
    "load_mesh": ".mesh",
    "save_ply": ".mesh",
    "to_trimesh": ".mesh",
    "unique_edges": ".mesh",
    "validate_mesh": ".mesh",
    "vertex_normals": ".mesh",
    # Each method's options
    "PaperParams": ".params",
    "PaperFeatureParams": ".params",
    "RobustParams": ".params",
    # The paper's method
    "MultiscaleRepresentation": ".diffusion",
    "differentiable_multiscale": ".diffusion",
    "estimate_memory": ".diffusion",
    "multiscale_representation": ".diffusion",
    "partitioned_multiscale": ".diffusion",
    "mesh_operators": ".operators",
    "scale_invariance": ".operators",
    "stochastic_laplacian": ".operators",
    # The robust variant
    "RobustRepresentation": ".robust",
    "RobustStructure": ".robust",
    "robust_structure": ".robust",
    # Saliency, features, interest points
    "VARIANTS": ".saliency_maps",
    "saliency": (".saliency_maps", "mesh_saliency"),
    "mesh_saliency": ".saliency_maps",
    "saliency_from_differences": ".saliency_maps",
    "multiscale_features": ".features",
    "feature_channel_names": ".features",
    "interest_points": ".interest",
    # Layers
    "InterestPointHead": ".nn",
    "MultiscaleFeatures": ".nn",
    "MultiscaleSaliency": ".nn",
    "RobustMultiscale": ".nn",
    "StochasticLaplacian": ".nn",
    # Training data
    "MeshCache": ".learning",
    "MeshFeatureDataset": ".learning",
    "StochasticFeatures": ".learning",
    "cached_features": ".learning",
    "cached_operators": ".learning",
    "cached_structure": ".learning.cache",
    "collate_meshes": ".learning",
    "load_features": ".learning",
    "warmup": "._warmup",
}

__all__ = ["__version__", *sorted(_EXPORTS)]


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    module, attribute = (
        _EXPORTS[name] if isinstance(_EXPORTS[name], tuple) else (_EXPORTS[name], name)
    )
    value = getattr(import_module(module, __name__), attribute)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted({*__all__, "__doc__", "__file__", "__name__", "__path__", "__version__"})
