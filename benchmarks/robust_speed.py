"""The ``speed`` section of ``benchmarks/robust.py``: every pipeline in a fresh process.

Each measurement runs this file as a child (``python benchmarks/robust_speed.py TASK MESH``)
with pinned threads: load, one warm-up call on a small mesh, a reset of the peak-RSS mark, then
:data:`SPEED_RUNS` timed runs; the child prints one JSON line. The HKS baseline is measured at
two OpenBLAS settings and the faster counts. The section waits for a quiet machine first.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from robust_common import (
    BLAS_TUNING_ENV,
    THREAD_ENV,
    THREADS,
    load,
    log,
    log_hks,
    pin_threads,
    robust_features,
    saliency,
)

SPEED_MESH = "gargoyle_50k.off"
SCALING_MESHES = ("gargoyle_50k.off", "gargoyle_loop1_200k.ply", "armadillo_loop2_692k.ply")
WARM_MESH = "camel.off"
SPEED_RUNS = 3
QUIET_LOAD, QUIET_POLL, QUIET_PATIENCE = 0.7, 20.0, 900.0


SPEED_TASKS = ("robust_features", "robust_saliency", "hks", "lee", "paper_saliency")


def _task(task: str):
    return {
        "robust_features": robust_features,
        "robust_saliency": lambda v, f: saliency(v, f, "robust"),
        "hks": lambda v, f: log_hks(v, f)[0],  # eigenpairs + signature
        "lee": lambda v, f: saliency(v, f, "lee"),
        "paper_saliency": lambda v, f: saliency(v, f, "paper"),
    }[task]


def memory_mb(key: str) -> float:
    """``VmRSS`` / ``VmHWM`` of this process in MB. Not ``ru_maxrss``: Linux carries the
    parent's high-water mark into a child across fork and exec."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {key} in /proc/self/status")


def child_main(task: str, name: str) -> None:
    """Inside the child: load, warm up on a small mesh, reset the peak-RSS mark, time
    :data:`SPEED_RUNS` runs, print one JSON line (seconds; RSS before, peak RSS, in MB)."""
    import gc

    pin_threads()
    function = _task(task)
    v, f = load(name)
    function(*load(WARM_MESH))
    gc.collect()
    base = memory_mb("VmRSS")
    try:
        Path("/proc/self/clear_refs").write_text("5")  # VmHWM := VmRSS
        reset = True
    except OSError:
        reset = False
    runs = []
    for _ in range(SPEED_RUNS):
        start = time.perf_counter()
        function(v, f)
        runs.append(time.perf_counter() - start)
    peak = memory_mb("VmHWM")
    print(
        json.dumps(
            {
                "task": task,
                "mesh": name,
                "V": len(v),
                "runs": runs,
                "median": float(np.median(runs)),
                "base_mb": base,
                "peak_mb": peak,
                "extra_mb": peak - base,
                "peak_reset": reset,
            }
        ),
        flush=True,
    )


def run_child(
    task: str, name: str, openblas_threads: int = THREADS, clean_blas: bool = False
) -> dict:
    """:func:`child_main` in a fresh interpreter with pinned threads."""
    env = dict(os.environ, **{k: str(THREADS) for k in THREAD_ENV})
    env["OPENBLAS_NUM_THREADS"] = str(openblas_threads)
    if clean_blas:
        for key in BLAS_TUNING_ENV:
            env.pop(key, None)
    out = subprocess.run(
        [sys.executable, __file__, task, name],
        env=env,
        capture_output=True,
        text=True,
        timeout=3600,
        check=False,
    )
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode or not lines:
        raise RuntimeError(f"{task} on {name} failed ({out.returncode}): {out.stderr[-1500:]}")
    result = json.loads(lines[-1])
    result.update(openblas_threads=openblas_threads, clean_blas=clean_blas)
    log(
        f"  {task:16s} {name:26s} median {result['median']:7.2f} s  runs "
        f"{[round(r, 2) for r in result['runs']]}  peak {result['peak_mb']:.0f} MB "
        f"(+{result['extra_mb']:.0f})  OPENBLAS threads {openblas_threads}"
    )
    return result


def wait_until_quiet() -> dict:
    """Poll the 1-minute load until it is below :data:`QUIET_LOAD` (at most
    :data:`QUIET_PATIENCE` seconds)."""
    start = time.time()
    load = os.getloadavg()[0]
    while load >= QUIET_LOAD and time.time() - start < QUIET_PATIENCE:
        log(f"  waiting for a quiet machine: 1-min load {load:.2f}")
        time.sleep(QUIET_POLL)
        load = os.getloadavg()[0]
    quiet = load < QUIET_LOAD
    log(
        f"speed section starts at 1-min load {load:.2f} after {time.time() - start:.0f} s"
        + ("" if quiet else " -- NOT QUIET, measured anyway")
    )
    return {
        "load_at_start": load,
        "waited_s": time.time() - start,
        "quiet": quiet,
        "blas_tuning_env": {k: os.environ.get(k) for k in BLAS_TUNING_ENV},
    }


def section_speed() -> dict:
    result = {
        "machine": wait_until_quiet(),
        "threads": THREADS,
        "warm_mesh": WARM_MESH,
        "pipelines": {},
        "hks_settings": [],
        "robust_openblas1": {},
        "scaling": [],
        "errors": [],
    }
    for task in SPEED_TASKS:
        try:
            if task == "hks":  # the faster of two OpenBLAS settings is the baseline
                tries = [run_child(task, SPEED_MESH, n, clean_blas=True) for n in (THREADS, 1)]
                result["hks_settings"] = tries
                result["pipelines"][task] = min(tries, key=lambda r: r["median"])
            else:
                result["pipelines"][task] = run_child(task, SPEED_MESH)
            if task.startswith("robust_"):  # for information: the library at 1 BLAS thread
                result["robust_openblas1"][task] = run_child(task, SPEED_MESH, 1)
        except Exception as exc:
            result["errors"].append(f"{task}: {exc}")
            log(f"FAILED {task}: {exc}")
    for name in SCALING_MESHES:
        for task in ("robust_features", "robust_saliency"):
            try:
                result["scaling"].append(run_child(task, name))
            except Exception as exc:
                result["errors"].append(f"{task} {name}: {exc}")
                log(f"FAILED {task} {name}: {exc}")
    result["machine"]["load_at_end"] = os.getloadavg()[0]
    return result


if __name__ == "__main__":
    child_main(*sys.argv[1:3])
