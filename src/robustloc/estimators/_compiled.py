"""Compiled (numba) per-epoch kernels for range positioning: the robust start and the
robust Gauss-Newton fit of :class:`robustloc.estimators.ranging.Locator`.

The NumPy implementation (:func:`robustloc.estimators.nonlinear.gauss_newton`,
``Locator._initial``, ``Locator._gn``) iterates all epochs together, one array operation per
step; every operation walks the whole batch, so a 2-D epoch of 10 ranges costs about 50 us
in temporaries and call overhead.  Here the same algorithm runs one epoch at a time in
machine code, with every intermediate in a few reused scratch vectors: the small ``p x p``
normal equations (``p = 2, 3``), order statistics by insertion sort, weights by
:func:`robustloc.robust._compiled.weight_value`.

The kernels reproduce the NumPy path step for step (same start candidates and subsets,
same damping schedule, stopping rules, MM-style per-stage scale and final statistics); the
tests compare the two on random logs.  They cover the range model
(:class:`~robustloc.models.ranging.RangeModel`, also used for RSSI converted to ranges) and
the built-in weight functions; anything else runs the NumPy path.

The solved dimension ``p`` (2 or 3) reaches every kernel as ``tag``, a tuple of ``p``
zeros: its length is part of its numba type, so each dimension gets its own compiled code
with the small ``p``-loops unrolled (about 1.4x faster than a run-time ``p``).

Status codes returned by the kernels: :data:`CODES` maps them to :mod:`robustloc.status`.

Threads: every epoch is an independent problem, and the kernels release the GIL
(``nogil``), so a batch of at least ``2 * MIN_CHUNK`` epochs is split into contiguous
spans solved at once in ``numba.get_num_threads()`` threads (:func:`in_threads`; set it
with ``numba.set_num_threads`` or the ``NUMBA_NUM_THREADS`` environment variable, which
the Dask engine's workers set to 1).  Each span writes its own rows of the outputs, with
its own scratch, so the results are identical for any thread count (tested).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable

import numba
import numpy as np
from numba import njit

from robustloc import status as st
from robustloc.estimators.linear import COFACTOR_UPDATES
from robustloc.robust._compiled import HAMPEL, HUBER, rho_value, weight_value

OK, INSUFFICIENT, ILL, NOT_CONVERGED = 0, 1, 2, 3
#: Status strings of the kernels' codes.
CODES = np.array([st.OK, st.INSUFFICIENT, st.ILL_CONDITIONED, st.NOT_CONVERGED], dtype=object)
COND_LIMIT = 1e10  # as robustloc.estimators._kernels.COND_LIMIT
ADJUGATE_RANK = 1e-12  # as robustloc.estimators._kernels.ADJUGATE_RANK
MAD_NORMAL = 0.6744897501960817
_HUBER_WARMUP = np.array([1.5, 0.0, 0.0])  # Huber(1.5), the redescending fits' first stage

#: Fewest epochs a thread is given (:func:`in_threads`): a span of 2 048 epochs takes
#: 5-30 ms in these kernels, starting a thread about 0.1 ms, so a batch below
#: ``2 * MIN_CHUNK`` epochs (a service request, a streaming window's tail) runs in the
#: calling thread alone.
MIN_CHUNK = 2048

# ruff: noqa: N803, N806  (matrix names)


def thread_spans(n: int, threads: int | None = None) -> list[tuple[int, int]]:
    """Contiguous spans ``[lo, hi)`` covering ``range(n)``, one per thread.

    ``threads`` (default ``numba.get_num_threads()``) is capped so that every span holds
    at least :data:`MIN_CHUNK` epochs; spans differ in length by at most one.
    """
    want = numba.get_num_threads() if threads is None else int(threads)
    k = max(1, min(want, n // MIN_CHUNK))
    edges = [(n * i) // k for i in range(k + 1)]
    return list(zip(edges[:-1], edges[1:], strict=True))


def in_threads(run: Callable[[int, int], None], n: int, threads: int | None = None) -> None:
    """Call ``run(lo, hi)`` for each of :func:`thread_spans` ``(n, threads)``, at once.

    The calling thread takes the first span, new threads the others (plain threads, not a
    pool: nothing survives the call, so a forked worker inherits no dead pool).  ``run``
    must write only its own rows and use its own scratch: the kernels release the GIL.
    An exception in any span is raised here after every span has finished.
    """
    spans = thread_spans(n, threads)
    if len(spans) == 1:
        run(*spans[0])
        return
    errors: list[BaseException] = []

    def guarded(lo: int, hi: int) -> None:
        try:
            run(lo, hi)
        except BaseException as exc:  # re-raised in the calling thread
            errors.append(exc)

    workers = [threading.Thread(target=guarded, args=span, daemon=True,
                                name=f"robustloc-kernel-{span[0]}") for span in spans[1:]]
    for t in workers:
        t.start()
    try:
        run(*spans[0])
    finally:
        for t in workers:
            t.join()
    if errors:
        raise errors[0]


# ------------------------------------------------------------------ small dense helpers
@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _inv_small(A, out, tag):  # pragma: no cover - jit
    """Inverse of a symmetric ``p x p`` (p <= 3) into ``out``; returns the *good* flag of
    :func:`robustloc.estimators._kernels.inv_spd` (finite, det > 0, Frobenius condition
    number below ``COND_LIMIT``); a bad matrix gets the identity, as there."""
    p = len(tag)  # compile-time: the dimension tag's tuple length
    if p == 1:
        det = A[0, 0]
        out[0, 0] = 1.0 / (det if det != 0 else 1.0)
    elif p == 2:
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        s = 1.0 / (det if det != 0 else 1.0)
        out[0, 0] = A[1, 1] * s
        out[0, 1] = -A[0, 1] * s
        out[1, 0] = -A[1, 0] * s
        out[1, 1] = A[0, 0] * s
    else:
        c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
        c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
        c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
        det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
        s = 1.0 / (det if det != 0 else 1.0)
        out[0, 0] = c00 * s
        out[1, 0] = c01 * s
        out[2, 0] = c02 * s
        out[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) * s
        out[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) * s
        out[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) * s
        out[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) * s
        out[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) * s
        out[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) * s
    fa = 0.0
    fi = 0.0
    for i in range(p):
        for j in range(p):
            fa += A[i, j] * A[i, j]
            fi += out[i, j] * out[i, j]
    cond2 = fa * fi  # squared Frobenius condition number (no square roots)
    good = math.isfinite(cond2) and det > 0 and cond2 < COND_LIMIT * COND_LIMIT
    if p == 3:  # numerical rank one: ||adj|| = ||A^-1|| det (ADJUGATE_RANK)
        good = good and fi * det * det > ADJUGATE_RANK * ADJUGATE_RANK * fa * fa
    if not good:
        for i in range(p):
            for j in range(p):
                out[i, j] = 1.0 if i == j else 0.0
    return good


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _order_stat(vals, buf, k):  # pragma: no cover - jit
    """``k``-th smallest (0-based) of the non-NaN ``vals`` (insertion sort into ``buf``);
    returns ``(value, count)``; ``value`` is NaN when there are fewer than ``k + 1``."""
    c = 0
    for v in vals:
        if v == v:
            j = c
            while j > 0 and buf[j - 1] > v:
                buf[j] = buf[j - 1]
                j -= 1
            buf[j] = v
            c += 1
    return (buf[k] if k < c else math.nan), c


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _median_abs(vals, tmp, buf):  # pragma: no cover - jit
    """NaN-ignoring median of ``|vals|`` (NaN if none), as ``nanmedian_fast``."""
    for i in range(vals.shape[0]):
        tmp[i] = abs(vals[i])
    _, c = _order_stat(tmp, buf, 0)
    if c == 0:
        return math.nan
    return 0.5 * (buf[(c - 1) // 2] + buf[c // 2])


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _lms(res, dim, tmp, buf):  # pragma: no cover - jit
    """:func:`robustloc.estimators.ranging.lms_score` of one residual vector."""
    m = res.shape[0]
    for i in range(m):
        tmp[i] = abs(res[i])
    _, c = _order_stat(tmp, buf, 0)
    if c == 0:
        return math.inf
    h = max((c + 1) // 2, dim + 2)
    h = min(max(min(h, c), 1), m) - 1
    return buf[h]


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _ranges(a, ho2, x, pred, J, tag):  # pragma: no cover - jit
    """Ranges ``sqrt(|x - a_i|^2 + dz_i^2)`` (seed 000 eq. (2)) and, if ``J`` has rows,
    the Jacobian ``(x - a_i) / d_i`` (as ``RangeModel.predict_jacobian``)."""
    m, p = a.shape[0], len(tag)
    for i in range(m):
        d2 = ho2[i]
        s = 0.0
        for k in range(p):
            t = x[k] - a[i, k]
            s += t * t
        d = math.sqrt(s + d2)
        pred[i] = d
        if J.shape[0]:
            dd = max(d, 1e-9)
            for k in range(p):
                J[i, k] = (x[k] - a[i, k]) / dd


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _jacobian_at(a, x, d, pred, J, tag):  # pragma: no cover - jit
    """``pred = d`` (ranges already computed at ``x``) and the Jacobian there."""
    m, p = J.shape[0], len(tag)
    for i in range(m):
        pred[i] = d[i]
        inv = 1.0 / max(d[i], 1e-9)
        for k in range(p):
            J[i, k] = (x[k] - a[i, k]) * inv


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _normal(J, w, r, Nm, g, tag):  # pragma: no cover - jit
    """``Nm = J^T diag(w) J`` and ``g = J^T diag(w) r`` in one pass over the rows."""
    m, p = J.shape[0], len(tag)
    for k in range(p):
        g[k] = 0.0
        for j in range(p):
            Nm[k, j] = 0.0
    for i in range(m):
        wi = w[i]
        if wi == 0.0:
            continue
        for k in range(p):
            jw = J[i, k] * wi
            g[k] += jw * r[i]
            for j in range(k, p):
                Nm[k, j] += jw * J[i, j]
    for k in range(p):
        for j in range(k):
            Nm[k, j] = Nm[j, k]


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _sandwich_prepare(J, w0, w, Nm, Ni, a, c, tag):  # pragma: no cover - jit
    """The shared part of the rows' ``Q_vv,ii`` (:func:`_sandwich_row`): ``Ni`` the
    inverse of ``J^T W J`` and ``c_k = w_k^2 / w0_k`` (0 for a row the fit leaves out);
    returns whether the normal matrix is good (:func:`_inv_small`).  Overwrites ``Nm``,
    ``Ni``, the p-vector ``a`` and the m-vector ``c``."""
    _normal(J, w, w, Nm, a, tag)  # J^T W J (its right-hand side, into a, unused)
    good = _inv_small(Nm, Ni, tag)
    for k in range(J.shape[0]):
        c[k] = w[k] * w[k] / w0[k] if w[k] != 0.0 else 0.0
    return good


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _sandwich_row(J, w0, w, c, Ni, a, i, tag):  # pragma: no cover - jit
    """``Q_vv,ii`` of row ``i`` of the fit weighted by ``w`` when the observations'
    cofactors are ``1 / w0``, as :func:`robustloc.estimators.linear.sandwich_qvv`, after
    :func:`_sandwich_prepare`: ``sum_k (delta_ik - g_ik w_k)^2 / w0_k`` with
    ``g_ik = J_i^T (J^T W J)^-1 J_k``, nonnegative terms in row order, no cancellation
    (expanded, ``1/w0_i - 2 g_ii w_i / w0_i + ...`` loses digits on high-leverage rows).
    Overwrites the p-vector ``a``."""
    m, p = J.shape[0], len(tag)
    for k in range(p):  # a = (J^T W J)^-1 J_i
        t = 0.0
        for j in range(p):
            t += Ni[k, j] * J[i, j]
        a[k] = t
    q = 0.0
    for kk in range(m):
        if c[kk] == 0.0 and kk != i:  # a left-out or unheard row adds nothing
            continue
        gik = 0.0
        for k in range(p):
            gik += J[kk, k] * a[k]
        if kk == i:
            d = 1.0 - gik * w[i]
            q += d * d / w0[i]
        else:
            q += gik * gik * c[kk]
    return q


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _sandwich(J, w0, w, qvv, out, Nm, Ni, a, c, tag):  # pragma: no cover - jit
    """``out[i] = 1 / sqrt(Q_vv,ii)`` (NaN: untestable) of the fit weighted by ``w`` when
    the observations' cofactors are ``1 / w0`` (:func:`_sandwich_row`); the a-priori
    ``qvv`` where every weight is full, ``J^T W J`` is singular or a value is not finite.
    Overwrites ``Nm``, ``Ni``, the p-vector ``a`` and the m-vector ``c``."""
    m = J.shape[0]
    full = True
    for i in range(m):
        if w[i] != w0[i]:
            full = False
    if full:
        for i in range(m):
            out[i] = qvv[i] if w0[i] > 0 else math.nan
        return
    good = _sandwich_prepare(J, w0, w, Nm, Ni, a, c, tag)
    for i in range(m):
        if not w0[i] > 0:
            out[i] = math.nan
            continue
        if not good:
            out[i] = qvv[i]
            continue
        q = _sandwich_row(J, w0, w, c, Ni, a, i, tag)
        if not math.isfinite(q):
            out[i] = qvv[i]
            continue
        out[i] = 1.0 / math.sqrt(q) if q > 1e-10 / max(w0[i], 1e-300) else math.nan


# ------------------------------------------------------------------------ robust start
def initial_fixes(
    a: np.ndarray, d: np.ndarray, ho2: np.ndarray, combos: np.ndarray, Ginv: np.ndarray,
    c0: np.ndarray, centre: np.ndarray, radius: float, use_subsets: bool, rank: np.ndarray,
) -> np.ndarray:
    """Per-epoch start of the iterative solvers (``Locator._initial``), ``(N, dim)``.

    Candidates: the linearized LS fix of seed 000 eq. (3) (reference anchor the nearest;
    of equal ranges, the one of smallest ``rank``, :func:`ranging.canonical_rank`) clipped
    to the anchors' disc; the inverse-square-distance
    weighted centroid of the heard anchors; with ``use_subsets``, the exact fixes of the
    minimal anchor subsets ``combos (C, dim + 1)`` (inverted designs ``Ginv (C, dim, dim)``
    of the centroid-shifted anchors, shift ``c0``).  The smallest least-median-of-squares
    score wins (first candidate on ties); the disc centre if none is finite.
    """
    N, m = d.shape
    dim = a.shape[1]
    ac = a - c0
    n2 = np.sum(ac * ac, axis=1)
    rank = np.ascontiguousarray(rank, dtype=np.int64)
    out = np.empty((N, dim))

    def run(lo: int, hi: int) -> None:
        _initial_fixes(a, d[lo:hi], ho2, combos, Ginv, c0, centre, float(radius),
                       use_subsets, rank, ac, n2, out[lo:hi], np.empty((4, m)),
                       np.empty((5, dim)), np.empty((2, dim, dim)), (0.0,) * dim)

    in_threads(run, N)
    return out


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _initial_fixes(a, d, ho2, combos, Ginv, c0, centre, radius, use_subsets, rank, ac, n2,
                   out, vm, vp, mp, tag):  # pragma: no cover - jit
    """The loop of :func:`initial_fixes` (no allocation, no reference counting)."""
    N, m = d.shape
    dim = len(tag)
    C, q = combos.shape
    res, tmp, buf, d2 = vm[0], vm[1], vm[2], vm[3]
    cand, best, b, hs = vp[0], vp[1], vp[2], vp[3]
    Nm, Ni = mp[0], mp[1]
    for e in range(N):
        best_c = math.inf
        for k in range(dim):
            best[k] = math.nan
        ref = -1
        heard = 0
        for i in range(m):
            d2[i] = d[e, i] * d[e, i] - ho2[i]
            if math.isfinite(d2[i]):
                if ref < 0 or d[e, i] < d[e, ref] or (
                        d[e, i] == d[e, ref] and rank[i] < rank[ref]):
                    ref = i
            if d[e, i] == d[e, i]:
                heard += 1
        h_idx = min(max(min(max((heard + 1) // 2, dim + 2), heard), 1), m) - 1
        for ci in range(2 + (C if use_subsets else 0)):
            ok = True
            if ci == 0:  # linearized LS, eq. (3), clipped to the disc
                if ref < 0:
                    continue
                for k in range(dim):
                    b[k] = 0.0
                    for j in range(dim):
                        Nm[k, j] = 0.0
                for i in range(m):
                    if i == ref or not math.isfinite(d2[i]):
                        continue
                    h = 0.5 * (d2[ref] - d2[i] - n2[ref] + n2[i])
                    for k in range(dim):
                        gk = ac[i, k] - ac[ref, k]
                        b[k] += gk * h
                        for j in range(dim):
                            Nm[k, j] += gk * (ac[i, j] - ac[ref, j])
                if not _inv_small(Nm, Ni, tag):
                    continue
                r2 = 0.0
                for k in range(dim):
                    s = 0.0
                    for j in range(dim):
                        s += Ni[k, j] * b[j]
                    cand[k] = s + c0[k]
                    r2 += (cand[k] - centre[k]) ** 2
                r = math.sqrt(r2)
                if r > radius:
                    for k in range(dim):
                        cand[k] = centre[k] + (cand[k] - centre[k]) * (radius / r)
            elif ci == 1:  # weighted centroid
                ws = 0.0
                for k in range(dim):
                    cand[k] = 0.0
                for i in range(m):
                    if math.isfinite(d[e, i]):
                        wi = 1.0 / max(d[e, i], 0.5) ** 2
                        ws += wi
                        for k in range(dim):
                            cand[k] += wi * a[i, k]
                for k in range(dim):
                    cand[k] /= ws
            else:  # exact fix of a minimal subset
                c = ci - 2
                for j in range(q):
                    if not math.isfinite(d2[combos[c, j]]):
                        ok = False
                if not ok:
                    continue
                i0 = combos[c, 0]
                for j in range(dim):
                    i1 = combos[c, j + 1]
                    hs[j] = 0.5 * (d2[i0] - d2[i1] - n2[i0] + n2[i1])
                for k in range(dim):
                    s = 0.0
                    for j in range(dim):
                        s += Ginv[c, k, j] * hs[j]
                    cand[k] = s + c0[k]
            for k in range(dim):
                if not math.isfinite(cand[k]):
                    ok = False
            if not ok:
                continue
            # the score is the (h+1)-th smallest |residual|: it can only beat best_c if
            # more than h residuals do, i.e. if at most heard - h - 1 of them do not
            for i in range(m):  # branch-free, so the compiler vectorizes it
                t = ho2[i]
                for k in range(dim):
                    t += (cand[k] - a[i, k]) ** 2
                res[i] = math.sqrt(t) - d[e, i]
            above = 0
            for i in range(m):
                above += abs(res[i]) >= best_c
            if above > heard - h_idx - 1:
                continue
            score = _lms(res, dim, tmp, buf)
            if score < best_c:
                best_c = score
                for k in range(dim):
                    best[k] = cand[k]
        for k in range(dim):
            out[e, k] = best[k] if best_c < math.inf else centre[k]
    return out


# ---------------------------------------------------------------- robust Gauss-Newton
@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _gn_iterate(a, ho2, zz, w0, x, w, u, code, prm, robust, scale_fixed, min_scale,
                max_iter, tol, rel_tol, reuse, scale_in, pred, J, r, qvv, vn, tmp, buf, Nm,
                Ni, g, dx, xn, wa, tag):  # pragma: no cover - jit
    """One stage of :func:`robustloc.estimators.nonlinear.gauss_newton` for one epoch.

    ``x`` (start, overwritten by the solution), ``w`` (a-priori weights in, final
    weights out) and ``u`` (standardized residuals out) are this epoch's rows; the rest
    are scratch arrays.  ``reuse``: ``qvv`` already holds ``Q_vv`` at this start (a
    previous stage from the same start computed it) and ``scale_in`` its scale.
    Returns ``(iterations, converged, stage scale)``; on return ``pred`` and ``J`` hold
    the ranges and Jacobian at ``x`` (after at least one iteration).
    """
    m, p = J.shape[0], len(tag)
    lam = 1e-3
    stage_scale = math.nan
    conv = False
    it = 0
    fresh = False  # pred and J hold the values at x (kept across a rejected step)
    # redescending weights: the cofactors in use (vn, as 1 / sqrt(Q_vv)) follow the
    # weights until the fit has converged once, then are held (as gauss_newton)
    update = robust and code >= HAMPEL
    frozen = False
    pending = False
    prev_step = math.nan  # the last accepted step (nonlinear._still_to_go)
    while it < max_iter:
        if not fresh:
            _ranges(a, ho2, x, pred, J, tag)
            fresh = True
        for i in range(m):
            r[i] = zz[i] - pred[i]
        if robust:
            if it == 0 and not reuse:  # Q_vv of the a-priori fit, once per stage
                _normal(J, w0, r, Nm, g, tag)
                _inv_small(Nm, Ni, tag)
                for i in range(m):  # kept as 1 / sqrt(Q_vv,ii) of testable rows, else NaN
                    q = math.nan
                    if w0[i] > 0:
                        h = 0.0
                        for k in range(p):
                            for j in range(p):
                                h += J[i, k] * Ni[k, j] * J[i, j]
                        q = max(1.0 / w0[i] - h, 0.0)
                    testable = q == q and q > 1e-10 / max(w0[i], 1e-300)
                    qvv[i] = 1.0 / math.sqrt(q) if testable else math.nan
            # standardized residuals (seed 000 sec. 2.1), as standardized_residuals()
            if it == 0 and reuse:
                stage_scale = scale_in
            elif it == 0:
                if scale_fixed == scale_fixed:
                    sc = scale_fixed
                else:
                    for i in range(m):
                        vn[i] = -r[i] * qvv[i] if w0[i] > 0 else math.nan
                    sc = _median_abs(vn, tmp, buf) / MAD_NORMAL
                if not sc == sc:
                    sc = 0.0
                stage_scale = max(sc, max(min_scale, 1e-12))
            if it == 0:
                for i in range(m):
                    vn[i] = qvv[i]
            elif update and not frozen:
                _sandwich(J, w0, w, qvv, vn, Nm, Ni, dx, buf, tag)
                frozen = pending or it >= COFACTOR_UPDATES
            inv_scale = 1.0 / stage_scale
            n_pos = 0
            for i in range(m):
                if w0[i] > 0 and math.isfinite(r[i]):
                    u[i] = -r[i] * vn[i] * inv_scale if vn[i] == vn[i] else 0.0
                else:
                    u[i] = math.nan
                pw = weight_value(code, prm, u[i])
                wa[i] = w0[i] * (pw if pw == pw else 0.0)
                if wa[i] > 0:
                    n_pos += 1
            if n_pos < p:  # keep the geometry: fall back to the previous weights
                for i in range(m):
                    wa[i] = w[i]
        else:
            for i in range(m):
                wa[i] = w0[i]
        # damped normal equations (J^T W J + lam tr/p I) dx = J^T W r
        _normal(J, wa, r, Nm, g, tag)
        tr = 0.0
        for k in range(p):
            tr += Nm[k, k]
        tr = max(tr / p, 1e-12)
        for k in range(p):
            Nm[k, k] += lam * tr
        good = _inv_small(Nm, Ni, tag)
        step = 0.0
        for k in range(p):
            t = 0.0
            for j in range(p):
                t += Ni[k, j] * g[j]
            dx[k] = t
            xn[k] = x[k] + t
            step += t * t  # (NaN stays NaN)
        step = math.sqrt(step)  # the step's length, as nonlinear.gauss_newton's
        _ranges(a, ho2, xn, tmp, J[:0], tag)
        cost_old = 0.0
        cost_new = 0.0
        n_pos = 0
        for i in range(m):
            cost_old += wa[i] * r[i] * r[i]
            rn = zz[i] - tmp[i]
            cost_new += wa[i] * rn * rn
            if wa[i] > 0:
                n_pos += 1
        accept = good and math.isfinite(cost_new) and cost_new <= cost_old * (1 + 1e-12)
        if accept:
            for k in range(p):
                x[k] = xn[k]
            _jacobian_at(a, x, tmp, pred, J, tag)
        for i in range(m):
            w[i] = wa[i]
        lam = max(lam / 1.5, 1e-9) if accept else lam * 3.0
        it += 1
        flat_cost = 1e-6 if rel_tol > 0 else 1e-12  # (nonlinear.FLAT_COST, _FLOOR)
        flat = accept and (cost_old - cost_new <= flat_cost * max(cost_old, 1e-300))
        finite = math.isfinite(step)
        go = 0.0  # the distance still to go (nonlinear._still_to_go)
        if robust and accept and prev_step > 0:  # (reweighted: Gauss-Newton's is quadratic)
            q = step / prev_step
            go = step * q / (1.0 - q) if q < 1.0 else math.inf
        if accept:
            prev_step = step
        reach = step + go
        done = (accept and reach < tol) or flat or lam > 1e8 or not finite
        if done and update and not frozen and finite and lam <= 1e8:
            pending = True  # converged with moving cofactors: once more with them held
            done = False
        if accept and not done:  # a step below rel_tol of the fix's standard error
            dof = max(n_pos - p, 1)
            trn = 0.0
            for k in range(p):
                trn += Ni[k, k]
            sd = math.sqrt(trn * max(cost_new, 0.0) / dof) if cost_new == cost_new else math.nan
            if sd != sd:
                sd = 0.0
            elif sd == math.inf:
                sd = 1.7976931348623157e308
            done = reach <= rel_tol * sd
            if done and update and not frozen:
                pending = True
                done = False
        if done:
            conv = finite
            break
    return it, conv, stage_scale


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _finish(a, ho2, z, valid, x, w, v, qv, cov, fresh, full, pred, J, Nm, Ni,
            g, tag):  # pragma: no cover - jit
    """Final statistics at the solution (as the end of ``gauss_newton``): residuals
    ``v = f(x) - z``, ``Q_vv`` diagonal, covariance ``sigma0^2 N^-1``.  ``fresh``:
    ``pred``, ``J`` already hold the values at ``x``; ``full=False``: only the geometry
    check (a warm-up stage needs no statistics).  Returns ``(good, sigma0)``."""
    m, p = J.shape[0], len(tag)
    if not fresh:
        _ranges(a, ho2, x, pred, J, tag)
    n_pos = 0
    _normal(J, w, pred, Nm, g, tag)
    good = _inv_small(Nm, Ni, tag)
    if not full:
        return good, math.nan
    vpv = 0.0
    for i in range(m):
        v[i] = pred[i] - z[i] if valid[i] else math.nan
        if w[i] > 0:
            n_pos += 1
            vpv += w[i] * v[i] * v[i]
            h = 0.0
            for k in range(p):
                for j in range(p):
                    h += J[i, k] * Ni[k, j] * J[i, j]
            q = 1.0 / w[i] - h
        else:
            q = math.inf
        qv[i] = (0.0 if q < 0 else q) if valid[i] else math.nan
    dof = n_pos - p
    s0 = math.sqrt(vpv / max(dof, 1)) if dof > 0 else math.nan
    s2 = s0 * s0 if dof > 0 else 1.0
    for k in range(p):
        for j in range(p):
            cov[k, j] = Ni[k, j] * s2 if good else math.nan
    return good, s0


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _solve_slot(a, ho2, z, e, xstart, code, prm, robust, scale_fixed, min_scale, max_iter,
                tol, rel_tol, min_obs, n_valid, t, reuse, scale_in, full, XS, WS, US, VS, QS,
                CS, x, w, u, v, qv, cov, pred, J, r, qvv, vn, tmp, buf, Nm, Ni, g, dx, xn, wa,
                zz, w0, valid, tag):  # pragma: no cover - jit
    """One Gauss-Newton stage of epoch ``e`` from ``xstart`` plus the final statistics,
    stored in slot ``t`` of ``XS, WS, US, VS, QS, CS``; returns ``(status, iterations,
    converged, sigma0, n_used, stage scale)``.  Works on scratch vectors only (no per-epoch
    views); ``reuse``, ``scale_in``: see :func:`_gn_iterate`, ``full``: :func:`_finish`."""
    m, p = J.shape[0], len(tag)
    finite = True
    for i in range(m):
        w[i] = w0[i]
        u[i] = math.nan
        v[i] = math.nan
        qv[i] = math.nan
    for k in range(p):
        x[k] = xstart[k]
        finite = finite and math.isfinite(xstart[k])
        for j in range(p):
            cov[k, j] = math.nan
    status = OK
    if n_valid < min_obs:
        status = INSUFFICIENT
    elif not finite:
        status = ILL
    its, conv, s0, scale = 0, False, math.nan, math.nan
    if status == OK:
        its, conv, scale = _gn_iterate(
            a, ho2, zz, w0, x, w, u, code, prm, robust, scale_fixed, min_scale, max_iter, tol,
            rel_tol, reuse, scale_in, pred, J, r, qvv, vn, tmp, buf, Nm, Ni, g, dx, xn, wa,
            tag)
        good, s0 = _finish(a, ho2, z[e], valid, x, w, v, qv, cov, its > 0, full, pred, J, Nm,
                           Ni, g, tag)
        if not good:
            status = ILL
        elif not conv:
            status = NOT_CONVERGED
    n_used = 0
    unusable = status == INSUFFICIENT or status == ILL
    for i in range(m):
        if w[i] > 0:
            n_used += 1
        WS[t, i] = w[i] if valid[i] else math.nan
        US[t, i] = u[i]
        VS[t, i] = v[i]
        QS[t, i] = qv[i]
    for k in range(p):
        XS[t, k] = math.nan if unusable else x[k]
        for j in range(p):
            CS[t, k, j] = cov[k, j]
    return status, its, conv, s0, n_used, scale


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _objective(VS, t, sig, e, code, prm, scale, status):  # pragma: no cover - jit
    """Robust objective ``sum rho(v_i / (s sigma_i))`` of the fix in slot ``t`` from its
    residuals ``VS[t]`` (``f(x) - z``, NaN where not observed); inf if unusable."""
    if status == INSUFFICIENT or status == ILL:
        return math.inf
    tot = 0.0
    for i in range(VS.shape[1]):
        uu = VS[t, i] / (sig[e, i] * scale)
        if uu == uu:
            tot += rho_value(code, prm, uu)
    return tot


def fit_ranges(
    a: np.ndarray, ho2: np.ndarray, z: np.ndarray, sig: np.ndarray, x0: np.ndarray, code: int,
    prm: np.ndarray, robust: bool, redescending: bool, scale_fixed: float, min_scale: float,
    max_iter: int, tol: float, rel_tol: float, min_obs: int,
) -> tuple[np.ndarray, ...]:
    """``Locator._gn`` for every epoch: robust Gauss-Newton on the ranges ``z (N, m)``
    with a-priori ``sig (N, m)`` from the starts ``x0 (N, p)``.

    Redescending weights: a Huber(1.5) stage from ``x0``, then the redescending fit from
    the Huber fix and from ``x0``, keeping the smaller robust objective (both measured
    with the smaller MAD scale of the two starts).  Returns the arrays of a
    :class:`~robustloc.estimators.linear.LinearFit` with status codes:
    ``x, v, w, qvv, sigma0, cov, n_used, iterations, converged, status, u``, and the
    Jacobian ``jac (N, m, p)`` and ranges ``pred (N, m)`` at ``x`` (NaN where ``x`` is not
    finite; every anchor's, heard or not: :meth:`RangeModel.predict_jacobian`'s formula).

    Outputs and scratch are allocated here, so the compiled loop runs without numba's
    reference counting (``_nrt=False``): every array it touches is borrowed.  Long
    batches are split over threads (:func:`in_threads`), each span with its own scratch.
    """
    N, m = z.shape
    p = a.shape[1]
    out = (np.empty((N, p)), np.empty((N, m)), np.empty((N, m)), np.empty((N, m)),
           np.empty(N), np.empty((N, p, p)), np.empty(N, dtype=np.int64),
           np.empty(N, dtype=np.int64), np.empty(N, dtype=np.bool_),
           np.empty(N, dtype=np.int64), np.empty((N, m)), np.empty((N, m, p)),
           np.empty((N, m)))

    def run(lo: int, hi: int) -> None:
        _fit_ranges(a, ho2, z[lo:hi], sig[lo:hi], x0[lo:hi], code, prm, robust, redescending,
                    scale_fixed, min_scale, max_iter, tol, rel_tol, min_obs,
                    *(o[lo:hi] for o in out), np.empty((26, m)), np.empty((9, p)),
                    np.empty((6, p, p)), np.empty((m, p)), np.empty((1, m), dtype=np.bool_),
                    np.zeros((3, 3)), np.zeros((4, 3), dtype=np.int64), np.empty((0, p)),
                    _HUBER_WARMUP.copy(), (0.0,) * p)

    in_threads(run, N)
    return out


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _fit_ranges(a, ho2, z, sig, x0, code, prm, robust, redescending, scale_fixed, min_scale,
                max_iter, tol, rel_tol, min_obs, X, V, W, QV, S0, COV, NU, IT, CONV, STAT, U,
                JAC, PRED, vm, vp, mp, J, vb, sf, si, nojac, hub_prm,
                tag):  # pragma: no cover - jit
    """The loop of :func:`fit_ranges` over epochs; ``vm, vp, mp, J, vb, sf, si`` are scratch
    (rows of m-vectors, p-vectors, p x p matrices, the Jacobian, boolean m-vectors, and the
    per-slot float and integer outcomes)."""
    N, m = z.shape
    p = len(tag)
    # slots: 0 Huber warm-up, 1 fit from the warm-up fix, 2 fit from the start
    XS, CS = vp[0:3], mp[0:3]
    WS, US, VS, QS = vm[0:3], vm[3:6], vm[6:9], vm[9:12]
    x, xstart, xh, g, dx, xn = vp[3], vp[4], vp[5], vp[6], vp[7], vp[8]
    w, u, v, qv, pred, r, qvv, vn, tmp, buf, wa, zz, w0, res = (
        vm[12], vm[13], vm[14], vm[15], vm[16], vm[17], vm[18], vm[19], vm[20], vm[21],
        vm[22], vm[23], vm[24], vm[25])
    cov, Nm, Ni = mp[3], mp[4], mp[5]
    valid = vb[0]
    # per-slot outcomes: sigma0, stage scale (floats); status, iterations, n_used, converged
    S0S, SCS = sf[0], sf[1]
    STS, ITS, NUS, CVS = si[0], si[1], si[2], si[3]
    for e in range(N):
        n_valid = 0
        for i in range(m):
            valid[i] = math.isfinite(z[e, i]) and math.isfinite(sig[e, i]) and sig[e, i] > 0
            w0[i] = 1.0 / (sig[e, i] * sig[e, i]) if valid[i] else 0.0
            zz[i] = z[e, i] if valid[i] else 0.0
            n_valid += valid[i]
        for k in range(p):
            xstart[k] = x0[e, k]
        # stages: redescending weights run the Huber warm-up from the start (slot 0), the
        # redescending fit from the same start (slot 2: its Q_vv and scale equal the
        # warm-up's first ones) and from the warm-up fix (slot 1); others one fit (slot 1)
        for stage in range(3 if redescending else 1):
            start, c, pr, reuse, full, t = xstart, code, prm, False, True, 1
            if redescending and stage == 0:
                c, pr, full, t = HUBER, hub_prm, False, 0
            elif redescending and stage == 1:
                reuse, t = ITS[0] > 0, 2
            elif redescending:
                for k in range(p):
                    xh[k] = XS[0, k] if math.isfinite(XS[0, k]) else xstart[k]
                start = xh
            STS[t], ITS[t], CVS[t], S0S[t], NUS[t], SCS[t] = _solve_slot(
                a, ho2, z, e, start, c, pr, robust, scale_fixed, min_scale,
                max_iter, tol, rel_tol, min_obs, n_valid, t, reuse, SCS[0], full, XS, WS, US,
                VS, QS, CS, x, w, u, v, qv, cov, pred, J, r, qvv, vn, tmp, buf, Nm, Ni, g, dx,
                xn, wa, zz, w0, valid, tag)
        t = 1
        if redescending:
            # one scale for both objectives: the smaller MAD scale of the two starts
            sc = math.nan
            for which in range(2):
                _ranges(a, ho2, xh if which == 0 else xstart, pred, nojac, tag)
                for i in range(m):
                    res[i] = (pred[i] - z[e, i]) / sig[e, i]
                si = _median_abs(res, tmp, buf) / MAD_NORMAL
                if sc != sc or si < sc:
                    sc = si
            if not (math.isfinite(sc) and sc > 0):
                sc = 1.0
            oa = _objective(VS, 1, sig, e, code, prm, sc, STS[1])
            ob = _objective(VS, 2, sig, e, code, prm, sc, STS[2])
            t = 2 if ob < oa else 1
            # both starts reached one fix (within the step tolerance): the warm-up's, so
            # the choice does not rest on rounding
            gap = 0.0  # (the distance between them, as nonlinear.gauss_newton's step)
            for k in range(p):
                gap += (XS[1, k] - XS[2, k]) ** 2
            if math.sqrt(gap) <= tol:
                t = 1
        for k in range(p):
            X[e, k] = XS[t, k]
            for j in range(p):
                COV[e, k, j] = CS[t, k, j]
        for i in range(m):
            W[e, i] = WS[t, i]
            U[e, i] = US[t, i]
            V[e, i] = VS[t, i]
            QV[e, i] = QS[t, i]
        STAT[e] = STS[t]
        IT[e] = ITS[t] + (ITS[0] if redescending else 0)
        CONV[e] = CVS[t]
        S0[e] = S0S[t]
        NU[e] = NUS[t]
        # the design at the fix, for the integrity statistics (one range evaluation)
        finite = True
        for k in range(p):
            xn[k] = XS[t, k]
            finite = finite and math.isfinite(xn[k])
        if finite:
            _ranges(a, ho2, xn, pred, J, tag)
        for i in range(m):
            PRED[e, i] = pred[i] if finite else math.nan
            for k in range(p):
                JAC[e, i, k] = J[i, k] if finite else math.nan
    return X, V, W, QV, S0, COV, NU, IT, CONV, STAT, U, JAC, PRED


# ------------------------------------------------------------------- rescue grid search
def grid_lms(pred_grid: np.ndarray, z: np.ndarray, sig: np.ndarray, dim: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """Per epoch, the grid point of least :func:`~robustloc.estimators.ranging.lms_score`
    of the scaled residuals ``|pred_grid[g] - z[e]| / sig[e]`` (``Locator._rescue``).

    ``pred_grid (G, m)`` predicted observations at the grid points, ``z, sig (S, m)`` the
    epochs' observations (NaN: not heard) and their sigmas.  Returns ``index (S,)`` (the
    first grid point of the least score; -1 where every score is infinite) and that score.
    The same order statistic and the same first-wins tie rule as the NumPy loop.
    """
    S, m = z.shape
    index = np.empty(S, dtype=np.int64)
    score = np.empty(S)
    pg = np.ascontiguousarray(pred_grid, dtype=float)
    z = np.ascontiguousarray(z, dtype=float)
    sig = np.ascontiguousarray(sig, dtype=float)

    def run(lo: int, hi: int) -> None:
        _grid_lms(pg, z[lo:hi], sig[lo:hi], int(dim), index[lo:hi], score[lo:hi],
                  np.empty((3, m)))

    in_threads(run, S)
    return index, score


@njit(cache=True, nogil=True, error_model="numpy", _nrt=False)
def _grid_lms(pg, z, sig, dim, index, score, scratch):  # pragma: no cover - jit
    G, m = pg.shape
    res, tmp, buf = scratch[0], scratch[1], scratch[2]
    for e in range(z.shape[0]):
        best, best_c = -1, math.inf
        for g in range(G):
            # the score is the h-th smallest of the `heard` residuals (_lms); it can beat
            # best_c only if more than h of them are below it: a point with more than
            # heard - h - 1 residuals at or above best_c is skipped without sorting
            heard, above = 0, 0
            for i in range(m):
                r = abs(pg[g, i] - z[e, i]) / sig[e, i]
                res[i] = r
                if r == r:
                    heard += 1
                    if r >= best_c:
                        above += 1
            if heard == 0:
                continue
            h = min(max((heard + 1) // 2, dim + 2), heard) - 1
            if above > heard - h - 1:
                continue
            c = _lms(res, dim, tmp, buf)
            if c < best_c:
                best, best_c = g, c
        index[e] = best
        score[e] = best_c
