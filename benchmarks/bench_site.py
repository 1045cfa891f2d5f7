"""Benchmark: ``locate`` on a large site, where each epoch hears a few of many anchors.

Workload: ``--side`` x ``--side`` anchors on a grid ``--spacing`` m apart (default 10 x 10,
10 m: a warehouse), ``--epochs`` tags at random points of the grid's inner part, each
ranging to its ``--heard`` nearest anchors (the others missing) with Gaussian noise of
``--sigma`` m and, on a share ``--gross`` of the ranges, a positive gross error of 3-15 m
(NLOS).  Every method solves the whole batch with the whole site's anchors, as ``robustloc
locate`` does with the site's anchors file.

Peer, side by side: scipy ``least_squares`` (``soft_l1``, ``f_scale`` = sigma) per epoch on
the anchors it hears, started from their centroid -- what one would write by hand.

Columns: RMS and p95 of the 2-D error (m) over the epochs with a position (the default:
with a usable status), that share, and the solve's wall time (s).

Run:  python benchmarks/bench_site.py [--side 10] [--heard 10] [--epochs 2000]
      [--gross 0.15] [--sigma 0.15] [--seed 1] [--write DIR]

The command line on such a site (``--write``; 2026-12-05): ``python
benchmarks/bench_site.py --epochs 20000 --gross 0.05 --seed 7 --write site``, then
``robustloc locate site/meas.csv --anchors site/anchors.csv -o pos.csv`` (3.7 GB resident
and 21 s before the residuals' cofactors went in blocks, 0.62 GB and 12 s after, the same
file), and ``calibrate --self`` on the first 2 000 rows of ``meas.csv`` (200 epochs: 4 min
14 s before the self-calibration kept each epoch's matrices on its anchors, 12 s after).

2026-12-05, default arguments (2 000 epochs).  The robust start's minimal subsets had
been drawn over the whole site (24 of the 161 700 triples of 100 anchors: for most epochs
none within the 10 it hears), so it had only the linearized fix and the weighted centroid
to start from; now each epoch takes the subsets of the anchors it hears
(``robustloc.estimators.ranging._heard_groups``; LEGE, which had enumerated the site's
C(100, 4) sets and asked for 66 GB, searches the observed rows only):

===========================  ===================  ===================  =============
method                       before: rms / p95    after: rms / p95     available
===========================  ===================  ===================  =============
nls                          2.834 / 5.426        2.834 / 5.426        100 %
huber (log scale)            0.812 / 0.378        0.629 / 0.336        100 %
huber (per-epoch scale)      1.758 / 3.475        0.874 / 0.383        100 %
igg3 (log scale)             0.747 / 0.199        0.422 / 0.198        100 %
igg3 (per-epoch scale)       1.171 / 0.966        0.799 / 0.231        100 %
default (auto, protected)    0.109 / 0.193        0.110 / 0.195        98.5 -> 98.8 %
scipy least_squares soft_l1  0.840 / 0.283        (peer)               100 %
===========================  ===================  ===================  =============

The default re-solves robustly only the epochs whose plain fit fails its test and
withholds the few it cannot confirm, so the start matters little to it; the explicit
robust methods gain.  Times are of the order of a second either way (the subsets are
found once per pattern of anchors heard and cached).

2026-12-05, ``--side 20`` (400 anchors, 2 000 epochs; ``/usr/bin/time -v``): 97 s and 2.3
GB resident before the site's subsets were chosen among local ones (the whole site's
C(400, 3) = 1.1e7 triples had been listed and hashed) and the residuals' cofactors formed
on each epoch's heard anchors; 14 s and 0.40 GB after, every row the same (nls 2.770 /
5.244, huber log scale 0.715 / 0.358, igg3 log scale 0.645 / 0.209, the default 0.113 /
0.200 at 99.2 %, scipy 0.439 / 0.273).  ``--side 30`` (900 anchors): the default 0.119 /
0.212 at 99.0 % in 3.3 s, scipy 0.804 / 0.288 in 5.6 s.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from robustloc.estimators.ranging import Locator
from robustloc.integrity.fixes import locate_protected
from robustloc.options import int_in


def _site(side: int, spacing: float, heard: int, N: int, sigma: float, gross: float,
          seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    g = np.arange(side * side)
    axy = np.stack([spacing * (g % side), spacing * (g // side)], 1)
    lo, hi = spacing, spacing * (side - 2)
    p = rng.uniform(lo, max(hi, lo + 1e-9), (N, 2))
    d = np.linalg.norm(p[:, None] - axy[None], axis=2)
    r = d + rng.normal(0, sigma, d.shape)
    r = np.where(rng.random(d.shape) < gross, r + rng.uniform(3, 15, d.shape), r)
    far = np.argsort(d, axis=1)[:, heard:]
    np.put_along_axis(r, far, np.nan, axis=1)
    return axy, r, p


def _write(out: Path, axy: np.ndarray, r: np.ndarray, p: np.ndarray) -> None:
    """The site as the command line's files: one tag ``t``, epochs 0.1 s apart."""
    import pandas as pd

    out.mkdir(parents=True, exist_ok=True)
    ids = np.array([f"A{i}" for i in range(len(axy))])
    pd.DataFrame({"anchor": ids, "x": axy[:, 0], "y": axy[:, 1]}).to_csv(
        out / "anchors.csv", index=False)
    k, j = np.nonzero(np.isfinite(r))
    pd.DataFrame({"time": k * 0.1, "tag": "t", "anchor": ids[j], "range": r[k, j]}).to_csv(
        out / "meas.csv", index=False)
    pd.DataFrame({"time": np.arange(len(p)) * 0.1, "tag": "t", "x": p[:, 0],
                  "y": p[:, 1]}).to_csv(out / "truth.csv", index=False)
    print(f"wrote {out}/anchors.csv, meas.csv ({k.size} ranges), truth.csv")


def _stats(est: np.ndarray, p: np.ndarray) -> tuple[float, float, float]:
    e = np.hypot(*(est - p).T)
    ok = np.isfinite(e)
    e = e[ok]
    return float(np.sqrt(np.mean(e**2))), float(np.percentile(e, 95)), 100.0 * ok.mean()


def _usable(sol) -> np.ndarray:
    """A protected solution's positions where its status is usable (NaN elsewhere)."""
    from robustloc import status as st

    return np.where(st.among(sol.status, st.USABLE)[:, None], sol.position, np.nan)


def _scipy(axy: np.ndarray, r: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.optimize import least_squares

    out = np.full((r.shape[0], 2), np.nan)
    for k in range(r.shape[0]):
        h = np.isfinite(r[k])
        a, rk = axy[h], r[k, h]
        res = least_squares(lambda x, a=a, rk=rk: np.hypot(*(x - a).T) - rk, a.mean(axis=0),
                            loss="soft_l1", f_scale=sigma)
        out[k] = res.x
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--side", type=int_in(3, 100), default=10,
                    help="anchors per side of the grid (default: %(default)s)")
    ap.add_argument("--spacing", type=float, default=10.0,
                    help="grid spacing, m (default: %(default)s)")
    ap.add_argument("--heard", type=int_in(3, 10**4), default=10,
                    help="anchors each epoch hears, its nearest (default: %(default)s)")
    ap.add_argument("--epochs", type=int_in(1, 10**7), default=2000,
                    help="epochs (default: %(default)s)")
    ap.add_argument("--sigma", type=float, default=0.15,
                    help="range noise std, m (default: %(default)s)")
    ap.add_argument("--gross", type=float, default=0.15,
                    help="share of ranges with a +3..15 m gross error (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=1, help="random seed (default: %(default)s)")
    ap.add_argument("--write", metavar="DIR", default=None,
                    help="write the site as anchors.csv, meas.csv and truth.csv in DIR (for "
                         "the command line: robustloc locate DIR/meas.csv --anchors "
                         "DIR/anchors.csv ...) and stop (default: run the table)")
    a = ap.parse_args()
    axy, r, p = _site(a.side, a.spacing, a.heard, a.epochs, a.sigma, a.gross, a.seed)
    if a.write is not None:
        _write(Path(a.write), axy, r, p)
        return
    print(f"site: {a.side}x{a.side} anchors {a.spacing:g} m apart, {a.heard} heard per "
          f"epoch, {a.epochs} epochs, sigma {a.sigma:g} m, {100 * a.gross:g} % gross")
    print(f"{'method':34s} {'rms':>7s} {'p95':>7s} {'avail %':>8s} {'time s':>8s}")
    runs = [("nls", lambda: Locator("nls").solve(axy, r, "range").position),
            ("huber (log scale)", lambda: Locator("huber").solve(axy, r, "range").position),
            ("huber (per-epoch scale)",
             lambda: Locator("huber", robust_scale="mad").solve(axy, r, "range").position),
            ("igg3 (log scale)", lambda: Locator("igg3").solve(axy, r, "range").position),
            ("igg3 (per-epoch scale)",
             lambda: Locator("igg3", robust_scale="mad").solve(axy, r, "range").position),
            ("default (auto, protected)",
             lambda: _usable(locate_protected(Locator("auto"), axy, r, "range"))),
            ("scipy least_squares soft_l1", lambda: _scipy(axy, r, a.sigma))]
    Locator("huber").solve(axy, r[:2], "range")  # compile the kernels outside the timing
    for name, run in runs:
        t0 = time.perf_counter()
        est = run()
        dt = time.perf_counter() - t0
        rms, p95, avail = _stats(est, p)
        print(f"{name:34s} {rms:7.3f} {p95:7.3f} {avail:8.1f} {dt:8.2f}")


if __name__ == "__main__":
    main()
