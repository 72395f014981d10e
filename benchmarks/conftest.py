"""pytest setup for ``benchmarks/`` (outside ``tests/``, so the normal test run skips it).

The thread pools are sized through the environment before anything imports torch, numba or
scipy (OpenMP, MKL and OpenBLAS read it once): ``$STOCHLAP_BENCH_THREADS`` threads, every
logical core by default.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parent
if str(BENCH_DIR) not in sys.path:
    sys.path.insert(0, str(BENCH_DIR))

import benchlib  # noqa: E402

THREADS = benchlib.default_threads()
for _name, _value in benchlib.thread_env(THREADS).items():
    os.environ[_name] = _value
