"""How the kernels are compiled and cached, without touching the user's numba configuration.

:func:`kernel_jit` is ``numba.njit(cache=True, ...)`` whose cache can never fail the import
(plain ``cache=True`` raises at import on a read-only install without a writable home): after
numba's own locations it tries ``$STOCHLAP_CACHE_DIR``, the user's cache directory and a
private temporary directory, and with none writable compiles uncached, with one warning.
A kernel inlines helpers of other modules (``steps.py`` compiles ``block.py``'s ``_block``),
so its cache is also stamped with the sources of ``_kernels`` and of its own folder
(:func:`sources_digest`). The first real compile in a process logs one line at WARNING
(``STOCHLAP_QUIET=1`` silences it).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import logging
import os
import tempfile
import threading
import warnings

from .threads import numba

logger = logging.getLogger("stochlap_torch")


class KernelCacheWarning(RuntimeWarning):
    """The compiled kernels cannot be cached on disk: every process compiles them again."""


#: The private temporary cache folder's name (the folder is made readable by its user only).
_PRIVATE = f"stochlap_torch-{os.getuid() if hasattr(os, 'getuid') else 'user'}"


def _candidate_dirs() -> list[str]:
    """Cache roots to try, in order, after numba's own locators."""
    dirs = [os.environ["STOCHLAP_CACHE_DIR"]] if os.environ.get("STOCHLAP_CACHE_DIR") else []
    home_cache = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    dirs.append(os.path.join(home_cache, "stochlap_torch"))
    with contextlib.suppress(OSError):  # no usable temporary directory at all
        dirs.append(os.path.join(tempfile.gettempdir(), _PRIVATE))
    return dirs


#: The folder of the kernels and of every helper they inline.
KERNELS_DIR = os.path.dirname(os.path.abspath(__file__))


def kernel_source_folders(py_file: str) -> tuple[str, ...]:
    """The folders whose sources a kernel defined in ``py_file`` is compiled from: its own and
    :data:`KERNELS_DIR` (sorted, each once)."""
    return tuple(sorted({KERNELS_DIR, os.path.dirname(os.path.abspath(py_file))}))


@functools.cache
def sources_digest(folders: tuple[str, ...]) -> str:
    """SHA-256 (hex) of the path and bytes of every ``*.py`` directly in ``folders``; read
    once per process, as the modules themselves are."""
    digest = hashlib.sha256()
    for folder in folders:
        for name in sorted(n for n in os.listdir(folder) if n.endswith(".py")):
            with open(os.path.join(folder, name), "rb") as source:
                path = os.path.join(os.path.basename(folder), name)
                digest.update(path.encode() + b"\0" + source.read() + b"\0")
    return digest.hexdigest()


def _make_cache_class():
    """The cache class with the library's locators (numba internals, kept in one place)."""
    from numba.core import caching

    class PackageSourcesStamp:
        """Locator mixin: the cache of a kernel is fresh while its own file (numba's stamp)
        and every source it may compile (:func:`sources_digest`) are unchanged."""

        def get_source_stamp(self):
            folders = kernel_source_folders(self._py_file)
            return (super().get_source_stamp(), sources_digest(folders))

    def stamped(locator_class):
        return type(locator_class.__name__, (PackageSourcesStamp, locator_class), {})

    class LibraryCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
        """Cache files under the first writable directory of :func:`_candidate_dirs`."""

        def __init__(self, py_func, py_file, base):
            self._py_file = py_file
            self._lineno = py_func.__code__.co_firstlineno
            subpath = self.get_suitable_cache_subpath(py_file)
            self._cache_path = os.path.join(base, "numba", subpath)

        def get_cache_path(self):
            return self._cache_path

        @classmethod
        def from_function(cls, py_func, py_file):
            if not os.path.exists(py_file):
                return None
            for base in _candidate_dirs():
                locator = cls(py_func, py_file, base)
                try:
                    locator.ensure_cache_path()  # makedirs and a test write
                except OSError:
                    continue
                if base.endswith(_PRIVATE):
                    os.chmod(base, 0o700)  # a shared temporary directory: private
                return locator
            return None

    class CacheImpl(caching.CompileResultCacheImpl):
        _locator_classes = [  # noqa: RUF012  (numba's own attribute, a list)
            stamped(caching.UserProvidedCacheLocator),  # NUMBA_CACHE_DIR, when the user set it
            stamped(caching.InTreeCacheLocator),  # __pycache__ beside the source
            stamped(caching.UserWideCacheLocator),  # numba's own user-wide cache
            stamped(LibraryCacheLocator),
        ]

    class Cache(caching.FunctionCache):
        _impl_class = CacheImpl

    return Cache


_CACHE_CLASS = None
_warned = False


def kernel_jit(**options):
    """Decorator: ``numba.njit(**options)`` with a disk cache that never fails the import."""

    def decorate(function):
        global _CACHE_CLASS, _warned
        dispatcher = numba.njit(cache=False, **options)(function)
        try:
            if _CACHE_CLASS is None:
                _CACHE_CLASS = _make_cache_class()
            dispatcher._cache = _CACHE_CLASS(dispatcher.py_func)  # as enable_caching() does
        except (RuntimeError, AttributeError, ImportError, OSError) as error:
            if not _warned:
                _warned = True
                warnings.warn(
                    f"stochlap_torch: compiled kernels will not be cached ({error}); set "
                    "STOCHLAP_CACHE_DIR to a writable directory to avoid compiling them in "
                    "every process",
                    KernelCacheWarning,
                    stacklevel=2,
                )
        return dispatcher

    return decorate


def cache_directory(dispatcher) -> str | None:
    """Where ``dispatcher`` caches its compiled code (``None``: not cached)."""
    return getattr(getattr(dispatcher, "_cache", None), "cache_path", None)


_notice_lock = threading.Lock()
_noticed = False


def _notice() -> None:
    global _noticed
    with _notice_lock:
        if _noticed or os.environ.get("STOCHLAP_QUIET"):
            return
        _noticed = True
    logger.warning(
        "compiling the CPU kernels of stochlap_torch for this machine (once: later processes "
        "load them from the disk cache; `stochlap warmup` does it ahead of time)"
    )


if numba is not None:

    class _CompileNotice(numba.core.event.Listener):
        """Logs :func:`_notice` when one of the package's kernels is really compiled."""

        def on_start(self, event):
            dispatcher = (event.data or {}).get("dispatcher")
            module = getattr(getattr(dispatcher, "py_func", None), "__module__", "") or ""
            if module.startswith("stochlap_torch"):
                _notice()

        def on_end(self, event):
            pass

    numba.core.event.register("numba:compile", _CompileNotice())
