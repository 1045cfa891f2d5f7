"""``robustloc calibrate``: fit path-loss parameters or range bias/scale per anchor.

The command line over :mod:`robustloc.pipelines.calibrate`.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import pandas as pd

NAME = "calibrate"
HELP = ("fit path-loss parameters (RSSI) or range bias/scale per anchor from a survey, "
        "a log with truth, or the log alone (--self)")
DESCRIPTION = """\
RSSI survey (anchor, distance, rssi): fits per anchor, and pooled over all anchors,
  log-distance          RSSI = A - 10 n lg d                   (seed 000 eq. 1)  -> A, n
  attenuation-factor    P = p0 + 10 gamma lg(d0/d) + FAF       (seed 002 eq. 5)  -> gamma, faf
                        (p0 from --p0 at --d0, the anchors' p0 column at their d0
                        column (or --d0), or the mean RSSI at d0)
  friis                 P = p0 + 20 lg(d0/d)                   (seed 002 eq. 4)  -> p0
Range survey (anchor, distance, range): per-anchor bias (and scale with --scale) of
  range = scale * distance + bias;  `locate` applies range_corrected = (range - bias) / scale.
A survey may have a column weight: frequency weights, how many observations each row counts
for (e.g. histogram counts); its total minus the parameters is the residual degrees of
freedom, so probabilities summing to 1 are too little weight.
Instead of a survey, --measurements M --truth T --anchors A builds one from positioned data
(each measurement matched to the truth of its tag within --time-tolerance).  The distances
are 3-D when both the truth and the anchors have z, else horizontal (even when the anchors
have z).  Rows outside the physical limits (robustloc.io.limits; invalid_measurement in
`locate`) and RSSI rows with the truth on the anchor (distance 0) are not used and are
counted in a note; a SURVEY file with such a value is an error.
Options that do not apply to a survey fit are refused: --p0 (attenuation-factor only), --d0
(attenuation-factor, friis), --model and --scale by the data kind, --time-tolerance
without --measurements.

Self-calibration without truth (--self MEASUREMENTS --anchors A): the per-anchor range
bias and scale (ranges), or A and n (RSSI, log-distance; p0 and gamma with
--model attenuation-factor), and the noise sigma of every anchor are estimated jointly with
every epoch's position, from the redundancy across epochs, the anchor coordinates being the
datum (robust joint Gauss-Newton, positions eliminated by the Schur complement; see
robustloc.models.selfcal).  Bad epochs are left out and counted.  A parameter the log
cannot determine (inseparable from the positions, a model standard error above --se-ratio
sigma, a scale with the tags in the far field of the anchors or with the anchors close to
a line, a scale of an anchor whose distance to the tag hardly varies, every parameter when
the tag does not move, those of an anchor heard in fewer epochs than its parameters + 2)
gets a warning and is left at its prior: the anchors file's bias and scale (0 and 1 where
it has none) or A, n; the adjustment starts from the raw ranges either way, so what the log
determines does not depend on them.  A sigma the log cannot determine (an anchor whose
parameters were left out because the tag does not move, it is heard in too few epochs or
the log has no redundancy; or a variance component of at most 2 degrees of freedom) gets a
warning too: the anchors file's sigma stays, else the median of the determined anchors'
is written, and when no anchor's is determined none (locate then measures the log's noise
scale).  Writes the columns bias, scale, sigma (or A, n, sigma) and their
standard errors, cluster-robust over 50 time blocks of the log (errors that persist while
a tag dwells make the independent-epoch ones too small); the start fixes use the anchors
file's A, n for RSSI.  The start fixes are tested as `locate` tests them: an epoch whose fix is not
usable is left out (counted without a start fix), and with nearly collinear anchors an
ambiguous fix starts on the side of their line where the log's unambiguous fixes lie
(as `locate --side-prior log`).  The standard errors are too small when the tag dwells at
a point for more than a fiftieth of the log (take them as lower bounds there).
RSSI: the estimates carry an incidental-parameter bias (a note says so with every run),
and a tag that keeps one distance to an anchor can take its exponent far off with a small
standard error and no warning: on a simulated tag circling one anchor at 6 m, at 1.5-2.5
dB of noise 7 of 12 runs located worse with the calibration than with the prior A, n
(4.1-11.5 m against 3.9-4.1 m RMS; docs/limits.md).  Calibrate RSSI from a survey where
you can.

A survey that cannot determine a parameter (every sample at one distance, fewer rows than
parameters + 1, constant values, an exact fit, a fitted level at the reference distance
outside the RSSI limits or an exponent outside [0.01, 10]) is an error naming the anchor and
the parameter (exit code 2).

Prints each fit with standard errors and the residual standard deviation (dB or m).  The
standard errors are cluster-robust (Liang-Zeger, never below those of independent rows):
from --measurements and --truth over the tag's dwells (consecutive epochs at one truth
position), from a survey file over its column cluster (a row with that field empty stands
alone); a survey without the column, or with it all empty, has its rows taken as
independent.  An anchor (or the pooled fit) with more than 50 clusters has neighbouring
ones, in id order (dwells in time order), merged into 50 blocks: its standard errors then
differ from the plain estimator over every cluster (0.80 to 1.12 times it on simulated
surveys of 200 clusters per anchor; docs/formats.md).  Writes --anchors with the fitted
columns, their standard errors (<col>_se) and sigma (the residual standard deviation;
with --robust the MAD scale of the residuals, which gross errors do not inflate; for
ranges divided by the scale: the standard deviation of the corrected range
(range - bias) / scale, which `locate` fits and weights by it) added or replaced --
earlier standard errors and calib_fixed are dropped -- or, without --anchors, the
parameter table with the same columns.  Anchors with too few survey rows, or absent from
it, get the pooled fit (column calib_source; a note names the absent ones, which keep
their own p0 and d0 with attenuation-factor).  --robust fits by IRLS (default weight
huber; igg3, hampel, ...).

  robustloc calibrate survey.csv --model log-distance --anchors anchors.csv -o calibrated.csv
  robustloc calibrate --measurements train.csv --truth truth.csv --anchors aps.csv -o aps_cal.csv
  robustloc calibrate --self log.csv --anchors aps.csv -o aps_selfcal.csv"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.options import nonnegative_float, positive_float, tag_height_m
    from robustloc.pipelines.calibrate import CALIBRATION_MODELS, p0_dbm

    p.add_argument("survey", nargs="?", help="survey file: anchor, distance, rssi|range")
    p.add_argument(
        "--model", choices=CALIBRATION_MODELS,
        default="log-distance", help="path-loss model for RSSI data (default log-distance)",
    )
    p.add_argument("-o", "--out", required=True, help="anchors (or parameter table) to write")
    p.add_argument("--anchors", help="anchors file to add the fitted columns to")
    p.add_argument("--pooled", action="store_true", help="write the pooled fit to every anchor")
    p.add_argument(
        "--robust", nargs="?", const="huber", default=None, metavar="WEIGHT",
        help="robust IRLS fit; WEIGHT huber (default), hampel, igg, igg3",
    )
    p.add_argument(
        "--scale", action=argparse.BooleanOptionalAction, default=None,
        help="range data: fit a scale factor too (default: no for a survey, yes for --self)",
    )
    p.add_argument("--d0", type=positive_float, default=1.0,
                   help="reference distance d0 in m (default 1; attenuation-factor with the "
                        "anchors' p0: their d0 column)")
    p.add_argument("--p0", type=p0_dbm, default=None,
                   help="attenuation factor: P_r(d0) in dBm, -150 .. 30")
    p.add_argument(
        "--self", dest="self_log", metavar="MEASUREMENTS", default=None,
        help="self-calibration from a measurements log without truth (needs --anchors)",
    )
    p.add_argument("--dim", type=int, choices=(2, 3), default=2,
                   help="--self: solved dimension of the positions (default 2)")
    p.add_argument("--tag-height", type=tag_height_m, default=None, metavar="M",
                   help="--self, 2-D: tag height; the anchors' z gives the vertical offsets")
    p.add_argument("--se-ratio", type=positive_float, default=3.0,
                   help="--self: leave out a parameter whose model standard error "
                        "(independent epochs) exceeds this many sigma (default 3)")
    p.add_argument("--measurements", help="build the survey from these measurements ...")
    p.add_argument("--truth", help="... and this truth (needs --anchors)")
    p.add_argument(
        "--time-tolerance", type=nonnegative_float, default=1e-6, metavar="S",
        help="--measurements: largest |time difference| to match measurements to truth "
             "(default 1e-6 s)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _fmt(table: pd.DataFrame, unit: str) -> str:
    t = table.copy()
    for c in t.columns:
        if c in ("n_obs", "n_used"):
            t[c] = t[c].astype(int)
        elif t[c].dtype.kind == "f":
            t[c] = t[c].map(lambda v: "" if not np.isfinite(v) else f"{v:.3f}")
    t = t.rename(columns={"residual_std": f"resid_std_{unit}"})
    return t.to_string(index=False)


def _robust_took_the_survey(args: argparse.Namespace) -> None:
    """``--robust``'s optional WEIGHT swallows the survey file that follows it
    (``calibrate --robust survey.csv -o out.csv`` said "unknown weight function
    'survey.csv'": the calibration review).  A value that is no weight function but a
    file (it exists, or its name has a suffix such as ``.csv``) is taken as the survey,
    with the default weight (huber), when no file was given otherwise; else an error
    says what happened.  An unknown name that is no file keeps the unknown-name error."""
    from pathlib import Path

    from robustloc.errors import InputError
    from robustloc.robust.weights import get_weight

    if args.robust is None:
        return
    try:
        get_weight(str(args.robust))
        return
    except ValueError:
        pass
    value = str(args.robust)
    if not (Path(value).exists() or Path(value).suffix):
        return
    if args.survey is None and args.self_log is None and args.measurements is None:
        args.survey, args.robust = value, "huber"
        return
    raise InputError(f"--robust took {value!r} as its weight function: put --robust after "
                     "the file, or name the function (--robust huber)")


def run(args: argparse.Namespace) -> int:
    from robustloc.io import read_anchors, write_table
    from robustloc.io.atomic import check_not_input
    from robustloc.pipelines.calibrate import CalibrateSettings, run_calibrate

    # before any work: -o naming an input replaced it (the log, the survey, the truth or
    # the anchors themselves), where `locate` and `track` refused
    check_not_input(args.out, [args.survey, args.anchors, args.measurements, args.truth,
                               args.self_log])
    if args.out is not None:  # an -o write_table refuses (.xlsx, .png): before the work,
        # not after minutes of --self (the calibration review)
        from robustloc.io.tables import check_table_path

        check_table_path(args.out)
    _robust_took_the_survey(args)
    settings = CalibrateSettings.from_namespace(args)
    anchors = read_anchors(args.anchors) if args.anchors else None
    cal = run_calibrate(settings, survey=args.survey, anchors=anchors,
                        measurements=args.measurements, truth=args.truth,
                        self_log=args.self_log)
    path = write_table(cal.output, args.out)
    from robustloc.io.atomic import writes_to_stdout

    # the summary never goes into a data stream: stderr when the table goes to stdout
    dest = sys.stderr if writes_to_stdout(args.out) else sys.stdout
    if args.json:
        print(json.dumps({**cal.summary, "output": str(path)}, indent=2), file=dest)
    else:
        print(cal.headline, file=dest)
        print(_fmt(cal.parameters, cal.unit), file=dest)
        print(f"written: {path}", file=dest)
    for note in cal.notes:
        print(f"note: {note}", file=sys.stderr)
    for w in cal.warnings:
        print(f"warning: {w}", file=sys.stderr)
    return 0
