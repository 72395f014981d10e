"""The fused numba kernel: chunking and buffer reuse must not change a single value."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from reference import noisy_sphere

import stochlap_torch as sl
from stochlap_torch import kernels
from stochlap_torch.operators import mesh_operators

pytestmark = pytest.mark.skipif(not kernels.available(), reason="numba is not installed")


def _steps(ops, points, num_steps: int, workspace) -> list[tuple[np.ndarray, ...]]:
    """Run ``num_steps`` kernel steps from F^(1); return copies of every step's outputs."""
    first = ops.stochastic_laplacian()
    crow, col, val = first.crow.numpy(), first.col.numpy(), first.val.numpy()
    lhat = [t.numpy() for t in (ops.lhat.crow, ops.lhat.col, ops.lhat.val)]
    outputs = []
    for _ in range(num_steps):
        crow, col, val, difference, moved = kernels.fused_step(
            crow, col, val, *lhat, ops.alpha.numpy(), 1e-3, points, 2, False, workspace
        )
        outputs.append(tuple(a.copy() for a in (crow, col, val, difference, moved)))
    return outputs


@pytest.mark.parametrize("capacity", [1, 100_000])
def test_workspace_reuse_and_growth_change_nothing(monkeypatch, capacity: int) -> None:
    vertices, faces = noisy_sphere().tensors(torch.float64)
    ops = mesh_operators(vertices, faces)
    monkeypatch.setattr(kernels, "CHUNK_PRODUCTS", 500)  # many chunks, grown buffers
    monkeypatch.setattr(kernels, "SERIAL_ENTRIES", 0)  # the parallel path
    fresh = _steps(ops, vertices.numpy(), 6, None)
    workspace = kernels.Workspace(vertices.shape[0], vertices.shape[0], np.float64, capacity)
    reused = _steps(ops, vertices.numpy(), 6, workspace)
    for a, b in zip(fresh, reused, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)


def test_streaming_run_equals_the_run_that_keeps_operators() -> None:
    """Without operators the loop streams through shared buffers; results must not differ."""
    vertices, faces = noisy_sphere().tensors(torch.float64)
    streamed = sl.multiscale_representation(vertices, faces, 8)
    kept = sl.multiscale_representation(vertices, faces, 8, return_operators=True)
    torch.testing.assert_close(streamed.positions, kept.positions, rtol=0, atol=1e-12)
    torch.testing.assert_close(streamed.differences, kept.differences, rtol=0, atol=1e-12)
    assert torch.equal(streamed.entries, kept.entries)
