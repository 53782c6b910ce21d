"""Length units: everything inside livecap is millimetres; files say what they hold."""

from __future__ import annotations

MM_PER_UNIT = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}


def to_mm(value, units: str):
    """Scale ``value`` from ``units`` to millimetres; unknown units are an error, never a guess."""
    key = units.strip().lower()
    if key not in MM_PER_UNIT:
        raise ValueError(f"unknown length unit {units!r} (expected one of {sorted(MM_PER_UNIT)})")
    return value * MM_PER_UNIT[key]
