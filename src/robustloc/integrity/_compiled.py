"""Compiled (numba) kernels of :mod:`robustloc.integrity.fixes`: the protection levels
(:func:`~robustloc.integrity.fixes.protection_levels_local`), the mirror solution, a
robust fit's own residual cofactors (:func:`~robustloc.integrity.fixes.robust_fit_cofactors`),
the least-squares re-solution's statistic
(:func:`~robustloc.integrity.fixes.resolution_reduction`) and the least-squares
re-solution itself, Newton's method on the ranges, that tests a linearized fix
(:func:`~robustloc.integrity.fixes.least_squares_resolution`).

The NumPy references walk the whole batch once per array operation (about twenty
``(N, n, p)`` temporaries); here each epoch runs in machine code with its ``p x p``
normal matrix (``p = 2, 3``).  Same formulas, same order of the tests and the same edge
cases (an unused observation, a singular normal matrix, a redundancy number at or below
``R_MIN``): the tests compare each kernel with its reference on random geometries
(:mod:`tests.test_integrity_fixes`, :mod:`tests.test_robust_wtest`).  The wrappers run
long batches in two or more threads (:func:`robustloc.estimators._compiled.in_threads`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from robustloc.estimators._compiled import _inv_small, _sandwich_prepare, _sandwich_row

# ruff: noqa: N803, N806  (matrix names)


@njit(cache=True, nogil=True, error_model="numpy")
def _normal_checked(A, f, n, p, count, Nm):  # pragma: no cover - jit
    """``Nm = sum_i f_i a_i a_i^T`` (``a_i`` the rows of ``A``) and whether it is regular
    as the references test it: ``|det| > 1e-12 tr^p`` and at least ``p`` rows
    (``count``)."""
    for a in range(p):
        for b in range(p):
            acc = 0.0
            for i in range(n):
                acc += f[i] * A[i, a] * A[i, b]
            Nm[a, b] = acc
    tr = 0.0
    for a in range(p):
        tr += Nm[a, a]
    if p == 2:
        det = Nm[0, 0] * Nm[1, 1] - Nm[0, 1] * Nm[1, 0]
    else:
        det = (Nm[0, 0] * (Nm[1, 1] * Nm[2, 2] - Nm[1, 2] * Nm[2, 1])
               - Nm[0, 1] * (Nm[1, 0] * Nm[2, 2] - Nm[1, 2] * Nm[2, 0])
               + Nm[0, 2] * (Nm[1, 0] * Nm[2, 1] - Nm[1, 1] * Nm[2, 0]))
    return abs(det) > 1e-12 * max(tr, 1e-300) ** p and count >= p


@njit(cache=True, nogil=True, error_model="numpy")
def _cholesky_inverse(Nm, p, L, M, out):  # pragma: no cover - jit
    """``out = Nm^-1`` (the leading ``p x p`` blocks) through the Cholesky factor
    ``Nm = L L^T``: ``M = L^-1`` (lower triangular), ``out = M^T M``; ``L`` and ``M`` are
    left filled.  False where ``Nm`` is not positive definite in rounding (singular).
    The closed-form adjugate (``_inv_small``) loses up to ~300 cond x eps on the
    redundancy numbers ``1 - a_i^T N^-1 a_i``; Cholesky stays within cond x eps, like the
    LAPACK inverse of the references (the fit-weighted kernel used the adjugate: 1.03e-6
    off the matrix formulas at cond 8e5, r_i 1e-3, 6 x eps cond / r_i; the full suite,
    2026-12-07)."""
    for a in range(p):
        acc = Nm[a, a]
        for c in range(a):
            acc -= L[a, c] * L[a, c]
        if not acc > 0.0:
            return False
        L[a, a] = math.sqrt(acc)
        for b in range(a + 1, p):
            acc = Nm[b, a]
            for c in range(a):
                acc -= L[b, c] * L[a, c]
            L[b, a] = acc / L[a, a]
    for a in range(p):
        for b in range(p):
            M[a, b] = 0.0
    for a in range(p):
        M[a, a] = 1.0 / L[a, a]
        for b in range(a):
            acc = 0.0
            for c in range(b, a):
                acc += L[a, c] * M[c, b]
            M[a, b] = -acc / L[a, a]
    for a in range(p):
        for b in range(p):
            acc = 0.0
            for c in range(max(a, b), p):
                acc += M[c, a] * M[c, b]
            out[a, b] = acc
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def protection_levels_kernel(J, sigma, used, lam0, k_noise, r_min,
                             tag):  # pragma: no cover - jit
    """``(hpl, vpl, r)`` of every epoch; arguments and results as
    :func:`robustloc.integrity.fixes.protection_levels_local`.  ``tag``: a tuple of ``p``
    floats, so the dimension is a compile-time constant (the small loops unroll)."""
    N, n = J.shape[0], J.shape[1]
    p = len(tag)
    hpl = np.full(N, np.nan)
    vpl = np.full(N, np.nan)
    r_out = np.full((N, n), np.nan)
    A = np.zeros((n, 3))
    ones = np.ones(n)
    use = np.zeros(n, dtype=np.bool_)
    Nm = np.zeros((3, 3))
    C = np.zeros((3, 3))
    AN = np.zeros(3)
    Z = np.zeros(3)
    L = np.zeros((3, 3))
    M = np.zeros((3, 3))
    for k in range(N):
        count = 0
        for i in range(n):
            s = sigma[k, i]
            u = used[k, i] and np.isfinite(s) and s > 0.0
            for j in range(p):
                if not np.isfinite(J[k, i, j]):
                    u = False
            use[i] = u
            for j in range(p):
                A[i, j] = J[k, i, j] / s if u else 0.0
            if u:
                count += 1
        # normal matrix J^T P J
        if not _normal_checked(A, ones, n, p, count, Nm):
            continue  # hpl, vpl and r stay NaN, as in the reference
        # N^-1 through its Cholesky factor (_cholesky_inverse); L and M stay for the rows
        if not _cholesky_inverse(Nm, p, L, M, C):
            continue  # not positive definite in rounding: treated as singular
        # the largest squared slope terms; one square root per epoch at the end
        dh2_max = 0.0
        du2_max = 0.0
        for i in range(n):
            if not use[i]:
                continue
            # row i of A N^-1: d x / d (v_i / sigma_i)
            # z = L^-1 a_i, so a_i^T N^-1 a_i = |z|^2 and N^-1 a_i = M^T z
            dot = 0.0
            for a in range(p):
                acc = 0.0
                for c in range(a + 1):
                    acc += M[a, c] * A[i, c]
                Z[a] = acc
                dot += acc * acc
            mv = 0.0
            for b in range(p):
                acc = 0.0
                for a in range(b, p):
                    acc += M[a, b] * Z[a]
                AN[b] = acc
                mv += acc * acc
            r = 1.0 - dot
            r_out[k, i] = r
            if mv <= 1e-18:
                continue  # the observation does not move the fix (|N^-1 a_i| <= 1e-9)
            if r <= r_min:
                dh2_max = np.inf  # a fault here is undetectable and moves the fix: blind
                du2_max = np.inf
                continue
            kk2 = lam0 / r  # (MDB / sigma)^2
            dh2 = (AN[0] * AN[0] + AN[1] * AN[1]) * kk2
            if dh2 > dh2_max:
                dh2_max = dh2
            if p == 3:
                du2 = AN[2] * AN[2] * kk2
                if du2 > du2_max:
                    du2_max = du2
        dh_max = math.sqrt(dh2_max)
        du_max = math.sqrt(du2_max)
        t2 = C[0, 0] + C[1, 1]
        d2 = C[0, 0] * C[1, 1] - C[0, 1] ** 2
        lam_max = 0.5 * t2 + math.sqrt(max(0.25 * t2 * t2 - d2, 0.0))
        hpl[k] = dh_max + k_noise * math.sqrt(lam_max)
        if p == 3:
            vpl[k] = du_max + k_noise * math.sqrt(C[2, 2])
    return hpl, vpl, r_out


@njit(cache=True, nogil=True, error_model="numpy")
def fit_weighted_protection_kernel(J, sigma, used, fw, lam0, k_noise, r_min,
                                   tag):  # pragma: no cover - jit
    """``(hpl, vpl, r)`` of every epoch of a fix weighted by ``fw_i / sigma_i^2``
    (:func:`robustloc.integrity.fixes.protection_levels_local` with ``fit_weight``), in
    whitened form ``a_i = J_i / sigma_i``: ``Q = (sum f a a^T)^-1``, the gain
    ``g_i = f_i Q a_i``, ``C = sum g g^T``, ``r_i = 1 - f_i a_i^T Q a_i`` and the
    residual's variance ``q_i = sum_j ((I - H)_ij)^2``, ``H_ij = f_j a_i^T Q a_j``; the
    slope term
    ``|g_i,h| sqrt(lambda0 q_i) / |r_i|``."""
    N, n = J.shape[0], J.shape[1]
    p = len(tag)
    hpl = np.full(N, np.nan)
    vpl = np.full(N, np.nan)
    r_out = np.full((N, n), np.nan)
    A = np.zeros((n, 3))
    f = np.zeros(n)
    use = np.zeros(n, dtype=np.bool_)
    Nm = np.zeros((p, p))
    Q = np.zeros((p, p))
    Lf = np.zeros((p, p))
    Mf = np.zeros((p, p))
    C = np.zeros((3, 3))
    QA = np.zeros((n, 3))
    for k in range(N):
        count = 0
        for i in range(n):
            s = sigma[k, i]
            u = used[k, i] and np.isfinite(s) and s > 0.0
            for j in range(p):
                if not np.isfinite(J[k, i, j]):
                    u = False
            fi = fw[k, i]
            if not (fi > 0.0):  # NaN or non-positive: no weight in the fit
                fi = 0.0
            elif fi > 1.0:
                fi = 1.0
            use[i] = u
            f[i] = fi if u else 0.0
            for j in range(p):
                A[i, j] = J[k, i, j] / s if u else 0.0
            if u and fi > 0.0:
                count += 1
        if not _normal_checked(A, f, n, p, count, Nm):
            continue  # as the reference: NaN
        if not _cholesky_inverse(Nm, p, Lf, Mf, Q):
            continue  # not positive definite in rounding: singular, NaN as the reference
        for a in range(3):
            for b in range(3):
                C[a, b] = 0.0
        for i in range(n):
            for a in range(p):
                acc = 0.0
                for b in range(p):
                    acc += Q[a, b] * A[i, b]
                QA[i, a] = acc
            if f[i] > 0.0:
                for a in range(p):
                    for b in range(p):
                        C[a, b] += f[i] * f[i] * QA[i, a] * QA[i, b]
        dh2_max = 0.0
        du2_max = 0.0
        for i in range(n):
            if not use[i]:
                continue
            aqa = 0.0
            for a in range(p):
                aqa += A[i, a] * QA[i, a]
            r = 1.0 - f[i] * aqa
            r_out[k, i] = r
            # q_i = sum_j ((I - H)_ij)^2, H_ij = f_j a_i^T Q a_j: a sum of squares (the
            # closed form 1 - 2 f_i a_i^T Q a_i + a_i^T C a_i cancels where r_i is small)
            q = r * r
            for j in range(n):
                if j == i or f[j] == 0.0:
                    continue
                hij = 0.0
                for a in range(p):
                    hij += A[i, a] * QA[j, a]
                hij *= f[j]
                q += hij * hij
            g2 = 0.0
            for a in range(p):
                g2 += (f[i] * QA[i, a]) ** 2
            if g2 <= 1e-18:
                continue  # the observation does not move the fix
            if abs(r) <= r_min:
                dh2_max = np.inf
                du2_max = np.inf
                continue
            kk2 = lam0 * q / (r * r) * f[i] * f[i]  # (MDB / sigma)^2 times f^2
            dh2 = (QA[i, 0] * QA[i, 0] + QA[i, 1] * QA[i, 1]) * kk2
            if dh2 > dh2_max:
                dh2_max = dh2
            if p == 3:
                du2 = QA[i, 2] * QA[i, 2] * kk2
                if du2 > du2_max:
                    du2_max = du2
        t2 = C[0, 0] + C[1, 1]
        d2 = C[0, 0] * C[1, 1] - C[0, 1] ** 2
        lam_max = 0.5 * t2 + math.sqrt(max(0.25 * t2 * t2 - d2, 0.0))
        hpl[k] = math.sqrt(dh2_max) + k_noise * math.sqrt(lam_max)
        if p == 3:
            vpl[k] = math.sqrt(du2_max) + k_noise * math.sqrt(C[2, 2])
    return hpl, vpl, r_out


@njit(cache=True, nogil=True, error_model="numpy")
def _ranges_jacobian(a, h2, xa, f, J):  # pragma: no cover - jit
    """Ranges ``f`` and unit-vector Jacobian ``J`` at ``xa`` (as ``RangeModel``)."""
    for i in range(a.shape[0]):
        t = h2[i]
        for q in range(xa.shape[0]):
            t += (xa[q] - a[i, q]) ** 2
        f[i] = math.sqrt(t)
        for q in range(xa.shape[0]):
            J[i, q] = (xa[q] - a[i, q]) / max(f[i], 1e-9)


@njit(cache=True, nogil=True, error_model="numpy")
def _inverse_sigmas(keep, res, sigma, w):  # pragma: no cover - jit
    """Weights ``w_i = 1 / sigma_i`` of one epoch's kept rows with a finite residual and
    a positive sigma (0 elsewhere, and where ``1 / sigma`` overflows); returns how many
    rows have a weight."""
    kc = 0
    for i in range(w.shape[0]):
        s = sigma[i]
        wi = 0.0
        if keep[i] and math.isfinite(res[i]) and s > 0.0:
            wi = 1.0 / s
            if not math.isfinite(wi):
                wi = 0.0
        w[i] = wi
        if wi > 0.0:
            kc += 1
    return kc


@njit(cache=True, nogil=True, error_model="numpy")
def mirror_kernel(a, h2, x, res, sigma, keep, iterations, ridge):  # pragma: no cover - jit
    """``(x_alt, T_alt, J_alt)`` of :func:`robustloc.integrity.fixes.mirror_solution`, one
    epoch at a time, the same steps in the same order (the principal line / plane from
    LAPACK's symmetric eigensolver, each Gauss-Newton step from LAPACK's general solver,
    as the NumPy reference's batched calls): agreement to rounding, tested.  ``h2`` are
    the squared height offsets of the anchors (zeros without)."""
    N, p = x.shape
    m = a.shape[0]
    x_alt = np.full((N, p), np.nan)
    t_alt = np.full(N, np.nan)
    j_alt = np.full((N, m, p), np.nan)
    w = np.zeros(m)
    d = np.zeros(m)
    f = np.zeros(m)
    J = np.zeros((m, p))
    c = np.zeros(p)
    xa = np.zeros(p)
    S = np.zeros((p, p))
    Nm = np.zeros((p, p))
    g = np.zeros(p)
    for e in range(N):
        kc = _inverse_sigmas(keep[e], res[e], sigma[e], w)
        # observed ranges from the fix and its residuals (v = f(x) - d)
        for i in range(m):
            t = h2[i]
            for q in range(p):
                xq = x[e, q] if np.isfinite(x[e, q]) else 0.0
                t += (xq - a[i, q]) ** 2
            d[i] = math.sqrt(t) - res[e, i] if w[i] > 0.0 else 0.0
        cnt = max(kc, 1)
        for q in range(p):
            acc = 0.0
            for i in range(m):
                if w[i] > 0.0:
                    acc += a[i, q]
            c[q] = acc / cnt
        ext2 = 0.0
        for q in range(p):
            for r in range(p):
                S[q, r] = 0.0
        for i in range(m):
            if w[i] > 0.0:
                n2 = 0.0
                for q in range(p):
                    dq = a[i, q] - c[q]
                    n2 += dq * dq
                    for r in range(p):
                        S[q, r] += dq * (a[i, r] - c[r])
                ext2 = max(ext2, n2)
        extent = max(math.sqrt(ext2), 1.0)
        _, vec = np.linalg.eigh(S)
        proj = 0.0
        for q in range(p):
            proj += (x[e, q] - c[q]) * vec[q, 0]
        ok = kc > p
        for q in range(p):
            xa[q] = x[e, q] - 2.0 * proj * vec[q, 0]
            if not np.isfinite(xa[q]):
                ok = False
        if not ok:
            for q in range(p):
                xa[q] = 0.0
        for _ in range(iterations):
            _ranges_jacobian(a, h2, xa, f, J)
            for q in range(p):
                acc = 0.0
                for i in range(m):
                    if w[i] > 0.0:
                        acc += J[i, q] * w[i] * (d[i] - f[i]) * w[i]
                g[q] = acc
                for r in range(p):
                    acc = 0.0
                    for i in range(m):
                        if w[i] > 0.0:
                            acc += J[i, q] * w[i] * J[i, r] * w[i]
                    Nm[q, r] = acc
            tr = 0.0
            for q in range(p):
                tr += Nm[q, q]
            for q in range(p):  # the ridge of mirror_solution (MIRROR_RIDGE, relative)
                Nm[q, q] += ridge * max(tr, 1.0)
            finite = True
            for q in range(p):
                finite = finite and np.isfinite(g[q])
                for r in range(p):
                    finite = finite and np.isfinite(Nm[q, r])
            if not finite:  # (numba's solve refuses what NumPy's turns into NaN)
                ok = False
                break
            step = np.linalg.solve(Nm, g)
            ln = 0.0
            for q in range(p):
                ln += step[q] * step[q]
            scale = min(1.0, extent / max(math.sqrt(ln), 1e-300))
            if ok:
                for q in range(p):
                    xa[q] += step[q] * scale
        _ranges_jacobian(a, h2, xa, f, J)
        tsum = 0.0
        for i in range(m):
            if w[i] > 0.0:
                tsum += ((f[i] - d[i]) * w[i]) ** 2
        good = ok and np.isfinite(tsum)
        for q in range(p):
            if not np.isfinite(xa[q]):
                good = False
        if good:
            t_alt[e] = tsum
            for q in range(p):
                x_alt[e, q] = xa[q]
            for i in range(m):
                for q in range(p):
                    j_alt[e, i, q] = J[i, q]
    return x_alt, t_alt, j_alt


@njit(cache=True, nogil=True, error_model="numpy")
def resolution_reduction_kernel(J, sigma, keep, v, tag):  # pragma: no cover - jit
    """Per epoch ``b^T N^-1 b`` with ``N = sum J_i J_i^T / sigma_i^2`` and
    ``b = sum J_i v_i / sigma_i^2`` over the rows ``keep`` (finite there): what the
    least-squares re-solution of those rows from the fix takes off ``T``, as the NumPy
    reference in :func:`robustloc.integrity.fixes.resolution_reduction`.  NaN where ``N``
    is not good (:func:`robustloc.estimators._kernels.inv_spd`'s test, by the same
    closed-form inverse).  ``tag``: a tuple of ``p`` floats (``p <= 3``)."""
    N, n = keep.shape
    p = len(tag)
    red = np.full(N, np.nan)
    Nm = np.zeros((p, p))
    Ni = np.zeros((p, p))
    b = np.zeros(p)
    for e in range(N):
        for a in range(p):
            b[a] = 0.0
            for c in range(p):
                Nm[a, c] = 0.0
        for i in range(n):
            if not keep[e, i]:
                continue
            s = sigma[e, i]
            w = 1.0 / (s * s)
            vi = v[e, i]
            for a in range(p):
                ja = J[e, i, a] * w
                b[a] += ja * vi
                for c in range(a, p):
                    Nm[a, c] += ja * J[e, i, c]
        for a in range(p):
            for c in range(a):
                Nm[a, c] = Nm[c, a]
        if not _inv_small(Nm, Ni, tag):
            continue
        acc = 0.0
        for a in range(p):
            t = 0.0
            for c in range(p):
                t += Ni[a, c] * b[c]
            acc += b[a] * t
        red[e] = acc
    return red


@njit(cache=True, nogil=True, error_model="numpy")
def robust_cofactors_kernel(J, sigma, used, pw, qv, r_min, tag):  # pragma: no cover - jit
    """:func:`robustloc.integrity.fixes.robust_fit_cofactors`, one epoch at a time, by the
    Gauss-Newton kernel's own sandwich (:func:`robustloc.estimators._compiled._sandwich_row`:
    the terms and their order of the NumPy reference,
    :func:`robustloc.estimators.linear.sandwich_qvv`), the unused rows weighted zero.
    ``tag``: a tuple of ``p`` floats (``p <= 3``)."""
    N, n = used.shape
    p = len(tag)
    out = qv.copy()
    Nm = np.zeros((p, p))
    Ni = np.zeros((p, p))
    a = np.zeros(p)
    w0 = np.zeros(n)
    w = np.zeros(n)
    c = np.zeros(n)
    for e in range(N):
        full = True
        for i in range(n):
            w0[i] = 0.0
            w[i] = 0.0
            if used[e, i]:
                s = sigma[e, i]
                f = pw[e, i]
                f = 0.0 if not f == f else min(max(f, 0.0), 1.0)
                if f != 1.0:
                    full = False
                w0[i] = 1.0 / (s * s)
                w[i] = f * w0[i]
        if full:
            continue  # the fit's weights are the a-priori ones: qv as it is
        Je = J[e]
        if not _sandwich_prepare(Je, w0, w, Nm, Ni, a, c, tag):
            continue
        for i in range(n):
            if not (used[e, i] and np.isfinite(qv[e, i])):
                continue
            q = _sandwich_row(Je, w0, w, c, Ni, a, i, tag)
            s = sigma[e, i]
            if math.isfinite(q) and q > r_min * s * s:
                out[e, i] = q
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _weighted_cost(a, h2, xa, d, w):  # pragma: no cover - jit
    """``sum_i ((d_i - |xa - a_i|) w_i)^2`` over the rows with ``w_i > 0`` (a NaN term
    counts 0, as ``np.nan_to_num`` in the NumPy reference)."""
    c = 0.0
    for i in range(a.shape[0]):
        if w[i] > 0.0:
            t = h2[i]
            for q in range(xa.shape[0]):
                t += (xa[q] - a[i, q]) ** 2
            r = (d[i] - math.sqrt(t)) * w[i]
            if math.isfinite(r):
                c += r * r
    return c


@njit(cache=True, nogil=True, error_model="numpy")
def least_squares_resolution_kernel(a, h2, x0, res, sigma, keep, iterations, halvings,
                                    tol, extent, tag):  # pragma: no cover - jit
    """``(x_ls, v_ls, J_ls)`` of :func:`robustloc.integrity.fixes.least_squares_resolution`,
    one epoch at a time: the same Newton steps (Gauss-Newton's matrix where Newton's is
    not positive definite), the same trust region, halvings and stopping rule as the NumPy
    reference, which walks the batch once per array operation.  ``h2`` are the anchors'
    squared height offsets (zeros without), ``extent`` the trust region (m), ``tag`` a
    tuple of ``p`` floats (the dimension at compile time)."""
    N, m = res.shape
    p = len(tag)
    x_out = np.full((N, p), np.nan)
    v_out = np.full((N, m), np.nan)
    j_out = np.zeros((N, m, p))
    w = np.zeros(m)
    d = np.zeros(m)
    f = np.zeros(m)
    J = np.zeros((m, p))
    xa = np.zeros(p)
    xt = np.zeros(p)
    g = np.zeros(p)
    step = np.zeros(p)
    Ngn = np.zeros((p, p))
    Nn = np.zeros((p, p))
    Igs = np.zeros((p, p))
    Inw = np.zeros((p, p))
    for e in range(N):
        fin = True
        for q in range(p):
            fin = fin and math.isfinite(x0[e, q])
        for q in range(p):
            xa[q] = x0[e, q] if fin else 0.0
        # observed ranges from the fix and its residuals (v = f(x) - d); their weights
        _ranges_jacobian(a, h2, xa, f, J)
        kc = _inverse_sigmas(keep[e], res[e], sigma[e], w)
        for i in range(m):
            d[i] = f[i] - res[e, i]
        if fin and kc > p:
            for _ in range(iterations):
                _ranges_jacobian(a, h2, xa, f, J)
                c0 = 0.0
                csum = 0.0
                for q in range(p):
                    g[q] = 0.0
                    for s2 in range(p):
                        Ngn[q, s2] = 0.0
                        Nn[q, s2] = 0.0
                for i in range(m):
                    if w[i] > 0.0:
                        r = (d[i] - f[i]) * w[i]
                        if not math.isfinite(r):
                            r = 0.0
                        c0 += r * r
                        # Newton's curvature term w^2 r (I - u u^T) / rho (NumPy reference)
                        ci = r * w[i] / max(f[i], 1e-9)
                        csum += ci
                        for q in range(p):
                            aq = J[i, q] * w[i]
                            g[q] += aq * r
                            for s2 in range(p):
                                Ngn[q, s2] += aq * J[i, s2] * w[i]
                                Nn[q, s2] -= J[i, q] * ci * J[i, s2]
                for q in range(p):
                    Nn[q, q] += csum
                    for s2 in range(p):
                        Nn[q, s2] = Ngn[q, s2] - Nn[q, s2]
                newton = _inv_small(Nn, Inw, tag)
                good = _inv_small(Ngn, Igs, tag)
                ln = 0.0
                for q in range(p):
                    acc = 0.0
                    for s2 in range(p):
                        acc += (Inw[q, s2] if newton else Igs[q, s2]) * g[s2]
                    step[q] = acc
                    ln += acc * acc
                good = good or newton
                scale = min(1.0, extent / max(math.sqrt(ln), 1e-300))
                for q in range(p):
                    step[q] = step[q] * scale if good else 0.0
                for _h in range(halvings):
                    for q in range(p):
                        xt[q] = xa[q] + step[q]
                    if not _weighted_cost(a, h2, xt, d, w) > c0:
                        break
                    for q in range(p):
                        step[q] *= 0.5
                ln = 0.0
                for q in range(p):
                    xa[q] += step[q]
                    ln += step[q] * step[q]
                if not (good and math.sqrt(ln) > tol):
                    break
        _ranges_jacobian(a, h2, xa, f, J)
        for i in range(m):
            v_out[e, i] = f[i] - d[i]
            for q in range(p):
                j_out[e, i, q] = J[i, q]
        if fin:
            for q in range(p):
                x_out[e, q] = xa[q]
    return x_out, v_out, j_out
