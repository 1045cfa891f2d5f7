"""Iterative data snooping (fault detection and exclusion), batched over epochs (seed 003).

Per epoch, repeat (seed 003, sec. on RAIM):

1. solve the least-squares problem with the observations still in use;
2. **global test**: ``T = v^T P v`` against ``chi2(1 - alpha, n - p)``, ``alpha`` from the
   B-method for the current redundancy (:func:`robustloc.integrity.bmethod.global_alpha`)
   or fixed; if it passes, stop (status ``ok``, or ``fault_excluded`` if something was
   excluded);
3. **local test**: the observation with the largest w-test ``w_i`` (seed 003, eq. (1)) is
   excluded if ``w_i > N(1 - alpha0/2)``; with ``require_local=True`` (default) a global
   failure without any w-test above the critical value ends the epoch as ``unavailable``
   (detected, not identified);
4. stop with status ``unavailable`` when an exclusion would leave fewer than ``p + 1``
   observations (the remaining ones could no longer be tested: ``m`` gross errors need at
   least ``m + 1`` redundant observations), or after ``max_exclusions``.

Epochs with fewer than ``p`` usable observations get ``insufficient_anchors``, a singular
normal matrix ``ill_conditioned``, exactly ``p`` observations (no redundancy, nothing can be
tested) ``unavailable``.  Only epochs still failing are re-solved on each pass, so a batch of
10 000 epochs with one fault each costs about two batched solves.

Two entry points:

* :func:`snoop_linear` for a linear model ``y = H x + e`` (the design of a linearized
  trilateration, levelling, a Monte Carlo of a linearized GNSS snapshot);
* :func:`snoop` driven by a caller-supplied re-solver, for nonlinear models (ranges,
  pseudoranges) that must re-linearize after each exclusion::

      def solve(mask, rows):
          # mask: (K, n) bool, observations to use for the K epochs ``rows`` (int indices
          # into the batch).  Return, for those K epochs:
          #   x (K, p) solution, H (K, n, p) design at the solution,
          #   v (K, n) residuals (predicted - observed; NaN where not used is fine).
          ...
          return x, H, v

      res = snoop(solve, mask0, sigma=0.5)   # mask0: (N, n) observations available
      res.status, res.exclusion_order, res.x

  A re-solver taking a single argument ``solve(mask)`` with the full ``(N, n)`` mask and
  returning arrays for all ``N`` epochs is accepted too (then every epoch is re-solved on
  every pass, which is simpler to write and slower).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc.estimators.solution import Solution
from robustloc.integrity.bmethod import ALPHA0, BETA0, lambda0, w_critical
from robustloc.integrity.tests import (
    RCOND,
    _observation_array,
    as_design,
    broadcast_sigma,
    integrity_tests,
    whiten,
)

Array = NDArray[np.float64]
Solver = Callable[..., tuple[ArrayLike, ArrayLike, ArrayLike]]


@dataclass(frozen=True)
class SnoopingResult:
    """Per-epoch outcome of iterative data snooping over ``N`` epochs, ``n`` observations.

    Attributes
    ----------
    x : ndarray (N, p)
        Final solution (with the excluded observations removed).  Kept also for
        ``unavailable`` epochs (check ``status``); NaN where no solution exists.
    cov : ndarray (N, p, p)
        A-priori covariance ``(H^T P H)^-1`` of the final solution (``sigma0 = 1``).
    residuals : ndarray (N, n)
        Final residuals (NaN: missing or excluded).
    w : ndarray (N, n)
        Final w-test statistics of the observations in use.
    redundancy : ndarray (N, n)
        Final redundancy numbers ``r_i``.
    used : ndarray of bool (N, n)
        Observations in the final solution.
    excluded : ndarray of bool (N, n)
        Observations excluded by the local test.
    exclusion_order : ndarray of int (N, n)
        Indices of the excluded observations, in the order of exclusion, padded with -1.
    excluded_w : ndarray (N, n)
        The w-statistic of each excluded observation when it was excluded (same order).
    n_excluded, n_used : ndarray of int (N,)
    detected : ndarray of bool (N,)
        The first global test failed (a fault was detected).
    global_stat_initial, global_crit_initial : ndarray (N,)
        First global test statistic ``v^T P v`` and its critical value.
    dof_initial : ndarray of int (N,)
    global_stat, global_crit, alpha : ndarray (N,)
        Final global test statistic, critical value and significance used.
    dof : ndarray of int (N,)
        Final redundancy.
    w_crit : float
        Critical value of the w-test, ``N(1 - alpha0/2)``.
    alpha0, beta0, lambda0 : float
    iterations : ndarray of int (N,)
        Number of (re-)solutions for each epoch.
    status : ndarray of str (N,)
        ``ok``, ``fault_excluded``, ``unavailable``, ``insufficient_anchors`` or
        ``ill_conditioned`` (:mod:`robustloc.status`).
    """

    x: Array
    cov: Array
    residuals: Array
    w: Array
    redundancy: Array
    used: NDArray[np.bool_]
    excluded: NDArray[np.bool_]
    exclusion_order: NDArray[np.int64]
    excluded_w: Array
    n_excluded: NDArray[np.int64]
    n_used: NDArray[np.int64]
    detected: NDArray[np.bool_]
    global_stat_initial: Array
    global_crit_initial: Array
    dof_initial: NDArray[np.int64]
    global_stat: Array
    global_crit: Array
    alpha: Array
    dof: NDArray[np.int64]
    w_crit: float
    alpha0: float
    beta0: float
    lambda0: float
    iterations: NDArray[np.int64]
    status: NDArray[np.object_]
    extra: dict = field(default_factory=dict)

    @property
    def n_epochs(self) -> int:
        return int(self.x.shape[0])

    def to_solution(self, method: str = "snooping", position_dims: int | None = None) -> Solution:
        """The result as a :class:`~robustloc.estimators.solution.Solution`.

        Parameters
        ----------
        method : str
            Method name written in the positions file.
        position_dims : int, optional
            Number of leading unknowns that are the position (default all; e.g. 3 for a
            GNSS solution whose further unknowns are clock terms).
        """
        d = self.x.shape[1] if position_dims is None else int(position_dims)
        weights = np.where(self.used, 1.0, np.where(self.excluded, 0.0, np.nan))
        with np.errstate(invalid="ignore", divide="ignore"):
            s0 = np.sqrt(self.global_stat / np.where(self.dof >= 1, self.dof, np.nan))
        return Solution(
            position=self.x[:, :d].copy(),
            covariance=self.cov[:, :d, :d].copy(),
            residuals=self.residuals.copy(),
            weights=weights,
            excluded=self.excluded.copy(),
            sigma0=s0,
            iterations=self.iterations.copy(),
            converged=st.among(self.status, (st.OK, st.FAULT_EXCLUDED)),
            status=self.status.copy(),
            n_used=self.n_used.copy(),
            method=method,
            extra={
                "w": self.w,
                "global_stat": self.global_stat,
                "global_crit": self.global_crit,
                "global_stat_initial": self.global_stat_initial,
                "global_crit_initial": self.global_crit_initial,
                "exclusion_order": self.exclusion_order,
                "excluded_w": self.excluded_w,
                "detected": self.detected,
                "covariance_note": "a-priori (H^T P H)^-1, sigma0 = 1",
                **self.extra,
            },
        )


def _wants_rows(solve: Solver) -> bool:
    """True when ``solve`` accepts a second positional argument (``rows``)."""
    try:
        sig = inspect.signature(solve)
    except (TypeError, ValueError):  # builtins without a signature
        return True
    n_pos = 0
    for prm in sig.parameters.values():
        if prm.kind == prm.VAR_POSITIONAL:
            return True
        if prm.kind in (prm.POSITIONAL_ONLY, prm.POSITIONAL_OR_KEYWORD):
            n_pos += 1
    return n_pos >= 2


def snoop(
    solve: Solver,
    mask: ArrayLike,
    sigma: ArrayLike,
    *,
    alpha: float | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
    require_local: bool = True,
    max_exclusions: int | None = None,
    rcond: float = RCOND,
) -> SnoopingResult:
    """Iterative data snooping with a caller-supplied (re-linearizing) solver.

    Parameters
    ----------
    solve : callable
        ``solve(mask (K, n) bool, rows (K,) int) -> (x (K, p), H (K, n, p), v (K, n))``:
        least-squares solution of epochs ``rows`` using only the observations in ``mask``,
        the design (Jacobian) at that solution and the residuals ``v = f(x) - z``.  A
        one-argument ``solve(mask (N, n))`` returning arrays for all N epochs is accepted.
        A non-finite ``x`` for an epoch means no solution (``ill_conditioned``).
    mask : array_like of bool, shape (N, n)
        Observations available in each epoch (False: missing).
    sigma : float or array_like, broadcastable to (N, n)
        A-priori standard deviation of each observation (metres, dB, ...).
    alpha : float, optional
        Fixed significance of the global test; default: B-method value for each redundancy
        (seed 003, eq. (4)).
    alpha0 : float
        Significance of the w-test (default 0.1 %, critical value 3.29).
    beta0 : float
        Type II error of the B-method (default 10 %).
    require_local : bool
        If True, a failed global test with no w-test above the critical value ends the epoch
        as ``unavailable``; if False, the largest w-test is excluded anyway.
    max_exclusions : int, optional
        Stop (``unavailable``) after this many exclusions if the global test still fails.
    rcond : float
        Conditioning floor of the normal matrix.

    Returns
    -------
    SnoopingResult
    """
    m0 = np.asarray(mask, dtype=bool)
    if m0.ndim == 1:
        m0 = m0[None]
    if m0.ndim != 2:
        raise ValueError(f"mask must have shape (N, n), got {m0.shape}")
    N, n = m0.shape
    sig = broadcast_sigma(sigma, (N, n))
    m0 = m0 & np.isfinite(sig)
    if max_exclusions is None:
        max_exclusions = n
    kcrit = w_critical(alpha0)
    rows_mode = _wants_rows(solve)

    cur = m0.copy()
    active = np.ones(N, dtype=bool)
    p = -1
    # outputs, allocated once p is known
    out: dict[str, np.ndarray] = {}
    status = np.full(N, st.UNAVAILABLE, dtype=object)
    order = np.full((N, n), -1, dtype=np.int64)
    order_w = np.full((N, n), np.nan)
    n_exc = np.zeros(N, dtype=np.int64)
    iters = np.zeros(N, dtype=np.int64)
    first = np.ones(N, dtype=bool)
    stat0 = np.full(N, np.nan)
    crit0 = np.full(N, np.nan)
    dof0 = np.zeros(N, dtype=np.int64)
    detected = np.zeros(N, dtype=bool)

    for _ in range(n + 1):
        rows = np.flatnonzero(active)
        if rows.size == 0:
            break
        if rows_mode:
            x, H, v = solve(cur[rows], rows)
        else:
            x, H, v = solve(cur)
            x, H, v = np.asarray(x)[rows], np.asarray(H)[rows], np.asarray(v)[rows]
        x = np.asarray(x, dtype=float)
        H = as_design(H)
        v = np.asarray(v, dtype=float)
        if x.ndim != 2 or x.shape[0] != rows.size or H.shape[:2] != (rows.size, n) or (
            v.shape != (rows.size, n)
        ):
            raise ValueError(
                f"solve returned x {x.shape}, H {H.shape}, v {v.shape}; expected "
                f"({rows.size}, p), ({rows.size}, {n}, p), ({rows.size}, {n})"
            )
        if p < 0:
            p = H.shape[2]
            out = {
                "x": np.full((N, p), np.nan),
                "cov": np.full((N, p, p), np.nan),
                "v": np.full((N, n), np.nan),
                "w": np.full((N, n), np.nan),
                "r": np.full((N, n), np.nan),
                "used": np.zeros((N, n), dtype=bool),
                "stat": np.full(N, np.nan),
                "crit": np.full(N, np.nan),
                "alpha": np.full(N, np.nan),
                "dof": np.zeros(N, dtype=np.int64),
            }
        cm = cur[rows]
        x_ok = np.all(np.isfinite(x), axis=1)
        wh = whiten(H, sig[rows], mask=cm, rcond=rcond)
        t = integrity_tests(wh, v, alpha=alpha, alpha0=alpha0, beta0=beta0)
        iters[rows] += 1

        out["x"][rows] = x
        out["cov"][rows] = wh.Ninv
        out["v"][rows] = np.where(wh.used, v, np.nan)
        out["w"][rows] = t.w
        out["r"][rows] = t.redundancy
        out["used"][rows] = wh.used
        out["stat"][rows] = t.global_stat
        out["crit"][rows] = t.global_crit
        out["alpha"][rows] = t.alpha
        out["dof"][rows] = t.dof

        f = first[rows]
        stat0[rows[f]] = t.global_stat[f]
        crit0[rows[f]] = t.global_crit[f]
        dof0[rows[f]] = t.dof[f]
        detected[rows[f]] = t.testable[f] & ~t.global_pass[f]
        first[rows] = False

        n_used = wh.n_used
        done = np.zeros(rows.size, dtype=bool)
        # not solvable
        insuff = cm.sum(axis=1) < p
        ill = ~insuff & (~wh.ok | ~x_ok)
        status[rows[insuff]] = st.INSUFFICIENT
        status[rows[ill]] = st.ILL_CONDITIONED
        done |= insuff | ill
        # no redundancy: nothing to test
        untestable = ~done & ~t.testable
        status[rows[untestable]] = st.UNAVAILABLE
        done |= untestable
        # global test passes
        passed = ~done & t.global_pass
        status[rows[passed]] = np.where(n_exc[rows[passed]] > 0, st.FAULT_EXCLUDED, st.OK)
        done |= passed
        # global test fails: local test
        failing = ~done
        wz = np.where(np.isfinite(t.w), t.w, -np.inf)
        j = np.argmax(wz, axis=1)
        wmax = wz[np.arange(rows.size), j]
        no_local = failing & (wmax <= kcrit) if require_local else failing & ~np.isfinite(wmax)
        exhausted = failing & ~no_local & (
            (n_used - 1 < p + 1) | (n_exc[rows] >= max_exclusions)
        )
        stop = no_local | exhausted
        status[rows[stop]] = st.UNAVAILABLE
        done |= stop
        exc = ~done
        er, ej = rows[exc], j[exc]
        cur[er, ej] = False
        order[er, n_exc[er]] = ej
        order_w[er, n_exc[er]] = wmax[exc]
        n_exc[er] += 1
        active[rows[done]] = False

    if p < 0:  # N == 0
        p = 0
        out = {
            "x": np.zeros((0, 0)), "cov": np.zeros((0, 0, 0)), "v": np.zeros((0, n)),
            "w": np.zeros((0, n)), "r": np.zeros((0, n)), "used": np.zeros((0, n), bool),
            "stat": np.zeros(0), "crit": np.zeros(0), "alpha": np.zeros(0),
            "dof": np.zeros(0, np.int64),
        }
    excluded = np.zeros((N, n), dtype=bool)
    rr, cc = np.nonzero(order >= 0)
    excluded[rr, order[rr, cc]] = True
    return SnoopingResult(
        x=out["x"],
        cov=out["cov"],
        residuals=out["v"],
        w=out["w"],
        redundancy=out["r"],
        used=out["used"],
        excluded=excluded,
        exclusion_order=order,
        excluded_w=order_w,
        n_excluded=n_exc,
        n_used=out["used"].sum(axis=1).astype(np.int64),
        detected=detected,
        global_stat_initial=stat0,
        global_crit_initial=crit0,
        dof_initial=dof0,
        global_stat=out["stat"],
        global_crit=out["crit"],
        alpha=out["alpha"],
        dof=out["dof"],
        w_crit=kcrit,
        alpha0=float(alpha0),
        beta0=float(beta0),
        lambda0=lambda0(alpha0, beta0),
        iterations=iters,
        status=status,
    )


def snoop_linear(
    H: ArrayLike,
    y: ArrayLike,
    sigma: ArrayLike,
    *,
    mask: ArrayLike | None = None,
    alpha: float | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
    require_local: bool = True,
    max_exclusions: int | None = None,
    rcond: float = RCOND,
) -> SnoopingResult:
    """Iterative data snooping on a linear model ``y = H x + e``, ``e ~ N(0, diag(sigma^2))``.

    Parameters
    ----------
    H : array_like, shape (N, n, p) or (n, p)
        Design matrix (a 2-D design is shared by every epoch).
    y : array_like, shape (N, n)
        Observations; NaN = missing.
    sigma : float or array_like, broadcastable to (N, n)
        A-priori standard deviations.
    mask : array_like of bool (N, n), optional
        Observations to consider (default: all finite ones).
    alpha, alpha0, beta0, require_local, max_exclusions, rcond
        See :func:`snoop`.

    Returns
    -------
    SnoopingResult
        Residuals follow ``v = H x - y``.

    Examples
    --------
    Five direct measurements of one quantity, sigma 1, one of them 10 too large:

    >>> import numpy as np
    >>> y = np.array([[0.3, -0.5, 10.2, 0.1, -0.2]])
    >>> res = snoop_linear(np.ones((5, 1)), y, sigma=1.0)
    >>> res.status.tolist(), res.exclusion_order[0, :1].tolist()
    (['fault_excluded'], [2])
    """
    yy = np.asarray(y, dtype=float)
    if yy.ndim == 1:
        yy = yy[None]
    Hm = as_design(H)
    N, n = yy.shape
    if Hm.shape[0] == 1 and N != 1:
        Hm = np.broadcast_to(Hm, (N,) + Hm.shape[1:])
    if Hm.shape[:2] != (N, n):
        raise ValueError(f"design {Hm.shape} does not match observations {yy.shape}")
    sig = broadcast_sigma(sigma, (N, n))
    m = np.isfinite(yy) & np.all(np.isfinite(Hm), axis=2) & np.isfinite(sig)
    if mask is not None:
        m &= _observation_array("mask", mask, (N, n), bool)

    def _solve(mk: NDArray[np.bool_], rows: NDArray[np.int64]) -> tuple[Array, Array, Array]:
        Hr, yr = Hm[rows], yy[rows]
        wh = whiten(Hr, sig[rows], mask=mk, rcond=rcond)
        x = wh.solve(np.where(wh.used, yr, 0.0))
        v = np.einsum("kip,kp->ki", Hr, x) - yr
        return x, Hr, v

    res = snoop(
        _solve, m, sig, alpha=alpha, alpha0=alpha0, beta0=beta0,
        require_local=require_local, max_exclusions=max_exclusions, rcond=rcond,
    )
    if N == 0:  # no epoch: keep the number of unknowns in the shapes
        p = Hm.shape[2]
        res = replace(res, x=np.zeros((0, p)), cov=np.zeros((0, p, p)))
    return res
