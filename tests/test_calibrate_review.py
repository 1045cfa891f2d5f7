"""``robustloc calibrate`` (survey and --measurements/--truth modes): the review's defects.

The surveys are built so that the least-squares fit is known by hand: at each distance
two rows with errors +0.5 and -0.5 dB, so the residuals are orthogonal to ``[1, x]`` and
the fit returns the generating parameters exactly, with the residual standard deviation
``sqrt(k * 0.25 / (k - 2))`` for ``k`` rows.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main

DIST = np.array([1.0, 1.0, 2.0, 2.0, 4.0, 4.0, 8.0, 8.0])
ERR = np.array([0.5, -0.5] * 4)
#: residual standard deviation of the 8-row surveys: sqrt(8 * 0.25 / (8 - 2))
SIGMA8 = np.sqrt(1.0 / 3.0)


def _cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code = main(["calibrate", *args])
    out, err = capsys.readouterr()
    return code, out, err


def _write(path: Path, frame: pd.DataFrame) -> str:
    frame.to_csv(path, index=False)
    return str(path)


def _ld_survey(anchors: dict[str, tuple[float, float]]) -> pd.DataFrame:
    """Log-distance survey: RSSI = A - 10 n lg d + err per anchor ``{id: (A, n)}``."""
    return pd.concat([pd.DataFrame({"anchor": a, "distance": DIST,
                                    "rssi": A - 10 * n * np.log10(DIST) + ERR})
                      for a, (A, n) in anchors.items()])


def _positioned(tmp_path: Path, extra: list[tuple[float, float]]) -> list[str]:
    """Measurements/truth/anchors for one anchor ``a`` at the origin and the tag on the x
    axis: the 8-row survey (A = -40, n = 2) plus ``extra`` rows ``(x, rssi)``."""
    xs = np.concatenate([DIST, [e[0] for e in extra]])
    rssi = np.concatenate([-40 - 20 * np.log10(DIST) + ERR, [e[1] for e in extra]])
    t = np.arange(len(xs), dtype=float)
    m = _write(tmp_path / "m.csv", pd.DataFrame({"time": t, "tag": "t", "anchor": "a",
                                                 "rssi": rssi}))
    tr = _write(tmp_path / "t.csv", pd.DataFrame({"time": t, "tag": "t", "x": xs, "y": 0.0}))
    an = _write(tmp_path / "a.csv", pd.DataFrame({"anchor": ["a"], "x": [0.0], "y": [0.0]}))
    return ["--measurements", m, "--truth", tr, "--anchors", an]


# -- 1: implausible RSSI in --measurements mode -----------------------------------------


def test_measurements_rssi_outside_limits_dropped_and_counted(tmp_path, capsys):
    args = _positioned(tmp_path, [(3.0, -200.0)])
    code, _, err = _cli([*args, "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0
    assert "note: 1 measurement row(s) outside the physical limits" in err
    assert "[-150, 30] dBm" in err
    out = pd.read_csv(tmp_path / "o.csv")
    # the -200 row is not fitted: the 8 good rows give A = -40, n = 2 exactly
    assert out["A"].iloc[0] == pytest.approx(-40.0, abs=1e-9)
    assert out["n"].iloc[0] == pytest.approx(2.0, abs=1e-9)


def test_survey_rssi_outside_limits_still_refused(tmp_path, capsys):
    s = _ld_survey({"1": (-40, 2)})
    s.iloc[3, 2] = -200.0
    code, _, err = _cli([_write(tmp_path / "s.csv", s), "-o", str(tmp_path / "o.csv")],
                        capsys)
    assert code == 2
    assert "error:" in err and "-200 is implausible" in err


# -- 2: truth on the anchor --------------------------------------------------------------


def test_measurements_distance_zero_dropped_without_runtime_warning(tmp_path, capsys):
    args = _positioned(tmp_path, [(0.0, -20.0)])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        code, _, err = _cli([*args, "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0, err
    assert "note: 1 RSSI row(s) with the truth position on the anchor (distance 0" in err
    out = pd.read_csv(tmp_path / "o.csv")
    assert out["A"].iloc[0] == pytest.approx(-40.0, abs=1e-9)
    assert out["n"].iloc[0] == pytest.approx(2.0, abs=1e-9)


# -- 3 / 9b: an anchor absent from the survey --------------------------------------------


def _af_survey() -> pd.DataFrame:
    """Attenuation factor, d0 = 1: anchor 1 p0 -30, anchor 2 p0 -35, both gamma 2,
    faf -10 (so the pooled fit is gamma 2, faf -10 too)."""
    return pd.concat([pd.DataFrame({"anchor": a, "distance": DIST,
                                    "rssi": p0 - 20 * np.log10(DIST) - 10 + ERR})
                      for a, p0 in (("1", -30.0), ("2", -35.0))])


def test_absent_anchor_keeps_its_own_p0_and_d0(tmp_path, capsys):
    s = _write(tmp_path / "s.csv", _af_survey())
    an = _write(tmp_path / "a.csv", pd.DataFrame({
        "anchor": [1, 2, 3], "x": [0, 5, 0], "y": [0, 0, 5], "p0": [-30, -35, -28],
        "gamma": [2, 2, 2.5], "faf": [0, 0, 1], "d0": [np.nan, np.nan, 2.0]}))
    code, _, err = _cli([s, "--model", "attenuation-factor", "--anchors", an,
                         "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0, err
    out = pd.read_csv(tmp_path / "o.csv").set_index("anchor")
    assert out.loc[3, "p0"] == -28.0  # its own, not the mean -32.5 of the others
    assert out.loc[3, "d0"] == 2.0
    assert out.loc[3, "gamma"] == pytest.approx(2.0, abs=1e-9)  # pooled
    assert out.loc[3, "faf"] == pytest.approx(-10.0, abs=1e-9)  # pooled
    assert out.loc[3, "calib_source"] == "pooled"
    assert list(out.loc[[1, 2], "p0"]) == [-30.0, -35.0]
    assert "note: anchor(s) 3 have no survey row: the pooled fit was written" in err


def test_absent_anchor_note_log_distance(tmp_path, capsys):
    s = _write(tmp_path / "s.csv", _ld_survey({"1": (-40, 2), "2": (-45, 3)}))
    an = _write(tmp_path / "a.csv", pd.DataFrame({"anchor": [1, 2, 3], "x": [0, 5, 0],
                                                  "y": [0, 0, 5]}))
    code, _, err = _cli([s, "--anchors", an, "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0
    assert "note: anchor(s) 3 have no survey row" in err


# -- 4 / 9a: standard errors, calib_fixed, sigma -----------------------------------------


def _ld_se() -> tuple[float, float]:
    """Hand formula of the (A, n) standard errors of the 8-row survey:
    var n = s^2 / Sxx, var A = s^2 sum(x^2) / (k Sxx), x = -10 lg d, s^2 = 1/3."""
    x = -10 * np.log10(DIST)
    k = len(x)
    sxx = np.sum((x - x.mean()) ** 2)
    s2 = 1.0 / 3.0
    return float(np.sqrt(s2 * np.sum(x * x) / (k * sxx))), float(np.sqrt(s2 / sxx))


def test_recalibration_replaces_se_and_drops_calib_fixed(tmp_path, capsys):
    s = _write(tmp_path / "s.csv", _ld_survey({"1": (-40, 2)}))
    an = _write(tmp_path / "a.csv", pd.DataFrame({
        "anchor": [1], "x": [0], "y": [0], "A": [-50], "n": [2.5], "sigma": [3],
        "A_se": [0.4], "n_se": [0.05], "p0_se": [9.0], "calib_source": ["self"],
        "calib_fixed": ["n"]}))
    code, _, err = _cli([s, "--anchors", an, "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0, err
    out = pd.read_csv(tmp_path / "o.csv")
    assert "calib_fixed" not in out.columns and "p0_se" not in out.columns
    a_se, n_se = _ld_se()
    assert out["A_se"].iloc[0] == pytest.approx(a_se, rel=1e-9)
    assert out["n_se"].iloc[0] == pytest.approx(n_se, rel=1e-9)
    assert out["sigma"].iloc[0] == pytest.approx(SIGMA8, rel=1e-9)
    assert out["calib_source"].iloc[0] == "anchor"


def test_without_anchors_sigma_and_se_written(tmp_path, capsys):
    s = _write(tmp_path / "s.csv", _ld_survey({"1": (-40, 2)}))
    code, _, _ = _cli([s, "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0
    out = pd.read_csv(tmp_path / "o.csv")
    a_se, n_se = _ld_se()
    assert out["sigma"].iloc[0] == pytest.approx(SIGMA8, rel=1e-9)
    assert out["A_se"].iloc[0] == pytest.approx(a_se, rel=1e-9)
    assert out["n_se"].iloc[0] == pytest.approx(n_se, rel=1e-9)


# -- 6: the anchors' d0 goes with their p0 ------------------------------------------------


def _d02(tmp_path: Path) -> tuple[str, str]:
    # P = p0 + 10 gamma lg(d0/d) + faf with p0 -46 at d0 = 2 m, gamma 2, faf 0
    s = pd.DataFrame({"anchor": "1", "distance": DIST,
                      "rssi": -46 + 20 * np.log10(2.0 / DIST) + ERR})
    an = pd.DataFrame({"anchor": [1], "x": [0], "y": [0], "p0": [-46.0], "d0": [2.0]})
    return _write(tmp_path / "s.csv", s), _write(tmp_path / "a.csv", an)


def test_anchors_d0_used_with_their_p0(tmp_path, capsys):
    s, an = _d02(tmp_path)
    code, _, err = _cli([s, "--model", "attenuation-factor", "--anchors", an,
                         "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0, err
    out = pd.read_csv(tmp_path / "o.csv")
    assert out["d0"].iloc[0] == 2.0
    assert out["faf"].iloc[0] == pytest.approx(0.0, abs=1e-9)  # was 20 lg 2 = 6.02
    assert out["gamma"].iloc[0] == pytest.approx(2.0, abs=1e-9)


def test_explicit_d0_contradicting_the_anchors_refused(tmp_path, capsys):
    s, an = _d02(tmp_path)
    code, _, err = _cli([s, "--model", "attenuation-factor", "--anchors", an, "--d0", "3",
                         "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 2
    assert "error:" in err and "--d0 3 contradicts the anchors file's d0 (2)" in err
    code, _, err = _cli([s, "--model", "attenuation-factor", "--anchors", an, "--d0", "2",
                         "-o", str(tmp_path / "o.csv")], capsys)
    assert code == 0, err


# -- 7: options that do not apply ---------------------------------------------------------


@pytest.mark.parametrize(("kind", "opts", "text"), [
    ("range", ["--model", "attenuation-factor"], "--model attenuation-factor applies to RSSI"),
    ("range", ["--p0", "-30"], "--p0 applies to RSSI"),
    ("range", ["--d0", "2"], "--d0 applies to RSSI"),
    ("rssi", ["--scale"], "--scale is for range data"),
    ("rssi", ["--no-scale"], "--scale is for range data"),
    ("rssi", ["--p0", "-30"], "--p0 does not apply to --model log-distance"),
    ("rssi", ["--d0", "2"], "--d0 does not apply to --model log-distance"),
    ("rssi", ["--model", "friis", "--p0", "-30"], "--p0 does not apply to --model friis"),
    ("rssi", ["--time-tolerance", "9"], "--time-tolerance applies to --measurements"),
    ("range", ["--time-tolerance", "9"], "--time-tolerance applies to --measurements"),
])
def test_inapplicable_options_refused(tmp_path, capsys, kind, opts, text):
    s = (_ld_survey({"1": (-40, 2)}) if kind == "rssi" else
         pd.DataFrame({"anchor": "1", "distance": DIST, "range": DIST + 0.3 + ERR}))
    code, _, err = _cli([_write(tmp_path / "s.csv", s), *opts, "-o",
                         str(tmp_path / "o.csv")], capsys)
    assert code == 2
    assert err.startswith("error:") and text in err


@pytest.mark.parametrize(("kind", "opts"), [
    ("rssi", ["--model", "friis", "--d0", "2"]),
    ("rssi", ["--d0", "1", "--time-tolerance", "1e-6"]),  # the defaults are not "given"
    ("range", ["--scale"]),
])
def test_applicable_options_accepted(tmp_path, capsys, kind, opts):
    s = (_ld_survey({"1": (-40, 2)}) if kind == "rssi" else
         pd.DataFrame({"anchor": "1", "distance": DIST, "range": 1.1 * DIST + 0.3 + ERR}))
    code, _, err = _cli([_write(tmp_path / "s.csv", s), *opts, "-o",
                         str(tmp_path / "o.csv")], capsys)
    assert code == 0, err


# -- 8: probability weights ---------------------------------------------------------------


def test_probability_weights_message_and_help(tmp_path, capsys):
    s = _ld_survey({"1": (-40, 2)})
    s["weight"] = 1.0 / len(s)  # total weight 1 < 2 parameters: no degree of freedom
    code, _, err = _cli([_write(tmp_path / "s.csv", s), "-o", str(tmp_path / "o.csv")],
                        capsys)
    assert code == 2
    assert "total weight of its rows is too small for the parameters" in err
    assert "exact" not in err
    assert main(["calibrate", "--help"]) == 0
    help_text = " ".join(capsys.readouterr().out.split())
    assert "column weight: frequency weights" in help_text
    assert "else horizontal (even when the anchors have z)" in help_text


# -- 5: practically undetermined exponent -------------------------------------------------


def test_implausible_level_refused(tmp_path, capsys):
    # distances 3.000 and 3.003 m: A = +2149 dBm, n = 461 by least squares
    s = pd.DataFrame({"anchor": "1", "distance": [3.0, 3.0, 3.003, 3.003],
                      "rssi": [-50.0, -49.0, -51.0, -52.0]})
    code, _, err = _cli([_write(tmp_path / "s.csv", s), "-o", str(tmp_path / "o.csv")],
                        capsys)
    assert code == 2
    assert "anchor 1: fitted A = 2149 dBm at 1 m is implausible" in err
    assert not (tmp_path / "o.csv").exists()


def test_implausible_exponent_refused(tmp_path, capsys):
    # 1 and 1.1 m, 20 dB apart: n = 20 / (10 lg 1.1) = 48.32 with A = -40 dBm plausible
    d = np.array([1.0, 1.0, 1.1, 1.1])
    s = pd.DataFrame({"anchor": "1", "distance": d,
                      "rssi": -40 - 20 / np.log10(1.1) * np.log10(d) + ERR[:4]})
    code, _, err = _cli([_write(tmp_path / "s.csv", s), "-o", str(tmp_path / "o.csv")],
                        capsys)
    assert code == 2
    assert "anchor 1: fitted n = 48.32 is implausible" in err


@pytest.mark.parametrize("bad, shown", [(-1, "'-1.0'"), (np.inf, "'inf'"),
                                        (1e300, "'1e+300'")])
def test_a_bad_weight_is_named_as_written(tmp_path, capsys, bad, shown):
    """The message said ``np.int64(-1)`` / ``np.float64(inf)`` (NumPy's repr); 1e300
    (the input review) overflowed the fit into ``fitted n = nan is not positive``."""
    s = _ld_survey({"1": (-40, 2)})
    s["weight"] = 1.0
    s.loc[1, "weight"] = bad
    code, _, err = _cli([_write(tmp_path / "s.csv", s), "-o", str(tmp_path / "o.csv")],
                        capsys)
    assert code == 2
    assert f"column 'weight': {shown} must be a finite number in [0, 1e+09]" in err, err
    assert "np." not in err
