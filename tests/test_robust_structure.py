"""The robust variant's structure, built once and reused (issue 25 items 2 and 3): the same
numbers as a cold call, refused where it does not fit, movable, picklable, cacheable; and the
heat semigroup's torch recurrence against the scipy one."""

from __future__ import annotations

import copy
import dataclasses
import math
import pickle
import re

import numpy as np
import pytest
import torch
from reference import heat_apply, icosphere, noisy_sphere

import stochlap_torch as sl
from stochlap_torch.robust import RobustParams, RobustStructure
from stochlap_torch.robust.heat import (
    LevelSemigroup,
    chebyshev_apply,
    chebyshev_coefficients,
    chebyshev_terms,
    heat_operator,
)
from stochlap_torch.robust.structure import FORMAT_VERSION

#: Small enough for a pyramid of several levels on a 2562-vertex sphere.
SMALL = RobustParams(num_scales=4, min_vertices=100)


def _sphere_mesh():
    vertices, faces = icosphere(4).tensors(torch.float64)
    bumps = 1.0 + 0.15 * torch.sin(3.0 * vertices[:, [1]]) * torch.cos(2.0 * vertices[:, [0]])
    return vertices * bumps, faces


@pytest.fixture(scope="module")
def sphere():
    return _sphere_mesh()


@pytest.fixture(scope="module")
def structure(sphere):
    return sl.robust_structure(*sphere, robust=SMALL)


def test_a_reused_structure_gives_the_cold_call_numbers(sphere, structure):
    vertices, faces = sphere
    assert len(structure.levels) > 1, "the test needs a pyramid"
    cold = sl.multiscale_features(vertices, faces, robust=SMALL)
    warm = sl.multiscale_features(vertices, faces, robust=SMALL, structure=structure)
    torch.testing.assert_close(warm, cold, rtol=0, atol=1e-12)
    layer = sl.MultiscaleFeatures(robust=SMALL)
    torch.testing.assert_close(layer(vertices, faces, structure=structure), cold, rtol=0, atol=0)
    cold_saliency = sl.saliency(vertices, faces, robust=SMALL)
    warm_saliency = sl.saliency(vertices, faces, robust=SMALL, structure=structure)
    torch.testing.assert_close(warm_saliency, cold_saliency, rtol=0, atol=1e-12)
    module = sl.MultiscaleSaliency(robust=SMALL)
    torch.testing.assert_close(module(vertices, faces, structure=structure), cold_saliency)


def test_gradients_reach_the_vertices_with_the_structure_held(sphere, structure):
    vertices, faces = sphere
    moved = (vertices * 1.01).requires_grad_(True)
    features = sl.multiscale_features(moved, faces, robust=SMALL, structure=structure)
    features.square().sum().backward()
    assert moved.grad is not None and bool(torch.isfinite(moved.grad).all())
    assert float(moved.grad.abs().max()) > 0.0


def test_a_structure_that_does_not_fit_is_a_parameter_error(sphere, structure):
    vertices, faces = sphere
    other = noisy_sphere().tensors(torch.float64)
    with pytest.raises(sl.ParameterError, match="vertices"):
        sl.multiscale_features(*other, robust=SMALL, structure=structure)
    with pytest.raises(sl.ParameterError, match="settings"):
        sl.multiscale_features(vertices, faces, structure=structure)  # default params
    with pytest.raises(sl.ParameterError, match="RobustStructure"):
        sl.saliency(vertices, faces, robust=SMALL, structure="not a structure")
    with pytest.raises(sl.ParameterError, match="variant='paper'"):
        sl.multiscale_features(vertices, faces, variant="paper", structure=structure)
    with pytest.raises(sl.ParameterError, match="structure"):
        sl.saliency(vertices, faces, variant="paper", structure=structure)
    with pytest.raises(sl.ParameterError, match="structure"):
        sl.MultiscaleFeatures(variant="paper")(vertices, faces, structure=structure)


def test_a_batch_takes_one_structure_per_mesh(sphere):
    first = sphere
    second = noisy_sphere().tensors(torch.float64)
    vertices = torch.cat([first[0], second[0] * 2.0])
    faces = torch.cat([first[1], second[1] + first[0].shape[0]])
    index = torch.cat([torch.zeros(first[0].shape[0]), torch.ones(second[0].shape[0])]).long()
    structures = sl.robust_structure(vertices, faces, robust=SMALL, batch=index)
    assert isinstance(structures, list) and len(structures) == 2
    cold = sl.multiscale_features(vertices, faces, batch=index, robust=SMALL)
    warm = sl.multiscale_features(vertices, faces, batch=index, robust=SMALL, structure=structures)
    torch.testing.assert_close(warm, cold, rtol=0, atol=1e-12)
    with pytest.raises(sl.ParameterError, match="list of 2"):
        sl.multiscale_features(vertices, faces, batch=index, robust=SMALL, structure=structures[0])


def test_the_structure_pickles_moves_and_round_trips_through_its_state_dict(
    tmp_path, sphere, structure
):
    vertices, faces = sphere
    expected = sl.multiscale_features(vertices, faces, robust=SMALL, structure=structure)
    torch.save(structure.state_dict(), tmp_path / "structure.pt")
    loaded = RobustStructure.from_state_dict(
        torch.load(tmp_path / "structure.pt", weights_only=True)
    )
    numpy_state = {name: value.numpy() for name, value in structure.state_dict().items()}
    for value in numpy_state.values():
        value.setflags(write=False)  # as np.load's arrays may be
    for other in (
        pickle.loads(pickle.dumps(structure)),
        loaded,
        RobustStructure.from_state_dict(numpy_state),
        structure.to("cpu"),
    ):
        got = sl.multiscale_features(vertices, faces, robust=SMALL, structure=other)
        torch.testing.assert_close(got, expected, rtol=0, atol=0)
    state, again = structure.state_dict(), loaded.state_dict()
    assert list(again) == list(state)
    for name, value in state.items():
        assert value.device.type == "cpu" and value.dtype == again[name].dtype, name
        assert torch.equal(again[name], value), name
    assert int(state["format_version"]) == FORMAT_VERSION
    assert loaded.params == structure.params
    state["levels.1.corners"] = state["levels.1.corners"] + 10**6
    with pytest.raises(ValueError, match=r"levels\.1\.corners"):
        RobustStructure.from_state_dict(state)


def test_the_structure_is_the_operator(sphere, structure):
    """Built once, applied to the mesh's positions: the numbers of the functions."""
    vertices, faces = sphere
    features = sl.multiscale_features(vertices, faces, robust=SMALL, structure=structure)
    torch.testing.assert_close(structure.features(vertices), features, rtol=0, atol=0)
    saliency = sl.saliency(vertices, faces, robust=SMALL, structure=structure)
    torch.testing.assert_close(structure.saliency(vertices), saliency, rtol=0, atol=0)
    rep = structure.representation(vertices, dn_only=True)
    assert rep.spread is None and rep.dn.shape == (len(vertices), SMALL.num_scales)
    assert structure.channel_names() == sl.robust.robust_channel_names(SMALL)
    assert len(structure.channel_names()) == features.shape[1]
    with pytest.raises(sl.ParameterError, match="vertices"):
        structure.features(vertices[:-1])


def test_cached_structure_is_stored_and_reloaded(tmp_path, sphere):
    vertices, faces = sphere
    first = sl.cached_structure(vertices, faces, tmp_path, robust=SMALL)
    assert len(list(tmp_path.glob("*.npz"))) == 1
    second = sl.cached_structure(vertices, faces, tmp_path, robust=SMALL)
    one = sl.saliency(vertices, faces, robust=SMALL, structure=first)
    two = sl.saliency(vertices, faces, robust=SMALL, structure=second)
    torch.testing.assert_close(one, two, rtol=0, atol=0)
    sl.cached_structure(vertices, faces, tmp_path)  # other settings: another entry
    assert len(list(tmp_path.glob("*.npz"))) == 2


def _operator():
    mesh = noisy_sphere()
    return heat_operator(mesh.vertices, mesh.faces, cap=1.2)


@pytest.mark.parametrize("times", [(1e-9,), (1e-4, 2e-3), (4e-3, 1e-2, 3e-2)])
def test_the_torch_recurrence_matches_scipy_in_float64(times):
    """Increments ``F x - x`` by torch sparse CSR products against scipy's ``F x``."""
    operator = _operator()
    fields = np.random.default_rng(0).standard_normal((operator.num_vertices, 5))
    expected = heat_apply(operator, fields, times) - fields[None]
    got = chebyshev_apply(LevelSemigroup.of(operator), torch.from_numpy(fields), times, 1e-6)
    np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-12)


def test_the_torch_recurrence_runs_in_the_fields_dtype():
    operator = _operator()
    fields = torch.from_numpy(np.random.default_rng(1).standard_normal((operator.num_vertices, 3)))
    semigroup = LevelSemigroup.of(operator)
    single = chebyshev_apply(semigroup, fields.float(), (2e-3,), 1e-6)
    assert single.dtype == torch.float32
    double = chebyshev_apply(semigroup, fields, (2e-3,), 1e-6)
    torch.testing.assert_close(single.double(), double, rtol=0, atol=1e-5)


def test_a_float32_recurrence_takes_its_first_term_from_the_float64_fields():
    """Fields far from zero (as the spread's squared positions are): the first term, ``R x``,
    rounds relative to ``x``; computed from the float64 fields, the float32 increments keep
    their digits, which float32 fields lose."""
    operator = _operator()
    rng = np.random.default_rng(2)
    fields = torch.from_numpy(10.0 + 0.01 * rng.standard_normal((operator.num_vertices, 3)))
    semigroup = LevelSemigroup.of(operator)
    double = chebyshev_apply(semigroup, fields, (2e-3,), 1e-6)
    mixed = chebyshev_apply(semigroup, fields, (2e-3,), 1e-6, dtype=torch.float32)
    rounded = chebyshev_apply(semigroup, fields.float(), (2e-3,), 1e-6)
    assert mixed.dtype == torch.float32
    scale = float(double.abs().max())
    mixed_error = float((mixed.double() - double).abs().max()) / scale
    rounded_error = float((rounded.double() - double).abs().max()) / scale
    assert mixed_error < 1e-6 and rounded_error > 100.0 * mixed_error


#: The default scales on a pyramid of three levels for the 2562-vertex sphere: scales run on
#: levels 0, 1 and 2, so the interpolation to the mesh is on the path.
LEVELS = RobustParams(min_vertices=100)


def test_float32_features_and_gradients_are_within_a_thousandth_of_float64(sphere):
    vertices, faces = sphere
    structure = sl.robust_structure(vertices, faces, robust=LEVELS)
    assert set(structure.assignment) == {0, 1, 2}, "the test needs scales on three levels"
    width = len(sl.feature_channel_names())
    weights = torch.randn(len(vertices), width, dtype=torch.float64, generator=torch.Generator())

    def features_and_gradient(points):
        points = points.clone().requires_grad_(True)
        features = sl.multiscale_features(points, faces, robust=LEVELS, structure=structure)
        (features * weights.to(points.dtype)).sum().backward()
        return features.detach().double(), points.grad.double(), features.dtype

    double, double_grad, _ = features_and_gradient(vertices)
    single, single_grad, dtype = features_and_gradient(vertices.float())
    assert dtype == torch.float32
    error = (single - double).abs().max(dim=0).values / double.std(dim=0)
    assert float(error.max()) < 1e-3, error
    grad_error = (single_grad - double_grad).abs().max() / double_grad.abs().max()
    assert float(grad_error) < 1e-3


@pytest.mark.parametrize("scaled", [0.0, 1e-3, 1.0, 37.5, 1e3, 2.5e5])
def test_chebyshev_terms_are_the_kept_ones(scaled):
    """The bisection's count against a full-width table truncated at the tolerance."""
    from scipy.special import ive

    tol = 1e-6
    width = int(scaled + 12.0 * np.sqrt(scaled) + 30)
    k = np.arange(width)
    table = ive(k, scaled) * np.where(k == 0, 1.0, 2.0)
    kept = np.flatnonzero(table > tol)
    assert chebyshev_terms(scaled, tol) == (kept.max() + 1 if kept.size else 1)
    coefficients = chebyshev_coefficients(np.array([scaled * 2.0]), 1.0, tol)
    assert coefficients.shape[1] == chebyshev_terms(scaled, tol)
    if scaled >= 1e3:
        assert coefficients.shape[1] < 20 * np.sqrt(scaled)


def test_a_structure_of_the_same_counts_but_other_faces_is_refused(sphere, structure):
    """Same counts, same settings: the vertices renumbered (or another mesh of equal size)."""
    vertices, faces = sphere
    perm = torch.randperm(vertices.shape[0], generator=torch.Generator().manual_seed(0))
    inverse = torch.empty_like(perm)
    inverse[perm] = torch.arange(perm.numel())
    with pytest.raises(sl.ParameterError, match="other faces"):
        sl.multiscale_features(vertices[perm], inverse[faces], robust=SMALL, structure=structure)
    # Its own faces, wound the other way, fit: the structure winds them one way anyway.
    sl.multiscale_features(vertices, faces.flip(1), robust=SMALL, structure=structure)


def test_the_settings_travel_with_the_state(structure):
    assert RobustStructure.from_state_dict(structure.state_dict()).params == SMALL
    state = structure.state_dict()
    state["params.tolerance"] = torch.tensor(0.5, dtype=torch.float64)
    with pytest.raises(ValueError, match="tolerance"):
        RobustStructure.from_state_dict(state)


def _first_row_swapped(col):
    col[[0, 1]] = col[[1, 0]]
    return col


def _first_crow_raised(crow):
    crow[1] = crow[2] + 1
    return crow


def _first_set(value):
    return lambda array: array.reshape(-1).index_fill(0, torch.tensor(0), value).view_as(array)


#: What a crafted or damaged state may hold: ``(level, entry, change)``, the entry's level
#: the first with an operator (``"operator"``) or an interpolation (``"interpolation"``); each
#: is refused with a ValueError naming the entry. ``change`` returns the new value (``None``:
#: the entry removed).
CORRUPTIONS = {
    "zero bound": ("operator", "bound", lambda a: a * 0.0),
    "zero mass": ("operator", "capped_mass", _first_set(0.0)),
    "used reversed": ("", "used", lambda a: a.flip(0)),
    "level0 ids reversed": ("", "levels.0.vertex_ids", lambda a: a.flip(0)),
    "weights doubled": ("interpolation", "weights", lambda a: a * 2.0),
    "negative corner": ("interpolation", "corners", _first_set(-1)),
    "no settings": ("", "params.t0", lambda a: None),
    "column out of range": ("operator", "col", _first_set(10**9)),
    "columns unsorted": ("operator", "col", _first_row_swapped),
    "rows not monotone": ("operator", "crow", _first_crow_raised),
    "rows past the entries": ("operator", "crow", lambda a: a * 2),
    "values x100": ("operator", "val", lambda a: a * 100.0),
    "values negated": ("operator", "val", lambda a: -a),
    "values not finite": ("operator", "val", _first_set(math.nan)),
    "values float32": ("operator", "val", lambda a: a.float()),
    "heat 1e300": ("", "heat", _first_set(1e300)),
    "heat a column short": ("", "heat", lambda a: a[:, 1:]),
    "order not a permutation": ("operator", "order", _first_set(1)),
    "unknown version": ("", "format_version", lambda a: a + 1),
    "unknown entry": ("", "surprise", lambda a: torch.zeros(1)),
    "a scale on a level without operator": ("", "assignment", lambda a: a + 10),
}


@pytest.fixture(scope="module")
def three_levels(sphere):
    structure = sl.robust_structure(*sphere, robust=LEVELS)
    assert len(structure.levels) > 2 and structure.heat.shape[1] > 1
    return structure


@pytest.mark.parametrize("case", sorted(CORRUPTIONS))
def test_a_crafted_state_is_refused_naming_the_entry(three_levels, case):
    level, entry, change = CORRUPTIONS[case]
    if level:
        part = "semigroup" if level == "operator" else "prolongation"
        index = next(i for i, x in enumerate(three_levels.levels) if getattr(x, part) is not None)
        entry = f"levels.{index}.{entry}"
    state = three_levels.state_dict()
    value = change(state.get(entry, torch.zeros(0)).clone())
    if value is None:
        del state[entry]
    else:
        state[entry] = value
    with pytest.raises(ValueError, match=re.escape(entry)):
        RobustStructure.from_state_dict(state)


def test_a_pickled_structure_with_a_crafted_operator_is_refused(structure):
    """Pickling goes through the state dict's checks: a bad column index would otherwise
    reach the sparse kernels."""
    level = next(level for level in structure.levels if level.semigroup is not None)
    recurrence = level.semigroup.recurrence
    col = recurrence.col_indices().clone()
    col[0] = 10**6
    crafted = copy.copy(level.semigroup)
    crafted.recurrence = torch.sparse_csr_tensor(
        recurrence.crow_indices(),
        col,
        recurrence.values(),
        recurrence.shape,
        check_invariants=False,
    )
    levels = [
        dataclasses.replace(other, semigroup=crafted) if other is level else other
        for other in structure.levels
    ]
    with pytest.raises(ValueError, match="col"):
        pickle.loads(pickle.dumps(dataclasses.replace(structure, levels=levels)))


def test_a_state_that_is_no_mapping_of_arrays_is_refused(structure):
    with pytest.raises(ValueError, match="mapping"):
        RobustStructure.from_state_dict([("used", structure.used)])
    state = structure.state_dict()
    state["used"] = np.array(["not", "indices"])
    with pytest.raises(ValueError, match="used"):
        RobustStructure.from_state_dict(state)


def test_a_deep_copy_stays_on_the_device(structure):
    copied = copy.deepcopy(structure)
    assert copied is not structure and copied.device == structure.device
    assert torch.equal(copied.used, structure.used)


def test_the_state_dict_is_a_copy(structure):
    state = structure.state_dict()
    state["used"][0] = 10**6
    assert int(structure.used[0]) != 10**6


def test_a_second_derivative_through_the_semigroup_fails_clearly(sphere):
    vertices = sphere[0].clone().requires_grad_()
    features = sl.multiscale_features(vertices, sphere[1], robust=SMALL)
    (grad,) = torch.autograd.grad(features.sum(), vertices, create_graph=True)
    with pytest.raises(RuntimeError, match="differentiate twice"):
        grad.sum().backward()


def test_a_structure_serves_the_shape_it_was_built_on_up_to_a_similarity(sphere, structure):
    """A rotated, scaled and moved copy, or positions nudged by a gradient step, reuse the
    structure and get the cold call's features; positions jittered by an augmentation reuse
    it too. A stretched copy, or a part moved as in another pose of a template, has the same
    faces but is refused by name (it once got the other shape's pyramid: saliency 49 % off,
    silently)."""
    vertices, faces = sphere
    seed = torch.Generator().manual_seed(7)
    rotation = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=seed))[0]
    moved = 2.5 * vertices @ rotation.T + 1.0
    nudged = vertices + 1e-4 * torch.randn(vertices.shape, dtype=torch.float64, generator=seed)
    # examples/plot_train_on_device.py's augmentation: a third of an edge along the normals.
    edge = float((vertices[faces] - vertices[faces.roll(1, dims=1)]).norm(dim=-1).mean())
    normals = sl.vertex_normals(vertices, faces)
    shift = torch.randn(len(vertices), 1, dtype=torch.float64, generator=seed)
    jittered = vertices + edge / 3 * shift * normals
    for positions in (moved, nudged):
        reused = sl.multiscale_features(positions, faces, robust=SMALL, structure=structure)
        cold = sl.multiscale_features(positions, faces, robust=SMALL)
        torch.testing.assert_close(reused, cold, rtol=0, atol=1e-3 * float(cold.abs().max()))
    # Served with the clean mesh's operators, which is what the augmentation wants.
    assert torch.isfinite(structure.features(jittered)).all()
    stretched = vertices * torch.tensor([1.0, 1.0, 1.6], dtype=torch.float64)
    posed = vertices.clone()
    posed[vertices[:, 2] > 0.3, 0] += 1.0  # the top moved sideways
    for positions in (stretched, posed):
        with pytest.raises(sl.ParameterError, match="another shape"):
            sl.multiscale_features(positions, faces, robust=SMALL, structure=structure)
        with pytest.raises(sl.ParameterError, match="another shape"):
            structure.saliency(positions)


def test_a_loaded_shape_is_checked(structure):
    state = structure.state_dict()
    state["shape"] = state["shape"] * 1e9
    with pytest.raises(ValueError, match="shape"):
        RobustStructure.from_state_dict(state)
    state["shape"] = state["shape"][:-1]
    with pytest.raises(ValueError, match="shape"):
        RobustStructure.from_state_dict(state)


def test_the_structure_takes_the_options_as_the_calls_do(sphere, structure):
    """Keywords, the object and ``params=`` are one spelling of one structure; a paper option
    is refused by name."""
    for spelling in ({"num_scales": 4, "min_vertices": 100}, {"params": SMALL}):
        built = sl.robust_structure(*sphere, **spelling)
        assert built.params == structure.params
        assert built.assignment == structure.assignment
    with pytest.raises(sl.ParameterError, match="threshold"):
        sl.robust_structure(*sphere, threshold=0.1)
