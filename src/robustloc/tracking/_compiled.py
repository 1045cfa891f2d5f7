"""Compiled (numba) round of the range tracker: every step of :mod:`robustloc.tracking.tracker`
for ``K`` tags in one call.

One call of :func:`track_round_4` (CV) or :func:`track_round_6` (CA) -- :func:`track_round_n`
with offset states: the tag's range offset ``b`` as the last state (ranges ``d_i + b``,
``Tracker(range_offset=True)``), or each link's (``Tracker(link_offsets=True)``) --
advances ``K`` tags by one epoch each, doing in a loop over tags what
``Tracker._filter_numpy`` does with batched NumPy for the range model (items 2-8, 10 and 11
of the tracker's docstring, same order, same formulas):

1. prediction ``x- = F x``, ``P- = F P F^T + Q`` and the ranges ``h(x-)`` with their
   Jacobian rows (the fusion kernel's helpers :func:`robustloc.filters._compiled.predict`,
   :func:`~robustloc.filters._compiled.range_rows`); innovations ``y_i = o_i - h_i`` of
   the observations ``o_i`` (``z_i - b_i`` in the range domain, ``Tracker._observations``),
   ``(H P- H^T)_ii`` and ``e_i = y_i / sqrt((H P- H^T)_ii + s^2 sigma_i^2)``;
2. the CUSUM of each link in use, the ``moved`` rule, holds, offsets and re-admission;
3. the robust predict + update of the held-out measurement: one call of the fusion filter's
   kernel (:data:`robustloc.filters._compiled.KERNELS`, the tight model of the ranges only:
   ``pack_params(..., kinematic=False)``) -- the same compiled filter core as
   ``FusionFilter``;
4. the B-method global test (``NIS > chi2(1 - alpha(m); m)``, table ``gcrit``) -- a
   failure that one w-test exclusion explains (:func:`one_fault_explains`) passes -- and
   the "half rejected" rule: flags ``sus`` of the epochs the caller checks against the
   robust snapshot fix (NumPy, for those tags only), and ``moved``;
5. the Sage-Husa noise scale, the protection level ``hpl``, the status and the output row.

A tag whose filter is lost (item 9 of the tracker's docstring) is flagged in ``lost``: its
prediction is meaningless (``var_x + var_y > lost_pos_var`` and ``sqrt(eps) (var_x +
var_y) >= min_i R_ii`` over the components of the update, :func:`prediction_lost`; found in
step 1, before the update), or its update failed numerically (a non-finite state or
covariance, a negative variance, or a heard component without a positive innovation
variance, after step 3).  The kernel then returns :data:`LOST`
without writing anything; the caller re-starts the flagged tags and runs the round again
without them.

The state of the tags lives in the tracker's arrays, indexed by slot ``sl[k]``; the kernel
reads it and writes it back only when the whole round succeeded, so a round the kernel
cannot do (:data:`NOT_PD`: a Cholesky factor failed) leaves everything untouched for the
NumPy engine.  Sums over the links run in link order (NumPy's pairwise sums group them
differently): the results agree with the NumPy engine to rounding (tested to 1e-9).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from robustloc.filters._compiled import (
    _KIN,
    _KIND,
    _M,
    _N,
    _NANCH,
    _NPOW,
    _ROFF,
    BAD_SHAPE,
    DONE,
    OFF_LINKS,
    ST_FAULT_EXCLUDED,
    ST_OK,
    ST_PREDICTED,
    STATUS_CHARS,
    STATUSES,
    UKF,
    avail_index,
    cholesky_at,
    fusion_step_4,
    fusion_step_5,
    fusion_step_6,
    fusion_step_7,
    fusion_step_n,
    offset_rows,
    offsets,
    predict,
    range_rows,
    transition,
)

# layout of the tracker's settings vector (:func:`pack_settings`)
_CUSUM_K, _CUSUM_H, _READMIT, _LO, _HI, _FORGET, _SQRT_LAM0, _K_IR, _W2, _LOST_VAR = range(10)
#: Status codes written into ``code`` (as :data:`robustloc.filters._compiled.STATUSES`).
CODES = (ST_OK, ST_FAULT_EXCLUDED, ST_PREDICTED)
#: Return code of a round with lost filters (flagged in ``lost``; nothing written).  Beside
#: the fusion kernel's ``DONE, BAD_SHAPE, NOT_PD = 0, 1, 2``.
LOST = 3
#: ``sqrt(eps)`` of float64 (``2^-26``): a variance ``r`` added to ``V`` keeps fewer than
#: half of its significant digits in ``V + r`` once ``sqrt(eps) V >= r`` (its rounding
#: error ``eps V`` is then ``>= sqrt(eps) r``).
SQRT_EPS = 2.0**-26


def pack_settings(cusum_k: float, cusum_h: float, readmit_samples: int, noise_lo: float,
                  noise_hi: float, noise_forget: float, sqrt_lambda0: float,
                  k_ir: float, w2_crit: float, lost_pos_var: float) -> np.ndarray:
    """The tracker's settings as one float vector for :func:`track_round_4` / ``_6``.

    ``cusum_h = inf`` disables the step detector; ``noise_lo, noise_hi`` are the bounds of
    the squared noise scale ``s^2``; ``sqrt_lambda0`` the root of the w-test's
    non-centrality (MDB factor), ``k_ir`` the noise multiplier of ``hpl``, ``w2_crit`` the
    squared critical value of the w-test (``chi2.isf(alpha0, 1)``), ``lost_pos_var`` the
    tracker's setting of that name (:func:`prediction_lost`).
    """
    return np.array([cusum_k, cusum_h, float(readmit_samples), noise_lo, noise_hi,
                     noise_forget, sqrt_lambda0, k_ir, w2_crit, lost_pos_var],
                    dtype=np.float64)


@njit(cache=True, nogil=True, inline="always")
def prediction_lost(v_pos, r_min, lost_pos_var):  # pragma: no cover - jit
    """True when a prediction with position variance ``v_pos = var_x + var_y`` is
    meaningless for an update whose smallest measurement variance is ``r_min`` (``inf``
    without components; NaN propagates): beyond ``lost_pos_var`` and so wide that
    ``sqrt(eps) v_pos >= r_min``.  The innovation covariance ``S = H P- H^T + R`` then
    carries ``R`` to fewer than half of its digits (``(H P- H^T)_ii <= v_pos`` for the
    unit rows of ranges, its rounding ``eps v_pos``), and the update's ``P- - P- H^T S^-1
    H P-`` cancels as many: ``S`` turns singular or indefinite as ``eps v_pos`` nears
    ``r_min`` (a clock jump of hours).  NaN ``v_pos`` is lost.  The NumPy twin is
    ``robustloc.tracking.tracker._prediction_lost``."""
    return not (v_pos <= lost_pos_var or v_pos * SQRT_EPS < r_min)


@njit(cache=True, nogil=True, inline="always")
def innovation_cov(M, hv, hb, oc, Pp, rd, av, S):  # pragma: no cover - jit
    """``S = H P- H^T + diag(rd)`` (M x M) of the range rows, on the rows and columns
    where ``av`` is True (the others are left as they are, never read): position rows
    ``hv (M, 2)`` and, where ``oc[i] >= 0``, the entry ``hb[i]`` of an offset state in
    column ``oc[i]`` (:func:`robustloc.filters._compiled.offset_rows`)."""
    for i in range(M):
        if not av[i]:
            continue
        ci = oc[i]
        for j in range(i + 1):
            if not av[j]:
                continue
            cj = oc[j]
            v = (hv[i, 0] * (Pp[0, 0] * hv[j, 0] + Pp[0, 1] * hv[j, 1])
                 + hv[i, 1] * (Pp[1, 0] * hv[j, 0] + Pp[1, 1] * hv[j, 1]))
            if ci >= 0 and cj >= 0:  # + h_i,pos P_pos,cj hb_j + hb_i P_ci,pos h_j,pos + ..
                v += (((hv[i, 0] * Pp[0, cj] + hv[i, 1] * Pp[1, cj]) * hb[j]
                       + (Pp[ci, 0] * hv[j, 0] + Pp[ci, 1] * hv[j, 1]) * hb[i])
                      + hb[i] * hb[j] * Pp[ci, cj])
            if i == j:
                v += rd[i]
            S[i, j] = v
            S[j, i] = v


@njit(cache=True, nogil=True)
def linearized_gain_pos(M, hv, hb, oc, Pp, rd, w, av, S, L, Li, X, ia):  # pragma: no cover - jit
    """The position rows of the linearized gain ``G = P- H^T S'^-1`` over the components
    ``av`` the update used (``w_i > 0``), ``S' = H P- H^T + diag(rd / w)`` (the update's
    equivalent variances), transposed into ``X (M, 2)`` (row ``i``: component ``i``'s
    column; zero where not used): the UKF's hpl (``Tracker._hpl``).  False when ``S'`` is
    not positive definite.  Solved on the used components only (``ia (M,)`` scratch;
    :func:`robustloc.filters._compiled.cholesky_at`)."""
    innovation_cov(M, hv, hb, oc, Pp, rd, av, S)
    for i in range(M):
        if av[i]:
            S[i, i] += rd[i] * (1.0 / w[i] - 1.0)
    na = avail_index(av, M, ia)
    if not cholesky_at(S, 1.0, ia, na, L, Li):
        return False
    for i in range(M):
        X[i, 0] = 0.0
        X[i, 1] = 0.0
    for c in range(2):  # X[ia, c] = S^-1 a_c, a_c,i = (P- H_i^T)_c, compact in L's rows
        for a in range(na):
            i = ia[a]
            v = Pp[c, 0] * hv[i, 0] + Pp[c, 1] * hv[i, 1]
            if oc[i] >= 0:
                v += Pp[c, oc[i]] * hb[i]
            for b in range(a):
                v -= L[a, b] * X[ia[b], c]
            X[i, c] = v * Li[a]
        for a in range(na - 1, -1, -1):
            v = X[ia[a], c]
            for b in range(a + 1, na):
                v -= L[b, a] * X[ia[b], c]
            X[ia[a], c] = v * Li[a]
    return True


@njit(cache=True, nogil=True)
def one_fault_explains(M, hv, hb, oc, Pp, rd, y, av, w2_crit, crit_less, S, L, Li, u,
                       c, ia):  # pragma: no cover - jit
    """Data snooping with one exclusion (seed 003; :func:`robustloc.tracking.tracker.
    one_fault_explains` is the NumPy reference): the component ``i`` (>= 0) when the
    largest w-test statistic
    ``w_i^2 = (S^-1 y)_i^2 / (S^-1)_ii`` of the available components exceeds ``w2_crit``
    and the global test of the others passes: ``y^T S^-1 y - w_i^2 <= crit_less`` (the
    innovation quadratic form without component ``i``).  ``S = H P- H^T + diag(rd)`` from
    the position rows ``hv (M, 2)`` of the range Jacobian and, where ``oc[i] >= 0``, the
    entry ``hb[i]`` of an offset state in column ``oc[i]`` (the tag's range offset, or the
    link's: :func:`robustloc.filters._compiled.offset_rows`); ``S, L (M, M)``, ``Li, u, c,
    ia (M,)`` are scratch.  Solved on the available components only
    (:func:`robustloc.filters._compiled.cholesky_at`; ``u`` and ``c`` compact).  -1 where
    no one exclusion explains the failure."""
    innovation_cov(M, hv, hb, oc, Pp, rd, av, S)
    na = avail_index(av, M, ia)
    if not cholesky_at(S, 1.0, ia, na, L, Li):
        return -1
    for a in range(na):  # u = S^-1 y over the available components
        v = y[ia[a]]
        for b in range(a):
            v -= L[a, b] * u[b]
        u[a] = v * Li[a]
    for a in range(na - 1, -1, -1):
        v = u[a]
        for b in range(a + 1, na):
            v -= L[b, a] * u[b]
        u[a] = v * Li[a]
    q = 0.0
    best = 0.0
    at = -1
    for a in range(na):
        q += y[ia[a]] * u[a]
        # (S^-1)_ii = |L^-1 e_i|^2: column a of L^-1 by forward substitution
        d = 0.0
        for j in range(a, na):
            v = 1.0 if j == a else 0.0
            for r in range(a, j):
                v -= L[j, r] * c[r]
            c[j] = v * Li[j]
            d += c[j] * c[j]
        w2 = u[a] * u[a] / d
        if w2 > best:
            best = w2
            at = ia[a]
    return at if best > w2_crit and q - best <= crit_less else -1


@njit(cache=True, nogil=True)
def _round(n, sl, t, z, x_s, P_s, t_s, bias_s, held_s, gp_s, gm_s, hsum_s, hn_s, scale2_s,
           obs, r0, rssi_A, rssi_n, d_min, prm, tset, gcrit, idx, out_x, out_var, out_cxy,
           out_nu, out_nis, out_exc, out_hpl, out_scale, code, moved, sus, dof, xp_o, Pp_o,
           dt_o, lost):  # pragma: no cover - jit
    """Body of :func:`track_round_4` / ``_6`` for state size ``n`` (see their docstring)."""
    K = sl.shape[0]
    M = z.shape[1]
    m = M  # the fusion model's tight measurement without its speed and course rows
    nn = n * n
    if int(prm[_N]) != n or int(prm[_M]) != m or int(prm[_NANCH]) != M or prm[_KIN] != 0.0:
        return BAD_SHAPE
    # numba does not check bounds: the slots and rows must lie inside their arrays
    S = x_s.shape[0]
    if x_s.shape[1] != n or P_s.shape[0] != S or t_s.shape[0] != S or bias_s.shape[1] != M:
        return BAD_SHAPE
    if t.shape[0] != K or z.shape[0] != K or obs.shape != z.shape or r0.shape != z.shape:
        return BAD_SHAPE
    if idx.shape[0] != K or out_x.shape[1] != n or out_exc.shape[1] != M:
        return BAD_SHAPE
    if lost.shape[0] != K:
        return BAD_SHAPE
    for k in range(K):
        if not (0 <= sl[k] < S and 0 <= idx[k] < out_x.shape[0]):
            return BAD_SHAPE
    off_chi, off_F, off_a, off_s = offsets(prm, n, m)
    ck, ch = tset[_CUSUM_K], tset[_CUSUM_H]
    readmit = int(tset[_READMIT])
    lo, hi, lf = tset[_LO], tset[_HI], tset[_FORGET]
    sl0, kir = tset[_SQRT_LAM0], tset[_K_IR]
    w2c = tset[_W2]
    lost_var = tset[_LOST_VAR]
    max_held = max(1, (M - 1) // 2)
    rssi = rssi_A.shape[0] > 0
    omode = int(prm[_ROFF])  # offset states (OFF_NONE ..): the tag's, or each link's
    off_ln = off_s + len(STATUSES) * STATUS_CHARS  # their path-loss exponents (scaled)
    nm = n - M if omode >= OFF_LINKS else n  # the kinematic states (+ common offset)

    # ---- round arrays: gathered states, the fusion kernel's inputs and output row
    xg = np.empty((K, n))
    Pg = np.empty((K, n, n))
    zf = np.empty((K, m))
    R = np.empty((K, m, 1))  # diagonal (filters._compiled._r)
    o_P = K * n
    o_y = o_P + K * nn  # innovations, then standardized innovations (K, m) each
    o_e = o_y + K * m
    o_w = o_P + K * nn + 2 * K * m
    o_nis = o_w + K * m
    o_nu = o_nis + K
    o_st = o_nu + K
    o_g = o_st + K * STATUS_CHARS // 2
    fout = np.empty(o_g + (K + 7) // 8)
    iout = fout[o_nu:o_st].view(np.int64)
    sout = fout[o_st:o_g].view(np.uint32)
    # per tag and link: kept from the first pass for the last one
    y = np.empty((K, M))
    hph = np.empty((K, M))
    rd = np.empty((K, M))
    hv = np.empty((K, M, 2))
    new_gp = np.empty((K, M))
    new_gm = np.empty((K, M))
    new_hsum = np.empty((K, M))
    new_hn = np.empty((K, M), np.int64)
    new_bias = np.empty((K, M))
    new_held = np.empty((K, M), np.bool_)
    held_now = np.empty((K, M), np.bool_)
    hbv = np.zeros((K, M))  # offset states: each row's entry and column (offset_rows)
    ocv = np.full((K, M), -1, np.int64)
    # scratch of one tag
    F = np.empty((n, n))
    Qm = np.empty((n, n))
    Ps = np.empty((n, n))
    T = np.empty((n, n))
    pw = np.empty(int(prm[_NPOW]))
    zh = np.empty(M)
    dist = np.empty(M)
    hvk = np.empty((M, 2))
    alarm = np.empty(M, np.bool_)
    use = np.empty(M, np.bool_)
    avk = np.empty(M, np.bool_)
    Ssn = np.empty((M, M))
    Lsn = np.empty((M, M))
    Lisn = np.empty(M)
    usn = np.empty(M)
    csn = np.empty(M)
    iasn = np.empty(M, np.int64)
    Xg = np.empty((M, 2))  # the UKF's linearized gain, position rows (transposed)
    ukf = int(prm[_KIND]) == UKF

    # ---- pass 1: prediction, innovations, CUSUM, holds (items 2 and 4 of the tracker)
    d_prev = math.nan
    any_lost = False
    for k in range(K):
        s = sl[k]
        d = max(t[k] - t_s[s], 0.0)
        dt_o[k] = d
        if not d == d_prev:
            transition(n, d, prm, off_F, pw, F, Qm)
            d_prev = d
        for i in range(n):
            xg[k, i] = x_s[s, i]
            for j in range(n):
                Pg[k, i, j] = P_s[s, i, j]
        xp = xp_o[k]
        Pp = Pp_o[k]
        predict(n, F, Qm, xg[k], Pg[k], xp, Pp, Ps, T)
        range_rows(xp, prm, off_a, M, zh, hvk)  # zh: the distances d_i(x-)
        for i in range(M):
            dist[i] = zh[i]
        # the predicted ranges with the offset states (d_i + b, d_i + b_i, d_i f_i)
        offset_rows(omode, xp, M, prm, off_ln, zh, hvk, hbv[k], ocv[k])
        sc2 = scale2_s[s]
        n_alarm = 0
        n_held = 0
        for i in range(M):
            h0 = hvk[i, 0]
            h1 = hvk[i, 1]
            v = h0 * (Pp[0, 0] * h0 + Pp[0, 1] * h1) + h1 * (Pp[1, 0] * h0 + Pp[1, 1] * h1)
            oci = ocv[k, i]
            if oci >= 0:  # H_i = (h0, h1, .., hb at oci): + 2 hb h_pos P_pos,oci + ..
                hb = hbv[k, i]
                v += ((h0 * Pp[0, oci] + h1 * Pp[1, oci]) * hb
                      + (Pp[oci, 0] * h0 + Pp[oci, 1] * h1) * hb) + hb * hb * Pp[oci, oci]
            hph[k, i] = v
            hv[k, i, 0] = h0
            hv[k, i, 1] = h1
            rd[k, i] = sc2 * r0[k, i]
            zi = z[k, i]
            yi = obs[k, i] - zh[i]
            y[k, i] = yi
            e = yi / math.sqrt(hph[k, i] + rd[k, i])
            hd = held_s[s, i]
            u = math.isfinite(zi) and not hd
            use[i] = u
            gp = gp_s[s, i]
            gm = gm_s[s, i]
            if u:  # g+ = max(0, g+ + e - k), g- = max(0, g- - e - k) (Page 1954)
                v = gp + e - ck
                gp = 0.0 if v < 0.0 else v
                v = gm - e - ck
                gm = 0.0 if v < 0.0 else v
            a = u and (gp > ch or gm > ch)
            alarm[i] = a
            if a:
                n_alarm += 1
            if hd or a or bias_s[s, i] != 0.0:  # (an offset in force: a step before)
                n_held += 1
            new_gp[k, i] = gp
            new_gm[k, i] = gm
        mv = n_alarm > 0 and n_held > max_held
        moved[k] = mv
        ma = 0
        for i in range(M):
            zi = z[k, i]
            a = alarm[i] and not mv
            hd = (held_s[s, i] and not mv) or a
            hs = hsum_s[s, i]
            hn = hn_s[s, i]
            if a or mv:
                new_gp[k, i] = 0.0
                new_gm[k, i] = 0.0
                hs = 0.0
                hn = 0
            heard = math.isfinite(zi)
            if hd and heard:  # held: accumulate the new offset against the prediction
                if rssi:  # in dB, through the path-loss model (LinkModel.rssi)
                    lg = math.log10(max(dist[i], d_min))
                    dr = zi - (rssi_A[i] - 10.0 * rssi_n[i] * lg)
                    if omode >= OFF_LINKS:  # (and the link's offset state, dB)
                        dr = dr - xp[nm + i]
                    hs = hs + dr
                else:
                    hs = hs + (zi - zh[i])
                hn += 1
            ready = hd and hn >= readmit
            new_bias[k, i] = (0.0 if mv else hs / max(hn, 1) if ready else bias_s[s, i])
            zin = math.nan if hd else obs[k, i]
            zf[k, i] = zin
            R[k, i, 0] = rd[k, i]
            if math.isfinite(zin):
                ma += 1
            held_now[k, i] = hd and heard
            new_held[k, i] = hd and not ready
            new_hsum[k, i] = 0.0 if ready else hs
            new_hn[k, i] = 0 if ready else hn
        dof[k] = ma
        # a meaningless prediction (item 9 of the tracker): the smallest variance of the
        # update's components (NaN propagating, as np.min) against the position variance
        r_min = math.inf
        for i in range(M):
            if math.isfinite(zf[k, i]) and r_min == r_min and not rd[k, i] >= r_min:
                r_min = rd[k, i]
        lk = ma > 0 and prediction_lost(Pp[0, 0] + Pp[1, 1], r_min, lost_var)
        lost[k] = lk
        any_lost = any_lost or lk
    if any_lost:  # nothing written: the caller re-starts these tags, runs the others again
        return LOST

    # ---- robust predict + update: the fusion filter's compiled kernel (item 3)
    if omode >= OFF_LINKS:
        rc = fusion_step_n(xg, Pg, dt_o, zf, R, prm, fout)
    elif n == 4:
        rc = fusion_step_4(xg, Pg, dt_o, zf, R, prm, fout)
    elif n == 5:
        rc = fusion_step_5(xg, Pg, dt_o, zf, R, prm, fout)
    elif n == 6:
        rc = fusion_step_6(xg, Pg, dt_o, zf, R, prm, fout)
    else:
        rc = fusion_step_7(xg, Pg, dt_o, zf, R, prm, fout)
    if rc != DONE:
        return rc
    # an update that failed numerically (a non-finite moment, a negative variance, or a
    # heard component whose innovation variance is not positive -- the prediction is no
    # covariance -- which the equivalent-variance update leaves out): lost
    for k in range(K):
        ok = True
        for i in range(m):
            ok = ok and not (math.isfinite(fout[o_y + k * m + i])
                             and not math.isfinite(fout[o_e + k * m + i]))
        for i in range(n):
            ok = ok and math.isfinite(fout[k * n + i])
            for j in range(n):
                v = fout[o_P + k * nn + i * n + j]
                ok = ok and math.isfinite(v) and (i != j or v >= 0.0)
        lost[k] = not ok
        any_lost = any_lost or not ok
    if any_lost:
        return LOST

    # ---- pass 2: B-method test, noise scale, hpl, rows, state (items 5, 6, 8)
    c_ok = np.uint32(prm[off_s + ST_OK * STATUS_CHARS])
    c_fe = np.uint32(prm[off_s + ST_FAULT_EXCLUDED * STATUS_CHARS])
    for k in range(K):
        s = sl[k]
        r = idx[k]
        ma = dof[k]
        nis = fout[o_nis + k]
        nu = iout[k]
        c0 = sout[k * STATUS_CHARS]
        c = ST_OK if c0 == c_ok else (ST_FAULT_EXCLUDED if c0 == c_fe else ST_PREDICTED)
        # global test (seed 003), unless one w-test exclusion explains its failure, and
        # the "half rejected" rule
        fail = ma > 0 and nis > gcrit[ma]
        explained = False
        fault = -1  # the component one exclusion explains the failed test by
        if fail and ma >= 2:
            for i in range(M):
                avk[i] = math.isfinite(zf[k, i])
            fault = one_fault_explains(M, hv[k], hbv[k], ocv[k], Pp_o[k], rd[k], y[k], avk,
                                       w2c, gcrit[ma - 1], Ssn, Lsn, Lisn, usn, csn, iasn)
            if fault >= 0:
                fail = False
                explained = True
        sus[k] = ma > 0 and (fail or 2 * nu <= ma)
        Pn00 = fout[o_P + k * nn]
        Pn01 = fout[o_P + k * nn + 1]
        Pn10 = fout[o_P + k * nn + n]
        Pn11 = fout[o_P + k * nn + n + 1]
        # UKF: its P+ is the sigma points', for which G = P+ H^T R^-1 does not hold: the
        # linearized gain P- H^T S'^-1 instead (Tracker._hpl)
        gain_ok = False
        if ukf and ma > 0:
            for i in range(M):
                avk[i] = math.isfinite(zf[k, i]) and fout[o_w + k * m + i] > 0.0
            gain_ok = linearized_gain_pos(M, hv[k], hbv[k], ocv[k], Pp_o[k], rd[k],
                                          fout[o_w + k * m: o_w + k * m + M], avk,
                                          Ssn, Lsn, Lisn, Xg, iasn)
        sw = 0.0
        swe = 0.0
        slope = 0.0
        any_held = False
        for i in range(M):
            wv = fout[o_w + k * m + i]
            av = math.isfinite(zf[k, i])
            if av:
                # Sage-Husa: weighted mean of (y^2 - (H P- H^T)_ii) / sigma_i^2 (Mehra 1972),
                # without the component the w-test identified (its fault is no noise)
                if i != fault:
                    sw += wv
                    swe += wv * ((y[k, i] * y[k, i] - hph[k, i]) / r0[k, i])
                # hpl slope: |G_pos,i| MDB_i, G_i = w_i P+ H_i^T / R_ii (seed 003 eq. (3))
                wr = wv / rd[k, i]
                # (with an offset state H_i has a third entry: + hb_i P+_c,pos)
                oci = ocv[k, i]
                if ukf:
                    g0 = Xg[i, 0] if gain_ok else math.inf  # no gain: unbounded
                    g1 = Xg[i, 1] if gain_ok else math.inf
                else:
                    g0 = hv[k, i, 0] * Pn00 + hv[k, i, 1] * Pn10
                    g1 = hv[k, i, 0] * Pn01 + hv[k, i, 1] * Pn11
                    if oci >= 0:
                        g0 += hbv[k, i] * fout[o_P + k * nn + oci * n]
                        g1 += hbv[k, i] * fout[o_P + k * nn + oci * n + 1]
                    g0 *= wr
                    g1 *= wr
                v = math.hypot(g0, g1) * (sl0 * math.sqrt(hph[k, i] + rd[k, i]))
                if slope == slope and not v <= slope:  # max, NaN propagating (np.max)
                    slope = v
            out_exc[r, i] = (av and wv <= 0.0) or held_now[k, i] or i == fault
            any_held = any_held or held_now[k, i]
            held_s[s, i] = new_held[k, i]
            gp_s[s, i] = new_gp[k, i]
            gm_s[s, i] = new_gm[k, i]
            hsum_s[s, i] = new_hsum[k, i]
            hn_s[s, i] = new_hn[k, i]
            bias_s[s, i] = new_bias[k, i]
        sc2 = scale2_s[s]
        if sw > 0.0:
            rh = swe / max(sw, 1e-300)
            if math.isfinite(rh):
                v = (1.0 - lf) * sc2 + lf * max(rh, 0.0)
                sc2 = min(max(v, lo), hi)
        scale2_s[s] = sc2
        tr = 0.5 * (Pn00 + Pn11)
        det = Pn00 * Pn11 - Pn01 * Pn01
        lmax = tr + math.sqrt(max(tr * tr - det, 0.0))
        out_hpl[r] = slope + kir * math.sqrt(max(lmax, 0.0))
        if c == ST_OK and (any_held or explained):  # (a w-test-identified fault that
            # the robust weight only down-weighted was `ok`: the track review)
            c = ST_FAULT_EXCLUDED
        code[k] = c
        out_nu[r] = nu
        out_nis[r] = nis
        out_scale[r] = math.sqrt(sc2)
        out_cxy[r] = Pn01
        t_s[s] = t[k]
        for i in range(n):
            xi = fout[k * n + i]
            out_x[r, i] = xi
            x_s[s, i] = xi
            out_var[r, i] = fout[o_P + k * nn + i * n + i]
            for j in range(n):
                P_s[s, i, j] = fout[o_P + k * nn + i * n + j]
    return DONE


_DOC = """One epoch of ``K`` tags of the range tracker, state size {n} ({model}).

    Parameters
    ----------
    sl, t, z : ``(K,)`` slots, ``(K,)`` times and ``(K, M)`` calibrated ranges (NaN: not
        heard) of the round's epochs, one per tag.
    x_s, P_s, t_s, bias_s, held_s, gp_s, gm_s, hsum_s, hn_s, scale2_s : the tracker's state
        arrays (all slots), read at ``sl`` and written back there on success.
    obs, r0 : ``(K, M)`` observations ``z - b`` in the filter's (range) domain and their
        a-priori variances (``Tracker._observations``: ranges as measured, or RSSI
        converted by the path-loss model).
    rssi_A, rssi_n, d_min : RSSI only (else ``(0,)`` arrays): the path-loss model of the
        links, in which a held link's offset is estimated (dB); its clamping distance.
    prm : the fusion kernel's settings (``FusionFilter.compiled_params(meas,
        kinematic=False)``: the ranges of the ``M`` anchors).
    tset : :func:`pack_settings`; gcrit : ``(M + 1,)`` B-method critical values by the
        number of components.
    idx : ``(K,)`` output rows; out_x, out_var ``(N, n)``, out_cxy, out_nu, out_nis,
        out_hpl, out_scale ``(N,)``, out_exc ``(N, M)``: the step's output columns, written
        at ``idx``.
    code, moved, sus, dof : ``(K,)`` outputs: status code (:data:`CODES`), the CUSUM's
        "tag moved" flag, the suspicious-epoch flag, the number of components used.
    xp_o, Pp_o, dt_o : ``(K, n)``, ``(K, n, n)``, ``(K,)`` outputs: the prediction and step.
    lost : ``(K,)`` output: the tags whose filter is lost (see the module docstring).

    Returns
    -------
    int
        :data:`robustloc.filters._compiled.DONE`; :data:`LOST` (the tags in ``lost``), or
        the fusion kernel's code (``BAD_SHAPE``, ``NOT_PD``): then no state and no row was
        written.
    """


@njit(cache=True, nogil=True)
def track_round_4(sl, t, z, x_s, P_s, t_s, bias_s, held_s, gp_s, gm_s, hsum_s, hn_s,
                  scale2_s, obs, r0, rssi_A, rssi_n, d_min, prm, tset, gcrit, idx, out_x,
                  out_var, out_cxy, out_nu, out_nis, out_exc, out_hpl, out_scale, code, moved,
                  sus, dof, xp_o, Pp_o, dt_o, lost):  # pragma: no cover - jit
    return _round(4, sl, t, z, x_s, P_s, t_s, bias_s, held_s, gp_s, gm_s, hsum_s, hn_s,
                  scale2_s, obs, r0, rssi_A, rssi_n, d_min, prm, tset, gcrit, idx, out_x,
                  out_var, out_cxy, out_nu, out_nis, out_exc, out_hpl, out_scale, code, moved,
                  sus, dof, xp_o, Pp_o, dt_o, lost)


@njit(cache=True, nogil=True)
def track_round_6(sl, t, z, x_s, P_s, t_s, bias_s, held_s, gp_s, gm_s, hsum_s, hn_s,
                  scale2_s, obs, r0, rssi_A, rssi_n, d_min, prm, tset, gcrit, idx, out_x,
                  out_var, out_cxy, out_nu, out_nis, out_exc, out_hpl, out_scale, code, moved,
                  sus, dof, xp_o, Pp_o, dt_o, lost):  # pragma: no cover - jit
    return _round(6, sl, t, z, x_s, P_s, t_s, bias_s, held_s, gp_s, gm_s, hsum_s, hn_s,
                  scale2_s, obs, r0, rssi_A, rssi_n, d_min, prm, tset, gcrit, idx, out_x,
                  out_var, out_cxy, out_nu, out_nis, out_exc, out_hpl, out_scale, code, moved,
                  sus, dof, xp_o, Pp_o, dt_o, lost)





@njit(cache=True, nogil=True)
def track_round_n(sl, t, z, x_s, P_s, t_s, bias_s, held_s, gp_s, gm_s, hsum_s, hn_s,
                  scale2_s, obs, r0, rssi_A, rssi_n, d_min, prm, tset, gcrit, idx, out_x,
                  out_var, out_cxy, out_nu, out_nis, out_exc, out_hpl, out_scale, code, moved,
                  sus, dof, xp_o, Pp_o, dt_o, lost):  # pragma: no cover - jit
    return _round(x_s.shape[1], sl, t, z, x_s, P_s, t_s, bias_s, held_s, gp_s, gm_s, hsum_s, hn_s,
                  scale2_s, obs, r0, rssi_A, rssi_n, d_min, prm, tset, gcrit, idx, out_x,
                  out_var, out_cxy, out_nu, out_nis, out_exc, out_hpl, out_scale, code, moved,
                  sus, dof, xp_o, Pp_o, dt_o, lost)


track_round_4.__doc__ = _DOC.format(n=4, model="CV")
track_round_6.__doc__ = _DOC.format(n=6, model="CA")
track_round_n.__doc__ = _DOC.format(
    n="any, at run time", model="with offset states: the tag's range offset (5 or 7), or "
    "the links' offsets (4 + M or 6 + M)")
#: Kernels by state size; with offset states (``Tracker(range_offset=True)``,
#: ``Tracker(link_offsets=True)``): :func:`track_round_n` (its fusion update is unrolled
#: for the common offset's sizes 5 and 7).
ROUNDS = {4: track_round_4, 6: track_round_6}
