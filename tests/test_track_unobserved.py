"""The tracker's bound where the ranges do not fix the position (tracker module docstring,
item 12): one anchor heard for a minute of a walk.

Before item 12 the EKF's covariance shrank along the range circle it could not observe:
on this walk (five anchors on a 20 m circle, ranges of 0.3 m, one anchor heard from 20 to
80 s) 29 % of the rows were beyond their ``hpl``, `ok` rows up to 51 m off with bounds of a
few metres.  The issue's target for simulation is at most 0.1 % of the usable rows beyond
their ``hpl`` at the documented integrity risk (1e-3).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.io import to_epochs
from robustloc.io.tables import Epochs
from robustloc.tracking import Tracker

SIGMA_M = 0.3
ANCHOR_RADIUS_M = 20.0


def _walk(seed: int, n_heard: int = 1, quiet: tuple[float, float] = (20.0, 80.0),
          dt: float = 0.2, duration: float = 100.0, one_per_epoch: bool = False):
    """A tag walking a circle of 8 m at 1 m/s amid five anchors; from ``quiet[0]`` to
    ``quiet[1]`` only the first ``n_heard`` anchors are heard.  ``one_per_epoch``: the
    anchors take turns, one range per epoch (round-robin UWB)."""
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, 5, endpoint=False)
    axy = ANCHOR_RADIUS_M * np.c_[np.cos(ang), np.sin(ang)]
    anchors = pd.DataFrame({"anchor": [f"a{i}" for i in range(5)], "x": axy[:, 0],
                            "y": axy[:, 1]})
    t = np.arange(0.0, duration, dt)
    th = t / 8.0 + rng.uniform(0, 2 * np.pi)
    xy = 8.0 * np.c_[np.cos(th), np.sin(th)]
    rows = []
    for k, tk in enumerate(t):
        which = [k % 5] if one_per_epoch else range(5)
        for i in which:
            if quiet[0] <= tk < quiet[1] and i >= n_heard:
                continue
            d = float(np.hypot(*(xy[k] - axy[i])))
            rows.append((tk, "t1", f"a{i}", d + rng.normal(0, SIGMA_M)))
    meas = pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"])
    ep = to_epochs(meas, list(anchors["anchor"]))
    truth = pd.DataFrame({"x": xy[:, 0], "y": xy[:, 1]}, index=t).loc[ep.time]
    return anchors, ep, truth.to_numpy(float)


def _part(ep: Epochs, s: slice) -> Epochs:
    return Epochs(ep.time[s], ep.tag[s], ep.values[s], ep.anchor_ids, ep.value, ep.line[s])


def _beyond(rows: pd.DataFrame, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    err = np.hypot(*(rows[["x", "y"]].to_numpy(float) - truth).T)
    usable = st.among(rows["status"].to_numpy(object), st.USABLE) & np.isfinite(err)
    return err, usable & ~(err <= rows["hpl"].to_numpy(float))


@pytest.mark.parametrize("flt", ["ekf", "ukf"])
def test_one_anchor_for_a_minute_stays_within_hpl(flt):
    beyond = total = 0
    for seed in range(3):
        anchors, ep, truth = _walk(seed)
        rows = Tracker(anchors, sigma=SIGMA_M, filter=flt).step(ep)
        err, bad = _beyond(rows, truth)
        beyond += int(bad.sum())
        total += len(rows)
        one = (ep.time >= 25) & (ep.time < 80)
        assert np.all(np.isfinite(rows["hpl"].to_numpy(float)[one]))
        if flt == "ekf":
            # the EKF's bound stays useful: the ring bound |x - a| + d + k s sigma, at most
            # the anchor circle's diameter, plus the walk's (16 m) and the range noise's
            # (k s sigma <= 3.7 * 4 * 0.3 m).  (The UKF's own covariance grows along the
            # circle: its bound is its own, hundreds of metres after a minute.)
            assert (np.median(rows["hpl"].to_numpy(float)[one])
                    <= 2 * ANCHOR_RADIUS_M + 2 * 8.0 + 5.0)
    # 0.1 % of 1 500 rows: at most 1 (before item 12: 29 % with the EKF)
    assert beyond <= total // 1000, (beyond, total)


def test_without_the_rule_the_ekf_is_misleading():
    """The control: the rule off (any two anchors ever heard count as observing the
    position) gives back the misleading rows, so the test above can fail."""
    anchors, ep, truth = _walk(0)
    rows = Tracker(anchors, sigma=SIGMA_M, observed_window_s=1e9).step(ep)
    _, bad = _beyond(rows, truth)
    assert bad.sum() > 50


def test_round_robin_ranges_stay_observed():
    """One range per epoch, the anchors in turn (uwb-labyrinth, uwb-dwm1001): every row is
    observed, so the rule changes no bound."""
    anchors, ep, truth = _walk(1, n_heard=5, one_per_epoch=True, dt=0.1)
    a = Tracker(anchors, sigma=SIGMA_M).step(ep)
    b = Tracker(anchors, sigma=SIGMA_M, observed_window_s=1e9).step(ep)
    np.testing.assert_array_equal(a["hpl"].to_numpy(float), b["hpl"].to_numpy(float))
    _, bad = _beyond(a, truth)
    assert bad.sum() <= len(a) // 1000


def test_engines_agree_and_state_round_trips():
    """The compiled and NumPy engines give the same bounds (the rule runs after either),
    and a tracker saved and loaded every 37 epochs gives the rows of one run: the
    observed time and covariance are part of the saved state."""
    anchors, ep, _ = _walk(2)
    ref = Tracker(anchors, sigma=SIGMA_M, engine="numpy").step(ep)
    com = Tracker(anchors, sigma=SIGMA_M).step(ep)
    np.testing.assert_allclose(com["hpl"].to_numpy(float), ref["hpl"].to_numpy(float),
                               rtol=1e-6)
    trk = Tracker(anchors, sigma=SIGMA_M)
    parts = []
    for lo in range(0, ep.n_epochs, 37):
        part = _part(ep, slice(lo, lo + 37))
        parts.append(trk.step(part))
        state = trk.state_dict()
        trk = Tracker(anchors, sigma=SIGMA_M)
        trk.load_state_dict(state)
    joined = pd.concat(parts, ignore_index=True)
    np.testing.assert_array_equal(joined["hpl"].to_numpy(float), com["hpl"].to_numpy(float))


def test_state_saved_before_the_rule_loads():
    """A state saved without the new arrays loads; its tags count as observed from their
    next observed row (no bound from an unknown past)."""
    anchors, ep, _ = _walk(3)
    trk = Tracker(anchors, sigma=SIGMA_M)
    trk.step(_part(ep, slice(0, 50)))
    state = trk.state_dict()
    for rec in state["tags"].values():
        for key in ("tkeep", "tdet", "Pdet"):
            del rec[key]
    new = Tracker(anchors, sigma=SIGMA_M)
    new.load_state_dict(state)
    rows = new.step(_part(ep, slice(50, 60)))
    assert np.all(np.isfinite(rows["hpl"].to_numpy(float)))
    assert np.isfinite(new._tdet).all()


# ------------------------------------------------------------------ the review of item 12
def _beyond_rate(anchors, ep, truth, **kw) -> tuple[int, int]:
    rows = Tracker(anchors, sigma=SIGMA_M, **kw).step(ep)
    _, bad = _beyond(rows, truth)
    return int(bad.sum()), len(rows)


def _in_turn(seed: int, pair: tuple[int, int], coloc: bool = False):
    """The walk of :func:`_walk`; from 20 to 80 s only the anchors ``pair`` are heard,
    one range per epoch, in turn (``coloc``: the second moved to 0.5 m from the first)."""
    anchors, _, _ = _walk(seed)
    rng = np.random.default_rng(100 + seed)
    axy = anchors[["x", "y"]].to_numpy(float).copy()
    if coloc:
        axy[pair[1]] = axy[pair[0]] + [0.5, 0.0]
        anchors = anchors.assign(x=axy[:, 0], y=axy[:, 1])
    t = np.arange(0.0, 100.0, 0.2)
    th = t / 8.0 + rng.uniform(0, 2 * np.pi)
    xy = 8.0 * np.c_[np.cos(th), np.sin(th)]
    rows = []
    for k, tk in enumerate(t):
        which = [pair[k % 2]] if 20 <= tk < 80 else range(5)
        rows += [(tk, "t1", f"a{i}", float(np.hypot(*(xy[k] - axy[i])))
                  + rng.normal(0, SIGMA_M)) for i in which]
    ep = to_epochs(pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]),
                   list(anchors["anchor"]))
    return anchors, ep, pd.DataFrame(xy, index=t).loc[ep.time].to_numpy(float)


@pytest.mark.parametrize("coloc", [False, True])
def test_two_anchors_in_turn_cover_their_mirror(coloc):
    """Anchors a0 and a2 heard in turn, one range per epoch, never kept two in one epoch:
    no line was carried, the track crossed it and followed the mirror side (11 % of the
    rows beyond hpl, `ok` rows 28 m off with hpl 2.5 m); two anchors 0.5 m apart counted
    as observing the position (9.5 %).  Target: at most 0.1 % (integrity risk 1e-3)."""
    beyond = total = 0
    for seed in range(3):
        b, n = _beyond_rate(*_in_turn(seed, (0, 2), coloc))
        beyond += b
        total += n
    assert beyond <= total // 1000, (beyond, total)


def test_a_corridor_ranged_in_turn_covers_its_mirror():
    """Five anchors 10 m apart, 0-0.3 m off one line, the three nearest ranged one per
    epoch in turn; the tag walks along the line, +-1 m across it: 5.4 % of the rows were
    beyond hpl, all on the mirror side."""
    beyond = total = 0
    for seed in range(3):
        rng = np.random.default_rng(seed)
        axy = np.c_[np.arange(0, 41, 10.0), rng.uniform(-0.3, 0.3, 5)]
        anchors = pd.DataFrame({"anchor": [f"a{i}" for i in range(5)], "x": axy[:, 0],
                                "y": axy[:, 1]})
        t = np.arange(0, 120, 0.1)
        s = t % 80
        xy = np.c_[np.where(s < 40, s, 80 - s),
                   np.sin(2 * np.pi * t / 37 + rng.uniform(0, 6.3))]
        rows = []
        for k, tk in enumerate(t):
            i = np.argsort(np.hypot(*(xy[k] - axy).T))[:3][k % 3]
            rows.append((tk, "t1", f"a{i}", float(np.hypot(*(xy[k] - axy[i])))
                         + rng.normal(0, SIGMA_M)))
        ep = to_epochs(pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]),
                       list(anchors["anchor"]))
        b, n = _beyond_rate(anchors, ep, pd.DataFrame(xy, index=t).loc[ep.time].to_numpy())
        beyond += b
        total += n
    assert beyond <= total // 1000, (beyond, total)


def test_reports_just_over_a_second_apart_stay_observed():
    """Five anchors in turn, one range per report every 1.05 s: every row counted as
    unobserved (two anchors never within 1 s) and its hpl tripled, on a track observed
    as well as at 0.95 s.  The last M updates count as recent too: the bounds are those
    of the rule switched off."""
    anchors, _, _ = _walk(0)
    axy = anchors[["x", "y"]].to_numpy(float)
    rng = np.random.default_rng(7)
    t = np.arange(200) * 1.05
    xy = np.clip(np.cumsum(0.5 * np.c_[np.cos(np.cumsum(rng.normal(0, .3, 200))),
                                       np.sin(np.cumsum(rng.normal(0, .3, 200)))], 0), -10, 10)
    rows = [(t[k], "t1", f"a{k % 5}", float(np.hypot(*(xy[k] - axy[k % 5])))
             + rng.normal(0, SIGMA_M)) for k in range(200)]
    ep = to_epochs(pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]),
                   list(anchors["anchor"]))
    a = Tracker(anchors, sigma=SIGMA_M, init_window_s=10.0).step(ep)
    b = Tracker(anchors, sigma=SIGMA_M, init_window_s=10.0, observed_window_s=1e9).step(ep)
    np.testing.assert_array_equal(a["hpl"].to_numpy(float), b["hpl"].to_numpy(float))
