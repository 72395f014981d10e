"""What the robust-variant benchmark's parts share: the meshes and their remeshed copies, the
pipelines measured (robust and paper features, the heat kernel signature, saliencies), the
thread pinning and the rank statistics. :mod:`robust` runs the sections; :mod:`robust_speed`
and :mod:`robust_figure` import from here, not from it, so no module imports one that imports
it back."""

from __future__ import annotations

import math
import os
import sys
import time
import zlib
from pathlib import Path

import numpy as np

BENCH = Path(__file__).resolve().parent
REPO = BENCH.parent
if str(REPO) not in sys.path:  # a plain checkout works without `pip install -e .`
    sys.path.insert(0, str(REPO))
MESHES = Path(os.environ.get("STOCHLAP_MESHES", REPO.parent / "shared" / "meshes"))
CACHE = BENCH / ".cache"
MESH_SET = (
    "horse_48k.ply",
    "gargoyle_50k.off",
    "armadillo.obj",
    "nefertiti.obj",
    "bunny.obj",
    "camel.off",
    "octopus.off",
)
SECTIONS = ("features", "saliency", "subdec", "speed")
THREADS = 2
THREAD_ENV = (
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "NUMEXPR_NUM_THREADS",
    "NUMBA_NUM_THREADS",
)
#: Set on some machines; they slow numpy's OpenBLAS, so the HKS child runs without them.
BLAS_TUNING_ENV = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE")
HKS_EIGENPAIRS, HKS_TIMES = 64, 16
NN_SAMPLES, NN_RADIUS = 2000, 0.05  # matches within NN_RADIUS * sqrt(area) count


def log(*parts) -> None:
    print(*parts, flush=True)


def pin_threads() -> None:
    """Pin every thread pool to :data:`THREADS` (env vars must precede the first BLAS load)."""
    for name in THREAD_ENV:
        os.environ.setdefault(name, str(THREADS))
    import torch

    torch.set_num_threads(THREADS)
    import numba

    numba.set_num_threads(min(THREADS, numba.config.NUMBA_NUM_THREADS))


# -- meshes and their copies -------------------------------------------------------------------


def load(name: str) -> tuple[np.ndarray, np.ndarray]:
    """A shared mesh, compacted (degenerate-index faces and unreferenced vertices dropped)."""
    import stochlap_torch as sl
    from stochlap_torch.evaluation import compact

    mesh = sl.load_mesh(MESHES / name)
    return compact(mesh.vertices.numpy(), mesh.faces.numpy())


def available(names) -> tuple[list[str], list[dict]]:
    """The meshes present, and a skip record (printed) for each missing one."""
    present, skipped = [], []
    for name in names:
        if (MESHES / name).is_file():
            present.append(name)
        else:
            skipped.append({"mesh": name, "reason": f"not found in {MESHES}"})
            log(f"SKIP {name}: not found in {MESHES}")
    return present, skipped


def make_copy(v: np.ndarray, f: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Another triangulation of the surface: ``acvd`` (isotropic, same V), ``subdec``
    (midpoint subdivision then quadric decimation to the same V), ``dec3`` / ``dec10``
    (quadric decimation to 1/3, 1/10 of V)."""
    from stochlap_torch.evaluation import decimate, isotropic_remesh

    if kind == "acvd":
        return isotropic_remesh(v, f, len(v))
    if kind == "subdec":
        import trimesh

        sv, sf = trimesh.remesh.subdivide(v, f)
        return decimate(np.asarray(sv), np.asarray(sf), len(v))
    return decimate(v, f, len(v) // {"dec3": 3, "dec10": 10}[kind])


def copy_of(name: str, v: np.ndarray, f: np.ndarray, kind: str):
    """:func:`make_copy`, cached as ``.cache/<stem>_<kind>_<V>.npz``."""
    CACHE.mkdir(exist_ok=True)
    ignore = CACHE / ".gitignore"
    if not ignore.exists():
        ignore.write_text("*\n")
    path = CACHE / f"{Path(name).stem}_{kind}_{len(v)}.npz"
    if path.exists():
        data = np.load(path)
        return data["v"], data["f"]
    start = time.perf_counter()
    cv, cf = make_copy(v, f, kind)
    np.savez(path, v=cv, f=cf)
    log(f"  made {path.name}: {len(cv)} vertices in {time.perf_counter() - start:.1f} s")
    return cv, cf


def seed_of(*parts: str) -> int:
    """A reproducible seed (``hash()`` of a string changes between processes)."""
    return zlib.crc32("/".join(parts).encode())


def surface_area(v: np.ndarray, f: np.ndarray) -> float:
    e1, e2 = v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    return float(0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum())


def valence(f: np.ndarray, num_vertices: int) -> np.ndarray:
    """Number of distinct edges at each vertex."""
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.bincount(np.unique(edges, axis=0).ravel(), minlength=num_vertices)


# -- the compared pipelines (numpy in, numpy out) ----------------------------------------------


def _tensors(v, f):
    import torch

    return torch.from_numpy(np.ascontiguousarray(v)), torch.from_numpy(np.ascontiguousarray(f))


def robust_features(v, f) -> np.ndarray:
    import stochlap_torch as sl

    return sl.multiscale_features(*_tensors(v, f), variant="robust").numpy()


def paper_features(v, f) -> np.ndarray:
    import stochlap_torch as sl

    return sl.multiscale_features(
        *_tensors(v, f), variant="paper", num_scales=8, rotation_invariant=True
    ).numpy()


def log_hks(v, f, times=None):
    """``(log HKS (V, 16), times)`` at unit area: intrinsic Delaunay Laplacian, 64 eigenpairs,
    Sun et al.'s times from this mesh's eigenvalues unless ``times`` are given."""
    from stochlap_torch.baselines import (
        heat_kernel_signature,
        heat_kernel_times,
        laplacian_eigenpairs,
    )

    unit, faces = _tensors((v - v.mean(axis=0)) / math.sqrt(surface_area(v, f)), f)
    pairs = laplacian_eigenpairs(unit, faces, HKS_EIGENPAIRS, laplacian="intrinsic")
    if times is None:
        times = heat_kernel_times(pairs.values, HKS_TIMES)
    hks = heat_kernel_signature(unit, faces, eigenpairs=pairs, times=times).numpy()
    return np.log(np.maximum(hks, 1e-300)), times


def saliency(v, f, method: str) -> np.ndarray:
    """``robust`` / ``paper`` (:func:`mesh_saliency`) or ``lee`` (Lee et al. 2005)."""
    if method == "lee":
        from stochlap_torch.baselines import lee_saliency

        return lee_saliency(*_tensors(v, f)).numpy()
    import stochlap_torch as sl

    return sl.mesh_saliency(*_tensors(v, f), variant=method).numpy()


# -- measures ----------------------------------------------------------------------------------


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Rank correlation; NaN when either side is constant."""
    from scipy.stats import spearmanr

    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    return float(spearmanr(a, b)[0])


def channel_spearman(values_a_at_b: np.ndarray, values_b: np.ndarray) -> list[float]:
    return [spearman(values_a_at_b[:, c], values_b[:, c]) for c in range(values_b.shape[1])]


def nn_match(desc_a, desc_b, points_a, truth_b, radius: float, seed: int) -> float:
    """Fraction of :data:`NN_SAMPLES` B vertices whose nearest A descriptor (channels
    standardised by A's mean and deviation) is at a vertex within ``radius`` of the point of A
    that corresponds to them."""
    import torch

    mean, std = desc_a.mean(axis=0), desc_a.std(axis=0) + 1e-12
    a = torch.from_numpy((desc_a - mean) / std)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(desc_b), min(NN_SAMPLES, len(desc_b)), replace=False)
    b = torch.from_numpy((desc_b[pick] - mean) / std)
    nearest = torch.cat([torch.cdist(chunk, a).argmin(dim=1) for chunk in b.split(200)])
    gap = np.linalg.norm(points_a[nearest.numpy()] - truth_b[pick], axis=1)
    return float(np.mean(gap <= radius))
