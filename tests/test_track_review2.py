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
