"""Argument checks shared by the map modules: clear errors naming the argument."""

from __future__ import annotations

import math

import numpy as np


def finite_number(name: str, value: object, unit: str, *, allow_zero: bool = False) -> float:
    """``value`` as a float after checking it is a finite number > 0 (>= 0 with ``allow_zero``).

    Args:
        name: argument name quoted in the error.
        value: the argument.
        unit: unit quoted in the error, e.g. "m/px".
        allow_zero: accept 0.

    Raises:
        ValueError: naming ``name``, the expected range and the value received.
    """
    bound = ">= 0" if allow_zero else "> 0"
    number = not isinstance(value, (bool, np.bool_)) and isinstance(
        value, (int, float, np.integer, np.floating)
    )
    if not number or not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name} must be a finite number {bound} [{unit}], got {value!r}")
    return float(value)


def number_in_range(name: str, value: object, low: float, high: float, unit: str) -> float:
    """``value`` as a float after checking it is a real number in [``low``, ``high``].

    Raises:
        ValueError: naming ``name``, the range with its ``unit`` and the value received.
    """
    number = not isinstance(value, (bool, np.bool_)) and isinstance(
        value, (int, float, np.integer, np.floating)
    )
    if not number or not low <= value <= high:  # NaN fails the comparison
        raise ValueError(f"{name} must be a number in [{low:g}, {high:g}] [{unit}], got {value!r}")
    return float(value)
