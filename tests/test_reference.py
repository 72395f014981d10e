"""The library against the dense float64 reference of ``reference.py``, on small meshes.

Every quantity of the numerics contract is compared: ``Lhat``-derived ``F^(1)``, ``alpha``, the
unique edges, every ``F^(k)``, positions, coefficients, difference maps and saliency.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest
import reference as ref
import torch
from reference import SMALL_MESH_BUILDERS, SmallMesh, to_numpy

import stochlap_torch as sl

NUM_SCALES = 6
FLOAT64_ATOL = 1e-10


def available_backends() -> list[str | None]:
    """The concrete diffusion backends of this build (``None``: the library has no choice).

    The library runs the steps either with the composed ``stochlap`` torch ops or with a fused
    numba kernel; both must match the reference, so every comparison runs on each.
    """
    from stochlap_torch import _kernels as kernels
    from stochlap_torch import diffusion

    names = [b for b in getattr(diffusion, "BACKENDS", ()) if b != "auto"]
    # The cases run on CPU tensors: the CUDA kernel takes them only under numba's simulator
    # (tests/test_cuda_kernel.py runs it there).
    if "cuda" in names and not kernels.cuda_simulator_enabled():
        names.remove("cuda")
    if "numba" in names and not kernels.numba_available():
        names.remove("numba")
    return names or [None]


@pytest.fixture(params=available_backends(), ids=str)
def backend(request) -> str | None:
    """Each available diffusion backend in turn."""
    return request.param


@cache
def reference_result(name: str, num_scales: int, threshold: float) -> ref.ReferenceResult:
    """The dense reference for one small mesh (cached: it is the slow part)."""
    mesh = SMALL_MESH_BUILDERS[name]()
    result = ref.multiscale(mesh.vertices, mesh.faces, num_scales, threshold)
    # Premise: no entry of a normalised product sits on the threshold, where rounding alone
    # would decide whether it survives (e.g. the icosahedron has G entries of exactly 0.02
    # and 0.3, so those thresholds are avoided).
    assert result.threshold_margin > 1e-9, f"{name}: an entry lies on threshold {threshold}"
    return result


def library_result(
    mesh: SmallMesh,
    num_scales: int,
    threshold: float,
    dtype: torch.dtype = torch.float64,
    backend: str | None = None,
) -> sl.MultiscaleRepresentation:
    """The library's representation with the operators kept, on ``backend`` if given."""
    vertices, faces = mesh.tensors(dtype)
    extra = {} if backend is None else {"backend": backend}
    return sl.multiscale_representation(
        vertices, faces, num_scales=num_scales, threshold=threshold, return_operators=True, **extra
    )


def mesh_scale(mesh: SmallMesh) -> float:
    """Largest absolute coordinate, to turn absolute position tolerances into relative ones."""
    return float(np.abs(mesh.vertices).max())


def test_unique_edges(small_mesh: SmallMesh) -> None:
    """``unique_edges`` gives each undirected edge once, ``i < j``, as the reference."""
    edges = sl.unique_edges(torch.tensor(small_mesh.faces))
    assert edges.dtype == torch.int64
    assert bool((edges[:, 0] < edges[:, 1]).all())
    got = sorted(map(tuple, edges.tolist()))
    assert got == [tuple(e) for e in ref.unique_edges(small_mesh.faces).tolist()]


def test_stochastic_laplacian(small_mesh: SmallMesh) -> None:
    """``F^(1)`` is a ``(V, V)`` sparse CSR tensor equal to ``[Lhat]_r``."""
    vertices, faces = small_mesh.tensors()
    matrix = sl.stochastic_laplacian(vertices, faces)
    assert matrix.layout == torch.sparse_csr
    assert matrix.shape == (vertices.shape[0],) * 2
    expected = ref.stochastic_laplacian(small_mesh.vertices, small_mesh.faces)
    np.testing.assert_allclose(to_numpy(matrix), expected, rtol=0, atol=FLOAT64_ATOL)


def test_stochastic_laplacian_sparsity(small_mesh: SmallMesh) -> None:
    """``F^(1)`` stores exactly the diagonal and the two directions of every edge."""
    vertices, faces = small_mesh.tensors()
    matrix = sl.stochastic_laplacian(vertices, faces)
    num_edges = ref.unique_edges(small_mesh.faces).shape[0]
    assert matrix.values().numel() == vertices.shape[0] + 2 * num_edges


def test_scale_invariance(small_mesh: SmallMesh) -> None:
    """``alpha`` of Eq. 9 (with ``alpha = 1`` for isolated vertices)."""
    vertices, faces = small_mesh.tensors()
    alpha = sl.scale_invariance(vertices, faces)
    assert alpha.shape == (vertices.shape[0],)
    expected = ref.alpha(small_mesh.vertices, small_mesh.faces)
    np.testing.assert_allclose(to_numpy(alpha), expected, rtol=0, atol=FLOAT64_ATOL)


@pytest.mark.parametrize("threshold", [1e-3, 1.5e-2])
def test_operators(small_mesh: SmallMesh, threshold: float, backend: str | None) -> None:
    """Every ``F^(k)``, ``k = 1..K``, equals the dense reference."""
    result = library_result(small_mesh, NUM_SCALES, threshold, backend=backend)
    expected = reference_result(small_mesh.name, NUM_SCALES, threshold)
    assert result.operators is not None
    assert len(result.operators) == NUM_SCALES
    for k, (got, want) in enumerate(zip(result.operators, expected.operators, strict=True), 1):
        assert got.layout == torch.sparse_csr, f"F^({k}) is not sparse CSR"
        np.testing.assert_allclose(
            to_numpy(got), want, rtol=0, atol=FLOAT64_ATOL, err_msg=f"F^({k})"
        )


@pytest.mark.parametrize("threshold", [1e-3, 1.5e-2])
def test_positions_coefficients_differences(
    small_mesh: SmallMesh, threshold: float, backend: str | None
) -> None:
    """Positions, coefficients and difference maps equal the reference to 1e-10."""
    result = library_result(small_mesh, NUM_SCALES, threshold, backend=backend)
    expected = reference_result(small_mesh.name, NUM_SCALES, threshold)
    num_vertices = small_mesh.vertices.shape[0]
    assert result.positions.shape == (NUM_SCALES, num_vertices, 3)
    assert result.coefficients.shape == (NUM_SCALES, num_vertices, 3)
    assert result.differences.shape == (NUM_SCALES, num_vertices)
    atol = FLOAT64_ATOL * mesh_scale(small_mesh)
    np.testing.assert_array_equal(to_numpy(result.positions[0]), small_mesh.vertices)
    np.testing.assert_allclose(to_numpy(result.positions), expected.positions, rtol=0, atol=atol)
    np.testing.assert_allclose(
        to_numpy(result.coefficients), expected.coefficients, rtol=0, atol=atol
    )
    np.testing.assert_allclose(
        to_numpy(result.differences), expected.differences, rtol=0, atol=FLOAT64_ATOL
    )


def test_saliency(small_mesh: SmallMesh, backend: str | None) -> None:
    """``saliency()`` of the representation and the ``saliency`` function match Algorithm 2."""
    expected = reference_result(small_mesh.name, NUM_SCALES, 1e-3).saliency
    result = library_result(small_mesh, NUM_SCALES, 1e-3, backend=backend)
    np.testing.assert_allclose(to_numpy(result.saliency()), expected, rtol=0, atol=FLOAT64_ATOL)
    vertices, faces = small_mesh.tensors()
    direct = sl.saliency(vertices, faces, num_scales=NUM_SCALES, threshold=1e-3, variant="paper")
    np.testing.assert_allclose(to_numpy(direct), expected, rtol=0, atol=FLOAT64_ATOL)


@pytest.mark.parametrize("name", ["noisy_sphere", "open_grid"])
@pytest.mark.parametrize("threshold", [0.3, 0.9])
def test_threshold_above_row_density_keeps_row_maximum(
    name: str, threshold: float, backend: str | None
) -> None:
    """A threshold above ``1/row_nnz`` still keeps each row's largest entry (no empty rows).

    The meshes are jittered, so no row has two equal maxima.
    """
    mesh = SMALL_MESH_BUILDERS[name]()
    result = library_result(mesh, 4, threshold, backend=backend)
    expected = reference_result(name, 4, threshold)
    for k, (got, want) in enumerate(zip(result.operators, expected.operators, strict=True), 1):
        np.testing.assert_allclose(
            to_numpy(got), want, rtol=0, atol=FLOAT64_ATOL, err_msg=f"F^({k})"
        )
    np.testing.assert_allclose(
        to_numpy(result.positions), expected.positions, rtol=0, atol=FLOAT64_ATOL * 10
    )


@pytest.mark.parametrize("name", ["noisy_sphere", "open_grid", "two_components"])
def test_float32_matches_float64_reference(name: str, backend: str | None) -> None:
    """float32 input gives float32 output within ~1e-5 (relative) of the float64 reference."""
    mesh = SMALL_MESH_BUILDERS[name]()
    result = library_result(mesh, NUM_SCALES, 1e-3, dtype=torch.float32, backend=backend)
    expected = reference_result(name, NUM_SCALES, 1e-3)
    assert result.positions.dtype == torch.float32
    assert result.differences.dtype == torch.float32
    scale = mesh_scale(mesh)
    np.testing.assert_allclose(
        to_numpy(result.positions), expected.positions, rtol=0, atol=1e-5 * scale
    )
    np.testing.assert_allclose(to_numpy(result.differences), expected.differences, atol=1e-5)
    np.testing.assert_allclose(to_numpy(result.saliency()), expected.saliency, atol=1e-5)
    for got, want in zip(result.operators, expected.operators, strict=True):
        np.testing.assert_allclose(to_numpy(got), want, rtol=0, atol=1e-5)
