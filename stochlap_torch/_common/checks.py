"""Checks of scalar parameters: a :class:`~.errors.ParameterError` naming the parameter, never
a silent acceptance of ``nan``, ``2.5``, ``True`` or ``10**400`` where a number is meant (numpy
scalars and 0-d tensors are accepted wherever a Python number is).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping

from .errors import ParameterError

#: Integers beyond int64, where every integer the library uses ends up.
_INT64 = 2**63 - 1


def _scalar(value):
    """A 0-d tensor or array as its Python scalar; ``bool`` (Python or numpy) kept as is."""
    if getattr(value, "ndim", 1) == 0 and hasattr(value, "item") and not _is_bool(value):
        return value.item()
    return value


def _is_bool(value) -> bool:
    return isinstance(value, bool) or type(value).__name__ == "bool_"


def _shown(value) -> str:
    """An integer for a message (its size when too long to print), or what overflows a float."""
    if not isinstance(value, numbers.Integral):
        return "a number beyond the float range"
    bits = abs(int(value)).bit_length()
    return str(int(value)) if bits <= 64 else f"an integer of {bits} bits"


def check_int(name: str, value, minimum: int | None = None, maximum: int | None = None) -> int:
    """``value`` as a Python ``int`` (Python, numpy or 0-d tensor integers; not ``bool``)
    within ``[minimum, maximum]`` and int64."""
    value = _scalar(value)
    if _is_bool(value) or not isinstance(value, numbers.Integral):
        raise ParameterError(f"{name} must be an integer, got {value!r}")
    value = int(value)
    if minimum is not None and value < minimum:
        raise ParameterError(f"{name} must be >= {minimum}, got {_shown(value)}")
    if maximum is not None and value > maximum:
        raise ParameterError(f"{name} must be <= {maximum}, got {_shown(value)}")
    if abs(value) > _INT64:
        raise ParameterError(f"{name} must fit in 64 bits, got {_shown(value)}")
    return value


def check_bool(name: str, value) -> bool:
    """``value`` if it is ``True`` or ``False`` (not a number standing for one)."""
    if not isinstance(value, bool):
        raise ParameterError(f"{name} must be True or False, got {value!r}")
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
    value = _scalar(value)
    if _is_bool(value) or not isinstance(value, numbers.Real):
        raise ParameterError(f"{name} must be a number, got {value!r}")
    try:
        number = float(value)
    except OverflowError:  # an integer or fraction beyond the float range
        raise ParameterError(f"{name} must be finite, got {_shown(value)}") from None
    if not math.isfinite(number):
        raise ParameterError(f"{name} must be finite, got {number!r}")
    below = low is not None and (number <= low if open_low else number < low)
    above = high is not None and (number >= high if open_high else number > high)
    if below or above:
        lower = "-inf" if low is None else f"{low:g}"
        upper = "inf" if high is None else f"{high:g}"
        bounds = f"{'(' if open_low else '['}{lower}, {upper}{')' if open_high else ']'}"
        raise ParameterError(f"{name} must lie in {bounds}, got {number!r}")
    return number


def check_choice(name: str, value, choices) -> str:
    """``value`` if it is one of ``choices``."""
    if value not in choices:
        raise ParameterError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


def refuse_unused(choice, options: Mapping[str, object], name: str = "variant") -> None:
    """:class:`ParameterError` naming every option of ``options`` (name -> value) that was
    given (is not ``None``) when the ``choice`` made for ``name`` (a variant, a mode, a set of
    methods) does not use them: an ignored option is a mistake the caller should hear of."""
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
