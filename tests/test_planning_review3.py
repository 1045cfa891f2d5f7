"""The simulate / stats / montecarlo / reliability review (2026-12-06): each defect it
confirmed, reproduced on the command line."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pymap3d
import pytest

from robustloc.cli import main

LAYOUT = "anchor,x,y\nA,0,0\nB,10,0\nC,10,8\nD,0,8\nE,5,12\n"
#: a projected (UTM-sized) offset of the same layout
EAST, NORTH = 512345.678, 4498765.432


@pytest.fixture
def a4(tmp_path):
    p = tmp_path / "a4.csv"
    p.write_text(LAYOUT)
    return p


@pytest.fixture
def utm(tmp_path):
    df = pd.read_csv(pd.io.common.StringIO(LAYOUT))
    df["x"] += EAST
    df["y"] += NORTH
    p = tmp_path / "utm.csv"
    df.to_csv(p, index=False)
    return p


def test_reliability_writes_projected_coordinates_exactly(utm, tmp_path):
    """The grid's coordinates kept 6 significant digits: every row of the 9 grid rows
    read y = 4498770 and 99 points merged into 11."""
    out = tmp_path / "rel"
    area = f"{EAST},{EAST + 10},{NORTH},{NORTH + 8}"
    assert main(["reliability", "--anchors", str(utm), "--area", area, "--step", "1",
                 "--sigma", "0.5", "-o", str(out), "-q", "--no-maps", "--suggest"]) == 0
    grid = pd.read_csv(out / "reliability.csv")
    assert len(grid) == 99 == len(grid[["x", "y"]].drop_duplicates())
    np.testing.assert_allclose(np.unique(grid["y"]), NORTH + np.arange(9.0), atol=1e-6)
    np.testing.assert_allclose(np.unique(grid["x"]), EAST + np.arange(11.0), atol=1e-6)
    sugg = pd.read_csv(out / "suggestions.csv")
    assert np.all((sugg["y"] >= NORTH - 1e-6) & (sugg["y"] <= NORTH + 8 + 1e-6))


def test_montecarlo_position_takes_projected_coordinates(utm, capsys):
    """--position used the fault-size parser (within +-1e6)."""
    assert main(["montecarlo", "--anchors", str(utm), "--position",
                 f"{EAST + 4},{NORTH + 3}", "--sigma", "0.5", "--trials", "50",
                 "--methods", "ls", "-q"]) == 0
    assert main(["montecarlo", "--anchors", str(utm), "--position", "2e7,0",
                 "--trials", "5", "-q"]) == 2
    assert "within +-1e+07" in capsys.readouterr().err


def test_montecarlo_refuses_a_tag_on_an_anchor(a4, capsys):
    """The tag on anchor A made A's design row [0, 0]: a table of a meaningless model."""
    assert main(["montecarlo", "--anchors", str(a4), "--position", "0,0",
                 "--trials", "50", "-q"]) == 2
    assert "is on anchor A" in capsys.readouterr().err


def test_raim_single_theory_is_at_its_own_alpha(a4, tmp_path):
    """raim-single tests at 0.001 whatever --alpha says; its theory_global said 0.05
    beside a measured 0.0009."""
    out = tmp_path / "mc.csv"
    assert main(["montecarlo", "--anchors", str(a4), "--position", "4,3", "--sigma", "0.5",
                 "--alpha", "0.05", "--trials", "20000", "--faults", "0",
                 "--methods", "snooping,raim-single", "-q", "-o", str(out)]) == 0
    t = pd.read_csv(out).set_index("method")
    assert t.loc["raim-single", "theory_global"] == pytest.approx(0.001)
    assert t.loc["snooping", "theory_global"] == pytest.approx(0.05)
    # measured within 5 binomial standard errors of the theory (20 000 trials)
    for m, a in (("raim-single", 0.001), ("snooping", 0.05)):
        assert abs(t.loc[m, "flag_rate"] - a) <= 5 * np.sqrt(a * (1 - a) / 20000)


def test_montecarlo_refuses_tag_z_in_3d(tmp_path, capsys):
    p = tmp_path / "a3.csv"
    p.write_text("anchor,x,y,z\nA,0,0,1\nB,10,0,2\nC,10,8,3\nD,0,8,1\nE,5,12,2.5\n")
    assert main(["montecarlo", "--anchors", str(p), "--dim", "3", "--tag-z", "5",
                 "--trials", "10", "-q"]) == 2
    assert "applies to --dim 2" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["montecarlo", "--anchors", "{a4}", "--position", "-1,3", "--trials", "20",
     "--methods", "ls", "-q"],
    ["reliability", "--anchors", "{a4}", "--area", "-5,10,0,8", "-o", "{tmp}/rel", "-q",
     "--no-maps"],
    ["simulate", "gnss", "--height", "-100", "--epochs", "1", "-o", "{tmp}/sg", "-q"],
])
def test_negative_numbers_are_values(argv, a4, tmp_path):
    """`--position -1,3` was refused as "expected one argument" (only `=` worked)."""
    argv = [a.format(a4=a4, tmp=tmp_path) for a in argv]
    assert main(argv) == 0


def test_simulated_gnss_truth_degrees_match_its_ecef(tmp_path):
    """lat/lon were written with 4 decimals: 4.9 m from the row's own x, y, z."""
    out = tmp_path / "sg"
    assert main(["simulate", "gnss", "--epochs", "2", "--lat", "47.123456", "--lon",
                 "-122.987654", "-o", str(out), "-q"]) == 0
    t = pd.read_csv(out / "truth.csv")
    x, y, z = pymap3d.geodetic2ecef(t["lat"], t["lon"], t["h"])
    # within the x, y, z columns' own 4 decimals (0.1 mm): 0.2 mm in 3-D
    assert np.max(np.hypot(np.hypot(x - t["x"], y - t["y"]), z - t["z"])) < 2e-4
    assert t["lat"].iloc[0] == pytest.approx(47.123456, abs=1e-9)


def test_stats_summary_says_whose_moments(tmp_path, capsys):
    """With --truth the summary's skewness is of the residuals, every per-anchor skewness
    of the RSSI: they even differ in sign on the wifi-room walk, and nothing said so."""
    sim = tmp_path / "w"
    assert main(["simulate", "wifi-room", "--seed", "1", "-o", str(sim), "-q"]) == 0
    args = [str(sim / "measurements.csv"), "--anchors", str(sim / "anchors.csv")]
    assert main(["stats", *args, "--truth", str(sim / "truth.csv"), "-o",
                 str(tmp_path / "s1")]) == 0
    s1 = json.loads((tmp_path / "s1" / "summary.json").read_text())
    pa = pd.read_csv(tmp_path / "s1" / "per_anchor.csv")
    assert s1["moments_of"] == "residuals"
    assert s1["median_skewness"] == pytest.approx(pa["resid_skewness"].median())
    capsys.readouterr()
    assert main(["stats", *args, "-o", str(tmp_path / "s2"), "--json"]) == 0
    s2 = json.loads(capsys.readouterr().out)
    assert s2["moments_of"] == "rssi"
    pa2 = pd.read_csv(tmp_path / "s2" / "per_anchor.csv")
    assert s2["median_skewness"] == pytest.approx(pa2["skewness"].median())
