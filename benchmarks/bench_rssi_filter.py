"""Benchmark: robust RSSI Kalman filter throughput (seed 002), all links in one pass.

Filtered RSSI samples per second for ``L`` links x ``T`` samples at once, on one core
(set ``OMP_NUM_THREADS=1`` etc. for a strict single-core figure).  Target: >= 1 million
samples/s over 1 000 links.  The ``update_linear`` row (the shared core update, slower)
runs a fifth of ``--steps`` (at least 50); the table's ``steps`` column shows what ran.

Run:  python benchmarks/bench_rssi_filter.py [--links 1000] [--steps 1000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from robustloc.filters.rssi import LinkParams, RobustRssiFilter


def bench(links: int, steps: int, repeat: int, **kw) -> tuple[float, float]:
    """Best wall-clock and best CPU-time rates (samples/s) over ``repeat`` runs."""
    rng = np.random.default_rng(0)
    z = -60 + rng.normal(0, 2, (steps, links))
    z[rng.random((steps, links)) < 0.03] -= 12  # fades: exercise the robust branch
    dt = np.full((steps, links), 0.5)
    params = LinkParams.broadcast(links, -35.0, 2.5)
    f = RobustRssiFilter(**kw)
    wall = cpu = np.inf
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        f.run(z, dt, params)
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return links * steps / wall, links * steps / cpu


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--links", type=int, default=1000,
                   help="links filtered at once, in one pass (default: %(default)s)")
    p.add_argument("--steps", type=int, default=1000,
                   help="samples per link; the update_linear row runs a fifth of them, at "
                        "least 50 (default: %(default)s)")
    p.add_argument("--repeat", type=int, default=3,
                   help="timed runs per row, the best wall and CPU rates are reported "
                        "(default: %(default)s)")
    a = p.parse_args()
    cases = [
        ("robust (asymmetric IGG), scalar update", {}),
        ("plain KF, scalar update", {"robust": False}),
        ("robust, shared core update_linear", {"engine": "core"}),
    ]
    print(f"{'variant':42s} {'links':>6s} {'steps':>6s} {'samples/s wall':>15s} "
          f"{'samples/s CPU':>14s}")
    for name, kw in cases:
        steps = a.steps if kw.get("engine") != "core" else max(a.steps // 5, 50)
        wall, cpu = bench(a.links, steps, a.repeat, **kw)
        print(f"{name:42s} {a.links:6d} {steps:6d} {wall:15.3e} {cpu:14.3e}")
    print(f"update_linear row: --steps / 5 (at least 50) = {max(a.steps // 5, 50)} steps")
    print("target: >= 1e6 samples/s over 1000 links (CPU time = one core; wall time also "
          "counts waiting for a shared machine)")


if __name__ == "__main__":
    main()
