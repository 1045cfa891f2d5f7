"""The Python API's checks of its arguments (robustloc.api): what the command line refuses,
the API refuses with the same words (an :class:`InputError`), and no argument makes it hang
or raise a raw pandas / NumPy error."""

from __future__ import annotations

import subprocess
import sys
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import pandas as pd
import pytest

import robustloc
from robustloc import InputError
from robustloc.cli import main

ANCHORS = pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 10.0, 10.0, 0.0],
                        "y": [0.0, 0.0, 10.0, 10.0]})


def _walk(n: int = 30, seed: int = 0) -> pd.DataFrame:
    """A range log of one tag walking across the 10 m square, ``n`` epochs 0.5 s apart."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.5
    xy = np.c_[2.0 + 0.2 * t, 5.0 + np.sin(0.3 * t)]
    d = np.hypot(ANCHORS.x.to_numpy() - xy[:, :1], ANCHORS.y.to_numpy() - xy[:, 1:])
    d = d + rng.normal(0.0, 0.05, d.shape)
    return pd.DataFrame({"time": np.repeat(t, 4), "tag": "t",
                         "anchor": np.tile(ANCHORS.anchor, n), "range": d.ravel()})


def _within(seconds: float, fn: Callable[[], Any]) -> Any:
    """``fn()``'s result, failing the test if it takes longer than ``seconds`` (the call
    is left running in a daemon thread: a hang fails instead of blocking the suite)."""
    out: dict[str, Any] = {}

    def run() -> None:
        try:
            out["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised below
            out["error"] = exc

    worker = threading.Thread(target=run, daemon=True)
    worker.start()
    worker.join(seconds)
    assert not worker.is_alive(), f"still running after {seconds} s"
    if "error" in out:
        raise out["error"]
    return out["value"]


def _states(frame: pd.DataFrame) -> np.ndarray:
    return frame[["x", "y", "vx", "vy", "var_x", "var_y", "cov_xy", "hpl"]].to_numpy(float)


# ---------------------------------------------------------------- track: smoothers


def test_fixed_lag_longer_than_the_log_is_the_fixed_interval_smoother_and_quick():
    """A lag beyond a segment's end is the RTS smoother over it; the work is bounded by
    the segment, not by the lag (a lag of 10**9 looped 10**9 times per segment)."""
    log = _walk(30)
    rts = robustloc.track(log, ANCHORS, smooth=True)
    full = robustloc.track(log, ANCHORS, fixed_lag=29)  # the segment's length - 1
    assert set(rts["status"]) == {"ok"}
    np.testing.assert_allclose(_states(full), _states(rts), rtol=0, atol=1e-9)
    huge = _within(30.0, lambda: robustloc.track(log, ANCHORS, fixed_lag=10**9))
    np.testing.assert_allclose(_states(huge), _states(rts), rtol=0, atol=1e-9)
    assert huge["method"].iloc[0] == "track-cv-ekf-lag1000000000"
    # a lag shorter than the log still smooths less than the whole log
    assert not np.allclose(_states(robustloc.track(log, ANCHORS, fixed_lag=2)), _states(rts))


def test_fixed_lag_longer_than_the_log_cli_is_quick(tmp_path):
    log = tmp_path / "m.csv"
    anchors = tmp_path / "a.csv"
    _walk(30).to_csv(log, index=False)
    ANCHORS.to_csv(anchors, index=False)
    # a child process, killed if it hangs
    cli = "import sys; from robustloc.cli import main; sys.exit(main(sys.argv[1:]))"
    subprocess.run([sys.executable, "-c", cli, "track", str(log), "--anchors",
                    str(anchors), "--fixed-lag", str(10**9), "-o", str(tmp_path / "t.csv")],
                   check=True, timeout=60, capture_output=True)
    assert len(pd.read_csv(tmp_path / "t.csv")) == 30


def test_smooth_and_fixed_lag_are_exclusive_as_on_the_command_line(tmp_path, capsys):
    log = tmp_path / "m.csv"
    anchors = tmp_path / "a.csv"
    _walk(10).to_csv(log, index=False)
    ANCHORS.to_csv(anchors, index=False)
    assert main(["track", str(log), "--anchors", str(anchors), "--smooth", "--fixed-lag",
                 "2", "-o", str(tmp_path / "t.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    with pytest.raises(InputError) as exc:
        robustloc.track(log, anchors, smooth=True, fixed_lag=2)
    assert str(exc.value) == "argument --fixed-lag: not allowed with argument --smooth"
    assert err.endswith(str(exc.value))
