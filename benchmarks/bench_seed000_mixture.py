"""Seed 000 scheme 2 (people walking): a self-calibrated outlier model, measured (not
adopted).

The body-blockage bursts of ``simulate ble-corridor --disturbance`` weaken a link's RSSI
by 6-18 dB.  The maximum-likelihood answer to one-sided errors is a mixture likelihood in
the dB domain: a clear Gaussian ``N(0, s)`` plus a blocked component ``N(-mu, s2)`` with
weight ``pi``.  Its four parameters are fitted without truth by EM over the whole log's
RSSI residuals at the plain Gauss-Newton (``nls``) fixes; each epoch is then solved by
maximising the mixture likelihood (Nelder-Mead from the ``nls`` fix and from beside the
three strongest beacons).  Beside it, ``nls`` and least squares in the dB domain.

Measured 2026-12-06, mean 2-D error over S1-S3 and seeds 1-4: ``nls`` 1.805 m, the mixture
1.828 m, dB-domain least squares 2.183 m.  The range domain stays better than any
dB-domain fit of this simulator (its calibration is censored at the sensitivity: the
pooled ``n`` comes out 1.96, 1.91, 2.04 and 1.98 on seeds 1-4 for the true 2.2), so the
mixture is not adopted.

Usage::

    python benchmarks/bench_seed000_mixture.py --seeds 1,2,3,4
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy.optimize import least_squares, minimize

from robustloc.estimators.ranging import Locator
from robustloc.reproduce.s10_ble_ranging import corridor_scheme


def _em(r: np.ndarray, iterations: int = 200) -> tuple[float, float, float, float]:
    """``pi, s, mu, s2`` of ``(1 - pi) N(0, s) + pi N(-mu, s2)`` fitted to residuals ``r``."""
    pi, s, mu, s2 = 0.2, 2.0, 8.0, 4.0
    for _ in range(iterations):
        g = (1 - pi) * np.exp(-0.5 * (r / s) ** 2) / s
        h = pi * np.exp(-0.5 * ((r + mu) / s2) ** 2) / s2
        w = h / (g + h)
        pi = w.mean()
        s = np.sqrt(np.sum((1 - w) * r**2) / np.sum(1 - w))
        mu = -np.sum(w * r) / np.sum(w)
        s2 = np.sqrt(np.sum(w * (r + mu) ** 2) / np.sum(w))
    return pi, s, mu, s2


def run_seed(seed: int) -> dict[str, float]:
    sc = corridor_scheme(seed, disturbance=True)  # (the report's scheme 2)
    fr, A, n, xy, ep = sc.fr, sc.A, sc.n, sc.xy, sc.ep
    truth = fr["truth"].set_index(["time", "tag"]).loc[list(zip(ep.time, ep.tag))]
    tr = truth[["x", "y"]].to_numpy()
    V = ep.values
    P0 = np.asarray(Locator("nls").solve(xy, V, "rssi", A=A, n=n).position)[:, :2].copy()
    bad = ~np.isfinite(P0).all(axis=1)
    for i in np.flatnonzero(bad):  # (no nls fix: start at the strongest beacon)
        P0[i] = xy[np.nanargmax(V[i])] + [0.0, 0.1]

    def pred(p: np.ndarray) -> np.ndarray:  # seed 000 eq. (1)
        return A - 10 * n * np.log10(np.maximum(np.hypot(*(xy - p).T), 0.1))

    r = np.concatenate([V[i] - pred(P0[i]) for i in np.flatnonzero(~bad)])
    pi, s, mu, s2 = _em(r[np.isfinite(r)])

    def nll(p: np.ndarray, v: np.ndarray) -> float:
        e = v - pred(p)
        e = e[np.isfinite(e)]
        lik = (1 - pi) * np.exp(-0.5 * (e / s) ** 2) / s + pi * np.exp(
            -0.5 * ((e + mu) / s2) ** 2) / s2
        return float(-np.sum(np.log(lik + 1e-300)))

    mix, dbls = np.empty_like(P0), np.empty_like(P0)
    for i in range(len(V)):
        starts = [P0[i]] + [xy[j] + [0, 2 - xy[j, 1]]
                            for j in np.argsort(-np.nan_to_num(V[i], nan=-999))[:3]]
        best = min((minimize(nll, x0, args=(V[i],), method="Nelder-Mead",
                             options={"xatol": 1e-4, "fatol": 1e-8}) for x0 in starts),
                   key=lambda o: o.fun)
        mix[i] = best.x
        dbls[i] = least_squares(lambda p, v=V[i]: (v - pred(p))[np.isfinite(v)], P0[i]).x

    def err(P: np.ndarray) -> float:
        return float(np.mean(np.hypot(*(P - tr).T)))

    return {"seed": seed, "nls": err(P0), "mixture (EM, dB)": err(mix),
            "dB least squares": err(dbls), "pi": pi, "s_db": s, "mu_db": mu, "s2_db": s2}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="1,2,3,4", help="comma-separated seeds (default 1-4)")
    args = ap.parse_args(argv)
    import pandas as pd

    rows = [run_seed(int(x)) for x in args.seeds.split(",")]
    df = pd.DataFrame(rows)
    print("mean 2-D error over S1-S3 (m); EM parameters in dB")
    print(df.to_string(index=False, float_format=lambda v: f"{v:.3f}"))
    print("mean over seeds:", {k: round(float(df[k].mean()), 3)
                               for k in ("nls", "mixture (EM, dB)", "dB least squares")})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
