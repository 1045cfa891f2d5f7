"""A survey file's optional ``cluster`` column (docs/formats.md): any ids, the standard
errors cluster-robust over them.  (Text ids were a ValueError traceback in ``calibrate``;
integer ids were read silently and undocumented.)"""

from __future__ import annotations

import numpy as np
import pandas as pd

from robustloc.cli import main
from robustloc.models.calibration import calibrate_pathloss


def _survey(seed: int = 0) -> pd.DataFrame:
    """Three anchors, 10 surveyed points each, 20 samples per point: each point's own
    multipath offset (sd 2 dB, shared by its samples) plus 0.5 dB of sample noise."""
    rng = np.random.default_rng(seed)
    rows = []
    for a in ("1", "2", "3"):
        for d in range(1, 11):
            off = rng.normal(0.0, 2.0)
            for _ in range(20):
                rows.append((a, float(d), -60 - 22 * np.log10(d) + off + rng.normal(0, 0.5),
                             f"{a}-point-{d}"))
    return pd.DataFrame(rows, columns=["anchor", "distance", "rssi", "cluster"])


def test_text_cluster_ids_give_cluster_robust_errors():
    s = _survey()
    with_text = calibrate_pathloss(s).table.set_index("anchor")
    codes = s.assign(cluster=pd.factorize(s["cluster"])[0])
    with_codes = calibrate_pathloss(codes).table.set_index("anchor")
    pd.testing.assert_frame_equal(with_text, with_codes)
    alone = calibrate_pathloss(s.drop(columns="cluster")).table.set_index("anchor")
    # the design effect of 20 samples sharing an offset of 2 dB over 0.5 dB of noise:
    # 1 + 19 * 4 / 4.25 = 18.9, so the independent rows' errors are sqrt(18.9) = 4.3x too
    # small; 10 clusters estimate it to about 1 / sqrt(2 * 9) = 24 %: above 2 by far
    ratio = with_text.loc[["1", "2", "3"], "A_se"] / alone.loc[["1", "2", "3"], "A_se"]
    assert (ratio > 2.0).all(), ratio


def test_rows_without_a_cluster_stand_alone():
    s = _survey()
    s.loc[s.index[:5], "cluster"] = np.nan
    t = calibrate_pathloss(s).table
    assert np.isfinite(t["A_se"]).all()


def test_calibrate_reads_a_survey_file_with_text_clusters(tmp_path, capsys):
    _survey().to_csv(tmp_path / "s.csv", index=False)
    (tmp_path / "a.csv").write_text("anchor,x,y\n1,0,0\n2,10,0\n3,0,10\n")
    out = tmp_path / "c.csv"
    assert main(["calibrate", str(tmp_path / "s.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(out)]) == 0
    assert "Traceback" not in capsys.readouterr().err
    assert np.isfinite(pd.read_csv(out)["A_se"]).all()


def test_an_all_empty_cluster_column_is_as_no_column(tmp_path, capsys):
    """A column with no id in it says no more than one left out: the rows independent
    (an IndexError traceback on the empty list of ids, exit 1, before: the commands
    review).  The written anchors are byte for byte those of the survey without it."""
    s = _survey().drop(columns="cluster")
    s.to_csv(tmp_path / "plain.csv", index=False)
    s.assign(cluster="").to_csv(tmp_path / "empty.csv", index=False)
    outs = []
    for name in ("plain", "empty"):
        out = tmp_path / f"{name}_out.csv"
        assert main(["calibrate", str(tmp_path / f"{name}.csv"), "-o", str(out)]) == 0
        assert "Traceback" not in capsys.readouterr().err
        outs.append(out.read_bytes())
    assert outs[0] == outs[1]


def test_blank_cluster_ids_in_a_frame_stand_alone_as_a_file_s_empty_fields():
    """From Python, "" (or blanks) is a missing id as a file's empty field is: all-blank
    is as no column (an IndexError before), and a few blank rows stand alone, as NaN."""
    s = _survey()
    plain = calibrate_pathloss(s.drop(columns="cluster")).table
    for blank in ("", "  "):
        pd.testing.assert_frame_equal(calibrate_pathloss(s.assign(cluster=blank)).table,
                                      plain)
    some_nan, some_blank = s.copy(), s.copy()
    some_nan.loc[s.index[:30], "cluster"] = np.nan
    some_blank.loc[s.index[:30], "cluster"] = ""
    pd.testing.assert_frame_equal(calibrate_pathloss(some_blank).table,
                                  calibrate_pathloss(some_nan).table)
