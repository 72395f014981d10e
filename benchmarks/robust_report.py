"""``ROBUST.md`` from the results of ``benchmarks/robust.py`` (no computation here).

:func:`run_info` describes a run (date, machine, versions, command), :func:`merge` folds the
sections of a run into the results of earlier runs (a section rerun replaces its old numbers),
:func:`render` writes the markdown: one table per section with a MEAN row, and a verdict line
per target of GitHub issue 14.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from pathlib import Path

import benchlib
import numpy as np

REPO = Path(__file__).resolve().parent.parent

#: Targets of issue 14.
FEATURE_SPEARMAN_TARGET = 0.9
SALIENCY_TARGET = 0.85
SPEED_TARGET = 10.0
#: Read as "about 0" for the rank correlation of saliency with vertex valence.
VALENCE_TOLERANCE = 0.05
#: "Linear" time and memory: per-vertex cost at the largest mesh within this factor of the
#: smallest's.
LINEAR_TOLERANCE = 1.5


def _commit() -> str:
    def git(*args):
        return subprocess.run(
            ["git", *args], cwd=REPO, capture_output=True, text=True, check=False
        ).stdout.strip()

    # Only changes that can move the numbers count: the library and the benchmark's code.
    return git("rev-parse", "--short", "HEAD") + (
        " (+ local changes)"
        if git(
            "status",
            "--porcelain",
            "--untracked-files=no",
            "--",
            "stochlap_torch",
            "benchmarks/*.py",
        )
        else ""
    )


def run_info(argv: list[str], threads: int) -> dict:
    """Date, machine, versions and command of this run."""
    import numba
    import numpy
    import scipy
    import torch

    import stochlap_torch

    script = os.path.relpath(argv[0], REPO) if os.path.isabs(argv[0]) else argv[0]
    return {
        "id": f"{time.time():.0f}-{os.getpid()}",
        "date": time.strftime("%Y-%m-%d %H:%M %Z"),
        "command": " ".join(["python", script, *argv[1:]]),
        "cpu": benchlib.cpu_model(),
        "cores": os.cpu_count(),
        "threads": threads,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numba": numba.__version__,
        "numpy": numpy.__version__,
        "scipy": scipy.__version__,
        "stochlap_torch": stochlap_torch.__version__,
        "commit": _commit(),
    }


def merge(json_path: Path, run: dict, new: dict, elapsed: float) -> dict:
    """The results of earlier runs in ``json_path`` with the sections of ``new`` replaced."""
    old = json.loads(json_path.read_text()) if json_path.exists() else {}
    runs, sections = old.get("runs", []), old.get("sections", {})
    if runs and runs[-1]["id"] == run["id"]:  # this run saved before: replace its record
        runs.pop()
    runs.append(dict(run, sections=sorted(new), elapsed_s=elapsed, commit_end=_commit()))
    for name, section in new.items():
        sections[name] = dict(section, run=len(runs) - 1)
    used = sorted({s["run"] for s in sections.values()})
    renumber = {old_index: i for i, old_index in enumerate(used)}
    for section in sections.values():
        section["run"] = renumber[section["run"]]
    return {"runs": [runs[i] for i in used], "sections": sections}


# -- cells -------------------------------------------------------------------------------------


def _f(value, digits: int = 3) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def _mean(rows, key) -> float:
    values = [r[key] for r in rows if r.get(key) is not None and np.isfinite(r[key])]
    return float(np.mean(values)) if values else float("nan")


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return [
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
        *("| " + " | ".join(r) + " |" for r in rows),
    ]


def _verdict(ok: bool, text: str) -> str:
    return f"- {'**met**' if ok else '**NOT met**'}: {text}"


def _skipped(section: dict) -> list[str]:
    """Meshes skipped, and methods that failed on a copy (MEANs are over the others)."""
    failed = [
        f"- **{m} failed** on {r['mesh']} (MEAN over the other meshes): {e}"
        for r in section.get("rows", [])
        for m, e in r.get("errors", {}).items()
    ]
    return failed + [f"- skipped {s['mesh']}: {s['reason']}" for s in section.get("skipped", [])]


# -- sections ----------------------------------------------------------------------------------


def _feature_table(section: dict) -> list[str]:
    keys = ("robust", "hks", "paper", "nn_robust", "nn_hks", "nn_paper")
    header = [
        "mesh",
        "V_A",
        "V_B",
        "robust",
        "HKS",
        "paper",
        "NN robust",
        "NN HKS",
        "NN paper",
        "worst robust channel",
    ]

    def cell(row, key):
        return "failed" if key.removeprefix("nn_") in row.get("errors", {}) else _f(row[key])

    body = [
        [
            r["mesh"],
            str(r["V_A"]),
            str(r["V_B"]),
            *(cell(r, k) for k in keys),
            f"{r['worst_channel']} {_f(r['worst_rho'], 2)}",
        ]
        for r in section["rows"]
    ]
    body.append(["**MEAN**", "", "", *(f"**{_f(_mean(section['rows'], k))}**" for k in keys), ""])
    return _table(header, body)


def _below(rows, key, other) -> str:
    worse = [
        f"{r['mesh']} ({_f(r[key])} vs {_f(r[other])})"
        for r in rows
        if np.isfinite(r[other]) and r[key] < r[other]
    ]
    return "; below on " + ", ".join(worse) if worse else "; not below on any mesh"


def features_md(section: dict) -> list[str]:
    rows = section["rows"]
    out = [
        "## 1. Features under isotropic remeshing (ACVD) + random similarity",
        "",
        "Mesh B: ACVD remeshing of A to the same vertex count, then a random rotation, "
        "uniform scale in [0.2, 5] and translation. Columns robust / HKS / paper: mean over "
        "channels of the Spearman correlation between A's values carried to B's vertices "
        "(closest point on A, barycentric; computed on the un-moved copy) and B's own. "
        "NN: fraction of 2000 sampled B vertices whose nearest A descriptor (channels "
        "standardised by A's statistics) lies within 0.05 sqrt(area) of the corresponding "
        "point. HKS: unit area, intrinsic Delaunay Laplacian, 64 eigenpairs, 16 times "
        '(B uses A\'s times), log. Paper: `variant="paper"`, 8 scales, rotation invariant.',
        "",
        *_feature_table(section),
        "",
    ]
    mean_rob, nn_rob, nn_hks = (_mean(rows, k) for k in ("robust", "nn_robust", "nn_hks"))
    low = min(rows, key=lambda r: r["robust"]) if rows else None
    if rows:
        out.append(
            _verdict(
                mean_rob >= FEATURE_SPEARMAN_TARGET,
                f"robust mean Spearman >= {FEATURE_SPEARMAN_TARGET}: MEAN "
                f"{_f(mean_rob)}; lowest mesh {low['mesh']} {_f(low['robust'])}",
            )
        )
        out.append(
            _verdict(
                nn_rob >= nn_hks,
                f"robust NN >= HKS NN: MEAN {_f(nn_rob)} vs "
                f"{_f(nn_hks)}{_below(rows, 'nn_robust', 'nn_hks')}",
            )
        )
    return out + _skipped(section) + [""]


def subdec_md(section: dict) -> list[str]:
    rows = section["rows"]
    out = [
        "## 3. Features under subdivide-then-decimate remeshing (harder, no target)",
        "",
        "As section 1, with B = `trimesh.remesh.subdivide` (midpoint, 4x faces) then "
        "quadric decimation back to A's vertex count: an adaptive, anisotropic "
        "triangulation of the same surface.",
        "",
        *_feature_table(section),
        "",
    ]
    if rows:
        wins = sum(r["robust"] >= r["hks"] for r in rows if np.isfinite(r["hks"]))
        out.append(
            f"- Spearman: robust MEAN {_f(_mean(rows, 'robust'))} vs HKS "
            f"{_f(_mean(rows, 'hks'))} (robust >= HKS on {wins} of {len(rows)} meshes)"
            f"{_below(rows, 'robust', 'hks')}."
        )
        out.append(
            f"- NN: robust MEAN {_f(_mean(rows, 'nn_robust'))} vs HKS "
            f"{_f(_mean(rows, 'nn_hks'))}{_below(rows, 'nn_robust', 'nn_hks')}."
        )
    return out + _skipped(section) + [""]


def saliency_md(section: dict) -> list[str]:
    rows, copies = section["rows"], section["copies"]
    names = {"dec3": "decimated 1/3", "dec10": "decimated 1/10", "acvd": "ACVD (same V)"}
    labels = {"robust": "robust", "lee": "Lee et al.", "paper": "paper"}
    header = ["mesh", "method", *(names[c] for c in copies), "rho with valence"]
    body = [
        [r["mesh"], labels[r["method"]], *(_f(r[c]) for c in copies), _f(r["valence"])]
        for r in rows
    ]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    for m in methods:
        sel = [r for r in rows if r["method"] == m]
        body.append(
            [
                "**MEAN**",
                f"**{labels[m]}**",
                *(f"**{_f(_mean(sel, c))}**" for c in (*copies, "valence")),
            ]
        )
    out = [
        "## 2. Saliency under decimation and remeshing",
        "",
        "Spearman correlation between the saliency of the full mesh and that of the copy, "
        "carried to the full mesh's vertices by nearest vertex (no smoothing). Quadric "
        "decimation (fast-simplification) to 1/3 and 1/10 of the vertices; ACVD to the same "
        "count. Last column: Spearman of the full mesh's saliency with vertex valence.",
        "",
        *_table(header, body),
        "",
    ]
    robust = [r for r in rows if r["method"] == "robust"]
    if robust:
        means = {c: _mean(robust, c) for c in copies}
        cells = [
            f"{r['mesh']} {names[c]} {_f(r[c])}"
            for r in robust
            for c in copies
            if not r[c] >= SALIENCY_TARGET
        ]
        out.append(
            _verdict(
                all(v >= SALIENCY_TARGET for v in means.values()),
                f"robust >= {SALIENCY_TARGET} in each column (MEAN): "
                + ", ".join(f"{names[c]} {_f(v)}" for c, v in means.items())
                + (
                    "; per-mesh cells below: " + ", ".join(cells)
                    if cells
                    else "; no per-mesh cell below"
                ),
            )
        )
        worst = max(robust, key=lambda r: abs(r["valence"]))
        out.append(
            _verdict(
                abs(worst["valence"]) <= VALENCE_TOLERANCE,
                f"robust saliency uncorrelated with valence (|rho| <= "
                f"{VALENCE_TOLERANCE} on every mesh): MEAN "
                f"{_f(_mean(robust, 'valence'))}, largest |rho| "
                f"{_f(abs(worst['valence']))} ({worst['mesh']})",
            )
        )
    return out + _skipped(section) + [""]


def _blas_note(machine: dict) -> str:
    found = {k: v for k, v in machine.get("blas_tuning_env", {}).items() if v is not None}
    where = (
        (", ".join(f"{k}={v}" for k, v in found.items()) + " in the benchmark's environment")
        if found
        else "neither was set in the benchmark's environment"
    )
    return (
        f"The HKS children run without OPENBLAS_CORETYPE and OPENBLAS_L2_SIZE, which slow "
        f"numpy's OpenBLAS on this kind of machine ({where}); the library's children keep "
        "the environment as it is."
    )


def speed_md(section: dict) -> list[str]:
    machine, pipes = section["machine"], section["pipelines"]
    labels = {
        "robust_features": "robust features",
        "robust_saliency": "robust saliency",
        "hks": "HKS pipeline (eigenpairs + HKS)",
        "lee": "Lee et al. saliency",
        "paper_saliency": "paper saliency (Algorithm 2)",
    }
    hks = pipes.get("hks", {}).get("median", float("nan"))
    extra = {f"{k}_1": p for k, p in section.get("robust_openblas1", {}).items()}
    for key in extra:
        labels[key] = f"{labels[key[:-2]]}, OPENBLAS_NUM_THREADS=1 (information)"
    body = [
        [
            labels[k],
            _f(p["median"], 2),
            ", ".join(_f(r, 2) for r in p["runs"]),
            _f(p["peak_mb"], 0),
            _f(p["extra_mb"], 0),
            _f(hks / p["median"], 1),
        ]
        for k, p in {**pipes, **extra}.items()
    ]
    quiet = (
        ""
        if machine["quiet"]
        else " **The machine never got quiet (limit 0.7 within 15 "
        "min): these timings were taken under load.**"
    )
    out = [
        "## 4. Speed and memory",
        "",
        f"Each pipeline in a fresh process: {section['threads']} threads (torch, "
        f"numba, OMP/MKL/OpenBLAS), loaded mesh, one warm-up call on {section['warm_mesh']}, "
        "then 3 timed "
        "runs (median). Peak RSS: the child's `VmHWM`, reset after the warm-up "
        "(`/proc/self/clear_refs`); extra = peak minus the RSS before the timed runs. "
        "(`ru_maxrss` is no use here: Linux hands the parent's high-water mark down to a "
        "child across fork and exec.) 1-minute load at start "
        f"{_f(machine['load_at_start'], 2)}, at end "
        f"{_f(machine.get('load_at_end'), 2)}.{quiet}",
        "",
        *([f"### {p['mesh']} ({p['V']} vertices)" for p in list(pipes.values())[:1]]),
        "",
        *_table(
            ["pipeline", "median (s)", "runs (s)", "peak RSS (MB)", "extra (MB)", "HKS / this"],
            body,
        ),
        "",
    ]
    tries = section.get("hks_settings", [])
    if tries:
        out.append(
            "HKS baseline = the faster of "
            + " and ".join(
                f"OPENBLAS_NUM_THREADS={t['openblas_threads']}: {_f(t['median'], 2)} s"
                for t in tries
            )
            + ". "
            + _blas_note(machine)
        )
        out.append("")
    for key in ("robust_features", "robust_saliency"):
        if key in pipes and "hks" in pipes:
            ratio = hks / pipes[key]["median"]
            best = min(pipes[key]["median"], extra.get(f"{key}_1", pipes[key])["median"])
            out.append(
                _verdict(
                    ratio >= SPEED_TARGET,
                    f"HKS / {labels[key]} >= "
                    f"{SPEED_TARGET:.0f}x: {ratio:.1f}x ({_f(hks, 2)} s vs "
                    f"{_f(pipes[key]['median'], 2)} s); with the library also at "
                    f"its faster OpenBLAS setting: {hks / best:.1f}x",
                )
            )
    return out + [""] + scaling_md(section) + [f"- error: {e}" for e in section["errors"]] + [""]


def scaling_md(section: dict) -> list[str]:
    rows = section["scaling"]
    meshes = list(dict.fromkeys(r["mesh"] for r in rows))
    by = {(r["mesh"], r["task"]): r for r in rows}
    body = []
    for mesh in meshes:
        cells = [mesh, str(next(r["V"] for r in rows if r["mesh"] == mesh))]
        for task in ("robust_features", "robust_saliency"):
            r = by.get((mesh, task))
            cells += (
                [
                    _f(r["median"], 2),
                    _f(1e6 * r["median"] / r["V"], 1),
                    _f(r["peak_mb"], 0),
                    _f(r["extra_mb"], 0),
                    _f(r["extra_mb"] * 2**20 / r["V"], 0),
                ]
                if r
                else ["n/a"] * 5
            )
        body.append(cells)
    head = ["mesh", "V"] + [
        f"{w} {c}"
        for w in ("features", "saliency")
        for c in ("s", "us/V", "peak MB", "extra MB", "extra B/V")
    ]
    out = ["### Time and memory per vertex (robust variant)", "", *_table(head, body), ""]
    for task, label in (("robust_features", "features"), ("robust_saliency", "saliency")):
        series = sorted((r for r in rows if r["task"] == task), key=lambda r: r["V"])
        if len(series) < 2:
            continue
        first, last = series[0], series[-1]
        t_ratio = (last["median"] / last["V"]) / (first["median"] / first["V"])
        m_ratio = (last["extra_mb"] / last["V"]) / max(first["extra_mb"] / first["V"], 1e-12)
        out.append(
            _verdict(
                t_ratio <= LINEAR_TOLERANCE,
                f"{label}: linear time (us/V at {last['V']} V within "
                f"{LINEAR_TOLERANCE}x of {first['V']} V): ratio {t_ratio:.2f}",
            )
        )
        out.append(
            _verdict(
                m_ratio <= LINEAR_TOLERANCE,
                f"{label}: memory bounded per vertex (extra bytes/V within "
                f"{LINEAR_TOLERANCE}x): ratio {m_ratio:.2f}, peak RSS "
                f"{_f(last['peak_mb'], 0)} MB at {last['V']} V",
            )
        )
    return out


# -- the document ------------------------------------------------------------------------------


def _header(runs: list[dict], sections: dict) -> list[str]:
    first = runs[-1]
    out = [
        "# The robust variant: discretisation robustness and speed (GitHub issue 14)",
        "",
        f"Generated by `benchmarks/robust.py` (measuring the library's public API; every "
        f"anchor measured in the same run). Machine: {first['cpu']}, {first['cores']} "
        f"cores, {first['threads']} threads used; Python {first['python']}, torch "
        f"{first['torch']}, numba {first['numba']}, numpy {first['numpy']}, scipy "
        f"{first['scipy']}; stochlap_torch {first['stochlap_torch']} at commit "
        f"{first['commit']}.",
        "",
    ]
    for i, run in enumerate(runs):
        done = [n for n, s in sections.items() if s["run"] == i]
        moved = run.get("commit_end", run["commit"]) != run["commit"]
        out.append(
            f"- {run['date']}: `{run['command']}` ({run['elapsed_s'] / 60:.0f} min; "
            f"sections here: {', '.join(done)})"
            + (
                f"; **the library changed during this run: {run['commit']} -> {run['commit_end']}**"
                if moved
                else ""
            )
        )
    return [*out, ""]


def render(results: dict) -> str:
    """The whole ``ROBUST.md``."""
    sections = results["sections"]
    writers = (
        ("features", features_md),
        ("saliency", saliency_md),
        ("subdec", subdec_md),
        ("speed", speed_md),
    )
    lines = _header(results["runs"], sections)
    for name, writer in writers:
        if name in sections:
            lines += writer(sections[name])
            lines.append(f"_Section time: {sections[name]['elapsed_s'] / 60:.1f} min._")
            lines.append("")
    return "\n".join(lines).rstrip() + "\n"
