"""What you ask is what you get: options a variant does not use are refused, settings are
resolved one way (so caches and PyG's staleness check do not depend on spelling), and every
setting that changes the numbers reaches the cache key and the transform's ``repr``."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import pytest
import torch
from reference import noisy_sphere

import stochlap_torch as sl
from stochlap_torch.features import feature_params
from stochlap_torch.learning.cache import features_key, operators_key
from stochlap_torch.params import PaperFeatureParams, PaperParams, RobustParams
from stochlap_torch.saliency_maps import saliency_params


def _deprecated_robust_laplacian(**options):
    with pytest.warns(DeprecationWarning, match="RobustMultiscale"):
        return sl.StochasticLaplacian(variant="robust", **options)


def _mesh():
    mesh = noisy_sphere()
    return torch.tensor(mesh.vertices), torch.tensor(mesh.faces)


# --------------------------------------------------------------------------------------------
# Refused, never ignored

#: (what is built, the option it is given that its variant does not use).
REFUSED = [
    (lambda: sl.MultiscaleSaliency(threshold=-1.0), "threshold"),
    (lambda: sl.MultiscaleSaliency(threshold=0.01), "threshold"),
    (lambda: sl.MultiscaleSaliency(variant="robust", threshold=0.01), "threshold"),
    (lambda: sl.MultiscaleSaliency(variant="robust", paper=PaperParams()), "paper"),
    (lambda: sl.MultiscaleSaliency(variant="robust", min_count=3), "min_count"),
    (lambda: sl.MultiscaleSaliency(variant="paper", robust=RobustParams()), "robust"),
    (lambda: sl.MultiscaleSaliency(variant="paper", min_count=3), "min_count"),
    (lambda: sl.MultiscaleFeatures(variant="robust", rotation_invariant=False), "rotation_inv"),
    (lambda: sl.MultiscaleFeatures(rotation_invariant=True), "rotation_invariant"),
    (lambda: sl.MultiscaleFeatures(threshold=1e-3), "threshold"),
    (lambda: sl.MultiscaleFeatures(include=("norms",)), "include"),
    (lambda: sl.MultiscaleFeatures(normalisation="none"), "normalisation"),
    (lambda: sl.MultiscaleFeatures(differentiable_operator=True), "differentiable_operator"),
    (lambda: sl.MultiscaleFeatures(paper=PaperParams()), "paper"),
    (lambda: sl.MultiscaleFeatures(variant="paper", robust=RobustParams()), "robust"),
    (lambda: _deprecated_robust_laplacian(threshold=0.01), "threshold"),
    (lambda: _deprecated_robust_laplacian(return_operators=True), "return_op"),
    (lambda: _deprecated_robust_laplacian(differentiable_operator=True), "differ"),
    (lambda: sl.RobustMultiscale(threshold=0.01), "threshold"),
    (lambda: sl.StochasticLaplacian(robust=RobustParams()), "robust"),
    (lambda: sl.StochasticFeatures(threshold=0.01), "threshold"),
    (lambda: sl.StochasticFeatures(variant="paper", robust={}), "robust"),
    (lambda: sl.saliency(*_mesh(), threshold=0.01), "threshold"),
    (lambda: sl.saliency(*_mesh(), backend="torch"), "backend"),
    (lambda: sl.saliency(*_mesh(), variant="normal_coefficients", min_count=5), "min_count"),
    (lambda: sl.multiscale_features(*_mesh(), rotation_invariant=False), "rotation_invariant"),
    (lambda: sl.multiscale_features(*_mesh(), variant="paper", robust={}), "robust"),
]


@pytest.mark.parametrize(
    "build, option", REFUSED, ids=[f"{i}-{o}" for i, (_, o) in enumerate(REFUSED)]
)
def test_an_option_the_variant_does_not_use_is_refused_naming_it(build, option):
    with pytest.raises(sl.ParameterError, match=rf"{option}.* not apply to variant="):
        build()


def test_dataset_and_cache_refuse_unused_options(tmp_path):
    vertices, faces = _mesh()
    mesh_file = tmp_path / "sphere.ply"
    sl.save_ply(mesh_file, vertices, faces)
    with pytest.raises(sl.ParameterError, match="threshold"):
        sl.MeshFeatureDataset([mesh_file], threshold=0.01, progress=False)
    with pytest.raises(sl.ParameterError, match="threshold"):
        sl.cached_features(vertices, faces, tmp_path / "cache", threshold=0.01)
    assert not (tmp_path / "cache").exists() or not list((tmp_path / "cache").iterdir())


def test_unknown_cache_options_are_named():
    vertices, faces = _mesh()
    with pytest.raises(sl.ParameterError, match=r"unknown option.*'num_scale'"):
        sl.cached_features(vertices, faces, "unused", num_scale=3)
    with pytest.raises(sl.ParameterError, match="one mesh at a time"):
        sl.cached_features(vertices, faces, "unused", batch=torch.zeros(3))


def test_robust_settings_accept_a_mapping_and_name_bad_ones():
    assert feature_params(robust={}) == feature_params()
    assert feature_params(robust={"t0": 2e-3}) == RobustParams(t0=2e-3)
    assert saliency_params("paper", paper={"num_scales": 3}) == PaperParams(num_scales=3)
    with pytest.raises(sl.ParameterError, match=r"unknown settings.*'bogus'"):
        feature_params(robust={"bogus": 1})
    with pytest.raises(sl.ParameterError, match="robust must be a RobustParams"):
        sl.MultiscaleSaliency(robust=5)
    with pytest.raises(sl.ParameterError, match="paper must be a PaperParams"):
        sl.MultiscaleSaliency(variant="paper", paper=5)


@pytest.mark.parametrize(
    "field, value",
    [(f.name, -1.0) for f in dataclasses.fields(RobustParams) if f.type in ("float", float)]
    + [("num_scales", 0), ("min_vertices", 2), ("heat_resolution", float("nan"))],
)
def test_every_robust_setting_is_checked(field, value):
    with pytest.raises(sl.ParameterError, match=field):
        RobustParams(**{field: value})


def test_cli_refuses_an_option_the_variant_does_not_use(tmp_path):
    out = tmp_path / "out.ply"
    command = ["saliency", "--threshold", "0.01", "-o", str(out), "--no-png"]
    result = subprocess.run(
        [sys.executable, "-m", "stochlap_torch", *command],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert "threshold" in result.stderr and "robust" in result.stderr
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------
# The documented defaults are the ones that run


def test_documented_defaults_are_the_ones_that_run():
    assert sl.RobustMultiscale().params == RobustParams()
    assert sl.RobustMultiscale().num_scales == RobustParams.num_scales
    assert _deprecated_robust_laplacian().params == RobustParams()
    assert isinstance(_deprecated_robust_laplacian(), sl.RobustMultiscale)
    assert sl.StochasticLaplacian().params == PaperParams(
        PaperParams.num_scales, PaperParams.threshold
    )
    assert sl.MultiscaleSaliency().params == RobustParams()
    assert sl.MultiscaleSaliency(variant="paper").num_scales == PaperParams.num_scales
    assert sl.MultiscaleFeatures(variant="paper").num_scales == PaperFeatureParams.num_scales
    assert (
        sl.MultiscaleFeatures().num_scales == RobustParams.num_scales == RobustParams().num_scales
    )


def test_robust_laplacian_honours_max_memory():
    vertices, faces = _mesh()
    with pytest.raises(sl.MemoryBudgetError):
        sl.RobustMultiscale(max_memory=1024)(vertices, faces)


def test_a_keyword_contradicting_the_settings_object_is_refused():
    """``num_scales=3`` beside ``RobustParams(num_scales=5)`` ran 3 scales without a word."""
    vertices, faces = _mesh()
    with pytest.raises(sl.ParameterError, match="num_scales=3 contradicts"):
        sl.saliency(vertices, faces, num_scales=3, robust=RobustParams(num_scales=5))
    with pytest.raises(sl.ParameterError, match=r"threshold=0\.1 contradicts"):
        sl.MultiscaleFeatures(variant="paper", threshold=0.1, paper=PaperParams(threshold=0.01))


def test_num_scales_fills_a_field_the_settings_object_leaves_at_its_default():
    assert sl.MultiscaleSaliency(num_scales=3, robust=RobustParams(t0=2e-3)).params == (
        RobustParams(num_scales=3, t0=2e-3)
    )
    params = saliency_params("paper", num_scales=3, paper=PaperParams(threshold=0.01))
    assert params == PaperParams(3, 0.01)


# --------------------------------------------------------------------------------------------
# One computation, one cache entry; every setting that changes it, another


#: Spellings of the default robust features.
ROBUST_SPELLINGS = [
    {},
    {"variant": "robust"},
    {"robust": RobustParams()},
    {"robust": {}},
    {"num_scales": RobustParams.num_scales},
    {"robust": RobustParams(resolution=8, normal_time=2e-3, num_scales=7)},
    {"max_memory": 2**40},
]
#: Spellings of the default paper features.
PAPER_SPELLINGS = [
    {"variant": "paper"},
    {
        "variant": "paper",
        "num_scales": PaperFeatureParams.num_scales,
        "threshold": PaperParams.threshold,
    },
    {"variant": "paper", "paper": PaperParams(num_scales=PaperFeatureParams.num_scales)},
    {"variant": "paper", "include": ("saliency", "differences", "norms", "coefficients")},
    {"variant": "paper", "rotation_invariant": True, "normalisation": "mean_edge"},
    {"variant": "paper", "threshold": torch.tensor(1e-3, dtype=torch.float64).item()},
]


@pytest.mark.parametrize("spellings", [ROBUST_SPELLINGS, PAPER_SPELLINGS], ids=["robust", "paper"])
def test_equal_computations_share_one_cache_entry(tmp_path, spellings):
    vertices, faces = _mesh()
    results = [sl.cached_features(vertices, faces, tmp_path, **options) for options in spellings]
    assert len(list(tmp_path.glob("*.npz"))) == 1
    for result in results[1:]:
        assert torch.equal(result, results[0])


def test_equal_dataset_options_share_one_feature_file(tmp_path, monkeypatch):
    vertices, faces = _mesh()
    mesh_file = tmp_path / "sphere.ply"
    sl.save_ply(mesh_file, vertices, faces)
    cache = tmp_path / "cache"
    sl.MeshFeatureDataset([mesh_file], cache_dir=cache, num_scales=3, progress=False)

    def fail(*args, **kwargs):
        raise AssertionError("recomputed although the file holds these options")

    monkeypatch.setattr("stochlap_torch.features.multiscale_features", fail)
    robust = RobustParams()  # num_scales replaces its default
    sl.MeshFeatureDataset([mesh_file], cache_dir=cache, num_scales=3, progress=False, robust=robust)
    assert [path.name for path in cache.iterdir()] == ["sphere.npz"]


def _changed(value):
    """Another valid value of a setting (positive numbers doubled, integers raised)."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    return value * 2.0


@pytest.mark.parametrize("field", [f.name for f in dataclasses.fields(RobustParams)])
def test_every_robust_setting_changes_the_cache_key(field):
    vertices, faces = _mesh()
    base = RobustParams()
    changed = dataclasses.replace(base, **{field: _changed(getattr(base, field))})
    assert features_key(vertices, faces, feature_params(robust=changed)) != features_key(
        vertices, faces, feature_params(robust=base)
    )


@pytest.mark.parametrize(
    "options",
    [
        {"num_scales": 5},
        {"threshold": 2e-3},
        {"include": ("norms",)},
        {"rotation_invariant": False},
        {"normalisation": "bbox_diagonal"},
    ],
    ids=lambda o: next(iter(o)),
)
def test_every_paper_setting_changes_the_cache_key(options):
    vertices, faces = _mesh()
    base = features_key(vertices, faces, feature_params("paper"))
    assert features_key(vertices, faces, feature_params("paper", **options)) != base


def test_operator_keys_follow_the_resolved_parameters(tmp_path):
    vertices, faces = _mesh()
    assert operators_key(vertices, faces, PaperParams(3, 1e-3)) != operators_key(
        vertices, faces, PaperParams(3, 2e-3)
    )
    sl.cached_operators(vertices, faces, tmp_path, num_scales=3)
    sl.cached_operators(vertices, faces, tmp_path, paper=PaperParams(num_scales=3))
    sl.cached_operators(vertices, faces, tmp_path, num_scales=3, threshold=PaperParams.threshold)
    assert len(list(tmp_path.glob("*.npz"))) == 1


# --------------------------------------------------------------------------------------------
# PyG: the repr marks every setting; features never truncated


@pytest.mark.parametrize("field", [f.name for f in dataclasses.fields(RobustParams)])
def test_transform_repr_names_every_robust_setting(field):
    pytest.importorskip("torch_geometric")
    base = RobustParams()
    changed = dataclasses.replace(base, **{field: _changed(getattr(base, field))})
    assert repr(sl.StochasticFeatures(robust=changed)) != repr(sl.StochasticFeatures(robust=base))
    assert repr(sl.StochasticFeatures(robust=changed)) == repr(
        sl.StochasticFeatures(robust=dataclasses.asdict(changed))
    )


def test_transform_repr_does_not_depend_on_spelling():
    pytest.importorskip("torch_geometric")
    spelled = {repr(sl.StochasticFeatures(**options)) for options in ROBUST_SPELLINGS[:-1]}
    assert spelled == {"StochasticFeatures(variant='robust')"}  # what differs from defaults
    paper = {repr(sl.StochasticFeatures(**options)) for options in PAPER_SPELLINGS}
    assert len(paper) == 1


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.float64])
def test_transform_promotes_integer_node_features(dtype):
    pytest.importorskip("torch_geometric")
    from torch_geometric.data import Data

    vertices, faces = _mesh()
    labels = (torch.arange(vertices.shape[0]) % 2).to(dtype)
    data = sl.StochasticFeatures(num_scales=3)(Data(pos=vertices, face=faces.t(), x=labels))
    expected = sl.multiscale_features(vertices, faces, num_scales=3)
    assert data.x.dtype == torch.promote_types(dtype, expected.dtype)
    assert data.x.is_floating_point()
    torch.testing.assert_close(data.x[:, 1:], expected.to(data.x.dtype))
    assert torch.equal(data.x[:, 0], labels.to(data.x.dtype))


def test_an_explicit_cuda_backend_never_falls_back(monkeypatch):
    """``backend="cuda"`` insists on the streaming kernel: a run it cannot stream (operators
    kept, a gradient graph) is refused; ``"auto"`` takes the torch ops for it instead."""
    import stochlap_torch.diffusion.engine as engine
    import stochlap_torch.diffusion.parameters as parameters

    # As on a CUDA device: the CUDA kernel runs here, and "auto" resolves to it.
    monkeypatch.setattr(parameters, "_cuda_kernel_runs_on", lambda device: True)
    resolve = parameters.resolve_backend
    monkeypatch.setattr(
        engine, "resolve_backend", lambda b, d: "cuda" if b == "auto" else resolve(b, d)
    )
    vertices, faces = _mesh()
    with pytest.raises(sl.ParameterError, match="keeps no operator"):
        sl.multiscale_representation(vertices, faces, 3, backend="cuda", return_operators=True)
    with pytest.raises(sl.ParameterError, match="keeps no operator"):
        sl.multiscale_representation(vertices.requires_grad_(), faces, 3, backend="cuda")
    rep = sl.multiscale_representation(vertices, faces, 3, backend="auto", return_operators=True)
    assert len(rep.operators) == 3


def test_a_resolved_options_object_refuses_the_other_variants_options():
    """``params=`` (what the layers, datasets and CLI pass) refuses a run option its variant
    does not use, as the keywords do."""
    vertices, faces = _mesh()
    with pytest.raises(sl.ParameterError, match="differentiable_operator"):
        sl.multiscale_features(
            vertices, faces, params=feature_params(), differentiable_operator=True
        )
    with pytest.raises(sl.ParameterError, match="backend"):
        sl.saliency(vertices, faces, params=saliency_params(), backend="torch")
    with pytest.raises(sl.ParameterError, match="structure"):
        sl.multiscale_features(vertices, faces, params=feature_params("paper"), structure=object())


@pytest.mark.parametrize(
    "build",
    [
        lambda: sl.InterestPointHead(mode="paper", radius=0.2),
        lambda: sl.interest_points(torch.rand(162), *_mesh(), mode="paper", radius=0.2),
    ],
    ids=["head", "function"],
)
def test_the_paper_interest_mode_refuses_a_suppression_radius(build):
    with pytest.raises(sl.ParameterError, match=r"radius=0\.2 does not apply to mode='paper'"):
        build()


def test_detectors_without_scales_refuse_scale_options():
    from stochlap_torch.evaluation import check_evaluation_parameters

    with pytest.raises(sl.ParameterError, match="num_scales=5 does not apply to methods="):
        check_evaluation_parameters(["lee", "hks", "robust"], num_scales=5)
    assert check_evaluation_parameters(["lee", "stochastic"], num_scales=5) == ("lee", "stochastic")


@pytest.mark.parametrize(
    "command",
    [
        ["interest", "--mode", "paper", "--radius", "0.3", "--no-png"],
        ["evaluate", "m.obj", "t.txt", "--methods", "lee", "-K", "5"],
        ["features", ".", "-o", "out", "--threshold", "0.01"],
    ],
    ids=["interest-radius", "evaluate-K", "features-threshold"],
)
def test_cli_commands_refuse_options_their_choice_does_not_use(tmp_path, command):
    result = subprocess.run(
        [sys.executable, "-m", "stochlap_torch", *command],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert "does not apply" in result.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "layer", [sl.StochasticLaplacian, sl.MultiscaleSaliency, sl.MultiscaleFeatures]
)
@pytest.mark.parametrize("budget", [float("nan"), -1, "x", True])
def test_layers_check_their_budget_at_construction(layer, budget):
    with pytest.raises(sl.ParameterError, match="max_memory"):
        layer(max_memory=budget)


# --------------------------------------------------------------------------------------------
# Third audit: options that reached the numbers unchecked, PyG attributes overwritten


@pytest.mark.parametrize(
    "options",
    [
        {"tolerance": 1.0},  # truncated the Chebyshev series to nothing
        {"tolerance": 1e308},
        {"t0": 1e-320},  # OverflowError downstream
        {"t0": 2**63},
        {"resolution": 1e308},
        {"t0": 10**400},  # OverflowError from float()
        {"min_vertices": 10**400},
    ],
    ids=lambda o: f"{next(iter(o))}={next(iter(o.values()))!r:.12}",
)
def test_robust_options_out_of_their_range_are_refused_by_name(options):
    name = next(iter(options))
    with pytest.raises(sl.ParameterError, match=name):
        sl.RobustParams(**options)
    with pytest.raises(sl.ParameterError, match=name):
        sl.saliency(*_mesh(), robust=options)


@pytest.mark.parametrize(
    "options, name",
    [
        ({"include": 0}, "include"),  # was a TypeError
        ({"params": [1, 2]}, "params"),  # was an AttributeError
        ({"paper": []}, "paper"),
    ],
)
def test_wrong_kinds_of_paper_options_are_named(options, name):
    with pytest.raises(sl.ParameterError, match=name):
        sl.MultiscaleFeatures(variant="paper", **options)


@pytest.mark.parametrize("name", ["pos", "face", "batch", "edge_index", "", 3])
def test_transform_refuses_to_overwrite_pygs_own_attributes(name):
    pytest.importorskip("torch_geometric")
    with pytest.raises(sl.ParameterError, match="attr_name"):
        sl.StochasticFeatures(attr_name=name)


def test_transform_refuses_node_features_of_another_row_count():
    pytest.importorskip("torch_geometric")
    from torch_geometric.data import Data

    vertices, faces = _mesh()
    data = Data(pos=vertices, face=faces.t(), x=torch.zeros(vertices.shape[0] - 1, 2))
    with pytest.raises(sl.ParameterError, match=r"data\.x has"):
        sl.StochasticFeatures(num_scales=3)(data)


def test_an_options_object_names_its_method_without_variant():
    """``params=`` alone picks the method of its class (a ``PaperParams`` given to the features
    becomes their ``PaperFeatureParams``, keeping its fields)."""
    from stochlap_torch.features import feature_params

    assert feature_params(params=PaperParams(num_scales=4)) == PaperFeatureParams(num_scales=4)
    assert feature_params(params=RobustParams(t0=2e-3)) == RobustParams(t0=2e-3)
    assert sl.MultiscaleSaliency(params=PaperParams(num_scales=4)).variant == "paper"
    with pytest.raises(sl.ParameterError, match="params must be a RobustParams"):
        sl.MultiscaleFeatures(variant="robust", params=PaperParams())
