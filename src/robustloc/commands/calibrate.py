"""``robustloc calibrate``: fit path-loss parameters or range bias/scale per anchor."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import pandas as pd

NAME = "calibrate"
HELP = "fit path-loss parameters (RSSI) or range bias/scale per anchor from a survey"
DESCRIPTION = """\
RSSI survey (anchor, distance, rssi): fits per anchor, and pooled over all anchors,
  log-distance          RSSI = A - 10 n lg d                   (seed 000 eq. 1)  -> A, n
  attenuation-factor    P = p0 + 10 gamma lg(d0/d) + FAF       (seed 002 eq. 5)  -> gamma, faf
                        (p0 from --p0, the anchors' p0 column, or the mean RSSI at d0)
  friis                 P = p0 + 20 lg(d0/d)                   (seed 002 eq. 4)  -> p0
Range survey (anchor, distance, range): per-anchor bias (and scale with --scale) of
  range = scale * distance + bias;  `locate` applies range_corrected = (range - bias) / scale.
Instead of a survey, --measurements M --truth T --anchors A builds one from positioned data.

Prints each fit with standard errors and the residual standard deviation (dB or m);
writes --anchors with the fitted columns added (or, without --anchors, the parameter
table).  Anchors with too few survey rows, or absent from it, get the pooled fit
(column calib_source).  --robust fits by IRLS (default weight huber; igg3, hampel, ...).

  robustloc calibrate survey.csv --model log-distance --anchors anchors.csv -o calibrated.csv
  robustloc calibrate --measurements train.csv --truth truth.csv --anchors aps.csv -o aps_cal.csv"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("survey", nargs="?", help="survey file: anchor, distance, rssi|range")
    p.add_argument(
        "--model", choices=("log-distance", "attenuation-factor", "friis"),
        default="log-distance", help="path-loss model for RSSI data (default log-distance)",
    )
    p.add_argument("-o", "--out", required=True, help="anchors (or parameter table) to write")
    p.add_argument("--anchors", help="anchors file to add the fitted columns to")
    p.add_argument("--pooled", action="store_true", help="write the pooled fit to every anchor")
    p.add_argument(
        "--robust", nargs="?", const="huber", default=None, metavar="WEIGHT",
        help="robust IRLS fit; WEIGHT huber (default), hampel, igg, igg3",
    )
    p.add_argument("--scale", action="store_true", help="range data: fit a scale factor too")
    p.add_argument("--d0", type=float, default=1.0, help="reference distance d0 in m (default 1)")
    p.add_argument("--p0", type=float, default=None, help="attenuation factor: P_r(d0) in dBm")
    p.add_argument("--measurements", help="build the survey from these measurements ...")
    p.add_argument("--truth", help="... and this truth (needs --anchors)")
    p.add_argument(
        "--time-tolerance", type=float, default=1e-6, metavar="S",
        help="largest |time difference| to match measurements to truth (default 1e-6 s)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")


def _load_survey(args: argparse.Namespace, anchors: pd.DataFrame | None) -> pd.DataFrame:
    from robustloc.io import read_measurements, read_survey, read_truth
    from robustloc.models.calibration import survey_from_positions

    if args.measurements or args.truth:
        if args.survey:
            raise ValueError("give either a SURVEY file or --measurements/--truth, not both")
        if not (args.measurements and args.truth and anchors is not None):
            raise ValueError("--measurements needs --truth and --anchors")
        meas = read_measurements(args.measurements, anchors)
        truth = read_truth(args.truth)
        survey = survey_from_positions(meas, truth, anchors, time_tolerance_s=args.time_tolerance)
        if len(survey) == 0:
            raise ValueError(
                f"{args.measurements}: no measurement matches the truth by (time, tag)"
            )
        if survey.attrs.get("n_unmatched"):
            print(
                f"note: {survey.attrs['n_unmatched']} measurement rows had no truth and "
                "were not used", file=sys.stderr,
            )
        return survey
    if not args.survey:
        raise ValueError("give a SURVEY file, or --measurements, --truth and --anchors")
    return read_survey(args.survey, anchors)


def _fmt(table: pd.DataFrame, unit: str) -> str:
    t = table.copy()
    for c in t.columns:
        if c in ("n_obs", "n_used"):
            t[c] = t[c].astype(int)
        elif t[c].dtype.kind == "f":
            t[c] = t[c].map(lambda v: "" if not np.isfinite(v) else f"{v:.3f}")
    t = t.rename(columns={"residual_std": f"resid_std_{unit}"})
    return t.to_string(index=False)


def run(args: argparse.Namespace) -> int:
    from robustloc.io import read_anchors, write_table
    from robustloc.models.calibration import (
        calibrate_pathloss,
        calibrate_ranges,
        default_p0_from_anchors,
    )

    anchors = read_anchors(args.anchors) if args.anchors else None
    survey = _load_survey(args, anchors)
    value = survey.attrs.get("value") or ("rssi" if "rssi" in survey.columns else "range")
    if value == "rssi":
        p0 = args.p0 if args.p0 is not None else default_p0_from_anchors(anchors)
        res = calibrate_pathloss(
            survey, args.model, robust=args.robust, pooled=args.pooled, d0=args.d0, p0=p0
        )
    else:
        res = calibrate_ranges(survey, scale=args.scale, robust=args.robust, pooled=args.pooled)
    out = res.apply_to_anchors(anchors)
    path = write_table(out, args.out)
    if args.json:
        table = res.table.replace({np.nan: None})
        print(json.dumps({
            "model": res.model, "robust": res.robust, "pooled": res.pooled, "unit": res.unit,
            "output": str(path), "parameters": table.to_dict(orient="records"),
            "notes": res.notes,
        }, indent=2))
    else:
        how = f"robust ({res.robust})" if res.robust else "least squares"
        print(f"{res.model} fit, {how}, {len(survey)} survey rows"
              + (" (pooled fit written to every anchor)" if res.pooled else ""))
        print(_fmt(res.table, res.unit))
        print(f"written: {path}")
    for note in res.notes:
        print(f"note: {note}", file=sys.stderr)
    return 0
