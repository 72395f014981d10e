"""The cells and tables of ``RESULTS.md``: how seconds, bytes and ratios are written."""

from __future__ import annotations

import math


def seconds(value) -> str:
    """Seconds with three significant-ish digits; ``-`` for none."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    size = abs(value)
    if size >= 100:
        return f"{value:.0f}"
    if size >= 10:
        return f"{value:.1f}"
    if size >= 0.01:
        return f"{value:.3f}"
    return f"{value:.4f}"


def mib(value) -> str:
    """Bytes as MiB with thousands separators."""
    return "-" if value is None else f"{value / 2**20:,.0f}"


def ratio(value) -> str:
    """A ratio as ``1.23x`` (``12.3x`` from 10 up)."""
    return "-" if value is None else f"{value:.2f}x" if value < 10 else f"{value:.1f}x"


def entries_at_k(result) -> str:
    """Mean stored entries per row of ``F^(K)``, the last scale."""
    entries = result.get("entries_per_row") or {}
    return f"{entries[max(entries, key=int)]:.1f}" if entries else "-"


def error_row(first: list, result: dict, width: int) -> list:
    """``first`` cells, then the error of a failed ``result``, padded to ``width`` cells."""
    row = [*first, f"error: {result.get('error')}"]
    return row + [""] * (width - len(row))


def table(header, rows: list[list]) -> list[str]:
    """A markdown table and a blank line."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return [*lines, ""]
