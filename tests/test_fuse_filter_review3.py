"""The third filter/fuse review: NMEA times that jump, strict JSON of ``filter``, bounded
noise options, empty path-loss cells, anchors far outside the others, duplicate ranges,
the loose fix's own test and the count of the rows ``fuse`` writes.

Every case runs the real command line in-process (``robustloc.cli.main``) on the simulated
cart of ``robustloc simulate uwb-cart`` (3 anchors, 51 epochs at 1 Hz, one GGA/RMC/VTG
triple per epoch) or the simulated WiFi room.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from robustloc import status as st
from robustloc.cli import main
from robustloc.io.nmea import nmea_checksum, parse_nmea


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    d = tmp_path_factory.mktemp("room")
    assert main(["simulate", "wifi-room", "--seed", "1", "--out", str(d)]) == 0
    return d


def _fuse(tmp_path, capsys, ranges, anchors, *extra):
    out = tmp_path / "track.csv"
    rc = main(["fuse", "--ranges", str(ranges), "--anchors", str(anchors), "-o", str(out),
               *extra])
    return rc, capsys.readouterr(), out


def _shifted_nmea(cart, shift_s: float, date=None) -> list[str]:
    """The cart's NMEA log with every time moved by ``shift_s`` (modulo a day), checksums
    valid; ``date(t)`` gives the RMC date of the shifted time ``t`` (s, not wrapped)."""
    out = []
    for line in (cart / "gps.nmea").read_text().splitlines():
        body = line[1 : line.index("*")]
        p = body.split(",")
        if p[0] in ("GPGGA", "GPRMC"):
            t = int(p[1][:2]) * 3600 + int(p[1][2:4]) * 60 + float(p[1][4:]) + shift_s
            if p[0] == "GPRMC" and date is not None:
                p[9] = date(t)
            t %= 86400.0
            p[1] = f"{int(t // 3600):02d}{int(t % 3600 // 60):02d}{t % 60:05.2f}"
        body = ",".join(p)
        out.append(f"${body}*{nmea_checksum(body)}")
    return out


def _shifted_ranges(cart, tmp_path, shift_s: float):
    m = pd.read_csv(cart / "measurements.csv")
    m["time"] += shift_s
    p = tmp_path / "ranges.csv"
    m.to_csv(p, index=False)
    return p


# --- D1: a sentence whose time jumps by hours does not move the rest of the log ----------

GLITCH = "GPGGA,000000.00,3000.002424,N,11959.999825,E,1,08,1.0,10.00,M,0.0,M,,"


def test_one_glitched_time_is_skipped_and_does_not_move_the_rest(cart, tmp_path, capsys):
    # the log at 13:00 UTC and one GGA stamped 00:00:00 after its tenth fix: the reader
    # added a day there and kept it, so the 41 fixes after it lay a day later (fuse wrote
    # 41 'predicted' rows a day after the ranges, var_x 7e18, exit 0)
    lines = _shifted_nmea(cart, 46800.0)
    lines.insert(30, f"${GLITCH}*{nmea_checksum(GLITCH)}")
    log = parse_nmea(lines)
    np.testing.assert_allclose(log.fixes["time_s"], 46800.0 + np.arange(51))
    np.testing.assert_allclose(log.motion["time_s"], np.repeat(46800.0 + np.arange(51), 2))
    assert log.summary.skipped["time_jump"] == 1
    assert log.summary.parsed == {"GGA": 51, "RMC": 51, "VTG": 51}
    nm = tmp_path / "glitch.nmea"
    nm.write_text("\n".join(lines) + "\n")
    rc, cap, out = _fuse(tmp_path, capsys, _shifted_ranges(cart, tmp_path, 46800.0),
                         cart / "anchors.csv", "--nmea", str(nm))
    assert rc == 0, cap.err
    assert "time_jump 1" in cap.out
    tr = pd.read_csv(out)
    assert len(tr) == 51 and (tr["status"] == st.OK).all()
    assert (tr["source"] == "uwb+gps").all()  # every epoch has its GPS speed again


def test_a_late_sentence_across_midnight_stays_on_its_day(cart, tmp_path, capsys):
    # the log from 23:59:30 to 00:00:20 with the 23:59:59 fix (GGA, RMC, VTG) arriving
    # after 00:00:20: it was placed a day later (172799 s)
    lines = _shifted_nmea(cart, 86370.0,
                          date=lambda t: "020124" if t >= 86400.0 else "010124")
    i = next(k for k, line in enumerate(lines) if "GGA,235959" in line)
    lines = lines[:i] + lines[i + 3 :] + lines[i : i + 3]
    log = parse_nmea(lines)
    assert log.summary.n_skipped == 0
    np.testing.assert_allclose(np.sort(log.fixes["time_s"]), 86370.0 + np.arange(51))
    assert log.fixes["time_s"].iloc[-1] == 86399.0
    assert log.day0_posix_s == pytest.approx(1704067200.0)  # 2024-01-01 00:00 UTC
    nm = tmp_path / "late.nmea"
    nm.write_text("\n".join(lines) + "\n")
    rc, cap, out = _fuse(tmp_path, capsys, _shifted_ranges(cart, tmp_path, 86370.0),
                         cart / "anchors.csv", "--nmea", str(nm))
    assert rc == 0, cap.err
    tr = pd.read_csv(out)
    assert len(tr) == 51 and (tr["status"] == st.OK).all()
    assert tr.loc[tr["time"] == 86399.0, "source"].item() == "uwb+gps"


def _stamps(times_s: list[float]) -> list[str]:
    from robustloc.io.nmea import make_gga, make_rmc, make_vtg

    return [s for t in times_s for s in (make_gga(t, 30.0, 120.0, 10.0),
                                         make_rmc(t, 1.0, 90.0), make_vtg(1.0, 90.0))]


#: (times of day of successive fixes, their times on the log's axis; None: set aside)
JUMPS = [
    # an excursion of two fixes that the log comes back from: both set aside
    ([46800, 46801, 0, 1, 46802], [46800, 46801, None, None, 46802]),
    # a lone first fix hours before the log: set aside, the log's day is day 0
    ([0, 46800, 46801, 46802], [None, 46800, 46801, 46802]),
    # a pause of 11 h across midnight, the log continuing: the next day, kept
    ([46800, 46801, 0, 1, 2], [46800, 46801, 86400, 86401, 86402]),
    # a pause of 2 h across midnight likewise
    ([82800, 82801, 3600, 3601], [82800, 82801, 90000, 90001]),
    # only single fixes hours apart: nothing to judge by, every jump believed (forward)
    ([3600, 50000], [3600, 50000]),
]


def test_time_jump_rule():
    for times, expected in JUMPS:
        log = parse_nmea(_stamps(times))
        kept = [e for e in expected if e is not None]
        np.testing.assert_allclose(log.fixes["time_s"], kept, err_msg=str(times))
        # RMC and VTG (the VTG of a fix set aside goes with it)
        np.testing.assert_allclose(log.motion["time_s"], np.repeat(kept, 2))
        sm = log.summary
        assert sm.skipped.get("time_jump", 0) == 3 * (len(expected) - len(kept))
        assert sum(sm.parsed.values()) + sm.n_skipped == sm.lines


# --- D5: filter --json is strict JSON when nothing was filtered ---------------------------


def _strict(text: str) -> dict:
    def refuse(token: str) -> None:
        raise AssertionError(f"{token} is no JSON")

    return json.loads(text, parse_constant=refuse)


def test_filter_json_without_any_filtered_value_is_strict(room, tmp_path, capsys):
    bad = tmp_path / "allbad.csv"
    bad.write_text("time,tag,anchor,rssi\n0,t,AP1,-200\n1,t,AP1,-200\n")
    assert main(["filter", str(bad), "--anchors", str(room / "anchors.csv"), "-o",
                 str(tmp_path / "o.csv"), "--json"]) == 0
    s = _strict(capsys.readouterr().out)
    assert s["invalid_measurement"] == 2 and s["raw_minus_filtered_std_db"] is None
    # the Dask engine's pooled spread says the same without any filtered value
    from robustloc._exact import Moments
    from robustloc.commands.filter import combine_partitions

    none = {"n_weighted": 0, "downweighted": 0, "diff": Moments()}
    assert combine_partitions([{"_moments": none}])["raw_minus_filtered_std_db"] is None


# --- D8: fuse's noise options are bounded ---------------------------------------------------


@pytest.mark.parametrize("opt", ["--sigma-range", "--range-k", "--sigma-speed"])
def test_fuse_refuses_huge_noise_options(cart, tmp_path, capsys, opt):
    # 1e300 passed: overflow warnings on stderr and every row ok with no range used
    # (--sigma-speed: an OverflowError traceback)
    rc, cap, out = _fuse(tmp_path, capsys, cart / "measurements.csv", cart / "anchors.csv",
                         "--nmea", str(cart / "gps.nmea"), opt, "1e300")
    assert rc == 2
    assert f"argument {opt}: expected a number in" in cap.err
    assert "Traceback" not in cap.err and "Warning" not in cap.err
    assert not out.exists()


# --- D6: filter refuses an anchor with empty path-loss cells, as locate does --------------


def test_filter_refuses_empty_path_loss_cells_as_locate(room, tmp_path, capsys):
    a = pd.read_csv(room / "anchors.csv")[["anchor", "x", "y", "A", "n"]]
    a.loc[1, ["A", "n"]] = np.nan  # AP2 on line 3 of the file
    pa = tmp_path / "anchors.csv"
    a.to_csv(pa, index=False)
    meas = str(room / "measurements.csv")
    assert main(["locate", meas, "--anchors", str(pa), "-o", str(tmp_path / "l.csv")]) == 2
    said = capsys.readouterr().err
    assert f"error: {pa}:3: anchor 'AP2' has no value for 'A'" in said
    out = tmp_path / "f.csv"
    assert main(["filter", meas, "--anchors", str(pa), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == said and "Traceback" not in err
    assert not out.exists()


# --- D3: an anchor far outside the others is not used, and said -----------------------------


def test_fuse_leaves_out_an_anchor_far_outside_the_others(cart, tmp_path, capsys):
    # BS.C typed in mm: fuse hung on its ranges, 51 rows fault_excluded with n_used 0,
    # 7 km off, exit 0 and not a word; locate and track name it and leave it out
    pa = tmp_path / "mm.csv"
    pa.write_text("anchor,x,y\nBS.A,0.0,10.0\nBS.B,10.0,0.0\nBS.C,10000.0,10000.0\n")
    rc, cap, out = _fuse(tmp_path, capsys, cart / "measurements.csv", pa, "--json")
    assert rc == 0, cap.err
    assert (f"warning: {pa}: anchor(s) BS.C lie far outside the others" in cap.err)
    assert _strict(cap.out)["anchors_not_used"] == ["BS.C"]
    tr = pd.read_csv(out)
    assert len(tr) == 51
    # two anchors left: no position can be ok, as locate says of these epochs
    assert (tr["status"] == st.INSUFFICIENT).all()
    truth = pd.read_csv(cart / "truth.csv")
    # the state stays between the two anchors' circles (10 m apart), not kilometres away
    assert np.hypot(tr["x"] - truth["x"], tr["y"] - truth["y"]).max() < 20.0


def test_fuse_row_without_any_component_kept_is_not_ok(cart, tmp_path, capsys):
    # one range per event (the three anchors 0.3 s apart, a full round within the 1 s
    # geometry window): an event whose only range the robust weight rejects kept nothing
    # (n_used 0) and said fault_excluded, as if an update had excluded a fault and kept
    # the rest; its state is the prediction
    m = pd.read_csv(cart / "measurements.csv")
    k = m.groupby("time").cumcount()
    m["time"] = m["time"] + 0.3 * k
    m.loc[(m["anchor"] == "BS.B") & (m["time"].round(1) == 30.3), "range"] += 5.0
    pm = tmp_path / "rr.csv"
    m.to_csv(pm, index=False)
    rc, cap, out = _fuse(tmp_path, capsys, pm, cart / "anchors.csv")
    assert rc == 0, cap.err
    tr = pd.read_csv(out)
    assert len(tr) == len(m)
    row = tr.loc[tr["time"].round(1) == 30.3].iloc[0]
    assert row["n_used"] == 0 and row["status"] == st.PREDICTED
    kept = st.among(tr["status"], (st.OK, st.FAULT_EXCLUDED))
    assert (tr.loc[kept, "n_used"] >= 1).all()


# --- D7: duplicate ranges are counted and said ------------------------------------------------


def test_fuse_counts_and_says_duplicate_ranges(cart, tmp_path, capsys):
    m = pd.read_csv(cart / "measurements.csv")
    pm = tmp_path / "dup.csv"
    pd.concat([m, m.iloc[:10]]).to_csv(pm, index=False)
    rc, cap, out = _fuse(tmp_path, capsys, pm, cart / "anchors.csv")
    assert rc == 0, cap.err
    assert "  10 duplicate rows (same time, tag and anchor) averaged" in cap.out
    dup = pd.read_csv(out)
    rc, cap, out = _fuse(tmp_path, capsys, cart / "measurements.csv", cart / "anchors.csv",
                         "--json")
    assert _strict(cap.out)["duplicates_merged"] == 0
    # a copy averaged with itself is the range itself: the same track
    pd.testing.assert_frame_equal(dup, pd.read_csv(out))
    rc, cap, out = _fuse(tmp_path, capsys, pm, cart / "anchors.csv", "--json")
    assert _strict(cap.out)["duplicates_merged"] == 10


# --- D2: loose coupling carries its fix's own test --------------------------------------------


@pytest.fixture(scope="module")
def four(cart, tmp_path_factory):
    """Four anchors around the cart, ranges with 0.1 m noise, and an anchors file with A3
    typed 3 m off (y 13 for 10)."""
    d = tmp_path_factory.mktemp("four")
    rng = np.random.default_rng(0)
    tr = pd.read_csv(cart / "truth.csv")
    A = {"A1": (0.0, 0.0), "A2": (10.0, 0.0), "A3": (10.0, 10.0), "A4": (0.0, 10.0)}
    rows = [(r.time, r.tag, k, np.hypot(r.x - ax, r.y - ay) + rng.normal(0, 0.1))
            for r in tr.itertuples() for k, (ax, ay) in A.items()]
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]).to_csv(
        d / "four.csv", index=False)
    pd.DataFrame([(k, *v) for k, v in A.items()], columns=["anchor", "x", "y"]).to_csv(
        d / "good.csv", index=False)
    A["A3"] = (10.0, 13.0)
    pd.DataFrame([(k, *v) for k, v in A.items()], columns=["anchor", "x", "y"]).to_csv(
        d / "bad.csv", index=False)
    return d


@pytest.mark.parametrize("fix", ["nls", "ls"])
def test_loose_rows_carry_the_fix_test_of_locate(four, tmp_path, capsys, fix):
    # A3 3 m off: every loose row said ok (tight coupling: fault_detected).  The row of an
    # ok event whose fix fails its own test is fault_detected; the test is locate's for
    # the same fix and sigma, epoch by epoch
    for layout in ("bad", "good"):
        anchors = four / f"{layout}.csv"
        rc, cap, out = _fuse(tmp_path, capsys, four / "four.csv", anchors, "--coupling",
                             "loose", "--fix", fix, "--sigma-range", "0.15", "-q")
        assert rc == 0, cap.err
        tr = pd.read_csv(out)
        pos = tmp_path / "pos.csv"
        assert main(["locate", str(four / "four.csv"), "--anchors", str(anchors),
                     "--method", fix, "--sigma", "0.15", "--robust-scale", "apriori", "-o",
                     str(pos), "-q"]) == 0
        loc = pd.read_csv(pos)
        assert len(tr) == len(loc) == 51
        failed = st.among(loc["status"], (st.FAULT_DETECTED, st.UNAVAILABLE))
        assert (tr.loc[failed, "status"] == st.FAULT_DETECTED).all(), layout
        if layout == "bad":  # 3 m at 0.15 m range noise: every fix fails
            assert failed.all()
        else:  # at 0.1 m noise and sigma 0.15 none does here, and every row is ok
            assert not failed.any() and (tr["status"] == st.OK).all()


# --- D10: the count said is the rows written --------------------------------------------------


def test_fuse_counts_the_rows_it_writes(cart, tmp_path, capsys):
    p = tmp_path / "weird.csv"
    p.write_text("time,tag,anchor,range\n0,t,BS.A,5\n0,t,BS.B,1e6\n0,t,BS.C,-60\n"
                 "1,t,BS.A,1e7\n2,t,BS.A,-1\n2,t,BS.B,-1\n2,t,BS.C,-1\n2e12,t,BS.A,3\n"
                 "-5,t,BS.B,4\n")
    rc, cap, out = _fuse(tmp_path, capsys, p, cart / "anchors.csv")
    assert rc == 0, cap.err
    tr = pd.read_csv(out)
    assert len(tr) == 5  # 2e12 s is outside the time limits: its own row
    assert f"fused {len(tr)} events of 1 tag(s)" in cap.out
    rc, cap, out = _fuse(tmp_path, capsys, p, cart / "anchors.csv", "--json")
    s = _strict(cap.out)
    assert s["events"] == len(tr) == sum(s["status"].values())
