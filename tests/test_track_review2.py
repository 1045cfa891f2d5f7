"""`track`'s defects found by the second hostile review of the tracker (2026-12-06), each
failing on the code before its fix."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main


@pytest.mark.parametrize("kernel", ["compiled", "numpy"])
def test_an_rssi_range_that_under_or_overflows_is_no_observation(tmp_path, capsys, kernel):
    """A path-loss exponent of 0.01 (the anchors reader's lower limit) maps -5 dBm to
    ``10^((A - rssi) / (10 n)) = 10^-350`` m: the compiled update divided by the zero
    variance (ZeroDivisionError, "internal error", exit 1) and the NumPy one wrote an
    ``ok`` row on the anchor with an infinite ``hpl``.  Such a range is now no
    observation: the three other anchors place the tag, with a finite bound."""
    (tmp_path / "a.csv").write_text("anchor,x,y,A,n\nB1,0,0,-40,0.01\nB2,10,0,-40,2\n"
                                    "B3,10,10,-40,2\nB4,0,10,-40,2\n")
    rows = ["time,tag,anchor,rssi"]
    for t, b1 in ((0, -60), (1, -5), (2, -60)):
        rows += [f"{t},T,B1,{b1}", f"{t},T,B2,-60", f"{t},T,B3,-60", f"{t},T,B4,-60"]
    (tmp_path / "m.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "t.csv"
    assert main(["track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(out), "--kernel", kernel, "-q"]) == 0
    assert "internal error" not in capsys.readouterr().err
    t = pd.read_csv(out)
    assert len(t) == 3
    usable = t[t.status.isin(["ok", "fault_excluded", "low_redundancy"])]
    assert len(usable) == 3
    # every usable row has a finite bound, and B1 (a 10^-350 m range at t = 1) did not
    # pull the tag onto itself at (0, 0): the three others put it near (5, 5)
    assert np.all(np.isfinite(usable.hpl))
    r1 = t[t.time == 1].iloc[0]
    assert np.hypot(r1.x, r1.y) > 1.0 and r1.n_used <= 3


def test_an_invalid_epoch_after_a_restart_keeps_the_restart_count(tmp_path):
    """An epoch whose every value is outside the physical limits never reaches the
    filter; its row said ``reinit`` 0 after the tag had re-started (after a gap of
    1e5 s), where the rows around it said 1."""
    (tmp_path / "a.csv").write_text("anchor,x,y\nA1,0,0\nA2,10,0\nA3,10,10\nA4,0,10\n")
    good = [f"{{t}},T,{a},7.07" for a in ("A1", "A2", "A3", "A4")]
    lines = ["time,tag,anchor,range"]
    for t in (0, 1, 100_000, 100_001):
        lines += [g.format(t=t) for g in good]
    lines += ["1e13,T,A1,7.07"]  # beyond the time limit: invalid_measurement
    (tmp_path / "m.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "t.csv"
    assert main(["track", str(tmp_path / "m.csv"), "--anchors", str(tmp_path / "a.csv"),
                 "-o", str(out), "-q"]) == 0
    t = pd.read_csv(out)
    assert t.status.tolist()[-1] == "invalid_measurement"
    assert t.reinit.tolist() == [0, 0, 1, 1, 1]


def _jump_log(seed: int = 2) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """One range per 0.1 s, round-robin over four anchors of a 10 m square (as
    uwb-labyrinth ranges), sigma 0.1 m; the tag walks at 0.05 m/s and is carried 8.5 m
    away at t = 15 s (the reviewer's log)."""
    rng = np.random.default_rng(seed)
    a = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0.0, 10, 10, 0],
                      "y": [0.0, 0, 10, 10]})
    rows, truth = [], []
    for k in range(400):
        t = round(k * 0.1, 4)
        x, y = (2 + 0.05 * t, 2.0) if t < 15 else (8.0, 8.0)
        truth.append((t, "T", x, y))
        an = a.iloc[k % 4]
        rows.append((t, "T", an.anchor, float(np.hypot(x - an.x, y - an.y)
                                             + rng.normal(0, 0.1))))
    return (a, pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]),
            pd.DataFrame(truth, columns=["time", "tag", "x", "y"]))


@pytest.mark.parametrize("kernel", ["compiled", "numpy"])
def test_a_fault_detected_rows_bound_stands_until_the_filter_is_confirmed(kernel, monkeypatch):
    """After the jump, the ranges of A1 and A3 fail the innovation test and those of A2
    and A4 (whose distances the jump hardly changed) pass: the rows alternated
    ``fault_detected`` and ``ok``, the ``ok`` ones 7-8 m off with ``hpl`` 0.7-2 m, for
    2 s.  A detected fault's bound now stands for the rows after it until passing epochs
    have used three ranges: no usable row lies beyond its bound.  The positions are those
    of the filter without the rule (it changes bounds only): checked against the same
    log's rows under the rule switched off."""
    from robustloc.io.tables import to_epochs
    from robustloc.tracking import Tracker
    from robustloc.tracking import tracker as tracker_mod

    a, meas, truth = _jump_log()
    ep = to_epochs(meas, a["anchor"])
    rows = Tracker(a, sigma=0.1, engine=kernel).step(ep)
    m = rows.merge(truth, on=["time", "tag"], suffixes=("", "_t"))
    err = np.hypot(m.x - m.x_t, m.y - m.y_t)
    usable = m.status.isin(["ok", "fault_excluded", "low_redundancy", "fault_detected"])
    assert (m.status[(m.time >= 15) & (m.time < 16)] == "fault_detected").sum() >= 4
    assert not np.any(err[usable] > m.hpl[usable])
    # the rule changes bounds only: the same log without it
    monkeypatch.setattr(tracker_mod.Tracker, "_carry_suspicion", lambda self, *args: None)
    old = Tracker(a, sigma=0.1, engine=kernel).step(ep)
    pd.testing.assert_frame_equal(rows.drop(columns="hpl"), old.drop(columns="hpl"))
    both = rows.hpl.notna() & old.hpl.notna()
    assert (rows.hpl.isna() == old.hpl.isna()).all() and (rows.hpl[both] >= old.hpl[both]).all()
    assert (rows.hpl[both] > old.hpl[both]).sum() >= 10
    beyond_old = usable & (err > old.hpl) & (old.status == "ok")
    assert beyond_old.sum() >= 5  # (the defect, as the review measured it)


def test_a_standing_suspicion_is_saved_and_restored():
    """`serve --track` steps one epoch per call through state_dict: the rows equal one
    step over the whole log (the standing bound travels with the tag's state), and a
    state saved before the rule existed (no ``susp`` keys) still loads."""
    import json

    from robustloc.io.tables import to_epochs
    from robustloc.tracking import Tracker

    a, meas, _ = _jump_log()
    ep = to_epochs(meas, a["anchor"])
    whole = Tracker(a, sigma=0.1).step(ep)
    parts = []
    saved = None
    for i in range(ep.n_epochs):
        t = Tracker(a, sigma=0.1)
        if saved is not None:
            t.load_state_dict(saved)
        parts.append(t.step(type(ep)(ep.time[i:i + 1], ep.tag[i:i + 1], ep.values[i:i + 1],
                                     ep.anchor_ids, ep.value, ep.line[i:i + 1])))
        saved = json.loads(json.dumps(t.state_dict()))
    pd.testing.assert_frame_equal(whole, pd.concat(parts, ignore_index=True))
    old = json.loads(json.dumps(saved))
    for rec in old["tags"].values():
        del rec["susp"], rec["susp_n"]
    Tracker(a, sigma=0.1).load_state_dict(old)


def _corridor_log(seed: int = 4):
    """Four anchors within 0.3 m of a line (a corridor); tag T2 walks 1.5 m to one side
    of it, each range heard with probability 0.7, sigma 0.3 m, 5 % of them 0-5 m long
    (the reviewer's log): many epochs keep one or two ranges."""
    rng = np.random.default_rng(seed)
    a = pd.DataFrame({"anchor": ["A1", "A2", "A3", "A4"], "x": [0.0, 10, 20, 30],
                      "y": [0.0, 0.3, 0, 0.2]})
    rows, truth = [], []
    for k in range(300):
        t = k * 0.2
        x, y = 1 + 0.9 * t, -1.5 + 0.3 * np.sin(0.3 * t)
        truth.append((t, "T2", x, y))
        for an in a.itertuples():
            if rng.random() < 0.3:
                continue
            r = np.hypot(x - an.x, y - an.y) + rng.normal(0, 0.3)
            if rng.random() < 0.05:
                r += rng.uniform(0, 5)
            rows.append((t, "T2", an.anchor, r))
    return (a, pd.DataFrame(rows, columns=["time", "tag", "anchor", "range"]),
            pd.DataFrame(truth, columns=["time", "tag", "x", "y"]))


def test_rows_of_few_ranges_after_an_ambiguous_epoch_cover_the_mirror(monkeypatch):
    """The tracker follows the mirror side of the corridor for stretches.  Epochs of three
    or more ranges are checked and their ``hpl`` covers the mirror; rows of one or two
    ranges between them were not (`ok`, 2-3.4 m off with ``hpl`` 1.9-2.6 m: 11 % of
    the tag's rows misleading).  They now cover their reflection across the last
    ambiguous epoch's line: no row of one or two kept ranges lies beyond its bound, and
    the positions are those without the rule."""
    from robustloc.io.tables import to_epochs
    from robustloc.tracking import Tracker

    a, meas, truth = _corridor_log()
    ep = to_epochs(meas, a["anchor"])
    rows = Tracker(a, sigma=0.3).step(ep)
    m = rows.merge(truth, on=["time", "tag"], suffixes=("", "_t"))
    err = np.hypot(m.x - m.x_t, m.y - m.y_t)
    usable = m.status.isin(["ok", "fault_excluded", "low_redundancy", "fault_detected"])
    few = m.n_used <= 2
    assert ((m.y * m.y_t) < 0).sum() > 50  # (the track on the mirror side for stretches)
    assert not np.any((err > m.hpl)[usable & few])
    assert (err > m.hpl)[usable].mean() < 0.01  # (checked rows whose mirror failed too)
    monkeypatch.setattr(Tracker, "_carry_mirror", lambda self, *args: None)
    old = Tracker(a, sigma=0.3).step(ep)
    pd.testing.assert_frame_equal(rows.drop(columns="hpl"), old.drop(columns="hpl"))
    assert (err > old.hpl)[usable & few].sum() >= 20  # (the defect)


def test_the_real_corridor_track_stays_within_its_bounds():
    """The mirror rule on real data: the wifi-rtt-rss corridor (access points nearly on a
    line; the tag walks beside it), tracked with the defaults at sigma 0.3 m.  Before the
    rule 14.2 % of its usable rows exceeded their ``hpl`` (tracker on the mirror side
    between checked epochs); with it 0.01 % (measured 2026-12-06): within the issue's 1 %
    of misleading rows.  Skipped without ``../shared/data``."""
    from pathlib import Path

    from robustloc import status as st
    from robustloc.eval.realdata import _wifi
    from robustloc.io.tables import to_epochs
    from robustloc.paths import default_data_dir
    from robustloc.tracking import Tracker

    data = default_data_dir()
    if data is None or not (Path(data) / "wifi-rtt-rss").is_dir():
        pytest.skip("needs the full public data in ../shared/data")
    case = _wifi("corridor", Path(data))
    ep = to_epochs(case.measurements().sort_values(["time", "tag"], kind="stable"),
                   case.anchors["anchor"])
    rows = Tracker(case.anchors, sigma=0.3).step(ep)
    assert len(rows) == len(case.time)  # (one row per epoch)
    m = rows.merge(case.truth_frame(), on=["time", "tag"], suffixes=("", "_t"))
    err = np.hypot(m.x - m.x_t, m.y - m.y_t)
    use = st.among(m.status.to_numpy(object), st.USABLE) & (m.status != "predicted")
    assert use.sum() > 6000
    assert (err[use] > m.hpl[use]).mean() <= 0.01
