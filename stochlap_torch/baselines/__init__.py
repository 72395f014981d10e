"""Baselines the paper compares against (Sec. 2, 4.1, 4.4; Figs. 5 and 11).

* :mod:`.laplacian_saliency`: Algorithm 2 run with the uniform or cotangent Laplacian
  (:mod:`stochlap_torch.operators.laplacians`) in place of the stochastic one (Fig. 11).
* :mod:`.spectral`: Laplacian eigenpairs (dense ``torch.linalg.eigh`` or sparse shift-invert
  ``eigsh``), the mesh projected onto its first ``k`` eigenvectors (Fig. 5) and the heat
  kernel signature of Sun et al. 2009.
* :mod:`.lee_saliency`: the mesh saliency of Lee, Varshney and Jacobs 2005.

The Laplacians themselves (uniform, cotangent, lumped masses) live in
:mod:`stochlap_torch.operators`.
"""

from .laplacian_saliency import laplacian_saliency
from .lee_saliency import LEE_SCALES, bounding_box_diagonal, lee_saliency, mean_curvature
from .spectral import (
    DENSE_LIMIT,
    EIGEN_METHODS,
    Eigenpairs,
    EigenSolverError,
    heat_kernel_signature,
    heat_kernel_times,
    laplacian_eigenpairs,
    spectral_reconstruction,
)

__all__ = [
    "DENSE_LIMIT",
    "EIGEN_METHODS",
    "LEE_SCALES",
    "EigenSolverError",
    "Eigenpairs",
    "bounding_box_diagonal",
    "heat_kernel_signature",
    "heat_kernel_times",
    "laplacian_eigenpairs",
    "laplacian_saliency",
    "lee_saliency",
    "mean_curvature",
    "spectral_reconstruction",
]
