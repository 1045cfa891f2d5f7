"""`robustloc calibrate`: the fifth calibration review's defects, each case failing on
the code before its fix.

* ``--self`` named an anchor "suspect" (check its coordinates: a misplaced anchor ...)
  for the ordinary bias or scale that ``--self`` exists to estimate, as the test ran on
  the raw log; it now runs on the calibrated one and still names a misplaced anchor.
* A range survey in millimetres was calibrated without ``--scale`` (biases of 10 km,
  exit 0); it is refused, naming the anchor and the unit.
* The survey's ``weight`` column (frequency weights: a row counts as ``weight`` rows) was
  ignored by the attenuation-factor ``p0`` and by the count of rows that gives an anchor
  a fit of its own: the weight column now gives what the rows repeated give.
* ``--self --model friis`` listed the exponent, 2 by the model's definition, as a
  parameter left out (``calib_fixed = n``) with the note that goes with one.
* ``calibrate --robust survey.csv`` took the survey for ``--robust``'s weight function.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import statsmodels.api as sm

from robustloc.cli import main
from robustloc.errors import InputError
from robustloc.models.calibration import calibrate_pathloss, calibrate_ranges

#: Five anchors around a 20 m square and a tag circling inside it (600 epochs, 5 cm
#: range noise): the reviewer's UWB log.
SQUARE = np.array([[0.0, 0.0], [20, 0], [20, 20], [0, 20], [10, -4]])
IDS = [f"A{j + 1}" for j in range(len(SQUARE))]


def _uwb_log(tmp_path: Path, bias: np.ndarray, scale: np.ndarray,
             moved: tuple[int, tuple[float, float]] | None = None) -> list[str]:
    """The ``calibrate --self`` arguments for the log; ``moved``: one anchor's position
    as written in the anchors file shifted by this much (misplaced)."""
    t = np.arange(600) * 0.5
    tag = np.c_[10 + 7 * np.sin(t / 13) + 2 * np.cos(t / 3.1),
                10 + 7 * np.cos(t / 17) + 2 * np.sin(t / 2.3)]
    d = np.hypot(*(tag[:, None, :] - SQUARE[None]).transpose(2, 0, 1))
    z = scale * d + bias + np.random.default_rng(0).normal(0, 0.05, d.shape)
    rows = [(float(ti), "T1", a, float(v)) for ti, zi in zip(t, z) for a, v in zip(IDS, zi)]
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]).to_csv(
        tmp_path / "m.csv", index=False)
    xy = SQUARE.copy()
    if moved is not None:
        xy[moved[0]] += moved[1]
    pd.DataFrame({"anchor": IDS, "x": xy[:, 0], "y": xy[:, 1]}).to_csv(
        tmp_path / "a.csv", index=False)
    return ["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
            str(tmp_path / "a.csv"), "-o", str(tmp_path / "cal.csv")]


DELAYS = np.array([0.45, 0.0, 0.02, -0.03, 0.01])  # a UWB antenna delay on A1


@pytest.mark.parametrize("bias, scale, moved, named", [
    # the bias and the scale --self estimates: named at 8.87x and 41.3x before the fix
    (DELAYS, np.ones(5), None, None),
    (np.zeros(5), np.array([1.1, 1, 1, 1, 1]), None, None),
    # an anchor written 2 m from where it is: named (A5 was not, before: 1.0x raw)
    (DELAYS, np.ones(5), (0, (0.0, 2.0)), "A1"),
    (DELAYS, np.ones(5), (4, (2.0, 0.0)), "A5"),
])
def test_self_names_a_misplaced_anchor_not_a_bias_or_scale(tmp_path, capsys, bias, scale,
                                                           moved, named):
    assert main(_uwb_log(tmp_path, bias, scale, moved)) == 0
    err = capsys.readouterr().err
    if named is None:
        assert "check their coordinates" not in err, err
        cal = pd.read_csv(tmp_path / "cal.csv")
        # the parameters the warning called a misplacement are recovered (5 cm noise,
        # 600 epochs: standard errors below 2 cm and 0.002)
        assert np.allclose(cal["bias"], bias, atol=0.06)
        assert np.allclose(cal["scale"], scale, atol=0.006)
    else:
        assert f"anchor(s) {named} (" in err and "check their coordinates" in err, err


def _mm_survey(tmp_path: Path, unit: float) -> Path:
    """Two anchors surveyed at 1-20 m, bias 0.3 m, ranges written in ``unit`` (m)."""
    rng = np.random.default_rng(0)
    d = rng.uniform(1, 20, 50)
    r = (d + 0.3 + rng.normal(0, 0.05, 50)) / unit
    path = tmp_path / "survey.csv"
    pd.DataFrame({"anchor": np.repeat(["A1", "A2"], 25), "distance": d, "range": r}).to_csv(
        path, index=False)
    return path


@pytest.mark.parametrize("extra", [[], ["--scale"]])
def test_range_survey_in_millimetres_is_refused_naming_the_unit(tmp_path, capsys, extra):
    survey = _mm_survey(tmp_path, 1e-3)
    out = tmp_path / "cal.csv"
    assert main(["calibrate", str(survey), "-o", str(out), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {survey}: anchor A1: ") and err.count("\n") == 1, err
    assert "ranges in mm read 1000x too long" in err, err
    assert not out.exists()
    # the same survey in metres is calibrated: the bias it was simulated with
    survey = _mm_survey(tmp_path, 1.0)
    assert main(["calibrate", str(survey), "-o", str(out), *extra]) == 0
    assert np.allclose(pd.read_csv(out)["bias"], 0.3, atol=0.1)


@pytest.mark.parametrize(("bias", "distances"), [
    (2.0, (1.0, 1.5, 2.0, 3.0)), (2.0, (0.5, 1.0, 1.5)), (0.3, (0.2, 0.3, 0.5))])
def test_a_true_bias_at_short_distances_is_calibrated_not_refused(bias, distances):
    """A bias adds to the ranges, a unit error multiplies them: WiFi RTT 2 m long at 1-3
    m (median range / distance 2.1) or at 0.5-1.5 m (a bias beyond every distance), a UWB
    antenna delay of 0.3 m at 0.2-0.5 m (ratio 2.0).  The unit check's first version
    refused all three; the bias-only fit is the mean of range - distance, to 3 standard
    errors of 0.05 m noise over 10 rows per distance."""
    rng = np.random.default_rng(0)
    d = np.repeat(np.asarray(distances), 10)
    s = pd.DataFrame({"anchor": "a", "distance": d,
                      "range": d + bias + rng.normal(0, 0.05, d.size)})
    got = calibrate_ranges(s).table["bias"].iloc[0]
    assert got == pytest.approx(float(np.mean(s["range"] - s["distance"])), abs=1e-9)
    assert got == pytest.approx(bias, abs=3 * 0.05 / np.sqrt(d.size))


def test_a_unit_error_is_refused_by_its_slope_or_its_one_distance():
    """Ranges in feet of distances of 1-20 m grow 3.28x as fast as the distances, beyond
    the scale limits by far more than 3 standard errors: refused, naming feet.  An anchor
    surveyed at one distance has no slope: in mm (1000x) it is refused, a 2 m bias at
    0.5 m (5x) is not."""
    rng = np.random.default_rng(3)
    d = rng.uniform(1, 20, 40)
    feet = pd.DataFrame({"anchor": "a", "distance": d,
                         "range": (d + 0.3 + rng.normal(0, 0.05, 40)) / 0.3048})
    with pytest.raises(InputError, match="ranges in feet read 3.28084x too long"):
        calibrate_ranges(feet)
    one = pd.DataFrame({"anchor": "a", "distance": 0.5, "range": 2.5 + rng.normal(0, 0.05, 9)})
    assert calibrate_ranges(one).table["bias"].iloc[0] == pytest.approx(2.0, abs=3 * 0.05 / 3)
    with pytest.raises(InputError, match="ranges in mm read 1000x too long"):
        calibrate_ranges(one.assign(range=one["range"] * 1000 / 5))


def _repeated(weighted: pd.DataFrame) -> pd.DataFrame:
    """The survey with each row repeated ``weight`` times (the column's meaning)."""
    return (weighted.loc[weighted.index.repeat(weighted["weight"])]
            .drop(columns="weight").reset_index(drop=True))


def test_attenuation_factor_p0_counts_the_weight_column():
    """p0 is the mean reading at d0 = 1 m: (9 x -40 + 1 x -50) / 10 = -41 dBm by hand,
    the weight-0 row (-90 dBm) not a reading at all.  The unweighted mean of the rows,
    that one included, gave -60; faf and gamma are statsmodels' WLS of ``rssi - p0`` on
    ``10 lg(d0 / d)`` with the weights (seed 002 eq. (5))."""
    rows = [("a", 1.0, -40.0, 9), ("a", 1.0, -50.0, 1), ("a", 1.0, -90.0, 0),
            ("a", 2.0, -47.0, 3), ("a", 2.0, -49.0, 2), ("a", 4.0, -55.0, 4),
            ("a", 4.0, -57.0, 2), ("a", 8.0, -62.0, 3), ("a", 8.0, -64.0, 1)]
    w = pd.DataFrame(rows, columns=["anchor", "distance", "rssi", "weight"])
    got = calibrate_pathloss(w, "attenuation-factor").table.iloc[0]
    assert got["p0"] == pytest.approx(-41.0, abs=1e-12)
    use = w[w.weight > 0]
    ref = sm.WLS(use.rssi + 41.0, sm.add_constant(-10 * np.log10(use.distance)),
                 weights=use.weight).fit()
    assert got["faf"] == pytest.approx(ref.params.iloc[0], abs=1e-9)
    assert got["gamma"] == pytest.approx(ref.params.iloc[1], abs=1e-9)
    rep = calibrate_pathloss(_repeated(w), "attenuation-factor").table.iloc[0]
    for c in ("p0", "faf", "gamma", "gamma_se", "residual_std"):
        assert got[c] == pytest.approx(rep[c], rel=1e-9, abs=1e-12), c


def _few_weighted_rows(value: str) -> pd.DataFrame:
    """Anchor "a": three rows (three distances) of weight 50 each; anchor "b": 40 rows
    of weight 1 (the reviewer's survey).  Ranges: "a" two rows, as a bias-only fit of
    its own needs three rows (``p + 2``)."""
    rng = np.random.default_rng(0)
    rows = []
    for d in (1.0, 3.0, 9.0):
        rows.append(("a", d, -50 - 20 * np.log10(d) + rng.normal(0, 1), 50))
    for d in np.linspace(1, 20, 40):
        rows.append(("b", d, -60 - 30 * np.log10(d) + rng.normal(0, 2), 1))
    s = pd.DataFrame(rows, columns=["anchor", "distance", "rssi", "weight"])
    if value == "range":  # (a bias-only fit, one parameter: "a" keeps two rows of three)
        s = s.assign(range=s.distance + 0.2 + 0.01 * (s.rssi - s.rssi.mean())).drop(
            columns="rssi").drop(index=1).reset_index(drop=True)
    return s


@pytest.mark.parametrize("value", ["rssi", "range"])
def test_own_fit_counts_the_weight_column(value):
    """150 readings of anchor "a" (three rows of weight 50; ranges: 100 in two rows)
    are enough for a fit of its own, as the same readings as rows are; counted by rows
    (3 < 4; 2 < 3) it took the pooled fit.  Its parameters are statsmodels' WLS of its
    rows alone."""
    w = _few_weighted_rows(value)
    fit = calibrate_pathloss if value == "rssi" else calibrate_ranges
    got = fit(w).table.set_index("anchor")
    rep = fit(_repeated(w)).table.set_index("anchor")
    assert got.loc["a", "calib_source"] == rep.loc["a", "calib_source"] == "anchor"
    a = w[w.anchor == "a"]
    if value == "rssi":
        ref = sm.WLS(a.rssi, sm.add_constant(-10 * np.log10(a.distance)),
                     weights=a.weight).fit()
        cols = {"A": ref.params.iloc[0], "n": ref.params.iloc[1]}
    else:
        cols = {"bias": np.average(a.range - a.distance, weights=a.weight)}
    for c, v in cols.items():
        assert got.loc["a", c] == pytest.approx(v, abs=1e-9), c
        assert got.loc["a", c] == pytest.approx(rep.loc["a", c], abs=1e-9), c


def test_self_friis_lists_no_exponent_as_left_out(tmp_path, capsys):
    """Free space has no exponent to estimate (2 by definition): nothing was left out
    for want of data, so ``calib_fixed`` is empty and the standard errors' note on
    parameters left out is not given."""
    rng = np.random.default_rng(5)
    a = np.array([[0.0, 0.0], [10, 0], [10, 8], [0, 8], [5, -2]])
    ids = [f"a{j}" for j in range(len(a))]
    x = rng.uniform([1.0, 1.0], [9.0, 7.0], (600, 2))
    d = np.hypot(*(x[:, None, :] - a[None]).transpose(2, 0, 1))
    z = -50.0 - 20 * np.log10(d) + rng.normal(0, 1.0, d.shape)
    rows = [(float(k), "t", an, z[k, j]) for k in range(len(x)) for j, an in enumerate(ids)]
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "rssi"]).to_csv(
        tmp_path / "m.csv", index=False)
    pd.DataFrame({"anchor": ids, "x": a[:, 0], "y": a[:, 1], "p0": -48.0, "d0": 1.0}).to_csv(
        tmp_path / "a.csv", index=False)
    out = tmp_path / "cal.csv"
    assert main(["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
                 str(tmp_path / "a.csv"), "--model", "friis", "-o", str(out)]) == 0
    err = capsys.readouterr().err
    cal = pd.read_csv(out)
    assert cal["calib_fixed"].isna().all(), cal["calib_fixed"].tolist()
    assert np.isfinite(cal["p0_se"]).all()  # (p0 estimated for every anchor)
    assert "parameters left out" not in err, err


def _survey(tmp_path: Path) -> Path:
    rng = np.random.default_rng(1)
    d = np.tile(np.linspace(1, 15, 15), 2)
    r = -45 - 25 * np.log10(d) + rng.normal(0, 2, d.size)
    r[::7] -= 20  # gross errors, so that the robust fit differs from least squares
    path = tmp_path / "survey.csv"
    pd.DataFrame({"anchor": np.repeat(["b1", "b2"], 15), "distance": d, "rssi": r}).to_csv(
        path, index=False)
    return path


def test_robust_before_the_survey_takes_the_survey_as_the_file(tmp_path, capsys):
    """``--robust survey.csv`` (the weight optional) is the survey with the default
    weight, as ``survey.csv --robust`` is; with a survey given as well it is an error
    that says what ``--robust`` took."""
    survey = _survey(tmp_path)
    first, after = tmp_path / "first.csv", tmp_path / "after.csv"
    assert main(["calibrate", "--robust", str(survey), "-o", str(first)]) == 0
    assert main(["calibrate", str(survey), "--robust", "-o", str(after)]) == 0
    assert main(["calibrate", str(survey), "-o", str(tmp_path / "ls.csv")]) == 0
    pd.testing.assert_frame_equal(pd.read_csv(first), pd.read_csv(after))
    assert not pd.read_csv(first)["A"].equals(pd.read_csv(tmp_path / "ls.csv")["A"])
    capsys.readouterr()
    assert main(["calibrate", str(survey), "--robust", str(survey), "-o",
                 str(tmp_path / "x.csv")]) == 2
    err = capsys.readouterr().err
    assert err == (f"error: --robust took {str(survey)!r} as its weight function: put "
                   "--robust after the file, or name the function (--robust huber)\n"), err


@pytest.mark.parametrize("pooled", [False, True])
def test_a_row_of_weight_0_is_no_second_distance(pooled):
    """Anchor ``a`` is surveyed at 2 m (weight 1) and at 1, 4 and 8 m with weight 0: one
    distance, as the same survey without those rows says, not "fitted n = nan" (its
    weight-0 distances passed the one-distance check).  With ``--pooled`` the anchor's
    own slope is undetermined either way: the two surveys give the same table."""
    rng = np.random.default_rng(1)
    rows = [(a, d, -45 - 22 * np.log10(d) + rng.normal(0, 1), 1.0)
            for a in ("a", "b") for d in (1.0, 2.0, 4.0, 8.0) for _ in range(10)]
    sv = pd.DataFrame(rows, columns=["anchor", "distance", "rssi", "weight"])
    sv.loc[(sv["anchor"] == "a") & (sv["distance"] != 2.0), "weight"] = 0.0
    dropped = sv[sv["weight"] > 0].reset_index(drop=True)
    if not pooled:
        for survey in (sv, dropped):
            with pytest.raises(InputError, match="anchor a: cannot determine n: all samples "
                                                 "at one distance"):
                calibrate_pathloss(survey, "log-distance")
        return
    got = calibrate_pathloss(sv, "log-distance", pooled=True).table
    want = calibrate_pathloss(dropped, "log-distance", pooled=True).table
    cols = [c for c in want.columns if want[c].dtype.kind == "f"]
    pd.testing.assert_frame_equal(got[cols], want[cols], rtol=1e-9)
