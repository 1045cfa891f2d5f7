"""`calibrate --measurements --truth`: the standard errors' dwells said aloud (the
calibration review, 2026-12-06).  They are cluster-robust over the tag's dwells (one
truth position each); with one dwell they silently fell back to independent rows (200
rows at one point: standard errors 0.007 m for a spread of 0.17-0.22 m), and with few
they are optimistic.  Each case fails on the code before the notes."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main

ANCHORS = pd.DataFrame({"anchor": ["a1", "a2", "a3", "a4"], "x": [0.0, 20, 0, 20],
                        "y": [0.0, 0, 20, 20]})


def _write(tmp_path, points: list[tuple[float, float]], per_point: int) -> list[str]:
    rng = np.random.default_rng(4)
    a = ANCHORS[["x", "y"]].to_numpy()
    rows, truth, t = [], [], 0.0
    for p in points:
        off = rng.normal(0, 0.2, 4)  # the point's multipath, shared by its rows
        d = np.hypot(*(np.asarray(p) - a).T)
        for _ in range(per_point):
            r = d + 0.1 + off + rng.normal(0, 0.05, 4)
            rows += [(t, "T", an, float(v)) for an, v in zip(ANCHORS.anchor, r)]
            truth.append((t, "T", *p))
            t += 1.0
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]).to_csv(
        tmp_path / "m.csv", index=False)
    pd.DataFrame(truth, columns=["time", "tag", "x", "y"]).to_csv(tmp_path / "t.csv",
                                                                  index=False)
    ANCHORS.to_csv(tmp_path / "a.csv", index=False)
    return ["calibrate", "--measurements", str(tmp_path / "m.csv"), "--truth",
            str(tmp_path / "t.csv"), "--anchors", str(tmp_path / "a.csv"),
            "-o", str(tmp_path / "cal.csv")]


@pytest.mark.parametrize("n_points, words", [
    (1, "every row at one truth position (one dwell)"),
    (5, "standard errors from 5 dwells per anchor (fewer than 20"),
    (60, None),
])
def test_the_dwells_behind_the_standard_errors_are_said(tmp_path, capsys, n_points, words):
    rng = np.random.default_rng(n_points)
    points = [tuple(rng.uniform(3, 17, 2)) for _ in range(n_points)]
    assert main(_write(tmp_path, points, max(2, 200 // n_points))) == 0
    err = capsys.readouterr().err
    if words is None:
        assert "dwell" not in err
    else:
        assert words in err
    assert (tmp_path / "cal.csv").is_file()


def test_self_calibration_names_a_misplaced_anchor(tmp_path, capsys):
    """An anchor placed 190 m from where it is made the log look static; every parameter
    was left out ("the tag does not move") and sigmas of 31-191 m written, with no word
    on the anchor.  The run now names it as `locate` does (anchors_suspect); with the
    anchor where it is, no such warning."""
    rng = np.random.default_rng(0)
    a = pd.DataFrame({"anchor": ["a1", "a2", "a3", "a4", "a5"],
                      "x": [0.0, 20, 0, 20, 10], "y": [0.0, 0, 20, 20, -3]})
    x = rng.uniform(2, 18, (300, 2))
    d = np.hypot(x[:, None, 0] - a.x.to_numpy(), x[:, None, 1] - a.y.to_numpy())
    z = d + rng.normal(0, 0.1, d.shape)
    rows = [(float(k), "t", an, z[k, j]) for k in range(300) for j, an in enumerate(a.anchor)]
    pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]).to_csv(
        tmp_path / "m.csv", index=False)
    wrong = a.copy()
    wrong.loc[4, ["x", "y"]] = [200.0, 10.0]
    for name, frame, named in (("wrong", wrong, True), ("right", a, False)):
        frame.to_csv(tmp_path / f"{name}.csv", index=False)
        assert main(["calibrate", "--self", str(tmp_path / "m.csv"), "--anchors",
                     str(tmp_path / f"{name}.csv"), "-o", str(tmp_path / f"c-{name}.csv")]) == 0
        err = capsys.readouterr().err
        assert ("anchor(s) a5 (" in err and "check their coordinates" in err) == named, err
