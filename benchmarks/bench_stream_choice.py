"""The live service's choice of the links' offsets (``serve --track --track-link-offsets
auto``, :class:`robustloc.tracking.AutoTracker`) on the shared real logs.

Each log (time order, the tracker's defaults, as ``bench_link_choice.py`` loads it) is
streamed in blocks of 50 epochs with a trial of half its epochs (``--fraction``); printed:
the stream's choice and t, ``track``'s choice on the same first epochs
(``choose_link_offsets``), and the RMS of the stream's rows against the tracker without
and with the offsets over the whole log.

Measured 2026-12-07 (``python benchmarks/bench_stream_choice.py --data ../shared/data``),
half of each log: the stream chose as ``track`` on all four (ble-tetam on, t 7.46; dwm1001
LOS off, -2.67; NLOS off, 0.13; uwb-labyrinth off, 3.18); ble-tetam's stream RMS 2.44 m
against 2.68 off and 2.31 on (the first half's rows are without the offsets).  At the
default trial of 20 000 epochs none of these logs (233-9 447 epochs) ends its trial: a
service run on them would keep the offsets off throughout.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_link_choice import _real  # noqa: E402

from robustloc.paths import default_data_dir  # noqa: E402
from robustloc.tracking import AutoTracker, Tracker  # noqa: E402
from robustloc.tracking.select import choose_link_offsets  # noqa: E402

BLOCK = 50


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=None,
                    help="real-data folder (default ../shared/data; else the excerpts)")
    ap.add_argument("--fraction", type=float, default=0.5,
                    help="the trial's share of each log's epochs (default 0.5)")
    a = ap.parse_args(argv)
    if not 0 < a.fraction <= 1:
        ap.error("--fraction must be in (0, 1]")
    data = a.data if a.data is not None else default_data_dir()
    for name, an, ep, err, extra in _real(data):
        order = np.lexsort((ep.tag.astype(str), ep.time))  # as track sorts a log
        back = np.argsort(order)  # (the error functions take rows in the log's order)
        ep = ep.take(order)
        n = max(1, int(a.fraction * ep.n_epochs))
        trk = AutoTracker(an, sample_epochs=n, **extra)
        rows = pd.concat([trk.step(ep.take(slice(i, min(i + BLOCK, ep.n_epochs))))
                          for i in range(0, ep.n_epochs, BLOCK)], ignore_index=True)
        ref = choose_link_offsets(an, ep.take(slice(0, n)), **extra)
        c = trk.choice

        def rms(r: pd.DataFrame, err=err, back=back) -> float:
            return float(np.sqrt(np.nanmean(err(r.iloc[back].reset_index(drop=True)) ** 2)))

        off = Tracker(an, **extra).step(ep)
        on = Tracker(an, link_offsets=True, **extra).step(ep)
        said = "trial" if c is None else ("on" if c.use else "off")
        t = float("nan") if c is None else c.t
        print(f"{name:18s} {ep.n_epochs:6d} epochs, trial {n:6d}: stream {said:5s} t {t:7.3f}"
              f" | track {'on' if ref.use else 'off':3s} t {ref.t:7.3f} | RMS stream "
              f"{rms(rows):.3f}  off {rms(off):.3f}  on {rms(on):.3f}", flush=True)


if __name__ == "__main__":
    main()
