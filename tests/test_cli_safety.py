"""The ``stochlap`` tool never overwrites an input or leaves a half-written output, and reports
user errors (only those) as one line with exit status 2."""

from __future__ import annotations

import io
import os
import signal
import stat
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import pytest

import stochlap_torch as sl
from stochlap_torch import cli
from stochlap_torch._common.errors import FileFormatError, MeshError
from stochlap_torch._common.files import NotARegularFileError, atomic_write
from stochlap_torch.cli import app, common
from stochlap_torch.cli import interest as interest_command
from stochlap_torch.cli.common import Terminated

SPOT = sl.bundled_mesh_path("spot")
REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def workdir(tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def mesh_copy(workdir) -> Path:
    """A copy of the bundled cow, ``in.obj``, in the working directory."""
    path = workdir / "in.obj"
    path.write_bytes(SPOT.read_bytes())
    return path


def _one_error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("stochlap: error: ")
    return lines[0]


# --------------------------------------------------------------------------------------------
# Inputs are never outputs


@pytest.mark.parametrize(
    "args",
    [
        ["saliency", "in.obj", "-o", "in.obj"],
        ["saliency", "in.obj", "--png", "in.obj"],
        ["saliency", "in.obj", "--png", "./sub/../in.obj"],
        ["interest", "in.obj", "-o", "in.obj"],
        ["interest", "in.obj", "--png", "link.obj"],
        ["saliency", "in.obj", "-o", "link.obj"],
    ],
)
def test_an_output_that_is_the_input_is_refused_before_any_work(mesh_copy, capsys, args):
    (mesh_copy.parent / "sub").mkdir()
    (mesh_copy.parent / "link.obj").symlink_to(mesh_copy)
    before = mesh_copy.read_bytes()
    assert cli.main(args) == 2
    captured = capsys.readouterr()
    assert "refusing to overwrite" in _one_error_line(captured.err)
    assert captured.out == ""  # not even loaded
    assert mesh_copy.read_bytes() == before
    assert sorted(p.name for p in mesh_copy.parent.iterdir()) == ["in.obj", "link.obj", "sub"]


def test_multiscale_files_may_not_be_the_input(mesh_copy, capsys):
    out = mesh_copy.parent / "ms"
    out.mkdir()
    (out / "in_k02.ply").symlink_to(mesh_copy)
    before = mesh_copy.read_bytes()
    assert cli.main(["multiscale", "in.obj", "-o", "ms", "-K", "3"]) == 2
    assert "in_k02.ply" in _one_error_line(capsys.readouterr().err)
    assert mesh_copy.read_bytes() == before


@pytest.mark.parametrize(
    "args, message",
    [
        (["saliency", "-o", "same.x", "--png", "same.x"], "same file"),
        (["interest", "-o", "pics/../p.txt", "--png", "p.txt"], "same file"),
        (["saliency", "-o", "."], "is a directory"),
        (["multiscale", "-o", "in.obj"], "not a directory"),
    ],
)
def test_conflicting_outputs_are_refused(mesh_copy, capsys, args, message):
    (mesh_copy.parent / "pics").mkdir()
    assert cli.main(args) == 2
    assert message in _one_error_line(capsys.readouterr().err)


# --------------------------------------------------------------------------------------------
# Failed writes keep the previous file


def _temporaries(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if p.name.endswith(".tmp")]


def test_failed_png_write_keeps_the_previous_picture(workdir, capsys, monkeypatch):
    pytest.importorskip("matplotlib")
    from PIL import Image

    assert cli.main(["saliency", "-K", "3", "-q"]) == 0
    png = workdir / "spot_saliency.png"
    good = png.read_bytes()

    real_save = Image.Image.save

    def half_then_full_disk(self, fp, *args, **kwargs):
        if isinstance(fp, io.BytesIO):  # matplotlib's own drawing, in memory
            return real_save(self, fp, *args, **kwargs)
        fp.write(good[:1000])
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Image.Image, "save", half_then_full_disk)
    assert cli.main(["saliency", "-K", "3", "-q"]) == 2
    line = _one_error_line(capsys.readouterr().err)
    assert "spot_saliency.png" in line and "No space left on device" in line
    assert png.read_bytes() == good
    assert not _temporaries(workdir)


def test_failed_points_write_keeps_the_previous_file(workdir, capsys, monkeypatch):
    assert cli.main(["interest", "-K", "3", "--no-png", "-q"]) == 0
    points = workdir / "spot_interest.txt"
    good = points.read_bytes()
    calls = []

    def fail_on_third(*args):
        calls.append(args)
        if len(calls) == 3:
            raise OSError(5, "Input/output error")
        return real_line(*args)

    real_line = interest_command.point_line
    monkeypatch.setattr(interest_command, "point_line", fail_on_third)
    assert cli.main(["interest", "-K", "3", "--no-png", "-q"]) == 2
    assert len(calls) == 3  # two lines were written before the failure
    assert "spot_interest.txt: Input/output error" in _one_error_line(capsys.readouterr().err)
    assert points.read_bytes() == good
    assert not _temporaries(workdir)


# --------------------------------------------------------------------------------------------
# Which errors are the user's


@pytest.fixture
def handler_runs(monkeypatch):
    """``handler_runs(handler)``: make ``stochlap info x.obj`` run ``handler(args)``."""

    def install(handler):
        parser = app.build_parser()
        parse_args = parser.parse_args

        def parse_with_handler(argv):
            args = parse_args(argv)
            args.handler = handler
            return args

        monkeypatch.setattr(parser, "parse_args", parse_with_handler)
        monkeypatch.setattr(app, "build_parser", lambda: parser)

    return install


def _raise(exc: BaseException):
    def handler(args):
        raise exc

    return handler


@pytest.mark.parametrize(
    "exc, status, text",
    [
        (MeshError("bad mesh\nsecond line"), 2, "stochlap: error: bad mesh second line"),
        (FileFormatError("t.txt:3: not a number"), 2, "stochlap: error: t.txt:3: not a number"),
        (common.CommandError("nope"), 2, "stochlap: error: nope"),
        (FileNotFoundError(2, "No such file or directory", "m.obj"), 2, "m.obj: No such file"),
        (PermissionError(13, "Permission denied", "out.ply"), 2, "out.ply: Permission denied"),
        (
            OSError(18, "Invalid cross-device link", "a", None, "b"),
            2,
            "a -> b: Invalid cross-device",
        ),
        (KeyboardInterrupt(), 130, "stochlap: interrupted"),
        (Terminated(signal.SIGTERM), 143, "stochlap: terminated by SIGTERM"),
    ],
)
def test_user_errors_are_one_line(handler_runs, capsys, exc, status, text):
    handler_runs(_raise(exc))
    assert cli.main(["info", "x.obj"]) == status
    captured = capsys.readouterr()
    lines = [line for line in captured.err.splitlines() if line]
    assert len(lines) == 1 and text in lines[0], captured.err


@pytest.mark.parametrize(
    "exc", [ValueError("a bug"), RuntimeError("a bug"), ImportError("a bug"), MemoryError("a bug")]
)
def test_bugs_are_not_usage_errors(handler_runs, exc):
    # Only the library's own errors are the user's: a plain exception is a traceback.
    handler_runs(_raise(exc))
    with pytest.raises(type(exc), match="a bug"):
        cli.main(["info", "x.obj"])


def test_library_warnings_are_one_line_each(handler_runs, capsys):
    import warnings

    def handler(args):
        for _ in range(3):
            warnings.warn("first\nline", UserWarning, stacklevel=1)
        return 0

    handler_runs(handler)
    assert cli.main(["info", "x.obj"]) == 0
    assert capsys.readouterr().err == "stochlap: warning: UserWarning: first line\n"


def test_argparse_errors_are_one_line(capsys):
    for args in (["saliency", "--no-such-option"], ["saliency", "-K", "x"], ["nope"], []):
        assert cli.main(args) == 2
        line = _one_error_line(capsys.readouterr().err)
        assert "--help" in line


def test_signed_up_axis(workdir):
    pytest.importorskip("matplotlib")
    for up in (["--up", "-y"], ["--up=-z"], ["--up", "x"]):
        assert cli.main(["saliency", "-K", "3", "-q", "--png", "s.png", *up]) == 0
    assert cli.main(["saliency", "--up", "w"]) == 2


def test_environment_untouched_after_a_run(workdir):
    import logging

    library = logging.getLogger("stochlap_torch")
    handlers, level = list(library.handlers), library.level
    dispositions = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)}
    assert cli.main(["info", "-v", str(SPOT)]) == 0
    assert library.handlers == handlers and library.level == level
    assert {s: signal.getsignal(s) for s in dispositions} == dispositions
    assert os.getcwd() == str(workdir)


def test_signals_are_taken_only_while_a_command_runs_and_only_from_their_default(handler_runs):
    during = {}

    def handler(args):
        during.update({s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGHUP)})
        return 0

    handler_runs(handler)
    # As under nohup: an ignored SIGHUP stays ignored.
    previous = {
        signal.SIGTERM: signal.signal(signal.SIGTERM, signal.SIG_DFL),
        signal.SIGHUP: signal.signal(signal.SIGHUP, signal.SIG_IGN),
    }
    try:
        assert cli.main(["info", "x.obj"]) == 0
        assert callable(during[signal.SIGTERM]) and during[signal.SIGHUP] is signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        for signum, disposition in previous.items():
            signal.signal(signum, disposition)


def test_failed_ply_write_keeps_the_previous_mesh(workdir, capsys, monkeypatch):
    assert cli.main(["saliency", "-K", "3", "--no-png", "-q"]) == 0
    ply = workdir / "spot_saliency.ply"
    good = ply.read_bytes()

    def full_disk(fd):  # the bytes are in the temporary file; the flush to disk fails
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    assert cli.main(["saliency", "-K", "4", "--no-png", "-q"]) == 2
    assert "No space left on device" in _one_error_line(capsys.readouterr().err)
    assert ply.read_bytes() == good
    assert not _temporaries(workdir)


def test_float32_mesh_is_checked_in_float32(workdir, capsys):
    # Coordinates beyond float32's range: a valid mesh in float64, not in float32.
    path = workdir / "large.obj"
    path.write_text("v 0 0 0\nv 1e39 0 0\nv 0 1e39 0\nf 1 2 3\n")
    assert cli.main(["info", str(path)]) == 0
    capsys.readouterr()
    assert cli.main(["saliency", str(path), "--no-png", "--dtype", "float32"]) == 2
    captured = capsys.readouterr()
    assert "large.obj" in _one_error_line(captured.err) and captured.out == ""
    assert not list(workdir.glob("*.ply"))


def test_version(capsys):
    from stochlap_torch._common.version import __version__

    assert cli.main(["--version"]) == 0
    assert capsys.readouterr().out == f"stochlap {__version__}\n"


# --------------------------------------------------------------------------------------------
# Outputs that are not regular files, links, permissions, signals


@pytest.fixture
def confined_writes(tmp_path, monkeypatch):
    """Temporary files may be created, and files replaced, only inside ``tmp_path`` (else the
    test fails): a broken check must never touch the real ``/dev/null`` (tests may run as
    root)."""
    root = os.path.realpath(tmp_path)

    def check_inside(path) -> None:
        if os.path.commonpath([root, os.path.realpath(path)]) != root:
            raise AssertionError(f"a write reached {path}")

    real_replace, real_mkstemp = os.replace, tempfile.mkstemp

    def replace(source, destination, *args, **kwargs):
        check_inside(destination)
        return real_replace(source, destination, *args, **kwargs)

    def mkstemp(*args, dir=None, **kwargs):
        check_inside(os.getcwd() if dir is None else dir)
        return real_mkstemp(*args, dir=dir, **kwargs)

    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    yield
    assert stat.S_ISCHR(os.stat("/dev/null").st_mode)


def _fifo(path: Path) -> Path:
    os.mkfifo(path)
    return path


def _dev_null_link(path: Path) -> Path:
    path.symlink_to("/dev/null")
    return path


def _is_fifo(path: Path) -> bool:
    return stat.S_ISFIFO(os.lstat(path).st_mode)


@pytest.mark.parametrize("make", [_fifo, _dev_null_link], ids=["fifo", "link-to-dev-null"])
def test_atomic_write_refuses_a_node_that_is_not_a_regular_file(tmp_path, confined_writes, make):
    node = make(tmp_path / "out.bin")
    entered = []
    with pytest.raises(NotARegularFileError, match=r"out\.bin.* not a regular file"):
        with atomic_write(node) as handle:
            entered.append(handle)  # the content is not even computed
    assert not entered
    assert _is_fifo(node) or os.readlink(node) == "/dev/null"
    assert sorted(tmp_path.iterdir()) == [node]


def test_atomic_write_refuses_a_fifo_that_appears_during_the_write(tmp_path, confined_writes):
    path = tmp_path / "out.bin"
    with pytest.raises(NotARegularFileError, match="is a FIFO"):
        with atomic_write(path) as handle:
            handle.write(b"data")
            os.mkfifo(path)  # e.g. while the command computed
    assert _is_fifo(path)
    assert sorted(tmp_path.iterdir()) == [path]


def test_atomic_write_goes_through_a_symbolic_link(tmp_path):
    (tmp_path / "kept").mkdir()
    target = tmp_path / "kept" / "data.txt"
    target.write_bytes(b"old\n")
    link = tmp_path / "link.txt"
    link.symlink_to(Path("kept") / "data.txt")
    with atomic_write(link) as handle:
        handle.write(b"new\n")
    assert link.is_symlink() and os.readlink(link) == str(Path("kept") / "data.txt")
    assert target.read_bytes() == b"new\n"
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["data.txt", "kept", "link.txt"]


@pytest.mark.parametrize("mode", [0o600, 0o640, 0o755])
def test_atomic_write_keeps_the_permissions_of_the_file_it_replaces(tmp_path, mode):
    path = tmp_path / "out.txt"
    path.write_bytes(b"old\n")
    path.chmod(mode)
    with atomic_write(path) as handle:
        handle.write(b"new\n")
    assert path.read_bytes() == b"new\n"
    assert stat.S_IMODE(path.stat().st_mode) == mode


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="needs root")
def test_atomic_write_keeps_the_owner_of_the_file_it_replaces(tmp_path):
    path = tmp_path / "out.txt"
    path.write_bytes(b"old\n")
    os.chown(path, 12345, 23456)
    with atomic_write(path) as handle:
        handle.write(b"new\n")
    assert (path.stat().st_uid, path.stat().st_gid) == (12345, 23456)


@pytest.mark.parametrize(
    "args, make, node",
    [
        (["saliency", "in.obj", "-o", "node"], _fifo, "node"),
        (["saliency", "in.obj", "--png", "node"], _fifo, "node"),
        (["interest", "in.obj", "-o", "node"], _dev_null_link, "node"),
        (["interest", "in.obj", "--png", "node"], _dev_null_link, "node"),
        (["multiscale", "in.obj", "-o", "ms", "-K", "3"], _fifo, "ms/in_k02.ply"),
        (["evaluate", "in.obj", "truth.txt", "--json", "node"], _fifo, "node"),
    ],
)
def test_outputs_that_are_not_regular_files_are_refused_before_any_work(
    mesh_copy, capsys, confined_writes, args, make, node
):
    (mesh_copy.parent / "ms").mkdir()
    make(mesh_copy.parent / node)
    before = sorted(mesh_copy.parent.rglob("*"))
    assert cli.main(args) == 2
    captured = capsys.readouterr()
    line = _one_error_line(captured.err)
    assert node in line and "not a regular file; refusing to replace it" in line
    assert captured.out == ""  # not even loaded
    assert sorted(mesh_copy.parent.rglob("*")) == before
    assert _is_fifo(mesh_copy.parent / node) or os.readlink(mesh_copy.parent / node)


def test_a_node_that_appears_while_computing_is_not_replaced(
    workdir, capsys, confined_writes, monkeypatch
):
    real_line = interest_command.point_line

    def fifo_first(*args):
        if not (workdir / "points.txt").exists():
            os.mkfifo(workdir / "points.txt")
        return real_line(*args)

    monkeypatch.setattr(interest_command, "point_line", fifo_first)
    assert cli.main(["interest", "-K", "3", "--no-png", "-q", "-o", "points.txt"]) == 2
    assert "points.txt is a FIFO" in _one_error_line(capsys.readouterr().err)
    assert _is_fifo(workdir / "points.txt")
    assert not _temporaries(workdir)


def test_an_output_link_stays_a_link_and_its_file_keeps_its_permissions(workdir):
    (workdir / "kept").mkdir()
    points = workdir / "kept" / "points.txt"
    points.write_text("old\n")
    points.chmod(0o600)
    (workdir / "points.txt").symlink_to(points)
    assert cli.main(["interest", "-K", "3", "--no-png", "-q", "-o", "points.txt"]) == 0
    assert (workdir / "points.txt").is_symlink()
    assert points.read_text().startswith("# vertex x y z saliency")
    assert stat.S_IMODE(points.stat().st_mode) == 0o600
    assert not _temporaries(workdir)


# A stochlap run in its own process that sends itself SIGNUM while it writes the points file,
# after two of its lines.
_SIGNAL_DURING_WRITE = """
import os, signal, sys
from stochlap_torch import cli
from stochlap_torch.cli import interest

signal.signal({signum}, signal.SIG_DFL)  # as from a shell, even under nohup
real_line, calls = interest.point_line, []

def signal_on_third(*args):
    calls.append(args)
    if len(calls) == 3:
        os.kill(os.getpid(), {signum})
    return real_line(*args)

interest.point_line = signal_on_third
sys.exit(cli.main(["interest", "-K", "3", "--no-png", "-q", "-o", "points.txt"]))
"""


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_signal_during_a_write_leaves_no_temporary(tmp_path, signum):
    (tmp_path / "points.txt").write_text("old\n")
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    result = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(_SIGNAL_DURING_WRITE.format(signum=int(signum)))],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert result.returncode == 128 + signum, result.stderr
    name = signal.Signals(signum).name
    assert result.stderr.splitlines()[-1] == f"stochlap: terminated by {name}"
    assert (tmp_path / "points.txt").read_text() == "old\n"
    assert not _temporaries(tmp_path)


def test_atomic_write_never_changes_the_process_umask(tmp_path, monkeypatch):
    """The umask is process-wide: reading it by setting it would let another thread create a
    file under the value set meanwhile."""
    calls = []
    real = os.umask
    umask = real(0o022)
    real(umask)

    def spy(mask):
        calls.append(mask)
        return real(mask)

    monkeypatch.setattr(os, "umask", spy)
    with atomic_write(tmp_path / "new.txt", "w") as handle:
        handle.write("x")
    assert calls == []
    assert stat.S_IMODE((tmp_path / "new.txt").stat().st_mode) == 0o666 & ~umask
