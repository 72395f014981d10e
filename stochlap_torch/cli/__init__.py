"""The ``stochlap`` command line tool: argument handling and printing only.

:mod:`.app` (the parser, :func:`main`), :mod:`.options` (shared options, value types),
:mod:`.common` (errors, messages, progress, the mesh, pictures, output files), and one module
per subcommand with ``HELP``, ``add_arguments(parser)`` and ``run(args)``. Importing this
package loads neither torch nor the library, so ``stochlap --help`` is fast.
"""

from .app import main

__all__ = ["main"]
