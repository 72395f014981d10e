"""Copies, labels and inputs of the segmentation example (``train_segmentation.py``).

A shape's original triangulation, its ACVD remeshing and quadric decimation; the ground truth
(area tertiles of the average geodesic distance, computed on the original and carried to a copy
by closest point); the inputs compared (robust and paper multiscale features, HKS, xyz). All
cached as ``.npz`` files.
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import torch

import stochlap_torch as sl
from stochlap_torch.baselines import heat_kernel_signature, laplacian_eigenpairs
from stochlap_torch.evaluation import compact, correspondence, decimate, isotropic_remesh
from stochlap_torch.learning.cache import numerics_fingerprint

MESHES = Path(__file__).resolve().parent.parent.parent / "shared" / "meshes"
TRAIN = [
    "cow.obj",
    "spot.obj",
    "dinosaur.obj",
    "horse_10k.obj",
    "horse.off",
    "maxplanck.obj",
    "fandisk.off",
    "foot.off",
    "polygirl.off",
    "rocker_arm.off",
    "squirrel.off",
]
TEST = ["camel.off", "teddy.off", "octopus.off", "gargoyle.off", "fertility.off"]
INPUTS = ("robust", "paper", "hks", "xyz")
CACHE_TAG = f"v3-{numerics_fingerprint()}"  # the library's numerics; bump v3 for copies, labels
ORIGINAL_KEYS = ("vertices", "faces", "agd", "thresholds")


def load_shape(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64)`` of a file, seams merged, compacted."""
    mesh = sl.load_mesh(path, merge_seams=True)
    return compact(mesh.vertices.numpy(), mesh.faces.numpy())


def average_geodesic_distance(vertices, faces, num_sources: int, seed: int) -> np.ndarray:
    """``(V,)`` mean edge-graph distance to ``num_sources`` farthest-point-sampled sources.

    Farthest-point sampling spreads the sources evenly over the surface (and reaches every
    component first), so the mean approximates the area integral; uniformly random vertices
    made the tertiles depend on the draw (33-90 % agreement between two draws of 64 sources,
    against 90-99 % here). NaN where no source is reachable.
    """
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    graph = scipy.sparse.coo_matrix((lengths, edges.T), shape=(len(vertices),) * 2).tocsr()
    source = int(np.random.default_rng(seed).integers(len(vertices)))
    nearest, total, count = np.full(len(vertices), np.inf), np.zeros(len(vertices)), 0
    for _ in range(num_sources):
        distances = scipy.sparse.csgraph.dijkstra(graph, directed=False, indices=source)
        finite = np.isfinite(distances)
        total, count = total + np.where(finite, distances, 0.0), count + finite
        nearest = np.minimum(nearest, distances)
        source = int(np.argmax(nearest))
    return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def surface_tertiles(values: np.ndarray, vertices, faces) -> np.ndarray:
    """The two values that cut the *surface area* (lumped vertex areas) into thirds.

    By area, not by vertex count: the labels must not depend on where a triangulation puts
    its vertices (the camel's legs hold a third of its vertices but far less of its area).
    """
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.bincount(faces.ravel(), np.repeat(np.linalg.norm(cross, axis=1) / 6, 3))
    area = np.pad(area, (0, len(vertices) - len(area)))
    keep = np.isfinite(values)
    order = np.argsort(values[keep])
    cumulative = np.cumsum(area[keep][order])
    return np.interp([1 / 3, 2 / 3], cumulative / cumulative[-1], values[keep][order])


def tertile_labels(values: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """``(V,)`` int64 class 0/1/2 of ``values`` cut at ``thresholds``; -1 where NaN."""
    labels = np.digitize(values, thresholds).astype(np.int64)
    labels[~np.isfinite(values)] = -1
    return labels


def random_rotation(seed: int) -> np.ndarray:
    """A uniformly random ``(3, 3)`` rotation."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def rotation_seed(name: str, kind: str, rotation: int) -> int:
    """The seed of the ``rotation``-th random rotation of a copy."""
    return zlib.crc32(f"{name}/{kind}".encode()) + rotation


def make_copy(vertices, faces, kind: str):
    """The ``"original"``, ``"remesh"`` (ACVD, same vertex count) or ``"decim"`` (1/3) copy."""
    if kind == "remesh":
        return isotropic_remesh(vertices, faces, len(vertices))
    if kind == "decim":
        return decimate(vertices, faces, len(vertices) // 3)
    return vertices, faces


def xyz_input(vertices: np.ndarray) -> np.ndarray:
    """``(V, 3)`` float32 positions centred and divided by the bounding-box diagonal."""
    centred = vertices - vertices.mean(axis=0)
    return (centred / np.linalg.norm(np.ptp(vertices, axis=0))).astype(np.float32)


def invariant_inputs(vertices: np.ndarray, faces: np.ndarray) -> dict[str, np.ndarray]:
    """``{"robust", "paper", "hks": (V, C) float32}`` of one copy, each computed on it."""
    v, f = torch.from_numpy(vertices), torch.from_numpy(faces)
    robust = sl.multiscale_features(v, f, variant="robust")
    paper = sl.multiscale_features(v, f, variant="paper", num_scales=8, rotation_invariant=True)
    corners = v[f]
    cross = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    unit = (v - v.mean(dim=0)) / (0.5 * cross.norm(dim=1).sum()).sqrt()
    pairs = laplacian_eigenpairs(unit, f, 64, laplacian="intrinsic")
    hks = heat_kernel_signature(unit, f, eigenpairs=pairs, num_times=16).clamp_min(1e-12).log()
    values = {"robust": robust, "paper": paper, "hks": hks}
    return {name: x.detach().numpy().astype(np.float32) for name, x in values.items()}


class ShapeSamples:
    """Copies, labels and inputs of the shapes in ``meshes``, cached as ``.npz`` files."""

    def __init__(self, meshes: Path, cache: Path):
        self.meshes, self.cache = meshes, cache / CACHE_TAG
        self.cache.mkdir(parents=True, exist_ok=True)

    def original(self, name: str):
        """``(vertices, faces, agd, thresholds)`` of a shape's original triangulation."""
        path = self.cache / f"{name}.truth.npz"
        if not path.exists():
            v, f = load_shape(self.meshes / name)
            agd = average_geodesic_distance(v, f, 128, zlib.crc32(name.encode()))
            thresholds = surface_tertiles(agd, v, f)
            np.savez(path, vertices=v, faces=f, agd=agd, thresholds=thresholds)
        data = np.load(path)
        return tuple(data[k] for k in ORIGINAL_KEYS)

    def copy(self, name: str, kind: str) -> dict[str, np.ndarray]:
        """A copy: ``vertices``, ``faces`` (in the original's frame) and the invariant inputs,
        computed on the copy turned by the rotation of seed ``rotation_seed(name, kind, 0)``."""
        path = self.cache / f"{name}.{kind}.npz"
        if not path.exists():
            cv, cf = make_copy(*self.original(name)[:2], kind)
            rotated = cv @ random_rotation(rotation_seed(name, kind, 0)).T
            np.savez(path, vertices=cv, faces=cf, **invariant_inputs(rotated, cf))
        return dict(np.load(path))

    def labels(self, name: str, kind: str, vertices: np.ndarray) -> np.ndarray:
        """``(V,)`` labels of a copy: the original's AGD at its closest points, cut at the
        original's tertiles."""
        v, f, agd, thresholds = self.original(name)
        values = agd if kind == "original" else correspondence(vertices, v, f).transfer(agd)
        return tertile_labels(values, thresholds)

    def sample(self, name: str, kind: str, rotation: int) -> tuple[dict, np.ndarray]:
        """``({input: (V, C)}, labels (V,))`` of a copy turned by rotation ``rotation`` (only
        ``xyz`` sees which: the other inputs are rotation invariant, computed once)."""
        data = self.copy(name, kind)
        turned = data["vertices"] @ random_rotation(rotation_seed(name, kind, rotation)).T
        inputs = {k: data[k] for k in INPUTS if k != "xyz"}
        return {**inputs, "xyz": xyz_input(turned)}, self.labels(name, kind, data["vertices"])
