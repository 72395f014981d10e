"""``stochlap evaluate`` (stochlap_torch.cli.evaluate) on constructed ground-truth files.

The benchmark's human ground truth is not available offline, so the files here are built from
known vertices: if the subjects marked exactly the points a detector returns, that detector
must score FNE = WME = 0 at r = 0.
"""

from __future__ import annotations

import argparse
import json
import os

import pytest

import stochlap_torch as sl
from stochlap_torch import cli
from stochlap_torch.cli import app, evaluate
from stochlap_torch.evaluation import EVALUATE_METHODS, GEODESIC_METHODS
from stochlap_torch.evaluation import geodesics as geodesics_module
from stochlap_torch.evaluation.truth import read_marks

SPOT = sl.bundled_mesh_path("spot")
SPOT_VERTICES = 2930


def main(argv: list[str]) -> int:
    """``stochlap evaluate ...``."""
    return cli.main(["evaluate", *argv])


@pytest.fixture(scope="module")
def stochastic_points() -> list[int]:
    mesh = sl.load_mesh(SPOT)
    saliency = sl.mesh_saliency(mesh.vertices, mesh.faces, variant="paper")  # "stochastic"
    return sl.interest_points(saliency, mesh.vertices, mesh.faces).tolist()


def test_read_marks_format(tmp_path):
    path = tmp_path / "truth.txt"
    path.write_text("# header\n1 2 3\n\n4,5;6  # trailing comment\n-\n   # only a comment\n7\t8\n")
    assert read_marks(path, 10) == [[1, 2, 3], [4, 5, 6], [], [7, 8]]
    assert read_marks(path, 10, one_based=True) == [[0, 1, 2], [3, 4, 5], [], [6, 7]]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("1 2 x\n", "expected vertex indices, got 'x'"),
        ("1 10\n", "vertex 10 is out of range"),
        ("# nothing\n-\n", "no marked vertices"),
        ("0 1\n", None),  # one_based: 0 is out of range
    ],
)
def test_read_marks_errors(tmp_path, text, message):
    path = tmp_path / "truth.txt"
    path.write_text(text)
    if message is None:
        with pytest.raises(ValueError, match="1-based"):
            read_marks(path, 10, one_based=True)
    else:
        with pytest.raises(ValueError, match=message):
            read_marks(path, 10)


def test_evaluate_end_to_end(tmp_path, stochastic_points, capsys):
    truth = tmp_path / "spot_truth.txt"
    subjects = [stochastic_points[:5], stochastic_points[:5], stochastic_points[:3]]
    truth.write_text("\n".join(" ".join(map(str, s)) for s in subjects) + "\n")
    out_json = tmp_path / "curves.json"
    status = main(
        [
            *(str(SPOT), str(truth), "--methods", "stochastic,uniform", "--radii", "0", "0.05"),
            *("--json", str(out_json), "-q"),
        ]
    )
    assert status == 0
    printed = capsys.readouterr().out
    assert "stochastic" in printed and "FNE" in printed
    result = json.loads(out_json.read_text())
    curves = result["meshes"][str(SPOT)]["methods"]["stochastic"]
    assert result["meshes"][str(SPOT)]["num_truth"] == 5
    assert curves["fne"][0] == 0.0 and curves["wme"][0] == 0.0
    assert curves["num_points"] == len(stochastic_points)
    assert curves["fpe"][0] == pytest.approx(1 - 5 / len(stochastic_points))
    uniform = result["meshes"][str(SPOT)]["methods"]["uniform"]
    assert all(0.0 <= x <= 1.0 for key in ("fne", "fpe", "wme") for x in uniform[key])
    assert uniform["fne"][1] <= uniform["fne"][0]  # a larger radius never detects fewer


def test_evaluate_png(tmp_path, stochastic_points):
    pytest.importorskip("matplotlib")
    truth = tmp_path / "t.txt"
    truth.write_text(f"{stochastic_points[0]} {stochastic_points[1]}\n{stochastic_points[0]}\n")
    png = tmp_path / "fig15.png"
    status = main(
        [
            *(str(SPOT), str(truth), "--methods", "stochastic", "--radii", "0", "0.1"),
            *("--png", str(png), "-q", "--top-k", "5"),
        ]
    )
    assert status == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--methods", "stochastic,nope"], "unknown method nope"),
        (["--sigma", "2"], "--sigma: must lie in"),
        (["--radii", "-1"], "--radii: must be >= 0"),
        (["--threshold", "nan"], "--threshold: expected a finite number"),
        (["--min-subjects", "9"], "no ground-truth point"),
    ],
)
def test_bad_options_exit_2_with_one_line(tmp_path, capsys, extra, message):
    truth = tmp_path / "t.txt"
    truth.write_text("1 2\n1 2\n")
    status = main([str(SPOT), str(truth), "--methods", "stochastic", "--radii", "0", *extra])
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("stochlap: error:") and message in err
    assert err.count("\n") == 1


def test_odd_inputs_and_missing_files(tmp_path, capsys):
    assert main([str(SPOT)]) == 2
    assert "MESH TRUTH pairs" in capsys.readouterr().err
    assert main([str(SPOT), str(tmp_path / "missing.txt")]) == 2
    assert "missing.txt" in capsys.readouterr().err


def test_subcommand_hook():
    parser = argparse.ArgumentParser(prog="stochlap")
    commands = parser.add_subparsers(dest="command", required=True)
    app.add_command(commands, [], evaluate)
    args = parser.parse_args(["evaluate", "m.obj", "t.txt", "--methods", "lee", "--top-k", "3"])
    assert args.command == "evaluate" and args.inputs == ["m.obj", "t.txt"]
    assert args.methods == ["lee"] and args.top_k == 3
    assert callable(args.handler)


def test_parser_choices_come_from_the_library(capsys):
    # From stochlap_torch.evaluation.constants, which --help imports without torch.
    assert evaluate.EVALUATE_METHODS is EVALUATE_METHODS
    assert evaluate.GEODESIC_METHODS is GEODESIC_METHODS
    assert cli.main(["evaluate", "--help"]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert all(method in out for method in EVALUATE_METHODS)
    assert 'pip install "stochlap_torch[evaluation]"' in out


def _truth_file(tmp_path, points) -> str:
    truth = tmp_path / "t.txt"
    truth.write_text(f"{points[0]} {points[1]}\n{points[0]} {points[1]}\n")
    return str(truth)


def test_dijkstra_fallback_is_one_warning_line(tmp_path, stochastic_points, capsys, monkeypatch):
    monkeypatch.setattr(geodesics_module, "_potpourri3d", lambda: None)
    out_json = tmp_path / "r.json"
    args = [str(SPOT), _truth_file(tmp_path, stochastic_points), "--methods", "stochastic"]
    assert main([*args, "--radii", "0", "--json", str(out_json), "-q"]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert len(warnings) == 1, err  # once per mesh, not once per distance computation
    assert warnings[0].startswith("stochlap: warning: spot.obj: potpourri3d is not installed")
    assert "Dijkstra" in warnings[0] and "stochlap_torch[evaluation]" in warnings[0]
    assert json.loads(out_json.read_text())["meshes"][str(SPOT)]["geodesics"] == "dijkstra"


def test_heat_without_potpourri3d_names_the_extra(tmp_path, stochastic_points, capsys, monkeypatch):
    monkeypatch.setattr(geodesics_module, "_potpourri3d", lambda: None)
    args = [str(SPOT), _truth_file(tmp_path, stochastic_points), "--geodesics", "heat"]
    assert main([*args, "--methods", "stochastic", "--radii", "0", "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("stochlap: error:") and err.count("\n") == 1
    assert 'pip install "stochlap_torch[evaluation]"' in err


@pytest.mark.parametrize("option", ["--png", "--json"])
def test_outputs_never_overwrite_inputs(tmp_path, capsys, option):
    truth = tmp_path / "t.txt"
    truth.write_text("1 2\n1 2\n")
    before = truth.read_bytes()
    assert main([str(SPOT), str(truth), option, str(truth)]) == 2
    captured = capsys.readouterr()
    assert "refusing to overwrite" in captured.err and captured.out == ""
    assert truth.read_bytes() == before
    same = tmp_path / "out"
    assert main([str(SPOT), str(truth), "--png", str(same), "--json", str(same)]) == 2
    assert "same file" in capsys.readouterr().err


def test_failed_json_write_keeps_the_previous_file(tmp_path, stochastic_points, monkeypatch):
    out_json = tmp_path / "r.json"
    out_json.write_text('{"previous": true}\n')
    args = [str(SPOT), _truth_file(tmp_path, stochastic_points), "--methods", "stochastic"]

    def full_disk(fd):  # the bytes are in the temporary file; the flush to disk fails
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    assert main([*args, "--radii", "0", "--json", str(out_json), "-q"]) == 2
    assert out_json.read_text() == '{"previous": true}\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json", "t.txt"]  # no temporary


def test_binary_truth_file_is_a_format_error(tmp_path, capsys):
    truth = tmp_path / "t.bin"
    truth.write_bytes(b"\x00\xff\xfe 12")
    assert main([str(SPOT), str(truth)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("stochlap: error:") and "t.bin" in err and err.count("\n") == 1
