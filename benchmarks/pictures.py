"""What a picture costs (issue 33 §5): ``render_scalar`` on gargoyle_50k and spot, smooth and
flat shading, each in a fresh process with 2 threads pinned (and 2 cores, where the system
lets a process choose), median of 3 runs after one warm-up; writes ``PICTURES.md``.

    python benchmarks/pictures.py [--before PATH] [--threads 2] [--runs 3]

``--before PATH``: also time the package at PATH (a checkout of an older commit, e.g.
``git worktree add /tmp/before <commit>``) with its own defaults, the "before" column.
The picture is the CLI's: three views, 100 dpi, a title, a colour bar, no markers; the field is
a smooth function of the positions (the picture's cost does not depend on the values).
A mesh missing from ``../shared/meshes`` is skipped, and the report says so.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import benchlib

OUT = benchlib.BENCH_DIR / "PICTURES.md"
MESHES = ("gargoyle_50k.off", "spot.obj")
#: The target of issue 33 §5: a picture of a 50k-vertex mesh within this many seconds.
TARGET_SECONDS, TARGET_MESH = 2.0, "gargoyle_50k.off"


def child(name: str, mode: str, threads: int, runs: int, package: str | None) -> dict:
    """Inside the fresh process: time ``runs`` pictures after one warm-up."""
    if hasattr(os, "sched_setaffinity") and len(os.sched_getaffinity(0)) > threads:
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[:threads])
    benchlib.pin_threads(threads)
    if package:
        sys.path.insert(0, package)
    import numpy as np

    import stochlap_torch
    from stochlap_torch import load_mesh
    from stochlap_torch.viz import render_scalar

    mesh = load_mesh(benchlib.mesh_file(name))
    vertices, faces = mesh.vertices.double().numpy(), mesh.faces.numpy()
    scale = float(np.ptp(vertices, axis=0).max())
    values = np.sin(6.0 * vertices[:, 0] / scale) + vertices[:, 1] / scale
    options = {"title": f"{name}: a picture", "views": 3, "dpi": 100}
    if mode != "before":
        options["shading"] = mode
    seconds = []
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "picture.png"
        for _ in range(runs + 1):
            start = time.perf_counter()
            render_scalar(vertices, faces, values, path, **options)
            seconds.append(time.perf_counter() - start)
        size = path.stat().st_size
    return {
        "mesh": name,
        "mode": mode,
        "vertices": int(vertices.shape[0]),
        "faces": int(faces.shape[0]),
        "warmup_s": seconds[0],
        "runs_s": seconds[1:],
        "median_s": statistics.median(seconds[1:]),
        "png_kb": size / 1024,
        "package": str(Path(stochlap_torch.__file__).parent),
    }


def measure(name: str, mode: str, threads: int, runs: int, package: str | None) -> dict:
    """One case in a fresh process (threads pinned through the environment before any load)."""
    command = [sys.executable, __file__, "--child", name, mode, "--threads", str(threads)]
    command += ["--runs", str(runs)] + (["--before", package] if package else [])
    env = {**os.environ, **benchlib.thread_env(threads)}
    result = subprocess.run(command, env=env, capture_output=True, text=True, check=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def git_commit(folder: Path) -> str:
    result = subprocess.run(
        ["git", "-C", str(folder), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    return result.stdout.strip() or "unknown"


def report(results: list[dict], skipped: list[str], threads: int, before: str | None) -> str:
    lines = [
        "# What a picture costs",
        "",
        "Written by `python benchmarks/pictures.py"
        + (" --before PATH" if before else "")
        + "` (issue 33 §5). `render_scalar` as the CLI calls it (three views, 100 dpi, a title "
        "and a colour bar), each case in a fresh process with "
        f"{threads} threads pinned, median of the runs after one warm-up.",
        "",
        f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} logical "
        f"cores, load average {os.getloadavg()[0]:.1f} at the start; Python "
        f"{platform.python_version()}; this code at {git_commit(benchlib.REPO)}"
        + (f", before = the package at {git_commit(Path(before))}" if before else "")
        + ".",
        "",
        "| mesh | vertices | faces | shading | median (s) | runs (s) | PNG (kB) |",
        "|---|---:|---:|---|---:|---|---:|",
    ]
    for r in results:
        mode = "before (mplot3d, flat)" if r["mode"] == "before" else r["mode"]
        runs = ", ".join(f"{s:.2f}" for s in r["runs_s"])
        lines.append(
            f"| {r['mesh']} | {r['vertices']} | {r['faces']} | {mode} | {r['median_s']:.2f} "
            f"| {runs} | {r['png_kb']:.0f} |"
        )
    lines.append("")
    target = [r for r in results if r["mesh"] == TARGET_MESH and r["mode"] == "smooth"]
    if target:
        seconds = target[0]["median_s"]
        verdict = "met" if seconds < TARGET_SECONDS else "NOT met"
        lines.append(
            f"Target (a smooth picture of the 50k-vertex mesh within {TARGET_SECONDS:g} s on "
            f"{threads} cores): {verdict}, {seconds:.2f} s."
        )
    for name in skipped:
        lines.append(f"Skipped {name}: not in {benchlib.MESHES_DIR}.")
    return "\n".join(lines) + "\n"


def main(argv=None) -> Path | None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--before", default=None, help="an older checkout to time as well")
    parser.add_argument("--out", default=str(OUT))
    parser.add_argument("--child", nargs=2, metavar=("MESH", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(*args.child, args.threads, args.runs, args.before)))
        return None
    results, skipped = [], []
    for name in MESHES:
        if benchlib.mesh_file(name) is None:
            print(f"skipping {name}: not in {benchlib.MESHES_DIR}", file=sys.stderr)
            skipped.append(name)
            continue
        modes = [("smooth", None), ("flat", None)]
        if args.before:
            modes.append(("before", str(Path(args.before).resolve())))
        for mode, package in modes:
            result = measure(name, mode, args.threads, args.runs, package)
            print(f"{name} {mode}: {result['median_s']:.2f} s ({result['package']})")
            results.append(result)
    out = Path(args.out)
    out.write_text(report(results, skipped, args.threads, args.before), encoding="utf-8")
    print(out)
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
