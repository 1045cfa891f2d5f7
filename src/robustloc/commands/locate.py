"""``robustloc locate``: position fixes for every epoch of a measurements log."""

from __future__ import annotations

import argparse
import json
import sys
import time as _time
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.engines import add_engine_arguments

NAME = "locate"
HELP = "position fixes from RSSI or ranges (LS, WLS, Gauss-Newton, robust IRLS, LEGE, ...)"
DESCRIPTION = """\
Solves every epoch (one time and tag) of a measurements file against the anchors and
writes one positions row per epoch and method with a status (never a silently dropped
epoch). The file is streamed in chunks of --chunk-rows rows (rows must be sorted by
time), so logs of tens of millions of rows run in bounded memory.

Methods (comma-separated list allowed; the `method` column tells them apart):
  ls        the paper's linearized difference system (seed 000 eq. 3)
  wls       the same, weighted by distance (seed 001 eq. 4)
  nls       Gauss-Newton on the raw observations, with covariance
  huber, hampel, igg, igg3
            robust IRLS (seed 000 eqs. 5-7) on the nonlinear equations (--solver
            nonlinear, default) or on the paper's linearized system
  lege      simultaneous location and estimation of gross errors (seed 000 sec. 2.4)
  snooping  w-test data snooping with the B-method (seed 003); needs --sigma

RSSI input uses the anchors' path-loss parameters (A, n or p0, gamma, faf, d0; see
`robustloc calibrate`); the nonlinear solvers fit ranges converted by the model, each
with sigma_d = d ln10 sigma_dB / (10 n), so a faded (long-reading) link down-weights
itself (--domain rssi fits in dB instead). Range input is corrected with the anchors' `bias`/`scale`
columns when present: range_corrected = (range - bias) / scale. An anchors' `sigma` column
(per-anchor observation std, m or dB) weights the anchors unless --sigma is given.

In 2-D, anchors' z is ignored unless --tag-height H is given, in which case slant ranges
are reduced with the known height difference z_anchor - H.

  robustloc locate meas.csv --anchors anchors.csv -o positions.csv
  robustloc locate meas.csv --anchors anchors.csv --method ls,nls,igg,lege -o all.csv"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.estimators.ranging import METHODS

    p.add_argument("measurements", help="measurements file (time, tag, anchor, rssi|range)")
    p.add_argument("--anchors", required=True, help="anchors file (anchor, x, y[, z], ...)")
    p.add_argument(
        "--method", default="huber",
        help=f"method or comma-separated methods: {', '.join(METHODS)} (default huber: the "
             "most accurate on the shared real data; igg is the seed-000 paper's favourite)",
    )
    p.add_argument("-o", "--out", required=True, help="positions file (.csv or .parquet)")
    p.add_argument("--dim", type=int, choices=(2, 3), default=2, help="solve in 2-D or 3-D")
    p.add_argument("--solver", choices=("nonlinear", "linearized"), default="nonlinear",
                   help="robust methods and LEGE: nonlinear equations (default) or linearized")
    p.add_argument("--reference", choices=("first", "nearest"), default="first",
                   help="linearized system: reference anchor = first heard (paper) or the "
                        "one with the shortest range")
    p.add_argument("--domain", choices=("range", "rssi"), default="range",
                   help="RSSI input, nonlinear solvers: fit ranges converted by the model "
                        "(default; fades then down-weight themselves) or fit in dB")
    p.add_argument("--sigma", type=float, default=None,
                   help="a-priori std of one observation (m or dB); default: the anchors' "
                        "`sigma` column (per-anchor, e.g. from calibrate) if present, else "
                        "equal weights")
    p.add_argument("--robust-scale", choices=("mad", "apriori"), default="mad",
                   help="robust methods: estimate the noise scale per epoch (mad, default) "
                        "or trust --sigma")
    p.add_argument("--min-scale", type=float, default=0.0,
                   help="floor of the estimated robust scale (units of --sigma)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="weight-function threshold, e.g. --param c=1.5 (repeatable)")
    p.add_argument("--model", choices=("log-distance", "attenuation-factor", "friis"),
                   default=None, help="path-loss columns to use (default: what the anchors have)")
    p.add_argument("--tag-height", type=float, default=None,
                   help="2-D only: known tag height, to reduce slant ranges (m)")
    p.add_argument("--no-range-calibration", action="store_true",
                   help="ignore the anchors' bias/scale columns")
    p.add_argument("--alpha0", type=float, default=0.001, help="w-test significance (snooping)")
    p.add_argument("--beta0", type=float, default=0.10, help="B-method type II error (snooping)")
    p.add_argument("--chunk-rows", type=int, default=500_000, help="rows read per chunk")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_engine_arguments(p)


def _params(items: list[str]) -> dict[str, float]:
    out: dict[str, float] = {}
    for it in items:
        name, sep, val = it.partition("=")
        try:
            if not sep:
                raise ValueError
            out[name.strip()] = float(val)
        except ValueError:
            raise ValueError(f"--param expects NAME=NUMBER, got {it!r}") from None
    return out


def locate_file(args: argparse.Namespace) -> dict:
    """Run ``locate`` as configured by ``args``; returns the summary."""
    from tqdm import tqdm

    from robustloc._jitnotice import compile_notice
    from robustloc.errors import InputError
    from robustloc.estimators.ranging import Locator
    from robustloc.io import iter_epochs, positions_frame, read_anchors
    from robustloc.io.tables import PositionsWriter
    from robustloc.models.calibration import apply_range_calibration
    from robustloc.models.pathloss import log_distance_arrays

    anchors = read_anchors(args.anchors)
    ids = [str(a) for a in anchors["anchor"]]
    if args.dim == 3 and "z" not in anchors.columns:
        raise InputError("--dim 3 needs a z column in the anchors file", args.anchors, 1)
    cols = ["x", "y"] + (["z"] if args.dim == 3 else [])
    xyz = anchors[cols].to_numpy(dtype=float)
    height = None
    if args.tag_height is not None:
        if args.dim != 2 or "z" not in anchors.columns:
            raise InputError("--tag-height needs --dim 2 and a z column in the anchors file",
                             args.anchors, 1)
        height = anchors["z"].to_numpy(dtype=float) - args.tag_height
    methods = [m.strip() for m in args.method.split(",") if m.strip()]
    params = _params(args.param)
    sigma: float | tuple[float, ...] | None = args.sigma
    if sigma is None and "sigma" in anchors.columns:
        sg = anchors["sigma"].to_numpy(dtype=float)
        if not np.all(np.isfinite(sg) & (sg > 0)):
            raise InputError("anchors' sigma column must be positive and finite", args.anchors)
        sigma = tuple(sg)
    locators = [
        Locator(
            m, solver=args.solver, domain=args.domain, sigma=sigma,
            robust_scale=args.robust_scale, reference=args.reference,
            weight_params=params if m in ("huber", "hampel", "igg", "igg3") else {},
            min_scale=args.min_scale, alpha0=args.alpha0, beta0=args.beta0,
        )
        for m in methods
    ]
    out = Path(args.out)
    writer = PositionsWriter(out).__enter__()
    counts: dict[str, dict[str, int]] = {m: {} for m in methods}
    n_epochs = n_dup = 0
    A = n = None
    kind = None
    t0 = _time.perf_counter()
    solve_s = 0.0
    bar = tqdm(unit=" epochs", disable=args.quiet or not sys.stderr.isatty(), file=sys.stderr)
    try:
        for block in iter_epochs(args.measurements, anchors, chunk_rows=args.chunk_rows):
            if kind is None:  # the first block: its input is valid, solving starts
                compile_notice("positioning")
                kind = block.value
                if kind == "rssi":
                    A, n = log_distance_arrays(anchors, args.model)
            values = block.values
            if kind == "range" and not args.no_range_calibration:
                values = apply_range_calibration(anchors, values)
            frames = []
            for loc in locators:
                ts = _time.perf_counter()
                sol = loc.solve(xyz, values, kind, A=A, n=n, height_offset=height)
                solve_s += _time.perf_counter() - ts
                frames.append(positions_frame(sol, block.time, block.tag, ids, loc.method))
                st, c = np.unique(sol.status.astype(str), return_counts=True)
                for s_, c_ in zip(st, c):
                    counts[loc.method][s_] = counts[loc.method].get(s_, 0) + int(c_)
            writer.write(pd.concat(frames, ignore_index=True) if len(frames) > 1 else frames[0])
            n_epochs += block.n_epochs
            n_dup += block.n_duplicates
            bar.update(block.n_epochs)
    finally:
        writer.__exit__(None, None, None)
        bar.close()
    wall = _time.perf_counter() - t0
    return {
        "measurements": str(args.measurements), "positions": str(out), "value": kind,
        "epochs": n_epochs, "methods": methods, "status": counts,
        "duplicates_merged": n_dup, "seconds": round(wall, 3),
        "solve_seconds": round(solve_s, 3),
        "fixes_per_second": round(n_epochs * len(methods) / max(solve_s, 1e-9), 1),
    }


def run(args: argparse.Namespace) -> int:
    if args.engine == "dask":
        from robustloc.engines.dask import run_locate
        return run_locate(args, locate_file)
    summary = locate_file(args)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"{summary['epochs']} epochs of {summary['value']} -> {summary['positions']} "
          f"({summary['seconds']:.2f} s, {summary['fixes_per_second']:.0f} fixes/s solving)")
    if summary["duplicates_merged"]:
        print(f"  {summary['duplicates_merged']} duplicate rows (same epoch and anchor) averaged")
    for m, c in summary["status"].items():
        print(f"  {m:9s} " + ", ".join(f"{k}: {v}" for k, v in sorted(c.items())))
    return 0
