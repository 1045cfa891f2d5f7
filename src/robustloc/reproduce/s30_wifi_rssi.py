"""Seed 002: WiFi positioning with a robust Kalman filter on RSSI (Tables 1-3, Fig. 5).

Simulation (``wifi-room``, the paper's room and APs): RSSI statistics in the form of Table 1,
path-loss fits, and the Table 3 summary -- static mean point error and RMS of X and Y,
walking mean point error -- for the raw attenuation model, the plain Kalman filter and the
robust filter, beside the paper's numbers.  Real data: the BLE tracks of ``ble-tetam``
and the RSS of ``wifi-rtt-rss`` positioned from raw and from filtered RSSI.

Positioning is the same for every variant: distances from the attenuation-factor model
(eq. (5)) and Gauss-Newton trilateration on them
(:class:`robustloc.estimators.ranging.Locator`, method ``nls``, range domain); only the RSSI
fed to it changes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.reproduce import Context, Section

TITLE = "Seed 002: WiFi RSSI statistics, attenuation-factor model and robust Kalman filter"
ORDER = 30

PAPER = {
    "static_robust": (0.544, 0.363, 0.406),
    "static_raw": (0.871, 0.636, 0.598),
    "walk_robust": 1.406,
    "walk_raw": 5.383,
}
PAPER_TABLE1 = pd.DataFrame({
    "distance_m": [1, 2, 3, 4, 5, 6, 7, 8],
    "mean": [-29.87, -44.25, -44.03, -48.67, -45.94, -51.48, -55.21, -59.97],
    "variance": [1.07, 1.87, 1.45, 1.09, 0.74, 2.18, 2.11, 2.33],
    "skewness": [-3.49, 0.52, -0.36, -1.02, -0.19, 0.08, -0.61, 0.67],
    "kurtosis": [17.56, 4.86, 2.54, 4.09, 3.31, 2.28, 2.98, 6.40],
})


# ---------------------------------------------------------------------------------------
# shared helpers
# ---------------------------------------------------------------------------------------


def _filters(sigma_rssi_db: float, static: bool = False) -> dict[str, object]:
    """Plain and robust filters; ``static``: the receiver is known not to move (``v = 0``,
    no acceleration: the filter becomes a (robust) running mean with a slow power walk),
    else the walking tuning (``sigma_a = 0.5 m/s^2``, prior speed std 1 m/s)."""
    from robustloc.filters.rssi import RobustRssiFilter

    kw = (dict(sigma_accel_mps2=0.0, init_speed_std_mps=0.0) if static
          else dict(sigma_accel_mps2=0.5, init_speed_std_mps=1.0))
    return {
        "plain KF": RobustRssiFilter(robust=False, sigma_rssi_db=sigma_rssi_db, **kw),
        "robust KF (eq. 14)": RobustRssiFilter(sigma_rssi_db=sigma_rssi_db, **kw),
    }


def _filtered_variants(meas: pd.DataFrame, anchors: pd.DataFrame, sigma_rssi_db: float,
                       static_tags: np.ndarray) -> dict[str, pd.DataFrame]:
    """Raw and filtered copies of ``meas``: static tags with the static tuning, others
    with the walking tuning."""
    from robustloc.filters.rssi import filter_measurements

    is_static = meas["tag"].isin(static_tags).to_numpy()
    out = {"raw": meas}
    fs, fw = _filters(sigma_rssi_db, static=True), _filters(sigma_rssi_db, static=False)
    for name in fs:
        parts = []
        if is_static.any():
            parts.append(filter_measurements(meas[is_static], anchors, fs[name]).frame)
        if (~is_static).any():
            parts.append(filter_measurements(meas[~is_static], anchors, fw[name]).frame)
        out[name] = pd.concat(parts).loc[meas.index]
    return out


def _locate(anchors: pd.DataFrame, values: np.ndarray, height_offset=None) -> np.ndarray:
    """Positions ``(N, 2)`` from RSSI ``(N, m)``: model distances + Gauss-Newton."""
    from robustloc.estimators.ranging import Locator
    from robustloc.models.pathloss import log_distance_arrays

    A, n = log_distance_arrays(anchors)
    sol = Locator(method="nls", domain="range").solve(
        anchors[["x", "y"]].to_numpy(float), values, kind="rssi", A=A, n=n,
        height_offset=height_offset,
    )
    return sol.position


def _errors(pos: np.ndarray, truth_xy: np.ndarray) -> dict[str, float]:
    ok = np.all(np.isfinite(pos), axis=1)
    d = pos[ok] - truth_xy[ok]
    e = np.hypot(d[:, 0], d[:, 1])
    return {
        "mean_error_m": float(e.mean()) if e.size else float("nan"),
        "median_error_m": float(np.median(e)) if e.size else float("nan"),
        "rms_x_m": float(np.sqrt(np.mean(d[:, 0] ** 2))) if e.size else float("nan"),
        "rms_y_m": float(np.sqrt(np.mean(d[:, 1] ** 2))) if e.size else float("nan"),
        "p90_error_m": float(np.percentile(e, 90)) if e.size else float("nan"),
        "epochs": int(ok.size),
        "fixes": int(ok.sum()),
    }


def _pivot(frame: pd.DataFrame, ids: list[str]):
    from robustloc.io import to_epochs

    return to_epochs(frame[["time", "tag", "anchor", "rssi"]], ids, "rssi")


def _truth_at(ep, truth: pd.DataFrame) -> np.ndarray:
    key = pd.MultiIndex.from_arrays([truth["time"].to_numpy(float), truth["tag"].astype(str)])
    t = truth.set_index(key)
    want = pd.MultiIndex.from_arrays([ep.time, ep.tag.astype(str)])
    return t.loc[want, ["x", "y"]].to_numpy(float)


# ---------------------------------------------------------------------------------------
# simulation: Tables 1 and 3
# ---------------------------------------------------------------------------------------


def _simulation(ctx: Context, sec: Section) -> dict:
    from robustloc.eval.rssi_stats import RssiStatistics
    from robustloc.sim.wifi_room import WifiRoomConfig, generate

    cfg = WifiRoomConfig()
    data = generate(cfg, ctx.seed)
    anchors = data.anchors
    ids = list(anchors["anchor"])
    meas = data.measurements

    # Table 1 structure: static RSSI at AP2 (the paper's example AP) at 1..8 m (survey)
    sv = data.survey[data.survey["anchor"] == "AP2"].copy()
    sv["tag"] = [f"d{d:g}" for d in sv["distance"]]
    sv["time"] = sv.groupby("tag").cumcount().astype(float)
    ap2 = anchors.set_index("anchor").loc["AP2"]
    truth1 = sv.groupby("tag", as_index=False)["distance"].first()
    truth1 = pd.DataFrame({"time": 0.0, "tag": truth1["tag"], "x": ap2["x"] + truth1["distance"],
                           "y": ap2["y"]})
    st = RssiStatistics(max_lag=20, min_samples=5).compute(sv, anchors, truth1)
    t1 = st.per_bin[["distance_m", "mean", "variance", "skewness", "kurtosis",
                     "decorrelation_lag"]].copy()
    t1 = t1.merge(PAPER_TABLE1.add_prefix("paper_").rename(
        columns={"paper_distance_m": "distance_m"}), on="distance_m", how="left")
    sec.table("Table 1 structure, simulated AP2 (50 static scans per distance) beside the "
              "paper's AP", t1.set_index("distance_m"))
    rp = meas[meas["tag"] != "walk"]
    st_rp = RssiStatistics(max_lag=20).compute(rp, anchors, data.truth)
    s1 = st_rp.summary()

    # Table 3: static and walking errors
    out_rows = []
    static_tags = np.array(sorted(set(meas["tag"]) - {"walk"}))
    variants = _filtered_variants(meas, anchors, 2.0, static_tags)
    variants["raw attenuation model"] = variants.pop("raw")
    pos_walk = {}
    walk_truth = None
    last_t = meas.loc[meas["tag"] != "walk", "time"].max()
    for name, frame in variants.items():
        ep = _pivot(frame, ids)
        txy = _truth_at(ep, data.truth)
        pos = _locate(anchors, ep.values)
        walk = ep.tag == "walk"
        last = ~walk & (ep.time == last_t)
        es, ew = _errors(pos[~walk], txy[~walk]), _errors(pos[walk], txy[walk])
        el = _errors(pos[last], txy[last])
        out_rows.append({"method": name, "static_mean_m": es["mean_error_m"],
                         "static_rms_x_m": es["rms_x_m"], "static_rms_y_m": es["rms_y_m"],
                         "static_last_scan_mean_m": el["mean_error_m"],
                         "walk_mean_m": ew["mean_error_m"], "walk_p90_m": ew["p90_error_m"]})
        pos_walk[name] = pos[walk]
        walk_truth = txy[walk]
    # static baseline that needs no filter: the mean of the point's scans
    mean_rp = rp.groupby(["tag", "anchor"], as_index=False)["rssi"].mean()
    mean_rp["time"] = 0.0
    ep = _pivot(mean_rp, ids)
    tr = data.truth.groupby("tag", as_index=False)[["x", "y"]].first()
    tr["time"] = 0.0
    es = _errors(_locate(anchors, ep.values), _truth_at(ep, tr))
    out_rows.append({"method": "mean of the point's scans (static only)",
                     "static_mean_m": np.nan, "static_rms_x_m": np.nan,
                     "static_rms_y_m": np.nan, "static_last_scan_mean_m": es["mean_error_m"],
                     "walk_mean_m": np.nan, "walk_p90_m": np.nan})
    for label, key, walk_key in (("paper: raw attenuation model", "static_raw", "walk_raw"),
                                 ("paper: robust filter", "static_robust", "walk_robust")):
        m_, x_, y_ = PAPER[key]
        out_rows.append({"method": label, "static_mean_m": m_, "static_rms_x_m": x_,
                         "static_rms_y_m": y_, "static_last_scan_mean_m": np.nan,
                         "walk_mean_m": PAPER[walk_key], "walk_p90_m": np.nan})
    t3 = pd.DataFrame(out_rows).set_index("method")
    sec.table(f"Table 3 summary (simulated wifi-room, seed {ctx.seed}): static = every scan "
              "of the 20 points (filters with the static tuning v = 0), last scan = the "
              "30th scan of each point, walk = every epoch (walking tuning); metres", t3)
    t3.to_csv(ctx.out_dir / "s30_table3_sim.csv")

    # what temporal filtering can gain on the walk depends on how correlated the noise is
    rows_phi = []
    for phi in () if ctx.quick else (0.0, 0.5, 0.88):
        dphi = generate(WifiRoomConfig(ar_phi=phi, samples_per_point=1), ctx.seed)
        mw = dphi.measurements[dphi.measurements["tag"] == "walk"]
        vs = _filtered_variants(mw, anchors, 2.0, np.array([], dtype=object))
        row = {"ar_phi": phi}
        for name, frame in vs.items():
            ep = _pivot(frame, ids)
            row[name] = _errors(_locate(anchors, ep.values),
                                _truth_at(ep, dphi.truth))["mean_error_m"]
        rows_phi.append(row)
    if rows_phi:
        tphi = pd.DataFrame(rows_phi).set_index("ar_phi")
        sec.table("Simulated walk: mean error (m) against the AR(1) coefficient of the noise "
                  "(0 = white; 0.88 = decorrelated after about 8 scans as the paper "
                  "measured)", tphi)

    _plot_walk(ctx.out_dir / "s30_walk.png", walk_truth, pos_walk)
    sec.figure("Simulated walk: truth and positions from raw and filtered RSSI",
               "s30_walk.png")
    _plot_fig5(ctx.out_dir / "s30_rssi_walk.png", meas, variants, "AP1")
    sec.figure("RSSI of AP1 on the walk (cf. the paper's Fig. 5): raw, plain and robust "
               "filter; environment change at epoch 50 (8 dB for 20 epochs)",
               "s30_rssi_walk.png")
    raw = t3.loc["raw attenuation model"]
    rob = t3.loc["robust KF (eq. 14)"]
    pla = t3.loc["plain KF"]
    sec.text(
        f"Simulated RSSI noise (static points, residuals about each distance bin): median "
        f"skewness {s1['median_skewness']:.2f}, median kurtosis {s1['median_kurtosis']:.2f}, "
        f"decorrelation lag {s1['median_decorrelation_lag']:.0f} scans, variance-distance "
        f"correlation {s1['variance_distance_corr']:.2f} (paper: left-skewed, kurtosis != 3, "
        f"lag 8, correlation 0.578).\n\n"
        f"Static: robust filter {rob['static_mean_m']:.3f} m over every scan and "
        f"{rob['static_last_scan_mean_m']:.3f} m at the last scan, raw "
        f"{raw['static_mean_m']:.3f} m (paper 0.544 vs 0.871); the plain filter "
        f"{pla['static_mean_m']:.3f} / {pla['static_last_scan_mean_m']:.3f} m.  On a static "
        "point the filter is a running mean; the robust one drops the fades (left tail) "
        "and so beats the plain mean of the scans.\n\n"
        f"Walking: robust {rob['walk_mean_m']:.3f} m, plain {pla['walk_mean_m']:.3f} m, raw "
        f"{raw['walk_mean_m']:.3f} m (paper 1.406 vs 5.383).  Here filtering gains nothing: "
        "the walker moves about 4 m within the noise correlation time, so a filter cannot "
        "average the correlated noise without lagging the signal (see the AR table: the gain "
        "appears only when the noise is closer to white), and the 8 dB environment drops "
        "last 20 epochs, longer than the re-lock (8), so they are followed, not rejected.  "
        "Our raw walking error is far below the paper's 5.4 m: the paper's hand-held log "
        "had much larger disturbances than this documented noise model."
    )
    return {
        "sim_static_raw_m": raw["static_mean_m"], "sim_static_robust_m": rob["static_mean_m"],
        "sim_static_plain_m": pla["static_mean_m"],
        "sim_static_last_raw_m": raw["static_last_scan_mean_m"],
        "sim_static_last_robust_m": rob["static_last_scan_mean_m"],
        "sim_walk_raw_m": raw["walk_mean_m"], "sim_walk_robust_m": rob["walk_mean_m"],
        "sim_walk_plain_m": pla["walk_mean_m"],
        "sim_median_skewness": s1["median_skewness"],
        "sim_median_kurtosis": s1["median_kurtosis"],
        "sim_variance_distance_corr": s1["variance_distance_corr"],
        "survey": data.survey, "anchors": anchors,
    }


def _plot_walk(path: Path, truth: np.ndarray, pos: dict[str, np.ndarray]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 5.2))
    ax.plot(truth[:, 0], truth[:, 1], "k-", lw=2, label="truth")
    styles = {"raw attenuation model": ("0.6", "."), "plain KF": ("tab:blue", "-"),
              "robust KF (eq. 14)": ("tab:red", "-")}
    for name, p in pos.items():
        c, ls = styles.get(name, ("g", "-"))
        ax.plot(p[:, 0], p[:, 1], ls, color=c, lw=0.8, ms=3, label=name)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _plot_fig5(path: Path, meas: pd.DataFrame, variants: dict[str, pd.DataFrame],
               anchor: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 3.4))
    for name, frame in variants.items():
        sel = (frame["tag"] == "walk") & (frame["anchor"] == anchor)
        style = {"raw attenuation model": dict(color="0.6", lw=0.8)}.get(name, dict(lw=1.2))
        ax.plot(np.arange(sel.sum()), frame.loc[sel, "rssi"].to_numpy(), label=name, **style)
    ax.set_xlabel("epoch")
    ax.set_ylabel("RSSI (dBm)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


# ---------------------------------------------------------------------------------------
# path-loss fits: attenuation factor vs log-distance vs Friis
# ---------------------------------------------------------------------------------------


def _fits(survey: pd.DataFrame, label: str) -> pd.DataFrame:
    """Residual std per AP of the three path-loss models on one survey.

    ``p0`` at ``d0 = 1 m`` is the survey mean near 1 m when there are such rows; else
    (real surveys rarely go that close) the pooled log-distance ``A`` (the power the
    fitted line predicts at 1 m), said in the label.
    """
    from robustloc.errors import InputError
    from robustloc.models.calibration import calibrate_pathloss

    p0 = None
    try:
        calibrate_pathloss(survey, "attenuation-factor")
    except InputError:
        pooled = calibrate_pathloss(survey, "log-distance").table.set_index("anchor")
        p0 = float(pooled.loc["*pooled*", "A"])
        label += f" (p0 = {p0:.1f} dBm from the pooled line)"
    out = None
    for model, col in (("attenuation-factor", "attenuation_factor_std_db"),
                       ("log-distance", "log_distance_std_db"), ("friis", "friis_std_db")):
        kw = {"p0": p0} if model == "attenuation-factor" and p0 is not None else {}
        t = calibrate_pathloss(survey, model, **kw).table.set_index("anchor")
        keep = t[["residual_std"]].rename(columns={"residual_std": col})
        if model == "attenuation-factor":
            keep = t[["p0", "gamma", "faf"]].join(keep)
        out = keep if out is None else out.join(keep)
    out.insert(0, "data", label)
    return out


def _fit_section(ctx: Context, sec: Section, sim: dict, wifi: dict[str, object],
                 ble_survey: pd.DataFrame | None) -> None:
    tables = [_fits(sim["survey"], "sim wifi-room survey")]
    for room, train in wifi.items():
        tables.append(_fits(train, f"wifi-rtt-rss {room} (train)"))
    if ble_survey is not None:
        tables.append(_fits(ble_survey, "ble-tetam histogram means"))
    t = pd.concat(tables)
    sec.table("Path-loss fits per AP: residual std (dB) of the attenuation-factor model "
              "(eq. 5, p0 fixed at 1 m, gamma and FAF fitted), log-distance (A, n fitted) and "
              "Friis (exponent 2, p0 fitted); paper's example AP: gamma 2.275, FAF -1.076, "
              "p0 -29 dBm, residual std 1.59 dB", t)
    t.to_csv(ctx.out_dir / "s30_pathloss_fits.csv")
    sec.text(
        "With p0 pinned to the reference power the attenuation-factor model has two free "
        "parameters (gamma, FAF) on the same regressor lg(d) as the log-distance model "
        "(A, n): the two fits are the same straight line, so their residuals are equal "
        "(FAF only re-labels the intercept).  Friis fixes the exponent at 2 and drifts from "
        "the data where the true exponent differs, as the paper says."
    )


# ---------------------------------------------------------------------------------------
# real data
# ---------------------------------------------------------------------------------------


def _ble(ctx: Context, sec: Section) -> dict:
    from robustloc.datasets import ble_tetam
    from robustloc.eval.rssi_stats import RssiStatistics
    from robustloc.models.calibration import calibrate_pathloss

    src = ble_tetam.resolve(ctx.data_dir)
    ctx.note(src)
    anchors = ble_tetam.load_anchors(ctx.data_dir)
    survey = ble_tetam.load_survey_means(ctx.data_dir)
    cal = calibrate_pathloss(survey, "log-distance")
    anchors = cal.apply_to_anchors(anchors)
    res_sd = cal.table["residual_std"].to_numpy(float)
    pooled = (cal.table["calib_source"] == "pooled").to_numpy()
    tag_height_m = 1.75  # beacon carried at about this height (truth z 1.6-1.9 m)
    hoff = anchors["z"].to_numpy(float) - tag_height_m
    ctx.note(ble_tetam.tracks_note(ctx.data_dir))
    tracks = ble_tetam.list_tracks(ctx.data_dir)
    if ctx.quick:
        tracks = tracks[:1]
    rows, all_samples, all_truth = [], [], []
    for name in tracks:
        meas, truth = ble_tetam.load_track(name, ctx.data_dir, window_s=None)
        all_samples.append(meas)
        all_truth.append(truth)
        variants = _filtered_variants(meas, anchors, 4.0, np.array([], dtype=object))
        variants["raw (1 s window mean)"] = variants.pop("raw")
        for vname, e in _window_errors(meas, truth, variants, anchors, hoff, 1.0).items():
            rows.append({"track": name, "method": vname, **e})
    t = pd.DataFrame(rows)
    piv = t.pivot(index="track", columns="method", values="mean_error_m")
    sec.table(f"ble-tetam ({src.kind} data): mean horizontal error (m) per track, 12 "
              "receivers, log-distance per sensor fitted on the histogram means, 1 s epochs",
              piv)
    t.to_csv(ctx.out_dir / "s30_ble_tracks.csv", index=False)
    overall = t.groupby("method")[["mean_error_m", "median_error_m", "p90_error_m"]].mean()
    sec.table("ble-tetam, averaged over the tracks", overall)

    # statistics of real BLE RSSI (Table 1 structure) on the labelled tracks
    samples = pd.concat(all_samples, ignore_index=True)
    truth = pd.concat(all_truth, ignore_index=True)
    st = RssiStatistics(max_lag=20, bin_width_m=1.0, min_samples=20).compute(
        samples, anchors, truth)
    s = st.summary()
    cols = ["anchor", "n", "resid_variance", "resid_skewness", "resid_kurtosis",
            "decorrelation_lag", "normaltest_p"]
    sec.table("ble-tetam RSSI statistics per receiver (track samples, residuals about "
              "1 m distance bins; lag in samples of that receiver)",
              st.per_anchor[cols].set_index("anchor"))
    raw_e = overall.loc["raw (1 s window mean)", "mean_error_m"]
    rob_e = overall.loc["robust KF (eq. 14)", "mean_error_m"]
    pla_e = overall.loc["plain KF", "mean_error_m"]
    sec.text(
        f"Real BLE RSSI: median residual skewness {s['median_skewness']:.2f}, kurtosis "
        f"{s['median_kurtosis']:.2f}, normality rejected at 5 % for "
        f"{100 * s['share_anchors_normal_rejected_5pct']:.0f} % of receivers, decorrelation "
        f"lag {s['median_decorrelation_lag']:.0f} samples, variance-distance correlation "
        f"{s['variance_distance_corr']:.2f}.  Positioning: robust filter {rob_e:.2f} m, plain "
        f"filter {pla_e:.2f} m, raw window means {raw_e:.2f} m (filtering gains "
        f"{100 * (raw_e - rob_e) / raw_e:.0f} %).  The path-loss model itself misfits the "
        f"survey by {np.median(res_sd[~pooled]):.1f} dB per receiver (median residual std"
        + (f"; {res_sd[pooled][0]:.1f} dB pooled" if pooled.any() else "")
        + "; see the fits table): that bias, not sample "
        "noise, dominates the BLE error, so filtering the noise can only gain a little here."
    )
    static = _ble_static(ctx, sec, anchors, hoff)
    return {"ble_raw_m": raw_e, "ble_robust_m": rob_e, "ble_plain_m": pla_e, **static,
            "ble_source": src.kind, "ble_tracks": len(tracks),
            "ble_median_skewness": s["median_skewness"],
            "ble_median_kurtosis": s["median_kurtosis"], "ble_survey": survey}


def _window_errors(meas: pd.DataFrame, truth: pd.DataFrame, variants: dict[str, pd.DataFrame],
                   anchors: pd.DataFrame, hoff: np.ndarray, window_s: float) -> dict[str, dict]:
    """Errors of 1-window epochs: raw variants averaged, filtered ones take the last value."""
    ids = list(anchors["anchor"])
    w = np.floor(meas["time"].to_numpy() / window_s)
    tr = truth.assign(win=np.floor(truth["time"].to_numpy() / window_s)).groupby("win")[
        ["x", "y"]].mean()
    out = {}
    for vname, frame in variants.items():
        agg = "mean" if vname.startswith("raw") else "last"
        g = frame.assign(win=w).groupby(["win", "anchor"], as_index=False)["rssi"].agg(agg)
        g["time"] = g["win"]
        g["tag"] = str(meas["tag"].iloc[0])
        ep = _pivot(g, ids)
        out[vname] = _errors(_locate(anchors, ep.values, height_offset=hoff),
                             tr.reindex(ep.time).to_numpy(float))
    return out


def _ble_static(ctx: Context, sec: Section, anchors: pd.DataFrame, hoff: np.ndarray) -> dict:
    """The 30-minute static logs of ble-tetam (full data only): Table 1 structure on real
    BLE RSSI and static positioning from raw and filtered RSSI."""
    from robustloc.datasets import ble_tetam
    from robustloc.eval.rssi_stats import RssiStatistics, plot_autocorrelation

    points = ble_tetam.list_static_points(ctx.data_dir)
    if not points or ctx.quick:
        sec.text("ble-tetam static logs: not run (" + ("quick mode" if points else
                 "only in the full data set; the shipped excerpt has no raw static logs")
                 + ").")
        return {}
    rows, samples, truths = [], [], []
    for pt in points:
        meas, truth = ble_tetam.load_static(pt, ctx.data_dir, window_s=None)
        samples.append(meas)
        truths.append(truth)
        variants = _filtered_variants(meas, anchors, 4.0, meas["tag"].unique())
        variants["raw (1 s window mean)"] = variants.pop("raw")
        errs = _window_errors(meas, truth, variants, anchors, hoff, 1.0)
        whole = meas.groupby("anchor", as_index=False)["rssi"].mean().assign(
            time=0.0, tag="p")
        ep = _pivot(whole, list(anchors["anchor"]))
        xy = truth[["x", "y"]].to_numpy(float)[:1]
        e_mean = _errors(_locate(anchors, ep.values, height_offset=hoff), xy)
        row = {"point": pt, **{k: v["mean_error_m"] for k, v in errs.items()},
               "mean of the whole log": e_mean["mean_error_m"]}
        rows.append(row)
    t = pd.DataFrame(rows).set_index("point")
    sec.table("ble-tetam static points (30-minute logs, 12 receivers): mean error (m) of "
              "1 s epochs from raw and filtered RSSI (static tuning), and of one fix from "
              "the mean of the whole log", t)
    st = RssiStatistics(max_lag=40, bin_width_m=0.5, min_samples=100).compute(
        pd.concat(samples, ignore_index=True), anchors, pd.concat(truths, ignore_index=True))
    pb = st.per_bin.sort_values("distance_m")
    show = pb[["anchor", "distance_m", "n", "mean", "variance", "skewness", "kurtosis",
               "decorrelation_lag"]]
    sec.table("Table 1 structure on real BLE RSSI: the static logs per receiver and distance "
              "(0.5 m bins; lag in samples of that receiver, about 2 per second)",
              show.set_index(["anchor", "distance_m"]))
    pb.to_csv(ctx.out_dir / "s30_ble_static_table1.csv", index=False)
    plot_autocorrelation(st, ctx.out_dir / "s30_ble_static_acf.png")
    sec.figure("Autocorrelation of the static BLE RSSI per receiver (dashed: 0.2)",
               "s30_ble_static_acf.png")
    s = st.summary()
    left = float((pb["skewness"] < 0).mean())
    sec.text(
        f"Real static BLE RSSI: {100 * left:.0f} % of the receiver-distance cells are "
        f"left-skewed, median kurtosis {pb['kurtosis'].median():.2f} (3 for normal), "
        f"normality rejected at 5 % in {100 * (pb['normaltest_p'] < 0.05).mean():.0f} % of "
        f"cells, median decorrelation lag {pb['decorrelation_lag'].median():.0f} samples, "
        f"variance-distance correlation {s['variance_distance_corr']:.2f} (paper: mostly "
        "left-skewed, heavy-tailed, lag 8, correlation 0.578).  Unlike the paper's WiFi "
        "RSSI, most cells have kurtosis well below 3: the values form two or three clusters "
        "several dB apart (e.g. sensor20 at the first point: -77 and -70 dBm), consecutive "
        "samples alternating between them -- BLE advertises on three channels whose gains "
        "differ -- which is also why the autocorrelation is gone after 1-2 samples.  Those "
        "modes are not outliers: the adaptive scale grows to cover them, so the robust and "
        "the plain filter agree, and both roughly reach the whole-log mean, well below the "
        "error of raw 1 s windows."
    )
    return {"ble_static_raw_m": float(t["raw (1 s window mean)"].mean()),
            "ble_static_robust_m": float(t["robust KF (eq. 14)"].mean()),
            "ble_static_plain_m": float(t["plain KF"].mean()),
            "ble_static_share_left_skewed": left,
            "ble_static_median_kurtosis": float(pb["kurtosis"].median()),
            "ble_static_median_lag": float(pb["decorrelation_lag"].median()),
            "ble_static_variance_distance_corr": s["variance_distance_corr"]}


def _wifi(ctx: Context, sec: Section) -> tuple[dict, dict]:
    from robustloc.datasets import wifi_rtt
    from robustloc.models.calibration import calibrate_pathloss, survey_from_positions

    rooms = ("lecture_theatre",) if ctx.quick else wifi_rtt.ROOMS
    rows, trains = [], {}
    kind = None
    for room in rooms:
        train = wifi_rtt.load_room(room, "train", ctx.data_dir)
        test = wifi_rtt.load_room(room, "test", ctx.data_dir)
        kind = train.source.kind
        ctx.note(train.source)
        sv = survey_from_positions(train.rssi, train.truth, train.anchors)
        trains[room] = sv
        # p0 at 1 m is not surveyed: the attenuation-factor fit takes its own p0 = A of the
        # log-distance fit, so use the log-distance parameters (same line) for positioning
        cal = calibrate_pathloss(sv, "log-distance")
        anchors = cal.apply_to_anchors(train.anchors)
        ids = list(anchors["anchor"])
        # one static series per reference point: links are (rp, anchor), scans 1 s apart
        meas = test.rssi.assign(tag=test.rssi["rp"].astype(str))
        truth = test.truth.assign(tag=test.truth["rp"].astype(str))
        variants = _filtered_variants(meas, anchors, 3.0, meas["tag"].unique())
        variants["raw (every scan)"] = variants.pop("raw")
        for vname, frame in variants.items():
            ep = _pivot(frame, ids)
            pos = _locate(anchors, ep.values)
            e = _errors(pos, _truth_at(ep, truth))
            rows.append({"room": room, "method": vname, **e})
        mean_rp = meas.groupby(["tag", "anchor"], as_index=False)["rssi"].mean()
        mean_rp["time"] = 0.0
        ep = _pivot(mean_rp, ids)
        tr = truth.groupby("tag", as_index=False)[["x", "y"]].first().assign(time=0.0)
        e = _errors(_locate(anchors, ep.values), _truth_at(ep, tr))
        rows.append({"room": room, "method": "mean of the point's scans", **e})
    t = pd.DataFrame(rows)
    t.to_csv(ctx.out_dir / "s30_wifi_rss.csv", index=False)
    piv = t.pivot(index="room", columns="method", values="mean_error_m")
    sec.table(f"wifi-rtt-rss RSS ({kind} data): mean error (m) on the test points, "
              "log-distance per AP calibrated on the train points", piv)
    gain = (piv["raw (every scan)"] - piv["robust KF (eq. 14)"]).to_dict()
    sec.text(
        "wifi-rtt-rss: the test points are static, 60 scans each; the filter runs over each "
        "point's scans.  Gain of the robust filter over raw scans (m): "
        + ", ".join(f"{k} {v:+.2f}" for k, v in gain.items())
        + ".  The remaining error is the path-loss model's misfit (walls, NLOS: several dB "
        "per AP that no filter over time can remove); the per-point mean is about what "
        "a filter can reach on static data here."
    )
    summ: dict = {f"wifi_{r}_{k}": float(piv.loc[r, m]) for r in piv.index
                  for k, m in (("raw_m", "raw (every scan)"),
                               ("robust_m", "robust KF (eq. 14)"))}
    summ["wifi_source"] = kind
    return summ, trains


def _gain_verdict(ratios: list[float], paper_ratio: float) -> str:
    """The robust filter's error ratios to raw (ours, one per data set) against the
    paper's: the change of the error in % and whether the gain is as large as the
    paper's."""
    ch = sorted(100 * (r - 1) for r in ratios)
    lo, hi = f"{ch[0]:+.0f}", f"{ch[-1]:+.0f}"
    ours = f"{lo} %" if lo == hi else f"{lo} to {hi} %"
    same = all(r <= paper_ratio for r in ratios)
    return (f"error {ours} (paper's {100 * (paper_ratio - 1):+.0f} %): "
            + ("a gain as large as the paper's" if same else "a smaller gain than the paper's"))


def _headlines(sec: Section, b: dict, w: dict) -> None:
    """Seed 002's real-data headlines for the report's summary (its simulated Table 3 rows
    are s60_tracks'): the paper's real walk and room beside ours on real BLE tracks and
    real WiFi RSS points.  No peer filter runs on these (FilterPy is not run here)."""
    from robustloc.reproduce import data_label, fmt_num

    walk = PAPER["walk_robust"] / PAPER["walk_raw"]
    r = b["ble_robust_m"] / b["ble_raw_m"]
    sec.headline(
        "002", f"ble-tetam tracks, real BLE {data_label(b['ble_source'])}: mean error, raw "
        "1 s means -> robust filter (m)",
        f"{PAPER['walk_raw']:.2f} -> {PAPER['walk_robust']:.2f} ({walk:.2f}x; its WiFi walk)",
        f"{fmt_num(b['ble_raw_m'])} -> {fmt_num(b['ble_robust_m'])} ({fmt_num(r)}x; plain "
        f"KF {fmt_num(b['ble_plain_m'])})", "- (no peer filter run)", _gain_verdict([r], walk))
    rooms = sorted(k[len("wifi_"):-len("_raw_m")] for k in w if k.endswith("_raw_m"))
    static = PAPER["static_robust"][0] / PAPER["static_raw"][0]
    ratios = [w[f"wifi_{m}_robust_m"] / w[f"wifi_{m}_raw_m"] for m in rooms]
    sec.headline(
        "002", f"wifi-rtt-rss RSS static test points, real WiFi {data_label(w['wifi_source'])}"
        f": mean error, raw scans -> robust filter (m), {'/'.join(rooms)}",
        f"{PAPER['static_raw'][0]:.3f} -> {PAPER['static_robust'][0]:.3f} ({static:.2f}x; "
        "its room)",
        " / ".join(f"{fmt_num(w[f'wifi_{m}_raw_m'])} -> {fmt_num(w[f'wifi_{m}_robust_m'])}"
                   for m in rooms), "- (no peer filter run)", _gain_verdict(ratios, static))


def run(ctx: Context) -> Section:
    sec = Section(TITLE)
    sec.text(
        "Seed 002 (Li & Huang 2016): attenuation-factor path loss (eq. 5), RSSI statistics "
        "(Table 1), robust M-estimation Kalman filter with the asymmetric equivalent "
        "weight of eq. (14) (K0 = 2, K1 = C = 3 adaptive standard errors) on the state "
        "[P_r, d, v] of eq. (15), and static/walking positioning (Table 3).  Positions are "
        "Gauss-Newton trilateration on model distances for every variant."
    )
    summary: dict = {}
    sim = _simulation(ctx, sec)
    # (a data set missing from --data is the shipped excerpt's; a damaged one is the
    # user's error, FILE:LINE and exit 2, not a section that says "skipped" and exit 0:
    # the reproduce review)
    b = _ble(ctx, sec)
    ble_survey = b.pop("ble_survey")
    summary.update(b)
    w, wifi_train = _wifi(ctx, sec)
    summary.update(w)
    _headlines(sec, b, w)
    _fit_section(ctx, sec, sim, wifi_train, ble_survey)
    summary.update({k: v for k, v in sim.items() if k not in ("survey", "anchors")})
    sec.summary.update({k: (float(v) if isinstance(v, (int, float, np.floating)) else v)
                        for k, v in summary.items()})
    return sec
