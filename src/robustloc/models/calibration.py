"""Calibration of path-loss models and of range bias/scale from a survey.

Every calibration here is a straight-line fit ``y = a + b x`` (or ``y = a`` when the slope
is fixed), per anchor and/or pooled over all anchors, solved for all anchors at once from
grouped sums (no loop over anchors):

* log-distance (seed 000 eq. (1)): ``y = rssi``, ``x = -10 lg d``, ``(a, b) = (A, n)``;
* attenuation factor (seed 002 eq. (5)): ``y = rssi - p0``, ``x = 10 lg(d0/d)``,
  ``(a, b) = (faf, gamma)``;
* free space (seed 002 eq. (4)): ``y = rssi - 20 lg(d0/d)``, ``a = p0`` (no slope);
* range: ``y = range``, ``x = d``, ``(a, b) = (bias, scale)``; without scale
  ``y = range - d``, ``a = bias``.

Least squares gives the parameters, their standard errors from
``cov = s^2 (X^T W X)^-1`` with ``s^2 = sum(w v^2) / (n_used - p)``, and the residual
standard deviation ``s`` (dB for RSSI, m for ranges).

Robust option (the survey has outliers too: people, multipath): iteratively reweighted
least squares with a weight function of :mod:`robustloc.robust.weights` (Huber, Hampel,
IGG, IGG3, ...) on standardized residuals ``u = v / (sigma sqrt(q_vv))``, ``sigma`` the
MAD scale of the current residuals of the group (seed 000 sec. 2.1) and ``q_vv = 1 - h``
(``h`` the leverage), until the parameters change by less than ``tol``.  The standard
errors of the robust fit use the final weights in the formula above (an approximation:
it treats the final weights as known).  Its residual standard deviation (the ``sigma``
written) is the MAD scale of the final residuals standardized by ``sqrt(q_vv)``, not
``s``: Huber's weights leave each gross error ``c |u| sigma^2`` of ``sum(w v^2)``, so with
20 % of a survey's rows 20 dB low ``s`` read 3.6x the noise.

Attenuation factor: only ``p0 + faf`` is identifiable from RSSI alone.  As in the paper,
``p0`` is the reference power at ``d0``; it is taken from ``p0=`` (scalar or per anchor),
else as the mean survey RSSI of that anchor within 5 % of ``d0``, else as the pooled mean
there; with no sample near ``d0`` and no ``p0`` given it is an error.

A survey may carry a ``weight`` column: frequency weights of its rows (how many
observations each row counts for, e.g. a sample count or the count of each bin of an RSSI
histogram), used in every sum above; the residual degrees of freedom are their total
minus the parameters, so probabilities summing to 1 are too little weight.

Anchors with fewer survey rows than parameters + 1 get the pooled parameters (column
``calib_source = "pooled"``), so that every anchor is usable after calibration.

Range calibration is applied as ``range_corrected = (range - bias) / scale``
(:func:`apply_range_calibration`): ``bias`` is the constant offset of the ranging device
(m), ``scale`` its scale factor (1 when not fitted).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from robustloc._arrays import to_number
from robustloc.errors import InputError
from robustloc.io.limits import PATH_LOSS_EXPONENT_LIMITS
from robustloc.models.selfcal import SelfCalibration
from robustloc.robust.scale import MAD_NORMAL
from robustloc.robust.weights import Huber, WeightFunction, get_weight

Array = NDArray[np.float64]

#: Fitted columns written to the anchors file, per model.
FIT_COLUMNS: dict[str, tuple[str, ...]] = {
    "log-distance": ("A", "n"),
    "attenuation-factor": ("p0", "gamma", "faf", "d0"),
    "friis": ("p0", "d0"),
    "range": ("bias", "scale"),
}
PATHLOSS_MODELS = ("log-distance", "attenuation-factor", "friis")
#: Path-loss columns of every model, dropped from an anchors file when another model is
#: written (so ``locate`` cannot pick stale parameters).
_ALL_PATHLOSS_COLUMNS = ("A", "n", "p0", "gamma", "faf", "d0")
POOLED = "*pooled*"


# --------------------------------------------------------------------------------------
# batched line fit
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LineFit:
    """Grouped weighted fit of ``y = a + b x`` (``b`` fixed at 0 when ``slope=False``).

    Arrays have one entry per group (shape ``(g,)``), except ``weights`` and ``residuals``
    (one per row, ``v = a + b x - y``).  ``residual_std`` is ``sqrt(sum(w v^2) / dof)`` of a
    least-squares fit and the MAD scale of a robust one's (module doc).  ``n_count``: the
    observations each group's fit counts, ``n_used`` without prior weights and the sum of
    the frequency weights of the rows in use with them (``dof + p``); None: ``n_used``.
    """

    a: Array
    b: Array
    a_se: Array
    b_se: Array
    cov_ab: Array
    residual_std: Array
    n_obs: NDArray[np.int64]
    n_used: NDArray[np.int64]
    iterations: int
    converged: bool
    weights: Array
    residuals: Array
    n_count: Array | None = None

    def counted(self) -> Array:
        """:attr:`n_count`, or :attr:`n_used` where it is None."""
        return np.asarray(self.n_used if self.n_count is None else self.n_count,
                          dtype=float)



def _sigma_floor(sigma: ArrayLike) -> Array:
    """A fitted ``sigma`` as an anchors file may carry it: at least the lower end of
    :data:`robustloc.options.SIGMA_RANGE` (1e-6), which an exact simulation's residual
    standard deviation (some 1e-12) would undercut, so that ``locate`` reads the
    calibrated file back."""
    from robustloc.options import SIGMA_RANGE

    with np.errstate(invalid="ignore"):
        return np.where(np.isnan(sigma), np.nan, np.maximum(np.asarray(sigma, float),
                                                            SIGMA_RANGE[0]))

def _group_sums(g: NDArray[np.int64], n_groups: int, *cols: Array) -> list[Array]:
    return [np.bincount(g, weights=c, minlength=n_groups) for c in cols]


def _solve_lines(
    x: Array, y: Array, w: Array, g: NDArray[np.int64], n_groups: int, slope: bool
) -> tuple[Array, Array, Array]:
    """Weighted least squares per group from sums; returns ``a, b, det``."""
    sw, swx, swy, swxx, swxy = _group_sums(g, n_groups, w, w * x, w * y, w * x * x, w * x * y)
    if not slope:
        with np.errstate(invalid="ignore", divide="ignore"):
            a = swy / sw
        return a, np.zeros(n_groups), sw
    det = sw * swxx - swx * swx
    with np.errstate(invalid="ignore", divide="ignore"):
        b = (sw * swxy - swx * swy) / det
        a = (swy - b * swx) / sw
    return a, b, det


def fit_lines(
    x: ArrayLike,
    y: ArrayLike,
    group: ArrayLike,
    n_groups: int,
    *,
    slope: bool = True,
    robust: WeightFunction | None = None,
    max_iter: int = 50,
    tol: float = 1e-8,
    weights: ArrayLike | None = None,
    cluster: ArrayLike | None = None,
) -> LineFit:
    """Fit ``y = a + b x`` in every group at once; least squares or robust IRLS.

    Parameters
    ----------
    x, y : array_like, shape (k,)
        Regressor and observation of each row (``x`` ignored when ``slope=False``).
    group : array_like of int, shape (k,)
        Group index of each row in ``0 .. n_groups-1``.
    n_groups : int
    slope : bool
        Fit the slope ``b`` (else ``b = 0``, one parameter).
    robust : WeightFunction, optional
        IRLS weight function on standardized residuals (MAD scale per group, leverage
        ``q_vv = 1 - h``); ``None`` for least squares.
    max_iter, tol : int, float
        IRLS stop: ``max |delta a|, |delta b| < tol`` or ``max_iter`` iterations.
    weights : array_like, shape (k,), optional
        Prior (frequency) weights of the rows, e.g. histogram counts;
        the robust weights multiply them.  The residual variance is
        ``sum(w v^2) / (sum of the prior weights of the rows in use - p)``.
    cluster : array_like of int, shape (k,), optional
        A cluster id per row (rows whose errors may be correlated: a tag dwelling at one
        point sees the same multipath): the standard errors are then cluster-robust,
        :func:`cluster_robust_lines`.  Default: the rows are independent.

    Returns
    -------
    LineFit
        Groups with too few rows (``n_used <= p``) have NaN parameters or standard errors.
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    g = np.asarray(group, dtype=np.int64)
    p = 2 if slope else 1
    w0 = np.ones_like(y) if weights is None else np.asarray(weights, dtype=float)
    if w0.shape != y.shape or np.any(~np.isfinite(w0)) or np.any(w0 < 0):
        raise ValueError("weights must be finite, non-negative, one per row")
    w = w0.copy()
    xs = x if slope else np.zeros_like(y)
    a, b, _ = _solve_lines(xs, y, w, g, n_groups, slope)
    it = 0
    converged = robust is None
    if robust is not None:
        stages: list[WeightFunction] = [robust]
        if np.isfinite(robust.rejection_threshold):
            # redescending weights: converge with Huber first, so the final stage starts
            # near the robust solution rather than at the outlier-pulled LS line
            stages = [Huber(1.5), robust]
        for wf in stages:
            a, b, w, k, converged = _irls(
                xs, y, g, n_groups, slope, wf, a, b, max_iter, tol, w0
            )
            it += k
    with np.errstate(invalid="ignore", over="ignore"):  # (an undetermined group: inf)
        v = a[g] + b[g] * xs - y
    used = w > 0
    n_obs = np.bincount(g, minlength=n_groups).astype(np.int64)
    n_used = np.bincount(g, weights=used.astype(float), minlength=n_groups).astype(np.int64)
    (wvv, n_freq) = _group_sums(g, n_groups, w * v * v, np.where(used, w0, 0.0))
    n_count = n_used.astype(float) if weights is None else n_freq
    dof = n_count - p
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = np.where(dof > 0, wvv / np.maximum(dof, 1), np.nan)
    sw, swx, swxx = _group_sums(g, n_groups, w, w * xs, w * xs * xs)
    with np.errstate(invalid="ignore", divide="ignore"):
        if slope:
            det = sw * swxx - swx * swx
            var_a = s2 * swxx / det
            var_b = s2 * sw / det
            cov_ab = -s2 * swx / det
        else:
            var_a = s2 / sw
            var_b = np.zeros(n_groups)
            cov_ab = np.zeros(n_groups)
    if cluster is not None:
        var_a, var_b, cov_ab = cluster_robust_lines(
            xs, v, w, g, n_groups, slope, np.asarray(cluster, dtype=np.int64),
            (var_a, var_b, cov_ab))
    few = n_used < p
    a = np.where(few, np.nan, a)
    b = np.where(few, np.nan, b) if slope else b
    sd = np.sqrt(s2)
    if robust is not None:
        # the noise scale of a robust fit: the MAD about zero of the residuals standardized
        # by their redundancy, sqrt(q_vv) (seed 000 sec. 2.1; the estimator of the IRLS
        # and of locate's log scale).  sum(w v^2) / dof is not one: Huber's weights leave
        # a gross error c |u| sigma^2 of it (20 % of rows 20 dB low: 3.6x the noise), and
        # a redescending weight's rejections take the noise's tails with them (IGG3 0.85x
        # on Gaussian rows)
        with np.errstate(invalid="ignore", divide="ignore"):
            w_rob = np.where(w0 > 0, w / w0, 0.0)
        qvv = np.clip(1.0 - _leverage(xs, w, g, n_groups, slope, w_rob), 1e-12, None)
        with np.errstate(invalid="ignore"):
            mad = _grouped_mad(v / np.sqrt(qvv), g, n_groups, w0)
        sd = np.where(dof > 0, mad, np.nan)
    return LineFit(
        a=a, b=b, a_se=_sqrt(var_a), b_se=_sqrt(var_b) if slope else var_b,
        cov_ab=cov_ab, residual_std=sd, n_obs=n_obs, n_used=n_used,
        iterations=it, converged=converged, weights=w, residuals=v, n_count=n_count,
    )


#: At most this many clusters per group in :func:`cluster_robust_lines` (contiguous ones
#: merged), as the self-calibration's time blocks (:mod:`robustloc.models.selfcal`).
SE_CLUSTERS = 50


def cluster_robust_lines(
    x: Array, v: Array, w: Array, g: NDArray[np.int64], n_groups: int, slope: bool,
    cluster: NDArray[np.int64], model: tuple[Array, Array, Array],
) -> tuple[Array, Array, Array]:
    """Cluster-robust (sandwich) ``var a, var b, cov ab`` of :func:`fit_lines`.

    ``N^-1 (sum_c s_c s_c^T) N^-1 G / (G - 1)`` per group (Liang & Zeger 1986), ``N`` the
    group's weighted normal matrix, ``s_c = sum_{i in c} w_i v_i (1, x_i)`` the score of
    cluster ``c`` and ``G`` the group's number of clusters; at most :data:`SE_CLUSTERS`
    per group, contiguous clusters (in id order) merged.  Each variance is floored at the
    model's (``model``: independent rows), as the self-calibration's are; a group with
    fewer than two clusters keeps the model's.  With independent errors the two agree;
    a tag dwelling at survey points shares each point's multipath across its rows, and
    the model's standard errors came out 8x too small there (the calibration review,
    2026-12-06: 65 % of the biases more than 4 of them from the truth).
    """
    var_a, var_b, cov_ab = (np.array(m, dtype=float, copy=True) for m in model)
    use = (w > 0) & np.isfinite(v)
    if not use.any():
        return var_a, var_b, cov_ab
    gu, cu = g[use], cluster[use]
    pair, inv = np.unique(np.stack([gu, cu]), axis=1, return_inverse=True)
    inv = inv.ravel()
    pg = pair[0]  # the pairs sorted by group, then cluster id
    n_c = np.bincount(pg, minlength=n_groups)
    first = np.concatenate([[0], np.cumsum(n_c)[:-1]])
    rank = np.arange(pg.size) - first[pg]
    blocks = np.minimum(n_c, SE_CLUSTERS)
    blk = (rank * blocks[pg]) // np.maximum(n_c[pg], 1)  # contiguous merge
    key = pg * SE_CLUSTERS + blk
    wv = (w * v)[use]
    s1 = np.bincount(key[inv], weights=wv, minlength=n_groups * SE_CLUSTERS)
    sx = np.bincount(key[inv], weights=wv * x[use], minlength=n_groups * SE_CLUSTERS)
    s1, sx = s1.reshape(n_groups, SE_CLUSTERS), sx.reshape(n_groups, SE_CLUSTERS)
    m11, m12, m22 = (s1 * s1).sum(1), (s1 * sx).sum(1), (sx * sx).sum(1)
    G = blocks.astype(float)
    ok = G >= 2
    with np.errstate(invalid="ignore", divide="ignore"):
        f = np.where(ok, G / np.maximum(G - 1.0, 1.0), np.nan)
        sw, swx, swxx = _group_sums(g, n_groups, w, w * x, w * x * x)
        if slope:
            det = sw * swxx - swx * swx
            i11, i12, i22 = swxx / det, -swx / det, sw / det
            ca = f * (i11 * i11 * m11 + 2 * i11 * i12 * m12 + i12 * i12 * m22)
            cb = f * (i12 * i12 * m11 + 2 * i12 * i22 * m12 + i22 * i22 * m22)
            cab = f * (i11 * i12 * m11 + (i11 * i22 + i12 * i12) * m12 + i12 * i22 * m22)
        else:
            ca = f * m11 / (sw * sw)
            cb = np.zeros(n_groups)
            cab = np.zeros(n_groups)
    fin = ok & np.isfinite(ca) & np.isfinite(cb)
    var_a = np.where(fin, np.fmax(var_a, ca), var_a)
    if slope:
        var_b = np.where(fin, np.fmax(var_b, cb), var_b)
        cov_ab = np.where(fin, cab, cov_ab)
    return var_a, var_b, cov_ab


def _sqrt(v: Array) -> Array:
    """Square root of a variance; NaN (no standard error) where it is not >= 0."""
    with np.errstate(invalid="ignore"):
        return np.sqrt(v)


def _irls(
    xs: Array, y: Array, g: NDArray[np.int64], n_groups: int, slope: bool,
    wf: WeightFunction, a: Array, b: Array, max_iter: int, tol: float, w0: Array,
) -> tuple[Array, Array, Array, int, bool]:
    w = w0.copy()
    for k in range(1, max_iter + 1):
        v = a[g] + b[g] * xs - y
        # per-observation leverage: a row of frequency weight c stands for c observations,
        # each with q_vv = 1 - p_robust x^T N^-1 x
        with np.errstate(invalid="ignore", divide="ignore"):
            w_rob = np.where(w0 > 0, w / w0, 0.0)
        qvv = np.clip(1.0 - _leverage(xs, w, g, n_groups, slope, w_rob), 1e-12, None)
        # robust scale per group: med|v| / 0.6745 over the rows in use (seed 000 sec. 2.1)
        sigma = _grouped_mad(v, g, n_groups, w0)
        with np.errstate(invalid="ignore", divide="ignore"):
            u = v / (sigma[g] * np.sqrt(qvv))
        u = np.where(np.isfinite(u), u, 0.0)  # zero scale (exact fit): keep full weight
        w = w0 * np.nan_to_num(wf.weights(u), nan=0.0)
        a_new, b_new, _ = _solve_lines(xs, y, w, g, n_groups, slope)
        step = np.abs(np.concatenate([a_new - a, b_new - b]))
        step = np.nanmax(step) if np.isfinite(step).any() else 0.0
        a, b = np.where(np.isfinite(a_new), a_new, a), np.where(np.isfinite(b_new), b_new, b)
        if step < tol:
            return a, b, w, k, True
    return a, b, w, max_iter, False


def _leverage(
    x: Array, w: Array, g: NDArray[np.int64], n_groups: int, slope: bool,
    p: Array | None = None,
) -> Array:
    """Hat-matrix diagonal ``h_i = p_i x_i^T (X^T W X)^-1 x_i`` per row (``p = w`` unless
    given)."""
    p = w if p is None else p
    sw, swx, swxx = _group_sums(g, n_groups, w, w * x, w * x * x)
    with np.errstate(invalid="ignore", divide="ignore"):
        if not slope:
            return np.nan_to_num(p / sw[g])
        det = sw * swxx - swx * swx
        h = p * (swxx[g] - 2.0 * x * swx[g] + x * x * sw[g]) / det[g]
    return np.nan_to_num(h)


def _grouped_mad(
    v: Array, g: NDArray[np.int64], n_groups: int, w: Array | None = None
) -> Array:
    """``med|v| / 0.6745`` per group, NaN ignored; a weighted median with weights ``w``
    (the lower weighted median averaged with the next value at an exact half, which
    equals the plain median of the rows repeated ``w`` times for integer ``w``)."""
    a = np.abs(v)
    ok = np.isfinite(a)
    if w is None:
        out = pd.Series(a[ok]).groupby(g[ok]).median()
        s = np.full(n_groups, np.nan)
        s[out.index.to_numpy()] = out.to_numpy()
        return s / MAD_NORMAL
    ok &= w > 0
    a, gg, ww = a[ok], g[ok], w[ok]
    order = np.lexsort((a, gg))
    a, gg, ww = a[order], gg[order], ww[order]
    tot = np.bincount(gg, weights=ww, minlength=n_groups)
    start = np.concatenate(([0.0], np.cumsum(tot)[:-1]))
    cum = np.cumsum(ww) - start[gg]  # cumulative weight within the group
    half = 0.5 * tot[gg]
    s = np.full(n_groups, np.nan)
    first = (cum >= half - 1e-12 * tot[gg]) & (cum - ww < half - 1e-12 * tot[gg])
    idx = np.flatnonzero(first)
    med = a[idx].copy()
    exact = np.isclose(cum[idx], half[idx], rtol=1e-12, atol=0.0)
    nxt = np.minimum(idx + 1, len(a) - 1)
    same = gg[nxt] == gg[idx]
    med = np.where(exact & same, 0.5 * (med + a[nxt]), med)
    s[gg[idx]] = med
    return s / MAD_NORMAL


# --------------------------------------------------------------------------------------
# calibrations
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CalibrationResult:
    """Fitted parameters per anchor and pooled.

    Attributes
    ----------
    model : str
        ``log-distance``, ``attenuation-factor``, ``friis`` or ``range``.
    table : DataFrame
        One row per anchor plus a last row ``anchor = "*pooled*"``: the fitted columns
        (:data:`FIT_COLUMNS`), their standard errors (``<col>_se``), ``residual_std`` (dB
        or m), ``n_obs``, ``n_used`` (rows with non-zero weight), ``calib_source``
        (``anchor`` or ``pooled``: anchors with too few survey rows take the pooled fit).
    pooled : bool
        Whether :meth:`apply_to_anchors` writes the pooled parameters to every anchor.
    robust : str or None
        Weight function name of a robust fit.
    unit : str
        ``dB`` or ``m``.
    """

    model: str
    table: pd.DataFrame
    pooled: bool = False
    robust: str | None = None
    unit: str = "dB"
    notes: list[str] = field(default_factory=list)

    def parameters(self) -> pd.DataFrame:
        """Per-anchor parameters actually used (pooled rows substituted), indexed by anchor."""
        t = self.table.set_index("anchor")
        per = t.drop(index=POOLED)
        if self.pooled:
            per = per.copy()
            for c in FIT_COLUMNS[self.model]:
                if self.model == "attenuation-factor" and c in ("p0", "d0"):
                    continue  # gamma, faf pooled relative to each anchor's own p0 at d0
                per[c] = t.loc[POOLED, c]
                if f"{c}_se" in per.columns:
                    per[f"{c}_se"] = t.loc[POOLED, f"{c}_se"]
            per["calib_source"] = "pooled"
        return per

    def se_columns(self) -> list[str]:
        """The standard-error columns (``<col>_se``) of the fitted parameters."""
        return [f"{c}_se" for c in FIT_COLUMNS[self.model] if f"{c}_se" in self.table.columns]

    def _sigma(self, ids: pd.Series) -> Array:
        """The ``sigma`` written per anchor id (see :meth:`apply_to_anchors`): for ranges
        divided by the ``scale`` written, the standard deviation of the corrected range
        ``(range - bias) / scale`` that ``locate`` fits (the residual standard deviation
        is the raw range's)."""
        par = self.parameters()
        pooled = self.table.set_index("anchor").loc[POOLED]
        pooled_sd = float(pooled["residual_std"])
        sd = ids.map(par["residual_std"]).astype(float).to_numpy()
        use_pooled = self.pooled | ~(np.isfinite(sd) & (sd > 0))
        sd = np.where(use_pooled, pooled_sd, sd)
        if self.model == "range":
            sc = ids.map(par["scale"]).astype(float).fillna(float(pooled["scale"]))
            sd = sd / sc.to_numpy()
        return _sigma_floor(sd)

    def apply_to_anchors(self, anchors: pd.DataFrame | None) -> pd.DataFrame:
        """Anchors frame with the fitted columns set (added or replaced).

        Anchors absent from the survey get the pooled parameters, except that with the
        attenuation-factor model an anchor keeps the anchors file's own ``p0`` and ``d0``
        where it has a ``p0`` (``gamma`` and ``faf`` are pooled relative to each anchor's
        own ``p0``).  For a path-loss model the columns of the *other* path-loss models are
        dropped, so ``locate`` cannot pick stale parameters; so are the standard errors
        (``<col>_se``) of every path-loss column and a self-calibration's ``calib_fixed``,
        which would describe an earlier calibration.  Without ``anchors``, returns
        ``anchor`` + parameters.

        Written with the parameters: their standard errors (``<col>_se``, the pooled ones
        where the pooled fit is written) and ``sigma``, the fit's residual standard
        deviation (dB for RSSI, m for ranges; of a robust fit the MAD scale of its
        residuals; the pooled one for pooled fits or where an anchor's own is not
        positive), for ranges divided by the ``scale`` written: the standard deviation
        of the corrected range ``(range - bias) / scale``.  ``robustloc locate`` weights
        each anchor by it.
        """
        cols = list(FIT_COLUMNS[self.model])
        se = self.se_columns()
        par = self.parameters()
        pooled_row = self.table.set_index("anchor").loc[POOLED]
        if anchors is None:
            out = par[cols + ["calib_source"]].reset_index()
            out["sigma"] = self._sigma(out["anchor"].astype(str))
            for c in se:
                out[c] = par[c].to_numpy(dtype=float)
            return out
        out = anchors.copy()
        fitted = cols if self.model == "range" else list(_ALL_PATHLOSS_COLUMNS)
        stale = [f"{c}_se" for c in fitted] + ["calib_fixed"]
        if self.model in PATHLOSS_MODELS:
            stale += [c for c in _ALL_PATHLOSS_COLUMNS if c not in cols]
        out = out.drop(columns=[c for c in out.columns if c in stale])
        ids = out["anchor"].astype(str)
        own = ["p0", "d0"] if self.model == "attenuation-factor" and "p0" in anchors.columns else []
        has_own = (to_number(anchors["p0"]).notna().to_numpy()
                   if own else np.zeros(len(ids), dtype=bool))
        for c in cols:
            vals = ids.map(par[c]).astype(float)
            if c in own and c in anchors.columns:
                # an absent anchor keeps its own p0 (and the d0 that goes with it)
                mine = to_number(anchors[c]).where(has_own)
                vals = vals.fillna(pd.Series(mine.to_numpy(dtype=float), index=vals.index))
            out[c] = vals.fillna(float(pooled_row[c])).to_numpy()
        src = ids.map(par["calib_source"])
        out["calib_source"] = src.fillna("pooled").to_numpy()
        out["sigma"] = self._sigma(ids)
        for c in se:
            out[c] = ids.map(par[c]).astype(float).fillna(float(pooled_row[c])).to_numpy()
        return out

    def absent_anchors(self, anchors: pd.DataFrame | None) -> list[str]:
        """Ids of ``anchors`` without a survey row (they get the pooled fit)."""
        if anchors is None:
            return []
        known = set(self.table["anchor"].astype(str)) - {POOLED}
        return [a for a in anchors["anchor"].astype(str) if a not in known]

    def summary(self) -> pd.DataFrame:
        """The table with parameters and standard errors, for printing."""
        return self.table.copy()


def _robust_weight(robust: str | WeightFunction | None) -> WeightFunction | None:
    if robust is None or robust is False:
        return None
    if isinstance(robust, WeightFunction):
        return robust
    return get_weight(str(robust))


def _survey_values(survey: pd.DataFrame, value: str, path_loss: bool) -> tuple[Array, Array]:
    """The survey's ``distance`` and ``value`` columns as floats, checked: distances finite
    and positive (``>= 0`` for ranges: a log of 0 has no path loss), values finite within
    their physical limits.  ``read_survey`` checks a file's rows; a hand-made frame had
    given an anchor's bias NaN from one NaN distance, with no error, and a distance of 0
    was blamed on "constant values?" (the API review)."""
    from robustloc.io.limits import limits_for

    d = to_number(survey["distance"]).to_numpy(dtype=float)
    v = to_number(survey[value]).to_numpy(dtype=float)
    lim = limits_for(value)
    with np.errstate(invalid="ignore"):
        bad_d = ~(np.isfinite(d) & ((d > 0) if path_loss else (d >= 0)))
    for bad, col, what in ((bad_d, "distance", "a finite distance " +
                            ("> 0 m" if path_loss else ">= 0 m")),
                           (~lim.check(v), value, f"finite, within [{lim.low:g}, "
                            f"{lim.high:g}] {lim.unit}")):
        if bad.any():
            i = int(np.argmax(bad))
            line = int(survey.index[i]) if survey.index.name == "line" else None
            raise InputError(f"column '{col}': {str(survey[col].iloc[i])!r} must be {what}",
                             survey.attrs.get("path"), line)
    return d, v


#: The largest frequency weight of a survey row (the copies of it the fit counts).
SURVEY_WEIGHT_MAX = 1e9


def _survey_weights(survey: pd.DataFrame) -> Array | None:
    """The survey's optional ``weight`` column (frequency weights), validated."""
    if "weight" not in survey.columns:
        return None
    w = to_number(survey["weight"]).to_numpy(dtype=float)
    # at most SURVEY_WEIGHT_MAX copies of a row: 1e300 on every row overflowed the fit's
    # sums into "fitted n = nan is not positive" (the input review)
    bad = ~((w >= 0) & (w <= SURVEY_WEIGHT_MAX))
    if bad.any():
        i = int(np.argmax(bad))
        line = int(survey.index[i]) if survey.index.name == "line" else None
        raise InputError(
            f"column 'weight': {str(survey['weight'].iloc[i])!r} must be a finite number in "
            f"[0, {SURVEY_WEIGHT_MAX:g}]", survey.attrs.get("path"), line,
        )
    return w


def _natural_key(s: str) -> tuple[int, float, str]:
    try:
        return (0, float(s), s)
    except ValueError:
        return (1, 0.0, s)


def _cluster_key(s: str) -> tuple:
    """Natural sort key of a cluster id: numbers numerically (``2.0`` and ``2`` alike),
    text by its runs of digits as numbers (``p2`` before ``p10``)."""
    try:
        return (0, float(s), ())
    except ValueError:
        return (1, 0.0, tuple((0, int(p), "") if p.isdigit() else (1, 0, p)
                              for p in re.split(r"(\d+)", s) if p))


def _survey_clusters(survey: pd.DataFrame) -> NDArray[np.int64] | None:
    """The cluster of each row (column ``cluster``: a survey built from positions,
    :func:`survey_from_positions`, has its dwells there; a survey file may name its own,
    any ids, e.g. the surveyed point of each sample), as codes in the ids' natural order
    (:func:`_cluster_key`: p2 before p10); a row without one is a cluster of its
    own.  None without the column, or with no id in it (rows taken as independent: a
    column left empty says no more than one left out, and was an IndexError traceback
    on the empty list of ids, the commands review).  (A file's text ids were
    a ValueError traceback: the review of 2026-12-06.)  Sorted, not in order of
    appearance: :func:`cluster_robust_lines` merges neighbouring codes into blocks, and
    codes numbered by appearance put a shuffled file's far-apart dwells side by side
    (standard errors 3.3x smaller than those of the same rows sorted: the calibration
    review of 2026-12-06)."""
    if "cluster" not in survey.columns:
        return None
    ids = survey["cluster"]
    # an empty field is no id, from a file (NaN) or a DataFrame ("" or blanks): "" was
    # one cluster of all such rows, where a file's empty field stands alone
    text = ids.astype(str)
    codes, uniques = pd.factorize(text.where(~(ids.isna() | text.str.strip().eq(""))))
    if len(uniques) == 0:
        return None
    codes = codes.astype(np.int64)
    order = sorted(range(len(uniques)), key=lambda i: _cluster_key(str(uniques[i])))
    remap = np.empty(len(uniques), dtype=np.int64)
    remap[order] = np.arange(len(uniques))
    codes = np.where(codes >= 0, remap[np.maximum(codes, 0)], -1)
    alone = codes < 0  # (missing: NaN or an empty field)
    if alone.any():
        codes[alone] = codes.max(initial=-1) + 1 + np.arange(int(alone.sum()))
    return codes


def _groups(survey: pd.DataFrame) -> tuple[NDArray[np.int64], list[str]]:
    """Group index per row; anchors in natural order (numeric ids numerically)."""
    codes, uniques = pd.factorize(survey["anchor"].astype(str), sort=False)
    ids = [str(u) for u in uniques]
    order = sorted(range(len(ids)), key=lambda i: _natural_key(ids[i]))
    remap = np.empty(len(ids), dtype=np.int64)
    remap[order] = np.arange(len(ids))
    return remap[codes], [ids[i] for i in order]


def _p0_per_anchor(
    survey: pd.DataFrame,
    g: NDArray[np.int64],
    ids: list[str],
    d0: Array,
    p0: float | Mapping[str, float] | None,
    weights: Array | None = None,
) -> Array:
    """``p0`` per anchor (module notes); ``d0`` per anchor, shape ``(m,)``; ``weights``:
    the survey's frequency weights (:func:`_survey_weights`), by which the readings near
    ``d0`` are averaged, as the same rows repeated would be (the unweighted mean, weight-0
    rows included, gave p0 -45 dBm for the -41 of the rows repeated, and moved faf by as
    much: the calibration review)."""
    m = len(ids)
    if isinstance(p0, Mapping):
        vals = np.array([float(p0.get(a, np.nan)) for a in ids])
    elif p0 is not None:
        vals = np.full(m, float(p0))
    else:
        vals = np.full(m, np.nan)
    if np.all(np.isfinite(vals)):
        return vals
    d = survey["distance"].to_numpy(dtype=float)
    r = survey["rssi"].to_numpy(dtype=float)
    w = np.ones_like(r) if weights is None else np.asarray(weights, dtype=float)
    near = (np.abs(d - d0[g]) <= 0.05 * d0[g]) & (w > 0)
    cnt = np.bincount(g[near], weights=w[near], minlength=m)
    s = np.bincount(g[near], weights=w[near] * r[near], minlength=m)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_near = s / cnt
    pooled_near = (float(np.sum(w[near] * r[near]) / np.sum(w[near])) if near.any()
                   else np.nan)
    vals = np.where(np.isfinite(vals), vals, mean_near)
    vals = np.where(np.isfinite(vals), vals, pooled_near)
    if not np.all(np.isfinite(vals)):
        raise InputError(
            f"attenuation-factor fit needs the reference power p0 at d0 = "
            f"{', '.join(f'{v:g}' for v in np.unique(d0))} m: give p0 "
            "(--p0, or a p0 column in the anchors file) or survey rows at that distance",
            survey.attrs.get("path"),
        )
    return vals


def calibrate_pathloss(
    survey: pd.DataFrame,
    model: str = "log-distance",
    *,
    robust: str | WeightFunction | None = None,
    pooled: bool = False,
    d0: float | Mapping[str, float] = 1.0,
    p0: float | Mapping[str, float] | None = None,
    max_iter: int = 50,
) -> CalibrationResult:
    """Fit a path-loss model per anchor and pooled from an RSSI survey.

    Parameters
    ----------
    survey : DataFrame
        ``anchor, distance, rssi`` (:func:`robustloc.io.read_survey`).
    model : {"log-distance", "attenuation-factor", "friis"}
        Log-distance ``A, n`` (seed 000 eq. (1)); attenuation factor ``gamma, faf`` with
        ``p0`` fixed (seed 002 eq. (5)); free space ``p0`` with exponent 2 (eq. (4)).
    robust : str or WeightFunction, optional
        Robust IRLS (e.g. ``"huber"``, ``"igg3"``); default least squares.
    pooled : bool
        Write the pooled fit (all anchors together) to every anchor.
    d0 : float or mapping anchor -> float
        Reference distance (m) of the attenuation-factor and Friis models; per anchor
        (every survey anchor, e.g. the anchors file's ``d0`` that goes with its ``p0``)
        for the attenuation-factor model only.
    p0 : float or mapping anchor -> float, optional
        Reference power for the attenuation-factor fit (see the module notes).
    max_iter : int
        IRLS iteration limit.

    Returns
    -------
    CalibrationResult
    """
    if model not in PATHLOSS_MODELS:
        raise ValueError(f"unknown path-loss model {model!r}; one of {', '.join(PATHLOSS_MODELS)}")
    if "rssi" not in survey.columns:
        raise InputError(
            "path-loss calibration needs an RSSI survey (anchor, distance, rssi)",
            survey.attrs.get("path"), 1,
        )
    weight = _robust_weight(robust)
    g, ids = _groups(survey)
    d, r = _survey_values(survey, "rssi", path_loss=True)
    m = len(ids)
    if isinstance(d0, Mapping):
        if model != "attenuation-factor":
            raise ValueError("d0 per anchor is for the attenuation-factor model")
        missing = [a for a in ids if a not in d0]
        if missing:
            raise ValueError(f"d0 per anchor has no value for anchor(s) {', '.join(missing)}")
        d0_arr = np.array([float(d0[a]) for a in ids])
    else:
        d0_arr = np.full(m, float(d0))
    if not np.all(d0_arr > 0):  # NaN too
        raise ValueError(f"d0 must be positive, got {d0}")
    sw = _survey_weights(survey)
    p0_arr = np.zeros(m)  # the level offset: the attenuation-factor p0, else 0
    if model == "log-distance":
        x, y, slope = -10.0 * np.log10(d), r, True
    elif model == "attenuation-factor":
        p0_arr = _p0_per_anchor(survey, g, ids, d0_arr, p0, sw)
        x, y, slope = 10.0 * np.log10(d0_arr[g] / d), r - p0_arr[g], True
    else:
        x, y, slope = np.zeros_like(d), r - 20.0 * np.log10(d0_arr[g] / d), False
    cl = _survey_clusters(survey)
    per = fit_lines(x, y, g, m, slope=slope, robust=weight, max_iter=max_iter, weights=sw,
                    cluster=cl)
    pool = fit_lines(
        x, y, np.zeros_like(g), 1, slope=slope, robust=weight, max_iter=max_iter, weights=sw,
        cluster=cl,
    )
    names = {"log-distance": ("A", "n"), "attenuation-factor": ("faf", "gamma"),
             "friis": ("p0",)}[model]
    _check_determined(survey, per, pool, ids, d, g, names, pooled, "RSSI")
    _check_plausible(survey, per, pool, ids, model, pooled,
                     p0_arr, d0_arr)
    rows = _assemble(per, pool, ids, slope,
                     _one_distance(d, g, m, sw) if slope and pooled else None)
    if model == "log-distance":
        table = _table(rows, {"A": "a", "n": "b"})
    elif model == "attenuation-factor":
        table = _table(rows, {"faf": "a", "gamma": "b"})
        # the pooled row's p0 (for anchors absent from the survey with no p0 of their
        # own): the anchors' p0 brought to one reference distance with the pooled gamma,
        # P(d0') = p0 + 10 gamma lg(d0 / d0') (seed 002 eq. (5)), and averaged
        d0_pool = float(np.median(d0_arr))
        if p0 is None or isinstance(p0, Mapping):
            gam = float(pool.b[0])
            pooled_p0 = float(np.mean(p0_arr + 10.0 * gam * np.log10(d0_arr / d0_pool)))
        else:
            pooled_p0 = float(p0)
        table.insert(1, "p0", np.append(p0_arr, pooled_p0))
        table["d0"] = np.append(d0_arr, d0_pool)
    else:
        table = _table(rows, {"p0": "a"})
        table["d0"] = np.append(d0_arr, d0_arr[0])
    notes = _notes(per, ids, weight, 2 if slope else 1)
    truncated = _truncation_note(r, d, g, per)
    if truncated:
        notes.append(truncated)
    return CalibrationResult(
        model=model, table=table, pooled=pooled,
        robust=None if weight is None else weight.name, unit="dB", notes=notes,
    )


#: The share of the survey's readings the fitted model puts below the lowest reading
#: received, above which :func:`_truncation_note` speaks (a Gaussian fit of an
#: untruncated survey puts about 1 / (2 N) there).
TRUNCATED_SHARE = 0.02


def _truncation_note(r: Array, d: Array, g: NDArray[np.int64], per: LineFit) -> str | None:
    """A note when the survey looks cut at a receiver's sensitivity: the fitted model
    (each anchor's line and residual sd) puts more than :data:`TRUNCATED_SHARE` of the
    readings below the lowest one received, ``sum_i p_i / (1 - p_i)``, ``p_i =
    Phi((floor - r_hat_i) / sigma)`` (the expected count of readings lost at each
    received one's distance, for a Gaussian fit).  A receiver drops what reads below
    its sensitivity, so the far distances keep only their strong readings and a
    least-squares fit comes out with ``n`` low and ``A`` high (the simulated BLE corridor:
    n 1.86-2.20 for the true 2.2, fixes 1.41 m RMS against 0.99 m with the true model --
    the new-user review, 2026-12-06)."""
    from scipy.special import ndtr

    use = np.isfinite(per.residuals) & (per.weights > 0) & np.isfinite(r)
    if use.sum() < 10:
        return None
    floor = float(np.min(r[use]))
    sd = per.residual_std[g]
    r_hat = r + per.residuals  # v = a + b x - y: the model's reading at the row
    with np.errstate(invalid="ignore", divide="ignore"):
        p = np.where(use & (sd > 0), ndtr((floor - r_hat) / sd), 0.0)
        lost = np.where(p < 1.0, p / (1.0 - p), np.inf)
    share = float(np.sum(lost) / (np.sum(lost) + use.sum()))
    if not share > TRUNCATED_SHARE:
        return None
    far = d[use & (p >= 0.1)]
    where = f" (a tenth or more beyond about {float(np.min(far)):.3g} m)" if far.size else ""
    return (f"the survey's readings stop at {floor:.4g} dBm, and the fitted model puts "
            f"{100 * share:.0f} % of them below it{where}: a receiver's sensitivity drops "
            "those, the far distances keep only their strong readings, and the fit's n "
            "comes out low and A high.  Survey nearer the anchors, or keep only the "
            "distances every sample was received at")


def calibrate_ranges(
    survey: pd.DataFrame,
    *,
    scale: bool = False,
    robust: str | WeightFunction | None = None,
    pooled: bool = False,
    max_iter: int = 50,
) -> CalibrationResult:
    """Fit a per-anchor range bias (and optionally scale) from ``anchor, distance, range``.

    The model is ``range = scale * distance + bias + noise``; without ``scale`` the scale
    is 1 and ``bias`` is the (robust) mean of ``range - distance``.  Apply it with
    :func:`apply_range_calibration`: ``range_corrected = (range - bias) / scale``.
    """
    if "range" not in survey.columns:
        raise InputError(
            "range calibration needs a survey with a 'range' column (anchor, distance, range)",
            survey.attrs.get("path"), 1,
        )
    weight = _robust_weight(robust)
    g, ids = _groups(survey)
    d, r = _survey_values(survey, "range", path_loss=False)
    if scale:
        x, y = d, r
    else:
        x, y = np.zeros_like(d), r - d
    sw = _survey_weights(survey)
    cl = _survey_clusters(survey)
    per = fit_lines(x, y, g, len(ids), slope=scale, robust=weight, max_iter=max_iter,
                    weights=sw, cluster=cl)
    pool = fit_lines(
        x, y, np.zeros_like(g), 1, slope=scale, robust=weight, max_iter=max_iter, weights=sw,
        cluster=cl,
    )
    _check_determined(survey, per, pool, ids, d, g, ("bias", "scale") if scale else ("bias",),
                      pooled, "range")
    ratio = _range_ratios(d, r, g, len(ids), sw)
    lo, hi = RANGE_SCALE_LIMITS
    if scale:
        own = _own_fit(per, 2) & (not pooled)
        check = [(f"anchor {ids[j]}", per.b[j], ratio[j]) for j in np.flatnonzero(own)]
        for who, b, q in check + [("pooled fit", pool.b[0], ratio[-1])]:
            if not lo <= b <= hi:
                why = (f"the ranges read {q:.4g}x the distances: {_unit_hint(q)}"
                       if not lo <= q <= hi else
                       "the survey does not determine it (too small a spread of distances?)")
                raise InputError(
                    f"{who}: fitted scale = {b:.4g} is implausible (a range scale lies in "
                    f"[{lo:g}, {hi:g}]): {why}", survey.attrs.get("path"))
    else:
        _check_range_units(survey, ids, d, r, g, ratio, sw, weight, max_iter)
    rows = _assemble(per, pool, ids, scale,
                     _one_distance(d, g, len(ids), sw) if scale and pooled else None)
    table = _table(rows, {"bias": "a", "scale": "b"} if scale else {"bias": "a"})
    if not scale:
        table.insert(3, "scale", 1.0)
    return CalibrationResult(
        model="range", table=table, pooled=pooled,
        robust=None if weight is None else weight.name, unit="m",
        notes=_notes(per, ids, weight, 2 if scale else 1),
    )


def _range_ratios(d: Array, r: Array, g: NDArray[np.int64], m: int,
                  weights: Array | None) -> Array:
    """The median of ``range / distance`` of each anchor's rows (distance > 0; weighted
    by the survey's frequency weights) and, last, of every row: shape ``(m + 1,)``, NaN
    where no row has a distance."""
    with np.errstate(invalid="ignore", divide="ignore"):
        q = np.where(d > 0, r / np.where(d > 0, d, 1.0), np.nan)
    per = _grouped_mad(q, g, m, weights) * MAD_NORMAL  # (q >= 0: med |q| = med q)
    pool = _grouped_mad(q, np.zeros_like(g), 1, weights) * MAD_NORMAL
    return np.append(per, pool)


#: Units a survey's ranges or distances may come in by mistake, with their length in
#: metres (:func:`_unit_hint`).
_UNITS = (("mm", 1e-3), ("cm", 1e-2), ("inches", 0.0254), ("feet", 0.3048),
          ("km", 1e3))


def _unit_hint(ratio: float) -> str:
    """The unit mistake a median ``range / distance`` of ``ratio`` suggests (ranges in
    mm read 1000x too long), or a general question."""
    for unit, metres in _UNITS:
        for f, col in ((1.0 / metres, "ranges"), (metres, "distances")):
            if f > 1.0 and np.isfinite(ratio) and abs(np.log(ratio / f)) < np.log(1.25):
                return (f"a unit error? {col} in {unit} read {f:g}x too long; convert the "
                        f"{col} to metres")
    return "are the ranges and the distances both in metres?"


#: A single-distance survey cannot tell a scale from a bias; its median ``range /
#: distance`` is refused only beyond this factor either way (a unit error of mm, cm or km,
#: not a bias of a few metres at a short distance).
RANGE_RATIO_ONE_DISTANCE = 50.0


def _check_range_units(
    survey: pd.DataFrame, ids: list[str], d: Array, r: Array, g: NDArray[np.int64],
    ratio: Array, weights: Array | None, robust: WeightFunction | None, max_iter: int,
) -> None:
    """Refuse a bias-only range calibration of a survey whose ranges and distances are
    not both in metres.  A unit error multiplies the ranges, a bias adds to them, so the
    test is the slope of range on distance (the ``--scale`` fit, with the survey's
    weights and ``robust``): an anchor of two distinct distances or more whose slope lies
    outside :data:`RANGE_SCALE_LIMITS` by more than 3 standard errors.  An anchor surveyed
    at one distance has no slope: its median ``range / distance`` (``ratio``,
    :func:`_range_ratios`) beyond :data:`RANGE_RATIO_ONE_DISTANCE` either way.

    A survey in millimetres of distances of 1-20 m was written with biases of 10.7 km,
    exit 0 (the calibration review).  The first fix judged the median ratio of every
    anchor against the scale limits, and so refused true biases at short distances (a
    UWB antenna delay of 0.3 m surveyed at 0.2-0.5 m: ratio 2.02; WiFi RTT 2 m long at
    1-3 m: 2.12); and a least-squares bias beyond every surveyed distance, which a real
    bias can be (2 m at 0.5-1.5 m).  Both were reverted the same session."""
    path = survey.attrs.get("path")
    lo, hi = RANGE_SCALE_LIMITS
    m = len(ids)
    fit = fit_lines(d, r, g, m, slope=True, robust=robust, max_iter=max_iter,
                    weights=weights)
    spread = ~_one_distance(d, g, m, weights)
    for j, name in enumerate(ids):
        b, se = float(fit.b[j]), float(fit.b_se[j])
        if spread[j] and np.isfinite(b):
            margin = 3.0 * se if np.isfinite(se) else 0.0
            if b - margin > hi or b + margin < lo:
                raise InputError(
                    f"anchor {name}: the ranges grow {b:.4g}x as fast as the surveyed "
                    f"distances (a range is its distance times a scale in [{lo:g}, {hi:g}] "
                    f"plus a bias): {_unit_hint(b)}", path)
        elif np.isfinite(ratio[j]) and not (
                1.0 / RANGE_RATIO_ONE_DISTANCE <= ratio[j] <= RANGE_RATIO_ONE_DISTANCE):
            raise InputError(
                f"anchor {name}: the ranges read {ratio[j]:.4g}x the surveyed distance "
                f"(one distance: the median of range / distance): "
                f"{_unit_hint(float(ratio[j]))}", path)


def _check_determined(
    survey: pd.DataFrame, per: LineFit, pool: LineFit, ids: list[str], d: Array,
    g: NDArray[np.int64], names: tuple[str, ...], pooled: bool, what: str,
) -> None:
    """Refuse a calibration whose parameters the survey cannot determine (issue 15).

    * the pooled fit (used by every anchor with too few rows) needs more rows than
      parameters: with ``n_used <= p`` there is no residual, hence no standard error and
      no ``sigma``;
    * a slope (``n``, ``gamma``, ``scale``) needs at least two distinct distances, in each
      anchor's own fit (unless ``pooled``) and in the pooled one;
    * the slope must come out positive: ``n <= 0`` (e.g. constant RSSI) cannot turn RSSI
      into a distance, and ``scale <= 0`` cannot correct a range.

    Raises :class:`InputError` naming the anchor, the parameter and why.
    """
    path = survey.attrs.get("path")
    p = len(names)
    both = " and ".join(names)
    n_pool = int(pool.n_used[0])
    if n_pool <= p:
        raise InputError(
            f"cannot determine {both}: {n_pool} usable survey row(s) for {p} "
            f"parameter(s) (need at least {p + 1}, so that a standard error and the "
            "noise sigma can be estimated)", path)
    if p < 2:
        return
    slope = names[1]
    m = len(ids)
    # the samples that count: a row of weight 0 is no sample (as the same survey without
    # it: its distance made the check pass, and the fit then said "n = nan")
    sw = _survey_weights(survey)
    if sw is not None and np.any(sw > 0):
        d, g = d[sw > 0], g[sw > 0]
    dmin = np.full(m, np.inf)
    np.minimum.at(dmin, g, d)
    one = _one_distance(d, g, m)
    own = _own_fit(per, p)  # anchors with their own fit (the others: pooled)
    for j in np.flatnonzero(one & own & (not pooled)):
        raise InputError(
            f"anchor {ids[j]}: cannot determine {slope}: all samples at one distance "
            f"({dmin[j]:g} m; need at least two distinct distances)", path)
    if np.isclose(d.min(), d.max(), rtol=1e-9, atol=0.0):
        raise InputError(
            f"cannot determine {slope}: all samples at one distance ({d.min():g} m; need "
            "at least two distinct distances)", path)
    why = ("the " + what + " does not fall with distance" if what == "RSSI"
           else "ranges do not grow with distance")
    check = [(ids[j], per.b[j]) for j in np.flatnonzero(own & (not pooled))]
    check.append(("(pooled)", pool.b[0]))
    for name, b in check:
        if not (np.isfinite(b) and b > 0):
            who = "pooled fit" if name == "(pooled)" else f"anchor {name}"
            raise InputError(
                f"{who}: cannot determine {slope}: fitted {slope} = {b:.3g} is not positive "
                f"({why}; constant values?)", path)


#: Largest plausible path-loss exponent ``n`` / ``gamma``.  Free space is 2; measured
#: indoor and obstructed exponents stay below about 6 (Rappaport, Wireless
#: Communications, table 4.2: 4-6 in obstructed buildings).  10 means 100 dB per decade
#: of distance, beyond any propagation: such a fit is the survey's noise divided by a
#: tiny spread of distances (3.000 and 3.003 m gave n = 461).
MAX_EXPONENT = 10.0
#: Smallest plausible path-loss exponent: the smallest an anchors file may hold
#: (:data:`robustloc.io.limits.PATH_LOSS_EXPONENT_LIMITS`, 0.01: 0.1 dB per decade of
#: distance).  A survey whose RSSI hardly falls with distance fitted n = 0.004 and was
#: written, exit 0, and ``locate`` then refused the file (the input review).
MIN_EXPONENT = PATH_LOSS_EXPONENT_LIMITS[0]


#: Plausible range scales (``range = scale * distance + bias``).  A ranging scale error
#: is a clock or propagation-speed error: parts per million for UWB, a few per cent for
#: WiFi RTT through walls (the shared real logs: 0.93-1.22 per anchor).  A scale of 2 or
#: 1/2 is no ranging error but a survey that does not determine it: 5.000 and 5.001 m
#: gave a scale of 50 (the calibration review).
RANGE_SCALE_LIMITS = (0.5, 2.0)


def _check_plausible(
    survey: pd.DataFrame, per: LineFit, pool: LineFit, ids: list[str], model: str,
    pooled: bool, p0_arr: Array, d0_arr: Array,
) -> None:
    """Refuse a path-loss fit the survey determines only on paper.

    The fitted level at the reference distance (``A`` at 1 m, ``p0 + faf`` or the Friis
    ``p0`` at ``d0``) is an RSSI, so it must lie within the physical RSSI limits of
    :mod:`robustloc.io.limits` (-150 .. +30 dBm: no received power exceeds the +30 dBm
    EIRP ceiling); the exponent must lie in ``[MIN_EXPONENT, MAX_EXPONENT]`` (inside
    what the anchors reader accepts, so that ``locate`` reads every file written).
    Checked for each
    anchor with its own fit (unless ``pooled``) and for the pooled fit.
    """
    from robustloc.io.limits import limits_for

    lim = limits_for("rssi")
    slope = model != "friis"
    level_name, at = {"log-distance": ("A", "1 m"),
                      "attenuation-factor": ("p0 + faf", "d0"),
                      "friis": ("p0", "d0")}[model]
    exp_name = "n" if model == "log-distance" else "gamma"
    own = _own_fit(per, 2 if slope else 1) & (not pooled)
    check = [(f"anchor {ids[j]}", per.a[j] + p0_arr[j], per.b[j], d0_arr[j])
             for j in np.flatnonzero(own)]
    check += [("pooled fit", pool.a[0] + p, pool.b[0], d) for p, d in zip(p0_arr, d0_arr)]
    for who, level, b, d0 in check:
        where = "1 m" if at == "1 m" else f"d0 = {d0:g} m"
        if not lim.check(level):
            raise InputError(
                f"{who}: fitted {level_name} = {level:.4g} dBm at {where} is implausible "
                f"({lim.describe()}): the survey does not determine the path loss (too "
                "small a spread of distances?)", survey.attrs.get("path"))
        # (the message said "(0, 10]" while 0.004 passed here and the anchors reader
        # refused it: the interval stated is the one checked -- the input review)
        if slope and not MIN_EXPONENT <= b <= MAX_EXPONENT:
            why = ("too small a spread of distances?" if b > MAX_EXPONENT else
                   "the RSSI hardly falls with distance over the survey")
            raise InputError(
                f"{who}: fitted {exp_name} = {b:.4g} is implausible (a path-loss exponent "
                f"lies in {exponent_interval()}): the survey does not determine it "
                f"({why})", survey.attrs.get("path"))


def exponent_interval() -> str:
    """The plausible path-loss exponents as messages state them: ``[0.01, 10]``."""
    return f"[{MIN_EXPONENT:g}, {MAX_EXPONENT:g}]"


def _own_fit(per: LineFit, p: int) -> NDArray[np.bool_]:
    """Anchors with observations enough for a fit of their own: ``p + 2`` (two degrees
    of freedom for ``sigma``; the others take the pooled fit).  With ``p + 1`` the
    anchor's sigma came from one degree of freedom and ``locate`` weighted it by that:
    one in ten such anchors gets a sigma under 1/8 of the noise, 60x its weight (the
    calibration review, 2026-12-06); ``calibrate --self`` leaves such anchors out the
    same way.

    The observations are counted as the fit counts its degrees of freedom
    (:meth:`LineFit.counted`): with a ``weight`` column its frequency weights, so that a
    row of weight 50 is 50 rows.  Counted by rows, an anchor surveyed at three distances
    of 50 readings each took the pooled fit, which the same readings as 150 rows did not
    (the calibration review).  A slope of its own still needs two distinct distances
    (:func:`_check_determined`), with weights as with repeated rows."""
    return per.counted() >= p + 2


def _one_distance(d: Array, g: NDArray[np.int64], m: int,
                  weights: Array | None = None) -> NDArray[np.bool_]:
    """Per anchor: every sample at one distance (its own slope undetermined); with the
    survey's frequency ``weights``, rows of weight 0 are no samples."""
    if weights is not None and np.any(weights > 0):
        d, g = d[weights > 0], g[weights > 0]
    dmin = np.full(m, np.inf)
    dmax = np.full(m, -np.inf)
    np.minimum.at(dmin, g, d)
    np.maximum.at(dmax, g, d)
    return np.isclose(dmin, dmax, rtol=1e-9, atol=0.0)


def _assemble(per: LineFit, pool: LineFit, ids: list[str], slope: bool,
              undetermined: NDArray[np.bool_] | None = None) -> dict[str, Array]:
    p = 2 if slope else 1
    few = ~_own_fit(per, p)  # no trustworthy sigma: take the pooled fit
    if undetermined is not None:
        # (--pooled, an anchor surveyed at one distance: its own "fit" was shown as the
        # anchor's, with A = n = -inf or n = -0.000; the calibration review)
        few = few | undetermined
    src = np.where(few, "pooled", "anchor").astype(object)
    out: dict[str, Array] = {"anchor": np.array(ids + [POOLED], dtype=object)}
    for k in ("a", "b", "a_se", "b_se", "residual_std"):
        pv = getattr(per, k)
        out[k] = np.append(np.where(few, getattr(pool, k)[0], pv), getattr(pool, k))
    out["n_obs"] = np.append(per.n_obs, pool.n_obs)
    out["n_used"] = np.append(per.n_used, pool.n_used)
    out["calib_source"] = np.append(src, "pooled")
    return out


def _table(rows: dict[str, Array], names: dict[str, str]) -> pd.DataFrame:
    data: dict[str, object] = {"anchor": rows["anchor"]}
    for col, key in names.items():
        data[col] = rows[key]
    for col, key in names.items():
        data[f"{col}_se"] = rows[f"{key}_se"]
    for k in ("residual_std", "n_obs", "n_used", "calib_source"):
        data[k] = rows[k]
    return pd.DataFrame(data)


def _notes(
    per: LineFit, ids: list[str], weight: WeightFunction | None, p: int
) -> list[str]:
    notes = []
    few = [a for a, own in zip(ids, _own_fit(per, p)) if not own]
    if few:
        notes.append(f"too few survey rows, pooled fit used for anchor(s): {', '.join(few)}")
    if weight is not None and not per.converged:
        notes.append(f"robust fit stopped at the iteration limit ({per.iterations})")
    return notes


@dataclass(frozen=True)
class PathLossCalibrator:
    """Settings of a path-loss calibration; :meth:`fit` takes the survey.

    See :func:`calibrate_pathloss` for the parameters.  Example::

        res = PathLossCalibrator("log-distance", robust="igg3").fit(read_survey("s.csv"))
        anchors = res.apply_to_anchors(read_anchors("anchors.csv"))
    """

    model: str = "log-distance"
    robust: str | None = None
    pooled: bool = False
    d0: float = 1.0
    p0: float | None = None
    max_iter: int = 50

    def fit(
        self, survey: pd.DataFrame, p0: Mapping[str, float] | None = None
    ) -> CalibrationResult:
        """Fit the survey; ``p0`` per anchor overrides the scalar setting."""
        return calibrate_pathloss(
            survey, self.model, robust=self.robust, pooled=self.pooled, d0=self.d0,
            p0=p0 if p0 is not None else self.p0, max_iter=self.max_iter,
        )


@dataclass(frozen=True)
class RangeCalibrator:
    """Settings of a range bias/scale calibration; :meth:`fit` takes the survey
    (see :func:`calibrate_ranges`)."""

    scale: bool = False
    robust: str | None = None
    pooled: bool = False
    max_iter: int = 50

    def fit(self, survey: pd.DataFrame) -> CalibrationResult:
        """Fit ``range = scale * distance + bias`` per anchor and pooled."""
        return calibrate_ranges(
            survey, scale=self.scale, robust=self.robust, pooled=self.pooled,
            max_iter=self.max_iter,
        )


def apply_range_calibration(anchors: pd.DataFrame, values: ArrayLike) -> Array:
    """Correct ranges ``(N, m)`` with the anchors' ``bias``/``scale`` columns.

    ``range_corrected = (range - bias) / scale`` per anchor column (anchor order of the
    frame's rows).  A missing column, or an empty value, means ``bias = 0``/``scale = 1``.
    NaN ranges stay NaN.
    """
    v = np.asarray(values, dtype=float)
    m = len(anchors)
    if v.shape[-1] != m:
        raise ValueError(f"values have {v.shape[-1]} anchor columns, anchors frame has {m}")
    bias, scale = range_calibration(anchors)
    return (v - bias) / scale


def range_calibration(anchors: pd.DataFrame) -> tuple[Array, Array]:
    """The anchors' range ``bias`` and ``scale`` arrays ``(m,)`` as
    :func:`apply_range_calibration` applies them (a missing column or an empty value:
    ``bias = 0``, ``scale = 1``); a non-positive scale is an input error."""
    m = len(anchors)
    bias = (
        np.nan_to_num(anchors["bias"].to_numpy(dtype=float), nan=0.0)
        if "bias" in anchors.columns else np.zeros(m)
    )
    scale = (
        np.nan_to_num(anchors["scale"].to_numpy(dtype=float), nan=1.0)
        if "scale" in anchors.columns else np.ones(m)
    )
    if np.any(scale <= 0):
        raise InputError("anchors file has a non-positive range 'scale'", anchors.attrs.get("path"))
    return bias, scale


def survey_from_positions(
    measurements: pd.DataFrame,
    truth: pd.DataFrame,
    anchors: pd.DataFrame,
    *,
    time_tolerance_s: float = 1e-6,
    dim: int | None = None,
) -> pd.DataFrame:
    """Build a survey (``anchor, distance, rssi|range``) from measurements with truth.

    Each measurement row is matched to the truth row of the same ``tag`` with the nearest
    ``time`` within ``time_tolerance_s``; unmatched rows are dropped (their count is in
    ``frame.attrs["n_unmatched"]``).  ``distance`` is 3-D when ``dim == 3`` or when both
    anchors and truth have ``z`` (``dim=None``), else horizontal.

    Rows that cannot be fitted are dropped and counted, as ``locate`` sets them aside
    (:func:`robustloc.io.read_measurements` keeps them on purpose):

    * ``attrs["n_invalid"]``: a value outside the physical limits of
      :mod:`robustloc.io.limits` (``invalid_measurement``; a survey file refuses them);
    * ``attrs["n_zero_distance"]``: RSSI rows whose truth position is on the anchor
      (distance 0, where a log-distance model has no value).

    An anchor reported more than once in one epoch (same ``time, tag, anchor``) gives
    one row, its values averaged as :func:`robustloc.io.tables.to_epochs` averages them
    (``attrs["n_duplicates"]``: the rows merged).
    """
    from robustloc.io.limits import limits_for

    value = measurements.attrs.get("value") or ("rssi" if "rssi" in measurements else "range")
    # an anchor reported twice in one epoch: one row, the values averaged, as ``locate``
    # does (counted twice, the standard errors read sqrt(2) too small: the review)
    key = [c for c in ("time", "tag", "anchor") if c in measurements.columns]
    dup = measurements.duplicated(key, keep="first").to_numpy()
    n_dup = int(dup.sum())
    if n_dup:
        attrs = dict(measurements.attrs)
        mean = measurements.groupby(key, sort=False)[value].transform("mean")
        measurements = measurements.assign(**{value: mean}).loc[~dup]
        measurements.attrs = attrs
    plausible = limits_for(value).check(measurements[value].to_numpy(dtype=float))
    n_invalid = int((~plausible).sum())
    if n_invalid:
        measurements = measurements.loc[plausible]
    pos = _match_truth(measurements, truth, time_tolerance_s)
    ok = np.isfinite(pos[:, 0])
    meas = measurements.loc[ok] if not ok.all() else measurements
    pos = pos[ok]
    a = anchors.set_index(anchors["anchor"].astype(str))
    ai = a.index.get_indexer(meas["anchor"].astype(str))
    if (ai < 0).any():
        i = int(np.argmax(ai < 0))
        line = int(meas.index[i]) if meas.index.name == "line" else None
        raise InputError(
            f"unknown anchor id {meas['anchor'].iloc[i]!r} (not in the anchors file)",
            measurements.attrs.get("path"), line,
        )
    use3 = (dim == 3) or (dim is None and "z" in a.columns and "z" in truth.columns)
    axy = a[["x", "y"]].to_numpy(dtype=float)[ai]
    dist2 = np.sum((axy - pos[:, :2]) ** 2, axis=1)
    if use3:
        az = a["z"].to_numpy(dtype=float)[ai] if "z" in a.columns else 0.0
        dist2 = dist2 + (az - pos[:, 2]) ** 2
    dist = np.sqrt(dist2)
    at_anchor = (dist <= 0) if value == "rssi" else np.zeros(len(dist), dtype=bool)
    # each row's dwell: consecutive epochs of a tag at one truth position (a survey point)
    # share their multipath, so the standard errors are cluster-robust over the dwells
    # (merged into at most SE_CLUSTERS contiguous blocks per anchor: a moving tag's epochs
    # form blocks of time, as the self-calibration's)
    order = np.lexsort((meas["time"].to_numpy(dtype=float),
                        pd.factorize(meas["tag"].astype(str), sort=True)[0]))
    ps, tg = pos[order, :2], meas["tag"].astype(str).to_numpy()[order]
    new_dwell = np.ones(len(order), dtype=bool)
    if len(order) > 1:
        new_dwell[1:] = (tg[1:] != tg[:-1]) | (np.hypot(*(ps[1:] - ps[:-1]).T) > 1e-6)
    dwell = np.empty(len(order), dtype=np.int64)
    dwell[order] = np.cumsum(new_dwell) - 1
    out = pd.DataFrame(
        {"anchor": meas["anchor"].astype(str).to_numpy()[~at_anchor],
         "distance": dist[~at_anchor], value: meas[value].to_numpy(dtype=float)[~at_anchor],
         "cluster": dwell[~at_anchor]},
        index=meas.index[~at_anchor],
    )
    out.attrs["value"] = value
    out.attrs["n_unmatched"] = int((~ok).sum())
    out.attrs["n_invalid"] = n_invalid
    out.attrs["n_duplicates"] = n_dup
    out.attrs["n_zero_distance"] = int(at_anchor.sum())
    out.attrs["path"] = measurements.attrs.get("path")
    return out


def _match_truth(
    frame: pd.DataFrame, truth: pd.DataFrame, tol: float
) -> Array:
    """Truth position ``(k, 3)`` (z = 0 if absent) for each row of ``frame``; NaN if none."""
    k = len(frame)
    out = np.full((k, 3), np.nan)
    has_z = "z" in truth.columns
    tt = truth.assign(_z=truth["z"] if has_z else 0.0)
    ft = frame["tag"].astype(str).to_numpy()
    ftime = frame["time"].to_numpy(dtype=float)
    for tag, grp in tt.groupby(tt["tag"].astype(str), sort=False):
        rows = np.flatnonzero(ft == tag)
        if rows.size == 0:
            continue
        grp = grp.sort_values("time")
        ts = grp["time"].to_numpy(dtype=float)
        j = np.clip(np.searchsorted(ts, ftime[rows]), 1, max(len(ts) - 1, 1))
        j0 = np.clip(j - 1, 0, len(ts) - 1)
        j1 = np.clip(j, 0, len(ts) - 1)
        pick = np.where(np.abs(ts[j0] - ftime[rows]) <= np.abs(ts[j1] - ftime[rows]), j0, j1)
        near = np.abs(ts[pick] - ftime[rows]) <= tol
        xyz = grp[["x", "y", "_z"]].to_numpy(dtype=float)[pick]
        out[rows[near]] = xyz[near]
    return out


def self_calibration_table(
    res: SelfCalibration, anchors: pd.DataFrame, model: object | None = None
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The parameter table of a self-calibration and the anchors frame with its columns.

    Ranges: ``bias, scale, sigma, bias_se, scale_se``.  RSSI: the log-distance ``A, n``;
    for an attenuation-factor model (``model`` from
    :func:`robustloc.models.pathloss.model_from_anchors`) ``p0 = A - faf - 10 gamma lg d0``
    and ``gamma`` (its ``faf`` and ``d0`` kept), for Friis ``p0 = A - 20 lg d0``; standard
    errors propagated from the ``(A, n)`` covariance.  Also ``n_obs``, ``n_used``,
    ``calib_source = "self"`` and ``calib_fixed`` (the parameters left at their prior).
    A left-out parameter has an empty standard error.  ``sigma``: :func:`_self_sigma`.
    """
    from robustloc.models.pathloss import AttenuationFactor, FreeSpace

    ids = anchors["anchor"].astype(str).to_numpy()
    off, slo, cov = res.offset, res.slope, res.cov
    fixed = [";".join(n for n, f in zip(_self_param_names(res, model), fr) if f)
             for fr in self_left_out(res, model)]
    sigma = _self_sigma(res, anchors)
    cols: dict[str, Array] = {}
    drop: list[str] = []
    if res.kind == "range":
        cols = {"bias": off, "scale": slo, "sigma": sigma,
                "bias_se": res.offset_se, "scale_se": res.slope_se}
    elif isinstance(model, (AttenuationFactor, FreeSpace)):
        m = len(ids)
        d0 = np.broadcast_to(np.asarray(model.d0, dtype=float), (m,))
        c = 10.0 * np.log10(d0)
        if isinstance(model, AttenuationFactor):
            faf = np.broadcast_to(np.asarray(model.faf, dtype=float), (m,))
            p0 = off - faf - c * slo  # seed 002 eq. (5) as A - 10 gamma lg d
            var = cov[:, 0, 0] + c * c * cov[:, 1, 1] - 2.0 * c * cov[:, 0, 1]
            cols = {"p0": p0, "gamma": slo, "faf": faf, "d0": d0, "sigma": sigma,
                    "p0_se": np.where(res.free[:, 0], np.sqrt(np.maximum(var, 0)), np.nan),
                    "gamma_se": res.slope_se}
        else:
            cols = {"p0": off - 2.0 * c, "d0": d0, "sigma": sigma, "p0_se": res.offset_se}
        drop = [c_ for c_ in _ALL_PATHLOSS_COLUMNS if c_ not in cols]
    else:
        cols = {"A": off, "n": slo, "sigma": sigma, "A_se": res.offset_se,
                "n_se": res.slope_se}
        drop = [c_ for c_ in _ALL_PATHLOSS_COLUMNS if c_ not in cols]
    table = pd.DataFrame({"anchor": ids, **cols, "n_obs": res.n_obs, "n_used": res.n_used,
                          "calib_fixed": fixed})
    out = anchors.drop(columns=[c_ for c_ in drop + [f"{c_}_se" for c_ in drop]
                                if c_ in anchors.columns]).copy()
    cols["sigma"] = _sigma_floor(cols["sigma"])
    if not np.isfinite(cols["sigma"]).any():
        del cols["sigma"]  # (no anchor's determined, none in the file: none written)
    for k, v in cols.items():
        out[k] = np.asarray(v, dtype=float)
    out["calib_source"] = "self"
    out["calib_fixed"] = fixed
    return table, out


def _self_param_names(res: SelfCalibration, model: object | None) -> tuple[str, str]:
    """The names of a self-calibration's offset and slope as the written columns call
    them (``calib_fixed``): ``bias, scale`` for ranges; ``p0, gamma`` for an
    attenuation-factor model and ``p0, n`` for free space (whose exponent is never left
    out, :func:`self_left_out`); ``A, n`` else.  (``calib_fixed`` said ``A`` for an
    attenuation-factor file, whose column is ``p0``: the calibration fixer's note.)"""
    from robustloc.models.pathloss import AttenuationFactor, FreeSpace

    if res.kind == "rssi" and isinstance(model, AttenuationFactor):
        return ("p0", "gamma")
    if res.kind == "rssi" and isinstance(model, FreeSpace):
        return ("p0", "n")
    return (str(res.param_names[0]), str(res.param_names[1]))

def self_left_out(res: SelfCalibration, model: object | None = None) -> NDArray[np.bool_]:
    """Which parameters of each anchor a self-calibration left at their prior, shape
    ``(m, 2)``: those it did not estimate (``~res.free``), except the exponent of a
    free-space model (``model``, :class:`robustloc.models.pathloss.FreeSpace`), which is
    2 by the model's definition, not for want of data.  ``--self --model friis`` had
    written ``calib_fixed = n`` for every anchor and the note that the standard errors
    assume the parameters left out equal their priors (the calibration review)."""
    from robustloc.models.pathloss import FreeSpace

    out = ~np.asarray(res.free, dtype=bool)
    if res.kind == "rssi" and isinstance(model, FreeSpace):
        out[:, 1] = False
    return out


def _self_sigma(res: SelfCalibration, anchors: pd.DataFrame) -> Array:
    """The ``sigma`` a self-calibration writes: the standard deviation of the value
    ``locate`` fits, so for ranges of the corrected range ``(range - bias) / scale``,
    ``res.sigma / scale`` (``res.sigma`` is the raw range's: with a scale of 1.5 and
    0.2 m of noise the file said 0.229 m where the corrected ranges spread 0.139 m, the
    self-calibration review).  Where the log does not determine an anchor's sigma
    (:meth:`SelfCalibration.sigma_determined`) the anchors file's ``sigma`` stays; without
    one, the median of the determined anchors'; when no anchor's is determined and the
    file has none, none (NaN: ``locate`` then measures the log's noise scale itself)."""
    sig = np.asarray(res.sigma, dtype=float)
    if res.kind == "range":
        sig = sig / np.asarray(res.slope, dtype=float)
    det = res.sigma_determined() & np.isfinite(sig) & (sig > 0)
    prior = (to_number(anchors["sigma"]).to_numpy(dtype=float) if "sigma" in anchors.columns
             else np.full(sig.shape, np.nan))
    out = np.where(det, sig, prior)
    missing = ~np.isfinite(out)
    if missing.any() and det.any():
        out[missing] = float(np.median(sig[det]))
    return out


def default_p0_from_anchors(anchors: pd.DataFrame | None) -> dict[str, float] | None:
    """``{anchor: p0}`` from an anchors frame's ``p0`` column, if it has finite values."""
    if anchors is None or "p0" not in anchors.columns:
        return None
    vals = anchors["p0"].to_numpy(dtype=float)
    if not np.isfinite(vals).any():
        return None
    return {str(a): float(v) for a, v in zip(anchors["anchor"], vals) if np.isfinite(v)}


__all__: Sequence[str] = (
    "CalibrationResult",
    "LineFit",
    "PathLossCalibrator",
    "RangeCalibrator",
    "apply_range_calibration",
    "calibrate_pathloss",
    "calibrate_ranges",
    "default_p0_from_anchors",
    "fit_lines",
    "self_calibration_table",
    "survey_from_positions",
)
