"""Position fixes from ranges or RSSI to known anchors: every method, batched over epochs.

:class:`Locator` holds the settings (method, solver, noise level) and solves a whole log
at once: ``anchors (m, dim)``, ``values (N, m)`` with NaN for an anchor not heard.

Methods
-------
``ls``
    The paper's linearized difference system, seed 000 eq. (3), ``P = I``.
``wls``
    The same system weighted by ``1 / (d_i^2 s_i^2)`` (a row of the difference system
    carries the range error times ``d_i``; ``s_i`` the range standard deviation: constant
    for measured ranges, ``∝ d_i`` for ranges converted from RSSI, seed 001 eq. (4)).
``nls``
    Gauss-Newton on the raw observations (ranges, or RSSI in dB for RSSI input by default),
    initialised from ``ls``; covariance of the fix.
``huber``, ``hampel``, ``igg``, ``igg3``
    Robust IRLS (seed 000 eqs. (5)-(7)) on the nonlinear observation equations
    (``solver="nonlinear"``, default) or on the paper's linearized system
    (``solver="linearized"``).
``lege``
    LEGE (seed 000 sec. 2.4) on the linearized system, or on the Gauss-Newton
    linearization followed by a re-solve without the located gross errors.
``snooping``
    Iterative w-test data snooping with the B-method (seed 003), Gauss-Newton re-solved
    after each exclusion; needs the a-priori ``sigma``.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace
from functools import lru_cache
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from robustloc import status as st
from robustloc._stats import norm_ppf, t_ppf
from robustloc.estimators.linear import LinearFit, irls, lege, sandwich_qvv, solve_wls
from robustloc.estimators.nonlinear import gauss_newton
from robustloc.estimators.solution import Solution
from robustloc.models.geometry import collinear as _collinear
from robustloc.models.geometry import unique_rows as _unique_rows
from robustloc.models.ranging import LN10, RangeModel, RssiModel
from robustloc.robust.scale import MAD_NORMAL, mad_scale
from robustloc.robust.weights import Huber, get_weight

Array = NDArray[np.float64]

METHODS = ("ls", "wls", "nls", "huber", "hampel", "igg", "igg3", "asym", "lege", "snooping")
#: Other names of ``METHODS``: ``asymmetric-igg``, the weight's name in ``filter``,
#: ``fuse`` and ``track``, is ``asym`` (its constants are ``locate``'s, below).
METHOD_SYNONYMS = {"asymmetric-igg": "asym"}
#: The method ``robustloc locate`` uses when none is named (chosen by measurement on the
#: shared real data and the seed-000 simulation: the report's "out of the box" section).
DEFAULT_METHOD = "auto"
ROBUST = ("huber", "hampel", "igg", "igg3", "asym")
#: A standardized residual beyond this many sigma counts as a gross error in
#: :meth:`Locator.log_statistics` (Gaussian: two-sided probability 6.3e-5).
GROSS_U = 4.0
#: How far :meth:`Locator.log_statistics` lets each anchor's scale weight its fits: the
#: weights use ``common (s_j / common) ** w`` with ``common`` the scale pooled over every
#: anchor; ``w = 1`` is the full variance-component iteration, ``w = 0`` equal weights.
#: Half a step in log (a shrinkage toward the pooled scale, the usual guard against the
#: runaway of variance components at low redundancy) measured best of 0, 0.5 and 1 over
#: the shared real logs and the seed-000 simulation (issue 10; equal weights took the
#: corridor to 3.57 m but cost scheme 1: 0.9993 of nls over seeds 1-10, 1.006 on the
#: report's seed).  Against the full iteration, the
#: wifi-rtt-rss corridor's default RMS 4.04 -> 3.78 m, p95 6.99 -> 6.09 m and availability
#: 99.0 -> 99.6 %; uwb-labyrinth 0.215 -> 0.197 m; the others within 1 %; the seed-000
#: scheme 1 mean over seeds 1-10 unchanged (0.9955 of nls).  The full iteration read the
#: real logs' per-anchor biases as noise and spread the anchors' scales far wider than their
#: noise measured against the truth (the standard deviation of the log ratio of scale to
#: noise: 0.43 on the corridor, 0.24 with half a step; closer on 6 of the 7 shared sets);
#: on Gaussian noise of unequal anchors it is unbiased where half a step leaves the
#: quietest anchor's scale high (a conservative error: its tests lose power): 25-40 % at
#: 4:1, 3.3x at 8:1 (five anchors, sd 0.05-0.44 m; the locate review of 2026-12-06).
LOG_SCALE_WEIGHTING = 0.5
#: The one-sided level of Student's t that widens the log's scale for the redundancy it
#: was estimated with (:meth:`Locator.log_statistics`): that of the bounds' default
#: ``k = N(1 - alpha0 / 2)`` with ``alpha0 = 0.001`` (robustloc.integrity.bmethod), the
#: quantile the per-epoch scale's widening uses too (robustloc.integrity.fixes.protect).
LOG_SCALE_T_LEVEL = 0.9995
#: The Gaussian efficiency of the MAD as a scale estimate, 8 phi(c)^2 c^2 with
#: c = 0.6745 (Huber 1981, sec. 5.4): its variance is that of a standard deviation of
#: 0.37 times the degrees of freedom (:meth:`Locator.log_statistics`).
MAD_EFFICIENCY = 0.3675
#: A log's scale from fewer equivalent degrees of freedom than this is widened by Student's
#: t (:meth:`Locator.log_statistics`); from more it is taken as known: t's quantile
#: (:data:`LOG_SCALE_T_LEVEL`) is then within 11 % of the normal one (the labyrinth's 59
#: epochs give about 40, a 7 % widening left out; 5 000 residuals 0.2 %).
LOG_SCALE_MIN_DOF = 30.0


def method_weight(method: str, **params: float):
    """The weight function of a robust method: the paper's by name, and ``asym`` the
    asymmetric IGG of seed 002 eq. (14) turned to ranges: the residual ``v = f(x) - d`` of
    a range that reads long (NLOS, a faded RSSI) is negative, so the negative branch
    (linear descent of psi to zero at ``-c``) takes the long ranges and the IGG-III branch
    up to ``k1`` the short ones; ``k0 = 1.5, c = 3, k1 = 5``: a long range is rejected from
    3 sigma, a short one (rare: the direct path cannot be beaten) only from 5."""
    if method == "asym":
        return get_weight("asymmetric-igg", **{"k0": 1.5, "k1": 5.0, "c": 3.0, **params})
    return get_weight(method, **params)


class _WhitenedLinear:
    """The linear model ``f(x) = H x`` of whitened design rows ``H`` (K, m, p), in the
    interface :func:`~robustloc.estimators.nonlinear.gauss_newton` solves."""

    def __init__(self, H: Array) -> None:
        self.H = H

    def subset(self, rows: NDArray[np.int64]) -> _WhitenedLinear:
        return _WhitenedLinear(self.H[rows])

    def predict(self, x: Array) -> Array:
        return np.einsum("kip,kp->ki", self.H, x)

    def jacobian(self, x: Array) -> Array:
        return self.H


#: Seed of the Gaussian draws of :func:`_gaussian_mad_factor` (fixed: a log's scale is a
#: function of the log).
MAD_FACTOR_SEED = 20261204
#: Standardized residuals :func:`_gaussian_mad_factor` draws, about (every k-th epoch of
#: the log's sample, or its epochs repeated with new draws, at most 32 times).  The MAD of
#: ``n`` Gaussian values alone has a relative standard error of ``1.166 / sqrt(n)``, 0.8 %
#: here, the same for every log of one layout; as a ratio to the least-squares MAD of the
#: same draws the factor varies by about 0.1 % between seeds (0.06 % at 50 000 draws:
#: 0.9872-0.9885 at Huber ``c = 2`` on six anchors), against the 1.1-5 % it corrects.  The
#: draws add a few hundredths of a second to the first pass of a 10-anchor log (about
#: 0.13 s at 50 000 draws, which cost ``bench_locate.py``'s ``auto`` row a tenth of its
#: speed).
MAD_FACTOR_DRAWS = 20_000


def _gaussian_mad_factor(fit_loc: Locator, Jw: Array, heard: NDArray[np.bool_],
                         r: Array) -> float:
    """What ``med |u| / 0.6745`` of :meth:`Locator.log_statistics` reads for Gaussian noise
    of unit scale, at the log's own geometry.

    A Huber-type fit with a known scale leaves its standardized residuals more peaked than
    Gaussian: it follows the small residuals and lets the large ones be (down-weighted
    rows keep their error), so the MAD of Gaussian residuals of unit variance reads low
    (the integrity review: 0.983 at Huber ``c = 2``, 0.943 at ``c = 1.5``, 0.996 in the
    least-squares limit, on six anchors), and a test at that scale rejects more often than
    its alpha (1.27 % of fault-free epochs against the B-method's 1.10 %).  The factor
    depends on the weight, its constants and the redundancy, so it is measured on the log
    itself: unit Gaussian noise on the fits' whitened design rows ``Jw`` (K, m, p; the
    rows the epochs ``heard``), the same robust fit (``fit_loc``'s weight, scale 1,
    :func:`~robustloc.estimators.nonlinear.gauss_newton` as :meth:`Locator.solve` runs
    it) and the same standardization (``r``: the redundancy numbers, NaN where
    unusable; :func:`~robustloc.estimators.linear.sandwich_qvv`), pooled over the anchors
    (an anchor's own factor differs from the pooled one by less than the noise of its
    estimate), from :data:`MAD_FACTOR_DRAWS` residuals, as the ratio of their MAD to the
    MAD of the least-squares residuals of the same draws (unit scale exactly: a control
    variate).  In each epoch the draws go to the heard observations in the order of their
    redundancy numbers (largest first), a function of the geometry alone: the factor, like
    the fixes, does not depend on the anchors' order, the frame's rotation or an unheard
    anchor (a symmetric layout's equal numbers trade draws between mirror images, which
    leaves the residuals' median as it is).

    Returns
    -------
    float
        The factor; 1.0 where nothing could be measured.
    """
    p = Jw.shape[2]
    r = np.where(heard, r, np.nan)  # (an unheard row's zero design row has r = 1)
    rows = np.flatnonzero(np.isfinite(r).any(axis=1))
    n_res = int(np.sum(np.isfinite(r[rows]))) if rows.size else 0
    if n_res == 0:
        return 1.0
    if n_res > MAD_FACTOR_DRAWS:  # every k-th epoch: about MAD_FACTOR_DRAWS residuals
        rows = rows[:: -(-n_res // MAD_FACTOR_DRAWS)]
        n_res = int(np.sum(np.isfinite(r[rows])))
    reps = int(min(32, -(-MAD_FACTOR_DRAWS // n_res)))
    H = np.tile(Jw[rows], (reps, 1, 1))
    hd = np.tile(heard[rows], (reps, 1))
    rr = np.tile(r[rows], (reps, 1))
    # each epoch's heard rows by decreasing redundancy (its own a-priori fit's 1 - h)
    with np.errstate(all="ignore"):
        Hh = np.where(hd[..., None], H, 0.0)
        Ninv = np.linalg.pinv(np.einsum("kip,kiq->kpq", Hh, Hh))
        r_all = 1.0 - np.einsum("kip,kpq,kiq->ki", Hh, Ninv, Hh)
    key = np.where(hd & np.isfinite(r_all), r_all, -np.inf)
    width = int(hd.sum(axis=1).max())
    # the heard rows, in that order, in the first columns (the unheard ones dropped: the
    # arithmetic below is then the same whatever the anchors' number and order)
    idx = np.argsort(-key, axis=1, kind="stable")[:, :width]
    H = np.take_along_axis(H, idx[..., None], axis=1)
    hd = np.take_along_axis(hd, idx, axis=1)
    rr = np.take_along_axis(rr, idx, axis=1)
    draws = np.random.default_rng(MAD_FACTOR_SEED).standard_normal((hd.shape[0], width))
    e = np.where(hd, draws, np.nan)
    wf = method_weight(fit_loc.method, **fit_loc.weight_params)
    fit = gauss_newton(_WhitenedLinear(H), e, np.zeros((H.shape[0], p)), 1.0, weight=wf,
                       scale=1.0, min_scale=0.0, max_iter=fit_loc.max_iter, tol=fit_loc.tol,
                       min_obs=p + 1, rel_tol=fit_loc.rel_tol, warmup=False)
    ls = solve_wls(H, e, hd.astype(float))
    with np.errstate(all="ignore"):
        v = np.einsum("kip,kp->ki", H, fit.x) - e
        q = sandwich_qvv(H, hd.astype(float), np.where(hd, np.nan_to_num(fit.w), 0.0), rr)
        u = np.abs(v) / np.sqrt(np.where(np.isfinite(rr), q, np.nan))
        # control variate: the least-squares fit of the same draws, whose standardized
        # residuals v / sqrt(r) are exactly N(0, 1) (seed 003's Q_vv), so their MAD's
        # own sampling error divides out (seeds 1-4: 0.9862-0.9895 alone, 0.9885-0.9893
        # as the ratio, at Huber c = 2 on the review's six anchors)
        v_ls = np.einsum("kip,kp->ki", H, ls.x) - e
        u_ls = np.abs(v_ls) / np.sqrt(rr)
    keep = st.among(fit.status, st.USABLE)[:, None] & np.isfinite(u) & np.isfinite(u_ls)
    if not keep.any():
        return 1.0
    kappa = float(np.median(u[keep]) / np.median(u_ls[keep]))
    return kappa if np.isfinite(kappa) and kappa > 0 else 1.0


def _anchor_key(a: ArrayLike) -> tuple[bytes, tuple[int, ...]]:
    """Hashable key of an anchor array for the caches of anchor-only work (a solve of a
    few epochs -- a tracker's check, a live service's message -- would otherwise redo it
    each call: about half of such a call's time)."""
    a = np.ascontiguousarray(a, dtype=float)
    return a.tobytes(), a.shape


def _from_key(key: bytes, shape: tuple[int, ...]) -> Array:
    return np.frombuffer(key, dtype=float).reshape(shape)


def _frozen(*arrays: NDArray) -> None:
    for arr in arrays:
        arr.setflags(write=False)


#: The iterative solvers' least-median-of-squares start tries every minimal anchor subset
#: when there are at most this many (2-D: up to 6 anchors; 3-D: up to 6), and a fixed
#: pseudo-random choice of about this many otherwise (:func:`minimal_subsets`).  Trying
#: every subset is not better: on the seed-000 corridor (10 beacons, 120 subsets; seeds 1-10)
#: IGG's mean error rose 1.60 -> 1.76 m (scheme 1) and 2.44 -> 2.64 m (scheme 2) with all
#: of them, and the robust fits took twice as long (measured 2026-12-02).
MAX_SUBSETS = 24


def canonical_rank(anchors: ArrayLike) -> NDArray[np.int64]:
    """Each anchor's rank in an order that depends on where the anchors are, not on the
    order of the anchors file: by distance from their centroid (equal to 1e-9 of the
    largest), then by x, y and z (equal anchors by index).

    The iterative solvers' start breaks ties between equal ranges and chooses minimal
    subsets in this order (:meth:`Locator._initial`), so listing the anchors in another
    order gives the same fixes.  The distance comes first so that the order, and the fixes,
    also survive a rotation or translation of the frame, unless two anchors lie at the
    same distance from the centroid (a regular grid) and the choice reaches them."""
    return _canonical_rank_cached(*_anchor_key(anchors))


#: Entries of the caches that :meth:`Locator._initial` fills once per pattern of anchors
#: heard on a large site (:func:`_heard_groups`; each 1-3 kB, so at most some 40 MB): a
#: moving tag's patterns recur, and the log-scale pass solves each epoch four times.  With
#: 4 096, the 7 300 patterns of 20 000 epochs on a site of 900 anchors were chosen 29 458
#: times (``robustloc locate`` 39 s); with 16 384, once each (33 s).
_PATTERN_CACHE = 16384


@lru_cache(maxsize=_PATTERN_CACHE)
def _canonical_rank_cached(key: bytes, shape: tuple[int, ...]) -> NDArray[np.int64]:
    a = _from_key(key, shape)
    if a.ndim != 2 or a.shape[0] == 0:
        return np.arange(shape[0], dtype=np.int64)
    with np.errstate(all="ignore"):
        dist = np.linalg.norm(a - np.nanmean(a, axis=0), axis=1)
        top = np.nanmax(dist) if np.any(np.isfinite(dist)) else 1.0
        level = np.round(dist / (1e-9 * max(float(top), 1e-300)))
    order = np.lexsort(tuple(a.T[::-1]) + (level,))
    rank = np.empty(shape[0], dtype=np.int64)
    rank[order] = np.arange(shape[0])
    _frozen(rank)
    return rank


def _sane_anchors(a: Array) -> NDArray[np.bool_]:
    """Anchors whose coordinates make sense for the layout: finite and within 20 times the
    median distance (at least 1 m) of the median anchor.  An anchor outside (a typo such as
    1e200) is not used at all: it would otherwise change every start candidate and the
    anchors' area while no epoch can hear it.  A property of the anchors file alone, so a
    fix never depends on which other epochs are solved with it (cached per anchor array;
    the result is read-only)."""
    return _sane_anchors_cached(*_anchor_key(a))


@lru_cache(maxsize=64)
def _sane_anchors_cached(key: bytes, shape: tuple[int, ...]) -> NDArray[np.bool_]:
    a = _from_key(key, shape)
    with np.errstate(all="ignore"):
        fin = np.all(np.isfinite(a), axis=1)
        if np.any(fin):
            med = np.median(a[fin], axis=0)
            dist = np.linalg.norm(a - med, axis=1)
            fin = fin & (dist <= 20.0 * max(float(np.median(dist[fin])), 1.0))
    _frozen(fin)
    return fin


def _area(a: Array) -> tuple[Array, float]:
    """The anchors' area: a disc (ball) around their centroid, 1.25 times the farthest
    anchor's distance (at least 1 m).  Rotation- and translation-invariant, unlike a
    bounding box, so the solvers' results move rigidly with the anchors.  Cached per
    anchor array (the centre is read-only)."""
    return _area_cached(*_anchor_key(a))


@lru_cache(maxsize=64)
def _area_cached(key: bytes, shape: tuple[int, ...]) -> tuple[Array, float]:
    a = _from_key(key, shape)
    centre = a.mean(axis=0)
    _frozen(centre)
    return centre, 1.25 * max(float(np.max(np.linalg.norm(a - centre, axis=1))), 1.0)


def _rescue_grid(a: Array, centre: Array, radius: float) -> Array:
    """The rescue's grid (:meth:`Locator._rescue`): the square of side ``2 radius`` around
    the anchors' centre, 24 x 24 points in 2-D (10 x 10 x 5 in 3-D, the height from the
    box's bottom to its top), its sides along the horizontal direction from the centre to
    the anchor farthest from it (:func:`canonical_rank`'s last; the next where that one
    lies straight above the centre) and across it.  A grid along the frame's axes depended
    on the frame's rotation, and so did a rescued fix (the locate review of 2026-12-06:
    igg3 fixes 6.6 m apart in a frame turned by 0.7 rad); this one turns with the anchors
    and does not depend on their order in the file."""
    dim = a.shape[1]
    off = a[:, :2] - centre[:2]
    order = np.argsort(-canonical_rank(a))
    far = order[np.hypot(off[order, 0], off[order, 1]) > 1e-9 * radius]
    u = off[far[0]] / np.hypot(*off[far[0]]) if far.size else np.array([1.0, 0.0])
    v = np.array([-u[1], u[0]])
    per = 24 if dim == 2 else 10
    s = np.linspace(-radius, radius, per)
    su, sv = np.meshgrid(s, s, indexing="ij")
    xy = centre[:2] + su.reshape(-1, 1) * u + sv.reshape(-1, 1) * v
    if dim == 2:
        return xy
    zs = np.linspace(centre[2] - radius, centre[2] + radius, 5)
    return np.column_stack([np.repeat(xy, zs.size, axis=0), np.tile(zs, xy.shape[0])])


#: 3-D anchors whose spread out of their best-fitting plane is below this fraction of
#: their largest spread in it (square root of the smallest over the largest eigenvalue of
#: their scatter matrix) are coplanar for the solvers' start (:func:`_off_plane`).
COPLANAR_RATIO = 0.05


def _off_plane(a: Array, x0: Array, heard: NDArray[np.bool_] | None = None) -> Array:
    """3-D starts moved off the plane of coplanar anchors, to its lower side.

    Ranges from anchors in one plane (all on the ceiling, say) fit a point and its mirror
    image across the plane equally well, and on the plane itself the range Jacobian has no
    component across it: Gauss-Newton started there never leaves it (measured: every
    epoch ``ill_conditioned`` with 8 ceiling anchors and the tag 1-2.5 m below).  The
    start is moved to the side of the plane towards lower ``z`` (ceiling-mounted anchors
    above the tags; a vertical plane: towards negative ``x``, then ``y``), at least
    a tenth of the anchors' area radius away from it, keeping its distance when larger.
    The integrity check covers the mirror solution (its vertical protection level spans
    both sides when the data cannot tell them apart).  Other layouts: ``x0`` unchanged.

    The plane is that of the anchors each epoch *hears* (``heard (N, m)``, default all):
    a layout that is not coplanar as a whole (ceiling anchors and two near the floor)
    still leaves an epoch that hears only the ceiling's in the ambiguous case (measured:
    99.9 % of such epochs ``ill_conditioned`` before this took the heard anchors).  Three
    heard anchors always span a plane; collinear ones (no plane) and fewer than three
    leave the start unchanged.  Planes are found once per distinct heard pattern.
    """
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 3 or not np.all(np.isfinite(a)):
        return x0
    if heard is None or bool(np.all(heard)):
        plane = _plane_cached(*_anchor_key(a))
        if plane is None:
            return x0
        c, nrm, off = (v[None] for v in (plane[0], plane[1], np.asarray(plane[2])))
        inverse = np.zeros(x0.shape[0], dtype=np.intp)
    else:
        patterns, inverse = _unique_rows(np.asarray(heard, dtype=bool))
        c, nrm, off = _planes(a, patterns)
    with np.errstate(invalid="ignore"):
        cc, nn = c[inverse], nrm[inverse]
        s = np.einsum("ij,ij->i", x0 - cc, nn)
        moved = x0 + (np.maximum(np.abs(s), off[inverse]) - s)[:, None] * nn
    return np.where(np.isfinite(cc[:, :1]), moved, x0)


@lru_cache(maxsize=64)
def _plane_cached(key: bytes, shape: tuple[int, ...]) -> tuple[Array, Array, float] | None:
    """Centre, unit normal (towards lower z, then x, y) and start offset of coplanar
    anchors; None when they are not coplanar, or collinear (no plane)."""
    a = _from_key(key, shape)
    c = a.mean(axis=0)
    ev, vec = np.linalg.eigh((a - c).T @ (a - c))
    if not ev[-1] > 0 or np.sqrt(max(ev[0], 0.0) / ev[-1]) >= COPLANAR_RATIO:
        return None
    if np.sqrt(max(ev[1], 0.0) / ev[-1]) < COPLANAR_RATIO:  # collinear: no plane
        return None
    nrm = vec[:, 0]
    lead = next((k for k in (2, 0, 1) if abs(nrm[k]) > 1e-9), 2)
    if nrm[lead] > 0:  # oriented towards lower z (then x, y)
        nrm = -nrm
    _frozen(c, nrm)
    return c, nrm, 0.1 * _area(a)[1]


def _planes(a: Array, patterns: NDArray[np.bool_]) -> tuple[Array, Array, Array]:
    """:func:`_plane_cached` for the anchors of each row of ``patterns (P, m)`` at once:
    centres ``(P, 3)`` (NaN where no plane: not coplanar, collinear or fewer than three
    anchors), unit normals ``(P, 3)`` and start offsets ``(P,)`` (batched: a log whose
    epochs hear many different subsets costs one ``eigh`` call, not one per subset)."""
    k = patterns.astype(float)
    cnt = k.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        c = (k @ a) / cnt[:, None]
        d = np.where(patterns[..., None], a[None] - c[:, None], 0.0)
        ev, vec = np.linalg.eigh(np.nan_to_num(np.einsum("pmi,pmj->pij", d, d)))
        top = ev[:, -1]
        flat = np.sqrt(np.maximum(ev[:, 0], 0.0) / top) < COPLANAR_RATIO
        line = np.sqrt(np.maximum(ev[:, 1], 0.0) / top) < COPLANAR_RATIO
    ok = (cnt >= 3) & (top > 0) & flat & ~line
    nrm = vec[:, :, 0]
    # oriented towards lower z, then x, then y: the first of those with a component
    big = np.abs(nrm[:, [2, 0, 1]]) > 1e-9
    lead = np.array([2, 0, 1])[np.argmax(big, axis=1)]
    lead = np.where(big.any(axis=1), lead, 2)
    nrm = np.where((nrm[np.arange(len(nrm)), lead] > 0)[:, None], -nrm, nrm)
    radius = np.sqrt(np.max(np.sum(d * d, axis=2), axis=1))
    off = 0.1 * 1.25 * np.maximum(radius, 1.0)  # a tenth of _area's radius
    return np.where(ok[:, None], c, np.nan), nrm, off


def _clip_disc(x: Array, centre: Array, radius: float) -> Array:
    """Pull points outside the disc back onto its boundary (NaN stays NaN)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.linalg.norm(x - centre, axis=1, keepdims=True)
        f = np.where(r > radius, radius / r, 1.0)
    return centre + (x - centre) * f


def _rows(fit: LinearFit, idx: NDArray) -> LinearFit:
    """The epochs ``idx`` of a fit."""
    return LinearFit(
        x=fit.x[idx], v=fit.v[idx], w=fit.w[idx], qvv=fit.qvv[idx], sigma0=fit.sigma0[idx],
        cov=fit.cov[idx], n_used=fit.n_used[idx], iterations=fit.iterations[idx],
        converged=fit.converged[idx], status=fit.status[idx],
        extra={k: v[idx] for k, v in fit.extra.items() if isinstance(v, np.ndarray)},
    )


def _merge(fit: LinearFit, sub: LinearFit, idx: NDArray, take: NDArray[np.bool_],
           inplace: bool = False) -> LinearFit:
    """Replace epochs ``idx[take]`` of ``fit`` by the matching rows of ``sub`` (in
    ``fit``'s own arrays with ``inplace=True``: for a fit no one else holds, it saves a
    copy of every array of the batch)."""
    out = {}
    for name in ("x", "v", "w", "qvv", "sigma0", "cov", "n_used", "iterations", "converged",
                 "status"):
        arr = getattr(fit, name) if inplace else getattr(fit, name).copy()
        arr[idx[take]] = getattr(sub, name)[take]
        out[name] = arr
    extra = dict(fit.extra)
    for k, v in sub.extra.items():
        if k in extra and isinstance(v, np.ndarray) and extra[k].shape[1:] == v.shape[1:]:
            e = extra[k] if inplace else extra[k].copy()
            e[idx[take]] = v[take]
            extra[k] = e
    return LinearFit(**out, extra=extra)


def linearized_system(
    anchors: ArrayLike,
    ranges: ArrayLike,
    height_offset: ArrayLike | None = None,
    reference: str = "first",
) -> tuple[Array, Array, NDArray[np.int64], Array]:
    """The paper's difference system ``G Z = h`` (seed 000 eq. (3)), batched.

    The reference is the first anchor heard in each epoch (the paper's choice,
    ``reference="first"``) or the one with the shortest range (``"nearest"``: its error,
    which enters every row, is then the smallest; of equal ranges, the first anchor in
    :func:`canonical_rank` order, so that the system does not depend on the anchors'
    order in their file); the other rows are
    ``G_i = a_i - a_r`` and ``h_i = (d_r^2 - d_i^2 - |a_r|^2 + |a_i|^2) / 2``.  Anchors are
    first shifted to their centroid (returned) so the system is well scaled; known height
    offsets turn slant ranges into horizontal ones (``d^2 - dz^2``).

    Returns
    -------
    G : (N, m, dim) design, rows of missing anchors and of the reference are NaN.
    h : (N, m) right-hand side, NaN on those rows.
    ref : (N,) index of the reference anchor (-1 when no anchor was heard).
    centroid : (dim,) shift to add back to the solution.
    """
    a = np.asarray(anchors, dtype=float)
    d = np.asarray(ranges, dtype=float)
    N, m = d.shape
    centroid = a.mean(axis=0)
    ac = a - centroid
    d2 = d * d
    if height_offset is not None:
        d2 = d2 - np.asarray(height_offset, dtype=float)[None, :] ** 2
    heard = np.isfinite(d2)
    if reference == "first":
        ref = np.where(heard.any(axis=1), np.argmax(heard, axis=1), -1)
    elif reference == "nearest":
        dd = np.where(heard, d, np.inf)
        tie = dd == dd.min(axis=1, keepdims=True)  # equal ranges: the canonical first
        rank = canonical_rank(a)
        ref = np.where(heard.any(axis=1), np.argmin(np.where(tie, rank, m), axis=1), -1)
    else:
        raise ValueError(f"reference must be 'first' or 'nearest', got {reference!r}")
    rr = np.maximum(ref, 0)
    a_r = ac[rr]  # (N, dim)
    d2_r = d2[np.arange(N), rr]
    n2 = np.sum(ac * ac, axis=1)
    G = ac[None, :, :] - a_r[:, None, :]
    h = 0.5 * (d2_r[:, None] - d2 - n2[rr][:, None] + n2[None, :])  # seed 000 eq. (3)
    use = heard.copy()
    use[np.arange(N), rr] = False
    G = np.where(use[..., None], G, np.nan)
    h = np.where(use, h, np.nan)
    return G, h, ref, centroid


def lms_score(residuals: Array, dim: int, axis: int = -1) -> Array:
    """Least-median-of-squares score of candidate fixes: the ``h``-th smallest absolute
    residual with ``h = max(ceil(n/2), dim + 2)`` (NaN ignored; ``n`` heard anchors).

    A fix from a minimal subset of ``dim + 1`` anchors has zero residual on those, so the
    score must look at least one anchor further to tell good subsets from bad ones.
    """
    r = np.moveaxis(np.abs(np.asarray(residuals, dtype=float)), axis, -1)
    nan = np.isnan(r)
    m = r.shape[-1]
    if not nan.any():  # the common case: one order statistic by partition, no sort
        h = min(max((m + 1) // 2, dim + 2), m) - 1
        return np.partition(r, h, axis=-1)[..., h]
    cnt = m - nan.sum(axis=-1)
    srt = np.sort(np.where(nan, np.inf, r), axis=-1)
    h = np.maximum((cnt + 1) // 2, dim + 2)
    h = np.clip(np.minimum(h, cnt), 1, m) - 1
    out = np.take_along_axis(srt, h[..., None], -1)[..., 0]
    return np.where(cnt > 0, out, np.inf)


def minimal_subsets(
    anchors: ArrayLike, max_subsets: int = MAX_SUBSETS, seed: int = 0
) -> tuple[NDArray[np.int64], Array, Array]:
    """The minimal anchor subsets of :func:`subset_fixes` and their inverted designs.

    Returns ``combos (C, dim + 1)``, ``Ginv (C, dim, dim)`` the inverses of
    ``G = a_j - a_0`` of the centroid-shifted anchors, and that centroid ``c0``.  A
    function of the anchors alone: cached per anchor array, the arrays are read-only.

    Every subset when there are at most ``max_subsets``; otherwise a pseudo-random choice
    that depends on the subsets' shapes alone, so that the same anchors listed in another
    order, rotated or shifted give the same subsets: each subset is keyed by its sorted
    pairwise distances (to 1e-9 of the layout's size), the keys are ordered by a hash of
    the key and ``seed`` (a random order, but the same for congruent subsets wherever and
    however listed), and the first ``max_subsets`` are taken together with every subset
    congruent to the last one taken (a symmetric layout's subsets come in whole classes;
    so ``C`` may exceed ``max_subsets`` a little).  Near-degenerate subsets are dropped.
    """
    return _minimal_subsets_cached(*_anchor_key(anchors), int(max_subsets), int(seed))


@lru_cache(maxsize=_PATTERN_CACHE)
def _minimal_subsets_cached(key: bytes, shape: tuple[int, ...], max_subsets: int, seed: int
                            ) -> tuple[NDArray[np.int64], Array, Array]:
    a = _from_key(key, shape)
    m, dim = a.shape
    q = dim + 1
    c0 = a.mean(axis=0)
    if m < q:
        out = np.zeros((0, q), dtype=np.int64), np.zeros((0, dim, dim)), c0
        _frozen(*out)
        return out
    rank = _canonical_rank_cached(key, shape)
    order = np.argsort(rank)  # anchor indices, canonical
    if math.comb(m, q) > LARGE_ENUMERATION:
        combos = _local_subsets(a, rank, q)
    else:
        combos = order[np.array(list(combinations(range(m), q)), dtype=np.int64)]
    if combos.shape[0] > max_subsets:
        combos = _shape_choice(a, combos, max_subsets, seed)
    sub = (a - c0)[combos]  # (C, q, dim)
    G = sub[:, 1:, :] - sub[:, :1, :]  # (C, dim, dim)
    with np.errstate(all="ignore"):
        det = np.linalg.det(G)
        scale = np.prod(np.linalg.norm(G, axis=2), axis=1)
        good = np.abs(det) > 1e-3 * np.maximum(scale, 1e-300)
    combos, G = combos[good], G[good]
    out = combos, np.linalg.inv(G) if combos.shape[0] else np.zeros((0, dim, dim)), c0
    _frozen(*out)
    return out


#: Above this many minimal subsets of a site's anchors (2-D: 116 anchors and more; 3-D:
#: 52), :func:`minimal_subsets` chooses among the local ones (:func:`_local_subsets`)
#: instead of enumerating all, whose count grows with the cube (2-D) or fourth power
#: (3-D) of the anchors: 2.8 s for 196 anchors, and 7.7 GB of traced memory to list those
#: of 600 (``tests/test_large_site.py``).
LARGE_ENUMERATION = 250_000

#: Neighbours of each anchor whose subsets with it form the local pool (2-D: 15 triples
#: per anchor; 3-D: 35 sets of four).
LOCAL_NEIGHBOURS = 6


def _local_subsets(a: Array, rank: NDArray[np.int64], q: int) -> NDArray[np.int64]:
    """The minimal subsets of a large site that lie close together: each anchor with
    ``q - 1`` of its :data:`LOCAL_NEIGHBOURS` nearest (scipy's k-d tree), each subset
    once, the anchors of each in canonical order and the subsets sorted by their
    canonical ranks, as :func:`minimal_subsets` lists every subset of a small site.

    An epoch on a large site hears the anchors near it, so the subsets worth trying are
    local; no subset spanning the site is heard whole.  The pool depends on where the
    anchors are, not on their order in the file: the neighbours are taken by distance
    (equal to 1e-9 of the layout's size), then by :func:`canonical_rank`, and every anchor
    at the same distance as the last neighbour taken is taken too (the 4 or 8 equidistant
    neighbours of a grid).  Anchors that make no sense for the layout (not finite, or far
    outside it: :func:`_sane_anchors`) take no part.
    """
    from scipy.spatial import cKDTree

    m, dim = a.shape
    fin = np.flatnonzero(_sane_anchors(a))
    if fin.size < q:
        return np.zeros((0, q), dtype=np.int64)
    pts = a[fin]
    size = float(np.max(np.ptp(pts, axis=0))) or 1.0
    tol = 1e-9 * size
    k = min(LOCAL_NEIGHBOURS, fin.size - 1)
    tree = cKDTree(pts)
    dk = tree.query(pts, k=k + 1)[0][:, -1]  # the k-th neighbour's distance
    rows: list[NDArray[np.int64]] = []
    for i, near in enumerate(tree.query_ball_point(pts, dk + 2.0 * tol)):
        near = np.asarray([j for j in near if j != i], dtype=np.int64)
        level = np.round(np.linalg.norm(pts[near] - pts[i], axis=1) / tol)
        o = np.lexsort((rank[fin[near]], level))
        near, level = near[o], level[o]
        near = near[level <= level[k - 1]]  # and every one as far as the k-th (ties)
        sub = np.array(list(combinations(near.tolist(), q - 1)), dtype=np.int64)
        rows.append(np.column_stack([np.full(len(sub), i), sub]))
    pool = fin[np.concatenate(rows)]  # anchor indices
    ranks = np.unique(np.sort(rank[pool], axis=1), axis=0)  # each subset once, canonical
    return np.argsort(rank)[ranks]


def _shape_choice(a: Array, combos: NDArray[np.int64], k: int, seed: int
                  ) -> NDArray[np.int64]:
    """The first ``k`` of ``combos`` in a pseudo-random order of their shapes, with every
    subset congruent to the last taken (:func:`minimal_subsets`)."""
    import hashlib

    pts = a[combos]  # (C, q, dim)
    i, j = np.triu_indices(combos.shape[1], 1)
    dist = np.sort(np.linalg.norm(pts[:, i] - pts[:, j], axis=2), axis=1)  # (C, pairs)
    size = float(np.nanmax(dist)) if np.any(np.isfinite(dist)) else 1.0
    shape_key = np.nan_to_num(np.round(dist / (1e-9 * max(size, 1e-300))),
                              nan=-1.0).astype(np.int64)
    salt = int(seed).to_bytes(8, "little", signed=True)
    h = np.array([int.from_bytes(hashlib.blake2b(row.tobytes() + salt, digest_size=8)
                                 .digest(), "little") >> 1 for row in shape_key],
                 dtype=np.int64)
    rank = np.lexsort(tuple(shape_key.T[::-1]) + (h,))  # by hash, then by the key itself
    last = shape_key[rank[k - 1]]
    take = np.zeros(combos.shape[0], dtype=bool)
    take[rank[:k]] = True
    take |= np.all(shape_key == last, axis=1)
    return combos[rank[take[rank]]]


def subset_fixes(
    anchors: ArrayLike,
    ranges: ArrayLike,
    height_offset: ArrayLike | None = None,
    max_subsets: int = MAX_SUBSETS,
    seed: int = 0,
) -> tuple[Array, Array]:
    """Least-median-of-squares start: exact fixes from minimal anchor subsets.

    Every subset of ``dim + 1`` anchors gives an exact position from its own difference
    system (seed 000 eq. (3) with ``dim`` rows); its design depends only on the anchors, so
    it is inverted once per subset and applied to all epochs.  Each epoch keeps the subset
    fix with the smallest :func:`lms_score` over all heard anchors.  At most
    ``max_subsets`` subsets are used (:data:`MAX_SUBSETS`; a fixed pseudo-random choice
    by shape when there are more, :func:`minimal_subsets`): with a fraction ``e`` of gross
    errors a subset is clean with probability ``(1 - e)^(dim+1)``, so 24 subsets all fail
    with probability 4e-8 at e = 20 % and 3e-3 at e = 40 % (2-D).

    Returns
    -------
    x : (N, dim) best subset fix (NaN where no subset was fully heard).
    score : (N,) its :func:`lms_score`.
    """
    a = np.asarray(anchors, dtype=float)
    d = np.asarray(ranges, dtype=float)
    N, m = d.shape
    dim = a.shape[1]
    combos, Ginv, c0 = minimal_subsets(a, max_subsets, seed)
    if combos.shape[0] == 0:
        return np.full((N, dim), np.nan), np.full(N, np.inf)
    sub = (a - c0)[combos]  # (C, q, dim)
    d2 = d * d
    if height_offset is not None:
        d2 = d2 - np.asarray(height_offset, dtype=float)[None, :] ** 2
    n2 = np.sum(sub * sub, axis=2)  # (C, q)
    d2s = d2[:, combos]  # (N, C, q)
    h = 0.5 * (d2s[:, :, :1] - d2s[:, :, 1:] - n2[None, :, :1] + n2[None, :, 1:])
    x = np.einsum("cij,ncj->nci", Ginv, h) + c0  # (N, C, dim)
    best = np.full((N, dim), np.nan)
    best_c = np.full(N, np.inf)
    C = combos.shape[0]
    step = max(1, 4_000_000 // max(C * m, 1))  # bound the (E, C, m) temporaries
    for s0 in range(0, N, step):
        xs = x[s0 : s0 + step]  # (E, C, dim)
        diff = xs[:, :, None, :] - a[None, None, :, :]
        r2 = np.einsum("ecmi,ecmi->ecm", diff, diff)
        if height_offset is not None:
            r2 = r2 + np.asarray(height_offset, dtype=float) ** 2
        res = np.sqrt(r2) - d[s0 : s0 + step, None, :]
        score = lms_score(res, dim)  # (E, C)
        score = np.where(np.all(np.isfinite(xs), axis=2) & np.isfinite(score), score, np.inf)
        k = np.argmin(score, axis=1)
        e = np.arange(xs.shape[0])
        best[s0 : s0 + step] = xs[e, k]
        best_c[s0 : s0 + step] = score[e, k]
    best[~np.isfinite(best_c)] = np.nan
    return best, best_c


#: Epochs x anchors of one solve where a batch is solved in parts (:func:`_solve_in_parts`,
#: ``robustloc locate``'s blocks): every batch of a small site is one part (12 anchors:
#: 166 000 epochs), a site of 900 anchors is solved 2 222 epochs at a time.  The fits'
#: ``(epochs, anchors)`` arrays, about 15 of them, are then bounded (16 MB each).
SOLVE_CELLS = 2_000_000


def _solve_in_parts(loc: Locator, a: Array, z: Array, kind: str, **kw
                    ) -> tuple[NDArray, Array, Array, Array]:
    """``loc.solve(a, z, kind, **kw)`` in parts of at most :data:`SOLVE_CELLS` epochs x
    anchors: the ``status``, ``residuals``, ``weights`` and Jacobian that
    :meth:`Locator.log_statistics` reads, joined (the same numbers: each epoch's fix is its
    own, ``loc`` with a per-epoch or a given scale).  Each part's other arrays (a
    solution holds some 16 of ``(epochs, anchors)``) are dropped as it ends: on a site of
    900 anchors the log-scale pass over 5 000 epochs peaked at 1.2 GB of traced memory."""
    step = max(1, SOLVE_CELLS // max(z.shape[1], 1))
    out: list[tuple[NDArray, Array, Array, Array]] = []
    for s0 in range(0, max(z.shape[0], 1), step):
        sol = loc.solve(a, z[s0:s0 + step], kind, **kw)
        out.append((sol.status, sol.residuals, sol.weights, sol.extra["jacobian"]))
        del sol
    if len(out) == 1:
        return out[0]
    status, residuals, weights, jac = (np.concatenate(c) for c in zip(*out))
    return status, residuals, weights, jac


#: A pattern of heard anchors with fewer of the site's minimal subsets than this takes
#: its own (:func:`_heard_groups`): the least-median-of-squares start needs candidates.
MIN_HEARD_SUBSETS = 3


def _heard_groups(a: Array, ranges: Array
                  ) -> list[tuple[NDArray[np.intp] | None, NDArray[np.intp]]] | None:
    """The epochs grouped by the anchors they hear, for :meth:`Locator._initial`'s minimal
    subsets: ``(anchor indices, rows)`` for each pattern heard that takes its own
    subsets, ``(None, rows)`` for the rows that take the whole site's.  None when every
    epoch takes the site's.

    The site's subsets are all of them when there are at most :data:`MAX_SUBSETS`
    (every subset of what an epoch hears is among them), else a choice of that many, and
    few of those lie within what one epoch hears: on a 10 x 10 grid of anchors with each
    epoch hearing its 10 nearest, none of the 24 of 161 700 for most epochs.  The start
    then had only the linearized fix and the weighted centroid to choose from, and a
    robust fit started from one that gross ranges had pulled away stayed there (huber
    with the per-epoch scale: p95 3.48 m, 0.38 m with each epoch's own subsets;
    ``benchmarks/bench_site.py``).  A pattern of anchors (fewer than all, at least
    ``dim + 1``) that holds fewer than :data:`MIN_HEARD_SUBSETS` of the site's subsets
    takes its own.  Not every pattern: on seed 000's 10-beacon corridor, where an epoch
    hearing 6 finds 4 of the site's 24 subsets on average, every pattern's own subsets
    moved the robust methods' mean error by -0.8 to +3.5 % over six seeds and both
    schemes (igg, a redescending weight, the worst); with the threshold, -0.7 to +1.4 %
    (the epochs hearing 3 to 5 beacons change), no direction.  On a site of more than
    :data:`LARGE_ENUMERATION` subsets every such pattern takes its own: the site's choice
    is then among local subsets (:func:`_local_subsets`) of a few places."""
    m, dim = a.shape
    if math.comb(m, dim + 1) <= MAX_SUBSETS or ranges.ndim != 2 or ranges.shape[1] != m:
        return None
    heard = np.isfinite(ranges)
    count = heard.sum(axis=1)
    partial = (count < m) & (count >= dim + 1)
    if not partial.any():
        return None
    pats, inv = _unique_rows(heard)
    pat_partial = np.zeros(pats.shape[0], dtype=bool)
    pat_partial[inv[partial]] = True
    if math.comb(m, dim + 1) <= LARGE_ENUMERATION:
        # the patterns that the site's own choice leaves almost without a subset
        combos = minimal_subsets(a)[0]
        within = np.all(pats[:, combos], axis=2).sum(axis=1)  # (patterns,)
        pat_partial &= within < MIN_HEARD_SUBSETS
    if not pat_partial.any():
        return None
    groups: list[tuple[NDArray[np.intp] | None, NDArray[np.intp]]] = []
    whole = np.flatnonzero(~pat_partial[inv])
    if whole.size:
        groups.append((None, whole))
    order = np.argsort(inv, kind="stable")
    bounds = np.searchsorted(inv[order], np.arange(pats.shape[0] + 1))
    for j in np.flatnonzero(pat_partial):
        groups.append((np.flatnonzero(pats[j]), order[bounds[j]:bounds[j + 1]]))
    return groups


def _height2(height_offset: ArrayLike | None, m: int) -> Array:
    if height_offset is None:
        return np.zeros(m)
    return np.broadcast_to(np.asarray(height_offset, dtype=float), (m,)) ** 2


def _compiled_gn(
    model: RangeModel, obs: Array, x0: Array, sig: Array, weight, kw: dict
) -> LinearFit | None:
    """``Locator._gn`` through the compiled kernels (None: no compiled twin of ``weight``)."""
    from robustloc.estimators import _compiled
    from robustloc.robust._compiled import weight_spec

    spec = weight_spec(weight)
    if spec is None:
        return None
    code, prm = spec
    a = model.anchors
    m = obs.shape[1]
    scale = kw["scale"]
    out = _compiled.fit_ranges(
        a, _height2(model.height_offset, m), np.ascontiguousarray(obs, dtype=float),
        np.ascontiguousarray(np.broadcast_to(sig, obs.shape), dtype=float),
        np.ascontiguousarray(x0, dtype=float), code, prm, weight is not None,
        weight is not None and bool(np.isfinite(weight.rejection_threshold)),
        np.nan if scale is None else float(scale), float(kw["min_scale"]), int(kw["max_iter"]),
        float(kw["tol"]), float(kw["rel_tol"]), int(kw["min_obs"]),
    )
    x, v, w, qvv, s0, cov, n_used, iters, conv, status, u, jac, pred = out
    return LinearFit(
        x=x, v=v, w=w, qvv=qvv, sigma0=s0, cov=cov, n_used=n_used, iterations=iters,
        converged=conv, status=_compiled.CODES[status],
        extra={"u": u, "jacobian": jac, "predicted": pred},
    )


def _checked_inputs(anchors: ArrayLike, values: ArrayLike) -> tuple[Array, Array]:
    """The anchors ``(m, 2|3)`` and the values ``(epochs, m)`` as float arrays, checked
    (:meth:`Locator.solve`, :meth:`Locator.log_statistics`): ``TypeError`` for ``None``,
    booleans and complex numbers, ``ValueError`` for the shapes."""
    from robustloc._arrays import real_array

    a = real_array(anchors, "anchors")
    z = np.atleast_2d(real_array(values, "values"))
    if a.ndim != 2 or a.shape[1] not in (2, 3) or a.shape[0] == 0:
        raise ValueError(f"anchors must be (m, 2) or (m, 3) with m >= 1, got {a.shape}")
    if z.ndim != 2:
        raise ValueError(f"values must be (epochs, anchors), got shape {z.shape}")
    if z.shape[1] != a.shape[0]:
        raise ValueError(f"values have {z.shape[1]} columns for {a.shape[0]} anchors")
    return a, z


@dataclass(frozen=True)
class Locator:
    """Batched position solver for ranging (UWB, WiFi RTT) and RSSI (BLE, WiFi) logs.

    Parameters
    ----------
    method : str
        One of :data:`METHODS` (see the module docstring).
    solver : {"nonlinear", "linearized"}
        For the robust methods and LEGE: IRLS on the raw observation equations (default,
        one bad anchor is one bad row) or on the paper's difference system.
    domain : {"range", "rssi"}
        For RSSI input and the nonlinear solvers: fit ranges converted by the path-loss
        model with ``sigma_d = d ln10 sigma_dB / (10 n)`` (default), or fit in dB.
        The dB domain is the maximum-likelihood choice for Gaussian dB noise, but RSSI
        fades are one-sided: in the range domain a faded link reads long and its own
        ``sigma_d`` grows with it, so it is down-weighted automatically.  Measured here:
        ble-tetam tracks (12 receivers) 2-D RMS 2.94 m in range vs 3.61 m in dB (nls),
        2.87 vs 4.14 m (huber); simulated corridor 1.24 vs 1.47 m (nls).
    sigma : float or sequence of float (one per anchor), optional
        A-priori standard deviation of one observation (metres for ranges, dB for RSSI),
        e.g. the per-anchor residual std of a calibration.  It sets the relative weights
        of the anchors; None: equal weights.  Required by ``snooping``.
    robust_scale : {"log", "mad", "apriori"}
        Robust methods: where the noise scale that standardizes the residuals comes from.
        ``"log"`` (default): estimated per anchor over the whole batch (the log, or one
        streaming window of it) by :meth:`log_scale`, a first robust pass, and then held
        fixed (the MM idea: a scale from many residuals, not from the 3-8 of one epoch);
        ``"mad"``: per epoch, the MAD of that epoch's standardized residuals (the paper's
        choice; noisy at redundancy 1-6, where it makes redescending weights throw away
        good observations); ``"apriori"``: trust ``sigma`` as the true noise level.
    weight_params : dict[str, float]
        Overrides of the weight function's thresholds (e.g. ``{"c": 1.5}`` for Huber).
    min_scale : float
        Floor on the estimated robust scale, in units of ``sigma`` (or of the observation
        when ``sigma`` is None).
    max_iter, tol : iteration limit and step threshold (metres) of the iterative solvers.
    rel_tol : float
        Also converged when a step is below this fraction of the fix's standard error, or
        lowers the cost by at most 1e-6 of it (``0``: ``tol`` stops the iteration, or a
        cost that falls by no more than rounding).
    alpha0, beta0 : significance and power of the w-test (``snooping``, B-method).
    reference : {"first", "nearest"}
        Reference anchor of the linearized system (:func:`linearized_system`): the
        paper's first heard anchor, or the one with the shortest range.  The linearized
        solver's; the iterative solvers start from the nearest anchor's system whatever
        it says (:meth:`_initial`: fixes independent of the anchors' order).
    log_scale_fixed : tuple of float (one per anchor), optional
        With ``robust_scale="log"``: the per-anchor scale already estimated over the log
        (e.g. by a first pass over a file too large for one batch, :meth:`log_scale`);
        None estimates it from the batch being solved.
    log_gross_share : float, optional
        The share of the log's standardized residuals beyond :data:`GROSS_U` (4) in the
        first pass (:meth:`log_statistics`): how often the log carries gross errors
        (Gaussian noise: 6e-5).  Method ``auto`` uses it
        (:func:`robustloc.integrity.fixes.locate_protected`); None: unknown.
    log_sides : tuple of ((anchor indices), side) pairs, optional
        With ``robust_scale="log"``: for each set of nearly collinear (coplanar) kept
        anchors, the side of their line (plane) on which the log's unambiguous fixes lie,
        +1 or -1 (:func:`robustloc.integrity.fixes.ambiguity_sides`, from the first pass);
        an ambiguous fix on the other side is moved to its mirror solution
        (:func:`robustloc.integrity.fixes.resolve_sides`).  None: found from the batch
        being solved; an empty tuple: no side preferred.
    engine : {"compiled", "numpy"}
        ``"compiled"``: the robust start and the Gauss-Newton fits of ranges (and of RSSI
        converted to ranges) run per epoch in the numba kernels of
        :mod:`robustloc.estimators._compiled` (a whole ``solve`` 3-5x faster; the first
        call in a fresh install compiles them, about 20 s, cached on disk afterwards; a
        batch of 4 096 epochs or more is split over numba's threads, all cores unless
        ``NUMBA_NUM_THREADS`` or ``numba.set_num_threads`` says otherwise, with
        bit-identical results for any count);
        ``"numpy"``: the batched NumPy implementation, which the kernels reproduce (the
        tests compare them) and which serves the dB-domain model and custom weight
        functions.
    """

    method: str = "huber"
    solver: str = "nonlinear"
    domain: str = "range"
    sigma: float | tuple[float, ...] | None = None
    robust_scale: str = "log"
    weight_params: dict[str, float] = field(default_factory=dict)
    min_scale: float = 0.0
    max_iter: int = 100
    tol: float = 1e-3
    rel_tol: float = 1e-2
    alpha0: float = 0.001
    beta0: float = 0.10
    reference: str = "first"
    engine: str = "compiled"
    log_scale_fixed: tuple[float, ...] | None = None
    log_gross_share: float | None = None
    log_sides: tuple[tuple[tuple[int, ...], int], ...] | None = None

    def __post_init__(self) -> None:
        if self.method not in METHODS + ("auto",):
            raise ValueError(f"unknown method {self.method!r}; choose one of {', '.join(METHODS)}")
        if self.solver not in ("nonlinear", "linearized"):
            raise ValueError(f"solver must be 'nonlinear' or 'linearized', got {self.solver!r}")
        if self.domain not in ("rssi", "range"):
            raise ValueError(f"domain must be 'rssi' or 'range', got {self.domain!r}")
        if self.sigma is not None:
            sg = np.atleast_1d(np.asarray(self.sigma, dtype=float))
            if sg.ndim != 1 or not np.all(np.isfinite(sg) & (sg > 0)):
                raise ValueError(f"sigma must be positive and finite, got {self.sigma}")
            object.__setattr__(self, "sigma", float(sg[0]) if sg.size == 1 else tuple(sg))
        if self.reference not in ("first", "nearest"):
            raise ValueError(f"reference must be 'first' or 'nearest', got {self.reference!r}")
        if self.robust_scale not in ("log", "mad", "apriori"):
            raise ValueError(
                f"robust_scale must be 'log', 'mad' or 'apriori', got {self.robust_scale!r}")
        if self.robust_scale == "apriori" and self.sigma is None:
            raise ValueError("robust_scale='apriori' needs sigma")
        if self.method == "snooping" and self.sigma is None and self.robust_scale != "log":
            raise ValueError("method 'snooping' needs the a-priori standard deviation --sigma")
        if self.method in ROBUST:
            method_weight(self.method, **self.weight_params)  # validate early
        elif self.method == "auto":  # its robust refit is huber (integrity.fixes.AUTO_ROBUST)
            method_weight("huber", **self.weight_params)
        if self.engine not in ("compiled", "numpy"):
            raise ValueError(f"engine must be 'compiled' or 'numpy', got {self.engine!r}")
        # the numeric settings, by name (the API review: min_scale=nan was blamed on
        # sigma; alpha0=2, min_scale=-1, max_iter=0 and tol=-1 passed; max_iter=1.5 ran on
        # one engine and raised TypeError on the other)
        if isinstance(self.max_iter, bool) or not (
                isinstance(self.max_iter, int | np.integer) and self.max_iter >= 1):
            raise ValueError(f"max_iter must be a whole number >= 1, got {self.max_iter!r}")
        for name, lo, hi, closed in (("min_scale", 0.0, 1e6, True), ("tol", 0.0, np.inf, True),
                                     ("rel_tol", 0.0, np.inf, True),
                                     ("alpha0", 0.0, 0.5, False), ("beta0", 0.0, 1.0, False)):
            v = getattr(self, name)
            try:
                v = float(v)
            except (TypeError, ValueError):
                raise ValueError(f"{name} must be a number, got {v!r}") from None
            inside = (lo <= v <= hi) if closed else (lo < v < hi)
            if not (inside and np.isfinite(v)):
                raise ValueError(f"{name} must lie in {'[' if closed else '('}{lo:g}, "
                                 f"{hi:g}{']' if closed else ')'}, got {v!r}")
        if self.log_scale_fixed is not None:
            ls = np.asarray(self.log_scale_fixed, dtype=float)
            if ls.ndim != 1 or not np.all(np.isfinite(ls) & (ls > 0)):
                raise ValueError("log_scale_fixed must be positive finite scales, one per "
                                 f"anchor, got {self.log_scale_fixed!r}")
        if self.log_sides is not None:
            try:
                sides = tuple((tuple(int(i) for i in idx), int(side))
                              for idx, side in self.log_sides)
            except (TypeError, ValueError) as exc:
                raise ValueError("log_sides must be ((anchor indices), side) pairs, got "
                                 f"{self.log_sides!r}") from exc
            if any(side not in (-1, 1) or min(idx, default=-1) < 0 for idx, side in sides):
                raise ValueError(f"log_sides: each side is +1 or -1 of non-negative anchor "
                                 f"indices, got {self.log_sides!r}")
            object.__setattr__(self, "log_sides", sides)

    # ------------------------------------------------------------------ public
    def solve(
        self,
        anchors: ArrayLike,
        values: ArrayLike,
        kind: str = "range",
        *,
        A: ArrayLike | None = None,
        n: ArrayLike | None = None,
        height_offset: ArrayLike | None = None,
    ) -> Solution:
        """Solve every epoch.

        Parameters
        ----------
        anchors : (m, dim) anchor coordinates (dim 2 or 3: the solved dimension).
        values : (N, m) ranges in metres or RSSI in dBm; NaN = not heard, and so is an
            infinite value (a range of ``inf``, an RSSI of ``-inf`` dBm: no signal), on
            both engines.  The command-line readers refuse ``inf`` in a file
            (``FILE:LINE``); leave the cell empty there.
        kind : {"range", "rssi"}
        A, n : (m,) log-distance parameters per anchor (required for RSSI).
        height_offset : (m,) known anchor-minus-tag heights for 2-D solutions with
            slant ranges.

        Returns
        -------
        Solution
        """
        if self.method == "auto":
            raise ValueError("method 'auto' chooses per epoch by the fix's own test: solve "
                             "it with robustloc.integrity.fixes.locate_protected")
        a, z = _checked_inputs(anchors, values)
        if height_offset is not None:
            # one per anchor (or one for all), finite: a NaN made the compiled engine's
            # fixes `ok` and the NumPy engine's `ill_conditioned` (the API review)
            h = np.asarray(height_offset, dtype=float)
            if h.ndim > 1 or (h.ndim == 1 and h.shape[0] != a.shape[0]):
                raise ValueError(f"height_offset has shape {h.shape}; expected a number or "
                                 f"({a.shape[0]},), one per anchor")
            if not np.all(np.isfinite(h)):
                raise ValueError("height_offset must be finite")
            height_offset = np.broadcast_to(h, (a.shape[0],)).copy()
        z = np.where(np.isfinite(z), z, np.nan)
        sane = _sane_anchors(a)
        if np.any(sane) and not np.all(sane):
            return self._solve_subset(a, z, kind, sane, A, n, height_offset)
        if kind == "rssi":
            if A is None or n is None:
                raise ValueError("RSSI positioning needs path-loss parameters A and n per anchor")
            for name, v in (("A", A), ("n", n)):
                if np.ndim(v) > 1 or (np.ndim(v) == 1 and np.shape(v)[0] != a.shape[0]):
                    raise ValueError(f"{name} has shape {np.shape(v)}; expected a number or "
                                     f"({a.shape[0]},), one per anchor")
            rmodel = RssiModel(a, A, n, height_offset)
            ranges = rmodel.distance(z)
        elif kind == "range":
            rmodel = None
            ranges = z
        else:
            raise ValueError(f"kind must be 'range' or 'rssi', got {kind!r}")
        if self.robust_scale == "log":
            # the log's per-anchor noise scale: the robust pass's a-priori sigma, and the
            # sigma of every method's integrity statistics (robustloc.integrity.fixes)
            if self.log_scale_fixed is not None:
                scale = np.asarray(self.log_scale_fixed, dtype=float)
                if scale.shape != (a.shape[0],):
                    raise ValueError(f"log_scale_fixed has {scale.size} values for "
                                     f"{a.shape[0]} anchors")
            else:
                scale = self.log_scale(a, z, kind, A=A, n=n, height_offset=height_offset)
            base = self._sigma_array((1, a.shape[0]))[0]
            if self._log_scaled():
                second = replace(self, sigma=tuple(base * scale), robust_scale="apriori")
            else:
                second = replace(self, robust_scale="mad")
            sol = second.solve(a, z, kind, A=A, n=n, height_offset=height_offset)
            if self._log_scaled():
                # sigma0 as every method reports it: the ratio of the residuals to the
                # a-priori sigma, not to the log's scale times it (the robust fit's
                # weights are p / (s sigma)^2: times s^2 they are p / sigma^2)
                w = np.where(np.asarray(sol.weights) > 0, sol.weights, 0.0) * scale**2
                dof = np.sum(w > 0, axis=1) - a.shape[1]
                with np.errstate(all="ignore"):
                    vpv = np.nansum(w * np.asarray(sol.residuals) ** 2, axis=1)
                    s0 = np.sqrt(vpv / np.maximum(dof, 1))
                sol = replace(sol, sigma0=np.where(np.isfinite(sol.sigma0) & (dof > 0), s0,
                                                   sol.sigma0))
            sol.extra["log_scale"] = scale
            sol.extra["sigma_obs"] = self._range_sigma(
                np.broadcast_to(base * scale, z.shape), ranges, rmodel)
            if not self._log_scaled() and self.solver == "nonlinear" and self.method in (
                    "nls", "lege", "snooping"):
                # the fit weighted by 1 / sigma^2, its tests by 1 / (s sigma)^2: each
                # residual is tested against its variance under the fit's own weights, as
                # a robust fit's (robustloc.integrity.fixes.protect; relative factors,
                # largest 1).  Tested as if the fit had the log's weights, ranges of
                # unequal noise (sd 0.05-0.44 m) said fault_detected in 13 % of Gaussian
                # epochs where the B-method means about 1 % (the locate review of
                # 2026-12-06).  The fix stays unweighted: weighted by the log's scale,
                # nls lost 15 % on the lecture theatre and 21 % on the labyrinth, whose
                # per-anchor biases the log's scale reads as noise
                with np.errstate(all="ignore"):
                    f = (scale / np.max(scale)) ** 2  # p / (s sigma)^2 = 1 / sigma^2 ...
                sol.extra["weight_factor"] = np.where(np.isfinite(sol.residuals),
                                                      f[None, :], np.nan)
                # ... and so is its bound: the fix of these weights keeps a flagged row
                # at its weight (a plain fit), and its covariance is the sandwich
                # (robustloc.integrity.fixes.protection_levels_local, fit_weight).  With
                # the log's weights the bound was that of a weighted fix: one anchor of
                # sd 1 m among five of 0.1 m left 7.7 % of `ok` fixes beyond their hpl
                sol.extra["fit_weight_factor"] = sol.extra["weight_factor"]
            return sol
        dim = a.shape[1]
        n_heard = np.sum(np.isfinite(z), axis=1)
        fit = self._dispatch(a, z, ranges, rmodel, height_offset)
        status = fit.status.copy()
        if dim == 2:
            status[_collinear(a, np.isfinite(z)) & (status != st.INSUFFICIENT)] = (
                st.ILL_CONDITIONED
            )
        status[n_heard < dim + 1] = st.INSUFFICIENT
        status[n_heard == 0] = st.INVALID
        # (reshaped: the snooping fit of no epochs is (0, 0), and broke the range model)
        x = np.where(st.among(status, st.USABLE)[:, None], fit.x, np.nan).reshape(
            z.shape[0], dim)
        w = fit.w
        excluded = np.isfinite(z) & (w <= 0)  # NaN weight: not heard, not excluded
        if self.method == "lege" or self.method == "snooping":
            excluded |= fit.extra.get("flagged", np.zeros_like(excluded))
        n_used = np.sum(np.isfinite(z), axis=1) - excluded.sum(axis=1)
        # what integrity statistics need, in the range domain whatever the fit's domain:
        # residuals v = f(x) - range and the design d range / d x at the fix
        rng_model = RangeModel(a, height_offset)
        xs = np.nan_to_num(x)
        use = st.among(status, st.USABLE)[:, None]
        extra = dict(fit.extra)
        # the compiled fit's, at its fix (the same formula): no second pass over (N, m, p)
        jac, pred = extra.pop("jacobian", None), extra.pop("predicted", None)
        if jac is None or pred is None or jac.shape != z.shape + (dim,):
            pred, jac = rng_model.predict_jacobian(xs)
        extra["range_residuals"] = np.where(use, pred - ranges, np.nan)
        extra["jacobian"] = np.where(use[..., None], jac, np.nan)
        extra["anchor_extent"] = self._the_area(a)
        # which fix it is: a least-squares or robust fit of the ranges, or one of the
        # paper's linearized difference system (robustloc.integrity.fixes.protect)
        # (``ls`` and ``wls`` are always the latter, as :meth:`_dispatch` solves them)
        extra["solver"] = ("linearized" if self.method in ("ls", "wls") or (
            self.solver == "linearized" and self.method in ROBUST + ("lege",))
            else "nonlinear")
        if self.sigma is not None:
            extra["sigma_obs"] = self._range_sigma(self._sigma_array(z.shape), ranges, rmodel)
        return Solution(
            position=x, covariance=fit.cov, residuals=fit.v, weights=w, excluded=excluded,
            sigma0=fit.sigma0, iterations=fit.iterations, converged=fit.converged,
            status=status, n_used=n_used, method=self.method, extra=extra,
        )

    def solve_as(self, method: str, anchors: ArrayLike, values: ArrayLike,
                 kind: str = "range", **kw: object) -> Solution:
        """:meth:`solve` with another method and every other setting kept."""
        return replace(self, method=method).solve(anchors, values, kind, **kw)

    def with_method(self, method: str, log_scale: ArrayLike | None = None) -> Locator:
        """This locator with another method (and, optionally, a fixed log scale)."""
        loc = replace(self, method=method)
        if log_scale is not None:
            loc = replace(loc, log_scale_fixed=tuple(float(v) for v in np.asarray(log_scale)))
        return loc

    def _solve_subset(self, a, z, kind, heard, A, n, height_offset) -> Solution:
        """Solve with the sane anchors only (:func:`_sane_anchors`), then put the
        per-anchor arrays back in the caller's anchor order (NaN / False for the others):
        an anchor file's absurd entry changes no fix."""
        m = a.shape[0]
        sub = self
        if self.sigma is not None and np.ndim(self.sigma) == 1 and len(self.sigma) == m:
            sub = replace(sub, sigma=tuple(np.asarray(self.sigma, dtype=float)[heard]))
        if self.log_scale_fixed is not None and len(self.log_scale_fixed) == m:
            sub = replace(sub, log_scale_fixed=tuple(
                np.asarray(self.log_scale_fixed, dtype=float)[heard]))

        def pick(v: ArrayLike | None) -> Array | None:
            return None if v is None else np.broadcast_to(np.asarray(v, dtype=float), (m,))[heard]

        sol = sub.solve(a[heard], z[:, heard], kind, A=pick(A), n=pick(n),
                        height_offset=pick(height_offset))
        cols = np.flatnonzero(heard)

        def widen(arr: NDArray, fill: object) -> NDArray:
            out = np.full((arr.shape[0], m) + arr.shape[2:], fill, dtype=arr.dtype)
            out[:, cols] = arr
            return out

        extra = {}
        for k, v in sol.extra.items():
            if isinstance(v, np.ndarray) and v.ndim >= 2 and v.shape[1] == cols.size:
                v = widen(v, False if v.dtype == bool else np.nan)
            elif k == "log_scale":
                # an anchor no fix uses keeps the scale it was given (NaN without one): a
                # NaN there was refused when the fixes' scale was handed on (`auto`'s
                # refit: a ValueError traceback for an anchors file's typo, x 7.5 -> 750;
                # the fuzz review of 2026-12-06)
                wide = widen(v[None, :], np.nan)[0]
                if self.log_scale_fixed is not None and len(self.log_scale_fixed) == m:
                    wide[~heard] = np.asarray(self.log_scale_fixed, dtype=float)[~heard]
                v = wide
            extra[k] = v
        return replace(
            sol, residuals=widen(sol.residuals, np.nan), weights=widen(sol.weights, np.nan),
            excluded=widen(sol.excluded, False), extra=extra,
        )

    def _the_area(self, a: Array) -> tuple[Array, float]:
        return _area(a)

    def _log_scaled(self) -> bool:
        # snooping tests against a known sigma: the log's scale stands in only without one
        return self.robust_scale == "log" and (
            (self.method in ROBUST and self.solver == "nonlinear")
            or (self.method == "snooping" and self.sigma is None))

    def log_scale(
        self,
        anchors: ArrayLike,
        values: ArrayLike,
        kind: str = "range",
        *,
        A: ArrayLike | None = None,
        n: ArrayLike | None = None,
        height_offset: ArrayLike | None = None,
        max_epochs: int = 5_000,
        min_count: int = 20,
        iterations: int = 3,
        weighting: float = LOG_SCALE_WEIGHTING,
    ) -> Array:
        """Per-anchor noise scale over a whole log, in units of ``sigma``.

        A robust fit (this locator with the per-epoch MAD scale; Huber's for the
        redescending and the non-robust methods, as a redescending fit leaves the residuals
        it keeps smaller than the noise: IGG's own fits gave 0.79 of the true scale of
        Gaussian ranges) over at most
        ``max_epochs`` epochs spread evenly over the log gives standardized residuals
        ``u_ij = v_ij / (sigma_ij s_j sqrt(r_ij))`` with ``r_ij`` the redundancy number of
        observation ``i`` in epoch ``j``'s a-priori weighted fit (a fit absorbs part of
        each observation's noise: seed 003's ``Q_vv P``); epochs without redundancy carry
        no information on the scale.  Anchor ``j``'s scale is updated by the MAD about zero
        (seed 000 sec. 2.1) of its ``u_ij`` over all epochs, ``s_j <- s_j med |u_ij| /
        0.6745``, and the fit repeated with the new weights (``iterations`` times: with few
        anchors an unweighted fit spreads a noisy anchor's errors over the others; the
        iteration is the robust analogue of Helmert's variance component estimation).  The
        weights use each scale shrunk toward the pooled one, ``common (s_j / common) **
        weighting`` (:data:`LOG_SCALE_WEIGHTING`: 1 is the full iteration, 0 equal
        weights; the scales returned are always each anchor's own).  A
        median over hundreds of residuals instead of three to eight, with a 50 % breakdown
        point over the log, so an anchor's outliers (fades, NLOS) do not inflate it.  An
        anchor with fewer than ``min_count`` residuals gets the scale pooled over every
        anchor.  From the second iteration on (the fits of a known scale) the MAD is
        divided by its Gaussian consistency factor for the fit, measured on the log's own
        geometry (:func:`_gaussian_mad_factor`: a Huber fit's residuals are more peaked
        than Gaussian, and the MAD read 0.983 of a Gaussian scale at ``c = 2``, 0.943 at
        ``c = 1.5``; now 0.996 and 0.989, the least-squares limit's 0.996 -- the
        integrity review's six anchors).  For RSSI fitted as ranges the unit is dB
        (``sigma_ij = d ln10 sigma_dB / (10 n)``), for ranges metres.

        Returns
        -------
        ndarray (m,)
            Scale factors, positive and finite (1.0 when nothing could be estimated).
        """
        return self.log_statistics(anchors, values, kind, A=A, n=n,
                                   height_offset=height_offset, max_epochs=max_epochs,
                                   min_count=min_count, iterations=iterations,
                                   weighting=weighting)[0]

    def log_statistics(
        self,
        anchors: ArrayLike,
        values: ArrayLike,
        kind: str = "range",
        *,
        A: ArrayLike | None = None,
        n: ArrayLike | None = None,
        height_offset: ArrayLike | None = None,
        max_epochs: int = 5_000,
        min_count: int = 20,
        iterations: int = 3,
        weighting: float = LOG_SCALE_WEIGHTING,
    ) -> tuple[Array, float]:
        """:meth:`log_scale` and the log's gross-error share.

        Returns
        -------
        scale : ndarray (m,)
            As :meth:`log_scale`.
        gross_share : float
            The share of the last pass's standardized residuals ``u_ij`` (in the final
            scale) with ``|u_ij| > GROSS_U = 4``: 6.3e-5 for Gaussian noise; measured
            0.13-2.2 % on the shared real logs (NLOS biases and fades), 4.9 % and 20 % on
            simulated ranges with 5 % and 20 % gross errors
            (:data:`robustloc.integrity.fixes.AUTO_GROSS_SHARE`).  NaN when no residual
            could be standardized.
        """
        if not 0.0 <= weighting <= 1.0:
            raise ValueError(f"weighting must lie in [0, 1], got {weighting!r}")
        # (as solve() checks them: iterations = 0 was an UnboundLocalError, 1-D anchors
        # an IndexError, max_epochs = 0 all-ones scales; the API review)
        for name, v in (("max_epochs", max_epochs), ("min_count", min_count),
                        ("iterations", iterations)):
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise ValueError(f"{name} must be a whole number >= 1, got {v!r}")
        a, z = _checked_inputs(anchors, values)
        N, m = z.shape
        rows = np.arange(N)
        if N > max_epochs:
            rows = np.unique(np.linspace(0, N - 1, max_epochs).astype(np.int64))
        if self.method in ROBUST and self.solver == "nonlinear" and not np.isfinite(
                method_weight(self.method, **self.weight_params).rejection_threshold):
            first = replace(self, robust_scale="mad", log_scale_fixed=None)
        else:
            # the scale of a non-robust method's log still comes from a robust fit; so
            # does a redescending method's, from Huber's: a redescending fit leaves the
            # residuals it keeps smaller than the noise (with IGG's own fits the log
            # scale of Gaussian ranges came out 0.79 of the truth, and IGG then rejected
            # 17 % of them where k1 = 2.5 means 1.2 %)
            # (on the ranges themselves whatever the method's solver: the residuals and
            # weights of a fit of the linearized difference system are its equations'
            # (m^2), and with them the scale of uwb-dwm1001 NLOS collapsed to the 1e-6
            # floor at three of four anchors, Gaussian ranges read 8.5-19x their sigma)
            first = Locator("huber", domain=self.domain, sigma=self.sigma, robust_scale="mad",
                            engine=self.engine, max_iter=self.max_iter, tol=self.tol,
                            rel_tol=self.rel_tol, solver="nonlinear",
                            reference=self.reference)
        zz = z[rows]
        base = self._sigma_array((1, m))[0]
        rm = RssiModel(a, A, n, height_offset) if kind == "rssi" else None
        rng_obs = rm.distance(zz) if rm is not None else zz
        scale = np.ones(m)
        common = 1.0  # the scale pooled over every anchor
        p = a.shape[1]
        floor = max(self.min_scale, 1e-6)
        kappa: float | None = None
        for it in range(iterations):
            # the fits' weights: each anchor's scale shrunk toward the pooled one
            fit_scale = common * (scale / common) ** weighting
            sig_fit = np.broadcast_to(base * fit_scale, zz.shape)
            # the first fit standardizes by each epoch's own MAD; later ones trust the
            # scale found so far (fixed, as MM-estimators do), so Gaussian residuals keep
            # their full weight and the next estimate is not shrunk by down-weighting
            step_loc = replace(first, sigma=tuple(base * fit_scale),
                               robust_scale="mad" if it == 0 else "apriori")
            status, residuals, weights, J = _solve_in_parts(
                step_loc, a, zz, kind, A=A, n=n, height_offset=height_offset)
            if kind == "rssi" and self.domain == "range":
                sig_fit = self._range_sigma(sig_fit, rng_obs, rm)
            # redundancy numbers r_ij = 1 - h_ii of the a-priori weighted fit (seed 003),
            # from the range-domain design (a row's scaling to dB cancels in J_i / sigma_i)
            sig_r = self._range_sigma(sig_fit, rng_obs, rm) if self.domain == "rssi" and (
                rm is not None) else sig_fit
            with np.errstate(all="ignore"):
                Jw = np.where(np.isfinite(zz)[..., None], J / sig_r[..., None], 0.0)
                Jw = np.where(np.isfinite(Jw), Jw, 0.0)
                Nm = np.einsum("kip,kiq->kpq", Jw, Jw)
                # invertible: det above 1e-12 of trace^p (no SVD per epoch)
                tr = np.einsum("kii->k", Nm)
                ok = np.abs(np.linalg.det(Nm)) > 1e-12 * np.maximum(tr, 1e-300) ** p
                Ninv = np.linalg.inv(np.where(ok[:, None, None], Nm, np.eye(p)))
                r = 1.0 - np.einsum("kip,kpq,kiq->ki", Jw, Ninv, Jw)
                r = np.where(ok[:, None] & (r > 0.05), r, np.nan)
                # each residual's own cofactor in the fit that gave it (its robust
                # weights, p = w sigma^2, down-weighted rows included): a row the fit
                # down-weighted is left nearer its prediction variance (1 + h) than the
                # a-priori 1 - h (for Huber's passes the two differ little; it is the
                # Huber pass above that keeps the scale of a redescending method right)
                p_w = np.where(np.isfinite(zz), np.nan_to_num(weights) * sig_fit**2, 0.0)
                q = sandwich_qvv(Jw, np.isfinite(zz).astype(float), p_w, r)
                u = np.abs(residuals) / (sig_fit * np.sqrt(np.where(np.isfinite(r), q,
                                                                        np.nan)))
            u = np.where(st.among(status, st.USABLE)[:, None] & np.isfinite(u), u, np.nan)
            if it >= 1:
                # the fits of a known scale (not the first, per-epoch MAD one): their
                # MAD reads low of a Gaussian scale by a factor measured once on this
                # log's own geometry (_gaussian_mad_factor), divided out here
                if kappa is None:
                    kappa = _gaussian_mad_factor(step_loc, Jw, np.isfinite(zz), r)
                u = u / kappa
            count = np.sum(np.isfinite(u), axis=0)
            pooled = np.nanmedian(u) / MAD_NORMAL if np.any(count) else np.nan
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                per = np.nanmedian(u, axis=0) / MAD_NORMAL
            step = np.where(count >= min_count, per, pooled)
            step = np.where(np.isfinite(step), step, 1.0)
            scale = np.maximum(fit_scale * step, floor)
            common = max(common * (float(pooled) if np.isfinite(pooled) else 1.0), floor)
        # the last residuals in the final scale (u / step, before the floor)
        with np.errstate(all="ignore"):
            u_final = u / step[None, :]
        fin = np.isfinite(u_final)
        gross = float(np.mean(u_final[fin] > GROSS_U)) if fin.any() else float("nan")
        # a scale from a short log is an estimate: below LOG_SCALE_MIN_DOF degrees of
        # freedom (those of a standard deviation as precise as this median: the MAD's
        # Gaussian efficiency, MAD_EFFICIENCY, times the residuals' redundancy) it is
        # widened by Student's t for them (a common factor: least-squares fixes do not
        # move; tests and bounds widen, robust weights a little).  Taken as known, the
        # scale of a one-epoch log (redundancy 3) made 2 % of its fixes exceed their hpl
        # and excluded good ranges (the locate review of 2026-12-06); with the
        # redundancy alone as degrees of freedom, 0.2 %; now none of 4 000
        dof = MAD_EFFICIENCY * float(np.sum(np.where(np.isfinite(u) & np.isfinite(r), r,
                                                     0.0)))
        if 0.0 < dof < LOG_SCALE_MIN_DOF:
            scale = scale * float(t_ppf(LOG_SCALE_T_LEVEL, dof) / norm_ppf(LOG_SCALE_T_LEVEL))
        return scale, gross

    # ----------------------------------------------------------------- helpers
    def _dispatch(self, a, z, ranges, rmodel, height_offset) -> LinearFit:
        meth = self.method
        if meth == "ls":
            return self._linearized(a, ranges, height_offset, None)
        if meth == "wls":
            return self._linearized(a, ranges, height_offset, self._wls_weights(ranges, rmodel))
        if self.solver == "linearized" and meth in ROBUST + ("lege",):
            return self._linearized(a, ranges, height_offset, None, robust=meth)
        x0 = self._initial(a, ranges, height_offset)
        model, obs, sig = self._nonlinear_problem(a, z, ranges, rmodel, height_offset, x0)
        if meth == "nls":
            return self._gn(model, obs, x0, sig, None)
        if meth in ROBUST:
            wf = method_weight(meth, **self.weight_params)
            fit = self._rescue(model, obs, sig, wf, self._gn(model, obs, x0, sig, wf), a)
            # redundancy 0 or 1: robust weights have nothing to compare a residual with;
            # the plain fit and its global test (robustloc.integrity.fixes) say more
            low = np.sum(np.isfinite(obs), axis=1) - a.shape[1] <= 1
            if np.any(low):
                rows = np.flatnonzero(low)
                plain = self._gn(model, obs[rows], x0[rows], sig[rows], None)
                fit = _merge(fit, plain, rows, np.ones(rows.size, dtype=bool), inplace=True)
            fit.extra["fallback"] = low
            # each observation's robust weight factor p(u) in [0, 1] (the fit's weights
            # are p / sigma^2 in its own domain): the integrity tests take a residual's
            # variance under these weights (robustloc.integrity.fixes.protect)
            # (NaN where the fit gave no weight: not observed.  In place, three passes:
            # the masked form cost bench_locate's auto row 4 % of its time)
            with np.errstate(all="ignore"):
                pw = fit.w * sig
                pw *= sig
                fit.extra["weight_factor"] = np.clip(pw, 0.0, 1.0, out=pw)
            return fit
        if meth == "lege":
            return self._lege_nonlinear(model, obs, x0, sig)
        return self._snooping(model, obs, x0, sig)

    def _wls_weights(self, ranges: Array, rmodel: RssiModel | None) -> Array:
        d = np.maximum(ranges, 0.1)
        # difference row i carries d_i * e_i; e_i ∝ d_i for RSSI-derived ranges
        power = 4.0 if rmodel is not None else 2.0
        return 1.0 / d**power

    def _linearized(self, a, ranges, height_offset, w, robust: str | None = None,
                    reference: str | None = None) -> LinearFit:
        G, h, ref, c = linearized_system(a, ranges, height_offset,
                                         self.reference if reference is None else reference)
        if robust is None:
            fit = solve_wls(G, h, w)
        elif robust == "lege":
            fit = lege(G, h, w)
            fit.extra["flagged"] = fit.extra["gross_errors"] != 0
        else:
            # start from the least-median-of-squares subset fix (shifted like the system)
            xs, _ = subset_fixes(a, ranges, height_offset)
            fit = irls(
                G, h, method_weight(robust, **self.weight_params), w,
                max_iter=self.max_iter, tol=self.tol, min_scale=self.min_scale, x0=xs - c,
            )
        x = fit.x + c
        return LinearFit(
            x=x, v=fit.v, w=fit.w, qvv=fit.qvv, sigma0=fit.sigma0, cov=fit.cov,
            n_used=fit.n_used, iterations=fit.iterations, converged=fit.converged,
            status=fit.status, extra={**fit.extra, "reference": ref},
        )

    def _initial(self, a, ranges, height_offset) -> Array:
        """Start for the iterative solvers, robust to wild ranges and to masking.

        Candidates per epoch: the linearized LS fix clipped to the anchors' area
        (:func:`_area`), the inverse-square-distance weighted centroid of the
        heard anchors, and (for the robust methods) the exact fixes of minimal subsets of
        ``dim + 1`` anchors (:func:`subset_fixes`).  The candidate with the smallest median
        absolute range residual wins (least median of squares): an M-estimator started
        from it is no longer masked by several gross errors pulling the LS start.  With
        coplanar 3-D anchors the start is moved off their plane (:func:`_off_plane`).

        The linearized candidate is referenced to the nearest anchor whatever
        :attr:`reference` says (that option is the linearized solver's), and ties and
        subsets follow :func:`canonical_rank`: the start, and so the fix, does not depend
        on the order of the anchors file.  Referenced to the first heard anchor, the
        default's RMS on the wifi-rtt-rss office ranged from 1.174 to 1.307 m over the 120
        orders of its five access points (measured 2026-12-02); now 1.177 m for every
        order.
        """
        centre, radius = self._the_area(a)
        robust = self.method in ROBUST + ("lege", "snooping")
        groups = _heard_groups(a, ranges) if robust else None
        if groups is None:
            best = self._initial_candidates(a, ranges, height_offset, centre, radius, robust)
        else:  # (the site's area and plane throughout)
            best = np.empty((ranges.shape[0], a.shape[1]))
            ho = None if height_offset is None else np.broadcast_to(
                np.asarray(height_offset, dtype=float), (a.shape[0],))
            for idx, rows in groups:
                if idx is None:
                    best[rows] = self._initial_candidates(a, ranges[rows], height_offset,
                                                          centre, radius, robust)
                else:
                    best[rows] = self._initial_candidates(
                        a[idx], ranges[np.ix_(rows, idx)], None if ho is None else ho[idx],
                        centre, radius, robust)
        return _off_plane(a, np.where(np.isfinite(best), best, centre), np.isfinite(ranges))

    def _initial_candidates(self, a, ranges, height_offset, centre, radius,
                            robust: bool) -> Array:
        """:meth:`_initial`'s least-median-of-squares choice among its candidates (NaN
        where none is finite), for the anchors ``a`` and the site's area."""
        if self.engine == "compiled":
            from robustloc.estimators import _compiled

            combos, Ginv, c0 = minimal_subsets(a)
            ho2 = _height2(height_offset, a.shape[0])
            return _compiled.initial_fixes(
                a, np.ascontiguousarray(ranges, dtype=float), ho2, combos, Ginv, c0, centre,
                radius, robust, canonical_rank(a))
        fit = self._linearized(a, ranges, height_offset, None, reference="nearest")
        cands = [_clip_disc(fit.x, centre, radius)]
        with np.errstate(all="ignore"):
            wts = np.where(np.isfinite(ranges), 1.0 / np.maximum(ranges, 0.5) ** 2, 0.0)
            cands.append((wts @ a) / wts.sum(axis=1, keepdims=True))
        if robust:
            cands.append(subset_fixes(a, ranges, height_offset)[0])
        model = RangeModel(a, height_offset)
        best = np.full_like(cands[0], np.nan)
        best_c = np.full(ranges.shape[0], np.inf)
        for xc in cands:
            c = lms_score(model.predict(np.nan_to_num(xc)) - ranges, a.shape[1])
            c = np.where(np.all(np.isfinite(xc), axis=1) & np.isfinite(c), c, np.inf)
            better = c < best_c
            best[better] = xc[better]
            best_c[better] = c[better]
        return best

    def _nonlinear_problem(self, a, z, ranges, rmodel, height_offset, x0):
        if rmodel is not None and self.domain == "rssi":
            return rmodel, z, self._sigma_array(z.shape)
        model = RangeModel(a, height_offset)
        if rmodel is not None:  # RSSI converted to range: s_d = d ln10 s_dB / (10 n)
            s_db = self._sigma_array(z.shape)
            sig = np.maximum(ranges, 0.1) * LN10 * s_db / (10.0 * rmodel.n[None, :])
            return model, ranges, sig
        return model, ranges, self._sigma_array(ranges.shape)

    @staticmethod
    def _range_sigma(sig: Array, ranges: Array, rmodel: RssiModel | None) -> Array:
        """A-priori sigma of each observation as a range (m): ``sig`` itself for ranges,
        ``d ln10 sig_dB / (10 n)`` for RSSI (first-order propagation of seed 000 eq. (1))."""
        if rmodel is None:
            return np.array(sig, dtype=float)
        return np.maximum(ranges, 0.1) * LN10 * sig / (10.0 * rmodel.n[None, :])

    def _sigma_array(self, shape: tuple[int, int]) -> Array:
        if self.sigma is None:
            return np.ones(shape)
        sg = np.atleast_1d(np.asarray(self.sigma, dtype=float))
        if sg.size not in (1, shape[1]):
            raise ValueError(f"sigma has {sg.size} values for {shape[1]} anchors")
        return np.broadcast_to(sg, shape).astype(float)

    def _gn(self, model, obs, x0, sig, weight) -> LinearFit:
        """Gauss-Newton / robust IRLS from ``x0`` with this locator's settings.

        Redescending weights (Hampel, IGG, IGG-III): a Huber(1.5) fit from ``x0``, then
        the redescending fit from both the Huber fix and ``x0`` (the high-breakdown subset
        start), keeping the one with the smaller robust objective.  Measured (IGG RMS):
        on the simulated corridor (fading noise, beacons on two lines, many near-collinear
        subsets; 3 seeds) 2.73 m from the subset start alone, 1.74 m from the Huber fix
        alone, 1.97 m keeping the better; on the benchmark's distinct gross errors (20 %
        outliers) the 95th percentile is 0.21 m from the subset start, 2.2 m from the
        Huber fix, 0.20 m keeping the better.  Two fits within ``tol`` of each other
        (both starts reached one fix) are a tie, kept from the Huber fix, so the choice
        does not rest on rounding.
        """
        kw = dict(
            scale=1.0 if self.robust_scale == "apriori" else None,
            min_scale=self.min_scale, max_iter=self.max_iter, tol=self.tol,
            min_obs=model.anchors.shape[1] + 1, rel_tol=self.rel_tol, warmup=False,
        )
        if self.engine == "compiled" and type(model) is RangeModel:
            fit = _compiled_gn(model, obs, x0, sig, weight, kw)
            if fit is not None:
                return fit
        if weight is None or not np.isfinite(weight.rejection_threshold):
            return gauss_newton(model, obs, x0, sig, weight=weight, **kw)
        hub = gauss_newton(model, obs, x0, sig, weight=Huber(1.5), **kw)
        xh = np.where(np.isfinite(hub.x), hub.x, x0)
        fa = gauss_newton(model, obs, xh, sig, weight=weight, **kw)
        fb = gauss_newton(model, obs, x0, sig, weight=weight, **kw)
        # keep the fit with the smaller robust objective sum rho(v / (s sigma)), with one
        # scale s for both (the smaller MAD scale of the two starts), so they compare
        with np.errstate(all="ignore"):
            s_h = np.fmin(
                mad_scale((model.predict(xh) - obs) / sig, axis=1),
                mad_scale((model.predict(x0) - obs) / sig, axis=1),
            )
        s_h = np.where(np.isfinite(s_h) & (s_h > 0), s_h, 1.0)[:, None]

        def objective(f: LinearFit) -> Array:
            xx = np.where(np.isfinite(f.x), f.x, x0)
            u = (model.predict(xx) - obs) / (sig * s_h)
            val = np.nansum(weight.rho(u), axis=1)
            return np.where(st.among(f.status, st.USABLE), val, np.inf)

        take_b = objective(fb) < objective(fa)
        # both starts reached one fix (within the step tolerance): the warm-up's, so the
        # choice does not rest on rounding (the step's length, as the solvers measure it)
        with np.errstate(invalid="ignore"):
            take_b &= ~(np.sqrt(np.sum((fa.x - fb.x) ** 2, axis=1)) <= self.tol)
        fit = _merge(fa, fb, np.arange(len(take_b)), take_b)
        return replace(fit, iterations=fit.iterations + hub.iterations)

    def _rescue(self, model, obs, sig, wf, fit: LinearFit, a: Array) -> LinearFit:
        """Second chance for epochs that look trapped in a wrong basin.

        A robust fit that failed, left the anchors' area (:func:`_area`) or rejected half
        or more of its observations is restarted from the best point of a coarse grid over
        the square around that disc, scored by :func:`lms_score` (least median of
        squares); the restarted fit replaces the first where its score is smaller.  Only
        those epochs pay for the grid.
        """
        centre, radius = self._the_area(a)
        x = fit.x
        n_obs = np.sum(np.isfinite(obs), axis=1)
        rejected = np.sum(fit.w <= 0, axis=1)  # NaN (not heard) is not rejected
        with np.errstate(invalid="ignore"):
            outside = ~(np.linalg.norm(x - centre, axis=1) <= radius)
        sus = np.flatnonzero((n_obs >= a.shape[1] + 1) & (outside | (rejected * 2 > n_obs)))
        if sus.size == 0:
            return fit
        dim = a.shape[1]
        grid = _rescue_grid(a, centre, radius)
        zs, ss = obs[sus], sig[sus]
        pred_g = model.predict(grid)  # (G, m)
        if self.engine == "compiled":
            from robustloc.estimators import _compiled

            j, _ = _compiled.grid_lms(pred_g, zs, ss, dim)
            best = np.where((j >= 0)[:, None], grid[np.maximum(j, 0)], np.nan)
        else:
            best = np.full((sus.size, dim), np.nan)
            best_c = np.full(sus.size, np.inf)
            for g0 in range(0, grid.shape[0], 64):
                pg = pred_g[g0 : g0 + 64]
                r = np.abs(pg[None, :, :] - zs[:, None, :]) / ss[:, None, :]
                c = lms_score(r, dim, axis=2)  # (S, G)
                j = np.argmin(c, axis=1)
                cj = c[np.arange(sus.size), j]
                upd = cj < best_c
                best[upd] = grid[g0 + j[upd]]
                best_c[upd] = cj[upd]
        refit = self._gn(model, zs, best, ss, wf)

        def score(f: LinearFit, rows: slice | NDArray) -> Array:
            xx = np.nan_to_num(f.x)
            c = lms_score((model.predict(xx) - zs) / ss, dim)
            return np.where(st.among(f.status, st.USABLE), c, np.inf)

        take = score(refit, sus) < score(_rows(fit, sus), sus)
        if not np.any(take):
            return fit
        return _merge(fit, refit, sus, take, inplace=True)  # fit: this call's own

    def _lege_nonlinear(self, model, obs, x0, sig) -> LinearFit:
        base = self._gn(model, obs, x0, sig, None)
        xs = np.where(np.isfinite(base.x), base.x, x0)
        w0 = np.where(np.isfinite(obs), 1.0 / sig**2, 0.0)
        flagged = np.zeros(obs.shape, dtype=bool)
        # LEGE on the linearization y = J dx + e (y = obs - f(x)) at the LS fix, then once
        # more at the fix without the located errors (the first linearization point is
        # pulled by the very errors being sought)
        truncated = np.zeros(obs.shape[0], dtype=bool)
        for _ in range(2):
            pred, J = model.predict(xs), model.jacobian(xs)
            found = lege(J, obs - pred, w0)
            flagged = found.extra["gross_errors"] != 0
            truncated |= found.extra["search_truncated"]
            fit = self._gn(model, np.where(flagged, np.nan, obs), xs, sig, None)
            xs = np.where(np.isfinite(fit.x), fit.x, xs)
        fit.extra.update(
            flagged=flagged, gross_errors=found.extra["gross_errors"], order=found.extra["order"],
            search_truncated=truncated,
        )
        # keep the excluded observations' residuals visible
        v = np.where(flagged, model.predict(np.nan_to_num(fit.x)) - obs, fit.v)
        return LinearFit(
            x=fit.x, v=v, w=np.where(flagged, 0.0, fit.w), qvv=fit.qvv, sigma0=fit.sigma0,
            cov=fit.cov, n_used=fit.n_used, iterations=fit.iterations, converged=fit.converged,
            status=fit.status, extra=fit.extra,
        )

    def _snooping(self, model, obs, x0, sig) -> LinearFit:
        from robustloc.estimators._snooping import snooping_ranging

        return snooping_ranging(self, model, obs, x0, sig)
