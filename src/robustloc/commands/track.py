"""``robustloc track``: a robust tight filter per tag -> one track row per input epoch.

The command line over :mod:`robustloc.pipelines.track` (options parsed into its
:class:`~robustloc.pipelines.track.TrackSettings`).
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

import pandas as pd

from robustloc.engines import add_engine_arguments
from robustloc.errors import InputError

if TYPE_CHECKING:
    from robustloc.pipelines.locate import HplTally

NAME = "track"
HELP = "tracks from RSSI or ranges: a robust tight EKF/UKF per tag, with RTS smoothing"
DESCRIPTION = """\
Tracks every tag of a measurements file with its own robust filter (state [x, y, vx, vy]
for cv, + [ax, ay] for ca, [x, y] for static), updated directly with each epoch's anchor
observations: ranges (corrected with the anchors' bias/scale columns as `locate` does) or
RSSI (converted by the anchors' path-loss model to ranges with sigma_d = d ln10 sigma_dB /
(10 n), or in dB with --domain rssi). An epoch with 1 or 2 anchors still updates.

  start        a robust snapshot fix (huber) of the tag's first usable epoch
  update       robust M-estimation update with --weight: a link of weight w enters with
               the variance R/w (w = 0: left out), so an update never widens the
               prediction's covariance (seed 002's gain K D, eq. 12, can)
  env. change  robust weights down-weight a link whose level steps; --cusum-h H adds a
               two-sided CUSUM on each link's innovations: a link whose level steps is
               held out (never inflating the covariance) while its new offset is
               estimated, then re-admitted with it
  tests        B-method global test on the innovations (--alpha0, --beta0); a filter that
               fails repeatedly or disagrees with the robust fix re-starts (reinit column)
  noise        the measurement noise scale adapts within [--noise-scale-min, -max]
  offset       --range-offset: each tag's common range offset (a UWB antenna delay) as
               one more state, estimated with the track; --link-offsets: one offset per
               link (dB of RSSI, m of ranges); by default (auto) the log's first epochs
               choose whether the links' offsets are estimated
  coasting     nothing heard: status `predicted`
  hpl          max_i |gain_i| MDB_i + k sigma_major, k from --integrity-risk (2-D); with
               nearly collinear anchors, plus the distance to the mirror solution across
               their line when that fits the epoch as well (rows of one or two ranges:
               the anchors of the tag's recent updates); where those recent updates
               (the last second, or the last M of M anchors) kept fewer than two anchors
               10 degrees apart, also the motion since the last row that had them (or
               the kept range's circle, where smaller)
  --smooth     fixed-interval Rauch-Tung-Striebel smoother over the forward pass (keeps its
               robust weights); --fixed-lag N uses only the next N epochs; a smoothed
               row's hpl is the forward row's plus the distance smoothing moved it

Output, one row per input epoch (never a dropped epoch): time, tag, x, y, vx, vy[, ax, ay],
method, status, var_x, var_y, cov_xy, var_vx, var_vy, hpl, n_used, nis, noise_scale,
reinit, excluded (+ range_offset, var_range_offset with --range-offset). Statuses: ok,
fault_excluded (a component rejected, a link held out, or a down-weighted one that the
w-test names: 'excluded' lists it though the update still used it at its robust
weight, as locate's fault_excluded), fault_detected (the
innovations' global test failed and one exclusion does not explain it, or half the
components were rejected: hpl widened by sqrt(NIS / dof); on clean data at the test's
false-alarm rate, about 2 % on smooth motion, 3-8 % where the tag turns more sharply
than --q allows: the track review, 2026-12-06), predicted; a start row (a tag's first
fix, or a re-start) says its snapshot fix's status where that says more than ok
(low_redundancy, unverified, fault_excluded, extrapolated), and before a tag's first fix
each row carries the fix's own status (insufficient_anchors, ill_conditioned,
invalid_measurement); an epoch wholly outside the physical limits is invalid_measurement.
`robustloc evaluate` reads the file.

  robustloc simulate wifi-room --seed 1 --out room
  robustloc track room/measurements.csv --anchors room/anchors.csv -o room/track.csv
  robustloc track room/measurements.csv --anchors room/anchors.csv --smooth -o smooth.csv
  robustloc evaluate room/track.csv --truth room/truth.csv

Beyond one machine (docs/dask.md): partition by tag, then --engine dask tracks each tag
group on a worker with this same code; the dataset of part files holds the same rows:
  robustloc partition big.parquet -o by-tag --by tag --buckets 16
  robustloc track by-tag --anchors anchors.csv -o tracks --engine dask [--scheduler ADDR]"""


def noise_scale_value(text: str) -> float:
    """``--noise-scale-min`` / ``--noise-scale-max``: a factor in [1e-6, 1e6], the range of
    ``--sigma``.  (Only "positive and finite" before: the tracker squares it, so 1e200
    ended in an OverflowError traceback and 1e-170 in a ZeroDivisionError.)"""
    from robustloc.options import float_in

    return float_in(1e-6, 1e6)(text)


def check_options(args: argparse.Namespace) -> None:
    """The refusals that involve two options, named as on the command line.

    Raises
    ------
    InputError
        ``--noise-scale-min: 5 is above --noise-scale-max 1`` (the tracker said
        ``need 0 < noise_scale_min <= noise_scale_max``, its Python names).
    """
    lo, hi = args.noise_scale_min, args.noise_scale_max
    if lo > hi:
        raise InputError(f"{lo:g} is above --noise-scale-max {hi:g} (the noise scale adapts "
                         "within [--noise-scale-min, --noise-scale-max])",
                         "--noise-scale-min")


def _check_anchors_on_client(args: argparse.Namespace) -> None:
    """``--engine dask``: the anchors file read and checked here first, as the local
    command does before any work (``--tag-height`` without a z column: the workers said
    ``tag_height needs ...``, the tracker's Python name)."""
    from robustloc.io import read_anchors

    _tag_height_needs_z(args.tag_height, read_anchors(args.anchors))


def _resolve_auto_on_client(args: argparse.Namespace, infos: list) -> dict:
    """``--engine dask`` with ``--link-offsets auto`` (the default): the choice made once,
    here, and handed to every worker as ``on`` or ``off`` (each partition choosing for
    itself would give one log two models).

    Its sample is the single process's: the dataset's first
    :data:`~robustloc.tracking.select.AUTO_SAMPLE_EPOCHS` epochs by time, then tag,
    over every partition file.  The files are read in the order of their first times
    (empty ones skipped, as the planner skips them), each as the single process reads
    and sorts a file, and the sample kept cut to its first epochs; once it holds them,
    its last epoch's time bounds the next files: a time-sorted file is read only up to
    that time or up to its own first epochs
    (:func:`~robustloc.engines.dataset.read_first_epochs`), a file starting after it not
    at all, a file not in time order whole.  (The files in path order until the sample
    was full, then sorted: on a dataset partitioned by tag, each file spanning the whole
    log, that was the first files' tags alone -- a walk of 30 tags, 10 of them with link
    offsets, chose ``off`` where the single process chose ``on``, and 59 970 of its
    60 000 rows differed; the dask review.)

    Parameters
    ----------
    args : argparse.Namespace
        The command's options; ``link_offsets`` is set to ``on`` or ``off``.
    infos : list of PartitionInfo
        Every partition, checked by the planner (in path order, empty files included).

    Returns
    -------
    dict
        The summary's ``link_offsets_auto`` (``sample``: the files holding the sample's
        epochs, in path order), or nothing (not ``auto``).
    """
    if args.link_offsets != "auto":
        return {}
    import numpy as np

    from robustloc.engines.dataset import read_first_epochs
    from robustloc.io import iter_epochs, read_anchors
    from robustloc.io.tables import Epochs
    from robustloc.pipelines.track import TrackSettings, resolve_link_offsets
    from robustloc.tracking import select

    want = select.AUTO_SAMPLE_EPOCHS
    anchors = read_anchors(args.anchors)
    settings = TrackSettings.from_namespace(args)
    sample: Epochs | None = None  # the first ``want`` epochs of the files read so far
    source = np.zeros(0, dtype=np.int64)  # the file (index in ``infos``) of each epoch
    until = None  # the sample's last time, once it holds ``want`` epochs
    # (by first time: a dataset split by time fills the sample from its first files and
    # reads none of the later ones)
    order = sorted((k for k, i in enumerate(infos) if i.n_rows),
                   key=lambda k: (infos[k].time_min, infos[k].part.path))
    for k in order:
        if until is not None and infos[k].time_min > until:
            break  # this file's epochs, and every later file's, come after the sample's
        blocks = [b for b in iter_epochs(read_first_epochs(infos[k].part, want, until=until),
                                         anchors, chunk_rows=settings.chunk_rows,
                                         order="sort") if b.n_epochs]
        if not blocks:
            continue
        n_new = sum(b.n_epochs for b in blocks)
        if sample is not None:
            blocks.insert(0, sample)
        joined = Epochs.concat(blocks)
        source = np.concatenate([source, np.full(n_new, k, dtype=np.int64)])
        # by time, then tag, as the single process's blocks order epochs (to_epochs)
        keep = np.lexsort((joined.tag.astype(str), joined.time))[:want]
        sample, source = joined.take(keep), source[keep]
        if sample.n_epochs >= want:
            until = float(sample.time[-1])
    settings, choice, _ = resolve_link_offsets(iter([] if sample is None else [sample]),
                                               anchors, settings, args.measurements)
    args.link_offsets = "on" if settings.link_offsets else "off"
    files = [infos[k].part.path for k in sorted(set(source.tolist()))]
    return {} if choice is None else {"link_offsets_auto": {**choice.as_dict(),
                                                           "sample": files}}


def _tag_height_needs_z(tag_height: float | None, anchors: pd.DataFrame) -> None:
    """Refuse ``--tag-height`` with anchors that have no z (as ``run_track`` does)."""
    if tag_height is not None and "z" not in anchors.columns:
        raise InputError("--tag-height needs a z column in the anchors file",
                         anchors.attrs.get("path"), 1)


def _far_anchors(anchors: pd.DataFrame) -> list[str]:
    """The anchors far outside the others (a typo), as ``run_track``'s summary names
    them in ``anchors_not_used``."""
    from robustloc.estimators.ranging import _sane_anchors

    dims = [c for c in ("x", "y", "z") if c in anchors.columns]
    far = ~_sane_anchors(anchors[dims].to_numpy(dtype=float))
    return [str(a) for a, f in zip(anchors["anchor"], far) if f]


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.options import (
        PROCESS_NOISE_MAX,
        positive_float,
        positive_int,
        positive_process_noise,
        process_noise,
        sigma_value,
        tag_height_m,
    )

    scale = noise_scale_value
    from robustloc.options import choice
    from robustloc.pipelines.track import WEIGHT_SYNONYMS, WEIGHTS, TrackSettings

    d = TrackSettings()
    # (0 and 1 passed argparse and were refused by the settings in their Python name;
    # the range of locate's and spp's --alpha0: the tracker review)
    from robustloc.pipelines.track import _PROBABILITY as probability
    p.add_argument("measurements", help="measurements file (time, tag, anchor, rssi|range)")
    p.add_argument("--anchors", required=True, help="anchors file (anchor, x, y[, z], ...)")
    p.add_argument("-o", "--out", required=True, help="track file (.csv or .parquet)")
    p.add_argument("--model", "--motion", dest="model", choices=("cv", "ca", "static"),
                   default=d.model, help="motion model (default cv; --motion as in fuse); "
                                         "static is for tags that stand still: a walking "
                                         "tag lags, and hpl has no term for the lag "
                                         "(docs/limits.md)")
    p.add_argument("--filter", choices=("ekf", "ukf"), default=d.filter,
                   help="filter (default ekf)")
    # (the q-like options end at PROCESS_NOISE_MAX: 1e308 overflowed the covariance into
    # rows 'ok' without hpl -- the input review)
    p.add_argument("--q", type=positive_process_noise, default=d.q,
                   help="process noise: white-acceleration variance (m/s^2)^2 for cv, jerk "
                        f"variance for ca, position step variance for static (at most "
                        f"{PROCESS_NOISE_MAX:g}; default {d.q}; "
                        "hpl has no term for the motion model's error: a tag that "
                        "accelerates harder than q allows, 5-10 m/s turning, lags and 0.5-3 %% "
                        "of its rows exceed hpl, see docs/limits.md)")
    p.add_argument("--weight", "--robust", dest="weight", default=None, choices=WEIGHTS,
                   type=choice(WEIGHT_SYNONYMS),
                   help="robust weight (default huber for ranges, asymmetric-igg with "
                        "--domain rssi; --robust as in filter and fuse; none = ls, asym = "
                        "asymmetric-igg)")
    p.add_argument("--domain", choices=("range", "rssi"), default=d.domain,
                   help="RSSI input: update with converted ranges (default) or in dB")
    p.add_argument("--sigma", type=sigma_value, default=None,
                   help="a-priori std of one observation (m or dB); default the anchors' "
                        "sigma column, else 0.3 m / 3 dB.  0.3 m suits UWB; WiFi RTT ranges "
                        "are several times noisier: run `calibrate --self` first (it "
                        "writes the log's sigma per anchor), or the track's covariance and "
                        "hpl will be too small (WiFi RTT corridor: 4.9 %% of the rows beyond "
                        "hpl at 0.3 m, none with the self-calibrated sigma)")
    smoothers = p.add_mutually_exclusive_group()  # (both at once: which one was meant?)
    smoothers.add_argument("--smooth", action="store_true",
                           help="fixed-interval RTS smoother")
    smoothers.add_argument("--fixed-lag", type=positive_int, default=None, metavar="N",
                           help="fixed-lag RTS smoother over the next N epochs of each tag")
    p.add_argument("--kernel", choices=("compiled", "numpy"), default=d.kernel,
                   help="the tracker's kernels: compiled (default) or the NumPy reference "
                        "(Tracker(engine=...); --engine chooses where the command runs); "
                        "they agree to rounding until a test lands within rounding of its "
                        "critical value, then their rows may part")
    p.add_argument("--noise-scale-min", type=scale, default=d.noise_scale_min,
                   help="lower bound of the adaptive measurement noise scale (a factor of "
                        f"--sigma, in [1e-6, 1e6]; default {d.noise_scale_min:g})")
    p.add_argument("--noise-scale-max", type=scale, default=d.noise_scale_max,
                   help="upper bound of the adaptive measurement noise scale (>= "
                        f"--noise-scale-min; default {d.noise_scale_max:g})")
    p.add_argument("--cusum-h", type=positive_float, default=d.cusum_h,
                   help="enable the per-link step detector (environment changes) with this "
                        "CUSUM threshold, e.g. 10 (default off: measured to cost accuracy "
                        "on the seed-002 walk and uwb-dwm1001, see the report).  For steps "
                        "on a minority of the links: a re-admitted link's offset is "
                        "measured against the track and hpl does not cover its error "
                        "(four links stepping 0-3 m every 20 s: 3-9 %% of rows beyond hpl, "
                        "against 0.1-1.3 %% without it; docs/limits.md)")
    p.add_argument("--alpha0", type=probability, default=d.alpha0,
                   help="w-test significance (B-method; default %(default)s)")
    p.add_argument("--beta0", type=probability, default=d.beta0,
                   help="w-test missed-detection probability (B-method; default %(default)s)")
    p.add_argument("--integrity-risk", type=probability, default=d.integrity_risk,
                   help="probability of the error exceeding hpl's noise term (default 1e-3)")
    p.add_argument("--tag-height", type=tag_height_m, default=None,
                   help="known tag height, to reduce slant ranges (m; anchors need z)")
    p.add_argument("--range-offset", action="store_true",
                   help="ranges: estimate each tag's common range offset (m, added to every "
                        "range it measures: a UWB tag's uncalibrated antenna delay) as one "
                        "more state, written as range_offset, var_range_offset.  Measured: "
                        "uwb-labyrinth 0.215 -> 0.144 m RMS with --filter ukf --q 2 --sigma 0.1 "
                        "(its ranges read ~0.1 m long "
                        "at every anchor); uwb-dwm1001 LOS 0.77 -> 0.91 m (its errors "
                        "differ by anchor: use calibrate --self there)")
    p.add_argument("--range-offset-sd", type=sigma_value, default=d.range_offset_sd,
                   help="a-priori std of the offset at a tag's start "
                        f"(m, default {d.range_offset_sd})")
    p.add_argument("--range-offset-q", type=process_noise, default=d.range_offset_q,
                   help="random-walk variance growth of the offset "
                        f"(m^2/s, 0 to {PROCESS_NOISE_MAX:g}, default {d.range_offset_q}; 0: "
                        "constant)")
    p.add_argument("--link-offsets", nargs="?", const="on", default="auto",
                   choices=("on", "off", "auto"), metavar="{on,off,auto}",
                   help="auto (the default): the log chooses; on (the option alone) or "
                        "off: estimate, or not, an offset of each link (anchor) of each tag "
                        "as one more state per anchor: dB added to its RSSI, or m added to "
                        "its ranges (what the anchors' calibration misses where the tag "
                        "walks); the summary gives each tag's final offsets.  Measured: "
                        "ble-tetam 0.77x -> 0.71x the default locate's RMS (the offsets it "
                        "finds correlate 0.93 with the truth's); uwb-dwm1001 LOS 0.77 -> "
                        "0.55 m, NLOS 0.74 -> 0.61 m; uwb-labyrinth 0.215 -> 0.172 m; where "
                        "there are none they cost (simulated walk, 4 APs: 0.93x -> 1.25x the "
                        "snapshot fixes' RMS) and 4 + M states, M the anchors of the file, "
                        "are slower (bench_track.py: 85 k against 252 k tag-epochs/s with 8 "
                        "anchors).  auto: the log's first 20 000 epochs (with --engine dask "
                        "too: by time, then tag, over every partition file) tracked "
                        "without and with them; they are kept when their one-step "
                        "predictions of the observations score better beyond chance (a "
                        "batch-means t-test at 0.1 %%: robustloc.tracking.select; the "
                        "summary's line says which and why); off on sites of more than 24 "
                        "anchors, with fewer than 20 x M observations in those epochs (M "
                        "anchors), with --range-offset, and with --model static (a standing "
                        "tag's offsets stay confounded with its position).  Measured: on "
                        "for ble-tetam and "
                        "uwb-labyrinth, off for 20 of 20 simulated walks "
                        "(benchmarks/bench_link_choice.py)")
    p.add_argument("--link-offset-sd", type=sigma_value, default=None,
                   help="a-priori std of each link's offset at a tag's start, in the "
                        "measurement's unit (default 1 dB for RSSI, 0.1 m for ranges)")
    p.add_argument("--link-offset-q", type=process_noise, default=d.link_offset_q,
                   help="random-walk variance growth of the links' offsets (unit^2/s, 0 to "
                        f"{PROCESS_NOISE_MAX:g}, default {d.link_offset_q}: constant)")
    p.add_argument("--chunk-rows", type=positive_int, default=500_000,
                   help="rows read per chunk (default %(default)s)")
    p.add_argument("--json", action="store_true",
                   help="print the run summary as JSON (method: the method column's "
                        "value; statuses; hpl_quantiles: the usable rows' n, unbounded, "
                        "median_m and p95_bound_m, a value at or below which 95 %% of "
                        "their hpl lie, exact up to 10^6 rows, else from bins of 1/1000 "
                        "decade (exact false); hpl_histogram: their hpl counted in bins "
                        "of 1/20 decade, key floor(20 log10 hpl), 'inf' for unbounded "
                        "ones; seconds, of which compile_seconds numba compiled kernels "
                        "not yet cached, and epochs_per_second without the compiling)")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="no progress bar and no text summary (as locate)")
    from robustloc.commands._plot import add_plot_argument

    add_plot_argument(p, "track")
    add_engine_arguments(p, what="a tag-partitioned Parquet dataset")


def track_file(args: argparse.Namespace, hpl_tally: HplTally | None = None) -> dict:
    """Run the ``track`` pipeline as configured by ``args``; returns the summary
    (``hpl_tally``: as :func:`robustloc.pipelines.track.run_track`'s)."""
    from robustloc.io import read_anchors
    from robustloc.pipelines.track import TrackSettings, run_track

    _, summary = run_track(args.measurements, read_anchors(args.anchors),
                           TrackSettings.from_namespace(args), args.out,
                           progress=not args.quiet, hpl_tally=hpl_tally)
    return summary


def track_partition(meas: pd.DataFrame, anchors: pd.DataFrame, args: argparse.Namespace
                    ) -> tuple[pd.DataFrame, dict]:
    """``--engine dask``: one tag group read whole (its files concatenated in time order)
    -> (track rows, additive counts).  Used when a group spans several files; a group of
    one file is streamed by :func:`track_partition_file`."""
    from robustloc._jitnotice import compile_watch
    from robustloc.io.tables import to_epochs
    from robustloc.pipelines.locate import HplTally
    from robustloc.pipelines.track import (
        TrackSettings,
        link_offset_key,
        link_offsets,
        range_offsets,
        track_blocks,
    )

    settings = TrackSettings.from_namespace(args)
    _tag_height_needs_z(settings.tag_height, anchors)  # as run_track, before any work
    trk = settings.tracker(anchors)
    epochs = to_epochs(meas, trk.anchor_ids)  # sorted by (time, tag): each tag in order
    hist: dict[str, int] = {}
    tally: dict[str, int] = {}
    hpl = HplTally()
    with compile_watch("tracker and filter") as jit:
        table, n, counts = track_blocks(trk, [epochs], settings, hpl_histogram=hist,
                                        source=meas, tally=tally, hpl_tally=hpl)
    method = settings.method_name(trk)  # the method column's
    summary = {"epochs": n, "tags": len(trk.tags), "status": counts,
               "hpl_histogram": {method: hist},
               "hpl_tally": {method: hpl},  # merged by the engine into hpl_quantiles
               "compile_seconds": jit.seconds,
               "invalid_measurement_rows": tally.get("invalid_measurement_rows", 0),
               "duplicates_merged": tally.get("duplicates_merged", 0),
               # the same in every group: the single-process summary's keys
               "shared": {"method": method,
                          "smoother": (("fixed-lag" if settings.fixed_lag else "rts")
                                       if settings.smoothing else None),
                          "sorted_first": False,  # (read whole and sorted by to_epochs)
                          "anchors_not_used": _far_anchors(anchors)}}
    per_tag = {}  # per tag, merged (not summed) over the tag groups
    if settings.range_offset:
        per_tag["range_offset_m"] = range_offsets(trk)
    if settings.link_offsets:
        per_tag[link_offset_key(trk)] = link_offsets(trk)
    if per_tag:
        summary["per_tag"] = per_tag
    return table, summary


def track_partition_file(args: argparse.Namespace) -> dict:
    """``--engine dask``: the pipeline on one partition file (streamed in
    ``--chunk-rows``, so a worker's memory does not grow with the partition) -> the
    additive counts of its summary."""
    from robustloc.pipelines.locate import HplTally

    hpl = HplTally()
    s = track_file(args, hpl)
    summary = {"epochs": s["epochs"], "tags": s["tags"], "status": s["status"],
               "hpl_histogram": s["hpl_histogram"], "rows_out": s["epochs"],
               "hpl_tally": {s["method"]: hpl},  # merged by the engine: hpl_quantiles
               "compile_seconds": s["compile_seconds"],
               "invalid_measurement_rows": s["invalid_measurement_rows"],
               "duplicates_merged": s["duplicates_merged"],
               "shared": {k: s[k] for k in ("method", "smoother", "sorted_first",
                                            "anchors_not_used") if k in s}}
    per_tag = {k: s[k] for k in ("range_offset_m", "link_offset_m", "link_offset_db")
               if k in s}
    if per_tag:  # per tag, merged (not summed) over the tag groups
        summary["per_tag"] = per_tag
    return summary


def run(args: argparse.Namespace) -> int:
    from robustloc.commands._plot import check_plot, draw_plot

    check_options(args)
    check_plot(args, "track")
    if args.engine == "dask":
        from robustloc.engines.dask import run_tagwise

        _check_anchors_on_client(args)
        return run_tagwise(args, track_partition, "track", file_fn=track_partition_file,
                           local_keys={"measurements": str(args.measurements),
                                       "track": str(args.out)},
                           prepare=lambda infos: _resolve_auto_on_client(args, infos))
    summary = track_file(args)
    draw_plot(args)
    from robustloc.commands._summary import summary_head, timing_text
    from robustloc.pipelines.track import track_lines

    if (dest := summary_head(args, summary)) is None:
        return 0
    print(f"{summary['epochs']} epochs, {summary['tags']} tags -> {summary['track']} "
          + timing_text(summary, "epochs_per_second", "epochs/s"), file=dest)
    for line in track_lines(summary):  # as the Dask engine's
        print(line, file=dest)
    return 0
