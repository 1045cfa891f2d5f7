"""Dilution of precision and the Cramer-Rao lower bound of a position.

For independent Gaussian observations ``z_i = f_i(x) + e_i``, ``e_i ~ N(0, sigma_i^2)``, the
Fisher information of the position is ``J(x) = H^T diag(1 / sigma_i^2) H`` with
``H = d f / d x`` at the true position, and any unbiased estimator has
``cov(x_hat) >= J^-1`` (the Cramer-Rao lower bound, CRLB).  The bound on the position RMSE
is ``sqrt(trace J^-1)``.

* ranges (UWB, WiFi RTT): ``H`` rows are the unit vectors from the anchors, so
  ``J = (1/sigma^2) G^T G`` and ``CRLB = sigma^2 (G^T G)^-1 = (sigma DOP)^2``;
* RSSI with the log-distance model ``RSSI = A - 10 n lg d + N(0, sigma_dB^2)``
  (seed 000 eq. (1)): ``d RSSI / d x = -10 n / (ln 10) (x - a) / d^2``, so each anchor
  contributes ``(10 n / (sigma_dB ln 10 d))^2 u u^T``: ranging precision degrades in
  proportion to distance (the classical RSS CRLB, Patwari et al. 2005).

All functions are batched over ``N`` positions (a grid of tag positions, a trajectory).
Anchors may carry a height while the tag is solved in 2-D: pass ``height_offset`` (the
known vertical offsets between anchors and tag, as in
:class:`robustloc.models.ranging.RangeModel`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc.models.ranging import RangeModel, RssiModel

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DOP:
    """Dilution-of-precision figures of ``N`` geometries (NaN: singular geometry / absent).

    Attributes
    ----------
    gdop : ``sqrt(trace Q)`` over all unknowns, ``Q = (H^T H)^-1``.
    pdop : over the position unknowns.
    hdop : over the first two position unknowns.
    vdop : the third position unknown (NaN for a 2-D position).
    tdop : over the clock unknowns (NaN without clock columns).
    """

    gdop: Array
    pdop: Array
    hdop: Array
    vdop: Array
    tdop: Array


def _inv_info(J: Array, rcond: float = 1e-12) -> tuple[Array, NDArray[np.bool_]]:
    lam, V = np.linalg.eigh(J)
    top = lam[:, -1]
    ok = np.isfinite(top) & (top > 0) & (lam[:, 0] > rcond * np.where(top > 0, top, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        il = np.where(ok[:, None], 1.0 / np.where(lam > 0, lam, 1.0), np.nan)
    return np.einsum("kpi,ki,kqi->kpq", V, il, V), ok


def dop(H: ArrayLike, n_position: int | None = None, weights: ArrayLike | None = None) -> DOP:
    """DOP from a design of unit line-of-sight vectors (plus clock columns).

    Parameters
    ----------
    H : array_like, shape (N, n, p) or (n, p)
        Rows ``[u_i, 1, ...]``: unit vectors (first ``n_position`` columns, in a local frame
        such as ENU for the horizontal / vertical split to be meaningful) then clock columns.
        Rows with NaN are ignored (missing observation).
    n_position : int, optional
        Number of position unknowns (default ``min(p, 3)``); the remaining columns are clock
        terms.
    weights : array_like (N, n), optional
        Relative weights (weighted DOP); default 1.
    """
    h = np.asarray(H, dtype=float)
    if h.ndim == 2:
        h = h[None]
    if h.ndim != 3:
        raise ValueError(f"H must have shape (N, n, p), got {h.shape}")
    N, n, p = h.shape
    k = min(p, 3) if n_position is None else int(n_position)
    if not 1 <= k <= p:
        raise ValueError(f"n_position must be in 1..{p}, got {k}")
    w = np.ones((N, n)) if weights is None else np.broadcast_to(np.asarray(weights, float), (N, n))
    good = np.all(np.isfinite(h), axis=2) & np.isfinite(w)
    hz = np.where(good[..., None], h, 0.0)
    wz = np.where(good, w, 0.0)
    Q, _ = _inv_info(np.einsum("kip,ki,kiq->kpq", hz, wz, hz))
    d = np.diagonal(Q, axis1=1, axis2=2)
    nan = np.full(N, np.nan)
    return DOP(
        gdop=np.sqrt(d.sum(axis=1)),
        pdop=np.sqrt(d[:, :k].sum(axis=1)),
        hdop=np.sqrt(d[:, : min(k, 2)].sum(axis=1)),
        vdop=np.sqrt(d[:, 2]) if k >= 3 else nan,
        tdop=np.sqrt(d[:, k:].sum(axis=1)) if p > k else nan.copy(),
    )


@dataclass(frozen=True)
class CRLB:
    """Cramer-Rao lower bound of ``N`` positions.

    Attributes
    ----------
    cov : ndarray (N, d, d)
        ``J^-1``, m^2 (NaN: singular geometry).
    rmse : ndarray (N,)
        ``sqrt(trace J^-1)``: lower bound on the position RMSE, m.
    horizontal : ndarray (N,)
        ``sqrt(J^-1_xx + J^-1_yy)``, m.
    """

    cov: Array
    rmse: Array
    horizontal: Array


def _crlb_from_jacobian(Jac: Array, sigma: ArrayLike) -> CRLB:
    N, m, d = Jac.shape
    s = np.broadcast_to(np.asarray(sigma, dtype=float), (N, m))
    if np.any(s <= 0):
        raise ValueError("measurement standard deviation must be positive")
    good = np.all(np.isfinite(Jac), axis=2) & np.isfinite(s)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(good, 1.0 / (s * s), 0.0)
    Jz = np.where(good[..., None], Jac, 0.0)
    cov, _ = _inv_info(np.einsum("kip,ki,kiq->kpq", Jz, w, Jz))
    dg = np.diagonal(cov, axis1=1, axis2=2)
    return CRLB(cov=cov, rmse=np.sqrt(dg.sum(axis=1)), horizontal=np.sqrt(dg[:, :2].sum(axis=1)))


def _positions(positions: ArrayLike, dim: int) -> Array:
    x = np.atleast_2d(np.asarray(positions, dtype=float))
    if x.shape[1] != dim:
        raise ValueError(f"positions must have {dim} columns like the anchors, got {x.shape}")
    return x


def ranging_dop(
    anchors: ArrayLike,
    positions: ArrayLike,
    height_offset: ArrayLike | None = None,
    mask: ArrayLike | None = None,
) -> DOP:
    """DOP of range positioning from ``anchors (m, d)`` at tag ``positions (N, d)``.

    ``mask (N, m)`` selects the anchors heard at each position (default: all).
    """
    model = RangeModel(np.asarray(anchors, float), height_offset)
    G = model.jacobian(_positions(positions, model.dim))
    if mask is not None:
        G = np.where(np.asarray(mask, bool)[..., None], G, np.nan)
    return dop(G, n_position=model.dim)


def crlb_range(
    anchors: ArrayLike,
    positions: ArrayLike,
    sigma_m: ArrayLike,
    height_offset: ArrayLike | None = None,
    mask: ArrayLike | None = None,
) -> CRLB:
    """CRLB of a position from ranges with Gaussian noise ``sigma_m`` (scalar, (m,) or (N, m)).

    ``CRLB = sigma^2 (G^T G)^-1`` for equal sigmas, ``G`` the unit vectors.
    """
    model = RangeModel(np.asarray(anchors, float), height_offset)
    G = model.jacobian(_positions(positions, model.dim))
    if mask is not None:
        G = np.where(np.asarray(mask, bool)[..., None], G, np.nan)
    return _crlb_from_jacobian(G, sigma_m)


def crlb_rssi(
    anchors: ArrayLike,
    positions: ArrayLike,
    sigma_db: ArrayLike,
    n: ArrayLike,
    height_offset: ArrayLike | None = None,
    mask: ArrayLike | None = None,
) -> CRLB:
    """CRLB of a position from log-distance RSSI (seed 000 eq. (1)) with shadowing ``sigma_db``.

    Parameters
    ----------
    anchors : (m, d) anchor coordinates, m.
    positions : (N, d) true tag positions, m.
    sigma_db : float or array_like
        Standard deviation of the RSSI about the model, dB.
    n : float or (m,)
        Path-loss exponents (``A`` does not enter the bound).
    height_offset, mask : see :func:`crlb_range`.
    """
    model = RssiModel(np.asarray(anchors, float), A=0.0, n=n, height_offset=height_offset)
    J = model.jacobian(_positions(positions, model.anchors.shape[1]))
    if mask is not None:
        J = np.where(np.asarray(mask, bool)[..., None], J, np.nan)
    return _crlb_from_jacobian(J, sigma_db)
