"""Speed, memory and accuracy of the batched position estimators against per-epoch peers.

Workload (issue 2, "Speed"): ``--epochs`` epochs (default 100 000) of 2-D range
positioning with 10 anchors and 20 % outlying ranges, solved by every method of
``robustloc.estimators`` in one batched call each, beside the same work done one epoch at a
time by

* statsmodels ``RLM(M=HuberT())`` on the paper's linearized difference system
  (seed 000, eq. (3): ``G Z = h``, one RLM fit per epoch), and
* ``scipy.optimize.least_squares(loss="huber", f_scale=0.6)`` on the raw ranges (nonlinear,
  started at the anchors' centroid; ``f_scale`` = 2 sigma, the paper's Huber ``c = 2``),
* and, as the ceiling of batching, bare NumPy normal equations of eq. (3) for all epochs at
  once (no validation, statuses or covariance), on all epochs.

The peers are timed on a subsample (``--peer-epochs``, default 500) and reported per fix
(fixes/s extrapolate linearly: every epoch is an independent small problem).

Simulated data (seeded, ``--seed``): anchors at the corners, edge midpoints and two interior
points of a 30 m x 30 m square; true positions uniform in [5, 25]^2 m; range noise
N(0, 0.3 m); each range independently an outlier with probability 0.2, outliers get a
positive NLOS-like error U(3, 15) m.

Columns: fixes/s, microseconds per fix, ratio to the statsmodels loop, peak traced memory
of the call (``tracemalloc``, a separate run so tracing does not slow the timing), RMS and
95th percentile of the 2-D position error over usable fixes, % epochs without a usable fix.

Options that do not reach every row: ``--solver`` applies to the robust methods and
``lege`` (and, with ``--mad-scale``, to ``snooping``'s first pass for the log's scale);
``auto``, ``ls``, ``wls`` and ``nls`` run as without it; with ``--solver linearized`` the
``[numpy]`` rows of the robust methods and ``lege`` are dropped (the linearized solver has
no compiled kernel: they would repeat the compiled rows).  ``--mad-scale`` does not apply
to ``auto`` (it estimates the log's scale itself), nor change the fixes of ``ls`` and
``wls`` (a sigma common to every anchor weights them alike).  A ``--numpy-methods`` name
not in ``--methods`` gives no row.  The script says so in a note when it happens.

Usage::

    python benchmarks/bench_locate.py            # 100 000 epochs (a few minutes)
    python benchmarks/bench_locate.py --quick    # 5 000 epochs, 200 peer epochs
    python benchmarks/bench_locate.py --epochs 20000 --methods ls,igg --json -o bench.csv
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import tracemalloc
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass

# "on one core": pin the BLAS pools before NumPy loads (override by setting them yourself)
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
from numpy.typing import NDArray  # noqa: E402

Array = NDArray[np.float64]

METHODS = ("auto", "ls", "wls", "nls", "huber", "hampel", "igg", "igg3", "lege", "snooping")
#: The methods ``--solver`` applies to (``Locator.solver``: the robust ones and LEGE).
SOLVER_METHODS = ("huber", "hampel", "igg", "igg3", "lege")
SIGMA_M = 0.3
OUTLIER_RATE = 0.2


# ----------------------------------------------------------------------------- data


@dataclass(frozen=True)
class Workload:
    anchors: Array  # (m, 2)
    truth: Array  # (N, 2)
    ranges: Array  # (N, m)
    outlier: NDArray[np.bool_]  # (N, m)


def make_workload(n_epochs: int, seed: int = 0) -> Workload:
    """Simulated range epochs (see the module docstring for every number)."""
    rng = np.random.default_rng(seed)
    anchors = np.array(
        [
            [0, 0], [30, 0], [30, 30], [0, 30], [15, 0],
            [30, 15], [15, 30], [0, 15], [10, 20], [20, 10],
        ],
        dtype=float,
    )  # fmt: skip
    truth = rng.uniform(5.0, 25.0, size=(n_epochs, 2))
    d = np.linalg.norm(truth[:, None, :] - anchors[None], axis=2)
    noise = rng.normal(0.0, SIGMA_M, size=d.shape)
    outlier = rng.random(d.shape) < OUTLIER_RATE
    gross = np.where(outlier, rng.uniform(3.0, 15.0, size=d.shape), 0.0)
    return Workload(anchors, truth, d + noise + gross, outlier)


def linearized_system(anchors: Array, ranges: Array) -> tuple[Array, Array]:
    """The paper's difference system (seed 000, eq. (3)), first anchor as reference.

    ``G`` row ``i-1`` = ``a_i - a_1``; ``h`` row ``i-1`` =
    ``(d_1^2 - d_i^2 - |a_1|^2 + |a_i|^2) / 2``.  Returns ``G (N, m-1, 2)`` (a broadcast
    view) and ``h (N, m-1)``.
    """
    a1 = anchors[0]
    G = anchors[1:] - a1
    k = np.sum(anchors**2, axis=1)
    h = 0.5 * (ranges[:, :1] ** 2 - ranges[:, 1:] ** 2 - k[0] + k[1:])
    return np.broadcast_to(G, (ranges.shape[0],) + G.shape), h


# ----------------------------------------------------------------------------- ours


@dataclass(frozen=True)
class Fixes:
    position: Array  # (N, 2), NaN = no usable fix
    how: str  # what was called


def _usable(x: Array, status: NDArray[np.object_]) -> Array:
    from robustloc import status as st

    return np.where(np.isin(status, st.USABLE)[:, None], x, np.nan)


def our_solver(
    method: str, mad_scale: bool = False, solver: str = "nonlinear", engine: str = "compiled"
) -> Callable[[Workload], Fixes]:
    """A batched solver for ``method``.

    Uses :class:`robustloc.estimators.ranging.Locator` when it exists (what
    ``robustloc locate`` runs) with the known range sigma (the same information scipy gets
    through ``f_scale``; ``mad_scale=True``: sigma unknown, MAD scale per epoch), else calls
    the kernels directly: ``linear.solve_wls`` / ``linear.lege`` on the eq. (3) system,
    ``nonlinear.gauss_newton`` on :class:`RangeModel` started from ``ls``.
    """
    try:
        from robustloc.estimators.ranging import Locator
    except ImportError:
        Locator = None  # noqa: N806
    if Locator is not None and method == "auto":
        # the default of `robustloc locate` as a new user gets it: no sigma given; the log's
        # scale (first pass), Gauss-Newton, every fix tested with its protection level, the
        # robust refit of the epochs whose test fails
        from robustloc.integrity.fixes import locate_protected

        auto = Locator(method="auto", engine=engine)

        def run_auto(wl: Workload) -> Fixes:
            sol = locate_protected(auto, wl.anchors, wl.ranges, "range")
            return Fixes(_usable(sol.position, sol.status),
                         "locate_protected(Locator(auto)): log scale + gross share, then "
                         "nls + test + hpl + huber refit (igg above 3.3 % gross)")

        return run_auto
    if Locator is not None:
        loc = Locator(method=method, solver=solver, sigma=None if mad_scale else SIGMA_M,
                      engine=engine)

        def run_locator(wl: Workload) -> Fixes:
            sol = loc.solve(wl.anchors, wl.ranges, kind="range")
            how = f"Locator({method}, {solver}, sigma={loc.sigma}, engine={engine})"
            return Fixes(_usable(sol.position, sol.status), how)

        return run_locator

    from robustloc.estimators import linear, nonlinear
    from robustloc.models.ranging import RangeModel
    from robustloc.robust.weights import get_weight

    def ls(wl: Workload) -> Fixes:
        G, h = linearized_system(wl.anchors, wl.ranges)
        fit = linear.solve_wls(G, h)
        return Fixes(_usable(fit.x, fit.status), "linear.solve_wls(eq. 3)")

    def lege(wl: Workload) -> Fixes:
        G, h = linearized_system(wl.anchors, wl.ranges)
        fit = linear.lege(G, h)
        return Fixes(_usable(fit.x, fit.status), "linear.lege(eq. 3)")

    def gn(wl: Workload) -> Fixes:
        G, h = linearized_system(wl.anchors, wl.ranges)
        x0 = linear.solve_wls(G, h).x
        x0 = np.where(np.isfinite(x0), x0, wl.anchors.mean(axis=0))
        wf = None if method == "nls" else get_weight(method)
        scale = None if mad_scale else 1.0
        fit = nonlinear.gauss_newton(
            RangeModel(wl.anchors), wl.ranges, x0, SIGMA_M, weight=wf, scale=scale
        )
        how = f"nonlinear.gauss_newton({method}, scale={'MAD' if mad_scale else 'sigma'})"
        return Fixes(_usable(fit.x, fit.status), how + " from ls")

    table = {"ls": ls, "lege": lege, "nls": gn, "huber": gn, "hampel": gn, "igg": gn, "igg3": gn}
    if method not in table:
        raise NotImplementedError(f"{method}: needs estimators.ranging.locate (not present yet)")
    return table[method]


# ----------------------------------------------------------------------------- peers


def statsmodels_rlm(wl: Workload) -> Fixes:
    """statsmodels RLM(HuberT), one fit per epoch on the eq. (3) system."""
    import statsmodels.api as sm

    G, h = linearized_system(wl.anchors, wl.ranges)
    out = np.full((wl.ranges.shape[0], 2), np.nan)
    norm = sm.robust.norms.HuberT()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for i in range(out.shape[0]):
            out[i] = sm.RLM(h[i], G[i], M=norm).fit().params
    return Fixes(out, "statsmodels RLM(HuberT) per epoch")


def scipy_huber(wl: Workload) -> Fixes:
    """scipy least_squares(loss='huber') on the raw ranges, one call per epoch."""
    from scipy.optimize import least_squares

    A = wl.anchors
    x0 = A.mean(axis=0)
    out = np.full((wl.ranges.shape[0], 2), np.nan)
    for i in range(out.shape[0]):
        z = wl.ranges[i]

        def f(x: Array, z: Array = z) -> Array:
            return np.hypot(x[0] - A[:, 0], x[1] - A[:, 1]) - z

        def jac(x: Array) -> Array:
            d = x - A
            return d / np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-12)[:, None]

        r = least_squares(f, x0, jac=jac, loss="huber", f_scale=2 * SIGMA_M)
        out[i] = r.x if r.success else np.nan
    return Fixes(out, "scipy least_squares(huber) per epoch")


def numpy_bare_ls(wl: Workload) -> Fixes:
    """Ceiling reference: bare batched NumPy LS on the eq. (3) system (no checks, no
    statuses, no covariance): normal equations solved for all epochs at once."""
    G, h = linearized_system(wl.anchors, wl.ranges)
    Gt = G[0].T
    x = np.linalg.solve(Gt @ G[0], Gt @ h.T).T
    return Fixes(x, "numpy normal equations, all epochs at once")


PEERS: dict[str, Callable[[Workload], Fixes]] = {
    "statsmodels-RLM(HuberT)": statsmodels_rlm,
    "scipy-least_squares(huber)": scipy_huber,
}


# ----------------------------------------------------------------------------- harness


@dataclass
class Row:
    method: str
    epochs: int
    seconds: float
    fixes_per_s: float
    us_per_fix: float
    ratio_vs_statsmodels: float
    peak_mem_mb: float
    rms_m: float
    p95_m: float
    failed_pct: float
    how: str


def _subset(wl: Workload, n: int) -> Workload:
    return Workload(wl.anchors, wl.truth[:n], wl.ranges[:n], wl.outlier[:n])


def measure(
    name: str, fn: Callable[[Workload], Fixes], wl: Workload, memory: bool, repeats: int = 1
) -> Row:
    """Time ``fn`` on the workload (best of ``repeats`` calls: on a shared machine the
    fastest run is the least disturbed one); optionally one more, traced call for memory.

    A warm-up call on 20 epochs first, so imports, first-call and numba compilation costs
    are not timed.
    """
    fn(_subset(wl, 20))
    dt = float("inf")
    for _ in range(max(repeats, 1)):
        t = time.perf_counter()
        fx = fn(wl)
        dt = min(dt, time.perf_counter() - t)
    peak = float("nan")
    if memory:
        tracemalloc.start()
        fn(wl)
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    err = np.linalg.norm(fx.position - wl.truth, axis=1)
    ok = np.isfinite(err)
    n = wl.ranges.shape[0]
    return Row(
        method=name,
        epochs=n,
        seconds=dt,
        fixes_per_s=n / dt,
        us_per_fix=1e6 * dt / n,
        ratio_vs_statsmodels=float("nan"),
        peak_mem_mb=peak,
        rms_m=float(np.sqrt(np.mean(err[ok] ** 2))) if ok.any() else float("nan"),
        p95_m=float(np.percentile(err[ok], 95)) if ok.any() else float("nan"),
        failed_pct=100.0 * float(np.mean(~ok)),
        how=fx.how,
    )


def run(
    epochs: int,
    peer_epochs: int,
    methods: list[str],
    seed: int,
    memory: bool = True,
    mad_scale: bool = False,
    solver: str = "nonlinear",
    repeats: int = 3,
    numpy_methods: tuple[str, ...] = ("nls", "huber", "igg"),
) -> list[Row]:
    """Run the peers and our methods; return one row each (ratio filled in).

    ``numpy_methods`` are also run with ``Locator(engine="numpy")`` (rows ``name[numpy]``):
    the batched NumPy implementation that the compiled kernels reproduce.
    """
    wl = make_workload(epochs, seed)
    rows: list[Row] = []
    peer_wl = _subset(wl, min(peer_epochs, epochs))
    for name, fn in PEERS.items():
        print(f"  {name} on {peer_wl.ranges.shape[0]} epochs ...", file=sys.stderr)
        rows.append(measure(name, fn, peer_wl, memory))
    print(f"  numpy bare LS on {epochs} epochs ...", file=sys.stderr)
    rows.append(measure("numpy-bare-LS(reference)", numpy_bare_ls, wl, memory))
    for m in methods:
        print(f"  {m} on {epochs} epochs ...", file=sys.stderr)
        try:
            fn = our_solver(m, mad_scale, solver)
            rows.append(measure(m, fn, wl, memory, repeats))
            if m in numpy_methods and (solver == "nonlinear" or m not in SOLVER_METHODS):
                fn = our_solver(m, mad_scale, solver, engine="numpy")
                rows.append(measure(f"{m}[numpy]", fn, wl, False))
        except NotImplementedError as e:
            print(f"  skipped: {e}", file=sys.stderr)
    ref = rows[0].us_per_fix
    for r in rows:
        r.ratio_vs_statsmodels = ref / r.us_per_fix
    return rows


def option_notes(methods: list[str], numpy_methods: tuple[str, ...], solver: str,
                 mad_scale: bool) -> list[str]:
    """One line per requested row that is not run, or option that does not apply."""
    notes = []
    if solver == "linearized":
        applies = SOLVER_METHODS + (("snooping",) if mad_scale else ())
        same = [m for m in methods if m not in applies]
        if same:
            notes.append(f"--solver linearized does not apply to {', '.join(same)} "
                         f"(only to {', '.join(applies)}): run as without it")
        dropped = [m for m in numpy_methods if m in methods and m in SOLVER_METHODS]
        if dropped:
            notes.append(f"--solver linearized: no [numpy] row for {', '.join(dropped)} (the "
                         "linearized solver has no compiled kernel: it would repeat the row)")
    if mad_scale and "auto" in methods:
        notes.append("--mad-scale does not apply to auto (it estimates the log's scale "
                     "itself): run as without it")
    linear = [m for m in ("ls", "wls") if m in methods]
    if mad_scale and linear:
        notes.append(f"--mad-scale does not change the fixes of {', '.join(linear)} (a sigma "
                     "common to every anchor weights them alike)")
    absent = [m for m in numpy_methods if m not in methods]
    if absent:
        notes.append(f"--numpy-methods {', '.join(absent)}: not in --methods, no [numpy] row")
    return notes


def format_table(rows: list[Row]) -> str:
    head = (
        f"{'method':<28}{'epochs':>8}{'fixes/s':>12}{'us/fix':>10}{'x RLM':>9}"
        f"{'peak MB':>9}{'RMS m':>8}{'p95 m':>8}{'fail %':>8}  called"
    )
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r.method:<28}{r.epochs:>8d}{r.fixes_per_s:>12,.0f}{r.us_per_fix:>10.2f}"
            f"{r.ratio_vs_statsmodels:>9.1f}{r.peak_mem_mb:>9.1f}{r.rms_m:>8.3f}{r.p95_m:>8.3f}"
            f"{r.failed_pct:>8.2f}  {r.how}"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--epochs", type=int, default=100_000, help="epochs for our methods")
    ap.add_argument("--peer-epochs", type=int, default=500, help="epochs for per-epoch peers")
    ap.add_argument("--quick", action="store_true", help="5 000 epochs, 200 peer epochs")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods")
    ap.add_argument("--seed", type=int, default=0,
                    help="seed of the simulated workload (default: %(default)s)")
    ap.add_argument("--no-memory", action="store_true", help="skip the traced memory run")
    ap.add_argument("--mad-scale", action="store_true",
                    help="no a-priori sigma: the robust methods, nls and snooping scale "
                         "their residuals themselves (no effect on auto, which estimates the "
                         "log's scale itself, nor on the fixes of ls and wls)")
    ap.add_argument(
        "--solver",
        choices=("nonlinear", "linearized"),
        default="nonlinear",
        help="robust methods and lege: nonlinear (default) or the paper's linearized system "
             "(not auto, ls, wls, nls; snooping only with --mad-scale; with linearized the "
             "[numpy] rows of the robust methods and lege are dropped)",
    )
    ap.add_argument("--repeats", type=int, default=3,
                    help="timed calls per method, the best is reported (default 3)")
    ap.add_argument("--numpy-methods", default="nls,huber,igg",
                    help="methods (of --methods) also timed with the NumPy engine ('' for "
                         "none; default: %(default)s)")
    ap.add_argument("--threads", type=int, default=None,
                    help="threads of the compiled kernels (numba.set_num_threads; default: "
                         "numba's, all cores unless NUMBA_NUM_THREADS says otherwise); "
                         "a batch of 4096 epochs or more is split over them")
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    ap.add_argument("-o", "--out", help="also write the rows to this CSV file")
    args = ap.parse_args(argv)
    import numba

    if args.threads is not None:
        if not 1 <= args.threads <= numba.config.NUMBA_NUM_THREADS:
            ap.error(f"--threads must lie in 1..{numba.config.NUMBA_NUM_THREADS}")
        numba.set_num_threads(args.threads)
    if args.quick:
        args.epochs, args.peer_epochs = 5_000, 200
    if args.epochs < 1 or args.peer_epochs < 1:
        ap.error("--epochs and --peer-epochs must be positive")
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        ap.error(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    numpy_methods = tuple(m.strip() for m in args.numpy_methods.split(",") if m.strip())
    unknown = [m for m in numpy_methods if m not in METHODS]
    if unknown:
        ap.error(f"--numpy-methods: unknown method(s) {unknown}; choose from "
                 f"{', '.join(METHODS)}")
    notes = option_notes(methods, numpy_methods, args.solver, args.mad_scale)
    for note in notes:  # before the run, and under the table
        print(f"note: {note}", file=sys.stderr)
    rows = run(
        args.epochs,
        args.peer_epochs,
        methods,
        args.seed,
        memory=not args.no_memory,
        mad_scale=args.mad_scale,
        solver=args.solver,
        repeats=args.repeats,
        numpy_methods=numpy_methods,
    )
    if args.out:
        import pandas as pd

        pd.DataFrame([asdict(r) for r in rows]).to_csv(args.out, index=False)
    if args.json:
        print(json.dumps([asdict(r) for r in rows], indent=2))
    else:
        print(
            f"{args.epochs} epochs x 10 anchors, 2-D, range sigma {SIGMA_M} m, "
            f"{OUTLIER_RATE:.0%} outliers U(3,15) m, seed {args.seed}; "
            f"peers timed on {min(args.peer_epochs, args.epochs)} epochs; "
            f"compiled kernels on {numba.get_num_threads()} thread(s), peers on one"
        )
        print(format_table(rows))
        for note in notes:
            print(f"note: {note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
