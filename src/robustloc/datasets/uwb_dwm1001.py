"""Loader for the outdoor DWM1001 UWB data set (cucudasluv/UWB-dataset, Apache-2.0).

A run folder (``Dynamic_measurements/{LOS,NLOS}/Trajectory_A/Case_1``) holds

* ``A3.csv, A5.csv, A9.csv, A12.csv`` -- ROS ``rostopic echo -p`` dumps, one per anchor:
  ``%time`` (ns), ``field.id``, the anchor position ``field.x/y/z`` on every row,
  ``field.distanceFromTag`` (m), ``field.rssi``;
* ``trajectory.csv`` -- RTK truth in the local frame (``timestamp`` ns, ``x, y, z``);
* ``LS.csv``, ``ESKF.csv`` -- the authors' own estimates (``timestamp, x, y, z``);
* ``gnss.csv`` -- the RTK NavSatFix the truth was made from (not an independent sensor:
  it is *not* used as a GPS input).

Conversions (*checked*): the tag is carried at 1.0 m above the ground (the static data
set's true range is ``sqrt(d^2 + (h_anchor - 1.0)^2)``), so 2-D solutions use the known
vertical offsets ``z_anchor - 1.0``.  Times are seconds since ``t0_ns`` (the first range
of the run, floored to the second), kept in :attr:`Dwm1001Run.t0_ns`.

The shipped excerpt (``robustloc/data/uwb-dwm1001``) holds the first 60 s of both runs as
gzip'd CSV in the same layout; see its ``SOURCE.md``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from robustloc.errors import InputError
from robustloc.paths import PACKAGE_DATA, DataDir, data_folder

ANCHOR_FILES = ("A3", "A5", "A9", "A12")
TAG_HEIGHT_M = 1.0
RUNS = ("LOS", "NLOS")
#: Full-data run folders below the data set root.
RUN_DIRS = {r: Path("Dynamic_measurements") / r / "Trajectory_A" / "Case_1" for r in RUNS}


@dataclass(frozen=True)
class Dwm1001Run:
    """One dynamic run as contract frames.

    Attributes
    ----------
    name : ``LOS`` or ``NLOS``.
    anchors : ``anchor, x, y, z`` (metres).
    measurements : ``time, tag, anchor, range, rssi`` sorted by time.
    truth : ``time, tag, x, y``.
    authors : ``{"LS": frame, "ESKF": frame}`` with ``time, x, y``.
    t0_ns : time origin (ns since the Unix epoch).
    tag_height_m : height of the tag used for the vertical offsets.
    """

    name: str
    anchors: pd.DataFrame
    measurements: pd.DataFrame
    truth: pd.DataFrame
    authors: dict[str, pd.DataFrame]
    t0_ns: int
    tag_height_m: float = TAG_HEIGHT_M

    @property
    def height_offset_m(self) -> np.ndarray:
        return self.anchors["z"].to_numpy(float) - self.tag_height_m


def _find(folder: Path, stem: str) -> Path:
    for suffix in (".csv", ".csv.gz"):
        p = folder / (stem + suffix)
        if p.is_file():
            return p
    raise InputError(f"missing {stem}.csv in the run folder", folder)


def _read(path: Path) -> pd.DataFrame:
    try:
        return pd.read_csv(path)
    except (OSError, ValueError, pd.errors.ParserError) as exc:
        raise InputError(f"cannot read: {exc}", path) from None


def load_run(folder: str | Path, name: str | None = None) -> Dwm1001Run:
    """Load one run folder (full data or the shipped excerpt) into contract frames."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError("run folder does not exist", folder)
    frames = []
    anchors = []
    for stem in ANCHOR_FILES:
        p = _find(folder, stem)
        df = _read(p)
        need = ["%time", "field.id", "field.x", "field.y", "field.z", "field.distanceFromTag"]
        miss = [c for c in need if c not in df.columns]
        if miss:
            raise InputError(f"missing column(s) {', '.join(miss)}", p, 1)
        aid = stem
        anchors.append(
            (
                aid,
                float(df["field.x"].median()),
                float(df["field.y"].median()),
                float(df["field.z"].median()),
            )
        )
        frames.append(
            pd.DataFrame(
                {
                    "t_ns": df["%time"].to_numpy(np.int64),
                    "anchor": aid,
                    "range": df["field.distanceFromTag"].to_numpy(float),
                    "rssi": df.get("field.rssi", pd.Series(np.nan, index=df.index)).to_numpy(float),
                }
            )
        )
    meas = pd.concat(frames, ignore_index=True).sort_values("t_ns", kind="stable")
    t0 = int(meas["t_ns"].iloc[0] // 1_000_000_000 * 1_000_000_000)

    def sec(ns) -> np.ndarray:
        return (np.asarray(ns, dtype=np.float64) - t0) / 1e9

    meas.insert(0, "time", sec(meas.pop("t_ns")))
    meas.insert(1, "tag", "tag")
    meas = meas[np.isfinite(meas["range"])].reset_index(drop=True)
    tr = _read(_find(folder, "trajectory"))
    truth = pd.DataFrame(
        {
            "time": sec(tr["timestamp"].to_numpy(np.float64)),
            "tag": "tag",
            "x": tr["x"].to_numpy(float),
            "y": tr["y"].to_numpy(float),
        }
    )
    authors = {}
    for est in ("LS", "ESKF"):
        try:
            e = _read(_find(folder, est))
        except InputError:
            continue
        authors[est] = pd.DataFrame(
            {
                "time": sec(e["timestamp"].to_numpy(np.float64)),
                "x": e["x"].to_numpy(float),
                "y": e["y"].to_numpy(float),
            }
        )
    anc = pd.DataFrame(anchors, columns=["anchor", "x", "y", "z"])
    return Dwm1001Run(
        name=name or folder.name,
        anchors=anc,
        measurements=meas,
        truth=truth,
        authors=authors,
        t0_ns=t0,
    )


def load(run: str = "LOS", data_dir: DataDir | None = None) -> Dwm1001Run:
    """Load the ``LOS`` or ``NLOS`` run: full data under ``data_dir/uwb-dwm1001`` when
    given (e.g. ``/work/shared/data``), else the shipped 60 s excerpt."""
    key = run.upper()
    if key not in RUNS:
        raise ValueError(f"run must be one of {RUNS}, got {run!r}")
    if data_dir is not None:
        return load_run(data_folder(data_dir) / "uwb-dwm1001" / RUN_DIRS[key], key)
    return load_run(PACKAGE_DATA / "uwb-dwm1001" / key, key)


def error_stats(
    t_est: np.ndarray, xy_est: np.ndarray, truth: pd.DataFrame, span: tuple[float, float]
) -> dict[str, float]:
    """2-D error against truth interpolated at the estimate times within ``span``.

    Returns ``rms, p95, mean, n`` (metres; ``n`` epochs compared).  Epochs without an
    estimate (NaN) count as missing, reported in ``missing``.
    """
    t = np.asarray(t_est, float)
    xy = np.asarray(xy_est, float)
    tt = truth["time"].to_numpy(float)
    m = (t >= max(span[0], tt[0])) & (t <= min(span[1], tt[-1]))
    xi = np.interp(t[m], tt, truth["x"].to_numpy(float))
    yi = np.interp(t[m], tt, truth["y"].to_numpy(float))
    err = np.hypot(xy[m, 0] - xi, xy[m, 1] - yi)
    ok = np.isfinite(err)
    e = err[ok]
    return {
        "rms": float(np.sqrt(np.mean(e**2))) if e.size else float("nan"),
        "p95": float(np.percentile(e, 95)) if e.size else float("nan"),
        "mean": float(np.mean(e)) if e.size else float("nan"),
        "n": int(m.sum()),
        "missing": int((~ok).sum()),
    }
