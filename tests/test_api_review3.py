"""Defects the review of the Python API of 2026-12-06 found, each with the case that
showed it (each failed on the old code)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import robustloc
from robustloc.estimators.ranging import Locator
from robustloc.integrity.fixes import locate_protected
from robustloc.io.tables import Epochs, to_epochs
from robustloc.robust import get_weight
from robustloc.tracking import Tracker

RAW = pd.DataFrame({"anchor": list("abcd"), "x": [0, 10, 10, 0.0], "y": [0, 0, 10, 10.0]})
ANCHORS = robustloc.read_anchors(RAW)
XY = RAW[["x", "y"]].to_numpy(float)


def _ranges(tags, t=0.0, p=(3.0, 4.0)) -> pd.DataFrame:
    d = np.hypot(XY[:, 0] - p[0], XY[:, 1] - p[1])
    return pd.DataFrame({"time": t, "tag": np.repeat(tags, 4),
                         "anchor": np.tile(ANCHORS["anchor"], len(tags)),
                         "range": np.tile(d, len(tags))})


def _ep(frame: pd.DataFrame):
    return to_epochs(frame, ANCHORS["anchor"])


def test_forget_one_tag_given_as_a_string():
    t = Tracker(ANCHORS)
    t.step(_ep(_ranges(["t1", "t", "1"])))
    assert t.forget("t1") == 1  # (its characters were taken as tags 't' and '1')
    assert sorted(t.tags) == ["1", "t"]


def test_smoothed_rows_are_numbered_across_steps():
    log = pd.concat([_ranges(["t1"], t=0.5 * k, p=(2 + 0.15 * k, 5.0)) for k in range(10)])
    whole = Tracker(ANCHORS, record=True)
    whole.step(_ep(log))
    parts = Tracker(ANCHORS, record=True)
    parts.step(_ep(log.iloc[:20]))
    parts.step(_ep(log.iloc[20:]))
    # the second step's rows overwrote the first's (rows 5-9 NaN): now one history
    np.testing.assert_allclose(parts.smoothed(10)[0], whole.smoothed(10)[0], rtol=0,
                               atol=1e-9)
    for bad in ({"n_rows": 3}, {"n_rows": 10, "lag": -1}, {"n_rows": 10, "lag": 1.5},
                {"n_rows": 10.0}):
        with pytest.raises(ValueError):
            whole.smoothed(**bad)


@pytest.mark.parametrize("kw", [{"k_noise": -1.0}, {"k_noise": np.nan},
                                {"alert_limit": -1.0}, {"alert_limit": np.nan}])
def test_locate_protected_refuses_bad_integrity_options(kw):
    r = np.hypot(*(XY - [3, 4]).T)[None].repeat(3, 0) + [[0.02, -0.01, 0.03, 0.0]]
    with pytest.raises(ValueError):
        locate_protected(Locator("auto"), XY, r, **kw)
    with pytest.raises(TypeError):
        locate_protected(Locator("auto"), XY, r, k_noise=np.complex128(3 + 1j))


@pytest.mark.parametrize("kw", [{"max_bad_epochs": float("nan")}, {"max_bad_epochs": 2.5},
                                {"readmit_samples": float("inf")},
                                {"q": np.complex128(1 + 1j)}, {"q": True}])
def test_tracker_settings_are_real_numbers_and_counts_whole(kw):
    with pytest.raises(TypeError):
        Tracker(ANCHORS, **kw)


def test_float_ids_do_not_depend_on_the_other_values():
    b = pd.DataFrame({"time": 0.0, "tag": np.array([1.0] * 4 + [7] * 4 + ["x"] * 4,
                                                   dtype=object),
                      "anchor": list("abcd") * 3, "range": 5.0})
    assert list(robustloc.read_measurements(b)["tag"].unique()) == ["1", "7", "x"]
    with pytest.raises(robustloc.InputError, match="duplicate anchor id '1'"):
        robustloc.read_anchors(pd.DataFrame({
            "anchor": np.array([1.0, 1, "c", "d"], dtype=object), "x": [0, 10, 10, 0.0],
            "y": [0, 0, 10, 10.0]}))


def test_complex_and_boolean_arrays_are_refused():
    v = np.hypot(XY[:, 0] - 3, XY[:, 1] - 4) + 7j
    ep = Epochs(np.zeros(1), np.array(["t"], dtype=object), v[None], tuple(ANCHORS["anchor"]),
                "range", np.zeros(1, np.int64))
    with pytest.raises(TypeError, match="complex"):
        Tracker(ANCHORS).step(ep)
    r = np.hypot(*(XY - [3, 4]).T)[None].repeat(5, 0)
    with pytest.raises(TypeError, match="complex"):
        Locator("huber").log_scale(XY, r + 5j)
    with pytest.raises(TypeError, match="complex"):
        get_weight("huber").weights(np.array([3 + 4j]))
    with pytest.raises(ValueError):
        get_weight("huber", c=np.complex128(1 + 1j))
    with pytest.raises(TypeError, match="booleans"):
        Locator("huber").solve(XY, [[True, True, False, True]])
    with pytest.raises(TypeError, match="booleans"):
        Locator("nls").solve(XY.astype(bool), [[5.0, 8.06, 9.2, 6.7]])


def test_tracker_rollback_and_alike_tags():
    t = Tracker(ANCHORS)
    t.step(_ep(_ranges(["t"])))
    for bad in (None, {}):
        with pytest.raises(TypeError):
            t.rollback(bad)
    t.step(_ep(_ranges(["t"], t=1.0)))  # intact after the refused rollbacks
    v = np.hypot(XY[:, 0] - 3, XY[:, 1] - 4)
    two = Epochs(np.zeros(2), np.array([1, "1"], dtype=object), np.vstack([v, v]),
                 tuple(ANCHORS["anchor"]), "range", np.zeros(2, np.int64))
    with pytest.raises(ValueError, match="read alike"):
        Tracker(ANCHORS).step(two)


def test_tracker_and_get_weight_name_the_caller_mistake():
    with pytest.raises(robustloc.InputError, match="y"):
        Tracker(RAW.drop(columns="y"))
    with pytest.raises(robustloc.InputError, match="anchor"):
        Tracker(RAW.drop(columns="anchor"))
    with pytest.raises(robustloc.InputError, match="duplicate"):
        Tracker(RAW.assign(anchor=list("abcc")))
    with pytest.raises(TypeError):
        Tracker(None)
    with pytest.raises(TypeError):
        Tracker(ANCHORS, weight=3)
    with pytest.raises(TypeError):
        get_weight(None)
    with pytest.raises(ValueError):
        get_weight("igg", c=float("nan"))


def test_log_statistics_checks_its_inputs():
    r = np.hypot(*(XY - [3, 4]).T)[None].repeat(5, 0)
    with pytest.raises(ValueError, match="iterations"):
        Locator("huber").log_scale(XY, r, iterations=0)
    with pytest.raises(ValueError, match="max_epochs"):
        Locator("huber").log_scale(XY, r, max_epochs=0)
    with pytest.raises(ValueError, match="anchors must be"):
        Locator("huber").log_scale(XY[0], r)
    with pytest.raises(TypeError, match="None"):
        locate_protected(Locator("auto"), None, r)


@pytest.mark.parametrize("value", [np.complex128(1 + 1j), np.complex64(1 + 1j), 1 + 1j])
def test_locate_refuses_a_complex_option(value):
    log = _ranges(["t"])
    with pytest.raises(robustloc.InputError, match="real number"):
        robustloc.locate(log, ANCHORS, sigma=value)
