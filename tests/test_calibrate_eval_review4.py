"""The calibrate / evaluate / io review (2026-12-06): the two defects it confirmed."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd

from robustloc.cli import main


def _survey(rng: np.random.Generator) -> pd.DataFrame:
    """200 surveyed points of one beacon, 10 samples each sharing the point's multipath
    offset (sd 3 dB), the distance growing with the point's number: more than the 50
    clusters :func:`cluster_robust_lines` keeps, so neighbouring ones are merged."""
    rows = []
    for k in range(200):
        d = 1 + 9 * k / 199
        off = rng.normal(0, 3)
        rows += [("B1", d, -60 - 20 * np.log10(d) + off + rng.normal(0, 1), f"p{k}")
                 for _ in range(10)]
    return pd.DataFrame(rows, columns=["anchor", "distance", "rssi", "cluster"])


def test_survey_standard_errors_do_not_depend_on_row_order(tmp_path):
    """Clusters were numbered in order of appearance, and neighbouring numbers merged:
    a shuffled survey's blocks mixed far-apart points (A_se 0.556 sorted, 0.628
    shuffled).  Now numbered in the ids' natural order (p2 before p10)."""
    s = _survey(np.random.default_rng(0))
    out = {}
    for name, frame in (("sorted", s), ("shuffled", s.sample(frac=1, random_state=1)),
                        ("reversed", s.iloc[::-1])):
        frame.to_csv(tmp_path / f"{name}.csv", index=False)
        assert main(["calibrate", str(tmp_path / f"{name}.csv"), "-o",
                     str(tmp_path / f"cal_{name}.csv")]) == 0
        out[name] = pd.read_csv(tmp_path / f"cal_{name}.csv")
    pd.testing.assert_frame_equal(out["sorted"], out["shuffled"])
    pd.testing.assert_frame_equal(out["sorted"], out["reversed"])


def test_truth_calibration_standard_errors_do_not_depend_on_row_order(tmp_path):
    """`calibrate --measurements --truth`: the dwells were numbered in time order and then
    again in file order (bias_se 0.016 sorted, 0.005 shuffled: 3.3x too small)."""
    rng = np.random.default_rng(0)
    anc = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4", "A5", "A6"],
                        "x": [0, 20, 20, 0, 10, -3], "y": [0, 0, 20, 20, -4, 10]})
    bias = np.array([0.5, -0.3, 0.0, 0.8, -0.6, 0.2])
    t = np.arange(600) * 0.5
    px = 10 + 7 * np.sin(t / 13.0) + 2 * np.cos(t / 3.1)
    py = 10 + 7 * np.cos(t / 17.0) + 2 * np.sin(t / 2.3)
    axy = anc[["x", "y"]].to_numpy(float)
    d = np.hypot(axy[None, :, 0] - px[:, None], axy[None, :, 1] - py[:, None])
    # slowly varying errors (an AR(1) per anchor): what cluster-robust errors are for
    e = np.zeros_like(d)
    for k in range(1, len(t)):
        e[k] = 0.95 * e[k - 1] + rng.normal(0, 0.05, 6)
    r = d + bias + e
    meas = pd.DataFrame({"time": np.repeat(t, 6), "tag": "T1",
                         "anchor": np.tile(anc["anchor"], len(t)), "range": r.ravel()})
    anc.to_csv(tmp_path / "anchors.csv", index=False)
    pd.DataFrame({"time": t, "tag": "T1", "x": px, "y": py}).to_csv(tmp_path / "truth.csv",
                                                                    index=False)
    out = {}
    for name, frame in (("sorted", meas), ("shuffled", meas.sample(frac=1, random_state=3))):
        frame.to_csv(tmp_path / f"m_{name}.csv", index=False)
        assert main(["calibrate", "--measurements", str(tmp_path / f"m_{name}.csv"),
                     "--truth", str(tmp_path / "truth.csv"), "--anchors",
                     str(tmp_path / "anchors.csv"), "-o",
                     str(tmp_path / f"c_{name}.csv")]) == 0
        out[name] = pd.read_csv(tmp_path / f"c_{name}.csv")
    pd.testing.assert_frame_equal(out["sorted"], out["shuffled"], rtol=1e-9)


def test_evaluate_says_unbounded_not_blank(tmp_path, capsys):
    """A usable fix without an hpl counts as unbounded: -o said inf, --json null (its
    word for "no such value") and the text report left the cell blank."""
    (tmp_path / "t.csv").write_text("time,tag,x,y\n0,a,0,0\n1,a,1,0\n")
    (tmp_path / "p.csv").write_text("time,tag,x,y,method,status,hpl\n"
                                    "0,a,0.2,0,ls,ok,\n1,a,1.1,0,ls,ok,\n")
    args = [str(tmp_path / "p.csv"), "--truth", str(tmp_path / "t.csv")]
    assert main(["evaluate", *args, "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert rows[0]["hpl_median"] is None
    assert {"hpl_median", "hpl_over_error"} <= set(rows[0]["infinite"])
    assert "rms" not in rows[0]["infinite"]
    assert main(["evaluate", *args]) == 0
    text = capsys.readouterr().out.splitlines()
    head = text[1].split()
    cells = text[2].split()
    assert cells[head.index("hpl_over_error")] == "inf"
