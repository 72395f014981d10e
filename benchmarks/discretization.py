"""The discretization-robust correspondence benchmark (DiffusionNet's; GitHub issue 31).

The FAUST test bodies remeshed four ways in one pose (``iso``, ``qes``, ``mc``, ``dense``;
``nmwsharp/discretization-robust-correspondence-benchmark``, MPI-FAUST licence: read from the
folder given, never copied here). Each ``qes`` / ``mc`` / ``dense`` mesh, moved by a random
rotation, scale and translation, against its body's ``iso`` mesh:

* **matching**: ``--samples`` remeshed vertices each go to the ``iso`` vertex of nearest
  descriptor (channels standardised by the ``iso`` mesh's); error: geodesic distance on ``iso``
  (heat method, potpourri3d), in units of sqrt(``iso`` area), to the true vertex (the nearest
  ``iso`` vertex in the original pose); and the far misses that land on the truth's left/right
  mirror (the vertex with the same geodesic distances to head, hands and feet, sides swapped);
* **saliency**: Spearman against the ``iso`` saliency at the true vertices (HKS: mid-time
  HKS), and per robust feature channel the same;
* **repeatability**: fraction of the top 20 interest points whose true vertex lies within 0.05
  (geodesic) of an ``iso`` interest point;
* **time**: one thread; robust = structure + features (and, apart, the structure alone: the
  features on a structure built ahead take the difference), HKS = Laplacian + eigsh + HKS;
* **handles**: the genus of the remeshed body (its largest component; every ``iso`` body is a
  sphere): where the remeshing joined parts that touch in the pose (on body 087 ``mc`` joins
  the two legs), a change of the surface itself.

Methods: ``robust`` (the default variant), ``hks`` (the anchor: unit-area HKS on
robust_laplacian's Laplacian, ``eigsh`` k=64, 16 times from each mesh's own eigenvalues),
``paper`` (``variant="paper"``) and ``random``. A mesh a method refuses is recorded with its
error and counted as a failure. From the repository root::

    python benchmarks/discretization.py DATA_DIR [--bodies 080-089] [--samples 300] [--seed 0]
                                        [--out benchmarks/DISCRETIZATION.md] [--report-only]

or from a script with ``benchmarks/`` on ``sys.path``: ``evaluate_body(data_dir, "080",
"dense", methods=("robust", "hks"), robust={"ratio": 8.0})`` returns a :class:`BodyResult`.
"""

from __future__ import annotations

import os
import sys

if __name__ == "__main__":  # one thread everywhere; BLAS reads these when numpy loads
    for _name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ[_name] = "1"

import argparse
import json
import math
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from robust_common import BENCH, HKS_EIGENPAIRS, HKS_TIMES, log, seed_of, spearman
from robust_common import surface_area as area

POLICIES = ("qes", "mc", "dense")
METHODS = ("robust", "hks", "paper", "random")
RADIUS = 0.05  # in units of sqrt(iso area)
TOP_K = 20
FAR = 0.2  # a match this far from the truth is a far miss
#: FAUST template vertices (the .txt labels) at the head, a hand, the other, a foot, the other.
TIPS = (411, 2446, 5905, 6615, 3220)
RANDOM_CHANNELS = 16


def read(data_dir, policy: str, body: str) -> tuple[np.ndarray, np.ndarray]:
    """The mesh as stored (``trimesh``, no processing: duplicates and all)."""
    import trimesh

    mesh = trimesh.load(Path(data_dir) / policy / f"tr_reg_{policy}_{body}.ply", process=False)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


# -- the pipelines: descriptors, saliency and interest points of one mesh --------------------


@dataclass
class Descriptors:
    features: np.ndarray | None = None  # (V, C)
    saliency: np.ndarray | None = None  # (V,)
    points: np.ndarray | None = None  # (<= TOP_K,) interest points, most salient first
    seconds: float = float("nan")  # the timed pipeline
    build_seconds: float = float("nan")  # robust: of which building the structure
    error: str | None = None  # the exception, when the method refused the mesh
    note: str | None = None  # the exception, when only the interest points failed


def hks_pipeline(v, f):
    """``(log HKS (V, 16), mid-time HKS (V,))``: unit area, robust_laplacian, eigsh k=64; the
    sum written out, as ``heat_kernel_signature`` refuses the meshes robust_laplacian takes."""
    import robust_laplacian
    import torch
    from scipy.sparse.linalg import eigsh

    from stochlap_torch.baselines import heat_kernel_times

    unit = (v - v.mean(axis=0)) / math.sqrt(area(v, f))
    stiffness, mass = robust_laplacian.mesh_laplacian(unit, f)
    values, vectors = eigsh(stiffness, k=HKS_EIGENPAIRS, M=mass, sigma=-1e-8)
    values, vectors = torch.from_numpy(values), torch.from_numpy(vectors)
    times = heat_kernel_times(values, HKS_TIMES)
    hks = (vectors.square() @ torch.exp(-values.clamp(min=0)[:, None] * times)).numpy()
    return np.log(np.maximum(hks, 1e-300)), hks[:, HKS_TIMES // 2]


def describe(v, f, method: str, robust=None, seed: int = 0) -> Descriptors:
    """One method on one mesh; ``robust``: :class:`RobustParams` or a mapping of its fields."""
    import torch

    import stochlap_torch as sl

    vt, ft = torch.from_numpy(np.ascontiguousarray(v)), torch.from_numpy(f)
    out = Descriptors()
    start = time.perf_counter()
    try:
        if method == "robust":
            structure = sl.robust_structure(vt, ft, robust=robust)
            out.build_seconds = time.perf_counter() - start
            out.features = structure.features(vt).numpy()
            out.seconds = time.perf_counter() - start
            out.saliency = structure.saliency(vt).numpy()
        elif method == "hks":
            out.features, out.saliency = hks_pipeline(v, f)
            out.seconds = time.perf_counter() - start
        elif method == "paper":
            out.features = sl.multiscale_features(vt, ft, variant="paper").numpy()
            out.seconds = time.perf_counter() - start
            out.saliency = sl.saliency(vt, ft, variant="paper").numpy()
        else:
            out.features = np.random.default_rng(seed).normal(size=(len(v), RANDOM_CHANNELS))
    except Exception as exc:  # a refused mesh is a result: record it and go on
        return Descriptors(error=f"{type(exc).__name__}: {exc}")
    try:
        if out.saliency is not None:
            saliency = torch.from_numpy(np.ascontiguousarray(out.saliency))
            out.points = sl.interest_points(saliency, vt, ft, top_k=TOP_K).numpy()
    except Exception as exc:  # the HKS's saliency on a mesh the library refuses
        out.note = f"{type(exc).__name__}: {exc}"
    return out


# -- the iso reference of a body and the comparison of one remeshing with it ------------------


@dataclass
class Reference:
    body: str
    v: np.ndarray
    f: np.ndarray
    unit: float  # sqrt(area)
    methods: dict[str, Descriptors]
    point_distance: dict[str, np.ndarray]  # (V,) geodesic distance to the nearest interest point
    mirror: np.ndarray | None = None  # (V,) the left/right mirror vertex of each vertex

    def geodesics(self, sources: np.ndarray) -> np.ndarray:
        """``(S, V)`` geodesic distances on the iso mesh in units of sqrt(area)."""
        return geodesics(self.v, self.f, sources, self.unit)


def geodesics(v: np.ndarray, f: np.ndarray, sources: np.ndarray, unit: float) -> np.ndarray:
    """``(S, V)`` geodesic distances (heat method) from ``sources``, in units of ``unit``."""
    from stochlap_torch.evaluation import geodesic_distances

    return geodesic_distances(v, f, sources, method="heat").distances.numpy() / unit


def reference(data_dir, body: str, methods=METHODS, robust=None, seed: int = 0) -> Reference:
    v, f = read(data_dir, "iso", body)
    ref = Reference(body, v, f, math.sqrt(area(v, f)), {}, {})
    for method in methods:
        ref.methods[method] = d = describe(v, f, method, robust, seed_of(str(seed), body, "iso"))
        if d.error:
            raise RuntimeError(f"{method} failed on iso {body}: {d.error}")
        if d.points is not None:
            ref.point_distance[method] = ref.geodesics(d.points).min(axis=0)
    labels = Path(data_dir) / "iso" / f"tr_reg_iso_{body}.txt"
    ref.mirror = mirror_map(ref, np.loadtxt(labels, dtype=np.int64)) if labels.exists() else None
    return ref


def mirror_map(ref: Reference, labels: np.ndarray) -> np.ndarray:
    """The vertex whose geodesic distances to the head, hands and feet are a vertex's own with
    the two hands and the two feet swapped: its left/right mirror, in any pose."""
    from scipy.spatial import cKDTree

    tips = [np.flatnonzero(labels == k)[:1] for k in TIPS]  # head, hand, hand, foot, foot
    distance = ref.geodesics(np.concatenate(tips))
    for i, tip in enumerate(tips):  # a label the remeshing lost: the farthest point instead
        if not tip.size:
            tips[i] = np.array([np.argmax(distance.min(axis=0))])
            distance = ref.geodesics(np.concatenate(tips))
    signature = distance.T
    return cKDTree(signature).query(signature[:, [0, 2, 1, 4, 3]])[1]


@dataclass
class MethodResult:
    seconds: float = float("nan")
    build_seconds: float = float("nan")  # robust: of which building the structure
    error: str | None = None  # the method refused the mesh
    note: str | None = None  # the interest points failed
    matches: float = float("nan")  # fraction of samples within RADIUS
    mean_error: float = float("nan")
    saliency_rho: float = float("nan")
    repeatability: float = float("nan")
    flips: float = float("nan")  # fraction of samples far (> FAR) from the truth, near its mirror
    mean_error_lr: float = float("nan")  # mean error to the nearer of the truth and its mirror
    channel_rho: list[float] = field(default_factory=list)
    matched: np.ndarray | None = None  # (samples,) iso vertex of each sample's match
    errors: np.ndarray | None = None  # (samples,) geodesic error of each match

    def summary(self) -> dict:
        return {k: v for k, v in vars(self).items() if k not in ("matched", "errors")}


@dataclass
class BodyResult:
    body: str
    policy: str
    num_vertices: int
    handles: int  # genus of the largest component
    samples: np.ndarray  # (S,) remeshed vertices
    truth: np.ndarray  # (S,) their true iso vertices
    methods: dict[str, MethodResult]

    def summary(self) -> dict:
        return {
            "body": self.body,
            "policy": self.policy,
            "V": self.num_vertices,
            "handles": self.handles,
            "methods": {m: r.summary() for m, r in self.methods.items()},
        }


def genus(v: np.ndarray, f: np.ndarray) -> int:
    """The genus of the largest connected component of a closed mesh, from its Euler
    characteristic ``V - E + F = 2 - 2 g`` (unreferenced vertices ignored)."""
    import torch

    from stochlap_torch.mesh import connected_components, unique_edges

    edges = unique_edges(torch.from_numpy(f), len(v)).numpy()
    labels = connected_components(len(v), edges)
    largest = np.bincount(labels[f[:, 0]]).argmax()
    vertices = np.unique(f[labels[f[:, 0]] == largest]).size
    euler = vertices - np.sum(labels[edges[:, 0]] == largest) + np.sum(labels[f[:, 0]] == largest)
    return (2 - int(euler)) // 2


def nearest_descriptor(iso: np.ndarray, query: np.ndarray) -> np.ndarray:
    mean, std = iso.mean(axis=0), iso.std(axis=0) + 1e-12
    from scipy.spatial import cKDTree

    return cKDTree((iso - mean) / std).query((query - mean) / std)[1]


def evaluate_body(
    data_dir, body: str, policy: str, methods=METHODS, samples=300, seed=0, robust=None, ref=None
) -> BodyResult:
    """One remeshing of one body against its iso mesh (pass ``ref`` to reuse the iso side)."""
    from scipy.spatial import cKDTree

    from stochlap_torch.evaluation import random_similarity

    ref = ref or reference(data_dir, body, methods, robust, seed)
    v, f = read(data_dir, policy, body)
    rotation, scale, shift = random_similarity(seed_of(str(seed), body, policy))
    moved = scale * v @ rotation.T + shift
    truth_of = cKDTree(ref.v).query(v)[1]  # in the original pose
    rng = np.random.default_rng(seed_of(str(seed), body, policy, "samples"))
    pick = rng.choice(len(v), min(samples, len(v)), replace=False)
    sources, row = np.unique(truth_of[pick], return_inverse=True)
    distances = ref.geodesics(sources)
    if ref.mirror is not None:
        mirrors, mirror_row = np.unique(ref.mirror[truth_of[pick]], return_inverse=True)
        to_mirror = ref.geodesics(mirrors)
    result = BodyResult(body, policy, len(v), genus(v, f), pick, truth_of[pick], {})
    for method in methods:
        d = describe(moved, f, method, robust, seed_of(str(seed), body, policy))
        r = result.methods[method] = MethodResult(d.seconds, d.build_seconds, d.error, d.note)
        if d.error:
            log(f"  {method} FAILED on {policy} {body}: {d.error}")
            continue
        iso = ref.methods[method]
        r.matched = nearest_descriptor(iso.features, d.features[pick])
        r.errors = distances[row, r.matched]
        r.matches, r.mean_error = float(np.mean(r.errors <= RADIUS)), float(np.mean(r.errors))
        if ref.mirror is not None:
            lr = to_mirror[mirror_row, r.matched]
            r.flips = float(np.mean((r.errors > FAR) & (lr <= 2 * RADIUS)))
            r.mean_error_lr = float(np.mean(np.minimum(r.errors, lr)))
        if d.saliency is not None:
            r.saliency_rho = spearman(iso.saliency[truth_of], d.saliency)
        if d.points is not None:
            near = ref.point_distance[method][truth_of[d.points]]
            r.repeatability = float(np.mean(near <= RADIUS))
        if method == "robust":
            at = iso.features[truth_of]
            r.channel_rho = [spearman(at[:, c], d.features[:, c]) for c in range(at.shape[1])]
    return result


def warm_up() -> None:
    """Compile and load every pipeline once (the bundled spot), so no timing pays for it."""
    import stochlap_torch as sl

    mesh = sl.load_mesh(sl.bundled_mesh_path())
    v, f = mesh.vertices.numpy(), mesh.faces.numpy()
    for method in METHODS:
        describe(v, f, method)


# -- the report --------------------------------------------------------------------------------


def _f(x, digits=3) -> str:
    return "n/a" if x is None or not np.isfinite(x) else f"{x:.{digits}f}"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(r) + " |" for r in [header, ["---"] * len(header), *rows]]


def aggregate(rows: list[dict], policy: str, method: str) -> dict:
    """Means over the meshes the method took (times: medians), and how many it refused."""
    rows = [r["methods"] for r in rows if r["policy"] == policy]
    ok = [r for r in rows if not r[method]["error"]] or [{method: {}, "hks": {}}]
    out = {"failed": sum(bool(r[method]["error"]) for r in rows)}
    keys = ["matches", "mean_error", "saliency_rho", "repeatability", "flips", "mean_error_lr"]
    with warnings.catch_warnings():  # random has no saliency: the mean of nothing is NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        for key in keys + ["channel_rho"] * (method == "robust"):
            out[key] = np.nanmean([r[method].get(key, np.nan) for r in ok], axis=0)
    times = np.array([[r[m].get("seconds", np.nan) for m in (method, "hks")] for r in ok])
    build = np.array([r[method].get("build_seconds", np.nan) for r in ok])
    out["seconds"] = float(np.median(times[:, 0]))
    out["speedup"] = float(np.median(times[:, 1] / times[:, 0]))  # HKS / this, per mesh
    with warnings.catch_warnings():  # no build time: every method but robust
        warnings.simplefilter("ignore", RuntimeWarning)
        out["build_seconds"] = float(np.median(build))
        # HKS / the features on a structure built ahead: the speed if the build were free
        out["built_speedup"] = float(np.median(times[:, 1] / (times[:, 0] - build)))
    return out


CHECKS = {  # issue 31's acceptance: (robust, hks) aggregates -> passed
    "matches >= HKS + 0.05": lambda r, h: r["matches"] >= h["matches"] + 0.05,
    "mean error <= HKS": lambda r, h: r["mean_error"] <= h["mean_error"],
    "saliency Spearman >= 0.98": lambda r, h: r["saliency_rho"] >= 0.98,
    "repeatability >= 0.90": lambda r, h: r["repeatability"] >= 0.90,
    "speed >= 10x HKS (median ratio)": lambda r, h: r["speedup"] >= 10.0,
    "no mesh refused": lambda r, h: r["failed"] == 0,
}
MEASURES = {  # row label: (key, digits)
    "matches within 0.05": ("matches", 3),
    "mean error": ("mean_error", 3),
    "saliency Spearman (HKS: mid-time HKS)": ("saliency_rho", 3),
    f"repeatability (top {TOP_K} within 0.05, geodesic)": ("repeatability", 2),
    "time, s (median, one thread)": ("seconds", 2),
    "of which building the structure, s (median)": ("build_seconds", 2),
    "meshes refused": ("failed", 0),
    f"far misses (> {FAR}) within 0.1 of the truth's left/right mirror": ("flips", 3),
    "mean error to the nearer of the truth and its mirror": ("mean_error_lr", 3),
}


def _robust_sections(rows: list[dict], agg: dict, channels: list[str]) -> list[str]:
    """Acceptance, the meshes where robust loses to HKS, the channels' Spearman."""
    verdict = [
        [label] + ["pass" if ok(agg[p, "robust"], agg[p, "hks"]) else "**FAIL**" for p in POLICIES]
        for label, ok in CHECKS.items()
    ]
    for column, p in enumerate(POLICIES, 1):
        robust = agg[p, "robust"]
        verdict[4][column] += (
            f" ({_f(robust['speedup'], 1)}x; {_f(robust['built_speedup'], 1)}x with the "
            "structure built ahead)"
        )
    losses = []
    for r in rows:
        rb, hk = r["methods"]["robust"], r["methods"]["hks"]
        if rb["error"] or rb["matches"] < hk["matches"] or rb["mean_error"] > hk["mean_error"]:
            cells = [f"{_f(rb[k])} / {_f(hk[k])}" for k in ("matches", "mean_error")]
            losses.append([r["body"], r["policy"], *cells])
    rho = [
        [n]
        + [_f(np.broadcast_to(agg[p, "robust"]["channel_rho"], len(channels))[c]) for p in POLICIES]
        for c, n in enumerate(channels)
    ]
    measures = [("saliency_rho", 3), ("repeatability", 2)]
    joined = [
        [r["body"], r["policy"], str(r["handles"])]
        + [_f(r["methods"][m][k], d) for k, d in measures for m in ("robust", "hks")]
        for r in rows
        if r.get("handles")
    ]
    names = ["Spearman robust", "Spearman HKS", "repeatability robust", "repeatability HKS"]
    return [
        *("", "## Acceptance (robust against HKS)", ""),
        *_table(["", *POLICIES], verdict),
        *("", "## Meshes where robust loses to HKS (matches or mean error)", ""),
        *_table(["body", "policy", "matches robust / HKS", "mean error robust / HKS"], losses),
        *("", "## Where the remeshing joined touching parts", ""),
        "Meshes whose body has handles (genus > 0; every iso body is a sphere): the remeshing "
        "joined parts that touch in the pose, a change of the surface itself.",
        "",
        *_table(["body", "policy", "handles", *names], joined),
        *("", "## Robust feature channels: Spearman across the remeshing (mean)", ""),
        *_table(["channel", *POLICIES], rho),
    ]


def render(results: dict) -> str:
    run, rows, load = results["run"], results["rows"], results["load"]
    methods = [m for m in METHODS if m in rows[0]["methods"]]
    agg = {(p, m): aggregate(rows, p, m) for p in POLICIES for m in methods}
    table = [
        [label] + [" / ".join(_f(agg[p, m][k], d) for p in POLICIES) for m in methods]
        for label, (k, d) in MEASURES.items()
    ]
    refused = [
        f"- {m} on {r['policy']} {r['body']}: "
        + (
            f"refused, `{x['error'][:160]}`"
            if x["error"]
            else f"no interest points, `{x['note'][:160]}`"
        )
        for r in rows
        for m in methods
        if (x := r["methods"][m])["error"] or x.get("note")
    ]
    lines = [
        "# The discretization-robust correspondence benchmark (issue 31)",
        "",
        f"`{run['command']}` at commit {run['commit']}, {run['date']}, "
        f"{results['elapsed_s'] / 60:.1f} min; {run['cpu']}, {run['cores']} cores, one thread; "
        f"load average {load[0]:.2f} at start, {load[1]:.2f} at end. Bodies "
        f"{results['bodies'][0]}-{results['bodies'][-1]}, {results['samples']} sampled vertices "
        "per mesh. Errors: geodesic on the iso mesh (heat method, potpourri3d), in units of "
        "sqrt(iso area). Means over the meshes a method took; cells: qes / mc / dense.",
        "",
        *_table(["", *methods], table),
        "",
        *refused,
    ]
    if {"robust", "hks"} <= set(methods):
        lines += _robust_sections(rows, agg, results["channels"])
    return "\n".join(lines) + "\n"


# -- command line ------------------------------------------------------------------------------


def bodies_of(spec: str) -> list[str]:
    """``080-089`` or ``080,084``."""
    if "-" in spec:
        first, last = spec.split("-")
        return [f"{b:03d}" for b in range(int(first), int(last) + 1)]
    return spec.split(",")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data_dir", nargs="?", help="folder with iso/ qes/ mc/ dense/")
    parser.add_argument("--bodies", default="080-089")
    parser.add_argument("--samples", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=str(BENCH / "DISCRETIZATION.md"))
    parser.add_argument("--report-only", action="store_true", help="rewrite the report from json")
    args = parser.parse_args(argv)
    out = Path(args.out)
    json_path = out.with_name("discretization.json")
    if args.report_only:
        out.write_text(render(json.loads(json_path.read_text())))
        return 0
    if not args.data_dir:
        parser.error("DATA_DIR is required unless --report-only")
    import numba
    import robust_report
    import torch

    torch.set_num_threads(1)
    numba.set_num_threads(1)
    start, load = time.time(), [os.getloadavg()[0]]
    warm_up()
    from stochlap_torch.features import feature_channel_names

    results = {
        "run": robust_report.run_info(sys.argv, 1),
        "bodies": bodies_of(args.bodies),
        "samples": args.samples,
        "seed": args.seed,
        "channels": feature_channel_names(variant="robust"),
        "rows": [],
    }
    for body in results["bodies"]:
        ref = reference(args.data_dir, body, seed=args.seed)
        for policy in POLICIES:
            row = evaluate_body(
                args.data_dir, body, policy, samples=args.samples, seed=args.seed, ref=ref
            ).summary()
            results["rows"].append(row)
            log(
                f"{body} {policy:5s} V={row['V']:6d} | "
                + " | ".join(
                    f"{m} {_f(r['matches'])} {_f(r['mean_error'])} {_f(r['seconds'], 2)}s"
                    for m, r in row["methods"].items()
                )
            )
        results["load"] = [load[0], os.getloadavg()[0]]
        results["elapsed_s"] = time.time() - start
        json_path.write_text(json.dumps(results, indent=1) + "\n")
        out.write_text(render(results))
    log(f"wrote {out} and {json_path} ({time.time() - start:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
