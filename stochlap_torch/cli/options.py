"""The options the subcommands share, and the types that check option values.

A bad value is a usage error naming the option, raised by argparse before any work. Nothing
here imports torch or the library (``stochlap --help`` stays fast).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from .._common.variants import (
    DEFAULT_RADIUS,
    DEFAULT_T_GLOBAL,
    DEFAULT_THRESHOLD,
    DEFAULT_VARIANT,
    PAPER_NUM_SCALES,
    ROBUST_NUM_SCALES,
    VARIANTS,
)

__all__ = [
    "MODES",
    "add_command",
    "add_common_options",
    "add_compute_options",
    "add_detector_options",
    "add_mesh_arguments",
    "add_picture_options",
    "closed_unit",
    "colormap_name",
    "non_negative_float",
    "num_scales",
    "open_unit",
    "positive_float",
    "positive_int",
    "view_spec",
]

#: ``--up`` values: the signed axes of the mesh file (``--up -y`` works as well as ``--up=-y``).
UP_CHOICES = ("x", "y", "z", "-x", "-y", "-z")
DTYPES = ("float64", "float32")
#: ``--mode`` of the interest-point detector (:func:`~stochlap_torch.interest.interest_points`).
MODES = ("nms", "paper")
#: Help of ``--mode``, ``--radius``, ``--top-k``: in full, and brief (``_DETECTOR_HELP[brief]``).
_DETECTOR_HELP = (
    (
        "nms: well-separated maxima (default); paper: every 1-ring maximum above t_global",
        f"nms suppression radius, fraction of the bounding-box diagonal (default: "
        f"{DEFAULT_RADIUS:g}; not with --mode paper)",
        "keep at most N points",
    ),
    (
        "detector mode",
        f"nms radius, fraction of the bounding-box diagonal (default: {DEFAULT_RADIUS:g})",
        "at most N points",
    ),
)


# --------------------------------------------------------------------------------------------
# Option types


def _number(text: str, kind):
    try:
        value = kind(text)
    except ValueError:
        name = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"expected {name}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def _number_type(kind, accept: Callable[[float], bool], expected: str, name: str):
    """An argparse ``type``: ``text`` as a ``kind`` (int, or a finite float) that ``accept``
    takes, else the usage error ``<expected>, got '<text>'``."""

    def parse(text: str):
        value = _number(text, kind)
        if not accept(value):
            raise argparse.ArgumentTypeError(f"{expected}, got {text!r}")
        return value

    parse.__name__ = parse.__qualname__ = name
    return parse


positive_int = _number_type(int, lambda v: v >= 1, "expected a positive integer", "positive_int")
num_scales = _number_type(int, lambda v: v >= 2, "must be an integer >= 2", "num_scales")
#: A float in the open interval (0, 1).
open_unit = _number_type(
    float, lambda v: 0.0 < v < 1.0, "must lie in the open interval (0, 1)", "open_unit"
)
closed_unit = _number_type(float, lambda v: 0.0 <= v <= 1.0, "must lie in [0, 1]", "closed_unit")
positive_float = _number_type(float, lambda v: v > 0.0, "must be positive", "positive_float")
non_negative_float = _number_type(float, lambda v: v >= 0.0, "must be >= 0", "non_negative_float")


def path(text: str) -> str:
    """An argparse ``type``: a path that is not empty (``""`` would mean the current folder)."""
    if not text:
        raise argparse.ArgumentTypeError("expected a path, got an empty one")
    return text


#: ``--dpi``: the range of :func:`stochlap_torch.viz._arrays.check_dpi` (below it the fonts
#: vanish, above it a picture takes minutes and gigabytes), checked before any work.
DPI_RANGE = (10, 600)
dpi = _number_type(
    int,
    lambda v: DPI_RANGE[0] <= v <= DPI_RANGE[1],
    f"must lie in [{DPI_RANGE[0]}, {DPI_RANGE[1]}]",
    "dpi",
)


# --------------------------------------------------------------------------------------------
# Options


def add_common_options(parser: argparse.ArgumentParser, default) -> None:
    """``--threads``, ``-v``, ``-q``; accepted before and after the subcommand name."""
    parser.add_argument(
        "--threads",
        type=positive_int,
        metavar="N",
        default=default,
        help="CPU threads (at most the CPUs this process may use)",
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


def add_compute_options(
    parser: argparse.ArgumentParser, dtype: bool = True, variant: bool = False
) -> None:
    """``-K``, ``--threshold``, (optionally) ``--dtype`` and (optionally) ``--variant``."""
    if variant:
        parser.add_argument(
            "--variant",
            choices=VARIANTS,
            default=DEFAULT_VARIANT,
            help=f"saliency variant (default: {DEFAULT_VARIANT}, the same for the same surface "
            "meshed twice; paper: the paper's Algorithm 2)",
        )
    parser.add_argument(
        "-K",
        "--num-scales",
        type=num_scales,
        default=None if variant else PAPER_NUM_SCALES,
        metavar="K",
        help="number of scales K >= 2 (default: "
        + (
            f"{ROBUST_NUM_SCALES} for robust, {PAPER_NUM_SCALES} for the others)"
            if variant
            else f"{PAPER_NUM_SCALES})"
        ),
    )
    parser.add_argument(
        "--threshold",
        type=open_unit,
        # With --variant, left unset so that a variant that does not use it can refuse it.
        default=None if variant else DEFAULT_THRESHOLD,
        metavar="LAMBDA",
        help="precision lambda in (0, 1): smaller operator entries are dropped (default: "
        f"{DEFAULT_THRESHOLD:g}{'; the paper variants only' if variant else ''})",
    )
    if dtype:
        parser.add_argument(
            "--dtype",
            choices=DTYPES,
            default="float64",
            help="floating-point type of the computation (default: float64)",
        )


def add_detector_options(
    parser: argparse.ArgumentParser, brief: bool = False, t_global: bool = False
) -> None:
    """``--mode``, ``--radius`` and ``--top-k`` of the interest-point detector
    (:func:`~stochlap_torch.interest.interest_points`), with ``brief`` help texts for a
    command of many options, and ``--t-global`` with ``t_global``."""
    mode, radius, top_k = _DETECTOR_HELP[brief]
    parser.add_argument("--mode", choices=MODES, default="nms", help=mode)
    parser.add_argument("--radius", type=positive_float, default=None, help=radius)
    parser.add_argument("--top-k", type=positive_int, metavar="N", help=top_k)
    if t_global:
        parser.add_argument(
            "--t-global",
            type=closed_unit,
            default=DEFAULT_T_GLOBAL,
            help="fraction of the saliency range a point must reach (default: "
            f"{DEFAULT_T_GLOBAL:g})",
        )


def colormap_name(text: str) -> str:
    """An argparse ``type``: the name of a matplotlib colormap (unchecked without matplotlib,
    which draws no picture anyway)."""
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return text
    from ..viz.colors import check_cmap

    try:
        return check_cmap(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def view_spec(text: str) -> list[tuple[float, float]]:
    """An argparse ``type``: ``--views`` as ``(elevation, azimuth)`` pairs."""
    from ..viz.framing import resolve_views

    try:
        return resolve_views(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_picture_options(
    parser: argparse.ArgumentParser, png: bool = True, cmap: bool = True
) -> None:
    """``--png PNG`` (optional) / ``--no-png``, ``--up``, ``--views``, ``--dpi``,
    ``--no-title`` and, with ``cmap`` (a picture coloured by a scalar), ``--cmap``."""
    group = parser.add_mutually_exclusive_group()
    if png:
        group.add_argument("--png", metavar="PNG", help="picture file (default: derived name)")
    group.add_argument("--no-png", action="store_true", help="do not draw a picture")
    parser.add_argument(
        "--up",
        choices=UP_CHOICES,
        default=None,
        metavar="AXIS",
        help="vertical axis of the mesh file in pictures: x, y, z, -x, -y or -z (default: "
        "y, or the middle extent for a flat mesh, turned over when the flat base of the mesh "
        "is at the top, stood upright when the mesh evidently lies on its side)",
    )
    parser.add_argument(
        "--views",
        type=view_spec,
        default=None,
        metavar="SPEC",
        help="the views in the picture, one panel each: a count (1 to 12), or comma-separated "
        "front, back, side, left, right, top, bottom, iso or ELEV:AZIM in degrees, e.g. "
        "front,side,top or front,20:-130 (write --views=-10:40 when it starts with -)",
    )
    parser.add_argument(
        "--dpi",
        type=dpi,
        default=None,
        metavar="N",
        help=f"picture resolution, {DPI_RANGE[0]} to {DPI_RANGE[1]} (default: 100)",
    )
    if cmap:
        parser.add_argument(
            "--cmap",
            type=colormap_name,
            default=None,
            metavar="NAME",
            help="matplotlib colormap of the picture, e.g. viridis (default: inferno)",
        )
    parser.add_argument("--no-title", action="store_true", help="draw the picture without a title")


def add_mesh_arguments(
    parser: argparse.ArgumentParser,
    output: tuple[str, str] | None = None,
    compute: bool = True,
    variant: bool = False,
) -> None:
    """The options of a command that reads one mesh: ``MESH`` (default: the bundled cow) and
    ``--merge-seams``; ``-o/--output`` when ``output`` is ``(metavar, help)``; then, with
    ``compute``, :func:`add_compute_options` (with ``--variant`` if ``variant``)."""
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
    if output is not None:
        parser.add_argument("-o", "--output", metavar=output[0], help=output[1])
    if compute:
        add_compute_options(parser, variant=variant)


def add_command(
    commands,
    parents: list[argparse.ArgumentParser],
    name: str,
    summary: str,
    description: str,
    run: Callable[[argparse.Namespace], int],
    add_arguments: Callable[[argparse.ArgumentParser], None],
    **parser_options,
) -> argparse.ArgumentParser:
    """The parser of subcommand ``name``: ``summary`` is its line in ``stochlap --help``,
    ``description`` the paragraph of ``stochlap <name> --help``; ``add_arguments(parser)``
    adds its options and ``run(args)`` runs it."""
    parser = commands.add_parser(
        name, parents=parents, help=summary, description=description, **parser_options
    )
    add_arguments(parser)
    parser.set_defaults(handler=run)
    return parser
