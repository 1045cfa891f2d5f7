"""A robust tight tracker for every tag: one filter per tag, all tags advanced together.

Per tag, the state ``x = [x, y, vx, vy(, ax, ay)]`` (``cv``, ``ca``) or ``[x, y]``
(``static``) is advanced epoch by epoch with the shared filter core
(:mod:`robustloc.filters.core`; compiled twin :mod:`robustloc.filters._compiled`):

1. **Start.**  The first state is a robust snapshot fix (:class:`~robustloc.estimators.
   ranging.Locator`, ``huber``) of the tag's first epoch with enough anchors; its
   covariance (floored) is the starting position covariance, the velocity starts at 0 with
   variance ``init_vel_var``.  Until then a tag's rows carry the fix's status
   (``insufficient_anchors``, ``ill_conditioned``, ...).  The start row (and a
   re-start's) is bounded as the epoch's protected fix bounds it, ``hpl = max(k sigma,
   |x - x_s| + HPL_s)``, and carries that fix's status where it says more than ``ok``
   (``low_redundancy``, ``fault_excluded``, ``fault_detected``, ...).
2. **Predict** with the motion model, ``x = F x``, ``P = F P F^T + Q`` (seed 002 eq. (13);
   ``Q`` of :mod:`robustloc.filters.motion`, ``q`` the white-acceleration variance).
3. **Tight update** with every heard anchor as one component (:mod:`robustloc.tracking.
   measurement`; RSSI in dB through the path-loss model, or calibrated ranges), an epoch
   with one or two anchors updating too.  The update is the core's robust one: equivalent
   weights ``D = p(e_i)`` of the standardized innovations (seed 002 eq. (11)), in the
   equivalent-variance form (``RobustUpdate(mode="variance")``): component ``i`` enters
   with the variance ``R_ii / D_ii`` (left out at ``D_ii = 0``) and the gain is the Kalman
   gain of that model, so ``P+ <= P-`` -- the update never widens the prediction's
   covariance, while seed 002's ``K D`` (eq. (12)), the gain of every heard link with the
   rejected columns cut, does when links are rejected (its true covariance, Joseph's form,
   grew by up to 5.5 m^2 in a UKF's position block on the simulated wifi-room walk);
   default Huber for ranges (measured, or RSSI converted by the path-loss
   model, the default domain as in ``locate``) and the asymmetric IGG of seed 002 eq. (14)
   for RSSI in dB (fades read low: ``e < 0`` is the long tail); ``R_ii = (s sigma_i)^2`` with
   ``sigma_i`` the anchor's a-priori sigma and ``s`` the tag's noise scale (step 6).
4. **Environment changes** (a door, a person: a link's level steps by several dB for
   seconds or minutes).  A two-sided CUSUM (Page 1954) runs on each link's standardized
   innovation ``e_i``: ``g+ = max(0, g+ + e_i - k)``, ``g- = max(0, g- - e_i - k)``; when
   one passes ``h`` the link is *held out* (no longer used: its weight is 0, the
   covariance is *not* inflated) while its offset ``b_i = mean(z_i - h_i(x-))`` is
   estimated against the prediction from the other links; after ``readmit_samples`` held
   epochs it is re-admitted with the new offset (and the CUSUM restarts).  A step that
   ends is a second step back, detected and handled the same way.  At most
   ``max(1, (M - 1) // 2)`` of the ``M`` links may be held at once: when more alarm, the
   tag moved (or the filter drifted), not the links -- every hold is released and the
   epoch counts towards divergence instead.
5. **Innovation tests (B-method, seed 003).**  The global test of the normalized
   innovation squared ``NIS`` over the ``m`` heard components uses the critical value
   ``chi2(1 - alpha(m); m)`` with ``alpha(m)`` tied to the w-test (``alpha0``, ``beta0``)
   by :func:`robustloc.integrity.bmethod.global_alpha`.  A rejection that one w-test
   exclusion explains (data snooping: the largest ``|w_i|`` beyond the w-test's critical
   value, and the test of the other ``m - 1`` components passing; :func:`one_fault_explains`)
   is one faulty link, which the robust update already down-weights: the epoch passes.
   An epoch whose test rejects otherwise, or
   whose robust weights rejected half of the components, is checked against the robust
   snapshot fix of the epoch (when its anchors allow one): it fails when the filtered
   position lies outside the ``1 - alpha0`` ellipse of the fix's covariance ``C_fix``.  After
   ``max_bad_epochs`` consecutive failing epochs the filter has diverged and re-starts
   from the robust fix of the current epoch (counted in ``reinit``).  A check is solved
   only when its answer can decide a re-start (``Tracker._count_bad``): the rows are
   those of checking every epoch, at a fraction of the snapshot fixes.  So does a filter
   whose position variance passed ``lost_pos_var`` when the epoch's fix is more certain
   (after the update; a prediction too wide to update is item 9).
6. **Measurement noise adapts within bounds.**  After each update the tag's noise scale
   follows the accepted innovations (Sage-Husa, Mehra 1972):
   ``s^2 <- (1 - l) s^2 + l mean_w((y_i^2 - (H P- H^T)_ii) / sigma_i^2)``, ``l =
   noise_forget``, clipped to ``[noise_scale_min^2, noise_scale_max^2]``.
7. **Coasting.**  An epoch without any usable observation is predicted only: status
   ``predicted``, its covariance grows with ``Q``.
8. **Protection level.**  ``hpl = max_i |G_pos,i| MDB_i + k sigma_major``: ``G`` the robust
   gain of the update (EKF: ``w_i P+ H_i^T / R_ii``; UKF: the linearized ``w_i P- H^T
   S^-1 e_i``, since its sigma-point ``P+`` does not satisfy the EKF identity),
   ``MDB_i = sqrt(lambda0) sqrt(S_ii)`` the bias of component ``i`` the w-test detects
   with power ``1 - beta0`` (seed 003 eq. (3); the slope form of RAIM/``spp``),
   ``sigma_major`` the square root of the largest eigenvalue of the
   position covariance and ``k = sqrt(chi2.isf(integrity_risk, 2))`` (2-D error beyond
   ``k`` sigma with probability ``integrity_risk`` for a Gaussian error).  Predicted rows
   get the noise term only.  Where the anchors a row's update kept are nearly collinear
   and the row's position reflected across their line (refined on the epoch's
   observations) passes the epoch's global test, ``hpl = max(hpl, |x' - x| + hpl)``: the
   mirror is as consistent as the track (``Tracker._cover_mirror``).  A usable row whose
   bound exceeds :data:`SNAPSHOT_BOUND_RATIO` times its noise term (after a gap, where
   ``(H P- H^T)_ii`` and with it the MDB grow without bound) also takes the epoch's own
   protected fix's bound ``|x - x_s| + HPL_s`` where smaller
   (``Tracker._snapshot_bound``).  A ``fault_detected`` row's bound (widened by
   ``sqrt(NIS / dof)``) stands for the tag's next rows until passing epochs after it
   have used :data:`SUSPICION_CONFIRM` observations: an update of one range cannot show
   the state wrong across that range (``Tracker._carry_suspicion``).
9. **A lost filter starts again.**  A prediction can be too wide to update: over a long
   gap (a tag's clock jumping ahead by hours) ``P-`` grows as ``q dt^4 / 4`` (``cv``), and
   once its position variance ``V = var_x + var_y`` reaches ``r_min / sqrt(eps)`` (``r_min``
   the smallest variance ``R_ii`` of the epoch's components, ``eps`` that of float64) the
   innovation covariance ``S = H P- H^T + R`` carries ``R`` to fewer than half of its
   digits (``(H P- H^T)_ii <= V``, rounded to ``eps V``): ``S`` turns singular or
   indefinite as ``eps V`` nears ``r_min``, and the update fails or returns a negative
   variance before the rule of item 5 could see it.  So the rule also runs *before* the
   update: a prediction with ``V > lost_pos_var`` and ``sqrt(eps) V >= r_min`` is
   meaningless -- the filter is dropped and the tag starts again as in item 1, from the
   epoch's robust fix (counted in ``reinit`` when dropped).  With the defaults (``cv``,
   ``q = 1``, ranges of 0.3 m) that is a gap beyond 59 s (``V = dt^4 / 2``; a 1.7 km
   standard deviation).  Without a usable fix the row carries the fix's status and the
   tag starts at its next epoch that gives one (with ``init_window_s``).  (Measured
   on the 44 199 filtered epochs of the report's section ``s60_tracks``: ``V <= 57 m^2``,
   ``eps V / r_min <= 4e-13``, four decades below ``sqrt(eps) = 1.5e-8``: none is
   dropped, every row is as before.)  A filter whose update fails numerically all the
   same (a singular system, a non-finite state or covariance, a negative variance, a
   heard component whose innovation variance ``S_ii`` is not positive) is dropped alike;
   the other tags of the round are advanced as if it were not there.

10. **A tag's range offset** (``range_offset``, ranges only).  Every range a tag measures
   can carry the same offset ``b``: a UWB tag's uncalibrated antenna delay, a phone's WiFi
   RTT offset.  ``b`` is then the state's last component, ``h_i(x) = d_i(p) + b``
   (``dh_i/db = 1``), a random walk of ``range_offset_q`` m^2/s started at 0 with the
   standard deviation ``range_offset_sd`` (the clock-bias state of a GNSS filter; Brown &
   Hwang 2012, sec. 9.2).  In one epoch ``b`` is nearly confounded with the position (a
   tag amid its anchors reads every range long and stays put); as the tag moves the
   geometry changes and the filter separates them.  The robust fixes of the checks and
   re-starts use the ranges with the current ``b`` removed; a re-start keeps ``b`` and its
   variance.  Measured (report section ``s60_tracks``): uwb-labyrinth, whose ranges read
   0.07-0.15 m long at every anchor, 0.215 -> 0.144 m RMS (``b`` -> 0.085 m; after
   ``calibrate --self`` it stays near 0); uwb-dwm1001 LOS 0.77 -> 0.91 m, whose range
   errors differ in sign by anchor.  An option, not the default.

11. **The links' offsets** (``link_offsets``).  Each link of a tag can read its own
   constant offset ``b_i``: an anchor whose calibration (``A`` of the path-loss model, a
   range bias) does not hold where the tag walks, a receiver's orientation.  ``b_i``
   (one state per anchor, in anchor order after the kinematic states; random walks of
   ``link_offset_q`` unit^2/s started at 0 with ``link_offset_sd``) is added to the link's
   measurement: ``h_i = d_i(p) + b_i`` for ranges, ``A_i - 10 n_i lg d_i + b_i`` for RSSI
   in dB, and, for RSSI turned into ranges (``domain="range"``: the measured range of
   ``z - b_i`` is ``d_i 10^(-b_i / (10 n_i))``), ``h_i = d_i 10^(-b_i / (10 n_i))``,
   ``dh_i/db_i = -h_i ln10 / (10 n_i)``.  As the tag moves, the geometry separates the
   offsets from the position (in one epoch they are confounded).  The checks, re-starts
   and the mirror test use the measurements with the current offsets removed; a re-start
   keeps the offsets and their covariance.  This is the state-space form of item 2's
   held-link offsets: those follow a step, these a standing offset from the first epoch.
   Measured (report section ``s60_tracks``, default priors): ble-tetam, whose RSSI
   differs from the survey's calibration by -2.5 to +1.5 dB per receiver on the walks
   (against the truth; the filter's offsets correlate 0.93 with those), RMS 2.20 -> 2.03 m
   (0.77x -> 0.71x the default ``locate``'s); uwb-dwm1001 LOS 0.77 -> 0.55 m, NLOS 0.74
   -> 0.61 m; uwb-labyrinth 0.215 -> 0.172 m (after ``calibrate --self`` 0.139 -> 0.148
   m: the calibration had removed the offsets).  Where there are no offsets to find it
   costs accuracy: the simulated wifi-room walk (4 access points, an exact path-loss
   model) 0.93x -> 1.25x the snapshot fixes' RMS.  Off in this filter unless told (``4 +
   M`` states cost time: ``benchmarks/bench_track.py``, 8 anchors, EKF 38 k tag-epochs per
   second compiled, 24 k on NumPy, against 144 k without them); ``robustloc track`` and
   :func:`robustloc.track`, which read the log first, let it choose by default
   (``link_offsets="auto"``, :mod:`robustloc.tracking.select`).

12. **A position the ranges do not fix.**  One range says how far the tag is from its
   anchor, not where on that circle it is; the EKF's covariance, linearized at a point
   that slides along the circle, shrinks in every direction all the same.  A row counts
   as *observed* when its tag's recent updates (the last ``observed_window_s`` seconds,
   or its last ``M`` updates within ten such windows, ``M`` the anchors) kept two or
   more distinct anchors at least 10 degrees apart as seen from it (two: the reflection
   across their line is item 8's, which takes the same recent anchors for a row that
   keeps one or two; round-robin UWB ranges, one anchor per epoch, stay observed); it
   records its time and covariance.  Every other usable row's ``hpl`` also covers the
   motion since: ``k sigma_major`` of the last observed covariance predicted to the row
   (``F P F^T + Q``, without the updates that could not fix the position), or, where
   smaller, the ranges the row kept, ``min_i |x - a_i| + d_i + k s sigma_i`` (the tag is
   within its range of the anchor).  Measured (the tracker review's case: five anchors
   on a 20 m circle, ranges of 0.3 m, one anchor heard for 60 s of a walk, six seeds):
   29 % of the rows beyond their ``hpl`` (`ok` rows up to 51 m off, ``hpl`` a few
   metres) -> 0; median ``hpl`` 39-47 m there, errors 12-25 m.  Its review (2026-12-06):
   two anchors heard in turn (11 % beyond, rows 28 m off), two anchors 0.5 m apart (9.5
   %), a corridor of nearly collinear anchors ranged in turn (5.4 %) -> 0; reports of
   one range just over a second apart keep the bounds of the rule switched off.  On
   every shared real data set no row changes.

Engines: ``compiled`` (default) runs the whole round of the ``cv``/``ca`` models in the
range domain (ranges, or RSSI converted to ranges), with or without the offset states
(items 10 and 11), in one fused numba kernel (:mod:`robustloc.tracking._compiled`: items 2-8 in a
loop over the tags, its update the fusion filter's compiled kernel on the ranges); only
the robust snapshot fixes of suspicious epochs and the re-starts (items 5 and 9) stay in
NumPy, for the tags that need them.
``numpy`` (and RSSI in dB and ``static``) runs the batched NumPy core,
the reference implementation.  The two agree to rounding, 1e-9 m (tested, also on random
workloads with holds, outliers and re-starts), as long as no decision falls within rounding
of its threshold: a w-test or global test at its critical value, the mirror check, a
re-start.  Where one does, the kernels take different branches and their rows part from
there on, as two runs of any filter would on inputs that differ in the last digit (the
track review, 2026-12-06: the wifi-rtt corridor after ``calibrate --self`` with
``--filter ukf --sigma 0.1``, a first difference of 1.3e-9 m at row 281, 42 of 6 840 rows
with another status later; with the defaults, positions within 3e-8 m and ``hpl`` within
1.3e-4 m, the largest where a near-collinear mirror test is close to its limit).

Batching: :meth:`Tracker.step` takes an :class:`~robustloc.io.tables.Epochs` block and
advances each tag through its epochs in time order; the ``j``-th epochs of all tags are
one vectorized round.  Every row depends only on its tag's own history, so feeding a file
in one call or one epoch at a time gives the same rows (tested).
"""

from __future__ import annotations

import functools
import math
import typing
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from robustloc import status as st
from robustloc._arrays import real_array
from robustloc._stats import chi2_isf
from robustloc.filters.core import (
    RobustUpdate,
    SigmaPoints,
    predict_linear,
    update_ekf,
    update_ukf,
)
from robustloc.filters.motion import (
    ConstantAcceleration,
    ConstantVelocity,
    RandomWalkAugmented,
    _Kinematic,
)
from robustloc.integrity.bmethod import global_critical, lambda0
from robustloc.io.tables import anchor_sigma, validate_anchors
from robustloc.robust.weights import get_weight
from robustloc.tracking.measurement import LN10, LinkModel

#: A usable row whose ``hpl`` exceeds this many times its noise term ``k sigma_major`` is
#: also bounded by the epoch's own protected fix (:meth:`Tracker._snapshot_bound`).
SNAPSHOT_BOUND_RATIO = 10.0
#: ... when its prediction widened the position variance of the previous update at least
#: this many times (a gap).
SNAPSHOT_PREDICTION_RATIO = 25.0
#: An anchor kept among a tag's last ``M`` updates counts as recent (``Tracker.
#: _recent_kept``) if kept within this many ``observed_window_s`` too.
OBSERVED_COUNT_SPAN = 10.0
#: Smallest eigenvalue of ``sum_i u_i u_i^T`` over a row's recent anchors' unit vectors
#: for its position to count as observed (``Tracker._spans``): ``1 - cos 10 deg``, two
#: anchors 10 degrees apart as seen from the tag.
OBSERVED_MIN_EIGENVALUE = 1.0 - math.cos(math.radians(10.0))
#: Observations that passing epochs must use after a ``fault_detected`` row before its
#: bound stops standing for the tag's rows (:meth:`Tracker._carry_suspicion`): a 2-D
#: position and one more, the redundancy that can show the filter right.
SUSPICION_CONFIRM = 3

Array = NDArray[np.float64]
#: Default a-priori sd of a link's offset (``link_offsets``) by measurement: metres for
#: ranges, dB for RSSI.  RSSI: a receiver's residual calibration offset of about 1 dB
#: (ble-tetam against the truth: -2.5 to +1.5 dB by receiver, sd 1.4 dB); the filter's
#: RMS there is flat from 0.5 to 1.5 dB (report ``s60_tracks``, which prints the sweep).
#: Ranges: 0.1 m, a UWB anchor's typical antenna-delay spread (uwb-labyrinth: 0.07-0.15
#: m by anchor).
LINK_OFFSET_SD = {"range": 0.1, "rssi": 1.0}

MODELS = ("cv", "ca", "static")
FILTERS = ("ekf", "ukf")
#: Method name written in the ``method`` column (``robustloc evaluate`` groups by it).
METHOD_PREFIX = "track"
#: ``sqrt(eps)`` of float64, ``2^-26`` (:data:`robustloc.tracking._compiled.SQRT_EPS`, not
#: imported here: that module needs numba).
_SQRT_EPS = float(np.sqrt(np.finfo(np.float64).eps))


#: Range of the settings the tracker squares (the noise scale's bounds, the offsets'
#: a-priori standard deviations): their squares stay normal floats.
_SQUARED_MIN, _SQUARED_MAX = 1e-100, 1e100


@functools.cache
def _type_hints(cls: type) -> dict[str, Any]:
    """``cls``'s field types, resolved once (the annotations are strings here)."""
    return typing.get_type_hints(cls)


@dataclass(frozen=True)
class TrackerSettings:
    """Every setting of the tracker (defaults in the parameter list).

    Parameters
    ----------
    model : ``cv`` (constant velocity), ``ca`` (constant acceleration) or ``static``
        (position random walk).
    filter : ``ekf`` or ``ukf`` (Merwe sigma points ``alpha = 1, kappa = 0``, seed 001).
    q : process noise: white-acceleration variance ((m/s^2)^2) for ``cv``, jerk variance
        for ``ca``, position-step variance per s^2 for ``static`` (discrete noise model of
        :mod:`robustloc.filters.motion`).
    weight : robust weight of the update (``huber, hampel, igg, igg3, asymmetric-igg, ls``);
        ``None``: ``asymmetric-igg`` in the dB domain (fades: ``e < 0`` is the long
        tail), ``huber`` for ranges (measured or converted from RSSI).
    sigma : a-priori standard deviation of one observation (m or dB); ``None``: the
        anchors' ``sigma`` column, else 3 dB for RSSI and 0.3 m for ranges.
    engine : ``compiled`` or ``numpy``.
    domain : RSSI only: update with ranges converted by the path-loss model (``range``,
        default; ``sigma_d = d ln10 sigma_dB / (10 n)``) or in dB through the model
        (``rssi``).  Measured on the seed-002 walk: see the report section ``s60_tracks``.
    noise_scale_min, noise_scale_max, noise_forget : bounds and forgetting factor of the
        adaptive noise scale ``s`` (item 6 of the module docstring).
    cusum_k, cusum_h : CUSUM drift and threshold (standardized innovations); ``cusum_h =
        None`` (default) disables the step detector: measured on the seed-002 walk (8 dB
        steps of 10 s) and on uwb-dwm1001, holding links out costs more accuracy than the
        robust weights lose on the steps (report section ``s60_tracks``); ``10`` is a
        sensible threshold when steps are long and the anchors many.
    readmit_samples : held epochs before a link is re-admitted with its new offset.
    alpha0, beta0 : w-test significance and missed-detection probability (B-method).
    max_bad_epochs : consecutive failing epochs that count as divergence (re-start).
    integrity_risk : probability that the position error exceeds the noise part of
        ``hpl`` (``k = sqrt(chi2.isf(integrity_risk, 2))``).
    init_pos_var_min, init_vel_var, init_acc_var : floor of the starting position variance
        (m^2) and the starting velocity ((m/s)^2) and acceleration ((m/s^2)^2) variances.
    tag_height : known tag height (m): 2-D slant ranges use ``z_anchor - tag_height``.
    lost_pos_var : when the position variance ``var_x + var_y`` (m^2) exceeds this, the
        epoch's robust fix is computed and, if it is more certain, the filter re-starts
        from it at once (a filter that lost its track: long coasting, or a UKF whose sigma
        points spread beyond the measurement's linear range).  A prediction beyond it and
        too wide to update in float64 is dropped before its update (item 9 of the module
        docstring).
    init_window_s : before its first fix, a tag's last observation of each anchor within
        this many seconds joins the current epoch's (asynchronous UWB ranges arrive one
        anchor at a time: the starting fix needs three).
    range_offset : ranges only: estimate the tag's common range offset ``b`` (m, added to
        every range it measures: a UWB tag's uncalibrated antenna delay, a phone's WiFi
        RTT offset) as one more state (item 10 of the module docstring).
    range_offset_sd : a-priori standard deviation of that offset (m) at a tag's start.
    range_offset_q : its random-walk variance growth (m^2/s): 0 for a constant offset,
        at most 1e6 (:data:`robustloc.options.PROCESS_NOISE_MAX`, as ``q``).
    link_offsets : estimate an offset of each link (anchor) of each tag as one more state
        per anchor (item 11 of the module docstring): metres added to its ranges, or dB
        added to its RSSI (what the anchors file's calibration misses where the tag is).
        Not with ``range_offset`` (their mean is the common offset).
    link_offset_sd : a-priori standard deviation of each link's offset at a tag's start, in
        the measurement's unit (m or dB); None: 0.1 m for ranges, 1 dB for RSSI.
    link_offset_q : its random-walk variance growth (unit^2/s): 0 for constant
        offsets, at most 1e6.
    """

    model: str = "cv"
    filter: str = "ekf"
    q: float = 1.0
    weight: str | None = None
    sigma: float | None = None
    engine: str = "compiled"
    domain: str = "range"
    noise_scale_min: float = 1.0
    noise_scale_max: float = 4.0
    noise_forget: float = 0.02
    cusum_k: float = 1.0
    cusum_h: float | None = None
    readmit_samples: int = 6
    alpha0: float = 0.001
    beta0: float = 0.10
    max_bad_epochs: int = 5
    integrity_risk: float = 1e-3
    init_pos_var_min: float = 0.25
    init_vel_var: float = 1.0
    init_acc_var: float = 0.25
    tag_height: float | None = None
    init_window_s: float = 1.0
    observed_window_s: float = 1.0
    lost_pos_var: float = 25.0
    range_offset: bool = False
    range_offset_sd: float = 0.5
    range_offset_q: float = 1e-4
    link_offsets: bool = False
    link_offset_sd: float | None = None
    link_offset_q: float = 0.0

    def __post_init__(self) -> None:
        def bad(msg: str) -> None:
            raise ValueError(msg)

        # numbers are real numbers, counts whole ones (the API review: q = 1+1j ran on its
        # real part, max_bad_epochs = NaN turned the divergence re-starts off, 2.5 and
        # readmit_samples = inf passed "< 1")
        hints = _type_hints(type(self))
        for f in fields(self):
            v = getattr(self, f.name)
            kind = hints[f.name]
            if kind in (float, float | None) and v is not None and (
                    isinstance(v, bool | np.bool_)
                    or not isinstance(v, int | float | np.integer | np.floating)):
                raise TypeError(f"{f.name} must be a real number, got {v!r}")
            if kind is int and (isinstance(v, bool | np.bool_)
                                    or not isinstance(v, int | np.integer)):
                raise TypeError(f"{f.name} must be a whole number, got {v!r}")
        if self.model not in MODELS:
            bad(f"model must be one of {', '.join(MODELS)}, got {self.model!r}")
        if self.filter not in FILTERS:
            bad(f"filter must be 'ekf' or 'ukf', got {self.filter!r}")
        if self.domain not in ("range", "rssi"):
            bad(f"domain must be 'range' or 'rssi', got {self.domain!r}")
        if self.engine not in ("compiled", "numpy"):
            bad(f"engine must be 'compiled' or 'numpy', got {self.engine!r}")
        for name in ("q", "init_window_s", "observed_window_s", "lost_pos_var",
                     "noise_forget", "cusum_k", "init_vel_var", "init_acc_var",
                     "init_pos_var_min", "range_offset_q", "link_offset_q"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                bad(f"{name} must be finite and >= 0, got {v}")
        from robustloc.options import PROCESS_NOISE_MAX

        for name in ("q", "range_offset_q", "link_offset_q"):
            # (1e308 overflowed the covariance: rows 'ok' without hpl, NumPy overflow
            # warnings on stderr -- the input review; 1e6 is 1000 units per second)
            v = getattr(self, name)
            if v > PROCESS_NOISE_MAX:
                bad(f"{name} must be at most {PROCESS_NOISE_MAX:g}, got {v}")
        if self.cusum_h is not None and not (math.isfinite(self.cusum_h) and self.cusum_h > 0):
            bad(f"cusum_h must be positive and finite (or None), got {self.cusum_h}")
        if not 0 < self.noise_scale_min <= self.noise_scale_max < math.inf:
            bad("need 0 < noise_scale_min <= noise_scale_max < inf")
        for name in ("noise_scale_min", "noise_scale_max", "range_offset_sd",
                     "link_offset_sd"):
            # squared as Python floats: 1e200 raised OverflowError, 1e-170 divided by 0
            v = getattr(self, name)
            if v is not None and not _SQUARED_MIN <= v <= _SQUARED_MAX:
                bad(f"{name} must be in [{_SQUARED_MIN:g}, {_SQUARED_MAX:g}], got {v}")
        if not 0 <= self.noise_forget <= 1:
            bad(f"noise_forget must be in [0, 1], got {self.noise_forget}")
        if self.tag_height is not None and not abs(self.tag_height) <= 1e4:
            # as robustloc.options.tag_height_m (squared: 1e200 made every row
            # ill_conditioned)
            bad(f"tag_height must be in [-10000, 10000] m, got {self.tag_height}")
        if self.sigma is not None and not (math.isfinite(self.sigma) and self.sigma > 0):
            bad(f"sigma must be positive and finite, got {self.sigma}")
        if not (math.isfinite(self.range_offset_sd) and self.range_offset_sd > 0):
            bad(f"range_offset_sd must be positive and finite, got {self.range_offset_sd}")
        if self.link_offset_sd is not None and not (math.isfinite(self.link_offset_sd)
                                                    and self.link_offset_sd > 0):
            bad(f"link_offset_sd must be positive and finite, got {self.link_offset_sd}")
        if self.range_offset and self.link_offsets:
            bad("range_offset and link_offsets exclude each other: the links' offsets "
                "include the common one (their mean)")
        for name in ("alpha0", "beta0", "integrity_risk"):
            v = getattr(self, name)
            if not 0 < v < 1:
                bad(f"{name} must be strictly between 0 and 1, got {v}")
        if self.readmit_samples < 1 or self.max_bad_epochs < 1:
            bad("readmit_samples and max_bad_epochs must be >= 1")
        if self.weight is not None:
            get_weight(self.weight)  # validates the name

    def motion(self, n_links: int = 0) -> _Kinematic | RandomWalkAugmented:
        """The motion model of the state (with the random walks of the range offset, or of
        the ``n_links`` links' offsets, appended)."""
        base: _Kinematic
        if self.model == "cv":
            base = ConstantVelocity(q=self.q)
        elif self.model == "ca":
            base = ConstantAcceleration(q=self.q)
        else:
            base = _Kinematic(q=self.q, order=0, name="static")
        if self.range_offset:
            return RandomWalkAugmented(base, q_extra=self.range_offset_q)
        if self.link_offsets and n_links > 0:
            return RandomWalkAugmented(base, q_extra=self.link_offset_q, extra=n_links)
        return base


def _state_size(model: str) -> int:
    return {"cv": 4, "ca": 6, "static": 2}[model]


class Tracker:
    """Stateful robust tight tracker of many tags (see the module docstring).

    Parameters
    ----------
    anchors : DataFrame
        Anchors frame (``anchor, x, y[, z]`` + path-loss columns for RSSI, ``bias, scale``
        for ranges, optional ``sigma``), as from :func:`robustloc.io.read_anchors`.
    model, filter : motion model and filter (see :class:`TrackerSettings`).
    record : keep every step's filtered and predicted moments for :meth:`smoothed`.
    **options : any other field of :class:`TrackerSettings`.

    Examples
    --------
    >>> trk = Tracker(anchors, model="cv", filter="ekf")      # doctest: +SKIP
    >>> rows = trk.step(epochs)                                # doctest: +SKIP
    >>> saved = trk.state_dict()                               # doctest: +SKIP
    >>> trk2 = Tracker(anchors); trk2.load_state_dict(saved)   # doctest: +SKIP
    """

    def __init__(self, anchors: pd.DataFrame, *, model: str = "cv", filter: str = "ekf",
                 record: bool = False, **options: Any) -> None:
        known = {f.name for f in fields(TrackerSettings)}
        unknown = set(options) - known
        if unknown:
            raise TypeError(f"unknown tracker option(s): {', '.join(sorted(unknown))}")
        self.settings = TrackerSettings(model=model, filter=filter, **options)
        # the anchors checked as read_anchors checks them (a frame without 'y' failed at
        # the first step with a KeyError, None with an AttributeError, duplicate ids were
        # taken: the API review); a frame read by read_anchors passes unchanged
        if not isinstance(anchors, pd.DataFrame):
            raise TypeError("anchors must be a DataFrame (robustloc.read_anchors), got "
                            f"{type(anchors).__name__}")
        anchors = validate_anchors(anchors, anchors.attrs.get("path"))
        if self.settings.sigma is None:
            anchor_sigma(anchors)  # a partly empty column: refused now, with its line
        self.anchors = anchors.reset_index(drop=True)
        # the frame as read (same rows, same order): its index is the file's lines, which
        # the path-loss and range-calibration errors name (the reset one lost them)
        self._anchors_read = anchors
        self.anchor_ids = tuple(str(a) for a in self.anchors["anchor"])
        from robustloc.estimators.ranging import _sane_anchors

        dims = [c for c in ("x", "y", "z") if c in self.anchors.columns]
        self._sane = _sane_anchors(self.anchors[dims].to_numpy(dtype=float))
        self.record = record
        M = len(self.anchor_ids)
        #: kinematic states, then the range offset (``range_offset``) as the last one, or
        #: the links' offsets in anchor order (``link_offsets``)
        self.n_motion = _state_size(model)
        self.n = (self.n_motion + int(self.settings.range_offset)
                  + (M if self.settings.link_offsets else 0))
        self._motion = self.settings.motion(M)
        self._kind: str | None = None
        self._link: LinkModel | None = None
        self._slot: dict[str, int] = {}
        self._alloc(0, M)
        self._history: list[dict[str, Any]] = []
        self._s2_before = np.ones(0)  # the noise scales of the round being filtered
        #: rows output by the recorded steps so far: the history numbers rows across
        #: steps (each step's from 0 overwrote the earlier steps' in smoothed(): the API
        #: review)
        self._rows_recorded = 0
        # deferred snapshot checks (``_count_bad``): a log of checked epochs, appended
        # per round (slot, generation, fails before, passing resets, x, z)
        self._checks: list[tuple[NDArray[Any], ...]] = []
        self._kernel: Any = None
        self._locator = None
        self._lam0 = lambda0(self.settings.alpha0, self.settings.beta0)
        self._k_ir = math.sqrt(chi2_isf(self.settings.integrity_risk, 2))
        self._chi2_fix = float(chi2_isf(self.settings.alpha0, 2))  # 2-D fix ellipse
        self._w2_crit = float(chi2_isf(self.settings.alpha0, 1))  # w-test, squared
        self._gcrit = global_critical(np.arange(0, M + 1), None, self.settings.alpha0,
                                      self.settings.beta0)

    # ------------------------------------------------------------------ state arrays
    def _alloc(self, S: int, M: int) -> None:
        n = self.n
        self._x = np.zeros((S, n))
        self._P = np.zeros((S, n, n))
        self._t = np.zeros(S)
        self._init = np.zeros(S, dtype=bool)
        self._bias = np.zeros((S, M))
        self._held = np.zeros((S, M), dtype=bool)
        self._gp = np.zeros((S, M))
        self._gm = np.zeros((S, M))
        self._hsum = np.zeros((S, M))
        self._hn = np.zeros((S, M), dtype=np.int64)
        self._scale2 = np.ones(S)
        self._bad = np.zeros(S, dtype=np.int64)
        self._reinit = np.zeros(S, dtype=np.int64)
        self._lastz = np.full((S, M), np.nan)
        self._lastt = np.full((S, M), np.nan)
        self._susp = np.zeros(S)
        self._susp_n = np.zeros(S, dtype=np.int64)
        self._mline = np.full((S, 4), np.nan)
        self._tkeep = np.full((S, M), np.nan)
        self._ikeep = np.full((S, M), np.nan)
        self._nupd = np.zeros(S)
        self._tdet = np.full(S, np.nan)
        self._Pdet = np.zeros((S, n, n))
        self._alloc_pending(S)

    def _alloc_pending(self, S: int) -> None:
        """Per-slot state of the deferred checks (:meth:`_count_bad`; not part of
        :meth:`state_dict`, which settles them) for ``S`` slots, kept for the slots that
        exist: ``on`` (checks pending), the lower bound ``lo`` of the divergence counter
        (``_bad`` holds the upper one), the exact counter ``b0`` before the first pending
        check, the known failures ``after`` the last one, and a generation that voids the
        slot's logged checks when they stop mattering."""
        have = 0 if S == 0 or not hasattr(self, "_p_on") else self._p_on.shape[0]
        if have == 0:
            self._checks = []
        for name, dtype in (("_p_on", bool), ("_p_lo", np.int64), ("_p_b0", np.int64),
                            ("_p_after", np.int64), ("_p_gen", np.int64)):
            head = getattr(self, name)[:have] if have else np.zeros(0, dtype)
            setattr(self, name, np.concatenate([head, np.zeros(S - have, dtype)]))

    _ARRAYS = ("_x", "_P", "_t", "_init", "_bias", "_held", "_gp", "_gm", "_hsum", "_hn",
               "_scale2", "_bad", "_reinit", "_lastz", "_lastt", "_susp", "_susp_n",
               "_mline", "_tkeep", "_ikeep", "_nupd", "_tdet", "_Pdet")
    #: Arrays a state saved before they existed lacks: loaded as these values (``None``:
    #: NaN throughout; a tag without an observed row counts as observed from its next one).
    _ARRAY_DEFAULTS = {"_susp": 0.0, "_susp_n": 0, "_mline": None, "_tkeep": None,
                       "_ikeep": None, "_nupd": 0.0, "_tdet": None, "_Pdet": None}
    #: Arrays whose new slots start as NaN (not 0): no observation, no line, no time.
    _NAN_PADDED = ("_lastz", "_lastt", "_mline", "_tkeep", "_ikeep", "_tdet")

    def _slots(self, tags: NDArray[np.object_]) -> NDArray[np.int64]:
        """Each tag's slot in the state arrays (new tags get new slots)."""
        try:  # the usual case: every tag known
            return np.fromiter(map(self._slot.__getitem__, tags), dtype=np.int64,
                               count=len(tags))
        except KeyError:
            pass
        new = [t for t in dict.fromkeys(tags) if t not in self._slot]
        if new:
            # two tags that read alike (1 and "1") are one tag in the saved state, whose
            # keys are text: state_dict() kept one of them (the API review)
            seen = {str(t): t for t in self._slot}
            for t in new:
                other = seen.setdefault(str(t), t)
                if other is not t and other != t:
                    raise ValueError(f"tags {other!r} and {t!r} read alike: give tags as "
                                     "text (robustloc.read_measurements does)")
            S0 = len(self._slot)
            for i, t in enumerate(new):
                self._slot[t] = S0 + i
            grow = len(new)
            for name in self._ARRAYS:
                a = getattr(self, name)
                pad = np.zeros((grow, *a.shape[1:]), dtype=a.dtype)
                if name == "_scale2":
                    pad[:] = 1.0
                elif name in self._NAN_PADDED:
                    pad[:] = np.nan
                setattr(self, name, np.concatenate([a, pad]))
            self._alloc_pending(len(self._slot))
        return np.fromiter((self._slot[t] for t in tags), dtype=np.int64, count=len(tags))

    @property
    def tags(self) -> list[str]:
        """Tags seen so far (and not forgotten)."""
        return list(self._slot)

    def forget(self, tags: Any) -> int:
        """Drop every state of ``tags`` (an iterable of tags, or one tag as a string): each
        given again is a new tag, started afresh
        from a fix (a long-running service forgets the tags that stopped reporting;
        ``robustloc serve --forget-after``).  Tags not held are ignored.

        The other tags' states are kept exactly: their snapshot checks still pending are
        solved first (as :meth:`state_dict` does; outputs are unaffected), then the state
        arrays lose the forgotten tags' rows.

        Returns
        -------
        int
            The number of tags forgotten.

        Raises
        ------
        ValueError
            A recording tracker (``record=True``) with a history (its history for
            :meth:`smoothed` holds the tags' state rows; after :meth:`forget_record` it
            can forget).
        """
        if self.record and (self._history or self._rows_recorded):
            raise ValueError("a recording tracker (record=True) cannot forget tags: its "
                             "history for smoothed() refers to their state rows "
                             "(forget_record() first)")
        if isinstance(tags, str):  # one tag (its characters were taken as tags: forget("t1")
            tags = [tags]           # dropped tags 't' and '1' and kept 't1', the API review)
        gone = [t for t in dict.fromkeys(tags) if t in self._slot]
        if not gone:
            return 0
        self._settle()  # every logged check void after it: the log can restart empty
        S = len(self._slot)
        keep = np.ones(S, dtype=bool)
        keep[np.fromiter((self._slot[t] for t in gone), dtype=np.int64, count=len(gone))] = False
        new = np.cumsum(keep) - 1
        self._slot = {t: int(new[k]) for t, k in self._slot.items() if keep[k]}
        for name in self._ARRAYS:
            setattr(self, name, getattr(self, name)[keep])
        for name in ("_p_on", "_p_lo", "_p_b0", "_p_after", "_p_gen"):
            setattr(self, name, np.zeros(0, getattr(self, name).dtype))
        self._alloc_pending(len(self._slot))
        return len(gone)

    def link_offsets(self) -> pd.DataFrame:
        """The links' offsets (``link_offsets``, item 11 of the module docstring) of every
        started tag at its last epoch: one row per tag and anchor, columns ``tag, anchor,
        offset, sd`` in the measurement's unit (dB of RSSI, m of ranges).

        Raises
        ------
        ValueError
            The tracker does not estimate the links' offsets.
        """
        if not self.settings.link_offsets:
            raise ValueError("this tracker does not estimate the links' offsets "
                             "(link_offsets=False)")
        nm, M = self.n_motion, len(self.anchor_ids)
        tags = [t for t, k in self._slot.items() if self._init[k]]
        sl = np.fromiter((self._slot[t] for t in tags), dtype=np.int64, count=len(tags))
        b = self._x[sl, nm:]
        var = np.diagonal(self._P[sl], axis1=1, axis2=2)[:, nm:]
        return pd.DataFrame({"tag": np.repeat(np.asarray(tags, dtype=object), M),
                             "anchor": np.tile(np.asarray(self.anchor_ids, dtype=object),
                                               len(tags)),
                             "offset": b.ravel(), "sd": np.sqrt(np.maximum(var, 0.0)).ravel()})

    # ------------------------------------------------------------------ model setup
    def _setup(self, kind: str) -> None:
        from robustloc.errors import InputError
        from robustloc.models.pathloss import log_distance_arrays

        s = self.settings
        a = self.anchors
        if s.range_offset and kind != "range":
            raise InputError("range_offset is for ranges: this log has RSSI (a device's "
                             "RSSI offset is the path-loss model's A: calibrate it)",
                             a.attrs.get("path"), 1)
        M = len(a)
        xy = a[["x", "y"]].to_numpy(dtype=float)
        dz2 = np.zeros(M)
        if s.tag_height is not None:
            if "z" not in a.columns:
                raise InputError("tag_height needs a z column in the anchors file",
                                 a.attrs.get("path"), 1)
            dz2 = (a["z"].to_numpy(dtype=float) - s.tag_height) ** 2
        if s.sigma is not None:
            sigma = np.full(M, s.sigma)
        elif (given := anchor_sigma(a)) is not None:
            sigma = given
        else:
            sigma = np.full(M, 3.0 if kind == "rssi" else 0.3)
        A = nn = None
        if kind == "rssi":
            A, nn = log_distance_arrays(self._anchors_read)
            A, nn = np.asarray(A, float), np.asarray(nn, float)
        self._kind = kind
        if kind == "range":
            from robustloc.models.calibration import range_calibration

            self._range_cal = range_calibration(self._anchors_read)
        self._link = LinkModel(xy, "range" if kind == "range" or s.domain == "range"
                               else "rssi", dz2, sigma, A, nn)
        #: a-priori sd of the links' offsets (item 11), in the measurement's unit
        self._link_offset_sd = (s.link_offset_sd if s.link_offset_sd is not None
                                else LINK_OFFSET_SD[kind])
        wname = s.weight or ("asymmetric-igg" if self._link.kind == "rssi" else "huber")
        self._weight = get_weight(wname)
        # the equivalent-variance gain: never wider than the prediction (item 3)
        self._robust = RobustUpdate(weight=self._weight, mode="variance")
        self._weight_name = wname
        from robustloc.estimators.ranging import Locator

        # per-epoch scale: a start fix must not depend on which epochs share its batch
        self._locator = Locator("huber", sigma=tuple(sigma), robust_scale="mad")
        # the epoch's own protected fix, which bounds a row whose filter bound exploded
        # (:meth:`_snapshot_bound`): ``locate``'s default with the a-priori sigma
        self._bound_locator = Locator("auto", sigma=tuple(sigma), robust_scale="apriori")
        self._kernel = None
        if s.engine == "compiled" and self._link.kind == "range" and s.model in ("cv", "ca"):
            from robustloc.filters import _compiled as fc
            from robustloc.fusion.pipeline import FusionFilter, FusionMeasurement
            from robustloc.tracking import _compiled

            # the fusion filter's compiled core with the tight model of these anchors (the
            # ranges only, no speed and course): settings for the fused round
            fusion = FusionFilter(kind=s.filter, motion=self._motion, robust=self._robust,
                                  max_rejected=0, engine="compiled")
            offsets = (fc.OFF_COMMON if s.range_offset else
                       (fc.OFF_LINKS_SCALED if self._scaled_links() else fc.OFF_LINKS)
                       if s.link_offsets else fc.OFF_NONE)
            prm = fusion.compiled_params(FusionMeasurement(self.n, xy, np.sqrt(dz2)),
                                         kinematic=False, offsets=offsets,
                                         link_n=self._link.n if offsets == fc.OFF_LINKS_SCALED
                                         else None)
            if prm is not None:
                self._kernel = (_compiled.track_round_n if offsets != fc.OFF_NONE
                                else _compiled.ROUNDS[self.n])
                self._prm = prm
                self._tset = _compiled.pack_settings(
                    s.cusum_k, math.inf if s.cusum_h is None else s.cusum_h,
                    s.readmit_samples, s.noise_scale_min**2, s.noise_scale_max**2,
                    s.noise_forget, math.sqrt(self._lam0), self._k_ir, self._w2_crit,
                    s.lost_pos_var)
                rssi = self._kind == "rssi"  # held links' offsets live in dB
                self._rssi_A = np.asarray(A if rssi else np.zeros(0), dtype=float)
                self._rssi_n = np.asarray(nn if rssi else np.zeros(0), dtype=float)
                self._gcrit_f = np.ascontiguousarray(self._gcrit, dtype=float)

    @property
    def method(self) -> str:
        """The ``method`` column value, e.g. ``track-cv-ekf``."""
        return f"{METHOD_PREFIX}-{self.settings.model}-{self.settings.filter}"

    def _scaled_links(self) -> bool:
        """RSSI turned into ranges: a link's offset (dB) scales its range."""
        return self._kind == "rssi" and self._link.kind == "range"

    def _link_factor(self, x: Array) -> Array:
        """``10^(-b_i / (10 n_i)) (K, M)``: the range of RSSI ``z - b_i`` over that of ``z``
        (item 11; seed 000 eq. (1) solved for the distance)."""
        return 10.0 ** (-x[:, self.n_motion:] / (10.0 * self._link.n[None]))

    def _predict(self, x: Array) -> Array:
        """``h(x) (K, M)``: the link model's, plus the range offset or the links' offsets
        when estimated (items 10 and 11 of the module docstring)."""
        h = self._link.predict(x)
        if self.settings.range_offset:
            return h + x[:, -1:]
        if self.settings.link_offsets:
            if self._scaled_links():
                return h * self._link_factor(x)
            return h + x[:, self.n_motion:]
        return h

    def _jacobian(self, x: Array) -> Array:
        """``dh/dx (K, M, n)``: the link model's; ``dh_i/db = 1`` for the range offset and
        a link's offset (``-h_i ln10 / (10 n_i)`` for RSSI turned into ranges)."""
        J = self._link.jacobian(x)
        if self.settings.range_offset:
            J[:, :, -1] = 1.0
        elif self.settings.link_offsets:
            M, nm = self._link.M, self.n_motion
            links = np.arange(M)
            if self._scaled_links():
                f = self._link_factor(x)
                J[:, :, :nm] *= f[..., None]
                h = self._link.predict(x) * f
                J[:, links, nm + links] = -h * (LN10 / 10.0) / self._link.n[None]
            else:
                J[:, links, nm + links] = 1.0
        return J

    def _offset(self, sl: NDArray[np.int64]) -> Array:
        """The tags' estimated offsets in the measurement's unit, to subtract from their
        measurements: the range offset ``(K, 1)``, the links' offsets ``(K, M)`` (m or dB),
        or 0."""
        if self.settings.range_offset:
            return self._x[sl, -1:]
        if self.settings.link_offsets:
            return self._x[sl, self.n_motion:]
        return np.zeros((len(sl), 1))

    def _calibrate(self, values: Array) -> Array:
        """Non-finite values as NaN; ranges corrected with the anchors' ``bias``/``scale``
        (:func:`robustloc.models.calibration.apply_range_calibration`, read at setup)."""
        z = np.where(np.isfinite(values), values, np.nan)
        # an anchor far outside the layout (a typo such as y = 1e300; the command names it)
        # is not used, as by locate: it was "heard" and listed as excluded in every row
        # while the status stayed ok (the tracker review)
        z[:, ~self._sane] = np.nan
        if self._kind == "range":
            bias, scale = self._range_cal
            z = (z - bias) / scale
        return z

    def _observations(self, z: Array) -> tuple[Array, Array]:
        """Observations in the filter's domain and their a-priori variances ``(K, M)``.

        Ranges (and RSSI with ``domain="rssi"``) as measured, variance ``sigma_i^2``.
        RSSI with ``domain="range"``: the path-loss model's range
        ``d = 10^((A - rssi) / (10 n))`` with ``sigma_d = d ln10 sigma_dB / (10 n)`` at
        the measured ``d``, as ``locate``: a faded link reads long and down-weights itself.
        Measured on the seed-002 walk (seed 1, q = 3): walk RMS 1.75 m with the measured
        ``d``, 2.72 m with the predicted distance (which is free of the pull towards
        short readings but leaves the fades at full weight).
        """
        link = self._link
        var = np.broadcast_to(link.sigma[None] ** 2, z.shape)
        if self._kind != "rssi" or self.settings.domain == "rssi":
            return z, var
        with np.errstate(over="ignore", invalid="ignore", under="ignore"):
            d = 10.0 ** ((link.A[None] - z) / (10.0 * link.n[None]))
            sd = d * (np.log(10.0) / 10.0) * link.sigma[None] / link.n[None]
            var = sd * sd
        # a range that under- or overflows (a path-loss exponent near the reader's lower
        # limit 0.01 maps an RSSI to 10^-350 m or 10^200 m, a variance of 0 or inf) is
        # no observation: the compiled update divided by it (ZeroDivisionError, an
        # internal error) and the NumPy one gave `ok` rows without a bound (the review)
        bad = ~((d > 0) & np.isfinite(d) & (var > 0) & np.isfinite(var))
        return np.where(bad, np.nan, d), np.where(bad, np.nan, var)

    # ------------------------------------------------------------------ public API
    def step(self, epochs: Any) -> pd.DataFrame:
        """Advance each tag by the given epochs (time-sorted per tag).

        A tag whose epoch is earlier than its previous one (a device clock that restarted)
        starts again from a robust fix, as after a divergence.

        Parameters
        ----------
        epochs : :class:`robustloc.io.tables.Epochs`
            Its ``anchor_ids`` must be this tracker's anchors in order.

        Returns
        -------
        DataFrame
            One track row per epoch, in the order of ``epochs`` (see :func:`track_columns`).
        """
        if not all(hasattr(epochs, k) for k in ("time", "tag", "values", "anchor_ids",
                                                   "value")):
            raise TypeError("epochs must be robustloc.io.tables.Epochs (to_epochs(frame, "
                            f"anchor_ids)), got {type(epochs).__name__}")
        if tuple(epochs.anchor_ids) != self.anchor_ids:
            raise ValueError("epochs' anchor columns differ from the tracker's anchors")
        if epochs.value not in ("rssi", "range"):
            raise ValueError(f"epochs' value must be 'rssi' or 'range', got {epochs.value!r}")
        # every shape checked before any state changes (the API review: a time array
        # shorter than the values raised IndexError after earlier rounds had moved the
        # filters)
        N = epochs.n_epochs
        shapes = {"time": np.shape(epochs.time), "tag": np.shape(epochs.tag),
                  "values": np.shape(epochs.values)}
        want = {"time": (N,), "tag": (N,), "values": (N, len(self.anchor_ids))}
        bad = [f"{k} {shapes[k]} (expected {want[k]})" for k in want if shapes[k] != want[k]]
        if bad:
            raise ValueError("epochs' arrays disagree: " + ", ".join(bad))
        if self._kind is None:
            self._setup(epochs.value)
        elif epochs.value != self._kind:
            raise ValueError(f"tracker runs on {self._kind}, got {epochs.value} epochs")
        out = _Rows(N, self.n, len(self.anchor_ids))
        if N == 0:
            return self._frame(epochs, out)
        if self.record:  # this step's rows follow the earlier steps' (smoothed())
            first = len(self._history)
            frame = self._step_rows(epochs, out)
            for h in self._history[first:]:
                h["idx"] = h["idx"] + self._rows_recorded
            self._rows_recorded += N
            return frame
        return self._step_rows(epochs, out)

    def _step_rows(self, epochs: Any, out: _Rows) -> pd.DataFrame:
        """:meth:`step` after its checks (``N > 0``)."""
        time = np.asarray(epochs.time, dtype=float)
        tags = np.asarray(epochs.tag, dtype=object)
        z_all = self._calibrate(real_array(epochs.values, "epochs' values"))
        slots = self._slots(tags)
        # an epoch whose every row is outside the physical limits (robustloc.io.limits,
        # e.g. a time of 1e13 s) keeps status invalid_measurement and no state: it never
        # reaches the filter (a prediction to such a time was an absurd `predicted` row)
        # (and so does one whose time is not finite: NaN times were filtered as `ok`)
        live = ~np.asarray(epochs.all_invalid, dtype=bool) & np.isfinite(time)
        rank = _rank_within(slots)
        order = np.argsort(rank, kind="stable")
        bounds = np.searchsorted(rank[order], np.arange(rank.max() + 2))
        for r in range(rank.max() + 1):
            idx = order[bounds[r]: bounds[r + 1]]
            dead = idx[~live[idx]]
            # (the tag's re-start count so far: such a row said 0 after a re-start)
            out.reinit[dead] = self._reinit[slots[dead]]
            idx = idx[live[idx]]
            if idx.size:
                self._round(idx, slots[idx], time[idx], z_all[idx], out)
        return self._frame(epochs, out)

    # ------------------------------------------------------------------ one round
    def _round(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array, z: Array,
               out: _Rows) -> None:
        # an epoch earlier than its tag's last filtered one: the device's clock restarted
        # (the service re-bases such a tag and solves its new run after the old one).  How
        # long the tag was away and where it went are unknown, so its filter is dropped
        # and it starts again from a robust fix, counted as a re-start (a prediction over
        # dt = 0 kept the old run's position: metres off for the first epochs)
        back = self._init[sl] & (t < self._t[sl])
        if back.any():
            self._drop(sl[back])
        init = self._init[sl]
        if not init.all():
            ni = ~init
            self._start_new(idx[ni], sl[ni], t[ni], z[ni], out)
        if init.any():
            i = np.flatnonzero(init)
            # each slot's position variance before this round, and whether its velocity
            # is still the a-priori one of a (re)start (``_snapshot_bound``)
            self._var_before = self._P[:, 0, 0] + self._P[:, 1, 1]
            self._fresh = (self._P[:, 2, 2] >= self.settings.init_vel_var
                           if self.n_motion >= 4 else np.zeros(len(self._P), bool))
            lost = self._filter(idx[i], sl[i], t[i], z[i], out)
            if lost.any():  # dropped filters (item 9): their tags start again, now
                i = i[lost]
                self._drop(sl[i])
                self._start_new(idx[i], sl[i], t[i], z[i], out)
        recent = self._recent_kept(idx, sl, t, z, out)
        self._cover_mirror(idx, sl, z, out, recent)
        self._cover_unobserved(idx, sl, t, z, out, recent)

    def _start_new(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array, z: Array,
                   out: _Rows) -> None:
        """Start tags without a filter (item 1): the epoch's observations, completed by
        each anchor's last observation within ``init_window_s``, to a robust fix."""
        heard = np.isfinite(z)
        with np.errstate(invalid="ignore"):
            recent = (t[:, None] - self._lastt[sl]) <= self.settings.init_window_s
        zi = np.where(heard, z, np.where(recent, self._lastz[sl], np.nan))
        self._lastz[sl] = np.where(heard, z, self._lastz[sl])
        self._lastt[sl] = np.where(heard, t[:, None], self._lastt[sl])
        self._start(idx, sl, t, zi, out, reinit=False)

    def _drop(self, sl: NDArray[np.int64]) -> None:
        """Drop the filters of ``sl`` (item 9): the tags have no filter, as before their
        first fix, and count one re-start each.  The observations they collected before
        their first fix are forgotten (only those from now on complete a start)."""
        self._init[sl] = False
        self._reinit[sl] += 1
        self._bad[sl] = 0
        self._bias[sl] = 0.0
        self._drop_pending(sl)
        self._lastz[sl] = np.nan
        self._lastt[sl] = np.nan
        self._susp[sl] = 0.0
        self._susp_n[sl] = 0
        self._mline[sl] = np.nan
        self._tkeep[sl] = np.nan
        self._ikeep[sl] = np.nan
        self._tdet[sl] = np.nan

    def _cover_mirror(self, idx: NDArray[np.int64], sl: NDArray[np.int64], z: Array,
                      out: _Rows, recent: NDArray[np.bool_]) -> None:
        """Widen ``hpl`` over the mirror solution where the epoch's kept anchors are nearly
        collinear (module docstring, item 8; :mod:`robustloc.integrity.fixes`, item 5).

        The row's position reflected across the principal line of the anchors its update
        kept, refined by Gauss-Newton on the epoch's observations (ranges, or RSSI turned
        to ranges), passes the global test at the row's noise scale, or fits the epoch at
        least as well as the row's own position: the epoch cannot tell the two apart, and
        the motion model, built from such epochs, need not either
        (on the wifi-rtt-rss corridor the tracker followed the mirror side for whole
        stretches: 5.7 % of its rows beyond their ``hpl``, 86 % of them across the line).
        Then ``hpl = max(hpl, |x' - x| + hpl)``.  RSSI fitted in dB is not checked.

        The line of such an epoch stays with its tag: the rows after it continue a track
        that may lie on either side, and while they keep too few anchors for the check
        (one or two) or nearly collinear ones, their ``hpl`` covers their own reflection
        across it, ``hpl + 2 |(x - c) . u|`` (``c`` the anchors' centroid, ``u`` the
        line's normal), until an epoch keeps anchors that span the plane.  (On a
        corridor, rows of one or two ranges on the mirror side were `ok` 2-3.4 m off
        with ``hpl`` 1.9-2.6 m, and so were checked rows whose mirror failed the test
        by the anchors' 0.3 m off the line: the tracker review, 2026-12-06.)

        A row that keeps one or two anchors takes the anchors its tag's updates kept over
        the window of :meth:`_recent_kept` (``recent``) as its epoch: two of them, or
        nearly collinear ones, leave a line whose reflection the row covers and which
        stays with the tag; ones that span the plane clear it.  (Two anchors heard in
        turn, one range per epoch, never kept two in an epoch: the track crossed their
        line, `ok` rows 28 m off with ``hpl`` 2.5 m, 11 % of the rows beyond; a corridor
        of nearly collinear anchors ranged in turn, 5.4 %: the tracker review of item
        12.)"""
        from robustloc.integrity.fixes import AMBIGUITY_ELONGATION

        if self._link is None or (self._kind == "rssi" and self.settings.domain == "rssi"):
            return
        # the anchors each row's update kept, and whether they are nearly collinear: a
        # function of the pattern alone, cached (a few hundred patterns at most)
        keep_all = np.isfinite(z) & ~out.excluded[idx]
        elong = self._pattern_elongation(keep_all)
        dof_all = keep_all.sum(axis=1) - 2
        pre = (dof_all >= 1) & (elong < AMBIGUITY_ELONGATION)
        x = out.x[idx, :2]
        spread = (dof_all >= 1) & ~pre
        # the window's anchors for rows of one or two (ranges taken in turn)
        few = keep_all.sum(axis=1) < 3
        win_n = recent.sum(axis=1)
        win_el = self._pattern_elongation(recent)
        win_line = few & ((win_n == 2) | ((win_n >= 3) & (win_el < AMBIGUITY_ELONGATION)))
        spread |= few & (win_n >= 3) & (win_el >= AMBIGUITY_ELONGATION)
        prev = self._mline[sl]  # (the lines left by earlier epochs: a copy)
        lined = np.isfinite(prev[:, 0])
        if lined.any():  # (anchors that span the plane tell the sides)
            self._mline[sl[spread & lined]] = np.nan
        covered = self._check_mirror(idx, sl, z, out, keep_all, pre, x)
        if lined.any():
            self._carry_mirror(idx, prev, x, lined & ~spread & ~covered & ~win_line, out)
        if win_line.any():
            from robustloc.models.geometry import principal_lines

            w = np.flatnonzero(win_line)
            c, u = principal_lines(self._link.anchors_xy, recent[w])
            line = np.full((len(idx), 4), np.nan)
            line[w] = np.c_[c, u]
            self._carry_mirror(idx, line, x, win_line, out)
            self._mline[sl[w]] = line[w]
        # two anchors kept: the tag and its reflection across their line fit alike, and
        # no test can tell them apart; the row covers its reflection, and the line stays
        # with the tag for its rows of one anchor.  (Three of five anchors falling silent
        # left two for 60 s: the track crossed their line and followed the mirror side,
        # `ok` rows 10-27 m off with hpl about 2 m, 10 % of the rows beyond their hpl;
        # only a line left by an earlier collinear epoch was carried: the track review
        # of 2026-12-06)
        two = np.flatnonzero((keep_all.sum(axis=1) == 2) & ~win_line)
        if two.size:
            from robustloc.models.geometry import principal_lines

            c, u = principal_lines(self._link.anchors_xy, keep_all[two])
            line = np.full((len(idx), 4), np.nan)
            line[two] = np.c_[c, u]
            self._carry_mirror(idx, line, x, np.isfinite(line[:, 0]), out)
            self._mline[sl[two]] = line[two]

    def _check_mirror(self, idx: NDArray[np.int64], sl: NDArray[np.int64], z: Array,
                      out: _Rows, keep_all: NDArray[np.bool_], pre: NDArray[np.bool_],
                      x: Array) -> NDArray[np.bool_]:
        """The check of :meth:`_cover_mirror` on the rows ``pre`` (nearly collinear kept
        anchors, redundancy): widens the ambiguous rows' ``hpl`` by their refined mirror,
        leaves each one's line with its tag, and returns which rows it widened."""
        from robustloc.integrity.fixes import AMBIGUITY_ELONGATION, mirror_solution
        from robustloc.models.geometry import principal_lines
        from robustloc.models.ranging import RangeModel

        link = self._link
        covered = np.zeros(len(idx), dtype=bool)
        if not pre.any():
            return covered
        cand_rows = np.flatnonzero(pre)
        use = (st.among(out.status[idx[cand_rows]], st.USABLE)
               & (out.status[idx[cand_rows]] != st.PREDICTED)
               & np.all(np.isfinite(x[cand_rows]), axis=1)
               & np.isfinite(out.hpl[idx[cand_rows]]))
        rows = cand_rows[use]
        if rows.size == 0:
            return covered
        obs, var = self._observations(z[rows] - self._bias[sl[rows]]
                                      - self._offset(sl[rows]))
        keep = keep_all[rows] & np.isfinite(obs)
        dof = keep.sum(axis=1) - 2
        ok = dof >= 1
        changed = np.flatnonzero(np.any(keep != keep_all[rows], axis=1))
        if changed.size:  # (an observation the conversion could not use)
            ok[changed] &= self._pattern_elongation(keep[changed]) < AMBIGUITY_ELONGATION
        cand = np.flatnonzero(ok)
        r, kc = rows[cand], keep[cand]
        scale = out.scale[idx[r]]
        sig = np.sqrt(var[cand]) * np.where(np.isfinite(scale), scale, 1.0)[:, None]
        model = RangeModel(link.anchors_xy, np.sqrt(link.dz2))
        xr = x[r]
        v = np.where(kc, model.predict(xr) - obs[cand], np.nan)
        x_alt, T_alt, _ = mirror_solution(model, xr, v, sig, kc)
        crit = global_critical(dof[cand], alpha0=self.settings.alpha0,
                               beta0=self.settings.beta0)
        # ambiguous: the mirror passes the test, or fits at least as well as the row does
        T_x = np.nansum(np.where(kc, (v / sig) ** 2, 0.0), axis=1)
        amb = np.isfinite(T_alt) & (T_alt <= np.fmax(crit, T_x))
        if np.any(amb):
            rr = idx[r[amb]]
            d = np.hypot(*(x_alt[amb] - xr[amb]).T)
            out.hpl[rr] = np.fmax(out.hpl[rr], d + out.hpl[rr])
            c, u = principal_lines(link.anchors_xy, kc[amb])
            self._mline[sl[r[amb]]] = np.c_[c, u]
            covered[r[amb]] = True
        return covered

    def _carry_mirror(self, idx: NDArray[np.int64], line: Array, x: Array,
                      few: NDArray[np.bool_], out: _Rows) -> None:
        """Rows ``few`` (too few or nearly collinear kept anchors) of a tag whose last
        ambiguous epoch left its line: ``hpl`` also covers the reflection across it
        (:meth:`_cover_mirror`; ``line`` each row's tag's, before this round)."""
        rows = np.flatnonzero(few & np.isfinite(line[:, 0]))
        rows = rows[st.among(out.status[idx[rows]], st.USABLE)
                    & (out.status[idx[rows]] != st.PREDICTED)
                    & np.all(np.isfinite(x[rows]), axis=1)]
        if rows.size == 0:
            return
        c, u = line[rows, :2], line[rows, 2:]
        d = 2.0 * np.abs(np.einsum("ki,ki->k", x[rows] - c, u))
        rr = idx[rows]
        out.hpl[rr] = np.maximum(out.hpl[rr], d + out.hpl[rr])

    def _recent_kept(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array,
                     z: Array, out: _Rows) -> NDArray[np.bool_]:
        """Record the anchors each row's update kept; return, per row, those its tag's
        updates kept recently: within ``observed_window_s`` seconds, or among its last
        ``M`` updates (``M`` the anchors) within :data:`OBSERVED_COUNT_SPAN` windows (one
        range per report just over a second apart, anchors in turn, made every row
        unobserved and tripled its ``hpl``: the tracker review of item 12)."""
        W = self.settings.observed_window_s
        x = out.x[idx, :2]
        have = self._init[sl] & np.all(np.isfinite(x), axis=1)
        upd = have & (out.status[idx] != st.PREDICTED)
        kept = upd[:, None] & np.isfinite(z) & ~out.excluded[idx]
        nupd = self._nupd[sl] + upd
        self._nupd[sl] = nupd
        tk = np.where(kept, t[:, None], self._tkeep[sl])
        ik = np.where(kept, nupd[:, None], self._ikeep[sl])
        self._tkeep[sl] = tk
        self._ikeep[sl] = ik
        M = kept.shape[1]
        with np.errstate(invalid="ignore"):
            age = t[:, None] - tk
            recent = (age <= W) | ((nupd[:, None] - ik < M) & (age <= OBSERVED_COUNT_SPAN * W))
        return recent & have[:, None]

    def _spans(self, x: Array, recent: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Whether each row's recent anchors, seen from its position, span the plane:
        the smallest eigenvalue of ``sum_i u_i u_i^T`` (``u_i`` the unit vectors to them)
        at least :data:`OBSERVED_MIN_EIGENVALUE` (two anchors at least 10 degrees apart).
        Two anchors 0.5 m apart, 20 m away, counted as observing the position: their
        ranges are one circle (9.5 % of the rows beyond ``hpl``, the tracker review)."""
        d = x[:, None, :] - self._link.anchors_xy[None]
        with np.errstate(invalid="ignore", divide="ignore"):
            u = d / np.hypot(d[..., 0], d[..., 1])[..., None]
        u = np.where(recent[..., None] & np.isfinite(u), u, 0.0)
        a = np.einsum("km,km->k", u[..., 0], u[..., 0])
        b = np.einsum("km,km->k", u[..., 1], u[..., 1])
        c = np.einsum("km,km->k", u[..., 0], u[..., 1])
        lam_min = 0.5 * (a + b) - np.sqrt(np.maximum(0.25 * (a - b) ** 2 + c * c, 0.0))
        return lam_min >= OBSERVED_MIN_EIGENVALUE

    def _cover_unobserved(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array,
                          z: Array, out: _Rows, recent: NDArray[np.bool_]) -> None:
        """Widen ``hpl`` over the motion since the tag's position was last observed
        (module docstring, item 12).

        A row counts as observed when its tag's recent updates (:meth:`_recent_kept`)
        kept two or more distinct anchors that span the plane as seen from it
        (:meth:`_spans`; a start row always counts); it
        then records its time ``t_o`` and covariance ``P_o``.  Any other usable row is
        also bounded by ``k sigma_major`` of ``F(dt) P_o F(dt)^T + Q(dt)``, ``dt = t -
        t_o``: the covariance of the last observed state predicted to the row without the
        updates since, which could not fix the position.  One range says how far the tag
        is from its anchor, not where on that circle it is, and the EKF's covariance,
        linearized at a point that slides along the circle, shrinks in every direction all
        the same (a walk with one anchor of five heard for 60 s: `ok` rows up to 51 m off
        with ``hpl`` of a few metres, 29 % of the rows beyond their ``hpl``)."""
        x = out.x[idx, :2]
        have = self._init[sl] & np.all(np.isfinite(x), axis=1)
        started = have & (self._tdet[sl] == t)  # (a start row of this round: _start)
        obs = have & (recent.sum(axis=1) >= 2) & ~started
        if obs.any():
            obs[obs] = self._spans(x[obs], recent[obs])
        if obs.any():
            self._tdet[sl[obs]] = t[obs]
            self._Pdet[sl[obs]] = self._P[sl[obs]]
        rows = np.flatnonzero(have & ~obs & ~started & np.isfinite(self._tdet[sl])
                              & st.among(out.status[idx], st.USABLE))
        if rows.size == 0:
            return
        s_u = sl[rows]
        dt = np.maximum(t[rows] - self._tdet[s_u], 0.0)
        F, Q = self._motion.F(dt), self._motion.Q(dt)
        Pu = F @ self._Pdet[s_u] @ np.swapaxes(F, 1, 2) + Q
        a, b, c = Pu[:, 0, 0], Pu[:, 1, 1], Pu[:, 0, 1]
        lam = 0.5 * (a + b) + np.sqrt(np.maximum(0.25 * (a - b) ** 2 + c * c, 0.0))
        bound = self._k_ir * np.sqrt(lam)
        ring = self._ring_bound(sl[rows], z[rows], x[rows],
                                self._tkeep[sl[rows]] == t[rows, None], out.scale[idx[rows]])
        rr = idx[rows]
        out.hpl[rr] = np.maximum(out.hpl[rr], np.fmin(bound, ring))

    def _ring_bound(self, sl: NDArray[np.int64], z: Array, x: Array,
                    kept: NDArray[np.bool_], scale: Array) -> Array:
        """A bound of each row's horizontal error from the ranges it kept alone:
        ``min_i |x - a_i| + d_i + k s sigma_i`` (``d_i`` the horizontal distance of the
        range, the observation with its offsets removed, ``s sigma_i`` its noise): the tag
        lies within ``d_i + k s sigma_i`` of anchor ``i`` unless the range reads short by
        more than ``k`` of its sigmas (NLOS and fading read long).  Infinite where no range
        is kept, and for RSSI fitted in dB (:meth:`_cover_unobserved`)."""
        out = np.full(len(sl), np.inf)
        if self._link is None or (self._kind == "rssi" and self.settings.domain == "rssi"):
            return out
        link = self._link
        obs, var = self._observations(z - self._bias[sl] - self._offset(sl))
        with np.errstate(invalid="ignore"):
            d = np.sqrt(np.maximum(obs * obs - link.dz2[None], 0.0))
            sig = np.sqrt(var) * np.where(np.isfinite(scale), scale, 1.0)[:, None]
            far = np.hypot(x[:, None, 0] - link.anchors_xy[None, :, 0],
                           x[:, None, 1] - link.anchors_xy[None, :, 1])
            b = np.where(kept & np.isfinite(obs), far + d + self._k_ir * sig, np.inf)
        return np.min(np.where(np.isnan(b), np.inf, b), axis=1, initial=np.inf)

    def _pattern_elongation(self, keep: NDArray[np.bool_]) -> Array:
        """:func:`robustloc.models.geometry.anchor_elongation` of each row's kept anchors,
        each distinct pattern computed once per tracker."""
        from robustloc.models.geometry import anchor_elongation

        M = keep.shape[1]
        if M > 20:  # (a lookup table of 2^M entries would be too large)
            return anchor_elongation(self._link.anchors_xy, keep)
        table = self.__dict__.get("_elong_table")
        if table is None or table.size != 1 << M:
            table = self._elong_table = np.full(1 << M, np.nan)  # NaN: not computed yet
        key = keep.astype(np.int64) @ (np.int64(1) << np.arange(M, dtype=np.int64))
        el = table[key]
        todo = np.isnan(el)
        if todo.any():
            uk, first = np.unique(key[todo], return_index=True)
            table[uk] = np.nan_to_num(
                anchor_elongation(self._link.anchors_xy, keep[np.flatnonzero(todo)[first]]),
                nan=np.inf)  # (fewer than two anchors: never elongated)
            el = table[key]
        return el

    def _start(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array, z: Array,
               out: _Rows, reinit: bool) -> NDArray[np.bool_]:
        """Robust snapshot fixes; usable ones start (or re-start) their tag's filter."""
        s = self.settings
        sol = self._fix(z)
        pos = np.asarray(sol.position, dtype=float)
        ok = st.among(sol.status, st.USABLE) & np.all(np.isfinite(pos), axis=1)
        # the start's own test: Huber's fit with the epoch's own scale tests nothing, and a
        # start from ranges of 40, 1, 40, 1 and 20 m (a tag 2 m from its true place at 1 m
        # noise) began 19 m off as `ok` with hpl 2 m, where `locate` says `unavailable`
        # (the input review).  The epoch's protected fix is the judge: where it detects a
        # fault it cannot exclude, or gives no fix at all, the start row is
        # `fault_detected`, bounded as the snapshot bounds it (:meth:`_snapshot_bound`),
        # or without a bound (hpl inf) when the snapshot has none.  The filter still
        # starts there (refusing it, a tag whose a-priori sigma is too small for its log
        # never started) and re-starts if it then diverges.
        snap = self._protected_fix(z)
        snap_status = np.asarray(snap.status, dtype=object)
        detected = ok & ((snap_status == st.FAULT_DETECTED)
                         | ~st.among(snap_status, st.USABLE))
        cov = self._fix_cov(pos, z, np.asarray(sol.excluded, bool))
        var0 = (np.diagonal(cov, axis1=1, axis2=2) if cov.ndim == 3
                else np.full(pos.shape, np.nan))
        var = np.clip(np.where(np.isfinite(var0), var0, 4.0), s.init_pos_var_min, 100.0)
        # the filter starts from the fix's clipped variances without their correlation,
        # and the row says so (cov_xy 0): it gave the fix's correlation, so the row claimed
        # a covariance the filter did not have and the smoothed first row was not within
        # it (the tracker review).  Starting the filter from the correlation instead was
        # measured on s60 (2026-12-04): ble-tetam 0.769 -> 0.807x locate (--link-offsets
        # 0.709 -> 0.757x, past the 0.75x target), dwm1001 --range-offset 0.906 -> 0.779 m
        # (LOS) and 0.811 -> 0.772 m (NLOS); the start stays diagonal.  The first row's
        # hpl still covers the fix's major axis (below).
        cxy = np.zeros(len(pos))
        n = self.n
        k = sl[ok]
        x0 = np.zeros((ok.sum(), n))
        x0[:, :2] = pos[ok]
        diag = np.zeros((ok.sum(), n))
        diag[:, :2] = var[ok]
        if self.n_motion >= 4:
            diag[:, 2:4] = s.init_vel_var
        if self.n_motion >= 6:
            diag[:, 4:6] = s.init_acc_var
        nm = self.n_motion
        keep_P = None
        if s.range_offset:
            # a re-start keeps the tag's offset (its fix used ranges with it removed); a
            # new tag starts from the a-priori offset 0 +- range_offset_sd
            diag[:, -1] = s.range_offset_sd**2
            if reinit:
                x0[:, -1] = self._x[k, -1]
                diag[:, -1] = self._P[k, -1, -1]
        elif s.link_offsets:  # the same for the links' offsets (with their covariance)
            diag[:, nm:] = self._link_offset_sd**2
            if reinit:
                x0[:, nm:] = self._x[k, nm:]
                keep_P = self._P[k, nm:, nm:].copy()
        self._x[k] = x0
        self._P[k] = diag[:, :, None] * np.eye(n)[None]
        if keep_P is not None:
            self._P[k, nm:, nm:] = keep_P
        self._t[k] = t[ok]
        self._init[k] = True
        self._bad[k] = 0
        self._drop_pending(k)
        self._gp[k] = 0.0
        self._gm[k] = 0.0
        self._held[k] = False
        self._hsum[k] = 0.0
        self._hn[k] = 0
        self._bias[k] = 0.0  # (offsets measured against the filter that is re-started)
        self._susp[k] = 0.0  # (a start row is bounded by its own snapshot)
        self._susp_n[k] = 0
        self._mline[k] = np.nan
        # the start row is observed (item 12): the anchors its fix kept count as kept now
        self._tdet[k] = t[ok]
        self._Pdet[k] = self._P[k]
        used0 = np.isfinite(z[ok]) & ~np.asarray(sol.excluded, bool)[ok]
        self._tkeep[k] = np.where(used0, t[ok, None], np.nan)
        self._ikeep[k] = np.where(used0, self._nupd[k][:, None], np.nan)
        if reinit:
            self._reinit[k] += 1
        # rows: the fix (its status), or the failed fix's status
        out.x[idx] = np.nan
        out.x[idx[ok]] = x0
        out.var[idx] = np.nan
        out.var[idx[ok]] = diag
        out.cxy[idx] = np.where(ok, cxy, np.nan)
        # a usable snapshot's status where it says more than `ok` (low_redundancy,
        # fault_excluded, unverified, extrapolated: the start row said `ok` with them)
        snap_says = ok & ~detected & st.among(snap_status, st.USABLE) & (snap_status != st.OK)
        out.status[idx] = np.where(detected, st.FAULT_DETECTED,
                                   np.where(snap_says, snap_status,
                                            np.asarray(sol.status, dtype=object)))
        out.n_used[idx] = np.asarray(sol.n_used, dtype=np.int64)
        exc = np.asarray(sol.excluded, dtype=bool)
        out.excluded[idx] = exc
        sig = np.sqrt(np.maximum(np.linalg.eigvalsh(np.where(
            np.isfinite(cov), cov, 0.0)) if cov.ndim == 3 else np.zeros((len(idx), 2)), 0.0))
        smaj = np.sqrt(var.max(axis=1))
        if cov.ndim == 3:
            smaj = np.maximum(smaj, sig[:, -1])
        hpl = self._k_ir * smaj
        # every start row is bounded as its snapshot bounds it: |x - x_s| + HPL_s
        # (:meth:`_snapshot_bound`), never narrower; no snapshot bound, no bound (inf).
        # The start's variance alone (clipped below at init_pos_var_min) gave 1.86 m to
        # a fix 10 m off on the corridor, and 19-33 % of one-epoch starts with one range
        # biased by up to 5 m exceeded it, all `ok` (the track review, 2026-12-06)
        if ok.any():
            with np.errstate(invalid="ignore"):
                alt = (np.hypot(*(pos[ok] - snap.position[ok, :2]).T)
                       + np.asarray(snap.extra["hpl"], dtype=float)[ok])
            hpl[ok] = np.fmax(hpl[ok], np.where(np.isnan(alt), np.inf, alt))
        out.hpl[idx] = np.where(ok, hpl, np.nan)
        out.reinit[idx] = self._reinit[sl]
        if self.record:
            self._history.append({"idx": idx[ok], "slot": k, "start": np.ones(ok.sum(), bool),
                                  "xf": x0, "Pf": self._P[k].copy(), "xp": x0,
                                  "Pp": self._P[k].copy(), "dt": np.zeros(ok.sum())})
        return ok

    def _filter(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array, z: Array,
                out: _Rows) -> NDArray[np.bool_]:
        """Predict + update the started tags of one round (the fused compiled round, or
        the NumPy engine when there is none or it cannot do this round).

        Returns the mask of the tags whose filter is lost (item 9): nothing was written
        for them (state or row); every other tag was advanced as without them."""
        if self.record:  # the noise scales the update uses (predictive_score)
            self._s2_before = self._scale2.copy()
        lost = None if self._kernel is None else self._filter_compiled(idx, sl, t, z, out)
        return self._filter_numpy(idx, sl, t, z, out) if lost is None else lost

    def _filter_compiled(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array,
                         z: Array, out: _Rows) -> NDArray[np.bool_] | None:
        """The round in one call of the fused kernel (:mod:`robustloc.tracking._compiled`);
        ``None`` (nothing changed) when the kernel cannot do it, else the lost tags (as
        :meth:`_filter`; the kernel flags them, the others run again without them)."""
        from robustloc.tracking import _compiled

        K, n = len(idx), self.n
        code = np.empty(K, dtype=np.int64)
        moved = np.empty(K, dtype=bool)
        sus = np.empty(K, dtype=bool)
        dof = np.empty(K, dtype=np.int64)
        xp = np.empty((K, n))
        Pp = np.empty((K, n, n))
        dt = np.empty(K)
        lost = np.zeros(K, dtype=bool)
        z = np.ascontiguousarray(z, dtype=float)
        obs, R0 = self._observations(z - self._bias[sl])
        rc = self._kernel(
            np.ascontiguousarray(sl), np.ascontiguousarray(t, dtype=float), z, self._x,
            self._P, self._t, self._bias, self._held, self._gp, self._gm, self._hsum,
            self._hn, self._scale2, np.ascontiguousarray(obs, dtype=float),
            np.ascontiguousarray(R0, dtype=float), self._rssi_A, self._rssi_n,
            self._link.d_min_m, self._prm, self._tset, self._gcrit_f,
            np.ascontiguousarray(idx), out.x, out.var, out.cxy, out.n_used, out.nis,
            out.excluded, out.hpl, out.scale, code, moved, sus, dof, xp, Pp, dt, lost)
        if rc == _compiled.LOST:
            return self._without(lost, idx, sl, t, z, out, self._filter)
        if rc != 0:
            return None
        out.status[idx] = _CODE_STATUS[code]
        if self.n > self.n_motion:  # the snapshot fixes of checks and re-starts: the
            z = z - self._offset(sl)  # offsets removed
        self._finish(idx, sl, t, z, out, moved, sus, dof, xp, Pp, dt)
        return lost

    @staticmethod
    def _without(lost: NDArray[np.bool_], idx: NDArray[np.int64], sl: NDArray[np.int64],
                 t: Array, z: Array, out: _Rows,
                 engine: Callable[..., NDArray[np.bool_]]) -> NDArray[np.bool_]:
        """The round of the tags not ``lost`` through ``engine`` (as :meth:`_filter`; each
        tag's row depends on its own history only, so they are the rows without the
        lost ones); returns every lost tag."""
        lost = lost.copy()
        keep = np.flatnonzero(~lost)
        if keep.size:
            lost[keep] = engine(idx[keep], sl[keep], t[keep], z[keep], out)
        return lost

    def _filter_numpy(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array,
                      z: Array, out: _Rows) -> NDArray[np.bool_]:
        """The round with the batched NumPy core (the reference implementation); returns
        the lost tags (as :meth:`_filter`: a meaningless prediction before the update, a
        numerical failure of the update; nothing is written before both are known)."""
        s = self.settings
        link = self._link
        M = link.M
        x, P = self._x[sl], self._P[sl]
        dt = np.maximum(t - self._t[sl], 0.0)
        F, Q = self._motion.F(dt), self._motion.Q(dt)
        xp = (F @ x[:, :, None])[:, :, 0]
        Pp = F @ P @ np.swapaxes(F, 1, 2) + Q
        Pp = 0.5 * (Pp + np.swapaxes(Pp, 1, 2))
        # innovations of every heard link against the prediction (CUSUM, offsets, hpl)
        bias = self._bias[sl]
        heard = np.isfinite(z)
        if self._kind == "rssi":  # offsets live in dB: residual against the path-loss model
            d_raw = z - link.rssi(xp)
            if s.link_offsets:  # (and the links' offset states)
                d_raw = d_raw - xp[:, self.n_motion:]
        else:
            d_raw = None
        hp = self._predict(xp)
        obs, R0 = self._observations(z - bias)
        if d_raw is None:
            d_raw = z - hp
        H = self._jacobian(xp)
        PHt = Pp @ np.swapaxes(H, 1, 2)  # (K, n, M)
        HPH = (H * np.swapaxes(PHt, 1, 2)).sum(axis=2)
        scale2 = self._scale2[sl]
        Rd = scale2[:, None] * R0
        y = obs - hp
        with np.errstate(invalid="ignore"):
            e = y / np.sqrt(HPH + Rd)
        # --- step detector (CUSUM) on the links in use
        held = self._held[sl].copy()
        gp, gm = self._gp[sl].copy(), self._gm[sl].copy()
        use = heard & ~held
        ev = np.where(use, e, 0.0)
        gp = np.where(use, np.maximum(0.0, gp + ev - s.cusum_k), gp)
        gm = np.where(use, np.maximum(0.0, gm - ev - s.cusum_k), gm)
        h_cusum = math.inf if s.cusum_h is None else s.cusum_h
        alarm = use & ((gp > h_cusum) | (gm > h_cusum))
        # more links stepping than a minority of the anchors: the tag moved (or the filter
        # drifted), not its links -- release every hold, count the epoch as failing.  A
        # link whose offset from an earlier step is still in force counts as stepping,
        # and the offsets go with the holds: each offset is measured against the filter's
        # prediction, so offsets on most links carry the filter's drift, not the links'
        # (the track review: --cusum-h 10 on four links stepping 0-3 m every 20 s left
        # offsets of -10 to +5 m on all four, the track 6-10 m off, 75 % of its rows
        # beyond hpl, all `ok`)
        stepped = held | alarm | (bias != 0.0)
        moved = alarm.any(axis=1) & (stepped.sum(axis=1) > max(1, (M - 1) // 2))
        reset = moved[:, None] & np.ones((1, M), dtype=bool)
        alarm &= ~reset
        held &= ~reset
        gp = np.where(alarm | reset, 0.0, gp)
        gm = np.where(alarm | reset, 0.0, gm)
        held |= alarm
        hsum = np.where(alarm | reset, 0.0, self._hsum[sl])
        hn = np.where(alarm | reset, 0, self._hn[sl])
        # held links: accumulate the new offset, re-admit after readmit_samples
        acc = held & heard
        hsum = hsum + np.where(acc, d_raw, 0.0)
        hn = hn + acc
        ready = held & (hn >= s.readmit_samples)
        new_bias = np.where(reset, 0.0, np.where(ready, hsum / np.maximum(hn, 1), bias))
        zin = np.where(held, np.nan, obs)
        held_now = held & heard
        held = held & ~ready
        hsum = np.where(ready, 0.0, hsum)
        hn = np.where(ready, 0, hn)
        avail = np.isfinite(zin)
        # --- a meaningless prediction (item 9): dropped before its update
        r_min = np.min(np.where(avail, Rd, np.inf), axis=1) if M else np.full(len(sl), np.inf)
        lost = avail.any(axis=1) & _prediction_lost(Pp[:, 0, 0] + Pp[:, 1, 1], r_min,
                                                    s.lost_pos_var)
        if lost.any():
            return self._without(lost, idx, sl, t, z, out, self._filter_numpy)

        try:
            # --- the filter step: predict + robust update (shared core)
            xq, Pq = predict_linear(x, P, F, Q)
            R = Rd[:, :, None] * np.eye(M)[None]
            if s.filter == "ekf":
                res = update_ekf(xq, Pq, zin, self._predict, R, jac=self._jacobian,
                                 robust=self._robust)
            else:
                res = update_ukf(xq, Pq, zin, self._predict, R, points=SigmaPoints(),
                                 robust=self._robust)
            xn, Pn, w = res.x, res.P, res.weights
            nis, rstat, nu = res.nis, res.status, res.n_used

            # --- B-method global test, divergence
            dof = avail.sum(axis=1)
            crit = self._gcrit[dof]
            with np.errstate(invalid="ignore"):
                test_fail = (dof > 0) & (nis > crit)
            # a suspicious epoch (the global test failed and one exclusion does not explain
            # it, or half the components rejected) is checked against the robust snapshot
            # fix: a filter that drifted off, or locked onto a wrong solution (two
            # consistent links, the others rejected), disagrees
            cand = test_fail & (dof >= 2)
            explained = np.zeros(len(sl), dtype=bool)
            fault = np.full(len(sl), -1, dtype=np.int64)  # the component that explains it
            if cand.any():  # a failure that one w-test exclusion explains passes
                explained[cand], fault[cand] = one_fault_explains(
                    H[cand], Pp[cand], Rd[cand], y[cand], avail[cand], self._w2_crit,
                    self._gcrit[dof[cand] - 1], return_index=True)
                test_fail &= ~explained
        except np.linalg.LinAlgError:
            # a singular system of some tag (the batched solvers stop at the first): the
            # tags one at a time, so that only those that fail alone are lost
            if len(idx) == 1:
                return np.ones(1, dtype=bool)
            return np.concatenate([self._filter_numpy(idx[k:k + 1], sl[k:k + 1], t[k:k + 1],
                                                      z[k:k + 1], out)
                                   for k in range(len(idx))])
        # --- an update that failed numerically (item 9): non-finite, negative variance,
        # or a heard component whose innovation variance is not positive (the prediction
        # is no covariance; the equivalent-variance update leaves such a component out and
        # could return a plausible P+ from a broken P-)
        with np.errstate(invalid="ignore"):
            no_var = (np.isfinite(res.innovation) & ~np.isfinite(res.standardized)).any(axis=1)
        lost = ~_finite_moments(xn, Pn) | no_var
        if lost.any():
            return self._without(lost, idx, sl, t, z, out, self._filter_numpy)
        sus = test_fail | ((dof > 0) & (2 * nu <= dof))

        # --- adaptive noise scale (accepted components, robust weights; not the component
        # the w-test identified: one 10 m range took the scale from 1.0 to 1.44 and held
        # it there, the track review)
        wa = np.where(avail & (np.arange(M)[None, :] != fault[:, None]), w, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            est = np.where(avail, (y * y - HPH) / R0, 0.0)
            sw = wa.sum(axis=1)
            r_hat = np.where(sw > 0, (wa * est).sum(axis=1) / np.maximum(sw, 1e-300), np.nan)
        lo, hi = s.noise_scale_min**2, s.noise_scale_max**2
        upd = np.isfinite(r_hat)
        scale2 = np.where(upd, np.clip((1 - s.noise_forget) * scale2
                                       + s.noise_forget * np.maximum(r_hat, 0.0), lo, hi),
                          scale2)

        # --- protection level: robust gain columns times the MDB, plus k sigma
        hpl = self._hpl(H, HPH, Rd, avail, w, Pn, Pp)

        # --- store
        self._x[sl] = xn
        self._P[sl] = Pn
        self._t[sl] = t
        self._bias[sl] = new_bias
        self._held[sl] = held
        self._gp[sl], self._gm[sl] = gp, gm
        self._hsum[sl], self._hn[sl] = hsum, hn
        self._scale2[sl] = scale2
        status = np.asarray(rstat, dtype=object).copy()
        # a held link, or a fault the w-test identified (the robust weight may only have
        # down-weighted it: Huber's; it said `ok`, the track review): fault_excluded
        status[(status == st.OK) & (held_now.any(axis=1) | explained)] = st.FAULT_EXCLUDED
        out.x[idx] = xn
        out.var[idx] = np.diagonal(Pn, axis1=1, axis2=2)
        out.cxy[idx] = Pn[:, 0, 1]
        out.status[idx] = status
        out.n_used[idx] = nu
        out.nis[idx] = nis
        out.excluded[idx] = ((avail & (w <= 0)) | held_now
                             | (np.arange(M)[None, :] == fault[:, None]))
        out.hpl[idx] = hpl
        out.scale[idx] = np.sqrt(scale2)
        if self.n > self.n_motion:  # the snapshot fixes of checks and re-starts: the
            z = z - self._offset(sl)  # offsets removed (stored above)
        self._finish(idx, sl, t, z, out, moved, sus, dof, xp, Pp, dt)
        return lost

    def _finish(self, idx: NDArray[np.int64], sl: NDArray[np.int64], t: Array, z: Array,
                out: _Rows, moved: NDArray[np.bool_], sus: NDArray[np.bool_],
                dof: NDArray[np.int64], xp: Array, Pp: Array, dt: Array) -> None:
        """Divergence bookkeeping of a filtered round (both engines): suspicious epochs
        against the robust fix, the bad-epoch count, re-starts; the recorded moments."""
        s = self.settings
        xn, Pn = self._x[sl], self._P[sl]
        # a suspicious epoch (the global test on the innovations failed and one exclusion
        # does not explain it, or half the components were rejected) is not `ok`: as
        # `locate`'s failed test, fault_detected, its hpl widened by the a-posteriori
        # variance factor sqrt(NIS / dof) (the rows were `ok`, some beyond their hpl)
        fd = sus & st.among(out.status[idx], (st.OK, st.FAULT_EXCLUDED))
        if fd.any():
            rows = idx[fd]
            out.status[rows] = st.FAULT_DETECTED
            with np.errstate(invalid="ignore", divide="ignore"):
                f = np.sqrt(np.maximum(out.nis[rows] / np.maximum(dof[fd], 1), 1.0))
            out.hpl[rows] = out.hpl[rows] * np.where(np.isfinite(f), f, 1.0)
        self._snapshot_bound(idx, sl, xn, Pn, Pp, z, out)
        self._carry_suspicion(idx, sl, z, out)
        bad = self._count_bad(sl, xn, z, moved, sus, dof)
        if self.record:
            self._history.append({"idx": idx, "slot": sl.copy(),
                                  "start": np.zeros(len(idx), bool), "xf": xn, "Pf": Pn,
                                  "xp": xp, "Pp": Pp, "dt": dt,
                                  "s2": self._s2_before[sl]})
        # --- divergence: re-start from the robust fix of this epoch
        div = bad >= s.max_bad_epochs
        lost = ~div & (Pn[:, 0, 0] + Pn[:, 1, 1] > s.lost_pos_var)
        if lost.any():  # a filter less certain than a snapshot fix has lost its track
            div[lost] = self._better_fix(Pn[lost], z[lost])
        if div.any():
            keep_rows = {a: getattr(out, a)[idx[div]].copy() for a in _Rows.FIELDS}
            ok = self._start(idx[div], sl[div], t[div], z[div], out, reinit=True)
            if not ok.all():  # no usable fix: keep the filtered rows, try again next epoch
                rows = idx[div][~ok]
                for a, v in keep_rows.items():
                    getattr(out, a)[rows] = v[~ok]
        out.reinit[idx] = self._reinit[sl]

    def _carry_suspicion(self, idx: NDArray[np.int64], sl: NDArray[np.int64], z: Array,
                         out: _Rows) -> None:
        """Carry a ``fault_detected`` row's bound to its tag's next rows until they
        confirm the filter (module docstring, item 8).

        A detected fault that no exclusion explains may be the state's, not the
        observations': the filter keeps its state (it rejects the observations), and an
        update of one range cannot show it wrong across that range's direction.  So the
        row's widened ``hpl`` stands as a lower bound of the tag's next rows' until
        passing epochs after it have used ``3`` observations (2-D position plus one:
        one redundant epoch, or three single-range epochs in a row).  Before, one range
        a round (round-robin ranging) after a jump of the tag gave ``fault_detected``
        and ``ok`` rows in turn, the ``ok`` ones 8 m off with ``hpl`` 0.7-2 m, for 2 s
        (the tracker review, 2026-12-06).  Positions are unchanged.
        """
        status = out.status[idx]
        fd = status == st.FAULT_DETECTED
        cur = self._susp[sl]
        on = fd | ~(cur <= 0)  # (NaN: state_dict saves inf, no bound, as null)
        if not on.any():
            return
        # only the rows of tags under suspicion, or detecting a fault now
        idx, sl, z, status, fd = idx[on], sl[on], z[on], status[on], fd[on]
        cur, cnt = self._susp[sl], self._susp_n[sl]
        cur = np.where(np.isnan(cur), np.inf, cur)
        used = (np.isfinite(z) & ~out.excluded[idx]).sum(axis=1)
        passing = ~fd & st.among(status, st.USABLE) & (cur > 0)
        cnt = np.where(passing, cnt + used, np.where(fd, 0, cnt))
        done = passing & (cnt >= SUSPICION_CONFIRM)
        under = (passing & ~done) | (fd & (cur > 0))
        hpl = out.hpl[idx]
        out.hpl[idx[under]] = np.maximum(hpl[under], cur[under])
        with np.errstate(invalid="ignore"):
            new = np.where(fd, np.fmax(cur, np.where(np.isnan(hpl), np.inf, hpl)), cur)
        self._susp[sl] = np.where(done, 0.0, new)
        self._susp_n[sl] = np.where(done, 0, cnt)

    def _snapshot_bound(self, idx: NDArray[np.int64], sl: NDArray[np.int64], xn: Array,
                        Pn: Array, Pp: Array, z: Array, out: _Rows) -> None:
        """Bound a row whose filter bound exploded by the epoch's own protected fix.

        After a gap the predicted ranges' variance ``(H P- H^T)_ii`` dominates the
        innovation's, and with it the MDB of the component-wise w-test: the first row after
        a 50 s gap had ``hpl`` 3.6 km for an error of 0.8 m (the tracker review), where
        ``locate`` bounds the same epoch by 0.6 m.  The error of the filtered position
        ``x`` is at most ``|x - x_s| + HPL_s`` whenever the snapshot fix ``x_s`` of the
        epoch (``locate``'s default, the a-priori sigma) is within its bound ``HPL_s``, so
        a usable row whose ``hpl`` exceeds :data:`SNAPSHOT_BOUND_RATIO` times its noise
        term, and whose prediction widened the position variance of the previous update
        :data:`SNAPSHOT_PREDICTION_RATIO`-fold or more (a gap: in steady state it grows a
        few times at most; the epoch after a (re)start, whose velocity is the a-priori one,
        is left out: it widens as much, and solving those epochs cost ``bench_track.py`` a
        third of its speed), takes
        ``min(hpl, |x - x_s| + HPL_s)``.  Either bound
        fails with its own integrity risk, so the smaller one fails at most with their
        sum.  (Rows widened by a failed test in steady state are left alone: solving
        their epochs cost ``bench_track.py`` 60 % of its speed.)
        """
        P2 = Pn[:, :2, :2]
        tr = 0.5 * (P2[:, 0, 0] + P2[:, 1, 1])
        det = P2[:, 0, 0] * P2[:, 1, 1] - P2[:, 0, 1] ** 2
        noise = self._k_ir * np.sqrt(np.maximum(tr + np.sqrt(np.maximum(tr * tr - det, 0.0)),
                                                0.0))
        hpl = out.hpl[idx]
        with np.errstate(invalid="ignore"):
            wide = (hpl > SNAPSHOT_BOUND_RATIO * noise) & np.isfinite(hpl) & ~self._fresh[sl] & (
                Pp[:, 0, 0] + Pp[:, 1, 1] > SNAPSHOT_PREDICTION_RATIO * self._var_before[sl])
        if not wide.any():
            return
        wide &= st.among(out.status[idx], st.USABLE) & (np.isfinite(z).sum(axis=1) > 2)
        if not wide.any():
            return
        snap = self._protected_fix(z[wide])
        with np.errstate(invalid="ignore"):
            alt = (np.hypot(*(xn[wide, :2] - snap.position[:, :2]).T)
                   + np.asarray(snap.extra["hpl"], dtype=float))
        alt = np.where(st.among(snap.status, st.USABLE) & np.isfinite(alt), alt, np.inf)
        rows = idx[wide]
        out.hpl[rows] = np.fmin(out.hpl[rows], alt)

    def _count_bad(self, sl: NDArray[np.int64], xn: Array, z: Array, moved: NDArray[np.bool_],
                   sus: NDArray[np.bool_], dof: NDArray[np.int64]) -> NDArray[np.int64]:
        """The divergence counter after this round: ``bad + 1`` on a failing epoch (the
        tag moved, or a suspicious epoch disagrees with its robust fix), 0 on a passing
        epoch with ``dof > 0``, unchanged otherwise; exact wherever it decides a re-start
        (the value where it reaches ``max_bad_epochs``, a lower bound elsewhere).

        The snapshot check of a suspicious epoch is deferred, not run each round: the
        counter's two updates are monotone in it and the failing one is the larger, so
        counting every pending check as failing (``hi``) or as passing (``lo``) bounds
        the exact counter.  A passing unsuspicious epoch resets it (0 whatever the
        pending checks say): those checks are dropped unsolved.  Only a tag with
        ``lo < max_bad_epochs <= hi`` needs its checks now; the rest are solved together
        at the end of :meth:`step`.  The robust fix depends on the epoch's observations
        alone, so the answers, the counters and every output are those of checking each
        round (tested); most checks are never solved (5 consecutive failing epochs are
        rare).  Checks still pending stay with the tag across :meth:`step` calls (a live
        service steps one epoch at a time) and are solved together by
        :meth:`state_dict`, which needs the exact counters.
        """
        hi0 = self._bad[sl]
        check = sus & ~moved  # a moved epoch fails whatever its check says
        pos = dof > 0
        hi = np.where(moved | check, hi0 + 1, np.where(pos, 0, hi0))
        on = self._p_on[sl]
        if not check.any() and not on.any():
            self._bad[sl] = hi
            return hi
        lo0 = np.where(on, self._p_lo[sl], hi0)
        lo = np.where(moved, lo0 + 1, np.where(pos, 0, lo0))
        exact = lo == hi  # the bounds meet: the pending checks cannot matter any more
        self._drop_pending(sl[on & exact])
        new = check & ~on  # a check's bounds never meet: hi = hi0 + 1 > lo
        if new.any():
            sn = sl[new]
            self._p_on[sn] = True
            self._p_b0[sn] = lo0[new]
            self._p_after[sn] = 0
        if check.any():
            sc = sl[check]
            self._checks.append((sc, self._p_gen[sc], self._p_after[sc], pos[check],
                                 xn[check, :2], z[check]))
            self._p_after[sc] = 0
        self._p_after[sl[moved & on & ~exact]] += 1
        self._p_lo[sl[~exact]] = lo[~exact]
        need = (lo < self.settings.max_bad_epochs) & (hi >= self.settings.max_bad_epochs)
        if need.any():
            hi[need] = self._resolve(sl[need])
        self._bad[sl] = hi
        self._compact_checks()
        return hi

    def _drop_pending(self, slots: NDArray[np.int64]) -> None:
        """The pending checks of ``slots`` no longer matter (their logged rows are void)."""
        slots = slots[self._p_on[slots]]
        if slots.size:
            self._p_on[slots] = False
            self._p_gen[slots] += 1

    def _compact_checks(self) -> None:
        """Forget logged checks that no longer matter: the oldest rounds while all their
        rows are void, and everything void once the log grows long."""
        log = self._checks
        while log and not np.any(log[0][1] == self._p_gen[log[0][0]]):
            log.pop(0)
        if len(log) > 256:
            rows = [tuple(c[live] for c in e) for e in log
                    if (live := e[1] == self._p_gen[e[0]]).any()]
            self._checks = [tuple(np.concatenate(cols) for cols in zip(*rows))] if rows else []

    def _settle(self) -> None:
        """Solve every pending snapshot check: the divergence counters exact."""
        slots = np.flatnonzero(self._p_on)
        if slots.size:
            self._bad[slots] = self._resolve(slots)

    def _resolve(self, slots: NDArray[np.int64]) -> NDArray[np.int64]:
        """Solve the pending snapshot checks of ``slots`` (one batched call) and return
        their exact divergence counters; the checks are no longer pending."""
        want = np.zeros(self._p_on.shape[0], dtype=bool)
        want[slots] = True
        parts = [tuple(c[m] for c in e) for e in self._checks
                 if (m := want[e[0]] & (e[1] == self._p_gen[e[0]])).any()]
        b = self._p_b0.copy()
        if parts:
            sl_e, _, gap, reset, x2, z = (np.concatenate(c) for c in zip(*parts))
            fails = self._disagrees(x2, None, z)
            for k, g, r, f in zip(sl_e.tolist(), gap.tolist(), reset.tolist(),
                                  fails.tolist()):  # in time order
                b[k] += g
                b[k] = b[k] + 1 if f else (0 if r else b[k])
        out = b[slots] + self._p_after[slots]
        self._drop_pending(slots)
        return out

    def _protected_fix(self, z: Array) -> Any:
        """The epochs' own protected fixes: ``locate``'s default with the a-priori sigma
        (:func:`robustloc.integrity.fixes.locate_protected`: tested status and ``hpl``)."""
        from robustloc.integrity.fixes import locate_protected

        link, kw = self._link, {}
        if self._kind == "rssi":
            kw = {"A": link.A, "n": link.n}
        if self.settings.tag_height is not None:
            kw["height_offset"] = np.sqrt(link.dz2)
        return locate_protected(self._bound_locator, link.anchors_xy, z, self._kind, **kw)

    def _fix(self, z: Array) -> Any:
        s = self.settings
        link = self._link
        kw: dict[str, Any] = {}
        if self._kind == "rssi":
            kw = {"A": link.A, "n": link.n}
        if s.tag_height is not None:
            kw["height_offset"] = np.sqrt(link.dz2)
        return self._locator.solve(link.anchors_xy, z, self._kind, **kw)

    def _fix_cov(self, pos: Array, z: Array, excluded: NDArray[np.bool_]) -> Array:
        """A-priori covariance ``(J^T R^-1 J)^-1`` of fixes ``pos (K, 2)`` from the heard,
        not excluded observations ``z`` (the fix's own a-posteriori covariance scales by
        its ``sigma0``, a noisy estimate from a handful of residuals -- or 0 for a perfect
        fit).  NaN where the geometry is singular."""
        K = len(pos)
        n = self.n
        xs = np.zeros((K, n))
        xs[:, :2] = np.where(np.isfinite(pos), pos, 0.0)
        J = self._link.jacobian(xs)[:, :, :2]
        _, var = self._observations(z)
        w = np.where(np.isfinite(z) & ~excluded & np.isfinite(var), 1.0 / var, 0.0)
        N = np.einsum("kmi,km,kmj->kij", J, w, J)
        det = N[:, 0, 0] * N[:, 1, 1] - N[:, 0, 1] ** 2
        good = np.isfinite(det) & (det > 1e-12 * np.maximum(N[:, 0, 0] * N[:, 1, 1], 1e-300))
        inv = np.full((K, 2, 2), np.nan)
        dg = det[good]
        inv[good, 0, 0] = N[good, 1, 1] / dg
        inv[good, 1, 1] = N[good, 0, 0] / dg
        inv[good, 0, 1] = inv[good, 1, 0] = -N[good, 0, 1] / dg
        return inv

    def _better_fix(self, P: Array, z: Array) -> NDArray[np.bool_]:
        """True where this epoch's robust fix is usable and more certain than the filter
        (``trace C_fix < trace P_pos``)."""
        sol = self._fix(z)
        C = self._fix_cov(np.asarray(sol.position, float), z, np.asarray(sol.excluded, bool))
        tr = C[:, 0, 0] + C[:, 1, 1]
        ok = _fixed(sol.status) & np.isfinite(tr)
        return ok & (tr < P[:, 0, 0] + P[:, 1, 1])

    def _disagrees(self, x: Array, P: Array, z: Array) -> NDArray[np.bool_]:
        """True where the robust fix of the epoch is usable and the filtered position is
        outside its ``1 - alpha0`` ellipse: ``d^T C_fix^-1 d > chi2(1 - alpha0, 2)``.

        The filtered state already contains this epoch's observations, so ``d = x - x_fix``
        has a covariance near ``C_fix - P`` (Hausman), not ``C_fix + P``; ``C_fix`` alone
        bounds it and, unlike ``P + C_fix``, does not let a runaway filter with a huge
        ``P`` pass the test."""
        sol = self._fix(z)
        pos = np.asarray(sol.position, dtype=float)
        C = self._fix_cov(pos, z, np.asarray(sol.excluded, bool))
        ok = _fixed(sol.status) & np.all(np.isfinite(pos), 1)
        ok &= np.all(np.isfinite(C.reshape(len(x), -1)), axis=1)
        d = np.where(ok[:, None], x[:, :2] - pos, 0.0)
        Sm = np.where(ok[:, None, None], C, np.eye(2)[None])
        q = np.einsum("ki,ki->k", d, np.linalg.solve(Sm, d[..., None])[..., 0])
        return ok & (q > self._chi2_fix)

    def _hpl(self, H: Array, HPH: Array, Rd: Array, avail: NDArray[np.bool_], w: Array,
             Pn: Array, Pp: Array) -> Array:
        """``max_i |G_pos,i| MDB_i + k sigma_major`` (module docstring, item 8).

        EKF: the gain column of component ``i`` is ``G_i = w_i P+ H_i^T / R_ii``: the
        update's gain is the Kalman gain of the equivalent variances ``R_ii / w_i``
        (``RobustUpdate(mode="variance")``), for which ``G = P+ H^T R'^-1`` holds exactly,
        and which avoids a second factorization of ``S``.  UKF: its ``P+`` comes from the
        sigma points, for which that identity does not hold -- next to an anchor, where the
        range bends within the points' spread and an RSSI range's variance ``R_ii`` is
        small, ``P+ H_i^T / R_ii`` reached 10^3 m in a 10 m room -- so the gain is the
        linearized ``G = P- H^T S'^-1``, ``S' = H P- H^T + R'`` over the components the
        update used (``w_i > 0``), ``R'_ii = R_ii / w_i``.
        """
        K, M = avail.shape
        if self.settings.filter == "ukf" and M:
            used = avail & (w > 0)
            with np.errstate(divide="ignore"):
                Rv = np.where(used, Rd / np.where(used, w, 1.0), 1.0)  # R_ii / w_i
            S = H @ Pp @ np.swapaxes(H, 1, 2) + Rv[:, :, None] * np.eye(M)[None]
            both = used[:, :, None] & used[:, None, :]
            S = np.where(both, S, np.eye(M)[None])  # identity over unused components
            A = np.where(used[:, :, None], (H @ Pp)[:, :, :2], 0.0)  # rows: (P- H_i^T)_pos
            try:
                X = np.linalg.solve(S, A)
            except np.linalg.LinAlgError:  # a singular S of some tag: its bound unbounded
                X = np.empty_like(A)
                for k in range(K):
                    try:
                        X[k] = np.linalg.solve(S[k], A[k])
                    except np.linalg.LinAlgError:
                        X[k] = np.inf
            G = X
        else:
            wr = np.where(avail, w, 0.0) / Rd  # (K, M)
            if self.n > self.n_motion:  # the offsets' columns feed the position rows too
                G = (H @ Pn[:, :, :2]) * wr[:, :, None]
            else:
                Hp = H[:, :, :2]  # position columns
                G = (Hp @ Pn[:, :2, :2]) * wr[:, :, None]  # (K, M, 2): rows are G_pos,i^T
        gpos = np.hypot(G[:, :, 0], G[:, :, 1])
        mdb = math.sqrt(self._lam0) * np.sqrt(np.where(avail, HPH + Rd, 0.0))
        slope = np.max(np.where(avail, gpos * mdb, 0.0), axis=1) if M else np.zeros(K)
        P2 = Pn[:, :2, :2]
        tr = 0.5 * (P2[:, 0, 0] + P2[:, 1, 1])
        det = P2[:, 0, 0] * P2[:, 1, 1] - P2[:, 0, 1] ** 2
        lmax = tr + np.sqrt(np.maximum(tr * tr - det, 0.0))
        return slope + self._k_ir * np.sqrt(np.maximum(lmax, 0.0))

    # ------------------------------------------------------------------ output
    def _frame(self, epochs: Any, out: _Rows) -> pd.DataFrame:
        return track_frame(np.asarray(epochs.time, float), np.asarray(epochs.tag, object),
                           out, self.n_motion, self.anchor_ids, self.method,
                           range_offset=self.settings.range_offset)

    # ------------------------------------------------------------------ persistence
    def checkpoint(self) -> dict[str, Any]:
        """An in-memory copy of everything :meth:`step` changes, for :meth:`rollback`.

        Arrays are copied, lists, dicts and sets shallowly (their items are not changed in
        place once stored: the per-tag state lives in arrays); the rest (settings, the
        anchors' model, compiled kernels) is shared.  Cheap next to a step: about the size
        of the per-tag state, without :meth:`state_dict`'s conversion (8-10 ms for 1 000
        tags).  A service keeps one before each block, so that a block the tracker fails
        on can be rolled back and retried tag by tag (``robustloc serve --track``)."""
        return _copy_attributes(self.__dict__)

    def rollback(self, checkpoint: dict[str, Any]) -> None:
        """Return to a :meth:`checkpoint` (usable again: it is copied, not consumed).

        Raises
        ------
        TypeError
            ``checkpoint`` is not one of :meth:`checkpoint`'s (checked before anything
            changes: ``rollback({})`` left a tracker without its anchors, the API review).
        """
        if not isinstance(checkpoint, dict) or not {
                "settings", "anchor_ids", "_slot", "_history", "_x", "_P"} <= set(checkpoint):
            raise TypeError("rollback() takes what checkpoint() returned, got "
                            f"{type(checkpoint).__name__}")
        self.__dict__.clear()
        self.__dict__.update(_copy_attributes(checkpoint))

    def state_dict(self) -> dict:
        """JSON-serialisable state: settings, anchors, link kind and every tag's filter.

        Solves the snapshot checks still pending first (:meth:`_count_bad`), so the
        saved divergence counters are exact; outputs are unaffected."""
        self._settle()
        slots = np.fromiter(self._slot.values(), dtype=np.int64, count=len(self._slot))
        per_name = {}  # each array's per-tag values, converted for all tags at once
        for name in self._ARRAYS:
            a = np.asarray(getattr(self, name))[slots]
            # (explicit width: a fresh tracker's (0, ...) arrays cannot infer -1)
            flat = a.reshape(len(slots), int(np.prod(a.shape[1:], dtype=np.int64)))
            if a.dtype.kind == "f":  # Python floats; None for NaN and infinities
                obj = flat.astype(object)
                obj[~np.isfinite(flat)] = None
                flat = obj
            rows = flat.tolist()  # per tag: its values flattened (a scalar: one value)
            per_name[name[1:]] = rows if a.ndim > 1 else [r[0] for r in rows]
        tags = {str(tag): {key: rows[j] for key, rows in per_name.items()}
                for j, tag in enumerate(self._slot)}
        # the tags as given (JSON keys are strings: tags 1 and 2 came back as '1' and '2',
        # and the next step started new filters for 1 and 2 -- the API review)
        ids = [t.item() if isinstance(t, np.generic) else t for t in self._slot]
        return {"version": 1, "settings": asdict(self.settings), "anchors": list(self.anchor_ids),
                "value": self._kind, "n_states": self.n, "tags": tags, "tag_ids": ids}

    def load_state_dict(self, state: dict) -> None:
        """Restore a :meth:`state_dict` (the settings and anchors must match this tracker).

        All or nothing: a state that cannot be loaded raises ``ValueError`` and leaves the
        tracker as it was (one malformed tag had cleared it and loaded the others)."""
        if not isinstance(state, dict):
            raise TypeError(f"state must be a dict from state_dict(), got "
                            f"{type(state).__name__}")
        missing = [k for k in ("version", "settings", "anchors", "tags") if k not in state]
        if missing:
            raise ValueError("saved tracker state lacks " + ", ".join(missing))
        before = dict(self.__dict__)
        try:
            self._load_state(state)
        except (ValueError, TypeError, KeyError) as exc:
            self.__dict__.clear()
            self.__dict__.update(before)
            if isinstance(exc, KeyError):
                raise ValueError(f"saved tracker state lacks {exc}") from None
            raise

    def _load_state(self, state: dict) -> None:
        if state.get("version") != 1:
            raise ValueError(f"unsupported tracker state version {state.get('version')!r}")
        if tuple(state["anchors"]) != self.anchor_ids:
            raise ValueError("saved tracker state is for other anchors")
        now = asdict(self.settings)
        # a setting added after the state was saved (e.g. range_offset) had its default
        saved = {**{f.name: f.default for f in fields(TrackerSettings)}, **state["settings"]}
        other = [k for k in now if saved.get(k) != now[k]] + [k for k in saved if k not in now]
        if other:
            raise ValueError("saved tracker state has other settings: " + ", ".join(
                f"{k} {saved.get(k)!r} (now {now.get(k)!r})" for k in other))
        M = len(self.anchor_ids)
        self._slot = {}
        self._alloc(0, M)
        self._kind = None
        if state.get("value") is not None:
            self._setup(state["value"])
        if state.get("value") not in (None, "rssi", "range"):
            raise ValueError(f"saved tracker state's value must be 'rssi' or 'range', got "
                             f"{state.get('value')!r}")
        if state.get("value") is not None and state.get("n_states", self.n) != self.n:
            raise ValueError(f"saved tracker state has {state.get('n_states')} states per "
                             f"tag, this tracker {self.n}")
        keys = list(state["tags"])
        ids = state.get("tag_ids", keys)  # (states saved before tag_ids: the keys)
        if len(ids) != len(keys) or [str(t) for t in ids] != keys:
            raise ValueError("saved tracker state's tag_ids do not match its tags")
        sl = self._slots(np.array(ids, dtype=object))
        for key, tag, k in zip(keys, ids, sl):
            rec = state["tags"][key]
            for name in self._ARRAYS:
                a = getattr(self, name)
                if name in self._ARRAY_DEFAULTS and name[1:] not in rec:  # (older states)
                    default = self._ARRAY_DEFAULTS[name]
                    rec = {**rec, name[1:]: [None] * int(np.prod(a.shape[1:], dtype=np.int64))
                           if default is None else default}
                v = np.array([np.nan if u is None else u for u in np.ravel(rec[name[1:]])]
                             if isinstance(rec[name[1:]], list) else
                             [np.nan if rec[name[1:]] is None else rec[name[1:]]])
                if v.size != int(np.prod(a.shape[1:], dtype=np.int64)):
                    raise ValueError(f"saved state of tag {tag!r}: {name[1:]} has {v.size} "
                                     f"values, expected {a.shape[1:] or 1}")
                a[k] = v.reshape(a.shape[1:]).astype(a.dtype)
            self._check_loaded(tag, k)

    def _check_loaded(self, tag: object, k: int) -> None:
        """A loaded tag's state is one a tracker can hold: its statistics finite (only
        its last observations may be missing), its noise scale positive, its counters
        non-negative (a scale of NaN had left the tag `predicted`, a bias of NaN every
        row `predicted`, a scale of 0 `ok` rows with hpl inf: the API review).  A broken
        filter state or covariance is left to the tracker, which drops such a filter at
        the next epoch and starts the tag again from its fix (``test_track``)."""
        checks = [(name, np.isfinite(getattr(self, name)[k]).all())
                  for name in ("_bias", "_gp", "_gm", "_hsum", "_scale2")]
        checks.append(("_scale2", self._scale2[k] > 0))
        checks += [(name, (getattr(self, name)[k] >= 0).all())
                   for name in ("_hn", "_bad", "_reinit", "_susp_n")]
        checks.append(("_susp", not self._susp[k] < 0))  # (NaN: saved inf, no bound)
        for name, ok in checks:
            if not ok:
                raise ValueError(f"saved state of tag {tag!r}: {name[1:]} is not a value a "
                                 "tracker holds (not finite, or out of range)")

    # ------------------------------------------------------------------ smoothing
    def predictive_score(self, values: Any) -> tuple[Array, NDArray[np.int64]]:
        """The recorded forward pass's one-step-ahead predictive score of each row.

        For each filtered row (not a start) and each observation ``i`` it heard, the
        prediction ``h_i(x-)`` and its variance ``S_ii = (H P- H^T)_ii + s^2 sigma_i^2``
        (``sigma_i`` the anchors' a-priori sigma in the filter's domain, ``s`` the tag's
        noise scale the update used: item 6 of the module docstring) give the robust log
        score of :func:`robustloc.tracking.select.huber_log_score`.  (With ``sigma_i^2``
        alone, a log noisier than its anchors' sigma scored the filter without offsets as
        overconfident, and any extra state's spread as a gain: the review of 2026-12-07,
        offsets chosen on 9 of 10 clean logs at 3x the stated sigma.)  A higher score predicted
        the observations better: the prequential comparison of two trackers on the same
        log (Dawid 1984), as :func:`robustloc.tracking.select.choose_link_offsets` makes
        it.

        Parameters
        ----------
        values : ``(N, M)`` the recorded steps' epochs' values, in their order (the rows
            :meth:`step` was given, every step's after the earlier ones').

        Returns
        -------
        (ndarray, ndarray)
            Per row, the sum of its observations' scores (NaN where none was scored: a
            start, a coasting or invalid row) and how many were scored.

        Raises
        ------
        ValueError
            Not a recording tracker, or ``values`` not ``(rows recorded, M)``.
        """
        from robustloc.tracking.select import huber_log_score

        if not self.record:
            raise ValueError("the predictive score needs Tracker(..., record=True)")
        v = np.asarray(values, dtype=float)
        if v.shape != (self._rows_recorded, len(self.anchor_ids)):
            raise ValueError(f"values must be ({self._rows_recorded}, "
                             f"{len(self.anchor_ids)}) (the recorded rows), got {v.shape}")
        score = np.full(self._rows_recorded, np.nan)
        count = np.zeros(self._rows_recorded, dtype=np.int64)
        # every filtered (not started) row of every round at once: one vectorized pass,
        # not a Python loop over the rounds (one per epoch of a tag's log)
        parts = [(h["idx"][~h["start"]], h["xp"][~h["start"]], h["Pp"][~h["start"]],
                  h["s2"][~h["start"]] if "s2" in h else np.ones(int((~h["start"]).sum())))
                 for h in self._history if (~h["start"]).any()]
        if not parts:
            return score, count
        rows, xp, Pp, s2 = (np.concatenate(a) for a in zip(*parts))
        # a row recorded twice (a re-start after its filtered entry): its last entry
        last = len(rows) - 1 - np.unique(rows[::-1], return_index=True)[1]
        rows, xp, Pp, s2 = rows[last], xp[last], Pp[last], s2[last]
        y, var = self._observations(self._calibrate(v[rows]))
        J = self._jacobian(xp)
        S = np.einsum("kmi,kij,kmj->km", J, Pp, J) + s2[:, None] * var
        nu = y - self._predict(xp)
        ok = np.isfinite(nu) & np.isfinite(S) & (S > 0)
        sc = np.where(ok, huber_log_score(np.where(ok, nu, 0.0), np.where(ok, S, 1.0)), 0.0)
        n_ok = ok.sum(axis=1)
        score[rows] = np.where(n_ok > 0, sc.sum(axis=1), np.nan)
        count[rows] = n_ok
        return score, count

    def forget_record(self) -> None:
        """Drop what a recording tracker (``record=True``) has recorded: its filter states
        are kept, and :meth:`predictive_score` and :meth:`smoothed` then cover the steps
        after this call, their rows numbered from 0 again.  For scoring a long log in
        pieces with bounded memory (the history holds two covariance matrices per row:
        20 000 rows of 24 anchors are about 250 MB)."""
        self._history = []
        self._rows_recorded = 0

    def smoothed(self, n_rows: int, lag: int | None = None) -> tuple[Array, Array]:
        """Rauch-Tung-Striebel smoothing of the recorded forward pass (``record=True``).

        Returns smoothed states ``(n_rows, n)`` and covariances ``(n_rows, n, n)`` by row
        index of the recorded steps, numbered across them in order (the first step's rows
        from 0, the next step's after them; NaN for rows without a filter state);
        ``lag=None``: fixed interval (all later data), ``lag=N``: fixed lag (the next
        ``N`` epochs).  See :func:`robustloc.tracking.smooth.rts`.

        Raises
        ------
        ValueError
            Not a recording tracker; ``n_rows`` fewer than the recorded steps' rows;
            ``lag`` not a whole number >= 0.
        """
        from robustloc.tracking.smooth import rts_rows

        if not self.record:
            raise ValueError("smoothing needs Tracker(..., record=True)")
        if isinstance(n_rows, bool) or not isinstance(n_rows, int | np.integer) or (
                n_rows < self._rows_recorded):
            raise ValueError(f"n_rows must be a whole number >= the {self._rows_recorded} "
                             f"rows of the recorded steps, got {n_rows!r}")
        if lag is not None and (isinstance(lag, bool) or not isinstance(lag, int | np.integer)
                                or lag < 0):
            raise ValueError(f"lag must be None or a whole number >= 0, got {lag!r}")
        return rts_rows(self._history, n_rows, self.n, self._motion, lag)


def one_fault_explains(H: Array, Pp: Array, Rd: Array, y: Array, avail: NDArray[np.bool_],
                       w2_crit: float, crit_less: Array, return_index: bool = False,
                       ) -> Any:
    """Data snooping with one exclusion (seed 003): does one faulty component explain a
    failed global test?

    With ``S = H P- H^T + diag(Rd)`` over the available components and ``u = S^-1 y``,
    the w-test statistic of component ``i`` is ``w_i = u_i / sqrt((S^-1)_ii)`` and the
    innovation quadratic form without component ``i`` is ``y^T S^-1 y - w_i^2`` (the
    Schur complement of ``S``).  True where the largest ``w_i^2`` exceeds ``w2_crit`` and
    the remaining quadratic form passes ``crit_less`` (the global test's critical value
    for one component fewer).  NumPy reference of the compiled
    :func:`robustloc.tracking._compiled.one_fault_explains`.

    Parameters
    ----------
    H : ``(K, M, n)`` Jacobians at the prediction; Pp : ``(K, n, n)`` predicted covariances;
    Rd : ``(K, M)`` measurement variances; y : ``(K, M)`` innovations; avail : ``(K, M)``
        components in the update; w2_crit : squared w-test critical value;
    crit_less : ``(K,)`` critical values of the global test with one component fewer.
    return_index : also return, per row, the component that explains it (-1: none), as
        the compiled kernel does (the row lists it in ``excluded``).
    """
    K, M = avail.shape
    S = H @ Pp @ np.swapaxes(H, 1, 2) + Rd[:, :, None] * np.eye(M)[None]
    S = np.where(avail[:, :, None] & avail[:, None, :], S, np.eye(M)[None])
    Si = np.linalg.inv(S)
    y0 = np.where(avail, y, 0.0)
    u = (Si @ y0[:, :, None])[:, :, 0]
    q = np.sum(y0 * u, axis=1)
    w2 = np.where(avail, u * u / np.diagonal(Si, axis1=1, axis2=2), 0.0)
    best = w2.max(axis=1) if M else np.zeros(K)
    ok = (best > w2_crit) & (q - best <= crit_less)
    if not return_index:
        return ok
    at = np.argmax(w2, axis=1) if M else np.zeros(K, dtype=np.int64)
    return ok, np.where(ok, at, -1)


def _fixed(status: NDArray[np.object_]) -> NDArray[np.bool_]:
    """Fixes whose status is ``ok`` or ``fault_excluded`` (a usable robust fix)."""
    status = np.asarray(status, dtype=object)
    return (status == st.OK) | (status == st.FAULT_EXCLUDED)


def _prediction_lost(v_pos: Array, r_min: Array, lost_pos_var: float) -> NDArray[np.bool_]:
    """A meaningless prediction (module docstring, item 9): position variance ``v_pos =
    var_x + var_y`` beyond ``lost_pos_var`` and ``sqrt(eps) v_pos >= r_min`` (the smallest
    variance of the update's components: ``S = H P- H^T + R`` keeps fewer than half of the
    digits of ``R``); NaN is lost.  NumPy twin of the compiled
    :func:`robustloc.tracking._compiled.prediction_lost`."""
    with np.errstate(invalid="ignore"):
        return ~((v_pos <= lost_pos_var) | (v_pos * _SQRT_EPS < r_min))


def _finite_moments(x: Array, P: Array) -> NDArray[np.bool_]:
    """Updated moments that are usable: ``x (K, n)`` and ``P (K, n, n)`` finite, and no
    negative variance on the diagonal of ``P`` (an update whose arithmetic failed).  The
    compiled kernel checks the same (:mod:`robustloc.tracking._compiled`)."""
    return (np.isfinite(x).all(axis=1) & np.isfinite(P).all(axis=(1, 2))
            & (np.diagonal(P, axis1=1, axis2=2) >= 0.0).all(axis=1))


#: Status of the fused kernel's codes (:data:`robustloc.tracking._compiled.CODES`).
_CODE_STATUS = np.array([st.OK, st.FAULT_EXCLUDED, st.PREDICTED], dtype=object)


def _rank_within(slots: NDArray[np.int64]) -> NDArray[np.int64]:
    """Position of each entry among the earlier entries with the same slot (0, 1, ...)."""
    order = np.argsort(slots, kind="stable")
    ss = slots[order]
    first = np.r_[True, ss[1:] != ss[:-1]]
    start = np.maximum.accumulate(np.where(first, np.arange(len(ss)), 0))
    rank = np.empty(len(ss), dtype=np.int64)
    rank[order] = np.arange(len(ss)) - start
    return rank


class _Rows:
    """Output buffers of one :meth:`Tracker.step` call."""

    FIELDS = ("x", "var", "cxy", "status", "n_used", "nis", "excluded", "hpl", "scale",
              "reinit")

    def __init__(self, N: int, n: int, M: int) -> None:
        self.x = np.full((N, n), np.nan)
        self.var = np.full((N, n), np.nan)
        self.cxy = np.full(N, np.nan)
        self.status = np.full(N, st.INVALID, dtype=object)
        self.n_used = np.zeros(N, dtype=np.int64)
        self.nis = np.full(N, np.nan)
        self.excluded = np.zeros((N, M), dtype=bool)
        self.hpl = np.full(N, np.nan)
        self.scale = np.full(N, np.nan)
        self.reinit = np.zeros(N, dtype=np.int64)


def track_frame(time: Array, tag: NDArray[np.object_], out: _Rows, n: int,
                anchor_ids: tuple[str, ...], method: str,
                range_offset: bool = False) -> pd.DataFrame:
    """The track table: ``time, tag, x, y, vx, vy[, ax, ay], method, status, var_x,
    var_y, cov_xy, var_vx, var_vy, hpl, n_used, nis, noise_scale, reinit, excluded`` and,
    with ``range_offset`` (the state's last component), ``range_offset,
    var_range_offset`` (m, m^2).  ``n``: the kinematic states."""
    data: dict[str, Any] = {"time": time, "tag": tag, "x": out.x[:, 0], "y": out.x[:, 1]}
    vel = n >= 4
    data["vx"] = out.x[:, 2] if vel else np.where(np.isfinite(out.x[:, 0]), 0.0, np.nan)
    data["vy"] = out.x[:, 3] if vel else np.where(np.isfinite(out.x[:, 0]), 0.0, np.nan)
    if n >= 6:
        data["ax"], data["ay"] = out.x[:, 4], out.x[:, 5]
    data["method"] = np.full(len(time), method, dtype=object)  # (a scalar: +0.7 ms/1 000)
    data["status"] = out.status
    data["var_x"], data["var_y"], data["cov_xy"] = out.var[:, 0], out.var[:, 1], out.cxy
    data["var_vx"] = out.var[:, 2] if vel else np.where(np.isfinite(out.x[:, 0]), 0.0, np.nan)
    data["var_vy"] = out.var[:, 3] if vel else np.where(np.isfinite(out.x[:, 0]), 0.0, np.nan)
    data["hpl"] = out.hpl
    data["n_used"] = out.n_used
    data["nis"] = out.nis
    data["noise_scale"] = out.scale
    data["reinit"] = out.reinit
    data["excluded"] = _joined(out.excluded, anchor_ids)
    if range_offset:
        data["range_offset"] = out.x[:, -1]
        data["var_range_offset"] = out.var[:, -1]
    return pd.DataFrame(data)


def _joined(mask: NDArray[np.bool_], names: tuple[str, ...]) -> NDArray[np.object_]:
    """Per row, the ``names`` where ``mask (N, M)`` is True joined by ``;`` (``""`` if
    none).  Each distinct row pattern is joined once (few patterns, many rows)."""
    N, M = mask.shape
    out = np.full(N, "", dtype=object)
    rows = np.flatnonzero(mask.any(axis=1)) if M else np.zeros(0, dtype=np.int64)
    if rows.size == 0:
        return out
    ids = np.asarray(names, dtype=object)
    sub = mask[rows]
    if M <= 62:  # the row's bits as one integer key
        key = sub.astype(np.int64) @ (np.int64(1) << np.arange(M, dtype=np.int64))
        _, first, inv = np.unique(key, return_index=True, return_inverse=True)
    else:
        _, first, inv = np.unique(np.packbits(sub, axis=1), axis=0, return_index=True,
                                  return_inverse=True)
    text = np.array([";".join(ids[sub[f]]) for f in first], dtype=object)
    out[rows] = text[inv.ravel()]
    return out


def _copy_attributes(attrs: dict[str, Any]) -> dict[str, Any]:
    """``attrs`` with arrays copied and lists, dicts and sets copied shallowly
    (:meth:`Tracker.checkpoint`)."""
    out: dict[str, Any] = {}
    for k, v in attrs.items():
        if isinstance(v, np.ndarray):
            out[k] = v.copy()
        elif isinstance(v, (list, dict, set)):
            out[k] = type(v)(v) if not isinstance(v, dict) else dict(v)
        else:
            out[k] = v
    return out
