"""The parent's side of a measurement: one fresh process per case, and what comes back.

:func:`run_case` starts ``python benchmarks/run.py --child spec.json`` with the thread
environment of the case set before the child imports anything (``child.py`` measures), streams
its output, kills it at the timeout and records a failure instead of raising. :func:`record`
adds a result to the list: a later round of the scaling series is pooled into the earlier
rounds (:func:`fold_round`) and the saliency of a main case is compared with the library's.
Nothing here imports torch.
"""

from __future__ import annotations

import json
import math
import os
import platform
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from dataclasses import asdict
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

import benchlib
from cases import Case, find_result, ok_results
from child import MEMORY_EXIT

RUN_SCRIPT = benchlib.BENCH_DIR / "run.py"
#: Peak compute memory per vertex assumed when no smaller case of the series has run.
DEFAULT_BYTES_PER_VERTEX = 2500
#: The packages whose versions the report lists.
VERSIONED_PACKAGES = ("torch", "numba", "llvmlite", "scipy", "numpy", "trimesh", "psutil")


def _stream(pipe, tail: deque) -> None:
    for line in pipe:
        sys.stderr.write("    | " + line)
        sys.stderr.flush()
        tail.append(line.rstrip("\n"))


def _write_spec(case: Case, args, workdir: Path) -> dict:
    """The child's instructions: the case, its share of the runs and where results go."""
    index = len(list(workdir.glob("spec-*.json")))
    spec = asdict(case)
    spec.update(
        repeats=math.ceil(args.repeats / case.rounds),
        budget=args.budget / case.rounds,
        min_seconds=args.min_seconds / case.rounds,
        min_free_bytes=int(args.min_free_gb * 2**30),
        result_path=str(workdir / f"result-{index}.json"),
        saliency_path=str(workdir / f"saliency-{index}.npy") if case.save_saliency else None,
        spec_path=str(workdir / f"spec-{index}.json"),
    )
    Path(spec["spec_path"]).write_text(json.dumps(spec))
    return spec


def _warmed_cache(workdir: Path, cache_dirs: dict) -> None:
    """A fresh numba cache filled by ``stochlap warmup`` (once per run; its time recorded)."""
    if "warmed" in cache_dirs:
        return
    cache_dirs["warmed"] = tempfile.mkdtemp(prefix="numba-warmed-", dir=workdir)
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dirs["warmed"])
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", "from stochlap_torch.cli import main; main(['warmup', '-q'])"],
        env=env,
        check=True,
    )
    cache_dirs["warmup_s"] = time.perf_counter() - start


def _child_env(case: Case, workdir: Path, cache_dirs: dict) -> dict:
    """The environment of the child: pinned thread pools and the case's numba cache."""
    env = dict(os.environ)
    env.update(benchlib.thread_env(case.threads))
    env["PYTHONUNBUFFERED"] = "1"
    if case.numba_cache == "warmed":
        _warmed_cache(workdir, cache_dirs)
    if case.numba_cache == "cold":
        cache_dirs["cold"] = tempfile.mkdtemp(prefix="numba-cold-", dir=workdir)
    cache = "cold" if case.numba_cache == "reuse-cold" else case.numba_cache
    env["NUMBA_CACHE_DIR"] = cache_dirs[cache]
    return env


def _wait(process: subprocess.Popen, timeout: float) -> str | None:
    """Wait for the child; kill its session at the timeout (it holds only what we started)."""
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        return f"timed out after {timeout:.0f} s"
    except KeyboardInterrupt:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        raise
    return None


def _failure(returncode: int, result: dict, tail: deque, args) -> str | None:
    """Why the child failed without writing its own error, or None."""
    if returncode == MEMORY_EXIT:
        return f"aborted by the memory watchdog (available memory < {args.min_free_gb} GiB); " + (
            tail[-1] if tail else ""
        )
    if not result:
        return f"child exited with status {returncode}: {' / '.join(list(tail)[-3:])}"
    return None


def run_case(case: Case, args, workdir: Path, cache_dirs: dict) -> dict:
    """Run one case in a fresh process; return its result dict (``ok`` False on failure)."""
    spec = _write_spec(case, args, workdir)
    command = [sys.executable, str(RUN_SCRIPT), "--child", spec["spec_path"]]
    tail: deque = deque(maxlen=30)
    env = _child_env(case, workdir, cache_dirs)
    start = time.perf_counter()
    process = subprocess.Popen(
        command,
        cwd=benchlib.REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    reader = threading.Thread(target=_stream, args=(process.stdout, tail), daemon=True)
    reader.start()
    error = _wait(process, args.case_timeout)
    reader.join(timeout=5)
    wall = time.perf_counter() - start
    result_path = Path(spec["result_path"])
    result = json.loads(result_path.read_text()) if result_path.is_file() else {}
    error = error or _failure(process.returncode, result, tail, args)
    if error:
        result.update(ok=False, error=error)
    result.setdefault("ok", False)
    result["process_wall_s"] = wall
    result["case"] = asdict(case)
    if case.numba_cache == "warmed":
        result["warmup_s"] = cache_dirs.get("warmup_s")
    if case.save_saliency and result.get("ok"):
        result["saliency_path"] = spec["saliency_path"]
    return result


def memory_guard(case: Case, results: list[dict], args) -> str | None:
    """A reason to skip ``case`` if its extrapolated peak memory does not fit, else None."""
    import psutil

    if case.kind != "multiscale" or case.section != "scaling":
        return None
    vertices = case.vertices or 0
    done = ok_results(results, section="scaling", method=case.method)
    # Compute bytes per vertex fall slowly with size (fixed buffers), so the largest mesh done
    # gives a slight overestimate; add the interpreter and the new mesh (~100 B per vertex).
    if done:
        largest = max(done, key=lambda r: r["vertices"])
        per_vertex = (largest["peak_rss"] - largest["base_rss"]) / largest["vertices"]
    else:
        per_vertex = DEFAULT_BYTES_PER_VERTEX
    needed = per_vertex * vertices + (600 << 20) + 100 * vertices
    available = psutil.virtual_memory().available - args.min_free_gb * 2**30
    if needed > available:
        return (
            f"needs about {needed / 2**30:.1f} GiB (extrapolated from smaller meshes), "
            f"{available / 2**30:.1f} GiB available"
        )
    return None


def fold_round(results: list[dict], result: dict) -> bool:
    """Fold ``result``, a later round of the library's scaling series, into the earlier
    rounds' result for the same case: pooled runs, median and min over all of them, the
    peak RSS of the round that reached the highest. False if there is nothing to fold into."""
    case = result["case"]
    if case["rounds"] <= 1 or not result.get("ok"):
        return False
    keys = ("section", "mesh", "method", "threads", "dtype", "num_scales")
    earlier = find_result(results, **{key: case[key] for key in keys})
    if earlier is None:
        return False
    earlier["times_s"] = earlier["times_s"] + result["times_s"]
    earlier["median_s"] = statistics.median(earlier["times_s"])
    earlier["min_s"] = min(earlier["times_s"])
    earlier.setdefault("round_medians_s", {}).update(result["round_medians_s"])
    if result["peak_rss"] > earlier["peak_rss"]:
        earlier["peak_rss"], earlier["base_rss"] = result["peak_rss"], result["base_rss"]
    return True


def saliency_gap(result: dict, reference: dict | None) -> float | None:
    """Max abs difference of the saliency of two cases that saved theirs, else None."""
    import numpy as np

    if not (reference and result.get("saliency_path") and reference.get("saliency_path")):
        return None
    difference = np.load(result["saliency_path"]) - np.load(reference["saliency_path"])
    return float(np.abs(difference).max())


def record(results: list[dict], result: dict, case: Case, threads: int) -> bool:
    """Add ``result`` of ``case`` to ``results``; True if it was folded into earlier rounds.

    A main case that saved its saliency gets its gap to the library's (numba, ``threads``).
    """
    if result.get("ok") and case.rounds > 1:
        result["round_medians_s"] = {str(case.round): result["median_s"]}
    folded = fold_round(results, result)
    if not folded:
        results.append(result)
    if result.get("saliency_path"):
        reference = find_result(
            results, section="main", mesh=case.mesh, method="numba", threads=threads
        )
        result["saliency_gap"] = saliency_gap(result, reference)
    return folded


def _versions() -> dict[str, str]:
    versions = {}
    for package in VERSIONED_PACKAGES:
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "not installed"
    return versions


def _git(*command: str) -> str:
    return subprocess.run(
        ["git", *command], cwd=benchlib.REPO, capture_output=True, text=True, check=True
    ).stdout.strip()


def _commit() -> str:
    try:
        commit = _git("rev-parse", "--short", "HEAD")
        return commit + (" (+ uncommitted changes)" if _git("status", "--porcelain") else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine_header(args) -> dict:
    """CPU, memory and library versions of this machine (no torch import in the parent)."""
    import psutil

    frequency = psutil.cpu_freq()
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "command": "python benchmarks/run.py " + " ".join(sys.argv[1:]),
        "cpu": benchlib.cpu_model(),
        "cpu_mhz": round(frequency.max or frequency.current) if frequency else None,
        "logical_cores": psutil.cpu_count(logical=True),
        "physical_cores": psutil.cpu_count(logical=False),
        "memory_gib": psutil.virtual_memory().total / 2**30,
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "versions": _versions(),
        "threads": args.threads,
        "commit": _commit(),
        "load_at_start": os.getloadavg(),
    }
