"""Loader for the *WiFi RSS & RTT dataset with different LOS conditions* ("wifi-rtt-rss").

Source: Fx386483710/WiFi_RSS_RTT_Dataset_for_Model_Selection @48e41763 (MIT), Feng,
Nguyen & Luo, DOI 10.5281/zenodo.11558792.  WiFi RTT (FTM) ranges and RSS, 60 scans per
reference point (RP), in three rooms: a lecture theatre (5 APs, all line of sight), an
office (5 APs, mixed) and a corridor (4 APs, all non-line-of-sight).

Conversions (checked on the data, see ``tests/test_datasets.py``):

* Point (``X, Y``) and AP coordinates are grid units: multiplied by :data:`GRID_M` = 0.6 m.
  With that, the median of RTT range minus true distance per AP is between -0.9 and
  +1.0 m in the lecture theatre and office (a per-AP bias, not a scale error).
* ``RTT (mm) / 1000`` is the range in metres; ``100000 mm`` means no signal and
  ``-200 dBm`` means no signal: such (scan, AP) pairs are *missing* (no measurement row).
* Corridor: the CSV has five AP columns but column ``AP1`` is never heard; the four AP
  positions in ``lecture theatre+office+corridor_AP_position.txt`` belong, in order, to
  columns ``AP2 .. AP5`` (range-distance correlation 0.98-0.99 with this mapping, and
  medians of range minus distance +0.9 .. +1.8 m; with the naive mapping
  position k -> column APk the correlations fall to 0.84 / -0.45 / 0.91 and the medians
  reach +10 m).  Anchor ids are the CSV column names, so the corridor anchors are
  ``AP2 .. AP5``.

Sizes (full data): 7200 / 6480 / 6840 scans, 60 per RP; the train/test files of the lecture
theatre hold 5280 / 1920 scans (the upstream README says 5400 / 1800).

Epochs: one per scan (one CSV row).  ``tag`` is the room name, ``time`` the scan index
(0-based; with ``split="all"`` the test scans follow the train scans).  Extra columns:
``rp`` (reference-point id ``"<X>_<Y>"`` in grid units), ``split`` and ``scan`` (row index in
its own file); in the measurement frames ``los`` (bool: the AP is listed in the scan's
``LOS APs``), in the truth ``los_aps`` (``;``-joined anchor ids, empty: none).

When ``data_dir`` is None the full shared data is used if present, else the excerpt in
``robustloc/data/wifi-rtt-rss`` (every 10th scan of each file); :attr:`WifiRoom.source` says
which.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd

from robustloc._arrays import to_number
from robustloc.datasets.ble_tetam import DatasetSource, _existing, _read_text, resolve_dataset
from robustloc.errors import InputError
from robustloc.paths import DataDir

NAME = "wifi-rtt-rss"
ROOMS = ("lecture_theatre", "office", "corridor")
SPLITS = ("train", "test", "all")
#: Size of one grid unit in metres (README: grid size 0.6 x 0.6 m).
GRID_M = 0.6
#: RTT value (mm) meaning "no signal".
NO_RTT_MM = 100000.0
#: RSS value (dBm) meaning "no signal".
NO_RSS_DBM = -200.0
AP_POSITION_FILE = "data/lecture theatre+office+corridor_AP_position.txt"
_ROOM_IN_POSITION_FILE = {
    "lecture_theatre": "lecture theatre",
    "office": "office",
    "corridor": "corridor",
}
#: CSV column number of each AP listed in the position file, per room (see module doc).
_AP_COLUMNS = {
    "lecture_theatre": (1, 2, 3, 4, 5),
    "office": (1, 2, 3, 4, 5),
    "corridor": (2, 3, 4, 5),
}


@dataclass(frozen=True)
class WifiRoom:
    """One room of the data set, as contract frames.

    Attributes
    ----------
    room, split : str
    anchors : DataFrame
        ``anchor, x, y`` in metres (2-D; the data set gives no heights).
    ranges : DataFrame
        Measurements ``time, tag, anchor, range`` (metres) plus ``los, rp, split, scan``.
    rssi : DataFrame
        Measurements ``time, tag, anchor, rssi`` (dBm) plus ``los, rp, split, scan``.
    truth : DataFrame
        ``time, tag, x, y`` (metres) plus ``rp, split, scan, los_aps``; one row per scan.
    source : DatasetSource
        Folder and kind (``"full"`` or ``"excerpt"``) the data came from.
    """

    room: str
    split: str
    anchors: pd.DataFrame
    ranges: pd.DataFrame
    rssi: pd.DataFrame
    truth: pd.DataFrame
    source: DatasetSource

    @property
    def n_scans(self) -> int:
        return len(self.truth)


def resolve(data_dir: DataDir | None = None) -> DatasetSource:
    """The wifi-rtt-rss folder used for ``data_dir`` (shared data, else the excerpt)."""
    return resolve_dataset(NAME, AP_POSITION_FILE, data_dir)


def _check_room(room: str) -> None:
    if room not in ROOMS:
        raise ValueError(f"unknown room {room!r}; one of {', '.join(ROOMS)}")


def load_anchors(room: str, data_dir: DataDir | None = None) -> pd.DataFrame:
    """AP positions of ``room`` as an anchors frame ``anchor, x, y`` (metres)."""
    _check_room(room)
    src = resolve(data_dir)
    path = src.path / AP_POSITION_FILE
    text = _read_text(path)
    want = _ROOM_IN_POSITION_FILE[room]
    section: str | None = None
    xs: list[float] | None = None
    ys: list[float] | None = None
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        m = re.match(r"^AP\s*([XY])\s*:(.*)$", s)
        if m is None:
            section = s.lower()
            continue
        if section != want:
            continue
        try:
            vals = [float(v) for v in m.group(2).split(",")]
        except ValueError:
            raise InputError(f"non-numeric AP coordinate in {s!r}", path, i) from None
        if m.group(1) == "X":
            xs = vals
        else:
            ys = vals
    cols = _AP_COLUMNS[room]
    if xs is None or ys is None:
        raise InputError(f"no AP X/AP Y lines for {want!r}", path)
    if len(xs) != len(cols) or len(ys) != len(cols):
        raise InputError(
            f"{want}: expected {len(cols)} AP coordinates, got {len(xs)} X and {len(ys)} Y", path
        )
    df = pd.DataFrame(
        {
            "anchor": [f"AP{c}" for c in cols],
            "x": np.asarray(xs) * GRID_M,
            "y": np.asarray(ys) * GRID_M,
        }
    )
    df.attrs.update(dataset=NAME, source=src.kind, path=str(src.path), room=room)
    return df


def _read_room_csv(path: Path) -> pd.DataFrame:
    path = _existing(path)
    try:
        df = pd.read_csv(path, dtype={"LOS APs": str}, keep_default_na=False, na_values=[])
    except (pd.errors.ParserError, ValueError, OSError, EOFError) as e:
        raise InputError(f"malformed CSV: {e}", path) from None
    need = ["X", "Y"] + [f"AP{k} {q}" for q in ("RTT(mm)", "RSS(dBm)") for k in range(1, 6)]
    missing = [c for c in need if c not in df.columns]
    if missing:
        raise InputError(f"missing column(s): {', '.join(missing)}", path, 1)
    for c in need:
        num = to_number(df[c]).to_numpy(dtype=float)
        bad = ~np.isfinite(num)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"non-numeric or non-finite {c}: {df[c].iloc[i]!r}", path, i + 2)
        df[c] = num
    if "LOS APs" not in df.columns:
        df["LOS APs"] = ""
    return df


def load_room(
    room: str,
    split: Literal["train", "test", "all"] = "train",
    data_dir: DataDir | None = None,
) -> WifiRoom:
    """Load one room (see the module docstring for units, epochs and missing values).

    Parameters
    ----------
    room : {"lecture_theatre", "office", "corridor"}
    split : {"train", "test", "all"}
        The data set's own train / test files, or both (train scans first).
    data_dir : str, PathLike or Traversable, optional
        Shared data root or the data set folder; None: shared data, else the excerpt.
    """
    _check_room(room)
    if split not in SPLITS:
        raise ValueError(f"unknown split {split!r}; one of {', '.join(SPLITS)}")
    src = resolve(data_dir)
    anchors = load_anchors(room, src.path)
    cols = _AP_COLUMNS[room]
    parts = []
    for sp in ("train", "test") if split == "all" else (split,):
        df = _read_room_csv(src.path / "data" / f"database_{room}_{sp}.csv")
        parts.append(df.assign(split=sp, scan=np.arange(len(df))))
    df = pd.concat(parts, ignore_index=True)
    n = len(df)
    time = np.arange(n, dtype=float)
    gx, gy = df["X"].to_numpy(), df["Y"].to_numpy()
    rp = np.array([f"{a:g}_{b:g}" for a, b in zip(gx, gy)], dtype=object)

    # LOS AP numbers refer to CSV columns: "1 3 4" -> {AP1, AP3, AP4}
    los_sets = [set(str(s).split()) for s in df["LOS APs"]]
    los = np.array([[str(c) in s for c in cols] for s in los_sets], dtype=bool).reshape(n, -1)
    los_aps = [";".join(f"AP{c}" for c in cols if str(c) in s) for s in los_sets]

    rtt_mm = df[[f"AP{c} RTT(mm)" for c in cols]].to_numpy()
    rss = df[[f"AP{c} RSS(dBm)" for c in cols]].to_numpy()
    ids = np.array([f"AP{c}" for c in cols], dtype=object)

    def frame(values: np.ndarray, present: np.ndarray, column: str) -> pd.DataFrame:
        r, k = np.nonzero(present)
        out = pd.DataFrame(
            {
                "time": time[r],
                "tag": room,
                "anchor": ids[k],
                column: values[r, k],
                "los": los[r, k],
                "rp": rp[r],
                "split": df["split"].to_numpy()[r],
                "scan": df["scan"].to_numpy()[r],
            }
        )
        out.attrs.update(dataset=NAME, source=src.kind, path=str(src.path), room=room)
        return out

    ranges = frame(rtt_mm / 1000.0, rtt_mm != NO_RTT_MM, "range")
    rssi = frame(rss, rss != NO_RSS_DBM, "rssi")
    truth = pd.DataFrame(
        {
            "time": time,
            "tag": room,
            "x": gx * GRID_M,
            "y": gy * GRID_M,
            "rp": rp,
            "split": df["split"].to_numpy(),
            "scan": df["scan"].to_numpy(),
            "los_aps": los_aps,
        }
    )
    truth.attrs.update(dataset=NAME, source=src.kind, path=str(src.path), room=room)
    return WifiRoom(room, split, anchors, ranges, rssi, truth, src)
