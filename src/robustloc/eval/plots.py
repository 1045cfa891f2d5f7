"""Figures of an evaluation: the error distribution and the Stanford diagram of each method.

The **Stanford diagram** is the standard picture of a protection level's integrity (it
was drawn first for WAAS at Stanford; RTCA DO-229 uses it to state the requirement): each
usable fix is a point at (its horizontal error, its ``hpl``).  Points above the diagonal
``hpl = error`` are bounded; points below it are *misleading* (the error exceeds the bound,
the event the integrity risk limits).  How far above the diagonal the cloud sits says how
useful the bound is (issue 10's target: the median ``hpl`` at most 12x the median error).
The regions are counted as :func:`robustloc.eval.metrics.integrity_stats` counts them, so
the figure and ``robustloc evaluate``'s ``n_misleading`` agree: a missing (NaN) bound is
misleading, an infinite one ("unbounded": nothing confirms the fix) is bounded and drawn
on the top edge.

:func:`evaluation_figure` is ``robustloc evaluate --plot``; :func:`plot_stanford` draws one
panel and also serves the report (section ``s05_out_of_box``).
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
from numpy.typing import NDArray

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.legend import Legend

#: At most this many methods get a Stanford panel (the CDF panel shows every method; a
#: panel beside the diagrams names the others).  Every method of ``locate`` fits.
MAX_METHODS = 12
#: Length of the ticks of unbounded fixes on the Stanford diagram's top edge (points).
UNBOUNDED_TICK_PT = 8.0
#: At most this many methods are named in a legend; the others are drawn unnamed and the
#: legend says how many ("N more methods"): 300 methods' legend covered the figure and
#: made ``tight_layout`` warn.
MAX_LEGEND = 10
#: The log axes of errors and bounds span at most ``ERROR_VIEW_MIN`` .. ``ERROR_VIEW_MAX``
#: metres; values beyond are drawn on the edge and counted on the panel.  A fix 1e300 m
#: off overflowed matplotlib's log ticker (a traceback) and 1e200 leaked overflow
#: warnings; no real positioning error or bound comes near either end.
ERROR_VIEW_MIN = 1e-9
ERROR_VIEW_MAX = 1e9
#: The map shows coordinates within this many metres of the origin only: beyond, a fix
#: (or a truth point) is absurd for any local or projected frame, and matplotlib's axes
#: overflow near 1e300.
MAP_COORD_MAX = 1e9
#: The map shows the truth's extent widened on every side by the 95th percentile of the
#: usable fixes' errors, at most this many extents (or :data:`MAP_MIN_REACH`, if larger);
#: fixes beyond are left out and counted on the panel.
MAP_REACH_EXTENTS = 100.0
MAP_MIN_REACH = 1000.0


def _m(v: float) -> str:
    """Metres for a label: 2 decimals, or 3 significant digits from 1e6 m on (a p95 of
    1e300 m printed 300 digits)."""
    return f"{v:.2f}" if abs(v) < 1e6 else f"{v:.3g}"


def _n(k: int, what: str) -> str:
    """``1 error``, ``2 errors`` (``fix``: ``fixes``)."""
    return f"{k} {what}" if k == 1 else f"{k} {what}{'es' if what.endswith('x') else 's'}"


#: A method's name in a legend or a title is cut to this many characters ("..." ending it).
MAX_NAME = 30


def _short(name: str) -> str:
    """``name``, cut to :data:`MAX_NAME` characters (a 150-character method name pushed
    the panels out of the figure)."""
    return name if len(name) <= MAX_NAME else name[: MAX_NAME - 3] + "..."


def _legend_label(i: int, name: str) -> str:
    """The legend label of the ``i``-th method: ``name`` up to :data:`MAX_LEGEND`, then
    matplotlib's "not in the legend" (a leading underscore)."""
    return name if i < MAX_LEGEND else "_nolegend_"


#: Space between an axes' x label and a legend drawn below it (points).
LEGEND_GAP_PT = 6.0
#: Legend markers are drawn at least this large (points): the map's 2-point dots were
#: specks in the legend.
LEGEND_MIN_MARKER = 5.0


def _colour(i: int) -> str:
    """The colour of the ``i``-th method, the same in every panel of a figure (a panel
    that skips a method without data shifted the default colour cycle against the
    others)."""
    return f"C{i % 10}"


def _renderer(fig):  # noqa: ANN001, ANN202 - a matplotlib Figure, its renderer
    """A renderer to measure ``fig``'s text with: its canvas's (pyplot's Agg figures), or
    an Agg renderer of its size (a bare ``Figure()``'s canvas draws nothing)."""
    get = getattr(fig.canvas, "get_renderer", None)
    if get is not None:
        return get()
    from matplotlib.backends.backend_agg import RendererAgg

    return RendererAgg(int(fig.bbox.width), int(fig.bbox.height), fig.dpi)


def _legend_below(ax: Axes, fontsize: float = 7.0, ncol: int | None = None,
                  **kwargs: object) -> Legend | None:
    """The legend of ``ax`` under its x label, outside the axes: it never covers data
    (inside, "best" still hid anchors, fixes and curves once there were ten methods).

    Call it once the axes' limits, ticks and labels are set: the legend goes below their
    extent measured now, in points, which a later layout (``tight_layout``, which makes
    room for the legend) does not change.  ``ncol`` (default: 1 for up to 3 entries,
    else 2) is lowered while the legend is wider than 1.5 times the axes (long method
    names overran the figure).  Returns the legend (None without labelled artists).
    """
    from matplotlib.lines import Line2D
    from matplotlib.transforms import offset_copy

    handles, labels = ax.get_legend_handles_labels()
    if not handles:
        return None
    fig = ax.figure  # (matplotlib >= 3.7: no get_figure(root=True))
    renderer = _renderer(fig)
    box = ax.get_window_extent(renderer)
    under = ax.xaxis.get_tightbbox(renderer)
    drop_px = max(0.0, box.y0 - under.y0) if under is not None else 0.0
    drop_pt = drop_px * 72.0 / fig.dpi + LEGEND_GAP_PT
    anchor = offset_copy(ax.transAxes, fig=fig, y=-drop_pt, units="points")
    ncol = ncol or (1 if len(labels) <= 3 else 2)
    while True:  # fewer columns while the legend is much wider than the axes
        leg = ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0),
                        bbox_transform=anchor, ncol=ncol, fontsize=fontsize, frameon=False,
                        borderaxespad=0.0, columnspacing=1.2, handletextpad=0.4, **kwargs)
        if ncol == 1 or leg.get_window_extent(renderer).width <= 1.5 * box.width:
            break
        ncol -= 1
    for h in leg.legend_handles:
        if isinstance(h, Line2D) and h.get_marker() not in (None, "None", " ", ""):
            h.set_markersize(max(h.get_markersize(), LEGEND_MIN_MARKER))
            h.set_alpha(1.0)
    return leg


def _more_methods(ax: Axes, n_methods: int) -> None:
    """A legend entry "N more methods" (no symbol) when more than :data:`MAX_LEGEND`
    methods are drawn."""
    if n_methods > MAX_LEGEND:
        ax.plot([], [], " ", label=f"{n_methods - MAX_LEGEND} more methods")


@dataclass(frozen=True)
class StanfordCounts:
    """The regions of a Stanford diagram over ``n`` usable fixes (``hpl >= error``:
    bounded, of which ``unbounded`` have an infinite bound; ``error > hpl`` or a missing
    bound: ``misleading``)."""

    n: int
    bounded: int
    unbounded: int
    misleading: int

    @property
    def misleading_pct(self) -> float:
        """Misleading share of the usable fixes, % (NaN without fixes)."""
        return 100.0 * self.misleading / self.n if self.n else float("nan")


def stanford_counts(error_m: NDArray[np.float64], hpl_m: NDArray[np.float64]) -> StanfordCounts:
    """Count the regions of the Stanford diagram of fixes with horizontal errors
    ``error_m`` and bounds ``hpl_m`` (same length; NaN errors are left out, an infinite
    one -- beyond the floats -- counts as :func:`robustloc.eval.metrics.integrity_stats`
    counts it).

    >>> c = stanford_counts(np.array([1.0, 2.0, 3.0, 4.0]), np.array([5.0, 1.0, np.inf, np.nan]))
    >>> (c.n, c.bounded, c.unbounded, c.misleading)
    (4, 2, 1, 2)
    """
    e = np.asarray(error_m, dtype=float)
    h = np.asarray(hpl_m, dtype=float)
    if e.shape != h.shape:
        raise ValueError(f"error and hpl differ in shape: {e.shape} and {h.shape}")
    keep = ~np.isnan(e)
    e, h = e[keep], h[keep]
    with np.errstate(invalid="ignore"):
        ok = e <= h  # NaN bound: not ok (as integrity_stats)
    return StanfordCounts(n=int(e.size), bounded=int(ok.sum()),
                          unbounded=int(np.sum(ok & np.isinf(h))),
                          misleading=int(e.size - ok.sum()))


def _log_ticks(axis) -> None:  # noqa: ANN001 - a matplotlib Axis
    """Log-axis ticks at 1, 2, 5 per decade labelled as plain numbers (``0.5``, ``20``),
    readable when the data span less than a decade; at the decades alone when the axis
    (its limits when this is called) spans more than 2 (the labels overlapped, and
    matplotlib's locator gave no tick at all with 1, 2, 5 over 10 decades)."""
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    lo, hi = sorted(float(v) for v in axis.get_view_interval())
    wide = lo > 0 and np.isfinite(hi) and hi > lo * 150.0
    axis.set_major_locator(LogLocator(subs=(1.0,) if wide else (1.0, 2.0, 5.0)))
    axis.set_major_formatter(FormatStrFormatter("%g"))
    axis.set_minor_formatter(NullFormatter())


def plot_stanford(ax: Axes, error_m: NDArray[np.float64], hpl_m: NDArray[np.float64],
                  title: str = "", bins: int = 60) -> StanfordCounts:
    """Draw the Stanford diagram of ``error_m`` against ``hpl_m`` on ``ax`` and return its
    counts (:func:`stanford_counts`).

    Log-log axes spanning the data; a 2-D histogram with a logarithmic colour scale (many
    fixes stay readable); the diagonal ``hpl = error``; misleading fixes (below it) in red;
    unbounded fixes (``hpl = inf``) as ticks hanging from the top edge (inside the axes,
    clear of the title); fixes with no bound (NaN) are counted as misleading.  The counts
    (usable, misleading, unbounded, no bound, off the axes) and the median ``hpl`` over
    the median error are a legend under the axes (:func:`_legend_below`): nothing is
    written over the data.
    """
    from matplotlib.colors import LogNorm
    from matplotlib.ticker import FormatStrFormatter, LogLocator, NullFormatter

    counts = stanford_counts(error_m, hpl_m)
    e = np.asarray(error_m, dtype=float)
    h = np.asarray(hpl_m, dtype=float)
    fin = ~np.isnan(e) & np.isfinite(h)  # (an infinite error: on the edge, counted)
    pos = fin & (e > 0) & (h > 0)
    if pos.any():
        lo = 10.0 ** np.floor(np.log10(min(e[pos].min(), h[pos].min())))
        # (the decade above 1.4e308 overflowed: at most ERROR_VIEW_MAX's, as below)
        hi = 10.0 ** min(np.ceil(np.log10(max(e[pos].max(), h[pos].max()))),
                         np.log10(ERROR_VIEW_MAX))
    else:
        lo, hi = 0.01, 100.0
    # absurd values (1e300 m) on the edge of a sane range, counted below
    lo = min(max(lo, ERROR_VIEW_MIN), ERROR_VIEW_MAX / 100.0)
    hi = min(max(hi, lo * 100.0), ERROR_VIEW_MAX)
    n_edge = int(np.sum(pos & ((e < lo) | (e > hi) | (h < lo) | (h > hi))))
    edges = np.geomspace(lo, hi, bins + 1)
    if pos.any():
        ee, hh = np.clip(e[pos], lo, hi), np.clip(h[pos], lo, hi)
        H, _, _ = np.histogram2d(ee, hh, bins=(edges, edges))
        mesh = ax.pcolormesh(edges, edges, np.ma.masked_equal(H.T, 0), cmap="viridis",
                             norm=LogNorm(vmin=1, vmax=max(H.max(), 2)), shading="flat")
        cb = ax.figure.colorbar(mesh, ax=ax, label="fixes per cell", fraction=0.046,
                                pad=0.02)
        cb.ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        cb.ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
        cb.ax.yaxis.set_minor_formatter(NullFormatter())
        bad = e[pos] > h[pos]
        if bad.any():
            ax.plot(ee[bad], hh[bad], "r.", ms=4)
    unb = ~np.isnan(e) & np.isposinf(h) & (e > 0)
    if unb.any():
        # ticks hanging from the top edge, inside the axes: centred on the edge they rose
        # into the panel's title (the report's "uwb-dwm1001 LOS")
        from matplotlib.transforms import offset_copy

        down = offset_copy(ax.transData, fig=ax.figure, y=-UNBOUNDED_TICK_PT / 2.0,
                           units="points")
        ax.plot(np.clip(e[unb], lo, hi), np.full(int(unb.sum()), hi), "|", color="0.3",
                ms=UNBOUNDED_TICK_PT, clip_on=False, transform=down)
    ax.plot([lo, hi], [lo, hi], "k-", lw=1)
    ax.fill_between([lo, hi], [lo, lo], [lo, hi], color="red", alpha=0.07, lw=0)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_aspect("equal")
    ax.set_xlabel("horizontal error (m)")
    ax.set_ylabel("hpl (m)")
    nan_h = int(np.sum(~np.isnan(e) & np.isnan(h)))
    # the counts and the key, under the axes (a box or a legend on the axes covered
    # fixes: the bounded ones are top left, the misleading ones bottom right)
    ax.plot([], [], " ", label=f"{counts.n} usable fixes" if counts.n else "no usable fix")
    if counts.n:
        ax.plot([], [], "r.", label=f"misleading {counts.misleading} "
                f"({counts.misleading_pct:.2f} %)")
    if unb.any():
        ax.plot([], [], "|", color="0.3", ms=UNBOUNDED_TICK_PT,
                label=f"unbounded (hpl = inf): {int(unb.sum())}, ticks on the top edge")
    if nan_h:
        ax.plot([], [], " ", label=f"(no hpl: {nan_h}, counted misleading)")
    if n_edge:
        ax.plot([], [], " ", label=f"{n_edge} off the axes, drawn on the edge")
    if counts.n and fin.any():
        from robustloc.eval.metrics import _median  # (scaled: errors of 1e308 overflowed)

        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.float64(_median(np.where(np.isnan(h), np.inf, h)[~np.isnan(e)])) / (
                _median(e[~np.isnan(e)]))
        ax.plot([], [], " ", label=f"median hpl / median error {ratio:.1f}")
    if title:
        ax.set_title(title, fontsize=9)
    _legend_below(ax, fontsize=7)
    return counts


def _figure_format(path: str | os.PathLike[str]) -> str:
    """The format of a figure's file name (:func:`robustloc.options.figure_path`'s check;
    ``ValueError`` for another suffix), checked before anything is drawn."""
    from robustloc.options import figure_path

    try:
        figure_path(str(path))
    except argparse.ArgumentTypeError as exc:
        raise ValueError(str(exc)) from None
    return Path(path).suffix.lower().lstrip(".")


def _render_figure(fig, fmt: str) -> bytes:  # noqa: ANN001 - a matplotlib Figure
    """Lay out, render into memory and close: every drawing error comes before a file is
    written (``evaluate`` then writes its figure and its table together)."""
    import io
    import warnings

    import matplotlib.pyplot as plt

    try:
        with warnings.catch_warnings():
            # a layout that cannot be tightened keeps the default margins: the figure is
            # complete, and the warning is matplotlib's, not the user's to act on
            warnings.filterwarnings("ignore", message="Tight layout not applied",
                                    category=UserWarning)
            # twice: a square (equal-aspect) panel settles in its new slot only after the
            # first pass, and the legend under it moves with it (it was cut at the bottom)
            fig.tight_layout()
            fig.tight_layout()
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt, dpi=110)
    finally:
        plt.close(fig)
    return buf.getvalue()


def write_figure_bytes(data: bytes, path: str | os.PathLike[str]) -> None:
    """Write a rendered figure (:func:`render_evaluation_figure`) atomically
    (:func:`robustloc.io.atomic.atomic_output`)."""
    from robustloc.io.atomic import atomic_output

    with atomic_output(path) as (target, stream):
        if stream is not None:  # pragma: no cover - a figure's name is never "-"
            stream.write(data)
        else:
            with open(target, "wb") as f:
                f.write(data)


def _write_figure(fig, path: str | os.PathLike[str], fmt: str) -> None:  # noqa: ANN001
    """Lay out, render, close and write atomically."""
    write_figure_bytes(_render_figure(fig, fmt), path)


#: At most this many fixes per method are drawn on the map (an even subsample beyond).
MAP_POINTS = 20_000


def _map_view(xt: NDArray[np.float64], yt: NDArray[np.float64],
              errors: NDArray[np.float64]
              ) -> tuple[float, float, float, float, float] | None:
    """The box ``(x0, x1, y0, y1, reach)`` the map shows: the extent of the truth points
    within :data:`MAP_COORD_MAX`, widened on every side by ``reach``, the 95th percentile
    of the usable ``errors`` (at least the extent, at most :data:`MAP_REACH_EXTENTS`
    extents or :data:`MAP_MIN_REACH`); None without such a truth point."""
    t = (np.isfinite(xt) & np.isfinite(yt) & (np.abs(xt) <= MAP_COORD_MAX)
         & (np.abs(yt) <= MAP_COORD_MAX))
    if not t.any():
        return None
    x0, x1 = float(xt[t].min()), float(xt[t].max())
    y0, y1 = float(yt[t].min()), float(yt[t].max())
    extent = max(x1 - x0, y1 - y0, 1.0)
    e = errors[np.isfinite(errors)]
    p95 = float(np.percentile(e, 95)) if e.size else 0.0
    reach = max(extent, min(p95, max(MAP_REACH_EXTENTS * extent, MAP_MIN_REACH)))
    return x0 - reach, x1 + reach, y0 - reach, y1 + reach, reach


def _plot_map(ax: Axes, errors: pd.DataFrame, methods: list[str], meth: NDArray[np.object_],
              usable: NDArray[np.bool_]) -> None:
    """The usable fixes of each method over the truth (black), equal axes; fixes outside
    :func:`_map_view` (absurd ones: 1e300 m) are left out and counted on the panel."""
    xt = errors["x_true"].to_numpy(dtype=float)
    yt = errors["y_true"].to_numpy(dtype=float)
    x = errors["x"].to_numpy(dtype=float)
    y = errors["y"].to_numpy(dtype=float)
    view = _map_view(xt, yt, errors["error_2d"].to_numpy(dtype=float)[usable])
    with np.errstate(invalid="ignore"):
        if view is None:
            inside = (np.abs(x) <= MAP_COORD_MAX) & (np.abs(y) <= MAP_COORD_MAX)
        else:
            inside = (x >= view[0]) & (x <= view[1]) & (y >= view[2]) & (y <= view[3])
    n_out = int(np.sum(usable & ~inside))
    for i, m in enumerate(methods):
        sel = np.flatnonzero(usable & inside & (meth == m))
        if sel.size > MAP_POINTS:
            sel = sel[np.linspace(0, sel.size - 1, MAP_POINTS).astype(np.int64)]
        ax.plot(x[sel], y[sel], ".", ms=2, alpha=0.5, color=_colour(i),
                label=_legend_label(i, _short(m)))
    _more_methods(ax, len(methods))
    t = (np.isfinite(xt) & np.isfinite(yt) & (np.abs(xt) <= MAP_COORD_MAX)
         & (np.abs(yt) <= MAP_COORD_MAX))
    if t.any():
        pts = np.unique(np.column_stack((xt[t], yt[t])), axis=0)
        if len(pts) > MAP_POINTS:
            pts = pts[np.linspace(0, len(pts) - 1, MAP_POINTS).astype(np.int64)]
        ax.plot(pts[:, 0], pts[:, 1], "k.", ms=2, label="truth")
    n_t_out = len(np.unique(np.column_stack((xt, yt))[np.isfinite(xt) & np.isfinite(yt) & ~t],
                            axis=0))
    # what is left out, under the title (a box on the axes would hide fixes)
    notes = ["usable fixes and the truth"]
    if n_out:
        notes.append(f"{_n(n_out, 'usable fix')} not drawn: more than "
                     + (f"{MAP_COORD_MAX:g} m from the origin" if view is None else
                        f"{_m(view[4])} m beyond the truth"))
    if n_t_out:
        notes.append(f"{_n(n_t_out, 'truth point')} not drawn: beyond {MAP_COORD_MAX:g} m")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title("\n".join(notes), fontsize=9 if len(notes) == 1 else 8)
    ax.grid(alpha=0.3)
    _legend_below(ax, ncol=3)


def _plot_cdf(ax: Axes, e_all: NDArray[np.float64], methods: list[str],
              meth: NDArray[np.object_], usable: NDArray[np.bool_]) -> None:
    """The empirical CDF of the usable fixes' horizontal errors per method, on a log axis
    from the decade below the smallest positive error to the decade above the largest
    (within :data:`ERROR_VIEW_MIN` .. :data:`ERROR_VIEW_MAX`); errors below (exact fixes,
    error 0) or beyond are drawn on the edge and counted on the panel."""
    from robustloc.eval.metrics import _p95

    e_use = e_all[usable]
    e_pos = e_use[e_use > 0]
    if e_pos.size:
        lo = 10.0 ** np.floor(np.log10(e_pos.min()))
        # (the decade above 1.4e308 overflowed: at most ERROR_VIEW_MAX's, as below)
        hi = 10.0 ** min(np.ceil(np.log10(e_pos.max())), np.log10(ERROR_VIEW_MAX))
    else:  # no positive error (every fix exact, or none usable): a floor of 1 cm
        lo = hi = 0.01
    lo = min(max(lo, ERROR_VIEW_MIN), ERROR_VIEW_MAX / 100.0)
    hi = min(max(hi, lo * 100.0), ERROR_VIEW_MAX)
    for i, m in enumerate(methods):
        e = np.sort(e_all[usable & (meth == m)])
        if e.size == 0:
            continue
        q = np.arange(1, e.size + 1) / e.size
        p95 = _p95(e)  # (an infinite error made numpy's NaN, and a warning)
        label = _legend_label(i, f"{_short(m)} (n={e.size}, p95 {_m(p95)} m)")
        ax.step(np.clip(e, lo, hi), q, where="post", lw=1.2, color=_colour(i), label=label)
        ax.plot([min(max(p95, lo), hi)], [0.95], "o", color=_colour(i), ms=4)
    _more_methods(ax, len(methods))
    ax.axhline(0.95, color="0.6", lw=0.6)
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    _log_ticks(ax.xaxis)
    # what is drawn on the edge, under the title (a box on the axes would hide a curve)
    notes = ["error distribution (usable fixes)"]
    n_lo, n_hi = int(np.sum(e_use < lo)), int(np.sum(e_use > hi))
    if n_lo:
        notes.append(f"{_n(n_lo, 'error')} below {lo:g} m (exact fixes) drawn at {lo:g} m")
    if n_hi:
        notes.append(f"{_n(n_hi, 'error')} beyond {hi:g} m drawn at {hi:g} m")
    ax.set_xlabel("horizontal error (m)")
    ax.set_ylabel("share of usable fixes")
    ax.set_title("\n".join(notes), fontsize=9 if len(notes) == 1 else 8)
    ax.grid(alpha=0.3, which="both")
    _legend_below(ax)


def _left_out_note(ax: Axes, n_shown: int, left_out: list[str]) -> None:
    """The panel after the last Stanford diagram: which methods have none (it was the
    figure's title alone, easy to miss above the first row)."""
    n_all = n_shown + len(left_out)
    names = [_short(m) for m in left_out[:MAX_LEGEND]]
    if len(left_out) > MAX_LEGEND:
        names.append(f"and {len(left_out) - MAX_LEGEND} more")
    ax.axis("off")
    ax.text(0.0, 1.0, f"Stanford diagrams of the first {n_shown} of {n_all} methods;\n"
            "no diagram for:\n  " + "\n  ".join(names)
            + "\n\n(the table's n_misleading counts their misleading fixes)",
            transform=ax.transAxes, ha="left", va="top", fontsize=9, wrap=True)


def render_evaluation_figure(
    errors: pd.DataFrame, path: str | os.PathLike[str], max_methods: int = MAX_METHODS,
    baseline: str = "ls",
) -> tuple[bytes, dict[str, StanfordCounts]]:
    """The figure of :func:`evaluation_figure`, rendered into memory and not written.

    ``robustloc evaluate`` draws it before writing its table, then writes both: a figure
    that cannot be drawn leaves no table behind.

    Parameters
    ----------
    errors : DataFrame
        As :func:`evaluation_figure`.
    path : str or PathLike
        Its suffix gives the format (``.png``, ``.svg`` or ``.pdf``; another:
        ``ValueError``); nothing is written.
    max_methods : int
        As :func:`evaluation_figure`.
    baseline : str
        As :func:`evaluation_figure`.

    Returns
    -------
    tuple
        The file's bytes, and per method with a panel its :class:`StanfordCounts`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fmt = _figure_format(path)
    from robustloc.eval.metrics import method_order

    # the table's order (it was the file's: the same rows in another order, another figure)
    methods = (method_order(errors["method"], baseline) if "method" in errors.columns
               else ["positions"])
    meth = (errors["method"].astype(str).to_numpy() if "method" in errors.columns
            else np.full(len(errors), "positions", dtype=object))
    usable = errors["usable"].to_numpy(dtype=bool)
    e_all = errors["error_2d"].to_numpy(dtype=float)
    has_hpl = "hpl" in errors.columns
    shown = methods[:max_methods] if has_hpl else []
    left_out = methods[len(shown):] if has_hpl else []
    first = 2  # the CDF and the map come first
    n_panels = first + len(shown) + (1 if left_out else 0)  # (the note on those left out)
    ncol = min(3 if n_panels <= 9 else 4, n_panels)
    nrow = int(np.ceil(n_panels / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.6 * ncol, 5.0 * nrow), squeeze=False)
    try:
        _plot_cdf(axes[0, 0], e_all, methods, meth, usable)
        _plot_map(axes.flat[1], errors, methods, meth, usable)
        out: dict[str, StanfordCounts] = {}
        hpl = errors["hpl"].to_numpy(dtype=float) if has_hpl else None
        for k, m in enumerate(shown):
            ax = axes.flat[first + k]
            sel = usable & (meth == m)
            # numbered when some are left out: "3 of 14" says so on every diagram
            title = f"Stanford diagram: {_short(m)}"
            if left_out:
                title = f"Stanford diagram {k + 1} of {len(methods)}:" + (
                    " " if len(m) <= 12 else "\n") + _short(m)
            out[m] = plot_stanford(ax, e_all[sel], hpl[sel], title=title)
        for ax in axes.flat[first + len(shown):]:
            ax.axis("off")
        if left_out:
            _left_out_note(axes.flat[first + len(shown)], len(shown), left_out)
    except BaseException:
        plt.close(fig)
        raise
    return _render_figure(fig, fmt), out


def evaluation_figure(errors: pd.DataFrame, path: str | os.PathLike[str],
                      max_methods: int = MAX_METHODS, baseline: str = "ls",
                      ) -> dict[str, StanfordCounts]:
    """``robustloc evaluate --plot``: the figure of an evaluation, written atomically.

    Parameters
    ----------
    errors : the per-row errors of :func:`robustloc.eval.metrics.epoch_errors` (columns
        ``error_2d``, ``usable``, ``method`` and, when the positions have it, ``hpl``).
    path : ``.png``, ``.svg`` or ``.pdf`` (:data:`robustloc.options.FIGURE_FORMATS`; another
        suffix: ``ValueError``).
    max_methods : at most this many methods get a Stanford panel (in the order of the
        table's rows, :func:`robustloc.eval.metrics.method_order`: ``baseline`` first,
        the others by name; :data:`MAX_METHODS` by default); the CDF panel shows every
        method, and a panel after the last diagram names the methods left without one
        (each diagram's title then numbers it: "Stanford diagram 3 of 14: nls").
    baseline : the method drawn first, when the errors have it (``evaluate --baseline``).

    Returns
    -------
    dict
        Per method with a panel, its :class:`StanfordCounts` (empty without ``hpl``).

    Panels: the empirical CDF of the horizontal error of the usable fixes per method (its
    95th percentile marked), a map of the usable fixes over the truth (at most
    :data:`MAP_POINTS` per method), then, when the positions carry ``hpl``, one Stanford
    diagram per method (:func:`plot_stanford`), four panels a row from ten panels on.
    The legends are under their panels, never over the data; they name the first
    :data:`MAX_LEGEND` methods and say how many more there are, and a method has the same
    colour in every panel.  Absurd values stay
    within sane axes, counted on their panel: errors and bounds outside
    :data:`ERROR_VIEW_MIN` .. :data:`ERROR_VIEW_MAX` m (errors of 0 among them) on the
    edge of the log axes, fixes far beyond the truth (:func:`_map_view`) off the map.
    """
    data, out = render_evaluation_figure(errors, path, max_methods, baseline)
    write_figure_bytes(data, path)
    return out


#: Usable statuses the map marks (a fix the user should look at before trusting it).
_FLAGGED = ("fault_detected", "extrapolated", "unverified")
#: At most this many tags get their own colour on the map (the rest share one).
MAX_TAG_COLOURS = 10


def read_positions_for_plot(path: str | os.PathLike[str]) -> pd.DataFrame:
    """The columns :func:`positions_figure` draws (``time, tag, x, y, method, status,
    hpl`` where present) of a positions or track file that a command has just written
    (``.csv``, ``.csv.gz`` or ``.parquet``)."""
    wanted = ("time", "tag", "x", "y", "method", "status", "hpl")
    p = Path(path)
    if p.suffix.lower() in (".parquet", ".pq"):
        import pyarrow.parquet as pq

        have = set(pq.read_schema(p).names)
        return pd.read_parquet(p, columns=[c for c in wanted if c in have])
    return pd.read_csv(p, usecols=lambda c: c in wanted, dtype={"tag": str})


def _near_anchors(x: NDArray[np.float64], y: NDArray[np.float64], usable: NDArray[np.bool_],
                  anchors: pd.DataFrame
                  ) -> tuple[NDArray[np.bool_], int, float | None]:
    """The fixes the positions map draws: within :func:`_map_view` of the anchors (their
    box widened by the 95th percentile of the usable fixes' distances from it, bounded);
    returns the mask, the usable fixes left out and the reach (None: no anchor within
    :data:`MAP_COORD_MAX`, the view is then :data:`MAP_COORD_MAX` from the origin)."""
    ax_ = anchors["x"].to_numpy(dtype=float)
    ay_ = anchors["y"].to_numpy(dtype=float)
    a = np.isfinite(ax_) & np.isfinite(ay_) & (np.abs(ax_) <= MAP_COORD_MAX) \
        & (np.abs(ay_) <= MAP_COORD_MAX)
    with np.errstate(invalid="ignore", over="ignore"):
        if a.any():
            dx = np.maximum(np.maximum(ax_[a].min() - x, x - ax_[a].max()), 0.0)
            dy = np.maximum(np.maximum(ay_[a].min() - y, y - ay_[a].max()), 0.0)
            dist = np.hypot(dx, dy)
        else:
            dist = np.full(x.shape, np.nan)
        view = _map_view(ax_, ay_, dist[usable])
        if view is None:
            inside = (np.abs(x) <= MAP_COORD_MAX) & (np.abs(y) <= MAP_COORD_MAX)
        else:
            inside = (x >= view[0]) & (x <= view[1]) & (y >= view[2]) & (y <= view[3])
    return inside, int(np.sum(usable & ~inside)), None if view is None else view[4]


#: The status panel draws one bar per method and status up to this many bars, each with
#: its count at its end; beyond, the bars were thinner than their counts' text (ten
#: methods: the counts overlapped), and the panel is a table of counts instead
#: (:func:`_status_matrix`).
MAX_STATUS_BARS = 16


def _status_bars(ax: Axes, counts: dict[str, dict[str, int]], methods: list[str],
                 names: list[str]) -> None:
    """One bar per method and status, grouped by status, with its count at its end."""
    ypos = np.arange(len(names))
    h = 0.8 / max(len(methods), 1)
    top = max((v for c in counts.values() for v in c.values()), default=0)
    for i, m in enumerate(methods):
        v = [counts[m].get(s, 0) for s in names]
        bars = ax.barh(ypos + i * h, v, height=h, color=_colour(i),
                       label=_legend_label(i, _short(m)))
        # (a status of 1 row in 10 000 is a bar too thin to see: the count says it)
        ax.bar_label(bars, labels=[str(c) if c else "" for c in v], fontsize=7, padding=2)
    ax.set_yticks(ypos + 0.4 - h / 2, names, fontsize=7)
    ax.invert_yaxis()  # the first status on top
    # room for the longest bar's count inside the axes (it ran over the right edge)
    ax.set_xlim(0, max(top, 1) * 1.22)
    ax.set_xlabel("rows")
    ax.set_title("status of every row", fontsize=9)
    ax.grid(alpha=0.3, axis="x")
    if len(methods) > 1:
        _legend_below(ax)


def _status_matrix(ax: Axes, counts: dict[str, dict[str, int]], methods: list[str],
                   names: list[str]) -> None:
    """The rows per status (row) and method (column) as a table of counts, shaded by the
    count (log scale, blank where 0); the counts' font fits the cells (none when the
    cells are too small for any: the summary has them)."""
    from matplotlib.colors import LogNorm

    n_s, n_m = len(names), len(methods)
    table = np.array([[counts[m].get(s, 0) for m in methods] for s in names], dtype=float)
    # the cells' size in points once laid out (about 70 % of the axes' size now)
    box = ax.get_window_extent(_renderer(ax.figure))
    cell_w = 0.7 * box.width * 72.0 / ax.figure.dpi / n_m
    cell_h = 0.7 * box.height * 72.0 / ax.figure.dpi / n_s
    norm = LogNorm(vmin=1, vmax=max(float(table.max()), 2.0))
    ax.pcolormesh(np.ma.masked_equal(table, 0), cmap="Blues", norm=norm,
                  edgecolors="white", linewidth=0.5 if cell_w >= 4.0 else 0.0)
    ax.set_xlim(0, n_m)
    ax.set_ylim(n_s, 0)
    ax.set_yticks(np.arange(n_s) + 0.5, names, fontsize=7)
    # method names 40 degrees up: one every 11 points at most (7-point text)
    step = int(np.ceil(n_m / max(1.0, cell_w * n_m / 11.0)))
    ax.set_xticks(np.arange(0, n_m, step) + 0.5, [_short(m) for m in methods[::step]],
                  rotation=40, ha="right", rotation_mode="anchor", fontsize=7)
    ax.tick_params(length=0)
    for side in ax.spines.values():
        side.set_visible(False)
    digits = len(str(int(table.max()))) if table.size else 1
    size = min(8.0, 0.85 * cell_w / (0.62 * digits), 0.6 * cell_h)
    note = ""
    if size >= 4.0:
        for r in range(n_s):
            for c in range(n_m):
                if table[r, c]:
                    dark = norm(table[r, c]) > 0.6
                    ax.text(c + 0.5, r + 0.5, f"{int(table[r, c])}", ha="center",
                            va="center", fontsize=size, color="white" if dark else "black")
    else:
        note = "\n(too many methods to write the counts: see the summary)"
    ax.set_title("status of every row (rows per method)" + note, fontsize=9)


def positions_figure(positions: pd.DataFrame, anchors: pd.DataFrame,
                     path: str | os.PathLike[str], title: str = "") -> dict[str, dict[str, int]]:
    """``robustloc locate|track --plot``: what an output holds, for a person to look at,
    written atomically (no truth needed).

    Panels: a map of the anchors and the usable fixes (coloured by tag when there are at
    most :data:`MAX_TAG_COLOURS` tags; a track's rows joined per tag; fixes whose status
    says to look twice -- ``fault_detected``, ``extrapolated``, ``unverified`` -- crossed
    in red; at most :data:`MAP_POINTS` fixes per method, an even subsample beyond; fixes
    far beyond the anchors -- :func:`_near_anchors` -- counted under the title instead),
    the count of each status per method (bars with their counts, :func:`_status_bars`;
    with more than :data:`MAX_STATUS_BARS` bars a table of counts,
    :func:`_status_matrix`), and the distribution of the usable fixes' ``hpl`` per
    method (what an ``--alert-limit`` would keep).  Legends are under their panels
    (:func:`_legend_below`) and a method has the same colour in every panel.

    Returns
    -------
    dict
        Per method, its rows per status (as the summary counts them).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from robustloc import status as st
    fmt = _figure_format(path)
    n = len(positions)
    meth = (positions["method"].astype(str).to_numpy() if "method" in positions.columns
            else np.full(n, "positions", dtype=object))
    status = (positions["status"].astype(str).to_numpy() if "status" in positions.columns
              else np.full(n, st.OK, dtype=object))
    methods = list(dict.fromkeys(meth))
    x = positions["x"].to_numpy(dtype=float)
    y = positions["y"].to_numpy(dtype=float)
    usable = st.among(status, st.USABLE) & np.isfinite(x) & np.isfinite(y)
    tags = positions["tag"].astype(str).to_numpy() if "tag" in positions.columns else None
    counts = {m: {str(k): int(v) for k, v in
                  pd.Series(status[meth == m]).value_counts(sort=False).items()}
              for m in methods}

    fig, axes = plt.subplots(1, 3, figsize=(15.5, 5.8), squeeze=False,
                             gridspec_kw={"width_ratios": [1.35, 1.0, 1.0]})
    ax_map, ax_st, ax_h = axes[0]
    # --- map
    ax_map.plot(anchors["x"].to_numpy(float), anchors["y"].to_numpy(float), "r^", ms=7,
                label="anchors", zorder=5)
    for (_, a) in anchors.iterrows():
        ax_map.annotate(str(a["anchor"]), (float(a["x"]), float(a["y"])), fontsize=6,
                        xytext=(3, 3), textcoords="offset points")
    inside, n_out, reach = _near_anchors(x, y, usable, anchors)
    by_tag = tags is not None and len(methods) == 1 and len(set(tags)) <= MAX_TAG_COLOURS
    flagged = []
    for i, m in enumerate(methods):
        sel = np.flatnonzero(usable & inside & (meth == m))
        if sel.size > MAP_POINTS:
            sel = sel[np.linspace(0, sel.size - 1, MAP_POINTS).astype(np.int64)]
        track = m.startswith("track")
        if by_tag and tags is not None:
            for tg in dict.fromkeys(tags[sel]):
                s = sel[tags[sel] == tg]
                ax_map.plot(x[s], y[s], "-" if track else ".", lw=0.8, ms=2, alpha=0.7,
                            label=f"tag {tg}")
        else:
            ax_map.plot(x[sel], y[sel], ".", ms=2, alpha=0.5, color=_colour(i),
                        label=_legend_label(i, _short(m)))
        flagged.append(sel[np.isin(status[sel], _FLAGGED)])
    if not by_tag:
        _more_methods(ax_map, len(methods))
    flag = np.concatenate(flagged) if flagged else np.zeros(0, dtype=np.int64)
    if flag.size:  # (one key for every method: the status panel counts them per method)
        who = f"{_short(methods[0])}: " if len(methods) == 1 else ""
        ax_map.plot(x[flag], y[flag], "x", color="red", ms=4, alpha=0.8,
                    label=f"{who}{flag.size} to look at ({', '.join(_FLAGGED)})")
    ax_map.set_aspect("equal", adjustable="datalim")
    ax_map.set_xlabel("x (m)")
    ax_map.set_ylabel("y (m)")
    ax_map.grid(alpha=0.3)
    heading = title or "anchors and usable fixes"
    if n_out:  # (one fix at 1e300 m shrank the site to a dot: the review)
        heading += (f"\n{_n(n_out, 'usable fix')} not drawn: more than "
                    + (f"{MAP_COORD_MAX:g} m from the origin" if reach is None
                       else f"{_m(reach)} m beyond the anchors"))
    ax_map.set_title(heading, fontsize=9 if not n_out else 8)
    _legend_below(ax_map, ncol=3)
    # --- statuses
    names = [s for s in st.ALL if any(s in c for c in counts.values())]
    names += sorted({k for c in counts.values() for k in c} - set(names))
    if len(names) * len(methods) <= MAX_STATUS_BARS:
        _status_bars(ax_st, counts, methods, names)
    else:
        _status_matrix(ax_st, counts, methods, names)
    # --- hpl
    if "hpl" in positions.columns:
        hpl = positions["hpl"].to_numpy(dtype=float)
        for i, m in enumerate(methods):
            hm = hpl[usable & (meth == m)]
            fin = np.sort(hm[np.isfinite(hm) & (hm > 0)])
            if fin.size == 0:
                continue
            q = np.arange(1, fin.size + 1) / hm.size  # unbounded fixes never reach 1
            n_inf = int(np.sum(np.isposinf(hm)))
            ax_h.step(fin, q, where="post", lw=1.2, color=_colour(i), label=_legend_label(
                i, f"{_short(m)}: median {np.median(hm):.3g} m, {n_inf} unbounded"))
        _more_methods(ax_h, len(methods))
        ax_h.set_xscale("log")
        _log_ticks(ax_h.xaxis)
        ax_h.set_xlabel("hpl (m)")
        ax_h.set_ylabel("share of usable fixes with hpl at most x")
        ax_h.set_title("protection levels (an --alert-limit keeps the left of it)",
                       fontsize=9)
        ax_h.grid(alpha=0.3, which="both")
        _legend_below(ax_h)
    else:
        ax_h.axis("off")
    _write_figure(fig, path, fmt)
    return counts
