"""Do the protection levels of smoothed track rows hold on real data?

For each shared real data set the report's section ``s60_tracks`` tracks (ble-tetam's
five walks, uwb-dwm1001 LOS and NLOS, uwb-labyrinth with the default settings,
``--range-offset`` and ``--link-offsets``; the report's settings), the tracker's forward
rows, the fixed-interval RTS smoother (``track --smooth``) and the fixed-lag one
(``--fixed-lag``) are scored against the truth: RMS, the share of rows beyond their
``hpl`` (misleading) and the median ``hpl`` over the median error.

A smoothed row's ``hpl`` is the forward row's plus the distance smoothing moved the
position (:func:`robustloc.pipelines.track.apply_smoother`).  Measured 2026-12-06 (the
previous rule, the forward slope term plus k sigma of the smoothed covariance, in
brackets): ble-tetam smoothed rows beyond hpl 0 % (3.22 %), fixed lag 0 % (2.34 %);
uwb-dwm1001 0 % (0.18 %); uwb-labyrinth 0 % (0 %).  Median hpl / error of the smoothed
rows: ble-tetam 2.8-7.2 per walk, dwm1001 LOS / NLOS 6.3 / 7.5, labyrinth 8.4 / 15.1 /
14.4 (default / --range-offset / --link-offsets).

Usage::

    python benchmarks/bench_smooth_bound.py                # ../shared/data (about 10 s)
    python benchmarks/bench_smooth_bound.py --data DIR
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from robustloc.datasets import ble_tetam as bt
from robustloc.datasets import uwb_dwm1001, uwb_labyrinth
from robustloc.io import to_epochs
from robustloc.models.calibration import calibrate_pathloss
from robustloc.paths import default_data_dir
from robustloc.pipelines.track import apply_smoother
from robustloc.reproduce import s60_tracks as S
from robustloc.tracking import Tracker


def _score(name: str, trk: Tracker, rows: pd.DataFrame, truth_xy, keep: np.ndarray,
           lag: int, out: list[dict]) -> None:
    for label, lg in (("forward", "fwd"), ("RTS", None), (f"fixed lag {lag}", lag)):
        t = rows if lg == "fwd" else apply_smoother(trk, rows, lg)
        xy = truth_xy(t["time"].to_numpy(float))
        e = np.hypot(*(t[["x", "y"]].to_numpy(float) - xy).T)[keep]
        h = t["hpl"].to_numpy(float)[keep]
        ok = np.isfinite(e)
        e, h = e[ok], h[ok]
        out.append({"data set": name, "rows": label, "n": len(e),
                    "rms_m": float(np.sqrt(np.mean(e**2))),
                    "misleading_pct": float(100 * np.mean(~(h >= e))),
                    "hpl_over_error": float(np.median(h) / np.median(e))})


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None, help="shared data folder (default ../shared/data)")
    args = ap.parse_args(argv)
    data = args.data if args.data is not None else default_data_dir()
    out: list[dict] = []
    for run in uwb_dwm1001.RUNS:
        r = uwb_dwm1001.load(run, data)
        ls = r.authors["LS"]
        an = r.anchors
        ep = to_epochs(r.measurements.drop(columns=["rssi"]), [str(a) for a in an["anchor"]])
        trk = Tracker(an, tag_height=r.tag_height_m, record=True, **S.DWM_OPTS)
        rows = trk.step(ep)
        tt = r.truth["time"].to_numpy(float)
        t = rows["time"].to_numpy(float)
        keep = (t >= float(ls["time"].iloc[0])) & (t <= float(ls["time"].iloc[-1]))
        _score(f"uwb-dwm1001 {run}", trk, rows, lambda q, r=r, tt=tt: np.c_[
            np.interp(q, tt, r.truth["x"]), np.interp(q, tt, r.truth["y"])], keep, 3, out)
    r = uwb_labyrinth.load(data)
    ep = to_epochs(r.measurements.drop(columns=["var"]), [str(a) for a in r.anchors["anchor"]])
    tt = r.truth["time"].to_numpy(float)
    for label, opts in (("", S.LAB_OPTS), (" --range-offset", S.LAB_OFFSET_OPTS),
                        (" --link-offsets", {**S.LAB_OPTS, "link_offsets": True})):
        trk = Tracker(r.anchors, record=True, **opts)
        rows = trk.step(ep)
        t = rows["time"].to_numpy(float)
        _score(f"uwb-labyrinth{label}", trk, rows, lambda q: np.c_[
            np.interp(q, tt, r.truth["x"]), np.interp(q, tt, r.truth["y"])],
            (t >= 1.0) & (t <= tt[-1]), S.LAB_LAG, out)
    src = bt.resolve(data)
    an = calibrate_pathloss(bt.load_survey_means(src.path),
                            "log-distance").apply_to_anchors(bt.load_anchors(src.path))
    ids = [str(a) for a in an["anchor"]]
    for tr in bt.list_tracks(src.path):
        meas, truth = bt.load_track(tr, src.path)
        ep = to_epochs(meas, ids)
        tru = truth.set_index("time")
        trk = Tracker(an, tag_height=float(truth["z"].mean()), record=True, **S.BLE_OPTS)
        rows = trk.step(ep)
        _score(f"ble-tetam {tr}", trk, rows,
               lambda q, tru=tru: tru.loc[q, ["x", "y"]].to_numpy(float),
               np.ones(len(rows), bool), S.BLE_LAG, out)
    with pd.option_context("display.width", 160, "display.max_rows", 200):
        print(pd.DataFrame(out).to_string(index=False, float_format=lambda v: f"{v:.3g}"))


if __name__ == "__main__":
    main()
