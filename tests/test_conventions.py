"""Conventions shared by every entry point: one ``rotation_invariant`` default, ``load_mesh``'s
``dtype``, and validation once per call."""

from __future__ import annotations

import inspect
from pathlib import Path

import pytest
import torch
from reference import icosphere, noisy_sphere

import stochlap_torch as sl
from stochlap_torch._common.errors import StochlapError
from stochlap_torch.features import feature_params
from stochlap_torch.mesh import validation


def _write_obj(path: Path) -> Path:
    """icosphere(2) as an OBJ file of ``v`` and ``f`` records."""
    small = icosphere(2)
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in small.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in small.faces]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_rotation_invariant_has_one_default_everywhere():
    """No entry point declares ``rotation_invariant`` (its one default is
    :class:`PaperFeatureParams`'s), and the paper variant resolves it to ``True`` in each."""
    pytest.importorskip("torch_geometric", reason="StochasticFeatures needs torch_geometric")
    users = [sl.multiscale_features, sl.MultiscaleFeatures, sl.MeshFeatureDataset]
    users.append(sl.StochasticFeatures)
    declared = [
        user.__name__
        for user in users
        if "rotation_invariant" in inspect.signature(user).parameters
    ]
    assert declared == []  # one declaration: PaperFeatureParams
    resolved = [
        feature_params(variant="paper"),
        sl.MultiscaleFeatures(variant="paper").params,
        sl.StochasticFeatures(variant="paper").params,
    ]
    assert [params.rotation_invariant for params in resolved] == [True] * 3


def test_load_mesh_dtype_is_float32_or_float64_and_nothing_else(tmp_path):
    path = _write_obj(tmp_path / "sphere.obj")
    single = sl.load_mesh(path, dtype=torch.float32)
    double = sl.load_mesh(path)
    assert single.vertices.dtype == torch.float32 and double.vertices.dtype == torch.float64
    assert torch.equal(single.vertices, double.vertices.float())
    assert torch.equal(single.faces, double.faces)
    with pytest.raises(StochlapError, match="dtype"):
        sl.load_mesh(path, dtype=torch.float16)


def test_each_call_validates_its_mesh_once(monkeypatch):
    """Validation happens at the public boundary, once per call, and nothing is remembered
    between calls (no cache keyed by the tensors)."""
    calls = []
    check = validation.validate_mesh

    def spy(*args, **kwargs):
        calls.append(1)
        return check(*args, **kwargs)

    monkeypatch.setattr(validation, "validate_mesh", spy)
    vertices, faces = noisy_sphere().tensors(torch.float64)
    for run in (
        lambda: sl.saliency(vertices, faces, variant="paper"),
        lambda: sl.saliency(vertices, faces),
        lambda: sl.multiscale_representation(vertices, faces, 3),
    ):
        for _ in range(2):
            calls.clear()
            run()
            assert calls == [1]
