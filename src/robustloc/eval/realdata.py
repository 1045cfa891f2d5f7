"""The shared real data sets as uniform positioning cases, and their peer solvers.

Each :class:`Case` is what a new user would hand ``robustloc locate``: an anchors table,
an epoch matrix of ranges or RSSI (one row per epoch, NaN = not heard) and, for scoring
only, the truth.  Nothing here is tuned per data set; the epoch rules are the data's own:

* ``wifi-rtt-rss``: one epoch per scan (the data set's own unit), train and test files.
* ``uwb-dwm1001``: the four anchors answer within a few ms of each other every 0.1 s; rows
  closer than 20 ms form one epoch (time = the mean of its rows), the tag's height of 1 m
  reduces the slant ranges (``height_offset``).
* ``uwb-labyrinth``: one range every 0.128 s, cycling over the four anchors; four
  consecutive ranges form one epoch (the robot moves at most a few cm in 0.5 s).
* ``ble-tetam``: the five tracks, one-second epochs (the loader's default), the path-loss
  model fitted on the static histograms (the data set's survey), receivers' heights known.

Peers (:func:`peer_fixes`) are what a user would write by hand: scipy
``least_squares`` per epoch (``linear`` = plain Gauss-Newton/Levenberg-Marquardt,
``soft_l1`` and ``huber`` with ``f_scale = 1``) on the raw observations (ranges in metres,
RSSI in dB through the same path-loss model), started from the linearized LS fix (the
anchors' centroid where that fails), and statsmodels ``RLM`` (Huber's T) on the paper's
linearized difference system.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from numpy.typing import NDArray

Array = NDArray[np.float64]

__all__ = ["Case", "load_cases", "peer_fixes", "error_stats"]


@dataclass
class Case:
    """One real data set as a positioning problem.

    Attributes
    ----------
    name : str
    kind : {"range", "rssi"}
    anchors : DataFrame
        ``anchor, x, y[, z]`` plus ``A, n`` for RSSI.
    xy : (m, 2) anchor coordinates used for 2-D solving.
    values : (N, m) observations per epoch; NaN = not heard.
    time : (N,) epoch times (s).
    tag : (N,) tag ids.
    truth : (N, 2) true horizontal position of each epoch.
    height_offset : (m,) anchor-minus-tag heights (slant-range reduction) or None.
    source : str
        ``full`` (shared data) or ``excerpt`` (shipped in the package).
    """

    name: str
    kind: str
    anchors: pd.DataFrame
    xy: Array
    values: Array
    time: Array
    tag: NDArray[np.object_]
    truth: Array
    height_offset: Array | None
    source: str

    @property
    def A(self) -> Array | None:  # noqa: N802 - the paper's symbol
        return self.anchors["A"].to_numpy(float) if self.kind == "rssi" else None

    @property
    def n(self) -> Array | None:
        return self.anchors["n"].to_numpy(float) if self.kind == "rssi" else None

    @property
    def sigma(self) -> tuple[float, ...] | None:
        """The anchors' a-priori sigma column, as ``robustloc locate`` reads it (None
        without one): a :class:`~robustloc.estimators.ranging.Locator` given it solves
        the case as the command does (ble-tetam's survey calibration has one)."""
        from robustloc.io.tables import anchor_sigma

        sg = anchor_sigma(self.anchors)
        return None if sg is None else tuple(float(v) for v in sg)

    def measurements(self) -> pd.DataFrame:
        """The epochs as a contract measurements frame (``time, tag, anchor, value``)."""
        ids = self.anchors["anchor"].astype(str).to_numpy()
        i, j = np.nonzero(np.isfinite(self.values))
        return pd.DataFrame({"time": self.time[i], "tag": self.tag[i], "anchor": ids[j],
                             self.kind: self.values[i, j]})

    def truth_frame(self) -> pd.DataFrame:
        return pd.DataFrame({"time": self.time, "tag": self.tag,
                             "x": self.truth[:, 0], "y": self.truth[:, 1]})


def _wifi(room: str, data_dir: Path | None) -> Case:
    from robustloc.datasets import wifi_rtt
    from robustloc.io import to_epochs

    full = wifi_rtt.load_room(room, "all", data_dir)
    ids = [str(a) for a in full.anchors["anchor"]]
    ep = to_epochs(full.ranges, ids)
    truth = full.truth.set_index(["time", "tag"]).loc[list(zip(ep.time, ep.tag))]
    return Case(f"wifi-rtt {room.replace('_', ' ')}", "range", full.anchors,
                full.anchors[["x", "y"]].to_numpy(float), ep.values, ep.time,
                np.asarray(ep.tag, dtype=object), truth[["x", "y"]].to_numpy(float), None,
                full.source.kind)


def _group_rows(meas: pd.DataFrame, ids: list[str], value: str, new_epoch: NDArray[np.bool_]):
    """Epoch matrix from rows sorted by time, an epoch starting where ``new_epoch``."""
    g = np.cumsum(new_epoch) - 1
    n_ep = int(g[-1]) + 1
    col = pd.Index(ids).get_indexer(meas["anchor"].astype(str))
    vals = np.full((n_ep, len(ids)), np.nan)
    vals[g, col] = meas[value].to_numpy(float)  # a repeated anchor: the later row wins
    t = np.bincount(g, weights=meas["time"].to_numpy(float)) / np.bincount(g)
    return vals, t


def _dwm(run: str, data_dir: Path | None) -> Case:
    from robustloc.datasets import uwb_dwm1001

    full = data_dir is not None and (data_dir / "uwb-dwm1001").is_dir()
    r = uwb_dwm1001.load(run, data_dir if full else None)
    m = r.measurements.sort_values("time", kind="stable").reset_index(drop=True)
    ids = [str(a) for a in r.anchors["anchor"]]
    t = m["time"].to_numpy(float)
    new = np.r_[True, np.diff(t) > 0.02]
    vals, te = _group_rows(m, ids, "range", new)
    tr = r.truth.sort_values("time")
    truth = np.c_[np.interp(te, tr["time"], tr["x"]), np.interp(te, tr["time"], tr["y"])]
    # score only inside the truth's span (no extrapolated truth)
    keep = (te >= tr["time"].iloc[0]) & (te <= tr["time"].iloc[-1])
    return Case(f"uwb-dwm1001 {run}", "range", r.anchors, r.anchors[["x", "y"]].to_numpy(float),
                vals[keep], te[keep], np.full(keep.sum(), "tag", dtype=object), truth[keep],
                r.height_offset_m, "full" if full else "excerpt")


def _labyrinth(data_dir: Path | None) -> Case:
    from robustloc.datasets import uwb_labyrinth

    full = data_dir is not None and (data_dir / "uwb-labyrinth").is_dir()
    r = uwb_labyrinth.load(data_dir if full else None)
    m = r.measurements.sort_values("time", kind="stable").reset_index(drop=True)
    ids = [str(a) for a in r.anchors["anchor"]]
    new = np.arange(len(m)) % len(ids) == 0
    vals, te = _group_rows(m, ids, "range", new)
    tr = r.truth.sort_values("time")
    truth = np.c_[np.interp(te, tr["time"], tr["x"]), np.interp(te, tr["time"], tr["y"])]
    keep = (te >= tr["time"].iloc[0]) & (te <= tr["time"].iloc[-1])
    return Case("uwb-labyrinth", "range", r.anchors, r.anchors[["x", "y"]].to_numpy(float),
                vals[keep], te[keep], np.full(keep.sum(), "robot", dtype=object), truth[keep],
                None, "full" if full else "excerpt")


def _ble(data_dir: Path | None) -> Case:
    from robustloc.datasets import ble_tetam as bt
    from robustloc.io import to_epochs
    from robustloc.models.calibration import calibrate_pathloss

    src = bt.resolve(data_dir)
    anchors = bt.load_anchors(src.path)
    ids = [str(a) for a in anchors["anchor"]]
    cal = calibrate_pathloss(bt.load_survey_means(src.path), "log-distance")
    an = cal.apply_to_anchors(anchors)
    vals, times, tags, truth = [], [], [], []
    for k, tr in enumerate(bt.list_tracks(src.path)):
        meas, tt = bt.load_track(tr, src.path)
        ep = to_epochs(meas, ids)
        t = tt.set_index("time").loc[ep.time]
        vals.append(ep.values)
        times.append(ep.time + 1e6 * k)  # tracks one after another on one clock
        tags.append(np.full(len(ep.time), tr, dtype=object))
        truth.append(t[["x", "y", "z"]].to_numpy(float))
    tz = np.concatenate(truth)
    # the beacon is carried at a fixed height: the mean labelled z of the tracks
    h = anchors["z"].to_numpy(float) - float(np.mean(tz[:, 2]))
    return Case("ble-tetam tracks", "rssi", an, anchors[["x", "y"]].to_numpy(float),
                np.vstack(vals), np.concatenate(times), np.concatenate(tags), tz[:, :2], h,
                src.kind)


CASES = ("wifi-rtt lecture theatre", "wifi-rtt office", "wifi-rtt corridor",
         "uwb-dwm1001 LOS", "uwb-dwm1001 NLOS", "uwb-labyrinth", "ble-tetam tracks")


def load_cases(data_dir: str | Path | None = None,
               only: list[str] | None = None) -> list[Case]:
    """Every shared real data set as a :class:`Case` (full data when ``data_dir`` has it,
    else the excerpts shipped in the package)."""
    d = None if data_dir is None else Path(data_dir)
    loaders = {
        "wifi-rtt lecture theatre": lambda: _wifi("lecture_theatre", d),
        "wifi-rtt office": lambda: _wifi("office", d),
        "wifi-rtt corridor": lambda: _wifi("corridor", d),
        "uwb-dwm1001 LOS": lambda: _dwm("LOS", d),
        "uwb-dwm1001 NLOS": lambda: _dwm("NLOS", d),
        "uwb-labyrinth": lambda: _labyrinth(d),
        "ble-tetam tracks": lambda: _ble(d),
    }
    return [loaders[k]() for k in CASES if only is None or k in only]


def _start(case: Case) -> Array:
    from robustloc.estimators.ranging import Locator

    sol = Locator("ls").solve(case.xy, case.values, case.kind, A=case.A, n=case.n,
                              height_offset=case.height_offset)
    x0 = sol.position
    return np.where(np.isfinite(x0), x0, case.xy.mean(axis=0))


def peer_fixes(case: Case, rows: NDArray[np.int64] | None = None,
               peers: tuple[str, ...] = ("scipy linear", "scipy soft_l1", "scipy huber",
                                         "statsmodels RLM")) -> dict[str, Array]:
    """Per-epoch peer fixes on ``rows`` (default: every epoch); NaN where a peer gives
    no fix (fewer than 3 anchors heard, or an exception in the peer)."""
    from scipy.optimize import least_squares

    rows = np.arange(len(case.time)) if rows is None else rows
    x0 = _start(case)
    h2 = np.zeros(case.xy.shape[0]) if case.height_offset is None else case.height_offset**2
    out = {p: np.full((len(case.time), 2), np.nan) for p in peers}
    for i in rows:
        ok = np.isfinite(case.values[i])
        if ok.sum() < 3:
            continue
        a, z, hh = case.xy[ok], case.values[i, ok], h2[ok]
        if case.kind == "range":
            def fun(p, a=a, z=z, hh=hh):
                return np.sqrt((a[:, 0] - p[0]) ** 2 + (a[:, 1] - p[1]) ** 2 + hh) - z
        else:
            A, n = case.A[ok], case.n[ok]

            def fun(p, a=a, z=z, hh=hh, A=A, n=n):
                d = np.sqrt((a[:, 0] - p[0]) ** 2 + (a[:, 1] - p[1]) ** 2 + hh)
                return A - 10.0 * n * np.log10(np.maximum(d, 0.1)) - z
        for p in peers:
            if p.startswith("scipy"):
                try:
                    out[p][i] = least_squares(fun, x0[i], loss=p.split()[1]).x
                except (ValueError, np.linalg.LinAlgError):
                    pass
    if "statsmodels RLM" in peers:
        out["statsmodels RLM"] = _rlm_fixes(case, rows)
    return out


def _rlm_fixes(case: Case, rows: NDArray[np.int64]) -> Array:
    import warnings

    import statsmodels.api as sm

    from robustloc.estimators.ranging import linearized_system
    from robustloc.models.ranging import RssiModel

    ranges = case.values
    if case.kind == "rssi":
        ranges = RssiModel(case.xy, case.A, case.n, case.height_offset).distance(case.values)
    G, h, _, c = linearized_system(case.xy, ranges[rows], case.height_offset, "first")
    out = np.full((len(case.time), 2), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k, i in enumerate(rows):
            ok = np.all(np.isfinite(G[k]), axis=1) & np.isfinite(h[k])
            if ok.sum() < 3:
                continue
            try:
                res = sm.RLM(h[k][ok], G[k][ok], M=sm.robust.norms.HuberT()).fit()
                out[i] = res.params + (c[k] if np.ndim(c) == 2 else c)
            except (ValueError, np.linalg.LinAlgError, ZeroDivisionError):
                pass
    return out


def error_stats(pos: Array, truth: Array, usable: NDArray[np.bool_] | None = None,
                hpl: Array | None = None) -> dict[str, float]:
    """RMS, p95, availability and (with ``hpl``) the misleading rate of 2-D fixes.

    ``usable`` marks the fixes the method itself calls usable (default: finite);
    a misleading fix is usable with an error above its ``hpl``.
    """
    err = np.hypot(*(pos - truth).T)
    fin = np.isfinite(err)
    use = fin if usable is None else (usable & fin)
    e = err[use]
    out = {
        "rms": float(np.sqrt(np.mean(e**2))) if e.size else np.nan,
        "p95": float(np.percentile(e, 95)) if e.size else np.nan,
        "availability": float(use.mean()),
        "n": int(use.sum()),
    }
    if hpl is not None:  # the definitions of `robustloc evaluate`
        from robustloc.eval.metrics import integrity_stats

        iv = integrity_stats(e, np.asarray(hpl, dtype=float)[use])
        out["misleading"] = iv["misleading_pct"] / 100.0
        out["hpl_median_over_err_median"] = iv["hpl_over_error"]
    return out
