"""Compiled (numba) predict + robust update of the UWB/GPS fusion model for ``K`` tracks.

One call of a kernel of :data:`KERNELS` advances ``K`` tracks of the built-in fusion model of
:mod:`robustloc.fusion.pipeline` by one event: the linear CV/CA prediction
``x = F x, P = F P F^T + Q`` (seed 002 eq. (13)) and the EKF or UKF update of
``FusionMeasurement`` followed by everything :func:`robustloc.filters.core.update_from_moments`
does: chi-square gate, equivalent weights ``D``, robust gain ``K_hat = K D`` (seed 002 eq.
(12); its default ``mode="gain"``) or the gain of the equivalent variances ``R_ii / D_ii``
(``mode="variance"``, the tracker's; ``pack_params(variance=True)``), and the covariance of
that estimator (Joseph form for the EKF).  It is the loop-per-track twin of the batched
NumPy core for this one model, written to remove NumPy's per-call overhead (a single track
costs one compiled call instead of a few dozen small array calls); tests check it against
the NumPy path to rounding.

Measurement ``z`` (seed 001): loose coupling ``[x, y, v, theta]``, tight coupling
``[r_1 .. r_M, v, theta]`` with ``r_i = sqrt((x - a_ix)^2 + (y - a_iy)^2 + dz_i^2)``,
``v = sqrt(x'^2 + y'^2)``, ``theta = atan2(x', y')`` (clockwise from north).  The course is
missing when ``|v_measured| < min_speed``; NaN components are left out of a track's update.

EKF (seed 001 eq. (10)): analytic Jacobian ``H`` at the predicted state (with the guards of
``FusionMeasurement.jacobian``), ``S = H P H^T + R``, ``P_xz = P H^T``.
UKF (seed 001 eqs. (20)-(23)): Merwe scaled sigma points of the predicted state,
``z_hat = sum W_m h(X_s)`` (circular mean for the course), ``S = sum W_c dz dz^T + R``,
``P_xz = sum W_c dx dz^T``.  The linear CV/CA prediction is the unscented transform of a
linear ``f`` exactly, so the kernel predicts with ``F`` for the UKF too.  As in
``update_from_moments``, a missing component gets an identity row and column in ``S`` and a
zero innovation, cross covariance and weight, so every track solves the same ``m x m``
system.  The state size (4 for CV, 6 for CA) is a compile-time constant of each kernel, so
its small matrix loops are unrolled; so is ``m = 4`` in the CV loose-coupling kernel (the
common single-track case), the others take ``m`` at run time (see :data:`KERNELS`).
``R`` is taken as symmetric (the Cholesky factor of ``S`` reads its lower triangle).
The range tracker (:mod:`robustloc.tracking._compiled`) adds state sizes 5 and 7: CV and CA
with a tag's range offset ``b`` as the last state, ranges only, ``r_i = d_i + b``
(``Tracker(range_offset=True)``; ``pack_params(..., range_offset=True)``).

Parameters travel in one float vector (see :func:`pack_params`); all outputs, including the
integer counts, the status strings (as ``<U14`` characters) and the gate flags, are written
into one preallocated row whose typed views the caller made beforehand (:func:`layout`), so
a single-track step costs one compiled call and no array boxing.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numba import njit, prange

from robustloc import status as st
from robustloc.robust._compiled import weight_scalar

#: Filter kinds (``prm[_KIND]``).
EKF, UKF = 0, 1
#: Statuses written by the kernels, in this order (as ``<U14`` characters, see :func:`layout`).
STATUSES = (st.OK, st.FAULT_EXCLUDED, st.PREDICTED)
ST_OK, ST_FAULT_EXCLUDED, ST_PREDICTED = 0, 1, 2
#: Characters of a status (``numpy`` dtype ``<U14``: the longest is ``fault_excluded``).
STATUS_CHARS = 14
#: Return values of the kernels.
DONE, BAD_SHAPE, NOT_PD = 0, 1, 2

# layout of the parameter vector
_Q, _MIN_SPEED, _SCALE, _WM0, _WMI, _WC0, _WCI = 0, 1, 2, 3, 4, 5, 6
_WPRM = 7  # 3 weight parameters
_WCODE, _KIND, _NPOW, _N, _M, _NANCH, _KIN = 10, 11, 12, 13, 14, 15, 16
_ROFF = 17  # the tracker's offset states: one of OFF_NONE .. OFF_LINKS_SCALED
_VAR = 18  # 1.0: the equivalent-variance gain (``RobustUpdate(mode="variance")``)
_HEAD = 19
#: Offset states of the range tracker (``prm[_ROFF]``, :func:`pack_params` ``offsets``):
#: none; a common range offset as the last state (``r_i = d_i + b``); one offset per link
#: after the kinematic states (``r_i = d_i + b_i``: ranges, or RSSI fitted in dB); one per
#: link of RSSI turned into ranges (``r_i = d_i 10^(-b_i / (10 n_i))``, ``b_i`` in dB).
OFF_NONE, OFF_COMMON, OFF_LINKS, OFF_LINKS_SCALED = 0, 1, 2, 3
_LN10 = math.log(10.0)


def layout(K: int, n: int, m: int) -> dict[str, int]:
    """Offsets (in float64 units) of the outputs in the ``fout`` row of ``K`` tracks.

    Blocks, each track-major: ``x`` (K, n), ``P`` (K, n, n), innovations, standardized
    innovations, weights (K, m) each, NIS (K,) -- float64; components used (K,) -- int64;
    status (K,) -- ``<U14`` (7 floats a track); gated (K,) -- bool (bytes).  ``size`` is the
    row length.  The kernels compute the same offsets.
    """
    o = {"x": 0, "P": K * n}
    o["innovation"] = o["P"] + K * n * n
    o["standardized"] = o["innovation"] + K * m
    o["weights"] = o["standardized"] + K * m
    o["nis"] = o["weights"] + K * m
    o["n_used"] = o["nis"] + K
    o["status"] = o["n_used"] + K
    o["gated"] = o["status"] + K * STATUS_CHARS // 2
    o["size"] = o["gated"] + (K + 7) // 8
    return o


def monomials(C: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """``(coefficient, power)`` of each entry of ``M(dt) = sum_p dt^p C[p]``.

    The CV/CA matrices have one power of ``dt`` per entry; ``None`` if some entry has more.
    """
    nz = C != 0.0
    if (nz.sum(axis=0) > 1).any():
        return None
    power = np.argmax(nz, axis=0).astype(float)
    coef = C.sum(axis=0)
    return coef, power


def pack_params(
    kind: int,
    q: float,
    min_speed: float,
    scale: float,
    wm: np.ndarray,
    wc: np.ndarray,
    weight_code: int,
    weight_prm: np.ndarray,
    chi2_table: np.ndarray,
    coef_F: np.ndarray,
    coef_Q: np.ndarray,
    anchors: np.ndarray,
    dz2: np.ndarray,
    kinematic: bool = True,
    offsets: int = OFF_NONE,
    link_n: np.ndarray | None = None,
    variance: bool = False,
) -> np.ndarray | None:
    """Pack the settings of one filter and measurement model into one float vector.

    Parameters
    ----------
    kind : :data:`EKF` or :data:`UKF`.
    q : process-noise intensity; ``Q(dt) = q sum_p dt^p coef_Q[p]``.
    min_speed : course measurements with ``|v| < min_speed`` are ignored.
    scale : ``n + lambda`` of the sigma points (seed 001 eq. (20)).
    wm, wc : sigma-point mean and covariance weights ``(2n + 1,)`` (uniform but the first).
    weight_code, weight_prm : compiled weight function
        (:func:`robustloc.robust._compiled.weight_spec`).
    chi2_table : ``(m + 1,)`` gate thresholds by degrees of freedom (``inf``: no gate).
    coef_F, coef_Q : ``(npow, n, n)`` polynomial coefficients in ``dt`` of ``F`` and ``Q / q``
        (``robustloc.filters.motion._coefficients``).
    anchors : ``(M, 2)`` anchor positions (``M = 0`` for loose coupling).
    dz2 : ``(M,)`` squared height offsets.
    kinematic : the measurement ends with the speed and course components (the fusion
        model, ``m = M + 2``, or ``4`` loose); ``False``: ranges only, ``m = M >= 1`` (the
        tracker's tight model: the same kernel without the two always-missing rows).
    offsets : the tracker's offset states (ranges only: requires ``kinematic=False``):
        :data:`OFF_COMMON`, the state's last component is a range offset ``b`` added to
        every range, ``r_i = d_i + b`` (``dr_i/db = 1``; ``range_offset``, state size 5 for
        CV and 7 for CA); :data:`OFF_LINKS`, the last ``M`` components are the links'
        offsets, ``r_i = d_i + b_i``; :data:`OFF_LINKS_SCALED`, the same for RSSI turned
        into ranges, ``r_i = d_i 10^(-b_i / (10 n_i))`` (``link_offsets``; state size
        ``4 + M`` or ``6 + M``, the kernel :func:`fusion_step_n`).
    link_n : ``(M,)`` path-loss exponents ``n_i`` of :data:`OFF_LINKS_SCALED`.
    variance : the gain of ``update_from_moments(mode="variance")``: a component of
        weight ``D_ii < 1`` enters with the equivalent variance ``R_ii / D_ii`` (left out
        at ``D_ii = 0``) and the gain is the Kalman gain of that model, so the update
        never widens the prediction's covariance; ``False``: ``K_hat = K D``.

    Returns
    -------
    ndarray or None
        ``prm`` for a kernel of :data:`KERNELS` (:func:`fusion_step_n` with the links'
        offsets); ``None`` if the model has no compiled kernel (state size other than 4
        or 6, 5 or 7 with the common offset, 4 + M or 6 + M with the links' offsets;
        matrices that are not monomials in ``dt``, or an ``F`` that is not upper
        triangular).
    """
    npow, n, _ = coef_F.shape
    fm, qm = monomials(coef_F), monomials(coef_Q)
    m = chi2_table.shape[0] - 1
    M = anchors.shape[0]
    links = offsets in (OFF_LINKS, OFF_LINKS_SCALED)
    kernel = fusion_step_n if links else kernel_for(n, m)
    if kernel is None or fm is None or qm is None or len(wm) != 2 * n + 1:
        return None
    if np.any(np.tril(fm[0], -1) != 0.0):  # the kernels use that F is upper triangular
        return None
    if m != ((M if M else 2) + 2 if kinematic else M) or m < 1:
        return None
    if offsets not in (OFF_NONE, OFF_COMMON, OFF_LINKS, OFF_LINKS_SCALED):
        return None
    if offsets != OFF_NONE and (kinematic or M == 0):
        return None
    if (n in (5, 7)) != (offsets == OFF_COMMON) and not links:
        return None
    if links and n - M not in (4, 6):
        return None
    ln = np.zeros(0)
    if offsets == OFF_LINKS_SCALED:
        ln = np.asarray(link_n, dtype=float).reshape(-1)
        if ln.shape != (M,) or not np.all(np.isfinite(ln) & (ln > 0)):
            return None
    head = np.zeros(_HEAD)
    head[_Q], head[_MIN_SPEED], head[_SCALE] = q, min_speed, scale
    head[_WM0], head[_WMI], head[_WC0], head[_WCI] = wm[0], wm[1], wc[0], wc[1]
    head[_WPRM : _WPRM + 3] = weight_prm[:3]
    head[_WCODE], head[_KIND], head[_NPOW] = weight_code, kind, npow
    head[_N], head[_M], head[_NANCH], head[_KIN] = n, m, M, 1.0 if kinematic else 0.0
    head[_ROFF] = float(offsets)
    head[_VAR] = 1.0 if variance else 0.0
    anch = np.column_stack([np.asarray(anchors, float).reshape(M, 2), dz2]).ravel()
    chars = np.zeros((len(STATUSES), STATUS_CHARS))
    for c, name in enumerate(STATUSES):
        chars[c, : len(name)] = [ord(ch) for ch in name]
    parts = [head, chi2_table, fm[0].ravel(), fm[1].ravel(), qm[0].ravel(), qm[1].ravel(), anch,
             chars.ravel(), ln]
    return np.ascontiguousarray(np.concatenate(parts), dtype=np.float64)


@njit(cache=True, nogil=True, inline="always")
def _wrap(a: float) -> float:  # pragma: no cover - jit
    """Angle wrapped to ``[-pi, pi)``: ``(a + pi) % (2 pi) - pi`` as ``core.wrap_angle``.

    The remainder is skipped when ``a + pi`` is already in ``[0, 2 pi)``, where it is exact,
    so the result is the same to the bit.
    """
    t = a + math.pi
    if 0.0 <= t < 2.0 * math.pi:
        return t - math.pi
    return t % (2.0 * math.pi) - math.pi


@njit(cache=True, nogil=True, inline="always")
def _r(R, k, i, j):  # pragma: no cover - jit
    """``R_k[i, j]`` of a measurement noise given whole, ``R (Kr, m, m)``, or as its
    diagonal, ``R (Kr, m, 1)`` (the range tracker's: an ``m x m`` matrix per tag would be
    80 MB per round of 1 000 tags that each could hear 100 anchors)."""
    if R.shape[2] == 1:
        return R[k, i, 0] if i == j else 0.0
    return R[k, i, j]


@njit(cache=True, nogil=True, inline="always")
def avail_index(av, size, ia):  # pragma: no cover - jit
    """The indices ``i < size`` where ``av[i]`` is True, in order, into ``ia``; returns
    their count."""
    c = 0
    for i in range(size):
        if av[i]:
            ia[c] = i
            c += 1
    return c


@njit(cache=True, nogil=True)
def cholesky_at(A, scale, ia, ma, L, Li):  # pragma: no cover - jit
    """Lower Cholesky factor ``L[:ma, :ma]`` (and ``Li = 1 / diag(L)``) of ``scale *
    A[ia, ia]``, the rows and columns ``ia[:ma]`` of ``A`` (:func:`avail_index`).  False
    if not positive definite.

    The kernels had factored the whole ``size x size`` matrix with the unavailable rows
    and columns replaced by the identity (as ``update_from_moments`` does for missing
    components): those rows' entries of the padded factor are exact zeros, whose
    products the padded sums added and these skip, so the two agree to the bit on the
    available rows; the work falls from ``size^3 / 6`` to ``ma^3 / 6`` (a tag that hears
    12 of 100 anchors: 580x fewer operations)."""
    for a in range(ma):
        i = ia[a]
        for b in range(a + 1):
            s = scale * A[i, ia[b]]
            for c in range(b):
                s -= L[a, c] * L[b, c]
            if a == b:
                if not s > 0.0:
                    return False
                L[a, a] = math.sqrt(s)
                Li[a] = 1.0 / L[a, a]
            else:
                L[a, b] = s * Li[b]
    return True


@njit(cache=True, nogil=True, inline="always")
def cholesky_solve(L, Li, ma, B, nc):  # pragma: no cover - jit
    """``B[:ma, :nc] <- A^-1 B[:ma, :nc]`` in place, ``L`` the Cholesky factor of ``A``
    (:func:`cholesky_at`): forward then back substitution, all right-hand sides at once."""
    for a in range(ma):  # forward substitution
        for l in range(a):
            f = L[a, l]
            for c in range(nc):
                B[a, c] -= f * B[l, c]
        f = Li[a]
        for c in range(nc):
            B[a, c] *= f
    for a in range(ma - 1, -1, -1):  # back substitution
        for l in range(a + 1, ma):
            f = L[l, a]
            for c in range(nc):
                B[a, c] -= f * B[l, c]
        f = Li[a]
        for c in range(nc):
            B[a, c] *= f


@njit(cache=True, nogil=True, inline="always")
def offsets(prm, n, m):  # pragma: no cover - jit
    """Offsets in ``prm`` (:func:`pack_params`) of the gate table, the ``F``/``Q``
    coefficients, the anchors and the status characters for state size ``n`` and
    measurement size ``m``."""
    off_chi = _HEAD
    off_F = off_chi + m + 1
    off_a = off_F + 4 * n * n
    off_s = off_a + 3 * int(prm[_NANCH])
    return off_chi, off_F, off_a, off_s


@njit(cache=True, nogil=True, inline="always")
def transition(n, d, prm, off_F, pw, F, Qm):  # pragma: no cover - jit
    """``F(dt)`` and ``Q(dt)`` into ``F, Qm (n, n)``: one monomial in ``dt`` per entry
    (:func:`monomials`; ``pw (npow,)`` scratch)."""
    nn = n * n
    q = prm[_Q]
    for p in range(pw.shape[0]):
        pw[p] = math.pow(d, float(p))
    for i in range(n):
        for j in range(n):
            F[i, j] = pw[int(prm[off_F + nn + i * n + j])] * prm[off_F + i * n + j]
            Qm[i, j] = q * (
                pw[int(prm[off_F + 3 * nn + i * n + j])] * prm[off_F + 2 * nn + i * n + j]
            )


@njit(cache=True, nogil=True, inline="always")
def predict(n, F, Qm, xk, Pk, xp, Pp, Ps, T):  # pragma: no cover - jit
    """``xp = F xk``, ``Pp = F Pk F^T + Q`` (seed 002 eq. (13)) for one track.

    ``F`` is upper triangular (checked by :func:`pack_params`); only the upper triangle of
    the symmetric ``F P F^T + Q`` is computed, from ``sym(P)`` (``sym(F P F^T) = F sym(P)
    F^T``).  ``Ps, T (n, n)`` are scratch."""
    for i in range(n):
        s = 0.0
        for j in range(i, n):
            s += F[i, j] * xk[j]
        xp[i] = s
    for i in range(n):
        for j in range(n):
            Ps[i, j] = 0.5 * (Pk[i, j] + Pk[j, i])
    for i in range(n):  # T = F sym(P)
        for j in range(n):
            s = 0.0
            for l in range(i, n):
                s += F[i, l] * Ps[l, j]
            T[i, j] = s
    for i in range(n):  # Pp = T F^T + Q
        for j in range(i, n):
            s = 0.0
            for l in range(j, n):
                s += T[i, l] * F[j, l]
            Pp[i, j] = s + Qm[i, j]
            Pp[j, i] = Pp[i, j]


@njit(cache=True, nogil=True, inline="always")
def range_rows(xp, prm, off_a, M, zh, hv):  # pragma: no cover - jit
    """Ranges ``zh[i] = sqrt((x - a_ix)^2 + (y - a_iy)^2 + dz_i^2)`` of the ``M`` anchors
    at the state ``xp`` and the non-zero entries ``hv[i] = (x - a_ix, y - a_iy) /
    max(r_i, 1e-9)`` of their Jacobian rows (position columns)."""
    for i in range(M):
        dx = xp[0] - prm[off_a + 3 * i]
        dy = xp[1] - prm[off_a + 3 * i + 1]
        r = math.sqrt((dx * dx + dy * dy) + prm[off_a + 3 * i + 2])
        zh[i] = r
        r = max(r, 1e-9)
        hv[i, 0] = dx / r
        hv[i, 1] = dy / r


@njit(cache=True, nogil=True, inline="always")
def offset_rows(mode, xs, M, prm, off_ln, zh, hv, hb, oc):  # pragma: no cover - jit
    """The offset states of the range tracker (``mode``, :data:`OFF_NONE` ..) applied to the
    ``M`` ranges ``zh`` and their position Jacobian rows ``hv (M, 2)`` at the state ``xs``
    (``Tracker._predict`` / ``_jacobian``): the offset's column of each row in ``oc[i]``
    (-1: none) with its entry ``hb[i]``.  Common offset: ``zh_i + b``, entry 1; links'
    offsets ``zh_i + b_i``, entry 1; scaled: ``zh_i f_i``, ``hv_i f_i``, entry ``-zh_i f_i
    ln10 / (10 n_i)`` with ``f_i = 10^(-b_i / (10 n_i))``."""
    n = xs.shape[0]
    nm = n - M
    for i in range(M):
        if mode == OFF_COMMON:
            zh[i] += xs[n - 1]
            hb[i] = 1.0
            oc[i] = n - 1
        elif mode == OFF_LINKS:
            zh[i] += xs[nm + i]
            hb[i] = 1.0
            oc[i] = nm + i
        elif mode == OFF_LINKS_SCALED:
            ni = prm[off_ln + i]
            f = 10.0 ** (-xs[nm + i] / (10.0 * ni))
            zh[i] *= f
            hv[i, 0] *= f
            hv[i, 1] *= f
            hb[i] = -zh[i] * (_LN10 / 10.0) / ni
            oc[i] = nm + i
        else:
            hb[i] = 0.0
            oc[i] = -1


@njit(cache=True, nogil=True, inline="always")
def _h(xs, prm, off_a, M, kin, mode, off_ln, zout):  # pragma: no cover - jit
    """``h(x)`` of the fusion model (``FusionMeasurement.predict``) into ``zout (m,)``;
    without the speed and course when ``kin`` is False; with the offset states of
    ``mode`` (:func:`offset_rows`) on the ranges (``Tracker._predict``)."""
    if M == 0:
        zout[0] = xs[0]
        zout[1] = xs[1]
    else:
        n = xs.shape[0]
        nm = n - M
        for i in range(M):
            dx = xs[0] - prm[off_a + 3 * i]
            dy = xs[1] - prm[off_a + 3 * i + 1]
            r = math.sqrt((dx * dx + dy * dy) + prm[off_a + 3 * i + 2])
            if mode == OFF_COMMON:
                r = r + xs[n - 1]
            elif mode == OFF_LINKS:
                r = r + xs[nm + i]
            elif mode == OFF_LINKS_SCALED:
                r = r * 10.0 ** (-xs[nm + i] / (10.0 * prm[off_ln + i]))
            zout[i] = r
    if kin:
        nr = 2 if M == 0 else M
        zout[nr] = math.hypot(xs[2], xs[3])
        zout[nr + 1] = math.atan2(xs[2], xs[3])


@njit(cache=True, nogil=True)
def _step(n, mc, x, P, dt, z, R, prm, fout, k0, k1):  # pragma: no cover - jit
    """Body of the kernels for a state size ``n`` (4 or 6) and measurement size ``mc``
    (0: the run-time ``prm[_M]``), both constants in each kernel's call: LLVM inlines this
    body into the kernel and unrolls the loops of these sizes.  Advances tracks
    ``k0 .. k1 - 1`` (its own scratch: chunks may run in parallel threads)."""
    K = x.shape[0]
    m = mc if mc > 0 else int(prm[_M])
    if int(prm[_M]) != m:
        return BAD_SHAPE
    M = int(prm[_NANCH])
    kin = prm[_KIN] != 0.0  # speed and course rows (else ranges only)
    omode = int(prm[_ROFF])  # offset states of the range tracker (ranges only)
    npow = int(prm[_NPOW])
    kind = int(prm[_KIND])
    wcode = int(prm[_WCODE])
    # ---- shapes (numba does not check bounds: anything off goes to the NumPy path)
    if int(prm[_N]) != n or x.shape[1] != n or P.shape[0] != K or P.shape[1] != n:
        return BAD_SHAPE
    if P.shape[2] != n or dt.shape[0] != K or z.shape[0] != K or z.shape[1] != m:
        return BAD_SHAPE
    Kr = R.shape[0]
    if ((Kr != 1 and Kr != K) or R.shape[1] != m or (R.shape[2] != m and R.shape[2] != 1)
            or m < (3 if kin else 1)):
        return BAD_SHAPE
    # output blocks (as in :func:`layout`)
    nn = n * n
    o_P = K * n
    o_y = o_P + K * nn
    o_e = o_y + K * m
    o_w = o_e + K * m
    o_nis = o_w + K * m
    o_nu = o_nis + K
    o_st = o_nu + K
    o_g = o_st + K * STATUS_CHARS // 2
    if fout.shape[0] != o_g + (K + 7) // 8:
        return BAD_SHAPE
    iout = fout[o_nu:o_st].view(np.int64)
    sout = fout[o_st:o_g].view(np.uint32)
    bout = fout[o_g:].view(np.uint8)

    min_speed = prm[_MIN_SPEED]
    scale = prm[_SCALE]
    wp0, wp1, wp2 = prm[_WPRM], prm[_WPRM + 1], prm[_WPRM + 2]
    off_chi, off_F, off_a, off_s = offsets(prm, n, m)
    off_ln = off_s + len(STATUSES) * STATUS_CHARS  # offset states' path-loss exponents
    ns = 2 * n + 1
    ci = m - 1 if kin else -1  # course (-1: none)
    si = m - 2 if kin else -1  # speed
    nr = 2 if M == 0 else M  # position rows

    # ---- scratch (separate small arrays: faster loops than views of one buffer)
    F = np.empty((n, n))
    Qm = np.empty((n, n))
    Pp = np.empty((n, n))
    T = np.empty((n, n))
    A = np.empty((n, n))
    Pn = np.empty((n, n))
    Ls = np.empty((n, n))
    Lsi = np.empty(n)
    all_n = np.arange(n)  # every state (cholesky_at)
    sig = np.empty((ns, n))
    Pxz = np.empty((n, m))  # state-measurement cross covariance
    Gt = np.empty((m, n))  # robust gain K D, transposed
    wd = np.empty(m)  # weights D
    ex = np.empty(m)  # equivalent variance added to R (variance mode)
    GMG = np.empty((n, n))
    Mm = np.empty((m, m))
    V = np.empty((n, m))
    Li = np.empty(m)
    y0 = np.empty(m)
    av = np.empty(m, np.bool_)  # available components
    pre = np.empty(m, np.bool_)  # components with a measurement
    ia = np.empty(m, np.int64)  # the available components' indices (avail_index)
    solc = np.empty((m, n + 1))  # sol over the available components, compact
    sol = np.empty((m, n + 1))
    S = np.empty((m, m))
    L = np.empty((m, m))
    zs = np.empty((ns, m))
    dz = np.empty((ns, m))
    hv = np.empty((m, 2))  # EKF: the two non-zero entries of each row of H
    hb = np.zeros(m)  # and the offset state's (offset_rows), in column oc
    oc = np.full(m, -1, np.int64)
    zh = np.empty(m)
    y = np.empty(m)
    xp = np.empty(n)
    pw = np.empty(npow)
    chars = np.empty(3 * STATUS_CHARS, np.uint32)
    for c in range(3 * STATUS_CHARS):
        chars[c] = np.uint32(prm[off_s + c])
    wm0, wmi, wc0, wci = prm[_WM0], prm[_WMI], prm[_WC0], prm[_WCI]
    var = prm[_VAR] != 0.0

    dt_prev = math.nan
    for k in range(k0, k1):
        rk = k if Kr > 1 else 0
        for i in range(m):  # the components with a measurement (S is needed only there)
            pre[i] = math.isfinite(z[k, i])
        # ------------------------------------------------ predict (seed 002 eq. (13))
        d = dt[k]
        if not d == dt_prev:  # F(dt), Q(dt)
            transition(n, d, prm, off_F, pw, F, Qm)
            dt_prev = d
        predict(n, F, Qm, x[k], P[k], xp, Pp, Pn, T)

        # ------------------------------------------------ measurement moments
        if kind == EKF:  # h and its Jacobian at the prediction (seed 001 eq. (10))
            vx = xp[2]
            vy = xp[3]
            if M == 0:
                zh[0] = xp[0]
                zh[1] = xp[1]
                hv[0, 0], hv[0, 1], hv[1, 0], hv[1, 1] = 1.0, 0.0, 0.0, 1.0
            else:
                range_rows(xp, prm, off_a, M, zh, hv)
                offset_rows(omode, xp, M, prm, off_ln, zh, hv, hb, oc)
            if kin:
                vv = vx * vx + vy * vy
                zh[si] = math.sqrt(vv)  # hypot(vx, vy) to rounding
                zh[ci] = math.atan2(vx, vy)
                v2 = max(vv, 1e-12)
                v = math.sqrt(v2)
                hv[si, 0], hv[si, 1] = vx / v, vy / v
                hv[ci, 0], hv[ci, 1] = vy / v2, -vx / v2
            # H has two non-zero columns per row: 0, 1 (position rows) or 2, 3; with an
            # offset state a range row has a third, column oc[i] (entry hb[i])
            for i in range(m):  # Pxz = P H^T
                b = 0 if i < nr else 2
                oci = oc[i] if i < nr else -1
                for j in range(n):
                    v = Pp[j, b] * hv[i, 0] + Pp[j, b + 1] * hv[i, 1]
                    Pxz[j, i] = v + Pp[j, oci] * hb[i] if oci >= 0 else v
            for i in range(m):  # S = H Pxz + R (where measured: the rest is never read)
                if not pre[i]:
                    continue
                b = 0 if i < nr else 2
                oci = oc[i] if i < nr else -1
                for j in range(m):
                    if not pre[j]:
                        continue
                    v = hv[i, 0] * Pxz[b, j] + hv[i, 1] * Pxz[b + 1, j]
                    if oci >= 0:
                        v += hb[i] * Pxz[oci, j]
                    S[i, j] = v + _r(R, rk, i, j)
        else:
            # sigma points of the prediction (seed 001 eq. (20)): chol((n + lambda) P)
            if not cholesky_at(Pp, scale, all_n, n, Ls, Lsi):
                return NOT_PD
            for j in range(n):
                sig[0, j] = xp[j]
            for c in range(n):
                for j in range(n):
                    lv = Ls[j, c] if j >= c else 0.0
                    sig[1 + c, j] = xp[j] + lv
                    sig[1 + n + c, j] = xp[j] - lv
            for p in range(ns):
                _h(sig[p], prm, off_a, M, kin, omode, off_ln, zs[p])
            # weighted means (eq. (22)); circular for the course
            for j in range(m):
                s = wm0 * zs[0, j]
                for p in range(1, ns):
                    s += wmi * zs[p, j]
                zh[j] = s
            if kin:
                sn = wm0 * math.sin(zs[0, ci])
                cs = wm0 * math.cos(zs[0, ci])
                for p in range(1, ns):
                    sn += wmi * math.sin(zs[p, ci])
                    cs += wmi * math.cos(zs[p, ci])
                zh[ci] = math.atan2(sn, cs)
            for p in range(ns):
                for j in range(m):
                    dz[p, j] = zs[p, j] - zh[j]
                if kin:
                    dz[p, ci] = _wrap(dz[p, ci])
            for i in range(m):  # S = sum W_c dz dz^T + R (eq. (23)), where measured
                if not pre[i]:
                    continue
                for j in range(m):
                    if not pre[j]:
                        continue
                    s = (dz[0, i] * wc0) * dz[0, j]
                    for p in range(1, ns):
                        s += (dz[p, i] * wci) * dz[p, j]
                    S[i, j] = s + _r(R, rk, i, j)
            for i in range(n):  # Pxz = sum W_c dx dz^T
                for j in range(m):
                    s = ((sig[0, i] - xp[i]) * wc0) * dz[0, j]
                    for p in range(1, ns):
                        s += ((sig[p, i] - xp[i]) * wci) * dz[p, j]
                    Pxz[i, j] = s

        # ------------------------------------------------ innovation, available components
        course_ok = kin and abs(z[k, si]) >= min_speed
        ma = 0
        for i in range(m):
            yi = z[k, i] - zh[i]
            if i == ci:
                yi = _wrap(yi) if course_ok else math.nan
            y[i] = yi
            ok = math.isfinite(yi) and math.isfinite(S[i, i])
            av[i] = ok
            y0[i] = yi if ok else 0.0
            ma += ok
        # as update_from_moments: S over the available components (identity elsewhere,
        # whose rows of the solution are zero); Cholesky factor and sol = S^-1 [P_xz^T |
        # y], on the available components only (cholesky_at: the same numbers, the work
        # of the anchors heard rather than of every anchor)
        na = avail_index(av, m, ia)
        if not cholesky_at(S, 1.0, ia, na, L, Li):
            return NOT_PD
        for a in range(na):
            i = ia[a]
            for c in range(n):
                solc[a, c] = Pxz[c, i]
            solc[a, n] = y0[i]
        cholesky_solve(L, Li, na, solc, n + 1)
        for i in range(m):
            for c in range(n + 1):
                sol[i, c] = 0.0
        for a in range(na):
            for c in range(n + 1):
                sol[ia[a], c] = solc[a, c]
        nis = 0.0
        for a in range(na):
            nis += y0[ia[a]] * sol[ia[a], n]
        gated = ma > 0 and nis > prm[off_chi + ma]

        # ------------------------------------------------ weights D, gain K D (seed 002 (12))
        nu = 0
        down = False  # a heard component weighted below 1
        for i in range(m):
            if av[i]:
                e = y[i] / math.sqrt(S[i, i])
                fout[o_y + k * m + i] = y[i]
                fout[o_e + k * m + i] = e
                wv = weight_scalar(wcode, wp0, wp1, wp2, e)
                if gated or not math.isfinite(wv):
                    wv = 0.0
                elif var and wv > 0.0 and not math.isfinite(
                        _r(R, rk, i, i) * (1.0 / wv - 1.0)):
                    wv = 0.0  # the added variance overflows: infinite, left out
            else:
                fout[o_y + k * m + i] = math.nan
                fout[o_e + k * m + i] = math.nan
                wv = 0.0
            fout[o_w + k * m + i] = wv
            wd[i] = wv
            nu += wv > 0.0
            down = down or (av[i] and wv != 1.0)
            for j in range(n):  # row i of K_hat^T = (K D)^T
                Gt[i, j] = sol[i, j] * wv
        vu = var and down
        if vu:
            # the equivalent-variance gain (update_from_moments, mode="variance"): the used
            # components (D_ii > 0) with S'_ii = S_ii + R_ii (1 / D_ii - 1), the others left
            # out; G = P_xz S'^-1, so P+ = P - G S' G^T never exceeds P
            na = 0
            for i in range(m):
                ex[i] = 0.0
                if wd[i] > 0.0:
                    ex[i] = _r(R, rk, i, i) * (1.0 / wd[i] - 1.0)
                    S[i, i] += ex[i]
                    ia[na] = i
                    na += 1
            if not cholesky_at(S, 1.0, ia, na, L, Li):
                return NOT_PD
            for a in range(na):
                for c in range(n):
                    solc[a, c] = Pxz[c, ia[a]]
            cholesky_solve(L, Li, na, solc, n)
            for i in range(m):
                for j in range(n):
                    Gt[i, j] = 0.0
            for a in range(na):
                for j in range(n):
                    Gt[ia[a], j] = solc[a, j]
        for j in range(n):  # x+ = x + K_hat y
            s = 0.0
            for i in range(m):
                s += Gt[i, j] * y0[i]
            fout[k * n + j] = xp[j] + s

        # ------------------------------------------------ covariance of x+
        # GMG = K_hat M K_hat^T, M = R (EKF) or S (UKF) over the available components
        # (K_hat's other rows are zero: the sums skip them)
        for a in range(na):
            i = ia[a]
            for b in range(na):
                j = ia[b]
                Mm[a, b] = _r(R, rk, i, j) if kind == EKF else S[i, j]
                if vu and kind == EKF and a == b:  # R_eff = R + the equivalent variance
                    Mm[a, b] += ex[i]
        for i in range(n):  # V = G M
            for b in range(na):
                s = 0.0
                for a in range(na):
                    s += Gt[ia[a], i] * Mm[a, b]
                V[i, b] = s
        for i in range(n):
            for j in range(i, n):
                s = 0.0
                for b in range(na):
                    s += V[i, b] * Gt[ia[b], j]
                GMG[i, j] = s
        # P+ is symmetric: its upper triangle is computed and mirrored
        if kind == EKF:  # Joseph form (I - G H) P (I - G H)^T + G R G^T
            for i in range(n):
                for j in range(n):
                    T[i, j] = 0.0
            for a in range(na):  # T <- G H (H: two non-zero columns per row)
                l = ia[a]
                b = 0 if l < nr else 2
                h0 = hv[l, 0]
                h1 = hv[l, 1]
                oci = oc[l] if l < nr else -1
                for j in range(n):
                    T[j, b] += Gt[l, j] * h0
                    T[j, b + 1] += Gt[l, j] * h1
                    if oci >= 0:
                        T[j, oci] += Gt[l, j] * hb[l]
            for i in range(n):
                for j in range(n):
                    A[i, j] = (1.0 if i == j else 0.0) - T[i, j]
            for i in range(n):  # T = A P
                for j in range(n):
                    s = 0.0
                    for l in range(n):
                        s += A[i, l] * Pp[l, j]
                    T[i, j] = s
            for i in range(n):  # P+ = T A^T + G R G^T
                for j in range(i, n):
                    s = 0.0
                    for l in range(n):
                        s += T[i, l] * A[j, l]
                    s += GMG[i, j]
                    fout[o_P + k * nn + i * n + j] = s
                    fout[o_P + k * nn + j * n + i] = s
        else:  # P - G Pxz^T - Pxz G^T + G S G^T
            for i in range(n):  # T = G Pxz^T (missing columns of Pxz are zero)
                for j in range(n):
                    s = 0.0
                    for a in range(na):
                        l = ia[a]
                        s += Gt[l, i] * Pxz[j, l]
                    T[i, j] = s
            for i in range(n):
                for j in range(i, n):
                    s = ((Pp[i, j] - T[i, j]) - T[j, i]) + GMG[i, j]
                    fout[o_P + k * nn + i * n + j] = s
                    fout[o_P + k * nn + j * n + i] = s

        fout[o_nis + k] = nis if ma > 0 else math.nan
        iout[k] = nu
        bout[k] = 1 if gated else 0
        if ma == 0:
            code = ST_PREDICTED
        elif gated or nu < ma:
            code = ST_FAULT_EXCLUDED
        else:
            code = ST_OK
        for c in range(STATUS_CHARS):
            sout[k * STATUS_CHARS + c] = chars[code * STATUS_CHARS + c]
    return DONE


_DOC = """Predict + robust update of ``K`` tracks (state size {n}, measurement size {m}).

    Parameters
    ----------
    x, P : ``(K, n)`` states and ``(K, n, n)`` covariances at the previous event.
    dt : ``(K,)`` steps.
    z : ``(K, m)`` measurements, NaN where missing.
    R : ``(1, m, m)`` shared or ``(K, m, m)`` per-track measurement noise, or its diagonal
        alone, ``(1, m, 1)`` or ``(K, m, 1)``.
    prm : settings from :func:`pack_params`.
    fout : output row, blocks as in :func:`layout` (``x+``, ``P+``, innovations,
        standardized innovations, weights, NIS, components used, status, gated).

    Returns
    -------
    int
        :data:`DONE`; :data:`BAD_SHAPE` when an input does not fit the model (nothing
        written); :data:`NOT_PD` when a Cholesky factor failed (``(n + lambda) P`` of the
        sigma points, or ``S``): the caller then takes the NumPy path for the whole call.
    """


@njit(cache=True, nogil=True)
def fusion_step_4_4(x, P, dt, z, R, prm, fout):  # pragma: no cover - jit
    return _step(4, 4, x, P, dt, z, R, prm, fout, 0, x.shape[0])


@njit(cache=True, nogil=True)
def fusion_step_4(x, P, dt, z, R, prm, fout):  # pragma: no cover - jit
    return _step(4, 0, x, P, dt, z, R, prm, fout, 0, x.shape[0])


@njit(cache=True, nogil=True)
def fusion_step_6(x, P, dt, z, R, prm, fout):  # pragma: no cover - jit
    return _step(6, 0, x, P, dt, z, R, prm, fout, 0, x.shape[0])


@njit(cache=True, nogil=True)
def fusion_step_n(x, P, dt, z, R, prm, fout):  # pragma: no cover - jit
    return _step(x.shape[1], 0, x, P, dt, z, R, prm, fout, 0, x.shape[0])


@njit(cache=True, nogil=True)
def fusion_step_5(x, P, dt, z, R, prm, fout):  # pragma: no cover - jit
    return _step(5, 0, x, P, dt, z, R, prm, fout, 0, x.shape[0])


@njit(cache=True, nogil=True)
def fusion_step_7(x, P, dt, z, R, prm, fout):  # pragma: no cover - jit
    return _step(7, 0, x, P, dt, z, R, prm, fout, 0, x.shape[0])


# multi-threaded twins for many tracks: ``chunks`` blocks of tracks in numba's thread pool
# (the sizes stay literal constants in each block's call, so the loops still unroll; the
# caller passes the block count: numba cannot cache a kernel that asks for its threads)
@njit(cache=True, nogil=True, parallel=True)
def fusion_step_4_4_mt(x, P, dt, z, R, prm, fout, chunks):  # pragma: no cover - jit
    K = x.shape[0]
    chunks = max(1, min(K, chunks))
    size = (K + chunks - 1) // chunks
    flags = np.zeros(chunks, np.int64)
    for c in prange(chunks):
        flags[c] = _step(4, 4, x, P, dt, z, R, prm, fout, c * size, min(K, (c + 1) * size))
    return flags.max()


@njit(cache=True, nogil=True, parallel=True)
def fusion_step_4_mt(x, P, dt, z, R, prm, fout, chunks):  # pragma: no cover - jit
    K = x.shape[0]
    chunks = max(1, min(K, chunks))
    size = (K + chunks - 1) // chunks
    flags = np.zeros(chunks, np.int64)
    for c in prange(chunks):
        flags[c] = _step(4, 0, x, P, dt, z, R, prm, fout, c * size, min(K, (c + 1) * size))
    return flags.max()


@njit(cache=True, nogil=True, parallel=True)
def fusion_step_6_mt(x, P, dt, z, R, prm, fout, chunks):  # pragma: no cover - jit
    K = x.shape[0]
    chunks = max(1, min(K, chunks))
    size = (K + chunks - 1) // chunks
    flags = np.zeros(chunks, np.int64)
    for c in prange(chunks):
        flags[c] = _step(6, 0, x, P, dt, z, R, prm, fout, c * size, min(K, (c + 1) * size))
    return flags.max()


fusion_step_4_4.__doc__ = _DOC.format(n=4, m="4 (loose coupling)")
fusion_step_4.__doc__ = _DOC.format(n=4, m="any")
fusion_step_6.__doc__ = _DOC.format(n=6, m="any")
fusion_step_5.__doc__ = _DOC.format(n="5 (CV and a range offset)", m="any (ranges)")
fusion_step_7.__doc__ = _DOC.format(n="7 (CA and a range offset)", m="any (ranges)")
fusion_step_n.__doc__ = _DOC.format(n="any, at run time (the links' offsets: 4 + M or 6 + M)",
                                    m="any (ranges)")
for _k, _s in ((fusion_step_4_4_mt, fusion_step_4_4), (fusion_step_4_mt, fusion_step_4),
               (fusion_step_6_mt, fusion_step_6)):
    _k.__doc__ = (_s.__doc__ or "") + (
        "\n    Multi-threaded: ``chunks`` (last argument) blocks of tracks run in numba's "
        "thread pool.\n")
#: Kernels by ``(n, m)``, ``m = 0`` for any measurement size.  Sizes fixed at compile time
#: let the compiler unroll the small matrix loops; the CV loose-coupling EKF (the common
#: fast case) has its own kernel, the others share one per state size.  State sizes 5 and 7
#: are CV and CA with a range offset (the tracker's ``range_offset``: ranges only).
KERNELS = {(4, 4): fusion_step_4_4, (4, 0): fusion_step_4, (6, 0): fusion_step_6,
           (5, 0): fusion_step_5, (7, 0): fusion_step_7}
#: Multi-threaded kernels, same keys; ``FusionFilter.step`` uses them for many tracks
#: (``robustloc.fusion.pipeline._MT_MIN_TRACKS``) when numba has more than one thread.
KERNELS_MT = {(4, 4): fusion_step_4_4_mt, (4, 0): fusion_step_4_mt, (6, 0): fusion_step_6_mt}


def kernel_for(n: int, m: int, threaded: bool = False) -> Callable | None:
    """The compiled kernel for state size ``n`` and measurement size ``m`` (or ``None``);
    ``threaded``: its multi-threaded twin."""
    table = KERNELS_MT if threaded else KERNELS
    return table.get((n, m), table.get((n, 0)))
