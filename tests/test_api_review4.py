"""The Python API review of 2026-12-06: settings given as ``None`` or as text, and the
other refusals it found."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

import robustloc
from robustloc.errors import InputError

ANCHORS = pd.DataFrame({"anchor": list("abcd"), "x": [0, 10, 10, 0.0], "y": [0, 0, 10, 10.0]})


@pytest.fixture
def log() -> pd.DataFrame:
    rng = np.random.default_rng(0)
    rows = [(float(t), "T", k, float(np.hypot(x - 3 - 0.2 * t, y - 4)) + rng.normal(0, 0.05))
            for t in range(12) for k, x, y in zip(ANCHORS.anchor, ANCHORS.x, ANCHORS.y)]
    return pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"])


@pytest.mark.parametrize("call, kw, flag", [
    ("locate", {"chunk_rows": None}, "--chunk-rows"),
    ("track", {"q": None}, "--q"),
    ("track", {"alpha0": None}, "--alpha0"),
    ("track", {"noise_scale_min": None}, "--noise-scale-min"),
    ("track", {"integrity_risk": None}, "--integrity-risk"),
])
def test_none_for_a_setting_with_a_default_is_refused_by_name(log, call, kw, flag):
    """``None`` passed validation as "not given" and met the numerical code: a
    TypeError comparing NoneType and int, deep inside."""
    with pytest.raises(InputError, match=f"argument {flag}: expected a value, got None"):
        getattr(robustloc, call)(log, ANCHORS, **kw)


def test_settings_given_as_text_are_read_as_the_command_line_reads_them(log):
    """Text passed the checks and reached the numerical code as text (a TypeError
    comparing str and float): now converted, the rows those of the numbers."""
    pd.testing.assert_frame_equal(robustloc.locate(log, ANCHORS, min_scale="0.1"),
                                  robustloc.locate(log, ANCHORS, min_scale=0.1))
    pd.testing.assert_frame_equal(robustloc.track(log, ANCHORS, q="1", fixed_lag="3"),
                                  robustloc.track(log, ANCHORS, q=1.0, fixed_lag=3))
    pos = robustloc.locate(log, ANCHORS)
    truth = pd.DataFrame({"time": np.arange(12.0), "tag": "T", "x": 3 + 0.2 * np.arange(12),
                          "y": 4.0})
    pd.testing.assert_frame_equal(robustloc.evaluate(pos, truth, time_tolerance="1"),
                                  robustloc.evaluate(pos, truth, time_tolerance=1.0))


def test_spp_systems_none_is_named(tmp_path):
    with pytest.raises(InputError, match="expected letters of .* as text, got None"):
        from robustloc.options import check_systems

        check_systems(None, "GREC")  # type: ignore[arg-type]


@pytest.mark.parametrize("robust", [0, "", 1, [1]])
def test_calibrate_robust_takes_a_flag_or_a_weight_name(robust):
    """``robust=0`` and ``""`` were taken as "plain", ``1`` refused as a weight's name."""
    d = np.array([1.0, 2.0, 4.0, 6.0, 8.0])
    survey = pd.DataFrame({"anchor": "a", "distance": d, "range": 1.05 * d + 0.3})
    with pytest.raises(InputError, match="robust: expected True, False or a weight's name"):
        robustloc.calibrate(survey, robust=robust)


def test_track_is_typed():
    """``robustloc.track`` was missing from the package's static view (py.typed)."""
    import inspect

    import robustloc as pkg

    src = inspect.getsource(pkg)
    head = src.split("if TYPE_CHECKING:", 1)[1].split(")", 1)[0]
    assert {"track", "locate", "calibrate", "evaluate", "spp"} <= {
        w.strip(" ,\n") for w in head.split("\n")}
