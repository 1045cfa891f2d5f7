"""The few distribution functions the command-line pipelines need, from ``scipy.special``.

``import scipy.stats`` costs about 1.1 s more than ``import scipy.special`` (it builds every
distribution and parses their docstrings), and every ``robustloc locate`` / ``track`` /
``fuse`` run paid it for a handful of chi-square and normal quantiles.  These are the
same ``scipy.special`` calls that ``scipy.stats`` makes for them (SciPy 1.17,
``scipy/stats/_continuous_distns.py``: ``chi2_gen._sf``, ``_isf``, ``_ppf``;
``norm_gen._ppf``, ``_cdf``; ``t_gen._ppf``; ``ncx2_gen._ppf`` for a non-zero
non-centrality), so the values are identical (tested against ``scipy.stats``), without
its argument checks: callers pass probabilities in ``(0, 1)`` and positive degrees of
freedom, and anything else gives NaN here as there.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

__all__ = ["chi2_isf", "chi2_ppf", "chi2_sf", "ncx2_ppf", "norm_cdf", "norm_ppf", "t_ppf"]


def chi2_sf(x: ArrayLike, df: ArrayLike) -> NDArray[np.float64]:
    """``scipy.stats.chi2.sf(x, df)``: ``P(X > x)`` for ``X ~ chi2(df)``."""
    return np.asarray(special.chdtrc(df, x), dtype=float)


def chi2_isf(q: ArrayLike, df: ArrayLike) -> NDArray[np.float64]:
    """``scipy.stats.chi2.isf(q, df)``: the ``x`` with ``P(X > x) = q``."""
    return np.asarray(special.chdtri(df, q), dtype=float)


def chi2_ppf(p: ArrayLike, df: ArrayLike) -> NDArray[np.float64]:
    """``scipy.stats.chi2.ppf(p, df)``: the ``x`` with ``P(X <= x) = p``."""
    return np.asarray(2.0 * special.gammaincinv(np.divide(df, 2.0), p), dtype=float)


def norm_ppf(p: ArrayLike) -> NDArray[np.float64]:
    """``scipy.stats.norm.ppf(p)``: the standard normal quantile."""
    return np.asarray(special.ndtri(p), dtype=float)


def norm_cdf(x: ArrayLike) -> NDArray[np.float64]:
    """``scipy.stats.norm.cdf(x)``: the standard normal distribution function."""
    return np.asarray(special.ndtr(x), dtype=float)


def ncx2_ppf(p: ArrayLike, df: ArrayLike, nc: ArrayLike) -> NDArray[np.float64]:
    """``scipy.stats.ncx2.ppf(p, df, nc)`` for ``nc > 0`` (the central case is
    :func:`chi2_ppf`): the non-central chi-square quantile."""
    return np.asarray(special.chndtrix(p, df, nc), dtype=float)


def t_ppf(p: ArrayLike, df: ArrayLike) -> NDArray[np.float64]:
    """``scipy.stats.t.ppf(p, df)``: Student's t quantile."""
    return np.asarray(special.stdtrit(df, p), dtype=float)
