"""Shared pieces of the benchmarks: paths, thread pinning, meshes and the timed functions.

Import this before torch when threads must be pinned through the environment (OpenMP, MKL and
OpenBLAS read it once, at load time); :func:`pin_threads` then fixes torch's and numba's pools.
"""

from __future__ import annotations

import logging
import os
import platform
import re
import sys
from contextlib import contextmanager
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
REPO = BENCH_DIR.parent
MESHES_DIR = REPO.parent / "shared" / "meshes"

if str(REPO) not in sys.path:  # a plain checkout works without `pip install -e .`
    sys.path.insert(0, str(REPO))

#: Environment variables that size the thread pools of OpenMP, MKL, OpenBLAS and numba.
THREAD_ENV = (
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "NUMBA_NUM_THREADS",
)

#: Vertex counts of the shared meshes used here (from ``../shared/meshes/SOURCES.md``), so
#: that cases can be filtered by size without loading them.
KNOWN_VERTICES = {
    "spot.obj": 2930,
    "cow.obj": 2903,
    "fertility.off": 4494,
    "fandisk.off": 7229,
    "horse_10k.obj": 9926,
    "horse.off": 19851,
    "squirrel.off": 9995,
    "foot.off": 10010,
    "camel.off": 9770,
    "gargoyle.off": 10002,
    "dinosaur.obj": 14000,
    "maxplanck.obj": 13502,
    "bunny.obj": 35947,
    "gargoyle_50k.off": 50002,
    "gargoyle_loop1_200k.ply": 200002,
    "armadillo_loop2_692k.ply": 691858,
}

#: The library's per-scale debug message (logged by ``stochlap_torch.diffusion.engine``).
_ENTRIES_MESSAGE = re.compile(r"scale (\d+)/(\d+): ([0-9.eE+-]+) entries per row")


def default_threads() -> int:
    """``$STOCHLAP_BENCH_THREADS``, else every logical core."""
    return int(os.environ.get("STOCHLAP_BENCH_THREADS", os.cpu_count() or 1))


def thread_env(threads: int) -> dict[str, str]:
    """The environment variables of :data:`THREAD_ENV`, all set to ``threads``."""
    return {name: str(threads) for name in THREAD_ENV}


def pin_threads(threads: int) -> None:
    """Pin torch's intra-op pool and numba's pool to ``threads`` (env vars for the rest)."""
    for name, value in thread_env(threads).items():
        os.environ.setdefault(name, value)
    import torch

    torch.set_num_threads(threads)
    try:
        import numba

        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    except ImportError:  # pragma: no cover - numba is a dependency of the library
        pass


def mesh_file(name: str) -> Path | None:
    """``../shared/meshes/<name>`` if it exists (the bundled ``spot.obj`` as a fallback)."""
    path = MESHES_DIR / name
    if path.is_file():
        return path
    if name == "spot.obj":
        from stochlap_torch.mesh import bundled_mesh_path

        return bundled_mesh_path("spot")
    return None


def icosphere_vertices(subdivisions: int) -> int:
    """Vertices of ``trimesh.creation.icosphere(subdivisions)``: ``10 * 4^s + 2``."""
    return 10 * 4**subdivisions + 2


def mesh_vertices(spec: str) -> int | None:
    """Vertex count of a mesh spec without loading it (``None`` if unknown)."""
    kind, _, value = spec.partition(":")
    if kind == "icosphere":
        return icosphere_vertices(int(value))
    return KNOWN_VERTICES.get(value)


def load(spec: str):
    """``(vertices, faces)`` float64 / int64 torch tensors for a mesh spec.

    Specs: ``file:<name in ../shared/meshes>`` (``file:spot.obj`` falls back to the copy
    bundled with the library) or ``icosphere:<subdivisions>``.

    Raises:
        FileNotFoundError: the file is not in ``../shared/meshes``.
    """
    import torch

    kind, _, value = spec.partition(":")
    if kind == "icosphere":
        import trimesh

        sphere = trimesh.creation.icosphere(subdivisions=int(value))
        vertices = torch.from_numpy(sphere.vertices.astype("float64", copy=True))
        faces = torch.from_numpy(sphere.faces.astype("int64", copy=True))
        return vertices, faces
    if kind == "file":
        path = mesh_file(value)
        if path is None:
            raise FileNotFoundError(f"{value} not found in {MESHES_DIR}")
        from stochlap_torch import load_mesh

        mesh = load_mesh(path)
        return mesh.vertices, mesh.faces
    raise ValueError(f"unknown mesh spec {spec!r}")


@contextmanager
def background_load(count: int):
    """``count`` busy-looping Python processes for the duration (a shared server, other
    DataLoader workers).

    Started by the measured process itself, so that they are in its session: Linux's
    autogroup scheduling (on by default on desktop and many server kernels) shares the CPU
    fairly between *sessions* first, and busy processes of another session would leave the
    measured one a full core's share whatever they do (a single-threaded baseline then shows
    no slow-down at all, as the first contention runs of ``run.py`` did).
    """
    import subprocess
    import time

    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(count)]
    try:
        if busy:
            time.sleep(0.5)  # let them reach the scheduler before the case starts
        yield
    finally:
        for process in busy:
            process.kill()
            process.wait()


@contextmanager
def entries_per_row_log():
    """Collect the library's per-scale ``entries per row`` debug messages.

    Yields a dict ``{k: mean entries per row of F^(k)}``, filled for ``k = 2..K`` while the
    context is open. The library exposes these numbers only as a DEBUG log line of
    ``stochlap_torch.diffusion.engine``, caught here on its parent logger
    ``stochlap_torch.diffusion``; an empty dict means the message changed.
    """
    found: dict[int, float] = {}

    class _Handler(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            match = _ENTRIES_MESSAGE.search(record.getMessage())
            if match:
                found[int(match.group(1))] = float(match.group(3))

    logger = logging.getLogger("stochlap_torch.diffusion")
    handler, level, propagate = _Handler(logging.DEBUG), logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(logging.DEBUG)
    logger.propagate = False
    try:
        yield found
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


def run_library(vertices, faces, num_scales, backend="numba", max_memory=None):
    """The library's Algorithms 1 and 2: ``(MultiscaleRepresentation, saliency (V,))``."""
    from stochlap_torch import multiscale_representation

    result = multiscale_representation(
        vertices, faces, num_scales=num_scales, backend=backend, max_memory=max_memory
    )
    return result, result.saliency()


def first_call_function(path: str | None, vertices, faces, num_scales, backend="numba"):
    """The call a first-call case times: the paper's saliency (``path=None``) or one of
    :data:`cases.FIRST_CALL_PATHS` (the mesh's vertices cast to the path's dtype)."""
    import torch

    import stochlap_torch as sl

    if path is None:
        return lambda: run_library(vertices, faces, num_scales, backend)
    what, _, dtype_name = path.rpartition(", ")
    points = vertices.to(getattr(torch, dtype_name))

    def features_backward():
        moving = points.clone().requires_grad_(True)
        sl.multiscale_features(moving, faces, variant="paper").sum().backward()

    calls = {
        "paper saliency": lambda: sl.saliency(points, faces, num_scales, variant="paper"),
        "return_operators=True": lambda: sl.multiscale_representation(
            points, faces, num_scales, return_operators=True
        ),
        "paper features + backward": features_backward,
        "robust saliency": lambda: sl.saliency(points, faces, variant="robust"),
        "robust features": lambda: sl.multiscale_features(points, faces, variant="robust"),
    }
    return calls[what]


def library_entries(result, vertices, faces, num_scales, logged, fallback_max_vertices=200_000):
    """``({k: mean entries per row of F^(k)}, source)`` for a library run.

    From ``MultiscaleRepresentation.entries`` when the library has it, else from its DEBUG log
    line (``logged``, see :func:`entries_per_row_log`; ``F^(1)`` is then ``1 + 2E/V``), else
    recomputed with ``return_operators=True`` on meshes of at most ``fallback_max_vertices``.
    """
    num_vertices = int(vertices.shape[0])
    counts = getattr(result, "entries", None)
    if counts is not None:
        per_row = {k + 1: int(n) / num_vertices for k, n in enumerate(counts.tolist())}
        return per_row, "MultiscaleRepresentation.entries"
    if logged:
        first = 1.0 + 2.0 * edge_count(faces, num_vertices) / num_vertices
        return {1: first, **logged}, "debug log"
    if num_vertices <= fallback_max_vertices:
        return library_entries_per_row(vertices, faces, num_scales), "return_operators=True"
    return {}, "unavailable"


def edge_count(faces, num_vertices: int) -> int:
    """Unique undirected edges of a mesh (``stochlap_torch.mesh.unique_edges``)."""
    from stochlap_torch.mesh import unique_edges

    return int(unique_edges(faces, num_vertices).shape[0])


def library_memory_estimate(vertices, faces, num_scales, threshold=1e-3) -> int | None:
    """What the library's memory check counts for a run like the benchmark's (outputs and
    scratch rows of a streamed run, on top of the operators it builds), or None if its API
    differs."""
    try:
        from stochlap_torch.diffusion import streamed_memory
        from stochlap_torch.operators import mesh_operators

        return int(streamed_memory(mesh_operators(vertices, faces), num_scales))
    except Exception:  # an API in flux: the report shows "-"
        return None


def run_scipy(vertices, faces, num_scales):
    """The scipy.sparse baseline (NumPy inputs): :class:`~scipy_baseline.ScipyMultiscale`."""
    from scipy_baseline import multiscale_scipy

    return multiscale_scipy(vertices, faces, num_scales)


def library_entries_per_row(vertices, faces, num_scales) -> dict[int, float]:
    """``{k: entries per row of F^(k)}`` for ``k = 1..K`` from ``return_operators=True``.

    Holds all ``K`` operators at once: only for small meshes.
    """
    from stochlap_torch import multiscale_representation

    result = multiscale_representation(vertices, faces, num_scales, return_operators=True)
    rows = vertices.shape[0]
    return {k + 1: op.values().shape[0] / rows for k, op in enumerate(result.operators)}


def _baseline(name: str):
    """A function of ``stochlap_torch.baselines`` (written by another engineer)."""
    try:
        import stochlap_torch.baselines as baselines
    except ImportError as exc:
        raise RuntimeError(f"stochlap_torch.baselines is not importable: {exc}") from exc
    if not hasattr(baselines, name):
        raise RuntimeError(f"stochlap_torch.baselines has no {name}() yet")
    return getattr(baselines, name)


def run_dense_eigh(vertices, faces, num_eigenpairs=128):
    """Every eigenpair of the cotangent Laplacian by dense ``torch.linalg.eigh`` (``O(V^3)``);
    the first ``num_eigenpairs`` are kept. Returns the eigenvalues."""
    eigenpairs = _baseline("laplacian_eigenpairs")
    return eigenpairs(vertices, faces, num_eigenpairs, method="dense").values


def run_eigsh_hks(vertices, faces, num_eigenpairs=128, num_times=16):
    """``num_eigenpairs`` eigenpairs by scipy ``eigsh`` (shift-invert) and the heat kernel
    signature at ``num_times`` times: ``(V, T)``."""
    hks = _baseline("heat_kernel_signature")
    return hks(vertices, faces, num_eigenpairs=num_eigenpairs, num_times=num_times, method="sparse")


def cpu_model() -> str:
    """The processor's model name (``/proc/cpuinfo``), for the reports' machine headers."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()
