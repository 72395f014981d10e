"""Baselines (stochlap_torch.baselines): Laplacians against hand-computed values, Algorithm 2
with them against a dense NumPy loop, spectral reconstruction identities, dense vs sparse
eigensolvers, the heat kernel signature on a sphere against the continuum formula, and Lee et
al.'s saliency (invariance, spike, kernel cross-check)."""

from __future__ import annotations

import importlib
import math
import time

import numpy as np
import pytest
import reference as ref
import torch
from reference import icosphere, noisy_sphere

import stochlap_torch as sl
from stochlap_torch.baselines import (
    EigenSolverError,
    bounding_box_diagonal,
    heat_kernel_signature,
    heat_kernel_times,
    laplacian_eigenpairs,
    laplacian_saliency,
    lee_saliency,
    mean_curvature,
    spectral_reconstruction,
)
from stochlap_torch.operators import (
    cotangent_laplacian,
    laplacian_operators,
    lumped_mass,
    uniform_laplacian,
)


def tensors(vertices, faces, dtype=torch.float64):
    return torch.tensor(np.asarray(vertices), dtype=dtype), torch.tensor(np.asarray(faces))


def regular_tetrahedron():
    """Edge length 2 sqrt(2), all angles 60 degrees, every face of area 2 sqrt(3)."""
    vertices = [[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]
    faces = [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]
    return tensors(vertices, faces)


def flat_grid(n: int = 5, spacing: float = 0.5, jitter: float = 0.0, seed: int = 0):
    """``n x n`` planar grid, each square split along the same diagonal (z = 0)."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(n) * spacing, np.arange(n) * spacing, indexing="ij")
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    interior = ((xs > 0) & (xs < xs.max()) & (ys > 0) & (ys < ys.max())).ravel()
    vertices[interior, :2] += jitter * spacing * rng.uniform(-1, 1, size=(interior.sum(), 2))
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            faces += [(a, b, c), (a, c, d)]
    return (*tensors(vertices, faces), interior)


def jittered_torus(nu: int = 40, nv: int = 50, seed: int = 0):
    """A closed genus-1 mesh of ``nu * nv`` vertices with the tube radius jittered by 5 %."""
    u, v = np.meshgrid(
        np.arange(nu) * 2 * np.pi / nu, np.arange(nv) * 2 * np.pi / nv, indexing="ij"
    )
    tube = 0.4 * (1 + 0.05 * np.random.default_rng(seed).uniform(-1, 1, u.shape))
    ring = 1.0 + tube * np.cos(v)
    points = np.stack([ring * np.cos(u), ring * np.sin(u), tube * np.sin(v)], -1).reshape(-1, 3)
    idx = np.arange(nu * nv).reshape(nu, nv)
    a, b = idx, np.roll(idx, -1, 0)
    c, d = np.roll(idx, -1, 1), np.roll(b, -1, 1)
    faces = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)]).reshape(-1, 3)
    return tensors(points, faces)


def dense_cotangent(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``L = D - W`` with ``W_ij = 0.5 sum cot(opposite angle)``, angles from arccos."""
    num = vertices.shape[0]
    weights = np.zeros((num, num))
    for face in faces:
        for corner in range(3):
            k, i, j = face[corner], face[(corner + 1) % 3], face[(corner + 2) % 3]
            u, w = vertices[i] - vertices[k], vertices[j] - vertices[k]
            angle = np.arccos(u @ w / np.linalg.norm(u) / np.linalg.norm(w))
            weights[i, j] += 0.5 / np.tan(angle)
            weights[j, i] += 0.5 / np.tan(angle)
    return np.diag(weights.sum(axis=1)) - weights


# --- Laplacians -----------------------------------------------------------------------------


def test_uniform_laplacian_of_a_tetrahedron_is_4i_minus_j():
    vertices, faces = regular_tetrahedron()
    lap = uniform_laplacian(vertices, faces)
    expected = 4 * torch.eye(4, dtype=torch.float64) - torch.ones(4, 4, dtype=torch.float64)
    torch.testing.assert_close(lap.to_dense(), expected)
    torch.testing.assert_close(lap.mass, torch.ones(4, dtype=torch.float64))


@pytest.mark.parametrize("mass", ["voronoi", "barycentric"])
def test_cotangent_laplacian_of_a_regular_tetrahedron(mass):
    vertices, faces = regular_tetrahedron()
    lap = cotangent_laplacian(vertices, faces, mass=mass)
    w = 1.0 / math.sqrt(3.0)  # 0.5 (cot 60 + cot 60)
    expected = w * (4 * torch.eye(4, dtype=torch.float64) - torch.ones(4, 4, dtype=torch.float64))
    torch.testing.assert_close(lap.to_dense(), expected)
    # Three faces of area 2 sqrt(3) per vertex, a third of each (equilateral: Voronoi = 1/3).
    torch.testing.assert_close(lap.mass, torch.full((4,), 2 * math.sqrt(3.0), dtype=torch.float64))


@pytest.mark.parametrize("mass", ["voronoi", "barycentric"])
def test_cotangent_laplacian_of_a_flat_grid_is_the_five_point_stencil(mass):
    spacing = 0.5
    vertices, faces, interior = flat_grid(5, spacing)
    lap = cotangent_laplacian(vertices, faces, mass=mass)
    dense = lap.to_dense().numpy()
    n = 5
    for v in np.flatnonzero(interior):
        expected = np.zeros(n * n)
        expected[v] = 4.0
        expected[[v - 1, v + 1, v - n, v + n]] = -1.0  # cot 45 twice; diagonals: cot 90 = 0
        np.testing.assert_allclose(dense[v], expected, atol=1e-12)
        assert lap.mass[v].item() == pytest.approx(spacing**2)
    assert lap.mass.sum().item() == pytest.approx((4 * spacing) ** 2)


def test_cotangent_laplacian_is_exact_on_linear_functions_of_a_jittered_plane():
    vertices, faces, interior = flat_grid(7, 1.0, jitter=0.3)
    lap = cotangent_laplacian(vertices, faces)
    dense = lap.to_dense()
    linear = 2.0 * vertices[:, 0] - 3.0 * vertices[:, 1] + 1.0
    torch.testing.assert_close(
        (dense @ linear)[torch.from_numpy(interior)], torch.zeros(25, dtype=torch.float64)
    )
    torch.testing.assert_close(dense, dense.T)


def test_cotangent_laplacian_matches_arccos_loop_and_areas_sum_to_surface():
    base = icosphere(2)
    radial = 1.0 + np.random.default_rng(5).uniform(-0.3, 0.3, size=(len(base.vertices), 1))
    points = base.vertices * radial  # rough enough for obtuse triangles
    vertices, faces = tensors(points, base.faces)
    lap = cotangent_laplacian(vertices, faces)
    expected = dense_cotangent(points, base.faces)
    np.testing.assert_allclose(lap.to_dense().numpy(), expected, atol=1e-12)
    assert bool((lap.weights < 0).any()), "obtuse pairs give negative weights"
    corners = points[base.faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1).sum()
    for kind in ("voronoi", "barycentric"):
        masses = lumped_mass(vertices, faces, kind)
        assert masses.sum().item() == pytest.approx(area)
        assert bool((masses > 0).all())


def test_abs_operators_take_absolute_values_of_negative_cotangent_weights():
    # A flat rhombus whose shared edge faces two 120-degree angles: W = 0.5 (2 cot 120) < 0.
    s = math.sqrt(3.0)
    vertices, faces = tensors(
        [[0, 0, 0], [s, 0, 0], [s / 2, 0.5, 0], [s / 2, -0.5, 0]], [[0, 3, 1], [0, 1, 2]]
    )
    lap = cotangent_laplacian(vertices, faces)
    dense = lap.to_dense()
    assert dense[0, 1].item() == pytest.approx(1.0 / s)  # -W(0, 1), W = -1/sqrt(3)
    ops = laplacian_operators(vertices, faces, "cotangent")
    torch.testing.assert_close(ops.lhat.to_dense(), dense.abs())
    torch.testing.assert_close(ops.alpha, sl.scale_invariance(vertices, faces))


def test_unknown_laplacian_and_mass_names_raise():
    vertices, faces = regular_tetrahedron()
    with pytest.raises(ValueError, match="laplacian"):
        laplacian_saliency(vertices, faces, laplacian="stochastic")
    with pytest.raises(ValueError, match="mass"):
        cotangent_laplacian(vertices, faces, mass="lumped")
    with pytest.raises(sl.MeshError):
        uniform_laplacian(vertices, faces[:, :2])


# --- Algorithm 2 with the uniform and cotangent Laplacians ----------------------------------


def dense_saliency(lhat: np.ndarray, alpha: np.ndarray, num_scales: int, threshold: float):
    """Algorithm 2 densely, with a given ``Lhat``."""
    current = ref.row_normalise(lhat)
    differences = [np.zeros(lhat.shape[0])]
    for _ in range(2, num_scales + 1):
        g = ref.threshold_keep_max(ref.row_normalise(current @ lhat), threshold)
        following = ref.row_normalise(g * alpha[None, :])
        differences.append(np.abs(following - current).sum(axis=1))
        current = following
    return ref.saliency_from_differences(np.stack(differences))


@pytest.mark.parametrize("laplacian", ["uniform", "cotangent"])
def test_laplacian_saliency_matches_a_dense_loop(laplacian):
    mesh = noisy_sphere()
    vertices, faces = mesh.tensors()
    if laplacian == "uniform":
        adjacency = np.zeros((len(mesh.vertices),) * 2)
        for i, j in ref.unique_edges(mesh.faces):
            adjacency[i, j] = adjacency[j, i] = 1.0
        lhat = np.diag(adjacency.sum(axis=1)) + adjacency
    else:
        lhat = np.abs(dense_cotangent(mesh.vertices, mesh.faces))
    expected = dense_saliency(lhat, ref.alpha(mesh.vertices, mesh.faces), 6, 1e-3)
    got = laplacian_saliency(vertices, faces, laplacian, num_scales=6)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-9, atol=1e-12)
    torch_path = laplacian_saliency(vertices, faces, laplacian, num_scales=6, backend="torch")
    torch.testing.assert_close(torch_path, got)


def test_laplacian_saliency_respects_dtype_and_memory_budget():
    vertices, faces = icosphere(2).tensors(torch.float32)
    saliency = laplacian_saliency(vertices, faces, "cotangent", num_scales=3)
    assert saliency.dtype == torch.float32 and bool(torch.isfinite(saliency).all())
    with pytest.raises(sl.MemoryBudgetError):
        laplacian_saliency(vertices, faces, "uniform", max_memory=1000)


# --- Spectral processing --------------------------------------------------------------------


@pytest.mark.parametrize("laplacian", ["uniform", "cotangent"])
def test_spectral_reconstruction_identities(laplacian):
    mesh = noisy_sphere()
    vertices, faces = mesh.tensors()
    num = vertices.shape[0]
    recon = spectral_reconstruction(vertices, faces, [1, 10, num], laplacian=laplacian)
    assert recon.shape == (3, num, 3)
    torch.testing.assert_close(recon[2], vertices, atol=1e-10, rtol=0)
    mass = torch.ones(num, dtype=torch.float64)
    if laplacian == "cotangent":
        mass = lumped_mass(vertices, faces)
    centroid = (mass[:, None] * vertices).sum(dim=0) / mass.sum()
    torch.testing.assert_close(recon[0], centroid.expand(num, 3), atol=1e-10, rtol=0)
    # Projections: more eigenvectors never move the mesh farther (in the M-norm) from itself.
    errors = [(mass[:, None] * (r - vertices) ** 2).sum().item() for r in recon]
    assert errors[0] > errors[1] > errors[2]


def test_spectral_reconstruction_keeps_dtype_and_unreferenced_vertices():
    mesh = ref.with_unreferenced_vertex()
    vertices, faces = mesh.tensors(torch.float32)
    recon = spectral_reconstruction(vertices, faces, [1, vertices.shape[0] - 1])
    assert recon.dtype == torch.float32
    torch.testing.assert_close(recon[:, 20], vertices[20].expand(2, 3))  # the unreferenced one
    torch.testing.assert_close(recon[1], vertices, atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="num_eigenpairs"):
        spectral_reconstruction(vertices, faces, [vertices.shape[0]])


def test_eigenvectors_are_mass_orthonormal():
    vertices, faces = icosphere(2).tensors()
    pairs = laplacian_eigenpairs(vertices, faces, 12)
    gram = pairs.vectors.T @ (pairs.mass[:, None] * pairs.vectors)
    torch.testing.assert_close(gram, torch.eye(12, dtype=torch.float64), atol=1e-10, rtol=0)
    # Unit sphere: 0, then 2 (x3), then ~6 (x5) for the continuous Laplace-Beltrami operator.
    assert pairs.values[0].abs().item() < 1e-10
    np.testing.assert_allclose(pairs.values[1:4].numpy(), 2.0, rtol=0.03)


def test_sparse_eigsh_matches_dense_eigh_on_a_2k_vertex_mesh():
    vertices, faces = jittered_torus(40, 50)
    assert vertices.shape[0] == 2000
    dense = laplacian_eigenpairs(vertices, faces, 12, method="dense")
    sparse = laplacian_eigenpairs(vertices, faces, 12, method="sparse")
    assert (dense.method, sparse.method) == ("dense", "sparse")
    torch.testing.assert_close(sparse.values, dense.values, atol=1e-9, rtol=1e-9)
    # The jitter splits the torus's symmetric pairs, so each eigenvector is determined up to
    # sign, which both paths fix the same way.
    torch.testing.assert_close(sparse.vectors, dense.vectors, atol=1e-8, rtol=0)


def test_sparse_solver_retries_then_raises(monkeypatch):
    from scipy.sparse import linalg

    real = linalg.eigsh
    calls = []

    def flaky(*args, **kwargs):
        calls.append(kwargs["sigma"])
        if len(calls) == 1:
            raise linalg.ArpackNoConvergence("no convergence", np.zeros(0), np.zeros((0, 0)))
        return real(*args, **kwargs)

    vertices, faces = icosphere(2).tensors()
    monkeypatch.setattr(linalg, "eigsh", flaky)
    pairs = laplacian_eigenpairs(vertices, faces, 4, method="sparse")
    assert len(calls) == 2 and calls[1] == pytest.approx(10 * calls[0]) and calls[0] < 0
    expected = laplacian_eigenpairs(vertices, faces, 4, method="dense")
    torch.testing.assert_close(pairs.values, expected.values, atol=1e-9, rtol=0)

    def broken(*args, **kwargs):
        raise RuntimeError("Factor is exactly singular")

    monkeypatch.setattr(linalg, "eigsh", broken)
    with pytest.raises(EigenSolverError, match="exactly singular"):
        laplacian_eigenpairs(vertices, faces, 4, method="sparse")


# --- Heat kernel signature ------------------------------------------------------------------


def test_hks_on_a_sphere_is_positive_decreasing_constant_and_near_the_continuum():
    vertices, faces = icosphere(3).tensors()
    # 64 = 1 + 3 + ... + 15 eigenpairs: complete clusters l = 0..7, so the sum is rotation
    # invariant and the signature is the same at every vertex.
    hks = heat_kernel_signature(vertices, faces, num_eigenpairs=64, num_times=8)
    assert hks.shape == (vertices.shape[0], 8)
    assert bool((hks > 0).all())
    assert bool((hks.diff(dim=1) < 0).all())
    mean = hks.mean(dim=0)
    assert (hks.std(dim=0) / mean).max().item() < 1e-3
    pairs = laplacian_eigenpairs(vertices, faces, 64)
    times = heat_kernel_times(pairs.values, 8)
    assert times[0].item() == pytest.approx(4 * math.log(10) / pairs.values[-1].item())
    assert times[-1].item() == pytest.approx(4 * math.log(10) / pairs.values[1].item())
    degree = np.arange(60)
    continuum = [
        np.sum((2 * degree + 1) / (4 * np.pi) * np.exp(-degree * (degree + 1) * t))
        for t in times.tolist()
    ]
    np.testing.assert_allclose(mean.numpy(), continuum, rtol=0.03)


def test_hks_zeroes_unreferenced_vertices_and_checks_times():
    vertices, faces = ref.with_unreferenced_vertex().tensors()
    hks = heat_kernel_signature(vertices, faces, num_eigenpairs=10, num_times=4)
    assert bool((hks[20] == 0).all())
    others = hks[torch.arange(hks.shape[0]) != 20]
    assert bool(torch.isfinite(others).all()) and bool((others > 0).all())
    with pytest.raises(ValueError, match="times"):
        heat_kernel_signature(vertices, faces, 10, times=torch.tensor([1.0, -1.0]))


def test_precomputed_eigenpairs_give_the_same_hks_and_reconstruction(monkeypatch):
    vertices, faces = icosphere(2).tensors()
    pairs = laplacian_eigenpairs(vertices, faces, 20)
    expected_hks = heat_kernel_signature(vertices, faces, num_eigenpairs=20, num_times=6)
    expected_rec = spectral_reconstruction(vertices, faces, [4, 20])
    import stochlap_torch.baselines.spectral as sp

    def no_solve(*args, **kwargs):
        raise AssertionError("the eigenpairs were recomputed")

    monkeypatch.setattr(sp, "_eigenpairs", no_solve)
    hks = heat_kernel_signature(vertices, faces, num_times=6, eigenpairs=pairs)
    torch.testing.assert_close(hks, expected_hks, atol=1e-12, rtol=1e-10)
    rec = spectral_reconstruction(vertices, faces, [4, 20], eigenpairs=pairs)
    torch.testing.assert_close(rec, expected_rec, atol=1e-12, rtol=0)
    hks32 = heat_kernel_signature(vertices.float(), faces, num_times=6, eigenpairs=pairs)
    assert hks32.dtype == torch.float32
    with pytest.raises(ValueError, match="21 eigenpairs are needed, 20"):
        spectral_reconstruction(vertices, faces, [21], eigenpairs=pairs)
    other, other_faces = icosphere(1).tensors()
    with pytest.raises(ValueError, match="mesh with 162 vertices, this one has 42"):
        heat_kernel_signature(other, other_faces, eigenpairs=pairs)
    with pytest.raises(ValueError, match="must be an Eigenpairs"):
        heat_kernel_signature(vertices, faces, eigenpairs=(pairs.values, pairs.vectors))


def test_intrinsic_laplacian_is_cotangent_on_a_delaunay_mesh_and_nonnegative_on_a_bad_one():
    # An icosphere's triangulation is already Delaunay: the intrinsic Laplacian is the
    # cotangent one (robust-laplacian's mass is barycentric).
    vertices, faces = icosphere(2).tensors()
    intrinsic = sl.operators.intrinsic_laplacian(vertices, faces)
    cotangent = cotangent_laplacian(vertices, faces, mass="barycentric")
    torch.testing.assert_close(intrinsic.to_dense(), cotangent.to_dense(), atol=1e-10, rtol=0)
    torch.testing.assert_close(intrinsic.mass, cotangent.mass, atol=1e-12, rtol=0)
    # A jittered torus has obtuse angles: negative cotangent weights, none intrinsically.
    vertices, faces = jittered_torus(12, 16, seed=1)
    assert (cotangent_laplacian(vertices, faces).weights < 0).any()
    intrinsic = sl.operators.intrinsic_laplacian(vertices.float(), faces)
    assert intrinsic.weights.dtype == torch.float32 and bool((intrinsic.weights >= 0).all())
    dense = intrinsic.to_dense().double()
    assert dense.sum(dim=1).abs().max().item() < 1e-5  # L 1 = 0
    torch.testing.assert_close(dense, dense.T)
    hks = heat_kernel_signature(vertices, faces, num_eigenpairs=16, laplacian="intrinsic")
    assert bool((hks > 0).all()) and bool((hks.diff(dim=1) < 0).all())


# --- Lee et al. mesh saliency ---------------------------------------------------------------


def bumpy_ellipsoid(seed: int = 3):
    """A sphere stretched to distinct axes (so its principal frame is well defined) with
    smooth bumps (so the saliency is not flat)."""
    mesh = icosphere(3)
    points = mesh.vertices * np.array([1.6, 1.0, 0.7])
    bumps = 1.0 + 0.08 * np.sin(3 * mesh.vertices[:, :1]) * np.cos(2 * mesh.vertices[:, 1:2])
    return tensors(points * bumps, mesh.faces)


def test_mean_curvature_of_a_sphere():
    vertices, faces = icosphere(3).tensors()
    curvature = mean_curvature(2.0 * vertices, faces)
    np.testing.assert_allclose(curvature.numpy(), 0.5, rtol=1e-3)


def test_lee_saliency_is_rotation_invariant_and_finite():
    vertices, faces = bumpy_ellipsoid()
    saliency = lee_saliency(vertices, faces)
    assert bool(torch.isfinite(saliency).all()) and bool((saliency >= 0).all())
    assert saliency.max().item() > 0
    q, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))
    rotated = vertices @ torch.from_numpy(q).T + torch.tensor([3.0, -1.0, 2.0], dtype=torch.float64)
    torch.testing.assert_close(lee_saliency(rotated, faces), saliency, atol=1e-9, rtol=1e-7)
    assert bounding_box_diagonal(rotated.numpy()) == pytest.approx(
        bounding_box_diagonal(vertices.numpy())
    )


def test_lee_saliency_is_highest_near_a_spike():
    mesh = icosphere(4)
    vertices, faces = mesh.tensors()
    spike = 0
    vertices[spike] *= 1.25
    edge = np.linalg.norm(
        mesh.vertices[mesh.faces[:, 0]] - mesh.vertices[mesh.faces[:, 1]], axis=1
    ).mean()
    saliency = lee_saliency(vertices, faces, epsilon=edge / 2)
    distance = (vertices - vertices[spike]).norm(dim=1)
    near, far = distance < 6 * edge, distance > 12 * edge
    assert distance[saliency.argmax()].item() < 4 * edge
    assert saliency[near].mean().item() > 20 * saliency[far].mean().item()


def test_lee_saliency_numba_and_numpy_paths_agree_and_unreferenced_vertices_get_zero():
    mesh = noisy_sphere()
    extra = 30  # an unreferenced vertex inserted at index 30, inside the sphere
    points = np.insert(mesh.vertices, extra, [[0.1, 0.2, -0.1]], axis=0)
    vertices, faces = tensors(points, np.where(mesh.faces >= extra, mesh.faces + 1, mesh.faces))
    eps = 0.047
    fast = lee_saliency(vertices, faces, epsilon=eps)
    slow = lee_saliency(vertices, faces, epsilon=eps, use_numba=False)
    torch.testing.assert_close(fast, slow, atol=1e-12, rtol=1e-10)
    assert fast[extra].item() == 0.0
    without = lee_saliency(*mesh.tensors(), epsilon=eps)
    torch.testing.assert_close(torch.cat([fast[:extra], fast[extra + 1 :]]), without)


@pytest.mark.parametrize("use_numba", [True, False])
def test_lee_suppression_factor_on_a_line(use_numba):
    # Points 1 apart on a line, neighbourhood radius 1.5 (one point each side). Local maxima:
    # 1.0 (global, excluded), 0.5, 0.3 and 0.25, so m_bar = 0.35 and the factor is 0.65^2.
    module = importlib.import_module("stochlap_torch.baselines.lee_saliency")
    points = np.stack([np.arange(10.0), np.zeros(10), np.zeros(10)], axis=1)
    values = np.array([[0.1, 1.0, 0.2, 0.5, 0.4, 0.05, 0.3, 0.2, 0.25, 0.1]])
    factors = module._suppression_factors(points, values, np.array([1.5]), use_numba)
    assert factors.tolist() == pytest.approx([0.65**2])


def test_lee_saliency_rejects_bad_input():
    vertices, faces = icosphere(1).tensors()
    with pytest.raises(ValueError, match="scales"):
        lee_saliency(vertices, faces, scales=[])
    with pytest.raises(ValueError, match="epsilon"):
        lee_saliency(vertices, faces, epsilon=-1.0)
    with pytest.raises(ValueError, match="curvature"):
        lee_saliency(vertices, faces, curvature=torch.zeros(3))


@pytest.mark.slow
def test_lee_saliency_and_eigsh_on_a_50k_mesh(meshes_dir):
    path = meshes_dir / "gargoyle_50k.off"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    mesh = sl.load_mesh(path)
    start = time.perf_counter()
    saliency = lee_saliency(mesh.vertices, mesh.faces)
    assert time.perf_counter() - start < 60.0
    assert bool(torch.isfinite(saliency).all())
    pairs = laplacian_eigenpairs(mesh.vertices, mesh.faces, 20)
    assert pairs.method == "sparse" and pairs.values[0].abs().item() < 1e-8


def test_hks_on_a_real_mesh_takes_the_sparse_path(meshes_dir):
    path = meshes_dir / "spot.obj"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    mesh = sl.load_mesh(path)
    assert mesh.num_vertices > 2000  # above DENSE_LIMIT: method="auto" is eigsh
    pairs = laplacian_eigenpairs(mesh.vertices, mesh.faces, 24)
    assert pairs.method == "sparse"
    gram = pairs.vectors.T @ (pairs.mass[:, None] * pairs.vectors)
    torch.testing.assert_close(gram, torch.eye(24, dtype=torch.float64), atol=1e-8, rtol=0)
    hks = heat_kernel_signature(mesh.vertices, mesh.faces, num_eigenpairs=24, num_times=5)
    assert bool((hks > 0).all()) and bool((hks.diff(dim=1) < 0).all())


def test_sparse_eigenpairs_are_the_same_on_every_call():
    """ARPACK starts from a random vector unless given one: the HKS (and the ``hks``
    detector of ``stochlap evaluate``) differed call to call in their last digits."""
    mesh = sl.load_mesh(sl.bundled_mesh_path())
    first = sl.baselines.laplacian_eigenpairs(mesh.vertices, mesh.faces, 16, method="sparse")
    second = sl.baselines.laplacian_eigenpairs(mesh.vertices, mesh.faces, 16, method="sparse")
    assert torch.equal(first.values, second.values)
    assert torch.equal(first.vectors, second.vectors)
