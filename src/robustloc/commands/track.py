"""``robustloc track``: a robust tight filter per tag -> one track row per input epoch."""

from __future__ import annotations

import argparse
import json
import sys
import time as _time
from pathlib import Path

import numpy as np
import pandas as pd

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
  robustloc evaluate room/track.csv --truth room/truth.csv"""


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
    p.add_argument("--engine", choices=("compiled", "numpy"), default=d.engine,
                   help="compiled kernels (default) or the NumPy reference")
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


def track_file(args: argparse.Namespace) -> dict:
    """Run ``track`` as configured by ``args``; returns the summary."""
    from tqdm import tqdm

    from robustloc._jitnotice import compile_notice
    from robustloc.errors import InputError
    from robustloc.io import iter_epochs, read_anchors, write_table
    from robustloc.io.atomic import atomic_output, check_not_input
    from robustloc.io.tables import UnsortedInput, is_parquet
    from robustloc.tracking import Tracker

    anchors = read_anchors(args.anchors)
    smooth = args.smooth or args.fixed_lag is not None
    if args.tag_height is not None and "z" not in anchors.columns:
        raise InputError("--tag-height needs a z column in the anchors file", args.anchors, 1)
    def make_tracker() -> Tracker:
        try:
            return Tracker(
                anchors, model=args.model, filter=args.filter, record=smooth, q=args.q,
                weight=args.weight, domain=args.domain, sigma=args.sigma, engine=args.engine,
                noise_scale_min=args.noise_scale_min, noise_scale_max=args.noise_scale_max,
                cusum_h=args.cusum_h, alpha0=args.alpha0, beta0=args.beta0,
                integrity_risk=args.integrity_risk, tag_height=args.tag_height,
            )
        except ValueError as exc:
            raise InputError(str(exc)) from None

    check_not_input(args.out, [args.measurements, args.anchors])
    out = args.out
    t0 = _time.perf_counter()

    def one_pass(order: str) -> tuple:
        """Every epoch through a fresh tracker; the streamed file is written atomically
        (nothing at -o after an error or an interrupt); raises UnsortedInput when rows
        turn out not to be in time order (the caller sorts and starts again)."""
        trk = make_tracker()
        frames: list[pd.DataFrame] = []
        n = 0
        bar = tqdm(unit=" epochs", disable=args.quiet or not sys.stderr.isatty(),
                   file=sys.stderr)
        status_counts: dict[str, int] = {}
        try:
            with atomic_output(out) as (target, _stream):
                stream = target is not None and not smooth
                writer = TrackWriter(target, parquet=is_parquet(out)) if stream else None
                try:
                    for block in iter_epochs(args.measurements, anchors,
                                             chunk_rows=args.chunk_rows, order=order):
                        if n == 0:
                            compile_notice("filter", "tracker")
                        rows = trk.step(block)
                        for k, v in rows["status"].value_counts().items():
                            status_counts[str(k)] = status_counts.get(str(k), 0) + int(v)
                        if writer is None:
                            frames.append(rows)
                        else:
                            writer.write(rows)
                        n += block.n_epochs
                        bar.update(block.n_epochs)
                finally:
                    if writer is not None:
                        writer.close()
                if not stream:
                    table = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
                    if smooth and len(table):
                        table = apply_smoother(trk, table, args.fixed_lag)
                        status_counts = {str(k): int(v) for k, v in
                                         table["status"].value_counts().items()}
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
    summary = track_file(args)
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    print(f"{summary['epochs']} epochs, {summary['tags']} tags -> {summary['track']} "
          f"({summary['seconds']:.2f} s, {summary['epochs_per_second']:.0f} epochs/s)")
    print("  " + ", ".join(f"{k}: {v}" for k, v in sorted(summary["status"].items())))
    return 0
