"""The closed-form eigenvalues of symmetric 3 x 3 matrices behind the robust spread, against
``torch.linalg.eigvalsh`` (LAPACK, float64): values and gradients."""

from __future__ import annotations

import pytest
import torch

from stochlap_torch._common.tensors import symmetric_eigenvalues


def _matrices(eigenvalues: torch.Tensor, seed: int = 0) -> torch.Tensor:
    """``(n, 3, 3)`` symmetric matrices of the given ``(n, 3)`` spectra in random frames."""
    generator = torch.Generator().manual_seed(seed)
    count = eigenvalues.shape[0]
    frames = torch.linalg.qr(torch.randn(count, 3, 3, dtype=torch.float64, generator=generator)).Q
    matrices = frames @ torch.diag_embed(eigenvalues) @ frames.transpose(1, 2)
    return 0.5 * (matrices + matrices.transpose(1, 2))


def _entries(matrices: torch.Tensor) -> tuple[torch.Tensor, ...]:
    m = matrices
    return m[:, 0, 0], m[:, 1, 1], m[:, 2, 2], m[:, 0, 1], m[:, 1, 2], m[:, 2, 0]


def _spectra(kind: str, count: int = 2000) -> torch.Tensor:
    generator = torch.Generator().manual_seed(1)
    if kind == "random":
        return torch.rand(count, 3, dtype=torch.float64, generator=generator) * 4.0 - 1.0
    fixed = {
        "plane": [1.0, 1.0, 0.0],  # the spread of a flat patch
        "near_plane": [1.0, 1.0 + 1e-9, 1e-5],
        "needle": [1.0, 1e-4, 1e-4 + 1e-12],
        "round": [2.0, 2.0, 2.0],
        "zero": [0.0, 0.0, 0.0],
        "wide_range": [1.0, 0.3, 1e-7],
    }[kind]
    return torch.tensor(fixed, dtype=torch.float64).expand(count, 3)


@pytest.mark.parametrize(
    ("kind", "tolerance"),
    [
        ("random", 1e-10),
        ("wide_range", 1e-12),
        ("round", 1e-12),
        ("zero", 0.0),
        # Two nearly equal eigenvalues: the arc cosine near +-1 costs about half the digits.
        ("plane", 1e-7),
        ("near_plane", 1e-7),
        ("needle", 1e-7),
    ],
)
def test_the_eigenvalues_are_lapacks_in_ascending_order(kind, tolerance):
    matrices = _matrices(_spectra(kind))
    expected = torch.linalg.eigvalsh(matrices)
    got = symmetric_eigenvalues(*_entries(matrices))
    scale = matrices.flatten(1).norm(dim=1, keepdim=True).clamp_min(1e-300)
    assert float(((got - expected).abs() / scale).max()) <= tolerance
    assert bool((got.diff(dim=1) >= -tolerance * scale).all())


def test_a_well_separated_small_eigenvalue_keeps_its_relative_digits():
    """The spread's smallest eigenvalue, 1e-7 of the others, to within 1e-7 of itself."""
    matrices = _matrices(_spectra("wide_range"))
    got = symmetric_eigenvalues(*_entries(matrices))[:, 0]
    torch.testing.assert_close(got, torch.full_like(got, 1e-7), rtol=1e-7, atol=0)


def test_the_gradient_is_eigvalshs():
    matrices = _matrices(_spectra("random", 200), seed=3)
    upstream = torch.randn(200, 3, dtype=torch.float64)
    entries = [entry.clone().requires_grad_(True) for entry in _entries(matrices)]
    symmetric_eigenvalues(*entries).backward(upstream)
    full = matrices.clone().requires_grad_(True)
    # eigvalsh reads one triangle; symmetrising makes each off-diagonal entry count twice.
    torch.linalg.eigvalsh(0.5 * (full + full.transpose(1, 2))).backward(upstream)
    expected = _entries(full.grad)
    for index, (got, want) in enumerate(zip(entries, expected, strict=True)):
        factor = 1.0 if index < 3 else 2.0
        torch.testing.assert_close(got.grad, factor * want, rtol=0, atol=1e-9)


@pytest.mark.parametrize("magnitude", [1e-120, 1e-30, 1e30, 1e120])
def test_huge_and_tiny_matrices_are_scaled_not_overflowed(magnitude):
    matrices = _matrices(_spectra("random", 200)) * magnitude
    expected = torch.linalg.eigvalsh(matrices)
    got = symmetric_eigenvalues(*_entries(matrices))
    assert bool(torch.isfinite(got).all())
    torch.testing.assert_close(got / magnitude, expected / magnitude, rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    "kind", ["random", "wide_range", "plane", "near_plane", "needle", "round", "zero"]
)
def test_the_gradient_is_the_spectral_projectors_sum(kind):
    """``d sum_i g_i lambda_i / dA = Q diag(g) Q^T`` from the frames the matrices were built
    in: with an upstream gradient that is a function of the eigenvalue (equal on a repeated
    one, where only that is defined), also on planes, needles and multiples of the identity
    (the closed-form eigenvectors' degenerate branches)."""
    spectra = _spectra(kind, 300)
    generator = torch.Generator().manual_seed(5)
    frames = torch.linalg.qr(torch.randn(300, 3, 3, dtype=torch.float64, generator=generator)).Q
    matrices = frames @ torch.diag_embed(spectra) @ frames.transpose(1, 2)
    matrices = 0.5 * (matrices + matrices.transpose(1, 2))

    def upstream_of(values):
        return torch.sin(3.0 * values) + values.square()

    entries = [entry.clone().requires_grad_(True) for entry in _entries(matrices)]
    values = symmetric_eigenvalues(*entries)
    values.backward(upstream_of(values.detach()))
    expected = frames @ torch.diag_embed(upstream_of(spectra)) @ frames.transpose(1, 2)
    for index, (got, want) in enumerate(zip(entries, _entries(expected), strict=True)):
        factor = 1.0 if index < 3 else 2.0
        torch.testing.assert_close(got.grad, factor * want, rtol=0, atol=1e-7)


def test_the_gradient_of_huge_and_tiny_matrices_is_finite_and_scale_free():
    matrices = _matrices(_spectra("random", 200), seed=4)
    grads = []
    for magnitude in (1e-150, 1.0, 1e150):
        entries = [(e * magnitude).requires_grad_(True) for e in _entries(matrices)]
        weights = torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
        (symmetric_eigenvalues(*entries) * weights).sum().backward()
        grads.append(torch.stack([e.grad for e in entries]))
    for grad in grads:
        torch.testing.assert_close(grad, grads[1], rtol=0, atol=1e-9)
