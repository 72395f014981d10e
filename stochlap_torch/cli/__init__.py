"""The ``stochlap`` command line tool: argument handling and printing only.

* :mod:`.app`: the parser, :func:`main` and its error handling;
* :mod:`.common`: shared options, one-line messages, the progress printer, threads;
* :mod:`.outputs`: output names, the checks that no input is overwritten, atomic writing;
* one module per subcommand: :mod:`.saliency`, :mod:`.multiscale`, :mod:`.interest`,
  :mod:`.info`, :mod:`.evaluate`, each with ``add_parser(commands, parents)`` and
  ``run(args)``.

Importing this package loads neither torch nor the library: the subcommands import what they
need when they run, so ``stochlap --help`` is fast.
"""

from .app import main

__all__ = ["main"]
