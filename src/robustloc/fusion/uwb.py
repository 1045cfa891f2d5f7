"""UWB range-only fixes: the paper's linearized LS and distance-weighted WLS (seed 001).

Linearization (seed 001, eqs. (3)-(4), as in seed 000 eq. (2)): subtracting the equation of a
reference anchor ``r`` (per epoch, the first anchor heard) from that of anchor ``i`` gives

    (a_i - a_r)^T x = (d_r^2 - d_i^2 + |a_i|^2 - |a_r|^2) / 2

a linear system ``A x = b`` built by :func:`robustloc.estimators.ranging.linearized_system`
(the same one ``robustloc locate --method ls`` solves) and solved for all epochs at once
with :func:`robustloc.estimators.linear.solve_wls`.  In 2-D with known vertical offsets
``dz_i`` (anchor height minus tag height) the slant ranges are first made horizontal,
``d_i^2 <- d_i^2 - dz_i^2``.

WLS weights (seed 001 eq. (5), lost in extraction -- our documented choice): the range noise
grows with distance, ``sigma_i = sigma0_m + k * d_i``; the linearized observation is half a
*squared* range, whose standard deviation is ``d_i sigma_i``; so

    omega_i = 1 / (d_i sigma_i)^2              (k = 0: omega_i proportional to 1 / d_i^2)

which down-weights far anchors twice: by their noisier range and by the squaring.  The
reference anchor's error enters every row: the weights ignore it (as in the paper), the
reported covariance includes it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc.estimators.linear import solve_wls
from robustloc.estimators.ranging import linearized_system

Array = NDArray[np.float64]


@dataclass(frozen=True)
class UwbFix:
    """Per-epoch UWB fixes.

    Attributes
    ----------
    position : (N, dim) positions (NaN where no fix).
    covariance : (N, dim, dim) covariance ``(A^T omega A)^-1`` scaled to metres.
    n_used : (N,) ranges used.
    status : (N,) status strings (``ok``, ``insufficient_anchors``, ``ill_conditioned``).
    """

    position: Array
    covariance: Array
    n_used: NDArray[np.int64]
    status: NDArray[np.str_]


def range_sigma(range_m: ArrayLike, sigma0_m: float = 0.1, k: float = 0.0) -> Array:
    """Distance-dependent range standard deviation ``sigma0_m + k d`` (module docstring)."""
    return sigma0_m + k * np.abs(np.asarray(range_m, dtype=float))


def uwb_fix(
    anchors: ArrayLike,
    ranges_m: ArrayLike,
    method: Literal["ls", "wls", "nls"] = "ls",
    height_offset_m: ArrayLike | None = None,
    sigma0_m: float = 0.1,
    k: float = 0.0,
) -> UwbFix:
    """Linearized LS or WLS UWB fixes for ``N`` epochs at once (seed 001, eqs. (3)-(4)).

    Parameters
    ----------
    anchors : (m, dim) anchor coordinates.
    ranges_m : (N, m) measured ranges, NaN where an anchor was not heard.
    method : ``"ls"`` (equal weights), ``"wls"`` (``omega_i = 1/(d_i sigma_i)^2``) or
        ``"nls"``: Gauss-Newton on the range equations themselves
        (:func:`robustloc.estimators.nonlinear.gauss_newton` with
        :class:`robustloc.models.ranging.RangeModel`, weights ``1/sigma_i^2``) started from
        the LS fix -- the better fix when the anchors span little compared with the ranges.
    height_offset_m : (m,) optional anchor-minus-tag heights for 2-D fixes from slant ranges.
    sigma0_m, k : range noise model ``sigma_i = sigma0_m + k d_i`` (WLS weights and the
        covariance of both methods).
    """
    a = np.asarray(anchors, dtype=float)
    d = np.atleast_2d(np.asarray(ranges_m, dtype=float))
    if a.ndim != 2 or d.shape[1] != a.shape[0]:
        raise ValueError(f"anchors {a.shape} and ranges {d.shape} do not match")
    if method not in ("ls", "wls", "nls"):
        raise ValueError(f"method must be 'ls', 'wls' or 'nls', got {method!r}")
    N, m = d.shape
    dim = a.shape[1]
    d = np.where(np.isfinite(d), d, np.nan)
    # the paper's difference system (first heard anchor as reference), shared with
    # robustloc locate: rows a_i - a_ref, rhs (d_ref^2 - d_i^2 - |a_ref|^2 + |a_i|^2) / 2
    H, y, ref, centre = linearized_system(a, d, height_offset_m)
    heard = np.isfinite(d)
    rows = np.arange(N)
    rr = np.maximum(ref, 0)
    sig = range_sigma(d, sigma0_m, k)
    var_own = (np.abs(d) * sig) ** 2  # own noise of each row: d_i e_i
    var_ref = (np.abs(d[rows, rr]) * sig[rows, rr]) ** 2  # d_ref e_ref, shared by all rows
    if method == "wls":
        w = 1.0 / np.maximum(var_own, 1e-12)  # documented weights, 1 / (d_i sigma_i)^2
    else:
        w = np.ones((N, m))
    fit = solve_wls(H, y, np.where(np.isfinite(y), w, 0.0))
    # covariance (A^T W A)^-1 A^T W C_b W A (A^T W A)^-1 with the row covariance
    # C_b = diag(var_own) + var_ref 1 1^T (the reference range enters every row)
    Wm = np.where(np.isfinite(y), w, 0.0)
    Hz = np.where(np.isfinite(y)[..., None], H, 0.0)
    Nm = np.einsum("kmi,km,kmj->kij", Hz, Wm, Hz)
    C = np.einsum("kmi,km,kmj->kij", Hz, Wm * Wm * np.nan_to_num(var_own), Hz)
    g = np.einsum("kmi,km->ki", Hz, Wm)
    C = C + np.nan_to_num(var_ref)[:, None, None] * np.einsum("ki,kj->kij", g, g)
    good = np.isfinite(fit.x).all(axis=1) & (np.abs(np.linalg.det(Nm)) > 1e-12)
    Ninv = np.full_like(Nm, np.nan)
    if good.any():
        Ninv[good] = np.linalg.inv(Nm[good])
    cov = Ninv @ C @ Ninv
    n_used = heard.sum(axis=1)
    status = np.asarray(fit.status, dtype=object).copy()
    status[n_used < dim + 1] = st.INSUFFICIENT
    pos = np.where((status == st.OK)[:, None], fit.x + centre, np.nan)
    if method == "nls":
        return _nls_fix(a, d, pos, status, height_offset_m, sigma0_m, k)
    return UwbFix(
        position=pos,
        covariance=np.where((status == st.OK)[:, None, None], cov, np.nan),
        n_used=n_used.astype(np.int64),
        status=status.astype(str),
    )


def _nls_fix(
    a: Array, d: Array, x_ls: Array, status_ls: NDArray, height_offset_m, sigma0_m: float,
    k: float,
) -> UwbFix:
    """Gauss-Newton fixes on the range equations, started at the linearized LS fix."""
    from robustloc.estimators.nonlinear import gauss_newton
    from robustloc.models.ranging import RangeModel

    N, m = d.shape
    dim = a.shape[1]
    hz = None if height_offset_m is None else np.broadcast_to(
        np.asarray(height_offset_m, dtype=float), (m,))
    model = RangeModel(a, hz)
    x0 = np.where(np.isfinite(x_ls), x_ls, a.mean(axis=0)[None] + 1.0)
    heard = np.isfinite(d).sum(axis=1)
    sig = range_sigma(d, sigma0_m, k)
    fit = gauss_newton(model, d, x0, sig, scale=1.0, min_obs=dim + 1)
    status = np.asarray(fit.status, dtype=object).copy()
    status[heard < dim + 1] = st.INSUFFICIENT
    # not_converged is a usable fix (every step was damped and lowered the cost): it is
    # kept, and reported as such rather than relabelled ok
    usable = st.among(status, st.USABLE)
    good = usable & np.isfinite(fit.x).all(axis=1)
    # the a-priori covariance sigma^2 (J^T W J)^-1 at the fix: the sigmas are trusted
    # (``scale=1``), so the one-epoch estimate of the unit-weight variance in ``fit.cov``
    # (one redundant range with three anchors) does not belong in it -- it made the fixes
    # up to 100 times too confident for the filter (the filter/fuse review: mean e^2/var
    # 38 and 143 on ten simulated carts; 0 on noise-free ranges)
    from robustloc.estimators._kernels import inv_spd, normal_matrix

    J = model.jacobian(np.where(good[:, None], fit.x, x0))
    Ninv, regular = inv_spd(normal_matrix(J, np.where(np.isfinite(d), 1.0 / sig**2, 0.0)))
    good &= regular
    status[~good & usable] = st.ILL_CONDITIONED
    return UwbFix(
        position=np.where(good[:, None], fit.x, np.nan),
        covariance=np.where(good[:, None, None], Ninv, np.nan),
        n_used=heard.astype(np.int64),
        status=status.astype(str),
    )


def fix_test_status(
    anchors: ArrayLike,
    ranges_m: ArrayLike,
    fix: UwbFix,
    method: Literal["ls", "wls", "nls"],
    height_offset_m: ArrayLike | None = None,
    sigma0_m: float = 0.1,
    k: float = 0.0,
) -> NDArray[np.str_]:
    """The fixes' own test, as ``robustloc locate`` tests a fix of the same method.

    The fixes of :func:`uwb_fix` go through :func:`robustloc.integrity.fixes.protect`
    (the w-test and the B-method's global test of the range residuals, seed 003) with the
    a-priori range sigmas ``sigma0_m + k d`` the fixes' covariances trust -- the test of
    ``locate --method METHOD --sigma SIGMA0 --robust-scale apriori``, not a second one
    (the same statuses epoch by epoch on ``tests/test_fuse_filter_review3.py``'s log).  A
    linearized fix (``ls``, ``wls``) is tested on the least-squares re-solution of its
    ranges, as there.

    Parameters
    ----------
    anchors : (m, 2) anchor coordinates.
    ranges_m : (N, m) the ranges the fixes were made from (NaN: not heard).
    fix : the fixes (:func:`uwb_fix` of the same ranges).
    method : the fixes' method.
    height_offset_m : (m,) optional anchor-minus-tag heights (slant ranges).
    sigma0_m, k : range noise model ``sigma_i = sigma0_m + k d_i``.

    Returns
    -------
    ndarray of str, shape (N,)
        ``protect``'s status of each fix: ``fault_detected`` or ``unavailable`` where the
        test failed (or flagged observations left nothing to confirm the rest), ``ok``
        etc. where it passed; a fix that is not usable keeps its own status.
    """
    from robustloc.estimators.ranging import _area
    from robustloc.estimators.solution import Solution
    from robustloc.integrity.fixes import protect, range_model_of
    from robustloc.models.ranging import RangeModel

    a = np.asarray(anchors, dtype=float)
    d = np.atleast_2d(np.asarray(ranges_m, dtype=float))
    N, m = d.shape
    hz = None if height_offset_m is None else np.broadcast_to(
        np.asarray(height_offset_m, dtype=float), (m,))
    status = np.asarray(fix.status, dtype=object)
    usable = st.among(status, st.USABLE) & np.isfinite(fix.position).all(axis=1)
    x = np.where(usable[:, None], fix.position, np.nan)
    pred, jac = RangeModel(a, hz).predict_jacobian(np.nan_to_num(x))
    use = usable[:, None] & np.isfinite(d)
    v = np.where(use, pred - d, np.nan)  # range residuals f(x) - d, as Locator.solve's
    sig = range_sigma(d, sigma0_m, k)
    dof = use.sum(axis=1) - a.shape[1]
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma0 = np.sqrt(np.nansum((v / sig) ** 2, axis=1) / dof)
    sol = Solution(
        position=x, covariance=fix.covariance, residuals=v,
        weights=np.where(use, 1.0 / sig**2, np.nan), excluded=np.zeros((N, m), dtype=bool),
        sigma0=np.where(dof > 0, sigma0, np.nan), iterations=np.zeros(N, dtype=np.int64),
        converged=np.ones(N, dtype=bool), status=status.copy(),
        n_used=np.asarray(fix.n_used, dtype=np.int64), method=method,
        extra={"range_residuals": v, "jacobian": np.where(use[..., None], jac, np.nan),
               "sigma_obs": sig, "anchor_extent": _area(a),
               "solver": "linearized" if method in ("ls", "wls") else "nonlinear"},
    )
    return np.asarray(protect(sol, range_model=range_model_of(a, hz)).status, dtype=str)
