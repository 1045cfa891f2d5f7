"""A row without a value at the time of a valid sample of its link (the filter review).

``robustloc filter`` sets an RSSI outside the physical limits aside (NaN for the filter);
when it shared its time with a valid sample of the same link, the two were one merged
sample and the invalid row got that sample's weight, innovation and posterior state,
while ``--help`` says it is not fed to the filter and carries the filter's prediction.
The summary counted rows: one rejected sample of two rows was 2 rejections, and "filtered
N samples" counted rows never filtered.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.filters.rssi import RobustRssiFilter

ANCHORS = "anchor,x,y,A,n\nAP1,9.0,7.8,-26.353,2.556\n"


def _log(values: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t = np.array([v[0] for v in values])
    return np.zeros(t.size, dtype=np.int64), t, np.array([v[1] for v in values])


# a walk of five samples, then a fade at t = 5 (rejected) with a missing one beside it
HEAD = [(float(t), -50.0 - 0.8 * t) for t in range(5)]


def test_a_nan_sample_merged_with_a_finite_one_gets_the_prediction():
    filt = RobustRssiFilter()
    both = filt.filter_samples(*_log([*HEAD, (5.0, -75.0), (5.0, np.nan)]))
    alone = filt.filter_samples(*_log([*HEAD, (5.0, np.nan)]))  # the prediction at t = 5
    valid = filt.filter_samples(*_log([*HEAD, (5.0, -75.0)]))
    assert valid.weight[5] == 0.0  # the fade is rejected: its posterior is not its prior
    for name in ("rssi_dbm", "distance_m", "speed_mps", "rssi_var_db2"):
        got, pred = getattr(both, name), getattr(alone, name)
        assert got[6] == pred[5], name  # the NaN row: the prediction, not the update
        assert got[5] == getattr(valid, name)[5], name  # the valid row: unchanged
    assert not np.isclose(both.distance_m[6], valid.distance_m[5])
    for name in ("innovation_db", "standardized", "scale_db", "weight"):
        assert np.isnan(getattr(both, name)[6]), name
    assert not both.relocked[6] and not both.restarted[6]
    assert both.extra["duplicates_merged"] == 0


def test_a_nan_sample_beside_the_first_sample_of_its_link_has_no_prediction():
    res = RobustRssiFilter().filter_samples(*_log([(0.0, np.nan), (0.0, -50.0),
                                                   (1.0, -51.0)]))
    assert np.isnan(res.rssi_dbm[0]) and np.isnan(res.distance_m[0])
    assert np.isnan(res.weight[0]) and res.weight[1] == 1.0


def _write(path, rows):
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "rssi"]).to_csv(path, index=False)
    return str(path)


@pytest.mark.parametrize("static", [False, True])
def test_filter_an_invalid_row_is_not_fed_and_not_counted(tmp_path, capsys, static):
    (tmp_path / "a.csv").write_text(ANCHORS)
    head = [(float(t), "T1", "AP1", -50.0) for t in range(5)]
    tail = [(6.0, "T1", "AP1", -50.0)]
    opts = ["--anchors", str(tmp_path / "a.csv"), "--json"] + (["--static"] if static
                                                               else [])
    frames, summaries = {}, {}
    for name, rows in {
        "invalid": [*head, (5.0, "T1", "AP1", -70.0), (5.0, "T1", "AP1", -500.0), *tail],
        "alone": [*head, (5.0, "T1", "AP1", -500.0), *tail],  # the prediction at t = 5
        "duplicate": [*head, (5.0, "T1", "AP1", -70.0), (5.0, "T1", "AP1", -70.0), *tail],
    }.items():
        out = tmp_path / f"{name}.csv"
        assert main(["filter", _write(tmp_path / f"m_{name}.csv", rows), *opts,
                     "-o", str(out)]) == 0
        summaries[name] = json.loads(capsys.readouterr().out)
        frames[name] = pd.read_csv(out)
    f, alone = frames["invalid"], frames["alone"]
    assert f.loc[5, "weight"] == 0.0 and f.loc[6, "status"] == "invalid_measurement"
    assert np.isnan(f.loc[6, "weight"]) and np.isnan(f.loc[6, "innovation"])
    assert not f.loc[6, "relocked"]
    for c in ("distance_state", "speed"):
        assert f.loc[6, c] == alone.loc[5, c], c
    s = summaries["invalid"]
    assert (s["samples"], s["filtered_samples"], s["invalid_measurement"]) == (8, 7, 1)
    assert (s["rejected"], s["downweighted"]) == (1, 1)
    # two valid rows at one time: one sample, one rejection
    d = summaries["duplicate"]
    assert (d["samples"], d["filtered_samples"], d["duplicates_merged"]) == (8, 7, 1)
    assert (d["rejected"], d["downweighted"]) == (1, 1)
    assert d["share_downweighted"] == pytest.approx(1 / 6)  # of the 6 with an innovation


def test_filter_text_summary_counts_samples_and_rows(tmp_path, capsys):
    (tmp_path / "a.csv").write_text(ANCHORS)
    rows = [(float(t), "T1", "AP1", -50.0) for t in range(5)] + [(4.0, "T1", "AP1", -500.0)]
    assert main(["filter", _write(tmp_path / "m.csv", rows), "--anchors",
                 str(tmp_path / "a.csv"), "-o", str(tmp_path / "f.csv")]) == 0
    assert "filtered 5 samples (6 rows) on 1 links" in capsys.readouterr().out


def test_the_dask_partitions_count_the_same_samples(tmp_path):
    """``--engine dask`` adds each tag partition's counts (filter_partition) and takes the
    share of down-weighted samples from their moments: one row per merged sample there
    too, invalid rows left out, the single process's number."""
    from robustloc.cli import build_parser
    from robustloc.commands.filter import combine_partitions, filter_frame, filter_partition
    from robustloc.io import read_anchors, read_measurements

    (tmp_path / "a.csv").write_text(ANCHORS)
    rows = [(float(t), "T1", "AP1", -50.0) for t in range(8)]
    rows += [(5.0, "T1", "AP1", -70.0), (5.0, "T1", "AP1", -70.0), (6.0, "T1", "AP1", -500.0),
             (3.0, "T1", "AP1", -56.0)]
    path = _write(tmp_path / "m.csv", rows)
    args = build_parser().parse_args(["filter", path, "--anchors", str(tmp_path / "a.csv"),
                                      "-o", str(tmp_path / "f.csv")])
    anchors = read_anchors(args.anchors)
    meas = read_measurements(path, anchors)
    _, local = filter_frame(meas, anchors, args)
    _, counts = filter_partition(meas, anchors, args)
    shared = combine_partitions([counts])
    assert local["filtered_samples"] == counts["filtered_samples"] == 8
    assert shared["share_downweighted"] == local["share_downweighted"]
    assert local["downweighted"] >= 1
    assert local["share_downweighted"] == local["downweighted"] / 7  # 8 minus the first
