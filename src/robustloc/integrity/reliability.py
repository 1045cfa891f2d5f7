"""Internal and external reliability of a (linearized) least-squares adjustment (seed 003).

Batched over ``N`` epochs (or grid points) with ``n`` observations and ``p`` unknowns; the
weight matrix is ``P = diag(1 / sigma_i^2)`` (a-priori unit-weight sigma0 = 1), see
:mod:`robustloc.integrity.tests`.

* **Redundancy numbers** ``r_i = (Q_vv P)_ii`` in ``[0, 1]``; ``sum_i r_i = n - p``.  ``r_i``
  is the part of a bias on observation ``i`` that shows in its own residual.
* **Minimal detectable bias** ``MDB_i = sigma_i sqrt(lambda0 / r_i)`` (seed 003): the bias the
  w-test detects with probability ``1 - beta0`` at significance ``alpha0``.
* **External reliability**: the effect on the estimate of an undetected bias of size
  ``MDB_i`` on observation ``i``, ``dx_i = (H^T P H)^-1 H^T P e_i MDB_i``; reported per
  unknown and as a horizontal length over ``horizontal`` axes, plus the dimensionless
  bias-to-noise ratio ``sqrt(lambda0 (1 - r_i) / r_i)``.
* **Correlation of the w-tests** ``rho_ij = Q_vv,ij / sqrt(Q_vv,ii Q_vv,jj)`` (seed 003):
  when ``|rho_ij|`` is close to 1, a bias on ``i`` moves ``w_j`` nearly as much as ``w_i`` and
  data snooping cannot tell which observation is faulty.  Pairs with
  ``|rho_ij| > rho_threshold`` are flagged; the default :data:`RHO_THRESHOLD` = 0.9 means
  that, for a bias of MDB size on ``i`` (``E[w_i] = sqrt(lambda0) = 4.57``), ``E[w_j]`` is
  at least 4.11, and the wrong observation has the larger w-test statistic with a
  probability of about 15 % (``Phi(-sqrt(lambda0) (1 - rho) / sqrt(2 - 2 rho))``, the
  difference ``w_i - w_j`` being normal with mean ``sqrt(lambda0) (1 - rho)`` and variance
  ``2 - 2 rho``: 15 % at ``rho = 0.9``, 23 % at 0.95, 37 % at 0.99), so identification
  is unreliable (at ``|rho| = 1`` it is a coin toss).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc.integrity.bmethod import ALPHA0, BETA0, lambda0
from robustloc.integrity.tests import R_MIN, RCOND, whiten

Array = NDArray[np.float64]

#: Default ``|rho_ij|`` above which two observations' gross errors are flagged as not
#: separable (see the module docstring for the reasoning).
RHO_THRESHOLD = 0.9


@dataclass(frozen=True)
class Reliability:
    """Reliability measures of ``N`` epochs / grid points.

    Attributes
    ----------
    redundancy : ndarray (N, n)
        ``r_i``; NaN for unused observations.
    redundancy_total : ndarray (N,)
        ``sum r_i`` (equals ``n_used - p`` for a well-conditioned epoch).
    mdb : ndarray (N, n)
        Minimal detectable bias, observation units; ``inf`` where ``r_i = 0``.
    external : ndarray (N, n, p)
        Effect of an undetected ``MDB_i`` on each unknown (signed).
    external_horizontal : ndarray (N, n)
        Its length over the ``horizontal`` unknowns.
    bias_to_noise : ndarray (N, n)
        ``sqrt(lambda0 (1 - r_i) / r_i)``.
    rho : ndarray (N, n, n)
        Correlation of the w-tests ``rho_ij`` (1 on the diagonal, NaN for unused).
    max_abs_rho : ndarray (N,)
        Largest off-diagonal ``|rho_ij|``.
    flagged : ndarray of bool (N, n, n)
        ``|rho_ij| > rho_threshold``, ``i != j``.
    n_used : ndarray of int (N,)
    ok : ndarray of bool (N,)
        Normal matrix invertible.
    lambda0, rho_threshold : float
    """

    redundancy: Array
    redundancy_total: Array
    mdb: Array
    external: Array
    external_horizontal: Array
    bias_to_noise: Array
    rho: Array
    max_abs_rho: Array
    flagged: NDArray[np.bool_]
    n_used: NDArray[np.int64]
    ok: NDArray[np.bool_]
    lambda0: float
    rho_threshold: float

    def flagged_pairs(self, epoch: int = 0) -> list[tuple[int, int, float]]:
        """Pairs ``(i, j, rho_ij)``, ``i < j``, flagged in one epoch."""
        ii, jj = np.nonzero(np.triu(self.flagged[epoch], 1))
        return [(int(i), int(j), float(self.rho[epoch, i, j])) for i, j in zip(ii, jj)]

    @property
    def min_redundancy(self) -> Array:
        """Smallest ``r_i`` per epoch."""
        return _nan_reduce(np.nanmin, self.redundancy)

    @property
    def max_mdb(self) -> Array:
        """Largest ``MDB_i`` per epoch."""
        return _nan_reduce(np.nanmax, self.mdb)

    @property
    def max_external_horizontal(self) -> Array:
        """Largest horizontal effect of an undetected MDB per epoch."""
        return _nan_reduce(np.nanmax, self.external_horizontal)


def _nan_reduce(fn, a: Array) -> Array:  # noqa: ANN001
    ok = np.any(~np.isnan(a), axis=1)
    out = np.full(a.shape[0], np.nan)
    if np.any(ok):
        out[ok] = fn(a[ok], axis=1)
    return out


def check_chunk(chunk: int) -> None:
    """``chunk`` (epochs processed at once) a whole number >= 1: 0 said "range() arg 3
    must not be zero" (the API review)."""
    if isinstance(chunk, bool) or not (isinstance(chunk, int | np.integer) and chunk >= 1):
        raise ValueError(f"chunk must be a whole number >= 1, got {chunk!r}")


def reliability(
    H: ArrayLike,
    sigma: ArrayLike,
    mask: ArrayLike | None = None,
    *,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
    rho_threshold: float = RHO_THRESHOLD,
    horizontal: tuple[int, ...] | None = None,
    rcond: float = RCOND,
    chunk: int = 2048,
) -> Reliability:
    """Redundancy, MDB, external reliability and w-test correlation (seed 003).

    Parameters
    ----------
    H : array_like, shape (N, n, p) or (n, p)
        Design (Jacobian) matrix at the (true or estimated) solution.
    sigma : float or array_like, broadcastable to (N, n)
        A-priori standard deviations of the observations.
    mask : array_like of bool (N, n), optional
        Observations used (default: every row with a finite design row and sigma).
    alpha0, beta0 : float
        Significance and type II error of the w-test (define ``lambda0``).
    rho_threshold : float
        ``|rho_ij|`` above which a pair is flagged (default 0.9).
    horizontal : tuple of int, optional
        Unknowns whose combined length is the horizontal external reliability (default the
        first two, ``(0, 1)``: x, y, or east, north of a design expressed in ENU).
    rcond : float
        Conditioning floor of the normal matrix.
    chunk : int
        Epochs processed at once (the ``(N, n, n)`` correlation matrices bound memory).

    Returns
    -------
    Reliability
    """
    Hm = np.asarray(H, dtype=float)
    check_chunk(chunk)
    if mask is not None and Hm.ndim in (2, 3):
        try:  # (a mask of the wrong width said "operands could not be broadcast")
            np.broadcast_to(np.asarray(mask, dtype=bool), Hm.shape[:-1])
        except ValueError:
            raise ValueError(f"mask has shape {np.shape(mask)}; expected {Hm.shape[:-1]} "
                             "(epochs, observations) or one that broadcasts to it") from None
    if Hm.ndim == 3 and Hm.shape[0] > chunk:
        N = Hm.shape[0]
        sig = np.broadcast_to(np.asarray(sigma, dtype=float), Hm.shape[:2])
        mk = None if mask is None else np.broadcast_to(np.asarray(mask, bool), Hm.shape[:2])
        parts = [
            reliability(Hm[s : s + chunk], sig[s : s + chunk],
                        None if mk is None else mk[s : s + chunk], alpha0=alpha0, beta0=beta0,
                        rho_threshold=rho_threshold, horizontal=horizontal, rcond=rcond,
                        chunk=chunk)
            for s in range(0, N, chunk)
        ]
        arrays = {k: np.concatenate([getattr(p, k) for p in parts]) for k in (
            "redundancy", "redundancy_total", "mdb", "external", "external_horizontal",
            "bias_to_noise", "rho", "max_abs_rho", "flagged", "n_used", "ok")}
        return Reliability(**arrays, lambda0=parts[0].lambda0,
                           rho_threshold=parts[0].rho_threshold)
    if not 0.0 < rho_threshold <= 1.0:
        raise ValueError(f"rho_threshold must be in (0, 1], got {rho_threshold}")
    wh = whiten(H, sigma, mask=mask, rcond=rcond)
    N, n, p = wh.A.shape
    if horizontal is None:
        horizontal = tuple(range(min(2, p)))
    if any(not 0 <= h < p for h in horizontal):
        raise ValueError(f"horizontal axes {horizontal} out of range for {p} unknowns")
    lam = lambda0(alpha0, beta0)
    valid = wh.used & wh.ok[:, None]
    U = wh.hat()
    R = np.eye(n)[None] - U  # whitened Q_vv P, seed 003 eq. (2)
    r = np.clip(np.diagonal(R, axis1=1, axis2=2), 0.0, 1.0)
    r = np.where(valid, r, np.nan)
    with np.errstate(divide="ignore", invalid="ignore"):
        rpos = np.where(r > R_MIN, r, np.nan)
        mdb = np.where(valid, np.where(r > R_MIN, wh.sigma * np.sqrt(lam / rpos), np.inf), np.nan)
        bnr = np.where(valid, np.where(r > R_MIN, np.sqrt(lam * (1 - r) / rpos), np.inf), np.nan)
        # dx_i = Ninv A^T e_i (MDB_i / sigma_i)
        G = np.einsum("kpq,kiq->kip", wh.Ninv, wh.A)
        ext = G * (mdb / wh.sigma)[:, :, None]
        ext = np.where(valid[:, :, None], ext, np.nan)
        ext = np.where(np.isinf(mdb)[:, :, None], np.inf, ext)
        ext_h = np.sqrt(np.sum(ext[:, :, list(horizontal)] ** 2, axis=2))
        sr = np.sqrt(rpos)
        # a correlation, within [-1, 1] (rounding gave 1.000000000000001, flagged above a
        # threshold of 1: the reliability review)
        rho = np.clip(R / (sr[:, :, None] * sr[:, None, :]), -1.0, 1.0)
    eye = np.eye(n, dtype=bool)[None]
    rho = np.where(eye & valid[:, :, None], 1.0, rho)
    off = np.where(eye, np.nan, np.abs(rho))
    flagged = np.nan_to_num(off, nan=0.0) > rho_threshold
    maxrho = np.full(N, np.nan)
    has = np.any(np.isfinite(off), axis=(1, 2))
    if np.any(has):
        maxrho[has] = np.nanmax(off[has], axis=(1, 2))
    return Reliability(
        redundancy=r,
        redundancy_total=np.where(wh.ok, np.nansum(r, axis=1), np.nan),
        mdb=mdb,
        external=ext,
        external_horizontal=ext_h,
        bias_to_noise=bnr,
        rho=rho,
        max_abs_rho=maxrho,
        flagged=flagged,
        n_used=wh.n_used,
        ok=wh.ok,
        lambda0=lam,
        rho_threshold=float(rho_threshold),
    )
