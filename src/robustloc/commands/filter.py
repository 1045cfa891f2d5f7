"""``robustloc filter``: robust RSSI Kalman filter over every (tag, anchor) link."""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING

import numpy as np

from robustloc.engines import add_engine_arguments
from robustloc.options import choice, float_in, nonnegative_int, sigma_value
from robustloc.robust.weights import weight_synonyms

if TYPE_CHECKING:  # pandas is imported where it is used
    import pandas as pd

NAME = "filter"
HELP = "robust RSSI Kalman filter per (tag, anchor) link (seed 002); output feeds locate"
DESCRIPTION = """\
Filters the RSSI of every (tag, anchor) link with the robust M-estimation Kalman filter of
seed 002: state [P_r, d, v] (eq. 15), measurement RSSI = [1 0 0] X + r (eq. 16), gain
re-weighted K D by the asymmetric equivalent weight of eq. (14) with adaptive K0 = 2,
K1 = C = 3 standard errors of the innovations.  All links run in one vectorized pass.

The output is a measurements file with the same rows in the same order: 'rssi' holds the
filtered value (so 'robustloc locate' runs on it unchanged), plus 'rssi_raw', 'distance'
(m, the filtered RSSI through the anchor's path-loss model), 'distance_state' (the filter's
own d, weakly observable from RSSI alone), 'speed' (m/s), 'weight' (D), 'innovation' (dB)
and 'relocked'.  Rows of one link (tag, anchor) at the same time are one sample of the
filter, their RSSI averaged as 'locate' averages them (counted in the summary): each keeps
its own 'rssi_raw' and gets the merged sample's filtered values, whatever the row order.
An RSSI outside -150 .. +30 dBm (robustloc.io.limits) is not fed to the
filter, nor is a row whose time is beyond +-1e12 s: the row keeps the raw value in 'rssi'
and 'rssi_raw' (so 'locate' sets it aside as on the raw file), 'distance' is empty,
'distance_state' and 'speed' are the filter's prediction (empty for a time beyond the
limits: no prediction reaches it), 'weight' and 'innovation' are empty, and 'status' says
invalid_measurement (else ok); such rows are counted in the summary.  The summary counts
the weights, rejections, re-locks and restarts over the filter's samples (rows merged
into one sample once, invalid rows not): "filtered N samples (M rows)".
A link whose predicted RSSI variance exceeds 25 times the measurement's starts again at
its sample, as at its first one: the prior then weighs under 4 % of the update, and the
distance and speed states are drawn from the sample instead of carried across the gap
(counted as restarts).  A moving link's power prediction also widens near an anchor, so
it restarts only when its distance's sd exceeds the distance as well (after a gap, or
within decimetres of an anchor); with --static the distance never moves and the power's
variance grows with --q-rssi alone: a link restarts after a gap of about
(25 sigma^2) / q-rssi (2000 s at the defaults).
Use --static when the receivers do not move.  Path-loss parameters come
from the anchors file, the model 'locate' takes from it: A, n (log-distance) when the file
has them, else p0, gamma[, faf, d0] (attenuation factor), else p0[, d0] (friis); an anchor
with an empty one is refused as 'locate' refuses it (file, line and anchor named).  A file
with both A, n and p0, gamma that describe different path losses gets a note on stderr
naming the first such anchor: A, n are used, as in 'locate'.

What it can gain (measured, issue 11): on the wifi-room walk (seed 3), positions from
the filtered file (locate --method nls) against positions from the raw file:
  white RSSI noise (--ar-phi 0), no environment changes   1.33 -> 1.04 m RMS (0.78x)
  white noise, three 8 dB environment changes              1.56 -> 1.40 m (0.90x)
  correlated noise (AR(1) phi 0.88 per scan, the default)  1.36 -> 1.27 m (0.93x)
  correlated noise and the environment changes             1.56 -> 1.56 m (1.00x)
A per-link filter averages successive samples of one link.  With noise correlated from
scan to scan (phi = 0.88: N scans carry about N (1 - phi)/(1 + phi) = N/16 independent
samples) the samples it averages share their error, and a window long enough to hold
many independent ones is seconds long, during which a walker moves metres: it cannot
average the correlated part without lagging the motion, so the gain vanishes.  It helps
with white, fast noise.  `robustloc track` filters positions instead (tight, one filter
per tag); it meets the same limit on correlated noise (report section s60_tracks).
On tags that stand still while bodies block links in bursts (simulate ble-corridor
--disturbance, 5 seeds, default locate after each; benchmarks/bench_blockage.py), mean
error: raw 1.57 m, filter --static 0.98 m, but the default (moving) filter 2.07 m: a
burst's dip drives its speed state.  Use --static for standing tags.

Example:
  robustloc simulate wifi-room --seed 1 --out sim
  robustloc filter sim/measurements.csv --anchors sim/anchors.csv -o sim/filtered.csv
"""

WEIGHTS = ("asymmetric-igg", "igg3", "igg", "huber", "hampel", "none")


#: ``--sigma-accel``'s default, by which a value given is told from none.
SIGMA_ACCEL_DEFAULT = 0.5
#: ``--max-rejected``'s default (the option's default is None: a value given is told from
#: none, :func:`_refuse_idle_robust_options`).
MAX_REJECTED_DEFAULT = 8


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("measurements", help="measurements file (time, tag, anchor, rssi)")
    p.add_argument("--anchors", required=True, help="anchors file with path-loss columns")
    p.add_argument("-o", "--out", required=True, help="filtered measurements (CSV/Parquet)")
    p.add_argument("--robust", "--weight", dest="robust", choices=WEIGHTS,
                   type=choice(weight_synonyms(WEIGHTS)), default="asymmetric-igg",
                   help="equivalent weight of the gain (default asymmetric-igg, eq. 14; "
                        "'none' = plain Kalman filter; --weight as in track; ls = none, "
                        "asym = asymmetric-igg)")
    p.add_argument("--sigma-rssi", "--sigma", dest="sigma_rssi", type=sigma_value,
                   default=2.0,
                   help="measurement noise std, dB (default 2; 1e-6 to 1e6; --sigma as in "
                        "locate and track)")
    p.add_argument("--sigma-accel", type=float_in(0.0, 1e3), default=SIGMA_ACCEL_DEFAULT,
                   help="radial acceleration std, m/s^2 (default 0.5; 0 to 1000; refused "
                        "with --static)")
    p.add_argument("--q-rssi", type=float_in(0.0, 1e6), default=0.05,
                   help="power random walk, dB^2/s (default 0.05; 0 to 1e6)")
    p.add_argument("--exponent", type=float_in(0.1, 10.0), default=None,
                   help="path-loss exponent of the transition (default: each anchor's "
                        "gamma; 2 = the paper's 20 lg; refused with --static)")
    p.add_argument("--static", action="store_true",
                   help="receivers do not move: speed fixed at 0, no acceleration (the "
                        "filter becomes a robust running mean with a slow power walk)")
    p.add_argument("--max-rejected", type=nonnegative_int, default=None,
                   help="rejections in a row after which a link re-locks, taking that "
                        "sample with weight 1 (0: never; default 8); a young link re-locks "
                        "sooner, at the rejection that makes its rejections in a row "
                        "outnumber the samples it has taken (weight > 0) since it started "
                        "or restarted; refused with --robust none or huber, which "
                        "never reject)")
    p.add_argument("--no-adaptive", action="store_true",
                   help="standardize by the predicted innovation std only (refused with "
                        "--robust none)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar and no text summary (as locate; warnings stay)")
    add_engine_arguments(p)


def filter_frame(meas, anchors, args: argparse.Namespace, progress: bool = False):
    """The filter configured by ``args`` over one measurements frame.

    The single core of ``filter``: the whole file here, each tag partition under
    ``--engine dask``.  RSSI outside the physical limits (robustloc.io.limits) never
    reaches the filter: its row keeps the raw value in ``rssi`` and ``rssi_raw``, no
    ``distance``, and status ``invalid_measurement``; a row whose time is outside the
    limits likewise.  So ``locate`` on the output sets such rows aside as it does on the
    raw file.  Anchors with path-loss columns are checked as ``locate`` checks them
    (:func:`robustloc.models.pathloss.model_from_anchors`): an empty parameter of an
    anchor raises :class:`~robustloc.errors.InputError` naming the file, line and anchor;
    the model is ``locate``'s too (:func:`robustloc.filters.rssi.link_params_from_anchors`
    chooses it by the same code: ``A, n`` over ``p0, gamma``).
    Returns ``(frame, summary)``.
    """
    import numpy as np

    from robustloc import status as st
    from robustloc.filters.rssi import RobustRssiFilter, filter_measurements
    from robustloc.io.limits import LIMITS
    from robustloc.models.pathloss import model_from_anchors
    from robustloc.robust.weights import get_weight

    cols = set(anchors.columns)
    if {"A", "n"} <= cols or "p0" in cols:
        # an anchor whose parameters are empty is refused as `locate` refuses it (file,
        # line, anchor): the filter took p0 = -40 dBm, gamma = 2 for it without a word,
        # and its distance columns looked real (the filter/fuse review)
        model_from_anchors(anchors)
    bad = np.zeros(len(meas), dtype=bool)
    raw = None
    if "rssi" in meas.columns:  # implausible values never reach the filter
        raw = meas["rssi"].to_numpy(dtype=float)
        bad = ~np.isnan(raw) & ~LIMITS["rssi"].check(raw)
        if bad.any():
            meas = meas.copy()
            meas["rssi"] = np.where(bad, np.nan, raw)
    robust = args.robust != "none"
    filt = RobustRssiFilter(
        get_weight(args.robust) if robust else None,
        robust=robust,
        sigma_rssi_db=args.sigma_rssi,
        sigma_accel_mps2=0.0 if args.static else args.sigma_accel,
        init_speed_std_mps=0.0 if args.static else 1.0,
        q_rssi_db2_per_s=args.q_rssi,
        exponent=args.exponent,
        max_rejected=(MAX_REJECTED_DEFAULT if args.max_rejected is None
                      else args.max_rejected),
        adaptive=not args.no_adaptive,
    )
    # a time outside the limits (|t| >= 1e12 s) never reaches the filter either: its
    # prediction over such a gap overflows (and would pass every later sample's state
    # through it); the row keeps its values and gets invalid_measurement
    late = ~LIMITS["time"].check(meas["time"].to_numpy(dtype=float))
    res = filter_measurements(meas[~late] if late.any() else meas, anchors, filt,
                              progress=progress)
    frame = res.frame
    if late.any():
        # the late rows back in their places with every input column (extra columns
        # too: the output has the same rows), the filter's columns empty
        import pandas as pd

        pos = np.r_[np.flatnonzero(~late), np.flatnonzero(late)]
        frame = pd.concat([frame, meas[late]]).iloc[np.argsort(pos, kind="stable")]
        frame["relocked"] = frame["relocked"].fillna(False).astype(bool)
    bad = bad | late
    if bad.any():
        # an invalid row keeps its raw value in 'rssi' too, so that `locate` on the
        # filtered file sets it aside exactly as on the raw file (it never counts as
        # heard); 'distance' (the filtered RSSI through the model) has no value, while
        # 'distance_state' and 'speed' keep the filter's prediction of the link (a row of
        # a time beyond the limits has none: they stay empty, as --help says)
        frame = frame.copy()
        values = raw if raw is not None else meas["rssi"].to_numpy(dtype=float)
        for c in ("rssi", "rssi_raw"):
            frame[c] = np.where(bad, values, frame[c].to_numpy(dtype=float))
        frame["distance"] = np.where(bad, np.nan, frame["distance"].to_numpy(dtype=float))
    frame["status"] = np.where(bad, st.INVALID, st.OK)
    return frame, dict(res.summary, samples=int(len(meas)), invalid_measurement=int(bad.sum()))


#: Largest difference, at 1 m (dB) and in the exponent, of two path-loss models of one
#: anchor that still agree: the rounding of values written with three decimals.
_AGREE_DB, _AGREE_N = 0.01, 1e-3


def pathloss_note(anchors: pd.DataFrame) -> str | None:
    """The note for an anchors file whose ``A, n`` and ``p0, gamma[, faf, d0]`` (or friis
    ``p0[, d0]``) columns describe different path losses, or ``None``.

    Both are read by :func:`robustloc.models.pathloss.model_from_anchors` (``locate``'s
    reader) and compared as ``A - 10 n lg d``; the filter uses ``A, n``, as ``locate``
    does.  It took ``p0, gamma`` without a word (the filter/fuse review 4), so a file
    whose columns disagree (a calibration that rewrote one set and kept the other) gave
    the filter one path loss and ``locate`` another.  Anchors with an empty cell in either
    set are not compared (the filter refuses an empty ``A`` or ``n`` as ``locate`` does).
    """
    from robustloc.models.pathloss import MODEL_COLUMNS, model_from_anchors

    cols = set(anchors.columns)
    if not ({"A", "n"} <= cols and "p0" in cols):
        return None
    other = "attenuation-factor" if "gamma" in cols else "friis"
    both = anchors[anchors[[c for c in (*MODEL_COLUMNS["log-distance"],
                                        *MODEL_COLUMNS[other]) if c in cols]]
                   .notna().all(axis=1)]
    if both.empty:
        return None
    try:
        A1, n1 = model_from_anchors(both, "log-distance").log_distance_params()
        A2, n2 = model_from_anchors(both, other).log_distance_params()
    except ValueError:  # a parameter no model takes (n <= 0): refused elsewhere
        return None
    off = (np.abs(A1 - A2) > _AGREE_DB) | (np.abs(n1 - n2) > _AGREE_N)
    if not off.any():
        return None
    i = int(np.argmax(off))
    path = anchors.attrs.get("path", "anchors")
    line = f":{both.index[i]}" if both.index.name == "line" else ""
    names = ", ".join(c for c in MODEL_COLUMNS[other] if c in cols)
    return (f"{path}{line}: anchor {both['anchor'].iloc[i]!r} has A {A1[i]:g} dBm, n "
            f"{n1[i]:g} and {names} that give A {A2[i]:g} dBm, n {n2[i]:g} "
            f"({int(off.sum())} of {len(both)} anchors disagree): the filter uses A, n "
            "(log-distance), as locate does")


def filter_partition(meas, anchors, args: argparse.Namespace):
    """``--engine dask``: one tag partition -> (filtered frame, additive counts, plus
    ``shared`` (the filter's name) and ``_moments`` for :func:`combine_partitions`)."""
    from robustloc._exact import Moments

    frame, summary = filter_frame(meas, anchors, args)
    counts = {k: v for k, v in summary.items() if isinstance(v, int)}
    counts["shared"] = {"filter": summary["filter"]}
    import pandas as pd

    from robustloc import status as st
    from robustloc.filters.rssi import one_row_per_sample

    # as filter_measurements' summary: over the rows fed to the filter (an invalid row
    # keeps its raw value in both columns: not a difference of the filter's), the weights
    # over one row of each sample of the filter
    fed = frame["status"].to_numpy() == st.OK
    diff = (frame["rssi_raw"] - frame["rssi"]).to_numpy(dtype=float)[fed]
    diff = diff[np.isfinite(diff)]
    link = pd.MultiIndex.from_arrays([frame["tag"].astype(str),
                                      frame["anchor"].astype(str)]).factorize()[0]
    one = one_row_per_sample(link, frame["time"].to_numpy(dtype=float),
                             fed & np.isfinite(frame["rssi_raw"].to_numpy(dtype=float)))
    innovated = one & np.isfinite(frame["innovation"].to_numpy(dtype=float))
    w = frame["weight"].to_numpy(dtype=float)[innovated]
    counts["_moments"] = {"n_weighted": int(innovated.sum()),
                          "downweighted": int(np.sum(w < 1)), "diff": Moments.of(diff)}
    return frame, counts


def combine_partitions(counts_list: list[dict]) -> dict:
    """The filter summary's ``share_downweighted`` and ``raw_minus_filtered_std_db`` over
    every partition, as the single process computes them on the whole file: the spread
    from the partitions' exact moments added up (:class:`robustloc._exact.Moments`), the
    very number of the single process (which pooled means and squared deviations, Chan
    et al. 1983, differed from it in the last digits: 3.4992829190566606 against
    ...597, the Dask review)."""
    from robustloc._exact import Moments

    n_w = down = 0
    diff = Moments()
    for c in counts_list:
        mo = c.pop("_moments", None)
        if mo is None:
            continue
        n_w += mo["n_weighted"]
        down += mo["downweighted"]
        diff = diff + mo["diff"]
    return {"share_downweighted": down / n_w if n_w else 0.0,
            # None (JSON null) without any filtered value, as filter_measurements says
            "raw_minus_filtered_std_db": diff.std()}


def _refuse_moving_options(args: argparse.Namespace) -> None:
    """Options of a moving receiver, refused with ``--static`` (they were taken and
    changed no output byte: the commands review).  Under ``--static`` the speed stays 0,
    so no acceleration enters the state and the transition's path-loss exponent, which
    turns a change of distance into one of power, has no change to turn."""
    from robustloc.errors import InputError

    if not args.static:
        return
    given = [flag for flag, on in (("--sigma-accel", args.sigma_accel != SIGMA_ACCEL_DEFAULT),
                                   ("--exponent", args.exponent is not None)) if on]
    if given:
        raise InputError(f"{', '.join(given)} does not apply to --static (the receivers do "
                         "not move: no acceleration, and no change of distance for the "
                         "transition's exponent to turn into power)")


def _refuse_idle_robust_options(args: argparse.Namespace) -> None:
    """Options of the robust weight, refused where the weight makes them idle (they were
    taken and changed no output byte: the filter review).  A link re-locks only after a
    rejection (weight 0): ``--robust none`` gives every sample weight 1, and Huber's weight
    ``c / |u|`` is never 0 for a finite innovation, so ``--max-rejected`` has nothing to
    count; the adaptive scale only standardizes the innovation for the weight, which
    ``--robust none`` does not take."""
    from robustloc.errors import InputError

    why = {"none": "the plain filter gives every sample weight 1",
           "huber": "Huber's weight c/|u| is never 0"}.get(args.robust)
    if why is None:
        return
    given = [flag for flag, on in (
        ("--max-rejected", args.max_rejected is not None),
        ("--no-adaptive", args.no_adaptive and args.robust == "none")) if on]
    if given:
        what = ("no sample is rejected, so no link re-locks, and the innovation's scale "
                "weighs nothing" if len(given) > 1 else
                "no sample is rejected, so no link re-locks" if given[0] == "--max-rejected"
                else "the innovation's scale weighs nothing")
        raise InputError(f"{', '.join(given)} does not apply to --robust {args.robust} "
                         f"({why}: {what})")


def run(args: argparse.Namespace) -> int:
    from robustloc.io.atomic import check_not_input

    _refuse_moving_options(args)  # before any work
    _refuse_idle_robust_options(args)

    if args.engine != "dask":  # (the Dask engine checks its output tree itself)
        check_not_input(args.out, [args.measurements, args.anchors])
    from robustloc.io import read_anchors, read_measurements, write_table

    anchors = read_anchors(args.anchors)
    note = pathloss_note(anchors)
    if note:  # (either engine: the model choice is the kernel's, this says it)
        print(f"note: {note}", file=sys.stderr)
    if args.engine == "dask":
        from robustloc.engines.dask import run_filter
        return run_filter(args, filter_partition, combine_partitions)
    cols = set(anchors.columns)
    if not ({"A", "n"} <= cols or "p0" in cols):
        # the filtered RSSI barely depends on it, but the distance columns would look real
        print(f"warning: {args.anchors}: anchors have no path-loss parameters (A, n, or p0 "
              "with gamma or alone for friis): the distance columns use p0 = -40 dBm, "
              "gamma = 2 and are only indicative; run `robustloc calibrate` for real "
              "distances", file=sys.stderr)
    meas = read_measurements(args.measurements, anchors)
    frame, summary = filter_frame(meas, anchors, args, progress=not args.quiet)
    write_table(frame, args.out)
    s = dict(summary, out=str(args.out))
    from robustloc.io.atomic import writes_to_stdout

    # the summary never goes into a data stream: stderr when the output goes to stdout
    dest = sys.stderr if writes_to_stdout(args.out) else sys.stdout
    if args.json:
        print(json.dumps(s, indent=2), file=dest)
    elif not args.quiet:
        rows = (f" ({s['samples']} rows)" if s["samples"] != s["filtered_samples"]
                else "")
        print(f"filtered {s['filtered_samples']} samples{rows} on {s['links']} links "
              f"({s['filter']}): "
              f"{s['downweighted']} down-weighted, {s['rejected']} rejected, "
              f"{s['relocked']} re-locks, {s['restarted']} restarts -> {s['out']}",
              file=dest)
        note = (" (RSSI outside -150 .. +30 dBm or time beyond +-1e12 s: not filtered)"
                if s["invalid_measurement"] else "")
        print(f"invalid_measurement: {s['invalid_measurement']}{note}", file=dest)
        if s.get("duplicates_merged"):  # (as locate reports them)
            print(f"  {s['duplicates_merged']} duplicate rows (same time, tag and anchor) "
                  "averaged", file=dest)
    return 0
