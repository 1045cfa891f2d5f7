"""Typed ``argparse`` converters shared by every command.

``type=float`` accepts ``nan``, ``inf`` and any sign, so a typo such as
``--elevation-mask nan`` would silently disable a check.  These converters refuse such
values with a message naming the accepted range; argparse prints it as
``robustloc CMD: error: argument --x: ...`` and exits with code 2.

Examples
--------
>>> finite_float("1.5")
1.5
>>> float_in(0, 90)("45")
45.0
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

__all__ = [
    "finite_float",
    "positive_float",
    "nonnegative_float",
    "float_in",
    "positive_int",
    "nonnegative_int",
    "int_in",
]


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """A finite float (no NaN, no infinity)."""
    return _float(text)


def positive_float(text: str) -> float:
    """A finite float > 0."""
    value = _float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def nonnegative_float(text: str) -> float:
    """A finite float >= 0."""
    value = _float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def float_in(low: float, high: float) -> Callable[[str], float]:
    """Converter for a finite float in the closed interval ``[low, high]``."""

    def convert(text: str) -> float:
        value = _float(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(
                f"expected a number in [{low:g}, {high:g}], got {text!r}")
        return value

    convert.__name__ = f"float_in_{low:g}_{high:g}"
    return convert


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None


def positive_int(text: str) -> int:
    """A whole number >= 1."""
    value = _int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return value


def nonnegative_int(text: str) -> int:
    """A whole number >= 0."""
    value = _int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return value


def int_in(low: int, high: int) -> Callable[[str], int]:
    """Converter for a whole number in ``[low, high]``."""

    def convert(text: str) -> int:
        value = _int(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(
                f"expected a whole number in [{low}, {high}], got {text!r}")
        return value

    convert.__name__ = f"int_in_{low}_{high}"
    return convert
