"""Every way through the engine gives the same numbers.

The steps run through one driver (``stochlap_torch.diffusion.run_steps``) along several paths:
rows streamed through every step by the compiled kernel, whole operators stepped by the fused
operator (kept, or with gradients), the composed torch ops, a row range per rank
(distributed), the memory estimate's sample, the differentiable step, and the Laplacian
baselines. This runs each on the same meshes and checks they agree: bit for bit in float64 where
they run the same arithmetic in the same order, to rounding elsewhere (each case says which).
"""

from __future__ import annotations

import pytest
import torch
from reference import noisy_sphere, two_components, with_unreferenced_vertex

import stochlap_torch as sl
from stochlap_torch import _kernels
from stochlap_torch.diffusion import estimate_memory, row_partition, run_steps
from stochlap_torch.operators import laplacian_operators, mesh_operators

K = 6

pytestmark = pytest.mark.skipif(not _kernels.numba_available(), reason="numba is not installed")


def _meshes():
    yield "noisy_sphere", noisy_sphere().tensors(torch.float64)
    yield "two_components", two_components().tensors(torch.float64)
    yield "unreferenced", with_unreferenced_vertex().tensors(torch.float64)
    spot = sl.load_mesh(sl.bundled_mesh_path())  # 2930 vertices, irregular valences
    yield "spot", (spot.vertices, spot.faces)


MESHES = dict(_meshes())


@pytest.fixture(scope="module", params=sorted(MESHES))
def mesh(request):
    return MESHES[request.param]


@pytest.fixture(scope="module")
def plain(mesh):
    """The default run (rows streamed through the compiled kernel), which most paths are
    compared with: computed once per mesh."""
    return sl.multiscale_representation(*mesh, K)


def _same(a: torch.Tensor, b: torch.Tensor) -> None:
    assert a.dtype == b.dtype and a.shape == b.shape
    assert torch.equal(a, b), f"max difference {(a - b).abs().max().item():.3g}"


def test_streamed_and_stepped_kernels_agree(mesh, plain) -> None:
    """Streaming rows and stepping whole operators run the same block kernel on the same row
    blocks. Kept operators are stepped with their columns sorted (canonical CSR), which changes
    the order a block sums its products in: equal to rounding, same sparsity. Unsorted
    stepping (the gradient path) is bitwise equal, see the next test."""
    streamed = plain
    stepped = sl.multiscale_representation(*mesh, K, return_operators=True)
    _same(stepped.entries, streamed.entries)
    torch.testing.assert_close(stepped.positions, streamed.positions, rtol=0, atol=1e-13)
    torch.testing.assert_close(stepped.differences, streamed.differences, rtol=0, atol=1e-13)


def test_gradient_path_agrees_bitwise_on_the_operators(mesh, plain) -> None:
    """With gradients the operators are stepped whole, columns unsorted like the streamed rows:
    the difference maps and entries are bitwise equal. The positions are ``spmm(F^(k), P)``
    (another summation order than the kernel's): equal to rounding."""
    vertices, faces = mesh
    tracked = sl.multiscale_representation(vertices.clone().requires_grad_(True), faces, K)
    _same(tracked.differences, plain.differences)
    _same(tracked.entries, plain.entries)
    torch.testing.assert_close(tracked.positions.detach(), plain.positions, rtol=0, atol=1e-13)


@pytest.mark.parametrize(
    "options",
    [{}, {"return_operators": True}, {"backend": "torch"}, {"dtype": torch.float32}],
    ids=["streamed", "stepped", "torch_ops", "float32"],
)
def test_difference_maps_alone_are_bitwise_those_of_a_full_run(mesh, options) -> None:
    """``positions=False`` (the paper's saliency) skips ``P^(k)`` and the streamed kernel's
    cost counts: the difference maps and entries do not change by a bit."""
    vertices, faces = mesh
    options = dict(options)
    vertices = vertices.to(options.pop("dtype", vertices.dtype))
    full = sl.multiscale_representation(vertices, faces, K, **options)
    alone = sl.multiscale_representation(vertices, faces, K, positions=False, **options)
    _same(alone.differences, full.differences)
    _same(alone.entries, full.entries)
    assert alone.positions.shape == (K, vertices.shape[0], 0)
    assert alone.coefficients.shape == (K, vertices.shape[0], 0)


def test_torch_ops_agree_to_rounding(mesh, plain) -> None:
    """The composed torch ops sum in another order: equal to rounding, same sparsity."""
    numba = plain
    ops = sl.multiscale_representation(*mesh, K, backend="torch")
    _same(ops.entries, numba.entries)
    torch.testing.assert_close(ops.positions, numba.positions, rtol=0, atol=1e-12)
    torch.testing.assert_close(ops.differences, numba.differences, rtol=0, atol=1e-12)


@pytest.mark.parametrize("parts", [1, 2, 3])
def test_row_ranges_agree_bitwise_with_the_whole_run(mesh, parts: int) -> None:
    """A distributed rank runs the engine on a range of rows starting at a block boundary:
    its rows equal the whole run's."""
    vertices, faces = mesh
    ops = mesh_operators(vertices, faces)
    whole = run_steps(ops, vertices, K, 1e-3)
    for start, stop in row_partition(ops.num_vertices, parts, align=_kernels.LANES):
        local = run_steps(ops, vertices, K, 1e-3, rows=(start, stop))
        _same(local.positions, whole.positions[:, start:stop])
        _same(local.differences, whole.differences[:, start:stop])


def test_partitioned_entry_point_agrees_bitwise(mesh, plain) -> None:
    single = plain
    partitioned = sl.partitioned_multiscale(*mesh, K)
    _same(partitioned.positions, single.positions)
    _same(partitioned.differences, single.differences)
    _same(partitioned.entries, single.entries)


def test_memory_sample_of_every_row_counts_the_run_exactly(mesh, plain) -> None:
    """The estimate steps a sample of rows like the run: sampling every row gives the run's
    entry counts exactly."""
    vertices, faces = mesh
    ops = mesh_operators(vertices, faces)
    run = plain
    for backend in ("numba", "torch"):
        estimate = estimate_memory(ops, K, 1e-3, sample_rows=ops.num_vertices, backend=backend)
        counted = [round(e * ops.num_vertices) for e in estimate.entries_per_row]
        assert counted == run.entries.tolist()


def test_differentiable_step_agrees_to_rounding(mesh, plain) -> None:
    """The differentiable step builds every value with gathers: equal to rounding, and the
    same thresholded patterns."""
    vertices, faces = mesh
    differentiable = sl.differentiable_multiscale(vertices.clone().requires_grad_(True), faces, K)
    _same(differentiable.entries, plain.entries)
    torch.testing.assert_close(
        differentiable.positions.detach(), plain.positions, rtol=0, atol=1e-12
    )
    torch.testing.assert_close(
        differentiable.differences.detach(), plain.differences, rtol=0, atol=1e-12
    )


@pytest.mark.parametrize("laplacian", ["uniform", "cotangent"])
def test_laplacian_baselines_use_the_same_engine(mesh, laplacian: str) -> None:
    """Algorithm 2 on ``|L|`` goes through the same engine: its streamed and stepped runs
    agree (to rounding, see above), and the baseline's saliency is Algorithm 2 of the streamed
    run, bitwise."""
    from stochlap_torch.baselines import laplacian_saliency

    vertices, faces = mesh
    ops = laplacian_operators(vertices, faces, laplacian)
    points = vertices.new_zeros(ops.num_vertices, 1)
    streamed = run_steps(ops, points, K, 1e-3)
    stepped = run_steps(ops, points, K, 1e-3, keep_operators=True)
    assert stepped.entries == streamed.entries
    torch.testing.assert_close(stepped.differences, streamed.differences, rtol=0, atol=1e-13)
    expected = sl.saliency_from_differences(streamed.differences)
    _same(laplacian_saliency(vertices, faces, laplacian, K), expected)
