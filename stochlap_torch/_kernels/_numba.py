"""numba, imported once: the kernels are compiled only where it can be imported."""

from __future__ import annotations

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; kept for exotic platforms
    numba = None

__all__ = ["numba", "numba_available"]


def numba_available() -> bool:
    """Whether the compiled kernels can run here (numba importable)."""
    return numba is not None
