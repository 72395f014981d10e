"""Inside a case's own process: load the mesh, warm up, time the runs, read the peak memory.

``python benchmarks/run.py --child spec.json`` ends up in :func:`child_main`. The parent
(``measure.py``) has already set the thread environment (OpenMP, MKL, OpenBLAS, numba) before
this process imported anything; :func:`benchlib.pin_threads` then sizes torch's and numba's
pools here, in the benchmark process itself, never through a library call. Only the standard
library is imported at module level, so that the first-call case can time ``import torch``.
"""

from __future__ import annotations

import gc
import json
import math
import os
import re
import statistics
import sys
import threading
import time
import traceback
from pathlib import Path

import benchlib
from cases import NUM_EIGENPAIRS, NUM_TIMES, mesh_name

#: Exit status of a child whose memory watchdog fired.
MEMORY_EXIT = 86
#: Timed runs of a multiscale case go on until they add up to this many seconds (a 10k-vertex
#: run takes 25 ms: five of them sample a tenth of a second of a host whose speed drifts).
MIN_TIMED_SECONDS = 1.0
#: ... but no further than this many runs.
MAX_TIMED_RUNS = 200


def log(message: str) -> None:
    """One line of progress on stderr (the parent streams it with a ``|`` prefix)."""
    sys.stderr.write(message + "\n")
    sys.stderr.flush()


# --------------------------------------------------------------------------------------------
# Memory


def _status_kib(key: str) -> int | None:
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    match = re.search(rf"^{key}:\s+(\d+) kB", text, re.MULTILINE)
    return int(match.group(1)) if match else None


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (``VmHWM``) of this process; False if unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def peak_rss_bytes() -> int:
    """This process's RSS high-water mark (``VmHWM``; ``ru_maxrss`` where there is none)."""
    hwm = _status_kib("VmHWM")
    if hwm is not None:
        return hwm * 1024
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def rss_bytes() -> int:
    """This process's resident set size now."""
    import psutil

    return psutil.Process().memory_info().rss


def start_memory_watchdog(min_free: int) -> None:
    """Exit with :data:`MEMORY_EXIT` if the machine's available memory drops below
    ``min_free`` bytes (the machine is shared: never push it into the OOM killer)."""
    import psutil

    def watch():
        while True:
            available = psutil.virtual_memory().available
            if available < min_free:
                log(
                    f"memory watchdog: only {available / 2**30:.2f} GiB available "
                    f"(< {min_free / 2**30:.2f} GiB); peak RSS "
                    f"{peak_rss_bytes() / 2**30:.2f} GiB; aborting this case"
                )
                os._exit(MEMORY_EXIT)
            time.sleep(0.2)

    threading.Thread(target=watch, daemon=True).start()


# --------------------------------------------------------------------------------------------
# Time and threads


def planned_repeats(seconds: float, repeats: int, budget: float, min_seconds: float = 0.0) -> int:
    """Timed runs of ``seconds`` each: ``repeats``, more (at most :data:`MAX_TIMED_RUNS`) to
    fill ``min_seconds``, fewer (at least one) when they would take more than ``budget``."""
    seconds = max(seconds, 1e-9)
    wanted = max(repeats, min(MAX_TIMED_RUNS, math.ceil(min_seconds / seconds)))
    return max(1, min(wanted, int(budget // seconds)))


def timed(function):
    """``(wall seconds, result)`` of one call, after a garbage collection."""
    gc.collect()
    start = time.perf_counter()
    result = function()
    return time.perf_counter() - start, result


def thread_report() -> dict:
    """torch's and numba's thread counts now, and numba's threading layer."""
    import torch

    report = {"torch_threads": torch.get_num_threads()}
    try:
        import numba

        report["numba_threads"] = numba.get_num_threads()
        try:
            report["numba_threading_layer"] = numba.threading_layer()
        except ValueError:  # no parallel numba function has run in this process
            report["numba_threading_layer"] = None
    except ImportError:
        pass
    return report


def _check_threads_kept(before: dict, after: dict) -> None:
    """Warn if a library call changed this process's thread counts (it must not)."""
    changed = {
        key: (before[key], after.get(key))
        for key in ("torch_threads", "numba_threads")
        if key in before and before[key] != after.get(key)
    }
    if changed:
        log(f"WARNING: a library call changed the process's thread settings: {changed}")


# --------------------------------------------------------------------------------------------
# The two kinds of measurement


def _cache_index_files(cache: str) -> int | None:
    return sum(1 for _ in Path(cache).rglob("*.nbi")) if cache else None


def measure_first_call(spec: dict) -> dict:
    """Cold-start latency: ``import torch``, ``import stochlap_torch``, the first library call
    and the median of three steady calls, and numba's cache index files before and after."""
    start = time.perf_counter()
    import torch  # noqa: F401  (timed: the import cost a user pays)

    torch_import = time.perf_counter() - start
    start = time.perf_counter()
    import stochlap_torch  # noqa: F401  (imports numba and the kernels)

    library_import = time.perf_counter() - start
    benchlib.pin_threads(spec["threads"])
    threads = thread_report()
    vertices, faces = benchlib.load(spec["mesh"])
    cache = os.environ.get("NUMBA_CACHE_DIR", "")
    cache_before = _cache_index_files(cache)

    call = benchlib.first_call_function(
        spec["info"].get("path"), vertices, faces, spec["num_scales"], spec["method"]
    )

    first, _ = timed(call)
    steady = [timed(call)[0] for _ in range(3)]
    after = thread_report()
    _check_threads_kept(threads, after)
    return {
        "torch_import_s": torch_import,
        "library_import_s": library_import,
        "first_call_s": first,
        "steady_s": statistics.median(steady),
        "cache_index_files_before": cache_before,
        "cache_index_files_after": _cache_index_files(cache),
        "vertices": int(vertices.shape[0]),
        **after,
    }


def _load_mesh(spec: dict):
    """``(vertices, faces, load seconds)``: the case's mesh, its vertices in the case's dtype."""
    start = time.perf_counter()
    vertices, faces = benchlib.load(spec["mesh"])
    if spec.get("dtype", "float64") != "float64":
        import torch

        vertices = vertices.to(getattr(torch, spec["dtype"]))
    return vertices, faces, time.perf_counter() - start


def _function(spec: dict, vertices, faces):
    """The timed function of a case: a call with no arguments."""
    kind, method, num_scales = spec["kind"], spec["method"], spec["num_scales"]
    if kind == "dense_eigh":
        return lambda: benchlib.run_dense_eigh(vertices, faces, NUM_EIGENPAIRS)
    if kind == "eigsh_hks":
        return lambda: benchlib.run_eigsh_hks(vertices, faces, NUM_EIGENPAIRS, NUM_TIMES)
    if method == "scipy":
        vertices_np, faces_np = vertices.numpy(), faces.numpy()
        return lambda: benchlib.run_scipy(vertices_np, faces_np, num_scales)
    max_memory = 1 << 62 if spec["unlimited_memory"] else None
    return lambda: benchlib.run_library(vertices, faces, num_scales, method, max_memory)


def _warm_up(spec: dict, function) -> float | None:
    """One untimed run: at full size, or on a small icosphere for the slow spectral cases."""
    if spec["warmup"] == "full":
        seconds, _ = timed(function)
        log(f"warm-up (full size): {seconds:.3f} s")
        return seconds
    if spec["warmup"] == "small":
        small = benchlib.load("icosphere:2" if spec["kind"] == "dense_eigh" else "icosphere:3")
        seconds, _ = timed(_function(spec, *small))
        log(f"warm-up (small icosphere, {small[0].shape[0]} vertices): {seconds:.3f} s")
        return seconds
    return None


def _timed_runs(spec: dict, function) -> tuple[list[float], object, dict]:
    """The timed runs (the first plans how many), the last result and the library's logged
    entries per row."""
    min_seconds = spec["min_seconds"] if spec["kind"] == "multiscale" else 0.0
    planned, times, result = None, [], None
    with benchlib.entries_per_row_log() as logged:
        while planned is None or len(times) < planned:
            result = None  # the previous result's memory is free before the next run
            seconds, result = timed(function)
            times.append(seconds)
            if planned is None:
                planned = planned_repeats(seconds, spec["repeats"], spec["budget"], min_seconds)
            log(f"run {len(times)}/{planned}: {seconds:.3f} s")
    return times, result, logged


def _multiscale_outputs(spec: dict, result, vertices, faces, logged) -> dict:
    """Entries per row of every ``F^(k)``, the library's memory estimate, and the saliency
    saved for the parent's comparison if asked."""
    num_scales = spec["num_scales"]
    if spec["method"] == "scipy":
        entries, source = dict(enumerate(result.entries_per_row(), start=1)), "scipy"
        saliency = result.saliency
    else:
        entries, source = benchlib.library_entries(result[0], vertices, faces, num_scales, logged)
        saliency = result[1].numpy()
    if spec.get("saliency_path"):
        import numpy as np

        np.save(spec["saliency_path"], saliency)
    return {
        "entries_per_row": {str(k): v for k, v in sorted(entries.items())},
        "entries_from": source,
        "library_estimate_bytes": benchlib.library_memory_estimate(vertices, faces, num_scales),
    }


def measure_case(spec: dict) -> dict:
    """Median and min seconds of the timed runs after a warm-up, and the peak RSS over the
    timed runs only (the warm-up may JIT-compile, and LLVM is big) and the RSS before them."""
    benchlib.pin_threads(spec["threads"])
    threads = thread_report()
    vertices, faces, load_seconds = _load_mesh(spec)
    num_vertices, num_faces = int(vertices.shape[0]), int(faces.shape[0])
    num_edges = benchlib.edge_count(faces, num_vertices)
    log(
        f"loaded {mesh_name(spec['mesh'])}: V={num_vertices} F={num_faces} E={num_edges} "
        f"in {load_seconds:.2f} s"
    )
    function = _function(spec, vertices, faces)
    warmup_seconds = _warm_up(spec, function)

    gc.collect()
    base_rss = rss_bytes()
    peak_reset = reset_peak_rss()
    times, result, logged = _timed_runs(spec, function)
    peak_rss = peak_rss_bytes()
    after = thread_report()
    _check_threads_kept(threads, after)

    out = {
        "vertices": num_vertices,
        "faces": num_faces,
        "edges": num_edges,
        "load_s": load_seconds,
        "warmup_s": warmup_seconds,
        "times_s": times,
        "median_s": statistics.median(times),
        "min_s": min(times),
        "base_rss": base_rss,
        "peak_rss": peak_rss,
        "peak_rss_since_start": not peak_reset,
        **after,
    }
    if spec["kind"] == "multiscale":
        out.update(_multiscale_outputs(spec, result, vertices, faces, logged))
    return out


def child_main(spec_path: str) -> int:
    """Run the case of ``spec_path`` and write its result where the spec says; 0 if it ran."""
    spec = json.loads(Path(spec_path).read_text())
    start_memory_watchdog(spec["min_free_bytes"])
    out: dict = {"ok": False, "load_before": os.getloadavg()[0]}
    try:
        measure = measure_first_call if spec["kind"] == "first_call" else measure_case
        with benchlib.background_load(spec.get("background", 0)):  # in this session
            out.update(measure(spec))
        out["ok"] = True
    except Exception as exc:  # recorded in the report; the parent carries on
        traceback.print_exc()
        out["error"] = f"{type(exc).__name__}: {exc}"
    out["load_after"] = os.getloadavg()[0]
    Path(spec["result_path"]).write_text(json.dumps(out))
    return 0 if out["ok"] else 1
