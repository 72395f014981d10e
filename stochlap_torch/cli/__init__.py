"""The ``stochlap`` command line tool: argument handling and printing only.

* :mod:`.app`: the parser, :func:`main` and its error handling;
* :mod:`.options`: the shared options and the types that check their values;
* :mod:`.common`: one-line messages, the progress printer, loading the mesh, pictures;
* :mod:`.outputs`: output names, the checks that no input is overwritten, atomic writing;
* one module per subcommand: :mod:`.saliency`, :mod:`.multiscale`, :mod:`.interest`,
  :mod:`.info`, :mod:`.evaluate`, each with ``add_parser(commands, parents)`` (its
  description is the second paragraph of its docstring) and ``run(args)``.

Importing this package loads neither torch nor the library: the subcommands import what they
need when they run, so ``stochlap --help`` is fast.
"""

from .app import main

__all__ = ["main"]
