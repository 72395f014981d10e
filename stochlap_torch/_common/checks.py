"""Checks of scalar parameters: a :class:`~.errors.ParameterError` naming the parameter, never
a silent acceptance of ``nan``, ``2.5`` or ``True`` where an integer or a number is meant.

numpy scalars (``np.int64(8)``, ``np.float32(0.1)``) and 0-d tensors are accepted wherever a
Python number is.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping

from .errors import ParameterError

__all__ = [
    "check_choice",
    "check_int",
    "check_number",
    "check_optional_int",
    "format_bytes",
    "refuse_unused",
]


def _is_bool(value) -> bool:
    return isinstance(value, bool) or type(value).__name__ == "bool_"


def check_int(name: str, value, minimum: int | None = None, maximum: int | None = None) -> int:
    """``value`` as a Python ``int`` (Python, numpy or 0-d tensor integers; not ``bool``)."""
    if hasattr(value, "ndim") and getattr(value, "ndim", 1) == 0 and hasattr(value, "item"):
        value = value.item() if not _is_bool(value) else value
    if _is_bool(value) or not isinstance(value, numbers.Integral):
        raise ParameterError(f"{name} must be an integer, got {value!r}")
    value = int(value)
    if minimum is not None and value < minimum:
        raise ParameterError(f"{name} must be >= {minimum}, got {value}")
    if maximum is not None and value > maximum:
        raise ParameterError(f"{name} must be <= {maximum}, got {value}")
    return value


def check_optional_int(name: str, value, minimum: int | None = None) -> int | None:
    """:func:`check_int`, or ``None``."""
    return None if value is None else check_int(name, value, minimum)


def check_number(
    name: str,
    value,
    low: float | None = None,
    high: float | None = None,
    *,
    open_low: bool = False,
    open_high: bool = False,
) -> float:
    """``value`` as a finite Python ``float`` within ``[low, high]`` (ends open if asked)."""
    if hasattr(value, "ndim") and getattr(value, "ndim", 1) == 0 and hasattr(value, "item"):
        value = value.item() if not _is_bool(value) else value
    if _is_bool(value) or not isinstance(value, numbers.Real):
        raise ParameterError(f"{name} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ParameterError(f"{name} must be finite, got {value!r}")
    below = low is not None and (value <= low if open_low else value < low)
    above = high is not None and (value >= high if open_high else value > high)
    if below or above:
        lower = "-inf" if low is None else f"{low:g}"
        upper = "inf" if high is None else f"{high:g}"
        bounds = f"{'(' if open_low else '['}{lower}, {upper}{')' if open_high else ']'}"
        raise ParameterError(f"{name} must lie in {bounds}, got {value!r}")
    return value


def check_choice(name: str, value, choices) -> str:
    """``value`` if it is one of ``choices``."""
    if value not in choices:
        raise ParameterError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


def refuse_unused(choice, options: Mapping[str, object], name: str = "variant") -> None:
    """:class:`ParameterError` naming every option of ``options`` (name -> value) that was
    given (is not ``None``), when the ``choice`` made for ``name`` (a variant, a mode, a set of
    methods) does not use them: an option that is ignored is a mistake the caller should hear
    of, not a silent no-op."""
    given = [option for option, value in options.items() if value is not None]
    if given:
        names = ", ".join(f"{option}={options[option]!r}" for option in given)
        verb, pronoun = ("does", "it") if len(given) == 1 else ("do", "them")
        raise ParameterError(
            f"{names} {verb} not apply to {name}={choice!r}: leave {pronoun} unset, or "
            f"choose a {name} that uses {pronoun}"
        )


def format_bytes(count: float) -> str:
    """``count`` bytes for a message: ``"512 B"``, ``"3.2 KiB"``, ``"1.50 GiB"``."""
    for unit, size in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if abs(count) >= size:
            return f"{count / size:.2f} {unit}" if unit == "GiB" else f"{count / size:.1f} {unit}"
    return f"{int(count)} B"
