"""Issue 15, part B: plausibility at the door of ``fuse`` and the NMEA reader, honest
statuses for degenerate anchor layouts, and a fusion filter that nothing can poison.

Every case runs the real command line in-process (``robustloc.cli.main``) on the simulated
cart of ``robustloc simulate uwb-cart`` (3 anchors, 51 epochs at 1 Hz, one RMC/VTG/GGA
triple per epoch).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main
from robustloc.fusion.pipeline import FusionFilter, FusionMeasurement, initial_state
from robustloc.io.nmea import nmea_checksum, parse_nmea


@pytest.fixture(scope="module")
def cart(tmp_path_factory):
    d = tmp_path_factory.mktemp("cart")
    assert main(["simulate", "uwb-cart", "--seed", "1", "--out", str(d)]) == 0
    return d


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
        assert len(tr) == 51 and (tr["status"] == st.ILL_CONDITIONED).all(), coupling
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
    assert len(tr) == 51 and (tr["status"] == st.INSUFFICIENT).all()


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
