"""Baselines the paper compares against (Sec. 2, 4.1, 4.4; Figs. 5 and 11).

* :mod:`.laplacian_saliency`: Algorithm 2 run with the uniform or cotangent Laplacian
  (:mod:`stochlap_torch.operators.laplacians`) in place of the stochastic one (Fig. 11).
* :mod:`.spectral`: Laplacian eigenpairs (dense ``torch.linalg.eigh`` or sparse shift-invert
  ``eigsh``) and the mesh projected onto its first ``k`` eigenvectors (Fig. 5).
* :mod:`.heat_kernel`: the heat kernel signature of Sun et al. 2009.
* :mod:`.lee_saliency`: the mesh saliency of Lee, Varshney and Jacobs 2005.

The Laplacians themselves live in :mod:`stochlap_torch.operators` and are re-exported here.
"""

from ..operators.laplacians import (
    LAPLACIANS,
    MASS_TYPES,
    MeshLaplacian,
    cotangent_laplacian,
    face_cotangents,
    laplacian_operators,
    lumped_mass,
    mesh_laplacian,
    uniform_laplacian,
)
from .heat_kernel import heat_kernel_signature, heat_kernel_times
from .laplacian_saliency import laplacian_saliency
from .lee_saliency import LEE_SCALES, bounding_box_diagonal, lee_saliency, mean_curvature
from .spectral import (
    DENSE_LIMIT,
    EIGEN_METHODS,
    Eigenpairs,
    EigenSolverError,
    laplacian_eigenpairs,
    spectral_reconstruction,
)

__all__ = [
    "DENSE_LIMIT",
    "EIGEN_METHODS",
    "LAPLACIANS",
    "LEE_SCALES",
    "MASS_TYPES",
    "EigenSolverError",
    "Eigenpairs",
    "MeshLaplacian",
    "bounding_box_diagonal",
    "cotangent_laplacian",
    "face_cotangents",
    "heat_kernel_signature",
    "heat_kernel_times",
    "laplacian_eigenpairs",
    "laplacian_operators",
    "laplacian_saliency",
    "lee_saliency",
    "lumped_mass",
    "mean_curvature",
    "mesh_laplacian",
    "spectral_reconstruction",
    "uniform_laplacian",
]
