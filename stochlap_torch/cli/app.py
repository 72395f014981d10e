"""The ``stochlap`` command line tool: the parser, ``main`` and its error handling.

Exit status: 0 on success; 2 for a user error (bad option or value, unreadable or invalid
file, an output that would overwrite an input, a library :class:`StochlapError`), printed as
one line ``stochlap: error: <message>`` on stderr; 130 when interrupted; 128 + the signal's
number on SIGTERM (143) or SIGHUP (129), after removing any half-written output. Any other
exception is a bug and propagates with its traceback (status 1). ``features`` goes on past a
mesh that fails (one error line each), then exits with status 1.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from .._common.errors import StochlapError
from .._common.version import __version__
from . import (
    common,
    compare,
    evaluate,
    features,
    info,
    interest,
    multiscale,
    saliency,
    warmup,
)
from .common import PROG, CommandError, Parser
from .options import add_common_options

#: The subcommand modules, in the order of ``stochlap --help``.
COMMANDS = (saliency, multiscale, interest, info, compare, evaluate, features, warmup)


def add_command(commands, parents, module) -> argparse.ArgumentParser:
    """The parser of a subcommand module, named by it: ``HELP``, the docstring's second
    paragraph (or ``DESCRIPTION``), ``add_arguments(parser)``; ``run(args)`` runs it."""
    description = getattr(module, "DESCRIPTION", None) or module.__doc__.split("\n\n")[1]
    options = {"help": module.HELP, "description": description}
    name = module.__name__.rpartition(".")[2]
    parser = commands.add_parser(
        name, parents=parents, **options, **getattr(module, "PARSER_OPTIONS", {})
    )
    module.add_arguments(parser)
    parser.set_defaults(handler=module.run)
    return parser


def build_parser() -> argparse.ArgumentParser:
    """The ``stochlap`` parser with every subcommand; ``args.handler(args)`` runs one."""
    parser = Parser(
        prog=PROG,
        description=(
            "Multiscale analysis of triangle meshes with the stochastic mesh Laplacian: "
            "saliency, multiscale representation, interest points, comparison with "
            "eigendecomposition baselines, evaluation."
        ),
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    add_common_options(parser, argparse.SUPPRESS)
    parser.set_defaults(threads=None, verbose=False, quiet=False)
    # The same options are accepted after the subcommand too (``stochlap info -q MESH``).
    after = Parser(add_help=False)
    add_common_options(after, argparse.SUPPRESS)
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in COMMANDS:
        add_command(commands, [after], module)
    return parser


def _join_signed_axes(argv: Sequence[str]) -> list[str]:
    """``--up -y`` as ``--up=-y``: argparse would take ``-y`` for an option."""
    joined: list[str] = []
    for arg in argv:
        signed = joined and joined[-1] == "--up" and arg in ("-x", "-y", "-z")
        joined[-1:] = [f"--up={arg}"] if signed else [*joined[-1:], arg]
    return joined


def _error(message: object) -> int:
    sys.stderr.write(f"{PROG}: error: {common.one_line(message)}\n")
    sys.stderr.flush()
    return 2


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``stochlap`` command; returns the exit status (0; 2 for a user error)."""
    argv = sys.argv[1:] if argv is None else argv
    try:
        args = build_parser().parse_args(_join_signed_axes(argv))
    except CommandError as exc:  # argparse's usage errors (Parser.error)
        return _error(exc)
    except SystemExit as exc:  # --help, --version
        return exc.code if isinstance(exc.code, int) else 0
    with common.messages(args.verbose), common.terminate_by_exception():
        try:
            # features applies them once it has work: a rerun with nothing to do skips torch
            if args.threads is not None and args.command != "features":
                common.apply_threads(args.threads)
            return int(args.handler(args))
        except (CommandError, StochlapError) as exc:
            return _error(str(exc) or type(exc).__name__)
        except OSError as exc:  # a missing or unreadable input, an output that cannot be written
            return _error(common.describe_os_error(exc))
        except (KeyboardInterrupt, common.Terminated) as exc:
            signum = getattr(exc, "signum", None)
            reason = f"terminated by {exc.name}" if signum else "interrupted"
            newline = "\n" if sys.stderr.isatty() else ""  # after a progress line
            sys.stderr.write(f"{newline}{PROG}: {reason}\n")
            return 128 + signum if signum else 130
