"""`robustloc stats --truth`: rows outside the truth, and duplicate truth (review D7, D8).

D7: the truth was held constant beyond its time span (np.interp), so a moving tag's rows
after its last truth row were binned at its last known distance; rows of a tag without
truth were dropped without a word.  D8: two truth rows for one (time, tag) were accepted
(np.interp picked either), while `evaluate` refuses the same file.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.errors import InputError
from robustloc.eval.rssi_stats import RssiStatistics

SPEED = 0.1  # m/s along +x from (1, 0)
T_TRUTH = 10  # truth rows at t = 0..10 s: x = 1 .. 2 m
T_MEAS = 30  # measurements at t = 0..30 s: x would reach 4 m
N_U = 7  # epochs of tag U, which has no truth


def _rssi(k: int) -> float:
    """A non-constant, plausible RSSI (dBm), the same for every run."""
    return -60.0 + float((k * 7) % 5) - 0.5 * (k % 3)


def _files(tmp_path: Path, dup: bool = False) -> dict[str, Path]:
    anchors = pd.DataFrame({"anchor": ["A", "B"], "x": [0.0, 10.0], "y": [0.0, 0.0]})
    rows = []
    for k in range(T_MEAS + 1):
        for a in ("A", "B"):
            rows.append((float(k), "T", a, _rssi(k + (a == "B"))))
    for k in range(N_U):
        for a in ("A", "B"):
            rows.append((float(k), "U", a, _rssi(k)))
    rows.append((3.5, "U", "A", -200.0))  # outside the physical limits: invalid, not U's
    meas = pd.DataFrame(rows, columns=["time", "tag", "anchor", "rssi"])
    t = np.arange(T_TRUTH + 1, dtype=float)
    truth = pd.DataFrame({"time": t, "tag": "T", "x": 1.0 + SPEED * t, "y": 0.0})
    if dup:  # header line 1, t = 0..10 on lines 2..12, then t = 4 and 5 again (13, 14)
        truth = pd.concat([truth, truth.iloc[[4, 5]].assign(x=50.0)], ignore_index=True)
    paths = {k: tmp_path / f"{k}.csv" for k in ("anchors", "meas", "truth")}
    anchors.to_csv(paths["anchors"], index=False)
    meas.to_csv(paths["meas"], index=False)
    truth.to_csv(paths["truth"], index=False)
    return paths


def _run(paths: dict[str, Path], out: Path, *extra: str) -> int:
    return main(["stats", str(paths["meas"]), "--anchors", str(paths["anchors"]),
                 "--truth", str(paths["truth"]), "-o", str(out), "--min-samples", "2",
                 *extra])


def test_rows_outside_the_truth_span_and_without_truth_are_left_out_and_counted(
        tmp_path, capsys):
    paths = _files(tmp_path)
    out = tmp_path / "out"
    assert _run(paths, out, "--json") == 0
    cap = capsys.readouterr()
    summary = json.loads(cap.out)
    assert summary == json.loads((out / "summary.json").read_text())
    # analysed: T at t = 0..10 with both anchors; left out: T at t = 11..30 (outside the
    # span) and all of U (no truth); the -200 dBm row counts as invalid only
    n_in = T_TRUTH + 1
    n_out = 2 * (T_MEAS - T_TRUTH)
    assert summary["n_samples"] == 2 * n_in
    assert summary["n_outside_truth_span"] == n_out
    assert summary["n_without_truth"] == 2 * N_U
    assert summary["invalid_measurement"] == 1
    assert cap.err.splitlines() == [
        f"note: {2 * N_U} measurement rows had no truth (their tag is not in the truth) "
        "and were not analysed",
        f"note: {n_out} measurement rows lay outside their tag's truth time span and were "
        "not analysed (the truth is not extrapolated)",
    ]
    pa = pd.read_csv(out / "per_anchor.csv").set_index("anchor")
    assert pa["n"].to_dict() == {"A": n_in, "B": n_in}
    # within the span x runs from 1 to 2 m: |A| from 1 to 2, |B| from 9 to 8
    x_end = 1.0 + SPEED * T_TRUTH
    assert pa.loc["A", "distance_min_m"] == pytest.approx(1.0)
    assert pa.loc["A", "distance_max_m"] == pytest.approx(x_end)
    assert pa.loc["B", "distance_min_m"] == pytest.approx(10.0 - x_end)
    assert pa.loc["B", "distance_max_m"] == pytest.approx(9.0)
    pb = pd.read_csv(out / "per_bin.csv")
    assert pb["n"].sum() == 2 * n_in  # no bin holds a row outside the span
    assert pb.loc[pb["anchor"] == "A", "distance_m"].max() == pytest.approx(2.0)


def test_interpolation_inside_the_span_and_its_exact_ends(tmp_path):
    """Rows between truth rows are interpolated; a row at t_max is in, just after it out."""
    anchors = pd.DataFrame({"anchor": ["A"], "x": [0.0], "y": [0.0]})
    truth = pd.DataFrame({"time": [0.0, 10.0], "tag": "T", "x": [1.0, 2.0], "y": 0.0})
    meas = pd.DataFrame({"time": [0.0, 2.5, 10.0, 10.0 + 1e-9, -1e-9], "tag": "T",
                         "anchor": "A", "rssi": [-60.0, -61.0, -62.0, -63.0, -64.0]})
    res = RssiStatistics(min_samples=2).compute(meas, anchors, truth)
    assert res.samples.sort_values("time")["distance_m"].tolist() == pytest.approx(
        [1.0, 1.25, 2.0])
    assert (res.n_outside_truth_span, res.n_without_truth) == (2, 0)


def test_a_tag_with_one_truth_row_is_a_static_point(tmp_path):
    """The documented convention (a survey point, as reproduce s30 builds its Table 1
    truth): one truth row holds at every time of its tag."""
    anchors = pd.DataFrame({"anchor": ["A"], "x": [0.0], "y": [0.0]})
    truth = pd.DataFrame({"time": [0.0], "tag": "S", "x": [3.0], "y": [4.0]})
    meas = pd.DataFrame({"time": np.arange(12.0), "tag": "S", "anchor": "A",
                         "rssi": [_rssi(k) for k in range(12)]})
    res = RssiStatistics(min_samples=2).compute(meas, anchors, truth)
    assert res.summary()["n_samples"] == 12 and res.n_outside_truth_span == 0
    assert np.allclose(res.samples["distance_m"], 5.0)


def test_every_row_outside_the_span_is_an_error_saying_so(tmp_path, capsys):
    paths = _files(tmp_path)
    pd.DataFrame({"time": [100.0, 110.0], "tag": "T", "x": [1.0, 2.0], "y": 0.0}).to_csv(
        paths["truth"], index=False)
    assert _run(paths, tmp_path / "out") == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err == (f"error: {paths['truth']}: no measurement has a truth position: none "
                   "lies within its tag's truth time span (the truth is not extrapolated)")
    assert not (tmp_path / "out").exists()


def test_duplicate_truth_is_refused_as_evaluate_refuses_it(tmp_path, capsys):
    paths = _files(tmp_path, dup=True)
    want = f"error: {paths['truth']}:13: duplicate truth for time 4.0 and tag 'T'"
    assert _run(paths, tmp_path / "out") == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == want
    assert not (tmp_path / "out").exists()
    # the same file given to evaluate: the same refusal, word for word
    pos = tmp_path / "pos.csv"
    pd.DataFrame({"time": [0.0], "tag": ["T"], "x": [1.0], "y": [0.0]}).to_csv(
        pos, index=False)
    assert main(["evaluate", str(pos), "--truth", str(paths["truth"])]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == want


def test_duplicate_truth_frame_is_refused_by_the_library_too():
    """A frame that did not pass the reader (the Python API) meets the same check."""
    anchors = pd.DataFrame({"anchor": ["A"], "x": [0.0], "y": [0.0]})
    truth = pd.DataFrame({"time": [0.0, 1.0, 1.0], "tag": "T", "x": [1.0, 2.0, 9.0],
                          "y": 0.0})
    meas = pd.DataFrame({"time": [0.0, 1.0], "tag": "T", "anchor": "A",
                         "rssi": [-60.0, -61.0]})
    with pytest.raises(InputError, match=r"duplicate truth for time 1.0 and tag 'T'"):
        RssiStatistics(min_samples=2).compute(meas, anchors, truth)
