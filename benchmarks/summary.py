"""What a run concludes: the targets of the issue and the numbers checked against them.

The speed-up over the scipy baseline on the main meshes, and the spread of the time per vertex
over the scaling series (pooled, and within each round); ``report.py`` prints them under its
tables and ``run.py`` at the end of a run.
"""

from __future__ import annotations

from cases import LARGE_MESH, MAIN_MESHES, find_result, ok_results

#: The speed-up target (issue 3) is set on this mesh; spot is reported beside it.
TARGET_SPEEDUP_MESH = "gargoyle_50k.off"
TARGET_SPEEDUP = 10.0
TARGET_LARGE_SECONDS = 5.0
TARGET_LARGE_GIB = 3.0
TARGET_PER_VERTEX_SPREAD = 1.5
#: Issue 15: the first call of any dtype and path after ``stochlap warmup``.
TARGET_FIRST_CALL_SECONDS = 3.0


def main_threads(results) -> int:
    """The thread count of the main comparison (its largest)."""
    threads = [r["case"]["threads"] for r in results if r["case"]["section"] == "main"]
    return max(threads) if threads else 1


def speedups(results) -> dict[str, float]:
    """``{mesh: scipy median / library median}`` for the main comparison."""
    ratios = {}
    for name in MAIN_MESHES:
        mesh = f"file:{name}"
        library = find_result(
            results, section="main", mesh=mesh, method="numba", threads=main_threads(results)
        )
        scipy = find_result(results, section="main", mesh=mesh, method="scipy")
        if library and scipy:
            ratios[name] = scipy["median_s"] / library["median_s"]
    return ratios


def speedup_line(name: str, value: float) -> str:
    """How a main mesh's speed-up reads in the log and the report, with the verdict where the
    target applies (:data:`TARGET_SPEEDUP_MESH`)."""
    line = f"{name}: library {value:.2f}x faster than the scipy baseline"
    if name != TARGET_SPEEDUP_MESH:
        return f"{line} (no target: the {TARGET_SPEEDUP:.0f}x target is on {TARGET_SPEEDUP_MESH})"
    verdict = "met" if value >= TARGET_SPEEDUP else "NOT met"
    return f"{line} (target >= {TARGET_SPEEDUP:.0f}x: {verdict})"


def contention_lines(results) -> list[str]:
    """The speed-up over scipy with both beside busy processes, against the quiet target."""
    mesh = f"file:{TARGET_SPEEDUP_MESH}"
    library = find_result(results, section="contention", mesh=mesh, method="numba")
    scipy = find_result(results, section="contention", mesh=mesh, method="scipy")
    if not (library and scipy):
        return []
    value = scipy["median_s"] / library["median_s"]
    verdict = "met" if value >= TARGET_SPEEDUP else "NOT met"
    return [
        f"- **{TARGET_SPEEDUP_MESH} under contention: library {value:.2f}x faster than the "
        f"scipy baseline (target >= {TARGET_SPEEDUP:.0f}x, as in a quiet run: {verdict}).**"
    ]


def per_round_spreads(results) -> list[float]:
    """Time per vertex max / min of the library's scaling series within each round alone."""
    rows = ok_results(results, section="scaling", method="numba")
    rounds = sorted({r for row in rows for r in row.get("round_medians_s", {})}, key=int)
    spreads = []
    for r in rounds:
        per_vertex = [
            row["round_medians_s"][r] / row["vertices"]
            for row in rows
            if r in row.get("round_medians_s", {})
        ]
        if len(per_vertex) > 1:
            spreads.append(max(per_vertex) / min(per_vertex))
    return spreads


def per_vertex_spread(results, icospheres_only=False) -> tuple[float, int] | None:
    """``(max / min of median seconds per vertex, number of meshes)`` over the scaling
    series (library, numba kernel)."""
    rows = ok_results(results, section="scaling", method="numba")
    if icospheres_only:
        rows = [r for r in rows if r["case"]["mesh"].startswith("icosphere")]
    per_vertex = [r["median_s"] / r["vertices"] for r in rows]
    if len(per_vertex) < 2:
        return None
    return max(per_vertex) / min(per_vertex), len(per_vertex)


def large_mesh_line(results) -> str | None:
    """The verdict on the large-mesh targets (time and peak RSS)."""
    large = find_result(results, section="main", mesh=f"file:{LARGE_MESH}", method="numba")
    if not large:
        return None
    median, gib = large["median_s"], large["peak_rss"] / 2**30
    met = median < TARGET_LARGE_SECONDS and gib < TARGET_LARGE_GIB
    return (
        f"- **{LARGE_MESH} (float64, library only): median {median:.2f} s, "
        f"peak RSS {gib:.2f} GiB (targets < {TARGET_LARGE_SECONDS:.0f} s and "
        f"< {TARGET_LARGE_GIB:.0f} GiB: {'met' if met else 'NOT met'}).**"
    )
