"""track's process-noise options end at 1e6 (the input review).

``track --link-offsets on --link-offset-q 1e308`` exited 0 with 73 of 180 rows ``ok``
without ``hpl`` (the covariance overflowed); ``--range-offset-q 1e308`` leaked NumPy
overflow warnings.  ``--q``, ``--range-offset-q``, ``--link-offset-q`` and ``serve
--track-q`` now end at :data:`robustloc.options.PROCESS_NOISE_MAX` (1e6: an offset
wandering by 1000 units in a second), refused by the parser (exit 2) and by the library's
settings (ValueError).
"""

from __future__ import annotations

import warnings

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.options import PROCESS_NOISE_MAX
from robustloc.pipelines.track import TrackSettings
from robustloc.tracking import Tracker

ANCHORS = pd.DataFrame({"anchor": list("abcd"), "x": [0.0, 20, 0, 20], "y": [0.0, 0, 20, 20]})


def _ranges(n_epochs: int = 30, seed: int = 0) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    anc = ANCHORS[["x", "y"]].to_numpy()
    k = np.repeat(np.arange(n_epochs), 4)
    j = np.tile(np.arange(4), n_epochs)
    pos = np.column_stack([2 + 0.5 * np.arange(n_epochs), np.full(n_epochs, 8.0)])
    d = np.hypot(pos[k, 0] - anc[j, 0], pos[k, 1] - anc[j, 1])
    return pd.DataFrame({"time": k * 0.5, "tag": "T", "anchor": ANCHORS["anchor"].to_numpy()[j],
                         "range": d + rng.normal(0, 0.05, d.size)})


@pytest.fixture()
def files(tmp_path):
    ANCHORS.to_csv(tmp_path / "a.csv", index=False)
    _ranges().to_csv(tmp_path / "m.csv", index=False)
    return tmp_path


@pytest.mark.parametrize("more, flag, shown", [
    (["--link-offsets", "on", "--link-offset-q", "1e308"], "--link-offset-q",
     "[0, 1e+06], got '1e308'"),
    (["--range-offset", "--range-offset-q", "1e308"], "--range-offset-q",
     "[0, 1e+06], got '1e308'"),
    (["--q", "1e308"], "--q", "(0, 1e+06], got '1e308'"),
    (["--q", "2e6"], "--q", "(0, 1e+06], got '2e6'"),
])
def test_track_refuses_a_process_noise_beyond_1e6(files, capsys, more, flag, shown):
    out = files / "t.csv"
    assert main(["track", str(files / "m.csv"), "--anchors", str(files / "a.csv"),
                 "-o", str(out), "-q", *more]) == 2
    err = capsys.readouterr().err
    assert f"error: argument {flag}: expected a number in {shown}" in err, err
    assert not out.exists()


@pytest.mark.parametrize("more", [["--link-offsets", "on", "--link-offset-q", "1e6"],
                                  ["--range-offset", "--range-offset-q", "1e6"],
                                  ["--q", "1e6"]])
def test_track_at_the_bound_runs_without_overflow(files, capsys, more):
    """1e6 is far from overflow: every ``ok`` row has its ``hpl``, no warning."""
    out = files / "t.csv"
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        assert main(["track", str(files / "m.csv"), "--anchors", str(files / "a.csv"),
                     "-o", str(out), "-q", *more]) == 0
    assert capsys.readouterr().err == ""
    d = pd.read_csv(out)
    ok = d["status"] == "ok"
    assert ok.any() and d.loc[ok, "hpl"].notna().all()


@pytest.mark.parametrize("argv, shown", [
    (["--track", "--track-q", "1e308"], "argument --track-q: expected a number in "
     "(0, 1e+06], got '1e308'"),
    (["--track", "--sigma", "1e308"], "argument --sigma: expected a number in "
     "[1e-06, 1e+06], got '1e308'"),
])
def test_serve_refuses_them_too(files, capsys, argv, shown):
    assert main(["serve", "--anchors", str(files / "a.csv"), *argv]) == 2
    assert shown in capsys.readouterr().err


@pytest.mark.parametrize("name", ["q", "range_offset_q", "link_offset_q"])
def test_the_library_refuses_them(name):
    with pytest.raises(ValueError, match=f"{name} must be at most 1e\\+06, got 1e\\+308"):
        Tracker(ANCHORS, **{name: 1e308})
    with pytest.raises(ValueError, match="expected a number in"):  # InputError: a ValueError
        TrackSettings(**{name: 1e308})
    Tracker(ANCHORS, **{name: PROCESS_NOISE_MAX})  # the bound itself is accepted
    TrackSettings(**{name: PROCESS_NOISE_MAX})
