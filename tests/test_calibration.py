"""Calibration: recovery within standard errors, statsmodels OLS as reference, robust fits,
range bias/scale, survey built from measurements with truth."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import statsmodels.api as sm

from robustloc.errors import InputError
from robustloc.models.calibration import (
    POOLED,
    PathLossCalibrator,
    RangeCalibrator,
    apply_range_calibration,
    calibrate_pathloss,
    calibrate_ranges,
    fit_lines,
    survey_from_positions,
)
from robustloc.models.pathloss import AttenuationFactor, LogDistance


def _survey(model, n_anchors, distances, sigma_db, rng):
    d = np.tile(distances, n_anchors)
    ids = np.repeat([f"b{i}" for i in range(n_anchors)], len(distances))
    r = model.rssi(d) + rng.normal(0, sigma_db, d.size)
    return pd.DataFrame({"anchor": ids, "distance": d, "rssi": r})


def test_log_distance_matches_statsmodels_ols():
    rng = np.random.default_rng(3)
    s = _survey(LogDistance(-61.0, 2.4), 1, np.arange(1.0, 31.0), 2.5, rng)
    res = calibrate_pathloss(s)
    row = res.table.iloc[0]
    X = sm.add_constant(-10 * np.log10(s["distance"].to_numpy()))
    ols = sm.OLS(s["rssi"].to_numpy(), X).fit()
    np.testing.assert_allclose([row["A"], row["n"]], ols.params, rtol=1e-10)
    np.testing.assert_allclose([row["A_se"], row["n_se"]], ols.bse, rtol=1e-8)
    np.testing.assert_allclose(row["residual_std"], np.sqrt(ols.scale), rtol=1e-10)


def test_log_distance_recovers_known_parameters_within_standard_errors():
    # seed 000: A and n calibrated from RSSI sampled every 1 m along the corridor
    rng = np.random.default_rng(7)
    s = _survey(LogDistance(-59.0, 2.2), 1, np.arange(1.0, 41.0), 3.0, rng)
    row = calibrate_pathloss(s).table.iloc[0]
    assert abs(row["A"] + 59.0) < 3 * row["A_se"]
    assert abs(row["n"] - 2.2) < 3 * row["n_se"]
    assert 2.2 < row["residual_std"] < 3.8


def test_standard_errors_have_nominal_coverage():
    # 400 independent anchors in one batched call: ~95 % of |error| < 1.96 SE
    rng = np.random.default_rng(11)
    s = _survey(LogDistance(-59.0, 2.2), 400, np.arange(1.0, 21.0), 2.0, rng)
    t = calibrate_pathloss(s).table
    t = t[t["anchor"] != POOLED]
    cov_A = np.mean(np.abs(t["A"] + 59.0) < 1.96 * t["A_se"])
    cov_n = np.mean(np.abs(t["n"] - 2.2) < 1.96 * t["n_se"])
    assert 0.91 < cov_A < 0.99 and 0.91 < cov_n < 0.99


def test_attenuation_factor_paper_example_recovered():
    # seed 002: d0 = 1 m, P_r(d0) = -29 dBm, gamma = 2.275, FAF = -1.076, residual 1.59 dBm
    rng = np.random.default_rng(5)
    truth = AttenuationFactor(p0=-29.0, gamma=2.275, faf=-1.076, d0=1.0)
    s = _survey(truth, 1, np.repeat(np.arange(1.0, 9.0), 25), 1.59, rng)
    res = calibrate_pathloss(s, "attenuation-factor", p0=-29.0)
    row = res.table.iloc[0]
    assert row["p0"] == -29.0 and row["d0"] == 1.0
    assert abs(row["gamma"] - 2.275) < 3 * row["gamma_se"]
    assert abs(row["faf"] + 1.076) < 3 * row["faf_se"]
    assert abs(row["residual_std"] - 1.59) < 0.2
    assert row["gamma_se"] < 0.1


def test_attenuation_factor_p0_from_reference_samples_and_error():
    rng = np.random.default_rng(2)
    s = _survey(AttenuationFactor(-29.0, 2.0, 0.0), 2, np.arange(1.0, 11.0), 0.5, rng)
    res = calibrate_pathloss(s, "attenuation-factor")
    at_d0 = s[s["distance"] == 1.0].groupby("anchor")["rssi"].mean().to_numpy()
    np.testing.assert_allclose(res.table["p0"].to_numpy()[:2], at_d0)
    with pytest.raises(InputError, match="needs the reference power p0"):
        calibrate_pathloss(s[s["distance"] > 2], "attenuation-factor")


def test_friis_fits_reference_power_only():
    rng = np.random.default_rng(4)
    s = _survey(LogDistance(-40.0, 2.0), 1, np.arange(1.0, 21.0), 1.0, rng)
    row = calibrate_pathloss(s, "friis").table.iloc[0]
    assert abs(row["p0"] + 40.0) < 3 * row["p0_se"]
    np.testing.assert_allclose(row["p0_se"], row["residual_std"] / np.sqrt(20))


def test_robust_fit_resists_outliers_where_ls_does_not():
    rng = np.random.default_rng(9)
    s = _survey(LogDistance(-59.0, 2.2), 1, np.arange(1.0, 41.0), 1.5, rng)
    s.loc[s.index[::5], "rssi"] -= 20.0  # body blockage: 20 % of samples 20 dB low
    ls = calibrate_pathloss(s).table.iloc[0]
    for name in ("huber", "igg3", "hampel"):
        rb = calibrate_pathloss(s, robust=name).table.iloc[0]
        assert abs(rb["A"] + 59.0) < abs(ls["A"] + 59.0)
        assert abs(rb["n"] - 2.2) < 0.25, name
    igg3 = calibrate_pathloss(s, robust="igg3").table.iloc[0]
    assert igg3["n_used"] == 32  # the 8 blocked samples rejected
    assert abs(ls["A"] + 59.0) > 2.0


def _mad_under_contamination(share: float, sigma: float, shift: float) -> float:
    """The MAD scale (med|v| / 0.6745) of ``(1 - share) N(0, sigma) + share N(-shift,
    sigma)`` residuals about zero, from its defining equation (brentq)."""
    from scipy.optimize import brentq
    from scipy.stats import norm

    def half(q):
        clear = 2 * norm.cdf(q / sigma) - 1
        blocked = norm.cdf((q + shift) / sigma) - norm.cdf((-q + shift) / sigma)
        return (1 - share) * clear + share * blocked - 0.5

    return brentq(half, 1e-9, 10 * (sigma + shift)) / 0.6744897501960817


@pytest.mark.parametrize(("weight", "share"), [
    ("huber", 0.0), ("hampel", 0.0), ("igg", 0.0), ("igg3", 0.0),
    ("huber", 0.05), ("hampel", 0.2), ("igg3", 0.2)])
def test_robust_fit_sigma_is_the_noise_scale(weight, share):
    """A robust fit's written sigma is the MAD scale of its residuals.  Tolerance: four
    standard deviations of the MAD, 1.166 sigma / sqrt(n) for Gaussian rows (its asymptotic
    variance 1.3605 sigma^2 / n), n = 2 000 rows: 10.4 %.  The old sum(w v^2) / dof read
    2.1 dB for 1.59 (Huber, 5 % of rows 20 dB low) and 1.27 dB for 1.5 (IGG3, clean).
    Huber is not tested at 20 %: one-sided gross errors bias its line (A 1-5 dB off), and
    its residuals with it."""
    rng = np.random.default_rng(21)
    s = _survey(LogDistance(-59.0, 2.2), 1, np.repeat(np.arange(1.0, 41.0), 50), 1.5, rng)
    s.loc[rng.random(len(s)) < share, "rssi"] -= 20.0
    got = calibrate_pathloss(s, robust=weight).table.iloc[0]["residual_std"]
    want = _mad_under_contamination(share, 1.5, 20.0)
    assert abs(got / want - 1) < 4 * 1.166 / np.sqrt(len(s)), (got, want)
    an = calibrate_pathloss(s, robust=weight).apply_to_anchors(None)
    assert an["sigma"].iloc[0] == pytest.approx(got)


def test_robust_equals_ls_on_exact_data():
    d = np.arange(1.0, 11.0)
    s = pd.DataFrame({"anchor": "a", "distance": d, "rssi": LogDistance(-50, 3).rssi(d)})
    for robust in (None, "huber", "igg"):
        row = calibrate_pathloss(s, robust=robust).table.iloc[0]
        np.testing.assert_allclose([row["A"], row["n"]], [-50, 3], atol=1e-9)


def test_pooled_and_sparse_anchors_and_apply_to_anchors():
    rng = np.random.default_rng(1)
    s = _survey(LogDistance(-60.0, 2.0), 3, np.arange(1.0, 16.0), 1.0, rng)
    s = pd.concat([s, pd.DataFrame({"anchor": ["lonely"] * 2, "distance": [1.0, 2.0],
                                    "rssi": [-60.0, -66.0]})])
    res = calibrate_pathloss(s)
    t = res.table.set_index("anchor")
    assert t.loc["lonely", "calib_source"] == "pooled"
    assert t.loc["lonely", "A"] == t.loc[POOLED, "A"]
    assert any("lonely" in n for n in res.notes)
    anchors = pd.DataFrame({"anchor": ["b0", "b1", "b2", "lonely", "new"], "x": range(5),
                            "y": 0.0, "p0": -1.0, "gamma": 2.0})
    out = res.apply_to_anchors(anchors)
    assert "p0" not in out.columns and "gamma" not in out.columns  # stale model dropped
    assert out.loc[4, "calib_source"] == "pooled"
    assert out.loc[4, "A"] == t.loc[POOLED, "A"]
    assert out.loc[0, "A"] == t.loc["b0", "A"]
    pooled = calibrate_pathloss(s, pooled=True).apply_to_anchors(anchors)
    assert np.all(pooled["A"] == t.loc[POOLED, "A"])


def test_range_bias_and_scale():
    rng = np.random.default_rng(6)
    d = np.tile(np.linspace(1, 20, 40), 2)
    ids = np.repeat(["ap1", "ap2"], 40)
    bias = np.where(ids == "ap1", 0.8, -0.3)
    scl = np.where(ids == "ap1", 1.02, 1.0)
    r = scl * d + bias + rng.normal(0, 0.1, d.size)
    s = pd.DataFrame({"anchor": ids, "distance": d, "range": r})
    t = calibrate_ranges(s).table.set_index("anchor")
    np.testing.assert_allclose(t.loc["ap2", "bias"], np.mean(r[40:] - d[40:]))
    assert t.loc["ap2", "scale"] == 1.0
    ts = calibrate_ranges(s, scale=True).table.set_index("anchor")
    assert abs(ts.loc["ap1", "bias"] - 0.8) < 3 * ts.loc["ap1", "bias_se"]
    assert abs(ts.loc["ap1", "scale"] - 1.02) < 3 * ts.loc["ap1", "scale_se"]
    anchors = calibrate_ranges(s, scale=True).apply_to_anchors(
        pd.DataFrame({"anchor": ["ap1", "ap2"], "x": [0.0, 1.0], "y": [0.0, 0.0]})
    )
    corrected = apply_range_calibration(anchors, np.array([[1.02 * 10 + 0.8, np.nan]]))
    np.testing.assert_allclose(corrected[0, 0], 10.0, atol=0.1)
    assert np.isnan(corrected[0, 1])


def test_apply_range_calibration_defaults():
    a = pd.DataFrame({"anchor": ["1", "2"], "x": [0.0, 1], "y": [0.0, 1], "bias": [0.5, np.nan]})
    np.testing.assert_allclose(apply_range_calibration(a, [[3.0, 4.0]]), [[2.5, 4.0]])
    with pytest.raises(ValueError, match="anchor columns"):
        apply_range_calibration(a, [[1.0, 2.0, 3.0]])


def test_survey_from_positions():
    anchors = pd.DataFrame({"anchor": ["a", "b"], "x": [0.0, 10.0], "y": [0.0, 0.0],
                            "z": [2.0, 2.0]})
    truth = pd.DataFrame({"time": [0.0, 1.0], "tag": ["T", "T"], "x": [3.0, 5.0],
                          "y": [4.0, 0.0], "z": [2.0, 2.0]})
    meas = pd.DataFrame({"time": [0.0, 0.0, 1.0, 2.0], "tag": ["T"] * 4,
                         "anchor": ["a", "b", "a", "a"], "range": [5.5, 8.0, 5.2, 1.0]})
    meas.attrs["value"] = "range"
    s = survey_from_positions(meas, truth, anchors)
    np.testing.assert_allclose(s["distance"], [5.0, np.hypot(7, 4), 5.0])
    assert s.attrs["n_unmatched"] == 1  # time 2.0 has no truth
    t = calibrate_ranges(s).table.set_index("anchor")
    # anchor a has 2 rows for its 1 parameter: one degree of freedom for its sigma, too
    # few for a fit of its own since 2026-12-06 (the calibration review): the pooled
    # mean of the three rows' range - distance
    assert t.loc["a", "calib_source"] == "pooled"
    np.testing.assert_allclose(t.loc["a", "bias"], (0.5 + 0.2 + 8.0 - np.hypot(7, 4)) / 3)
    truth3 = pd.concat([truth, truth.iloc[[0]].assign(time=3.0)], ignore_index=True)
    meas3 = pd.concat([meas, meas.iloc[[0]].assign(time=3.0, range=5.3)], ignore_index=True)
    meas3.attrs["value"] = "range"
    t3 = calibrate_ranges(survey_from_positions(meas3, truth3, anchors)).table
    t3 = t3.set_index("anchor")
    assert t3.loc["a", "calib_source"] == "anchor"  # three rows: its own fit
    np.testing.assert_allclose(t3.loc["a", "bias"], (0.5 + 0.2 + 0.3) / 3)


def test_fit_lines_groups_independent_and_vectorized():
    rng = np.random.default_rng(0)
    g = rng.integers(0, 50, 2000)
    x = rng.normal(size=2000)
    y = 2.0 * g + (0.1 * g) * x + rng.normal(0, 0.01, 2000)
    f = fit_lines(x, y, g, 50)
    np.testing.assert_allclose(f.a, 2.0 * np.arange(50), atol=0.01)
    np.testing.assert_allclose(f.b, 0.1 * np.arange(50), atol=0.01)


def test_calibrator_objects_match_functions():
    rng = np.random.default_rng(8)
    s = _survey(LogDistance(-60.0, 2.0), 2, np.arange(1.0, 21.0), 1.0, rng)
    a = PathLossCalibrator("log-distance", robust="huber").fit(s).table
    b = calibrate_pathloss(s, robust="huber").table
    pd.testing.assert_frame_equal(a, b)
    r = s.rename(columns={"rssi": "range"}).assign(range=lambda f: f["distance"] + 0.3)
    assert RangeCalibrator().fit(r).table["bias"].iloc[0] == pytest.approx(0.3)


def test_frequency_weights_equal_repeated_rows():
    rng = np.random.default_rng(12)
    d = np.arange(1.0, 16.0)
    r = LogDistance(-60.0, 2.0).rssi(d) + rng.normal(0, 2, d.size)
    counts = rng.integers(1, 5, d.size)
    weighted = pd.DataFrame({"anchor": "a", "distance": d, "rssi": r, "weight": counts})
    repeated = pd.DataFrame({"anchor": "a", "distance": np.repeat(d, counts),
                             "rssi": np.repeat(r, counts)})
    r[::4] -= 15.0  # outliers, so that the robust weights (and the MAD scale) matter
    weighted["rssi"] = r
    repeated["rssi"] = np.repeat(r, counts)
    for robust in (None, "huber", "igg3"):
        tw = calibrate_pathloss(weighted, robust=robust).table.iloc[0]
        tr = calibrate_pathloss(repeated, robust=robust).table.iloc[0]
        for c in ("A", "n", "A_se", "n_se", "residual_std"):
            np.testing.assert_allclose(tw[c], tr[c], rtol=1e-9, err_msg=f"{robust} {c}")
    bad = weighted.assign(weight=-1.0)
    with pytest.raises(InputError, match="'weight'"):
        calibrate_pathloss(bad)


def test_weighted_mad_equals_repeated_median():
    from robustloc.models.calibration import _grouped_mad

    rng = np.random.default_rng(2)
    for _ in range(30):
        k = rng.integers(1, 12)
        v = rng.normal(size=k)
        c = rng.integers(1, 4, k)
        g = np.zeros(k, dtype=np.int64)
        got = _grouped_mad(v, g, 1, c.astype(float))[0]
        want = np.median(np.abs(np.repeat(v, c))) / 0.6744897501960817
        np.testing.assert_allclose(got, want, rtol=1e-12)


def test_a_hand_made_survey_with_distances_it_cannot_use_is_refused_by_column():
    """The API review: one NaN distance gave an anchor's bias (and the pooled one) NaN
    with ``n_used`` 5 and no error; negative distances a bias of 8.9 m; a distance of 0
    in a path-loss survey was blamed on "constant values?"."""
    from robustloc.errors import InputError
    from robustloc.models.calibration import calibrate_pathloss, calibrate_ranges

    s = pd.DataFrame({"anchor": np.repeat(["a", "b"], 5),
                      "distance": np.tile([1.0, 2, 4, 6, 8], 2),
                      "range": np.tile([1.3, 2.4, 4.5, 6.6, 8.7], 2)})
    for d, words in ((np.r_[np.nan, s.distance[1:]], "'nan'"), (-s.distance, "'-1.0'")):
        with pytest.raises(InputError, match=f"column 'distance': {words}"):
            calibrate_ranges(s.assign(distance=d))
    with pytest.raises(InputError, match="column 'range'"):
        calibrate_ranges(s.assign(range=np.r_[np.inf, s["range"][1:]]))
    p = s.drop(columns="range").assign(rssi=np.tile([-40.0, -46, -52, -55, -58], 2))
    with pytest.raises(InputError, match="'0.0' must be a finite distance > 0"):
        calibrate_pathloss(p.assign(distance=np.r_[0.0, p.distance[1:]]))
    assert np.allclose(calibrate_ranges(s).table["bias"], 0.5)  # the clean survey


def _dwell_log(seed: int):
    """Six anchors, a tag standing 60 epochs at each of 10 surveyed points; each
    (point, anchor) link keeps an offset N(0, 0.2 m) while it dwells (its multipath),
    plus white noise N(0, 0.05 m); known per-anchor biases U(-0.5, 0.5) m."""
    rng = np.random.default_rng(300 + seed)
    A = np.array([[0, 0], [20, 0], [20, 15], [0, 15], [10, -3], [10, 18]], float)
    ids = [f"a{i}" for i in range(len(A))]
    bias = rng.uniform(-0.5, 0.5, len(A))
    pts = rng.uniform([1, 1], [19, 14], (10, 2))
    off = rng.normal(0.0, 0.2, (10, len(A)))
    t = np.arange(600.0)
    p = np.repeat(pts, 60, axis=0)
    d = np.linalg.norm(p[:, None] - A[None], axis=2)
    r = d + bias + np.repeat(off, 60, axis=0) + rng.normal(0.0, 0.05, d.shape)
    meas = pd.DataFrame({"time": np.repeat(t, len(A)), "tag": "t0",
                         "anchor": np.tile(ids, 600), "range": r.ravel()})
    truth = pd.DataFrame({"time": t, "tag": "t0", "x": p[:, 0], "y": p[:, 1]})
    anchors = pd.DataFrame({"anchor": ids, "x": A[:, 0], "y": A[:, 1]})
    return meas, truth, anchors, bias


def test_truth_calibration_standard_errors_hold_when_the_tag_dwells():
    """``calibrate --measurements --truth`` took every row as independent; a tag standing
    at points shares each point's multipath across its rows, and the standard errors came
    out about 8x too small (the calibration review, 2026-12-06: over 8 logs,
    (estimate - truth) / bias_se had sd 9.7 and 65 % beyond 4).  They are now
    cluster-robust over the dwells (``models.calibration.cluster_robust_lines``).  With
    10 clusters the sandwich has about 9 degrees of freedom: the z-scores are Student-t
    like (sd about 1.1-1.3: 1.25 measured over the same 8 logs), so sd < 2 and none beyond
    5 (t_9 exceeds 5 with probability 7e-4, 48 scores) separate it from the old 9.7."""
    import robustloc

    z = []
    for seed in range(8):
        meas, truth, anchors, bias = _dwell_log(seed)
        cal = robustloc.calibrate(anchors=anchors, measurements=meas, truth=truth)
        z.extend((cal["bias"].to_numpy() - bias) / cal["bias_se"].to_numpy())
    z = np.asarray(z)
    assert np.isfinite(z).all()
    assert z.std() < 2.0 and np.abs(z).max() < 5.0


def test_cluster_robust_errors_match_the_model_for_independent_rows():
    """One row per cluster: the sandwich estimates the same variance as the model's
    ``s^2 (X^T W X)^-1`` (it is floored there); with the rows independent the two agree
    in expectation, so the reported errors barely move (at most the floor)."""
    from robustloc.models.calibration import fit_lines

    rng = np.random.default_rng(2)
    n = 4000
    x = rng.uniform(1.0, 20.0, n)
    g = rng.integers(0, 3, n)
    y = 0.3 + 1.01 * x + rng.normal(0.0, 0.1, n)
    plain = fit_lines(x, y, g, 3)
    rob = fit_lines(x, y, g, 3, cluster=np.arange(n))
    np.testing.assert_array_equal(rob.a, plain.a)
    assert np.all(rob.a_se >= plain.a_se) and np.all(rob.b_se >= plain.b_se)
    # (50 merged clusters of ~27 rows: a variance from 50 terms, within ~20 % at 1 sigma)
    assert np.all(rob.a_se <= 1.5 * plain.a_se) and np.all(rob.b_se <= 1.5 * plain.b_se)
