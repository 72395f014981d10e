"""``stochlap compare``: the table, the JSON, the picture and the refusals."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import stochlap_torch as sl
from stochlap_torch.cli import main
from stochlap_torch.evaluation import compare_methods

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
FAST = ["--in-process", "--methods", "stochastic,uniform"]


@pytest.fixture
def workdir(tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(tmp_path)
    return tmp_path


def test_the_table_and_the_json_hold_what_the_function_measures(workdir, capsys) -> None:
    assert main(["compare", *FAST, "--json", "figures.json", "-q"]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].split()[:3] == ["method", "seconds", "peak"]
    assert [line.split()[0] for line in table[1:]] == ["stochastic", "uniform"]
    figures = json.loads((workdir / "figures.json").read_text())
    assert figures["reference"] == "stochastic" and list(figures["runs"]) == [
        "stochastic",
        "uniform",
    ]
    spot = sl.load_mesh(sl.bundled_mesh_path("spot"))
    expected = compare_methods(spot.vertices, spot.faces, ["stochastic", "uniform"], isolate=False)
    for name, run in expected.runs.items():
        assert figures["runs"][name]["spearman"] == pytest.approx(run.spearman, abs=1e-12)
        assert figures["runs"][name]["num_points"] == run.points.numel()
        assert figures["runs"][name]["peak_bytes"] is None  # in process: not measured


def test_json_to_standard_output_replaces_the_table(workdir, capsys) -> None:
    assert main(["compare", *FAST, "--reference", "uniform", "--json", "-", "-q"]) == 0
    figures = json.loads(capsys.readouterr().out)
    assert figures["reference"] == "uniform"
    assert figures["runs"]["uniform"]["shared_points"] == 1.0


def test_the_picture_has_a_row_per_method(workdir) -> None:
    pytest.importorskip("matplotlib")
    assert main(["compare", *FAST, "--png", "rows.png", "--dpi", "40", "-q"]) == 0
    data = (workdir / "rows.png").read_bytes()
    assert data[:8] == PNG_SIGNATURE
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert height > 1.5 * width / 2  # two rows of two side-by-side views


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--methods", "robust,fft"], "distinct names from"),
        (["--methods", "hks,hks"], "distinct names from"),
        (["--methods", "hks", "--reference", "lee"], "--reference lee is not among --methods"),
    ],
)
def test_bad_choices_exit_2_with_one_line(workdir, capsys, arguments, message) -> None:
    assert main(["compare", "--in-process", *arguments]) == 2
    error = capsys.readouterr().err
    assert message in error and error.count("\n") == 1


def test_the_json_never_overwrites_the_mesh(workdir, capsys) -> None:
    mesh = workdir / "cow.obj"
    mesh.write_bytes(sl.bundled_mesh_path("spot").read_bytes())
    before = mesh.read_bytes()
    assert main(["compare", *FAST, str(mesh), "--json", str(mesh)]) == 2
    assert mesh.read_bytes() == before and "error" in capsys.readouterr().err
