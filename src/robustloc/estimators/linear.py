"""Batched least-squares kernels on linear models ``y = H x + e`` (pure arrays).

Every function solves ``N`` independent systems at once: ``H`` has shape ``(N, n, p)``,
``y`` shape ``(N, n)`` with NaN marking a missing observation, optional a-priori weights
``w`` shape ``(N, n)`` (the diagonal of ``P``).  Residuals follow the papers' convention
``v = H x - y`` (seed 000 eq. (4)).

* :func:`solve_wls`: (weighted) least squares, seed 000 eq. (3).
* :func:`irls`: robust "selection-of-weights iteration" with any
  :class:`~robustloc.robust.WeightFunction` (seed 000 sec. 2, eqs. (5)-(7)).
* :func:`lege`: simultaneous location and estimation of several gross errors
  (seed 000 sec. 2.4, eqs. (8)-(12), with the digest's sign correction ``S = I - R``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc._arrays import true_first
from robustloc.estimators._kernels import inv_spd, normal_matrix
from robustloc.robust.scale import mad_scale
from robustloc.robust.weights import Huber, WeightFunction

Array = NDArray[np.float64]



@dataclass(frozen=True)
class LinearFit:
    """Result of a batched linear fit.

    Attributes
    ----------
    x : (N, p) estimated parameters (NaN where no solution).
    v : (N, n) residuals ``H x - y`` (NaN for missing observations).
    w : (N, n) final weights (a-priori times equivalent weight; 0 = rejected, NaN = missing).
    qvv : (N, n) diagonal of the residual cofactor matrix ``Q_vv`` of the final fit
        (``1/w_i - h_i^T N^-1 h_i``; ``inf`` for rejected observations).
    sigma0 : (N,) a-posteriori unit-weight standard error ``sqrt(v^T P v / (n_used - p))``.
    cov : (N, p, p) covariance ``sigma0^2 N^-1`` (``N^-1`` alone when the redundancy is 0).
    n_used : (N,) observations with non-zero weight.
    iterations, converged, status : per epoch.
    extra : dict of method-specific per-epoch arrays.
    """

    x: Array
    v: Array
    w: Array
    qvv: Array
    sigma0: Array
    cov: Array
    n_used: NDArray[np.int64]
    iterations: NDArray[np.int64]
    converged: NDArray[np.bool_]
    status: NDArray[np.object_]
    extra: dict = field(default_factory=dict)


def _prepare(H: ArrayLike, y: ArrayLike, w: ArrayLike | None) -> tuple[Array, Array, Array]:
    H = np.asarray(H, dtype=float)
    y = np.asarray(y, dtype=float)
    if H.ndim == 2:  # one epoch
        H, y = H[None], y[None]
        if w is not None:
            w = np.asarray(w, dtype=float)[None]
    if H.ndim != 3 or y.shape != H.shape[:2]:
        raise ValueError(f"expected H (N, n, p) and y (N, n), got {H.shape} and {y.shape}")
    w = np.ones_like(y) if w is None else np.broadcast_to(np.asarray(w, dtype=float), y.shape)
    valid = np.isfinite(y) & np.all(np.isfinite(H), axis=2) & np.isfinite(w)
    w = np.where(valid, w, 0.0)
    H = np.where(valid[..., None], H, 0.0)
    return H, y, w


def _normal_solve(H: Array, y: Array, w: Array) -> tuple[Array, Array, NDArray[np.bool_]]:
    """Solve the weighted normal equations; returns ``x``, ``N^-1`` and a good-geometry mask."""
    yz = np.where(w > 0, y, 0.0)
    HwT = np.swapaxes(H * w[..., None], 1, 2)
    Nm = np.matmul(HwT, H)
    b = np.matmul(HwT, yz[..., None])[..., 0]
    Ninv, good = inv_spd(Nm)
    x = np.matmul(Ninv, b[..., None])[..., 0]
    x[~good] = np.nan
    Ninv[~good] = np.nan
    return x, Ninv, good


def _finish(
    H: Array, y: Array, w: Array, x: Array, Ninv: Array, good: NDArray[np.bool_]
) -> tuple[Array, Array, Array, Array, NDArray[np.int64]]:
    """Residuals, Q_vv diagonal, sigma0 and covariance of a solved system."""
    p = H.shape[2]
    v = np.einsum("kni,ki->kn", H, x) - y
    observed = np.isfinite(y)
    v = np.where(observed, v, np.nan)
    n_used = np.sum(w > 0, axis=1)
    dof = n_used - p
    with np.errstate(all="ignore"):
        hNh = np.sum(np.matmul(H, Ninv) * H, axis=2)
        qvv = np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0) - hNh, np.inf)
        qvv = np.where(observed, np.maximum(qvv, 0.0), np.nan)
        vpv = np.nansum(np.where(w > 0, w * v * v, 0.0), axis=1)
        sigma0 = np.where(dof > 0, np.sqrt(vpv / np.maximum(dof, 1)), np.nan)
        s2 = np.where(dof > 0, sigma0**2, 1.0)
    cov = Ninv * s2[:, None, None]
    sigma0 = np.where(good, sigma0, np.nan)
    return v, qvv, sigma0, cov, n_used


def _status(good: NDArray[np.bool_], n_valid: NDArray[np.int64], p: int) -> NDArray[np.object_]:
    out = np.full(good.shape, st.OK, dtype=object)
    out[~good] = st.ILL_CONDITIONED
    out[n_valid < p] = st.INSUFFICIENT
    return out


def solve_wls(H: ArrayLike, y: ArrayLike, w: ArrayLike | None = None) -> LinearFit:
    """Batched weighted least squares ``x = (H^T P H)^-1 H^T P y`` (seed 000 eq. (3)).

    Parameters
    ----------
    H : array_like, shape (N, n, p)
        Design matrices (a single ``(n, p)`` system is accepted as ``N = 1``).
    y : array_like, shape (N, n)
        Observations; NaN marks a missing one.
    w : array_like, shape (N, n) or broadcastable, optional
        A-priori weights (diagonal of ``P``); 1 by default.

    Returns
    -------
    LinearFit
    """
    H, y, w = _prepare(H, y, w)
    x, Ninv, good = _normal_solve(H, y, w)
    v, qvv, sigma0, cov, n_used = _finish(H, y, w, x, Ninv, good)
    N = H.shape[0]
    return LinearFit(
        x=x, v=v, w=np.where(np.isfinite(y), w, np.nan), qvv=qvv, sigma0=sigma0, cov=cov,
        n_used=n_used, iterations=np.ones(N, dtype=np.int64), converged=good.copy(),
        status=_status(good, n_used, H.shape[2]),
    )


def standardized_residuals(
    v: Array, qvv: Array, w0: Array, scale: float | Array | None, min_scale: float = 0.0
) -> tuple[Array, Array]:
    """Standardized residuals ``u_i = v_i / (sigma sqrt(Q_vv,ii))`` (seed 000 sec. 2.1).

    ``sigma`` is the given a-priori scale, or (``scale=None``) the robust scale
    ``med|v_i / sqrt(Q_vv,ii)| / 0.6745`` of the epoch, floored at ``min_scale``.
    Observations with (near) zero redundancy cannot be tested and get ``u = 0``.
    Returns ``(u, sigma)``.
    """
    with np.errstate(all="ignore"):
        testable = np.isfinite(qvv) & (qvv > 1e-10 / np.maximum(w0, 1e-300))
        vn = np.where(testable, v / np.sqrt(np.where(testable, qvv, 1.0)), np.nan)
        if scale is None:
            sigma = mad_scale(vn, axis=1)
        else:
            sigma = np.broadcast_to(np.asarray(scale, dtype=float), v.shape[:1]).copy()
        sigma = np.maximum(np.nan_to_num(sigma, nan=0.0), max(min_scale, 1e-12))
        u = np.where(testable, vn / sigma[:, None], 0.0)
    u = np.where(np.isfinite(v), u, np.nan)
    return u, sigma


#: Values of one ``(K, m, m)`` block of :func:`sandwich_qvv` (32 MB): its products are
#: formed for this many epochs at a time.  At once, 5 000 epochs of a site of 100
#: anchors (the log scale's pass) took 1.3 GB; 1 000 anchors would have taken 130 GB.
SANDWICH_BLOCK = 4_000_000

#: From this many rows :func:`sandwich_qvv` forms its products on each epoch's observed
#: rows when those are at most half of them (a large site, a few anchors heard): on 400
#: anchors with 10 heard, 2 000 epochs took 7.7 s in the ``(K, m, m)`` form.  Below it, and
#: for the shared data sets (at most 12 anchors), the plain form runs, unchanged.
SANDWICH_COMPACT_ROWS = 32


def sandwich_qvv(J: Array, w0: Array, w: Array, fallback: Array) -> Array:
    """Cofactors of the residuals of a fit weighted by ``w`` when the observations' own
    cofactors are ``1 / w0``: the diagonal of ``Q_vv = (I - H) Q (I - H)^T`` with
    ``H = J (J^T W J)^-1 J^T W`` and ``Q = diag(1 / w0)`` (seed 003's ``Q_vv`` for
    equivalent weights).  With ``w = w0`` it is the usual ``1 / w0 - h_i``; a row the
    weights leave out (``w = 0``) gets its prediction cofactor ``1 / w0 + h_i``.
    ``fallback`` where ``J^T W J`` is singular.

    Parameters
    ----------
    J : ndarray (K, m, p)
    w0, w, fallback : ndarray (K, m)
    """
    K, m = J.shape[0], J.shape[1]
    avail = (w0 > 0) | (w > 0)  # the rows in a sum (q0 > 0) or in the fit
    h = int(avail.sum(axis=1).max()) if K else 0
    if m >= SANDWICH_COMPACT_ROWS and 2 * h <= m:
        # a large site's epochs observe a few of its rows: Q_vv,ii of an observed row
        # sums over the observed rows only (q0 = 0 elsewhere) and an unobserved row takes
        # its fallback, so the products are formed on each epoch's observed rows, heard
        # first (K, h, h) instead of (K, m, m)
        idx = true_first(avail, h)
        keep = np.take_along_axis(avail, idx, axis=1)
        fb = np.broadcast_to(fallback, (K, m))
        qc = sandwich_qvv(np.take_along_axis(J, idx[:, :, None], axis=1),
                          np.where(keep, np.take_along_axis(w0, idx, axis=1), 0.0),
                          np.where(keep, np.take_along_axis(w, idx, axis=1), 0.0),
                          np.take_along_axis(fb, idx, axis=1))
        out = fb.copy()
        np.put_along_axis(out, idx, np.where(keep, qc, np.take_along_axis(fb, idx, axis=1)),
                          axis=1)
        return out
    step = max(1, SANDWICH_BLOCK // max(m * m, 1))
    if K > step:  # in blocks of epochs: the (K, m, m) products are per epoch
        fb = np.broadcast_to(fallback, (K, m))
        return np.concatenate([sandwich_qvv(J[s:s + step], w0[s:s + step], w[s:s + step],
                                            fb[s:s + step]) for s in range(0, K, step)])
    Qx, good = inv_spd(normal_matrix(J, w))
    with np.errstate(all="ignore"):
        G = np.matmul(np.matmul(J, Qx), np.swapaxes(J, 1, 2))  # (K, m, m)
        q0 = np.where(w0 > 0, 1.0 / np.where(w0 > 0, w0, 1.0), 0.0)
        # Q_vv,ii = sum_k (delta_ik - G_ik w_k)^2 q0_k: nonnegative terms, no cancellation
        # (expanded, q0 - 2 G_ii w_i q0 + ..., it loses digits on high-leverage rows).  A
        # plain sum over the rows: an unheard row adds exact zeros, so a layout with an
        # extra unheard anchor gives bit-identical cofactors
        D = np.eye(J.shape[1]) - G * np.where(w > 0, w, 0.0)[:, None, :]
        out = np.sum(D * D * q0[:, None, :], axis=2)
        out = np.where(w0 > 0, out, np.nan)
    return np.where(good[:, None] & np.isfinite(out), out, fallback)


#: Iterations after which a redescending stage stops updating the residuals' cofactors
#: (:func:`robustloc.estimators.nonlinear.gauss_newton`): the rest converge as with
#: fixed cofactors.
COFACTOR_UPDATES = 20


def irls(
    H: ArrayLike,
    y: ArrayLike,
    weight: WeightFunction,
    w0: ArrayLike | None = None,
    *,
    scale: float | None = None,
    min_scale: float = 0.0,
    max_iter: int = 50,
    tol: float = 1e-6,
    warmup: bool = True,
    x0: ArrayLike | None = None,
) -> LinearFit:
    """Robust IRLS on a batch of linear systems (seed 000 sec. 2, eqs. (4)-(7)).

    Iterates ``Z^k = (H^T P̄^k H)^-1 H^T P̄^k y`` with the equivalent weights
    ``P̄_i = P_i p(u_i)`` until ``max|Z^k - Z^(k-1)| < tol``.  The standardized residuals
    ``u`` use ``Q_vv`` of the a-priori least-squares fit (fixed: the textbook M-estimator,
    equal to statsmodels' ``RLM`` where the redundancy numbers are equal, which the tests
    check) and the scale of :func:`standardized_residuals` estimated at the start of each
    stage and then held fixed (as in MM-estimation: a scale re-estimated at every step
    lets a drifting fit inflate its own scale and re-admit the outliers).  Unlike
    :func:`robustloc.estimators.nonlinear.gauss_newton` it does not update the cofactors
    with the weights: a row a redescending weight left out is still judged by the
    ``1/P - h`` of a fit that held it, so rejections confirm themselves (IGG with a known
    scale leaves out 3.1 % of Gaussian rows where ``k1 = 2.5`` means 1.2 %).

    Parameters
    ----------
    H, y, w0 : as in :func:`solve_wls` (``w0`` the a-priori weights ``P``).
    weight : WeightFunction
        Huber, Hampel, IGG, IGG3, ...
    scale : float, optional
        Known a-priori standard deviation of unit weight; default: robust MAD scale.
    min_scale : float
        Floor on the robust scale (same units as ``y``).
    max_iter, tol : iteration limit and convergence threshold on the parameters.
    warmup : bool
        For redescending weights (zero beyond a threshold), first iterate with a
        Huber(1.5) weight to convergence, then switch: the standard safeguard against a
        redescending M-estimator locking onto a bad start.
    x0 : (N, p) array, optional
        Start (e.g. a high-breakdown fix); default the least-squares solution.  Epochs
        with a non-finite start use least squares.

    Returns
    -------
    LinearFit
        ``w`` holds the final weights, ``extra["u"]`` the standardized residuals.
    """
    H, y, w0 = _prepare(H, y, w0)
    N, n, p = H.shape
    fit0 = solve_wls(H, y, w0)
    qvv0 = fit0.qvv
    x = fit0.x.copy()
    if x0 is not None:
        xs = np.asarray(x0, dtype=float).reshape(x.shape)
        okx = np.all(np.isfinite(xs), axis=1)
        x[okx] = xs[okx]
    w = w0.copy()
    iters = np.zeros(N, dtype=np.int64)
    conv = np.zeros(N, dtype=bool)
    active = np.flatnonzero(fit0.status == st.OK)
    stages = [weight]
    if warmup and np.isfinite(weight.rejection_threshold):
        stages = [Huber(1.5), weight]
    u_all = np.full((N, n), np.nan)
    for si, wf in enumerate(stages):
        act = active.copy()
        last = si == len(stages) - 1
        # the robust scale is estimated at the start of each stage, then held fixed
        stage_scale = np.full(N, np.nan) if scale is None else np.full(N, float(scale))
        for it in range(max_iter):
            if act.size == 0:
                break
            Ha, ya, wa0 = H[act], y[act], w0[act]
            v = np.einsum("kni,ki->kn", Ha, x[act]) - ya
            u, s_used = standardized_residuals(
                v, qvv0[act], wa0, None if it == 0 and scale is None else stage_scale[act],
                min_scale,
            )
            if it == 0:
                stage_scale[act] = s_used
            pw = np.nan_to_num(wf.weights(u), nan=0.0)
            wn = wa0 * pw
            xn, _, good = _normal_solve(Ha, ya, wn)
            # a weighting that destroys the geometry keeps the previous iterate
            enough = np.sum(wn > 0, axis=1) >= p
            ok = good & enough
            step = np.where(ok, np.sqrt(np.sum(np.nan_to_num(xn - x[act]) ** 2, axis=1)), 0.0)
            x[act[ok]] = xn[ok]
            w[act[ok]] = wn[ok]
            u_all[act] = u
            iters[act] += 1
            done = (step < tol) | ~ok
            if last:
                conv[act[done]] = True
            act = act[~done]
    Hx, yx = H, y
    xf, Ninv, good = _normal_solve(Hx, yx, w)
    good &= fit0.status == st.OK
    xf = np.where(good[:, None], xf, fit0.x)
    v, qvv, sigma0, cov, n_used = _finish(H, y, w, xf, Ninv, good)
    status = fit0.status.copy()
    status[(status == st.OK) & ~conv] = st.NOT_CONVERGED
    return LinearFit(
        x=xf, v=v, w=np.where(np.isfinite(y), w, np.nan), qvv=qvv, sigma0=sigma0, cov=cov,
        n_used=n_used, iterations=iters, converged=conv, status=status, extra={"u": u_all},
    )


#: Residual degrees of freedom LEGE keeps by default (:func:`lege`, ``min_dof``): the
#: order search stops ``LEGE_MIN_DOF`` short of the redundancy.
LEGE_MIN_DOF = 4

#: Sets of suspected observations :func:`lege` enumerates per epoch at most
#: (``max_sets``): the orders ``k = 1, 2, ...`` are searched over every set while the sets
#: of orders ``1 .. k`` number at most this many (:func:`lege_exhaustive_order`), the
#: higher ones by forward selection.  Every order is enumerated up to 14 observations
#: (2-D ranges; seed 000's corridor has 10); with 20 the orders 1-4, with 25 the orders
#: 1-4, with 60 the orders 1-2.  The full search costs ``C(n, k)`` solves per order: a
#: fault-free epoch of 25 ranges (no order's ratio fires, so every order up to ``r - 4``
#: is searched) needed 5.2 million sets of order 12 and a 2.4 GB block, 20 ranges 33 s
#: per epoch, 60 ranges more than 23 GB (the API review of 2026-12-08).
LEGE_MAX_SETS = 20_000

#: Values (float64) of one block of :func:`lege`'s ``(epochs, sets, k, k)`` matrices at
#: most (64 MB; with the copies the determinant and the solve make, about 4 times that),
#: and of its forward search's ``(epochs, n, n)`` ones.  Measured on 200 fault-free
#: epochs of 25 ranges: 32e6 values (the former 256 MB bound) took 0.65 GB and 28 ms per
#: epoch, 8e6 0.16 GB and 16 ms.
_LEGE_BLOCK = 8_000_000


def lege_exhaustive_order(n_obs: int, max_sets: int = LEGE_MAX_SETS) -> int:
    """Largest order :func:`lege` searches over every set of ``n_obs`` observations.

    Parameters
    ----------
    n_obs : int
        Observations of the epoch (those with a positive weight).
    max_sets : int
        Sets enumerated per epoch at most (:data:`LEGE_MAX_SETS`).

    Returns
    -------
    int
        The largest ``K`` with ``C(n, 1) + ... + C(n, K) <= max_sets`` (at most ``n``);
        orders above ``K`` are searched by forward selection.

    Examples
    --------
    >>> [lege_exhaustive_order(n) for n in (10, 14, 15, 20, 25, 60, 100)]
    [10, 14, 7, 4, 4, 2, 2]
    """
    total, k = 0, 0
    while k < n_obs:
        total += math.comb(n_obs, k + 1)
        if total > max_sets:
            break
        k += 1
    return k


def lege(
    H: ArrayLike,
    y: ArrayLike,
    w0: ArrayLike | None = None,
    *,
    rho_stop: float = 3.0,
    max_order: int | None = None,
    min_dof: int = LEGE_MIN_DOF,
    chunk: int = 4096,
    max_sets: int = LEGE_MAX_SETS,
) -> LinearFit:
    """LEGE: simultaneous location and estimation of several gross errors (seed 000 sec. 2.4).

    For each order ``k = 1, 2, ..., r - 1`` (``r = n - p`` the redundancy) and every set
    ``J`` of ``k`` observations, the gross errors ``Δ_J`` are estimated from the residuals
    through ``S = I - R``, ``R = H (H^T P H)^-1 H^T P`` (eqs. (8)-(11), with the digest's
    sign: ``V = -S Δ``), the observations corrected ``y_J <- y_J - Δ_J`` and
    ``σ̂0^(k)`` computed; the best ``J`` of each order minimizes ``σ̂0^(k)``.  The search
    stops at the first ``k`` with ``ρ = σ̂0^(k-1) / σ̂0^(k) > rho_stop`` (eq. (12)), and that
    ``J`` is accepted as the gross errors.

    In the weighted case the least-squares solution of eq. (10) for ``Δ_J`` is
    ``Δ_J = -(P Q_vv P)_JJ^-1 (P v)_J`` and the corrected fit's
    ``v^T P v = v^T P v - (P v)_J^T (P Q_vv P)_JJ^-1 (P v)_J``, which is what is evaluated
    here, batched over epochs and sets.  Correcting ``y_J`` by ``Δ_J`` gives the same
    position as deleting those observations.

    The paper's search enumerates ``C(n, k)`` sets per order, and on an epoch without a
    gross error no ratio fires, so every order up to ``r - min_dof`` is searched: with
    many observations that is millions of sets (25 ranges: 5.2 million of order 12).  The
    orders are therefore enumerated while an epoch's sets of orders ``1 .. k`` number at
    most ``max_sets`` (:func:`lege_exhaustive_order`; every order up to 14 observations
    by default); each higher order's set is the previous order's best set plus the one
    observation whose correction lowers ``σ̂0`` most (forward selection: the largest
    w-statistic after the previous corrections, as in iterative data snooping, seed 003),
    with the same ratio rule.  That search is exact for the first orders and greedy
    beyond: it can miss a set of many gross errors whose best subsets are not nested;
    ``extra["search_truncated"]`` marks the epochs that were searched so.

    Parameters
    ----------
    H, y, w0 : as in :func:`solve_wls`.
    rho_stop : float
        Threshold of eq. (12); the paper uses 3.
    max_order : int, optional
        Largest order searched; default ``r - 1`` as in the paper, further limited by
        ``min_dof``.
    min_dof : int
        Only orders leaving at least this redundancy ``r - k`` are searched.  The ratio
        rule of eq. (12) fires on pure noise once few degrees of freedom remain (the best
        of ``C(n, k)`` subsets always fits well): measured on pure Gaussian noise with
        ``n = 10, p = 2``, false detections are 0 % while ``r - k >= 5``, 1.3 % at 4, 6 % at
        3, 25 % at 2 and 64 % at 1.  Default 4; ``min_dof=1`` is the paper's full search.
    chunk : int
        Epochs processed at once at most (bounds memory; fewer where an order has many
        sets, so that a block of ``(epochs, sets, k, k)`` values stays within 64 MB, and
        a single epoch's sets are taken in blocks of that size too).
    max_sets : int
        Sets enumerated per epoch at most (:data:`LEGE_MAX_SETS`); the orders beyond are
        searched by forward selection.  ``0``: forward selection from order 1.

    Returns
    -------
    LinearFit
        ``extra["gross_errors"]`` (N, n): estimated ``Δ`` (0 where not flagged),
        ``extra["order"]`` (N,): number of gross errors found, ``extra["rho"]``,
        ``extra["exhaustive_order"]`` (N,): the largest order searched over every set,
        ``extra["search_truncated"]`` (N,): ``True`` where a higher order was searched by
        forward selection.
    """
    H, y, w0 = _prepare(H, y, w0)
    N, n, p = H.shape
    max_sets = max(int(max_sets), 0)
    fit0 = solve_wls(H, y, w0)
    # full residual cofactor matrix Q_vv = P^-1 - H N^-1 H^T, and P Q_vv P
    observed = w0 > 0
    Ninv = np.nan_to_num(np.linalg.inv(np.where(
        (fit0.status == st.OK)[:, None, None],
        np.einsum("kni,kn,knj->kij", H, w0, H), np.eye(p))))
    HNH = np.einsum("kni,kij,kmj->knm", H, Ninv, H)
    # M = P Q_vv P = P - P H N^-1 H^T P  (rows/cols of missing observations are zero)
    M = np.einsum("kn,knm,km->knm", w0, -HNH, w0)
    M[:, np.arange(n), np.arange(n)] += w0
    vz = np.nan_to_num(fit0.v)
    Pv = w0 * vz
    vpv = np.sum(Pv * vz, axis=1)
    n_valid = observed.sum(axis=1)
    r = n_valid - p
    orders_max = np.maximum(np.minimum(r - 1, r - min_dof), 0)
    if max_order is not None:
        orders_max = np.minimum(orders_max, max_order)
    kmax = int(orders_max.max()) if N else 0

    sig_prev = np.where(r > 0, np.sqrt(vpv / np.maximum(r, 1)), np.nan)
    found = np.zeros(N, dtype=np.int64)
    # each epoch's best set of the last order searched, in the (front) columns searched
    best_set = np.full((N, max(kmax, 1)), -1, dtype=np.int64)
    last = np.zeros(N, dtype=np.int64)
    rho_found = np.full(N, np.nan)
    searching = (fit0.status == st.OK) & (orders_max >= 1) & (sig_prev > 0)
    exh = np.zeros(N, dtype=np.int64)
    for c in np.unique(n_valid):
        exh[n_valid == c] = lege_exhaustive_order(int(c), max_sets)
    exh = np.minimum(exh, orders_max)
    # the sets are drawn from each epoch's observed rows, moved to the front in their
    # order (the same sets in the same order as over all n rows, the unobserved ones
    # left out): a site of 100 anchors of which an epoch hears 10 has C(100, 4) = 3.9e6
    # sets of order 4, which took 66 GB per chunk, where C(10, 4) = 210 do
    nc = int(n_valid.max()) if N else 0
    if nc < n or not np.all(n_valid == nc):
        front = true_first(observed, nc)  # (N, nc)
        Mc = M[np.arange(N)[:, None, None], front[:, :, None], front[:, None, :]]
        Pvc = np.take_along_axis(Pv, front, axis=1)
    else:
        front, Mc, Pvc = None, M, Pv
    for k in range(1, int(exh.max(initial=0)) + 1):
        todo = searching & (exh >= k)
        if not todo.any():
            break
        # the epochs hearing c observations: the sets of k among their first c columns
        for c in np.unique(n_valid[todo]):
            idx = np.flatnonzero(todo & (n_valid == c))
            combos = np.array(list(combinations(range(int(c)), k)),
                              dtype=np.int64).reshape(-1, k)  # (C, k), C <= max_sets
            n_sets = combos.shape[0]
            # blocks of at most _LEGE_BLOCK values (64 MB): sets of one epoch, then
            # epochs (at most ``chunk``): C(30, 4) = 27 405 sets took 14 GB at 4 096 epochs
            cstep = max(1, min(n_sets, _LEGE_BLOCK // (k * k)))
            step = max(1, min(chunk, _LEGE_BLOCK // (cstep * k * k)))
            for s in range(0, idx.size, step):
                e = idx[s : s + step]
                sbest = np.full(e.size, np.inf)
                ibest = np.zeros(e.size, dtype=np.int64)
                for c0 in range(0, n_sets, cstep):
                    cb = combos[c0 : c0 + cstep]
                    sig_k = _lege_block(Mc, Pvc, vpv, r, e, cb, k)
                    b = np.argmin(sig_k, axis=1)
                    sb = sig_k[np.arange(e.size), b]
                    better = sb < sbest  # (strict: the first of equal sets, as one block)
                    sbest = np.where(better, sb, sbest)
                    ibest = np.where(better, b + c0, ibest)
                with np.errstate(all="ignore"):
                    rho = sig_prev[e] / sbest
                fin = np.isfinite(sbest)
                stop = fin & ((rho > rho_stop) | (sbest <= 1e-12 * sig_prev[e]))
                best_set[e[fin], :k] = combos[ibest[fin]]
                last[e[fin]] = k
                hit = e[stop]
                found[hit] = k
                rho_found[hit] = rho[stop]
                searching[hit] = False
                upd = fin & ~stop
                sig_prev[e[upd]] = sbest[upd]
    # the orders beyond the enumerated ones: forward selection from the last best set
    truncated = np.zeros(N, dtype=bool)
    fwd = np.flatnonzero(searching & (orders_max > exh) & (last == exh))
    step = max(1, min(chunk, _LEGE_BLOCK // max(nc * nc, 1)))
    for s in range(0, fwd.size, step):
        e = fwd[s : s + step]
        f_found, f_sets, f_rho, f_used = _lege_forward(
            Mc[e], Pvc[e], np.arange(nc)[None, :] < n_valid[e][:, None], vpv[e], r[e],
            exh[e], orders_max[e], best_set[e], sig_prev[e], rho_stop)
        hit = f_found > 0
        found[e[hit]] = f_found[hit]
        rho_found[e[hit]] = f_rho[hit]
        width = f_sets.shape[1]
        best_set[e[hit], :width] = f_sets[hit]
        truncated[e] = f_used
    sel = np.flatnonzero(found > 0)
    if front is not None and sel.size:  # the rows of the sets found
        cols = best_set[sel]  # (its width max(kmax, 1) <= nc)
        best_set[sel] = np.where(cols >= 0, np.take_along_axis(
            front[sel], np.maximum(cols, 0), axis=1), -1)
    # estimate the gross errors (eq. (11)) and re-solve without them (same as correcting)
    gross = np.zeros((N, n))
    w = w0.copy()
    for k in range(1, kmax + 1):
        e = np.flatnonzero(found == k)
        if e.size == 0:
            continue
        J = best_set[e, :k]
        MJ = M[e[:, None, None], J[:, :, None], J[:, None, :]]
        qJ = Pv[e[:, None], J]
        dJ = -np.linalg.solve(MJ, qJ[..., None])[..., 0]  # Δ_J, eq. (11) with S = I - R
        gross[e[:, None], J] = dJ
        w[e[:, None], J] = 0.0
    x, Ninv2, good = _normal_solve(H, y, w)
    good &= fit0.status == st.OK
    x = np.where(good[:, None], x, fit0.x)
    v, qvv, sigma0, cov, n_used = _finish(H, y, w, x, Ninv2, good)
    return LinearFit(
        x=x, v=v, w=np.where(np.isfinite(y), w, np.nan), qvv=qvv, sigma0=sigma0, cov=cov,
        n_used=n_used, iterations=found + 1, converged=fit0.status == st.OK,
        status=fit0.status.copy(),
        extra={"gross_errors": gross, "order": found, "rho": rho_found,
               "exhaustive_order": exh, "search_truncated": truncated},
    )


def _lege_block(Mc: Array, Pvc: Array, vpv: Array, r: NDArray[np.int64],
                e: NDArray[np.intp], combos: NDArray[np.int64], k: int) -> Array:
    """:func:`lege`'s ``σ̂0^(k)`` of the epochs ``e`` after correcting each of the sets
    ``combos`` (C, k) of their (front) columns; ``inf`` for a set whose ``(P Q_vv P)_JJ``
    is singular.  Returns (E, C)."""
    Me = Mc[e[:, None, None, None], combos[None, :, :, None],
            combos[None, :, None, :]]  # (E, C, k, k)
    qe = Pvc[e[:, None, None], combos[None, :, :]]  # (E, C, k)
    with np.errstate(all="ignore"):
        valid = np.linalg.det(Me) > 1e-12 * np.prod(
            np.maximum(np.diagonal(Me, axis1=2, axis2=3), 1e-300), axis=2)
    Ms = np.where(valid[..., None, None], Me, np.eye(k))
    red = np.einsum("eck,eck->ec", qe, np.linalg.solve(Ms, qe[..., None])[..., 0])
    vpv_k = np.where(valid, vpv[e][:, None] - red, np.inf)
    dof = (r[e] - k)[:, None]
    return np.sqrt(np.maximum(vpv_k, 0.0) / np.maximum(dof, 1))


def _lege_forward(
    M: Array, q: Array, obs: NDArray[np.bool_], vpv: Array, r: NDArray[np.int64],
    k0: NDArray[np.int64], kend: NDArray[np.int64], start: NDArray[np.int64],
    sig_prev: Array, rho_stop: float,
) -> tuple[NDArray[np.int64], NDArray[np.int64], Array, NDArray[np.bool_]]:
    """:func:`lege`'s orders ``k0 + 1 .. kend`` by forward selection, per epoch.

    The epoch's set starts as its best set of order ``k0`` (``start[:, :k0]``) and grows
    by the observation ``j`` whose correction lowers ``v^T P v`` most: with ``M' , q'``
    the matrix ``P Q_vv P`` and ``P v`` after correcting the set (a Schur complement,
    updated by one rank-one step per observation), the reduction is ``q'_j^2 / M'_jj``
    (the squared w-statistic of ``j``), the same ``σ̂0^(k)`` the enumeration computes for
    that set.  A candidate whose ``(P Q_vv P)`` block would be singular by the
    enumeration's test (its determinant below ``1e-12`` of its diagonal's product) is
    left out.  The ratio rule of eq. (12) against ``sig_prev`` (``σ̂0`` of order ``k0``)
    stops the search.

    Returns
    -------
    (found, sets, rho, used)
        ``found`` (E,): the order at which the ratio fired (0: none), ``sets`` (E, K) the
        set's columns (its first ``found`` entries), ``rho`` (E,), ``used`` (E,):
        ``True`` where an order was searched so (not only the start replayed).
    """
    E, c, _ = M.shape
    ar = np.arange(E)
    Mp, qp = M.copy(), q.copy()
    d0 = np.maximum(np.diagonal(M, axis1=1, axis2=2), 1e-300)
    ratio, red = np.ones(E), np.zeros(E)
    free = obs.copy()
    K = int(kend.max(initial=0))
    sets = np.full((E, max(K, 1)), -1, dtype=np.int64)
    sets[:, : min(start.shape[1], K)] = start[:, : min(start.shape[1], K)]
    found = np.zeros(E, dtype=np.int64)
    rho_out = np.full(E, np.nan)
    active = np.ones(E, dtype=bool)
    used = np.zeros(E, dtype=bool)
    sig_prev = sig_prev.copy()
    for t in range(K):
        k = t + 1
        go = active & (k <= kend)
        if not go.any():
            break
        forced = t < k0
        dg = np.diagonal(Mp, axis1=1, axis2=2)
        with np.errstate(all="ignore"):
            gain = qp**2 / dg
            ok = free & (ratio[:, None] * dg > 1e-12 * d0) & np.isfinite(gain)
        gain = np.where(ok, gain, -np.inf)
        pick = np.argmax(gain, axis=1)
        j = np.where(forced, sets[:, t], pick)
        j = np.maximum(j, 0)
        with np.errstate(all="ignore"):
            g = np.where(forced, qp[ar, j] ** 2 / dg[ar, j], gain[ar, j])
        greedy = go & ~forced & np.isfinite(g)
        red_k = red + g
        with np.errstate(all="ignore"):
            sig_k = np.sqrt(np.maximum(vpv - red_k, 0.0) / np.maximum(r - k, 1))
            rho = sig_prev / sig_k
        stop = greedy & ((rho > rho_stop) | (sig_k <= 1e-12 * sig_prev))
        used |= greedy
        sets[greedy, t] = j[greedy]
        found[stop] = k
        rho_out[stop] = rho[stop]
        active &= ~stop & (forced | greedy)  # no candidate left: nothing more to search
        cont = go & active
        sig_prev = np.where(cont & ~forced, sig_k, sig_prev)
        # correct j: M' <- M' - M'_:j M'_j: / M'_jj,  q' <- q' - M'_:j q'_j / M'_jj
        col = Mp[ar, :, j]  # (E, c)
        piv = Mp[ar, j, j]
        with np.errstate(all="ignore"):
            f = np.where(cont, 1.0 / piv, 0.0)
        f = np.where(np.isfinite(f), f, 0.0)
        Mp -= (f[:, None] * col)[:, :, None] * col[:, None, :]
        qp -= (f * qp[ar, j])[:, None] * col
        red = np.where(cont, red_k, red)
        ratio = np.where(cont, ratio * piv / d0[ar, j], ratio)
        free[ar[cont], j[cont]] = False
    return found, sets, rho_out, used


def with_status(fit: LinearFit, status: NDArray[np.object_]) -> LinearFit:
    """Copy of ``fit`` with another status array."""
    return replace(fit, status=status)
