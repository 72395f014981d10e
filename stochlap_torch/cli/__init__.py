"""The ``stochlap`` command line tool: argument handling and printing only.

:mod:`.app` (the parser, :func:`main`), :mod:`.options` (shared options, value types),
:mod:`.common` (messages, progress, the mesh, pictures), :mod:`.outputs` (output checks), and
one module per subcommand with ``HELP``, ``add_arguments(parser)`` and ``run(args)``.

Importing this package loads neither torch nor the library: the subcommands import what they
need when they run, so ``stochlap --help`` is fast.
"""

from .app import main

__all__ = ["main"]
