"""``robustloc locate``: position fixes for every epoch of a measurements log.

The command line over :mod:`robustloc.pipelines.locate`: its options are parsed into a
:class:`~robustloc.pipelines.locate.LocateSettings`, the pipeline runs, the summary is
printed.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from robustloc.engines import add_engine_arguments

if TYPE_CHECKING:
    from robustloc.pipelines.locate import LocateSettings

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
-150..+30 dBm, |time| <= 1e12 s) is not used and is counted (`invalid_measurement: N
rows`); an epoch with nothing else gets status invalid_measurement.

Methods (comma-separated list allowed; the `method` column tells them apart):
  auto      the default: Gauss-Newton (nls) on every epoch, each fix tested; the robust
            huber fit on the epochs whose test fails without naming the ranges at fault
            (a fix whose flagged ranges are all that fails stays nls, fault_detected);
            igg on every epoch of a log with more than 3.3 % gross residuals ("test,
            then robustify": no efficiency lost where the data agree with the noise
            model; chosen by measurement, see the report's "out of the box" section)
  ls        the paper's linearized difference system (seed 000 eq. 3)
  wls       the same, weighted by distance (seed 001 eq. 4)
  nls       Gauss-Newton on the raw observations, with covariance
  huber, hampel, igg, igg3
            robust IRLS (seed 000 eqs. 5-7) on the nonlinear equations (--solver
            nonlinear, default) or on the paper's linearized system
  asym      robust IRLS with the asymmetric IGG weight (seed 002 eq. 14) turned to
            ranges: a long range (NLOS, a fade) is rejected from 3 sigma, a short one
            only from 5
  lege      simultaneous location and estimation of gross errors (seed 000 sec. 2.4);
            it searches only where 7 anchors are heard (8 in 3-D: 4 degrees of freedom
            stay after its exclusions), below that its fix is nls'; it tries every set
            of suspects up to 20 000 sets per epoch, larger sets by forward selection
            (a warning says so)
  snooping  w-test data snooping with the B-method (seed 003)

Every fix is tested and gets a protection level (robustloc.integrity.fixes): the noise
scale of each anchor comes from the whole log (--robust-scale log, a first pass over an
even sample of it), the w-test flags observations the fix does not explain, the global
test (B-method significance) checks the rest, and `hpl` (`vpl` in 3-D) is the MDB slope
bound plus k sigma of the fault-free noise (--alpha0, --beta0, --k-noise).  Statuses:
ok, fault_excluded, low_redundancy (redundancy 1: detectable, not identifiable),
unverified (redundancy 0, hpl = inf), fault_detected (the test fails, or the w-test flags
a range that a plain fit, ls, wls, nls (and lege, snooping: the rows they kept) keeps;
hpl of the fix as it is, widened by the a-posteriori variance factor), extrapolated
(farther than 10x the anchors' extent; a failed test stays fault_detected), all
usable with not_converged; unavailable (a flagged observation leaves nothing to confirm
the rest, or half or more of the heard observations are flagged: no majority supports the
fix), protection_exceeded (hpl > --alert-limit), insufficient_anchors, ill_conditioned and
invalid_measurement are not.

Nearly collinear anchors (a corridor) fit a fix and its mirror image across their line
equally well; such a fix's hpl covers both.  With --side-prior log (default, with
--robust-scale log) an ambiguous fix is placed on the side of the line where the log's
unambiguous fixes lie, when a sign test finds them significantly more often on one side
(the wifi-rtt corridor: 6.08 -> 3.57 m RMS); --side-prior none leaves each fix where its
estimator put it.

RSSI input uses the anchors' path-loss parameters (A, n or p0, gamma, faf, d0; see
`robustloc calibrate`); the nonlinear solvers fit ranges converted by the model, each
with sigma_d = d ln10 sigma_dB / (10 n), so a faded (long-reading) link down-weights
itself (--domain rssi fits in dB instead). Range input is corrected with the anchors' `bias`/`scale`
columns when present: range_corrected = (range - bias) / scale. An anchors' `sigma` column
(per-anchor observation std, m or dB) weights the anchors unless --sigma is given.

In 2-D, anchors' z is ignored unless --tag-height H is given, in which case slant ranges
are reduced with the known height difference z_anchor - H.  In 3-D (--dim 3), anchors in
one plane (all on the ceiling) cannot tell a tag below them from its mirror image above:
the solvers start below the plane (lower z) and vpl covers the mirror.  The plane is that
of the anchors each epoch hears (an epoch that hears only the ceiling's anchors of a
layout with a few low ones is the same case); with the tag's height known, 2-D with
--tag-height is the better model.

  robustloc locate meas.csv --anchors anchors.csv -o positions.csv
  robustloc locate meas.csv --anchors anchors.csv --method ls,nls,igg,lege -o all.csv"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.estimators.ranging import DEFAULT_METHOD
    from robustloc.options import (
        float_in,
        nonnegative_float,
        positive_float,
        positive_int,
        scale_floor,
        sigma_value,
        tag_height_m,
    )
    from robustloc.pipelines.locate import PATH_LOSS_MODELS, method_list, methods_known

    p.add_argument("measurements",
                   help="measurements file (time, tag, anchor, rssi|range); - for stdin")
    p.add_argument("--anchors", required=True, help="anchors file (anchor, x, y[, z], ...)")
    p.add_argument(
        "--method", default=[DEFAULT_METHOD], type=method_list,
        help=f"method or comma-separated methods: {', '.join(methods_known())} "
             f"(default {DEFAULT_METHOD}: see above; igg is the seed-000 paper's favourite; "
             "asymmetric-igg, the weight's name in filter, fuse and track, = asym)",
    )
    p.add_argument("-o", "--out", required=True,
                   help="positions file (.csv or .parquet); - for CSV on standard output")
    p.add_argument("--dim", type=int, choices=(2, 3), default=2,
                   help="solve in 2-D or 3-D (default %(default)s)")
    p.add_argument("--solver", choices=("nonlinear", "linearized"), default="nonlinear",
                   help="robust methods and LEGE: nonlinear equations (default) or linearized")
    p.add_argument("--reference", choices=("first", "nearest"), default="first",
                   help="linearized solver (ls, wls, --solver linearized): reference "
                        "anchor = the first heard in the anchors file's order (the paper's; "
                        "its fixes then depend on that order) or the one with the shortest "
                        "range (the iterative solvers always start from the nearest, so "
                        "their fixes do not depend on the anchors' order; default %(default)s)")
    p.add_argument("--domain", choices=("range", "rssi"), default="range",
                   help="RSSI input, nonlinear solvers: fit ranges converted by the model "
                        "(default; fades then down-weight themselves) or fit in dB")
    p.add_argument("--sigma", type=sigma_value, default=None,
                   help="a-priori std of one observation (m or dB); default: the anchors' "
                        "`sigma` column (per-anchor, e.g. from calibrate) if present, else "
                        "equal weights.  With --robust-scale log (default) the log's noise "
                        "level is measured in units of it, so one value moves no fix and no "
                        "hpl (only sigma0, a ratio to it), except snooping's, which "
                        "tests against a given sigma as known; apriori trusts it")
    p.add_argument("--robust-scale", choices=("log", "mad", "apriori"), default="log",
                   help="noise scale of the robust methods and of every fix's test and "
                        "protection level: per anchor over the log (log, default: a first "
                        "robust pass over an even sample of the whole log), per epoch from "
                        "its own residuals (mad, the paper's; without --sigma hpl then "
                        "uses Student's t for that estimated scale, a wider bound, and a "
                        "plain fit's test, nls' and auto's, cannot fail: its scale is "
                        "that of the residuals it tests, so a gross range shows only in "
                        "hpl), or trust --sigma (apriori)")
    p.add_argument("--side-prior", choices=("log", "none"), default="log",
                   help="nearly collinear anchors: place a fix that fits either side of "
                        "their line on the side where the log's unambiguous fixes lie "
                        "(log, default; a first-pass sign test) or leave it (none)")
    p.add_argument("--alert-limit", type=positive_float, default=None, metavar="L",
                   help="horizontal alert limit (m): a fix whose hpl exceeds it gets status "
                        "protection_exceeded (not usable)")
    p.add_argument("--k-noise", type=nonnegative_float, default=None, metavar="K",
                   help="protection levels: multiplier of the fault-free noise on the "
                        "major semi-axis (default N(1 - alpha0/2) = 3.29 for alpha0 = 0.1 %%, "
                        "the 1-D quantile, as WAAS; 3.72 = sqrt(chi2(1 - alpha0; 2)) bounds "
                        "the 2-D noise at alpha0 as the tracker does)")
    p.add_argument("--min-scale", type=scale_floor, default=0.0,
                   help="floor of the estimated robust scale (units of --sigma; default 0, "
                        "at most 1e6)")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="weight-function threshold, e.g. --param c=1.5 (repeatable; default: the "
                        "method's own constants)")
    p.add_argument("--model", choices=PATH_LOSS_MODELS,
                   default=None, help="path-loss columns to use (default: what the anchors have)")
    p.add_argument("--tag-height", type=tag_height_m, default=None,
                   help="2-D only: known tag height, to reduce slant ranges (m)")
    p.add_argument("--no-range-calibration", action="store_true",
                   help="ignore the anchors' bias/scale columns")
    p.add_argument("--alpha0", type=float_in(1e-12, 0.5), default=0.001,
                   help="w-test significance (every fix's test and hpl; snooping; default "
                        "%(default)s)")
    p.add_argument("--beta0", type=float_in(1e-6, 0.99), default=0.10,
                   help="B-method type II error (every fix's test and hpl; snooping; default "
                        "%(default)s)")
    p.add_argument("--chunk-rows", type=positive_int, default=500_000,
                   help="rows read per chunk (default %(default)s)")
    p.add_argument("--json", action="store_true",
                   help="print the run summary as JSON (statuses per method; "
                        "hpl_quantiles: per method the usable fixes' n, unbounded, "
                        "median_m and p95_bound_m, a value at or below which 95 %% of "
                        "their hpl lie, exact up to 10^6 fixes, else from bins of 1/1000 "
                        "decade (exact false); hpl_histogram: their hpl counted in bins "
                        "of 1/20 decade, key floor(20 log10 hpl), 'inf' for unbounded "
                        "ones; seconds, of which compile_seconds numba compiled kernels "
                        "not yet cached, and fixes_per_second over the solving alone)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar and no text summary")
    from robustloc.commands._plot import add_plot_argument

    add_plot_argument(p, "positions")
    add_engine_arguments(p)


def settings_from(args: argparse.Namespace) -> LocateSettings:
    """The pipeline settings of a parsed command line."""
    from robustloc.pipelines.locate import LocateSettings

    return LocateSettings.from_namespace(args)


def locate_file(args: argparse.Namespace) -> dict:
    """Run the ``locate`` pipeline as configured by ``args`` (the command line, or one
    partition of the Dask engine); returns the summary.  On a partition (``args.engine``
    ``"dask"``: the command line itself hands a Dask run to the engine) the summary also
    holds ``hpl_tally``, each method's :class:`~robustloc.pipelines.locate.HplTally`, which
    the engine merges into the dataset's ``hpl_quantiles`` and leaves out of its own."""
    from robustloc.io import read_anchors
    from robustloc.pipelines.locate import run_locate

    tallies: dict | None = {} if getattr(args, "engine", "local") == "dask" else None
    _, summary = run_locate(args.measurements, read_anchors(args.anchors),
                            settings_from(args), args.out, progress=not args.quiet,
                            hpl_tallies=tallies)
    if tallies is not None:
        summary["hpl_tally"] = tallies
    return summary


def run(args: argparse.Namespace) -> int:
    from robustloc.commands._plot import check_plot, draw_plot

    check_plot(args, "positions")
    if args.engine == "dask":
        from robustloc.engines.dask import run_locate
        return run_locate(args, locate_file)
    summary = locate_file(args)
    draw_plot(args)
    from robustloc.commands._summary import summary_head, timing_text
    from robustloc.pipelines.locate import locate_lines

    if (dest := summary_head(args, summary)) is None:
        return 0
    print(f"{summary['epochs']} epochs of {summary['value']} -> {summary['positions']} "
          + timing_text(summary, "fixes_per_second", "fixes/s solving"), file=dest)
    for line in locate_lines(summary):
        print(line, file=dest)
    return 0

