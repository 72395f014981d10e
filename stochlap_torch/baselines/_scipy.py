"""Lazy import of scipy, the optional dependency of the baselines and the evaluation."""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["require_scipy"]

_HINT = 'install it with: pip install "stochlap_torch[baselines]"'


def require_scipy(submodule: str) -> ModuleType:
    """``scipy.<submodule>``, or an ``ImportError`` that says how to install scipy.

    Args:
        submodule: e.g. ``"sparse"``, ``"sparse.linalg"``, ``"spatial"``.
    """
    try:
        return importlib.import_module(f"scipy.{submodule}")
    except ImportError as exc:
        raise ImportError(
            f"this function needs scipy (scipy.{submodule}), which is not installed; {_HINT}"
        ) from exc
