"""RSSI statistics (seed 002, sec. 2, Table 1) against scipy.stats / statsmodels / numpy."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import stats
from statsmodels.tsa.stattools import acf as sm_acf

from robustloc.errors import InputError
from robustloc.eval.rssi_stats import (
    RssiStatistics,
    autocorrelation,
    decorrelation_lag,
    moments,
    normality,
    plot_autocorrelation,
    plot_histograms,
    truth_distances,
)


def test_moments_against_scipy():
    rng = np.random.default_rng(0)
    x = -50 + stats.skewnorm(-5).rvs(500, random_state=rng) * 2
    m = moments(x)
    assert m["n"] == 500
    assert m["mean"] == pytest.approx(np.mean(x))
    assert m["variance"] == pytest.approx(np.var(x, ddof=1))
    assert m["skewness"] == pytest.approx(stats.skew(x))
    assert m["kurtosis"] == pytest.approx(stats.kurtosis(x, fisher=False))
    assert m["skewness"] < 0  # left-skewed as the paper's RSSI


def test_moments_hand_case_and_degenerate():
    m = moments([1.0, 2.0, 3.0, 10.0])
    c = np.array([1, 2, 3, 10]) - 4.0
    assert m["skewness"] == pytest.approx(np.mean(c**3) / np.mean(c**2) ** 1.5)
    assert np.isnan(moments([3.0])["variance"])
    assert np.isnan(moments([2.0, 2.0, 2.0])["skewness"])


def test_autocorrelation_against_statsmodels():
    rng = np.random.default_rng(1)
    e = rng.normal(size=400)
    x = np.empty(400)
    x[0] = e[0]
    for i in range(1, 400):
        x[i] = 0.8 * x[i - 1] + e[i]
    r = autocorrelation(x, 20)
    np.testing.assert_allclose(r, sm_acf(x, nlags=20, adjusted=False, fft=False), atol=1e-12)
    # AR(1) with phi = 0.8: 0.8^k < 0.2 from k = 8 (the paper's lag)
    assert 6 <= decorrelation_lag(r) <= 10


def test_autocorrelation_runs_do_not_mix():
    x = np.array([1.0, -1.0, 1.0, -1.0, 5.0, 5.0])
    runs = np.array([0, 0, 0, 0, 1, 1])
    r = autocorrelation(x, 2, runs=runs, center=0.0)
    den = np.sum(x * x)
    assert r[1] == pytest.approx((-1 - 1 - 1 + 25) / den)
    assert r[2] == pytest.approx((1 + 1) / den)


def test_decorrelation_lag_never():
    assert np.isnan(decorrelation_lag([1.0, 0.9, 0.5]))
    assert decorrelation_lag([1.0, 0.5, 0.1]) == 2


def test_normality_against_scipy():
    rng = np.random.default_rng(2)
    x = rng.normal(size=200)
    p = normality(x)
    assert p["normaltest_p"] == pytest.approx(stats.normaltest(x).pvalue)
    assert p["shapiro_p"] == pytest.approx(stats.shapiro(x).pvalue)
    assert np.isnan(normality([1.0, 2.0])["shapiro_p"])


def _table():
    """Static tag at 3 distances from one anchor, 200 samples each, noise grows with d."""
    rng = np.random.default_rng(4)
    anchors = pd.DataFrame({"anchor": ["A"], "x": [0.0], "y": [0.0]})
    frames, truths = [], []
    for i, d in enumerate([1.0, 3.0, 6.0]):
        t = np.arange(200.0)
        frames.append(pd.DataFrame({
            "time": t, "tag": f"p{i}", "anchor": "A",
            "rssi": -40 - 20 * np.log10(d) + rng.normal(0, 0.5 * d, 200),
        }))
        truths.append(pd.DataFrame({"time": [0.0, 199.0], "tag": f"p{i}", "x": d, "y": 0.0}))
    return pd.concat(frames, ignore_index=True), anchors, pd.concat(truths, ignore_index=True)


def test_per_bin_table_and_variance_distance_correlation(tmp_path):
    meas, anchors, truth = _table()
    res = RssiStatistics(max_lag=10).compute(meas, anchors, truth)
    pb = res.per_bin
    np.testing.assert_allclose(pb["distance_m"], [1, 3, 6])
    for (_, row), (_, g) in zip(pb.iterrows(), meas.groupby("tag")):
        assert row["mean"] == pytest.approx(g["rssi"].mean())
        assert row["variance"] == pytest.approx(g["rssi"].var(ddof=1))
        assert row["kurtosis"] == pytest.approx(stats.kurtosis(g["rssi"], fisher=False))
    expected = np.corrcoef([1, 3, 6], pb["variance"])[0, 1]
    assert res.variance_distance_corr == pytest.approx(expected)
    assert res.variance_distance_corr > 0.9
    # residual moments remove the distance trend: close to normal
    pa = res.per_anchor.iloc[0]
    assert abs(pa["resid_skewness"]) < 0.5 and pa["skewness"] != pa["resid_skewness"]
    paths = res.write_csv(tmp_path)
    assert {p.name for p in paths} == {"per_anchor.csv", "per_bin.csv", "acf.csv"}
    assert plot_histograms(res, tmp_path / "h.png").stat().st_size > 1000
    assert plot_autocorrelation(res, tmp_path / "a.png").stat().st_size > 1000
    s = res.summary()
    assert s["n_samples"] == 600 and s["n_bins"] == 3


def test_without_truth_per_anchor_only():
    meas, _, _ = _table()
    res = RssiStatistics(max_lag=5).compute(meas)
    assert res.per_bin is None and np.isnan(res.variance_distance_corr)
    assert res.per_anchor.loc[0, "n"] == 600
    assert res.acf.shape == (6, 1)



def test_repeated_readings_at_one_time_are_averaged_in_any_order():
    """Two readings of the link at every time, in either order within the time: the
    autocorrelation is that of the series of their means (statsmodels, one run), the
    same for both orders, per anchor and per distance bin; the moments keep every
    sample.  (In file order, ``a1 b1 a2 b2 ...`` against ``b1 a1 b2 a2 ...`` gave lag-1
    autocorrelations of -0.26 and +0.34: the input-order review, 2026-12-07.)"""
    rng = np.random.default_rng(12)
    n = 120
    ar = np.empty(n)
    ar[0] = 0.0
    for i in range(1, n):  # AR(1), phi 0.8: a lag the mixing would spoil
        ar[i] = 0.8 * ar[i - 1] + rng.normal()
    a = -60 + ar + rng.normal(0, 0.3, n)
    b = -60 + ar + rng.normal(0, 3.0, n)  # the second reading: far noisier
    t = np.arange(n, dtype=float)

    def frame(first, second):
        return pd.DataFrame({"time": np.repeat(t, 2), "tag": "T", "anchor": "A",
                             "rssi": np.column_stack((first, second)).ravel()})

    anchors = pd.DataFrame({"anchor": ["A"], "x": [0.0], "y": [0.0]})
    truth = pd.DataFrame({"time": [0.0, n - 1.0], "tag": "T", "x": 3.0, "y": 0.0})
    calc = RssiStatistics(max_lag=10, min_samples=10)
    ra, rb = (calc.compute(frame(*o)) for o in ((a, b), (b, a)))
    want = sm_acf((a + b) / 2, nlags=10, adjusted=False, fft=False)
    np.testing.assert_allclose(ra.acf["A"], want, atol=1e-12)
    np.testing.assert_allclose(rb.acf["A"], want, atol=1e-12)
    assert ra.per_anchor.loc[0, "decorrelation_lag"] == rb.per_anchor.loc[0,
                                                                          "decorrelation_lag"]
    assert ra.per_anchor.loc[0, "n"] == 2 * n  # every sample in the moments
    assert ra.per_anchor.loc[0, "variance"] == pytest.approx(np.var(np.r_[a, b], ddof=1))
    # with truth: the one bin's lag, of the same series
    ba, bb = (calc.compute(frame(*o), anchors, truth) for o in ((a, b), (b, a)))
    lag = decorrelation_lag(want)
    assert ba.per_bin.loc[0, "decorrelation_lag"] == bb.per_bin.loc[0, "decorrelation_lag"]
    assert ba.per_bin.loc[0, "decorrelation_lag"] == lag

def test_truth_distance_interpolation_3d():
    meas = pd.DataFrame({"time": [0.5], "tag": ["t"], "anchor": ["A"], "rssi": [-50.0]})
    anchors = pd.DataFrame({"anchor": ["A"], "x": [0.0], "y": [0.0], "z": [1.0]})
    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": ["t", "t"], "x": [2.0, 4.0],
                          "y": [0.0, 0.0], "z": [1.0, 1.0]})
    assert truth_distances(meas, anchors, truth)[0] == pytest.approx(3.0)


def test_bad_inputs():
    meas, anchors, truth = _table()
    with pytest.raises(InputError):
        RssiStatistics().compute(meas.rename(columns={"rssi": "range"}))
    with pytest.raises(ValueError):
        RssiStatistics().compute(meas, None, truth)
    with pytest.raises(ValueError):
        RssiStatistics(max_lag=0)
    bad = meas.copy()
    bad.loc[3, "anchor"] = "nope"
    with pytest.raises(InputError, match="unknown anchor"):
        RssiStatistics().compute(bad, anchors, truth)


def test_stats_with_no_distance_bin_of_min_samples(tmp_path, capsys):
    """`robustloc stats --truth` ended in a KeyError traceback when no distance bin held
    --min-samples samples, and its per_bin.csv was one empty line (the CLI review).
    Now the table has its columns and no rows, and the command says why."""
    from robustloc.cli import main

    (tmp_path / "a.csv").write_text("anchor,x,y,A,n\nA1,0,0,-40,2\nA2,10,0,-40,2\n"
                                    "A3,0,10,-40,2\n")
    (tmp_path / "m.csv").write_text("time,tag,anchor,rssi\n0,T,A1,-60\n0,T,A2,-62\n"
                                    "0,T,A3,-61\n1,T,A1,-59\n1,T,A2,-63\n1,T,A3,-60\n")
    (tmp_path / "t.csv").write_text("time,tag,x,y\n0,T,5,5\n1,T,5,5\n")
    out = tmp_path / "st"
    assert main(["stats", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "--truth", str(tmp_path / "t.csv"), "-o", str(out)]) == 0
    assert "none of 1 m holds --min-samples 10 samples" in capsys.readouterr().out
    pb = pd.read_csv(out / "per_bin.csv")
    assert pb.empty and list(pb.columns[:4]) == ["anchor", "distance_m", "n", "mean"]
    assert {"variance", "decorrelation_lag", "normaltest_p"} <= set(pb.columns)
