"""What the benchmark measures: the cases of each section, and how results are looked up.

A case is one measurement run in its own process (see ``measure.py``): a mesh, a method and
the parameters of the run. :func:`build_cases` turns the command line into the list of cases
and the list of those left out (mesh missing, larger than ``--max-vertices``), with the reason.
Nothing here imports torch: the parent process stays light.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import benchlib

#: Sections of the report, in the order the cases run.
SECTIONS = ("first-call", "main", "contention", "table1", "spectral", "scaling")

MAIN_MESHES = ("spot.obj", "gargoyle_50k.off")
MAIN_SCALES = 8
#: The large-mesh target: the library alone, in its default float64, at K = 8.
LARGE_MESH = "armadillo_loop2_692k.ply"

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

#: The first-call variants: label, backend, numba cache ("cold": a fresh empty cache,
#: "reuse-cold": the one the cold variant filled, "run": the run's shared cache).
FIRST_CALL_VARIANTS = (
    ("numba, empty on-disk cache (JIT compile)", "numba", "cold"),
    ("numba, on-disk cache present (cache load)", "numba", "reuse-cold"),
    ("torch ops (steps not compiled; the numba mesh kernel builds Lhat)", "torch", "run"),
)
#: Every path a user's first call may take, each in a fresh process after ``stochlap warmup``
#: filled a fresh numba cache ("warmed"): the README's promise of a first call in seconds.
FIRST_CALL_PATHS = (
    "paper saliency, float64",
    "paper saliency, float32",
    "return_operators=True, float64",
    "paper features + backward, float32",
    "robust saliency, float64",
    "robust features, float32",
)
#: Busy processes beside a contention case (as many as the machine's cores: every core shared).
CONTENTION_BACKGROUND = 2


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
    numba_cache: str = "run"  # "run": the run's cache; "cold": a fresh one; "warmed": warmup's
    background: int = 0  # busy-looping processes running beside the case
    dtype: str = "float64"  # of the vertices (the library computes in their dtype)
    round: int = 0  # visit of the library's scaling series (see --rounds)
    rounds: int = 1
    info: dict = field(default_factory=dict)

    @property
    def vertices(self) -> int | None:
        return benchlib.mesh_vertices(self.mesh)


def mesh_name(spec: str) -> str:
    """How a mesh spec reads in labels and tables: ``icosphere(7)`` or the file name."""
    kind, _, value = spec.partition(":")
    return f"icosphere({value})" if kind == "icosphere" else value


def multiscale_case(section, mesh, method, num_scales, threads, dtype="float64", **kwargs):
    """A multiscale case (Algorithms 1 and 2, timed from tensors to positions and saliency).

    Always a full-size warm-up: the first run at a given size in a fresh process is slower
    (fresh memory), which would bend the scaling curve.
    """
    label = f"{section}: {mesh_name(mesh)} K={num_scales} {method} x{threads}"
    label += "" if dtype == "float64" else f" {dtype}"
    if kwargs.get("rounds", 1) > 1:
        label += f" (round {kwargs['round'] + 1}/{kwargs['rounds']})"
    return Case(
        section,
        label,
        "multiscale",
        mesh,
        method,
        num_scales,
        threads,
        "full",
        dtype=dtype,
        **kwargs,
    )


def spectral_case(name: str, kind: str, threads: int, warmup: str) -> Case:
    """A spectral baseline on ``name``: ``dense_eigh`` (every eigenpair by dense
    ``torch.linalg.eigh``) or ``eigsh_hks`` (:data:`NUM_EIGENPAIRS` pairs by ``eigsh`` and
    the heat kernel signature at :data:`NUM_TIMES` times)."""
    what = "dense eigh" if kind == "dense_eigh" else "eigsh+HKS"
    label = f"spectral: {name} {what} x{threads}"
    return Case("spectral", label, kind, f"file:{name}", kind, threads=threads, warmup=warmup)


class _Selection:
    """The cases kept so far and the ones left out, with the reason."""

    def __init__(self, max_vertices: int):
        self.max_vertices = max_vertices
        self.cases: list[Case] = []
        self.left_out: list[dict] = []

    def skip(self, label: str, reason: str) -> None:
        self.left_out.append({"label": label, "reason": reason})

    def add(self, case: Case, limit: int | None = None) -> None:
        """Keep ``case`` unless its mesh is missing or has more than ``limit`` vertices."""
        limit = self.max_vertices if limit is None else min(limit, self.max_vertices)
        if case.kind != "first_call" and case.mesh.startswith("file:"):
            if benchlib.mesh_file(case.mesh[5:]) is None:
                self.skip(case.label, f"mesh not found in {benchlib.MESHES_DIR}")
                return
        vertices = case.vertices
        # 1 % slack: "--max-vertices 50000" keeps gargoyle_50k (50,002 vertices).
        if vertices is not None and vertices > limit * 1.01:
            self.skip(case.label, f"{vertices} vertices > {limit}")
            return
        self.cases.append(case)


def _first_call_cases(chosen: _Selection, args) -> None:
    """Cold start on spot: imports, first call, steady calls, per numba cache state."""
    for label, backend, cache in FIRST_CALL_VARIANTS:
        chosen.add(
            Case(
                "first-call",
                f"first-call: {label}",
                "first_call",
                "file:spot.obj",
                backend,
                MAIN_SCALES,
                args.threads,
                "none",
                numba_cache=cache,
                info={"variant": label},
            )
        )
    for path in FIRST_CALL_PATHS:
        chosen.add(
            Case(
                "first-call",
                f"first-call after warmup: {path}",
                "first_call",
                "file:spot.obj",
                "numba",
                MAIN_SCALES,
                args.threads,
                "none",
                numba_cache="warmed",
                info={"variant": f"after warmup: {path}", "path": path},
            )
        )


def _main_cases(chosen: _Selection, args) -> None:
    """Library (numba, also on one thread), torch ops and scipy on the main meshes; the large
    mesh with the library alone."""
    threads = args.threads
    for name in MAIN_MESHES:
        mesh = f"file:{name}"
        runs = [("numba", threads)] + ([("numba", 1)] if threads > 1 else [])
        runs += [("torch", threads), ("scipy", threads)]
        for method, count in runs:
            chosen.add(
                multiscale_case("main", mesh, method, MAIN_SCALES, count, save_saliency=True)
            )
    chosen.add(multiscale_case("main", f"file:{LARGE_MESH}", "numba", MAIN_SCALES, threads))


def _contention_cases(chosen: _Selection, args) -> None:
    """The target mesh with :data:`CONTENTION_BACKGROUND` busy processes beside it: the library
    and scipy (the quiet pair is the main section's)."""
    mesh = f"file:{MAIN_MESHES[-1]}"
    for method in ("numba", "scipy"):
        chosen.add(
            multiscale_case(
                "contention",
                mesh,
                method,
                MAIN_SCALES,
                args.threads,
                background=CONTENTION_BACKGROUND,
            )
        )


def _table1_cases(chosen: _Selection, args) -> None:
    """The library and scipy at the paper's K on every Table 1 mesh that is here."""
    for model, paper_vertices, num_scales, paper_seconds, files in PAPER_TABLE_1:
        info = {"model": model, "paper_vertices": paper_vertices, "paper_seconds": paper_seconds}
        if not files:
            chosen.skip(f"table1: {model}", "no such mesh in ../shared/meshes (SOURCES.md)")
        for name in files:
            for method in ("numba", "scipy"):
                chosen.add(
                    multiscale_case(
                        "table1", f"file:{name}", method, num_scales, args.threads, info=dict(info)
                    )
                )


def _spectral_cases(chosen: _Selection, args) -> None:
    """Dense eigh (small meshes only), eigsh + HKS and the library on the same meshes."""
    for name in SPECTRAL_MESHES + SPECTRAL_EXTRA_EIGSH:
        if name in SPECTRAL_MESHES:
            chosen.add(
                spectral_case(name, "dense_eigh", args.threads, "small"),
                limit=args.dense_max_vertices,
            )
        vertices = benchlib.mesh_vertices(f"file:{name}") or 0
        warmup = "full" if vertices <= 20_000 else "small"
        chosen.add(spectral_case(name, "eigsh_hks", args.threads, warmup))
        chosen.add(multiscale_case("spectral", f"file:{name}", "numba", MAIN_SCALES, args.threads))


def _scaling_cases(chosen: _Selection, args) -> None:
    """Icospheres and the Loop-subdivided meshes, smallest first: scipy and torch ops up to
    ``--baseline-max-vertices``, then the library's series ``--rounds`` times."""
    meshes = [f"icosphere:{s}" for s in SCALING_ICOSPHERES]
    meshes += [f"file:{name}" for name in SCALING_FILES]
    meshes.sort(key=lambda spec: benchlib.mesh_vertices(spec) or 0)
    for mesh in meshes:
        for method in ("scipy", "torch"):
            dtype = "float64" if method == "scipy" else args.scaling_dtype
            chosen.add(
                multiscale_case(
                    "scaling",
                    mesh,
                    method,
                    args.scaling_scales,
                    args.threads,
                    dtype,
                    unlimited_memory=True,
                ),
                limit=args.baseline_max_vertices,
            )
    # The library's series is visited ``rounds`` times, every mesh in each round, so that the
    # host's speed drifting over the series falls on every mesh alike.
    for round_index in range(args.rounds):
        for mesh in meshes:
            chosen.add(
                multiscale_case(
                    "scaling",
                    mesh,
                    "numba",
                    args.scaling_scales,
                    args.threads,
                    args.scaling_dtype,
                    unlimited_memory=True,
                    round=round_index,
                    rounds=args.rounds,
                )
            )


_SECTION_BUILDERS = {
    "first-call": _first_call_cases,
    "main": _main_cases,
    "contention": _contention_cases,
    "table1": _table1_cases,
    "spectral": _spectral_cases,
    "scaling": _scaling_cases,
}


def build_cases(args) -> tuple[list[Case], list[dict]]:
    """All cases for ``args``, and the ones left out (with the reason)."""
    chosen = _Selection(args.max_vertices)
    for section in SECTIONS:
        if section in args.sections:
            _SECTION_BUILDERS[section](chosen, args)
    cases = chosen.cases
    if args.only:
        pattern = re.compile(args.only)
        cases = [case for case in cases if pattern.search(case.label)]
    return cases, chosen.left_out


def ok_results(results: list[dict], **where) -> list[dict]:
    """The successful results whose case has every ``key=value`` of ``where``."""
    return [
        result
        for result in results
        if result.get("ok") and all(result["case"].get(k) == v for k, v in where.items())
    ]


def find_result(results: list[dict], **where) -> dict | None:
    """The first of :func:`ok_results`, or None."""
    found = ok_results(results, **where)
    return found[0] if found else None
