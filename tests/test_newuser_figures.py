"""The new-user walkthrough's findings on the figures and the report, measured.

Figures: what covers what is measured on the drawn figure (its renderer's window extents,
in pixels), not looked at: no legend over any axes, no count over another count, nothing
of a Stanford panel between its axes and its title, every method's Stanford diagram
drawn (or the ones left out named beside the diagrams).  Report: no Sphinx markup in the
report's text, and fault sizes of an RSSI layout in dB.

The reference for every check is geometry or text; the tolerance of an overlap is 1 px^2
(an anti-aliased edge shared by two boxes is not an overlap).
"""

from __future__ import annotations

import itertools
import re

import numpy as np
import pandas as pd
import pytest

from robustloc.cli import main
from robustloc.eval import plots

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")

#: Every method of ``locate`` (the walkthrough's ``--method`` list).
TEN = "ls,wls,nls,huber,hampel,igg,igg3,asym,lege,snooping"
#: Overlap below this area (px^2) is a shared anti-aliased edge, not an overlap.
TOUCH_PX2 = 1.0


def _area(a, b) -> float:  # noqa: ANN001 - matplotlib Bbox
    """Area of the intersection of two boxes (0 when apart)."""
    w = min(a.x1, b.x1) - max(a.x0, b.x0)
    h = min(a.y1, b.y1) - max(a.y0, b.y0)
    return max(w, 0.0) * max(h, 0.0)


def _drawn(fig):  # noqa: ANN001, ANN202 - a matplotlib Figure
    """Draw ``fig`` as it was laid out (on an Agg canvas: a closed figure has none) and
    return its renderer."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return canvas.get_renderer()


def _frames(fig, r):  # noqa: ANN001, ANN202
    """The data areas of the figure: each visible axes' box (colour bars included)."""
    return [(ax, ax.get_window_extent(r)) for ax in fig.axes if ax.axison]


def _legends_clear_of_every_axes(fig, r) -> None:  # noqa: ANN001
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    assert legends, "no legend drawn"
    for leg in legends:
        lb = leg.get_window_extent(r)
        for ax, box in _frames(fig, r):
            assert _area(lb, box) <= TOUCH_PX2, (
                f"legend {[t.get_text() for t in leg.get_texts()][:3]} covers the axes "
                f"{ax.get_title()!r}: {lb} over {box}")


def _texts_apart(texts, r) -> None:  # noqa: ANN001
    boxes = [(t.get_text(), t.get_window_extent(r)) for t in texts]
    for (ta, a), (tb, b) in itertools.combinations(boxes, 2):
        assert _area(a, b) <= TOUCH_PX2, f"{ta!r} and {tb!r} overlap: {a} {b}"


# --------------------------------------------------------------- locate --plot (finding 1)
@pytest.fixture(scope="module")
def corridor(tmp_path_factory):
    d = tmp_path_factory.mktemp("newuser")
    assert main(["simulate", "ble-corridor", "--seed", "1", "--out", str(d)]) == 0
    return d


def _located(corridor, tmp_path, methods: str) -> pd.DataFrame:  # noqa: ANN001
    out = tmp_path / f"pos-{methods.replace(',', '_')}.csv"
    assert main(["locate", str(corridor / "measurements.csv"), "--anchors",
                 str(corridor / "anchors.csv"), "--method", methods, "-o", str(out),
                 "--quiet"]) == 0
    return plots.read_positions_for_plot(out)


def _positions_fig(positions, anchors, tmp_path, monkeypatch):  # noqa: ANN001, ANN202
    from _figures import keep_written_figures  # (tests/_figures.py)

    figs = keep_written_figures(monkeypatch)
    counts = plots.positions_figure(positions, anchors, tmp_path / "p.png")
    return counts, figs[0]


@pytest.mark.parametrize("methods", [TEN, "auto", "auto,nls"])
def test_positions_figure_legends_cover_no_axes(corridor, tmp_path, monkeypatch, methods):
    """Ten methods: the map's legend covered anchors and fixes and the hpl legend the
    curves (one method: the map's legend sat on the site too).  Now no legend touches
    any axes, and each method is in the map's and the hpl panel's legends."""
    from robustloc.io import read_anchors

    pos = _located(corridor, tmp_path, methods)
    _, fig = _positions_fig(pos, read_anchors(corridor / "anchors.csv"), tmp_path,
                            monkeypatch)
    r = _drawn(fig)
    _legends_clear_of_every_axes(fig, r)
    for ax in (fig.axes[0], fig.axes[2]):
        keys = " ".join(t.get_text() for t in ax.get_legend().get_texts())
        assert all(m in keys for m in methods.split(",")), keys


def test_positions_figure_status_counts_apart(corridor, tmp_path, monkeypatch):
    """Ten methods: the counts of the status panel were written over each other ("150
    160", a stack of "1"s).  Now no two counts overlap, every count stays inside the
    panel, and every non-zero count of the summary is written once -- with ten methods
    (a table of counts) as with one and two (bars)."""
    from robustloc.io import read_anchors

    anchors = read_anchors(corridor / "anchors.csv")
    for methods in (TEN, "auto", "auto,nls"):
        pos = _located(corridor, tmp_path, methods)
        counts, fig = _positions_fig(pos, anchors, tmp_path, monkeypatch)
        r = _drawn(fig)
        ax_st = fig.axes[1]
        texts = [t for t in ax_st.texts if t.get_text()]
        _texts_apart(texts, r)
        box = ax_st.get_window_extent(r)
        for t in texts:
            tb = t.get_window_extent(r)
            assert box.x0 - 1 <= tb.x0 and tb.x1 <= box.x1 + 1, (t.get_text(), tb, box)
        written = sorted(int(t.get_text()) for t in texts)
        assert written == sorted(v for c in counts.values() for v in c.values() if v)


# ----------------------------------------------------------- evaluate --plot (finding 1)
def _evaluation_fig(errors, tmp_path, monkeypatch, **kw):  # noqa: ANN001, ANN202
    figs = []
    real = plots._render_figure

    def keep(fig, fmt):  # noqa: ANN001, ANN202
        figs.append(fig)
        return real(fig, fmt)

    monkeypatch.setattr(plots, "_render_figure", keep)
    counts = plots.evaluation_figure(errors, tmp_path / "e.png", **kw)
    return counts, figs[0]


def _stanford_axes(fig):  # noqa: ANN001, ANN202
    return [ax for ax in fig.axes if ax.get_title().startswith("Stanford diagram")]


def _ten_errors(corridor, tmp_path) -> pd.DataFrame:  # noqa: ANN001
    from robustloc.eval.metrics import epoch_errors
    from robustloc.io import read_truth

    pos = pd.read_csv(_write_ten(corridor, tmp_path))
    return epoch_errors(pos, read_truth(corridor / "truth.csv"))


def test_evaluation_figure_draws_every_method(corridor, tmp_path, monkeypatch):
    """Ten methods got six Stanford diagrams (and only the figure's title said so): now
    all ten are drawn, with the counts that evaluate's table has."""
    counts, fig = _evaluation_fig(_ten_errors(corridor, tmp_path), tmp_path, monkeypatch)
    # in the table's order: the baseline (ls) first, the others by name
    order = ["ls", *sorted(TEN.split(",")[1:])]
    assert list(counts) == order
    assert [ax.get_title() for ax in _stanford_axes(fig)] == [
        f"Stanford diagram: {m}" for m in order]


def test_evaluation_figure_legends_and_counts_cover_no_data(corridor, tmp_path, monkeypatch):
    """The CDF's and the map's legends and each diagram's box of counts sat on the data.
    Now no legend touches any axes and no text of a diagram is on its axes."""
    _, fig = _evaluation_fig(_ten_errors(corridor, tmp_path), tmp_path, monkeypatch)
    r = _drawn(fig)
    _legends_clear_of_every_axes(fig, r)
    for ax in _stanford_axes(fig):
        box = ax.get_window_extent(r)
        for t in ax.texts:
            assert _area(t.get_window_extent(r), box) <= TOUCH_PX2, t.get_text()


def _write_ten(corridor, tmp_path):  # noqa: ANN001, ANN202
    out = tmp_path / "ten.csv"
    assert main(["locate", str(corridor / "measurements.csv"), "--anchors",
                 str(corridor / "anchors.csv"), "--method", TEN, "-o", str(out),
                 "--quiet"]) == 0
    return out


def test_evaluation_figure_names_the_methods_left_out_beside_the_diagrams(corridor, tmp_path,
                                                                          monkeypatch):
    """Beyond the limit, the methods without a diagram are named in a panel of the grid
    (the figure's title alone said "the first 6 of 10"), and each diagram's title says
    which of how many it is."""
    from robustloc.eval.metrics import epoch_errors
    from robustloc.io import read_truth

    ten = pd.read_csv(_write_ten(corridor, tmp_path))
    many = pd.concat([ten, ten.assign(method=ten["method"] + "-2")], ignore_index=True)
    errors = epoch_errors(many, read_truth(corridor / "truth.csv"))
    n_max = plots.MAX_METHODS
    counts, fig = _evaluation_fig(errors, tmp_path, monkeypatch)
    assert len(counts) == n_max
    diagrams = _stanford_axes(fig)
    assert len(diagrams) == n_max
    order = ["ls", *sorted(set(many["method"]) - {"ls"})]  # (the table's)
    assert [ax.get_title() for ax in diagrams] == [
        f"Stanford diagram {k + 1} of 20: {m}" for k, m in enumerate(order[:n_max])]
    notes = [t.get_text() for ax in fig.axes for t in ax.texts
             if f"first {n_max} of 20" in t.get_text()]
    assert len(notes) == 1, [t.get_text() for ax in fig.axes for t in ax.texts]
    left_out = order[n_max:]
    assert all(m in notes[0] for m in left_out[:plots.MAX_LEGEND])


# ------------------------------------------------------- the report's Stanford (finding 2)
def test_report_stanford_panels_keep_their_titles_clear(tmp_path, monkeypatch):
    """``s05_stanford.png``: the ticks of unbounded fixes on the top edge crossed the title
    "uwb-dwm1001 LOS", and the legend of those ticks covered fixes.  Now nothing of a
    panel but its title is drawn above its axes, and its legend is off the axes."""
    import matplotlib.pyplot as plt

    from robustloc.reproduce import Context
    from robustloc.reproduce.s05_out_of_box import _stanford_figure

    rng = np.random.default_rng(5)
    panels = []
    for name in ("wifi-rtt office", "uwb-dwm1001 LOS", "uwb-dwm1001 NLOS"):
        err = rng.lognormal(-1.0, 1.0, 900)
        hpl = err * rng.uniform(2.0, 30.0, 900)
        hpl[::150] = np.inf  # unbounded fixes: ticks on the top edge
        hpl[7] = err[7] / 2  # one misleading fix
        panels.append((name, err, hpl))
    closed = []
    real_close = plt.close
    monkeypatch.setattr(plt, "close", lambda fig=None: (closed.append(fig), real_close(fig)))
    name = _stanford_figure(Context(out_dir=tmp_path, data_dir=None), panels)
    assert (tmp_path / name).is_file()
    fig = closed[0]
    r = _drawn(fig)
    titled = [ax for ax in fig.axes if ax.get_title()]
    assert [ax.get_title() for ax in titled] == [p[0] for p in panels]
    for ax in titled:
        box, title = ax.get_window_extent(r), ax.title.get_window_extent(r)
        for line in ax.lines:
            if len(line.get_xdata()) == 0:
                continue  # (a legend key, not drawn)
            lb = line.get_window_extent(r)  # (markers included)
            assert lb.y1 <= box.y1 + 1.0, (ax.get_title(), line, lb, box)
            assert _area(lb, title) <= TOUCH_PX2, (ax.get_title(), lb, title)
    _legends_clear_of_every_axes(fig, r)


# -------------------------------------------------------- report text and units (3 and 4)
_SPHINX = re.compile(r":[a-z]+:`|``")


def test_report_text_has_no_sphinx_markup(tmp_path, monkeypatch):
    """The s05 and s20 introductions are their modules' docstrings: the report showed
    ``:data:`robustloc....DEFAULT_METHOD```, ``:mod:`` and double backticks.  Now they are
    Markdown (roles as the last dotted name in backticks), and report.html shows them as
    code."""
    from robustloc.eval import realdata
    from robustloc.reproduce import Context, render, s05_out_of_box, s20_uwb_gps

    real = realdata.load_cases
    # (one small shipped data set: the introduction does not depend on the data)
    monkeypatch.setattr(realdata, "load_cases",
                        lambda d=None: [c for c in real(d) if c.name == "uwb-labyrinth"])
    ctx = Context(out_dir=tmp_path, data_dir=None, quick=True)
    sections = [s05_out_of_box.run(ctx), s20_uwb_gps.run(ctx)]
    texts = [p for s in sections for k, p in s.blocks if k == "text"]
    intro = texts[0]
    assert "`DEFAULT_METHOD`" in intro and "`least_squares`" in intro
    for t in texts:
        assert not _SPHINX.search(t), _SPHINX.search(t).group(0) + " in " + t[:300]
    md, html_path = render(sections, tmp_path, {})
    assert not _SPHINX.search(md.read_text())
    page = html_path.read_text()
    assert "<code>DEFAULT_METHOD</code>" in page and ":data:" not in page


def test_rssi_monte_carlo_faults_are_in_db(tmp_path):
    """The table "ble-corridor RSSI at S2, 12 dB blockages" labelled its faults
    "1 x 12 m"; RSSI faults are in dB."""
    from robustloc.reproduce import Context, s40_integrity

    sec = s40_integrity.run(Context(out_dir=tmp_path, data_dir=None, quick=True))
    rssi = {cap: t for k, (cap, t) in ((k, p) for k, p in sec.blocks if k == "table")
            if "ble-corridor RSSI" in cap}
    assert len(rssi) == 2, list(rssi)
    for cap, t in rssi.items():
        faults = set(t["faults"])
        assert faults == {"none", "1 x 12 dB"}, (cap, faults)
    ranges = [t for k, (cap, t) in ((k, p) for k, p in sec.blocks if k == "table")
              if "ble-corridor ranges" in cap]
    assert ranges and all(not any(f.endswith("dB") for f in t["faults"]) for t in ranges)
    text = " ".join(p for k, p in sec.blocks if k == "text")
    assert "a 12 dB blockage is detected in" in text
