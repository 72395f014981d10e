"""``stochlap features``: per-vertex multiscale features of every mesh of a dataset, to files.

Compute the (V, C) per-vertex features of every mesh file in the folders (searched
recursively) and files given, and write OUTDIR/<name>.npz for each, with --ply also
OUTDIR/<name>.ply (one float vertex property per channel). Meshes already done with the same
settings are skipped, so a rerun resumes an interrupted one; --shard I/N (under torchrun:
RANK/WORLD_SIZE) splits the meshes across machines. A mesh that fails is reported on one line
and the others go on; the exit status is then 1.

Names: a file found in folder DIR at DIR/a/b.obj is written as OUTDIR/a/b.npz, a file named
on the command line as OUTDIR/<stem>.npz; two meshes that would share a name are refused
before any work. The folder walk does not follow links to folders, and leaves out OUTDIR when
it lies inside a folder searched. The arrays of the ``.npz`` and what makes a mesh "done":
:mod:`.feature_jobs`.

Shards: the meshes sorted by output name, mesh ``k`` goes to shard ``k mod N``, the same on
every machine given the same inputs. Workers: ``--workers N`` processes (started fresh, not
forked: torch's threads do not survive a fork), each with ``--threads / N`` torch threads
(default: the CPUs this process may use, divided among torchrun's processes on the machine).
"""

from __future__ import annotations

import os
import sys
import time
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path

from .._common.cpus import available_cpus
from .._common.variants import (
    DEFAULT_FEATURE_VARIANT,
    DEFAULT_THRESHOLD,
    FEATURE_VARIANTS,
    PAPER_FEATURE_SCALES,
    ROBUST_NUM_SCALES,
)
from . import common, options
from .feature_jobs import Job, Outcome

NAME = "features"
HELP = "per-vertex multiscale features of every mesh of a dataset, to .npz files"
DESCRIPTION = __doc__.split("\n\n")[1]


def add_arguments(parser) -> None:
    parser.add_argument(
        "inputs",
        type=options.path,
        nargs="+",
        metavar="DIR_OR_FILE",
        help="mesh files, or folders searched recursively for .obj .off .ply .stl .glb .gltf",
    )
    parser.add_argument(
        "-o",
        "--output",
        type=options.path,
        required=True,
        metavar="OUTDIR",
        help="output folder (created)",
    )
    parser.add_argument(
        "--variant",
        choices=FEATURE_VARIANTS,
        default=DEFAULT_FEATURE_VARIANT,
        help=f"feature channels (default: {DEFAULT_FEATURE_VARIANT}, the same for the same "
        "surface meshed twice; paper: the coefficients and differences of the paper's "
        "Algorithm 1)",
    )
    parser.add_argument(
        "-K",
        "--num-scales",
        type=options.positive_int,
        metavar="K",
        help=f"number of scales (default: {ROBUST_NUM_SCALES} for robust, "
        f"{PAPER_FEATURE_SCALES} for paper)",
    )
    parser.add_argument(
        "--threshold",
        type=options.open_unit,
        metavar="LAMBDA",
        help=f"precision lambda in (0, 1) (the paper variant only; default: {DEFAULT_THRESHOLD:g})",
    )
    parser.add_argument(
        "--dtype",
        choices=options.DTYPES,
        default="float64",
        help="floating-point type of the computation and of the stored features (default: float64)",
    )
    parser.add_argument(
        "--merge-seams",
        action="store_true",
        help="merge vertices at identical positions (texture/normal seams) before processing",
    )
    parser.add_argument(
        "--ply",
        action="store_true",
        help="also write OUTDIR/<name>.ply with one float vertex property per channel",
    )
    parser.add_argument(
        "--workers",
        type=options.positive_int,
        default=1,
        metavar="N",
        help="worker processes (default: 1, in this process)",
    )
    parser.add_argument(
        "--shard",
        type=shard,
        metavar="I/N",
        help="process only shard I of N (0 <= I < N); default: torchrun's RANK/WORLD_SIZE "
        "when set, else every mesh",
    )


def add_parser(commands, parents):
    return options.add_command(commands, parents, NAME, HELP, DESCRIPTION, run, add_arguments)


# --------------------------------------------------------------------------------------------
# Shards and threads


def shard(text: str) -> tuple[int, int]:
    """``--shard I/N`` as ``(I, N)`` with ``0 <= I < N`` (an argparse ``type``)."""
    import argparse

    index, _, count = text.partition("/")
    try:
        index, count = int(index), int(count)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N such as 0/4, got {text!r}") from None
    if not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"expected I/N with 0 <= I < N, got {text!r}")
    return index, count


def shard_from_environment(environ: Mapping[str, str]) -> tuple[int, int]:
    """``(RANK, WORLD_SIZE)`` as torchrun sets them, or ``(0, 1)`` when neither is set.

    Raises:
        CommandError: only one is set, or they are not integers with ``0 <= RANK <
            WORLD_SIZE``.
    """
    rank, size = environ.get("RANK"), environ.get("WORLD_SIZE")
    if rank is None and size is None:
        return 0, 1
    if rank is None or size is None:
        missing = "RANK" if rank is None else "WORLD_SIZE"
        raise common.CommandError(
            f"the environment sets {'WORLD_SIZE' if rank is None else 'RANK'} but not "
            f"{missing}: set both (torchrun does), or pass --shard I/N"
        )
    try:
        index, count = int(rank), int(size)
    except ValueError:
        index = count = -1
    if not 0 <= index < count:
        raise common.CommandError(
            f"RANK={rank!r} and WORLD_SIZE={size!r} in the environment are not a shard "
            "(integers, 0 <= RANK < WORLD_SIZE); pass --shard I/N to choose one"
        )
    return index, count


def threads_per_worker(threads: int | None, workers: int, environ: Mapping[str, str]) -> int:
    """Torch threads of each of ``workers`` processes: ``--threads`` (at most the CPUs) shared
    among them, else the CPUs this process may use shared among them and among torchrun's
    processes on this machine (``LOCAL_WORLD_SIZE``); at least 1."""
    cpus = available_cpus()
    total = min(threads, cpus) if threads is not None else cpus // _local_processes(environ)
    return max(1, total // workers)


def _local_processes(environ: Mapping[str, str]) -> int:
    try:
        return max(1, int(environ.get("LOCAL_WORLD_SIZE", "1")))
    except ValueError:  # not torchrun's: ignored like an unset variable
        return 1


# --------------------------------------------------------------------------------------------
# The meshes and their outputs


def find_jobs(inputs: Sequence[str], out_dir: Path, ply: bool) -> list[Job]:
    """The :class:`~.feature_jobs.Job` of every mesh of ``inputs``, sorted by output name.

    Raises:
        CommandError: an input does not exist or is not a regular file or folder, no mesh file
            was found, two meshes would write the same file, an output would replace an input,
            or ``--ply`` would write into a folder searched for meshes.
    """
    from ..learning.datasets import MESH_SUFFIXES

    sources: dict[str, Path] = {}  # output name (OUTDIR-relative, no suffix) -> mesh file
    for given in inputs:
        path = Path(given)
        if path.is_dir():
            if ply and out_dir.resolve().is_relative_to(path.resolve()):
                raise common.CommandError(
                    f"--ply into the input folder {path} (-o {out_dir}): the next run would "
                    "read the PLY files written there as meshes; choose another -o"
                )
            found = [
                (mesh, mesh.relative_to(path).with_suffix("").as_posix())
                for mesh in _walk(path, MESH_SUFFIXES, out_dir)
            ]
        elif path.is_file():
            found = [(path, path.stem)]
        elif path.exists() or path.is_symlink():
            raise common.CommandError(f"{path} is neither a mesh file nor a folder")
        else:
            raise common.CommandError(f"no such file or folder: {path}")
        for mesh, name in found:
            _add_source(sources, name, mesh, out_dir)
    if not sources:
        listed = ", ".join(inputs)
        raise common.CommandError(f"no mesh files ({', '.join(MESH_SUFFIXES)}) in {listed}")
    jobs = [
        Job(mesh, out_dir / f"{name}.npz", out_dir / f"{name}.ply" if ply else None)
        for name, mesh in sorted(sources.items())
    ]
    _refuse_overwriting_inputs(jobs)
    return jobs


def _walk(folder: Path, suffixes: Sequence[str], out_dir: Path) -> Iterator[Path]:
    """Mesh files under ``folder`` (by suffix; regular files or links to them), leaving out
    ``out_dir``, whose PLY files are outputs."""
    skip = out_dir.resolve()
    for root, folders, files in os.walk(folder):
        folders[:] = [name for name in folders if Path(root, name).resolve() != skip]
        for name in files:
            path = Path(root, name)
            if path.suffix.lower() in suffixes and path.is_file():
                yield path


def _add_source(sources: dict[str, Path], name: str, mesh: Path, out_dir: Path) -> None:
    earlier = sources.get(name)
    if earlier is None:
        sources[name] = mesh
    elif not _same_path(earlier, mesh):  # the same file given twice is done once
        raise common.CommandError(
            f"{earlier} and {mesh} would both be written to {out_dir / name}.npz; rename one, "
            "or run them with different -o"
        )


def _same_path(a: Path, b: Path) -> bool:
    return a.resolve() == b.resolve()


def _refuse_overwriting_inputs(jobs: Sequence[Job]) -> None:
    inputs = {job.source.resolve(): job.source for job in jobs}
    for job in jobs:
        for output in (job.npz, job.ply):
            if output is not None and output.resolve() in inputs:
                raise common.CommandError(
                    f"output {output} is the input mesh {inputs[output.resolve()]}; refusing "
                    "to overwrite it (choose another -o)"
                )


# --------------------------------------------------------------------------------------------
# Running


def run(args) -> int:
    settings = _resolve_settings(args)
    index, count = args.shard if args.shard else shard_from_environment(os.environ)
    out_dir = Path(args.output)
    if out_dir.exists() and not out_dir.is_dir():
        raise common.CommandError(f"-o {out_dir} exists and is not a folder")
    jobs = find_jobs(args.inputs, out_dir, args.ply)
    mine = jobs[index::count]
    shard_text = f", shard {index}/{count}: {len(mine)}" if count > 1 else ""
    common.say(
        args,
        f"features ({_describe(settings)}) of {len(jobs)} meshes{shard_text} -> {out_dir}",
    )
    out_dir.mkdir(parents=True, exist_ok=True)

    from .feature_jobs import settings_record

    record = settings_record(settings, args.dtype, args.merge_seams)
    workers = min(args.workers, len(mine))
    threads = threads_per_worker(args.threads, max(workers, 1), os.environ)
    start = time.perf_counter()
    report = _Report(len(mine), args.quiet)
    try:
        if workers > 1:
            _run_in_pool(mine, settings, record, report, workers, threads, args.verbose)
        else:
            with _in_process_threads(args.threads, threads):
                _run_here(mine, settings, record, report)
    finally:
        report.close()
    counts = report.counts
    common.say(
        args,
        f"{len(mine)} meshes in {time.perf_counter() - start:.1f} s: {counts['computed']} "
        f"computed, {counts['skipped']} already done, {counts['failed']} failed",
    )
    if counts["failed"]:
        report.error(
            f"{counts['failed']} of {len(mine)} meshes failed (each named above); a rerun "
            "retries them and skips the others"
        )
        return 1
    return 0


def _resolve_settings(args):
    """The features' parameters object of the options, before any file is
    read or written: an option the variant does not use is a usage error (exit 2)."""
    from .._common.errors import ParameterError
    from ..features import feature_params

    try:
        return feature_params(args.variant, num_scales=args.num_scales, threshold=args.threshold)
    except ParameterError as error:
        raise common.UsageError(str(error)) from None


def _describe(params) -> str:
    from ..params import RobustParams

    if isinstance(params, RobustParams):
        return f"variant=robust, K={params.num_scales}"
    return f"variant=paper, K={params.num_scales}, threshold={params.threshold:g}"


@contextmanager
def _in_process_threads(requested: int | None, threads: int) -> Iterator[None]:
    """Under torchrun without ``--threads``, this process's share of the CPUs
    (:func:`threads_per_worker`) for the run; ``--threads`` is already applied by ``main``."""
    import torch

    before = torch.get_num_threads()
    change = requested is None and _local_processes(os.environ) > 1
    if change:
        torch.set_num_threads(threads)
    try:
        yield
    finally:
        if change:
            torch.set_num_threads(before)


def _run_here(jobs: Sequence[Job], settings, record: dict, report: _Report) -> None:
    from .feature_jobs import run_job

    for job in jobs:
        report.add(job, run_job(job, settings, record))


def _run_in_pool(
    jobs: Sequence[Job],
    settings,
    record: dict,
    report: _Report,
    workers: int,
    threads: int,
    verbose: bool,
) -> None:
    """The jobs in ``workers`` fresh processes (spawned: a forked child of a process whose
    torch has started its threads can deadlock) of ``threads`` torch threads each."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed
    from concurrent.futures.process import BrokenProcessPool

    from .feature_jobs import init_worker, run_job_in_worker

    earlier = set(multiprocessing.active_children())
    executor = ProcessPoolExecutor(
        workers,
        mp_context=multiprocessing.get_context("spawn"),
        initializer=init_worker,
        initargs=(threads, verbose, os.getpid()),
    )
    try:
        futures = {executor.submit(run_job_in_worker, job, settings, record): job for job in jobs}
        for future in as_completed(futures):
            try:
                outcome = future.result()
            except BrokenProcessPool:
                left = len(jobs) - report.done
                report.add_lost(
                    left,
                    f"a worker process died (killed, or out of memory?); {left} meshes were "
                    "not done, a rerun does them",
                )
                break
            report.add(futures[future], outcome)
    except BaseException:  # interrupted, terminated, or a bug: no worker outlives the command
        for process in set(multiprocessing.active_children()) - earlier:
            process.terminate()
        executor.shutdown(wait=True, cancel_futures=True)
        raise
    executor.shutdown(wait=True)


class _Report:
    """Progress of the meshes on stderr (a tqdm bar on a terminal when tqdm is installed, else
    a line per mesh; nothing with ``-q``), error lines always, and the counts."""

    def __init__(self, total: int, quiet: bool):
        self.total = total
        self.quiet = quiet
        self.counts: Counter[str] = Counter()
        self.bar = None if quiet or not _is_terminal(sys.stderr) else _tqdm(total)

    @property
    def done(self) -> int:
        return sum(self.counts.values())

    def add(self, job: Job, outcome: Outcome) -> None:
        self.counts[outcome.status] += 1
        if outcome.status == "failed":
            self.error(outcome.message)
        if self.bar is not None:
            self.bar.update(1)
        elif not self.quiet:
            self._write(
                f"{common.PROG}: {NAME}: {self.done}/{self.total} {job.source} ({outcome.status})"
            )

    def add_lost(self, count: int, message: str) -> None:
        """``count`` meshes that failed together, for the reason ``message``."""
        self.counts["failed"] += count
        self.error(message)

    def error(self, message: str) -> None:
        self._write(f"{common.PROG}: error: {common.one_line(message)}")

    def _write(self, line: str) -> None:
        if self.bar is not None:
            self.bar.write(line, file=sys.stderr)
        else:
            sys.stderr.write(line + "\n")
            sys.stderr.flush()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def _is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def _tqdm(total: int):
    """A tqdm bar of ``total`` meshes on stderr, or ``None`` without tqdm (``progress`` extra)."""
    try:
        from tqdm import tqdm
    except ImportError:
        return None
    return tqdm(total=total, desc=NAME, unit="mesh", file=sys.stderr, dynamic_ncols=True)
