"""``RESULTS.md`` from the results of a run: one function per section, one per table row.

Everything here reads the result dicts (the ``results`` of ``results.json``) and the command
line of the run; nothing measures. :func:`render_report` is the whole text;
:func:`write_outputs` writes it with ``results.json`` beside it. The targets and the numbers
checked against them are in ``summary.py``, the plot in ``plot.py``.
"""

from __future__ import annotations

import json
from pathlib import Path

import benchlib
from cases import (
    CONTENTION_BACKGROUND,
    LARGE_MESH,
    MAIN_MESHES,
    MAIN_SCALES,
    NUM_EIGENPAIRS,
    NUM_TIMES,
    PAPER_HARDWARE,
    PAPER_TABLE_1,
    SPECTRAL_EXTRA_EIGSH,
    SPECTRAL_MESHES,
    find_result,
    mesh_name,
    ok_results,
)
from cells import entries_at_k, error_row, mib, ratio, seconds, table
from child import MAX_TIMED_RUNS
from summary import (
    TARGET_FIRST_CALL_SECONDS,
    TARGET_PER_VERTEX_SPREAD,
    contention_lines,
    large_mesh_line,
    per_round_spreads,
    per_vertex_spread,
    speedup_line,
    speedups,
)

METHOD_NAMES = {
    "numba": "library (numba kernel)",
    "torch": "library (torch ops)",
    "scipy": "scipy.sparse baseline",
    "dense_eigh": "dense torch.linalg.eigh",
    "eigsh_hks": f"scipy eigsh ({NUM_EIGENPAIRS} pairs) + HKS",
}

# Column headers of the tables.
MAIN_COLUMNS = (
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
)
FIRST_CALL_COLUMNS = (
    "variant",
    "import torch (s)",
    "import stochlap_torch (s)",
    "first call (s)",
    "steady call (s)",
    "first - steady (s)",
    "numba cache index files",
)
CONTENTION_COLUMNS = (
    "mesh",
    "method",
    "threads",
    "quiet median (s)",
    "loaded median (s)",
    "slow-down",
)
TABLE1_COLUMNS = (
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
)
SPECTRAL_COLUMNS = (
    "mesh",
    "V",
    "dense eigh (s)",
    "RSS (MiB)",
    "eigsh + HKS (s)",
    "RSS (MiB)",
    "library (s)",
    "RSS (MiB)",
    "eigsh+HKS / library",
)
SCALING_COLUMNS = (
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
)


def _section(results, name: str) -> list[dict]:
    return [r for r in results if r["case"]["section"] == name]


# --------------------------------------------------------------------------------------------
# Machine


def machine_section(results, header: dict, args) -> list[str]:
    """Date, command, CPU, versions, threads, load and how runs were repeated."""
    mode = "quick" if args.quick else "full"
    versions = ", ".join(f"{k} {v}" for k, v in header["versions"].items())
    layers = {r.get("numba_threading_layer") for r in results if r.get("numba_threading_layer")}
    load_end = header.get("load_at_end")
    return [
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
        "`n` says how many. Every case runs in a fresh process; peak RSS is that process's "
        "high-water mark from the end of the warm-up to the end of the timed runs (interpreter, "
        "torch and the mesh included); 'peak - before' subtracts the RSS at the start of the "
        "timed runs.",
        "",
    ]


# --------------------------------------------------------------------------------------------
# Library vs scipy vs torch ops


def _main_row(name: str, result: dict, scipy: dict | None) -> list:
    """Time, speed-up, memory, saliency gap and fill of one main case."""
    case = result["case"]
    first = [name, METHOD_NAMES[case["method"]], case["threads"]]
    if not result.get("ok"):
        return error_row([*first, "-"], result, len(MAIN_COLUMNS))
    speedup = scipy["median_s"] / result["median_s"] if scipy else None
    gap = result.get("saliency_gap")
    return [
        *first,
        len(result["times_s"]),
        seconds(result["median_s"]),
        seconds(result["min_s"]),
        ratio(speedup),
        mib(result["peak_rss"]),
        mib(result["peak_rss"] - result["base_rss"]),
        "-" if gap is None else f"{gap:.1e}",
        entries_at_k(result),
    ]


def main_section(results) -> list[str]:
    """The main comparison on spot and gargoyle_50k, and the large mesh."""
    main = _section(results, "main")
    if not main:
        return []
    rows = []
    for name in (*MAIN_MESHES, LARGE_MESH):
        mesh = f"file:{name}"
        scipy = find_result(results, section="main", mesh=mesh, method="scipy")
        rows += [_main_row(name, r, scipy) for r in main if r["case"]["mesh"] == mesh]
    lines = [f"## Library vs scipy baseline vs torch ops (K = {MAIN_SCALES})", ""]
    lines += table(MAIN_COLUMNS, rows)
    lines += [f"- **{speedup_line(name, value)}.**" for name, value in speedups(results).items()]
    large = large_mesh_line(results)
    return [*lines, *([large] if large else []), ""]


# --------------------------------------------------------------------------------------------
# First call


def _first_call_row(result: dict) -> list:
    """Import times, first and steady call, and numba's cache files of one variant."""
    variant = result["case"]["info"]["variant"]
    if not result.get("ok"):
        return error_row([variant], result, len(FIRST_CALL_COLUMNS))
    first, steady = result["first_call_s"], result["steady_s"]
    cache = f"{result['cache_index_files_before']} -> {result['cache_index_files_after']}"
    return [
        variant,
        seconds(result["torch_import_s"]),
        seconds(result["library_import_s"]),
        seconds(first),
        seconds(steady),
        seconds(first - steady),
        cache,
    ]


def first_call_section(results) -> list[str]:
    """Cold-start latency in a fresh process, per numba cache state."""
    first = _section(results, "first-call")
    if not first:
        return []
    lines = ["## First-call latency (fresh process, spot.obj, K = 8)", ""]
    lines += table(FIRST_CALL_COLUMNS, [_first_call_row(r) for r in first])
    warmed = [r for r in first if r["case"]["numba_cache"] == "warmed" and r.get("ok")]
    if warmed:
        worst = max(warmed, key=lambda r: r["first_call_s"])
        verdict = "met" if worst["first_call_s"] <= TARGET_FIRST_CALL_SECONDS else "NOT met"
        warmup = warmed[0].get("warmup_s")
        lines += [
            "",
            f"- `stochlap warmup` filled the fresh cache in "
            f"{'-' if warmup is None else f'{warmup:.1f}'} s (once per machine); after it "
            f"the slowest first call is {worst['first_call_s']:.2f} s "
            f"({worst['case']['info']['path']}; target <= "
            f"{TARGET_FIRST_CALL_SECONDS:.0f} s for any dtype and path: {verdict}).",
            "",
        ]
    return lines


# --------------------------------------------------------------------------------------------
# Contention


def contention_section(results) -> list[str]:
    """The target mesh quiet (main section) and beside busy processes, library and scipy."""
    loaded = _section(results, "contention")
    if not loaded:
        return []
    rows = []
    for result in loaded:
        case = result["case"]
        quiet = find_result(
            results,
            section="main",
            mesh=case["mesh"],
            method=case["method"],
            threads=case["threads"],
        )
        name = [mesh_name(case["mesh"]), METHOD_NAMES[case["method"]], case["threads"]]
        if not result.get("ok") or quiet is None:
            rows.append(error_row(name, result, len(CONTENTION_COLUMNS)))
            continue
        rows.append(
            [
                *name,
                seconds(quiet["median_s"]),
                seconds(result["median_s"]),
                ratio(result["median_s"] / quiet["median_s"]),
            ]
        )
    lines = [
        f"## Under contention ({CONTENTION_BACKGROUND} busy processes on the same cores, "
        f"K = {MAIN_SCALES})",
        "",
    ]
    lines += table(CONTENTION_COLUMNS, rows)
    return [*lines, *contention_lines(results), ""]


# --------------------------------------------------------------------------------------------
# Paper Table 1


def _table1_row(model, paper_vertices, num_scales, paper_seconds, name, results, table1):
    """The library and scipy beside the paper's time for one mesh; None if it did not run."""
    mesh = f"file:{name}"
    library = find_result(results, section="table1", mesh=mesh, method="numba")
    scipy = find_result(results, section="table1", mesh=mesh, method="scipy")
    failed = [r for r in table1 if r["case"]["mesh"] == mesh and not r.get("ok")]
    if not (library or scipy or failed):
        return None
    note = "; ".join(f"{r['case']['method']} error: {r.get('error')}" for r in failed)
    vertices = (library or scipy or {}).get("vertices", "-")
    first = [model, name, paper_vertices, vertices, num_scales, seconds(paper_seconds)]
    if not library:
        return [*first, note or "-", seconds(scipy["median_s"]) if scipy else "-", "-", "-"]
    return [
        *first,
        seconds(library["median_s"]),
        seconds(scipy["median_s"]) if scipy else "-",
        ratio(paper_seconds / library["median_s"]),
        entries_at_k(library),
    ]


def table1_section(results, left_out: list[dict]) -> list[str]:
    """The paper's Table 1 models at the paper's K, with the paper's times."""
    table1 = _section(results, "table1")
    if not (table1 or any(x["label"].startswith("table1") for x in left_out)):
        return []
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
                    seconds(paper_seconds),
                    "-",
                    "-",
                    "-",
                    "-",
                ]
            )
        for name in files:
            row = _table1_row(
                model, paper_vertices, num_scales, paper_seconds, name, results, table1
            )
            rows += [row] if row else []
    lines = [
        "## Paper Table 1 meshes",
        "",
        f"The paper's times were measured on {PAPER_HARDWARE}; the hardware, the implementation "
        "and in most rows the mesh differ (see `../shared/meshes/SOURCES.md`), so the ratio is "
        "a rough indication only.",
        "",
    ]
    return lines + table(TABLE1_COLUMNS, rows)


# --------------------------------------------------------------------------------------------
# Spectral baselines


def _spectral_cells(result: dict | None) -> tuple[str, str]:
    """``(median (n=runs), peak RSS)`` of one spectral or library case."""
    if result is None:
        return "-", "-"
    if not result.get("ok"):
        return f"error: {result.get('error')}", "-"
    return f"{seconds(result['median_s'])} (n={len(result['times_s'])})", mib(result["peak_rss"])


def _spectral_row(name: str, found: dict) -> list:
    """Dense eigh, eigsh + HKS and the library on one mesh, and eigsh+HKS / library."""
    vertices = next((r["vertices"] for r in found.values() if r.get("ok")), "-")
    eigsh, library = found.get("eigsh_hks", {}), found.get("numba", {})
    value = "-"
    if eigsh.get("ok") and library.get("ok"):
        value = ratio(eigsh["median_s"] / library["median_s"])
    cells = [_spectral_cells(found.get(key)) for key in ("dense_eigh", "eigsh_hks", "numba")]
    return [name, vertices, *(cell for pair in cells for cell in pair), value]


def spectral_section(results) -> list[str]:
    """Dense eigh and eigsh + HKS against the library, time and peak RSS."""
    spectral = _section(results, "spectral")
    if not spectral:
        return []
    rows = []
    for name in SPECTRAL_MESHES + SPECTRAL_EXTRA_EIGSH:
        found = {r["case"]["method"]: r for r in spectral if r["case"]["mesh"] == f"file:{name}"}
        rows += [_spectral_row(name, found)] if found else []
    lines = [
        "## Spectral baselines",
        "",
        f"Dense: every eigenpair of the cotangent Laplacian (`torch.linalg.eigh`, O(V^3)); "
        f"eigsh: {NUM_EIGENPAIRS} eigenpairs by scipy shift-invert ARPACK and the heat "
        f"kernel signature at {NUM_TIMES} times (`stochlap_torch.baselines`). Library: "
        f"K = {MAIN_SCALES}, numba kernel.",
        "",
    ]
    return lines + table(SPECTRAL_COLUMNS, rows)


# --------------------------------------------------------------------------------------------
# Scaling series


def _scaling_intro(args) -> list[str]:
    """The heading, the memory guard and (with rounds) how rounds are pooled."""
    lines = [
        f"## Scaling series (K = {args.scaling_scales}, {args.scaling_dtype} vertices, numba "
        "kernel unless stated; the scipy baseline always computes in float64)",
        "",
        "The library's memory guard is switched off here (`max_memory` huge): its default "
        "budget is half the RAM, and what it counts for these streamed runs (outputs and "
        "scratch rows; column 'library estimate', `stochlap_torch.diffusion.streamed_memory`) "
        "is shown beside the measured peak. The harness instead skips a case whose peak, "
        "extrapolated from the smaller meshes, would not fit in the available memory, and a "
        f"watchdog aborts a case that drives the machine below {args.min_free_gb} GiB free.",
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
    return lines


def _scaling_row(result: dict) -> list:
    """Time, time per vertex, memory, memory per vertex and fill of one scaling case."""
    case = result["case"]
    method = METHOD_NAMES[case["method"]]
    if not result.get("ok"):
        first = [mesh_name(case["mesh"]), benchlib.mesh_vertices(case["mesh"]) or "-", method]
        return error_row([*first, "-"], result, len(SCALING_COLUMNS))
    vertices = result["vertices"]
    delta = result["peak_rss"] - result["base_rss"]
    estimate = result.get("library_estimate_bytes")
    return [
        mesh_name(case["mesh"]),
        f"{vertices:,}",
        method,
        len(result["times_s"]),
        seconds(result["median_s"]),
        seconds(result["min_s"]),
        f"{1e6 * result['median_s'] / vertices:.2f}",
        mib(result["peak_rss"]),
        mib(delta),
        f"{delta / vertices:.0f}",
        "-" if estimate is None else f"{estimate / 2**30:.2f} GiB",
        entries_at_k(result),
    ]


def _scaling_order(result: dict):
    case = result["case"]
    return case["method"] != "numba", case["method"], benchlib.mesh_vertices(case["mesh"]) or 0


def _spread_lines(results) -> list[str]:
    """Time per vertex max / min over the series, the icospheres and each round alone."""
    lines = []
    for icospheres_only in (False, True):
        spread = per_vertex_spread(results, icospheres_only)
        if spread:
            what = "icospheres only" if icospheres_only else "whole series"
            verdict = "met" if spread[0] <= TARGET_PER_VERTEX_SPREAD else "NOT met"
            lines.append(
                f"- **Time per vertex, max / min ({what}, {spread[1]} meshes): "
                f"{spread[0]:.2f} (target <= {TARGET_PER_VERTEX_SPREAD}: "
                f"{verdict}).**"
            )
    spreads = per_round_spreads(results)
    if len(spreads) > 1:
        each = ", ".join(f"{x:.2f}" for x in spreads)
        lines.append(f"- Time per vertex, max / min, each round alone (whole series): {each}.")
    return lines


def _entries_table(results) -> list[str]:
    """Mean stored entries per row of every ``F^(k)`` on each mesh of the library's series."""
    rows = [
        r
        for r in ok_results(results, section="scaling", method="numba")
        if r.get("entries_per_row")
    ]
    if not rows:
        return []
    num_scales = max(len(r["entries_per_row"]) for r in rows)
    scales = range(1, num_scales + 1)
    cells = [
        [mesh_name(r["case"]["mesh"])]
        + [f"{r['entries_per_row'].get(str(k), float('nan')):.1f}" for k in scales]
        for r in rows
    ]
    lines = ["", "Mean stored entries per row of F^(k) (library, numba kernel):", ""]
    return lines + table(["mesh"] + [f"k={k}" for k in scales], cells)


def scaling_section(results, args) -> list[str]:
    """Time and memory against size, the per-vertex spread and the fill of ``F^(k)``."""
    scaling = _section(results, "scaling")
    if not scaling:
        return []
    rows = [_scaling_row(r) for r in sorted(scaling, key=_scaling_order)]
    lines = _scaling_intro(args) + table(SCALING_COLUMNS, rows)
    lines += _spread_lines(results) + _entries_table(results)
    return [*lines, "![time vs vertices](scaling.png)", ""]


# --------------------------------------------------------------------------------------------
# The whole report


def failures_section(results, left_out: list[dict]) -> list[str]:
    """Every failed case with its error, and every case left out with the reason."""
    failures = [r for r in results if not r.get("ok")]
    if not (failures or left_out):
        return []
    lines = ["## Failed and skipped cases", ""]
    lines += [f"- {r['case']['label']}: **{r.get('error')}**" for r in failures]
    lines += [f"- {x['label']}: skipped ({x['reason']})" for x in left_out]
    return [*lines, ""]


def render_report(
    results: list[dict], left_out: list[dict], header: dict, args, finished: bool
) -> str:
    """The text of ``RESULTS.md``."""
    lines = ["# stochlap_torch: speed and scale", ""]
    if not finished:
        lines += ["**Run in progress or interrupted: the tables below are partial.**", ""]
    lines += machine_section(results, header, args)
    lines += main_section(results)
    lines += contention_section(results)
    lines += first_call_section(results)
    lines += table1_section(results, left_out)
    lines += spectral_section(results)
    lines += scaling_section(results, args)
    lines += failures_section(results, left_out)
    return "\n".join(lines)


def write_outputs(
    results: list[dict], left_out: list[dict], header: dict, args, finished: bool
) -> None:
    """``RESULTS.md`` and ``results.json`` in ``args.output_dir``."""
    out = Path(args.output_dir)
    (out / "RESULTS.md").write_text(render_report(results, left_out, header, args, finished))
    data = {"header": header, "results": results, "left_out": left_out}
    (out / "results.json").write_text(json.dumps(data, indent=1, default=str))
