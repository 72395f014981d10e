"""For training scripts: feature files, feature datasets, the on-disk cache and the PyG
transform.

Each name is imported from its module on first use (PEP 562): ``stochlap features`` reads
:mod:`.feature_files` without loading torch, and :class:`StochasticFeatures` needs
torch_geometric.
"""

from __future__ import annotations

#: Public name -> the module of this package that defines it.
_EXPORTS = {
    "MESH_SUFFIXES": ".feature_files",
    "CacheWarning": ".cache",
    "FeatureFile": ".feature_files",
    "MeshCache": ".cache",
    "MeshFeatureBatch": ".batching",
    "MeshFeatureDataset": ".datasets",
    "MeshSample": ".batching",
    "StochasticFeatures": ".pyg",
    "cached_features": ".cache",
    "cached_operators": ".cache",
    "collate_meshes": ".batching",
    "content_key": ".cache",
    "find_mesh_files": ".datasets",
    "load_features": ".feature_files",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(_EXPORTS[name], __name__), name)
    globals()[name] = value  # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted({*__all__, "__doc__", "__file__", "__name__", "__path__"})
