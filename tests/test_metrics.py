"""Error statistics: hand values, numpy references, matching, aggregates, improvements."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc.errors import InputError
from robustloc.eval.metrics import epoch_errors, error_stats, error_table


def test_error_stats_hand_values():
    s = error_stats(np.array([3.0, 4.0, 5.0, np.nan]))
    assert s["max"] == 5.0 and s["min"] == 3.0 and s["mean"] == 4.0
    np.testing.assert_allclose(s["rms"], np.sqrt((9 + 16 + 25) / 3))  # seed 000 sigma0
    np.testing.assert_allclose(s["sigma1"], np.sqrt(2 / 3))  # population spread
    assert s["median"] == 4.0
    np.testing.assert_allclose(s["p95"], 4.9)  # linear interpolation
    np.testing.assert_allclose(s["rms"] ** 2, s["mean"] ** 2 + s["sigma1"] ** 2)
    assert np.isnan(error_stats(np.array([]))["mean"])


def test_error_stats_against_numpy_random():
    e = np.random.default_rng(0).gamma(2.0, 1.5, 500)
    s = error_stats(e)
    np.testing.assert_allclose(s["sigma1"], np.std(e))
    np.testing.assert_allclose(s["p95"], np.quantile(e, 0.95))
    np.testing.assert_allclose(s["median"], np.median(e))


def _frames():
    truth = pd.DataFrame({"time": [0.0, 1, 2] * 2, "tag": ["A"] * 3 + ["B"] * 3,
                          "x": [0.0, 1, 2, 10, 10, 10], "y": 0.0})
    ls = truth.assign(x=truth["x"] + [3.0, 4, np.nan, 1, 2, 2], method="ls",
                      status=["ok", "ok", "insufficient_anchors", "ok", "ok", "ok"])
    igg = truth.assign(y=[1.0, 2, 2, 1, 1, 1], method="igg", status="ok")
    bad = truth.assign(x=truth["x"] + 9, method="igg", status="ill_conditioned").iloc[:1]
    return truth, pd.concat([ls, igg], ignore_index=True), bad


def test_error_table_per_tag_aggregates_and_improvement():
    truth, pos, _ = _frames()
    t = error_table(pos, truth).set_index(["tag", "method"])
    a_ls = t.loc[("A", "ls")]
    assert a_ls["n"] == 3 and a_ls["n_failed"] == 1 and a_ls["n_ok"] == 2
    assert a_ls["mean"] == 3.5 and a_ls["max"] == 4.0
    np.testing.assert_allclose(a_ls["rms"], np.sqrt(12.5))
    a_igg = t.loc[("A", "igg")]
    np.testing.assert_allclose(a_igg["mean"], 5 / 3)
    np.testing.assert_allclose(a_igg["mean_impr_pct"], 100 * (3.5 - 5 / 3) / 3.5)
    assert t.loc[("A", "ls"), "mean_impr_pct"] == 0.0
    # "all" pools epochs: ls errors 3, 4, 1, 2, 2 (one failed)
    all_ls = t.loc[("all", "ls")]
    assert all_ls["n"] == 6 and all_ls["n_failed"] == 1
    np.testing.assert_allclose(all_ls["mean"], 12 / 5)
    # "mean" averages the per-tag statistics (paper's Table 1 average rows)
    np.testing.assert_allclose(t.loc[("mean", "ls"), "max"], (4 + 2) / 2)
    np.testing.assert_allclose(t.loc[("mean", "ls"), "mean"], (3.5 + 5 / 3) / 2)
    np.testing.assert_allclose(
        t.loc[("mean", "igg"), "rms_impr_pct"],
        100 * (t.loc[("mean", "ls"), "rms"] - t.loc[("mean", "igg"), "rms"])
        / t.loc[("mean", "ls"), "rms"],
    )
    assert "rms_3d" not in t.columns


def test_tags_named_all_and_mean_stay_apart_from_the_aggregates(tmp_path, capsys):
    """A real tag named ``all`` (or ``mean``) made the baseline's rows share a tag with
    the aggregates: ``evaluate`` died with a pandas traceback.  Now column ``aggregate``
    tells them apart, each row is compared with the baseline's row of its own kind (the
    same hand values as :func:`test_error_table_per_tag_aggregates_and_improvement`,
    tags renamed), and the report brackets the aggregates."""
    from robustloc.cli import main

    truth, pos, _ = _frames()
    names = {"A": "all", "B": "mean"}
    truth, pos = truth.replace({"tag": names}), pos.replace({"tag": names})
    t = error_table(pos, truth)
    assert t["aggregate"].tolist() == [False] * 4 + [True] * 4
    per = t[~t["aggregate"]].set_index(["tag", "method"])
    agg = t[t["aggregate"]].set_index(["tag", "method"])
    assert per.loc[("all", "ls"), "mean"] == 3.5 and per.loc[("all", "ls"), "n"] == 3
    np.testing.assert_allclose(per.loc[("all", "igg"), "mean_impr_pct"],
                               100 * (3.5 - 5 / 3) / 3.5)
    assert agg.loc[("all", "ls"), "n"] == 6
    np.testing.assert_allclose(agg.loc[("all", "ls"), "mean"], 12 / 5)
    np.testing.assert_allclose(agg.loc[("mean", "ls"), "mean"], (3.5 + 5 / 3) / 2)
    np.testing.assert_allclose(
        agg.loc[("all", "igg"), "mean_impr_pct"],
        100 * (agg.loc[("all", "ls"), "mean"] - agg.loc[("all", "igg"), "mean"])
        / agg.loc[("all", "ls"), "mean"])
    truth.to_csv(tmp_path / "t.csv", index=False)
    pos.to_csv(tmp_path / "p.csv", index=False)
    assert main(["evaluate", str(tmp_path / "p.csv"), "--truth", str(tmp_path / "t.csv")]) == 0
    tags = [ln.split()[0] for ln in capsys.readouterr().out.splitlines()[2:]]
    assert tags == ["all", "all", "mean", "mean", "[all]", "[all]", "[mean]", "[mean]"]
    # without such a tag, the aggregates keep their plain names
    t2 = error_table(*_frames()[1::-1])
    assert t2.loc[t2["aggregate"], "tag"].tolist() == ["all", "all", "mean", "mean"]


def test_failed_status_counts_even_with_coordinates():
    truth, pos, bad = _frames()
    # the ill-conditioned row replaces igg's row of the same epoch (a duplicate is refused)
    keep = ~((pos["method"] == "igg") & (pos["time"] == 0.0) & (pos["tag"] == "A"))
    t = error_table(pd.concat([pos[keep], bad]), truth).set_index(["tag", "method"])
    assert t.loc[("A", "igg"), "n_failed"] == 1
    assert t.loc[("A", "igg"), "max"] == 2.0  # the 9 m ill-conditioned fix is not scored


def test_three_d_errors():
    truth = pd.DataFrame({"time": [0.0], "tag": ["T"], "x": [0.0], "y": [0.0], "z": [1.0]})
    pos = pd.DataFrame({"time": [0.0], "tag": ["T"], "x": [3.0], "y": [0.0], "z": [5.0],
                        "method": "nls", "status": "ok"})
    t = error_table(pos, truth)
    assert t.loc[0, "mean"] == 3.0 and t.loc[0, "mean_3d"] == 5.0


def test_time_tolerance_and_unmatched():
    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": ["T", "T"], "x": [0.0, 1.0], "y": 0.0})
    pos = pd.DataFrame({"time": [0.01, 0.98, 5.0], "tag": "T", "x": [0.0, 1.0, 9.0], "y": 0.0})
    with pytest.raises(InputError, match="no positions row matches"):
        error_table(pos, truth)
    t = error_table(pos, truth, time_tolerance_s=0.05)
    assert t.attrs["n_unmatched"] == 1 and t.loc[0, "n"] == 2 and t.loc[0, "max"] == 0.0
    e = epoch_errors(pos, truth, time_tolerance_s=0.05)
    assert list(e["matched"]) == [True, True, False]


def test_duplicate_truth_is_an_error():
    truth = pd.DataFrame({"time": [0.0, 0.0], "tag": ["T", "T"], "x": 0.0, "y": 0.0})
    truth.index = pd.Index([2, 3], name="line")
    with pytest.raises(InputError, match="duplicate truth") as ei:
        error_table(truth.assign(method="ls"), truth)
    assert ei.value.line == 3


def test_missing_truth_epochs_count_as_failed():
    """Issue 15: truth epochs without a position are failed, in n and in failed_pct."""
    truth, pos, _ = _frames()
    drop = (pos["method"] == "igg") & (pos["tag"] == "B") & (pos["time"] > 0)
    t = error_table(pos[~drop], truth).set_index(["tag", "method"])
    b = t.loc[("B", "igg")]
    assert b["n"] == 3 and b["n_missing"] == 2 and b["n_failed"] == 2 and b["n_ok"] == 1
    np.testing.assert_allclose(b["failed_pct"], 100 * 2 / 3)
    assert t.loc[("all", "igg"), "n_missing"] == 2 and t.loc[("all", "igg"), "n"] == 6
    assert t.loc[("B", "ls"), "n_missing"] == 0
    np.testing.assert_allclose(b["mean"], 1.0)  # the one matched epoch: error 1 m


def test_duplicate_positions_rejected_with_line():
    truth, pos, _ = _frames()
    twice = pd.concat([pos, pos.iloc[[4]]], ignore_index=True)
    twice.index = pd.RangeIndex(2, 2 + len(twice), name="line")
    twice.attrs["path"] = "p.csv"
    with pytest.raises(InputError, match=r"duplicate position for time 1.0, tag 'B' and "
                                         r"method 'ls'") as ei:
        error_table(twice, truth)
    assert ei.value.path == "p.csv" and ei.value.line == 2 + len(pos)


def test_integrity_columns_hand_values():
    """Four usable fixes 3-4-5 m off (errors 1, 2, 3, 5 m) with bounds 10, NaN, inf, 4 m
    and one unusable fix: the NaN bound and the 5 m error over 4 m are misleading (2 of
    4, 50 %); the median bound takes NaN as unbounded (median of 4, 10, inf, inf = inf);
    an unusable fix with a tiny bound is not scored.  Without ``hpl`` there are no such
    columns."""
    from robustloc.eval.metrics import INTEGRITY_COLUMNS

    truth = pd.DataFrame({"time": [0.0, 1, 2, 3, 4], "tag": "t", "x": 0.0, "y": 0.0})
    pos = truth.assign(x=[1.0, 2.0, 3.0, 3.0, 9.0], y=[0.0, 0.0, 0.0, 4.0, 0.0],
                       method="m", status=["ok", "ok", "unverified", "fault_detected",
                                           "unavailable"],
                       hpl=[10.0, np.nan, np.inf, 4.0, 0.1])
    row = error_table(pos, truth).set_index("tag").loc["all"]
    assert row["n_misleading"] == 2 and row["misleading_pct"] == pytest.approx(50.0)
    assert row["hpl_median"] == np.inf and row["hpl_over_error"] == np.inf
    finite = pos.assign(hpl=[10.0, 6.0, 8.0, 4.0, 0.1])
    row = error_table(finite, truth).set_index("tag").loc["all"]
    # median bound (6 + 8) / 2 = 7 m over the median error (2 + 3) / 2 = 2.5 m
    assert row["n_misleading"] == 1 and row["hpl_over_error"] == pytest.approx(7.0 / 2.5)
    assert not set(INTEGRITY_COLUMNS) & set(error_table(pos.drop(columns="hpl"), truth))


def test_integrity_columns_with_exact_fixes_and_the_vertical_bound():
    """Fixes exactly at the truth (median error 0: the ratio is inf, no exception -- it
    raised ZeroDivisionError); vertical errors 0.5, 2 and 1 m against vpl 1, 1 and inf:
    one misleading (2 > 1), median vpl 1 m over median vertical error 1 m."""
    truth = pd.DataFrame({"time": [0.0, 1, 2], "tag": "t", "x": 0.0, "y": 0.0, "z": 1.0})
    pos = truth.assign(z=[1.5, 3.0, 0.0], method="m", status="ok", hpl=5.0,
                       vpl=[1.0, 1.0, np.inf])
    row = error_table(pos, truth).set_index("tag").loc["all"]
    assert row["n_misleading"] == 0 and row["hpl_median"] == 5.0
    assert row["hpl_over_error"] == np.inf
    assert row["n_misleading_v"] == 1 and row["misleading_pct_v"] == pytest.approx(100 / 3)
    assert row["vpl_median"] == 1.0 and row["vpl_over_error"] == pytest.approx(1.0)


def test_the_report_counts_misleading_fixes_as_evaluate_does():
    """One definition of a misleading fix: the report's out-of-the-box table
    (``eval.realdata.error_stats``) and its track section (``s60_tracks._mislead``) give
    ``evaluate``'s numbers on the same fixes (a NaN bound exceeded, an infinite one not,
    unusable rows left out)."""
    from robustloc.eval.realdata import error_stats as report_stats
    from robustloc.reproduce.s60_tracks import _mislead

    truth = np.zeros((5, 2))
    pos = np.array([[1.0, 0], [2, 0], [3, 0], [3, 4], [9, 0]])
    hpl = np.array([10.0, np.nan, np.inf, 4.0, 0.1])
    usable = np.array([True, True, True, True, False])
    rep = report_stats(pos, truth, usable, hpl)
    assert rep["misleading"] == pytest.approx(0.5)  # 2 of the 4 usable fixes
    assert rep["hpl_median_over_err_median"] == np.inf
    err = np.where(usable, np.hypot(*pos.T), np.nan)  # a track's rows without a fix: NaN
    assert _mislead(err, hpl) == pytest.approx(0.5)


def test_error_stats_of_huge_errors_do_not_overflow():
    """An error of 1e300 m (an absurd position in a positions file) squared to inf: a
    RuntimeWarning on `evaluate`'s stderr and an infinite rms where the rms is 1e300.
    The squares are now scaled by the largest error; small errors give the same numbers
    as the formula (to rounding)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        s = error_stats(np.array([1e300, 1e300]))
    assert s["rms"] == pytest.approx(1e300, rel=1e-12) and s["sigma1"] == 0.0
    e = np.array([3.0, 4.0, 5.0])
    s = error_stats(e)
    assert s["rms"] == pytest.approx(np.sqrt(np.mean(e * e)), rel=1e-15)
    assert s["sigma1"] == pytest.approx(np.std(e), rel=1e-15)


def test_the_mean_row_is_over_every_tag_or_none():
    """The ``mean`` row skipped the tags where a method had no usable fix: ``nls`` was
    averaged over tag A alone and ``ls`` over A and B, and ``mean_impr_pct`` compared the
    two (-56 % in the self-calibration review).  An error statistic of the mean row is
    now NaN for a method without a usable fix on some tag."""
    truth = pd.DataFrame({"time": [0.0, 1] * 2, "tag": ["A", "A", "B", "B"],
                          "x": 0.0, "y": 0.0})
    ls = truth.assign(x=[1.0, 1.0, 3.0, 3.0], method="ls", status="ok")
    nls = truth.assign(x=[0.5, 0.5, np.nan, np.nan], method="nls",
                       status=["ok", "ok", "unavailable", "unavailable"])
    t = error_table(pd.concat([ls, nls], ignore_index=True), truth)
    mean = t[t["aggregate"] & (t["tag"] == "mean")].set_index("method")
    assert mean.loc["ls", "rms"] == 2.0  # (1 + 3) / 2
    assert np.isnan(mean.loc["nls", "rms"]) and np.isnan(mean.loc["nls", "mean_impr_pct"])
    assert mean.loc["nls", "n_failed"] == 1.0  # counts still average (0 and 2 failed)


def test_a_method_none_of_whose_rows_meets_the_truth_is_all_failed(tmp_path, capsys):
    # every row of `rob` is stamped 0.5 s off the truth epochs: its three epochs are
    # missing (failed), not absent from the table (it vanished: the missing rows were
    # built from the matched rows' methods only)
    truth = pd.DataFrame({"time": [0.0, 1.0, 2.0], "tag": "A", "x": 0.0, "y": 0.0})
    ls = truth.assign(x=[0.0, 1.0, 5.0], method="ls", status="ok")
    rob = truth.assign(time=truth["time"] + 0.5, method="rob", status="ok")
    t = error_table(pd.concat([ls, rob], ignore_index=True), truth).set_index(
        ["tag", "method"])
    r = t.loc[("A", "rob")]
    assert r["n"] == 3 and r["n_missing"] == 3 and r["n_failed"] == 3 and r["n_ok"] == 0
    assert r["failed_pct"] == 100.0 and np.isnan(r["rms"])
    assert t.loc[("all", "rob"), "n_failed"] == 3
    assert t.attrs["n_unmatched"] == 3
    # the command says so too
    from robustloc.cli import main

    pd.concat([ls, rob]).to_csv(tmp_path / "p.csv", index=False)
    truth.to_csv(tmp_path / "t.csv", index=False)
    assert main(["evaluate", str(tmp_path / "p.csv"), "--truth", str(tmp_path / "t.csv"),
                 "--json"]) == 0
    import json

    rows = json.loads(capsys.readouterr().out)["rows"]
    assert {(r["tag"], r["method"], r["n_failed"]) for r in rows if r["method"] == "rob"} == {
        ("A", "rob", 3), ("all", "rob", 3), ("mean", "rob", 3)}


def test_the_mean_row_3d_and_integrity_statistics_are_over_every_tag_or_none():
    # tag A: errors 5 and 1 (3-D as 2-D, z = 0), hpl 10; tag B: no usable fix.  The mean
    # row's 2-D statistics were NaN but its 3-D ones and hpl_median averaged over A alone
    truth = pd.DataFrame({"time": [0.0, 1.0, 0.0], "tag": ["A", "A", "B"], "x": 0.0,
                          "y": 0.0, "z": 0.0})
    pos = truth.assign(x=[5.0, 1.0, np.nan], y=0.0, z=0.0, method="ls",
                       status=["ok", "ok", "unavailable"], hpl=[10.0, 10.0, np.nan])
    t = error_table(pos, truth)
    mean = t[t["aggregate"] & (t["tag"] == "mean")].iloc[0]
    a = t[(t["tag"] == "A") & ~t["aggregate"]].iloc[0]
    assert a["mean_3d"] == 3.0 and a["hpl_median"] == 10.0
    np.testing.assert_allclose(a["rms_3d"], np.sqrt(13.0), rtol=1e-15)  # sqrt((25 + 1) / 2)
    for c in ("mean", "rms", "mean_3d", "rms_3d", "max_3d", "hpl_median", "hpl_over_error"):
        assert np.isnan(mean[c]), c
