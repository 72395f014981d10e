"""The parts of the robust variant against plain dense float64 references written here: the
heat semigroup (Chebyshev) against ``expm``, its backward pass against the dense transpose,
the heat kernel diagonal from a few eigenpairs against the dense exponential's diagonal, the
pyramid's interpolation against a loop, the closest-triangle kernel against brute force, the
removal of stacked triangles against a loop, the operator's bandwidth-reducing order (a
permutation of the Laplacian) and its recurrence matrix, the blocks of Chebyshev terms
against the plain recurrence, the clamp of the edge weights against a loop (and its effect:
near-coincident vertices keep the features), and the saliency's ``dn``-only path against the full
representation."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse
import scipy.stats
import torch
from reference import heat_apply, icosphere, noisy_sphere

import stochlap_torch as sl
from stochlap_torch._kernels import closest_triangles
from stochlap_torch.robust import RobustParams, robust_representation, robust_saliency
from stochlap_torch.robust import heat as heat_module
from stochlap_torch.robust.channels import unit_area
from stochlap_torch.robust.heat import (
    HEAT_TRUNCATION,
    HeatSemigroups,
    LevelSemigroup,
    chebyshev_apply,
    chebyshev_apply_groups,
    chebyshev_coefficients,
    clamped_weights,
    heat_diagonal,
    heat_operator,
)
from stochlap_torch.robust.pyramid import Interpolation, _unstacked, build_pyramid
from stochlap_torch.robust.structure import build_structure as robust_structure

DEFAULT_TOLERANCE = RobustParams().tolerance


def _bumpy_sphere(subdivisions: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """An icosphere at unit area with smooth bumps and a little noise."""
    mesh = icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    v = mesh.vertices * (1.0 + 0.15 * np.sin(3.0 * mesh.vertices[:, [1]]))
    v = v + 0.002 * rng.standard_normal(v.shape)
    f = torch.from_numpy(mesh.faces)
    return unit_area(torch.from_numpy(v), f)[0].numpy(), mesh.faces


def _dense_generator(operator) -> np.ndarray:
    """``m^-1 L`` as a dense array (``m`` the capped masses)."""
    return operator.laplacian.toarray() / operator.capped_mass[:, None]


def _capped_operator(subdivisions: int):
    """The heat operator of a bumpy sphere with a low mass cap, so that the capped masses and
    the vertex areas differ (a test that takes one for the other fails)."""
    vertices, faces = _bumpy_sphere(subdivisions)
    operator = heat_operator(vertices, faces, cap=1.2)
    assert (operator.capped_mass > operator.mass).sum() > 0.05 * operator.num_vertices
    return operator


def test_semigroup_matches_the_dense_exponential():
    operator = _capped_operator(3)
    fields = np.random.default_rng(1).standard_normal((operator.num_vertices, 5))
    times = [2e-3, 8e-3, 3e-2]
    out = heat_apply(operator, fields, times)
    for index, t in enumerate(times):
        expected = scipy.linalg.expm(-t * _dense_generator(operator)) @ fields
        np.testing.assert_allclose(out[index], expected, rtol=0, atol=1e-5)


def test_operator_order_is_a_permutation_of_the_laplacian():
    operator = _capped_operator(3)
    order = operator.order
    np.testing.assert_array_equal(np.sort(order), np.arange(operator.num_vertices))
    scaled = 2.0 * (2.0 / operator.bound * _dense_generator(operator) - np.eye(order.size))
    np.testing.assert_allclose(
        operator.recurrence.toarray(),
        scaled[np.ix_(order, order)],
        rtol=1e-15,
        atol=1e-15 * np.abs(scaled).max(),
    )


def _naive_chebyshev(operator, fields: np.ndarray, times: list[float]) -> np.ndarray:
    """``(T, n, C)``: the Chebyshev sum of the semigroup, term by term in the mesh's own
    order with a dense ``y = (2 / bound) m^-1 L - I``."""
    coefficients = chebyshev_coefficients(np.asarray(times), operator.bound, DEFAULT_TOLERANCE)
    y = 2.0 / operator.bound * _dense_generator(operator) - np.eye(fields.shape[0])
    terms = [fields, y @ fields]
    while len(terms) < coefficients.shape[1]:
        terms.append(2.0 * y @ terms[-1] - terms[-2])
    return np.stack(
        [
            sum(coefficients[t, k] * terms[k] for k in range(coefficients.shape[1]))
            for t in range(len(times))
        ]
    )


@pytest.mark.parametrize("per_product", [2, 3, 4, 16])
def test_semigroup_blocks_of_terms_add_up_to_the_plain_recurrence(monkeypatch, per_product):
    """The terms are summed a block at a time: every count of terms, at and beside the block
    boundaries, gives the plain recurrence's sum."""
    monkeypatch.setattr(heat_module, "_MAX_TERMS_PER_PRODUCT", per_product)
    monkeypatch.setattr(heat_module, "_TERMS_PER_TIME", per_product)  # blocks of per_product
    operator = _capped_operator(2)
    fields = np.random.default_rng(3).standard_normal((operator.num_vertices, 4))
    counts = set()
    singles = [[float(t)] for t in np.geomspace(1e-12, 0.3, 25)]
    for times in [*singles, [1e-6, 1e-5], [1e-4, 4e-4, 2e-3], [0.1, 0.3]]:
        counts.add(
            chebyshev_coefficients(np.asarray(times), operator.bound, DEFAULT_TOLERANCE).shape[1]
        )
        increments = chebyshev_apply(
            LevelSemigroup.of(operator), torch.from_numpy(fields), times, DEFAULT_TOLERANCE
        )
        np.testing.assert_allclose(
            increments.numpy() + fields,
            _naive_chebyshev(operator, fields, times),
            rtol=0.0,
            atol=1e-12,
        )
    assert {1, 2, 3}.issubset(counts) and max(counts) > 2 * per_product, counts


@pytest.mark.parametrize("per_product", [2, 5, 16])
def test_semigroup_backward_is_the_dense_transpose(monkeypatch, per_product):
    """Three times, their gradients by one adjoint (Clenshaw) recurrence whose terms come in
    blocks of two, five or sixteen (a last block shorter)."""
    monkeypatch.setattr(heat_module, "_MAX_TERMS_PER_PRODUCT", per_product)
    operator = _capped_operator(2)
    times = (4e-3, 1e-2, 2e-2)
    rng = np.random.default_rng(2)
    count = operator.num_vertices
    fields = torch.from_numpy(rng.standard_normal((count, 3))).requires_grad_(True)
    upstream = torch.from_numpy(rng.standard_normal((len(times), count, 3)))
    (out,) = HeatSemigroups.apply(
        LevelSemigroup.of(operator), (times,), 1e-10, torch.float64, fields
    )
    out.backward(upstream)
    identity = np.eye(count)
    expected = sum(
        (scipy.linalg.expm(-t * _dense_generator(operator)) - identity).T @ upstream[i].numpy()
        for i, t in enumerate(times)
    )
    np.testing.assert_allclose(fields.grad.numpy(), expected, rtol=0, atol=1e-8)


def test_groups_sharing_a_recurrence_get_their_own_increments():
    """Groups of fields side by side in one recurrence (each its times, its truncation and its
    first term's dtype) get what each gets alone, up to rounding: a group of fewer terms keeps
    its truncation, ``keep`` picks one time."""
    semigroup = LevelSemigroup.of(_capped_operator(2))
    rng = np.random.default_rng(4)
    count = semigroup.order.numel()
    wide = torch.from_numpy(rng.standard_normal((count, 4)))
    narrow = torch.from_numpy(rng.standard_normal((count, 3))).float()
    plans = [(wide, (4e-3, 1e-2), None), (narrow, (1e-4,), None), (wide[:, :2], (4e-3, 2e-2), 1)]
    together = chebyshev_apply_groups(semigroup, plans, DEFAULT_TOLERANCE, torch.float64)
    for (fields, times, keep), got in zip(plans, together, strict=True):
        alone = chebyshev_apply(semigroup, fields, times, DEFAULT_TOLERANCE, torch.float64)
        alone = alone if keep is None else alone[keep]
        assert got.shape == alone.shape and got.dtype == torch.float64
        torch.testing.assert_close(got, alone, rtol=0, atol=1e-14)


def test_the_grouped_semigroup_backward_is_each_groups():
    semigroup = LevelSemigroup.of(_capped_operator(2))
    rng = np.random.default_rng(5)
    count = semigroup.order.numel()
    first = torch.from_numpy(rng.standard_normal((count, 4))).requires_grad_(True)
    second = torch.from_numpy(rng.standard_normal((count, 3))).requires_grad_(True)
    times = ((4e-3, 1e-2, 2e-2, 3e-2), (2e-3, 1.25e-4))
    up = [
        torch.from_numpy(rng.standard_normal((len(t), count, f.shape[1])))
        for t, f in zip(times, (first, second), strict=True)
    ]
    outputs = HeatSemigroups.apply(semigroup, times, 1e-10, torch.float64, first, second)
    torch.autograd.backward(outputs, up)
    for fields, group, upstream in zip((first, second), times, up, strict=True):
        alone = fields.detach().clone().requires_grad_(True)
        (out,) = HeatSemigroups.apply(semigroup, (group,), 1e-10, torch.float64, alone)
        out.backward(upstream)
        torch.testing.assert_close(fields.grad, alone.grad, rtol=0, atol=1e-12)


@pytest.mark.parametrize("subdivisions", [2, 3], ids=["dense", "lanczos"])
def test_heat_diagonal_matches_the_dense_exponential(subdivisions):
    """A few hundred vertices: a full eigendecomposition; 642: the low eigenpairs only."""
    operator = _capped_operator(subdivisions)
    times = np.array([0.032, 0.064])
    values = heat_diagonal(operator, times)
    # h_t(i, i) = exp(-t M^-1 L)(i, i) / M_i: the kernel with respect to the vertex areas.
    generator = operator.laplacian.toarray() / operator.mass[:, None]
    for index, t in enumerate(times):
        diagonal = np.diag(scipy.linalg.expm(-t * generator))
        expected = np.log(4.0 * math.pi * t * diagonal / operator.mass)
        # The truncation changes h relatively by about HEAT_TRUNCATION at the smallest time.
        np.testing.assert_allclose(
            values[:, index], expected, rtol=0, atol=20 * HEAT_TRUNCATION + 1e-9
        )


def test_clamped_weights_bound_every_edge_rate():
    rng = np.random.default_rng(4)
    edges = rng.integers(0, 30, size=(200, 2))
    weights = rng.lognormal(0.0, 2.0, size=200)
    weights[:3] = 0.0
    mass = rng.lognormal(0.0, 1.0, size=30)
    clamp = 5.0
    out = clamped_weights(edges, weights, mass, clamp)
    rates = [w / min(mass[i], mass[j]) for (i, j), w in zip(edges, weights, strict=True) if w > 0]
    limit = clamp * float(np.median(rates))
    for (i, j), w, clamped in zip(edges, weights, out, strict=True):
        assert clamped == pytest.approx(min(w, limit * min(mass[i], mass[j])), rel=1e-15)


def _split_edges(vertices, faces, count: int, fraction: float, seed: int = 0):
    """``count`` edges, no two sharing a vertex, each split by a new vertex at ``fraction`` of
    its length from one end (a near-coincident pair, as quadric decimation leaves them)."""
    rng = np.random.default_rng(seed)
    points, triangles, used = list(vertices), [list(t) for t in faces], set()
    for _ in range(count):
        a, b = triangles[int(rng.integers(len(triangles)))][:2]
        while {a, b} & used:
            a, b = triangles[int(rng.integers(len(triangles)))][:2]
        used.update((a, b))
        points.append(points[a] + fraction * (points[b] - points[a]))
        split = []
        for t in triangles:
            if a in t and b in t:
                split += [
                    [len(points) - 1 if c == b else c for c in t],
                    [len(points) - 1 if c == a else c for c in t],
                ]
            else:
                split.append(t)
        triangles = split
    return np.array(points), np.array(triangles)


def test_near_coincident_vertices_do_not_become_heat_reservoirs():
    """A near-coincident pair shares a huge cotangent weight: the clamp keeps the masses the
    areas, and the features at the mesh's own vertices barely move (raising the pair's masses
    instead multiplied the total mass by 19 and dropped the mean rank correlation to 0.76)."""
    vertices, faces = _bumpy_sphere(4)
    split_vertices, split_faces = _split_edges(vertices, faces, 60, 1e-4)
    operator = heat_operator(split_vertices, split_faces)
    assert operator.capped_mass.sum() < 1.01 * operator.mass.sum()
    plain = sl.multiscale_features(torch.from_numpy(vertices), torch.from_numpy(faces)).numpy()
    split = sl.multiscale_features(torch.from_numpy(split_vertices), torch.from_numpy(split_faces))
    split = split.numpy()[: len(vertices)]
    # The twist of a near-symmetric sphere is noise of 1e-4, with no ranks to keep: it must
    # stay small beside the curvature's spread.
    twist = np.array([name.startswith("twist") for name in sl.feature_channel_names()])
    shaped = np.flatnonzero(~twist)
    rho = [scipy.stats.spearmanr(plain[:, c], split[:, c])[0] for c in shaped]
    assert np.mean(rho) > 0.98 and np.min(rho) > 0.9, rho
    assert np.abs(plain[:, twist] - split[:, twist]).max() < 0.1 * plain[:, 0].std()


def test_interpolation_is_the_barycentric_sum():
    rng = np.random.default_rng(3)
    corners = torch.from_numpy(rng.integers(0, 10, size=(25, 3)))
    weights = torch.from_numpy(rng.dirichlet(np.ones(3), size=25))
    values = torch.from_numpy(rng.standard_normal((10, 2, 3)))
    out = Interpolation(corners, weights)(values)
    expected = torch.zeros(25, 2, 3, dtype=torch.float64)
    for row in range(25):
        for k in range(3):
            expected[row] += weights[row, k] * values[corners[row, k]]
    torch.testing.assert_close(out, expected, rtol=0, atol=1e-14)


def test_interpolation_gradients_are_the_transposed_sum():
    """The backward pass multiplies by the stored transpose: gradcheck against finite
    differences, on corners that repeat across rows (the transpose's rows gather them)."""
    rng = np.random.default_rng(4)
    corners = torch.from_numpy(np.argsort(rng.random((40, 6)), axis=1)[:, :3])  # a triangle's
    weights = torch.from_numpy(rng.dirichlet(np.ones(3), size=40))
    values = torch.from_numpy(rng.standard_normal((6, 2))).requires_grad_(True)
    assert torch.autograd.gradcheck(Interpolation(corners, weights), (values,))
    with pytest.raises(ValueError, match="5 vertices"):
        Interpolation(corners, weights)(values[:5])


def _brute_closest(point, vertices, faces):
    """Squared distance from ``point`` to the closest of all triangles (sampled densely)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    best = np.inf
    steps = 60
    for i in range(steps + 1):
        for j in range(steps + 1 - i):
            u, v = i / steps, j / steps
            q = a + u * (b - a) + v * (c - a)
            best = min(best, float(((q - point) ** 2).sum(axis=1).min()))
    return best


def test_closest_triangles_against_brute_force():
    coarse = icosphere(1)
    rng = np.random.default_rng(4)
    points = rng.standard_normal((40, 3))
    points = points / np.linalg.norm(points, axis=1, keepdims=True) * rng.uniform(0.9, 1.1, (40, 1))
    everything = np.tile(np.arange(coarse.vertices.shape[0]), (points.shape[0], 1))
    face, bary = closest_triangles(points, coarse.vertices, coarse.faces, everything, threads=2)
    assert np.allclose(bary.sum(axis=1), 1.0) and (bary >= -1e-12).all()
    found = np.einsum("ij,ijc->ic", bary, coarse.vertices[coarse.faces[face]])
    for point, closest in zip(points, found, strict=True):
        distance = float(((closest - point) ** 2).sum())
        # The sampled brute force is an upper bound of the true distance: never below it.
        assert distance <= _brute_closest(point, coarse.vertices, coarse.faces) + 1e-12


def test_pyramid_levels_are_subsets_with_convex_interpolation():
    vertices, faces = _bumpy_sphere(4)  # 2562 vertices
    levels = build_pyramid(vertices, faces, ratio=4.0, min_vertices=100, threads=2)
    assert len(levels) >= 3
    for above, level in itertools.pairwise(levels):
        n_above, n = above.vertices.shape[0], level.vertices.shape[0]
        assert n_above / 8 < n < n_above / 2
        np.testing.assert_array_equal(level.vertices, vertices[level.vertex_ids])
        assert set(level.vertex_ids) <= set(above.vertex_ids)
        face, bary = level.prolong
        assert face.shape == (n_above,) and ((face >= 0) & (face < level.faces.shape[0])).all()
        assert np.allclose(bary.sum(axis=1), 1.0) and (bary >= -1e-12).all()


def test_unstacked_drops_every_copy_of_a_stacked_triangle():
    rng = np.random.default_rng(3)
    triangles = rng.integers(0, 30, (200, 3))
    triangles[7] = triangles[150][[2, 0, 1]]  # the same three vertices, other order
    triangles[90] = triangles[150]
    kept = _unstacked(triangles)
    for i, triangle in enumerate(triangles):
        others = [
            j for j in range(len(triangles)) if j != i and sorted(triangles[j]) == sorted(triangle)
        ]
        assert kept[i] == (not others)
    assert not kept[[7, 90, 150]].any()


def test_structure_without_heat_has_the_same_levels():
    vertices, faces = noisy_sphere().tensors()
    params = RobustParams(min_vertices=40, num_scales=4)
    full = robust_structure(vertices, faces, params)
    light = robust_structure(vertices, faces, params, heat=False)
    assert light.heat is None and full.heat is not None
    assert light.assignment == full.assignment
    assert [lv.num_vertices for lv in light.levels] == [lv.num_vertices for lv in full.levels]


def test_saliency_computes_dn_alone_with_the_same_result():
    """The saliency's path diffuses half the fields and skips the spread and heat channels;
    its dn (and so the saliency) is the full representation's."""
    mesh = sl.load_mesh(sl.bundled_mesh_path())
    full = robust_representation(mesh.vertices, mesh.faces)
    light = robust_representation(mesh.vertices, mesh.faces, dn_only=True)
    assert light.spread is None and light.heat is None
    torch.testing.assert_close(light.dn, full.dn, rtol=0, atol=1e-12)
    torch.testing.assert_close(
        sl.saliency(mesh.vertices, mesh.faces), robust_saliency(full), rtol=0, atol=1e-12
    )


def _rl_weights(vertices, faces):
    """robust-laplacian's weights as a dict {(i, j): w} (i < j) and its masses."""
    robust_laplacian = pytest.importorskip("robust_laplacian")
    laplacian, mass = robust_laplacian.mesh_laplacian(vertices, faces)
    upper = scipy.sparse.triu(laplacian, k=1).tocoo()
    return {
        (int(i), int(j)): -float(w)
        for i, j, w in zip(upper.row, upper.col, upper.data, strict=True)
    }, mass.diagonal()


def _jittered_sphere(seed: int, amplitude: float = 0.06) -> tuple[np.ndarray, np.ndarray]:
    """icosphere(3) with vertices slid along the surface: many obtuse triangles, so the
    intrinsic Delaunay triangulation differs from the mesh's."""
    mesh = icosphere(3)
    rng = np.random.default_rng(seed)
    v = mesh.vertices + amplitude * rng.standard_normal(mesh.vertices.shape)
    return v / np.linalg.norm(v, axis=1, keepdims=True), mesh.faces


def _cotan_weights(vertices, faces) -> np.ndarray:
    """Plain (extrinsic) cotangent weight of every face corner's opposite edge, per corner."""
    out = []
    for corner in range(3):
        a, b, c = (vertices[faces[:, (corner + s) % 3]] for s in range(3))
        u, w = b - a, c - a
        out.append(np.einsum("ij,ij->i", u, w) / np.linalg.norm(np.cross(u, w), axis=1))
    return np.stack(out, 1)


@pytest.mark.parametrize(
    ("seed", "amplitude", "loops"), [(1, 0.06, 0), (2, 0.06, 0), (0, 0.06, 1), (0, 0.1, 9)]
)
def test_intrinsic_delaunay_flips_match_robust_laplacian(seed, amplitude, loops):
    """The library's flips give robust-laplacian's weights. From seed 0 they reach edges
    whose two triangles share all three vertices (around a vertex of degree 2: two sides of
    the quad are one edge): the flip joins a vertex to itself, as geometry-central's does,
    and the loop drops out of the Laplacian. At the larger amplitude many such flips follow
    one another."""
    from stochlap_torch._kernels import intrinsic_delaunay_weights

    vertices, faces = _jittered_sphere(seed, amplitude)
    # the mesh itself is far from Delaunay: some edges have negative cotangent weights
    corner_cot = _cotan_weights(vertices, faces)
    assert (corner_cot < -0.3).sum() > 10
    rows, cols, _, _ = sl._kernels.intrinsic_delaunay(vertices, faces)
    assert int((rows == cols).sum()) == loops
    edges, weights, mass = intrinsic_delaunay_weights(vertices, faces)
    expected, expected_mass = _rl_weights(vertices, faces)
    ours = {(int(i), int(j)): float(w) for (i, j), w in zip(edges, weights, strict=True)}
    for key in set(ours) | set(expected):
        assert ours.get(key, 0.0) == pytest.approx(max(expected.get(key, 0.0), 0.0), abs=1e-10)
    np.testing.assert_allclose(mass, expected_mass, rtol=1e-12, atol=0)
    mesh_edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    assert set(ours) - {(int(a), int(b)) for a, b in mesh_edges}  # flips made new edges


@pytest.mark.parametrize("seed", range(4))
def test_intrinsic_delaunay_flips_keep_a_triangulation(seed):
    """After many flips, loops among them, every halfedge's twin runs back between the same
    two vertices along the same edge, every edge has two halfedges, and the triangles keep
    the surface's area: a flip that mis-wires a side of its quad breaks one of these."""
    from stochlap_torch._kernels.geometry import delaunay_triangulation

    vertices, faces = _jittered_sphere(seed, 0.15)
    tail, twin, edge, length = delaunay_triangulation(vertices, faces)
    halfedge = np.arange(tail.size)
    following = halfedge - halfedge % 3 + (halfedge + 1) % 3  # the next corner of its face
    assert (twin[twin] == halfedge).all() and (twin != halfedge).all()
    assert (tail[twin] == tail[following]).all()  # the twin starts where the halfedge ends
    assert (edge[twin] == edge).all()
    assert (np.bincount(edge, minlength=length.size) == 2).all()
    assert (tail == tail[following]).sum() >= 8  # loops: the flips joined vertices to themselves
    sides = length[edge].reshape(-1, 3)
    half = sides.sum(axis=1) / 2.0
    heron = np.sqrt(np.clip(half * (half[:, None] - sides).prod(axis=1), 0.0, None))
    corners = vertices[faces]
    doubled = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert heron.sum() == pytest.approx(np.linalg.norm(doubled, axis=1).sum() / 2.0, rel=1e-6)


def test_intrinsic_delaunay_matches_robust_laplacian_on_many_jittered_spheres():
    """100 spheres jittered by up to a sixth of their radius (hundreds of loop flips, many
    around vertices of degree 2): every one takes the library's flips and gets
    robust-laplacian's weights and areas."""
    import robust_laplacian
    from scipy import sparse

    loops = 0
    for seed in range(100):
        rng = np.random.default_rng(seed)
        mesh = icosphere(int(rng.integers(2, 4)))
        jitter = rng.uniform(0.03, 0.15) * (0.5 if len(mesh.vertices) > 700 else 1.0)
        v = mesh.vertices + jitter * rng.standard_normal(mesh.vertices.shape)
        v /= np.linalg.norm(v, axis=1, keepdims=True)
        if rng.random() < 0.5:
            v *= 1.0 + 0.3 * rng.random((len(v), 1))
        rows, cols, weights, mass = sl._kernels.intrinsic_delaunay(v, mesh.faces)
        edge = rows != cols
        loops += int((~edge).sum())
        n = len(v)
        upper = sparse.coo_matrix((weights[edge], (rows[edge], cols[edge])), shape=(n, n))
        ours = (upper + upper.T).tocsr()
        ours = sparse.diags(np.asarray(ours.sum(axis=1)).ravel()) - ours
        expected, expected_mass = robust_laplacian.mesh_laplacian(v, mesh.faces)
        scale = abs(expected).max()
        assert abs(ours - expected).max() <= 1e-9 * scale, seed
        np.testing.assert_allclose(mass, expected_mass.diagonal(), rtol=1e-9, atol=0)
    assert loops > 100, loops


@pytest.mark.parametrize("builder", ["open_grid", "two_triangles_on_an_edge"])
def test_intrinsic_delaunay_leaves_other_meshes_to_robust_laplacian(builder):
    """Boundaries and non-manifold edges: the kernel declines; robust-laplacian answers."""
    from reference import open_grid

    from stochlap_torch._kernels import intrinsic_delaunay_weights

    if builder == "open_grid":
        mesh = open_grid()
        vertices, faces = mesh.vertices, mesh.faces
    else:  # three triangles on one edge
        vertices = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1.0]])
        faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    assert sl._kernels.intrinsic_delaunay(vertices, faces) is None
    edges, weights, mass = intrinsic_delaunay_weights(vertices, faces)
    expected, expected_mass = _rl_weights(vertices, faces)
    ours = {(int(i), int(j)): float(w) for (i, j), w in zip(edges, weights, strict=True)}
    assert set(ours) == set(expected)
    for key, value in expected.items():
        assert ours[key] == pytest.approx(max(value, 0.0), abs=1e-12)
    np.testing.assert_allclose(mass, expected_mass)


def test_features_are_reproducible_call_to_call():
    """The heat channel's Lanczos path starts from a fixed vector: two calls agree bit for bit
    (spot's heat level has more vertices than the dense path takes)."""
    mesh = sl.load_mesh(sl.bundled_mesh_path())
    structure = robust_structure(mesh.vertices, mesh.faces, RobustParams())
    heat_level = max(i for i, level in enumerate(structure.levels) if level.semigroup)
    assert structure.levels[heat_level].num_vertices > 400
    first = sl.multiscale_features(mesh.vertices, mesh.faces)
    assert torch.equal(first, sl.multiscale_features(mesh.vertices, mesh.faces))
