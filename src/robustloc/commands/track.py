"""``robustloc track``: a robust tight filter per tag -> one track row per input epoch."""

from __future__ import annotations

import argparse
import json
import sys
import time as _time
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.engines import add_engine_arguments

NAME = "track"
HELP = "tracks from RSSI or ranges: a robust tight EKF/UKF per tag, with RTS smoothing"
DESCRIPTION = """\
Tracks every tag of a measurements file with its own robust filter (state [x, y, vx, vy]
for cv, + [ax, ay] for ca, [x, y] for static), updated directly with each epoch's anchor
observations: ranges (corrected with the anchors' bias/scale columns as `locate` does) or
RSSI (converted by the anchors' path-loss model to ranges with sigma_d = d ln10 sigma_dB /
(10 n), or in dB with --domain rssi). An epoch with 1 or 2 anchors still updates.

  start        a robust snapshot fix (huber) of the tag's first usable epoch
  update       robust M-estimation update (gain K D, seed 002 eq. 12) with --weight
  env. change  robust weights down-weight a link whose level steps; --cusum-h H adds a
               two-sided CUSUM on each link's innovations: a link whose level steps is
               held out (never inflating the covariance) while its new offset is
               estimated, then re-admitted with it
  tests        B-method global test on the innovations (--alpha0, --beta0); a filter that
               fails repeatedly or disagrees with the robust fix re-starts (reinit column)
  noise        the measurement noise scale adapts within [--noise-scale-min, -max]
  coasting     nothing heard: status `predicted`
  hpl          max_i |gain_i| MDB_i + k sigma_major, k from --integrity-risk (2-D)
  --smooth     fixed-interval Rauch-Tung-Striebel smoother over the forward pass (keeps its
               robust weights); --fixed-lag N uses only the next N epochs

Output, one row per input epoch (never a dropped epoch): time, tag, x, y, vx, vy[, ax, ay],
method, status, var_x, var_y, cov_xy, var_vx, var_vy, hpl, n_used, nis, noise_scale,
reinit, excluded. Statuses: ok, fault_excluded (a component rejected or a link held out),
predicted, and before a tag's first fix the fix's own status (insufficient_anchors,
ill_conditioned, invalid_measurement). `robustloc evaluate` reads the file.

  robustloc simulate wifi-room --seed 1 --out room
  robustloc track room/measurements.csv --anchors room/anchors.csv -o room/track.csv
  robustloc track room/measurements.csv --anchors room/anchors.csv --smooth -o smooth.csv
  robustloc evaluate room/track.csv --truth room/truth.csv

Beyond one machine (docs/dask.md): partition by tag, then --engine dask tracks each tag
group on a worker with this same code; the dataset of part files holds the same rows:
  robustloc partition big.parquet -o by-tag --by tag --buckets 16
  robustloc track by-tag --anchors anchors.csv -o tracks --engine dask [--scheduler ADDR]"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from robustloc.commands._argtypes import float_in, positive_float, positive_int
    from robustloc.tracking.tracker import TrackerSettings

    d = TrackerSettings()
    probability = float_in(0.0, 1.0)
    p.add_argument("measurements", help="measurements file (time, tag, anchor, rssi|range)")
    p.add_argument("--anchors", required=True, help="anchors file (anchor, x, y[, z], ...)")
    p.add_argument("-o", "--out", required=True, help="track file (.csv or .parquet)")
    p.add_argument("--model", choices=("cv", "ca", "static"), default=d.model,
                   help="motion model (default cv)")
    p.add_argument("--filter", choices=("ekf", "ukf"), default=d.filter,
                   help="filter (default ekf)")
    p.add_argument("--q", type=positive_float, default=d.q,
                   help="process noise: white-acceleration variance (m/s^2)^2 for cv, jerk "
                        f"variance for ca, position step variance for static (default {d.q})")
    p.add_argument("--weight", default=None,
                   choices=("ls", "huber", "hampel", "igg", "igg3", "asymmetric-igg"),
                   help="robust weight (default huber for ranges, asymmetric-igg with "
                        "--domain rssi)")
    p.add_argument("--domain", choices=("range", "rssi"), default=d.domain,
                   help="RSSI input: update with converted ranges (default) or in dB")
    p.add_argument("--sigma", type=positive_float, default=None,
                   help="a-priori std of one observation (m or dB); default the anchors' "
                        "sigma column, else 0.3 m / 3 dB")
    p.add_argument("--smooth", action="store_true", help="fixed-interval RTS smoother")
    p.add_argument("--fixed-lag", type=positive_int, default=None, metavar="N",
                   help="fixed-lag RTS smoother over the next N epochs of each tag")
    p.add_argument("--kernel", choices=("compiled", "numpy"), default=d.engine,
                   help="the tracker's kernels: compiled (default) or the NumPy reference "
                        "(Tracker(engine=...); --engine chooses where the command runs)")
    p.add_argument("--noise-scale-min", type=positive_float, default=d.noise_scale_min)
    p.add_argument("--noise-scale-max", type=positive_float, default=d.noise_scale_max)
    p.add_argument("--cusum-h", type=positive_float, default=d.cusum_h,
                   help="enable the per-link step detector (environment changes) with this "
                        "CUSUM threshold, e.g. 10 (default off: measured to cost accuracy "
                        "on the seed-002 walk and uwb-dwm1001, see the report)")
    p.add_argument("--alpha0", type=probability, default=d.alpha0,
                   help="w-test significance (B-method)")
    p.add_argument("--beta0", type=probability, default=d.beta0,
                   help="w-test missed-detection probability (B-method)")
    p.add_argument("--integrity-risk", type=probability, default=d.integrity_risk,
                   help="probability of the error exceeding hpl's noise term (default 1e-3)")
    p.add_argument("--tag-height", type=float, default=None,
                   help="known tag height, to reduce slant ranges (m; anchors need z)")
    p.add_argument("--chunk-rows", type=positive_int, default=500_000,
                   help="rows read per chunk")
    p.add_argument("--json", action="store_true", help="print the run summary as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_engine_arguments(p, what="a tag-partitioned Parquet dataset")


def make_tracker(anchors: pd.DataFrame, args: argparse.Namespace) -> object:
    """The :class:`robustloc.tracking.Tracker` configured by ``args`` (a refused setting
    is an InputError; ``--smooth``/``--fixed-lag`` record the forward pass)."""
    from robustloc.errors import InputError
    from robustloc.tracking import Tracker

    if args.tag_height is not None and "z" not in anchors.columns:
        raise InputError("--tag-height needs a z column in the anchors file", args.anchors, 1)
    try:
        return Tracker(
            anchors, model=args.model, filter=args.filter, record=_smoothing(args), q=args.q,
            weight=args.weight, domain=args.domain, sigma=args.sigma, engine=args.kernel,
            noise_scale_min=args.noise_scale_min, noise_scale_max=args.noise_scale_max,
            cusum_h=args.cusum_h, alpha0=args.alpha0, beta0=args.beta0,
            integrity_risk=args.integrity_risk, tag_height=args.tag_height,
        )
    except ValueError as exc:
        raise InputError(str(exc)) from None


def _smoothing(args: argparse.Namespace) -> bool:
    return bool(args.smooth or args.fixed_lag is not None)


def track_blocks(trk: object, blocks: object, args: argparse.Namespace,
                 write: object = None, progress: object = None
                 ) -> tuple[pd.DataFrame | None, int, dict[str, int]]:
    """The single core of ``track``: every epoch block through ``trk`` in order.

    Parameters
    ----------
    trk : Tracker
        From :func:`make_tracker`.
    blocks : iterable of Epochs
        The log's epochs in time order (a file streamed by ``iter_epochs``, or one tag
        partition under ``--engine dask``).
    args : argparse.Namespace
        ``smooth``, ``fixed_lag``.
    write : callable, optional
        Without smoothing, each block's rows are handed to ``write`` (streamed, bounded
        memory) and no table is returned; else they are kept and returned.
    progress : callable, optional
        Called with each block's epoch count.

    Returns
    -------
    (table or None, epochs, status counts)
    """
    from robustloc._jitnotice import compile_notice

    smooth = _smoothing(args)
    stream = write is not None and not smooth
    if smooth:
        # the smoother indexes the recorded steps by their row in one step's output, so
        # the whole log goes through the tracker in one step (the smoother holds every
        # epoch anyway); block by block, rows of later blocks were smoothed with the
        # states of earlier ones (the result depended on --chunk-rows)
        blocks = [_joined(list(blocks))]
    frames: list[pd.DataFrame] = []
    n = 0
    status_counts: dict[str, int] = {}
    for block in blocks:
        if n == 0:
            compile_notice("filter")
        rows = trk.step(block)
        for k, v in rows["status"].value_counts().items():
            status_counts[str(k)] = status_counts.get(str(k), 0) + int(v)
        if stream:
            write(rows)
        else:
            frames.append(rows)
        n += block.n_epochs
        if progress is not None:
            progress(block.n_epochs)
    if stream:
        return None, n, status_counts
    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if smooth and len(table):
        table = apply_smoother(trk, table, args.fixed_lag)
        status_counts = {str(k): int(v) for k, v in table["status"].value_counts().items()}
    return table, n, status_counts


def _joined(blocks: list) -> object:
    """Epoch blocks (consecutive, in time order) as one :class:`Epochs`."""
    from dataclasses import replace

    if len(blocks) == 1:
        return blocks[0]
    if not blocks:
        raise ValueError("no epoch blocks")
    b0 = blocks[0]
    return replace(b0, time=np.concatenate([b.time for b in blocks]),
                   tag=np.concatenate([np.asarray(b.tag, dtype=object) for b in blocks]),
                   values=np.concatenate([b.values for b in blocks]),
                   line=np.concatenate([b.line for b in blocks]),
                   n_duplicates=sum(b.n_duplicates for b in blocks),
                   n_invalid=np.concatenate([b.n_invalid for b in blocks]))


def track_file(args: argparse.Namespace) -> dict:
    """Run ``track`` as configured by ``args``; returns the summary."""
    from tqdm import tqdm

    from robustloc.io import iter_epochs, read_anchors, write_table
    from robustloc.io.atomic import atomic_output, check_not_input
    from robustloc.io.tables import UnsortedInput, is_parquet

    anchors = read_anchors(args.anchors)
    smooth = _smoothing(args)
    check_not_input(args.out, [args.measurements, args.anchors])
    out = args.out
    t0 = _time.perf_counter()

    def one_pass(order: str) -> tuple:
        """Every epoch through a fresh tracker; the streamed file is written atomically
        (nothing at -o after an error or an interrupt); raises UnsortedInput when rows
        turn out not to be in time order (the caller sorts and starts again)."""
        trk = make_tracker(anchors, args)
        bar = tqdm(unit=" epochs", disable=args.quiet or not sys.stderr.isatty(),
                   file=sys.stderr)
        try:
            with atomic_output(out) as (target, _stream):
                stream = target is not None and not smooth
                writer = TrackWriter(target, parquet=is_parquet(out)) if stream else None
                try:
                    blocks = iter_epochs(args.measurements, anchors,
                                         chunk_rows=args.chunk_rows, order=order)
                    table, n, status_counts = track_blocks(
                        trk, blocks, args, None if writer is None else writer.write,
                        bar.update)
                finally:
                    if writer is not None:
                        writer.close()
                if table is not None:
                    if target is None:
                        write_table(table, out)
                    else:
                        write_table(table, target, parquet=is_parquet(out))
        finally:
            bar.close()
        return trk, n, status_counts

    try:
        trk, n_epochs, counts = one_pass("auto")
    except UnsortedInput:
        trk, n_epochs, counts = one_pass("sort")
    wall = _time.perf_counter() - t0
    return {"measurements": str(args.measurements), "track": str(out), "epochs": n_epochs,
            "tags": len(trk.tags), "method": trk.method, "status": counts,
            "smoother": ("fixed-lag" if args.fixed_lag else "rts") if smooth else None,
            "seconds": round(wall, 3),
            "epochs_per_second": round(n_epochs / max(wall, 1e-9), 1)}


def track_partition(meas: pd.DataFrame, anchors: pd.DataFrame, args: argparse.Namespace
                    ) -> tuple[pd.DataFrame, dict[str, int]]:
    """``--engine dask``: one tag group read whole (its files concatenated in time order)
    -> (track rows, additive counts).  Used when a group spans several files; a group of
    one file is streamed by :func:`track_partition_file`."""
    from robustloc.io.tables import to_epochs

    trk = make_tracker(anchors, args)
    epochs = to_epochs(meas, trk.anchor_ids)  # sorted by (time, tag): each tag in order
    table, n, counts = track_blocks(trk, [epochs], args)
    return table, {"epochs": n, "tags": len(trk.tags), "status": counts}


def track_partition_file(args: argparse.Namespace) -> dict:
    """``--engine dask``: ``track_file`` on one partition file (streamed in
    ``--chunk-rows``, so a worker's memory does not grow with the partition) -> the
    additive counts of its summary."""
    s = track_file(args)
    return {"epochs": s["epochs"], "tags": s["tags"], "status": s["status"],
            "rows_out": s["epochs"]}


class TrackWriter:
    """Append track rows chunk by chunk to a CSV or Parquet file (columns of the first)."""

    def __init__(self, path: Path, parquet: bool | None = None) -> None:
        from robustloc.io.tables import is_parquet

        self.path = Path(path)
        self.parquet = is_parquet(self.path) if parquet is None else parquet
        self._columns: list[str] | None = None
        self._pq = None

    def write(self, frame: pd.DataFrame) -> None:
        if self._columns is None:
            self._columns = list(frame.columns)
        out = frame[self._columns].reset_index(drop=True)
        out.attrs = {}
        if self.parquet:
            import pyarrow as pa
            import pyarrow.parquet as pq

            table = pa.Table.from_pandas(out, preserve_index=False)
            if self._pq is None:
                self._pq = pq.ParquetWriter(self.path, table.schema)
            self._pq.write_table(table.cast(self._pq.schema))
        else:
            first = not hasattr(self, "_started")
            out.to_csv(self.path, mode="w" if first else "a", header=first, index=False)
            self._started = True

    def close(self) -> None:
        if self._pq is not None:
            self._pq.close()
        elif self._columns is None:  # nothing written: an empty file with the header
            self.path.write_text("")


def apply_smoother(trk: object, table: pd.DataFrame, lag: int | None) -> pd.DataFrame:
    """Replace the filtered states of ``table`` (rows in step order) by smoothed ones."""
    xs, Ps = trk.smoothed(len(table), lag)
    have = np.all(np.isfinite(xs), axis=1)
    t = table.copy()
    t.loc[have, "x"], t.loc[have, "y"] = xs[have, 0], xs[have, 1]
    t.loc[have, "var_x"], t.loc[have, "var_y"] = Ps[have, 0, 0], Ps[have, 1, 1]
    t.loc[have, "cov_xy"] = Ps[have, 0, 1]
    if xs.shape[1] >= 4:
        t.loc[have, "vx"], t.loc[have, "vy"] = xs[have, 2], xs[have, 3]
        t.loc[have, "var_vx"], t.loc[have, "var_vy"] = Ps[have, 2, 2], Ps[have, 3, 3]
    if xs.shape[1] >= 6:
        t.loc[have, "ax"], t.loc[have, "ay"] = xs[have, 4], xs[have, 5]
    # hpl: the filtered slope term carries over; the noise term shrinks with the covariance
    P2 = Ps[have][:, :2, :2]
    tr = 0.5 * (P2[:, 0, 0] + P2[:, 1, 1])
    det = P2[:, 0, 0] * P2[:, 1, 1] - P2[:, 0, 1] ** 2
    smaj = np.sqrt(np.maximum(tr + np.sqrt(np.maximum(tr * tr - det, 0.0)), 0.0))
    vf = table.loc[have, ["var_x", "var_y", "cov_xy"]].to_numpy(float)
    trf = 0.5 * (vf[:, 0] + vf[:, 1])
    detf = vf[:, 0] * vf[:, 1] - vf[:, 2] ** 2
    smaj_f = np.sqrt(np.maximum(trf + np.sqrt(np.maximum(trf * trf - detf, 0.0)), 0.0))
    k = trk._k_ir
    slope = table.loc[have, "hpl"].to_numpy(float) - k * smaj_f
    t.loc[have, "hpl"] = np.maximum(slope, 0.0) + k * smaj
    t["method"] = table["method"] + ("-rts" if lag is None else f"-lag{lag}")
    return t


def run(args: argparse.Namespace) -> int:
    if args.engine == "dask":
        from robustloc.engines.dask import run_tagwise
        return run_tagwise(args, track_partition, "track", file_fn=track_partition_file)
    summary = track_file(args)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"{summary['epochs']} epochs, {summary['tags']} tags -> {summary['track']} "
          f"({summary['seconds']:.2f} s, {summary['epochs_per_second']:.0f} epochs/s)")
    print("  " + ", ".join(f"{k}: {v}" for k, v in sorted(summary["status"].items())))
    return 0
