"""Anchor parameters that only make sense positive are refused with file and line
(issue 15: `n = 0` printed a numpy array, `scale <= 0` named the file but not the line)."""

from __future__ import annotations

import pytest

from robustloc.cli import main


@pytest.mark.parametrize(("header", "rows", "message"), [
    ("anchor,x,y,A,n", ["a,0,0,-60,0", "b,10,0,-60,2", "c,0,10,-60,2"],
     "an.csv:2: path-loss exponent n must be positive, got 0 for anchor 'a'"),
    ("anchor,x,y,bias,scale", ["a,0,0,0,1", "b,10,0,0,-1", "c,0,10,0,1"],
     "an.csv:3: range scale must be positive, got -1 for anchor 'b'"),
    ("anchor,x,y,sigma", ["a,0,0,0.1", "b,10,0,0.2", "c,0,10,0"],
     "an.csv:4: sigma must be positive, got 0 for anchor 'c'"),
    # the input review: these overflowed into every range (every epoch
    # invalid_measurement, the file unnamed) or made every fix ill_conditioned
    ("anchor,x,y,bias,scale", ["a,0,0,1e300,1", "b,10,0,0,1", "c,0,10,0,1"],
     "an.csv:2: range bias must lie in [-100000, 100000], got 1e+300 for anchor 'a'"),
    ("anchor,x,y,bias,scale", ["a,0,0,0,1", "b,10,0,0,1e-300", "c,0,10,0,1"],
     "an.csv:3: range scale must lie in [0.001, 1000], got 1e-300 for anchor 'b'"),
    ("anchor,x,y,sigma", ["a,0,0,0.1", "b,10,0,0.2", "c,0,10,1e-300"],
     "an.csv:4: sigma must lie in [1e-06, 1e+06], got 1e-300 for anchor 'c'"),
])
def test_absurd_anchor_parameters_name_the_line(tmp_path, capsys, header, rows, message):
    (tmp_path / "an.csv").write_text("\n".join([header, *rows]) + "\n")
    value = "rssi" if ",A,n" in header else "range"
    (tmp_path / "m.csv").write_text(f"time,tag,anchor,{value}\n0,t,a,-70\n0,t,b,-70\n"
                                    "0,t,c,-70\n" if value == "rssi" else
                                    f"time,tag,anchor,{value}\n0,t,a,7\n0,t,b,7\n0,t,c,7\n")
    rc = main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "an.csv"),
               "-o", str(tmp_path / "p.csv")])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.startswith("error: ") and message in err and "Traceback" not in err
    assert not (tmp_path / "p.csv").exists()


def test_a_calibration_of_near_exact_ranges_is_read_back(tmp_path):
    """Ranges with 1e-9 m of noise: ``calibrate --self`` finds sigmas of some 1e-9 m,
    below what an anchors file may carry (1e-6, as ``--sigma``).  It writes the floor, so
    that ``locate`` reads the calibrated file (refused otherwise, naming the line)."""
    import numpy as np
    import pandas as pd

    a = pd.DataFrame({"anchor": ["a", "b", "c", "e"], "x": [0, 10, 10, 0.0],
                      "y": [0, 0, 10, 10.0]})
    a.to_csv(tmp_path / "an.csv", index=False)
    rng = np.random.default_rng(0)
    rows = []
    for k in range(40):
        p = rng.uniform(1, 9, 2)
        rows += [(float(k), "t", r.anchor, float(np.hypot(p[0] - r.x, p[1] - r.y)) + 0.2
                  + rng.normal(0.0, 1e-9)) for r in a.itertuples()]
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]).to_csv(
        tmp_path / "m.csv", index=False)
    assert main(["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
                 str(tmp_path / "an.csv"), "-o", str(tmp_path / "cal.csv")]) == 0
    cal = pd.read_csv(tmp_path / "cal.csv")
    assert (cal["sigma"] == 1e-6).all()
    assert np.allclose(cal["bias"], 0.2, atol=1e-6)
    assert main(["locate", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "cal.csv"),
                 "-o", str(tmp_path / "p.csv")]) == 0
    assert len(pd.read_csv(tmp_path / "p.csv")) == 40


def _gap_files(tmp_path):
    """Four anchors with a log-distance model whose second anchor has no A (line 3)."""
    (tmp_path / "an.csv").write_text("anchor,x,y,A,n\na,0,0,-40,2\nb,10,0,,2\n"
                                     "c,10,10,-40,2\nd,0,10,-40,2\n")
    (tmp_path / "m.csv").write_text(
        "time,tag,anchor,rssi\n" + "".join(f"{t},t,{a},-60\n" for t in range(3)
                                            for a in "abcd"))
    return str(tmp_path / "an.csv"), str(tmp_path / "m.csv")


@pytest.mark.parametrize("command", ["locate", "track", "filter"])
def test_an_anchor_without_its_path_loss_value_is_named_with_its_line(
        tmp_path, capsys, command):
    # track said "an.csv: anchor 'b' ..." without the line: the tracker's copy of the
    # anchors had lost the file's line numbers
    an, m = _gap_files(tmp_path)
    assert main([command, m, "--anchors", an, "-o", str(tmp_path / "o.csv"), "-q"]) == 2
    assert capsys.readouterr().err.strip().endswith(
        "an.csv:3: anchor 'b' has no value for 'A' (log-distance model)")


@pytest.mark.parametrize("command", ["reliability", "montecarlo"])
def test_planners_refuse_a_path_loss_model_with_a_gap(tmp_path, capsys, command):
    # they took the file for a ranging layout and planned 1 m ranges without a word
    an, _ = _gap_files(tmp_path)
    extra = ["--trials", "20"] if command == "montecarlo" else ["--no-maps", "-q"]
    out = str(tmp_path / ("o.csv" if command == "montecarlo" else "plan"))
    assert main([command, "--anchors", an, "-o", out, *extra]) == 2
    assert "an.csv:3: anchor 'b' has no value for 'A'" in capsys.readouterr().err
    # --model range says the path-loss columns do not matter
    assert main([command, "--anchors", an, "-o", out, "--model", "range", *extra]) == 0
