"""Baselines the paper compares against (Sec. 2, 4.1, 4.4; Figs. 5 and 11).

* :mod:`.laplacian_saliency`: Algorithm 2 run with the uniform or cotangent Laplacian
  (:mod:`stochlap_torch.operators.laplacians`) in place of the stochastic one (Fig. 11).
* :mod:`.spectral`: Laplacian eigenpairs (dense ``torch.linalg.eigh`` or sparse shift-invert
  ``eigsh``), the mesh projected onto its first ``k`` eigenvectors (Fig. 5) and the heat
  kernel signature of Sun et al. 2009.
* :mod:`.lee_saliency`: the mesh saliency of Lee, Varshney and Jacobs 2005.
"""

from . import laplacian_saliency as _laplacian
from . import lee_saliency as _lee
from . import spectral
from .laplacian_saliency import *  # noqa: F403
from .lee_saliency import *  # noqa: F403
from .spectral import *  # noqa: F403

__all__ = sorted(name for module in (_laplacian, _lee, spectral) for name in module.__all__)
