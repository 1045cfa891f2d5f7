"""RAIM fault detection and exclusion (FDE) and protection levels for SPP (seed 003).

The detector is the integrity layer's iterative data snooping
(:func:`robustloc.integrity.snooping.snoop`), driven by a GNSS re-solver that re-linearizes
the pseudorange model after every exclusion, for all epochs still failing at once:

1. global test of ``v^T P v`` against ``chi2(1 - alpha, n - p)`` with ``alpha`` from the
   B-method for the current redundancy (seed 003, eqs. (3)-(4));
2. on failure, the w-test ``w_i = |v_i| / sqrt(Q_vv,ii)`` (seed 003, eqs. (1)-(2)); the
   largest above ``N(1 - alpha0/2)`` (3.29) is excluded and the epoch re-solved;
3. repeat while the global test fails and at least one redundant observation remains after
   the exclusion (several faulty satellites are excluded in turn).

A-priori sigmas are the elevation model of :class:`~robustloc.gnss.spp.SppSolver`, frozen at
the first solution.  One receiver clock per constellation: constellations absent from an
epoch get a unit pseudo-observation on their clock column (zero residual, zero redundancy:
never tested, never excluded, and the redundancy ``n - p`` stays right), so one fixed-width
design serves every epoch.

**Protection levels** (Baarda's external reliability plus the fault-free noise, per epoch,
after FDE): a bias equal to the minimal detectable bias ``MDB_i = sigma_i sqrt(lambda0 / r_i)``
on satellite ``i`` is missed by the w-test with probability ``beta0`` (10 %), and moves the
position by ``dx_i = (H^T P H)^-1 H^T P e_i MDB_i``.  With ``dx_i`` in east/north/up and the
a-priori covariance ``C = (H^T P H)^-1`` of the position in ENU::

    HPL = max_i sqrt(dE_i^2 + dN_i^2) + k sqrt(lambda_max(C_EN)),
    VPL = max_i |dU_i|                 + k sqrt(C_UU),          k = N(1 - alpha0/2) = 3.29

over the satellites in the solution; infinite when a satellite that moves the position has
zero redundancy (its fault could not be detected).  The first term is the slope method of
snapshot RAIM (slope_i times sqrt(lambda0)) with the B-method's ``lambda0``, the second the
fault-free noise along the major semi-axis, with the one-dimensional quantile as the WAAS
MOPS does (``K_H d_major``).  That quantile holds along the axis (and for ``VPL``); the
horizontal error's probability of exceeding ``k`` major semi-axes is higher in 2-D: at most
``exp(-k^2 / 2)`` = 0.0045 for a circular ellipse (4.5 ``alpha0``), 0.0015 at axis ratio
0.7, 0.0010 for a thin ellipse.  ``sqrt(chi2.isf(alpha0, 2))`` = 3.72 bounds it at
``alpha0`` whatever the shape (the tracker's choice, :mod:`robustloc.tracking.tracker`);
pass it as ``k_noise`` for that.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import NDArray

from robustloc import status as st
from robustloc.errors import InputError
from robustloc.gnss.corrections import enu_matrix, geodetic
from robustloc.gnss.rinex import NavData, ObsData
from robustloc.gnss.sp3 import PreciseProducts
from robustloc.gnss.spp import SppResult, SppSolver, dops
from robustloc.integrity.bmethod import ALPHA0, BETA0, lambda0, w_critical
from robustloc.integrity.snooping import snoop
from robustloc.integrity.tests import R_MIN, global_and_w_tests, integrity_tests, whiten


def protection_levels(
    H: NDArray[np.float64], sigma: NDArray[np.float64], used: NDArray[np.bool_],
    xyz_m: NDArray[np.float64], lam0: float, k_noise: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Horizontal and vertical protection levels (m) from MDB-sized faults (see module doc).

    See :func:`protection_levels_and_mdb` for the parameters.
    """
    hpl, vpl, _ = protection_levels_and_mdb(H, sigma, used, xyz_m, lam0, k_noise)
    return hpl, vpl


def protection_levels_and_mdb(
    H: NDArray[np.float64], sigma: NDArray[np.float64], used: NDArray[np.bool_],
    xyz_m: NDArray[np.float64], lam0: float, k_noise: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """HPL, VPL (N,) and the minimal detectable bias ``MDB_i`` (N, n) of every observation.

    Parameters
    ----------
    H : ndarray (N, n, p)
        Design at the solution; columns 0-2 ECEF position, the rest clocks.
    sigma : ndarray (N, n)
    used : ndarray of bool (N, n)
    xyz_m : ndarray (N, 3)
        Position, for the ENU rotation.
    lam0 : float
        Non-centrality ``lambda0`` of the B-method.
    k_noise : float
        Multiplier of the fault-free standard deviation added to the bias term (0: the
        pure external-reliability bound; :class:`RaimFde` uses ``N(1 - alpha0/2)``).
    """
    N = H.shape[0]
    good = np.all(np.isfinite(xyz_m), axis=1)
    lat, lon, _ = geodetic(np.where(good[:, None], xyz_m, [6378137.0, 0.0, 0.0]))
    R = enu_matrix(lat, lon)
    Henu = H.copy()
    Henu[..., :3] = np.einsum("nij,nsj->nsi", R, np.nan_to_num(H[..., :3]))
    Henu = np.where(np.isfinite(H), Henu, np.nan)
    wh = whiten(Henu, np.where(used, sigma, np.nan), mask=used)
    r = 1.0 - wh.hat_diagonal()
    G = np.einsum("kpq,kiq->kip", wh.Ninv, wh.A)[..., :3]  # d position / d (v_i / sigma_i)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.sqrt(lam0 / np.where(r > R_MIN, r, np.nan))
        moves = np.linalg.norm(G, axis=2) > 1e-9
        dx = G * k[..., None]
        dh = np.hypot(dx[..., 0], dx[..., 1])
        du = np.abs(dx[..., 2])
        blind = wh.used & (r <= R_MIN) & moves
        dh = np.where(blind, np.inf, np.where(wh.used & moves, dh, 0.0))
        du = np.where(blind, np.inf, np.where(wh.used & moves, du, 0.0))
    ok = wh.ok & good & (wh.n_used > 0)
    C = wh.Ninv[:, :3, :3]
    cen = C[:, :2, :2]
    tr, det = cen[:, 0, 0] + cen[:, 1, 1], cen[:, 0, 0] * cen[:, 1, 1] - cen[:, 0, 1] ** 2
    lam_max = 0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    with np.errstate(invalid="ignore"):
        sig_h, sig_u = np.sqrt(lam_max), np.sqrt(C[:, 2, 2])
    hpl = np.where(ok, np.max(np.nan_to_num(dh, nan=0.0), axis=1) + k_noise * sig_h, np.nan)
    vpl = np.where(ok, np.max(np.nan_to_num(du, nan=0.0), axis=1) + k_noise * sig_u, np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        mdb = np.where(wh.used & ok[:, None],
                       np.where(r > R_MIN, wh.sigma * k, np.inf), np.nan)  # seed 003 MDB
    return hpl.reshape(N), vpl.reshape(N), mdb


class RaimFde:
    """Snapshot RAIM with fault detection and exclusion of several satellites.

    Parameters
    ----------
    alpha0 : float
        Significance of the w-test (default 0.1 %).
    beta0 : float
        Missed-detection probability of the B-method (default 10 %), defines ``lambda0``.
    alpha : float, optional
        Fixed significance of the global test; default: the B-method value per redundancy.
    max_exclusions : int, optional
        At most this many satellites excluded per epoch (default: as long as redundancy
        allows).
    gn_iterations : int
        Gauss-Newton iterations of each re-solution (default 4).
    check_ambiguity : bool
        After an exclusion, re-test every swap of an excluded satellite for a used one; if
        any alternative also passes the global test the exclusion is not identifiable and
        the epoch is ``unavailable`` (default True).
    rho_min : float
        Only swaps with satellites whose w-test correlates with the excluded one by more
        than this (``|rho_jk|``, before exclusion) are re-tested (default 0.3; a swap with
        an uncorrelated satellite cannot pass the global test for a detectable fault).
    max_subsets : int
        After two or more exclusions, every other subset of at most as many satellites is
        tested too (ambiguous if one passes); skipped when there are more subsets than this.
    """

    def __init__(
        self,
        alpha0: float = ALPHA0,
        beta0: float = BETA0,
        alpha: float | None = None,
        max_exclusions: int | None = None,
        gn_iterations: int = 4,
        check_ambiguity: bool = True,
        rho_min: float = 0.3,
        max_subsets: int = 2000,
    ) -> None:
        self.lambda0 = lambda0(alpha0, beta0)  # validates alpha0, beta0
        self.alpha0 = float(alpha0)
        self.beta0 = float(beta0)
        self.alpha = alpha
        if max_exclusions is not None and max_exclusions < 0:
            raise ValueError("max_exclusions must be >= 0")
        self.max_exclusions = max_exclusions
        self.gn_iterations = int(gn_iterations)
        self.check_ambiguity = bool(check_ambiguity)
        self.rho_min = float(rho_min)
        self.max_subsets = int(max_subsets)

    def _readmit(self, res, resolve, sigma_ext, used, excl) -> NDArray[np.int64]:  # noqa: ANN001
        """Backward step after snooping: try to put every excluded satellite back, one at a
        time; keep it if the global test still passes and its own w-test is below the
        critical value (a good satellite excluded because two faults bent the solution
        towards it).  Updates ``used``/``excl`` in place; returns re-admissions per epoch."""
        N = used.shape[0]
        count = np.zeros(N, dtype=np.int64)
        cand = np.flatnonzero((res.n_excluded >= 2) & (res.status == st.FAULT_EXCLUDED))
        for kk in range(int(res.n_excluded[cand].max()) if cand.size else 0):
            rows = cand[res.exclusion_order[cand, kk] >= 0]
            if rows.size == 0:
                continue
            ks = res.exclusion_order[rows, kk]
            m = used[rows].copy()
            m[np.arange(rows.size), ks] = True
            _, He, ve = resolve(m, rows)
            t = global_and_w_tests(He, ve, sigma_ext[rows], mask=m, alpha=self.alpha,
                                   alpha0=self.alpha0, beta0=self.beta0)
            wk = t.w[np.arange(rows.size), ks]
            keep = t.global_pass & (np.nan_to_num(wk, nan=np.inf) <= t.w_crit)
            r, k = rows[keep], ks[keep]
            used[r, k] = True
            excl[r, k] = False
            count[r] += 1
        return count

    def _ambiguous(self, res, lin, sigma_ext, S: int, used, excl) -> NDArray[np.bool_]:  # noqa: ANN001
        """Epochs whose exclusion is not unique: swapping an excluded satellite for a used
        one (or, after several exclusions, excluding any other subset of at most as many
        satellites) also passes the global test (highly correlated w-tests, seed 003's
        identifiability problem).  Such epochs are reported ``unavailable`` instead of
        trusting a coin toss.  The alternatives are tested on the model linearized at the
        final solution (``lin(rows) -> (H, l)``), which differs from a re-linearized one by
        far less than the noise."""
        N = res.used.shape[0]
        amb = np.zeros(N, dtype=bool)
        cand = np.flatnonzero((res.n_excluded > 0) & (res.status == st.FAULT_EXCLUDED))
        if cand.size == 0:
            return amb
        He, le = lin(cand)
        # w-test correlations rho_jk (seed 003) in the geometry before any exclusion: a swap
        # can only pass the global test when the two w-tests are correlated
        m0 = used[cand] | excl[cand]
        wh0 = whiten(He, sigma_ext[cand], mask=m0)
        r0 = 1.0 - wh0.hat_diagonal()
        for kk in range(int(res.n_excluded[cand].max())):
            k_sat = res.exclusion_order[cand, kk]
            has_k = k_sat >= 0
            has_k[has_k] = excl[cand[has_k], k_sat[has_k]]  # not re-admitted
            kz = np.where(has_k, k_sat, 0)
            ak = wh0.A[np.arange(cand.size), kz]  # (C, p)
            u = np.einsum("cip,cpq,cq->ci", wh0.A, wh0.Ninv, ak)  # U[:, :, k]
            with np.errstate(invalid="ignore", divide="ignore"):
                rho = -u / np.sqrt(r0 * r0[np.arange(cand.size), kz][:, None])
            related = np.abs(np.nan_to_num(rho)) > self.rho_min
            for j in range(S):
                sel = has_k & used[cand, j] & ~amb[cand] & related[:, j]
                rows = cand[sel]
                if rows.size == 0:
                    continue
                ks = res.exclusion_order[rows, kk]
                m = used[rows].copy()
                m[:, j] = False
                m[np.arange(rows.size), ks] = True
                wh = whiten(He[sel], sigma_ext[rows], mask=m)
                v = np.einsum("kip,kp->ki", He[sel], wh.solve(le[sel])) - le[sel]
                t = integrity_tests(wh, np.where(m, v, np.nan), alpha=self.alpha,
                                    alpha0=self.alpha0, beta0=self.beta0)
                amb[rows[t.global_pass]] = True
        # several exclusions: any other subset of at most as many satellites whose
        # exclusion also passes the global test makes the result ambiguous (a wrong pair
        # can pass where single swaps cannot)
        multi = cand[(res.n_excluded[cand] >= 2) & ~amb[cand]]
        for e in multi:
            ci = int(np.flatnonzero(cand == e)[0])
            pool = np.flatnonzero((used[e] | excl[e])[:S])
            m = int(excl[e, :S].sum())
            actual = set(np.flatnonzero(excl[e, :S]).tolist())
            combos = [c for k in range(1, m + 1) for c in itertools.combinations(pool, k)
                      if set(c) != actual]
            if not combos or len(combos) > self.max_subsets:
                continue
            masks = np.repeat((used[e] | excl[e])[None], len(combos), axis=0)
            for r_, c in enumerate(combos):
                masks[r_, list(c)] = False
            Hc = np.repeat(He[ci][None], len(combos), axis=0)
            lc = np.repeat(le[ci][None], len(combos), axis=0)
            sc = np.repeat(sigma_ext[e][None], len(combos), axis=0)
            wh = whiten(Hc, sc, mask=masks)
            v = np.einsum("kip,kp->ki", Hc, wh.solve(lc)) - lc
            t = integrity_tests(wh, np.where(masks, v, np.nan), alpha=self.alpha,
                                alpha0=self.alpha0, beta0=self.beta0)
            amb[e] = bool(np.any(t.global_pass))
        return amb

    def solve(
        self,
        solver: SppSolver,
        obs: ObsData,
        nav: NavData | None = None,
        precise: PreciseProducts | None = None,
        x0: NDArray | None = None,
    ) -> SppResult:
        """SPP of every epoch with FDE; the result carries the test statistics and PLs."""
        P = solver.prepare(obs, nav, precise)
        return self.solve_prepared(solver, P, x0)

    def solve_prepared(self, solver: SppSolver, P, x0: NDArray | None = None) -> SppResult:  # noqa: ANN001
        """As :meth:`solve` on the output of :meth:`SppSolver.prepare` (for benchmarks)."""
        solver.check_prepared(P)
        N, S = P.pr.shape
        K = len(P.systems)
        p = 3 + K
        x = solver.initial_state(P, x0)
        x, H, v, use, el, az, sig, conv, n_it, absent = solver._gauss_newton(
            P, np.arange(N), x, P.avail, solver.max_iter + 5, True
        )
        sig_fixed = np.where(use, sig, np.nan)
        xcur = x.copy()
        pseudo_H = np.zeros((K, p))
        pseudo_H[np.arange(K), 3 + np.arange(K)] = 1.0

        first = {"pending": True}
        mask0 = np.concatenate([use, absent], axis=1)
        v0 = np.where(use, v, np.nan)

        def resolve(mask: NDArray[np.bool_], rows: NDArray[np.int64]):  # noqa: ANN202
            if first["pending"] and rows.size == N and np.array_equal(mask, mask0):
                first["pending"] = False  # the initial solution is already at hand
                He = np.concatenate([H, np.broadcast_to(pseudo_H, (N, K, p))], axis=1)
                return x, He, np.concatenate([v0, np.zeros((N, K))], axis=1)
            allowed = mask[:, :S]
            xr, Hr, vr, *_ = solver._gauss_newton(
                P, rows, xcur[rows], allowed, self.gn_iterations, False, sig_fixed[rows]
            )
            xcur[rows] = xr
            He = np.concatenate([Hr, np.broadcast_to(pseudo_H, (len(rows), K, p))], axis=1)
            ve = np.concatenate([vr, np.zeros((len(rows), K))], axis=1)
            return xr, He, ve

        def linearized(rows: NDArray[np.int64]):  # noqa: ANN202
            """Design and prefit residuals ``l = z - f(x)`` of every satellite at ``x``."""
            xr = np.where(np.all(np.isfinite(res.x[rows]), axis=1)[:, None], res.x[rows],
                          xcur[rows])
            pred, Hr, *_ = solver._model(P, rows, xr)
            He = np.concatenate([Hr, np.broadcast_to(pseudo_H, (len(rows), K, p))], axis=1)
            le = np.concatenate([P.pr[rows] - pred, np.zeros((len(rows), K))], axis=1)
            return He, le

        sigma_ext = np.concatenate([sig_fixed, np.ones((N, K))], axis=1)
        res = snoop(
            resolve, mask0, sigma_ext, alpha=self.alpha, alpha0=self.alpha0, beta0=self.beta0,
            max_exclusions=self.max_exclusions,
        )
        used_ext, excl_ext = res.used.copy(), res.excluded.copy()
        readmitted = self._readmit(res, resolve, sigma_ext, used_ext, excl_ext)
        status = res.status.copy()
        ambiguous = np.zeros(N, dtype=bool)
        if self.check_ambiguity:
            ambiguous = self._ambiguous(res, linearized, sigma_ext, S, used_ext, excl_ext)
            status[ambiguous] = st.UNAVAILABLE
        used = used_ext[:, :S]
        excluded = excl_ext[:, :S]
        xs, vs, ws = res.x.copy(), res.residuals.copy(), res.w.copy()
        gstat, gcrit, dof = res.global_stat.copy(), res.global_crit.copy(), res.dof.copy()
        rr = np.flatnonzero(readmitted > 0)
        if rr.size:  # re-solve the epochs that got satellites back
            xr, He, ve = resolve(used_ext[rr], rr)
            t = global_and_w_tests(He, ve, sigma_ext[rr], mask=used_ext[rr], alpha=self.alpha,
                                   alpha0=self.alpha0, beta0=self.beta0)
            xs[rr], vs[rr], ws[rr] = xr, np.where(used_ext[rr], ve, np.nan), t.w
            gstat[rr], gcrit[rr], dof[rr] = t.global_stat, t.global_crit, t.dof
        # final geometry for residuals, DOPs and protection levels
        xf = np.where(np.all(np.isfinite(xs), axis=1)[:, None], xs, xcur)
        _, pred_H, el, az, _, _ = solver._model(P, np.arange(N), xf)
        vfin = vs[:, :S]
        absent_f = np.einsum(
            "ks,sj->kj", used.astype(float),
            (P.sys_idx[:, None] == np.arange(K)[None, :]).astype(float),
        ) == 0
        # the clocks of constellations without a satellite in use pinned by pseudo-rows, as
        # in the tests (without them a zero clock column made every such epoch's
        # protection levels NaN: the GNSS review, 2026-12-04); a pseudo-row moves no
        # position, so it adds no slope
        hpl, vpl, mdb = protection_levels_and_mdb(
            np.concatenate([pred_H, np.broadcast_to(pseudo_H, (N, K, p))], axis=1),
            np.concatenate([sig_fixed, np.ones((N, K))], axis=1),
            np.concatenate([used, absent_f], axis=1), xf[:, :3], self.lambda0,
            w_critical(self.alpha0))
        mdb = mdb[:, :S]
        # RTKLIB-like geometry screen on top of the tests
        dop = dops(pred_H, used, xf[:, :3], absent_f)
        gd = dop[:, 0]
        status[st.among(status, (st.OK, st.FAULT_EXCLUDED)) & ~(gd <= solver.max_gdop)] = (
            st.ILL_CONDITIONED
        )
        # the project's majority rule (robustloc.status: a fix kept by a minority of its
        # observations is unavailable): 12 of 20 satellites excluded was fault_excluded,
        # usable, 91-213 m off against an hpl of 14-49 m (the spp review)
        n_excl = excluded.sum(axis=1)
        n_seen = n_excl + used.sum(axis=1)
        status[(status == st.FAULT_EXCLUDED) & (2 * n_excl >= n_seen)] = st.UNAVAILABLE
        extra = {
            "global_stat_initial": res.global_stat_initial,
            "global_crit_initial": res.global_crit_initial,
            "global_stat": gstat,
            "global_crit": gcrit,
            "dof": dof,
            "detected": res.detected,
            "ambiguous": ambiguous,
            "readmitted": readmitted,
            "n_excluded": excluded.sum(axis=1),
            "w": ws[:, :S],
            "hpl_m": np.where(st.among(status, st.USABLE), hpl, np.nan),
            "vpl_m": np.where(st.among(status, st.USABLE), vpl, np.nan),
            "mdb_m": mdb,
            "lambda0": self.lambda0,
            "w_crit": res.w_crit,
        }
        return solver._result(P, xf, pred_H, vfin, used, el, az, sig, conv, n_it, absent_f,
                              excluded, extra, status=status, dop=dop)


def inject_faults(
    obs: ObsData, faults: dict[str, float], from_t_gps_s: float | None = None,
    until_t_gps_s: float | None = None,
) -> ObsData:
    """Copy of ``obs`` with biases added to every code observation of some satellites.

    Parameters
    ----------
    faults : dict sat -> bias (m)
        E.g. ``{"G11": 20.0}``.  Every pseudorange type (``C*``, ``P*``) gets the bias, so
        single-frequency and ionosphere-free solutions see the same fault.
    from_t_gps_s, until_t_gps_s : float, optional
        Time window (GPS seconds) of the fault; default the whole file.
    """
    rows = np.ones(obs.n_epochs, dtype=bool)
    if from_t_gps_s is not None:
        rows &= obs.t_gps_s >= from_t_gps_s
    if until_t_gps_s is not None:
        rows &= obs.t_gps_s <= until_t_gps_s
    new = {k: v.copy() for k, v in obs.obs.items()}
    for sat, bias in faults.items():
        if sat not in obs.sats:
            raise InputError(f"--inject: satellite {sat} is not in the file (has "
                             f"{', '.join(obs.sats)})", obs.path)
        j = obs.sats.index(sat)
        for name, arr in new.items():
            if name[0] in "CP":
                arr[rows, j] += float(bias)
    return ObsData(obs.path, obs.version, obs.t_gps_s, list(obs.sats), new, obs.approx_xyz_m,
                   obs.epoch_flag, obs.line, dict(obs.header), obs.invalid,
                   obs.invalid_cells)
