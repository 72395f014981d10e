"""``stochlap features``: per-vertex multiscale features of every mesh of a dataset, to files.

Compute the (V, C) per-vertex features of every mesh file in the folders (searched
recursively) and files given, and write OUTDIR/<name>.npz for each, with --ply also
OUTDIR/<name>.ply (one float vertex property per channel). Meshes already done with the same
settings are skipped, so a rerun resumes an interrupted one; --shard I/N (under torchrun:
RANK/WORLD_SIZE) splits the meshes across machines. A mesh that fails is reported on one line
and the others go on; the exit status is then 1.

Names: DIR/a/b.obj found in folder DIR is written as OUTDIR/a/b.npz, a file named on the
command line as OUTDIR/<stem>.npz; two meshes that would share a name are refused before any
work. The walk does not follow links to folders and leaves out OUTDIR. Shards: the meshes
sorted by output name, mesh ``k`` goes to shard ``k mod N``. The files and what makes a mesh
"done": :mod:`stochlap_torch.learning.feature_files`.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from collections import Counter
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from .._common.cpus import available_cpus
from ..params import PaperFeatureParams, RobustParams, resolve_params
from . import common, options

if TYPE_CHECKING:  # imported when run: numpy is not loaded for --help
    from .feature_jobs import Job, Outcome

HELP = "per-vertex multiscale features of every mesh of a dataset, to .npz files"


# fmt: off
def add_arguments(parser) -> None:
    add = parser.add_argument
    suffixes = ".obj .off .ply .stl .glb .gltf"
    add("inputs", type=options.path, nargs="+", metavar="DIR_OR_FILE", help=f"mesh files, or "
        f"folders searched recursively for {suffixes}")
    add("-o", "--output", type=options.path, required=True, metavar="OUTDIR", help="output "
        "folder (created)")
    default = "robust"
    add("--variant", choices=("robust", "paper"), default=default, help="feature channels "
        f"(default: {default}, the same for the same surface meshed twice; paper: the "
        "coefficients and differences of the paper's Algorithm 1)")
    scales = f"{RobustParams.num_scales} for robust, {PaperFeatureParams.num_scales} for paper"
    add("-K", "--num-scales", type=options.positive_int, metavar="K", help="number of scales "
        f"(default: {scales})")
    add("--threshold", type=options.open_unit, metavar="LAMBDA", help="precision lambda in "
        f"(0, 1) (the paper variant only; default: {PaperFeatureParams.threshold:g})")
    add("--dtype", choices=options.DTYPES, default="float64", help="floating-point type of "
        "the computation and of the stored features (default: float64)")
    options.add_merge_seams(parser)
    add("--ply", action="store_true", help="also write OUTDIR/<name>.ply with one float vertex "
        "property per channel")
    add("--workers", type=options.positive_int, default=1, metavar="N", help="worker processes "
        "(default: 1, in this process)")
    add("--shard", type=shard, metavar="I/N", help="process only shard I of N (0 <= I < N); "
        "default: torchrun's RANK/WORLD_SIZE when set, else every mesh")
# fmt: on


def shard(text: str) -> tuple[int, int]:
    """``--shard I/N`` as ``(I, N)`` with ``0 <= I < N`` (an argparse ``type``)."""
    index, _, count = text.partition("/")
    try:
        index, count = int(index), int(count)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected I/N such as 0/4, got {text!r}") from None
    if not 0 <= index < count:
        raise argparse.ArgumentTypeError(f"expected I/N with 0 <= I < N, got {text!r}")
    return index, count


def shard_from_environment(environ: Mapping[str, str]) -> tuple[int, int]:
    """``(RANK, WORLD_SIZE)`` as torchrun sets them, ``(0, 1)`` when neither is set, else a
    :class:`CommandError`."""
    rank, size = environ.get("RANK"), environ.get("WORLD_SIZE")
    if rank is None and size is None:
        return 0, 1
    if rank is None or size is None:
        given, missing = ("WORLD_SIZE", "RANK") if rank is None else ("RANK", "WORLD_SIZE")
        raise common.CommandError(
            f"the environment sets {given} but not {missing}: set both (torchrun does), or "
            "pass --shard I/N"
        )
    try:
        return shard(f"{rank}/{size}")
    except argparse.ArgumentTypeError:
        raise common.CommandError(
            f"RANK={rank!r} and WORLD_SIZE={size!r} in the environment are not a shard "
            "(integers, 0 <= RANK < WORLD_SIZE); pass --shard I/N to choose one"
        ) from None


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


def find_jobs(inputs: Sequence[str], out_dir: Path, ply: bool) -> list[Job]:
    """The :class:`~.feature_jobs.Job` of every mesh of ``inputs``, sorted by output name, or
    a :class:`CommandError`: an input missing or not a file or folder, no mesh, two meshes to
    one file, an output replacing an input, or ``--ply`` into a folder searched for meshes."""
    from ..learning.feature_files import MESH_SUFFIXES
    from .feature_jobs import Job

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
            earlier = sources.setdefault(name, mesh)
            if earlier.resolve() != mesh.resolve():  # the same file given twice is done once
                raise common.CommandError(
                    f"{earlier} and {mesh} would both be written to {out_dir / name}.npz; "
                    "rename one, or run them with different -o"
                )
    if not sources:
        listed = ", ".join(inputs)
        raise common.CommandError(f"no mesh files ({', '.join(MESH_SUFFIXES)}) in {listed}")
    jobs = [
        Job(mesh, out_dir / f"{name}.npz", out_dir / f"{name}.ply" if ply else None)
        for name, mesh in sorted(sources.items())
    ]
    given = {job.source.resolve(): job.source for job in jobs}
    for output in (output for job in jobs for output in (job.npz, job.ply) if output):
        if output.resolve() in given:
            raise common.CommandError(
                f"output {output} is the input mesh {given[output.resolve()]}; refusing to "
                "overwrite it (choose another -o)"
            )
    return jobs


def _walk(folder: Path, suffixes: Sequence[str], out_dir: Path) -> Iterator[Path]:
    """Mesh files (by suffix) under ``folder``, leaving out ``out_dir``."""
    skip = out_dir.resolve()
    for root, folders, files in os.walk(folder):
        folders[:] = [name for name in folders if Path(root, name).resolve() != skip]
        for name in files:
            path = Path(root, name)
            if path.suffix.lower() in suffixes and path.is_file():
                yield path


def run(args) -> int:
    from ..learning.feature_files import settings_record
    from .feature_jobs import Outcome, is_done

    with common.usage_errors():  # an option the variant does not use, before any work
        params_class = PaperFeatureParams if args.variant == "paper" else RobustParams
        options = {"num_scales": args.num_scales, "threshold": args.threshold}
        args.params = resolve_params(params_class, args.variant, options)
    index, count = args.shard or shard_from_environment(os.environ)
    out_dir = Path(args.output)
    if out_dir.exists() and not out_dir.is_dir():
        raise common.CommandError(f"-o {out_dir} exists and is not a folder")
    jobs = find_jobs(args.inputs, out_dir, args.ply)
    mine = jobs[index::count]
    shard_text = f", shard {index}/{count}: {len(mine)}" if count > 1 else ""
    text = f"features ({common.compute_settings(args)}) of {len(jobs)} meshes{shard_text}"
    common.say(args, f"{text} -> {out_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)

    record = settings_record(args.params, args.dtype, args.merge_seams)
    start = time.perf_counter()
    report = _Report(len(mine), args.quiet)
    try:
        # What is done is decided here, before torch is imported or a worker started: a rerun
        # of a finished folder only hashes its meshes and reads its outputs' headers.
        todo = []
        for job in mine:
            if is_done(job, record):
                report.add(job, Outcome("skipped"))
            else:
                todo.append(job)
        if todo:
            _run_jobs(todo, args, record, report)
    finally:
        report.close()
    counts = report.counts
    done = f"{counts['computed']} computed, {counts['skipped']} already done"
    seconds = time.perf_counter() - start
    common.say(args, f"{len(mine)} meshes in {seconds:.1f} s: {done}, {counts['failed']} failed")
    if counts["failed"]:
        failed = f"{counts['failed']} of {len(mine)} meshes failed (each named above)"
        report.error(f"{failed}; a rerun retries them and skips the others")
        return 1
    return 0


def _run_jobs(jobs: Sequence[Job], args, record: dict, report) -> None:
    """The jobs in this process or in ``--workers`` processes, on their share of the CPUs
    (this process's thread setting restored after)."""
    import torch

    from .feature_jobs import run_job

    if args.threads is not None:
        common.apply_threads(args.threads)
    workers = min(args.workers, len(jobs))
    threads = threads_per_worker(args.threads, workers, os.environ)
    before = torch.get_num_threads()
    try:
        if workers > 1:
            _run_in_pool(jobs, args.params, record, report, workers, threads, args.verbose)
        else:
            # Under torchrun without --threads, this process's share of the CPUs for the run
            # (--threads is applied by main).
            if args.threads is None and _local_processes(os.environ) > 1:
                torch.set_num_threads(threads)
            for job in jobs:
                report.add(job, run_job(job, args.params, record))
    finally:
        torch.set_num_threads(before)


def _run_in_pool(jobs: Sequence[Job], settings, record, report, workers, threads, verbose):
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
                report.counts["failed"] += left
                report.error(
                    f"a worker process died (killed, or out of memory?); {left} meshes were "
                    "not done, a rerun does them"
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
        self.total, self.quiet = total, quiet
        self.counts: Counter[str] = Counter()
        self.bar = None
        if not quiet and common.stderr_is_terminal():
            with contextlib.suppress(ImportError):
                from tqdm import tqdm  # the progress extra

                options = {"unit": "mesh", "file": sys.stderr, "dynamic_ncols": True}
                self.bar = tqdm(total=total, desc="features", **options)

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
                f"{common.PROG}: features: {self.done}/{self.total} {job.source} ({outcome.status})"
            )

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
