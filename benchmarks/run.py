"""Speed and scale benchmark of stochlap_torch: one command, one report.

    python benchmarks/run.py [--quick] [--max-vertices N] [--threads N] [--sections ...]

Every case runs in a fresh Python process (so that its peak RSS is its own, and the first
call is measured cold), with the thread pools pinned. The parent streams progress to stderr,
records a failing or timed-out case as an error and carries on, and rewrites
``benchmarks/RESULTS.md``, ``benchmarks/results.json`` and ``benchmarks/scaling.png`` after
every case. See ``benchmarks/README.md`` for the sections and columns.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import os
import platform
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from collections import deque
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
if str(BENCH_DIR) not in sys.path:
    sys.path.insert(0, str(BENCH_DIR))

import benchlib  # noqa: E402  (no torch import at module level: the parent stays light)

#: Exit status of a child whose memory watchdog fired.
MEMORY_EXIT = 86
#: Peak compute memory per vertex assumed when no smaller case of the series has run.
DEFAULT_BYTES_PER_VERTEX = 2500

MAIN_MESHES = ("spot.obj", "gargoyle_50k.off")
MAIN_SCALES = 8
#: The speed-up target (issue 3) is set on this mesh; spot is reported beside it.
TARGET_SPEEDUP_MESH = "gargoyle_50k.off"
TARGET_SPEEDUP = 10.0
#: The large-mesh target: the library alone, in its default float64, at K = 8.
LARGE_MESH = "armadillo_loop2_692k.ply"
TARGET_LARGE_SECONDS = 5.0
TARGET_LARGE_GIB = 3.0
TARGET_PER_VERTEX_SPREAD = 1.5
#: Timed runs of a multiscale case go on until they add up to this many seconds (a 10k-vertex
#: run takes 25 ms: five of them sample a tenth of a second of a host whose speed drifts).
MIN_TIMED_SECONDS = 1.0
#: ... but no further than this many runs.
MAX_TIMED_RUNS = 200

#: Paper Table 1: model, paper vertices, K, paper seconds, files here (each present one runs).
PAPER_TABLE_1 = (
    ("Horse (Fig. 5)", 7502, 12, 2.18, ("horse_10k.obj", "horse.off")),
    ("Bunny (Fig. 6)", 35947, 8, 3.24, ("bunny.obj",)),
    ("Dinosaur (Fig. 7)", 14053, 10, 2.82, ("dinosaur.obj",)),
    ("Squirrel (Fig. 8)", 9995, 10, 1.65, ("squirrel.off",)),
    ("Girl bust (Fig. 10)", 15516, 8, 1.46, ()),
    ("Angel (Fig. 10)", 40000, 6, 2.18, ()),
    ("Foot (Fig. 10)", 10010, 10, 1.96, ("foot.off",)),
    ("Max Planck (Fig. 10)", 49132, 6, 1.64, ("maxplanck.obj",)),
    ("Cow (Fig. 10)", 11610, 10, 1.82, ("cow.obj",)),
    ("Camel (Fig. 10)", 9757, 6, 0.25, ("camel.off",)),
    ("Gargoyle (Fig. 12)", 10002, 6, 0.38, ("gargoyle.off",)),
)
PAPER_HARDWARE = "an old dual-core 2.4 GHz PC with 3.25 GB RAM (paper Sec. 4.2)"

SPECTRAL_MESHES = ("spot.obj", "fertility.off", "fandisk.off", "gargoyle.off")
SPECTRAL_EXTRA_EIGSH = ("gargoyle_50k.off",)
NUM_EIGENPAIRS = 128
NUM_TIMES = 16

SCALING_ICOSPHERES = (5, 6, 7, 8, 9, 10)
#: K and vertex dtype of the scaling series: K = 8 as in the targets, and float32, because the
#: library's peak per vertex in float64 (about 2.3 kB, measured at 692k vertices) would put the
#: 10.5M-vertex icosphere at the limit of a 24 GiB machine; float32 takes about 1.7 kB.
SCALING_SCALES = 8
SCALING_DTYPE = "float32"
SCALING_FILES = ("gargoyle_loop1_200k.ply", "armadillo_loop2_692k.ply")

SECTIONS = ("first-call", "main", "table1", "spectral", "scaling")

METHOD_NAMES = {
    "numba": "library (numba kernel)",
    "torch": "library (torch ops)",
    "scipy": "scipy.sparse baseline",
    "dense_eigh": "dense torch.linalg.eigh",
    "eigsh_hks": f"scipy eigsh ({NUM_EIGENPAIRS} pairs) + HKS",
}


# --------------------------------------------------------------------------------------------
# Cases


@dataclass
class Case:
    """One benchmark case, run in its own process."""

    section: str
    label: str
    kind: str  # "multiscale" | "dense_eigh" | "eigsh_hks" | "first_call"
    mesh: str  # benchlib.load spec
    method: str = "numba"  # "numba" | "torch" | "scipy" | kind for the spectral ones
    num_scales: int = MAIN_SCALES
    threads: int = 1
    warmup: str = "full"  # "full" | "small" | "none"
    unlimited_memory: bool = False
    save_saliency: bool = False
    numba_cache: str = "run"  # "run": the run's cache dir; "cold": a fresh empty one
    dtype: str = "float64"  # of the vertices (the library computes in their dtype)
    round: int = 0  # visit of the library's scaling series (see --rounds)
    rounds: int = 1
    info: dict = field(default_factory=dict)

    @property
    def vertices(self) -> int | None:
        return benchlib.mesh_vertices(self.mesh)


def mesh_name(spec: str) -> str:
    kind, _, value = spec.partition(":")
    return f"icosphere({value})" if kind == "icosphere" else value


def multiscale_case(section, mesh, method, num_scales, threads, dtype="float64",
                    **kwargs) -> Case:  # fmt: skip
    """A multiscale case. Always a full-size warm-up: the first run at a given size in a fresh
    process is slower (fresh memory), which would bend the scaling curve."""
    label = f"{section}: {mesh_name(mesh)} K={num_scales} {method} x{threads}"
    label += "" if dtype == "float64" else f" {dtype}"
    if kwargs.get("rounds", 1) > 1:
        label += f" (round {kwargs['round'] + 1}/{kwargs['rounds']})"
    return Case(section, label, "multiscale", mesh, method, num_scales, threads, "full",
                dtype=dtype, **kwargs)  # fmt: skip


def build_cases(args) -> tuple[list[Case], list[dict]]:
    """All cases for ``args``, and the ones left out (with the reason)."""
    threads = args.threads
    cases: list[Case] = []
    left_out: list[dict] = []

    def want(section):
        return section in args.sections

    def add(case: Case, limit: int | None = None) -> None:
        vertices = case.vertices
        limit = args.max_vertices if limit is None else min(limit, args.max_vertices)
        if case.kind != "first_call" and case.mesh.startswith("file:"):
            if benchlib.mesh_file(case.mesh[5:]) is None:
                left_out.append({"label": case.label, "reason": f"mesh not found in "
                                 f"{benchlib.MESHES_DIR}"})  # fmt: skip
                return
        # 1 % slack: "--max-vertices 50000" keeps gargoyle_50k (50,002 vertices).
        if vertices is not None and vertices > limit * 1.01:
            left_out.append({"label": case.label, "reason": f"{vertices} vertices > {limit}"})
            return
        cases.append(case)

    if want("first-call"):
        spot = "file:spot.obj"
        for label, backend, cache in (
            ("numba, empty on-disk cache (JIT compile)", "numba", "cold"),
            ("numba, on-disk cache present (cache load)", "numba", "reuse-cold"),
            ("torch ops (steps not compiled; the numba mesh kernel builds Lhat)", "torch", "run"),
        ):
            add(
                Case(
                    "first-call",
                    f"first-call: {label}",
                    "first_call",
                    spot,
                    backend,
                    MAIN_SCALES,
                    threads,
                    "none",
                    numba_cache=cache,
                    info={"variant": label},
                )
            )
    if want("main"):
        for name in MAIN_MESHES:
            mesh = f"file:{name}"
            add(multiscale_case("main", mesh, "numba", MAIN_SCALES, threads, save_saliency=True))
            if threads > 1:
                add(multiscale_case("main", mesh, "numba", MAIN_SCALES, 1, save_saliency=True))
            add(multiscale_case("main", mesh, "torch", MAIN_SCALES, threads, save_saliency=True))
            add(multiscale_case("main", mesh, "scipy", MAIN_SCALES, threads, save_saliency=True))
        add(multiscale_case("main", f"file:{LARGE_MESH}", "numba", MAIN_SCALES, threads))
    if want("table1"):
        for model, paper_vertices, num_scales, paper_seconds, files in PAPER_TABLE_1:
            info = {"model": model, "paper_vertices": paper_vertices,
                    "paper_seconds": paper_seconds}  # fmt: skip
            if not files:
                left_out.append(
                    {
                        "label": f"table1: {model}",
                        "reason": "no such mesh in ../shared/meshes (SOURCES.md)",
                    }
                )
            for name in files:
                for method in ("numba", "scipy"):
                    add(multiscale_case("table1", f"file:{name}", method, num_scales, threads,
                                        info=dict(info)))  # fmt: skip
    if want("spectral"):
        for name in SPECTRAL_MESHES + SPECTRAL_EXTRA_EIGSH:
            mesh = f"file:{name}"
            if name in SPECTRAL_MESHES:
                add(
                    Case(
                        "spectral",
                        f"spectral: {name} dense eigh x{threads}",
                        "dense_eigh",
                        mesh,
                        "dense_eigh",
                        threads=threads,
                        warmup="small",
                    ),
                    limit=args.dense_max_vertices,
                )
            vertices = benchlib.mesh_vertices(mesh) or 0
            add(
                Case(
                    "spectral",
                    f"spectral: {name} eigsh+HKS x{threads}",
                    "eigsh_hks",
                    mesh,
                    "eigsh_hks",
                    threads=threads,
                    warmup="full" if vertices <= 20_000 else "small",
                )
            )
            add(multiscale_case("spectral", mesh, "numba", MAIN_SCALES, threads))
    if want("scaling"):
        meshes = [f"icosphere:{s}" for s in SCALING_ICOSPHERES]
        meshes += [f"file:{name}" for name in SCALING_FILES]
        meshes.sort(key=lambda spec: benchlib.mesh_vertices(spec) or 0)
        for mesh in meshes:
            for method in ("scipy", "torch"):
                dtype = "float64" if method == "scipy" else args.scaling_dtype
                add(multiscale_case("scaling", mesh, method, args.scaling_scales, threads,
                                    dtype, unlimited_memory=True),
                    limit=args.baseline_max_vertices)  # fmt: skip
        # The library's series is visited ``rounds`` times, every mesh in each round, so
        # that the host's speed drifting over the series falls on every mesh alike.
        for round_index in range(args.rounds):
            for mesh in meshes:
                add(multiscale_case("scaling", mesh, "numba", args.scaling_scales, threads,
                                    args.scaling_dtype, unlimited_memory=True,
                                    round=round_index, rounds=args.rounds))  # fmt: skip
    if args.only:
        pattern = re.compile(args.only)
        cases = [case for case in cases if pattern.search(case.label)]
    return cases, left_out


# --------------------------------------------------------------------------------------------
# Child process


def _status_kib(key: str) -> int | None:
    try:
        text = Path("/proc/self/status").read_text()
    except OSError:
        return None
    match = re.search(rf"^{key}:\s+(\d+) kB", text, re.MULTILINE)
    return int(match.group(1)) if match else None


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (``VmHWM``) of this process; False if unsupported."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        return False
    return True


def _peak_rss_bytes() -> int:
    hwm = _status_kib("VmHWM")
    if hwm is not None:
        return hwm * 1024
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def _rss_bytes() -> int:
    import psutil

    return psutil.Process().memory_info().rss


def _start_memory_watchdog(min_free: int) -> None:
    """Exit with :data:`MEMORY_EXIT` if the machine's available memory drops below
    ``min_free`` bytes (the machine is shared: never push it into the OOM killer)."""
    import psutil

    def watch():
        while True:
            available = psutil.virtual_memory().available
            if available < min_free:
                sys.stderr.write(
                    f"memory watchdog: only {available / 2**30:.2f} GiB available "
                    f"(< {min_free / 2**30:.2f} GiB); peak RSS "
                    f"{_peak_rss_bytes() / 2**30:.2f} GiB; aborting this case\n"
                )
                sys.stderr.flush()
                os._exit(MEMORY_EXIT)
            time.sleep(0.2)

    threading.Thread(target=watch, daemon=True).start()


def _planned_repeats(seconds: float, repeats: int, budget: float, min_seconds: float = 0.0
                     ) -> int:  # fmt: skip
    """Timed runs of ``seconds`` each: ``repeats``, more (at most :data:`MAX_TIMED_RUNS`) to
    fill ``min_seconds``, fewer (at least one) when they would take more than ``budget``."""
    seconds = max(seconds, 1e-9)
    wanted = max(repeats, min(MAX_TIMED_RUNS, math.ceil(min_seconds / seconds)))
    return max(1, min(wanted, int(budget // seconds)))


def _log(message: str) -> None:
    sys.stderr.write(message + "\n")
    sys.stderr.flush()


def _timed(function):
    gc.collect()
    start = time.perf_counter()
    result = function()
    return time.perf_counter() - start, result


def _unique_edge_count(faces) -> int:
    import numpy as np

    faces = np.asarray(faces, dtype=np.int64)
    pairs = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    return int(np.unique(pairs[:, 0] * (int(faces.max()) + 1) + pairs[:, 1]).shape[0])


def _thread_report() -> dict:
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


def _child_first_call(spec: dict) -> dict:
    start = time.perf_counter()
    import torch  # noqa: F401  (timed: the import cost a user pays)

    torch_import = time.perf_counter() - start
    start = time.perf_counter()
    import stochlap_torch  # noqa: F401  (imports numba and the kernel module)

    library_import = time.perf_counter() - start
    benchlib.pin_threads(spec["threads"])
    vertices, faces = benchlib.load(spec["mesh"])
    cache = os.environ.get("NUMBA_CACHE_DIR", "")
    cache_before = sum(1 for _ in Path(cache).rglob("*.nbi")) if cache else None

    def call():
        return benchlib.run_library(vertices, faces, spec["num_scales"], spec["method"])

    first, _ = _timed(call)
    steady = [_timed(call)[0] for _ in range(3)]
    cache_after = sum(1 for _ in Path(cache).rglob("*.nbi")) if cache else None
    return {
        "torch_import_s": torch_import,
        "library_import_s": library_import,
        "first_call_s": first,
        "steady_s": statistics.median(steady),
        "cache_index_files_before": cache_before,
        "cache_index_files_after": cache_after,
        "vertices": int(vertices.shape[0]),
        **_thread_report(),
    }


def _child_measure(spec: dict) -> dict:
    benchlib.pin_threads(spec["threads"])
    start = time.perf_counter()
    vertices, faces = benchlib.load(spec["mesh"])
    if spec.get("dtype", "float64") != "float64":
        import torch

        vertices = vertices.to(getattr(torch, spec["dtype"]))
    load_seconds = time.perf_counter() - start
    num_vertices, num_faces = int(vertices.shape[0]), int(faces.shape[0])
    num_edges = _unique_edge_count(faces.numpy())
    _log(f"loaded {mesh_name(spec['mesh'])}: V={num_vertices} F={num_faces} E={num_edges} "
         f"in {load_seconds:.2f} s")  # fmt: skip
    kind, method, num_scales = spec["kind"], spec["method"], spec["num_scales"]
    max_memory = 1 << 62 if spec["unlimited_memory"] else None

    def make(v, f):
        if kind == "dense_eigh":
            return lambda: benchlib.run_dense_eigh(v, f, NUM_EIGENPAIRS)
        if kind == "eigsh_hks":
            return lambda: benchlib.run_eigsh_hks(v, f, NUM_EIGENPAIRS, NUM_TIMES)
        if method == "scipy":
            from scipy_baseline import multiscale_scipy

            v_np, f_np = v.numpy(), f.numpy()
            return lambda: multiscale_scipy(v_np, f_np, num_scales)
        return lambda: benchlib.run_library(v, f, num_scales, method, max_memory)

    function = make(vertices, faces)
    warmup_seconds = None
    if spec["warmup"] == "full":
        warmup_seconds, _ = _timed(function)
        _log(f"warm-up (full size): {warmup_seconds:.3f} s")
    elif spec["warmup"] == "small":
        small = benchlib.load("icosphere:2" if kind == "dense_eigh" else "icosphere:3")
        warmup_seconds, _ = _timed(make(*small))
        _log(f"warm-up (small icosphere, {small[0].shape[0]} vertices): {warmup_seconds:.3f} s")
        del small

    # Peak RSS of the timed runs only (the warm-up may JIT-compile, and LLVM is big).
    gc.collect()
    base_rss = _rss_bytes()
    peak_reset = _reset_peak_rss()
    repeats, budget = spec["repeats"], spec["budget"]
    min_seconds = spec["min_seconds"] if kind == "multiscale" else 0.0
    planned, times, result = None, [], None  # the first timed run plans the others
    with benchlib.entries_per_row_log() as logged:
        while planned is None or len(times) < planned:
            result = None
            seconds, result = _timed(function)
            times.append(seconds)
            if planned is None:
                planned = _planned_repeats(seconds, repeats, budget, min_seconds)
            _log(f"run {len(times)}/{planned}: {seconds:.3f} s")
    peak_rss = _peak_rss_bytes()

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
        **_thread_report(),
    }
    if kind == "multiscale":
        if method == "scipy":
            entries, source = dict(enumerate(result.entries_per_row(), start=1)), "scipy"
            saliency = result.saliency
        else:
            entries, source = benchlib.library_entries(result[0], vertices, faces, num_scales,
                                                       logged)  # fmt: skip
            saliency = result[1].numpy()
        out["entries_per_row"] = {str(k): v for k, v in sorted(entries.items())}
        out["entries_from"] = source
        out["library_estimate_bytes"] = benchlib.library_memory_estimate(vertices, faces,
                                                                         num_scales)  # fmt: skip
        if spec.get("saliency_path"):
            import numpy as np

            np.save(spec["saliency_path"], saliency)
    return out


def child_main(spec_path: str) -> int:
    spec = json.loads(Path(spec_path).read_text())
    _start_memory_watchdog(spec["min_free_bytes"])
    out: dict = {"ok": False, "load_before": os.getloadavg()[0]}
    try:
        if spec["kind"] == "first_call":
            out.update(_child_first_call(spec))
        else:
            out.update(_child_measure(spec))
        out["ok"] = True
    except Exception as exc:  # recorded in the report; the parent carries on
        traceback.print_exc()
        out["error"] = f"{type(exc).__name__}: {exc}"
    out["load_after"] = os.getloadavg()[0]
    Path(spec["result_path"]).write_text(json.dumps(out))
    return 0 if out["ok"] else 1


# --------------------------------------------------------------------------------------------
# Parent process


def _stream(pipe, tail: deque) -> None:
    for line in pipe:
        sys.stderr.write("    | " + line)
        sys.stderr.flush()
        tail.append(line.rstrip("\n"))


def run_case(case: Case, args, workdir: Path, cache_dirs: dict) -> dict:
    """Run one case in a fresh process; return its result dict (``ok`` False on failure)."""
    index = len(list(workdir.glob("spec-*.json")))
    spec_path, result_path = workdir / f"spec-{index}.json", workdir / f"result-{index}.json"
    spec = asdict(case)
    spec.update(
        repeats=math.ceil(args.repeats / case.rounds),
        budget=args.budget / case.rounds,
        min_seconds=args.min_seconds / case.rounds,
        min_free_bytes=int(args.min_free_gb * 2**30),
        result_path=str(result_path),
        saliency_path=str(workdir / f"saliency-{index}.npy") if case.save_saliency else None,
    )
    spec_path.write_text(json.dumps(spec))
    env = dict(os.environ)
    env.update(benchlib.thread_env(case.threads))
    env["PYTHONUNBUFFERED"] = "1"
    if case.numba_cache == "cold":
        cache_dirs["cold"] = tempfile.mkdtemp(prefix="numba-cold-", dir=workdir)
    env["NUMBA_CACHE_DIR"] = cache_dirs["cold" if case.numba_cache == "reuse-cold" else
                                        case.numba_cache]  # fmt: skip
    command = [sys.executable, str(Path(__file__).resolve()), "--child", str(spec_path)]
    tail: deque = deque(maxlen=30)
    start = time.perf_counter()
    process = subprocess.Popen(
        command, cwd=benchlib.REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
        text=True, start_new_session=True,
    )  # fmt: skip
    reader = threading.Thread(target=_stream, args=(process.stdout, tail), daemon=True)
    reader.start()
    error = None
    try:
        process.wait(timeout=args.case_timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)  # the child's own session: only what we started
        process.wait()
        error = f"timed out after {args.case_timeout:.0f} s"
    except KeyboardInterrupt:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        raise
    reader.join(timeout=5)
    wall = time.perf_counter() - start
    result = {}
    if result_path.is_file():
        result = json.loads(result_path.read_text())
    if error is None and process.returncode == MEMORY_EXIT:
        error = (f"aborted by the memory watchdog (available memory < {args.min_free_gb} GiB); "
                 + (tail[-1] if tail else ""))  # fmt: skip
    elif error is None and not result:
        last = " / ".join(list(tail)[-3:])
        error = f"child exited with status {process.returncode}: {last}"
    if error:
        result.update(ok=False, error=error)
    result.setdefault("ok", False)
    result["process_wall_s"] = wall
    result["case"] = asdict(case)
    if case.save_saliency and result.get("ok"):
        result["saliency_path"] = spec["saliency_path"]
    return result


def machine_header(args) -> dict:
    """CPU, memory and library versions of this machine (no torch import in the parent)."""
    import psutil

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    frequency = psutil.cpu_freq()
    versions = {}
    for package in ("torch", "numba", "llvmlite", "scipy", "numpy", "trimesh", "psutil"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = "not installed"
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=benchlib.REPO,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain"],
            cwd=benchlib.REPO,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        commit += " (+ uncommitted changes)" if dirty else ""
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "command": "python benchmarks/run.py " + " ".join(sys.argv[1:]),
        "cpu": cpu,
        "cpu_mhz": round(frequency.max or frequency.current) if frequency else None,
        "logical_cores": psutil.cpu_count(logical=True),
        "physical_cores": psutil.cpu_count(logical=False),
        "memory_gib": psutil.virtual_memory().total / 2**30,
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "versions": versions,
        "threads": args.threads,
        "commit": commit,
        "load_at_start": os.getloadavg(),
    }


# --------------------------------------------------------------------------------------------
# Report


def _seconds(value) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    size = abs(value)
    if size >= 100:
        return f"{value:.0f}"
    if size >= 10:
        return f"{value:.1f}"
    if size >= 0.01:
        return f"{value:.3f}"
    return f"{value:.4f}"


def _mib(value) -> str:
    return "-" if value is None else f"{value / 2**20:,.0f}"


def _ratio(value) -> str:
    return "-" if value is None else f"{value:.2f}x" if value < 10 else f"{value:.1f}x"


def _table(header: list[str], rows: list[list]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return [*lines, ""]


def _ok(results, **where) -> list[dict]:
    found = []
    for result in results:
        case = result["case"]
        if result.get("ok") and all(case.get(k) == v for k, v in where.items()):
            found.append(result)
    return found


def _find(results, **where) -> dict | None:
    found = _ok(results, **where)
    return found[0] if found else None


def _entries_at_k(result) -> str:
    entries = result.get("entries_per_row") or {}
    return f"{entries[max(entries, key=int)]:.1f}" if entries else "-"


def saliency_gap(result: dict, reference: dict | None) -> float | None:
    """Max abs difference of the saliency of two cases that saved theirs, else None."""
    import numpy as np

    if not (reference and result.get("saliency_path") and reference.get("saliency_path")):
        return None
    return float(np.abs(np.load(result["saliency_path"])
                        - np.load(reference["saliency_path"])).max())  # fmt: skip


def speedups(results) -> dict[str, float]:
    """``{mesh: scipy median / library median}`` for the main comparison."""
    ratios = {}
    for name in MAIN_MESHES:
        mesh = f"file:{name}"
        library = _find(results, section="main", mesh=mesh, method="numba",
                        threads=_main_threads(results))  # fmt: skip
        scipy = _find(results, section="main", mesh=mesh, method="scipy")
        if library and scipy:
            ratios[name] = scipy["median_s"] / library["median_s"]
    return ratios


def speedup_line(name: str, ratio: float) -> str:
    """How a main mesh's speed-up reads in the log and the report, with the verdict where the
    target applies (:data:`TARGET_SPEEDUP_MESH`)."""
    line = f"{name}: library {ratio:.2f}x faster than the scipy baseline"
    if name != TARGET_SPEEDUP_MESH:
        return f"{line} (no target: the {TARGET_SPEEDUP:.0f}x target is on {TARGET_SPEEDUP_MESH})"
    verdict = "met" if ratio >= TARGET_SPEEDUP else "NOT met"
    return f"{line} (target >= {TARGET_SPEEDUP:.0f}x: {verdict})"


def _main_threads(results) -> int:
    threads = [r["case"]["threads"] for r in results if r["case"]["section"] == "main"]
    return max(threads) if threads else 1


def fold_round(results: list[dict], result: dict) -> bool:
    """Fold ``result``, a later round of the library's scaling series, into the earlier
    rounds' result for the same case: pooled runs, median and min over all of them, the
    peak RSS of the round that reached the highest. False if there is nothing to fold into."""
    case = result["case"]
    if case["rounds"] <= 1 or not result.get("ok"):
        return False
    keys = ("section", "mesh", "method", "threads", "dtype", "num_scales")
    earlier = _find(results, **{key: case[key] for key in keys})
    if earlier is None:
        return False
    earlier["times_s"] = earlier["times_s"] + result["times_s"]
    earlier["median_s"] = statistics.median(earlier["times_s"])
    earlier["min_s"] = min(earlier["times_s"])
    earlier.setdefault("round_medians_s", {}).update(result["round_medians_s"])
    if result["peak_rss"] > earlier["peak_rss"]:
        earlier["peak_rss"], earlier["base_rss"] = result["peak_rss"], result["base_rss"]
    return True


def per_round_spreads(results) -> list[float]:
    """Time per vertex max / min of the library's scaling series within each round alone."""
    rows = _ok(results, section="scaling", method="numba")
    rounds = sorted({r for row in rows for r in row.get("round_medians_s", {})}, key=int)
    spreads = []
    for r in rounds:
        per_vertex = [row["round_medians_s"][r] / row["vertices"] for row in rows
                      if r in row.get("round_medians_s", {})]  # fmt: skip
        if len(per_vertex) > 1:
            spreads.append(max(per_vertex) / min(per_vertex))
    return spreads


def per_vertex_spread(results, icospheres_only=False) -> tuple[float, int] | None:
    """``(max / min of median seconds per vertex, number of meshes)`` over the scaling
    series (library, numba kernel)."""
    rows = _ok(results, section="scaling", method="numba")
    if icospheres_only:
        rows = [r for r in rows if r["case"]["mesh"].startswith("icosphere")]
    per_vertex = [r["median_s"] / r["vertices"] for r in rows]
    if len(per_vertex) < 2:
        return None
    return max(per_vertex) / min(per_vertex), len(per_vertex)


def write_report(results: list[dict], left_out: list[dict], header: dict, args,
                 finished: bool) -> None:  # fmt: skip
    lines = ["# stochlap_torch: speed and scale", ""]
    if not finished:
        lines += ["**Run in progress or interrupted: the tables below are partial.**", ""]
    mode = "quick" if args.quick else "full"
    versions = ", ".join(f"{k} {v}" for k, v in header["versions"].items())
    layers = {r.get("numba_threading_layer") for r in results if r.get("numba_threading_layer")}
    load_end = header.get("load_at_end")
    lines += [
        "## Machine",
        "",
        f"- Date: {header['date']}; command: `{header['command']}` ({mode} mode); "
        f"commit {header['commit']}",
        f"- CPU: {header['cpu']}"
        + (f", {header['cpu_mhz']} MHz" if header["cpu_mhz"] else "")
        + f"; {header['logical_cores']} logical / {header['physical_cores']} physical cores; "
        f"{header['memory_gib']:.1f} GiB RAM; {header['os']}; Python {header['python']}",
        f"- Versions: {versions}",
        f"- Threads: {header['threads']} (torch.set_num_threads, numba.set_num_threads, "
        "OMP/MKL/OPENBLAS/NUMBA_NUM_THREADS) unless a row says otherwise; numba threading "
        f"layer: {', '.join(sorted(layers)) or 'n/a'}. scipy.sparse itself is single-threaded.",
        "- Load average (1 min) at start: "
        + ", ".join(f"{x:.2f}" for x in header["load_at_start"])
        + (f"; at end: {', '.join(f'{x:.2f}' for x in load_end)}" if load_end else "")
        + ". Anything well above 0 means other work shared the cores.",
        f"- Repeats: median of at least {args.repeats} timed runs after one warm-up, more "
        f"(up to {MAX_TIMED_RUNS}) until the runs of a multiscale case add up to "
        f"{args.min_seconds:g} s, fewer when they would exceed {args.budget:.0f} s per case; "
        "`n` says how many. Every case runs "
        "in a fresh process; peak RSS is that process's high-water mark from "
        "the end of the warm-up to the end of the timed runs (interpreter, torch and the mesh "
        "included); 'peak - before' subtracts the RSS at the start of the timed runs.",
        "",
    ]

    # Main comparison.
    main = [r for r in results if r["case"]["section"] == "main"]
    if main:
        lines += [f"## Library vs scipy baseline vs torch ops (K = {MAIN_SCALES})", ""]
        rows = []
        for name in (*MAIN_MESHES, LARGE_MESH):
            mesh = f"file:{name}"
            scipy = _find(results, section="main", mesh=mesh, method="scipy")
            for result in (r for r in main if r["case"]["mesh"] == mesh):
                case = result["case"]
                if not result.get("ok"):
                    rows.append(
                        [
                            name,
                            METHOD_NAMES[case["method"]],
                            case["threads"],
                            "-",
                            f"error: {result.get('error')}",
                            "",
                            "",
                            "",
                            "",
                            "",
                            "",
                        ]
                    )
                    continue
                speedup = scipy["median_s"] / result["median_s"] if scipy else None
                rows.append([
                    name, METHOD_NAMES[case["method"]], case["threads"],
                    len(result["times_s"]), _seconds(result["median_s"]),
                    _seconds(result["min_s"]), _ratio(speedup), _mib(result["peak_rss"]),
                    _mib(result["peak_rss"] - result["base_rss"]),
                    "-" if result.get("saliency_gap") is None
                    else f"{result['saliency_gap']:.1e}", _entries_at_k(result),
                ])  # fmt: skip
        lines += _table(
            [
                "mesh",
                "method",
                "threads",
                "n",
                "median (s)",
                "min (s)",
                "speed-up vs scipy",
                "peak RSS (MiB)",
                "peak - before (MiB)",
                "max abs saliency diff vs library",
                "F entries/row at K",
            ],
            rows,
        )
        for name, ratio in speedups(results).items():
            lines.append(f"- **{speedup_line(name, ratio)}.**")
        large = _find(results, section="main", mesh=f"file:{LARGE_MESH}", method="numba")
        if large and large.get("ok"):
            seconds, gib = large["median_s"], large["peak_rss"] / 2**30
            verdict = ("met" if seconds < TARGET_LARGE_SECONDS and gib < TARGET_LARGE_GIB
                       else "NOT met")  # fmt: skip
            lines.append(
                f"- **{LARGE_MESH} (float64, library only): median {seconds:.2f} s, "
                f"peak RSS {gib:.2f} GiB (targets < {TARGET_LARGE_SECONDS:.0f} s and "
                f"< {TARGET_LARGE_GIB:.0f} GiB: {verdict}).**"
            )
        lines.append("")

    # First-call latency.
    first = [r for r in results if r["case"]["section"] == "first-call"]
    if first:
        lines += ["## First-call latency (fresh process, spot.obj, K = 8)", ""]
        rows = []
        for result in first:
            variant = result["case"]["info"]["variant"]
            if not result.get("ok"):
                rows.append([variant, f"error: {result.get('error')}", "", "", "", "", ""])
                continue
            rows.append([
                variant, _seconds(result["torch_import_s"]),
                _seconds(result["library_import_s"]), _seconds(result["first_call_s"]),
                _seconds(result["steady_s"]),
                _seconds(result["first_call_s"] - result["steady_s"]),
                f"{result['cache_index_files_before']} -> {result['cache_index_files_after']}",
            ])  # fmt: skip
        lines += _table(
            [
                "variant",
                "import torch (s)",
                "import stochlap_torch (s)",
                "first call (s)",
                "steady call (s)",
                "first - steady (s)",
                "numba cache index files",
            ],
            rows,
        )

    # Table 1.
    table1 = [r for r in results if r["case"]["section"] == "table1"]
    if table1 or any(x["label"].startswith("table1") for x in left_out):
        lines += [
            "## Paper Table 1 meshes",
            "",
            f"The paper's times were measured on {PAPER_HARDWARE}; the hardware, the "
            "implementation and in most rows the mesh differ (see `../shared/meshes/"
            "SOURCES.md`), so the ratio is a rough indication only.",
            "",
        ]
        rows = []
        for model, paper_vertices, num_scales, paper_seconds, files in PAPER_TABLE_1:
            if not files:
                rows.append(
                    [
                        model,
                        "(no mesh)",
                        paper_vertices,
                        "-",
                        num_scales,
                        _seconds(paper_seconds),
                        "-",
                        "-",
                        "-",
                        "-",
                    ]
                )
            for name in files:
                mesh = f"file:{name}"
                library = _find(results, section="table1", mesh=mesh, method="numba")
                scipy = _find(results, section="table1", mesh=mesh, method="scipy")
                failed = [r for r in table1 if r["case"]["mesh"] == mesh and not r.get("ok")]
                if not (library or scipy or failed):
                    continue
                note = "; ".join(f"{r['case']['method']} error: {r.get('error')}"
                                 for r in failed)  # fmt: skip
                vertices = (library or scipy or {}).get("vertices", "-")
                rows.append([
                    model, name, paper_vertices, vertices, num_scales, _seconds(paper_seconds),
                    _seconds(library["median_s"]) if library else note or "-",
                    _seconds(scipy["median_s"]) if scipy else "-",
                    _ratio(paper_seconds / library["median_s"]) if library else "-",
                    _entries_at_k(library) if library else "-",
                ])  # fmt: skip
        lines += _table(
            [
                "model",
                "file",
                "V (paper)",
                "V (here)",
                "K",
                "paper (s)",
                "library (s)",
                "scipy baseline (s)",
                "paper / library",
                "F entries/row at K",
            ],
            rows,
        )

    # Spectral baselines.
    spectral = [r for r in results if r["case"]["section"] == "spectral"]
    if spectral:
        lines += [
            "## Spectral baselines",
            "",
            f"Dense: every eigenpair of the cotangent Laplacian (`torch.linalg.eigh`, O(V^3)); "
            f"eigsh: {NUM_EIGENPAIRS} eigenpairs by scipy shift-invert ARPACK and the heat "
            f"kernel signature at {NUM_TIMES} times (`stochlap_torch.baselines`). Library: "
            f"K = {MAIN_SCALES}, numba kernel.",
            "",
        ]
        rows = []
        for name in SPECTRAL_MESHES + SPECTRAL_EXTRA_EIGSH:
            mesh = f"file:{name}"
            found = {r["case"]["method"]: r for r in spectral if r["case"]["mesh"] == mesh}
            if not found:
                continue

            def cell(key, found=found):
                result = found.get(key)
                if result is None:
                    return "-", "-"
                if not result.get("ok"):
                    return f"error: {result.get('error')}", "-"
                return (f"{_seconds(result['median_s'])} (n={len(result['times_s'])})",
                        _mib(result["peak_rss"]))  # fmt: skip

            dense, eigsh, library = cell("dense_eigh"), cell("eigsh_hks"), cell("numba")
            vertices = next((r["vertices"] for r in found.values() if r.get("ok")), "-")
            ratio = "-"
            if found.get("eigsh_hks", {}).get("ok") and found.get("numba", {}).get("ok"):
                ratio = _ratio(found["eigsh_hks"]["median_s"] / found["numba"]["median_s"])
            rows.append([name, vertices, *dense, *eigsh, *library, ratio])
        lines += _table(["mesh", "V", "dense eigh (s)", "RSS (MiB)", "eigsh + HKS (s)",
                         "RSS (MiB)", "library (s)", "RSS (MiB)", "eigsh+HKS / library"],
                        rows)  # fmt: skip

    # Scaling series.
    scaling = [r for r in results if r["case"]["section"] == "scaling"]
    if scaling:
        lines += [
            f"## Scaling series (K = {args.scaling_scales}, {args.scaling_dtype} vertices, numba "
            "kernel unless stated; the scipy baseline always computes in float64)",
            "",
            "The library's memory guard is switched off here (`max_memory` huge): its default "
            "budget is half the RAM, and what it counts for these streamed runs (outputs and "
            "scratch rows; column 'library estimate', `stochlap_torch.diffusion."
            "streamed_memory`) is shown beside the measured peak. The harness instead skips a "
            "case whose peak, extrapolated from the smaller "
            "meshes, would not fit in the available memory, and a watchdog aborts a case that "
            "drives the machine "
            f"below {args.min_free_gb} GiB free.",
            "",
        ]
        if args.rounds > 1:
            lines += [
                f"The library's series runs in {args.rounds} rounds, each visiting every mesh "
                "from the smallest up, each visit a fresh process with its own warm-up and "
                f"1/{args.rounds} of the runs and seconds above; its rows pool the runs of "
                "every round (peak RSS: the round that reached the highest). The host's speed "
                "drifts by 20-50% over minutes on these shared VMs, so one pass over the "
                "series would hand each mesh a different speed.",
                "",
            ]
        rows = []
        for result in sorted(scaling, key=lambda r: (r["case"]["method"] != "numba",
                                                     r["case"]["method"],
                                                     benchlib.mesh_vertices(r["case"]["mesh"])
                                                     or 0)):  # fmt: skip
            case = result["case"]
            name = mesh_name(case["mesh"])
            if not result.get("ok"):
                rows.append(
                    [
                        name,
                        benchlib.mesh_vertices(case["mesh"]) or "-",
                        METHOD_NAMES[case["method"]],
                        "-",
                        f"error: {result.get('error')}",
                    ]
                    + [""] * 7
                )
                continue
            delta = result["peak_rss"] - result["base_rss"]
            rows.append([
                name, f"{result['vertices']:,}", METHOD_NAMES[case["method"]],
                len(result["times_s"]), _seconds(result["median_s"]), _seconds(result["min_s"]),
                f"{1e6 * result['median_s'] / result['vertices']:.2f}",
                _mib(result["peak_rss"]), _mib(delta), f"{delta / result['vertices']:.0f}",
                "-" if result.get("library_estimate_bytes") is None
                else f"{result['library_estimate_bytes'] / 2**30:.2f} GiB",
                _entries_at_k(result),
            ])  # fmt: skip
        lines += _table(
            [
                "mesh",
                "V",
                "method",
                "n",
                "median (s)",
                "min (s)",
                "us / vertex",
                "peak RSS (MiB)",
                "peak - before (MiB)",
                "bytes / vertex",
                "library estimate",
                "F entries/row at K",
            ],
            rows,
        )
        for icospheres_only in (False, True):
            spread = per_vertex_spread(results, icospheres_only)
            if spread:
                what = "icospheres only" if icospheres_only else "whole series"
                verdict = "met" if spread[0] <= TARGET_PER_VERTEX_SPREAD else "NOT met"
                lines.append(f"- **Time per vertex, max / min ({what}, {spread[1]} meshes): "
                             f"{spread[0]:.2f} (target <= {TARGET_PER_VERTEX_SPREAD}: "
                             f"{verdict}).**")  # fmt: skip
        spreads = per_round_spreads(results)
        if len(spreads) > 1:
            lines.append(
                "- Time per vertex, max / min, each round alone (whole series): "
                + ", ".join(f"{x:.2f}" for x in spreads)
                + "."
            )
        numba_rows = [r for r in _ok(results, section="scaling", method="numba")
                      if r.get("entries_per_row")]  # fmt: skip
        if numba_rows:
            num_scales = max(len(r["entries_per_row"]) for r in numba_rows)
            lines += ["", "Mean stored entries per row of F^(k) (library, numba kernel):", ""]
            lines += _table(["mesh"] + [f"k={k}" for k in range(1, num_scales + 1)], [
                [mesh_name(r["case"]["mesh"])]
                + [f"{r['entries_per_row'].get(str(k), float('nan')):.1f}"
                   for k in range(1, num_scales + 1)]
                for r in numba_rows
            ])  # fmt: skip
        lines += ["![time vs vertices](scaling.png)", ""]

    failures = [r for r in results if not r.get("ok")]
    if failures or left_out:
        lines += ["## Failed and skipped cases", ""]
        lines += [f"- {r['case']['label']}: **{r.get('error')}**" for r in failures]
        lines += [f"- {x['label']}: skipped ({x['reason']})" for x in left_out]
        lines.append("")

    out = Path(args.output_dir)
    (out / "RESULTS.md").write_text("\n".join(lines))
    (out / "results.json").write_text(
        json.dumps(
            {"header": header, "results": results, "left_out": left_out}, indent=1, default=str
        )
    )


def write_plot(results: list[dict], args) -> None:
    """Log-log time vs vertices of every successful multiscale and spectral case."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(8, 6))
    styles = {
        "numba": ("library (numba kernel)", "C0", "o"),
        "torch": ("library (torch ops)", "C1", "s"),
        "scipy": ("scipy.sparse baseline", "C2", "^"),
        "eigsh_hks": (METHOD_NAMES["eigsh_hks"], "C3", "D"),
        "dense_eigh": (METHOD_NAMES["dense_eigh"], "C4", "v"),
    }
    plotted = False
    for method, (label, colour, marker) in styles.items():
        rows = [
            r
            for r in results
            if r.get("ok")
            and r["case"]["method"] == method
            and r["case"]["kind"] != "first_call"
            and r["case"]["threads"] == args.threads
        ]
        if not rows:
            continue
        series = sorted((r["vertices"], r["median_s"]) for r in rows
                        if r["case"]["section"] == "scaling")  # fmt: skip
        others = [(r["vertices"], r["median_s"]) for r in rows
                  if r["case"]["section"] != "scaling"]  # fmt: skip
        if series:
            dtype = "float64" if method == "scipy" else args.scaling_dtype
            axes.plot(
                *zip(*series, strict=True),
                color=colour,
                marker=marker,
                label=f"{label}, scaling series (K={args.scaling_scales}, {dtype})",
            )
        if others:
            axes.scatter(
                *zip(*others, strict=True),
                color=colour,
                marker=marker,
                facecolors="none",
                label=f"{label}, other meshes",
            )
        plotted = True
    # Anchor the reference on the smallest mesh of the scaling series (else of any library run).
    library = sorted((r["vertices"], r["median_s"])
                     for r in _ok(results, section="scaling", method="numba"))  # fmt: skip
    library = library or sorted(
        (r["vertices"], r["median_s"])
        for r in _ok(results, method="numba")
        if r["case"]["kind"] == "multiscale"
    )
    vertices = sorted(r["vertices"] for r in results if r.get("ok") and "vertices" in r)
    if library and vertices:
        v0, t0 = library[0]
        span = [vertices[0], vertices[-1]]
        axes.plot(
            span, [t0 * v / v0 for v in span], "k--", lw=1, label="linear reference (time ∝ V)"
        )
    if not plotted:
        plt.close(figure)
        return
    axes.set_xscale("log")
    axes.set_yscale("log")
    axes.set_xlabel("vertices")
    axes.set_ylabel("median time (s)")
    axes.set_title(
        f"stochlap_torch, {args.threads} thread(s); hollow markers: other meshes "
        f"(main and spectral K={MAIN_SCALES}, Table 1 the paper's K)",
        fontsize=9,
    )
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7)
    figure.tight_layout()
    figure.savefig(Path(args.output_dir) / "scaling.png", dpi=120)
    plt.close(figure)


def _memory_guard(case: Case, results: list[dict], args) -> str | None:
    """A reason to skip ``case`` if its extrapolated peak memory does not fit, else None."""
    import psutil

    if case.kind != "multiscale" or case.section != "scaling":
        return None
    vertices = case.vertices or 0
    done = _ok(results, section="scaling", method=case.method)
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
        return (f"needs about {needed / 2**30:.1f} GiB (extrapolated from smaller meshes), "
                f"{available / 2**30:.1f} GiB available")  # fmt: skip
    return None


def parse_args(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="3 repeats, 60 s per case, dense eigh up to 5000 vertices",
    )
    parser.add_argument(
        "--max-vertices",
        type=int,
        default=11_000_000,
        help="skip meshes with more vertices (default 11M: everything, "
        "including the 10.5M-vertex icosphere)",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=benchlib.default_threads(),
        help="threads for torch, numba, OpenMP, MKL, OpenBLAS (default: all logical cores)",
    )
    parser.add_argument("--repeats", type=int, help="timed runs per case (default 5; quick 3)")
    parser.add_argument(
        "--budget",
        type=float,
        help="seconds of timed runs per case before repeats are cut (default 300; quick 60)",
    )
    parser.add_argument(
        "--min-seconds",
        type=float,
        help="timed seconds a multiscale case adds runs up to (default "
        f"{MIN_TIMED_SECONDS:g}; quick 0.3)",
    )
    parser.add_argument(
        "--rounds",
        type=int,
        help="visits of the library's scaling series, every mesh in each (default 3; quick 1)",
    )
    parser.add_argument(
        "--sections",
        default=",".join(SECTIONS),
        help=f"comma-separated subset of {','.join(SECTIONS)}",
    )
    parser.add_argument("--only", help="regular expression on case labels")
    parser.add_argument(
        "--scaling-scales",
        type=int,
        default=SCALING_SCALES,
        help=f"K of the scaling series (default {SCALING_SCALES})",
    )
    parser.add_argument(
        "--scaling-dtype",
        choices=("float32", "float64"),
        default=SCALING_DTYPE,
        help=f"vertex dtype of the library in the scaling series (default "
        f"{SCALING_DTYPE}: in float64 the 10.5M case needs about 24 GiB)",
    )
    parser.add_argument(
        "--dense-max-vertices",
        type=int,
        help="largest mesh for dense eigh (default 10500; quick 5000)",
    )
    parser.add_argument(
        "--baseline-max-vertices",
        type=int,
        default=250_000,
        help="largest mesh of the scaling series for the scipy and torch paths (default 250000)",
    )
    parser.add_argument(
        "--case-timeout",
        type=float,
        default=4 * 3600,
        help="seconds before a case is killed (default 4 h)",
    )
    parser.add_argument(
        "--min-free-gb",
        type=float,
        default=1.0,
        help="abort a case when available memory falls below this",
    )
    parser.add_argument(
        "--output-dir",
        default=str(BENCH_DIR),
        help="where RESULTS.md, results.json and scaling.png go",
    )
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.repeats is None:
        args.repeats = 3 if args.quick else 5
    if args.budget is None:
        args.budget = 60.0 if args.quick else 300.0
    if args.min_seconds is None:
        args.min_seconds = 0.3 if args.quick else MIN_TIMED_SECONDS
    if args.rounds is None:
        args.rounds = 1 if args.quick else 3
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    if args.dense_max_vertices is None:
        args.dense_max_vertices = 5000 if args.quick else 10_500
    args.sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = set(args.sections) - set(SECTIONS)
    if unknown:
        parser.error(f"unknown sections {sorted(unknown)}; choose from {SECTIONS}")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.child:
        return child_main(args.child)
    Path(args.output_dir).mkdir(parents=True, exist_ok=True)
    if not benchlib.MESHES_DIR.is_dir():
        _log(
            f"NOTE: {benchlib.MESHES_DIR} not found: every case on a shared mesh is skipped "
            "(spot.obj falls back to the copy bundled with the library)"
        )
    cases, left_out = build_cases(args)
    header = machine_header(args)
    _log(
        f"{len(cases)} cases, {len(left_out)} skipped; {args.threads} thread(s); "
        f"{header['cpu']}; load average {header['load_at_start'][0]:.2f}"
    )
    results: list[dict] = []
    workdir = Path(tempfile.mkdtemp(prefix="stochlap-bench-"))
    cache_dirs = {"run": str(workdir / "numba-cache")}
    started = time.perf_counter()
    finished = False
    try:
        for number, case in enumerate(cases, start=1):
            reason = _memory_guard(case, results, args)
            if reason:
                _log(f"[{number}/{len(cases)}] {case.label}: SKIPPED ({reason})")
                left_out.append({"label": case.label, "reason": reason})
                continue
            _log(f"[{number}/{len(cases)}] {case.label} "
                 f"(elapsed {time.perf_counter() - started:.0f} s)")  # fmt: skip
            try:
                result = run_case(case, args, workdir, cache_dirs)
            except OSError as exc:
                result = {"ok": False, "error": f"could not run the case: {exc}",
                          "case": asdict(case)}  # fmt: skip
            if result.get("ok") and case.rounds > 1:
                result["round_medians_s"] = {str(case.round): result["median_s"]}
            folded = fold_round(results, result)
            if not folded:
                results.append(result)
            if result.get("saliency_path"):
                reference = _find(results, section="main", mesh=case.mesh, method="numba",
                                  threads=args.threads)  # fmt: skip
                result["saliency_gap"] = saliency_gap(result, reference)
            if result.get("ok") and "median_s" in result:
                _log(
                    f"    -> median {result['median_s']:.3f} s over {len(result['times_s'])}"
                    f" runs, peak RSS {result['peak_rss'] / 2**20:.0f} MiB"
                    + (" (folded into the earlier rounds)" if folded else "")
                )
            elif result.get("ok"):
                _log(f"    -> first call {result['first_call_s']:.3f} s, steady "
                     f"{result['steady_s']:.3f} s")  # fmt: skip
            else:
                _log(f"    -> FAILED: {result.get('error')}")
            if case.section == "main" and case.method == "scipy":
                ratio = speedups(results).get(case.mesh[5:])
                if ratio is not None:
                    _log(f"    == {speedup_line(case.mesh[5:], ratio)}")
            write_report(results, left_out, header, args, finished=False)
        finished = True
    finally:
        header["load_at_end"] = os.getloadavg()
        header["total_wall_s"] = time.perf_counter() - started
        write_report(results, left_out, header, args, finished)
        write_plot(results, args)
        shutil.rmtree(workdir, ignore_errors=True)
    for name, ratio in speedups(results).items():
        print(speedup_line(name, ratio))
    spread = per_vertex_spread(results)
    if spread:
        print(
            f"time per vertex max/min over the scaling series: {spread[0]:.2f} "
            f"(target <= {TARGET_PER_VERTEX_SPREAD})"
        )
    failed = sum(not r.get("ok") for r in results)
    print(
        f"{len(results)} cases run, {failed} failed, {len(left_out)} skipped in "
        f"{header['total_wall_s']:.0f} s; wrote {Path(args.output_dir) / 'RESULTS.md'}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
