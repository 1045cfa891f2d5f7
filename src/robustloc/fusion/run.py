"""End-to-end fusion of contract frames: ranges + anchors (+ NMEA) -> track frame.

Used by ``robustloc fuse``, the ``uwb_gps`` report section and the real-data loaders.
Loose coupling: per UWB epoch an LS/WLS fix (:mod:`robustloc.fusion.uwb`) with the
diagonal of its covariance as ``R`` (seed 001's ``R = diag(...)``: the fix's x-y
correlation is not used); tight coupling: the ranges themselves (:mod:`robustloc.fusion.pipeline`).
GPS speed and course (RMC/VTG) join as further components.  Streams are aligned as
documented in :mod:`robustloc.fusion.align`.

Plausibility at the door (:mod:`robustloc.io.limits`): a range outside the ``range`` limits
(-50 .. 1e5 m; NaN or infinite included) or a GPS speed outside ``speed`` is an *invalid
measurement*: it is counted (``summary["invalid_measurement"]``), set aside before any fix
or filter update, and its event still gets a row -- with status ``invalid_measurement``
when nothing valid arrived with it (the row then carries the filter's prediction).  A
time outside the ``time`` limits (``|t| < 1e12`` s; ranges, or NMEA times plus the offset)
cannot be placed on the timeline: such rows are counted (``invalid["time"]``), never reach
the filter, and each (tag, time) gets an ``invalid_measurement`` row without a state, as in
``robustloc locate``.

Honest statuses (consistent with ``robustloc locate``): ranges alone fix a 2-D position
only from three anchors that are not collinear.  An event is ``ok`` / ``fault_excluded``
only when the anchors heard by its tag within ``geometry_window_s`` (the event's own and
the preceding ranges) span such a layout; otherwise it is ``insufficient_anchors`` (fewer
than three distinct anchors) or ``ill_conditioned`` (three or more, but all at one point or
on one line -- the anchors' scatter matrix fails the condition test of
:func:`robustloc.estimators._kernels.inv_spd`).  The filtered state is still written on
such rows, with a position covariance that also covers the position the ranges cannot
tell from it (:func:`_cover_mirror`); GPS speed and course (velocity only) cannot make the
position observable.  These two qualify an *updated* row that passed its test: a failed
test (``fault_detected``, ``unavailable``) keeps its status.  A tag whose first ranges
come from anchors on one line (two) starts at each of the two positions they allow and
keeps the run with the smaller sum of NIS (:func:`_mirror_starts`).
A row that nothing updated is ``predicted`` in either
coupling, whatever its anchors (its state is the motion model's prediction, ``n_used`` 0):
a lost track's coasting rows, and in loose coupling every event of one or two anchors
without GPS -- loose coupling has no fix from them, where tight coupling updates with the
ranges themselves (so the same epoch is ``insufficient_anchors`` in tight and ``predicted``
in loose coupling: the rows' states differ).  ``invalid_measurement`` is an event whose
values were *all* outside their limits; one with a valid range left unused is
``predicted``.
An event of one or two components whose update kept none (all rejected, ``n_used`` 0) is
``predicted`` too, whatever its anchors (one of three or more is ``unavailable``).  In
loose coupling an ``ok`` event whose fix failed its own test (:func:`fix_test_status`,
``locate``'s) is ``fault_detected``.  An anchor far outside the others
(:func:`robustloc.estimators.ranging._sane_anchors`, as in ``locate`` and ``track``) is
not used; ``summary["anchors_not_used"]`` names it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from robustloc import status as st
from robustloc.errors import InputError
from robustloc.fusion.align import Stream, merge_streams
from robustloc.fusion.pipeline import (
    FusionFilter,
    FusionMeasurement,
    gps_velocity,
    initial_state,
)
from robustloc.fusion.uwb import fix_test_status, range_sigma, uwb_fix
from robustloc.io.limits import LIMITS
from robustloc.io.nmea import NmeaLog

Array = NDArray[np.float64]

#: Largest growth ``k`` of the range std with distance, ``sigma = s0 + k d``: at ``k = 1``
#: a range's std is the range itself (it says nothing more of the position); 1e300
#: overflowed to infinite variances (the filter/fuse review).
RANGE_K_MAX = 1.0


@dataclass(frozen=True)
class FuseOptions:
    """Settings of :func:`fuse` (defaults tuned on simulation, documented in the CLI help).

    Parameters
    ----------
    coupling : ``"loose"`` (UWB fixes) or ``"tight"`` (raw ranges).
    fix_method : ``"ls"``, ``"wls"`` or ``"nls"`` (Gauss-Newton) UWB fixes (loose coupling).
    sigma_range_m, range_k : range noise ``sigma0 + k d`` (m, -).
    sigma_speed_mps, sigma_course_deg : GPS speed and course noise.
    nmea_offset_s : added to NMEA times to reach the ranges' clock; ``None`` (default):
        automatic -- POSIX time (``NmeaLog.day0_posix_s``) when the ranges' times look like
        POSIX seconds (median above 1e8) and the log has a dated RMC, else 0 (simulated
        logs: NMEA time of day 0 = time 0 of the ranges).
    merge_window_s : a time stamp at most this long after an event's first one joins it,
        unless it repeats a measured component (an anchor's range, a GPS speed) the event
        already holds (:mod:`robustloc.fusion.align`, step 2).
    tag_height_m : tag height for slant-range correction when anchors have ``z``.
    init_var_m2 : initial position variance.
    init_acc_var : initial acceleration variance (CA), (m/s^2)^2.
    geometry_window_s : ranges heard within this many seconds before an event (inclusive)
        make up the anchor layout that decides whether the event's position can be ``ok``
        (module docstring).  1 s holds a full round of any UWB/RTT ranging schedule.
    nmea_tags : the tags that carry the GPS receiver of the NMEA log (its speed and course
        are fused into their tracks only); ``None`` (default): every tag.
    """

    coupling: Literal["loose", "tight"] = "tight"
    fix_method: Literal["ls", "wls", "nls"] = "nls"
    sigma_range_m: float = 0.15
    range_k: float = 0.0
    sigma_speed_mps: float = 0.05
    sigma_course_deg: float = 5.0
    nmea_offset_s: float | None = None
    merge_window_s: float = 0.02
    tag_height_m: float | None = None
    init_var_m2: float = 4.0
    init_acc_var: float = 0.01
    geometry_window_s: float = 1.0
    nmea_tags: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        from robustloc.options import SIGMA_RANGE

        if self.coupling not in ("loose", "tight"):
            raise ValueError(f"coupling must be 'loose' or 'tight', got {self.coupling!r}")
        for name in ("sigma_range_m", "sigma_speed_mps", "sigma_course_deg", "init_var_m2"):
            if not np.isfinite(getattr(self, name)) or not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive and finite")
        for name in ("range_k", "merge_window_s", "geometry_window_s", "init_acc_var"):
            if not np.isfinite(getattr(self, name)) or getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0 and finite")
        # a-priori stds as everywhere (SIGMA_RANGE; the command line's bounds)
        lo, hi = SIGMA_RANGE
        for name in ("sigma_range_m", "sigma_speed_mps"):
            if not lo <= getattr(self, name) <= hi:
                raise ValueError(f"{name} must lie in [{lo:g}, {hi:g}], got "
                                 f"{getattr(self, name)}")
        if self.range_k > RANGE_K_MAX:
            raise ValueError(f"range_k must lie in [0, {RANGE_K_MAX:g}], got {self.range_k}")
        # the offset moves NMEA times onto the ranges' clock, whose times lie within the
        # time limits of robustloc.io.limits
        if self.nmea_offset_s is not None and not LIMITS["time"].check(self.nmea_offset_s):
            raise ValueError("nmea_offset_s must be finite, within +-1e12 s")


@dataclass(frozen=True)
class FuseResult:
    """Track frame (contract ``track`` columns) plus a run summary."""

    track: pd.DataFrame
    summary: dict = field(default_factory=dict)


def _anchor_arrays(anchors: pd.DataFrame, opts: FuseOptions) -> tuple[Array, Array | None]:
    a = anchors[["x", "y"]].to_numpy(float)
    if "z" in anchors.columns and opts.tag_height_m is not None:
        return a, anchors["z"].to_numpy(float) - opts.tag_height_m
    return a, None



#: A two-anchor start's other side (the mirror image across the anchors' line) is kept
#: only when its run's sum of NIS is smaller by more than this: ``chi2(0.99; 1)``, the
#: likelihood-ratio test of one discrete alternative at 1 %.  Without GPS the two mirror
#: runs fit about equally, and the smaller sum was a coin flip: a tag on the site's side
#: went to the other (9.9 m median error against 0.14 m; the review of the fix).
MIRROR_SIDE_NIS = 6.635

def fuse(
    measurements: pd.DataFrame,
    anchors: pd.DataFrame,
    nmea: NmeaLog | pd.DataFrame | None,
    filt: FusionFilter,
    opts: FuseOptions = FuseOptions(),
    progress: bool = False,
) -> FuseResult:
    """Fuse UWB ranges (and GPS speed/course) of every tag into tracks.

    Parameters
    ----------
    measurements : ``time, tag, anchor, range`` (contract measurements frame).
    anchors : ``anchor, x, y[, z]``.
    nmea : parsed NMEA (its ``motion`` rows go to every tag), or directly a motion frame
        ``time_s, speed_mps, course_rad`` (e.g. wheel odometry speed, course NaN), or None.
    filt : the filter settings (EKF/UKF, motion model, robust update).
    opts : coupling and noise settings.

    Returns
    -------
    FuseResult
        ``track``: one row per fused event and tag: ``time, tag, x, y, vx, vy[, ax, ay],
        status, var_x, var_y, var_vx, var_vy[, var_ax, var_ay], n_used, nis, source``.
    """
    if "range" not in measurements.columns:
        raise InputError("fusion needs a 'range' column in the measurements")
    ids = [str(a) for a in anchors["anchor"]]
    col = pd.Index(ids).get_indexer(measurements["anchor"].astype(str))
    if (col < 0).any():
        bad = measurements["anchor"].astype(str)[col < 0].iloc[0]
        raise InputError(f"unknown anchor id {bad!r} (not in the anchors)")
    a_xy, dz = _anchor_arrays(anchors, opts)
    M = len(ids)
    # an anchor far outside the others (a typo: a coordinate in mm, 1e200) is not used, as
    # locate and track leave it out (estimators.ranging._sane_anchors), and is named: the
    # filter hung on its ranges and wrote every row fault_excluded 7 km off (the filter/
    # fuse review).  Its coordinates become the others' centroid so that no arithmetic
    # (the range model of every component, the layout's scatter) meets them
    from robustloc.estimators.ranging import _sane_anchors

    dims = [c for c in ("x", "y", "z") if c in anchors.columns]
    far = ~_sane_anchors(anchors[dims].to_numpy(dtype=float))
    if far.any():
        a_xy = np.where(far[:, None], a_xy[~far].mean(axis=0), a_xy)
        dz = None if dz is None else np.where(far, 0.0, dz)
    n = filt.motion.n_states
    t = measurements["time"].to_numpy(float)
    tags = measurements["tag"].astype(str).to_numpy(object)
    all_tags = np.unique(tags.astype(str))
    # GPS speed and course go to every tag, or to the tags that carry the receiver
    gps_tags = (all_tags if opts.nmea_tags is None
                else all_tags[np.isin(all_tags, np.asarray(opts.nmea_tags, dtype=str))])
    rng_m = measurements["range"].to_numpy(float)
    # plausibility at the door: a time outside the limits (|t| < 1e12 s) cannot be placed
    # on the timeline (a filter step over 1e300 s overflows): its rows are set aside and
    # get one invalid_measurement row per (tag, time), as in locate
    bad_time = ~LIMITS["time"].check(t)
    aside = [pd.DataFrame({"time": t[bad_time], "tag": tags[bad_time], "source": "uwb"})]
    if bad_time.any():
        keep = ~bad_time
        t, tags, col, rng_m = t[keep], tags[keep], col[keep], rng_m[keep]
    if {"bias", "scale"} & set(anchors.columns):  # per-anchor range calibration
        from robustloc.models.calibration import apply_range_calibration

        one = np.full((len(rng_m), M), np.nan)
        one[np.arange(len(rng_m)), col] = rng_m
        rng_m = apply_range_calibration(anchors, one)[np.arange(len(rng_m)), col]
    # plausibility at the door: an absurd range never reaches a fix or the filter
    bad_range = ~LIMITS["range"].check(rng_m)
    rng_m = np.where(bad_range | far[col], np.nan, rng_m)  # (a far anchor's: not heard)
    flag = np.where(bad_range, 1.0, np.nan)[:, None]  # invalid marker, NaN = valid
    ones = np.ones((len(t), 1))
    # rows of one (time, tag, anchor) are averaged into one range (fusion.align, step 3),
    # as locate and filter average them: counted and said, as they say it
    used = np.isfinite(rng_m)
    n_dup = int(pd.DataFrame({"t": t[used], "tag": tags[used], "a": col[used]})
                .duplicated().sum())

    streams: list[Stream] = []
    summary: dict = {"coupling": opts.coupling, "filter": filt.kind, "motion": filt.motion.name,
                     "anchors_not_used": [a for a, f in zip(ids, far) if f],
                     "duplicates_merged": n_dup}
    # Columns of the merged vector after the m filter components: an always-present event
    # marker (so that an event whose values are all invalid still gets its row), the
    # invalid marker and, for loose coupling, the fix variances and the anchors heard.
    if opts.coupling == "tight":
        m = M + 2
        c_mark, c_inv = m, m + 1
        m_aug = m + 2
        vals = np.full((len(t), M), np.nan)
        vals[np.arange(len(t)), col] = rng_m
        streams.append(Stream(t, tags, np.concatenate([vals, ones, flag], axis=1),
                              [*range(M), c_mark, c_inv]))
        meas = FusionMeasurement(n, a_xy, dz)
    else:
        m = 4
        c_var, c_mark, c_inv, c_fail, c_heard = 4, 6, 7, 8, 9
        m_aug = c_heard + M
        # UWB epochs: rows with the same (tag, time within the window) form one fix epoch
        tl_u = merge_streams(
            [Stream(t, tags, np.concatenate([_one_hot(len(t), M, col, rng_m), flag], axis=1),
                    [*range(M), M])], M + 1, opts.merge_window_s, distinct=range(M),
        )
        K, J = tl_u.time_s.shape
        flat = tl_u.z.reshape(K * J, M + 1)
        live = np.isfinite(tl_u.time_s.reshape(-1))
        fix = uwb_fix(a_xy, flat[live, :M], opts.fix_method, dz, opts.sigma_range_m,
                      opts.range_k)
        summary["fixes"] = int(np.isfinite(fix.position).all(axis=1).sum())
        summary["uwb_epochs"] = int(live.sum())
        # the fix's own test, locate's (fix_test_status): one whose ranges disagree (an
        # anchor's coordinates 3 m off: every row was ok, where tight coupling and locate
        # said fault_detected; the filter/fuse review) marks its event
        fix_st = fix_test_status(a_xy, flat[live, :M], fix, opts.fix_method, dz,
                                 opts.sigma_range_m, opts.range_k)
        failed = np.where(st.among(fix_st, (st.FAULT_DETECTED, st.UNAVAILABLE)), 1.0, np.nan)
        tag_rep = np.repeat(tl_u.tags, J)[live]
        heard = np.where(np.isfinite(flat[live, :M]), 1.0, np.nan)
        # x, y, the fix variances, the epoch marker (an epoch without a fix still gets its
        # predicted row), the invalid marker, the failed-test marker and the anchors heard
        v = np.concatenate(
            [fix.position, np.diagonal(fix.covariance, axis1=1, axis2=2),
             np.ones((len(fix.status), 1)), flat[live, M:], failed[:, None], heard], axis=1,
        )
        streams.append(Stream(tl_u.time_s.reshape(-1)[live], tag_rep, v,
                              [0, 1, c_var, c_var + 1, c_mark, c_inv, c_fail,
                               *range(c_heard, c_heard + M)]))
        meas = FusionMeasurement(n)
    invalid = {"range": int(bad_range.sum()), "time": int(bad_time.sum())}
    mo = nmea.motion if isinstance(nmea, NmeaLog) else nmea
    if isinstance(nmea, NmeaLog):
        invalid["speed"] = int(nmea.summary.invalid.get("speed", 0))
        invalid["course"] = int(nmea.summary.invalid.get("course", 0))
        invalid["nmea_sentence"] = int(nmea.summary.skipped.get("invalid_measurement", 0))
    if mo is not None and len(mo):
        spd = mo["speed_mps"].to_numpy(float)
        crs = mo["course_rad"].to_numpy(float)
        bad_spd = ~np.isnan(spd) & ~LIMITS["speed"].check(spd)
        bad_crs = ~np.isnan(crs) & ~(np.abs(crs) <= 2.0 * np.pi)
        if bad_spd.any() or bad_crs.any():  # a motion frame given directly (Python API)
            invalid["speed"] = invalid.get("speed", 0) + int(bad_spd.sum())
            invalid["course"] = invalid.get("course", 0) + int((bad_crs & ~bad_spd).sum())
            mo = mo.assign(speed_mps=np.where(bad_spd, np.nan, spd),
                           course_rad=np.where(bad_spd | bad_crs, np.nan, crs))
    if isinstance(nmea, NmeaLog) and (mo is None or not len(mo)):
        # a log of GGA sentences only: "used GGA 51" was printed over rows all of source
        # uwb -- nothing of it is fused (the fuse review)
        summary.setdefault("warnings", []).append(
            "the log has no RMC or VTG sentence with a speed or course: nothing of it is "
            "fused (GGA positions are not used)")
    offset = opts.nmea_offset_s
    if offset is None:
        day0 = nmea.day0_posix_s if isinstance(nmea, NmeaLog) else None
        offset = day0 if (day0 is not None and len(t) and np.median(t) > 1e8) else 0.0
    summary["nmea_offset_s"] = float(offset)
    if mo is not None and len(mo):
        g_t = mo["time_s"].to_numpy(float) + offset
        bad_gt = ~LIMITS["time"].check(g_t)
        if bad_gt.any():  # a sentence's time on the ranges' clock beyond the limits
            invalid["time"] += int(bad_gt.sum())
            for tg in gps_tags:
                aside.append(pd.DataFrame({"time": g_t[bad_gt], "tag": tg, "source": "gps"}))
            mo = mo[~bad_gt]
    if mo is not None and len(mo) and np.isfinite(t).any():
        # GPS sentences all outside the ranges' span: nothing of the log is fused (a log of
        # another day, a missing --nmea-offset), which went without a word (the filter/
        # fuse review: 48 sentences a day away, "ok 51, predicted 48")
        g_t = mo["time_s"].to_numpy(float) + offset
        t0, t1 = float(np.nanmin(t)), float(np.nanmax(t))
        if not np.any((g_t >= t0 - opts.merge_window_s) & (g_t <= t1 + opts.merge_window_s)):
            summary.setdefault("warnings", []).append(
                f"no GPS sentence falls within the ranges' time span ({t0:.6g} .. {t1:.6g} "
                f"s): on the ranges' clock (offset {offset:.6g} s) they lie at "
                f"{float(g_t.min()):.6g} .. {float(g_t.max()):.6g} s, so no speed or course "
                "is fused; --nmea-offset S aligns the two clocks")
    if mo is not None and len(mo):
        ut = gps_tags
        gv = mo[["speed_mps", "course_rad"]].to_numpy(float)
        # a sentence whose speed was invalid (NaN speed) marks its event as invalid
        g_flag = np.where(np.isnan(gv[:, :1]), 1.0, np.nan)
        gv = np.concatenate([gv, np.ones((len(gv), 1)), g_flag], axis=1)
        for tg in ut:
            streams.append(
                Stream(mo["time_s"].to_numpy(float), np.full(len(mo), tg, dtype=object),
                       gv, [m - 2, m - 1, c_mark, c_inv], offset)
            )
    summary["invalid"] = invalid
    summary["invalid_measurement"] = int(sum(invalid.values()))
    # the measured components (ranges or fixes with the anchors they heard, speed, course)
    # come once per event: a second value of one is the next epoch (align, step 2)
    distinct = ([*range(M), m - 2, m - 1] if opts.coupling == "tight"
                else [*range(m), *range(c_heard, c_heard + M)])
    # the course (m - 1) of an RMC and a VTG sentence of one fix: a circular mean
    tl = merge_streams(streams, m_aug, opts.merge_window_s, distinct=distinct,
                       angles=[m - 1])
    K, J = tl.time_s.shape
    z = tl.z[..., :m]
    # per-event diagonal R
    Rd = np.empty((K, J, m))
    if opts.coupling == "tight":
        Rd[..., :M] = range_sigma(np.nan_to_num(z[..., :M]), opts.sigma_range_m, opts.range_k) ** 2
    else:
        fv = tl.z[..., c_var : c_var + 2]
        Rd[..., :2] = np.where(np.isfinite(fv), fv, 1.0)
        z[..., :2] = np.where(np.isfinite(fv), z[..., :2], np.nan)
    Rd[..., m - 2] = opts.sigma_speed_mps**2
    Rd[..., m - 1] = np.deg2rad(opts.sigma_course_deg) ** 2

    heard = (np.isfinite(z[..., :M]) if opts.coupling == "tight"
             else np.isfinite(tl.z[..., c_heard : c_heard + M]))
    x0pos, has, fixes, alt = _initial_positions(tl, z, opts, a_xy, dz, M, heard)
    x0, P0 = initial_state(x0pos, n, opts.init_var_m2, acc_var=opts.init_acc_var)
    # a track whose prediction is lost (a long gap), or that started without a position,
    # restarts from its event's fix with the initial covariance of a track that has one,
    # and with its event's GPS velocity as below where it has one, else at rest with the
    # velocity variance of a start without GPS (FusionFilter.run, Notes).  It had the
    # first event's: fitted to a speed measured before the gap
    P_restart = P0.copy()
    # a track whose first event carries a GPS speed (at least min_speed_mps) and course
    # starts with that velocity, not at rest: at rest the speed and course rows of the
    # Jacobian are 0, and the velocity's first updates overshoot (0.38 m/s for 0.2 on a
    # simulated cart), so the innovation test failed on its events 2-5 (FusionFilter.run)
    if K * J:
        # course clockwise from north; its variance per axis the speed's plus the
        # course's across the track, v sigma_c (as a restart takes it)
        v, var_v, moving = gps_velocity(z[:, 0, m - 2], z[:, 0, m - 1], Rd[:, 0, m - 2],
                                        Rd[:, 0, m - 1], filt.min_speed_mps)
        x0[moving, 2:4] = v[moving]
        P0[moving, 2, 2] = P0[moving, 3, 3] = var_v[moving]
    # a track without a position starts wide; one at a two-anchor start (_mirror_starts)
    # is placed by its ranges as a fix places it, but for the side (run both, below):
    # from 1e4 m^2 the UKF's sigma points (200 m out) straddled the anchors (24 m median
    # error, 548 m max on the two-anchor cart; the fuse review, finding 2)
    wide = ~has & ~np.isfinite(alt).all(axis=1)
    P0[wide, 0, 0] = P0[wide, 1, 1] = 1e4
    tr = filt.run(tl.time_s, z, Rd, meas, x0, P0, progress=progress, restart=fixes,
                  P_restart=P_restart, placed=has)
    # a tag that starts on a line of anchors (two heard) has two starts, mirror images:
    # the other is run too, and the run whose innovations are smaller in sum (NIS: GPS
    # course tells the sides apart, a track on the wrong side fails the test) is kept.
    # From the file's centroid, on the side of an anchor never heard, the cart's track
    # kept to the mirror side: 3.3 m median error (the fuse review, finding 2)
    amb = np.flatnonzero(np.isfinite(alt).all(axis=1))
    summary["mirror_starts"] = int(amb.size)
    sided = np.zeros(len(x0), dtype=bool)  # tags whose side the two runs' fits told
    if amb.size:
        x0b = x0[amb].copy()
        x0b[:, :2] = alt[amb]
        tr_b = filt.run(tl.time_s[amb], z[amb], Rd[amb], meas, x0b, P0[amb],
                        restart=fixes[amb], P_restart=P_restart[amb], placed=has[amb])
        score_a = np.nansum(tr.nis[amb], axis=1)
        score_b = np.nansum(tr_b.nis, axis=1)
        other = score_b < score_a - MIRROR_SIDE_NIS
        sided[amb] = np.abs(score_b - score_a) > MIRROR_SIDE_NIS
        tr = _take_tracks(tr, tr_b, amb[other], other)

    layout = _layout_status(tl.time_s, heard, a_xy, opts.geometry_window_s)
    if opts.coupling == "tight":  # (loose coupling's filter never sees two ranges)
        tr = _cover_mirror(tr, _recent_anchors(tl.time_s, heard, opts.geometry_window_s),
                           layout, a_xy, sided)
    status = np.asarray(tr.status, dtype=object).copy()
    if tr.time_s.size:
        # an update that kept no component (every one rejected: n_used 0, a GPS speed or
        # course kept counts) left the prediction: predicted, never ok / fault_excluded,
        # and before the layout -- insufficient_anchors and ill_conditioned qualify an
        # updated row (an event of two anchors whose two ranges were both rejected said
        # insufficient_anchors over the prediction: the fuse status review).  An
        # event of three or more components that kept none stays unavailable
        status = np.where(st.among(status, (st.OK, st.FAULT_EXCLUDED)) & (tr.n_used == 0),
                          st.PREDICTED, status)
        if opts.coupling == "loose":  # a fused fix that failed its own test
            status = np.where((status == st.OK) & np.isfinite(tl.z[..., c_fail]),
                              st.FAULT_DETECTED, status)
        # the layout qualifies a row that passed its test (ok, fault_excluded): a failed
        # test (fault_detected, unavailable) says more -- the filter and the event's
        # measurements disagree -- and keeps its status.  Replaced, it hid NIS 14 000 (a
        # +20 m range) under insufficient_anchors while the warning named fault_detected
        # rows (the fuse review, finding 1)
        fixed = st.among(status, (st.OK, st.FAULT_EXCLUDED)) & (tr.n_used > 0)
        status = np.where(fixed & (layout != ""), layout, status)
        # nothing valid arrived with the event: its own input was unusable.  Not an event
        # with a valid value that nothing used -- loose coupling's one or two ranges, no fix
        # to update with: predicted, as without the invalid one (it said
        # invalid_measurement; the filter/fuse review 4)
        own = heard.any(axis=-1) | np.isfinite(z[..., m - 2 :]).any(axis=-1)
        bad_event = np.isfinite(tl.z[..., c_inv]) & ~own & (status == st.PREDICTED)
        status = np.where(bad_event, st.INVALID, status)
    frame = _track_frame(tl.tags, tl.time_s, tr, filt, z, m, opts, status)
    frame = _with_set_aside(frame, pd.concat(aside, ignore_index=True), fusion_method(filt))
    summary["rejected_updates"] = int(np.sum(tr.extra.get("nonfinite", 0)))
    summary["restarts"] = int(np.sum(tr.extra.get("restarts", 0)))
    summary["diverged"] = int(np.sum(tr.extra.get("diverged", 0)))
    # the rows written: the fused events and the set-aside (tag, time) rows of times
    # outside the limits ("fused 4 events" was said over 5 rows: the filter/fuse review)
    summary["events"] = int(len(frame))
    summary["tags"] = int(frame["tag"].nunique())
    summary["status"] = frame["status"].value_counts().to_dict()
    return FuseResult(track=frame, summary=summary)


def fusion_method(filt: FusionFilter) -> str:
    """The ``method`` column of a fused track, as ``track`` names its rows: ``fuse-cv-ukf``,
    ``fuse-ca-ekf``, ..."""
    return f"fuse-{'cv' if filt.motion.n_states == 4 else 'ca'}-{filt.kind}"


def _with_set_aside(frame: pd.DataFrame, aside: pd.DataFrame, method: str) -> pd.DataFrame:
    """``frame`` with one ``invalid_measurement`` row per distinct (tag, time, source) of
    the rows ``aside`` (times outside the limits), in tag then time order.

    Their state is NaN: the filter never saw them (like ``locate``'s rows of such epochs).
    """
    if aside.empty:
        return frame
    rows = aside.drop_duplicates(["tag", "time", "source"])
    add = pd.DataFrame({c: np.full(len(rows), np.nan) for c in frame.columns})
    add["time"] = rows["time"].to_numpy(float)
    add["tag"] = rows["tag"].astype(str).to_numpy(object)
    add["status"] = st.INVALID
    add["method"] = method
    add["n_used"] = 0
    add["source"] = rows["source"].to_numpy(object)
    out = pd.concat([frame, add.astype({"n_used": frame["n_used"].dtype})],
                    ignore_index=True)
    # the filtered rows are already in tag, time order: a stable sort only places the rest
    order = np.lexsort((out["time"].to_numpy(float), out["tag"].astype(str).to_numpy()))
    return out.iloc[order].reset_index(drop=True)


def _one_hot(L: int, M: int, col: NDArray[np.int64], v: Array) -> Array:
    out = np.full((L, M), np.nan)
    out[np.arange(L), col] = v
    return out


def _take_tracks(tr, tr_b, rows: NDArray[np.int64], pick: NDArray[np.bool_]):
    """``tr`` with the tracks ``rows`` replaced by ``tr_b``'s tracks ``pick`` (``tr_b``
    ran on a subset of ``tr``'s tags, in order)."""
    from dataclasses import replace

    if rows.size == 0:
        return tr
    out = {}
    for name in ("time_s", "x", "var", "status", "n_used", "nis", "weights", "P_last",
                 "cov_xy"):
        v = getattr(tr, name)
        if v is None:
            continue
        v = v.copy()
        v[rows] = getattr(tr_b, name)[pick]
        out[name] = v
    extra = {}
    for k, v in tr.extra.items():
        vb = tr_b.extra.get(k)
        if isinstance(v, np.ndarray) and isinstance(vb, np.ndarray) and v.shape[:1] == (
                len(tr.time_s),):
            v = v.copy()
            v[rows] = vb[pick]
        extra[k] = v
    return replace(tr, extra=extra, **out)


def _mirror_starts(time_s: Array, z: Array, a_xy: Array, dz: Array | None,
                   start: NDArray[np.bool_], window_s: float) -> tuple[Array, Array]:
    """The two positions, mirror images across the line of a tag's start anchors, that
    its first ranges allow, for each tag whose start anchors (:func:`_start_anchors`) are
    two, or more on one line (tight coupling; NaN for the other tags).

    Along the line (centroid ``c``, direction ``v``, normal ``u``), anchor ``i`` at
    ``p_i`` and the tag at ``s + h u``: ``r_i^2 - p_i^2 = -2 p_i s + (s^2 + h^2)``, linear
    in ``s`` and ``s^2 + h^2`` -- least squares over the start anchors' first ranges within
    ``window_s`` of the tag's first range (each anchor's first), ``h`` clipped at 0."""
    from robustloc.estimators._kernels import inv_spd
    from robustloc.models.geometry import principal_lines

    K, J, M = z.shape
    a = np.full((K, 2), np.nan)
    b = np.full((K, 2), np.nan)
    cnt = start.sum(axis=1)
    c, u = principal_lines(a_xy, start)
    ca = a_xy[None] - c[:, None]  # (K, M, 2) anchors about each tag's centroid
    on_line = np.abs(np.einsum("kmi,ki->km", ca, u))
    ext = np.max(np.where(start, np.hypot(ca[..., 0], ca[..., 1]), 0.0), axis=1)
    # a line: two anchors, or more within 1e-6 of their extent off it (the layout test's
    # ill_conditioned covers these and more; a nearly collinear layout still has one fix)
    tol = 1e-6 * np.maximum(ext, 1e-300)[:, None]
    line = (cnt >= 2) & np.all(~start | (on_line <= tol), axis=1) & (ext > 0)
    if not line.any():
        return a, b
    r = np.where(start[:, None, :], z, np.nan)
    with np.errstate(invalid="ignore"):
        t0 = np.nanmin(np.where(np.isfinite(r).any(axis=-1), time_s, np.nan), axis=1) \
            if J else np.full(K, np.nan)
        early = time_s <= (t0 + window_s)[:, None]
    r = np.where(early[..., None], r, np.nan)
    has_r = np.isfinite(r)
    first = np.argmax(has_r, axis=1)  # (K, M) each anchor's first range
    r1 = np.take_along_axis(r, first[:, None, :], axis=1)[:, 0]
    r1 = np.where(has_r.any(axis=1), r1, np.nan)
    if dz is not None:  # slant ranges to horizontal ones
        r1 = np.sqrt(np.maximum(r1**2 - dz[None] ** 2, 0.0))
    v = np.stack([-u[:, 1], u[:, 0]], axis=1)
    pp = np.einsum("kmi,ki->km", ca, v)  # along-line coordinates
    ok = np.isfinite(r1) & start
    line &= ok.sum(axis=1) >= 2
    w = ok.astype(float)
    A = np.stack([-2.0 * pp, np.ones_like(pp)], axis=-1) * w[..., None]  # (K, M, 2)
    y = np.where(ok, r1**2 - pp**2, 0.0)
    N = np.einsum("kmi,kmj->kij", A, A)
    Ninv, good = inv_spd(N)
    sol = np.einsum("kij,kmj,km->ki", Ninv, A, y)
    sa = sol[:, 0]
    h = np.sqrt(np.maximum(sol[:, 1] - sa**2, 0.0))
    line &= good & np.isfinite(h)
    base = c + sa[:, None] * v
    a[line] = (base + h[:, None] * u)[line]
    b[line] = (base - h[:, None] * u)[line]
    return a, b


def _initial_positions(tl, z, opts, a_xy, dz, M, heard, max_age_s: float = 1.0):
    """First usable position of each tag: a fix (loose), or in tight coupling an LS fix of
    the latest range of every anchor heard within ``max_age_s`` (ranges of one TWR round
    rarely share a time stamp).

    Returns the ``(K, 2)`` positions at each tag's first event (where that event has no
    fix: the centroid of the anchors the tag hears within ``geometry_window_s`` of its
    first range, or of all anchors when it hears none), whether it has one, and the
    ``(K, J, 2)`` fixes of every event (NaN: none), where a lost track restarts.
    ``heard`` is the ``(K, J, M)`` mask of the anchors each event heard."""
    K, J = tl.time_s.shape
    if opts.coupling == "loose":
        pos = z[..., :2]
    else:
        r = z[..., :M]
        idx = np.where(np.isfinite(r), np.arange(J)[None, :, None], -1)
        last = np.maximum.accumulate(idx, axis=1)  # (K, J, M) index of the latest range
        kk = np.arange(K)[:, None, None]
        mm = np.arange(M)[None, None, :]
        held = np.where(last >= 0, r[kk, np.maximum(last, 0), mm], np.nan)
        t_last = np.where(last >= 0, tl.time_s[kk, np.maximum(last, 0)], np.nan)
        age = tl.time_s[..., None] - t_last
        held = np.where(age <= max_age_s, held, np.nan)
        pos = uwb_fix(a_xy, held.reshape(K * J, M), "ls", dz).position.reshape(K, J, 2)
    ok = np.isfinite(pos).all(axis=-1)
    # the track starts at its first event: with that event's fix, or without a position
    # (the anchors' centroid, wide) until its first fix restarts it there.  The first fix
    # of the log, whenever it came, was taken: a GPS-only row 10 s (or 1.7e9 s) before
    # any range sat at a later fix with a 2 m sd (the fuse/filter review, 2026-12-07)
    has = ok[:, 0] if J else np.zeros(K, dtype=bool)
    # without a fix, the centroid of the anchors the tag hears around its start: that of
    # all anchors in the file pulled a two-anchor track to the mirror side of their line
    # (an anchor never heard, BS.C of the cart, sat on that side: 3.3 m median error with
    # a 0.11 m sd; the fuse review, finding 2)
    start = _start_anchors(tl.time_s, heard, opts.geometry_window_s)
    cnt = start.sum(axis=1)
    near = (start @ a_xy) / np.maximum(cnt, 1)[:, None]
    # (one anchor heard: its centroid is the anchor itself, where the range's gradient is
    # undefined -- the track stuck there, 29 m off, fault_detected: the review of the
    # fix; the site's centroid, as before, is a start the ranges can move)
    centre = np.where(cnt[:, None] >= 2, near, a_xy.mean(axis=0)[None])
    x0 = np.where(has[:, None], pos[:, 0] if J else np.zeros((K, 2)), centre)
    # on the line of two anchors (their centroid) the ranges say nothing across it: a
    # tag heard by two (or collinear) anchors starts at one of the two positions their
    # first ranges allow; fuse runs the other too and keeps the better (_mirror_starts)
    alt = np.full((K, 2), np.nan)
    if opts.coupling == "tight" and J:
        one, two = _mirror_starts(tl.time_s, z[..., :M], a_xy, dz, start,
                                  opts.geometry_window_s)
        amb = ~has & np.isfinite(one).all(axis=1)
        # the first start on the side of the site's centroid (the anchors a tag does not
        # hear are where the site is): kept unless the other's innovations are clearly
        # smaller (:data:`MIRROR_SIDE_NIS`)
        site = a_xy.mean(axis=0)[None]
        swap = (np.hypot(*(two - site).T) < np.hypot(*(one - site).T))[:, None]
        one, two = np.where(swap, two, one), np.where(swap, one, two)
        x0 = np.where(amb[:, None], one, x0)
        alt = np.where(amb[:, None], two, alt)
    return x0, has, np.where(ok[..., None], pos, np.nan), alt


def _start_anchors(time_s: Array, heard: NDArray[np.bool_],
                   window_s: float) -> NDArray[np.bool_]:
    """``(K, M)``: the anchors each tag hears from its first event with a range up to
    ``window_s`` seconds later (all false for a tag that hears none)."""
    K, J, M = heard.shape
    if K * J == 0:
        return np.zeros((K, M), dtype=bool)
    any_r = heard.any(axis=-1)
    first = np.argmax(any_r, axis=1)
    t0 = np.where(any_r.any(axis=1), time_s[np.arange(K), first], np.nan)
    with np.errstate(invalid="ignore"):
        early = time_s <= (t0 + window_s)[:, None]
    return (heard & early[..., None]).any(axis=1)


def _recent_anchors(time_s: Array, heard: NDArray[np.bool_],
                    window_s: float) -> NDArray[np.bool_]:
    """``(K, J, M)``: the anchors each event's tag heard within ``window_s`` seconds up to
    it (the event's own included): the layout of :func:`_layout_status`."""
    K, J, M = heard.shape
    idx = np.where(heard, np.arange(J)[None, :, None], -1)
    last = np.maximum.accumulate(idx, axis=1)  # (K, J, M) latest event that heard anchor m
    t_last = np.take_along_axis(
        np.broadcast_to(time_s[:, :, None], (K, J, M)), np.maximum(last, 0), axis=1)
    with np.errstate(invalid="ignore"):
        return (last >= 0) & (time_s[..., None] - t_last <= window_s)


def _cover_mirror(tr, recent: NDArray[np.bool_], layout: NDArray[np.object_],
                  a_xy: Array, sided: NDArray[np.bool_] | None = None):
    """``tr`` with the position covariance of every event whose anchors cannot fix the
    position (``layout`` not ``''``) widened to cover the positions its ranges cannot
    tell from its own: ``+ (2 d)^2 u u^T``, ``d`` the distance from the line of the
    anchors heard (:func:`robustloc.models.geometry.principal_lines`, normal ``u``) --
    the mirror image lies ``2 d`` across it -- or, for anchors at one point, the circle
    about it: ``+ (2 rho)^2 t t^T``, ``rho`` the distance to the point, ``t`` the
    tangent.  The filter's own covariance is that of the side it follows: on the
    two-anchor cart the EKF followed the mirror side 3.3 m off with a 0.11 m sd (the
    fuse review, finding 2).  Rows that heard no anchor recently are left as they are,
    and so are a tag's rows after its first of a full layout (its side was fixed then)
    and the rows of the tags in ``sided`` (two mirror starts whose fits told the side)."""
    from dataclasses import replace

    from robustloc.models.geometry import principal_lines

    K, J, M = recent.shape
    # only until the tag's first row of a full layout: after it the track holds its side
    # (three anchors plus GPS course fixed it; a 0.08 m error was given a 3.4 m sd when a
    # third anchor dropped out: the review of the fix)
    full = (layout == "") & recent.any(axis=-1)
    since_full = np.cumsum(full, axis=1) > 0
    rows = ((layout != "") & ~since_full & recent.any(axis=-1)
            & np.isfinite(tr.x[..., :2]).all(axis=-1))
    if sided is not None:  # nor for a tag whose two mirror starts' fits told the side
        rows &= ~sided[:, None]  # apart (by more than MIRROR_SIDE_NIS: GPS course)
    if not rows.any():
        return tr
    k, j = np.nonzero(rows)
    keep = recent[k, j]
    c, u = principal_lines(a_xy, keep)
    x = tr.x[k, j, :2]
    spread = np.max(np.where(keep, np.hypot(*(a_xy[None] - c[:, None]).transpose(2, 0, 1)),
                             0.0), axis=1)
    rel = x - c
    rho = np.hypot(rel[:, 0], rel[:, 1])
    point = spread <= 1e-9 * np.maximum(rho, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        tang = np.stack([-rel[:, 1], rel[:, 0]], axis=1) / rho[:, None]
    tang = np.where(np.isfinite(tang), tang, 0.0)
    d = np.where(point, rho, np.abs(np.einsum("ki,ki->k", rel, u)))
    dirn = np.where(point[:, None], tang, u)
    add = (2.0 * d)[:, None, None] ** 2 * (dirn[:, :, None] * dirn[:, None, :])
    var = tr.var.copy()
    var[k, j, 0] += add[:, 0, 0]
    var[k, j, 1] += add[:, 1, 1]
    cov = None
    if tr.cov_xy is not None:
        cov = tr.cov_xy.copy()
        cov[k, j] += add[:, 0, 1]
    return replace(tr, var=var, cov_xy=cov)


def _layout_status(time_s: Array, heard: NDArray[np.bool_], a_xy: Array,
                   window_s: float) -> NDArray[np.object_]:
    """Per event: ``''`` when the anchors heard within ``window_s`` fix a 2-D position,
    else ``insufficient_anchors`` (fewer than three anchors) or ``ill_conditioned``
    (their scatter matrix fails the condition test of ``inv_spd``, as in ``locate``)."""
    from robustloc.estimators._kernels import inv_spd

    K, J, M = heard.shape
    out = np.full((K, J), "", dtype=object)
    if K * J == 0:
        return out
    recent = _recent_anchors(time_s, heard, window_s)
    cnt = recent.sum(axis=-1)
    w = recent.astype(float)
    # scatter of the recent anchors: sum w c c^T - n m m^T with c the anchors about their
    # centroid (identical anchors give exactly 0), without a (K, J, M, 2) temporary
    c = a_xy - a_xy.mean(axis=0)
    m = np.einsum("kjm,mi->kji", w, c) / np.maximum(cnt, 1)[..., None]
    S = np.einsum("kjm,ma,mb->kjab", w, c, c) - cnt[..., None, None] * (
        m[..., :, None] * m[..., None, :])
    S = S.reshape(K * J, 2, 2)
    _, good = inv_spd(S)
    out[~good.reshape(K, J)] = st.ILL_CONDITIONED
    out[cnt < 3] = st.INSUFFICIENT
    return out


def _track_frame(tags, time_s, tr, filt: FusionFilter, z, m, opts,
                 status: NDArray[np.object_]) -> pd.DataFrame:
    K, J = time_s.shape
    live = np.isfinite(time_s)
    k_idx, j_idx = np.nonzero(live)
    x = tr.x[k_idx, j_idx]
    var = tr.var[k_idx, j_idx]
    names = ["x", "y", "vx", "vy", "ax", "ay"][: filt.motion.n_states]
    data: dict[str, object] = {"time": time_s[k_idx, j_idx], "tag": tags[k_idx]}
    for i, c in enumerate(names):
        data[c] = x[:, i]
    # as `track` names its rows (track-cv-ekf): what made them, for `evaluate`
    data["method"] = fusion_method(filt)
    data["status"] = np.asarray(status[k_idx, j_idx], dtype=str)
    for i, c in enumerate(names):
        data["var_" + c] = var[:, i]
        if c == "y":  # the track contract (docs/formats.md): var_x, var_y, cov_xy, ...
            data["cov_xy"] = tr.cov_xy[k_idx, j_idx]
    data["n_used"] = tr.n_used[k_idx, j_idx]
    data["nis"] = tr.nis[k_idx, j_idx]
    zz = z[k_idx, j_idx]
    uwb = np.isfinite(zz[:, : m - 2]).any(axis=1)
    gps = np.isfinite(zz[:, m - 2 :]).any(axis=1)
    data["source"] = np.where(
        uwb & gps, "uwb+gps", np.where(uwb, "uwb", np.where(gps, "gps", "none"))
    )
    return pd.DataFrame(data)
