"""Benchmark: ``robustloc.tracking.Tracker`` tag-epochs per second, FilterPy side by side.

Workload (issue 11): CV model, ``--tags`` tags (default 1 000) x ``--anchors`` anchors
(default 8) of UWB-like ranges (0.1 m noise, 5 % outliers of +1..5 m), ``--epochs`` epochs
per tag at 2 Hz.  Every tag's state starts from a robust fix in the first epoch; the
timed part is the tracking epochs after it (the full robust step: prediction,
innovations, CUSUM, tight robust update, B-method test, adaptive noise, hpl).

Peer: FilterPy 2.0 ``ExtendedKalmanFilter`` (EKF) and ``UnscentedKalmanFilter`` (UKF)
with the same CV model and range measurement, plain (not robust), one object per tag and
a Python loop over tags -- how one would track many tags with it; timed on
``--peer-tags`` tags and reported per tag-epoch.

Run:  NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 python benchmarks/bench_track.py
      [--tags 1000] [--anchors 8] [--epochs 40] [--rounds 3]
One core: ``NUMBA_NUM_THREADS=1`` keeps the compiled kernels on one thread.

Measured on this project's 2-core machine under a load average of 10-14 (several agents;
wall-clock figures several times slower than on an idle core, compare the ratios):
EKF 19-22 k tag-epochs/s (FilterPy plain EKF 2.2-3.0 k: 7-9x), UKF 18-21 k (FilterPy 420-520:
35-49x) -- below the issue's 200 k / 50 k.  Per round of 1 000 tags the compiled predict +
update is about a fifth of the time; the rest is the per-tag NumPy work around it
(innovations of held links, the B-method test and robust-fix checks of suspicious epochs,
hpl, the output frame).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from robustloc.io.tables import Epochs
from robustloc.tracking import Tracker

SIGMA_M = 0.1


def _data(K: int, M: int, N: int, seed: int = 0) -> tuple[pd.DataFrame, list[Epochs]]:
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 2 * np.pi, M, endpoint=False)
    axy = np.stack([10 + 12 * np.cos(ang), 10 + 12 * np.sin(ang)], 1)
    anchors = pd.DataFrame({"anchor": [f"A{i}" for i in range(M)], "x": axy[:, 0],
                            "y": axy[:, 1]})
    ph = rng.uniform(0, 2 * np.pi, K)
    ids = tuple(anchors["anchor"])
    tags = np.array([f"t{k}" for k in range(K)], dtype=object)
    blocks = []
    for j in range(N):
        t = 0.5 * j
        p = np.stack([10 + 5 * np.cos(0.1 * t + ph), 10 + 4 * np.sin(0.13 * t + ph)], 1)
        r = np.linalg.norm(p[:, None] - axy[None], axis=2) + rng.normal(0, SIGMA_M, (K, M))
        r += np.where(rng.random((K, M)) < 0.05, rng.uniform(1, 5, (K, M)), 0.0)
        blocks.append(Epochs(np.full(K, t), tags, r, ids, "range",
                             np.zeros(K, dtype=np.int64)))
    return anchors, blocks


def _ours(anchors: pd.DataFrame, blocks: list[Epochs], filt: str, engine: str) -> float:
    trk = Tracker(anchors, model="cv", filter=filt, sigma=SIGMA_M, engine=engine)
    trk.step(blocks[0])  # start: robust fixes
    trk.step(blocks[1])  # warm (compiles on first use)
    t0 = time.perf_counter()
    for b in blocks[2:]:
        trk.step(b)
    dt = time.perf_counter() - t0
    return sum(b.n_epochs for b in blocks[2:]) / dt


def _filterpy(anchors: pd.DataFrame, blocks: list[Epochs], filt: str, K: int) -> float:
    from filterpy.kalman import ExtendedKalmanFilter, MerweScaledSigmaPoints, UnscentedKalmanFilter

    from robustloc.filters.motion import ConstantVelocity

    axy = anchors[["x", "y"]].to_numpy()
    M = len(axy)
    F, Q = ConstantVelocity(q=1.0).FQ(0.5)
    R = np.eye(M) * SIGMA_M**2

    def hx(x: np.ndarray) -> np.ndarray:
        return np.hypot(x[0] - axy[:, 0], x[1] - axy[:, 1])

    def H_of(x: np.ndarray) -> np.ndarray:
        d = hx(x)
        H = np.zeros((M, 4))
        H[:, 0] = (x[0] - axy[:, 0]) / d
        H[:, 1] = (x[1] - axy[:, 1]) / d
        return H

    filters = []
    for k in range(K):
        z0 = blocks[0].values[k]
        if filt == "ekf":
            f = ExtendedKalmanFilter(dim_x=4, dim_z=M)
            f.F, f.Q, f.R = F, Q, R
        else:
            pts = MerweScaledSigmaPoints(4, alpha=1.0, beta=2.0, kappa=0.0)
            f = UnscentedKalmanFilter(dim_x=4, dim_z=M, dt=0.5, hx=hx,
                                      fx=lambda x, dt: F @ x, points=pts)
            f.Q, f.R = Q, R
        f.x = np.array([10.0, 10.0, 0.0, 0.0]) + 0 * z0[:4]
        f.P = np.eye(4)
        filters.append(f)
    t0 = time.perf_counter()
    for b in blocks[2:]:
        for k in range(K):
            f = filters[k]
            if filt == "ekf":
                f.predict()
                f.update(b.values[k], H_of, hx)
            else:
                f.predict()
                f.update(b.values[k])
    dt = time.perf_counter() - t0
    return K * (len(blocks) - 2) / dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tags", type=int, default=1000)
    ap.add_argument("--anchors", type=int, default=8)
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--peer-tags", type=int, default=50)
    a = ap.parse_args()
    anchors, blocks = _data(a.tags, a.anchors, a.epochs)
    print(f"track: CV, {a.tags} tags x {a.anchors} anchors, {a.epochs - 2} timed epochs "
          f"per tag (best of {a.rounds} rounds; tag-epochs per second)")
    print(f"{'filter':6s} {'compiled':>12s} {'numpy':>12s} {'FilterPy':>12s} {'x FilterPy':>11s}"
          f" {'target':>9s}")
    for filt, target in (("ekf", 200_000), ("ukf", 50_000)):
        comp = max(_ours(anchors, blocks, filt, "compiled") for _ in range(a.rounds))
        nump = max(_ours(anchors, blocks, filt, "numpy") for _ in range(a.rounds))
        peer = _filterpy(anchors, blocks, filt, min(a.peer_tags, a.tags))
        print(f"{filt:6s} {comp:12,.0f} {nump:12,.0f} {peer:12,.0f} {comp / peer:10.0f}x"
              f" {target:9,d}")


if __name__ == "__main__":
    main()
