"""calibrate never writes a path-loss exponent that locate / track refuse (the input review).

A survey whose RSSI hardly falls with distance fitted ``n = 0.00399`` (``gamma`` with
``--model attenuation-factor``), written with exit 0; ``locate`` then refused the file
(``path-loss exponent n must lie in [0.01, 20]``).  calibrate's interval is now
``[0.01, 10]``: its lower end is the anchors reader's, shared, and its message states it
(it said ``(0, 10]``).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.errors import InputError
from robustloc.io import read_anchors
from robustloc.io.limits import PATH_LOSS_EXPONENT_LIMITS
from robustloc.models.calibration import MAX_EXPONENT, MIN_EXPONENT, exponent_interval

ANCHORS = "anchor,x,y\n1,0,0\n2,10,0\n3,0,10\n"


def _survey(n: float, A: float = -70.0, dists=(1, 2, 4, 8, 16), sd: float = 0.05,
            seed: int = 0) -> pd.DataFrame:
    """20 readings per distance per anchor of ``A - 10 n lg d`` (the review's
    calr/make_surveys.py)."""
    rng = np.random.default_rng(seed)
    d = np.repeat(np.asarray(dists, float), 20)
    rows = [pd.DataFrame({"anchor": a, "distance": d,
                          "rssi": A - 10 * n * np.log10(d) + rng.normal(0, sd, d.size)})
            for a in ("1", "2", "3")]
    return pd.concat(rows, ignore_index=True)


def test_calibrate_interval_lies_inside_the_anchors_readers():
    """The shared constant: what calibrate accepts, the anchors reader accepts."""
    lo, hi = PATH_LOSS_EXPONENT_LIMITS
    assert MIN_EXPONENT == lo and lo < MAX_EXPONENT <= hi
    assert exponent_interval() == "[0.01, 10]"


@pytest.mark.parametrize("model, name", [("log-distance", "n"),
                                         ("attenuation-factor", "gamma")])
@pytest.mark.parametrize("pooled", [False, True])
def test_an_exponent_below_locates_bound_is_refused(tmp_path, capsys, model, name, pooled):
    """The review's flat survey (n about 0.004): exit 2, nothing written, the anchor (or
    the pooled fit) and the interval named."""
    _survey(0.004).to_csv(tmp_path / "s.csv", index=False)
    (tmp_path / "a.csv").write_text(ANCHORS)
    out = tmp_path / "cal.csv"
    argv = ["calibrate", str(tmp_path / "s.csv"), "--anchors", str(tmp_path / "a.csv"),
            "--model", model, "-o", str(out)] + (["--pooled"] if pooled else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    who = "pooled fit" if pooled else "anchor 1"
    assert f"error: {tmp_path / 's.csv'}: {who}: fitted {name} = 0.00" in err, err
    assert ("is implausible (a path-loss exponent lies in [0.01, 10]): the survey does "
            "not determine it (the RSSI hardly falls with distance over the survey)") in err
    assert not out.exists()


def test_a_distance_of_1e_300_is_refused(tmp_path, capsys):
    """The review's ms/tiny_dist.csv: one reading at 1e-300 m drags the fit to
    n = 0.0033; this one 0.001)."""
    s = pd.DataFrame({"anchor": "1", "distance": [1e-300, 2.5, 2.5, 5.0, 5.0],
                      "rssi": [-73.0, -75.0, -70.0, -80.0, -79.0]})
    s.to_csv(tmp_path / "s.csv", index=False)
    (tmp_path / "a.csv").write_text("anchor,x,y\n1,1.5,0\n")
    assert main(["calibrate", str(tmp_path / "s.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(tmp_path / "cal.csv")]) == 2
    err = capsys.readouterr().err
    assert "anchor 1: fitted n = 0.001" in err and "lies in [0.01, 10]" in err, err
    assert not (tmp_path / "cal.csv").exists()


def test_the_upper_bound_message_states_the_interval(tmp_path, capsys):
    """n about 25 was refused saying "(0, 10]", an interval 0.004 passed."""
    _survey(25.0, A=-20.0, dists=(1, 1.2, 1.5, 2), sd=0.5).to_csv(tmp_path / "s.csv",
                                                                   index=False)
    assert main(["calibrate", str(tmp_path / "s.csv"), "-o", str(tmp_path / "cal.csv")]) == 2
    err = capsys.readouterr().err
    assert "is implausible (a path-loss exponent lies in [0.01, 10]): the survey does not " \
           "determine it (too small a spread of distances?)" in err, err
    assert "(0, 10]" not in err


@pytest.mark.parametrize("model", ["log-distance", "attenuation-factor", "friis"])
def test_what_calibrate_writes_locate_reads(tmp_path, capsys, model):
    """A small but plausible exponent (0.05) is written, and read back by the anchors
    reader that locate and track use."""
    _survey(0.05, sd=0.02).to_csv(tmp_path / "s.csv", index=False)
    (tmp_path / "a.csv").write_text(ANCHORS)
    out = tmp_path / "cal.csv"
    assert main(["calibrate", str(tmp_path / "s.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "--model", model, "-o", str(out)]) == 0, capsys.readouterr().err
    read_anchors(out)  # no InputError


def test_rssi_self_calibration_is_held_to_the_same_interval():
    """``calibrate --self`` (RSSI): an exponent of 0.004 (or 25) was refused only when not
    positive, and written otherwise."""
    from robustloc.pipelines.calibrate import _refuse_implausible

    free = np.ones((3, 2), bool)
    values = np.full((2, 3), -70.0)
    res = SimpleNamespace(param_names=("A", "n"), free=free,
                          offset=np.array([-60.0, -61.0, -62.0]),
                          slope=np.array([0.004, 2.0, 25.0]), epochs_used=2, epochs_total=2)
    with pytest.raises(InputError) as e:
        _refuse_implausible(res, ["a", "b", "c"], "rssi", values, "log.csv")
    msg = str(e.value)
    assert "n of anchor a = 0.004 (a path-loss exponent lies in [0.01, 10])" in msg
    assert "n of anchor c = 25 (a path-loss exponent lies in [0.01, 10])" in msg
    assert "anchor b" not in msg
    ok = SimpleNamespace(**{**vars(res), "slope": np.array([0.01, 2.0, 10.0])})
    _refuse_implausible(ok, ["a", "b", "c"], "rssi", values, "log.csv")  # no error
    # a parameter left out (fixed at its prior) is not the fit's: not checked here
    fixed = SimpleNamespace(**{**vars(res), "free": np.zeros((3, 2), bool)})
    _refuse_implausible(fixed, ["a", "b", "c"], "rssi", values, "log.csv")
