"""The heat kernel signature (Sun, Ovsjanikov and Guibas 2009; paper Sec. 2, ref. [4]).

``HKS(x, t) = h_t(x, x) = sum_i exp(-lambda_i t) phi_i(x)^2`` over the computed eigenpairs of
``L phi = lambda M phi`` (:func:`~.spectral.laplacian_eigenpairs`, ``M``-orthonormal
``phi_i``, the constant ``phi_1`` included). Following Sun et al., the times are
logarithmically spaced from ``t_min = 4 ln 10 / lambda_max`` to ``t_max = 4 ln 10 / lambda_2``,
``lambda_max`` the largest computed eigenvalue and ``lambda_2`` the smallest non-zero one
(the first above ``1e-8 lambda_max``; on a mesh of several components the zero eigenvalue is
repeated). Every term is positive and decreasing in ``t``, and so is the signature.

Vertices that no face references carry no heat (they have no mass and no edges): their rows
are 0, so that no output holds NaN.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._common.errors import ParameterError
from ..mesh import as_mesh_tensors
from .spectral import DENSE_LIMIT, Eigenpairs, _eigenpairs, check_eigenpairs, referenced

__all__ = ["heat_kernel_signature", "heat_kernel_times"]

#: Eigenvalues below this fraction of the largest count as zero when choosing ``lambda_2``.
_ZERO_EIGENVALUE = 1e-8


def heat_kernel_times(eigenvalues: Tensor, num_times: int = 16) -> Tensor:
    """Sun et al.'s time samples: ``num_times`` log-spaced from ``4 ln10 / lambda_max`` to
    ``4 ln10 / lambda_2``.

    Args:
        eigenvalues: ``(k,)`` float, ascending.
        num_times: ``T >= 1`` (``T = 1`` gives ``t_min`` only).

    Returns:
        ``(T,)`` float, ascending, in the dtype of ``eigenvalues``.

    Raises:
        ValueError: fewer than one non-zero eigenvalue, or ``num_times < 1``.
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
    """The heat kernel signature of every vertex at ``T`` times.

    The eigendecomposition is the whole cost: compute it once with
    :func:`~.spectral.laplacian_eigenpairs` and pass it as ``eigenpairs`` to evaluate other
    times (or the same signature again) for free.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        num_eigenpairs: eigenpairs to sum over (capped at the number of referenced vertices).
        num_times: ``T``, used when ``times`` is ``None``.
        laplacian: ``"cotangent"`` (default) or ``"uniform"``.
        mass: lumped mass of the cotangent Laplacian, ``"voronoi"`` or ``"barycentric"``.
        times: optional ``(T,)`` explicit positive times instead of :func:`heat_kernel_times`.
        method, dense_limit: eigensolver choice, see
            :func:`~stochlap_torch.baselines.spectral.laplacian_eigenpairs`.
        eigenpairs: precomputed :class:`~.spectral.Eigenpairs` of this mesh; then
            ``num_eigenpairs``, ``laplacian``, ``mass``, ``method`` and ``dense_limit`` are
            not used.

    Returns:
        ``(V, T)`` float in the dtype of ``vertices``; zero rows at unreferenced vertices.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    keep = referenced(faces, vertices.shape[0])
    if eigenpairs is None:
        if num_eigenpairs < 2:
            raise ParameterError(f"num_eigenpairs must be >= 2, got {num_eigenpairs}")
        k = min(int(num_eigenpairs), int(keep.sum()))
        pairs = _eigenpairs(vertices.detach(), faces, k, laplacian, mass, method, dense_limit)
    else:
        pairs = check_eigenpairs(eigenpairs, vertices, minimum=2)
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
