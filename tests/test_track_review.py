"""Review of the tracker and the fusion filters (tracker/fusion review helper).

1. ``fuse`` writes the track contract's ``cov_xy`` (docs/formats.md: track (filters,
   fusion) ``var_x, var_y, cov_xy, var_vx, var_vy``), checked against FilterPy's EKF run
   on the same events, model and noise.
2. The course of an RMC and a VTG sentence of one fix is averaged on the circle: 179.97 deg
   (RMC) and 180.0 deg (VTG) wrap to +3.1411 and -3.1416 rad, whose arithmetic mean is
   0 deg -- due north for a tag driving due south.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc.filters import RobustUpdate, motion_model
from robustloc.fusion.align import Stream, merge_streams
from robustloc.fusion.pipeline import FusionFilter
from robustloc.fusion.run import FuseOptions, fuse
from robustloc.fusion.uwb import uwb_fix
from robustloc.io.nmea import parse_nmea

filterpy = pytest.importorskip("filterpy.kalman")


def _checksum(body: str) -> str:
    c = 0
    for ch in body:
        c ^= ord(ch)
    return f"${body}*{c:02X}"


def _elongated_log(seed: int = 4) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Four anchors in a 20 m x 2 m strip, a tag beyond its end, diagonally: fixes correlated
    in x and y (the case where ``cov_xy`` matters)."""
    rng = np.random.default_rng(seed)
    a = np.array([[0.0, 0.0], [20.0, 0.0], [0.0, 2.0], [20.0, 2.0]])
    anchors = pd.DataFrame({"anchor": list("ABCD"), "x": a[:, 0], "y": a[:, 1]})
    rows = []
    for k in range(40):
        p = np.array([26.0 + 0.3 * k, 8.0 + 0.1 * k])
        for i in range(4):
            rows.append((0.5 * k, "t", "ABCD"[i], np.hypot(*(p - a[i])) + rng.normal(0, 0.15)))
    return pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]), anchors


def test_fuse_writes_cov_xy_equal_to_filterpy_ekf():
    meas, anchors = _elongated_log()
    q, sr = 0.5, 0.15
    filt = FusionFilter("ekf", motion_model("cv", q=q), RobustUpdate())
    tr = fuse(meas, anchors, None, filt, FuseOptions(sigma_range_m=sr)).track
    assert "cov_xy" in tr.columns
    cols = list(tr.columns)
    assert cols.index("var_y") < cols.index("cov_xy") < cols.index("var_vx")

    # the same filter in FilterPy: first event at the LS fix, P0 = diag(4, 4, 1, 1)
    a = anchors[["x", "y"]].to_numpy(float)
    Z = meas.pivot(index="time", columns="anchor", values="range")[list("ABCD")]
    t = Z.index.to_numpy(float)
    Z = Z.to_numpy(float)
    x0 = uwb_fix(a, Z[:1], "ls").position[0]

    def hx(s):
        return np.hypot(s[0] - a[:, 0], s[1] - a[:, 1])

    def HJ(s):
        d = np.hypot(s[0] - a[:, 0], s[1] - a[:, 1])
        J = np.zeros((4, 4))
        J[:, 0], J[:, 1] = (s[0] - a[:, 0]) / d, (s[1] - a[:, 1]) / d
        return J

    cv = motion_model("cv", q=q)
    ekf = filterpy.ExtendedKalmanFilter(4, 4)
    ekf.x = np.r_[x0, 0.0, 0.0]
    ekf.P = np.diag([4.0, 4.0, 1.0, 1.0])
    ekf.R = np.eye(4) * sr**2
    ref = []
    for k in range(len(t)):
        dt = 0.0 if k == 0 else t[k] - t[k - 1]
        ekf.F, ekf.Q = cv.F(dt), cv.Q(dt)
        ekf.predict()
        ekf.update(Z[k], HJ, hx)
        ref.append([*ekf.x[:2], ekf.P[0, 0], ekf.P[1, 1], ekf.P[0, 1]])
    ref = np.array(ref)
    got = tr[["x", "y", "var_x", "var_y", "cov_xy"]].to_numpy(float)
    # the same arithmetic in another order: rounding only
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12)
    # the geometry makes the correlation large: a diagonal covariance would misstate it
    rho = ref[5:, 4] / np.sqrt(ref[5:, 2] * ref[5:, 3])
    assert np.max(np.abs(rho)) > 0.3


def _south_drive(tmp_vtg: bool) -> tuple[pd.DataFrame, pd.DataFrame, str]:
    rng = np.random.default_rng(3)
    a = np.array([[-10.0, -30.0], [10.0, -30.0], [-10.0, 10.0], [10.0, 10.0]])
    anchors = pd.DataFrame({"anchor": list("ABCD"), "x": a[:, 0], "y": a[:, 1]})
    rows, lines = [], []
    kn = 3600.0 / 1852.0  # 1 m/s in knots
    for k in range(20):
        p = np.array([0.0, -1.0 * k])  # due south at 1 m/s
        for i in range(4):
            rows.append((float(k), "car", "ABCD"[i], np.hypot(*(p - a[i])) + rng.normal(0, 0.1)))
        crs = 179.97 if k == 5 else 180.0 + rng.normal(0, 0.5)
        lines.append(_checksum(f"GPRMC,0000{k:02d}.00,A,4807.038,N,01131.000,E,{kn:.3f},"
                               f"{crs % 360:.2f},230394,,,A"))
        if tmp_vtg:  # the same fix, course with one decimal
            lines.append(_checksum(f"GPVTG,{crs % 360:.1f},T,,M,{kn:.3f},N,{kn * 1.852:.3f},K,A"))
    return (pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]), anchors,
            "\n".join(lines) + "\n")


def test_course_of_rmc_and_vtg_is_averaged_on_the_circle():
    c = np.deg2rad([179.97, 180.0])
    c = (c + np.pi) % (2 * np.pi) - np.pi  # as read_nmea wraps them: +3.1411, -3.1416
    tl = merge_streams([Stream(np.zeros(2), np.array(["g", "g"], dtype=object),
                               np.c_[np.ones(2), c], [0, 1])], 2, 0.02, distinct=[0, 1],
                       angles=[1])
    # the circular mean of the two: 179.985 deg
    assert abs(np.rad2deg(tl.z[0, 0, 1]) % 360 - 179.985) < 1e-9


def test_fuse_with_rmc_and_vtg_equals_rmc_alone():
    meas, anchors, both = _south_drive(True)
    _, _, rmc = _south_drive(False)
    filt = FusionFilter("ekf", motion_model("cv", q=0.5), RobustUpdate())
    a = fuse(meas, anchors, parse_nmea(both.splitlines()), filt).track
    b = fuse(meas, anchors, parse_nmea(rmc.splitlines()), filt).track
    # VTG repeats RMC's course to 0.05 deg (9e-4 rad): at 1 m/s its velocity differs by
    # at most that much (gain <= 1); the arithmetic mean of 179.97 and 180.0 turned the
    # course north and vx jumped by 2.9 m/s
    assert np.max(np.abs(a["vx"] - b["vx"])) < 1e-3
    assert np.max(np.abs(a["vy"] - b["vy"])) < 1e-3
    assert (a["status"] == "ok").all()


# --------------------------------------------------------------------------------------
# the API review (2026-12-05): the Tracker's own checks and its saved state
# --------------------------------------------------------------------------------------
def _two_tag_log():
    from robustloc.io.tables import Epochs, to_epochs

    anc = pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 10, 10, 0], "y": [0.0, 0, 10, 10]})
    rng = np.random.default_rng(0)
    rows = []
    for tag in ("t1", "t2"):
        for k in range(20):
            t = 0.5 * k
            p = (2 + 0.3 * t, 5.0)
            rows += [(t, tag, a.anchor, np.hypot(a.x - p[0], a.y - p[1]) + rng.normal(0, 0.05))
                     for a in anc.itertuples()]
    log = pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"])

    def ep(df):  # tags 1 and 2, ints (what Epochs and step accept)
        e = to_epochs(df, list(anc.anchor), "range")
        tags = np.where(e.tag == "t1", 1, 2).astype(object)
        return Epochs(e.time, tags, e.values, e.anchor_ids, "range", e.line)

    return anc, ep(log[log.time < 5]), ep(log[log.time >= 5])


def test_a_saved_tracker_keeps_tags_that_are_not_strings():
    """JSON keys are strings: tags 1 and 2 came back as '1' and '2', and the next step
    started new filters for 1 and 2 (fixes differing from the uninterrupted run, no
    warning).  A fresh tracker's state_dict raised ValueError (reshape of empty arrays)."""
    import json

    from robustloc.tracking import Tracker

    anc, e1, e2 = _two_tag_log()
    tr = Tracker(anc)
    tr.step(e1)
    ref = tr.step(e2)
    tr = Tracker(anc)
    tr.step(e1)
    saved = json.loads(json.dumps(tr.state_dict()))
    tr2 = Tracker(anc)
    tr2.load_state_dict(saved)
    out = tr2.step(e2)
    assert tr2.tags == [1, 2]
    np.testing.assert_array_equal(out[["x", "y", "var_x"]], ref[["x", "y", "var_x"]])
    fresh = Tracker(anc).state_dict()
    assert fresh["tags"] == {} and fresh["tag_ids"] == []
    Tracker(anc).load_state_dict(json.loads(json.dumps(fresh)))


def test_a_tracker_refuses_bad_input_before_changing_its_state():
    """An Epochs whose time is shorter than its values raised IndexError after earlier
    rounds had moved the filters; a saved state with one malformed tag cleared the
    tracker, then failed part-way, and values a tracker never holds (a noise scale of NaN
    or 0, a NaN bias) loaded and left tags `predicted`.  Now each raises ValueError and
    leaves the tracker as it was.
    Epochs whose time is not finite get invalid_measurement rows (they were `ok`)."""
    from robustloc.io.tables import Epochs
    from robustloc.tracking import Tracker

    anc, e1, e2 = _two_tag_log()
    tr = Tracker(anc)
    tr.step(e1)
    ref = Tracker(anc)
    ref.step(e1)
    short = Epochs(e2.time[:3], e2.tag, e2.values, e2.anchor_ids, "range", e2.line)
    with pytest.raises(ValueError, match="time"):
        tr.step(short)
    state = tr.state_dict()
    bad = {**state, "tags": {**state["tags"], "2": {**state["tags"]["2"], "x": [1.0]}}}
    with pytest.raises(ValueError, match="tag 2: x has 1 values"):
        tr.load_state_dict(bad)
    for field, value in (("scale2", None), ("scale2", 0.0), ("bias", [None] * 4),
                         ("hn", [-1] * 4)):
        tampered = {**state, "tags": {**state["tags"],
                                      "2": {**state["tags"]["2"], field: value}}}
        with pytest.raises(ValueError, match=f"tag 2: {field} is not a value"):
            tr.load_state_dict(tampered)
    with pytest.raises(TypeError):
        tr.step(pd.DataFrame())
    np.testing.assert_array_equal(tr.step(e2)[["x", "y"]], ref.step(e2)[["x", "y"]])
    nan_t = Epochs(np.full(e2.n_epochs, np.nan), e2.tag, e2.values, e2.anchor_ids, "range",
                   e2.line)
    rows = Tracker(anc).step(nan_t)
    assert (rows["status"] == "invalid_measurement").all()
