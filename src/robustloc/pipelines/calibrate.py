"""The ``calibrate`` workflow: path-loss parameters or range bias/scale per anchor.

Three ways in (:func:`run_calibrate`): a survey (``anchor, distance, rssi|range``), a
survey built from positioned data (``measurements`` + ``truth``), or self-calibration
from a log without truth (``self_log``; :mod:`robustloc.models.selfcal`).
:class:`CalibrateSettings` holds every setting.  ``robustloc calibrate`` and
:func:`robustloc.calibrate` run this code.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from robustloc._arrays import to_number
from robustloc.errors import InputError
from robustloc.io.tables import refuse_duplicate_truth
from robustloc.options import (
    check_settings,
    finite_float,
    nonnegative_float,
    option,
    positive_float,
    tag_height_m,
)

#: ``model`` values.
CALIBRATION_MODELS = ("log-distance", "attenuation-factor", "friis")


def p0_dbm(text: str) -> float:
    """``--p0``: an RSSI at ``d0`` within the RSSI limits of :mod:`robustloc.io.limits`
    (-150 to +30 dBm), which the anchors reader enforces on a ``p0`` column.  (Any finite
    number was taken: ``--p0 1000`` wrote anchors that ``locate`` and ``filter`` then
    refused, ``--p0 1e308`` said "fitted gamma = nan": the commands review.)

    Raises
    ------
    argparse.ArgumentTypeError
        Not a finite number, or outside the limits.
    """
    from robustloc.io.limits import limits_for

    value = finite_float(text)
    lim = limits_for("rssi")
    if not lim.low <= value <= lim.high:
        raise argparse.ArgumentTypeError(
            f"expected the RSSI at d0 in [{lim.low:g}, {lim.high:g}] dBm (the physical "
            f"limits an anchors file's p0 is held to), got {text!r}")
    return value


def weight_name(name: str) -> str:
    """A robust weight function's name (:func:`robustloc.robust.weights.get_weight`
    refuses an unknown one, naming the known)."""
    from robustloc.robust.weights import get_weight

    get_weight(str(name))
    return str(name)


@dataclass(frozen=True)
class CalibrateSettings:
    """Every setting of ``calibrate`` (the ``robustloc calibrate`` options of the same name).

    Parameters
    ----------
    model : {"log-distance", "attenuation-factor", "friis"}
        Path-loss model for RSSI data.
    robust : str, optional
        Robust IRLS fit with this weight (``huber``, ``hampel``, ``igg``, ``igg3``).
    scale : bool, optional
        Range data: fit a scale factor too (default no for a survey, yes for a self-log).
    pooled : bool
        Write the pooled fit to every anchor.
    d0, p0 : float
        Reference distance (m) and ``P_r(d0)`` (dBm) of the attenuation-factor model.
    time_tolerance : float
        Largest absolute time difference (s) matching measurements to truth.
    dim, tag_height, se_ratio
        Self-calibration: solved dimension, 2-D tag height (m), and the standard-error
        ratio beyond which a parameter is left at its prior.
    """

    model: str = option("log-distance", choices=CALIBRATION_MODELS)
    robust: str | None = option(None, check=weight_name)
    scale: bool | None = None
    pooled: bool = False
    d0: float = option(1.0, check=positive_float)
    p0: float | None = option(None, check=p0_dbm)
    time_tolerance: float = option(1e-6, check=nonnegative_float)
    dim: int = option(2, choices=(2, 3))
    tag_height: float | None = option(None, check=tag_height_m)
    se_ratio: float = option(3.0, check=positive_float)

    def __post_init__(self) -> None:
        check_settings(self)

    @classmethod
    def from_namespace(cls, args: argparse.Namespace) -> CalibrateSettings:
        """The settings of a parsed ``robustloc calibrate`` command line."""
        from dataclasses import fields

        return cls(**{f.name: getattr(args, f.name) for f in fields(cls)})


@dataclass
class Calibration:
    """What :func:`run_calibrate` found.

    Attributes
    ----------
    output : DataFrame
        The anchors with the fitted columns, or without anchors the parameter table:
        what ``-o`` gets.
    parameters : DataFrame
        The fit table (one row per anchor, and the pooled fit), standard errors included.
    unit : str
        ``dB`` or ``m``.
    summary : dict
        The run summary (``--json``; the output path is the front end's to add).
    headline : str
        One line saying what was fitted, for people.
    notes, warnings : list of str
        What the command line prints as ``note:`` and ``warning:``.
    """

    output: pd.DataFrame
    parameters: pd.DataFrame
    unit: str
    summary: dict[str, Any]
    headline: str
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def run_calibrate(
    settings: CalibrateSettings, *, survey: Any = None, anchors: pd.DataFrame | None = None,
    measurements: Any = None, truth: Any = None, self_log: Any = None,
) -> Calibration:
    """Calibrate from a survey, from positioned data, or from a log alone.

    Parameters
    ----------
    settings : CalibrateSettings
    survey, measurements, truth, self_log : str, PathLike or DataFrame, optional
        Files, or frames validated by :mod:`robustloc.io` (``validate_survey`` & co.).
    anchors : DataFrame, optional
        Validated anchors to add the fitted columns to (required by ``measurements`` and
        ``self_log``).
    """
    if self_log is not None:
        if survey is not None or measurements is not None or truth is not None:
            raise InputError("--self takes the log alone: no SURVEY, --measurements or "
                             "--truth")
        if anchors is None:
            raise InputError("--self needs --anchors (the anchor coordinates are the datum)")
        # options of the survey fit mean nothing here: refused, not silently ignored
        default = CalibrateSettings()
        survey_only = {"--robust": settings.robust != default.robust,
                       "--pooled": settings.pooled != default.pooled,
                       "--d0": settings.d0 != default.d0, "--p0": settings.p0 != default.p0}
        if settings.time_tolerance != default.time_tolerance:  # (accepted and ignored:
            # the calibration review)
            raise InputError("--time-tolerance applies to --measurements with --truth "
                             "only (--self matches no truth)")
        given = [k for k, v in survey_only.items() if v]
        if given:
            raise InputError(
                f"{', '.join(given)} applies to a survey fit, not to --self (which is "
                "always robust, per anchor, and takes p0 and d0 from the anchors file)")
        return _self(settings, anchors, self_log)
    default = CalibrateSettings()
    self_only = {"--dim": settings.dim != default.dim,
                 "--tag-height": settings.tag_height != default.tag_height,
                 "--se-ratio": settings.se_ratio != default.se_ratio}
    given = [k for k, v in self_only.items() if v]
    if given:
        raise InputError(f"{', '.join(given)} applies to --self only (a survey, or "
                         "--measurements with --truth, has its distances already)")
    return _from_survey(settings, survey, anchors, measurements, truth)


def _name(src: Any) -> str:
    if isinstance(src, pd.DataFrame):
        return str(src.attrs.get("path") or "<DataFrame>")
    return str(src)


def _load_survey(settings: CalibrateSettings, survey: Any, anchors: pd.DataFrame | None,
                 measurements: Any, truth: Any, notes: list[str]) -> pd.DataFrame:
    from robustloc.io import read_measurements, read_survey, read_truth
    from robustloc.models.calibration import survey_from_positions

    if measurements is not None or truth is not None:
        if survey is not None:
            raise InputError("give either a SURVEY file or --measurements/--truth, not both")
        if measurements is None or truth is None or anchors is None:
            raise InputError("--measurements needs --truth and --anchors")
        meas = (measurements if isinstance(measurements, pd.DataFrame)
                else read_measurements(measurements, anchors))
        tru = truth if isinstance(truth, pd.DataFrame) else read_truth(truth)
        refuse_duplicate_truth(tru)
        out = survey_from_positions(meas, tru, anchors,
                                    time_tolerance_s=settings.time_tolerance)
        # rows outside the physical limits are set aside and counted, as `locate` and
        # `stats` do with the same file (read_measurements keeps them on purpose; a
        # SURVEY file, which holds nothing else, refuses them); so are RSSI rows whose
        # truth is on the anchor (distance 0: no log-distance value there)
        from robustloc.io.limits import limits_for

        value = out.attrs["value"]
        lim = limits_for(value).describe()
        dropped = []
        if out.attrs.get("n_invalid"):
            dropped.append(f"{out.attrs['n_invalid']} measurement row(s) outside the "
                           f"physical limits ({lim}; invalid_measurement)")
        if out.attrs.get("n_zero_distance"):
            dropped.append(f"{out.attrs['n_zero_distance']} RSSI row(s) with the truth "
                           "position on the anchor (distance 0, where the path-loss "
                           "models have no value)")
        for d in dropped:
            notes.append(f"{d} were not used")
        if out.attrs.get("n_duplicates"):
            notes.append(f"{out.attrs['n_duplicates']} duplicate rows (same epoch and "
                         "anchor) averaged")
        if len(out) == 0:
            why = "; ".join(dropped)
            raise InputError(f"{_name(measurements)}: no measurement matches the truth by "
                             "(time, tag)" + (f" and can be fitted ({why})" if why else ""))
        if out.attrs.get("n_unmatched"):
            notes.append(f"{out.attrs['n_unmatched']} measurement rows had no truth and "
                         "were not used")
        notes.extend(_dwell_notes(out))
        return out
    if survey is None:
        raise InputError("give a SURVEY file, or --measurements, --truth and --anchors")
    return survey if isinstance(survey, pd.DataFrame) else read_survey(survey, anchors)


#: Below this many dwells (truth positions) per anchor the note of :func:`_dwell_notes`
#: says the cluster-robust standard errors are optimistic.
FEW_DWELLS = 20


def _dwell_notes(out: pd.DataFrame) -> list[str]:
    """Notes on the dwells behind ``--truth`` standard errors (the calibration review,
    2026-12-06).  The errors are cluster-robust over the dwells: with one dwell there is
    no spread between dwells to measure, and the rows' own scatter stands (200 rows at
    one point with 0.2 m of multipath: standard errors of 0.007 m for a spread of
    0.17-0.22 m, 95 % intervals covering 5 %); with few, the sandwich estimate is low
    (its known small-sample bias: 12 dwells covered 80 %, 50 dwells 90 %, measured by
    Monte Carlo)."""
    if "cluster" not in out.columns or out.empty:
        return []
    per = out.groupby("anchor", sort=True)["cluster"].nunique()
    notes = []
    one = per.index[per < 2].tolist()
    if one:
        named = ", ".join(one[:10]) + (f" and {len(one) - 10} more" if len(one) > 10 else "")
        notes.append(f"anchor(s) {named}: every row at one truth position (one dwell): their "
                     "standard errors assume independent rows, which a dwell's shared "
                     "multipath breaks: they can be many times too small (survey more "
                     "points)")
    few = per[(per >= 2) & (per < FEW_DWELLS)]
    if len(few):
        lo, hi = int(few.min()), int(few.max())
        notes.append(f"standard errors from {lo if lo == hi else f'{lo}-{hi}'} dwells per "
                     f"anchor (fewer than {FEW_DWELLS}; {len(few)} anchor(s)): cluster-robust "
                     "over the dwells but optimistic with so few (95 % intervals covered "
                     "80 % at 12 dwells in simulation)")
    return notes


def _from_survey(settings: CalibrateSettings, survey: Any, anchors: pd.DataFrame | None,
                 measurements: Any, truth: Any) -> Calibration:
    from robustloc.models.calibration import (
        POOLED,
        calibrate_pathloss,
        calibrate_ranges,
        default_p0_from_anchors,
    )

    notes: list[str] = []
    default = CalibrateSettings()
    if settings.time_tolerance != default.time_tolerance and measurements is None:
        raise InputError("--time-tolerance applies to --measurements with --truth only (a "
                         "SURVEY file has its distances already)")
    table = _load_survey(settings, survey, anchors, measurements, truth, notes)
    value = table.attrs.get("value") or ("rssi" if "rssi" in table.columns else "range")
    # options that do not apply to this fit are refused, not silently ignored (as --self
    # refuses the survey options); a default value is not "given"
    given = {"--scale": settings.scale is not None,
             "--d0": settings.d0 != default.d0, "--p0": settings.p0 != default.p0}
    if value == "range":
        wrong = [k for k in ("--d0", "--p0") if given[k]]
        if settings.model != default.model:
            wrong.insert(0, f"--model {settings.model}")
        if wrong:
            raise InputError(f"{', '.join(wrong)} applies to RSSI data (a path-loss model), "
                             "but the survey holds ranges", table.attrs.get("path"))
    else:
        if given["--scale"]:
            raise InputError("--scale is for range data", table.attrs.get("path"))
        # friis takes d0 (its p0 is fitted); log-distance has neither
        wrong = [k for k in ("--p0", "--d0") if given[k] and not (
            settings.model == "attenuation-factor"
            or (k == "--d0" and settings.model == "friis"))]
        if wrong:
            raise InputError(
                f"{', '.join(wrong)} does not apply to --model {settings.model} (--p0 is "
                "for attenuation-factor, --d0 for attenuation-factor and friis)",
                table.attrs.get("path"))
    if value == "rssi":
        p0 = settings.p0 if settings.p0 is not None else default_p0_from_anchors(anchors)
        d0 = _d0_with_p0(settings, table, anchors) if settings.p0 is None else settings.d0
        res = calibrate_pathloss(table, settings.model, robust=settings.robust,
                                 pooled=settings.pooled, d0=d0, p0=p0)
    else:
        res = calibrate_ranges(table, scale=bool(settings.scale), robust=settings.robust,
                               pooled=settings.pooled)
    out = res.apply_to_anchors(anchors)
    if anchors is not None:
        notes.extend(_dropped_columns(anchors, out))
    absent = res.absent_anchors(anchors)
    if absent:
        kept = ("; each keeps the anchors file's own p0 and d0 where it has a p0"
                if res.model == "attenuation-factor" and anchors is not None
                and "p0" in anchors.columns else "")
        notes.append(f"anchor(s) {', '.join(absent)} have no survey row: the pooled fit "
                     f"was written to them (calib_source pooled{kept})")
    # the noise sigma written (and used by `locate` to weight the anchors): each anchor's
    # residual std, the pooled one with --pooled; 1e-6 m or dB is far below any physical
    # noise and above the rounding of an exact fit
    t = res.table
    rows = t[t["anchor"] == POOLED] if res.pooled else t[t["anchor"] != POOLED]
    sg = rows["residual_std"].to_numpy(dtype=float)
    bad = ~(np.isfinite(sg) & (sg > 1e-6))
    if bad.any():
        who = rows["anchor"].iloc[int(np.argmax(bad))]
        who = "pooled fit" if who == POOLED else f"anchor {who}"
        why = "the fit is exact (zero residual)"
        if "weight" in table.columns and not np.isfinite(sg[bad][0]):
            # no residual degree of freedom: sum(weight) - parameters <= 0
            why = ("the total weight of its rows is too small for the parameters (the "
                   "'weight' column holds frequency weights, how many observations each "
                   "row counts for, such as histogram counts; probabilities summing to 1 "
                   "leave no degree of freedom)")
        raise InputError(
            f"{who}: cannot determine sigma: {why}, so `locate` could not weight the "
            "anchor", table.attrs.get("path"))
    how = f"robust ({res.robust})" if res.robust else "least squares"
    headline = (f"{res.model} fit, {how}, {len(table)} survey rows"
                + (" (pooled fit written to every anchor)" if res.pooled else ""))
    summary = {"model": res.model, "robust": res.robust, "pooled": res.pooled,
               "unit": res.unit, "parameters": _records(res.table),
               "notes": notes + list(res.notes)}
    return Calibration(out, res.table, res.unit, summary, headline, notes + list(res.notes))


def _dropped_columns(anchors: pd.DataFrame, out: pd.DataFrame) -> list[str]:
    """A note naming the anchors file's columns the output lacks: another path-loss
    model's, which the calibrated ones replace (dropped without a word by --self, the
    self-calibration review, and by a truth or survey fit, the calibration review)."""
    gone = [c for c in anchors.columns if c not in out.columns
            and not c.endswith("_se") and c != "calib_fixed"]  # (dropped as documented)
    if not gone:
        return []
    new = ", ".join(c for c in ("A", "n", "p0", "gamma", "faf", "bias", "scale")
                    if c in out.columns)
    return [f"columns {', '.join(gone)} of the anchors file are not in the output: they "
            f"describe another path-loss model, which the calibrated {new} replace "
            "(--model names the model to calibrate)"]


def _d0_with_p0(settings: CalibrateSettings, table: pd.DataFrame,
                anchors: pd.DataFrame | None) -> float | dict[str, float]:
    """The attenuation-factor ``d0``: the anchors file's own ``d0`` where its ``p0`` is
    used (a p0 is a power at its own d0), else ``--d0``; an explicit ``--d0`` that
    differs from the file's is refused."""
    if (settings.model != "attenuation-factor" or anchors is None
            or "p0" not in anchors.columns or "d0" not in anchors.columns):
        return settings.d0
    ids = anchors["anchor"].astype(str).to_numpy()
    p0 = to_number(anchors["p0"]).to_numpy(dtype=float)
    d0 = to_number(anchors["d0"]).to_numpy(dtype=float)
    use = np.isfinite(p0) & np.isfinite(d0)
    if not use.any():
        return settings.d0
    bad = use & ~(d0 > 0)
    if bad.any():
        raise InputError(f"anchor {ids[np.argmax(bad)]}: d0 must be positive, got "
                         f"{d0[np.argmax(bad)]:g}", anchors.attrs.get("path"))
    if settings.d0 != CalibrateSettings().d0 and np.any(d0[use] != settings.d0):
        raise InputError(
            f"--d0 {settings.d0:g} contradicts the anchors file's d0 "
            f"({', '.join(f'{v:g}' for v in np.unique(d0[use]))}) that goes with its p0: "
            "drop --d0, or give --p0 with it", anchors.attrs.get("path"))
    own = dict(zip(ids[use], d0[use].tolist()))
    return {a: own.get(a, settings.d0) for a in table["anchor"].astype(str).unique()}


def _records(table: pd.DataFrame) -> list[dict[str, Any]]:
    """The table's rows for ``--json``: NaN and infinities as None (strict JSON; a
    ``-Infinity`` came out for an undetermined fit: the calibration review)."""
    return table.replace({np.nan: None, np.inf: None, -np.inf: None}).to_dict(
        orient="records")


def self_calibrate(
    anchors: pd.DataFrame, xyz: np.ndarray, values: np.ndarray, kind: str, *,
    height_offset: np.ndarray | None = None, model_name: str | None = "log-distance",
    fit_scale: bool = True, se_ratio: float = 3.0, tags: np.ndarray | None = None,
    diagnostics: dict[str, Any] | None = None,
) -> tuple[Any, Any]:
    """Self-calibration on arrays: robust start fixes (huber), then the joint adjustment
    of :class:`robustloc.models.selfcal.SelfCalibrator` (``tags``: each epoch's tag, for
    its test of tags that stand still).  ``diagnostics``, when given, receives
    ``anchors_suspect``: the anchors whose log scale after the calibration is far above
    the median anchor's, as ``locate`` reports them (:func:`_suspect_after`).

    The priors, which a parameter the log cannot determine keeps: the anchors' ``A, n``
    (RSSI; also the start) or their range ``bias, scale`` (0 / 1 where not given; the
    adjustment starts from 0 / 1 and the raw ranges' fixes either way).

    Returns ``(SelfCalibration, path-loss model or None)``; the anchors frame with the new
    columns is ``robustloc.models.calibration.self_calibration_table(res, anchors, model)``.
    """
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
        start = _start_fixes(xyz, values, "rssi", A=A0, n=n0, height_offset=height_offset)
        cal = SelfCalibrator("rssi", fit_slope=type(model).__name__ != "FreeSpace",
                             se_ratio=se_ratio)
        res = cal.fit(xyz, values, start, offset0=A0, slope0=n0,
                      height_offset=height_offset, anchor_ids=ids, tags=tags)
    else:
        from robustloc.models.calibration import range_calibration

        # the raw ranges' fixes and model (0 / 1) are the start, so that what the log
        # determines does not depend on the anchors file's bias and scale; a parameter it
        # cannot determine keeps the file's (its prior)
        bias0, scale0 = range_calibration(anchors)
        start = _start_fixes(xyz, values, "range", height_offset=height_offset)
        cal = SelfCalibrator("range", fit_slope=fit_scale, se_ratio=se_ratio)
        res = cal.fit(xyz, values, start, offset_prior=bias0, slope_prior=scale0,
                      height_offset=height_offset, anchor_ids=ids, tags=tags)
    if diagnostics is not None:
        diagnostics["anchors_suspect"] = _suspect_after(res, xyz, values, kind, ids,
                                                        height_offset)
    return res, model


def _suspect_after(res: Any, xyz: np.ndarray, values: np.ndarray, kind: str,
                   ids: list[str], height_offset: np.ndarray | None) -> dict[str, float]:
    """``locate``'s suspect anchors (:func:`robustloc.pipelines.locate.suspect_of_scale`:
    log scale over the median's above
    :data:`~robustloc.pipelines.locate.SUSPECT_SCALE_RATIO`) of the *calibrated* log: the
    ranges ``(z - bias) / scale`` or the RSSI under the fitted ``A, n``, each parameter
    left out at its prior.

    The test ran on the raw log (the start fixes' model), where the bias or scale that
    ``--self`` exists to estimate is itself a disagreement: a UWB antenna delay of 0.45 m
    at 5 cm noise, recovered to 0.453 m, was named "misplaced" at 8.87x, a scale of 1.1
    at 41.3x.  After the calibration they read 1.0x, while an anchor placed 2 m off in a
    20 m square of five still reads 8-14x (the fit absorbs part of it into its bias and
    scale) and one 190 m off, which leaves every parameter out, 2 560x
    (``tests/test_calibrate_review5.py``)."""
    from robustloc.estimators.ranging import DEFAULT_METHOD, Locator
    from robustloc.pipelines.locate import suspect_of_scale

    offset = np.asarray(res.offset, dtype=float)
    slope = np.asarray(res.slope, dtype=float)
    if not (np.isfinite(offset).all() and np.isfinite(slope).all() and (slope > 0).all()):
        return {}  # (refused by _refuse_implausible; nothing calibrated to test)
    loc = Locator(DEFAULT_METHOD)
    if kind == "rssi":
        scale = loc.log_scale(xyz, values, "rssi", A=offset, n=slope,
                              height_offset=height_offset)
    else:
        scale = loc.log_scale(xyz, (values - offset) / slope, "range",
                              height_offset=height_offset)
    return suspect_of_scale(scale, ids)


def _start_fixes(xyz: np.ndarray, values: np.ndarray, kind: str, **kw: Any) -> np.ndarray:
    """The self-calibration's start positions: the fixes ``robustloc locate`` gives with
    its defaults (:func:`robustloc.integrity.fixes.locate_protected` with
    :data:`~robustloc.estimators.ranging.DEFAULT_METHOD`: the log's scale, every fix
    tested, an ambiguous fix of nearly collinear anchors on the side of their line that
    the log's unambiguous fixes show).  A fix that is not usable (a minority of its
    observations kept, ...) gives no start and its epoch is left out.  The joint
    adjustment stays in the basin of its start.

    Measured on the wifi-rtt corridor, whose tags walk on one side of the access points'
    line (``locate`` after ``calibrate --self``, RMS / p95 / misleading fixes): every plain
    fix as a start, 3.43 / 5.83 m / 0.89 %; the usable ``huber`` fixes on the log's side,
    3.15 / 4.89 m / 0.52 % with the log scale's full variance-component weighting, but
    3.60 / 7.20 m / 0.67 % with :data:`~robustloc.estimators.ranging.LOG_SCALE_WEIGHTING`
    (the starts' side of the line is that fragile); the default fixes, 3.22 / 5.09 m /
    0.59 %.  The default fixes also take the office from 1.29 to 1.27 m and ble-tetam from
    2.76 to 2.74 m; the lecture theatre, uwb-dwm1001 and uwb-labyrinth move by less than
    1 %.

    The w-test's flags are all taken at once here (``snoop=False``): a fix that one-at-
    a-time snooping rescues keeps three of four ranges (redundancy 1), and as starts
    such fixes took the joint adjustment of a tag circling inside four anchors, 8 % of
    its ranges 5-15 m long, to another root (scales 1.13-1.28 for 1.01; the default
    ``locate``'s median error after it 0.49 m against 0.29 m as surveyed;
    ``tests/test_calibrate_review2.py``)."""
    from robustloc import status as st
    from robustloc.estimators.ranging import DEFAULT_METHOD, Locator
    from robustloc.integrity.fixes import locate_protected

    loc = Locator(DEFAULT_METHOD)
    sol = locate_protected(loc, xyz, values, kind, snoop=False, **kw)
    pos = np.array(sol.position, dtype=float)
    pos[~st.among(sol.status, st.USABLE)] = np.nan
    return pos


def _self(settings: CalibrateSettings, anchors: pd.DataFrame, self_log: Any) -> Calibration:
    from robustloc.io import read_measurements, to_epochs
    from robustloc.models.calibration import self_calibration_table, self_left_out

    where = anchors.attrs.get("path")
    if ((settings.dim == 3 or settings.tag_height is not None)
            and "z" not in anchors.columns):
        raise InputError("--dim 3 and --tag-height need a z column in the anchors file",
                         where, 1)
    if settings.dim == 3 and settings.tag_height is not None:
        raise InputError("--tag-height is for --dim 2")
    ids = [str(a) for a in anchors["anchor"]]
    meas = (self_log if isinstance(self_log, pd.DataFrame)
            else read_measurements(self_log, anchors))
    ep = to_epochs(meas, ids)
    kind = ep.value
    cols = ["x", "y"] + (["z"] if settings.dim == 3 else [])
    xyz = anchors[cols].to_numpy(dtype=float)
    height = None
    if settings.tag_height is not None:
        height = anchors["z"].to_numpy(dtype=float) - settings.tag_height
    if kind == "rssi" and settings.scale is not None:
        raise InputError("--scale is for range data")
    if kind == "range" and settings.model != "log-distance":
        raise InputError(f"--model {settings.model} is a path-loss model for RSSI, but "
                         "this log holds ranges", _name(self_log))
    res, model = self_calibrate(anchors, xyz, ep.values, kind, height_offset=height,
                                model_name=settings.model,
                                fit_scale=settings.scale is not False,
                                se_ratio=settings.se_ratio, tags=ep.tag,
                                diagnostics=(diag := {}))
    if res.epochs_used == 0 and res.epochs_bad:
        # (every epoch had its redundancy, and every one failed its test: the reason was
        # given as "no epoch has a fix with redundancy"; the self-calibration review)
        raise InputError(
            f"nothing to self-calibrate: every epoch with a fix failed its test "
            f"({res.epochs_bad} of {res.epochs_total} epochs bad, {res.epochs_no_start} "
            "without a start fix): the prior model does not fit the log (tags far from the "
            "anchors, a wrong path-loss model or anchor position?)"
            + (f"; {len(res.warnings)} warning(s), the first: {res.warnings[0]}"
               if res.warnings else ""), _name(self_log))
    if res.epochs_used == 0:
        from robustloc.models.selfcal import _elongation

        heard = np.isfinite(ep.values).any(axis=0)
        flat = _elongation(xyz[heard]) if heard.sum() > settings.dim else 1.0
        why = (f"; the anchors heard lie on a {'line' if settings.dim == 2 else 'plane'} "
               f"(elongation {flat:.2g}), where every fix is ill-conditioned"
               if flat < 1e-6 else "")
        raise InputError(
            f"nothing to self-calibrate: no epoch has a fix with redundancy (need at least "
            f"{settings.dim + 1} anchors heard in one epoch; {res.epochs_total} epochs, "
            f"{res.epochs_no_start} without a start fix{why})", _name(self_log))
    _refuse_implausible(res, ids, kind, ep.values, _name(self_log))
    table, out = self_calibration_table(res, anchors, model)
    notes = []
    # the input rows set aside, said as `locate` says them for the same file (they were
    # silent here: the calibration review)
    if ep.n_duplicates:
        notes.append(f"{ep.n_duplicates} duplicate rows (same epoch and anchor) averaged")
    if int(np.sum(ep.n_invalid)):
        notes.append(f"invalid_measurement: {int(np.sum(ep.n_invalid))} rows (outside the "
                     "physical limits of robustloc.io.limits; not used)")
    if res.free.any() and self_left_out(res, model)[np.asarray(res.n_obs) > 0].any():
        # (the calibration review: a true bias of 0.3 m left out at its prior 0 moved the
        # scales by 3-17 of their standard errors)
        notes.append("the standard errors assume that the parameters left out equal "
                     "their priors: where one does not, the estimates that share its "
                     "epochs are off by more than their standard errors say")
    notes.extend(_sigma_notes(res, anchors, out))
    notes.extend(_dropped_columns(anchors, out))
    if kind == "rssi":
        # the self-calibration review: on simulated logs the (A, n) estimates were off by
        # several standard errors already at 1 dB of noise (A by -2.2 dB, n by -0.2), and
        # 10 % one-sided gross errors could drive them far off, without a warning
        notes.append(RSSI_SELFCAL_NOTE)
    summary = {
        "kind": kind, "epochs": res.epochs_total, "epochs_used": res.epochs_used,
        "epochs_no_redundancy": res.epochs_no_redundancy, "epochs_bad": res.epochs_bad,
        "epochs_no_start": res.epochs_no_start,
        "observations_rejected": res.observations_rejected,
        "sigma0": round(res.sigma0, 4), "iterations": res.iterations,
        "converged": res.converged, "parameters": _records(table),
        "warnings": list(res.warnings), "notes": notes,
    }
    headline = (f"self-calibration ({kind}), {res.epochs_used} of {res.epochs_total} epochs "
                f"used ({res.epochs_no_redundancy} without redundancy, {res.epochs_bad} bad, "
                f"{res.epochs_no_start} without a start fix; {res.observations_rejected} "
                f"observations rejected), {res.iterations} iterations over its stages, "
                f"sigma0 {res.sigma0:.3f}")
    warn = list(res.warnings) + _suspect_warnings(diag.get("anchors_suspect") or {})
    summary["warnings"] = warn
    return Calibration(out, table, "m" if kind == "range" else "dB", summary, headline,
                       notes=notes, warnings=[f"{_name(self_log)}: {w}" for w in warn])


def _sigma_notes(res: Any, anchors: pd.DataFrame, out: pd.DataFrame) -> list[str]:
    """What was written for the anchors whose sigma the log does not determine
    (:func:`robustloc.models.calibration._self_sigma`)."""
    und = ~res.sigma_determined()
    if not und.any():
        return []
    ids = anchors["anchor"].astype(str).to_numpy()
    if "sigma" not in out.columns or not to_number(out["sigma"]).notna().any():
        return ["no sigma written: the log determines no anchor's (locate measures the "
                "log's noise scale itself)"]
    given = (to_number(anchors["sigma"]).notna().to_numpy() if "sigma" in anchors.columns
             else np.zeros(len(ids), dtype=bool))
    notes = []
    for who, what in ((und & given, "the anchors file's sigma kept"),
                      (und & ~given, "sigma written as the median of the determined "
                       "anchors'")):
        if who.any():
            sel = ids[who]
            named = ", ".join(sel[:20]) + (f" and {sel.size - 20} more" if sel.size > 20
                                           else "")
            notes.append(f"anchor(s) {named}: {what} (the log does not determine theirs)")
    return notes


def _suspect_warnings(suspect: dict[str, float]) -> list[str]:
    """A warning naming the anchors whose calibrated observations disagree with the fixes
    far more than the median anchor's, as ``locate``'s ``anchors_suspect`` (their log
    scale over the median's; :func:`_suspect_after`).  An anchor placed 190 m off made
    the log look static ("the tag does not move"), every parameter was left out and
    sigmas of 31-191 m written, with no word on the anchor (the self-calibration review,
    2026-12-06)."""
    if not suspect:
        return []
    each = ", ".join(f"{a} ({r:g}x)" for a, r in suspect.items())
    return [f"anchor(s) {each}: observations that disagree with the fixes far more than "
            "the median anchor's even after the calibration (their noise scale over the "
            "calibrated log, against the median's); check their coordinates and ids: a "
            "misplaced anchor is no bias or scale, and it spoils the whole fit"]


def _refuse_implausible(res: Any, ids: list[str], kind: str, values: np.ndarray,
                        where: str | None) -> None:
    """Refuse a self-calibration that settled on a model no log can have: a scale or a
    path-loss exponent that is not positive (the observations would grow with distance:
    RSSI, or shrink: ranges), an RSSI exponent outside the interval a survey's fit is held
    to (:func:`robustloc.models.calibration.exponent_interval`), or a range bias beyond
    the anchor's longest range (every predicted range would exceed every measured
    one).  On a short log of three anchors the adjustment wandered to a bias of 8 km and
    a scale of -0.07 and wrote them, exit 0; ``locate`` then refused the file (the
    calibration review)."""
    from robustloc.io.limits import RANGE_SCALE_LIMITS
    from robustloc.models.calibration import MAX_EXPONENT, MIN_EXPONENT, exponent_interval

    names = res.param_names
    bad = []
    for j, name in enumerate(ids):
        if res.free[j, 1] and not (np.isfinite(res.slope[j]) and res.slope[j] > 0):
            bad.append(f"{names[1]} of anchor {name} = {res.slope[j]:.4g} (must be positive)")
        elif res.free[j, 1] and kind == "rssi" and not (
                MIN_EXPONENT <= res.slope[j] <= MAX_EXPONENT):
            # (a survey's fit is held to the same interval: an exponent the anchors
            # reader refuses was written, exit 0 -- the input review)
            bad.append(f"{names[1]} of anchor {name} = {res.slope[j]:.4g} (a path-loss "
                       f"exponent lies in {exponent_interval()})")
        elif res.free[j, 1] and kind == "range" and not (
                RANGE_SCALE_LIMITS[0] <= res.slope[j] <= RANGE_SCALE_LIMITS[1]):
            # (the anchors reader refuses such a scale: it was written, exit 0, and
            # locate refused the file -- the input review)
            lo, hi = RANGE_SCALE_LIMITS
            bad.append(f"{names[1]} of anchor {name} = {res.slope[j]:.4g} (a range scale "
                       f"lies in [{lo:g}, {hi:g}])")
        if res.free[j, 0] and not np.isfinite(res.offset[j]):
            bad.append(f"{names[0]} of anchor {name} = {res.offset[j]}")
        elif res.free[j, 0] and kind == "range":
            col = values[:, j]
            longest = float(np.nanmax(col)) if np.isfinite(col).any() else np.inf
            if abs(res.offset[j]) > longest:
                bad.append(f"bias of anchor {name} = {res.offset[j]:.4g} m, beyond its "
                           f"longest range {longest:.4g} m")
    if bad:
        raise InputError(
            "self-calibration settled on an implausible model: " + "; ".join(bad[:5])
            + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
            + f" ({res.epochs_used} of {res.epochs_total} epochs used): the log does not "
            "determine the anchors' parameters (too few anchors or epochs, or the tag's "
            "path does not vary the geometry); nothing written", where)


#: What RSSI self-calibration cannot promise (printed with every RSSI ``--self`` run).
RSSI_SELFCAL_NOTE = (
    "RSSI self-calibration: each epoch's position is an unknown of its own, so A and n "
    "carry an incidental-parameter bias the standard errors leave out (simulated 5-anchor "
    "rooms at 1 dB of noise: A off by 2-4 dB and n by 0.2-0.36, 3-6 standard errors, "
    "moving with the prior and the seed), and one-sided "
    "gross errors (10 % of readings 10-25 dB weak) can take them far off, as can a tag that "
    "keeps one distance to an anchor at 1.5 dB of noise or more (its n, with a small standard "
    "error and no warning: docs/limits.md); calibrate RSSI "
    "from a survey (robustloc calibrate SURVEY) where you can")
