"""One mesh of ``stochlap features``: its output files, whether they are done, and the work.

A job runs in the command's process or in a worker process, so what it needs travels in a
picklable :class:`Job` and it returns an :class:`Outcome` rather than printing. Its ``.npz``
is written last, atomically like the PLY, so that it marks the mesh as done; an output counts
as done when it names the same settings and the same source bytes (SHA-256) and its arrays
have consistent shapes: other settings, or a changed mesh file, are recomputed.

The ``.npz`` arrays: ``features`` ``(V, C)`` float (``--dtype``), ``channel_names`` ``(C,)``
str, ``vertices`` ``(V, 3)`` float and ``faces`` ``(F, 3)`` int64 of the loaded mesh (after
``--merge-seams``: row ``i`` of ``features`` is vertex ``i`` of ``vertices``), ``settings``
(a JSON string: the method and every parameter, ``dtype``, ``merge_seams``),
``source_sha256`` and ``version`` (the library's, recorded but not compared).
"""

from __future__ import annotations

import dataclasses
import glob
import hashlib
import json
import os
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from .._common.files import atomic_write
from .._common.version import __version__
from .common import Terminated, describe_os_error, messages

#: Start of the PLY header comment that holds the settings and the source's digest.
COMMENT_PREFIX = "stochlap_torch features "
#: The arrays of a ``.npz`` whose headers :func:`_done_vertices` checks.
_ARRAYS = ("features", "channel_names", "vertices", "faces")
#: A temporary of an output untouched this long is a killed run's, not a live writer's.
STALE_SECONDS = 600.0


@dataclass(frozen=True)
class Job:
    """One mesh: its file, and the files it is written to (``ply`` ``None`` without ``--ply``)."""

    source: Path
    npz: Path
    ply: Path | None = None


@dataclass(frozen=True)
class Outcome:
    """``status`` ``"computed"``, ``"skipped"`` (already done) or ``"failed"`` (``message``)."""

    status: str
    message: str = ""


def settings_record(settings, dtype: str, merge_seams: bool) -> dict:
    """The JSON-ready settings of a run, everything the numbers depend on: the parameters
    object (its class names the method), the dtype and ``merge_seams``."""
    record = {"method": type(settings).__name__, **dataclasses.asdict(settings), "dtype": dtype}
    record["merge_seams"] = bool(merge_seams)
    # Through JSON once, so that it compares equal to what a file holds (tuples as lists).
    return json.loads(json.dumps(record, sort_keys=True))


def run_job(job: Job, settings, record: dict) -> Outcome:
    """Make ``job``'s outputs unless they are done (``record``: :func:`settings_record`); any
    problem with this mesh is a failed :class:`Outcome`: the others go on."""
    try:
        return _make_outputs(job, settings, record)
    except Exception as error:
        return Outcome("failed", _message(job.source, error))


def _make_outputs(job: Job, settings, record: dict) -> Outcome:
    data = job.source.read_bytes()  # read once: hashed, and parsed (_compute)
    digest = hashlib.sha256(data).hexdigest()
    done = _done_vertices(job.npz, record, digest)
    if done is not None:
        if job.ply is None or _ply_done(job.ply, record, digest, done):
            return Outcome("skipped")
        # Only the PLY is missing (an earlier run without --ply): written from the stored arrays.
        _write_ply(job.ply, _load_npz(job.npz), record, digest)
        return Outcome("computed")
    arrays = _compute(job.source, data, settings, record)
    if job.ply is not None:
        _write_ply(job.ply, arrays, record, digest)
    _write_npz(job.npz, arrays, record, digest)  # last: it marks the mesh as done
    return Outcome("computed")


def _compute(source: Path, data: bytes, settings, record: dict) -> dict:
    """``{"features", "channel_names", "vertices", "faces"}`` (NumPy) of the mesh file whose
    bytes are ``data``, and ``"file_vertices"`` when the file's corners were merged (a soup such
    as an STL, or ``--merge-seams``): the row of ``features`` of every vertex of the file.
    Parsed from a private copy of ``data``, so that a file rewritten meanwhile cannot leave
    other bytes' features under its digest; a ``.gltf`` in place (its buffers lie beside it)."""
    import tempfile

    import numpy as np
    import torch

    from ..features import channel_names, multiscale_features
    from ..mesh import load_mesh

    options = {"merge_seams": record["merge_seams"], "dtype": getattr(torch, record["dtype"])}
    if source.suffix.lower() == ".gltf":
        mesh = load_mesh(source, **options)
    else:
        with tempfile.TemporaryDirectory(prefix="stochlap-") as folder:
            copy = Path(folder, source.name)
            copy.write_bytes(data)
            try:
                mesh = load_mesh(copy, **options)
            except Exception as error:  # named by the user's file, not the copy
                error.args = tuple(
                    arg.replace(str(copy), str(source)) if isinstance(arg, str) else arg
                    for arg in error.args
                )
                if isinstance(error, OSError) and error.filename == str(copy):
                    error.filename = str(source)
                raise
    with torch.no_grad():
        features = multiscale_features(mesh.vertices, mesh.faces, params=settings)
    arrays = {
        "features": features.detach().cpu().numpy(),
        "channel_names": np.array(channel_names(settings), dtype=str),
        "vertices": mesh.vertices.detach().cpu().numpy(),
        "faces": mesh.faces.detach().cpu().numpy(),
    }
    if mesh.file_vertices is not None:
        arrays["file_vertices"] = mesh.file_vertices.cpu().numpy()
    return arrays


def _json(record: dict) -> str:
    return json.dumps(record, sort_keys=True)


def _comment(record: dict, digest: str) -> str:
    return COMMENT_PREFIX + _json({"settings": record, "source_sha256": digest})


def _write_npz(path: Path, arrays: dict, record: dict, digest: str) -> None:
    import numpy as np

    _remove_stale_temporaries(path)
    meta = {"settings": _json(record), "source_sha256": digest, "version": __version__}
    with atomic_write(path, "wb") as handle:
        np.savez(handle, **arrays, **{name: np.array(text) for name, text in meta.items()})


def _write_ply(path: Path, arrays: dict, record: dict, digest: str) -> None:
    """The mesh with one float vertex property per channel and the settings as a comment."""
    from ..mesh import save_ply

    _remove_stale_temporaries(path)
    features = arrays["features"]
    scalars = {str(name): features[:, c] for c, name in enumerate(arrays["channel_names"])}
    comments = [_comment(record, digest)]
    save_ply(path, arrays["vertices"], arrays["faces"], scalars=scalars, comments=comments)


def _done_vertices(path: Path, record: dict, digest: str) -> int | None:
    """The vertex count of a done ``.npz`` (these settings, this digest, arrays of consistent
    shapes), else ``None``. Only the small members and the arrays' headers are read (a file
    is whole or absent), so a resumption does not read a dataset's features again."""
    import zipfile

    import numpy as np
    from numpy.lib import format as npy

    if not path.is_file():
        return None  # nothing there, or a node that is not a file (the write refuses it)

    def header(archive, name: str):
        with archive.open(f"{name}.npy") as member:
            version = npy.read_magic(member)
            read = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
            shape, _, dtype = read(member)
        return shape, dtype

    def text(archive, name: str) -> str:
        with archive.open(f"{name}.npy") as member:
            return str(npy.read_array(member, allow_pickle=False))

    try:
        with zipfile.ZipFile(path) as archive:
            if json.loads(text(archive, "settings")) != record:
                return None
            if text(archive, "source_sha256") != digest:
                return None
            (features, dtype), (names, _), (vertices, _), (faces, _) = (
                header(archive, name) for name in _ARRAYS
            )
    except Exception:  # damaged in any of many ways (zip, header, JSON, a member): not done
        return None
    if (len(names), len(vertices), len(faces)) != (1, 2, 2) or (vertices[1], faces[1]) != (3, 3):
        return None
    consistent = features == (vertices[0], names[0]) and dtype == np.dtype(record["dtype"])
    return vertices[0] if consistent else None


def _load_npz(path: Path) -> dict:
    """The arrays of a done ``.npz``, to write its PLY from."""
    import numpy as np

    # Opened here: np.load leaves a file it opened itself open when the archive is damaged.
    with open(path, "rb") as handle, np.load(handle, allow_pickle=False) as data:
        return {name: data[name] for name in _ARRAYS}


def _ply_done(path: Path, record: dict, digest: str, num_vertices: int) -> bool:
    """Whether the PLY header holds this run's comment and vertex count (a PLY is written
    whole or not at all, so a right header means a right file)."""
    if not path.is_file():
        return False
    try:
        with open(path, "rb") as handle:
            header = handle.read(1 << 16)
    except OSError:
        return False
    end = header.find(b"end_header")
    lines = header[: max(end, 0)].decode("utf-8", errors="replace").splitlines()
    comment = f"comment {_comment(record, digest)}"
    return comment in lines and f"element vertex {num_vertices}" in lines


def _remove_stale_temporaries(path: Path) -> None:
    """Remove the temporaries (``.<name>.*.tmp``) of ``path`` that a killed run left, only
    :data:`STALE_SECONDS` old ones (another run may be writing it right now)."""
    target = Path(os.path.realpath(path))
    if target.parent.is_dir():
        now = time.time()
        for leftover in target.parent.glob(f".{glob.escape(target.name)}.*.tmp"):
            try:
                if now - leftover.stat().st_mtime > STALE_SECONDS:
                    leftover.unlink(missing_ok=True)
            except OSError:  # gone meanwhile: its writer finished or cleaned up
                pass


def _message(source: Path, error: Exception) -> str:
    """``<source>: <reason>`` in one line (the reason alone when it names the file already);
    an unexpected error (not the library's, nor the system's) is named by its type."""
    from .._common.errors import StochlapError

    reason = describe_os_error(error) if isinstance(error, OSError) else str(error)
    reason = " ".join((reason or type(error).__name__).split())
    if not isinstance(error, (StochlapError, OSError, MemoryError)):
        reason = f"unexpected {type(error).__name__}: {reason}"
    return reason if reason.startswith(str(source)) else f"{source}: {reason}"


class _WorkerState:
    busy = False
    messages = None  # the worker's message settings, entered for the process's life


def init_worker(threads: int, verbose: bool, parent: int) -> None:
    """Set up a worker process: ``threads`` torch threads, library messages as the command
    prints them, SIGINT left to the command (which stops the workers), SIGTERM ending the
    worker (a write in progress removes its temporary), and an end when the process
    ``parent`` is gone (killed by SIGKILL or for memory)."""
    import torch

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_terminate)
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()
    torch.set_num_threads(threads)
    _WorkerState.messages = messages(verbose)
    _WorkerState.messages.__enter__()


def _watch_parent(parent: int) -> None:
    """Once the parent is gone, SIGTERM this worker, and exit for sure a few seconds later if
    a long native call delays the handler."""
    while os.getppid() == parent:
        time.sleep(0.25)
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(3.0)
    os._exit(128 + signal.SIGTERM)


def _on_terminate(signum, frame) -> None:
    if _WorkerState.busy:
        raise Terminated(signum)  # unwinds the job: atomic_write removes its temporary
    os._exit(128 + signum)


def run_job_in_worker(job: Job, settings, record: dict) -> Outcome:
    """:func:`run_job` in a worker process set up by :func:`init_worker`."""
    _WorkerState.busy = True
    try:
        return run_job(job, settings, record)
    except Terminated as stop:
        os._exit(128 + stop.signum)
    finally:
        _WorkerState.busy = False
