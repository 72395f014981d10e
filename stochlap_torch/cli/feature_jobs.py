"""One mesh of ``stochlap features``: whether its outputs are done, and the work.

A job runs in the command's process or in a worker process, so what it needs travels in a
picklable :class:`Job` and it returns an :class:`Outcome` rather than printing. Its ``.npz``
(the format, and what makes it done: :mod:`stochlap_torch.learning.feature_files`) is written
last, atomically like the PLY, so that it marks the mesh as done.
"""

from __future__ import annotations

import json
import os
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from ..learning.feature_files import (
    compute_arrays,
    feature_file_status,
    read_arrays,
    remove_stale_temporaries,
    source_digest,
    write_feature_file,
)
from .common import Terminated, describe_os_error, messages

#: Start of the PLY header comment that holds the settings and the source's digest.
COMMENT_PREFIX = "stochlap_torch features "


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


def is_done(job: Job, record: dict) -> bool:
    """Whether ``job``'s outputs are done for ``record`` (hashing the mesh file and reading
    the outputs' headers only: no torch); a file that cannot be read is not done."""
    try:
        digest = source_digest(job.source.read_bytes())
    except OSError:
        return False
    status = feature_file_status(job.npz, record, digest)
    return status.done and (job.ply is None or _ply_done(job.ply, record, digest, status))


def run_job(job: Job, settings, record: dict) -> Outcome:
    """Make ``job``'s outputs unless they are done (``record``:
    :func:`~stochlap_torch.learning.feature_files.settings_record`); any problem with this
    mesh is a failed :class:`Outcome`: the others go on."""
    try:
        return _make_outputs(job, settings, record)
    except Exception as error:
        return Outcome("failed", _message(job.source, error))


def _make_outputs(job: Job, settings, record: dict) -> Outcome:
    data = job.source.read_bytes()  # read once: hashed, and parsed (compute_arrays)
    digest = source_digest(data)
    status = feature_file_status(job.npz, record, digest)
    if status.done:
        if job.ply is None or _ply_done(job.ply, record, digest, status):
            return Outcome("skipped")
        # Only the PLY is missing (an earlier run without --ply): written from the stored arrays.
        _write_ply(job.ply, read_arrays(job.npz), record, digest)
        return Outcome("computed")
    arrays = compute_arrays(job.source, settings, record, data)
    if job.ply is not None:
        _write_ply(job.ply, arrays, record, digest)
    write_feature_file(job.npz, arrays, record, digest)  # last: it marks the mesh as done
    return Outcome("computed")


def _comment(record: dict, digest: str) -> str:
    return COMMENT_PREFIX + json.dumps(
        {"settings": record, "source_sha256": digest}, sort_keys=True
    )


def _write_ply(path: Path, arrays: dict, record: dict, digest: str) -> None:
    """The mesh with one float vertex property per channel and the settings as a comment."""
    from ..mesh import save_ply

    remove_stale_temporaries(path)
    features = arrays["features"]
    scalars = {str(name): features[:, c] for c, name in enumerate(arrays["channel_names"])}
    comments = [_comment(record, digest)]
    save_ply(path, arrays["vertices"], arrays["faces"], scalars=scalars, comments=comments)


def _ply_done(path: Path, record: dict, digest: str, status) -> bool:
    """Whether the PLY header holds this run's comment and the vertex count of the done
    ``.npz`` (a PLY is written whole or not at all, so a right header means a right file)."""
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
    return comment in lines and f"element vertex {status.num_vertices}" in lines


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
