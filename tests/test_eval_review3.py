"""The third review of ``evaluate``, ``stats`` and ``montecarlo``: absurd and degenerate
inputs to ``evaluate --plot``, fixes without a vertical solution, the distance bins and
residual moments of ``stats``, its share of anchors rejected as normal, and output names
checked before any work.  Every case goes through the command line."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main


def _run(argv: list[str]) -> int:
    """``main(argv)`` with every warning an error: a warning that would reach stderr
    makes the command fail (an internal error, exit code 1) instead."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return main(argv)


def _evaluate_files(tmp_path, pos: pd.DataFrame, truth: pd.DataFrame) -> list[str]:
    pos.to_csv(tmp_path / "pos.csv", index=False)
    truth.to_csv(tmp_path / "truth.csv", index=False)
    return ["evaluate", str(tmp_path / "pos.csv"), "--truth", str(tmp_path / "truth.csv")]


# ------------------------------------------------------------------ 1. absurd coordinates
@pytest.mark.parametrize("fix_x, truth_x", [(1e300, 0.0), (1e200, 0.0), (0.0, 1e300)])
def test_evaluate_plot_of_absurd_coordinates_draws_a_sane_figure(tmp_path, capsys, fix_x,
                                                                  truth_x):
    """A fix (or a truth point) 1e300 m away ended in an OverflowError traceback of
    matplotlib's log ticker, 1e200 m in warnings; the table itself was fine.  Now the
    figure is drawn with the absurd error on the edge of a log axis ending at 1e9 m and
    says so, and the map leaves the absurd point out and says so."""
    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": "A", "x": [truth_x, 1.0], "y": 0.0})
    pos = pd.DataFrame({"time": [0.0, 1.0], "tag": "A", "x": [fix_x, 1.5], "y": 0.0,
                        "method": "ls", "status": "ok", "hpl": 1.0})
    fig = tmp_path / "f.svg"
    assert _run([*_evaluate_files(tmp_path, pos, truth), "--plot", str(fig)]) == 0
    err = capsys.readouterr().err
    assert "Traceback" not in err and "Warning" not in err
    svg = fig.read_text()
    assert "1 error beyond 1e+09 m drawn at 1e+09 m" in svg  # the CDF
    assert "1 off the axes, drawn on the edge" in svg  # the Stanford diagram
    if truth_x == 0.0:  # the fix is off the map
        assert "1 usable fix not drawn: more than 1000.00 m beyond the truth" in svg
    else:  # the truth point is
        assert "1 truth point not drawn: beyond 1e+09 m" in svg


# --------------------------------------------------------- 2. fixes without a vertical z
def test_evaluate_leaves_fixes_without_z_out_of_the_vertical_statistics(tmp_path, capsys):
    """Tag A: a 3-D method (dz 0.2, 0.1, 0.3 m), a 2-D one (z empty) and a 3-D one whose
    second row has no z.  A fix without z was counted vertically misleading (NaN <= vpl
    is false: 1 of 3, 33 %) and its vpl/error ratio NaN, while the 3-D statistics left
    it out over a count that said 3."""
    truth = pd.DataFrame({"time": [0.0, 1.0, 2.0], "tag": "A", "x": [0.0, 1.0, 2.0],
                          "y": 0.0, "z": 0.0})
    rows = []
    for m, z in (("nls3d", [0.2, 0.1, 0.3]), ("huber2d", [np.nan] * 3),
                 ("gap3d", [0.2, np.nan, 0.1])):
        rows.append(pd.DataFrame({"time": [0.0, 1.0, 2.0], "tag": "A", "x": [0.5, 1.5, 2.1],
                                  "y": 0.0, "z": z, "method": m, "status": "ok",
                                  "hpl": 1.0, "vpl": 1.0}))
    args = _evaluate_files(tmp_path, pd.concat(rows, ignore_index=True), truth)
    assert _run([*args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)["rows"]
    by = {(r["tag"], r["method"]): r for r in out}
    for tag in ("A", "all", "mean"):
        full, flat, gap = by[tag, "nls3d"], by[tag, "huber2d"], by[tag, "gap3d"]
        # the 2-D method: no vertical statistics at all, not 3 misleading fixes
        for c in ("n_misleading_v", "misleading_pct_v", "vpl_median", "vpl_over_error",
                  "rms_3d", "mean_3d", "max_3d"):
            assert flat[c] is None, c
        # one row without z: the other two, counted as such
        assert gap["n_misleading_v"] == 0 and gap["misleading_pct_v"] == 0.0
        assert gap["vpl_over_error"] == pytest.approx(1.0 / 0.15, rel=1e-12)  # 1 / med(.2,.1)
        # rms over the two 3-D errors, sqrt(0.5^2 + 0.2^2) and sqrt(0.1^2 + 0.1^2)
        assert gap["rms_3d"] == pytest.approx(np.sqrt((0.29 + 0.02) / 2), rel=1e-12)
        assert (gap["n_ok"], gap["n_ok_3d"]) == (3, 2)
        assert (flat["n_ok"], flat["n_ok_3d"]) == (3, 0)
        assert (full["n_ok"], full["n_ok_3d"], full["n_misleading_v"]) == (3, 3, 0)
    assert _run([*args]) == 0
    text = capsys.readouterr().out
    assert "n_ok_3d" in text.split("3-D error (m)")[1]
    assert main(["evaluate", "--help"]) == 0
    assert "n_ok_3d" in capsys.readouterr().out


# ------------------------------------------------------------------ 3. stats distance bins
def _one_anchor(tmp_path, tags: dict[str, tuple[float, list[float]]]) -> list[str]:
    """One anchor at the origin; each static tag at (distance, 0) with its RSSI series."""
    pd.DataFrame({"anchor": ["A"], "x": [0.0], "y": [0.0], "A": [-40.0], "n": [2.0]}).to_csv(
        tmp_path / "anchors.csv", index=False)
    pd.DataFrame({"time": 0.0, "tag": list(tags), "x": [d for d, _ in tags.values()],
                  "y": 0.0}).to_csv(tmp_path / "truth.csv", index=False)
    pd.DataFrame([(float(t), tag, "A", v) for tag, (_, vs) in tags.items()
                  for t, v in enumerate(vs)],
                 columns=["time", "tag", "anchor", "rssi"]).to_csv(tmp_path / "meas.csv",
                                                                   index=False)
    return ["stats", str(tmp_path / "meas.csv"), "--anchors", str(tmp_path / "anchors.csv"),
            "--truth", str(tmp_path / "truth.csv")]


def test_stats_bins_are_centred_on_multiples_of_the_width_half_up(tmp_path, capsys):
    """Survey points at 1, 3, 5 and 7 m.  Width 2: the bins [1, 3), [3, 5), [5, 7),
    [7, 9) labelled 2, 4, 6, 8 m (np.round, half to even, put 3 m and 5 m into one "4 m"
    bin of 40 samples and left 6 m empty); width 100: one bin, [0, 50) labelled 0 m (it
    was "100 m", from a floor of one width), and no correlation from one distance."""
    rng = np.random.default_rng(3)
    args = _one_anchor(tmp_path, {f"d{d}": (float(d), list(np.round(
        -40 - 20 * np.log10(d) + rng.normal(0, 2, 20)))) for d in (1, 3, 5, 7)})
    assert _run([*args, "--bin-width", "2", "-o", str(tmp_path / "w2"), "--json"]) == 0
    s2 = json.loads(capsys.readouterr().out)
    pb = pd.read_csv(tmp_path / "w2" / "per_bin.csv")
    assert pb["distance_m"].tolist() == [2.0, 4.0, 6.0, 8.0]
    assert pb["n"].tolist() == [20, 20, 20, 20]
    assert s2["n_bins"] == 4 and s2["variance_distance_corr"] is not None
    assert _run([*args, "--bin-width", "100", "-o", str(tmp_path / "w100"), "--json"]) == 0
    s100 = json.loads(capsys.readouterr().out)
    pb = pd.read_csv(tmp_path / "w100" / "per_bin.csv")
    assert pb["distance_m"].tolist() == [0.0] and pb["n"].tolist() == [80]
    assert s100["variance_distance_corr"] is None


def test_stats_correlation_needs_three_distinct_bin_distances(tmp_path, capsys):
    """Three anchors heard by one static tag, all in one 100 m bin: three per_bin rows at
    one distance.  numpy's correlation divided 0 by 0 (a RuntimeWarning on stderr, as on
    the simulated corridor with --bin-width 100); now it is null, and the text says why."""
    pd.DataFrame({"anchor": ["A", "B", "C"], "x": [0.0, 4.0, 0.0],
                  "y": [0.0, 0.0, 4.0]}).to_csv(tmp_path / "anchors.csv", index=False)
    pd.DataFrame({"time": [0.0], "tag": ["T"], "x": [1.0], "y": [1.0]}).to_csv(
        tmp_path / "truth.csv", index=False)
    rng = np.random.default_rng(5)
    pd.DataFrame([(float(t), "T", a, float(np.round(-60 + rng.normal(0, s))))
                  for a, s in (("A", 1.0), ("B", 2.0), ("C", 4.0)) for t in range(30)],
                 columns=["time", "tag", "anchor", "rssi"]).to_csv(tmp_path / "meas.csv",
                                                                   index=False)
    args = ["stats", str(tmp_path / "meas.csv"), "--anchors", str(tmp_path / "anchors.csv"),
            "--truth", str(tmp_path / "truth.csv"), "--bin-width", "100"]
    assert _run([*args, "-o", str(tmp_path / "s"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["variance_distance_corr"] is None
    assert len(pd.read_csv(tmp_path / "s" / "per_bin.csv")) == 3
    assert _run([*args, "-o", str(tmp_path / "t")]) == 0
    assert "none (fewer than 3 distinct bin distances)" in capsys.readouterr().out


# ------------------------------------------------------------- 4. stats residual moments
def test_stats_residual_moments_use_the_kept_bins_and_their_degrees_of_freedom(tmp_path,
                                                                               capsys):
    """Bin 1 m: 10 samples -40 +- 1 (residuals +-1); bin 3 m: 10 samples -50 +- 2
    (residuals +-2); bin 5 m: 1 sample, dropped by --min-samples 10.  Sum of squared
    residuals 10 + 40 = 50 over 20 samples in 2 fitted bins: variance 50 / 18 (it was
    (50 + 0) / (21 - 1) = 2.5, with the dropped bin's residual 0 and ddof 1), kurtosis
    E r^4 / (E r^2)^2 = (170 / 20) / 2.5^2 = 1.36 (was 1.428), skewness 0.  The values
    are integers and halves, so every sum is exact: equality up to the division's
    rounding."""
    args = _one_anchor(tmp_path, {"p1": (1.0, [-39.0, -41.0] * 5),
                                  "p3": (3.0, [-48.0, -52.0] * 5),
                                  "p5": (5.0, [-55.0])})
    assert _run([*args, "-o", str(tmp_path / "s"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    pa = pd.read_csv(tmp_path / "s" / "per_anchor.csv").iloc[0]
    assert pa["resid_variance"] == pytest.approx(50 / 18, rel=1e-15)
    assert pa["resid_kurtosis"] == pytest.approx(1.36, rel=1e-15)
    assert pa["resid_skewness"] == 0.0
    assert summary["median_kurtosis"] == pytest.approx(1.36, rel=1e-15)
    assert (pa["n"], pa["resid_n"], pa["resid_bins"]) == (21, 20, 2)
    assert main(["stats", "--help"]) == 0
    assert "resid_n - resid_bins" in capsys.readouterr().out


# ------------------------------------------------------ 5. stats normality among testable
def test_stats_share_rejected_as_normal_counts_the_testable_anchors(tmp_path, capsys):
    """Anchor C: 200 exponential samples (normality rejected, p ~ 1e-18); R1, R2: 5
    samples each, too few for D'Agostino-Pearson (p NaN).  The share was 1/3 (an
    untestable anchor counted as not rejected); it is 1 of the 1 testable anchor, and
    null when no anchor is testable."""
    rng = np.random.default_rng(2)
    rows = [(float(t), "T", "C", -60 - float(rng.exponential(4))) for t in range(200)]
    rows += [(float(t), "T", "R1", -80.0 - t) for t in range(5)]
    rows += [(float(t), "T", "R2", -82.0 + t) for t in range(5)]
    meas = pd.DataFrame(rows, columns=["time", "tag", "anchor", "rssi"])
    meas.to_csv(tmp_path / "rare.csv", index=False)
    assert _run(["stats", str(tmp_path / "rare.csv"), "-o", str(tmp_path / "s"),
                 "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["share_anchors_normal_rejected_5pct"] == 1.0
    assert s["n_anchors_normality_tested"] == 1
    meas[meas["anchor"] != "C"].to_csv(tmp_path / "few.csv", index=False)
    assert _run(["stats", str(tmp_path / "few.csv"), "-o", str(tmp_path / "f"),
                 "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["share_anchors_normal_rejected_5pct"] is None
    assert s["n_anchors_normality_tested"] == 0


# ------------------------------------------------- 6. output names before any work
@pytest.mark.parametrize("out", ["h/mc.png", "h/mc.csv.bz2"])
def test_montecarlo_refuses_the_output_name_before_the_simulation(tmp_path, capsys,
                                                                  monkeypatch, out):
    """`-o h/mc.png` ran the whole simulation, then refused the extension."""
    import robustloc.integrity.montecarlo as mc

    def never(*_a, **_k):  # pragma: no cover - the point of the test
        raise AssertionError("the simulation ran before -o was checked")

    monkeypatch.setattr(mc, "run_montecarlo", never)
    monkeypatch.chdir(tmp_path)
    assert _run(["montecarlo", "--gnss", "--trials", "10", "-q", "-o", out]) == 2
    assert "cannot write" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("out", ["table.xlsx", "table.csv.bz2"])
def test_evaluate_refuses_the_table_name_before_the_figure(tmp_path, capsys, monkeypatch,
                                                           out):
    """`--plot fig.png -o table.xlsx` wrote fig.png, then exited 2 on the table's name."""
    import robustloc.eval.metrics as metrics

    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": "A", "x": [0.0, 1.0], "y": 0.0})
    args = _evaluate_files(tmp_path, truth.assign(x=[0.5, 1.5], method="ls"), truth)

    def never(*_a, **_k):  # pragma: no cover - the point of the test
        raise AssertionError("the table was computed before -o was checked")

    monkeypatch.setattr(metrics, "error_table", never)
    assert _run([*args, "--plot", str(tmp_path / "fig.png"), "-o", str(tmp_path / out)]) == 2
    assert "cannot write" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pos.csv", "truth.csv"]


def test_evaluate_writes_neither_output_when_the_table_cannot_be_written(tmp_path, capsys):
    """A table that cannot be written (its parent is a file) leaves no figure behind."""
    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": "A", "x": [0.0, 1.0], "y": 0.0})
    args = _evaluate_files(tmp_path, truth.assign(x=[0.5, 1.5], method="ls"), truth)
    (tmp_path / "file").write_text("")
    assert _run([*args, "--plot", str(tmp_path / "fig.png"), "-o",
                 str(tmp_path / "file" / "t.csv")]) == 2
    assert "a parent of this path is a file" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "pos.csv", "truth.csv"]


# ------------------------------------------------------------------ 8. many methods
def test_evaluate_plot_of_many_methods_caps_the_legends(tmp_path, capsys):
    """300 methods: 300 legend entries covered the figure and matplotlib warned "Tight
    layout not applied" on stderr.  The legends name 10 and say how many more."""
    truth = pd.DataFrame({"time": [0.0, 1, 2, 3], "tag": "A", "x": [0.0, 1, 2, 3], "y": 0.0})
    pos = pd.concat([truth.assign(x=truth["x"] + 0.01 * (m + 1), method=f"m{m}",
                                  status="ok", hpl=1.0) for m in range(300)],
                    ignore_index=True)
    fig = tmp_path / "f.svg"
    assert _run([*_evaluate_files(tmp_path, pos, truth), "--plot", str(fig)]) == 0
    svg = fig.read_text()
    assert svg.count("290 more methods") == 2  # the CDF and the map
    # the first 10 in the table's order, by name: m0, m1, m10, m100 .. m106
    assert "m106 (n=4" in svg and "m107 (n=4" not in svg and "m9 (n=4" not in svg
    # a method name of 150 characters is cut in the legends and the panel's title
    long = pos[pos["method"].isin(["m0", "m1"])].replace({"m1": "x" * 150})
    assert _run([*_evaluate_files(tmp_path, long, truth), "--plot", str(fig)]) == 0
    svg = fig.read_text()
    assert "x" * 31 not in svg and "x" * 27 + "..." in svg


# ------------------------------------------------------------------ 9. every error 0
def test_evaluate_plot_of_exact_fixes_floors_the_log_axis(tmp_path, capsys):
    """Every usable error exactly 0: matplotlib warned "Data has no positive values, and
    therefore cannot be log-scaled" and the CDF was blank.  The zeros are drawn at the
    floor of the axis, and the panel says so."""
    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": "A", "x": [0.0, 1.0], "y": 0.0})
    pos = truth.assign(method="ls", status="ok", hpl=1.0)
    fig = tmp_path / "f.svg"
    assert _run([*_evaluate_files(tmp_path, pos, truth), "--plot", str(fig)]) == 0
    assert "2 errors below 0.01 m (exact fixes) drawn at 0.01 m" in fig.read_text()


# ------------------------------------------------------------------ 10. integral counts
def test_evaluate_json_misleading_counts_are_integers(tmp_path, capsys):
    """n_misleading and n_misleading_v were floats (0.0) beside integral counts."""
    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": "A", "x": [0.0, 1.0], "y": 0.0,
                          "z": 0.0})
    pos = truth.assign(x=[0.5, 1.5], z=[0.1, 3.0], method="ls", status="ok", hpl=1.0,
                       vpl=1.0)
    assert _run([*_evaluate_files(tmp_path, pos, truth), "--json"]) == 0
    for r in json.loads(capsys.readouterr().out)["rows"]:
        assert type(r["n_misleading"]) is int and r["n_misleading"] == 0
        assert type(r["n_misleading_v"]) is int and r["n_misleading_v"] == 1


def test_global_test_power_of_a_huge_fault_is_one():
    """scipy's ncx2.sf returns NaN from a noncentrality of about 1e19 on: montecarlo's
    theory_global came out NaN (null) for --size 1e6 --sigma 1e-4 (the review)."""
    import numpy as np

    from robustloc.integrity.bmethod import detection_power_global

    p = detection_power_global(np.array([1e19, 1e25, 1e300]), np.array([1, 3, 10]))
    assert np.all(p == 1.0)
