"""Is the robust variant discretisation-robust? The benchmark of GitHub issue 14.

Measures the library's public API (``variant="robust"`` against the paper's variant, the heat
kernel signature and Lee et al.'s saliency, all computed in the same run) and writes
``benchmarks/ROBUST.md`` (tables and verdicts, :mod:`robust_report`) and
``benchmarks/robust.json`` (raw numbers). Sections:

* ``features``: features of a mesh A and of an isotropic remeshing B to the same vertex count
  (ACVD) moved by a random rotation, uniform scale and translation; mean per-channel Spearman
  between A's values carried to B's vertices (closest point, barycentric) and B's own, and
  nearest-neighbour descriptor matching.
* ``saliency``: saliency of the full mesh against that of its quadric decimations to 1/3 and
  1/10 of the vertices and of its ACVD remeshing (nearest-vertex transfer, no smoothing), and
  against vertex valence.
* ``subdec``: as ``features``, with B = midpoint subdivision then quadric decimation back to
  the vertex count: adaptive, anisotropic triangles, a harder route.
* ``speed``: each pipeline in a fresh process with pinned threads (median of 3 warm runs, peak
  RSS), once the machine is quiet; then time and memory per vertex up to 692k vertices
  (:mod:`robust_speed`).

Remeshed copies are cached in ``benchmarks/.cache/``. Run from the repository root::

    python benchmarks/robust.py [--sections features,saliency,subdec,speed] [--meshes NAMES]
                                [--out benchmarks/ROBUST.md] [--figure] [--report-only]

A partial run (``--sections``) replaces those sections in ``robust.json`` and keeps the others;
the report lists the command and commit of every run its sections come from.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from functools import cache
from pathlib import Path

import numpy as np
from robust_common import (
    BENCH,
    MESH_SET,
    NN_RADIUS,
    SECTIONS,
    THREADS,
    available,
    channel_spearman,
    copy_of,
    load,
    log,
    log_hks,
    nn_match,
    paper_features,
    pin_threads,
    robust_features,
    saliency,
    seed_of,
    spearman,
    surface_area,
    valence,
)

# -- sections ----------------------------------------------------------------------------------

FEATURE_METHODS = ("robust", "hks", "paper")


@cache
def reference(name: str) -> dict:
    """Mesh A and its descriptors (shared by the ``features`` and ``subdec`` sections)."""
    v, f = load(name)
    hks, times = log_hks(v, f)
    return {
        "v": v,
        "f": f,
        "robust": robust_features(v, f),
        "hks": hks,
        "hks_times": times,
        "paper": paper_features(v, f),
    }


def descriptors_of_copy(v, f, method: str, ref: dict) -> np.ndarray:
    if method == "hks":
        return log_hks(v, f, times=ref["hks_times"])[0]
    return {"robust": robust_features, "paper": paper_features}[method](v, f)


def feature_row(name: str, route: str, channels: list[str]) -> dict:
    """One mesh of the ``features`` / ``subdec`` table."""
    from stochlap_torch.evaluation import correspondence, random_similarity

    ref = reference(name)
    va, fa = ref["v"], ref["f"]
    vb, fb = copy_of(name, va, fa, route)
    rotation, scale, shift = random_similarity(seed_of(name, route))
    moved = scale * vb @ rotation.T + shift  # what every method sees
    match = correspondence(vb, va, fa)  # on the un-moved copy: the transform is known
    radius = NN_RADIUS * math.sqrt(surface_area(va, fa))
    row = {"mesh": name, "V_A": len(va), "V_B": len(vb), "scale": scale, "seconds": {}}
    row.update(worst_channel="n/a", worst_rho=float("nan"), errors={})
    for method in FEATURE_METHODS:
        start = time.perf_counter()
        try:
            desc_b = descriptors_of_copy(moved, fb, method, ref)
        except Exception as exc:  # a method failing on a copy is a result: record it
            row[method] = row[f"nn_{method}"] = float("nan")
            row["errors"][method] = f"{type(exc).__name__}: {exc}"
            log(f"  {method} FAILED on {name} {route}: {row['errors'][method]}")
            continue
        row["seconds"][method] = time.perf_counter() - start
        per = channel_spearman(match.transfer(ref[method]), desc_b)
        row[method] = float(np.nanmean(per))
        row[f"nn_{method}"] = nn_match(
            ref[method], desc_b, va, match.points, radius, seed_of(name, route, "nn")
        )
        if method == "robust":
            row["per_channel"] = dict(zip(channels, per, strict=True))
            worst = int(np.nanargmin(per))
            row["worst_channel"], row["worst_rho"] = channels[worst], per[worst]
    log(
        f"{name:18s} {route:6s} V_B={len(vb):6d} | robust {row['robust']:.3f} HKS "
        f"{row['hks']:.3f} paper {row['paper']:.3f} | NN {row['nn_robust']:.3f} "
        f"{row['nn_hks']:.3f} {row['nn_paper']:.3f} | worst {row['worst_channel']} "
        f"{row['worst_rho']:.2f} | B times {row['seconds']}"
    )
    return row


def section_features(meshes, route: str = "acvd") -> dict:
    """Features of A against those of a remeshed, moved copy B (``route``)."""
    from stochlap_torch.features import feature_channel_names

    channels = feature_channel_names(variant="robust")
    present, skipped = available(meshes)
    rows = []
    for name in present:
        try:
            rows.append(feature_row(name, route, channels))
        except Exception as exc:  # record and go on: one bad mesh must not lose the run
            skipped.append({"mesh": name, "reason": f"{type(exc).__name__}: {exc}"})
            log(f"FAILED {name} {route}: {type(exc).__name__}: {exc}")
    return {"route": route, "channels": channels, "rows": rows, "skipped": skipped}


SALIENCY_COPIES = ("dec3", "dec10", "acvd")
SALIENCY_METHODS = ("robust", "lee", "paper")


def saliency_rows(name: str) -> list[dict]:
    """One mesh of the ``saliency`` table: a row per method."""
    from scipy.spatial import cKDTree

    va, fa = load(name)
    degree = valence(fa, len(va))
    copies = {kind: copy_of(name, va, fa, kind) for kind in SALIENCY_COPIES}
    nearest = {kind: cKDTree(vb).query(va)[1] for kind, (vb, _) in copies.items()}
    rows = []
    for method in SALIENCY_METHODS:
        full = saliency(va, fa, method)
        row = {"mesh": name, "method": method, "V": len(va), "valence": spearman(full, degree)}
        for kind, (vb, fb) in copies.items():
            row[kind] = spearman(full, saliency(vb, fb, method)[nearest[kind]])
            row[f"V_{kind}"] = len(vb)
        log(
            f"{name:18s} {method:6s} "
            + " ".join(f"{k} {row[k]:.3f}" for k in SALIENCY_COPIES)
            + f" | valence {row['valence']:+.3f}"
        )
        rows.append(row)
    return rows


def section_saliency(meshes) -> dict:
    present, skipped = available(meshes)
    rows = []
    for name in present:
        try:
            rows.extend(saliency_rows(name))
        except Exception as exc:
            skipped.append({"mesh": name, "reason": f"{type(exc).__name__}: {exc}"})
            log(f"FAILED {name} saliency: {type(exc).__name__}: {exc}")
    return {"copies": list(SALIENCY_COPIES), "rows": rows, "skipped": skipped}


# -- command line ------------------------------------------------------------------------------


def _section_speed() -> dict:
    from robust_speed import section_speed

    return section_speed()


def run_sections(sections, meshes, save) -> None:
    """Every requested section, in the order of :data:`SECTIONS`, with its wall time;
    ``save(results so far)`` after each, so that a late failure loses nothing."""
    runners = {
        "features": lambda: section_features(meshes, "acvd"),
        "saliency": lambda: section_saliency(meshes),
        "subdec": lambda: section_features(meshes, "subdec"),
        "speed": _section_speed,
    }
    done = {}
    for section in SECTIONS:
        if section in sections:
            log(f"\n## {section}")
            start = time.perf_counter()
            done[section] = runners[section]()
            done[section]["elapsed_s"] = time.perf_counter() - start
            log(f"## {section}: {done[section]['elapsed_s']:.0f} s")
            save(done)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--sections",
        default=",".join(SECTIONS),
        help=f"comma-separated subset of {','.join(SECTIONS)}",
    )
    parser.add_argument(
        "--meshes",
        default=",".join(MESH_SET),
        help="comma-separated mesh files (features, saliency, subdec)",
    )
    parser.add_argument(
        "--out",
        default=str(BENCH / "ROBUST.md"),
        help="report path; the raw numbers go to robust.json beside it",
    )
    parser.add_argument(
        "--figure", action="store_true", help="also draw docs/figures/variants_two_resolutions.png"
    )
    parser.add_argument(
        "--report-only",
        action="store_true",
        help="run nothing: rewrite the report from robust.json",
    )
    args = parser.parse_args(argv)
    sections = [s for s in args.sections.split(",") if s]
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        parser.error(f"unknown sections {unknown}; choose from {SECTIONS}")
    import robust_report

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    json_path = out.with_name("robust.json")
    if args.report_only:
        out.write_text(robust_report.render(json.loads(json_path.read_text())))
        return 0
    pin_threads()
    start = time.time()
    run = robust_report.run_info(sys.argv, THREADS)

    def save(done: dict) -> None:
        results = robust_report.merge(json_path, run, done, time.time() - start)
        json_path.write_text(json.dumps(results, indent=1, default=float) + "\n")
        out.write_text(robust_report.render(results))

    run_sections(sections, [m for m in args.meshes.split(",") if m], save)
    log(f"\nwrote {out} and {json_path} ({time.time() - start:.0f} s)")
    if args.figure:
        import robust_figure

        log(f"wrote {robust_figure.main([])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
