"""Spectral baselines (paper Sec. 2 and 3.6, Fig. 5): Laplacian eigenpairs, the mesh
projected onto the first ``k`` of them, and the heat kernel signature.

The eigenproblem is ``L phi = lambda M phi`` with the lumped mass ``M`` of
:mod:`stochlap_torch.operators` (the identity for the uniform Laplacian), the eigenvectors
``M``-orthonormal (``Phi^T M Phi = I``), so that the projection onto the first ``k`` is
``P_k = Phi_k Phi_k^T M P`` (Eq. 15 in the ``M`` inner product): ``P`` itself with all of
them, the ``M``-weighted centroid with ``k = 1`` on a connected mesh.

Solvers: ``"dense"``, ``torch.linalg.eigh`` of ``M^-1/2 L M^-1/2`` in the vertices' dtype, for
meshes up to ``dense_limit`` vertices (``O(V^3)`` time, ``O(V^2)`` memory); ``"sparse"``,
scipy's ``eigsh`` in float64, shift-invert with a small negative shift (``L - sigma M`` is
positive definite though ``L`` is singular), one retry, then :class:`EigenSolverError`.

The heat kernel signature (Sun, Ovsjanikov and Guibas 2009; paper ref. [4]) is
``HKS(x, t) = sum_i exp(-lambda_i t) phi_i(x)^2`` over the computed pairs, ``phi_1``
included, at times log-spaced from ``4 ln 10 / lambda_max`` to ``4 ln 10 / lambda_2``
(``lambda_2`` the first eigenvalue above ``1e-8 lambda_max``: several components repeat 0).

Only the vertices some face references take part: the eigenvectors and the signature are zero
at the others, and the reconstruction leaves them in place.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .._common.checks import check_choice
from .._common.errors import ParameterError, StochlapError
from ..mesh import as_mesh_tensors
from ..operators.laplacians import (
    MASS_TYPES,
    MeshLaplacian,
    check_laplacian,
    laplacian_of_valid_mesh,
)

__all__ = [
    "DENSE_LIMIT",
    "EIGEN_METHODS",
    "EigenSolverError",
    "Eigenpairs",
    "heat_kernel_signature",
    "heat_kernel_times",
    "laplacian_eigenpairs",
    "spectral_reconstruction",
]

logger = logging.getLogger(__name__)

#: Above this many (referenced) vertices ``method="auto"`` uses the sparse solver.
DENSE_LIMIT = 2000
#: ``method=`` values of :func:`laplacian_eigenpairs`.
EIGEN_METHODS = ("auto", "dense", "sparse")
#: Shift of the first sparse attempt, relative to the median of ``diag(L) / diag(M)``; the
#: retry uses ten times this.
_RELATIVE_SHIFT = 1e-6
#: Eigenvalues below this fraction of the largest count as zero when choosing ``lambda_2``.
_ZERO_EIGENVALUE = 1e-8


class EigenSolverError(StochlapError, RuntimeError):
    """The sparse eigensolver failed with every shift and Krylov space size it tried."""


@dataclass(frozen=True)
class Eigenpairs:
    """The first eigenpairs of ``L phi = lambda M phi``.

    Attributes:
        values: ``(k,)`` float eigenvalues, ascending (the first is ~0).
        vectors: ``(V, k)`` float ``M``-orthonormal eigenvectors; zero at unreferenced
            vertices. Each is signed so that its entry of largest magnitude is positive.
        mass: ``(V,)`` float diagonal of ``M``.
        method: ``"dense"`` or ``"sparse"``, the solver that produced them.
    """

    @property
    def num_pairs(self) -> int:
        """``k``."""
        return int(self.values.shape[0])

    values: Tensor
    vectors: Tensor
    mass: Tensor
    method: str


def referenced(faces: Tensor, num_vertices: int) -> Tensor:
    """``(V,)`` bool: the vertex appears in some face."""
    mask = torch.zeros(num_vertices, dtype=torch.bool, device=faces.device)
    return mask.index_fill_(0, faces.reshape(-1), True)


def _sparse_eigenpairs(stiffness, mass: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """First ``k`` pairs of ``(L, diag(mass))`` by shift-invert ARPACK, with one retry."""
    from scipy import sparse
    from scipy.sparse import linalg

    n = stiffness.shape[0]
    mass_matrix = sparse.diags(mass).tocsc()
    stiffness = stiffness.tocsc()
    # The median, not the mean: a few vertices of almost no area (a decimated or graded mesh)
    # push the mean far up, and eigsh is slow with a shift far from 0.
    typical = float(np.median(stiffness.diagonal()[mass > 0] / mass[mass > 0]))
    attempts = [
        (-_RELATIVE_SHIFT * typical, min(n - 1, max(2 * k + 1, 20))),
        (-10.0 * _RELATIVE_SHIFT * typical, min(n - 1, max(4 * k + 1, 2 * k + 40))),
    ]
    failures = []
    # A fixed start vector: ARPACK's own is random, and the pairs would differ in their last
    # digits from call to call (and the HKS, and the detectors built on it).
    start = np.random.default_rng(0).standard_normal(n)
    for shift, ncv in attempts:
        try:
            values, vectors = linalg.eigsh(
                stiffness, k=k, M=mass_matrix, sigma=shift, which="LM", ncv=ncv, v0=start
            )
        except (linalg.ArpackNoConvergence, linalg.ArpackError, RuntimeError) as exc:
            logger.warning("eigsh failed with sigma=%.3g, ncv=%d: %s", shift, ncv, exc)
            failures.append(f"sigma={shift:.3g}, ncv={ncv}: {exc}")
            continue
        order = np.argsort(values)
        return values[order], vectors[:, order]
    raise EigenSolverError(
        f"eigsh found no {k} eigenpairs for a {n}-vertex mesh: "
        + "; ".join(failures)
        + ". Try fewer eigenpairs, method='dense' on a small mesh, or check the mesh for "
        "degenerate faces."
    )


def _solve(lap: MeshLaplacian, index: Tensor, k: int, method: str):
    """``(values, vectors)`` of the Laplacian restricted to the vertices ``index``."""
    mass = lap.mass[index]
    if not bool((mass > 0).all()):
        bad = index[mass <= 0][:8].tolist()
        raise ParameterError(
            f"vertices {bad} have zero mass (every face around them has zero area); the "
            "generalised eigenproblem needs a positive mass at every referenced vertex"
        )
    if method == "dense":  # eigh of M^-1/2 L M^-1/2
        scale = mass.rsqrt()
        symmetric = scale.unsqueeze(1) * lap.to_dense()[index][:, index] * scale.unsqueeze(0)
        values, vectors = torch.linalg.eigh(0.5 * (symmetric + symmetric.T))
        return values[:k], scale.unsqueeze(1) * vectors[:, :k]
    sub = lap.stiffness_scipy()
    if index.shape[0] < lap.num_vertices:
        index_np = index.cpu().numpy()
        sub = sub[index_np][:, index_np]
    values, vectors = _sparse_eigenpairs(sub, mass.detach().cpu().double().numpy(), k)
    vectors, mass64 = torch.from_numpy(vectors), mass.double().cpu()
    # Phi R^-1 with R^T R = Phi^T M Phi (Cholesky), so that Phi^T M Phi = I.
    gram = vectors.T @ (mass64.unsqueeze(1) * vectors)
    try:
        upper = torch.linalg.cholesky(0.5 * (gram + gram.T), upper=True)
    except torch.linalg.LinAlgError as exc:
        raise EigenSolverError(f"eigsh returned linearly dependent eigenvectors: {exc}") from exc
    vectors = torch.linalg.solve_triangular(upper, vectors, upper=True, left=False)
    return torch.from_numpy(values).to(lap.mass), vectors.to(lap.mass)


def laplacian_eigenpairs(
    vertices,
    faces,
    num_eigenpairs: int,
    laplacian: str = "cotangent",
    mass: str = "voronoi",
    method: str = "auto",
    dense_limit: int = DENSE_LIMIT,
) -> Eigenpairs:
    """The ``num_eigenpairs`` smallest eigenpairs of ``L phi = lambda M phi``.

    Args:
        vertices: ``(V, 3)`` float tensor; the dense solver works in its dtype, the sparse one
            in float64 (results are cast back).
        faces: ``(F, 3)`` integer tensor.
        num_eigenpairs: ``k >= 1``, at most the number of referenced vertices.
        laplacian: ``"cotangent"`` or ``"uniform"``.
        mass: the cotangent Laplacian's lumped mass, ``"voronoi"`` or ``"barycentric"``.
        method: ``"auto"`` (dense up to ``dense_limit`` vertices), ``"dense"`` or ``"sparse"``.
        dense_limit: vertex count above which ``"auto"`` switches to the sparse solver.

    Returns:
        :class:`Eigenpairs`; :class:`EigenSolverError` if the sparse solver fails.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    return _eigenpairs(
        vertices.detach(), faces, num_eigenpairs, laplacian, mass, method, dense_limit
    )


def _eigenpairs(vertices, faces, num_eigenpairs, laplacian, mass, method, dense_limit):
    """:func:`laplacian_eigenpairs` of checked tensors."""
    check_laplacian(laplacian)
    check_choice("mass", mass, MASS_TYPES)
    check_choice("method", method, EIGEN_METHODS)
    keep = referenced(faces, vertices.shape[0])
    n, k = int(keep.sum()), int(num_eigenpairs)
    if not 1 <= k <= n:
        raise ParameterError(f"num_eigenpairs must lie in [1, {n}] for this mesh, got {k}")
    if method == "auto":
        method = "dense" if n <= dense_limit or k >= n - 1 else "sparse"
    if method == "sparse" and k >= n - 1:
        raise ParameterError(f"method='sparse' needs num_eigenpairs < V - 1 = {n - 1}, got {k}")
    lap = laplacian_of_valid_mesh(vertices, faces, laplacian, mass)
    values, sub_vectors = _solve(lap, keep.nonzero().flatten(), k, method)
    # Flip each vector so that its entry of largest magnitude is positive.
    signs = torch.sign(sub_vectors.gather(0, sub_vectors.abs().argmax(dim=0).unsqueeze(0)))
    vectors = vertices.new_zeros(vertices.shape[0], k)
    vectors[keep] = sub_vectors * torch.where(signs == 0, torch.ones_like(signs), signs)
    return Eigenpairs(values, vectors, lap.mass, method)


def _pairs(eigenpairs, vertices: Tensor, faces: Tensor, k: int, minimum: int, *solver):
    """``eigenpairs``, checked against the mesh (at least ``minimum`` pairs) and cast to the
    vertices' dtype and device, or ``k`` pairs computed with the ``solver`` options."""
    if eigenpairs is None:
        return _eigenpairs(vertices.detach(), faces, k, *solver)
    if not isinstance(eigenpairs, Eigenpairs):
        raise ParameterError(
            f"eigenpairs must be an Eigenpairs (from laplacian_eigenpairs), got {type(eigenpairs)}"
        )
    pairs, num_vertices = eigenpairs, vertices.shape[0]
    if pairs.vectors.ndim != 2 or pairs.vectors.shape[0] != num_vertices:
        raise ParameterError(
            f"eigenpairs are of a mesh with {pairs.vectors.shape[0]} vertices, "
            f"this one has {num_vertices}"
        )
    if pairs.num_pairs < minimum:
        raise ParameterError(f"{minimum} eigenpairs are needed, {pairs.num_pairs} were given")
    cast = (part.to(vertices) for part in (pairs.values, pairs.vectors, pairs.mass))
    return Eigenpairs(*cast, pairs.method)


def spectral_reconstruction(
    vertices,
    faces,
    k_values: Sequence[int],
    laplacian: str = "cotangent",
    mass: str = "voronoi",
    method: str = "auto",
    dense_limit: int = DENSE_LIMIT,
    eigenpairs: Eigenpairs | None = None,
) -> Tensor:
    """The mesh projected onto its first ``k`` Laplacian eigenvectors, ``P_k = Phi_k Phi_k^T M
    P``, for each ``k``; unreferenced vertices keep their input positions.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        k_values: numbers of eigenvectors, each in ``[1, V_referenced]``.
        laplacian, mass, method, dense_limit: as in :func:`laplacian_eigenpairs`.
        eigenpairs: precomputed :class:`Eigenpairs` of this mesh (at least ``max(k_values)``
            of them; ``None``: computed here); then the four arguments above are not used.

    Returns:
        ``(len(k_values), V, 3)`` positions in the dtype of ``vertices``.
    """
    ks = [int(k) for k in k_values]
    if not ks:
        raise ParameterError("k_values is empty")
    if min(ks) < 1:
        raise ParameterError(f"every k must be >= 1, got {ks}")
    vertices, faces = as_mesh_tensors(vertices, faces)
    vertices = vertices.detach()
    solver = (laplacian, mass, method, dense_limit)
    pairs = _pairs(eigenpairs, vertices, faces, max(ks), max(ks), *solver)
    coefficients = pairs.vectors.T @ (pairs.mass.unsqueeze(1) * vertices)  # (k_max, 3)
    keep = referenced(faces, vertices.shape[0]).unsqueeze(1)
    out = [torch.where(keep, pairs.vectors[:, :k] @ coefficients[:k], vertices) for k in ks]
    return torch.stack(out)


def heat_kernel_times(eigenvalues: Tensor, num_times: int = 16) -> Tensor:
    """Sun et al.'s ``num_times`` times (module docstring).

    Args:
        eigenvalues: ``(k,)`` float, ascending, at least one of them non-zero.
        num_times: ``T >= 1`` (``T = 1`` gives ``t_min`` only).

    Returns:
        ``(T,)`` float, ascending, in the dtype of ``eigenvalues``.
    """
    if num_times < 1:
        raise ParameterError(f"num_times must be >= 1, got {num_times}")
    largest = float(eigenvalues.max())
    positive = eigenvalues[eigenvalues > _ZERO_EIGENVALUE * max(largest, 0.0)]
    if largest <= 0.0 or positive.numel() == 0:
        raise ParameterError(
            "no non-zero eigenvalue among the computed ones; compute more eigenpairs"
        )
    t_min = 4.0 * math.log(10.0) / largest
    t_max = 4.0 * math.log(10.0) / float(positive.min())
    to = {"dtype": eigenvalues.dtype, "device": eigenvalues.device}
    return torch.logspace(math.log10(t_min), math.log10(t_max), num_times, **to)


def heat_kernel_signature(
    vertices,
    faces,
    num_eigenpairs: int = 128,
    num_times: int = 16,
    laplacian: str = "cotangent",
    mass: str = "voronoi",
    times: Tensor | None = None,
    method: str = "auto",
    dense_limit: int = DENSE_LIMIT,
    eigenpairs: Eigenpairs | None = None,
) -> Tensor:
    """The heat kernel signature of every vertex at ``T`` times (the eigendecomposition is the
    whole cost: pass :func:`laplacian_eigenpairs` as ``eigenpairs`` to evaluate other times).

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        num_eigenpairs: eigenpairs to sum over (capped at the number of referenced vertices).
        num_times: ``T``, used when ``times`` is ``None``.
        laplacian, mass, method, dense_limit: as in :func:`laplacian_eigenpairs`.
        times: optional ``(T,)`` explicit positive times (``None``: :func:`heat_kernel_times`).
        eigenpairs: precomputed :class:`Eigenpairs` of this mesh (``None``: computed here); then
            ``num_eigenpairs`` and the four arguments above are not used.

    Returns:
        ``(V, T)`` float in the dtype of ``vertices``; zero rows at unreferenced vertices.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    keep = referenced(faces, vertices.shape[0])
    if eigenpairs is None and num_eigenpairs < 2:
        raise ParameterError(f"num_eigenpairs must be >= 2, got {num_eigenpairs}")
    k = min(int(num_eigenpairs), int(keep.sum()))
    pairs = _pairs(eigenpairs, vertices, faces, k, 2, laplacian, mass, method, dense_limit)
    if times is None:
        times = heat_kernel_times(pairs.values, num_times)
    else:
        times = torch.as_tensor(times, dtype=pairs.values.dtype, device=pairs.values.device)
        if times.ndim != 1 or times.numel() == 0 or not bool((times > 0).all()):
            raise ParameterError("times must be a non-empty 1-D tensor of positive values")
    decay = torch.exp(-pairs.values.clamp(min=0.0).unsqueeze(1) * times.unsqueeze(0))  # (k, T)
    signature = pairs.vectors.square() @ decay
    signature[~keep] = 0.0
    return signature
