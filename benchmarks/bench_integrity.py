"""Speed of the integrity layer (batched over epochs / trials / grid points).

Run:  python benchmarks/bench_integrity.py [--quick]

Prints one row per workload: size, wall time, throughput (with its unit: epochs/s,
points/s or trials/s), and for data snooping the speed-up over a straightforward per-epoch
Python loop (numpy per epoch, same algorithm); '-' where a column does not apply.  Every
workload is first run once on a small input, untimed (numba compilation, first-call
costs).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from robustloc.estimators.ranging import Locator
from robustloc.integrity import reliability, snoop_linear
from robustloc.integrity.bmethod import global_critical, w_critical
from robustloc.integrity.fixes import least_squares_resolution, protect, range_model_of
from robustloc.integrity.montecarlo import gnss_layout, run_montecarlo
from robustloc.integrity.planner import plan


def _loop_snooping(H: np.ndarray, y: np.ndarray, sigma: float) -> np.ndarray:
    """Reference: per-epoch loop of the same procedure (for the speed comparison)."""
    N, n, p = H.shape
    k = w_critical()
    out = np.zeros(N, dtype=int)
    for e in range(N):
        m = np.ones(n, dtype=bool)
        while True:
            A = H[e][m] / sigma
            b = y[e][m] / sigma
            Ninv = np.linalg.inv(A.T @ A)
            v = A @ (Ninv @ (A.T @ b)) - b
            r = 1 - np.einsum("ip,pq,iq->i", A, Ninv, A)
            dof = m.sum() - p
            if v @ v <= float(global_critical(dof)) or dof < 2:
                break
            w = np.abs(v) / np.sqrt(r)
            j = int(np.argmax(w))
            if w[j] <= k:
                break
            m[np.flatnonzero(m)[j]] = False
            out[e] += 1
    return out


def _rate(count: float, seconds: float, unit: str) -> str:
    return f"{count / seconds:.3g} {unit}/s"


def _warm_up() -> None:
    """Each workload once on a small input, untimed: numba compilation (or the loading of
    its cache) and other first-call costs (~0.75 s) stay out of the first timed row."""
    rng = np.random.default_rng(1)
    H = rng.normal(size=(50, 10, 2))
    y = rng.normal(size=(50, 10))
    y[::3, 3] += 20.0
    snoop_linear(H, y, 1.0)
    _loop_snooping(H[:5], y[:5], 1.0)
    reliability(rng.normal(size=(50, 12, 4)), 1.0)
    anchors = np.column_stack([1.5 + 3 * np.arange(10), np.where(np.arange(10) % 2, 4.0, 0.0)])
    plan(anchors, (0, 30, 0, 4), 1.0, 1.0)
    for m in ("snooping", "huber", "igg3", "lege"):
        run_montecarlo(gnss_layout(), n_faults=1, size=1.0, trials=20, methods=(m,),
                       lege_max_order=2)
    sq = np.array([[0, 0], [30, 0], [30, 30], [0, 30]], dtype=float)
    z = np.linalg.norm(rng.uniform(5, 25, (50, 1, 2)) - sq[None], axis=-1)
    for method in ("nls", "ls"):
        protect(Locator(method, sigma=0.3, robust_scale="apriori").solve(sq, z),
                range_model=range_model_of(sq, None))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true",
                    help="a tenth of the epochs, geometries and trials, and a planner grid "
                         "of 0.1 m instead of 0.05 m (default: the full sizes)")
    a = ap.parse_args()
    scale = 10 if a.quick else 1
    _warm_up()
    rng = np.random.default_rng(0)
    rows = []

    N, n, p = 100_000 // scale, 10, 2
    H = rng.normal(size=(N, n, p))
    y = rng.normal(size=(N, n))
    y[rng.random(N) < 0.3, 3] += 20.0
    t0 = time.perf_counter()
    res = snoop_linear(H, y, 1.0)
    dt = time.perf_counter() - t0
    nl = 2000 // scale
    t1 = time.perf_counter()
    loop = _loop_snooping(H[:nl], y[:nl], 1.0)
    dl = (time.perf_counter() - t1) * N / nl
    agree = np.mean(loop == res.n_excluded[:nl])
    rows.append({"workload": f"snoop_linear, {N} epochs x {n} obs, 30 % faulty", "seconds": dt,
                 "throughput": _rate(N, dt, "epochs"), "loop seconds (extrapolated)": dl,
                 "speed-up": dl / dt, "note": f"same exclusions as loop: {agree:.1%}"})

    G = 20_000 // scale
    Hg = rng.normal(size=(G, 12, 4))
    t0 = time.perf_counter()
    reliability(Hg, 1.0)
    dt = time.perf_counter() - t0
    rows.append({"workload": f"reliability (r, MDB, ext., rho), {G} x 12 obs x 4 unknowns",
                 "seconds": dt, "throughput": _rate(G, dt, "epochs")})

    anchors = np.column_stack([1.5 + 3 * np.arange(10), np.where(np.arange(10) % 2, 4.0, 0.0)])
    t0 = time.perf_counter()
    g = plan(anchors, (0, 30, 0, 4), 0.05 * (2 if a.quick else 1), 1.0)
    dt = time.perf_counter() - t0
    rows.append({"workload": f"planner grid, {len(g.table)} points, 10 anchors", "seconds": dt,
                 "throughput": _rate(len(g.table), dt, "points")})

    # protect (tests and bounds of every fix): a least-squares fix, and a fix of the
    # linearized difference system, tested on the least-squares re-solution of its ranges
    # (Gauss-Newton with the anchors, one linearized step without them)
    N = 100_000 // scale
    sq = np.array([[0, 0], [30, 0], [30, 30], [0, 30], [15, 0], [30, 15], [15, 30], [0, 15]],
                  dtype=float)
    xt = rng.uniform(5.0, 25.0, (N, 2))
    z = np.linalg.norm(xt[:, None] - sq[None], axis=-1) + rng.normal(0.0, 0.3, (N, 8))
    gross = rng.random(z.shape) < 0.1
    z[gross] += rng.uniform(3.0, 15.0, int(gross.sum()))
    rm = range_model_of(sq, None)
    for label, method, model in (("nls", "nls", rm), ("ls (linearized), with anchors", "ls", rm),
                                 ("ls (linearized), one step", "ls", None)):
        sol = Locator(method, sigma=0.3, robust_scale="apriori").solve(sq, z)
        t0 = time.perf_counter()
        out = protect(sol, range_model=model)
        dt = time.perf_counter() - t0
        err = np.linalg.norm(out.position - xt, axis=1)
        usable = np.isfinite(out.extra["hpl"])
        rows.append({"workload": f"protect {label}, {N} epochs x 8 ranges, 10 % gross",
                     "seconds": dt, "throughput": _rate(N, dt, "epochs"),
                     "note": f"ok {np.mean(out.status == 'ok'):.1%}, misleading "
                             f"{np.mean(err[usable] > out.extra['hpl'][usable]):.3%}"})
    # the least-squares re-solution alone (what the linearized rows above add): the numba
    # kernel against its batched NumPy reference, from the linearized fixes
    sol = Locator("ls", sigma=0.3, robust_scale="apriori").solve(sq, z)
    v0 = rm.predict(sol.position) - z
    sig = np.full(z.shape, 0.3)
    keep = np.isfinite(z)
    for engine in ("compiled", "numpy"):
        t0 = time.perf_counter()
        least_squares_resolution(rm, sol.position, v0, sig, keep, engine=engine)
        dt = time.perf_counter() - t0
        rows.append({"workload": f"least_squares_resolution ({engine}), {N} epochs x 8 "
                                 "ranges", "seconds": dt, "throughput": _rate(N, dt, "epochs")})

    lay = gnss_layout()
    T = 10_000 // scale
    for m in ("snooping", "huber", "igg3", "lege"):
        t0 = time.perf_counter()
        run_montecarlo(lay, n_faults=1, size=1.0, trials=T, methods=(m,), lege_max_order=2)
        dt = time.perf_counter() - t0
        rows.append({"workload": f"montecarlo {m}, GNSS {lay.n} sats, {T} trials", "seconds": dt,
                     "throughput": _rate(T, dt, "trials")})
    pd.set_option("display.width", 160)
    print(pd.DataFrame(rows).to_string(index=False, float_format=lambda v: f"{v:.3g}",
                                       na_rep="-"))


if __name__ == "__main__":
    main()
