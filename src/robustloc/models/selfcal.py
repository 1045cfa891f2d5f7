"""Self-calibration without truth: per-anchor observation model jointly with the positions.

Every observation of a log is modelled as (anchor ``j``, epoch ``k``)

.. math::  z_{kj} = a_j + b_j f(\\rho_{kj}) + e_{kj},\\quad
           \\rho_{kj} = \\sqrt{|x_k - p_j|^2 + h_j^2},\\quad e_{kj} \\sim (0, \\sigma_j^2)

* ranges: ``f(rho) = rho``, ``a = bias`` (m), ``b = scale``, prior ``(0, 1)``; this is the
  survey model of :func:`robustloc.models.calibration.calibrate_ranges`;
* RSSI (log-distance, seed 000 eq. (1)): ``f(rho) = -10 lg rho``, ``a = A`` (dBm),
  ``b = n``, prior the anchors file's ``A, n`` (the attenuation-factor and Friis models
  are the same line, seed 002 eqs. (4)-(5), see :func:`robustloc.models.pathloss`).

The anchor coordinates ``p_j`` are the datum (held fixed); ``h_j`` are known
anchor-minus-tag heights of a 2-D solution from slant observations (else 0).  The unknowns
are every epoch's position ``x_k`` (``dim`` each) and the free calibration parameters
``theta = (a_j, b_j)``.  They are estimated together by Gauss-Newton with iteratively
reweighted least squares (IRLS) on the whole log:

1. Normal equations of the joint problem, ordered (positions, theta)::

       [ N_xx   N_xt ] [dx]   [g_x]        N_xx block diagonal, one (dim x dim) block
       [ N_tx   N_tt ] [dt] = [g_t]        per epoch

   with ``N = J^T W J``, ``g = J^T W v``, ``v = z - model``, ``W = w(u) / sigma_j^2``.
2. The positions are eliminated epoch by epoch (Schur complement, e.g. Triggs et al.,
   "Bundle adjustment - a modern synthesis", 2000, sec. 6.1)::

       S = N_tt - sum_k N_tk N_kk^-1 N_kt,      S dt = g_t - sum_k N_tk N_kk^-1 g_k
       dx_k = N_kk^-1 (g_k - N_kt dt)

   ``S`` is small (two parameters per anchor); the eliminations are batched over epochs.
3. ``sigma_j``: variance components over the whole log (MINQUE, see :meth:`_vce`)
   from the residuals ``v_eq = R_k v`` of each epoch's fix with the robust weights alone,
   ``E v_eq,j^2 = sum_i R_k,ji^2 sigma_i^2``.  (The iterated per-anchor scale of
   weighted residuals, Foerstner's VCE, drifts for a precise anchor of high leverage: on a
   simulated 5-anchor room it took a 0.10 m anchor to 0.06 m in 30 iterations.  Fixes
   weighted by the robust weights over the previous iteration's variances, iterated
   MINQUE, spread a precise anchor's estimate 0.7 times as much on that room, but on
   uwb-labyrinth's 58 ranging cycles the noisy variances moved the calibration: its
   `locate` RMS went 0.150 -> 0.188 m.)  The final scale is divided by its Gaussian
   consistency factor measured on the log's own geometry
   (:meth:`SelfCalibrator._sigma_consistency`).
   Robust weights ``w(u)``, ``u = v_eq / sqrt(sum_i R^2 sigma_i^2)``: Huber (c = 1.5) until
   convergence, then the redescending IGG-III (k0 = 2, k1 = 5: full weight within 2 sigma,
   about 95 % of Gaussian data; zero weight beyond 5 sigma) so that gross errors get
   no weight at all.  The Huber stage standardizes by a robust scale: the same MINQUE
   with each anchor's weighted mean square replaced by its median square over
   ``chi2_1``'s median (:data:`CHI2_1_MEDIAN`); with the weighted squares themselves,
   gross ranges (8 % of them, 5-15 m long, four anchors) inflated the scale until Huber
   hardly down-weighted them, and the scales came out 0.40-1.23 for a truth of 1.01 (the
   calibration review).  The redescending stage refines that estimate; where it ends in
   a fit whose noise scale is over :data:`RUNAWAY_SCALE` times the Huber stage's, it
   found another root and the Huber estimate stands, with a warning
   (:meth:`SelfCalibrator._ran_away`).  Over ten such
   logs the worst scale error went 0.61 -> 0.11; on clean logs nothing moved by more
   than 0.002, and the report's self-calibrated rows (section ``s05_out_of_box``) moved
   by -0.6 to +4.5 %.
4. Covariance of theta: ``sigma0^2 S^-1`` (``S^-1`` is exactly the theta block of the
   inverse of the joint normal matrix), ``sigma0^2 = sum W v^2 / kappa / (n_used - u)``
   the a-posteriori variance factor (``kappa`` the weights' consistency factor, see
   :meth:`SelfCalibrator._vce`; the final weights taken as known, as in
   :func:`robustloc.models.calibration.fit_lines`).  That model covariance assumes
   errors independent from epoch to epoch; on real logs they are not (a tag dwelling at
   one spot sees the same multipath for a while), and it can be many times too small
   (wifi-rtt-rss lecture theatre: scale standard errors 0.004; across 50 time blocks
   0.023-0.029).  The reported covariance is therefore cluster-robust (the sandwich
   ``S^-1 (sum_c g_c g_c^T) S^-1 G / (G - 1)``, Liang & Zeger 1986, with ``g_c`` the
   reduced-gradient share of ``se_blocks`` = 50 contiguous blocks of epochs), its
   diagonal floored at the model's.  With independent errors the two agree (tested by
   Monte Carlo); with errors correlated within blocks the robust one matches the spread
   of the estimates where the model one does not.  It does not see the incidental-
   parameter bias below.  The observability tests use the model covariance: they ask
   whether the log's geometry determines a parameter.

Bad epochs: an epoch whose position cannot be solved (no start, singular ``N_kk``), whose
observations with non-zero weight are at most ``dim`` (no redundancy: it says nothing about
the calibration), in which more than half of the observations are rejected (weight 0), or
whose observations in use fail the global test ``sum w u^2 > chi2_{0.999}(n_w - dim)``
is left out of the adjustment and counted.

Own redundancy: an anchor heard in fewer epochs (with a fix and redundancy) than its free
parameters plus :data:`OWN_REDUNDANCY` has them left out before the adjustment: with one
observation its bias would be that observation's residual, a gross error included, and
with one more a gross error is detected but not told from the others.

Observability: the correlation form ``D^-1/2 S D^-1/2`` of the reduced normal matrix is
tested by its eigenvalues.  While the smallest is below ``rank_tol`` the parameter with the
largest component in that eigenvector is left out (fixed at its prior); this catches
exactly inseparable parameters (e.g. every epoch exactly at one point: bias and scale of
an anchor; collinear anchors with the tag on their line).  After convergence a parameter whose
standard error exceeds the documented bound is left out too and the log re-adjusted (the
worst in each round; on a site of many anchors also the offenders whose anchors share no
epoch with it, :meth:`SelfCalibrator._se_test`):

* offset ``a_j``: ``se(a_j) > se_ratio * sigma_j`` (known no better than one observation);
* slope ``b_j``: ``se(b_j) * sd_j(f) > se_ratio * sigma_j`` (``sd_j(f)`` the spread of
  ``f(rho)`` over the anchor's observations: the slope's uncertainty moves the predicted
  observations over the anchor's distances by more than one observation's noise).

Motion: after a first adjustment, the log must show the tag moving, and the distance to
each anchor varying, by more than the fixes' noise explains (the share of the spread
that the noise explains at most ``max_dilution`` = 0.5; ``SelfCalibrator._motion_test``
has the tests).  A tag that does not move gives one value per anchor, which its
position and the anchor's parameters share: every parameter is left out (with the fixes
jittering by their noise, the tests above caught a few and let the rest pass as
determined: scales of 0.25-3.2 for a truth near 1).  A distance that hardly varies (a tag
circling an anchor) leaves that anchor's slope out and keeps its offset: a slope fitted
there is diluted toward the fixes' noise (0.46 for a true 0.97).  What either leaves out
is re-adjusted from the start.

Far field: when the median start fix lies farther from the anchors' centroid than
``far_field_ratio`` (3) times the anchors' extent, every slope is left out before the
adjustment: a scale there is a radial stretch of the fixes, and a scale error is amplified
into the fixes' angle by about distance / extent.

Elongated anchors: when, in more than half (:data:`MIRROR_SHARE`) of the epochs that hear
an anchor, the anchors heard lie close to a line as seen from the tag (a plane in 3-D;
:func:`robustloc.models.geometry.mirror_flatness` of the start fix below
``elongation_ratio``, 0.05, the threshold of the fixes' ambiguity check), that anchor's
slope is left out before the adjustment. Each fix then has a mirror image across the line
that fits nearly as well, the two told apart only by the anchors' small deviations from the
line -- which per-anchor slopes can mimic, so the adjustment can lock fixes onto the wrong
side and calibrate the observations to fit them there. Measured on the wifi-rtt-rss
corridor (elongation 0.006): with scales, 4.3 % of the default ``locate``'s usable fixes
were misleading afterwards (mirror fixes 8-10 m off on the wrong side, passing their own
test), RMS 6.18 m; with the biases only, 0.9 %, RMS 6.06 m (report section
``s05_out_of_box``).

Each left-out parameter gets a warning naming the anchor, the parameter and the reason.

Limits (measured, ``benchmarks/bench_selfcal.py``): every epoch's position is its own
unknown, so the estimate carries an incidental-parameter bias of order ``sigma^2`` that does
not shrink with the length of the log (Neyman & Scott 1948); for RSSI it reaches several
standard errors along the common mode of (A, n) already at 1 dB of noise (A -2.2 dB, n
-0.2 on a simulated 5-anchor room; the self-calibration review, 2026-12-04), and 10 %
one-sided gross errors (10-25 dB weak) can drive the fit far off: ``robustloc calibrate
--self`` prints a note with every RSSI run.  A common bias and a
common scale of all anchors are weakly determined when the tags stay near the anchors' line
(wifi-rtt-rss office: smallest eigenvalue 0.045); there the self-calibration moves
``locate`` RMS from 1.33 to 1.52 m, while a truth-based calibration reaches 1.21 m.
"""

from __future__ import annotations

import warnings as _warnings
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

from robustloc._arrays import true_first
from robustloc.models.geometry import elongation_rows, mirror_flatness
from robustloc.robust.weights import IGG3, Huber, WeightFunction

Array = NDArray[np.float64]

KINDS = ("range", "rssi")
_LN10 = np.log(10.0)
#: Start of the reason given when the tag does not move (:meth:`SelfCalibrator._motion_test`).
STATIC_REASON = "the tag does not move"
#: Start of the reason given when several tags each stand still
#: (:meth:`SelfCalibrator._static_tags`).
STATIC_TAGS_REASON = "the tags do not move"
#: The reason given for the parameters of an anchor heard in too few epochs (one warning
#: line for every such anchor: a short log of a large site has hundreds).
FEW_REASON = ("heard in fewer epochs with a fix than its free parameters + 2 (a gross "
              "range would be taken for a parameter; n_used gives the count)")
#: Start of the reason given when the log has no redundancy left for the calibration.
NO_REDUNDANCY_REASON = "no redundancy left for it"
#: An anchor whose parameters were left out for one of these reasons has no determined
#: ``sigma`` either (:meth:`SelfCalibrator._sigma_undetermined`).
SIGMA_WITH_PARAMS = (STATIC_REASON, STATIC_TAGS_REASON, FEW_REASON, NO_REDUNDANCY_REASON)
#: Parameter names per kind: (offset, slope).
PARAM_NAMES = {"range": ("bias", "scale"), "rssi": ("A", "n")}
#: Gaussian draws (observations) from which :meth:`SelfCalibrator._sigma_consistency`
#: measures the robust scale's factor on the log's own geometry.
SIGMA_FACTOR_DRAWS = 50_000
#: The redescending stage may not end with the anchors' median noise scale more than
#: this many times the Huber stage's (:meth:`SelfCalibrator._ran_away`): for Gaussian
#: errors the two estimate the same scale, within a few per cent on any log of some
#: hundred observations.
RUNAWAY_SCALE = 2.0

#: Median of the chi-square distribution with one degree of freedom, ``chi2.ppf(0.5, 1)``:
#: ``median(v^2) / CHI2_1_MEDIAN`` estimates the variance of Gaussian residuals ``v``
#: (the square of the MAD scale ``median|v| / 0.6745``).
CHI2_1_MEDIAN = 0.454936423119572

#: An anchor's slope is left out when, in more than this share of the epochs that hear
#: it, the anchors heard look flat from the tag (:func:`mirror_flatness` below
#: ``elongation_ratio``): most of its observations then fit a mirror image as well.
MIRROR_SHARE = 0.5

#: Seed of those draws: the factor, like the calibration, is a function of the log.
SIGMA_FACTOR_SEED = 20_261_204


def _elongation(a: Array) -> float:
    """:func:`robustloc.models.geometry.anchor_elongation` of all the anchors ``a``: 0 on
    a line (2-D) or a plane (3-D), 1 for anchors spread evenly; 1 when fewer than two
    anchors (nothing to be elongated)."""
    e = elongation_rows(a, np.ones((1, a.shape[0]), dtype=bool))[0]
    return 1.0 if not np.isfinite(e) else float(e)


@dataclass(frozen=True)
class SelfCalibration:
    """Result of :meth:`SelfCalibrator.fit`.

    Attributes
    ----------
    offset, slope : (m,) estimates (``bias, scale`` or ``A, n``); prior where left out.
    offset_se, slope_se : (m,) standard errors; NaN where left out (fixed).
    cov : (m, 2, 2) covariance of ``(offset, slope)`` per anchor (0 rows where fixed).
    sigma : (m,) robust standard deviation of one observation (m or dB), in the units
        of the raw observation ``z``; for ranges the corrected range ``(z - bias) /
        scale`` has ``sigma / scale``, which
        :func:`robustloc.models.calibration.self_calibration_table` writes.
    free : (m, 2) bool, which parameters were estimated.
    sigma_free : (m,) bool, which ``sigma`` the log determined
        (:meth:`SelfCalibrator._sigma_undetermined`); None: every one.
    positions : (N, dim) adjusted positions (NaN for epochs left out).
    epoch_used : (N,) bool.
    weights : (N, m) final robust weights (NaN: not observed).
    n_obs, n_used : (m,) observations per anchor, and with non-zero weight.
    epochs_total, epochs_used, epochs_no_redundancy, epochs_bad, epochs_no_start : int
    observations_rejected : int (weight 0 in epochs used)
    sigma0 : float, a-posteriori variance factor's square root.
    min_eigenvalue : float, smallest eigenvalue of the correlation form of the reduced
        normal matrix of the free parameters at the solution (1 / its square root is the
        standard-error inflation of the worst-determined combination).
    iterations : int
    converged : bool
    warnings : list of str
    """

    kind: str
    param_names: tuple[str, str]
    offset: Array
    slope: Array
    offset_se: Array
    slope_se: Array
    cov: Array
    sigma: Array
    free: NDArray[np.bool_]
    positions: Array
    epoch_used: NDArray[np.bool_]
    weights: Array
    n_obs: NDArray[np.int64]
    n_used: NDArray[np.int64]
    epochs_total: int
    epochs_used: int
    epochs_no_redundancy: int
    epochs_bad: int
    epochs_no_start: int
    observations_rejected: int
    sigma0: float
    iterations: int
    converged: bool
    min_eigenvalue: float = float("nan")
    warnings: list[str] = field(default_factory=list)
    sigma_free: NDArray[np.bool_] | None = None

    def sigma_determined(self) -> NDArray[np.bool_]:
        """Which anchors' ``sigma`` the log determined (:attr:`sigma_free`; every anchor
        when it is None)."""
        if self.sigma_free is None:
            return np.ones(self.sigma.shape[0], dtype=bool)
        return np.asarray(self.sigma_free, dtype=bool)


@dataclass(frozen=True)
class SelfCalibrator:
    """Settings of a self-calibration; :meth:`fit` takes the log (see the module notes).

    Parameters
    ----------
    kind : {"range", "rssi"}
    fit_offset, fit_slope : bool
        Estimate the offset (bias / A) and the slope (scale / n) of every anchor.
    huber_c : float
        Huber threshold of the first IRLS stage (standardized residuals).
    igg3_k0, igg3_k1 : float
        IGG-III thresholds of the final, redescending stage (``k1 <= 0``: no such stage).
    rank_tol : float
        Smallest eigenvalue of the correlation form of the reduced normal matrix below
        which a parameter is inseparable from the others.
    se_ratio : float
        Bound of the standard-error test (module notes), in units of ``sigma_j``.
    max_iter : int
        Gauss-Newton/IRLS iterations per stage.
    tol : float
        Stop when, in two successive iterations, every parameter step is below ``tol``
        times its standard error.
    bad_epoch_fraction : float
        An epoch with more than this fraction of its observations rejected is left out.
    epoch_alpha : float
        Significance of the global test of each epoch (its observations in use).
    far_field_ratio : float
        Slopes are left out when the median distance of the start fixes from the anchors'
        centroid exceeds this many times the anchors' extent (largest anchor distance from
        the centroid).
    elongation_ratio : float
        An anchor's slope is left out when, in most epochs that hear it, the anchors heard
        lie close to a line (a plane in 3-D) as seen from the tag:
        :func:`~robustloc.models.geometry.mirror_flatness` below this (the threshold of the
        fixes' ambiguity check,
        :data:`robustloc.integrity.fixes.AMBIGUITY_ELONGATION`; module notes).
    se_blocks : int
        The reported covariance is cluster-robust over this many contiguous blocks of
        epochs (in the log's order, i.e. time), never below the model-based one (module
        notes, item 4); ``0``: the model-based covariance only.
    max_dilution : float
        Motion tests (module notes, "Motion"): when the fixes' noise explains more than
        this share of the start fixes' spread, every parameter is left out (the tag does
        not move); of the spread of the distances to an anchor, its slope (the regression
        dilution of the slope estimate).
    """

    kind: str = "range"
    fit_offset: bool = True
    fit_slope: bool = True
    huber_c: float = 1.5
    igg3_k0: float = 2.0
    igg3_k1: float = 5.0
    rank_tol: float = 1e-8
    se_ratio: float = 3.0
    max_iter: int = 50
    tol: float = 2e-2
    bad_epoch_fraction: float = 0.5
    epoch_alpha: float = 1e-3
    far_field_ratio: float = 3.0
    elongation_ratio: float = 0.05
    se_blocks: int = 50
    max_dilution: float = 0.5

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind must be 'range' or 'rssi', got {self.kind!r}")
        for name in ("huber_c", "rank_tol", "se_ratio", "tol", "elongation_ratio"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be positive and finite, got {v}")
        if self.max_iter < 1:
            raise ValueError(f"max_iter must be >= 1, got {self.max_iter}")
        if self.se_blocks < 0 or self.se_blocks == 1:
            raise ValueError(f"se_blocks must be 0 or >= 2, got {self.se_blocks}")
        if not 0 < self.bad_epoch_fraction <= 1:
            raise ValueError("bad_epoch_fraction must be in (0, 1]")
        if not 0 < self.max_dilution < 1:
            raise ValueError(f"max_dilution must be in (0, 1), got {self.max_dilution}")

    # ------------------------------------------------------------------ model
    def _f(self, rho: Array) -> tuple[Array, Array]:
        """``f(rho)`` and ``f'(rho)``."""
        if self.kind == "range":
            return rho, np.ones_like(rho)
        r = np.maximum(rho, 1e-3)
        return -10.0 * np.log10(r), -10.0 / (r * _LN10)

    # ------------------------------------------------------------------ fit
    def fit(
        self,
        anchors: ArrayLike,
        values: ArrayLike,
        x0: ArrayLike,
        *,
        offset0: ArrayLike | None = None,
        slope0: ArrayLike | None = None,
        offset_prior: ArrayLike | None = None,
        slope_prior: ArrayLike | None = None,
        height_offset: ArrayLike | None = None,
        anchor_ids: list[str] | None = None,
        tags: ArrayLike | None = None,
    ) -> SelfCalibration:
        """Adjust the log.

        Parameters
        ----------
        anchors : (m, dim) anchor coordinates (the datum).
        values : (N, m) ranges (m) or RSSI (dBm) per epoch; NaN = not heard.
        x0 : (N, dim) start positions (e.g. robust fixes with the prior calibration);
            NaN rows are left out (counted as ``epochs_no_start``).
        offset0, slope0 : (m,) the model the adjustment starts from, which the start
            fixes ``x0`` used and the motion tests take as the prior calibration (default
            bias 0 / scale 1; required for RSSI).
        offset_prior, slope_prior : (m,) the values a parameter left out keeps, in the
            adjustment and in the result (default ``offset0, slope0``; NaN: that
            default).  ``calibrate --self`` passes the anchors file's range bias and scale
            here and starts from 0 / 1: a parameter the log cannot determine keeps the
            file's value, and the estimates of those it determines do not depend on it.
        height_offset : (m,) anchor-minus-tag heights for 2-D fixes from slant values.
        anchor_ids : names used in the warnings (default ``"0", "1", ...``).
        tags : (N,) each epoch's tag (default: one tag).  Tags that each stand still
            give one position apiece, which the motion test counts against the unknowns
            (:meth:`_static_tags`).
        """
        a = np.asarray(anchors, dtype=float)
        z = np.asarray(values, dtype=float)
        x = np.array(x0, dtype=float, copy=True)
        m, dim = a.shape
        N = z.shape[0]
        if z.shape != (N, m) or x.shape != (N, dim):
            raise ValueError(f"values must be (N, {m}) and x0 (N, {dim})")
        ids = list(anchor_ids) if anchor_ids is not None else [str(i) for i in range(m)]
        names = PARAM_NAMES[self.kind]
        if self.kind == "rssi" and (offset0 is None or slope0 is None):
            raise ValueError("RSSI self-calibration needs the prior A and n of every anchor")
        off = np.zeros(m) if offset0 is None else np.array(offset0, dtype=float)
        slo = np.ones(m) if slope0 is None else np.array(slope0, dtype=float)
        off_start, slo_start = off.copy(), slo.copy()  # the model of the start fixes
        off_prior, slo_prior = off.copy(), slo.copy()
        for given, into in ((offset_prior, off_prior), (slope_prior, slo_prior)):
            if given is not None:
                q = np.broadcast_to(np.asarray(given, dtype=float), (m,))
                into[np.isfinite(q)] = q[np.isfinite(q)]
        h2 = np.zeros(m) if height_offset is None else np.asarray(height_offset, float) ** 2
        obs = np.isfinite(z)
        start_ok = np.all(np.isfinite(x), axis=1)
        x[~start_ok] = 0.0
        tag_codes = (np.zeros(N, dtype=np.int64) if tags is None
                     else pd.factorize(np.asarray(tags, dtype=object))[0].astype(np.int64))
        if tag_codes.shape != (N,):
            raise ValueError(f"tags must be (N,) = ({N},)")
        free = np.zeros((m, 2), dtype=bool)
        free[:, 0] = self.fit_offset
        free[:, 1] = self.fit_slope
        heard = obs.sum(axis=0)
        free[heard == 0] = False
        warnings: list[str] = []
        silent = np.flatnonzero(heard == 0)  # one line (a large site's short log: many)
        if silent.size:
            named = ", ".join(ids[j] for j in silent[:20]) + (
                f" and {silent.size - 20} more" if silent.size > 20 else "")
            warnings.append(f"anchor{'s' if silent.size > 1 else ''} {named}: no observation; "
                            "parameters and sigma left at their priors (sigma: the anchors "
                            "file's, else the median of the other anchors')")
        left_out: dict[tuple[int, int], str] = {}
        # an anchor heard in too few epochs with a fix: its own parameters need a
        # redundancy of OWN_REDUNDANCY among its observations (module notes)
        n_k = obs.sum(axis=1)
        in_fit = (obs & (start_ok & (n_k > dim))[:, None]).sum(axis=0)
        need = free.sum(axis=1) + OWN_REDUNDANCY
        for j in np.flatnonzero(free.any(axis=1) & (in_fit < need)):
            for p in np.flatnonzero(free[j]):
                left_out[(int(j), int(p))] = FEW_REASON
            free[j] = False
        # far field: tags mostly far outside the anchors' extent (e.g. a 2 m cluster heard
        # 5-50 m away): a scale is then a radial stretch of the fixes to O(extent /
        # distance), and the amplification of a scale error into the angle of the fixes is
        # of order distance / extent; slopes are left out (measured on uwb-dwm1001 LOS: a
        # 0.9 % scale error on one anchor, 1.2 -> 2.9 m RMS)
        centre = a.mean(axis=0)
        extent = max(float(np.max(np.linalg.norm(a - centre, axis=1))), 1e-9)
        if start_ok.any() and free[:, 1].any():
            far = float(np.median(np.linalg.norm(x[start_ok] - centre, axis=1)))
            if far > self.far_field_ratio * extent:
                for j in np.flatnonzero(free[:, 1]):
                    free[j, 1] = False
                    left_out[(int(j), 1)] = (
                        f"far field: the median tag distance from the anchors' centroid, "
                        f"{far:.3g} m, exceeds {self.far_field_ratio:g} x their extent "
                        f"{extent:.3g} m (a scale is a radial stretch of the fixes there)")
        # elongated anchors: each fix has a mirror image across their line (plane) that
        # fits nearly as well, told apart only by the anchors' small deviations from it,
        # which per-anchor slopes can mimic (module notes)
        # Judged per epoch, from the tag (mirror_flatness): the elongation of all the
        # heard anchors together took a square of four anchors with a fifth 190 m away,
        # or a 150 m hall with anchors on both walls, for a line, and fixed every scale
        # (biases then 13-30 standard errors off; the self-calibration review)
        cand0 = start_ok & (n_k > dim)
        if free[:, 1].any() and cand0.any():
            hears = obs[cand0]
            flat = mirror_flatness(a, hears, x[cand0])
            amb = ~(flat >= self.elongation_ratio)  # (NaN: no spread at all)
            n_j = hears.sum(axis=0)
            share = (hears & amb[:, None]).sum(axis=0) / np.maximum(n_j, 1)
            for j in np.flatnonzero(free[:, 1] & (n_j > 0) & (share > MIRROR_SHARE)):
                free[j, 1] = False
                left_out.setdefault((int(j), 1), (
                    f"the anchors lie close to a {'line' if dim == 2 else 'plane'} as seen "
                    f"from the tag in {share[j]:.0%} of the epochs that hear it (flatness "
                    f"below {self.elongation_ratio:g}): a fix and its mirror image across "
                    f"it differ only through the anchors' small deviations from it, which "
                    f"per-anchor {names[1]}s can mimic"))

        # redundancy left for the calibration: observations of the epochs with a start and
        # redundancy, minus their positions and the free parameters
        cand = start_ok & (n_k > dim)
        red = int(n_k[cand].sum()) - dim * int(cand.sum()) - int(free.sum())
        if red <= 0 and free.any():
            for j, p in zip(*np.nonzero(free)):
                left_out[(int(j), int(p))] = (
                    f"{NO_REDUNDANCY_REASON} ({int(n_k[cand].sum())} observations in "
                    f"epochs with a fix, for {dim * int(cand.sum())} position unknowns and "
                    f"{int(free.sum())} parameters)")
            free[:] = False
        # what is not estimated (left out so far, or never free) holds its prior
        off = np.where(free[:, 0], off_start, off_prior)
        slo = np.where(free[:, 1], slo_start, slo_prior)
        stages: list[WeightFunction] = [Huber(self.huber_c)]
        if self.igg3_k1 > 0:
            stages.append(IGG3(self.igg3_k0, self.igg3_k1))
        total_it = 0
        converged = True
        ran_away = 0
        state = None
        x_start = x.copy()
        for _round in range(2 * m + 3):  # re-adjust after each se-test exclusion
            huber = None
            ran_away = 0  # (of the last round, whose state is the result)
            for i_stage, wf in enumerate(stages):
                # the Huber stage standardizes by the median scale (a robust MINQUE,
                # module notes item 3) when a redescending stage follows
                state = self._iterate(a, z, obs, x, off, slo, h2, free, start_ok, wf,
                                      left_out, ids,
                                      median_scale=i_stage < len(stages) - 1)
                if huber is not None and self._ran_away(huber, state, free):
                    state = huber  # another root: the Huber estimate stands
                    ran_away += 1
                huber = state
                x, off, slo = state["x"], state["off"], state["slo"]
                total_it += state["iterations"]
                converged = state["converged"]
            if _round == 0 and free.any():
                # motion tests on the start fixes, with the noise of this first adjustment
                # (module notes): what they leave out is re-adjusted from the start
                out = self._motion_test(a, z, obs, x_start, off_start, slo_start, h2,
                                        state, free, ids, left_out, tag_codes)
                if out:
                    for j, p in out:
                        free[j, p] = False
                    # re-adjusted from scratch, as if left out from the start
                    off = np.where(free[:, 0], off_start, off_prior)
                    slo = np.where(free[:, 1], slo_start, slo_prior)
                    x = x_start.copy()
                    continue
            # standard-error test: leave out the worst offending parameter (and the
            # offenders that share no epoch with it: _se_test), re-adjust
            worst = self._se_test(state, free, ids, left_out, obs)
            if not worst:
                break
            for j, p in worst:
                free[j, p] = False
                off[j], slo[j] = (off_prior[j], slo[j]) if p == 0 else (off[j], slo_prior[j])
        assert state is not None
        lin = self._linearize(a, np.where(obs, z, 0.0), obs, state["x"], state["off"],
                              state["slo"], h2)
        state["sigma"] = state["sigma"] / self._sigma_consistency(
            lin["Jx"], obs, state["used"], state["sigma"], stages[-1], dim,
            state["iterations"], ids)
        by_reason: dict[str, list[tuple[int, int]]] = {}
        for (j, p), why in left_out.items():
            by_reason.setdefault(why, []).append((j, p))
        for why, items in by_reason.items():
            if len(items) == 1 or not (why.startswith((STATIC_REASON, STATIC_TAGS_REASON))
                                       or why == FEW_REASON):
                for j, p in items:
                    warnings.append(f"anchor {ids[j]}: cannot determine {names[p]}: "
                                    f"{why}; left out (fixed at its prior {names[p]} = "
                                    f"{(off_prior if p == 0 else slo_prior)[j]:g})")
                continue
            # a static tag (every parameter of every anchor), or anchors heard in too few
            # epochs: one line, naming at most 20 anchors
            params = [q for q in (0, 1) if any(p == q for _, p in items)]
            who = sorted({j for j, _ in items})
            named = ", ".join(ids[j] for j in who[:20]) + (
                f" and {len(who) - 20} more" if len(who) > 20 else "")
            warnings.append(f"anchors {named}: cannot determine "
                            f"{' or '.join(names[q] for q in params)}: {why}; left out "
                            f"(fixed at their priors)")
        for (j, p) in left_out:
            if p == 0:
                off[j] = off_prior[j]
            else:
                slo[j] = slo_prior[j]
        sigma_why = self._sigma_undetermined(state["sigma_dof"], free, left_out, heard)
        by_why: dict[str, list[int]] = {}
        for j, why in sigma_why.items():
            if heard[j] > 0:  # (an anchor never heard has its warning above)
                by_why.setdefault(why, []).append(j)
        for why, who in by_why.items():
            named = ", ".join(ids[j] for j in who[:20]) + (
                f" and {len(who) - 20} more" if len(who) > 20 else "")
            warnings.append(f"anchor{'s' if len(who) > 1 else ''} {named}: cannot determine "
                            f"sigma: {why}; left out (kept at its prior)")
        sigma_free = np.ones(m, dtype=bool)
        sigma_free[list(sigma_why)] = False
        if ran_away:
            warnings.append(f"the redescending stage (IGG-III) left the Huber estimate for "
                            f"a fit whose noise scale is over {RUNAWAY_SCALE:g} times "
                            "larger (another root, pulled by gross errors): the Huber "
                            "estimate was kept")
        if not converged:
            warnings.append(f"self-calibration stopped at the iteration limit ({self.max_iter} "
                            "per stage)")
        cov = state["cov"]
        se_off = np.where(free[:, 0], np.sqrt(cov[:, 0, 0]), np.nan)
        se_slo = np.where(free[:, 1], np.sqrt(cov[:, 1, 1]), np.nan)
        return SelfCalibration(
            kind=self.kind, param_names=names, offset=off, slope=slo,
            offset_se=se_off, slope_se=se_slo, cov=cov, sigma=state["sigma"], free=free,
            positions=np.where(state["used"][:, None], x, np.nan),
            epoch_used=state["used"], weights=np.where(obs, state["w"], np.nan),
            n_obs=heard.astype(np.int64),
            n_used=np.sum((state["w"] > 0) & state["used"][:, None], axis=0).astype(np.int64),
            epochs_total=N, epochs_used=int(state["used"].sum()),
            epochs_no_redundancy=int(state["no_red"].sum()),
            epochs_bad=int(state["bad"].sum()), epochs_no_start=int((~start_ok).sum()),
            observations_rejected=int(np.sum((state["w"] == 0) & obs
                                             & state["used"][:, None])),
            sigma0=float(state["sigma0"]), iterations=total_it, converged=converged,
            min_eigenvalue=float(state["min_ev"]), warnings=warnings,
            sigma_free=sigma_free,
        )

    def _sigma_undetermined(
        self, dof: Array, free: NDArray[np.bool_], left_out: dict[tuple[int, int], str],
        heard: NDArray[np.int64],
    ) -> dict[int, str]:
        """The anchors whose ``sigma`` the log does not determine, with the reason.

        * never heard;
        * no parameter estimated, left out because the tag does not move, the tags stand
          still, the anchor is heard in too few epochs or the log has no redundancy
          (:data:`SIGMA_WITH_PARAMS`): its residuals then carry its unfitted bias (on a
          simulated static tag the sigmas came out 0.11-1.04 m for a truth of
          0.10-0.17 m, and ``locate`` went 0.21 -> 0.53 m RMS with them; the
          self-calibration review);
        * the variance component has at most :data:`SIGMA_MIN_DOF` degrees of freedom
          (Satterthwaite's ``nu_j = 2 var_j^2 / Var(var_j)`` of the MINQUE,
          :meth:`_vce_dof`; ``nu_j <= 2`` is the estimate within one standard error of
          zero): the two degrees of freedom a truth-based calibration asks of an anchor's
          own sigma (:func:`robustloc.models.calibration._own_fit`).  With ``nu = 2``
          the variance is ``chi2_2 / 2`` distributed: one anchor in 20 reads it below
          1/20 of the truth (its sigma below 0.22 of it), and ``locate`` weights it by
          that; a one-epoch log of five anchors (3 residual degrees of freedom for five
          components) wrote five sigmas off by factors 0.46-14.
        """
        out: dict[int, str] = {}
        short = {STATIC_REASON: "the tag does not move",
                 STATIC_TAGS_REASON: "the tags do not move",
                 FEW_REASON: "it is heard in too few epochs",
                 NO_REDUNDANCY_REASON: "the log has no redundancy"}
        for j in range(free.shape[0]):
            if heard[j] == 0:
                out[j] = "no observation"
                continue
            whys = [w for (jj, _), w in left_out.items()
                    if jj == j and w.startswith(SIGMA_WITH_PARAMS)]
            if whys and not free[j].any():
                label = next(v for k, v in short.items() if whys[0].startswith(k))
                out[j] = (f"its parameters were left out ({label}), so its residuals "
                          "carry their errors")
            elif not dof[j] > SIGMA_MIN_DOF:
                nu = max(float(np.nan_to_num(dof[j])), 0.0)
                out[j] = (f"the log gives its variance {nu:.2g} degrees of freedom, at "
                          f"most {SIGMA_MIN_DOF:g} (not told from zero)")
        return out

    # ------------------------------------------------------------------ core
    def _iterate(
        self, a: Array, z: Array, obs: NDArray[np.bool_], x: Array, off: Array, slo: Array,
        h2: Array, free: NDArray[np.bool_], start_ok: NDArray[np.bool_], wf: WeightFunction,
        left_out: dict[tuple[int, int], str], ids: list[str], median_scale: bool = False,
    ) -> dict:
        N, m = z.shape
        dim = a.shape[1]
        zz = np.where(obs, z, 0.0)
        x = x.copy()
        off, slo = off.copy(), slo.copy()
        sigma = None
        converged = False
        it = 0
        last_small = False
        lam, prev_dth = 1.0, None
        kappa = _consistency(wf)
        n_obs = obs.sum(axis=1)
        no_red = start_ok & (n_obs <= dim)
        base = start_ok & ~no_red
        lost = np.zeros(N, dtype=bool)
        centre = a.mean(axis=0)
        extent = max(float(np.max(np.linalg.norm(a - centre, axis=1))), 1.0)
        for it in range(1, self.max_iter + 1):
            lin = self._linearize(a, zz, obs, x, off, slo, h2)
            v, Jx, fval = lin["v"], lin["Jx"], lin["f"]
            if sigma is None:  # first pass: unit weights, q_vv from the geometry alone
                w = np.where(obs, 1.0, 0.0)
                sigma = np.ones(m)
            # q_vv = 1 - h, h the leverage of the observation within its epoch's fix
            P = np.where(base[:, None], w, 0.0) / sigma[None, :] ** 2
            veq, R, regular = self._robust_fit(Jx, np.where(base[:, None], w, 0.0), v)
            sigma, sigma_dof = self._vce_dof(veq, R, np.where(base[:, None] & obs, w, 0.0),
                                             kappa, median=median_scale)
            with np.errstate(invalid="ignore", divide="ignore"):
                u = veq / np.sqrt(R.variances(sigma**2))
            w = np.where(obs, np.nan_to_num(wf.weights(np.where(obs, u, 0.0)), nan=0.0), 0.0)
            used, bad = self._epochs(w, u, obs, base & regular, dim)
            bad |= (base & ~regular) | lost
            P = np.where(used[:, None], w / sigma[None, :] ** 2, 0.0)
            Jt = np.stack([np.ones_like(fval), fval], axis=-1)  # (N, m, 2)
            sol = self._solve(Jx, Jt, P, v, free, used, left_out, ids)
            dx, dth = sol["dx"], sol["dth"]
            # relaxation against the 2-cycles of IRLS (weights flipping between two
            # states): a step that reverses the previous one is halved, down to 1/8
            if prev_dth is not None and float(np.sum(dth * prev_dth)) < 0:
                lam = max(0.5 * lam, 1.0 / 32.0)
            prev_dth = dth
            dx, dth = lam * dx, lam * dth
            # trust region of the positions: a step at most half the anchors' extent, and an
            # epoch that leaves 3 extents around the anchors is lost (left out, bad)
            step = np.linalg.norm(dx, axis=1, keepdims=True)
            dx = dx * np.minimum(1.0, 0.5 * extent / np.maximum(step, 1e-300))
            x = x + np.where(used[:, None], dx, 0.0)
            lost |= used & (np.linalg.norm(x - centre, axis=1) > 3.0 * extent)
            base &= ~lost
            off = off + dth[:, 0]
            slo = slo + dth[:, 1]
            se = np.sqrt(np.maximum(np.diagonal(sol["Sinv"], axis1=1, axis2=2), 0.0))
            with np.errstate(invalid="ignore", divide="ignore"):
                # the step applied (relaxed): at a 2-cycle any point between is as good
                rel = np.where(free & (se > 0), np.abs(dth) / se, 0.0)
            # the calibration is converged when no parameter moves by more than tol of its
            # standard error (twice in a row: IRLS weights of low-redundancy epochs can
            # flip between iterations); positions follow from it
            small = np.max(rel, initial=0.0) < self.tol
            if np.max(rel, initial=0.0) < 1.0:
                # the parameters have settled (steps below one standard error): the bad
                # epochs found so far stay out, so that the set cannot flip back and forth
                lost |= bad
                base &= ~lost
            if small and last_small and it > 2:
                converged = True
                break
            last_small = small
        # final quantities at the solution
        lin = self._linearize(a, zz, obs, x, off, slo, h2)
        v, Jx, fval = lin["v"], lin["Jx"], lin["f"]
        P = np.where(used[:, None], w / sigma[None, :] ** 2, 0.0)
        Jt = np.stack([np.ones_like(fval), fval], axis=-1)
        sol = self._solve(Jx, Jt, P, v, free, used, left_out, ids, scores=True)
        n_used = int(np.sum(P > 0))
        n_unk = int(used.sum()) * dim + int(free.sum())
        dof = max(n_used - n_unk, 1)
        s02 = float(np.sum(P * v * v) / kappa / dof)
        cov_model = s02 * sol["Sinv"]
        cov = self._robust_cov(sol, used, cov_model, n_used / dof)
        fsd = np.zeros(m)
        for j in range(m):
            sel = obs[:, j] & used & (w[:, j] > 0)
            fsd[j] = float(np.std(fval[sel, j])) if sel.sum() > 1 else 0.0
        return {
            "x": x, "off": off, "slo": slo, "sigma": sigma, "w": w, "used": used,
            "no_red": no_red, "bad": bad, "cov": cov, "cov_model": cov_model,
            "sigma0": np.sqrt(s02), "sigma_dof": sigma_dof,
            "iterations": it, "converged": converged, "fsd": fsd, "min_ev": sol["min_ev"],
        }

    @staticmethod
    def _ran_away(huber: dict, state: dict, free: NDArray[np.bool_]) -> bool:
        """Did the redescending stage leave the Huber stage's estimate for a worse fit:
        the anchors' median noise scale grown more than :data:`RUNAWAY_SCALE` times?  A
        redescending M-estimator finds the root of the basin it starts in (Hampel et al.,
        "Robust Statistics", 1986, sec. 2.6); refining a consistent start it rejects
        gross errors and the scale shrinks or stays, but with a gross error in a third of
        the epochs it left a Huber estimate of scale 1.02 (truth 1.01, noise 0.05 m) for
        0.40, its median noise scale going 0.05 -> 0.20 m (the calibration review)."""
        def level(st: dict) -> float:
            sig = np.asarray(st["sigma"], dtype=float)
            sig = sig[np.isfinite(sig) & (sig > 0)]
            return float(np.median(sig)) if sig.size else float("nan")
        before, after = level(huber), level(state)
        return bool(np.isfinite(before) and np.isfinite(after)
                    and after > RUNAWAY_SCALE * before)

    def _linearize(
        self, a: Array, zz: Array, obs: NDArray[np.bool_], x: Array, off: Array,
        slo: Array, h2: Array,
    ) -> dict:
        diff = x[:, None, :] - a[None, :, :]  # (N, m, dim)
        rho = np.sqrt(np.sum(diff * diff, axis=-1) + h2[None, :])
        rho = np.maximum(rho, 1e-6)
        f, fp = self._f(rho)
        pred = off[None, :] + slo[None, :] * f
        v = np.where(obs, zz - pred, 0.0)
        Jx = (slo[None, :] * fp / rho)[..., None] * diff  # d pred / d x
        Jx = np.where(obs[..., None], Jx, 0.0)
        return {"v": v, "Jx": Jx, "f": np.where(obs, f, 0.0)}

    @staticmethod
    def _robust_fit(
        Jx: Array, W: Array, v: Array
    ) -> tuple[Array, _Residuals, NDArray[np.bool_]]:
        """Residuals of each epoch's fix with the weights ``W``, and its residual matrix.

        ``R_k = I - J (J^T W J)^-1 J^T W`` maps the observation errors of epoch ``k`` to
        its residuals: ``v_eq = R_k v`` (a change of the position is annihilated, so the
        current residuals serve) and ``E v_eq,j^2 = sum_i R_k,ji^2 sigma_i^2``.  Returns
        ``v_eq (N, m)``, ``R`` (:class:`_Residuals`: each epoch's matrix on the anchors it
        observed) and whether ``J^T W J`` is regular.
        """
        m = Jx.shape[1]
        front = _front(np.any(Jx != 0.0, axis=2) | (W > 0) | (v != 0.0))
        if front is not None:  # the rows of the anchors each epoch observed, in order
            Jx = np.take_along_axis(Jx, front[..., None], axis=1)
            W = np.take_along_axis(W, front, axis=1)
            v = np.take_along_axis(v, front, axis=1)
        Nxx = np.einsum("kjd,kj,kje->kde", Jx, W, Jx)
        Ninv, regular = _inv_batched(Nxx)
        H = np.einsum("kjd,kde,kie,ki->kji", Jx, Ninv, Jx, W)
        R = np.eye(Jx.shape[1])[None] - H
        veq = np.einsum("kji,ki->kj", R, v)
        res = _Residuals(front, R, m)
        return res.scatter(veq, 0.0), res, regular

    @classmethod
    def _vce(cls, veq: Array, R: _Residuals, W: Array, kappa: float,
             median: bool = False) -> Array:
        """:meth:`_vce_dof`'s scales alone."""
        return cls._vce_dof(veq, R, W, kappa, median)[0]

    @staticmethod
    def _vce_dof(veq: Array, R: _Residuals, W: Array, kappa: float,
                 median: bool = False) -> tuple[Array, Array]:
        """Per-anchor variances from the whole log, unbiased (MINQUE with the robust
        weights as the norm, Rao 1971; Koch, "Parameter Estimation and Hypothesis Testing
        in Linear Models", sec. 3.6): ``sum_k w_kj v_kj^2 = sum_i (sum_k w_kj R_k,ji^2)
        sigma_i^2``, an ``m x m`` linear system ``s = B var``.  Not iterated on the
        variances themselves (so no anchor's estimate can pull itself to zero), the
        estimate of a precise anchor is not inflated by the others' noise (as a plain
        pooled residual scale is).  An undetermined solution falls back to the scale of the
        anchor's own residuals ``naive_j = sqrt(s_j / B_jj)``.

        Where the log cannot tell the variance from zero (the estimate within one of its
        own standard errors of it) the estimate is raised to ``(naive_j / 2)^2``, a
        conservative value: a noisy small estimate would pin every fix to that anchor
        (with 300 epochs one came out at 0.013 m for a 0.10 m anchor).  For Gaussian
        residuals ``Cov(s_j, s_i) = 2 sum_k w_kj w_ki C_k,ji^2 / kappa^2`` with
        ``C_k = R_k diag(var) R_k^T`` the residuals' covariance in epoch ``k`` (Isserlis'
        theorem), so ``Cov(var) = B^-1 Cov(s) B^-T``, evaluated at the estimate raised to
        ``(naive_j / 2)^2``.  A determined estimate is left as it is, and so unbiased.  (As
        a floor for every estimate, the first rule, ``naive_j / 2`` bound for a precise
        anchor among noisier ones, whose own residuals carry their noise: on the test
        room's 0.10 m anchor at ``(0, 8)`` it lay 7 % above the truth and the estimate read
        9 % high over 60 logs of 1500 epochs.  With the standard error itself as the
        floor, the wifi-rtt corridor's AP2, not determined by its log, came out at 0.35 m
        instead of 0.89 m and the corridor's self-calibrated RMS went 3.50 -> 3.62 m.)

        The robust weights shrink the tails: ``sum w v^2`` is divided by
        ``kappa = E[w(u) u^2] / P(w(u) > 0)`` for standard normal ``u``
        (:func:`_consistency`) and ``B`` counts the observations in use, so that the
        estimate is consistent for Gaussian errors.

        Returns the scales and each anchor's degrees of freedom, Satterthwaite's
        ``nu_j = 2 var_j^2 / Var(var_j)`` at the unfloored estimate (the ``nu`` of a
        ``chi2_nu / nu`` with the estimate's variance; 0 where the estimate is not
        positive, NaN where it could not be formed): "not told from zero" above is
        ``nu_j <= 2``."""
        m = veq.shape[1]
        R2 = R.R * R.R
        if median:
            inl = W > 0
            cnt = inl.sum(axis=0)
            with np.errstate(all="ignore"), _warnings.catch_warnings():
                _warnings.simplefilter("ignore", RuntimeWarning)  # (an unheard anchor)
                med = np.nanmedian(np.where(inl, veq * veq, np.nan), axis=0)
            s = cnt * np.where(cnt > 0, med, 0.0) / CHI2_1_MEDIAN
            W = inl.astype(float)
            kappa = 1.0
        else:
            s = np.sum(W * veq * veq, axis=0) / kappa
        if R.front is None:
            B = np.einsum("kj,kji->ji", (W > 0).astype(float), R2)
        else:  # the same sums over the epochs' compact blocks
            Wc = R.take(W)
            B = R.gather_sum(np.einsum("kj,kji->kji", (Wc > 0).astype(float), R2))
        naive = np.sqrt(s / np.maximum(np.diagonal(B), 1e-300))
        # the anchors with residuals in use: an anchor without any (never heard, or every
        # observation rejected) has a zero row and column in B, which made the system
        # singular and every anchor fall back to its naive scale (an unheard anchor in the
        # anchors file moved the others' sigma by up to 85 %: the calibration review)
        act = np.flatnonzero(np.diagonal(B) > 0)
        var = np.full(m, np.nan)
        Binv = np.full((m, m), np.nan)
        try:
            Ba = B[np.ix_(act, act)]
            var[act] = np.linalg.solve(Ba, s[act])
            Binv[np.ix_(act, act)] = np.linalg.inv(Ba)
        except np.linalg.LinAlgError:
            var[:] = np.nan
        ok = np.isfinite(var) & (np.sum(W > 0, axis=0) > 0)
        cap = (0.5 * naive) ** 2
        plug = np.maximum(np.where(ok, var, 0.0), cap)
        # (an anchor heard in a handful of epochs can leave B nearly singular and its
        # plug-in variance beyond float range: its se_var is then not finite, and the
        # variance undetermined below -- no warning; 200 epochs of 900 anchors)
        with np.errstate(over="ignore", invalid="ignore"):
            if R.front is None:
                C = np.einsum("kjl,l,kil->kji", R.R, np.nan_to_num(plug), R.R)
                cov_s = 2.0 * np.einsum("kj,ki,kji->ji", W, W, C * C) / kappa**2
            else:
                C = np.einsum("kjl,kl,kil->kji", R.R, R.take(np.nan_to_num(plug)), R.R)
                cov_s = 2.0 * R.gather_sum(np.einsum("kj,ki,kji->kji", Wc, Wc, C * C)
                                           ) / kappa**2
        se_var = np.full(m, np.nan)
        with np.errstate(invalid="ignore", over="ignore"):
            Bi = Binv[np.ix_(act, act)]
            se_var[act] = np.sqrt(np.maximum(np.diagonal(
                Bi @ cov_s[np.ix_(act, act)] @ Bi.T), 0.0))
        raw = np.where(ok, var, 0.0)
        # not told from zero (within one standard error of it): the conservative floor
        undetermined = ~(raw > np.where(np.isfinite(se_var), se_var, np.inf))
        var = np.where(undetermined, np.maximum(raw, cap), raw)
        out = np.where(ok, np.sqrt(var), naive)
        pos = np.isfinite(out) & (out > 0)
        fill = float(np.median(out[pos])) if pos.any() else 1.0
        sig = np.where(pos, out, fill)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            dof = np.where(ok & np.isfinite(se_var),
                           np.where(raw > 0, 2.0 * raw**2 / se_var**2, 0.0), np.nan)
        return sig, dof

    def _sigma_consistency(
        self, Jx: Array, obs: NDArray[np.bool_], used: NDArray[np.bool_], sigma: Array,
        wf: WeightFunction, dim: int, iterations: int, ids: list[str] | None = None,
    ) -> Array:
        """What the final stage's per-anchor scale reads, as a share of the truth, for
        Gaussian errors of scale ``sigma`` on the log's own geometry.

        ``kappa`` (:func:`_consistency`) makes the weighted squares consistent for a
        standardized residual known to be ``N(0, 1)``; the stage standardizes with its own
        estimate, its weights move the fits whose residuals it squares, and the epochs that
        fail their global test leave the sums.  On the test room's 60 simulated logs of
        1 500 epochs (equal ``sigma``), the scale read 0.989 +- 0.002 of the truth.  So the
        stage is run again, as :meth:`_iterate` ran it (unit weights first, then its
        weight function, :meth:`_robust_fit`, :meth:`_vce`, :meth:`_epochs`, for its
        number of ``iterations``), on
        :data:`SIGMA_FACTOR_DRAWS` Gaussian observations of scale ``sigma`` at the
        solution's design rows ``Jx`` of the epochs ``used`` (repeated), and its scale is
        divided by the least-squares MINQUE of the same draws, which is unbiased (a control
        variate: the draws' own noise cancels in the ratio).

        Returns
        -------
        ndarray (m,)
            The factor of each anchor; 1 where nothing could be measured.
        """
        rows = np.flatnonzero(used)
        n_obs = int(obs[rows].sum())
        if n_obs == 0:
            return np.ones(sigma.shape[0])
        reps = int(min(16, max(1, -(-SIGMA_FACTOR_DRAWS // n_obs))))
        J = np.tile(Jx[rows], (reps, 1, 1))
        ob = np.tile(obs[rows], (reps, 1))
        # one stream of draws per anchor, seeded by its id: the factor of an anchor does
        # not depend on the order of the anchors file or on anchors never heard (with one
        # stream for the whole matrix, reversing the file moved a sigma by 5 %)
        import zlib

        names = ids if ids is not None else [str(j) for j in range(ob.shape[1])]
        draws = np.column_stack([
            np.random.default_rng([SIGMA_FACTOR_SEED, zlib.crc32(str(n).encode())])
            .standard_normal(ob.shape[0]) for n in names])
        e = np.where(ob, draws * sigma[None, :], 0.0)
        unit = ob.astype(float)
        veq, R, _ = self._robust_fit(J, unit, e)
        ls = self._vce(veq, R, unit, 1.0)
        kappa = _consistency(wf)
        w = unit
        cand = np.ones(ob.shape[0], dtype=bool)
        lost = np.zeros_like(cand)
        sig = sigma
        for _ in range(max(iterations, 1)):
            veq, R, regular = self._robust_fit(J, np.where(cand[:, None], w, 0.0), e)
            new = self._vce(veq, R, np.where(cand[:, None] & ob, w, 0.0), kappa)
            with np.errstate(invalid="ignore", divide="ignore"):
                u = veq / np.sqrt(R.variances(new**2))
            w = np.where(ob, np.nan_to_num(wf.weights(np.where(ob, u, 0.0)), nan=0.0), 0.0)
            used_sim, bad = self._epochs(w, u, ob, regular & ~lost, dim)
            lost |= bad
            cand, sig = used_sim, new
        if not np.all(np.isfinite(sig)):
            return np.ones(sigma.shape[0])
        factor = sig / ls
        return np.where(np.isfinite(factor) & (factor > 0), factor, 1.0)

    def _epochs(
        self, w: Array, u: Array, obs: NDArray[np.bool_], cand: NDArray[np.bool_], dim: int
    ) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """Epochs used, and candidates left out as bad: too many rejections, no
        redundancy left, or the global test of the epoch's observations in use fails
        (``sum w u^2 > chi2_{1 - epoch_alpha}(n_w - dim)``, seed 003's global test)."""
        from robustloc._stats import chi2_ppf

        n_obs = obs.sum(axis=1)
        inl = (w > 0) & obs
        n_w = inl.sum(axis=1)
        red = n_w - dim
        T = np.sum(np.where(inl, w * np.nan_to_num(u) ** 2, 0.0), axis=1)
        with np.errstate(invalid="ignore"):
            crit = chi2_ppf(1.0 - self.epoch_alpha, np.maximum(red, 1))
        bad = cand & ((red <= 0) | (n_obs - n_w > self.bad_epoch_fraction * n_obs)
                      | (T > crit))
        return cand & ~bad, bad

    def _solve(
        self, Jx: Array, Jt: Array, P: Array, v: Array, free: NDArray[np.bool_],
        used: NDArray[np.bool_], left_out: dict[tuple[int, int], str], ids: list[str],
        scores: bool = False,
    ) -> dict:
        """One Gauss-Newton step of the joint problem by the Schur complement.

        With ``scores``: also each epoch's share of the reduced gradient, ``g_k = g_t,k -
        N_tk N_kk^-1 g_x,k`` ``(N, 2m)`` (they sum to the reduced gradient), and the
        inverse of the free block of the reduced normal matrix ``(2m, 2m)``."""
        N, m, dim = Jx.shape
        Nxx = np.einsum("kjd,kj,kje->kde", Jx, P, Jx)  # (N, dim, dim)
        Nxx[~used] = np.eye(dim)
        Ninv, _ = _inv_batched(Nxx)
        gx = np.einsum("kjd,kj,kj->kd", Jx, P, v)
        # N_xt: (N, dim, m, 2), only anchor j's own parameters touch observation (k, j)
        Nxt = np.einsum("kjd,kj,kjp->kdjp", Jx, P, Jt).reshape(N, dim, 2 * m)
        Ntt_blk = np.einsum("kjp,kj,kjq->jpq", Jt, P, Jt)  # (m, 2, 2)
        gt = np.einsum("kjp,kj,kj->jp", Jt, P, v).reshape(2 * m)
        M = np.einsum("kde,kep->kdp", Ninv, Nxt)  # N_kk^-1 N_kt
        S = _block_diag(Ntt_blk) - _schur_sum(Nxt, M, P != 0)
        gr = gt - np.einsum("kdp,kd->p", M, gx)
        S = 0.5 * (S + S.T)
        # observability: leave out inseparable parameters until S_FF is regular
        while True:
            F = np.flatnonzero(free.reshape(-1))
            if F.size == 0:
                break
            SF = S[np.ix_(F, F)]
            d = np.sqrt(np.clip(np.diag(SF), 0.0, None))
            tiny = d <= 1e-300
            if tiny.any():
                k = int(F[np.argmax(tiny)])
                self._leave_out(free, left_out, k, "the log carries no information on it")
                continue
            C = SF / np.outer(d, d)
            if F.size >= 2 * SCHUR_SPARSE_FROM:  # a large site: the vectors only if needed
                ev = np.linalg.eigvalsh(C)
                if ev[0] >= self.rank_tol:
                    break
            ev, vec = np.linalg.eigh(C)
            if ev[0] >= self.rank_tol:
                break
            comp = np.abs(vec[:, 0])
            # among the parameters involved in the null direction (component at least
            # 10 % of the largest) a slope goes first (an offset is the more common need),
            # the one with the largest share of that direction
            near = comp >= 0.1 * comp.max()
            slope_first = near & (F % 2 == 1)
            pick = np.flatnonzero(slope_first if slope_first.any() else near)
            k = int(F[pick[np.argmax(comp[pick])]])
            others = [int(F[i]) for i in np.argsort(-comp)[:4]
                      if comp[i] > 0.2 and int(F[i]) != k][:3]
            names = PARAM_NAMES[self.kind]
            partners = ", ".join(f"{names[q % 2]} of anchor {ids[q // 2]}" for q in others)
            why = ("inseparable from the positions" + (f" and from {partners}" if partners
                                                       else "")
                   + f" (eigenvalue {max(ev[0], 0.0):.1e} of the reduced normal matrix "
                   f"< {self.rank_tol:g})")
            self._leave_out(free, left_out, k, why)
        F = np.flatnonzero(free.reshape(-1))
        dth = np.zeros(2 * m)
        Sinv = np.zeros((2 * m, 2 * m))
        if F.size:
            SF = S[np.ix_(F, F)]
            d = np.sqrt(np.diag(SF))
            Ci = np.linalg.inv(SF / np.outer(d, d))
            SFi = Ci / np.outer(d, d)
            dth[F] = SFi @ gr[F]
            Sinv[np.ix_(F, F)] = SFi
        dx = np.einsum("kde,ke->kd", Ninv, gx - np.einsum("kdp,p->kd", Nxt, dth))
        blocks = np.stack([Sinv[2 * j:2 * j + 2, 2 * j:2 * j + 2] for j in range(m)])
        min_ev = float(ev[0]) if F.size else float("nan")
        out = {"dx": dx, "dth": dth.reshape(m, 2), "Sinv": blocks, "min_ev": min_ev}
        if scores:
            gtk = (Jt * (P * v)[..., None]).reshape(N, 2 * m)
            out["scores"] = np.where(used[:, None], gtk - np.einsum("kdp,kd->kp", M, gx),
                                     0.0)
            out["Sinv_full"] = Sinv
        return out

    def _robust_cov(self, sol: dict, used: NDArray[np.bool_], cov_model: Array,
                    dof_factor: float) -> Array:
        """Cluster-robust (sandwich) covariance of the parameters, per anchor ``(m, 2, 2)``
        (module notes, item 4): ``S^-1 (sum_c g_c g_c^T) S^-1 G / (G - 1) n / (n - u)``
        over ``G`` contiguous blocks of the used epochs, ``g_c`` the sum of the block's
        epoch scores.  ``dof_factor = n / (n - u)`` (observations over redundancy, as in
        ``sigma0^2``): each epoch's own position absorbs part of its errors, so the
        residuals in the scores are smaller than the errors (measured without it: the
        standardized errors' spread 1.33 instead of 1 with 5 anchors, ``sqrt(5 / 3)``).
        Its diagonal is floored at the model covariance's (adding a non-negative diagonal
        keeps it positive semi-definite)."""
        n_used = int(used.sum())
        G = min(self.se_blocks, n_used)
        if G < 2:
            return cov_model
        m = cov_model.shape[0]
        label = np.full(used.shape[0], -1)
        label[used] = np.arange(n_used) * G // n_used
        g = np.zeros((G, 2 * m))
        np.add.at(g, label[used], sol["scores"][used])
        Si = sol["Sinv_full"]
        cov = Si @ (g.T @ g) @ Si * (G / (G - 1) * dof_factor)
        blocks = np.stack([cov[2 * j:2 * j + 2, 2 * j:2 * j + 2] for j in range(m)])
        dm = np.diagonal(cov_model, axis1=1, axis2=2)
        dr = np.diagonal(blocks, axis1=1, axis2=2)
        return blocks + np.einsum("jp,pq->jpq", np.maximum(dm - dr, 0.0), np.eye(2))

    def _motion_test(
        self, a: Array, z: Array, obs: NDArray[np.bool_], x0: Array, off0: Array,
        slo0: Array, h2: Array, state: dict, free: NDArray[np.bool_], ids: list[str],
        left_out: dict[tuple[int, int], str], tags: NDArray[np.int64] | None = None,
    ) -> list[tuple[int, int]]:
        """Does the tag move, and do the distances to each anchor vary, by more than the
        fixes' noise explains?  (Module notes, "Motion".)  Returns the parameters to leave
        out, their reasons recorded in ``left_out``.

        ``D`` is the share of a typical spread that the noise explains (``1 - D``
        estimates the reliability ratio, var(signal) / var(signal + noise), whose
        shortfall is the regression dilution of a slope fitted to noisy regressors:
        Fuller, "Measurement Error Models", 1987, sec. 1.1).  Medians throughout: the
        fixes' errors have heavy tails.

        * Positions (:meth:`_static_share`): the spread of the log's fixes with the prior
          calibration against the spread of fixes of a simulated static tag at their
          median point, with the same anchors heard and the log's per-anchor sigmas
          (a parametric bootstrap of "the tag does not move", so that the fixes'
          nonlinearity is in both: for RSSI a linearized covariance predicted a fifth of
          a simulated static tag's spread).
        * Anchor ``j``, on the first adjustment's positions and model (the start fixes
          carry the prior calibration's errors, which move with the tag: on a circle
          around an anchor they spread the start distances to it by 0.25 m, 2.5 times the
          noise): ``D_j = chi2_0.5(1) / median_k t_kj``, ``t_kj = (f_kj - fmed_j)^2 /
          var f_kj``, ``var f_kj = f'(rho)^2 g^T C_k g`` (``C_k`` the fix's covariance
          with the adjustment's weights and sigmas, ``g`` the unit vector from the
          anchor).

        ``D > max_dilution``: on a static tag every offset and slope is left out (the log
        gives one value per anchor, which the position and the anchor's parameters share;
        a simulated static tag gave scales of 0.25-3.2 for a truth of 0.97-1.03 with the
        slopes in); at a constant distance from an anchor, its slope (its offset stays,
        the more common need; a simulated tag circling an anchor, D = 0.71, fitted a scale
        of 0.46 for 0.97).  Measured on the shared real logs: positions, D at most 0.02
        for ranges and 0.11 for ble-tetam; anchors, at most 0.03 for ranges and 0.11-0.22
        for ble-tetam's RSSI.  A simulated static RSSI tag (2-3 dB): D above 1."""
        from robustloc._stats import chi2_ppf

        names = PARAM_NAMES[self.kind]
        out: list[tuple[int, int]] = []
        D, n = self._static_share(a, z, obs, x0, off0, slo0, h2, state)
        if D > self.max_dilution:
            why = (f"{STATIC_REASON}: the spread of its {n} fixes is {min(D, 1.0):.0%} or "
                   f"more noise (more than {self.max_dilution:.0%}; a simulated static "
                   f"tag's), so the log gives one value per anchor, which the position and "
                   f"the anchor's parameters share")
            for j in range(free.shape[0]):
                for p in range(2):
                    if free[j, p] or (j, p) in left_out:
                        left_out[(j, p)] = why  # the reason, whatever round 0 found
                        if free[j, p]:
                            out.append((j, p))
            return out
        sigma, w = state["sigma"], np.nan_to_num(state["w"], nan=0.0)
        slo, used = state["slo"], state["used"]
        ob = obs[used]
        lin = self._linearize(a, np.where(ob, z[used], 0.0), ob, state["x"][used],
                              np.zeros(a.shape[0]), slo, h2)
        C, reg = _inv_batched(np.einsum("kjd,kj,kje->kde", lin["Jx"],
                                        np.where(ob, w[used], 0.0) / sigma**2, lin["Jx"]))
        # d f / d x = f'(rho) g = Jx / slope
        G = lin["Jx"] / np.where(slo == 0, 1.0, slo)[None, :, None]
        var = np.einsum("kjd,kde,kje->kj", G, C, G)
        if tags is not None:
            out += self._static_tags(state["x"][used], C, reg, ob, tags[used], free,
                                     left_out)
        for j in np.flatnonzero(free[:, 1]):
            sel = reg & ob[:, j] & (var[:, j] > 0)
            nj = int(sel.sum())
            if nj < 2:
                continue
            fj = lin["f"][sel, j]
            tj = (fj - np.median(fj)) ** 2 / var[sel, j]
            Dj = float(chi2_ppf(0.5, 1)) / max(float(np.median(tj)), 1e-300)
            if Dj > self.max_dilution:
                left_out[(int(j), 1)] = (
                    f"the distances to it vary too little: the fixes' noise explains "
                    f"{min(Dj, 1.0):.0%} of their spread over {nj} fixes (more than "
                    f"{self.max_dilution:.0%}), so its {names[1]} cannot be told from its "
                    f"{names[0]} (a {names[1]} fitted there is diluted toward the noise)")
                out.append((int(j), 1))
        return out

    def _static_tags(
        self, x: Array, C: Array, reg: NDArray[np.bool_], ob: NDArray[np.bool_],
        tags: NDArray[np.int64], free: NDArray[np.bool_],
        left_out: dict[tuple[int, int], str],
    ) -> list[tuple[int, int]]:
        """Tags that each stand still: one position apiece, counted against the unknowns.

        The log moves (the test of :meth:`_static_share` passed) and yet it may hold only
        a few positions: two tags each standing at its own point give two values per
        anchor, and the fit of their positions and every anchor's bias and scale was
        "determined" by the fixes' jitter (scales 0.7-1.9 for a truth of 0.98-1.05, a
        bias of -6.5 m, ``locate`` 9 m off where the prior gave 0.5 m: the
        self-calibration review, 2026-12-06).  A tag stands still when the noise explains
        more than ``max_dilution`` of its fixes' spread: ``D_t = (chi2_0.5(dim) / dim) /
        median_k (|x_k - xmed_t|^2 / tr C_k)`` (``C_k`` the fix's covariance of the first
        adjustment, as the anchor test's; a linearized covariance understates RSSI fixes'
        spread, so RSSI tags at rest may pass for moving: the test then changes nothing).
        When every tag stands still, the log holds ``V`` distinct values (each tag's
        anchors) for ``dim`` unknowns per tag and the free parameters: the slopes are
        left out while the redundancy ``V - unknowns`` is below :data:`OWN_REDUNDANCY`,
        then the offsets too.  Returns the parameters left out."""
        from robustloc._stats import chi2_ppf

        if tags.size == 0 or int(tags.max()) < 1 or not free.any():
            return []
        dim = x.shape[1]
        with np.errstate(invalid="ignore", divide="ignore"):
            tr = np.trace(C, axis1=1, axis2=2)
        ok = reg & np.isfinite(tr) & (tr > 0) & np.all(np.isfinite(x), axis=1)
        # per tag at once (grouped, no loop over tags): each fix's squared distance from
        # its tag's median point over its covariance's trace, and that ratio's median
        g = tags[ok]
        frame = pd.DataFrame(x[ok], columns=[f"c{i}" for i in range(dim)])
        med = frame.groupby(g).transform("median").to_numpy()
        tk = np.sum((x[ok] - med) ** 2, axis=1) / tr[ok]
        per = pd.DataFrame({"g": g, "t": tk}).groupby("g")["t"].agg(["median", "size"])
        per = per[per["size"] >= 2]
        if len(per) < 2:
            return []
        D = float(chi2_ppf(0.5, dim)) / dim / np.maximum(per["median"].to_numpy(), 1e-300)
        if np.any(D <= self.max_dilution):
            return []  # a tag that moves: positions enough (the tests before stand)
        static = len(per)
        # each static tag's distinct values: the anchors it hears
        heard = pd.DataFrame(ob[ok]).groupby(g).any()
        values = int(heard.loc[per.index].to_numpy().sum())
        names = PARAM_NAMES[self.kind]
        out: list[tuple[int, int]] = []
        for p in (1, 0):  # slopes first, then offsets
            n_free = int(free.sum()) - sum(1 for j, q in out if free[j, q])
            red = values - dim * static - n_free
            if red >= OWN_REDUNDANCY:
                break
            why = (f"{STATIC_TAGS_REASON}: {static} tags each standing at one point give "
                   f"{values} distinct values for {dim * static} position unknowns and "
                   f"{n_free} parameters (a redundancy of {red}; "
                   f"{names[1] + 's' if p == 1 else 'every parameter'} left out below "
                   f"{OWN_REDUNDANCY})")
            for j in np.flatnonzero(free[:, p]):
                left_out[(int(j), p)] = why
                out.append((int(j), p))
        return out

    def _static_share(
        self, a: Array, z: Array, obs: NDArray[np.bool_], x0: Array, off0: Array,
        slo0: Array, h2: Array, state: dict,
    ) -> tuple[float, int]:
        """The share of the spread of the log's fixes that a tag at rest would show:
        ``D = median_k |s_k - smed|^2 / median_k |x_k - xmed|^2`` and the number of fixes.

        ``x_k``: each epoch's fix with the prior calibration (:meth:`_fixes`, from the
        start fix ``x0``; the start fixes come from another estimator, and on a
        simulated static tag they spread 1.2-1.6 times the noise of these).  ``s_k``: the
        same estimator's fixes of a simulated tag at rest at ``xmed`` with the same
        anchors heard, observations ``offset + slope f(rho) + sigma_j e`` (a fixed seed:
        the test is reproducible).  ``sigma_j``: the robust per-anchor scale of the
        residuals of the ``x_k`` (:meth:`_vce` with the first adjustment's final robust
        weights); at rest it includes the prior calibration's inconsistency, so that a
        tag at rest shows ``D`` at or above 1."""
        dim = a.shape[1]
        rows = np.all(np.isfinite(x0), axis=1) & (obs.sum(axis=1) > dim)
        w = np.nan_to_num(state["w"], nan=0.0)
        ob = obs[rows]
        zz = np.where(ob, z[rows], 0.0)
        wr = np.where(ob, w[rows], 0.0)
        x = self._fixes(a, zz, ob, x0[rows], off0, slo0, h2, wr / state["sigma"] ** 2)
        ok = np.all(np.isfinite(x), axis=1)
        if ok.sum() < 2:
            return 0.0, int(ok.sum())
        x, ob, zz, wr = x[ok], ob[ok], zz[ok], wr[ok]
        lin = self._linearize(a, zz, ob, x, off0, slo0, h2)
        veq, R, _ = self._robust_fit(lin["Jx"], wr, lin["v"])
        kappa = _consistency(IGG3(self.igg3_k0, self.igg3_k1) if self.igg3_k1 > 0
                             else Huber(self.huber_c))
        sigma = self._vce(veq, R, wr, kappa)
        xmed = np.median(x, axis=0)
        rho = np.sqrt(np.sum((xmed - a) ** 2, axis=1) + h2)
        f, _ = self._f(np.maximum(rho, 1e-6))
        e = np.random.default_rng(0).standard_normal(ob.shape)
        zs = np.where(ob, off0 + slo0 * f + sigma * e, 0.0)
        xs_ = self._fixes(a, zs, ob, np.broadcast_to(xmed, x.shape).copy(), off0, slo0, h2,
                          np.where(ob, 1.0, 0.0) / sigma**2)
        oks = np.all(np.isfinite(xs_), axis=1)
        if oks.sum() < 2:
            return 0.0, int(ok.sum())
        rs = np.sum((xs_[oks] - np.median(xs_[oks], axis=0)) ** 2, axis=1)
        ro = np.sum((x - xmed) ** 2, axis=1)
        return float(np.median(rs)) / max(float(np.median(ro)), 1e-300), int(x.shape[0])

    def _fixes(
        self, a: Array, zz: Array, ob: NDArray[np.bool_], x: Array, off: Array, slo: Array,
        h2: Array, P: Array, steps: int = 5,
    ) -> Array:
        """Each epoch's weighted fix (weights ``P``) with the model ``off, slo``: Gauss-
        Newton from ``x``, each step at most half the anchors' extent; NaN where ``J^T P
        J`` is singular."""
        extent = max(float(np.max(np.linalg.norm(a - a.mean(axis=0), axis=1))), 1.0)
        x = x.copy()
        for _ in range(steps):
            lin = self._linearize(a, zz, ob, x, off, slo, h2)
            C, _ = _inv_batched(np.einsum("kjd,kj,kje->kde", lin["Jx"], P, lin["Jx"]))
            dx = np.einsum("kde,kjd,kj,kj->ke", C, lin["Jx"], P, lin["v"])
            step = np.linalg.norm(dx, axis=1, keepdims=True)
            x = x + dx * np.minimum(1.0, 0.5 * extent / np.maximum(step, 1e-300))
        lin = self._linearize(a, zz, ob, x, off, slo, h2)
        _, reg = _inv_batched(np.einsum("kjd,kj,kje->kde", lin["Jx"], P, lin["Jx"]))
        return np.where(reg[:, None], x, np.nan)

    @staticmethod
    def _leave_out(
        free: NDArray[np.bool_], left_out: dict[tuple[int, int], str], k: int, why: str
    ) -> None:
        j, p = divmod(k, 2)
        free[j, p] = False
        left_out.setdefault((j, p), why)

    def _se_test(
        self, state: dict, free: NDArray[np.bool_], ids: list[str],
        left_out: dict[tuple[int, int], str], obs: NDArray[np.bool_],
    ) -> list[tuple[int, int]]:
        """The parameters the standard-error test leaves out this round: the worst
        offender; on a site of at least :data:`SE_TEST_SEPARATE_FROM` anchors also each
        further offender, worst first, whose anchor shares no epoch in use with an anchor
        already taken.

        One at a time, the re-adjustment after each changes the others' standard errors
        and the anchors' sigmas (the bound): an offender that shares no epoch with those
        taken is coupled to them only through chains of shared positions and through the
        re-estimated weights.  On a large site, where the offenders are many, one at a
        time costs one re-adjustment each: a site of 196 anchors (14 x 14, 10 heard per
        epoch) with 200 epochs took 34 rounds and 78 s, and 400 anchors did not finish in
        15 minutes; taken together, 6 rounds and 19 s, with 47 parameters left out instead
        of 45 (two more biases; one of those anchors' scale then absorbs its bias, 2.2
        standard errors from the one-at-a-time value) and every other estimate within 0.29
        of its standard error of the one-at-a-time result.  Below, and on every shared
        data set (at most 12 anchors), the worst alone."""
        # the geometry's question (does the log determine it?): the model covariance
        cov, sigma, fsd = state["cov_model"], state["sigma"], state["fsd"]
        se = np.sqrt(np.maximum(np.diagonal(cov, axis1=1, axis2=2), 0.0))  # (m, 2)
        bound = self.se_ratio * sigma
        ratio = np.zeros_like(se)
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio[:, 0] = se[:, 0] / bound
            ratio[:, 1] = se[:, 1] * fsd / bound
        ratio = np.where(free, np.nan_to_num(ratio, nan=np.inf), 0.0)
        unit = "m" if self.kind == "range" else "dB"
        heard = obs & state["used"][:, None]  # the epochs in use
        blocked = np.zeros(ratio.shape[0], dtype=bool)
        out: list[tuple[int, int]] = []
        for flat in np.argsort(-ratio, axis=None, kind="stable"):  # worst first (argmax)
            j, p = (int(v) for v in np.unravel_index(int(flat), ratio.shape))
            if ratio[j, p] <= 1.0 or (out and ratio.shape[0] < SE_TEST_SEPARATE_FROM):
                break
            if blocked[j]:
                continue
            if p == 0:
                why = (f"standard error {se[j, 0]:.3g} {unit} exceeds {self.se_ratio:g} x "
                       f"sigma = {bound[j]:.3g} {unit}")
            else:
                why = (f"standard error {se[j, 1]:.3g} times the spread of the model term "
                       f"{fsd[j]:.3g} exceeds {self.se_ratio:g} x sigma = {bound[j]:.3g} "
                       f"{unit}")
            left_out.setdefault((j, p), why)
            out.append((j, p))
            blocked[j] = True  # and every anchor heard in an epoch with it
            blocked |= heard[heard[:, j]].any(axis=0)
        return out


#: Observations of an anchor (in epochs with a fix and redundancy) beyond its free
#: parameters needed to estimate them: a gross error among them is detected with one more
#: and identified with two (Baarda's local redundancy, seed 003); with fewer, the one range
#: of an anchor heard once became its "bias" (5.8 m, standard error 0.15 m, on a site of
#: 196 anchors with 200 epochs).
OWN_REDUNDANCY = 2

#: An anchor's ``sigma`` is left out when the degrees of freedom of its variance
#: component are at most this (:meth:`SelfCalibrator._sigma_undetermined`): the
#: :data:`OWN_REDUNDANCY` a truth-based calibration asks of an anchor's own sigma.
SIGMA_MIN_DOF = float(OWN_REDUNDANCY)


#: From this many anchors the standard-error test takes, with the worst offender, the
#: offenders that share no epoch with the anchors already taken
#: (:meth:`SelfCalibrator._se_test`); below, the worst alone in every round.
SE_TEST_SEPARATE_FROM = 32


def _consistency(wf: WeightFunction) -> float:
    """``E[w(u) u^2] / P(w(u) > 0)`` for ``u ~ N(0, 1)`` (trapezoid rule on |u| <= 10,
    step 1e-3: error far below 1e-6): divides a weighted sum of squared residuals into a
    consistent variance estimate."""
    u = np.linspace(-10.0, 10.0, 20001)
    phi = np.exp(-0.5 * u * u) / np.sqrt(2.0 * np.pi)
    w = np.nan_to_num(wf.weights(u), nan=0.0)
    return float(np.trapezoid(w * u * u * phi, u) / np.trapezoid((w > 0) * phi, u))


def _front(keep: NDArray[np.bool_]) -> NDArray[np.intp] | None:
    """Each epoch's anchors with ``keep`` first, in their order, then the others, cut to
    the most any epoch keeps: ``(N, nc)`` indices; None when that is every anchor."""
    if keep.ndim != 2 or keep.shape[0] == 0:
        return None
    nc = max(int(keep.sum(axis=1).max()), 1)
    if nc >= keep.shape[1]:
        return None
    return true_first(keep, nc)


@dataclass(frozen=True)
class _Residuals:
    """Each epoch's residual matrix ``R_k`` (:meth:`SelfCalibration._robust_fit`) on the
    anchors it observed (``front``, :func:`_front`; None: every anchor in order).

    The rows and columns of an anchor an epoch did not observe are the identity's (its
    design row is zero), so ``R_k`` is kept on the others: on a site of 100 anchors of
    which an epoch hears 10, ``(N, 10, 10)`` instead of ``(N, 100, 100)``, and the
    variance components' ``R diag(var) R^T`` 1 000x cheaper (200 epochs took 4 min)."""

    front: NDArray[np.intp] | None
    R: Array  # (N, nc, nc)
    m: int

    def take(self, a: Array) -> Array:
        """``a (N, m)`` or ``(m,)`` at each epoch's compact rows: ``(N, nc)``."""
        a = np.asarray(a, dtype=float)
        if self.front is None:
            return np.broadcast_to(a, (self.R.shape[0], self.m))
        if a.ndim == 1:
            return a[self.front]
        return np.take_along_axis(a, self.front, axis=1)

    def scatter(self, c: Array, fill: float | Array) -> Array:
        """``c (N, nc)`` at the anchors' columns of an ``(N, m)`` array holding ``fill``
        elsewhere."""
        if self.front is None:
            return c
        out = np.empty((c.shape[0], self.m))
        out[...] = fill
        np.put_along_axis(out, self.front, c, axis=1)
        return out

    def gather_sum(self, c: Array) -> Array:
        """``sum_k c_k`` of per-epoch ``(nc, nc)`` blocks at the anchors' rows and
        columns: an ``(m, m)`` matrix."""
        if self.front is None:
            return np.sum(c, axis=0)
        m = self.m
        idx = (self.front[:, :, None] * m + self.front[:, None, :]).ravel()
        return np.bincount(idx, weights=c.ravel(), minlength=m * m).reshape(m, m)

    def variances(self, var: Array) -> Array:
        """``sum_i R_k,ji^2 var_i`` for every epoch and anchor, ``(N, m)`` (``var_j``
        where the epoch did not observe ``j``: its row of ``R_k`` is the identity's)."""
        if self.front is None:
            return np.einsum("kji,i->kj", self.R * self.R, var)
        c = np.einsum("kji,ki->kj", self.R * self.R, self.take(var))
        return self.scatter(c, np.asarray(var, dtype=float)[None, :])


def _inv_batched(Nb: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Inverse of a batch of small SPD matrices, and which were regular (determinant above
    1e-10 times the trace's power: condition number below about 1e10); singular blocks
    give 0."""
    det = np.linalg.det(Nb)
    scale = np.einsum("kdd->k", Nb)
    ok = np.isfinite(det) & (np.abs(det) > 1e-10 * np.maximum(scale, 1e-300) ** Nb.shape[-1])
    out = np.zeros_like(Nb)
    if ok.any():
        out[ok] = np.linalg.inv(Nb[ok])
    return out, ok


#: From this many anchors :func:`_schur_sum` adds each epoch's products on the anchors it
#: touches, when those are at most half of them.
SCHUR_SPARSE_FROM = 32


def _schur_sum(Nxt: Array, M: Array, touched: NDArray[np.bool_]) -> Array:
    """``sum_k N_tk N_kk^-1 N_kt`` of the reduced normal matrix: ``Nxt, M (N, dim, 2m)``,
    ``touched (N, m)`` the anchors whose parameters epoch ``k`` involves (its columns
    ``2j, 2j + 1`` are zero elsewhere).

    On a site of many anchors of which each epoch hears a few, the products are formed on
    each epoch's own columns and added into place (``N (2h)^2`` terms, not ``N (2m)^2``:
    on 196 anchors with 10 heard the dense sum was half of ``calibrate --self``'s time);
    otherwise the dense sum, unchanged."""
    N, _, q = Nxt.shape
    m = q // 2
    h = int(touched.sum(axis=1).max()) if N else 0
    if m < SCHUR_SPARSE_FROM or 2 * h > m:
        return np.einsum("kdp,kdq->pq", Nxt, M)
    idx = true_first(touched, h)  # touched first
    keep = np.take_along_axis(touched, idx, axis=1)
    cols = np.stack([2 * idx, 2 * idx + 1], axis=2).reshape(N, 2 * h)
    live = np.repeat(keep, 2, axis=1)
    Nc = np.where(live[:, None, :], np.take_along_axis(Nxt, cols[:, None, :], axis=2), 0.0)
    Mc = np.where(live[:, None, :], np.take_along_axis(M, cols[:, None, :], axis=2), 0.0)
    prod = np.einsum("kdp,kdq->kpq", Nc, Mc)  # (N, 2h, 2h)
    lin = cols[:, :, None] * q + cols[:, None, :]
    return np.bincount(lin.ravel(), weights=prod.ravel(), minlength=q * q).reshape(q, q)


def _block_diag(blocks: Array) -> Array:
    m, p, _ = blocks.shape
    out = np.zeros((m * p, m * p))
    for j in range(m):
        out[j * p:(j + 1) * p, j * p:(j + 1) * p] = blocks[j]
    return out


__all__ = ["PARAM_NAMES", "SelfCalibration", "SelfCalibrator"]
