"""Benchmark: filter steps of robustloc vs FilterPy, and the paper's flop counts.

Models (seed 001): a 6-state constant-acceleration UKF and a 4-state constant-velocity
EKF, both measuring ``z = [x, y, v, heading]``.  For each: time per step (predict +
update) for one track, robustloc vs FilterPy 2.0 on the same model and data, and
aggregate steps per second when 1 000 independent tracks advance in one batched step.
The paper's flop counts (:mod:`robustloc.filters.complexity`) are printed beside the
measured time per step.

Run:  OMP_NUM_THREADS=1 python benchmarks/bench_filters.py [--steps 300] [--tracks 1000]
      [--rounds 7] [--sigma-predict]
"ours" is the public ``FusionFilter.step`` with its default compiled engine (one numba call
per step, :mod:`robustloc.filters._compiled`); the "numpy" columns run the same step with
``engine="numpy"`` (the batched NumPy core).  The machine's load matters (wall time): the
variants are timed in interleaved rounds and each ratio is the median of the ratios within
a round.  From 256 tracks a step runs on numba's threads (all cores by default): "batch x"
is measured that way and "1-thr x" on one thread.  Measured here (2 cores, FilterPy's EKF
step 39-87 us depending on the machine's load; several runs): EKF 4-state CV one track
6.4-7.0x FilterPy, 1 000 tracks batched 167-173x on 2 threads and 100-130x on one (NumPy
engine: 0.3x and 18-20x); UKF 6-state CA one track 44-52x, batched 287-318x on 2 threads
and 146-198x on one (NumPy engine: 1.7x and 70-95x).  Compiled, per track-step on one
thread: about 0.35-0.7 us (EKF), 2-4 us (UKF).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from robustloc.filters import ConstantAcceleration, ConstantVelocity, SigmaPoints
from robustloc.filters.complexity import ekf_flops, ukf_flops
from robustloc.fusion.pipeline import FusionFilter, FusionMeasurement


def _data(steps: int, K: int, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * 1.0
    pos = np.stack([0.2 * t, 0.2 * t], axis=-1)
    z = np.empty((K, steps, 4))
    z[..., :2] = pos[None] + rng.normal(0, 0.1, (K, steps, 2))
    z[..., 2] = 0.2 * np.sqrt(2) + rng.normal(0, 0.02, (K, steps))
    z[..., 3] = np.pi / 4 + rng.normal(0, 0.03, (K, steps))
    x0 = np.zeros((K, n))
    x0[:, 2:4] = 0.14
    return z, x0


R = np.diag([0.01, 0.01, 4e-4, 1e-3])
#: UKF predict through sigma points (True) or, exact for the linear CA model, with F (False).
SIGMA_PREDICT = False


def _ours(kind: str, motion, z: np.ndarray, x0: np.ndarray, repeats: int = 5,
          engine: str = "compiled", threads: int | None = None) -> float:
    """Median seconds per ``FusionFilter.step`` of ``K`` tracks (z: (K, steps, 4)).

    ``threads``: numba's thread count for the call (None: its default, all cores); a step
    of 256 tracks or more runs its compiled kernel on that many threads.
    """
    import numba

    prev = numba.get_num_threads()
    numba.set_num_threads(threads or prev)
    try:
        return _time_steps(kind, motion, z, x0, repeats, engine)
    finally:
        numba.set_num_threads(prev)


def _time_steps(kind: str, motion, z: np.ndarray, x0: np.ndarray, repeats: int,
                engine: str) -> float:
    K, steps, _ = z.shape
    f = FusionFilter(kind, motion, points=SigmaPoints(1.0, 2.0, 0.0), min_speed_mps=0.0,
                     sigma_point_predict=SIGMA_PREDICT, engine=engine)
    meas = FusionMeasurement(motion.n_states)
    dt = np.ones(K)
    zs = [np.ascontiguousarray(z[:, j]) for j in range(steps)]  # data as a caller holds it
    f.step(x0.copy(), np.tile(np.eye(motion.n_states), (K, 1, 1)), dt, zs[0], R, meas)  # warm
    best = []
    for _ in range(repeats):
        x = x0.copy()
        P = np.tile(np.eye(motion.n_states), (K, 1, 1))
        t0 = time.perf_counter()
        for j in range(steps):
            r = f.step(x, P, dt, zs[j], R, meas)
            x, P = r.x, r.P
        best.append((time.perf_counter() - t0) / steps)
    return float(np.median(best))


def _hx(x):
    return np.array([x[0], x[1], np.hypot(x[2], x[3]), np.arctan2(x[2], x[3])])


def _hjac(x):
    vx, vy = x[2], x[3]
    v2 = vx * vx + vy * vy
    v = np.sqrt(v2)
    J = np.zeros((4, len(x)))
    J[0, 0] = J[1, 1] = 1.0
    J[2, 2], J[2, 3] = vx / v, vy / v
    J[3, 2], J[3, 3] = vy / v2, -vx / v2
    return J


def _res_z(a, b):
    d = np.subtract(a, b)
    d[3] = (d[3] + np.pi) % (2 * np.pi) - np.pi
    return d


def _filterpy_ukf(z: np.ndarray, x0: np.ndarray, repeats: int = 5) -> float:
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    motion = ConstantAcceleration(q=1e-4)
    F, Q = motion.F(1.0), motion.Q(1.0)
    steps = z.shape[1]
    out = []
    for _ in range(repeats):
        pts = MerweScaledSigmaPoints(6, alpha=1.0, beta=2.0, kappa=0.0)
        f = UnscentedKalmanFilter(6, 4, 1.0, hx=_hx, fx=lambda x, dt: F @ x, points=pts,
                                  residual_z=_res_z)
        f.x = x0[0].copy()
        f.P = np.eye(6)
        f.Q, f.R = Q, R
        t0 = time.perf_counter()
        for j in range(steps):
            f.predict()
            f.update(z[0, j])
        out.append((time.perf_counter() - t0) / steps)
    return float(np.median(out))


def _filterpy_ekf(z: np.ndarray, x0: np.ndarray, repeats: int = 5) -> float:
    from filterpy.kalman import ExtendedKalmanFilter

    motion = ConstantVelocity(q=1e-3)
    steps = z.shape[1]
    out = []
    for _ in range(repeats):
        f = ExtendedKalmanFilter(4, 4)
        f.x = x0[0].copy()
        f.P = np.eye(4)
        f.F, f.Q, f.R = motion.F(1.0), motion.Q(1.0), R
        t0 = time.perf_counter()
        for j in range(steps):
            f.predict()
            f.update(z[0, j], _hjac, _hx, residual=_res_z)
        out.append((time.perf_counter() - t0) / steps)
    return float(np.median(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=300,
                    help="filter steps of the one-track runs; the K-track batches run a tenth "
                         "of them, at least 20 (default: %(default)s)")
    ap.add_argument("--tracks", type=int, default=1000,
                    help="K: tracks advanced in one batched step (default: %(default)s)")
    ap.add_argument("--rounds", type=int, default=7,
                    help="interleaved timing rounds (default: %(default)s)")
    ap.add_argument("--sigma-predict", action="store_true",
                    help="UKF predict through sigma points (default: exact linear predict)")
    args = ap.parse_args()
    global SIGMA_PREDICT
    SIGMA_PREDICT = args.sigma_predict
    S, K = args.steps, args.tracks
    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; {S} steps; "
          f"UKF predict: {'sigma points' if SIGMA_PREDICT else 'linear (exact for CA)'}")
    rows = []
    cases = [
        ("UKF 6-state CA", "ukf", ConstantAcceleration(q=1e-4), _filterpy_ukf, ukf_flops(6, 4)),
        ("EKF 4-state CV", "ekf", ConstantVelocity(q=1e-3), _filterpy_ekf, ekf_flops(4, 4)),
    ]
    for label, kind, motion, ref, flops in cases:
        z1, x1 = _data(S, 1, motion.n_states)
        zK, xK = _data(max(S // 10, 20), K, motion.n_states)
        # interleaved rounds: every variant is timed in each round, so a change of the
        # machine's load between rounds hits all alike; ratios are taken within a round
        t = np.array([
            [ref(z1, x1, repeats=1),
             _ours(kind, motion, z1, x1, repeats=1),
             _ours(kind, motion, zK, xK, repeats=1),
             _ours(kind, motion, z1, x1, repeats=1, engine="numpy"),
             _ours(kind, motion, zK, xK, repeats=1, engine="numpy"),
             _ours(kind, motion, zK, xK, repeats=1, threads=1)]
            for _ in range(args.rounds)
        ])
        ratio = np.median(t[:, :1] / t[:, 1:] * [1, K, 1, K, K], axis=0)
        rows.append((label, flops["total"], *np.median(t, axis=0), *ratio))
    print()
    print(f"{'model':16s} {'flops':>6s} {'FilterPy us':>11s} {'ours 1 us':>9s} "
          f"{'1-track x':>9s} {'ours K us':>9s} {'K steps/s':>11s} {'FilterPy st/s':>13s} "
          f"{'batch x':>8s} {'1-thr x':>8s} {'ns/flop':>8s} {'numpy 1 us':>10s} "
          f"{'numpy K x':>9s}")
    for label, fl, t_ref, t_one, t_b, t_np, _, t_b1, x_one, x_b, _, x_np_b, x_b1 in rows:
        print(f"{label:16s} {fl:6d} {t_ref * 1e6:11.1f} {t_one * 1e6:9.1f} "
              f"{x_one:9.2f} {t_b * 1e6:9.0f} {K / t_b:11.0f} {1 / t_ref:13.0f} "
              f"{x_b:8.1f} {x_b1:8.1f} {t_b1 / K / fl * 1e9:8.3f} {t_np * 1e6:10.1f} "
              f"{x_np_b:9.1f}")
    import numba

    print(f"\nK = {K} tracks per batched step; 'batch x' = aggregate steps/s over FilterPy's "
          f"single-track steps/s, on numba's {numba.get_num_threads()} threads; '1-thr x' the "
          "same on one thread.  ns/flop: one-thread batched time per track-step over the "
          "paper's flop count.  'ours': FusionFilter.step (compiled engine); 'numpy': the "
          "same with engine='numpy' (one track: us per step; K tracks: batch x).  Times: "
          "medians over the rounds; ratios: medians of the ratios within a round.")
    print("\nflops per step by the paper's counting rules (n states, l measurements):")
    print(f"{'n':>3s} {'l':>3s} {'EKF':>8s} {'UKF':>8s}")
    for n, l in ((4, 2), (4, 4), (6, 2), (6, 4), (9, 6)):
        print(f"{n:3d} {l:3d} {ekf_flops(n, l)['total']:8d} {ukf_flops(n, l)['total']:8d}")


if __name__ == "__main__":
    main()
