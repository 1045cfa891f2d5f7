"""The fourth review of ``evaluate`` and ``stats``: errors beyond the floats' range, a
positions file whose extra columns bear internal names, the matching hint, the order of
the method rows, the anchors of the stats figures and the distance bins' labels.  The
commands run with every warning an error."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest
from test_eval_review3 import _evaluate_files, _run  # (every warning an error)


def _rows(capsys) -> dict[tuple[str, str], dict]:
    out = json.loads(capsys.readouterr().out)["rows"]
    return {(r["tag"], r["method"]): r for r in out}


# ------------------------------------------------------- 1. statistics of huge errors
def test_mean_median_and_sigma1_of_huge_errors_do_not_overflow(tmp_path, capsys):
    """Errors of sqrt(2) 1e308 m (finite): the mean, the median (the mean of the two
    middle errors) and sigma1 summed them to inf, with a RuntimeWarning, while max and
    rms were finite; the "mean" row over two such tags likewise, and the hpl median.
    Each is now at most the max: here all equal to it, sigma1 0 (exactly: the errors
    are equal, and the scaling by a power of two is exact)."""
    truth = pd.DataFrame({"time": [0.0, 1.0, 0.0, 1.0], "tag": ["A", "A", "B", "B"],
                          "x": 0.0, "y": 0.0})
    pos = truth.assign(x=[1e308, -1e308, 1e308, -1e308], y=1e308, method="ls",
                       status="ok", hpl=1e308)
    args = _evaluate_files(tmp_path, pos, truth)
    assert _run([*args, "--json", "--plot", str(tmp_path / "f.png")]) == 0
    by = _rows(capsys)
    e = float(np.hypot(1e308, 1e308))
    for key in (("A", "ls"), ("all", "ls"), ("mean", "ls")):
        r = by[key]
        assert r["infinite"] == [], key
        for c in ("max", "min", "mean", "rms", "median", "p95"):
            assert r[c] == e, (key, c)
        assert r["sigma1"] == 0.0 and r["hpl_median"] == 1e308, key


def test_a_fix_whose_error_overflows_is_usable_and_scored(tmp_path, capsys):
    """A fix at x = 1e308 (finite, status ok) against a truth at -1e308: the difference
    overflowed to inf (a RuntimeWarning on stderr) and ``isfinite(error)`` counted the fix
    failed and left it out of the statistics (max 5, n_failed 1).  It is usable: its
    error is inf, and so are max, mean, rms, sigma1, and median and p95 here (the linear
    interpolation between 5 and inf); min stays 5.  In 3-D, likewise: it has a vertical
    solution (z given), its 3-D error is inf; a fix without z stays out of the 3-D
    statistics (its 3-D error NaN, not the inf of hypot(inf, NaN))."""
    truth = pd.DataFrame({"time": [0.0, 1.0, 2.0], "tag": "A", "x": [-1e308, 0.0, 0.0],
                          "y": 0.0, "z": 0.0})
    pos = pd.DataFrame({"time": [0.0, 1.0, 2.0], "tag": "A", "x": [1e308, 3.0, 1e308],
                        "y": [0.0, 4.0, 0.0], "z": [0.0, 0.0, np.nan], "method": "ls",
                        "status": "ok", "hpl": 10.0})
    pos.loc[2, "x"] = 0.0  # the third: error 0 horizontally, no z
    args = _evaluate_files(tmp_path, pos, truth)
    assert _run([*args, "--json", "--plot", str(tmp_path / "f.png")]) == 0
    r = _rows(capsys)["A", "ls"]
    assert (r["n"], r["n_failed"], r["n_ok"], r["n_ok_3d"]) == (3, 0, 3, 2)
    assert r["min"] == 0.0 and r["min_3d"] == 5.0
    assert {"max", "mean", "rms", "sigma1", "max_3d", "mean_3d", "rms_3d", "sigma1_3d",
            "median_3d", "p95_3d"} <= set(r["infinite"])
    assert r["median"] == 5.0 and "median" not in r["infinite"]
    assert r["n_misleading"] == 1  # inf > hpl 10
    # the text report: scored, not failed, and no warning on stderr
    assert _run(args) == 0
    out = capsys.readouterr()
    assert "inf" in out.out and out.err == ""


# ------------------------------------------------- 2. extra columns with internal names
@pytest.mark.parametrize("col", ["x_true", "y_true", "z_true", "_truth_row", "_t_true",
                                 "_row"])
def test_extra_positions_columns_with_internal_names(tmp_path, capsys, col):
    """An extra positions column named as a column the matching adds (x_true, ...,
    _truth_row) or uses (_t_true, _row) ended evaluate in a KeyError traceback (exit 1),
    or (_row) was overwritten, and a z_true beside a z with a 2-D truth was taken for the
    truth's z.  The matched truth's replace the first kind, the helpers take other names
    and are carried through: the table is the one without the column (errors 5 and 1,
    not 3-D)."""
    from robustloc.eval.metrics import match_truth

    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": "A", "x": 0.0, "y": 0.0})
    pos = pd.DataFrame({"time": [1.0, 0.0], "tag": "A", "x": [1.0, 3.0], "y": [0.0, 4.0],
                        "z": 1.0, "method": "ls", "status": "ok", col: [7.0, 9.0]})
    assert _run([*_evaluate_files(tmp_path, pos, truth), "--json"]) == 0
    r = _rows(capsys)["A", "ls"]
    assert (r["n_ok"], r["max"], r["min"], r["mean"]) == (2, 5.0, 1.0, 3.0)
    assert "rms_3d" not in r
    m = match_truth(pos, truth)
    if col in ("_t_true", "_row"):
        assert m[col].tolist() == [7.0, 9.0]
    else:
        assert col not in ("x_true", "y_true") or m[col].tolist() == [0.0, 0.0]
        assert col != "_truth_row" or m[col].tolist() == [1, 0]
        assert col != "z_true" or "z_true" not in m.columns


# ------------------------------------------------------------------ 3. the matching hint
def test_the_time_hint_needs_most_rows_unmatched(tmp_path, capsys):
    """1000 of 1001 positions rows matched, and the hint said positions and truth
    "mostly miss each other's times" (n_missing >= n_unmatched // 2 held for one
    unmatched row).  It now needs most rows of both sides unmatched; the note on the
    one row stays (test_newuser_review2 has the case that does get the hint)."""
    truth = pd.DataFrame({"time": np.arange(1000.0), "tag": "A", "x": 0.0, "y": 0.0})
    pos = pd.concat([truth.assign(x=1.0), truth.iloc[:1].assign(time=1000.5)],
                    ignore_index=True).assign(method="ls", status="ok")
    args = _evaluate_files(tmp_path, pos, truth)
    assert _run([*args, "-q", "-o", str(tmp_path / "out.csv")]) == 0
    err = capsys.readouterr().err
    assert "1 position rows had no truth" in err and "hint" not in err


# ---------------------------------------------------------------- 4. the rows' order
def test_the_table_and_the_figure_do_not_depend_on_the_rows_order(tmp_path, capsys):
    """The method rows came in the order the file's rows first named them: the same
    rows in another order gave another table (and another figure: colours, legends and
    the Stanford panels follow the methods' order).  Now the --baseline method comes
    first and the others by name, in the table and in the figure."""
    from robustloc.eval.metrics import epoch_errors
    from robustloc.eval.plots import render_evaluation_figure

    truth = pd.DataFrame({"time": [0.0], "tag": "A", "x": 0.0, "y": 0.0})
    pos = pd.DataFrame({"time": 0.0, "tag": "A", "x": [0.0, 3.0, 1.0, 2.0], "y": 1.0,
                        "method": ["nls", "ls", "igg", "huber"], "status": "ok",
                        "hpl": 5.0})
    cases = [(pos.iloc[order].reset_index(drop=True), baseline)
             for order, baseline in (([0, 1, 2, 3], "ls"), ([3, 2, 1, 0], "ls"),
                                     ([2, 0, 3, 1], "igg"))]
    tables = []
    for p, baseline in cases:
        out = tmp_path / f"t{len(tables)}.csv"
        assert _run([*_evaluate_files(tmp_path, p, truth), "-q", "-o", str(out),
                     "--baseline", baseline]) == 0
        tables.append(pd.read_csv(out))
    assert tables[0]["method"].tolist() == ["ls", "huber", "igg", "nls"] * 3
    pd.testing.assert_frame_equal(tables[0], tables[1])
    assert tables[2]["method"].tolist() == ["igg", "huber", "ls", "nls"] * 3
    figures = [list(render_evaluation_figure(epoch_errors(p, truth), "f.svg",
                                             baseline=baseline)[1])
               for p, baseline in cases]
    assert figures == [["ls", "huber", "igg", "nls"]] * 2 + [["igg", "huber", "ls", "nls"]]


# --------------------------------------------------------------- 5. the stats figures
def _rssi(n_anchors: int) -> pd.DataFrame:
    rng = np.random.default_rng(2)
    return pd.DataFrame([(float(t), "T", f"A{a:03d}", -60 + rng.normal(0, 3))
                         for t in range(12) for a in range(n_anchors)],
                        columns=["time", "tag", "anchor", "rssi"])


def test_stats_figures_show_every_anchor_or_say_which(tmp_path, monkeypatch):
    """histograms.png drew the first 16 anchors and said nothing of the others (20
    here), and autocorrelation.png had no legend beyond 12 anchors.  Now every anchor
    has a panel up to MAX_HISTOGRAMS (48; the first ones by name beyond, said in the
    title) and a legend entry up to MAX_ACF_LEGEND (40; the title says when there are
    too many)."""
    from robustloc.eval import rssi_stats
    from robustloc.eval.rssi_stats import RssiStatistics, plot_autocorrelation, plot_histograms

    res = RssiStatistics().compute(_rssi(20))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        hist = plot_histograms(res, tmp_path / "h.svg").read_text()
        acf = plot_autocorrelation(res, tmp_path / "a.svg").read_text()
    assert all(f"<!-- A{a:03d}: skew" in hist for a in range(20))
    assert "the first" not in hist
    assert all(f"<!-- A{a:03d} -->" in acf for a in range(20))
    # beyond the caps (lowered here: 48 panels take a minute to draw as SVG)
    hist = plot_histograms(res, tmp_path / "h2.svg", max_panels=8).read_text()
    assert "<!-- A007: skew" in hist and "<!-- A008: skew" not in hist
    assert "the first 8 of 20 anchors (by name); per_anchor.csv has every one" in hist
    monkeypatch.setattr(rssi_stats, "MAX_ACF_LEGEND", 12)
    acf = plot_autocorrelation(res, tmp_path / "a2.svg").read_text()
    assert "20 anchors: too many to name (acf.csv has each)" in acf
    assert "<!-- A000 -->" not in acf


# ----------------------------------------------------------- 6. the distance bins' labels
def test_stats_bin_labels_are_the_multiples_as_written(tmp_path, capsys):
    """--bin-width 0.1: per_bin.csv labelled the bins 0.30000000000000004 and
    11.100000000000001 (3 x 0.1 and 111 x 0.1 in floats); to 12 significant digits
    they are 0.3 and 11.1."""
    from test_eval_review3 import _one_anchor  # (tests/test_eval_review3.py)

    rng = np.random.default_rng(4)
    args = _one_anchor(tmp_path, {f"d{d}": (d, list(np.round(-60 + rng.normal(0, 2, 12))))
                                  for d in (0.3, 11.1)})
    assert _run([*args, "--bin-width", "0.1", "-o", str(tmp_path / "s"), "--json"]) == 0
    capsys.readouterr()
    text = (tmp_path / "s" / "per_bin.csv").read_text().splitlines()
    assert [line.split(",")[1] for line in text[1:]] == ["0.3", "11.1"]
