"""The package version, in one place (the package and its cache read it from here)."""

__version__ = "0.2.0"
