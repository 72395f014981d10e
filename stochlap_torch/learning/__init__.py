"""For training scripts: the on-disk cache, feature datasets and the PyG transform."""

from .batching import MeshFeatureBatch, MeshSample, collate_meshes
from .cache import CacheWarning, MeshCache, cached_features, cached_operators, content_key
from .datasets import MESH_SUFFIXES, MeshFeatureDataset, find_mesh_files

__all__ = [
    "MESH_SUFFIXES",
    "CacheWarning",
    "MeshCache",
    "MeshFeatureBatch",
    "MeshFeatureDataset",
    "MeshSample",
    "StochasticFeatures",
    "cached_features",
    "cached_operators",
    "collate_meshes",
    "content_key",
    "find_mesh_files",
]


def __getattr__(name: str):
    if name == "StochasticFeatures":  # needs torch_geometric: imported on first use
        from .pyg import StochasticFeatures

        return StochasticFeatures
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
