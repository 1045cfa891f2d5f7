"""Seed 000: robust RSSI ranging (Table 1) on simulation, then the same methods on real data.

1. **Table 1** on the ``ble-corridor`` simulation (the paper's corridor, 10 beacons, points
   S1-S3, 60 epochs, scheme 1 undisturbed and scheme 2 with people walking): the paper's
   methods on its linearized system (eq. (3)) -- LS, Huber, Hampel, IGG, LEGE -- beside the
   published averages, and the same methods on the nonlinear observation equations, with
   the Cramer-Rao bound of the simulated noise.
2. **Real BLE** (``ble-tetam``: one moving beacon, 12 fixed receivers, AR-tracked truth):
   path loss calibrated per receiver on the static histograms, every method on the five
   labelled tracks.
3. **Real WiFi RTT** (``wifi-rtt-rss``, lecture theatre, office, corridor): per-AP range
   bias and scale and per-AP noise calibrated on the train files, every scan of train and
   test positioned, beside the standard peers (scipy ``least_squares``) and the figures
   the issue measured for them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from robustloc.reproduce import Context, Section, data_label, fmt_num

TITLE = "Seed 000: robust RSSI and range positioning (Table 1), real BLE and WiFi RTT"
ORDER = 10

#: Table 1 of seed 000, mean over S1-S3 (max, min, mean, RMS, spread), metres.
PAPER_TABLE1 = {
    (1, "ls"): (15.4, 1.3, 4.1, 5.1, 2.9),
    (1, "huber"): (11.3, 0.6, 2.7, 3.4, 2.1),
    (1, "hampel"): (10.8, 0.5, 2.8, 3.4, 2.0),
    (1, "igg"): (8.5, 0.4, 2.2, 2.7, 1.6),
    (1, "lege"): (13.6, 1.2, 3.8, 4.5, 2.5),
    (2, "ls"): (14.2, 1.6, 6.8, 7.6, 3.3),
    (2, "huber"): (11.1, 1.3, 3.5, 4.2, 2.1),
    (2, "hampel"): (10.3, 1.2, 4.1, 4.6, 2.0),
    (2, "igg"): (7.0, 0.4, 2.6, 3.0, 1.5),
    (2, "lege"): (12.0, 1.6, 5.3, 5.9, 2.4),
}
PAPER_METHODS = ("ls", "huber", "hampel", "igg", "lege")

#: The issue's reference figures on wifi-rtt-rss (2-D RMS, all scans), measured with the
#: standard methods: Gauss-Newton, scipy least_squares soft_l1 / huber, linearized LS.
ISSUE_WIFI = {
    "lecture_theatre": {"Gauss-Newton": 0.94, "scipy soft_l1": 0.98, "linearized LS": 1.73},
    "office": {"scipy soft_l1": 1.17, "Gauss-Newton": 1.22},
    "corridor": {"scipy huber": 6.26, "scipy soft_l1": 6.30, "linearized LS": 42.0},
}

#: The method whose fixes the track plot shows (see README).
DEFAULT_METHOD = "auto"


def _errors(pos: np.ndarray, truth_xy: np.ndarray) -> np.ndarray:
    return np.hypot(pos[:, 0] - truth_xy[:, 0], pos[:, 1] - truth_xy[:, 1])


def _stats(e: np.ndarray) -> dict[str, float]:
    ok = np.isfinite(e)
    v = e[ok]
    if v.size == 0:
        return {"n": int(e.size), "failed_pct": 100.0}
    return {
        "n": int(e.size),
        "failed_pct": 100.0 * float(np.mean(~ok)),
        "mean": float(v.mean()),
        "rms": float(np.sqrt(np.mean(v**2))),
        "median": float(np.median(v)),
        "p95": float(np.percentile(v, 95)),
        "max": float(v.max()),
    }


def _cdf_plot(path: Path, curves: dict[str, np.ndarray], title: str, xmax: float | None = None):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    for name, e in curves.items():
        v = np.sort(e[np.isfinite(e)])
        if v.size:
            ax.plot(v, np.arange(1, v.size + 1) / e.size, label=name)
    ax.set_xlabel("horizontal error (m)")
    ax.set_ylabel("fraction of epochs")
    ax.set_title(title)
    if xmax is not None:
        ax.set_xlim(0, xmax)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


#: The peer tools (:func:`robustloc.eval.realdata.peer_fixes`): scipy ``least_squares``
#: per epoch on the raw observation equations, statsmodels ``RLM`` (Huber's T) on the
#: paper's linearized system.  Their rows in the tables are ``peer: NAME``.
PEERS = ("scipy linear", "scipy soft_l1", "scipy huber", "statsmodels RLM")


def _peer_positions(name: str, anchors: pd.DataFrame, xy: np.ndarray, values: np.ndarray,
                    time: np.ndarray, tag: np.ndarray, truth_xy: np.ndarray,
                    height_offset: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """The peers' fixes ``(N, 2)`` of RSSI epochs ``values`` (``anchors`` with the
    calibrated ``A, n``), one entry per peer of :data:`PEERS`."""
    from robustloc.eval.realdata import Case, peer_fixes

    case = Case(name, "rssi", anchors, xy, values, np.asarray(time, dtype=float),
                np.asarray(tag, dtype=object), truth_xy, height_offset, "-")
    return peer_fixes(case, peers=PEERS)


def _best_peer(rows: pd.DataFrame, col: str) -> pd.Series | None:
    """The row of the peer (``method`` starting ``peer: ``) with the lowest ``col``."""
    peers = rows[rows["method"].astype(str).str.startswith("peer: ")]
    peers = peers[np.isfinite(peers[col].to_numpy(dtype=float))]
    return None if peers.empty else peers.loc[peers[col].idxmin()]


# --------------------------------------------------------------------------- simulation
@dataclass(frozen=True)
class CorridorScheme:
    """One Table-1 scheme of the simulated corridor, as the paper sets it up: the frames
    of :func:`robustloc.sim.ble_corridor.simulate_ble_corridor` (``fr``), A and n
    calibrated (pooled) from its 1 m-step survey, the anchors' ids and coordinates, and
    the measurements as epochs."""

    fr: dict
    ids: list[str]
    A: np.ndarray
    n: np.ndarray
    xy: np.ndarray
    ep: Any


def corridor_scheme(seed: int, disturbance: bool) -> CorridorScheme:
    """:class:`CorridorScheme` of scheme 1 (``disturbance=False``) or 2 (people walking)."""
    from robustloc.io import to_epochs
    from robustloc.models.calibration import calibrate_pathloss
    from robustloc.models.pathloss import log_distance_arrays
    from robustloc.sim import ble_corridor as bc

    fr = bc.simulate_ble_corridor(seed=seed, disturbance=disturbance)
    cal = calibrate_pathloss(fr["survey"], "log-distance", pooled=True)
    anchors = cal.apply_to_anchors(fr["anchors"][["anchor", "x", "y"]])
    ids = [str(a) for a in anchors["anchor"]]
    A, n = log_distance_arrays(anchors)
    return CorridorScheme(fr, ids, A, n, anchors[["x", "y"]].to_numpy(float),
                          to_epochs(fr["measurements"], ids))


def _table1(ctx: Context, sec: Section) -> None:
    from robustloc.estimators.ranging import Locator
    from robustloc.eval.crlb import crlb_rssi
    from robustloc.eval.metrics import error_table
    from robustloc.integrity.fixes import locate_protected
    from robustloc.io import positions_frame
    from robustloc.sim import ble_corridor as bc

    rows = []
    per_point = []
    for scheme, dist in ((1, False), (2, True)):
        sc = corridor_scheme(ctx.seed, dist)
        fr, ids, A, n, xy, ep = sc.fr, sc.ids, sc.A, sc.n, sc.xy, sc.ep
        truth = fr["truth"]
        variants = (
            [(m, "linearized", "first", m) for m in PAPER_METHODS]
            + [(m, "linearized", "nearest", f"{m} (nearest ref.)") for m in ("ls", "igg")]
            + [(m, "nonlinear", "first", f"{m} (nonlinear)")
               for m in ("nls", "huber", "hampel", "igg", "igg3", "lege")]
        )
        variants.append(("auto", "nonlinear", "first", "auto (robustloc default)"))
        frames = []
        for m, solver, ref, label in variants:
            loc = Locator(m, solver=solver, reference=ref)
            if m == "auto":
                sol = locate_protected(loc, xy, ep.values, "rssi", A=A, n=n)
            else:
                sol = loc.solve(xy, ep.values, "rssi", A=A, n=n)
            frames.append(positions_frame(sol, ep.time, ep.tag, ids, label))
        if dist:  # the oracle: exactly the blocked links dropped, then Gauss-Newton
            blocked = fr["blocked"]
            key = pd.MultiIndex.from_arrays([ep.time, ep.tag])
            row = key.get_indexer(pd.MultiIndex.from_arrays([blocked["time"], blocked["tag"]]))
            col = pd.Index(ids).get_indexer(blocked["anchor"].astype(str))
            vals = ep.values.copy()
            ok = (row >= 0) & (col >= 0)
            vals[row[ok], col[ok]] = np.nan
            sol = Locator("nls").solve(xy, vals, "rssi", A=A, n=n)
            frames.append(positions_frame(sol, ep.time, ep.tag, ids,
                                          "oracle: nls without the blocked links"))
        # the peer tools on the same epochs (scipy least_squares, statsmodels RLM)
        tkey = truth.set_index(["time", "tag"])[["x", "y"]]
        txy = tkey.reindex(pd.MultiIndex.from_arrays([ep.time, ep.tag])).to_numpy(float)
        an = pd.DataFrame({"anchor": ids, "x": xy[:, 0], "y": xy[:, 1], "A": A, "n": n})
        for name, pos in _peer_positions("ble-corridor", an, xy, ep.values, ep.time,
                                         ep.tag, txy).items():
            frames.append(pd.DataFrame({"time": ep.time, "tag": ep.tag, "x": pos[:, 0],
                                        "y": pos[:, 1], "method": f"peer: {name}",
                                        "status": "ok"}))
        tab = error_table(pd.concat(frames, ignore_index=True), truth)
        # CRLB of each point for the simulated shadowing (sample noise sd) and exponent
        pts = np.array([bc.TEST_POINTS[t] for t in ("S1", "S2", "S3")])
        sd = float(np.hypot(bc.SAMPLE_GAUSS_DB, bc.LINK_SHADOW_DB))
        cr = crlb_rssi(xy, pts, sd, n)
        crlb_rms = float(np.sqrt(np.mean(np.asarray(cr.horizontal) ** 2)))
        for _, r in tab[tab["tag"].isin(["S1", "S2", "S3"])].iterrows():
            per_point.append({"scheme": scheme, "point": r["tag"], "method": r["method"],
                              **{k: r[k] for k in ("max", "min", "mean", "rms", "sigma1")}})
        for _, r in tab[tab["tag"] == "mean"].iterrows():
            key = (scheme, r["method"])
            paper = PAPER_TABLE1.get(key, (np.nan,) * 5)
            rows.append({
                "scheme": scheme, "method": r["method"],
                "max": r["max"], "min": r["min"], "mean": r["mean"], "rms": r["rms"],
                "spread": r["sigma1"], "mean_vs_ls_%": r["mean_impr_pct"],
                "paper_max": paper[0], "paper_mean": paper[2], "paper_rms": paper[3],
                "paper_spread": paper[4],
                "paper_mean_vs_ls_%": (100 * (1 - paper[2] / PAPER_TABLE1[(scheme, "ls")][2])
                                       if key in PAPER_TABLE1 else np.nan),
                "crlb_rms": crlb_rms,
            })
    t1 = pd.DataFrame(rows)
    t1.to_csv(ctx.out_dir / "seed000_table1.csv", index=False)
    pd.DataFrame(per_point).to_csv(ctx.out_dir / "seed000_table1_points.csv", index=False)
    sec.text(
        "Simulated corridor (`robustloc simulate ble-corridor`, the scenario's docstring "
        "lists every assumed number); A and n calibrated (pooled) from the 1 m-step survey, "
        "as in the paper. Rows without a suffix are the paper's methods on its linearized "
        "system (eq. 3) with its first anchor as reference; `(nearest ref.)` rows take the "
        "anchor with the shortest range as reference instead; `(nonlinear)` rows solve the "
        "raw observation equations (range domain, Levenberg-damped Gauss-Newton). Statistics "
        "are the paper's: per point over 60 epochs, then averaged over S1-S3. `peer:` rows "
        "are the peer tools on the same epochs: scipy `least_squares` per epoch on the raw "
        "RSSI equations (loss linear, soft_l1, huber; f_scale 1) from the linearized LS "
        "fix, and statsmodels `RLM` (Huber's T) on the paper's linearized system. "
        "`crlb_rms` is "
        "the Cramer-Rao bound of the simulated noise averaged over the three points. "
        "`paper_mean_vs_ls_%` is computed from the paper's Table 1 means, not quoted from "
        "its text (which rounds some: scheme 1 Hampel 33 %, scheme 2 IGG 61 %)."
    )
    sec.table("Table 1 (seed 000): mean over S1-S3, metres, beside the paper", t1)
    for scheme in (1, 2):
        lin = t1[(t1.scheme == scheme) & t1.method.isin(PAPER_METHODS)].set_index("method")
        sec.summary[f"table1_scheme{scheme}_rms"] = lin["rms"].round(3).to_dict()
    best_nl = t1[t1.method.str.contains("nonlinear")].groupby("scheme")["rms"].min()
    sec.summary["table1_best_nonlinear_rms"] = best_nl.round(3).to_dict()
    for scheme in (1, 2):
        t = t1[t1.scheme == scheme].set_index("method")["mean"]
        d, g = t["auto (robustloc default)"], t["nls (nonlinear)"]
        paper = PAPER_TABLE1[(scheme, "igg")][2]
        oracle = t.get("oracle: nls without the blocked links", np.nan)
        sec.summary[f"table1_scheme{scheme}_default_vs_nls"] = {
            "default_mean": float(d), "nls_mean": float(g), "oracle_mean": float(oracle)}
        # issue 10's targets, said with the verdict (the summary printed "target met"
        # without saying which: the report review)
        target = (d <= g) if scheme == 1 else (d <= 0.9 * g or d <= 1.03 * oracle)
        what = ("default <= nls" if scheme == 1 else
                "default <= 0.9x nls, or <= 1.03x the oracle")
        # the paper's column is its published IGG mean; the best peer is the best peer
        # tool's run on the same epochs (it showed our run of the paper's LS, the worst
        # method: the report review); the corridor is simulated, and the row says so
        peer = _best_peer(t1[t1.scheme == scheme], "mean")
        verdict = f"target ({what}) " + ("met" if target else "missed")
        if peer is not None:
            verdict += ("; at or below the best peer" if d <= peer["mean"]
                        else "; above the best peer")
        sec.headline("000", f"Table 1 scheme {scheme} (simulated corridor): mean error over "
                     "S1-S3 (m)",
                     f"IGG {paper:.1f}", f"default {fmt_num(d)} (nls {fmt_num(g)}"
                     + (f", oracle {fmt_num(oracle)})" if scheme == 2 else ")"),
                     "-" if peer is None else
                     f"{peer['method'].removeprefix('peer: ')} {fmt_num(peer['mean'])}",
                     verdict + " (simulation)")


# ------------------------------------------------------------------------------ real BLE
def _ble(ctx: Context, sec: Section) -> None:
    from robustloc.datasets import ble_tetam as bt
    from robustloc.estimators.ranging import Locator
    from robustloc.io import to_epochs
    from robustloc.models.calibration import calibrate_pathloss
    from robustloc.models.pathloss import log_distance_arrays

    src = bt.resolve(ctx.data_dir)
    ctx.note(src)
    anchors = bt.load_anchors(src.path)
    ids = [str(a) for a in anchors["anchor"]]
    survey = bt.load_survey_means(src.path)
    cal = calibrate_pathloss(survey, "log-distance")
    an = cal.apply_to_anchors(anchors)
    A, n = log_distance_arrays(an)
    xy = anchors[["x", "y"]].to_numpy(float)
    ctx.note(bt.tracks_note(src.path))
    tracks = bt.list_tracks(src.path)
    data = []
    for tr in tracks:
        meas, truth = bt.load_track(tr, src.path)
        ep = to_epochs(meas, ids)
        tt = truth.set_index("time").loc[ep.time]
        data.append((tr, ep, tt))
    # the beacon is carried at a fixed height: the mean labelled z of the tracks
    z_tag = float(np.mean(np.concatenate([d[2]["z"].to_numpy() for d in data])))
    h = anchors["z"].to_numpy(float) - z_tag
    from robustloc.integrity.fixes import locate_protected

    variants = [
        ("auto", {}),
        ("ls", {}), ("wls", {}), ("nls", {}), ("nls (dB domain)", {"domain": "rssi"}),
        ("huber", {}), ("hampel", {}), ("igg", {}), ("igg3", {}), ("lege", {}),
        ("igg (linearized, paper)", {"solver": "linearized"}),
    ]
    rows, curves = [], {}
    track_plot = None
    for label, kw in variants:
        method = label.split(" ")[0]
        errs = []
        for tr, ep, tt in data:
            if method == "auto":
                sol = locate_protected(Locator(method, **kw), xy, ep.values, "rssi", A=A, n=n,
                                       height_offset=h)
            else:
                sol = Locator(method, **kw).solve(xy, ep.values, "rssi", A=A, n=n,
                                                  height_offset=h)
            errs.append(_errors(sol.position, tt[["x", "y"]].to_numpy()))
            if label == DEFAULT_METHOD and track_plot is None:
                track_plot = (tr, sol.position, tt[["x", "y"]].to_numpy())
        e = np.concatenate(errs)
        rows.append({"method": label, **_stats(e)})
        curves[label] = e
    # the peer tools on the same epochs, each track its own log as above (the linearized
    # LS start of scipy is the track's own)
    peer_err: dict[str, list[np.ndarray]] = {p: [] for p in PEERS}
    an_xy = an.assign(A=A, n=n)
    for tr, ep, tt in data:
        txy = tt[["x", "y"]].to_numpy(float)
        for name, pos in _peer_positions(tr, an_xy, xy, ep.values, ep.time,
                                         np.full(len(ep.time), tr, dtype=object), txy,
                                         h).items():
            peer_err[name].append(_errors(pos, txy))
    for name, es in peer_err.items():
        rows.append({"method": f"peer: {name}", **_stats(np.concatenate(es))})
    tab = pd.DataFrame(rows)
    tab.to_csv(ctx.out_dir / "seed000_ble_tetam.csv", index=False)
    sec.text(
        f"Real BLE: `ble-tetam` ({src.kind} data: {len(tracks)} tracks, {len(curves['ls'])} "
        "one-second epochs, 12 receivers). Path loss calibrated per receiver on the static "
        f"RSSI histograms (81 points; pooled fit A = {cal.table['A'].iloc[-1]:.1f} dBm, "
        f"n = {cal.table['n'].iloc[-1]:.2f}, residual {cal.table['residual_std'].iloc[-1]:.1f} "
        f"dB); 2-D fixes with the beacon height {z_tag:.2f} m (mean labelled z) and the "
        "receivers' heights known. Errors against the AR-tracked truth. Each track is "
        "solved as its own log (its own log scale) and every method with equal a-priori "
        "sigmas, as the paper runs them; the sections `s05_out_of_box` and `s60_tracks` "
        f"run the default as `robustloc locate` does on one file of the {len(tracks)} "
        "tracks, with the survey's sigma per receiver, which moves its RMS in the third "
        "digit.  `peer:` rows are the peer tools on the same epochs: scipy `least_squares` "
        "per epoch on the raw RSSI equations (loss linear, soft_l1, huber; f_scale 1) from "
        "the linearized LS fix, and statsmodels `RLM` (Huber's T) on the paper's "
        "linearized system."
    )
    sec.table("Real BLE (ble-tetam): horizontal error over all tracks, metres", tab)
    fig = "seed000_ble_cdf.png"
    _cdf_plot(ctx.out_dir / fig, {k: curves[k] for k in ("ls", "nls", "huber", "igg", "lege",
                                                           "igg (linearized, paper)")},
              "ble-tetam tracks: error CDF", xmax=12)
    sec.figure("ble-tetam: error CDF per method", fig)
    if track_plot is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        tr, p, t = track_plot
        fig2, ax = plt.subplots(figsize=(5.5, 5.5))
        ax.plot(t[:, 0], t[:, 1], "k-", lw=2, label="truth")
        ax.plot(p[:, 0], p[:, 1], ".-", alpha=0.7, label=DEFAULT_METHOD)
        ax.plot(xy[:, 0], xy[:, 1], "r^", label="receivers")
        ax.set_aspect("equal")
        ax.set_title(f"ble-tetam track {tr}")
        ax.legend(fontsize=8)
        fig2.tight_layout()
        fig2.savefig(ctx.out_dir / "seed000_ble_track.png", dpi=110)
        plt.close(fig2)
        sec.figure(f"ble-tetam {tr}: {DEFAULT_METHOD} fixes against the truth",
                   "seed000_ble_track.png")
    sec.summary["ble_tetam_rms"] = tab.set_index("method")["rms"].round(3).to_dict()
    r = sec.summary["ble_tetam_rms"]
    # the paper has no figure on this data: its column is "-", our run of its method is
    # in the verdict; the best peer is the best peer tool's run on the same epochs (it
    # showed our LS, the worst method, as the peer: the report review)
    peer = _best_peer(tab, "rms")
    paper_m = r["igg (linearized, paper)"]
    verdict = (("below" if r["auto"] < paper_m else "not below")
               + f" the paper's method (linearized IGG, run here: {fmt_num(paper_m)})")
    if peer is not None:
        verdict += ("; at or below the best peer" if r["auto"] <= peer["rms"]
                    else "; above the best peer")
    sec.headline("000", f"ble-tetam tracks, 12 receivers {data_label(src.kind)}: "
                 "2-D RMS (m)", "-",
                 f"default {fmt_num(r['auto'])}, huber {fmt_num(r['huber'])}",
                 "-" if peer is None else
                 f"{peer['method'].removeprefix('peer: ')} {fmt_num(peer['rms'])}", verdict)


# ---------------------------------------------------------------------------- WiFi RTT
def _scipy_peers(xy: np.ndarray, ranges: np.ndarray, x0: np.ndarray, rows: np.ndarray):
    """Per-scan scipy least_squares fixes (the peers), on the scans ``rows``."""
    from scipy.optimize import least_squares

    out = {k: np.full((ranges.shape[0], 2), np.nan) for k in ("scipy soft_l1", "scipy huber")}
    for i in rows:
        ok = np.isfinite(ranges[i])
        if ok.sum() < 3:
            continue
        a, d = xy[ok], ranges[i, ok]

        def fun(p, a=a, d=d):
            return np.hypot(a[:, 0] - p[0], a[:, 1] - p[1]) - d

        for name, loss in (("scipy soft_l1", "soft_l1"), ("scipy huber", "huber")):
            out[name][i] = least_squares(fun, x0[i], loss=loss).x
    return out


def _wifi(ctx: Context, sec: Section) -> None:
    from robustloc.datasets import wifi_rtt
    from robustloc.estimators.ranging import Locator
    from robustloc.io import to_epochs
    from robustloc.models.calibration import (
        apply_range_calibration,
        calibrate_ranges,
        survey_from_positions,
    )
    from robustloc.robust.scale import mad_scale

    rows = []
    figs = {}
    peer_step = 30 if ctx.quick else 10
    for room in wifi_rtt.ROOMS:
        train = wifi_rtt.load_room(room, "train", ctx.data_dir)
        full = wifi_rtt.load_room(room, "all", ctx.data_dir)
        ctx.note(full.source)
        ids = [str(a) for a in train.anchors["anchor"]]
        xy = train.anchors[["x", "y"]].to_numpy(float)
        survey = survey_from_positions(train.ranges, train.truth, train.anchors)
        cal = calibrate_ranges(survey, scale=True, robust="huber")
        an = cal.apply_to_anchors(train.anchors)
        # per-AP noise: robust std of the calibrated range residuals on the train files
        ai = pd.Index(ids).get_indexer(survey["anchor"].astype(str))
        bias = an["bias"].to_numpy(float)[ai]
        scale = an["scale"].to_numpy(float)[ai]
        res = (survey["range"].to_numpy(float) - bias) / scale - survey["distance"].to_numpy(float)
        sig = np.array([mad_scale(res[ai == k]) for k in range(len(ids))])
        ep = to_epochs(full.ranges, ids)
        truth = full.truth.set_index("time").loc[ep.time]
        txy = truth[["x", "y"]].to_numpy(float)
        is_test = (truth["split"] == "test").to_numpy()
        raw = ep.values
        corr = apply_range_calibration(an, raw)
        variants = {
            "ls (paper eq. 3, raw)": Locator("ls").solve(xy, raw),
            "nls (Gauss-Newton, raw)": Locator("nls").solve(xy, raw),
            "nls (calibrated)": Locator("nls", sigma=tuple(sig)).solve(xy, corr),
            # the first release's configuration (README table): the train files' per-AP
            # sigma and each scan's own MAD scale
            "huber (calibrated)": Locator("huber", sigma=tuple(sig),
                                          robust_scale="mad").solve(xy, corr),
            "huber (calibrated, log scale)": Locator("huber", sigma=tuple(sig)).solve(xy, corr),
            "igg3 (calibrated)": Locator("igg3", sigma=tuple(sig),
                                         robust_scale="mad").solve(xy, corr),
            "lege (calibrated)": Locator("lege", sigma=tuple(sig)).solve(xy, corr),
            "snooping (calibrated)": Locator("snooping", sigma=tuple(sig)).solve(xy, corr),
        }
        errs = {k: _errors(s.position, txy) for k, s in variants.items()}
        # peers on every peer_step-th scan (scipy is one Python call per scan)
        sub = np.arange(0, len(ep.time), peer_step)
        x0 = np.where(np.isfinite(variants["ls (paper eq. 3, raw)"].position),
                      variants["ls (paper eq. 3, raw)"].position, xy.mean(0))
        t0 = time.perf_counter()
        peers = _scipy_peers(xy, raw, x0, sub)
        peer_us = (time.perf_counter() - t0) / max(len(sub), 1) / 2 * 1e6
        for k, p in peers.items():
            errs[f"{k} (raw, every {peer_step}th scan)"] = _errors(p[sub], txy[sub])
        for k, e in errs.items():
            st_all = _stats(e)
            test_e = e[is_test] if e.size == len(is_test) else e[is_test[sub]]
            rows.append({"room": room, "method": k, **st_all,
                         "test_rms": _stats(test_e).get("rms", np.nan),
                         "test_p95": _stats(test_e).get("p95", np.nan)})
        figs[room] = {k: v for k, v in errs.items() if "every" not in k}
        sec.summary[f"wifi_{room}"] = {
            # (named for what it is: the key said default_rms, and the default `locate`
            # is the section s05's -- the report review)
            "huber_calibrated_rms": float(_stats(errs["huber (calibrated)"])["rms"]),
            "huber_calibrated_p95": float(_stats(errs["huber (calibrated)"])["p95"]),
            "issue_best_peer_rms": min(ISSUE_WIFI[room].values()),
            "scipy_us_per_fix": peer_us,
            "source": full.source.kind,
        }
    tab = pd.DataFrame(rows)
    tab.to_csv(ctx.out_dir / "seed000_wifi_rtt.csv", index=False)
    ref = "; ".join(f"{r}: " + ", ".join(f"{k} {v}" for k, v in d.items())
                    for r, d in ISSUE_WIFI.items())
    sec.text(
        "Real WiFi RTT: `wifi-rtt-rss`, every scan of the train and test files (one fix per "
        "scan). Per-AP range bias and scale (robust Huber fit) and per-AP noise (MAD of the "
        "calibrated residuals) come from the train files only; `test_*` columns are the "
        "test scans alone. Peers: scipy `least_squares` (loss soft_l1 / huber, f_scale 1) "
        "per scan from the LS start, on a subsample of scans. The issue's figures for the "
        f"standard methods (2-D RMS, all scans): {ref}."
    )
    sec.table("Real WiFi RTT (wifi-rtt-rss): horizontal error per room, metres", tab)
    for room, curves in figs.items():
        fig = f"seed000_wifi_{room}_cdf.png"
        _cdf_plot(ctx.out_dir / fig, curves, f"wifi-rtt-rss {room}: error CDF",
                  xmax=15 if room == "corridor" else 5)
        sec.figure(f"wifi-rtt-rss {room}: error CDF per method", fig)


def run(ctx: Context) -> Section:
    sec = Section(TITLE)
    _table1(ctx, sec)
    _ble(ctx, sec)
    _wifi(ctx, sec)
    return sec
