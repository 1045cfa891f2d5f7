"""Integrity of position fixes from ranges or RSSI: the fix's own test, and a protection
level on every fix (seed 003 applied to :class:`robustloc.estimators.ranging.Locator`).

For each epoch, at the fix ``x`` of any method, with the range-domain residuals
``v_i = f_i(x) - d_i``, the design ``J`` (``d f / d x``) and the a-priori standard deviations
``sigma_i`` (the log's per-anchor scale, :meth:`Locator.log_scale`, or the user's sigma):

1. **Flag** the observations the fix does not explain: the w-statistic
   ``w_i = v_i / (sigma_i sqrt(r_i))`` (seed 003, eqs. (1)-(2); ``r_i`` the redundancy
   number of the heard observations) above ``N(1 - alpha0/2)`` (3.29), and observations
   the estimator itself excluded (weight zero).  A robust fix has already down-weighted
   them; they leave the test and the protection level.  A robust fit's residual is
   tested against its own variance under the fit's weights instead of
   ``sigma_i^2 r_i`` (seed 003's ``Q_vv`` for equivalent weights,
   :func:`~robustloc.estimators.linear.sandwich_qvv`, with the fit's
   ``extra["weight_factor"]``): a row it down-weighted keeps most of its error, and with
   ``r_i`` the w-test flagged 3.6x (huber) to 18x (igg3) ``alpha0`` of Gaussian rows.  A
   plain fit (``ls``, ``wls``, ``nls``) keeps them at full weight: its test and bound
   stay over every observation of the fix, and a flag makes it ``fault_detected``.
2. **Global test** of the remaining observations: ``T = sum v_i^2 / sigma_i^2`` against
   ``chi2(1 - alpha; n' - p)`` with ``alpha`` from the B-method for that redundancy (seed
   003, eqs. (3)-(4)); of a robust fit, ``T`` of the least-squares re-solution over the
   remaining observations (linearized at the fix), the test after the exclusion.
3. **Status**:

   ========================  ====================================================  ======
   status                    when                                                  usable
   ========================  ====================================================  ======
   ``ok``                    nothing flagged, the test passes, redundancy >= 2      yes
   ``fault_excluded``        observations flagged (excluded or down-weighted by     yes
                             the estimator, or flagged by the w-test where the
                             estimator down-weights; they leave the test and the
                             protection level), the test of the rest passes
   ``low_redundancy``        redundancy 1 (robust methods: the plain fit was        yes
                             used), nothing flagged, the test passes: a fault of
                             the MDB would be detected but not identified
   ``unverified``            redundancy 0, or no scale to test with (the epoch's    yes
                             own ``sigma0`` is 0: exactly consistent observations
                             under a per-epoch scale): nothing can be tested;
                             ``hpl = inf``
   ``fault_detected``        the test fails (``hpl`` from sigma scaled by the       yes
                             a-posteriori factor ``sqrt(T / dof)``), or the w-test
                             flags an observation that a plain fit (``ls``,
                             ``wls``, ``nls``: :data:`PLAIN_FIT_METHODS`) keeps
                             at full weight (test and bound then over every
                             observation of the fix): a fault is detected and
                             cannot be excluded; the position is kept, its bound
                             says how little it is worth
   ``unavailable``           a flagged observation leaves no redundancy to          no
                             confirm the rest (nothing bounds the fix); or half
                             or more of the heard observations are flagged
                             (item 6: no majority supports the fix)
   ``extrapolated``          usable by the above, but farther than 10 times the     yes
                             heard anchors' extent from them: the geometry is
                             extrapolated, ``hpl`` (large there) says how far; a
                             far fix whose test fails stays ``fault_detected``
   ``protection_exceeded``   usable, but ``hpl`` (kept) above ``--alert-limit``     no
   ========================  ====================================================  ======

   A ``not_converged`` fix (usable: the iterations stopped before the step fell below
   the tolerance) is tested the same way: a failed test or a minority kept overrides its
   status, a passing test keeps it.  Any other status an epoch already has is kept.
   A usable fix whose bound cannot be computed gets ``hpl = inf``, never NaN.
4. **Protection levels** (Baarda's external reliability, the slope method of snapshot RAIM
   with the B-method's ``lambda0``, as :mod:`robustloc.gnss.raim` does for GNSS): a bias
   of the size of the minimal detectable bias ``MDB_i = sigma_i sqrt(lambda0 / r_i)`` on
   observation ``i`` moves the fix by ``dx_i = (J^T P J)^-1 J^T P e_i MDB_i``;

       HPL = max_i |dx_i|_horizontal + k sqrt(lambda_max(C_xy)),
       VPL = max_i |dz_i|             + k sqrt(C_zz),              k = N(1 - alpha0/2)

   with ``C = (J^T P J)^-1`` over the unflagged observations.  Infinite where an
   observation that moves the fix has no redundancy (its fault could not be detected).
   The integrity-risk parameters are ``alpha0`` (false alarm of the w-test, 0.1 %),
   ``beta0`` (missed detection of an MDB-sized fault, 10 %) and ``k``.  The default ``k``
   is the one-dimensional quantile on the major semi-axis, as in
   :mod:`robustloc.gnss.raim` (whose docstring gives the 2-D exceedance it allows: up to
   4.5 ``alpha0`` for a circular ellipse); ``k_noise = sqrt(chi2.isf(alpha0, 2))`` = 3.72,
   the tracker's, bounds it at ``alpha0`` (``--k-noise 3.72``).
   A plain fit whose weights are not ``P`` (Gauss-Newton with equal weights on anchors
   of unequal noise, ``extra["fit_weight_factor"]``) is bounded as the fix it gave: its
   gain, its sandwich covariance and MDBs under its own weights
   (:func:`protection_levels_local` with ``fit_weight``).  A ``fault_excluded`` fix
   also covers every other single exclusion whose least-squares fix passes the test,
   ``HPL = max(HPL, |x_j - x|_h + k sigma_major(x_j))`` (:func:`_cover_other_exclusions`: at
   redundancy 2 the largest ``w`` often names a healthy range).
5. **Ambiguity** (with the anchors known, :func:`locate_protected` passes them): ranges
   from collinear anchors (2-D; coplanar in 3-D) fit the fix and its mirror image across
   the anchors' line (plane) equally well, and nearly collinear anchors leave a second
   minimum that fits almost as well; no residual and no slope sees a fix on the wrong
   side.  Where the kept anchors are elongated (:func:`anchor_elongation` below
   :data:`AMBIGUITY_ELONGATION`), the fix reflected across the principal line (plane) of
   its kept anchors is refined by Gauss-Newton (:func:`mirror_solution`); when that
   alternative ``x'`` passes the fix's own global test (``T' <= chi2(1 - alpha; n' - p)``, the same
   observations and sigma), the data cannot tell the two apart and the bound covers the
   alternative, as a float-versus-fixed ambiguity must be covered in carrier-phase
   integrity:

       HPL = max(HPL, |x' - x|_horizontal + HPL(x')),   VPL likewise with |z' - z|

   with ``HPL(x')`` the slope bound of item 4 at the alternative.  Measured on the
   wifi-rtt-rss corridor (four nearly collinear access points) after ``calibrate
   --self``: every fix whose error exceeded its bound lay across the anchors' line from
   the truth (cross-line error 8.8 m median, along 0.5 m), and the mirror passed the
   fix's test in 72 % of them (issue 10); the term takes the misleading share there from
   15 % to 4.3 % (the rest: the mirror fails a test whose sigma, the calibrated sigma
   times the log's MAD scale, is 0.4-0.8 of the residual spread at the truth).  The
   bound assumes one fault, and so does the check: where the mirror fails on every kept
   observation, the mirror refined without one of them, ``x'_j``, that passes its test
   is covered as well, ``HPL = max(HPL, |x'_j - x|_h + k sigma_major(x'_j))``
   (:func:`_cover_mirror_exclusions`; bound only, the fix is not moved).  The same
   corridor (2026-12-07): 75 of 6 832 usable fixes beyond their bound, one access point
   4-8 m long in each, then none.

6. **Majority.**  A fix whose flagged observations are half or more of those heard is
   ``unavailable``: the flagged ones may be the consistent ones.  No estimator breaks
   down more slowly than 50 % (the breakdown point of regression equivariant estimators,
   Rousseeuw & Leroy 1987, sec. 3.4): with a minority kept, another subset of the same
   size or larger may fit as well elsewhere, and neither the test nor the slope bound
   (both single-fault arguments over the kept observations) can tell.  Measured on
   ``bench_locate.py``'s workload (10 ranges, 20 % gross errors U(3, 15) m, 100 000
   epochs, the default ``auto``): the misleading share of usable fixes (error > hpl)
   falls from 0.81 % to 0.06 % and the availability from 99.7 % to 96.7 %; every
   misleading fix had flagged 4-7 of its 10 ranges, mostly good ones (epochs with 5 or
   more gross errors: 2.9 %).  The flags counted are the w-test's, one at a time where
   flagging every ``w`` above the critical value at once would leave a robust fit no
   majority: one fault spreads over every residual, and data snooping (seed 003) flags
   the largest ``w`` alone when the least-squares fit of the rest passes its test and
   keeps a finite bound (:func:`_snoop_one`).  Measured on the shared real logs
   (default ``auto``, 2026-12-06): fixes that were ``unavailable`` and are now usable,
   every one within its bound: uwb-labyrinth 1 of 59, dwm1001 LOS 10, NLOS 17, the
   WiFi RTT corridor 2 and office 1; the lecture theatre and ble-tetam none.

7. **The log's side** (:func:`locate_protected` with ``robust_scale="log"``; ``robustloc
   locate --side-prior log``, the default).  Item 5 bounds an ambiguous fix, but the
   epoch cannot say which of the two is the tag; the log often can.  The usable fixes
   that are unambiguous (spread anchors, or a mirror that failed the test) show where the
   tags are: for each set of anchors that kept an ambiguous fix, and for the whole layout
   when it is one line (plane), the sides of its principal line on which the fixes that
   kept none but those anchors lie are counted, and a side is preferred when a two-sided
   sign test rejects a fair coin at :data:`SIDE_ALPHA` (1 %)
   (:func:`ambiguity_sides`: an empirical prior, from the first pass's sample when
   streaming).  An ambiguous fix on the other side, whose alternative lies on the
   preferred one, becomes its alternative (:func:`resolve_sides`); the bound covers both
   as before and the status is unchanged.  The wifi-rtt-rss corridor (every scan,
   ``auto``; 2026-12-06): 1 959 of 6 833 usable fixes moved, RMS 6.13 -> 3.67 m and p95
   11.3 -> 5.91 m, against scipy's 6.10 / 11.2; no fix moves on the other shared data sets
   (lecture theatre and office: 8 and 38 ambiguous fixes, no significant side).  A log
   whose tags are on both sides of the line gets no preference, and an ambiguous fix
   with a weak (not significant) prior stays where its estimator put it.

The a-priori ``sigma_i`` carries the whole statistical meaning: with the log's scale it is
the robust spread of each anchor's residuals over the log, so a fix whose residuals are
far larger than its anchors usually show fails its test instead of being called ``ok``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc._stats import chi2_sf, norm_cdf, t_ppf
from robustloc.estimators._kernels import inv_spd
from robustloc.estimators.linear import sandwich_qvv
from robustloc.estimators.ranging import _unique_rows, canonical_rank
from robustloc.estimators.solution import Solution
from robustloc.integrity.bmethod import ALPHA0, BETA0, global_critical, lambda0, w_critical
from robustloc.integrity.tests import R_MIN
from robustloc.models.geometry import anchor_elongation, elongation_rows
from robustloc.models.ranging import RangeModel

Array = NDArray[np.float64]

__all__ = ["ambiguity_sides", "anchor_elongation", "locate_protected", "mirror_solution",
           "protect", "protection_levels_local", "range_model_of", "resolve_sides"]

#: Horizontal axes of the solved dimension (x, y); the third, when present, is vertical.
_H = slice(0, 2)


def _per_observation(shape: tuple[int, int], **arrays: ArrayLike) -> list[Array]:
    """Each of ``arrays`` broadcast to ``shape`` (epochs, observations), named in the
    error when it cannot be: the compiled kernels read every row and column without
    bounds checks (the API review: a ``used`` of 100 columns beside a ``J`` of 4 wrote
    past an array's end -- "double free or corruption", SIGSEGV), and the NumPy
    reference broadcasts where they did not (an ``(N, 1)`` sigma: three ``hpl`` of 50
    differed)."""
    out = []
    for name, arr in arrays.items():
        a = np.asarray(arr)
        try:
            out.append(np.broadcast_to(a, shape))
        except ValueError:
            raise ValueError(f"{name} has shape {a.shape}; expected {shape} (epochs, "
                             "observations) or one that broadcasts to it") from None
    return out


def _design(J: ArrayLike) -> Array:
    """``J`` as a float array (epochs, observations, axes), axes 1 to 3."""
    Ja = np.asarray(J, dtype=float)
    if Ja.ndim != 3 or not 1 <= Ja.shape[2] <= 3:
        raise ValueError(f"J has shape {Ja.shape}; expected (epochs, observations, p) "
                         "with p = 1, 2 or 3")
    return Ja


def _fix_rows(range_model: RangeModel, position: ArrayLike, residuals: ArrayLike,
              **arrays: ArrayLike) -> tuple[Array, Array, list[Array]]:
    """``position (N, p)`` with ``p`` the anchors' axes, ``residuals (N, m)`` with ``m``
    the anchors, and ``arrays`` broadcast to ``(N, m)`` (:func:`_per_observation`)."""
    a = range_model.anchors
    x = np.asarray(position, dtype=float)
    if x.ndim != 2 or x.shape[1] != a.shape[1]:
        raise ValueError(f"position has shape {x.shape}; expected (epochs, "
                         f"{a.shape[1]}) for anchors of {a.shape[1]} axes")
    res = np.asarray(residuals, dtype=float)
    if res.shape != (x.shape[0], a.shape[0]):
        raise ValueError(f"residuals has shape {res.shape}; expected "
                         f"{(x.shape[0], a.shape[0])} (epochs, anchors)")
    return x, res, _per_observation(res.shape, **arrays)


def protection_levels_local(
    J: Array, sigma: Array, used: NDArray[np.bool_], lam0: float, k_noise: float,
    engine: str = "compiled", fit_weight: Array | None = None,
) -> tuple[Array, Array, Array]:
    """HPL, VPL (N,) and redundancy numbers (N, n) in a local frame (x, y[, z]).

    ``hpl = max_i |d x_h / d v_i| MDB_i + k sigma_major`` (the MDB slope bound of seed 003
    eq. (3) plus ``k_noise`` times the major semi-axis of the horizontal covariance); an
    observation whose fault moves the fix but cannot be detected (redundancy number at or
    below ``R_MIN``) makes the bound infinite.

    With ``fit_weight`` the fix is that of the weights ``f_i / sigma_i^2`` while each
    observation's noise is ``sigma_i`` (Gauss-Newton with equal weights on anchors of
    unequal noise): in whitened form ``a_i = J_i / sigma_i``, ``Q = (sum_i f_i a_i
    a_i^T)^-1``, the fix's gain ``g_i = f_i Q a_i`` and covariance ``C = sum_i g_i
    g_i^T`` (the sandwich), the residual's variance under those weights ``q_i = sum_j
    ((I - H)_ij)^2``, ``H_ij = f_j a_i^T Q a_j`` (:func:`robust_fit_cofactors`' ``Q_vv``,
    which the w-test takes), and a fault ``b`` on observation ``i`` shifts its residual by ``r_i
    b``, ``r_i = 1 - f_i a_i^T Q a_i``: ``MDB_i = sqrt(lambda0 q_i) sigma_i / |r_i|``
    and ``hpl = max_i |g_i,h| MDB_i / sigma_i + k sqrt(lambda_max(C_h))``.  With
    ``f = 1`` every term is the one above (``q_i = r_i``).  ``r`` is then ``r_i``.

    Parameters
    ----------
    J : ndarray (N, n, p)
        Design at the fix, ``p`` = 2 or 3 (x, y[, z] in metres).
    sigma : ndarray (N, n)
        A-priori standard deviation of each observation (m).
    used : ndarray of bool (N, n)
        Observations in the solution.
    lam0 : float
        Non-centrality ``lambda0`` of the B-method.
    k_noise : float
        Multiplier of the fault-free standard deviation.
    engine : {"compiled", "numpy"}
        The numba kernel (:mod:`robustloc.integrity._compiled`, default) or this NumPy
        reference; they agree to rounding (tested).
    fit_weight : ndarray (N, n), optional
        The fit's weight factors ``f_i`` in [0, 1] (NaN counts as 0), relative to
        ``1 / sigma_i^2``: the bound of the fix these weights gave (above).  Default: the
        fix weighted by ``1 / sigma_i^2``.

    Returns
    -------
    hpl, vpl, r
        ``vpl`` is NaN for 2-D fixes.
    """
    J = _design(J)
    N, n, p = J.shape
    sigma, used = _per_observation((N, n), sigma=sigma, used=used)
    if fit_weight is not None:
        (fw,) = _per_observation((N, n), fit_weight=fit_weight)
        return _fit_weighted_levels(J, sigma, used, fw, lam0, k_noise, engine)
    if engine == "compiled" and p in (2, 3) and N:
        from robustloc.integrity._compiled import protection_levels_kernel

        return _levels_compiled(protection_levels_kernel, (J, sigma, used), lam0, k_noise)
    if engine not in ("compiled", "numpy"):
        raise ValueError(f"engine must be 'compiled' or 'numpy', got {engine!r}")
    use, A = _whitened(J, sigma, used)
    Nm = np.matmul(np.swapaxes(A, 1, 2), A)  # J^T P J, (N, p, p)
    tr = np.einsum("kii->k", Nm)
    ok = (np.abs(np.linalg.det(Nm)) > 1e-12 * np.maximum(tr, 1e-300) ** p) & (
        use.sum(axis=1) >= p)
    Ninv = np.linalg.inv(np.where(ok[:, None, None], Nm, np.eye(p)))
    AN = np.matmul(A, Ninv)  # row i: (N^-1 A_i^T)^T = d x / d (v_i / sigma_i)
    r = np.where(use, 1.0 - np.sum(AN * A, axis=2), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        kk = np.sqrt(lam0 / np.where(r > R_MIN, r, np.nan))
        moves = np.sqrt(np.sum(AN * AN, axis=2)) > 1e-9
    return _levels(ok, use, moves, use & (r <= R_MIN) & moves, AN * kk[..., None], Ninv, r,
                   k_noise)


def _whitened(J: Array, sigma: Array, used: NDArray[np.bool_]
              ) -> tuple[NDArray[np.bool_], Array]:
    """The observations that count (used, finite, positive sigma) and the whitened design
    ``J_i / sigma_i`` (0 elsewhere)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        use = used & np.isfinite(sigma) & (sigma > 0) & np.all(np.isfinite(J), axis=2)
        A = np.where(use[..., None], J / np.where(use, sigma, 1.0)[..., None], 0.0)
    return use, A


def _levels_compiled(kernel, arrays: tuple, lam0: float, k_noise: float,
                     ) -> tuple[Array, Array, Array]:
    """Run a protection-level kernel (:mod:`robustloc.integrity._compiled`) over the
    epochs of ``arrays`` (``J`` first, then per-observation arrays) in threads."""
    from robustloc.estimators._compiled import in_threads

    J = arrays[0]
    N, n, p = J.shape
    cont = [np.ascontiguousarray(a, dtype=np.bool_ if a.dtype == bool else np.float64)
            for a in arrays]
    res = (np.empty(N), np.empty(N), np.empty((N, n)))

    def run(lo: int, hi: int) -> None:
        for o, part in zip(res, kernel(*(c[lo:hi] for c in cont), float(lam0),
                                       float(k_noise), float(R_MIN), (0.0,) * p),
                           strict=True):
            o[lo:hi] = part

    in_threads(run, N)
    return res


def _levels(ok: NDArray[np.bool_], use: NDArray[np.bool_], moves: NDArray[np.bool_],
            blind: NDArray[np.bool_], dx: Array, C: Array, r: Array, k_noise: float,
            ) -> tuple[Array, Array, Array]:
    """``(hpl, vpl, r)`` from each observation's MDB shift ``dx`` (N, n, p) and the fix's
    covariance ``C``: the largest horizontal (vertical) shift, infinite where ``blind``,
    plus ``k_noise`` standard deviations (the horizontal major semi-axis)."""
    N, _, p = dx.shape
    with np.errstate(invalid="ignore", divide="ignore"):
        dh = np.where(blind, np.inf, np.where(use & moves, np.hypot(dx[..., 0], dx[..., 1]),
                                               0.0))
        du = (np.where(blind, np.inf, np.where(use & moves, np.abs(dx[..., 2]), 0.0))
              if p == 3 else None)
    cen = C[:, _H, _H]
    tr, det = cen[:, 0, 0] + cen[:, 1, 1], cen[:, 0, 0] * cen[:, 1, 1] - cen[:, 0, 1] ** 2
    lam_max = 0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    with np.errstate(invalid="ignore"):
        hpl = np.where(ok, np.max(np.nan_to_num(dh, nan=0.0, posinf=np.inf), axis=1)
                       + k_noise * np.sqrt(lam_max), np.nan)
        vpl = (np.where(ok, np.max(np.nan_to_num(du, nan=0.0, posinf=np.inf), axis=1)
                        + k_noise * np.sqrt(C[:, 2, 2]), np.nan)
               if p == 3 else np.full(N, np.nan))
    return hpl, vpl, np.where(use & ok[:, None], r, np.nan)


def _fit_weighted_levels(J: Array, sigma: Array, used: NDArray[np.bool_], fw: Array,
                         lam0: float, k_noise: float, engine: str
                         ) -> tuple[Array, Array, Array]:
    """:func:`protection_levels_local` with ``fit_weight`` (its docstring has the terms)."""
    N, n, p = J.shape
    fw = np.clip(np.nan_to_num(np.asarray(fw, dtype=float), nan=0.0), 0.0, 1.0)
    if engine == "compiled" and p in (2, 3) and N:
        from robustloc.integrity._compiled import fit_weighted_protection_kernel

        return _levels_compiled(fit_weighted_protection_kernel, (J, sigma, used, fw), lam0,
                                k_noise)
    if engine not in ("compiled", "numpy"):
        raise ValueError(f"engine must be 'compiled' or 'numpy', got {engine!r}")
    use, A = _whitened(J, sigma, used)
    f = np.where(use, fw, 0.0)
    Nm = np.einsum("kip,ki,kiq->kpq", A, f, A)
    tr = np.einsum("kii->k", Nm)
    ok = (np.abs(np.linalg.det(Nm)) > 1e-12 * np.maximum(tr, 1e-300) ** p) & (
        np.sum(use & (f > 0), axis=1) >= p)
    Q = np.linalg.inv(np.where(ok[:, None, None], Nm, np.eye(p)))
    QA = np.einsum("kpq,kiq->kip", Q, A)  # rows: Q a_i
    G = QA * f[..., None]  # the gains g_i
    C = np.einsum("kip,kiq->kpq", G, G)
    aqa = np.sum(A * QA, axis=2)
    r = 1.0 - f * aqa
    # q_i = sum_j ((I - H)_ij)^2 with H_ij = f_j a_i^T Q a_j, as a sum of squares (the
    # closed form 1 - 2 f_i a_i^T Q a_i + a_i^T C a_i cancels where r_i is small)
    # (in blocks of epochs: the (K, n, n) products of a large site's every anchor would
    # need N n^2 floats at once)
    q = np.empty((N, n))
    eye = np.eye(n, dtype=bool)[None]
    step = max(1, (1 << 22) // max(n * n, 1))
    for lo in range(0, N, step):
        sl = slice(lo, lo + step)
        H = np.einsum("kip,kjp->kij", A[sl], QA[sl]) * f[sl, None, :]
        IH = np.where((use[sl, None, :] & (f[sl, None, :] > 0)) | eye, eye - H, 0.0)
        q[sl] = np.sum(IH * IH, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        moves = np.sum(G * G, axis=2) > 1e-18
        kk = np.sqrt(lam0 * q) / np.abs(r)
    return _levels(ok, use, moves, use & moves & (np.abs(r) <= R_MIN), G * kk[..., None], C,
                   r, k_noise)


#: Gauss-Newton iterations of the mirror solution (:func:`mirror_solution`).
MIRROR_ITERATIONS = 10
#: Ridge of the mirror solution's normal matrix, relative to its trace (at least 1):
#: ``N + MIRROR_RIDGE max(tr N, 1) I``.  One kept observation of tiny sigma (an RSSI of
#: -10 dBm is a range of centimetres, its sigma ~1e-4 m) makes ``N`` rank one at
#: entries ~1e7; an absolute ridge of 1e-12 vanished in rounding there and LAPACK's
#: solve raised "singular matrix".  Relative, the ridge stays ~1e4 times the
#: elimination's rounding (2.2e-16 tr N); the Gauss-Newton step along the flat direction
#: is then large and the trust region (the kept anchors' extent) limits it.
MIRROR_RIDGE = 1e-12
#: The ambiguity check (module docstring, item 5) runs on the epochs whose kept anchors
#: are elongated: :func:`anchor_elongation` below this.  The reflection across the
#: anchors' line starts a second minimum only when they are close to a line; where they
#: span the plane the refinement returns to the fix.  Measured per epoch on the shared
#: real sets: the wifi-rtt corridor 0-0.015 (the ambiguity the check exists for), every
#: other set's median 0.14-0.97 (three heard anchors in a line: 0, checked); on the
#: benchmark's 10 spread anchors the check would cost half the default pipeline's time.
AMBIGUITY_ELONGATION = 0.05


def mirror_solution(
    range_model: RangeModel, position: Array, residuals: Array, sigma: Array,
    keep: NDArray[np.bool_], iterations: int = MIRROR_ITERATIONS, engine: str = "compiled",
) -> tuple[Array, Array, Array]:
    """The fix's mirror solution: reflected across its anchors' principal line, refined.

    For each epoch the kept anchors ``a_i`` give the centroid ``c`` and the unit normal
    ``u`` of their least-squares line (2-D; plane in 3-D): the eigenvector of the
    smallest eigenvalue of ``sum_i (a_i - c)(a_i - c)^T``.  The start
    ``x0 = x - 2 ((x - c) . u) u`` is the fix reflected across it (the exact second
    solution when the anchors are collinear, a start in the basin of the second minimum
    when they nearly are); ``iterations`` Gauss-Newton steps on the kept observations
    ``d_i = f_i(x) - v_i`` (the observed ranges, recovered from the fix and its residuals
    ``v = f(x) - d``) with weights ``1 / sigma_i^2`` refine it.  Where the anchors span
    the plane well the refinement usually returns to the fix itself (distance 0).

    Parameters
    ----------
    range_model : RangeModel
        Anchors (m, p) and height offsets of the fix, in the residuals' anchor order.
    position : ndarray (N, p)
        The fixes.
    residuals : ndarray (N, m)
        Range residuals ``f(x) - d`` at the fixes (NaN: not heard).
    sigma : ndarray (N, m)
        Standard deviation of each observation (m).
    keep : ndarray of bool (N, m)
        Observations the fix's test keeps.
    iterations : int
        Gauss-Newton steps.
    engine : {"compiled", "numpy"}
        The numba kernel (:func:`robustloc.integrity._compiled.mirror_kernel`, default:
        one epoch at a time, ~3x faster in 3-D where nearly every fix is checked) or this
        NumPy reference; they agree to rounding (tested).

    Returns
    -------
    x_alt : ndarray (N, p)
        The alternative solution (NaN where it could not be formed).
    T_alt : ndarray (N,)
        ``sum_i keep_i ((f_i(x_alt) - d_i) / sigma_i)^2``: its global test statistic.
    J_alt : ndarray (N, m, p)
        The design ``d f / d x`` at the alternative (for its protection level).
    """
    x, residuals, (sigma, keep) = _fix_rows(range_model, position, residuals, sigma=sigma,
                                            keep=keep)
    N, p = x.shape
    a = range_model.anchors
    if engine not in ("compiled", "numpy"):
        raise ValueError(f"engine must be 'compiled' or 'numpy', got {engine!r}")
    if engine == "compiled" and N and p in (2, 3):
        from robustloc.integrity._compiled import mirror_kernel

        h = range_model.height_offset
        h2 = np.zeros(a.shape[0]) if h is None else np.asarray(h, dtype=float) ** 2
        return mirror_kernel(np.ascontiguousarray(a, dtype=float), np.ascontiguousarray(h2),
                             np.ascontiguousarray(x), np.ascontiguousarray(residuals, float),
                             np.ascontiguousarray(sigma, dtype=float),
                             np.ascontiguousarray(keep, dtype=bool), int(iterations),
                             MIRROR_RIDGE)
    with np.errstate(invalid="ignore"):
        w = np.where(keep & np.isfinite(residuals) & (sigma > 0), 1.0 / sigma, 0.0)
    w = np.nan_to_num(w, nan=0.0, posinf=0.0)
    f0 = range_model.predict(np.nan_to_num(x))
    d = np.where(w > 0, f0 - np.nan_to_num(residuals), 0.0)  # observed ranges
    # principal line (plane) of each epoch's kept anchors
    from robustloc.models.geometry import principal_lines

    kept = w > 0
    k = kept.astype(float)
    c, u = principal_lines(a, kept)
    da = np.where(kept[..., None], a[None, :, :] - c[:, None, :], 0.0)  # (N, m, p)
    xa = x - 2.0 * np.einsum("ki,ki->k", x - c, u)[:, None] * u
    # Gauss-Newton, step limited to the kept anchors' extent (a trust region against a
    # start in a flat valley)
    extent = np.sqrt(np.max(np.einsum("kmi,kmi->km", da, da), axis=1))
    extent = np.maximum(extent, 1.0)
    ok = np.all(np.isfinite(xa), axis=1) & (k.sum(axis=1) > p)
    xa = np.where(ok[:, None], xa, 0.0)
    for _ in range(iterations):
        f, J = range_model.predict_jacobian(xa)
        A = np.where(w[..., None] > 0, J * w[..., None], 0.0)
        b = np.where(w > 0, (d - f) * w, 0.0)
        Nm = np.einsum("kmi,kmj->kij", A, A)
        tr = np.maximum(np.trace(Nm, axis1=1, axis2=2), 1.0)
        Nm = Nm + (MIRROR_RIDGE * tr)[:, None, None] * np.eye(p)[None]
        g = np.einsum("kmi,km->ki", A, b)
        step = np.linalg.solve(Nm, g[..., None])[..., 0]
        ln = np.linalg.norm(step, axis=1)
        step = step * np.minimum(1.0, extent / np.maximum(ln, 1e-300))[:, None]
        xa = xa + np.where(ok[:, None], step, 0.0)
    f, J = range_model.predict_jacobian(xa)
    T = np.sum(np.where(w > 0, ((f - d) * w) ** 2, 0.0), axis=1)
    ok &= np.all(np.isfinite(xa), axis=1) & np.isfinite(T)
    return (np.where(ok[:, None], xa, np.nan), np.where(ok, T, np.nan),
            np.where(ok[:, None, None], J, np.nan))


#: Significance of the sign test by which a line (plane) of kept anchors gets a preferred
#: side from the log (:func:`ambiguity_sides`): two-sided, the unambiguous fixes' sides
#: against a fair coin.
SIDE_ALPHA = 0.01


def _side_frame(anchors: Array, pattern: NDArray[np.bool_]) -> tuple[Array, Array]:
    """Centroid ``c`` and unit normal ``u`` of the principal line (plane) of the anchors
    in ``pattern``; ``u`` is oriented so that its largest component (the first of equal
    ones) is positive: the same anchors give the same side everywhere."""
    a = anchors[pattern]
    c = a.mean(axis=0)
    _, vec = np.linalg.eigh((a - c).T @ (a - c))
    u = vec[:, 0]
    return c, (u if u[np.argmax(np.abs(u))] > 0 else -u)


def ambiguity_sides(sol: Solution, range_model: RangeModel, alpha: float = SIDE_ALPHA
                    ) -> tuple[tuple[tuple[int, ...], int], ...]:
    """The side of each line (plane) of kept anchors on which the log's unambiguous fixes
    lie: the log's prior for the fixes that :func:`protect` found ambiguous (module
    docstring, item 7).

    Evidence: the usable, bounded fixes of ``sol`` (a :func:`protect`-ed batch, the log
    or its first pass's sample) with redundancy that are not ambiguous: their anchors
    span the plane, or their mirror failed their test, so the data of those epochs told
    the sides apart.  The anchor sets examined are those that kept an ambiguous fix, and
    all anchors when the whole layout is elongated (a corridor: one line, so that every
    fix of the log is evidence for it).  For a set, the evidence is the fixes that kept
    none but its anchors (they are beside that stretch of line); ``n+`` of them lie on the
    positive side of its principal line (normal oriented by :func:`_side_frame`) and
    ``n-`` on the other.  The side is preferred when the two-sided sign test rejects a
    fair coin, ``2 P(X <= min(n+, n-)) < alpha`` with ``X ~ Binomial(n+ + n-, 1/2)``
    (:func:`resolve_sides` then uses the smallest preferred set that contains a fix's
    kept anchors).  Measured on the wifi-rtt-rss corridor: the tags are 3.2-4.6 m to one
    side of the four access points' line; 94 % of the 267 unambiguous fixes lie on that
    side, 62 % of the 6 559 ambiguous ones (``auto``, every scan, 2026-12-04).

    Returns
    -------
    tuple of ((anchor indices, side), ...)
        ``side`` is +1 or -1; sets without a significant majority are left out (an empty
        tuple: no preference anywhere).  The :attr:`Locator.log_sides` format.
    """
    from scipy.special import bdtr

    extra = sol.extra
    alt = extra.get("ambiguity_position")
    keep = extra.get("test_kept")
    if alt is None or keep is None or not np.any(np.isfinite(alt[:, 0])):
        return ()  # nothing ambiguous: no side to prefer
    pos = sol.position
    p = pos.shape[1]
    ok = (st.among(sol.status, st.USABLE) & np.all(np.isfinite(pos), axis=1)
          & ~np.isfinite(alt[:, 0]) & (keep.sum(axis=1) > p)
          & np.isfinite(np.asarray(extra.get("hpl", np.full(len(pos), np.nan)))))
    rows = np.flatnonzero(ok)
    if rows.size == 0:
        return ()
    a = range_model.anchors
    amb_rows = np.flatnonzero(np.isfinite(alt[:, 0]))
    sets = [pattern for pattern in _unique_rows(keep[amb_rows])[0]]
    every = np.all(np.isfinite(a), axis=1)
    if every.sum() > p and elongation_rows(a, every[None, :])[0] < AMBIGUITY_ELONGATION:
        sets.append(every)  # the whole layout is one line (plane): a corridor
    sets = list({tuple(m): m for m in sets}.values())  # each set once
    x, kx = pos[rows], keep[rows]
    m = a.shape[0]
    bits = np.int64(1) << np.arange(m, dtype=np.int64) if m <= 62 else None
    kkey = kx.astype(np.int64) @ bits if bits is not None else None
    out = []
    for anchor_set in sets:
        c, u = _side_frame(a, anchor_set)
        # evidence: the fixes that kept none but these anchors
        if kkey is not None:
            inside = (kkey & ~np.int64(anchor_set.astype(np.int64) @ bits)) == 0
        else:
            inside = ~np.any(kx & ~anchor_set, axis=1)
        side = np.sign((x[inside] - c) @ u)
        n_pos, n_neg = int(np.sum(side > 0)), int(np.sum(side < 0))
        n = n_pos + n_neg
        if n and 2.0 * bdtr(min(n_pos, n_neg), n, 0.5) < alpha:
            out.append((tuple(int(i) for i in np.flatnonzero(anchor_set)),
                        1 if n_pos > n_neg else -1))
    return tuple(sorted(out))


def resolve_sides(sol: Solution, sides: tuple[tuple[tuple[int, ...], int], ...],
                  range_model: RangeModel) -> Solution:
    """Move each ambiguous fix to the side of its anchors' line the log prefers.

    A usable fix of ``sol`` with an alternative that passed its test
    (``extra["ambiguity_position"]``, :func:`protect`) whose kept anchors have a side in
    ``sides`` (:func:`ambiguity_sides`), lying on the other side while the alternative lies
    on that one, becomes the alternative: position, ``range_residuals``, ``jacobian``,
    ``test_statistic`` and the bounds are the alternative's, ``hpl = max(HPL(x'),
    |x - x'|_horizontal + HPL(x))`` (``vpl`` likewise), so the bound still covers both;
    the covariance is reflected across the anchors' line (plane), ``H C H`` with ``H = I -
    2 u u^T`` (exact for collinear anchors), and ``sigma0`` is scaled by ``sqrt(T' / T)``.
    The status stays (both passed the same test); ``residuals`` and ``weights`` stay the
    estimator's at the original fix; ``test_kept`` and ``flagged`` become the
    alternative's (``extra["ambiguity_kept"]``: after a wrong exclusion, another
    observation is the one left out).  ``extra["side_from_log"]`` marks the moved fixes.
    """
    extra = sol.extra
    alt = extra.get("ambiguity_position")
    N = sol.position.shape[0]
    moved = np.zeros(N, dtype=bool)
    if not sides or alt is None:
        return replace(sol, extra={**extra, "side_from_log": moved})
    pos = sol.position
    p = pos.shape[1]
    rows = np.flatnonzero(np.isfinite(alt[:, 0]) & st.among(sol.status, st.USABLE))
    if rows.size == 0:
        return replace(sol, extra={**extra, "side_from_log": moved})
    a = range_model.anchors
    m = a.shape[0]
    known = []  # (size, mask, side): the most specific set first
    rank = canonical_rank(a)
    for idx, side in sides:
        if not idx or max(idx) >= m:  # (sides of another layout: not these anchors')
            continue
        mask = np.zeros(m, dtype=bool)
        mask[list(idx)] = True
        known.append((len(idx), mask, side))
    # of sets of one size, the first in the layout's own order (canonical_rank), not the
    # anchors file's: the same anchors listed in another order move the same fixes
    known.sort(key=lambda k: (k[0], sorted(rank[k[1]].tolist())))
    patterns, inverse = _unique_rows(extra["test_kept"][rows])
    swap = np.zeros(rows.size, dtype=bool)
    H = np.zeros((rows.size, p, p))
    for j, pattern in enumerate(patterns):
        match = next(((mask, side) for _, mask, side in known
                      if not np.any(pattern & ~mask)), None)
        if match is None:
            continue
        mask, side = match
        sel = inverse == j
        c, u = _side_frame(a, mask)
        # of the fix and its mirror, the one on the log's side of this line
        swap[sel] = ((np.sign((pos[rows[sel]] - c) @ u) != side)
                     & (np.sign((alt[rows[sel]] - c) @ u) == side))
        # the covariance reflects across the mirror's own line (the kept anchors')
        u_fix = _side_frame(a, pattern)[1]
        H[sel] = np.eye(p) - 2.0 * np.outer(u_fix, u_fix)
    r, H = rows[swap], H[swap]
    if r.size == 0:
        return replace(sol, extra={**extra, "side_from_log": moved})
    moved[r] = True
    x, xa = pos[r], alt[r]
    new_pos = pos.copy()
    new_pos[r] = xa
    new_alt = alt.copy()
    new_alt[r] = x
    terms = extra["ambiguity_terms"].copy()
    h_fix, v_fix, h_alt, v_alt, T_alt = terms[r].T
    T_fix = np.asarray(extra["test_statistic"], dtype=float)[r]
    terms[r] = np.column_stack((h_alt, v_alt, h_fix, v_fix, T_fix))
    d = xa - x
    hpl = np.array(extra["hpl"], dtype=float)
    hpl[r] = np.fmax(h_alt, np.hypot(d[:, 0], d[:, 1]) + h_fix)
    vpl = np.array(extra["vpl"], dtype=float)
    if p == 3:
        vpl[r] = np.fmax(v_alt, np.abs(d[:, 2]) + v_fix)
    # the alternative's ranges and design: the observed ranges d = f(x) - v are the same
    v = np.array(extra["range_residuals"], dtype=float)
    J = np.array(extra["jacobian"], dtype=float)
    f_x = range_model.predict(x)
    f_a, J_a = range_model.predict_jacobian(xa)
    heard = np.isfinite(v[r])
    v[r] = np.where(heard, f_a - (f_x - v[r]), np.nan)
    J[r] = np.where(heard[..., None], J_a, np.nan)
    T = np.array(extra["test_statistic"], dtype=float)
    T[r] = T_alt
    swapped = {}
    if "ambiguity_kept" in extra:  # the alternative's test may keep other observations
        kept = np.array(extra["test_kept"], dtype=bool)
        alt_kept = np.array(extra["ambiguity_kept"], dtype=bool)
        kept[r], alt_kept[r] = alt_kept[r], kept[r].copy()
        flagged = np.array(extra["flagged"], dtype=bool)
        flagged[r] = heard & ~kept[r]
        swapped = {"test_kept": kept, "ambiguity_kept": alt_kept, "flagged": flagged}
    sigma0 = np.array(sol.sigma0, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        sigma0[r] *= np.sqrt(np.where(T_fix > 0, T_alt / T_fix, np.nan))
    cov = np.array(sol.covariance, dtype=float)
    cov[r] = H @ cov[r] @ H
    new_extra = {**extra, "ambiguity_position": new_alt, "ambiguity_terms": terms,
                 "hpl": hpl, "vpl": vpl, "range_residuals": v, "jacobian": J,
                 "test_statistic": T, "side_from_log": moved, **swapped}
    return replace(sol, position=new_pos, covariance=cov, sigma0=sigma0, extra=new_extra)


def _test_alpha(crit: Array, dof: NDArray[np.int64]) -> Array:
    """``chi2.sf(crit, max(dof, 1))`` per epoch, evaluated once per distinct pair (a log
    has a handful: ``crit`` is the B-method's value for each ``dof``)."""
    # NaN and inf coded as -1 and -2 (a critical value is never negative) so they merge
    code = np.nan_to_num(crit, nan=-1.0, posinf=-2.0, neginf=-1.0)
    # one complex key per pair, factorized by hashing (np.unique's sort: 4x slower at
    # 100 000 epochs; over rows, ~40x)
    import pandas as pd

    inverse, uniq = pd.factorize(code + 1j * dof.astype(float), sort=True)
    c = np.select([uniq.real == -1.0, uniq.real == -2.0], [np.nan, np.inf], uniq.real)
    vals = chi2_sf(c, np.maximum(uniq.imag, 1))
    return vals[np.asarray(inverse).reshape(-1)]


def _rows_compiled(kernel, arrays: tuple, out_shape: tuple[int, ...], *extra) -> Array:
    """``kernel(*arrays, *extra)`` of a row-wise compiled kernel (each epoch on its own,
    one output array), over spans of epochs in threads
    (:func:`robustloc.estimators._compiled.in_threads`): masks as bool, the rest as
    contiguous float64."""
    from robustloc.estimators._compiled import in_threads

    args = tuple(np.ascontiguousarray(a, dtype=np.bool_ if np.asarray(a).dtype == bool
                                      else np.float64) for a in arrays)
    out = np.empty(out_shape)

    def run(lo: int, hi: int) -> None:
        out[lo:hi] = kernel(*(a[lo:hi] for a in args), *extra)

    in_threads(run, out_shape[0])
    return out


def robust_fit_cofactors(J: Array, sig: Array, used: NDArray[np.bool_], weight_factor: Array,
                         qv: Array, engine: str = "compiled") -> Array:
    """The variances ``Q_vv,ii`` of a robust fit's residuals under its own weights: the
    w-test's denominators (:func:`protect`).

    The fit weighted the used observations by ``p_i / sigma_i^2`` (``p_i`` its weight
    factor in [0, 1]); their own cofactors are ``sigma_i^2``.  Seed 003's ``Q_vv`` for
    equivalent weights (:func:`~robustloc.estimators.linear.sandwich_qvv`) gives a
    down-weighted row up to ``sigma_i^2 (1 + h_i)``, where the a-priori least-squares
    fit's ``sigma_i^2 r_i`` says ``sigma_i^2 (1 - h_i)``.

    Parameters
    ----------
    J : ndarray (N, n, p)
        Design at the fix (finite where ``used``).
    sig : ndarray (N, n)
        A-priori standard deviations (m; finite and positive where ``used``).
    used : ndarray of bool (N, n)
        The observations of the fix.
    weight_factor : ndarray (N, n)
        The fit's ``p_i`` (NaN counts as 0; clipped to [0, 1]).
    qv : ndarray (N, n)
        The a-priori ``sigma_i^2 r_i`` (NaN: untestable), kept where every used row has
        ``p = 1`` (the same value), ``J^T W J`` is singular or ill-conditioned
        (:func:`~robustloc.estimators._kernels.inv_spd`), ``qv`` is NaN, or the robust
        variance is within ``R_MIN sigma_i^2`` of zero.
    engine : {"compiled", "numpy"}
        The numba kernel (:func:`robustloc.integrity._compiled.robust_cofactors_kernel`,
        default, ``p <= 3``) or this NumPy reference; equal to rounding (tested).

    Returns
    -------
    ndarray (N, n)
    """
    if engine not in ("compiled", "numpy"):
        raise ValueError(f"engine must be 'compiled' or 'numpy', got {engine!r}")
    J = _design(J)
    p = J.shape[2]
    sig, used, weight_factor, qv = _per_observation(
        J.shape[:2], sig=sig, used=used, weight_factor=weight_factor, qv=qv)
    if engine == "compiled" and J.shape[0] and 1 <= p <= 3:
        from robustloc.integrity._compiled import robust_cofactors_kernel

        return _rows_compiled(robust_cofactors_kernel, (J, sig, used, weight_factor, qv),
                              used.shape, float(R_MIN), (0.0,) * p)
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(used, np.clip(np.nan_to_num(weight_factor), 0.0, 1.0), 0.0)
        w0 = np.where(used, 1.0 / (sig * sig), 0.0)
        Jz = np.where(used[..., None], np.nan_to_num(J), 0.0)
        qs = sandwich_qvv(Jz, w0, f * w0, qv)
        full = np.all(~used | (f == 1.0), axis=1)
        return np.where(used & ~full[:, None] & np.isfinite(qv) & np.isfinite(qs)
                        & (qs > R_MIN * sig * sig), qs, qv)


def _reduced_normals(J: Array, sig: Array, keep: NDArray[np.bool_],
                     v: Array) -> tuple[Array, NDArray[np.bool_], Array]:
    """``N^-1``, whether ``N`` is well conditioned, and ``b`` of the least-squares step
    over the rows ``keep``: ``N = J^T P J``, ``b = J^T P v``, ``P = 1 / sig^2``."""
    with np.errstate(invalid="ignore", divide="ignore"):
        P = np.where(keep, 1.0 / (sig * sig), 0.0)
        Jz = np.where(keep[..., None], np.nan_to_num(J), 0.0)
        vz = np.where(keep, np.nan_to_num(v), 0.0)
        Nm = np.einsum("kip,ki,kiq->kpq", Jz, P, Jz)
        b = np.einsum("kip,ki,ki->kp", Jz, P, vz)
    Ninv, good = inv_spd(Nm)
    return Ninv, good, b


def resolution_reduction(J: Array, sig: Array, keep: NDArray[np.bool_], v: Array,
                         engine: str = "compiled") -> Array:
    """What the least-squares re-solution of the rows ``keep`` from the fix takes off
    ``T = sum v_i^2 / sigma_i^2``: ``b^T N^-1 b`` with ``N = J^T P J`` and
    ``b = J^T P v`` over those rows (one linearized Gauss-Newton step; seed 003's global
    test after the exclusion).  Zero at a least-squares fix of those rows.

    Parameters
    ----------
    J : ndarray (N, n, p)
        Design at the fix (finite where ``keep``).
    sig : ndarray (N, n)
        A-priori standard deviations (m; finite and positive where ``keep``).
    keep : ndarray of bool (N, n)
    v : ndarray (N, n)
        Residuals at the fix (m; finite where ``keep``).
    engine : {"compiled", "numpy"}
        The numba kernel (:func:`robustloc.integrity._compiled.resolution_reduction_kernel`,
        default, ``p <= 3``) or this NumPy reference; equal to rounding (tested).

    Returns
    -------
    ndarray (N,)
        NaN where ``N`` is singular or ill-conditioned
        (:func:`robustloc.estimators._kernels.inv_spd`).
    """
    if engine not in ("compiled", "numpy"):
        raise ValueError(f"engine must be 'compiled' or 'numpy', got {engine!r}")
    J = _design(J)
    p = J.shape[2]
    sig, keep, v = _per_observation(J.shape[:2], sig=sig, keep=keep, v=v)
    if engine == "compiled" and J.shape[0] and 1 <= p <= 3:
        from robustloc.integrity._compiled import resolution_reduction_kernel

        return _rows_compiled(resolution_reduction_kernel, (J, sig, keep, v),
                              keep.shape[:1], (0.0,) * p)
    Ninv, good, b = _reduced_normals(J, sig, keep, v)
    red = np.einsum("kp,kpq,kq->k", b, Ninv, b)
    return np.where(good, red, np.nan)


def resolution_step(J: Array, sig: Array, keep: NDArray[np.bool_], v: Array) -> Array:
    """The least-squares re-solution of the rows ``keep`` from the fix, one linearized
    Gauss-Newton step: ``dx = -N^-1 b`` with ``N = J^T P J``, ``b = J^T P v`` (``v`` the
    residuals ``predicted - observed`` at the fix); the re-solution's residuals are
    ``v + J dx``.  Zero at a least-squares fix of those rows (the step whose
    :func:`resolution_reduction` is ``b^T N^-1 b``).

    Returns
    -------
    ndarray (N, p)
        NaN where ``N`` is singular or ill-conditioned.
    """
    Ninv, good, b = _reduced_normals(J, sig, keep, v)
    dx = -np.einsum("kpq,kq->kp", Ninv, b)
    return np.where(good[:, None], dx, np.nan)


#: Most Gauss-Newton iterations of :func:`least_squares_resolution`.
LS_RESOLUTION_ITERATIONS = 20
#: :func:`least_squares_resolution` stops an epoch's iterations at a step below this (m).
LS_RESOLUTION_TOL = 1e-9
#: Halvings of a :func:`least_squares_resolution` step that does not lower the cost.
LS_RESOLUTION_HALVINGS = 20


def least_squares_resolution(
    range_model: RangeModel, position: Array, residuals: Array, sigma: Array,
    keep: NDArray[np.bool_], iterations: int = LS_RESOLUTION_ITERATIONS,
    engine: str = "compiled",
) -> tuple[Array, Array, Array]:
    """The least-squares fix of the rows ``keep``, Newton's method from ``position``.

    The observed ranges are recovered from the fix and its residuals ``v = f(x) - d``
    (as :func:`mirror_solution` does); each step is Newton's on the weighted sum of
    squares (weights ``1 / sigma^2``; Gauss-Newton's where Newton's matrix is not
    positive definite), at most the anchors' extent long (a trust region) and
    halved while it does not lower the weighted sum of squares, until a step is below
    :data:`LS_RESOLUTION_TOL` or after ``iterations``.  An epoch without
    redundancy over ``keep`` or with a singular normal matrix keeps its start.

    ``engine="compiled"`` (default, ``p <= 3``) runs each epoch in the numba kernel
    :func:`robustloc.integrity._compiled.least_squares_resolution_kernel`; ``"numpy"``
    is this function's batched reference.  They take the same steps (tested).

    Returns
    -------
    x_ls : ndarray (N, p)
        The re-solution (NaN where ``position`` is).
    v_ls : ndarray (N, m)
        Residuals ``f(x_ls) - d`` of every observation (NaN: not heard).
    J_ls : ndarray (N, m, p)
        The design ``d f / d x`` at ``x_ls``.
    """
    if engine not in ("compiled", "numpy"):
        raise ValueError(f"engine must be 'compiled' or 'numpy', got {engine!r}")
    x0, residuals, (sigma, keep) = _fix_rows(range_model, position, residuals, sigma=sigma,
                                             keep=keep)
    p = x0.shape[1]
    a = range_model.anchors
    extent = max(float(np.max(np.linalg.norm(a - a.mean(axis=0), axis=1))), 1.0)
    if engine == "compiled" and x0.shape[0] and 1 <= p <= 3:
        return _resolution_compiled(range_model, x0, residuals, sigma, keep, iterations,
                                    extent)
    fin = np.all(np.isfinite(x0), axis=1)
    x = np.where(fin[:, None], x0, 0.0)
    d = range_model.predict(x) - residuals  # observed ranges (NaN: not heard)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.where(keep & np.isfinite(d) & (sigma > 0), 1.0 / sigma, 0.0)
    w = np.nan_to_num(w, nan=0.0, posinf=0.0)
    ok = fin & ((w > 0).sum(axis=1) > p)

    def cost(rows: NDArray[np.int64], xr: Array) -> Array:
        r = np.where(w[rows] > 0, (d[rows] - range_model.predict(xr)) * w[rows], 0.0)
        return np.sum(np.nan_to_num(r) ** 2, axis=1)

    act = np.flatnonzero(ok)  # the epochs still moving
    for _ in range(iterations):
        if act.size == 0:
            break
        f, Jm = range_model.predict_jacobian(x[act])
        wa = w[act]
        A = np.where(wa[..., None] > 0, Jm * wa[..., None], 0.0)
        r = np.where(wa > 0, np.nan_to_num(d[act] - f) * wa, 0.0)
        Ngn = np.einsum("kmi,kmj->kij", A, A)
        # Newton's matrix: Gauss-Newton's minus the ranges' curvature, sum_i w_i^2 r_i
        # (I - u_i u_i^T) / rho_i with u_i = d rho_i / d x (Nocedal & Wright, "Numerical
        # Optimization", eq. 10.5).  Plain Gauss-Newton converged only linearly, next to
        # an anchor at rate 0.999 (a 3-D case took 1 000 steps); Newton's is used where
        # it is positive definite, Gauss-Newton's elsewhere
        rho = np.maximum(np.nan_to_num(f, nan=1.0), 1e-9)
        c = np.where(wa > 0, r * wa / rho, 0.0)  # w^2 r / rho (r already carries one w)
        curv = (np.sum(c, axis=1)[:, None, None] * np.eye(p)
                - np.einsum("kmi,kmj->kij", Jm * c[..., None], Jm))
        Nn_inv, newton = inv_spd(Ngn - curv)
        Ngn_inv, good = inv_spd(Ngn)
        Ninv = np.where(newton[:, None, None], Nn_inv, Ngn_inv)
        good = good | newton
        # (in two products: the three-operand einsum took half of protect's time)
        step = np.einsum("kij,kj->ki", Ninv, np.einsum("kmj,km->kj", A, r))
        ln = np.linalg.norm(step, axis=1)
        step *= np.minimum(1.0, extent / np.maximum(ln, 1e-300))[:, None]
        step = np.where(good[:, None], step, 0.0)
        # halved while it does not lower the cost: next to an anchor a range curves and
        # plain Gauss-Newton stepped back and forth (0.007 m each way, for 50 steps)
        c0 = np.sum(r * r, axis=1)
        rows = np.arange(act.size)
        for _h in range(LS_RESOLUTION_HALVINGS):
            worse = cost(act[rows], x[act[rows]] + step[rows]) > c0[rows]
            rows = rows[worse]
            if rows.size == 0:
                break
            step[rows] *= 0.5
        x[act] += step
        ln = np.linalg.norm(step, axis=1)
        act = act[good & (ln > LS_RESOLUTION_TOL)]
    f, Jm = range_model.predict_jacobian(x)
    x = np.where(fin[:, None], x, np.nan)
    return x, f - d, Jm


def _resolution_compiled(range_model: RangeModel, x0: Array, residuals: Array, sigma: Array,
                         keep: NDArray[np.bool_], iterations: int,
                         extent: float) -> tuple[Array, Array, Array]:
    """:func:`least_squares_resolution` by its numba kernel, spans of epochs in threads."""
    from robustloc.estimators._compiled import in_threads
    from robustloc.integrity._compiled import least_squares_resolution_kernel

    N, p = x0.shape
    a = np.ascontiguousarray(range_model.anchors, dtype=np.float64)
    h = range_model.height_offset
    h2 = np.zeros(len(a)) if h is None else np.ascontiguousarray(h, dtype=np.float64) ** 2
    xc = np.ascontiguousarray(x0, dtype=np.float64)
    rc = np.ascontiguousarray(residuals, dtype=np.float64)
    # (sigma and keep broadcast against the residuals, as in the NumPy reference)
    sc = np.ascontiguousarray(np.broadcast_to(sigma, rc.shape), dtype=np.float64)
    kc = np.ascontiguousarray(np.broadcast_to(keep, rc.shape), dtype=np.bool_)
    m = rc.shape[1]
    out = (np.empty((N, p)), np.empty((N, m)), np.empty((N, m, p)))

    def run(lo: int, hi: int) -> None:
        for o, part in zip(out, least_squares_resolution_kernel(
                a, h2, xc[lo:hi], rc[lo:hi], sc[lo:hi], kc[lo:hi], int(iterations),
                LS_RESOLUTION_HALVINGS, LS_RESOLUTION_TOL, extent, (0.0,) * p), strict=True):
            o[lo:hi] = part

    in_threads(run, N)
    return out


def _global_test(v: Array, sig: Array, keep: NDArray[np.bool_], p: int, alpha0: float,
                 beta0: float, J: Array | None = None,
                 ) -> tuple[Array, Array, NDArray[np.int64]]:
    """``T = sum v_i^2 / sigma_i^2`` over ``keep``, its B-method critical value (NaN without
    redundancy) and the redundancy ``dof``, per epoch.

    With the design ``J`` (N, n, p), ``T`` is that of the least-squares re-solution over
    ``keep`` from the fix (:func:`resolution_reduction`), which equals ``T`` at a
    least-squares fix of those rows."""
    dof = keep.sum(axis=1) - p
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(keep, v / sig, 0.0)
    u = np.where(np.isnan(u), 0.0, u)  # (kept rows are finite; NaN would count as 0)
    u *= u
    # (np.sum, as nansum before: einsum's order differs with an extra unheard anchor's
    # zero column, and a layout with one must give bit-identical fixes and bounds)
    T = u.sum(axis=1)
    if J is not None:
        red = resolution_reduction(J, sig, keep, v)
        T = np.where((dof >= 1) & np.isfinite(red), np.maximum(T - red, 0.0), T)
    crit = np.full(dof.shape, np.nan)
    has = dof >= 1
    if np.any(has):
        crit[has] = global_critical(dof[has], alpha0=alpha0, beta0=beta0)
    return T, crit, dof


def _snoop_one(flagged: NDArray[np.bool_], w: Array, used: NDArray[np.bool_],
               heard: NDArray[np.bool_], excl: NDArray[np.bool_], v: Array, J: Array,
               sig: Array, p: int, alpha0: float, beta0: float, lam0: float, k: float,
               tested: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """The w-test's flags, with Baarda's one-at-a-time rule where flagging every
    ``w > k`` at once would leave no bound (module docstring, item 6).

    One fault spreads over every residual of the fit, so with little redundancy the
    w-tests of good observations exceed the critical value beside the faulty one's.
    Data snooping (seed 003, section 2) flags only the largest ``w`` and tests the fit
    without it.  An epoch whose simultaneous flags are half or more of what it heard, or
    leave no redundancy, keeps only its largest flag when the least-squares re-solution of
    the rest passes the global test (B-method critical value) and keeps a majority: the
    single-fault hypothesis then explains the epoch.  Otherwise the flags stay and item 6
    applies.  Measured on uwb-labyrinth (four anchors, one range 0.5 m long, 7 sigma):
    every ``w`` above 3.29 flagged two of four ranges and the fix was ``unavailable``; the
    rest, three ranges at redundancy 1, fit at ``T = 0.9``.
    """
    n_out = np.sum(heard & (excl | flagged), axis=1)
    dof_rest = np.sum(used & ~flagged, axis=1) - p
    rows = np.flatnonzero(tested & (flagged.sum(axis=1) >= 2)
                          & ((dof_rest < 1) | (2 * n_out >= heard.sum(axis=1))))
    if rows.size == 0:
        return flagged
    wz = np.where(flagged[rows], w[rows], -np.inf)
    one = np.zeros((rows.size, flagged.shape[1]), dtype=bool)
    one[np.arange(rows.size), np.argmax(wz, axis=1)] = True
    rest = used[rows] & ~one
    n_out1 = np.sum(heard[rows] & (excl[rows] | one), axis=1)
    T, crit, dof = _global_test(v[rows], sig[rows], rest, p, alpha0, beta0, J=J[rows])
    hpl, _, _ = protection_levels_local(J[rows], sig[rows], rest, lam0, k)
    with np.errstate(invalid="ignore"):
        single = ((dof >= 1) & (T <= crit) & (2 * n_out1 < heard[rows].sum(axis=1))
                  & np.isfinite(hpl))
    out = flagged.copy()
    out[rows[single]] = one[single]
    return out


def _cover_other_exclusions(
    range_model: RangeModel, position: Array, v: Array, sig: Array,
    heard: NDArray[np.bool_], out: NDArray[np.bool_], rows: NDArray[np.bool_], hpl: Array,
    vpl: Array, widen: Array, alpha0: float, beta0: float, lam0: float, k: float,
) -> None:
    """Widen, in place, the bound of each fix in ``rows`` (``fault_excluded``) over every
    other single exclusion that also passes the test.

    A fix that left the observations ``out`` out is right when they hold the fault.  Had
    another observation ``j`` held it instead, the least-squares fix ``x_j`` of every
    heard observation but ``j`` would be fault-free, and where its global test passes
    the data cannot tell the two hypotheses apart.  Under the hypothesis that ``j`` holds
    the one fault, ``x_j`` is fault-free and its error is within its noise term ``k
    sigma_major(x_j)`` (widened as the fix's; no slope term: the bound assumes one fault,
    as the solution separation of ARAIM does), so ``hpl = max(hpl, |x - x_j|_h + k
    sigma_major(x_j))`` over every such ``j``, on the fixes whose kept observations have
    redundancy 1.  (With the alternative's own slope bound in place of its noise term, an
    alternative kept only by an anchor of useless weight, an RSSI range of 1e200 m, made
    the bound infinite.)  At redundancy 2 (four ranges in 2-D) the
    w-tests of the ranges are strongly correlated, and the largest one often names a
    healthy range: with 2 % of the ranges 1.5-3 m long, 3.1 % of the single-fault
    epochs' fixes lay beyond the bound of their exclusion alone (the locate review of
    2026-12-07); snooping with five ranges, 0.4 %; now none.
    """
    p = position.shape[1]
    idx = np.flatnonzero(rows & np.isfinite(hpl) & np.all(np.isfinite(position), axis=1)
                         & (heard.sum(axis=1) - p >= 2))  # an alternative keeps dof >= 1
    if idx.size == 0:
        return
    # only where the rest has redundancy 1: its test then detects a fault left in it but
    # cannot say which, and the exclusion's choice among strongly correlated w-tests is
    # the weak link.  With redundancy 2 or more left, covering every alternative changed
    # no bound that mattered (simulated rooms of four and five anchors, one range in 30-50
    # faulty: the same single-fault epochs beyond their bound with and without), and on
    # bench_locate's 10 ranges with 20 % gross errors it cost 3x the default's time
    idx = idx[(heard[idx] & ~out[idx]).sum(axis=1) - p <= 1]
    ee, alt = _one_out(heard & ~out, idx, heard)
    if ee.size == 0:
        return
    x_a, v_a, J_a = least_squares_resolution(range_model, position[ee], v[ee], sig[ee], alt)
    T_a, crit_a, dof_a = _global_test(v_a, sig[ee], alt, p, alpha0, beta0)
    ok = (dof_a >= 1) & (T_a <= crit_a) & np.all(np.isfinite(x_a), axis=1)
    if not np.any(ok):
        return
    ee, alt, x_a, J_a = ee[ok], alt[ok], x_a[ok], J_a[ok]
    # under the hypothesis that ``j`` holds the one fault, ``x_j`` is fault-free: its
    # error is bounded by its noise term alone (no slope term: no other fault to miss)
    _cover_fault_free(position, ee, x_a, J_a, sig[ee], alt, widen, k, hpl, vpl)


def _one_out(mask: NDArray[np.bool_], rows: NDArray[np.intp],
             base: NDArray[np.bool_] | None = None
             ) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Every single exclusion of one of ``mask``'s observations on the epochs ``rows``:
    the epoch of each (repeated once per observation) and ``base`` (default ``mask``)
    without that observation."""
    ee, jj = np.nonzero(mask[rows])
    ee = rows[ee]
    alt = (mask if base is None else base)[ee].copy()
    alt[np.arange(ee.size), jj] = False
    return ee, alt

def _cover_fault_free(
    position: Array, ee: NDArray[np.intp], x_a: Array, J_a: Array, sig: Array,
    alt: NDArray[np.bool_], widen: Array, k: float, hpl: Array, vpl: Array,
) -> None:
    """Widen, in place, the bounds of the fixes ``ee`` (with repeats) to cover the
    fault-free alternatives ``x_a`` (the least-squares fixes of observations ``alt``,
    design ``J_a``, sigma ``sig``): ``hpl = max(hpl, |x_a - x|_h + k sigma_major(x_a))``
    and ``vpl = max(vpl, |z_a - z| + k sigma_z(x_a))``, the noise terms widened as the
    fix's (``widen``); infinite where the alternative's normal matrix is singular."""
    p = position.shape[1]
    use, A = _whitened(J_a, sig, alt)
    Nm = np.matmul(np.swapaxes(A, 1, 2), A)
    C, good = inv_spd(Nm)
    cen = C[:, _H, _H]
    tr, det = cen[:, 0, 0] + cen[:, 1, 1], cen[:, 0, 0] * cen[:, 1, 1] - cen[:, 0, 1] ** 2
    noise_h = k * np.sqrt(0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0)))
    d = x_a - position[ee]
    cover = np.where(good, np.hypot(d[:, 0], d[:, 1]) + noise_h * widen[ee], np.inf)
    np.fmax.at(hpl, ee, np.where(np.isfinite(cover), cover, np.inf))
    if p == 3:
        cover_v = np.where(good, np.abs(d[:, 2]) + k * np.sqrt(C[:, 2, 2]) * widen[ee],
                           np.inf)
        np.fmax.at(vpl, ee, np.where(np.isfinite(cover_v), cover_v, np.inf))


def _cover_mirror_exclusions(
    range_model: RangeModel, position: Array, v: Array, sc: Array,
    keep: NDArray[np.bool_], rows: NDArray[np.intp], hpl: Array, vpl: Array, widen: Array,
    alpha0: float, beta0: float, k: float,
) -> None:
    """Widen, in place, the bound of each fix in ``rows`` (elongated kept anchors, a
    mirror that fails its test) over the mirror solutions with one observation left out.

    The slope bound assumes at most one fault; so must the ambiguity check (module
    docstring, item 5).  Where the mirror ``x'`` fails the test on every kept observation,
    one fault on observation ``j`` may be what makes it fail: the mirror ``x'_j`` refined
    on the kept observations but ``j`` (:func:`mirror_solution`, its own principal line)
    is then fault-free, and where its global test passes (redundancy at least 1) the data
    cannot tell the fix from the tag across the line with ``j`` faulty.  As for the other
    exclusions (:func:`_cover_other_exclusions`, the solution separation of ARAIM), the
    hypothesis bounds ``x'_j``'s error by its noise term alone: ``hpl = max(hpl, |x'_j -
    x|_h + k sigma_major(x'_j))`` over every such ``j`` (widened as the fix's).  Only the
    bound moves: the log's side prior (item 7) moves a fix to an alternative that fits
    without a fault, not to one that needs one.  Measured on the wifi-rtt-rss corridor
    after ``calibrate --self`` (every scan, 2026-12-07): of its 75 usable fixes beyond
    their bound, all ``ok`` and across the access points' line from the truth, an access
    point reading 4-8 m long made the mirror fail while the wrong side fitted.
    """
    p = position.shape[1]
    rows = rows[keep[rows].sum(axis=1) - p >= 2]  # x'_j keeps redundancy >= 1
    ee, alt = _one_out(keep, rows)
    if ee.size == 0:
        return
    x_a, T_a, J_a = mirror_solution(range_model, position[ee], v[ee], sc[ee], alt)
    dof_a = alt.sum(axis=1) - p
    crit_a = global_critical(dof_a, alpha0=alpha0, beta0=beta0)
    ok = np.isfinite(T_a) & (T_a <= crit_a) & np.all(np.isfinite(x_a), axis=1)
    if not np.any(ok):
        return
    ee, alt, x_a, J_a = ee[ok], alt[ok], x_a[ok], J_a[ok]
    _cover_fault_free(position, ee, x_a, J_a, sc[ee], alt, widen, k, hpl, vpl)


def _real_option(name: str, value: object) -> float:
    """An option's value as a float; ``TypeError`` for what is not a real number (a bool,
    a complex number, whose imaginary part ``float()`` would drop)."""
    if isinstance(value, bool | complex | np.bool_ | np.complexfloating) or not isinstance(
            value, int | float | np.integer | np.floating):
        raise TypeError(f"{name} must be a real number, got {value!r}")
    return float(value)


def _check_protection_options(k_noise: float | None, alert_limit: float | None) -> None:
    """``k_noise`` finite and >= 0, ``alert_limit`` > 0 (as ``robustloc.locate`` checks
    them): a negative ``k_noise`` halved the bounds of `ok` fixes, a NaN one made them
    infinite, an ``alert_limit`` of -1 or NaN refused every fix (the API review)."""
    if k_noise is not None:
        k = _real_option("k_noise", k_noise)
        if not (np.isfinite(k) and k >= 0):
            raise ValueError(f"k_noise must be finite and >= 0, got {k_noise!r}")
    if alert_limit is not None:
        a = _real_option("alert_limit", alert_limit)
        if not a > 0:
            raise ValueError(f"alert_limit must be > 0 (m), got {alert_limit!r}")


def protect(
    sol: Solution,
    *,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
    k_noise: float | None = None,
    alert_limit: float | None = None,
    fallback_rows: NDArray[np.bool_] | None = None,
    range_model: RangeModel | None = None,
    snoop: bool = True,
) -> Solution:
    """Test every fix and attach its protection levels (see the module docstring).

    Parameters
    ----------
    sol : Solution
        From :meth:`Locator.solve`, whose ``extra`` holds ``range_residuals``,
        ``jacobian`` and, when known, ``sigma_obs``.  Without it the epoch's own scale
        stands in: the fit's ``sigma0`` for the tests; for the bound, the larger of it
        and the least-squares scale of every heard range (with ``range_model``), times
        ``t(Phi(k), r) / k``, Student's t for the redundancy ``r`` it was estimated
        with (a bound about 2.6 times wider at redundancy 4: the scale is not known).
    alpha0, beta0 : float
        Significance of the w-test and missed-detection probability of the B-method.
    k_noise : float, optional
        Multiplier of the fault-free noise; default ``N(1 - alpha0/2)``.
    alert_limit : float, optional
        Usable fixes with ``hpl`` above it get ``protection_exceeded`` (metres).
    fallback_rows : ndarray of bool (N,), optional
        Epochs a robust method solved by the plain fit (low redundancy): a passing test
        gives ``low_redundancy`` instead of ``ok``.  Default: ``sol.extra["fallback"]``.
    range_model : RangeModel, optional
        The anchors (and known height offsets) of the solution, in its anchor order: with
        it the bound covers the mirror solution when that passes the fix's test (module
        docstring, item 5); without it no ambiguity is checked.  A fix of the linearized
        difference system (``sol.extra["solver"] == "linearized"``) is tested on the
        least-squares re-solution of its ranges: with the anchors by Gauss-Newton
        (:func:`least_squares_resolution`), without them by one linearized step from the
        fix (:func:`resolution_step`), which identified one 15 m range in six in 82-98 %
        of the epochs where the Gauss-Newton re-solution found it in all.

    Returns
    -------
    Solution
        A copy with updated ``status`` and ``position`` (NaN where no longer usable) and
        ``extra["hpl"]``, ``extra["vpl"]``, ``extra["test_statistic"]``,
        ``extra["test_critical"]``, ``extra["flagged"]`` and, with ``range_model``,
        ``extra["ambiguity_distance"]`` (metres from the fix to an alternative solution
        that passes its test; NaN where none does), ``extra["ambiguity_position"]`` (that
        alternative), ``extra["ambiguity_terms"]`` (N, 5: the fix's own hpl and vpl, the
        alternative's, and its test statistic), ``extra["test_kept"]`` (the
        observations the test kept) and ``extra["ambiguity_kept"]`` (those the
        alternative's test keeps), which :func:`resolve_sides` uses.
    snoop : bool
        Flag the w-test's observations one at a time where flagging them all at once
        leaves a robust fit no majority (module docstring, item 6; :func:`_snoop_one`).
        False: every ``w`` above the critical value is flagged, as before 2026-12-06
        (the self-calibration's starts, which want no fix rescued at redundancy 1).

        The alternative is the mirror refined on the kept observations; where that fails
        and the test had left observations out, the mirror refined on every heard
        observation with one exclusion of its own by the w-test (a wrong exclusion: a
        robust fit can reach the far side of nearly collinear anchors by rejecting the
        one anchor off their line that tells the sides apart; on the corridor of
        ``test_ambiguous_fixes_move_to_the_side_the_log_shows`` such a fix was 6.2 m off
        with hpl 4.8 m).
    """
    _check_protection_options(k_noise, alert_limit)
    for key in ("range_residuals", "jacobian"):
        if key not in sol.extra:
            raise ValueError(f"the solution has no {key!r}: solve it with Locator.solve")
    v = sol.extra["range_residuals"]
    J = sol.extra["jacobian"]
    N, n, p = J.shape
    sig = sol.extra.get("sigma_obs")
    per_epoch = sig is None
    if per_epoch:  # no a-priori scale: the fit's own sigma0 (NaN at zero redundancy)
        sig = np.broadcast_to(sol.sigma0[:, None], (N, n))
    sig = np.where(np.isfinite(sig) & (sig > 0), sig, np.nan)
    k = w_critical(alpha0) if k_noise is None else float(k_noise)
    lam0 = lambda0(alpha0, beta0)
    status = np.array(sol.status, dtype=object)
    testable = st.among(status, (st.OK, st.FAULT_EXCLUDED))
    # a fix the iterations left before convergence is usable: it is tested like the rest
    # (a failed test or a minority kept overrides its status), and keeps its label when
    # the test passes
    unconv = status == st.NOT_CONVERGED
    heard = np.isfinite(v) & np.isfinite(sig)
    for q in range(p):  # (np.all over the short last axis is ~10x slower)
        heard &= np.isfinite(J[..., q])
    excl = sol.excluded if sol.excluded.shape == (N, n) else np.zeros((N, n), dtype=bool)
    used = heard & ~excl
    # a fix of the paper's linearized difference system (seed 000 eq. (3)) is not a
    # least-squares fix of the ranges: its range residuals exceed those of one, and
    # tested as such they failed 3.4 % (ls) to 40 % (igg) of fault-free Gaussian epochs
    # where the B-method means 1.1 %.  The tests take the residuals of the least-squares
    # re-solution of every heard row, Gauss-Newton from the fix with the anchors
    # (one linearized step without them; seed 003's tests are those of the least-squares
    # adjustment), and its design; the bound adds the fix's distance from that
    # re-solution (step 4: |x - x_hat| <= |x - x_ls| + |x_ls - x_hat|)
    linearized = sol.extra.get("solver") == "linearized"
    vt, Jt, x_ls = v, J, None
    if linearized:
        # every heard row: the bound holds whichever rows the fix used, and the rows that
        # a redescending fit of the difference system rejected are often the good ones
        # (igg, one range in five grossly long: 1.7 % of its fixes misleading when tested
        # on the rows it kept, 0.35 % on every row)
        used = heard.copy()
        if range_model is not None:
            x_ls, vt, Jt = least_squares_resolution(range_model, sol.position, v, sig, used)
            vt = np.where(heard, vt, np.nan)
            Jt = np.where(heard[..., None], Jt, np.nan)
        else:
            with np.errstate(invalid="ignore"):
                dx_used = resolution_step(J, sig, used, v)
                vt = v + np.einsum("kip,kp->ki", J, np.nan_to_num(dx_used))
    # 1. w-test on the observations the estimator kept (a linearized fix: every one)
    hpl_used, vpl_used, r = protection_levels_local(Jt, sig, used, lam0, k)
    # a plain fit whose weights are not the tests' a-priori ones (Gauss-Newton with equal
    # weights, nls / lege / snooping, tested with the log's per-anchor scale): its bound
    # is that of the fix it gave, with the sandwich covariance (the locate review of
    # 2026-12-07: one anchor of sd 1 m among five of 0.1 m, 7.7 % of `ok` fixes beyond the
    # bound of the weighted fix)
    fw_fit = sol.extra.get("fit_weight_factor")
    fw_fit = (np.asarray(fw_fit, dtype=float)
              if fw_fit is not None and np.shape(fw_fit) == (N, n) and not linearized
              else None)
    if fw_fit is not None:
        hpl_used, vpl_used, _ = protection_levels_local(Jt, sig, used, lam0, k,
                                                        fit_weight=fw_fit)
    plain = sol.method in PLAIN_FIT_METHODS or fw_fit is not None
    with np.errstate(invalid="ignore", divide="ignore"):
        qv = sig * sig * np.where(r > R_MIN, r, np.nan)  # Q_vv,ii of the a-priori fit
    pw = sol.extra.get("weight_factor")
    # (a plain fit gives weight factors when its weights are not the tests' a-priori
    # ones: Gauss-Newton with equal weights tested with the log's per-anchor scale)
    robust_fit = pw is not None and np.shape(pw) == (N, n)
    if robust_fit:
        # a robust fit's residual is not that of the a-priori weighted adjustment: a row
        # it down-weighted keeps most of its error (variance up to sigma^2 (1 + h), not
        # sigma^2 (1 - h)).  Each is tested against its own variance under the fit's
        # weights (seed 003's Q_vv for equivalent weights, sandwich_qvv): with the
        # a-priori one the w-test flagged 3.6x (huber) to 18x (igg3) alpha0 of Gaussian
        # rows, and 2.2-10 % of fault-free fixes said fault_excluded (integrity review D1)
        qv = robust_fit_cofactors(J, sig, used, np.asarray(pw, dtype=float), qv)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = np.abs(vt) / np.sqrt(qv)
    flagged = used & (w > w_critical(alpha0))
    if linearized:
        # the least-squares re-solution spreads one fault over the rows: the largest w-test
        # alone is flagged (the first step of Baarda's data snooping, seed 003).  With
        # every w above the critical value flagged, one gross error in six ranges flagged
        # three and the minority rule left 70 % of such epochs unavailable; snooping on
        # (re-solve, flag the next largest) made 3 % of the usable fixes misleading on 20 %
        # gross errors, against 0.3 % for one flag (huber)
        wz = np.where(flagged, w, -np.inf)
        flagged &= wz >= wz.max(axis=1, keepdims=True)
    elif snoop and not plain:
        flagged = _snoop_one(flagged, w, used, heard, excl, vt, Jt, sig, p, alpha0, beta0,
                             lam0, k, testable | unconv)
    # a plain fit (ls, wls, nls) keeps a flagged observation at its full weight: the fix
    # carries the fault, so the test and the bound are those of the fix itself (the
    # statistics review: such fixes said fault_excluded with the fault still in them)
    # (lege below seven anchors is nls, and lege and snooping keep at full weight the
    # rows they did not exclude themselves: their flagged rows are carried too; the locate
    # review: such lege fixes said fault_excluded with the fault in them, 8.4 % beyond
    # their hpl)
    carries = flagged.any(axis=1) & plain
    rest = used & ~flagged
    keep = np.where(carries[:, None], used, rest)
    # 2. global test of the rest (of the whole fix where it carries its flags); of a
    # robust fit, that of the least-squares re-solution over the rows it keeps (seed 003:
    # the test after the exclusion), not of its own residuals, which its down-weighted
    # rows inflate (with the w-test above alone, huber's fault_detected went from 0.29 to
    # 0.72 % of Gaussian epochs where the B-method means 1.1 % for both tests together)
    vk, Jk, xk = vt, Jt, x_ls  # residuals, design and fix of the rows ``keep``
    v_rest, J_rest = vt, Jt  # of the rows ``rest``
    if x_ls is not None:
        # the least-squares fix of the rest, re-solved in full: one linear step from the
        # fix of every row, which a 15 m fault had pulled metres away, left its T
        # inflated by the curvature (39 % of such epochs fault_detected)
        out = np.flatnonzero(np.any(rest != used, axis=1))
        v_rest, J_rest, x_rest = vt.copy(), Jt.copy(), x_ls.copy()
        if out.size:
            xo, vo, Jo = least_squares_resolution(range_model, x_ls[out], vt[out],
                                                  sig[out], rest[out])
            v_rest[out] = np.where(heard[out], vo, np.nan)
            J_rest[out] = np.where(heard[out][..., None], Jo, np.nan)
            x_rest[out] = xo
        # a fix that carries its flags is tested on all its rows
        vk = np.where(carries[:, None], vt, v_rest)
        Jk = np.where(carries[:, None, None], Jt, J_rest)
        xk = np.where(carries[:, None], x_ls, x_rest)
    T, crit, dof = _global_test(vk, sig, keep, p, alpha0, beta0,
                                J=Jk if robust_fit or linearized else None)
    has = dof >= 1
    passed = has & (T <= crit)
    # the flagged observations are all that is wrong with a fix that carries them: the
    # test of the rest passes (``auto`` keeps such a fix, measured best on real logs)
    rest_passes = np.zeros(N, dtype=bool)
    if np.any(carries):
        T_r, crit_r, dof_r = _global_test(v_rest[carries], sig[carries], rest[carries], p,
                                          alpha0, beta0,
                                          J=J_rest[carries] if linearized else None)
        rest_passes[carries] = (dof_r >= 1) & (T_r <= crit_r)
    # 3. status
    new = status.copy()
    any_flag = flagged.any(axis=1) | excl.any(axis=1)
    if fallback_rows is None:
        fallback_rows = sol.extra.get("fallback")
    fb = np.zeros(N, dtype=bool) if fallback_rows is None else np.asarray(fallback_rows, bool)
    failed = (testable | unconv) & has & ~passed
    # item 6: a minority kept (flagged by the estimator or the w-test: half or more)
    n_out = np.sum(heard & (excl | flagged), axis=1)
    dof_rest = np.sum(used & ~flagged, axis=1) - p  # what a removal would leave
    blind = (testable | unconv) & any_flag & ((dof_rest < 1)
                                              | (2 * n_out >= heard.sum(axis=1)))
    failed &= ~blind
    # a fault detected by the w-test and left in the fix by a plain fit: not excluded
    failed |= (testable | unconv) & carries & ~blind
    new[testable & (dof == 0) & ~any_flag] = st.UNVERIFIED
    new[failed] = st.FAULT_DETECTED
    # a flagged observation that leaves nothing to confirm the rest: no bound at all
    new[blind] = st.UNAVAILABLE
    new[testable & passed & any_flag & ~blind & ~carries] = st.FAULT_EXCLUDED
    new[testable & passed & ~any_flag & ((dof == 1) | fb)] = st.LOW_REDUNDANCY
    new[testable & passed & ~any_flag & (dof >= 2) & ~fb] = st.OK
    # no scale to test with (the epoch's own sigma0 is 0: its residuals vanish, as on
    # noise-free ranges with a per-epoch scale): the test said nothing, nothing bounds it
    noscale = testable & ~heard.any(axis=1) & np.isfinite(v).any(axis=1)
    new[noscale] = st.UNVERIFIED
    # 4. protection levels over the observations kept; a failed test scales sigma by the
    # a-posteriori variance factor sqrt(T / dof) (> 1), the classical remedy when the
    # a-priori noise is too optimistic for this epoch
    with np.errstate(invalid="ignore", divide="ignore"):
        factor = np.where(failed, np.fmax(np.sqrt(T / np.maximum(dof, 1)), 1.0), 1.0)
    hpl, vpl = hpl_used * factor, vpl_used * factor  # sigma scales the bound linearly
    again = np.flatnonzero(np.any(keep != used, axis=1))
    if again.size:
        hpl[again], vpl[again], _ = protection_levels_local(
            Jk[again], sig[again] * factor[again, None], keep[again], lam0, k,
            fit_weight=None if fw_fit is None else fw_fit[again])
    # a scale estimated from the epoch's own residuals: Student's t (seed 003's
    # variance-factor test with sigma0 unknown) widens the bound by t(1 - a/2, r) / k,
    # a the two-sided risk of k and r the redundancy the scale was estimated with.  With
    # the normal k alone, 0.4 % (nls) to 17 % (igg3, whose exclusions leave few and the
    # smallest residuals) of fault-free fixes of six ranges exceeded the bound (the
    # review of 2026-12-06), against the documented 0.1 %
    widen = np.ones(N)
    if per_epoch:
        r_scale = used.sum(axis=1) - p
        with np.errstate(invalid="ignore", divide="ignore"):
            widen = np.where(r_scale >= 1,
                             t_ppf(norm_cdf(k), np.maximum(r_scale, 1)) / k, np.inf)
            if range_model is not None and not linearized:
                r_all = heard.sum(axis=1) - p
                _, v_all, _ = least_squares_resolution(range_model, sol.position, v,
                                                       np.ones((N, n)), heard)
                s_all = np.sqrt(np.nansum(np.where(heard, v_all * v_all, 0.0), axis=1)
                                / np.maximum(r_all, 1))
                w_all = s_all / sol.sigma0 * t_ppf(norm_cdf(k), np.maximum(r_all, 1)) / k
                widen = np.fmax(widen, np.where(r_all >= 1, w_all, np.inf))
        hpl, vpl = hpl * widen, vpl * widen
    if linearized:  # the linearized fix's distance from the least-squares one it bounds
        d_ls = resolution_step(J, sig, keep, v) if xk is None else sol.position - xk
        hpl = hpl + np.hypot(d_ls[:, 0], d_ls[:, 1])  # NaN: nothing bounds it (below)
        if p == 3:
            vpl = vpl + np.abs(d_ls[:, 2])
    if range_model is not None and not linearized:
        _cover_other_exclusions(range_model, sol.position, v, sig, heard,
                                heard & (excl | flagged), new == st.FAULT_EXCLUDED, hpl,
                                vpl, widen, alpha0, beta0, lam0, k)
    # the ambiguity check of a plain fix that keeps its flagged observations while the
    # rest passes is that of the rest, as before those fixes said fault_detected: with
    # every observation and the widened sigma the mirror passed far more often, and the
    # corridor excerpt's side prior lost its evidence (348 scans: 122 fixes moved, RMS
    # 3.49 m; then none, 6.28 m)
    kept_rest = carries & rest_passes & ~blind
    keep_a = np.where(kept_rest[:, None], rest, keep)
    factor_a = np.where(kept_rest, 1.0, factor)
    crit_a, has_a = crit.copy(), has.copy()
    if np.any(kept_rest):
        crit_a[carries] = np.where(kept_rest[carries], crit_r, crit[carries])
        has_a |= kept_rest
    amb_dist = np.full(N, np.nan)
    amb_pos = np.full((N, p), np.nan)
    amb_terms = np.full((N, 5), np.nan)  # the fix's own hpl, vpl; the alternative's; T'
    amb_kept = keep_a.copy()  # the observations the alternative's test keeps
    if range_model is not None:
        cand = np.flatnonzero(st.among(new, st.USABLE) & has_a
                              & np.isfinite(hpl) & np.all(np.isfinite(sol.position), axis=1))
        cand = cand[anchor_elongation(range_model.anchors, keep_a[cand]) < AMBIGUITY_ELONGATION]
        if cand.size:
            sc = sig[cand] * factor_a[cand, None]
            x_alt, T_alt, J_alt = mirror_solution(range_model, sol.position[cand], v[cand],
                                                  sc, keep_a[cand])
            amb = np.isfinite(T_alt) & (T_alt <= crit_a[cand])

            def ambiguous(rows, x_a, J_a, s_a, keep_a, T_a) -> None:
                d = x_a - sol.position[rows]
                h_alt, v_alt, _ = protection_levels_local(J_a, s_a, keep_a, lam0, k)
                h_alt, v_alt = h_alt * widen[rows], v_alt * widen[rows]
                dh = np.hypot(d[:, 0], d[:, 1])
                amb_dist[rows] = np.linalg.norm(d, axis=1)
                amb_pos[rows] = x_a
                amb_terms[rows] = np.column_stack((hpl[rows], vpl[rows], h_alt, v_alt, T_a))
                amb_kept[rows] = keep_a
                hpl[rows] = np.fmax(hpl[rows], dh + h_alt)  # NaN h_alt: keep the fix's
                if p == 3:
                    vpl[rows] = np.fmax(vpl[rows], np.abs(d[:, 2]) + v_alt)

            if np.any(amb):
                rows = cand[amb]
                ambiguous(rows, x_alt[amb], J_alt[amb], sc[amb], keep_a[rows], T_alt[amb])
            # a wrong exclusion: where the test left observations out and the mirror on
            # the kept ones failed, the mirror refined on every heard observation, with
            # one exclusion of its own by the w-test, may pass (the excluded anchor was
            # the one off the line that told the sides apart)
            ex = ~amb & np.any(heard[cand] & ~keep_a[cand], axis=1)
            if np.any(ex):
                rows2, sc2 = cand[ex], sc[ex]
                hk = heard[rows2]
                x2, _, J2 = mirror_solution(range_model, sol.position[rows2], v[rows2], sc2,
                                            hk)
                obs2 = range_model.predict(sol.position[rows2]) - v[rows2]
                with np.errstate(invalid="ignore", divide="ignore"):
                    u2 = np.where(hk, (range_model.predict(np.nan_to_num(x2)) - obs2) / sc2,
                                  np.nan)
                    _, _, r2 = protection_levels_local(J2, sc2, hk, lam0, k)
                    w2 = np.abs(u2) / np.sqrt(np.where(r2 > R_MIN, r2, np.nan))
                w2 = np.where(np.isfinite(w2), w2, -1.0)
                jj = np.argmax(w2, axis=1)
                ii = np.arange(jj.size)
                keep2 = hk.copy()
                drop = w2[ii, jj] > w_critical(alpha0)
                keep2[ii[drop], jj[drop]] = False
                T2 = np.nansum(np.where(keep2, u2 * u2, 0.0), axis=1)
                dof2 = keep2.sum(axis=1) - p
                crit2 = np.full(jj.size, np.nan)
                if np.any(dof2 >= 1):
                    crit2[dof2 >= 1] = global_critical(dof2[dof2 >= 1], alpha0=alpha0,
                                                       beta0=beta0)
                amb2 = np.isfinite(x2[:, 0]) & (dof2 >= 1) & (T2 <= crit2)
                if np.any(amb2):
                    ambiguous(rows2[amb2], x2[amb2], J2[amb2], sc2[amb2], keep2[amb2],
                              T2[amb2])
                amb[np.flatnonzero(ex)[amb2]] = True
            # one fault: the mirror with one observation left out (bound only)
            _cover_mirror_exclusions(range_model, sol.position, v, sig * factor_a[:, None],
                                     keep_a, cand[~amb], hpl, vpl, widen, alpha0, beta0, k)
    # a passing fix without a finite bound (an observation whose fault its test cannot
    # detect: a redundancy number below R_MIN, as of a range from an anchor in line with
    # two others and the tag) is no more verified than one without redundancy: not ok,
    # not low_redundancy, which say an MDB-sized fault would have been detected (a
    # low_redundancy row with hpl inf; the serve review of 2026-12-06)
    new[st.among(new, (st.OK, st.LOW_REDUNDANCY)) & ~np.isfinite(hpl)] = st.UNVERIFIED
    usable = st.among(new, st.USABLE)
    # nothing bounds a usable fix whose bound could not be computed (no redundancy, no
    # scale): infinite, never NaN -- a NaN would pass every ``error > hpl`` check unseen
    unbounded = (new == st.UNVERIFIED) | blind | ~np.isfinite(hpl)
    hpl = np.where(usable, np.where(unbounded, np.inf, hpl), np.nan)
    vpl = np.where(usable & (p == 3),
                   np.where(unbounded | ~np.isfinite(vpl), np.inf, vpl), np.nan)
    # a fix far outside anything its anchors can vouch for is no fix (issue 15: never ok
    # with a non-finite sigma0, or a position outside 10x the anchors' extent)
    pos = sol.position
    if np.any(usable):
        span = sol.extra.get("anchor_extent")
        if span is not None:
            centre, radius = span
            with np.errstate(invalid="ignore"):
                far = np.linalg.norm(pos - centre, axis=1) > 10.0 * max(radius, 1.0)
            # (a failed test says more: the fix is not only far, it is wrong -- an `ls`
            # fix with sigma0 3 096 said `extrapolated`; the locate review)
            new[usable & far & (new != st.FAULT_DETECTED)] = st.EXTRAPOLATED
    if alert_limit is not None:
        with np.errstate(invalid="ignore"):
            new[st.among(new, st.USABLE) & (new != st.PREDICTED) & ~(hpl <= alert_limit)] = (
                st.PROTECTION_EXCEEDED)
    usable = st.among(new, st.USABLE)
    bounded = usable | (new == st.PROTECTION_EXCEEDED)  # a refused fix: by how much
    extra = dict(sol.extra)
    extra.update(hpl=np.where(bounded, hpl, np.nan), vpl=np.where(bounded, vpl, np.nan),
                 test_statistic=T, test_critical=crit, flagged=flagged,
                 test_alpha=_test_alpha(crit, dof), flags_kept=kept_rest)
    if range_model is not None:
        extra["ambiguity_distance"] = np.where(usable, amb_dist, np.nan)
        extra["ambiguity_position"] = np.where(usable[:, None], amb_pos, np.nan)
        extra["ambiguity_terms"] = np.where(usable[:, None], amb_terms, np.nan)
        extra["test_kept"] = keep_a
        extra["ambiguity_kept"] = amb_kept
    # ``excluded`` and ``n_used`` stay the estimator's (what the fix used); the test's
    # flags are in extra["flagged"]
    return replace(sol, status=new, position=np.where(usable[:, None], pos, np.nan),
                   extra=extra)


#: Methods whose fit keeps every observation at its a-priori weight: an observation the
#: w-test flags stays in their fix (:func:`protect` gives ``fault_detected``, not
#: ``fault_excluded``; ``auto`` then solves the epoch again robustly).
PLAIN_FIT_METHODS = frozenset({"ls", "wls", "nls"})

#: ``robustloc locate``'s default: Gauss-Newton where the epoch passes its own test, the
#: robust fit where the test finds a fault (:func:`locate_protected`).
AUTO = "auto"
#: The robust method ``auto`` switches to on an epoch whose plain fit fails its test.
AUTO_ROBUST = "huber"
#: The method ``auto`` uses on every epoch of a log with frequent gross errors.
AUTO_HEAVY = "igg"
#: A log whose share of gross residuals (:attr:`Locator.log_gross_share`, ``|u| > 4``)
#: exceeds this is solved by :data:`AUTO_HEAVY` on every epoch.  The geometric mean of
#: what was measured (2026-12-01): at most 2.2 % on every shared real log (corridor 2.17,
#: ble-tetam 2.13, dwm1001 NLOS 1.56, the others 0.13-1.3 %), where Gauss-Newton is the
#: better fit, and 4.9 % on simulated ranges with 5 % gross errors (20 %: 20 %), where a
#: redescending fit is 3x better; Gaussian noise gives 6.3e-5 (0.07 % measured).  A log
#: with 2 % gross errors (1.9 %) stays with test-then-robustify.
AUTO_GROSS_SHARE = 0.033


def locate_protected(
    locator,  # robustloc.estimators.ranging.Locator (method "auto" allowed here)
    anchors: Array,
    values: Array,
    kind: str = "range",
    *,
    A: Array | None = None,
    n: Array | None = None,
    height_offset: Array | None = None,
    alpha0: float = ALPHA0,
    beta0: float = BETA0,
    k_noise: float | None = None,
    alert_limit: float | None = None,
    snoop: bool = True,
) -> Solution:
    """Solve every epoch and :func:`protect` it: the one entry point of every front end
    (``locate``, the service, the Dask engine) for fixes with their integrity.

    ``locator.method == "auto"`` ("test, then robustify") solves every epoch by plain
    Gauss-Newton (``nls``, the maximum-likelihood fix when the noise is what the log's
    scale says) and tests it; an epoch whose test fails (``fault_detected``, or
    ``unavailable``: flagged observations left nothing to confirm the rest, as happens
    when one gross error spreads over every residual of a least-squares fit) is solved
    again by :data:`AUTO_ROBUST` with the log's scale and tested again.  On epochs that
    agree with the noise model it is exactly ``nls`` (no efficiency lost); on epochs the
    test proves inconsistent it is the robust fix.  The choice is measured in the report's
    "out of the box" section: on the shared real data plain Gauss-Newton is as good as any
    peer, while M-estimation on every epoch loses up to 20 % there (systematic NLOS biases
    that no residual pattern reveals); on ranges with 20 % gross errors the switch cuts
    the RMS by 40 %.

    A log whose first pass found frequent gross errors (``locator.log_gross_share`` above
    :data:`AUTO_GROSS_SHARE`) is solved by the redescending :data:`AUTO_HEAVY` on every
    epoch instead: with one range in twenty grossly wrong, many faulty epochs pass a
    least-squares test (a gross error spreads over every residual), and test-then-robustify
    keeps them.
    """
    _check_protection_options(k_noise, alert_limit)  # (before any epoch is solved)
    kw = dict(A=A, n=n, height_offset=height_offset)
    rm = range_model_of(anchors, height_offset)
    pk = dict(alpha0=alpha0, beta0=beta0, k_noise=k_noise, alert_limit=alert_limit,
              range_model=rm, snoop=snoop)
    sol = _locate_tested(locator, anchors, values, kind, kw, pk)
    if rm is None or locator.robust_scale != "log":
        return sol
    # item 7: an ambiguous fix on the side of its anchors' line the log's fixes avoid
    sides = locator.log_sides
    if sides is None:  # the log is this batch
        sides = ambiguity_sides(sol, rm)
    return resolve_sides(sol, sides, rm)


def _locate_tested(locator, anchors: Array, values: Array, kind: str, kw: dict,
                   pk: dict) -> Solution:
    """:func:`locate_protected` before the log's side of ambiguous fixes."""
    from dataclasses import replace as _replace

    alert_limit = pk["alert_limit"]
    if locator.method != AUTO:
        return protect(locator.solve(anchors, values, kind, **kw), **pk)
    if locator.robust_scale == "log" and locator.log_scale_fixed is None:
        # the log is this batch: its first pass gives the scale and the gross share
        scale, share = locator.log_statistics(anchors, values, kind, **kw)
        locator = _replace(locator, log_scale_fixed=tuple(float(v) for v in scale),
                           log_gross_share=share)
    share = locator.log_gross_share
    if share is not None and share > AUTO_GROSS_SHARE:
        # (--param thresholds given for auto are the huber refit's: not igg's)
        heavy_loc = _replace(locator.with_method(AUTO_HEAVY), weight_params={})
        heavy = protect(heavy_loc.solve(anchors, values, kind, **kw), **pk)
        extra = dict(heavy.extra)
        extra["robust_refit"] = np.ones(heavy.position.shape[0], dtype=bool)
        return _replace(heavy, method=AUTO, extra=extra)
    plain = protect(locator.solve_as("nls", anchors, values, kind, **kw), **pk)
    # (a fix whose flagged ranges are all that fails its test is kept: refitting those
    # epochs by huber, or dropping the flagged range, lost 1-7 % on four real logs,
    # docs/choosing-a-method.md, benchmarks/bench_auto_refit.py)
    redo = st.among(plain.status, (st.FAULT_DETECTED, st.UNAVAILABLE)) & ~plain.extra[
        "flags_kept"]
    if alert_limit is not None:  # a fix the alert limit refused may have failed its test
        redo |= (plain.status == st.PROTECTION_EXCEEDED) & ~(
            plain.extra["test_statistic"] <= plain.extra["test_critical"]) & ~plain.extra[
            "flags_kept"]
    if not np.any(redo):
        return _replace(plain, method=AUTO,
                        extra={**plain.extra, "robust_refit": np.zeros(redo.shape, bool)})
    scale = plain.extra.get("log_scale")
    robust_loc = locator.with_method(AUTO_ROBUST, log_scale=scale)
    rows = np.flatnonzero(redo)
    rob = protect(robust_loc.solve(anchors, np.asarray(values)[rows], kind, **kw), **pk)
    return _merge_rows(_replace(plain, method=AUTO), rob, rows)


def range_model_of(anchors: Array, height_offset: Array | None) -> RangeModel | None:
    """The anchors as a :class:`RangeModel` for the ambiguity check (an anchor with a
    non-finite coordinate is never kept by a fix: any finite stand-in serves), or None
    when the anchors are not a 2-D / 3-D array."""
    a = np.asarray(anchors, dtype=float)
    if a.ndim != 2 or a.shape[1] not in (2, 3) or a.shape[0] == 0:
        return None
    h = None
    if height_offset is not None and a.shape[1] == 2:
        h = np.nan_to_num(np.broadcast_to(np.asarray(height_offset, dtype=float),
                                          a.shape[0]))
    return RangeModel(np.nan_to_num(a), h)


#: ``Solution.extra`` entries that hold one value per anchor, not per epoch.
_PER_ANCHOR = frozenset({"log_scale"})


def _merge_rows(base: Solution, sub: Solution, rows: NDArray[np.int64]) -> Solution:
    """``base`` with epochs ``rows`` replaced by ``sub`` (whose epochs are ``rows``)."""
    out = {}
    for name in ("position", "covariance", "residuals", "weights", "excluded", "sigma0",
                 "iterations", "converged", "status", "n_used"):
        arr = np.array(getattr(base, name), copy=True)
        arr[rows] = getattr(sub, name)
        out[name] = arr
    extra = dict(base.extra)
    N = base.position.shape[0]
    for k, v in sub.extra.items():
        b = extra.get(k)
        # per-epoch arrays only: one row per epoch in both (a per-anchor array such as
        # ``log_scale`` has the epochs' length when there are as many epochs as anchors)
        if (k not in _PER_ANCHOR and isinstance(v, np.ndarray) and isinstance(b, np.ndarray)
                and b.shape[:1] == (N,) and v.shape[:1] == (len(rows),)
                and b.shape[1:] == v.shape[1:]):
            arr = b.copy()
            arr[rows] = v
            extra[k] = arr
    robust = np.zeros(N, dtype=bool)
    robust[rows] = True
    extra["robust_refit"] = robust
    return replace(base, **out, extra=extra)
