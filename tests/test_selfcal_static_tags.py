"""``calibrate --self`` on tags that each stand still (the self-calibration review,
2026-12-06): two tags at two points gave the fit 10 distinct values for 4 position
unknowns and 10 parameters, which the fixes' jitter "determined" (scales 0.7-1.9 for a
truth near 1, a bias of -6.5 m; ``locate`` 9 m off where the prior gave 0.5 m), exit 0.
The motion test pooled the fixes, and two points look like motion.  Now each tag is
tested, and static tags are counted against the unknowns.  Each test fails on the code
before the rule."""

from __future__ import annotations

import numpy as np
import pandas as pd

from robustloc.cli import main
from robustloc.models.selfcal import SelfCalibrator

A = np.array([[0.0, 0], [20, 0], [0, 20], [20, 20], [10, -3]])
BIAS = np.array([0.3, -0.2, 0.5, 0.0, 0.1])
SCALE = np.array([1.02, 0.98, 1.0, 1.05, 1.0])


def _static_log(points: list[tuple[float, float]], n: int = 200, seed: int = 0,
                walker: bool = False):
    rng = np.random.default_rng(seed)
    xs, tags = [], []
    for i, p in enumerate(points):
        xs.append(np.tile(p, (n, 1)))
        tags += [f"T{i}"] * n
    if walker:  # one tag walking over the floor
        xs.append(rng.uniform(2, 18, (n, 2)))
        tags += ["W"] * n
    x = np.vstack(xs)
    d = np.linalg.norm(x[:, None, :] - A[None], axis=-1)
    z = SCALE * d + BIAS + rng.normal(size=d.shape) * 0.1
    return x, z, np.array(tags)


def test_two_static_tags_leave_every_parameter_out():
    x, z, tags = _static_log([(5.0, 5.0), (15.0, 8.0)])
    r = SelfCalibrator("range").fit(A, z, x + 0.2, anchor_ids=list("abcde"), tags=tags)
    assert not r.free.any()
    assert np.all(r.slope == 1.0) and np.all(r.offset == 0.0)
    assert any("the tags do not move: 2 tags each standing at one point give 10 distinct "
               "values" in w for w in r.warnings)


def test_three_static_tags_keep_the_biases_and_leave_the_scales_out():
    """15 values for 6 position unknowns: the 5 biases leave a redundancy of 4, the 10
    parameters of -1."""
    x, z, tags = _static_log([(5.0, 5.0), (15.0, 8.0), (8.0, 16.0)], seed=1)
    r = SelfCalibrator("range").fit(A, z, x + 0.2, anchor_ids=list("abcde"), tags=tags)
    assert not r.free[:, 1].any()
    assert any("scales left out below 2" in w for w in r.warnings)
    assert not any("every parameter left out" in w for w in r.warnings)


def test_a_walking_tag_beside_static_ones_changes_nothing():
    """A tag that moves gives positions enough: the rule leaves the fit as it was (the
    same estimates as without the tags)."""
    x, z, tags = _static_log([(5.0, 5.0), (15.0, 8.0)], seed=2, walker=True)
    with_tags = SelfCalibrator("range").fit(A, z, x + 0.2, tags=tags)
    without = SelfCalibrator("range").fit(A, z, x + 0.2)
    assert with_tags.free.all()
    np.testing.assert_array_equal(with_tags.slope, without.slope)
    np.testing.assert_array_equal(with_tags.offset, without.offset)


def test_the_command_keeps_the_prior_for_two_static_tags(tmp_path, capsys):
    x, z, tags = _static_log([(5.0, 5.0), (15.0, 8.0)], seed=3)
    t = np.repeat(np.arange(len(x) // 2, dtype=float), 1)
    times = np.r_[t, t]  # the two tags measured at the same times
    rows = [(times[k], tags[k], f"a{j}", z[k, j]) for k in range(len(x)) for j in range(5)]
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]).to_csv(
        tmp_path / "m.csv", index=False)
    pd.DataFrame({"anchor": [f"a{j}" for j in range(5)], "x": A[:, 0], "y": A[:, 1]}).to_csv(
        tmp_path / "a.csv", index=False)
    assert main(["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
                 str(tmp_path / "a.csv"), "-o", str(tmp_path / "cal.csv")]) == 0
    assert "the tags do not move" in capsys.readouterr().err
    cal = pd.read_csv(tmp_path / "cal.csv")
    assert np.all(cal["scale"].fillna(1.0) == 1.0) and np.all(cal["bias"].fillna(0.0) == 0.0)
