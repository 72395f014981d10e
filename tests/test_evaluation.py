"""Evaluation (stochlap_torch.evaluation): geodesic distances on meshes with known distances
(flat grid, sphere), the handling of awkward meshes, and the interest point measures of
Dutagaci et al. 2012 on constructed cases with known values."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
import torch
from reference import icosphere, two_components

from stochlap_torch import load_mesh
from stochlap_torch._common.errors import FileFormatError, MissingDependencyError, ParameterError
from stochlap_torch.evaluation import (
    GeodesicFallbackWarning,
    GroundTruth,
    build_ground_truth,
    check_evaluation_parameters,
    choose_geodesic_method,
    detection_errors,
    error_curves,
    evaluate_interest_points,
    geodesic_distances,
    ground_truth_from_distances,
    match_points,
    mean_error_curves,
    mesh_diameter,
    nonmanifold_edges,
    read_marks,
)
from stochlap_torch.evaluation import geodesics as geodesics_module

HAS_POTPOURRI = importlib.util.find_spec("potpourri3d") is not None
needs_potpourri = pytest.mark.skipif(
    not HAS_POTPOURRI,
    reason='potpourri3d is not installed (pip install "stochlap_torch[evaluation]")',
)


def flat_grid(n: int = 21):
    """Unit square, ``n x n`` vertices, every cell split along its (0,0)-(1,1) diagonal."""
    xs, ys = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            faces += [(a, b, c), (a, c, d)]
    return torch.tensor(vertices), torch.tensor(faces)


def sphere_with_fin():
    """icosphere(2) plus a triangle glued to one of its edges: one non-manifold edge."""
    mesh = icosphere(2)
    a, b = (int(i) for i in mesh.faces[0, :2])
    middle = 0.5 * (mesh.vertices[a] + mesh.vertices[b])
    tip = middle * 1.5
    vertices = np.vstack([mesh.vertices, tip])
    faces = np.vstack([mesh.faces, [[a, b, len(mesh.vertices)]]])
    return torch.tensor(vertices), torch.tensor(faces), (min(a, b), max(a, b))


# --- Geodesic distances ---------------------------------------------------------------------


def test_dijkstra_on_a_flat_grid_is_euclidean_along_edges_and_bounded_elsewhere():
    vertices, faces = flat_grid(21)
    centre = 10 * 21 + 10
    result = geodesic_distances(vertices, faces, [centre, 0], method="dijkstra")
    assert result.method == "dijkstra" and result.distances.shape == (2, 21 * 21)
    distance = result.distances[0].numpy()
    euclid = np.linalg.norm(vertices.numpy() - vertices[centre].numpy(), axis=1)
    offset = vertices.numpy()[:, :2] - vertices[centre].numpy()[:2]
    along = (np.abs(offset).min(axis=1) < 1e-12) | (np.abs(offset[:, 0] - offset[:, 1]) < 1e-12)
    np.testing.assert_allclose(distance[along], euclid[along], atol=1e-12)
    assert bool(np.all(distance >= euclid - 1e-12))
    assert bool(np.all(distance <= math.sqrt(2) * euclid + 1e-12))
    assert result.distances[1, -1].item() == pytest.approx(math.sqrt(2))  # along the diagonal


@needs_potpourri
def test_heat_method_on_a_flat_grid_is_euclidean_within_an_edge_length():
    vertices, faces = flat_grid(31)
    centre = 15 * 31 + 15
    result = geodesic_distances(vertices, faces, [centre], method="heat")
    assert result.method == "heat"
    euclid = (vertices - vertices[centre]).norm(dim=1)
    error = (result.distances[0] - euclid).abs()
    assert error.max().item() < 1.0 / 30  # one edge length
    assert error.mean().item() < 0.01
    assert result.distances[0, centre].item() == 0.0


def test_unreachable_and_unreferenced_vertices_are_infinitely_far():
    mesh = two_components()
    vertices = np.vstack([mesh.vertices[:5], [[9.0, 9.0, 9.0]], mesh.vertices[5:]])
    faces = np.where(mesh.faces >= 5, mesh.faces + 1, mesh.faces)  # vertex 5: unreferenced
    first = 43  # the second component starts after 42 + 1 vertices
    methods = ["dijkstra"] + (["heat"] if HAS_POTPOURRI else [])
    for method in methods:
        result = geodesic_distances(torch.tensor(vertices), torch.tensor(faces), [0, 5], method)
        row, lonely = result.distances[0], result.distances[1]
        assert bool(torch.isinf(row[first:]).all()) and bool(torch.isfinite(row[:5]).all())
        assert math.isinf(row[5].item()) and lonely[5].item() == 0.0
        assert int(torch.isfinite(lonely).sum()) == 1
    if HAS_POTPOURRI:
        heat = geodesic_distances(torch.tensor(vertices), torch.tensor(faces), [0], "heat")
        graph = geodesic_distances(torch.tensor(vertices), torch.tensor(faces), [0], "dijkstra")
        reach = torch.isfinite(graph.distances[0])
        # Edge paths over-estimate; the heat method may under-estimate a little.
        ratio = heat.distances[0][reach][1:] / graph.distances[0][reach][1:]
        assert 0.7 < ratio.min().item() and ratio.max().item() < 1.05


def test_nonmanifold_edges_make_auto_fall_back_to_dijkstra():
    vertices, faces, fin_edge = sphere_with_fin()
    assert nonmanifold_edges(faces).tolist() == [list(fin_edge)]
    assert nonmanifold_edges(icosphere(2).faces).shape == (0, 2)
    if HAS_POTPOURRI:  # without it, "auto" falls back (and warns) anyway
        with pytest.warns(GeodesicFallbackWarning, match=r"1 non-manifold edges.*Dijkstra"):
            result = geodesic_distances(vertices, faces, [fin_edge[0]], method="auto")
    else:
        result = geodesic_distances(vertices, faces, [fin_edge[0]], method="dijkstra")
    assert result.method == "dijkstra"
    tip = vertices.shape[0] - 1
    assert result.distances[0, tip].item() == pytest.approx(
        (vertices[tip] - vertices[fin_edge[0]]).norm().item()
    )


@needs_potpourri
def test_auto_uses_the_heat_method_on_a_manifold_mesh():
    vertices, faces = icosphere(2).tensors()
    assert geodesic_distances(vertices, faces, [0], "auto").method == "heat"


def test_heat_method_without_potpourri3d_raises_and_auto_falls_back(monkeypatch):
    monkeypatch.setattr(geodesics_module, "_potpourri3d", lambda: None)
    vertices, faces = icosphere(1).tensors()
    with pytest.raises(MissingDependencyError, match=r'pip install "stochlap_torch\[evaluation\]"'):
        geodesic_distances(vertices, faces, [0], method="heat")
    with pytest.warns(GeodesicFallbackWarning, match=r"potpourri3d is not installed.*Dijkstra"):
        assert geodesic_distances(vertices, faces, [0], method="auto").method == "dijkstra"
    with pytest.warns(GeodesicFallbackWarning):
        assert choose_geodesic_method(faces) == "dijkstra"


def test_no_warning_when_the_method_is_chosen(recwarn):
    vertices, faces, _ = sphere_with_fin()
    geodesic_distances(vertices, faces, [0], method="dijkstra")
    mesh_diameter(*icosphere(1).tensors(), method="dijkstra")
    assert not [w for w in recwarn if issubclass(w.category, GeodesicFallbackWarning)]


@needs_potpourri
def test_choose_geodesic_method():
    assert choose_geodesic_method(icosphere(1).faces) == "heat"
    assert choose_geodesic_method(icosphere(1).faces, "dijkstra") == "dijkstra"
    with pytest.raises(ParameterError, match="method"):
        choose_geodesic_method(icosphere(1).faces, "exact")


def test_geodesic_distances_reject_bad_sources_and_methods():
    vertices, faces = icosphere(1).tensors()
    with pytest.raises(ValueError, match="source"):
        geodesic_distances(vertices, faces, [42])
    with pytest.raises(ValueError, match="method"):
        geodesic_distances(vertices, faces, [0], method="exact")


def test_mesh_diameter_of_a_square_and_a_sphere():
    vertices, faces = flat_grid(11)
    assert mesh_diameter(vertices, faces, "dijkstra") == pytest.approx(math.sqrt(2))
    sphere, sphere_faces = icosphere(3).tensors()
    diameter = mesh_diameter(sphere, sphere_faces)
    assert math.pi * 0.97 < diameter < math.pi * 1.1


# --- Measures -------------------------------------------------------------------------------


def test_perfect_detection_gives_zero_errors():
    distances = np.array([[0.0, 2.0, 3.0], [2.0, 0.0, 1.5], [3.0, 1.5, 0.0]])
    for matching in ("greedy", "optimal"):
        errors = detection_errors(distances, [4, 2, 1], radius=0.0, matching=matching)
        assert (errors.fne, errors.fpe, errors.wme, errors.num_correct) == (0.0, 0.0, 0.0, 3)


def test_far_detections_give_full_errors():
    distances = np.full((3, 5), 10.0)
    errors = detection_errors(distances, [4, 2, 1], radius=1.0)
    assert (errors.fne, errors.fpe, errors.wme, errors.num_correct) == (1.0, 1.0, 1.0, 0)
    nothing = detection_errors(np.zeros((3, 0)), [4, 2, 1], radius=1.0)
    assert (nothing.fne, nothing.fpe, nothing.wme) == (1.0, 0.0, 1.0)


def test_partial_matching_known_values():
    # g0 (5 votes) and g1 (3 votes) have detections within 0.5; g2 (2 votes) has none.
    # d0 is closest to g0 and also within reach of g1, which must take d1 instead.
    distances = np.array(
        [
            [0.1, 0.9, 2.0, 3.0],
            [0.3, 0.4, 2.0, 3.0],
            [2.0, 2.0, 0.8, 0.9],
        ]
    )
    errors = detection_errors(distances, [5, 3, 2], radius=0.5)
    assert errors.num_correct == 2
    assert errors.fne == pytest.approx(1 / 3)
    assert errors.fpe == pytest.approx(1 / 2)
    assert errors.wme == pytest.approx(2 / 10)
    assert errors.matched_truth.tolist() == [True, True, False]
    assert errors.matched_detections.tolist() == [True, True, False, False]
    curves = error_curves(distances, [5, 3, 2], radii=[0.0, 0.2, 0.5, 1.0])
    assert curves.num_correct.tolist() == [0, 1, 2, 3]
    np.testing.assert_allclose(curves.fne.numpy(), [1.0, 2 / 3, 1 / 3, 0.0])
    np.testing.assert_allclose(curves.fpe.numpy(), [1.0, 3 / 4, 1 / 2, 1 / 4])
    np.testing.assert_allclose(curves.wme.numpy(), [1.0, 0.5, 0.2, 0.0])


def test_greedy_and_optimal_matchings_differ_where_nearest_first_is_suboptimal():
    # g0's nearest detection d0 is g1's only one: greedy matches 1 point, optimal 2.
    distances = np.array([[0.1, 0.2], [0.15, np.inf]])
    assert match_points(distances, 0.3, matching="greedy").tolist() == [0, -1]
    assert match_points(distances, 0.3, matching="optimal").tolist() == [1, 0]
    greedy = detection_errors(distances, [1, 1], 0.3, "greedy")
    optimal = detection_errors(distances, [1, 1], 0.3, "optimal")
    assert (greedy.fne, optimal.fne) == (0.5, 0.0)
    # Greedy takes pairs by distance, not by ground-truth order: g1 is closer to d0.
    assert match_points(np.array([[0.2], [0.1]]), 0.3).tolist() == [-1, 0]
    # With one detection for two candidates, "optimal" gives it to the better-voted point.
    single = np.array([[0.2], [0.1]])
    assert match_points(single, 0.3, votes=[5, 1], matching="optimal").tolist() == [0, -1]
    assert match_points(single, 0.3, votes=[1, 5], matching="optimal").tolist() == [-1, 0]


def test_measures_reject_bad_input():
    with pytest.raises(ValueError, match="no ground-truth"):
        detection_errors(np.zeros((0, 2)), [], 1.0)
    with pytest.raises(ValueError, match="votes"):
        detection_errors(np.zeros((2, 2)), [1, 0], 1.0)
    with pytest.raises(ValueError, match="matching"):
        match_points(np.zeros((2, 2)), 1.0, matching="hungarian")
    # match_points checks the votes it is given, for either matching
    for matching in ("greedy", "optimal"):
        with pytest.raises(ValueError, match=r"votes must have shape \(2,\)"):
            match_points(np.zeros((2, 2)), 1.0, votes=[1, 1, 1], matching=matching)
        with pytest.raises(ValueError, match="votes must be finite"):
            match_points(np.zeros((2, 2)), 1.0, votes=[1, np.nan], matching=matching)
    with pytest.raises(ValueError, match="non-negative"):
        detection_errors(np.array([[np.nan]]), [1], 1.0)


# --- Ground truth ---------------------------------------------------------------------------


def line_distances(positions):
    positions = np.asarray(positions, dtype=np.float64)
    return np.abs(positions[:, None] - positions[None, :])


def test_ground_truth_from_marks_on_a_line():
    # Three subjects mark points on a line (vertex id = 10 x position + 1). Cluster A near 0
    # is marked by all three (subjects 0 and 1 twice, counted once), cluster B near 5 by
    # subjects 0 and 1, C at 9 by subject 2 alone.
    marks = [(-0.1, 2), (0.0, 0), (0.1, 1), (0.2, 0), (0.35, 1), (5.0, 0), (5.3, 1), (9.0, 2)]
    positions = [p for p, _ in marks]
    subjects = [s for _, s in marks]
    vertices = [round(10 * p) + 1 for p in positions]
    distances = line_distances(positions)
    truth = ground_truth_from_distances(vertices, subjects, distances, sigma=0.5, min_subjects=2)
    assert truth.num_subjects == 3 and truth.min_subjects == 2 and truth.sigma == 0.5
    # A's representative is its medoid, the median mark 0.1 (vertex 2), with 3 votes; B's
    # two marks tie and the first (5.0, vertex 51) is kept; 5.3 lies within 2 sigma of it.
    assert truth.vertices.tolist() == [2, 51]
    assert truth.votes.tolist() == [3, 2]
    unanimous = ground_truth_from_distances(vertices, subjects, distances, 0.5, 3)
    assert unanimous.vertices.tolist() == [2] and unanimous.votes.tolist() == [3]
    everything = ground_truth_from_distances(vertices, subjects, distances, 0.5, 1)
    assert everything.vertices.tolist() == [2, 51, 91]
    assert everything.votes.tolist() == [3, 2, 1]
    with pytest.raises(ValueError, match="sigma"):
        ground_truth_from_distances(vertices, subjects, distances, 0.0, 1)


def test_build_ground_truth_and_evaluate_on_a_sphere():
    mesh = icosphere(3)
    vertices, faces = mesh.tensors()
    points = mesh.vertices
    north, south = int(np.argmax(points[:, 2])), int(np.argmin(points[:, 2]))
    ring = sorted({int(v) for face in mesh.faces if north in face for v in face} - {north})
    first = ring[0]
    opposite = max(ring, key=lambda v: np.linalg.norm(points[v] - points[first]))
    # Three subjects agree on the north pole (two of them one ring off); one also marks the
    # south pole, another a point on the equator: neither gets a second vote.
    marks = [[north, south], [first], [opposite, int(np.argmax(points[:, 0]))]]
    sigma = 0.06  # of the diameter pi: 0.19, more than one edge (about 0.16)
    truth = build_ground_truth(vertices, faces, marks, sigma, 2, diameter=math.pi)
    assert truth.num_subjects == 3 and truth.sigma == pytest.approx(sigma * math.pi)
    assert truth.vertices.tolist() == [north] and truth.votes.tolist() == [3]
    radii = [0.0, sigma]
    perfect = evaluate_interest_points(vertices, faces, truth, [north], radii, diameter=math.pi)
    assert perfect.fne.tolist() == [0.0, 0.0] and perfect.wme.tolist() == [0.0, 0.0]
    assert perfect.fpe.tolist() == [0.0, 0.0] and perfect.radii.tolist() == radii
    shifted = evaluate_interest_points(
        vertices, faces, truth, [first, south], radii, diameter=math.pi
    )
    assert shifted.fne.tolist() == [1.0, 0.0] and shifted.wme.tolist() == [1.0, 0.0]
    assert shifted.fpe.tolist() == [1.0, 0.5]


def test_ground_truth_container_counts_points():
    truth = GroundTruth(torch.tensor([3, 7]), torch.tensor([2, 2]), 4, 0.1, 2)
    assert truth.num_points == 2


@pytest.mark.filterwarnings("ignore::stochlap_torch.evaluation.GeodesicFallbackWarning")
def test_real_mesh_with_nonmanifold_edges_uses_dijkstra(meshes_dir):
    path = meshes_dir / "squirrel.off"
    if not path.is_file():
        pytest.skip(f"{path} not found")
    mesh = load_mesh(path)
    assert nonmanifold_edges(mesh.faces).shape[0] == 2  # as SOURCES.md records
    result = geodesic_distances(mesh.vertices, mesh.faces, [0], method="auto")
    assert result.method == "dijkstra"
    assert result.distances[0, 0].item() == 0.0
    assert bool((result.distances[0][torch.isfinite(result.distances[0])] >= 0).all())


# --- Files and the benchmark ----------------------------------------------------------------


def test_read_marks_rejects_a_binary_file(tmp_path):
    path = tmp_path / "truth.bin"
    path.write_bytes(b"12 \xff\xfe 7\n")
    with pytest.raises(FileFormatError, match="not a text file"):
        read_marks(path, 100)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"methods": ["stochastic", "nope"]}, "unknown method nope"),
        ({"methods": []}, "none given"),
        ({"sigma": 0.0}, "sigma"),
        ({"min_subjects": 0}, "min_subjects"),
        ({"radii": [0.0, -0.1]}, "radii"),
        ({"radii": [float("nan")]}, "radii"),
        ({"num_scales": 1}, "num_scales"),
        ({"threshold": 1.5}, "threshold"),
        ({"mode": "best"}, "mode"),
        ({"radius": 0.0}, "radius"),
        ({"top_k": 0}, "top_k"),
        ({"geodesics": "exact"}, "geodesics"),
    ],
)
def test_check_evaluation_parameters(kwargs, message):
    arguments = {"methods": ["stochastic"], **kwargs}
    with pytest.raises(ParameterError, match=message):
        check_evaluation_parameters(**arguments)


def test_check_evaluation_parameters_keeps_order_once():
    assert check_evaluation_parameters(["lee", "hks", "lee"]) == ("lee", "hks")


def test_evaluate_detectors_on_a_sphere(monkeypatch):
    from stochlap_torch.evaluation import benchmark

    mesh = icosphere(3)
    vertices, faces = mesh.tensors()
    north = int(np.argmax(mesh.vertices[:, 2]))
    # A detector whose only point is the north pole, which every subject marked.
    monkeypatch.setattr(benchmark, "detector_saliency", lambda method, v, f, k, t: v[:, 2].clone())
    seen = []
    result = benchmark.evaluate_detectors(
        vertices,
        faces,
        [[north], [north]],
        ["stochastic", "lee"],
        radii=[0.0, 0.05],
        geodesics="dijkstra",
        top_k=1,
        progress=lambda method, detector: seen.append(method),
    )
    assert seen == ["stochastic", "lee"]
    assert (result.num_truth, result.num_subjects, result.geodesics) == (1, 2, "dijkstra")
    assert math.pi * 0.97 < result.diameter < math.pi * 1.1
    stochastic = result.results["stochastic"]
    assert stochastic.num_points == 1 and stochastic.curves.fne.tolist() == [0.0, 0.0]
    summary = result.as_dict()
    assert summary["methods"]["lee"]["wme"] == [0.0, 0.0] and summary["num_truth"] == 1
    mean = mean_error_curves([result, result])
    assert mean["stochastic"] == {"fne": [0.0, 0.0], "fpe": [0.0, 0.0], "wme": [0.0, 0.0]}
    with pytest.raises(ParameterError, match="no ground-truth point"):
        benchmark.evaluate_detectors(
            vertices, faces, [[north]], ["lee"], min_subjects=2, geodesics="dijkstra"
        )
