"""Speed and scale benchmark of stochlap_torch: one command, one report.

    python benchmarks/run.py [--quick] [--max-vertices N] [--threads N] [--sections ...]
    python benchmarks/run.py --report-from benchmarks/results.json --output-dir DIR

Every case runs in a fresh Python process (so that its peak RSS is its own, and the first
call is measured cold), with the thread pools pinned. The parent streams progress to stderr,
records a failing or timed-out case as an error and carries on, and rewrites
``benchmarks/RESULTS.md``, ``benchmarks/results.json`` and ``benchmarks/scaling.png`` after
every case. See ``benchmarks/README.md`` for the sections and columns.

The cases are in ``cases.py``, the parent's side of a measurement in ``measure.py``, the
child's in ``child.py``, and the report in ``report.py`` and ``plot.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import shutil
import sys
import tempfile
import time
from dataclasses import asdict
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
if str(BENCH_DIR) not in sys.path:
    sys.path.insert(0, str(BENCH_DIR))

# No torch import at module level in any of these: the parent stays light, and the child
# times its own `import torch`.
import benchlib  # noqa: E402
import measure  # noqa: E402
import report  # noqa: E402
import summary  # noqa: E402
from cases import SCALING_DTYPE, SCALING_SCALES, SECTIONS, build_cases  # noqa: E402
from child import MIN_TIMED_SECONDS, child_main, log  # noqa: E402
from plot import write_plot  # noqa: E402


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    add = parser.add_argument
    add(
        "--quick",
        action="store_true",
        help="3 repeats, 60 s per case, dense eigh up to 5000 vertices",
    )
    add(
        "--max-vertices",
        type=int,
        default=11_000_000,
        help="skip meshes with more vertices (default 11M: everything, "
        "including the 10.5M-vertex icosphere)",
    )
    add(
        "--threads",
        type=int,
        default=benchlib.default_threads(),
        help="threads for torch, numba, OpenMP, MKL, OpenBLAS (default: all logical cores)",
    )
    add("--repeats", type=int, help="timed runs per case (default 5; quick 3)")
    add(
        "--budget",
        type=float,
        help="seconds of timed runs per case before repeats are cut (default 300; quick 60)",
    )
    add(
        "--min-seconds",
        type=float,
        help=f"timed seconds a multiscale case adds runs up to (default {MIN_TIMED_SECONDS:g}; "
        "quick 0.3)",
    )
    add(
        "--rounds",
        type=int,
        help="visits of the library's scaling series, every mesh in each (default 3; quick 1)",
    )
    add(
        "--sections",
        default=",".join(SECTIONS),
        help=f"comma-separated subset of {','.join(SECTIONS)}",
    )
    add("--only", help="regular expression on case labels")
    add(
        "--scaling-scales",
        type=int,
        default=SCALING_SCALES,
        help=f"K of the scaling series (default {SCALING_SCALES})",
    )
    add(
        "--scaling-dtype",
        choices=("float32", "float64"),
        default=SCALING_DTYPE,
        help=f"vertex dtype of the library in the scaling series (default {SCALING_DTYPE}: "
        "in float64 the 10.5M case needs about 24 GiB)",
    )
    add(
        "--dense-max-vertices",
        type=int,
        help="largest mesh for dense eigh (default 10500; quick 5000)",
    )
    add(
        "--baseline-max-vertices",
        type=int,
        default=250_000,
        help="largest mesh of the scaling series for the scipy and torch paths (default 250000)",
    )
    add(
        "--case-timeout",
        type=float,
        default=4 * 3600,
        help="seconds before a case is killed (default 4 h)",
    )
    add(
        "--min-free-gb",
        type=float,
        default=1.0,
        help="abort a case when available memory falls below this",
    )
    add(
        "--output-dir",
        default=str(BENCH_DIR),
        help="where RESULTS.md, results.json and scaling.png go",
    )
    add(
        "--report-from",
        metavar="RESULTS_JSON",
        help="run nothing: render RESULTS.md and scaling.png into --output-dir from the "
        "results.json of an earlier run, with the options of that run's command",
    )
    add("--child", help=argparse.SUPPRESS)
    return parser


def parse_args(argv=None):
    """The options, with the defaults that depend on ``--quick`` filled in."""
    parser = _parser()
    args = parser.parse_args(argv)
    quick = args.quick
    defaults = {
        "repeats": 3 if quick else 5,
        "budget": 60.0 if quick else 300.0,
        "min_seconds": 0.3 if quick else MIN_TIMED_SECONDS,
        "rounds": 1 if quick else 3,
        "dense_max_vertices": 5000 if quick else 10_500,
    }
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    args.sections = [s.strip() for s in args.sections.split(",") if s.strip()]
    unknown = set(args.sections) - set(SECTIONS)
    if unknown:
        parser.error(f"unknown sections {sorted(unknown)}; choose from {SECTIONS}")
    return args


def rerender(args) -> int:
    """``--report-from``: RESULTS.md and scaling.png from a results.json, nothing run.

    The report's wording depends on the run's options (quick mode, repeats, rounds, scaling K
    and dtype, threads); they are parsed again from the command the header records. A run is
    taken as finished when its header has the load at the end.
    """
    data = json.loads(Path(args.report_from).read_text())
    header = data["header"]
    command = shlex.split(header["command"])[2:]  # after "python benchmarks/run.py"
    run_args = parse_args([*command, "--threads", str(header["threads"])])
    run_args.output_dir = args.output_dir
    Path(args.output_dir).mkdir(parents=True, exist_ok=True)
    finished = "load_at_end" in header
    text = report.render_report(data["results"], data["left_out"], header, run_args, finished)
    (Path(args.output_dir) / "RESULTS.md").write_text(text)
    write_plot(data["results"], run_args)
    print(f"wrote {Path(args.output_dir) / 'RESULTS.md'} and scaling.png from {args.report_from}")
    return 0


class _Run:
    """The state of a run: its options, the results so far, the cases left out and where the
    children write."""

    def __init__(self, args, left_out: list[dict]):
        self.args, self.left_out = args, left_out
        self.results: list[dict] = []
        self.workdir = Path(tempfile.mkdtemp(prefix="stochlap-bench-"))
        self.cache_dirs = {"run": str(self.workdir / "numba-cache")}
        self.started = time.perf_counter()

    def case(self, case, number: int, total: int) -> None:
        """Run case ``number`` of ``total`` (unless the memory guard skips it) and log it."""
        results, args = self.results, self.args
        reason = measure.memory_guard(case, results, args)
        if reason:
            log(f"[{number}/{total}] {case.label}: SKIPPED ({reason})")
            self.left_out.append({"label": case.label, "reason": reason})
            return
        log(f"[{number}/{total}] {case.label} (elapsed {time.perf_counter() - self.started:.0f} s)")
        try:
            result = measure.run_case(case, args, self.workdir, self.cache_dirs)
        except OSError as exc:
            result = {"ok": False, "error": f"could not run the case: {exc}", "case": asdict(case)}
        folded = measure.record(results, result, case, args.threads)
        _log_result(result, folded)
        if case.section == "main" and case.method == "scipy":
            value = summary.speedups(results).get(case.mesh[5:])
            if value is not None:
                log(f"    == {summary.speedup_line(case.mesh[5:], value)}")


def _log_result(result: dict, folded: bool) -> None:
    if result.get("ok") and "median_s" in result:
        log(
            f"    -> median {result['median_s']:.3f} s over {len(result['times_s'])} runs, "
            f"peak RSS {result['peak_rss'] / 2**20:.0f} MiB"
            + (" (folded into the earlier rounds)" if folded else "")
        )
    elif result.get("ok"):
        log(f"    -> first call {result['first_call_s']:.3f} s, steady {result['steady_s']:.3f} s")
    else:
        log(f"    -> FAILED: {result.get('error')}")


def _summary(results, left_out, header, args) -> None:
    """The verdicts and counts, on stdout."""
    for name, value in summary.speedups(results).items():
        print(summary.speedup_line(name, value))
    spread = summary.per_vertex_spread(results)
    if spread:
        print(
            f"time per vertex max/min over the scaling series: {spread[0]:.2f} "
            f"(target <= {summary.TARGET_PER_VERTEX_SPREAD})"
        )
    failed = sum(not r.get("ok") for r in results)
    wrote = Path(args.output_dir) / "RESULTS.md"
    print(
        f"{len(results)} cases run, {failed} failed, {len(left_out)} skipped in "
        f"{header['total_wall_s']:.0f} s; wrote {wrote}"
    )


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.child:
        return child_main(args.child)
    if args.report_from:
        return rerender(args)
    Path(args.output_dir).mkdir(parents=True, exist_ok=True)
    if not benchlib.MESHES_DIR.is_dir():
        log(
            f"NOTE: {benchlib.MESHES_DIR} not found: every case on a shared mesh is skipped "
            "(spot.obj falls back to the copy bundled with the library)"
        )
    cases, left_out = build_cases(args)
    header = measure.machine_header(args)
    log(
        f"{len(cases)} cases, {len(left_out)} skipped; {args.threads} thread(s); "
        f"{header['cpu']}; load average {header['load_at_start'][0]:.2f}"
    )
    run = _Run(args, left_out)
    finished = False
    try:
        for number, case in enumerate(cases, start=1):
            run.case(case, number, len(cases))
            report.write_outputs(run.results, left_out, header, args, finished=False)
        finished = True
    finally:
        header["load_at_end"] = os.getloadavg()
        header["total_wall_s"] = time.perf_counter() - run.started
        report.write_outputs(run.results, left_out, header, args, finished)
        write_plot(run.results, args)
        shutil.rmtree(run.workdir, ignore_errors=True)
    _summary(run.results, left_out, header, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
