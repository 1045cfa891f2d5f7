"""``robustloc calibrate``: fit path-loss parameters or range bias/scale per anchor."""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import pandas as pd

from robustloc.commands._argtypes import finite_float, nonnegative_float, positive_float

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

Self-calibration without truth (--self MEASUREMENTS --anchors A): the per-anchor range
bias and scale (ranges), or A and n (RSSI, log-distance; p0 and gamma with
--model attenuation-factor), and the noise sigma of every anchor are estimated jointly with
every epoch's position, from the redundancy across epochs, the anchor coordinates being the
datum (robust joint Gauss-Newton, positions eliminated by the Schur complement; see
robustloc.models.selfcal).  Bad epochs are left out and counted.  A parameter the log
cannot determine (inseparable from the positions, a standard error above --se-ratio
sigma, or a scale with the tags in the far field of the anchors) gets a warning and is left
at its prior (bias 0, scale 1, or the anchors file's A, n).  Writes the columns bias,
scale, sigma (or A, n, sigma) and their standard errors; the start fixes use the anchors
file's A, n for RSSI.

A survey that cannot determine a parameter (every sample at one distance, fewer rows than
parameters + 1, constant values, an exact fit) is an error naming the anchor and the
parameter (exit code 2).

Prints each fit with standard errors and the residual standard deviation (dB or m);
writes --anchors with the fitted columns added (or, without --anchors, the parameter
table).  Anchors with too few survey rows, or absent from it, get the pooled fit
(column calib_source).  --robust fits by IRLS (default weight huber; igg3, hampel, ...).

  robustloc calibrate survey.csv --model log-distance --anchors anchors.csv -o calibrated.csv
  robustloc calibrate --measurements train.csv --truth truth.csv --anchors aps.csv -o aps_cal.csv
  robustloc calibrate --self log.csv --anchors aps.csv -o aps_selfcal.csv"""


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
    p.add_argument(
        "--scale", action=argparse.BooleanOptionalAction, default=None,
        help="range data: fit a scale factor too (default: no for a survey, yes for --self)",
    )
    p.add_argument("--d0", type=positive_float, default=1.0,
                   help="reference distance d0 in m (default 1)")
    p.add_argument("--p0", type=finite_float, default=None,
                   help="attenuation factor: P_r(d0) in dBm")
    p.add_argument(
        "--self", dest="self_log", metavar="MEASUREMENTS", default=None,
        help="self-calibration from a measurements log without truth (needs --anchors)",
    )
    p.add_argument("--dim", type=int, choices=(2, 3), default=2,
                   help="--self: solved dimension of the positions (default 2)")
    p.add_argument("--tag-height", type=finite_float, default=None, metavar="M",
                   help="--self, 2-D: tag height; the anchors' z gives the vertical offsets")
    p.add_argument("--se-ratio", type=positive_float, default=3.0,
                   help="--self: leave out a parameter whose standard error exceeds this "
                        "many sigma (default 3)")
    p.add_argument("--measurements", help="build the survey from these measurements ...")
    p.add_argument("--truth", help="... and this truth (needs --anchors)")
    p.add_argument(
        "--time-tolerance", type=nonnegative_float, default=1e-6, metavar="S",
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


def self_calibrate(
    anchors: pd.DataFrame, xyz: np.ndarray, values: np.ndarray, kind: str, *,
    height_offset: np.ndarray | None = None, model_name: str | None = "log-distance",
    fit_scale: bool = True, se_ratio: float = 3.0,
):
    """``calibrate --self`` on arrays: robust start fixes (huber), then the joint
    adjustment of :class:`robustloc.models.selfcal.SelfCalibrator`.

    Returns ``(SelfCalibration, path-loss model or None)``; the anchors frame with the new
    columns is ``robustloc.models.calibration.self_calibration_table(res, anchors, model)``.
    """
    from robustloc.estimators.ranging import Locator
    from robustloc.models.pathloss import model_from_anchors
    from robustloc.models.selfcal import SelfCalibrator

    ids = [str(a) for a in anchors["anchor"]]
    model = None
    if kind == "rssi":
        # the model named by --model; the default (log-distance) yields to the anchors'
        # own attenuation-factor columns when they have no A, n
        use_default = model_name == "log-distance" and not {"A", "n"} <= set(anchors.columns)
        model = model_from_anchors(anchors, None if use_default else model_name)
        A0, n0 = model.log_distance_params()
        A0 = np.broadcast_to(A0, (len(ids),)).astype(float)
        n0 = np.broadcast_to(n0, (len(ids),)).astype(float)
        start = Locator("huber").solve(xyz, values, "rssi", A=A0, n=n0,
                                       height_offset=height_offset)
        cal = SelfCalibrator("rssi", fit_slope=type(model).__name__ != "FreeSpace",
                             se_ratio=se_ratio)
        res = cal.fit(xyz, values, start.position, offset0=A0, slope0=n0,
                      height_offset=height_offset, anchor_ids=ids)
    else:
        start = Locator("huber").solve(xyz, values, "range", height_offset=height_offset)
        cal = SelfCalibrator("range", fit_slope=fit_scale, se_ratio=se_ratio)
        res = cal.fit(xyz, values, start.position, height_offset=height_offset,
                      anchor_ids=ids)
    return res, model


def _run_self(args: argparse.Namespace) -> int:
    from robustloc.errors import InputError
    from robustloc.io import read_anchors, read_measurements, to_epochs, write_table
    from robustloc.models.calibration import self_calibration_table

    if args.survey or args.measurements or args.truth:
        raise ValueError("--self takes the log alone: no SURVEY, --measurements or --truth")
    if not args.anchors:
        raise ValueError("--self needs --anchors (the anchor coordinates are the datum)")
    anchors = read_anchors(args.anchors)
    if (args.dim == 3 or args.tag_height is not None) and "z" not in anchors.columns:
        raise InputError("--dim 3 and --tag-height need a z column in the anchors file",
                         args.anchors, 1)
    if args.dim == 3 and args.tag_height is not None:
        raise ValueError("--tag-height is for --dim 2")
    ids = [str(a) for a in anchors["anchor"]]
    meas = read_measurements(args.self_log, anchors)
    ep = to_epochs(meas, ids)
    kind = ep.value
    cols = ["x", "y"] + (["z"] if args.dim == 3 else [])
    xyz = anchors[cols].to_numpy(dtype=float)
    height = None
    if args.tag_height is not None:
        height = anchors["z"].to_numpy(dtype=float) - args.tag_height
    if kind == "rssi" and args.scale is not None:
        raise ValueError("--scale is for range data")
    res, model = self_calibrate(anchors, xyz, ep.values, kind, height_offset=height,
                                model_name=args.model, fit_scale=args.scale is not False,
                                se_ratio=args.se_ratio)
    if res.epochs_used == 0:
        raise InputError(
            f"nothing to self-calibrate: no epoch has a fix with redundancy (need at least "
            f"{args.dim + 1} anchors heard in one epoch; {res.epochs_total} epochs, "
            f"{res.epochs_no_start} without a start fix)", args.self_log)
    table, out = self_calibration_table(res, anchors, model)
    path = write_table(out, args.out)
    summary = {
        "kind": kind, "epochs": res.epochs_total, "epochs_used": res.epochs_used,
        "epochs_no_redundancy": res.epochs_no_redundancy, "epochs_bad": res.epochs_bad,
        "epochs_no_start": res.epochs_no_start,
        "observations_rejected": res.observations_rejected,
        "sigma0": round(res.sigma0, 4), "iterations": res.iterations,
        "converged": res.converged, "output": str(path),
    }
    if args.json:
        print(json.dumps({**summary, "parameters": table.replace({np.nan: None})
                          .to_dict(orient="records"), "warnings": res.warnings}, indent=2))
    else:
        unit = "m" if kind == "range" else "dB"
        print(f"self-calibration ({kind}), {res.epochs_used} of {res.epochs_total} epochs used "
              f"({res.epochs_no_redundancy} without redundancy, {res.epochs_bad} bad, "
              f"{res.epochs_no_start} without a start fix; {res.observations_rejected} "
              f"observations rejected), {res.iterations} iterations, "
              f"sigma0 {res.sigma0:.3f}")
        print(_fmt(table, unit))
        print(f"written: {path}")
    for w in res.warnings:
        print(f"warning: {args.self_log}: {w}", file=sys.stderr)
    return 0


def run(args: argparse.Namespace) -> int:
    if args.self_log:
        return _run_self(args)
    from robustloc.io import read_anchors, write_table
    from robustloc.models.calibration import (
        POOLED,
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
        res = calibrate_ranges(survey, scale=bool(args.scale), robust=args.robust,
                               pooled=args.pooled)
    out = res.apply_to_anchors(anchors)
    # the noise sigma written (and used by `locate` to weight the anchors): each anchor's
    # residual std, the pooled one with --pooled; 1e-6 m or dB is far below any physical
    # noise and above the rounding of an exact fit
    t = res.table
    rows = t[t["anchor"] == POOLED] if res.pooled else t[t["anchor"] != POOLED]
    sg = rows["residual_std"].to_numpy(dtype=float)
    bad = ~(np.isfinite(sg) & (sg > 1e-6))
    if bad.any():
        from robustloc.errors import InputError

        who = rows["anchor"].iloc[int(np.argmax(bad))]
        who = "pooled fit" if who == POOLED else f"anchor {who}"
        raise InputError(
            f"{who}: cannot determine sigma: the fit is exact (zero residual), so `locate` "
            "could not weight the anchor", survey.attrs.get("path"))
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
