"""``multiscale_representation``: a mesh in, Algorithm 1's representation out."""

from __future__ import annotations

import torch
from torch import Tensor

from ..mesh import MeshError, Renumbering, as_mesh_tensors, check_batch, extent_scale, validate_mesh
from ..operators import operators_of_valid_mesh
from ..params import PaperParams
from .engine import run_steps
from .parameters import ProgressCallback, check_parameters, resolve_backend
from .representation import MultiscaleRepresentation


def multiscale_representation(
    vertices,
    faces,
    num_scales: int = PaperParams.num_scales,
    threshold: float = PaperParams.threshold,
    return_operators: bool = False,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    backend: str = "auto",
    batch: Tensor | None = None,
    positions: bool = True,
) -> MultiscaleRepresentation:
    """Multiscale representation of a mesh (Algorithm 1) with the difference maps of Alg. 2.

    Args:
        vertices: ``(V, 3)`` float tensor; its dtype and device are kept throughout. Gradients
            flow into ``positions`` through ``P^(k) = F^(k) P``, the operators held constant.
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``, below which entries are dropped at every step.
        return_operators: keep all ``F^(k)`` (costs ``K`` times the memory of one).
        max_memory: byte budget (default: ``$STOCHLAP_MAX_MEMORY``, else half the physical memory).
        progress: called as ``progress(k, K)`` as the run advances (``None``: no reports).
        backend: one of :data:`~stochlap_torch.diffusion.BACKENDS`; ``"cuda"`` is
            experimental (not yet checked on a GPU) and runs only when asked for by name.
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch
            (:class:`~stochlap_torch.mesh.MeshBatch`; ``None``: one mesh); outputs equal
            separate runs.
        positions: compute ``P^(k) = F^(k) P``; ``False``: the difference maps alone (all
            Algorithm 2 needs), ``positions`` and ``coefficients`` ``(K, V, 0)``.

    Raises:
        MeshError: bad input mesh.
        ValueError: bad ``num_scales`` or ``threshold``.
        MemoryBudgetError: the operators would not fit the budget.
    """
    num_scales, threshold = check_parameters(num_scales, threshold)
    # Zero-length edges are caught where the weights are built (abs_laplacian).
    points, faces = as_mesh_tensors(vertices, faces, check_edge_lengths=False)
    backend = resolve_backend(backend, points.device)
    if batch is not None:
        batch = check_batch(batch, points.shape[0], faces)
    # A power of two keeps squared edge lengths finite (exact; the operators are scale
    # invariant), then scaled back.
    scale = extent_scale(points)
    scaled = points if scale == 1.0 else points * scale
    # Large meshes: work in a cache-friendly vertex order, hand results back in file order.
    renumbering = Renumbering.for_locality(scaled)
    work_points, work_faces, work_batch = (
        (scaled, faces, batch) if renumbering is None else renumbering.mesh(scaled, faces, batch)
    )
    try:
        with torch.no_grad():
            ops = operators_of_valid_mesh(work_points.detach(), work_faces, work_batch)
    except MeshError:
        if renumbering is not None:
            validate_mesh(points, faces)  # the same error, in the caller's vertex numbering
        raise
    options = {"backend": backend, "keep_operators": return_operators, "progress": progress}
    points = work_points if positions else work_points[:, :0]
    options.update(max_memory=max_memory, renumbering=renumbering)
    return run_steps(ops, points, num_scales, threshold, **options).representation(scale, batch)
