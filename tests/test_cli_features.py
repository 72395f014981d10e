"""``stochlap features``: a folder of meshes to per-vertex feature files.

The features are compared with :func:`~stochlap_torch.features.multiscale_features` of the mesh
loaded in the test; the PLY is read back by trimesh, not by the library's writer; shards are
checked against the rule written out here (sorted output names, name ``k`` to shard ``k mod
n``). The paper variant with two scales on meshes of at most 162 vertices keeps each run short.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from reference import icosphere, noisy_sphere, open_grid, two_components

from stochlap_torch._common.errors import ParameterError
from stochlap_torch.cli import feature_jobs, main
from stochlap_torch.cli import features as features_command
from stochlap_torch.features import feature_channel_names, multiscale_features
from stochlap_torch.learning import feature_files
from stochlap_torch.mesh import load_mesh, save_ply

REPO_ROOT = Path(__file__).resolve().parents[1]
FAST = ["--variant", "paper", "-K", "2"]
#: The dataset of :func:`_dataset`: output name -> (file, mesh builder).
MESHES = {
    "a": ("a.obj", lambda: icosphere(1)),
    "c": ("c.off", open_grid),
    "d": ("d.stl", two_components),
    "sub/b": ("sub/b.ply", noisy_sphere),
}


def _dataset(root: Path, names=tuple(MESHES)) -> Path:
    """A folder with the meshes of :data:`MESHES` named ``names``, written by trimesh."""
    for name in names:
        file, build = MESHES[name]
        mesh = build()
        path = root / file
        path.parent.mkdir(parents=True, exist_ok=True)
        trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(path)
    return root


def _outputs(out: Path, suffix: str = ".npz") -> list[str]:
    """Output names (OUTDIR-relative, no suffix) of the files of ``suffix`` under ``out``."""
    return sorted(
        path.relative_to(out).with_suffix("").as_posix() for path in out.rglob(f"*{suffix}")
    )


def _expected(path: Path, dtype: str = "float64") -> np.ndarray:
    """The paper features, K=2, of the mesh file, computed here by the library's function."""
    import torch

    mesh = load_mesh(path, dtype=getattr(torch, dtype))
    return multiscale_features(mesh.vertices, mesh.faces, variant="paper", num_scales=2).numpy()


def _mtimes(out: Path) -> dict[str, int]:
    return {p.relative_to(out).as_posix(): p.stat().st_mtime_ns for p in out.rglob("*.*")}


def _error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("stochlap: error: ")]


def _run(*args: str) -> int:
    return main(["features", *args])


# --------------------------------------------------------------------------------------------
# What is written


def test_npz_holds_the_features_of_every_mesh(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST, "-q") == 0
    assert capsys.readouterr().out == ""
    assert _outputs(out) == sorted(MESHES)  # the folder searched recursively, names mirrored
    names = feature_channel_names("paper", num_scales=2)
    for name, (file, _) in MESHES.items():
        with np.load(out / f"{name}.npz", allow_pickle=False) as stored:
            mesh = load_mesh(data / file)
            np.testing.assert_array_equal(stored["features"], _expected(data / file))
            assert stored["features"].dtype == np.float64
            assert stored["channel_names"].tolist() == names
            np.testing.assert_array_equal(stored["vertices"], mesh.vertices.numpy())
            np.testing.assert_array_equal(stored["faces"], mesh.faces.numpy())
            settings = json.loads(str(stored["settings"]))
    assert settings["method"] == "PaperFeatureParams"
    assert settings["num_scales"] == 2 and settings["threshold"] == 1e-3
    assert settings["dtype"] == "float64" and settings["merge_seams"] is False


def test_dtype_float32_and_explicit_files(tmp_path):
    data = _dataset(tmp_path / "data", ["a", "sub/b"])
    out = tmp_path / "out"
    files = [str(data / "sub" / "b.ply"), str(data / "a.obj")]
    assert _run(*files, "-o", str(out), *FAST, "--dtype", "float32", "-q") == 0
    assert _outputs(out) == ["a", "b"]  # files named on the command line: OUTDIR/<stem>.npz
    with np.load(out / "b.npz") as stored:
        assert stored["features"].dtype == np.float32
        expected = _expected(data / "sub" / "b.ply", "float32")
        np.testing.assert_array_equal(stored["features"], expected)


def test_two_workers_write_the_same_features_and_plys(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST, "--ply", "--workers", "2") == 0
    captured = capsys.readouterr()
    assert "4 computed" in captured.out
    assert _outputs(out) == _outputs(out, ".ply") == sorted(MESHES)
    names = feature_channel_names("paper", num_scales=2)
    for name, (file, _) in MESHES.items():
        expected = _expected(data / file)
        with np.load(out / f"{name}.npz") as stored:
            np.testing.assert_array_equal(stored["features"], expected)
        loaded = trimesh.load(out / f"{name}.ply", process=False)
        properties = loaded.metadata["_ply_raw"]["vertex"]["data"]
        assert properties.dtype.names == ("x", "y", "z", *names)
        for column, channel in enumerate(names):
            np.testing.assert_array_equal(properties[channel], expected[:, column].astype("f4"))
        np.testing.assert_allclose(loaded.vertices, load_mesh(data / file).vertices, atol=1e-6)


def test_merge_seams(tmp_path):
    data = _dataset(tmp_path / "data", ["d"])  # STL: a triangle soup, three vertices a face
    out = tmp_path / "out"
    assert _run(str(data / "d.stl"), "-o", str(out), *FAST, "--merge-seams", "-q") == 0
    mesh = load_mesh(data / "d.stl", merge_seams=True)
    assert mesh.num_vertices < 3 * mesh.num_faces
    expected = multiscale_features(mesh.vertices, mesh.faces, variant="paper", num_scales=2)
    with np.load(out / "d.npz") as stored:
        np.testing.assert_array_equal(stored["vertices"], mesh.vertices.numpy())
        np.testing.assert_array_equal(stored["features"], expected.numpy())
        assert json.loads(str(stored["settings"]))["merge_seams"] is True


# --------------------------------------------------------------------------------------------
# Resuming


def test_rerun_skips_every_done_mesh(tmp_path, capsys):
    data = _dataset(tmp_path / "data", ["a", "c"])
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST, "--ply") == 0
    before = _mtimes(out)
    capsys.readouterr()
    assert _run(str(data), "-o", str(out), *FAST, "--ply") == 0
    assert "0 computed, 2 already done" in capsys.readouterr().out
    assert _mtimes(out) == before


def test_damaged_or_stale_outputs_are_recomputed(tmp_path, capsys):
    data = _dataset(tmp_path / "data")
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST, "-q") == 0
    whole = (out / "a.npz").read_bytes()
    (out / "a.npz").write_bytes(whole[: len(whole) // 2])  # a truncated file
    (out / "c.npz").unlink()  # killed before its file was renamed into place: a temporary left
    leftover = out / ".c.npz.k3j2h1.tmp"
    leftover.write_bytes(whole[:100])
    stale = time.time() - 2 * feature_files.STALE_SECONDS
    os.utime(leftover, (stale, stale))
    live = out / ".a.npz.x9y8z7.tmp"  # another run writing a.npz right now: left alone
    live.write_bytes(b"being written")
    moved = two_components()  # the mesh file changed since
    trimesh.Trimesh(moved.vertices * 2.0, moved.faces, process=False).export(data / "d.stl")
    before = _mtimes(out)
    assert _run(str(data), "-o", str(out), *FAST) == 0
    assert "3 computed, 1 already done" in capsys.readouterr().out
    after = _mtimes(out)
    assert after["sub/b.npz"] == before["sub/b.npz"]
    assert after["d.npz"] != before["d.npz"]
    assert not leftover.exists()
    assert live.read_bytes() == b"being written"
    for name in ("a", "c", "d"):
        with np.load(out / f"{name}.npz") as stored:
            np.testing.assert_array_equal(stored["features"], _expected(data / MESHES[name][0]))
    # The right settings and source, but a channel short: not done either.
    with np.load(out / "sub" / "b.npz") as stored:
        arrays = dict(stored)
    np.savez(out / "sub" / "b.npz", **{**arrays, "features": arrays["features"][:, :-1]})
    assert _run(str(data), "-o", str(out), *FAST) == 0
    assert "1 computed, 3 already done" in capsys.readouterr().out
    with np.load(out / "sub" / "b.npz") as stored:
        np.testing.assert_array_equal(stored["features"], _expected(data / "sub" / "b.ply"))


def test_other_settings_recompute_and_ply_is_added_from_the_stored_features(tmp_path, capsys):
    data = _dataset(tmp_path / "data", ["a"])
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST, "-q") == 0
    first = _mtimes(out)["a.npz"]
    assert _run(str(data), "-o", str(out), *FAST, "--ply") == 0
    assert "1 computed" in capsys.readouterr().out
    assert _mtimes(out)["a.npz"] == first  # the PLY was written from the .npz
    loaded = trimesh.load(out / "a.ply", process=False)
    np.testing.assert_array_equal(
        loaded.metadata["_ply_raw"]["vertex"]["data"]["diff2"],
        _expected(data / "a.obj")[:, 3].astype("f4"),
    )
    # K=3 without --ply leaves the PLY of K=2; with --ply, that PLY does not pass for done.
    assert _run(str(data), "-o", str(out), "--variant", "paper", "-K", "3", "-q") == 0
    with np.load(out / "a.npz") as stored:
        assert stored["channel_names"].tolist() == feature_channel_names("paper", num_scales=3)
    assert b"diff3" not in (out / "a.ply").read_bytes().split(b"end_header")[0]
    assert _run(str(data), "-o", str(out), "--variant", "paper", "-K", "3", "--ply", "-q") == 0
    assert b"diff3" in (out / "a.ply").read_bytes().split(b"end_header")[0]


# --------------------------------------------------------------------------------------------
# Shards


def test_shards_partition_the_sorted_meshes(tmp_path):
    data = _dataset(tmp_path / "data")
    names = sorted(MESHES)
    seen = []
    for index in range(2):
        out = tmp_path / f"out{index}"
        assert _run(str(data), "-o", str(out), *FAST, "--shard", f"{index}/2", "-q") == 0
        done = _outputs(out)
        assert done == [name for k, name in enumerate(names) if k % 2 == index]
        seen += done
    assert sorted(seen) == names
    # Files named in any order are sorted by output name too: a, b, c, d.
    files = [str(data / MESHES[name][0]) for name in reversed(names)]
    assert _run(*files, "-o", str(tmp_path / "files"), *FAST, "--shard", "0/2", "-q") == 0
    assert _outputs(tmp_path / "files") == ["a", "c"]


def test_torchrun_environment_picks_the_shard(tmp_path, monkeypatch):
    data = _dataset(tmp_path / "data")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "3")
    assert _run(str(data), "-o", str(tmp_path / "env"), *FAST, "-q") == 0
    assert _outputs(tmp_path / "env") == [sorted(MESHES)[1]]
    # --shard wins over the environment.
    assert _run(str(data), "-o", str(tmp_path / "given"), *FAST, "--shard", "0/4", "-q") == 0
    assert _outputs(tmp_path / "given") == [sorted(MESHES)[0]]


@pytest.mark.parametrize(
    ("environment", "message"),
    [({"RANK": "1"}, "WORLD_SIZE"), ({"RANK": "2", "WORLD_SIZE": "2"}, "RANK='2'")],
)
def test_a_bad_torchrun_environment_is_refused(tmp_path, monkeypatch, capsys, environment, message):
    data = _dataset(tmp_path / "data", ["a"])
    monkeypatch.delenv("WORLD_SIZE", raising=False)
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    assert _run(str(data), "-o", str(tmp_path / "out"), *FAST) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and message in lines[0]
    assert not (tmp_path / "out").exists()


def test_threads_are_shared_among_workers(monkeypatch):
    monkeypatch.setattr(features_command, "available_cpus", lambda: 8)
    share = features_command.threads_per_worker
    assert share(None, 2, {}) == 4
    assert share(None, 2, {"LOCAL_WORLD_SIZE": "2"}) == 2  # torchrun's processes on a machine
    assert share(4, 2, {"LOCAL_WORLD_SIZE": "2"}) == 2  # --threads is the whole process's
    assert share(32, 2, {}) == 4  # at most the CPUs
    assert share(3, 4, {}) == 1


# --------------------------------------------------------------------------------------------
# Errors


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--threshold", "0.01"], "threshold=0.01 does not apply to variant='robust'"),
        (["--variant", "robust", "-K", "99"], "num_scales"),
        (["--shard", "2/2"], "--shard: expected I/N with 0 <= I < N, got '2/2'"),
        (["--shard", "one/two"], "--shard: expected I/N such as 0/4"),
        (["--workers", "0"], "--workers: expected a positive integer"),
    ],
)
def test_refused_options_exit_2_before_any_work(tmp_path, capsys, args, message):
    data = _dataset(tmp_path / "data", ["a"])
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *args) == 2
    captured = capsys.readouterr()
    lines = _error_lines(captured.err)
    assert len(lines) == 1 and message in lines[0] and captured.out == ""
    assert not out.exists()


def test_one_bad_mesh_among_good_ones(tmp_path, capsys):
    data = _dataset(tmp_path / "data", ["a", "c"])
    (data / "b.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n")  # a face past the end
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST, "--ply") == 1
    captured = capsys.readouterr()
    errors = _error_lines(captured.err)
    assert len(errors) == 2
    assert str(data / "b.obj") in errors[0]
    assert "1 of 3 meshes failed" in errors[1]
    assert "2 computed, 0 already done, 1 failed" in captured.out
    assert _outputs(out) == _outputs(out, ".ply") == ["a", "c"]


def test_an_unexpected_error_on_one_mesh_does_not_stop_the_others(tmp_path, capsys, monkeypatch):
    data = _dataset(tmp_path / "data", ["a", "c"])
    compute = feature_jobs.compute_arrays

    def failing(source, *args):
        if source.stem == "c":
            raise RuntimeError("the solver did not converge")
        return compute(source, *args)

    monkeypatch.setattr(feature_jobs, "compute_arrays", failing)
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST) == 1
    errors = _error_lines(capsys.readouterr().err)
    assert "unexpected RuntimeError: the solver did not converge" in errors[0]
    assert _outputs(out) == ["a"]


@pytest.mark.parametrize("case", ["same-stem", "ply-into-input", "output-is-input", "no-meshes"])
def test_conflicting_inputs_and_outputs_are_refused(tmp_path, capsys, case):
    data = _dataset(tmp_path / "data", ["a", "sub/b"])
    out = tmp_path / "out"
    args = {
        "same-stem": [str(data / "a.obj"), str(_dataset(tmp_path / "other", ["a"]) / "a.obj")],
        "ply-into-input": [str(data), "--ply"],
        "output-is-input": [str(data / "sub" / "b.ply"), "--ply"],
        "no-meshes": [str(data / "sub" / "nothing")],
    }[case]
    if case == "output-is-input":
        out = data / "sub"
    elif case == "ply-into-input":
        out = data
    elif case == "no-meshes":
        (data / "sub" / "nothing").mkdir()
    message = {
        "same-stem": "would both be written to",
        "ply-into-input": "--ply into the input folder",
        "output-is-input": "is the input mesh",
        "no-meshes": "no mesh files",
    }[case]
    before = sorted(p.name for p in tmp_path.rglob("*"))
    assert _run(*args, "-o", str(out), *FAST) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and message in lines[0]
    assert sorted(p.name for p in tmp_path.rglob("*")) == before


def test_output_folder_inside_the_input_folder_is_not_searched(tmp_path, capsys):
    data = _dataset(tmp_path / "data", ["a"])
    out = data / "features"
    out.mkdir()
    (out / "x.ply").write_bytes((data / "a.obj").read_bytes())  # not an input: never read
    assert _run(str(data), "-o", str(out), *FAST) == 0
    assert "1 meshes in" in capsys.readouterr().out
    assert _outputs(out) == ["a"]


def test_ply_into_a_folder_under_the_input_is_refused(tmp_path, capsys):
    """Issue 32: ``features DIR -o DIR/feat --ply`` was accepted, and a later run with another
    -o read those PLY files as meshes."""
    data = _dataset(tmp_path / "data", ["a"])
    assert _run(str(data), "-o", str(data / "feat" / "deeper"), *FAST, "--ply") == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "--ply into the input folder" in lines[0]
    assert not (data / "feat").exists()


@pytest.mark.parametrize("where", ["input", "output"])
def test_an_empty_path_is_a_usage_error(tmp_path, capsys, monkeypatch, where):
    """Issue 32: ``-o ""`` wrote into the current folder, an input ``""`` walked all of it."""
    data = _dataset(tmp_path / "data", ["a"])
    monkeypatch.chdir(data)
    argv = ["", "-o", str(tmp_path / "out")] if where == "input" else [str(data), "-o", ""]
    assert _run(*argv, *FAST) == 2
    lines = _error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and "expected a path, got an empty one" in lines[0]
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a.obj", "data"]


def test_the_digest_is_of_the_bytes_parsed(tmp_path, monkeypatch):
    """Issue 32: a mesh rewritten in place while it was read left the features of one content
    under the digest of another, and a rerun skipped it for good."""
    import hashlib

    import stochlap_torch.mesh

    data = _dataset(tmp_path / "data", ["a"])
    source = data / "a.obj"
    first = source.read_bytes()
    load = stochlap_torch.mesh.load_mesh

    def rewritten_while_read(path, **options):
        bigger = icosphere(2)  # the file changes under the reader
        trimesh.Trimesh(bigger.vertices, bigger.faces, process=False).export(source)
        return load(path, **options)

    monkeypatch.setattr(stochlap_torch.mesh, "load_mesh", rewritten_while_read)
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST, "-q") == 0
    with np.load(out / "a.npz") as stored:
        digest, vertices = str(stored["source_sha256"]), stored["vertices"]
    assert digest == hashlib.sha256(first).hexdigest()
    assert len(vertices) == len(icosphere(1).vertices)  # the bytes hashed, not the new file
    monkeypatch.setattr(stochlap_torch.mesh, "load_mesh", load)
    assert _run(str(data), "-o", str(out), *FAST, "-q") == 0  # the rewritten file: recomputed
    with np.load(out / "a.npz") as stored:
        assert str(stored["source_sha256"]) == hashlib.sha256(source.read_bytes()).hexdigest()
        assert len(stored["vertices"]) == len(icosphere(2).vertices)


#: Put on PYTHONPATH by the next test: in a worker of ``stochlap features`` (not in the
#: command, which hashes the meshes to see which are done), hashing a mesh marks the worker
#: busy and then takes a minute (a long mesh).
_SLOW_JOBS = """
import hashlib, multiprocessing, os, sys, time
sha256 = hashlib.sha256
def slow(*args, **kwargs):
    caller = sys._getframe(1).f_globals.get("__name__")
    worker = multiprocessing.parent_process() is not None
    if worker and caller == "stochlap_torch.learning.feature_files":
        open(os.path.join(os.environ["BUSY_DIR"], str(os.getpid())), "w").close()
        time.sleep(60)
    return sha256(*args, **kwargs)
hashlib.sha256 = slow
"""


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc")
def test_workers_end_when_the_command_is_killed(tmp_path):
    """Issue 32: after ``kill -9`` of ``stochlap features --workers N`` (what an out-of-memory
    kill does) the workers ran on for minutes with no parent."""
    import signal

    data = _dataset(tmp_path / "data", ["a", "c", "sub/b"])
    hooks, busy = tmp_path / "hooks", tmp_path / "busy"
    hooks.mkdir()
    busy.mkdir()
    (hooks / "sitecustomize.py").write_text(_SLOW_JOBS)
    env = dict(os.environ, BUSY_DIR=str(busy))
    env["PYTHONPATH"] = os.pathsep.join([str(hooks), str(REPO_ROOT), env.get("PYTHONPATH", "")])
    argv = ["features", str(data), "-o", str(tmp_path / "out"), *FAST, "--workers", "2", "-q"]
    command = subprocess.Popen(
        [sys.executable, "-m", "stochlap_torch", *argv], env=env, stderr=subprocess.DEVNULL
    )
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 180
        while len(workers) < 2 and time.monotonic() < deadline and command.poll() is None:
            time.sleep(0.2)
            workers = [int(p.name) for p in busy.iterdir()]
        assert len(workers) == 2, command.poll()
        command.send_signal(signal.SIGKILL)
        command.wait()
        deadline = time.monotonic() + 10
        while any(map(_alive, workers)) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(map(_alive, workers))
    finally:
        for pid in filter(_alive, workers):
            os.kill(pid, signal.SIGKILL)
        if command.poll() is None:
            command.kill()


def test_features_help_does_not_import_torch():
    script = (
        "import sys\nfrom stochlap_torch.cli import main\n"
        "assert main(['features', '--help']) == 0\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'numpy')))\n"
    )
    env = dict(os.environ, PYTHONPATH=str(REPO_ROOT))
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, check=True
    )
    assert "--shard I/N" in result.stdout
    assert result.stdout.strip().splitlines()[-1] == "[]"


# --------------------------------------------------------------------------------------------
# save_ply: header comments, property names


def test_save_ply_header_comments(tmp_path):
    mesh = icosphere(1)
    path = save_ply(
        tmp_path / "m.ply",
        mesh.vertices,
        mesh.faces,
        scalars={"dn0": np.arange(42.0)},
        comments=["made by a test", '{"k": 2}'],
    )
    header = path.read_bytes().split(b"end_header")[0].decode().splitlines()
    assert header[:4] == [
        "ply",
        "format binary_little_endian 1.0",
        "comment made by a test",
        'comment {"k": 2}',
    ]
    loaded = trimesh.load(path, process=False)
    np.testing.assert_array_equal(loaded.metadata["_ply_raw"]["vertex"]["data"]["dn0"], range(42))


@pytest.mark.parametrize(
    ("comments", "scalars", "message"),
    [
        (["two\nlines"], {}, "one line"),
        ([], {"two words": np.zeros(42)}, "one word"),
        ([], {"": np.zeros(42)}, "one word"),
        ([], {"x": np.zeros(42)}, "taken"),
    ],
)
def test_save_ply_refuses_what_would_corrupt_the_header(tmp_path, comments, scalars, message):
    mesh = icosphere(1)
    with pytest.raises(ParameterError, match=message):
        save_ply(tmp_path / "m.ply", mesh.vertices, mesh.faces, scalars=scalars, comments=comments)
    assert not (tmp_path / "m.ply").exists()


def test_a_merged_file_keeps_the_map_back_to_its_vertices(tmp_path):
    """An STL's corners are merged into one surface; the ``.npz`` keeps which row of the
    features each of the file's vertices has."""
    data = _dataset(tmp_path / "data", ["d"])
    out = tmp_path / "out"
    assert _run(str(data), "-o", str(out), *FAST, "-q") == 0
    soup = trimesh.load(data / "d.stl", process=False)
    with np.load(out / "d.npz") as stored:
        file_vertices = stored["file_vertices"]
        assert file_vertices.shape == (len(soup.vertices),)
        np.testing.assert_array_equal(stored["vertices"][file_vertices], soup.vertices)
        assert stored["features"][file_vertices].shape[0] == len(soup.vertices)
