"""The options the subcommands share, and the types that check their values before any work
(a usage error naming the option); no torch, no library (``stochlap --help`` stays fast)."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

from .. import params
from .._common import variants

#: ``--up`` values: the signed axes of the mesh file (``--up -y`` works as well as ``--up=-y``).
UP_CHOICES = ("x", "y", "z", "-x", "-y", "-z")
DTYPES = ("float64", "float32")


def _number_type(kind, accept: Callable[[float], bool], expected: str):
    """An argparse ``type``: a ``kind`` (int, or a finite float) that ``accept`` takes, else
    the usage error ``<expected>, got '<text>'``."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            name = "an integer" if kind is int else "a number"
            raise argparse.ArgumentTypeError(f"expected {name}, got {text!r}") from None
        if kind is float and not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        if not accept(value):
            raise argparse.ArgumentTypeError(f"{expected}, got {text!r}")
        return value

    return parse


positive_int = _number_type(int, lambda v: v >= 1, "expected a positive integer")
num_scales = _number_type(int, lambda v: v >= 2, "must be an integer >= 2")
open_unit = _number_type(float, lambda v: 0.0 < v < 1.0, "must lie in the open interval (0, 1)")
closed_unit = _number_type(float, lambda v: 0.0 <= v <= 1.0, "must lie in [0, 1]")
positive_float = _number_type(float, lambda v: v > 0.0, "must be positive")
non_negative_float = _number_type(float, lambda v: v >= 0.0, "must be >= 0")
#: ``--dpi``: the range of :func:`stochlap_torch.viz._arrays.check_dpi` (below it the fonts
#: vanish, above it a picture takes minutes and gigabytes), checked before any work.
DPI_MIN, DPI_MAX = 10, 600
dpi = _number_type(int, lambda v: DPI_MIN <= v <= DPI_MAX, f"must lie in [{DPI_MIN}, {DPI_MAX}]")


def path(text: str) -> str:
    """An argparse ``type``: a path that is not empty (``""`` would mean the current folder)."""
    if not text:
        raise argparse.ArgumentTypeError("expected a path, got an empty one")
    return text


# fmt: off
def add_common_options(parser: argparse.ArgumentParser, default) -> None:
    """``--threads``, ``-v``, ``-q``; accepted before and after the subcommand name."""
    add = parser.add_argument
    add("--threads", type=positive_int, metavar="N", default=default, help="CPU threads (at "
        "most the CPUs this process may use)")
    add("-v", "--verbose", action="store_true", default=default, help="log library messages")
    add("-q", "--quiet", action="store_true", default=default, help="print only errors and "
        "warnings (no progress, no summary)")


def add_compute_options(
    parser: argparse.ArgumentParser, dtype: bool = True, variant: bool = False
) -> None:
    """``-K``, ``--threshold``, (optionally) ``--dtype`` and (optionally) ``--variant``; with
    ``--variant`` the others are left unset, so that a variant that does not use one can
    refuse it."""
    add = parser.add_argument
    if variant:
        default = variants.DEFAULT_VARIANT
        add("--variant", choices=variants.VARIANTS, default=default, help="saliency variant "
            f"(default: {default}, the same for the same surface meshed twice; paper: the "
            "paper's Algorithm 2)")
    paper, threshold = params.PaperParams.num_scales, params.PaperParams.threshold
    robust = params.RobustParams.num_scales
    scales = f"{robust} for robust, {paper} for the others" if variant else paper
    add("-K", "--num-scales", type=num_scales, default=None if variant else paper, metavar="K",
        help=f"number of scales K >= 2 (default: {scales})")
    only = "; the paper variants only" if variant else ""
    add("--threshold", type=open_unit, default=None if variant else threshold, metavar="LAMBDA",
        help=f"precision lambda in (0, 1): smaller operator entries are dropped (default: "
        f"{threshold:g}{only})")
    if dtype:
        add("--dtype", choices=DTYPES, default="float64", help="floating-point type of the "
            "computation (default: float64)")


def add_detector_options(parser: argparse.ArgumentParser, t_global: bool = False) -> None:
    """``--mode``, ``--radius`` and ``--top-k`` of the interest-point detector
    (:func:`~stochlap_torch.interest.interest_points`), and ``--t-global`` with ``t_global``."""
    add = parser.add_argument
    add("--mode", choices=("nms", "paper"), default="nms", help="nms: well-separated maxima "
        "(default); paper: every 1-ring maximum above t_global")
    add("--radius", type=positive_float, default=None, help="nms suppression radius, fraction of "
        f"the bounding-box diagonal (default: {variants.DEFAULT_RADIUS:g}; not with --mode paper)")
    add("--top-k", type=positive_int, metavar="N", help="keep at most N points")
    if t_global:
        default = variants.DEFAULT_T_GLOBAL
        add("--t-global", type=closed_unit, default=default, help="fraction of the saliency "
            f"range a point must reach (default: {default:g})")


def add_picture_options(
    parser: argparse.ArgumentParser, png: bool = True, cmap: bool = True
) -> None:
    """``--png PNG`` (optional) / ``--no-png``, ``--up``, ``--views``, ``--dpi``,
    ``--no-title`` and, with ``cmap`` (a picture coloured by a scalar), ``--cmap``."""
    add, group = parser.add_argument, parser.add_mutually_exclusive_group()
    if png:
        group.add_argument("--png", metavar="PNG", help="picture file (default: derived name)")
    group.add_argument("--no-png", action="store_true", help="do not draw a picture")
    add("--up", choices=UP_CHOICES, default=None, metavar="AXIS", help="vertical axis of the "
        "mesh file in pictures: x, y, z, -x, -y or -z (default: y, or the middle extent for a "
        "flat mesh, turned over when the flat base of the mesh is at the top, stood upright "
        "when the mesh evidently lies on its side)")
    add("--views", type=view_spec, default=None, metavar="SPEC", help="the views in the "
        "picture, one panel each: a count (1 to 12), or comma-separated front, back, side, "
        "left, right, top, bottom, iso or ELEV:AZIM in degrees, e.g. front,side,top or "
        "front,20:-130 (write --views=-10:40 when it starts with -)")
    add("--dpi", type=dpi, default=None, metavar="N", help=f"picture resolution, {DPI_MIN} to "
        f"{DPI_MAX} (default: 100)")
    if cmap:
        add("--cmap", type=colormap_name, default=None, metavar="NAME", help="matplotlib "
            "colormap of the picture, e.g. viridis (default: inferno)")
    add("--shading", choices=("smooth", "flat"), default=None, help="smooth: colours and "
        "light interpolated across each triangle (default); flat: one colour per triangle")
    add("--no-title", action="store_true", help="draw the picture without a title")


def add_merge_seams(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--merge-seams", action="store_true", help="merge vertices at "
        "identical positions (texture/normal seams) before processing")


def add_mesh_arguments(
    parser: argparse.ArgumentParser,
    output: tuple[str, str] | None = None,
    compute: bool = True,
    variant: bool = False,
) -> None:
    """The options of a command that reads one mesh: ``MESH`` (default: the bundled cow) and
    ``--merge-seams``; ``-o/--output`` when ``output`` is ``(metavar, help)``; then, with
    ``compute``, :func:`add_compute_options` (with ``--variant`` if ``variant``)."""
    parser.add_argument("mesh", nargs="?", metavar="MESH", help="triangle mesh file (OBJ, "
        "OFF, PLY, STL, ...); default: the bundled 'spot' cow")
    add_merge_seams(parser)
    if output is not None:
        parser.add_argument("-o", "--output", metavar=output[0], help=output[1])
    if compute:
        add_compute_options(parser, variant=variant)
# fmt: on


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
