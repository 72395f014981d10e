"""A user's first week, timed: reading an OBJ, `stochlap features` on a folder and its rerun,
and a fully cached `MeshFeatureDataset` (issue "A user's first week", section 1).

    python benchmarks/first_week.py [--out benchmarks/FIRST_WEEK.md] [--threads 1]

Every timing is a fresh process (what a user waits for: imports included) unless it says
"in process"; medians of ``--repeats`` runs. Targets, as ratios measured in the same run: the
OBJ reader at least as fast as trimesh, a rerun of a finished folder at least 5x faster than
the first run, a fully cached 9-mesh dataset constructed in under 2 s.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MESHES = ROOT.parent / "shared" / "meshes"
#: Nine small shared meshes (2.9k-10k vertices): OBJ and OFF, with and without defects.
DATASET = (
    "spot.obj cow.obj horse_10k.obj camel.off foot.off squirrel.off fandisk.off "
    "rocker_arm.off teddy.off"
).split()
READ = "armadillo.obj"


def timed(command: list[str], env: dict) -> float:
    start = time.perf_counter()
    subprocess.run(command, check=True, env=env, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def in_process(code: str, env: dict) -> float:
    """Seconds a snippet reports on its last stdout line, run in a fresh process."""
    out = subprocess.run(
        [sys.executable, "-c", code], check=True, env=env, capture_output=True, text=True
    )
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "FIRST_WEEK.md")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    missing = [n for n in (*DATASET, READ) if not (MESHES / n).is_file()]
    if missing:
        parser.exit(2, f"first_week: needs {', '.join(missing)} in {MESHES}\n")
    threads = str(args.threads)
    env = {**os.environ, "OMP_NUM_THREADS": threads, "STOCHLAP_BENCH_THREADS": threads}
    median = statistics.median
    results: dict[str, float] = {}

    read = (
        "import time, trimesh; from pathlib import Path; "
        "from stochlap_torch.mesh.io import read_obj; p = Path({path!r}); "
        "s = time.perf_counter(); {call}; print(time.perf_counter() - s)"
    )
    path = str(MESHES / READ)
    for name, call in (("reader", "read_obj(p)"), ("trimesh", "trimesh.load(p, process=False)")):
        runs = [in_process(read.format(path=path, call=call), env) for _ in range(args.repeats)]
        results[f"read_{name}_s"] = median(runs)

    with tempfile.TemporaryDirectory() as tmp:
        folder, out = Path(tmp) / "meshes", Path(tmp) / "features"
        folder.mkdir()
        for name in DATASET:
            shutil.copyfile(MESHES / name, folder / name)
        cli = [sys.executable, "-m", "stochlap_torch", "features", str(folder), "-o", str(out)]
        cli += ["-q", "--threads", threads]
        results["features_first_s"] = timed(cli, env)
        results["features_rerun_s"] = median(timed(cli, env) for _ in range(args.repeats))

        build = (
            "import time, torch; torch.set_num_threads({threads}); "
            "from stochlap_torch.learning import MeshFeatureDataset; s = time.perf_counter(); "
            "MeshFeatureDataset({folder!r}, cache_dir={cache!r}, progress=False); "
            "print(time.perf_counter() - s)"
        ).format(threads=args.threads, folder=str(folder), cache=str(Path(tmp) / "cache"))
        results["dataset_first_s"] = in_process(build, env)
        results["dataset_cached_s"] = median(in_process(build, env) for _ in range(args.repeats))

    results["read_ratio"] = results["read_trimesh_s"] / results["read_reader_s"]
    results["rerun_ratio"] = results["features_first_s"] / results["features_rerun_s"]
    write_report(args.out, results, args)


def write_report(path: Path, r: dict, args) -> None:
    def verdict(ok: bool) -> str:
        return "met" if ok else "NOT met"

    lines = [
        "# A user's first week, timed",
        "",
        f"`python benchmarks/first_week.py --threads {args.threads}`: {args.repeats} repeats "
        f"(median), {os.cpu_count()} CPUs, 1-minute load {os.getloadavg()[0]:.1f} at the end.",
        "",
        "| what | seconds | target |",
        "|---|---|---|",
        f"| read `{READ}` (in process): the library's reader | {r['read_reader_s']:.3f} | |",
        f"| read `{READ}` (in process): trimesh, `process=False` | {r['read_trimesh_s']:.3f} "
        f"| reader at least as fast: {r['read_ratio']:.2f}x, {verdict(r['read_ratio'] >= 1)} |",
        f"| `stochlap features` on {len(DATASET)} meshes, first run | "
        f"{r['features_first_s']:.2f} | |",
        f"| the same, rerun with nothing to do | {r['features_rerun_s']:.2f} | at least 5x "
        f"faster: {r['rerun_ratio']:.1f}x, {verdict(r['rerun_ratio'] >= 5)} |",
        f"| `MeshFeatureDataset` of the {len(DATASET)} meshes, empty cache (in process) | "
        f"{r['dataset_first_s']:.2f} | |",
        f"| the same, fully cached (in process) | {r['dataset_cached_s']:.2f} | under 2 s: "
        f"{verdict(r['dataset_cached_s'] < 2)} |",
        "",
        f"Meshes: {', '.join(DATASET)}.",
    ]
    path.write_text("\n".join(lines) + "\n")
    path.with_suffix(".json").write_text(json.dumps(r, indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
