"""The ``spp`` workflow: GNSS single-point positioning of a RINEX file, with RAIM FDE.

:func:`run_spp` reads the observation and navigation (or SP3/CLK) files, optionally
injects faults, solves every epoch (:class:`~robustloc.gnss.spp.SppSolver`, with
:class:`~robustloc.gnss.raim.RaimFde` when ``raim``) and returns the solution frame and
the run summary.  :class:`SppSettings` holds every setting.  ``robustloc spp``,
:func:`robustloc.spp` and the Dask engine run this code.
"""

from __future__ import annotations

import argparse
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from os import PathLike
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from robustloc.errors import InputError
from robustloc.options import check_settings, float_in, nonnegative_int, option


def parse_time(text: str | float | None, what: str) -> float | None:
    """GPS seconds, or an ISO time, as GPS seconds (``None`` passes).

    An ISO time without a time zone is on the GPS scale (as RINEX epochs are); one with a
    zone (``Z``, ``+02:00``) is a civil time: converted to UTC, then to GPS time with the
    leap seconds (numpy parsed the zone with a deprecation UserWarning and left the
    18 s out).
    """
    from datetime import datetime, timezone

    from robustloc.gnss.rinex import _utc_to_gps_s, datetime64_to_gps_s

    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        try:
            stamp = datetime.fromisoformat(str(text).strip())
        except ValueError:
            try:  # forms numpy reads and datetime does not ("2021-04": the month's start)
                with warnings.catch_warnings():  # (a zone numpy reads with a UserWarning)
                    warnings.simplefilter("error")
                    value = float(datetime64_to_gps_s(
                        np.array([np.datetime64(str(text))]))[0])
            except (ValueError, UserWarning):
                value = float("nan")
        else:
            zone = stamp.utcoffset()
            naive = stamp.astimezone(timezone.utc).replace(tzinfo=None) if zone is not None \
                else stamp
            value = float(datetime64_to_gps_s(np.array([np.datetime64(naive, "ns")]))[0])
            if zone is not None:
                value = float(_utc_to_gps_s(np.array([value]))[0])
    if not np.isfinite(value):
        raise InputError(f"{what}: expected GPS seconds or an ISO time, got {text!r}")
    return value


def _check_nav_covers(ephemerides: Any, t_obs_gps_s: np.ndarray) -> None:
    """Refuse navigation files none of whose records is valid at any observation epoch:
    files of another day gave "no usable pseudoranges" naming the observation file."""
    from robustloc.gnss.ephemeris import MAX_AGE_S

    toe = np.asarray(ephemerides.toe_gps_s, dtype=float)
    age = np.array([MAX_AGE_S.get(str(s)[:1], 7201.0) for s in ephemerides.sat])
    ok = np.isfinite(toe)
    if not ok.any():
        return
    lo, hi = float(np.min((toe - age)[ok])), float(np.max((toe + age)[ok]))
    o0, o1 = float(np.nanmin(t_obs_gps_s)), float(np.nanmax(t_obs_gps_s))
    if hi < o0 or lo > o1:
        paths = list(ephemerides.paths)
        others = f" (and {', '.join(paths[1:])})" if len(paths) > 1 else ""
        raise InputError(f"the ephemerides{others} are valid for GPS seconds {lo:.0f} .. "
                         f"{hi:.0f} (time of ephemeris +- {MAX_AGE_S['G']:.0f} s for GPS), "
                         f"the observations span {o0:.0f} .. {o1:.0f}: no epoch in common "
                         "(another day?)", paths[0])


def parse_reference(text: str) -> tuple[float, float, float]:
    """``--reference X,Y,Z`` (ECEF m) -> a checked position (see :func:`check_reference`)."""
    try:
        ref = tuple(float(v) for v in text.split(","))
    except ValueError:
        ref = ()
    return check_reference(ref, text)


def check_reference(ref: Sequence[float], shown: object = None) -> tuple[float, float, float]:
    """An ECEF position on or near the Earth: 6 356 km (pole) .. 6 378 km plus 1e5 m slack."""
    arr = np.asarray(ref, dtype=float).ravel()
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or not (
            6.2e6 <= np.linalg.norm(arr) <= 6.5e6):
        raise InputError(f"--reference: expected X,Y,Z ECEF metres of a point near the "
                         f"Earth's surface (norm 6.2e6 .. 6.5e6 m), got "
                         f"{shown if shown is not None else tuple(ref)!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


def parse_inject(text: str) -> dict[str, float]:
    """``--inject PRN:BIAS_M[,PRN:BIAS_M]`` -> ``{"G11": 20.0, ...}`` (checked)."""
    out: dict[str, float] = {}
    for item in text.split(","):
        try:
            sat, bias = item.split(":")
            one = check_inject({sat: float(bias)}, item)
        except ValueError:
            raise InputError(f"--inject: expected PRN:BIAS_M, got {item!r}") from None
        (key,) = one
        if key in out:  # G11:20,G11:30 kept the last silently: say which was meant
            raise InputError(f"--inject: {key} given twice ({text!r}); one bias per satellite")
        out.update(one)
    return out


def check_inject(inject: Mapping[str, float], shown: str | None = None) -> dict[str, float]:
    """Per-satellite biases: ids normalized (``G5`` -> ``G05``), finite, within +-1e6 m."""
    out: dict[str, float] = {}
    for sat, bias in inject.items():
        s = str(sat).strip().upper()
        if len(s) == 2:
            s = s[0] + "0" + s[1]
        b = float(bias)
        if not np.isfinite(b) or abs(b) > 1e6:
            raise InputError("--inject: bias must be finite, within +-1e6 m, got "
                             f"{shown if shown is not None else f'{sat}:{bias}'!r}")
        out[s] = b
    return out


def _systems(text: str) -> str:
    from robustloc.options import check_systems

    check_systems(text, "GREC")
    return text


@dataclass(frozen=True)
class SppSettings:
    """Every setting of ``spp`` (the ``robustloc spp`` options of the same name).

    ``reference`` is an ECEF position (m) for the summary's errors (default the RINEX
    header's); ``inject`` per-satellite biases (m) added between ``inject_from`` and
    ``inject_until`` (GPS seconds or ISO times); ``iono`` ``None`` means ``iflc`` with
    precise products, else ``klobuchar``.
    """

    systems: str = "GREC"
    elevation_mask: float = option(15.0, check=float_in(-90.0, 90.0))
    iono: str | None = option(None, choices=("klobuchar", "iflc", "none"))
    tropo: str = option("saastamoinen", choices=("saastamoinen", "none"))
    smooth: int = option(0, check=nonnegative_int)
    raim: bool = False
    alpha0: float = option(0.001, check=float_in(1e-15, 0.5))
    beta0: float = option(0.10, check=float_in(1e-15, 0.5))
    max_exclusions: int | None = option(None, check=nonnegative_int)
    reference: tuple[float, float, float] | None = None
    inject: Mapping[str, float] | None = None
    inject_from: str | float | None = None
    inject_until: str | float | None = None

    def __post_init__(self) -> None:
        check_settings(self)
        _systems(self.systems)
        if self.reference is not None:
            object.__setattr__(self, "reference", check_reference(self.reference))
        if self.inject:
            object.__setattr__(self, "inject", check_inject(self.inject))
        parse_time(self.inject_from, "--inject-from")
        parse_time(self.inject_until, "--inject-until")

    @classmethod
    def from_namespace(cls, args: argparse.Namespace) -> SppSettings:
        """The settings of a parsed ``robustloc spp`` command line (text options parsed)."""
        # (--alpha0 and --beta0 default to None on the command line, which refuses them
        # without --raim: None is the settings' default)
        tests = {k: getattr(args, k) for k in ("alpha0", "beta0")
                 if getattr(args, k, None) is not None}
        return cls(
            systems=args.systems, elevation_mask=args.elevation_mask, iono=args.iono,
            tropo=args.tropo, smooth=args.smooth, raim=args.raim, **tests,
            max_exclusions=args.max_exclusions,
            reference=None if args.reference is None else parse_reference(args.reference),
            inject=parse_inject(args.inject) if args.inject else None,
            inject_from=args.inject_from, inject_until=args.inject_until)


def _model_notes(iono: str, nav: bool, precise: bool, systems: str) -> list[str]:
    """What the run's models could not take from its inputs (printed as notes)."""
    notes = []
    if iono == "klobuchar" and not nav:
        notes.append("Klobuchar ionosphere with RTKLIB's default coefficients: no "
                     "navigation file gives the day's")
    if precise and iono != "iflc":
        if not nav:
            notes.append("single-frequency code with precise clocks (they refer to the "
                         "ionosphere-free pair) and no navigation file: the satellites' "
                         "group delays (TGD/BGD, up to a few metres) are not applied; give "
                         "the navigation file too, or use --iono iflc")
        elif set(systems) & set("RC"):
            notes.append("single-frequency code with precise clocks: the group delays of "
                         "GPS and Galileo come from the navigation file, those of GLONASS "
                         "and BeiDou are not applied")
    return notes


def _nearest_fix(res: Any, approx_xyz_m: np.ndarray) -> np.ndarray:
    """Each epoch's usable fix, else the one nearest in time, else the header position
    (NaN when that is none): where to take the elevations of an epoch without a fix."""
    t = np.asarray(res.t_gps_s, dtype=float)
    out = np.full((t.size, 3), np.nan)
    if np.linalg.norm(approx_xyz_m) > 6.0e6:
        out[:] = approx_xyz_m
    have = np.flatnonzero(res.ok)
    if have.size:
        order = have[np.argsort(t[have], kind="stable")]
        ts = t[order]
        k = np.clip(np.searchsorted(ts, t), 1, max(ts.size - 1, 1))
        before = order[np.clip(k - 1, 0, ts.size - 1)]
        after = order[np.clip(k, 0, ts.size - 1)]
        pick = np.where(np.abs(t - t[before]) <= np.abs(t[after] - t), before, after)
        out = res.xyz_m[pick].copy()
    return out


def run_spp(obs: str, nav: Sequence[str] | str, settings: SppSettings, *,
            sp3: str | None = None,
            clk: str | None = None) -> tuple[pd.DataFrame, dict[str, Any]]:
    """Solve every epoch of a RINEX observation file (``nav``: one navigation file's path,
    or a sequence of them; one path was read character by character, "file not found"
    naming its first letter).

    Returns
    -------
    (DataFrame, dict)
        One row per epoch (``SppResult.to_frame``: time, ECEF and geodetic position,
        clock, status, satellites used and excluded, DOP, protection levels), and the run
        summary (errors against the reference, status counts, RAIM counts, and
        ``nav_records_set_aside``: a ``FILE:LINE: ...`` message per navigation record that
        cannot describe a satellite, when there are any; :func:`read_nav` also issues each
        as a :class:`~robustloc.gnss.rinex.NavRecordWarning`).
    """
    from robustloc import status as st
    from robustloc.gnss.raim import RaimFde, inject_faults
    from robustloc.gnss.rinex import read_nav, read_obs

    if isinstance(nav, (str, PathLike)):
        nav = [nav]
    from robustloc.gnss.sp3 import N_LAGRANGE, PreciseProducts, read_clk, read_sp3
    from robustloc.gnss.spp import SppSolver, error_summary

    nav = list(nav)
    if str(obs).lower().endswith((".csv", ".parquet", ".pq")):
        # a table (the pseudoranges and satellite positions `simulate gnss` writes) is
        # not an observation file; without this, the first complaint was the missing
        # navigation file
        raise InputError("spp solves a RINEX observation file with navigation files (or "
                         "--sp3); a table of pseudoranges with satellite positions, as "
                         "`robustloc simulate gnss` writes, is for integrity studies from "
                         "Python (robustloc.integrity.snooping.snoop_linear on the "
                         "pseudoranges linearized at truth.csv; `simulate gnss --help` shows "
                         "how) or `robustloc montecarlo --gnss`", obs)
    if not nav and sp3 is None:
        raise InputError("give at least one navigation file or --sp3")
    if clk is not None and sp3 is None:
        raise InputError("--clk needs --sp3")
    # (each was accepted and changed nothing: the GNSS review)
    if not settings.inject:
        for given, name in ((settings.inject_from, "--inject-from"),
                            (settings.inject_until, "--inject-until")):
            if given is not None:
                raise InputError(f"{name} goes with --inject")
    if settings.max_exclusions is not None and not settings.raim:
        raise InputError("--max-exclusions goes with --raim")
    for f in [obs, *nav, sp3, clk]:
        if f is not None and not Path(f).is_file():
            raise InputError("file not found" if not Path(f).exists()
                             else "is not a regular file", f)
    t_from = parse_time(settings.inject_from, "--inject-from")
    t_until = parse_time(settings.inject_until, "--inject-until")
    if t_from is not None and t_until is not None and t_from > t_until:
        # (nothing was injected, without a word)
        raise InputError(f"--inject-from ({settings.inject_from}) is later than "
                         f"--inject-until ({settings.inject_until}): no epoch between them")
    observations = read_obs(obs)
    # epochs out of time order are solved in time order, as the measurement readers take
    # rows in any order (docs/formats.md), and said: in file order the Hatch filter
    # smoothed across the backward step and the rows came out unsorted, without a word
    # (the GNSS review: the first two GEONET epochs swapped moved fixes 0.26 m)
    unsorted_note = None
    back = np.flatnonzero(np.diff(observations.t_gps_s) < 0)
    if back.size:
        line = int(observations.line[back[0] + 1])
        observations = observations.select(np.argsort(observations.t_gps_s, kind="stable"))
        unsorted_note = (f"{obs}:{line}: an epoch earlier than the one before it "
                         f"({back.size} such in the file): the epochs are solved and "
                         "written in time order")
    ephemerides = read_nav(nav) if nav else None
    precise = None
    if sp3 is not None:
        precise = PreciseProducts(read_sp3(sp3), read_clk(clk) if clk else None)
        for name, product in ((sp3, precise.sp3), (clk, precise.clk)):
            # a product of another day gave no value, and the clocks of the SP3 (or no
            # satellite) were used without a word
            if product is None or not len(product.t_gps_s) or not observations.n_epochs:
                continue
            if product is precise.sp3 and len(product.t_gps_s) < N_LAGRANGE:
                # (3 epochs were interpolated by a parabola: orbits hundreds of metres off,
                # fixes labelled ok: the spp review)
                raise InputError(f"{len(product.t_gps_s)} epochs: interpolating the orbits "
                                 f"needs at least {N_LAGRANGE} (degree-{N_LAGRANGE - 1} "
                                 "Lagrange); use a product that covers the observations with "
                                 "margin", name)
            t0, t1 = float(np.nanmin(product.t_gps_s)), float(np.nanmax(product.t_gps_s))
            o0 = float(np.nanmin(observations.t_gps_s))
            o1 = float(np.nanmax(observations.t_gps_s))
            if t1 < o0 or t0 > o1:
                raise InputError(f"covers GPS seconds {t0:.0f} .. {t1:.0f}, the observations "
                                 f"{o0:.0f} .. {o1:.0f}: no epoch in common (another day?)",
                                 name)
    if ephemerides is not None and precise is None and observations.n_epochs:
        _check_nav_covers(ephemerides, observations.t_gps_s)
    injected_epochs = None
    if settings.inject:
        observations = inject_faults(observations, dict(settings.inject), t_from, t_until)
        t = observations.t_gps_s
        injected_epochs = int(np.sum((t >= (-np.inf if t_from is None else t_from))
                                     & (t <= (np.inf if t_until is None else t_until))))
    iono = settings.iono or ("iflc" if precise is not None else "klobuchar")
    if settings.smooth and iono != "iflc":  # (the solver's words were iono='iflc')
        raise InputError(f"--smooth needs --iono iflc (it smooths the ionosphere-free "
                         f"combination with carrier phase); the ionosphere is {iono}")
    try:  # settings the solver refuses (e.g. --smooth without iflc) are option errors
        solver = SppSolver(systems=settings.systems,
                           elevation_mask_deg=settings.elevation_mask, iono=iono,
                           tropo=settings.tropo, smoothing_epochs=settings.smooth)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if settings.raim:
        res = RaimFde(alpha0=settings.alpha0, beta0=settings.beta0,
                      max_exclusions=settings.max_exclusions
                      ).solve(solver, observations, ephemerides, precise)
    else:
        res = solver.solve(observations, ephemerides, precise)
    frame = res.to_frame()
    n_invalid = observations.invalid_per_epoch
    if len(frame) == len(n_invalid):
        # an epoch left without a solution by implausible pseudoranges: not one whose
        # values were of satellites it could not use (below the mask, another
        # constellation), which keeps its own reason (SppSolver.lost_to_invalid)
        judge = np.flatnonzero((n_invalid > 0) & ~frame["status"].isin(st.USABLE).to_numpy())
        if judge.size:
            near = _nearest_fix(res, observations.approx_xyz_m)[judge]
            lost = solver.lost_to_invalid(observations.select(judge), ephemerides, precise,
                                          near)
            status = frame["status"].to_numpy(copy=True)
            status[judge[lost]] = st.INVALID
            frame["status"] = status
    if settings.reference is not None:
        ref = np.asarray(settings.reference, dtype=float)
        ref_src = "--reference"
    else:
        ref = observations.approx_xyz_m
        ref_src = "RINEX header APPROX POSITION XYZ"
    summary: dict[str, Any] = {
        "obs": str(obs), "systems": res.systems, "iono": iono, "raim": bool(settings.raim),
        "invalid_measurement": int(n_invalid.sum())}
    if ephemerides is not None and ephemerides.rejected:
        summary["nav_records_set_aside"] = list(ephemerides.rejected)
    notes = _model_notes(iono, ephemerides is not None, precise is not None, res.systems)
    if unsorted_note is not None:
        notes.insert(0, unsorted_note)
    if (iono == "klobuchar" and ephemerides is not None
            and getattr(ephemerides, "ion_alpha", None) is None):
        # (the same default, silently, when the navigation file has no ION ALPHA/BETA:
        # the spp review)
        notes.append("Klobuchar ionosphere with RTKLIB's default coefficients: the "
                     "navigation file has no ION ALPHA / ION BETA (IONOSPHERIC CORR) record")
    if injected_epochs is not None:
        summary["injected_epochs"] = injected_epochs
        if injected_epochs == 0:  # (nothing injected, and nothing said: the spp review)
            notes.append("--inject: no epoch lies between --inject-from and --inject-until: "
                         "nothing was injected")
    if notes:
        summary["notes"] = notes
    if np.linalg.norm(ref) > 6.0e6:
        summary["reference"] = ref_src
        summary["reference_xyz_m"] = [float(v) for v in ref]
        summary.update(error_summary(res, ref))
    else:  # (no error statistics, and no share of errors within the bound)
        summary.update(error_summary(res, np.zeros(3)))
        summary["reference"] = "none (no --reference and no header position)"
    summary["status_counts"] = {str(k): int(v)
                                for k, v in frame["status"].value_counts().items()}
    return frame, summary
