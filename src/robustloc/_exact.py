"""Exact, mergeable sums of floats: statistics that do not depend on the order of the rows.

A float sum rounds at every addition, so the same numbers summed in another order (one
file against a dataset's partitions combined on the client) differ in the last digits.
:class:`Moments` keeps the count, the sum and the sum of squares of a set of finite
floats *exactly* (as :class:`fractions.Fraction`): two parts' moments add up exactly to
the whole's, so the standard deviation computed from them is the same number whichever
way the values were split or ordered.

Each float is ``m * 2**e`` with an integer mantissa ``m`` (``|m| < 2**53``); the
mantissas of equal exponent are summed in two halves, exactly (integers below ``2**51``
in a float, by blocks of ``2**24`` values), then as Python integers.  A square is split
without rounding into the sum of two floats (Dekker's product of the mantissas, exact
for them; the exponent is kept apart, so no square overflows or underflows).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["Moments", "exact_sum"]

_HALF = 26
_LOW = (1 << _HALF) - 1
#: Values per block (the sums of one block's half-mantissas stay exact in a float).
_CHUNK = 1 << 24


def _sum_scaled(values: NDArray[np.float64], shift: NDArray[np.int64]) -> Fraction:
    """The exact value of ``sum(values[i] * 2**shift[i])`` (finite values)."""
    total = 0  # in units of 2**base
    base = None
    for a in range(0, values.size, _CHUNK):
        m, e = np.frexp(values[a:a + _CHUNK])
        mant = np.ldexp(m, 53).astype(np.int64)  # exact: |m| < 1 has at most 53 bits
        expo = e.astype(np.int64) + shift[a:a + _CHUNK] - 53
        lo_k = int(expo.min())
        k = expo - lo_k
        # per exponent, the halves of the mantissas summed as floats: integers below
        # 2**51 (at most _CHUNK of them, each below 2**27), so exactly
        high = np.bincount(k, weights=(mant >> _HALF).astype(float))
        low = np.bincount(k, weights=(mant & _LOW).astype(float))
        part = 0
        for j in np.flatnonzero((high != 0) | (low != 0)):
            part += ((int(high[j]) << _HALF) + int(low[j])) << int(j)
        if base is None or lo_k < base:
            total <<= 0 if base is None else base - lo_k
            base = lo_k
        total += part << (lo_k - base)
    if base is None:
        return Fraction(0)
    return Fraction(total << base) if base >= 0 else Fraction(total, 1 << -base)


def _finite(values: ArrayLike) -> NDArray[np.float64]:
    x = np.asarray(values, dtype=float).ravel()
    if not np.isfinite(x).all():
        raise ValueError("exact sums take finite values only")
    return x


def exact_sum(values: ArrayLike) -> Fraction:
    """The exact sum of finite floats (a :class:`~fractions.Fraction`).

    Raises
    ------
    ValueError
        A value is NaN or infinite.
    """
    x = _finite(values)
    return _sum_scaled(x, np.zeros(x.size, dtype=np.int64))


def _exact_sum_of_squares(x: NDArray[np.float64]) -> Fraction:
    m, e = np.frexp(x)  # x**2 = m**2 * 2**(2 e), 0.5 <= |m| < 1 (or 0)
    p = m * m
    c = 134217729.0 * m  # Veltkamp's split of m into two 26-bit halves (2**27 + 1)
    mh = c - (c - m)
    ml = m - mh
    err = ((mh * mh - p) + 2.0 * mh * ml) + ml * ml  # Dekker: m**2 == p + err exactly
    shift = 2 * e.astype(np.int64)
    return _sum_scaled(np.r_[p, err], np.r_[shift, shift])


@dataclass(frozen=True)
class Moments:
    """Count, exact sum and exact sum of squares of a set of finite floats.

    Attributes
    ----------
    n : int
        Number of values.
    s1 : Fraction
        Their sum, exactly.
    s2 : Fraction
        The sum of their squares, exactly.
    """

    n: int = 0
    s1: Fraction = field(default_factory=Fraction)
    s2: Fraction = field(default_factory=Fraction)

    @classmethod
    def of(cls, values: ArrayLike) -> Moments:
        """The moments of ``values`` (finite floats).

        Raises
        ------
        ValueError
            A value is NaN or infinite.
        """
        x = _finite(values)
        return cls(int(x.size), _sum_scaled(x, np.zeros(x.size, dtype=np.int64)),
                   _exact_sum_of_squares(x))

    def __add__(self, other: Moments) -> Moments:
        """The moments of both sets together (exact)."""
        return Moments(self.n + other.n, self.s1 + other.s1, self.s2 + other.s2)

    def std(self) -> float | None:
        """The population standard deviation (``numpy.std``'s, ``ddof=0``), from the
        exact variance rounded once; None for no values."""
        if self.n == 0:
            return None
        import math

        var = (self.n * self.s2 - self.s1 * self.s1) / (self.n * self.n)
        # scaled by a power of 4 when it exceeds a float (values beyond 1e154)
        k = max(0, (var.numerator.bit_length() - var.denominator.bit_length()) // 2 - 500)
        root = math.sqrt(float(var / (1 << (2 * k))))
        return root * 2.0**k if k < 1000 else math.inf
