"""What a self-calibration (and a truth-based range calibration) writes for ``sigma``, and
what a parameter the log cannot determine keeps (the self-calibration review,
2026-12-07).

* ``sigma`` is the standard deviation of the value ``locate`` fits: for ranges of the
  corrected range ``(range - bias) / scale``, i.e. the raw range's sigma over the scale.
* A range anchor the log cannot determine keeps the anchors file's ``bias, scale,
  sigma`` (they were reset to 0, 1 and the median of the others' sigmas).
* A sigma the log cannot determine is left out: of an anchor whose parameters were left
  out because the tag does not move (its residuals carry the unfitted biases), or whose
  variance component has at most 2 degrees of freedom.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.models.calibration import calibrate_ranges, self_calibration_table
from robustloc.models.selfcal import SelfCalibrator

ANCHORS = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 8.0], [0.0, 8.0], [5.0, -2.0]])
IDS = [f"a{i}" for i in range(len(ANCHORS))]


def _log(rng, n, scale, sigma, bias=0.0, static=None):
    x = (np.broadcast_to(np.asarray(static, float), (n, 2)).copy() if static is not None
         else rng.uniform([1.0, 1.0], [9.0, 7.0], (n, 2)))
    d = np.linalg.norm(x[:, None, :] - ANCHORS[None], axis=-1)
    return x, scale * d + bias + rng.normal(size=d.shape) * sigma


def _files(tmp_path, x, z, anchors):
    k, j = np.nonzero(np.isfinite(z))
    pd.DataFrame({"time": k.astype(float), "tag": "t", "anchor": np.array(IDS)[j],
                  "range": z[k, j]}).to_csv(tmp_path / "m.csv", index=False)
    anchors.to_csv(tmp_path / "a.csv", index=False)
    pd.DataFrame({"time": np.arange(len(x), dtype=float), "tag": "t", "x": x[:, 0],
                  "y": x[:, 1]}).to_csv(tmp_path / "t.csv", index=False)


def _anchors(**cols):
    return pd.DataFrame({"anchor": IDS, "x": ANCHORS[:, 0], "y": ANCHORS[:, 1], **cols})


# -------------------------------------------------------------------- 1: sigma's units
def test_self_calibration_writes_the_corrected_ranges_sigma():
    """The written sigma is ``res.sigma / scale`` (the corrected range's sd), to rounding.
    On the code before it was ``res.sigma``: 1.5x too large on the two anchors of scale
    1.5 (the review: 0.229 written for a corrected spread of 0.139)."""
    rng = np.random.default_rng(11)
    scale = np.array([1.0, 1.0, 1.5, 1.5, 1.0])
    x, z = _log(rng, 400, scale, 0.2)
    res = SelfCalibrator("range").fit(ANCHORS, z, x + rng.normal(size=x.shape) * 0.3)
    assert res.free.all() and np.all(np.abs(res.slope - scale) < 4 * res.slope_se)
    table, out = self_calibration_table(res, _anchors())
    np.testing.assert_allclose(out["sigma"], res.sigma / res.slope, rtol=1e-12)
    np.testing.assert_allclose(table["sigma"], res.sigma / res.slope, rtol=1e-12)


def test_truth_calibration_writes_the_corrected_ranges_sigma():
    """A survey of scale 1.5 and 0.2 m of noise: the corrected ranges spread 0.2 / 1.5 =
    0.133 m, which is what the file must say (it said 0.2).  Tolerance: the least-squares
    residual sd of n = 2 000 rows has a relative sd of 1 / sqrt(2 (n - 2)) = 1.6 %; 4 of
    them, 6.4 %."""
    rng = np.random.default_rng(5)
    n = 2000
    d = rng.uniform(1.0, 15.0, n)
    sv = pd.DataFrame({"anchor": "a0", "distance": d,
                       "range": 1.5 * d + 0.3 + rng.normal(size=n) * 0.2})
    res = calibrate_ranges(sv, scale=True)
    out = res.apply_to_anchors(pd.DataFrame({"anchor": ["a0"], "x": [0.0], "y": [0.0]}))
    assert out["scale"].iloc[0] == pytest.approx(1.5, abs=0.01)
    assert out["sigma"].iloc[0] == pytest.approx(0.2 / 1.5, rel=0.064)


# ------------------------------------------------------------ 2: the anchors file's priors
def test_an_undetermined_range_anchor_keeps_the_anchors_files_calibration(tmp_path, capsys):
    """Anchor a4 heard alone, in two epochs (no fix): its bias, scale and sigma stay the
    file's (they were written as 0, 1 and the others' median sigma).  The determined
    anchors come out the same, to the last digit, from the raw file and from the
    calibrated one, and a second run on the output changes nothing (idempotent)."""
    rng = np.random.default_rng(3)
    x, z = _log(rng, 300, 1.0, 0.1, bias=np.array([0.2, -0.1, 0.3, 0.0, 0.4]))
    z[:, 4] = np.nan
    z[:2, :4], z[:2, 4] = np.nan, [9.0, 9.5]
    raw = _anchors()
    cal_in = _anchors(bias=[0.1, 0.1, 0.1, 0.1, 0.229], scale=[1.0, 1.0, 1.0, 1.0, 0.979],
                      sigma=[0.1, 0.1, 0.1, 0.1, 0.152])
    _files(tmp_path, x, z, raw)
    cal_in.to_csv(tmp_path / "c.csv", index=False)
    outs = {}
    for name, src in (("raw", "a.csv"), ("cal", "c.csv")):
        assert main(["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
                     str(tmp_path / src), "-o", str(tmp_path / f"o-{name}.csv")]) == 0
        outs[name] = pd.read_csv(tmp_path / f"o-{name}.csv").set_index("anchor")
    err = capsys.readouterr().err
    assert "fixed at their priors" in err and "anchor a4: cannot determine sigma" in err
    got = outs["cal"].loc["a4"]
    assert (got["bias"], got["scale"], got["sigma"]) == (0.229, 0.979, 0.152)
    assert outs["cal"].loc["a4", "calib_fixed"] == "bias;scale"
    det = IDS[:4]
    for c in ("bias", "scale", "sigma", "bias_se", "scale_se"):
        np.testing.assert_array_equal(outs["cal"].loc[det, c], outs["raw"].loc[det, c])
    # again on its own output: nothing moves
    assert main(["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
                 str(tmp_path / "o-cal.csv"), "-o", str(tmp_path / "o-2.csv")]) == 0
    again = pd.read_csv(tmp_path / "o-2.csv").set_index("anchor")
    for c in ("bias", "scale", "sigma"):
        np.testing.assert_array_equal(again[c], outs["cal"][c])


def test_fit_offset_prior_is_what_a_left_out_parameter_keeps():
    """``offset_prior``/``slope_prior`` are the values of the parameters left out; the
    start (``offset0``/``slope0``, default 0 / 1) is unchanged."""
    rng = np.random.default_rng(4)
    x, z = _log(rng, 300, 1.0, 0.1)
    cal = SelfCalibrator("range", fit_slope=False)
    r0 = cal.fit(ANCHORS, z, x)
    r1 = cal.fit(ANCHORS, z, x, slope_prior=np.full(5, 1.02))
    assert np.all(r0.slope == 1.0) and np.all(r1.slope == 1.02)
    # the biases absorb the 2 % scale held: fitted with it, not with 1
    assert not np.allclose(r0.offset, r1.offset)


# --------------------------------------------------------------- 3: undetermined sigma
def test_static_tag_writes_no_sigma_and_locate_is_as_with_the_raw_file(tmp_path, capsys):
    """A static tag: every bias and scale left out, and (new) every sigma: they absorbed
    the biases (0.11-1.04 m for 0.10-0.17 m in the review).  Without a sigma in the file,
    none is written, and ``locate`` with the output gives the raw file's positions
    exactly (the review: 0.53 m RMS with the sigmas written, 0.21 m without)."""
    rng = np.random.default_rng(1)
    x, z = _log(rng, 300, 1.0, np.array([0.16, 0.13, 0.10, 0.17, 0.10]),
                bias=np.array([0.0, 0.45, -0.36, 0.45, -0.19]), static=(4.0, 5.0))
    _files(tmp_path, x, z, _anchors())
    assert main(["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
                 str(tmp_path / "a.csv"), "-o", str(tmp_path / "c.csv")]) == 0
    err = capsys.readouterr().err
    assert "cannot determine sigma: its parameters were left out (the tag does not move)" \
        in err
    assert "no sigma written" in err
    out = pd.read_csv(tmp_path / "c.csv")
    assert "sigma" not in out.columns
    pos = {}
    for name in ("a", "c"):
        assert main(["locate", str(tmp_path / "m.csv"), "--anchors",
                     str(tmp_path / f"{name}.csv"), "-o", str(tmp_path / f"p-{name}.csv"),
                     "--quiet"]) == 0
        pos[name] = pd.read_csv(tmp_path / f"p-{name}.csv")[["x", "y"]].to_numpy()
    np.testing.assert_array_equal(pos["a"], pos["c"])


def test_a_file_sigma_stays_where_the_log_does_not_determine_it(tmp_path):
    """The same static log with a sigma in the anchors file: the file's sigmas stay."""
    rng = np.random.default_rng(1)
    x, z = _log(rng, 300, 1.0, 0.15, static=(4.0, 5.0))
    sig = [0.11, 0.12, 0.13, 0.14, 0.15]
    _files(tmp_path, x, z, _anchors(sigma=sig))
    assert main(["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
                 str(tmp_path / "a.csv"), "-o", str(tmp_path / "c.csv")]) == 0
    np.testing.assert_array_equal(pd.read_csv(tmp_path / "c.csv")["sigma"], sig)


def test_a_variance_component_of_few_degrees_of_freedom_is_left_out():
    """Three epochs, nothing fitted (bias and scale held): 9 residual degrees of freedom
    for five variance components.  An anchor's sigma is determined only when its
    Satterthwaite degrees of freedom exceed 2 (the estimate more than one of its standard
    errors from zero); here none does, and each gets a warning.  On a log of 300 epochs
    (about 180 degrees of freedom each) every one is determined."""
    from robustloc.models.selfcal import SIGMA_MIN_DOF

    rng = np.random.default_rng(3)
    for n, determined in ((3, False), (300, True)):
        x, z = _log(rng, n, 1.0, 0.15)
        res = SelfCalibrator("range", fit_offset=False, fit_slope=False).fit(ANCHORS, z, x)
        assert np.all(res.sigma_determined() == determined), n
        said = [w for w in res.warnings if "cannot determine sigma" in w]
        assert (len(said) > 0) != determined
        assert all(f"at most {SIGMA_MIN_DOF:g}" in w for w in said)
