"""Several processes: loopback process groups and a row partition of the diffusion steps.
Row ``i`` of ``F^(k)`` depends only on row ``i`` of ``F^(k-1)``, ``Lhat`` and ``alpha``: each
rank builds those for the whole mesh and steps a range of rows starting at a multiple of the
kernel's row block, so the results are bitwise those of a single process.
"""

from __future__ import annotations

import hashlib
import logging
import os
import socket
import struct
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor

from .. import _kernels
from .._common.errors import DistributedError, ParameterError, StochlapError
from ..mesh import Renumbering, as_mesh_tensors, check_batch, extent_scale
from ..operators import operators_of_valid_mesh
from ..params import PaperParams
from .engine import Steps, run_steps
from .parameters import check_parameters, resolve_backend
from .representation import MultiscaleRepresentation

logger = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"


def find_free_port() -> int:
    """A TCP port on ``127.0.0.1`` that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind((LOOPBACK, 0))
        return int(probe.getsockname()[1])


def init_loopback_group(rank: int, world_size: int, port: int, backend: str = "gloo") -> None:
    """``torch.distributed.init_process_group`` on ``127.0.0.1:port`` only (for gloo, on the
    interface ``lo`` when there is one)."""
    if not 0 <= rank < world_size:
        raise ParameterError(f"rank must lie in [0, {world_size}), got {rank}")
    os.environ["MASTER_ADDR"] = LOOPBACK
    os.environ["MASTER_PORT"] = str(port)
    if backend == "gloo" and Path("/sys/class/net/lo").exists():
        os.environ.setdefault("GLOO_SOCKET_IFNAME", "lo")
    dist.init_process_group(
        backend, init_method=f"tcp://{LOOPBACK}:{port}", rank=rank, world_size=world_size
    )


def row_partition(num_rows: int, parts: int, align: int = 1) -> list[tuple[int, int]]:
    """``parts`` contiguous ``[start, stop)`` ranges covering ``num_rows`` rows, every start a
    multiple of ``align`` and the sizes equal within ``align``."""
    if parts < 1:
        raise ParameterError(f"parts must be >= 1, got {parts}")
    if align < 1:
        raise ParameterError(f"align must be >= 1, got {align}")
    blocks = -(-num_rows // align)
    base, extra = divmod(blocks, parts)
    bounds, start = [], 0
    for part in range(parts):
        stop = min(start + (base + (part < extra)) * align, num_rows)
        bounds.append((start, stop))
        start = stop
    return bounds


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


@contextmanager
def _shared_failure(group, world_size: int, stage: str) -> Iterator[None]:
    """Run the block, then share whether any rank failed in it: that rank raises its own
    error, every other rank a :class:`DistributedError`."""
    failure: BaseException | None = None
    try:
        yield
    except (StochlapError, MemoryError) as error:
        failure = error
    if world_size > 1:
        flag = torch.tensor([0 if failure is None else 1], dtype=torch.int64)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX, group=group)
        if failure is None and int(flag) != 0:
            raise DistributedError(f"another rank failed while {stage}; see its error")
    if failure is not None:
        raise failure


#: What :func:`_signature` holds, in order (for the error that names a disagreement).
_SIGNATURE = ("vertex counts", "face counts", "num_scales", "thresholds", "mesh contents", "dtypes")


def _signature(
    points: Tensor, faces: Tensor, batch: Tensor | None, num_scales: int, threshold: float
) -> Tensor:
    """``(6,)`` int64 of what :data:`_SIGNATURE` names (the threshold's bits, a 62-bit hash of
    the mesh's and batch's bytes, the dtype's size)."""
    digest = hashlib.sha256()
    for array in (points, faces, batch):
        if array is not None:
            digest.update(np.ascontiguousarray(array.detach().cpu().numpy()).tobytes())
    mesh_hash = int.from_bytes(digest.digest()[:8], "little") >> 2
    threshold_bits = struct.unpack("<q", struct.pack("<d", threshold))[0]
    values = [points.shape[0], faces.shape[0], num_scales, threshold_bits, mesh_hash]
    return torch.tensor([*values, points.element_size()], dtype=torch.int64)


def _check_agreement(signature: Tensor, group) -> None:
    """Raise :class:`DistributedError` on every rank unless all hold the same ``signature``."""
    low, high = signature.clone(), signature.clone()
    dist.all_reduce(low, op=dist.ReduceOp.MIN, group=group)
    dist.all_reduce(high, op=dist.ReduceOp.MAX, group=group)
    if not torch.equal(low, high):
        differing = [name for name, a, b in zip(_SIGNATURE, low, high, strict=True) if a != b]
        raise DistributedError(
            f"the ranks of partitioned_multiscale disagree on {', '.join(differing)}: every "
            "rank must call it with the same mesh and parameters"
        )


def partitioned_multiscale(
    vertices,
    faces,
    num_scales: int = PaperParams.num_scales,
    threshold: float = PaperParams.threshold,
    group=None,
    batch: Tensor | None = None,
    backend: str = "auto",
    max_memory: int | None = None,
) -> MultiscaleRepresentation:
    """Algorithm 1 with the rows of every ``F^(k)`` split across the ranks of ``group``.

    Every rank calls it with the same mesh and parameters and returns the gathered result of
    :func:`~stochlap_torch.diffusion.multiscale_representation` (without an initialised
    process group, in one process). No gradients; ``operators`` is ``None``.

    Args:
        vertices, faces, num_scales, threshold, batch: as for
            :func:`~stochlap_torch.diffusion.multiscale_representation`.
        group: a ``torch.distributed`` process group (default: the world).
        backend: ``"auto"``, ``"torch"`` or ``"numba"`` for the local steps.
        max_memory: byte budget of each rank (default: ``$STOCHLAP_MAX_MEMORY``, else half the
            physical memory).

    Raises:
        MeshError: bad input mesh.
        ParameterError: bad ``num_scales`` or ``threshold``.
        DistributedError: the ranks disagree on the mesh, its dtype or the parameters, or
            another rank failed (every rank raises; none is left waiting).
    """
    rank, world_size = _group_info(group)
    # Every failure before a collective is shared first: an error on one rank alone would
    # leave the others waiting in the next collective (or aborted by gloo).
    with _shared_failure(group, world_size, "checking its input"):
        num_scales, threshold = check_parameters(num_scales, threshold)
        points, faces = as_mesh_tensors(vertices, faces)
        if batch is not None:
            batch = check_batch(batch, points.shape[0], faces)
        backend = resolve_backend(backend, points.device)
    if world_size > 1:
        _check_agreement(_signature(points, faces, batch, num_scales, threshold), group)
    scale = extent_scale(points)  # exact power of two, see multiscale_representation
    points = points.detach() if scale == 1.0 else points.detach() * scale
    num_vertices = points.shape[0]
    # Large meshes: a space-filling-curve order makes each rank's rows a compact region.
    renumbering, sorted_batch = Renumbering.for_locality(points), batch
    if renumbering is not None:
        points, faces, sorted_batch = renumbering.mesh(points, faces, batch)
    bounds = row_partition(num_vertices, world_size, align=_kernels.LANES)
    start, stop = bounds[rank]
    with torch.no_grad():
        with _shared_failure(group, world_size, "computing its rows"):
            ops = operators_of_valid_mesh(points, faces, sorted_batch)
            options = {"backend": backend, "rows": (start, stop), "max_memory": max_memory}
            steps = run_steps(ops, points, num_scales, threshold, **options)
        logger.debug("rank %d: rows [%d, %d), %s entries", rank, start, stop, steps.entries)
        positions = steps.positions.permute(1, 0, 2).reshape(stop - start, -1)
        local = torch.cat([positions, steps.differences.T], dim=1)
        gathered = _gather_rows(local, bounds, group)
        counts = torch.tensor(steps.entries, dtype=torch.int64)
        if world_size > 1:
            dist.all_reduce(counts, group=group)
    stacked = gathered[:, : 3 * num_scales].reshape(num_vertices, num_scales, 3).transpose(0, 1)
    difference_maps = gathered[:, 3 * num_scales :].T
    if renumbering is not None:
        stacked = renumbering.restore(stacked, dim=1)
        difference_maps = renumbering.restore(difference_maps, dim=1)
    steps = Steps(stacked.contiguous(), difference_maps.contiguous(), counts.tolist(), None)
    return steps.representation(scale, batch)
