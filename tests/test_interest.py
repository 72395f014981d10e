"""Interest points (paper Sec. 4.5): paper mode and greedy geodesic non-maximum suppression.

Both modes are compared with ``reference.py`` on random and real saliency fields; the NMS
output is checked for separation, order and ``top_k``; and on synthetic fields with known
maxima the detected points must be exactly those maxima.
"""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest
import reference as ref
import torch
from reference import SMALL_MESH_BUILDERS, SmallMesh, to_numpy

import stochlap_torch as sl
from stochlap_torch.interest import InterestPointWarning


def random_field(mesh: SmallMesh, seed: int) -> torch.Tensor:
    """A random float64 saliency field (distinct values with probability one)."""
    rng = np.random.default_rng(seed)
    return torch.tensor(rng.normal(size=mesh.vertices.shape[0]))


def library_saliency(mesh: SmallMesh) -> torch.Tensor:
    """Saliency of Algorithm 2 from the library (K = 6)."""
    vertices, faces = mesh.tensors()
    return sl.saliency(vertices, faces, num_scales=6, variant="paper")


def detect(saliency: torch.Tensor, mesh: SmallMesh, **kwargs) -> list[int]:
    """Call ``interest_points`` and check the output type before returning a list; fewer
    points than ``top_k`` come with exactly one :class:`InterestPointWarning`, else none."""
    vertices, faces = mesh.tensors()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        points = sl.interest_points(saliency, vertices, faces, **kwargs)
    short = kwargs.get("top_k") is not None and points.numel() < kwargs["top_k"]
    assert [w.category for w in caught] == ([InterestPointWarning] if short else [])
    assert points.dtype == torch.int64
    assert points.ndim == 1
    assert points.device == saliency.device
    return points.tolist()


def cone_field(mesh: SmallMesh, seeds: list[int], bonus: list[float]) -> np.ndarray:
    """``max_s (bonus_s - geodesic(v, s))``: its 1-ring maxima are exactly the seeds.

    Every other vertex has a neighbour on its shortest path to the dominating seed with a
    strictly larger value; a seed beats its neighbours as long as the bonuses differ by less
    than the seed-to-seed distances.
    """
    pairs = zip(seeds, bonus, strict=True)
    cones = [b - ref.dijkstra(mesh.vertices, mesh.faces, s) for s, b in pairs]
    return np.max(cones, axis=0)


def nearest_vertex(mesh: SmallMesh, direction: list[float]) -> int:
    """The vertex of a unit sphere closest to ``direction``."""
    target = np.asarray(direction, dtype=np.float64)
    return int(np.argmax(mesh.vertices @ (target / np.linalg.norm(target))))


@pytest.mark.parametrize("name", sorted(SMALL_MESH_BUILDERS))
@pytest.mark.parametrize("t_global", [0.0, 0.4, 0.8])
@pytest.mark.parametrize("include_boundary", [False, True])
def test_paper_mode_on_random_field(name: str, t_global: float, include_boundary: bool) -> None:
    """Paper mode equals the reference: 1-ring maxima over the global threshold, sorted, rim
    vertices only when asked."""
    mesh = SMALL_MESH_BUILDERS[name]()
    field = random_field(mesh, seed=len(name))
    got = detect(field, mesh, mode="paper", t_global=t_global, include_boundary=include_boundary)
    expected = ref.interest_points_paper(field.numpy(), mesh.faces, t_global, include_boundary)
    assert got == expected


@pytest.mark.parametrize("name", ["noisy_sphere", "open_grid", "two_components"])
def test_paper_mode_on_library_saliency(name: str) -> None:
    """Paper mode on the saliency of Algorithm 2 equals the reference."""
    mesh = SMALL_MESH_BUILDERS[name]()
    field = library_saliency(mesh)
    got = detect(field, mesh, mode="paper")
    assert got == ref.interest_points_paper(to_numpy(field), mesh.faces)
    assert got, "expected at least the global maximum"


def test_paper_mode_with_ties_is_sorted() -> None:
    """On the symmetric icosphere (tied saliency) the set matches and the order is descending."""
    mesh = SMALL_MESH_BUILDERS["icosphere2"]()
    field = library_saliency(mesh)
    got = detect(field, mesh, mode="paper")
    assert set(got) == set(ref.interest_points_paper(to_numpy(field), mesh.faces))
    values = to_numpy(field)[got]
    assert bool(np.all(np.diff(values) <= 0))


@pytest.mark.parametrize(
    "name", ["noisy_sphere", "open_grid", "two_components", "icosphere2", "unreferenced_vertex"]
)
@pytest.mark.parametrize("radius", [0.05, 0.2, 0.5])
@pytest.mark.parametrize("top_k", [None, 3])
def test_nms_on_random_field_matches_reference(name: str, radius: float, top_k: int | None):
    """NMS mode equals the greedy reference with a plain Dijkstra."""
    mesh = SMALL_MESH_BUILDERS[name]()
    field = random_field(mesh, seed=11)
    got = detect(field, mesh, mode="nms", radius=radius, top_k=top_k)
    expected = ref.interest_points_nms(field.numpy(), mesh.vertices, mesh.faces, radius, top_k)
    assert got == expected


def rim_peak(mesh: SmallMesh) -> tuple[torch.Tensor, int]:
    """A field highest at one rim vertex of ``mesh`` and falling off with distance from it."""
    rim = sorted(ref.rim_vertices(mesh.vertices.shape[0], mesh.faces))
    peak = rim[len(rim) // 2]
    distance = np.linalg.norm(mesh.vertices - mesh.vertices[peak], axis=1)
    return torch.tensor(-distance), peak


@pytest.mark.parametrize("mode", ["nms", "paper"])
def test_the_rim_of_a_hole_is_not_an_interest_point_unless_asked(mode: str) -> None:
    """On the open grid a field peaking on the rim gives no point there (nor on the ring
    inside it, which the rim outranks) by default, and exactly that point when asked."""
    grid = SMALL_MESH_BUILDERS["open_grid"]()
    field, peak = rim_peak(grid)
    rim = ref.rim_vertices(grid.vertices.shape[0], grid.faces)
    default = detect(field, grid, mode=mode, top_k=None)
    assert not set(default) & rim
    assert peak not in default and all(
        peak not in ref.neighbours(len(field), grid.faces)[p] for p in default
    )
    asked = detect(field, grid, mode=mode, include_boundary=True)
    assert asked[0] == peak
    if mode == "paper":
        assert asked == ref.interest_points_paper(field.numpy(), grid.faces, 0.4, True)


def test_include_boundary_is_a_flag() -> None:
    mesh = SMALL_MESH_BUILDERS["open_grid"]()
    with pytest.raises(sl.ParameterError, match="include_boundary"):
        detect(random_field(mesh, 0), mesh, include_boundary="no")


def test_too_few_points_warn_with_a_radius_that_gives_top_k(bumpy: SmallMesh) -> None:
    """When suppression leaves fewer than ``top_k`` points the warning names a radius, and
    that radius does give ``top_k`` points."""
    field = random_field(bumpy, seed=3)
    top_k = 8
    with pytest.warns(InterestPointWarning, match="leaves no room") as caught:
        few = detect_quietly(field, bumpy, radius=0.5, top_k=top_k)
    assert len(few) < top_k
    advised = float(re.search(r"radius=([0-9.e-]+) gives", str(caught[0].message)).group(1))
    assert len(detect(field, bumpy, radius=advised, top_k=top_k)) == top_k
    assert len(detect(field, bumpy, radius=2 * advised, top_k=top_k)) < top_k


def test_too_few_maxima_warn_about_t_global(bumpy: SmallMesh) -> None:
    field = random_field(bumpy, seed=3)
    maxima = len(detect(field, bumpy, mode="paper"))
    with pytest.warns(InterestPointWarning, match=f"only {maxima} local maxima"):
        detect_quietly(field, bumpy, mode="paper", top_k=maxima + 1)


def detect_quietly(saliency: torch.Tensor, mesh: SmallMesh, **kwargs) -> list[int]:
    """``interest_points`` without :func:`detect`'s own check of the warnings."""
    return sl.interest_points(saliency, *mesh.tensors(), **kwargs).tolist()


def geodesic_matrix(mesh: SmallMesh, points: list[int]) -> np.ndarray:
    """Pairwise graph-geodesic distances between ``points``."""
    rows = [ref.dijkstra(mesh.vertices, mesh.faces, p)[points] for p in points]
    return np.array(rows).reshape(len(points), len(points))


@pytest.mark.parametrize("radius", [0.05, 0.15, 0.3])
def test_nms_points_are_separated_and_sorted(bumpy: SmallMesh, radius: float) -> None:
    """Accepted points are more than ``radius * bbox diagonal`` apart and most salient first."""
    field = library_saliency(bumpy)
    got = detect(field, bumpy, mode="nms", radius=radius)
    assert got
    limit = radius * ref.bbox_diagonal(bumpy.vertices, bumpy.faces)
    distances = geodesic_matrix(bumpy, got)
    off_diagonal = distances[~np.eye(len(got), dtype=bool)]
    assert bool(np.all(off_diagonal > limit))
    values = to_numpy(field)[got]
    assert bool(np.all(np.diff(values) <= 0))
    assert int(np.argmax(to_numpy(field))) == got[0]


def test_nms_top_k_is_a_prefix(bumpy: SmallMesh) -> None:
    """``top_k`` caps the count and keeps the first (most salient) accepted points."""
    field = random_field(bumpy, seed=3)
    full = detect(field, bumpy, mode="nms", radius=0.05)
    assert len(full) > 4
    for top_k in (1, 2, 4, len(full) + 5):
        capped = detect(field, bumpy, mode="nms", radius=0.05, top_k=top_k)
        assert capped == full[:top_k]


def test_nms_is_a_subset_of_paper_mode(bumpy: SmallMesh) -> None:
    """Every NMS point is a paper-mode point (same candidates, then suppression)."""
    field = library_saliency(bumpy)
    nms = detect(field, bumpy, mode="nms", radius=0.1)
    paper = detect(field, bumpy, mode="paper")
    assert set(nms) <= set(paper)
    assert len(nms) <= len(paper)


def test_default_mode_is_nms(bumpy: SmallMesh) -> None:
    """Without ``mode`` the NMS mode runs."""
    field = random_field(bumpy, seed=4)
    vertices, faces = bumpy.tensors()
    default = sl.interest_points(field, vertices, faces, radius=0.2).tolist()
    assert default == detect(field, bumpy, mode="nms", radius=0.2)
    assert default != detect(field, bumpy, mode="paper")


@pytest.mark.parametrize("mode", ["nms", "paper"])
def test_known_maxima_are_found_exactly(mode: str) -> None:
    """On ``max_s (b_s - geodesic(v, s))`` over 3 seeds the points are exactly the seeds.

    The seeds sit near three orthogonal axes of icosphere(3), about a quarter of a great circle
    apart, so a suppression radius of 0.1 bounding-box diagonals (0.35) keeps all three. The
    bonuses give them distinct saliency, hence a known order.
    """
    mesh = ref.icosphere(3)
    seeds = [nearest_vertex(mesh, d) for d in ([1, 0, 0], [0, 1, 0], [0, 0, -1])]
    field = torch.tensor(cone_field(mesh, seeds, bonus=[0.02, 0.03, 0.01]))
    got = detect(field, mesh, mode=mode, radius=0.1 if mode == "nms" else None)
    assert got == [seeds[1], seeds[0], seeds[2]]


def test_nms_suppresses_the_weaker_of_two_close_maxima() -> None:
    """Two seeds closer than the radius: only the more salient survives; a far one stays.

    Seeds A and B are about 35 degrees apart (geodesic ~0.6), C is on the opposite axis. With
    ``radius * diagonal`` = 0.9 (between 0.6 and the A-C / B-C distances) B is suppressed.
    """
    mesh = ref.icosphere(3)
    a = nearest_vertex(mesh, [1, 0, 0])
    b = nearest_vertex(mesh, [1, 0.7, 0])
    c = nearest_vertex(mesh, [-1, 0, 0])
    distances = geodesic_matrix(mesh, [a, b, c])
    diagonal = ref.bbox_diagonal(mesh.vertices, mesh.faces)
    reach = 0.9
    assert distances[0, 1] < reach < min(distances[0, 2], distances[1, 2])
    field = torch.tensor(cone_field(mesh, [a, b, c], bonus=[0.3, 0.2, 0.1]))
    assert detect(field, mesh, mode="paper") == [a, b, c]
    assert detect(field, mesh, mode="nms", radius=reach / diagonal) == [a, c]


def test_interest_point_head_matches_function(bumpy: SmallMesh) -> None:
    """``InterestPointHead`` gives the function's result in both modes."""
    field = library_saliency(bumpy)
    vertices, faces = bumpy.tensors()
    for mode, radius in (("nms", 0.15), ("paper", None)):
        head = sl.InterestPointHead(mode=mode, radius=radius, t_global=0.3)
        expected = sl.interest_points(
            field, vertices, faces, mode=mode, radius=radius, t_global=0.3
        )
        assert head(field, vertices, faces).tolist() == expected.tolist()


@pytest.mark.parametrize("include_boundary", [False, True])
def test_interest_point_head_passes_include_boundary(include_boundary: bool) -> None:
    grid = SMALL_MESH_BUILDERS["open_grid"]()
    field, _ = rim_peak(grid)
    head = sl.InterestPointHead(mode="paper", include_boundary=include_boundary)
    expected = detect(field, grid, mode="paper", include_boundary=include_boundary)
    assert head(field, *grid.tensors()).tolist() == expected
    assert f"include_boundary={include_boundary}" in repr(head)
