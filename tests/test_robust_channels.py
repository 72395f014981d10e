"""The robust variant's ``dn`` and ``twist`` channels against a dense float64 reference written
here, and ``dn`` against itself without the pyramid: a coarse level's triangulation must not
show in it."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import scipy.linalg
import torch
from reference import noisy_sphere
from scipy.stats import spearmanr

import stochlap_torch as sl
from stochlap_torch.robust.heat import heat_operator

#: No pyramid: every scale runs on the mesh itself.
ONE_LEVEL = 10**6


def _reference_dn(
    vertices: np.ndarray, faces: np.ndarray, params: sl.RobustParams
) -> tuple[np.ndarray, np.ndarray]:
    """``(dn (V, T), twist (V, W))``: with ``d_t = ((exp(-t G) - I) P) / sqrt(t)`` at unit
    area, ``dn = -d_t . n`` and ``twist = n . (d_t x d_2t)`` at ``t >= twist_from``; ``G =
    m^-1 L`` the heat operator's generator and ``n`` the unit area-weighted vertex normal
    smoothed by ``exp(-normal_time G)`` plus a quarter of it smoothed by ``exp(-normal_time G /
    16)`` (outward on this sphere)."""
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    unit = (vertices - vertices.mean(axis=0)) / np.sqrt(0.5 * np.linalg.norm(cross, axis=1).sum())
    operator = heat_operator(unit, faces, params.cap, params.clamp)
    generator = operator.laplacian.toarray() / operator.capped_mass[:, None]
    normals = np.zeros_like(unit)
    corners = unit[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    for corner in range(3):
        np.add.at(normals, faces[:, corner], cross)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    smoothed = scipy.linalg.expm(-params.normal_time * generator) @ normals
    lightly = scipy.linalg.expm(-params.normal_time / 16 * generator) @ normals
    normals = smoothed + 0.25 * lightly
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    shifts = [(scipy.linalg.expm(-t * generator) @ unit - unit) / np.sqrt(t) for t in params.times]
    dn = [-(shift * normals).sum(axis=1) for shift in shifts]
    pairs = [
        (a, b)
        for t, (a, b) in zip(params.times, itertools.pairwise(shifts), strict=False)
        if t >= params.twist_from
    ]
    twist = [(np.cross(a, b) * normals).sum(axis=1) for a, b in pairs]
    return np.stack(dn, axis=1), np.stack(twist, axis=1)


def test_dn_and_twist_match_the_dense_reference():
    mesh = noisy_sphere()
    vertices, faces = mesh.vertices, mesh.faces
    params = sl.RobustParams(min_vertices=ONE_LEVEL)
    expected_dn, expected_twist = _reference_dn(vertices, faces, params)
    features = sl.multiscale_features(
        torch.from_numpy(vertices), torch.from_numpy(faces), params=params
    )
    names = sl.feature_channel_names(params=params)
    dn = features[:, : params.num_scales].numpy()
    twist = features[:, [names.index(f"twist{k}") for k in (3, 4, 5)]]
    np.testing.assert_allclose(dn, expected_dn, rtol=0, atol=1e-5 * np.abs(expected_dn).max())
    scale = np.abs(expected_twist).max()
    np.testing.assert_allclose(twist.numpy(), expected_twist, rtol=0, atol=1e-5 * scale)


def test_coarse_scales_follow_the_surface_not_the_pyramid():
    """``dn`` of the scales that run on coarse levels (spot: 725 and 182 vertices) equals, to
    a fraction of its spread, ``dn`` computed on the mesh itself. Taking the normal component
    on a coarse level and interpolating it put errors of 2 to 4 deviations there (rank
    correlation down to 0.77)."""
    spot = sl.load_mesh(sl.bundled_mesh_path())
    params = sl.RobustParams(min_vertices=100)
    structure = sl.robust_structure(spot.vertices, spot.faces, params)
    assert len(structure.levels) >= 3 and max(structure.assignment) >= 2
    coarse = sl.multiscale_features(spot.vertices, spot.faces, params=params)
    fine = sl.multiscale_features(spot.vertices, spot.faces, min_vertices=ONE_LEVEL)
    for k in range(params.num_scales):
        if structure.assignment[k] == 0:
            continue
        a, b = coarse[:, k].numpy(), fine[:, k].numpy()
        assert np.abs(a - b).max() < 0.5 * b.std(), k
        assert spearmanr(a, b)[0] > 0.99, k


def _with_coincident_pair(vertices: np.ndarray, faces: np.ndarray):
    """The mesh with its first edge ``(a, b)`` split at ``a``: a new vertex ``d`` on ``a`` and
    the edge ``(a, d)`` of zero length between two faces of zero area (marching cubes leaves
    such pairs)."""
    a, b, c = faces[0]
    other = next(i for i, face in enumerate(faces) if {a, b} <= set(face) and i != 0)
    rolled = np.roll(faces[other], -list(faces[other]).index(b))  # (b, a, e)
    e = rolled[2]
    d = vertices.shape[0]
    kept = np.delete(faces, [0, other], axis=0)
    split = np.array([[a, d, c], [d, b, c], [b, d, e], [d, a, e]])
    return np.vstack([vertices, vertices[a]]), np.vstack([kept, split]), a, d


def test_a_zero_length_edge_is_taken_by_the_robust_variant(tmp_path):
    """Coincident vertices joined by an edge (two ``mc`` meshes of the discretization
    benchmark) are taken without merging: the intrinsic Laplacian's mollification gives the
    pair finite weights. The features and saliency equal the unsplit mesh's to a few
    hundredths; the paper's method, whose ``1/|Pi-Pj|^2`` weight is infinite there, still
    refuses."""
    mesh = noisy_sphere()
    vertices, faces = mesh.vertices, mesh.faces
    split_vertices, split_faces, a, d = _with_coincident_pair(vertices, faces)
    points, triangles = torch.from_numpy(split_vertices), torch.from_numpy(split_faces)
    features = sl.multiscale_features(points, triangles)
    saliency = sl.saliency(points, triangles)
    assert torch.isfinite(features).all() and torch.isfinite(saliency).all()
    expected = sl.multiscale_features(torch.from_numpy(vertices), torch.from_numpy(faces))
    # Channels are dimensionless (logarithms, ratios): the pair's neighbours move by a few
    # hundredths, the other vertices by far less.
    error = (features[:-1] - expected).abs()
    assert error.max() < 0.05
    # The twist is noise of 1e-4 on a sphere: its spread is no yardstick.
    shaped = torch.tensor([not name.startswith("twist") for name in sl.feature_channel_names()])
    assert (error / expected.std(dim=0))[:, shaped].mean() < 0.01
    assert (features[d] - features[a]).abs().max() < 0.05
    assert len(sl.interest_points(saliency, points, triangles)) > 0
    path = tmp_path / "split.obj"
    path.write_text(
        "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in split_vertices.tolist())
        + "".join(f"f {i + 1} {j + 1} {k + 1}\n" for i, j, k in split_faces.tolist())
    )
    assert sl.load_mesh(path).num_vertices == split_vertices.shape[0]
    with pytest.raises(sl.MeshError, match="zero length"):
        sl.saliency(points, triangles, variant="paper")
