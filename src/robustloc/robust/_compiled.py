"""Compiled (numba) twins of the weight functions in :mod:`robustloc.robust.weights`.

A weight object describes itself to compiled kernels by :func:`weight_spec`: an integer
code and a parameter vector.  :func:`weight_value` evaluates ``p(u)`` for one scalar with
the same formulas as the NumPy ``weights`` methods (tests check them against each other);
:func:`rho_value` does the same for ``rho(u)``.  Custom ``WeightFunction`` subclasses have
no compiled twin: :func:`weight_spec` returns ``None`` for them and callers fall back to the
NumPy path.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from robustloc.robust.weights import (
    IGG,
    IGG3,
    AsymmetricIGG,
    Hampel,
    Huber,
    LeastSquares,
    WeightFunction,
)

LS, HUBER, HAMPEL, IGG1, IGG_III, ASYM_IGG = 0, 1, 2, 3, 4, 5


def weight_spec(weight: WeightFunction | None) -> tuple[int, np.ndarray] | None:
    """``(code, params)`` of a built-in weight function (exact class), else ``None``.

    ``weight=None`` (no robust weighting) is least squares: code ``LS``.
    """
    t = type(weight)
    if weight is None or t is LeastSquares:
        return LS, np.zeros(3)
    if t is Huber:
        return HUBER, np.array([weight.c, 0.0, 0.0])
    if t is Hampel:
        return HAMPEL, np.array([weight.a, weight.b, weight.c])
    if t is IGG:
        return IGG1, np.array([weight.k0, weight.k1, weight.c])
    if t is IGG3:
        return IGG_III, np.array([weight.k0, weight.k1, 0.0])
    if t is AsymmetricIGG:
        return ASYM_IGG, np.array([weight.k0, weight.k1, weight.c])
    return None


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def weight_value(code: int, prm: np.ndarray, u: float) -> float:  # pragma: no cover - jit
    """Equivalent weight ``p(u)`` (NaN for NaN ``u``), parameters from ``prm[:3]``."""
    return weight_scalar(code, prm[0], prm[1], prm[2], u)


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def weight_scalar(code: int, p0: float, p1: float, p2: float,
                  u: float) -> float:  # pragma: no cover - jit
    """Equivalent weight ``p(u)`` with the parameters as scalars (no array passes from a
    kernel that keeps reference counts, which would cost two atomic operations a call)."""
    prm = (p0, p1, p2)
    if math.isnan(u):
        return math.nan
    x = abs(u)
    if code == LS:
        return 1.0
    if code == HUBER:  # seed 000 eq. (5)
        return 1.0 if x <= prm[0] else prm[0] / x
    if code == HAMPEL:  # seed 000 eq. (6)
        a, b, c = prm[0], prm[1], prm[2]
        if x <= a:
            return 1.0
        if x <= b:
            return a / x
        if x <= c:
            return a * (c - x) / ((c - b) * x)
        return 0.0
    if code == IGG1:  # seed 000 eq. (7)
        if x < prm[0]:
            return 1.0
        if x < prm[1]:
            return 1.0 / (x + prm[2])
        return 0.0
    if code == IGG_III:
        k0, k1 = prm[0], prm[1]
        if x <= k0:
            return 1.0
        if x <= k1:
            r = (k1 - x) / (k1 - k0)
            return (k0 / x) * r * r
        return 0.0
    # ASYM_IGG, seed 002 eq. (14)
    k0, k1, c = prm[0], prm[1], prm[2]
    e = u
    if e < -c:
        return 0.0
    if e < -k0:
        return (-k0 / e) * (c + e) / (c - k0)
    if e < k0:
        return 1.0
    if e < k1:
        r = (k1 - e) / (k1 - k0)
        return (k0 / e) * r * r
    return 0.0


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def rho_value(code: int, prm: np.ndarray, u: float) -> float:  # pragma: no cover - jit
    """Objective ``rho(u)`` (NaN for NaN ``u``), the same formulas as the NumPy ``rho``
    methods."""
    if math.isnan(u):  # (Hampel and IGG fell through to their outer value)
        return math.nan
    x = abs(u)
    if code == LS:
        return 0.5 * u * u
    if code == HUBER:
        c = prm[0]
        return 0.5 * x * x if x <= c else c * x - 0.5 * c * c
    if code == HAMPEL:
        a, b, c = prm[0], prm[1], prm[2]
        r_b = a * b - 0.5 * a * a
        if x <= a:
            return 0.5 * x * x
        if x <= b:
            return a * x - 0.5 * a * a
        if x <= c:
            return r_b + a / (c - b) * (c * x - 0.5 * x * x - c * b + 0.5 * b * b)
        return r_b + 0.5 * a * (c - b)
    if code == IGG1:
        k0, k1, c = prm[0], prm[1], prm[2]
        if x < k0:
            return 0.5 * x * x
        t = x if x < k1 else k1
        return 0.5 * k0 * k0 + (t - k0) - c * math.log((t + c) / (k0 + c))
    if code == IGG_III:
        k0, k1 = prm[0], prm[1]
        if x <= k0:
            return 0.5 * x * x
        g = k0 / (3.0 * (k1 - k0) ** 2)
        return 0.5 * k0 * k0 + g * ((k1 - k0) ** 3 - (k1 - min(x, k1)) ** 3)
    k0, k1, c = prm[0], prm[1], prm[2]
    e = u
    if e < -k0:
        en = max(e, -c)
        return 0.5 * k0 * k0 + k0 / (2.0 * (c - k0)) * ((c - k0) ** 2 - (c + en) ** 2)
    if e < k0:
        return 0.5 * e * e
    g = k0 / (3.0 * (k1 - k0) ** 2)
    return 0.5 * k0 * k0 + g * ((k1 - k0) ** 3 - (k1 - min(e, k1)) ** 3)
