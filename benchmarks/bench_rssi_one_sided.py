"""One-sided data snooping of RSSI in the dB domain, measured (not adopted).

A body, a wall or a fade only ever weakens a link: the one-sided error of seed 002's
asymmetric weight.  ``auto`` fits RSSI as ranges (``sigma_d = d ln10 sigma_dB / (10 n)``
of the observed range), where a weakened link reads long and its own ``sigma_d`` grows
with it: its standardized residual is at most ``10 n / (ln10 sigma_dB)`` whatever the
attenuation, and the fix's test seldom sees it.  In dB the same link stands out (on seed
000's scheme 2 the blocked links that are still heard sit 4.8 / 8.7 / 13.1 dB below the
model at the truth, 10th / 50th / 90th percentile, against a clear link's 95th
percentile of 3.6 dB).  The candidate measured here keeps the range-domain Gauss-Newton
fix (``nls``) and snoops in dB: the heard link whose RSSI lies furthest *below* the
model at the fix, as a w-test ``w_i = e_i / (s sqrt(r_i))`` (``e_i`` model minus
observed, dB; ``r_i`` its redundancy number in the dB domain; ``s`` the log's MAD of the
dB residuals at the ``nls`` fixes, per anchor on the real log), is left out when ``w_i``
exceeds the one-sided normal quantile ``N(1 - alpha)``, the epoch re-solved, and so on
while two degrees of freedom remain (at most four links).  ``two-sided`` tests ``|w_i|``
instead (a control: the one-sidedness is what helps).

Measured 2026-12-07 (``python benchmarks/bench_rssi_one_sided.py``; the simulation: mean
2-D error over S1-S3, seeds 1-10; ble-tetam: RMS over its five tracks, ``../shared/data``):

    candidate              scheme 1   scheme 2   ble-tetam RMS (real)
    nls                     1.032      1.798      2.889
    one-sided, a = 0.001    1.010      1.645      2.914
    one-sided, a = 0.01     1.004      1.600      2.924
    one-sided, a = 0.05     0.999      1.551      2.969
    two-sided, a = 0.01     1.117      1.701      (not run)
    oracle (scheme 2)                  1.462

wifi-rtt-rss RSS (real, every test scan, path loss from the train files), mean / RMS:

    room               nls            a = 0.001      a = 0.01       a = 0.05
    lecture theatre    3.167 / 3.784  3.141 / 3.706  3.145 / 3.687  3.174 / 3.697
    office             1.757 / 2.118  1.755 / 2.112  1.768 / 2.118  1.799 / 2.142
    corridor           4.723 / 5.529  4.816 / 5.510  4.775 / 5.440  4.707 / 5.358

On the simulator it is what issue 10 asks of scheme 2 (0.89x ``nls`` at a = 0.01, seed
000's oracle drops exactly the blocked links: 1.462), and it costs nothing in scheme 1.
On the real logs it is no such gain: ble-tetam's 12 receivers lose 1-3 % (the links it
drops there are not blocked: its RSSI errors are not the simulator's one-sided bursts),
the WiFi rooms move by -3 to +2 % with no level that helps all three.  Real data is the
judge, so ``auto`` keeps the range-domain fix (``docs/limits.md``).

Usage::

    python benchmarks/bench_rssi_one_sided.py [--seeds 10] [--data ../shared/data]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import norm

from robustloc.estimators.ranging import Locator
from robustloc.integrity.bmethod import lambda0
from robustloc.integrity.fixes import protection_levels_local

ALPHAS = (0.001, 0.01, 0.05)


def _db_residuals(xy: np.ndarray, h: np.ndarray, A: np.ndarray, n: np.ndarray,
                  pos: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Model minus observed RSSI (dB; positive: weaker than the model) at the fixes, and
    the dB model's design ``d rssi / d x`` (seed 000 eq. (1))."""
    dxy = pos[:, None, :2] - xy[None]
    d2 = np.maximum(np.sum(dxy**2, axis=2) + h[None] ** 2, 0.01)
    e = (A[None] - 5.0 * n[None] * np.log10(d2)) - v
    J = (-10.0 * n[None, :, None] / np.log(10.0)) * dxy / d2[..., None]
    return e, J


def snoop_db(xy: np.ndarray, values: np.ndarray, A: np.ndarray, n: np.ndarray,
             s_db: np.ndarray, alpha: float, one_sided: bool = True,
             height_offset: np.ndarray | None = None, sigma: object = None,
             max_drop: int = 4) -> np.ndarray:
    """The candidate: ``nls`` fixes with dB data snooping (module docstring)."""
    h = np.zeros(len(A)) if height_offset is None else np.asarray(height_offset, float)
    loc = Locator("nls", sigma=sigma)
    v = np.array(values, dtype=float)
    k = norm.ppf(1 - alpha) if one_sided else norm.ppf(1 - alpha / 2)
    sig = np.broadcast_to(np.asarray(s_db, float), v.shape)
    for it in range(max_drop + 1):
        pos = loc.solve(xy, v, "rssi", A=A, n=n, height_offset=height_offset).position
        if it == max_drop:
            break
        ok = np.all(np.isfinite(pos), axis=1)
        used = np.isfinite(v) & ok[:, None]
        e, J = _db_residuals(xy, h, A, n, np.where(ok[:, None], pos, 0.0), v)
        J = np.where(used[..., None], J, 0.0)
        _, _, r = protection_levels_local(J, sig, used, lambda0(), 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = e / (sig * np.sqrt(r))
        w = np.where(used & (r > 0.05) & np.isfinite(w), w if one_sided else np.abs(w), -np.inf)
        j = np.argmax(w, axis=1)
        i = np.arange(len(j))
        drop = (w[i, j] > k) & (np.isfinite(v).sum(axis=1) - 2 >= 2)
        if not drop.any():
            break
        v[i[drop], j[drop]] = np.nan
    return pos


def _mad(e: np.ndarray, axis: int | None = None) -> np.ndarray:
    med = np.nanmedian(e, axis=axis, keepdims=True)
    return 1.4826 * np.nanmedian(np.abs(e - med), axis=axis)


def corridor(seeds: int) -> pd.DataFrame:
    """Seed 000's corridor, schemes 1 and 2: mean error per seed and candidate."""
    from robustloc.reproduce.s10_ble_ranging import corridor_scheme
    from robustloc.sim import ble_corridor as bc

    rows = []
    for scheme in (1, 2):
        for seed in range(1, seeds + 1):
            sc = corridor_scheme(seed, scheme == 2)
            ep = sc.ep
            truth = np.array([bc.TEST_POINTS[t] for t in ep.tag])

            def err(p: np.ndarray, truth: np.ndarray = truth) -> float:
                return float(np.nanmean(np.hypot(*(p[:, :2] - truth).T)))

            p0 = Locator("nls").solve(sc.xy, ep.values, "rssi", A=sc.A, n=sc.n).position
            e, _ = _db_residuals(sc.xy, np.zeros(len(sc.A)), sc.A, sc.n,
                                 np.nan_to_num(p0), ep.values)
            s = float(_mad(e[np.isfinite(e) & np.isfinite(p0[:, :1])]))
            row = {"scheme": scheme, "seed": seed, "nls": err(p0)}
            for a in ALPHAS:
                row[f"one-sided {a}"] = err(snoop_db(sc.xy, ep.values, sc.A, sc.n, s, a))
            row["two-sided 0.01"] = err(snoop_db(sc.xy, ep.values, sc.A, sc.n, s, 0.01,
                                                 one_sided=False))
            if scheme == 2:  # seed 000's oracle: exactly the blocked links dropped
                bl = sc.fr["blocked"]
                key = pd.MultiIndex.from_arrays([ep.time, ep.tag])
                ri = key.get_indexer(pd.MultiIndex.from_arrays([bl["time"], bl["tag"]]))
                ci = pd.Index(sc.ids).get_indexer(bl["anchor"].astype(str))
                vals = ep.values.copy()
                keep = (ri >= 0) & (ci >= 0)
                vals[ri[keep], ci[keep]] = np.nan
                row["oracle"] = err(Locator("nls").solve(sc.xy, vals, "rssi", A=sc.A,
                                                         n=sc.n).position)
            rows.append(row)
    return pd.DataFrame(rows)


def ble_tetam(data: Path) -> pd.DataFrame:
    """ble-tetam's tracks (as ``robustloc.eval.realdata.load_cases`` loads them): RMS."""
    from robustloc.eval.realdata import load_cases

    case = next(c for c in load_cases(data) if c.name == "ble-tetam tracks")
    A, n = np.asarray(case.A, float), np.asarray(case.n, float)
    h = np.zeros(len(A)) if case.height_offset is None else np.asarray(case.height_offset)

    def rms(p: np.ndarray) -> float:
        e = np.hypot(*(p[:, :2] - case.truth[:, :2]).T)
        return float(np.sqrt(np.nanmean(e**2)))

    p0 = Locator("nls", sigma=case.sigma).solve(case.xy, case.values, "rssi", A=A, n=n,
                                                height_offset=case.height_offset).position
    e, _ = _db_residuals(case.xy, h, A, n, np.nan_to_num(p0), case.values)
    s = _mad(np.where(np.isfinite(p0[:, :1]), e, np.nan), axis=0)  # per receiver
    row = {"nls": rms(p0)}
    for a in ALPHAS:
        row[f"one-sided {a}"] = rms(snoop_db(case.xy, case.values, A, n, s[None], a,
                                             height_offset=case.height_offset,
                                             sigma=case.sigma))
    return pd.DataFrame([row])



def wifi_rss(data: Path) -> pd.DataFrame:
    """wifi-rtt-rss's RSS, every test scan of each room, the path loss calibrated on the
    train files (as the report's ``s30_wifi_rssi``): mean and RMS 2-D error."""
    from robustloc.datasets import wifi_rtt
    from robustloc.io import to_epochs
    from robustloc.models.calibration import calibrate_pathloss, survey_from_positions
    from robustloc.models.pathloss import log_distance_arrays

    rows = []
    for room in wifi_rtt.ROOMS:
        train = wifi_rtt.load_room(room, "train", data)
        test = wifi_rtt.load_room(room, "test", data)
        sv = survey_from_positions(train.rssi, train.truth, train.anchors)
        an = calibrate_pathloss(sv, "log-distance").apply_to_anchors(train.anchors)
        A, n = (np.asarray(v, float) for v in log_distance_arrays(an))
        xy = an[["x", "y"]].to_numpy(float)
        meas = test.rssi.assign(tag=test.rssi["rp"].astype(str))
        ep = to_epochs(meas[["time", "tag", "anchor", "rssi"]], list(an["anchor"]), "rssi")
        tr = test.truth.assign(tag=test.truth["rp"].astype(str)).set_index(["time", "tag"])
        truth = tr.loc[list(zip(ep.time, ep.tag)), ["x", "y"]].to_numpy(float)

        def err(p: np.ndarray, truth: np.ndarray = truth) -> tuple[float, float]:
            e = np.hypot(*(p[:, :2] - truth).T)
            return float(np.nanmean(e)), float(np.sqrt(np.nanmean(e**2)))

        p0 = Locator("nls").solve(xy, ep.values, "rssi", A=A, n=n).position
        e, _ = _db_residuals(xy, np.zeros(len(A)), A, n, np.nan_to_num(p0), ep.values)
        s = _mad(np.where(np.isfinite(p0[:, :1]), e, np.nan), axis=0)  # per access point
        row = {"room": room, "nls mean": err(p0)[0], "nls rms": err(p0)[1]}
        for a in ALPHAS:
            m, r = err(snoop_db(xy, ep.values, A, n, s[None], a))
            row[f"one-sided {a} mean"], row[f"one-sided {a} rms"] = m, r
        rows.append(row)
    return pd.DataFrame(rows)

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", type=int, default=10, help="corridor seeds 1..N (default 10)")
    ap.add_argument("--data", type=Path, default=Path("../shared/data"),
                    help="the shared data folder (ble-tetam); skipped when missing")
    args = ap.parse_args(argv)
    fmt = {"float_format": lambda v: f"{v:.3f}", "index": False}
    df = corridor(args.seeds)
    print("seed 000 corridor: mean 2-D error over S1-S3 (m)")
    print(df.to_string(**fmt))
    print("\nmean over seeds")
    print(df.drop(columns="seed").groupby("scheme").mean().to_string(
        float_format=lambda v: f"{v:.3f}"))
    if (args.data / "ble-tetam").exists():
        print("\nble-tetam tracks (real): 2-D RMS (m)")
        print(ble_tetam(args.data).to_string(**fmt))
    else:
        print(f"\n(no {args.data / 'ble-tetam'}: the real-data row is skipped)")
    if (args.data / "wifi-rtt-rss").exists():
        print("\nwifi-rtt-rss RSS (real), test scans: 2-D error (m)")
        print(wifi_rss(args.data).to_string(**fmt))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
