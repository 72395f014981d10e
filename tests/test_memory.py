"""The memory estimate samples rows; it must predict the real fill and refuse over budget."""

from __future__ import annotations

import pytest
import reference as ref
import torch
from reference import noisy_sphere

import stochlap_torch as sl
from stochlap_torch.diffusion import MemoryBudgetError, estimate_memory
from stochlap_torch.diffusion import memory as diffusion
from stochlap_torch.operators import mesh_operators
from stochlap_torch.sparse import CSR, select_rows


def _sphere() -> tuple[torch.Tensor, torch.Tensor]:
    return noisy_sphere().tensors(torch.float64)


def test_select_rows_matches_dense_rows() -> None:
    vertices, faces = _sphere()
    matrix = CSR.from_sparse_csr(sl.stochastic_laplacian(vertices, faces))
    rows = torch.tensor([5, 0, 17, 5])
    picked = select_rows(matrix, rows)
    torch.testing.assert_close(picked.to_dense(), matrix.to_dense()[rows])


@pytest.mark.parametrize("threshold", [1e-3, 1e-2])
def test_sampled_fill_predicts_the_real_fill(threshold: float) -> None:
    vertices, faces = _sphere()
    ops = mesh_operators(vertices, faces)
    result = sl.multiscale_representation(vertices, faces, 6, threshold)
    actual = (result.entries.double() / vertices.shape[0]).tolist()
    every_row = estimate_memory(ops, 6, threshold, sample_rows=vertices.shape[0])
    assert every_row.entries_per_row == pytest.approx(actual, rel=1e-12)
    sampled = estimate_memory(ops, 6, threshold, sample_rows=40)
    assert sampled.complete
    assert sampled.entries_per_row == pytest.approx(actual, rel=0.2)


def test_estimate_grows_with_kept_operators() -> None:
    vertices, faces = _sphere()
    ops = mesh_operators(vertices, faces)
    two = estimate_memory(ops, 6, 1e-3).peak_bytes
    all_six = estimate_memory(ops, 6, 1e-3, return_operators=True).peak_bytes
    assert all_six > two > 0


def test_budget_stops_sampling_early_and_refuses() -> None:
    vertices, faces = _sphere()
    ops = mesh_operators(vertices, faces)
    partial = estimate_memory(ops, 30, 1e-12, budget=1 << 12)
    assert not partial.complete and len(partial.entries_per_row) < 30
    with pytest.raises(MemoryBudgetError, match="entries per row"):
        sl.multiscale_representation(
            vertices, faces, 30, 1e-12, return_operators=True, max_memory=1 << 12
        )


def test_streamed_run_holds_no_operator() -> None:
    """Without operators, rows go through every step block by block: a threshold that fills
    ``F`` (rows reach most of the mesh) needs no more than the outputs, whereas keeping the
    operators is refused under the same budget."""
    vertices, faces = ref.icosphere(3).tensors()
    ops = mesh_operators(vertices, faces)
    budget = diffusion.streamed_memory(ops, 16) + (1 << 20)
    assert estimate_memory(ops, 16, 1e-12, return_operators=True).peak_bytes > 4 * budget
    streamed = sl.multiscale_representation(vertices, faces, 16, 1e-12, max_memory=budget)
    assert streamed.entries[-1] > vertices.shape[0] ** 2 / 2  # F^(16) is mostly full
    with pytest.raises(MemoryBudgetError):
        sl.multiscale_representation(
            vertices, faces, 16, 1e-12, return_operators=True, max_memory=budget
        )


def test_torch_backend_never_runs_the_numba_kernel(monkeypatch) -> None:
    """``backend="torch"`` steps the memory sample with the torch ops too (nothing compiled)."""
    from stochlap_torch import _kernels as kernels

    def refuse(*args, **kwargs):
        raise AssertionError("the numba kernel ran")

    monkeypatch.setattr(kernels, "fused_step", refuse)
    monkeypatch.setattr(kernels, "stream_steps", refuse)
    vertices, faces = noisy_sphere().tensors(torch.float64)
    sl.multiscale_representation(vertices, faces, 4, backend="torch")
    with pytest.raises(AssertionError, match="numba kernel ran"):
        sl.multiscale_representation(vertices, faces, 4, backend="numba")


def test_differentiable_runs_are_budgeted_with_their_graph() -> None:
    """The autograd graph of a differentiable run holds every step and its product pattern:
    the estimate counts them (a 50k-vertex run at K = 12 and a 1e-12 threshold passed 10 GiB
    unchecked before), and the run refuses a budget it would exceed."""
    vertices, faces = noisy_sphere().tensors(torch.float64)
    ops = mesh_operators(vertices, faces)
    plain = estimate_memory(ops, 5, 1e-3)
    graph = estimate_memory(ops, 5, 1e-3, differentiable=True)
    assert graph.peak_bytes > 2 * plain.peak_bytes
    with pytest.raises(MemoryBudgetError):
        sl.differentiable_multiscale(
            vertices.clone().requires_grad_(True), faces, 5, max_memory=graph.peak_bytes // 2
        )
    sl.differentiable_multiscale(
        vertices.clone().requires_grad_(True), faces, 5, max_memory=graph.peak_bytes * 2
    )


@pytest.mark.parametrize(
    "options, name",
    [
        ({"threshold": 0.0}, "threshold"),  # segfaulted: every entry kept
        ({"threshold": -1.0}, "threshold"),  # aborted
        ({"threshold": float("nan")}, "threshold"),  # ZeroDivisionError
        ({"num_scales": 10**6}, "num_scales"),  # ran for hours
        ({"sample_rows": 0}, "sample_rows"),  # ZeroDivisionError
        ({"budget": -5}, "budget"),
    ],
    ids=lambda value: str(value),
)
def test_estimate_memory_checks_its_inputs(options, name):
    """The public ``sl.estimate_memory`` checks its options like every other entry point."""
    vertices, faces = noisy_sphere().tensors(torch.float64)
    arguments = {"num_scales": 4, "threshold": 1e-3, **options}
    with pytest.raises(sl.ParameterError, match=name):
        sl.estimate_memory(sl.mesh_operators(vertices, faces), **arguments)
    with pytest.raises(sl.ParameterError, match="MeshOperators"):
        sl.estimate_memory((vertices, faces), 4, 1e-3)
