"""``locate|track --plot``: one absurd fix shrank the site to a dot, and a status of a few
rows was a bar too thin to see."""

from __future__ import annotations

import numpy as np
import pandas as pd

from robustloc.eval import plots


def _draw(positions: pd.DataFrame, anchors: pd.DataFrame, tmp_path, monkeypatch):
    from _figures import keep_written_figures  # (tests/_figures.py)

    figs = keep_written_figures(monkeypatch)
    counts = plots.positions_figure(positions, anchors, tmp_path / "p.svg")
    return counts, figs[0], (tmp_path / "p.svg").read_text()


def test_absurd_fixes_are_counted_not_drawn_and_small_counts_are_written(tmp_path,
                                                                          monkeypatch):
    rng = np.random.default_rng(7)
    anchors = pd.DataFrame({"anchor": ["a", "b", "c"], "x": [0.0, 10.0, 0.0],
                            "y": [0.0, 0.0, 10.0]})
    n = 200
    pos = pd.DataFrame({"time": np.arange(n), "tag": "t", "x": rng.uniform(0, 10, n),
                        "y": rng.uniform(0, 10, n), "method": "huber", "status": "ok",
                        "hpl": rng.uniform(0.5, 5, n)})
    pos.loc[3, ["x", "y"]] = [1e300, 1e300]
    pos.loc[4, ["x", "y"]] = [1e7, -1e7]
    pos.loc[5, ["status", "x", "y"]] = ["fault_detected", 15.0, 3.0]  # near: drawn
    counts, fig, svg = _draw(pos, anchors, tmp_path, monkeypatch)
    assert counts == {"huber": {"ok": 199, "fault_detected": 1}}
    ax_map, ax_st = fig.axes[0], fig.axes[1]
    # the site fills the map: the anchors' 10 m box, widened by at most the 95th
    # percentile of the fixes' distances from it (5 m here) -- not 1e300 m
    assert max(abs(v) for v in (*ax_map.get_xlim(), *ax_map.get_ylim())) < 100.0
    assert "2 usable fixes not drawn" in ax_map.get_title()
    assert "2 usable fixes not drawn" in svg
    labels = [t.get_text() for t in ax_st.texts]
    assert "199" in labels and "1" in labels
