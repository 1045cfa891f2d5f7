"""``robustloc locate``: position fixes for every epoch of a measurements log."""

from __future__ import annotations

import argparse
import json
import sys
import time as _time

import numpy as np
import pandas as pd

from robustloc.engines import add_engine_arguments

NAME = "locate"
HELP = "position fixes from RSSI or ranges (LS, WLS, Gauss-Newton, robust IRLS, LEGE, ...)"
DESCRIPTION = """\
Solves every epoch (one time and tag) of a measurements file against the anchors and
writes one positions row per epoch and method with a status (never a silently dropped
epoch). Rows may come in any order (several tags' logs one after another, shuffled): a
file in epoch order (time non-decreasing, each epoch's rows together) is streamed in
chunks of --chunk-rows rows, in bounded memory whatever the grouping; any other order is
sorted first (in memory when it fits, else out of core with DuckDB). `-` reads standard
input. The positions file is written atomically (nothing is left at -o after an error,
Ctrl-C or a full disk); `-o -` writes CSV to standard output and the run summary to
stderr. A value outside the physical limits (robustloc.io.limits: range -50..1e5 m, RSSI
-150..+30 dBm, |time| < 1e12 s) is not used and is counted (`invalid_measurement: N
rows`); an epoch with nothing else gets status invalid_measurement.

Methods (comma-separated list allowed; the `method` column tells them apart):
  auto      the default: Gauss-Newton (nls) on every epoch that passes its own test,
            the robust huber fit on the epochs whose test finds a fault ("test, then
            robustify": no efficiency lost where the data agree with the noise model;
            chosen by measurement, see the report's "out of the box" section)
  ls        the paper's linearized difference system (seed 000 eq. 3)
  wls       the same, weighted by distance (seed 001 eq. 4)
  nls       Gauss-Newton on the raw observations, with covariance
  huber, hampel, igg, igg3
            robust IRLS (seed 000 eqs. 5-7) on the nonlinear equations (--solver
            nonlinear, default) or on the paper's linearized system
  asym      robust IRLS with the asymmetric IGG weight (seed 002 eq. 14) turned to
            ranges: a long range (NLOS, a fade) is rejected from 3 sigma, a short one
            only from 5
  lege      simultaneous location and estimation of gross errors (seed 000 sec. 2.4)
  snooping  w-test data snooping with the B-method (seed 003)

Every fix is tested and gets a protection level (robustloc.integrity.fixes): the noise
scale of each anchor comes from the whole log (--robust-scale log, a first pass over an
even sample of it), the w-test flags observations the fix does not explain, the global
test (B-method significance) checks the rest, and `hpl` (`vpl` in 3-D) is the MDB slope
bound plus k sigma of the fault-free noise (--alpha0, --beta0, --k-noise).  Statuses:
ok, fault_excluded, low_redundancy (redundancy 1: detectable, not identifiable),
unverified (redundancy 0, hpl = inf), fault_detected (the test fails; hpl widened by the
a-posteriori variance factor), extrapolated (farther than 10x the anchors' extent), all
usable with not_converged; protection_exceeded (hpl > --alert-limit), insufficient_anchors,
ill_conditioned and invalid_measurement are not.

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


def _method_list(text: str) -> list[str]:
    """``--method`` value: comma-separated known methods, each once."""
    from robustloc.estimators.ranging import METHODS

    METHODS = ("auto",) + METHODS  # noqa: N806 - the default joins the estimators' list
    methods = [m.strip() for m in text.split(",")]
    if not any(methods):
        raise argparse.ArgumentTypeError(
            f"expected one or more of {', '.join(METHODS)}, got {text!r}")
    if "" in methods:
        raise argparse.ArgumentTypeError(f"empty method name in {text!r}")
    for m in methods:
        if m not in METHODS:
            raise argparse.ArgumentTypeError(
                f"unknown method {m!r}; choose from {', '.join(METHODS)}")
    dup = [m for i, m in enumerate(methods) if m in methods[:i]]
    if dup:
        raise argparse.ArgumentTypeError(f"method {dup[0]!r} given twice in {text!r}")
    return methods


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.commands._argtypes import (
        finite_float,
        float_in,
        nonnegative_float,
        positive_float,
        positive_int,
    )
    from robustloc.estimators.ranging import DEFAULT_METHOD, METHODS

    p.add_argument("measurements",
                   help="measurements file (time, tag, anchor, rssi|range); - for stdin")
    p.add_argument("--anchors", required=True, help="anchors file (anchor, x, y[, z], ...)")
    p.add_argument(
        "--method", default=[DEFAULT_METHOD], type=_method_list,
        help=f"method or comma-separated methods: {', '.join(('auto',) + METHODS)} "
             f"(default {DEFAULT_METHOD}: see above; igg is the seed-000 paper's favourite)",
    )
    p.add_argument("-o", "--out", required=True,
                   help="positions file (.csv or .parquet); - for CSV on standard output")
    p.add_argument("--dim", type=int, choices=(2, 3), default=2, help="solve in 2-D or 3-D")
    p.add_argument("--solver", choices=("nonlinear", "linearized"), default="nonlinear",
                   help="robust methods and LEGE: nonlinear equations (default) or linearized")
    p.add_argument("--reference", choices=("first", "nearest"), default="first",
                   help="linearized system: reference anchor = first heard (paper) or the "
                        "one with the shortest range")
    p.add_argument("--domain", choices=("range", "rssi"), default="range",
                   help="RSSI input, nonlinear solvers: fit ranges converted by the model "
                        "(default; fades then down-weight themselves) or fit in dB")
    p.add_argument("--sigma", type=positive_float, default=None,
                   help="a-priori std of one observation (m or dB); default: the anchors' "
                        "`sigma` column (per-anchor, e.g. from calibrate) if present, else "
                        "equal weights")
    p.add_argument("--robust-scale", choices=("log", "mad", "apriori"), default="log",
                   help="noise scale of the robust methods and of every fix's test and "
                        "protection level: per anchor over the log (log, default: a first "
                        "robust pass over an even sample of the whole log), per epoch from "
                        "its own residuals (mad, the paper's), or trust --sigma (apriori)")
    p.add_argument("--alert-limit", type=positive_float, default=None, metavar="L",
                   help="horizontal alert limit (m): a fix whose hpl exceeds it gets status "
                        "protection_exceeded (not usable)")
    p.add_argument("--k-noise", type=nonnegative_float, default=None, metavar="K",
                   help="protection levels: multiplier of the fault-free noise (default "
                        "N(1 - alpha0/2) = 3.29 for alpha0 = 0.1 %%)")
    p.add_argument("--min-scale", type=nonnegative_float, default=0.0,
                   help="floor of the estimated robust scale (units of --sigma)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="weight-function threshold, e.g. --param c=1.5 (repeatable)")
    p.add_argument("--model", choices=("log-distance", "attenuation-factor", "friis"),
                   default=None, help="path-loss columns to use (default: what the anchors have)")
    p.add_argument("--tag-height", type=finite_float, default=None,
                   help="2-D only: known tag height, to reduce slant ranges (m)")
    p.add_argument("--no-range-calibration", action="store_true",
                   help="ignore the anchors' bias/scale columns")
    p.add_argument("--alpha0", type=float_in(1e-12, 0.5), default=0.001,
                   help="w-test significance (snooping)")
    p.add_argument("--beta0", type=float_in(1e-6, 0.99), default=0.10,
                   help="B-method type II error (snooping)")
    p.add_argument("--chunk-rows", type=positive_int, default=500_000,
                   help="rows read per chunk")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON")
    p.add_argument("--quiet", action="store_true",
                   help="no progress bar and no text summary")
    add_engine_arguments(p)


def _params(items: list[str], methods: list[str]) -> dict[str, dict[str, float]]:
    """``--param NAME=VALUE`` items -> per robust method, the thresholds it knows.

    A name that no chosen robust method has is an error naming the known ones."""
    import dataclasses
    import math

    from robustloc.errors import InputError
    from robustloc.estimators.ranging import ROBUST, method_weight
    from robustloc.integrity.fixes import AUTO, AUTO_ROBUST

    # 'auto' refits failing epochs with AUTO_ROBUST: its thresholds apply there
    robust = [m for m in methods if m in ROBUST or m == AUTO]
    known = {m: [f.name for f in dataclasses.fields(
        type(method_weight(AUTO_ROBUST if m == AUTO else m)))] for m in robust}
    out: dict[str, dict[str, float]] = {m: {} for m in robust}
    for it in items:
        name, sep, val = it.partition("=")
        name = name.strip()
        try:
            value = float(val) if sep and name else math.nan
        except ValueError:
            value = math.nan
        if not math.isfinite(value):
            raise InputError(f"--param expects NAME=NUMBER (finite), got {it!r}")
        if not robust:
            raise InputError(f"--param {name}: weight-function thresholds apply only to the "
                             f"robust methods {', '.join(ROBUST)}")
        users = [m for m in robust if name in known[m]]
        if not users:
            names = "; ".join(f"{m}: {', '.join(known[m])}" for m in robust)
            raise InputError(f"--param {name!r} is not a threshold of the chosen method(s) "
                             f"(known: {names})")
        for m in users:
            out[m][name] = value
    return out


def _locators(args: argparse.Namespace, anchors: pd.DataFrame) -> tuple:
    """The configured locators, the anchors' coordinates and height offsets."""
    from robustloc.errors import InputError
    from robustloc.estimators.ranging import Locator

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
    methods = list(args.method)
    params = _params(args.param, methods)
    sigma: float | tuple[float, ...] | None = args.sigma
    if sigma is None and "sigma" in anchors.columns:
        sg = anchors["sigma"].to_numpy(dtype=float)
        if not np.all(np.isfinite(sg) & (sg > 0)):
            raise InputError("anchors' sigma column must be positive and finite", args.anchors)
        sigma = tuple(sg)
    try:  # the settings are the user's: a refused combination is a user error
        locators = [
            Locator(
                m, solver=args.solver, domain=args.domain, sigma=sigma,
                robust_scale=args.robust_scale, reference=args.reference,
                weight_params=params.get(m, {}),
                min_scale=args.min_scale, alpha0=args.alpha0, beta0=args.beta0,
            )
            for m in methods
        ]
    except (ValueError, TypeError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"invalid settings: {exc}") from None
    return locators, anchors, xyz, height


def locate_file(args: argparse.Namespace) -> dict:
    """Run ``locate`` as configured by ``args``; returns the summary."""
    from robustloc.io import read_anchors
    from robustloc.io.atomic import check_not_input, is_stdio
    from robustloc.io.tables import UnsortedInput

    check_not_input(args.out, [args.measurements, args.anchors])
    locators, anchors, xyz, height = _locators(args, read_anchors(args.anchors))
    if any(loc.robust_scale == "log" for loc in locators):
        try:
            locators = _fix_log_scale(args, anchors, locators, xyz, height, "auto")
        except UnsortedInput:
            locators = _fix_log_scale(args, anchors, locators, xyz, height, "sort")
    out = args.out
    # a restartable output (a regular file: the temporary file is discarded) streams and
    # restarts sorted if the rows turn out not to be in epoch order; standard output or a
    # device cannot be taken back, so the order is checked first.
    rewindable = not is_stdio(out) and not _is_special(out)
    order = "auto" if rewindable else "check"
    while True:
        try:
            summary = _run_once(args, order, locators, anchors, xyz, height)
            break
        except UnsortedInput:
            if order != "auto":
                raise
            order = "sort"
    return summary


def _is_special(path: str) -> bool:
    import os
    import stat

    try:
        return not stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


def _run_once(
    args: argparse.Namespace, order: str, locators: list, anchors: pd.DataFrame,
    xyz: np.ndarray, height: np.ndarray | None,
) -> dict:
    """One pass over the measurements; raises UnsortedInput (output discarded) when the
    streamed rows turn out not to be in epoch order."""
    from tqdm import tqdm

    from robustloc._jitnotice import compile_notice
    from robustloc.integrity.fixes import locate_protected
    from robustloc.io import iter_epochs, positions_frame
    from robustloc.io.tables import PositionsWriter
    from robustloc.models.pathloss import log_distance_arrays
    from robustloc.status import INVALID

    out = args.out
    methods = [loc.method for loc in locators]
    ids = [str(a) for a in anchors["anchor"]]
    counts: dict[str, dict[str, int]] = {m: {} for m in methods}
    n_epochs = n_dup = n_invalid = 0
    A = n = None
    kind = None
    t0 = _time.perf_counter()
    solve_s = 0.0
    bar = tqdm(unit=" epochs", disable=args.quiet or not sys.stderr.isatty(), file=sys.stderr)
    try:
        with PositionsWriter(out) as writer:
            for block in iter_epochs(args.measurements, anchors, chunk_rows=args.chunk_rows,
                                     order=order):
                if kind is None:  # the first block: its input is valid, solving starts
                    compile_notice("positioning")
                    kind = block.value
                    if kind == "rssi":
                        A, n = log_distance_arrays(anchors, args.model)
                values = _prepared_values(args, anchors, block)
                bad = block.all_invalid
                frames = []
                for loc in locators:
                    ts = _time.perf_counter()
                    sol = locate_protected(
                        loc, xyz, values, kind, A=A, n=n, height_offset=height,
                        alpha0=args.alpha0, beta0=args.beta0, k_noise=args.k_noise,
                        alert_limit=args.alert_limit)
                    solve_s += _time.perf_counter() - ts
                    fr = positions_frame(sol, block.time, block.tag, ids, loc.method)
                    if bad.any():  # every row of the epoch was outside the physical limits
                        fr.loc[bad, "status"] = INVALID
                        fr.loc[bad, [c for c in ("x", "y", "z", "sigma0") if c in fr]] = np.nan
                        fr.loc[bad, "n_used"] = 0
                    frames.append(fr)
                    st, c = np.unique(fr["status"].to_numpy(dtype=str), return_counts=True)
                    for s_, c_ in zip(st, c):
                        counts[loc.method][s_] = counts[loc.method].get(s_, 0) + int(c_)
                writer.write(pd.concat(frames, ignore_index=True) if len(frames) > 1
                             else frames[0])
                n_epochs += block.n_epochs
                n_dup += block.n_duplicates
                n_invalid += int(block.n_invalid.sum())
                bar.update(block.n_epochs)
    finally:
        bar.close()
    wall = _time.perf_counter() - t0
    return {
        "measurements": str(args.measurements), "positions": str(out), "value": kind,
        "epochs": n_epochs, "methods": methods, "status": counts,
        "duplicates_merged": n_dup, "invalid_measurement_rows": n_invalid,
        "sorted_first": order == "sort", "seconds": round(wall, 3),
        "solve_seconds": round(solve_s, 3),
        "fixes_per_second": round(n_epochs * len(methods) / max(solve_s, 1e-9), 1),
    }


def _prepared_values(args: argparse.Namespace, anchors: pd.DataFrame, block) -> np.ndarray:
    """A block's observation matrix as the solvers see it (range calibration applied)."""
    from robustloc.models.calibration import apply_range_calibration

    if block.value == "range" and not args.no_range_calibration:
        return apply_range_calibration(anchors, block.values)
    return block.values


#: The first pass keeps at most ``2 LOG_SAMPLE_CAP`` epochs of the log (an even sample).
LOG_SAMPLE_CAP = 5_000


def log_sample_step(n_epochs: int, cap: int | None = None) -> int:
    """The first pass's sampling step ``k``: every ``k``-th epoch of the log (global epoch
    index ``i`` with ``i % k == 0``) is kept, ``k`` the smallest power of two that keeps at
    most ``2 cap`` of ``n_epochs`` (``ceil(n / k) <= 2 cap``).  The streamed first pass
    reaches the same ``k`` by doubling as the log grows, whatever the chunks.  ``cap``:
    default :data:`LOG_SAMPLE_CAP`."""
    cap = LOG_SAMPLE_CAP if cap is None else cap
    k = 1
    while -(-n_epochs // k) > 2 * cap:
        k *= 2
    return k


def _fix_log_scale(args, anchors, locators, xyz, height, order: str,
                   cap: int | None = None, paths: list | None = None) -> list:
    """First pass over the whole log: each locator's per-anchor noise scale from an even
    sample of at most ``2 cap`` epochs (every ``k``-th epoch, ``k`` doubling as the log
    grows: :func:`log_sample_step`), so the scale, and every fix, is the same whatever
    ``--chunk-rows`` is.  ``paths``: the log's files in order (a partitioned dataset;
    default the one file).  ``args.log_scale_fixed`` (set by the Dask engine, which
    computes it once for the whole dataset) is used as it is."""
    from dataclasses import replace

    from robustloc.io import iter_epochs

    cap = LOG_SAMPLE_CAP if cap is None else cap
    fixed = getattr(args, "log_scale_fixed", None)
    if fixed is not None:
        return [replace(loc, log_scale_fixed=tuple(fixed[loc.method]))
                if loc.robust_scale == "log" else loc for loc in locators]
    if paths is None:  # standard input and FIFOs are spooled once (io.tables): re-readable
        paths = [args.measurements]
    k, seen, kept, idx = 1, 0, [], []
    kind = None
    blocks = (b for path in paths for b in iter_epochs(path, anchors,
                                                       chunk_rows=args.chunk_rows, order=order))
    for block in blocks:
        kind = block.value
        gi = np.arange(seen, seen + block.n_epochs)
        seen += block.n_epochs
        sel = gi % k == 0
        kept.append(_prepared_values(args, anchors, block)[sel])
        idx.append(gi[sel])
        while sum(len(i) for i in idx) > 2 * cap:
            k *= 2
            kept = [v[i % k == 0] for v, i in zip(kept, idx)]
            idx = [i[i % k == 0] for i in idx]
    if kind is None:
        return locators
    return log_scales_from_sample(args, anchors, locators, xyz, height, kind,
                                  np.vstack(kept), cap)


def log_scales_from_sample(args, anchors, locators, xyz, height, kind: str,
                           sample: np.ndarray, cap: int | None = None) -> list:
    """The locators with their per-anchor log scale fixed from the first pass's
    ``sample`` (its epochs' prepared values, in log order)."""
    from dataclasses import replace

    from robustloc.models.pathloss import log_distance_arrays

    cap = LOG_SAMPLE_CAP if cap is None else cap
    A = n = None
    if kind == "rssi":
        A, n = log_distance_arrays(anchors, args.model)
    out = []
    for loc in locators:
        if loc.robust_scale != "log":
            out.append(loc)
            continue
        scale = loc.log_scale(xyz, sample, kind, A=A, n=n, height_offset=height,
                              max_epochs=2 * cap)
        out.append(replace(loc, log_scale_fixed=tuple(float(v) for v in scale)))
    return out


def log_sample_of(args: argparse.Namespace, path: str, offset: int, k: int
                  ) -> tuple[str | None, np.ndarray, int]:
    """One file's share of the first pass when the log is split in files: its epochs
    whose global index (``offset`` + index in the file) is a multiple of ``k``.

    Returns ``(kind, prepared values of those epochs, epochs in the file)``; the caller
    stacks the files' samples in log order (the Dask engine, on the workers)."""
    from robustloc.io import iter_epochs, read_anchors
    from robustloc.io.tables import UnsortedInput

    _, anchors, _, _ = _locators(args, read_anchors(args.anchors))

    def sample(order: str) -> tuple[str | None, np.ndarray, int]:
        kind, seen, kept = None, 0, []
        for block in iter_epochs(path, anchors, chunk_rows=args.chunk_rows, order=order):
            kind = block.value
            gi = offset + np.arange(seen, seen + block.n_epochs)
            seen += block.n_epochs
            kept.append(_prepared_values(args, anchors, block)[gi % k == 0])
        m = len(anchors)
        return kind, (np.vstack(kept) if kept else np.empty((0, m))), seen

    try:
        return sample("auto")
    except UnsortedInput:  # as the whole pass does: sorted, the same epochs in order
        return sample("sort")


def log_scales_for(args: argparse.Namespace, paths: list, cap: int | None = None,
                   sample: np.ndarray | None = None, kind: str | None = None
                   ) -> dict[str, tuple[float, ...]]:
    """Each method's per-anchor log scale over the files ``paths`` (in order), as
    ``locate`` estimates it in its first pass: what the Dask engine hands to every
    partition so that each solves with the whole dataset's scale.  With ``sample`` and
    ``kind`` (the files' :func:`log_sample_of` stacked in order, computed elsewhere), the
    files are not read again."""
    from robustloc.io import read_anchors
    from robustloc.io.tables import UnsortedInput

    locators, anchors, xyz, height = _locators(args, read_anchors(args.anchors))
    if sample is not None:
        fixed = (log_scales_from_sample(args, anchors, locators, xyz, height, kind, sample,
                                        cap) if kind is not None else locators)
    else:
        try:
            fixed = _fix_log_scale(args, anchors, locators, xyz, height, "auto", cap,
                                   paths=paths)
        except UnsortedInput:
            fixed = _fix_log_scale(args, anchors, locators, xyz, height, "sort", cap,
                                   paths=paths)
    return {loc.method: loc.log_scale_fixed for loc in fixed
            if loc.log_scale_fixed is not None}


def run(args: argparse.Namespace) -> int:
    from robustloc.io.atomic import writes_to_stdout

    if args.engine == "dask":
        from robustloc.engines.dask import run_locate
        return run_locate(args, locate_file)
    summary = locate_file(args)
    # the summary never goes into a data stream: stderr when the positions go to stdout
    dest = sys.stderr if writes_to_stdout(args.out) else sys.stdout
    if args.json:
        print(json.dumps(summary, indent=2), file=dest)
        return 0
    if args.quiet:
        return 0
    print(f"{summary['epochs']} epochs of {summary['value']} -> {summary['positions']} "
          f"({summary['seconds']:.2f} s, {summary['fixes_per_second']:.0f} fixes/s solving)",
          file=dest)
    if summary["sorted_first"]:
        print("  rows were not in epoch order: sorted by time and tag first", file=dest)
    if summary["duplicates_merged"]:
        print(f"  {summary['duplicates_merged']} duplicate rows (same epoch and anchor) averaged",
              file=dest)
    if summary["invalid_measurement_rows"]:
        print(f"  invalid_measurement: {summary['invalid_measurement_rows']} rows (outside the "
              "physical limits of robustloc.io.limits; not used)", file=dest)
    for m, c in summary["status"].items():
        print(f"  {m:9s} " + ", ".join(f"{k}: {v}" for k, v in sorted(c.items())), file=dest)
    return 0
