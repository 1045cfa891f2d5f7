"""The matplotlib figures :mod:`robustloc.eval.plots` writes during a test, kept for the
test to measure (legends, labels, limits) after they are written as usual."""

from __future__ import annotations

from typing import Any


def keep_written_figures(monkeypatch: Any) -> list:
    """Collect every figure ``plots._write_figure`` writes from now on (the test's
    ``monkeypatch`` undoes it); returns the list they are appended to."""
    from robustloc.eval import plots

    figs: list = []
    real = plots._write_figure

    def keep(fig, path, fmt):  # noqa: ANN001, ANN202
        figs.append(fig)
        return real(fig, path, fmt)

    monkeypatch.setattr(plots, "_write_figure", keep)
    return figs
