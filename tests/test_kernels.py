"""The fused numba kernel: output layout, overflow rounds and buffer reuse change no value."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from reference import noisy_sphere

import stochlap_torch as sl
from stochlap_torch import _kernels as kernels
from stochlap_torch._kernels import buffers as kernel_buffers
from stochlap_torch.operators import mesh_operators

pytestmark = pytest.mark.skipif(not kernels.numba_available(), reason="numba is not installed")


def _steps(ops, points, num_steps: int, workspace, growth: float) -> list[tuple[np.ndarray, ...]]:
    """Run ``num_steps`` kernel steps from F^(1); return each step's packed outputs."""
    first = ops.stochastic_laplacian()
    rows = kernels.Rows.from_csr(first.crow.numpy(), first.col.numpy(), first.val.numpy())
    lhat = kernels.split_lhat(*(t.numpy() for t in (ops.lhat.crow, ops.lhat.col, ops.lhat.val)))
    outputs = []
    for _ in range(num_steps):
        rows, difference, moved = kernels.fused_step(
            rows, lhat, ops.alpha.numpy(), 1e-3, points, 2, False, workspace, growth
        )
        outputs.append((*rows.to_csr(), difference, moved))
    return outputs


@pytest.fixture
def sphere_ops():
    vertices, faces = noisy_sphere().tensors(torch.float64)
    return mesh_operators(vertices, faces), vertices.numpy()


@pytest.mark.parametrize("growth", [1e-6, 0.5, 1.0])
@pytest.mark.parametrize("reuse", [False, True])
def test_overflow_rounds_and_buffer_reuse_change_nothing(monkeypatch, sphere_ops, growth, reuse):
    """Regions too small for every row (growth 1e-6: all rows overflow into later rounds),
    too small for some, and buffers shared between steps give exactly the roomy result."""
    ops, points = sphere_ops
    monkeypatch.setattr(kernels.steps, "SERIAL_ENTRIES", 0)  # the parallel path
    monkeypatch.setattr(kernels.steps, "PARTS_PER_THREAD", 7)
    roomy = _steps(ops, points, 6, None, 1000.0)
    workspace = kernel_buffers.Workspace(points.shape[0], np.float64, 1) if reuse else None
    tight = _steps(ops, points, 6, workspace, growth)
    for a, b in zip(roomy, tight, strict=True):
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x, y)


def test_overflow_is_exercised(monkeypatch, sphere_ops, caplog) -> None:
    """The tight setting above really sends rows to later rounds (the test is not vacuous)."""
    ops, points = sphere_ops
    monkeypatch.setattr(kernels.steps, "SERIAL_ENTRIES", 0)
    with caplog.at_level("DEBUG", logger="stochlap_torch._kernels.steps"):
        _steps(ops, points, 2, None, 1e-6)
    assert any("overflowed" in record.message for record in caplog.records)


def test_rows_pack_to_the_same_csr(sphere_ops) -> None:
    """``Rows.from_csr`` then ``to_csr`` is the identity; costs are the next step's products."""
    ops, points = sphere_ops
    first = ops.stochastic_laplacian()
    crow, col, val = (t.numpy() for t in (first.crow, first.col, first.val))
    packed = kernels.Rows.from_csr(crow, col, val).to_csr()
    for x, y in zip(packed, (crow, col, val), strict=True):
        np.testing.assert_array_equal(x, y)
    lhat = kernels.split_lhat(*(t.numpy() for t in (ops.lhat.crow, ops.lhat.col, ops.lhat.val)))
    rows, _, _ = kernels.fused_step(
        kernels.Rows.from_csr(crow, col, val), lhat, ops.alpha.numpy(), 1e-3, points, 1
    )
    l_lengths = np.diff(ops.lhat.crow.numpy())
    next_crow, next_col, _ = rows.to_csr()
    expected = np.add.reduceat(l_lengths[next_col], next_crow[:-1])
    np.testing.assert_array_equal(rows.costs, expected)


def test_streaming_run_equals_the_run_that_keeps_operators() -> None:
    """Without operators the loop streams through shared buffers; results must not differ."""
    vertices, faces = noisy_sphere().tensors(torch.float64)
    streamed = sl.multiscale_representation(vertices, faces, 8)
    kept = sl.multiscale_representation(vertices, faces, 8, return_operators=True)
    torch.testing.assert_close(streamed.positions, kept.positions, rtol=0, atol=1e-12)
    torch.testing.assert_close(streamed.differences, kept.differences, rtol=0, atol=1e-12)
    torch.testing.assert_close(streamed.coefficients, kept.coefficients, rtol=0, atol=1e-12)
    assert torch.equal(streamed.entries, kept.entries)


def test_progress_is_reported_per_scale_and_changes_nothing() -> None:
    """With a callback a streamed run goes to the kernel in ``K - 1`` slices and reports
    ``(k, K)`` for every scale; the results are those of a run without one, bit for bit."""
    vertices, faces = noisy_sphere().tensors(torch.float64)
    calls = []
    reported = sl.multiscale_representation(
        vertices, faces, 8, progress=lambda k, n: calls.append((k, n))
    )
    silent = sl.multiscale_representation(vertices, faces, 8)
    assert calls == [(k, 8) for k in range(1, 9)]
    assert torch.equal(reported.positions, silent.positions)
    assert torch.equal(reported.differences, silent.differences)
    assert torch.equal(reported.entries, silent.entries)


def test_pooled_workspaces_are_reused_and_change_nothing(monkeypatch) -> None:
    """Runs borrow their buffers from ``kernel_buffers.WORKSPACES``: a run after runs on other
    meshes (other sizes) equals a run with a fresh pool, and the buffers really are reused."""
    small, large = (
        noisy_sphere(seed=3).tensors(torch.float64),
        noisy_sphere().tensors(torch.float64),
    )
    monkeypatch.setattr(kernels, "WORKSPACES", kernel_buffers.WorkspacePool(0))
    fresh = sl.multiscale_representation(*small, 6)

    pool = kernel_buffers.WorkspacePool(2**30)
    monkeypatch.setattr(kernels, "WORKSPACES", pool)
    idle = []
    for mesh in (large, small, large, small):
        pooled = sl.multiscale_representation(*mesh, 6)
        idle.append(list(pool._idle))
    assert all(len(kept) == 1 and kept[0] is idle[0][0] for kept in idle)
    torch.testing.assert_close(pooled.positions, fresh.positions, rtol=0, atol=0)
    torch.testing.assert_close(pooled.differences, fresh.differences, rtol=0, atol=0)


def test_pool_lends_a_workspace_to_one_run_at_a_time_and_keeps_within_its_bound() -> None:
    pool = kernel_buffers.WorkspacePool(2**20)
    with (
        pool.borrow(10, np.float64, 100, np.int32) as a,
        pool.borrow(10, np.float64, 100, np.int32) as b,
    ):
        assert a is not b
    assert pool.idle_bytes == a.nbytes + b.nbytes <= 2**20
    with pool.borrow(10, np.float32, 100, np.int32) as c:
        assert c is not a and c is not b  # other dtypes: a new workspace
    with pool.borrow(10, np.float64, 10**6, np.int32) as d:
        assert d in (a, b) and d.outputs[0][1].shape[0] >= 10**6  # grown to the capacity
    assert pool.idle_bytes <= 2**20  # the grown one (12 MB) was dropped, the oldest first
    none_kept = kernel_buffers.WorkspacePool(0)
    with none_kept.borrow(10, np.float64, 100, np.int32):
        pass
    assert none_kept.idle_bytes == 0


def test_lhat_is_split_once_per_streamed_run_and_never_kept(monkeypatch) -> None:
    """A streamed run (the default) splits ``Lhat`` once; a whole step splits its own (under
    1% of the step), so no split outlives its call."""
    calls = []
    split = kernels.split_lhat

    def counting(*arrays):
        calls.append(arrays[0].shape[0])
        return split(*arrays)

    monkeypatch.setattr(kernels, "split_lhat", counting)
    mesh = noisy_sphere().tensors(torch.float64)
    sl.multiscale_representation(*mesh, 6)
    assert len(calls) == 1
    # Op by op (operators kept): the estimate's five sample steps and the run's five.
    sl.multiscale_representation(*mesh, 6, return_operators=True)
    assert len(calls) == 1 + 2 * 5


def test_lhat_modified_in_place_is_split_again() -> None:
    """Nothing is kept between calls: an in-place change of ``Lhat`` is seen."""
    vertices, faces = noisy_sphere().tensors(torch.float64)
    ops = mesh_operators(vertices, faces)
    first = ops.stochastic_laplacian()
    lhat = (ops.lhat.crow, ops.lhat.col, ops.lhat.val)
    args = (ops.alpha, 1e-3, vertices)
    before = torch.ops.stochlap.diffusion_step(first.crow, first.col, first.val, *lhat, *args)
    ops.lhat.val.mul_(torch.linspace(1.0, 2.0, ops.lhat.val.shape[0], dtype=torch.float64))
    after = torch.ops.stochlap.diffusion_step(first.crow, first.col, first.val, *lhat, *args)
    fresh = torch.ops.stochlap.diffusion_step(
        first.crow, first.col, first.val, *(t.clone() for t in lhat), *args
    )
    assert not torch.equal(before[4], after[4])
    for x, y in zip(after, fresh, strict=True):
        assert torch.equal(x, y)


@pytest.mark.parametrize("channels", [0, 1, 3, 5])
def test_moved_points_are_f_times_points_for_any_channel_count(sphere_ops, channels) -> None:
    """``P^(k) = F^(k) P`` for any number of channels (three take a path of their own), and
    the same values channel by channel whatever the count."""
    ops, points = sphere_ops
    rng = np.random.default_rng(0)
    extra = rng.standard_normal((points.shape[0], 2))
    many = np.ascontiguousarray(np.concatenate([points, extra], axis=1)[:, :channels])
    first = ops.stochastic_laplacian()
    rows = kernels.Rows.from_csr(*(t.numpy() for t in (first.crow, first.col, first.val)))
    lhat = kernels.split_lhat(*(t.numpy() for t in (ops.lhat.crow, ops.lhat.col, ops.lhat.val)))
    rows, _, moved = kernels.fused_step(rows, lhat, ops.alpha.numpy(), 1e-3, many, 1)
    crow, col, val = rows.to_csr()
    dense = np.zeros((points.shape[0], points.shape[0]))
    dense[np.repeat(np.arange(points.shape[0]), np.diff(crow)), col] = val
    assert moved.shape == (points.shape[0], channels)
    np.testing.assert_allclose(moved, dense @ many, rtol=0, atol=1e-12)
    _, _, moved_five = kernels.fused_step(
        kernels.Rows.from_csr(*(t.numpy() for t in (first.crow, first.col, first.val))),
        lhat,
        ops.alpha.numpy(),
        1e-3,
        np.concatenate([points, extra], axis=1),
        1,
    )
    np.testing.assert_array_equal(moved, moved_five[:, :channels])


def test_first_rows_are_the_normalised_rows_of_lhat(sphere_ops) -> None:
    """``first_rows`` gives the rows of ``F^(1)`` (all, or picked ones in the given order) with
    the values of the torch op, in the asked index dtype."""
    ops, _ = sphere_ops
    lhat_csr = tuple(t.numpy() for t in (ops.lhat.crow, ops.lhat.col, ops.lhat.val))
    lhat = kernels.split_lhat(*lhat_csr)
    first = ops.stochastic_laplacian()
    every = kernels.first_rows(lhat, index=np.int32).to_csr()
    assert every[1].dtype == np.int32
    for x, y in zip(every, (first.crow, first.col, first.val), strict=True):
        np.testing.assert_array_equal(x, y.numpy())
    picked = np.array([5, 0, 17, 5], dtype=np.int64)
    some = kernels.first_rows(lhat, picked).to_csr()
    dense = first.to_dense().numpy()[picked]
    rebuilt = np.zeros_like(dense)
    rebuilt[np.repeat(np.arange(picked.shape[0]), np.diff(some[0])), some[1]] = some[2]
    np.testing.assert_array_equal(rebuilt, dense)


def test_balanced_parts_match_the_running_total_split() -> None:
    """Row ranges end where the running work first exceeds each ``p / parts`` of the total
    (the searchsorted reading), empty ranges dropped, the ranges covering every row."""
    rng = np.random.default_rng(1)
    for _ in range(300):
        work = rng.integers(0, 6, int(rng.integers(0, 40))) * (rng.random(1) < 0.9)
        parts = int(rng.integers(1, 50))
        first, last = kernels.steps._balanced_parts(work.astype(np.int64), parts)
        cumulative = np.cumsum(work)
        inner = (
            np.searchsorted(cumulative, cumulative[-1] * np.arange(1, parts) / parts, side="right")
            if work.size
            else np.zeros(0, np.int64)
        )
        bounds = np.unique(np.concatenate([[0], inner, [work.shape[0]]]))
        bounds = bounds if work.size else np.zeros(0, np.int64)
        np.testing.assert_array_equal(first, bounds[:-1])
        np.testing.assert_array_equal(last, bounds[1:])


@pytest.mark.parametrize("threshold", [1e-3, 0.3])
@pytest.mark.parametrize("extra", [0, 1, 2, 3])
def test_blocks_of_rows_match_the_torch_ops_for_any_row_count(extra, threshold) -> None:
    """Rows are computed in blocks of ``LANES``; with 162 + ``extra`` vertices the last block
    is full or holds 1 to 3 rows. Both backends agree (isolated vertices pad the count), also
    with a threshold so high that rows keep only their maximum."""
    vertices, faces = noisy_sphere().tensors(torch.float64)
    far = torch.arange(1, extra + 1, dtype=torch.float64)[:, None].expand(extra, 3) + 5.0
    vertices = torch.cat([vertices, far])
    results = [
        sl.multiscale_representation(vertices, faces, 7, threshold, backend=b, return_operators=r)
        for b, r in (("numba", False), ("numba", True), ("torch", True))
    ]
    for result in results[1:]:
        torch.testing.assert_close(results[0].positions, result.positions, rtol=0, atol=1e-12)
        torch.testing.assert_close(results[0].differences, result.differences, rtol=0, atol=1e-12)
        assert torch.equal(results[0].entries, result.entries)


def test_results_do_not_depend_on_threads_or_row_ranges(monkeypatch, sphere_ops) -> None:
    """A row's block is fixed by its index, so one thread, two threads and other row ranges
    give bit-identical steps."""
    ops, points = sphere_ops
    monkeypatch.setattr(kernels.steps, "SERIAL_ENTRIES", 0)
    first = ops.stochastic_laplacian()
    lhat = kernels.split_lhat(*(t.numpy() for t in (ops.lhat.crow, ops.lhat.col, ops.lhat.val)))
    results = []
    for threads, parts in ((1, 32), (2, 32), (2, 3), (2, 61)):
        monkeypatch.setattr(kernels.steps, "PARTS_PER_THREAD", parts)
        rows = kernels.Rows.from_csr(*(t.numpy() for t in (first.crow, first.col, first.val)))
        for _ in range(4):
            rows, difference, moved = kernels.fused_step(
                rows, lhat, ops.alpha.numpy(), 1e-3, points, threads, True
            )
        results.append((*rows.to_csr(), difference, moved))
    for other in results[1:]:
        for x, y in zip(results[0], other, strict=True):
            np.testing.assert_array_equal(x, y)


_BOUNDS_SCRIPT = """
import numpy as np, torch
from reference import noisy_sphere
from stochlap_torch import _kernels as kernels
from stochlap_torch._kernels import buffers as kernel_buffers
from stochlap_torch.operators import mesh_operators
kernels.steps.SERIAL_ENTRIES = 0
for extra in range(4):
    vertices, faces = noisy_sphere().tensors(torch.float64)
    far = torch.arange(1, extra + 1, dtype=torch.float64)[:, None].expand(extra, 3) + 5.0
    ops = mesh_operators(torch.cat([vertices, far]), faces)
    lhat = kernels.split_lhat(*(t.numpy() for t in (ops.lhat.crow, ops.lhat.col,
                                                            ops.lhat.val)))
    points = ops.alpha.new_ones(ops.num_vertices, 3).numpy()
    for threshold, growth, threads in ((1e-3, 1e-6, 2), (0.3, 1.0, 1), (1e-3, None, 2)):
        rows = kernels.first_rows(lhat)
        for _ in range(5):
            rows, _, _ = kernels.fused_step(rows, lhat, ops.alpha.numpy(), threshold, points,
                                            threads, True, None, growth)
        n = ops.num_vertices
        differences, positions = np.zeros((6, n)), np.zeros((6, n, 3))
        kernels.stream_steps(lhat, ops.alpha.numpy(), threshold, points, threads, (0, n),
                             differences, positions)
print("ok")
"""


def test_kernel_stays_in_bounds(tmp_path) -> None:
    """The kernel compiled with numba's bounds checks (a fresh cache) raises nothing on partial
    blocks, rows that keep only their maximum and overflowing output regions."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=str(tmp_path))
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).parent), env.get("PYTHONPATH", "")])
    done = subprocess.run(
        [sys.executable, "-c", _BOUNDS_SCRIPT], env=env, capture_output=True, text=True, timeout=600
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.strip().endswith("ok")


def _first_and_split(ops):
    csr = tuple(t.numpy() for t in (ops.lhat.crow, ops.lhat.col, ops.lhat.val))
    lhat = kernels.split_lhat(*csr)
    return kernels.first_rows(lhat), lhat


@pytest.mark.parametrize("threads", [1, 2])
def test_streamed_rows_equal_the_step_by_step_kernel(monkeypatch, sphere_ops, threads) -> None:
    """Rows taken through every step block by block give exactly the results of whole steps
    (the same blocks, the same arithmetic), in any slices of whole blocks."""
    monkeypatch.setattr(kernels.steps, "SERIAL_ENTRIES", 0)
    monkeypatch.setattr(kernels.steps, "SERIAL_ROWS", 0)
    ops, points = sphere_ops
    first, lhat = _first_and_split(ops)
    alpha, num_scales, n = ops.alpha.numpy(), 6, first.num_rows
    rows, stepped, entries = first, [], []
    for _ in range(num_scales - 1):
        rows, difference, moved = kernels.fused_step(
            rows, lhat, alpha, 1e-3, points, threads, False
        )
        stepped.append((difference, moved))
        entries.append(rows.nnz)
    for slices in ([0, n], [0, 40, 120, n], [0, 4, 8, n]):
        differences = np.zeros((num_scales, n))
        positions = np.zeros((num_scales, n, 3))
        counted = sum(
            kernels.stream_steps(lhat, alpha, 1e-3, points, threads, rows, differences, positions)
            for rows in itertools.pairwise(slices)
        )
        np.testing.assert_array_equal(counted, entries)
        for k, (difference, moved) in enumerate(stepped, start=1):
            np.testing.assert_array_equal(differences[k], difference)
            np.testing.assert_array_equal(positions[k], moved)


def test_streamed_rows_must_be_whole_blocks_of_the_matrix(sphere_ops) -> None:
    ops, points = sphere_ops
    _, lhat = _first_and_split(ops)
    n = ops.num_vertices
    outputs = np.zeros((3, n)), np.zeros((3, n, 3))
    with pytest.raises(ValueError, match="multiple of 4"):
        kernels.stream_steps(lhat, ops.alpha.numpy(), 1e-3, points, 1, (2, 10), *outputs)
    with pytest.raises(ValueError, match="row range"):
        kernels.stream_steps(lhat, ops.alpha.numpy(), 1e-3, points, 1, (0, n + 4), *outputs)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int32, np.uint8])
def test_prefaulted_zeros_are_zeros_on_one_thread_or_several(monkeypatch, dtype) -> None:
    """Large arrays are filled by several threads in runs of pages; the result is the same."""
    monkeypatch.setattr(kernel_buffers, "PARALLEL_FILL_BYTES", 1)
    for threads in (1, 2):
        for shape in ((3, 1_000_003), (5,), (0,)):
            array = kernel_buffers.prefaulted_zeros(shape, dtype, threads)
            assert array.shape == shape and array.dtype == dtype
            assert not array.any()


def test_float32_rows_with_a_float64_lhat_compute_in_float32(sphere_ops) -> None:
    """The accumulator takes the rows' dtype; ``Lhat`` weights of another dtype are cast into
    it (the vector operation needs one dtype)."""
    ops, points = sphere_ops
    first, lhat = _first_and_split(ops)
    single = kernels.Rows(first.starts, first.counts, first.col, first.val.astype(np.float32))
    lhat32 = kernels.SplitLhat(
        *(
            a.astype(np.float32) if a.dtype == np.float64 else a
            for a in (lhat.diagonal, lhat.w_crow, lhat.w_col, lhat.w_val, lhat.row_sums)
        )
    )
    alpha32 = ops.alpha.numpy().astype(np.float32)
    mixed = kernels.fused_step(single, lhat, alpha32, 1e-3, points.astype(np.float32), 1)
    same = kernels.fused_step(single, lhat32, alpha32, 1e-3, points.astype(np.float32), 1)
    assert mixed[1].dtype == np.float32
    np.testing.assert_allclose(mixed[1], same[1], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(mixed[2], same[2], rtol=1e-5, atol=1e-6)
