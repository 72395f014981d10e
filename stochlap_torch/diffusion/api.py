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
            flow into ``positions`` through ``P^(k) = F^(k) P`` with the operators held
            constant. Meshes of :data:`~stochlap_torch.mesh.LOCALITY_MIN_VERTICES` or more
            are processed in a cache-friendly vertex order internally; every output is in the
            input's order.
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``; entries of the normalised product below it are
            dropped at every step.
        return_operators: keep all ``F^(k)`` (costs ``K`` times the memory of one).
        max_memory, progress: as for :func:`~stochlap_torch.diffusion.run_steps`.
        backend: one of :data:`~stochlap_torch.diffusion.BACKENDS`; ``"cuda"`` (the CUDA kernel
            of the streamed steps) is experimental: not yet checked on a GPU
            (``benchmarks/gpu.py``), and runs only when asked for by name.
        batch: optional ``(V,)`` int64 mesh index of every vertex when ``vertices`` and
            ``faces`` pack several meshes (:class:`~stochlap_torch.mesh.MeshBatch`); every
            per-vertex output then equals that of a separate run on each mesh.
        positions: compute ``P^(k) = F^(k) P``. ``False`` computes the difference maps alone,
            all that Algorithm 2 needs, and skips the product with the positions at every
            scale; ``positions`` and ``coefficients`` then have no channels, ``(K, V, 0)``.

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
    # Coordinates so large or small that squared edge lengths would overflow or underflow are
    # scaled by a power of two (exact; the operators are scale invariant), then scaled back.
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
    steps = run_steps(ops, points, num_scales, threshold, **options)
    operators = steps.operators
    return MultiscaleRepresentation(
        positions=steps.positions if scale == 1.0 else steps.positions / scale,
        differences=steps.differences,
        entries=torch.tensor(steps.entries, dtype=torch.int64),
        operators=None if operators is None else [op.to_sparse_csr() for op in operators],
        batch=batch,
    )
