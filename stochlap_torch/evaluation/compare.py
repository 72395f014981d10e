"""The multiscale saliency side by side with eigendecomposition baselines on one mesh
(``stochlap compare``): :func:`compare_methods` runs each method, by default in a fresh
process of its own, and reports its time, its peak memory and how far its saliency and its
interest points agree with those of a reference method.

The methods, each a ``(V,)`` saliency:

* ``robust`` and ``stochastic``: this library's robust saliency and the paper's Algorithm 2;
* ``hks``: the heat kernel signature (Sun et al. 2009) at the middle of 16 log-spaced times,
  from 100 cotangent-Laplacian eigenpairs;
* ``spectral``: spectral filtering, the detail a low-pass onto the first
  ``SPECTRAL_EIGENVECTORS`` (64) eigenvectors removes (``|P - P_k|`` per vertex, Fig. 5);
* ``lee``: the mesh saliency of Lee et al. 2005;
* ``uniform``, ``cotangent``: Algorithm 2 with those Laplacians in place of the stochastic one.
"""

from __future__ import annotations

import gc
import math
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from .._common.errors import ParameterError
from ..baselines import spectral_reconstruction
from ..mesh import as_mesh_tensors
from .benchmark import detector_saliency
from .constants import COMPARE_METHODS, DEFAULT_COMPARE_METHODS

#: Eigenvectors kept by the spectral low-pass filter of the ``spectral`` method.
SPECTRAL_EIGENVECTORS = 64
#: Two interest points agree when they lie within this fraction of the bounding-box diagonal.
AGREEMENT_RADIUS = 0.05


@dataclass(frozen=True)
class MethodRun:
    """One method of a :class:`Comparison`.

    Attributes:
        method: its name (:data:`~stochlap_torch.evaluation.COMPARE_METHODS`).
        seconds: wall time of its saliency on the mesh, after a warm-up call on the bundled
            spot when it ran in a process of its own.
        peak_bytes: memory its run added at its peak (the process's resident-set high-water
            mark minus the resident set before the run); ``None`` when not measured (run in
            this process, or no ``/proc`` to read it from).
        spearman: rank correlation of its saliency with the reference's, over the vertices
            faces use.
        shared_points: fraction of the reference's interest points with one of this method's
            within ``AGREEMENT_RADIUS`` (0.05) of the diagonal.
        saliency: ``(V,)`` float64 saliency.
        points: ``(N,)`` int64 interest points (non-maximum suppression, default radius).
    """

    method: str
    seconds: float
    peak_bytes: int | None
    spearman: float
    shared_points: float
    saliency: Tensor
    points: Tensor


@dataclass(frozen=True)
class Comparison:
    """What :func:`compare_methods` measured on one mesh; ``runs`` in the order asked."""

    num_vertices: int
    reference: str
    runs: dict[str, MethodRun]

    def table(self) -> str:
        """The runs as a plain-text table, one row per method."""
        head = ("method", "seconds", "peak MB", f"Spearman vs {self.reference}", "shared points")
        rows = [head]
        for run in self.runs.values():
            peak = "-" if run.peak_bytes is None else f"{run.peak_bytes / 2**20:.0f}"
            shared = f"{run.shared_points:.2f}"
            rows.append((run.method, f"{run.seconds:.2f}", peak, f"{run.spearman:.3f}", shared))
        widths = [max(len(row[i]) for row in rows) for i in range(len(head))]
        lines = [
            "  ".join(cell.rjust(w) for cell, w in zip(row, widths, strict=True)) for row in rows
        ]
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The figures as plain JSON-ready values (no per-vertex arrays)."""
        runs = {
            name: {
                "seconds": run.seconds,
                "peak_bytes": run.peak_bytes,
                "spearman": run.spearman,
                "shared_points": run.shared_points,
                "num_points": int(run.points.numel()),
            }
            for name, run in self.runs.items()
        }
        return {"num_vertices": self.num_vertices, "reference": self.reference, "runs": runs}


def method_saliency(method: str, vertices: Tensor, faces: Tensor) -> Tensor:
    """The ``(V,)`` saliency of one of :data:`~stochlap_torch.evaluation.COMPARE_METHODS`
    (module docstring) of a ``(V, 3)`` float, ``(F, 3)`` int64 mesh."""
    if method == "spectral":
        used = int(torch.unique(faces).numel())
        smooth = spectral_reconstruction(vertices, faces, [min(SPECTRAL_EIGENVECTORS, used)])
        return (vertices - smooth[0]).norm(dim=1)
    return detector_saliency(method, vertices, faces)


def compare_methods(
    vertices,
    faces,
    methods: Sequence[str] = DEFAULT_COMPARE_METHODS,
    *,
    reference: str | None = None,
    isolate: bool = True,
    progress: Callable[[str], None] | None = None,
) -> Comparison:
    """Run each method on the mesh and compare it with the reference.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float (computed in float64) and ``(F, 3)``
            integer tensors or arrays.
        methods: names from :data:`~stochlap_torch.evaluation.COMPARE_METHODS`, each once.
        reference: the method the others are compared with (default: the first of
            ``methods``); it must be one of them.
        isolate: run each method in a fresh process (spawned), warmed up on the bundled spot,
            so that its time and peak memory are its own; ``False`` runs them here, one after
            the other, and measures no memory.
        progress: called with one line of text before each method (``None``: no reports).

    Returns:
        :class:`Comparison`.

    Raises:
        ParameterError: an unknown or repeated method, or a reference not among them.
        MeshError: a bad mesh.
    """
    methods = tuple(methods)
    unknown = [m for m in methods if m not in COMPARE_METHODS]
    if unknown or not methods or len(set(methods)) != len(methods):
        raise ParameterError(
            f"methods must be distinct names from {', '.join(COMPARE_METHODS)}; got "
            f"{', '.join(methods) or 'none'}"
        )
    reference = methods[0] if reference is None else reference
    if reference not in methods:
        raise ParameterError(f"reference {reference!r} is not among the methods")
    if not isinstance(isolate, bool):
        raise ParameterError(f"isolate must be True or False, got {isolate!r}")
    vertices, faces = as_mesh_tensors(vertices, faces)
    vertices = vertices.detach().double()
    measured = {}
    for number, method in enumerate(methods, start=1):
        if progress is not None:
            progress(f"{method} ({number} of {len(methods)})")
        if isolate:
            measured[method] = _in_fresh_process(method, vertices, faces)
        else:
            measured[method] = _measure(method, vertices, faces, warm_up=False)
    return _compared(vertices, faces, reference, measured)


def _compared(vertices: Tensor, faces: Tensor, reference: str, measured: dict) -> Comparison:
    """The agreement of every measured ``(saliency, seconds, peak)`` with the reference's."""
    from ..interest import interest_points

    used = torch.unique(faces)
    extent = vertices[used].amax(dim=0) - vertices[used].amin(dim=0)
    reach = AGREEMENT_RADIUS * float(extent.norm())
    points = {m: interest_points(s, vertices, faces) for m, (s, _, _) in measured.items()}
    truth, anchor = points[reference], measured[reference][0][used]
    runs = {}
    for method, (saliency, seconds, peak) in measured.items():
        found = points[method]
        if truth.numel() and found.numel():
            near = torch.cdist(vertices[truth], vertices[found]).amin(dim=1) <= reach
            shared = float(near.double().mean())
        else:
            shared = float(truth.numel() == found.numel())
        correlation = _spearman(saliency[used], anchor)
        runs[method] = MethodRun(method, seconds, peak, correlation, shared, saliency, found)
    return Comparison(int(vertices.shape[0]), reference, runs)


def _spearman(a: Tensor, b: Tensor) -> float:
    """Spearman's rank correlation (ties ranked by their mean); NaN when one is constant."""
    from scipy.stats import spearmanr

    if bool(a.amax() == a.amin()) or bool(b.amax() == b.amin()):
        return math.nan
    return float(spearmanr(a.numpy(), b.numpy()).statistic)


def _measure(method: str, vertices: Tensor, faces: Tensor, warm_up: bool):
    """``(saliency, seconds, peak bytes or None)`` of one method here, after a warm-up call on
    the bundled spot (JIT and first-use costs out of the timing) when asked."""
    if warm_up:
        from ..mesh import bundled_mesh_path, load_mesh

        spot = load_mesh(bundled_mesh_path("spot"))
        method_saliency(method, spot.vertices, spot.faces)
    gc.collect()
    before = _status_bytes("VmRSS")
    reset = warm_up and before is not None and _reset_peak()
    start = time.perf_counter()
    saliency = method_saliency(method, vertices, faces).detach().double()
    seconds = time.perf_counter() - start
    peak = _status_bytes("VmHWM") if reset else None
    return saliency, seconds, None if peak is None else max(peak - before, 0)


def _in_fresh_process(method: str, vertices: Tensor, faces: Tensor):
    """:func:`_measure` in a spawned process with this process's torch thread count."""
    import multiprocessing
    from concurrent.futures.process import BrokenProcessPool

    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        job = pool.submit(_child, method, vertices, faces, torch.get_num_threads())
        try:
            return job.result()
        except BrokenProcessPool as exc:
            raise RuntimeError(
                f"the process running {method} ended abruptly (out of memory?); "
                "isolate=False runs the methods in this process"
            ) from exc


def _child(method: str, vertices: Tensor, faces: Tensor, threads: int):
    """The body of :func:`_in_fresh_process` (a spawned process owns its thread settings)."""
    torch.set_num_threads(threads)
    return _measure(method, vertices, faces, warm_up=True)


def _status_bytes(key: str) -> int | None:
    """A ``kB`` line of ``/proc/self/status`` in bytes (``None`` where there is none)."""
    if not sys.platform.startswith("linux"):
        return None
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) * 1024
    return None


def _reset_peak() -> bool:
    """Set this process's resident-set high-water mark to its resident set now (Linux)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True
