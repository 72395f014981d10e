"""Several processes: loopback process groups and a row partition of the diffusion steps.

Row ``i`` of ``F^(k)`` depends only on row ``i`` of ``F^(k-1)``, on ``Lhat`` and on ``alpha``.
:func:`partitioned_multiscale` therefore gives each rank a contiguous block of rows: every rank
builds ``Lhat`` and ``alpha`` for the whole mesh (``O(V)``), runs every step on its rows only
(the fused CPU kernel, or the torch ops elsewhere, on the row-sliced CSR), and the positions
and difference maps are gathered at the end. Each rank holds ``1 / world_size`` of every
``F^(k)``; the results equal a single-process run.

The ``nn.Module`` layers have no state, so they work unchanged inside
``torch.nn.parallel.DistributedDataParallel``; :func:`init_loopback_group` starts a process
group on ``127.0.0.1`` for tests and single-machine runs.
"""

from __future__ import annotations

import logging
import os
import socket
from pathlib import Path

import torch
import torch.distributed as dist
from torch import Tensor

from .batch import check_batch
from .diffusion import MultiscaleRepresentation, check_parameters, fused_step, resolve_backend
from .mesh import as_mesh_tensors
from .operators import LOCALITY_MIN_VERTICES, locality_order, mesh_operators
from .sparse_ops import CSR

__all__ = [
    "find_free_port",
    "init_loopback_group",
    "partitioned_multiscale",
    "row_partition",
    "slice_rows",
]

logger = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"


def find_free_port() -> int:
    """A TCP port on ``127.0.0.1`` that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((LOOPBACK, 0))
        return int(probe.getsockname()[1])


def init_loopback_group(rank: int, world_size: int, port: int, backend: str = "gloo") -> None:
    """``torch.distributed.init_process_group`` on ``127.0.0.1:port`` only.

    Sets ``MASTER_ADDR``/``MASTER_PORT`` and, for gloo, ``GLOO_SOCKET_IFNAME=lo`` when the
    loopback interface is called ``lo`` (so no other interface is used).
    """
    if not 0 <= rank < world_size:
        raise ValueError(f"rank must lie in [0, {world_size}), got {rank}")
    os.environ["MASTER_ADDR"] = LOOPBACK
    os.environ["MASTER_PORT"] = str(port)
    if backend == "gloo" and Path("/sys/class/net/lo").exists():
        os.environ.setdefault("GLOO_SOCKET_IFNAME", "lo")
    dist.init_process_group(
        backend, init_method=f"tcp://{LOOPBACK}:{port}", rank=rank, world_size=world_size
    )


def row_partition(num_rows: int, parts: int) -> list[tuple[int, int]]:
    """``parts`` contiguous ``[start, stop)`` ranges covering ``num_rows`` rows, sizes within 1."""
    if parts < 1:
        raise ValueError(f"parts must be >= 1, got {parts}")
    base, extra = divmod(num_rows, parts)
    bounds, start = [], 0
    for part in range(parts):
        stop = start + base + (part < extra)
        bounds.append((start, stop))
        start = stop
    return bounds


def slice_rows(matrix: CSR, start: int, stop: int) -> CSR:
    """Rows ``[start, stop)`` of a CSR as a ``(stop - start, num_cols)`` CSR."""
    lo, hi = int(matrix.crow[start]), int(matrix.crow[stop])
    return CSR(
        matrix.crow[start : stop + 1] - lo, matrix.col[lo:hi], matrix.val[lo:hi], matrix.num_cols
    )


def _group_info(group) -> tuple[int, int]:
    """``(rank, world_size)`` in ``group``; ``(0, 1)`` when no process group is initialised."""
    if not (dist.is_available() and dist.is_initialized()):
        if group is not None:
            raise RuntimeError("a process group was given but torch.distributed is not initialised")
        return 0, 1
    return dist.get_rank(group), dist.get_world_size(group)


def _gather_rows(local: Tensor, bounds: list[tuple[int, int]], group) -> Tensor:
    """Concatenate every rank's row block (padded to equal sizes for ``all_gather``)."""
    if len(bounds) == 1:
        return local
    largest = max(stop - start for start, stop in bounds)
    padded = local.new_zeros((largest, *local.shape[1:]))
    padded[: local.shape[0]] = local
    pieces = [torch.empty_like(padded) for _ in bounds]
    dist.all_gather(pieces, padded.contiguous(), group=group)
    return torch.cat(
        [piece[: stop - start] for piece, (start, stop) in zip(pieces, bounds, strict=True)]
    )


def partitioned_multiscale(
    vertices,
    faces,
    num_scales: int = 8,
    threshold: float = 1e-3,
    group=None,
    batch: Tensor | None = None,
    backend: str = "auto",
) -> MultiscaleRepresentation:
    """Algorithm 1 with the rows of every ``F^(k)`` split across the ranks of ``group``.

    Every rank must call it with the same mesh and parameters. Each computes rows
    ``row_partition(V, world_size)[rank]`` of every step; ``positions``, ``coefficients``,
    ``differences`` and ``entries`` are gathered, so every rank returns the full result, equal
    to :func:`~stochlap_torch.diffusion.multiscale_representation`. Without an initialised
    process group it runs in one process. No gradients (an inference path for large meshes);
    ``operators`` is ``None``.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``.
        group: a ``torch.distributed`` process group (default: the world).
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch.
        backend: ``"auto"``, ``"torch"`` or ``"numba"`` for the local steps.

    Raises:
        MeshError: bad input mesh.
        ValueError: bad ``num_scales`` or ``threshold``.
    """
    check_parameters(num_scales, threshold)
    points, faces = as_mesh_tensors(vertices, faces)
    points = points.detach()
    num_vertices = points.shape[0]
    if batch is not None:
        batch = check_batch(batch.to(points.device), num_vertices, faces)
    rank, world_size = _group_info(group)
    backend = resolve_backend(backend, points.device)
    # Large meshes: a space-filling-curve order makes each rank's rows a compact region.
    order = locality_order(points) if num_vertices >= LOCALITY_MIN_VERTICES else None
    if order is not None:
        new_index = torch.empty_like(order)
        new_index[order] = torch.arange(num_vertices, device=order.device)
        points, faces = points[order], new_index[faces]
        sorted_batch = None if batch is None else batch[order]
    else:
        sorted_batch = batch
    with torch.no_grad():
        ops = mesh_operators(points, faces, sorted_batch)
        bounds = row_partition(num_vertices, world_size)
        start, stop = bounds[rank]
        current = slice_rows(ops.stochastic_laplacian(), start, stop)
        positions = [points[start:stop]]
        differences = [points.new_zeros(stop - start)]
        entries = [current.nnz]
        for _ in range(2, num_scales + 1):
            current, difference, moved = fused_step(
                current, ops, threshold, points, backend, sort_columns=False
            )
            positions.append(moved)
            differences.append(difference)
            entries.append(current.nnz)
        logger.debug("rank %d: rows [%d, %d), %s entries", rank, start, stop, entries)
        local = torch.cat(
            [
                torch.stack(positions, dim=1).reshape(stop - start, -1),
                torch.stack(differences, dim=1),
            ],
            dim=1,
        )
        gathered = _gather_rows(local, bounds, group)
        counts = torch.tensor(entries, dtype=torch.int64)
        if world_size > 1:
            dist.all_reduce(counts, group=group)
    stacked = gathered[:, : 3 * num_scales].reshape(num_vertices, num_scales, 3).transpose(0, 1)
    difference_maps = gathered[:, 3 * num_scales :].T
    if order is not None:
        stacked, difference_maps = stacked[:, new_index], difference_maps[:, new_index]
    stacked, difference_maps = stacked.contiguous(), difference_maps.contiguous()
    return MultiscaleRepresentation(
        positions=stacked,
        differences=difference_maps,
        entries=counts,
        operators=None,
        batch=batch,
    )
