"""``compare_methods``: the multiscale saliency beside the eigendecomposition baselines."""

from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import reference as ref
import torch

import stochlap_torch as sl
from stochlap_torch.evaluation.compare import (
    AGREEMENT_RADIUS,
    COMPARE_METHODS,
    compare_methods,
    method_saliency,
)


def ranks(values: np.ndarray) -> np.ndarray:
    """Ranks 1..n, ties sharing their mean rank (plain loops)."""
    order = sorted(range(len(values)), key=lambda i: values[i])
    out = np.empty(len(values))
    i = 0
    while i < len(order):
        j = i
        while j + 1 < len(order) and values[order[j + 1]] == values[order[i]]:
            j += 1
        for k in range(i, j + 1):
            out[order[k]] = (i + j) / 2 + 1
        i = j + 1
    return out


@pytest.fixture(scope="module")
def sphere() -> tuple[torch.Tensor, torch.Tensor]:
    return ref.noisy_sphere().tensors()


@pytest.fixture(scope="module")
def compared(sphere):
    vertices, faces = sphere
    lines: list[str] = []
    result = compare_methods(
        vertices, faces, COMPARE_METHODS, reference="hks", isolate=False, progress=lines.append
    )
    return result, lines


def test_every_method_is_compared_with_the_reference(compared, sphere) -> None:
    result, lines = compared
    vertices = sphere[0]
    assert list(result.runs) == list(COMPARE_METHODS) and len(lines) == len(COMPARE_METHODS)
    assert result.reference == "hks" and result.num_vertices == vertices.shape[0]
    truth = result.runs["hks"]
    assert truth.spearman == pytest.approx(1.0) and truth.shared_points == 1.0
    diagonal = float((vertices.amax(0) - vertices.amin(0)).norm())
    for run in result.runs.values():
        assert run.saliency.shape == (vertices.shape[0],) and run.saliency.dtype == torch.float64
        assert run.seconds > 0 and run.peak_bytes is None  # not isolated: memory not measured
        a, b = ranks(run.saliency.numpy()), ranks(truth.saliency.numpy())
        assert run.spearman == pytest.approx(np.corrcoef(a, b)[0, 1], abs=1e-12)
        near = [
            min(np.linalg.norm((vertices[p] - vertices[q]).numpy()) for q in run.points.tolist())
            <= AGREEMENT_RADIUS * diagonal
            for p in truth.points.tolist()
        ]
        assert run.shared_points == pytest.approx(np.mean(near))


def test_the_saliencies_are_the_librarys(compared, sphere) -> None:
    result, _ = compared
    vertices, faces = sphere
    robust = sl.saliency(vertices, faces).double()
    torch.testing.assert_close(result.runs["robust"].saliency, robust, rtol=0, atol=0)
    paper = sl.saliency(vertices, faces, variant="paper").double()
    torch.testing.assert_close(result.runs["stochastic"].saliency, paper, rtol=0, atol=0)


def test_spectral_keeping_every_eigenvector_removes_nothing() -> None:
    """With as many eigenvectors as vertices the low-pass is the identity: no detail left."""
    vertices, faces = ref.icosphere(1).tensors()  # 42 vertices, fewer than the 64 kept
    detail = method_saliency("spectral", vertices, faces)
    assert float(detail.abs().max()) < 1e-9
    vertices, faces = ref.noisy_sphere().tensors()
    assert float(method_saliency("spectral", vertices, faces).abs().max()) > 1e-4


def test_the_table_and_json_hold_every_run(compared) -> None:
    result, _ = compared
    table = result.table().splitlines()
    assert len(table) == 1 + len(COMPARE_METHODS) and "Spearman vs hks" in table[0]
    data = result.to_dict()
    assert set(data["runs"]) == set(COMPARE_METHODS)
    assert data["runs"]["lee"]["num_points"] == result.runs["lee"].points.numel()


@pytest.mark.parametrize(
    ("methods", "reference", "match"),
    [
        (["robust", "fft"], None, "fft"),
        (["robust", "robust"], None, "distinct"),
        ([], None, "none"),
        (["robust", "hks"], "lee", "reference 'lee' is not among"),
    ],
)
def test_bad_choices_are_named(sphere, methods, reference, match) -> None:
    with pytest.raises(sl.ParameterError, match=match):
        compare_methods(*sphere, methods, reference=reference, isolate=False)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="peak memory is read from /proc")
def test_an_isolated_run_measures_its_own_time_and_memory(sphere) -> None:
    result = compare_methods(*sphere, ["stochastic"], isolate=True)
    run = result.runs["stochastic"]
    assert run.seconds > 0 and isinstance(run.peak_bytes, int) and run.peak_bytes >= 0
    paper = sl.saliency(*sphere, variant="paper").double()
    torch.testing.assert_close(run.saliency, paper, rtol=0, atol=0)
    assert not math.isnan(run.spearman)
