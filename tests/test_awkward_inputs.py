"""Awkward inputs that used to hang, blow the memory budget or end in a raw error:
a few tiny triangles beside a huge one, a featureless plate, subnormal coordinates, collinear
faces, a batch entry without faces and budgets that are not numbers of bytes."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
import torch
from reference import SMALL_MESH_BUILDERS, icosphere

import stochlap_torch as sl
from stochlap_torch._common.errors import ParameterError
from stochlap_torch.baselines.laplacian_saliency import laplacian_saliency
from stochlap_torch.cli.app import main
from stochlap_torch.diffusion import memory
from stochlap_torch.interest import InterestPointWarning
from stochlap_torch.mesh import extent_scale
from stochlap_torch.mesh.validation import check_surface_area
from stochlap_torch.robust import RobustParams, robust_representation
from stochlap_torch.robust.heat import chebyshev_coefficients
from stochlap_torch.robust.structure import build_structure as robust_structure
from stochlap_torch.robust.structure import robust_memory, semigroup_memory

MIB = 1 << 20


def _big_and_tiny(side: float, count: int = 100) -> tuple[torch.Tensor, torch.Tensor]:
    """One right triangle of area 50 and, from its corner ``(10, 0, 0)``, a strip of ``count``
    equilateral triangles of side ``side``: one surface (not a soup, which is refused before
    any of this is counted), ``count + 5`` vertices."""
    top = side * math.sqrt(3) / 2
    bottom = [[10.0 + side * i, 0.0, 0.0] for i in range(count // 2 + 2)]
    upper = [[10.0 + side * (i + 0.5), top, 0.0] for i in range(count // 2 + 2)]
    vertices = [[0.0, 0.0, 0.0], [0.0, 10.0, 0.0], *bottom, *upper]
    lower, high = 2, 2 + len(bottom)
    faces = [[0, lower, 1]]
    for i in range(count // 2):
        faces += [[lower + i, lower + i + 1, high + i], [lower + i + 1, high + i + 1, high + i]]
    return torch.tensor(vertices), torch.tensor(faces)


def _plate(n: int = 10) -> tuple[torch.Tensor, torch.Tensor]:
    """An exactly flat ``n x n`` grid in the plane ``z = 0``."""
    xs, ys = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    faces = []
    for r in range(n - 1):
        for c in range(n - 1):
            a = r * n + c
            faces += [(a, a + 1, a + n + 1), (a, a + n + 1, a + n)]
    return torch.tensor(vertices), torch.tensor(faces)


def _tensors(name: str) -> tuple[torch.Tensor, torch.Tensor]:
    return SMALL_MESH_BUILDERS[name]().tensors()


# --------------------------------------------------------------------------------------------
# 1. the robust variant's Chebyshev terms are in its budget


def test_tiny_triangles_beside_a_huge_one_run_within_a_small_budget() -> None:
    """A level that needs millions of Chebyshev steps keeps only the ~sqrt(a) coefficients
    above the tolerance: it runs within 50 MiB (a table ``a`` terms wide took 1.4 GiB)."""
    vertices, faces = _big_and_tiny(1.5e-3)
    rep = robust_representation(vertices, faces, max_memory=50 * MIB)
    assert bool(torch.isfinite(rep.dn).all()) and bool(torch.isfinite(rep.spread).all())
    params = RobustParams()
    table = semigroup_memory(robust_structure(vertices, faces, params, heat=False), params)
    assert table < 4 * MIB  # the kept terms alone


def test_the_chebyshev_table_is_counted_in_the_budget_before_diffusing() -> None:
    """A budget that holds the run but not its coefficient table is refused, naming them."""
    vertices, faces = _big_and_tiny(1.5e-3)
    params = RobustParams()
    table = semigroup_memory(robust_structure(vertices, faces, params, heat=False), params)
    budget = robust_memory(vertices.shape[0], params) + table // 2
    with pytest.raises(sl.MemoryBudgetError, match="Chebyshev coefficients") as caught:
        robust_representation(vertices, faces, max_memory=budget)
    assert "max_memory" in str(caught.value)
    with pytest.raises(sl.MemoryBudgetError, match="Chebyshev coefficients"):
        sl.saliency(vertices, faces, variant="robust", max_memory=budget)


def test_semigroup_memory_bounds_the_coefficient_table_it_counts() -> None:
    """The estimate against numpy's own count of the table's bytes (tracemalloc): above it,
    and within a small constant of it."""
    vertices, faces = _big_and_tiny(0.01, count=20)
    params = RobustParams()
    structure = robust_structure(vertices, faces, params, heat=False)
    estimate = semigroup_memory(structure, params)
    peak = 0
    for index, level in enumerate(structure.levels):
        if level.semigroup is None:
            continue
        times = [
            params.times[k] for k, chosen in enumerate(structure.assignment) if chosen == index
        ]
        tracemalloc.start()
        chebyshev_coefficients(np.array(times), level.semigroup.bound, params.tolerance)
        peak = max(peak, tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    assert 0 < peak <= estimate <= 1.25 * peak + 64 * 1024


def test_an_even_mesh_needs_little_for_its_coefficients() -> None:
    vertices, faces = _tensors("noisy_sphere")
    params = RobustParams()
    structure = robust_structure(vertices, faces, params, heat=False)
    assert 0 < semigroup_memory(structure, params) < MIB


# --------------------------------------------------------------------------------------------
# 2. nothing salient, no interest points


@pytest.mark.parametrize("mode", ["nms", "paper"])
def test_a_flat_plate_has_no_interest_points(mode: str) -> None:
    vertices, faces = _plate()
    saliency = sl.saliency(vertices, faces, variant="robust")
    assert bool((saliency == 0).all()), "an exactly flat plate has no saliency"
    with pytest.warns(InterestPointWarning, match="the same on every vertex"):
        points = sl.interest_points(saliency, vertices, faces, mode=mode, top_k=10)
    assert points.dtype == torch.int64 and points.shape == (0,)


def test_a_constant_field_has_no_interest_points_but_a_batch_neighbour_does() -> None:
    plate_v, plate_f = _plate(6)
    bumpy_v, bumpy_f = _tensors("noisy_sphere")
    vertices = torch.cat([plate_v, bumpy_v])
    faces = torch.cat([plate_f, bumpy_f + plate_v.shape[0]])
    batch = torch.cat([torch.zeros(plate_v.shape[0]), torch.ones(bumpy_v.shape[0])]).long()
    field = torch.cat([torch.full((plate_v.shape[0],), 2.5), torch.rand(bumpy_v.shape[0]) + 1])
    with pytest.warns(InterestPointWarning, match="0 interest points found in mesh 0"):
        points = sl.interest_points(field, vertices, faces, top_k=5, batch=batch)
    alone = sl.interest_points(field[plate_v.shape[0] :], bumpy_v, bumpy_f, top_k=5)
    assert points.tolist() == (alone + plate_v.shape[0]).tolist() and alone.numel() > 0


# --------------------------------------------------------------------------------------------
# 3. named errors, or results, where raw errors were


def _tetrahedron() -> tuple[torch.Tensor, torch.Tensor]:
    vertices = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0.2, 0.3, 1]], dtype=torch.float64)
    return vertices, torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def test_subnormal_coordinates_are_scaled_up_exactly() -> None:
    """A mesh scaled by ``2**-1040`` (subnormal coordinates): the largest finite power of two
    scales it back (no OverflowError), and every scale-invariant output equals the mesh's."""
    vertices, faces = icosphere(1).tensors()
    vertices = torch.round(vertices * 2.0**20) / 2.0**20  # 21 bits: subnormals hold them
    tiny = vertices * 2.0**-1040
    assert torch.equal(tiny * 2.0**1000 * 2.0**40, vertices), "the scaling is exact"
    assert extent_scale(tiny) == 2.0**1023
    assert extent_scale(tiny.float()) == 1.0  # float32 holds none of it: all zero
    sl.validate_mesh(tiny, faces)
    paper, reference = (sl.multiscale_representation(v, faces, 3) for v in (tiny, vertices))
    assert torch.equal(paper.differences, reference.differences)
    robust, robust_reference = (robust_representation(v, faces) for v in (tiny, vertices))
    assert torch.equal(robust.dn, robust_reference.dn)
    assert torch.equal(robust.spread, robust_reference.spread)


def test_subnormal_float32_extent_gets_a_float32_scale() -> None:
    vertices, _ = _tetrahedron()
    tiny = (vertices * 2.0**-140).float()  # float32 subnormals, 2**-140 exactly representable
    scale = extent_scale(tiny)
    assert scale == 2.0**127 and torch.isfinite(tiny * scale).all()


def test_info_reports_a_mesh_with_subnormal_coordinates(tmp_path, capsys) -> None:
    path = tmp_path / "tiny.off"
    rows = ["0 0 0", "1e-310 0 0", "0 1e-310 0", "0 0 1e-310"]
    path.write_text("OFF\n4 4 0\n" + "\n".join(rows) + "\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "valid (float64)         yes" in out


_COLLINEAR = {
    "axis-aligned": torch.tensor([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=torch.float64),
    # On a line in general position: the cross products are rounding, not zero.
    "rounded": torch.tensor([1.1, 2.3, 0.7], dtype=torch.float64)
    + torch.tensor([0.0, 0.3, 0.5, 1.0], dtype=torch.float64)[:, None]
    * torch.tensor([0.3, 0.7, 0.11], dtype=torch.float64),
}


@pytest.mark.parametrize("name", sorted(_COLLINEAR))
def test_collinear_faces_are_a_mesh_error_in_the_robust_variant(name: str) -> None:
    vertices, faces = _COLLINEAR[name], torch.tensor([[0, 1, 2], [1, 2, 3]])
    for call in (
        lambda: robust_representation(vertices, faces),
        lambda: sl.saliency(vertices, faces, variant="robust"),
        lambda: sl.multiscale_features(vertices, faces, variant="robust"),
    ):
        with pytest.raises(sl.MeshError, match="collinear") as caught:
            call()
        assert "face indices [0, 1]" in str(caught.value)
    # The paper variant needs edge lengths only: the mesh is valid there.
    assert torch.isfinite(sl.saliency(vertices, faces, num_scales=3, variant="paper")).all()


def test_info_says_the_robust_variant_refuses_collinear_faces(tmp_path, capsys) -> None:
    path = tmp_path / "line.off"
    path.write_text("OFF\n4 2 0\n0 0 0\n1 0 0\n2 0 0\n3 0 0\n3 0 1 2\n3 1 2 3\n")
    assert main(["info", str(path)]) == 0
    rows = dict(line.split("  ", 1) for line in capsys.readouterr().out.splitlines())
    assert rows["valid (robust variant)"].strip().startswith("no: the mesh has no surface area")
    assert rows["valid (float64)"].strip() == "yes"


def test_thin_but_real_surfaces_have_an_area() -> None:
    """Only rounding counts as no area: a strip a billionth as wide as it is long passes,
    in float64, and so does a float32 one a hundred-thousandth as wide."""
    vertices, faces = _plate(4)
    check_surface_area(vertices * torch.tensor([1.0, 1e-9, 1.0], dtype=torch.float64), faces)
    check_surface_area((vertices * torch.tensor([1.0, 1e-5, 1.0])).float(), faces)


def test_a_batch_entry_without_faces_gets_plane_values() -> None:
    """Mesh 1 of the batch is three vertices no face uses: they get the values of a plane,
    and mesh 0 the values of a run on its own."""
    vertices, faces = _tensors("noisy_sphere")
    extra = torch.tensor([[5.0, 0, 0], [6.0, 0, 0], [5.0, 1, 0]], dtype=torch.float64)
    batch = torch.cat([torch.zeros(vertices.shape[0]), torch.ones(3)]).long()
    packed = robust_representation(torch.cat([vertices, extra]), faces, batch=batch)
    alone = robust_representation(vertices, faces)
    count = vertices.shape[0]
    assert torch.equal(packed.dn[:count], alone.dn)
    assert torch.equal(packed.heat[:count], alone.heat)
    assert (packed.dn[count:] == 0).all() and (packed.mass[count:] == 0).all()
    assert (packed.heat[count:] == 0).all()
    assert packed.spread[count:].tolist() == [[[0.0, 1.0, 1.0]] * packed.num_scales] * 3
    assert packed.referenced.tolist() == [True] * count + [False] * 3
    saliency = sl.saliency(torch.cat([vertices, extra]), faces, batch=batch, variant="robust")
    assert torch.isfinite(saliency).all() and (saliency[count:] == 0).all()


_BAD_BUDGETS = [float("nan"), -1, 0, float("inf"), True, "1e9"]


def _entry_points(vertices: torch.Tensor, faces: torch.Tensor):
    """Every public function that takes ``max_memory``, as ``name -> call(max_memory)``."""
    return {
        "multiscale_representation": lambda m: sl.multiscale_representation(
            vertices, faces, 3, max_memory=m
        ),
        "multiscale_representation (operators)": lambda m: sl.multiscale_representation(
            vertices, faces, 3, return_operators=True, max_memory=m
        ),
        "differentiable_multiscale": lambda m: sl.differentiable_multiscale(
            vertices.clone().requires_grad_(True), faces, 3, max_memory=m
        ),
        "partitioned_multiscale": lambda m: sl.partitioned_multiscale(
            vertices, faces, 3, max_memory=m
        ),
        "robust_representation": lambda m: robust_representation(vertices, faces, max_memory=m),
        "saliency (paper)": lambda m: sl.saliency(vertices, faces, variant="paper", max_memory=m),
        "saliency (robust)": lambda m: sl.saliency(vertices, faces, max_memory=m),
        "features (paper)": lambda m: sl.multiscale_features(
            vertices, faces, variant="paper", max_memory=m
        ),
        "features (robust)": lambda m: sl.multiscale_features(vertices, faces, max_memory=m),
        "laplacian_saliency": lambda m: laplacian_saliency(vertices, faces, max_memory=m),
        "StochasticLaplacian": lambda m: sl.StochasticLaplacian(num_scales=3, max_memory=m)(
            vertices, faces
        ),
    }


@pytest.mark.parametrize("budget", _BAD_BUDGETS, ids=repr)
def test_a_budget_that_is_not_a_number_of_bytes_is_a_parameter_error(budget) -> None:
    vertices, faces = _tetrahedron()
    for name, call in _entry_points(vertices, faces).items():
        with pytest.raises(ParameterError, match="max_memory") as caught:
            call(budget)
        assert not isinstance(caught.value, sl.MemoryBudgetError), name


@pytest.mark.parametrize("text", ["nan", "-5", "inf", "lots"])
def test_a_bad_budget_in_the_environment_is_a_parameter_error(monkeypatch, text: str) -> None:
    monkeypatch.setenv(memory.MEMORY_ENV, text)
    vertices, faces = _tetrahedron()
    for call in (
        lambda: sl.multiscale_representation(vertices, faces, 3),
        lambda: robust_representation(vertices, faces),
    ):
        with pytest.raises(ParameterError, match=memory.MEMORY_ENV):
            call()


def test_good_budgets_of_every_numeric_type_are_accepted() -> None:
    vertices, faces = _tetrahedron()
    for budget in (1 << 30, 1e9, np.int64(1 << 30), torch.tensor(1 << 30)):
        assert memory.resolve_budget(budget) == int(budget)
        robust_representation(vertices, faces, max_memory=budget)


@pytest.mark.parametrize("value", ["lots", "nan", "-5", "0"])
def test_a_bad_archive_limit_in_the_environment_is_named(tmp_path, monkeypatch, value):
    import zipfile

    archive = tmp_path / "mesh.zip"
    with zipfile.ZipFile(archive, "w") as writer:
        writer.writestr("mesh.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    monkeypatch.setenv("STOCHLAP_MAX_ARCHIVE_BYTES", value)
    with pytest.raises(ParameterError, match="STOCHLAP_MAX_ARCHIVE_BYTES"):
        sl.load_mesh(archive)


def test_stored_zeros_across_components_do_not_reach_the_dense_blocks():
    """Two equal components, and a stored zero coupling them: the batched dense heat diagonal
    is that of the same operator without the stored zero."""
    from scipy import sparse

    from stochlap_torch.robust.heat import _blocks_of_size

    path = np.array([[1.0, -1.0, 0.0], [-1.0, 2.0, -1.0], [0.0, -1.0, 1.0]])
    dense = np.zeros((6, 6))
    dense[:3, :3] = dense[3:, 3:] = path
    clean = sparse.csr_matrix(dense)
    coo = clean.tocoo()
    stored = sparse.csr_matrix(
        (
            np.concatenate([coo.data, [0.0, 0.0]]),
            (np.concatenate([coo.row, [1, 4]]), np.concatenate([coo.col, [4, 1]])),
        ),
        shape=(6, 6),
    )
    assert stored.nnz > clean.nnz
    labels = np.array([0, 0, 0, 1, 1, 1])
    members = np.array([[0, 1, 2], [3, 4, 5]])
    mass, times = np.ones(6), np.array([0.5, 1.0])
    expected = _blocks_of_size(clean, mass, labels, members, 10.0, times)
    np.testing.assert_allclose(
        _blocks_of_size(stored, mass, labels, members, 10.0, times), expected
    )
