"""The ``stochlap`` command line tool.

Subcommands (every ``MESH`` defaults to the bundled "spot" cow)::

    stochlap saliency   [MESH] [-o OUT.ply] [--png OUT.png | --no-png] [-K 8] [--threshold 1e-3]
    stochlap multiscale [MESH] [-o DIR] [-K 8] [--threshold 1e-3] [--no-png]
    stochlap interest   [MESH] [-o POINTS.txt] [--png OUT.png | --no-png] [--mode nms|paper]
                        [--radius 0.1] [--top-k N] [--t-global 0.4]
    stochlap info       [MESH] [--json]
    stochlap evaluate   MESH TRUTH [MESH TRUTH ...] [--methods ...] [--png OUT.png]

Options of every subcommand, before or after its name: ``--threads N``, ``-v/--verbose``,
``-q/--quiet``.
Bad input prints one line ``stochlap: error: <message>`` on stderr and exits with status 2.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch

from ..mesh import Mesh, bundled_mesh_path, load_mesh, mesh_report, save_ply, validate_mesh

__all__ = ["main"]

logger = logging.getLogger("stochlap_torch.cli")

PROG = "stochlap"
_DTYPES = {"float32": torch.float32, "float64": torch.float64}
_VIZ_HINT = 'pip install "stochlap_torch[viz]"'


class CommandError(Exception):
    """A problem with the user's input, reported as one line and exit status 2."""


# --------------------------------------------------------------------------------------------
# Progress and output helpers


class _Progress:
    """``progress(k, K)`` callback: a ``scale k/K`` line, redrawn with ``\\r`` on a terminal,
    one line per scale otherwise; silent with ``--quiet``."""

    def __init__(self, label: str, quiet: bool = False, stream=None):
        self.label = label
        self.quiet = quiet
        self.stream = sys.stderr if stream is None else stream
        self.start = time.perf_counter()
        self.width = 0
        try:
            self.tty = bool(self.stream.isatty())
        except (AttributeError, ValueError):
            self.tty = False

    def __call__(self, k: int, num_scales: int) -> None:
        if self.quiet:
            return
        elapsed = time.perf_counter() - self.start
        text = f"{self.label}: scale {k}/{num_scales} ({elapsed:.1f} s)"
        if self.tty:
            end = "\n" if k >= num_scales else ""
            self.width = max(self.width, len(text))
            self.stream.write(f"\r{text:<{self.width}}{end}")
        else:
            self.stream.write(f"{PROG}: {text}\n")
        self.stream.flush()


def _mesh_path(path: str | None) -> Path:
    return bundled_mesh_path("spot") if path is None else Path(path)


def _load(args) -> tuple[Path, Mesh]:
    """Load ``args.mesh`` with ``--merge-seams`` and cast it to ``--dtype``."""
    path = _mesh_path(args.mesh)
    mesh = load_mesh(path, merge_seams=getattr(args, "merge_seams", False))
    dtype = _DTYPES[getattr(args, "dtype", "float64")]
    if dtype != mesh.vertices.dtype:
        mesh = mesh.to(dtype=dtype)
        validate_mesh(mesh.vertices, mesh.faces)  # edge lengths must be usable in that dtype
    return path, mesh


def _check_parameters(args) -> None:
    """Reject bad numeric options before loading anything (the library's own checks)."""
    from ..diffusion import check_parameters

    check_parameters(args.num_scales, args.threshold)
    if getattr(args, "radius", 1.0) <= 0.0:
        raise CommandError(f"--radius must be positive, got {args.radius:g}")
    if not 0.0 <= getattr(args, "t_global", 0.0) <= 1.0:
        raise CommandError(f"--t-global must lie in [0, 1], got {args.t_global:g}")
    scales = getattr(args, "scales", None)
    if scales:
        bad = [k for k in scales if not 1 <= k <= args.num_scales]
        if bad:
            raise CommandError(f"--scales must lie in 1..{args.num_scales}, got {bad}")


def _want_picture(args) -> bool:
    """Whether to draw the picture: not with ``--no-png``; without matplotlib, an explicit
    ``--png`` is an error (raised before any long computation) and the default picture is
    skipped with a warning."""
    if getattr(args, "no_png", False):
        return False
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        if getattr(args, "png", None):
            raise CommandError(f"--png needs matplotlib: {_VIZ_HINT}, or pass --no-png") from exc
        sys.stderr.write(
            f"{PROG}: warning: matplotlib is not installed, so no picture is drawn "
            f"({_VIZ_HINT}; --no-png silences this)\n"
        )
        return False
    return True


def _summary(message: str, args) -> None:
    if not args.quiet:
        print(message)


def _stats(values: torch.Tensor) -> str:
    values = values.detach().double()
    return (
        f"min {values.min().item():.4g}, max {values.max().item():.4g}, "
        f"mean {values.mean().item():.4g}"
    )


# --------------------------------------------------------------------------------------------
# Subcommands


def _prepare(args, suffix: str, extension: str):
    """Check the parameters, load the mesh, name the outputs: ``(path, mesh, out, png)``."""
    _check_parameters(args)
    draw = _want_picture(args)
    path, mesh = _load(args)
    out_path = Path(args.output) if args.output else Path(f"{path.stem}_{suffix}.{extension}")
    png_path = (Path(args.png) if args.png else Path(f"{path.stem}_{suffix}.png")) if draw else None
    _summary(f"{path.name}: {mesh.num_vertices} vertices, {mesh.num_faces} faces", args)
    return path, mesh, out_path, png_path


def _saliency_of(mesh, args):
    """Saliency of ``mesh`` with the command's parameters, with progress on stderr."""
    from .. import saliency

    return saliency(
        mesh.vertices,
        mesh.faces,
        num_scales=args.num_scales,
        threshold=args.threshold,
        progress=_Progress("saliency", args.quiet),
    )


def _cmd_saliency(args) -> int:
    path, mesh, ply_path, png_path = _prepare(args, "saliency", "ply")
    start = time.perf_counter()
    values = _saliency_of(mesh, args)
    elapsed = time.perf_counter() - start
    _summary(
        f"saliency (K={args.num_scales}, threshold={args.threshold:g}) in {elapsed:.2f} s: "
        + _stats(values),
        args,
    )

    from ..viz.render import robust_range, scalar_colors

    saliency_np = values.detach().cpu().double().numpy()
    # The colour range of the vertices the faces use (the picture's range too).
    vmin, vmax = robust_range(saliency_np, mesh.faces)
    save_ply(
        ply_path,
        mesh.vertices,
        mesh.faces,
        colors=scalar_colors(saliency_np, vmin=vmin, vmax=vmax),
        scalars={"saliency": saliency_np},
    )
    _summary(f"wrote {ply_path}", args)
    if png_path is not None:
        from ..viz.render import render_scalar

        render_scalar(
            mesh.vertices,
            mesh.faces,
            saliency_np,
            png_path,
            title=f"{path.name}: saliency (K={args.num_scales}, threshold={args.threshold:g})",
            label="saliency",
            up=args.up,
        )
        _summary(f"wrote {png_path}", args)
    return 0


def _cmd_multiscale(args) -> int:
    from .. import multiscale_representation

    _check_parameters(args)
    draw = _want_picture(args)
    path, mesh = _load(args)
    stem = path.stem
    out_dir = Path(args.output) if args.output else Path(f"{stem}_multiscale")
    if out_dir.exists() and not out_dir.is_dir():
        raise CommandError(f"output {out_dir} exists and is not a directory")
    _summary(f"{path.name}: {mesh.num_vertices} vertices, {mesh.num_faces} faces", args)

    start = time.perf_counter()
    representation = multiscale_representation(
        mesh.vertices,
        mesh.faces,
        num_scales=args.num_scales,
        threshold=args.threshold,
        progress=_Progress("multiscale", args.quiet),
    )
    elapsed = time.perf_counter() - start
    _summary(
        f"multiscale representation (K={args.num_scales}, threshold={args.threshold:g}) "
        f"in {elapsed:.2f} s",
        args,
    )

    out_dir.mkdir(parents=True, exist_ok=True)
    positions = representation.positions.detach().cpu().double()
    differences = representation.differences.detach().cpu().double().numpy()
    for k in range(1, representation.num_scales + 1):
        save_ply(
            out_dir / f"{stem}_k{k:02d}.ply",
            positions[k - 1],
            mesh.faces,
            scalars={"difference": differences[k - 1]},
        )
    _summary(
        f"wrote {representation.num_scales} meshes {out_dir / f'{stem}_k01.ply'} .. "
        f"{stem}_k{representation.num_scales:02d}.ply",
        args,
    )
    if draw:
        from ..viz.render import render_multiscale

        png_path = out_dir / f"{stem}_multiscale.png"
        render_multiscale(
            positions,
            mesh.faces,
            png_path,
            scales=None if args.scales is None else [k - 1 for k in args.scales],
            title=f"{path.name}: multiscale representation P^(k)",
            up=args.up,
        )
        _summary(f"wrote {png_path}", args)
    return 0


def _cmd_interest(args) -> int:
    from .. import interest_points

    path, mesh, txt_path, png_path = _prepare(args, "interest", "txt")
    start = time.perf_counter()
    values = _saliency_of(mesh, args)
    points = interest_points(
        values,
        mesh.vertices,
        mesh.faces,
        mode=args.mode,
        radius=args.radius,
        top_k=args.top_k,
        t_global=args.t_global,
    )
    elapsed = time.perf_counter() - start
    _summary(
        f"{points.numel()} interest points (mode={args.mode}"
        + (f", radius={args.radius:g}" if args.mode == "nms" else "")
        + f", K={args.num_scales}) in {elapsed:.2f} s",
        args,
    )

    indices = points.detach().cpu().numpy().astype(np.int64)
    xyz = mesh.vertices.detach().cpu().double().numpy()[indices]
    saliency_np = values.detach().cpu().double().numpy()
    txt_path.parent.mkdir(parents=True, exist_ok=True)
    with txt_path.open("w", encoding="utf-8") as handle:
        handle.write(
            f"# vertex x y z saliency  ({path.name}, mode={args.mode}, radius={args.radius:g}, "
            f"top_k={args.top_k}, t_global={args.t_global:g}, K={args.num_scales}, "
            f"threshold={args.threshold:g}; most salient first)\n"
        )
        for index, (x, y, z) in zip(indices.tolist(), xyz.tolist(), strict=True):
            handle.write(f"{index} {x:.9g} {y:.9g} {z:.9g} {saliency_np[index]:.9g}\n")
    _summary(f"wrote {txt_path}", args)
    if png_path is not None:
        from ..viz.render import render_interest_points

        render_interest_points(
            mesh.vertices,
            mesh.faces,
            saliency_np,
            indices,
            png_path,
            title=f"{path.name}: {indices.size} interest points ({args.mode})",
            up=args.up,
        )
        _summary(f"wrote {png_path}", args)
    return 0


# --------------------------------------------------------------------------------------------
# info


def _format_report(path: Path, report: dict) -> str:
    def vec(values) -> str:
        return "(" + ", ".join(f"{v:.4g}" for v in values) + ")"

    def verdict(value) -> str:
        return "yes" if value is True else f"no: {value}"

    rows = [
        ("mesh", str(path)),
        ("vertices", report["vertices"]),
        ("faces", report["faces"]),
        ("edges", report["edges"]),
        ("boundary edges", report["boundary_edges"]),
        ("non-manifold edges", report["non_manifold_edges"]),
        ("unreferenced vertices", report["unreferenced_vertices"]),
        ("connected components", report["components"]),
        ("closed", "yes" if report["closed"] else "no"),
        ("consistently oriented", "yes" if report["consistently_oriented"] else "no"),
        ("Euler characteristic", report["euler_characteristic"]),
        ("bounding box min", vec(report["bbox_min"])),
        ("bounding box max", vec(report["bbox_max"])),
        ("bounding box size", vec(report["bbox_size"])),
        ("mean edge length", f"{report['mean_edge_length']:.4g}"),
        ("shortest edge", f"{report['min_edge_length']:.4g}"),
        ("valid (float64)", verdict(report["valid_float64"])),
        ("valid (float32)", verdict(report["valid_float32"])),
    ]
    width = max(len(name) for name, _ in rows)
    return "\n".join(f"{name:<{width}}  {value}" for name, value in rows)


def _cmd_info(args) -> int:
    path = _mesh_path(args.mesh)
    # load_mesh validates in float64: a mesh that fails is reported as one error line.
    mesh = load_mesh(path, merge_seams=args.merge_seams)
    report = mesh_report(mesh)
    if args.json:
        print(json.dumps({"mesh": str(path), **report}, indent=2))
    else:
        print(_format_report(path, report))
    return 0


# --------------------------------------------------------------------------------------------
# Argument parsing


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def _add_mesh(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "mesh",
        nargs="?",
        metavar="MESH",
        help="triangle mesh file (OBJ, OFF, PLY, STL, ...); default: the bundled 'spot' cow",
    )
    parser.add_argument(
        "--merge-seams",
        action="store_true",
        help="merge vertices at identical positions (texture/normal seams) before processing",
    )


def _add_compute(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "-K",
        "--num-scales",
        type=int,
        default=8,
        metavar="K",
        help="number of scales K >= 2 (default: 8)",
    )
    parser.add_argument(
        "--threshold",
        type=float,
        default=1e-3,
        metavar="LAMBDA",
        help="precision lambda in (0, 1): smaller operator entries are dropped (default: 1e-3)",
    )
    parser.add_argument(
        "--dtype",
        choices=sorted(_DTYPES),
        default="float64",
        help="floating-point type of the computation (default: float64)",
    )


def _add_picture(parser: argparse.ArgumentParser, png: bool = True) -> None:
    group = parser.add_mutually_exclusive_group()
    if png:
        group.add_argument("--png", metavar="PNG", help="picture file (default: derived name)")
    group.add_argument("--no-png", action="store_true", help="do not draw a picture")
    parser.add_argument(
        "--up",
        choices=("x", "y", "z"),
        default=None,
        help="vertical axis of the mesh in pictures (default: guessed from the bounding box)",
    )


def _add_common(parser: argparse.ArgumentParser, default) -> None:
    parser.add_argument(
        "--threads",
        type=_positive_int,
        metavar="N",
        default=default,
        help="number of CPU threads for torch",
    )
    parser.add_argument(
        "-v", "--verbose", action="store_true", default=default, help="log library messages"
    )
    parser.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=default,
        help="print only errors and warnings (no progress, no summary)",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=PROG,
        description=(
            "Multiscale analysis of triangle meshes with the stochastic mesh Laplacian: "
            "saliency, multiscale representation, interest points."
        ),
    )
    _add_common(parser, argparse.SUPPRESS)
    parser.set_defaults(threads=None, verbose=False, quiet=False)
    # The same options are accepted after the subcommand too (``stochlap info -q MESH``).
    common = argparse.ArgumentParser(add_help=False)
    _add_common(common, argparse.SUPPRESS)
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    saliency = commands.add_parser(
        "saliency",
        parents=[common],
        help="per-vertex saliency (Algorithm 2) to a coloured PLY and a picture",
        description=(
            "Compute mesh saliency and write a binary PLY with saliency as vertex colours and "
            "a 'saliency' float property, plus a PNG picture. Default outputs: "
            "<stem>_saliency.ply and <stem>_saliency.png in the current directory."
        ),
    )
    _add_mesh(saliency)
    saliency.add_argument("-o", "--output", metavar="PLY", help="output PLY file")
    _add_compute(saliency)
    _add_picture(saliency)
    saliency.set_defaults(handler=_cmd_saliency)

    multiscale = commands.add_parser(
        "multiscale",
        parents=[common],
        help="the meshes P^(k) at every scale, and a picture strip",
        description=(
            "Write the multiscale representation: DIR/<stem>_kNN.ply for k = 1..K (with the "
            "difference map D^(k) as a 'difference' vertex property) and "
            "DIR/<stem>_multiscale.png. Default DIR: <stem>_multiscale."
        ),
    )
    _add_mesh(multiscale)
    multiscale.add_argument("-o", "--output", metavar="DIR", help="output directory")
    _add_compute(multiscale)
    multiscale.add_argument(
        "--scales",
        type=_positive_int,
        nargs="+",
        metavar="k",
        help="scales (1..K) shown in the picture (default: about 5 evenly spaced)",
    )
    _add_picture(multiscale, png=False)
    multiscale.set_defaults(handler=_cmd_multiscale)

    interest = commands.add_parser(
        "interest",
        parents=[common],
        help="interest points (local saliency maxima) to a text file and a picture",
        description=(
            "Detect interest points and write one per line, most salient first, as "
            "'vertex x y z saliency' after a '#' header line. Default outputs: "
            "<stem>_interest.txt and <stem>_interest.png."
        ),
    )
    _add_mesh(interest)
    interest.add_argument("-o", "--output", metavar="TXT", help="output points file")
    _add_compute(interest)
    interest.add_argument(
        "--mode",
        choices=("nms", "paper"),
        default="nms",
        help="nms: well-separated maxima (default); paper: every 1-ring maximum above t_global",
    )
    interest.add_argument(
        "--radius",
        type=float,
        default=0.1,
        help="nms suppression radius, fraction of the bounding-box diagonal (default: 0.1)",
    )
    interest.add_argument(
        "--top-k", type=_positive_int, default=None, metavar="N", help="keep at most N points"
    )
    interest.add_argument(
        "--t-global",
        type=float,
        default=0.4,
        help="fraction of the saliency range a point must reach (default: 0.4)",
    )
    _add_picture(interest)
    interest.set_defaults(handler=_cmd_interest)

    info = commands.add_parser(
        "info",
        parents=[common],
        help="counts and checks of a mesh file",
        description=(
            "Report vertices, faces, edges, boundary and non-manifold edges, unreferenced "
            "vertices, connected components, bounding box, edge lengths, and whether the mesh "
            "passes the input checks in float64 and float32."
        ),
    )
    info.add_argument(
        "mesh", nargs="?", metavar="MESH", help="triangle mesh file (default: the bundled cow)"
    )
    info.add_argument(
        "--merge-seams", action="store_true", help="merge vertices at identical positions first"
    )
    info.add_argument("--json", action="store_true", help="print the report as JSON")
    info.set_defaults(handler=_cmd_info)

    from .evaluate import add_evaluate_parser

    add_evaluate_parser(commands, common)
    return parser


def _set_threads(count: int) -> None:
    """Cap torch's intra-op threads, and numba's (the fused kernel) when numba is installed."""
    torch.set_num_threads(count)
    try:
        import numba
    except ImportError:
        return
    numba.set_num_threads(min(count, numba.config.NUMBA_NUM_THREADS))


def _error(message: str) -> int:
    # One line: collapse any newlines in the message.
    text = " ".join(str(message).split())
    sys.stderr.write(f"{PROG}: error: {text}\n")
    sys.stderr.flush()
    return 2


def main(argv: list[str] | None = None) -> int:
    """Run the ``stochlap`` command; returns the exit status (0, or 2 for bad input)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or argparse's own usage error (status 2)
        return exc.code if isinstance(exc.code, int) else 2
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING,
        format=f"{PROG}: %(name)s: %(message)s",
        stream=sys.stderr,
    )
    if args.threads is not None:
        _set_threads(args.threads)
    logger.info(
        "%s with torch %s, %d threads", args.command, torch.__version__, torch.get_num_threads()
    )
    try:
        return int(args.handler(args))
    except OSError as exc:  # a missing mesh file, an output that cannot be written, ...
        if exc.filename is not None and exc.strerror:
            return _error(f"{exc.filename}: {exc.strerror}")
        return _error(str(exc) or type(exc).__name__)
    except (CommandError, ValueError) as exc:  # MeshError is a ValueError
        return _error(str(exc) or type(exc).__name__)
    except MemoryError as exc:  # includes the library's MemoryBudgetError
        return _error(str(exc) or "out of memory: lower -K or raise --threshold")
    except ImportError as exc:
        return _error(f"{exc}; {_VIZ_HINT}" if "matplotlib" in str(exc) else str(exc))
    except KeyboardInterrupt:
        sys.stderr.write(f"\n{PROG}: interrupted\n")
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
