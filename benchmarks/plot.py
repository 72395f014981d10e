"""``scaling.png``: log-log median time against vertices, from the results of a run.

Lines are the scaling series of each method, hollow markers the other meshes (main, Table 1 at
the paper's K, spectral), and a dashed line proportional to ``V`` through the smallest library
point. Only cases run at the run's thread count are drawn.
"""

from __future__ import annotations

from pathlib import Path

from cases import MAIN_SCALES, ok_results
from report import METHOD_NAMES

#: Legend label, colour and marker of each method.
STYLES = {
    "numba": ("library (numba kernel)", "C0", "o"),
    "torch": ("library (torch ops)", "C1", "s"),
    "scipy": ("scipy.sparse baseline", "C2", "^"),
    "eigsh_hks": (METHOD_NAMES["eigsh_hks"], "C3", "D"),
    "dense_eigh": (METHOD_NAMES["dense_eigh"], "C4", "v"),
}


def _method_points(results, method: str, threads: int):
    """``(scaling series points sorted by size, other points)`` of one method, or None."""
    rows = [
        r
        for r in ok_results(results, method=method, threads=threads)
        if r["case"]["kind"] != "first_call"
    ]
    if not rows:
        return None
    series = sorted(
        (r["vertices"], r["median_s"]) for r in rows if r["case"]["section"] == "scaling"
    )
    others = [(r["vertices"], r["median_s"]) for r in rows if r["case"]["section"] != "scaling"]
    return series, others


def _plot_method(axes, method: str, series, others, args) -> None:
    label, colour, marker = STYLES[method]
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


def _linear_reference(axes, results) -> None:
    """A line ``time ∝ V`` through the smallest mesh of the library's scaling series (else of
    any library multiscale run), across the vertex range of every successful case."""
    library = sorted(
        (r["vertices"], r["median_s"])
        for r in ok_results(results, section="scaling", method="numba")
    )
    library = library or sorted(
        (r["vertices"], r["median_s"])
        for r in ok_results(results, method="numba")
        if r["case"]["kind"] == "multiscale"
    )
    vertices = sorted(r["vertices"] for r in results if r.get("ok") and "vertices" in r)
    if library and vertices:
        v0, t0 = library[0]
        span = [vertices[0], vertices[-1]]
        axes.plot(
            span, [t0 * v / v0 for v in span], "k--", lw=1, label="linear reference (time ∝ V)"
        )


def _decorate(axes, threads: int) -> None:
    axes.set_xscale("log")
    axes.set_yscale("log")
    axes.set_xlabel("vertices")
    axes.set_ylabel("median time (s)")
    axes.set_title(
        f"stochlap_torch, {threads} thread(s); hollow markers: other meshes "
        f"(main and spectral K={MAIN_SCALES}, Table 1 the paper's K)",
        fontsize=9,
    )
    axes.grid(True, which="both", alpha=0.3)
    axes.legend(fontsize=7)


def write_plot(results: list[dict], args) -> None:
    """``scaling.png`` in ``args.output_dir``: every successful multiscale and spectral case
    at ``args.threads`` threads (nothing is written if there is none)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(8, 6))
    plotted = False
    for method in STYLES:
        points = _method_points(results, method, args.threads)
        if points:
            _plot_method(axes, method, *points, args)
            plotted = True
    _linear_reference(axes, results)
    if plotted:
        _decorate(axes, args.threads)
        figure.tight_layout()
        figure.savefig(Path(args.output_dir) / "scaling.png", dpi=120)
    plt.close(figure)
