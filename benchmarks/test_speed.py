"""pytest-benchmark cases: library (numba kernel) vs torch ops vs the scipy baseline, and the
spectral baselines.

    pytest benchmarks/ --benchmark-only [--benchmark-group-by=group]

Threads are pinned to ``$STOCHLAP_BENCH_THREADS`` (default: every logical core) for torch,
numba, OpenMP, MKL and OpenBLAS (see ``conftest.py``); every case runs one warm-up round
(numba compiles or loads its cache there) before the timed rounds. Meshes come from
``../shared/meshes`` and the cases that need one are skipped when it is absent. These tests
are outside ``tests/`` (the configured testpath), so the normal test run never collects them.
For per-case peak memory and the full report use ``python benchmarks/run.py``.
"""

from __future__ import annotations

from functools import cache

import pytest

pytest.importorskip("pytest_benchmark")

import benchlib

NUM_SCALES = 8
THREADS = benchlib.default_threads()  # conftest.py has set the environment to match


@pytest.fixture(scope="module", autouse=True)
def _pinned_threads():
    benchlib.pin_threads(THREADS)


@cache
def _load(spec: str):
    vertices, faces = benchlib.load(spec)
    return vertices, faces, vertices.numpy(), faces.numpy()


def _mesh(name: str):
    if benchlib.mesh_file(name) is None:
        pytest.skip(f"{name} not found in {benchlib.MESHES_DIR} (expected ../shared/meshes)")
    return _load(f"file:{name}")


def _run(benchmark, function, rounds: int, **info) -> None:
    benchmark.extra_info.update(threads=THREADS, **info)
    benchmark.pedantic(function, rounds=rounds, iterations=1, warmup_rounds=1)


@pytest.mark.parametrize("method", ["numba", "torch", "scipy"])
@pytest.mark.parametrize(("name", "rounds"), [("spot.obj", 5), ("gargoyle_50k.off", 3)])
def test_multiscale(benchmark, name, rounds, method):
    """Algorithms 1 and 2 (positions and saliency) at K = 8."""
    vertices, faces, vertices_np, faces_np = _mesh(name)
    benchmark.group = f"multiscale K={NUM_SCALES}: {name}"
    if method == "scipy":

        def function():
            return benchlib.run_scipy(vertices_np, faces_np, NUM_SCALES)
    else:

        def function():
            return benchlib.run_library(vertices, faces, NUM_SCALES, backend=method)

    _run(
        benchmark,
        function,
        rounds,
        vertices=int(vertices.shape[0]),
        method=method,
        num_scales=NUM_SCALES,
    )


def test_eigsh_heat_kernel_signature_10k(benchmark):
    """128 eigenpairs by scipy eigsh (shift-invert) and the HKS at 16 times, 10k vertices."""
    vertices, faces, _, _ = _mesh("gargoyle.off")
    benchmark.group = "spectral"
    _run(
        benchmark,
        lambda: benchlib.run_eigsh_hks(vertices, faces, 128, 16),
        3,
        vertices=int(vertices.shape[0]),
    )


@pytest.mark.parametrize("name", ["spot.obj", "fertility.off"])
def test_dense_eigh(benchmark, name):
    """Every eigenpair by dense torch.linalg.eigh (O(V^3)), 2.9k and 4.5k vertices."""
    vertices, faces, _, _ = _mesh(name)
    benchmark.group = "spectral"
    _run(
        benchmark,
        lambda: benchlib.run_dense_eigh(vertices, faces, 128),
        3,
        vertices=int(vertices.shape[0]),
    )
