"""Glue between :class:`~robustloc.estimators.ranging.Locator` and the integrity layer's
iterative data snooping (seed 003), with Gauss-Newton re-solved after each exclusion."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from robustloc.estimators.linear import LinearFit
from robustloc.estimators.nonlinear import gauss_newton

Array = NDArray[np.float64]


def snooping_ranging(locator, model, obs: Array, x0: Array, sig: Array) -> LinearFit:
    """Data snooping on ranging/RSSI observation equations.

    Each pass re-solves (Gauss-Newton from the previous solution) only the epochs whose
    global test still fails, with the excluded observations removed; the global test uses
    the B-method's ``alpha`` for the current redundancy and the w-test ``N(1 - alpha0/2)``.
    """
    from robustloc.integrity.snooping import snoop

    x_state = np.array(x0, dtype=float)
    dim = x0.shape[1]

    def solve(mask: NDArray[np.bool_], rows: NDArray[np.int64]):
        z = np.where(mask, obs[rows], np.nan)
        fit = gauss_newton(
            model, z, x_state[rows], sig[rows], max_iter=locator.max_iter, tol=locator.tol,
            min_obs=dim + 1,
        )
        x = fit.x
        ok = np.all(np.isfinite(x), axis=1)
        x_state[rows[ok]] = x[ok]
        xs = np.where(ok[:, None], x, x_state[rows])
        J = model.jacobian(xs)
        v = model.predict(xs) - obs[rows]
        return x, J, np.where(mask, v, np.nan)

    mask = np.isfinite(obs)
    res = snoop(solve, mask, sig, alpha0=locator.alpha0, beta0=locator.beta0)
    with np.errstate(all="ignore"):
        s0 = np.sqrt(res.global_stat / np.where(res.dof >= 1, res.dof, np.nan))
    # the a-posteriori covariance sigma0^2 (J^T P J)^-1, as every other method's (the
    # LinearFit contract); snooping's own is the a-priori one (the numerical review of
    # 2026-12-06: cov_xx of snooping rows 1/sigma0^2 of nls' on the same fix)
    s2 = np.where(np.isfinite(s0), s0 * s0, 1.0)
    weights = np.where(res.used, 1.0 / sig**2, np.where(res.excluded, 0.0, np.nan))
    return LinearFit(
        x=res.x, v=res.residuals, w=weights, qvv=res.redundancy * sig**2, sigma0=s0,
        cov=res.cov * s2[:, None, None], n_used=res.n_used, iterations=res.iterations,
        converged=np.isin(res.status, ("ok", "fault_excluded")), status=res.status,
        extra={
            "flagged": res.excluded, "w_test": res.w, "global_stat": res.global_stat,
            "global_crit": res.global_crit, "exclusion_order": res.exclusion_order,
            "detected": res.detected,
        },
    )
