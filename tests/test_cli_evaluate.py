"""``stochlap evaluate`` (stochlap_torch.cli_evaluate) on constructed ground-truth files.

The benchmark's human ground truth is not available offline, so the files here are built from
known vertices: if the subjects marked exactly the points a detector returns, that detector
must score FNE = WME = 0 at r = 0.
"""

from __future__ import annotations

import argparse
import json

import pytest

import stochlap_torch as sl
from stochlap_torch.cli.evaluate import add_evaluate_parser, main
from stochlap_torch.evaluation.truth import read_marks

SPOT = sl.bundled_mesh_path("spot")
SPOT_VERTICES = 2930


@pytest.fixture(scope="module")
def stochastic_points() -> list[int]:
    mesh = sl.load_mesh(SPOT)
    saliency = sl.mesh_saliency(mesh.vertices, mesh.faces)
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
        [str(SPOT), str(truth), "--methods", "stochastic,uniform", "--radii", "0", "0.05",
         "--json", str(out_json), "-q"]
    )  # fmt: skip
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
        [str(SPOT), str(truth), "--methods", "stochastic", "--radii", "0", "0.1", "--png",
         str(png), "-q", "--top-k", "5"]
    )  # fmt: skip
    assert status == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--methods", "stochastic,nope"], "unknown nope"),
        (["--sigma", "2"], "--sigma must lie in"),
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
    add_evaluate_parser(commands)
    args = parser.parse_args(["evaluate", "m.obj", "t.txt", "--methods", "lee", "--top-k", "3"])
    assert args.command == "evaluate" and args.inputs == ["m.obj", "t.txt"]
    assert args.methods == "lee" and args.top_k == 3
    assert callable(args.handler)
