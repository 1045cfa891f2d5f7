"""``robustloc stats``: RSSI statistics per anchor and distance bin (seed 002, Table 1)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from robustloc.options import MAX_LAG, float_in, int_in, positive_float

NAME = "stats"
HELP = "RSSI statistics per anchor and distance bin: moments, autocorrelation, normality"
DESCRIPTION = """\
Per anchor, and per (anchor, distance bin) when --truth is given: sample count, mean,
variance, skewness E(x-mu)^3/sigma^3 and kurtosis E(x-mu)^4/sigma^4 (Pearson, 3 for a
normal law, as seed 002 Table 1), the autocorrelation up to --max-lag samples and the lag
where it drops below 0.2, D'Agostino-Pearson and Shapiro-Wilk normality p-values, and the
correlation of the variance with distance (paper: 0.578).

Distance bins are centred on the multiples of --bin-width w: the bin labelled k*w holds
the distances from (k - 1/2) w, included, to (k + 1/2) w (so 0 holds those below w/2).
Bins of fewer than --min-samples samples are left out of per_bin.csv and of everything
computed from bins: the correlation (null with fewer than 3 distinct bin distances) and
the per-anchor moments of the residuals about the bin means (resid_n samples in
resid_bins bins; resid_variance divides by resid_n - resid_bins, one degree of freedom
per fitted bin mean; empty without a bin).  The summary's shares of anchors count the
anchors that have the statistic (share_anchors_normal_rejected_5pct: among the
n_anchors_normality_tested anchors of 8 samples or more, not constant; null if none).
Its median_skewness, median_kurtosis and share_anchors_left_skewed are of the residuals
about the bin means (resid_skewness, resid_kurtosis) when --truth gives bins, else of
the RSSI values (skewness, kurtosis): the RSSI of a walk mixes distances, and its
skewness is the distances' as much as the noise's.  summary.json says which in
moments_of (residuals or rssi), and so does the text output.

Writes into --out: per_anchor.csv, per_bin.csv (with truth), acf.csv, histograms.png
(one panel per anchor, up to 48: beyond, the first 48 by name, said on the figure),
autocorrelation.png (its legend names up to 40 anchors; beyond, the figure says so),
summary.json.  They are written into a temporary folder beside it
and moved in only when all are complete: after an error nothing is left behind.  RSSI
values outside -150 .. +30 dBm (robustloc.io.limits) are left out and counted
(invalid_measurement N).  Rows may come in any order.  The moments take every sample;
the autocorrelation takes each link's series in time, one value per time: readings of
one link at one time are averaged there, as every other command averages them.

With --truth, each row's distance comes from its tag's truth position interpolated
linearly at the row's time, within the tag's truth time span [t_min, t_max] (exact ends,
no tolerance; the truth is never extrapolated).  A tag with a single truth row is a static
point, its position valid at every time.  Rows whose tag has no truth (n_without_truth) or
that lie outside their tag's truth span (n_outside_truth_span) are left out of every
statistic and counted: a note on stderr and in summary.json.  Two truth rows for one
(time, tag) are an error, as in `robustloc evaluate`.

Example:
  robustloc stats sim/measurements.csv --anchors sim/anchors.csv --truth sim/truth.csv -o stats
"""


def _text(v: object) -> str:
    """A summary number for the text output (``none`` for null)."""
    return "none" if v is None else f"{v:.3g}"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("measurements", help="measurements file (time, tag, anchor, rssi)")
    p.add_argument("--anchors", default=None, help="anchors file (needed with --truth)")
    p.add_argument("--truth", default=None,
                   help="truth file (time, tag, x, y[, z]): enables distance bins; rows "
                        "without truth or outside their tag's truth time span are left "
                        "out and counted")
    p.add_argument("--max-lag", type=int_in(1, MAX_LAG), default=30,
                   help=f"largest autocorrelation lag in samples (default 30, at most "
                        f"{MAX_LAG})")
    p.add_argument("--bin-width", type=positive_float, default=1.0,
                   help="distance bin width, m (default 1)")
    p.add_argument("--min-samples", type=int_in(2, 10**9), default=10,
                   help="smallest bin reported (default 10 samples)")
    p.add_argument("--threshold", type=float_in(1e-6, 1 - 1e-6), default=0.2,
                   help="autocorrelation level of the decorrelation lag (default 0.2)")
    p.add_argument("-o", "--out", required=True, help="output folder")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def run(args: argparse.Namespace) -> int:
    import pandas as pd

    from robustloc.errors import InputError
    from robustloc.eval.rssi_stats import (
        RssiStatistics,
        plot_autocorrelation,
        plot_histograms,
    )
    from robustloc.io import read_anchors, read_measurements, read_truth

    if args.truth is not None and args.anchors is None:
        raise InputError("--truth needs --anchors (anchor positions give the distances)")
    anchors = read_anchors(args.anchors) if args.anchors else None
    meas = read_measurements(args.measurements, anchors)
    truth = read_truth(args.truth) if args.truth else None
    res = RssiStatistics(
        max_lag=args.max_lag, bin_width_m=args.bin_width, threshold=args.threshold,
        min_samples=args.min_samples,
    ).compute(meas, anchors, truth)
    out = Path(args.out)
    summary = res.summary()
    import sys

    # what was left out, on stderr (also with --json: stdout stays the summary alone)
    if summary["n_without_truth"]:
        print(f"note: {summary['n_without_truth']} measurement rows had no truth (their "
              "tag is not in the truth) and were not analysed", file=sys.stderr)
    if summary["n_outside_truth_span"]:
        print(f"note: {summary['n_outside_truth_span']} measurement rows lay outside their "
              "tag's truth time span and were not analysed (the truth is not "
              "extrapolated)", file=sys.stderr)

    def write(folder: Path) -> None:
        res.write_csv(folder)
        plot_histograms(res, folder / "histograms.png")
        plot_autocorrelation(res, folder / "autocorrelation.png", args.threshold)
        (folder / "summary.json").write_text(json.dumps(summary, indent=2))

    from robustloc.commands._folder import write_folder

    # a file of the folder that is an input (stats -o . on ./per_anchor.csv) is refused
    write_folder(args.out, write, [args.measurements, args.anchors, args.truth],
                 owns=("per_anchor.csv", "per_bin.csv", "acf.csv", "histograms.png",
                       "autocorrelation.png", "summary.json"))
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    with pd.option_context("display.width", 160, "display.max_columns", 20):
        cols = ["anchor", "n", "mean", "variance", "skewness", "kurtosis",
                "decorrelation_lag", "normaltest_p"]
        print("per anchor:")
        print(res.per_anchor[cols].to_string(index=False, float_format=lambda v: f"{v:.3g}"))
        if res.per_bin is not None and res.per_bin.empty:
            print(f"\nper distance bin: none of {args.bin_width:g} m holds --min-samples "
                  f"{args.min_samples} samples")
        elif res.per_bin is not None:
            print("\nper distance bin:")
            print(res.per_bin[["anchor", "distance_m"] + cols[1:]].to_string(
                index=False, float_format=lambda v: f"{v:.3g}"))
            corr = res.variance_distance_corr
            print("\ncorrelation of variance with distance: "
                  + (f"{corr:.3f}" if np.isfinite(corr) else
                     "none (fewer than 3 distinct bin distances)") + " (seed 002: 0.578)")
    sk_of = ("the residuals about the bin means (resid_skewness)"
             if summary.get("moments_of") == "residuals" else "the RSSI values (skewness)")
    print(f"\nsummary: median skewness {_text(summary['median_skewness'])}, share of "
          f"anchors left-skewed {_text(summary['share_anchors_left_skewed'])}, of {sk_of}")
    print(f"\ninvalid_measurement: {summary['invalid_measurement']}"
          + (" (RSSI outside -150 .. +30 dBm, left out)" if summary["invalid_measurement"]
             else ""))
    print(f"tables and figures in {out}")
    return 0

