"""Gradients through the operators (``autodiff``) and through the default constant-operator path."""

from __future__ import annotations

import inspect

import pytest
import torch
from reference import SMALL_MESH_BUILDERS, open_grid

import stochlap_torch as sl
from stochlap_torch.diffusion import differentiable_multiscale
from stochlap_torch.sparse import CSR, csr_matmul, pattern_matmul

THRESHOLD = 1e-2


def _grid() -> tuple[torch.Tensor, torch.Tensor]:
    """30 jittered vertices of an open height-field patch, bent out of the plane."""
    mesh = open_grid(5, 6)
    vertices = torch.tensor(mesh.vertices)
    vertices[:, 2] = 0.2 * torch.sin(vertices[:, 0]) * torch.cos(0.7 * vertices[:, 1])
    return vertices, torch.tensor(mesh.faces)


@pytest.mark.parametrize("name", sorted(SMALL_MESH_BUILDERS))
@pytest.mark.parametrize("threshold", [1e-3, 0.05])
def test_forward_equals_library(name, threshold):
    mesh = SMALL_MESH_BUILDERS[name]()
    vertices, faces = torch.tensor(mesh.vertices), torch.tensor(mesh.faces)
    expected = sl.multiscale_representation(vertices, faces, 5, threshold, return_operators=True)
    got = differentiable_multiscale(vertices, faces, 5, threshold, return_operators=True)
    torch.testing.assert_close(got.positions, expected.positions, rtol=0, atol=1e-12)
    torch.testing.assert_close(got.differences, expected.differences, rtol=0, atol=1e-12)
    torch.testing.assert_close(got.coefficients, expected.coefficients, rtol=0, atol=1e-12)
    assert torch.equal(got.entries, expected.entries)
    for mine, theirs in zip(got.operators, expected.operators, strict=True):
        torch.testing.assert_close(mine.to_dense(), theirs.to_dense(), rtol=0, atol=1e-12)


def test_forward_equals_library_on_batch():
    first, second = SMALL_MESH_BUILDERS["noisy_sphere"](), SMALL_MESH_BUILDERS["open_grid"]()
    packed = sl.MeshBatch.from_meshes(
        [(torch.tensor(m.vertices), torch.tensor(m.faces)) for m in (first, second)]
    )
    expected = sl.multiscale_representation(packed.vertices, packed.faces, 4, batch=packed.batch)
    got = differentiable_multiscale(packed.vertices, packed.faces, 4, batch=packed.batch)
    torch.testing.assert_close(got.positions, expected.positions, rtol=0, atol=1e-12)
    torch.testing.assert_close(got.differences, expected.differences, rtol=0, atol=1e-12)


def test_threshold_pattern_is_stable_around_the_gradcheck_point():
    """No normalised entry lies within 0.1 % of the threshold: finite differences keep it."""
    vertices, faces = _grid()
    entries = [
        differentiable_multiscale(vertices, faces, 3, THRESHOLD * factor).entries
        for factor in (0.999, 1.0, 1.001)
    ]
    assert torch.equal(entries[0], entries[1]) and torch.equal(entries[1], entries[2])
    # and the threshold does drop entries here, so the test exercises the fixed pattern
    assert int(entries[1][-1]) < int(
        differentiable_multiscale(vertices, faces, 3, 1e-9).entries[-1]
    )


def test_gradcheck_through_operators():
    vertices, faces = _grid()
    vertices.requires_grad_(True)

    def outputs(points):
        rep = differentiable_multiscale(points, faces, 3, THRESHOLD)
        return rep.positions, rep.differences

    assert torch.autograd.gradcheck(outputs, (vertices,), fast_mode=True)


def test_gradient_differs_from_constant_operator_path():
    """The operator terms matter: the two paths give different vertex gradients."""
    vertices, faces = _grid()
    weights = torch.randn(3, 30, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    grads = []
    for run in (sl.multiscale_representation, differentiable_multiscale):
        points = vertices.clone().requires_grad_(True)
        (run(points, faces, 3, THRESHOLD).positions * weights).sum().backward()
        grads.append(points.grad)
    assert (grads[0] - grads[1]).abs().max() > 1e-3


def _similarity(vertices, scale, shift, angles):
    """``scale * R(angles) vertices + shift``; the operators are invariant to all three."""
    zero = torch.zeros((), dtype=vertices.dtype)
    skew = torch.stack(
        [
            torch.stack([zero, -angles[2], angles[1]]),
            torch.stack([angles[2], zero, -angles[0]]),
            torch.stack([-angles[1], angles[0], zero]),
        ]
    )
    return scale * vertices @ torch.linalg.matrix_exp(skew).T + shift


def test_gradcheck_default_path_wrt_vertices():
    """Default path: gradients reach the vertices with F held constant.

    ``F`` is invariant to similarity transforms of the vertices, so along a similarity the
    finite differences see constant operators too and must match the analytic gradient.
    Random projections of the Jacobian (``fast_mode``): the one custom op on this path,
    ``spmm``, has its full gradcheck in test_sparse_ops.py.
    """
    vertices, faces = _grid()
    scale = torch.tensor(1.3, dtype=torch.float64, requires_grad=True)
    shift = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64, requires_grad=True)
    angles = torch.tensor([0.2, -0.1, 0.4], dtype=torch.float64, requires_grad=True)

    def outputs(s, t, a):
        moved = _similarity(vertices, s, t, a)
        return sl.multiscale_representation(moved, faces, 3, THRESHOLD).positions

    assert torch.autograd.gradcheck(outputs, (scale, shift, angles), fast_mode=True)


def test_default_path_jacobian_is_the_operator():
    vertices, faces = _grid()
    rep = sl.multiscale_representation(vertices, faces, 3, THRESHOLD, return_operators=True)
    points = vertices.clone().requires_grad_(True)
    last = sl.multiscale_representation(points, faces, 3, THRESHOLD).positions[-1]
    (gradient,) = torch.autograd.grad(last[:, 1].sum(), points)
    column_sums = rep.operators[-1].to_dense().sum(dim=0)
    torch.testing.assert_close(gradient[:, 1], column_sums, rtol=0, atol=1e-12)
    assert gradient[:, 0].abs().max() == 0 and gradient[:, 2].abs().max() == 0


def test_pattern_matmul_gradcheck_in_small_blocks(monkeypatch):
    """The product's backward recomputes its terms block by block; blocks must not matter."""
    import stochlap_torch.sparse.autograd as autodiff

    monkeypatch.setattr(autodiff, "EXPANSION_BLOCK", 7)
    generator = torch.Generator().manual_seed(1)
    dense_a = (torch.rand(6, 5, generator=generator) < 0.5) * torch.rand(6, 5, generator=generator)
    dense_b = (torch.rand(5, 4, generator=generator) < 0.5) * torch.rand(5, 4, generator=generator)
    a = CSR.from_sparse_csr(dense_a.double().to_sparse_csr())
    b = CSR.from_sparse_csr(dense_b.double().to_sparse_csr())
    pattern = csr_matmul(a, b)
    a_val = a.val.clone().requires_grad_(True)
    b_val = b.val.clone().requires_grad_(True)

    def product(x, y):
        return pattern_matmul(a.with_values(x), b.with_values(y), pattern)

    torch.testing.assert_close(product(a_val, b_val), pattern.val, rtol=0, atol=1e-15)
    assert torch.autograd.gradcheck(product, (a_val, b_val))


def test_bad_input():
    vertices, faces = _grid()
    with pytest.raises(TypeError, match="floating-point"):
        differentiable_multiscale(vertices.long(), faces, 3)
    with pytest.raises(ValueError):
        differentiable_multiscale(vertices, faces, 1)
    with pytest.raises(sl.MeshError):
        differentiable_multiscale(vertices, faces + 100, 3)


@pytest.mark.skipif(
    "differentiable_operator" not in inspect.signature(sl.StochasticLaplacian).parameters,
    reason="StochasticLaplacian(differentiable_operator=...) not in modules.py yet",
)
def test_module_flag_uses_the_differentiable_path():
    vertices, faces = _grid()
    points = vertices.clone().requires_grad_(True)
    constant = sl.StochasticLaplacian(3, THRESHOLD)(points, faces)
    assert not constant.differences.requires_grad  # operators held constant by default
    layer = sl.StochasticLaplacian(3, THRESHOLD, differentiable_operator=True)
    layer(points, faces).differences.sum().backward()
    expected = vertices.clone().requires_grad_(True)
    differentiable_multiscale(expected, faces, 3, THRESHOLD).differences.sum().backward()
    assert points.grad.abs().max() > 0
    torch.testing.assert_close(points.grad, expected.grad, rtol=0, atol=1e-14)
