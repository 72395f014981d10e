"""Compile every CPU kernel ahead of time, so that no first call pays for it.

numba compiles the kernels on first use and caches them on disk (:mod:`stochlap_torch.
_kernels.jit`). :func:`warmup` runs every path on a small mesh in both dtypes (the paper's
streamed and stepped runs, the robust variant, the gradient path, the baselines' kernels);
``stochlap warmup`` calls it, once after installing or in a container's build step.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable

import torch

logger = logging.getLogger(__name__)


def _sphere(subdivisions: int, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """An ellipsoid with a bump, ``10 * 4**subdivisions + 2`` vertices."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions)
    vertices = torch.tensor(mesh.vertices) * torch.tensor([1.0, 0.8, 0.6])
    vertices = vertices + 0.05 * torch.sin(5.0 * vertices[:, [1, 2, 0]])
    return vertices.to(dtype), torch.tensor(mesh.faces)


def _gradient(mesh: tuple[torch.Tensor, torch.Tensor]) -> None:
    """The paper's features with a backward pass (the constant-operator gradient path)."""
    from .features import multiscale_features

    points = mesh[0].clone().requires_grad_(True)
    multiscale_features(points, mesh[1], variant="paper", num_scales=3).sum().backward()


def _paths(dtype: torch.dtype) -> list[tuple[str, Callable[[], object]]]:
    from . import _kernels
    from .baselines import lee_saliency
    from .diffusion import multiscale_representation
    from .features import multiscale_features
    from .params import RobustParams

    numpy_dtype = torch.empty(0, dtype=dtype).numpy().dtype
    small = _sphere(3, dtype)  # 642 vertices
    large = _sphere(5, dtype)  # 10242: above the kernels' one-thread limits, a real pyramid
    robust = RobustParams(min_vertices=200)
    return [
        ("streamed steps", lambda: multiscale_representation(*large, 3)),
        ("whole steps", lambda: multiscale_representation(*small, 3, return_operators=True)),
        ("gradient path", lambda: _gradient(small)),
        ("robust variant", lambda: multiscale_features(*large, robust=robust)),
        ("buffers", lambda: _kernels.prefaulted_zeros((5 << 20,), numpy_dtype, threads=2)),
        ("Lee et al. baseline", lambda: lee_saliency(*small)),
    ]


def warmup(
    dtypes=(torch.float64, torch.float32), report: Callable[[str], None] | None = None
) -> float:
    """Compile (or load from the disk cache) every kernel the library uses, for the vertex
    ``dtypes``; ``report`` gets a line per path done (default: a log line at INFO). Returns
    the seconds it took."""
    report = report or logger.info
    start = time.perf_counter()
    # Without the first compile's notice, which asks the user to run this very function.
    quiet = os.environ.get("STOCHLAP_QUIET")
    os.environ["STOCHLAP_QUIET"] = "1"
    try:
        for dtype in dtypes:
            for name, run in _paths(dtype):
                tic = time.perf_counter()
                run()
                report(f"{name} ({str(dtype)[6:]}): {time.perf_counter() - tic:.1f} s")
    finally:
        if quiet is None:
            del os.environ["STOCHLAP_QUIET"]
        else:
            os.environ["STOCHLAP_QUIET"] = quiet
    return time.perf_counter() - start
