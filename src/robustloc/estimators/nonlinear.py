"""Batched nonlinear least squares (Gauss-Newton with Levenberg damping) and robust IRLS.

Works with any measurement model exposing ``predict(x) -> (N, n)`` and
``jacobian(x) -> (N, n, p)`` (e.g. :class:`~robustloc.models.ranging.RangeModel`,
:class:`~robustloc.models.ranging.RssiModel`).  All epochs are iterated together; an epoch
leaves the active set when it converges.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc.estimators._kernels import inv_spd, normal_matrix
from robustloc.estimators.linear import (
    COFACTOR_UPDATES,
    LinearFit,
    sandwich_qvv,
    standardized_residuals,
)
from robustloc.robust.weights import Huber, WeightFunction

Array = NDArray[np.float64]


class MeasurementModel(Protocol):
    """What :func:`gauss_newton` needs from a model."""

    def predict(self, x: Array) -> Array: ...

    def jacobian(self, x: Array) -> Array: ...


_inv_small = inv_spd

#: An accepted step that lowers the weighted cost by at most this fraction of it ends the
#: iteration (with ``rel_tol > 0``; the compiled kernel uses the same value).
FLAT_COST = 1e-6
#: The same with ``rel_tol = 0``: a cost that no longer falls beyond rounding (a few
#: hundred ulp of a sum of squares), where a step of ``tol`` may never come.
FLAT_COST_FLOOR = 1e-12


def _still_to_go(step: NDArray[np.float64], prev: NDArray[np.float64],
                 accept: NDArray[np.bool_]) -> NDArray[np.float64]:
    """Bound on the distance a linearly converging iteration still moves: ``step q / (1 -
    q)`` with ``q = step / prev`` the last contraction; 0 without a previous accepted
    step (the step alone then decides, as for Gauss-Newton's quadratic convergence),
    infinite when the steps do not shrink.  The compiled kernel computes the same."""
    with np.errstate(all="ignore"):
        q = step / prev
        go = np.where(q < 1.0, step * q / (1.0 - q), np.inf)
    return np.where(accept & np.isfinite(prev) & (prev > 0), go, 0.0)


def _model_rows(model: MeasurementModel, x: Array, rows: NDArray[np.int64] | None):
    """Predict/Jacobian for a subset of epochs when the model is epoch-dependent."""
    if rows is not None and hasattr(model, "subset"):
        model = model.subset(rows)
    if hasattr(model, "predict_jacobian"):
        return model.predict_jacobian(x)
    return model.predict(x), model.jacobian(x)


def _predict_rows(model: MeasurementModel, x: Array, rows: NDArray[np.int64] | None) -> Array:
    if rows is not None and hasattr(model, "subset"):
        model = model.subset(rows)
    return model.predict(x)


def gauss_newton(
    model: MeasurementModel,
    z: ArrayLike,
    x0: ArrayLike,
    sigma: ArrayLike | float = 1.0,
    *,
    weight: WeightFunction | None = None,
    scale: float | None = None,
    min_scale: float = 0.0,
    max_iter: int = 50,
    tol: float = 1e-6,
    min_obs: int | None = None,
    warmup: bool = True,
    rel_tol: float = 1e-2,
) -> LinearFit:
    """Gauss-Newton / Levenberg-Marquardt on ``N`` epochs at once, optionally robust.

    Minimizes ``sum_i w_i (z_i - f_i(x))^2`` with ``w_i = P_i p(u_i)``: ``P_i = 1/sigma_i^2``
    the a-priori weight and ``p(u_i)`` the robust equivalent weight of the standardized
    residual (seed 000 sec. 2: the "selection-of-weights iteration" carried to the
    nonlinear observation equations, so one bad range is one bad row).  Steps are damped
    (``(J^T W J + λ tr(J^T W J)/p I) dx = J^T W r``) and accepted only when they lower the
    weighted cost, so an epoch never diverges.

    The residuals are standardized by the cofactors of the a-priori fit at the stage's
    first iteration; with redescending weights (a finite rejection threshold) then by the
    cofactors of the fit the last weights made (:func:`sandwich_qvv`), until the fit has
    converged once or after :data:`COFACTOR_UPDATES` iterations, and held from there (the
    rest converges as with fixed cofactors).  A row the weights left out is so judged by
    its prediction cofactor ``1/P + h``: with the a-priori ``1/P - h`` a rejection
    confirmed itself (IGG left out 6.3 % of Gaussian ranges where ``k1 = 2.5`` means
    1.2 %; tests/test_robust_cofactors.py).

    Parameters
    ----------
    model : object with ``predict`` and ``jacobian`` (see :class:`MeasurementModel`).
        If it has ``subset(rows)`` returning a model for those epochs, models whose
        geometry varies per epoch (e.g. GNSS satellites) are supported.
    z : (N, n) observations, NaN = missing.
    x0 : (N, p) initial positions.
    sigma : float or (n,) or (N, n)
        A-priori standard deviations of the observations.
    weight : WeightFunction, optional
        Robust weight function; None = plain (weighted) least squares.
    scale : float, optional
        Factor on ``sigma`` trusted as the true noise level (``1.0`` = trust ``sigma``);
        default None estimates it per epoch by the MAD of the standardized residuals.
    min_scale : float
        Floor on the estimated scale (in units of ``sigma``).
    max_iter, tol : iteration limit (per stage) and threshold on the step size.
    rel_tol : float
        An epoch has also converged when its step is below ``rel_tol`` times the
        standard error of its fix (``sqrt(trace((J^T W J)^-1) s^2)``): iterating further
        moves the fix by a negligible fraction of its own uncertainty; or when an accepted
        step lowers its weighted cost by at most :data:`FLAT_COST` of it.  ``0`` turns
        both relative stops off: ``tol`` (and ``max_iter``) end the iteration, or a cost
        that falls by no more than rounding (:data:`FLAT_COST_FLOOR`).
    min_obs : int, optional
        Fewer valid observations give status ``insufficient_anchors`` (default: p).
    warmup : bool
        Redescending weights start from a Huber(1.5) solution (see
        :func:`robustloc.estimators.linear.irls`).

    Returns
    -------
    LinearFit
        ``x`` the solutions, ``v = f(x) - z``, final weights ``w``, ``qvv``, ``sigma0``,
        covariance ``sigma0^2 (J^T W J)^-1``; ``extra["u"]`` the standardized residuals.
    """
    z = np.atleast_2d(np.asarray(z, dtype=float))
    x = np.array(np.atleast_2d(np.asarray(x0, dtype=float)), dtype=float)
    N, n = z.shape
    p = x.shape[1]
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (N, n))
    valid = np.isfinite(z) & np.isfinite(sig) & (sig > 0)
    w0 = np.where(valid, 1.0 / np.where(valid, sig, 1.0) ** 2, 0.0)
    zz = np.where(valid, z, 0.0)
    n_valid = valid.sum(axis=1)
    min_obs = p if min_obs is None else min_obs
    status = np.full(N, st.OK, dtype=object)
    status[n_valid < min_obs] = st.INSUFFICIENT
    status[~np.all(np.isfinite(x), axis=1) & (status == st.OK)] = st.ILL_CONDITIONED
    w = w0.copy()
    iters = np.zeros(N, dtype=np.int64)
    conv = np.zeros(N, dtype=bool)
    u_all = np.full((N, n), np.nan)
    stages: list[WeightFunction | None] = [weight]
    if weight is not None and warmup and np.isfinite(weight.rejection_threshold):
        stages = [Huber(1.5), weight]
    base = np.flatnonzero(status == st.OK)
    for si, wf in enumerate(stages):
        last = si == len(stages) - 1
        act = base.copy()
        lam = np.full(N, 1e-3)
        # MM-style: the robust scale is estimated at the start of each stage and then held
        # fixed, so a drifting fit cannot inflate its own scale and re-admit outliers
        stage_scale = np.full(N, np.nan) if scale is None else np.full(N, float(scale))
        # redescending weights: the residuals' cofactors follow the weights (see below)
        update = wf is not None and np.isfinite(wf.rejection_threshold)
        prev_step = np.full(N, np.nan)  # each epoch's last accepted step (see below)
        frozen = np.zeros(N, dtype=bool)
        pending = np.zeros(N, dtype=bool)
        for it in range(max_iter):
            if act.size == 0:
                break
            xa = x[act]
            pred, J = _model_rows(model, xa, act)
            r = zz[act] - pred
            wa0 = w0[act]
            if wf is not None:
                if it == 0:  # Q_vv of the a-priori fit, once per stage (geometry barely moves)
                    Ninv0, _ = _inv_small(normal_matrix(J, wa0))
                    with np.errstate(all="ignore"):
                        hNh = np.sum(np.matmul(J, Ninv0) * J, axis=2)
                        qvv0 = np.where(wa0 > 0, 1.0 / np.where(wa0 > 0, wa0, 1) - hNh, np.nan)
                    stage_qvv = np.full((N, n), np.nan)
                    stage_qvv[act] = np.maximum(qvv0, 0.0)
                    q_now = stage_qvv.copy()
                elif update:
                    # the cofactors of the fit the last weights made: a row they left out
                    # is judged by its prediction cofactor 1/P + h, not by the 1/P - h of
                    # a fit that held it (with those, a rejection confirmed itself: IGG
                    # rejected 6.3 % of Gaussian ranges where k1 = 2.5 means 1.2 %).
                    # Updated until the fit has converged once (or COFACTOR_UPDATES
                    # iterations), then held: the rest converges as with fixed cofactors
                    # (updating to the end, 1-2 % of IGG fits never settled)
                    upd = ~frozen[act]
                    if upd.any():
                        ia = act[upd]
                        # (every weight full: the a-priori cofactors, as at the start)
                        q_now[ia] = np.where(
                            np.all(w[ia] == wa0[upd], axis=1)[:, None], stage_qvv[ia],
                            sandwich_qvv(J[upd], wa0[upd], w[ia], stage_qvv[ia]))
                        frozen[ia] = pending[ia] | (it >= COFACTOR_UPDATES)
                u, s_used = standardized_residuals(
                    np.where(wa0 > 0, -r, np.nan), q_now[act], wa0,
                    None if it == 0 and scale is None else stage_scale[act], min_scale,
                )
                if it == 0:
                    stage_scale[act] = s_used
                wa = wa0 * np.nan_to_num(wf.weights(u), nan=0.0)
                if np.any(np.sum(wa > 0, axis=1) < p):  # keep geometry: fall back to a-priori
                    bad = np.sum(wa > 0, axis=1) < p
                    wa[bad] = w[act][bad]
                u_all[act] = u
            else:
                wa = wa0
            JW = J * wa[..., None]
            Nm = np.matmul(np.swapaxes(JW, 1, 2), J)
            g = np.matmul(np.swapaxes(JW, 1, 2), r[..., None])[..., 0]
            # damping by the mean diagonal (trace / p) times I: unlike Marquardt's
            # diag(J^T W J) it is rotation-invariant, so fixes move rigidly with the anchors
            tr = np.maximum(np.einsum("kii->k", Nm) / p, 1e-12)
            Nd = Nm + (lam[act] * tr)[:, None, None] * np.eye(p)
            Ninv, good = _inv_small(Nd)
            dx = np.matmul(Ninv, g[..., None])[..., 0]
            xn = xa + dx
            pred_n = _predict_rows(model, xn, act)
            cost_old = np.sum(wa * r * r, axis=1)
            rn = zz[act] - pred_n
            cost_new = np.sum(wa * rn * rn, axis=1)
            accept = good & np.isfinite(cost_new) & (cost_new <= cost_old * (1 + 1e-12))
            x[act[accept]] = xn[accept]
            w[act] = wa
            lam[act] = np.where(accept, np.maximum(lam[act] / 1.5, 1e-9), lam[act] * 3.0)
            iters[act] += 1
            # the step's length (Euclidean: a per-coordinate maximum depends on the frame's
            # rotation, and so did where a reweighted fit stopped -- an asym fix moved
            # 0.22 m with the frame, the locate review of 2026-12-06)
            step = np.sqrt(np.sum(dx**2, axis=1))
            # the distance still to go: a reweighted iteration converges linearly, its
            # steps shrinking by a ratio q, so the steps to come add up to step q/(1 - q)
            # (none known after the first step).  Stopping at a small step alone left
            # robust fixes 5 standard errors short of their optimum as "converged" (steps
            # 12, 5, 3, 1.4, 0.97 mm, the optimum 0.28 m on; the review of 2026-12-06)
            go = _still_to_go(step, prev_step[act], accept & (wf is not None))
            prev_step[act] = np.where(accept, step, prev_step[act])
            reach = step + go
            # a relative stop, as rel_tol's; with rel_tol = 0 only at the rounding floor (at
            # 1e-6 it left a Gauss-Newton fix 1.5 mm short of its optimum whatever tol
            # said, the API review of 2026-12-07)
            flat_cost = FLAT_COST if rel_tol > 0 else FLAT_COST_FLOOR
            flat = accept & (cost_old - cost_new <= flat_cost * np.maximum(cost_old, 1e-300))
            # a step below 1e-3 of the fix's own standard error changes nothing that matters
            dof = np.maximum(np.sum(wa > 0, axis=1) - p, 1)
            with np.errstate(all="ignore"):
                sd = np.sqrt(np.einsum("kii->k", Ninv) * np.maximum(cost_new, 0) / dof)
            tiny = accept & (reach <= rel_tol * np.nan_to_num(sd, nan=0.0))
            done = (accept & (reach < tol)) | flat | tiny | (lam[act] > 1e8) | ~np.isfinite(step)
            if update:  # converged with moving cofactors: once more with them held
                again = done & ~frozen[act] & np.isfinite(step) & (lam[act] <= 1e8)
                pending[act[again]] = True
                done &= ~again
            if last:
                conv[act[done & np.isfinite(step)]] = True
            act = act[~done]
    # final statistics at the solution
    ok = status == st.OK
    idx = np.flatnonzero(ok)
    v = np.full((N, n), np.nan)
    qvv_f = np.full((N, n), np.nan)
    cov = np.full((N, p, p), np.nan)
    sigma0 = np.full(N, np.nan)
    n_used = np.sum(w > 0, axis=1)
    if idx.size:
        pred, J = _model_rows(model, x[idx], idx)
        wi = w[idx]
        Ninv, good = _inv_small(normal_matrix(J, wi))
        vi = np.where(valid[idx], pred - z[idx], np.nan)
        dof = n_used[idx] - p
        with np.errstate(all="ignore"):
            hNh = np.sum(np.matmul(J, Ninv) * J, axis=2)
            qv = np.where(wi > 0, 1.0 / np.where(wi > 0, wi, 1) - hNh, np.inf)
            vpv = np.nansum(np.where(wi > 0, wi * vi * vi, 0.0), axis=1)
            s0 = np.where(dof > 0, np.sqrt(vpv / np.maximum(dof, 1)), np.nan)
            s2 = np.where(dof > 0, s0**2, 1.0)
        v[idx] = vi
        qvv_f[idx] = np.where(valid[idx], np.maximum(qv, 0), np.nan)
        cov[idx] = Ninv * s2[:, None, None]
        sigma0[idx] = s0
        bad = idx[~good]
        status[bad] = st.ILL_CONDITIONED
        cov[bad] = np.nan
    status[(status == st.OK) & ~conv] = st.NOT_CONVERGED
    x[~st.among(status, st.USABLE)] = np.nan
    return LinearFit(
        x=x, v=v, w=np.where(valid, w, np.nan), qvv=qvv_f, sigma0=sigma0, cov=cov,
        n_used=n_used, iterations=iters, converged=conv, status=status, extra={"u": u_all},
    )
