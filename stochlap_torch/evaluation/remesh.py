"""Other triangulations of the same surface, and values carried between them, for the
discretisation-robustness benchmark and the segmentation example: quadric decimation
(fast-simplification), isotropic remeshing (pyacvd, the ``remesh`` extra), a random
similarity, and closest-point transfer (barycentric, on the closest triangle). Numpy arrays in
and out: ``vertices (V, 3) float64``, ``faces (F, 3) int64``.
"""

from __future__ import annotations

import warnings

import numpy as np

from .. import _kernels
from .._common.errors import MissingDependencyError, ParameterError


def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drops faces with a repeated index and the vertices no face references.

    Returns ``(vertices (V', 3) float64, faces (F', 3) int64)``, vertices in their old order.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    faces = faces[(faces != np.roll(faces, 1, axis=1)).all(axis=1)]
    used = np.unique(faces)
    remap = np.full(len(vertices), -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    return np.asarray(vertices, dtype=np.float64)[used], remap[faces]


def _check_target(num_vertices: int, have: int) -> int:
    if isinstance(num_vertices, bool) or int(num_vertices) != num_vertices or num_vertices < 4:
        raise ParameterError(f"num_vertices must be an integer >= 4, got {num_vertices!r}")
    if num_vertices > have:
        raise ParameterError(f"num_vertices={num_vertices} exceeds the mesh's {have} vertices")
    return int(num_vertices)


def decimate(vertices: np.ndarray, faces: np.ndarray, num_vertices: int):
    """Quadric decimation (fast-simplification) to about ``num_vertices`` vertices: new
    positions, new triangles, as another level of detail would have them. Returns
    ``(vertices, faces)``, compacted."""
    import fast_simplification

    target = _check_target(num_vertices, len(vertices))
    points, triangles = fast_simplification.simplify(
        np.asarray(vertices, dtype=np.float32),
        np.asarray(faces, dtype=np.int32),
        target_reduction=1.0 - target / len(vertices),
    )
    return compact(np.asarray(points, dtype=np.float64), np.asarray(triangles, dtype=np.int64))


def isotropic_remesh(
    vertices: np.ndarray, faces: np.ndarray, num_vertices: int, subdivide: int = 2
):
    """Isotropic remeshing by ACVD clustering (pyacvd, the ``remesh`` extra) to about
    ``num_vertices`` vertices: the surface, split ``subdivide`` times, is clustered into regions
    of equal area whose centroids become the vertices. Returns ``(vertices, faces)``, compacted.
    """
    try:
        import pyacvd
        import pyvista
    except ImportError as error:
        raise MissingDependencyError(
            'isotropic remeshing needs pyacvd: pip install "stochlap_torch[remesh]"'
        ) from error
    target = _check_target(num_vertices, 10**12)
    faces = np.asarray(faces, dtype=np.int64)
    cells = np.hstack([np.full((len(faces), 1), 3, dtype=np.int64), faces]).ravel()
    with warnings.catch_warnings():  # pyacvd 0.4 calls a deprecated pyvista accessor
        warnings.filterwarnings("ignore", message=".*deprecated")
        clustering = pyacvd.Clustering(pyvista.PolyData(np.asarray(vertices, np.float64), cells))
        if subdivide:
            clustering.subdivide(subdivide)
        clustering.cluster(target)
        remeshed = clustering.create_mesh()
    new_faces = np.asarray(remeshed.faces).reshape(-1, 4)[:, 1:]
    return compact(np.asarray(remeshed.points, dtype=np.float64), new_faces)


def random_similarity(seed: int) -> tuple[np.ndarray, float, np.ndarray]:
    """A random rotation ``(3, 3)``, scale in ``[0.2, 5]`` and translation ``(3,)``.

    Apply as ``scale * vertices @ rotation.T + translation``.
    """
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q, float(rng.uniform(0.2, 5.0)), rng.normal(size=3)


class Correspondence:
    """The closest point on a mesh A of every point of B: ``face (N,)`` and ``bary (N, 3)``.

    :meth:`transfer` carries per-vertex values of A (``(V_A, ...)``) to the points of B by
    barycentric interpolation; ``points`` are the closest points themselves ``(N, 3)``.
    """

    def __init__(self, faces_a: np.ndarray, face: np.ndarray, bary: np.ndarray, points: np.ndarray):
        self.faces_a, self.face, self.bary, self.points = faces_a, face, bary, points

    def transfer(self, values: np.ndarray) -> np.ndarray:
        """``(V_A, ...)`` values of A at the points of B: ``(N, ...)``."""
        return np.einsum("ij,ij...->i...", self.bary, np.asarray(values)[self.faces_a[self.face]])


def correspondence(
    points: np.ndarray,
    vertices_a: np.ndarray,
    faces_a: np.ndarray,
    candidates: int = 8,
    threads: int = 1,
) -> Correspondence:
    """Closest points on mesh A of ``points (N, 3)`` (in A's frame), among the triangles
    around their ``candidates`` nearest vertices of A: exact where the triangles are not much
    larger than their spacing, as on the meshes compared here."""
    from scipy.spatial import cKDTree

    vertices_a = np.asarray(vertices_a, dtype=np.float64)
    faces_a = np.asarray(faces_a, dtype=np.int64)
    points = np.asarray(points, dtype=np.float64)
    k = min(candidates, len(vertices_a))
    _, near = cKDTree(vertices_a).query(points, k=k)
    near = np.asarray(near, dtype=np.int64).reshape(len(points), k)
    face, bary = _kernels.closest_triangles(points, vertices_a, faces_a, near, threads)
    closest = np.einsum("ij,ijc->ic", bary, vertices_a[faces_a[face]])
    return Correspondence(faces_a, face, bary, closest)
