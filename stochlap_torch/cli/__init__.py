"""The ``stochlap`` command line tool: argument handling and printing only."""

from .main import main

__all__ = ["main"]
