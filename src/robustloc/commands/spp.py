"""``robustloc spp``: GNSS single-point positioning from RINEX, with RAIM FDE.

The command line over :mod:`robustloc.pipelines.spp`.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings

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
satellite.  The levels bound one fault at a time (the slope of the worst single
satellite): two faulty satellites at once can mislead the test into excluding a healthy
one and leave a fix beyond its hpl (docs/limits.md).  --inject adds a bias to real
pseudoranges to exercise the detector.

Output: one row per epoch (time as GPS seconds, week, time of week and UTC ISO; ECEF, lat,
lon, h; receiver clock(s); n_sats; DOPs; sigma0; status; excluded satellites; test
statistics; hpl/vpl).  Status 'unavailable' (RAIM detected a fault it could not attribute,
or no redundancy to test) keeps the position but marks it unverified.  A pseudorange
outside 1.5e7 .. 5e7 m (robustloc.io.limits) is an invalid measurement: it is never used,
counted in the summary (invalid_measurement N), and an epoch left without a solution
because of such values has status 'invalid_measurement': when they were of satellites it
would have used (a constellation of --systems, above the elevation mask) and with them it
would have had a usable set (a satellite per unknown, GDOP <= 30); otherwise the epoch
keeps its own status (insufficient_anchors, ill_conditioned, ...).  A satellite with
two records in one epoch is an error (FILE:LINE, exit 2): a receiver writes one record per
satellite and epoch, and which one is right cannot be told (locate averages the duplicate
rows of a measurements table: repeated measurements of one range).  A summary of errors
against --reference (default: the RINEX header's APPROX POSITION XYZ) is printed (--json
for JSON).

Example:
  robustloc spp 07590920.05o 07590920.05n --systems G --raim -o sol.csv
  robustloc spp slac1180.21o --sp3 COD.SP3 --clk COD.CLK --systems GRE --smooth 60 -o s.csv
  robustloc spp 07590920.05o 07590920.05n --raim --inject G11:20 --inject-from 796436400 -o f.csv
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.options import float_in, nonnegative_int

    p.add_argument("obs", help="RINEX observation file (2.xx, 3.xx or 4.xx)")
    p.add_argument("nav", nargs="*", help="RINEX navigation file(s) (2.xx or 3.xx)")
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
    p.add_argument("--alpha0", type=float_in(1e-15, 0.5), default=None,
                   help="w-test significance (0.001; with --raim)")
    p.add_argument("--beta0", type=float_in(1e-15, 0.5), default=None,
                   help="B-method missed detection (0.10; with --raim)")
    p.add_argument("--max-exclusions", type=nonnegative_int, default=None,
                   help="at most this many satellites excluded per epoch (with --raim)")
    p.add_argument("--reference", default=None, metavar="X,Y,Z",
                   help="reference ECEF position (m) for the error summary (default: RINEX "
                        "header); write --reference=X,Y,Z when X is negative")
    p.add_argument("--inject", default=None, metavar="PRN:BIAS_M[,PRN:BIAS_M]",
                   help="add biases (m) to these satellites' pseudoranges, e.g. G11:20,G24:-15")
    p.add_argument("--inject-from", default=None, metavar="T",
                   help="start of the injected fault (with --inject): GPS seconds or ISO "
                        "time (GPS scale; with Z or +HH:MM a civil time, converted with the "
                        "leap seconds)")
    p.add_argument("--inject-until", default=None, metavar="T",
                   help="end of the injected fault (with --inject; same formats)")
    p.add_argument("-o", "--out", required=True, help="solution file (.csv or .parquet)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_engine_arguments(p, what="the observation files (OBS: a directory or a glob)")


def run(args: argparse.Namespace) -> int:
    from robustloc.errors import InputError

    # options that would change nothing are refused, as --clk without --sp3: each was
    # accepted and the solution came out the same (the GNSS review)
    for name in ("alpha0", "beta0", "max_exclusions"):
        if getattr(args, name) is not None and not args.raim:
            raise InputError(f"--{name.replace('_', '-')} goes with --raim")
    if args.engine == "dask":
        from robustloc.engines.dask import run_spp
        return run_spp(args, run)
    from robustloc.gnss.rinex import NavRecordWarning
    from robustloc.io import write_table
    from robustloc.io.atomic import check_not_input
    from robustloc.pipelines.spp import SppSettings
    from robustloc.pipelines.spp import run_spp as solve

    # before any work: -o naming the observation, a navigation, SP3 or CLK file replaced it
    check_not_input(args.out, [args.obs, *args.nav, args.sp3, args.clk])
    with warnings.catch_warnings():  # printed once below, as `warning: FILE:LINE: ...`
        warnings.simplefilter("ignore", NavRecordWarning)
        frame, summary = solve(args.obs, args.nav, SppSettings.from_namespace(args),
                               sp3=args.sp3, clk=args.clk)
    for text in summary.get("nav_records_set_aside", []):  # a warning, even with --json
        print(f"warning: {text}", file=sys.stderr)
    for text in summary.get("notes", []):
        print(f"note: {text}", file=sys.stderr)
    from robustloc.io.atomic import writes_to_stdout

    out = args.out
    write_table(frame, out)  # atomic: nothing at -o after an error or an interrupt
    summary = {"obs": summary["obs"], "out": str(out),
               **{k: v for k, v in summary.items() if k != "obs"}}
    # the summary never goes into a data stream: stderr when the table goes to stdout
    # (it was appended to the CSV of `-o -`)
    dest = sys.stderr if writes_to_stdout(out) else sys.stdout
    if args.json:
        print(json.dumps(summary, indent=2), file=dest)
    else:
        print(f"{summary['solved']}/{summary['epochs']} epochs solved "
              f"({', '.join(f'{k} {v}' for k, v in summary['status_counts'].items())}); "
              f"systems {summary['systems']}, iono {summary['iono']}; written to {out}", file=dest)
        print(f"invalid_measurement: {summary['invalid_measurement']}"
              + (" (pseudoranges outside 1.5e7 .. 5e7 m, never used)"
                 if summary["invalid_measurement"] else ""), file=dest)
        if "rms_h_m" in summary:
            print(f"errors vs {summary['reference']}: ENU bias {summary['bias_e_m']:.2f} "
                  f"{summary['bias_n_m']:.2f} {summary['bias_u_m']:.2f} m; RMS horizontal "
                  f"{summary['rms_h_m']:.2f} m, 3-D {summary['rms_3d_m']:.2f} m; 95 % "
                  f"horizontal {summary['p95_h_m']:.2f} m; max 3-D {summary['max_3d_m']:.2f} m",
                  file=dest)
        if "faults_detected" in summary:  # (also when RAIM left no usable fix)
            print(f"RAIM: faults detected in {summary['faults_detected']} epochs, exclusions "
                  f"in {summary['epochs_with_exclusion']}"
                  + (f"; median HPL {summary['median_hpl_m']:.1f} m, VPL "
                     f"{summary['median_vpl_m']:.1f} m" if "median_hpl_m" in summary
                     else "; no usable fix to bound"), file=dest)
    sys.stdout.flush()
    return 0
