"""The new-user walkthrough of 2026-12-06: what a first user's natural mistakes and the
tour's own survey showed."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.models.calibration import TRUNCATED_SHARE, calibrate_pathloss


def _survey(seed: int, floor: float | None) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    rows = [(f"a{a}", d, -60 - 22 * np.log10(d) + rng.normal(0, 3))
            for a in range(4) for d in np.arange(1.0, 31.0) for _ in range(10)]
    s = pd.DataFrame(rows, columns=["anchor", "distance", "rssi"])
    return s if floor is None else s[s["rssi"] >= floor].reset_index(drop=True)


def test_a_survey_cut_at_a_sensitivity_is_named():
    """The tour's BLE survey stops at the receiver's -90 dBm: its fit's n came out 1.86-
    2.20 for the true 2.2, and nothing said so.  A Gaussian survey of 1 200 rows puts
    about 1 / 1 200 of its readings below its lowest one: the note speaks above 2 %."""
    cut = calibrate_pathloss(_survey(0, -88.0))
    assert any("readings stop at -87.9" in n for n in cut.notes)
    false = sum(any("readings stop" in n for n in calibrate_pathloss(_survey(k, None)).notes)
                for k in range(40))
    assert false == 0 and TRUNCATED_SHARE == 0.02


def test_the_tours_survey_says_it(tmp_path, capsys):
    sim = tmp_path / "c"
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(sim), "-q"]) == 0
    assert main(["calibrate", str(sim / "survey.csv"), "--model", "log-distance",
                 "--anchors", str(sim / "anchors.csv"), "-o", str(tmp_path / "cal.csv")]) == 0
    assert "note: the survey's readings stop at -90 dBm" in capsys.readouterr().err


def test_ranges_in_millimetres_get_a_hint(tmp_path, capsys):
    sim = tmp_path / "cart"
    assert main(["simulate", "uwb-cart", "--seed", "1", "--out", str(sim), "-q"]) == 0
    m = pd.read_csv(sim / "measurements.csv")
    m["range"] *= 1000
    m.to_csv(tmp_path / "mm.csv", index=False)
    capsys.readouterr()
    assert main(["locate", str(tmp_path / "mm.csv"), "--anchors", str(sim / "anchors.csv"),
                 "-o", str(tmp_path / "o.csv")]) == 0
    assert "hint: most fixes lie far outside the anchors" in capsys.readouterr().out
    # the same log in metres: no hint
    assert main(["locate", str(sim / "measurements.csv"), "--anchors",
                 str(sim / "anchors.csv"), "-o", str(tmp_path / "o2.csv")]) == 0
    assert "hint:" not in capsys.readouterr().out


def test_rssi_without_its_sign_gets_a_hint(tmp_path, capsys):
    sim = tmp_path / "c"
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(sim), "-q"]) == 0
    m = pd.read_csv(sim / "measurements.csv")
    m["rssi"] = -m["rssi"]
    m.to_csv(tmp_path / "pos.csv", index=False)
    capsys.readouterr()
    assert main(["locate", str(tmp_path / "pos.csv"), "--anchors", str(sim / "anchors.csv"),
                 "-o", str(tmp_path / "o.csv")]) == 0
    assert "hint: every epoch is invalid_measurement: RSSI is negative dBm" in (
        capsys.readouterr().out)


def test_evaluate_hints_at_time_units(tmp_path, capsys):
    (tmp_path / "t.csv").write_text("time,tag,x,y\n0,a,0,0\n1,a,1,0\n2,a,2,0\n")
    (tmp_path / "p.csv").write_text("time,tag,x,y,method,status\n"
                                    "0,a,0,0,ls,ok\n1000,a,1,0,ls,ok\n2000,a,2,0,ls,ok\n")
    assert main(["evaluate", str(tmp_path / "p.csv"), "--truth", str(tmp_path / "t.csv")]) == 0
    assert "hint: positions and truth mostly miss each other's times" in (
        capsys.readouterr().out)


@pytest.mark.parametrize("argv, said", [
    (["calibrate", "{m}", "--anchors", "{a}", "-o", "{tmp}/x.csv"],
     "this looks like a measurements log: calibrate it with --self"),
    (["locate", "{tmp}", "--anchors", "{a}", "-o", "{tmp}/o.csv"],
     "a partitioned dataset is read with --engine dask"),
])
def test_natural_mix_ups_say_what_was_meant(argv, said, tmp_path, capsys):
    sim = tmp_path / "c"
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(sim), "-q"]) == 0
    argv = [a.format(m=sim / "measurements.csv", a=sim / "anchors.csv", tmp=tmp_path / "d")
            for a in argv]
    (tmp_path / "d").mkdir()
    assert main(argv) == 2
    assert said in capsys.readouterr().err


def test_method_names_are_case_insensitive(tmp_path):
    sim = tmp_path / "c"
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(sim), "-q"]) == 0
    args = [str(sim / "measurements.csv"), "--anchors", str(sim / "anchors.csv")]
    assert main(["locate", *args, "--method", "LS,IGG", "-o", str(tmp_path / "a.csv")]) == 0
    assert main(["locate", *args, "--method", "ls,igg", "-o", str(tmp_path / "b.csv")]) == 0
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "a.csv"),
                                  pd.read_csv(tmp_path / "b.csv"))


def test_evaluate_says_when_its_arguments_look_swapped(tmp_path, capsys):
    (tmp_path / "t.csv").write_text("time,tag,x,y\n0,a,0,0\n1,a,1,0\n")
    (tmp_path / "p.csv").write_text("time,tag,x,y,method,status\n0,a,0.1,0,ls,ok\n"
                                    "1,a,,,ls,insufficient_anchors\n")
    # the positions' failed row (no x) refused as truth: the error says why
    assert main(["evaluate", str(tmp_path / "t.csv"), "--truth", str(tmp_path / "p.csv")]) == 2
    assert "are the positions and --truth swapped?" in capsys.readouterr().err
    (tmp_path / "p2.csv").write_text("time,tag,x,y,method,status\n0,a,0.1,0,ls,ok\n"
                                     "1,a,1.1,0,ls,ok\n")
    assert main(["evaluate", str(tmp_path / "t.csv"), "--truth", str(tmp_path / "p2.csv")]) == 0
    assert "are the positions and --truth swapped?" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "p2.csv"), "--truth", str(tmp_path / "t.csv")]) == 0
    assert "swapped" not in capsys.readouterr().err
