"""Where users run the library: forked and spawned workers, several threads, the caller's
thread settings.

The compiled kernels run on plain Python threads (``stochlap_torch._kernels.run_workers``),
never on numba's threading layer (GNU OpenMP here), so a process that used the library can
fork, a forked child can use it, and no process-wide thread setting changes.
"""

from __future__ import annotations

import pickle
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest
import torch
import trimesh
from reference import icosphere as ref_icosphere
from reference import noisy_sphere

import stochlap_torch as sl

TESTS = Path(__file__).parent
LARGE_ROWS = 9000  # above the kernels' one-thread limits (SERIAL_ROWS = 8192)


def _run(script: str, timeout: float = 240) -> str:
    """Run ``script`` in a fresh interpreter (tests/ on the path); return its stdout."""
    result = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=TESTS,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result.stdout


def _large_sphere_script() -> str:
    return """
        import torch, trimesh
        sphere = trimesh.creation.icosphere(5)  # 10242 vertices: above LARGE_ROWS
        vertices = torch.tensor(sphere.vertices) * torch.tensor([1.0, 1.3, 0.8])
        faces = torch.tensor(sphere.faces)
    """


def test_library_calls_change_no_thread_setting() -> None:
    """torch's thread count stays what the caller set, and numba's threading layer (whose
    OpenMP start raised torch's count) is never started."""
    out = _run(
        _large_sphere_script()
        + """
        torch.set_num_threads(1)
        import stochlap_torch as sl
        sl.saliency(vertices, faces)
        sl.multiscale_representation(vertices, faces, 4, return_operators=True)
        from numba.np.ufunc import parallel
        print(torch.get_num_threads(), parallel._is_initialized)
        """
    )
    assert out.split() == ["1", "False"]


_DATALOADER_SCRIPT = """
import sys
import torch
import trimesh
from torch.utils.data import DataLoader, Dataset

import stochlap_torch as sl


class Shapes(Dataset):
    \"\"\"Ellipsoids of 10242 vertices (above the kernels' one-thread limits); features computed
    in the worker, per item.\"\"\"

    def __len__(self):
        return 2

    def __getitem__(self, index):
        sphere = trimesh.creation.icosphere(5)
        vertices = torch.tensor(sphere.vertices) * torch.tensor([1.0, 1.0 + 0.1 * index, 0.8])
        # No exact symmetry: the robust variant's decimation would break its ties by rounding.
        vertices = vertices + 0.003 * torch.sin(13.0 * vertices[:, [1, 2, 0]])
        faces = torch.tensor(sphere.faces)
        return sl.multiscale_features(vertices, faces, num_scales=4)


if __name__ == "__main__":
    data = Shapes()
    expected = [data[i] for i in range(len(data))]  # the parent uses the library first
    torch.zeros(10**6).add_(1)  # and torch's own thread pool
    for method in sys.argv[1:]:
        loader = DataLoader(data, batch_size=None, num_workers=2,
                            multiprocessing_context=method, timeout=200)
        got = list(loader)
        # Workers run torch on one thread (DataLoader sets it), the parent on its own count:
        # sums may be reordered, so the features agree to rounding, relative to their size.
        error = max(
            float((a - b).abs().max() / b.abs().max()) for a, b in zip(got, expected, strict=True)
        )
        print(method, len(got) == len(expected) and error < 1e-12)
"""

START_METHODS = ["fork", "spawn", "forkserver"]


def test_dataloader_workers_of_every_start_method_after_the_parent_used_the_library(
    tmp_path,
) -> None:
    """Features computed in ``DataLoader(num_workers=2)`` workers, for each start method in
    turn, after the parent computed some (GNU OpenMP, which numba used, aborts or hangs in a
    child forked after the parent ran parallel code). The one test of every start method:
    elsewhere workers are forked, the cheapest."""
    assert LARGE_ROWS <= 10242
    script = tmp_path / "loader.py"
    script.write_text(_DATALOADER_SCRIPT)
    result = subprocess.run(
        [sys.executable, str(script), *START_METHODS],
        capture_output=True,
        text=True,
        timeout=500,
        cwd=TESTS,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.split() == [word for m in START_METHODS for word in (m, "True")]


def _pyg_shape(index: int):
    """A small jittered ellipsoid as PyG ``Data`` (positions and faces only)."""
    from torch_geometric.data import Data

    sphere = ref_icosphere(2)
    pos = torch.from_numpy(sphere.vertices) * torch.tensor([1.0, 1.0 + 0.1 * index, 0.8])
    pos = pos + 0.01 * torch.sin(7.0 * pos[:, [1, 2, 0]])
    return Data(pos=pos, face=torch.from_numpy(sphere.faces).t().contiguous())


def test_pyg_transform_in_dataloader_workers_gives_the_in_process_features() -> None:
    """``StochasticFeatures`` as a PyG dataset's transform: forked workers compute what this
    process computes, and the transform survives pickling (how spawned and forkserver workers
    receive it; those start methods are tested above)."""
    pytest.importorskip("torch_geometric", reason="torch_geometric is not installed")
    from torch_geometric.data import Dataset
    from torch_geometric.loader import DataLoader

    class Shapes(Dataset):
        def __init__(self, transform=None):
            super().__init__(None, transform=transform)

        def len(self):
            return 4

        def get(self, index):
            return _pyg_shape(index)

    transform = sl.StochasticFeatures()
    data = Shapes(transform=transform)
    expected = [data[i].x for i in range(len(data))]  # this process uses the library first
    assert expected[0].shape[1] == len(transform.channel_names())
    loader = DataLoader(
        data, batch_size=1, num_workers=2, multiprocessing_context="fork", timeout=200
    )
    got = [batch.x for batch in loader]
    assert len(got) == len(expected)
    for a, b in zip(got, expected, strict=True):  # workers run torch on one thread: rounding
        assert a.shape == b.shape
        assert float((a - b).abs().max()) <= 1e-12 * float(b.abs().max())
    unpickled = pickle.loads(pickle.dumps(transform))
    assert torch.equal(unpickled(_pyg_shape(1)).x, expected[1])


def test_two_python_threads_at_once() -> None:
    """Two threads calling the library concurrently get what each gets alone."""
    meshes = [noisy_sphere(seed=s).tensors(torch.float64) for s in (0, 1)]
    expected = [sl.saliency(*mesh) for mesh in meshes]
    results: dict[int, torch.Tensor] = {}

    def run(index: int) -> None:
        for _ in range(3):
            results[index] = sl.saliency(*meshes[index])

    threads = [threading.Thread(target=run, args=(i,)) for i in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for index, values in enumerate(expected):
        assert torch.equal(results[index], values)


# --- the caller's thread count holds inside a call, and the kernels use it ---------------------


def test_a_call_keeps_the_callers_thread_count_and_its_kernels_use_it(monkeypatch) -> None:
    from stochlap_torch import _kernels

    calls = []
    real = _kernels.stream_steps

    def spy(lhat, alpha, threshold, moved, threads, *rest):
        calls.append((threads, torch.get_num_threads()))
        return real(lhat, alpha, threshold, moved, threads, *rest)

    monkeypatch.setattr(_kernels, "stream_steps", spy)
    vertices, faces = noisy_sphere().tensors()
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        sl.saliency(vertices, faces, variant="paper")
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert calls and all(call == (2, 2) for call in calls)


def test_robust_sparse_products_run_on_the_callers_threads(monkeypatch) -> None:
    """``torch.set_num_threads(2)`` before a call: the robust variant's sparse products run
    with 2 threads, and the count is 2 during and after the call (no library call changes it)."""
    seen = []
    real = torch.addmm

    def spy(*args, **kwargs):  # the Chebyshev recurrence's sparse products
        if args[1].layout == torch.sparse_csr:
            seen.append(torch.get_num_threads())
        return real(*args, **kwargs)

    mesh = sl.load_mesh(sl.bundled_mesh_path())
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        monkeypatch.setattr(torch, "addmm", spy)
        sl.multiscale_features(mesh.vertices, mesh.faces)
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert seen and set(seen) == {2}


def test_threaded_robust_builds_equal_serial_builds(monkeypatch) -> None:
    """Robust structures and features built in many threads at once equal serial ones.

    fast-simplification keeps the mesh being decimated in C++ globals, loaded and read back by
    separate calls; a thread switching in between built another mesh's pyramid (and the cache
    stored its wrong features). A short sleep between the calls widens that window so that
    unguarded threads meet in it every time.
    """
    import time

    from fast_simplification import _simplify

    first = sl.load_mesh(sl.bundled_mesh_path())
    sphere = trimesh.creation.icosphere(4)  # 2562 vertices: decimated once
    stretch = torch.tensor([1.0, 1.4, 0.7], dtype=torch.float64)
    second = sl.Mesh(torch.tensor(sphere.vertices) * stretch, torch.tensor(sphere.faces))
    meshes = [first, second]

    def sizes(structure) -> list[int]:
        return [level.num_vertices for level in structure.levels]

    expected = [sl.multiscale_features(m.vertices, m.faces) for m in meshes]
    levels = [sizes(sl.robust_structure(m.vertices, m.faces)) for m in meshes]
    assert all(len(built) > 1 for built in levels)  # decimation ran: the case under test
    simplify = _simplify.simplify

    def slow_simplify(*args):
        time.sleep(0.02)  # releases the GIL: another thread may load its mesh now
        return simplify(*args)

    monkeypatch.setattr(_simplify, "simplify", slow_simplify)
    results: dict[int, tuple] = {}

    def run(index: int) -> None:
        mesh = meshes[index % 2]
        structure = sl.robust_structure(mesh.vertices, mesh.faces)
        results[index] = (sizes(structure), sl.multiscale_features(mesh.vertices, mesh.faces))

    threads = [threading.Thread(target=run, args=(i,)) for i in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(results) == list(range(6))
    for index, (built, features) in results.items():
        assert built == levels[index % 2]
        assert torch.equal(features, expected[index % 2])
