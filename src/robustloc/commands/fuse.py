"""``robustloc fuse``: UWB ranges + GPS speed/course (NMEA) fused by an EKF or UKF."""

from __future__ import annotations

import argparse
import json
import sys

from robustloc.options import (
    choice,
    float_in,
    nonnegative_float,
    sigma_value,
    tag_height_m,
)
from robustloc.robust.weights import weight_synonyms

NAME = "fuse"
HELP = "fuse UWB ranges and GPS speed/course (NMEA) with an EKF or UKF (seed 001)"
DESCRIPTION = """\
Fuses UWB ranges with GPS speed and course (RMC/VTG sentences of an NMEA log) for every tag
(seed 001; --nmea-tag: the GPS only for the tag that carries the receiver).  State
[x, y, vx, vy] (cv) or [x, y, vx, vy, ax, ay] (ca), east/north metres; any filter with any
motion model.

Coupling:
  loose  per UWB epoch a fix (--fix: linearized LS/WLS or Gauss-Newton) is the measurement
         [x, y] with the variances of its a-priori covariance, plus [v, course] from GPS
         (the paper's model).  The fix's x-y correlation is not used: tried, it took
         uwb-dwm1001 (fixes correlated near +-1) from 1.4 to 17 m RMS, plain EKF;
  tight  the raw ranges are measurements (default): epochs with fewer than three anchors
         still update, and a robust update (--robust) down-weights one bad range instead
         of a whole fix.  A component of weight w enters with the variance R/w (w = 0:
         left out), so an update never widens the prediction's covariance.

From the NMEA log only speed and course are fused (the paper's GPS measurements); GGA
positions are not used (a log without RMC/VTG sentences gives a warning: nothing of it is
fused).

Time alignment: NMEA times (seconds of the UTC day) plus --nmea-offset must match the
ranges' time column (automatic for POSIX-time ranges and dated RMC sentences).
Measurements stamped at most --merge-window seconds after an event's first time stamp (the
asynchronous ranges of one ranging cycle) form one filter event; windows do not chain, and
a second range of an anchor (or a second GPS speed) already in the event starts the next
one, so every epoch of the log gets its own row however fast it is sampled.
Course is ignored below 0.1 m/s.

Output (track contract): time, tag, x, y, vx, vy[, ax, ay], method, status, var_x, var_y,
cov_xy, var_vx, var_vy[, var_ax, var_ay], n_used, nis, source.  One row per event (every
input epoch is in one); status:
  ok                    updated, and the anchors heard within --geometry-window fix the
                        position (three or more, not all on one line or at one point)
  fault_excluded        as ok, but a component was rejected by the robust weights or gate
  fault_detected        updated, but the event failed its test: the normalized innovation
                        squared (NIS) beyond the B-method's chi-square bound (alpha0 0.001,
                        beta0 0.10, as in locate and track) with every component kept.
                        Usable, but the filter and this event's measurements disagree (a
                        fault no weight removed, a diverging filter).  Not tested while
                        the predicted speed is below 0.1 m/s (speed and course are not
                        linear there).  5 such events in a row give a warning (the
                        filter diverged; the UKF's track then restarts from the next
                        event's fix, as after a gap).  Loose coupling: also an ok event
                        whose fix failed its own test (that of `locate --method FIX
                        --sigma SIGMA_RANGE --robust-scale apriori`)
  unavailable           the update kept a strict minority of the event's three or more
                        components (the rest rejected): only the filter's own prediction
                        supports the row.  Counts toward the warning above
  predicted             nothing to update with, or every measurement of an event of one or
                        two components was rejected (n_used 0): the state is the motion
                        model's prediction, whatever the anchors.  Loose coupling has no
                        fix from one or two anchors: such an event without GPS is
                        predicted, where tight coupling updates with its ranges
                        (insufficient_anchors)
  invalid_measurement   every value of the event was outside its physical limits
                        (robustloc.io.limits: range -50..1e5 m, speed 0..515 m/s, course
                        0..360 deg); they were set aside, the row is the prediction.
                        A time outside |t| <= 1e12 s (ranges, or NMEA times plus
                        --nmea-offset) cannot be placed on the timeline: one such row
                        per (tag, time), without a state (as in locate)
  insufficient_anchors  updated and the test passed, but fewer than three anchors heard
                        within --geometry-window: ranges cannot fix the position (as in
                        locate).  A failed test stays fault_detected or unavailable
  ill_conditioned       as insufficient_anchors, but the anchors heard are all at one
                        point or on one line (as in locate); GPS speed/course do not fix a
                        position either
The filtered state is written on every row; its var_* columns say how far to trust it
under the noise it assumes (--sigma-range, --q): ranges noisier than --sigma-range make
them optimistic.  Where the anchors heard cannot fix the position (the last two
statuses, and a failed test with such anchors) var_x, var_y and cov_xy also cover the
position's mirror image across the anchors' line, (2 d)^2 across it at a distance d
(about a single anchor: its circle): the ranges cannot tell the two apart.  A tag whose
first ranges come from two anchors (or more on one line) starts at each of the two
positions they allow, and the run with the smaller sum of NIS is kept (GPS course tells
the sides apart; without GPS the choice is no better than a guess, which the variances
say).
On uwb-dwm1001 at the defaults the errors are about 3x their sd (the
mean NEES 18-20 where 2 is consistent); --sigma-range 0.5 brings it to 4, for 1.27
instead of 0.92 m RMS (docs/limits.md).
A track whose prediction is too wide to update (a gap of a day, a clock jump: position
variance var_x + var_y beyond 1e4 m^2 and beyond R_min / sqrt(eps), R_min the event's
smallest measurement variance -- about 50 s without measurements for cv at the default q
and 0.15 m ranges) starts again from the event's own fix (and GPS velocity, as a track
starts), counted as restarts; without a fix its rows are predicted (the last estimate,
with the prediction's variances) until an event gives one.  The UKF also starts again
from an event's fix when its prediction has var_x + var_y beyond 1e4 m^2 at an event with
ranges (its sigma points, 2 (cv) or 2.4 (ca) standard deviations out, would straddle the
anchors), and after a divergence (fault_detected, above); without a fix it updates as
before.
An anchor far outside the others (more than 20 times their median spread: a typo such as a
coordinate in mm) is not used, as in locate and track: a warning and the summary
(anchors_not_used) name it.  Range rows of one time, tag and anchor are averaged into one
range (counted: duplicates_merged).
Values outside the physical limits are counted in the summary (invalid_measurement N) and
never reach the filter; an update that would make the state non-finite or absurd (beyond
1e9 m) is rejected: the row is predicted, counted as rejected_updates.

Defaults (--filter ekf --robust hampel), measured: tight coupling, CV, default --q; 2-D RMS
(m) of the shared uwb-dwm1001 runs (LOS, NLOS; no GPS), the uwb-labyrinth run, and 8 seeds of
`simulate uwb-cart` each (group A: T = 1 s, B: T = 10 s; NLOS: --nlos-prob 0.1):
                 dwm LOS  dwm NLOS  labyrinth  A clean  A NLOS  B clean  B NLOS
  ekf none        3.60     4.87      0.240      0.063    0.315   0.178    0.619
  ekf hampel      0.919    0.851     0.239      0.063    0.102   0.178    0.619
  ekf igg3        0.902    0.848     0.260      0.063    0.076   0.178    0.619
  ukf none        1.35     3.57      0.274      0.127    0.802   57.1     68.9
  ukf hampel      0.922    0.853     0.272      0.127    0.403   27.5     45.2
hampel was never worse than none on any of the 35 runs (largest RMS ratio 1.000) and is
much better where ranges are bad; igg3 is better on the NLOS carts but 1.08x none on the
labyrinth (one range per update, where a redescending weight rejects good ranges).  The
UKF with the paper's sigma points (alpha = 1, kappa = 0) is worse than the EKF on the carts
and diverges at T = 10 s: its sigma points (+-2 sigma, 35 m per axis) span the ranges'
curvature 100 m from the anchors (its rows there are fault_detected, with a warning, and
the track restarts from a fix: 4344 and 398 m RMS before; the restarts also took the plain
UKF's largest error on dwm NLOS from 24 to 58 m, a fix holding an NLOS range).  A track
whose first event has a GPS speed and course starts with that velocity, and so does a
restart (after a gap or a divergence) from its own event's GPS speed and course; without
them it restarts at rest with the velocity variance of a start without GPS.  Rerun:
benchmarks/bench_fuse_defaults.py.
With --motion ca the default filter is the UKF (RMS, m, 4 seeds, hampel, q = 0.1;
bench_fuse_defaults.py --motion ca --q 0.1):
                 dwm LOS  dwm NLOS  labyrinth  A clean  A NLOS  B clean  B NLOS
  ekf ca          1.15     1.01      0.324      0.501    0.281    182      225
  ukf ca          1.10     0.917     0.312      0.131    0.292    9.31     32.3
Neither holds group B's 10 s steps at this q (the EKF is lost, the UKF diverges and
restarts); use CV there, or a --q that fits a steadily moving cart (the report's seed-001
section: 1e-6 / T^2).

`-o -` writes the track as CSV to standard output and the run summary to stderr.

Example:
  robustloc simulate uwb-cart --seed 1 --out cart
  robustloc fuse --ranges cart/measurements.csv --anchors cart/anchors.csv \\
      --nmea cart/gps.nmea --filter ukf --motion ca -o cart/track.csv
"""

ROBUST = ("none", "huber", "hampel", "igg", "igg3", "asymmetric-igg")
#: Bounds of --q, a variance ((m/s^2)^2 for cv, (m/s^3)^2 for ca): the sigma options'
#: upper bound 1e6 (an acceleration std of 1 km/s^2, 100 g: from about there every event of
#: a 1 Hz log restarts the track from its fix) and the square of their lower bound 1e-6
#: (the report's seed-001 q for group B, 1e-6 / T^2 = 1e-8, lies well inside).
Q_RANGE = (1e-12, 1e6)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.fusion.run import RANGE_K_MAX

    p.add_argument("--ranges", required=True, help="measurements file: time, tag, anchor, range")
    p.add_argument("--anchors", required=True, help="anchors file: anchor, x, y[, z]")
    p.add_argument("--nmea", default=None, help="NMEA log with RMC/VTG (optional)")
    p.add_argument("-o", "--out", required=True, help="track file (CSV or Parquet)")
    p.add_argument("--filter", choices=["ekf", "ukf"], default=None,
                   help="default ekf with --motion cv, ukf with --motion ca (seed 001's "
                        "pairs). CV: the UKF with the paper's alpha = 1 is no better on "
                        "real UWB and diverges when a prediction's spread nears the anchor "
                        "distances, e.g. 10 s steps at the default --q (see Defaults). CA: "
                        "the EKF linearizes the GPS course at a predicted velocity whose "
                        "spread can exceed a slow tag's speed and lost the 0.2 m/s cart "
                        "(0.50 against 0.13 m RMS); the UKF was as good (within 0.5 %%) or "
                        "better on every CA case measured but group B's 10 s steps, where "
                        "both are lost (benchmarks/bench_fuse_defaults.py --motion ca)")
    p.add_argument("--motion", choices=["cv", "ca"], default="cv", help="default cv")
    p.add_argument("--coupling", choices=["loose", "tight"], default="tight",
                   help="default tight")
    p.add_argument("--fix", choices=["ls", "wls", "nls"], default=None,
                   help="UWB fix for loose coupling (refused with tight coupling, which "
                        "fuses the ranges): linearized ls/wls or Gauss-Newton nls "
                        "(default nls)")
    p.add_argument("--robust", "--weight", dest="robust", choices=ROBUST, default="hampel",
                   type=choice(weight_synonyms(ROBUST)),
                   help="equivalent weight of the robust update (default hampel; none is "
                        "the paper's plain filter; see Defaults; --weight as in track; ls = "
                        "none, asym = asymmetric-igg)")
    p.add_argument("--gate", type=float_in(0.5, 1.0, open_high=True), default=None,
                   metavar="PROB",
                   help="chi-square gate probability on the innovation, e.g. 0.999 "
                        "(0.5 <= PROB < 1)")
    # bounded as the a-priori sigmas are (robustloc.options.SIGMA_RANGE: 1e-6 to 1e6 for a
    # std; a variance's lower bound is its square): 1e300 passed, and every event of a
    # 1 Hz log restarted the track from its fix, exit 0 (the filter/fuse review 4)
    p.add_argument("--q", type=float_in(Q_RANGE[0], Q_RANGE[1]), default=None,
                   help="process noise: acceleration (cv) or jerk (ca) variance "
                        "(default 0.5 cv, 0.1 ca; 1e-12 to 1e6)")
    # bounded as every a-priori sigma (robustloc.options.SIGMA_RANGE): 1e300 passed,
    # overflowed to an infinite variance with numpy warnings, and no range was used while
    # every row said ok (the filter/fuse review); a speed std of 1e300 was a traceback
    p.add_argument("--sigma-range", type=sigma_value, default=0.15,
                   help="range std, m (default 0.15; 1e-6 to 1e6)")
    p.add_argument("--range-k", type=float_in(0.0, RANGE_K_MAX), default=0.0,
                   help="range std growth with distance, sigma = s0 + k d (default 0; 0 to "
                        "1: at k = 1 a range's std is the range itself)")
    p.add_argument("--sigma-speed", type=sigma_value, default=None,
                   help="GPS speed std, m/s (default 0.05; 1e-6 to 1e6; with --nmea)")
    p.add_argument("--sigma-course", type=float_in(1e-6, 180.0), default=None,
                   help="GPS course std, deg (default 5; with --nmea)")
    p.add_argument("--nmea-offset", type=float_in(-1e12, 1e12), default=None,
                   help="seconds added to NMEA times (UTC seconds of day) to reach the "
                        "ranges' clock (default: POSIX time from the RMC date when the "
                        "ranges' times are POSIX seconds, else 0; with --nmea)")
    p.add_argument("--nmea-tag", action="append", default=None, metavar="TAG",
                   help="the tag that carries the NMEA log's GPS receiver: its speed and "
                        "course are fused into this tag's track only (repeatable; default: "
                        "every tag, with a warning when the ranges hold several)")
    p.add_argument("--merge-window", type=nonnegative_float, default=0.02,
                   help="measurements at most this long (s) after an event's first time "
                        "stamp join it, unless they repeat an anchor (0.02)")
    p.add_argument("--geometry-window", type=nonnegative_float, default=1.0, metavar="S",
                   help="anchors heard within this many seconds up to an event decide "
                        "whether its position can be ok (default 1)")
    p.add_argument("--tag-height", type=tag_height_m, default=None,
                   help="tag height, m: with anchor z, slant ranges are made horizontal")
    # kept to say so: fuse fuses no GGA position (only RMC/VTG speed and course), so an
    # origin changed nothing -- a byte-identical track (the fuse review)
    p.add_argument("--origin", default=None, metavar="LAT,LON,H",
                   help="refused: the ENU origin of GGA positions, which fuse does not use "
                        "(it fuses RMC/VTG speed and course only)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar and no text summary (as locate; warnings stay)")


def run(args: argparse.Namespace) -> int:
    from robustloc.errors import InputError
    from robustloc.filters import RobustUpdate, motion_model
    from robustloc.fusion.pipeline import FusionFilter
    from robustloc.fusion.run import FuseOptions, fuse
    from robustloc.io import read_anchors, read_measurements, write_table
    from robustloc.io.atomic import check_not_input, writes_to_stdout
    from robustloc.io.nmea import read_nmea
    from robustloc.robust.weights import get_weight

    check_not_input(args.out, [args.ranges, args.anchors, args.nmea])
    # options that would change nothing are refused, as --nmea-tag without --nmea: each
    # was accepted and the track came out byte-identical (the fuse review)
    if args.origin is not None:
        raise InputError("--origin sets the ENU origin of GGA positions, which fuse does "
                         "not use (it fuses RMC/VTG speed and course): it would change "
                         "nothing; leave it out")
    if args.fix is not None and args.coupling == "tight":
        raise InputError("--fix goes with --coupling loose (tight coupling, the default, "
                         "fuses the ranges, not fixes)")
    for given, name in ((args.sigma_speed, "--sigma-speed"),
                        (args.sigma_course, "--sigma-course"),
                        (args.nmea_offset, "--nmea-offset")):
        if given is not None and args.nmea is None:
            raise InputError(f"{name} goes with --nmea")
    anchors = read_anchors(args.anchors)
    if args.tag_height is not None and "z" not in anchors.columns:
        # the slant-range correction needs the anchors' heights: never ignore it silently
        raise InputError("--tag-height needs a z column in the anchors file",
                         anchors.attrs.get("path", args.anchors), 1)
    # fuse takes the range column: a file that also has rssi (the DWM1001 loader writes
    # both) is read for its ranges, where locate refuses the ambiguity
    meas = read_measurements(args.ranges, anchors, value="range")
    from robustloc._jitnotice import compile_notice

    compile_notice("positioning", "filter")
    nmea = read_nmea(args.nmea) if args.nmea else None
    tags = sorted(set(meas["tag"].astype(str)))
    if args.nmea_tag is not None:
        if nmea is None:
            raise InputError("--nmea-tag goes with --nmea")
        missing = sorted(set(args.nmea_tag) - set(tags))
        if missing:
            raise InputError(f"--nmea-tag {', '.join(missing)}: no such tag in the ranges "
                             f"(tags: {', '.join(tags[:10])}"
                             f"{', ...' if len(tags) > 10 else ''})", args.ranges)
    elif nmea is not None and len(tags) > 1:
        print(f"warning: {args.nmea}: one GPS log and {len(tags)} tags: its speed and "
              "course are fused into every tag's track; --nmea-tag TAG names the tag "
              "that carries the receiver", file=sys.stderr)
    q = args.q if args.q is not None else (0.5 if args.motion == "cv" else 0.1)
    if args.filter is None:  # seed 001's pairs, measured (the --filter help)
        args.filter = "ekf" if args.motion == "cv" else "ukf"
    # the equivalent-variance form (a component of weight w enters with R / w): an update
    # never widens the prediction's covariance, as seed 002's gain K D can (docs/limits.md)
    robust = RobustUpdate(
        weight=None if args.robust == "none" else get_weight(args.robust),
        gate_probability=args.gate, mode="variance",
    )
    filt = FusionFilter(args.filter, motion_model(args.motion, q=q), robust)
    opts = FuseOptions(
        coupling=args.coupling, fix_method=args.fix or "nls",
        sigma_range_m=args.sigma_range, range_k=args.range_k,
        sigma_speed_mps=0.05 if args.sigma_speed is None else args.sigma_speed,
        sigma_course_deg=5.0 if args.sigma_course is None else args.sigma_course,
        nmea_offset_s=args.nmea_offset,
        merge_window_s=args.merge_window, tag_height_m=args.tag_height,
        geometry_window_s=args.geometry_window,
        nmea_tags=None if args.nmea_tag is None else tuple(args.nmea_tag),
    )
    res = fuse(meas, anchors, nmea, filt, opts, progress=not args.quiet)
    # the summary never goes into a data stream: stderr when the track goes to stdout
    dest = sys.stderr if writes_to_stdout(args.out) else sys.stdout
    write_table(res.track, args.out)
    s = dict(res.summary, out=str(args.out))
    for text in s.get("warnings", []):  # a warning, even with --json
        print(f"warning: {args.nmea}: {text}", file=sys.stderr)
    from robustloc.pipelines.locate import anchor_warnings

    for text in anchor_warnings(s, args.anchors):  # (as locate and track word it)
        print(f"warning: {text}", file=sys.stderr)
    if s["diverged"]:  # a warning, even with --json
        print(f"warning: the innovation test failed with every measurement kept, or the "
              f"update kept a minority of them, on {filt.max_failed} or more consecutive "
              f"events, {s['diverged']} time(s): the filter disagrees with its measurements "
              "(those rows are fault_detected or unavailable); "
              + ("the UKF's sigma points may span the ranges' curvature (a wide prediction: "
                 "long steps or a large --q), its track restarts from the next fix: try "
                 "--filter ekf or a --q that fits the motion"
                 if args.filter == "ukf" else
                 "a --q that fits the motion, or --robust to down-weight bad ranges"),
              file=sys.stderr)
    if nmea is not None:
        s["nmea"] = nmea.summary.text()
    if args.json:
        print(json.dumps(s, indent=2, default=str), file=dest)
    elif not args.quiet:
        if nmea is not None:
            print(s["nmea"], file=dest)
        st = ", ".join(f"{k} {v}" for k, v in s["status"].items())
        print(f"fused {s['events']} events of {s['tags']} tag(s) with {args.filter.upper()}/"
              f"{args.motion.upper()} ({args.coupling}): {st} -> {s['out']}", file=dest)
        bad = ", ".join(f"{k} {v}" for k, v in s["invalid"].items() if v)
        print(f"invalid_measurement: {s['invalid_measurement']}"
              + (f" ({bad}; outside the physical limits, never used)" if bad else ""),
              file=dest)
        if s["duplicates_merged"]:  # (as locate and filter report them)
            print(f"  {s['duplicates_merged']} duplicate rows (same time, tag and anchor) "
                  "averaged", file=dest)
        if s["rejected_updates"]:
            print(f"rejected_updates: {s['rejected_updates']}", file=dest)
        if s["restarts"]:
            why = ", or a diverged UKF" if args.filter == "ukf" else ""
            print(f"restarts: {s['restarts']} (a prediction too wide to update after a gap"
                  f"{why}: the track started again from its event's fix)", file=dest)
    return 0
