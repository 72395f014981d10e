"""``stochlap warmup``: compile every CPU kernel now, so that no first call waits for it.

Compile the library's CPU kernels for float64 and float32 (or the given --dtype) and store
them in the disk cache, so that the first saliency, features or training step of every later
process starts in about a second instead of tens of seconds. Run it once after installing.
"""

from __future__ import annotations

from . import common, options

HELP = "compile the CPU kernels ahead of time (once after installing)"


def add_arguments(parser) -> None:
    text = "vertex dtype to compile for (default: both)"
    parser.add_argument("--dtype", choices=(*options.DTYPES, "both"), default="both", help=text)


def run(args) -> int:
    import torch

    from .._warmup import warmup

    names = options.DTYPES if args.dtype == "both" else (args.dtype,)
    dtypes = tuple(getattr(torch, name) for name in names)
    seconds = warmup(dtypes, report=lambda line: common.say(args, f"warmup: {line}"))
    common.say(args, f"compiled (or loaded) every kernel in {seconds:.1f} s")
    return 0
