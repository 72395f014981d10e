"""Mesh saliency of Lee, Varshney and Jacobs, "Mesh saliency", SIGGRAPH 2005 (paper ref. [1]).

1. Mean curvature ``C`` (:func:`mean_curvature`, Meyer et al. 2003).
2. Gaussian-weighted average over the Euclidean ball of radius ``2 sigma``,
   ``G(C, sigma)(v) = sum_{|x - v| <= 2 sigma} C(x) w / sum w``,
   ``w = exp(-|x - v|^2 / (2 sigma^2))``: a numba kernel over a grid of cubes, or with
   ``use_numba=False`` a k-d tree in chunks of points; never a dense all-pairs matrix.
3. Scales ``sigma_i = s_i eps``, ``s_i in {2, 3, 4, 5, 6}``, ``eps = 0.3 %`` of the
   bounding-box diagonal; the box is aligned with the principal axes by default
   (``frame="principal"``; Lee et al. use the coordinate axes), so that the result does not
   depend on the model's orientation.
4. Centre-surround ``S_i = |G(C, sigma_i) - G(C, 2 sigma_i)|``.
5. Normalisation after Itti et al. 1998: ``S_i`` rescaled to ``[0, 1]`` and multiplied by
   ``(1 - m_bar)^2``, ``m_bar`` the mean of the local maxima other than the global one (0 if
   there are none). A local maximum is ``>=`` every vertex within ``2 sigma_i`` (the Gaussian's
   support; Lee et al. name no neighbourhood), up to ``1e-9`` so that rounding cannot split
   ties. A constant ``S_i`` contributes nothing.
6. Saliency ``= sum_i`` of the normalised ``S_i``; 0 at vertices no face references.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from .._common.checks import check_choice
from .._common.errors import MissingDependencyError, ParameterError
from .._kernels import kernel_jit, kernel_thread_count, numba_available, run_workers
from ..mesh import as_mesh_tensors, vertex_normals
from ..operators.laplacians import laplacian_of_valid_mesh
from ..sparse.csr import row_ids
from .spectral import referenced

__all__ = ["LEE_SCALES", "bounding_box_diagonal", "lee_saliency", "mean_curvature"]

#: Lee et al.'s scale factors: ``sigma_i = s_i eps``.
LEE_SCALES = (2.0, 3.0, 4.0, 5.0, 6.0)
#: ``eps`` as a fraction of the bounding-box diagonal.
LEE_EPSILON = 0.003
_FRAMES = ("principal", "axis")
#: Step 5's tolerance on the neighbourhood maximum (the maps are in [0, 1]).
_TIE_TOLERANCE = 1e-9
#: Points per part a kernel worker takes.
_CHUNK = 256
#: Roughly how many neighbour pairs one chunk of the k-d tree query may list.
_PAIRS_PER_CHUNK = 4_000_000


def mean_curvature(vertices, faces) -> Tensor:
    """Signed mean curvature ``H_i = (L P)_i . n_i / (2 A_i)``: cotangent Laplacian
    ``L = D - W``, mixed Voronoi area ``A_i``, unit area-weighted normal ``n_i``; ``+1/R`` on an
    outward-oriented sphere of radius ``R``.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.

    Returns:
        ``(V,)`` float in the dtype of ``vertices``; 0 at unreferenced vertices.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    vertices = vertices.detach()
    lap = laplacian_of_valid_mesh(vertices, faces, "cotangent", "voronoi")
    stiffness = lap.stiffness()
    laplace = vertices.new_zeros(vertices.shape).index_add_(
        0, row_ids(stiffness.crow), stiffness.val.unsqueeze(1) * vertices[stiffness.col]
    )
    normals = vertex_normals(vertices, faces)
    area = lap.mass
    safe = torch.where(area > 0, area, torch.ones_like(area))
    return torch.where(area > 0, (laplace * normals).sum(dim=1) / (2.0 * safe), 0.0 * area)


def bounding_box_diagonal(points: np.ndarray, frame: str = "principal") -> float:
    """Length of the diagonal of the bounding box of ``(N, 3)`` points.

    Args:
        points: ``(N, 3)`` float array.
        frame: ``"principal"`` (box aligned with the principal axes of the points) or
            ``"axis"`` (the coordinate axes).
    """
    check_choice("frame", frame, _FRAMES)
    points = np.asarray(points, dtype=np.float64)
    if frame == "principal":
        centred = points - points.mean(axis=0)
        _, axes = np.linalg.eigh(centred.T @ centred)
        points = centred @ axes
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


if numba_available():
    from .._kernels.threads import next_part

    @kernel_jit(nogil=True)
    def _ball_worker(
        thread, counter, points, values, radii, gaussian, cells, dims, keys, starts, out, den
    ):  # pragma: no cover - compiled
        """:func:`_ball_reduce` on points sorted by cell, for the parts taken from ``counter``:
        the points of the 27 cells around each point's cell, accumulated as they are found."""
        while True:
            first = next_part(counter) * _CHUNK
            if first >= points.shape[0]:
                break
            for i in range(first, min(first + _CHUNK, points.shape[0])):
                for cell in range(27):
                    x = cells[i, 0] + cell // 9 - 1
                    y = cells[i, 1] + cell // 3 % 3 - 1
                    z = cells[i, 2] + cell % 3 - 1
                    if not (0 <= x < dims[0] and 0 <= y < dims[1] and 0 <= z < dims[2]):
                        continue
                    key = (x * dims[1] + y) * dims[2] + z
                    slot = np.searchsorted(keys, key)
                    if slot == keys.shape[0] or keys[slot] != key:
                        continue
                    for j in range(starts[slot], starts[slot + 1]):
                        d2 = 0.0
                        for a in range(3):
                            diff = points[i, a] - points[j, a]
                            d2 += diff * diff
                        for s in range(radii.shape[0]):
                            if d2 > radii[s] * radii[s]:
                                break
                            if gaussian:
                                w = math.exp(-d2 / (0.5 * radii[s] * radii[s]))
                                out[s, i] += w * values[0, j]
                                den[s, i] += w
                            elif values[s, j] > out[s, i]:
                                out[s, i] = values[s, j]


def _ball_reduce(points, values, radii, gaussian: bool, use_numba: bool) -> np.ndarray:
    """``values`` reduced over the ball of each radius around each point.

    Args:
        points: ``(N, 3)`` float64.
        values: ``(1, N)`` float64 with ``gaussian``, else ``(S, N)``.
        radii: ``(S,)`` float64, descending.
        gaussian: average ``values[0]`` with weights ``w = exp(-d^2 / 2 sigma^2)``,
            ``sigma = radii[s] / 2``, instead of taking the largest ``values[s]``.
        use_numba: the grid kernel, else the k-d tree.

    Returns:
        ``(S, N)`` float64: ``sum w values / sum w``, or the largest value within ``radii[s]``.
    """
    out = np.zeros((len(radii), len(points))) if gaussian else np.full_like(values, -np.inf)
    den = np.zeros_like(out)
    reach = float(radii[0])
    if use_numba:  # a grid of cubes of side reach; cell keys (x dims[1] + y) dims[2] + z
        cells = np.floor((points - points.min(axis=0)) / reach).astype(np.int64)
        dims = cells.max(axis=0) + 1
        if float(np.prod(dims.astype(np.float64))) > 2.0**62:
            raise ParameterError(f"epsilon {reach:g} is too small for a grid over this mesh")
        key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
        order = np.argsort(key, kind="stable")
        keys, counts = np.unique(key[order], return_counts=True)
        starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        sorted_points = np.ascontiguousarray(points[order])
        sorted_values = np.ascontiguousarray(values[:, order])
        grid = (np.ascontiguousarray(cells[order]), dims, keys, starts)
        threads = kernel_thread_count(torch.get_num_threads(), -(-len(points) // _CHUNK))
        args = (sorted_points, sorted_values, radii, gaussian, *grid, out, den)
        run_workers(_ball_worker, threads, np.zeros(1, dtype=np.int64), *args)
        result = np.empty_like(out)
        result[:, order] = out / den if gaussian else out
        return result
    from scipy import spatial

    tree = spatial.cKDTree(points)
    sample = points[:: max(1, points.shape[0] // 256)]
    per_point = max(1.0, float(np.mean(tree.query_ball_point(sample, reach, return_length=True))))
    chunk = max(64, int(_PAIRS_PER_CHUNK / per_point))
    for start in range(0, points.shape[0], chunk):
        block = spatial.cKDTree(points[start : start + chunk])
        pairs = block.sparse_distance_matrix(tree, reach, output_type="ndarray")
        rows, cols, dist = pairs["i"] + start, pairs["j"], pairs["v"]
        for s, radius in enumerate(radii):
            inside = dist <= radius
            r, c, d = rows[inside], cols[inside], dist[inside]
            if gaussian:
                w = np.exp(-(d * d) / (0.5 * radius * radius))
                out[s] += np.bincount(r, weights=w * values[0, c], minlength=len(points))
                den[s] += np.bincount(r, weights=w, minlength=len(points))
            else:
                np.maximum.at(out[s], r, values[s, c])
    return out / den if gaussian else out


def _suppression_factors(points, maps, radii, use_numba) -> np.ndarray:
    """``(S,)`` ``(M - m_bar)^2`` of each ``[0, 1]``-normalised map in ``maps`` ``(S, N)``,
    local maxima taken within ``radii`` ``(S,)`` (descending)."""
    neighbour_max = _ball_reduce(points, maps, radii, gaussian=False, use_numba=use_numba)
    factors = np.empty(maps.shape[0])
    for s, saliency_map in enumerate(maps):
        is_max = saliency_map >= neighbour_max[s] - _TIE_TOLERANCE
        is_max[int(np.argmax(saliency_map))] = False
        local = saliency_map[is_max]
        factors[s] = (1.0 - (float(local.mean()) if local.size else 0.0)) ** 2
    return factors


def lee_saliency(
    vertices,
    faces,
    scales: Sequence[float] = LEE_SCALES,
    epsilon: float | None = None,
    frame: str = "principal",
    curvature: Tensor | None = None,
    use_numba: bool | None = None,
) -> Tensor:
    """Mesh saliency of Lee, Varshney and Jacobs 2005 (module docstring).

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        scales: the factors ``s_i`` of ``sigma_i = s_i eps``.
        epsilon: ``eps`` in the units of ``vertices``; default ``0.3 %`` of
            :func:`bounding_box_diagonal` of the referenced vertices.
        frame: box frame for the default ``eps``, ``"principal"`` or ``"axis"``.
        curvature: optional ``(V,)`` per-vertex field to use (``None``:
            :func:`mean_curvature`).
        use_numba: run the pair loops with numba (default: when it is installed).

    Returns:
        ``(V,)`` non-negative saliency in the dtype of ``vertices`` (0 at unreferenced
        vertices).
    """
    scale_factors = np.asarray(list(scales), dtype=np.float64)
    if scale_factors.size == 0 or not bool(np.all(scale_factors > 0)):
        raise ParameterError(
            f"scales must be a non-empty sequence of positive numbers, got {scales}"
        )
    if use_numba is None:
        use_numba = numba_available()
    elif use_numba and not numba_available():
        raise MissingDependencyError("use_numba=True needs numba, which is not installed")
    vertices, faces = as_mesh_tensors(vertices, faces)
    vertices = vertices.detach()
    keep = referenced(faces, vertices.shape[0])
    if curvature is None:
        curvature = mean_curvature(vertices, faces)
    elif tuple(curvature.shape) != (vertices.shape[0],):
        raise ParameterError(
            f"curvature must have shape ({vertices.shape[0]},), got {tuple(curvature.shape)}"
        )
    points = vertices[keep].cpu().double().numpy()
    values = curvature.detach()[keep].cpu().double().numpy()
    if not np.all(np.isfinite(values)):
        raise ParameterError("curvature holds NaN or Inf values")
    if epsilon is None:
        epsilon = LEE_EPSILON * bounding_box_diagonal(points, frame)
    if not (isinstance(epsilon, (int, float)) and epsilon > 0):
        raise ParameterError(f"epsilon must be a positive number, got {epsilon!r}")

    # Every distinct sigma and 2 sigma once, the radii descending (as the kernels need).
    ascending = np.unique(np.concatenate([scale_factors, 2.0 * scale_factors]))
    radii = 2.0 * (ascending[::-1] * epsilon)
    averages = _ball_reduce(points, values[None], radii, gaussian=True, use_numba=use_numba)[::-1]
    centre = averages[np.searchsorted(ascending, scale_factors)]
    maps = np.abs(centre - averages[np.searchsorted(ascending, 2.0 * scale_factors)])  # (S, N)
    low = maps.min(axis=1, keepdims=True)
    spread = maps.max(axis=1, keepdims=True) - low
    flat = spread[:, 0] <= 0
    maps = np.where(spread > 0, (maps - low) / np.where(spread > 0, spread, 1.0), 0.0)
    order = np.argsort(-scale_factors)
    factors = np.zeros(len(scale_factors))
    factors[order] = _suppression_factors(
        points, maps[order], 2.0 * scale_factors[order] * epsilon, use_numba
    )
    factors[flat] = 0.0
    saliency = vertices.new_zeros(vertices.shape[0])
    saliency[keep] = torch.from_numpy(factors @ maps).to(vertices)
    return saliency
