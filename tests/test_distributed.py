"""Two processes on 127.0.0.1 (gloo): DistributedDataParallel and the row partition."""

from __future__ import annotations

import pytest
import torch
import torch.distributed as dist
from reference import noisy_sphere, open_grid, two_components
from torch import nn

import stochlap_torch as sl
from stochlap_torch.diffusion.distributed import (
    find_free_port,
    init_loopback_group,
    partitioned_multiscale,
    row_partition,
)
from stochlap_torch.nn import MultiscaleFeatures
from stochlap_torch.sparse import CSR, slice_rows

WORLD_SIZE = 2
SCALES = 4


class TinyNet(nn.Module):
    """Multiscale features, then a two-layer per-vertex classifier."""

    def __init__(self):
        super().__init__()
        self.features = MultiscaleFeatures(num_scales=3, rotation_invariant=True, variant="paper")
        self.head = nn.Sequential(
            nn.Linear(self.features.num_channels, 8), nn.ReLU(), nn.Linear(8, 2)
        )

    def forward(self, vertices, faces):
        return self.head(self.features(vertices, faces))


def _tensors(mesh):
    return torch.tensor(mesh.vertices), torch.tensor(mesh.faces)


def _partition_cases():
    packed = sl.MeshBatch.from_meshes([_tensors(noisy_sphere()), _tensors(open_grid())])
    return {
        "noisy_sphere": (*_tensors(noisy_sphere()), None, "auto"),
        "two_components": (*_tensors(two_components()), None, "auto"),
        "open_grid_torch": (*_tensors(open_grid()), None, "torch"),
        "batch": (packed.vertices, packed.faces, packed.batch, "auto"),
    }


def _training_mesh(rank):
    vertices, faces = _tensors(noisy_sphere(seed=rank))
    labels = (vertices[:, 2] > 0).long()
    return vertices, faces, labels


def _loss(model, rank):
    vertices, faces, labels = _training_mesh(rank)
    return nn.functional.cross_entropy(model(vertices, faces), labels)


def _disagreements(rank):
    """Each case makes the ranks disagree or one rank fail: the name of the error each rank
    raised (every rank must raise, none may hang or abort)."""
    vertices, faces = _tensors(noisy_sphere())
    other = _tensors(noisy_sphere(seed=1))
    nan_vertices = vertices.clone()
    nan_vertices[3, 0] = float("nan")
    cases = {
        "num_scales": lambda: partitioned_multiscale(vertices, faces, 3 + rank),
        "mesh": lambda: partitioned_multiscale(*(other if rank else (vertices, faces)), 3),
        "dtype": lambda: partitioned_multiscale(vertices.float() if rank else vertices, faces, 3),
        "bad_mesh_on_one_rank": lambda: partitioned_multiscale(
            nan_vertices if rank else vertices, faces, 3
        ),
        "budget_on_one_rank": lambda: partitioned_multiscale(
            vertices, faces, 3, max_memory=1 if rank else None
        ),
    }
    raised = {}
    for name, call in cases.items():
        try:
            call()
            raised[name] = None
        except Exception as error:
            raised[name] = type(error).__name__
    return raised


def _worker(rank, port, folder):
    torch.set_num_threads(1)
    init_loopback_group(rank, WORLD_SIZE, port)
    try:
        results = {}
        for name, (vertices, faces, batch, backend) in _partition_cases().items():
            rep = partitioned_multiscale(
                vertices, faces, SCALES, 1e-3, batch=batch, backend=backend
            )
            results[name] = (rep.positions, rep.coefficients, rep.differences, rep.entries)
        results["errors"] = _disagreements(rank)
        torch.manual_seed(0)
        model = nn.parallel.DistributedDataParallel(TinyNet().double())
        _loss(model, rank).backward()
        results["grads"] = [p.grad.clone() for p in model.parameters()]
        optimiser = torch.optim.SGD(model.parameters(), lr=0.1)
        for _ in range(3):
            optimiser.zero_grad()
            _loss(model, rank).backward()
            optimiser.step()
        results["params"] = [p.detach().clone() for p in model.parameters()]
        torch.save(results, f"{folder}/rank{rank}.pt")
    finally:
        dist.destroy_process_group()


@pytest.fixture(scope="module")
def two_ranks(tmp_path_factory):
    """Run :func:`_worker` on two spawned processes once; the results of both ranks."""
    folder = tmp_path_factory.mktemp("ranks")
    torch.multiprocessing.spawn(_worker, args=(find_free_port(), str(folder)), nprocs=WORLD_SIZE)
    return [torch.load(folder / f"rank{r}.pt", weights_only=True) for r in range(WORLD_SIZE)]


def test_disagreeing_or_failing_ranks_all_raise(two_ranks):
    """Different meshes, dtypes or parameters on different ranks: a DistributedError on every
    rank (gloo aborted a rank before); a failure on one rank: its own error there, a
    DistributedError on the other."""
    first, second = (ranks["errors"] for ranks in two_ranks)
    for name in ("num_scales", "mesh", "dtype"):
        assert first[name] == second[name] == "DistributedError", name
    assert (first["bad_mesh_on_one_rank"], second["bad_mesh_on_one_rank"]) == (
        "DistributedError",
        "MeshError",
    )
    assert (first["budget_on_one_rank"], second["budget_on_one_rank"]) == (
        "DistributedError",
        "MemoryBudgetError",
    )


@pytest.mark.parametrize("name", sorted(_partition_cases()))
def test_partitioned_equals_single_process(two_ranks, name):
    vertices, faces, batch, _ = _partition_cases()[name]
    expected = sl.multiscale_representation(vertices, faces, SCALES, 1e-3, batch=batch)
    for results in two_ranks:
        positions, coefficients, differences, entries = results[name]
        torch.testing.assert_close(positions, expected.positions, rtol=0, atol=1e-12)
        torch.testing.assert_close(coefficients, expected.coefficients, rtol=0, atol=1e-12)
        torch.testing.assert_close(differences, expected.differences, rtol=0, atol=1e-12)
        assert torch.equal(entries, expected.entries)


def test_ddp_gradients_are_the_mean_of_the_ranks(two_ranks):
    torch.manual_seed(0)
    model = TinyNet().double()
    for rank in range(WORLD_SIZE):
        (_loss(model, rank) / WORLD_SIZE).backward()
    expected = [p.grad for p in model.parameters()]
    for results in two_ranks:
        for got, want in zip(results["grads"], expected, strict=True):
            torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    # one rank's gradient alone differs: the all-reduce did something
    assert not torch.allclose(expected[0], _single_rank_gradient(0))


def _single_rank_gradient(rank):
    torch.manual_seed(0)
    model = TinyNet().double()
    _loss(model, rank).backward()
    return next(model.parameters()).grad


def test_ddp_ranks_stay_in_sync(two_ranks):
    for first, second in zip(two_ranks[0]["params"], two_ranks[1]["params"], strict=True):
        assert torch.equal(first, second)


def test_partitioned_without_process_group_is_single_process():
    vertices, faces = _tensors(noisy_sphere())
    rep = partitioned_multiscale(vertices, faces, 3)
    expected = sl.multiscale_representation(vertices, faces, 3)
    torch.testing.assert_close(rep.positions, expected.positions, rtol=0, atol=1e-12)
    with pytest.raises(RuntimeError, match="not initialised"):
        partitioned_multiscale(vertices, faces, 3, group=object())


def test_row_partition_and_slices():
    assert row_partition(7, 3) == [(0, 3), (3, 5), (5, 7)]
    assert row_partition(1, 2) == [(0, 1), (1, 1)]
    with pytest.raises(ValueError):
        row_partition(5, 0)
    dense = torch.tensor([[1.0, 0, 2], [0, 0, 0], [3, 4, 0], [0, 5, 6]])
    matrix = CSR.from_sparse_csr(dense.to_sparse_csr())
    torch.testing.assert_close(slice_rows(matrix, 1, 3).to_dense(), dense[1:3])
    torch.testing.assert_close(slice_rows(matrix, 2, 2).to_dense(), dense[2:2])
