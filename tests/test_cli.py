"""The ``stochlap`` command line tool: every subcommand on the bundled mesh, and bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from reference import open_grid, two_components, with_unreferenced_vertex

import stochlap_torch as sl
from stochlap_torch.cli import main
from stochlap_torch.interest import InterestPointWarning, boundary_vertices
from stochlap_torch.mesh import mesh_report

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
SPOT_VERTICES = 2930
SPOT_FACES = 5856
REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def workdir(tmp_path, monkeypatch) -> Path:
    """Run in an empty temporary directory (default outputs land in the current directory)."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def mpl():
    return pytest.importorskip("matplotlib")


def _is_png(path: Path) -> bool:
    return path.is_file() and path.read_bytes()[:8] == PNG_SIGNATURE


def _ply_property(path: Path, name: str) -> np.ndarray:
    """A float vertex property of a PLY file, read by trimesh (independent of our writer)."""
    loaded = trimesh.load(path, process=False)
    return np.asarray(loaded.metadata["_ply_raw"]["vertex"]["data"][name], dtype=np.float64)


def _write_obj(path: Path, vertices, faces) -> Path:
    lines = [f"v {x} {y} {z}" for x, y, z in np.asarray(vertices, dtype=float)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces)]
    path.write_text("\n".join(lines) + "\n")
    return path


def _error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


# --------------------------------------------------------------------------------------------
# saliency


def test_saliency_default_outputs(workdir, mpl, capsys):
    assert main(["saliency", "-K", "4"]) == 0
    ply, png = workdir / "spot_saliency.ply", workdir / "spot_saliency.png"
    assert _is_png(png)
    mesh = sl.load_mesh(ply)
    assert mesh.num_vertices == SPOT_VERTICES and mesh.num_faces == SPOT_FACES

    spot = sl.load_mesh(sl.bundled_mesh_path("spot"))
    expected = sl.saliency(spot.vertices, spot.faces, num_scales=4).numpy()
    np.testing.assert_allclose(_ply_property(ply, "saliency"), expected, rtol=1e-5, atol=1e-5)
    colours = trimesh.load(ply, process=False).visual.vertex_colors
    assert colours.shape == (SPOT_VERTICES, 4)
    # The most salient vertex is brighter than the least salient one (inferno: dark to light).
    brightest, darkest = colours[expected.argmax(), :3], colours[expected.argmin(), :3]
    assert int(brightest.sum()) > int(darkest.sum())

    captured = capsys.readouterr()
    assert "2930 vertices" in captured.out
    assert "spot_saliency.ply" in captured.out and "spot_saliency.png" in captured.out
    # Not a terminal: one progress line per scale.
    assert "scale 4/4" in captured.err
    assert "Traceback" not in captured.err


def test_saliency_named_outputs_without_png(workdir, capsys):
    args = ["saliency", "-K", "3", "-o", "out/cow.ply", "--no-png", "-q", "--dtype", "float32"]
    assert main(args) == 0
    assert sl.load_mesh(workdir / "out" / "cow.ply").num_vertices == SPOT_VERTICES
    assert not list(workdir.rglob("*.png"))
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""  # --quiet


def test_saliency_explicit_png_and_mesh_path(workdir, mpl):
    mesh_path = str(sl.bundled_mesh_path("spot"))
    assert main(["saliency", mesh_path, "-K", "3", "--png", "pics/s.png", "--up", "y"]) == 0
    assert _is_png(workdir / "pics" / "s.png")
    assert (workdir / "spot_saliency.ply").is_file()


# --------------------------------------------------------------------------------------------
# multiscale


def test_multiscale_writes_every_scale(workdir, mpl):
    assert main(["multiscale", "-K", "4", "-o", "ms", "-q"]) == 0
    out = workdir / "ms"
    plys = sorted(out.glob("spot_k*.ply"))
    assert [p.name for p in plys] == [f"spot_k{k:02d}.ply" for k in range(1, 5)]
    spot = sl.load_mesh(sl.bundled_mesh_path("spot"))
    representation = sl.multiscale_representation(spot.vertices, spot.faces, num_scales=4)
    for k, ply in enumerate(plys, start=1):
        mesh = sl.load_mesh(ply)
        assert mesh.num_vertices == SPOT_VERTICES
        torch.testing.assert_close(
            mesh.vertices, representation.positions[k - 1], rtol=0, atol=1e-5
        )
        np.testing.assert_allclose(
            _ply_property(ply, "difference"),
            representation.differences[k - 1].numpy(),
            rtol=1e-5,
            atol=1e-6,
        )
    assert _is_png(out / "spot_multiscale.png")


def test_multiscale_default_directory_and_scales(workdir, mpl):
    assert main(["multiscale", "-K", "3", "--scales", "1", "3", "-q"]) == 0
    assert len(list((workdir / "spot_multiscale").glob("*.ply"))) == 3
    assert _is_png(workdir / "spot_multiscale" / "spot_multiscale.png")


# --------------------------------------------------------------------------------------------
# interest


def test_interest_points_file(workdir, mpl, capsys):
    args = ["interest", "-K", "4", "-o", "pts.txt", "--png", "pts.png", "--top-k", "12", "-q"]
    assert main(args) == 0
    # 11 of the 12 asked for: one warning line that says why and what to try.
    (warning,) = capsys.readouterr().err.splitlines()
    assert "top_k=12 asked for, 11 interest points found" in warning and "radius=" in warning
    assert _is_png(workdir / "pts.png")
    text = (workdir / "pts.txt").read_text().splitlines()
    assert text[0].startswith("# vertex x y z saliency")
    table = np.loadtxt(workdir / "pts.txt", comments="#", ndmin=2)
    assert table.shape[1] == 5 and 1 <= table.shape[0] <= 12
    indices = table[:, 0].astype(np.int64)
    assert np.array_equal(indices, table[:, 0])  # integral
    spot = sl.load_mesh(sl.bundled_mesh_path("spot"))
    values = sl.saliency(spot.vertices, spot.faces, num_scales=4)
    with pytest.warns(InterestPointWarning):
        expected = sl.interest_points(values, spot.vertices, spot.faces, top_k=12)
    assert indices.tolist() == expected.tolist()
    np.testing.assert_allclose(table[:, 1:4], spot.vertices.numpy()[indices], atol=1e-7)
    np.testing.assert_allclose(table[:, 4], values.numpy()[indices], rtol=1e-7)
    assert np.all(np.diff(table[:, 4]) <= 1e-12)  # most salient first


def test_interest_paper_mode_no_png(workdir):
    assert main(["interest", "-K", "3", "--mode", "paper", "--no-png", "-q"]) == 0
    table = np.loadtxt(workdir / "spot_interest.txt", comments="#", ndmin=2)
    assert table.shape[0] >= 1
    assert not (workdir / "spot_interest.png").exists()


# --------------------------------------------------------------------------------------------
# info


def test_info_on_bundled_mesh(capsys):
    assert main(["info", str(sl.bundled_mesh_path("spot"))]) == 0
    out = capsys.readouterr().out
    rows = dict(line.split("  ", 1) for line in out.splitlines())
    rows = {key.strip(): value.strip() for key, value in rows.items()}
    assert rows["vertices"] == "2930"
    assert rows["faces"] == "5856"
    assert rows["edges"] == "8784"
    assert rows["boundary edges"] == "0"
    assert rows["connected components"] == "1"
    assert rows["valid (float64)"] == "yes"


def test_info_json(capsys):
    assert main(["info", "--json", str(sl.bundled_mesh_path("spot"))]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["vertices"] == SPOT_VERTICES
    assert report["closed"] is True and report["euler_characteristic"] == 2
    assert report["mean_edge_length"] > 0


@pytest.mark.parametrize(
    "builder, expected",
    [
        (open_grid, {"boundary_edges": 22, "components": 1, "closed": False}),
        (two_components, {"components": 2, "boundary_edges": 0, "closed": True}),
        (with_unreferenced_vertex, {"unreferenced_vertices": 1, "components": 1}),
    ],
)
def test_mesh_report_counts(builder, expected):
    small = builder()
    report = mesh_report(sl.Mesh(*small.tensors()))
    for key, value in expected.items():
        assert report[key] == value, key
    assert report["non_manifold_edges"] == 0
    assert report["valid_float64"] is True


def test_mesh_report_non_manifold_edge():
    # Three triangles on the edge (0, 1).
    vertices = torch.tensor(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]], dtype=torch.float64
    )
    faces = torch.tensor([[0, 1, 2], [1, 0, 3], [0, 1, 4]])
    report = mesh_report(sl.Mesh(vertices, faces))
    assert report["non_manifold_edges"] == 1
    assert report["boundary_edges"] == 6
    assert report["consistently_oriented"] is False


@pytest.mark.parametrize(
    "vertices, faces",
    [
        ([[0, 0, 0], [1, 0, 0], [float("nan"), 1, 0]], [[0, 1, 2]]),  # NaN vertex
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]]),  # face index out of range
    ],
    ids=["nan-vertex", "out-of-range-face"],
)
def test_info_bad_mesh_is_one_error_line(tmp_path, capsys, vertices, faces):
    path = _write_obj(tmp_path / "bad.obj", vertices, faces)
    assert main(["info", str(path)]) == 2
    captured = capsys.readouterr()
    lines = _error_lines(captured.err)
    assert len(lines) == 1, captured.err
    assert lines[0].startswith("stochlap: error: ")
    assert captured.out == ""


@pytest.mark.parametrize("command", ["info", "saliency", "multiscale", "interest"])
def test_missing_file(workdir, capsys, command):
    extra = [] if command == "info" else ["--no-png"]
    assert main([command, str(workdir / "no_such_mesh.obj"), *extra]) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1
    assert lines[0].startswith("stochlap: error: ") and "no_such_mesh.obj" in lines[0]


@pytest.mark.parametrize(
    "args",
    [
        ["saliency", "-K", "1"],
        ["saliency", "--threshold", "0"],
        ["multiscale", "-K", "3", "--scales", "4"],
        ["interest", "--radius", "-1"],
        ["interest", "--t-global", "2"],
    ],
)
def test_bad_parameters_fail_before_any_work(workdir, capsys, args):
    assert main(args) == 2
    captured = capsys.readouterr()
    lines = _error_lines(captured.err)
    assert len(lines) == 1 and lines[0].startswith("stochlap: error: ")
    assert captured.out == ""
    assert not list(workdir.iterdir())


def test_memory_budget_error_is_one_line(workdir, capsys, monkeypatch):
    monkeypatch.setenv("STOCHLAP_MAX_MEMORY", "1000")
    assert main(["saliency", "-K", "3", "--no-png", "-q"]) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("stochlap: error: ")


def test_usage_errors_and_help(capsys):
    assert main([]) == 2
    assert main(["saliency", "--no-such-option"]) == 2
    assert main(["--help"]) == 0
    assert "saliency" in capsys.readouterr().out


def test_threads_option(workdir, capsys):
    numba = pytest.importorskip("numba")
    before, numba_before = torch.get_num_threads(), numba.get_num_threads()
    try:
        assert main(["--threads", "1", "info", str(sl.bundled_mesh_path("spot"))]) == 0
        assert torch.get_num_threads() == 1
        # The CLI sets torch's count only; the library's kernels follow torch's.
        assert numba.get_num_threads() == numba_before
        assert "warning" not in capsys.readouterr().err
    finally:
        torch.set_num_threads(before)


def test_threads_capped_at_the_available_cpus(workdir, capsys):
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cpus = os.cpu_count()
    before = torch.get_num_threads()
    try:
        assert main(["info", "--threads", "5000", str(sl.bundled_mesh_path("spot"))]) == 0
        assert torch.get_num_threads() == cpus
    finally:
        torch.set_num_threads(before)
    message = f"stochlap: warning: --threads 5000: this process may use {cpus} CPUs, so {cpus}"
    assert capsys.readouterr().err.splitlines() == [f"{message} threads"]


# --------------------------------------------------------------------------------------------
# The real entry point


def _run_module(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    # Works from a plain checkout as well as from an installed package.
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    return subprocess.run(
        [sys.executable, "-m", "stochlap_torch", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_python_dash_m_entry_point(tmp_path):
    result = _run_module("info", str(sl.bundled_mesh_path("spot")), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "2930" in result.stdout

    bad = _write_obj(tmp_path / "bad.obj", [[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 5]])
    result = _run_module("info", str(bad), cwd=tmp_path)
    assert result.returncode == 2
    assert len(_error_lines(result.stderr)) == 1
    assert "Traceback" not in result.stderr


# --------------------------------------------------------------------------------------------
# Without matplotlib (an optional extra)


@pytest.fixture
def no_matplotlib(monkeypatch):
    """Make ``import matplotlib`` fail for the duration of a test."""
    for name in list(sys.modules):
        if name == "matplotlib" or name.startswith(("matplotlib.", "mpl_toolkits")):
            monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)


def test_explicit_png_without_matplotlib_fails_early(workdir, capsys, no_matplotlib):
    assert main(["saliency", "-K", "3", "--png", "s.png"]) == 2
    captured = capsys.readouterr()
    lines = _error_lines(captured.err)
    assert len(lines) == 1 and "stochlap_torch[viz]" in lines[0] and "--no-png" in lines[0]
    assert captured.out == ""  # nothing computed or written
    assert not list(workdir.iterdir())


@pytest.mark.parametrize("command", ["saliency", "multiscale", "interest"])
def test_default_picture_skipped_without_matplotlib(workdir, capsys, no_matplotlib, command):
    assert main([command, "-K", "3", "-q"]) == 0
    err = capsys.readouterr().err
    assert "warning: matplotlib is not installed" in err
    assert not list(workdir.rglob("*.png"))
    assert list(workdir.rglob("*.ply")) or list(workdir.rglob("*.txt"))


def test_saliency_ply_without_matplotlib(workdir, no_matplotlib):
    assert main(["saliency", "-K", "3", "--no-png", "-q"]) == 0
    colours = trimesh.load(workdir / "spot_saliency.ply", process=False).visual.vertex_colors
    assert colours.shape == (SPOT_VERTICES, 4)
    assert len(np.unique(colours, axis=0)) > 20  # the built-in inferno ramp was used


def test_warmup_compiles_every_path(capsys):
    """``stochlap warmup`` runs every kernel path once (loading them from the cache here)."""
    assert main(["warmup", "--dtype", "float64"]) == 0
    out = capsys.readouterr().out
    for path in ("streamed steps", "whole steps", "gradient path", "robust variant"):
        assert f"warmup: {path} (float64)" in out


def test_warmup_quiet_prints_nothing(capsys, monkeypatch):
    """Issue 33: ``stochlap warmup -q`` printed the first compile's notice, which tells the
    user to run ``stochlap warmup``."""
    import importlib

    from stochlap_torch._kernels import jit

    warmup = importlib.import_module("stochlap_torch._warmup")  # the module, not the function
    monkeypatch.setattr(jit, "_noticed", False)
    monkeypatch.delenv("STOCHLAP_QUIET", raising=False)
    monkeypatch.setattr(warmup, "_paths", lambda dtype: [("a kernel", jit._notice)])
    assert main(["warmup", "-q"]) == 0
    assert capsys.readouterr() == ("", "")


@pytest.mark.parametrize("flag", [[], ["--include-boundary"]])
def test_interest_rims_only_with_include_boundary(workdir, flag):
    """On an open patch the command gives the library's points, rim vertices only when asked
    (the paper saliency of this patch peaks on its rim)."""
    grid = open_grid()
    trimesh.Trimesh(grid.vertices, grid.faces, process=False).export(workdir / "grid.ply")
    args = ["interest", "grid.ply", "--variant", "paper", "-K", "3", "--mode", "paper"]
    assert main([*args, "-o", "pts.txt", "--no-png", "-q", *flag]) == 0
    got = np.loadtxt(workdir / "pts.txt", comments="#", ndmin=2)[:, 0].astype(int).tolist()
    mesh = sl.load_mesh(workdir / "grid.ply")
    values = sl.saliency(mesh.vertices, mesh.faces, variant="paper", num_scales=3)
    include = bool(flag)
    expected = sl.interest_points(
        values, mesh.vertices, mesh.faces, mode="paper", include_boundary=include
    )
    assert got == expected.tolist()
    rim = set(boundary_vertices(mesh.faces, mesh.num_vertices).nonzero().flatten().tolist())
    assert bool(set(got) & rim) == include
