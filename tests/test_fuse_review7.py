"""The seventh fuse review: tags heard by fewer than three anchors.

Findings (``simulate uwb-cart --seed 1`` with anchor BS.C's ranges removed: two anchors,
``BS.A (0, 10)`` and ``BS.B (10, 0)``; the cart drives east along ``y = 5`` from
``x = 0`` to ``10``, across the anchors' line ``x + y = 10``):

1. every row said ``insufficient_anchors`` while the warning named ``fault_detected``
   rows: the layout's status replaced a failed test (NIS median 30; 14 000 with a +20 m
   range).
2. the track started at the centroid of *all* anchors, on BS.C's side of the line, and
   followed the mirror image: 3.3 m median error with a 0.11 m sd (EKF), 24 m median and
   548 m max (UKF, from a 1e4 m^2 start).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.stats import chi2

from robustloc import status as st
from robustloc.cli import main

#: chi-square 99 % point with 2 degrees of freedom: the 2-D NEES of a consistent
#: position covariance exceeds it on 1 % of the rows
NEES_99 = chi2.ppf(0.99, 2)


def _two_anchors(cart, tmp_path, shift: float = 0.0):
    m = pd.read_csv(cart / "measurements.csv")
    m = m[m["anchor"] != "BS.C"].copy()
    m.loc[(m["anchor"] == "BS.A") & (m["time"] == 20.0), "range"] += shift
    p = tmp_path / "two.csv"
    m.to_csv(p, index=False)
    return p


def _fuse(cart, tmp_path, capsys, ranges, *extra):
    out = tmp_path / "track.csv"
    rc = main(["fuse", "--ranges", str(ranges), "--anchors", str(cart / "anchors.csv"),
               "-o", str(out), "-q", *extra])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    return pd.read_csv(out), cap


def _errors(tr: pd.DataFrame, cart) -> tuple[np.ndarray, np.ndarray]:
    """Each row's 2-D position error (m) and NEES under its own covariance."""
    truth = pd.read_csv(cart / "truth.csv").set_index("time").reindex(tr["time"])
    ex = tr["x"].to_numpy() - truth["x"].to_numpy()
    ey = tr["y"].to_numpy() - truth["y"].to_numpy()
    vx, vy, c = (tr[k].to_numpy() for k in ("var_x", "var_y", "cov_xy"))
    nees = (ex**2 * vy - 2 * ex * ey * c + ey**2 * vx) / (vx * vy - c**2)
    return np.hypot(ex, ey), nees


# --- 1: a failed test keeps its status under the layout's ---------------------------------


def test_failed_test_is_not_hidden_by_too_few_anchors(cart, tmp_path, capsys):
    # a +20 m range at t = 20 s, the plain filter (nothing down-weights it): its event's
    # NIS is in the thousands.  It said insufficient_anchors, as did every row
    two = _two_anchors(cart, tmp_path, shift=20.0)
    tr, cap = _fuse(cart, tmp_path, capsys, two, "--robust", "none")
    row = tr.loc[tr["time"] == 20.0].iloc[0]
    assert row["nis"] > 1000.0
    assert row["status"] == st.FAULT_DETECTED
    assert "fault_detected or unavailable" in cap.err  # the warning's word, now on rows
    # the rows before the fault passed their test: the layout's status
    assert (tr.loc[tr["time"] < 20.0, "status"] == st.INSUFFICIENT).all()
    # a robust update rejects the range (n_used 1): the row passed with the other one
    tr, _ = _fuse(cart, tmp_path, capsys, two)
    row = tr.loc[tr["time"] == 20.0].iloc[0]
    assert row["n_used"] == 1 and row["status"] == st.INSUFFICIENT


# --- 2: two anchors: the track's side, and a covariance that covers the other ---------------


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_two_anchor_track_with_gps_keeps_to_the_right_side(cart, tmp_path, capsys, kind):
    # GPS course (east) tells the sides apart: the mirror track runs south.  Both starts
    # are run; the one whose innovations are smaller is kept.  The mirror image of the
    # truth lies sqrt(2) |x - 5| away (median 3.5 m): an error median below 0.5 m (3x
    # the ranges' 0.1-0.11 m sd) is the right side
    two = _two_anchors(cart, tmp_path)
    tr, _ = _fuse(cart, tmp_path, capsys, two, "--filter", kind, "--nmea",
                  str(cart / "gps.nmea"), "--json")
    err, nees = _errors(tr, cart)
    assert len(tr) == 51
    assert np.median(err) < 0.5, np.median(err)  # was 3.3 m (ekf), 24 m (ukf)
    assert err.max() < 2.0, err.max()  # was 8.1 m (ekf), 548 m (ukf)
    assert (tr["status"] == st.INSUFFICIENT).all()
    # the covariance covers the mirror image: at most 5 % of the rows (2 of 51, where a
    # consistent covariance gives 1 %) beyond the 99 % NEES bound; all of them were
    assert np.mean(nees > NEES_99) <= 0.05


def test_two_anchor_track_without_gps_says_it_may_be_the_mirror(cart, tmp_path, capsys):
    # without GPS nothing tells the sides apart (either straight track fits the ranges):
    # the EKF may follow the mirror -- it does here, 3.6 m median -- but its covariance
    # must then say so: (2 d)^2 across the anchors' line, d the distance to it.  It said
    # 0.37 m sd (NEES median 113, 76 % of the rows beyond the 99 % bound)
    two = _two_anchors(cart, tmp_path)
    tr, _ = _fuse(cart, tmp_path, capsys, two)
    err, nees = _errors(tr, cart)
    assert np.mean(nees > NEES_99) <= 0.05
    assert (tr["status"] == st.INSUFFICIENT).all()


def test_two_anchor_starts_per_tag(cart, tmp_path, capsys):
    # tags are started and chosen one by one: a second tag heard by BS.A and BS.C, the
    # first by BS.A and BS.B, each as its run alone
    m = pd.read_csv(cart / "measurements.csv")
    ab = m[m["anchor"] != "BS.C"]
    ac = m[m["anchor"] != "BS.B"].assign(tag="other")
    both = tmp_path / "both.csv"
    pd.concat([ab, ac]).to_csv(both, index=False)
    tr, _ = _fuse(cart, tmp_path, capsys, both, "--nmea-tag", "cart", "--nmea",
                  str(cart / "gps.nmea"))
    (tmp_path / "a").mkdir()
    ab_p = tmp_path / "a" / "ab.csv"
    ab.to_csv(ab_p, index=False)
    one, _ = _fuse(cart, tmp_path / "a", capsys, ab_p, "--nmea", str(cart / "gps.nmea"))
    pd.testing.assert_frame_equal(tr[tr["tag"] == "cart"].reset_index(drop=True), one)
    (tmp_path / "b").mkdir()
    ac_p = tmp_path / "b" / "ac.csv"
    ac.to_csv(ac_p, index=False)
    other, _ = _fuse(cart, tmp_path / "b", capsys, ac_p)
    pd.testing.assert_frame_equal(tr[tr["tag"] == "other"].reset_index(drop=True), other)


# --- the review of the fix: one start anchor, a side told by GPS, a layout seen -----------


def test_a_tag_first_heard_by_one_anchor_does_not_start_on_it(cart, tmp_path, capsys):
    # BS.A alone for the first 3 s: the centroid of the one anchor heard is the anchor
    # itself, where a range's gradient is undefined -- the track stuck there, 29 m off,
    # rows fault_detected.  It starts at the site's centroid, as before the two-anchor
    # starts: the same track as then (max 15.9 m in its first row, 0.054 m median)
    m = pd.read_csv(cart / "measurements.csv")
    m = m[~((m["time"] < 3.0) & (m["anchor"] != "BS.A"))]
    p = tmp_path / "one.csv"
    m.to_csv(p, index=False)
    tr, _ = _fuse(cart, tmp_path, capsys, p, "--nmea", str(cart / "gps.nmea"))
    err, _ = _errors(tr, cart)
    assert np.median(err) < 0.1 and err[3:].max() < 0.5, err[:6]
    a = pd.read_csv(cart / "anchors.csv").set_index("anchor").loc["BS.A"]
    assert np.hypot(tr["x"].iloc[0] - a["x"], tr["y"].iloc[0] - a["y"]) > 1.0


@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_a_side_told_by_gps_keeps_the_filters_covariance(cart, tmp_path, capsys, kind):
    # the two mirror runs' fits differ by far more than chi2(0.99; 1): the side is known,
    # and the rows keep the filter's covariance (a 0.085 m error had a 3.7 m sd), still
    # consistent: at most 5 % beyond the 99 % NEES bound
    two = _two_anchors(cart, tmp_path)
    tr, _ = _fuse(cart, tmp_path, capsys, two, "--filter", kind, "--nmea",
                  str(cart / "gps.nmea"))
    err, nees = _errors(tr, cart)
    sd = np.sqrt(tr["var_x"] + tr["var_y"])
    assert np.median(sd) < 0.5, np.median(sd)
    assert np.mean(nees > NEES_99) <= 0.05


def test_a_layout_seen_fixes_the_side_and_loose_coupling_is_not_widened(cart, tmp_path,
                                                                         capsys):
    # three anchors for the first 2 s, then two: the side was fixed while three were
    # heard, so the two-anchor rows keep the filter's covariance (they had 3.4 m sd
    # around a 0.08 m error); loose coupling never filters two ranges: not widened
    m = pd.read_csv(cart / "measurements.csv")
    m = m[~((m["time"] >= 2.0) & (m["anchor"] == "BS.C"))]
    p = tmp_path / "three_then_two.csv"
    m.to_csv(p, index=False)
    for extra in ((), ("--coupling", "loose")):
        tr, _ = _fuse(cart, tmp_path, capsys, p, "--nmea", str(cart / "gps.nmea"), *extra)
        err, nees = _errors(tr, cart)
        sd = np.sqrt(tr["var_x"] + tr["var_y"])
        assert np.median(err) < 0.2 and np.median(sd) < 0.5, (np.median(err), np.median(sd))
        assert np.mean(nees > NEES_99) <= 0.05


def test_without_gps_the_start_keeps_to_the_sites_side(cart, tmp_path, capsys):
    # the cart's log heard by BS.B and BS.C only, no GPS: the two mirror runs fit about
    # equally, and the smaller NIS sum was a coin flip that went to the far side (9.9 m
    # median error).  The start on the side of the site's centroid is kept unless the
    # other fits better by more than chi2(0.99; 1): here it stays on the truth's side
    m = pd.read_csv(cart / "measurements.csv")
    p = tmp_path / "bc.csv"
    m[m["anchor"] != "BS.A"].to_csv(p, index=False)
    tr, _ = _fuse(cart, tmp_path, capsys, p)
    err, nees = _errors(tr, cart)
    assert np.median(err) < 0.5, np.median(err)
    assert np.mean(nees > NEES_99) <= 0.05


# --- 6: an open bound is said as open ------------------------------------------------------


@pytest.mark.parametrize("value", ["1", "0.4", "1.5"])
def test_gate_out_of_range_names_the_open_interval(cart, tmp_path, capsys, value):
    # the bound was 1 - 1e-12, printed with :g: "expected a number in [0.5, 1], got '1'"
    rc = main(["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors",
               str(cart / "anchors.csv"), "-o", str(tmp_path / "t.csv"), "--gate", value])
    assert rc == 2
    assert f"expected a number in [0.5, 1), got '{value}'" in capsys.readouterr().err


def test_gate_accepts_up_to_one(cart, tmp_path, capsys):
    for value in ("0.5", "0.999", "0.999999999999"):
        tr, _ = _fuse(cart, tmp_path, capsys, cart / "measurements.csv", "--gate", value)
        assert len(tr) == 51


# --- 4: a ranges file that also has rssi (the DWM1001 loader writes both) ------------------


def test_fuse_reads_the_range_column_beside_rssi(cart, tmp_path, capsys):
    # fuse refused it ("has both 'rssi' and 'range' columns; keep exactly one")
    m = pd.read_csv(cart / "measurements.csv")
    both = tmp_path / "both.csv"
    m.assign(rssi=-60.0).assign(rssi=lambda d: d["rssi"].where(d.index != 3)).to_csv(
        both, index=False)  # an rssi NaN too: fuse never reads that column
    tr, _ = _fuse(cart, tmp_path, capsys, both)
    (tmp_path / "r").mkdir()
    ref, _ = _fuse(cart, tmp_path / "r", capsys, cart / "measurements.csv")
    pd.testing.assert_frame_equal(tr, ref)
    # locate cannot tell which is meant and still refuses (docs: one of rssi or range)
    assert main(["locate", str(both), "--anchors", str(cart / "anchors.csv"), "-o",
                 str(tmp_path / "p.csv")]) == 2
    assert "keep exactly one" in capsys.readouterr().err
    # an rssi-only file: fuse says what it takes
    rs = tmp_path / "rssi.csv"
    m.assign(rssi=-60.0).drop(columns="range").to_csv(rs, index=False)
    assert main(["fuse", "--ranges", str(rs), "--anchors", str(cart / "anchors.csv"),
                 "-o", str(tmp_path / "t.csv")]) == 2
    assert f"error: {rs}:1: measurements file has no 'range' column" in capsys.readouterr().err


# --- 3: options that change nothing are refused ------------------------------------------


def test_fuse_refuses_options_that_change_nothing(cart, tmp_path, capsys):
    # each gave a byte-identical track, exit 0
    base = ["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors",
            str(cart / "anchors.csv"), "-o", str(tmp_path / "t.csv")]
    for extra, said in ((["--fix", "ls"], "--fix goes with --coupling loose"),
                        (["--sigma-course", "3"], "--sigma-course goes with --nmea"),
                        (["--sigma-speed", "0.1"], "--sigma-speed goes with --nmea"),
                        (["--nmea-offset", "1"], "--nmea-offset goes with --nmea"),
                        (["--origin", "10,10,0", "--nmea", str(cart / "gps.nmea")],
                         "--origin sets the ENU origin of GGA positions, which fuse does "
                         "not use")):
        assert main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err
        assert f"error: {said}" in err, err
    # with what they go with, accepted
    assert main([*base, "--coupling", "loose", "--fix", "ls", "--nmea",
                 str(cart / "gps.nmea"), "--sigma-course", "3", "--sigma-speed", "0.1",
                 "--nmea-offset", "0", "-q"]) == 0


def test_fuse_warns_of_a_log_without_speed_or_course(cart, tmp_path, capsys):
    # "used GGA 51", and every row's source uwb: nothing of the log was fused, unsaid
    gga = tmp_path / "gga.nmea"
    gga.write_text("".join(s for s in (cart / "gps.nmea").read_text().splitlines(True)
                           if s.startswith("$GPGGA")))
    tr, cap = _fuse(cart, tmp_path, capsys, cart / "measurements.csv", "--nmea", str(gga))
    assert (tr["source"] == "uwb").all()
    assert (f"warning: {gga}: the log has no RMC or VTG sentence with a speed or course"
            in cap.err)
    # a log with them: no such warning
    _, cap = _fuse(cart, tmp_path, capsys, cart / "measurements.csv", "--nmea",
                   str(cart / "gps.nmea"))
    assert "no RMC or VTG" not in cap.err
