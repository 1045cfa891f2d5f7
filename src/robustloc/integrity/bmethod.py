"""Baarda's B-method: tie the global test to the local w-test (seed 003, eqs. (3)-(4)).

The local w-test of one observation is run at significance ``alpha0`` and power
``1 - beta0``; a bias that the w-test detects with probability ``1 - beta0`` shifts the
w-statistic by ``sqrt(lambda0)``, with

``lambda0 = (N(1 - alpha0/2) + N(1 - beta0))^2``                     (seed 003, eq. (3))

(``N(q)`` the standard normal quantile).  The global test on ``v^T P v`` with ``dof = n - p``
degrees of freedom then gets the significance ``alpha`` for which the same bias is detected
with the same power ``1 - beta0``: the ``beta0`` quantile of the non-central chi-square with
non-centrality ``lambda0`` equals the ``1 - alpha`` quantile of the central one,

``chi2(beta0; dof, lambda0) = chi2(1 - alpha; dof)``                  (seed 003, eq. (4))

so ``alpha = chi2.sf(ncx2.ppf(beta0, dof, lambda0), dof)`` in closed form (no root search).
Reference values (``alpha0 = 0.1 %``, ``beta0 = 10 %``): ``lambda0 = 20.90``;
``alpha = 0.0010, 0.0029, 0.0057, 0.0095, 0.0193`` for ``dof = 1, 2, 3, 4, 6``.
"""

from __future__ import annotations

import numbers
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc._stats import chi2_isf, chi2_sf, ncx2_ppf, norm_cdf, norm_ppf

#: Default significance of the local w-test (seed 003: 0.1 %).
ALPHA0 = 0.001
#: Default probability of a missed detection (type II error) of the w-test (seed 003: 10 %).
BETA0 = 0.10


def _check_prob(name: str, value: float) -> float:
    # a real number only: float() took the string "0.1" and called True 1.0, and None
    # gave float()'s own message without the parameter's name
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    value = float(value)
    if not 0.0 < value < 1.0:
        raise ValueError(f"{name} must be strictly between 0 and 1, got {value}")
    return value


@lru_cache(maxsize=256)  # pure; every protected block asks for the same few values
def lambda0(alpha0: float = ALPHA0, beta0: float = BETA0) -> float:
    """Reference non-centrality ``lambda0 = (N(1-alpha0/2) + N(1-beta0))^2`` (seed 003, eq. (3)).

    Parameters
    ----------
    alpha0 : float
        Significance of the two-sided local w-test.
    beta0 : float
        Type II error (1 - power) of the w-test for a bias of the size of the MDB.

    Returns
    -------
    float
        ``lambda0`` (20.90 for the defaults).
    """
    a = _check_prob("alpha0", alpha0)
    b = _check_prob("beta0", beta0)
    return float((norm_ppf(1.0 - a / 2.0) + norm_ppf(1.0 - b)) ** 2)


@lru_cache(maxsize=256)
def w_critical(alpha0: float = ALPHA0) -> float:
    """Critical value ``N(1 - alpha0/2)`` of the two-sided w-test (3.29 for 0.1 %)."""
    return float(norm_ppf(1.0 - _check_prob("alpha0", alpha0) / 2.0))


@lru_cache(maxsize=4096)
def _alpha_one(dof: int, alpha0: float, beta0: float) -> float:
    lam = lambda0(alpha0, beta0)
    q = ncx2_ppf(beta0, dof, lam)  # seed 003, eq. (4): left side (lam > 0)
    return float(chi2_sf(q, dof))  # 1 - alpha quantile equals q


def _alpha_direct(
    dof: NDArray[np.float64], alpha0: float, beta0: float
) -> NDArray[np.float64]:
    """Eq. (4) for non-integer ``dof`` (vectorized, not cached): as :func:`_alpha_one`."""
    q = ncx2_ppf(beta0, dof, lambda0(alpha0, beta0))
    return np.asarray(chi2_sf(q, dof), dtype=float)


def global_alpha(
    dof: ArrayLike, alpha0: float = ALPHA0, beta0: float = BETA0
) -> NDArray[np.float64]:
    """Significance of the global test for ``dof`` degrees of freedom (seed 003, eq. (4)).

    Solves ``chi2(beta0; dof, lambda0) = chi2(1 - alpha; dof)`` for ``alpha``.  Vectorized
    over ``dof``; each distinct whole ``dof`` is computed once and cached, a non-integer
    ``dof`` (the chi-square of real degrees of freedom) directly.

    Parameters
    ----------
    dof : float or array_like of float
        Redundancy ``n - p`` (any shape).  Entries ``< 1`` give NaN (no test possible).
    alpha0, beta0 : float
        Local-test significance and type II error (defaults 0.1 %, 10 %).

    Returns
    -------
    ndarray
        ``alpha`` with the shape of ``dof`` (0-d array for a scalar).
    """
    a0 = _check_prob("alpha0", alpha0)
    b0 = _check_prob("beta0", beta0)
    d = np.asarray(dof)
    out = np.full(d.shape, np.nan)
    finite = np.isfinite(d) & (d >= 1)
    whole = finite & (d == np.floor(d))
    if np.any(whole):
        keys, inv = np.unique(d[whole].astype(np.int64), return_inverse=True)
        vals = np.array([_alpha_one(int(k), a0, b0) for k in keys])
        out[whole] = vals[inv]
    rest = finite & ~whole
    if np.any(rest):  # non-integer dof: eq. (4) as asked (it was rounded down)
        out[rest] = _alpha_direct(np.asarray(d[rest], dtype=float), a0, b0)
    return out


def global_critical(
    dof: ArrayLike,
    alpha: ArrayLike | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
) -> NDArray[np.float64]:
    """Critical value ``chi2(1 - alpha; dof)`` of the global test on ``v^T P v / sigma0^2``.

    Parameters
    ----------
    dof : array_like of float
        Degrees of freedom ``n - p``; entries ``< 1`` give NaN.
    alpha : float or array_like, optional
        Significance; default: the B-method value :func:`global_alpha` for each ``dof``.
    alpha0, beta0 : float
        Used only when ``alpha`` is None (checked always).

    Returns
    -------
    ndarray
        Critical values with the broadcast shape of ``dof`` and ``alpha``.
    """
    d = np.asarray(dof, dtype=float)
    a0 = _check_prob("alpha0", alpha0)  # (checked also when unused: NaN went through)
    b0 = _check_prob("beta0", beta0)
    if alpha is None:  # one quantile per distinct dof (a block has a handful), cached
        out = np.full(d.shape, np.nan)
        whole = np.isfinite(d) & (d >= 1) & (d == np.floor(d))
        if np.any(whole):
            keys, inv = np.unique(d[whole].astype(np.int64), return_inverse=True)
            vals = np.array([_critical_one(int(k), a0, b0) for k in keys])
            out[whole] = vals[inv.reshape(-1)]
        rest = np.isfinite(d) & (d >= 1) & ~whole
        if np.any(rest):  # non-integer dof: as asked, directly
            out[rest] = chi2_isf(global_alpha(d[rest], a0, b0), d[rest])
        return out
    a = np.asarray(alpha, dtype=float)
    if not np.all((a > 0) & (a < 1)):  # (NaN refused: every test failed silently)
        raise ValueError(f"alpha must be strictly between 0 and 1, got {alpha}")
    with np.errstate(invalid="ignore"):
        out = chi2_isf(a, np.where(d >= 1, d, np.nan))
    return np.asarray(out, dtype=float)


@lru_cache(maxsize=4096)
def _critical_one(dof: int, alpha0: float, beta0: float) -> float:
    return float(chi2_isf(_alpha_one(dof, alpha0, beta0), dof))


def detection_power_w(
    bias_over_sigma_w: ArrayLike, alpha0: float = ALPHA0
) -> NDArray[np.float64]:
    """Probability that the two-sided w-test rejects, for a w-statistic shifted by ``delta``.

    ``P(|N(delta, 1)| > k) = Phi(delta - k) + Phi(-delta - k)``, ``k = N(1 - alpha0/2)``.
    For ``delta = sqrt(lambda0)`` (a bias equal to the MDB) this is ``1 - beta0`` up to the
    negligible far tail.
    """
    k = w_critical(alpha0)
    d = np.abs(np.asarray(bias_over_sigma_w, dtype=float))
    return norm_cdf(d - k) + norm_cdf(-d - k)


def detection_power_global(
    noncentrality: ArrayLike,
    dof: ArrayLike,
    alpha: ArrayLike | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
) -> NDArray[np.float64]:
    """Probability that the global test rejects: ``1 - ncx2.cdf(crit, dof, lambda)``.

    ``noncentrality`` is ``lambda = delta^2`` (``lambda0`` for a single bias of MDB size, for
    which the result is ``1 - beta0`` by construction of the B-method).
    """
    from scipy import stats  # (the planners' and Monte Carlo's, not the pipelines')

    crit = global_critical(dof, alpha, alpha0, beta0)
    lam = np.asarray(noncentrality, dtype=float)
    d = np.asarray(dof, dtype=float)
    with np.errstate(invalid="ignore"):
        p = np.asarray(stats.ncx2.sf(crit, d, np.maximum(lam, 1e-300)), dtype=float)
    # scipy returns NaN from lambda ~ 1e19 on (montecarlo --size 1e6 --sigma 1e-4: the
    # review); from 1e15 the distribution's mean lies 1e7 standard deviations above any
    # critical value of a test's degrees of freedom, so the power is 1 to double precision
    return np.where(np.isnan(p) & (lam >= 1e15), 1.0, p)
