"""The fifth filter/fuse review: a fused row that kept no component is ``predicted``
whatever its anchors, a lost track restarts as a track starts (with its event's GPS
velocity, or the uninformative velocity variance), and ``filter --static`` restarts a link
after a gap as its help says.

The command line runs in-process (``robustloc.cli.main``) on ``robustloc simulate
uwb-cart`` (3 anchors in a 10 m field, 51 epochs at 1 Hz) and on small logs built here.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main
from robustloc.filters import ConstantVelocity, RobustUpdate
from robustloc.fusion.pipeline import FusionFilter, FusionMeasurement
from robustloc.fusion.run import FuseOptions, fuse
from robustloc.robust.weights import get_weight


def _fuse(tmp_path, capsys, ranges, anchors, *extra):
    out = tmp_path / "track.csv"
    rc = main(["fuse", "--ranges", str(ranges), "--anchors", str(anchors), "-o", str(out),
               "--json", *extra])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    return pd.read_csv(out), json.loads(cap.out)


# --- 1: an event whose every component was rejected is predicted, whatever its anchors ----


@pytest.mark.parametrize("layout", [st.INSUFFICIENT, st.ILL_CONDITIONED])
def test_fuse_row_that_kept_nothing_is_predicted_whatever_the_anchors(cart, tmp_path, capsys,
                                                                      layout):
    # two anchors per event; both ranges of t = 20 are 8 m long: the update rejects both
    # (n_used 0) and the row is the prediction.  It said insufficient_anchors (or
    # ill_conditioned), statuses of an *updated* row (fuse --help)
    m = pd.read_csv(cart / "measurements.csv")
    two = m[m["anchor"] != "BS.C"].copy()
    pa = cart / "anchors.csv"
    if layout == st.ILL_CONDITIONED:
        # BS.C at BS.A's place, heard half a second after each epoch (its own event of one
        # range): the anchors heard within the 1 s window are three at two points
        a = pd.read_csv(pa)
        a.loc[a["anchor"] == "BS.C", ["x", "y"]] = a.loc[a["anchor"] == "BS.A",
                                                         ["x", "y"]].to_numpy()
        pa = tmp_path / "anchors.csv"
        a.to_csv(pa, index=False)
        c = two[two["anchor"] == "BS.A"].assign(anchor="BS.C")
        c["time"] += 0.5
        two = pd.concat([two, c], ignore_index=True).sort_values("time", kind="stable")
    two.loc[two["time"] == 20.0, "range"] += 8.0
    pm = tmp_path / "ranges.csv"
    two.to_csv(pm, index=False)
    tr, summary = _fuse(tmp_path, capsys, pm, pa)
    row = tr.loc[tr["time"] == 20.0].iloc[0]
    assert row["n_used"] == 0
    assert row["status"] == st.PREDICTED
    # the other updated rows keep the layout's status (the first event, before BS.C is
    # heard, has two anchors); none that kept nothing does
    updated = tr["n_used"] > 0
    assert (tr.loc[updated & (tr["time"] >= 0.5), "status"] == layout).all()
    assert (tr.loc[~updated, "status"] == st.PREDICTED).all()


# --- 2: a lost track restarts as a track starts: its event's GPS velocity, or wide ----------

WALK_ANCHORS = pd.DataFrame({"anchor": ["A1", "A2", "A3"], "x": [0.0, 300.0, 0.0],
                             "y": [0.0, 0.0, 300.0]})


def _walk(gps_after_gap: bool):
    """A tag walking east at 1 m/s amid three anchors 300 m apart, with GPS speed and
    course every second, and 100 s without any measurement (t = 100 .. 199): the track is
    lost and restarts at t = 200.  Ranges sigma 0.1 m; ``gps_after_gap=False``: no GPS
    after the gap."""
    rng = np.random.default_rng(0)
    a = WALK_ANCHORS[["x", "y"]].to_numpy()
    rows, gps = [], []
    for t in [*range(100), *range(200, 300)]:
        x = np.array([10.0 + t, 100.0])
        for name, p in zip(WALK_ANCHORS["anchor"], a):
            rows.append((float(t), "tag", name, float(np.hypot(*(x - p))
                                                      + rng.normal(0.0, 0.1))))
        if t < 100 or gps_after_gap:
            gps.append((float(t), 1.0 + rng.normal(0.0, 0.02),
                        np.deg2rad(90.0 + rng.normal(0.0, 2.0))))
    meas = pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"])
    motion = pd.DataFrame(gps, columns=["time_s", "speed_mps", "course_rad"])
    return meas, motion


def _fuse_walk(kind: str, engine: str, gps_after_gap: bool):
    meas, motion = _walk(gps_after_gap)
    # fuse's defaults (--filter ekf/ukf --motion cv --robust hampel, q 0.5)
    filt = FusionFilter(kind, ConstantVelocity(q=0.5), RobustUpdate(get_weight("hampel")),
                        engine=engine)
    res = fuse(meas, WALK_ANCHORS, motion, filt, FuseOptions())
    assert res.summary["restarts"] == 1
    return res.track


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_restart_takes_its_event_gps_velocity(kind):
    # it restarted at rest (vx 0) with var_vx 0.0101 fitted to the first event's speed
    # (10 sd off the true 1 m/s), and the event's own speed and course were rejected
    # (Jacobian rows 0 at v = 0): fault_excluded.  Now as the track's start: that velocity
    tracks = [_fuse_walk(kind, e, True) for e in ("compiled", "numpy")]
    for tr in tracks:
        row = tr.loc[tr["time"] == 200.0].iloc[0]
        assert row["status"] == st.OK and row["n_used"] == 5
        assert abs(row["vx"] - 1.0) < 0.05 and abs(row["vy"]) < 0.1
        z = (tr["vx"] - 1.0) / np.sqrt(tr["var_vx"])
        assert (np.abs(z[tr["time"] >= 200.0]) < 4.0).all()
        assert (tr.loc[tr["time"] >= 200.0, "status"] == st.OK).all()
    # both engines alike
    a, b = tracks
    pd.testing.assert_frame_equal(a, b, rtol=1e-9, atol=1e-10)


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_restart_without_gps_has_the_velocity_variance_of_a_start_without_gps(kind):
    # no GPS at the restart's event: at rest, with the velocity variance of a track that
    # starts without GPS (1 (m/s)^2, the initial state's), not the 0.0101 of the first
    # event's speed, which put its 1 m/s 10 sd off
    tracks = [_fuse_walk(kind, e, False) for e in ("compiled", "numpy")]
    for tr in tracks:
        row = tr.loc[tr["time"] == 200.0].iloc[0]
        assert row["vx"] == pytest.approx(0.0, abs=1e-6)
        assert row["var_vx"] == pytest.approx(1.0, rel=0.05)
        z = (tr["vx"] - 1.0) / np.sqrt(tr["var_vx"])
        assert (np.abs(z[tr["time"] >= 200.0]) < 4.0).all()
    a, b = tracks
    pd.testing.assert_frame_equal(a, b, rtol=1e-9, atol=1e-10)


def test_restart_velocity_unit():
    # FusionFilter._restart (the lost track's restart, and the track-by-track retry after
    # an update that raised): a GPS speed of at least min_speed_mps with a course gives
    # the velocity, R_speed + v^2 R_course per axis; a slow speed or no course: at rest,
    # P_init's velocity block.  R as (m, m) and (K, m, m) alike
    f = FusionFilter("ekf", ConstantVelocity(q=0.5))
    meas = FusionMeasurement(4, WALK_ANCHORS[["x", "y"]].to_numpy())
    K, m = 4, meas.m
    x = np.full((K, 4), 7.0)
    P = np.tile(3.0 * np.eye(4), (K, 1, 1))
    P_init = np.tile(np.diag([0.25, 0.25, 1.0, 1.0]), (K, 1, 1))
    fix = np.array([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0], [8.0, 9.0]])
    z = np.full((K, m), np.nan)
    z[:, meas.speed_index] = [2.0, 0.05, 2.0, 2.0]
    z[:, meas.course_index] = [np.pi / 6, 1.0, np.nan, np.pi / 6]
    R = np.diag([0.01] * (m - 2) + [0.05**2, np.deg2rad(5.0) ** 2])
    go = np.array([True, True, True, False])
    for RR in (R, np.broadcast_to(R, (K, m, m))):
        xr, Pr = f._restart(go, x, P, P_init, fix, z, RR, meas)
        np.testing.assert_allclose(xr[0], [1.0, 2.0, 2.0 * 0.5, 2.0 * np.cos(np.pi / 6)])
        var_v = 0.05**2 + 4.0 * np.deg2rad(5.0) ** 2
        np.testing.assert_allclose(Pr[0], np.diag([0.25, 0.25, var_v, var_v]))
        for k in (1, 2):  # too slow, no course: at rest with P_init
            np.testing.assert_array_equal(xr[k], [*fix[k], 0.0, 0.0])
            np.testing.assert_array_equal(Pr[k], P_init[k])
        np.testing.assert_array_equal(xr[3], x[3])  # not restarted
        np.testing.assert_array_equal(Pr[3], P[3])


# --- 3: filter --static restarts a link after a gap, as its help says ------------------------


@pytest.mark.parametrize("static", [False, True], ids=["moving", "static"])
def test_filter_restarts_a_link_after_a_gap(tmp_path, capsys, static):
    # one link at -50 dBm (3.16 m from an anchor of A = -40, n = 2), then 10 000 s later at
    # -60 dBm (10 m).  The help: a link whose predicted RSSI variance exceeds 25 times the
    # measurement's starts again, its distance drawn from the sample.  --static never did
    # (its distance variance does not grow, and the rule also wanted it beyond d^2): its
    # distance state stayed at 3.3 m
    pa, pm, out = tmp_path / "a.csv", tmp_path / "m.csv", tmp_path / "f.csv"
    pa.write_text("anchor,x,y,A,n\nAP1,0,0,-40,2\n")
    rows = ([f"{t},t,AP1,-50" for t in range(20)]
            + [f"{10000 + t},t,AP1,-60" for t in range(20)])
    pm.write_text("time,tag,anchor,rssi\n" + "\n".join(rows) + "\n")
    rc = main(["filter", str(pm), "--anchors", str(pa), "-o", str(out), "--json",
               *(["--static"] if static else [])])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert json.loads(cap.out)["restarted"] == 1
    f = pd.read_csv(out)
    after = f.iloc[20]
    assert after["distance_state"] == pytest.approx(10.0, rel=1e-9)
    assert after["rssi"] == pytest.approx(-60.0, abs=1e-9)
    assert f.iloc[21:]["distance_state"].sub(10.0).abs().max() < 0.5


def test_static_filter_restarts_after_its_random_walk_passes_the_ratio():
    # a static link's power variance grows by q_rssi per second only: past 25 R after about
    # (25 R - P) / q = (100 - 0.43) / 0.05 = 1990 s at the defaults (filter --help)
    from robustloc.filters.rssi import RobustRssiFilter

    f = RobustRssiFilter(sigma_accel_mps2=0.0, init_speed_std_mps=0.0)
    for gap, want in ((1900.0, 0), (2100.0, 1)):
        t = np.r_[np.arange(20.0), gap + 19.0 + np.arange(5.0)]
        z = np.r_[np.full(20, -50.0), np.full(5, -60.0)]
        r = f.filter_samples(np.zeros(len(t), dtype=np.int64), t, z)
        assert int(r.restarted.sum()) == want, gap
    assert f.static and not RobustRssiFilter().static
