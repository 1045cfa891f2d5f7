"""Issue 15, part B: plausibility at the door of ``fuse`` and the NMEA reader, honest
statuses for degenerate anchor layouts, and a fusion filter that nothing can poison.

Every case runs the real command line in-process (``robustloc.cli.main``) on the simulated
cart of ``robustloc simulate uwb-cart`` (3 anchors, 51 epochs at 1 Hz, one RMC/VTG/GGA
triple per epoch).
"""

from __future__ import annotations

import io
import warnings

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main
from robustloc.fusion.pipeline import FusionFilter, FusionMeasurement, initial_state
from robustloc.io.nmea import nmea_checksum, parse_nmea


def _resum(line: str, change) -> str:
    """An NMEA sentence with some fields changed and a *valid* checksum."""
    body = line[1 : line.index("*")]
    parts = body.split(",")
    change(parts)
    body = ",".join(parts)
    return f"${body}*{nmea_checksum(body)}"


def _nmea_with(cart, tmp_path, index: int, change, kind: str = "RMC"):
    lines = (cart / "gps.nmea").read_text().splitlines()
    at = [i for i, line in enumerate(lines) if line[3:6] == kind][index]
    lines[at] = _resum(lines[at], change)
    p = tmp_path / "gps.nmea"
    p.write_text("\n".join(lines) + "\n")
    return p


def _fuse(cart, tmp_path, capsys, *extra, ranges=None, anchors=None):
    out = tmp_path / "track.csv"
    rc = main(["fuse", "--ranges", str(ranges or cart / "measurements.csv"),
               "--anchors", str(anchors or cart / "anchors.csv"), "-o", str(out), *extra])
    cap = capsys.readouterr()
    return rc, cap, out


def test_range_1e308_is_invalid_counted_and_does_not_lose_the_track(cart, tmp_path, capsys):
    m = pd.read_csv(cart / "measurements.csv")
    m.loc[10, "range"] = 1e308  # epoch 3 (three anchors per epoch)
    bad = tmp_path / "m.csv"
    m.to_csv(bad, index=False)
    rc, cap, out = _fuse(cart, tmp_path, capsys, "--nmea", str(cart / "gps.nmea"), ranges=bad)
    assert rc == 0, cap.err
    assert "invalid_measurement: 1" in cap.out
    tr = pd.read_csv(out)
    assert len(tr) == 51  # every epoch a row
    assert np.isfinite(tr[["x", "y", "vx", "vy"]].to_numpy()).all()
    assert (tr["status"] == st.OK).all()  # the other two ranges still fix the epoch
    truth = pd.read_csv(cart / "truth.csv")
    err = np.hypot(tr["x"] - truth["x"], tr["y"] - truth["y"])
    # same accuracy as the clean run: the bad value never reached the filter
    rc, cap, clean = _fuse(cart, tmp_path, capsys, "--nmea", str(cart / "gps.nmea"))
    ref = pd.read_csv(clean)
    err_ref = np.hypot(ref["x"] - truth["x"], ref["y"] - truth["y"])
    assert err.max() < 2 * err_ref.max() + 0.5


def test_epoch_with_only_invalid_ranges_gets_an_invalid_row(cart, tmp_path, capsys):
    m = pd.read_csv(cart / "measurements.csv")
    m.loc[m["time"] == 20.0, "range"] = -1e6  # every range of epoch 20
    bad = tmp_path / "m.csv"
    m.to_csv(bad, index=False)
    rc, cap, out = _fuse(cart, tmp_path, capsys, ranges=bad)
    assert rc == 0, cap.err
    assert "invalid_measurement: 3" in cap.out
    tr = pd.read_csv(out)
    assert len(tr) == 51
    row = tr[tr["time"] == 20.0].iloc[0]
    assert row["status"] == st.INVALID and row["n_used"] == 0
    assert np.isfinite(row[["x", "y"]].to_numpy(float)).all()  # the prediction
    assert (tr.loc[tr["time"] > 20.0, "status"] == st.OK).all()


def test_nmea_speed_1e300_knots_is_invalid(cart, tmp_path, capsys):
    nm = _nmea_with(cart, tmp_path, 3, lambda p: p.__setitem__(7, "1e300"))
    nm_vtg = _nmea_with(cart, tmp_path, 3, lambda p: p.__setitem__(7, "1e300"), "VTG")
    log = parse_nmea(nm.read_text().splitlines())
    assert log.summary.invalid == {"speed": 1}
    assert np.isnan(log.motion["speed_mps"]).sum() == 1
    rc, cap, out = _fuse(cart, tmp_path, capsys, "--nmea", str(nm_vtg))
    assert rc == 0, cap.err
    rc, cap, out = _fuse(cart, tmp_path, capsys, "--nmea", str(nm))
    assert rc == 0, cap.err
    assert "invalid_measurement: 1" in cap.out and "speed 1" in cap.out
    tr = pd.read_csv(out)
    assert len(tr) == 51 and (tr["status"] == st.OK).all()
    # before: positions near 1e298; the cart moves in a 10 m square
    assert tr[["x", "y"]].abs().max().max() < 20.0
    assert tr[["vx", "vy"]].abs().max().max() < 5.0


def test_nmea_course_out_of_range_is_invalid():
    body = "GPRMC,120000.00,A,3000.0,N,12000.0,E,1.0,400.0,010124,,,A"
    log = parse_nmea(["$" + body + "*" + nmea_checksum(body)])
    assert log.summary.invalid == {"course": 1}
    assert log.motion["speed_mps"].iloc[0] == pytest.approx(1852 / 3600)
    assert np.isnan(log.motion["course_rad"].iloc[0])


def test_nmea_gga_latitude_beyond_90_is_skipped_as_invalid():
    body = "GPGGA,120000.00,9130.0,N,12000.0,E,1,08,1.0,10.0,M,0.0,M,,"
    log = parse_nmea(["$" + body + "*" + nmea_checksum(body)])
    assert log.summary.skipped["invalid_measurement"] == 1 and len(log.fixes) == 0


def test_nmea_field_that_is_not_a_number_is_malformed_not_truncated():
    # the GNSS review (2026-12-04): a GGA latitude "30XY.002135" under a valid checksum
    # was counted as truncated; an empty field still is
    bad = "GPGGA,000003.00,30XY.002135,N,12000.000604,E,1,08,1.0,10.00,M,0.0,M,,"
    rmc = "GPRMC,000003.00,A,3000.0,N,12000.0,E,0.3x31,93.73,010124,,,A"
    empty = "GPRMC,000003.00,A,3000.0,N,12000.0,E,,93.73,010124,,,A"
    log = parse_nmea(["$" + b + "*" + nmea_checksum(b) for b in (bad, rmc, empty)])
    assert log.summary.skipped["malformed"] == 2
    assert log.summary.skipped["truncated"] == 1
    assert len(log.fixes) == 0 and len(log.motion) == 0


def test_rmc_date_320124_is_skipped_not_a_traceback(cart, tmp_path, capsys):
    nm = _nmea_with(cart, tmp_path, 0, lambda p: p.__setitem__(9, "320124"))
    rc, cap, out = _fuse(cart, tmp_path, capsys, "--nmea", str(nm))
    assert rc == 0, cap.err
    assert "Traceback" not in cap.err
    assert "invalid_measurement 1" in cap.out  # the NMEA summary line
    assert len(pd.read_csv(out)) == 51


def test_identical_anchors_are_ill_conditioned_not_ok(cart, tmp_path, capsys):
    a = pd.read_csv(cart / "anchors.csv")
    a[["x", "y"]] = [5.0, 5.0]
    p = tmp_path / "a.csv"
    a.to_csv(p, index=False)
    for coupling in ("tight", "loose"):
        rc, cap, out = _fuse(cart, tmp_path, capsys, "--coupling", coupling, "--nmea",
                             str(cart / "gps.nmea"), anchors=p)
        assert rc == 0, cap.err
        tr = pd.read_csv(out)
        # no row ok; a row whose test failed (ranges to three anchors at one point
        # disagree: NIS in the thousands) keeps fault_detected / unavailable, which the
        # layout's status hid (the fuse review, finding 1)
        assert len(tr) == 51, coupling
        assert set(tr["status"]) <= {st.ILL_CONDITIONED, st.FAULT_DETECTED,
                                     st.UNAVAILABLE}, coupling
        assert (tr["status"] == st.ILL_CONDITIONED).any(), coupling
    # locate agrees
    rc = main(["locate", str(cart / "measurements.csv"), "--anchors", str(p), "-o",
               str(tmp_path / "pos.csv")])
    capsys.readouterr()
    assert set(pd.read_csv(tmp_path / "pos.csv")["status"]) == {st.ILL_CONDITIONED}


def test_one_anchor_is_insufficient_not_ok(cart, tmp_path, capsys):
    a = pd.read_csv(cart / "anchors.csv").iloc[:1]
    m = pd.read_csv(cart / "measurements.csv")
    m = m[m["anchor"] == a["anchor"].iloc[0]]
    pa, pm = tmp_path / "a.csv", tmp_path / "m.csv"
    a.to_csv(pa, index=False)
    m.to_csv(pm, index=False)
    rc, cap, out = _fuse(cart, tmp_path, capsys, ranges=pm, anchors=pa)
    assert rc == 0, cap.err
    tr = pd.read_csv(out)
    # never ok: insufficient_anchors where a range updated the row; the track starts at
    # the anchor itself (the centroid of one anchor), where the range's Jacobian is 0 and
    # every range is rejected (n_used 0): those rows are the prediction, predicted
    # whatever the anchors (fuse --help)
    assert len(tr) == 51
    assert (tr["status"] == np.where(tr["n_used"] > 0, st.INSUFFICIENT, st.PREDICTED)).all()


def test_collinear_anchors_are_ill_conditioned():
    from robustloc.fusion.run import _layout_status

    t = np.arange(4.0)[None]
    heard = np.ones((1, 4, 3), bool)
    line = np.array([[0.0, 0.0], [1.0, 1.0], [3.0, 3.0]])
    tri = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])
    assert (_layout_status(t, heard, line, 1.0) == st.ILL_CONDITIONED).all()
    assert (_layout_status(t, heard, tri, 1.0) == "").all()
    # one anchor per event, round-robin: the window gathers the layout
    rr = np.zeros((1, 4, 3), bool)
    rr[0, [0, 1, 2, 3], [0, 1, 2, 0]] = True
    got = _layout_status(t, rr, tri, 2.0)[0]
    assert list(got) == [st.INSUFFICIENT, st.INSUFFICIENT, "", ""]


def test_fusion_filter_rejects_a_nonfinite_update_and_keeps_going():
    """A value that slips past the door (here straight into the filter) must not poison
    the state: the update is rejected, the prior kept, the next updates recover."""
    anchors = np.array([[0.0, 10.0], [10.0, 0.0], [10.0, 10.0]])
    meas = FusionMeasurement(4, anchors)
    truth = np.array([4.0, 5.0])
    J = 20
    r = np.hypot(*(truth[None] - anchors).T)
    z = np.full((1, J, 5), np.nan)
    z[0, :, :3] = r
    z[0, 5, 0] = 1e308  # overflows r^2 in the update
    t = np.arange(J, dtype=float)[None]
    x0, P0 = initial_state(truth[None] + 0.5, 4)
    for engine in ("compiled", "numpy"):
        for kind in ("ekf", "ukf"):
            f = FusionFilter(kind, engine=engine)
            with np.errstate(all="ignore"):
                tr = f.run(t, z, np.diag([0.01] * 3 + [1.0, 1.0]), meas, x0, P0)
            assert np.isfinite(tr.x).all() and np.isfinite(tr.var).all(), (engine, kind)
            assert tr.status[0, 5] in ("predicted", st.FAULT_EXCLUDED), (engine, kind)
            assert np.hypot(*(tr.x[0, -1, :2] - truth)) < 0.1, (engine, kind)


@pytest.mark.parametrize("opt,value", [
    ("--nmea-offset", "nan"), ("--sigma-range", "-1"), ("--merge-window", "inf"),
    ("--tag-height", "nan"), ("--gate", "2"), ("--q", "0"), ("--origin", "200,0,0"),
])
def test_fuse_refuses_absurd_option_values(cart, tmp_path, capsys, opt, value):
    try:  # argparse exits with 2; a value checked by the command returns 2
        rc, cap, out = _fuse(cart, tmp_path, capsys, opt, value)
        err = cap.err
    except SystemExit as e:
        rc, err = e.code, capsys.readouterr().err
    assert rc == 2
    assert "error" in err and opt in err and "Traceback" not in err
    assert not (tmp_path / "track.csv").exists()


# --- fuzzing (seed 001): the run summary, times outside the limits, a day-long gap -------

def test_fuse_to_stdout_keeps_the_summary_out_of_the_csv(cart, tmp_path, capsys):
    for extra in ((), ("--json",)):
        rc = main(["fuse", "--ranges", str(cart / "measurements.csv"), "--anchors",
                   str(cart / "anchors.csv"), "--nmea", str(cart / "gps.nmea"), "-o", "-",
                   *extra])
        cap = capsys.readouterr()
        assert rc == 0, cap.err
        lines = cap.out.splitlines()
        assert len(lines) == 1 + 51  # the header and one row per epoch, nothing else
        tr = pd.read_csv(io.StringIO(cap.out))
        assert list(tr.columns[:2]) == ["time", "tag"] and tr["time"].notna().all()
        assert "fused 51 events" in cap.err or '"events": 51' in cap.err


def test_times_outside_the_limits_are_invalid_rows_as_in_locate(cart, tmp_path, capsys):
    m = pd.read_csv(cart / "measurements.csv")
    n_ok = m["time"].nunique()
    bad = pd.DataFrame({"time": [2e12, 2e12, 1e300, -5e12], "tag": m["tag"].iloc[0],
                        "anchor": m["anchor"].iloc[[0, 1, 0, 2]].to_numpy(),
                        "range": m["range"].iloc[:4].to_numpy()})
    p = tmp_path / "m.csv"
    pd.concat([m, bad]).to_csv(p, index=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # before: overflow RuntimeWarnings
        rc, cap, out = _fuse(cart, tmp_path, capsys, "--nmea", str(cart / "gps.nmea"),
                             "--motion", "ca", ranges=p)
    assert rc == 0, cap.err
    assert "invalid_measurement: 4 (time 4;" in cap.out
    tr = pd.read_csv(out)
    assert len(tr) == n_ok + 3  # one row per (tag, time), as locate gives
    inv = tr[tr["status"] == st.INVALID]
    np.testing.assert_allclose(inv["time"], [-5e12, 2e12, 1e300])
    assert inv[["x", "y", "var_x"]].isna().all().all()  # the filter never saw them
    # the rest is the clean run, row for row (before: 2e12 and 1e300 were ok rows)
    rc, cap, clean = _fuse(cart, tmp_path, capsys, "--nmea", str(cart / "gps.nmea"),
                           "--motion", "ca")
    ref = pd.read_csv(clean)
    pd.testing.assert_frame_equal(tr[tr["status"] != st.INVALID].reset_index(drop=True), ref)
    # locate agrees on these epochs
    rc = main(["locate", str(p), "--anchors", str(cart / "anchors.csv"), "-o",
               str(tmp_path / "pos.csv")])
    capsys.readouterr()
    pos = pd.read_csv(tmp_path / "pos.csv")
    np.testing.assert_allclose(np.sort(pos.loc[pos["status"] == st.INVALID, "time"]),
                               [-5e12, 2e12, 1e300])


def test_nmea_times_beyond_the_limits_are_invalid_and_absurd_offset_refused(cart, tmp_path,
                                                                            capsys):
    # offset 1e12 - 25 s: the sentences of seconds 0..24 land inside the limits, those of
    # 26..50 beyond (second 25 is exactly 1e12: the limits are inclusive); the ranges'
    # clock is far away, so every sentence is its own gps event
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rc, cap, out = _fuse(cart, tmp_path, capsys, "--nmea", str(cart / "gps.nmea"),
                             "--nmea-offset", str(1e12 - 25))
    assert rc == 0, cap.err
    n_sent = len(parse_nmea((cart / "gps.nmea").read_text().splitlines()).motion)
    per_s = n_sent // 51  # RMC and VTG of one second share its time
    assert f"time {25 * per_s}" in cap.out
    tr = pd.read_csv(out)
    gps_bad = tr[(tr["source"] == "gps") & (tr["status"] == st.INVALID)]
    assert len(gps_bad) == 25 and gps_bad[["x", "y"]].isna().all().all()
    assert len(tr) == 51 + 26 + 25
    rc, cap, out = _fuse(cart, tmp_path, capsys, "--nmea", str(cart / "gps.nmea"),
                         "--nmea-offset", "1e300")
    assert rc == 2 and "--nmea-offset" in cap.err and "Traceback" not in cap.err


def test_fuse_day_long_gap_is_a_restart_not_a_traceback(tmp_path, capsys):
    # the fuzzer's reproduction: two identical epochs one day apart, --motion ca; before:
    # exit 1, LinAlgError (Singular matrix) in the UKF update after the gap
    a = tmp_path / "a.csv"
    a.write_text("anchor,x,y\nA1,0,0\nA2,10,0\nA3,10,10\nA4,0,10\n")
    g = tmp_path / "gap.csv"
    body = "".join(f"{t},t1,{k},{r}\n" for t in (0, 86400)
                   for k, r in (("A1", 3.6), ("A2", 8.5), ("A3", 10.6), ("A4", 7.3)))
    g.write_text("time,tag,anchor,range\n" + body)
    for motion in ("ca", "cv"):
        out = tmp_path / "f.csv"
        rc = main(["fuse", "--ranges", str(g), "--anchors", str(a), "--motion", motion,
                   "-o", str(out)])
        cap = capsys.readouterr()
        assert rc == 0 and "Traceback" not in cap.err, cap.err
        assert "restarts: 1" in cap.out
        tr = pd.read_csv(out)
        assert len(tr) == 2 and (tr["status"] == st.OK).all()
        # the same ranges after the gap: the restarted track is where the first row was
        # (both the LS solution of the same four ranges; 1 cm covers the UKF's sigma-point
        # shift at the restart's 4 m^2 prior, a fifteenth of the 0.15 m range sigma)
        assert np.hypot(*(tr[["x", "y"]].iloc[1] - tr[["x", "y"]].iloc[0])) < 0.01
        assert tr["var_x"].iloc[1] < 1.0


def test_gga_with_a_valid_checksum_but_an_impossible_position_is_invalid():
    """The GNSS review (2026-12-07): a hemisphere ``X`` read as latitude 0, 65 minutes
    read as 38.09 deg, an infinite altitude (north 2e292 m) and an altitude in feet were
    fixes; they are skipped as ``invalid_measurement``.  A GGA without its geoid
    separation keeps its position without an ellipsoidal height (``h_m``, ``up_m`` NaN;
    the altitude alone was taken as ellipsoidal, 28 m off here), counted as
    ``geoid_separation``."""
    good = "GPGGA,000001.00,3725.590397,N,12210.422534,W,1,24,0.4,51.9,M,-28.4,M,,"
    bad = ["GPGGA,000002.00,3725.590397,X,12210.422534,W,1,24,0.4,51.9,M,-28.4,M,,",
           "GPGGA,000003.00,3765.590397,N,12210.422534,W,1,24,0.4,51.9,M,-28.4,M,,",
           "GPGGA,000004.00,3725.590397,N,12260.422534,W,1,24,0.4,51.9,M,-28.4,M,,",
           "GPGGA,000005.00,3725.590397,N,12210.422534,W,1,24,0.4,inf,M,-28.4,M,,",
           "GPGGA,000006.00,3725.590397,N,12210.422534,W,1,24,0.4,51.9,F,-28.4,M,,",
           "GPGGA,000007.00,3725.590397,N,12210.422534,W,1,24,0.4,2e6,M,-28.4,M,,"]
    nosep = "GPGGA,000008.00,3725.590397,N,12210.422534,W,1,24,0.4,51.9,M,,M,,"
    log = parse_nmea(["$" + b + "*" + nmea_checksum(b) for b in (good, *bad, nosep)])
    assert log.summary.skipped["invalid_measurement"] == len(bad)
    fx = log.fixes
    assert list(fx["time_s"]) == [1.0, 8.0]
    assert fx["h_m"].iloc[0] == pytest.approx(51.9 - 28.4)
    assert np.isnan(fx["h_m"].iloc[1]) and np.isnan(fx["up_m"].iloc[1])
    assert np.isfinite(fx[["east_m", "north_m"]].to_numpy()).all()
    assert log.summary.invalid == {"geoid_separation": 1}
