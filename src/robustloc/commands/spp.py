"""``robustloc spp``: GNSS single-point positioning from RINEX, with RAIM FDE."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from robustloc.commands._argtypes import float_in, nonnegative_int
from robustloc.engines import add_engine_arguments

NAME = "spp"
HELP = "GNSS single-point positioning from RINEX (broadcast or SP3/CLK), with RAIM FDE"
DESCRIPTION = """\
Single-point positioning of every epoch of a RINEX 2/3 observation file: broadcast
ephemerides (GPS, Galileo, BeiDou) from one or more navigation files, or SP3 precise orbits
(+ CLK clocks) for any constellation including GLONASS; Klobuchar or ionosphere-free,
Saastamoinen troposphere, elevation mask and elevation weights, one receiver clock per
constellation, iterated WLS over all epochs at once.

--raim adds fault detection and exclusion: global test + w-test data snooping with the
B-method (alpha0 = 0.1 %, beta0 = 10 %), excluding several satellites in turn while the
redundancy allows, and horizontal/vertical protection levels from the MDB of each
satellite.  --inject adds a bias to real pseudoranges to exercise the detector.

Output: one row per epoch (time as GPS seconds, week, time of week and UTC ISO; ECEF, lat,
lon, h; receiver clock(s); n_sats; DOPs; sigma0; status; excluded satellites; test
statistics; hpl/vpl).  Status 'unavailable' (RAIM detected a fault it could not attribute,
or no redundancy to test) keeps the position but marks it unverified.  A pseudorange
outside 1.5e7 .. 5e7 m (robustloc.io.limits) is an invalid measurement: it is never used,
counted in the summary (invalid_measurement N), and an epoch left without a solution
because of such values has status 'invalid_measurement'.  A summary of errors
against --reference (default: the RINEX header's APPROX POSITION XYZ) is printed (--json
for JSON).

Example:
  robustloc spp 07590920.05o 07590920.05n --systems G --raim -o sol.csv
  robustloc spp slac1180.21o --sp3 COD.SP3 --clk COD.CLK --systems GRE --smooth 60 -o s.csv
  robustloc spp 07590920.05o 07590920.05n --raim --inject G11:20 --inject-from 796436400 -o f.csv
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("obs", help="RINEX observation file (2.xx or 3.xx)")
    p.add_argument("nav", nargs="*", help="RINEX navigation file(s)")
    p.add_argument("--sp3", default=None, help="SP3 precise orbit file")
    p.add_argument("--clk", default=None, help="RINEX clock file (with --sp3)")
    p.add_argument("--systems", default="GREC",
                   help="constellations to use, letters of GREC (default GREC: all present)")
    p.add_argument("--elevation-mask", type=float_in(-90.0, 90.0), default=15.0, metavar="DEG",
                   help="elevation mask in degrees (default 15)")
    p.add_argument("--iono", choices=("klobuchar", "iflc", "none"), default=None,
                   help="ionosphere: broadcast Klobuchar, ionosphere-free combination or none "
                        "(default: iflc with --sp3, else klobuchar)")
    p.add_argument("--tropo", choices=("saastamoinen", "none"), default="saastamoinen")
    p.add_argument("--smooth", type=nonnegative_int, default=0, metavar="EPOCHS",
                   help="carrier-smooth the ionosphere-free code over up to EPOCHS epochs "
                        "(Hatch filter, needs --iono iflc; default 0 = off)")
    p.add_argument("--raim", action="store_true", help="fault detection and exclusion + PLs")
    p.add_argument("--alpha0", type=float_in(1e-15, 0.5), default=0.001,
                   help="w-test significance (0.001)")
    p.add_argument("--beta0", type=float_in(1e-15, 0.5), default=0.10,
                   help="B-method missed detection (0.10)")
    p.add_argument("--max-exclusions", type=nonnegative_int, default=None,
                   help="at most this many satellites excluded per epoch")
    p.add_argument("--reference", default=None, metavar="X,Y,Z",
                   help="reference ECEF position (m) for the error summary (default: RINEX "
                        "header); write --reference=X,Y,Z when X is negative")
    p.add_argument("--inject", default=None, metavar="PRN:BIAS_M[,PRN:BIAS_M]",
                   help="add biases (m) to these satellites' pseudoranges, e.g. G11:20,G24:-15")
    p.add_argument("--inject-from", default=None, metavar="T",
                   help="start of the injected fault: GPS seconds or ISO time (GPS scale)")
    p.add_argument("--inject-until", default=None, metavar="T",
                   help="end of the injected fault (same formats)")
    p.add_argument("-o", "--out", required=True, help="solution file (.csv or .parquet)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_engine_arguments(p, what="the observation files (OBS: a directory or a glob)")


def _parse_time(text: str | None, what: str) -> float | None:
    from robustloc.errors import InputError
    from robustloc.gnss.rinex import datetime64_to_gps_s

    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        try:
            value = float(datetime64_to_gps_s(np.array([np.datetime64(text)]))[0])
        except ValueError:
            value = float("nan")
    if not np.isfinite(value):
        raise InputError(f"{what}: expected GPS seconds or an ISO time, got {text!r}")
    return value


def _parse_reference(text: str) -> np.ndarray:
    from robustloc.errors import InputError

    try:
        ref = np.array([float(v) for v in text.split(",")])
    except ValueError:
        ref = np.array([])
    # an ECEF position on or near the Earth: 6 356 km (pole) .. 6 378 km plus 1e5 m slack
    if ref.shape != (3,) or not np.all(np.isfinite(ref)) or not (
            6.2e6 <= np.linalg.norm(ref) <= 6.5e6):
        raise InputError(f"--reference: expected X,Y,Z ECEF metres of a point near the "
                         f"Earth's surface (norm 6.2e6 .. 6.5e6 m), got {text!r}")
    return ref


def _parse_inject(text: str) -> dict[str, float]:
    from robustloc.errors import InputError

    out: dict[str, float] = {}
    for item in text.split(","):
        try:
            sat, bias = item.split(":")
            sat = sat.strip().upper()
            if len(sat) == 2:
                sat = sat[0] + "0" + sat[1]
            out[sat] = float(bias)
        except ValueError:
            raise InputError(f"--inject: expected PRN:BIAS_M, got {item!r}") from None
        if not np.isfinite(out[sat]) or abs(out[sat]) > 1e6:
            raise InputError(f"--inject: bias must be finite, within +-1e6 m, got {item!r}")
    return out


def run(args: argparse.Namespace) -> int:
    if args.engine == "dask":
        from robustloc.engines.dask import run_spp
        return run_spp(args, run)
    from robustloc import status as st
    from robustloc.errors import InputError
    from robustloc.gnss.raim import RaimFde, inject_faults
    from robustloc.gnss.rinex import read_nav, read_obs
    from robustloc.gnss.sp3 import PreciseProducts, read_clk, read_sp3
    from robustloc.gnss.spp import SppSolver, error_summary

    if not args.nav and args.sp3 is None:
        raise InputError("give at least one navigation file or --sp3")
    if args.clk is not None and args.sp3 is None:
        raise InputError("--clk needs --sp3")
    bad_sys = sorted(set(args.systems.upper()) - set("GREC"))
    if not args.systems or bad_sys:
        raise InputError(f"--systems: unknown constellation(s) {''.join(bad_sys)!r}; use "
                         f"letters of GREC, got {args.systems!r}")
    for f in [args.obs, *args.nav, args.sp3, args.clk]:
        if f is not None and not Path(f).is_file():
            raise InputError("file not found" if not Path(f).exists()
                             else "is not a regular file", f)
    ref = _parse_reference(args.reference) if args.reference is not None else None
    inject = _parse_inject(args.inject) if args.inject else None
    t_from = _parse_time(args.inject_from, "--inject-from")
    t_until = _parse_time(args.inject_until, "--inject-until")
    obs = read_obs(args.obs)
    nav = read_nav(args.nav) if args.nav else None
    precise = None
    if args.sp3 is not None:
        precise = PreciseProducts(read_sp3(args.sp3),
                                  read_clk(args.clk) if args.clk else None)
    if inject:
        obs = inject_faults(obs, inject, t_from, t_until)
    iono = args.iono or ("iflc" if precise is not None else "klobuchar")
    try:  # settings the solver refuses (e.g. --smooth without iflc) are option errors
        solver = SppSolver(systems=args.systems, elevation_mask_deg=args.elevation_mask,
                           iono=iono, tropo=args.tropo, smoothing_epochs=args.smooth)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if args.raim:
        res = RaimFde(alpha0=args.alpha0, beta0=args.beta0,
                      max_exclusions=args.max_exclusions).solve(solver, obs, nav, precise)
    else:
        res = solver.solve(obs, nav, precise)
    frame = res.to_frame()
    n_invalid = obs.invalid_per_epoch
    if len(frame) == len(n_invalid):
        # an epoch left without a solution by implausible pseudoranges
        lost = (n_invalid > 0) & ~frame["status"].isin(st.USABLE).to_numpy()
        frame.loc[lost, "status"] = st.INVALID
    out = Path(args.out)
    from robustloc.io import write_table

    write_table(frame, out)  # atomic: nothing at -o after an error or an interrupt
    if ref is not None:
        ref_src = "--reference"
    else:
        ref = obs.approx_xyz_m
        ref_src = "RINEX header APPROX POSITION XYZ"
    summary = {"obs": args.obs, "out": str(out), "systems": res.systems, "iono": iono,
               "raim": bool(args.raim), "invalid_measurement": int(n_invalid.sum())}
    if np.linalg.norm(ref) > 6.0e6:
        summary["reference"] = ref_src
        summary["reference_xyz_m"] = [float(v) for v in ref]
        summary.update(error_summary(res, ref))
    else:
        summary.update(error_summary(res, np.array([6378137.0, 0.0, 0.0])))
        for k in [k for k in summary if k.endswith("_m") and k[:3] in ("bia", "rms", "p95",
                                                                         "max")]:
            del summary[k]
        summary["reference"] = "none (no --reference and no header position)"
    summary["status_counts"] = {str(k): int(v)
                                for k, v in frame["status"].value_counts().items()}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(f"{summary['solved']}/{summary['epochs']} epochs solved "
              f"({', '.join(f'{k} {v}' for k, v in summary['status_counts'].items())}); "
              f"systems {res.systems}, iono {iono}; written to {out}")
        print(f"invalid_measurement: {summary['invalid_measurement']}"
              + (" (pseudoranges outside 1.5e7 .. 5e7 m, never used)"
                 if summary["invalid_measurement"] else ""))
        if "rms_h_m" in summary:
            print(f"errors vs {ref_src}: ENU bias {summary['bias_e_m']:.2f} "
                  f"{summary['bias_n_m']:.2f} {summary['bias_u_m']:.2f} m; RMS horizontal "
                  f"{summary['rms_h_m']:.2f} m, 3-D {summary['rms_3d_m']:.2f} m; 95 % "
                  f"horizontal {summary['p95_h_m']:.2f} m; max 3-D {summary['max_3d_m']:.2f} m")
        if "median_hpl_m" in summary:
            print(f"RAIM: faults detected in {summary['faults_detected']} epochs, exclusions "
                  f"in {summary['epochs_with_exclusion']}; median HPL "
                  f"{summary['median_hpl_m']:.1f} m, VPL {summary['median_vpl_m']:.1f} m")
    sys.stdout.flush()
    return 0
