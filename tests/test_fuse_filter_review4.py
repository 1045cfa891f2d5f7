"""The fourth filter/fuse review: a diverged UKF is not ``ok`` and restarts, an orphan VTG
is skipped, an epoch of two anchors is labelled by what became of it in loose and tight
coupling (and is no ``invalid_measurement`` for one absurd range), ``filter`` takes the
path-loss model ``locate`` takes, and ``fuse --q`` is bounded.

The command line runs in-process (``robustloc.cli.main``) on ``robustloc simulate
uwb-cart`` (group A: 3 anchors in a 10 m field, 51 epochs at 1 Hz with one GGA/RMC/VTG
triple each; group B: a 100 m field, 71 epochs at 0.1 Hz) and on ``simulate wifi-room``;
the filter itself on a tag at rest amid four anchors.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main
from robustloc.filters import ConstantVelocity
from robustloc.fusion.pipeline import FusionFilter, FusionMeasurement, initial_state
from robustloc.io.nmea import make_gga, make_rmc, make_vtg, nmea_checksum, parse_nmea

SQUARE = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0], [0.0, 5.0]])
AT = np.array([2.0, 2.5])  # where the tag stands


@pytest.fixture(scope="module")
def cart_b(tmp_path_factory):
    d = tmp_path_factory.mktemp("cart_b")
    assert main(["simulate", "uwb-cart", "--group", "B", "--seed", "1", "--out", str(d)]) == 0
    return d


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    d = tmp_path_factory.mktemp("room")
    assert main(["simulate", "wifi-room", "--seed", "1", "--out", str(d)]) == 0
    return d


def _fuse(tmp_path, capsys, d, *extra, ranges=None, anchors=None):
    out = tmp_path / "track.csv"
    rc = main(["fuse", "--ranges", str(ranges or d / "measurements.csv"), "--anchors",
               str(anchors or d / "anchors.csv"), "-o", str(out), *extra])
    return rc, capsys.readouterr(), out


def _at_rest(times_s: np.ndarray, seed: int = 3) -> np.ndarray:
    """Ranges (sigma 0.05 m) from ``AT`` to the four ``SQUARE`` anchors at ``times_s``,
    no GPS: ``z (1, J, 6)``."""
    rng = np.random.default_rng(seed)
    z = np.full((1, times_s.size, 6), np.nan)
    z[0, :, :4] = (np.linalg.norm(AT - SQUARE, axis=-1)
                   + rng.normal(0.0, 0.05, (times_s.size, 4)))
    return z


# --- 1: a diverged UKF is not ok, and starts again -----------------------------------------


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_a_diverged_ukf_restarts_at_the_next_fix(engine):
    # anchor 1 reads 2 m long (40 sigma) on events 30-34: the plain filters follow it and
    # fail the innovation test five times in a row -- one divergence.  The EKF is left to
    # come back by itself (measured: a restart at a fix holding a persistent NLOS range
    # hurt it); the UKF restarts at event 35: its row is one update of the fix, at rest
    # with the initial covariance, by event 35's ranges (dt = 0).  It wrote 'ok' from
    # event 35 on but was still 0.8 m off there, and never restarted.
    t = np.arange(60) * 0.25
    z = _at_rest(t)
    z[0, 30:35, 1] += 2.0
    fm = FusionMeasurement(4, SQUARE)
    x0, P0 = initial_state([AT], 4, 0.01, 0.01)
    R = np.diag([0.05**2] * 4 + [1.0, 1.0])
    fixes = np.broadcast_to(AT, (1, 60, 2)).copy()
    runs = {}
    for kind in ("ekf", "ukf"):
        f = FusionFilter(kind, ConstantVelocity(q=1e-3), engine=engine)
        runs[kind] = f, f.run(t[None], z, R, fm, x0, P0, restart=fixes)
    ekf, ukf = runs["ekf"][1], runs["ukf"][1]
    for tr in (ekf, ukf):
        assert (tr.status[0, 30:35] == st.FAULT_DETECTED).all()
        assert tr.extra["diverged"][0] == 1
    assert ekf.extra["restarts"][0] == 0
    assert ukf.extra["restarts"][0] == 1
    f = runs["ukf"][0]
    want = f.step(np.array([[*AT, 0.0, 0.0]]), P0, np.zeros(1), z[:, 35], R, fm)
    np.testing.assert_allclose(ukf.x[0, 35], np.asarray(want.x)[0], rtol=0, atol=1e-12)
    assert ukf.status[0, 35] == st.OK
    assert np.hypot(*(ukf.x[0, 35, :2] - AT)) < 0.15
    assert np.hypot(*(ukf.x[0, 34, :2] - AT)) > 0.5  # the diverged row, fault_detected


@pytest.mark.parametrize("engine", ["compiled", "numpy"])
def test_a_ukf_prediction_wider_than_a_cell_restarts(engine):
    # 20 s without ranges at q = 0.5: the prediction's V = var_x + var_y is about
    # 2 q dt^4 / 4 = 4e4 m^2 (140 m per axis), beyond lost_pos_var = 1e4 m^2, but
    # sqrt(eps) V = 6e-4 m^2 stays below the ranges' variance 2.5e-3 m^2, so the EKF
    # updates it.  The UKF's sigma points lie 2 sigma out, 280 m, across four anchors 5 m
    # apart: it restarts at the event's fix instead (it updated such a prior before)
    t = np.r_[np.arange(20) * 0.25, 4.75 + 20.0 + np.arange(20) * 0.25]
    z = _at_rest(t, seed=5)
    fm = FusionMeasurement(4, SQUARE)
    x0, P0 = initial_state([AT], 4, 0.01, 0.01)
    R = np.diag([0.05**2] * 4 + [1.0, 1.0])
    fixes = np.broadcast_to(AT, (1, t.size, 2)).copy()
    got = {}
    for kind in ("ekf", "ukf"):
        got[kind] = FusionFilter(kind, ConstantVelocity(q=0.5), engine=engine).run(
            t[None], z, R, fm, x0, P0, restart=fixes)
    assert got["ekf"].extra["restarts"][0] == 0
    assert got["ukf"].extra["restarts"][0] == 1
    ukf = got["ukf"]
    assert (ukf.status[0] == st.OK).all()
    # the event after the gap is one update of the fix, at rest, by its ranges
    assert np.hypot(*(ukf.x[0, 20, :2] - AT)) < 0.2
    np.testing.assert_allclose(ukf.x[0, 20, 2:], 0.0, atol=0.2)


def test_fuse_ukf_rows_far_off_are_never_ok(cart_b, tmp_path, capsys):
    # group B (10 s steps) with the UKF and the default hampel weights: the sigma points
    # span the ranges' curvature, the test passes now and then while the state drifts off,
    # and rows 116 m and 399 m from the truth said ok (the track came back only when its
    # variance passed the lost rule).  Now a UKF prediction wider than 1e4 m^2 and a
    # diverged UKF restart at the event's fix: no row 50 m off says ok
    rc, cap, out = _fuse(tmp_path, capsys, cart_b, "--nmea", str(cart_b / "gps.nmea"),
                         "--filter", "ukf", "--json")
    assert rc == 0, cap.err
    tr = pd.read_csv(out)
    truth = pd.read_csv(cart_b / "truth.csv")
    assert len(tr) == len(truth) == 71
    e = np.hypot(tr["x"] - truth["x"], tr["y"] - truth["y"])
    far = e > 50.0
    assert far.any()  # the UKF is still poor here (the EKF: 0.18 m RMS)
    # (fault_detected here; fault_excluded would claim a fix with one range set aside)
    assert not st.among(tr.loc[far, "status"], (st.OK, st.FAULT_EXCLUDED)).any()
    assert np.sqrt(np.mean(e**2)) < 100.0  # 319 m when the track restarted only when lost
    s = json.loads(cap.out)
    assert s["restarts"] >= 1 and s["diverged"] >= 1


# --- 2: an orphan VTG is skipped --------------------------------------------------------


def _bad(sentence: str) -> str:
    """``sentence`` with a wrong checksum."""
    body = sentence[1 : sentence.index("*")]
    wrong = f"{int(nmea_checksum(body), 16) ^ 0xFF:02X}"
    return f"${body}*{wrong}"


def test_orphan_vtg_is_skipped_and_counted(cart, tmp_path, capsys):
    # the GGA and RMC of 00:00:10 lost to bad checksums, their VTG kept: the VTG took the
    # time of the 00:00:09 fix, whose speed became the mean of three sentences (two of
    # 00:00:09, one of 00:00:10), and fuse merged it there
    lines = (cart / "gps.nmea").read_text().splitlines()
    i = next(k for k, s in enumerate(lines) if s.startswith("$GPGGA,000010"))
    assert lines[i + 1].startswith("$GPRMC,000010") and lines[i + 2].startswith("$GPVTG")
    lines[i], lines[i + 1] = _bad(lines[i]), _bad(lines[i + 1])
    log = parse_nmea(lines)
    sm = log.summary
    assert sm.skipped.get("orphan_vtg") == 1 and sm.skipped["bad_checksum"] == 2
    assert sm.parsed == {"GGA": 50, "RMC": 50, "VTG": 50}
    assert sum(sm.parsed.values()) + sm.n_skipped == sm.lines == 153
    at9 = log.motion[log.motion["time_s"] == 9.0]
    assert list(at9["sentence"]) == ["RMC", "VTG"]  # the fix's own two, no third
    assert not (log.motion["time_s"] == 10.0).any()
    nm = tmp_path / "orphan.nmea"
    nm.write_text("\n".join(lines) + "\n")
    rc, cap, out = _fuse(tmp_path, capsys, cart, "--nmea", str(nm))
    assert rc == 0, cap.err
    assert "orphan_vtg 1" in cap.out
    tr = pd.read_csv(out)
    assert tr.loc[tr["time"] == 10.0, "source"].item() == "uwb"  # no GPS of its own


def test_vtg_joins_only_a_fix_of_its_own():
    t0 = 46800.0
    fix = lambda t: [make_gga(t, 30.0, 120.0, 10.0), make_rmc(t, 1.0, 90.0)]  # noqa: E731
    vtg = make_vtg(2.0, 90.0)
    cases = [
        # a VTG before any timed sentence: no fix (it was counted as truncated)
        ([vtg, *fix(t0), make_vtg(1.0, 90.0)], [t0, t0]),
        # a second VTG after one fix (the next fix's GGA and RMC lost without a trace)
        ([*fix(t0), make_vtg(1.0, 90.0), vtg], [t0, t0]),
        # the next fix reported invalid (RMC status V) and its VTG
        ([*fix(t0), make_vtg(1.0, 90.0),
          make_gga(t0 + 1, 30.0, 120.0, 10.0, quality=0),
          make_rmc(t0 + 1, 2.0, 90.0).replace(",A,", ",V,", 1), vtg], [t0, t0]),
    ]
    for lines, times in cases:
        lines = [s if s.count(",V,") == 0 else _resum(s) for s in lines]
        log = parse_nmea(lines)
        assert log.summary.skipped.get("orphan_vtg") == 1, lines
        np.testing.assert_allclose(log.motion["time_s"], times)
        np.testing.assert_allclose(log.motion["speed_mps"], 1.0, rtol=1e-3)
    # a fix whose GGA was lost keeps its VTG: the RMC of the same time is kept
    lines = [*fix(t0), make_vtg(1.0, 90.0), _bad(make_gga(t0 + 1, 30.0, 120.0, 10.0)),
             make_rmc(t0 + 1, 2.0, 90.0), vtg]
    log = parse_nmea(lines)
    assert log.summary.skipped.get("orphan_vtg", 0) == 0
    np.testing.assert_allclose(log.motion["time_s"], [t0, t0, t0 + 1, t0 + 1])


def _resum(sentence: str) -> str:
    """``sentence`` with its checksum recomputed (after an edit of its body)."""
    body = sentence[1 : sentence.index("*")]
    return f"${body}*{nmea_checksum(body)}"


# --- 3: loose and tight coupling: the status says what the row's state is -----------------


def test_two_anchor_epochs_in_loose_and_tight_coupling(cart, tmp_path, capsys):
    # BS.C never heard: no epoch can fix a position.  insufficient_anchors qualifies an
    # updated row (the help's status table): tight coupling updates with the two ranges,
    # and so does loose coupling with GPS speed and course; loose coupling without GPS has
    # no fix from two anchors, nothing updates the filter, and its rows are the
    # prediction: predicted (n_used 0), as a coasting row of tight coupling is
    m = pd.read_csv(cart / "measurements.csv")
    two = tmp_path / "two.csv"
    m[m["anchor"] != "BS.C"].to_csv(two, index=False)
    want = {("tight", False): st.INSUFFICIENT, ("tight", True): st.INSUFFICIENT,
            ("loose", False): st.PREDICTED, ("loose", True): st.INSUFFICIENT}
    for (coupling, gps), status in want.items():
        extra = ("--nmea", str(cart / "gps.nmea")) if gps else ()
        rc, cap, out = _fuse(tmp_path, capsys, cart, "--coupling", coupling, *extra,
                             ranges=two)
        assert rc == 0, cap.err
        tr = pd.read_csv(out)
        assert len(tr) == 51 and (tr["status"] == status).all(), (coupling, gps)
        assert ((tr["n_used"] == 0) == (status == st.PREDICTED)).all()
    # an epoch with two valid ranges and an absurd third: not every value of it was
    # invalid, yet loose coupling said invalid_measurement (tight: the update's status).
    # Nothing used its two ranges (no fix): predicted, as without the absurd one
    bad = m.copy()
    bad.loc[(bad["anchor"] == "BS.C") & (bad["time"] == 20.0), "range"] = 1e7
    pb = tmp_path / "bad.csv"
    bad.to_csv(pb, index=False)
    want = {("tight", "0"): st.INSUFFICIENT, ("loose", "0"): st.PREDICTED,
            ("tight", "1"): st.OK, ("loose", "1"): st.PREDICTED}
    for (coupling, window), status in want.items():
        rc, cap, out = _fuse(tmp_path, capsys, cart, "--coupling", coupling,
                             "--geometry-window", window, "--json", ranges=pb)
        assert rc == 0, cap.err
        tr = pd.read_csv(out)
        assert tr.loc[tr["time"] == 20.0, "status"].item() == status, (coupling, window)
        assert '"range": 1' in cap.out  # the absurd range counted, never used
    # every value of an epoch absurd: invalid_measurement in both couplings
    bad.loc[bad["time"] == 30.0, "range"] = 1e7
    bad.to_csv(pb, index=False)
    for coupling in ("tight", "loose"):
        rc, cap, out = _fuse(tmp_path, capsys, cart, "--coupling", coupling, ranges=pb)
        assert rc == 0, cap.err
        tr = pd.read_csv(out)
        assert tr.loc[tr["time"] == 30.0, "status"].item() == st.INVALID, coupling


# --- 4: filter takes locate's path-loss model, and says so when the columns disagree -------


def test_filter_uses_the_model_locate_uses_and_notes_a_disagreement(room, tmp_path, capsys):
    # the simulated anchors carry both p0, gamma, faf, d0 and A, n (equal models); with
    # A 10 dB higher and n 0.5 larger the two disagree: filter used p0, gamma without a
    # word, locate (model_from_anchors) uses A, n
    a = pd.read_csv(room / "anchors.csv")
    a["A"] += 10.0
    a["n"] += 0.5
    both = tmp_path / "both.csv"
    a.to_csv(both, index=False)
    out = tmp_path / "f.csv"
    meas = str(room / "measurements.csv")
    assert main(["filter", meas, "--anchors", str(both), "-o", str(out), "-q"]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"note: {both}:2: anchor 'AP1' has A ")
    assert "(4 of 4 anchors disagree): the filter uses A, n (log-distance), as locate does" in err
    f = pd.read_csv(out)
    # distance = 10^((A - rssi) / (10 n)) with the anchor's A, n (the filtered rssi)
    An = a.set_index("anchor").loc[f["anchor"], ["A", "n"]].to_numpy()
    want = 10.0 ** ((An[:, 0] - f["rssi"].to_numpy()) / (10.0 * An[:, 1]))
    ok = f["status"].to_numpy() == st.OK
    np.testing.assert_allclose(f["distance"].to_numpy()[ok], want[ok], rtol=1e-9)
    # the same columns agreeing (the simulated file): no note, the same rows as A, n alone
    assert main(["filter", meas, "--anchors", str(room / "anchors.csv"), "-o",
                 str(out), "-q"]) == 0
    assert capsys.readouterr().err == ""


# --- 5: fuse --q is bounded ----------------------------------------------------------------


@pytest.mark.parametrize("q", ["1e300", "1e7"])
def test_fuse_refuses_a_process_noise_beyond_its_bound(cart, tmp_path, capsys, q):
    # 1e300 (and 1e7) passed: every event of the 1 Hz cart restarted the track from its
    # fix ("restarts: 50"), exit 0
    rc, cap, out = _fuse(tmp_path, capsys, cart, "--q", q)
    assert rc == 2
    err = cap.err
    assert f"argument --q: expected a number in [1e-12, 1e+06], got '{q}'" in err
    assert "Traceback" not in err
    assert not (tmp_path / "track.csv").exists()
    # the report's seed-001 q for group B (1e-6 / T^2) is inside the bounds
    rc, cap, out = _fuse(tmp_path, capsys, cart, "--q", "1e-8")
    assert rc == 0, cap.err
